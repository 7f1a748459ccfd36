//! The services on iceoryx2: their names, their settings in each delivery [`Mode`], and the
//! ports a stage opens on them. Every stage opens a service through these functions, so
//! creator and openers always agree on its settings (iceoryx2 refuses a mismatch).
//!
//! Each publish-subscribe service has an event service of the same name beside it: a
//! publisher notifies after every send, and a subscriber's WaitSet wakes on that event
//! instead of polling.

use std::fmt;
use std::str::FromStr;
use std::time::{Duration, Instant};

use iceoryx2::node::Node;
use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::port::update_connections::UpdateConnections;
use iceoryx2::port::BackpressureAction;
use iceoryx2::prelude::*;
use iceoryx2::service::port_factory::publish_subscribe::PortFactory;
use iceoryx2::service::port_factory::PortFactory as _;
use iceoryx2::waitset::WaitSetRunResult;
use thiserror::Error;

use crate::messages::{
    CameraStatusSet, ClusterSet, FrameHeader, ParticleHeader, RigHeader, ScenePoint, StreamProgress, TrajectorySample,
};

/// The transport: processes on one machine.
pub type Ipc = ipc::Service;
/// A node of the transport.
pub type IpcNode = Node<Ipc>;

/// Zenoh's own log, kept to errors unless `RUST_LOG` says otherwise: it warns at every retry
/// of a connection to an endpoint that is not up yet, which subscribers started before
/// their pipeline do by design.
pub const ZENOH_LOG: &str = "zenoh=error";

/// Logs of a stage process to standard error (the launcher passes them on), at the level
/// `RUST_LOG` gives (default `info`); each line names its stage by its crate
/// (`handflow_flow: ...`). Colours only on a terminal.
pub fn init_logging() {
    use std::io::IsTerminal;
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(format!("info,{ZENOH_LOG}")));
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_ansi(std::io::stderr().is_terminal())
        .with_writer(std::io::stderr)
        .try_init();
    end_with_launcher();
}

/// Set by the launcher in each stage's environment: its process id.
pub const LAUNCHER_PID_ENV: &str = "HANDFLOW_LAUNCHER_PID";

/// A stage started by the launcher ends (SIGTERM, as on Ctrl-C) when the launcher dies,
/// even by SIGKILL: orphaned stages would otherwise run on, holding shared memory and
/// cameras, with nobody to stop them.
pub fn end_with_launcher() {
    let Some(launcher) = std::env::var(LAUNCHER_PID_ENV).ok().and_then(|v| v.parse::<i32>().ok()) else { return };
    if let Err(e) = nix::sys::prctl::set_pdeathsig(nix::sys::signal::Signal::SIGTERM) {
        tracing::warn!("cannot ask to end with the launcher: {e}");
        return;
    }
    // The launcher may have died before the request was made.
    if nix::unistd::getppid().as_raw() != launcher {
        tracing::error!("the launcher (pid {launcher}) is gone: ending");
        std::process::exit(1);
    }
}

/// How the stages deliver messages.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Mode {
    /// Recordings: nothing is dropped; a publisher waits while a subscriber's buffer is full.
    #[default]
    Replay,
    /// Cameras: latest wins; a subscriber that falls behind loses the oldest samples and
    /// never slows its publisher.
    Live,
}

impl Mode {
    fn safe_overflow(self) -> bool {
        self == Mode::Live
    }
}

impl fmt::Display for Mode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Mode::Replay => "replay",
            Mode::Live => "live",
        })
    }
}

impl FromStr for Mode {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "replay" => Ok(Mode::Replay),
            "live" => Ok(Mode::Live),
            other => Err(format!("unknown delivery mode `{other}` (expected `replay` or `live`)")),
        }
    }
}

/// A failure of the transport, with the service it happened on.
#[derive(Debug, Error)]
#[error("service `{service}`: {what}")]
pub struct IpcError {
    /// The service's name.
    pub service: String,
    /// What failed.
    pub what: String,
}

impl IpcError {
    /// An error on `service`.
    pub fn new(service: impl Into<String>, what: impl fmt::Display) -> Self {
        Self { service: service.into(), what: what.to_string() }
    }
}

/// Default prefix of the service names.
pub const DEFAULT_PREFIX: &str = "handflow";

/// The services of one pipeline: `<prefix>/rig`, `<prefix>/frames`, `<prefix>/particles`,
/// `<prefix>/clusters`, `<prefix>/trajectories`. Two pipelines with different prefixes run
/// side by side on one machine.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ServiceNames {
    prefix: String,
}

impl Default for ServiceNames {
    fn default() -> Self {
        Self::new(DEFAULT_PREFIX)
    }
}

/// Suffixes of the services, in pipeline order.
pub const SERVICE_SUFFIXES: [&str; 6] = ["rig", "cameras", "frames", "particles", "clusters", "trajectories"];

impl ServiceNames {
    /// The services under `prefix`.
    pub fn new(prefix: impl Into<String>) -> Self {
        Self { prefix: prefix.into() }
    }

    /// The prefix.
    pub fn prefix(&self) -> &str {
        &self.prefix
    }

    /// `<prefix>/<suffix>`.
    pub fn full(&self, suffix: &str) -> String {
        format!("{}/{suffix}", self.prefix)
    }

    /// Rig calibration.
    pub fn rig(&self) -> String {
        self.full("rig")
    }

    /// Live cameras' health.
    pub fn cameras(&self) -> String {
        self.full("cameras")
    }

    /// Frame sets.
    pub fn frames(&self) -> String {
        self.full("frames")
    }

    /// Particle sets.
    pub fn particles(&self) -> String {
        self.full("particles")
    }

    /// Labelled clusters.
    pub fn clusters(&self) -> String {
        self.full("clusters")
    }

    /// Trajectory samples.
    pub fn trajectories(&self) -> String {
        self.full("trajectories")
    }

    /// How far stage `stage` (`ingest` or `publish`) has got, kept by the launcher for
    /// the stage it restarts.
    pub fn progress(&self, stage: &str) -> String {
        self.full(&format!("progress/{stage}"))
    }
}

fn service_name(name: &str) -> Result<ServiceName, IpcError> {
    ServiceName::new(name).map_err(|e| IpcError::new(name, format!("not a valid service name: {e:?}")))
}

/// A node named after its stage. iceoryx2's own log (which warns about a missing config
/// file in every process) is kept to errors unless `IOX2_LOG_LEVEL` says otherwise.
pub fn create_node(stage: &str) -> Result<Node<Ipc>, IpcError> {
    let namespace = UserNamespace::of_this_process().map_err(|e| IpcError::new(stage, e))?;
    create_node_in(&namespace, stage)
}

/// [`create_node`] in `namespace`. Segments a killed process left half created are removed
/// first: the node's creation would wait on them forever.
pub fn create_node_in(namespace: &UserNamespace, stage: &str) -> Result<Node<Ipc>, IpcError> {
    set_log_level_from_env_or(LogLevel::Error);
    let name = NodeName::new(stage).map_err(|e| IpcError::new(stage, format!("not a valid node name: {e:?}")))?;
    namespace.check_owner().map_err(|e| IpcError::new(stage, e))?;
    remove_unfinished_segments(&namespace.file_prefix());
    let config = namespace.config().map_err(|e| IpcError::new(stage, e))?;
    NodeBuilder::new()
        .name(&name)
        .config(&config)
        .create::<Ipc>()
        .map_err(|e| IpcError::new(stage, format!("creating the node in `{}`: {e:?}", namespace.root_dir())))
}

/// Where a user's iceoryx2 files live. iceoryx2's defaults put every user's in one
/// directory, which its first user creates readable by them alone (a second user cannot
/// even create a node), and name shared memory without the user (two users' services
/// of the same name would collide in `/dev/shm` whatever the directory). So every handflow
/// process, and subscribers in other languages (`examples/sign_recogniser.py` does the
/// same), use a directory and a file prefix of the user's own: `/tmp/handflow-iox2-<uid>/`
/// and `hf<uid>_`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct UserNamespace {
    uid: u32,
    /// Empty for the user's own namespace; else what sets an isolated one apart.
    label: String,
}

impl UserNamespace {
    /// The namespace of user `uid`.
    pub fn new(uid: u32) -> Self {
        Self { uid, label: String::new() }
    }

    /// A namespace of user `uid` apart from their own, named by `label` (ASCII letters and
    /// digits): nothing in it meets the user's pipelines, e.g. for tests that leave
    /// debris on purpose.
    pub fn isolated(uid: u32, label: &str) -> Result<Self, String> {
        if label.is_empty() || !label.bytes().all(|b| b.is_ascii_alphanumeric()) {
            return Err(format!("`{label}`: a namespace's label is ASCII letters and digits"));
        }
        Ok(Self { uid, label: label.to_string() })
    }

    /// The namespace of the user running this process (its effective user, the owner of
    /// `/proc/self`).
    pub fn of_this_process() -> Result<Self, String> {
        use std::os::unix::fs::MetadataExt;
        std::fs::metadata("/proc/self")
            .map(|m| Self::new(m.uid()))
            .map_err(|e| format!("cannot tell which user this process runs as (`/proc/self`: {e})"))
    }

    /// The directory of iceoryx2's service and node files.
    pub fn root_dir(&self) -> String {
        format!("/tmp/handflow-iox2-{}{}/", self.uid, self.label)
    }

    /// The prefix of every file name, shared memory included.
    pub fn file_prefix(&self) -> String {
        format!("hf{}{}_", self.uid, self.label)
    }

    /// Refuses a directory that exists but belongs to another user: someone else could
    /// then read or replace this user's services.
    pub fn check_owner(&self) -> Result<(), String> {
        use std::os::unix::fs::MetadataExt;
        match std::fs::symlink_metadata(self.root_dir()) {
            Ok(m) if m.uid() != self.uid || !m.is_dir() => Err(format!(
                "`{}` is not a directory of user {} (owner {}); remove it, it is not handflow's",
                self.root_dir(),
                self.uid,
                m.uid()
            )),
            _ => Ok(()),
        }
    }

    /// The lock file a launcher holds while it runs a pipeline under `prefix`; the prefix is
    /// escaped so that every prefix has a file of its own in this one directory.
    pub fn pipeline_lock_path(&self, prefix: &str) -> std::path::PathBuf {
        let mut name = String::from("pipeline-");
        for byte in prefix.bytes() {
            if byte.is_ascii_alphanumeric() || byte == b'-' || byte == b'.' {
                name.push(byte as char);
            } else {
                name.push_str(&format!("_{byte:02x}"));
            }
        }
        name.push_str(".lock");
        std::path::Path::new(&self.root_dir()).join(name)
    }

    /// Takes the lock of the pipeline under `prefix`: `Ok(None)` when another process holds
    /// it. The operating system releases it when the holder exits, however it exits, so a
    /// killed launcher never leaves a stale lock behind (a file's presence would).
    pub fn lock_pipeline(&self, prefix: &str) -> Result<Option<std::fs::File>, String> {
        let path = self.pipeline_lock_path(prefix);
        // The mode iceoryx2 gives the directory, should the lock be the first to need it.
        std::os::unix::fs::DirBuilderExt::mode(std::fs::DirBuilder::new().recursive(true), 0o750)
            .create(self.root_dir())
            .map_err(|e| format!("`{}`: {e}", self.root_dir()))?;
        self.check_owner()?;
        let file = std::fs::OpenOptions::new()
            .create(true)
            .truncate(false)
            .write(true)
            .open(&path)
            .map_err(|e| format!("`{}`: {e}", path.display()))?;
        match file.try_lock() {
            Ok(()) => Ok(Some(file)),
            Err(std::fs::TryLockError::WouldBlock) => Ok(None),
            Err(std::fs::TryLockError::Error(e)) => Err(format!("locking `{}`: {e}", path.display())),
        }
    }

    /// iceoryx2's settings (its global configuration, if the user has one) with this
    /// namespace's directory and prefix.
    pub fn config(&self) -> Result<iceoryx2::config::Config, String> {
        let mut config = iceoryx2::config::Config::global_config().clone();
        let root = Path::new(self.root_dir().as_bytes()).map_err(|e| format!("`{}`: {e:?}", self.root_dir()))?;
        config.global.set_root_path(&root);
        config.global.prefix =
            FileName::new(self.file_prefix().as_bytes()).map_err(|e| format!("`{}`: {e:?}", self.file_prefix()))?;
        Ok(config)
    }
}

/// The node of a stage process: created, then what dead processes left in shared memory
/// removed (a restarted stage must not find its predecessor's ports in the way).
pub fn stage_node(stage: &str) -> Result<IpcNode, IpcError> {
    let node = create_node(stage)?;
    let cleaned = cleanup_dead_nodes(&node);
    if cleaned > 0 {
        tracing::info!("cleaned up {cleaned} dead node(s)");
    }
    Ok(node)
}

/// Ends a stage process: status 0, or the error logged (with its causes) and status 1.
pub fn exit_with<E: fmt::Display>(result: Result<(), E>) -> ! {
    match result {
        Ok(()) => std::process::exit(0),
        Err(e) => {
            tracing::error!("{e:#}");
            std::process::exit(1)
        }
    }
}

/// Removes what dead processes left in shared memory (their ports stay registered, and a
/// lossless publisher would wait on a dead subscriber forever). Returns how many dead
/// nodes were cleaned.
pub fn cleanup_dead_nodes(node: &Node<Ipc>) -> usize {
    // A process that just died may have died creating a segment, on which the cleanup
    // would wait forever.
    remove_unfinished_segments(&node.config().global.prefix.to_string());
    node.try_cleanup_dead_nodes().cleanups as usize
}

/// [`crate::unfinished_shm::remove_unfinished_segments`] for the files named `prefix...`,
/// logged when it removed any.
fn remove_unfinished_segments(prefix: &str) {
    let removed = crate::unfinished_shm::remove_unfinished_segments(
        std::path::Path::new(crate::unfinished_shm::SHARED_MEMORY_DIR),
        prefix,
        crate::unfinished_shm::GRACE,
    );
    if !removed.is_empty() {
        let names: Vec<String> = removed.iter().map(|p| p.display().to_string()).collect();
        tracing::warn!(
            "removed {} shared-memory segment(s) a killed process left half created: {}",
            removed.len(),
            names.join(", ")
        );
    }
}

/// The sending end of a service: its publisher and the notifier that wakes subscribers.
pub struct Output<P: ?Sized + fmt::Debug + IceoryxSend + 'static, H: fmt::Debug + ZeroCopySend + 'static> {
    /// The publisher.
    pub publisher: Publisher<Ipc, P, H>,
    notifier: Notifier<Ipc>,
    service: PortFactory<Ipc, P, H>,
    name: String,
}

impl<P: ?Sized + fmt::Debug + IceoryxSend + 'static, H: fmt::Debug + ZeroCopySend + 'static> Output<P, H> {
    /// Wakes every subscriber's WaitSet.
    pub fn notify(&self) -> Result<(), IpcError> {
        self.notifier.notify().map(|_| ()).map_err(|e| IpcError::new(&self.name, format!("notify: {e:?}")))
    }

    /// Subscribers connected to the service.
    pub fn subscribers(&self) -> usize {
        self.service.dynamic_config().number_of_subscribers()
    }

    /// Waits (sleeping, not spinning) until at least `count` subscribers are connected, then
    /// connects to them, so that nothing sent afterwards is lost to a subscriber that has
    /// not yet attached (`false` on timeout or termination request).
    pub fn wait_for_subscribers(&self, node: &Node<Ipc>, count: usize, timeout: Duration) -> bool {
        let started = Instant::now();
        while self.subscribers() < count {
            if started.elapsed() > timeout || !nap(node, Duration::from_millis(5)) {
                return false;
            }
        }
        let _ = self.publisher.update_connections();
        true
    }

    /// Before a stage's first message: in replay mode, waits (logging that it does) until
    /// the next stage subscribes, so nothing is lost; in live mode, connects to whoever is
    /// there.
    pub fn connect_downstream(&self, node: &Node<Ipc>, mode: Mode) {
        let needed = usize::from(mode == Mode::Replay);
        if self.subscribers() < needed {
            tracing::info!("waiting for a subscriber on `{}`", self.name);
        }
        self.wait_for_subscribers(node, needed, Duration::MAX);
    }

    /// Connects to subscribers that arrived since the last send and hands them the
    /// history (iceoryx2 delivers history when the publisher notices a subscriber, so a
    /// publisher that sends rarely, like the rig's, calls this while it waits).
    pub fn update_connections(&self) {
        let _ = self.publisher.update_connections();
    }

    /// The service's name.
    pub fn name(&self) -> &str {
        &self.name
    }
}

/// The receiving end of a service: its subscriber and the listener its WaitSet waits on.
pub struct Input<P: ?Sized + fmt::Debug + IceoryxSend + 'static, H: fmt::Debug + ZeroCopySend + 'static> {
    /// The subscriber.
    pub subscriber: Subscriber<Ipc, P, H>,
    /// Woken by the publisher's notifier; attach it to a WaitSet.
    pub listener: Listener<Ipc>,
    name: String,
}

impl<P: ?Sized + fmt::Debug + IceoryxSend + 'static, H: fmt::Debug + ZeroCopySend + 'static> Input<P, H> {
    /// The service's name.
    pub fn name(&self) -> &str {
        &self.name
    }
}

/// How long a lossless publisher sleeps between attempts to deliver into a full buffer:
/// it waits for its subscriber without taking a core from it.
const BACKPRESSURE_SLEEP: Duration = Duration::from_micros(500);

fn publisher_builder_settings<P: ?Sized + fmt::Debug + IceoryxSend, H: fmt::Debug + ZeroCopySend>(
    service: &PortFactory<Ipc, P, H>,
    mode: Mode,
) -> iceoryx2::service::port_factory::publisher::PortFactoryPublisher<'_, Ipc, P, H> {
    let builder = service.publisher_builder().max_loaned_samples(2);
    match mode {
        Mode::Replay => builder
            .backpressure_strategy(BackpressureStrategy::RetryUntilDelivered)
            .set_backpressure_handler(|_: &iceoryx2::port::BackpressureInfo| {
                // A stop request must not wait for a subscriber that may never read again.
                if stop_requested() {
                    return BackpressureAction::DiscardData;
                }
                std::thread::sleep(BACKPRESSURE_SLEEP);
                BackpressureAction::Retry
            }),
        Mode::Live => builder.backpressure_strategy(BackpressureStrategy::DiscardData),
    }
}

/// Sleeps for `duration` on `node`; false once the stage is asked to stop (SIGINT or
/// SIGTERM). Any other signal cuts the sleep short without ending the stage: iceoryx2 reports
/// SIGCONT after a SIGSTOP as an interrupt, and a stage that took it for Ctrl-C ended with
/// status 0 in the middle of a stream (found by the fault campaign's stop-ingest).
pub fn nap(node: &Node<Ipc>, duration: Duration) -> bool {
    use std::sync::atomic::Ordering;
    match node.wait(duration) {
        Ok(()) => true,
        Err(iceoryx2::node::NodeWaitFailure::Interrupt) if !stop_requested() => true,
        Err(_) => {
            STOP_REQUESTED.store(true, Ordering::Relaxed);
            false
        }
    }
}

static STOP_REQUESTED: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

/// Whether SIGINT or SIGTERM has arrived. iceoryx2 hands a signal out once; this remembers
/// it, so that a publisher waiting on a full buffer and the stage's loop both see it.
pub fn stop_requested() -> bool {
    use std::sync::atomic::Ordering;
    if iceoryx2_bb_posix::signal::SignalHandler::termination_requested() {
        STOP_REQUESTED.store(true, Ordering::Relaxed);
    }
    STOP_REQUESTED.load(Ordering::Relaxed)
}

/// Settings of one service.
#[derive(Clone, Copy, Debug)]
struct Settings {
    max_subscribers: usize,
    buffer: usize,
    /// A live subscriber's buffer: the newest this many samples are kept.
    live_buffer: usize,
    borrowed: usize,
    history: usize,
}

/// Frame sets are large (2.8 MB for three VGA views): few subscribers, small buffers.
/// Live, two frame sets wait: one estimate slower than a frame interval then delays the next
/// frame instead of dropping it.
const FRAMES: Settings = Settings { max_subscribers: 4, buffer: 4, live_buffer: 2, borrowed: 4, history: 0 };
/// Live frame sets keep the last two as history: a restarted flow stage gets them at once
/// and estimates on the next frame set instead of waiting for three new ones (a third of a
/// second at 6 frames per second). Replay keeps none: a restarted stage must not estimate a
/// frame set twice.
const FRAMES_LIVE: Settings = Settings { history: 2, ..FRAMES };

fn frames_settings(mode: Mode) -> Settings {
    match mode {
        Mode::Replay => FRAMES,
        Mode::Live => FRAMES_LIVE,
    }
}
/// Particle sets.
const PARTICLES: Settings = Settings { max_subscribers: 4, buffer: 4, live_buffer: 1, borrowed: 2, history: 0 };
/// Labelled clusters (small).
const CLUSTERS: Settings = Settings { max_subscribers: 8, buffer: 16, live_buffer: 1, borrowed: 2, history: 0 };
/// Trajectory samples: any number of recognisers and viewers.
const TRAJECTORIES: Settings = Settings { max_subscribers: 32, buffer: 64, live_buffer: 8, borrowed: 4, history: 0 };
/// A stage's progress: only the newest matters.
const PROGRESS: Settings = Settings { max_subscribers: 2, buffer: 1, live_buffer: 1, borrowed: 1, history: 1 };

macro_rules! open_service {
    ($node:expr, $name:expr, $payload:ty, $header:ty, $settings:expr, $safe_overflow:expr) => {{
        let name = service_name($name)?;
        let builder = $node.service_builder(&name).publish_subscribe::<$payload>();
        builder
            .user_header::<$header>()
            .max_publishers(2)
            .max_subscribers($settings.max_subscribers)
            .subscriber_max_buffer_size($settings.buffer)
            .subscriber_max_borrowed_samples($settings.borrowed)
            .history_size($settings.history)
            .enable_safe_overflow($safe_overflow)
            .open_or_create()
            .map_err(|e| IpcError::new($name, format!("opening the service: {e:?}")))?
    }};
}

fn event_service(
    node: &Node<Ipc>,
    name: &str,
) -> Result<iceoryx2::service::port_factory::event::PortFactory<Ipc>, IpcError> {
    node.service_builder(&service_name(name)?)
        .event()
        .open_or_create()
        .map_err(|e| IpcError::new(name, format!("opening the event service: {e:?}")))
}

fn output<P: ?Sized + fmt::Debug + IceoryxSend, H: fmt::Debug + ZeroCopySend>(
    node: &Node<Ipc>,
    name: String,
    service: PortFactory<Ipc, P, H>,
    publisher: Result<Publisher<Ipc, P, H>, iceoryx2::port::publisher::PublisherCreateError>,
) -> Result<Output<P, H>, IpcError> {
    let publisher = publisher.map_err(|e| IpcError::new(&name, format!("creating the publisher: {e:?}")))?;
    let notifier = event_service(node, &name)?
        .notifier_builder()
        .create()
        .map_err(|e| IpcError::new(&name, format!("creating the notifier: {e:?}")))?;
    Ok(Output { publisher, notifier, service, name })
}

fn input<P: ?Sized + fmt::Debug + IceoryxSend, H: fmt::Debug + ZeroCopySend>(
    node: &Node<Ipc>,
    name: String,
    service: &PortFactory<Ipc, P, H>,
    buffer: usize,
) -> Result<Input<P, H>, IpcError> {
    // The listener first: a sample sent between the two would otherwise wake nobody.
    let listener = event_service(node, &name)?
        .listener_builder()
        .create()
        .map_err(|e| IpcError::new(&name, format!("creating the listener: {e:?}")))?;
    let subscriber = service
        .subscriber_builder()
        .buffer_size(buffer)
        .create()
        .map_err(|e| IpcError::new(&name, format!("creating the subscriber: {e:?}")))?;
    Ok(Input { subscriber, listener, name })
}

/// Buffer of a subscriber: latest only in live mode.
fn buffer_for(mode: Mode, settings: Settings) -> usize {
    match mode {
        Mode::Replay => settings.buffer,
        Mode::Live => settings.live_buffer,
    }
}

/// Publisher of the rig calibration (history 1: late joiners get the last one).
pub fn rig_output(node: &Node<Ipc>, names: &ServiceNames) -> Result<Output<[u8], RigHeader>, IpcError> {
    let name = names.rig();
    let service = rig_service(node, &name)?;
    let publisher = service
        .publisher_builder()
        .initial_max_slice_len(4096)
        .allocation_strategy(AllocationStrategy::PowerOfTwo)
        .create();
    output(node, name, service, publisher)
}

/// Subscriber of the rig calibration.
pub fn rig_input(node: &Node<Ipc>, names: &ServiceNames) -> Result<Input<[u8], RigHeader>, IpcError> {
    let name = names.rig();
    let service = rig_service(node, &name)?;
    input(node, name, &service, 1)
}

fn rig_service(node: &Node<Ipc>, name: &str) -> Result<PortFactory<Ipc, [u8], RigHeader>, IpcError> {
    // The rig is state, not a stream: latest wins in every mode.
    let settings = Settings { max_subscribers: 32, buffer: 1, live_buffer: 1, borrowed: 1, history: 1 };
    Ok(open_service!(node, name, [u8], RigHeader, settings, true))
}

/// The live cameras' health is state, like the rig: latest wins, and a late subscriber gets
/// the last one.
const CAMERAS: Settings = Settings { max_subscribers: 32, buffer: 2, live_buffer: 2, borrowed: 2, history: 1 };

/// Publisher of the live cameras' health.
pub fn cameras_output(node: &Node<Ipc>, names: &ServiceNames) -> Result<Output<CameraStatusSet, ()>, IpcError> {
    let name = names.cameras();
    let service = open_service!(node, &name, CameraStatusSet, (), CAMERAS, true);
    let publisher = service.publisher_builder().backpressure_strategy(BackpressureStrategy::DiscardData).create();
    output(node, name, service, publisher)
}

/// Publisher of frame sets of `frame_set_len` bytes.
pub fn frames_output(
    node: &Node<Ipc>,
    names: &ServiceNames,
    mode: Mode,
    frame_set_len: usize,
) -> Result<Output<[u8], FrameHeader>, IpcError> {
    let name = names.frames();
    let service = open_service!(node, &name, [u8], FrameHeader, frames_settings(mode), mode.safe_overflow());
    let publisher = publisher_builder_settings(&service, mode)
        .initial_max_slice_len(frame_set_len.max(1))
        .allocation_strategy(AllocationStrategy::PowerOfTwo)
        .create();
    output(node, name, service, publisher)
}

/// Publisher of stage `stage`'s progress (never waits: the newest overwrites).
pub fn progress_output(
    node: &Node<Ipc>,
    names: &ServiceNames,
    stage: &str,
) -> Result<Output<StreamProgress, ()>, IpcError> {
    let name = names.progress(stage);
    let service = open_service!(node, &name, StreamProgress, (), PROGRESS, true);
    let publisher = service.publisher_builder().backpressure_strategy(BackpressureStrategy::DiscardData).create();
    output(node, name, service, publisher)
}

/// Subscriber of stage `stage`'s progress; the newest sample is the one that counts.
pub fn progress_input(
    node: &Node<Ipc>,
    names: &ServiceNames,
    stage: &str,
) -> Result<Input<StreamProgress, ()>, IpcError> {
    let name = names.progress(stage);
    let service = open_service!(node, &name, StreamProgress, (), PROGRESS, true);
    input(node, name, &service, PROGRESS.buffer)
}

impl Output<StreamProgress, ()> {
    /// Publishes `progress`; a failure is logged, never fatal (only a restart would miss it).
    pub fn report(&self, progress: StreamProgress) {
        if let Err(error) = self.publisher.send_copy(progress) {
            tracing::warn!("cannot publish progress on `{}`: {error:?}", self.name);
        }
    }
}

/// Subscriber of frame sets.
pub fn frames_input(node: &Node<Ipc>, names: &ServiceNames, mode: Mode) -> Result<Input<[u8], FrameHeader>, IpcError> {
    let name = names.frames();
    let service = open_service!(node, &name, [u8], FrameHeader, frames_settings(mode), mode.safe_overflow());
    input(node, name, &service, buffer_for(mode, FRAMES))
}

/// Points a particle publisher reserves at first; it grows in powers of two.
const INITIAL_POINTS: usize = 1 << 16;

/// Publisher of particle sets.
pub fn particles_output(
    node: &Node<Ipc>,
    names: &ServiceNames,
    mode: Mode,
) -> Result<Output<[ScenePoint], ParticleHeader>, IpcError> {
    let name = names.particles();
    let service = open_service!(node, &name, [ScenePoint], ParticleHeader, PARTICLES, mode.safe_overflow());
    let publisher = publisher_builder_settings(&service, mode)
        .initial_max_slice_len(INITIAL_POINTS)
        .allocation_strategy(AllocationStrategy::PowerOfTwo)
        .create();
    output(node, name, service, publisher)
}

/// Subscriber of particle sets.
pub fn particles_input(
    node: &Node<Ipc>,
    names: &ServiceNames,
    mode: Mode,
) -> Result<Input<[ScenePoint], ParticleHeader>, IpcError> {
    let name = names.particles();
    let service = open_service!(node, &name, [ScenePoint], ParticleHeader, PARTICLES, mode.safe_overflow());
    input(node, name, &service, buffer_for(mode, PARTICLES))
}

/// Publisher of labelled clusters.
pub fn clusters_output(node: &Node<Ipc>, names: &ServiceNames, mode: Mode) -> Result<Output<ClusterSet, ()>, IpcError> {
    let name = names.clusters();
    let service = open_service!(node, &name, ClusterSet, (), CLUSTERS, mode.safe_overflow());
    let publisher = publisher_builder_settings(&service, mode).create();
    output(node, name, service, publisher)
}

/// Subscriber of labelled clusters.
pub fn clusters_input(node: &Node<Ipc>, names: &ServiceNames, mode: Mode) -> Result<Input<ClusterSet, ()>, IpcError> {
    let name = names.clusters();
    let service = open_service!(node, &name, ClusterSet, (), CLUSTERS, mode.safe_overflow());
    input(node, name, &service, buffer_for(mode, CLUSTERS))
}

/// Publisher of trajectory samples.
pub fn trajectories_output(
    node: &Node<Ipc>,
    names: &ServiceNames,
    mode: Mode,
) -> Result<Output<TrajectorySample, ()>, IpcError> {
    let name = names.trajectories();
    let service = open_service!(node, &name, TrajectorySample, (), TRAJECTORIES, mode.safe_overflow());
    let publisher = publisher_builder_settings(&service, mode).create();
    output(node, name, service, publisher)
}

/// Subscriber of trajectory samples.
pub fn trajectories_input(
    node: &Node<Ipc>,
    names: &ServiceNames,
    mode: Mode,
) -> Result<Input<TrajectorySample, ()>, IpcError> {
    let name = names.trajectories();
    let service = open_service!(node, &name, TrajectorySample, (), TRAJECTORIES, mode.safe_overflow());
    // Live subscribers keep a few samples: a recogniser wants the recent track, not one point.
    input(node, name, &service, buffer_for(mode, TRAJECTORIES))
}

macro_rules! tap_input {
    ($fn:ident, $payload:ty, $header:ty, $what:literal) => {
        #[doc = concat!("A subscriber of ", $what, " on an existing service `name`, whatever its mode (for `handflow tap`).")]
        pub fn $fn(node: &IpcNode, name: &str) -> Result<Input<$payload, $header>, IpcError> {
            let service = node
                .service_builder(&service_name(name)?)
                .publish_subscribe::<$payload>()
                .user_header::<$header>()
                .open()
                .map_err(|e| IpcError::new(name, format!("opening the service (is a pipeline running?): {e:?}")))?;
            let buffer = service.static_config().subscriber_max_buffer_size();
            input(node, name.to_owned(), &service, buffer)
        }
    };
}

tap_input!(tap_rig, [u8], RigHeader, "the rig calibration");
tap_input!(tap_frames, [u8], FrameHeader, "frame sets");
tap_input!(tap_cameras, CameraStatusSet, (), "the live cameras' health");
tap_input!(tap_particles, [ScenePoint], ParticleHeader, "particle sets");
tap_input!(tap_clusters, ClusterSet, (), "labelled clusters");
tap_input!(tap_trajectories, TrajectorySample, (), "trajectory samples");

/// What a sample handler wants next.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Next {
    /// Keep serving.
    Continue,
    /// Return from [`serve`].
    Stop,
}

/// An input whose samples can be received one by one (fixed-size and slice payloads
/// receive differently in iceoryx2).
pub trait Receive {
    /// A received sample.
    type Sample;
    /// The next waiting sample, if any.
    fn receive_one(&self) -> Result<Option<Self::Sample>, IpcError>;
    /// The listener woken by the publisher.
    fn wake_listener(&self) -> &Listener<Ipc>;
    /// The service's name.
    fn service_name(&self) -> &str;
}

impl<T: fmt::Debug + ZeroCopySend + 'static, H: fmt::Debug + ZeroCopySend + 'static> Receive for Input<T, H> {
    type Sample = iceoryx2::sample::Sample<Ipc, T, H>;

    fn receive_one(&self) -> Result<Option<Self::Sample>, IpcError> {
        self.subscriber.receive().map_err(|e| IpcError::new(&self.name, format!("receive: {e:?}")))
    }

    fn wake_listener(&self) -> &Listener<Ipc> {
        &self.listener
    }

    fn service_name(&self) -> &str {
        &self.name
    }
}

impl<T: fmt::Debug + ZeroCopySend + 'static, H: fmt::Debug + ZeroCopySend + 'static> Receive for Input<[T], H> {
    type Sample = iceoryx2::sample::Sample<Ipc, [T], H>;

    fn receive_one(&self) -> Result<Option<Self::Sample>, IpcError> {
        self.subscriber.receive().map_err(|e| IpcError::new(&self.name, format!("receive: {e:?}")))
    }

    fn wake_listener(&self) -> &Listener<Ipc> {
        &self.listener
    }

    fn service_name(&self) -> &str {
        &self.name
    }
}

/// Serves `input`: a WaitSet sleeps until the publisher's notification (or `idle` at the
/// latest, a safety net for a lost wake-up), then every waiting sample goes to `on_sample`,
/// oldest first. Returns when `on_sample` says [`Next::Stop`] or fails, or on SIGINT/SIGTERM.
pub fn serve<I: Receive, E: From<IpcError>>(
    input: &I,
    idle: Duration,
    mut on_sample: impl FnMut(I::Sample) -> Result<Next, E>,
) -> Result<(), E> {
    let name = input.service_name().to_owned();
    let waitset = WaitSetBuilder::new()
        .create::<Ipc>()
        .map_err(|e| IpcError::new(&name, format!("creating the WaitSet: {e:?}")))?;
    let _guard = waitset
        .attach_deadline(input.wake_listener(), idle)
        .map_err(|e| IpcError::new(&name, format!("attaching to the WaitSet: {e:?}")))?;
    let mut result = Ok(());
    let mut on_event = |_: WaitSetAttachmentId<Ipc>| {
        if STOP_REQUESTED.load(std::sync::atomic::Ordering::Relaxed) {
            return CallbackProgression::Stop;
        }
        let _ = input.wake_listener().try_wait(|_| {});
        loop {
            match input.receive_one() {
                Ok(Some(sample)) => match on_sample(sample) {
                    Ok(Next::Continue) => {}
                    Ok(Next::Stop) => return CallbackProgression::Stop,
                    Err(e) => {
                        result = Err(e);
                        return CallbackProgression::Stop;
                    }
                },
                Ok(None) => return CallbackProgression::Continue,
                Err(e) => {
                    result = Err(e.into());
                    return CallbackProgression::Stop;
                }
            }
        }
    };
    // Drain once before waiting: a subscriber only connects to its publishers (and only then
    // holds back a lossless one) on a receive, and samples sent before this wake nobody.
    if on_event(WaitSetAttachmentId::from_guard(&_guard)) == CallbackProgression::Continue {
        loop {
            let outcome =
                waitset.wait_and_process(&mut on_event).map_err(|e| IpcError::new(&name, format!("WaitSet: {e:?}")))?;
            match outcome {
                // Any signal that interrupts the wait, SIGCONT after a SIGSTOP included (epoll
                // is not restarted after a stop): only SIGINT and SIGTERM end the stage.
                WaitSetRunResult::Interrupt if !stop_requested() => continue,
                WaitSetRunResult::TerminationRequest | WaitSetRunResult::Interrupt => {
                    STOP_REQUESTED.store(true, std::sync::atomic::Ordering::Relaxed);
                    break;
                }
                _ => break,
            }
        }
    }
    result
}

/// Waits for the rig calibration (sleeping in steps of 10 ms; it arrives from the history
/// as soon as ingest has published it) and checks it. `None` on SIGINT/SIGTERM.
pub fn wait_for_rig(node: &IpcNode, names: &ServiceNames) -> Result<Option<(RigHeader, crate::Rig)>, IpcError> {
    let input = rig_input(node, names)?;
    let name = names.rig();
    let mut announced = false;
    loop {
        let sample = input.subscriber.receive().map_err(|e| IpcError::new(&name, format!("receive: {e:?}")))?;
        if let Some(sample) = sample {
            let header = *sample.user_header();
            return parse_rig(&name, &header, sample.payload()).map(|rig| Some((header, rig)));
        }
        if !announced {
            tracing::info!("waiting for the rig calibration on `{name}`");
            announced = true;
        }
        if !nap(node, Duration::from_millis(10)) {
            return Ok(None);
        }
    }
}

/// Whether each stage of pipeline `names` (ingest, flow, cluster, publish) is up: a live
/// process holds a publisher on the stage's output service. Node names are shared by every pipeline
/// on the machine; services carry the pipeline's prefix, so this tells pipelines apart.
pub fn stage_health(node: &IpcNode, names: &ServiceNames) -> Vec<(&'static str, bool)> {
    let mut alive = std::collections::HashSet::new();
    // A listing can fail part-way (a node created or removed meanwhile, an interrupted
    // lock query): the nodes seen so far are kept and the listing is tried again.
    for _ in 0..3 {
        let listed = Node::<Ipc>::list(node.config(), |state| {
            if let NodeState::Alive(view) = state {
                alive.insert(*iceoryx2::node::NodeView::id(&view));
            }
            CallbackProgression::Continue
        });
        if listed.is_ok() {
            break;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let publishing = |service: Option<&iceoryx2::service::dynamic_config::publish_subscribe::DynamicConfig<_>>| {
        let mut any = false;
        if let Some(config) = service {
            config.list_publishers(|details| {
                any = alive.contains(&details.node_id);
                if any {
                    CallbackProgression::Stop
                } else {
                    CallbackProgression::Continue
                }
            });
        }
        any
    };
    macro_rules! up {
        ($suffix:literal, $payload:ty, $header:ty) => {{
            let service = service_name(&names.full($suffix)).ok().and_then(|name| {
                node.service_builder(&name).publish_subscribe::<$payload>().user_header::<$header>().open().ok()
            });
            publishing(service.as_ref().map(|s| s.dynamic_config()))
        }};
    }
    vec![
        ("ingest", up!("frames", [u8], FrameHeader)),
        ("flow", up!("particles", [ScenePoint], ParticleHeader)),
        ("cluster", up!("clusters", ClusterSet, ())),
        ("publish", up!("trajectories", TrajectorySample, ())),
    ]
}

impl Output<[u8], FrameHeader> {
    /// Subscribers of these frames whose node also publishes particles: the flow stage's, not
    /// a viewer's or a tap's. A replay starts only once flow listens, whoever else does.
    pub fn flow_subscribers(&self, node: &IpcNode, names: &ServiceNames) -> usize {
        let Some(particles) = service_name(&names.full("particles")).ok().and_then(|name| {
            node.service_builder(&name).publish_subscribe::<[ScenePoint]>().user_header::<ParticleHeader>().open().ok()
        }) else {
            return 0;
        };
        let mut flow_nodes = Vec::new();
        particles.dynamic_config().list_publishers(|details| {
            flow_nodes.push(details.node_id);
            CallbackProgression::Continue
        });
        let mut count = 0;
        self.service.dynamic_config().list_subscribers(|details| {
            if flow_nodes.contains(&details.node_id) {
                count += 1;
            }
            CallbackProgression::Continue
        });
        count
    }
}

/// The rig calibration of a sample of service `name`: its header checked against the payload,
/// the payload read as the rig's TOML.
pub fn parse_rig(name: &str, header: &RigHeader, payload: &[u8]) -> Result<crate::Rig, IpcError> {
    header.validate(payload.len()).map_err(|e| IpcError::new(name, e))?;
    let text = std::str::from_utf8(payload).map_err(|e| IpcError::new(name, format!("rig text: {e}")))?;
    crate::Rig::from_toml_str(text).map_err(|e| IpcError::new(name, format!("rig: {e}")))
}

/// Nanoseconds since the Unix epoch (0 if the clock is before it).
pub fn unix_now_ns() -> u64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_nanos() as u64)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn modes_parse_and_print() {
        assert_eq!("live".parse::<Mode>().unwrap(), Mode::Live);
        assert_eq!(Mode::Replay.to_string(), "replay");
        assert!("fast".parse::<Mode>().unwrap_err().contains("`fast`"));
    }

    /// Sends frame sets 0, 1 and 2 on a fresh frames service in `mode`, then subscribes (as a
    /// restarted flow stage does) and returns the sequences the late subscriber is handed.
    fn late_subscriber_is_handed(mode: Mode) -> Vec<u64> {
        let node = create_node("ipc-history-test").unwrap();
        let names = ServiceNames::new(format!("history-test-{}-{mode}", std::process::id()));
        let frames = frames_output(&node, &names, mode, 4).unwrap();
        for sequence in 0..3 {
            let mut sample = frames.publisher.loan_slice(4).unwrap();
            *sample.user_header_mut() = FrameHeader { sequence, ..FrameHeader::default() };
            sample.send().unwrap();
        }
        let input = frames_input(&node, &names, mode).unwrap();
        frames.update_connections();
        let mut sequences = Vec::new();
        while let Some(sample) = input.receive_one().unwrap() {
            sequences.push(sample.user_header().sequence);
        }
        sequences
    }

    #[test]
    fn a_late_live_frames_subscriber_gets_the_last_two_frame_sets_and_a_replay_one_none() {
        assert_eq!(late_subscriber_is_handed(Mode::Live), vec![1, 2]);
        assert_eq!(late_subscriber_is_handed(Mode::Replay), Vec::<u64>::new());
    }

    #[test]
    fn a_pipeline_lock_is_refused_while_held_and_free_once_dropped() {
        let namespace = UserNamespace::of_this_process().unwrap();
        let prefix = format!("lock-test/{}-{:?}", std::process::id(), std::thread::current().id());
        let held = namespace.lock_pipeline(&prefix).unwrap();
        assert!(held.is_some(), "a free prefix is locked");
        assert!(namespace.lock_pipeline(&prefix).unwrap().is_none(), "a held lock is refused");
        drop(held);
        assert!(namespace.lock_pipeline(&prefix).unwrap().is_some(), "a dropped lock is free again");
        let _ = std::fs::remove_file(namespace.pipeline_lock_path(&prefix));
    }

    #[test]
    fn every_prefix_has_a_lock_file_of_its_own_in_the_namespace() {
        let namespace = UserNamespace::new(1000);
        let a = namespace.pipeline_lock_path("rig/a");
        let b = namespace.pipeline_lock_path("rig_a");
        assert_ne!(a, b);
        assert_eq!(a.parent().unwrap(), std::path::Path::new("/tmp/handflow-iox2-1000/"));
        assert!(!a.file_name().unwrap().to_str().unwrap().contains('/'));
    }

    /// Names the isolated namespace the victim of the next test creates its node in.
    const VICTIM_LABEL_ENV: &str = "HANDFLOW_TEST_VICTIM_NAMESPACE";

    /// Run by the next test as a process of its own: a node with a service in the
    /// namespace the environment names, then waits to be killed. Does nothing otherwise.
    #[test]
    #[ignore = "a helper process of the unsized-segment test, started by it"]
    fn victim_of_the_unsized_segment_test() {
        let Ok(label) = std::env::var(VICTIM_LABEL_ENV) else { return };
        let namespace = UserNamespace::isolated(UserNamespace::of_this_process().unwrap().uid, &label).unwrap();
        let node = create_node_in(&namespace, "victim").unwrap();
        let _frames = frames_output(&node, &ServiceNames::new("victim"), Mode::Live, 4).unwrap();
        println!("victim ready");
        std::thread::sleep(Duration::from_secs(120));
    }

    #[test]
    fn a_node_is_created_although_a_killed_process_left_a_segment_it_never_sized() {
        use std::io::BufRead;
        use std::os::unix::fs::OpenOptionsExt;
        let uid = UserNamespace::of_this_process().unwrap().uid;
        let label = format!("unsized{}", std::process::id());
        let namespace = UserNamespace::isolated(uid, &label).unwrap();
        let mut victim = std::process::Command::new(std::env::current_exe().unwrap())
            .args(["--exact", "ipc::tests::victim_of_the_unsized_segment_test", "--ignored", "--nocapture"])
            .env(VICTIM_LABEL_ENV, &label)
            .stdout(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        let stdout = std::io::BufReader::new(victim.stdout.take().unwrap());
        let ready = stdout.lines().map_while(Result::ok).any(|line| line == "victim ready");
        let _ = victim.kill();
        let _ = victim.wait();
        assert!(ready, "the victim process created its node and service");
        // What a process killed between creating its service's segments and sizing them
        // leaves: write-only segments of size zero.
        let shm = std::path::Path::new(crate::unfinished_shm::SHARED_MEMORY_DIR);
        let mut emptied = 0;
        for entry in std::fs::read_dir(shm).unwrap().flatten() {
            let name = entry.file_name().to_string_lossy().into_owned();
            if name.starts_with(&namespace.file_prefix()) && name.ends_with(".dynamic") {
                std::fs::remove_file(entry.path()).unwrap();
                std::fs::OpenOptions::new().write(true).create_new(true).mode(0o200).open(entry.path()).unwrap();
                emptied += 1;
            }
        }
        assert!(emptied > 0, "the victim's service has a dynamic segment");
        // Creating a node cleans up the dead victim, whose service's segment iceoryx2
        // would wait on forever.
        let (tx, rx) = std::sync::mpsc::channel();
        let apart = namespace.clone();
        std::thread::spawn(move || {
            let _ = tx.send(create_node_in(&apart, "after-the-kill").map(|node| cleanup_dead_nodes(&node)));
        });
        let outcome = rx.recv_timeout(Duration::from_secs(60));
        let _ = std::fs::remove_dir_all(namespace.root_dir());
        for entry in std::fs::read_dir(shm).unwrap().flatten() {
            if entry.file_name().to_string_lossy().starts_with(&namespace.file_prefix()) {
                let _ = std::fs::remove_file(entry.path());
            }
        }
        match outcome {
            Ok(Ok(_)) => {}
            Ok(Err(e)) => panic!("the node was not created: {e}"),
            Err(_) => panic!("creating a node waited a minute on the segment the killed process never sized"),
        }
    }

    #[test]
    fn service_names_share_the_prefix() {
        let n = ServiceNames::new("test-1");
        assert_eq!(n.frames(), "test-1/frames");
        assert_eq!(n.trajectories(), "test-1/trajectories");
    }
}
