//! `handflow bench cluster`: clustering and labelling time per frame on a synthetic
//! signer-like point set (head, two moving hands, a tenth of clutter), against EM on every
//! point without subsampling in the same run.

use std::time::Instant;

use handflow_cluster::em::{fit_mixture, EmConfig};
use handflow_cluster::tracks::{Tracker, TrackerConfig};
use handflow_cluster::WeightedPoint;
use nalgebra::Vector3;

/// What the benchmark measured.
#[derive(Clone, Debug, serde::Serialize)]
pub struct ClusterBench {
    /// Points per frame.
    pub points: usize,
    /// Frames timed.
    pub frames: usize,
    /// EM (subsampled, the default) plus labelling, mean milliseconds per frame.
    pub ms_per_frame: f64,
    /// Slowest frame, milliseconds.
    pub ms_per_frame_max: f64,
    /// Baseline: EM on every point, milliseconds per frame.
    pub baseline_ms_per_frame: f64,
    /// `baseline_ms_per_frame / ms_per_frame`.
    pub speedup: f64,
    /// Mean EM iterations per frame.
    pub iterations: f64,
    /// Largest distance between a track and the object it follows, metres (a check that
    /// the fast path still tracks).
    pub max_track_error_m: f64,
}

/// Deterministic uniform numbers in [0, 1) (splitmix64).
struct Uniform(u64);

impl Uniform {
    fn next(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Roughly normal: the sum of four uniforms, centred and scaled to unit variance.
    fn normal(&mut self) -> f64 {
        ((0..4).map(|_| self.next()).sum::<f64>() - 2.0) * 3.0f64.sqrt()
    }
}

/// The three objects' positions and velocities at time `t`: a still head, hands circling.
fn objects(t: f64) -> [(Vector3<f64>, Vector3<f64>); 3] {
    let w = 3.0;
    [
        (Vector3::new(0.0, 1.6, 0.0), Vector3::zeros()),
        (
            Vector3::new(0.25 + 0.1 * (w * t).cos(), 1.1 + 0.1 * (w * t).sin(), 0.3),
            Vector3::new(-0.3 * (w * t).sin(), 0.3 * (w * t).cos(), 0.0),
        ),
        (
            Vector3::new(-0.25 - 0.1 * (w * t).cos(), 1.1 + 0.1 * (w * t).sin(), 0.3),
            Vector3::new(0.3 * (w * t).sin(), 0.3 * (w * t).cos(), 0.0),
        ),
    ]
}

fn frame_points(rng: &mut Uniform, t: f64, n: usize, out: &mut Vec<WeightedPoint>) {
    out.clear();
    let objs = objects(t);
    for i in 0..n {
        let r = rng.next();
        let (p, v, spread) = if r < 0.45 {
            (objs[0].0, objs[0].1, 0.05)
        } else if r < 0.675 {
            (objs[1].0, objs[1].1, 0.03)
        } else if r < 0.9 {
            (objs[2].0, objs[2].1, 0.03)
        } else {
            // Clutter anywhere in a 4 m box.
            (Vector3::new(4.0 * rng.next() - 2.0, 3.0 * rng.next(), 4.0 * rng.next() - 3.0), Vector3::zeros(), 0.0)
        };
        out.push(WeightedPoint {
            position: p + Vector3::new(rng.normal(), rng.normal(), rng.normal()) * spread,
            velocity: v + Vector3::new(rng.normal(), rng.normal(), rng.normal()) * 0.1,
            weight: 0.5 + (i % 4) as f64 * 0.25,
        });
    }
}

/// Runs `frames` frames of `points` points at 30 fps.
pub fn bench_cluster(points: usize, frames: usize) -> ClusterBench {
    let fps = 30.0;
    let config = EmConfig::default();
    let mut rng = Uniform(7);
    let mut pts = Vec::with_capacity(points);
    let mut tracker = Tracker::new(TrackerConfig::default(), Vector3::y(), Vector3::x());
    let (mut total, mut worst, mut error) = (0.0f64, 0.0f64, 0.0f64);
    let mut iterations = 0usize;
    for f in 0..frames {
        let t = f as f64 / fps;
        frame_points(&mut rng, t, points, &mut pts);
        let initial = tracker.predictions(t).unwrap_or_else(|| objects(t));
        let started = Instant::now();
        let fit = fit_mixture(&pts, &initial, &config);
        let tracks = tracker.update(t, fit.as_ref());
        iterations += fit.as_ref().map_or(0, |f| f.iterations);
        let seconds = started.elapsed().as_secs_f64();
        total += seconds;
        worst = worst.max(seconds);
        for (k, (p, _)) in tracks.iter().zip(objects(t)) {
            error = error.max((k.position - p).norm());
        }
    }
    let baseline_config = EmConfig { max_points: points, ..config };
    let mut baseline = 0.0;
    let baseline_frames = frames.clamp(1, 5);
    for f in 0..baseline_frames {
        let t = f as f64 / fps;
        frame_points(&mut rng, t, points, &mut pts);
        let started = Instant::now();
        let _ = fit_mixture(&pts, &objects(t), &baseline_config);
        baseline += started.elapsed().as_secs_f64();
    }
    let ms = total * 1e3 / frames.max(1) as f64;
    let baseline_ms = baseline * 1e3 / baseline_frames as f64;
    ClusterBench {
        points,
        frames,
        ms_per_frame: ms,
        ms_per_frame_max: worst * 1e3,
        baseline_ms_per_frame: baseline_ms,
        speedup: baseline_ms / ms.max(1e-9),
        iterations: iterations as f64 / frames.max(1) as f64,
        max_track_error_m: error,
    }
}
