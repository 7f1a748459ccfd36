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

#[test]
fn a_lossless_video_recording_imports_to_its_frames_and_tracks_as_its_images() {
    if !have_ffmpeg() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let images = dir.path().join("images");
    let output = handflow(&["render", "--preset", "signer-3cam", "--frames", "12", "--out", arg(&images)]);
    assert!(output.status.success(), "{}", describe(&output));
    // The same recording as one lossless video per camera, with its rig and frame table.
    let videos = dir.path().join("videos");
    std::fs::create_dir_all(&videos).unwrap();
    for file in ["rig.toml", "frames.csv"] {
        std::fs::copy(images.join(file), videos.join(file)).unwrap();
    }
    let rig = handflow_protocol::Rig::load(images.join("rig.toml")).unwrap();
    for camera in &rig.cameras {
        let status = Command::new("ffmpeg")
            .args(["-loglevel", "error", "-y", "-framerate", "30", "-i"])
            .arg(images.join(&camera.name).join("%06d.png"))
            .args(["-c:v", "ffv1", "-pix_fmt", "bgr0"])
            .arg(videos.join(format!("{}.mkv", camera.name)))
            .status()
            .unwrap();
        assert!(status.success(), "encoding camera {}", camera.name);
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
