//! End-to-end tests of the streaming service: the real launcher and the four real stage
//! processes over real iceoryx2 shared memory, on rendered recordings.
//!
//! Each test uses its own service prefix; they run one at a time (a pipeline wants both
//! cores).

#![allow(clippy::unwrap_used)]

use std::collections::BTreeSet;
use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use handflow::commands::track::{track_recording, TrackOptions};
use handflow::eval::tracks::{evaluate_tracks, read_tracks};
use handflow_e2e::{binaries_dir, exit_within, in_own_group, pids_of, render_preset, unique_prefix};
use handflow_ingest::Recording;
use handflow_protocol::ipc::{self, Mode, ServiceNames};
use handflow_protocol::messages::{FrameHeader, RigHeader, END_OF_STREAM, PIXEL_FORMAT_RGB8, PROTOCOL_VERSION};

static ONE_PIPELINE_AT_A_TIME: Mutex<()> = Mutex::new(());

fn serial() -> std::sync::MutexGuard<'static, ()> {
    ONE_PIPELINE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner())
}

/// Standard error of a child, line by line, with the time each line arrived.
#[derive(Clone, Default)]
struct Log(Arc<Mutex<Vec<(Instant, String)>>>, Arc<std::sync::atomic::AtomicBool>);

impl Log {
    fn capture(child: &mut Child) -> Self {
        let log = Log::default();
        let stderr = child.stderr.take().unwrap();
        let (lines, ended) = (log.0.clone(), log.1.clone());
        std::thread::spawn(move || {
            for line in BufReader::new(stderr).lines() {
                let Ok(line) = line else { break };
                lines.lock().unwrap().push((Instant::now(), line));
            }
            ended.store(true, std::sync::atomic::Ordering::SeqCst);
        });
        log
    }

    /// The whole log of a child that has exited: its last lines may still be on their way
    /// through the pipe when its exit is seen.
    fn complete_text(&self, timeout: Duration) -> String {
        let started = Instant::now();
        while !self.1.load(std::sync::atomic::Ordering::SeqCst) && started.elapsed() < timeout {
            std::thread::sleep(Duration::from_millis(10));
        }
        self.text()
    }

    fn text(&self) -> String {
        self.0.lock().unwrap().iter().map(|(_, l)| l.as_str()).collect::<Vec<_>>().join("\n")
    }

    /// When the first line after `after` containing every needle arrived.
    fn first_after(&self, after: Instant, needles: &[&str]) -> Option<Instant> {
        self.0
            .lock()
            .unwrap()
            .iter()
            .find(|(t, l)| *t >= after && needles.iter().all(|n| l.contains(n)))
            .map(|(t, _)| *t)
    }
}

fn launcher(args: &[&str]) -> Child {
    let mut command = Command::new(binaries_dir().join("handflow"));
    command.args(["run", "--no-viewer"]).args(args).stdin(Stdio::null()).stdout(Stdio::piped()).stderr(Stdio::piped());
    in_own_group(&mut command).spawn().unwrap()
}

/// Waits for `child` to exit, killing it after `timeout`.
/// Replays `rec_dir` through the launcher into `out` under a fresh prefix named after `test`,
/// asserts that the run succeeded and returns its whole log.
fn replay_succeeds(rec_dir: &Path, out: &Path, test: &str) -> String {
    let prefix = unique_prefix(test);
    let mut run = launcher(&["--recording", str(rec_dir), "--out", str(out), "--services", &prefix]);
    let log = Log::capture(&mut run);
    let status = wait_with_timeout(&mut run, Duration::from_secs(300));
    let text = log.complete_text(Duration::from_secs(5));
    assert!(status.success(), "the run failed:\n{text}");
    text
}

fn wait_with_timeout(child: &mut Child, timeout: Duration) -> std::process::ExitStatus {
    exit_within(child, timeout).unwrap_or_else(|| panic!("the pipeline did not end within {timeout:?}"))
}

fn lines_in(path: &Path) -> usize {
    std::fs::read_to_string(path).map(|t| t.lines().count()).unwrap_or(0)
}

fn str(p: &Path) -> &str {
    p.to_str().unwrap()
}

#[test]
fn replay_through_the_four_processes_matches_the_truth_and_the_offline_tracker_frame_for_frame() {
    let _one = serial();
    let dir = tempfile::tempdir().unwrap();
    let frames = 60;
    let rec_dir = render_preset(dir.path(), "signer-3cam", frames, None);
    let out = dir.path().join("trajectories.jsonl");
    let text = replay_succeeds(&rec_dir, &out, "replay");

    let streamed = read_tracks(&out).unwrap();
    let numbers: Vec<u64> = streamed.iter().map(|r| r.frame).collect();
    // Every frame, the first included (estimated from itself and the next), once each, in order.
    assert_eq!(numbers, (0..u64::from(frames)).collect::<Vec<_>>(), "frames missing or repeated");

    let mut offline = Vec::new();
    track_recording(&rec_dir, &TrackOptions::default(), |r, _, _| {
        offline.push(r.clone());
        Ok(())
    })
    .unwrap();
    // Byte for byte, as `handflow track` would write them.
    let file = std::fs::read_to_string(&out).unwrap();
    assert_eq!(file.lines().count(), offline.len());
    for (line, record) in file.lines().zip(&offline) {
        assert_eq!(
            line,
            serde_json::to_string(record).unwrap(),
            "replay must give exactly what `handflow track` gives"
        );
    }

    let rec = Recording::open(&rec_dir).unwrap();
    let scores = evaluate_tracks(&rec, &streamed).unwrap();
    assert_eq!(scores.frames, frames as usize);
    assert_eq!(scores.head.agreement, 1.0, "{scores:?}");
    assert!(scores.left_hand.agreement >= 0.95 && scores.right_hand.agreement >= 0.95, "{scores:?}");
    assert_eq!(scores.identity_switches, 0);
    for o in [&scores.head, &scores.left_hand, &scores.right_hand] {
        assert!(o.rmse_3d_m < 0.03, "{scores:?}");
    }
    assert!(text.contains("0 frames lost upstream"), "{text}");
}

/// Renders the first `frames` frames of `signer-3cam` with its cameras mounted `turns`
/// clockwise quarter turns into `dir/name`.
fn render_mounted(dir: &Path, name: &str, turns: Vec<u8>, frames: u32) -> std::path::PathBuf {
    use handflow_ingest::synthetic::{write_recording, Renderer, SceneSpec};
    let mut spec = SceneSpec::preset("signer-3cam").unwrap();
    spec.frames = frames;
    spec.cameras.mount_quarter_turns = turns;
    let rec_dir = dir.join(name);
    write_recording(&Renderer::new(&spec).unwrap(), &rec_dir, frames).unwrap();
    rec_dir
}

/// Asserts that the replay's file `out` holds exactly what `handflow track` gives on
/// `rec_dir`, and returns its line count.
fn assert_replay_is_track(rec_dir: &Path, out: &Path) -> usize {
    let mut offline = Vec::new();
    track_recording(rec_dir, &TrackOptions::default(), |r, _, _| {
        offline.push(serde_json::to_string(r).unwrap());
        Ok(())
    })
    .unwrap();
    let file = std::fs::read_to_string(out).unwrap();
    assert!(
        file.lines().eq(offline.iter().map(String::as_str)),
        "replay must give exactly what `handflow track` gives"
    );
    file.lines().count()
}

#[test]
fn a_rig_with_a_camera_mounted_sideways_streams_its_portrait_views_and_replays_as_track_tracks() {
    let _one = serial();
    let dir = tempfile::tempdir().unwrap();
    let frames = 30;
    // The front camera held sideways: 480x640 frames between two 640x480 ones.
    let rec_dir = render_mounted(dir.path(), "sideways", vec![0, 1, 0], frames);
    let rec = Recording::open(&rec_dir).unwrap();
    let sizes: Vec<(u32, u32)> = rec.rig().cameras.iter().map(|c| (c.width, c.height)).collect();
    assert_eq!(sizes, [(640, 480), (480, 640), (640, 480)]);

    let out = dir.path().join("trajectories.jsonl");
    let text = replay_succeeds(&rec_dir, &out, "sideways");
    assert!(text.contains("640x480 / 480x640 / 640x480"), "ingest names each view's size:\n{text}");
    assert!(!text.contains("skipping frame set"), "no frame set refused:\n{text}");
    assert_eq!(assert_replay_is_track(&rec_dir, &out), frames as usize, "every frame");
}

#[test]
fn a_rig_mounted_sideways_whose_calibration_records_no_mounts_is_tracked_upright_by_its_faces() {
    let _one = serial();
    let dir = tempfile::tempdir().unwrap();
    // Every camera held sideways, two one way and one the other, and a calibration that
    // cannot say so (as Pose2Sim's, caliscope's and OpenCV's files cannot): the cameras'
    // own estimate of the up lies on its side.
    let rec_dir = render_mounted(dir.path(), "all-sideways", vec![1, 1, 3], 30);
    let rig_path = rec_dir.join("rig.toml");
    let rig = std::fs::read_to_string(&rig_path).unwrap();
    let unmounted: Vec<&str> = rig.lines().filter(|l| !l.starts_with("mount_quarter_turns")).collect();
    assert!(unmounted.len() < rig.lines().count(), "the rig file records the mounts:\n{rig}");
    std::fs::write(&rig_path, unmounted.join("\n")).unwrap();
    let rec = Recording::open(&rec_dir).unwrap();
    assert!(rec.rig().world_up().direction.y.abs() < 0.5, "the cameras' estimate lies on its side");

    let out = dir.path().join("trajectories.jsonl");
    let text = replay_succeeds(&rec_dir, &out, "faces-up");
    assert!(text.contains("from the faces the views see"), "the faces' up is said:\n{text}");
    let streamed = read_tracks(&out).unwrap();
    let scores = evaluate_tracks(&rec, &streamed).unwrap();
    for o in [&scores.head, &scores.left_hand, &scores.right_hand] {
        assert!(o.agreement >= 0.95 && o.rmse_3d_m < 0.03, "{scores:?}");
    }
    assert_eq!(scores.identity_switches, 0);
    assert_replay_is_track(&rec_dir, &out);
}

/// The sequences the publisher reported lost (`frames lost upstream: sequence a..=b`).
fn reported_losses(log: &str) -> BTreeSet<u64> {
    let mut lost = BTreeSet::new();
    for line in log.lines() {
        let Some(rest) = line.split("frames lost upstream: sequence ").nth(1) else { continue };
        let range = rest.split_whitespace().next().unwrap();
        let (a, b) = range.split_once("..=").unwrap();
        lost.extend(a.parse::<u64>().unwrap()..=b.parse::<u64>().unwrap());
    }
    lost
}

/// Starts a replay of `rec_dir` at its recorded pace into `out` and, once 40 trajectory
/// samples are written, kills this pipeline's `binary` with SIGKILL. Returns the run, its log
/// and when the kill happened.
fn replay_and_kill(binary: &str, rec_dir: &Path, out: &Path) -> (Child, Log, Instant) {
    let prefix = unique_prefix(binary);
    let mut run =
        launcher(&["--recording", str(rec_dir), "--out", str(out), "--services", &prefix, "--pace", "recorded"]);
    let log = Log::capture(&mut run);
    let started = Instant::now();
    while lines_in(out) < 40 {
        assert!(started.elapsed() < Duration::from_secs(120), "no trajectories:\n{}", log.text());
        assert!(run.try_wait().unwrap().is_none(), "the run ended early:\n{}", log.text());
        std::thread::sleep(Duration::from_millis(10));
    }
    let victims = pids_of(binary, &prefix);
    assert_eq!(victims.len(), 1, "one {binary} of this pipeline");
    let killed_at = Instant::now();
    nix::sys::signal::kill(nix::unistd::Pid::from_raw(victims[0]), nix::sys::signal::Signal::SIGKILL).unwrap();
    (run, log, killed_at)
}

fn kill_mid_stream(binary: &str, rec_dir: &Path, frames: u32) {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("trajectories.jsonl");
    let (mut run, log, killed_at) = replay_and_kill(binary, rec_dir, &out);

    let status = wait_with_timeout(&mut run, Duration::from_secs(300));
    let text = log.complete_text(Duration::from_secs(5));
    assert!(status.success(), "the run failed after the kill:\n{text}");
    let restarted = log.first_after(killed_at, &["restarting it"]).expect("the launcher restarts the stage");
    let stage = binary.trim_start_matches("handflow-");
    let ready = log.first_after(killed_at, &[&format!("handflow_{stage}"), "ready:"]).expect("the stage comes back");
    let recovered = ready - killed_at;
    let first_after = log.first_after(killed_at, &["frames lost upstream"]);

    let records = read_tracks(&out).unwrap();
    let present: BTreeSet<u64> = records.iter().map(|r| r.frame).collect();
    assert_eq!(present.len(), records.len(), "no frame twice");
    let missing: BTreeSet<u64> = (0..u64::from(frames)).filter(|f| !present.contains(f)).collect();
    let reported = reported_losses(&text);
    eprintln!(
        "{binary} killed after {} trajectory samples: restarted after {:?}, ready after {recovered:?}, \
         first trajectory after the gap reported after {:?}; frames lost: {missing:?}",
        present.iter().filter(|f| **f < *missing.first().unwrap_or(&0)).count(),
        restarted - killed_at,
        first_after.map(|t| t - killed_at),
    );
    assert!(!missing.is_empty(), "a killed stage loses what it held");
    assert_eq!(reported, missing, "the publisher reports exactly the frames that never arrived");
    assert!(recovered < Duration::from_secs(1), "stage ready again {recovered:?} after the kill");
    // Trajectories flow again within about a second (0.7 s measured in this debug build; the
    // bound leaves room for a loaded machine).
    let resumed = first_after.expect("trajectories resume") - killed_at;
    assert!(resumed < Duration::from_millis(1500), "trajectories resumed {resumed:?} after the kill");
    assert!(present.contains(&(u64::from(frames) - 1)), "the pipeline carries on to the last frame");
    // Tracking resumes: the head is right again on the frames after the gap.
    let rec = Recording::open(rec_dir).unwrap();
    let after_gap: Vec<_> = records.iter().filter(|r| r.frame > *missing.last().unwrap() + 10).cloned().collect();
    let scores = evaluate_tracks(&rec, &after_gap).unwrap();
    assert!(scores.head.agreement >= 0.9, "{scores:?}");
}

#[test]
fn killing_ingest_mid_stream_resumes_where_the_stream_was() {
    let _one = serial();
    let dir = tempfile::tempdir().unwrap();
    let frames = 120u32;
    let rec_dir = render_preset(dir.path(), "signer-3cam", frames, None);
    let out = dir.path().join("trajectories.jsonl");
    let (mut run, log, _) = replay_and_kill("handflow-ingest", &rec_dir, &out);
    let status = wait_with_timeout(&mut run, Duration::from_secs(300));
    let text = log.complete_text(Duration::from_secs(5));
    assert!(status.success(), "the run failed after the kill:\n{text}");
    assert!(text.contains("restarting it"), "the launcher restarts ingest:\n{text}");
    assert!(text.contains("resuming the stream at frame set"), "ingest resumes, not from frame 0:\n{text}");
    let records = read_tracks(&out).unwrap();
    let present: BTreeSet<u64> = records.iter().map(|r| r.frame).collect();
    assert_eq!(present.len(), records.len(), "no frame twice: the stream did not start again at frame 0");
    let order: Vec<u64> = records.iter().map(|r| r.frame).collect();
    assert!(order.windows(2).all(|w| w[0] < w[1]), "frames in order: {order:?}");
    let missing: BTreeSet<u64> = (0..u64::from(frames)).filter(|f| !present.contains(f)).collect();
    assert_eq!(reported_losses(&text), missing, "every frame is published or reported lost");
    assert!(missing.len() <= 3, "at most the frames in flight are lost: {missing:?}");
    assert!(present.contains(&(u64::from(frames) - 1)), "the stream goes on to its last frame");
    eprintln!("ingest killed and resumed; frames lost: {missing:?}");
}

#[test]
fn a_restarted_replay_ingest_waits_for_a_busy_flow_stage_instead_of_skipping_frame_sets() {
    let _one = serial();
    let dir = tempfile::tempdir().unwrap();
    let frames = 120u32;
    let rec_dir = render_preset(dir.path(), "signer-3cam", frames, None);
    let out = dir.path().join("trajectories.jsonl");
    let prefix = unique_prefix("restarted-ingest-busy-flow");
    // Replay at full speed: the new ingest could send far faster than flow estimates.
    let mut run = launcher(&["--recording", str(&rec_dir), "--out", str(&out), "--services", &prefix]);
    let log = Log::capture(&mut run);
    let started = Instant::now();
    while lines_in(&out) < 20 {
        assert!(started.elapsed() < Duration::from_secs(120), "no trajectories:\n{}", log.text());
        std::thread::sleep(Duration::from_millis(10));
    }
    // Flow busy (stopped) while ingest dies and its replacement starts sending: flow connects
    // to the new publisher only at its next read, a second later.
    let flow = pids_of("handflow-flow", &prefix);
    let ingest = pids_of("handflow-ingest", &prefix);
    assert_eq!((flow.len(), ingest.len()), (1, 1), "one flow and one ingest of this pipeline");
    let signal = |pid: i32, sig| nix::sys::signal::kill(nix::unistd::Pid::from_raw(pid), sig).unwrap();
    signal(flow[0], nix::sys::signal::Signal::SIGSTOP);
    let killed_at = Instant::now();
    signal(ingest[0], nix::sys::signal::Signal::SIGKILL);
    while log.first_after(killed_at, &["resuming the stream at frame set"]).is_none() {
        assert!(killed_at.elapsed() < Duration::from_secs(30), "ingest did not resume:\n{}", log.text());
        std::thread::sleep(Duration::from_millis(10));
    }
    std::thread::sleep(Duration::from_secs(1));
    signal(flow[0], nix::sys::signal::Signal::SIGCONT);
    let status = wait_with_timeout(&mut run, Duration::from_secs(300));
    let text = log.complete_text(Duration::from_secs(5));
    assert!(status.success(), "the run failed:\n{text}");
    let records = read_tracks(&out).unwrap();
    let present: BTreeSet<u64> = records.iter().map(|r| r.frame).collect();
    assert_eq!(present.len(), records.len(), "no frame twice");
    let missing: BTreeSet<u64> = (0..u64::from(frames)).filter(|f| !present.contains(f)).collect();
    assert_eq!(reported_losses(&text), missing, "every frame is published or reported lost");
    // Lost: what the dead ingest's shared memory held (flow's buffer of 4 and the set it was
    // reading), not what the new one sent while flow was busy (dozens before the fix).
    assert!(missing.len() <= 5, "frames lost: {missing:?}");
}

/// Replaces a rendered recording's `rig.toml` by the same rig as caliscope writes it
/// (`camera_array.toml`, rotations as 3x3 matrices, cameras `cam_N`), renaming the image
/// folders to match: the calibration then reaches the stages through a conversion (the rig
/// message's TOML), as real sessions' do.
fn as_caliscope_session(rec_dir: &Path) {
    let rig = Recording::open(rec_dir).unwrap().rig().clone();
    let mut text = String::new();
    for (n, camera) in rig.cameras.iter().enumerate() {
        let r = camera.rotation.matrix();
        let k = &camera.matrix;
        let d = camera.distortion.as_array();
        let t = &camera.translation;
        text.push_str(&format!(
            "[cameras.{n}]\nport = {n}\nsize = [{}, {}]\nrotation_count = 0\nerror = 0.3\n\
             matrix = [[{:?}, {:?}, {:?}], [{:?}, {:?}, {:?}], [{:?}, {:?}, {:?}]]\n\
             distortions = [{:?}, {:?}, {:?}, {:?}, {:?}]\n\
             rotation = [[{:?}, {:?}, {:?}], [{:?}, {:?}, {:?}], [{:?}, {:?}, {:?}]]\n\
             translation = [{:?}, {:?}, {:?}]\n\n",
            camera.width,
            camera.height,
            k[(0, 0)],
            k[(0, 1)],
            k[(0, 2)],
            k[(1, 0)],
            k[(1, 1)],
            k[(1, 2)],
            k[(2, 0)],
            k[(2, 1)],
            k[(2, 2)],
            d[0],
            d[1],
            d[2],
            d[3],
            d[4],
            r[(0, 0)],
            r[(0, 1)],
            r[(0, 2)],
            r[(1, 0)],
            r[(1, 1)],
            r[(1, 2)],
            r[(2, 0)],
            r[(2, 1)],
            r[(2, 2)],
            t.x,
            t.y,
            t.z,
        ));
        std::fs::rename(rec_dir.join(&camera.name), rec_dir.join(format!("cam_{n}"))).unwrap();
    }
    std::fs::remove_file(rec_dir.join("rig.toml")).unwrap();
    std::fs::write(rec_dir.join("camera_array.toml"), text).unwrap();
}

#[test]
fn a_truncated_image_in_the_middle_is_skipped_by_track_and_by_run_and_every_other_frame_is_kept() {
    let _one = serial();
    let dir = tempfile::tempdir().unwrap();
    let frames = 30u32;
    let rec_dir = render_preset(dir.path(), "signer-3cam", frames, Some((160, 120)));
    as_caliscope_session(&rec_dir);
    let rig = Recording::open(&rec_dir).unwrap().rig().clone();
    let broken = rec_dir.join(&rig.cameras[1].name).join("000004.png");
    let bytes = std::fs::read(&broken).unwrap();
    std::fs::write(&broken, &bytes[..bytes.len() / 2]).unwrap();
    let expected: Vec<u64> = (0..u64::from(frames)).filter(|&f| f != 4).collect();

    let mut offline = Vec::new();
    let summary = track_recording(&rec_dir, &TrackOptions::default(), |r, _, _| {
        offline.push(r.clone());
        Ok(())
    })
    .unwrap();
    assert_eq!(summary.skipped_frames, 1);
    assert_eq!(offline.iter().map(|r| r.frame).collect::<Vec<_>>(), expected, "every other frame is tracked");
    for r in &offline {
        assert_eq!(r.dropped_frames, u64::from(r.frame > 4), "frame {}: the skipped set is counted", r.frame);
    }

    let out = dir.path().join("trajectories.jsonl");
    let text = replay_succeeds(&rec_dir, &out, "truncated");
    assert!(!text.contains("restarting it"), "no stage died:\n{text}");
    assert!(text.contains("frame set 4 skipped") && text.contains("000004.png"), "one error naming the frame:\n{text}");
    assert_eq!(reported_losses(&text), BTreeSet::from([4]), "{text}");
    let file = std::fs::read_to_string(&out).unwrap();
    assert_eq!(file.lines().count(), offline.len(), "{text}");
    for (line, record) in file.lines().zip(&offline) {
        assert_eq!(line, serde_json::to_string(record).unwrap(), "replay and `handflow track` agree");
    }
}

#[test]
fn a_run_of_unreadable_frame_sets_longer_than_constant_velocity_spans_is_tracked_across() {
    let _one = serial();
    let dir = tempfile::tempdir().unwrap();
    let rec_dir = render_preset(dir.path(), "signer-3cam", 60, Some((320, 240)));
    let rig = Recording::open(&rec_dir).unwrap().rig().clone();
    // 17 sets unreadable in every camera, over half a second, as a live stage that fell
    // behind loses them: the recording still opens, and the estimate after the gap starts
    // from a stale posterior (held still, half drawn afresh), not one moved by velocities
    // half a second old.
    let (first_lost, last_lost) = (21u64, 37u64);
    for f in first_lost..=last_lost {
        for cam in &rig.cameras {
            std::fs::write(rec_dir.join(&cam.name).join(format!("{f:06}.png")), b"unreadable").unwrap();
        }
    }
    let mut records = Vec::new();
    let summary = track_recording(&rec_dir, &TrackOptions::default(), |r, _, _| {
        records.push(r.clone());
        Ok(())
    })
    .unwrap();
    assert_eq!(summary.skipped_frames, last_lost - first_lost + 1);
    let after: Vec<_> = records.into_iter().filter(|r| r.frame > last_lost).collect();
    assert_eq!(after.len(), 22, "every set after the gap is tracked");
    // Held with the usual share of fresh particles, the right hand was followed 7-17 cm off
    // for five of these 22 frames (0.77); started cold, the head drifted at low rates.
    let scores = evaluate_tracks(&Recording::open(&rec_dir).unwrap(), &after).unwrap();
    for (name, object) in [("head", &scores.head), ("left", &scores.left_hand), ("right", &scores.right_hand)] {
        assert!(object.agreement >= 0.85, "{name}: {scores:?}");
    }
}

#[test]
fn killing_flow_or_cluster_mid_stream_restarts_it_and_reports_exactly_the_frames_lost() {
    let _one = serial();
    let dir = tempfile::tempdir().unwrap();
    let frames = 120;
    let rec_dir = render_preset(dir.path(), "signer-3cam", frames, None);
    kill_mid_stream("handflow-flow", &rec_dir, frames);
    kill_mid_stream("handflow-cluster", &rec_dir, frames);
}

#[test]
fn a_malformed_frame_set_is_skipped_with_a_logged_error_and_the_stream_goes_on() {
    let _one = serial();
    let dir = tempfile::tempdir().unwrap();
    let frames = 26u32;
    let rec_dir = render_preset(dir.path(), "signer-3cam", frames, Some((160, 120)));
    let prefix = unique_prefix("malformed");
    let names = ServiceNames::new(&prefix);
    let mut flow = Command::new(binaries_dir().join("handflow-flow"))
        .args(["--services", &prefix])
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let log = Log::capture(&mut flow);

    // The frames go out from a thread of their own (iceoryx2 ports stay on the thread that
    // made them): a lossless publisher blocks while the flow stage is busy, and the flow
    // stage blocks while nobody reads its particles.
    let (go_tx, go_rx) = std::sync::mpsc::channel::<()>();
    let sender_log = log.clone();
    let sender_names = names.clone();
    let sender = std::thread::spawn(move || {
        let rec = Recording::open(&rec_dir).unwrap();
        let node = ipc::create_node("malformed-sender").unwrap();
        let rig = ipc::rig_output(&node, &sender_names).unwrap();
        let text = rec.rig().to_toml_string();
        let mut sample = rig.publisher.loan_slice(text.len()).unwrap();
        sample.payload_mut().copy_from_slice(text.as_bytes());
        *sample.user_header_mut() = RigHeader {
            protocol_version: PROTOCOL_VERSION,
            rig_version: 1,
            frame_rate_hz: 30.0,
            text_len: text.len() as u64,
        };
        sample.send().unwrap();
        let frames_out = ipc::frames_output(&node, &sender_names, Mode::Replay, rec.frame_set_len()).unwrap();
        let started = Instant::now();
        while frames_out.subscribers() == 0 {
            rig.update_connections();
            assert!(started.elapsed() < Duration::from_secs(30), "flow subscribes:\n{}", sender_log.text());
            std::thread::sleep(Duration::from_millis(5));
        }
        frames_out.update_connections();
        go_rx.recv().unwrap();
        let header = |sequence: u64| FrameHeader {
            protocol_version: PROTOCOL_VERSION,
            pixel_format: PIXEL_FORMAT_RGB8,
            sequence,
            frame: sequence,
            timestamp_s: sequence as f64 / 30.0,
            capture_unix_ns: ipc::unix_now_ns(),
            rig_version: 1,
            view_count: 3,
            view_sizes: FrameHeader::sizes_of([(160, 120); 3]).unwrap(),
            flags: 0,
            missing_views: 0,
            payload_len: rec.frame_set_len() as u64,
        };
        // A header that disagrees with its payload: one byte more than it carries.
        let mut bad = frames_out.publisher.loan_slice(rec.frame_set_len()).unwrap();
        *bad.user_header_mut() = FrameHeader { payload_len: rec.frame_set_len() as u64 + 1, ..header(0) };
        bad.send().unwrap();
        frames_out.notify().unwrap();
        for k in 0..u64::from(frames) {
            let mut s = frames_out.publisher.loan_slice(rec.frame_set_len()).unwrap();
            rec.read_frame_into(k, false, s.payload_mut()).unwrap();
            *s.user_header_mut() = header(k);
            s.send().unwrap();
            frames_out.notify().unwrap();
        }
        let mut end = frames_out.publisher.loan_slice(0).unwrap();
        *end.user_header_mut() = FrameHeader {
            protocol_version: PROTOCOL_VERSION,
            sequence: u64::from(frames),
            flags: END_OF_STREAM,
            ..FrameHeader::default()
        };
        end.send().unwrap();
        frames_out.notify().unwrap();
        // Stay until the flow stage has read everything from this process's memory.
        go_rx.recv().unwrap();
    });

    let node = ipc::create_node("malformed-receiver").unwrap();
    let particles = ipc::particles_input(&node, &names, Mode::Replay).unwrap();
    let started = Instant::now();
    while log.first_after(started - Duration::from_secs(60), &["ready:"]).is_none() {
        assert!(started.elapsed() < Duration::from_secs(30), "flow gets ready:\n{}", log.text());
        std::thread::sleep(Duration::from_millis(5));
    }
    // A subscriber connects (and holds a lossless publisher back) on its first receive.
    assert!(particles.subscriber.receive().unwrap().is_none());
    go_tx.send(()).unwrap();
    let mut estimated = Vec::new();
    let started = Instant::now();
    loop {
        assert!(started.elapsed() < Duration::from_secs(120), "no end of stream:\n{}", log.text());
        let Some(s) = particles.subscriber.receive().unwrap() else {
            std::thread::sleep(Duration::from_millis(5));
            continue;
        };
        let h = *s.user_header();
        h.validate(s.payload().len()).unwrap();
        if h.is_end_of_stream() {
            break;
        }
        assert!(h.point_count > 0, "frame {} has particles", h.sequence);
        estimated.push(h.sequence);
    }
    go_tx.send(()).unwrap();
    sender.join().unwrap();
    let _ = flow.kill();
    let _ = flow.wait();
    assert_eq!(estimated, (0..u64::from(frames)).collect::<Vec<_>>());
    let text = log.text();
    assert!(text.contains("skipping a malformed frame set") && text.contains("payload_len"), "{text}");
}

#[test]
fn a_slow_subscriber_never_stalls_a_live_pipeline() {
    let _one = serial();
    let dir = tempfile::tempdir().unwrap();
    let frames = 150u32;
    let rec_dir = render_preset(dir.path(), "signer-3cam", frames, None);
    let out = dir.path().join("trajectories.jsonl");
    let prefix = unique_prefix("live");
    let names = ServiceNames::new(&prefix);
    let node = ipc::create_node("slow-subscriber").unwrap();
    // Subscribed before the pipeline starts, so it sees the stream from the beginning.
    let slow = ipc::trajectories_input(&node, &names, Mode::Live).unwrap();
    let started = Instant::now();
    let mut run =
        launcher(&["--recording", str(&rec_dir), "--out", str(&out), "--services", &prefix, "--mode", "live"]);
    let log = Log::capture(&mut run);
    let mut received = 0;
    let status = loop {
        if let Some(status) = run.try_wait().unwrap() {
            break status;
        }
        assert!(started.elapsed() < Duration::from_secs(120), "the live run did not end:\n{}", log.text());
        if slow.subscriber.receive().unwrap().is_some() {
            received += 1;
            // Far slower than the stream's 30 samples per second, and than what a debug
            // build on a loaded 2-core machine publishes (about 3 per second seen at worst).
            std::thread::sleep(Duration::from_millis(1000));
        } else {
            std::thread::sleep(Duration::from_millis(10));
        }
    };
    let elapsed = started.elapsed();
    assert!(status.success(), "{}", log.text());
    let published = lines_in(&out);
    eprintln!("live: {published} samples published in {elapsed:?}, the slow subscriber took {received}");
    // 150 frames at 30 frames per second: 5 s of stream; a publisher held back by the slow
    // subscriber would take a second per sample.
    assert!(elapsed < Duration::from_secs(5 + 15), "{elapsed:?}");
    assert!(published >= 10, "the pipeline kept publishing: {published} samples\n{}", log.text());
    // Whatever live mode dropped is counted, and every frame is accounted for.
    let dropped = reported_losses(&log.text()).len();
    assert_eq!(published + dropped, frames as usize, "published + dropped = frames\n{}", log.text());
    assert!(received * 2 < published, "the slow subscriber lost samples instead of slowing the publisher");
}

/// Whether this test process runs as root and can run commands as another user.
fn can_run_as_nobody() -> bool {
    use std::os::unix::fs::MetadataExt;
    let root = std::fs::metadata("/proc/self").map(|m| m.uid() == 0).unwrap_or(false);
    root && Command::new("runuser").arg("--help").stdout(Stdio::null()).stderr(Stdio::null()).status().is_ok()
}

#[test]
fn a_second_pipeline_under_a_running_ones_prefix_is_refused_and_other_users_never_see_it() {
    let _one = serial();
    let prefix = unique_prefix("collide");
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("first.jsonl");
    let mut first =
        launcher(&["--preset", "signer-3cam", "--mode", "live", "--loop", "--services", &prefix, "--out", str(&out)]);
    let first_log = Log::capture(&mut first);
    let started = Instant::now();
    while lines_in(&out) < 3 {
        assert!(started.elapsed() < Duration::from_secs(120), "the first pipeline publishes");
        std::thread::sleep(Duration::from_millis(100));
    }
    let second_out = dir.path().join("second.jsonl");
    let mut second = launcher(&[
        "--preset",
        "signer-3cam",
        "--mode",
        "live",
        "--loop",
        "--services",
        &prefix,
        "--out",
        str(&second_out),
    ]);
    let second_log = Log::capture(&mut second);
    let status = wait_with_timeout(&mut second, Duration::from_secs(30));
    let text = second_log.complete_text(Duration::from_secs(10));
    let first_text = first_log.text();
    assert!(!status.success(), "the second pipeline must not start:\n{text}\nthe first's log:\n{first_text}");
    assert!(
        text.contains("already running under the services prefix") && text.contains(&prefix),
        "{text}\nthe first's log:\n{first_text}"
    );
    assert!(!second_out.exists(), "the refused pipeline writes nothing");
    if can_run_as_nobody() {
        // Another user's subscriber lives in its own iceoryx2 namespace: it starts (iceoryx2's
        // shared directory would refuse it) and does not see this user's pipeline.
        // `tap` waits for a pipeline to appear; `timeout` interrupts it after 5 s.
        let tap = Command::new("runuser")
            .args([
                "-u",
                "nobody",
                "--",
                "timeout",
                "-s",
                "INT",
                "5",
                binaries_dir().join("handflow").to_str().unwrap(),
            ])
            .args(["tap", "trajectories", "--count", "1", "--services", &prefix])
            .current_dir("/")
            .output()
            .unwrap();
        let text = String::from_utf8_lossy(&tap.stderr);
        assert!(!tap.status.success(), "{text}");
        assert!(text.contains("waiting for") && text.contains("interrupted before"), "{text}");
    } else {
        eprintln!("skipping the other-user half: not root, or no runuser");
    }
    let _ = nix::sys::signal::kill(nix::unistd::Pid::from_raw(first.id() as i32), nix::sys::signal::Signal::SIGINT);
    wait_with_timeout(&mut first, Duration::from_secs(30));
}

#[test]
fn killing_the_publisher_keeps_its_file_and_its_count_of_losses() {
    let _one = serial();
    let dir = tempfile::tempdir().unwrap();
    let frames = 120u32;
    let rec_dir = render_preset(dir.path(), "signer-3cam", frames, None);
    let out = dir.path().join("trajectories.jsonl");
    let (mut run, log, _) = replay_and_kill("handflow-publish", &rec_dir, &out);
    let status = wait_with_timeout(&mut run, Duration::from_secs(300));
    let text = log.complete_text(Duration::from_secs(5));
    assert!(status.success(), "the run failed after the kill:\n{text}");
    assert!(text.contains("going on from sequence"), "the publisher resumes its count:\n{text}");
    let records = read_tracks(&out).unwrap();
    let present: BTreeSet<u64> = records.iter().map(|r| r.frame).collect();
    assert_eq!(present.len(), records.len(), "no frame twice");
    // The 40 records written before the kill: frames 0 to 39.
    assert!(present.contains(&0) && present.contains(&39), "the records before the kill stay in the file");
    let missing: BTreeSet<u64> = (0..u64::from(frames)).filter(|f| !present.contains(f)).collect();
    assert_eq!(reported_losses(&text), missing, "every frame is in the file or reported lost, once");
    assert!(missing.len() <= 3, "at most the frames in flight are lost: {missing:?}");
    let last = records.last().unwrap();
    assert_eq!(last.frame, u64::from(frames) - 1);
    assert_eq!(last.dropped_frames, missing.len() as u64, "the running count spans the restart");
    eprintln!("publisher killed and restarted; frames lost: {missing:?}");
}

#[test]
fn a_stage_that_fails_at_start_on_bad_input_ends_the_run_instead_of_restarting_forever() {
    let _one = serial();
    let dir = tempfile::tempdir().unwrap();
    let rec_dir = render_preset(dir.path(), "signer-3cam", 4, Some((160, 120)));
    std::fs::write(rec_dir.join("rig.toml"), "[[cameras]]\nname = 3\n").unwrap();
    let prefix = unique_prefix("fails-at-start");
    let mut run =
        launcher(&["--recording", str(&rec_dir), "--services", &prefix, "--out", str(&dir.path().join("t.jsonl"))]);
    let log = Log::capture(&mut run);
    let status = wait_with_timeout(&mut run, Duration::from_secs(60));
    let text = log.complete_text(Duration::from_secs(5));
    assert!(!status.success(), "{text}");
    assert!(text.contains("rig.toml") && text.contains("not restarting it"), "{text}");
    assert_eq!(text.matches("started ingest").count(), 1, "{text}");
}

#[test]
fn stages_end_when_their_launcher_is_killed() {
    let _one = serial();
    let prefix = unique_prefix("orphans");
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("t.jsonl");
    let mut run =
        launcher(&["--preset", "signer-3cam", "--mode", "live", "--loop", "--services", &prefix, "--out", str(&out)]);
    let _log = Log::capture(&mut run);
    let started = Instant::now();
    while lines_in(&out) < 3 {
        assert!(started.elapsed() < Duration::from_secs(120), "the pipeline publishes");
        std::thread::sleep(Duration::from_millis(100));
    }
    run.kill().unwrap();
    run.wait().unwrap();
    let killed = Instant::now();
    let stages = || -> Vec<i32> {
        ["handflow-ingest", "handflow-flow", "handflow-cluster", "handflow-publish"]
            .iter()
            .flat_map(|b| pids_of(b, &prefix))
            .collect()
    };
    while !stages().is_empty() {
        assert!(killed.elapsed() < Duration::from_secs(10), "stages outlived their launcher: {:?}", stages());
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// Stops process `pid` (SIGSTOP) for `stopped`, continues it and gives it a moment.
fn stop_and_continue(pid: i32, stopped: Duration) {
    let pid = nix::unistd::Pid::from_raw(pid);
    nix::sys::signal::kill(pid, nix::sys::signal::Signal::SIGSTOP).unwrap();
    std::thread::sleep(stopped);
    nix::sys::signal::kill(pid, nix::sys::signal::Signal::SIGCONT).unwrap();
    std::thread::sleep(Duration::from_millis(300));
}

/// Waits (30 s at most) until `out` holds more lines than now.
fn wait_for_more_lines(out: &Path, log: &Log) {
    let before = lines_in(out);
    let resumed = Instant::now();
    while lines_in(out) <= before {
        assert!(resumed.elapsed() < Duration::from_secs(30), "trajectories go on:\n{}", log.text());
        std::thread::sleep(Duration::from_millis(50));
    }
}

#[test]
fn a_stage_stopped_and_continued_goes_on_without_a_restart() {
    let _one = serial();
    let prefix = unique_prefix("sigstop");
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("t.jsonl");
    let mut run =
        launcher(&["--preset", "signer-3cam", "--mode", "live", "--loop", "--services", &prefix, "--out", str(&out)]);
    let log = Log::capture(&mut run);
    let started = Instant::now();
    while lines_in(&out) < 3 {
        assert!(started.elapsed() < Duration::from_secs(120), "the pipeline publishes");
        std::thread::sleep(Duration::from_millis(100));
    }
    for stage in ["handflow-publish", "handflow-cluster", "handflow-flow"] {
        stop_and_continue(pids_of(stage, &prefix)[0], Duration::from_millis(700));
    }
    wait_for_more_lines(&out, &log);
    let _ = nix::sys::signal::kill(nix::unistd::Pid::from_raw(run.id() as i32), nix::sys::signal::Signal::SIGINT);
    wait_with_timeout(&mut run, Duration::from_secs(30));
    let text = log.complete_text(Duration::from_secs(5));
    assert!(!text.contains("restarting it"), "a stopped stage is not a dead one:\n{text}");
}

#[test]
fn a_paced_ingest_and_the_launcher_stopped_and_continued_go_on_without_a_restart() {
    let _one = serial();
    let prefix = unique_prefix("sigstop-ingest");
    let dir = tempfile::tempdir().unwrap();
    let rec_dir = render_preset(dir.path(), "signer-3cam", 30, Some((160, 120)));
    let out = dir.path().join("t.jsonl");
    let mut run = launcher(&[
        "--recording",
        str(&rec_dir),
        "--mode",
        "live",
        "--pace",
        "recorded",
        "--loop",
        "--services",
        &prefix,
        "--out",
        str(&out),
    ]);
    let log = Log::capture(&mut run);
    let started = Instant::now();
    while lines_in(&out) < 3 {
        assert!(started.elapsed() < Duration::from_secs(120), "the pipeline publishes:\n{}", log.text());
        std::thread::sleep(Duration::from_millis(100));
    }
    // A paced ingest sleeps between frame sets most of the time, as the launcher does between
    // its checks: a SIGCONT then cuts a sleep short, which both once took for Ctrl-C.
    for target in ["ingest", "ingest", "ingest", "launcher", "launcher"] {
        let pid = match target {
            "ingest" => pids_of("handflow-ingest", &prefix)[0],
            _ => run.id() as i32,
        };
        stop_and_continue(pid, Duration::from_millis(600));
    }
    wait_for_more_lines(&out, &log);
    assert!(run.try_wait().unwrap().is_none(), "the launcher is still running:\n{}", log.text());
    let _ = nix::sys::signal::kill(nix::unistd::Pid::from_raw(run.id() as i32), nix::sys::signal::Signal::SIGINT);
    wait_with_timeout(&mut run, Duration::from_secs(30));
    let text = log.complete_text(Duration::from_secs(5));
    assert!(!text.contains("restarting it"), "a stopped stage is not a dead one:\n{text}");
    assert_eq!(text.matches("interrupted: stopping").count(), 1, "only the final Ctrl-C stops the launcher:\n{text}");
}
