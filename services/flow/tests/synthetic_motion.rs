//! A rendered two-view scene with a known uniform motion: a textured plane translating in
//! front of two cameras. Both variants must recover its depth and velocity.

use handflow_flow::{EngineConfig, SceneFlowEngine, Temporal, Variant};
use handflow_protocol::{Camera, Distortion};
use nalgebra::{Matrix3, Point3, Rotation3, Vector3};

const WIDTH: u32 = 96;
const HEIGHT: u32 = 72;
const FOCAL: f64 = 100.0;
const PLANE_DEPTH: f64 = 4.0;
const VELOCITY: [f64; 3] = [0.06, -0.03, 0.0];

fn camera(name: &str, x: f64) -> Camera {
    distorted_camera(name, x, Distortion::default())
}

fn distorted_camera(name: &str, x: f64, distortion: Distortion) -> Camera {
    Camera::new(
        name,
        WIDTH,
        HEIGHT,
        Matrix3::new(FOCAL, 0.0, (WIDTH as f64 - 1.0) / 2.0, 0.0, FOCAL, (HEIGHT as f64 - 1.0) / 2.0, 0.0, 0.0, 1.0),
        distortion,
        Rotation3::identity(),
        Vector3::new(-x, 0.0, 0.0),
    )
    .expect("valid camera")
}

fn hash(ix: i64, iy: i64, salt: u64) -> f64 {
    let mut h =
        (ix as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ (iy as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F) ^ salt;
    h = (h ^ (h >> 31)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    h ^= h >> 29;
    (h % 10_000) as f64 / 10_000.0
}

/// Smooth value noise: bilinear between hashed lattice values, two octaves.
fn texture(x: f64, y: f64, salt: u64) -> f64 {
    let octave = |scale: f64, salt: u64| {
        let (u, v) = (x / scale, y / scale);
        let (ix, iy) = (u.floor() as i64, v.floor() as i64);
        let (fx, fy) = (u - u.floor(), v - v.floor());
        let s = |t: f64| t * t * (3.0 - 2.0 * t);
        let (sx, sy) = (s(fx), s(fy));
        let top = hash(ix, iy, salt) * (1.0 - sx) + hash(ix + 1, iy, salt) * sx;
        let bottom = hash(ix, iy + 1, salt) * (1.0 - sx) + hash(ix + 1, iy + 1, salt) * sx;
        top * (1.0 - sy) + bottom * sy
    };
    0.6 * octave(0.12, salt) + 0.4 * octave(0.05, salt ^ 0xABCD)
}

/// Renders what `camera` sees at frame `k`: the plane z = PLANE_DEPTH, its texture moved
/// by `k * VELOCITY`.
fn render(camera: &Camera, k: f64) -> Vec<u8> {
    let mut rgb = Vec::with_capacity((WIDTH * HEIGHT * 3) as usize);
    let centre = camera.centre();
    for y in 0..HEIGHT {
        for x in 0..WIDTH {
            let ray = camera.back_project(&nalgebra::Point2::new(x as f64, y as f64));
            let s = (PLANE_DEPTH - centre.z) / ray.direction.z;
            let p: Point3<f64> = ray.at(s);
            let (tx, ty) = (p.x - k * VELOCITY[0], p.y - k * VELOCITY[1]);
            for salt in [1u64, 2, 3] {
                rgb.push((40.0 + 180.0 * texture(tx, ty, salt)) as u8);
            }
        }
    }
    rgb
}

fn run(variant: Variant, temporal: Temporal) -> (f64, f64, f64) {
    run_with(variant, temporal, vec![camera("left", 0.0), camera("right", 0.4)])
}

fn run_with(variant: Variant, temporal: Temporal, cameras: Vec<Camera>) -> (f64, f64, f64) {
    let config =
        EngineConfig { temporal, depth_range: (2.0, 10.0), speed_bound: 0.2, ..EngineConfig::for_variant(variant) };
    run_config(config, cameras).0
}

/// Median depth, vx and vy errors of the first estimate, and the likelihood evaluations it took.
fn run_config(config: EngineConfig, cameras: Vec<Camera>) -> ((f64, f64, f64), u64) {
    let temporal = config.temporal;
    let mut engine = SceneFlowEngine::new(config, cameras.clone(), 0).expect("engine");
    let frames = if temporal == Temporal::TwoFrame { 2 } else { 3 };
    let mut done = false;
    for k in 0..frames {
        let views: Vec<Vec<u8>> = cameras.iter().map(|c| render(c, k as f64)).collect();
        let refs: Vec<&[u8]> = views.iter().map(Vec::as_slice).collect();
        done |= engine.push_frame(&refs).expect("push").is_some();
    }
    assert!(done, "an estimate was produced");
    let field = engine.field();
    // Median absolute errors over the central region (borders see less of the plane).
    let mut depth_err = Vec::new();
    let mut vx_err = Vec::new();
    let mut vy_err = Vec::new();
    for y in 12..(HEIGHT as usize - 12) {
        for x in 12..(WIDTH as usize - 20) {
            let i = y * WIDTH as usize + x;
            depth_err.push((f64::from(field.depth[i]) - PLANE_DEPTH).abs());
            vx_err.push((f64::from(field.velocity[i][0]) - VELOCITY[0]).abs());
            vy_err.push((f64::from(field.velocity[i][1]) - VELOCITY[1]).abs());
        }
    }
    let median = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    ((median(&mut depth_err), median(&mut vx_err), median(&mut vy_err)), engine.stats().evaluations)
}

#[test]
fn cold_start_passes_refine_a_first_frame_from_its_own_posterior() {
    let cameras = vec![camera("left", 0.0), camera("right", 0.4)];
    let config = EngineConfig {
        temporal: Temporal::TwoFrame,
        depth_range: (2.0, 10.0),
        speed_bound: 0.2,
        ..EngineConfig::for_variant(Variant::Paper)
    };
    let (once, once_evaluations) = run_config(config.clone(), cameras.clone());
    let (settled, settled_evaluations) = run_config(EngineConfig { cold_start_passes: 3, ..config }, cameras);
    eprintln!("one pass {once:?} ({once_evaluations} evaluations), four {settled:?} ({settled_evaluations})");
    // Every pass is a whole coarse-to-fine run.
    assert!(settled_evaluations > 3 * once_evaluations, "{settled_evaluations} vs {once_evaluations}");
    assert!(settled.0 <= once.0, "depth error {} after the passes, {} before", settled.0, once.0);
    assert!(settled.1 <= once.1 && settled.2 <= once.2, "velocity error {settled:?} vs {once:?}");
}

// Tolerances in image terms: at depth 4 and f = 100, 0.1 depth is 0.25 px of disparity
// across the 0.4 baseline and 0.01 of velocity is 0.25 px of flow.

#[test]
fn handflow_recovers_a_uniform_translation() {
    let (depth, vx, vy) = run(Variant::Handflow, Temporal::TwoFrame);
    assert!(depth < 0.1, "median depth error {depth}");
    assert!(vx < 0.01, "median vx error {vx}");
    assert!(vy < 0.01, "median vy error {vy}");
}

#[test]
fn handflow_forwards_backwards_recovers_a_uniform_translation() {
    let (depth, vx, vy) = run(Variant::Handflow, Temporal::ForwardsBackwards);
    assert!(depth < 0.1, "median depth error {depth}");
    assert!(vx < 0.01, "median vx error {vx}");
    assert!(vy < 0.01, "median vy error {vy}");
}

#[test]
fn handflow_recovers_a_uniform_translation_through_lens_distortion() {
    // Barrel distortion of a few pixels at the corners; rays and projections both model it.
    let lens = Distortion { k1: -0.15, k2: 0.02, p1: 0.001, p2: -0.001, k3: 0.0 };
    let cameras = vec![distorted_camera("left", 0.0, lens), distorted_camera("right", 0.4, lens)];
    let (depth, vx, vy) = run_with(Variant::Handflow, Temporal::TwoFrame, cameras);
    assert!(depth < 0.1, "median depth error {depth}");
    assert!(vx < 0.01, "median vx error {vx}");
    assert!(vy < 0.01, "median vy error {vy}");
}

#[test]
fn paper_variant_gets_close_to_a_uniform_translation() {
    // The reference method is ambiguous per pixel; the median still lands near the truth.
    let (depth, vx, vy) = run(Variant::Paper, Temporal::TwoFrame);
    assert!(depth < 0.5, "median depth error {depth}");
    assert!(vx < 0.04, "median vx error {vx}");
    assert!(vy < 0.04, "median vy error {vy}");
}

fn render_views(cameras: &[Camera], k: f64) -> Vec<Vec<u8>> {
    cameras.iter().map(|c| render(c, k)).collect()
}

fn engine(
    variant: Variant,
    temporal: Temporal,
    coverage: handflow_flow::Coverage,
    seed: u64,
) -> (SceneFlowEngine, Vec<Camera>) {
    let cameras = vec![camera("left", 0.0), camera("right", 0.4)];
    let config = EngineConfig {
        temporal,
        coverage,
        seed,
        depth_range: (2.0, 10.0),
        speed_bound: 0.2,
        ..EngineConfig::for_variant(variant)
    };
    (SceneFlowEngine::new(config, cameras.clone(), 0).expect("engine"), cameras)
}

fn push(engine: &mut SceneFlowEngine, views: &[Vec<u8>]) -> bool {
    let refs: Vec<&[u8]> = views.iter().map(Vec::as_slice).collect();
    engine.push_frame(&refs).expect("push").is_some()
}

fn central_median_vx_error(field: &handflow_flow::DenseField) -> f64 {
    let mut errs: Vec<f64> = Vec::new();
    for y in 12..(HEIGHT as usize - 12) {
        for x in 12..(WIDTH as usize - 20) {
            errs.push((f64::from(field.velocity[y * WIDTH as usize + x][0]) - VELOCITY[0]).abs());
        }
    }
    errs.sort_by(f64::total_cmp);
    errs[errs.len() / 2]
}

#[test]
fn the_previous_posterior_is_the_prior_of_the_next_frame() {
    let (mut engine, cameras) = engine(Variant::Handflow, Temporal::TwoFrame, handflow_flow::Coverage::Dense, 3);
    assert!(!push(&mut engine, &render_views(&cameras, 0.0)), "one frame completes nothing");
    assert!(push(&mut engine, &render_views(&cameras, 1.0)));
    assert!(!engine.stats().used_temporal_prior, "the first estimate starts from the broad prior");
    assert!(push(&mut engine, &render_views(&cameras, 2.0)));
    let stats = engine.stats();
    assert!(stats.used_temporal_prior, "consecutive frames carry the posterior over");
    assert_eq!(stats.frame, 2);
    let err = central_median_vx_error(engine.field());
    assert!(err < 0.01, "median vx error with the temporal prior {err}");
    // Particles are real weighted hypotheses on their rays.
    let ray = 40 * WIDTH as usize + 40;
    let particles = engine.ray_particles(ray);
    assert_eq!(particles.len(), 10);
    let total: f32 = particles.iter().map(|p| p.weight).sum();
    assert!((total - 1.0).abs() < 1e-4, "weights of a ray sum to one: {total}");
    let z = engine.particle_position(ray, &particles[0])[2];
    assert!((f64::from(z) - PLANE_DEPTH).abs() < 0.5, "particle depth {z}");
}

#[test]
fn sparse_mode_leaves_rays_empty_and_dense_mode_refills_them() {
    // The plane moves right by 1.5 px per frame in the reference view, so after the
    // constant-velocity prediction the leftmost column receives no particle.
    for coverage in [handflow_flow::Coverage::Sparse, handflow_flow::Coverage::Dense] {
        let (mut engine, cameras) = engine(Variant::Handflow, Temporal::TwoFrame, coverage, 5);
        for k in 0..3 {
            push(&mut engine, &render_views(&cameras, f64::from(k)));
        }
        let stats = engine.stats();
        assert!(stats.used_temporal_prior);
        let rays = (WIDTH * HEIGHT) as usize;
        let empty: Vec<usize> = (0..rays).filter(|&r| engine.ray_particles(r).is_empty()).collect();
        // The scene moved right: rays near the left border are the ones nothing moved onto.
        let empty_on_the_left = empty.iter().filter(|&&r| r % WIDTH as usize <= 3).count();
        let empty_rays_have_no_estimate =
            (0..rays).filter(|&r| engine.ray_particles(r).is_empty()).all(|r| engine.field().depth[r].is_nan());
        match coverage {
            handflow_flow::Coverage::Sparse => {
                assert!(stats.occupied_rays < rays, "some rays are empty");
                assert!(!empty.is_empty(), "rays nothing moved onto stay empty");
                // Elsewhere, forward-projected particles leave only splatting holes.
                let left_share = empty_on_the_left as f64 / (4.0 * f64::from(HEIGHT));
                let other_share =
                    (empty.len() - empty_on_the_left) as f64 / ((f64::from(WIDTH) - 4.0) * f64::from(HEIGHT));
                assert!(left_share > 5.0 * other_share, "empty share left {left_share}, elsewhere {other_share}");
                assert!(empty_rays_have_no_estimate, "an empty ray has no estimate");
            }
            _ => {
                assert_eq!(stats.occupied_rays, rays, "every ray refilled");
                assert!(empty.is_empty());
            }
        }
    }
}

#[test]
fn results_depend_on_the_seed_only_not_on_the_thread_count() {
    let run = |threads: usize, seed: u64| {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().expect("pool");
        pool.install(|| {
            let (mut engine, cameras) =
                engine(Variant::Handflow, Temporal::TwoFrame, handflow_flow::Coverage::Dense, seed);
            push(&mut engine, &render_views(&cameras, 0.0));
            push(&mut engine, &render_views(&cameras, 1.0));
            (engine.field().depth.clone(), engine.field().velocity.clone())
        })
    };
    let one = run(1, 9);
    let two = run(2, 9);
    assert!(one.0.iter().zip(&two.0).all(|(a, b)| a.to_bits() == b.to_bits()), "depth identical across thread counts");
    assert_eq!(one.1, two.1, "velocity identical across thread counts");
    let other = run(2, 10);
    assert_ne!(one.1, other.1, "another seed draws other particles");
}

#[test]
fn forwards_backwards_is_one_frame_late_and_flush_estimates_the_last_frame() {
    let (mut engine, cameras) =
        engine(Variant::Handflow, Temporal::ForwardsBackwards, handflow_flow::Coverage::Dense, 1);
    assert!(!push(&mut engine, &render_views(&cameras, 0.0)));
    assert!(!push(&mut engine, &render_views(&cameras, 1.0)), "frame 1 waits for frame 2");
    assert!(push(&mut engine, &render_views(&cameras, 2.0)));
    assert_eq!(engine.stats().frame, 1, "the estimate is for the middle frame");
    let last = engine.flush().is_some();
    assert!(last, "flush estimates the last frame");
    assert_eq!(engine.stats().frame, 2);
    assert!(engine.stats().used_temporal_prior);
    assert!(central_median_vx_error(engine.field()) < 0.01);
    assert!(engine.flush().is_none(), "nothing is left after a flush");
}

#[test]
fn a_first_frame_is_estimated_forwards_from_its_successor_when_asked() {
    let cameras = vec![camera("left", 0.0), camera("right", 0.4)];
    let config = EngineConfig {
        temporal: Temporal::ForwardsBackwards,
        estimate_first_frame: true,
        seed: 1,
        depth_range: (2.0, 10.0),
        speed_bound: 0.2,
        ..EngineConfig::for_variant(Variant::Handflow)
    };
    let mut engine = SceneFlowEngine::new(config, cameras.clone(), 0).expect("engine");
    assert!(!push(&mut engine, &render_views(&cameras, 0.0)));
    assert!(push(&mut engine, &render_views(&cameras, 1.0)), "frame 0 is estimated once frame 1 is in");
    assert_eq!(engine.stats().frame, 0);
    assert!(!engine.stats().used_temporal_prior);
    // The motion comes from t+1 alone, and is as right.
    assert!(central_median_vx_error(engine.field()) < 0.01);
    assert!(push(&mut engine, &render_views(&cameras, 2.0)));
    assert_eq!(engine.stats().frame, 1, "then one frame late, as without it");
    assert!(!engine.stats().used_temporal_prior, "the second frame starts afresh on all three frames");
    assert!(central_median_vx_error(engine.field()) < 0.01);
    assert!(push(&mut engine, &render_views(&cameras, 3.0)));
    assert_eq!(engine.stats().frame, 2);
    assert!(engine.stats().used_temporal_prior);
}

#[test]
fn bad_frames_are_refused_with_the_camera_named() {
    let (mut engine, cameras) = engine(Variant::Handflow, Temporal::TwoFrame, handflow_flow::Coverage::Dense, 0);
    let views = render_views(&cameras, 0.0);
    let err = engine.push_frame(&[views[0].as_slice()]).expect_err("one view missing").to_string();
    assert!(err.contains("expected 2 views"), "{err}");
    let short = &views[1][..100];
    let err = engine.push_frame(&[views[0].as_slice(), short]).expect_err("short view").to_string();
    assert!(err.contains("`right`") && err.contains("96x72"), "{err}");
    // Nothing accepted is lost: the engine still works after refusing.
    assert!(!push(&mut engine, &views));
    assert!(push(&mut engine, &render_views(&cameras, 1.0)));
}

/// Centre and radius, in plane coordinates, of the skin-coloured disc of [`render_skin`].
const DISC: (f64, f64, f64) = (0.2, 0.05, 0.35);

/// Like [`render`], with the plane bluish cloth except for a textured skin-coloured disc
/// that moves with it.
fn render_skin(camera: &Camera, k: f64) -> Vec<u8> {
    let mut rgb = Vec::with_capacity((WIDTH * HEIGHT * 3) as usize);
    let centre = camera.centre();
    for y in 0..HEIGHT {
        for x in 0..WIDTH {
            let ray = camera.back_project(&nalgebra::Point2::new(x as f64, y as f64));
            let s = (PLANE_DEPTH - centre.z) / ray.direction.z;
            let p: Point3<f64> = ray.at(s);
            let (tx, ty) = (p.x - k * VELOCITY[0], p.y - k * VELOCITY[1]);
            let t = texture(tx, ty, 1);
            let on_disc = (tx - DISC.0).hypot(ty - DISC.1) < DISC.2;
            let colour = if on_disc {
                [212.0, 178.0, 152.0].map(|c| c * (0.75 + 0.4 * t))
            } else {
                [30.0 + 60.0 * t, 60.0 + 80.0 * t, 120.0 + 100.0 * t]
            };
            rgb.extend(colour.map(|c| c.min(255.0) as u8));
        }
    }
    rgb
}

/// `config` for the skin disc scene: forwards/backwards, skin coverage, its depths and speeds.
fn skin_disc_config(config: EngineConfig) -> EngineConfig {
    EngineConfig {
        temporal: Temporal::ForwardsBackwards,
        coverage: handflow_flow::Coverage::Skin,
        depth_range: (2.0, 10.0),
        speed_bound: 0.2,
        ..config
    }
}

#[test]
fn skin_coverage_estimates_only_the_skin_and_gets_it_right() {
    let cameras = vec![camera("left", 0.0), camera("right", 0.4)];
    let config = skin_disc_config(EngineConfig::default());
    let mut engine = SceneFlowEngine::new(config, cameras.clone(), 0).expect("engine");
    assert_eq!(engine.skin_models().len(), 2, "generic models until replaced");
    let mut estimates = 0;
    for k in 0..4 {
        let views: Vec<Vec<u8>> = cameras.iter().map(|c| render_skin(c, f64::from(k))).collect();
        let refs: Vec<&[u8]> = views.iter().map(Vec::as_slice).collect();
        estimates += usize::from(engine.push_frame(&refs).expect("push").is_some());
    }
    assert_eq!(estimates, 2, "forwards/backwards: frames 1 and 2");
    // The estimate is for frame 2: where is the disc in the reference view then?
    let frame = 2.0;
    let reference = &cameras[0];
    let on_disc = |x: usize, y: usize, margin: f64| {
        let ray = reference.back_project(&nalgebra::Point2::new(x as f64, y as f64));
        let p = ray.at((PLANE_DEPTH - reference.centre().z) / ray.direction.z);
        let (tx, ty) = (p.x - frame * VELOCITY[0], p.y - frame * VELOCITY[1]);
        (tx - DISC.0).hypot(ty - DISC.1) < DISC.2 + margin * PLANE_DEPTH / FOCAL
    };
    let field = engine.field();
    let (w, h) = (field.width, field.height);
    let (mut estimated, mut outside, mut interior, mut interior_estimated) = (0, 0, 0, 0);
    let (mut depth_err, mut v_err) = (Vec::new(), Vec::new());
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            let has = field.confidence[i] > 0.0;
            if on_disc(x, y, -2.0) {
                interior += 1;
                interior_estimated += usize::from(has);
            }
            if !has {
                continue;
            }
            estimated += 1;
            if !on_disc(x, y, 1.5) {
                outside += 1;
                continue;
            }
            depth_err.push((f64::from(field.depth[i]) - PLANE_DEPTH).abs());
            v_err.push(
                (f64::from(field.velocity[i][0]) - VELOCITY[0])
                    .abs()
                    .max((f64::from(field.velocity[i][1]) - VELOCITY[1]).abs()),
            );
        }
    }
    let stats = engine.stats();
    eprintln!(
        "estimated {estimated} of {} rays, {outside} off the skin, {interior_estimated} of {interior} skin rays",
        w * h
    );
    assert_eq!(stats.occupied_rays, estimated, "every occupied ray has an estimate");
    assert!(estimated < w * h / 3, "a fraction of the rays: {estimated} of {}", w * h);
    assert!(outside * 50 < estimated, "{outside} of {estimated} estimates off the skin");
    assert!(interior_estimated * 10 > interior * 9, "{interior_estimated} of {interior} skin rays estimated");
    let median = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let (d, v) = (median(&mut depth_err), median(&mut v_err));
    assert!(d < 0.1 && v < 0.01, "median depth error {d}, velocity error {v}");
    // The skin map of the frame estimated is what the reference camera saw there.
    let x = (0..w).find(|&x| on_disc(x, h / 2, -2.0)).expect("the disc crosses the middle row");
    assert!(engine.skin_at(0, x, h / 2).is_some_and(|s| s > 0.0));
    assert!(engine.skin_at(0, w, 0).is_none(), "outside the image");
}

/// Estimates frame 2 of the skin disc scene with `config` (forwards/backwards, skin
/// coverage) and returns the engine.
fn skin_disc_engine(config: EngineConfig) -> (SceneFlowEngine, Vec<Camera>) {
    let cameras = vec![camera("left", 0.0), camera("right", 0.4)];
    let mut engine = SceneFlowEngine::new(skin_disc_config(config), cameras.clone(), 0).expect("engine");
    for k in 0..4 {
        let views: Vec<Vec<u8>> = cameras.iter().map(|c| render_skin(c, f64::from(k))).collect();
        let refs: Vec<&[u8]> = views.iter().map(Vec::as_slice).collect();
        engine.push_frame(&refs).expect("push");
    }
    (engine, cameras)
}

/// Estimated rays of the engine's field, and how many of them cover a pixel that is not skin.
fn rays_on_skin(engine: &SceneFlowEngine) -> (usize, usize) {
    let field = engine.field();
    let scale = WIDTH as usize / field.width;
    let (mut estimated, mut straddling) = (0, 0);
    for ray in (0..field.width * field.height).filter(|&r| field.confidence[r] > 0.0) {
        estimated += 1;
        let (x0, y0) = ((ray % field.width) * scale, (ray / field.width) * scale);
        let all_skin =
            (y0..y0 + scale).all(|y| (x0..x0 + scale).all(|x| engine.skin_at(0, x, y).is_some_and(|s| s > 0.0)));
        straddling += usize::from(!all_skin);
    }
    (estimated, straddling)
}

#[test]
fn the_finest_grid_holds_rays_mostly_on_skin() {
    let half = EngineConfig { finest_level: 1, ..EngineConfig::default() };
    let (whole, _) = skin_disc_engine(EngineConfig { skin_footprint_share: 1.0, ..half.clone() });
    let (any, _) = skin_disc_engine(EngineConfig { skin_footprint_share: 0.0, ..half.clone() });
    let (whole_rays, whole_straddling) = rays_on_skin(&whole);
    let (any_rays, any_straddling) = rays_on_skin(&any);
    eprintln!("whole: {whole_rays} rays, {whole_straddling} straddling; any: {any_rays}, {any_straddling}");
    assert_eq!(whole_straddling, 0, "every ray of the finest grid lies wholly on skin");
    assert!(any_straddling > 0, "with any skin pixel, the disc's rim rays straddle it");
    assert!(whole_rays * 2 > any_rays && whole_rays < any_rays, "only the rim goes: {whole_rays} of {any_rays}");
    // Rays three quarters on skin: some of the rim, never more than any.
    let (most, _) = skin_disc_engine(EngineConfig { skin_footprint_share: 0.75, ..half });
    let (most_rays, _) = rays_on_skin(&most);
    assert!(whole_rays <= most_rays && most_rays <= any_rays, "{whole_rays} <= {most_rays} <= {any_rays}");
}

#[test]
fn subsampled_rays_match_the_finer_images_and_get_the_motion_right() {
    let config = EngineConfig { ray_subsampling: 1, ..EngineConfig::default() };
    let (engine, _) = skin_disc_engine(config);
    let field = engine.field();
    assert_eq!((field.width, field.height), (WIDTH as usize / 2, HEIGHT as usize / 2), "rays on the half grid");
    let mut errors: Vec<(f64, f64)> = (0..field.width * field.height)
        .filter(|&r| field.confidence[r] > 0.0)
        .map(|r| {
            let v = field.velocity[r];
            let v_err = (f64::from(v[0]) - VELOCITY[0]).abs().max((f64::from(v[1]) - VELOCITY[1]).abs());
            ((f64::from(field.depth[r]) - PLANE_DEPTH).abs(), v_err)
        })
        .collect();
    assert!(errors.len() > 30, "{} rays estimated", errors.len());
    errors.sort_by(|a, b| a.0.total_cmp(&b.0));
    let depth = errors[errors.len() / 2].0;
    errors.sort_by(|a, b| a.1.total_cmp(&b.1));
    let velocity = errors[errors.len() / 2].1;
    assert!(depth < 0.1 && velocity < 0.01, "median depth error {depth}, velocity error {velocity}");
}

/// Pushes the frames rendered at `frames`, with their indices when `indexed`; returns the
/// median vx error and whether the posterior was carried, after each estimate.
fn push_with_gaps(frames: &[u64], indexed: bool) -> Vec<(f64, bool)> {
    let (mut engine, cameras) =
        engine(Variant::Handflow, Temporal::ForwardsBackwards, handflow_flow::Coverage::Dense, 11);
    let mut out = Vec::new();
    for &k in frames {
        let views = render_views(&cameras, k as f64);
        let refs: Vec<&[u8]> = views.iter().map(Vec::as_slice).collect();
        let done = if indexed {
            engine.push_frame_indexed(&refs, 0, k).expect("push").is_some()
        } else {
            engine.push_frame(&refs).expect("push").is_some()
        };
        if done {
            out.push((central_median_vx_error(engine.field()), engine.stats().used_temporal_prior));
        }
    }
    out
}

#[test]
fn frames_lost_on_the_way_are_spanned_at_the_velocity_per_frame() {
    // Frame 3 never arrives: the estimates of frames 2 (from 1, 2 and 4) and 4 (from 2, 4
    // and 5) span the gap.
    let frames = [0, 1, 2, 4, 5];
    let indexed = push_with_gaps(&frames, true);
    let counted = push_with_gaps(&frames, false);
    eprintln!("indexed {indexed:?}, counted {counted:?}");
    assert_eq!(indexed.len(), 3);
    for (k, (&(err, carried), &(naive, _))) in indexed.iter().zip(&counted).enumerate().skip(1) {
        assert!(err < 0.0015, "estimate {k}: median vx error {err}");
        assert!(carried, "estimate {k}: a gap of two frames still carries the posterior");
        // Taken for consecutive frames, the same images give a velocity between the two sides'.
        assert!(naive > 2.0 * err, "estimate {k}: {naive} without the indices, {err} with them");
    }
    // Over six frames a hand's path bends too far for constant velocity: the frame after
    // the gap is matched against its successor only, from the posterior held still with
    // half of it drawn afresh, and the plane's motion is found again.
    let far = push_with_gaps(&[0, 1, 2, 8, 9], true);
    assert_eq!(far.len(), 3);
    assert!(far[2].1 && far[2].0 < 0.005, "{far:?}");
}
