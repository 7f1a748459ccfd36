//! End-to-end tests of the footage commands on a lossless video recording: `import` gives
//! back the frames the videos were encoded from, and `track` on the videos writes the same
//! file as `track` on the images.
//!
//! The videos are encoded here with the `ffmpeg` tool (a test tool; handflow decodes with
//! GStreamer). Without it the test says so and passes, unless `HANDFLOW_REQUIRE_FFMPEG=1`
//! (as in CI).

#![allow(clippy::unwrap_used)]

mod common;

use std::path::Path;
use std::process::Command;

use common::{describe, handflow};

fn have_ffmpeg() -> bool {
    let found = Command::new("ffmpeg").arg("-version").output().is_ok_and(|o| o.status.success());
    if !found {
        assert!(
            std::env::var("HANDFLOW_REQUIRE_FFMPEG").as_deref() != Ok("1"),
            "ffmpeg is required (HANDFLOW_REQUIRE_FFMPEG=1) but not installed"
        );
        eprintln!("skipping: the `ffmpeg` tool that encodes the fixtures is not installed");
    }
    found
}

fn arg(path: &Path) -> &str {
    path.to_str().unwrap()
}

/// Renders 12 frames of `signer-3cam` into `dir/images` and returns that folder.
fn rendered_images(dir: &Path) -> std::path::PathBuf {
    let images = dir.join("images");
    let output = handflow(&["render", "--preset", "signer-3cam", "--frames", "12", "--out", arg(&images)]);
    assert!(output.status.success(), "{}", describe(&output));
    images
}

/// Encodes the PNGs `frames/000000.png`.. at 30 frames/s into the lossless video `out`.
fn encode_lossless(frames: &Path, out: &Path) {
    let status = Command::new("ffmpeg")
        .args(["-loglevel", "error", "-y", "-framerate", "30", "-i"])
        .arg(frames.join("%06d.png"))
        .args(["-c:v", "ffv1", "-pix_fmt", "bgr0"])
        .arg(out)
        .status()
        .unwrap();
    assert!(status.success(), "encoding {}", out.display());
}

#[test]
fn a_lossless_video_recording_imports_to_its_frames_and_tracks_as_its_images() {
    if !have_ffmpeg() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let images = rendered_images(dir.path());
    // The same recording as one lossless video per camera, with its rig and frame table.
    let videos = dir.path().join("videos");
    std::fs::create_dir_all(&videos).unwrap();
    for file in ["rig.toml", "frames.csv"] {
        std::fs::copy(images.join(file), videos.join(file)).unwrap();
    }
    let rig = handflow_protocol::Rig::load(images.join("rig.toml")).unwrap();
    for camera in &rig.cameras {
        encode_lossless(&images.join(&camera.name), &videos.join(format!("{}.mkv", camera.name)));
    }

    let imported = dir.path().join("imported");
    let output = handflow(&["import", "--recording", arg(&videos), "--out", arg(&imported)]);
    assert!(output.status.success(), "{}", describe(&output));
    for camera in &rig.cameras {
        for frame in 0..12 {
            let name = format!("{frame:06}.png");
            let a = image::open(images.join(&camera.name).join(&name)).unwrap().into_rgb8();
            let b = image::open(imported.join(&camera.name).join(&name)).unwrap().into_rgb8();
            assert!(a == b, "camera {}, frame {frame}: the imported frame differs", camera.name);
        }
    }
    let again = handflow(&["import", "--recording", arg(&videos), "--out", arg(&imported)]);
    assert!(!again.status.success() && describe(&again).contains("not empty"), "{}", describe(&again));

    let from_images = dir.path().join("images.jsonl");
    let from_videos = dir.path().join("videos.jsonl");
    for (recording, out) in [(&images, &from_images), (&videos, &from_videos)] {
        let output = handflow(&["track", "--recording", arg(recording), "--out", arg(out)]);
        assert!(output.status.success(), "{}", describe(&output));
    }
    let (a, b) = (std::fs::read_to_string(&from_images).unwrap(), std::fs::read_to_string(&from_videos).unwrap());
    assert_eq!(a.lines().count(), 12, "every frame");
    assert!(a == b, "track on the videos and on their images write the same file");
}

#[test]
fn frames_a_webcam_dropped_leave_their_sets_to_the_other_cameras() {
    if !have_ffmpeg() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let images = rendered_images(dir.path());
    // As caliscope records a session whose webcams each dropped a frame: camera k's video
    // lacks frame set 6 + 2k, and `timestamps.csv` has no row for it.
    let session = dir.path().join("session");
    std::fs::create_dir_all(&session).unwrap();
    for file in ["rig.toml", "truth.json"] {
        std::fs::copy(images.join(file), session.join(file)).unwrap();
    }
    let rig = handflow_protocol::Rig::load(images.join("rig.toml")).unwrap();
    let dropped = |k: usize| 6 + 2 * k as u64;
    // The capture times of the images' frame table, to the digit (the rate follows them).
    let table = std::fs::read_to_string(images.join("frames.csv")).unwrap();
    let times: Vec<&str> = table.lines().skip(1).map(|line| line.split(',').nth(1).unwrap()).collect();
    let mut timestamps = String::from("sync_index,cam_id,frame_index,frame_time\n");
    for (k, camera) in rig.cameras.iter().enumerate() {
        let kept = dir.path().join(format!("kept-{k}"));
        std::fs::create_dir_all(&kept).unwrap();
        for (position, frame) in (0..12u64).filter(|&f| f != dropped(k)).enumerate() {
            let name = format!("{frame:06}.png");
            std::fs::copy(images.join(&camera.name).join(name), kept.join(format!("{position:06}.png"))).unwrap();
            timestamps.push_str(&format!("{frame},{k},{position},{}\n", times[frame as usize]));
        }
        encode_lossless(&kept, &session.join(format!("{}.mkv", camera.name)));
    }
    std::fs::write(session.join("timestamps.csv"), timestamps).unwrap();

    let (from_images, from_session) = (dir.path().join("images.jsonl"), dir.path().join("session.jsonl"));
    let output = handflow(&["track", "--recording", arg(&images), "--out", arg(&from_images)]);
    assert!(output.status.success(), "{}", describe(&output));
    let output = handflow(&["track", "--recording", arg(&session), "--out", arg(&from_session)]);
    assert!(output.status.success(), "{}", describe(&output));
    let log = describe(&output);
    assert!(log.contains("read with the other cameras"), "the partial sets are noted: {log}");
    let (all, partial) =
        (std::fs::read_to_string(&from_images).unwrap(), std::fs::read_to_string(&from_session).unwrap());
    let frames: Vec<u64> = partial
        .lines()
        .map(|line| serde_json::from_str::<serde_json::Value>(line).unwrap()["frame"].as_u64().unwrap())
        .collect();
    // Every set has its record. The one without the reference camera's frame, which the
    // engine cannot estimate, is the tracks' predictions, with a word naming the camera; the
    // two without another camera's frame are estimated from the other two.
    assert_eq!(frames, (0..12).collect::<Vec<u64>>());
    let states = |line: &str| -> Vec<String> {
        let v: serde_json::Value = serde_json::from_str(line).unwrap();
        ["head", "left_hand", "right_hand"].map(|o| v["objects"][o]["state"].as_str().unwrap().to_owned()).to_vec()
    };
    let coasted: Vec<usize> = (0..3)
        .filter(|&k| states(partial.lines().nth(dropped(k) as usize).unwrap()).iter().all(|s| s == "predicted"))
        .collect();
    assert_eq!(coasted.len(), 1, "one set lacks the reference camera's frame");
    let reference = &rig.cameras[coasted[0]].name;
    assert!(log.contains(&format!("the reference camera `{reference}` has no frame in it")), "{log}");
    // The sets estimated without one camera put every object where the whole sets do.
    let positions = |text: &str| -> std::collections::BTreeMap<u64, Vec<[f64; 3]>> {
        text.lines()
            .map(|line| {
                let v: serde_json::Value = serde_json::from_str(line).unwrap();
                let at = |name: &str| -> [f64; 3] {
                    std::array::from_fn(|i| v["objects"][name]["pos"][i].as_f64().unwrap())
                };
                (v["frame"].as_u64().unwrap(), ["head", "left_hand", "right_hand"].map(at).to_vec())
            })
            .collect()
    };
    let (whole, without) = (positions(&all), positions(&partial));
    // Each record says which view its set went without, as the streaming service's do.
    for line in partial.lines() {
        let v: serde_json::Value = serde_json::from_str(line).unwrap();
        let frame = v["frame"].as_u64().unwrap();
        let want = (0..3).find(|&k| dropped(k) == frame).map_or(0, |k| 1u64 << k);
        assert_eq!(v["missing_views"].as_u64().unwrap_or(0), want, "frame {frame}");
    }
    // The predictions too, the hands moving less than a few centimetres in a frame interval.
    for k in 0..3 {
        let frame = dropped(k);
        for (object, (a, b)) in whole[&frame].iter().zip(&without[&frame]).enumerate() {
            let d = (0..3).map(|i| (a[i] - b[i]).powi(2)).sum::<f64>().sqrt();
            assert!(d < 0.03, "frame {frame} without camera {k}: object {object} {d} m from the whole set's");
        }
    }
    let output = handflow(&["eval", "tracks", "--recording", arg(&session), "--tracks", arg(&from_session), "--json"]);
    assert!(output.status.success(), "{}", describe(&output));
    let v: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    for name in ["head", "left_hand", "right_hand"] {
        assert!(v[name]["rmse_3d_m"].as_f64().unwrap() < 0.05, "{name} tracked through the partial sets: {v}");
    }
}
