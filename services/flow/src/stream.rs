//! The engine over a stream of frame sets, as the offline tracker and the flow service both
//! run it: the stream configuration, skin models adapted by face detection on a thread of
//! its own on a fixed schedule, and the estimates as [`ScenePoint`]s.
//!
//! The schedule depends on the stream alone, never on timing, so the same frames give the
//! same particles in one process or across processes: before the first estimate the models
//! adapt to frames 0, 10 and 20 ([`WARM_UP_ROUNDS`]; the frames up to there are held), then
//! faces are detected on every tenth frame and the models adapted to frame `k` are applied
//! at frame `k + MODEL_LAG`. [`FlowStream::with_frame_rate`] keeps those intervals in time
//! at lower rates (at 6 fps: frames 0, 2 and 4, every second frame, one frame later).

use std::collections::VecDeque;
use std::sync::mpsc::{channel, Receiver, Sender};
use std::thread::JoinHandle;

use handflow_protocol::messages::ScenePoint;
use handflow_protocol::Camera;
use nalgebra::{Point3, Vector3};

use crate::skin::adapt::{SkinAdapter, DEFAULT_ADAPTATION_RATE, DEFAULT_DETECT_EVERY};
use crate::skin::face_fusion::FusedFaces;
use crate::skin::faces::FaceBox;
use crate::skin::model::{skin_share_of, SkinModel, SKIN_SHARE_STRIDE};
use crate::{Coverage, EngineConfig, FlowError, SceneFlowEngine, Temporal, Variant};

/// Camera-frame depths searched on a stream, metres: a signer is between half a metre and
/// five metres from the cameras of an HCI rig.
pub const STREAM_DEPTH_RANGE_M: (f32, f32) = (0.5, 5.0);
/// Fastest motion searched, metres per second (a fast sign: hands move up to about 3 m/s).
pub const STREAM_SPEED_BOUND_M_S: f32 = 3.0;
/// Largest acceleration of a hand, metres per second squared (the tracker's bound too): what
/// the constant-velocity model can miss by over a frame interval `dt` is at most
/// `STREAM_MAX_ACCELERATION_M_S2 * dt^2 / 2`.
pub const STREAM_MAX_ACCELERATION_M_S2: f64 = 20.0;
/// Length of a hand, metres: a carried hypothesis off by less than this still lands on the
/// hand's skin.
pub const HAND_LENGTH_M: f64 = 0.17;
/// Extra coarsest-level loops on a warm frame (the previous posterior the prior) when the
/// constant-velocity prediction can miss a hand by a hand's length or more.
pub const MAX_WARM_COARSE_EXTRA_LOOPS: usize = 2;
/// Adaptation rounds before the first estimate.
pub const WARM_UP_ROUNDS: usize = 3;
/// Frames between detecting faces on a frame and using the models adapted to them, at 30
/// frames per second and above; at lower rates [`model_lag_for_rate`] keeps the lag near
/// [`MODEL_LAG_S`].
pub const MODEL_LAG: u64 = 5;
/// The time a detection round may take before its models are used, seconds (5 frames at
/// 30 fps): about what a round of four views costs one core.
pub const MODEL_LAG_S: f64 = 0.17;
/// Time between face detections in replay, seconds (10 frames at 30 fps). Faces anchor the
/// head track as well as the skin models, so the cadence follows time, not frames: at 6 fps
/// every 10th frame would be 1.7 s apart.
pub const DETECT_INTERVAL_S: f64 = 1.0 / 3.0;

/// Frames between face detections for a stream at `fps` ([`DETECT_INTERVAL_S`], at least
/// every frame, at most every [`DEFAULT_DETECT_EVERY`]-th).
pub fn detect_every_for_rate(fps: f64) -> u64 {
    frames_in(fps, DETECT_INTERVAL_S).min(DEFAULT_DETECT_EVERY)
}

/// Frames between detecting faces and using the models for a stream at `fps`.
pub fn model_lag_for_rate(fps: f64) -> u64 {
    frames_in(fps, MODEL_LAG_S).min(MODEL_LAG)
}

/// Frames in `seconds` of a stream at `fps`, rounded, at least 1 (1 for a rate that is not
/// a positive number).
pub fn frames_in(fps: f64, seconds: f64) -> u64 {
    if fps.is_finite() && fps > 0.0 {
        ((fps * seconds).round() as u64).max(1)
    } else {
        1
    }
}
/// Extra coarsest-level loops on a warm frame of a stream at `fps`. They are the search for
/// motion the carried posterior did not predict: each loop draws fresh hypotheses over the
/// whole speed range and spreads the good ones between rays. How far the prediction can
/// miss grows with the square of the frame interval ([`STREAM_MAX_ACCELERATION_M_S2`]):
/// 1.1 cm at 30 fps, 4.4 cm at 15, 28 cm at 6. A miss well within a hand's length leaves
/// the carried particles on the hand's skin, where the finest level's loops correct them;
/// so the loops follow the miss in hand lengths: none from about 20 fps up, one at 10 to
/// 15 fps, [`MAX_WARM_COARSE_EXTRA_LOOPS`] at 8 fps and below. Measured (BENCHMARKS.md):
/// at 30 fps every preset keeps its figures without them and the engine is 1.3x faster;
/// at 6 fps fewer than 2 lose hands on the shared real session and on `signer-6fps`.
pub fn warm_coarse_extra_loops_for_rate(fps: f64) -> usize {
    if !(fps.is_finite() && fps > 0.0) {
        return MAX_WARM_COARSE_EXTRA_LOOPS;
    }
    let miss_m = 0.5 * STREAM_MAX_ACCELERATION_M_S2 / (fps * fps);
    let loops = (MAX_WARM_COARSE_EXTRA_LOOPS as f64 * miss_m / HAND_LENGTH_M).round();
    (loops as usize).min(MAX_WARM_COARSE_EXTRA_LOOPS)
}

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
/// Extra passes over the first frame of a stream joined part-way (a restarted stage): the
/// stream's trajectories are already running, and the eight passes of a start cost a
/// restarted stage most of its second (0.7 s on four 1280x720 views), while the carried
/// posterior settles the depth over the next frames.
pub const JOIN_COLD_START_PASSES: usize = 1;
/// Frames a stream joined part-way pushes before its cold estimates are out (its first
/// frame's from t and t+1, then its second's from t-1, t and t+1).
const JOIN_FIRST_ESTIMATE_FRAMES: u64 = 3;

/// The engine configuration for trajectories: the variant's defaults, skin coverage, the
/// forwards/backwards likelihood, the search space of a signer at `fps`, the grid of the
/// working level the rig's image size and expected palm size give ([`working_level`]:
/// a hand needs a few hundred points, not every pixel) with rays two pixels apart where a
/// palm stays [`MIN_PALM_RAYS`] wide ([`ray_subsampling`]), at most 2
/// extra coarse loops instead of 7 once the previous frame's posterior is the prior (it
/// replaces most of the exploration a first frame needs; fewer as the frame rate rises,
/// [`warm_coarse_extra_loops_for_rate`]), extra passes over the first
/// frame ([`STREAM_COLD_START_PASSES`]) and no weighted-median refinement (on the
/// half-resolution grid its 9x9 window spans two palm widths' worth of edges and
/// measurably moved points off the hands), and 3x3 support windows instead of 5x5 on every
/// level (the same trajectories on every preset, 1.3x faster), and a weaker prior on
/// motion in depth ([`STREAM_VELOCITY_PRIOR_DEPTH`]). BENCHMARKS.md has the measurements.
pub fn stream_engine_config(
    variant: Variant,
    particles_per_ray: Option<usize>,
    fps: f64,
    cameras: &[Camera],
    reference: usize,
) -> EngineConfig {
    let defaults = EngineConfig::for_variant(variant);
    let palm_px = expected_palm_px(cameras, reference);
    let finest_level = cameras.get(reference).map_or(1, |_| working_level(palm_px));
    let ray_subsampling = ray_subsampling(palm_px, finest_level);
    EngineConfig {
        particles_per_ray: particles_per_ray.unwrap_or(STREAM_PARTICLES_PER_RAY),
        finest_level,
        ray_subsampling,
        // The working level and the levels up to one coarser than the finest ray grid: the
        // coarsest level's rays must lie farther apart than the finest's, or its loops only
        // blur the images (its search for depth and motion gains no reach). Measured on the
        // shared real session (rays two pixels apart): a fourth level instead of a third
        // kept the likelihood evaluations (150,000 per frame) and gave the left hand 5.3
        // points within 5 cm, the head 2.0 (six seeds, BENCHMARKS.md).
        pyramid_levels: finest_level + ray_subsampling + 2,
        warm_coarse_extra_loops: Some(warm_coarse_extra_loops_for_rate(fps).min(defaults.coarse_extra_loops)),
        cold_start_passes: STREAM_COLD_START_PASSES,
        estimate_first_frame: true,
        refine_radius: 0,
        coarse_window_radius: STREAM_WINDOW_RADIUS,
        coverage: Coverage::Skin,
        temporal: Temporal::ForwardsBackwards,
        depth_range: STREAM_DEPTH_RANGE_M,
        velocity_prior_depth: STREAM_VELOCITY_PRIOR_DEPTH,
        speed_bound: STREAM_SPEED_BOUND_M_S / fps.max(1.0) as f32,
        second_reference: true,
        ..defaults
    }
}

/// Extra passes over a live stream's first frame (twice as many) and its second: the
/// [`STREAM_COLD_START_PASSES`] of a recording cost 26 frames' work before the first
/// estimate is out, and a live stage skips every frame set that arrives meanwhile (over
/// a second of them on four 1280x720 views); 2 keep most of the gain (`signer-3cam`'s
/// head 99.3 % against 98.0 % with none and 100 % with 8).
pub const LIVE_COLD_START_PASSES: usize = 2;

/// The engine configuration of a live stream: [`stream_engine_config`] keeping the full
/// warm search ([`MAX_WARM_COARSE_EXTRA_LOOPS`]) whatever the rate, with
/// [`LIVE_COLD_START_PASSES`]. Live, the newest frame set wins: on a loaded machine
/// consecutive estimates can be several frame intervals apart, so the camera's rate says
/// nothing of how far the prediction can miss.
pub fn live_stream_engine_config(variant: Variant, fps: f64, cameras: &[Camera], reference: usize) -> EngineConfig {
    let config = stream_engine_config(variant, None, fps, cameras, reference);
    let full = MAX_WARM_COARSE_EXTRA_LOOPS.min(config.coarse_extra_loops);
    EngineConfig { warm_coarse_extra_loops: Some(full), cold_start_passes: LIVE_COLD_START_PASSES, ..config }
}

/// Width of an adult's palm, metres (the reference's palm centre sits in it).
pub const PALM_WIDTH_M: f64 = 0.085;
/// Least width of a palm in pixels of the level the engine estimates on. The working level
/// is the coarsest that keeps it: coarser levels cost a quarter as much per step but blur
/// fingers (a quarter of the palm) into the background. Measured: on the shared real
/// session's 1280x720 webcams (palms about 57 px wide at full resolution), 28 px palms
/// tracked the right hand within 5 cm in 74 % of frames and 14 px palms in 19 %; the
/// synthetic presets (palms 16 px on their working level) stay on target.
pub const MIN_PALM_PX: f64 = 16.0;
/// Least width of a palm in rays (rays of the finest grid across it). A hand's trajectory
/// needs its cluster, a hundred or so points, not a point per pixel; but the finest grid
/// keeps only rays wholly on skin, which erodes about one ray off every rim, and a small
/// cluster loses a larger share of its outline that way. Measured: palms 14 rays wide (the
/// shared real session's webcams, rays two pixels apart) tracked every object as well or
/// better than 28 rays did, at 1.8x the speed; palms 8 rays wide (the synthetic presets'
/// 640x480 rigs, rays two pixels apart) lost the hands at 6 fps and put heads 2.5 cm off
/// (BENCHMARKS.md). The bound lies between the two.
pub const MIN_PALM_RAYS: f64 = 12.0;
/// Coarsest working level (an eighth of the resolution).
pub const MAX_WORKING_LEVEL: usize = 3;
/// Distance to the signer assumed when the cameras' axes do not meet in front of the
/// reference camera (parallel cameras), metres: a seated signer before a desk rig.
pub const DEFAULT_SIGNER_DISTANCE_M: f64 = 1.5;

/// Where the rig's cameras look: the point nearest to every optical axis (least squares),
/// when it lies in front of the reference camera within [`STREAM_DEPTH_RANGE_M`]; its
/// distance from the reference camera, metres. `None` for a single camera or (nearly)
/// parallel axes.
pub fn rig_convergence_distance(cameras: &[Camera], reference: usize) -> Option<f64> {
    use nalgebra::Matrix3;
    if cameras.len() < 2 {
        return None;
    }
    let (mut a, mut b) = (Matrix3::zeros(), Vector3::zeros());
    for cam in cameras {
        let axis: Vector3<f64> = cam.rotation.inverse() * Vector3::z();
        let projector = Matrix3::identity() - axis * axis.transpose();
        a += projector;
        b += projector * cam.centre().coords;
    }
    // Parallel axes leave a direction unconstrained: a near-singular normal matrix.
    let eigen = a.symmetric_eigen();
    if eigen.eigenvalues.min() < 0.05 * cameras.len() as f64 {
        return None;
    }
    let point = a.try_inverse()? * b;
    let cam = cameras.get(reference)?;
    let depth = (cam.rotation * point + cam.translation).z;
    let (near, far) = STREAM_DEPTH_RANGE_M;
    (depth >= f64::from(near) && depth <= f64::from(far)).then(|| (point - cam.centre().coords).norm())
}

/// Expected width of a palm in the reference camera's full-resolution image, pixels: its
/// focal length times [`PALM_WIDTH_M`] over the distance to where the rig looks
/// ([`rig_convergence_distance`], else [`DEFAULT_SIGNER_DISTANCE_M`]).
pub fn expected_palm_px(cameras: &[Camera], reference: usize) -> f64 {
    let Some(cam) = cameras.get(reference) else { return 0.0 };
    let focal = 0.5 * (cam.matrix[(0, 0)] + cam.matrix[(1, 1)]);
    let distance = rig_convergence_distance(cameras, reference).unwrap_or(DEFAULT_SIGNER_DISTANCE_M);
    focal * PALM_WIDTH_M / distance
}

/// The working level for palms `palm_px` wide at full resolution: the coarsest level
/// (each halves the resolution) on which they are still [`MIN_PALM_PX`] wide, at most
/// [`MAX_WORKING_LEVEL`]. So a 1920x1080 rig costs what a 960x540 one does, and a
/// 640x480 one with the same field of view is estimated at full resolution.
pub fn working_level(palm_px: f64) -> usize {
    let mut level = 0;
    while level < MAX_WORKING_LEVEL && palm_px / f64::from(1u32 << (level + 1)) >= MIN_PALM_PX {
        level += 1;
    }
    level
}

/// Ray spacing on the working level `level` for palms `palm_px` wide at full resolution:
/// rays two pixels apart (1) when the palm is still [`MIN_PALM_RAYS`] rays wide with them,
/// else one per pixel (0). The images stay those of the working level: their detail is
/// what separates a hand from what lies behind it, while the rays are how many points the
/// clusters get. So a palm is 12 to 24 rays wide whatever the resolution (from 16 px up).
pub fn ray_subsampling(palm_px: f64, level: usize) -> usize {
    usize::from(palm_px / f64::from(1u32 << (level + 1)) >= MIN_PALM_RAYS)
}

/// One line for the log: the level the engine estimates on, its ray grid and why.
pub fn working_level_summary(config: &EngineConfig, cameras: &[Camera], reference: usize) -> String {
    let Some(cam) = cameras.get(reference) else { return String::from("no reference camera") };
    let scale = 1u32 << (config.finest_level + config.ray_subsampling);
    let distance = rig_convergence_distance(cameras, reference)
        .map_or(format!("{DEFAULT_SIGNER_DISTANCE_M} m (assumed)"), |d| format!("{d:.2} m (where the cameras look)"));
    let rays = match config.ray_subsampling {
        0 => String::new(),
        s => format!(", a ray every {} pixels of the level", 1u32 << s),
    };
    let second = match crate::engine::companion::second_reference_camera(cameras, reference) {
        Some(k) if config.second_reference => {
            format!("; where `{}` cannot see, rays from `{}`", cam.name, cameras[k].name)
        }
        _ => String::new(),
    };
    format!(
        "working level {} ({}x{} rays{rays} on `{}`): palms about {:.0} px wide at full resolution, signer at \
         {distance}{second}",
        config.finest_level,
        cam.width.div_ceil(scale),
        cam.height.div_ceil(scale),
        cam.name,
        expected_palm_px(cameras, reference),
    )
}

/// Frames between two reports of the cameras' skin shares when they change little: about
/// ten seconds at 30 fps (a steady scene needs no more; see [`SKIN_SHARE_REPORT_CHANGE`]).
pub const SKIN_SHARE_REPORT_EVERY: u64 = 300;
/// A change of any camera's skin share of at least this much (a share of the image) since
/// the last report is reported at once: a light switched on, a skin-coloured object
/// entering the view.
pub const SKIN_SHARE_REPORT_CHANGE: f32 = 0.05;
/// Face rounds remembered for [`FlowStream::faces_of_last_estimate`]: the estimate is one
/// frame behind the newest push, and a round can be applied on every frame.
const FACE_ROUNDS_KEPT: usize = 4;

/// The faces of one detection round, as the skin models were adapted with them.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct FaceRound {
    /// Push index (frame sets into the stream, from 0) of the frame set the faces were
    /// detected on.
    pub frame: u64,
    /// Per camera (rig order): what its own detector found, before fusion.
    pub detections: Vec<Vec<FaceBox>>,
    /// Per camera: the face its model was adapted with (own or lent by other views).
    pub fused: FusedFaces,
}

/// The face the last detection rounds placed in 3D, for the head track: where the head is,
/// whatever skin-coloured clutter the clusters find.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FaceCue {
    /// Centre of the face (the detector's box centres, triangulated), world metres.
    pub centre: [f64; 3],
    /// Physical width of the detector's box, metres.
    pub width_m: f64,
    /// Frame sets between the one the face was detected on and the estimate's.
    pub age_frames: u64,
}

/// Where a camera's face came from in a detection round.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FaceStatus {
    /// Its own detector found it and the other views confirmed it (or it was sure enough).
    Detected,
    /// Its detector missed it; the face the other views agreed on was projected into it.
    Lent,
    /// No face: its model kept its state.
    None,
}

impl FaceStatus {
    /// A word for logs and pictures.
    pub fn name(self) -> &'static str {
        match self {
            FaceStatus::Detected => "detected",
            FaceStatus::Lent => "lent",
            FaceStatus::None => "none",
        }
    }
}

impl FaceRound {
    /// Where camera `camera`'s face came from (`None` for an unknown camera too).
    pub fn status(&self, camera: usize) -> FaceStatus {
        match (self.fused.boxes.get(camera), self.fused.transferred.get(camera)) {
            (Some(Some(_)), Some(true)) => FaceStatus::Lent,
            (Some(Some(_)), _) => FaceStatus::Detected,
            _ => FaceStatus::None,
        }
    }
}

/// Share of camera `camera`'s pixels the engine counts as skin (skin ratio above the
/// configuration's `skin_threshold`) in the frame of the last estimate, counting every
/// `stride`-th pixel; `None` when the engine has no skin map for it.
pub fn skin_share(engine: &SceneFlowEngine, camera: usize, stride: usize) -> Option<f32> {
    Some(skin_share_of(engine.skin_map(camera)?, engine.config().skin_threshold, stride))
}

/// Models adapted in one round, with the faces they were adapted with.
type Adapted = Result<(Vec<SkinModel>, FaceRound), String>;

/// A detection round asked of the face worker: the push index and bytes of a frame set, its
/// missing views, and whether it is a warm-up round (the stream holds its frames for it).
struct FaceRequest {
    frame: u64,
    frame_set: Vec<u8>,
    missing: u32,
    warm_up: bool,
}

/// Face detection and skin adaptation on a thread of its own (the detector is not `Send`:
/// it lives and dies there). Frame sets go in (with their push index), adapted models come
/// out, one per frame set.
struct FaceWorker {
    frames: Option<Sender<FaceRequest>>,
    models: Receiver<Adapted>,
    /// Frame-set buffers the thread is done with, reused for the next rounds' copies: a
    /// fresh buffer per round (11 MB on four 1280x720 views) was faulted in page by page
    /// on the thread that feeds the engine, while the engine waited.
    spare: Receiver<Vec<u8>>,
    thread: Option<JoinHandle<()>>,
}

/// Nice value of the face-detection threads after the warm-up. Detections only adapt the
/// skin models, which a live stream applies whenever they are ready; at the default
/// priority a round (about 130 ms of one core for three cameras) took the cores from the
/// frame being estimated and set the live pipeline's p99 latency (BENCHMARKS.md). The
/// warm-up's rounds, which the stream holds its frames for (a joined stream's single round
/// too), run at the default priority: at this one, beside an engine and decoders that kept
/// both cores busy, a live stream's first round took 2 to 3 s.
const FACE_THREAD_NICE: i32 = 10;

/// Gives the calling thread the nice value [`FACE_THREAD_NICE`] (on Linux a thread's own
/// attribute; elsewhere it would be the whole process's, so nothing is done there).
fn lower_this_threads_priority() {
    #[cfg(target_os = "linux")]
    if let Err(e) = rustix::process::setpriority_process(None, FACE_THREAD_NICE) {
        tracing::debug!("face detection keeps the default priority: {e}");
    }
}

/// Threads of the face worker's pool: one per core, at most one per camera.
fn face_threads(cameras: usize) -> usize {
    std::thread::available_parallelism().map_or(1, |n| n.get()).min(cameras).max(1)
}

impl FaceWorker {
    fn new(cameras: &[Camera]) -> Self {
        let (frame_tx, frame_rx) = channel::<FaceRequest>();
        let (model_tx, model_rx) = channel();
        let (spare_tx, spare_rx) = channel();
        let cameras = cameras.to_vec();
        let thread = std::thread::Builder::new()
            .name("faces".into())
            .spawn(move || {
                // The views of a round are searched in parallel on threads as low in priority
                // as this one: a replay waiting for a round gets it from both cores, a live
                // stream's estimates still come first.
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(face_threads(cameras.len()))
                    .thread_name(|k| format!("faces-{k}"))
                    .build();
                let mut lowered = false;
                let mut adapter = match SkinAdapter::new(&cameras, DEFAULT_ADAPTATION_RATE, DEFAULT_DETECT_EVERY) {
                    Ok(a) => a,
                    Err(e) => {
                        let _ = model_tx.send(Err(e));
                        return;
                    }
                };
                for FaceRequest { frame, frame_set, missing, warm_up } in frame_rx {
                    // Lowered once, for good: a thread may lower its priority but not raise it.
                    if !warm_up && !lowered {
                        lower_this_threads_priority();
                        if let Ok(pool) = &pool {
                            pool.broadcast(|_| lower_this_threads_priority());
                        }
                        lowered = true;
                    }
                    let views = split_views(&cameras, &frame_set);
                    match &pool {
                        Ok(pool) => pool.install(|| adapter.adapt_now_partial(&views, missing)),
                        Err(_) => adapter.adapt_now_partial(&views, missing),
                    };
                    let round = FaceRound {
                        frame,
                        detections: adapter.last_detections().to_vec(),
                        fused: adapter.last_fused().clone(),
                    };
                    let _ = spare_tx.send(frame_set);
                    if model_tx.send(Ok((adapter.models().to_vec(), round))).is_err() {
                        return;
                    }
                }
            })
            .ok();
        Self { frames: Some(frame_tx), models: model_rx, spare: spare_rx, thread }
    }

    /// Starts a round on a copy of `frame_set` (frame `frame`); a `warm_up` round keeps the
    /// default priority (see [`FACE_THREAD_NICE`]).
    fn send(&self, frame: u64, frame_set: &[u8], missing: u32, warm_up: bool) -> Result<(), StreamError> {
        let mut copy = self.spare.try_recv().unwrap_or_default();
        copy.clear();
        copy.extend_from_slice(frame_set);
        let request = FaceRequest { frame, frame_set: copy, missing, warm_up };
        self.frames.as_ref().and_then(|tx| tx.send(request).ok()).ok_or(StreamError::FaceWorker)
    }

    /// The next models if they are ready.
    fn try_recv(&self) -> Result<Option<(Vec<SkinModel>, FaceRound)>, StreamError> {
        match self.models.try_recv() {
            Ok(Ok(models)) => Ok(Some(models)),
            Ok(Err(e)) => Err(StreamError::FaceDetector(e)),
            Err(std::sync::mpsc::TryRecvError::Empty) => Ok(None),
            Err(std::sync::mpsc::TryRecvError::Disconnected) => Err(StreamError::FaceWorker),
        }
    }

    fn recv(&self) -> Result<(Vec<SkinModel>, FaceRound), StreamError> {
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

/// What the stream hands out for each frame set, in the order the sets came.
#[derive(Clone, Copy)]
pub enum SetOutcome<'a> {
    /// The engine's estimate of the set, and the newest face the detection rounds applied
    /// by then placed in 3D.
    Estimated {
        /// The engine, holding the estimate.
        engine: &'a SceneFlowEngine,
        /// The face cue of [`FlowStream::face_cue_of_last_estimate`].
        face: Option<FaceCue>,
    },
    /// A set passed over ([`FlowStream::pass_over`]): no estimate.
    PassedOver,
}

/// A frame set held for the warm-up: its metadata and, unless it was passed over, its
/// bytes, missing views and grid index.
type HeldFrameSet<M> = (M, Option<(Vec<u8>, u32, Option<u64>)>);

/// A frame set awaiting its turn to be handed out: the push index of a set given to the
/// engine (`None`: passed over), and the caller's metadata.
type WaitingSet<M> = (Option<u64>, M);

/// The scene-flow engine over one stream of frame sets, each tagged with `M` (the caller's
/// frame metadata), handing every estimate out with the metadata of its frame.
pub struct FlowStream<M> {
    engine: SceneFlowEngine,
    faces: FaceWorker,
    frame_set_len: usize,
    /// Frames held until the warm-up rounds have their frames.
    held: Option<Vec<HeldFrameSet<M>>>,
    /// Frames pushed into the engine.
    pushed: u64,
    /// Frames at which the next adapted models are applied.
    pending_models: VecDeque<u64>,
    /// Sets not handed out yet, oldest first.
    waiting: VecDeque<WaitingSet<M>>,
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
    /// Push index of the first face detection (0; later for a stream joined part-way, whose
    /// first estimate should have both cores).
    detect_from: u64,
    /// Frames between a detection and the use of its models.
    model_lag: u64,
    /// Frames between the warm-up's detection rounds.
    warm_up_spacing: u64,
    /// The last face rounds applied, oldest first, each with the push index of the first
    /// frame whose skin maps its models made.
    face_rounds: VecDeque<(u64, FaceRound)>,
    /// Per camera, the face status last logged (`None` before the first round).
    faces_reported: Option<Vec<FaceStatus>>,
    /// Estimates handed out in this stream, and the estimate and skin shares last logged.
    estimates: u64,
    skin_reported: Option<(u64, Vec<f32>)>,
}

/// Frames the warm-up holds when its rounds are `spacing` frames apart.
fn warm_up_frames(spacing: u64) -> u64 {
    (WARM_UP_ROUNDS as u64 - 1) * spacing + 1
}

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
            warm_up_frames: warm_up_frames(DEFAULT_DETECT_EVERY),
            wait_for_models: true,
            waits_by_default: true,
            detect_every: DEFAULT_DETECT_EVERY,
            detect_from: 0,
            model_lag: MODEL_LAG,
            warm_up_spacing: DEFAULT_DETECT_EVERY,
            face_rounds: VecDeque::new(),
            faces_reported: None,
            estimates: 0,
            skin_reported: None,
        }
    }

    /// The faces of the detection round whose models made the skin maps of the last
    /// estimate's frame (`None` before the first round was applied).
    pub fn faces_of_last_estimate(&self) -> Option<&FaceRound> {
        let frame = self.engine.stats().frame;
        self.face_rounds.iter().rev().find(|(applied, _)| *applied <= frame).map(|(_, round)| round)
    }

    /// The newest face placed in 3D by the detection rounds applied up to the last
    /// estimate's frame (among the last few rounds), with its age in frame sets.
    pub fn face_cue_of_last_estimate(&self) -> Option<FaceCue> {
        let frame = self.engine.stats().frame;
        self.face_rounds.iter().rev().filter(|(applied, _)| *applied <= frame).find_map(|(_, round)| {
            round.fused.known.map(|known| FaceCue {
                centre: known.centre,
                width_m: known.width_m,
                age_frames: frame.saturating_sub(round.frame),
            })
        })
    }

    /// Times face detection for a stream at `fps` frames per second: every
    /// [`detect_every_for_rate`] frames, models used [`model_lag_for_rate`] frames later, and
    /// the warm-up's rounds as far apart (at 30 fps and above, the defaults). Call before
    /// the first push.
    pub fn with_frame_rate(mut self, fps: f64) -> Self {
        self.detect_every = detect_every_for_rate(fps);
        self.model_lag = model_lag_for_rate(fps);
        self.warm_up_spacing = self.detect_every;
        self.warm_up_frames = warm_up_frames(self.warm_up_spacing);
        self
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

    /// For a stream joined part-way through (a restarted stage, or a live run whose cameras
    /// started before this stage was ready): no warm-up backlog; the first frame set is held
    /// for one detection round (about a round's time, at the default priority), and
    /// estimates start two frames later, the first with
    /// [`JOIN_COLD_START_PASSES`] extra passes. The round is not left to run beside the
    /// estimates: the engine of a live stream that cannot keep up keeps both cores busy, and
    /// there the detector's low-priority threads took 2 to 3 s for a first round on four
    /// 1280x720 views at 30 fps, seconds of generic skin models in which a hand's track was
    /// swapped (BENCHMARKS.md). Later models are applied when ready.
    pub fn joining_mid_stream(&mut self) {
        // One frame held: one round (the warm-up's rounds are capped by the frames held).
        self.warm_up_frames = 1;
        self.wait_for_models = false;
        self.engine.set_next_cold_start_passes(JOIN_COLD_START_PASSES);
        // The next round starts after the first estimate instead of competing with it.
        self.detect_from = self.pushed + JOIN_FIRST_ESTIMATE_FRAMES;
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
    /// estimate it completes to `on_estimate` with its frame's metadata, and before it the
    /// sets passed over since the previous estimate. The handler's own error type passes
    /// through; the stream's errors convert into it.
    pub fn push<E: From<StreamError>>(
        &mut self,
        meta: M,
        frame_set: &[u8],
        on_estimate: impl FnMut(M, SetOutcome<'_>) -> Result<(), E>,
    ) -> Result<(), E> {
        self.push_partial(meta, frame_set, 0, on_estimate)
    }

    /// [`FlowStream::push`] for a set some cameras gave no view for (bit `k` of `missing`:
    /// camera `k`; its bytes are ignored): the engine leaves those views out, the face
    /// detector does not look at them and their skin models keep their state. A set without
    /// the reference camera's view is passed over ([`FlowStream::pass_over`]), with an error
    /// logged.
    pub fn push_partial<E: From<StreamError>>(
        &mut self,
        meta: M,
        frame_set: &[u8],
        missing: u32,
        on_estimate: impl FnMut(M, SetOutcome<'_>) -> Result<(), E>,
    ) -> Result<(), E> {
        self.push_indexed(meta, frame_set, missing, None, on_estimate)
    }

    /// [`FlowStream::push_partial`] for the frame set at `index` on the stream's frame grid
    /// (the capture sequence): sets lost before it (a live stage that fell behind) are
    /// spanned by the engine's constant-velocity model instead of being taken for one frame
    /// interval ([`SceneFlowEngine::push_frame_indexed`]).
    pub fn push_partial_at<E: From<StreamError>>(
        &mut self,
        meta: M,
        frame_set: &[u8],
        missing: u32,
        index: u64,
        on_estimate: impl FnMut(M, SetOutcome<'_>) -> Result<(), E>,
    ) -> Result<(), E> {
        self.push_indexed(meta, frame_set, missing, Some(index), on_estimate)
    }

    fn push_indexed<E: From<StreamError>>(
        &mut self,
        meta: M,
        frame_set: &[u8],
        missing: u32,
        index: Option<u64>,
        mut on_estimate: impl FnMut(M, SetOutcome<'_>) -> Result<(), E>,
    ) -> Result<(), E> {
        if frame_set.len() != self.frame_set_len {
            return Err(StreamError::FrameSetLength { expected: self.frame_set_len, got: frame_set.len() }.into());
        }
        let reference = self.engine.reference();
        if 1u32.checked_shl(reference as u32).is_some_and(|bit| missing & bit != 0) {
            // Every ray starts in the reference view (a webcam that dropped its frame).
            tracing::error!(
                "{}: the reference camera `{}` has no frame in it; its trajectories are the tracks' predictions",
                index.map_or_else(|| "a frame set".to_string(), |i| format!("frame set {i}")),
                self.engine.cameras()[reference].name
            );
            return self.pass_over(meta, on_estimate);
        }
        if let Some(held) = self.held.as_mut() {
            // Copies only the first frames of a stream, once.
            held.push((meta, Some((frame_set.to_vec(), missing, index))));
            if held.iter().filter(|(_, set)| set.is_some()).count() as u64 >= self.warm_up_frames {
                self.release_held(&mut on_estimate)?;
            }
            return Ok(());
        }
        self.push_now(meta, frame_set, missing, index, &mut on_estimate)
    }

    /// Passes over the next frame set: one the engine cannot estimate (it lacks the reference
    /// camera's view, which every ray starts from). It is handed out as
    /// [`SetOutcome::PassedOver`] in its place among the estimates, so the caller's records
    /// stay in order (clustering coasts its tracks there); with the sets pushed at their grid
    /// index ([`FlowStream::push_partial_at`]) the engine spans it as a gap.
    pub fn pass_over<E: From<StreamError>>(
        &mut self,
        meta: M,
        mut on_estimate: impl FnMut(M, SetOutcome<'_>) -> Result<(), E>,
    ) -> Result<(), E> {
        if let Some(held) = self.held.as_mut() {
            held.push((meta, None));
        } else if self.waiting.is_empty() {
            // Nothing before it awaits an estimate.
            on_estimate(meta, SetOutcome::PassedOver)?;
        } else {
            self.waiting.push_back((None, meta));
        }
        Ok(())
    }

    /// Ends the stream: estimates what is left (the last frame with the two-frame
    /// likelihood) and makes the stream ready for a new, unrelated one.
    pub fn finish<E: From<StreamError>>(
        &mut self,
        mut on_estimate: impl FnMut(M, SetOutcome<'_>) -> Result<(), E>,
    ) -> Result<(), E> {
        if self.held.as_ref().is_some_and(|h| !h.is_empty()) {
            self.release_held(&mut on_estimate)?;
        }
        if self.engine.flush().is_some() {
            self.hand_out(&mut on_estimate)?;
        }
        // Sets passed over after the last estimate; sets the engine never estimated have
        // nothing to hand out.
        for (pushed, meta) in std::mem::take(&mut self.waiting) {
            if pushed.is_none() {
                on_estimate(meta, SetOutcome::PassedOver)?;
            }
        }
        // Rounds whose models were not due yet: taken now, so the next stream does not get them.
        for _ in self.pending_models.drain(..) {
            self.faces.recv()?;
        }
        self.engine.reset();
        self.held = Some(Vec::new());
        self.warm_up_frames = warm_up_frames(self.warm_up_spacing);
        self.wait_for_models = self.waits_by_default;
        self.pushed = 0;
        self.detect_from = 0;
        self.pending_models.clear();
        self.waiting.clear();
        self.face_rounds.clear();
        self.faces_reported = None;
        self.estimates = 0;
        self.skin_reported = None;
        Ok(())
    }

    /// Applies adapted models from the next frame pushed on, remembers their faces and logs
    /// the cameras whose face status changed.
    fn apply_models(&mut self, models: &[SkinModel], round: FaceRound) -> Result<(), StreamError> {
        self.engine.set_skin_models(models)?;
        let statuses: Vec<FaceStatus> = (0..self.engine.cameras().len()).map(|c| round.status(c)).collect();
        for (c, (cam, status)) in self.engine.cameras().iter().zip(&statuses).enumerate() {
            let before = self.faces_reported.as_ref().and_then(|r| r.get(c).copied());
            if before == Some(*status) {
                continue;
            }
            let own = round.detections.get(c).map_or(0, Vec::len);
            match status {
                FaceStatus::Detected => {
                    tracing::info!("camera `{}`: face found by its own detector (frame set {})", cam.name, round.frame)
                }
                FaceStatus::Lent => tracing::info!(
                    "camera `{}`: face lent by the other views (own detections: {own}; frame set {})",
                    cam.name,
                    round.frame
                ),
                FaceStatus::None if before.is_none() => tracing::info!(
                    "camera `{}`: no face (own detections: {own}, none confirmed; frame set {})",
                    cam.name,
                    round.frame
                ),
                FaceStatus::None => tracing::info!(
                    "camera `{}`: face lost (own detections: {own}, none confirmed; frame set {}); its skin model \
                     keeps its state",
                    cam.name,
                    round.frame
                ),
            }
        }
        self.faces_reported = Some(statuses);
        if self.face_rounds.len() == FACE_ROUNDS_KEPT {
            self.face_rounds.pop_front();
        }
        self.face_rounds.push_back((self.pushed, round));
        Ok(())
    }

    /// Logs every camera's skin share at the first estimate, then when one changed by
    /// [`SKIN_SHARE_REPORT_CHANGE`] or every [`SKIN_SHARE_REPORT_EVERY`] estimates.
    fn report_skin_shares(&mut self) {
        let engine = &self.engine;
        let shares: Vec<f32> =
            (0..engine.cameras().len()).map(|c| skin_share(engine, c, SKIN_SHARE_STRIDE).unwrap_or(0.0)).collect();
        let due = match &self.skin_reported {
            None => true,
            Some((at, last)) => {
                self.estimates >= at + SKIN_SHARE_REPORT_EVERY
                    || last.iter().zip(&shares).any(|(a, b)| (a - b).abs() >= SKIN_SHARE_REPORT_CHANGE)
            }
        };
        if !due {
            return;
        }
        let listed: Vec<String> = engine
            .cameras()
            .iter()
            .zip(&shares)
            .map(|(cam, share)| format!("`{}` {:.1} %", cam.name, 100.0 * share))
            .collect();
        tracing::info!("skin share of the image at frame set {}: {}", engine.stats().frame, listed.join(", "));
        self.skin_reported = Some((self.estimates, shares));
    }

    /// Runs the warm-up on the held frames, then pushes them.
    fn release_held<E: From<StreamError>>(
        &mut self,
        on_estimate: &mut impl FnMut(M, SetOutcome<'_>) -> Result<(), E>,
    ) -> Result<(), E> {
        let held = self.held.take().unwrap_or_default();
        let sets: Vec<(&[u8], u32)> = held
            .iter()
            .filter_map(|(_, set)| set.as_ref().map(|(bytes, missing, _)| (bytes.as_slice(), *missing)))
            .collect();
        let rounds = WARM_UP_ROUNDS.min(sets.len());
        for k in 0..rounds {
            let index = (k as u64 * self.warm_up_spacing) as usize % sets.len();
            self.faces.send(index as u64, sets[index].0, sets[index].1, true)?;
            let (models, round) = self.faces.recv()?;
            self.apply_models(&models, round)?;
        }
        // A live stream skips the stale sets, and the sets passed over before the first it keeps.
        let mut skip = self.backlog_limit.map_or(0, |keep| sets.len().saturating_sub(keep));
        let stale = skip > 0;
        let mut kept = false;
        for (meta, set) in held {
            match set {
                Some(_) if skip > 0 => skip -= 1,
                Some((frame_set, missing, index)) => {
                    kept = true;
                    self.push_now(meta, &frame_set, missing, index, on_estimate)?;
                }
                None if stale && !kept => {}
                None => self.pass_over(meta, &mut *on_estimate)?,
            }
        }
        Ok(())
    }

    fn push_now<E: From<StreamError>>(
        &mut self,
        meta: M,
        frame_set: &[u8],
        missing: u32,
        index: Option<u64>,
        on_estimate: &mut impl FnMut(M, SetOutcome<'_>) -> Result<(), E>,
    ) -> Result<(), E> {
        let k = self.pushed;
        let detect = k >= self.detect_from && (k - self.detect_from).is_multiple_of(self.detect_every);
        if detect && (self.wait_for_models || self.pending_models.is_empty()) {
            self.faces.send(k, frame_set, missing, false)?;
            self.pending_models.push_back(k + self.model_lag);
        }
        if self.pending_models.front().is_some_and(|&due| due <= k) {
            let models = if self.wait_for_models { Some(self.faces.recv()?) } else { self.faces.try_recv()? };
            if let Some((models, round)) = models {
                self.pending_models.pop_front();
                self.apply_models(&models, round)?;
            }
        }
        let views = split_views(self.engine.cameras(), frame_set);
        self.waiting.push_back((Some(k), meta));
        self.pushed += 1;
        let pushed = match index {
            Some(index) => self.engine.push_frame_indexed(&views, missing, index),
            None => self.engine.push_frame_partial(&views, missing),
        };
        if pushed.map_err(StreamError::from)?.is_some() {
            self.hand_out(on_estimate)?;
        }
        Ok(())
    }

    /// Hands the engine's last estimate out with its frame's metadata, after the sets passed
    /// over before it; frames before it never get one (the first frame of a
    /// forwards/backwards stream whose engine does not estimate it).
    fn hand_out<E: From<StreamError>>(
        &mut self,
        on_estimate: &mut impl FnMut(M, SetOutcome<'_>) -> Result<(), E>,
    ) -> Result<(), E> {
        let frame = self.engine.stats().frame;
        self.report_skin_shares();
        self.estimates += 1;
        let face = self.face_cue_of_last_estimate();
        while let Some((pushed, meta)) = self.waiting.pop_front() {
            match pushed {
                None => on_estimate(meta, SetOutcome::PassedOver)?,
                Some(k) if k == frame => {
                    return on_estimate(meta, SetOutcome::Estimated { engine: &self.engine, face })
                }
                Some(_) => {}
            }
        }
        Ok(())
    }
}

/// The particles of the engine's last estimate, as what clustering needs: every particle
/// of every ray with confidence, its weight times the ray's confidence, and the skin
/// probability of the ray's pixel. Then those of the second reference's engine, if any,
/// that the reference camera cannot see.
pub fn scene_points(engine: &SceneFlowEngine) -> impl Iterator<Item = ScenePoint> + '_ {
    let unseen = engine.companion().into_iter().flat_map(move |companion| unseen_points(engine, companion));
    reference_points(engine, engine).chain(unseen)
}

/// The points of `engine`'s companion that `engine`'s reference camera cannot see.
fn unseen_points<'a>(
    engine: &'a SceneFlowEngine,
    companion: &'a SceneFlowEngine,
) -> impl Iterator<Item = ScenePoint> + 'a {
    reference_points(companion, engine).filter(move |p| !engine.reference_sees(p.position))
}

/// [`scene_points`] of one engine, the skin read from `images` (the engine whose frames it
/// estimated on).
fn reference_points<'a>(
    engine: &'a SceneFlowEngine,
    images: &'a SceneFlowEngine,
) -> impl Iterator<Item = ScenePoint> + 'a {
    let field = engine.field();
    let reference = engine.reference();
    let cam = &engine.cameras()[reference];
    let scale = cam.width as usize / field.width.max(1);
    (0..field.width * field.height).filter(move |&ray| field.confidence[ray] > 0.0).flat_map(move |ray| {
        let confidence = field.confidence[ray];
        let (x, y) = ((ray % field.width) * scale + scale / 2, (ray / field.width) * scale + scale / 2);
        // The clamped log10 ratio of skin to background likelihood, as a probability.
        let skin = images.skin_at(reference, x, y).map_or(0.0, |r| 1.0 / (1.0 + 10f32.powf(-r)));
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
    let own: usize = (0..field.width * field.height)
        .filter(|&ray| field.confidence[ray] > 0.0)
        .map(|ray| engine.ray_particles(ray).len())
        .sum();
    // The companion's points are kept by where they lie: counted by the same filter.
    own + engine.companion().map_or(0, |c| unseen_points(engine, c).count())
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_face_rounds_status_says_where_each_cameras_face_came_from() {
        let face = FaceBox { x: 10.0, y: 10.0, width: 50.0, height: 60.0, score: 7.0 };
        let round = FaceRound {
            frame: 20,
            detections: vec![vec![face], vec![], vec![face]],
            fused: FusedFaces {
                boxes: vec![Some(face), Some(face), None],
                transferred: vec![false, true, false],
                rejected: 1,
                known: None,
            },
        };
        assert_eq!(round.status(0), FaceStatus::Detected);
        assert_eq!(round.status(1), FaceStatus::Lent);
        assert_eq!(round.status(2), FaceStatus::None, "camera 2's own detection was rejected");
        assert_eq!(round.status(9), FaceStatus::None, "an unknown camera has no face");
        assert_eq!(FaceRound::default().status(0), FaceStatus::None);
    }

    /// Cameras `radius` m from the origin at these angles about the vertical (Y up),
    /// looking at it, `width` x `height` pixels with `fov_deg` across the width.
    fn arc(radius: f64, angles_deg: &[f64], width: u32, height: u32, fov_deg: f64) -> Vec<Camera> {
        use nalgebra::{Matrix3, Rotation3};
        let f = 0.5 * f64::from(width) / (0.5 * fov_deg.to_radians()).tan();
        let k = Matrix3::new(f, 0.0, f64::from(width) / 2.0, 0.0, f, f64::from(height) / 2.0, 0.0, 0.0, 1.0);
        angles_deg
            .iter()
            .enumerate()
            .map(|(i, a)| {
                let position = Vector3::new(radius * a.to_radians().sin(), 0.1, radius * a.to_radians().cos());
                let z = (-position).normalize();
                let x = z.cross(&-Vector3::y()).normalize();
                let y = z.cross(&x);
                let r = Rotation3::from_matrix_unchecked(Matrix3::from_rows(&[
                    x.transpose(),
                    y.transpose(),
                    z.transpose(),
                ]));
                let t = -(r * position);
                Camera::new(format!("cam{i}"), width, height, k, handflow_protocol::Distortion::default(), r, t)
                    .expect("valid camera")
            })
            .collect()
    }

    #[test]
    fn the_working_level_keeps_a_palm_sixteen_pixels_wide() {
        assert_eq!(working_level(10.0), 0);
        assert_eq!(working_level(31.9), 0);
        assert_eq!(working_level(32.0), 1);
        assert_eq!(working_level(57.0), 1, "the shared real session's webcams");
        assert_eq!(working_level(64.0), 2);
        assert_eq!(working_level(5000.0), MAX_WORKING_LEVEL);
        assert_eq!(working_level(f64::NAN), 0);
    }

    #[test]
    fn rays_are_two_pixels_apart_only_where_a_palm_stays_twelve_rays_wide() {
        // The shared real session's webcams: 28 px palms on level 1, 14 rays two pixels apart.
        assert_eq!(ray_subsampling(57.0, working_level(57.0)), 1);
        // 640x480 rigs: 16 px palms on level 1 would be 8 rays wide.
        assert_eq!(ray_subsampling(32.4, working_level(32.4)), 0);
        assert_eq!(ray_subsampling(47.9, working_level(47.9)), 0);
        assert_eq!(ray_subsampling(48.0, working_level(48.0)), 1);
        // Palms 16 px wide on level 2: one ray per pixel again.
        assert_eq!(ray_subsampling(64.0, working_level(64.0)), 0);
        assert_eq!(ray_subsampling(f64::NAN, 0), 0);
        // Every palm from 16 px up gets between 12 and 24 rays (below 16 px, one per pixel).
        for palm in (16..2000).map(f64::from) {
            let level = working_level(palm);
            let rays = palm / f64::from(1u32 << (level + ray_subsampling(palm, level)));
            assert!((MIN_PALM_RAYS..24.0).contains(&rays) || level == MAX_WORKING_LEVEL, "{palm} px: {rays} rays");
        }
    }

    #[test]
    fn the_working_level_follows_image_size_and_distance() {
        let level = |cams: &[Camera]| working_level(expected_palm_px(cams, 1));
        // Where three cameras on a 1.8 m arc look: the signer at the arc's centre.
        let cams = arc(1.8, &[-35.0, 0.0, 35.0], 640, 480, 50.0);
        let d = rig_convergence_distance(&cams, 1).expect("axes meet");
        assert!((d - 1.8).abs() < 0.01, "{d}");
        // 640x480 at 50 degrees: a palm 32 px wide, estimated at half resolution.
        assert!((expected_palm_px(&cams, 1) - 32.4).abs() < 0.2);
        assert_eq!(level(&cams), 1);
        // The same rig at 1920x1080 costs what 480x270 would; a portrait 1080x1920 camera
        // sees the same palm as a 1080-wide one; 320x240 keeps every pixel.
        assert_eq!(level(&arc(1.8, &[-35.0, 0.0, 35.0], 1920, 1080, 50.0)), 2);
        assert_eq!(level(&arc(1.8, &[-35.0, 0.0, 35.0], 1080, 1920, 50.0)), 1);
        assert_eq!(level(&arc(1.8, &[-35.0, 0.0, 35.0], 320, 240, 50.0)), 0);
        // Nearer cameras see bigger hands.
        assert_eq!(level(&arc(0.9, &[-35.0, 0.0, 35.0], 640, 480, 50.0)), 2);
        // Parallel cameras do not say where the signer is: the default distance.
        let mut parallel = arc(1.8, &[0.0, 0.0], 640, 480, 50.0);
        parallel[1].translation.x += 0.3;
        assert_eq!(rig_convergence_distance(&parallel, 1), None);
        let expected = parallel[1].matrix[(0, 0)] * PALM_WIDTH_M / DEFAULT_SIGNER_DISTANCE_M;
        assert!((expected_palm_px(&parallel, 1) - expected).abs() < 1e-9);
        assert_eq!(rig_convergence_distance(&cams[..1], 0), None, "one camera");
    }

    #[test]
    fn warm_coarse_loops_follow_how_far_the_prediction_can_miss_at_the_frame_rate() {
        // 28 cm at 6 fps, 16 cm at 8: the search runs in full.
        assert_eq!(warm_coarse_extra_loops_for_rate(6.0), 2);
        assert_eq!(warm_coarse_extra_loops_for_rate(8.0), 2);
        // 10 cm at 10 fps, 4.4 cm at 15: one loop.
        assert_eq!(warm_coarse_extra_loops_for_rate(10.0), 1);
        assert_eq!(warm_coarse_extra_loops_for_rate(15.0), 1);
        // 1.1 cm at 30 fps, 0.3 cm at 60: the carried posterior stays on the hand.
        assert_eq!(warm_coarse_extra_loops_for_rate(30.0), 0);
        assert_eq!(warm_coarse_extra_loops_for_rate(60.0), 0);
        // Never more at a lower rate, and an unknown rate searches in full.
        let rates = [1.0, 3.0, 6.0, 7.5, 10.0, 12.0, 15.0, 20.0, 24.0, 30.0, 60.0, 120.0];
        for pair in rates.windows(2) {
            assert!(warm_coarse_extra_loops_for_rate(pair[0]) >= warm_coarse_extra_loops_for_rate(pair[1]));
        }
        for bad in [0.0, -5.0, f64::NAN, f64::INFINITY] {
            assert_eq!(warm_coarse_extra_loops_for_rate(bad), MAX_WARM_COARSE_EXTRA_LOOPS);
        }
        let cams = arc(1.8, &[-35.0, 0.0, 35.0], 640, 480, 50.0);
        assert_eq!(stream_engine_config(Variant::Handflow, None, 30.0, &cams, 1).warm_coarse_extra_loops, Some(0));
        assert_eq!(stream_engine_config(Variant::Handflow, None, 6.0, &cams, 1).warm_coarse_extra_loops, Some(2));
        // Live, estimates can be frames apart: the full search at any rate.
        assert_eq!(live_stream_engine_config(Variant::Handflow, 30.0, &cams, 1).warm_coarse_extra_loops, Some(2));
        // Live, the first estimates come out after a few frames' work, not 26.
        assert_eq!(live_stream_engine_config(Variant::Handflow, 30.0, &cams, 1).cold_start_passes, 2);
        assert_eq!(stream_engine_config(Variant::Handflow, None, 30.0, &cams, 1).cold_start_passes, 8);
    }

    #[test]
    fn the_stream_configuration_estimates_on_the_working_level() {
        let cams = arc(1.8, &[-35.0, 0.0, 35.0], 1920, 1080, 50.0);
        let config = stream_engine_config(Variant::Handflow, None, 30.0, &cams, 1);
        // Palms 97 px wide: 24 px on level 2, 12 rays two pixels apart.
        assert_eq!((config.finest_level, config.pyramid_levels, config.ray_subsampling), (2, 5, 1));
        config.validate().expect("valid");
        // 1280x720 webcams at 1.5 m: palms 28 px on level 1, rays two pixels apart.
        let config =
            stream_engine_config(Variant::Handflow, None, 6.0, &arc(1.5, &[-30.0, 0.0, 30.0], 1280, 720, 70.0), 1);
        assert_eq!((config.finest_level, config.pyramid_levels, config.ray_subsampling), (1, 4, 1));
        config.validate().expect("valid");
        let config = stream_engine_config(Variant::Handflow, None, 30.0, &arc(1.8, &[0.0, 30.0], 320, 240, 50.0), 0);
        assert_eq!((config.finest_level, config.pyramid_levels), (0, 2));
        config.validate().expect("valid");
    }

    #[test]
    fn the_coarsest_level_has_sparser_rays_than_the_finest_at_every_resolution() {
        for width in (320..=3840).step_by(160) {
            for fov in [40.0, 60.0, 90.0] {
                let cams = arc(1.2, &[-30.0, 0.0, 30.0], width, width * 9 / 16, fov);
                let config = stream_engine_config(Variant::Handflow, None, 30.0, &cams, 1);
                config.validate().expect("valid");
                let finest_rays = config.finest_level + config.ray_subsampling;
                assert_eq!(
                    config.pyramid_levels,
                    finest_rays + 2,
                    "{width} px wide, {fov} degrees: the top level one ray grid coarser than the finest"
                );
                // A palm still spans two 3x3 windows on the coarsest level's grid.
                let top = config.pyramid_levels - 1;
                let palm_top = expected_palm_px(&cams, 1) / f64::from(1u32 << top);
                assert!(
                    palm_top >= 0.5 * MIN_PALM_RAYS || config.ray_subsampling == 0,
                    "{width} px, {fov} deg: {palm_top}"
                );
            }
        }
    }
}
