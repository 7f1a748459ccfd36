//! Maps of an estimate and its truth: PNG to look at, PFM for other tools.

use std::fs;
use std::path::{Path, PathBuf};

use nalgebra::{Point3, Vector3};

use super::{write_pfm, Problem, SceneError};

/// Optical-flow endpoint error (pixels) shown as white in `error.png`. A fixed scale, so
/// error maps of different runs compare; 3 px is several times the paper's RMSE.
pub const ERROR_SCALE_PX: f64 = 3.0;

/// Grey of `error.png` where the truth is unknown, distinct from the black of no error.
const UNKNOWN_GREY: [u8; 3] = [96, 96, 96];

/// What the estimate of one reference pixel implies, NaN where it cannot be computed.
struct PixelMaps {
    depth: f32,
    disparity: f32,
    flow: [f64; 2],
}

/// Writes the maps of an estimate of the reference view into `dir` (created if needed):
///
/// - `disparity.png`, `disparity_truth.png`: neighbour-view disparity `f / Z`, false colour
///   (turbo) from 0 to the largest true disparity; black where unknown;
/// - `flow.png`, `flow_truth.png`: optical flow of the reference view from `t-1` to `t`,
///   Middlebury colour wheel normalised by the largest true flow; black where unknown;
/// - `error.png`: optical-flow endpoint error, black (0) to white ([`ERROR_SCALE_PX`] and
///   above) through red and yellow; grey where the truth is unknown;
/// - `depth.pfm` (camera-frame Z), `disparity.pfm`, `disparity_truth.pfm` (1 channel) and
///   `scene_flow.pfm` (vx vy vz, world units per frame); NaN where unknown.
///
/// `positions` and `velocities` are as for [`super::evaluate`], but shown as given:
/// non-finite estimates stay unknown here instead of being scored. Returns the paths
/// written.
pub fn write_maps(
    dir: &Path,
    problem: &Problem,
    positions: &[[f32; 3]],
    velocities: &[[f32; 3]],
) -> Result<Vec<PathBuf>, SceneError> {
    let (width, height) = (problem.truth.width, problem.truth.height);
    let pixels = width as usize * height as usize;
    for (what, got) in [("positions", positions.len()), ("velocities", velocities.len())] {
        if got != pixels {
            return Err(SceneError::EstimateSize { what, got, expected: pixels, width, height });
        }
    }
    fs::create_dir_all(dir).map_err(|e| SceneError::io(dir, e))?;

    let estimate: Vec<PixelMaps> = positions.iter().zip(velocities).map(|(p, v)| pixel_maps(problem, p, v)).collect();
    let truth = &problem.truth.d1;
    // The true flow is (d1, 0), so one scale serves disparity and flow.
    let scale = match problem.truth.max_d1() {
        m if m > 0.0 => m,
        _ => estimate.iter().map(|e| f64::from(e.disparity)).filter(|d| d.is_finite()).fold(1.0, f64::max),
    };

    let mut written = Vec::new();
    let mut png = |name: &str, rgb: Vec<[u8; 3]>| -> Result<(), SceneError> {
        let path = dir.join(name);
        let bytes: Vec<u8> = rgb.into_iter().flatten().collect();
        image::save_buffer_with_format(&path, &bytes, width, height, image::ColorType::Rgb8, image::ImageFormat::Png)
            .map_err(|source| match source {
            image::ImageError::IoError(e) => SceneError::io(&path, e),
            source => SceneError::Encode { path: path.clone(), source },
        })?;
        written.push(path);
        Ok(())
    };
    let disparity_colour = |d: f64| if d.is_finite() { turbo(d / scale) } else { [0, 0, 0] };
    png("disparity.png", estimate.iter().map(|e| disparity_colour(f64::from(e.disparity))).collect())?;
    png("disparity_truth.png", truth.iter().map(|&d| disparity_colour(f64::from(d))).collect())?;
    png("flow.png", estimate.iter().map(|e| flow_colour(e.flow[0] / scale, e.flow[1] / scale)).collect())?;
    png("flow_truth.png", truth.iter().map(|&d| flow_colour(f64::from(d) / scale, 0.0)).collect())?;
    let error = estimate.iter().zip(truth).map(|(e, &d)| {
        if !d.is_finite() {
            return UNKNOWN_GREY;
        }
        // A flow that cannot be computed is as wrong as can be shown.
        let endpoint = (e.flow[0] - f64::from(d)).hypot(e.flow[1]);
        heat(if endpoint.is_finite() { endpoint / ERROR_SCALE_PX } else { 1.0 })
    });
    png("error.png", error.collect())?;

    let mut pfm = |name: &str, channels: usize, data: Vec<f32>| -> Result<(), SceneError> {
        let path = dir.join(name);
        write_pfm(&path, width, height, channels, &data).map_err(|e| SceneError::io(&path, e))?;
        written.push(path);
        Ok(())
    };
    pfm("depth.pfm", 1, estimate.iter().map(|e| e.depth).collect())?;
    pfm("disparity.pfm", 1, estimate.iter().map(|e| e.disparity).collect())?;
    pfm("disparity_truth.pfm", 1, truth.clone())?;
    pfm("scene_flow.pfm", 3, velocities.iter().flatten().copied().collect())?;
    Ok(written)
}

/// Depth, disparity and optical flow implied by one estimate.
fn pixel_maps(problem: &Problem, position: &[f32; 3], velocity: &[f32; 3]) -> PixelMaps {
    let camera = problem.reference_camera();
    let p = Point3::new(f64::from(position[0]), f64::from(position[1]), f64::from(position[2]));
    let v = Vector3::new(f64::from(velocity[0]), f64::from(velocity[1]), f64::from(velocity[2]));
    if !p.iter().all(|c| c.is_finite()) {
        return PixelMaps { depth: f32::NAN, disparity: f32::NAN, flow: [f64::NAN; 2] };
    }
    let z = camera.world_to_camera(&p).z;
    let disparity = if z > 0.0 { problem.focal() / z } else { f64::NAN };
    let flow = match (camera.project(&p), camera.project(&(p - v))) {
        (Some(now), Some(before)) if v.iter().all(|c| c.is_finite()) => [now.x - before.x, now.y - before.y],
        _ => [f64::NAN; 2],
    };
    PixelMaps { depth: z as f32, disparity: disparity as f32, flow }
}

/// The Middlebury flow colour wheel (Baker et al., `colorcode.cpp`): hue from the
/// direction, saturation from the magnitude (`(fx, fy)` already normalised so 1 is the
/// largest expected flow; beyond it the colour darkens). Non-finite flow is black.
pub fn flow_colour(fx: f64, fy: f64) -> [u8; 3] {
    if !(fx.is_finite() && fy.is_finite()) {
        return [0, 0, 0];
    }
    let wheel = colour_wheel();
    let n = wheel.len();
    let radius = fx.hypot(fy);
    let angle = (-fy).atan2(-fx) / std::f64::consts::PI;
    let fk = (angle + 1.0) / 2.0 * (n - 1) as f64;
    let k0 = (fk.floor() as usize).min(n - 1);
    let k1 = (k0 + 1) % n;
    let f = fk - k0 as f64;
    std::array::from_fn(|c| {
        let mut col = (1.0 - f) * wheel[k0][c] / 255.0 + f * wheel[k1][c] / 255.0;
        if radius <= 1.0 {
            // Towards white at the centre.
            col = 1.0 - radius * (1.0 - col);
        } else {
            col *= 0.75;
        }
        (255.0 * col).floor().clamp(0.0, 255.0) as u8
    })
}

/// The 55 colours of the Middlebury wheel: red, yellow, green, cyan, blue, magenta, with
/// segment lengths chosen for perceptual similarity.
fn colour_wheel() -> Vec<[f64; 3]> {
    const SEGMENTS: [usize; 6] = [15, 6, 4, 11, 13, 6]; // RY YG GC CB BM MR
    let mut wheel = Vec::with_capacity(SEGMENTS.iter().sum());
    for (segment, &len) in SEGMENTS.iter().enumerate() {
        for i in 0..len {
            let up = 255.0 * i as f64 / len as f64;
            let down = 255.0 - up;
            wheel.push(match segment {
                0 => [255.0, up, 0.0],
                1 => [down, 255.0, 0.0],
                2 => [0.0, 255.0, up],
                3 => [0.0, down, 255.0],
                4 => [up, 0.0, 255.0],
                _ => [255.0, 0.0, down],
            });
        }
    }
    wheel
}

/// Turbo false colour of `t` in [0, 1] (clamped): Google's polynomial approximation
/// (Mikhailov 2019), dark blue to dark red through green and yellow.
pub fn turbo(t: f64) -> [u8; 3] {
    let x = t.clamp(0.0, 1.0);
    let powers = [1.0, x, x * x, x * x * x, x.powi(4), x.powi(5)];
    let channel = |coefficients: [f64; 6]| {
        let v: f64 = coefficients.iter().zip(powers).map(|(c, p)| c * p).sum();
        (255.0 * v.clamp(0.0, 1.0)).round() as u8
    };
    [
        channel([0.13572138, 4.61539260, -42.66032258, 132.13108234, -152.94239396, 59.28637943]),
        channel([0.09140261, 2.19418839, 4.84296658, -14.18503333, 4.27729857, 2.82956604]),
        channel([0.10667330, 12.64194608, -60.58204836, 110.36276771, -89.90310912, 27.34824973]),
    ]
}

/// Black (0) to white (1, clamped) through red and yellow.
fn heat(t: f64) -> [u8; 3] {
    let t = t.clamp(0.0, 1.0);
    std::array::from_fn(|c| (255.0 * (3.0 * t - c as f64).clamp(0.0, 1.0)).round() as u8)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval::middlebury::testing::synthetic_scene;
    use crate::eval::middlebury::{read_pfm, Layout};

    #[test]
    fn colour_wheel_follows_the_middlebury_key() {
        assert_eq!(flow_colour(0.0, 0.0), [255, 255, 255], "no flow is white");
        assert_eq!(flow_colour(1.0, 0.0), [255, 0, 0], "rightwards is red");
        let left = flow_colour(-1.0, 0.0);
        assert!(left[0] == 0 && left[2] == 255, "leftwards is blue-cyan: {left:?}");
        // Image y points down: downwards is orange-yellow, upwards blue-violet.
        let down = flow_colour(0.0, 1.0);
        assert!(down[0] == 255 && down[1] > 200 && down[2] == 0, "downwards: {down:?}");
        let up = flow_colour(0.0, -1.0);
        assert!(up[0] < 150 && up[1] == 0 && up[2] == 255, "upwards: {up:?}");
        assert_eq!(flow_colour(f64::NAN, 0.0), [0, 0, 0]);
        let half = flow_colour(0.5, 0.0);
        assert_eq!(half, [255, 127, 127], "half the largest flow is half saturated");
        assert_eq!(flow_colour(2.0, 0.0), [191, 0, 0], "beyond the largest flow it darkens");
    }

    #[test]
    fn false_colours_run_dark_to_bright() {
        let low = turbo(0.0);
        let mid = turbo(0.5);
        let high = turbo(1.0);
        assert!(low.iter().all(|&c| c < 60), "{low:?}");
        assert!(mid[1] > 200, "turbo's middle is green: {mid:?}");
        assert!(high[0] > 100 && high[1] < 40 && high[2] < 40, "turbo ends dark red: {high:?}");
        assert_eq!(heat(0.0), [0, 0, 0]);
        assert_eq!(heat(1.0), [255, 255, 255]);
        assert_eq!(heat(1.0 / 3.0), [255, 0, 0]);
    }

    #[test]
    fn maps_of_the_exact_truth() {
        let (w, h) = (24u32, 16u32);
        let d1: Vec<f32> =
            (0..w * h).map(|i| if i % 7 == 0 { f32::NAN } else { 1.0 + (i % w) as f32 * 0.25 }).collect();
        let scene = synthetic_scene(w, h, vec![(2, d1.clone()), (6, d1)]);
        let problem = Problem::new(&scene, Layout::Multiview).expect("problem");
        let positions: Vec<[f32; 3]> = problem
            .truth
            .d1
            .iter()
            .enumerate()
            .map(|(i, &d)| {
                if !d.is_finite() {
                    return [f32::NAN; 3];
                }
                let p = problem.back_project(
                    (i % w as usize) as f64,
                    (i / w as usize) as f64,
                    problem.focal() / f64::from(d),
                );
                [p.x as f32, p.y as f32, p.z as f32]
            })
            .collect();
        let velocities = vec![[1.0f32, 0.0, 0.0]; positions.len()];
        let dir = tempfile::tempdir().expect("tempdir");
        let out = dir.path().join("maps");
        let written = write_maps(&out, &problem, &positions, &velocities).expect("maps");
        let names: Vec<String> =
            written.iter().filter_map(|p| p.file_name()).map(|n| n.to_string_lossy().into_owned()).collect();
        for name in [
            "disparity.png",
            "disparity_truth.png",
            "flow.png",
            "flow_truth.png",
            "error.png",
            "depth.pfm",
            "scene_flow.pfm",
            "disparity.pfm",
        ] {
            assert!(names.iter().any(|n| n == name), "{name} missing from {names:?}");
        }
        for path in &written {
            assert!(path.is_file(), "{}", path.display());
        }
        let rgb = |name: &str| image::open(out.join(name)).expect("png").into_rgb8();
        let (flow, flow_truth) = (rgb("flow.png"), rgb("flow_truth.png"));
        assert_eq!(flow.dimensions(), (w, h));
        let largest = flow.as_raw().iter().zip(flow_truth.as_raw()).map(|(a, b)| a.abs_diff(*b)).max();
        assert!(largest.is_some_and(|d| d <= 1), "flow maps differ by {largest:?}");
        let error = rgb("error.png");
        for (i, (pixel, d)) in error.pixels().zip(&problem.truth.d1).enumerate() {
            let expected = if d.is_finite() { [0, 0, 0] } else { UNKNOWN_GREY };
            assert_eq!(pixel.0, expected, "error.png pixel {i}");
        }
        let (pw, ph, channels, depth) = read_pfm(&out.join("depth.pfm")).expect("depth.pfm");
        assert_eq!((pw, ph, channels), (w, h, 1));
        for (z, d) in depth.iter().zip(&problem.truth.d1) {
            if d.is_finite() {
                assert!((f64::from(*z) - problem.focal() / f64::from(*d)).abs() < 1e-3, "{z} vs d1 {d}");
            } else {
                assert!(z.is_nan());
            }
        }
        let (_, _, channels, flow3) = read_pfm(&out.join("scene_flow.pfm")).expect("scene_flow.pfm");
        assert_eq!(channels, 3);
        assert_eq!(flow3, velocities.iter().flatten().copied().collect::<Vec<_>>());
    }

    #[test]
    fn estimates_of_the_wrong_size_are_refused() {
        let scene = synthetic_scene(4, 4, vec![]);
        let problem = Problem::new(&scene, Layout::Fb).expect("problem");
        let dir = tempfile::tempdir().expect("tempdir");
        let err = write_maps(dir.path(), &problem, &[[0.0; 3]; 3], &[[0.0; 3]; 16]).expect_err("short");
        assert!(err.to_string().contains("positions: 3 entries"), "{err}");
    }
}
