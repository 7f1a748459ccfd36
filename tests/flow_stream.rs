//! The flow stream's schedule on a small rendered recording: which frames get an estimate,
//! with which metadata, in which order, for a stream from its start, a live stream that skips
//! its warm-up backlog, and a stream joined part-way.

#![allow(clippy::unwrap_used)]

use handflow_e2e::render_preset;
use handflow_flow::stream::{scene_point_count, scene_points, stream_engine_config, FlowStream, StreamError};
use handflow_flow::{SceneFlowEngine, Variant};
use handflow_ingest::Recording;

const FRAMES: u32 = 26;

fn estimated_frames(configure: impl FnOnce(FlowStream<u64>) -> FlowStream<u64>, first: u64) -> Vec<u64> {
    let dir = tempfile::tempdir().unwrap();
    let rec = Recording::open(render_preset(dir.path(), "signer-3cam", FRAMES, Some((160, 120)))).unwrap();
    let rig = rec.rig();
    let reference = rig.most_frontal_camera();
    let config = stream_engine_config(Variant::Handflow, None, rec.frame_rate());
    let engine = SceneFlowEngine::new(config, rig.cameras.clone(), reference).unwrap();
    let mut stream = configure(FlowStream::new(engine));
    let mut buf = vec![0u8; rec.frame_set_len()];
    let mut seen = Vec::new();
    let mut record = |k: u64, engine: &SceneFlowEngine| {
        // The points handed to clustering are the estimate's, with sensible values.
        let points: Vec<_> = scene_points(engine).collect();
        assert_eq!(points.len(), scene_point_count(engine));
        assert!(!points.is_empty(), "frame {k} has particles on the skin");
        assert!(points.iter().all(|p| p.weight >= 0.0 && (0.0..=1.0).contains(&p.skin)));
        seen.push(k);
        Ok::<(), StreamError>(())
    };
    for k in first..u64::from(FRAMES) {
        rec.read_frame_into(k, false, &mut buf).unwrap();
        stream.push(k, &buf, &mut record).unwrap();
    }
    stream.finish(&mut record).unwrap();
    seen
}

#[test]
fn a_stream_from_its_start_estimates_every_frame_but_the_first_in_order() {
    assert_eq!(estimated_frames(|s| s, 0), (1..u64::from(FRAMES)).collect::<Vec<_>>());
}

#[test]
fn a_live_stream_skips_the_stale_part_of_its_warm_up_backlog() {
    let frames = estimated_frames(|s| s.with_backlog_limit(3).without_waiting_for_models(), 0);
    // Frames 0..=20 are held for the warm-up; of those only 18, 19 and 20 are pushed, so the
    // first estimate is frame 19's.
    assert_eq!(frames, (19..u64::from(FRAMES)).collect::<Vec<_>>());
}

#[test]
fn a_stream_joined_part_way_estimates_from_its_second_frame() {
    let frames = estimated_frames(
        |mut s| {
            s.joining_mid_stream();
            s
        },
        10,
    );
    assert_eq!(frames, (11..u64::from(FRAMES)).collect::<Vec<_>>());
}
