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
    Camera::new(
        name,
        WIDTH,
        HEIGHT,
        Matrix3::new(FOCAL, 0.0, (WIDTH as f64 - 1.0) / 2.0, 0.0, FOCAL, (HEIGHT as f64 - 1.0) / 2.0, 0.0, 0.0, 1.0),
        Distortion::default(),
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
    let cameras = vec![camera("left", 0.0), camera("right", 0.4)];
    let config =
        EngineConfig { temporal, depth_range: (2.0, 10.0), speed_bound: 0.2, ..EngineConfig::for_variant(variant) };
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
    (median(&mut depth_err), median(&mut vx_err), median(&mut vy_err))
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
fn paper_variant_gets_close_to_a_uniform_translation() {
    // The reference method is ambiguous per pixel; the median still lands near the truth.
    let (depth, vx, vy) = run(Variant::Paper, Temporal::TwoFrame);
    assert!(depth < 0.5, "median depth error {depth}");
    assert!(vx < 0.04, "median vx error {vx}");
    assert!(vy < 0.04, "median vy error {vy}");
}
