//! `handflow run`: starts the four stage processes of a pipeline, passes their logs on,
//! restarts a stage that dies, and stops them all together.
//!
//! A pipeline file (TOML) says what to run; flags override it:
//!
//! ```toml
//! mode = "replay"                  # or "live"
//! recording = "out/signer-3cam"    # a recording folder to replay, or
//! # preset = "signer-3cam"         # a synthetic scene ingest renders as it goes, or
//! # live cameras, each with its calibration's name (`calibration` says where they are):
//! # [[cameras]]
//! # name = "cam_0"
//! # source = "v4l2:///dev/video0"  # rtsp://, http(s)://, file:///video.mp4, gst:<GStreamer source>
//! # size = [1280, 720]             # asked of the device (default: the calibration's)
//! # fps = 30                       # asked of the device
//! # record = "out/session"         # live cameras: also write what they deliver as a recording
//! # record_quality = 18            # H.264 at this quantizer instead of lossless FFV1
//! out = "out/trajectories.jsonl"   # the JSON Lines file the publisher writes
//! pace = "max"                     # or "recorded" (default: max in replay, recorded in live)
//! loop = false                     # replay the source forever
//! # frames = 150                   # publish only the first N frame sets
//! # start = 300                    # the recording's first frame to publish (seeks in videos)
//! # calibration = "rig.toml"       # instead of the recording's own calibration
//! # up = [0.0, 0.0, 1.0]           # the world's up, instead of the calibration's or the estimate
//! services = "handflow"            # prefix of the iceoryx2 service names
//! variant = "handflow"             # or "paper"
//! max_restarts = 5                 # per stage within a minute, before the run gives up
//!
//! [viewer]                         # the live viewer page, served by the publisher
//! enabled = true                   # default on
//! listen = "127.0.0.1:8787"        # loopback unless the user says otherwise
//! thumbnails_hz = 2.0              # per camera; 0 for none
//!
//! [network]                        # off unless given: trajectories to other machines
//! zenoh = { listen = "tcp/127.0.0.1:7447" }   # or connect = "tcp/router:7447"; also
//! #   rig = "studio-a"               # key expressions handflow/<rig>/... (default: the source's name)
//! #   topics = ["clusters", "particles"]     # forwarded besides the trajectories
//! ```
//!
//! A run that is not looped (or has a fixed number of frames) ends when the publisher has published the end of the stream
//! (every frame through every stage); the launcher then stops the other stages and returns.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use handflow_protocol::ipc::{self, Mode};
use handflow_protocol::messages::StreamProgress;
use nix::sys::signal::{kill, Signal};
use nix::unistd::Pid;
use serde::Deserialize;

/// What a pipeline runs.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Pipeline {
    /// `replay` or `live`.
    pub mode: String,
    /// Recording folder to replay.
    pub recording: Option<PathBuf>,
    /// Synthetic scene rendered by ingest as it goes.
    pub preset: Option<String>,
    /// Live cameras (`[[cameras]]`), placed by `calibration`.
    pub cameras: Vec<handflow_ingest::live::LiveCameraSpec>,
    /// Live cameras: a folder (new or empty) where every frame set is also recorded.
    pub record: Option<PathBuf>,
    /// Recorded videos as H.264 at this quantizer instead of lossless.
    pub record_quality: Option<u32>,
    /// JSON Lines file of the trajectories.
    pub out: Option<PathBuf>,
    /// `max` or `recorded`.
    pub pace: Option<String>,
    /// Replay the source forever.
    #[serde(rename = "loop")]
    pub looped: bool,
    /// Publish only the first N frame sets.
    pub frames: Option<u64>,
    /// The recording's first frame number to publish (seeks in videos).
    pub start: Option<u64>,
    /// Calibration file instead of the recording's own.
    pub calibration: Option<PathBuf>,
    /// The world's up direction, instead of the calibration's or the estimate.
    pub up: Option<[f64; 3]>,
    /// Decode the recording into memory before the run (ingest's `--preload`): frame sets
    /// are then published as a camera delivers them, without decoding on the path.
    pub preload: bool,
    /// Prefix of the service names.
    pub services: String,
    /// Engine variant.
    pub variant: String,
    /// Restarts per stage before the run gives up.
    pub max_restarts: u32,
    /// Where the trajectories go beyond this machine.
    pub network: Network,
    /// The live viewer.
    pub viewer: ViewerSettings,
}

/// The `[viewer]` table.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct ViewerSettings {
    /// Serve the viewer.
    pub enabled: bool,
    /// Address to listen on.
    pub listen: String,
    /// Thumbnails per second per camera.
    pub thumbnails_hz: f64,
}

impl Default for ViewerSettings {
    fn default() -> Self {
        Self { enabled: true, listen: handflow_publish::viewer::DEFAULT_ADDRESS.into(), thumbnails_hz: 2.0 }
    }
}

/// The `[network]` table.
#[derive(Clone, Debug, Default, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Network {
    /// The Zenoh bridge: started when this names an endpoint.
    pub zenoh: Option<ZenohSettings>,
}

/// `[network] zenoh = { ... }`.
#[derive(Clone, Debug, Default, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct ZenohSettings {
    /// Endpoint the bridge listens on, `tcp/<host>:<port>` (loopback unless the user says
    /// otherwise).
    pub listen: Option<String>,
    /// Endpoint the bridge connects to (a Zenoh router).
    pub connect: Option<String>,
    /// The rig's name in the key expressions (default: the recording's folder, the preset,
    /// or the calibration's folder).
    pub rig: Option<String>,
    /// Topics forwarded besides the trajectories: `clusters`, `particles`.
    pub topics: Vec<String>,
}

impl Default for Pipeline {
    fn default() -> Self {
        Self {
            mode: "replay".into(),
            recording: None,
            preset: None,
            cameras: Vec::new(),
            record: None,
            record_quality: None,
            out: None,
            pace: None,
            looped: false,
            frames: None,
            start: None,
            calibration: None,
            up: None,
            preload: false,
            services: ipc::DEFAULT_PREFIX.into(),
            variant: "handflow".into(),
            max_restarts: 5,
            network: Network::default(),
            viewer: ViewerSettings::default(),
        }
    }
}

impl Pipeline {
    /// Reads a pipeline file; relative paths in it are relative to the file's folder.
    pub fn load(path: &Path) -> Result<Self> {
        let text = handflow_protocol::read_text_capped(path)
            .with_context(|| format!("reading pipeline `{}`", path.display()))?;
        let mut p: Pipeline = toml::from_str(&text).with_context(|| format!("pipeline `{}`", path.display()))?;
        let base = path.parent().unwrap_or(Path::new(""));
        for file in [&mut p.recording, &mut p.out, &mut p.calibration, &mut p.record].into_iter().flatten() {
            if file.is_relative() {
                *file = base.join(&*file);
            }
        }
        p.validate().with_context(|| format!("pipeline `{}`", path.display()))?;
        Ok(p)
    }

    /// Checks the fields that the stages would otherwise reject one by one.
    pub fn validate(&self) -> Result<()> {
        self.mode.parse::<Mode>().map_err(anyhow::Error::msg).context("field `mode`")?;
        if let Some(pace) = &self.pace {
            if pace != "max" && pace != "recorded" {
                bail!("field `pace`: `{pace}` (expected `max` or `recorded`)");
            }
        }
        let sources = [self.recording.is_some(), self.preset.is_some(), !self.cameras.is_empty()];
        match sources.iter().filter(|&&s| s).count() {
            0 => bail!("no source: give `recording` (a folder), `preset` (a synthetic scene) or `[[cameras]]` (live)"),
            1 => {}
            _ => bail!("fields `recording`, `preset` and `[[cameras]]`: give one source, not several"),
        }
        if self.record.is_some() && self.cameras.is_empty() {
            bail!("`record` needs live cameras (`[[cameras]]`): a recording or preset is already recorded");
        }
        if self.record_quality.is_some_and(|q| q > 51) {
            bail!("field `record_quality`: an H.264 quantizer, 0 (best) to 51");
        }
        if !self.cameras.is_empty() && self.calibration.is_none() {
            bail!("`[[cameras]]` need `calibration`: the file that says where each camera is");
        }
        for (k, camera) in self.cameras.iter().enumerate() {
            handflow_ingest::live::CameraSource::parse(&camera.source)
                .map_err(anyhow::Error::msg)
                .with_context(|| format!("`[[cameras]]` {} (`{}`)", k + 1, camera.name))?;
            if self.cameras[..k].iter().any(|c| c.name == camera.name) {
                bail!("`[[cameras]]`: camera `{}` is given twice", camera.name);
            }
        }
        if self.variant != "handflow" && self.variant != "paper" {
            bail!("field `variant`: `{}` (expected `handflow` or `paper`)", self.variant);
        }
        if self.services.is_empty() || self.services.contains(char::is_whitespace) {
            bail!("field `services`: `{}` is not a usable name prefix", self.services);
        }
        if self.viewer.enabled {
            self.viewer.listen.parse::<std::net::SocketAddr>().with_context(|| {
                format!("`[viewer] listen`: `{}` is not an address like 127.0.0.1:8787", self.viewer.listen)
            })?;
        }
        if !(self.viewer.thumbnails_hz.is_finite() && self.viewer.thumbnails_hz >= 0.0) {
            bail!("`[viewer] thumbnails_hz`: {} (expected 0 or more per second)", self.viewer.thumbnails_hz);
        }
        if let Some(z) = &self.network.zenoh {
            if z.listen.is_none() && z.connect.is_none() {
                bail!(
                    "`[network] zenoh`: give `listen` (for example \"{}\") or `connect`",
                    handflow_bridge::DEFAULT_ENDPOINT
                );
            }
            for (field, endpoint) in [("listen", &z.listen), ("connect", &z.connect)] {
                if let Some(endpoint) = endpoint {
                    handflow_bridge::check_endpoint(endpoint).with_context(|| format!("`[network] zenoh.{field}`"))?;
                }
            }
            for topic in &z.topics {
                topic
                    .parse::<handflow_bridge::Topic>()
                    .map_err(anyhow::Error::msg)
                    .context("`[network] zenoh.topics`")?;
            }
            if let Some(rig) = &z.rig {
                handflow_bridge::check_rig_name(rig).context("`[network] zenoh.rig`")?;
            }
        }
        Ok(())
    }

    /// The rig's name on the network: the one given, else the recording's folder name, the
    /// preset, or the calibration's folder name.
    pub fn rig_name(&self) -> String {
        if let Some(rig) = self.network.zenoh.as_ref().and_then(|z| z.rig.clone()) {
            return rig;
        }
        let from_path = |p: &Path| p.file_name().map(|n| n.to_string_lossy().into_owned());
        let name = match (&self.recording, &self.preset, &self.calibration) {
            (Some(r), _, _) => from_path(r),
            (None, Some(preset), _) => Some(preset.clone()),
            (None, None, Some(c)) => c.parent().and_then(from_path),
            _ => None,
        };
        handflow_bridge::rig_name_from(&name.unwrap_or_else(|| "live".into()))
    }

    /// Whether the run ends by itself (not looped, or a fixed number of frame sets).
    pub fn ends(&self) -> bool {
        !self.looped || self.frames.is_some()
    }
}

/// One stage process.
struct Stage {
    name: &'static str,
    program: PathBuf,
    args: Vec<String>,
    child: Option<Child>,
    restarts: u32,
    /// When the restarts of the last [`RESTART_WINDOW`] happened.
    recent_restarts: std::collections::VecDeque<Instant>,
    /// When the running process was started.
    started_at: Option<Instant>,
}

/// The progress services the launcher follows.
struct Progress {
    ingest: ipc::Input<StreamProgress, ()>,
    publish: ipc::Input<StreamProgress, ()>,
}

impl Stage {
    /// Sets option `flag` to `value` for the next start.
    fn set_arg(&mut self, flag: &str, value: String) {
        if let Some(i) = self.args.iter().position(|a| a == flag) {
            self.args.drain(i..=i + 1);
        }
        self.args.extend([flag.to_string(), value]);
    }

    fn new(name: &'static str, program: PathBuf, args: Vec<String>) -> Self {
        Self { name, program, args, child: None, restarts: 0, recent_restarts: Default::default(), started_at: None }
    }

    fn start(&mut self) -> Result<()> {
        let child = Command::new(&self.program)
            .args(&self.args)
            .env(ipc::LAUNCHER_PID_ENV, std::process::id().to_string())
            .stdin(Stdio::null())
            .spawn()
            .with_context(|| format!("starting `{}`", self.program.display()))?;
        tracing::info!("started {} (pid {})", self.name, child.id());
        self.child = Some(child);
        self.started_at = Some(Instant::now());
        Ok(())
    }

    fn pid(&self) -> Option<Pid> {
        self.child.as_ref().and_then(|c| i32::try_from(c.id()).ok()).map(Pid::from_raw)
    }
}

/// How a run ended.
#[derive(Clone, Debug, Default)]
pub struct RunReport {
    /// Stage restarts, by stage name.
    pub restarts: Vec<(String, u32)>,
    /// Whether the stream ended (rather than the run being interrupted).
    pub completed: bool,
    /// Wall time, seconds.
    pub seconds: f64,
}

/// The folder holding the stage binaries: the one `handflow` itself is in.
pub fn stage_dir() -> Result<PathBuf> {
    let exe = std::env::current_exe().context("locating the handflow binary")?;
    Ok(exe.parent().map(Path::to_path_buf).unwrap_or_default())
}

fn stage_binary(dir: &Path, name: &str) -> Result<PathBuf> {
    let path = dir.join(name);
    if !path.is_file() {
        bail!(
            "stage binary `{}` not found: build every binary with `cargo build --release` from the repository root",
            path.display()
        );
    }
    Ok(path)
}

/// How long stages get to stop after SIGTERM before they are killed.
const STOP_GRACE: Duration = Duration::from_secs(3);

/// Runs a pipeline until its stream ends, it is interrupted (SIGINT/SIGTERM), or a stage
/// keeps dying.
pub fn run_pipeline(p: &Pipeline) -> Result<RunReport> {
    p.validate()?;
    let dir = stage_dir()?;
    let mode = p.mode.clone();
    let common = |mut v: Vec<String>| {
        v.extend(["--mode".into(), mode.clone(), "--services".into(), p.services.clone()]);
        v
    };
    let mut ingest_args = Vec::new();
    if let Some(r) = &p.recording {
        ingest_args.extend(["--recording".into(), r.display().to_string()]);
    }
    if let Some(preset) = &p.preset {
        ingest_args.extend(["--preset".into(), preset.clone()]);
    }
    if !p.cameras.is_empty() {
        ingest_args.extend(["--cameras-json".into(), serde_json::to_string(&p.cameras)?]);
    }
    if let Some(dir) = &p.record {
        ingest_args.extend(["--record".into(), dir.display().to_string()]);
    }
    if let Some(q) = p.record_quality {
        ingest_args.extend(["--record-quality".into(), q.to_string()]);
    }
    if let Some(pace) = &p.pace {
        ingest_args.extend(["--pace".into(), pace.clone()]);
    }
    if p.looped {
        ingest_args.push("--loop".into());
    }
    if let Some(n) = p.frames {
        ingest_args.extend(["--frames".into(), n.to_string()]);
    }
    if p.preload {
        ingest_args.push("--preload".into());
    }
    if let Some(start) = p.start {
        ingest_args.extend(["--start".into(), start.to_string()]);
    }
    if let Some(calibration) = &p.calibration {
        ingest_args.extend(["--calibration".into(), calibration.display().to_string()]);
    }
    // A recording's up as `track` takes it (the faces' where they overrule the cameras'), so
    // a replay tracks on the same rig. A recording that does not open is the ingest stage's
    // to report, as it reports every fault of its input.
    let up = match (&p.recording, p.up) {
        (Some(dir), None) => {
            let options =
                handflow_ingest::OpenOptions { calibration: p.calibration.clone(), start: p.start, frames: None };
            match handflow_ingest::Recording::open_with(dir, &options) {
                Ok(rec) => crate::recording_engine::tracking_up(&rec, None)?,
                Err(_) => None,
            }
        }
        (_, up) => up,
    };
    if let Some([x, y, z]) = up {
        ingest_args.push(format!("--up={x},{y},{z}"));
    }
    let mut publish_args = Vec::new();
    if let Some(out) = &p.out {
        publish_args.extend(["--out".into(), out.display().to_string()]);
    }
    if p.ends() {
        publish_args.push("--exit-at-end".into());
    }
    if p.viewer.enabled {
        publish_args.extend([
            "--viewer".into(),
            p.viewer.listen.clone(),
            "--thumbnail-hz".into(),
            p.viewer.thumbnails_hz.to_string(),
        ]);
        if p.viewer.listen.ends_with(":0") {
            tracing::info!("viewer: the publisher picks a free port and logs its address");
        } else {
            tracing::info!("viewer: open http://{}/ in a browser", p.viewer.listen);
        }
    }
    let bridge_args = p.network.zenoh.as_ref().map(|z| {
        let mut args = vec!["--rig".to_string(), p.rig_name()];
        if let Some(endpoint) = &z.listen {
            args.extend(["--listen".into(), endpoint.clone()]);
        }
        if let Some(endpoint) = &z.connect {
            args.extend(["--connect".into(), endpoint.clone()]);
        }
        if !z.topics.is_empty() {
            args.extend(["--topics".into(), z.topics.join(",")]);
        }
        if p.ends() {
            args.push("--exit-at-end".into());
        }
        args
    });
    // A replay forwards every sample: the publisher waits for the bridge's subscription
    // before its first sample (live, it does not wait for anyone).
    if bridge_args.is_some() && p.mode == "replay" {
        publish_args.extend(["--subscribers".into(), "1".into()]);
    }
    // Downstream first, so each stage finds its subscriber waiting.
    let mut stages = vec![
        Stage::new("publish", stage_binary(&dir, "handflow-publish")?, common(publish_args)),
        Stage::new("cluster", stage_binary(&dir, "handflow-cluster")?, common(Vec::new())),
        Stage::new("flow", stage_binary(&dir, "handflow-flow")?, common(vec!["--variant".into(), p.variant.clone()])),
        Stage::new("ingest", stage_binary(&dir, "handflow-ingest")?, common(ingest_args)),
    ];
    if let Some(args) = bridge_args {
        // First, so it subscribes before anything is published.
        stages.insert(0, Stage::new(BRIDGE, stage_binary(&dir, "handflow-bridge")?, common(args)));
    }
    let node = ipc::create_node("handflow-run")?;
    let cleaned = ipc::cleanup_dead_nodes(&node);
    if cleaned > 0 {
        tracing::info!("cleaned up {cleaned} dead node(s) of an earlier run");
    }
    let names = ipc::ServiceNames::new(&p.services);
    // Held until this run ends: a second launcher under the same prefix is refused by the
    // lock, stages started by hand by their services.
    let _lock = lock_the_prefix(&names)?;
    refuse_a_running_pipeline(&node, &names)?;
    // How far ingest and the publisher have got, for a stage that has to be restarted.
    let progress = Progress {
        ingest: ipc::progress_input(&node, &names, "ingest")?,
        publish: ipc::progress_input(&node, &names, "publish")?,
    };
    let started = Instant::now();
    let outcome = supervise(&node, &mut stages, p, &progress);
    stop_all(&mut stages, matches!(outcome, Ok(true)));
    let completed = outcome?;
    Ok(RunReport {
        restarts: stages.iter().map(|s| (s.name.to_string(), s.restarts)).collect(),
        completed,
        seconds: started.elapsed().as_secs_f64(),
    })
}

/// The lock of this prefix's pipeline, or an error naming who holds it.
fn lock_the_prefix(names: &ipc::ServiceNames) -> Result<std::fs::File> {
    let namespace = ipc::UserNamespace::of_this_process().map_err(|e| anyhow::anyhow!(e))?;
    match namespace.lock_pipeline(names.prefix()).map_err(|e| anyhow::anyhow!(e))? {
        Some(lock) => Ok(lock),
        None => Err(already_running(
            names,
            &format!("its launcher holds `{}`", namespace.pipeline_lock_path(names.prefix()).display()),
        )),
    }
}

/// Why a second pipeline under a running one's prefix is refused, and what to do instead.
fn already_running(names: &ipc::ServiceNames, evidence: &str) -> anyhow::Error {
    anyhow::anyhow!(
        "a pipeline is already running under the services prefix `{}` ({evidence}); stop it, or give this one \
         its own prefix with `--services NAME` (or `services = \"NAME\"` in the pipeline file)",
        names.prefix()
    )
}

/// Two pipelines under one prefix would mix their streams: the second is refused.
fn refuse_a_running_pipeline(node: &ipc::IpcNode, names: &ipc::ServiceNames) -> Result<()> {
    let running: Vec<&str> = ipc::stage_health(node, names).into_iter().filter(|(_, up)| *up).map(|(s, _)| s).collect();
    if !running.is_empty() {
        return Err(already_running(names, &format!("its {} up", running.join(", "))));
    }
    Ok(())
}

/// Starts the stages and watches them; `Ok(true)` when the stream ended, `Ok(false)` when
/// interrupted.
fn supervise(node: &ipc::IpcNode, stages: &mut [Stage], p: &Pipeline, progress: &Progress) -> Result<bool> {
    for stage in stages.iter_mut() {
        stage.start()?;
    }
    let (mut ingest, mut publish) = (None::<StreamProgress>, None::<StreamProgress>);
    loop {
        // Wakes on SIGINT/SIGTERM as well as every 20 ms.
        if !ipc::nap(node, Duration::from_millis(20)) {
            tracing::info!("interrupted: stopping every stage");
            return Ok(false);
        }
        while let Ok(Some(sample)) = progress.ingest.subscriber.receive() {
            ingest = Some(*sample.payload());
        }
        while let Ok(Some(sample)) = progress.publish.subscriber.receive() {
            publish = Some(*sample.payload());
        }
        for stage in stages.iter_mut() {
            let Some(child) = stage.child.as_mut() else { continue };
            let Some(status) = child.try_wait().context("watching a stage")? else { continue };
            stage.child = None;
            if stage.name == "publish" && p.ends() && status.success() {
                tracing::info!("the stream has ended: stopping the other stages");
                return Ok(true);
            }
            if stage.name == BRIDGE && p.ends() && status.success() {
                continue;
            }
            if stage.name == BRIDGE && stage.recent_restarts.len() as u32 >= p.max_restarts {
                // The network is an extra: the local pipeline goes on without it.
                tracing::error!(
                    "the Zenoh bridge ended ({status}) after {} restarts: going on without it",
                    stage.restarts
                );
                continue;
            }
            // Where the stream was, not its first frame set again; the publisher appends
            // to its file and goes on counting losses from where it was.
            match (stage.name, ingest, publish) {
                ("ingest", Some(at), _) => stage.set_arg("--resume-at", at.next.to_string()),
                ("publish", _, Some(at)) => stage.set_arg("--resume", format!("{},{}", at.next, at.lost)),
                _ => {}
            }
            restart(node, stage, status, p.max_restarts)?;
        }
    }
}

/// The window in which a stage may be restarted `max_restarts` times: a service that runs
/// for weeks survives a rare crash, a stage that crashes at once on every start does not loop.
const RESTART_WINDOW: Duration = Duration::from_secs(60);

/// A stage that ends with an error status this soon after its start met input it cannot use
/// (a video it cannot open, a calibration it refuses): starting it again would fail again.
const FAILED_AT_START: Duration = Duration::from_secs(60);

fn restart(node: &ipc::IpcNode, stage: &mut Stage, status: ExitStatus, max_restarts: u32) -> Result<()> {
    let now = Instant::now();
    // An error exit (not a signal) is the stage's own verdict, logged above.
    if status.code().is_some_and(|c| c != 0)
        && stage.started_at.is_some_and(|t| now.duration_since(t) < FAILED_AT_START)
    {
        bail!(
            "stage {} failed ({status}) {:.1} s after its start: see its error above; not restarting it",
            stage.name,
            stage.started_at.map_or(0.0, |t| now.duration_since(t).as_secs_f64())
        );
    }
    while stage.recent_restarts.front().is_some_and(|t| now.duration_since(*t) > RESTART_WINDOW) {
        stage.recent_restarts.pop_front();
    }
    if stage.recent_restarts.len() as u32 >= max_restarts {
        bail!(
            "stage {} ended ({status}) after {} restarts within {} s: giving up",
            stage.name,
            stage.recent_restarts.len(),
            RESTART_WINDOW.as_secs()
        );
    }
    stage.restarts += 1;
    stage.recent_restarts.push_back(now);
    // What the dead process held in shared memory would block a lossless publisher.
    let cleaned = ipc::cleanup_dead_nodes(node);
    tracing::warn!(
        "stage {} ended ({status}); cleaned {cleaned} dead node(s), restarting it ({} in the last minute, at most {max_restarts})",
        stage.name,
        stage.recent_restarts.len()
    );
    stage.start()
}

/// The optional stage that forwards trajectories to Zenoh.
const BRIDGE: &str = "bridge";

/// How long the bridge gets, after the stream ended, to forward its last samples.
const BRIDGE_DRAIN: Duration = Duration::from_secs(2);

/// SIGTERM to every stage still running, then SIGKILL to those that have not stopped
/// within [`STOP_GRACE`].
fn stop_all(stages: &mut [Stage], stream_ended: bool) {
    // The bridge exits by itself once it has forwarded the end of the stream.
    if let Some(bridge) = stages.iter_mut().find(|s| s.name == BRIDGE && stream_ended) {
        let deadline = Instant::now() + BRIDGE_DRAIN;
        while let Some(child) = bridge.child.as_mut() {
            if !matches!(child.try_wait(), Ok(None)) || Instant::now() >= deadline {
                break;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
    }
    for stage in stages.iter() {
        if let Some(pid) = stage.pid() {
            let _ = kill(pid, Signal::SIGTERM);
        }
    }
    let deadline = Instant::now() + STOP_GRACE;
    for stage in stages.iter_mut() {
        let Some(mut child) = stage.child.take() else { continue };
        loop {
            match child.try_wait() {
                Ok(Some(_)) | Err(_) => break,
                Ok(None) if Instant::now() >= deadline => {
                    tracing::warn!("stage {} did not stop within {STOP_GRACE:?}: killing it", stage.name);
                    let _ = child.kill();
                    let _ = child.wait();
                    break;
                }
                Ok(None) => std::thread::sleep(Duration::from_millis(10)),
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_pipeline_file_resolves_paths_next_to_itself_and_checks_its_fields() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("p.toml");
        std::fs::write(&path, "mode = \"live\"\nrecording = \"rec\"\nout = \"t.jsonl\"\n").unwrap();
        let p = Pipeline::load(&path).unwrap();
        assert_eq!(p.recording.as_deref(), Some(dir.path().join("rec").as_path()));
        assert_eq!(p.services, "handflow");
        std::fs::write(&path, "mode = \"fast\"\nrecording = \"rec\"\n").unwrap();
        let e = format!("{:#}", Pipeline::load(&path).unwrap_err());
        assert!(e.contains("mode") && e.contains("fast"), "{e}");
        std::fs::write(&path, "recording = \"rec\"\nspeed = 3\n").unwrap();
        let e = format!("{:#}", Pipeline::load(&path).unwrap_err());
        assert!(e.contains("speed"), "{e}");
        std::fs::write(&path, "mode = \"replay\"\n").unwrap();
        assert!(format!("{:#}", Pipeline::load(&path).unwrap_err()).contains("no source"));
    }

    #[test]
    fn live_cameras_need_their_calibration_a_known_source_kind_and_no_other_source() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("p.toml");
        let camera = |name: &str, source: &str| format!("\n[[cameras]]\nname = \"{name}\"\nsource = \"{source}\"\n");
        let load = |text: String| {
            std::fs::write(&path, text).unwrap();
            Pipeline::load(&path).map_err(|e| format!("{e:#}"))
        };
        let ok = load(format!(
            "calibration = \"rig.toml\"\n{}{}",
            camera("a", "v4l2:///dev/video0"),
            camera("b", "rtsp://h/s")
        ))
        .unwrap();
        assert_eq!(ok.cameras.len(), 2);
        assert_eq!(ok.calibration.as_deref(), Some(dir.path().join("rig.toml").as_path()));
        let e = load(camera("a", "v4l2:///dev/video0")).unwrap_err();
        assert!(e.contains("calibration"), "{e}");
        let e = load(format!("calibration = \"rig.toml\"\n{}", camera("a", "/dev/video0"))).unwrap_err();
        assert!(e.contains("`a`") && e.contains("unknown kind"), "{e}");
        let e = load(format!(
            "calibration = \"rig.toml\"\n{}{}",
            camera("a", "gst:videotestsrc"),
            camera("a", "gst:videotestsrc")
        ))
        .unwrap_err();
        assert!(e.contains("given twice"), "{e}");
        let e = load(format!("recording = \"rec\"\ncalibration = \"rig.toml\"\n{}", camera("a", "gst:videotestsrc")))
            .unwrap_err();
        assert!(e.contains("not several"), "{e}");
    }

    #[test]
    fn the_viewer_is_on_and_on_loopback_by_default_and_its_table_is_checked() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("p.toml");
        let load = |viewer: &str| {
            std::fs::write(&path, format!("recording = \"r\"\n[viewer]\n{viewer}\n")).unwrap();
            Pipeline::load(&path).map_err(|e| format!("{e:#}"))
        };
        let p = load("").unwrap();
        assert!(p.viewer.enabled);
        assert!(p.viewer.listen.parse::<std::net::SocketAddr>().unwrap().ip().is_loopback());
        let off = load("enabled = false\nlisten = \"not checked when off\"").unwrap();
        assert!(!off.viewer.enabled);
        assert!(load("listen = \"localhost\"").unwrap_err().contains("`[viewer] listen`"));
        assert!(load("thumbnails_hz = -1.0").unwrap_err().contains("thumbnails_hz"));
        assert!(load("port = 8080").unwrap_err().contains("port"));
    }

    #[test]
    fn a_network_table_names_a_tcp_endpoint_and_known_topics_and_gives_the_rig_a_key_name() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("p.toml");
        let load = |network: &str| {
            std::fs::write(&path, format!("recording = \"sessions/studio a\"\n[network]\n{network}\n")).unwrap();
            Pipeline::load(&path).map_err(|e| format!("{e:#}"))
        };
        let p = load("zenoh = { listen = \"tcp/127.0.0.1:7447\", topics = [\"clusters\"] }").unwrap();
        assert_eq!(p.rig_name(), "studio_a");
        assert_eq!(p.network.zenoh.as_ref().unwrap().topics, ["clusters"]);
        assert!(load("zenoh = { }").unwrap_err().contains("give `listen`"));
        assert!(load("zenoh = { listen = \"udp/127.0.0.1:7447\" }").unwrap_err().contains("zenoh.listen"));
        assert!(load("zenoh = { connect = \"tcp/h:1\", topics = [\"frames\"] }").unwrap_err().contains("`frames`"));
        assert!(load("zenoh = { listen = \"tcp/h:1\", rig = \"a/b\" }").unwrap_err().contains("zenoh.rig"));
        assert!(load("zenoh = { listen = \"tcp/h:1\", port = 3 }").unwrap_err().contains("port"));
        let named = load("zenoh = { connect = \"tcp/h:1\", rig = \"studio-b\" }").unwrap();
        assert_eq!(named.rig_name(), "studio-b");
        assert!(load("").unwrap().network.zenoh.is_none());
    }

    #[test]
    fn the_example_pipeline_files_are_valid() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("pipelines");
        let mut seen = 0;
        for entry in std::fs::read_dir(&dir).unwrap() {
            let path = entry.unwrap().path();
            if path.extension().is_some_and(|e| e == "toml") {
                Pipeline::load(&path).unwrap_or_else(|e| panic!("{}: {e:#}", path.display()));
                seen += 1;
            }
        }
        assert!(seen >= 2);
    }
}
