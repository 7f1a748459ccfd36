//! Every parameter of the engine, in one place, with its default and the reason for it.

use serde::{Deserialize, Serialize};

/// Which formulation of Scene Particles runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Variant {
    /// The paper's method as written (sections 2.2, 4, 4.1): per-pixel colour variance
    /// likelihood, equation 5 weights, ray resampling, coarse-to-fine diffusion. A reference.
    Paper,
    /// The default: the same particle filter with spatial coupling and robust matching (see
    /// the README's engine section for each choice and its measured effect).
    #[default]
    Handflow,
}

impl Variant {
    /// The name used on the command line and in JSON.
    pub fn name(self) -> &'static str {
        match self {
            Variant::Paper => "paper",
            Variant::Handflow => "handflow",
        }
    }
}

impl std::str::FromStr for Variant {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "paper" => Ok(Variant::Paper),
            "handflow" => Ok(Variant::Handflow),
            other => Err(format!("unknown variant `{other}` (expected `handflow` or `paper`)")),
        }
    }
}

/// How many frames the likelihood looks at.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum Temporal {
    /// Equation 3: frames t-1 and t; an estimate as soon as frame t arrives.
    #[default]
    TwoFrame,
    /// Equation 6: frames t-1, t and t+1; estimates are one frame late.
    ForwardsBackwards,
}

/// What happens to rays that hold no particle.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Coverage {
    /// Empty rays are refilled from neighbouring rays (complete coverage, for evaluation).
    #[default]
    Dense,
    /// Empty rays stay empty (a sparse motion field is all trajectories need).
    Sparse,
    /// Particles are seeded and kept only on rays whose colour in the reference view is
    /// skin (the skin model's clamped log ratio above `skin_threshold`), and the skin term
    /// of equation 4 weighs every hypothesis: on a signer this is a few percent of the rays.
    Skin,
}

/// Configuration of [`crate::SceneFlowEngine`]. `Default` is the `handflow` variant;
/// [`EngineConfig::paper`] is the paper's method.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct EngineConfig {
    /// Formulation (default `handflow`).
    pub variant: Variant,
    /// Two-frame or forwards/backwards likelihood (default two-frame).
    pub temporal: Temporal,
    /// Dense or sparse ray coverage (default dense).
    pub coverage: Coverage,
    /// Scene Particles per ray of the reference camera (default 10, as in the paper; at most
    /// [`MAX_PARTICLES_PER_RAY`]).
    pub particles_per_ray: usize,
    /// Pyramid levels, coarse to fine (default 3, as in the paper).
    pub pyramid_levels: usize,
    /// Noise loops per level with shrinking diffusion (3 in `paper`, as in the paper; 2 in
    /// `handflow`, which spends its iterations on the cheap coarsest level instead, see
    /// `coarse_extra_loops`: measured on Teddy, 2 + 7 coarse loops beat 3 + 6 in accuracy
    /// and take 20% less time).
    pub noise_loops: usize,
    /// Extra noise loops on the coarsest level (default 7; 0 in `paper`): the coarse grid
    /// is 16x smaller than the fine one, so these cost a few percent of a frame and let
    /// hypotheses spread across the image before refinement.
    pub coarse_extra_loops: usize,
    /// Extra coarsest-level loops when the previous frame's posterior is the prior (default
    /// `None`: as `coarse_extra_loops`). A stream can afford fewer: the carried posterior
    /// already holds most of what the exploration of a first frame finds.
    pub warm_coarse_extra_loops: Option<usize>,
    /// Extra passes over a frame estimated without a temporal prior (the first of a
    /// stream), each taking the previous pass's posterior as its prior, held still (default
    /// 0). A stream's later frames inherit several frames of evidence through the carried
    /// posterior; these passes give the first frame some of it, so a trajectory does not
    /// start from a half-converged depth.
    pub cold_start_passes: usize,
    /// With forwards/backwards, also estimate a stream's first frame, from it and the next
    /// alone (it has no t-1), as soon as the next arrives (default false: the published
    /// method's first estimate is of the second frame). Streams set it: a trajectory then
    /// starts at the first frame. The second frame still starts afresh on all three.
    pub estimate_first_frame: bool,
    /// Rays of each pyramid level on that level's own pixel grid (true), or full-resolution
    /// rays on every level, coarse levels only blurring the images (false). The paper does
    /// not say which; coarse-to-fine hand-over copies a coarse ray's particles to the four
    /// finer rays it covers. Default true in both variants.
    pub per_level_rays: bool,
    /// Finest pyramid level estimated (default 0, full resolution). At 1 the rays are those
    /// of the half-resolution grid, a quarter as many: enough points for trajectories at a
    /// quarter of the work. Needs `per_level_rays`.
    pub finest_level: usize,
    /// Rays on the finest level are `2^ray_subsampling` pixels apart (default 0, one per
    /// pixel). At 1 the finest level's images are matched from the rays of the next coarser
    /// grid: a quarter of the rays keep the finer images' detail, which is what separates a
    /// hand from what is behind it, while the trajectories need far fewer points than
    /// pixels. Needs `per_level_rays`; `finest_level + ray_subsampling` must be a level.
    /// Streams choose it from the expected palm size (`stream::ray_subsampling`).
    pub ray_subsampling: usize,
    /// Seed of every random draw (default 0). Same seed, same result, any thread count.
    pub seed: u64,
    /// Camera-frame depth range of the reference camera, world units (near, far).
    pub depth_range: (f32, f32),
    /// Symmetric bound on each velocity component, world units per frame.
    pub speed_bound: f32,
    /// Equation 3's epsilon (default 0.001, as in the paper).
    pub epsilon: f32,
    /// Diffusion at the first noise loop of a level, in pixels of that level (default 1.0):
    /// the note on the prototype found a diffusion tied to the level's pixel size beats a
    /// fixed one, and a step of about one pixel matches the basin of the likelihood.
    pub diffusion_px: f32,
    /// Factor applied to the diffusion at each further noise loop (default 0.5).
    pub diffusion_shrink: f32,
    /// `handflow`: half-size of the square support window of the matching cost, in pixels of
    /// the full-resolution level (default 1, a 3x3 window; 0 is a single pixel; at most 2).
    pub window_radius: usize,
    /// `handflow`: radius of the local contrast normalisation of the images matched on
    /// (default 3, a 7x7 neighbourhood; 0 matches on the globally normalised images). Weak
    /// texture (a painted wall, cloth) otherwise barely moves the cost: on Teddy a wrong
    /// velocity cost less than 10% more than the right one with global normalisation only.
    pub local_normalisation_radius: usize,
    /// `handflow`: noise floor of the local normalisation, normalised units (default 0.05,
    /// about two grey levels of an 8-bit image with typical contrast).
    pub local_normalisation_floor: f32,
    /// `handflow`: per-channel colour difference (normalised units) beyond which a sample
    /// counts as an outlier (truncated L1; default 1.0, one standard deviation of the image).
    pub truncation: f32,
    /// `handflow`: share of the other images whose costs are summed, best first (default
    /// 0.6): an image where the point is occluded or outside must not spoil it.
    pub view_keep_fraction: f32,
    /// `handflow`: temperature of the likelihood `exp(-cost / T)` (default 0.1, about the
    /// matching cost of a correct match on locally normalised images; the paper's `1/var`
    /// keeps half the weight of a twice worse hypothesis, which is too weak to select).
    pub temperature: f32,
    /// `handflow`: offer every ray the best particle of its four neighbours at each
    /// iteration (default true): spatial coupling without smoothing across edges, as the
    /// neighbour's hypothesis survives only if it explains this ray's pixels.
    pub propagation: bool,
    /// `handflow`: random fresh particles offered to every ray per iteration on the
    /// coarsest level (default 1), so the filter keeps exploring.
    pub exploration_particles: usize,
    /// `handflow`: standard deviation of a zero-mean Gaussian prior on each velocity
    /// component across the view, as a fraction of `speed_bound` (default 1.0: weak, it only
    /// breaks ties; a strong one measurably drags estimates towards zero motion).
    pub velocity_prior: f32,
    /// `handflow`: the same prior for motion in depth (the velocity component along the
    /// reference camera's optical axis), as a fraction of `speed_bound` (default 0.1).
    /// Motion in depth moves projections by baseline/depth as much as motion across the
    /// view, so with a narrow rig the images leave a valley of velocities (across-view and
    /// in-depth traded against each other) nearly equally good; a zero-mean isotropic prior
    /// then slides every estimate down that valley towards slower, wrongly oriented motion.
    /// Pinning motion in depth instead picks the across-view solution unless the images
    /// clearly say otherwise.
    pub velocity_prior_depth: f32,
    /// `handflow`: half-size of the support window on the coarser levels (default 2, 5x5):
    /// coarse levels are 4-16x cheaper, and a wider support there resolves repetitive or
    /// weak texture before the full-resolution levels refine it with `window_radius`.
    pub coarse_window_radius: usize,
    /// `handflow`: sample spacing of the support window, pixels of the level (default 1).
    /// A spacing of 2 covers a twice wider window at the same cost.
    pub window_step: usize,
    /// `handflow`: scale of the velocity smoothness term, as the image displacement (pixels
    /// at the particle's depth) at which a velocity differing from the median of the
    /// neighbours' best velocities loses 1/e of its weight (default 0, off; applies on the
    /// full-resolution level only). Measured on Teddy it did not help (see the ablation
    /// table): propagation and the weighted median already couple neighbours.
    pub smoothness_px: f32,
    /// `handflow`: cap of the smoothness penalty in log-weight units (default 2.0): beyond
    /// it a motion edge costs no more, so discontinuities are kept.
    pub smoothness_cap: f32,
    /// `handflow`: per-ray estimate as the weighted mean of the candidates near the best one
    /// (true, default) or the best particle alone (false). The mean is slightly better on
    /// both Teddy layouts (see the ablation table), as the prototype note also found.
    pub mean_estimate: bool,
    /// `handflow`: radius of the edge-preserving weighted median applied to the per-ray
    /// estimate at full resolution (default 4, a 9x9 window; 0 disables it; at most 4).
    pub refine_radius: usize,
    /// `handflow`: colour distance (normalised units) at which a neighbour's vote in the
    /// weighted median falls to 1/e (default 0.3).
    pub refine_colour_sigma: f32,
    /// `skin` coverage: weight of the skin term of equation 4 in a particle's log-weight
    /// (default 1.0): the likelihood is multiplied by `10^(skin_weight * h)`, with `h` the
    /// sum over views of the clamped log10 skin ratio of the colour each view sees at the
    /// particle at time t. At 1 this is the product over views of the skin likelihood ratio
    /// `min(Ps/Pbg, 10^alpha)`: a depth where one view sees background instead of skin
    /// loses as much weight as that view's evidence says. 0 turns the factor off (rays are
    /// still chosen by skin colour).
    pub skin_weight: f32,
    /// `skin` coverage, `handflow`: leave the least skin-like view out of `h` when two or
    /// more views other than the reference see the point (default true; false in `paper`).
    /// A hand hidden from one camera shows that camera the body in front of it: summed
    /// over all views, that occluder's verdict outweighs the others' at the true depth and
    /// pulls the hand to a ghost depth where every view happens to see skin (measured on
    /// `occluded-side`: the right hand 43 % tracked with it, 97 % without).
    pub skin_drop_worst_view: bool,
    /// `skin` coverage: a reference-view pixel is skin when its clamped log10 skin ratio
    /// exceeds this (default 0: the skin model is the likelier).
    pub skin_threshold: f32,
    /// `skin` coverage: a ray of the finest ray grid holds particles only when at least
    /// this share of the full-resolution pixels it covers is skin (default 1: all of them;
    /// 0: any one, as on the coarser grids, which search). A ray straddling a silhouette
    /// matches a window that is partly background: its depth mixes the hand's with the
    /// wall's, and on a half-resolution grid such rays are a third of a small hand's. On a
    /// full-resolution grid a ray covers one pixel and this changes nothing. Measured on the
    /// shared real session, mean of three seeds: 1 against 0 put the head within 5 cm in 63
    /// instead of 45 % of frames, the right hand in 72 instead of 65 %; 0.75 gave 55 and 67
    /// (BENCHMARKS.md).
    pub skin_footprint_share: f32,
    /// Share of each ray's prior particles replaced by fresh random ones at a new frame when
    /// the previous posterior is carried over (default 0.2).
    pub fresh_fraction: f32,
    /// `skin` coverage: also cast rays from a second reference camera (the one looking
    /// from the most different direction, under 90 degrees, with three or more cameras) where
    /// the reference camera cannot see: its skin whose rays run mostly outside the
    /// reference view's image over the depth range. A hand below the reference view's image
    /// still gets points (default false).
    pub second_reference: bool,
}

/// Upper bound of [`EngineConfig::particles_per_ray`]: per-ray work happens in stack arrays.
pub const MAX_PARTICLES_PER_RAY: usize = 32;

impl Default for EngineConfig {
    fn default() -> Self {
        Self {
            variant: Variant::Handflow,
            temporal: Temporal::TwoFrame,
            coverage: Coverage::Dense,
            particles_per_ray: 10,
            pyramid_levels: 3,
            noise_loops: 2,
            coarse_extra_loops: 7,
            warm_coarse_extra_loops: None,
            cold_start_passes: 0,
            estimate_first_frame: false,
            per_level_rays: true,
            finest_level: 0,
            ray_subsampling: 0,
            seed: 0,
            depth_range: (0.5, 10.0),
            speed_bound: 0.1,
            epsilon: 0.001,
            diffusion_px: 1.0,
            diffusion_shrink: 0.5,
            window_radius: 1,
            local_normalisation_radius: 3,
            local_normalisation_floor: 0.05,
            truncation: 1.0,
            view_keep_fraction: 0.6,
            temperature: 0.1,
            propagation: true,
            exploration_particles: 1,
            velocity_prior: 1.0,
            velocity_prior_depth: 0.1,
            mean_estimate: true,
            smoothness_px: 0.0,
            smoothness_cap: 2.0,
            window_step: 1,
            coarse_window_radius: 2,
            refine_radius: 4,
            refine_colour_sigma: 0.3,
            fresh_fraction: 0.2,
            second_reference: false,
            skin_weight: 1.0,
            skin_drop_worst_view: true,
            skin_threshold: 0.0,
            skin_footprint_share: 1.0,
        }
    }
}

impl EngineConfig {
    /// The paper's method: the defaults with every `handflow` addition off.
    pub fn paper() -> Self {
        Self {
            variant: Variant::Paper,
            noise_loops: 3,
            coarse_extra_loops: 0,
            window_radius: 0,
            local_normalisation_radius: 0,
            propagation: false,
            exploration_particles: 0,
            refine_radius: 0,
            skin_drop_worst_view: false,
            ..Self::default()
        }
    }

    /// The defaults of a variant.
    pub fn for_variant(variant: Variant) -> Self {
        match variant {
            Variant::Paper => Self::paper(),
            Variant::Handflow => Self::default(),
        }
    }

    /// Whether a stream's first frame gets an estimate: only forwards/backwards with
    /// [`EngineConfig::estimate_first_frame`] (the two-frame likelihood needs t-1 too).
    pub fn estimates_first_frame(&self) -> bool {
        self.temporal == Temporal::ForwardsBackwards && self.estimate_first_frame
    }

    /// Checks every field; the message names the field at fault.
    pub fn validate(&self) -> Result<(), String> {
        let positive = |name: &str, v: f32| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(format!("`{name}` must be a positive number, got {v}"))
            }
        };
        if self.particles_per_ray == 0 || self.particles_per_ray > MAX_PARTICLES_PER_RAY {
            return Err(format!(
                "`particles_per_ray` must be between 1 and {MAX_PARTICLES_PER_RAY}, got {}",
                self.particles_per_ray
            ));
        }
        if self.pyramid_levels == 0 || self.pyramid_levels > 8 {
            return Err(format!("`pyramid_levels` must be between 1 and 8, got {}", self.pyramid_levels));
        }
        if self.finest_level >= self.pyramid_levels || (self.finest_level > 0 && !self.per_level_rays) {
            return Err(format!(
                "`finest_level` must be below `pyramid_levels` ({}) and 0 unless `per_level_rays`, got {}",
                self.pyramid_levels, self.finest_level
            ));
        }
        if self.ray_subsampling > 0
            && (!self.per_level_rays || self.finest_level + self.ray_subsampling >= self.pyramid_levels)
        {
            return Err(format!(
                "`ray_subsampling` needs `per_level_rays` and `finest_level + ray_subsampling` below \
                 `pyramid_levels` ({}), got {} + {}",
                self.pyramid_levels, self.finest_level, self.ray_subsampling
            ));
        }
        if !(0.0..=1.0).contains(&self.skin_footprint_share) {
            return Err(format!("`skin_footprint_share` must be between 0 and 1, got {}", self.skin_footprint_share));
        }
        if self.noise_loops == 0 {
            return Err("`noise_loops` must be at least 1".into());
        }
        let (near, far) = self.depth_range;
        positive("depth_range.0", near)?;
        if !(far.is_finite() && far > near) {
            return Err(format!("`depth_range` must satisfy 0 < near < far, got ({near}, {far})"));
        }
        positive("speed_bound", self.speed_bound)?;
        positive("epsilon", self.epsilon)?;
        positive("diffusion_px", self.diffusion_px)?;
        positive("diffusion_shrink", self.diffusion_shrink)?;
        positive("truncation", self.truncation)?;
        positive("temperature", self.temperature)?;
        positive("velocity_prior", self.velocity_prior)?;
        positive("refine_colour_sigma", self.refine_colour_sigma)?;
        positive("local_normalisation_floor", self.local_normalisation_floor)?;
        positive("velocity_prior_depth", self.velocity_prior_depth)?;
        if !(self.smoothness_px >= 0.0 && self.smoothness_cap >= 0.0) {
            return Err("`smoothness_px` and `smoothness_cap` must be non-negative".into());
        }
        if self.refine_radius > 4 {
            return Err(format!("`refine_radius` must be at most 4, got {}", self.refine_radius));
        }
        if self.window_step == 0 || self.window_step > 4 {
            return Err(format!("`window_step` must be between 1 and 4, got {}", self.window_step));
        }
        if !(self.view_keep_fraction > 0.0 && self.view_keep_fraction <= 1.0) {
            return Err(format!("`view_keep_fraction` must be in (0, 1], got {}", self.view_keep_fraction));
        }
        if !(self.skin_weight.is_finite() && self.skin_weight >= 0.0) {
            return Err(format!("`skin_weight` must be a non-negative number, got {}", self.skin_weight));
        }
        if !self.skin_threshold.is_finite() {
            return Err(format!("`skin_threshold` must be a number, got {}", self.skin_threshold));
        }
        if !(0.0..=1.0).contains(&self.fresh_fraction) {
            return Err(format!("`fresh_fraction` must be in [0, 1], got {}", self.fresh_fraction));
        }
        let max = crate::matching::likelihood::MAX_WINDOW_RADIUS;
        if self.window_radius > max || self.coarse_window_radius > max {
            return Err(format!(
                "`window_radius` and `coarse_window_radius` must be at most {max}, got {} and {}",
                self.window_radius, self.coarse_window_radius
            ));
        }
        if self.exploration_particles > 4 {
            return Err(format!("`exploration_particles` must be at most 4, got {}", self.exploration_particles));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_valid_and_paper_turns_additions_off() {
        EngineConfig::default().validate().expect("default valid");
        let paper = EngineConfig::paper();
        paper.validate().expect("paper valid");
        assert_eq!(paper.particles_per_ray, 10);
        assert_eq!(paper.pyramid_levels * paper.noise_loops, 9);
        assert!(!paper.propagation);
        assert_eq!(paper.epsilon, 0.001);
    }

    #[test]
    fn bad_fields_are_named() {
        let c = EngineConfig { particles_per_ray: 0, ..EngineConfig::default() };
        assert!(c.validate().unwrap_err().contains("particles_per_ray"));
        let c = EngineConfig { depth_range: (2.0, 1.0), ..EngineConfig::default() };
        assert!(c.validate().unwrap_err().contains("depth_range"));
        let c = EngineConfig { temperature: f32::NAN, ..EngineConfig::default() };
        assert!(c.validate().unwrap_err().contains("temperature"));
        let c = EngineConfig { finest_level: 3, ..EngineConfig::default() };
        assert!(c.validate().unwrap_err().contains("finest_level"));
        let c = EngineConfig { finest_level: 1, per_level_rays: false, ..EngineConfig::default() };
        assert!(c.validate().unwrap_err().contains("finest_level"));
        let c = EngineConfig { skin_weight: -1.0, ..EngineConfig::default() };
        assert!(c.validate().unwrap_err().contains("skin_weight"));
    }

    #[test]
    fn config_reads_from_partial_toml_like_json() {
        let c: EngineConfig = serde_json::from_str(r#"{"variant":"paper","particles_per_ray":5}"#).expect("parses");
        assert_eq!(c.variant, Variant::Paper);
        assert_eq!(c.particles_per_ray, 5);
        assert_eq!(c.pyramid_levels, 3);
    }
}
