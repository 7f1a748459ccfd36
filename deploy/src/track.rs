//! `handflow track`: recording in, trajectories out, in one process: ingest reading, the
//! scene-flow engine (skin coverage, forwards/backwards), EM clustering in 6D and
//! labelling, frame by frame.

use std::collections::BTreeMap;
use std::path::Path;
use std::time::Instant;

use anyhow::{Context, Result};
use handflow_cluster::em::{extremity_means, fit_mixture, Component, EmConfig};
use handflow_cluster::tracks::{State, Tracker, TrackerConfig, OBJECTS};
use handflow_cluster::WeightedPoint;
use handflow_flow::skin_adapt::{SkinAdapter, DEFAULT_ADAPTATION_RATE, DEFAULT_DETECT_EVERY};
use handflow_flow::{SceneFlowEngine, Variant};
use handflow_ingest::Recording;
use handflow_publish::{ObjectSample, TrackState, TrajectoryRecord};
use nalgebra::{Point3, Vector3};

use crate::recording_flow::{recording_engine_config, recording_fps, reference_camera, WARM_UP_ROUNDS};

/// Frames between detecting faces on a frame and using the models adapted to them.
pub const MODEL_LAG: u64 = 5;

/// The largest half-thickness the centre correction assumes for a hand, metres: an adult
/// palm is 2-4 cm thick, a loose fist a little more.
pub const HAND_HALF_THICKNESS_M: f64 = 0.02;

/// What to run.
#[derive(Clone, Debug)]
pub struct TrackOptions {
    /// Engine formulation.
    pub variant: Variant,
    /// Scene Particles per ray (the recording default when `None`).
    pub particles_per_ray: Option<usize>,
    /// Engine configuration overrides, `field=value`.
    pub overrides: Vec<String>,
    /// Track only the first N frames.
    pub max_frames: Option<usize>,
    /// Move each cluster's centre from the visible surface to the object's middle (see
    /// [`surface_to_centre`]; default true).
    pub centre_correction: bool,
}

impl Default for TrackOptions {
    fn default() -> Self {
        Self {
            variant: Variant::Handflow,
            particles_per_ray: None,
            overrides: Vec::new(),
            max_frames: None,
            centre_correction: true,
        }
    }
}

/// How a run went.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct TrackSummary {
    /// Trajectory records written (one per frame with an estimate).
    pub frames: usize,
    /// Wall time of the whole run (decoding, face detection, engine, clustering), seconds.
    pub seconds: f64,
    /// `frames / seconds`.
    pub frames_per_second: f64,
    /// Mean clustering and labelling time per frame, seconds.
    pub cluster_seconds_per_frame: f64,
    /// Tracks re-initialised on a cluster far from their prediction.
    pub reinitialisations: u64,
}

/// Runs the tracker over a recording, handing each frame's record to `on_record` with the
/// number of frames done and to do.
pub fn track_recording(
    dir: &Path,
    options: &TrackOptions,
    mut on_record: impl FnMut(&TrajectoryRecord, usize, usize) -> Result<()>,
) -> Result<TrackSummary> {
    let started = Instant::now();
    let rec = Recording::open(dir)?;
    let rig = rec.rig().clone();
    let fps = recording_fps(&rec);
    let config = recording_engine_config(options.variant, options.particles_per_ray, fps, &options.overrides)?;
    let reference = reference_camera(&rig);
    let camera = &rig.cameras[reference];
    // The signer faces the reference camera: image up is the world's up, image right the
    // signer's left.
    let axes = camera.rotation.matrix();
    let up = -axes.row(1).transpose();
    let signer_left = axes.row(0).transpose();
    let eye = camera.centre();
    let mut engine = SceneFlowEngine::new(config, rig.cameras.clone(), reference)?;
    let frames = options.max_frames.unwrap_or(rec.len()).min(rec.len());
    anyhow::ensure!(frames >= 2, "recording `{}` needs at least 2 frames, has {frames}", dir.display());
    let mut stage = ClusterStage {
        ray_spread_var: 0.0,
        tracker: Tracker::new(TrackerConfig::default(), up, signer_left),
        em: EmConfig::default(),
        points: Vec::new(),
        fps,
        eye,
        centre_correction: options.centre_correction,
        seconds: 0.0,
    };
    let mut written = 0;
    // Every frame but the first gets an estimate (the last through the flush).
    let total = frames - 1;
    // Three threads of control: frames are decoded one ahead, faces are detected beside the
    // engine, and the engine and clustering run here. Adapted models are applied
    // `MODEL_LAG` frames after the frame they were detected on, whatever the timing, so a
    // run's output depends on the recording alone.
    std::thread::scope(|scope| -> Result<()> {
        let (frame_tx, frame_rx) = std::sync::mpsc::sync_channel::<Result<Vec<u8>>>(2);
        let (spare_tx, spare_rx) = std::sync::mpsc::channel::<Vec<u8>>();
        let rec_ref = &rec;
        scope.spawn(move || {
            for k in 0..frames {
                let mut buf = spare_rx.try_recv().unwrap_or_else(|_| vec![0u8; rec_ref.frame_set_len()]);
                let read = rec_ref.read_frame_into(k as u64, false, &mut buf).map(|_| buf).map_err(anyhow::Error::from);
                let failed = read.is_err();
                if frame_tx.send(read).is_err() || failed {
                    return;
                }
            }
        });
        let (face_tx, face_rx) = std::sync::mpsc::channel::<Vec<u8>>();
        let (model_tx, model_rx) = std::sync::mpsc::channel::<Result<Vec<handflow_flow::skin::SkinModel>>>();
        let cameras = rig.cameras.clone();
        scope.spawn(move || {
            // The detector is not `Send`: it lives and dies on this thread.
            let mut adapter = match SkinAdapter::new(&cameras, DEFAULT_ADAPTATION_RATE, DEFAULT_DETECT_EVERY) {
                Ok(a) => a,
                Err(e) => {
                    let _ = model_tx.send(Err(anyhow::Error::msg(e)));
                    return;
                }
            };
            for frame_set in face_rx {
                let mut offset = 0;
                let views: Vec<&[u8]> = cameras
                    .iter()
                    .map(|c| {
                        let len = c.width as usize * c.height as usize * 3;
                        let v = &frame_set[offset..offset + len];
                        offset += len;
                        v
                    })
                    .collect();
                adapter.adapt_now(&views);
                if model_tx.send(Ok(adapter.models().to_vec())).is_err() {
                    return;
                }
            }
        });
        let apply_models = |engine: &mut SceneFlowEngine| -> Result<()> {
            let models = model_rx.recv().context("the face detection thread stopped")??;
            engine.set_skin_models(&models)?;
            Ok(())
        };
        // Adapt before the first estimate, as a running service would have by then.
        let mut warm = vec![0u8; rec.frame_set_len()];
        for k in 0..WARM_UP_ROUNDS.min(frames) {
            rec.read_frame_into((k as u64) * DEFAULT_DETECT_EVERY % rec.len() as u64, false, &mut warm)?;
            face_tx.send(warm.clone()).context("the face detection thread stopped")?;
            apply_models(&mut engine)?;
        }
        let mut pending = Vec::new();
        for k in 0..frames {
            let buf = frame_rx.recv().context("the decoding thread stopped")??;
            let k = k as u64;
            if k % DEFAULT_DETECT_EVERY == 0 {
                face_tx.send(buf.clone()).context("the face detection thread stopped")?;
                pending.push(k + MODEL_LAG);
            }
            if pending.first() == Some(&k) {
                pending.remove(0);
                apply_models(&mut engine)?;
            }
            let views = rec.views(&buf);
            let done = engine.push_frame(&views).with_context(|| format!("frame {k}"))?.is_some();
            let _ = spare_tx.send(buf);
            if done {
                let record = stage.record(&engine, &rec)?;
                written += 1;
                on_record(&record, written, total)?;
            }
        }
        drop(face_tx);
        if engine.flush().is_some() {
            let record = stage.record(&engine, &rec)?;
            written += 1;
            on_record(&record, written, total)?;
        }
        Ok(())
    })?;
    let seconds = started.elapsed().as_secs_f64();
    Ok(TrackSummary {
        frames: written,
        seconds,
        frames_per_second: written as f64 / seconds.max(1e-9),
        cluster_seconds_per_frame: stage.seconds / written.max(1) as f64,
        reinitialisations: stage.tracker.reinitialisations(),
    })
}

/// Clustering and labelling of the engine's estimates.
struct ClusterStage {
    /// Mean variance of a ray's particles along the ray, this frame, square metres.
    ray_spread_var: f64,
    tracker: Tracker,
    em: EmConfig,
    points: Vec<WeightedPoint>,
    fps: f64,
    eye: Point3<f64>,
    centre_correction: bool,
    seconds: f64,
}

impl ClusterStage {
    /// The trajectory record of the engine's last estimate.
    fn record(&mut self, engine: &SceneFlowEngine, rec: &Recording) -> Result<TrajectoryRecord> {
        let started = Instant::now();
        let index = engine.stats().frame as usize;
        let entry =
            rec.frames().get(index).with_context(|| format!("estimate for frame {index} beyond the recording"))?;
        let t = entry.timestamp;
        self.collect_points(engine);
        let initial = match self.tracker.predictions(t) {
            Some(p) => Some(p),
            None => extremity_means(&self.points, self.tracker_up(engine), self.tracker_left(engine)),
        };
        let mut fit = initial.and_then(|init| fit_mixture(&self.points, &init, &self.em));
        let raw = fit.clone();
        if let (Some(fit), true) = (fit.as_mut(), self.centre_correction) {
            for c in fit.components.iter_mut() {
                surface_to_centre(c, &self.eye, self.em.min_std, self.ray_spread_var, HAND_HALF_THICKNESS_M);
            }
        }
        let mut tracks = self.tracker.update(t, fit.as_ref());
        // The head's skin is its face, a shallow cap of a nearly round object: its depth spread
        // says little about its size, so its centre comes from the spread across the view.
        if let (Some(fit), Some(raw), true) = (&fit, &raw, self.centre_correction) {
            if let (State::Tracked, Some(m)) = (tracks[0].state, self.tracker.assigned()[0]) {
                let mut head = raw.components[m.cluster];
                surface_to_centre(&mut head, &self.eye, self.em.min_std, f64::INFINITY, f64::INFINITY);
                // By the share of the measurement the tracker took.
                tracks[0].position += (head.position - fit.components[m.cluster].position) * m.pull;
                self.tracker.set_position(0, tracks[0].position);
            }
        }
        let objects: BTreeMap<String, ObjectSample> = OBJECTS
            .iter()
            .zip(tracks)
            .map(|(name, k)| {
                let sample = ObjectSample {
                    pos: k.position.into(),
                    vel: k.velocity.into(),
                    confidence: k.confidence,
                    state: match k.state {
                        State::Tracked => TrackState::Tracked,
                        State::Predicted => TrackState::Predicted,
                        State::Lost => TrackState::Lost,
                    },
                };
                ((*name).to_owned(), sample)
            })
            .collect();
        self.seconds += started.elapsed().as_secs_f64();
        Ok(TrajectoryRecord { frame: entry.frame, t, objects })
    }

    fn tracker_up(&self, engine: &SceneFlowEngine) -> Vector3<f64> {
        -engine.cameras()[engine.reference()].rotation.matrix().row(1).transpose()
    }

    fn tracker_left(&self, engine: &SceneFlowEngine) -> Vector3<f64> {
        engine.cameras()[engine.reference()].rotation.matrix().row(0).transpose()
    }

    /// Every particle of the estimate as a weighted 6D point: the particle's weight times
    /// its ray's confidence, velocity in metres per second.
    fn collect_points(&mut self, engine: &SceneFlowEngine) {
        self.points.clear();
        let field = engine.field();
        let (mut spread, mut spread_weight) = (0.0, 0.0);
        for ray in 0..field.width * field.height {
            let confidence = f64::from(field.confidence[ray]);
            if confidence <= 0.0 {
                continue;
            }
            // The particles' own spread along the ray: part of every cluster's variance in
            // depth that says nothing about the object's shape.
            let particles = engine.ray_particles(ray);
            let w: f64 = particles.iter().map(|p| f64::from(p.weight)).sum();
            if w > 0.0 && particles.len() > 1 {
                let distance = |p: &handflow_flow::Particle| {
                    let q = engine.particle_position(ray, p);
                    (Vector3::new(f64::from(q[0]), f64::from(q[1]), f64::from(q[2])) - self.eye.coords).norm()
                };
                let mean = particles.iter().map(|p| f64::from(p.weight) * distance(p)).sum::<f64>() / w;
                let var = particles.iter().map(|p| f64::from(p.weight) * (distance(p) - mean).powi(2)).sum::<f64>() / w;
                spread += confidence * var;
                spread_weight += confidence;
            }
            for p in particles {
                let pos = engine.particle_position(ray, p);
                self.points.push(WeightedPoint {
                    position: Vector3::new(f64::from(pos[0]), f64::from(pos[1]), f64::from(pos[2])),
                    velocity: Vector3::new(
                        f64::from(p.velocity[0]),
                        f64::from(p.velocity[1]),
                        f64::from(p.velocity[2]),
                    ) * self.fps,
                    weight: f64::from(p.weight) * confidence,
                });
            }
        }
        self.ray_spread_var = if spread_weight > 0.0 { spread / spread_weight } else { 0.0 };
    }
}

/// Moves a cluster's centre from the surface the reference camera sees to the object's
/// middle. The points of a roughly convex object (a head, a hand) seen from one side lie on
/// its front: for a sphere of radius r the visible points' centroid is 2r/3 in front of the
/// centre. The radius along the line of sight is estimated twice, from the spread across
/// the view (r/2 for a sphere) and from the spread in depth (0.236 r), and the smaller is
/// used: a flat hand facing the camera is wide but thin, and depth noise only ever widens
/// the second estimate. `min_std` is the floor EM added to every variance and
/// `ray_spread_var` the variance a ray's particles have along it (the filter's own
/// uncertainty, not the object's depth): both are taken out of the depth spread first.
/// `max_depth_radius` bounds the result by what the object can be: depth noise the
/// filter's spread does not account for still widens the depth estimate, and a hand's
/// spread across the view is its width, not its thickness.
pub fn surface_to_centre(
    c: &mut Component,
    eye: &Point3<f64>,
    min_std: f64,
    ray_spread_var: f64,
    max_depth_radius: f64,
) {
    let Some(sight) = (c.position - eye.coords).try_normalize(1e-9) else { return };
    let p = c.covariance.fixed_view::<3, 3>(0, 0);
    let floor = min_std * min_std;
    let along = (sight.transpose() * p * sight)[(0, 0)];
    let across = (p.trace() - along) / 2.0;
    let r_across = 2.0 * (across - floor).max(0.0).sqrt();
    // An infinite `ray_spread_var` leaves only the estimate across the view.
    let r_along = if ray_spread_var.is_finite() {
        (along - floor - ray_spread_var).max(0.0).sqrt() / 0.236
    } else {
        f64::INFINITY
    };
    c.position += sight * (2.0 / 3.0) * r_across.min(r_along).min(max_depth_radius);
}
