//! The scene-flow engine on a recording: the configuration trajectories use (skin coverage,
//! forwards/backwards likelihood), and `handflow bench flow --recording`, which measures its
//! speed and, when the recording has object masks, whether its 3D points land on the same
//! object in the other views.

use std::path::Path;
use std::time::Instant;

use anyhow::{Context, Result};
use handflow_flow::skin::adapt::{SkinAdapter, DEFAULT_ADAPTATION_RATE, DEFAULT_DETECT_EVERY};
use handflow_flow::stream::{stream_engine_config, STREAM_DEPTH_RANGE_M, STREAM_SPEED_BOUND_M_S, WARM_UP_ROUNDS};
use handflow_flow::{DenseField, EngineConfig, SceneFlowEngine, Temporal, Variant};
use handflow_ingest::synthetic::MASKS_DIR;
use handflow_ingest::Recording;
use handflow_protocol::Camera;

use crate::engine_overrides::apply_overrides;

/// The rig the tracker runs on: the recording's, with the user's up if given, else with the
/// up the faces give where they overrule the cameras' estimate ([`tracking_up`]), exactly as
/// the streaming stages receive it (through the rig message's TOML, which writes rotations as
/// Rodrigues vectors), so that `handflow track` and `handflow run` compute on the same numbers
/// and write the same bytes.
pub fn tracking_rig(rec: &Recording, up: Option<[f64; 3]>) -> Result<handflow_protocol::Rig> {
    let mut rig = rec.rig().clone();
    if let Some(up) = tracking_up(rec, up)? {
        rig.set_up(nalgebra::Vector3::from(up))?;
    }
    Ok(handflow_protocol::Rig::from_toml_str(&rig.to_toml_string())?)
}

/// The up to declare for tracking a recording: the user's (`up`), else the faces' where the
/// rig states none and they overrule the cameras' estimate ([`crate::face_up::face_up`],
/// logged); `None` leaves the rig's own. `handflow run` passes it to the ingest service as
/// `--up`, so a replay tracks on the rig `track` does.
pub fn tracking_up(rec: &Recording, up: Option<[f64; 3]>) -> Result<Option<[f64; 3]>> {
    if up.is_some() {
        return Ok(up);
    }
    Ok(crate::face_up::face_up(rec, rec.rig())?.map(|found| {
        tracing::warn!("{}", found.summary());
        [found.direction.x, found.direction.y, found.direction.z]
    }))
}

/// The flow stream's face for the cluster stage, as the particle header carries it between
/// the services (`fps` turns its age into seconds).
pub fn cluster_face_cue(
    face: Option<handflow_flow::stream::FaceCue>,
    fps: f64,
) -> Option<handflow_cluster::stage::FaceCue> {
    face.map(|f| handflow_cluster::stage::FaceCue::new(f.centre, f.age_frames, fps))
}

/// The engine configuration for trajectories on a recording: the stream configuration
/// ([`stream_engine_config`], where each choice is explained) at the recording's frame
/// rate and for its cameras (`reference` is the engine's), then the overrides
/// (`field=value`).
pub fn recording_engine_config(
    variant: Variant,
    particles_per_ray: Option<usize>,
    fps: f64,
    cameras: &[Camera],
    reference: usize,
    overrides: &[String],
) -> Result<EngineConfig> {
    let config = apply_overrides(stream_engine_config(variant, particles_per_ray, fps, cameras, reference), overrides)?;
    config.validate().map_err(anyhow::Error::msg)?;
    tracing::info!("{}", handflow_flow::stream::working_level_summary(&config, cameras, reference));
    Ok(config)
}

/// What `handflow bench flow --recording` measured.
#[derive(Clone, Debug, serde::Serialize)]
pub struct RecordingFlowReport {
    /// The recording's folder.
    pub recording: String,
    /// Cameras and their size.
    pub cameras: usize,
    /// Image width (reference camera).
    pub width: u32,
    /// Image height (reference camera).
    pub height: u32,
    /// Reference camera's name.
    pub reference: String,
    /// Estimates made.
    pub frames: usize,
    /// Estimates per second of engine time (pyramids, skin maps and the filter).
    pub frames_per_second: f64,
    /// Mean engine time per estimate, seconds.
    pub seconds_per_frame: f64,
    /// Slowest estimate after the first, seconds.
    pub seconds_per_frame_max: f64,
    /// Mean share of the reference camera's rays holding particles.
    pub occupied_share: f64,
    /// Mean likelihood evaluations per estimate.
    pub evaluations_per_frame: f64,
    /// PNG decoding per frame set, seconds (ingest's work, not counted above).
    pub decode_seconds_per_frame: f64,
    /// Face detection and adaptation per round, seconds (off the hot path, not counted).
    pub face_detection_seconds_per_round: f64,
    /// Share of estimated rays on a skin-coloured object whose 3D point projects onto the
    /// same object in every other view where it lands inside the image (needs masks).
    pub mask_agreement: Option<f64>,
    /// Share of estimated rays whose reference pixel is on head or hands (needs masks).
    pub on_skin_objects: Option<f64>,
    /// Dense coverage at full resolution (every ray, the Middlebury configuration) on the
    /// first frames of the same recording, seconds per estimate: the baseline of this run.
    pub dense_seconds_per_frame: Option<f64>,
    /// `dense_seconds_per_frame / seconds_per_frame`.
    pub speedup_vs_dense: Option<f64>,
    /// The engine configuration's skin weight.
    pub skin_weight: f32,
    /// Engine worker threads.
    pub threads: usize,
}

/// Runs the engine over a recording (all frames, or the first `max_frames`).
pub fn bench_recording(
    dir: &Path,
    variant: Variant,
    particles_per_ray: Option<usize>,
    overrides: &[String],
    max_frames: Option<usize>,
    baseline: bool,
) -> Result<RecordingFlowReport> {
    let rec = Recording::open(dir)?;
    let rig = rec.rig().clone();
    let reference = rig.most_frontal_camera();
    let config =
        recording_engine_config(variant, particles_per_ray, rec.frame_rate(), &rig.cameras, reference, overrides)?;
    let skin_weight = config.skin_weight;
    let mut engine = SceneFlowEngine::new(config, rig.cameras.clone(), reference)?;
    let frames = max_frames.unwrap_or(rec.len()).min(rec.len());
    anyhow::ensure!(frames >= 2, "recording `{}` needs at least 2 frames, has {frames}", dir.display());
    let mut adapter =
        SkinAdapter::new(&rig.cameras, DEFAULT_ADAPTATION_RATE, DEFAULT_DETECT_EVERY).map_err(anyhow::Error::msg)?;
    let mut buf = vec![0u8; rec.frame_set_len()];
    // Adapt before the first estimate, as a running service would have by then.
    for k in 0..WARM_UP_ROUNDS.min(frames) {
        rec.read_frame_into((k as u64) * DEFAULT_DETECT_EVERY % rec.len() as u64, false, &mut buf)?;
        adapter.adapt_now(&rec.views(&buf));
    }
    engine.set_skin_models(adapter.models())?;
    let masks = MaskReader::new(&rec);
    let (mut decode, mut times, mut occupied, mut evaluations) = (0.0, Vec::new(), 0usize, 0u64);
    let mut agreement = AgreementCounts::default();
    for k in 0..frames {
        let started = Instant::now();
        let missing = rec.read_frame_into(k as u64, false, &mut buf)?.missing_views;
        decode += started.elapsed().as_secs_f64();
        if missing & (1 << reference) != 0 {
            tracing::error!("frame set {k} skipped: the reference camera has no frame in it");
            continue;
        }
        let views = rec.views(&buf);
        if adapter.observe(k as u64, &views) {
            engine.set_skin_models(adapter.models())?;
        }
        let done = engine.push_frame_partial(&views, missing).with_context(|| format!("frame {k}"))?.is_some();
        if done {
            let stats = engine.stats();
            times.push(stats.seconds);
            occupied += stats.occupied_rays;
            evaluations += stats.evaluations;
            if let Some(m) = &masks {
                agreement.add(m, &rig.cameras, reference, stats.frame as usize, engine.field())?;
            }
        }
    }
    if engine.flush().is_some() {
        let stats = engine.stats();
        times.push(stats.seconds);
        occupied += stats.occupied_rays;
        evaluations += stats.evaluations;
        if let Some(m) = &masks {
            agreement.add(m, &rig.cameras, reference, stats.frame as usize, engine.field())?;
        }
    }
    let n = times.len().max(1) as f64;
    let total: f64 = times.iter().sum();
    let dense = if baseline { Some(dense_seconds_per_frame(&rec, reference, &mut buf)?) } else { None };
    let stats = adapter.stats();
    let cam = &rig.cameras[reference];
    Ok(RecordingFlowReport {
        recording: dir.display().to_string(),
        cameras: rig.cameras.len(),
        width: cam.width,
        height: cam.height,
        reference: cam.name.clone(),
        frames: times.len(),
        frames_per_second: n / total.max(1e-9),
        seconds_per_frame: total / n,
        seconds_per_frame_max: times.iter().skip(1).copied().fold(0.0, f64::max),
        occupied_share: occupied as f64 / n / (engine.field().width * engine.field().height) as f64,
        evaluations_per_frame: evaluations as f64 / n,
        decode_seconds_per_frame: decode / frames as f64,
        face_detection_seconds_per_round: stats.seconds / stats.rounds.max(1) as f64,
        mask_agreement: masks.as_ref().map(|_| agreement.agreement()),
        on_skin_objects: masks.as_ref().map(|_| agreement.on_skin()),
        dense_seconds_per_frame: dense,
        speedup_vs_dense: dense.map(|d| d / (total / n)),
        skin_weight,
        threads: rayon::current_num_threads(),
    })
}

/// Frames of the dense baseline: two estimates with forwards/backwards.
const BASELINE_FRAMES: usize = 3;

/// Seconds per estimate of the default dense engine (full resolution, every ray,
/// forwards/backwards) on the first frames of the recording.
fn dense_seconds_per_frame(rec: &Recording, reference: usize, buf: &mut [u8]) -> Result<f64> {
    let config = EngineConfig {
        temporal: Temporal::ForwardsBackwards,
        depth_range: STREAM_DEPTH_RANGE_M,
        speed_bound: STREAM_SPEED_BOUND_M_S / rec.frame_rate().max(1.0) as f32,
        ..EngineConfig::default()
    };
    let mut engine = SceneFlowEngine::new(config, rec.rig().cameras.clone(), reference)?;
    let mut times = Vec::new();
    for k in 0..BASELINE_FRAMES.min(rec.len()) {
        rec.read_frame_into(k as u64, false, buf)?;
        if engine.push_frame(&rec.views(buf))?.is_some() {
            times.push(engine.stats().seconds);
        }
    }
    if engine.flush().is_some() {
        times.push(engine.stats().seconds);
    }
    Ok(times.iter().sum::<f64>() / times.len().max(1) as f64)
}

/// Object-id masks of a rendered recording (`masks/<camera>/<image name>`).
struct MaskReader<'a> {
    rec: &'a Recording,
}

impl<'a> MaskReader<'a> {
    fn new(rec: &'a Recording) -> Option<Self> {
        rec.dir().join(MASKS_DIR).is_dir().then_some(Self { rec })
    }

    fn read(&self, frame: usize, camera: usize) -> Result<image::GrayImage> {
        let entry = &self.rec.frames()[frame];
        let cam = &self.rec.rig().cameras[camera];
        let name = self
            .rec
            .image_path(frame, camera)
            .and_then(Path::file_name)
            .context("masks belong to image-folder recordings")?;
        let path = self.rec.dir().join(MASKS_DIR).join(&cam.name).join(name);
        let mask = image::open(&path)
            .with_context(|| format!("camera `{}`, frame {}: mask `{}`", cam.name, entry.frame, path.display()))?
            .into_luma8();
        anyhow::ensure!(
            mask.width() == cam.width && mask.height() == cam.height,
            "camera `{}`, frame {}: mask `{}` is {}x{}, the camera {}x{}",
            cam.name,
            entry.frame,
            path.display(),
            mask.width(),
            mask.height(),
            cam.width,
            cam.height
        );
        Ok(mask)
    }
}

/// Mask ids of head and hands in rendered recordings.
const SKIN_OBJECT_IDS: [u8; 3] = [1, 2, 3];

#[derive(Default)]
struct AgreementCounts {
    estimated: u64,
    on_skin: u64,
    checked: u64,
    agreed: u64,
}

impl AgreementCounts {
    fn add(
        &mut self,
        masks: &MaskReader,
        cameras: &[Camera],
        reference: usize,
        frame: usize,
        field: &DenseField,
    ) -> Result<()> {
        let all: Vec<image::GrayImage> = (0..cameras.len()).map(|c| masks.read(frame, c)).collect::<Result<_>>()?;
        for (ray, (pos, conf)) in field.position.iter().zip(&field.confidence).enumerate() {
            if *conf <= 0.0 {
                continue;
            }
            self.estimated += 1;
            // The ray's pixel centre at full resolution (the field may be on a coarser grid).
            let s = cameras[reference].width as usize / field.width.max(1);
            let (x, y) = ((ray % field.width) * s + s / 2, (ray / field.width) * s + s / 2);
            let Some(own) = all[reference].get_pixel_checked(x as u32, y as u32).map(|p| p.0[0]) else { continue };
            if !SKIN_OBJECT_IDS.contains(&own) {
                continue;
            }
            self.on_skin += 1;
            let p = nalgebra::Point3::new(f64::from(pos[0]), f64::from(pos[1]), f64::from(pos[2]));
            let mut agrees = true;
            for (c, cam) in cameras.iter().enumerate() {
                if c == reference {
                    continue;
                }
                let Some(q) = cam.project(&p) else { continue };
                let (x, y) = (q.x.round(), q.y.round());
                if x < 0.0 || y < 0.0 || x >= f64::from(cam.width) || y >= f64::from(cam.height) {
                    continue;
                }
                agrees &= all[c].get_pixel(x as u32, y as u32).0[0] == own;
            }
            self.checked += 1;
            self.agreed += u64::from(agrees);
        }
        Ok(())
    }

    fn agreement(&self) -> f64 {
        self.agreed as f64 / self.checked.max(1) as f64
    }

    fn on_skin(&self) -> f64 {
        self.on_skin as f64 / self.estimated.max(1) as f64
    }
}
