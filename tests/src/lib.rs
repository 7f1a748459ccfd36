//! Helpers for handflow's end-to-end tests: where the shared test data lives, and how to
//! make small scenes from it; [`browser`] drives headless Chromium.

pub mod browser;

use std::io::{BufRead, BufReader};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::sync::mpsc::{channel, Receiver};
use std::time::{Duration, Instant};

/// The Middlebury Teddy scene (`../shared/data/middlebury/teddy` from the repository root),
/// or `None` with a message when this clone does not have it.
pub fn teddy_dir() -> Option<PathBuf> {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/middlebury/teddy");
    if dir.join("scene.toml").is_file() {
        Some(dir)
    } else {
        eprintln!("skipped: {} is absent (shared test data not present in this clone)", dir.display());
        None
    }
}

/// Writes a `width x height` crop of Teddy at `(x0, y0)` as a scene folder in `dir`.
pub fn cropped_teddy(dir: &std::path::Path, x0: u32, y0: u32, width: u32, height: u32) -> Option<PathBuf> {
    let teddy = teddy_dir()?;
    let scene = handflow::eval::middlebury::Scene::load(&teddy).expect("Teddy loads");
    let crop = scene.crop(x0, y0, width, height).expect("crop inside the image");
    let out = dir.join("teddy-crop");
    crop.save(&out).expect("cropped scene saves");
    Some(out)
}

/// The folder holding the binaries of this build (`target/<profile>`), where the launcher
/// and the four stage binaries are.
pub fn binaries_dir() -> PathBuf {
    let exe = std::env::current_exe().expect("the test knows its path");
    // target/<profile>/deps/<test> -> target/<profile>
    let dir = exe.parent().and_then(|d| d.parent()).expect("test binary inside target/<profile>/deps").to_path_buf();
    for name in
        ["handflow", "handflow-ingest", "handflow-flow", "handflow-cluster", "handflow-publish", "handflow-bridge"]
    {
        assert!(
            dir.join(name).is_file(),
            "`{}` is missing: run the tests with `cargo test --workspace`, which builds every binary",
            dir.join(name).display()
        );
    }
    dir
}

/// A service prefix no other test (or run on this machine) uses.
pub fn unique_prefix(test: &str) -> String {
    let nanos = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.subsec_nanos());
    format!("test-{test}-{}-{nanos}", std::process::id())
}

/// Renders the first `frames` frames of a built-in scene into `dir/<preset>`, at
/// `width x height` when given (the scene's cameras keep their field of view).
pub fn render_preset(dir: &std::path::Path, preset: &str, frames: u32, size: Option<(u32, u32)>) -> PathBuf {
    use handflow_ingest::synthetic::{write_recording, Renderer, SceneSpec};
    let mut spec = SceneSpec::preset(preset).expect("a built-in preset");
    spec.frames = frames;
    if let Some((w, h)) = size {
        spec.width = w;
        spec.height = h;
    }
    let renderer = Renderer::new(&spec).expect("the preset renders");
    let out = dir.join(preset);
    write_recording(&renderer, &out, frames).expect("the recording writes");
    out
}

/// Runs `handflow track` on `recording`, writing its trajectories to `out`, and checks that it
/// succeeded: the file a replay of the same recording must match.
pub fn track_with_cli(recording: &std::path::Path, out: &std::path::Path) {
    let status = Command::new(binaries_dir().join("handflow"))
        .args(["track", "--recording"])
        .arg(recording)
        .arg("--out")
        .arg(out)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .expect("`handflow track` starts");
    assert!(status.success(), "`handflow track --recording {}` failed", recording.display());
}

/// Process ids of running `binary` processes whose command line holds `needle`.
pub fn pids_of(binary: &str, needle: &str) -> Vec<i32> {
    let Ok(entries) = std::fs::read_dir("/proc") else { return Vec::new() };
    entries
        .filter_map(|e| e.ok())
        .filter_map(|e| e.file_name().to_str().and_then(|n| n.parse::<i32>().ok()))
        .filter(|pid| {
            let cmdline = std::fs::read(format!("/proc/{pid}/cmdline")).unwrap_or_default();
            let args: Vec<&[u8]> = cmdline.split(|b| *b == 0).collect();
            let is_binary = args.first().is_some_and(|a| a.ends_with(binary.as_bytes()));
            is_binary && args.contains(&needle.as_bytes())
        })
        .collect()
}

/// A process whose standard output arrives line by line (a subscriber, `handflow tap`).
pub struct LineProcess {
    /// The process.
    pub child: Child,
    /// Its standard output, one line per message.
    pub lines: Receiver<String>,
}

/// Starts `command` with its standard output read line by line (standard error inherited).
pub fn spawn_lines(mut command: Command) -> LineProcess {
    let mut child = command.stdout(Stdio::piped()).stderr(Stdio::inherit()).spawn().expect("the process starts");
    let stdout = child.stdout.take().expect("piped standard output");
    let (tx, lines) = channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines().map_while(Result::ok) {
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    LineProcess { child, lines }
}

impl LineProcess {
    /// The next line, which must come within `timeout`.
    pub fn next_line(&self, timeout: Duration) -> String {
        self.lines.recv_timeout(timeout).expect("the process prints its next line in time")
    }

    /// Waits (at most `timeout`) for the process to exit successfully; returns the lines it
    /// printed that were not read yet.
    pub fn finish(mut self, timeout: Duration) -> Vec<String> {
        let started = Instant::now();
        let status = loop {
            if let Some(s) = self.child.try_wait().expect("waiting for the process") {
                break s;
            }
            if started.elapsed() > timeout {
                let _ = self.child.kill();
                panic!("the process did not end within {timeout:?}");
            }
            std::thread::sleep(Duration::from_millis(20));
        };
        assert!(status.success(), "the process failed: {status}");
        self.lines.try_iter().collect()
    }
}

/// Waits for `child` to exit; after `timeout` kills it (see [`kill_group`]) and returns
/// `None`.
pub fn exit_within(child: &mut std::process::Child, timeout: std::time::Duration) -> Option<std::process::ExitStatus> {
    let started = std::time::Instant::now();
    loop {
        if let Some(status) = child.try_wait().expect("the child's status") {
            return Some(status);
        }
        if started.elapsed() > timeout {
            kill_group(child);
            return None;
        }
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
}

/// Runs `command` in a process group of its own to its end, its output collected, as
/// [`Command::output`] does, but within `timeout`: after it the whole group is killed and
/// the test fails with the standard error so far.
pub fn output_within(command: &mut Command, timeout: Duration) -> std::process::Output {
    use std::io::Read;
    let mut child =
        in_own_group(command.stdout(Stdio::piped()).stderr(Stdio::piped())).spawn().expect("the process starts");
    let read_all = |mut pipe: Box<dyn Read + Send>| {
        std::thread::spawn(move || {
            let mut bytes = Vec::new();
            let _ = pipe.read_to_end(&mut bytes);
            bytes
        })
    };
    let stdout = read_all(Box::new(child.stdout.take().expect("piped standard output")));
    let stderr = read_all(Box::new(child.stderr.take().expect("piped standard error")));
    let status = exit_within(&mut child, timeout);
    // Every process of the group is gone once it ends or is killed: the pipes close.
    let (stdout, stderr) = (stdout.join().unwrap_or_default(), stderr.join().unwrap_or_default());
    let Some(status) = status else {
        panic!("{command:?} did not end within {timeout:?}:\n{}", String::from_utf8_lossy(&stderr))
    };
    std::process::Output { status, stdout, stderr }
}

/// Makes `command` start a process group of its own: a launcher started so takes its
/// stages along when [`kill_group`] kills it, and nothing is left holding the pipes a
/// test reads to their end.
pub fn in_own_group(command: &mut Command) -> &mut Command {
    std::os::unix::process::CommandExt::process_group(command, 0)
}

/// SIGKILL to `child`'s whole process group when it leads one (started [`in_own_group`]),
/// else to `child` alone; then reaps it.
pub fn kill_group(child: &mut std::process::Child) {
    use nix::sys::signal::{killpg, Signal};
    use nix::unistd::{getpgid, Pid};
    let pid = Pid::from_raw(child.id() as i32);
    if getpgid(Some(pid)) == Ok(pid) {
        let _ = killpg(pid, Signal::SIGKILL);
    } else {
        let _ = child.kill();
    }
    let _ = child.wait();
}
