//! `handflow track`: recording in, trajectories out, in one process: ingest reading, the
//! scene-flow engine (skin coverage, forwards/backwards), EM clustering in 6D and
//! labelling, frame by frame. The stages are the same library code the streaming services
//! run, in the same order, so both give the same trajectories.

use std::path::Path;
use std::time::Instant;

use anyhow::{Context, Result};
use handflow_cluster::stage::{labelled_clusters, ClusterStage};
use handflow_flow::stream::{ray_spread_variance, scene_points, FaceCue, FlowStream, SetOutcome};
use handflow_flow::{SceneFlowEngine, Variant};
use handflow_ingest::{OpenOptions, Recording};
use handflow_protocol::messages::{ClusterSet, ScenePoint, PROTOCOL_VERSION};
use handflow_publish::{trajectory_sample, TrajectoryRecord};

use crate::recording_engine::recording_engine_config;

/// What to run.
#[derive(Clone, Debug)]
pub struct TrackOptions {
    /// Engine formulation.
    pub variant: Variant,
    /// Scene Particles per ray (the recording default when `None`).
    pub particles_per_ray: Option<usize>,
    /// Engine configuration overrides, `field=value`.
    pub overrides: Vec<String>,
    /// Which calibration and which part of the recording (`--calibration`, `--start`,
    /// `--frames`).
    pub recording: OpenOptions,
    /// The world's up direction, overriding the calibration's or the estimate from the
    /// cameras (`--up`).
    pub up: Option<[f64; 3]>,
    /// Move each cluster's centre from the visible surface to the object's middle (see
    /// [`handflow_cluster::stage::surface_to_centre`]; default true).
    pub centre_correction: bool,
    /// Publish each hand at the distal end of its arm's skin (see
    /// [`handflow_cluster::hand::locate_hand`]; default true).
    pub hand_localisation: bool,
    /// Seed of the engine's random draws (`--seed`; default 0).
    pub seed: u64,
}

impl Default for TrackOptions {
    fn default() -> Self {
        Self {
            variant: Variant::Handflow,
            particles_per_ray: None,
            overrides: Vec::new(),
            recording: OpenOptions::default(),
            up: None,
            centre_correction: true,
            hand_localisation: true,
            seed: 0,
        }
    }
}

/// How a run went.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct TrackSummary {
    /// Trajectory records written (one per frame with an estimate).
    pub frames: usize,
    /// Frame sets that could not be read (corrupt image or video packet) and were skipped.
    pub skipped_frames: u64,
    /// Wall time of the whole run (decoding, face detection, engine, clustering), seconds.
    pub seconds: f64,
    /// `frames / seconds`.
    pub frames_per_second: f64,
    /// Mean clustering and labelling time per frame, seconds.
    pub cluster_seconds_per_frame: f64,
    /// Tracks re-initialised on a cluster far from their prediction.
    pub reinitialisations: u64,
}

/// What a frame set's estimate carries to clustering: which set, and how many sets were
/// skipped before it (reported in its trajectory record).
#[derive(Clone, Copy, Debug)]
struct Estimate {
    index: usize,
    dropped: u64,
}

/// The flow stream and the cluster stage `track` and `inspect` run on a recording's `rig`
/// (world `up`, `fps` frames per second), as `options` configure them, and the reference
/// camera's index.
pub(crate) fn tracker_stages<M>(
    options: &TrackOptions,
    rig: &handflow_protocol::Rig,
    up: nalgebra::Vector3<f64>,
    fps: f64,
) -> Result<(FlowStream<M>, ClusterStage, usize)> {
    let reference = rig.most_frontal_camera();
    let mut config = recording_engine_config(
        options.variant,
        options.particles_per_ray,
        fps,
        &rig.cameras,
        reference,
        &options.overrides,
    )?;
    config.seed = options.seed;
    let engine = SceneFlowEngine::new(config, rig.cameras.clone(), reference)?;
    let flow = FlowStream::new(engine).with_frame_rate(fps);
    let stage = ClusterStage::new(&rig.cameras[reference], up, options.centre_correction)
        .with_hand_localisation(options.hand_localisation);
    Ok((flow, stage, reference))
}

/// Runs the tracker over a recording, handing each frame's record to `on_record` with the
/// number of frames done and to do.
pub fn track_recording(
    dir: &Path,
    options: &TrackOptions,
    mut on_record: impl FnMut(&TrajectoryRecord, usize, usize) -> Result<()>,
) -> Result<TrackSummary> {
    let started = Instant::now();
    let rec = Recording::open_with(dir, &options.recording)?;
    tracing::info!("recording `{}`: {}", dir.display(), rec.summary());
    let rig = crate::recording_engine::tracking_rig(&rec, options.up)?;
    let up = rig.world_up();
    tracing::info!("world up {:?} ({})", up.direction.as_slice(), up.source);
    let fps = rec.frame_rate();
    let frames = rec.len();
    anyhow::ensure!(frames >= 2, "recording `{}` needs at least 2 frames, has {frames}", dir.display());
    let (mut flow, mut stage, _) = tracker_stages(options, &rig, up.direction, fps)?;
    let mut written = 0;
    let mut skipped: u64 = 0;
    // Every frame gets an estimate (the last through the flush; the first unless the
    // engine is told not to estimate it), less the frame sets that cannot be read.
    let total = frames - usize::from(!flow.engine().config().estimates_first_frame());
    // Three threads beside the engine's pool, as the services run in processes of their
    // own: frames are decoded one ahead, faces are detected inside the flow stream, and
    // each estimate is clustered while the engine works on the next frame (EM would
    // otherwise leave a core idle for its few milliseconds every frame).
    std::thread::scope(|scope| -> Result<()> {
        // Per frame set: its buffer and the cameras without a frame in it, or the error that
        // skipped it (a bad frame).
        let (frame_tx, frame_rx) = std::sync::mpsc::sync_channel::<Result<(Vec<u8>, u32), String>>(2);
        let (spare_tx, spare_rx) = std::sync::mpsc::channel::<Vec<u8>>();
        let (points_tx, points_rx) =
            std::sync::mpsc::sync_channel::<(Estimate, f64, Vec<ScenePoint>, Option<FaceCue>)>(2);
        let (spare_points_tx, spare_points_rx) = std::sync::mpsc::channel::<Vec<ScenePoint>>();
        let (record_tx, record_rx) = std::sync::mpsc::channel::<Result<TrajectoryRecord>>();
        let (fatal_tx, fatal_rx) = std::sync::mpsc::channel::<anyhow::Error>();
        let rec_ref = &rec;
        scope.spawn(move || {
            for k in 0..frames {
                let mut buf = spare_rx.try_recv().unwrap_or_else(|_| vec![0u8; rec_ref.frame_set_len()]);
                let read = match rec_ref.read_frame_into(k as u64, false, &mut buf) {
                    Ok(info) => Ok((buf, info.missing_views)),
                    Err(error) if error.is_bad_frame() => Err(error.to_string()),
                    Err(error) => {
                        let _ = fatal_tx.send(error.into());
                        return;
                    }
                };
                if frame_tx.send(read).is_err() {
                    return;
                }
            }
        });
        let stage_ref = &mut stage;
        scope.spawn(move || {
            for (estimate, spread, points, face) in points_rx {
                let record = rec_ref
                    .frames()
                    .get(estimate.index)
                    .with_context(|| format!("estimate for frame set {} beyond the recording", estimate.index))
                    .map(|entry| {
                        let face = crate::recording_engine::cluster_face_cue(face, fps);
                        let objects = stage_ref.update(entry.timestamp, fps, spread, &points, face);
                        let set = ClusterSet {
                            protocol_version: PROTOCOL_VERSION,
                            frame: entry.frame,
                            sequence: estimate.index as u64,
                            timestamp_s: entry.timestamp,
                            objects: labelled_clusters(&objects),
                            missing_views: entry.missing_views,
                            ..ClusterSet::default()
                        };
                        TrajectoryRecord::from_sample(&trajectory_sample(&set, estimate.dropped, 0))
                    });
                let _ = spare_points_tx.send(points);
                if record_tx.send(record).is_err() {
                    return;
                }
            }
        });
        let mut on_estimate = |estimate: Estimate, outcome: SetOutcome<'_>| -> Result<()> {
            let sent = match outcome {
                SetOutcome::Estimated { engine, face } => {
                    let mut points = spare_points_rx.try_recv().unwrap_or_default();
                    points.clear();
                    points.extend(scene_points(engine));
                    points_tx.send((estimate, ray_spread_variance(engine), points, face))
                }
                // A set without points: clustering coasts every track on its prediction.
                SetOutcome::PassedOver => points_tx.send((estimate, 0.0, Vec::new(), None)),
            };
            sent.context("the clustering thread stopped")
        };
        let mut hand_on = |record: Result<TrajectoryRecord>, skipped: u64| -> Result<()> {
            written += 1;
            on_record(&record?, written, total.saturating_sub(skipped as usize))
        };
        for k in 0..frames {
            let Ok(read) = frame_rx.recv() else {
                return Err(fatal_rx.try_recv().unwrap_or_else(|_| anyhow::anyhow!("the decoding thread stopped")));
            };
            let (buf, missing) = match read {
                Ok(read) => read,
                Err(problem) => {
                    // One error per bad frame set; the stream goes on without it.
                    skipped += 1;
                    tracing::error!("frame set {k} skipped ({skipped} so far): {problem}");
                    continue;
                }
            };
            // Indexed by position, so a set skipped above is a gap the engine spans (as the
            // flow stage does on a replay's sequence numbers) rather than one frame interval.
            // A camera that dropped its frame of the set is left out of it, as live (without
            // the reference camera's, the set is passed over: its record is the tracks'
            // predictions).
            let pushed = flow.push_partial_at(
                Estimate { index: k, dropped: skipped },
                &buf,
                missing,
                k as u64,
                &mut on_estimate,
            );
            let _ = spare_tx.send(buf);
            pushed.with_context(|| format!("frame {}", rec.frames()[k].frame))?;
            for record in record_rx.try_iter() {
                hand_on(record, skipped)?;
            }
        }
        let finished = flow.finish(&mut on_estimate);
        finished.context("end of the recording")?;
        drop(points_tx);
        for record in record_rx {
            hand_on(record, skipped)?;
        }
        Ok(())
    })?;
    let seconds = started.elapsed().as_secs_f64();
    Ok(TrackSummary {
        frames: written,
        skipped_frames: skipped,
        seconds,
        frames_per_second: written as f64 / seconds.max(1e-9),
        cluster_seconds_per_frame: stage.seconds_per_frame(),
        reinitialisations: stage.reinitialisations(),
    })
}
