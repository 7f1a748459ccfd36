//! `handflow-ingest`: fake cameras. Publishes the rig calibration (history 1) and one frame
//! set per instant, decoded (or rendered) straight into the loaned shared-memory sample.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use clap::Parser;
use handflow_ingest::live::{
    camera::{clock_now_ns, init_clock},
    sync::MAX_WAITING_FRAMES,
    CameraFeed, CameraSource, FeedEvent, FeedSpec, FrameSetSync, LiveCamera, LiveCameraSpec, RecordingWriter,
    StartOptions,
};
use handflow_ingest::synthetic::{Renderer, SceneSpec};
use handflow_ingest::{OpenOptions, Recording};
use handflow_protocol::ipc::{self, Mode, ServiceNames};
use handflow_protocol::messages::{
    camera_state, CameraStatusSet, FrameHeader, RigHeader, StreamProgress, END_OF_STREAM, MAX_FRAME_VIEWS,
    MAX_STATUS_CAMERAS, PIXEL_FORMAT_RGB8, PROTOCOL_VERSION,
};
use handflow_protocol::Rig;

#[derive(Parser, Debug)]
#[command(name = "handflow-ingest", about = "Fake cameras: replay a recording or render a synthetic scene")]
struct Args {
    /// Recording folder to replay.
    #[arg(long, conflicts_with_all = ["preset", "cameras_json"])]
    recording: Option<PathBuf>,
    /// Live cameras, as the pipeline file's `[[cameras]]` in JSON (the launcher passes
    /// them); their calibration comes from `--calibration`.
    #[arg(long, conflicts_with = "preset", requires = "calibration")]
    cameras_json: Option<String>,
    /// Live cameras: also write every published frame set as a recording in this folder
    /// (new or empty), which `handflow run` and `handflow track` replay.
    #[arg(long, requires = "cameras_json")]
    record: Option<PathBuf>,
    /// Quality of the recorded videos: H.264 at this quantizer (0 best, 51 worst); without
    /// it, lossless (FFV1).
    #[arg(long, requires = "record")]
    record_quality: Option<u32>,
    /// Built-in synthetic scene to render live instead (signer-3cam, hands-cross, ...).
    #[arg(long)]
    preset: Option<String>,
    /// Delivery mode: `replay` (nothing dropped) or `live` (latest wins).
    #[arg(long, default_value = "replay")]
    mode: Mode,
    /// Pace: `recorded` (the source's frame rate) or `max` (as fast as the pipeline takes it).
    /// Default: `max` in replay mode, `recorded` in live mode.
    #[arg(long)]
    pace: Option<Pace>,
    /// Start again at the first frame after the last, forever.
    #[arg(long = "loop")]
    looped: bool,
    /// Decode the whole recording into memory before publishing, so a frame set costs one
    /// copy instead of decoding its images: cameras that deliver raw frames, as real ones
    /// do (at most 4 GiB of frame sets).
    #[arg(long, conflicts_with = "preset")]
    preload: bool,
    /// Publish only the first N frames.
    #[arg(long)]
    frames: Option<u64>,
    /// Calibration file to use instead of the recording's own.
    #[arg(long, conflicts_with = "preset")]
    calibration: Option<PathBuf>,
    /// First frame number of the recording to publish (seeks in videos).
    #[arg(long, conflicts_with = "preset")]
    start: Option<u64>,
    /// The world's up direction `x,y,z`, published with the rig (overrides the calibration's
    /// or the estimate from the cameras).
    #[arg(long, value_parser = handflow_protocol::rig::parse_direction, allow_negative_numbers = true)]
    up: Option<[f64; 3]>,
    /// The frame set to start at: the launcher restarts a dead ingest where the stream was
    /// (the progress ingest publishes on `<services>/progress/ingest` after each frame set).
    #[arg(long)]
    resume_at: Option<u64>,
    /// Prefix of the service names.
    #[arg(long, default_value = ipc::DEFAULT_PREFIX)]
    services: String,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
enum Pace {
    Recorded,
    Max,
}

/// Where frame sets come from.
enum Source {
    Recording(Box<Recording>),
    Synthetic { renderer: Box<Renderer>, masks: Vec<u8> },
}

impl Source {
    fn rig(&self) -> &Rig {
        match self {
            Source::Recording(r) => r.rig(),
            Source::Synthetic { renderer, .. } => renderer.rig(),
        }
    }

    fn frame_rate(&self) -> f64 {
        match self {
            Source::Recording(r) => r.frame_rate(),
            Source::Synthetic { renderer, .. } => renderer.spec().fps,
        }
    }

    fn len(&self) -> u64 {
        match self {
            Source::Recording(r) => r.len() as u64,
            Source::Synthetic { renderer, .. } => u64::from(renderer.spec().frames),
        }
    }

    /// Fills `dst` with replay position `sequence`; returns its frame number, stream time and
    /// the views it lacks (a camera that dropped its frame), or `None` for a frame set that
    /// cannot be read (already reported: the stream goes on without it).
    fn fill(&mut self, sequence: u64, looped: bool, dst: &mut [u8]) -> Result<Option<(u64, f64, u32)>> {
        match self {
            Source::Recording(r) => match r.read_frame_into(sequence, looped, dst) {
                Ok(info) => Ok(Some((info.frame, info.timestamp, info.missing_views))),
                Err(error) if error.is_bad_frame() => {
                    tracing::error!("frame set {sequence} skipped, counted as dropped: {error}");
                    Ok(None)
                }
                Err(error) => Err(error.into()),
            },
            Source::Synthetic { renderer, masks } => {
                let n = u64::from(renderer.spec().frames.max(1));
                let frame = (sequence % n) as u32;
                renderer.render_into(frame, dst, masks);
                // Time keeps increasing across loops.
                Ok(Some((u64::from(frame), sequence as f64 / renderer.spec().fps, 0)))
            }
        }
    }
}

fn main() {
    ipc::init_logging();
    ipc::exit_with(run(Args::parse()))
}

fn run(args: Args) -> Result<()> {
    if let Some(json) = &args.cameras_json {
        let specs: Vec<LiveCameraSpec> = serde_json::from_str(json).context("`--cameras-json`")?;
        return run_live(&args, &specs);
    }
    let mut source = match (&args.recording, &args.preset) {
        (Some(dir), _) => {
            let options = OpenOptions { calibration: args.calibration.clone(), start: args.start, frames: None };
            let mut recording = Recording::open_with(dir, &options)?;
            tracing::info!("recording `{}`: {}", dir.display(), recording.summary());
            if args.preload {
                let started = Instant::now();
                recording.preload()?;
                tracing::info!(
                    "preloaded {} frame sets of `{}` in {:.1} s",
                    recording.len(),
                    dir.display(),
                    started.elapsed().as_secs_f64()
                );
            }
            Source::Recording(Box::new(recording))
        }
        (None, Some(name)) => {
            let spec = SceneSpec::preset(name).with_context(|| format!("unknown preset `{name}`"))?;
            let renderer = Renderer::new(&spec).map_err(anyhow::Error::msg)?;
            let masks = vec![0u8; renderer.view_len() / 3 * renderer.rig().cameras.len()];
            Source::Synthetic { renderer: Box::new(renderer), masks }
        }
        (None, None) => bail!("give a recording (--recording DIR) or a synthetic scene (--preset NAME)"),
    };
    let cameras = &source.rig().cameras;
    // Each view travels at its camera's size: a camera mounted sideways sends portrait frames.
    let Some(view_sizes) = FrameHeader::sizes_of(cameras.iter().map(|c| (c.width, c.height))) else {
        bail!("the rig has {} cameras; a streamed frame set carries at most {MAX_FRAME_VIEWS}", cameras.len());
    };
    let sizes = FrameHeader::describe_sizes(cameras.iter().map(|c| (c.width, c.height)));
    let view_count = cameras.len() as u32;
    let frame_set_len = cameras.iter().map(|c| c.width as usize * c.height as usize * 3).sum::<usize>();
    let pace = args.pace.unwrap_or(match args.mode {
        Mode::Replay => Pace::Max,
        Mode::Live => Pace::Recorded,
    });
    let names = ServiceNames::new(&args.services);
    let node = ipc::stage_node("handflow-ingest")?;
    // Kept alive: the rig's history lives as long as its publisher.
    let mut published_rig = source.rig().clone();
    if let Some(up) = &args.up {
        published_rig.set_up(nalgebra::Vector3::new(up[0], up[1], up[2]))?;
    }
    let up = published_rig.world_up();
    tracing::info!("world up {:?} ({})", up.direction.as_slice(), up.source);
    let rig = publish_rig(&node, &names, &published_rig, source.frame_rate())?;
    let frames = ipc::frames_output(&node, &names, args.mode, frame_set_len)?;
    let shape = FrameShape { view_count, view_sizes, len: frame_set_len };
    // Replay loses nothing: the flow stage must listen before a frame goes out (at the start
    // and after a restart of flow). Meanwhile late joiners get the rig.
    let wait_for_flow = || wait_for_flow(&node, &names, &rig, &frames);
    if args.mode == Mode::Replay && !wait_for_flow() {
        return Ok(());
    }
    let total = match (args.looped, args.frames) {
        (true, n) => n.unwrap_or(u64::MAX),
        (false, n) => n.unwrap_or(source.len()).min(source.len()),
    };
    tracing::info!(
        "publishing {} frame sets of {view_count} x {sizes} on `{}` ({} mode, {} pace)",
        if total == u64::MAX { "endless".to_string() } else { total.to_string() },
        frames.name(),
        args.mode,
        if pace == Pace::Max { "maximum" } else { "recorded" },
    );
    let interval = Duration::from_secs_f64(1.0 / source.frame_rate());
    let progress = ipc::progress_output(&node, &names, "ingest")?;
    // A stage killed after its last frame set resumes at the end and only ends the stream.
    let resume_from = args.resume_at.filter(|&p| p > 0).map(|p| p.min(total));
    if let Some(position) = resume_from {
        tracing::info!("resuming the stream at frame set {position} (restarted)");
    }
    let first = resume_from.unwrap_or(0);
    // Paced as if the stream had run from its first frame set.
    let already = interval.saturating_mul(first.min(u64::from(u32::MAX)) as u32);
    let started = Instant::now().checked_sub(already).unwrap_or_else(Instant::now);
    let mut history = HistoryHandOut::default();
    for sequence in first..total {
        if ipc::stop_requested() {
            return Ok(());
        }
        if pace == Pace::Recorded {
            let due = interval.saturating_mul(sequence.min(u64::from(u32::MAX)) as u32);
            if let Some(wait) = due.checked_sub(started.elapsed()) {
                if !wait_serving_history(&node, &frames, &mut history, args.mode, wait)? {
                    return Ok(());
                }
            }
        }
        let sent = send_until_delivered(&node, args.mode, || {
            rig.update_connections();
            if args.mode == Mode::Replay && frames.flow_subscribers(&node, &names) == 0 && !wait_for_flow() {
                return Ok(None);
            }
            send_frame_set(&mut source, &frames, sequence, args.looped, shape).map(Some)
        })?;
        let Some(sent) = sent else { return Ok(()) };
        if sent == Sent::Skipped {
            // Never sent: the publisher sees the gap in sequence numbers and counts it.
            progress.report(StreamProgress { next: sequence + 1, lost: 0 });
            continue;
        }
        frames.notify()?;
        progress.report(StreamProgress { next: sequence + 1, lost: 0 });
        if sequence % 30 == 0 {
            tracing::debug!("frame set {sequence} sent");
        }
    }
    end_stream(&node, &frames, &rig, total, args.mode)
}

/// How long a replay waits before sending again a frame set its subscriber did not get.
const UNDELIVERED_RETRY: Duration = Duration::from_millis(20);

/// Sends with `send` (`None`: asked to stop) and, in replay, sends again every
/// [`UNDELIVERED_RETRY`] while it reached no subscriber. Replay loses nothing: a subscriber
/// that existed before this publisher (a restarted ingest) connects to it only at its next
/// read, which may be a second away, and until then samples beyond its buffer are skipped
/// without blocking. `None` when asked to stop.
fn send_until_delivered(
    node: &ipc::IpcNode,
    mode: Mode,
    mut send: impl FnMut() -> Result<Option<Sent>>,
) -> Result<Option<Sent>> {
    loop {
        match send()? {
            Some(Sent::Delivered(0)) if mode == Mode::Replay => {
                if !ipc::nap(node, UNDELIVERED_RETRY) {
                    return Ok(None);
                }
            }
            sent => return Ok(sent),
        }
    }
}

/// What became of a frame set.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Sent {
    /// Sent, reaching this many subscribers.
    Delivered(usize),
    /// Not readable: not sent (already reported).
    Skipped,
}

/// The frame set's shape on the wire.
#[derive(Clone, Copy, Debug)]
struct FrameShape {
    view_count: u32,
    view_sizes: [[u32; 2]; MAX_FRAME_VIEWS],
    /// Bytes of the whole set.
    len: usize,
}

/// Reads replay position `sequence` into a loaned sample, decoded in the shared memory
/// itself, and sends it.
fn send_frame_set(
    source: &mut Source,
    frames: &ipc::Output<[u8], FrameHeader>,
    sequence: u64,
    looped: bool,
    shape: FrameShape,
) -> Result<Sent> {
    // The moment the frame set is taken: decoding it (unless preloaded) is part of the
    // pipeline's latency.
    let capture_unix_ns = ipc::unix_now_ns();
    // Zero-initialised, so the decoder writes into plain bytes.
    let mut sample = frames.publisher.loan_slice(shape.len).context("loaning a frame sample")?;
    let filled =
        source.fill(sequence, looped, sample.payload_mut()).with_context(|| format!("frame set {sequence}"))?;
    let Some((frame, timestamp_s, missing_views)) = filled else {
        return Ok(Sent::Skipped);
    };
    *sample.user_header_mut() = FrameHeader {
        protocol_version: PROTOCOL_VERSION,
        pixel_format: PIXEL_FORMAT_RGB8,
        sequence,
        frame,
        timestamp_s,
        capture_unix_ns,
        rig_version: 1,
        view_count: shape.view_count,
        view_sizes: shape.view_sizes,
        flags: 0,
        missing_views,
        payload_len: shape.len as u64,
    };
    let delivered = sample.send().with_context(|| format!("sending frame set {sequence}"))?;
    Ok(Sent::Delivered(delivered))
}

/// Waits until the flow stage listens on `frames` (replay loses nothing downstream: at the
/// start and after a restart of flow), meanwhile serving the rig to late joiners. False when
/// the process is asked to stop.
fn wait_for_flow(
    node: &ipc::IpcNode,
    names: &ServiceNames,
    rig: &ipc::Output<[u8], RigHeader>,
    frames: &ipc::Output<[u8], FrameHeader>,
) -> bool {
    let mut announced = false;
    loop {
        rig.update_connections();
        // Flow's subscriber, not the viewer's: a replay that started for the viewer alone
        // lost its first frame sets to a flow stage that came a moment later.
        if frames.flow_subscribers(node, names) > 0 {
            frames.update_connections();
            return true;
        }
        if !announced {
            tracing::info!("waiting for a subscriber on `{}`", frames.name());
            announced = true;
        }
        if !ipc::nap(node, Duration::from_millis(5)) {
            return false;
        }
    }
}

/// How often a paced live stream looks for new subscribers between frame sets.
const CONNECTION_CHECK: Duration = Duration::from_millis(20);

/// Hands a live stream's frame history to subscribers as they arrive (a restarted flow
/// stage), and wakes them: history alone notifies nobody, and the next frame set may be a
/// sixth of a second away.
#[derive(Default)]
struct HistoryHandOut {
    subscribers: usize,
}

impl HistoryHandOut {
    fn serve(&mut self, frames: &ipc::Output<[u8], FrameHeader>) -> Result<()> {
        frames.update_connections();
        let now = frames.subscribers();
        if now > self.subscribers {
            frames.notify()?;
        }
        self.subscribers = now;
        Ok(())
    }
}

/// Waits `wait` (false when asked to stop), live handing the history out meanwhile.
fn wait_serving_history(
    node: &ipc::IpcNode,
    frames: &ipc::Output<[u8], FrameHeader>,
    history: &mut HistoryHandOut,
    mode: Mode,
    wait: Duration,
) -> Result<bool> {
    if mode == Mode::Replay {
        return Ok(ipc::nap(node, wait));
    }
    let until = Instant::now() + wait;
    loop {
        history.serve(frames)?;
        let left = until.saturating_duration_since(Instant::now());
        if left.is_zero() {
            return Ok(true);
        }
        if !ipc::nap(node, left.min(CONNECTION_CHECK)) {
            return Ok(false);
        }
    }
}

/// Sends the end of the stream after `total` frame sets and stays until stopped: the
/// samples in flight live in this process's memory.
fn end_stream(
    node: &ipc::IpcNode,
    frames: &ipc::Output<[u8], FrameHeader>,
    rig: &ipc::Output<[u8], RigHeader>,
    total: u64,
    mode: Mode,
) -> Result<()> {
    // As a frame set: a replay's flow stage must get it, however late it connects.
    let sent = send_until_delivered(node, mode, || {
        frames.update_connections();
        let mut end = frames.publisher.loan_slice(0).context("loaning the end-of-stream sample")?;
        *end.user_header_mut() = FrameHeader {
            protocol_version: PROTOCOL_VERSION,
            sequence: total,
            flags: END_OF_STREAM,
            ..FrameHeader::default()
        };
        let delivered = end.send().context("sending end of stream")?;
        frames.notify()?;
        Ok(Some(Sent::Delivered(delivered)))
    })?;
    if sent.is_none() {
        return Ok(());
    }
    tracing::info!("end of stream after {total} frame sets; waiting to be stopped");
    while ipc::nap(node, Duration::from_millis(100)) {
        rig.update_connections();
    }
    Ok(())
}

/// Frame rate assumed for live cameras whose rate the pipeline file does not give.
const DEFAULT_LIVE_FPS: f64 = 30.0;
/// Time given to build every camera's pipeline before videos played as cameras start
/// together.
const RIG_START_MARGIN: Duration = Duration::from_millis(300);
/// How long the cameras get to deliver their first frames.
const FIRST_FRAME_TIMEOUT: Duration = Duration::from_secs(15);
/// How often the cameras' rates, drops and ages are logged.
const LIVE_REPORT_EVERY: Duration = Duration::from_secs(5);
/// How often the cameras' health goes out on the `cameras` service.
const STATUS_EVERY: Duration = Duration::from_secs(1);

/// Live cameras: every camera of the calibration started from its `[[cameras]]` source,
/// frames grouped into frame sets by capture time and published as they are decided. Live
/// mode gives a camera that stops or falls behind a stall timeout of four frame intervals
/// (its sets are dropped and counted); replay mode waits for it.
fn run_live(args: &Args, specs: &[LiveCameraSpec]) -> Result<()> {
    let calibration = args.calibration.as_deref().context("live cameras need `--calibration`")?;
    let mut rig = Rig::load(calibration)?;
    if let Some(up) = &args.up {
        rig.set_up(nalgebra::Vector3::new(up[0], up[1], up[2]))?;
    }
    for spec in specs {
        if !rig.cameras.iter().any(|c| c.name == spec.name) {
            bail!(
                "camera `{}` of the pipeline is not in the calibration `{}` (its cameras: {})",
                spec.name,
                calibration.display(),
                rig.cameras.iter().map(|c| format!("`{}`", c.name)).collect::<Vec<_>>().join(", ")
            );
        }
    }
    let (width, height) = (rig.cameras[0].width, rig.cameras[0].height);
    let mut cameras = Vec::with_capacity(rig.cameras.len());
    let mut fps = None;
    // Videos played as cameras start together once all are built (a camera that takes
    // longer delivers its first frames late, still stamped with their own instants).
    init_clock().map_err(anyhow::Error::msg).context("starting GStreamer for the cameras")?;
    let rig_start_ns = clock_now_ns() + RIG_START_MARGIN.as_nanos() as u64;
    for cam in &rig.cameras {
        let spec = specs.iter().find(|s| s.name == cam.name).with_context(|| {
            format!("camera `{}` of the calibration has no `[[cameras]]` source in the pipeline", cam.name)
        })?;
        if (cam.width, cam.height) != (width, height) {
            bail!(
                "every live camera must have the same size, but `{}` is {}x{} and `{}` {width}x{height}",
                cam.name,
                cam.width,
                cam.height,
                rig.cameras[0].name
            );
        }
        if let Some([w, h]) = spec.size {
            if (w, h) != (cam.width, cam.height) {
                bail!("camera `{}`: `size = [{w}, {h}]` but its calibration is {}x{}", cam.name, cam.width, cam.height);
            }
        }
        let source = CameraSource::parse(&spec.source)
            .map_err(anyhow::Error::msg)
            .with_context(|| format!("camera `{}`", cam.name))?;
        fps = fps.or(spec.fps);
        // Replay loses nothing after the cameras: a camera's frames wait for the pipeline.
        let options = StartOptions { lossless: args.mode == Mode::Replay, rig_start_ns: Some(rig_start_ns) };
        let camera = LiveCamera::start_with(&cam.name, &source, cam.width, cam.height, spec.size, spec.fps, options)?;
        tracing::info!("camera `{}`: started from `{}`", cam.name, spec.source);
        let feed = FeedSpec {
            name: cam.name.clone(),
            source,
            width: cam.width,
            height: cam.height,
            size: spec.size,
            fps: spec.fps,
            options,
            detect_silence: args.mode == Mode::Live,
        };
        cameras.push(CameraFeed::new(feed, camera));
    }
    let fps = fps.unwrap_or(DEFAULT_LIVE_FPS);
    let interval_ns = (1e9 / fps) as u64;
    // Refused at start: a camera that fails (wrong size, no device) or delivers nothing.
    let mut sync = FrameSetSync::new(cameras.len(), interval_ns);
    for (k, camera) in cameras.iter().enumerate() {
        match camera.frame_timeout(FIRST_FRAME_TIMEOUT) {
            Some(frame) => sync.push(k, frame),
            None => bail!(
                "camera `{}`: {}",
                camera.name(),
                camera.failure().unwrap_or_else(|| format!("no frame within {} s", FIRST_FRAME_TIMEOUT.as_secs()))
            ),
        }
    }
    let names = ServiceNames::new(&args.services);
    let node = ipc::stage_node("handflow-ingest")?;
    let up = rig.world_up();
    tracing::info!("world up {:?} ({})", up.direction.as_slice(), up.source);
    let rig_output = publish_rig(&node, &names, &rig, fps)?;
    let frame_set_len = cameras.len() * width as usize * height as usize * 3;
    let Some(view_sizes) = FrameHeader::sizes_of(cameras.iter().map(|_| (width, height))) else {
        bail!("{} live cameras; a streamed frame set carries at most {MAX_FRAME_VIEWS}", cameras.len());
    };
    let frames = ipc::frames_output(&node, &names, args.mode, frame_set_len)?;
    let status_output = ipc::cameras_output(&node, &names)?;
    if cameras.len() > MAX_STATUS_CAMERAS {
        tracing::warn!("the `cameras` service describes the first {MAX_STATUS_CAMERAS} of {} cameras", cameras.len());
    }
    let stall_ns = match args.mode {
        Mode::Live => 4 * interval_ns,
        Mode::Replay => u64::MAX,
    };
    let total = args.frames.unwrap_or(u64::MAX);
    tracing::info!(
        "publishing live frame sets of {} x {width}x{height} at {fps} fps on `{}` ({} mode)",
        cameras.len(),
        frames.name(),
        args.mode
    );
    // Replay mode loses nothing downstream: the flow stage listens before a set goes out
    // (the cameras' frames meanwhile wait in their hand-over).
    let wait_for_flow = || wait_for_flow(&node, &names, &rig_output, &frames);
    if args.mode == Mode::Replay && !wait_for_flow() {
        return Ok(());
    }
    let mut recorder = match &args.record {
        Some(dir) => {
            let writer = RecordingWriter::create(dir, &rig, fps, args.record_quality)?;
            tracing::info!("recording every frame set into `{}`", dir.display());
            Some(writer)
        }
        None => None,
    };
    // Capture times are on the monotonic clock; the wall clock's offset from it dates them.
    let unix_offset = ipc::unix_now_ns() as i128 - clock_now_ns() as i128;
    let (mut sequence, mut first_instant) = (0u64, None);
    let mut last_report = Instant::now();
    let mut failed = vec![false; cameras.len()];
    let mut gone = vec![false; cameras.len()];
    let mut delivered = vec![0u64; cameras.len()];
    let mut status = CameraHealth { delivered: vec![0; cameras.len()], since: Instant::now(), unix_offset };
    let mut unrecorded = 0u64;
    let mut history = HistoryHandOut::default();
    let reference = rig.most_frontal_camera();
    while sequence < total && !ipc::stop_requested() {
        for (k, camera) in cameras.iter_mut().enumerate() {
            // Read before the hand-over is emptied: an ended source is over once its last
            // frames are out of the hand-over too.
            let source_ended = camera.ended();
            // Replay: a camera's frames stay in its hand-over (holding the source back)
            // rather than overflow the synchroniser.
            loop {
                if args.mode == Mode::Replay && sync.waiting(k) >= MAX_WAITING_FRAMES {
                    break;
                }
                let Some(frame) = camera.try_frame() else {
                    if source_ended && !gone[k] {
                        sync.finish_camera(k);
                        gone[k] = true;
                    }
                    break;
                };
                tracing::trace!("camera `{}`: frame captured at {} ns", camera.name(), frame.capture_ns);
                sync.push(k, frame);
            }
            if gone[k] {
                continue;
            }
            match camera.poll(Instant::now()) {
                FeedEvent::Unchanged => {}
                FeedEvent::Failed(problem) => {
                    tracing::error!("camera `{}` stopped: {problem}", camera.name());
                    failed[k] = true;
                    // A failed camera delivers nothing more: sets stop waiting for it.
                    sync.finish_camera(k);
                    gone[k] = true;
                }
                FeedEvent::Lost(problem) => {
                    // The stream goes on without it while it is opened again.
                    tracing::warn!("camera `{}` lost: {problem}; opening it again", camera.name());
                    sync.finish_camera(k);
                }
                FeedEvent::Back { attempts, away } => {
                    tracing::info!(
                        "camera `{}`: back after {:.2} s ({attempts} attempt{})",
                        camera.name(),
                        away.as_secs_f64(),
                        if attempts == 1 { "" } else { "s" }
                    );
                    sync.rejoin_camera(k);
                }
            }
        }
        // Once every source has ended, what is left is decided at once; a camera that ended
        // or failed is not waited for (the synchroniser knows).
        let ended = gone.iter().all(|&g| g);
        let (now, stall) = if ended { (u64::MAX, 0) } else { (clock_now_ns(), stall_ns) };
        // The engine can go on without a camera while the reference camera (where its rays
        // start) and one other are there.
        let carried = |present: &[bool]| present[reference] && present.iter().filter(|&&p| p).count() >= 2;
        while let Some((instant, views)) = sync.next_set_or_partial(now, stall, carried) {
            rig_output.update_connections();
            if args.mode == Mode::Replay && frames.flow_subscribers(&node, &names) == 0 && !wait_for_flow() {
                return Ok(());
            }
            let first = *first_instant.get_or_insert(instant);
            let mut sample = frames.publisher.loan_slice(frame_set_len).context("loaning a frame sample")?;
            // A missing view stays zero, as the loan leaves it.
            let mut missing_views = 0u32;
            for (k, (dst, view)) in
                sample.payload_mut().chunks_exact_mut(frame_set_len / cameras.len()).zip(&views).enumerate()
            {
                match view {
                    Some(view) => dst.copy_from_slice(&view.data),
                    None => missing_views |= 1 << k,
                }
            }
            *sample.user_header_mut() = FrameHeader {
                protocol_version: PROTOCOL_VERSION,
                pixel_format: PIXEL_FORMAT_RGB8,
                sequence,
                frame: sequence,
                timestamp_s: (instant - first) as f64 * 1e-9,
                capture_unix_ns: (instant as i128 + unix_offset).max(0) as u64,
                rig_version: 1,
                view_count: cameras.len() as u32,
                view_sizes,
                flags: 0,
                missing_views,
                payload_len: frame_set_len as u64,
            };
            // A recording holds whole frame sets only: a replay cannot tell a missing view.
            if let Some(writer) = recorder.as_mut() {
                if missing_views == 0 {
                    let header = sample.user_header();
                    writer.write_set(header.frame, header.timestamp_s, sample.payload())?;
                } else {
                    unrecorded += 1;
                }
            }
            sample.send().with_context(|| format!("sending frame set {sequence}"))?;
            frames.notify()?;
            sequence += 1;
            if sequence >= total {
                break;
            }
        }
        if last_report.elapsed() >= LIVE_REPORT_EVERY {
            report_cameras(&cameras, &sync, &mut delivered, last_report.elapsed().as_secs_f64());
            last_report = Instant::now();
        }
        if status.since.elapsed() >= STATUS_EVERY {
            status.publish(&status_output, &cameras, &sync, &failed, sequence)?;
        }
        if ended {
            tracing::info!("every camera's source has ended");
            break;
        }
        if args.mode == Mode::Live {
            history.serve(&frames)?;
        }
        if !ipc::nap(&node, Duration::from_millis(2)) {
            return Ok(());
        }
    }
    report_cameras(&cameras, &sync, &mut delivered, last_report.elapsed().as_secs_f64());
    status.publish(&status_output, &cameras, &sync, &failed, sequence)?;
    if let Some(writer) = recorder {
        let written = writer.written();
        let dir = writer.finish()?;
        tracing::info!("recorded {written} frame sets into `{}`", dir.display());
        if unrecorded > 0 {
            tracing::warn!("{unrecorded} frame sets some camera missed were tracked but not recorded");
        }
    }
    if sync.partial_sets() > 0 {
        tracing::warn!("{} frame sets went on without a camera that had no frame for them", sync.partial_sets());
    }
    end_stream(&node, &frames, &rig_output, sequence, args.mode)
}

/// The live cameras' health for the `cameras` service.
struct CameraHealth {
    /// Each camera's delivered count at the last status.
    delivered: Vec<u64>,
    /// When the last status went out.
    since: Instant,
    /// Unix time minus the capture clock, nanoseconds.
    unix_offset: i128,
}

impl CameraHealth {
    /// Publishes every camera's health now; `frame_sets` published so far.
    fn publish(
        &mut self,
        out: &ipc::Output<CameraStatusSet, ()>,
        cameras: &[CameraFeed],
        sync: &FrameSetSync,
        failed: &[bool],
        frame_sets: u64,
    ) -> Result<()> {
        let seconds = self.since.elapsed().as_secs_f64().max(1e-3);
        self.since = Instant::now();
        let mut set = CameraStatusSet {
            protocol_version: PROTOCOL_VERSION,
            camera_count: cameras.len().min(MAX_STATUS_CAMERAS) as u32,
            published_unix_ns: ipc::unix_now_ns(),
            frame_sets,
            ..CameraStatusSet::default()
        };
        for (k, (camera, stats)) in cameras.iter().zip(sync.stats()).enumerate().take(MAX_STATUS_CAMERAS) {
            let count = camera.delivered();
            let status = &mut set.cameras[k];
            status.set_name(camera.name());
            status.rate_hz = (count - self.delivered[k].min(count)) as f64 / seconds;
            self.delivered[k] = count;
            status.delivered = count;
            status.used = stats.used;
            status.dropped = stats.dropped + camera.handover_dropped();
            status.missed_sets = stats.missed_sets;
            status.last_capture_unix_ns =
                stats.last_capture_ns.map_or(0, |t| (t as i128 + self.unix_offset).max(0) as u64);
            status.state = if failed[k] {
                camera_state::FAILED
            } else if camera.is_lost() {
                camera_state::RECONNECTING
            } else if camera.ended() {
                camera_state::ENDED
            } else {
                camera_state::RUNNING
            };
        }
        out.publisher.send_copy(set).context("sending the cameras' health")?;
        out.notify()?;
        Ok(())
    }
}

/// One log line per camera: its rate over the last `seconds`, frames in sets and dropped,
/// sets it missed, age of its newest frame. `delivered` holds each camera's count at the
/// last report.
fn report_cameras(cameras: &[CameraFeed], sync: &FrameSetSync, delivered: &mut [u64], seconds: f64) {
    let now = clock_now_ns();
    for ((camera, stats), before) in cameras.iter().zip(sync.stats()).zip(delivered.iter_mut()) {
        let count = camera.delivered();
        let rate = (count - (*before).min(count)) as f64 / seconds.max(1e-3);
        *before = count;
        let age = stats
            .last_capture_ns
            .map_or("never".to_string(), |t| format!("{:.0} ms ago", now.saturating_sub(t) as f64 * 1e-6));
        tracing::info!(
            "camera `{}`: {rate:.1} frames/s, {count} delivered, {} in frame sets, {} dropped ({} in the hand-over), \
             {} sets missed; last frame {age}",
            camera.name(),
            stats.used,
            stats.dropped + camera.handover_dropped(),
            camera.handover_dropped(),
            stats.missed_sets,
        );
    }
}

fn publish_rig(
    node: &ipc::IpcNode,
    names: &ServiceNames,
    rig: &Rig,
    frame_rate_hz: f64,
) -> Result<ipc::Output<[u8], RigHeader>> {
    let out = ipc::rig_output(node, names)?;
    let text = rig.to_toml_string();
    let mut sample = out.publisher.loan_slice(text.len()).context("loaning the rig sample")?;
    sample.payload_mut().copy_from_slice(text.as_bytes());
    *sample.user_header_mut() =
        RigHeader { protocol_version: PROTOCOL_VERSION, rig_version: 1, frame_rate_hz, text_len: text.len() as u64 };
    sample.send().context("sending the rig")?;
    out.notify()?;
    Ok(out)
}
