//! Edge-preserving refinement of the per-ray estimate: a joint weighted median.
//!
//! Each ray's inverse depth and velocity components become the weighted median of its
//! neighbourhood, where a neighbour votes with its confidence and with its colour similarity
//! to the ray's pixel. Medians do not average across a depth edge (the minority side loses),
//! and colour weights keep the vote on the ray's own surface.

use crate::matching::image::ColourImage;

/// Per-ray estimate before and after refinement.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RayEstimate {
    /// Inverse of camera-frame depth (0 for an empty ray).
    pub inverse_depth: f32,
    /// World velocity per frame.
    pub velocity: [f32; 3],
    /// Confidence in [0, 1] (0 for an empty ray).
    pub confidence: f32,
}

/// Writes the weighted-median refinement of `input` into `output`. `guide` is the
/// reference image at the resolution of the estimates.
pub fn weighted_median_refine(
    input: &[RayEstimate],
    output: &mut [RayEstimate],
    guide: &ColourImage,
    radius: usize,
    colour_sigma: f32,
) {
    use rayon::prelude::*;
    let (w, h) = (guide.width(), guide.height());
    debug_assert_eq!(input.len(), w * h);
    let inv_two_sigma_sq = 1.0 / (2.0 * colour_sigma * colour_sigma);
    output.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        let mut values = [(0f32, 0f32); 81];
        for (x, out) in row.iter_mut().enumerate() {
            let centre = guide.at(x, y);
            let own = input[y * w + x];
            // An empty ray (sparse mode) stays empty: refinement must not invent estimates.
            if own.confidence <= 0.0 {
                *out = own;
                continue;
            }
            let mut weights = [0f32; 81];
            let mut n = 0;
            let (y0, y1) = (y.saturating_sub(radius), (y + radius).min(h - 1));
            let (x0, x1) = (x.saturating_sub(radius), (x + radius).min(w - 1));
            let mut total = 0.0;
            for ny in y0..=y1 {
                for nx in x0..=x1 {
                    let e = input[ny * w + nx];
                    if e.confidence <= 0.0 {
                        continue;
                    }
                    let c = guide.at(nx, ny);
                    let d = (c[0] - centre[0]).powi(2) + (c[1] - centre[1]).powi(2) + (c[2] - centre[2]).powi(2);
                    let weight = e.confidence * (-d * inv_two_sigma_sq).exp();
                    weights[n] = weight;
                    total += weight;
                    n += 1;
                }
            }
            if n == 0 || total <= 0.0 {
                *out = own;
                continue;
            }
            let mut gather = |f: &dyn Fn(&RayEstimate) -> f32| -> f32 {
                let mut k = 0;
                for ny in y0..=y1 {
                    for nx in x0..=x1 {
                        let e = &input[ny * w + nx];
                        if e.confidence <= 0.0 {
                            continue;
                        }
                        values[k] = (f(e), weights[k]);
                        k += 1;
                    }
                }
                weighted_median(&mut values[..n], total)
            };
            let inverse_depth = gather(&|e| e.inverse_depth);
            let velocity = [gather(&|e| e.velocity[0]), gather(&|e| e.velocity[1]), gather(&|e| e.velocity[2])];
            *out = RayEstimate { inverse_depth, velocity, confidence: own.confidence };
        }
    });
}

/// The value at which the cumulative weight reaches half of `total`.
fn weighted_median(values: &mut [(f32, f32)], total: f32) -> f32 {
    values.sort_unstable_by(|a, b| a.0.total_cmp(&b.0));
    let half = 0.5 * total;
    let mut acc = 0.0;
    for &(v, w) in values.iter() {
        acc += w;
        if acc >= half {
            return v;
        }
    }
    values.last().map_or(0.0, |v| v.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn weighted_median_follows_the_weights() {
        let mut v = [(1.0, 1.0), (5.0, 3.0), (2.0, 1.0)];
        assert_eq!(weighted_median(&mut v, 5.0), 5.0);
        let mut v = [(1.0, 1.0), (5.0, 1.0), (2.0, 1.0)];
        assert_eq!(weighted_median(&mut v, 3.0), 2.0);
    }

    #[test]
    fn refinement_removes_an_outlier_and_keeps_a_colour_edge() {
        // Left half dark at inverse depth 0.1, right half bright at 0.2, one outlier.
        let (w, h) = (12, 8);
        let mut guide = ColourImage::new(w, h);
        let mut input = vec![RayEstimate::default(); w * h];
        for y in 0..h {
            for x in 0..w {
                let right = x >= w / 2;
                guide.pixels_mut()[y * w + x] = if right { [1.0; 4] } else { [-1.0; 4] };
                input[y * w + x] = RayEstimate {
                    inverse_depth: if right { 0.2 } else { 0.1 },
                    velocity: [1.0, 0.0, 0.0],
                    confidence: 1.0,
                };
            }
        }
        input[3 * w + 2].inverse_depth = 0.9;
        input[6 * w + 9] = RayEstimate::default();
        let mut output = vec![RayEstimate::default(); w * h];
        weighted_median_refine(&input, &mut output, &guide, 2, 0.3);
        assert_eq!(output[3 * w + 2].inverse_depth, 0.1, "outlier replaced");
        assert_eq!(output[6 * w + 9], RayEstimate::default(), "an empty ray stays empty");
        for y in 0..h {
            assert_eq!(output[y * w + w / 2 - 1].inverse_depth, 0.1, "edge kept, left");
            assert_eq!(output[y * w + w / 2].inverse_depth, 0.2, "edge kept, right");
        }
    }
}
