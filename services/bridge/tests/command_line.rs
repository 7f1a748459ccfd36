//! The bridge process as the launcher starts it: what it refuses before touching the network
//! or shared memory, with the field at fault named and a failing status (the launcher logs it
//! and restarts or gives up on the bridge, never on the pipeline).

#![allow(clippy::unwrap_used)]

use std::process::Command;

fn bridge(args: &[&str]) -> (bool, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_handflow-bridge"))
        .args(["--services", "test-bridge-command-line"])
        .args(args)
        .env("RUST_LOG", "error")
        .output()
        .unwrap();
    (out.status.success(), String::from_utf8_lossy(&out.stderr).into_owned())
}

#[test]
fn a_bridge_without_an_endpoint_or_with_a_bad_one_refuses_to_start_saying_why() {
    let (ok, log) = bridge(&[]);
    assert!(!ok && log.contains("no Zenoh endpoint"), "{log}");
    let (ok, log) = bridge(&["--listen", "udp/127.0.0.1:7447"]);
    assert!(!ok && log.contains("udp/127.0.0.1:7447") && log.contains("TCP only"), "{log}");
    let (ok, log) = bridge(&["--connect", "tcp/127.0.0.1"]);
    assert!(!ok && log.contains("no port"), "{log}");
}

#[test]
fn a_rig_name_that_would_be_a_wildcard_is_refused() {
    let (ok, log) = bridge(&["--listen", "tcp/127.0.0.1:7447", "--rig", "studio/*"]);
    assert!(!ok && log.contains("--rig") && log.contains("studio/*"), "{log}");
}

#[test]
fn an_unknown_topic_is_refused_naming_the_known_ones() {
    let (ok, log) = bridge(&["--listen", "tcp/127.0.0.1:7447", "--topics", "frames"]);
    assert!(!ok && log.contains("frames") && log.contains("clusters"), "{log}");
}
