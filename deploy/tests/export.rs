//! `handflow export` and `handflow track --format`: TRC, C3D and CSV, each read back by a
//! reader that shares no code with the writer (OpenSim's TRC layout and Python's csv module
//! in `tests/readers/read_exports.py`, the `c3d` package from PyPI, and c3dio in Rust).
//! Without python3 and `c3d` the Python half is skipped with a message, unless
//! `HANDFLOW_REQUIRE_PYTHON` is set (as `.ci/run` does).

#![allow(clippy::unwrap_used)]

mod common;

use std::collections::BTreeMap;
use std::path::Path;
use std::process::Command;

use common::{describe, handflow};
use handflow_publish::{ObjectSample, TrackState, TrajectoryRecord};
use serde_json::Value;

fn arg(path: &Path) -> &str {
    path.to_str().unwrap()
}

fn python_has_c3d() -> bool {
    let ok = Command::new("python3").args(["-c", "import c3d"]).output().is_ok_and(|o| o.status.success());
    if !ok {
        assert!(
            std::env::var_os("HANDFLOW_REQUIRE_PYTHON").is_none(),
            "python3 cannot import c3d: pip install c3d==0.6.0"
        );
        eprintln!("skipped the Python readers: python3 cannot import c3d (pip install c3d==0.6.0)");
    }
    ok
}

/// What the independent readers make of the files given (`--trc FILE` ...).
fn read_back(files: &[(&str, &Path)]) -> Value {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/readers/read_exports.py");
    let mut command = Command::new("python3");
    command.arg(script);
    for (flag, path) in files {
        command.arg(format!("--{flag}")).arg(path);
    }
    let output = command.output().unwrap();
    assert!(output.status.success(), "{}", describe(&output));
    serde_json::from_slice(&output.stdout).unwrap()
}

/// Records at 25 fps from frame 10: frame 12 skipped, the left hand lost at frame 13, the
/// right hand predicted throughout.
fn records() -> Vec<TrajectoryRecord> {
    [10u64, 11, 13, 14]
        .iter()
        .map(|&frame| {
            let t = frame as f64 / 25.0;
            let object =
                |pos: [f64; 3], confidence, state| ObjectSample { pos, vel: [0.1, 0.2, 0.3], confidence, state };
            let left_state = if frame == 13 { TrackState::Lost } else { TrackState::Tracked };
            let objects = BTreeMap::from([
                ("head".to_string(), object([0.01 * frame as f64, 1.6, 0.2], 1.0, TrackState::Tracked)),
                ("left_hand".to_string(), object([0.3, 1.1, -0.02 * frame as f64], 0.75, left_state)),
                ("right_hand".to_string(), object([-0.3, 1.2, 0.4], 0.5, TrackState::Predicted)),
            ]);
            TrajectoryRecord { frame, t, objects, dropped_frames: 0, missing_views: 0 }
        })
        .collect()
}

fn write_jsonl(path: &Path, records: &[TrajectoryRecord]) {
    let text: String = records.iter().map(|r| serde_json::to_string(r).unwrap() + "\n").collect();
    std::fs::write(path, text).unwrap();
}

fn close(a: f64, b: f64) -> bool {
    (a - b).abs() < 1e-5
}

#[test]
fn exports_are_read_back_by_independent_readers_frame_for_frame() {
    let tmp = tempfile::tempdir().unwrap();
    let tracks = tmp.path().join("take.jsonl");
    let records = records();
    write_jsonl(&tracks, &records);
    let (trc, c3d, csv) = (tmp.path().join("take.trc"), tmp.path().join("take.c3d"), tmp.path().join("take.csv"));
    for out in [&trc, &c3d] {
        let r = handflow(&["export", "--tracks", arg(&tracks), "--out", arg(out)]);
        assert!(r.status.success(), "{}", describe(&r));
    }
    let r = handflow(&["export", "--tracks", arg(&tracks), "--format", "csv", "--out", arg(&csv)]);
    assert!(r.status.success(), "{}", describe(&r));

    // c3dio, a Rust C3D library.
    let parsed = c3dio::C3d::load_path(c3d.clone()).expect("c3dio reads the export");
    assert_eq!(parsed.points.labels, ["Head", "LHand", "RHand"]);
    assert_eq!(parsed.points.size(), (5, 3));
    assert!(close(f64::from(parsed.points[(4, 0)].point[0]), 0.14));

    if !python_has_c3d() {
        return;
    }
    let back = read_back(&[("trc", &trc), ("c3d", &c3d), ("csv", &csv)]);
    let marker_of = |label: &str| match label {
        "head" => "Head",
        "left_hand" => "LHand",
        _ => "RHand",
    };

    let t = &back["trc"];
    assert_eq!((t["rate"].as_f64(), t["camera_rate"].as_f64()), (Some(25.0), Some(25.0)));
    assert_eq!((t["frames_declared"].as_u64(), t["markers_declared"].as_u64()), (Some(5), Some(3)));
    assert_eq!((t["units"].as_str(), t["first_frame"].as_u64()), (Some("m"), Some(10)));
    assert_eq!(t["names"], serde_json::json!(["Head", "LHand", "RHand"]));
    let frames = t["frames"].as_array().unwrap();
    assert_eq!(frames.len(), 5, "frames 10 to 14, the skipped one blank");
    assert!(frames[2]["markers"].as_object().unwrap().values().all(Value::is_null), "{}", frames[2]);
    assert!(frames[3]["markers"]["LHand"].is_null(), "lost at frame 13");

    let c = &back["c3d"];
    assert_eq!((c["rate"].as_f64(), c["units"].as_str()), (Some(25.0), Some("m")));
    assert_eq!(c["labels"], serde_json::json!(["Head", "LHand", "RHand"]));
    assert!(c["scale"].as_f64().unwrap() < 0.0, "float data");
    let c_frames = c["frames"].as_array().unwrap();
    assert_eq!(c_frames.len(), 5);
    assert!(c_frames[2]["markers"].as_object().unwrap().values().all(|m| m["position"].is_null()));
    assert!(c_frames[3]["markers"]["LHand"]["position"].is_null());

    for record in &records {
        let row = (record.frame - 10) as usize;
        let trc_row = &frames[row];
        assert_eq!(trc_row["frame"].as_u64(), Some(record.frame));
        assert!(close(trc_row["time"].as_f64().unwrap(), record.t));
        for (label, o) in &record.objects {
            let marker = marker_of(label);
            let (in_trc, in_c3d) = (&trc_row["markers"][marker], &c_frames[row]["markers"][marker]);
            if o.state == TrackState::Lost {
                assert!(in_trc.is_null() && in_c3d["position"].is_null(), "frame {} {label}", record.frame);
                continue;
            }
            for axis in 0..3 {
                assert!(close(in_trc[axis].as_f64().unwrap(), o.pos[axis]), "TRC frame {} {label}", record.frame);
                assert!(
                    close(in_c3d["position"][axis].as_f64().unwrap(), o.pos[axis]),
                    "C3D frame {} {label}",
                    record.frame
                );
            }
            // Residual: (1 - confidence) x 0.1 m.
            let residual = in_c3d["residual"].as_f64().unwrap();
            assert!((residual - (1.0 - o.confidence) * 0.1).abs() < 1e-3, "{label}: residual {residual}");
        }
    }

    let rows = back["csv"]["rows"].as_array().unwrap();
    assert_eq!(rows.len(), records.len(), "CSV: one line per record, none filled in");
    assert_eq!(back["csv"]["columns"].as_array().unwrap().len(), 2 + 3 * 8);
    for (row, record) in rows.iter().zip(&records) {
        assert_eq!(row["frame"].as_str().unwrap().parse::<u64>().unwrap(), record.frame);
        let o = &record.objects["left_hand"];
        assert!(close(row["left_hand_z"].as_str().unwrap().parse().unwrap(), o.pos[2]));
        assert!(close(row["left_hand_vy"].as_str().unwrap().parse().unwrap(), o.vel[1]));
        let state = serde_json::to_value(o.state).unwrap();
        assert_eq!(row["left_hand_state"].as_str(), state.as_str());
    }
}

/// `track --format trc|c3d` writes what `export` makes of `track`'s JSON Lines, byte for
/// byte (the same tracker, seed and records).
#[test]
fn track_writes_trc_and_c3d_directly() {
    let tmp = tempfile::tempdir().unwrap();
    let rec = tmp.path().join("rec");
    let r = handflow(&["render", "--preset", "signer-3cam", "--frames", "6", "--out", arg(&rec)]);
    assert!(r.status.success(), "{}", describe(&r));
    let tracks = tmp.path().join("tracks.jsonl");
    let r = handflow(&["track", "--recording", arg(&rec), "--out", arg(&tracks)]);
    assert!(r.status.success(), "{}", describe(&r));
    for format in ["trc", "c3d"] {
        let direct = tmp.path().join(format!("direct.{format}"));
        let r = handflow(&["track", "--recording", arg(&rec), "--format", format, "--out", arg(&direct)]);
        assert!(r.status.success(), "{}", describe(&r));
        let exported = tmp.path().join(format!("exported.{format}"));
        let r = handflow(&["export", "--tracks", arg(&tracks), "--out", arg(&exported)]);
        assert!(r.status.success(), "{}", describe(&r));
        let (a, b) = (std::fs::read(&direct).unwrap(), std::fs::read(&exported).unwrap());
        if format == "trc" {
            // The first line names the file.
            let body =
                |bytes: &[u8]| String::from_utf8(bytes.to_vec()).unwrap().split_once('\n').unwrap().1.to_string();
            assert_eq!(body(&a), body(&b));
        } else {
            assert_eq!(a, b, "C3D");
        }
    }
}

/// Bad requests are refused naming what is wrong.
#[test]
fn export_names_what_is_wrong() {
    let tmp = tempfile::tempdir().unwrap();
    let tracks = tmp.path().join("one.jsonl");
    write_jsonl(&tracks, &records()[..1]);
    let r = handflow(&["export", "--tracks", arg(&tracks), "--format", "trc"]);
    assert!(!r.status.success());
    assert!(String::from_utf8_lossy(&r.stderr).contains("--rate"), "{}", describe(&r));
    let r = handflow(&["export", "--tracks", arg(&tracks), "--format", "c3d"]);
    assert!(String::from_utf8_lossy(&r.stderr).contains("--out"), "{}", describe(&r));
    let missing = tmp.path().join("none.jsonl");
    let r = handflow(&["export", "--tracks", arg(&missing), "--format", "csv"]);
    assert!(String::from_utf8_lossy(&r.stderr).contains("none.jsonl"), "{}", describe(&r));
    let r = handflow(&["export", "--tracks", arg(&tracks), "--format", "trc", "--rate", "30"]);
    assert!(r.status.success(), "{}", describe(&r));
    assert!(String::from_utf8_lossy(&r.stdout).starts_with("PathFileType\t4"));
}
