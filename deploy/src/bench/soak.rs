//! `handflow bench soak`: the live pipeline on a looped recording for a long time, measured
//! window by window: each stage's resident memory and open file descriptors, the sustained
//! rate of trajectory samples, frames dropped and the latency percentiles. A leak shows as a
//! column that grows from window to window.

use std::path::Path;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use handflow_protocol::ipc::{self, Mode, Next, ServiceNames};
use serde::Serialize;

use super::stream::{looped_live, percentile};
use crate::commands::launcher::{run_pipeline, Pipeline};

/// One stage process's resources at the end of a window.
#[derive(Clone, Debug, Serialize)]
pub struct StageUse {
    /// The stage (`ingest`, `flow`, `cluster`, `publish`).
    pub stage: String,
    /// Resident memory, MiB.
    pub rss_mib: f64,
    /// Open file descriptors.
    pub fds: usize,
}

/// One window of the soak.
#[derive(Clone, Debug, Serialize)]
pub struct SoakWindow {
    /// Minutes since the measurement started, at the window's end.
    pub minute: f64,
    /// Trajectory samples per second in the window.
    pub samples_per_s: f64,
    /// Frame sets dropped upstream in the window (live: latest wins).
    pub dropped: u64,
    /// Glass-to-trajectory latency, median, milliseconds.
    pub latency_p50_ms: f64,
    /// Its 99th percentile, milliseconds.
    pub latency_p99_ms: f64,
    /// Each stage's resources at the window's end.
    pub stages: Vec<StageUse>,
}

/// The stage processes started by this process (the launcher runs in it), by stage name.
fn stage_processes() -> Vec<(String, u32)> {
    let me = std::process::id();
    let mut found = Vec::new();
    let Ok(entries) = std::fs::read_dir("/proc") else { return found };
    for entry in entries.flatten() {
        let Some(pid) = entry.file_name().to_str().and_then(|s| s.parse::<u32>().ok()) else { continue };
        // The parent is the fourth field of `stat`, after the command in parentheses.
        let Ok(stat) = std::fs::read_to_string(format!("/proc/{pid}/stat")) else { continue };
        let parent = stat.rsplit_once(')').and_then(|(_, rest)| rest.split_whitespace().nth(1)?.parse::<u32>().ok());
        if parent != Some(me) {
            continue;
        }
        let Ok(cmdline) = std::fs::read(format!("/proc/{pid}/cmdline")) else { continue };
        let program = cmdline.split(|&b| b == 0).next().unwrap_or_default();
        let name = Path::new(std::str::from_utf8(program).unwrap_or_default())
            .file_name()
            .and_then(|n| n.to_str())
            .unwrap_or_default()
            .to_string();
        if let Some(stage) = name.strip_prefix("handflow-") {
            found.push((stage.to_string(), pid));
        }
    }
    found.sort();
    found
}

/// Resident memory (MiB) and open descriptors of process `pid`.
fn process_use(pid: u32) -> Option<(f64, usize)> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let kib: f64 =
        status.lines().find_map(|l| l.strip_prefix("VmRSS:"))?.trim().trim_end_matches("kB").trim().parse().ok()?;
    let fds = std::fs::read_dir(format!("/proc/{pid}/fd")).ok()?.count();
    Some((kib / 1024.0, fds))
}

/// Where the soaked pipeline writes its trajectories.
pub const SOAK_TRAJECTORIES: &str = "out/soak-trajectories.jsonl";

/// Seconds after the first trajectory sample before the first window starts.
const WARM_UP_S: f64 = 10.0;

/// Runs the live pipeline on `recording` (looped at its recorded rate; `preload`: decoded
/// into memory first) for `minutes` after a warm-up, calling `on_window` at the end of each
/// window of `window_minutes`.
pub fn soak(
    recording: &Path,
    minutes: f64,
    window_minutes: f64,
    preload: bool,
    mut on_window: impl FnMut(&SoakWindow),
) -> Result<Vec<SoakWindow>> {
    let rec = handflow_ingest::Recording::open(recording)?;
    let fps = rec.frame_rate();
    let frames = ((minutes * 60.0 + WARM_UP_S + 5.0) * fps).ceil() as u64;
    let prefix = format!("bench-soak-{}", std::process::id());
    let names = ServiceNames::new(&prefix);
    let pipeline = Pipeline {
        // The publisher writes its file all along, as in service.
        out: Some(SOAK_TRAJECTORIES.into()),
        viewer: crate::commands::launcher::ViewerSettings { enabled: false, ..Default::default() },
        ..looped_live(recording, frames, preload, &prefix)
    };
    let node = ipc::create_node("handflow-bench-soak")?;
    let input = ipc::trajectories_input(&node, &names, Mode::Live)?;
    let runner = std::thread::spawn(move || run_pipeline(&pipeline));
    let window = Duration::from_secs_f64(window_minutes * 60.0);
    let total = Duration::from_secs_f64(minutes * 60.0);
    let mut windows = Vec::new();
    let (mut start, mut window_start) = (None::<Instant>, None::<Instant>);
    let (mut latencies, mut count, mut dropped_at_start, mut last_dropped) = (Vec::new(), 0u64, 0u64, 0u64);
    let mut warm_until = None::<Instant>;
    ipc::serve(&input, Duration::from_millis(100), |s| -> Result<Next> {
        let t = *s.payload();
        if t.is_end_of_stream() {
            return Ok(Next::Stop);
        }
        let now = Instant::now();
        if now < *warm_until.get_or_insert(now + Duration::from_secs_f64(WARM_UP_S)) {
            return Ok(Next::Continue);
        }
        let begun = *start.get_or_insert(now);
        let this_window = *window_start.get_or_insert_with(|| {
            dropped_at_start = t.dropped_frames;
            now
        });
        if now - this_window >= window {
            let stages = stage_processes()
                .into_iter()
                .filter_map(|(stage, pid)| process_use(pid).map(|(rss_mib, fds)| StageUse { stage, rss_mib, fds }))
                .collect();
            let w = SoakWindow {
                minute: (now - begun).as_secs_f64() / 60.0,
                samples_per_s: count as f64 / (now - this_window).as_secs_f64(),
                dropped: last_dropped.saturating_sub(dropped_at_start),
                latency_p50_ms: percentile(&mut latencies, 0.5),
                latency_p99_ms: percentile(&mut latencies, 0.99),
                stages,
            };
            on_window(&w);
            windows.push(w);
            latencies.clear();
            count = 0;
            dropped_at_start = t.dropped_frames;
            window_start = Some(now);
            if now - begun >= total {
                return Ok(Next::Stop);
            }
        }
        count += 1;
        last_dropped = t.dropped_frames;
        latencies.push(t.published_unix_ns.saturating_sub(t.capture_unix_ns) as f64 * 1e-6);
        Ok(Next::Continue)
    })?;
    // The stream ends by itself a few seconds after the last window.
    let report = runner.join().map_err(|_| anyhow::anyhow!("the pipeline thread panicked"))?;
    report.context("the soaked pipeline")?;
    Ok(windows)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn this_process_is_measured_from_proc() {
        let (rss, fds) = process_use(std::process::id()).expect("this process in /proc");
        assert!(rss > 1.0 && fds >= 3, "rss {rss} MiB, {fds} descriptors");
        // No stage started here.
        assert!(stage_processes().is_empty());
    }
}
