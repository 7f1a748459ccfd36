//! `handflow bench hop`: trajectory samples from a publisher in this process to two
//! subscribers in other processes, in one run: one on this machine through iceoryx2 (the
//! baseline), one behind the Zenoh bridge (a `handflow-bridge` process, then Zenoh over TCP
//! on loopback), as a recogniser on another machine would receive them.
//!
//! Two phases: samples at a steady rate, each stamped just before it is sent, for latency;
//! then a burst sent back to back, for the rate each side sustains (the bridge drops what
//! the network cannot take rather than slow the pipeline, so its side may receive fewer).

use std::io::{BufRead, BufReader};
use std::process::{Child, ChildStdout, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Context, Result};
use handflow_protocol::ipc::{self, Mode, Next, ServiceNames};
use handflow_protocol::messages::{TrajectorySample, END_OF_STREAM, PROTOCOL_VERSION};
use serde::{Deserialize, Serialize};

use crate::commands::launcher::stage_dir;

/// `timestamp_s` of the samples that warm the path up (not measured).
const WARM_UP: f64 = -1.0;
/// `timestamp_s` of the burst's samples.
const BURST: f64 = -2.0;

/// What one receiver measured.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct Received {
    /// Publish-to-receive latencies of the steady phase, microseconds.
    pub latencies_us: Vec<f64>,
    /// Burst samples received.
    pub burst_received: usize,
    /// From the first to the last burst sample received, seconds.
    pub burst_seconds: f64,
}

/// One transport's figures.
#[derive(Clone, Debug, Serialize)]
pub struct HopFigures {
    /// `iceoryx2` or `zenoh`.
    pub transport: String,
    /// Steady-phase samples sent.
    pub sent: usize,
    /// Of which received.
    pub received: usize,
    /// Latency median, microseconds.
    pub p50_us: f64,
    /// Latency 99th percentile, microseconds.
    pub p99_us: f64,
    /// Burst samples sent.
    pub burst_sent: usize,
    /// Of which received.
    pub burst_received: usize,
    /// Burst samples received per second.
    pub burst_per_s: f64,
}

fn percentile(values: &mut [f64], p: f64) -> f64 {
    values.sort_by(f64::total_cmp);
    values.get(((values.len() as f64 - 1.0) * p).round().max(0.0) as usize).copied().unwrap_or(f64::NAN)
}

/// A receiver process and its first line ("ready" once its first sample came).
struct Receiver {
    child: Child,
    stdout: BufReader<ChildStdout>,
}

impl Receiver {
    fn start(exe: &std::path::Path, args: &[&str]) -> Result<Self> {
        let mut child = Command::new(exe)
            .args(["bench", "hop-receiver"])
            .args(args)
            .stdout(Stdio::piped())
            .spawn()
            .with_context(|| format!("starting `{}`", exe.display()))?;
        let stdout = BufReader::new(child.stdout.take().ok_or_else(|| anyhow!("no standard output"))?);
        Ok(Self { child, stdout })
    }

    fn line(&mut self) -> Result<String> {
        let mut line = String::new();
        self.stdout.read_line(&mut line).context("reading a receiver")?;
        Ok(line)
    }

    fn finish(mut self) -> Result<Received> {
        let line = self.line()?;
        let status = self.child.wait()?;
        anyhow::ensure!(status.success(), "a receiver failed ({status})");
        serde_json::from_str(&line).context("reading a receiver's figures")
    }
}

/// Runs `bench hop`: `samples` samples at `rate_hz`, then a burst of `burst`.
pub fn bench_hop(samples: usize, rate_hz: f64, burst: usize) -> Result<Vec<HopFigures>> {
    let dir = stage_dir()?;
    let exe = dir.join("handflow");
    let names = ServiceNames::new(format!("bench-hop-{}", std::process::id()));
    let port = std::net::TcpListener::bind("127.0.0.1:0")?.local_addr()?.port();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let node = ipc::create_node("handflow-bench-hop")?;
    let out = ipc::trajectories_output(&node, &names, Mode::Replay)?;
    let mut bridge = Command::new(dir.join("handflow-bridge"))
        .args(["--services", names.prefix(), "--rig", "bench", "--listen", &endpoint, "--exit-at-end"])
        .stderr(Stdio::null())
        .spawn()
        .context("starting handflow-bridge (build every binary with `cargo build --release`)")?;
    let mut local = Receiver::start(&exe, &["--services", names.prefix()])?;
    let mut remote = Receiver::start(&exe, &["--zenoh", &endpoint])?;
    let result = (|| -> Result<Vec<HopFigures>> {
        if !out.wait_for_subscribers(&node, 2, Duration::from_secs(30)) {
            bail!("the bridge and the local receiver did not subscribe");
        }
        let send = |sequence: u64, timestamp_s: f64, flags: u32| -> Result<()> {
            let sample = TrajectorySample {
                protocol_version: PROTOCOL_VERSION,
                flags,
                sequence,
                frame: sequence,
                timestamp_s,
                published_unix_ns: ipc::unix_now_ns(),
                ..TrajectorySample::default()
            };
            out.publisher.send_copy(sample).context("sending")?;
            out.notify()?;
            Ok(())
        };
        // Warm up until both receivers have had a sample (the remote one once Zenoh has
        // connected and its subscription reached the bridge).
        let (tx, rx) = std::sync::mpsc::channel();
        let waiting = std::thread::scope(|scope| -> Result<u64> {
            for r in [&mut local, &mut remote] {
                let tx = tx.clone();
                scope.spawn(move || {
                    let _ = tx.send(r.line());
                });
            }
            let started = Instant::now();
            let mut sequence = 0u64;
            let mut ready = 0;
            while ready < 2 {
                if started.elapsed() > Duration::from_secs(30) {
                    bail!("the receivers did not get a sample within 30 s");
                }
                send(sequence, WARM_UP, 0)?;
                sequence += 1;
                std::thread::sleep(Duration::from_millis(20));
                ready += rx.try_iter().count();
            }
            Ok(sequence)
        })?;
        let mut sequence = waiting;
        let interval = Duration::from_secs_f64(1.0 / rate_hz);
        for k in 0..samples {
            send(sequence, k as f64, 0)?;
            sequence += 1;
            std::thread::sleep(interval);
        }
        for _ in 0..burst {
            send(sequence, BURST, 0)?;
            sequence += 1;
        }
        // Let the burst drain before the end of the stream.
        std::thread::sleep(Duration::from_millis(500));
        send(sequence, 0.0, END_OF_STREAM)?;
        let mut figures = Vec::new();
        for (transport, receiver) in [("iceoryx2", local), ("zenoh", remote)] {
            let mut r = receiver.finish()?;
            figures.push(HopFigures {
                transport: transport.into(),
                sent: samples,
                received: r.latencies_us.len(),
                p50_us: percentile(&mut r.latencies_us, 0.5),
                p99_us: percentile(&mut r.latencies_us, 0.99),
                burst_sent: burst,
                burst_received: r.burst_received,
                burst_per_s: if r.burst_seconds > 0.0 { r.burst_received as f64 / r.burst_seconds } else { f64::NAN },
            });
        }
        Ok(figures)
    })();
    let _ = bridge.wait();
    result
}

/// The receiving side of `bench hop` (a hidden command): through iceoryx2 on `services`,
/// or through Zenoh at `zenoh`. Prints `ready` at its first sample, then its figures as one
/// JSON line at the end of the stream.
pub fn hop_receiver(services: Option<&str>, zenoh: Option<&str>) -> Result<()> {
    let mut received = Received::default();
    let mut ready = false;
    let (mut burst_first, mut burst_last) = (None, None);
    let mut handle = |s: &TrajectorySample| -> Next {
        let now = ipc::unix_now_ns();
        if !ready {
            ready = true;
            println!("ready");
        }
        if s.is_end_of_stream() {
            return Next::Stop;
        }
        if s.timestamp_s == BURST {
            received.burst_received += 1;
            burst_first.get_or_insert(now);
            burst_last = Some(now);
        } else if s.timestamp_s >= 0.0 {
            received.latencies_us.push(now.saturating_sub(s.published_unix_ns) as f64 * 1e-3);
        }
        Next::Continue
    };
    match (services, zenoh) {
        (Some(prefix), None) => {
            let names = ServiceNames::new(prefix);
            let node = ipc::create_node("handflow-bench-hop-receiver")?;
            let input = ipc::trajectories_input(&node, &names, Mode::Replay)?;
            ipc::serve(&input, Duration::from_millis(100), |s| -> Result<Next> { Ok(handle(s.payload())) })?;
        }
        (None, Some(endpoint)) => {
            let remote = handflow_bridge::remote::RemoteTrajectories::connect(endpoint, Some("bench"))?;
            let started = Instant::now();
            loop {
                match remote.next(Duration::from_millis(100))? {
                    Some(s) if handle(&s) == Next::Stop => break,
                    Some(_) => {}
                    None if started.elapsed() > Duration::from_secs(300) => bail!("no end of stream in 300 s"),
                    None => {}
                }
            }
        }
        _ => bail!("give either --services or --zenoh"),
    }
    if let (Some(first), Some(last)) = (burst_first, burst_last) {
        received.burst_seconds = last.saturating_sub(first) as f64 * 1e-9;
    }
    println!("{}", serde_json::to_string(&received)?);
    Ok(())
}
