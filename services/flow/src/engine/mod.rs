//! The Scene Particle engine: frames in, weighted particles per ray and a dense per-ray
//! estimate out.

pub mod particles;
pub mod refine;
pub mod rng;

pub(crate) mod companion;
mod neighbour_costs;

use std::time::Instant;

use handflow_protocol::Camera;
use nalgebra::Point2;
use rayon::prelude::*;

use crate::config::{Coverage, EngineConfig, Temporal, Variant, MAX_PARTICLES_PER_RAY};
use crate::engine::neighbour_costs::{same_hypothesis, NeighbourCosts};
use crate::engine::particles::{ray_resample, Particle, SearchSpace};
use crate::engine::refine::{weighted_median_refine, RayEstimate};
use crate::engine::rng::RayRng;
use crate::matching::camera::{window_quarter_turns, LevelProjection};
use crate::matching::image::{LocalNormalisation, Pyramid};
use crate::matching::likelihood::{
    robust_window_costs, variance_likelihood, MatchImage, ReferenceWindow, COST_LANES, MAX_IMAGES,
};
use crate::skin::model::SkinModel;

/// Why the engine refused a configuration or a frame.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum FlowError {
    /// A configuration field is out of range.
    #[error("engine configuration: {0}")]
    Config(String),
    /// The rig is unusable for the engine.
    #[error("rig: {0}")]
    Rig(String),
    /// A frame set has the wrong number of views.
    #[error("frame {frame}: expected {expected} views (one per camera), got {got}")]
    ViewCount {
        /// Frame number (0-based, in push order).
        frame: u64,
        /// Cameras in the rig.
        expected: usize,
        /// Views in the frame set.
        got: usize,
    },
    /// A view's byte length does not match its camera's size.
    #[error("frame {frame}, camera `{camera}`: expected {expected} bytes of RGB8 ({width}x{height}), got {got}")]
    ViewSize {
        /// Frame number (0-based, in push order).
        frame: u64,
        /// Camera name.
        camera: String,
        /// Camera width.
        width: u32,
        /// Camera height.
        height: u32,
        /// Expected byte count.
        expected: usize,
        /// Actual byte count.
        got: usize,
    },
    /// A frame set lacks the reference camera's view, which every ray starts from.
    #[error("frame {frame}: the reference camera `{camera}` has no view; the set cannot be estimated")]
    ReferenceMissing {
        /// Frame number (0-based, in push order).
        frame: u64,
        /// The reference camera's name.
        camera: String,
    },
}

/// The dense per-ray output of the reference view (row-major), on the finest ray grid: that of
/// pyramid level `finest_level + ray_subsampling` (full resolution by default).
#[derive(Clone, Debug, Default)]
pub struct DenseField {
    /// Reference image width.
    pub width: usize,
    /// Reference image height.
    pub height: usize,
    /// Camera-frame depth of each ray's estimate (NaN for an empty ray).
    pub depth: Vec<f32>,
    /// World position of each ray's estimate (NaN for an empty ray).
    pub position: Vec<[f32; 3]>,
    /// World velocity per frame of each ray's estimate (zero for an empty ray).
    pub velocity: Vec<[f32; 3]>,
    /// Confidence in [0, 1] (0 for an empty ray).
    pub confidence: Vec<f32>,
}

/// What the last estimate cost.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FrameStats {
    /// Index (push order) of the frame the estimate is for.
    pub frame: u64,
    /// Particle likelihood evaluations.
    pub evaluations: u64,
    /// Wall time of the estimate, including normalisation and pyramids of the newest frame.
    pub seconds: f64,
    /// Rays holding at least one particle.
    pub occupied_rays: usize,
    /// Whether the previous posterior served as the prior.
    pub used_temporal_prior: bool,
}

/// A ray grid of the reference camera at one pyramid level.
struct RayGrid {
    width: usize,
    height: usize,
    /// World direction of each ray, scaled so that `origin + depth * dir` has camera-frame
    /// depth `depth` in the reference camera.
    dirs: Vec<[f32; 3]>,
}

/// The Scene Particle engine of one rig. See the crate documentation.
pub struct SceneFlowEngine {
    config: EngineConfig,
    cameras: Vec<Camera>,
    reference: usize,
    /// `projections[level][camera]`.
    projections: Vec<Vec<LevelProjection>>,
    /// Per camera, the quarter turns of its image relative to the reference's: the matching
    /// windows turn with it.
    window_turns: Vec<u8>,
    /// Ray grids per level (`paper` uses only level 0's: its rays are full-resolution pixels).
    grids: Vec<RayGrid>,
    origin: [f32; 3],
    optical_axis: [f32; 3],
    space: SearchSpace,
    /// Three frame slots of per-camera pyramids; `ring_newest` is the last pushed.
    ring: [Vec<Pyramid>; 3],
    /// `present[slot][camera]`: whether the camera delivered a view for the frame in `slot`
    /// (a live camera that stopped leaves its view out; its images are not matched against).
    present: [Vec<bool>; 3],
    ring_len: usize,
    ring_newest: usize,
    frames_pushed: u64,
    /// Per ring slot, its frame's place on the stream's frame grid: consecutive frames
    /// differ by 1, and a frame set lost on the way (a live stage that fell behind) leaves
    /// a gap that the constant-velocity model spans.
    slot_index: [u64; 3],
    /// Grid index of the last frame pushed.
    last_index: Option<u64>,
    particles: Vec<Particle>,
    particles_back: Vec<Particle>,
    counts: Vec<u8>,
    counts_back: Vec<u8>,
    best: Vec<Particle>,
    best_back: Vec<Particle>,
    /// Per ray, the costs its neighbours' candidates had in the previous loop.
    neighbour_costs: Vec<NeighbourCosts>,
    /// Counts `iterate` calls, so a ray's `neighbour_costs` are known to be the last loop's.
    loop_stamp: u32,
    /// Off only in tests, to compare against matching every candidate.
    reuse_neighbour_costs: bool,
    /// The engine of the second reference camera ([`EngineConfig::second_reference`]).
    companion: Option<Box<SceneFlowEngine>>,
    /// Full-resolution pixels of the reference view whose rays stay empty: what another
    /// engine's reference camera sees (row-major; empty: none).
    veto: Vec<bool>,
    estimates: Vec<RayEstimate>,
    refined: Vec<RayEstimate>,
    /// Occupancy of full-resolution rays in this frame's prior (sparse mode keeps it).
    prior_counts: Vec<u8>,
    /// Whether `prior_counts` belongs to the frame being estimated.
    prior_valid: bool,
    /// Frame index whose posterior `particles` holds at full resolution, if any.
    posterior_of: Option<u64>,
    /// Ring slot of that frame.
    posterior_slot: Option<usize>,
    field: DenseField,
    stats: FrameStats,
    /// Per-camera skin models (`skin` coverage; empty otherwise).
    skin_models: Vec<SkinModel>,
    /// `skin_maps[slot][camera]`: clamped log10 skin ratio of every full-resolution pixel
    /// of that ring slot's frame (`skin` coverage).
    skin_maps: [Vec<Vec<f32>>; 3],
    /// `active[grid level]`: rays that may hold particles in the frame being estimated
    /// (`skin` coverage): see `skin_footprint_share`. Grids finer than the finest ray grid
    /// cast no rays and are left as they are.
    active: Vec<Vec<bool>>,
    /// The finest ray grid's rays that cover any skin pixel (what the coarser grids of
    /// `active` are built from), kept to reuse its buffer.
    covers_skin: Vec<bool>,
    /// Extra passes for the next estimate without a carried posterior, instead of the
    /// configuration's (a stage joining a stream part-way must answer quickly).
    next_cold_start_passes: Option<usize>,
}

/// Where a pass over a frame takes its particles from.
#[derive(Clone, Copy, PartialEq)]
enum Prior {
    /// The broad initial prior: no earlier estimate to build on.
    None,
    /// The previous frame's posterior, moved by its velocities times `step` frame
    /// intervals (1, or up to [`MAX_SPANNED_GAP_FRAMES`] over frames lost on the way).
    Carried { step: f32 },
    /// A posterior from farther back than constant velocity spans (a live stage that fell
    /// behind): held where it was, with [`STALE_FRESH_SHARE`] of each ray drawn afresh from
    /// the broad prior. What stood still is still there; where a hand went, the old
    /// particles are only a guess.
    Stale,
    /// The previous pass's posterior for this same frame, unmoved.
    Held,
}

/// Frames the estimate looks at, oldest first, as ring slots.
#[derive(Clone, Copy)]
struct Window {
    slots: [usize; 3],
    len: usize,
    /// Index in `slots` of the frame estimated (t): 1, or 0 for a stream's first frame,
    /// which has only t+1 after it.
    centre: usize,
}

impl Window {
    /// Ring slot of the frame estimated.
    fn centre_slot(&self) -> usize {
        self.slots[self.centre]
    }
}

impl SceneFlowEngine {
    /// An engine for `cameras` whose rays are those of `cameras[reference]`.
    pub fn new(config: EngineConfig, cameras: Vec<Camera>, reference: usize) -> Result<Self, FlowError> {
        config.validate().map_err(FlowError::Config)?;
        if cameras.is_empty() {
            return Err(FlowError::Rig("the rig has no camera".into()));
        }
        if cameras.len() * 3 > MAX_IMAGES {
            return Err(FlowError::Rig(format!(
                "at most {} cameras are supported, got {}",
                MAX_IMAGES / 3,
                cameras.len()
            )));
        }
        let Some(ref_cam) = cameras.get(reference) else {
            return Err(FlowError::Rig(format!(
                "reference camera {reference} does not exist ({} cameras)",
                cameras.len()
            )));
        };
        let levels = config.pyramid_levels;
        let projections = (0..levels).map(|l| cameras.iter().map(|c| LevelProjection::new(c, l)).collect()).collect();
        // Turns are judged where the scene is expected: mid-way (geometrically) through the
        // depth range.
        let typical_depth = f64::from(config.depth_range.0 * config.depth_range.1).sqrt();
        let window_turns: Vec<u8> = cameras.iter().map(|c| window_quarter_turns(ref_cam, c, typical_depth)).collect();
        for (camera, &turns) in cameras.iter().zip(&window_turns).filter(|(_, &t)| t != 0) {
            tracing::debug!(
                "camera `{}` is turned by {} quarter turn(s) relative to the reference `{}`: its matching windows turn with it",
                camera.name,
                turns,
                ref_cam.name
            );
        }
        let grid_levels = if config.per_level_rays { levels } else { 1 };
        // Rays finer than the finest ray level are never cast: their grids keep only their
        // sizes (a 1280x720 camera's full-resolution grid would cost a quarter of a second
        // of undistortion at every start, which a restarted stage waits for).
        let cast_from = if config.per_level_rays { finest_ray_level(&config) } else { 0 };
        let grids: Vec<RayGrid> = (0..grid_levels).map(|l| ray_grid(ref_cam, l, l >= cast_from)).collect();
        let centre = ref_cam.centre();
        let origin = [centre.x as f32, centre.y as f32, centre.z as f32];
        let axis = ref_cam.rotation.matrix().row(2).transpose();
        let optical_axis = [axis.x as f32, axis.y as f32, axis.z as f32];
        let baseline = cameras.iter().map(|c| (c.centre() - centre).norm()).fold(0.0f64, f64::max);
        let focal = ref_cam.matrix[(0, 0)] as f32;
        // A single camera (or co-located ones) still has temporal parallax; use a nominal
        // baseline of one hundredth of the near depth so diffusion stays finite.
        let baseline = (baseline as f32).max(config.depth_range.0 * 0.01);
        let space = SearchSpace {
            inverse_depth: (1.0 / config.depth_range.1, 1.0 / config.depth_range.0),
            speed_bound: config.speed_bound,
            pixels_per_inverse_depth: focal * baseline,
            focal_px: focal,
        };
        // Particle stores for the largest grid that holds particles: a grid finer than the
        // finest ray level never does (four 1280x720 views: 265 MB of particles written at
        // every start otherwise, a tenth of a second a restarted stage waits for).
        let rays = grids[cast_from].width * grids[cast_from].height;
        let n = config.particles_per_ray;
        let ray_level = finest_ray_level(&config);
        let (field_width, field_height) = (grids[ray_level].width, grids[ray_level].height);
        let field_rays = field_width * field_height;
        let skin = config.coverage == Coverage::Skin;
        let skin_models = if skin { vec![SkinModel::generic(0.0); cameras.len()] } else { Vec::new() };
        let active = if skin { grids.iter().map(|g| vec![false; g.width * g.height]).collect() } else { Vec::new() };
        let mut engine = Self {
            config,
            cameras,
            reference,
            projections,
            window_turns,
            grids,
            origin,
            optical_axis,
            space,
            ring: Default::default(),
            present: Default::default(),
            ring_len: 0,
            ring_newest: 2,
            frames_pushed: 0,
            slot_index: [0; 3],
            last_index: None,
            particles: vec![Particle::EMPTY; rays * n],
            particles_back: vec![Particle::EMPTY; rays * n],
            counts: vec![0; rays],
            counts_back: vec![0; rays],
            best: vec![Particle::EMPTY; rays],
            best_back: vec![Particle::EMPTY; rays],
            neighbour_costs: vec![NeighbourCosts::default(); rays],
            loop_stamp: 0,
            reuse_neighbour_costs: true,
            companion: None,
            veto: Vec::new(),
            estimates: vec![RayEstimate::default(); rays],
            refined: vec![RayEstimate::default(); rays],
            prior_counts: vec![0; rays],
            prior_valid: false,
            posterior_of: None,
            posterior_slot: None,
            field: DenseField {
                width: field_width,
                height: field_height,
                depth: vec![f32::NAN; field_rays],
                position: vec![[f32::NAN; 3]; field_rays],
                velocity: vec![[0.0; 3]; field_rays],
                confidence: vec![0.0; field_rays],
            },
            stats: FrameStats::default(),
            skin_models,
            next_cold_start_passes: None,
            skin_maps: Default::default(),
            active,
            covers_skin: Vec::new(),
        };
        if engine.config.second_reference {
            engine.add_companion()?;
        }
        Ok(engine)
    }

    /// The per-camera skin models used by `skin` coverage (the generic prior until replaced).
    pub fn skin_models(&self) -> &[SkinModel] {
        &self.skin_models
    }

    /// Replaces the skin models (one per camera, rig order), e.g. after adapting them to face
    /// detections; they apply from the next pushed frame. Only `skin` coverage uses them.
    pub fn set_skin_models(&mut self, models: &[SkinModel]) -> Result<(), FlowError> {
        if self.config.coverage != Coverage::Skin {
            return Err(FlowError::Config("skin models need `coverage = \"skin\"`".into()));
        }
        if models.len() != self.cameras.len() {
            return Err(FlowError::Rig(format!(
                "{} skin models given for {} cameras",
                models.len(),
                self.cameras.len()
            )));
        }
        self.skin_models.clone_from_slice(models);
        if let Some(c) = self.companion.as_mut() {
            c.set_skin_models(models)?;
        }
        Ok(())
    }

    /// Whether world point `p` lies in front of the reference camera and inside its image.
    pub fn reference_sees(&self, p: [f32; 3]) -> bool {
        let cam = &self.cameras[self.reference];
        in_image(&self.projections[0][self.reference], cam.width, cam.height, p)
    }

    /// The clamped log10 skin ratio of the colour camera `camera` saw at full-resolution
    /// pixel (`x`, `y`) in the frame of the last estimate (`skin` coverage; `None` otherwise
    /// or outside the image).
    pub fn skin_at(&self, camera: usize, x: usize, y: usize) -> Option<f32> {
        let cam = self.cameras.get(camera)?;
        let slot = self.posterior_slot?;
        if x >= cam.width as usize || y >= cam.height as usize {
            return None;
        }
        self.skin_maps[slot].get(camera)?.get(y * cam.width as usize + x).copied()
    }

    /// The skin map of camera `camera` in the frame of the last estimate: the clamped log10
    /// skin ratio of every full-resolution pixel, row-major (what [`Self::skin_at`] reads;
    /// `None` without `skin` coverage, before the first estimate or for an unknown camera).
    pub fn skin_map(&self, camera: usize) -> Option<&[f32]> {
        let slot = self.posterior_slot?;
        self.skin_maps[slot].get(camera).map(Vec::as_slice).filter(|m| !m.is_empty())
    }

    /// The configuration in use.
    pub fn config(&self) -> &EngineConfig {
        &self.config
    }

    /// The cameras, in rig order.
    pub fn cameras(&self) -> &[Camera] {
        &self.cameras
    }

    /// Index of the reference camera.
    pub fn reference(&self) -> usize {
        self.reference
    }

    /// Cost of the last estimate.
    pub fn stats(&self) -> FrameStats {
        self.stats
    }

    /// The last estimate.
    pub fn field(&self) -> &DenseField {
        &self.field
    }

    /// The particles of ray `ray` of the finest estimated grid (the [`DenseField`]'s grid)
    /// after the last estimate (empty for an empty ray). World position of a particle:
    /// [`SceneFlowEngine::particle_position`].
    pub fn ray_particles(&self, ray: usize) -> &[Particle] {
        let n = self.config.particles_per_ray;
        &self.particles[ray * n..ray * n + usize::from(self.counts[ray])]
    }

    /// World position of a particle of ray `ray` of the finest estimated grid.
    pub fn particle_position(&self, ray: usize, particle: &Particle) -> [f32; 3] {
        point_on_ray(self.origin, self.grids[finest_ray_level(&self.config)].dirs[ray], particle.depth)
    }

    /// Runs `passes` extra passes instead of the configuration's `cold_start_passes` over
    /// the next frame estimated without a carried posterior (then the configuration's again).
    pub fn set_next_cold_start_passes(&mut self, passes: usize) {
        self.next_cold_start_passes = Some(passes);
        if let Some(c) = self.companion.as_mut() {
            c.set_next_cold_start_passes(passes);
        }
    }

    /// Forgets every frame and the posterior (a new, unrelated stream follows).
    pub fn reset(&mut self) {
        self.ring_len = 0;
        self.last_index = None;
        self.posterior_of = None;
        self.posterior_slot = None;
        self.next_cold_start_passes = None;
        if let Some(c) = self.companion.as_mut() {
            c.reset();
        }
    }

    /// Adds the next synchronised frame set (RGB8, one view per camera in rig order) and
    /// returns the estimate it completes: the newest frame with the two-frame likelihood,
    /// or the previous one with forwards/backwards (one frame late). Frames that complete
    /// nothing yet return `None`.
    pub fn push_frame(&mut self, views: &[&[u8]]) -> Result<Option<&DenseField>, FlowError> {
        self.push_frame_partial(views, 0)
    }

    /// [`SceneFlowEngine::push_frame`] for a set some cameras gave no view for: bit `k` of
    /// `missing` set means camera `k`'s view (zero bytes) is left out of every likelihood and
    /// of the skin term, for as long as this frame is in the window. The reference camera
    /// must be present.
    pub fn push_frame_partial(&mut self, views: &[&[u8]], missing: u32) -> Result<Option<&DenseField>, FlowError> {
        let next = self.last_index.map_or(0, |i| i + 1);
        self.push_frame_indexed(views, missing, next)
    }

    /// [`SceneFlowEngine::push_frame_partial`] for the frame at `index` on the stream's frame
    /// grid (its capture sequence): frames skipped since the last one pushed (lost, or
    /// dropped by a stage that fell behind) widen the window's intervals, and the
    /// constant-velocity model, its velocities still per frame interval, spans them. An
    /// index not after the last one counts as the next.
    pub fn push_frame_indexed(
        &mut self,
        views: &[&[u8]],
        missing: u32,
        index: u64,
    ) -> Result<Option<&DenseField>, FlowError> {
        let started = Instant::now();
        let frame = self.frames_pushed;
        let has = |k: usize| k >= 32 || missing & (1 << k) == 0;
        if !has(self.reference) {
            return Err(FlowError::ReferenceMissing { frame, camera: self.cameras[self.reference].name.clone() });
        }
        if views.len() != self.cameras.len() {
            return Err(FlowError::ViewCount { frame, expected: self.cameras.len(), got: views.len() });
        }
        for (cam, view) in self.cameras.iter().zip(views) {
            let expected = cam.width as usize * cam.height as usize * 3;
            if view.len() != expected {
                return Err(FlowError::ViewSize {
                    frame,
                    camera: cam.name.clone(),
                    width: cam.width,
                    height: cam.height,
                    expected,
                    got: view.len(),
                });
            }
        }
        let slot = (self.ring_newest + 1) % 3;
        let levels = self.config.pyramid_levels;
        let local = (self.config.variant == Variant::Handflow && self.config.local_normalisation_radius > 0).then_some(
            LocalNormalisation {
                radius: self.config.local_normalisation_radius,
                floor: self.config.local_normalisation_floor,
            },
        );
        let finest = self.config.finest_level;
        let pyramids = &mut self.ring[slot];
        pyramids.resize_with(self.cameras.len(), Pyramid::default);
        pyramids.par_iter_mut().zip(self.cameras.par_iter()).zip(views.par_iter()).for_each(|((pyr, cam), view)| {
            pyr.rebuild(cam.width as usize, cam.height as usize, view, levels, local, finest);
        });
        // Refilled in place: a steady stream allocates nothing per frame.
        self.present[slot].clear();
        self.present[slot].extend((0..self.cameras.len()).map(has));
        if self.config.coverage == Coverage::Skin {
            let maps = &mut self.skin_maps[slot];
            maps.resize_with(self.cameras.len(), Vec::new);
            let present = &self.present[slot];
            maps.par_iter_mut().zip(self.skin_models.par_iter()).zip(views.par_iter()).enumerate().for_each(
                |(k, ((map, model), view))| {
                    map.clear();
                    // A missing view's map stays empty: it says nothing about skin.
                    if present[k] {
                        map.extend(view.chunks_exact(3).map(|p| model.log_ratio([p[0], p[1], p[2]])));
                    }
                },
            );
        }
        let index = self.last_index.map_or(index, |last| index.max(last + 1));
        self.slot_index[slot] = index;
        self.last_index = Some(index);
        self.ring_newest = slot;
        self.ring_len = (self.ring_len + 1).min(3);
        self.frames_pushed += 1;
        let estimated = self.estimate_pending(started);
        if self.companion.is_some() {
            self.run_companion(started, |c| {
                c.slot_index[slot] = index;
                c.last_index = Some(index);
                c.ring_newest = slot;
                c.ring_len = (c.ring_len + 1).min(3);
                c.frames_pushed += 1;
                Ok(c.estimate_pending(started))
            })?;
        }
        Ok(estimated.then_some(&self.field))
    }

    /// Estimates the frame the window of pushed frames completes, if any.
    fn estimate_pending(&mut self, started: Instant) -> bool {
        let window = match self.config.temporal {
            Temporal::TwoFrame if self.ring_len >= 2 => Some(self.window(2, 1)),
            Temporal::ForwardsBackwards if self.ring_len >= 3 => Some(self.window(3, 1)),
            // The ring holds two frames only once per stream: its first two.
            Temporal::ForwardsBackwards if self.ring_len == 2 && self.config.estimates_first_frame() => {
                Some(self.window(2, 0))
            }
            _ => None,
        };
        match window {
            Some(w) => {
                // Run the whole filter on a pool thread: its many parallel loops then queue
                // work locally instead of through rayon's global injector, which allocates
                // a block per 63 jobs sent from outside the pool.
                rayon::scope(|_| self.estimate(w, started));
                true
            }
            None => false,
        }
    }

    /// Ends a stream: with forwards/backwards, estimates the last frame with the two-frame
    /// likelihood (there is no t+1). Returns `None` when there is nothing left to estimate.
    pub fn flush(&mut self) -> Option<&DenseField> {
        let started = Instant::now();
        let pending = self.config.temporal == Temporal::ForwardsBackwards && self.ring_len >= 2;
        self.ring_len = 0;
        if !pending {
            return None;
        }
        let w = self.window(2, 1);
        rayon::scope(|_| self.estimate(w, started));
        if self.companion.is_some() {
            // A flush cannot fail.
            let newest = self.ring_newest;
            let _ = self.run_companion(started, |c| {
                c.ring_newest = newest;
                Ok(c.flush().is_some())
            });
        }
        Some(&self.field)
    }

    /// The `len` newest frames, oldest first, estimating the one at index `centre`.
    fn window(&self, len: usize, centre: usize) -> Window {
        let mut slots = [0; 3];
        for (k, slot) in slots.iter_mut().enumerate().take(len) {
            *slot = (self.ring_newest + 3 - (len - 1 - k)) % 3;
        }
        Window { slots, len, centre }
    }

    /// Runs the filter for the centre frame of `window` (t-1, t[, t+1], or t, t+1).
    fn estimate(&mut self, window: Window, started: Instant) {
        let frame = self.frames_pushed - (window.len - window.centre) as u64;
        let _span = tracing::debug_span!("scene_flow", frame, variant = self.config.variant.name()).entered();
        // Frame intervals since the frame of the posterior held (1 unless frames were lost).
        let gap = match (self.posterior_of == Some(frame.wrapping_sub(1)), self.posterior_slot) {
            (true, Some(slot)) => Some(self.slot_index[window.centre_slot()].saturating_sub(self.slot_index[slot])),
            _ => None,
        };
        let prior = match gap {
            Some(g) if g <= MAX_SPANNED_GAP_FRAMES => Prior::Carried { step: g as f32 },
            Some(_) => Prior::Stale,
            None => Prior::None,
        };
        let carried = gap.is_some();
        let mut evaluations = self.estimate_pass(window, frame, prior, 0);
        // A stream's first frame is seen with its successor alone: a third less evidence of
        // each depth, and the velocity pinned from one side only. It gets twice the extra
        // passes (measured on `signer-3cam`: the head 3.9 cm off with the usual 8, 1.4 cm
        // with 16), and it is not carried on: the next frame starts cold as well. Carried,
        // it cost the shared real session's hands 2 to 6 points within 5 cm (BENCHMARKS.md).
        let first_frame = window.centre == 0;
        if !carried {
            let passes = if first_frame { self.next_cold_start_passes } else { self.next_cold_start_passes.take() };
            let passes = passes.unwrap_or(self.config.cold_start_passes) * if first_frame { 2 } else { 1 };
            for pass in 1..=passes as u64 {
                evaluations += self.estimate_pass(window, frame, Prior::Held, pass);
            }
        }
        if first_frame {
            self.posterior_of = None;
        }
        let ray_level = finest_ray_level(&self.config);
        let rays = self.grids[ray_level].width * self.grids[ray_level].height;
        let occupied_rays = self.counts[..rays].iter().filter(|&&c| c > 0).count();
        self.stats = FrameStats {
            frame,
            evaluations,
            seconds: started.elapsed().as_secs_f64(),
            occupied_rays,
            used_temporal_prior: carried,
        };
        tracing::debug!(
            frame,
            evaluations,
            seconds = self.stats.seconds,
            occupied_rays,
            temporal_prior = carried,
            "scene flow estimated"
        );
    }

    /// One coarse-to-fine pass over the centre frame of `window`; returns the number of
    /// likelihood evaluations. `pass` tells the random streams of repeated passes apart.
    fn estimate_pass(&mut self, window: Window, frame: u64, prior: Prior, pass: u64) -> u64 {
        let use_prior = prior != Prior::None;
        // Frame indices stay far below 2^40; later passes draw from their own streams.
        let frame_key = frame ^ (pass << 40);
        let mut evaluations = 0u64;
        self.prior_valid = use_prior;
        if self.config.coverage == Coverage::Skin {
            self.update_active(window.centre_slot());
        }
        if use_prior {
            let (step, fresh_share) = match prior {
                Prior::Carried { step } => (step, self.config.fresh_fraction),
                Prior::Stale => (0.0, STALE_FRESH_SHARE.max(self.config.fresh_fraction)),
                Prior::Held | Prior::None => (0.0, self.config.fresh_fraction),
            };
            self.carry_posterior_forward(frame_key, step, fresh_share);
            self.prior_counts.copy_from_slice(&self.counts);
        }
        let levels = self.config.pyramid_levels;
        let finest = self.config.finest_level;
        let per_level_grid = self.config.per_level_rays;
        let top = levels - 1;
        let ray_level = finest_ray_level(&self.config);
        let grid_of = |level: usize| if per_level_grid { level.max(ray_level) } else { 0 };
        self.seed_top_level(grid_of(top), use_prior, frame_key);
        for level in (finest..levels).rev() {
            let grid = grid_of(level);
            if level != top && grid != grid_of(level + 1) {
                self.upsample_particles(grid_of(level + 1), grid);
            }
            let extra = match (level == top, use_prior) {
                (false, _) => 0,
                (true, true) => self.config.warm_coarse_extra_loops.unwrap_or(self.config.coarse_extra_loops),
                (true, false) => self.config.coarse_extra_loops,
            };
            let loops = self.config.noise_loops + extra;
            for it in 0..loops {
                let sigma_level_px = self.config.diffusion_px * self.config.diffusion_shrink.powi(it as i32);
                let last = level == finest && it + 1 == loops;
                let stage = (level * 64 + it) as u64;
                evaluations += self.iterate(window, level, grid, sigma_level_px, last, frame_key, stage, it > 0);
                std::mem::swap(&mut self.best, &mut self.best_back);
            }
        }
        self.publish_field(window);
        self.posterior_of = Some(frame);
        self.posterior_slot = Some(window.centre_slot());
        evaluations
    }

    /// Marks the rays of every grid level that cover a skin pixel of the reference view in
    /// ring slot `slot`; on the finest ray grid, where `skin_footprint_share` of the pixels
    /// they cover are. Each full-resolution pixel is read once, by the finest ray covering it
    /// (an estimate's passes call this once each: marking every pixel's own grid first and
    /// halving it level by level cost 6 % of `track`'s time on four 1280x720 views).
    fn update_active(&mut self, slot: usize) {
        let threshold = self.config.skin_threshold;
        let map = &self.skin_maps[slot][self.reference];
        let veto = &self.veto;
        let is_skin = |i: usize| map.get(i).is_some_and(|&h| h > threshold) && !veto.get(i).copied().unwrap_or(false);
        let level = finest_ray_level(&self.config);
        let (w, h) = (self.grids[0].width, self.grids[0].height);
        let (cw, s) = (self.grids[level].width, 1usize << level);
        let share = if level > 0 { self.config.skin_footprint_share } else { 0.0 };
        let covers = &mut self.covers_skin;
        covers.resize(self.active[level].len(), false);
        self.active[level].par_iter_mut().zip(covers.par_iter_mut()).enumerate().for_each(|(ray, (a, covered))| {
            let (x0, y0) = ((ray % cw) * s, (ray / cw) * s);
            let (xs, ys) = (x0..(x0 + s).min(w), y0..(y0 + s).min(h));
            let pixels = xs.len() * ys.len();
            let skin = ys.flat_map(|y| xs.clone().map(move |x| y * w + x)).filter(|&i| is_skin(i)).count();
            *covered = skin > 0;
            // At least one pixel, as on the coarser grids, however small the share.
            *a = skin > 0 && (share <= 0.0 || skin as f32 >= share * pixels as f32);
        });
        // A coarser ray covers skin where any of the (up to) four finer rays it spans does;
        // grid sizes round up level by level, so this is any skin pixel in its block.
        for l in level + 1..self.active.len() {
            let (fw, fh) = (self.grids[l - 1].width, self.grids[l - 1].height);
            let cw = self.grids[l].width;
            let (finer, coarser) = self.active.split_at_mut(l);
            let finer: &[bool] = if l == level + 1 { &self.covers_skin } else { &finer[l - 1] };
            coarser[0].par_iter_mut().enumerate().for_each(|(ray, a)| {
                let (i, j) = (ray % cw, ray / cw);
                let (x0, y0) = (2 * i, 2 * j);
                *a = (y0..(y0 + 2).min(fh)).any(|y| (x0..(x0 + 2).min(fw)).any(|x| finer[y * fw + x]));
            });
        }
    }

    /// The prior of a new frame: the previous posterior moved by its own velocity
    /// (constant-velocity model), each particle re-assigned to the reference ray it now
    /// projects onto; rays receiving more than N keep a random N; a share of each ray is
    /// replaced by fresh random particles; empty rays are refilled from neighbours (dense)
    /// or stay empty (sparse).
    /// `step` scales the velocity move: 1 for the next frame, 0 to hold the posterior still
    /// for another pass over the same frame; `fresh_share` of each ray is then drawn from
    /// the broad prior.
    fn carry_posterior_forward(&mut self, frame: u64, step: f32, fresh_share: f32) {
        let n = self.config.particles_per_ray;
        let finest = finest_ray_level(&self.config);
        let grid = &self.grids[finest];
        let (w, h) = (grid.width, grid.height);
        let reference = &self.projections[finest][self.reference];
        self.counts_back.iter_mut().for_each(|c| *c = 0);
        let mut rng = RayRng::for_item(self.config.seed, frame, 1 << 20, 0);
        for ray in 0..w * h {
            let count = usize::from(self.counts[ray]);
            for p in &self.particles[ray * n..ray * n + count] {
                let moved = add(point_on_ray(self.origin, grid.dirs[ray], p.depth), scale(p.velocity, step));
                let Some([u, v]) = reference.project(moved) else { continue };
                let (x, y) = (u.round(), v.round());
                if !(x >= 0.0 && y >= 0.0 && x < w as f32 && y < h as f32) {
                    continue;
                }
                let target = y as usize * w + x as usize;
                let depth = reference.to_camera(moved)[2];
                if depth.is_nan() || depth <= 0.0 {
                    continue;
                }
                let slot_count = usize::from(self.counts_back[target]);
                let carried = Particle { depth, velocity: p.velocity, weight: p.weight, cost: f32::INFINITY };
                if slot_count < n {
                    self.particles_back[target * n + slot_count] = carried;
                    self.counts_back[target] += 1;
                } else {
                    // Keep a uniformly random subset of the arrivals (approximate reservoir:
                    // the arrival count is not tracked per ray, so a fixed replacement rate).
                    let k = (rng.uniform() * (2 * n) as f32) as usize;
                    if k < n {
                        self.particles_back[target * n + k] = carried;
                    }
                }
            }
        }
        let fresh = (fresh_share * n as f32).round() as usize;
        let refill = matches!(self.config.coverage, Coverage::Dense | Coverage::Skin);
        let active = (self.config.coverage == Coverage::Skin).then(|| self.active[finest].as_slice());
        let (seed, space) = (self.config.seed, self.space);
        let (back, counts_back) = (&self.particles_back, &self.counts_back);
        let (particles, counts) = (&mut self.particles[..w * h * n], &mut self.counts[..w * h]);
        particles.par_chunks_mut(n).zip(counts.par_iter_mut()).enumerate().for_each(|(ray, (out, count))| {
            if active.is_some_and(|a| !a[ray]) {
                *count = 0;
                return;
            }
            let mut rng = RayRng::for_item(seed, frame, 1 << 21, ray as u64);
            let mut have = usize::from(counts_back[ray]);
            out[..have].copy_from_slice(&back[ray * n..ray * n + have]);
            if have == 0 && refill {
                have = refill_from_neighbours(back, counts_back, n, w, h, ray, out, &mut rng);
            }
            if have == 0 && active.is_some() {
                // Skin that nothing moved onto (a hand entering the view): a fresh start.
                for slot in out.iter_mut() {
                    *slot = space.random_particle(&mut rng);
                }
                have = n;
            }
            if have == 0 {
                *count = 0;
                return;
            }
            // Duplicate to a full ray, then refresh a share for exploration.
            for k in have..n {
                out[k] = out[(rng.uniform() * have as f32) as usize % have];
            }
            for slot in out.iter_mut().skip(n - fresh.min(n - 1)) {
                *slot = space.random_particle(&mut rng);
            }
            for slot in out.iter_mut() {
                slot.weight = 1.0 / n as f32;
            }
            *count = n as u8;
        });
    }

    /// Initial particles on the coarsest grid: from the carried prior (sampled down from
    /// full resolution) or, without a prior, from the broad initial prior.
    fn seed_top_level(&mut self, grid_level: usize, use_prior: bool, frame: u64) {
        let n = self.config.particles_per_ray;
        // Neighbour bests from an earlier frame or level must not leak into this one.
        self.best.iter_mut().for_each(|b| *b = Particle::EMPTY);
        let finest = finest_ray_level(&self.config);
        if use_prior && grid_level == finest {
            return; // `particles` already holds the prior on the finest grid.
        }
        let (gw, gh) = (self.grids[grid_level].width, self.grids[grid_level].height);
        let (fw, fh) = (self.grids[finest].width, self.grids[finest].height);
        let space = self.space;
        let seed = self.config.seed;
        let active = (self.config.coverage == Coverage::Skin).then(|| self.active[grid_level].as_slice());
        if use_prior {
            // Coarse ray (i, j) covers finest-grid rays [i*s, (i+1)*s): take the middle one,
            // or with skin coverage the first of them holding particles.
            let s = 1usize << (grid_level - finest);
            std::mem::swap(&mut self.particles, &mut self.particles_back);
            std::mem::swap(&mut self.counts, &mut self.counts_back);
            let (src, src_counts) = (&self.particles_back, &self.counts_back);
            self.particles[..gw * gh * n]
                .par_chunks_mut(n)
                .zip(self.counts[..gw * gh].par_iter_mut())
                .enumerate()
                .for_each(|(ray, (out, count))| {
                    let (i, j) = (ray % gw, ray / gw);
                    let fx = (i * s + s / 2).min(fw - 1);
                    let fy = (j * s + s / 2).min(fh - 1);
                    let mut from = fy * fw + fx;
                    if let Some(active) = active {
                        if !active[ray] {
                            *count = 0;
                            return;
                        }
                        if src_counts[from] == 0 {
                            let block = (j * s..((j + 1) * s).min(fh))
                                .flat_map(|y| (i * s..((i + 1) * s).min(fw)).map(move |x| y * fw + x));
                            if let Some(occupied) = block.into_iter().find(|&r| src_counts[r] > 0) {
                                from = occupied;
                            } else {
                                let mut rng = RayRng::for_item(seed, frame, 1 << 22, ray as u64);
                                for slot in out.iter_mut() {
                                    *slot = space.random_particle(&mut rng);
                                    slot.weight = 1.0 / n as f32;
                                }
                                *count = n as u8;
                                return;
                            }
                        }
                    }
                    let c = src_counts[from];
                    *count = c;
                    out[..usize::from(c)].copy_from_slice(&src[from * n..from * n + usize::from(c)]);
                });
            return;
        }
        self.particles[..gw * gh * n]
            .par_chunks_mut(n)
            .zip(self.counts[..gw * gh].par_iter_mut())
            .enumerate()
            .for_each(|(ray, (out, count))| {
                if active.is_some_and(|a| !a[ray]) {
                    *count = 0;
                    return;
                }
                let mut rng = RayRng::for_item(seed, frame, 1 << 22, ray as u64);
                for slot in out.iter_mut() {
                    *slot = space.random_particle(&mut rng);
                    slot.weight = 1.0 / n as f32;
                }
                *count = n as u8;
            });
    }

    /// Coarse-to-fine hand-over (`handflow`): every ray of the finer grid starts from the
    /// particles of the coarse ray it lies in.
    fn upsample_particles(&mut self, coarse: usize, fine: usize) {
        let n = self.config.particles_per_ray;
        let (cw, ch) = (self.grids[coarse].width, self.grids[coarse].height);
        let (fw, fh) = (self.grids[fine].width, self.grids[fine].height);
        std::mem::swap(&mut self.particles, &mut self.particles_back);
        std::mem::swap(&mut self.counts, &mut self.counts_back);
        std::mem::swap(&mut self.best, &mut self.best_back);
        let (src, src_counts) = (&self.particles_back, &self.counts_back);
        let coarse_best = &self.best_back;
        // Sparse mode: a ray is occupied at this level only if the full-resolution ray at its
        // centre held particles in the prior, so empty rays stay empty through the pyramid.
        let occupancy = (self.config.coverage == Coverage::Sparse && self.prior_valid).then_some(&self.prior_counts);
        let active = (self.config.coverage == Coverage::Skin).then(|| self.active[fine].as_slice());
        let finest = finest_ray_level(&self.config);
        let (full_w, full_h) = (self.grids[finest].width, self.grids[finest].height);
        let s = 1usize << (fine - finest);
        self.particles[..fw * fh * n]
            .par_chunks_mut(n)
            .zip(self.counts[..fw * fh].par_iter_mut())
            .zip(self.best[..fw * fh].par_iter_mut())
            .enumerate()
            .for_each(|(ray, ((out, count), best))| {
                let (i, j) = ((ray % fw) / 2, (ray / fw) / 2);
                let from = j.min(ch - 1) * cw + i.min(cw - 1);
                let centre =
                    ((ray / fw) * s + s / 2).min(full_h - 1) * full_w + ((ray % fw) * s + s / 2).min(full_w - 1);
                if occupancy.is_some_and(|o| o[centre] == 0) || active.is_some_and(|a| !a[ray]) {
                    *count = 0;
                    *best = Particle::EMPTY;
                    return;
                }
                let c = src_counts[from];
                *count = c;
                out[..usize::from(c)].copy_from_slice(&src[from * n..from * n + usize::from(c)]);
                *best = coarse_best[from];
            });
    }

    /// One noise loop on one level: diffuse, evaluate, weight, resample, for every ray in
    /// parallel. Returns the number of likelihood evaluations.
    #[allow(clippy::too_many_arguments)]
    fn iterate(
        &mut self,
        window: Window,
        level: usize,
        grid_level: usize,
        sigma_level_px: f32,
        last: bool,
        frame: u64,
        stage: u64,
        elite_cost_valid: bool,
    ) -> u64 {
        self.advance_loop_stamp();
        let n = self.config.particles_per_ray;
        let grid = &self.grids[grid_level];
        let (gw, gh) = (grid.width, grid.height);
        // A fixed array, not a Vec: nothing is allocated per iteration.
        let first_slot = window.slots[0];
        let placeholder = MatchImage {
            offset: 0.0,
            image: self.ring[first_slot][0].matching_level(level),
            projection: &self.projections[level][0],
            is_reference_now: false,
            window_turns: 0,
        };
        let mut images = [placeholder; MAX_IMAGES];
        let mut n_images = 0;
        for (k, &slot) in window.slots.iter().enumerate().take(window.len) {
            let offset = (self.slot_index[slot] as f64 - self.slot_index[window.centre_slot()] as f64) as f32;
            if offset.abs() > MAX_SPANNED_GAP_FRAMES as f32 {
                continue;
            }
            for (q, pyr) in self.ring[slot].iter().enumerate() {
                if !self.present[slot].get(q).copied().unwrap_or(true) {
                    continue;
                }
                images[n_images] = MatchImage {
                    offset,
                    image: pyr.matching_level(level),
                    projection: &self.projections[level][q],
                    is_reference_now: k == window.centre && q == self.reference,
                    window_turns: self.window_turns[q],
                };
                n_images += 1;
            }
        }
        let images = &images[..n_images];
        let ctx = IterationContext {
            config: &self.config,
            space: self.space,
            images,
            reference_image: self.ring[window.centre_slot()][self.reference].matching_level(level),
            dirs: &grid.dirs,
            origin: self.origin,
            grid_width: gw,
            grid_height: gh,
            level,
            grid_level,
            per_level_grid: self.config.per_level_rays,
            sigma_px: sigma_level_px * (1u32 << level) as f32,
            keep: ((n_images - 1) as f32 * self.config.view_keep_fraction).ceil().max(1.0) as usize,
            optical_axis: self.optical_axis,
            sweep: Sweep::for_config(&self.config, stage),
            elite_cost_valid,
            skin: (self.config.coverage == Coverage::Skin && self.config.skin_weight > 0.0).then(|| SkinTerm {
                maps: &self.skin_maps[window.centre_slot()],
                projections: &self.projections[0],
                cameras: &self.cameras,
                reference: self.reference,
                weight: self.config.skin_weight * std::f32::consts::LN_10,
                drop_worst: self.config.skin_drop_worst_view,
            }),
            best_prev: &self.best,
            loop_stamp: self.loop_stamp,
            top_level: level + 1 == self.config.pyramid_levels,
            last,
            frame,
            stage,
        };
        let rays = gw * gh;
        let (particles, counts) = (&mut self.particles[..rays * n], &mut self.counts[..rays]);
        let (best_out, estimates) = (&mut self.best_back[..rays], &mut self.estimates[..rays]);
        let memos = &mut self.neighbour_costs[..rays];
        match ctx.sweep {
            // Jacobi: every ray reads its neighbours' previous best; fully parallel.
            Sweep::None => particles
                .par_chunks_mut(n)
                .zip(counts.par_iter_mut())
                .zip(best_out.par_iter_mut())
                .zip(estimates.par_iter_mut())
                .zip(memos.par_iter_mut())
                .enumerate()
                .map(|(ray, ((((p, c), b), e), memo))| ctx.update_ray(ray, p, c, None, b, e, memo))
                .sum(),
            // PatchMatch-style sweep along rows, rows in parallel: a good hypothesis can
            // cross the whole row in one iteration instead of one ray per iteration.
            Sweep::Rows { reverse } => particles
                .par_chunks_mut(gw * n)
                .zip(counts.par_chunks_mut(gw))
                .zip(best_out.par_chunks_mut(gw))
                .zip(estimates.par_chunks_mut(gw))
                .zip(memos.par_chunks_mut(gw))
                .enumerate()
                .map(|(y, ((((prow, crow), brow), erow), mrow))| {
                    let mut evals = 0;
                    for k in 0..gw {
                        let x = if reverse { gw - 1 - k } else { k };
                        let scan = match (reverse, x) {
                            (false, 0) => None,
                            (false, _) => Some(brow[x - 1]),
                            (true, _) if x + 1 == gw => None,
                            (true, _) => Some(brow[x + 1]),
                        };
                        let (p, c) = (&mut prow[x * n..(x + 1) * n], &mut crow[x]);
                        evals += ctx.update_ray(y * gw + x, p, c, scan, &mut brow[x], &mut erow[x], &mut mrow[x]);
                    }
                    evals
                })
                .sum(),
            // The same along columns: rows one after another, each row in parallel, reading
            // the row just updated.
            Sweep::Columns { reverse } => {
                let mut evals = 0;
                for k in 0..gh {
                    let y = if reverse { gh - 1 - k } else { k };
                    let row = y * gw..(y + 1) * gw;
                    let (before, rest) = best_out.split_at_mut(row.start);
                    let (this_row, after) = rest.split_at_mut(gw);
                    let previous: Option<&[Particle]> = match reverse {
                        false if y > 0 => Some(&before[(y - 1) * gw..]),
                        true if y + 1 < gh => Some(&after[..gw]),
                        _ => None,
                    };
                    // Sparse coverage: most rows are empty or nearly so; a parallel dispatch
                    // per row would cost more than the row's work.
                    let occupied = counts[row.clone()].iter().filter(|&&c| c > 0).count();
                    if occupied == 0 {
                        this_row.iter_mut().for_each(|b| *b = Particle::EMPTY);
                        if ctx.last {
                            estimates[row].iter_mut().for_each(|e| *e = RayEstimate::default());
                        }
                        continue;
                    }
                    if occupied < SEQUENTIAL_ROW_RAYS {
                        for x in 0..gw {
                            let (p, c) = (
                                &mut particles[(row.start + x) * n..(row.start + x + 1) * n],
                                &mut counts[row.start + x],
                            );
                            evals += ctx.update_ray(
                                y * gw + x,
                                p,
                                c,
                                previous.map(|r| r[x]),
                                &mut this_row[x],
                                &mut estimates[row.start + x],
                                &mut memos[row.start + x],
                            );
                        }
                        continue;
                    }
                    evals += particles[row.start * n..row.end * n]
                        .par_chunks_mut(n)
                        .zip(counts[row.clone()].par_iter_mut())
                        .zip(this_row.par_iter_mut())
                        .zip(estimates[row.clone()].par_iter_mut())
                        .zip(memos[row.clone()].par_iter_mut())
                        .enumerate()
                        .map(|(x, ((((p, c), b), e), memo))| {
                            ctx.update_ray(y * gw + x, p, c, previous.map(|r| r[x]), b, e, memo)
                        })
                        .sum::<u64>();
                }
                evals
            }
        }
    }

    /// Turns the per-ray estimates (refined for `handflow`) into the dense field.
    fn publish_field(&mut self, window: Window) {
        let refine = self.config.variant == Variant::Handflow && self.config.refine_radius > 0;
        let finest = finest_ray_level(&self.config);
        let rays = self.grids[finest].width * self.grids[finest].height;
        let source = if refine {
            let guide = self.ring[window.centre_slot()][self.reference].level(finest);
            weighted_median_refine(
                &self.estimates[..rays],
                &mut self.refined[..rays],
                guide,
                self.config.refine_radius,
                self.config.refine_colour_sigma,
            );
            &self.refined
        } else {
            &self.estimates
        };
        let dirs = &self.grids[finest].dirs;
        let origin = self.origin;
        let field = &mut self.field;
        field
            .depth
            .par_iter_mut()
            .zip(field.position.par_iter_mut())
            .zip(field.velocity.par_iter_mut())
            .zip(field.confidence.par_iter_mut())
            .enumerate()
            .for_each(|(ray, (((depth, position), velocity), confidence))| {
                let e = source[ray];
                if e.confidence > 0.0 && e.inverse_depth > 0.0 {
                    *depth = 1.0 / e.inverse_depth;
                    *position = point_on_ray(origin, dirs[ray], *depth);
                    *velocity = e.velocity;
                    *confidence = e.confidence;
                } else {
                    *depth = f32::NAN;
                    *position = [f32::NAN; 3];
                    *velocity = [0.0; 3];
                    *confidence = 0.0;
                }
            });
    }
}

/// Rows of a column sweep with fewer occupied rays than this are updated on one thread.
const SEQUENTIAL_ROW_RAYS: usize = 48;

/// Order in which rays are updated within one noise loop.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Sweep {
    /// All rays at once from the previous iteration's neighbours.
    None,
    /// Along rows; right to left when `reverse`.
    Rows { reverse: bool },
    /// Along columns; bottom to top when `reverse`.
    Columns { reverse: bool },
}

impl Sweep {
    /// The sweep of a noise loop: none without propagation (`paper`), else the four
    /// directions in turn so that information flows every way. With skin coverage rows
    /// only: a column sweep runs its rows one after another and a skin blob's rows are too
    /// short to share between threads, so vertical propagation instead comes from the
    /// neighbours above and below offering their previous best.
    fn for_config(config: &EngineConfig, stage: u64) -> Self {
        if config.variant != Variant::Handflow || !config.propagation {
            return Sweep::None;
        }
        if config.coverage == Coverage::Skin {
            return Sweep::Rows { reverse: stage % 2 == 1 };
        }
        match stage % 4 {
            0 => Sweep::Rows { reverse: false },
            1 => Sweep::Columns { reverse: false },
            2 => Sweep::Rows { reverse: true },
            _ => Sweep::Columns { reverse: true },
        }
    }
}

/// Read-only state of one noise loop, shared by all rays.
struct IterationContext<'a> {
    config: &'a EngineConfig,
    space: SearchSpace,
    images: &'a [MatchImage<'a>],
    reference_image: &'a crate::matching::image::ColourImage,
    dirs: &'a [[f32; 3]],
    origin: [f32; 3],
    grid_width: usize,
    grid_height: usize,
    level: usize,
    /// Level whose pixel grid the rays of this loop live on: `level`, or coarser on the
    /// finest levels with `ray_subsampling`.
    grid_level: usize,
    per_level_grid: bool,
    /// Diffusion in full-resolution pixels.
    sigma_px: f32,
    keep: usize,
    /// The reference camera's optical axis in the world: the direction of motion in depth.
    optical_axis: [f32; 3],
    /// Update order of this loop.
    sweep: Sweep,
    /// Whether `best_prev` holds costs evaluated on this level (not the first loop after a
    /// level change or a new frame), so the elite need not be evaluated again.
    elite_cost_valid: bool,
    /// Equation 4's factor (`skin` coverage with a positive `skin_weight`).
    skin: Option<SkinTerm<'a>>,
    best_prev: &'a [Particle],
    /// This loop's number (see [`NeighbourCosts`]).
    loop_stamp: u32,
    top_level: bool,
    last: bool,
    frame: u64,
    stage: u64,
}

/// The skin term of equation 4 at time t, as a natural-log weight.
struct SkinTerm<'a> {
    /// Per camera: clamped log10 skin ratio of each full-resolution pixel.
    maps: &'a [Vec<f32>],
    /// Full-resolution projections.
    projections: &'a [LevelProjection],
    cameras: &'a [Camera],
    reference: usize,
    /// `skin_weight * ln 10`.
    weight: f32,
    /// Leave out the least skin-like view when two or more others see the point.
    drop_worst: bool,
}

impl SkinTerm<'_> {
    /// `weight * sum over the other views of their clamped log ratio at the point's pixel`
    /// ([`SkinTerm::log_weights`] of one point, in every lane; the paper's variant weighs
    /// its particles one at a time).
    #[inline(always)]
    fn log_weight(&self, pos: [f32; 3]) -> f32 {
        let lanes = pos.map(|axis| [axis; COST_LANES]);
        let mut out = [0f32; COST_LANES];
        self.log_weights(&lanes, &mut out);
        out[0]
    }

    /// The skin term of up to [`COST_LANES`] points (`pos[axis][lane]`), their projections
    /// across SIMD lanes: `weight * sum over the other views of their clamped log ratio at the
    /// point's pixel`. The reference view is left out: it sees the same pixel for every
    /// hypothesis of a ray, so it cannot change their relative weights. Views a point falls
    /// outside of say nothing.
    #[inline(always)]
    fn log_weights(&self, pos: &[[f32; COST_LANES]; 3], out: &mut [f32; COST_LANES]) {
        let (mut h, mut worst, mut seen) = ([0f32; COST_LANES], [f32::INFINITY; COST_LANES], [0u32; COST_LANES]);
        for (q, ((map, proj), cam)) in self.maps.iter().zip(self.projections).zip(self.cameras).enumerate() {
            if q == self.reference {
                continue;
            }
            let (mut u, mut v) = ([0f32; COST_LANES], [0f32; COST_LANES]);
            let in_front = proj.project_lanes(pos, &mut u, &mut v);
            let (width, height) = (cam.width as f32, cam.height as f32);
            for l in 0..COST_LANES {
                // Nearest pixel: for u, v > -0.5 truncating u + 0.5 rounds (and, unlike
                // `round`, needs no libm call without SSE4.1).
                let (x, y) = (u[l] + 0.5, v[l] + 0.5);
                if in_front[l] && x > 0.0 && y > 0.0 && x < width && y < height {
                    // A camera without a view this frame has an empty map and no say.
                    let Some(&hq) = map.get(y as usize * cam.width as usize + x as usize) else { continue };
                    h[l] += hq;
                    worst[l] = worst[l].min(hq);
                    seen[l] += 1;
                }
            }
        }
        for l in 0..COST_LANES {
            if self.drop_worst && seen[l] >= 2 {
                h[l] -= worst[l];
            }
            out[l] = self.weight * h[l];
        }
    }
}

crate::matching::isa::vectorised_fn! {
    /// One update of a ray holding particles, in the variant's formulation. Dispatched per
    /// occupied ray: the CPU check is a cached load against microseconds of matching.
    #[allow(clippy::too_many_arguments)]
    fn update_occupied_ray(
        ctx: &IterationContext<'_>,
        ray: usize,
        particles: &mut [Particle],
        count: &mut u8,
        scan: Option<Particle>,
        best: &mut Particle,
        estimate: &mut RayEstimate,
        memo: &mut NeighbourCosts,
    ) -> u64 {
        let have = usize::from(*count);
        let mut rng = RayRng::for_item(ctx.config.seed, ctx.frame, ctx.stage, ray as u64);
        match ctx.config.variant {
            Variant::Paper => ctx.update_ray_paper(ray, &mut particles[..have], best, estimate, &mut rng),
            Variant::Handflow => ctx.update_ray_handflow(ray, particles, count, scan, best, estimate, memo, &mut rng),
        }
    }
}

/// Share of each ray's particles drawn afresh from the broad prior when the posterior is
/// stale (more than [`MAX_SPANNED_GAP_FRAMES`] back). Measured on `signer-3cam` with 17
/// frame sets lost (30 fps): held with the usual share, a hand was followed 7-17 cm off for
/// five frames; with half drawn afresh, 6-7 cm off for two; the frame started cold instead
/// left the head 6-7 cm off for two frames at 8 fps (its depth settles over several frames
/// without extra passes).
pub const STALE_FRESH_SHARE: f32 = 0.5;

/// Most frame intervals the constant-velocity model spans, between the frames of a window
/// and between a posterior and the next frame estimated from it: a frame or two lost on
/// the way, while over longer gaps a hand's path bends too far for it (its miss grows
/// with the square of the gap). A farther neighbour is left out of the window, and a farther
/// posterior is held where it was with [`STALE_FRESH_SHARE`] of it drawn afresh.
pub const MAX_SPANNED_GAP_FRAMES: u64 = 3;

/// Candidates a ray weighs per iteration: its particles, four neighbours' best, exploration.
const MAX_CANDIDATES: usize = MAX_PARTICLES_PER_RAY + 8;

impl IterationContext<'_> {
    #[allow(clippy::too_many_arguments)]
    fn update_ray(
        &self,
        ray: usize,
        particles: &mut [Particle],
        count: &mut u8,
        scan: Option<Particle>,
        best: &mut Particle,
        estimate: &mut RayEstimate,
        memo: &mut NeighbourCosts,
    ) -> u64 {
        let have = usize::from(*count);
        if have == 0 {
            *best = Particle::EMPTY;
            if self.last {
                *estimate = RayEstimate::default();
            }
            return 0;
        }
        update_occupied_ray(self, ray, particles, count, scan, best, estimate, memo)
    }

    /// The paper: diffuse every particle, weight by equation 5 (the average of the
    /// normalised likelihood and the previous weight), resample the ray.
    #[inline(always)]
    fn update_ray_paper(
        &self,
        ray: usize,
        particles: &mut [Particle],
        best: &mut Particle,
        estimate: &mut RayEstimate,
        rng: &mut RayRng,
    ) -> u64 {
        let dir = self.dirs[ray];
        // The ray's pixel on this level: full-resolution pixel (x, y) sits at
        // ((x + 0.5) / 2^l - 0.5, ...) of level l.
        let (x, y) = ((ray % self.grid_width) as f32, (ray / self.grid_width) as f32);
        let reference_colour = if self.per_level_grid {
            self.reference_image.sample(x, y)
        } else {
            let scale = 1.0 / (1u32 << self.level) as f32;
            self.reference_image.sample((x + 0.5) * scale - 0.5, (y + 0.5) * scale - 0.5)
        };

        let mut cands = [Particle::EMPTY; MAX_PARTICLES_PER_RAY];
        let mut likelihood = [0f32; MAX_PARTICLES_PER_RAY];
        let n = particles.len();
        let mut total = 0.0;
        for k in 0..n {
            let p = self.space.diffuse(&particles[k], self.sigma_px, rng);
            let pos = point_on_ray(self.origin, dir, p.depth);
            let mut l = variance_likelihood(self.images, reference_colour, pos, p.velocity, self.config.epsilon);
            if let Some(skin) = &self.skin {
                l *= skin.log_weight(pos).exp();
            }
            cands[k] = Particle { cost: 1.0 / l, ..p };
            likelihood[k] = l;
            total += l;
        }
        let prior_total: f32 = cands[..n].iter().map(|p| p.weight).sum::<f32>().max(f32::MIN_POSITIVE);
        let mut weights = [0f32; MAX_PARTICLES_PER_RAY];
        let mut best_k = 0;
        for k in 0..n {
            weights[k] = 0.5 * (likelihood[k] / total + cands[k].weight / prior_total);
            cands[k].weight = weights[k];
            if weights[k] > weights[best_k] {
                best_k = k;
            }
        }
        *best = cands[best_k];
        if self.last {
            *estimate = weighted_mean(
                &cands[..n],
                &weights[..n],
                None,
                1.0 / cands[best_k].cost.max(1e-12) / (1.0 / self.config.epsilon),
            );
        }
        if !ray_resample(&cands[..n], &weights[..n], particles, rng) {
            particles.copy_from_slice(&cands[..n]);
        }
        n as u64
    }

    /// handflow: the ray's particles (the best kept as it is, the rest diffused), the best
    /// particle of each neighbour and a few random ones compete under the robust windowed
    /// cost and the velocity prior; the ray keeps N of them by systematic resampling, always
    /// including the best.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn update_ray_handflow(
        &self,
        ray: usize,
        particles: &mut [Particle],
        count: &mut u8,
        scan: Option<Particle>,
        best: &mut Particle,
        estimate: &mut RayEstimate,
        memo: &mut NeighbourCosts,
        rng: &mut RayRng,
    ) -> u64 {
        let n = self.config.particles_per_ray;
        let have = usize::from(*count);
        let dir = self.dirs[ray];
        let (x, y) = (ray % self.grid_width, ray / self.grid_width);
        let radius = if self.level == 0 { self.config.window_radius } else { self.config.coarse_window_radius };
        // `handflow` rays live on this level's grid; `paper` rays are full-resolution pixels.
        let step = self.config.window_step;
        let reference = if !self.per_level_grid {
            ReferenceWindow::gather(self.reference_image, x >> self.level, y >> self.level, radius, step)
        } else if self.grid_level == self.level {
            ReferenceWindow::gather(self.reference_image, x, y, radius, step)
        } else {
            // A coarser grid's pixel centre on this level (the pyramid's centre convention).
            let s = (1u32 << (self.grid_level - self.level)) as f32;
            let (u, v) = ((x as f32 + 0.5) * s - 0.5, (y as f32 + 0.5) * s - 0.5);
            ReferenceWindow::gather_at(self.reference_image, u, v, radius, step)
        };
        let mut cands = [Particle::EMPTY; MAX_CANDIDATES];
        let mut m = 0;
        // The previous best survives undiffused (elitism): a ray never loses its best
        // hypothesis to a random step.
        let elite = if self.best_prev[ray].is_valid() { self.best_prev[ray] } else { particles[0] };
        cands[m] = elite;
        m += 1;
        for p in particles.iter().take(have).skip(1) {
            cands[m] = self.space.diffuse(p, self.sigma_px, rng);
            m += 1;
        }
        if have == 1 {
            cands[m] = self.space.diffuse(&particles[0], self.sigma_px, rng);
            m += 1;
        }
        // Neighbour bests: candidates for propagation and, through their per-component
        // median, the consensus velocity of the smoothness term.
        let mut consensus: Option<[f32; 3]> = None;
        let mut neighbours_from = m;
        if self.config.propagation {
            let (w, h) = (self.grid_width, self.grid_height);
            // The neighbour the sweep comes from is offered as updated this iteration
            // (`scan`), so its previous best is not offered again.
            let neighbours = [
                (x > 0 && self.sweep != Sweep::Rows { reverse: false }).then(|| ray - 1),
                (x + 1 < w && self.sweep != Sweep::Rows { reverse: true }).then(|| ray + 1),
                (y > 0 && self.sweep != Sweep::Columns { reverse: false }).then(|| ray - w),
                (y + 1 < h && self.sweep != Sweep::Columns { reverse: true }).then(|| ray + w),
            ];
            let previous = neighbours.into_iter().flatten().map(|nb| self.best_prev[nb]);
            let first = m;
            neighbours_from = first;
            for b in previous.chain(scan) {
                if b.is_valid() {
                    cands[m] = b;
                    m += 1;
                }
            }
            if m - first >= 2 && self.config.smoothness_px > 0.0 && self.level == 0 {
                consensus = Some(std::array::from_fn(|k| {
                    let mut vals = [0f32; 5];
                    let count = m - first;
                    for (slot, c) in vals.iter_mut().zip(&cands[first..m]) {
                        *slot = c.velocity[k];
                    }
                    let vals = &mut vals[..count];
                    vals.sort_unstable_by(f32::total_cmp);
                    if count % 2 == 1 {
                        vals[count / 2]
                    } else {
                        0.5 * (vals[count / 2 - 1] + vals[count / 2])
                    }
                }));
            }
        }
        let neighbours_to = m;
        if self.top_level {
            for _ in 0..self.config.exploration_particles {
                cands[m] = self.space.random_particle(rng);
                m += 1;
            }
        }
        let mut log_w = [0f32; MAX_CANDIDATES];
        let prior_scale = 1.0 / (2.0 * (self.config.velocity_prior * self.config.speed_bound).powi(2));
        let prior_scale_depth = 1.0 / (2.0 * (self.config.velocity_prior_depth * self.config.speed_bound).powi(2));
        let sight = self.optical_axis;
        let inv_t = 1.0 / self.config.temperature;
        let mut best_k = 0;
        // The elite (slot 0) kept its cost from the previous loop on this level.
        let elite_known = self.elite_cost_valid && self.best_prev[ray].is_valid() && cands[0].cost.is_finite();
        // The last loop's neighbour costs hold on this loop's images only on the same level.
        let memo_known = self.elite_cost_valid && memo.is_from_loop_before(self.loop_stamp);
        // Where each candidate's cost comes from. A neighbour's best is often the very
        // hypothesis this ray already holds (a good one spreads by propagation): the same
        // depth and velocity on the same ray cost the same, so it is evaluated once and its
        // cost copied, bit for bit. The rest are evaluated together, a batch of SIMD lanes.
        let mut copy_of = [usize::MAX; MAX_CANDIDATES];
        let mut batch = CandidateBatch::default();
        let mut evaluations = 0u64;
        for k in 0..m {
            if k == 0 && elite_known {
                continue;
            }
            if let Some(j) = (0..k).find(|&j| same_hypothesis(&cands[j], &cands[k])) {
                copy_of[k] = j;
                continue;
            }
            let from_neighbour = memo_known && (neighbours_from..neighbours_to).contains(&k);
            if let Some(cost) = from_neighbour.then(|| memo.cost_of(&cands[k])).flatten() {
                cands[k].cost = cost;
                continue;
            }
            evaluations += 1;
            if batch.push(k, point_on_ray(self.origin, dir, cands[k].depth), cands[k].velocity) {
                batch.cost_into(self, &reference, &mut cands);
            }
        }
        batch.cost_into(self, &reference, &mut cands);
        for k in 0..m {
            if copy_of[k] != usize::MAX {
                // The earlier candidate's cost is final: copies point backwards.
                cands[k].cost = cands[copy_of[k]].cost;
            }
        }
        // The skin term of every candidate, a batch of SIMD lanes at a time.
        let mut skin_log_w = [0f32; MAX_CANDIDATES];
        if let Some(skin) = &self.skin {
            for (from, chunk) in skin_log_w[..m].chunks_mut(COST_LANES).enumerate() {
                let first = from * COST_LANES;
                // Lanes past the candidates repeat the first one; their weights are dropped.
                // A plain loop: `array::from_fn` here was not inlined (so not built for AVX2).
                let mut points = [[0f32; 3]; COST_LANES];
                for (l, point) in points.iter_mut().enumerate() {
                    let k = if l < chunk.len() { first + l } else { first };
                    *point = point_on_ray(self.origin, dir, cands[k].depth);
                }
                let mut lanes = [[0f32; COST_LANES]; 3];
                for (axis, row) in lanes.iter_mut().enumerate() {
                    for (slot, point) in row.iter_mut().zip(&points) {
                        *slot = point[axis];
                    }
                }
                let mut out = [0f32; COST_LANES];
                skin.log_weights(&lanes, &mut out);
                chunk.copy_from_slice(&out[..chunk.len()]);
            }
        }
        for k in 0..m {
            let p = &cands[k];
            let v = p.velocity;
            let along = v[0] * sight[0] + v[1] * sight[1] + v[2] * sight[2];
            let across_sq = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2] - along * along).max(0.0);
            log_w[k] = -p.cost * inv_t - across_sq * prior_scale - along * along * prior_scale_depth;
            if self.skin.is_some() {
                log_w[k] += skin_log_w[k];
            }
            if let Some(c) = consensus {
                // Truncated quadratic: smooth within a surface, free across a motion edge.
                let sigma = self.config.smoothness_px * p.depth / self.space.focal_px;
                let d = [v[0] - c[0], v[1] - c[1], v[2] - c[2]];
                let e = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) / (2.0 * sigma * sigma);
                log_w[k] -= e.min(self.config.smoothness_cap);
            }
            if log_w[k] > log_w[best_k] {
                best_k = k;
            }
        }
        memo.remember(&cands[neighbours_from..neighbours_to], self.loop_stamp);
        let mut weights = [0f32; MAX_CANDIDATES];
        for k in 0..m {
            weights[k] = (log_w[k] - log_w[best_k]).exp();
        }
        *best = cands[best_k];
        if self.last {
            let confidence = (-cands[best_k].cost * inv_t * 0.5).exp();
            *estimate = if self.config.mean_estimate {
                weighted_mean(&cands[..m], &weights[..m], Some(&cands[best_k]), confidence.max(1e-6))
            } else {
                weighted_mean(&cands[best_k..=best_k], &[1.0], None, confidence.max(1e-6))
            };
        }
        particles[0] = cands[best_k];
        particles[0].weight = 1.0 / n as f32;
        if !ray_resample(&cands[..m], &weights[..m], &mut particles[1..n], rng) {
            for slot in particles[1..n].iter_mut() {
                *slot = cands[best_k];
            }
        }
        for p in particles[..n].iter_mut() {
            p.weight = 1.0 / n as f32;
        }
        *count = n as u8;
        evaluations
    }
}

/// The weighted mean of a ray's particles (the note on the prototype found it beats the
/// single best particle). With `mode` given, only particles within about a pixel of that
/// particle take part, so two separated modes are not averaged into a point between them.
#[inline(always)]
fn weighted_mean(particles: &[Particle], weights: &[f32], mode: Option<&Particle>, confidence: f32) -> RayEstimate {
    let mut sum_w = 0.0f32;
    let mut inverse = 0.0f32;
    let mut vel = [0.0f32; 3];
    for (p, &w) in particles.iter().zip(weights) {
        if let Some(m) = mode {
            let rel_depth = (p.depth - m.depth).abs() / m.depth;
            let dv = (p.velocity[0] - m.velocity[0]).abs()
                + (p.velocity[1] - m.velocity[1]).abs()
                + (p.velocity[2] - m.velocity[2]).abs();
            // ~1% of depth is about a pixel of disparity at the far end of typical rigs;
            // velocities compare at the same relative scale.
            if rel_depth > 0.02 || dv > 0.02 * m.depth.max(1e-3) {
                continue;
            }
        }
        sum_w += w;
        inverse += w / p.depth;
        for (acc, v) in vel.iter_mut().zip(p.velocity) {
            *acc += w * v;
        }
    }
    if sum_w.is_nan() || sum_w <= 0.0 {
        return RayEstimate::default();
    }
    RayEstimate {
        inverse_depth: inverse / sum_w,
        velocity: vel.map(|v| v / sum_w),
        confidence: confidence.clamp(1e-6, 1.0),
    }
}

/// Dense mode: an empty ray copies the particles of a random non-empty ray within a few
/// pixels. Returns how many particles were copied.
#[allow(clippy::too_many_arguments)]
fn refill_from_neighbours(
    src: &[Particle],
    counts: &[u8],
    n: usize,
    w: usize,
    h: usize,
    ray: usize,
    out: &mut [Particle],
    rng: &mut RayRng,
) -> usize {
    let (x, y) = ((ray % w) as isize, (ray / w) as isize);
    for radius in 1..=4isize {
        for _ in 0..8 {
            let nx = x + (rng.uniform() * (2 * radius + 1) as f32) as isize - radius;
            let ny = y + (rng.uniform() * (2 * radius + 1) as f32) as isize - radius;
            if nx < 0 || ny < 0 || nx >= w as isize || ny >= h as isize {
                continue;
            }
            let from = ny as usize * w + nx as usize;
            let c = usize::from(counts[from]);
            if c > 0 {
                out[..c].copy_from_slice(&src[from * n..from * n + c]);
                return c;
            }
        }
    }
    0
}

/// The pyramid level whose pixel grid the finest rays (and the [`DenseField`]) live on.
fn finest_ray_level(config: &EngineConfig) -> usize {
    config.finest_level + config.ray_subsampling
}

/// Rays of the reference camera through the pixel centres of pyramid level `level`; only
/// the grid's size unless `with_rays`.
fn ray_grid(camera: &Camera, level: usize, with_rays: bool) -> RayGrid {
    let s = 1usize << level;
    let width = (camera.width as usize).div_ceil(s).max(1);
    let height = (camera.height as usize).div_ceil(s).max(1);
    let rotation_t = camera.rotation.matrix().transpose();
    let mut dirs = Vec::with_capacity(if with_rays { width * height } else { 0 });
    for j in (0..height).take_while(|_| with_rays) {
        for i in 0..width {
            // Level pixel centre in full-resolution coordinates.
            let u = (i as f64 + 0.5) * s as f64 - 0.5;
            let v = (j as f64 + 0.5) * s as f64 - 0.5;
            let xn = camera.pixel_to_normalised(&Point2::new(u, v));
            let d = rotation_t * nalgebra::Vector3::new(xn.x, xn.y, 1.0);
            dirs.push([d.x as f32, d.y as f32, d.z as f32]);
        }
    }
    RayGrid { width, height, dirs }
}

/// Whether world point `p` lies in front of the camera of `projection` and inside its
/// `width` x `height` image (pixel centres at integers).
fn in_image(projection: &LevelProjection, width: u32, height: u32, p: [f32; 3]) -> bool {
    projection.to_camera(p)[2] > 0.0
        && projection
            .project(p)
            .is_some_and(|[u, v]| u >= -0.5 && v >= -0.5 && u < width as f32 - 0.5 && v < height as f32 - 0.5)
}

/// Candidates of one ray waiting for their costs, one SIMD lane each.
#[derive(Default)]
struct CandidateBatch {
    slots: [usize; COST_LANES],
    position: [[f32; COST_LANES]; 3],
    velocity: [[f32; COST_LANES]; 3],
    len: usize,
}

impl CandidateBatch {
    /// Adds candidate `slot`; true when the batch is full.
    #[inline(always)]
    fn push(&mut self, slot: usize, position: [f32; 3], velocity: [f32; 3]) -> bool {
        let l = self.len;
        self.slots[l] = slot;
        for axis in 0..3 {
            self.position[axis][l] = position[axis];
            self.velocity[axis][l] = velocity[axis];
        }
        self.len += 1;
        self.len == COST_LANES
    }

    /// Evaluates the waiting candidates into their slots of `cands` and empties the batch.
    #[inline(always)]
    fn cost_into(&mut self, ctx: &IterationContext<'_>, reference: &ReferenceWindow, cands: &mut [Particle]) {
        if self.len == 0 {
            return;
        }
        let mut costs = [0f32; COST_LANES];
        robust_window_costs(
            ctx.images,
            reference,
            &self.position,
            &self.velocity,
            self.len,
            ctx.config.truncation,
            ctx.keep,
            &mut costs,
        );
        for (&slot, &cost) in self.slots[..self.len].iter().zip(&costs) {
            cands[slot].cost = cost;
        }
        self.len = 0;
    }
}

#[inline(always)]
fn point_on_ray(origin: [f32; 3], dir: [f32; 3], depth: f32) -> [f32; 3] {
    [origin[0] + depth * dir[0], origin[1] + depth * dir[1], origin[2] + depth * dir[2]]
}

#[inline(always)]
fn add(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

fn scale(a: [f32; 3], k: f32) -> [f32; 3] {
    [a[0] * k, a[1] * k, a[2] * k]
}

#[cfg(test)]
mod tests {
    use super::*;
    use handflow_protocol::Distortion;
    use nalgebra::{Matrix3, Rotation3, Vector3};

    pub(super) fn camera(name: &str, x: f64) -> Camera {
        let k = Matrix3::new(50.0, 0.0, 15.5, 0.0, 50.0, 11.5, 0.0, 0.0, 1.0);
        Camera::new(name, 32, 24, k, Distortion::default(), Rotation3::identity(), Vector3::new(-x, 0.0, 0.0))
            .expect("valid camera")
    }

    #[test]
    fn each_ray_marks_skin_as_every_pixel_marked_and_halved_level_by_level_would() {
        // An odd-sized view, so grids round up at every level; some pixels vetoed.
        let k = Matrix3::new(50.0, 0.0, 18.0, 0.0, 50.0, 14.0, 0.0, 0.0, 1.0);
        let cam = |name: &str, x: f64| {
            Camera::new(name, 37, 29, k, Distortion::default(), Rotation3::identity(), Vector3::new(-x, 0.0, 0.0))
                .expect("valid camera")
        };
        let (w, h) = (37usize, 29usize);
        // Skin in the top-left corner only, whole in its first 8x8 pixels and scattered
        // beyond: every grid mixes rays on and off skin.
        let map: Vec<f32> = (0..w * h)
            .map(|i| match (i % w, i / w) {
                (x, y) if x < 8 && y < 8 => 2.0,
                (x, y) if x < 14 && y < 11 => ((i as f32 * 0.61).sin() * 3.0).powi(3),
                _ => -1.0,
            })
            .collect();
        let veto: Vec<bool> = (0..w * h).map(|i| i % 7 == 3 && i % w >= 8).collect();
        for (finest_level, ray_subsampling, share) in [(0, 0, 1.0), (0, 1, 0.5), (1, 1, 1.0), (1, 1, 0.0), (0, 2, 0.3)]
        {
            let config = EngineConfig {
                coverage: Coverage::Skin,
                pyramid_levels: 4,
                finest_level,
                ray_subsampling,
                skin_footprint_share: share,
                ..EngineConfig::default()
            };
            let mut engine = SceneFlowEngine::new(config, vec![cam("ref", 0.0), cam("b", 0.2)], 0).unwrap();
            engine.skin_maps[0] = vec![map.clone(), Vec::new()];
            engine.veto = veto.clone();
            engine.update_active(0);
            // Every pixel marked, each level the any of the finer one's 2x2 (clamped), then
            // the finest ray grid by the share of its block's pixels.
            let skin = |i: usize| map[i] > engine.config.skin_threshold && !veto[i];
            let mut chain: Vec<Vec<bool>> = vec![(0..w * h).map(skin).collect()];
            for l in 1..4 {
                let (fw, fh) = (engine.grids[l - 1].width, engine.grids[l - 1].height);
                let (cw, ch) = (engine.grids[l].width, engine.grids[l].height);
                let finer = &chain[l - 1];
                let level: Vec<bool> = (0..cw * ch)
                    .map(|r| {
                        let (x0, y0) = (2 * (r % cw), 2 * (r / cw));
                        (y0..(y0 + 2).min(fh)).any(|y| (x0..(x0 + 2).min(fw)).any(|x| finer[y * fw + x]))
                    })
                    .collect();
                chain.push(level);
            }
            let level = finest_level + ray_subsampling;
            if level > 0 && share > 0.0 {
                let (cw, s) = (engine.grids[level].width, 1usize << level);
                for (ray, a) in chain[level].iter_mut().enumerate() {
                    let (x0, y0) = ((ray % cw) * s, (ray / cw) * s);
                    let (xs, ys) = (x0..(x0 + s).min(w), y0..(y0 + s).min(h));
                    let pixels = xs.len() * ys.len();
                    let count = ys.flat_map(|y| xs.clone().map(move |x| y * w + x)).filter(|&i| skin(i)).count();
                    *a = count > 0 && count as f32 >= share * pixels as f32;
                }
            }
            for (l, want) in chain.iter().enumerate().skip(level) {
                assert_eq!(engine.active[l], *want, "level {l} of {finest_level} + {ray_subsampling}, share {share}");
                assert!(
                    want.iter().any(|&a| a) && !want.iter().all(|&a| a),
                    "level {l} of {finest_level} + {ray_subsampling}, share {share}: mixes skin and not"
                );
            }
        }
    }

    /// A 32x24 RGB view of a texture moved `shift` pixels to the right.
    pub(super) fn textured_view(shift: usize, seed: u32) -> Vec<u8> {
        (0..24 * 32)
            .flat_map(|i| {
                let (x, y) = ((i % 32 + 64 - shift) as u32, (i / 32) as u32);
                let v =
                    (x.wrapping_mul(2_654_435_761) ^ y.wrapping_mul(40_503) ^ seed).wrapping_mul(2_246_822_519) >> 24;
                [v as u8, (v as u8).wrapping_mul(3), 255 - v as u8]
            })
            .collect()
    }

    #[test]
    fn a_camera_missing_from_every_set_is_as_if_the_rig_had_no_such_camera() {
        let three = vec![camera("ref", 0.0), camera("a", 0.1), camera("gone", -0.1)];
        let config = EngineConfig { pyramid_levels: 2, coarse_extra_loops: 2, ..EngineConfig::default() };
        let mut partial = SceneFlowEngine::new(config.clone(), three.clone(), 0).unwrap();
        let mut whole = SceneFlowEngine::new(config, three[..2].to_vec(), 0).unwrap();
        let black = vec![0u8; 32 * 24 * 3];
        for f in 0..3 {
            let (r, a) = (textured_view(f, 1), textured_view(f + 2, 1));
            let with_gap = partial.push_frame_partial(&[&r, &a, &black], 0b100).unwrap().cloned();
            let without = whole.push_frame(&[&r, &a]).unwrap().cloned();
            assert_eq!(with_gap.is_some(), without.is_some());
            if let (Some(x), Some(y)) = (with_gap, without) {
                assert_eq!(x.depth, y.depth, "frame {f}");
                assert_eq!(x.velocity, y.velocity, "frame {f}");
                assert_eq!(x.confidence, y.confidence, "frame {f}");
            }
        }
        let e = partial.push_frame_partial(&[&black, &black, &black], 0b001).unwrap_err().to_string();
        assert!(e.contains("reference camera `ref`"), "{e}");
    }

    /// Skin term over a reference and two other views whose skin maps are uniform.
    fn log_weight(others: [f32; 2], drop_worst: bool) -> f32 {
        let cameras = vec![camera("ref", 0.0), camera("a", 0.2), camera("b", -0.2)];
        let maps = vec![vec![5.0; 32 * 24], vec![others[0]; 32 * 24], vec![others[1]; 32 * 24]];
        let projections: Vec<LevelProjection> = cameras.iter().map(|c| LevelProjection::new(c, 0)).collect();
        let term = SkinTerm {
            maps: &maps,
            projections: &projections,
            cameras: &cameras,
            reference: 0,
            weight: 1.0,
            drop_worst,
        };
        term.log_weight([0.0, 0.0, 3.0])
    }

    #[test]
    fn the_skin_term_leaves_out_the_reference_and_optionally_the_least_skin_like_view() {
        assert_eq!(log_weight([1.0, -2.0], false), -1.0, "the sum over the other views");
        // An occluder in front of the skin in one view: that view's verdict is dropped.
        assert_eq!(log_weight([1.0, -2.0], true), 1.0);
        assert_eq!(log_weight([-1.0, 0.5], true), 0.5);
    }

    #[test]
    fn with_a_single_other_view_nothing_is_dropped() {
        let cameras = vec![camera("ref", 0.0), camera("a", 0.2)];
        let maps = vec![vec![5.0; 32 * 24], vec![-2.0; 32 * 24]];
        let projections: Vec<LevelProjection> = cameras.iter().map(|c| LevelProjection::new(c, 0)).collect();
        let term = SkinTerm {
            maps: &maps,
            projections: &projections,
            cameras: &cameras,
            reference: 0,
            weight: 2.0,
            drop_worst: true,
        };
        assert_eq!(term.log_weight([0.0, 0.0, 3.0]), -4.0);
        // Behind the cameras: no view sees it, no evidence.
        assert_eq!(term.log_weight([0.0, 0.0, -3.0]), 0.0);
    }

    /// The skin term of one point, view by view: the oracle the lanes are checked against.
    fn skin_term_one_point_at_a_time(term: &SkinTerm<'_>, pos: [f32; 3]) -> f32 {
        let (mut h, mut worst, mut seen) = (0.0, f32::INFINITY, 0);
        for (q, ((map, proj), cam)) in term.maps.iter().zip(term.projections).zip(term.cameras).enumerate() {
            if q == term.reference {
                continue;
            }
            let Some([u, v]) = proj.project(pos) else { continue };
            let (x, y) = (u + 0.5, v + 0.5);
            if x > 0.0 && y > 0.0 && x < cam.width as f32 && y < cam.height as f32 {
                let Some(&hq) = map.get(y as usize * cam.width as usize + x as usize) else { continue };
                h += hq;
                worst = worst.min(hq);
                seen += 1;
            }
        }
        if term.drop_worst && seen >= 2 {
            h -= worst;
        }
        term.weight * h
    }

    #[test]
    fn the_skin_term_of_a_batch_is_each_points_to_the_bit() {
        let cameras = vec![camera("ref", 0.0), camera("a", 0.2), camera("b", -0.2)];
        // Maps that vary per pixel, so every lane reads its own values.
        let map = |seed: f32| (0..32 * 24).map(|i| ((i as f32 + seed) * 0.37).sin() * 3.0).collect::<Vec<f32>>();
        let maps = vec![map(0.0), map(5.0), map(9.0)];
        let projections: Vec<LevelProjection> = cameras.iter().map(|c| LevelProjection::new(c, 0)).collect();
        for drop_worst in [false, true] {
            let term = SkinTerm {
                maps: &maps,
                projections: &projections,
                cameras: &cameras,
                reference: 0,
                weight: 1.7,
                drop_worst,
            };
            // Seen by both other views, by one, by none (outside, behind).
            let points: [[f32; 3]; COST_LANES] = [
                [0.0, 0.0, 3.0],
                [0.1, -0.05, 2.0],
                [-0.2, 0.1, 4.0],
                [0.9, 0.0, 2.0],
                [-0.9, 0.0, 2.0],
                [5.0, 5.0, 1.0],
                [0.0, 0.0, -3.0],
                [0.05, 0.02, 2.5],
            ];
            let lanes = std::array::from_fn(|axis| std::array::from_fn(|l| points[l][axis]));
            let mut out = [0f32; COST_LANES];
            term.log_weights(&lanes, &mut out);
            for (l, p) in points.iter().enumerate() {
                let want = skin_term_one_point_at_a_time(&term, *p);
                assert_eq!(out[l].to_bits(), want.to_bits(), "lane {l}, drop_worst {drop_worst}");
                assert_eq!(term.log_weight(*p).to_bits(), want.to_bits(), "one point, drop_worst {drop_worst}");
            }
            assert!(out[0] != out[1] && out[6] == 0.0, "{out:?}");
        }
    }
}
