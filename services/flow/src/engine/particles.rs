//! Scene Particles and the per-ray operations on them: diffusion and ray resampling.

use crate::engine::rng::RayRng;

/// One Scene Particle: a hypothesis of the 3D point on its ray and of that point's motion.
///
/// The position is stored as the depth along the ray of the reference camera (camera-frame
/// z), so a particle cannot leave its ray; the world position is `origin + depth * ray`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Particle {
    /// Camera-frame depth in the reference camera, world units.
    pub depth: f32,
    /// World velocity, world units per frame.
    pub velocity: [f32; 3],
    /// Weight within its ray (sums to 1 over a ray after resampling).
    pub weight: f32,
    /// Matching cost at the last evaluation (`handflow`), or `1 / likelihood` (`paper`).
    pub cost: f32,
}

impl Particle {
    /// A particle that holds nothing (the slot of an empty ray).
    pub const EMPTY: Particle = Particle { depth: f32::NAN, velocity: [0.0; 3], weight: 0.0, cost: f32::INFINITY };

    /// Whether this is a real hypothesis.
    pub fn is_valid(&self) -> bool {
        self.depth.is_finite()
    }
}

/// Bounds of the search space, and the scales that turn pixels into world units.
#[derive(Clone, Copy, Debug)]
pub struct SearchSpace {
    /// Inverse depth bounds (1/far, 1/near).
    pub inverse_depth: (f32, f32),
    /// Bound on each velocity component.
    pub speed_bound: f32,
    /// Pixels of disparity per unit of inverse depth across the widest baseline: turns a
    /// diffusion in pixels into one in inverse depth.
    pub pixels_per_inverse_depth: f32,
    /// Focal length of the reference camera in full-resolution pixels.
    pub focal_px: f32,
}

impl SearchSpace {
    /// A particle drawn from the broad initial prior: uniform in inverse depth (uniform in
    /// disparity, where stereo measures), uniform velocity within the bound.
    #[inline(always)]
    pub fn random_particle(&self, rng: &mut RayRng) -> Particle {
        let inverse = rng.range(self.inverse_depth.0, self.inverse_depth.1);
        let b = self.speed_bound;
        Particle {
            depth: 1.0 / inverse,
            velocity: [rng.range(-b, b), rng.range(-b, b), rng.range(-b, b)],
            weight: 0.0,
            cost: f32::INFINITY,
        }
    }

    /// Random-walk diffusion of `sigma_px` full-resolution pixels: in inverse depth as a
    /// disparity across the widest baseline, in velocity as an image displacement at the
    /// particle's depth. Results are reflected into the search space.
    #[inline(always)]
    pub fn diffuse(&self, p: &Particle, sigma_px: f32, rng: &mut RayRng) -> Particle {
        let (lo, hi) = self.inverse_depth;
        let inverse = reflect(1.0 / p.depth + rng.normal() * sigma_px / self.pixels_per_inverse_depth, lo, hi);
        let depth = 1.0 / inverse;
        let dv = sigma_px * depth / self.focal_px;
        let b = self.speed_bound;
        let v = p.velocity;
        Particle {
            depth,
            velocity: [
                reflect(v[0] + rng.normal() * dv, -b, b),
                reflect(v[1] + rng.normal() * dv, -b, b),
                reflect(v[2] + rng.normal() * dv, -b, b),
            ],
            weight: p.weight,
            cost: f32::INFINITY,
        }
    }
}

/// Reflects `x` into `[lo, hi]` (once, then clamps: steps are small against the range).
#[inline(always)]
fn reflect(x: f32, lo: f32, hi: f32) -> f32 {
    let y = if x < lo {
        2.0 * lo - x
    } else if x > hi {
        2.0 * hi - x
    } else {
        x
    };
    y.clamp(lo, hi)
}

/// Ray Resampling: draws `out.len()` particles from `candidates` in proportion to
/// `weights` by systematic resampling (one uniform draw, low variance). Every output gets
/// weight `1 / out.len()`. Returns false, leaving `out` untouched, if all weights are zero.
#[inline(always)]
pub fn ray_resample(candidates: &[Particle], weights: &[f32], out: &mut [Particle], rng: &mut RayRng) -> bool {
    debug_assert_eq!(candidates.len(), weights.len());
    let total: f32 = weights.iter().sum();
    if !(total > 0.0 && total.is_finite()) || out.is_empty() {
        return false;
    }
    let n = out.len();
    let step = total / n as f32;
    let mut target = rng.uniform() * step;
    let mut cumulative = 0.0f32;
    let mut k = 0usize;
    let last = candidates.len() - 1;
    for slot in out.iter_mut() {
        while k < last && cumulative + weights[k] <= target {
            cumulative += weights[k];
            k += 1;
        }
        *slot = candidates[k];
        slot.weight = 1.0 / n as f32;
        target += step;
    }
    true
}

#[cfg(test)]
mod tests {
    use super::*;

    fn particle(depth: f32) -> Particle {
        Particle { depth, velocity: [0.0; 3], weight: 0.0, cost: 0.0 }
    }

    #[test]
    fn ray_resampling_keeps_the_particle_count_and_follows_the_weights() {
        let cands: Vec<Particle> = (1..=14).map(|d| particle(d as f32)).collect();
        let mut weights = vec![0.0f32; 14];
        weights[3] = 3.0;
        weights[9] = 1.0;
        let mut out = [Particle::EMPTY; 10];
        let mut rng = RayRng::for_item(1, 2, 3, 4);
        assert!(ray_resample(&cands, &weights, &mut out, &mut rng));
        assert!(out.iter().all(|p| p.is_valid()));
        let fours = out.iter().filter(|p| p.depth == 4.0).count();
        let tens = out.iter().filter(|p| p.depth == 10.0).count();
        assert_eq!(fours + tens, 10, "only weighted candidates survive");
        // Systematic resampling: counts within one of their expectation (7.5 and 2.5).
        assert!((7..=8).contains(&fours), "{fours}");
        assert!(out.iter().all(|p| (p.weight - 0.1).abs() < 1e-6));
    }

    #[test]
    fn ray_resampling_refuses_all_zero_weights() {
        let cands = [particle(1.0), particle(2.0)];
        let mut out = [Particle::EMPTY; 2];
        let mut rng = RayRng::for_item(0, 0, 0, 0);
        assert!(!ray_resample(&cands, &[0.0, 0.0], &mut out, &mut rng));
        assert!(!out[0].is_valid());
    }

    #[test]
    fn diffusion_stays_inside_the_search_space() {
        let space = SearchSpace {
            inverse_depth: (0.01, 0.1),
            speed_bound: 0.5,
            pixels_per_inverse_depth: 100.0,
            focal_px: 500.0,
        };
        let mut rng = RayRng::for_item(5, 0, 0, 0);
        let mut p = space.random_particle(&mut rng);
        for _ in 0..10_000 {
            p = space.diffuse(&p, 8.0, &mut rng);
            let inv = 1.0 / p.depth;
            assert!((0.01 - 1e-6..=0.1 + 1e-6).contains(&inv));
            assert!(p.velocity.iter().all(|v| v.abs() <= 0.5));
        }
    }
}
