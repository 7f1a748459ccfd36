//! Free-running cameras into frame sets: frames grouped by capture time.
//!
//! Every camera stamps its frames on one clock (nanoseconds). Free-running cameras at one
//! rate keep arbitrary phases, so a set is found in a window one frame interval long that
//! starts at the oldest frame waiting: each camera takes its frame in the window nearest the
//! latest of the cameras' first frames in it (a camera twice as fast gives the nearer of
//! its two), so every frame of a set lies within half a frame interval of the set's
//! instant, the middle of its frames. Frames a camera had before the one it took are passed
//! over (counted as dropped). A window is decided once every camera has shown a frame past
//! it (nothing of it can still come), or once the stall timeout has passed since its first
//! frames arrived (not since they were captured: frames that all come late must still find
//! each other): a camera that has gone quiet then misses the set, which is dropped as
//! incomplete and counted against it.

use std::collections::VecDeque;

/// One camera frame with its capture time on the rig's common clock.
#[derive(Clone, Debug, PartialEq)]
pub struct TimedFrame {
    /// Capture time, nanoseconds on the common clock.
    pub capture_ns: u64,
    /// When the camera handed it over, on the same clock: later than `capture_ns` by the
    /// source's latency (decoding, transport), which can be more than the stall timeout.
    pub delivered_ns: u64,
    /// RGB8 pixels.
    pub data: Vec<u8>,
}

/// What happened to one camera's frames so far.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CameraSyncStats {
    /// Frames received.
    pub received: u64,
    /// Frames that went into a published frame set.
    pub used: u64,
    /// Frames passed over or lost with an incomplete set.
    pub dropped: u64,
    /// Frame sets this camera had no frame for.
    pub missed_sets: u64,
    /// Capture time of its newest frame, nanoseconds.
    pub last_capture_ns: Option<u64>,
}

/// Groups timestamped frames of `cameras` cameras into frame sets.
#[derive(Debug)]
pub struct FrameSetSync {
    interval_ns: u64,
    queues: Vec<VecDeque<TimedFrame>>,
    stats: Vec<CameraSyncStats>,
    /// Incomplete frame sets dropped.
    incomplete_sets: u64,
    /// Incomplete frame sets returned without the cameras that missed them.
    partial_sets: u64,
    /// Cameras whose source has ended: nothing more will come from them.
    gone: Vec<bool>,
}

/// Frames a camera may have waiting before the oldest are dropped: a camera far ahead of
/// the others (or a stalled partner) must not hold memory without bound.
pub const MAX_WAITING_FRAMES: usize = 8;

impl FrameSetSync {
    /// A synchroniser for `cameras` cameras delivering a frame every `interval_ns`.
    pub fn new(cameras: usize, interval_ns: u64) -> Self {
        Self {
            interval_ns: interval_ns.max(1),
            queues: vec![VecDeque::new(); cameras],
            stats: vec![CameraSyncStats::default(); cameras],
            incomplete_sets: 0,
            partial_sets: 0,
            gone: vec![false; cameras],
        }
    }

    /// Per camera, what happened to its frames.
    pub fn stats(&self) -> &[CameraSyncStats] {
        &self.stats
    }

    /// Frame sets dropped because a camera had no frame for them.
    pub fn incomplete_sets(&self) -> u64 {
        self.incomplete_sets
    }

    /// Says that `camera` will deliver nothing more (its source ended and every frame it gave
    /// was pushed): windows no longer wait for it.
    pub fn finish_camera(&mut self, camera: usize) {
        if let Some(g) = self.gone.get_mut(camera) {
            *g = true;
        }
    }

    /// Says that `camera`, finished when it was lost, delivers again: windows wait for it
    /// once more.
    pub fn rejoin_camera(&mut self, camera: usize) {
        if let Some(g) = self.gone.get_mut(camera) {
            *g = false;
        }
    }

    /// Frames of `camera` waiting for their sets.
    pub fn waiting(&self, camera: usize) -> usize {
        self.queues.get(camera).map_or(0, VecDeque::len)
    }

    /// Frame sets returned without the cameras that missed them.
    pub fn partial_sets(&self) -> u64 {
        self.partial_sets
    }

    /// Adds a frame of `camera`. A frame older than one already waiting for the camera
    /// (a clock step back) is dropped.
    pub fn push(&mut self, camera: usize, frame: TimedFrame) {
        let (Some(queue), Some(stats)) = (self.queues.get_mut(camera), self.stats.get_mut(camera)) else { return };
        stats.received += 1;
        if queue.back().is_some_and(|last| frame.capture_ns <= last.capture_ns) {
            stats.dropped += 1;
            return;
        }
        stats.last_capture_ns = Some(frame.capture_ns);
        queue.push_back(frame);
        while queue.len() > MAX_WAITING_FRAMES {
            queue.pop_front();
            stats.dropped += 1;
        }
    }

    /// The next complete frame set (one frame per camera, in camera order) with its
    /// instant, if one can be decided at clock time `now_ns`. A camera whose frames stop
    /// holds the sets back until they are `stall_ns` old; then they go without it and are
    /// dropped as incomplete (`u64::MAX`: wait for it forever, as a replay must).
    pub fn next_set(&mut self, now_ns: u64, stall_ns: u64) -> Option<(u64, Vec<TimedFrame>)> {
        let (instant, frames) = self.next_set_or_partial(now_ns, stall_ns, |_| false)?;
        Some((instant, frames.into_iter().flatten().collect()))
    }

    /// [`FrameSetSync::next_set`], but a set some cameras missed is returned instead of
    /// dropped when `accept` says so of its cameras' presence (in camera order): a live
    /// stream goes on without a camera that stopped while the others can carry it.
    pub fn next_set_or_partial(
        &mut self,
        now_ns: u64,
        stall_ns: u64,
        accept: impl Fn(&[bool]) -> bool,
    ) -> Option<(u64, Vec<Option<TimedFrame>>)> {
        loop {
            let start = self.queues.iter().filter_map(|q| q.front()).map(|f| f.capture_ns).min()?;
            let end = start.saturating_add(self.interval_ns);
            let closed = self
                .queues
                .iter()
                .zip(&self.gone)
                .all(|(q, &gone)| gone || q.back().is_some_and(|f| f.capture_ns >= end));
            // A camera is waited for as long after its partners' frames *arrived*: frames
            // that all come late (a decoder behind the clock, a source's latency) must not
            // make every window look stalled.
            let arrived = self
                .queues
                .iter()
                .filter_map(|q| q.front())
                .filter(|f| f.capture_ns < end)
                .map(|f| f.delivered_ns.max(f.capture_ns))
                .min()
                .unwrap_or(start);
            if !closed && now_ns.saturating_sub(arrived) < stall_ns {
                return None;
            }
            // Queues are in time order and start at or after `start`: a front inside the
            // window is the camera's first frame in it.
            let reference =
                self.queues.iter().filter_map(|q| q.front()).map(|f| f.capture_ns).filter(|&t| t < end).max()?;
            let mut picked: Vec<Option<TimedFrame>> = Vec::with_capacity(self.queues.len());
            for (queue, stats) in self.queues.iter_mut().zip(&mut self.stats) {
                let nearest = queue
                    .iter()
                    .take_while(|f| f.capture_ns < end)
                    .enumerate()
                    .min_by_key(|(_, f)| f.capture_ns.abs_diff(reference))
                    .map(|(k, _)| k);
                let Some(k) = nearest else {
                    picked.push(None);
                    continue;
                };
                for _ in 0..k {
                    queue.pop_front();
                    stats.dropped += 1;
                }
                picked.push(queue.pop_front());
            }
            let present: Vec<bool> = picked.iter().map(Option::is_some).collect();
            let complete = present.iter().all(|&p| p);
            if complete || accept(&present) {
                let times = || picked.iter().flatten().map(|f| f.capture_ns);
                let (first, last) = (times().min().unwrap_or(start), times().max().unwrap_or(start));
                for (frame, stats) in picked.iter().zip(&mut self.stats) {
                    match frame {
                        Some(_) => stats.used += 1,
                        None => stats.missed_sets += 1,
                    }
                }
                if !complete {
                    self.partial_sets += 1;
                }
                return Some((first + (last - first) / 2, picked));
            }
            self.incomplete_sets += 1;
            for (frame, stats) in picked.iter().zip(&mut self.stats) {
                match frame {
                    Some(_) => stats.dropped += 1,
                    None => stats.missed_sets += 1,
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: u64 = 1_000_000;
    const T: u64 = 33 * MS;

    fn frame(ns: u64, camera: u8) -> TimedFrame {
        TimedFrame { capture_ns: ns, delivered_ns: ns, data: vec![camera] }
    }

    /// A set's instant and its cameras' capture times (`None`: the camera missed it).
    type TimedSet = (u64, Vec<Option<u64>>);

    /// Feeds each camera's capture times in time order, asking for sets after every frame
    /// with the clock at that frame (a set some camera missed is returned when `accept` says
    /// so); returns the sets' instants and per-set camera times, `None` for a missing camera.
    fn drive(times: &[Vec<u64>], stall: u64, accept: impl Fn(&[bool]) -> bool) -> (FrameSetSync, Vec<TimedSet>) {
        let mut sync = FrameSetSync::new(times.len(), T);
        let mut events: Vec<(u64, usize)> =
            times.iter().enumerate().flat_map(|(c, ts)| ts.iter().map(move |&t| (t, c))).collect();
        events.sort_unstable();
        let mut sets = Vec::new();
        for (t, c) in events {
            sync.push(c, frame(t, c as u8));
            while let Some((instant, frames)) = sync.next_set_or_partial(t, stall, &accept) {
                assert!(
                    frames.iter().enumerate().all(|(k, f)| f.as_ref().is_none_or(|f| f.data == vec![k as u8])),
                    "camera order"
                );
                sets.push((instant, frames.iter().map(|f| f.as_ref().map(|f| f.capture_ns)).collect()));
            }
        }
        (sync, sets)
    }

    /// [`drive`] with complete sets only.
    fn run(times: &[Vec<u64>], stall: u64) -> (FrameSetSync, Vec<(u64, Vec<u64>)>) {
        let (sync, sets) = drive(times, stall, |_| false);
        (sync, sets.into_iter().map(|(instant, frames)| (instant, frames.into_iter().flatten().collect())).collect())
    }

    #[test]
    fn cameras_a_third_of_a_frame_apart_and_jittering_make_one_set_per_instant() {
        // Three cameras up to a sixth of a frame apart, each jittering by up to a sixth: up
        // to a third of a frame between two cameras' frames of one instant.
        let jitter = |k: u64| [0, T / 6, T / 12, T / 8][(k % 4) as usize];
        let times: Vec<Vec<u64>> =
            (0..3u64).map(|c| (0..60u64).map(|k| 1_000 * MS + k * T + c * T / 12 + jitter(k + c)).collect()).collect();
        let (sync, sets) = run(&times, 4 * T);
        assert!(sets.len() >= 58, "{} sets", sets.len());
        for (instant, frames) in &sets {
            for &t in frames {
                assert!(t.abs_diff(*instant) <= T / 2, "{t} vs {instant}");
            }
        }
        // Instants a frame apart: no instant taken twice, none skipped.
        for pair in sets.windows(2) {
            let gap = pair[1].0 - pair[0].0;
            assert!(gap > T / 2 && gap < 3 * T / 2, "gap {gap}");
        }
        assert_eq!(sync.incomplete_sets(), 0);
        assert!(sync.stats().iter().all(|s| s.dropped == 0), "{:?}", sync.stats());
    }

    #[test]
    fn cameras_with_phases_spread_over_most_of_a_frame_lose_no_frame() {
        // Three cameras started 0, 15 and 25 ms apart at 30 fps: free-running phases.
        let times: Vec<Vec<u64>> = [0, 15, 25].iter().map(|&p| (0..30u64).map(|k| k * T + p * MS).collect()).collect();
        let (sync, sets) = run(&times, 4 * T);
        assert_eq!(sets.len(), 29, "all but the last, not yet decided");
        for (instant, frames) in &sets {
            assert!(frames.iter().all(|&t| t.abs_diff(*instant) <= T / 2));
        }
        assert!(sync.stats().iter().all(|s| s.dropped == 0), "{:?}", sync.stats());
    }

    #[test]
    fn a_camera_that_starts_late_costs_only_the_sets_before_it_starts() {
        let mut times: Vec<Vec<u64>> = (0..2).map(|_| (0..40u64).map(|k| k * T).collect()).collect();
        times.push((10..40u64).map(|k| k * T + 3 * MS).collect());
        let (sync, sets) = run(&times, 4 * T);
        // Live: the first instants wait out the stall timeout and go as incomplete sets; the
        // rest of the early frames are passed over once the late camera's first frame comes.
        assert!(sets.len() >= 29, "{} sets", sets.len());
        assert_eq!(sets[0].1[2], 10 * T + 3 * MS, "the first set is the late camera's first frame");
        assert_eq!(sync.stats()[2].missed_sets, sync.incomplete_sets());
        assert!(sync.incomplete_sets() >= 5, "{}", sync.incomplete_sets());
        assert_eq!(sync.stats()[0].used, sets.len() as u64);
        assert_eq!(sync.stats()[0].used + sync.stats()[0].dropped, 40 - 1, "all but the last frame, not yet decided");
    }

    #[test]
    fn a_camera_that_stops_is_counted_and_the_others_go_on_only_as_far_as_it_went() {
        let mut times: Vec<Vec<u64>> = (0..2).map(|_| (0..40u64).map(|k| k * T).collect()).collect();
        times.push((0..20u64).map(|k| k * T + MS).collect());
        let (sync, sets) = run(&times, 4 * T);
        assert!((19..=20).contains(&sets.len()), "{} sets", sets.len());
        // Every set after the stop (but the last few, not yet waited out) is incomplete.
        assert!(sync.stats()[2].missed_sets >= 15, "{:?}", sync.stats()[2]);
        assert_eq!(sync.stats()[0].received, 40);
        // Replay: without a stall timeout the sets wait for it.
        let (sync, sets) = run(&times, u64::MAX);
        assert_eq!(sets.len(), 19, "the last frame of the stopped camera is not yet decided");
        assert_eq!(sync.incomplete_sets(), 0);
    }

    #[test]
    fn a_live_stream_goes_on_without_a_camera_that_stopped_when_the_others_can_carry_it() {
        let mut times: Vec<Vec<u64>> = (0..2).map(|_| (0..40u64).map(|k| k * T).collect()).collect();
        times.push((0..20u64).map(|k| k * T + MS).collect());
        // Camera 0 (the reference) and one other at least.
        let (sync, sets) = drive(&times, 4 * T, |p| p[0] && p.iter().filter(|&&x| x).count() >= 2);
        // Every instant but the last four, still within the stall timeout at the last frame.
        assert_eq!(sets.len(), 36);
        assert!(sets[..20].iter().all(|(_, f)| f.iter().all(Option::is_some)));
        assert!(sets[20..].iter().all(|(_, f)| f[0].is_some() && f[1].is_some() && f[2].is_none()));
        assert_eq!(sync.partial_sets(), 16);
        assert_eq!(sync.incomplete_sets(), 0);
        assert_eq!(sync.stats()[2].missed_sets, 16);
    }

    #[test]
    fn a_camera_twice_as_fast_gives_one_frame_per_set_and_the_rest_are_dropped() {
        let times = vec![(0..30u64).map(|k| k * T).collect(), (0..60u64).map(|k| k * T / 2 + MS).collect::<Vec<_>>()];
        let (sync, sets) = run(&times, 4 * T);
        assert!(sets.len() >= 28);
        for (instant, frames) in &sets {
            assert!(frames[1].abs_diff(*instant) <= 2 * MS, "the nearer of two frames");
        }
        assert!(sync.stats()[1].dropped >= 27, "{:?}", sync.stats()[1]);
        assert_eq!(sync.stats()[0].dropped, 0);
    }

    #[test]
    fn frames_that_all_arrive_late_are_still_grouped_whole_in_a_live_stream() {
        // Three cameras whose frames arrive half a second after their capture (a decoder
        // behind the clock), each camera 10 ms after the one before; the stall timeout is
        // four frames. Timed from capture, every window would look stalled.
        let late = 500 * MS;
        let mut sync = FrameSetSync::new(3, T);
        let mut events: Vec<(u64, usize, u64)> =
            (0..30u64).flat_map(|n| (0..3).map(move |c| (n * T + late + c as u64 * 10 * MS, c, n * T))).collect();
        events.sort_unstable();
        let mut sets = 0;
        for (now, c, capture) in events {
            sync.push(c, TimedFrame { capture_ns: capture, delivered_ns: now, data: vec![c as u8] });
            while let Some((_, frames)) =
                sync.next_set_or_partial(now, 4 * T, |p| p[0] && p.iter().filter(|&&x| x).count() >= 2)
            {
                assert!(frames.iter().all(Option::is_some), "a set without a camera whose frame was on its way");
                sets += 1;
            }
        }
        assert!(sets >= 29, "{sets} sets of 30");
        assert!(sync.stats().iter().all(|s| s.dropped == 0 && s.missed_sets == 0), "{:?}", sync.stats());
    }

    #[test]
    fn a_frame_from_the_past_and_a_flood_are_dropped_not_kept() {
        let mut sync = FrameSetSync::new(2, T);
        sync.push(0, frame(10 * T, 0));
        sync.push(0, frame(9 * T, 0));
        assert_eq!(sync.stats()[0].dropped, 1);
        for k in 11..40 {
            sync.push(0, frame(k * T, 0));
        }
        assert_eq!(sync.queues[0].len(), MAX_WAITING_FRAMES);
        assert!(sync.next_set(40 * T, u64::MAX).is_none(), "camera 1 never came: replay waits");
    }
}
