//! Runs the scene-flow engine on a Middlebury problem: the glue between
//! [`crate::eval::middlebury`] (data, truth, metrics) and `handflow_flow` (the engine).

use anyhow::{bail, Result};
use handflow_flow::{DenseField, EngineConfig, FrameStats, SceneFlowEngine, Temporal, Variant};

use crate::engine_overrides::apply_overrides;
use crate::eval::middlebury::{evaluate, Layout, Metrics, Problem, Scene};

/// What to run: the engine variant and anything overridden on the command line.
#[derive(Clone, Debug, Default)]
pub struct EvalOptions {
    /// Engine formulation.
    pub variant: Variant,
    /// Scene Particles per ray (engine default when `None`).
    pub particles_per_ray: Option<usize>,
    /// Random seed.
    pub seed: u64,
    /// Engine configuration overrides as `field=value` (value in JSON, or a bare string).
    pub overrides: Vec<String>,
}

/// One estimate and its score.
pub struct RunResult {
    /// The protocol's metrics.
    pub metrics: Metrics,
    /// What the estimate cost.
    pub stats: FrameStats,
    /// The dense estimate of the reference view.
    pub field: DenseField,
}

/// The engine configuration for `problem`: the variant's defaults, the problem's search
/// space (depth range, speed bound), the layout's likelihood, then the overrides.
pub fn engine_config(problem: &Problem, layout: Layout, options: &EvalOptions) -> Result<EngineConfig> {
    let mut config = EngineConfig::for_variant(options.variant);
    config.depth_range = (problem.depth_range.0 as f32, problem.depth_range.1 as f32);
    config.speed_bound = problem.speed_bound as f32;
    config.temporal = match layout {
        Layout::Multiview => Temporal::TwoFrame,
        Layout::Fb => Temporal::ForwardsBackwards,
    };
    config.seed = options.seed;
    if let Some(n) = options.particles_per_ray {
        config.particles_per_ray = n;
    }
    let config = apply_overrides(config, &options.overrides)?;
    config.validate().map_err(anyhow::Error::msg)?;
    Ok(config)
}

/// Runs the engine once on `problem` and scores its dense estimate.
pub fn run_once(scene: &Scene, problem: &Problem, config: EngineConfig) -> Result<RunResult> {
    let mut engine = SceneFlowEngine::new(config, problem.cameras.clone(), problem.reference)?;
    let mut seconds = f64::NAN;
    for frame in &problem.frames {
        let views: Vec<&[u8]> = frame.iter().map(|&i| scene.images[i].as_slice()).collect();
        let started = std::time::Instant::now();
        let produced = engine.push_frame(&views)?.is_some();
        if produced {
            seconds = started.elapsed().as_secs_f64();
        }
    }
    if seconds.is_nan() {
        bail!("the engine produced no estimate for {} frames", problem.frames.len());
    }
    let mut stats = engine.stats();
    // Time per frame as in a stream: the push of the frame that completes the estimate
    // (its normalisation and pyramids, then the filter). Earlier frames' pyramids were
    // built when they arrived and are reused, as in the live pipeline.
    stats.seconds = seconds;
    let field = engine.field().clone();
    let metrics = evaluate(problem, &field.position, &field.velocity);
    Ok(RunResult { metrics, stats, field })
}

/// Loads a scene folder and poses its problem for a layout.
pub fn load_problem(dir: &std::path::Path, layout: Layout) -> Result<(Scene, Problem)> {
    let scene = Scene::load(dir)?;
    let problem = Problem::new(&scene, layout)?;
    if problem.truth.known() == 0 {
        bail!(
            "scene `{}`: no pixel of the {layout} reference view has ground truth (check `gt_views` in scene.toml)",
            dir.display()
        );
    }
    Ok((scene, problem))
}
