//! `handflow-flow`: the scene-flow stage. Frame sets in, one particle set per frame out, one
//! frame late (the forwards/backwards likelihood needs t+1). The engine's ring of three
//! frames' pyramids is the one-frame delay; a frame sample is released as soon as its
//! pyramids are built, so ingest can reuse the shared memory.

use std::time::Duration;

use anyhow::{Context, Result};
use clap::Parser;
use handflow_flow::stream::{
    frames_in, live_stream_engine_config, scene_point_count, scene_points, stream_engine_config, FaceCue, FlowStream,
    SetOutcome,
};
use handflow_flow::{SceneFlowEngine, Variant};
use handflow_protocol::ipc::{self, Mode, Next, Output, ServiceNames};
use handflow_protocol::messages::{FrameHeader, ParticleHeader, ScenePoint, END_OF_STREAM, PROTOCOL_VERSION};

#[derive(Parser, Debug)]
#[command(name = "handflow-flow", about = "Scene flow by Scene Particles: frame sets in, particle sets out")]
struct Args {
    /// Delivery mode: `replay` (nothing dropped) or `live` (latest wins).
    #[arg(long, default_value = "replay")]
    mode: Mode,
    /// Engine variant: `handflow` (default) or `paper`.
    #[arg(long, default_value = "handflow")]
    variant: String,
    /// Prefix of the service names.
    #[arg(long, default_value = ipc::DEFAULT_PREFIX)]
    services: String,
}

/// Seconds between face detections in live mode: once a second instead of three times
/// (measured on signer-3cam at 30 fps, 2 cores: see BENCHMARKS.md).
const LIVE_DETECT_INTERVAL_S: f64 = 1.0;

/// What the stage remembers of a frame until its estimate is out.
#[derive(Clone, Copy, Debug)]
struct FrameMeta {
    sequence: u64,
    frame: u64,
    timestamp_s: f64,
    capture_unix_ns: u64,
    missing_views: u32,
}

fn main() {
    ipc::init_logging();
    ipc::exit_with(run(Args::parse()))
}

fn run(args: Args) -> Result<()> {
    let variant: Variant = args.variant.parse().map_err(anyhow::Error::msg)?;
    let names = ServiceNames::new(&args.services);
    let node = ipc::stage_node("handflow-flow")?;
    let Some((rig_header, rig)) = ipc::wait_for_rig(&node, &names)? else { return Ok(()) };
    let fps = rig_header.frame_rate_hz;
    let reference = rig.most_frontal_camera();
    let config = match args.mode {
        Mode::Replay => stream_engine_config(variant, None, fps, &rig.cameras, reference),
        Mode::Live => live_stream_engine_config(variant, fps, &rig.cameras, reference),
    };
    tracing::info!("{}", handflow_flow::stream::working_level_summary(&config, &rig.cameras, reference));
    let engine = SceneFlowEngine::new(config, rig.cameras.clone(), reference)?;
    let views = rig.cameras.len() as u32;
    // Each view at its camera's size (a camera mounted sideways sends portrait frames).
    let rig_sizes: Vec<(u32, u32)> = rig.cameras.iter().map(|c| (c.width, c.height)).collect();
    let frames = ipc::frames_input(&node, &names, args.mode)?;
    let particles = ipc::particles_output(&node, &names, args.mode)?;
    tracing::info!(
        "ready: {views} cameras, reference `{}`, {fps:.1} frames/s, {variant:?} engine, {} mode",
        rig.cameras[reference].name,
        args.mode
    );
    let mut stream: FlowStream<FrameMeta> = match args.mode {
        Mode::Replay => FlowStream::new(engine).with_frame_rate(fps),
        // Live: after the warm-up, go on from the newest frames rather than catch up, and
        // never wait for the face detector. The warm-up's face rounds are timed by the rate
        // as in replay (ten frames apart, a 6 fps camera held 21 sets, 3.5 s); detections
        // after it are once a second.
        Mode::Live => FlowStream::new(engine)
            .with_frame_rate(fps)
            .with_backlog_limit(3)
            .without_waiting_for_models()
            .with_detect_every(frames_in(fps, LIVE_DETECT_INTERVAL_S)),
    };
    let mut connected = false;
    let mut last_sequence: Option<u64> = None;
    let mut dropped = 0u64;
    ipc::serve(&frames, Duration::from_millis(100), |sample| -> Result<Next> {
        let header = *sample.user_header();
        if let Err(e) = header.validate(sample.payload().len()) {
            tracing::error!("skipping a malformed frame set: {e}");
            return Ok(Next::Continue);
        }
        // `sizes` has one item per view, so this compares the view count too.
        if !header.is_end_of_stream() && !header.sizes().eq(rig_sizes.iter().copied()) {
            tracing::error!(
                "skipping frame set {}: {} views of {}, the rig has {views} of {}",
                header.sequence,
                header.view_count,
                FrameHeader::describe_sizes(header.sizes()),
                FrameHeader::describe_sizes(rig_sizes.iter().copied())
            );
            return Ok(Next::Continue);
        }
        if !connected {
            particles.connect_downstream(&node, args.mode);
            connected = true;
        }
        let mut publish = |meta: FrameMeta, outcome: SetOutcome<'_>| match outcome {
            SetOutcome::Estimated { engine, face } => {
                send_particles(&particles, &meta, engine, face, fps, rig_header.rig_version, reference as u32)
            }
            // Sent empty, in order: clustering coasts the tracks there.
            SetOutcome::PassedOver => {
                send_no_particles(&particles, &meta, fps, rig_header.rig_version, reference as u32)
            }
        };
        if let Some(last) = last_sequence {
            if header.sequence > last + 1 {
                dropped += header.sequence - last - 1;
                tracing::warn!(
                    "frame sets {}..{} never arrived ({dropped} dropped so far)",
                    last + 1,
                    header.sequence - 1
                );
            }
        }
        if header.is_end_of_stream() {
            stream.finish(&mut publish).context("end of stream")?;
            send_end_of_stream(&particles, header.sequence)?;
            tracing::info!("end of stream after frame set {}; {dropped} frame set(s) dropped", header.sequence);
            last_sequence = None;
            return Ok(Next::Continue);
        }
        if last_sequence.is_none() && header.sequence > 0 {
            // A stream joined part-way (this stage restarted): start estimating at once.
            tracing::info!("joining the stream at frame set {}", header.sequence);
            stream.joining_mid_stream();
        }
        last_sequence = Some(header.sequence);
        let meta = FrameMeta {
            sequence: header.sequence,
            frame: header.frame,
            timestamp_s: header.timestamp_s,
            capture_unix_ns: header.capture_unix_ns,
            missing_views: header.missing_views,
        };
        let pushed =
            stream.push_partial_at(meta, sample.payload(), header.missing_views, header.sequence, &mut publish);
        drop(sample);
        pushed.with_context(|| format!("frame set {}", header.sequence))?;
        Ok(Next::Continue)
    })?;
    tracing::info!("stopped");
    Ok(())
}

/// Writes the estimate's particles straight into a loaned sample and sends it.
fn send_particles(
    out: &Output<[ScenePoint], ParticleHeader>,
    meta: &FrameMeta,
    engine: &SceneFlowEngine,
    face: Option<FaceCue>,
    fps: f64,
    rig_version: u32,
    reference: u32,
) -> Result<()> {
    let count = scene_point_count(engine);
    let sample = out.publisher.loan_slice_uninit(count).with_context(|| format!("loaning {count} points"))?;
    let mut points = scene_points(engine);
    let mut sample = sample.write_from_fn(|_| points.next().unwrap_or_default());
    *sample.user_header_mut() = ParticleHeader {
        ray_spread_var: handflow_flow::stream::ray_spread_variance(engine),
        point_count: count as u64,
        flow_seconds: engine.stats().seconds,
        face_known: u32::from(face.is_some()),
        face_centre_m: face.map_or([0.0; 3], |f| f.centre),
        face_width_m: face.map_or(0.0, |f| f.width_m),
        face_age_frames: face.map_or(0, |f| f.age_frames),
        ..particle_header(meta, fps, rig_version, reference)
    };
    sample.send().context("sending particles")?;
    out.notify()?;
    Ok(())
}

/// The header of frame `meta`'s particle set, without points or a face.
fn particle_header(meta: &FrameMeta, fps: f64, rig_version: u32, reference: u32) -> ParticleHeader {
    ParticleHeader {
        protocol_version: PROTOCOL_VERSION,
        flags: 0,
        sequence: meta.sequence,
        frame: meta.frame,
        timestamp_s: meta.timestamp_s,
        capture_unix_ns: meta.capture_unix_ns,
        frame_rate_hz: fps,
        rig_version,
        reference_camera: reference,
        missing_views: meta.missing_views,
        ..ParticleHeader::default()
    }
}

/// Sends a set without particles for a frame set the engine could not estimate (no view of
/// the reference camera): clustering coasts every track on its prediction there.
fn send_no_particles(
    out: &Output<[ScenePoint], ParticleHeader>,
    meta: &FrameMeta,
    fps: f64,
    rig_version: u32,
    reference: u32,
) -> Result<()> {
    let mut sample = out.publisher.loan_slice(0).context("loaning an empty particle set")?;
    *sample.user_header_mut() = particle_header(meta, fps, rig_version, reference);
    sample.send().context("sending an empty particle set")?;
    out.notify()?;
    Ok(())
}

fn send_end_of_stream(out: &Output<[ScenePoint], ParticleHeader>, sequence: u64) -> Result<()> {
    let mut sample = out.publisher.loan_slice(0).context("loaning the end-of-stream sample")?;
    *sample.user_header_mut() = ParticleHeader {
        protocol_version: PROTOCOL_VERSION,
        flags: END_OF_STREAM,
        sequence,
        ..ParticleHeader::default()
    };
    sample.send().context("sending end of stream")?;
    out.notify()?;
    Ok(())
}
