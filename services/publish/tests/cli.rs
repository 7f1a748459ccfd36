//! The `handflow-publish` binary names a trajectory file it cannot create.

#![allow(clippy::unwrap_used)]

use std::process::Command;

#[test]
fn an_uncreatable_output_file_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let blocker = dir.path().join("a-file");
    std::fs::write(&blocker, "not a folder").unwrap();
    let out_path = blocker.join("trajectories.jsonl");
    let out = Command::new(env!("CARGO_BIN_EXE_handflow-publish"))
        .args(["--services", "publish-cli-test", "--out", out_path.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("a-file"), "{err}");
}
