//! The viewer's window on shared memory, on a thread of its own: the rig (for the 3D view
//! and to draw on the thumbnails), frame sets (a few per second become thumbnails with the
//! tracks drawn), the live cameras' health and each stage's liveness.

use std::collections::VecDeque;
use std::sync::mpsc::Receiver;
use std::time::{Duration, Instant};

use axum::body::Bytes;
use handflow_protocol::ipc::{self, Input, Receive, ServiceNames};
use handflow_protocol::messages::{camera_state, CameraStatusSet, FrameHeader};
use handflow_protocol::Rig;
use image::RgbImage;
use serde_json::{json, Value};

use super::{lock, thumbnails, Shared};
use crate::TrajectoryRecord;

/// How often the monitor looks at shared memory: frames of a replay wait for it.
const POLL: Duration = Duration::from_millis(15);
/// How often services not yet there are looked for, and stages' health refreshed.
const RECHECK: Duration = Duration::from_secs(1);
/// A chosen frame waits this long at most for its own trajectory sample (a live stage may
/// have dropped it), then is drawn with the latest ones.
const PAIRING_WAIT: Duration = Duration::from_secs(1);
/// Each track's positions over this last while are drawn on a thumbnail.
const TRAIL_SECONDS: f64 = 0.5;

/// A frame set chosen for thumbnails, waiting for its trajectory sample.
struct Pending {
    frame: u64,
    views: Vec<(RgbImage, f64)>,
    since: Instant,
}

/// Runs until the process is asked to stop. Failures are logged, never fatal: the
/// publisher goes on without thumbnails or health.
pub fn run(
    shared: &Shared,
    names: &ServiceNames,
    thumbnail_interval: Option<Duration>,
    samples: &Receiver<TrajectoryRecord>,
) {
    let node = match ipc::create_node("handflow-viewer") {
        Ok(node) => node,
        Err(e) => {
            tracing::error!("viewer: no shared memory, so no rig, thumbnails or health: {e}");
            return;
        }
    };
    let rig_input = match ipc::rig_input(&node, names) {
        Ok(input) => input,
        Err(e) => {
            tracing::error!("viewer: {e}");
            return;
        }
    };
    let mut rig: Option<(u32, Rig)> = None;
    let mut frames: Option<Input<[u8], FrameHeader>> = None;
    let mut cameras: Option<Input<CameraStatusSet, ()>> = None;
    let mut tail: VecDeque<TrajectoryRecord> = VecDeque::new();
    let mut pending: Option<Pending> = None;
    let mut next_thumbnail = Instant::now();
    let mut next_check = Instant::now();
    while !ipc::stop_requested() {
        let now = Instant::now();
        if let Ok(Some(sample)) = rig_input.receive_one() {
            let header = *sample.user_header();
            match ipc::parse_rig(&names.rig(), &header, sample.payload()) {
                Ok(new) => {
                    shared.set_rig(&new, header.frame_rate_hz);
                    rig = Some((header.rig_version, new));
                    pending = None;
                }
                Err(e) => tracing::error!("viewer: {e}"),
            }
        }
        if now >= next_check {
            next_check = now + RECHECK;
            *lock(&shared.stages) = ipc::stage_health(&node, names);
            if frames.is_none() && thumbnail_interval.is_some() {
                frames = ipc::tap_frames(&node, &names.frames()).ok();
            }
            if cameras.is_none() {
                cameras = ipc::tap_cameras(&node, &names.cameras()).ok();
            }
        }
        if let Some(input) = &frames {
            // Every waiting frame set is taken (a replay's ingest waits for this reader);
            // only one per interval is kept.
            while let Ok(Some(sample)) = input.receive_one() {
                let header = *sample.user_header();
                let due = thumbnail_interval.is_some_and(|_| Instant::now() >= next_thumbnail);
                let Some((version, rig)) = rig.as_ref().filter(|_| due && !header.is_end_of_stream()) else { continue };
                if header.rig_version != *version || header.validate(sample.payload().len()).is_err() {
                    continue;
                }
                let views = header
                    .views(sample.payload())
                    .iter()
                    .zip(&rig.cameras)
                    .enumerate()
                    .map(|(k, (view, cam))| {
                        let (width, height) = header.view_size(k);
                        let shrunk =
                            header.has_view(k).then(|| thumbnails::shrink(view, width, height, cam.width, cam.height));
                        shrunk.flatten().unwrap_or_else(|| (RgbImage::new(1, 1), 0.0))
                    })
                    .collect();
                pending = Some(Pending { frame: header.frame, views, since: Instant::now() });
                next_thumbnail = Instant::now() + thumbnail_interval.unwrap_or(RECHECK);
            }
        }
        while let Ok(record) = samples.try_recv() {
            if tail.back().is_some_and(|last| record.frame < last.frame) {
                tail.clear(); // A new stream.
            }
            tail.push_back(record);
            while tail.len() > 2 && tail.back().zip(tail.front()).is_some_and(|(b, f)| b.t - f.t > 2.0 * TRAIL_SECONDS)
            {
                tail.pop_front();
            }
        }
        if let (Some(p), Some((_, rig))) = (&pending, &rig) {
            let answered = tail.back().is_some_and(|r| r.frame >= p.frame);
            if answered || p.since.elapsed() > PAIRING_WAIT {
                if let Some(p) = pending.take() {
                    send_thumbnails(shared, rig, p, &tail);
                }
            }
        }
        if let Some(input) = &cameras {
            let mut latest = None;
            while let Ok(Some(sample)) = input.receive_one() {
                latest = Some(*sample.payload());
            }
            if let Some(set) = latest.filter(|s| s.validate().is_ok()) {
                *lock(&shared.cameras) = camera_rows(&set);
            }
        }
        if !ipc::nap(&node, POLL) {
            break;
        }
    }
}

/// Draws the tracks up to the pending frame on its views and sends them.
fn send_thumbnails(shared: &Shared, rig: &Rig, pending: Pending, tail: &VecDeque<TrajectoryRecord>) {
    let upto: Vec<TrajectoryRecord> = tail.iter().filter(|r| r.frame <= pending.frame).cloned().collect();
    let newest = upto.last().map_or(f64::NEG_INFINITY, |r| r.t);
    let drawn: Vec<TrajectoryRecord> = upto.into_iter().filter(|r| r.t >= newest - TRAIL_SECONDS).collect();
    for (k, ((image, scale), cam)) in pending.views.into_iter().zip(&rig.cameras).enumerate() {
        if scale == 0.0 {
            continue; // The camera delivered nothing for this set.
        }
        match thumbnails::encode(k as u32, pending.frame, image, scale, cam, &drawn) {
            Ok(message) => shared.send_thumbnail(k, Bytes::from(message)),
            Err(e) => tracing::warn!("viewer: thumbnail of camera `{}`: {e}", cam.name),
        }
    }
}

/// The live cameras' health as `/api/status` lists it.
fn camera_rows(set: &CameraStatusSet) -> Vec<Value> {
    let now = ipc::unix_now_ns();
    set.cameras[..(set.camera_count as usize).min(set.cameras.len())]
        .iter()
        .map(|c| {
            let state = match c.state {
                camera_state::RUNNING => "running",
                camera_state::ENDED => "ended",
                camera_state::RECONNECTING => "reconnecting",
                _ => "failed",
            };
            let age = (c.last_capture_unix_ns > 0).then(|| now.saturating_sub(c.last_capture_unix_ns) as f64 * 1e-9);
            json!({ "name": c.name(), "state": state, "rate_hz": c.rate_hz, "delivered": c.delivered,
                    "dropped": c.dropped, "missed_sets": c.missed_sets, "last_frame_age_s": age })
        })
        .collect()
}
