//! The rig TOML format: real samples, round trips and every bad-rig error.

mod common;

use std::f64::consts::PI;

use handflow_protocol::{Camera, Distortion, Fisheye, Rig, RigError};
use nalgebra::{Matrix3, Rotation3, Vector3};
use proptest::prelude::*;

/// Written by anipose (python `toml`: spaces and trailing commas, integer
/// sizes, five coefficients, a metadata table at the end).
const ANIPOSE_SAMPLE: &str = r#"[cam_0]
name = "A"
size = [ 1280, 1024,]
matrix = [ [ 1530.6385432283768, 0.0, 639.5,], [ 0.0, 1530.6385432283768, 511.5,], [ 0.0, 0.0, 1.0,],]
distortions = [ -0.1782366524716508, 0.0, 0.0, 0.0, 0.0,]
rotation = [ 1.6541063009986327, 0.5823427047213017, -0.6029838318101624,]
translation = [ 32.70566720349706, -1.3766541669017883, 286.8233413016328,]

[cam_1]
name = "B"
size = [ 1280, 1024,]
matrix = [ [ 1493.0781418466408, 0.0, 639.5,], [ 0.0, 1493.0781418466408, 511.5,], [ 0.0, 0.0, 1.0,],]
distortions = [ -0.1539516478733064, 0.0, 0.0, 0.0, 0.0,]
rotation = [ 1.2549349932536434, -1.0785738880212546, 1.2094412424106394,]
translation = [ -39.15005128584437, 35.31493155587454, 314.14693411519886,]

[cam_2]
name = "C"
size = [ 1280, 1024,]
matrix = [ [ 1546, 0, 639.5,], [ 0, 1546, 511.5,], [ 0, 0, 1,],]
distortions = [ -0.19, 0.0, 0.0, 0.0, 0.0,]
rotation = [ 0.10, 2.1, -2.2,]
translation = [ 12, 5, 301,]

[metadata]
adjusted = true
error = 0.5757376066186434
"#;

/// Written by Pose2Sim: `cam_01` keys, float sizes, four coefficients,
/// `fisheye = false`.
const POSE2SIM_SAMPLE: &str = r#"[cam_01]
name = "cam_01"
size = [ 1920.0, 1080.0,]
matrix = [ [ 1206.8837, 0.0, 959.5,], [ 0.0, 1207.6023, 539.5,], [ 0.0, 0.0, 1.0,],]
distortions = [ -0.0468, 0.0507, 0.0013, -0.0008,]
rotation = [ 1.6757, 0.8672, -0.5215,]
translation = [ 0.1225, 0.6536, 3.2910,]
fisheye = false

[cam_02]
name = "cam_02"
size = [ 1920.0, 1080.0,]
matrix = [ [ 1195.1, 0.0, 959.5,], [ 0.0, 1195.1, 539.5,], [ 0.0, 0.0, 1.0,],]
distortions = [ -0.0401, 0.0311, 0.0, 0.0,]
rotation = [ 1.3411, -1.2902, 1.0144,]
translation = [ -0.7201, 0.5066, 3.4101,]
fisheye = false

[metadata]
adjusted = false
error = 0.0
"#;

#[test]
fn parses_anipose_sample() {
    let rig = Rig::from_toml_str(ANIPOSE_SAMPLE).expect("valid anipose file");
    let names: Vec<&str> = rig.cameras.iter().map(|c| c.name.as_str()).collect();
    assert_eq!(names, ["A", "B", "C"]);
    let a = rig.camera("A").expect("camera A");
    assert_eq!((a.width, a.height), (1280, 1024));
    assert_eq!(a.matrix, Matrix3::new(1530.6385432283768, 0.0, 639.5, 0.0, 1530.6385432283768, 511.5, 0.0, 0.0, 1.0));
    assert_eq!(a.distortion, Distortion { k1: -0.1782366524716508, ..Distortion::default() });
    assert_eq!(a.rotation, Rotation3::new(Vector3::new(1.6541063009986327, 0.5823427047213017, -0.6029838318101624)));
    assert_eq!(a.translation, Vector3::new(32.70566720349706, -1.3766541669017883, 286.8233413016328));
    // Integers where floats are expected.
    let c = rig.camera("C").expect("camera C");
    assert_eq!(c.matrix[(0, 0)], 1546.0);
    assert_eq!(c.translation, Vector3::new(12.0, 5.0, 301.0));
    assert!(rig.camera("metadata").is_none());
    assert!(rig.camera("D").is_none());
}

#[test]
fn parses_pose2sim_sample() {
    let rig = Rig::from_toml_str(POSE2SIM_SAMPLE).expect("valid Pose2Sim file");
    assert_eq!(rig.cameras.len(), 2);
    let cam = &rig.cameras[0];
    assert_eq!((cam.name.as_str(), cam.width, cam.height), ("cam_01", 1920, 1080));
    // Four coefficients: k3 = 0.
    assert_eq!(cam.distortion, Distortion { k1: -0.0468, k2: 0.0507, p1: 0.0013, p2: -0.0008, k3: 0.0 });
    assert_eq!(cam.matrix[(1, 1)], 1207.6023);
}

#[test]
fn camera_order_is_file_order_not_key_order() {
    let mut text = String::new();
    for (key, name) in [("cam_10", "ten"), ("cam_2", "two"), ("z", "zed"), ("a", "ay")] {
        text.push_str(&format!(
            "[{key}]\nname = \"{name}\"\nsize = [640, 480]\nmatrix = [[500, 0, 320], [0, 500, 240], [0, 0, 1]]\n\
             distortions = [0, 0, 0, 0]\nrotation = [0, 0, 0]\ntranslation = [0, 0, 0]\n\n"
        ));
    }
    let rig = Rig::from_toml_str(&text).expect("valid");
    let names: Vec<&str> = rig.cameras.iter().map(|c| c.name.as_str()).collect();
    assert_eq!(names, ["ten", "two", "zed", "ay"]);
}

#[test]
fn accepts_a_rotation_matrix_and_cleans_it() {
    // A quarter turn about z, as written with 10 digits by some tool.
    let text = ANIPOSE_SAMPLE.replacen(
        "rotation = [ 1.6541063009986327, 0.5823427047213017, -0.6029838318101624,]",
        "rotation = [[0.0000000001, -1.0, 0.0], [1.0, 0.0000000003, 0.0], [0.0, 0.0, 1.0]]",
        1,
    );
    let rig = Rig::from_toml_str(&text).expect("valid");
    let rotation = rig.cameras[0].rotation;
    let expected = Rotation3::new(Vector3::new(0.0, 0.0, PI / 2.0));
    assert!((rotation.matrix() - expected.matrix()).amax() < 1e-9);
    // Orthonormal to rounding, so that saving it as a Rodrigues vector is exact.
    assert!((rotation.matrix().transpose() * rotation.matrix() - Matrix3::identity()).amax() < 1e-15);
}

/// `load(save(rig)) == rig` to 1e-12.
fn assert_same_rig(a: &Rig, b: &Rig) {
    assert_eq!(a.cameras.len(), b.cameras.len());
    for (x, y) in a.cameras.iter().zip(&b.cameras) {
        assert_eq!((&x.name, x.width, x.height), (&y.name, y.width, y.height));
        assert!((x.matrix - y.matrix).amax() <= 1e-12 * x.matrix.amax(), "{} matrix", x.name);
        for (p, q) in x.distortion.as_array().iter().zip(y.distortion.as_array()) {
            assert!((p - q).abs() <= 1e-12, "{} distortion", x.name);
        }
        assert_eq!(x.fisheye, y.fisheye, "{} fisheye lens", x.name);
        let rotation_error = (x.rotation.matrix() - y.rotation.matrix()).amax();
        assert!(rotation_error <= 1e-12, "{} rotation off by {rotation_error}", x.name);
        assert!(
            (x.translation - y.translation).amax() <= 1e-12 * (1.0 + x.translation.amax()),
            "{} translation",
            x.name
        );
    }
}

fn sample_rig() -> Rig {
    let k = Matrix3::new(1400.25, 0.5, 960.125, 0.0, 1399.75, 540.0625, 0.0, 0.0, 1.0);
    let d = Distortion { k1: -0.123456789, k2: 0.0123, p1: 1e-4, p2: -2e-4, k3: 3.3e-3 };
    let cameras = [
        ("left", Vector3::new(0.3, -1.2, 0.7)),
        ("right \"quoted\" \\", Vector3::new(PI, 0.0, 0.0)), // a half turn
        ("top", Vector3::new(1.0, 1.0, 1.0).normalize() * (PI - 1e-10)),
        ("fixed", Vector3::zeros()),
        ("nudged", Vector3::new(1e-10, -2e-10, 0.0)),
    ]
    .into_iter()
    .enumerate()
    .map(|(i, (name, rodrigues))| {
        let t = Vector3::new(0.1 * i as f64, -1.0 / 3.0, 2.0 + i as f64);
        Camera::new(name, 1920, 1080, k, d, Rotation3::new(rodrigues), t).expect("valid")
    })
    .collect();
    Rig::new(cameras)
}

#[test]
fn save_then_load_round_trips() {
    let rig = sample_rig();
    let dir = tempfile::tempdir().expect("temp dir");
    let path = dir.path().join("calibration.toml");
    rig.save(&path).expect("save");
    let loaded = Rig::load(&path).expect("load");
    assert_same_rig(&rig, &loaded);
    // Everything but the rotations (re-derived from Rodrigues vectors) is exact.
    for (a, b) in rig.cameras.iter().zip(&loaded.cameras) {
        assert_eq!((a.matrix, a.distortion, a.translation), (b.matrix, b.distortion, b.translation));
    }
}

#[test]
fn a_fisheye_camera_is_written_and_read_as_anipose_writes_it() {
    let mut rig = sample_rig();
    let lens = Fisheye { k1: 0.031, k2: -0.0123, k3: 0.0021, k4: -0.0003 };
    let fisheye = Camera { distortion: Distortion::default(), ..rig.cameras[2].clone() };
    rig.cameras[2] = fisheye.with_fisheye(lens).expect("valid");
    let text = rig.to_toml_string();
    let table: toml::Table = toml::from_str(&text).expect("valid TOML");
    let cam = table["cam_2"].as_table().expect("a table per camera");
    assert_eq!(cam["fisheye"].as_bool(), Some(true));
    assert_eq!(cam["distortions"].as_array().map(Vec::len), Some(4));
    let loaded = Rig::from_toml_str(&text).expect("read back");
    assert_same_rig(&rig, &loaded);
    assert_eq!(loaded.cameras[2].fisheye, Some(lens));
    assert_eq!(loaded.cameras[1].fisheye, None);
}

#[test]
fn saved_layout_is_the_anipose_one() {
    let text = sample_rig().to_toml_string();
    let table: toml::Table = toml::from_str(&text).expect("valid TOML");
    assert_eq!(table.len(), 5);
    let cam = table["cam_1"].as_table().expect("a table per camera");
    assert_eq!(cam["name"].as_str(), Some("right \"quoted\" \\"));
    assert_eq!(cam["size"].as_array().map(Vec::len), Some(2));
    assert_eq!(cam["matrix"].as_array().map(Vec::len), Some(3));
    assert_eq!(cam["distortions"].as_array().map(Vec::len), Some(5));
    assert_eq!(cam["rotation"].as_array().map(Vec::len), Some(3)); // a Rodrigues vector
    assert_eq!(cam["translation"].as_array().map(Vec::len), Some(3));
    assert_eq!(cam["fisheye"].as_bool(), Some(false));
    // The half turn is written as such, not as nothing (nalgebra's
    // `Rotation3::scaled_axis` would give zero here).
    let rotation: Vec<f64> = cam["rotation"].as_array().into_iter().flatten().filter_map(|v| v.as_float()).collect();
    assert!((Vector3::from_vec(rotation).norm() - PI).abs() < 1e-12);
}

#[test]
fn reads_back_the_anipose_sample_after_saving_it() {
    let rig = Rig::from_toml_str(ANIPOSE_SAMPLE).expect("valid");
    assert_same_rig(&rig, &Rig::from_toml_str(&rig.to_toml_string()).expect("valid"));
}

#[test]
fn io_errors_name_the_file() {
    let dir = tempfile::tempdir().expect("temp dir");
    let missing = dir.path().join("nope.toml");
    let error = Rig::load(&missing).expect_err("no such file");
    assert!(matches!(error, RigError::Io { .. }));
    let message = error.to_string();
    assert!(message.contains("cannot read") && message.contains("nope.toml"), "{message}");

    let unwritable = dir.path().join("no_such_dir").join("rig.toml");
    let message = sample_rig().save(&unwritable).expect_err("no such directory").to_string();
    assert!(message.contains("cannot write") && message.contains("rig.toml"), "{message}");
}

#[test]
fn empty_text_has_no_cameras() {
    assert!(matches!(Rig::from_toml_str(""), Err(RigError::NoCameras)));
}

#[test]
fn field_error_display_matches_the_documented_form() {
    let text = ANIPOSE_SAMPLE.replacen(
        "matrix = [ [ 1493.0781418466408, 0.0, 639.5,], [ 0.0, 1493.0781418466408, 511.5,], [ 0.0, 0.0, 1.0,],]",
        "matrix = [[1493.0, 0.0, 639.5], [0.0, 1493.0, 511.5]]",
        1,
    );
    let error = Rig::from_toml_str(&text).expect_err("2x3 matrix");
    assert_eq!(
        error.to_string(),
        "camera `cam_1` (name `B`), field `matrix`: expected 3 rows of 3 numbers, found 2 rows"
    );
}

/// Each bad fixture and what its error must say (beyond the file name).
const BAD_RIGS: &[(&str, &[&str])] = &[
    ("rig_missing_matrix.toml", &["camera `cam_1` (name `right`)", "field `matrix`", "missing"]),
    (
        "rig_matrix_wrong_shape.toml",
        &["camera `cam_1` (name `right`)", "field `matrix`", "expected 3 rows of 3 numbers, found 2 rows"],
    ),
    ("rig_matrix_last_row.toml", &["camera `cam_1` (name `right`)", "field `matrix`", "last row must be [0, 0, 1]"]),
    (
        "rig_nonfinite_matrix.toml",
        &["camera `cam_1` (name `right`)", "field `matrix`", "row 0, column 2 is not finite (inf)"],
    ),
    ("rig_singular_matrix.toml", &["camera `cam_1` (name `right`)", "field `matrix`", "singular"]),
    (
        "rig_nonfinite_translation.toml",
        &["camera `cam_1` (name `right`)", "field `translation`", "element 1 is not finite (NaN)"],
    ),
    (
        "rig_number_as_string.toml",
        &["camera `cam_1` (name `right`)", "field `translation`", "element 0: expected a number, found a string"],
    ),
    ("rig_rotation_not_orthonormal.toml", &["camera `cam_1` (name `right`)", "field `rotation`", "not orthonormal"]),
    ("rig_rotation_reflection.toml", &["camera `cam_1` (name `right`)", "field `rotation`", "determinant -1"]),
    ("rig_rotation_wrong_length.toml", &["camera `cam_1` (name `right`)", "field `rotation`", "found 2 numbers"]),
    (
        "rig_distortions_wrong_length.toml",
        &["camera `cam_1` (name `right`)", "field `distortions`", "expected 4 or 5 numbers", "found 3 numbers"],
    ),
    ("rig_size_negative.toml", &["camera `cam_1` (name `right`)", "field `size`", "width is -1920"]),
    ("rig_size_fractional.toml", &["camera `cam_1` (name `right`)", "field `size`", "width is 1920.5"]),
    ("rig_missing_name.toml", &["camera `cam_1`, field `name`: missing"]),
    ("rig_name_not_string.toml", &["camera `cam_1`, field `name`", "expected a string, found an integer"]),
    (
        "rig_duplicate_name.toml",
        &["camera `cam_1` (name `left`)", "field `name`", "duplicate camera name `left`", "camera `cam_0`"],
    ),
    (
        "rig_fisheye_five_coefficients.toml",
        &["camera `cam_1` (name `right`)", "field `distortions`", "4 fisheye coefficients", "found 5"],
    ),
    ("rig_no_cameras.toml", &["no cameras"]),
    ("rig_top_level_value.toml", &["top-level key `version`", "expected a camera table, found an integer"]),
    ("rig_syntax_error.toml", &["TOML syntax error at line 3"]),
];

#[test]
fn every_bad_rig_fails_with_a_precise_error_and_every_fixture_is_listed() {
    common::assert_bad_fixtures(BAD_RIGS, &["rig_"]);
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(1000))]

    /// Truncated or corrupted files give errors, never panics.
    #[test]
    fn damaged_files_never_panic(
        cut in 0usize..2000,
        edits in proptest::collection::vec((0usize..2000, prop::sample::select(vec![
            "", "[", "]", ",", "=", "\"", "\n", "nan", "-inf", "1e400", "-1", "0", "[[0]]", "true", "x", "[cam_0]",
        ])), 0..4),
    ) {
        let mut text = ANIPOSE_SAMPLE.to_owned();
        for (at, insert) in edits {
            let at = at.min(text.len());
            if text.is_char_boundary(at) {
                let end = (at + 3).min(text.len());
                if text.is_char_boundary(end) {
                    text.replace_range(at..end, insert);
                }
            }
        }
        let cut = cut.min(text.len());
        if text.is_char_boundary(cut) {
            text.truncate(cut);
        }
        let _ = Rig::from_toml_str(&text);
    }

    #[test]
    fn random_rigs_round_trip_through_text(
        cameras in proptest::collection::vec((
            (1u32..10_000, 1u32..10_000, 1.0..1e5, 1.0..1e5, -1e4..1e4, -1e4..1e4, -10.0..10.0),
            (-1.0..1.0, -1.0..1.0, -0.1..0.1, -0.1..0.1, -1.0..1.0),
            (-4.0..4.0, -4.0..4.0, -4.0..4.0),
            (-1e3..1e3, -1e3..1e3, -1e3..1e3),
        ), 1..5),
    ) {
        let cameras = cameras.into_iter().enumerate().map(|(i, ((w, h, fx, fy, cx, cy, s), (k1, k2, p1, p2, k3), (rx, ry, rz), (tx, ty, tz)))| {
            Camera::new(
                format!("cam {i}"), w, h,
                Matrix3::new(fx, s, cx, 0.0, fy, cy, 0.0, 0.0, 1.0),
                Distortion { k1, k2, p1, p2, k3 },
                Rotation3::new(Vector3::new(rx, ry, rz)),
                Vector3::new(tx, ty, tz),
            ).expect("valid")
        }).collect();
        let rig = Rig::new(cameras);
        let back = Rig::from_toml_str(&rig.to_toml_string()).expect("reads back");
        assert_same_rig(&rig, &back);
    }
}
