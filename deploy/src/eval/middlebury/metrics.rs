//! The accuracy metrics of EVALUATION.md section 1, over reference pixels with known truth.

use nalgebra::{Point3, Vector3};

use super::Problem;

/// The protocol's accuracy metrics of one estimate.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Metrics {
    /// RMSE of the optical flow of the reference view from `t-1` to `t`, pixels.
    pub of_rmse_px: f64,
    /// RMSE of the Z component of the scene flow, world units per frame.
    pub zflow_rmse: f64,
    /// RMSE of the neighbour-view disparity `f / Z` implied by the estimated depth, pixels.
    pub structure_rmse_px: f64,
    /// Mean angle between estimated and true scene-flow vectors, degrees.
    pub aae_deg: f64,
    /// Reference pixels scored (those with known truth). All metrics are NaN when 0.
    pub pixels: usize,
}

/// One pixel's estimate, made safe to score: see [`evaluate`].
struct Estimate {
    /// World position.
    position: Point3<f64>,
    /// World velocity per frame.
    velocity: Vector3<f64>,
}

/// Turns the raw estimate of reference pixel `index` into one every metric can score. A
/// position that is missing, non-finite or does not project into the reference camera
/// (behind it) is an error, scored as "no idea": a point at `z_far` on the pixel's ray,
/// not moving. A velocity that is missing or non-finite, or that puts the point at `t-1`
/// behind the camera, is scored as zero motion.
fn sanitise(problem: &Problem, index: usize, position: Option<&[f32; 3]>, velocity: Option<&[f32; 3]>) -> Estimate {
    let camera = problem.reference_camera();
    let to_f64 = |a: &[f32; 3]| Vector3::new(f64::from(a[0]), f64::from(a[1]), f64::from(a[2]));
    let finite = |v: &Vector3<f64>| v.iter().all(|c| c.is_finite());
    let position = position.map(to_f64).filter(finite).map(Point3::from).filter(|p| camera.project(p).is_some());
    let Some(position) = position else {
        let width = problem.truth.width as usize;
        let (x, y) = ((index % width) as f64, (index / width) as f64);
        return Estimate { position: problem.back_project(x, y, problem.depth_range.1), velocity: Vector3::zeros() };
    };
    let velocity = velocity
        .map(to_f64)
        .filter(finite)
        .filter(|v| camera.project(&(position - v)).is_some())
        .unwrap_or_else(Vector3::zeros);
    Estimate { position, velocity }
}

/// Scores a dense estimate of the reference view against the problem's truth.
///
/// `positions[i]` is the world position of reference pixel `i`'s estimate (row-major,
/// `width * height`), `velocities[i]` its world velocity per frame. Over pixels with known
/// truth `d1`:
/// - optical flow: `proj_ref(p) - proj_ref(p - v)` against `(d1, 0)`;
/// - Z flow: `v_z` against 0;
/// - structure: `f / Z_cam(p)` against `d1`;
/// - angle between `v` and `(1, 0, 0)`; a zero vector counts 90 degrees.
///
/// Estimates are errors, never skipped: a missing, non-finite or behind-the-camera position
/// is scored as a motionless point at `z_far` on the pixel's ray; a missing or non-finite
/// velocity as zero motion. Sums are in `f64`, in pixel order, so a score is reproducible.
pub fn evaluate(problem: &Problem, positions: &[[f32; 3]], velocities: &[[f32; 3]]) -> Metrics {
    let camera = problem.reference_camera();
    let f = problem.focal();
    let (mut of, mut zflow, mut structure, mut angle) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
    let mut pixels = 0usize;
    for (index, &d1) in problem.truth.d1.iter().enumerate() {
        if !(d1.is_finite() && d1 > 0.0) {
            continue;
        }
        let d1 = f64::from(d1);
        let Estimate { position, velocity } = sanitise(problem, index, positions.get(index), velocities.get(index));
        // sanitise() guarantees both project; the fallback only guards the invariant.
        let (Some(now), Some(before)) = (camera.project(&position), camera.project(&(position - velocity))) else {
            continue;
        };
        let flow = now - before;
        of += (flow.x - d1).powi(2) + flow.y.powi(2);
        zflow += velocity.z.powi(2);
        let z = camera.world_to_camera(&position).z;
        structure += (f / z - d1).powi(2);
        let speed = velocity.norm();
        angle += if speed > 0.0 { (velocity.x / speed).clamp(-1.0, 1.0).acos().to_degrees() } else { 90.0 };
        pixels += 1;
    }
    let n = pixels as f64;
    Metrics {
        of_rmse_px: (of / n).sqrt(),
        zflow_rmse: (zflow / n).sqrt(),
        structure_rmse_px: (structure / n).sqrt(),
        aae_deg: angle / n,
        pixels,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval::middlebury::testing::synthetic_scene;
    use crate::eval::middlebury::Layout;

    /// A problem whose truth is a slanted plane with a hole of unknown pixels.
    fn problem(layout: Layout) -> Problem {
        let (w, h) = (40u32, 30u32);
        let d1: Vec<f32> = (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                if (10..14).contains(&x) && (5..9).contains(&y) {
                    f32::NAN
                } else {
                    1.0 + 0.1 * x as f32 + 0.05 * y as f32
                }
            })
            .collect();
        let scene = synthetic_scene(w, h, vec![(2, d1.clone()), (6, d1)]);
        Problem::new(&scene, layout).expect("problem")
    }

    /// Positions at the true depth of every pixel (unknown pixels: depth 10).
    fn true_positions(problem: &Problem) -> Vec<[f32; 3]> {
        let w = problem.truth.width as usize;
        problem
            .truth
            .d1
            .iter()
            .enumerate()
            .map(|(i, &d)| {
                let z = if d.is_finite() { problem.focal() / f64::from(d) } else { 10.0 };
                let p = problem.back_project((i % w) as f64, (i / w) as f64, z);
                [p.x as f32, p.y as f32, p.z as f32]
            })
            .collect()
    }

    fn rms_d1(problem: &Problem, factor: f64) -> f64 {
        let known: Vec<f64> =
            problem.truth.d1.iter().filter(|d| d.is_finite()).map(|&d| f64::from(d) * factor).collect();
        (known.iter().map(|d| d * d).sum::<f64>() / known.len() as f64).sqrt()
    }

    #[test]
    fn exact_truth_scores_zero() {
        for layout in Layout::ALL {
            let problem = problem(layout);
            let positions = true_positions(&problem);
            let velocities = vec![[1.0f32, 0.0, 0.0]; positions.len()];
            let m = evaluate(&problem, &positions, &velocities);
            assert_eq!(m.pixels, problem.truth.known());
            // f32 positions: errors of order 1e-5 px.
            assert!(m.of_rmse_px < 1e-3, "{layout}: {m:?}");
            assert!(m.structure_rmse_px < 1e-3, "{layout}: {m:?}");
            assert_eq!(m.zflow_rmse, 0.0);
            assert_eq!(m.aae_deg, 0.0);
        }
    }

    #[test]
    fn sideways_velocity_error_scores_known_values() {
        let problem = problem(Layout::Multiview);
        let positions = true_positions(&problem);
        // v = (1, 0.1, 0): angle atan(0.1); vertical flow 0.1 * f / Z = 0.1 * d1.
        let m = evaluate(&problem, &positions, &vec![[1.0, 0.1, 0.0]; positions.len()]);
        assert!((m.aae_deg - 0.1f64.atan().to_degrees()).abs() < 1e-4, "{m:?}");
        assert!((m.of_rmse_px - rms_d1(&problem, 0.1)).abs() < 1e-3, "{m:?}");
        assert!(m.zflow_rmse == 0.0 && m.structure_rmse_px < 1e-3, "{m:?}");
        // v = (1, 0, 0.2): Z flow error 0.2 everywhere.
        let m = evaluate(&problem, &positions, &vec![[1.0, 0.0, 0.2]; positions.len()]);
        assert!((m.zflow_rmse - 0.2).abs() < 1e-6, "{m:?}");
        assert!((m.aae_deg - 0.2f64.atan().to_degrees()).abs() < 1e-4, "{m:?}");
    }

    #[test]
    fn depth_error_scores_as_disparity_error() {
        let problem = problem(Layout::Fb);
        let w = problem.truth.width as usize;
        // Every point twice as far: implied disparity d1 / 2, flow d1 / 2.
        let positions: Vec<[f32; 3]> = problem
            .truth
            .d1
            .iter()
            .enumerate()
            .map(|(i, &d)| {
                let z = if d.is_finite() { 2.0 * problem.focal() / f64::from(d) } else { 10.0 };
                let p = problem.back_project((i % w) as f64, (i / w) as f64, z);
                [p.x as f32, p.y as f32, p.z as f32]
            })
            .collect();
        let m = evaluate(&problem, &positions, &vec![[1.0, 0.0, 0.0]; positions.len()]);
        assert!((m.structure_rmse_px - rms_d1(&problem, 0.5)).abs() < 1e-3, "{m:?}");
        assert!((m.of_rmse_px - rms_d1(&problem, 0.5)).abs() < 1e-3, "{m:?}");
    }

    #[test]
    fn non_finite_and_missing_estimates_are_motionless_points_at_z_far() {
        let problem = problem(Layout::Multiview);
        let pixels = (problem.truth.width * problem.truth.height) as usize;
        let d_far = problem.focal() / problem.depth_range.1;
        let expected_structure = {
            let known: Vec<f64> =
                problem.truth.d1.iter().filter(|d| d.is_finite()).map(|&d| f64::from(d) - d_far).collect();
            (known.iter().map(|e| e * e).sum::<f64>() / known.len() as f64).sqrt()
        };
        let nan = vec![[f32::NAN; 3]; pixels];
        for (positions, velocities) in [(&nan[..], &nan[..]), (&[][..], &[][..])] {
            let m = evaluate(&problem, positions, velocities);
            assert_eq!(m.pixels, problem.truth.known());
            assert!((m.of_rmse_px - rms_d1(&problem, 1.0)).abs() < 1e-9, "{m:?}");
            assert!((m.structure_rmse_px - expected_structure).abs() < 1e-9, "{m:?}");
            assert_eq!(m.zflow_rmse, 0.0);
            assert_eq!(m.aae_deg, 90.0);
        }
        // A point behind the camera is no better than no estimate.
        let behind = vec![[0.0f32, 0.0, -5.0]; pixels];
        let m = evaluate(&problem, &behind, &vec![[1.0, 0.0, 0.0]; pixels]);
        assert!((m.structure_rmse_px - expected_structure).abs() < 1e-9, "{m:?}");
    }

    #[test]
    fn no_known_truth_gives_nan() {
        let scene = synthetic_scene(4, 4, vec![]);
        let problem = Problem::new(&scene, Layout::Multiview).expect("problem");
        let m = evaluate(&problem, &[], &[]);
        assert_eq!(m.pixels, 0);
        assert!(m.of_rmse_px.is_nan() && m.aae_deg.is_nan());
    }
}
