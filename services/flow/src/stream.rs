//! The engine over a stream of frame sets, as the offline tracker and the flow service both
//! run it: the stream configuration, skin models adapted by face detection on a thread of
//! its own on a fixed schedule, and the estimates as [`ScenePoint`]s.
//!
//! The schedule depends on the stream alone, never on timing, so the same frames give the
//! same particles in one process or across processes: before the first estimate the models
//! adapt to frames 0, 10 and 20 ([`WARM_UP_ROUNDS`]; the frames up to there are held), then
//! faces are detected on every tenth frame and the models adapted to frame `k` are applied
//! at frame `k + MODEL_LAG`.

use std::collections::VecDeque;
use std::sync::mpsc::{channel, Receiver, Sender};
use std::thread::JoinHandle;

use handflow_protocol::messages::ScenePoint;
use handflow_protocol::Camera;
use nalgebra::{Point3, Vector3};

use crate::skin::SkinModel;
use crate::skin_adapt::{SkinAdapter, DEFAULT_ADAPTATION_RATE, DEFAULT_DETECT_EVERY};
use crate::{Coverage, EngineConfig, FlowError, SceneFlowEngine, Temporal, Variant};

/// Camera-frame depths searched on a stream, metres: a signer is between half a metre and
/// five metres from the cameras of an HCI rig.
pub const STREAM_DEPTH_RANGE_M: (f32, f32) = (0.5, 5.0);
/// Fastest motion searched, metres per second (a fast sign: hands move up to about 3 m/s).
pub const STREAM_SPEED_BOUND_M_S: f32 = 3.0;
/// Adaptation rounds before the first estimate.
pub const WARM_UP_ROUNDS: usize = 3;
/// Frames between detecting faces on a frame and using the models adapted to them.
pub const MODEL_LAG: u64 = 5;
/// Scene Particles per ray on streams: 6 instead of the engine's 10. Every preset stays on
/// target with 6, as with 8, and so does every unseen scene that was (some figures a little
/// lower, the hardest scene's higher); the engine is 1.15 to 1.28x faster than with 8: what
/// the live pipeline needed to sustain 30 fps on two cores (BENCHMARKS.md).
pub const STREAM_PARTICLES_PER_RAY: usize = 6;
/// Half-size of the support window on the grids a stream estimates (3x3): a 5x5 window
/// costs 2.8x as much per evaluation and did not improve the trajectories on any preset
/// (BENCHMARKS.md).
pub const STREAM_WINDOW_RADIUS: usize = 1;
/// Prior on motion in depth on streams, as a fraction of the speed bound (the engine's
/// default, 0.1, was chosen on the narrow Middlebury rig). A signer's hands move towards
/// and away from the cameras at up to about 1 m/s; with 0.1 the flow's depth velocity for
/// such a hand stayed near zero, so its particles, carried by that velocity, lagged 2-7 cm
/// behind in depth (occluded-side's right hand: 94.6 % agreement; 99.3 % with 0.15).
/// BENCHMARKS.md has the sweep over presets and unseen scenes.
pub const STREAM_VELOCITY_PRIOR_DEPTH: f32 = 0.15;
/// Extra passes over a stream's first frame: without them the face's depth takes about
/// five frames to settle and the head starts 4-6 cm too far back (measured on
/// `signer-3cam`: head agreement 98.0 % with none, 99.3 % with 2, 100 % with 4 and 8; 8
/// costs about 0.25 s once).
pub const STREAM_COLD_START_PASSES: usize = 8;

/// The engine configuration for trajectories: the variant's defaults, skin coverage, the
/// forwards/backwards likelihood, the search space of a signer at `fps`, the
/// half-resolution grid (a quarter of the rays is plenty of points for clustering), 2
/// extra coarse loops instead of 7 once the previous frame's posterior is the prior (it
/// replaces most of the exploration a first frame needs), extra passes over the first
/// frame ([`STREAM_COLD_START_PASSES`]) and no weighted-median refinement (on the
/// half-resolution grid its 9x9 window spans two palm widths' worth of edges and
/// measurably moved points off the hands), and 3x3 support windows instead of 5x5 on every
/// level (the same trajectories on every preset, 1.3x faster), and a weaker prior on
/// motion in depth ([`STREAM_VELOCITY_PRIOR_DEPTH`]). BENCHMARKS.md has the measurements.
pub fn stream_engine_config(variant: Variant, particles_per_ray: Option<usize>, fps: f64) -> EngineConfig {
    let defaults = EngineConfig::for_variant(variant);
    EngineConfig {
        particles_per_ray: particles_per_ray.unwrap_or(STREAM_PARTICLES_PER_RAY),
        finest_level: 1,
        warm_coarse_extra_loops: Some(2.min(defaults.coarse_extra_loops)),
        cold_start_passes: STREAM_COLD_START_PASSES,
        refine_radius: 0,
        coarse_window_radius: STREAM_WINDOW_RADIUS,
        coverage: Coverage::Skin,
        temporal: Temporal::ForwardsBackwards,
        depth_range: STREAM_DEPTH_RANGE_M,
        velocity_prior_depth: STREAM_VELOCITY_PRIOR_DEPTH,
        speed_bound: STREAM_SPEED_BOUND_M_S / fps.max(1.0) as f32,
        ..defaults
    }
}

/// Face detection and skin adaptation on a thread of its own (the detector is not `Send`:
/// it lives and dies there). Frame sets go in, adapted models come out, one per frame set.
struct FaceWorker {
    frames: Option<Sender<Vec<u8>>>,
    models: Receiver<Result<Vec<SkinModel>, String>>,
    thread: Option<JoinHandle<()>>,
}

/// Nice value of the face-detection thread. Detections only adapt the skin models, which
/// a live stream applies whenever they are ready; at the default priority a round (about
/// 130 ms of one core for three cameras) took the cores from the frame being estimated and
/// set the live pipeline's p99 latency (BENCHMARKS.md).
const FACE_THREAD_NICE: i32 = 10;

/// Gives the calling thread the nice value [`FACE_THREAD_NICE`] (on Linux a thread's own
/// attribute; elsewhere it would be the whole process's, so nothing is done there).
fn lower_this_threads_priority() {
    #[cfg(target_os = "linux")]
    if let Err(e) = rustix::process::setpriority_process(None, FACE_THREAD_NICE) {
        tracing::debug!("face detection keeps the default priority: {e}");
    }
}

impl FaceWorker {
    fn new(cameras: &[Camera]) -> Self {
        let (frame_tx, frame_rx) = channel::<Vec<u8>>();
        let (model_tx, model_rx) = channel();
        let cameras = cameras.to_vec();
        let thread = std::thread::Builder::new()
            .name("faces".into())
            .spawn(move || {
                lower_this_threads_priority();
                let mut adapter = match SkinAdapter::new(&cameras, DEFAULT_ADAPTATION_RATE, DEFAULT_DETECT_EVERY) {
                    Ok(a) => a,
                    Err(e) => {
                        let _ = model_tx.send(Err(e));
                        return;
                    }
                };
                for frame_set in frame_rx {
                    let views = split_views(&cameras, &frame_set);
                    adapter.adapt_now(&views);
                    if model_tx.send(Ok(adapter.models().to_vec())).is_err() {
                        return;
                    }
                }
            })
            .ok();
        Self { frames: Some(frame_tx), models: model_rx, thread }
    }

    fn send(&self, frame_set: Vec<u8>) -> Result<(), StreamError> {
        self.frames.as_ref().and_then(|tx| tx.send(frame_set).ok()).ok_or(StreamError::FaceWorker)
    }

    /// The next models if they are ready.
    fn try_recv(&self) -> Result<Option<Vec<SkinModel>>, StreamError> {
        match self.models.try_recv() {
            Ok(Ok(models)) => Ok(Some(models)),
            Ok(Err(e)) => Err(StreamError::FaceDetector(e)),
            Err(std::sync::mpsc::TryRecvError::Empty) => Ok(None),
            Err(std::sync::mpsc::TryRecvError::Disconnected) => Err(StreamError::FaceWorker),
        }
    }

    fn recv(&self) -> Result<Vec<SkinModel>, StreamError> {
        match self.models.recv() {
            Ok(Ok(models)) => Ok(models),
            Ok(Err(e)) => Err(StreamError::FaceDetector(e)),
            Err(_) => Err(StreamError::FaceWorker),
        }
    }
}

impl Drop for FaceWorker {
    fn drop(&mut self) {
        self.frames = None;
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

fn split_views<'a>(cameras: &[Camera], frame_set: &'a [u8]) -> Vec<&'a [u8]> {
    let mut offset = 0;
    cameras
        .iter()
        .map(|c| {
            let len = c.width as usize * c.height as usize * 3;
            let v = frame_set.get(offset..offset + len).unwrap_or(&[]);
            offset += len;
            v
        })
        .collect()
}

/// What can stop a stream.
#[derive(Debug, thiserror::Error)]
pub enum StreamError {
    /// The engine refused a frame set.
    #[error(transparent)]
    Engine(#[from] FlowError),
    /// The face detector could not be built.
    #[error("face detector: {0}")]
    FaceDetector(String),
    /// The face detection thread stopped.
    #[error("the face detection thread stopped")]
    FaceWorker,
    /// A frame set's length does not fit the rig.
    #[error("frame set of {got} bytes, the rig's cameras need {expected}")]
    FrameSetLength {
        /// Bytes the cameras need.
        expected: usize,
        /// Bytes given.
        got: usize,
    },
}

/// The scene-flow engine over one stream of frame sets, each tagged with `M` (the caller's
/// frame metadata), handing every estimate out with the metadata of its frame.
pub struct FlowStream<M> {
    engine: SceneFlowEngine,
    faces: FaceWorker,
    frame_set_len: usize,
    /// Frames held until the warm-up rounds have their frames.
    held: Option<Vec<(M, Vec<u8>)>>,
    /// Frames pushed into the engine.
    pushed: u64,
    /// Frames at which the next adapted models are applied.
    pending_models: VecDeque<u64>,
    /// Push index and metadata of frames not yet estimated, oldest first.
    waiting: VecDeque<(u64, M)>,
    /// Of the frames held for the warm-up, only the newest this many are estimated (live
    /// streams: the older ones are stale by then).
    backlog_limit: Option<usize>,
    /// Frames held before the warm-up runs.
    warm_up_frames: u64,
    /// Whether a frame waits for models that are due but not ready (the fixed schedule that
    /// makes a replay repeatable), or goes on with the current ones (live streams).
    wait_for_models: bool,
    /// What `wait_for_models` is at the start of each stream.
    waits_by_default: bool,
    /// Frames between face detections.
    detect_every: u64,
}

/// Frames the warm-up looks at last: frame `(WARM_UP_ROUNDS - 1) * DEFAULT_DETECT_EVERY`.
const LAST_WARM_UP_FRAME: u64 = (WARM_UP_ROUNDS as u64 - 1) * DEFAULT_DETECT_EVERY;

impl<M> FlowStream<M> {
    /// A stream through `engine`.
    pub fn new(engine: SceneFlowEngine) -> Self {
        let faces = FaceWorker::new(engine.cameras());
        let frame_set_len = engine.cameras().iter().map(|c| c.width as usize * c.height as usize * 3).sum();
        Self {
            engine,
            faces,
            frame_set_len,
            held: Some(Vec::new()),
            pushed: 0,
            pending_models: VecDeque::new(),
            waiting: VecDeque::new(),
            backlog_limit: None,
            warm_up_frames: LAST_WARM_UP_FRAME + 1,
            wait_for_models: true,
            waits_by_default: true,
            detect_every: DEFAULT_DETECT_EVERY,
        }
    }

    /// Estimates only the newest `frames` of those held for the warm-up (at least 2, what
    /// the forwards/backwards window needs); the older ones are skipped. For live streams,
    /// where catching up on stale frames only adds latency.
    pub fn with_backlog_limit(mut self, frames: usize) -> Self {
        self.backlog_limit = Some(frames.max(2));
        self
    }

    /// Detects faces on every `frames`-th frame instead of every
    /// [`DEFAULT_DETECT_EVERY`]-th after the warm-up (a live stream on few cores spends the
    /// detector's time on frames instead; skin colour under steady lighting changes slowly).
    pub fn with_detect_every(mut self, frames: u64) -> Self {
        self.detect_every = frames.max(1);
        self
    }

    /// For a stream joined part-way through (a restarted stage): nothing is held and
    /// nothing waits for the face detector, so estimates start two frames later; the skin
    /// models start generic and adapt as detections finish.
    pub fn joining_mid_stream(&mut self) {
        self.warm_up_frames = 0;
        self.wait_for_models = false;
    }

    /// Never waits for the face detector: adapted models are applied at the first frame
    /// after they are both due and ready, and a new detection starts only when the last one
    /// has finished. For live streams, where a frame must not wait for a detector that is
    /// slower than the schedule (the estimates then depend on timing).
    pub fn without_waiting_for_models(mut self) -> Self {
        self.wait_for_models = false;
        self.waits_by_default = false;
        self
    }

    /// The engine (its configuration, cameras, last estimate).
    pub fn engine(&self) -> &SceneFlowEngine {
        &self.engine
    }

    /// Adds the next frame set (every view's RGB8 bytes in rig order) and hands each
    /// estimate it completes to `on_estimate` with its frame's metadata. The handler's own
    /// error type passes through; the stream's errors convert into it.
    pub fn push<E: From<StreamError>>(
        &mut self,
        meta: M,
        frame_set: &[u8],
        mut on_estimate: impl FnMut(M, &SceneFlowEngine) -> Result<(), E>,
    ) -> Result<(), E> {
        if frame_set.len() != self.frame_set_len {
            return Err(StreamError::FrameSetLength { expected: self.frame_set_len, got: frame_set.len() }.into());
        }
        if let Some(held) = self.held.as_mut() {
            // Copies only the first frames of a stream, once.
            held.push((meta, frame_set.to_vec()));
            if held.len() as u64 >= self.warm_up_frames {
                self.release_held(&mut on_estimate)?;
            }
            return Ok(());
        }
        self.push_now(meta, frame_set, &mut on_estimate)
    }

    /// Ends the stream: estimates what is left (the last frame with the two-frame
    /// likelihood) and makes the stream ready for a new, unrelated one.
    pub fn finish<E: From<StreamError>>(
        &mut self,
        mut on_estimate: impl FnMut(M, &SceneFlowEngine) -> Result<(), E>,
    ) -> Result<(), E> {
        if self.held.as_ref().is_some_and(|h| !h.is_empty()) {
            self.release_held(&mut on_estimate)?;
        }
        if self.engine.flush().is_some() {
            self.hand_out(&mut on_estimate)?;
        }
        self.engine.reset();
        self.held = Some(Vec::new());
        self.warm_up_frames = LAST_WARM_UP_FRAME + 1;
        self.wait_for_models = self.waits_by_default;
        self.pushed = 0;
        self.pending_models.clear();
        self.waiting.clear();
        Ok(())
    }

    /// Runs the warm-up on the held frames, then pushes them.
    fn release_held<E: From<StreamError>>(
        &mut self,
        on_estimate: &mut impl FnMut(M, &SceneFlowEngine) -> Result<(), E>,
    ) -> Result<(), E> {
        let held = self.held.take().unwrap_or_default();
        if held.is_empty() {
            return Ok(());
        }
        let rounds = if self.warm_up_frames == 0 { 0 } else { WARM_UP_ROUNDS.min(held.len()) };
        for k in 0..rounds {
            let index = (k as u64 * DEFAULT_DETECT_EVERY) as usize % held.len();
            self.faces.send(held[index].1.clone())?;
            let models = self.faces.recv()?;
            self.engine.set_skin_models(&models).map_err(StreamError::from)?;
        }
        let skip = self.backlog_limit.map_or(0, |keep| held.len().saturating_sub(keep));
        for (meta, frame_set) in held.into_iter().skip(skip) {
            self.push_now(meta, &frame_set, on_estimate)?;
        }
        Ok(())
    }

    fn push_now<E: From<StreamError>>(
        &mut self,
        meta: M,
        frame_set: &[u8],
        on_estimate: &mut impl FnMut(M, &SceneFlowEngine) -> Result<(), E>,
    ) -> Result<(), E> {
        let k = self.pushed;
        if k.is_multiple_of(self.detect_every) && (self.wait_for_models || self.pending_models.is_empty()) {
            self.faces.send(frame_set.to_vec())?;
            self.pending_models.push_back(k + MODEL_LAG);
        }
        if self.pending_models.front().is_some_and(|&due| due <= k) {
            let models = if self.wait_for_models { Some(self.faces.recv()?) } else { self.faces.try_recv()? };
            if let Some(models) = models {
                self.pending_models.pop_front();
                self.engine.set_skin_models(&models).map_err(StreamError::from)?;
            }
        }
        let views = split_views(self.engine.cameras(), frame_set);
        self.waiting.push_back((k, meta));
        self.pushed += 1;
        if self.engine.push_frame(&views).map_err(StreamError::from)?.is_some() {
            self.hand_out(on_estimate)?;
        }
        Ok(())
    }

    /// Hands the engine's last estimate out with its frame's metadata; frames before it
    /// never get one (the first frame of a forwards/backwards stream).
    fn hand_out<E: From<StreamError>>(
        &mut self,
        on_estimate: &mut impl FnMut(M, &SceneFlowEngine) -> Result<(), E>,
    ) -> Result<(), E> {
        let frame = self.engine.stats().frame;
        while let Some((k, meta)) = self.waiting.pop_front() {
            if k == frame {
                return on_estimate(meta, &self.engine);
            }
        }
        Ok(())
    }
}

/// The particles of the engine's last estimate, as what clustering needs: every particle
/// of every ray with confidence, its weight times the ray's confidence, and the skin
/// probability of the ray's pixel.
pub fn scene_points(engine: &SceneFlowEngine) -> impl Iterator<Item = ScenePoint> + '_ {
    let field = engine.field();
    let reference = engine.reference();
    let cam = &engine.cameras()[reference];
    let scale = cam.width as usize / field.width.max(1);
    (0..field.width * field.height).filter(move |&ray| field.confidence[ray] > 0.0).flat_map(move |ray| {
        let confidence = field.confidence[ray];
        let (x, y) = ((ray % field.width) * scale + scale / 2, (ray / field.width) * scale + scale / 2);
        // The clamped log10 ratio of skin to background likelihood, as a probability.
        let skin = engine.skin_at(reference, x, y).map_or(0.0, |r| 1.0 / (1.0 + 10f32.powf(-r)));
        engine.ray_particles(ray).iter().map(move |p| ScenePoint {
            position: engine.particle_position(ray, p),
            velocity: p.velocity,
            weight: p.weight * confidence,
            skin,
        })
    })
}

/// Number of points [`scene_points`] yields.
pub fn scene_point_count(engine: &SceneFlowEngine) -> usize {
    let field = engine.field();
    (0..field.width * field.height)
        .filter(|&ray| field.confidence[ray] > 0.0)
        .map(|ray| engine.ray_particles(ray).len())
        .sum()
}

/// The confidence-weighted mean variance of a ray's particles along the ray, square metres
/// (the filter's own depth uncertainty, measured from the reference camera's centre).
pub fn ray_spread_variance(engine: &SceneFlowEngine) -> f64 {
    let field = engine.field();
    let eye: Point3<f64> = engine.cameras()[engine.reference()].centre();
    let (mut spread, mut spread_weight) = (0.0, 0.0);
    for ray in 0..field.width * field.height {
        let confidence = f64::from(field.confidence[ray]);
        if confidence <= 0.0 {
            continue;
        }
        let particles = engine.ray_particles(ray);
        let w: f64 = particles.iter().map(|p| f64::from(p.weight)).sum();
        if w > 0.0 && particles.len() > 1 {
            let distance = |p: &crate::Particle| {
                let q = engine.particle_position(ray, p);
                (Vector3::new(f64::from(q[0]), f64::from(q[1]), f64::from(q[2])) - eye.coords).norm()
            };
            let mean = particles.iter().map(|p| f64::from(p.weight) * distance(p)).sum::<f64>() / w;
            let var = particles.iter().map(|p| f64::from(p.weight) * (distance(p) - mean).powi(2)).sum::<f64>() / w;
            spread += confidence * var;
            spread_weight += confidence;
        }
    }
    if spread_weight > 0.0 {
        spread / spread_weight
    } else {
        0.0
    }
}
