//! Trajectories across machines: a pipeline whose launcher starts the Zenoh bridge, and
//! remote subscribers that reach it only over Zenoh on loopback (no shared memory with the
//! pipeline): the Rust and Python recognisers and `handflow tap --zenoh`.
//!
//! The Python half needs `pip install eclipse-zenoh==1.10.2`; without it that half is skipped
//! with a message, unless `HANDFLOW_REQUIRE_PYTHON` is set (as `.ci/run` does).

#![allow(clippy::unwrap_used)]

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use handflow_e2e::{
    binaries_dir, exit_within, in_own_group, output_within, pids_of, render_preset, spawn_lines, unique_prefix,
    LineProcess,
};

/// A TCP port on loopback that nothing listens on right now.
fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

/// A replay pipeline of `rec` with the bridge listening on `endpoint` as rig `hands`.
fn write_pipeline(dir: &Path, rec: &Path, prefix: &str, endpoint: &str, pace: &str) -> (PathBuf, PathBuf) {
    let out = dir.join("trajectories.jsonl");
    let pipeline = dir.join("pipeline.toml");
    std::fs::write(
        &pipeline,
        format!(
            "recording = {:?}\nout = {:?}\nservices = {prefix:?}\npace = {pace:?}\n\n[network]\nzenoh = {{ listen = {endpoint:?}, rig = \"hands\" }}\n",
            rec.to_str().unwrap(),
            out.to_str().unwrap(),
        ),
    )
    .unwrap();
    (pipeline, out)
}

/// Frame numbers of the trajectory file, in order.
fn file_frames(out: &Path) -> Vec<u64> {
    std::fs::read_to_string(out)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap()["frame"].as_u64().unwrap())
        .collect()
}

/// Frame numbers in `handflow tap` lines (`trajectories seq S frame F ...`).
fn tap_frames(lines: &[String]) -> Vec<u64> {
    lines
        .iter()
        .filter_map(|l| l.split_once(" frame ").and_then(|(_, rest)| rest.split(' ').next()?.parse().ok()))
        .collect()
}

fn python_has_zenoh() -> bool {
    let ok = Command::new("python3").args(["-c", "import zenoh"]).output().is_ok_and(|o| o.status.success());
    if !ok {
        assert!(
            std::env::var_os("HANDFLOW_REQUIRE_PYTHON").is_none(),
            "python3 cannot import zenoh: pip install eclipse-zenoh==1.10.2"
        );
        eprintln!("skipped the Python subscriber: python3 cannot import zenoh (pip install eclipse-zenoh==1.10.2)");
    }
    ok
}

/// `handflow tap trajectories --zenoh endpoint`, started and subscribed.
fn remote_tap(endpoint: &str, count: Option<usize>) -> LineProcess {
    let mut tap = Command::new(binaries_dir().join("handflow"));
    tap.args(["tap", "trajectories", "--zenoh", endpoint, "--rig", "hands"]).stderr(Stdio::null());
    if let Some(n) = count {
        tap.args(["--count", &n.to_string()]);
    }
    spawn_lines(tap)
}

#[test]
fn remote_subscribers_receive_every_sample_of_a_replay_in_order() {
    let dir = tempfile::tempdir().unwrap();
    let frames = 80u32;
    let rec = render_preset(dir.path(), "hands-cross", frames, None);
    let prefix = unique_prefix("zenoh-every");
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let (pipeline, out) = write_pipeline(dir.path(), &rec, &prefix, &endpoint, "max");

    // The remote side first: it connects (retrying) before the bridge exists.
    let mut rust = Command::new(env!("CARGO_BIN_EXE_sign-recogniser"));
    rust.args(["--zenoh", &endpoint, "--rig", "hands"]);
    let rust = spawn_lines(rust);
    assert!(rust.next_line(Duration::from_secs(30)).starts_with("listening on"));
    let python = python_has_zenoh().then(|| {
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("sign_recogniser.py");
        let mut py = Command::new("python3");
        py.arg(script).args(["--zenoh", &endpoint]);
        let py = spawn_lines(py);
        assert!(py.next_line(Duration::from_secs(30)).starts_with("listening on"));
        py
    });
    // Every sample and the end of the stream.
    let tap = remote_tap(&endpoint, Some(frames as usize + 1));

    let run = output_within(
        Command::new(binaries_dir().join("handflow")).args(["run", "--no-viewer", pipeline.to_str().unwrap()]),
        Duration::from_secs(300),
    );
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));

    let published = file_frames(&out);
    assert_eq!(published, (0..frames as u64).collect::<Vec<_>>());
    let rust_lines = rust.finish(Duration::from_secs(30));
    let summary = rust_lines.last().unwrap();
    let expected = format!("summary: {} samples, frames 0..={}, 0 dropped upstream", published.len(), frames - 1);
    assert!(summary.starts_with(&expected), "{summary}");
    assert!(rust_lines.iter().any(|l| l.ends_with("hands crossed")), "{rust_lines:?}");
    if let Some(py) = python {
        assert_eq!(py.finish(Duration::from_secs(30)), rust_lines, "the JSON and the binary layout say the same");
    }
    let tap_lines = tap.finish(Duration::from_secs(30));
    assert_eq!(tap_frames(&tap_lines), published, "the remote tap sees every sample, in order");
    assert!(tap_lines.last().unwrap().ends_with("END OF STREAM"), "{tap_lines:?}");
}

#[test]
fn killing_the_bridge_leaves_the_local_outputs_whole_and_the_remote_side_resumes() {
    let dir = tempfile::tempdir().unwrap();
    // At the recorded 30 frames per second: long enough to kill the bridge mid-stream.
    let frames = 150u32;
    let rec = render_preset(dir.path(), "hands-cross", frames, None);
    let prefix = unique_prefix("zenoh-kill");
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let (pipeline, out) = write_pipeline(dir.path(), &rec, &prefix, &endpoint, "recorded");
    let tap = remote_tap(&endpoint, None);

    let mut run = in_own_group(&mut Command::new(binaries_dir().join("handflow")))
        .args(["run", "--no-viewer", pipeline.to_str().unwrap()])
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let log = run.stderr.take().unwrap();
    let log = std::thread::spawn(move || std::io::read_to_string(log).unwrap());

    // Kill the bridge once the remote side has seen 20 samples.
    let mut before = Vec::new();
    while before.len() < 20 {
        before.push(tap.next_line(Duration::from_secs(60)));
    }
    let bridges = pids_of("handflow-bridge", &prefix);
    assert_eq!(bridges.len(), 1, "one bridge for the pipeline");
    let killed_at = Instant::now();
    assert!(Command::new("kill").args(["-KILL", &bridges[0].to_string()]).status().unwrap().success());

    // The remote side resumes: a sample of a later frame than any before the kill.
    let last_before = *tap_frames(&before).last().unwrap();
    let mut after = Vec::new();
    let resumed = loop {
        let line = tap.next_line(Duration::from_secs(30));
        after.push(line);
        if tap_frames(&after).last().is_some_and(|&f| f > last_before + 1) {
            break killed_at.elapsed();
        }
    };
    let status = exit_within(&mut run, Duration::from_secs(300));
    let log = log.join().unwrap();
    assert!(status.is_some_and(|s| s.success()), "{status:?}\n{log}");
    assert!(log.contains("stage bridge ended") && log.contains("restarting it"), "{log}");
    // The pipeline never waited for the bridge: every frame, none lost, in the local file.
    assert_eq!(file_frames(&out), (0..frames as u64).collect::<Vec<_>>());
    std::thread::sleep(Duration::from_millis(500));
    let mut tap = tap;
    let _ = tap.child.kill();
    after.extend(tap.lines.try_iter());
    let remote: Vec<u64> = tap_frames(&before).into_iter().chain(tap_frames(&after)).collect();
    assert!(remote.windows(2).all(|w| w[0] < w[1]), "remote samples stay in order: {remote:?}");
    assert_eq!(remote.last(), Some(&(frames as u64 - 1)), "the remote side sees the stream to its end");
    eprintln!(
        "bridge killed after frame {last_before}: remote samples resumed {resumed:?} later; {} of {} frames reached the remote side",
        remote.len(),
        frames
    );
    assert!(resumed < Duration::from_secs(5), "remote samples resumed only {resumed:?} after the kill");
}
