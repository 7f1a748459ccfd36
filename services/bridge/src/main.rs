//! `handflow-bridge`: forwards a pipeline's trajectory samples (and on request its labelled
//! clusters and particle sets) from shared memory to Zenoh, for subscribers on other
//! machines.
//!
//! One thread per topic reads its service and never waits for the network: messages go to a
//! bounded queue, and when the network cannot take them the oldest are not held back but the
//! new ones dropped and counted. Zenoh itself drops rather than blocks (congestion control
//! `Drop`). So a slow link or a dead remote never slows the pipeline; a bridge that dies
//! is restarted by the launcher, and remote subscribers reconnect by themselves.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{sync_channel, RecvTimeoutError, SyncSender, TrySendError};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Context, Result};
use clap::Parser;
use handflow_bridge::json::{ClusterSetJson, TrajectoryJson};
use handflow_bridge::{check_rig_name, is_loopback, json_key, key, session_config, Topic};
use handflow_protocol::ipc::{self, Mode, Next, ServiceNames};
use handflow_protocol::wire;
use zenoh::bytes::Encoding;
use zenoh::qos::CongestionControl;
use zenoh::Wait;

#[derive(Parser, Debug)]
#[command(name = "handflow-bridge", about = "Forwards a pipeline's trajectories from shared memory to Zenoh")]
struct Args {
    /// Delivery mode of the pipeline (`replay` or `live`): the subscriptions must match it.
    #[arg(long, default_value = "replay")]
    mode: Mode,
    /// Prefix of the pipeline's service names.
    #[arg(long, default_value = ipc::DEFAULT_PREFIX)]
    services: String,
    /// The rig's name in the key expressions, `handflow/<rig>/<topic>`.
    #[arg(long, default_value = "rig")]
    rig: String,
    /// Zenoh endpoint to listen on (repeatable), `tcp/<host>:<port>`.
    #[arg(long)]
    listen: Vec<String>,
    /// Zenoh endpoint to connect to (repeatable): a router, or a subscriber that listens.
    #[arg(long)]
    connect: Vec<String>,
    /// Topics to forward besides `trajectories`: `clusters`, `particles` (comma-separated).
    #[arg(long, value_delimiter = ',')]
    topics: Vec<Topic>,
    /// Exit (status 0) once the end of the stream has been forwarded.
    #[arg(long)]
    exit_at_end: bool,
}

fn main() {
    ipc::init_logging();
    ipc::exit_with(run(Args::parse()))
}

/// Messages waiting for the network, at most: about four seconds of trajectories at 30 fps
/// plus what the other topics add.
const QUEUE: usize = 128;

/// One message for Zenoh.
struct Outgoing {
    topic: Topic,
    bytes: Vec<u8>,
    json: Option<String>,
    end_of_stream: bool,
}

/// What a reader thread hands the sender.
enum Event {
    Message(Outgoing),
    Failed(Topic, String),
}

/// Messages a reader could not queue, by topic.
#[derive(Default)]
struct Dropped([AtomicU64; 3]);

impl Dropped {
    fn count(&self, topic: Topic) -> &AtomicU64 {
        &self.0[topic as usize]
    }
}

fn run(args: Args) -> Result<()> {
    check_rig_name(&args.rig).context("--rig")?;
    let mut topics = vec![Topic::Trajectories];
    for &topic in &args.topics {
        if !topics.contains(&topic) {
            topics.push(topic);
        }
    }
    for endpoint in &args.listen {
        if !is_loopback(endpoint) {
            tracing::warn!(
                "listening on `{endpoint}`, beyond this machine: anyone who reaches it reads the trajectories"
            );
        }
    }
    let config = session_config(&args.listen, &args.connect)?;
    let session = zenoh::open(config).wait().map_err(|e| {
        anyhow!("opening the Zenoh session (listen {:?}, connect {:?}): {e}", args.listen, args.connect)
    })?;
    let mut publishers = BTreeMap::new();
    for &topic in &topics {
        let declare = |key: String, encoding: Encoding| {
            session
                .declare_publisher(key.clone())
                .encoding(encoding)
                .congestion_control(CongestionControl::Drop)
                .express(true)
                .wait()
                .map_err(|e| anyhow!("declaring the Zenoh publisher `{key}`: {e}"))
        };
        let binary = declare(key(&args.rig, topic), Encoding::APPLICATION_OCTET_STREAM)?;
        let json = if topic.has_json() {
            Some(declare(json_key(&args.rig, topic), Encoding::APPLICATION_JSON)?)
        } else {
            None
        };
        publishers.insert(topic as usize, (binary, json));
    }
    let (tx, rx) = sync_channel::<Event>(QUEUE);
    let dropped = Arc::new(Dropped::default());
    let mut readers = Vec::new();
    for &topic in &topics {
        let (tx, dropped) = (tx.clone(), Arc::clone(&dropped));
        let (services, mode, exit_at_end) = (args.services.clone(), args.mode, args.exit_at_end);
        readers.push(std::thread::spawn(move || {
            if let Err(e) = read_topic(topic, &services, mode, exit_at_end, &tx, &dropped) {
                let _ = tx.send(Event::Failed(topic, format!("{e:#}")));
            }
        }));
    }
    drop(tx);
    tracing::info!(
        "ready: forwarding {} to Zenoh as `{}`, listening on {:?}, connecting to {:?}, {} mode",
        topics.iter().map(|t| t.name()).collect::<Vec<_>>().join(", "),
        key(&args.rig, Topic::Trajectories),
        args.listen,
        args.connect,
        args.mode
    );
    let mut forwarded = [0u64; 3];
    let mut last_report = Instant::now();
    let mut matched = false;
    loop {
        match rx.recv_timeout(Duration::from_millis(200)) {
            Ok(Event::Message(out)) => {
                let Some((binary, json)) = publishers.get(&(out.topic as usize)) else { continue };
                // A failed put is the network's problem, not the pipeline's: logged, not fatal.
                if let Err(e) = binary.put(out.bytes).wait() {
                    tracing::warn!("Zenoh put on `{}`: {e}", binary.key_expr());
                }
                if let (Some(publisher), Some(text)) = (json, out.json) {
                    if let Err(e) = publisher.put(text).wait() {
                        tracing::warn!("Zenoh put on `{}`: {e}", publisher.key_expr());
                    }
                }
                forwarded[out.topic as usize] += 1;
                if out.end_of_stream && out.topic == Topic::Trajectories {
                    tracing::info!(
                        "end of stream forwarded ({} trajectory samples)",
                        forwarded[Topic::Trajectories as usize]
                    );
                    if args.exit_at_end {
                        break;
                    }
                }
            }
            Ok(Event::Failed(topic, e)) => bail!("reading {topic}: {e}"),
            Err(RecvTimeoutError::Timeout) => {
                if ipc::stop_requested() {
                    break;
                }
            }
            Err(RecvTimeoutError::Disconnected) => break,
        }
        if last_report.elapsed() >= Duration::from_secs(5) {
            last_report = Instant::now();
            let now_matched = publishers
                .get(&(Topic::Trajectories as usize))
                .map(|(b, j)| {
                    let m = |p: &zenoh::pubsub::Publisher<'_>| p.matching_status().wait().is_ok_and(|s| s.matching());
                    m(b) || j.as_ref().is_some_and(m)
                })
                .unwrap_or(false);
            if now_matched != matched {
                matched = now_matched;
                tracing::info!("remote subscribers of the trajectories: {}", if matched { "yes" } else { "none" });
            }
            tracing::info!(
                "forwarded: {}",
                topics
                    .iter()
                    .map(|&t| format!(
                        "{t} {} (dropped {})",
                        forwarded[t as usize],
                        dropped.count(t).load(Ordering::Relaxed)
                    ))
                    .collect::<Vec<_>>()
                    .join(", ")
            );
        }
    }
    // Let the last messages leave before the session's links close.
    std::thread::sleep(Duration::from_millis(200));
    let _ = session.close().wait();
    Ok(())
}

/// Queues one message; a full queue drops it (and counts it) rather than wait.
fn offer(tx: &SyncSender<Event>, dropped: &Dropped, out: Outgoing) -> Result<()> {
    let topic = out.topic;
    match tx.try_send(Event::Message(out)) {
        Ok(()) => Ok(()),
        Err(TrySendError::Full(_)) => {
            let n = dropped.count(topic).fetch_add(1, Ordering::Relaxed) + 1;
            if n == 1 || n.is_multiple_of(100) {
                tracing::warn!("the network is not keeping up: {n} {topic} message(s) dropped so far");
            }
            Ok(())
        }
        Err(TrySendError::Disconnected(_)) => bail!("the sender has stopped"),
    }
}

/// Reads one topic's service until its end of stream (with `exit_at_end`) or a stop
/// request, handing every message to the sender.
fn read_topic(
    topic: Topic,
    services: &str,
    mode: Mode,
    exit_at_end: bool,
    tx: &SyncSender<Event>,
    dropped: &Dropped,
) -> Result<()> {
    let names = ServiceNames::new(services);
    let node = ipc::stage_node("handflow-bridge")?;
    let idle = Duration::from_millis(100);
    let next = |end: bool| if end && exit_at_end { Next::Stop } else { Next::Continue };
    match topic {
        Topic::Trajectories => {
            let input = ipc::trajectories_input(&node, &names, mode)?;
            ipc::serve(&input, idle, |sample| -> Result<Next> {
                let s = *sample.payload();
                drop(sample);
                if let Err(e) = s.validate() {
                    tracing::error!("skipping a malformed trajectory sample: {e}");
                    return Ok(Next::Continue);
                }
                let json = serde_json::to_string(&TrajectoryJson::from_sample(&s))?;
                let end = s.is_end_of_stream();
                let bytes = wire::encode_trajectory_sample(&s);
                offer(tx, dropped, Outgoing { topic, bytes, json: Some(json), end_of_stream: end })?;
                Ok(next(end))
            })
        }
        Topic::Clusters => {
            let input = ipc::clusters_input(&node, &names, mode)?;
            ipc::serve(&input, idle, |sample| -> Result<Next> {
                let c = *sample.payload();
                drop(sample);
                if let Err(e) = c.validate() {
                    tracing::error!("skipping a malformed cluster set: {e}");
                    return Ok(Next::Continue);
                }
                let json = serde_json::to_string(&ClusterSetJson::from_set(&c))?;
                let end = c.is_end_of_stream();
                let bytes = wire::encode_cluster_set(&c);
                offer(tx, dropped, Outgoing { topic, bytes, json: Some(json), end_of_stream: end })?;
                Ok(next(end))
            })
        }
        Topic::Particles => {
            let input = ipc::particles_input(&node, &names, mode)?;
            ipc::serve(&input, idle, |sample| -> Result<Next> {
                let h = *sample.user_header();
                if let Err(e) = h.validate(sample.payload().len()) {
                    tracing::error!("skipping a malformed particle set: {e}");
                    return Ok(Next::Continue);
                }
                let bytes = wire::encode_particle_set(&h, sample.payload());
                drop(sample);
                let end = h.is_end_of_stream();
                offer(tx, dropped, Outgoing { topic, bytes, json: None, end_of_stream: end })?;
                Ok(next(end))
            })
        }
    }
}
