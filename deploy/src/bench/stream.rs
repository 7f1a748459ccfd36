//! Benchmarks of the streaming service.
//!
//! `handflow bench ipc`: one hop of a frame set through iceoryx2, from a publisher in this
//! process to a subscriber in a child process woken by its WaitSet, for frame sets of
//! growing size, against copying the same bytes once (the baseline, measured in the same
//! run). Zero-copy means the hop does not grow with the frame set; the copy does.
//!
//! `handflow bench pipeline`: the live pipeline (four processes) on a recording replayed at
//! its recorded rate, looped for a while; a subscriber in this process measures
//! glass-to-trajectory latency (from the moment ingest takes a frame set to the moment its
//! trajectory sample is published) and the sustained rate of trajectory samples.

use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use handflow_protocol::ipc::{self, Mode, Next, ServiceNames};
use handflow_protocol::messages::{FrameHeader, END_OF_STREAM, PIXEL_FORMAT_RGB8, PROTOCOL_VERSION};
use serde::Serialize;

use crate::commands::launcher::{run_pipeline, stage_dir, Pipeline};

/// Percentile `p` (0..1) of `values` (sorted in place).
pub(crate) fn percentile(values: &mut [f64], p: f64) -> f64 {
    values.sort_by(f64::total_cmp);
    values.get(((values.len() as f64 - 1.0) * p).round().max(0.0) as usize).copied().unwrap_or(f64::NAN)
}

/// One frame-set size of `bench ipc`.
#[derive(Clone, Debug, Serialize)]
pub struct HopResult {
    /// Views of 640x480 RGB8 in the frame set.
    pub views: u32,
    /// Bytes per frame set.
    pub bytes: usize,
    /// Samples measured.
    pub samples: usize,
    /// Publish-to-receive latency across processes, median, microseconds.
    pub hop_p50_us: f64,
    /// Its 99th percentile, microseconds.
    pub hop_p99_us: f64,
    /// Copying the same bytes once (memcpy into another buffer), median, microseconds.
    pub copy_p50_us: f64,
    /// `copy_p50_us / hop_p50_us`.
    pub copy_over_hop: f64,
}

/// Frame-set sizes measured: one, three (the signer-3cam rig) and twelve VGA views.
const HOP_VIEWS: [u32; 3] = [1, 3, 12];
const VGA: (u32, u32) = (640, 480);

/// Runs `bench ipc` with `samples` samples per size.
pub fn bench_ipc(samples: usize) -> Result<Vec<HopResult>> {
    let exe = stage_dir()?.join("handflow");
    let mut results = Vec::new();
    for views in HOP_VIEWS {
        let bytes = views as usize * VGA.0 as usize * VGA.1 as usize * 3;
        let vga_views =
            FrameHeader::sizes_of((0..views).map(|_| VGA)).context("more views than a frame set carries")?;
        let names = ServiceNames::new(format!("bench-ipc-{}-{views}", std::process::id()));
        let node = ipc::create_node("handflow-bench-ipc")?;
        let out = ipc::frames_output(&node, &names, Mode::Replay, bytes)?;
        let mut child = Command::new(&exe)
            .args(["bench", "ipc-receiver", "--services", names.prefix(), "--samples", &samples.to_string()])
            .stdout(Stdio::piped())
            .spawn()
            .with_context(|| format!("starting `{}`", exe.display()))?;
        if !out.wait_for_subscribers(&node, 1, Duration::from_secs(30)) {
            let _ = child.kill();
            bail!("the receiving process did not subscribe");
        }
        // Let the receiver reach its WaitSet.
        std::thread::sleep(Duration::from_millis(200));
        for k in 0..=samples as u64 {
            let end = k == samples as u64;
            let len = if end { 0 } else { bytes };
            let mut sample = out.publisher.loan_slice(len).context("loaning")?;
            // Touch every page once, as a decoder writing the frame would.
            for b in sample.payload_mut().iter_mut().step_by(4096) {
                *b = k as u8;
            }
            *sample.user_header_mut() = FrameHeader {
                protocol_version: PROTOCOL_VERSION,
                pixel_format: PIXEL_FORMAT_RGB8,
                sequence: k,
                view_count: if end { 0 } else { views },
                view_sizes: if end { Default::default() } else { vga_views },
                flags: if end { END_OF_STREAM } else { 0 },
                payload_len: len as u64,
                // Last thing before the send: the hop is what is measured, not the filling.
                capture_unix_ns: ipc::unix_now_ns(),
                ..FrameHeader::default()
            };
            sample.send().context("sending")?;
            out.notify()?;
            // 200 frame sets per second: each hop starts with the receiver asleep.
            std::thread::sleep(Duration::from_millis(5));
        }
        let output = child.wait_with_output().context("waiting for the receiver")?;
        anyhow::ensure!(output.status.success(), "the receiving process failed");
        let mut hops: Vec<f64> = serde_json::from_slice(&output.stdout).context("reading the receiver's latencies")?;
        let mut copies = copy_times(bytes, samples.min(200));
        results.push(HopResult {
            views,
            bytes,
            samples: hops.len(),
            hop_p50_us: percentile(&mut hops, 0.5),
            hop_p99_us: percentile(&mut hops, 0.99),
            copy_p50_us: percentile(&mut copies, 0.5),
            copy_over_hop: percentile(&mut copies, 0.5) / percentile(&mut hops, 0.5),
        });
    }
    Ok(results)
}

/// Microseconds to copy `bytes` once into a second buffer, `n` times (rotating over
/// several buffer pairs, so the copies are not all from the cache).
fn copy_times(bytes: usize, n: usize) -> Vec<f64> {
    let pairs = 4;
    let src: Vec<Vec<u8>> = (0..pairs).map(|k| vec![k as u8; bytes]).collect();
    let mut dst: Vec<Vec<u8>> = (0..pairs).map(|_| vec![0u8; bytes]).collect();
    (0..n)
        .map(|k| {
            let started = Instant::now();
            dst[k % pairs].copy_from_slice(&src[k % pairs]);
            let t = started.elapsed().as_secs_f64() * 1e6;
            std::hint::black_box(&dst[k % pairs]);
            t
        })
        .collect()
}

/// The receiving side of `bench ipc` (a hidden command): prints the hop latencies, in
/// microseconds, as a JSON array.
pub fn ipc_receiver(prefix: &str, samples: usize) -> Result<()> {
    let names = ServiceNames::new(prefix);
    let node = ipc::create_node("handflow-bench-ipc-receiver")?;
    let input = ipc::frames_input(&node, &names, Mode::Replay)?;
    let mut hops = Vec::with_capacity(samples);
    ipc::serve(&input, Duration::from_millis(100), |s| -> Result<Next> {
        let received = ipc::unix_now_ns();
        let h = *s.user_header();
        if h.is_end_of_stream() {
            return Ok(Next::Stop);
        }
        h.validate(s.payload().len()).map_err(anyhow::Error::msg)?;
        hops.push(received.saturating_sub(h.capture_unix_ns) as f64 * 1e-3);
        Ok(Next::Continue)
    })?;
    println!("{}", serde_json::to_string(&hops)?);
    Ok(())
}

/// What `bench pipeline` measured.
#[derive(Clone, Debug, Serialize)]
pub struct PipelineResult {
    /// Recording replayed.
    pub recording: String,
    /// Frame rate the frame sets were published at.
    pub input_fps: f64,
    /// Whether ingest preloaded the recording (cameras delivering raw frames) rather than
    /// decoding its images on the path.
    pub preloaded: bool,
    /// Seconds measured (after the warm-up).
    pub seconds: f64,
    /// Trajectory samples per second over the measured time.
    pub output_fps: f64,
    /// Frame sets dropped upstream in the measured time (live mode: latest wins).
    pub dropped: u64,
    /// Glass-to-trajectory latency, median, milliseconds.
    pub latency_p50_ms: f64,
    /// Its 99th percentile, milliseconds.
    pub latency_p99_ms: f64,
    /// The 99th percentile minus one frame interval (the forwards/backwards delay, which
    /// the target is on top of), milliseconds.
    pub latency_p99_beyond_fb_ms: f64,
    /// With the live viewer serving: what its clients received.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub viewer: Option<ViewerLoad>,
}

/// What a viewer client (the page's two WebSockets) received during a run.
#[derive(Clone, Debug, Default, Serialize)]
pub struct ViewerLoad {
    /// The viewer's address.
    pub address: String,
    /// Trajectory messages received.
    pub samples: u64,
    /// Thumbnails received.
    pub thumbnails: u64,
}

/// Reads the viewer at `address` as its page does (both WebSockets, reconnecting) until
/// `stop`; counts what arrives.
fn read_viewer(
    address: std::net::SocketAddr,
    stop: std::sync::Arc<std::sync::atomic::AtomicBool>,
) -> std::thread::JoinHandle<ViewerLoad> {
    use std::sync::atomic::Ordering;
    let reader = |path: &'static str, stop: std::sync::Arc<std::sync::atomic::AtomicBool>| {
        std::thread::spawn(move || {
            let mut received = 0u64;
            while !stop.load(Ordering::Relaxed) {
                let Ok((mut socket, _)) = tungstenite::connect(format!("ws://{address}{path}")) else {
                    std::thread::sleep(Duration::from_millis(100));
                    continue;
                };
                if let tungstenite::stream::MaybeTlsStream::Plain(s) = socket.get_ref() {
                    let _ = s.set_read_timeout(Some(Duration::from_millis(200)));
                }
                while !stop.load(Ordering::Relaxed) {
                    match socket.read() {
                        Ok(m) if m.is_text() || m.is_binary() => received += 1,
                        Ok(_) => {}
                        Err(tungstenite::Error::Io(e))
                            if matches!(e.kind(), std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut) => {}
                        Err(_) => break,
                    }
                }
            }
            received
        })
    };
    let samples = reader("/ws/trajectories", stop.clone());
    let thumbnails = reader("/ws/thumbnails", stop);
    std::thread::spawn(move || ViewerLoad {
        address: address.to_string(),
        samples: samples.join().unwrap_or(0),
        thumbnails: thumbnails.join().unwrap_or(0),
    })
}

/// The live pipeline on `recording` looped at its recorded rate for `frames` frame sets
/// (`preload`: decoded into memory first), under service prefix `prefix`.
pub(crate) fn looped_live(recording: &std::path::Path, frames: u64, preload: bool, prefix: &str) -> Pipeline {
    Pipeline {
        mode: "live".into(),
        recording: Some(recording.to_path_buf()),
        looped: true,
        frames: Some(frames),
        preload,
        services: prefix.to_string(),
        ..Pipeline::default()
    }
}

/// Seconds after the first trajectory sample that are not measured (face detections that
/// adapt the skin models, the first frame's extra passes).
const PIPELINE_WARM_UP_S: f64 = 3.0;

/// Runs the live pipeline on `recording` (looped at its recorded rate; `preload`: decoded
/// into memory first) for `seconds` plus the warm-up and measures its output; with
/// `viewer`, the live viewer serves there and a client reads both its WebSockets.
pub fn bench_pipeline(
    recording: &std::path::Path,
    seconds: f64,
    preload: bool,
    viewer: Option<std::net::SocketAddr>,
) -> Result<PipelineResult> {
    let rec = handflow_ingest::Recording::open(recording)?;
    let fps = rec.frame_rate();
    // One more second of frames: the warm-up counts from the first sample, not the start.
    let frames = ((seconds + PIPELINE_WARM_UP_S + 1.0) * fps).ceil() as u64;
    let prefix = format!("bench-pipeline-{}", std::process::id());
    let names = ServiceNames::new(&prefix);
    let pipeline = Pipeline {
        viewer: crate::commands::launcher::ViewerSettings {
            enabled: viewer.is_some(),
            listen: viewer.map(|a| a.to_string()).unwrap_or_default(),
            ..Default::default()
        },
        ..looped_live(recording, frames, preload, &prefix)
    };
    let stop_reader = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let viewer_reader = viewer.map(|address| read_viewer(address, stop_reader.clone()));
    let node = ipc::create_node("handflow-bench-pipeline")?;
    let input = ipc::trajectories_input(&node, &names, Mode::Live)?;
    let runner = std::thread::spawn(move || run_pipeline(&pipeline));
    let (mut latencies, mut first, mut last) = (Vec::new(), None::<(Instant, u64)>, None::<(Instant, u64, u64)>);
    let mut measure_from = None::<Instant>;
    let mut count = 0u64;
    ipc::serve(&input, Duration::from_millis(100), |s| -> Result<Next> {
        let t = *s.payload();
        if t.is_end_of_stream() {
            return Ok(Next::Stop);
        }
        let now = Instant::now();
        if now < *measure_from.get_or_insert(now + Duration::from_secs_f64(PIPELINE_WARM_UP_S)) {
            return Ok(Next::Continue);
        }
        first.get_or_insert((now, t.dropped_frames));
        count += 1;
        last = Some((now, count, t.dropped_frames));
        latencies.push(t.published_unix_ns.saturating_sub(t.capture_unix_ns) as f64 * 1e-6);
        Ok(Next::Continue)
    })?;
    let report = runner.join().map_err(|_| anyhow::anyhow!("the pipeline thread panicked"))??;
    stop_reader.store(true, std::sync::atomic::Ordering::Relaxed);
    let viewer = viewer_reader.and_then(|r| r.join().ok());
    anyhow::ensure!(report.completed, "the pipeline did not complete");
    let ((t0, d0), (t1, n, d1)) = first.zip(last).context("no trajectory samples after the warm-up")?;
    let measured = (t1 - t0).as_secs_f64();
    let p99 = percentile(&mut latencies, 0.99);
    Ok(PipelineResult {
        recording: recording.display().to_string(),
        input_fps: fps,
        preloaded: preload,
        seconds: measured,
        output_fps: (n - 1) as f64 / measured.max(1e-9),
        dropped: d1 - d0,
        latency_p50_ms: percentile(&mut latencies, 0.5),
        latency_p99_ms: p99,
        latency_p99_beyond_fb_ms: p99 - 1e3 / fps,
        viewer,
    })
}
