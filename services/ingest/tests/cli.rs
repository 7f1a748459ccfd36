//! The `handflow-ingest` binary refuses what it cannot replay with a message naming it.

#![allow(clippy::unwrap_used)]

use std::process::Command;

fn ingest(args: &[&str]) -> (bool, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_handflow-ingest")).args(args).output().unwrap();
    (out.status.success(), String::from_utf8_lossy(&out.stderr).into_owned())
}

#[test]
fn without_a_source_it_says_what_to_give() {
    let (ok, err) = ingest(&["--services", "ingest-cli-test-1"]);
    assert!(!ok);
    assert!(err.contains("--recording") && err.contains("--preset"), "{err}");
}

#[test]
fn a_missing_recording_and_an_unknown_preset_are_named() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("no-such-recording");
    let (ok, err) = ingest(&["--recording", missing.to_str().unwrap(), "--services", "ingest-cli-test-2"]);
    assert!(!ok);
    assert!(err.contains("no-such-recording"), "{err}");
    let (ok, err) = ingest(&["--preset", "juggler", "--services", "ingest-cli-test-3"]);
    assert!(!ok);
    assert!(err.contains("`juggler`"), "{err}");
}

#[test]
fn an_unknown_mode_is_refused_before_anything_starts() {
    let (ok, err) = ingest(&["--preset", "signer-3cam", "--mode", "fast"]);
    assert!(!ok);
    assert!(err.contains("fast"), "{err}");
}
