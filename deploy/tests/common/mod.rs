//! What the command-line tests share: running the binary and describing what it did.

#![allow(dead_code)]

use std::process::{Command, Output};

/// Runs the binary with `args`, logging at its defaults (the log variables of the caller's
/// environment removed).
pub fn handflow(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_handflow"))
        .args(args)
        .env_remove("HANDFLOW_LOG")
        .env_remove("RUST_LOG")
        .output()
        .expect("run the handflow binary")
}

/// The process's status, stdout and stderr, for assertion messages.
pub fn describe(output: &Output) -> String {
    format!(
        "status {:?}\n--- stdout ---\n{}\n--- stderr ---\n{}",
        output.status,
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    )
}
