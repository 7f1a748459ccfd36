//! The stream's live figures for `/api/status`: rate, latency percentiles, drops, each
//! track's latest estimate.

use std::collections::{BTreeMap, VecDeque};
use std::time::{Duration, Instant};

use handflow_protocol::messages::TrajectorySample;
use serde_json::{json, Value};

use crate::{ObjectSample, TrajectoryRecord};

/// The rate is counted over the samples of this last while.
const RATE_WINDOW: Duration = Duration::from_secs(5);
/// Latency percentiles are over this many latest samples.
const LATENCY_WINDOW: usize = 300;

/// What the viewer knows about the stream of trajectory samples.
#[derive(Debug, Default)]
pub struct StreamFigures {
    samples: u64,
    arrivals: VecDeque<Instant>,
    latencies_ms: VecDeque<f64>,
    dropped_frames: u64,
    missing_views: u32,
    last_frame: Option<u64>,
    last_arrival: Option<Instant>,
    ended: bool,
    tracks: BTreeMap<String, ObjectSample>,
}

impl StreamFigures {
    /// Notes a sample (`record` is its record) that arrived at `now` (an end of stream
    /// included).
    pub fn on_sample(&mut self, sample: &TrajectorySample, record: &TrajectoryRecord, now: Instant) {
        if sample.is_end_of_stream() {
            self.ended = true;
            return;
        }
        if self.ended {
            // A new stream: its figures start afresh.
            *self = StreamFigures::default();
        }
        self.samples += 1;
        self.arrivals.push_back(now);
        while self.arrivals.front().is_some_and(|&t| now.duration_since(t) > RATE_WINDOW) {
            self.arrivals.pop_front();
        }
        if let Some(ms) = latency_ms(sample) {
            self.latencies_ms.push_back(ms);
            if self.latencies_ms.len() > LATENCY_WINDOW {
                self.latencies_ms.pop_front();
            }
        }
        self.dropped_frames = sample.dropped_frames;
        self.missing_views = sample.missing_views;
        self.last_frame = Some(sample.frame);
        self.last_arrival = Some(now);
        self.tracks.clone_from(&record.objects);
    }

    /// Samples per second over the last few seconds (`None` before two samples).
    pub fn rate_hz(&self, now: Instant) -> Option<f64> {
        let recent: Vec<&Instant> = self.arrivals.iter().filter(|&&t| now.duration_since(t) <= RATE_WINDOW).collect();
        let (first, last) = (recent.first()?, recent.last()?);
        let span = last.duration_since(**first).as_secs_f64();
        (recent.len() >= 2 && span > 0.0).then(|| (recent.len() - 1) as f64 / span)
    }

    /// The `p`-quantile (0..=1) of the latest latencies, milliseconds.
    pub fn latency_percentile_ms(&self, p: f64) -> Option<f64> {
        let mut v: Vec<f64> = self.latencies_ms.iter().copied().collect();
        v.sort_by(f64::total_cmp);
        let last = v.len().checked_sub(1)?;
        v.get(((last as f64) * p.clamp(0.0, 1.0)).round() as usize).copied()
    }

    /// The `stream` and `tracks` members of `/api/status`.
    pub fn to_json(&self, now: Instant) -> (Value, Value) {
        let latency = match (self.latency_percentile_ms(0.5), self.latency_percentile_ms(0.99)) {
            (Some(p50), Some(p99)) => json!({ "p50": p50, "p99": p99 }),
            _ => Value::Null,
        };
        let missing: Vec<u32> = (0..32).filter(|k| self.missing_views & (1 << k) != 0).collect();
        let stream = json!({
            "samples": self.samples,
            "rate_hz": self.rate_hz(now),
            "latency_ms": latency,
            "dropped_frames": self.dropped_frames,
            "missing_views": missing,
            "last_frame": self.last_frame,
            "last_sample_age_s": self.last_arrival.map(|t| now.duration_since(t).as_secs_f64()),
            "ended": self.ended,
        });
        (stream, json!(self.tracks))
    }
}

/// Glass-to-trajectory latency of a sample, milliseconds (`None` without a capture time).
pub fn latency_ms(sample: &TrajectorySample) -> Option<f64> {
    (sample.capture_unix_ns > 0 && sample.published_unix_ns >= sample.capture_unix_ns)
        .then(|| (sample.published_unix_ns - sample.capture_unix_ns) as f64 * 1e-6)
}

/// The WebSocket message of a sample: `{"type":"sample", ...the trajectory file's record,
/// "sequence", "latency_ms"}` (`record` is the sample's record), or `{"type":"end","sequence"}`.
pub fn sample_message(sample: &TrajectorySample, record: &TrajectoryRecord) -> String {
    if sample.is_end_of_stream() {
        return json!({ "type": "end", "sequence": sample.sequence }).to_string();
    }
    json!({
        "type": "sample",
        "sequence": sample.sequence,
        "frame": record.frame,
        "t": record.t,
        "objects": record.objects,
        "dropped_frames": record.dropped_frames,
        "missing_views": record.missing_views,
        "latency_ms": latency_ms(sample),
    })
    .to_string()
}

#[cfg(test)]
mod tests {
    use super::*;
    use handflow_protocol::messages::{track_state, END_OF_STREAM};

    fn sample(frame: u64, latency_ms: u64) -> TrajectorySample {
        let mut s = TrajectorySample { frame, sequence: frame, timestamp_s: frame as f64 / 10.0, ..Default::default() };
        s.capture_unix_ns = 1_000_000_000;
        s.published_unix_ns = s.capture_unix_ns + latency_ms * 1_000_000;
        s.objects[0].position = [0.1, 1.6, 2.0];
        s.objects[0].state = track_state::TRACKED;
        s.objects[0].confidence = 0.8;
        s
    }

    #[test]
    fn rate_and_latency_percentiles_follow_the_recent_samples() {
        let t0 = Instant::now();
        let mut f = StreamFigures::default();
        for k in 0..=20u64 {
            let s = sample(k, 10 + k);
            f.on_sample(&s, &TrajectoryRecord::from_sample(&s), t0 + Duration::from_millis(100 * k));
        }
        let now = t0 + Duration::from_millis(2000);
        let rate = f.rate_hz(now).expect("rate");
        assert!((rate - 10.0).abs() < 1e-6, "{rate}");
        assert_eq!(f.latency_percentile_ms(0.5), Some(20.0));
        assert_eq!(f.latency_percentile_ms(0.99), Some(30.0));
        let (stream, tracks) = f.to_json(now);
        assert_eq!(stream["samples"], 21);
        assert_eq!(stream["last_frame"], 20);
        assert_eq!(tracks["head"]["state"], "tracked");
        // Long after the last sample the rate is unknown, not the old one.
        assert_eq!(f.rate_hz(now + Duration::from_secs(60)), None);
    }

    #[test]
    fn an_end_of_stream_is_reported_and_the_next_stream_starts_afresh() {
        let t0 = Instant::now();
        let mut f = StreamFigures::default();
        f.on_sample(&sample(1, 5), &TrajectoryRecord::from_sample(&sample(1, 5)), t0);
        let end = TrajectorySample { flags: END_OF_STREAM, sequence: 2, ..Default::default() };
        f.on_sample(&end, &TrajectoryRecord::from_sample(&end), t0);
        assert_eq!(f.to_json(t0).0["ended"], true);
        assert_eq!(sample_message(&end, &TrajectoryRecord::from_sample(&end)), r#"{"sequence":2,"type":"end"}"#);
        f.on_sample(&sample(1, 5), &TrajectoryRecord::from_sample(&sample(1, 5)), t0);
        let (stream, _) = f.to_json(t0);
        assert_eq!((stream["ended"].as_bool(), stream["samples"].as_u64()), (Some(false), Some(1)));
    }

    #[test]
    fn a_sample_message_carries_the_trajectory_files_record() {
        let s = sample(7, 12);
        let v: Value = serde_json::from_str(&sample_message(&s, &TrajectoryRecord::from_sample(&s))).expect("json");
        assert_eq!(v["type"], "sample");
        assert_eq!(v["frame"], 7);
        assert_eq!(v["latency_ms"], 12.0);
        assert_eq!(v["objects"]["head"]["pos"][1], 1.6);
        let record: TrajectoryRecord = serde_json::from_value(v).expect("reads as a record");
        assert_eq!(record.frame, 7);
    }
}
