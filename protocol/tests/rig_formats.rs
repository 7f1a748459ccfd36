//! Calibration formats other than our TOML (caliscope, OpenCV YAML and XML), format
//! detection, finding a folder's calibration, mount quarter turns and the world's up.

mod common;

use std::path::{Path, PathBuf};

use handflow_protocol::{Camera, Distortion, Rig, RigError, RigFormat, UpSource};
use nalgebra::{Matrix3, Point3, Rotation3, Vector3};
use proptest::prelude::*;

/// The same three-camera rig written in every format.
const FORMATS_DIR: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../tests/fixtures/rig_formats/");
/// The real caliscope session, outside the repository.
const CALISCOPE_HANDS: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../../shared/data/real/caliscope-hands/");

fn fixture(name: &str) -> PathBuf {
    Path::new(FORMATS_DIR).join(name)
}

fn reference_rig() -> Rig {
    let (rig, format) = Rig::load_detected(fixture("anipose.toml")).expect("reference rig");
    assert_eq!(format, RigFormat::AniposeToml);
    rig
}

/// Points in front of the rig, in and around every camera's view.
fn test_points() -> Vec<Point3<f64>> {
    let mut points = Vec::new();
    for i in -5..=5 {
        for j in -4..=4 {
            for k in -3..=3 {
                points.push(Point3::new(0.1 * f64::from(i), 0.1 * f64::from(j), 0.15 * f64::from(k)));
            }
        }
    }
    points
}

/// Same cameras in the same order, projecting every test point within 1e-6 px.
fn assert_same_projections(expected: &Rig, actual: &Rig, what: &str) {
    let names = |rig: &Rig| rig.cameras.iter().map(|c| c.name.clone()).collect::<Vec<_>>();
    assert_eq!(names(expected), names(actual), "{what}: camera names");
    for (a, b) in expected.cameras.iter().zip(&actual.cameras) {
        assert_eq!((a.width, a.height), (b.width, b.height), "{what}: {} size", a.name);
        assert_eq!(a.mount_quarter_turns, b.mount_quarter_turns, "{what}: {} mount turns", a.name);
        let mut compared = 0;
        for p in test_points() {
            match (a.project(&p), b.project(&p)) {
                (Some(x), Some(y)) => {
                    let error = (x - y).norm();
                    assert!(error <= 1e-6, "{what}: {} projects {p:?} {error} px apart", a.name);
                    compared += 1;
                }
                (None, None) => {}
                (x, y) => panic!("{what}: {} disagrees whether {p:?} is in front: {x:?} vs {y:?}", a.name),
            }
        }
        assert!(compared > 500, "{what}: only {compared} points compared");
    }
}

#[test]
fn an_older_caliscope_projects_config_projects_like_the_anipose_form() {
    let (rig, format) = Rig::load_detected(fixture("caliscope_config.toml")).expect("caliscope config.toml");
    assert_eq!(format, RigFormat::CaliscopeConfig);
    assert_same_projections(&reference_rig(), &rig, "caliscope config.toml");
    assert_eq!(rig.cameras[2].mount_quarter_turns, 1);
    // The ignored camera and the one never calibrated are left out, each with a note.
    assert_eq!(rig.notes.len(), 2, "{:?}", rig.notes);
    assert!(rig.notes[0].contains("cam_3") && rig.notes[0].contains("ignore"), "{:?}", rig.notes);
    assert!(rig.notes[1].contains("cam_4") && rig.notes[1].contains("not calibrated"), "{:?}", rig.notes);
    // A camera whose lens was calibrated but not its pose is left out too; a wrong field of
    // a calibrated one is an error naming its table and field.
    let text = std::fs::read_to_string(fixture("caliscope_config.toml")).expect("the fixture");
    let unposed = text.replace("translation = [0.0, 0.25, 2.0]\nrotation = [0.1, 0.0, 0.0]\n", "");
    let (rig, _) = Rig::from_str_detect(&unposed, "config").expect("one camera unposed");
    assert_eq!(rig.cameras.len(), 2);
    assert!(rig.notes.iter().any(|n| n.contains("cam_1") && n.contains("not posed")), "{:?}", rig.notes);
    // caliscope's camera_array.toml leaves such fields out the same way.
    let array = std::fs::read_to_string(fixture("camera_array.toml")).expect("the fixture");
    let unposed = array.replace("translation = [0.0, 0.25, 2.0]\n", "").replacen(
        "rotation = [[1.0, 0.0, 0.0], [0.0, 0.9950041652780258, -0.09983341664682815], [0.0, 0.09983341664682815, \
         0.9950041652780258]]\n",
        "",
        1,
    );
    let (rig, _) = Rig::from_str_detect(&unposed, "camera_array").expect("one camera unposed");
    assert_eq!(rig.cameras.iter().map(|c| c.name.as_str()).collect::<Vec<_>>(), ["cam_0", "cam_2"]);
    assert!(rig.notes.iter().any(|n| n.contains("cam_1") && n.contains("not posed")), "{:?}", rig.notes);
    let broken = text.replace("rotation = [0.1, 0.0, 0.0]", "rotation = [0.1, 0.0]");
    let error = Rig::from_str_detect(&broken, "config").expect_err("a short rotation").to_string();
    assert!(error.contains("cam_1") && error.contains("rotation"), "{error}");
}

#[test]
fn caliscope_form_projects_like_the_anipose_form() {
    let (rig, format) = Rig::load_detected(fixture("camera_array.toml")).expect("caliscope rig");
    assert_eq!(format, RigFormat::Caliscope);
    assert_same_projections(&reference_rig(), &rig, "caliscope");
    // `rotation_count = -3` is one clockwise quarter turn.
    assert_eq!(rig.cameras[2].mount_quarter_turns, 1);
    // The ignored fourth camera is left out, with a note saying so.
    assert_eq!(rig.notes.len(), 1, "{:?}", rig.notes);
    assert!(rig.notes[0].contains("cam_3") && rig.notes[0].contains("ignore"), "{:?}", rig.notes);
}

#[test]
fn opencv_yaml_and_xml_forms_project_like_the_anipose_form() {
    for (file, expected) in [("opencv_rig.yml", RigFormat::OpenCvYaml), ("opencv_rig.xml", RigFormat::OpenCvXml)] {
        let (rig, format) = Rig::load_detected(fixture(file)).expect(file);
        assert_eq!(format, expected, "{file}");
        assert_same_projections(&reference_rig(), &rig, file);
    }
}

#[test]
fn opencv_files_of_one_camera_each_make_one_rig() {
    let files: Vec<PathBuf> = ["cam_0.yml", "cam_1.yml", "cam_2.xml"].into_iter().map(fixture).collect();
    let rig = Rig::load_files(&files).expect("per-camera files");
    assert_same_projections(&reference_rig(), &rig, "per-camera files");

    // The same files alone in a folder are found as its calibration.
    let dir = tempfile::tempdir().expect("temp dir");
    for file in &files {
        std::fs::copy(file, dir.path().join(file.file_name().expect("a file name"))).expect("copy");
    }
    let found = Rig::find_in_dir(dir.path()).expect("found");
    assert_eq!(found.len(), 3);
    assert_same_projections(&reference_rig(), &Rig::load_dir(dir.path()).expect("load dir"), "folder");
}

/// The reference rig with its translations in millimetres, as anipose, FreeMoCap and OpenCV
/// calibrations measured with a board in millimetres have them.
fn reference_rig_in_millimetres() -> Rig {
    let mut rig = reference_rig();
    for camera in &mut rig.cameras {
        camera.translation *= 1000.0;
    }
    rig
}

#[test]
fn a_calibration_in_millimetres_is_read_in_metres_with_a_note() {
    let dir = tempfile::tempdir().expect("temp dir");
    let path = dir.path().join("calibration.toml");
    std::fs::write(&path, reference_rig_in_millimetres().to_toml_string()).expect("write");
    let rig = Rig::load(&path).expect("rig in millimetres");
    assert_same_projections(&reference_rig(), &rig, "millimetres");
    for (got, want) in rig.cameras.iter().zip(&reference_rig().cameras) {
        assert!((got.centre() - want.centre()).norm() < 1e-9, "{} at {:?}", got.name, got.centre());
    }
    assert!(rig.notes.iter().any(|n| n.contains("read as millimetres")), "{:?}", rig.notes);
    assert!(reference_rig().notes.iter().all(|n| !n.contains("millimetres")), "a rig in metres stays in metres");

    // One camera per file: each file alone has no width to judge; the rig they make has.
    let mut files = Vec::new();
    for camera in reference_rig_in_millimetres().cameras {
        let file = dir.path().join(format!("{}.toml", camera.name));
        std::fs::write(&file, Rig::new(vec![camera]).to_toml_string()).expect("write");
        files.push(file);
    }
    let rig = Rig::load_files(&files).expect("per-camera files in millimetres");
    assert_same_projections(&reference_rig(), &rig, "per-camera files in millimetres");
    assert!(rig.notes.iter().any(|n| n.contains("read as millimetres")), "{:?}", rig.notes);
}

#[test]
fn a_camera_in_two_files_is_an_error_naming_both() {
    let files = [fixture("cam_0.yml"), fixture("opencv_rig.yml")];
    let message = Rig::load_files(&files).expect_err("cam_0 twice").to_string();
    assert!(message.contains("camera `cam_0`"), "{message}");
    assert!(message.contains("cam_0.yml") && message.contains("opencv_rig.yml"), "{message}");
}

#[test]
fn find_in_dir_prefers_rig_toml_then_camera_array_then_a_single_file() {
    let dir = tempfile::tempdir().expect("temp dir");
    let path = dir.path();
    let copy = |from: &str, to: &str| std::fs::copy(fixture(from), path.join(to)).expect("copy");

    let message = Rig::find_in_dir(path).expect_err("empty").to_string();
    assert!(message.contains("no calibration found") && message.contains("found no calibration files"), "{message}");

    copy("opencv_rig.xml", "calibration.xml");
    assert_eq!(Rig::find_in_dir(path).expect("single"), [path.join("calibration.xml")]);

    copy("anipose.toml", "other.toml");
    let error = Rig::find_in_dir(path).expect_err("two candidates, one not OpenCV");
    assert!(matches!(error, RigError::NoCalibration { .. }));
    let message = error.to_string();
    assert!(message.contains("calibration.xml (OpenCV FileStorage XML)"), "{message}");
    assert!(message.contains("other.toml (TOML)"), "{message}");

    copy("camera_array.toml", "camera_array.toml");
    assert_eq!(Rig::find_in_dir(path).expect("caliscope"), [path.join("camera_array.toml")]);
    copy("anipose.toml", "rig.toml");
    assert_eq!(Rig::find_in_dir(path).expect("ours"), [path.join("rig.toml")]);
}

#[test]
fn mount_turns_and_declared_up_survive_the_rig_toml() {
    let mut rig = Rig::load(fixture("camera_array.toml")).expect("caliscope rig");
    let back = Rig::from_toml_str(&rig.to_toml_string()).expect("reads back");
    assert_same_projections(&rig, &back, "round trip");
    assert_eq!(back.cameras[2].mount_quarter_turns, 1);
    assert!(back.declared_up.is_none());

    rig.set_up(Vector3::new(0.0, 0.0, 2.0)).expect("a direction");
    let back = Rig::from_toml_str(&rig.to_toml_string()).expect("reads back");
    let up = back.world_up();
    assert_eq!((up.direction, up.source), (Vector3::z(), UpSource::Configured));

    // A file stating its up: the calibration's.
    let text =
        format!("{}\n[metadata]\nup = [0, -1, 0]\n", std::fs::read_to_string(fixture("anipose.toml")).expect("read"));
    let up = Rig::from_toml_str(&text).expect("valid").world_up();
    assert_eq!((up.direction, up.source), (-Vector3::y(), UpSource::Calibration));

    assert!(rig.set_up(Vector3::zeros()).is_err());
    assert!(rig.set_up(Vector3::new(f64::NAN, 0.0, 1.0)).is_err());
}

/// A camera at `position` looking at `target`, upright for `up`, then mounted by `turns`
/// clockwise quarter turns (its raw frames must be turned clockwise that often to be
/// upright), with the mount recorded when `record` is set.
fn camera(
    name: &str,
    position: Vector3<f64>,
    target: Vector3<f64>,
    up: Vector3<f64>,
    turns: u8,
    record: bool,
) -> Camera {
    let z = (target - position).normalize();
    let x = z.cross(&up).normalize();
    let y = z.cross(&x);
    let upright = Matrix3::from_rows(&[x.transpose(), y.transpose(), z.transpose()]);
    // Each turn rolls the camera so that its raw left edge points where its top did: its
    // x axis (raw right) then points down.
    let roll = Rotation3::from_axis_angle(&Vector3::z_axis(), std::f64::consts::FRAC_PI_2 * f64::from(turns));
    let r = Rotation3::from_matrix_unchecked(roll.matrix().transpose() * upright);
    let k = Matrix3::new(800.0, 0.0, 320.0, 0.0, 800.0, 240.0, 0.0, 0.0, 1.0);
    let camera = Camera::new(name, 640, 480, k, Distortion::default(), r, -(r * position)).expect("valid");
    if record {
        camera.with_mount_quarter_turns(turns)
    } else {
        camera
    }
}

/// Three cameras on an arc 2.5 m from the origin at 1.6 m, looking slightly down at it.
fn arc_rig(up: Vector3<f64>, forward: Vector3<f64>, sideways_turns: u8, record: bool) -> Rig {
    let side = forward.cross(&up);
    let cameras = [-0.6f64, 0.0, 0.7]
        .into_iter()
        .enumerate()
        .map(|(i, angle)| {
            let position = (forward * angle.cos() + side * angle.sin()) * -2.5 + up * 0.4;
            let turns = if i == 2 { sideways_turns } else { 0 };
            camera(&format!("cam_{i}"), position, Vector3::zeros(), up, turns, record)
        })
        .collect();
    Rig::new(cameras)
}

fn assert_estimated(rig: &Rig, expected: Vector3<f64>, what: &str) {
    let up = rig.world_up();
    let UpSource::Estimated { how } = &up.source else { panic!("{what}: not estimated: {:?}", up.source) };
    assert!((up.direction - expected).norm() < 1e-12, "{what}: {:?} ({how})", up.direction);
    assert!(how.contains("snapped"), "{what}: {how}");
}

#[test]
fn image_up_follows_the_mount_quarter_turns() {
    let up = Vector3::y();
    for turns in 0..4 {
        let c = camera("c", Vector3::new(0.0, 0.0, 3.0), Vector3::zeros(), up, turns, true);
        assert!((c.image_up() - up).norm() < 1e-12, "{turns}: {:?}", c.image_up());
    }
}

#[test]
fn up_is_estimated_from_all_cameras_in_a_y_up_world() {
    let (up, forward) = (Vector3::y(), -Vector3::z());
    assert_estimated(&arc_rig(up, forward, 0, true), up, "upright");
    // One camera mounted sideways, saying so.
    assert_estimated(&arc_rig(up, forward, 1, true), up, "sideways, recorded");
    // One camera mounted sideways without saying so: outvoted by the other two.
    let rig = arc_rig(up, forward, 3, false);
    assert!(rig.cameras[2].image_up().dot(&up).abs() < 0.5);
    assert_estimated(&rig, up, "sideways, unrecorded");
}

#[test]
fn unrecorded_mounts_are_inferred_from_the_geometry() {
    for (up, forward) in [(Vector3::y(), -Vector3::z()), (Vector3::z(), Vector3::y()), (-Vector3::y(), Vector3::z())] {
        for turns in 1..4 {
            let what = format!("up {up:?}, {turns} turn(s)");
            let mut rig = arc_rig(up, forward, turns, false);
            rig.infer_mounts();
            let mounts: Vec<u8> = rig.cameras.iter().map(|c| c.mount_quarter_turns).collect();
            assert_eq!(mounts, vec![0, 0, turns], "{what}");
            assert!(rig.cameras[2].image_up().dot(&up) > 0.9, "{what}");
            assert_eq!(rig.notes.len(), 1, "{what}: {:?}", rig.notes);
            assert!(rig.notes[0].contains("cam_2"), "{what}: {:?}", rig.notes);
            assert_estimated(&rig, up, &what);
            // Recorded, or inferred once already: nothing changes.
            let mut again = arc_rig(up, forward, turns, true);
            again.infer_mounts();
            assert!(again.notes.is_empty(), "{what}: {:?}", again.notes);
            assert_eq!(again.cameras[2].mount_quarter_turns, turns, "{what}");
        }
    }
    // A mount the file records is the user's word: kept even where the geometry disagrees.
    let mut rig = arc_rig(Vector3::y(), -Vector3::z(), 0, true);
    rig.cameras[1] = rig.cameras[1].clone().with_mount_quarter_turns(2);
    rig.infer_mounts();
    assert_eq!(rig.cameras[1].mount_quarter_turns, 2, "{:?}", rig.notes);
}

#[test]
fn mounts_inferred_under_a_wrong_estimate_are_judged_again_once_the_up_is_declared() {
    // Every camera sideways without saying so, two one way and one the other: the estimate
    // follows the two, and the third is inferred upside down under it.
    let up = Vector3::y();
    let cameras = [(-0.6f64, 1), (0.0, 1), (0.6, 3)]
        .into_iter()
        .enumerate()
        .map(|(i, (angle, turns))| {
            let position = Vector3::new(angle.sin(), 0.0, angle.cos()) * 1.8 + up * 0.15;
            camera(&format!("cam_{i}"), position, up * 0.1, up, turns, false)
        })
        .collect();
    let mut rig = Rig::new(cameras);
    rig.infer_mounts();
    assert!(rig.world_up().direction.dot(&up).abs() < 0.5, "the estimate lies on its side");
    assert_eq!(rig.cameras.iter().map(|c| c.mount_quarter_turns).collect::<Vec<_>>(), vec![0, 0, 2]);
    // Judged under a rough up, the cameras turned so give it back precisely, changing nothing.
    let rough = Vector3::new(0.2, 0.95, 0.1);
    assert_eq!(rig.estimate_up_under(rough).expect("valid up").direction, up);
    assert_eq!(rig.cameras.iter().map(|c| c.mount_quarter_turns).collect::<Vec<_>>(), vec![0, 0, 2]);
    // Told where up is, every mount the file did not record is judged again, the inferred
    // one included.
    rig.set_up(up).expect("valid up");
    assert_eq!(rig.cameras.iter().map(|c| c.mount_quarter_turns).collect::<Vec<_>>(), vec![1, 1, 3]);
    assert!(rig.cameras.iter().all(|c| c.image_up().dot(&up) > 0.9));
    assert_eq!(rig.mounts_inferred, vec![true, true, true]);
}

#[test]
fn mounts_are_left_alone_without_a_clear_up() {
    let up = Vector3::y();
    // Two of three cameras sideways without saying so: the estimated up is theirs to
    // outvote, so no camera is changed...
    let mut rig = arc_rig(up, -Vector3::z(), 1, false);
    rig.cameras[0] = camera("cam_0", Vector3::new(-1.4, 0.4, -2.1), Vector3::zeros(), up, 1, false);
    let before: Vec<u8> = rig.cameras.iter().map(|c| c.mount_quarter_turns).collect();
    rig.infer_mounts();
    assert_eq!(rig.cameras.iter().map(|c| c.mount_quarter_turns).collect::<Vec<_>>(), before);
    // ...until the user says where up is.
    rig.set_up(up).expect("valid up");
    assert_eq!(rig.cameras.iter().map(|c| c.mount_quarter_turns).collect::<Vec<_>>(), vec![1, 0, 1]);
    // A camera looking straight down has no up in its frames: its mount stays as written.
    let overhead = camera("top", Vector3::new(0.0, 3.0, 0.0), Vector3::zeros(), Vector3::z(), 1, true);
    let mut rig = arc_rig(up, -Vector3::z(), 0, true);
    rig.cameras.push(overhead);
    rig.infer_mounts();
    assert_eq!(rig.cameras[3].mount_quarter_turns, 1);
    assert!(rig.notes.is_empty(), "{:?}", rig.notes);
}

#[test]
fn a_calibration_without_mounts_gets_them_when_loaded() {
    let dir = tempfile::tempdir().expect("temp dir");
    let path = dir.path().join("rig.toml");
    let unrecorded = arc_rig(Vector3::y(), -Vector3::z(), 3, false);
    std::fs::write(&path, unrecorded.to_toml_string()).expect("write");
    assert!(!std::fs::read_to_string(&path).expect("read").contains("mount_quarter_turns"));
    let rig = Rig::load(&path).expect("loads");
    assert_eq!(rig.cameras[2].mount_quarter_turns, 3);
    assert!(rig.notes.iter().any(|n| n.contains("cam_2")), "{:?}", rig.notes);
}

#[test]
fn up_is_estimated_in_a_z_up_motion_capture_world() {
    assert_estimated(&arc_rig(Vector3::z(), Vector3::y(), 0, true), Vector3::z(), "Z up");
    assert_estimated(&arc_rig(Vector3::z(), Vector3::y(), 1, true), Vector3::z(), "Z up, one sideways");
}

#[test]
fn up_is_estimated_in_a_y_down_opencv_world() {
    assert_estimated(&arc_rig(-Vector3::y(), Vector3::z(), 0, true), -Vector3::y(), "Y down");
}

#[test]
fn reads_the_real_caliscope_session() {
    let path = Path::new(CALISCOPE_HANDS).join("camera_array.toml");
    if !path.is_file() {
        eprintln!("reads_the_real_caliscope_session: skipped, {} not found", path.display());
        return;
    }
    let (rig, format) = Rig::load_detected(&path).expect("real caliscope file");
    assert_eq!(format, RigFormat::Caliscope);
    let names: Vec<&str> = rig.cameras.iter().map(|c| c.name.as_str()).collect();
    assert_eq!(names, ["cam_0", "cam_1", "cam_2", "cam_3"]);
    assert!(rig.cameras.iter().all(|c| (c.width, c.height) == (1280, 720) && c.mount_quarter_turns == 0));
    assert_eq!(Rig::find_in_dir(CALISCOPE_HANDS).expect("found"), std::slice::from_ref(&path));
    let up = rig.world_up();
    assert!((up.direction.norm() - 1.0).abs() < 1e-12);
    eprintln!("caliscope-hands: up {:?}, {}", up.direction, up.source);
    // The cameras surround a seated person, 0.4 to 1 m away.
    let centres: Vec<_> = rig.cameras.iter().map(Camera::centre).collect();
    for (i, a) in centres.iter().enumerate() {
        for b in &centres[i + 1..] {
            assert!((a - b).norm() > 0.1 && (a - b).norm() < 3.0);
        }
    }
}

/// Each bad fixture and what its error must say (beyond the file name).
const BAD_CALIBRATIONS: &[(&str, &[&str])] = &[
    ("caliscope_missing_matrix.toml", &["camera `cameras.1` (name `cam_1`), field `matrix`: missing"]),
    (
        "caliscope_rotation_not_orthonormal.toml",
        &["camera `cameras.1` (name `cam_1`), field `rotation`", "not orthonormal"],
    ),
    (
        "caliscope_rotation_count_not_integer.toml",
        &["camera `cameras.1` (name `cam_1`), field `rotation_count`", "expected an integer"],
    ),
    ("caliscope_ignore_not_boolean.toml", &["camera `cameras.0` (name `cam_0`), field `ignore`", "expected a boolean"]),
    ("caliscope_all_ignored.toml", &["no cameras"]),
    ("opencv_missing_rotation.yml", &["camera `opencv_missing_rotation`, field `R`: missing (or `rvec`)"]),
    (
        "opencv_matrix_data_length.yml",
        &["camera `opencv_matrix_data_length`, field `camera_matrix`", "3x3 has 8 numbers"],
    ),
    ("opencv_distortion_rational_terms.yml", &["field `D`", "8 coefficients with coefficient 5 = 0.01 non-zero"]),
    ("opencv_distortion_count.yml", &["field `distortion_coefficients`", "found 6"]),
    ("opencv_missing_width.yml", &["field `image_width`: missing"]),
    ("opencv_nonfinite_translation.yml", &["field `T`", "y is not finite (NaN)"]),
    ("opencv_rvec_wrong_length.yml", &["field `rvec`", "found 2x1"]),
    ("opencv_unclosed_sequence.yml", &["OpenCV YAML syntax error at line 10", "unclosed `[`"]),
    ("opencv_second_camera_bad_matrix.yml", &["camera `right`", "field `K`", "expected a 3x3 matrix, found 2x3"]),
    (
        "opencv_duplicate_name.yml",
        &["camera `cam_1` (name `front`)", "field `name`", "duplicate camera name `front`", "camera `cam_0`"],
    ),
    ("opencv_missing_translation.xml", &["camera `opencv_missing_translation` (name `left`), field `T`: missing"]),
    ("opencv_singular_matrix.xml", &["camera `opencv_singular_matrix`, field `camera_matrix`", "singular"]),
    (
        "opencv_unclosed_element.xml",
        &[
            "OpenCV XML syntax error at line 30",
            "expected `</T>` (closing `<T>` of line 24), found `</opencv_storage>`",
        ],
    ),
    ("opencv_wrong_root.xml", &["OpenCV XML syntax error", "expected the root element `<opencv_storage>`"]),
];

#[test]
fn every_bad_calibration_fails_with_a_precise_error_and_every_fixture_is_listed() {
    common::assert_bad_fixtures(BAD_CALIBRATIONS, &["caliscope_", "opencv_"]);
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(500))]

    /// Truncated or corrupted OpenCV and caliscope files give errors, never panics.
    #[test]
    fn damaged_files_never_panic(
        file in prop::sample::select(vec!["opencv_rig.yml", "opencv_rig.xml", "cam_0.yml", "camera_array.toml"]),
        cut in 0usize..6000,
        edits in proptest::collection::vec((0usize..6000, prop::sample::select(vec![
            "", "[", "]", "<", ">", "</", "/>", ":", " ", "\n", "  ", "-", "- ", "!!opencv-matrix", ".nan",
            "\"", "'", "é", "type_id=\"", "<_>", "{", "}", ",", "#", "\t",
        ])), 0..5),
    ) {
        let mut text = std::fs::read_to_string(fixture(file)).expect("fixture");
        for (at, insert) in edits {
            let at = at.min(text.len());
            let end = (at + 2).min(text.len());
            if text.is_char_boundary(at) && text.is_char_boundary(end) {
                text.replace_range(at..end, insert);
            }
        }
        let cut = cut.min(text.len());
        if text.is_char_boundary(cut) {
            text.truncate(cut);
        }
        let _ = Rig::from_str_detect(&text, "stem");
    }
}
