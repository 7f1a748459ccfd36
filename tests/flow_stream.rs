//! The flow stream's schedule on a small rendered recording: which frames get an estimate,
//! with which metadata, in which order, for a stream from its start, a live stream that skips
//! its warm-up backlog, and a stream joined part-way (its skin models adapted first).

#![allow(clippy::unwrap_used)]

use handflow_e2e::render_preset;
use handflow_flow::stream::{
    detect_every_for_rate, model_lag_for_rate, scene_point_count, scene_points, stream_engine_config, FlowStream,
    SetOutcome, StreamError,
};
use handflow_flow::{SceneFlowEngine, Variant};
use handflow_ingest::Recording;

const FRAMES: u32 = 26;

/// `FRAMES` frame sets of `signer-3cam` rendered small into `dir`, and a stream engine for its rig.
fn rendered_recording_and_engine(dir: &std::path::Path) -> (Recording, SceneFlowEngine) {
    let rec = Recording::open(render_preset(dir, "signer-3cam", FRAMES, Some((160, 120)))).unwrap();
    let rig = rec.rig();
    let reference = rig.most_frontal_camera();
    let config = stream_engine_config(Variant::Handflow, None, rec.frame_rate(), &rig.cameras, reference);
    let engine = SceneFlowEngine::new(config, rig.cameras.clone(), reference).unwrap();
    (rec, engine)
}

/// What a stream configured by `configure` hands out for the frame sets `first..FRAMES`, the
/// sets in `passed` passed over ([`FlowStream::pass_over`]): each set's frame, and whether it
/// was estimated.
fn handed_out(
    configure: impl FnOnce(FlowStream<u64>) -> FlowStream<u64>,
    first: u64,
    passed: &[u64],
) -> Vec<(u64, bool)> {
    let dir = tempfile::tempdir().unwrap();
    let (rec, engine) = rendered_recording_and_engine(dir.path());
    let mut stream = configure(FlowStream::new(engine));
    let mut buf = vec![0u8; rec.frame_set_len()];
    let mut seen = Vec::new();
    let mut record = |k: u64, outcome: SetOutcome<'_>| {
        if let SetOutcome::Estimated { engine, .. } = outcome {
            // The points handed to clustering are the estimate's, with sensible values.
            let points: Vec<_> = scene_points(engine).collect();
            assert_eq!(points.len(), scene_point_count(engine));
            assert!(!points.is_empty(), "frame {k} has particles on the skin");
            assert!(points.iter().all(|p| p.weight >= 0.0 && (0.0..=1.0).contains(&p.skin)));
        }
        seen.push((k, matches!(outcome, SetOutcome::Estimated { .. })));
        Ok::<(), StreamError>(())
    };
    for k in first..u64::from(FRAMES) {
        if passed.contains(&k) {
            stream.pass_over(k, &mut record).unwrap();
            continue;
        }
        rec.read_frame_into(k, false, &mut buf).unwrap();
        stream.push(k, &buf, &mut record).unwrap();
    }
    stream.finish(&mut record).unwrap();
    seen
}

/// The frames a stream configured by `configure` estimates, from frame `first` on.
fn estimated_frames(configure: impl FnOnce(FlowStream<u64>) -> FlowStream<u64>, first: u64) -> Vec<u64> {
    let seen = handed_out(configure, first, &[]);
    assert!(seen.iter().all(|&(_, estimated)| estimated), "nothing was passed over: {seen:?}");
    seen.into_iter().map(|(k, _)| k).collect()
}

#[test]
fn a_stream_from_its_start_estimates_every_frame_in_order() {
    assert_eq!(estimated_frames(|s| s, 0), (0..u64::from(FRAMES)).collect::<Vec<_>>());
}

#[test]
fn sets_passed_over_are_handed_out_in_their_place_among_the_estimates() {
    // Passed over: one while the warm-up holds the first frames, two in a row later, and the
    // last set, after the last estimate's set.
    let passed = [3, 12, 13, u64::from(FRAMES) - 1];
    let seen = handed_out(|s| s, 0, &passed);
    let expected: Vec<(u64, bool)> = (0..u64::from(FRAMES)).map(|k| (k, !passed.contains(&k))).collect();
    assert_eq!(seen, expected);
    // A live stream drops the stale sets of its warm-up backlog and the sets passed over
    // before the first it keeps; a set passed over among the kept ones stays in its place.
    let live = |s: FlowStream<u64>| s.with_backlog_limit(3).without_waiting_for_models();
    // 21 sets held (frames 0..=22 less 5 and 21); kept: 19, 20 and 22.
    let expected: Vec<(u64, bool)> = (19..u64::from(FRAMES)).map(|k| (k, k != 21)).collect();
    assert_eq!(handed_out(live, 0, &[5, 21]), expected);
    // 21 sets held (frames 0..=22 less 5 and 19); kept: 20, 21 and 22; 19 is stale.
    let expected: Vec<(u64, bool)> = (20..u64::from(FRAMES)).map(|k| (k, true)).collect();
    assert_eq!(handed_out(live, 0, &[5, 19]), expected);
}

#[test]
fn a_live_stream_skips_the_stale_part_of_its_warm_up_backlog() {
    let frames = estimated_frames(|s| s.with_backlog_limit(3).without_waiting_for_models(), 0);
    // Frames 0..=20 are held for the warm-up; of those only 18, 19 and 20 are pushed, so the
    // first estimate is frame 18's.
    assert_eq!(frames, (18..u64::from(FRAMES)).collect::<Vec<_>>());
}

#[test]
fn at_a_low_frame_rate_the_warm_up_holds_the_same_time_not_the_same_frames() {
    // At 6 fps the warm-up's rounds are 2 frames apart (a third of a second, as 10 frames
    // at 30 fps): frames 0..=4 are held, and a live stream's first estimate is frame 2's.
    assert_eq!(detect_every_for_rate(6.0), 2);
    assert_eq!(model_lag_for_rate(6.0), 1);
    assert_eq!(detect_every_for_rate(30.0), handflow_flow::skin::adapt::DEFAULT_DETECT_EVERY);
    assert_eq!(detect_every_for_rate(120.0), handflow_flow::skin::adapt::DEFAULT_DETECT_EVERY);
    let frames = estimated_frames(|s| s.with_frame_rate(6.0).with_backlog_limit(3).without_waiting_for_models(), 0);
    assert_eq!(frames, (2..u64::from(FRAMES)).collect::<Vec<_>>());
    let frames = estimated_frames(|s| s.with_frame_rate(6.0), 0);
    assert_eq!(frames, (0..u64::from(FRAMES)).collect::<Vec<_>>());
}

#[test]
fn a_stream_joined_part_way_estimates_from_its_first_frame() {
    let frames = estimated_frames(
        |mut s| {
            s.joining_mid_stream();
            s
        },
        10,
    );
    assert_eq!(frames, (10..u64::from(FRAMES)).collect::<Vec<_>>());
}

/// Likelihood evaluations of the first estimate on three frames of a stream pushed from frame
/// `first` (its second frame's) and of the next, and whether the next carried its posterior.
fn first_two_estimates(join: bool, first: u64) -> (u64, u64, bool) {
    let dir = tempfile::tempdir().unwrap();
    let (rec, engine) = rendered_recording_and_engine(dir.path());
    let mut stream = FlowStream::new(engine).with_frame_rate(rec.frame_rate());
    if join {
        stream.joining_mid_stream();
    }
    let mut buf = vec![0u8; rec.frame_set_len()];
    let mut stats = Vec::new();
    // A stream from its start holds its first frames for the warm-up's face detections.
    for k in first..u64::from(FRAMES) {
        if stats.len() >= 3 {
            break;
        }
        rec.read_frame_into(k, false, &mut buf).unwrap();
        stream
            .push(k, &buf, |_, outcome: SetOutcome<'_>| {
                if let SetOutcome::Estimated { engine, .. } = outcome {
                    stats.push(engine.stats());
                }
                Ok::<(), StreamError>(())
            })
            .unwrap();
    }
    assert!(stats.len() >= 3, "three estimates from {} frames", u64::from(FRAMES) - first);
    // The first frame, seen with its successor alone, is estimated but not carried on.
    assert!(!stats[0].used_temporal_prior && !stats[1].used_temporal_prior, "{stats:?}");
    (stats[1].evaluations, stats[2].evaluations, stats[2].used_temporal_prior)
}

#[test]
fn a_stream_joined_part_way_answers_with_a_cheaper_first_estimate_then_carries_it() {
    let (start_first, start_second, start_carried) = first_two_estimates(false, 0);
    let (join_first, join_second, join_carried) = first_two_estimates(true, 10);
    assert!(start_carried && join_carried, "later estimates build on the first");
    // A first estimate runs its broad pass plus the extra passes: 1 + 8 at a stream's start,
    // 1 + 1 when joining. Each pass is about one carried estimate's work.
    assert!(
        join_first * 2 < start_first,
        "joining: {join_first} evaluations, start: {start_first} (carried: {start_second}, {join_second})"
    );
    assert!(join_first > join_second, "still more than a carried estimate: {join_first} vs {join_second}");
}

#[test]
fn a_stream_joined_part_way_adapts_its_skin_models_to_its_first_frame_before_estimating() {
    let dir = tempfile::tempdir().unwrap();
    let (rec, engine) = rendered_recording_and_engine(dir.path());
    let mut stream = FlowStream::new(engine).with_frame_rate(rec.frame_rate()).without_waiting_for_models();
    stream.joining_mid_stream();
    let mut buf = vec![0u8; rec.frame_set_len()];
    let mut estimated = 0;
    for k in 10..u64::from(FRAMES) {
        rec.read_frame_into(k, false, &mut buf).unwrap();
        stream
            .push(k, &buf, |_, _: SetOutcome<'_>| {
                estimated += 1;
                Ok::<(), StreamError>(())
            })
            .unwrap();
        if estimated > 0 {
            break;
        }
    }
    assert_eq!(estimated, 1, "the joined stream's first estimate");
    // Its skin maps came from the models of a detection round on the first frame pushed
    // (push index 0; at this size the round finds no face, so the models stay as they were).
    let round = stream.faces_of_last_estimate().expect("a face round made the first estimate's skin maps");
    assert_eq!(round.frame, 0);
}
