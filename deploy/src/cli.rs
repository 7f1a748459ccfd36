//! The `handflow` command line: argument parsing and reports. Each command is a thin layer
//! over the library modules.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{Context, Result};
use clap::{Args, Parser, Subcommand};
use handflow_flow::Variant;
use serde_json::json;

use crate::commands::track::{track_recording, TrackOptions};
use crate::eval::middlebury::{write_maps, Layout};
use crate::eval::middlebury_run::{engine_config, load_problem, run_once, EvalOptions, RunResult};
use crate::eval::tracks::{evaluate_tracks, read_tracks};
use crate::recording_engine::bench_recording;
use handflow_ingest::synthetic::{write_recording, Renderer, SceneSpec, PRESETS};

/// Where the demo looks for the built-in scene, relative to the working directory.
pub const DEFAULT_SCENE: &str = "../shared/data/middlebury/teddy";

/// handflow: 3D trajectories of head and hands from calibrated cameras, by clustered scene
/// flow. Without a command, runs the demo: the streaming pipeline on the built-in
/// `signer-3cam` scene (`handflow run`).
#[derive(Parser, Debug)]
#[command(name = "handflow", version)]
pub struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Measure accuracy against ground truth.
    #[command(subcommand)]
    Eval(EvalCommand),
    /// Measure speed (and accuracy over several seeds).
    #[command(subcommand)]
    Bench(BenchCommand),
    /// Ray-trace a synthetic signer scene into a recording with exact ground truth.
    Render(RenderArgs),
    /// 3D trajectories of head and hands from a recording (JSON Lines, or CSV).
    Track(TrackArgs),
    /// Draw the last positions of each trajectory on every camera's images.
    Overlay(OverlayArgs),
    /// What the tracker saw at one frame: each camera's skin map, faces, rays, clusters and
    /// tracks as pictures, a montage of them all, and a summary.
    Inspect(InspectArgs),
    /// Run the streaming pipeline: ingest, flow, cluster and publish processes over shared
    /// memory. Without arguments, the demo on the built-in `signer-3cam` scene.
    Run(RunArgs),
    /// Print what flows on a running pipeline's service (rig, frames, particles, clusters,
    /// trajectories).
    Tap(TapArgs),
    /// Run a pipeline of live cameras and write what they deliver as a recording that `run`
    /// and `track` replay (lossless unless `--quality`).
    Record(RecordArgs),
    /// The scene-flow demo: both Middlebury Teddy layouts with the default engine.
    FlowDemo,
    /// Inspect a calibration (any supported format) or convert it to handflow's rig TOML.
    #[command(subcommand)]
    Rig(crate::commands::rig::RigCommand),
    /// Write a recording (videos or images) in the image-folder layout: rig.toml, frames.csv,
    /// one PNG folder per camera.
    Import(ImportArgs),
    /// Write a trajectory file as TRC (OpenSim, Pose2Sim), C3D or CSV.
    Export(ExportArgs),
}

#[derive(Args, Debug)]
struct RecordArgs {
    /// Pipeline file with the live cameras (`[[cameras]]`) and their `calibration`.
    #[arg(long)]
    pipeline: PathBuf,
    /// Output folder (new or empty): rig.toml, frames.csv, one video per camera.
    #[arg(long)]
    out: PathBuf,
    /// Stop after this many seconds (default: until the sources end or Ctrl-C).
    #[arg(long)]
    seconds: Option<f64>,
    /// H.264 at this quantizer (0 best, 51 worst) instead of lossless FFV1.
    #[arg(long)]
    quality: Option<u32>,
}

#[derive(Args, Debug)]
struct ImportArgs {
    /// Recording folder (videos or image folders, with calibration and capture times).
    #[arg(long)]
    recording: PathBuf,
    /// Output folder (new or empty).
    #[arg(long)]
    out: PathBuf,
    #[command(flatten)]
    part: RecordingArgs,
}

#[derive(Args, Debug)]
struct OverlayArgs {
    /// Recording folder (videos or image folders).
    #[arg(long)]
    recording: PathBuf,
    /// Calibration file to use instead of the recording's own.
    #[arg(long)]
    calibration: Option<PathBuf>,
    /// Trajectory file (JSON Lines, as `handflow track` writes).
    #[arg(long)]
    tracks: PathBuf,
    /// Output folder: one image folder per camera (with `--video`, one video per camera and
    /// a montage of them all).
    #[arg(long)]
    out: PathBuf,
    /// Write WebM videos (VP8) instead of PNGs: `<camera>.webm` per camera and
    /// `montage.webm`, every camera in a grid, at the recording's frame rate.
    #[arg(long)]
    video: bool,
}

#[derive(Args, Debug)]
struct InspectArgs {
    /// Frame number to inspect (as in the recording's frame table). The tracker runs from
    /// the first frame read up to it.
    #[arg(long)]
    frame: u64,
    /// Output folder: one folder of pictures per camera and `montage.png`.
    #[arg(long)]
    out: PathBuf,
    #[command(flatten)]
    tracker: TrackerArgs,
}

#[derive(Args, Debug)]
struct TrackArgs {
    /// Output file (default: standard output).
    #[arg(long)]
    out: Option<PathBuf>,
    /// File format (default: the extension of `--out`, else JSON Lines): `csv` (frame, t,
    /// then per object x y z vx vy vz confidence state), `trc` or `c3d` (markers Head, LHand,
    /// RHand; written once the recording is tracked).
    #[arg(long, value_enum)]
    format: Option<crate::commands::export::Format>,
    /// Same as `--format csv`.
    #[arg(long, hide = true)]
    csv: bool,
    #[command(flatten)]
    tracker: TrackerArgs,
}

#[derive(Args, Debug)]
struct ExportArgs {
    /// Trajectory file (JSON Lines, as `track` and `run` write it).
    #[arg(long)]
    tracks: PathBuf,
    /// File format (default: the extension of `--out`, else JSON Lines).
    #[arg(long, value_enum)]
    format: Option<crate::commands::export::Format>,
    /// Output file (default: standard output; C3D needs a file).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Frame rate for TRC and C3D (default: what the records' frame numbers and times imply).
    #[arg(long)]
    rate: Option<f64>,
}

/// What the tracker runs on and how: shared by `track` and `inspect`.
#[derive(Args, Debug)]
struct TrackerArgs {
    /// Recording folder: one video per camera, or one image folder per camera, with its
    /// calibration and capture times.
    #[arg(long)]
    recording: PathBuf,
    #[command(flatten)]
    part: RecordingArgs,
    /// The world's up direction `x,y,z`, overriding the calibration's or the estimate from
    /// the cameras.
    #[arg(long, value_parser = handflow_protocol::rig::parse_direction)]
    up: Option<[f64; 3]>,
    /// Keep cluster centres on the visible surface instead of the objects' middles.
    #[arg(long)]
    no_centre_correction: bool,
    /// Publish each hand's cluster centre even when its skin runs on to the forearm,
    /// instead of the hand at the arm's distal end.
    #[arg(long)]
    no_hand_localisation: bool,
    /// Seed of the engine's random draws: the same seed gives the same trajectories;
    /// others show how much a figure owes to chance.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    #[command(flatten)]
    engine: EngineArgs,
}

impl TrackerArgs {
    fn options(&self) -> TrackOptions {
        TrackOptions {
            hand_localisation: !self.no_hand_localisation,
            seed: self.seed,
            ..track_options(&self.engine, &self.part, self.up, !self.no_centre_correction)
        }
    }
}

/// Which calibration and which part of a recording to read.
#[derive(Args, Debug, Default, Clone)]
struct RecordingArgs {
    /// Calibration file to use instead of the recording's own (rig.toml, camera_array.toml,
    /// or its only calibration file).
    #[arg(long)]
    calibration: Option<PathBuf>,
    /// First frame number to read (seeks in videos).
    #[arg(long)]
    start: Option<u64>,
    /// Read at most N frame sets.
    #[arg(long)]
    frames: Option<usize>,
}

impl RecordingArgs {
    fn options(&self) -> handflow_ingest::OpenOptions {
        handflow_ingest::OpenOptions { calibration: self.calibration.clone(), start: self.start, frames: self.frames }
    }
}

#[derive(Args, Debug, Default)]
struct RunArgs {
    /// Pipeline file (TOML; see deploy/pipelines/). Flags override its fields.
    pipeline: Option<PathBuf>,
    /// Recording folder to replay.
    #[arg(long)]
    recording: Option<PathBuf>,
    /// Synthetic scene for ingest to render as it goes (signer-3cam, hands-cross, ...).
    #[arg(long)]
    preset: Option<String>,
    /// Delivery mode: replay (nothing dropped) or live (latest wins).
    #[arg(long)]
    mode: Option<String>,
    /// JSON Lines file for the trajectories (default `out/trajectories.jsonl`).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Pace of the source: max or recorded.
    #[arg(long)]
    pace: Option<String>,
    /// Replay the source forever (until Ctrl-C).
    #[arg(long = "loop")]
    looped: bool,
    /// Publish only the first N frame sets.
    #[arg(long)]
    frames: Option<u64>,
    /// Decode the recording into memory first, so frame sets are published as raw frames
    /// (cameras deliver them so) instead of being decoded on the pipeline's path.
    #[arg(long)]
    preload: bool,
    /// Prefix of the service names (to run two pipelines side by side).
    #[arg(long)]
    services: Option<String>,
    /// Engine variant: handflow or paper.
    #[arg(long)]
    variant: Option<String>,
    /// Calibration file to use instead of the recording's own.
    #[arg(long)]
    calibration: Option<PathBuf>,
    /// First frame number of the recording to publish (seeks in videos).
    #[arg(long)]
    start: Option<u64>,
    /// The world's up direction `x,y,z`, overriding the calibration's or the estimate from
    /// the cameras.
    #[arg(long, value_parser = handflow_protocol::rig::parse_direction)]
    up: Option<[f64; 3]>,
    /// Serve the live viewer on this address (default 127.0.0.1:8787, loopback only; for
    /// example 0.0.0.0:8787 to open it from other machines).
    #[arg(long, conflicts_with = "no_viewer")]
    viewer: Option<String>,
    /// Do not serve the live viewer.
    #[arg(long)]
    no_viewer: bool,
}

#[derive(Args, Debug)]
struct TapArgs {
    /// Service: rig, frames, particles, clusters or trajectories (only trajectories with
    /// `--zenoh`).
    service: String,
    /// Read from a pipeline on another machine through its Zenoh bridge at this endpoint
    /// (`tcp/<host>:<port>`, as its pipeline file's `[network] zenoh` listens).
    #[arg(long)]
    zenoh: Option<String>,
    /// With `--zenoh`: the rig whose trajectories to read (default: every rig there).
    #[arg(long, requires = "zenoh")]
    rig: Option<String>,
    /// Prefix of the pipeline's service names.
    #[arg(long, default_value = handflow_protocol::ipc::DEFAULT_PREFIX)]
    services: String,
    /// Stop after N messages.
    #[arg(long)]
    count: Option<u64>,
}

#[derive(Args, Debug)]
struct RenderArgs {
    /// Scene description (TOML, the layout of `scene.toml` in a rendered recording).
    #[arg(long, conflicts_with = "preset")]
    scene: Option<PathBuf>,
    /// Built-in scene: signer-3cam (default), signer-2cam-narrow, hands-cross, occluded-side,
    /// signer-short-sleeves, signer-6fps, cluttered-room.
    #[arg(long)]
    preset: Option<String>,
    /// Output folder (created; must not exist or be empty).
    #[arg(long)]
    out: PathBuf,
    /// Number of frames (default: the scene's).
    #[arg(long)]
    frames: Option<u32>,
    /// Replace the recording already in `--out` (only a folder holding a recording's
    /// `frames.csv` is removed).
    #[arg(long)]
    force: bool,
}

#[derive(Subcommand, Debug)]
enum EvalCommand {
    /// Scene flow on a Middlebury multi-baseline scene (EVALUATION.md section 1).
    Middlebury(MiddleburyArgs),
    /// Skin decision against a recording's object masks, generic prior and adapted model.
    Skin(SkinArgs),
    /// Trajectories against a recording's truth.json (EVALUATION.md section 2).
    Tracks(EvalTracksArgs),
}

#[derive(Args, Debug)]
struct EvalTracksArgs {
    /// Recording folder (with truth.json unless --reference is given).
    #[arg(long)]
    recording: PathBuf,
    /// Trajectory file (JSON Lines, as `handflow track` writes); default: track now.
    #[arg(long)]
    tracks: Option<PathBuf>,
    /// Score against another tracker instead of truth.json: a `handflow-reference/1` file,
    /// or a folder of OpenPose JSON keypoints with one subfolder per camera.
    #[arg(long)]
    reference: Option<PathBuf>,
    /// OpenPose keypoint order (25 keypoints are BODY_25 unless told; 17, 18, 26, 133 and 136
    /// are COCO_17, COCO, HALPE_26, COCO_133 and HALPE_136).
    #[arg(long, value_enum, requires = "reference")]
    keypoints: Option<crate::eval::openpose::KeypointOrder>,
    /// With an OpenPose --reference: score against its nose and wrists instead of the ear
    /// midpoint and the palm centres (the points handflow publishes).
    #[arg(long, requires = "reference")]
    nose_and_wrists: bool,
    /// Calibration file to use instead of the recording's own.
    #[arg(long)]
    calibration: Option<PathBuf>,
    /// Print one JSON object instead of a table.
    #[arg(long)]
    json: bool,
    /// With --reference: also write each frame's error per object to this CSV file
    /// (`frame,object,state,error_3d_m,views`), to see when a track was off and which
    /// cameras saw the object then.
    #[arg(long, requires = "reference")]
    per_frame: Option<PathBuf>,
    #[command(flatten)]
    engine: EngineArgs,
}

#[derive(Args, Debug)]
struct SkinArgs {
    /// Recording folder with masks (as `handflow render` writes).
    #[arg(long)]
    recording: PathBuf,
    /// Print one JSON object instead of a table.
    #[arg(long)]
    json: bool,
}

#[derive(Subcommand, Debug)]
enum BenchCommand {
    /// Seconds per frame and likelihood evaluations per second, one thread and all cores.
    Flow(BenchFlowArgs),
    /// Accuracy averaged over seeds, for both layouts.
    Accuracy(BenchAccuracyArgs),
    /// Rendering speed of a synthetic scene (to memory), one thread and all cores.
    Render(BenchRenderArgs),
    /// Clustering and labelling time per frame, against EM on every point.
    Cluster(BenchClusterArgs),
    /// One hop of a frame set through iceoryx2 between processes, against copying it once.
    Ipc(BenchIpcArgs),
    /// The receiving process of `bench ipc`.
    #[command(hide = true)]
    IpcReceiver(IpcReceiverArgs),
    /// Trajectory samples to a subscriber through iceoryx2 and to one behind the Zenoh bridge
    /// (TCP on loopback), in one run: latency and sustained rate.
    Hop(BenchHopArgs),
    /// A receiving process of `bench hop`.
    #[command(hide = true)]
    HopReceiver(HopReceiverArgs),
    /// The live pipeline on a recording at its recorded rate: latency and sustained rate.
    Pipeline(BenchPipelineArgs),
    /// Reading a recording's videos into frame sets against reading the same frames as PNGs.
    Decode(BenchDecodeArgs),
    /// The live pipeline on a looped recording for a long time: each stage's memory and file
    /// descriptors, rate and latency, window by window.
    Soak(BenchSoakArgs),
    /// Malformed samples on a running pipeline's service (for the fault campaign).
    #[command(hide = true)]
    Inject(BenchInjectArgs),
}

#[derive(Args, Debug)]
struct BenchInjectArgs {
    /// Prefix of the pipeline's service names.
    #[arg(long)]
    services: String,
    /// `frames`, `particles`, `clusters` or `trajectories`.
    #[arg(long)]
    service: String,
    /// The pipeline's mode (the service's settings follow it).
    #[arg(long, default_value = "replay")]
    mode: handflow_protocol::ipc::Mode,
    /// Malformed samples sent.
    #[arg(long, default_value_t = 5)]
    count: u32,
    /// Seed of the malformations.
    #[arg(long, default_value_t = 1)]
    seed: u64,
}

#[derive(Args, Debug)]
struct BenchSoakArgs {
    /// Recording replayed (looped) at its recorded rate; the demo's `signer-3cam` by default
    /// (rendered first if need be).
    #[arg(long)]
    recording: Option<PathBuf>,
    /// Minutes measured, after a 10 s warm-up.
    #[arg(long, default_value_t = 60.0)]
    minutes: f64,
    /// Minutes per window.
    #[arg(long, default_value_t = 5.0)]
    window: f64,
    /// Decode the recording on the pipeline's path instead of preloading it.
    #[arg(long)]
    decode: bool,
    /// Also write the windows as CSV (one row per window and stage) to this file.
    #[arg(long)]
    csv: Option<PathBuf>,
}

#[derive(Args, Debug)]
struct BenchDecodeArgs {
    /// Recording folder of videos (default: the shared real session).
    #[arg(long, default_value = "../shared/data/real/caliscope-hands")]
    recording: PathBuf,
    /// Read only the first N frame sets.
    #[arg(long)]
    frames: Option<usize>,
    /// Passes over each source (the fastest is reported).
    #[arg(long, default_value_t = 3)]
    passes: usize,
    /// Print one JSON object.
    #[arg(long)]
    json: bool,
}

#[derive(Args, Debug)]
struct BenchIpcArgs {
    /// Frame sets sent per size.
    #[arg(long, default_value_t = 300)]
    samples: usize,
    /// Print one JSON array instead of a table.
    #[arg(long)]
    json: bool,
}

#[derive(Args, Debug)]
struct BenchHopArgs {
    /// Samples sent at the steady rate, for latency.
    #[arg(long, default_value_t = 2000)]
    samples: usize,
    /// The steady rate, samples per second.
    #[arg(long, default_value_t = 200.0)]
    rate: f64,
    /// Samples then sent back to back, for the sustained rate.
    #[arg(long, default_value_t = 20000)]
    burst: usize,
    /// Print one JSON array instead of a table.
    #[arg(long)]
    json: bool,
}

#[derive(Args, Debug)]
struct HopReceiverArgs {
    #[arg(long)]
    services: Option<String>,
    #[arg(long)]
    zenoh: Option<String>,
}

#[derive(Args, Debug)]
struct IpcReceiverArgs {
    #[arg(long)]
    services: String,
    #[arg(long)]
    samples: usize,
}

#[derive(Args, Debug)]
struct BenchPipelineArgs {
    /// Recording replayed (looped) at its recorded rate; the demo's `signer-3cam` by default
    /// (rendered first if need be).
    #[arg(long)]
    recording: Option<PathBuf>,
    /// Seconds measured after a 3 s warm-up.
    #[arg(long, default_value_t = 20.0)]
    seconds: f64,
    /// Decode the recording's images on the pipeline's path (ingest as a PNG reader)
    /// instead of preloading them (ingest as cameras delivering raw frames, the default).
    #[arg(long)]
    decode: bool,
    /// Also run it with the live viewer serving and a client reading both its WebSockets,
    /// right after the run without it: the viewer's cost.
    #[arg(long)]
    viewer: bool,
    /// Print one JSON object instead of a table.
    #[arg(long)]
    json: bool,
}

#[derive(Args, Debug)]
struct BenchClusterArgs {
    /// Weighted points per frame.
    #[arg(long, default_value_t = 100_000)]
    points: usize,
    /// Frames timed.
    #[arg(long, default_value_t = 60)]
    frames: usize,
    /// Print one JSON object instead of a table.
    #[arg(long)]
    json: bool,
}

#[derive(Args, Debug)]
struct BenchRenderArgs {
    /// Built-in scene.
    #[arg(long, default_value = "signer-3cam")]
    preset: String,
    /// Frames rendered per measurement.
    #[arg(long, default_value_t = 60)]
    frames: u32,
    /// Print one JSON object instead of a table.
    #[arg(long)]
    json: bool,
}

/// Engine selection shared by the commands.
#[derive(Args, Debug, Clone)]
struct EngineArgs {
    /// Engine variant: `handflow` (default) or `paper` (the published method).
    #[arg(long, default_value = "handflow")]
    variant: Variant,
    /// Scene Particles per ray (default 10 on a Middlebury scene, 6 on a recording).
    #[arg(long)]
    particles_per_ray: Option<usize>,
    /// Override any engine configuration field, e.g. `--set propagation=false` (repeatable).
    #[arg(long = "set", value_name = "FIELD=VALUE")]
    overrides: Vec<String>,
}

#[derive(Args, Debug)]
struct MiddleburyArgs {
    /// Scene folder (nine views im0..im8.ppm, dispK.pgm, scene.toml).
    #[arg(long, default_value = DEFAULT_SCENE)]
    scene: PathBuf,
    /// `multiview` (8 images, 2 frames) or `fb` (9 images, 3 frames).
    #[arg(long, default_value = "multiview")]
    layout: Layout,
    #[command(flatten)]
    engine: EngineArgs,
    /// Random seed.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Worker threads (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// Print one JSON object instead of a table.
    #[arg(long)]
    json: bool,
    /// Also write the estimated maps (PNG to look at, PFM for other tools) into this folder.
    #[arg(long)]
    out: Option<PathBuf>,
}

#[derive(Args, Debug)]
struct BenchFlowArgs {
    /// Scene folder.
    #[arg(long, default_value = DEFAULT_SCENE)]
    scene: PathBuf,
    /// Run on a recording instead: skin coverage, forwards/backwards likelihood, every frame
    /// (or `--frames`), reporting frames per second and the share of rays occupied.
    #[arg(long, conflicts_with_all = ["scene", "layout", "repeats"])]
    recording: Option<PathBuf>,
    /// With `--recording`: estimate only the first N frames.
    #[arg(long, requires = "recording")]
    frames: Option<usize>,
    /// With `--recording`: skip the dense full-resolution baseline (a few seconds per frame).
    #[arg(long, requires = "recording")]
    no_baseline: bool,
    /// `multiview` or `fb`.
    #[arg(long, default_value = "multiview")]
    layout: Layout,
    #[command(flatten)]
    engine: EngineArgs,
    /// Runs per thread count; the fastest counts (default 3).
    #[arg(long, default_value_t = 3)]
    repeats: usize,
    /// Print one JSON object instead of a table.
    #[arg(long)]
    json: bool,
}

#[derive(Args, Debug)]
struct BenchAccuracyArgs {
    /// Scene folder.
    #[arg(long, default_value = DEFAULT_SCENE)]
    scene: PathBuf,
    #[command(flatten)]
    engine: EngineArgs,
    /// Number of seeds (0, 1, ..); the table shows their mean.
    #[arg(long, default_value_t = 3)]
    seeds: u64,
    /// Layouts to run, comma separated.
    #[arg(long, default_value = "multiview,fb", value_delimiter = ',')]
    layouts: Vec<Layout>,
    /// Print JSON (one object per layout) instead of a table.
    #[arg(long)]
    json: bool,
}

/// Writes a line to standard output, returning the error (a closed pipe, as with
/// `handflow ... | head`, ends the command quietly instead of panicking like `println!`).
macro_rules! out {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        writeln!(std::io::stdout(), $($arg)*)?
    }};
}

/// Entry point of the binary.
pub fn main() -> ExitCode {
    let cli = Cli::parse();
    // The launcher reports what its stages do; other commands only warn.
    init_logging(match &cli.command {
        None | Some(Command::Run(_)) | Some(Command::Record(_)) => "info",
        // The few state changes a user of new footage needs (faces found or lost, how much
        // of each image is skin, why tracks have not started), without per-frame lines.
        Some(Command::Track(_) | Command::Inspect(_)) => TRACKER_LOG,
        _ => "warn",
    });
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) if is_broken_pipe(&err) => ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("handflow: error: {err:#}");
            ExitCode::FAILURE
        }
    }
}

fn is_broken_pipe(err: &anyhow::Error) -> bool {
    err.chain().any(|e| e.downcast_ref::<std::io::Error>().is_some_and(|e| e.kind() == std::io::ErrorKind::BrokenPipe))
}

/// Default log filter of `track` and `inspect`: warnings, and the info lines of the flow
/// stream and the cluster stage (state changes only), of the engine configuration (its
/// working level) and of the tracker command itself.
const TRACKER_LOG: &str =
    "warn,handflow_flow::stream=info,handflow_cluster::stage=info,handflow::commands=info,handflow::recording_engine=info";

fn init_logging(default_level: &str) {
    let filter = tracing_subscriber::EnvFilter::try_from_env("HANDFLOW_LOG").unwrap_or_else(|_| {
        tracing_subscriber::EnvFilter::new(format!("{default_level},{}", handflow_protocol::ipc::ZENOH_LOG))
    });
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .try_init();
}

fn run(cli: Cli) -> Result<()> {
    match cli.command {
        None => run_streaming(&RunArgs::default()),
        Some(Command::FlowDemo) => demo(),
        Some(Command::Rig(command)) => crate::commands::rig::run(&command),
        Some(Command::Import(args)) => import(&args),
        Some(Command::Export(args)) => {
            let count = crate::commands::export::export(&args.tracks, args.format, args.out.as_ref(), args.rate)?;
            if let Some(out) = &args.out {
                eprintln!("wrote {count} records of `{}` into `{}`", args.tracks.display(), out.display());
            }
            Ok(())
        }
        Some(Command::Run(args)) => run_streaming(&args),
        Some(Command::Record(args)) => record_live(&args),
        Some(Command::Tap(args)) => match &args.zenoh {
            Some(endpoint) if args.service == "trajectories" => crate::commands::tap::tap_zenoh(
                endpoint,
                args.rig.as_deref(),
                args.count,
                &mut std::io::stdout().lock(),
            ),
            Some(_) => anyhow::bail!(
                "`--zenoh` reads `trajectories` only (the bridge forwards clusters and particle sets on request; \
                 subscribe to `handflow/<rig>/clusters` with any Zenoh client)"
            ),
            None => crate::commands::tap::tap(&args.service, &args.services, args.count, &mut std::io::stdout().lock()),
        },
        Some(Command::Eval(EvalCommand::Middlebury(args))) => eval_middlebury(&args),
        Some(Command::Eval(EvalCommand::Skin(args))) => eval_skin(&args),
        Some(Command::Bench(BenchCommand::Flow(args))) => bench_flow(&args),
        Some(Command::Bench(BenchCommand::Accuracy(args))) => bench_accuracy(&args),
        Some(Command::Bench(BenchCommand::Render(args))) => bench_render(&args),
        Some(Command::Bench(BenchCommand::Cluster(args))) => bench_cluster(&args),
        Some(Command::Bench(BenchCommand::Decode(args))) => bench_decode(&args),
        Some(Command::Bench(BenchCommand::Soak(args))) => bench_soak(&args),
        Some(Command::Bench(BenchCommand::Inject(args))) => {
            crate::bench::inject::inject(&args.services, &args.service, args.mode, args.count, args.seed)
        }
        Some(Command::Bench(BenchCommand::Ipc(args))) => bench_ipc(&args),
        Some(Command::Bench(BenchCommand::IpcReceiver(args))) => {
            crate::bench::stream::ipc_receiver(&args.services, args.samples)
        }
        Some(Command::Bench(BenchCommand::Pipeline(args))) => bench_pipeline(&args),
        Some(Command::Bench(BenchCommand::Hop(args))) => bench_hop(&args),
        Some(Command::Bench(BenchCommand::HopReceiver(args))) => {
            crate::bench::hop::hop_receiver(args.services.as_deref(), args.zenoh.as_deref())
        }
        Some(Command::Render(args)) => render(&args),
        Some(Command::Track(args)) => track(&args),
        Some(Command::Overlay(args)) => overlay(&args),
        Some(Command::Inspect(args)) => inspect(&args),
        Some(Command::Eval(EvalCommand::Tracks(args))) => eval_tracks(&args),
    }
}

fn bench_ipc(args: &BenchIpcArgs) -> Result<()> {
    let results = crate::bench::stream::bench_ipc(args.samples)?;
    if args.json {
        out!("{}", serde_json::to_string(&results)?);
        return Ok(());
    }
    out!("one hop through iceoryx2 (publisher -> subscriber in another process, woken by its WaitSet)");
    out!("against copying the same bytes once; {} frame sets per size", args.samples);
    out!(
        "{:>6} {:>10} {:>12} {:>12} {:>12} {:>10}",
        "views",
        "MB",
        "hop p50 us",
        "hop p99 us",
        "copy p50 us",
        "copy/hop"
    );
    for r in &results {
        out!(
            "{:>6} {:>10.2} {:>12.1} {:>12.1} {:>12.1} {:>10.2}",
            r.views,
            r.bytes as f64 / 1e6,
            r.hop_p50_us,
            r.hop_p99_us,
            r.copy_p50_us,
            r.copy_over_hop
        );
    }
    Ok(())
}

fn bench_hop(args: &BenchHopArgs) -> Result<()> {
    anyhow::ensure!(args.rate > 0.0 && args.rate.is_finite(), "--rate: a positive number of samples per second");
    let results = crate::bench::hop::bench_hop(args.samples, args.rate, args.burst)?;
    if args.json {
        out!("{}", serde_json::to_string(&results)?);
        return Ok(());
    }
    out!(
        "trajectory samples, publisher -> subscriber in another process; zenoh = via handflow-bridge, TCP on loopback"
    );
    out!("{} samples at {} per second, then {} back to back", args.samples, args.rate, args.burst);
    out!(
        "{:>9} {:>14} {:>10} {:>10} {:>16} {:>12}",
        "transport",
        "received",
        "p50 us",
        "p99 us",
        "burst received",
        "burst /s"
    );
    for r in &results {
        out!(
            "{:>9} {:>14} {:>10.1} {:>10.1} {:>16} {:>12.0}",
            r.transport,
            format!("{}/{}", r.received, r.sent),
            r.p50_us,
            r.p99_us,
            format!("{}/{}", r.burst_received, r.burst_sent),
            r.burst_per_s
        );
    }
    if let [ipc, zenoh] = &results[..] {
        out!("zenoh / iceoryx2 latency: p50 {:.1}x, p99 {:.1}x", zenoh.p50_us / ipc.p50_us, zenoh.p99_us / ipc.p99_us);
    }
    Ok(())
}

/// The demo's recording, rendered first if it is not there yet.
fn demo_recording() -> Result<PathBuf> {
    let rec = PathBuf::from(DEMO_RECORDING);
    if !rec.join("frames.csv").is_file() {
        out!("rendering the built-in `signer-3cam` scene into {} first", rec.display());
        let spec = scene_spec(None, Some("signer-3cam"))?;
        let renderer = Renderer::new(&spec).map_err(anyhow::Error::msg)?;
        clear_output(&rec, true)?;
        write_recording(&renderer, &rec, spec.frames)?;
    }
    Ok(rec)
}

fn bench_pipeline(args: &BenchPipelineArgs) -> Result<()> {
    let rec = match &args.recording {
        Some(r) => r.clone(),
        None => demo_recording()?,
    };
    let mut runs = vec![crate::bench::stream::bench_pipeline(&rec, args.seconds, !args.decode, None)?];
    if args.viewer {
        // A free port on loopback, as a user's viewer would be.
        let address = std::net::TcpListener::bind("127.0.0.1:0")?.local_addr()?;
        runs.push(crate::bench::stream::bench_pipeline(&rec, args.seconds, !args.decode, Some(address))?);
    }
    if args.json {
        // One run: its object, as before; with the viewer: both, without it first.
        let text = match &runs[..] {
            [only] => serde_json::to_string(only)?,
            both => serde_json::to_string(both)?,
        };
        out!("{text}");
        return Ok(());
    }
    for r in &runs {
        out!(
            "live pipeline on `{}` at {:.0} frames/s ({}{}), {:.1} s measured: {:.1} trajectory samples/s, {} frame \
             sets dropped",
            r.recording,
            r.input_fps,
            if r.preloaded { "preloaded: raw frames" } else { "images decoded on the path" },
            r.viewer.as_ref().map_or(String::new(), |v| format!(
                "; viewer on {} read by a client: {} samples, {} thumbnails",
                v.address, v.samples, v.thumbnails
            )),
            r.seconds,
            r.output_fps,
            r.dropped
        );
        out!(
            "glass-to-trajectory latency p50 {:.1} ms, p99 {:.1} ms ({:.1} ms beyond the one-frame forwards/backwards delay)",
            r.latency_p50_ms,
            r.latency_p99_ms,
            r.latency_p99_beyond_fb_ms
        );
    }
    if let [without, with] = &runs[..] {
        out!(
            "with the viewer / without: samples/s x{:.3}, latency p50 x{:.2}, p99 x{:.2}",
            with.output_fps / without.output_fps.max(1e-9),
            with.latency_p50_ms / without.latency_p50_ms.max(1e-9),
            with.latency_p99_ms / without.latency_p99_ms.max(1e-9)
        );
    }
    Ok(())
}

fn bench_soak(args: &BenchSoakArgs) -> Result<()> {
    use std::io::Write;
    let rec = match &args.recording {
        Some(r) => r.clone(),
        None => demo_recording()?,
    };
    let mut csv = match &args.csv {
        Some(path) => {
            let mut file = std::fs::File::create(path).with_context(|| format!("creating `{}`", path.display()))?;
            writeln!(file, "minute,samples_per_s,dropped,latency_p50_ms,latency_p99_ms,stage,rss_mib,fds")?;
            Some((path.clone(), file))
        }
        None => None,
    };
    let mut csv_error = None;
    out!("soak: the live pipeline on `{}` for {} min, windows of {} min", rec.display(), args.minutes, args.window);
    let windows = crate::bench::soak::soak(&rec, args.minutes, args.window, !args.decode, |w| {
        let stages: Vec<String> =
            w.stages.iter().map(|s| format!("{} {:.1} MiB {} fds", s.stage, s.rss_mib, s.fds)).collect();
        // Standard output closed: the CSV and the summary still count.
        let _ = writeln!(
            std::io::stdout(),
            "{:6.1} min: {:.2} samples/s, {} dropped, latency p50 {:.0} ms p99 {:.0} ms | {}",
            w.minute,
            w.samples_per_s,
            w.dropped,
            w.latency_p50_ms,
            w.latency_p99_ms,
            stages.join(", ")
        );
        if let Some((path, file)) = csv.as_mut() {
            for s in &w.stages {
                let row = writeln!(
                    file,
                    "{:.2},{:.3},{},{:.1},{:.1},{},{:.2},{}",
                    w.minute, w.samples_per_s, w.dropped, w.latency_p50_ms, w.latency_p99_ms, s.stage, s.rss_mib, s.fds
                )
                .and_then(|()| file.flush());
                if let Err(e) = row {
                    csv_error.get_or_insert(format!("writing `{}`: {e}", path.display()));
                }
            }
        }
    })?;
    if let Some(e) = csv_error {
        anyhow::bail!(e);
    }
    // Growth: the last window against the first, per stage.
    if let (Some(first), Some(last)) = (windows.first(), windows.last()) {
        for s in &first.stages {
            if let Some(l) = last.stages.iter().find(|l| l.stage == s.stage) {
                out!(
                    "{}: memory {:.1} -> {:.1} MiB ({:+.1} %), descriptors {} -> {}",
                    s.stage,
                    s.rss_mib,
                    l.rss_mib,
                    (l.rss_mib / s.rss_mib - 1.0) * 100.0,
                    s.fds,
                    l.fds
                );
            }
        }
    }
    Ok(())
}

/// Where the demo renders its recording and writes its trajectories.
const DEMO_RECORDING: &str = "out/signer-3cam";
const DEMO_TRAJECTORIES: &str = "out/signer-3cam-trajectories.jsonl";

/// `handflow record`: the pipeline file's live cameras through the whole pipeline (its
/// trajectories go where the file says), every frame set also written to `--out`.
fn record_live(args: &RecordArgs) -> Result<()> {
    use crate::commands::launcher::{run_pipeline, Pipeline};
    let mut p = Pipeline::load(&args.pipeline)?;
    if p.cameras.is_empty() {
        anyhow::bail!("pipeline `{}` has no live cameras (`[[cameras]]`) to record", args.pipeline.display());
    }
    p.record = Some(args.out.clone());
    p.record_quality = args.quality.or(p.record_quality);
    if let Some(seconds) = args.seconds {
        let fps = p.cameras.iter().find_map(|c| c.fps).unwrap_or(30.0);
        p.frames = Some((seconds * fps).round().max(1.0) as u64);
    }
    let report = run_pipeline(&p)?;
    if !report.completed {
        anyhow::bail!("the recording run was interrupted; what was recorded is in `{}`", args.out.display());
    }
    eprintln!(
        "recorded into `{}` in {:.1} s; replay with `handflow run --recording {0}` or `handflow track --recording {0}`",
        args.out.display(),
        report.seconds
    );
    Ok(())
}

/// `handflow run`: the pipeline from the file and flags; without a source, the demo
/// (`signer-3cam`, rendered first if need be, replayed through the four processes and
/// checked against its truth).
fn run_streaming(args: &RunArgs) -> Result<()> {
    use crate::commands::launcher::{run_pipeline, Pipeline};
    let mut p = match &args.pipeline {
        Some(path) => Pipeline::load(path)?,
        None => Pipeline::default(),
    };
    if args.recording.is_some() {
        p.recording.clone_from(&args.recording);
        p.preset = None;
        p.cameras.clear();
    }
    if args.preset.is_some() {
        p.preset.clone_from(&args.preset);
        p.recording = None;
        p.cameras.clear();
    }
    for (field, value) in
        [(&mut p.mode, &args.mode), (&mut p.services, &args.services), (&mut p.variant, &args.variant)]
    {
        if let Some(v) = value {
            field.clone_from(v);
        }
    }
    if args.out.is_some() {
        p.out.clone_from(&args.out);
    }
    if args.pace.is_some() {
        p.pace.clone_from(&args.pace);
    }
    p.looped |= args.looped;
    p.preload |= args.preload;
    if args.frames.is_some() {
        p.frames = args.frames;
    }
    if args.start.is_some() {
        p.start = args.start;
    }
    if args.calibration.is_some() {
        p.calibration.clone_from(&args.calibration);
    }
    if args.up.is_some() {
        p.up = args.up;
    }
    if let Some(address) = &args.viewer {
        p.viewer.enabled = true;
        p.viewer.listen.clone_from(address);
    }
    if args.no_viewer {
        p.viewer.enabled = false;
    }
    let demo = p.recording.is_none() && p.preset.is_none() && p.cameras.is_empty();
    if demo {
        let rec = demo_recording()?;
        p.recording = Some(rec);
        if p.out.is_none() {
            p.out = Some(PathBuf::from(DEMO_TRAJECTORIES));
        }
    }
    if p.out.is_none() {
        p.out = Some(PathBuf::from("out/trajectories.jsonl"));
    }
    let report = run_pipeline(&p)?;
    let out_path = p.out.clone().unwrap_or_default();
    let restarts: Vec<String> =
        report.restarts.iter().filter(|(_, n)| *n > 0).map(|(s, n)| format!("{s} {n}x")).collect();
    out!(
        "{} after {:.1} s{}; trajectories in `{}`, live samples on `{}`",
        if report.completed { "stream ended" } else { "stopped" },
        report.seconds,
        if restarts.is_empty() { String::new() } else { format!(" (restarts: {})", restarts.join(", ")) },
        out_path.display(),
        handflow_protocol::ipc::ServiceNames::new(&p.services).trajectories()
    );
    if let (true, Some(rec)) = (report.completed, &p.recording) {
        let options = handflow_ingest::OpenOptions { calibration: p.calibration.clone(), ..Default::default() };
        let rec = handflow_ingest::Recording::open_with(rec, &options)?;
        if rec.truth_path().is_some() && out_path.is_file() {
            let s = evaluate_tracks(&rec, &read_tracks(&out_path)?)?;
            out!("against the recording's truth ({} frames, {} identity switches):", s.frames, s.identity_switches);
            for (name, o) in [("head", &s.head), ("left_hand", &s.left_hand), ("right_hand", &s.right_hand)] {
                out!(
                    "  {name:<11} agreement {:6.1} %  3D rmse {:.3} m  misses {}",
                    o.agreement * 100.0,
                    o.rmse_3d_m,
                    o.misses
                );
            }
        }
    }
    Ok(())
}

/// The no-argument demo: both layouts of the built-in scene with the default engine.
fn demo() -> Result<()> {
    let scene = Path::new(DEFAULT_SCENE);
    if !scene.join("scene.toml").is_file() {
        anyhow::bail!(
            "the demo scene `{}` is not here (run from the repository root, next to `../shared`), \
             or evaluate your own scene: handflow eval middlebury --scene DIR --layout multiview",
            scene.display()
        );
    }
    out!("handflow demo: multi-view scene flow on `{}` (EVALUATION.md section 1)\n", scene.display());
    for layout in [Layout::Multiview, Layout::Fb] {
        let out = PathBuf::from("out").join(format!("middlebury-{layout}"));
        let args = MiddleburyArgs {
            scene: scene.to_path_buf(),
            layout,
            engine: EngineArgs { variant: Variant::Handflow, particles_per_ray: None, overrides: vec![] },
            seed: 0,
            threads: None,
            json: false,
            out: Some(out),
        };
        eval_middlebury(&args)?;
        out!();
    }
    Ok(())
}

fn options(engine: &EngineArgs, seed: u64) -> EvalOptions {
    EvalOptions {
        variant: engine.variant,
        particles_per_ray: engine.particles_per_ray,
        seed,
        overrides: engine.overrides.clone(),
    }
}

fn thread_pool(threads: Option<usize>) -> Result<rayon::ThreadPool> {
    let mut builder = rayon::ThreadPoolBuilder::new();
    if let Some(n) = threads {
        anyhow::ensure!(n > 0, "--threads must be at least 1");
        builder = builder.num_threads(n);
    }
    builder.build().context("starting worker threads")
}

fn eval_middlebury(args: &MiddleburyArgs) -> Result<()> {
    let pool = thread_pool(args.threads)?;
    let (scene, problem) = load_problem(&args.scene, args.layout)?;
    let config = engine_config(&problem, args.layout, &options(&args.engine, args.seed))?;
    let threads = pool.current_num_threads();
    let result = pool.install(|| run_once(&scene, &problem, config.clone()))?;
    let written = match &args.out {
        Some(dir) => write_maps(dir, &problem, &result.field.position, &result.field.velocity)?,
        None => Vec::new(),
    };
    if args.json {
        let report = report_json(&scene.name, args.layout, &config, threads, &result);
        out!("{report}");
    } else {
        print_report(&scene.name, args.layout, &config, threads, &result)?;
        if let Some(dir) = &args.out {
            out!("maps written to {} ({} files)", dir.display(), written.len());
        }
    }
    Ok(())
}

fn report_json(
    scene: &str,
    layout: Layout,
    config: &handflow_flow::EngineConfig,
    threads: usize,
    r: &RunResult,
) -> serde_json::Value {
    let seed = config.seed;
    json!({
        "scene": scene,
        "layout": layout.to_string(),
        "variant": config.variant.name(),
        "of_rmse_px": r.metrics.of_rmse_px,
        "zflow_rmse": r.metrics.zflow_rmse,
        "structure_rmse_px": r.metrics.structure_rmse_px,
        "aae_deg": r.metrics.aae_deg,
        "seconds_per_frame": r.stats.seconds,
        "particles_per_ray": config.particles_per_ray,
        "seed": seed,
        "threads": threads,
        "pixels": r.metrics.pixels,
        "evaluations": r.stats.evaluations,
    })
}

fn print_report(
    scene: &str,
    layout: Layout,
    config: &handflow_flow::EngineConfig,
    threads: usize,
    r: &RunResult,
) -> Result<()> {
    let seed = config.seed;
    let m = &r.metrics;
    out!(
        "scene {scene}, layout {layout}, variant {}, {} particles/ray, seed {seed}, {threads} threads",
        config.variant.name(),
        config.particles_per_ray
    );
    out!("  optical flow RMSE   {:8.3} px", m.of_rmse_px);
    out!("  Z flow RMSE         {:8.4}", m.zflow_rmse);
    out!("  structure RMSE      {:8.3} px", m.structure_rmse_px);
    out!("  AAE                 {:8.2} deg", m.aae_deg);
    out!("  time                {:8.3} s/frame ({} pixels with truth)", r.stats.seconds, m.pixels);
    Ok(())
}

fn bench_flow(args: &BenchFlowArgs) -> Result<()> {
    if let Some(dir) = &args.recording {
        return bench_flow_recording(dir, args);
    }
    let (scene, problem) = load_problem(&args.scene, args.layout)?;
    let config = engine_config(&problem, args.layout, &options(&args.engine, 0))?;
    anyhow::ensure!(args.repeats > 0, "--repeats must be at least 1");
    let repeats = args.repeats;
    let fastest = |threads: Option<usize>| -> Result<(f64, u64, usize)> {
        let pool = thread_pool(threads)?;
        let mut best = f64::INFINITY;
        let mut evals = 0;
        for _ in 0..repeats {
            let r = pool.install(|| run_once(&scene, &problem, config.clone()))?;
            best = best.min(r.stats.seconds);
            evals = r.stats.evaluations;
        }
        Ok((best, evals, pool.current_num_threads()))
    };
    let (single, _, _) = fastest(Some(1))?;
    let (all, evals, threads) = fastest(None)?;
    let eps = evals as f64 / all;
    if args.json {
        out!(
            "{}",
            json!({
                "scene": scene.name,
                "layout": args.layout.to_string(),
                "variant": config.variant.name(),
                "particles_per_ray": config.particles_per_ray,
                "seconds_per_frame_1_thread": single,
                "seconds_per_frame": all,
                "evaluations_per_second": eps,
                "evaluations_per_frame": evals,
                "threads": threads,
                "speedup": single / all,
            })
        );
    } else {
        out!(
            "scene {}, layout {}, variant {}, {} particles/ray, best of {repeats}",
            scene.name,
            args.layout,
            config.variant.name(),
            config.particles_per_ray
        );
        out!("  1 thread     {single:8.3} s/frame");
        out!("  {threads} threads    {all:8.3} s/frame  ({:.2}x)", single / all);
        out!("  likelihood evaluations {evals} per frame, {:.2} M/s on {threads} threads", eps / 1e6);
    }
    Ok(())
}

fn bench_accuracy(args: &BenchAccuracyArgs) -> Result<()> {
    anyhow::ensure!(args.seeds > 0, "--seeds must be at least 1");
    for &layout in &args.layouts {
        let (scene, problem) = load_problem(&args.scene, layout)?;
        let mut sums = [0f64; 5];
        let mut per_seed = Vec::new();
        for seed in 0..args.seeds {
            let config = engine_config(&problem, layout, &options(&args.engine, seed))?;
            let r = run_once(&scene, &problem, config)?;
            let m = &r.metrics;
            for (s, v) in
                sums.iter_mut().zip([m.of_rmse_px, m.zflow_rmse, m.structure_rmse_px, m.aae_deg, r.stats.seconds])
            {
                *s += v;
            }
            per_seed.push(json!({"seed": seed, "of_rmse_px": m.of_rmse_px, "zflow_rmse": m.zflow_rmse, "structure_rmse_px": m.structure_rmse_px, "aae_deg": m.aae_deg, "seconds_per_frame": r.stats.seconds}));
        }
        let k = args.seeds as f64;
        let mean = sums.map(|s| s / k);
        if args.json {
            out!(
                "{}",
                json!({"scene": scene.name, "layout": layout.to_string(), "variant": args.engine.variant.name(), "seeds": args.seeds, "particles_per_ray": args.engine.particles_per_ray.unwrap_or(handflow_flow::EngineConfig::default().particles_per_ray),
                    "overrides": args.engine.overrides,
                    "of_rmse_px": mean[0], "zflow_rmse": mean[1], "structure_rmse_px": mean[2], "aae_deg": mean[3], "seconds_per_frame": mean[4], "runs": per_seed})
            );
        } else {
            out!(
                "| {} | {layout} | {} | {:.3} | {:.4} | {:.3} | {:.2} | {:.2} |",
                scene.name,
                args.engine.variant.name(),
                mean[0],
                mean[1],
                mean[2],
                mean[3],
                mean[4]
            );
        }
    }
    Ok(())
}

fn scene_spec(scene: Option<&Path>, preset: Option<&str>) -> Result<SceneSpec> {
    match (scene, preset) {
        (Some(path), _) => {
            let text = handflow_protocol::read_text_capped(path)
                .with_context(|| format!("reading scene `{}`", path.display()))?;
            let spec: SceneSpec = toml::from_str(&text).with_context(|| format!("scene `{}`", path.display()))?;
            spec.validate().map_err(|e| anyhow::anyhow!("scene `{}`: {e}", path.display()))?;
            Ok(spec)
        }
        (None, name) => {
            let name = name.unwrap_or("signer-3cam");
            SceneSpec::preset(name)
                .ok_or_else(|| anyhow::anyhow!("unknown preset `{name}` (presets: {})", PRESETS.join(", ")))
        }
    }
}

fn render(args: &RenderArgs) -> Result<()> {
    let mut spec = scene_spec(args.scene.as_deref(), args.preset.as_deref())?;
    if let Some(frames) = args.frames {
        anyhow::ensure!(frames > 0, "--frames must be at least 1");
        spec.frames = frames;
    }
    let renderer = Renderer::new(&spec).map_err(anyhow::Error::msg)?;
    clear_output(&args.out, args.force)?;
    let started = std::time::Instant::now();
    write_recording(&renderer, &args.out, spec.frames)?;
    out!(
        "rendered {} frames x {} cameras ({}x{}) into {} in {:.1} s (images, masks/, truth.json)",
        spec.frames,
        spec.cameras.angles_deg.len(),
        spec.width,
        spec.height,
        args.out.display(),
        started.elapsed().as_secs_f64()
    );
    Ok(())
}

fn track_options(
    engine: &EngineArgs,
    part: &RecordingArgs,
    up: Option<[f64; 3]>,
    centre_correction: bool,
) -> TrackOptions {
    TrackOptions {
        variant: engine.variant,
        particles_per_ray: engine.particles_per_ray,
        overrides: engine.overrides.clone(),
        recording: part.options(),
        up,
        centre_correction,
        hand_localisation: true,
        seed: 0,
    }
}

/// A one-line progress display on stderr when it is a terminal; nothing otherwise.
fn progress(done: usize, total: usize) {
    use std::io::Write as _;
    if std::io::IsTerminal::is_terminal(&std::io::stderr()) {
        let width = 30;
        let filled = (done * width).checked_div(total).unwrap_or(width).min(width);
        let mut err = std::io::stderr();
        let _ = write!(err, "\r[{}{}] {done}/{total} frames", "#".repeat(filled), " ".repeat(width - filled));
        if done >= total {
            let _ = writeln!(err);
        }
    }
}

fn track(args: &TrackArgs) -> Result<()> {
    use crate::commands::export::{choose_format, write_records, Format};
    use crate::export::csv::{csv_header, csv_line};
    use std::io::Write as _;
    let options = args.tracker.options();
    let format = if args.csv { Format::Csv } else { choose_format(args.format, args.out.as_deref()) };
    if format == Format::C3d && args.out.is_none() {
        anyhow::bail!("C3D is binary: give the file to write with --out");
    }
    // JSON Lines and CSV are written as they go, each record flushed: a failure late in a
    // long recording keeps every earlier frame. TRC and C3D count the frames in their
    // header, so they are written at the end.
    let to_file = args.out.is_some();
    let mut kept = Vec::new();
    let mut out: Box<dyn std::io::Write> = match (&args.out, format.needs_all_records()) {
        (_, true) => Box::new(std::io::sink()),
        (Some(path), false) => Box::new(std::io::BufWriter::new(
            std::fs::File::create(path).with_context(|| format!("creating `{}`", path.display()))?,
        )),
        (None, false) => Box::new(std::io::stdout().lock()),
    };
    if format == Format::Csv {
        writeln!(out, "{}", csv_header())?;
    }
    let summary = track_recording(&args.tracker.recording, &options, |record, done, total| {
        match format {
            Format::Csv => writeln!(out, "{}", csv_line(record)?)?,
            Format::Jsonl => {
                serde_json::to_writer(&mut out, record)?;
                writeln!(out)?;
            }
            Format::Trc | Format::C3d => kept.push(record.clone()),
        }
        if to_file {
            out.flush()?;
        }
        progress(done, total);
        Ok(())
    })?;
    if format.needs_all_records() {
        write_records(&kept, format, args.out.as_deref(), None)?;
    }
    out.flush()?;
    tracing::info!(
        frames = summary.frames,
        fps = summary.frames_per_second,
        reinitialisations = summary.reinitialisations,
        "tracked"
    );
    if let Some(path) = &args.out {
        let skipped = match summary.skipped_frames {
            0 => String::new(),
            n => format!(" ({n} unreadable frame sets skipped)"),
        };
        eprintln!(
            "tracked {} frames of `{}` at {:.1} frames per second into `{}`{skipped}",
            summary.frames,
            args.tracker.recording.display(),
            summary.frames_per_second,
            path.display()
        );
    }
    Ok(())
}

fn bench_cluster(args: &BenchClusterArgs) -> Result<()> {
    anyhow::ensure!(args.points > 0 && args.frames > 0, "--points and --frames must be at least 1");
    let r = crate::bench::cluster::bench_cluster(args.points, args.frames);
    if args.json {
        out!("{}", serde_json::to_string(&r)?);
        return Ok(());
    }
    out!("clustering and labelling, {} points per frame, {} frames", r.points, r.frames);
    out!(
        "  EM (subsampled) + labelling {:8.2} ms per frame ({:.2} ms slowest, {:.1} EM iterations)",
        r.ms_per_frame,
        r.ms_per_frame_max,
        r.iterations
    );
    out!("  baseline: EM on every point {:8.2} ms per frame: {:.1}x faster", r.baseline_ms_per_frame, r.speedup);
    out!("  largest track error         {:8.3} m", r.max_track_error_m);
    Ok(())
}

fn bench_decode(args: &BenchDecodeArgs) -> Result<()> {
    let r = crate::bench::decode::bench_decode(&args.recording, args.frames, args.passes)?;
    if args.json {
        out!("{}", serde_json::to_string(&r)?);
        return Ok(());
    }
    out!(
        "`{}`: {} frame sets of {} x {}x{}, fastest of {} passes, {} threads",
        r.recording,
        r.frame_sets,
        r.cameras,
        r.width,
        r.height,
        r.passes,
        r.threads
    );
    out!("  videos (GStreamer)  {:7.1} frame sets per second", r.video_sets_per_second);
    out!("  the same as PNGs    {:7.1} frame sets per second", r.png_sets_per_second);
    out!("  videos vs PNGs      {:7.2}x", r.video_vs_png);
    Ok(())
}

fn import(args: &ImportArgs) -> Result<()> {
    let report = crate::commands::import::import_recording(&args.recording, &args.part.options(), &args.out, progress)?;
    let skipped = match report.skipped.len() {
        0 => String::new(),
        n => format!(" ({n} unreadable frame sets left out)"),
    };
    out!("wrote {} frame sets into `{}`{skipped}", report.frame_sets, args.out.display());
    Ok(())
}

fn inspect(args: &InspectArgs) -> Result<()> {
    let options = args.tracker.options();
    let summary =
        crate::commands::inspect::inspect_recording(&args.tracker.recording, &options, args.frame, &args.out)?;
    out!("{}", summary.text.trim_end());
    out!(
        "wrote {} pictures into `{}` (montage: `{}`)",
        summary.files.len(),
        args.out.display(),
        args.out.join("montage.png").display()
    );
    Ok(())
}

fn overlay(args: &OverlayArgs) -> Result<()> {
    let options = handflow_ingest::OpenOptions { calibration: args.calibration.clone(), ..Default::default() };
    let rec = handflow_ingest::Recording::open_with(&args.recording, &options)?;
    let records = read_tracks(&args.tracks)?;
    if args.video {
        let videos = crate::commands::overlay::write_overlay_videos(&rec, &records, &args.out)?;
        out!(
            "wrote {} frames into {} camera videos and `{}`",
            videos.frames,
            videos.cameras.len(),
            videos.montage.display()
        );
        return Ok(());
    }
    let written = crate::commands::overlay::write_overlays(&rec, &records, &args.out)?;
    out!("wrote {written} images into `{}` (one folder per camera)", args.out.display());
    Ok(())
}

fn eval_tracks(args: &EvalTracksArgs) -> Result<()> {
    let part = RecordingArgs { calibration: args.calibration.clone(), ..RecordingArgs::default() };
    let rec = handflow_ingest::Recording::open_with(&args.recording, &part.options())?;
    let records = match &args.tracks {
        Some(path) => read_tracks(path)?,
        None => {
            let mut records = Vec::new();
            let options = track_options(&args.engine, &part, None, true);
            track_recording(&args.recording, &options, |r, done, total| {
                records.push(r.clone());
                progress(done, total);
                Ok(())
            })?;
            records
        }
    };
    if let Some(reference) = &args.reference {
        return eval_tracks_against_reference(args, &rec, &records, reference);
    }
    let s = evaluate_tracks(&rec, &records)?;
    if args.json {
        out!("{}", serde_json::to_string(&s)?);
        return Ok(());
    }
    out!(
        "trajectories on `{}`: {} frames, {} identity switches",
        args.recording.display(),
        s.frames,
        s.identity_switches
    );
    for (name, o) in [("head", &s.head), ("left_hand", &s.left_hand), ("right_hand", &s.right_hand)] {
        out!(
            "  {name:<11} agreement {:6.1} %  rms {:.3} / {:.3} palm widths (x / y)  3D rmse {:.3} m  misses {}  \
             velocity rmse {:.3} m/s, gain {:.2}",
            o.agreement * 100.0,
            o.rms_palm_x,
            o.rms_palm_y,
            o.rmse_3d_m,
            o.misses,
            o.rmse_velocity_m_s,
            o.velocity_gain
        );
    }
    Ok(())
}

/// `eval tracks --reference`: a file is a `handflow-reference/1`, a folder OpenPose keypoints.
fn eval_tracks_against_reference(
    args: &EvalTracksArgs,
    rec: &handflow_ingest::Recording,
    records: &[handflow_publish::TrajectoryRecord],
    path: &Path,
) -> Result<()> {
    use crate::eval::tracks_reference::evaluate_against_reference;
    let rig = rec.rig();
    let reference = if path.is_dir() {
        use crate::eval::openpose::{read_openpose, video_frames_of, OpenPosePoints};
        let points = if args.nose_and_wrists { OpenPosePoints::NoseAndWrists } else { OpenPosePoints::Centres };
        // OpenPose numbers each video's frames: map them to frame sets as the recording does.
        let video_frames = rec.video_positions().map(|positions| {
            let frames: Vec<u64> = rec.frames().iter().map(|f| f.frame).collect();
            video_frames_of(&frames, positions, rig.cameras.len())
        });
        read_openpose(path, rig, args.keypoints, points, video_frames.as_deref())?
    } else {
        anyhow::ensure!(
            args.keypoints.is_none() && !args.nose_and_wrists,
            "--keypoints and --nose-and-wrists apply to an OpenPose folder, not to `{}`",
            path.display()
        );
        crate::eval::reference::read_handflow_reference(path, rig)?
    };
    let s = evaluate_against_reference(rig, records, &reference);
    if let Some(out) = &args.per_frame {
        let rows = crate::eval::tracks_reference::frame_errors(rig, records, &reference);
        let csv = crate::eval::tracks_reference::frame_errors_csv(&rows);
        std::fs::write(out, csv).with_context(|| format!("writing the per-frame errors to `{}`", out.display()))?;
    }
    if args.json {
        out!("{}", serde_json::to_string(&s)?);
        return Ok(());
    }
    let d = &s.reference;
    out!(
        "trajectories on `{}` against `{}` ({}: head = {}, hands = {}): {} frames, {} identity switches",
        args.recording.display(),
        path.display(),
        d.format,
        d.head,
        d.hands,
        s.frames,
        s.identity_switches
    );
    let cell =
        |v: Option<f64>, scale: f64, digits: usize| v.map_or("-".to_owned(), |v| format!("{:.digits$}", v * scale));
    // `-`: cannot be computed (no frame, no 3D reference; `null` in the JSON).
    out!("  object        frames misses  agree%   rms_x   rms_y  median_m  <5cm% <10cm% <20cm%");
    for (name, o) in [("head", &s.head), ("left_hand", &s.left_hand), ("right_hand", &s.right_hand)] {
        out!(
            "  {name:<11} {:>6} {:>6} {:>7} {:>7} {:>7} {:>9} {:>6} {:>6} {:>6}",
            o.frames,
            o.misses,
            cell(o.agreement, 100.0, 1),
            cell(o.rms_palm_x, 1.0, 3),
            cell(o.rms_palm_y, 1.0, 3),
            cell(o.median_3d_m, 1.0, 3),
            cell(o.within_5cm, 100.0, 1),
            cell(o.within_10cm, 100.0, 1),
            cell(o.within_20cm, 100.0, 1)
        );
    }
    Ok(())
}

/// Makes sure a render does not mix its frames with an earlier recording's.
fn clear_output(out: &Path, force: bool) -> Result<()> {
    let Ok(mut entries) = std::fs::read_dir(out) else { return Ok(()) };
    if entries.next().is_none() {
        return Ok(());
    }
    anyhow::ensure!(
        force,
        "`{}` is not empty; choose a new folder or pass --force to replace the recording in it",
        out.display()
    );
    anyhow::ensure!(
        out.join("frames.csv").is_file(),
        "`{}` holds no recording (no frames.csv); refusing to delete it with --force",
        out.display()
    );
    std::fs::remove_dir_all(out).with_context(|| format!("removing the old recording `{}`", out.display()))
}

fn bench_flow_recording(dir: &Path, args: &BenchFlowArgs) -> Result<()> {
    let e = &args.engine;
    let r = bench_recording(dir, e.variant, e.particles_per_ray, &e.overrides, args.frames, !args.no_baseline)?;
    if args.json {
        out!("{}", serde_json::to_string(&r)?);
        return Ok(());
    }
    out!(
        "recording {}: {} cameras {}x{}, reference {}, {} estimates, skin coverage, forwards/backwards, {} threads",
        r.recording,
        r.cameras,
        r.width,
        r.height,
        r.reference,
        r.frames,
        r.threads
    );
    out!(
        "  frames per second   {:8.1}  ({:.1} ms mean, {:.1} ms slowest)",
        r.frames_per_second,
        r.seconds_per_frame * 1e3,
        r.seconds_per_frame_max * 1e3
    );
    out!("  rays occupied       {:8.2} %", r.occupied_share * 100.0);
    out!("  evaluations/frame   {:8.0}", r.evaluations_per_frame);
    out!("  decode (ingest)     {:8.1} ms per frame set, not counted", r.decode_seconds_per_frame * 1e3);
    out!(
        "  face detection      {:8.1} ms per round, off the hot path, not counted",
        r.face_detection_seconds_per_round * 1e3
    );
    if let (Some(d), Some(x)) = (r.dense_seconds_per_frame, r.speedup_vs_dense) {
        out!("  baseline: dense     {:8.0} ms per frame (every ray, full resolution): {x:.0}x faster", d * 1e3);
    }
    if let (Some(a), Some(s)) = (r.mask_agreement, r.on_skin_objects) {
        out!("  on head or hands    {:8.2} % of estimated rays", s * 100.0);
        out!("  same object in all views {:5.2} % of those", a * 100.0);
    }
    Ok(())
}

fn bench_render(args: &BenchRenderArgs) -> Result<()> {
    let spec = scene_spec(None, Some(&args.preset))?;
    anyhow::ensure!(args.frames > 0, "--frames must be at least 1");
    let renderer = Renderer::new(&spec).map_err(anyhow::Error::msg)?;
    let views = spec.cameras.angles_deg.len();
    let measure = |threads: Option<usize>| -> Result<(f64, usize)> {
        let pool = thread_pool(threads)?;
        let fps = pool.install(|| {
            let mut rgb = vec![0u8; renderer.view_len() * views];
            let mut masks = vec![0u8; renderer.view_len() / 3 * views];
            let started = std::time::Instant::now();
            for frame in 0..args.frames {
                renderer.render_into(frame, &mut rgb, &mut masks);
            }
            f64::from(args.frames) / started.elapsed().as_secs_f64()
        });
        Ok((fps, pool.current_num_threads()))
    };
    let (single, _) = measure(Some(1))?;
    let (all, threads) = measure(None)?;
    if args.json {
        out!(
            "{}",
            json!({"preset": args.preset, "cameras": views, "width": spec.width, "height": spec.height,
                "frames_per_second_1_thread": single, "frames_per_second": all, "threads": threads})
        );
    } else {
        out!("render {}: {views} cameras, {}x{}, {} frames", args.preset, spec.width, spec.height, args.frames);
        out!("  1 thread   {single:7.1} frames/s");
        out!("  {threads} threads  {all:7.1} frames/s");
    }
    Ok(())
}

fn eval_skin(args: &SkinArgs) -> Result<()> {
    let s = crate::eval::skin::evaluate_skin(&args.recording)?;
    if args.json {
        out!("{}", serde_json::to_string(&s)?);
    } else {
        out!(
            "skin decision on `{}` ({} frames scored, {} face detections used, {} rejected by the other views)",
            args.recording.display(),
            s.frames_scored,
            s.face_detections,
            s.faces_rejected
        );
        out!("  adapted   precision {:.3}  recall {:.3}", s.precision, s.recall);
        out!("  generic   precision {:.3}  recall {:.3}", s.precision_generic, s.recall_generic);
        for c in &s.cameras {
            out!(
                "  camera {:<10} precision {:.3}  recall {:.3}  ({} faces detected, {} lent by other views)",
                c.camera,
                c.precision,
                c.recall,
                c.face_detections,
                c.faces_transferred
            );
        }
        for o in &s.objects {
            out!("  object {:<10} recall {:.3}  ({} pixels)", o.object, o.recall, o.pixels);
        }
    }
    Ok(())
}
