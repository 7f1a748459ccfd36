//! The sign recogniser examples, Rust and Python, subscribed to a real pipeline: each
//! receives every trajectory sample and reports the hands crossing.
//!
//! The Python half needs `pip install iceoryx2==0.10.0`; without it that half is skipped
//! with a message, unless `HANDFLOW_REQUIRE_PYTHON` is set (as `.ci/run` does).

#![allow(clippy::unwrap_used)]

use std::path::Path;
use std::process::Command;
use std::time::Duration;

use handflow_e2e::{binaries_dir, output_within, render_preset, spawn_lines, unique_prefix, LineProcess};

/// Starts a subscriber and waits until it listens.
fn start(command: Command) -> LineProcess {
    let process = spawn_lines(command);
    let first = process.next_line(Duration::from_secs(30));
    assert!(first.starts_with("listening on"), "{first}");
    process
}

fn python_has_iceoryx2() -> bool {
    let ok = Command::new("python3").args(["-c", "import iceoryx2"]).output().is_ok_and(|o| o.status.success());
    if !ok {
        assert!(
            std::env::var_os("HANDFLOW_REQUIRE_PYTHON").is_none(),
            "python3 cannot import iceoryx2: pip install iceoryx2==0.10.0"
        );
        eprintln!("skipped the Python subscriber: python3 cannot import iceoryx2 (pip install iceoryx2==0.10.0)");
    }
    ok
}

#[test]
fn rust_and_python_recognisers_get_every_sample_and_see_the_hands_cross() {
    let dir = tempfile::tempdir().unwrap();
    let frames = 80u32;
    let rec = render_preset(dir.path(), "hands-cross", frames, None);
    let out = dir.path().join("trajectories.jsonl");
    let prefix = unique_prefix("subscribers");

    let mut rust = Command::new(env!("CARGO_BIN_EXE_sign-recogniser"));
    rust.args(["--services", &prefix]);
    let rust_process = start(rust);
    let python = python_has_iceoryx2().then(|| {
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("sign_recogniser.py");
        let mut py = Command::new("python3");
        py.arg(script).args(["--services", &prefix]);
        start(py)
    });

    let run = output_within(
        Command::new(binaries_dir().join("handflow")).args([
            "run",
            "--no-viewer",
            "--recording",
            rec.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--services",
            &prefix,
        ]),
        Duration::from_secs(300),
    );
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));

    let published = std::fs::read_to_string(&out).unwrap().lines().count();
    assert_eq!(published, frames as usize);
    let expected_summary = format!("summary: {published} samples, frames 0..={}, 0 dropped upstream", frames - 1);
    let rust_lines = rust_process.finish(Duration::from_secs(60));
    let summary = rust_lines.last().unwrap();
    assert!(summary.starts_with(&expected_summary), "{summary}");
    assert!(rust_lines.iter().any(|l| l.ends_with("hands crossed")), "{rust_lines:?}");
    if let Some(process) = python {
        let python_lines = process.finish(Duration::from_secs(60));
        assert_eq!(python_lines, rust_lines, "both recognisers report the same");
    }
}
