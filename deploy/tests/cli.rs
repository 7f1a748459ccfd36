//! End-to-end tests of the `handflow` binary: each test spawns the real executable on a small
//! crop of the Middlebury Teddy scene (or on a tiny synthetic scene for the error paths) and
//! checks its exit status, its JSON reports, the maps it writes and its error messages.
//!
//! Tests that need Teddy print a "skipped" message and pass when the data is absent.

#![allow(clippy::unwrap_used)]

mod common;

use std::path::{Path, PathBuf};
use std::process::Output;

use common::{describe, handflow};
use handflow::eval::middlebury::{read_pfm, Scene};
use serde_json::{Map, Value};
use tempfile::TempDir;

/// The built-in Teddy scene, relative to this crate.
const TEDDY: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../../shared/data/middlebury/teddy");

/// Width and height of the crop the tests run on: small enough for debug builds.
const CROP: (u32, u32) = (120, 90);

/// Keys every `eval middlebury --json` report carries.
const EVAL_KEYS: [&str; 11] = [
    "scene",
    "layout",
    "variant",
    "of_rmse_px",
    "zflow_rmse",
    "structure_rmse_px",
    "aae_deg",
    "seconds_per_frame",
    "particles_per_ray",
    "seed",
    "threads",
];

/// The accuracy metrics of a report: what a fixed seed must reproduce exactly.
const METRICS: [&str; 4] = ["of_rmse_px", "zflow_rmse", "structure_rmse_px", "aae_deg"];

/// A temporary folder holding a cropped Teddy scene in `crop/`, or `None` (after saying
/// so) when the data is absent.
fn teddy_crop(test: &str) -> Option<(TempDir, PathBuf)> {
    let teddy = Path::new(TEDDY);
    if !teddy.join("scene.toml").is_file() {
        eprintln!("{test}: skipped, Teddy not found at {}", teddy.display());
        return None;
    }
    let tmp = tempfile::tempdir().expect("temporary folder");
    let dir = tmp.path().join("crop");
    let scene = Scene::load(teddy).expect("load Teddy");
    scene.crop(150, 100, CROP.0, CROP.1).expect("crop Teddy").save(&dir).expect("save the crop");
    Some((tmp, dir))
}

/// A tiny valid scene that needs no data: nine textured views and a constant disparity
/// of 2 px between neighbours for views 2 and 6, saved into `tmp/name`.
fn synthetic_scene(tmp: &Path, name: &str) -> PathBuf {
    let (width, height) = (24u32, 16u32);
    let pixels = (width * height) as usize;
    let images = (0..9)
        .map(|view| {
            (0..pixels)
                .flat_map(|i| {
                    let x = (i % width as usize) as i64 + 2 * view;
                    let y = (i / width as usize) as i64;
                    let v = ((x * 37 + y * 11) % 251) as u8;
                    [v, v.wrapping_mul(3), v.wrapping_add(90)]
                })
                .collect()
        })
        .collect();
    let scene = Scene {
        name: name.to_string(),
        dir: tmp.join(name),
        width,
        height,
        images,
        disparity_scale: 4.0,
        disparity_span: 4.0,
        disparity_range: (0.0, 16.0),
        gt: vec![(2, vec![2.0; pixels]), (6, vec![2.0; pixels])],
    };
    let dir = tmp.join(name);
    scene.save(&dir).expect("save the synthetic scene");
    dir
}

/// Asserts a successful run whose stdout is exactly one JSON object, and returns it.
fn json_report(output: &Output) -> Map<String, Value> {
    assert!(output.status.success(), "expected success\n{}", describe(output));
    let stdout = String::from_utf8(output.stdout.clone()).expect("stdout is UTF-8");
    let lines: Vec<&str> = stdout.lines().filter(|l| !l.trim().is_empty()).collect();
    assert_eq!(lines.len(), 1, "expected one line of JSON on stdout\n{}", describe(output));
    match serde_json::from_str::<Value>(lines[0]) {
        Ok(Value::Object(map)) => map,
        other => panic!("stdout is not one JSON object ({other:?})\n{}", describe(output)),
    }
}

/// The finite number under `key`.
fn number(report: &Map<String, Value>, key: &str) -> f64 {
    let value = report.get(key).unwrap_or_else(|| panic!("key `{key}` missing from {report:?}"));
    let x = value.as_f64().unwrap_or_else(|| panic!("`{key}` is not a number: {value}"));
    assert!(x.is_finite(), "`{key}` is not finite: {x}");
    x
}

/// The string under `key`.
fn string<'a>(report: &'a Map<String, Value>, key: &str) -> &'a str {
    let value = report.get(key).unwrap_or_else(|| panic!("key `{key}` missing from {report:?}"));
    value.as_str().unwrap_or_else(|| panic!("`{key}` is not a string: {value}"))
}

/// Checks every key of an eval report is present and its numbers are finite.
fn check_eval_report(report: &Map<String, Value>) {
    for key in EVAL_KEYS {
        assert!(report.contains_key(key), "key `{key}` missing from {report:?}");
    }
    for key in ["scene", "layout", "variant"] {
        assert!(!string(report, key).is_empty(), "`{key}` is empty");
    }
    for key in METRICS {
        assert!(number(report, key) >= 0.0, "`{key}` is negative");
    }
    assert!(number(report, "seconds_per_frame") > 0.0);
    assert!(report["particles_per_ray"].is_u64(), "particles_per_ray: {}", report["particles_per_ray"]);
    assert!(report["seed"].is_u64(), "seed: {}", report["seed"]);
    assert!(report["threads"].as_u64().is_some_and(|t| t >= 1), "threads: {}", report["threads"]);
}

/// Asserts a failed run that explains itself on stderr (naming every one of `needles`)
/// without panicking, and returns stderr.
fn check_failure(output: &Output, needles: &[&str]) -> String {
    assert!(!output.status.success(), "expected failure\n{}", describe(output));
    assert!(output.status.code().is_some(), "killed by a signal\n{}", describe(output));
    let stderr = String::from_utf8_lossy(&output.stderr).into_owned();
    assert!(!stderr.contains("panicked"), "the binary panicked\n{}", describe(output));
    assert!(!stderr.trim().is_empty(), "no error message\n{}", describe(output));
    for needle in needles {
        assert!(stderr.contains(needle), "stderr does not mention `{needle}`\n{}", describe(output));
    }
    stderr
}

/// Path as a command-line argument.
fn arg(path: &Path) -> &str {
    path.to_str().expect("temporary paths are UTF-8")
}

#[test]
fn eval_multiview_json_reports_every_metric() {
    let Some((_tmp, scene)) = teddy_crop("eval_multiview_json_reports_every_metric") else { return };
    let output = handflow(&[
        "eval",
        "middlebury",
        "--scene",
        arg(&scene),
        "--layout",
        "multiview",
        "--particles-per-ray",
        "4",
        "--seed",
        "7",
        "--json",
    ]);
    let report = json_report(&output);
    check_eval_report(&report);
    assert_eq!(string(&report, "layout"), "multiview");
    assert_eq!(string(&report, "variant"), "handflow");
    assert_eq!(report["seed"].as_u64(), Some(7));
    assert_eq!(report["particles_per_ray"].as_u64(), Some(4));
}

#[test]
fn eval_fb_paper_single_thread_json() {
    let Some((_tmp, scene)) = teddy_crop("eval_fb_paper_single_thread_json") else { return };
    let output = handflow(&[
        "eval",
        "middlebury",
        "--scene",
        arg(&scene),
        "--layout",
        "fb",
        "--variant",
        "paper",
        "--threads",
        "1",
        "--particles-per-ray",
        "4",
        "--seed",
        "3",
        "--json",
    ]);
    let report = json_report(&output);
    check_eval_report(&report);
    assert_eq!(string(&report, "layout"), "fb");
    assert_eq!(string(&report, "variant"), "paper");
    assert_eq!(report["threads"].as_u64(), Some(1));
    assert_eq!(report["seed"].as_u64(), Some(3));
    assert_eq!(report["particles_per_ray"].as_u64(), Some(4));
}

#[test]
fn eval_out_writes_maps_of_the_crop_size() {
    let Some((tmp, scene)) = teddy_crop("eval_out_writes_maps_of_the_crop_size") else { return };
    let out = tmp.path().join("maps");
    let output = handflow(&[
        "eval",
        "middlebury",
        "--scene",
        arg(&scene),
        "--layout",
        "multiview",
        "--particles-per-ray",
        "4",
        "--out",
        arg(&out),
    ]);
    assert!(output.status.success(), "expected success\n{}", describe(&output));

    let (width, height) = CROP;
    let pixels = (width * height) as usize;
    let (w, h, channels, data) = read_pfm(&out.join("depth.pfm")).expect("read depth.pfm");
    assert_eq!((w, h, channels), (width, height, 1), "depth.pfm");
    assert_eq!(data.len(), pixels);
    assert!(data.iter().any(|z| z.is_finite() && *z > 0.0), "depth.pfm has no positive depth");
    let (w, h, channels, data) = read_pfm(&out.join("scene_flow.pfm")).expect("read scene_flow.pfm");
    assert_eq!((w, h, channels), (width, height, 3), "scene_flow.pfm");
    assert_eq!(data.len(), pixels * 3);

    for name in ["disparity.png", "flow.png"] {
        let path = out.join(name);
        let (w, h) = image::image_dimensions(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        assert_eq!((w, h), (width, height), "{name}");
    }
}

#[test]
fn eval_same_seed_same_metrics() {
    let Some((_tmp, scene)) = teddy_crop("eval_same_seed_same_metrics") else { return };
    let run = |seed: &str| {
        let output = handflow(&[
            "eval",
            "middlebury",
            "--scene",
            arg(&scene),
            "--layout",
            "multiview",
            "--particles-per-ray",
            "4",
            "--threads",
            "2",
            "--seed",
            seed,
            "--json",
        ]);
        json_report(&output)
    };
    let first = run("11");
    let second = run("11");
    for key in METRICS {
        assert_eq!(number(&first, key), number(&second, key), "`{key}` differs between two runs with seed 11");
    }
    // Another seed may or may not change the result; it must still run and report.
    check_eval_report(&run("12"));
}

#[test]
fn bench_flow_json_reports_speed() {
    let Some((_tmp, scene)) = teddy_crop("bench_flow_json_reports_speed") else { return };
    let output = handflow(&[
        "bench",
        "flow",
        "--scene",
        arg(&scene),
        "--layout",
        "multiview",
        "--particles-per-ray",
        "4",
        "--repeats",
        "1",
        "--json",
    ]);
    let report = json_report(&output);
    for key in ["seconds_per_frame_1_thread", "seconds_per_frame", "evaluations_per_second", "threads"] {
        assert!(number(&report, key) > 0.0, "`{key}` is not positive in {report:?}");
    }
    assert!(report["threads"].is_u64(), "threads: {}", report["threads"]);
}

#[test]
fn missing_scene_folder_is_named() {
    let tmp = tempfile::tempdir().expect("temporary folder");
    let missing = tmp.path().join("no-such-scene");
    let output = handflow(&["eval", "middlebury", "--scene", arg(&missing), "--json"]);
    check_failure(&output, &[arg(&missing)]);
    assert!(output.stdout.is_empty(), "nothing on stdout after an error\n{}", describe(&output));

    let output = handflow(&["bench", "flow", "--scene", arg(&missing), "--repeats", "1"]);
    check_failure(&output, &[arg(&missing)]);
}

#[test]
fn missing_view_image_is_named() {
    let tmp = tempfile::tempdir().expect("temporary folder");
    let scene = synthetic_scene(tmp.path(), "no-im3");
    std::fs::remove_file(scene.join("im3.ppm")).expect("remove im3.ppm");
    let output = handflow(&["eval", "middlebury", "--scene", arg(&scene), "--json"]);
    check_failure(&output, &["im3"]);
}

#[test]
fn unknown_layout_is_a_usage_error() {
    let tmp = tempfile::tempdir().expect("temporary folder");
    let scene = synthetic_scene(tmp.path(), "layout");
    let output = handflow(&["eval", "middlebury", "--scene", arg(&scene), "--layout", "sideways"]);
    check_failure(&output, &["sideways", "--layout"]);
    assert_eq!(output.status.code(), Some(2), "clap's usage-error status\n{}", describe(&output));
}

#[test]
fn unknown_override_field_is_named() {
    let tmp = tempfile::tempdir().expect("temporary folder");
    let scene = synthetic_scene(tmp.path(), "override");
    let output = handflow(&["eval", "middlebury", "--scene", arg(&scene), "--set", "no_such_field=1", "--json"]);
    check_failure(&output, &["no_such_field"]);
    assert!(output.stdout.is_empty(), "nothing on stdout after an error\n{}", describe(&output));
}

#[test]
fn zero_particles_per_ray_is_rejected() {
    let tmp = tempfile::tempdir().expect("temporary folder");
    let scene = synthetic_scene(tmp.path(), "particles");
    let output = handflow(&["eval", "middlebury", "--scene", arg(&scene), "--particles-per-ray", "0", "--json"]);
    check_failure(&output, &["particles_per_ray"]);

    let output = handflow(&["bench", "flow", "--scene", arg(&scene), "--particles-per-ray", "0", "--repeats", "1"]);
    check_failure(&output, &["particles_per_ray"]);
}

#[test]
fn synthetic_scene_evaluates() {
    // The fixture the error tests rely on is itself a valid scene.
    let tmp = tempfile::tempdir().expect("temporary folder");
    let scene = synthetic_scene(tmp.path(), "valid");
    let output =
        handflow(&["eval", "middlebury", "--scene", arg(&scene), "--particles-per-ray", "2", "--seed", "5", "--json"]);
    let report = json_report(&output);
    check_eval_report(&report);
    assert_eq!(report["seed"].as_u64(), Some(5));
}

/// `handflow render` writes a recording that ingest opens, with truth and masks.
#[test]
fn render_writes_a_recording_with_truth() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("rec");
    let scene = tmp.path().join("scene.toml");
    // A small scene file: the preset's layout, smaller and shorter.
    let mut spec = handflow_ingest::synthetic::SceneSpec::preset("hands-cross").unwrap();
    spec.width = 96;
    spec.height = 72;
    spec.frames = 3;
    std::fs::write(&scene, toml::to_string(&spec).unwrap()).unwrap();
    let output = handflow(&["render", "--scene", arg(&scene), "--out", arg(&out)]);
    assert!(output.status.success(), "{}", describe(&output));
    let rec = handflow_ingest::Recording::open(&out).unwrap();
    assert_eq!(rec.len(), 3);
    assert!(rec.truth_path().is_some());
    assert!(out.join("masks/cam0/000002.png").is_file());

    // A second render into the same folder must not mix with the first.
    let output = handflow(&["render", "--scene", arg(&scene), "--out", arg(&out), "--frames", "2"]);
    check_failure(&output, &["not empty", "--force"]);
    let output = handflow(&["render", "--scene", arg(&scene), "--out", arg(&out), "--frames", "2", "--force"]);
    assert!(output.status.success(), "{}", describe(&output));
    assert_eq!(handflow_ingest::Recording::open(&out).unwrap().len(), 2);
    assert!(!out.join("cam0/000002.png").exists(), "the old frame is gone");
    // --force never deletes a folder that holds no recording.
    let other = tmp.path().join("notes");
    std::fs::create_dir(&other).unwrap();
    std::fs::write(other.join("todo.txt"), "keep me").unwrap();
    let output = handflow(&["render", "--scene", arg(&scene), "--out", arg(&other), "--force"]);
    check_failure(&output, &["no recording"]);
    assert!(other.join("todo.txt").is_file());

    let output = handflow(&["render", "--preset", "ballet", "--out", arg(&tmp.path().join("x"))]);
    check_failure(&output, &["ballet", "signer-3cam"]);
}

/// `handflow eval skin` scores a rendered recording and prints the documented JSON keys;
/// a recording without masks is refused naming the mask file.
#[test]
fn eval_skin_scores_a_rendered_recording() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("rec");
    let r = handflow(&["render", "--preset", "signer-3cam", "--frames", "4", "--out", arg(&out)]);
    assert!(r.status.success(), "{}", describe(&r));
    let r = handflow(&["eval", "skin", "--recording", arg(&out), "--json"]);
    assert!(r.status.success(), "{}", describe(&r));
    let v: serde_json::Value = serde_json::from_slice(&r.stdout).unwrap();
    for key in ["precision", "recall", "precision_generic", "recall_generic"] {
        let x = v[key].as_f64().unwrap_or(-1.0);
        assert!((0.0..=1.0).contains(&x), "{key} = {x}");
    }
    assert!(v["face_detections"].as_u64().unwrap_or(0) >= 1, "the face is found: {v}");
    let objects = v["objects"].as_array().expect("per-object recall");
    let names: Vec<_> = objects.iter().filter_map(|o| o["object"].as_str()).collect();
    assert_eq!(names, ["head", "left_hand", "right_hand"]);
    assert_eq!(v["cameras"].as_array().map(Vec::len), Some(3));
    std::fs::remove_file(out.join("masks/cam2/000003.png")).unwrap();
    check_failure(&handflow(&["eval", "skin", "--recording", arg(&out)]), &["cam2", "000003.png"]);
}

/// `handflow bench flow --recording` runs skin coverage with forwards/backwards on a
/// rendered recording and reports its speed, occupancy and agreement with the masks.
#[test]
fn bench_flow_on_a_recording_reports_frames_per_second() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("rec");
    let r = handflow(&["render", "--preset", "signer-3cam", "--frames", "5", "--out", arg(&out)]);
    assert!(r.status.success(), "{}", describe(&r));
    let r = handflow(&["bench", "flow", "--recording", arg(&out), "--json", "--no-baseline"]);
    assert!(r.status.success(), "{}", describe(&r));
    let v: serde_json::Value = serde_json::from_slice(&r.stdout).unwrap();
    assert_eq!(v["frames"].as_u64(), Some(5), "frame 0 from t+1 alone, 1-3 with both, the last one flushed: {v}");
    assert!(v["frames_per_second"].as_f64().unwrap_or(0.0) > 0.0, "{v}");
    let occupied = v["occupied_share"].as_f64().unwrap_or(-1.0);
    assert!(occupied > 0.005 && occupied < 0.2, "head and hands are a few percent of the view: {v}");
    assert!(v["mask_agreement"].as_f64().unwrap_or(0.0) > 0.8, "{v}");
    assert_eq!(v["reference"].as_str(), Some("cam1"), "the frontal camera");
    assert!(v["speedup_vs_dense"].is_null(), "no baseline asked for");
    // A bad override is named; a recording with one frame is refused.
    check_failure(
        &handflow(&["bench", "flow", "--recording", arg(&out), "--set", "finest_level=7"]),
        &["finest_level"],
    );
    check_failure(&handflow(&["bench", "flow", "--recording", arg(&out), "--frames", "1"]), &["at least 2 frames"]);
}

/// `handflow track` writes one JSON object per frame with the documented schema; `eval
/// tracks` scores it (against a reference also frame by frame, and names a malformed line);
/// `overlay` draws it; `--csv` has a header.
#[test]
fn track_writes_json_lines_that_eval_and_overlay_read() {
    let tmp = tempfile::tempdir().unwrap();
    let rec = tmp.path().join("rec");
    let r = handflow(&["render", "--preset", "signer-3cam", "--frames", "8", "--out", arg(&rec)]);
    assert!(r.status.success(), "{}", describe(&r));
    let tracks = tmp.path().join("tracks.jsonl");
    let r = handflow(&["track", "--recording", arg(&rec), "--out", arg(&tracks)]);
    assert!(r.status.success(), "{}", describe(&r));
    let text = std::fs::read_to_string(&tracks).unwrap();
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(lines.len(), 8, "every frame, the first included");
    for (i, line) in lines.iter().enumerate() {
        let v: serde_json::Value = serde_json::from_str(line).unwrap();
        assert_eq!(v["frame"].as_u64(), Some(i as u64));
        assert!((v["t"].as_f64().unwrap() - i as f64 / 30.0).abs() < 1e-5, "timestamps of frames.csv");
        let objects = v["objects"].as_object().unwrap();
        assert_eq!(objects.keys().collect::<Vec<_>>(), ["head", "left_hand", "right_hand"]);
        for (name, o) in objects {
            assert_eq!(o["pos"].as_array().map(Vec::len), Some(3), "{name}");
            assert_eq!(o["vel"].as_array().map(Vec::len), Some(3), "{name}");
            assert!(o["pos"].as_array().unwrap().iter().all(|x| x.as_f64().is_some_and(f64::is_finite)));
            let c = o["confidence"].as_f64().unwrap();
            assert!((0.0..=1.0).contains(&c), "{name}: {c}");
            assert!(["tracked", "predicted", "lost"].contains(&o["state"].as_str().unwrap()));
        }
    }
    let r = handflow(&["eval", "tracks", "--recording", arg(&rec), "--tracks", arg(&tracks), "--json"]);
    assert!(r.status.success(), "{}", describe(&r));
    let v: serde_json::Value = serde_json::from_slice(&r.stdout).unwrap();
    assert_eq!(v["frames"].as_u64(), Some(8));
    for name in ["head", "left_hand", "right_hand"] {
        for key in ["agreement", "rms_palm_x", "rms_palm_y", "rmse_3d_m"] {
            assert!(v[name][key].as_f64().is_some_and(f64::is_finite), "{name}.{key}: {v}");
        }
    }
    assert!(v["identity_switches"].as_u64().is_some());
    assert!(v["head"]["rmse_3d_m"].as_f64().unwrap() < 0.1, "the head is found: {v}");

    // Against another tracker's reference, frame by frame: a reference that puts the head
    // 3 cm beside the tracks and the hands on them, seen by `cam0` alone in frame 5.
    let frames: Vec<serde_json::Value> = lines
        .iter()
        .map(|line| {
            let v: serde_json::Value = serde_json::from_str(line).unwrap();
            let frame = v["frame"].as_u64().unwrap();
            let at = |name: &str, dx: f64| {
                let p = &v["objects"][name]["pos"];
                let pos = [p[0].as_f64().unwrap() + dx, p[1].as_f64().unwrap(), p[2].as_f64().unwrap()];
                let views =
                    if frame == 5 { serde_json::json!({"cam0": [320.0, 240.0]}) } else { serde_json::json!({}) };
                serde_json::json!({"2d": views, "3d": pos})
            };
            serde_json::json!({"frame": frame, "objects": {
                "head": at("head", 0.03), "left_hand": at("left_hand", 0.0), "right_hand": at("right_hand", 0.0)}})
        })
        .collect();
    let reference = tmp.path().join("reference.json");
    let file = serde_json::json!({"format": "handflow-reference/1", "palm_width_m": 0.085,
        "cameras": ["cam0", "cam1", "cam2"], "frames": frames});
    std::fs::write(&reference, file.to_string()).unwrap();
    let per_frame = tmp.path().join("per-frame.csv");
    let r = handflow(&[
        "eval",
        "tracks",
        "--recording",
        arg(&rec),
        "--tracks",
        arg(&tracks),
        "--reference",
        arg(&reference),
        "--per-frame",
        arg(&per_frame),
    ]);
    assert!(r.status.success(), "{}", describe(&r));
    let rows = std::fs::read_to_string(&per_frame).unwrap();
    let rows: Vec<Vec<&str>> = rows.lines().map(|l| l.split(',').collect()).collect();
    assert_eq!(rows[0], ["frame", "object", "state", "error_3d_m", "views"]);
    assert_eq!(rows.len(), 1 + 8 * 3, "a row per frame and object");
    for row in &rows[1..] {
        let tracked = row[2] != "lost";
        let error: Option<f64> = row[3].parse().ok();
        match (row[1], tracked) {
            ("head", true) => assert!((error.unwrap() - 0.03).abs() < 1e-3, "{row:?}"),
            (_, true) => assert!(error.unwrap() < 1e-3, "{row:?}"),
            (_, false) => assert_eq!(error, None, "a lost estimate is a miss, not a distance: {row:?}"),
        }
        assert_eq!(row[4], if row[0] == "5" { "cam0" } else { "" }, "{row:?}");
    }
    let eval_with = |extra: &[&str]| {
        let mut args = vec!["eval", "tracks", "--recording", arg(&rec), "--tracks", arg(&tracks)];
        args.extend_from_slice(extra);
        handflow(&args)
    };
    check_failure(&eval_with(&["--per-frame", arg(&per_frame)]), &["--reference"]);
    // OpenPose's choice of points applies to an OpenPose folder only.
    check_failure(
        &eval_with(&["--reference", arg(&reference), "--nose-and-wrists"]),
        &["--nose-and-wrists", "OpenPose folder", "reference.json"],
    );

    let overlays = tmp.path().join("overlay");
    let r = handflow(&["overlay", "--recording", arg(&rec), "--tracks", arg(&tracks), "--out", arg(&overlays)]);
    assert!(r.status.success(), "{}", describe(&r));
    assert!(overlays.join("cam2/000007.png").is_file());
    let videos = tmp.path().join("overlay-videos");
    let r =
        handflow(&["overlay", "--recording", arg(&rec), "--tracks", arg(&tracks), "--out", arg(&videos), "--video"]);
    assert!(r.status.success(), "{}", describe(&r));
    for (name, size) in [("cam0", "640x480"), ("cam2", "640x480"), ("montage", "1280x960")] {
        let video = videos.join(format!("{name}.webm"));
        // Read back by ffprobe, another media library than the writer's.
        let Ok(probe) = std::process::Command::new("ffprobe")
            .args(["-v", "error", "-count_frames", "-select_streams", "v:0"])
            .args(["-show_entries", "stream=codec_name,width,height,nb_read_frames", "-of", "csv=p=0"])
            .arg(&video)
            .output()
        else {
            assert!(std::env::var_os("HANDFLOW_REQUIRE_FFMPEG").is_none(), "ffprobe is not installed");
            eprintln!("skipped reading the overlay videos back: ffprobe is not installed");
            break;
        };
        let fields = String::from_utf8_lossy(&probe.stdout).trim().to_string();
        let (w, h) = size.split_once('x').unwrap();
        assert_eq!(fields, format!("vp8,{w},{h},8"), "{}: eight frames of {size}", video.display());
    }

    let csv = tmp.path().join("tracks.csv");
    let r = handflow(&["track", "--recording", arg(&rec), "--out", arg(&csv), "--csv", "--frames", "4"]);
    assert!(r.status.success(), "{}", describe(&r));
    let text = std::fs::read_to_string(&csv).unwrap();
    assert!(text.starts_with("frame,t,head_x,head_y,head_z,head_vx"));
    assert_eq!(text.lines().count(), 1 + 4, "a header and the four frames");

    let bad = tmp.path().join("bad.jsonl");
    std::fs::write(&bad, format!("{}\n{{\"frame\": 2}}\n", lines[0])).unwrap();
    let r = handflow(&["eval", "tracks", "--recording", arg(&rec), "--tracks", arg(&bad)]);
    check_failure(&r, &["bad.jsonl", "line 2"]);
}

/// Bad input to the tracker commands is named: a missing recording, a recording without
/// truth, a trajectory file for another recording.
#[test]
fn track_commands_name_what_is_wrong() {
    let tmp = tempfile::tempdir().unwrap();
    let missing = tmp.path().join("nowhere");
    check_failure(&handflow(&["track", "--recording", arg(&missing)]), &["nowhere"]);
    let rec = tmp.path().join("rec");
    let r = handflow(&["render", "--preset", "signer-2cam-narrow", "--frames", "3", "--out", arg(&rec)]);
    assert!(r.status.success(), "{}", describe(&r));
    let tracks = tmp.path().join("t.jsonl");
    let r = handflow(&["track", "--recording", arg(&rec), "--out", arg(&tracks)]);
    assert!(r.status.success(), "{}", describe(&r));
    // A trajectory frame the recording's truth does not have.
    let text = std::fs::read_to_string(&tracks).unwrap();
    let shifted = text.replacen("\"frame\":1,", "\"frame\":99,", 1);
    let other = tmp.path().join("other.jsonl");
    std::fs::write(&other, shifted).unwrap();
    check_failure(&handflow(&["eval", "tracks", "--recording", arg(&rec), "--tracks", arg(&other)]), &["frame 99"]);
    std::fs::remove_file(rec.join("truth.json")).unwrap();
    check_failure(&handflow(&["eval", "tracks", "--recording", arg(&rec), "--tracks", arg(&tracks)]), &["truth.json"]);
    check_failure(&handflow(&["track", "--recording", arg(&rec), "--frames", "1"]), &["at least 2 frames"]);
}
