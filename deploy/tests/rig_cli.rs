//! End-to-end tests of `handflow rig show` and `handflow rig convert` on the calibration
//! fixtures (the same three-camera rig in every supported format).

#![allow(clippy::unwrap_used)]

mod common;

use std::path::{Path, PathBuf};
use std::process::Output;

use common::handflow;
use handflow_protocol::Rig;
use nalgebra::Point3;

/// The format fixtures, relative to this crate.
const FORMATS: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../tests/fixtures/rig_formats");

fn fixture(name: &str) -> PathBuf {
    Path::new(FORMATS).join(name)
}

fn stdout(output: &Output) -> String {
    assert!(output.status.success(), "failed: {}", String::from_utf8_lossy(&output.stderr));
    String::from_utf8_lossy(&output.stdout).into_owned()
}

#[test]
fn rig_show_describes_a_caliscope_file() {
    let file = fixture("camera_array.toml");
    let text = stdout(&handflow(&["rig", "show", file.to_str().unwrap()]));
    for needle in [
        "format: caliscope camera_array.toml",
        "cameras: 3",
        "  cam_0:",
        "size: 1920x1080",
        "focal length: fx 1400.00 px, fy 1398.50 px",
        "viewing direction: [",
        "mount quarter turns: 1",
        "baselines (m):",
        "world up: [0.0000, -1.0000, 0.0000] (estimated: ",
        "snapped to it",
        "`cam_3`",
        "ignore = true",
    ] {
        assert!(text.contains(needle), "lacks {needle:?}:\n{text}");
    }
}

#[test]
fn rig_show_names_each_cameras_lens_model_and_an_older_caliscope_config() {
    let file = fixture("caliscope_config.toml");
    let text = stdout(&handflow(&["rig", "show", file.to_str().unwrap()]));
    for needle in [
        "format: caliscope config.toml (older versions)",
        "cameras: 3",
        "lens: pinhole, k1 k2 p1 p2 k3 = -0.11 0.031 0.0004 -0.0002 -0.005",
        "`cam_4`",
        "not calibrated yet",
    ] {
        assert!(text.contains(needle), "lacks {needle:?}:\n{text}");
    }
    let tmp = tempfile::tempdir().unwrap();
    let wide = tmp.path().join("wide.toml");
    let anipose = std::fs::read_to_string(fixture("anipose.toml")).unwrap();
    let fisheye = anipose
        .replace("distortions = [0.02, -0.01, 0.0, 0.0]", "distortions = [0.03, -0.01, 0.002, 0.0]\nfisheye = true");
    std::fs::write(&wide, fisheye).unwrap();
    let text = stdout(&handflow(&["rig", "show", wide.to_str().unwrap()]));
    assert!(text.contains("lens: fisheye, k1 k2 k3 k4 = 0.03 -0.01 0.002 0"), "{text}");
}

#[test]
fn rig_show_reports_a_bad_file_with_its_error() {
    let bad = Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/fixtures/bad/opencv_missing_rotation.yml");
    let output = handflow(&["rig", "show", bad.to_str().unwrap()]);
    assert!(!output.status.success());
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(stderr.contains("opencv_missing_rotation.yml") && stderr.contains("field `R`"), "{stderr}");
}

#[test]
fn rig_convert_writes_our_toml_of_the_same_rig() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("rig.toml");
    let text = stdout(&handflow(&[
        "rig",
        "convert",
        fixture("opencv_rig.xml").to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]));
    assert!(text.contains("wrote 3 cameras"), "{text}");
    let converted = Rig::from_toml_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
    let reference = Rig::load(fixture("anipose.toml")).unwrap();
    assert_eq!(converted.cameras.len(), reference.cameras.len());
    for (a, b) in reference.cameras.iter().zip(&converted.cameras) {
        assert_eq!((&a.name, a.mount_quarter_turns), (&b.name, b.mount_quarter_turns));
        for p in [Point3::new(0.0, 0.0, 0.0), Point3::new(0.3, -0.2, 0.1), Point3::new(-0.4, 0.3, -0.2)] {
            let (x, y) = (a.project(&p).unwrap(), b.project(&p).unwrap());
            assert!((x - y).norm() < 1e-6, "{}: {x} vs {y}", a.name);
        }
    }
}

/// `signer-3cam` rendered for `frames` frames into `dir/name` with every camera held sideways
/// the same way, its rig file without mounts (as most formats are): the cameras' own estimate
/// of the up lies on its side.
fn sideways_recording_without_mounts(dir: &Path, name: &str, frames: u32) -> PathBuf {
    use handflow_ingest::synthetic::{write_recording, Renderer, SceneSpec};
    let mut spec = SceneSpec::preset("signer-3cam").unwrap();
    spec.frames = frames;
    spec.cameras.mount_quarter_turns = vec![1, 1, 1];
    let rec = dir.join(name);
    write_recording(&Renderer::new(&spec).unwrap(), &rec, frames).unwrap();
    let rig_path = rec.join("rig.toml");
    let rig = std::fs::read_to_string(&rig_path).unwrap();
    let unmounted: Vec<&str> = rig.lines().filter(|l| !l.starts_with("mount_quarter_turns")).collect();
    std::fs::write(&rig_path, unmounted.join("\n")).unwrap();
    rec
}

#[test]
fn rig_show_on_a_recording_mostly_mounted_sideways_gives_the_up_its_faces_show() {
    let dir = tempfile::tempdir().unwrap();
    let rec = sideways_recording_without_mounts(dir.path(), "sideways", 1);
    let rig_path = rec.join("rig.toml");
    let estimate = stdout(&handflow(&["rig", "show", rig_path.to_str().unwrap()]));
    assert!(!estimate.contains("world up: [0.0000, 1.0000, 0.0000]"), "the file alone:\n{estimate}");

    let text = stdout(&handflow(&["rig", "show", rec.to_str().unwrap()]));
    assert!(text.contains("world up: [0.0000, 1.0000, 0.0000] (configured)"), "{text}");
    assert!(text.contains("from the faces the views see"), "{text}");
    assert_eq!(text.matches("mount quarter turns: 1").count(), 3, "{text}");
}

#[test]
fn the_faces_up_comes_from_a_later_frame_set_when_the_first_shows_no_face() {
    let dir = tempfile::tempdir().unwrap();
    // Its first frame set shows no one (a lens cap, a person not yet in the views): every
    // view of frame 0 a flat grey.
    let rec = sideways_recording_without_mounts(dir.path(), "late", 3);
    for cam in ["cam0", "cam1", "cam2"] {
        let first = rec.join(cam).join("000000.png");
        let (w, h) = image::image_dimensions(&first).unwrap();
        image::RgbImage::from_pixel(w, h, image::Rgb([96, 96, 96])).save(&first).unwrap();
    }
    let text = stdout(&handflow(&["rig", "show", rec.to_str().unwrap()]));
    assert!(text.contains("world up: [0.0000, 1.0000, 0.0000] (configured)"), "{text}");
    assert!(text.contains("from the faces the views see in frame 2"), "{text}");
}
