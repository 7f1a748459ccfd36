//! The `handflow-cluster` binary refuses bad arguments with a message naming them.

#![allow(clippy::unwrap_used)]

use std::process::Command;

#[test]
fn an_unknown_mode_is_named() {
    let out = Command::new(env!("CARGO_BIN_EXE_handflow-cluster")).args(["--mode", "fast"]).output().unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("unknown delivery mode `fast`"), "{err}");
}
