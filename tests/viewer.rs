//! The live viewer in a real browser: a replay through the four processes, the page opened
//! in headless Chromium over its DevTools protocol; samples arrive, the head and hand markers
//! move with the trajectories the publisher writes, thumbnails come for every camera, the page
//! reconnects after the publisher is killed and restarted, and a page of another origin cannot
//! open the viewer's WebSockets. And a replay with the viewer on (the demo) writes what
//! `handflow track` writes.

#![allow(clippy::unwrap_used)]

use std::io::{Read, Write};
use std::net::TcpListener;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use handflow_e2e::browser::{chromium_binary, http_get, Browser};
use handflow_e2e::{
    binaries_dir, exit_within, in_own_group, kill_group, pids_of, render_preset, track_with_cli, unique_prefix,
};
use serde_json::Value;
use tungstenite::client::IntoClientRequest;

/// Colours of head, left hand and right hand, as the page draws them.
const COLOURS: [(&str, [u64; 3]); 3] =
    [("head", [255, 220, 0]), ("left_hand", [0, 230, 80]), ("right_hand", [255, 40, 40])];

/// The page's state, the canvas pixel under each marker and the thumbnails' widths.
const STATE: &str = r"(() => {
  const v = window.handflowViewer;
  if (!v) return null;
  const s = v.state();
  const c = v.canvas, ctx = c.getContext('2d'), dpr = c.width / c.clientWidth;
  s.pixels = {};
  for (const [name, m] of Object.entries(s.markers || {})) {
    if (!m.screen) continue;
    const d = ctx.getImageData(Math.round(m.screen[0] * dpr), Math.round(m.screen[1] * dpr), 1, 1).data;
    s.pixels[name] = [d[0], d[1], d[2]];
  }
  s.thumbWidths = [0, 1, 2].map(i => { const e = document.getElementById('thumb-' + i); return e ? e.naturalWidth : 0; });
  return s;
})()";

fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

fn chromium_or_skip() -> Option<std::path::PathBuf> {
    let found = chromium_binary();
    if found.is_none() {
        assert!(
            std::env::var_os("HANDFLOW_REQUIRE_CHROMIUM").is_none(),
            "HANDFLOW_REQUIRE_CHROMIUM is set but no Chromium was found (apt-get install chromium)"
        );
        eprintln!("skipped: no `chromium` on the path (apt-get install chromium, or set HANDFLOW_CHROMIUM)");
    }
    found
}

/// A running `handflow run`, stopped (SIGINT, as Ctrl-C) however the test ends: a failed
/// assertion must not leave a looping pipeline behind.
struct RunningPipeline(Child);

impl Drop for RunningPipeline {
    fn drop(&mut self) {
        let child = &mut self.0;
        let _ = nix::sys::signal::kill(nix::unistd::Pid::from_raw(child.id() as i32), nix::sys::signal::Signal::SIGINT);
        let started = Instant::now();
        while matches!(child.try_wait(), Ok(None)) {
            if started.elapsed() > Duration::from_secs(30) {
                kill_group(child);
                break;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }
}

/// `handflow run` on `rec`, looped at the recorded pace, with the viewer on `port`.
fn start_pipeline(rec: &Path, out: &Path, prefix: &str, port: u16, log: &Path) -> RunningPipeline {
    let child = in_own_group(&mut Command::new(binaries_dir().join("handflow")))
        .args(["run", "--loop", "--pace", "recorded", "--services", prefix, "--viewer"])
        .arg(format!("127.0.0.1:{port}"))
        .arg("--recording")
        .arg(rec)
        .arg("--out")
        .arg(out)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(log).unwrap())
        .spawn()
        .unwrap();
    RunningPipeline(child)
}

/// Records of the trajectory file written so far.
fn records(path: &Path) -> Vec<Value> {
    std::fs::read_to_string(path).unwrap_or_default().lines().filter_map(|l| serde_json::from_str(l).ok()).collect()
}

fn samples(state: &Value) -> u64 {
    state["samples"].as_u64().unwrap_or(0)
}

/// Every object's marker is drawn, on screen.
fn all_markers_on_screen(state: &Value) -> bool {
    COLOURS.iter().all(|(name, _)| state["markers"][name]["screen"].is_array())
}

/// A page of another origin (this server's) that tries to open the viewer's WebSocket and
/// says what happened in `window.result`.
fn serve_foreign_page(viewer_port: u16) -> u16 {
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let port = listener.local_addr().unwrap().port();
    let page = format!(
        "<!doctype html><script>window.result = null;\
         const ws = new WebSocket('ws://127.0.0.1:{viewer_port}/ws/trajectories');\
         ws.onopen = () => {{ window.result = 'open'; }};\
         ws.onmessage = () => {{ window.result = 'message'; }};\
         ws.onclose = e => {{ window.result = window.result || ('closed ' + e.code); }};</script>"
    );
    std::thread::spawn(move || {
        for mut stream in listener.incoming().map_while(Result::ok) {
            let mut buf = [0u8; 4096];
            let _ = stream.read(&mut buf);
            let response = format!(
                "HTTP/1.1 200 OK\r\nContent-Type: text/html\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{page}",
                page.len()
            );
            let _ = stream.write_all(response.as_bytes());
        }
    });
    port
}

#[test]
fn the_viewer_follows_a_replay_in_a_real_browser_reconnects_after_a_restart_and_refuses_other_origins() {
    let Some(chromium) = chromium_or_skip() else { return };
    let dir = tempfile::tempdir().unwrap();
    let rec = render_preset(dir.path(), "signer-3cam", 60, Some((320, 240)));
    let out = dir.path().join("trajectories.jsonl");
    let log = dir.path().join("run.log");
    let prefix = unique_prefix("viewer");
    let port = free_port();
    let authority = format!("127.0.0.1:{port}");
    let run = start_pipeline(&rec, &out, &prefix, port, &log);
    let started = Instant::now();
    while !matches!(http_get(&authority, "/api/status", &[]), Ok((200, _))) {
        assert!(
            started.elapsed() < Duration::from_secs(60),
            "the viewer never answered on {authority}:\n{}",
            std::fs::read_to_string(&log).unwrap_or_default()
        );
        std::thread::sleep(Duration::from_millis(100));
    }

    // Outside a browser: a foreign origin is refused; a client without one gets samples.
    let url = format!("ws://{authority}/ws/trajectories");
    let mut foreign = url.as_str().into_client_request().unwrap();
    foreign.headers_mut().insert("Origin", "http://evil.example".parse().unwrap());
    match tungstenite::connect(foreign) {
        Err(tungstenite::Error::Http(response)) => assert_eq!(response.status(), 403),
        other => panic!("a WebSocket from another origin was not refused: {:?}", other.map(|_| ())),
    }
    let (mut socket, _) = tungstenite::connect(url.as_str()).unwrap();
    let message = socket.read().unwrap();
    let first: Value = serde_json::from_str(message.to_text().unwrap()).unwrap();
    assert!(first["type"] == "sample" || first["type"] == "end", "{first}");
    drop(socket);
    let (status, _) = http_get(&authority, "/", &[("Host", "evil.example")]).unwrap();
    assert_eq!(status, 403, "a page asked for under another host name (DNS rebinding) is refused");

    let mut browser = Browser::start(&chromium, 1280, 800);
    browser.navigate(&format!("http://{authority}/"));
    let first = browser.wait_for(STATE, Duration::from_secs(90), |s| {
        samples(s) >= 3 && s["rigCameras"] == 3 && all_markers_on_screen(s)
    });
    let second = browser.wait_for(STATE, Duration::from_secs(90), |s| {
        samples(s) >= samples(&first) + 10
            && all_markers_on_screen(s)
            && s["thumbWidths"].as_array().is_some_and(|w| w.iter().all(|w| w.as_u64() > Some(0)))
    });
    assert_eq!(second["connected"], true);
    assert_eq!(second["statusOk"], true, "{}", second["status"]);
    for stage in second["status"]["stages"].as_array().unwrap() {
        assert_eq!(stage["alive"], true, "stage health: {stage}");
    }
    let mut cameras: Vec<u64> =
        second["thumbnailCameras"].as_array().unwrap().iter().filter_map(Value::as_u64).collect();
    cameras.sort_unstable();
    assert_eq!(cameras, [0, 1, 2], "a thumbnail from every camera");

    // The markers are the published trajectories, drawn where the page says, and they move.
    let written = records(&out);
    for (name, colour) in COLOURS {
        let marker = &second["markers"][name];
        let frame = marker["frame"].as_u64().unwrap();
        let pos = marker["pos"].clone();
        assert!(
            written.iter().any(|r| r["frame"] == frame && r["objects"][name]["pos"] == pos),
            "{name} at frame {frame} is drawn at {pos}, which the trajectory file does not hold"
        );
        assert_eq!(second["pixels"][name], serde_json::json!(colour), "the canvas under the {name} marker");
    }
    let moved = |name: &str| {
        let (a, b) = (&first["markers"][name]["screen"], &second["markers"][name]["screen"]);
        let d = |i: usize| a[i].as_f64().unwrap() - b[i].as_f64().unwrap();
        d(0).hypot(d(1))
    };
    assert!(
        moved("left_hand").max(moved("right_hand")) > 2.0,
        "the hands' markers stay put: {} / {}",
        first["markers"],
        second["markers"]
    );

    let shot = browser.screenshot();
    let image = image::load_from_memory(&shot).unwrap().to_rgb8();
    assert_eq!((image.width(), image.height()), (1280, 800));
    let screenshot = Path::new(env!("CARGO_TARGET_TMPDIR")).join("viewer.png");
    std::fs::write(&screenshot, &shot).unwrap();
    eprintln!("screenshot of the viewer: {}", screenshot.display());

    // The publisher dies and the launcher restarts it: the page reconnects by itself.
    let before: Vec<i32> = pids_of("handflow-publish", &prefix);
    assert_eq!(before.len(), 1, "one publisher");
    nix::sys::signal::kill(nix::unistd::Pid::from_raw(before[0]), nix::sys::signal::Signal::SIGKILL).unwrap();
    let killed_at = browser.evaluate(STATE);
    let started = Instant::now();
    while pids_of("handflow-publish", &prefix).iter().all(|p| before.contains(p)) {
        assert!(started.elapsed() < Duration::from_secs(30), "the launcher did not restart the publisher");
        std::thread::sleep(Duration::from_millis(50));
    }
    let resumed = browser
        .wait_for(STATE, Duration::from_secs(90), |s| s["connected"] == true && samples(s) >= samples(&killed_at) + 10);
    assert!(all_markers_on_screen(&resumed), "{}", resumed["markers"]);

    // A page of another origin cannot open the viewer's WebSocket.
    let foreign_port = serve_foreign_page(port);
    browser.navigate(&format!("http://127.0.0.1:{foreign_port}/"));
    let result = browser.wait_for("window.result", Duration::from_secs(30), |r| !r.is_null());
    let result = result.as_str().unwrap_or_default().to_owned();
    assert!(result.starts_with("closed"), "a page of another origin opened the viewer's WebSocket: {result}");

    drop(browser);
    drop(run);
}

/// The README's first command runs a replay with the viewer on. The viewer taps the frames
/// too, and a replay that started for it alone lost its first frame sets to a flow stage that
/// came a moment later: the demo's file then varied from run to run. With the viewer on, a
/// replay must still write byte for byte what `handflow track` writes.
#[test]
fn a_replay_with_the_viewer_on_writes_what_track_writes() {
    let dir = tempfile::tempdir().unwrap();
    let rec = render_preset(dir.path(), "signer-3cam", 30, Some((320, 240)));
    let tracked = dir.path().join("tracked.jsonl");
    track_with_cli(&rec, &tracked);
    for run in 0..2 {
        let out = dir.path().join(format!("replayed-{run}.jsonl"));
        let log = dir.path().join(format!("run-{run}.log"));
        let mut child = in_own_group(&mut Command::new(binaries_dir().join("handflow")))
            .args(["run", "--services", &unique_prefix("viewer-replay"), "--viewer"])
            .arg(format!("127.0.0.1:{}", free_port()))
            .arg("--recording")
            .arg(&rec)
            .arg("--out")
            .arg(&out)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(&log).unwrap())
            .spawn()
            .unwrap();
        let status = exit_within(&mut child, Duration::from_secs(300))
            .unwrap_or_else(|| panic!("the run did not end:\n{}", std::fs::read_to_string(&log).unwrap_or_default()));
        assert!(status.success(), "the run failed:\n{}", std::fs::read_to_string(&log).unwrap_or_default());
        assert_eq!(
            std::fs::read_to_string(&out).unwrap(),
            std::fs::read_to_string(&tracked).unwrap(),
            "run {run}: the replay with the viewer on wrote other trajectories than `track`"
        );
    }
}
