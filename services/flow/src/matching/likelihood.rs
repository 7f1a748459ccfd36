//! How well a Scene Particle explains the images: the paper's colour variance (equations 3
//! and 6) and handflow's robust windowed matching cost.

use crate::matching::camera::LevelProjection;
use crate::matching::image::{ColourImage, Rgba};

/// Most images one likelihood looks at (3 frames x 8 cameras).
pub const MAX_IMAGES: usize = 24;
/// Largest support window radius.
pub const MAX_WINDOW_RADIUS: usize = 2;
/// Most samples in a support window. Kept small: the window is rebuilt for every ray at
/// every iteration, and a larger array would be mostly zero-filling.
pub const MAX_WINDOW: usize = (2 * MAX_WINDOW_RADIUS + 1) * (2 * MAX_WINDOW_RADIUS + 1);

/// One image the likelihood samples: a camera at a frame, on the current pyramid level.
#[derive(Clone, Copy)]
pub struct MatchImage<'a> {
    /// Frame offset from the estimated frame: -1 (t-1), 0 (t) or +1 (t+1). The point seen
    /// at frame t+k sits at `r + k v` under the constant-velocity model.
    pub offset: f32,
    /// The image.
    pub image: &'a ColourImage,
    /// Its camera's projection onto this level.
    pub projection: &'a LevelProjection,
    /// True for the reference camera at frame t, whose pixel defines the ray.
    pub is_reference_now: bool,
    /// Quarter turns of this camera's image relative to the reference's
    /// ([`crate::matching::camera::window_quarter_turns`]): the windows compared on it are
    /// the reference window turned by as much.
    pub window_turns: u8,
}

/// Equation 3 (with two frames) or 6 (with three): `1 / sqrt(var^2 + eps^2)` where `var` is
/// the variance of the colours the particle projects to in every image, summed over
/// channels. Images the point falls outside of do not vote; with fewer than two votes
/// there is no evidence and the likelihood is that of a maximally inconsistent point.
#[inline(always)]
///
/// `reference_colour`, when given, is the colour of the ray's own pixel in the reference
/// image at t: every particle of the ray projects there, so the caller samples it once per
/// ray and the reference image is skipped here.
pub fn variance_likelihood(
    images: &[MatchImage<'_>],
    reference_colour: Option<Rgba>,
    position: [f32; 3],
    velocity: [f32; 3],
    epsilon: f32,
) -> f32 {
    // Four lanes (the pad lane is zero everywhere) so the sums vectorise.
    let mut sum = [0f32; 4];
    let mut sum_sq = [0f32; 4];
    let mut n = 0u32;
    if let Some(c) = reference_colour {
        for k in 0..4 {
            sum[k] += c[k];
            sum_sq[k] += c[k] * c[k];
        }
        n += 1;
    }
    for img in images {
        if img.is_reference_now && reference_colour.is_some() {
            continue;
        }
        let p = displaced(position, velocity, img.offset);
        let Some([u, v]) = img.projection.project(p) else { continue };
        let Some(c) = img.image.sample(u, v) else { continue };
        for k in 0..4 {
            sum[k] += c[k];
            sum_sq[k] += c[k] * c[k];
        }
        n += 1;
    }
    variance_to_likelihood(sum, sum_sq, n, epsilon)
}

/// Equation 3 from the colour sums of `n` samples.
#[inline(always)]
fn variance_to_likelihood(sum: [f32; 4], sum_sq: [f32; 4], n: u32, epsilon: f32) -> f32 {
    let sum_sq = sum_sq[0] + sum_sq[1] + sum_sq[2];
    // Normalised images have unit variance per channel; 3 channels summed.
    const NO_EVIDENCE_VARIANCE: f32 = 3.0;
    let var = if n >= 2 {
        let inv = 1.0 / n as f32;
        (sum_sq * inv - (sum[0] * sum[0] + sum[1] * sum[1] + sum[2] * sum[2]) * inv * inv).max(0.0)
    } else {
        NO_EVIDENCE_VARIANCE
    };
    1.0 / (var * var + epsilon * epsilon).sqrt()
}

/// The reference window of a ray: the pixels around it in the reference image at frame t.
pub struct ReferenceWindow {
    /// Colours, row-major over the window.
    pub colours: [Rgba; MAX_WINDOW],
    /// Number of samples used.
    pub len: usize,
    /// Half-size in samples.
    pub radius: usize,
    /// Spacing of samples, pixels.
    pub step: usize,
}

impl ReferenceWindow {
    /// Gathers the `(2r+1)^2` window around pixel `(x, y)` of `image`, samples `step`
    /// pixels apart, clamped at borders.
    pub fn gather(image: &ColourImage, x: usize, y: usize, radius: usize, step: usize) -> Self {
        let mut w =
            ReferenceWindow { colours: [[0.0; 4]; MAX_WINDOW], len: 0, radius: radius.min(MAX_WINDOW_RADIUS), step };
        let r = radius.min(MAX_WINDOW_RADIUS) as isize;
        let step = step as isize;
        let (wmax, hmax) = (image.width() as isize - 1, image.height() as isize - 1);
        for dy in -r..=r {
            for dx in -r..=r {
                let sx = (x as isize + dx * step).clamp(0, wmax) as usize;
                let sy = (y as isize + dy * step).clamp(0, hmax) as usize;
                w.colours[w.len] = image.at(sx, sy);
                w.len += 1;
            }
        }
        w
    }

    /// The window around the sub-pixel position `(u, v)` of `image`, each sample bilinear,
    /// clamped at borders: the reference window of a ray whose centre falls between pixels.
    pub fn gather_at(image: &ColourImage, u: f32, v: f32, radius: usize, step: usize) -> Self {
        let radius = radius.min(MAX_WINDOW_RADIUS);
        let mut w = ReferenceWindow { colours: [[0.0; 4]; MAX_WINDOW], len: 0, radius, step };
        let (wmax, hmax) = ((image.width() - 1) as f32, (image.height() - 1) as f32);
        let (r, step) = (radius as isize, step as f32);
        for dy in -r..=r {
            for dx in -r..=r {
                let x = (u + dx as f32 * step).clamp(0.0, wmax);
                let y = (v + dy as f32 * step).clamp(0.0, hmax);
                // Inside by construction, so `sample` never refuses.
                w.colours[w.len] = image.sample(x, y).unwrap_or([0.0; 4]);
                w.len += 1;
            }
        }
        w
    }

    /// The window as an image turned by `quarter_turns` clockwise quarter turns sees it:
    /// sample `(dx, dy)` of the result is the reference's sample at the offset that turns
    /// onto `(dx, dy)`. Zero turns give the window itself.
    pub fn turned(&self, quarter_turns: u8) -> ReferenceWindow {
        let mut out = ReferenceWindow { ..*self };
        let r = self.radius as isize;
        let side = 2 * r + 1;
        if quarter_turns.is_multiple_of(4) || self.len != (side * side) as usize {
            return out;
        }
        for dy in -r..=r {
            for dx in -r..=r {
                // Clockwise on the image (y down): (x, y) -> (-y, x) per quarter turn, so the
                // source is the target turned back.
                let (sx, sy) = match quarter_turns % 4 {
                    1 => (dy, -dx),
                    2 => (-dx, -dy),
                    _ => (-dy, dx),
                };
                out.colours[((dy + r) * side + dx + r) as usize] = self.colours[((sy + r) * side + sx + r) as usize];
            }
        }
        out
    }
}

/// Candidates [`robust_window_costs`] takes at once: eight `f32` lanes fill an AVX2 register.
pub const COST_LANES: usize = 8;

/// handflow's matching cost of up to [`COST_LANES`] particles of one ray (their world points
/// `position` and velocities `velocity`, one lane each, `count` of them used), written into
/// `out[..count]`; lower is better. Per particle: for every image other than the reference
/// at t, the truncated L1 colour difference between the reference window and the window
/// around the particle's projection (the window translated, not warped: at the scale of a
/// few pixels the local warp between views is close to a translation, once a view mounted
/// a quarter turn from the reference has its window turned, [`MatchImage::window_turns`]), averaged over
/// samples and channels. Only the best `keep` images are averaged, so views where the point
/// is occluded do not spoil it. Images the point falls outside of do not vote at all:
/// counting them as mismatches would bias every ray near the border towards hypotheses
/// that keep their projections inside the frame. With no vote, the cost is the maximum.
///
/// Every image projects all the points together ([`LevelProjection::project_lanes`]), and
/// the window's bounds test and texel index are computed lane by lane; then each point's
/// window is compared on its own. Each cost is that of the particle costed alone, bit for
/// bit (the tests keep that one-particle form). Measured on the shared real session: the
/// lens distortion alone took a sixth of the engine's time when each candidate was
/// projected on its own.
// Lane loops index several arrays by lane; iterators would hide that.
#[allow(clippy::too_many_arguments, clippy::needless_range_loop)]
#[inline(always)]
pub fn robust_window_costs(
    images: &[MatchImage<'_>],
    reference: &ReferenceWindow,
    position: &[[f32; COST_LANES]; 3],
    velocity: &[[f32; COST_LANES]; 3],
    count: usize,
    truncation: f32,
    keep: usize,
    out: &mut [f32; COST_LANES],
) {
    let count = count.min(COST_LANES);
    // One row per image, one lane per candidate; slots a candidate does not fill stay
    // infinite, so they sort last.
    let mut costs = [[f32::INFINITY; COST_LANES]; MAX_IMAGES];
    let mut n = [0usize; COST_LANES];
    let norm = 1.0 / (reference.len as f32 * 3.0);
    let (mut present, mut seen) = (0u8, [0u8; COST_LANES]);
    let mut turned = None;
    for img in images {
        if img.is_reference_now {
            continue;
        }
        // A view turned relative to the reference (a camera mounted sideways) is compared
        // with the window turned as much, built once for consecutive views of that turn.
        let reference = if img.window_turns == 0 {
            reference
        } else {
            if turned.as_ref().map(|(turns, _)| *turns) != Some(img.window_turns) {
                turned = Some((img.window_turns, reference.turned(img.window_turns)));
            }
            turned.as_ref().map_or(reference, |(_, window)| window)
        };
        let bit = 1u8 << ((img.offset as i32 + 1).clamp(0, 2) as u32);
        present |= bit;
        let k = img.offset;
        // Plain lane loops: `array::from_fn` here was not always inlined, and outside this
        // function its code is not compiled for AVX2.
        let mut points = [[0f32; COST_LANES]; 3];
        for axis in 0..3 {
            for l in 0..COST_LANES {
                points[axis][l] = position[axis][l] + k * velocity[axis][l];
            }
        }
        let (mut u, mut v) = ([0f32; COST_LANES], [0f32; COST_LANES]);
        let in_front = img.projection.project_lanes(&points, &mut u, &mut v);
        // Whether each point's window centre is inside the image, and its texel patch too.
        let (w, h) = (img.image.width(), img.image.height());
        let (wmax, hmax) = ((w - 1) as f32, (h - 1) as f32);
        let r = reference.radius as i32;
        let (mut inside, mut interior) = ([false; COST_LANES], [false; COST_LANES]);
        let (mut cx, mut cy) = ([0i32; COST_LANES], [0i32; COST_LANES]);
        let (mut fx, mut fy) = ([0f32; COST_LANES], [0f32; COST_LANES]);
        for l in 0..COST_LANES {
            inside[l] = in_front[l] && u[l] >= 0.0 && v[l] >= 0.0 && u[l] <= wmax && v[l] <= hmax;
            // Inside, u and v are >= 0, so the conversion truncates to their floor.
            (cx[l], cy[l]) = (u[l] as i32, v[l] as i32);
            (fx[l], fy[l]) = (u[l] - cx[l] as f32, v[l] - cy[l] as f32);
            interior[l] = cx[l] >= r && cy[l] >= r && cx[l] + r + 1 < w as i32 && cy[l] + r + 1 < h as i32;
        }
        for l in 0..count {
            if !inside[l] {
                continue;
            }
            let corner = || (cy[l] - r) as usize * w + (cx[l] - r) as usize;
            let c = match (reference.step, reference.radius) {
                (1, 1) if interior[l] => {
                    window_cost_at::<3, 4>(img.image, reference, corner(), fx[l], fy[l], truncation)
                }
                (1, 2) if interior[l] => {
                    window_cost_at::<5, 6>(img.image, reference, corner(), fx[l], fy[l], truncation)
                }
                _ => window_cost_clamped(img.image, reference, u[l], v[l], truncation),
            };
            costs[n[l]][l] = c * norm;
            n[l] += 1;
            seen[l] |= bit;
        }
    }
    for l in 0..count {
        // A frame the point left entirely gives no evidence of the motion: count it as one
        // full mismatch, or moving out of every image would be the cheapest explanation of
        // anything.
        for _ in 0..(present & !seen[l]).count_ones() {
            costs[n[l]][l] = truncation;
            n[l] += 1;
        }
    }
    let most = n[..count].iter().copied().max().unwrap_or(0);
    if most <= SORTED_ROWS {
        // Every lane sorted at once by a fixed network: the insertion sort's branches
        // mispredicted on every candidate. The sorted values are the same, so are the sums.
        let rows: &mut [[f32; COST_LANES]; SORTED_ROWS] = (&mut costs[..SORTED_ROWS]).try_into().expect("rows");
        for &(a, b) in SORT_NETWORK.iter() {
            let (a, b) = (usize::from(a), usize::from(b));
            let (x, y) = (rows[a], rows[b]);
            for l in 0..COST_LANES {
                (rows[a][l], rows[b][l]) = if x[l] < y[l] { (x[l], y[l]) } else { (y[l], x[l]) };
            }
        }
        for l in 0..count {
            out[l] = if n[l] == 0 {
                truncation
            } else {
                let keep = keep.clamp(1, n[l]);
                rows[..keep].iter().map(|row| row[l]).sum::<f32>() / keep as f32
            };
        }
        return;
    }
    for l in 0..count {
        let mut values: [f32; MAX_IMAGES] = std::array::from_fn(|i| costs[i][l]);
        out[l] = if n[l] == 0 { truncation } else { mean_of_smallest(&mut values[..n[l]], keep.clamp(1, n[l])) };
    }
}

/// Rows [`robust_window_costs`] sorts with [`SORT_NETWORK`]: 11 images of four cameras at
/// three frames, plus up to three frames counted as unseen, fit.
const SORTED_ROWS: usize = 16;

/// Batcher's odd-even merge sort of [`SORTED_ROWS`] values: 63 compare-exchanges, the same
/// for every input, so eight lanes go through it together.
const SORT_NETWORK: [(u8, u8); 63] = odd_even_merge_sort();

const fn odd_even_merge_sort() -> [(u8, u8); 63] {
    let mut pairs = [(0u8, 0u8); 63];
    let mut len = 0;
    let mut p = 1;
    while p < SORTED_ROWS {
        let mut k = p;
        while k >= 1 {
            let mut j = k % p;
            while j + k < SORTED_ROWS {
                let mut i = 0;
                while i < k && i + j + k < SORTED_ROWS {
                    if (i + j) / (2 * p) == (i + j + k) / (2 * p) {
                        pairs[len] = ((i + j) as u8, (i + j + k) as u8);
                        len += 1;
                    }
                    i += 1;
                }
                j += 2 * k;
            }
            k /= 2;
        }
        p *= 2;
    }
    assert!(len == 63, "Batcher's network of 16 has 63 comparators");
    pairs
}

/// The mean of the `keep` smallest values. An insertion sort: `values` holds at most
/// [`MAX_IMAGES`] costs, where a general selection's call and set-up cost more than the
/// sort itself.
#[inline(always)]
fn mean_of_smallest(values: &mut [f32], keep: usize) -> f32 {
    for i in 1..values.len() {
        let v = values[i];
        let mut j = i;
        while j > 0 && values[j - 1] > v {
            values[j] = values[j - 1];
            j -= 1;
        }
        values[j] = v;
    }
    values[..keep].iter().sum::<f32>() / keep as f32
}

/// The general case: every sample bilinear on its own, clamped to the image.
fn window_cost_clamped(image: &ColourImage, reference: &ReferenceWindow, u: f32, v: f32, truncation: f32) -> f32 {
    let wmax = (image.width() - 1) as f32;
    let hmax = (image.height() - 1) as f32;
    let mut sum = 0.0f32;
    let side = 2 * reference.radius + 1;
    let (r, step) = (reference.radius as f32, reference.step as f32);
    for s in 0..reference.len {
        let dx = ((s % side) as f32 - r) * step;
        let dy = ((s / side) as f32 - r) * step;
        let x = (u + dx).clamp(0.0, wmax);
        let y = (v + dy).clamp(0.0, hmax);
        // Inside by construction, so `sample` never refuses; a refusal would be a bug.
        let c = image.sample(x, y).unwrap_or([f32::INFINITY; 4]);
        let r = reference.colours[s];
        for k in 0..3 {
            sum += (c[k] - r[k]).abs().min(truncation);
        }
    }
    sum
}

/// The hot case: a unit-step window whose texel patch lies inside the image. All samples
/// share one fractional offset, so the `(2r+2)^2` texels are interpolated along rows once
/// and the rows blended per sample: 16 loads for a 3x3 window instead of 36. Radii 1 and 2
/// are compiled with their sizes known, so the loops unroll into SIMD over the four lanes.
/// This is the window whose top-left texel is `corner` (a pixel index), at fractional
/// offsets `fx`, `fy` within the texels.
#[inline(always)]
fn window_cost_at<const SIDE: usize, const TEXELS: usize>(
    image: &ColourImage,
    reference: &ReferenceWindow,
    corner: usize,
    fx: f32,
    fy: f32,
    truncation: f32,
) -> f32 {
    let w = image.width();
    let pixels = image.pixels();
    let mut acc = [0f32; 4];
    let mut upper = lerp_row::<SIDE, TEXELS>(pixels, corner, fx);
    for j in 0..SIDE {
        let lower = lerp_row::<SIDE, TEXELS>(pixels, corner + (j + 1) * w, fx);
        for i in 0..SIDE {
            let refc = reference.colours[j * SIDE + i];
            for k in 0..4 {
                let d = (upper[i][k] + (lower[i][k] - upper[i][k]) * fy - refc[k]).abs();
                acc[k] += if d < truncation { d } else { truncation };
            }
        }
        upper = lower;
    }
    acc[0] + acc[1] + acc[2] + acc[3]
}

/// `SIDE` samples along a texel row starting at `base`, each interpolated at `fx` between
/// its texel and the next. A function rather than a closure so it is always inlined: as a
/// call, its result went through the stack on every row.
#[inline(always)]
fn lerp_row<const SIDE: usize, const TEXELS: usize>(pixels: &[Rgba], base: usize, fx: f32) -> [Rgba; SIDE] {
    let texels: &[Rgba; TEXELS] = match pixels.get(base..base + TEXELS).and_then(|t| t.try_into().ok()) {
        Some(t) => t,
        None => &[[0.0; 4]; TEXELS],
    };
    std::array::from_fn(|i| std::array::from_fn(|k| texels[i][k] + (texels[i + 1][k] - texels[i][k]) * fx))
}

/// The world point of a particle at frame offset `k`: `r + k v`.
#[inline(always)]
pub fn displaced(position: [f32; 3], velocity: [f32; 3], offset: f32) -> [f32; 3] {
    [position[0] + offset * velocity[0], position[1] + offset * velocity[1], position[2] + offset * velocity[2]]
}

#[cfg(test)]
mod tests {
    use super::*;
    use handflow_protocol::{Camera, Distortion};
    use nalgebra::{Matrix3, Rotation3, Vector3};

    fn camera_at(x: f64) -> LevelProjection {
        let cam = Camera::new(
            "c",
            4,
            4,
            Matrix3::new(2.0, 0.0, 1.5, 0.0, 2.0, 1.5, 0.0, 0.0, 1.0),
            Distortion::default(),
            Rotation3::identity(),
            Vector3::new(-x, 0.0, 0.0),
        )
        .expect("valid");
        LevelProjection::new(&cam, 0)
    }

    /// The one-particle form the lanes of [`robust_window_costs`] must give bit for bit: each
    /// point projected, its window cost taken, the costs sorted, one at a time.
    fn robust_window_cost(
        images: &[MatchImage<'_>],
        reference: &ReferenceWindow,
        position: [f32; 3],
        velocity: [f32; 3],
        truncation: f32,
        keep: usize,
    ) -> f32 {
        let mut costs = [truncation; MAX_IMAGES];
        let mut n = 0usize;
        let norm = 1.0 / (reference.len as f32 * 3.0);
        // Frames (by offset -1, 0, +1) that have images, and those where the point was seen.
        let (mut present, mut seen) = (0u8, 0u8);
        for img in images {
            if img.is_reference_now {
                continue;
            }
            let bit = 1u8 << ((img.offset as i32 + 1).clamp(0, 2) as u32);
            present |= bit;
            let p = displaced(position, velocity, img.offset);
            let Some([u, v]) = img.projection.project(p) else { continue };
            if let Some(c) = window_cost(img.image, reference, u, v, truncation) {
                costs[n] = c * norm;
                n += 1;
                seen |= bit;
            }
        }
        // A frame the point left entirely gives no evidence of the motion: count it as one full
        // mismatch, or moving out of every image would be the cheapest explanation of anything.
        for _ in 0..(present & !seen).count_ones() {
            costs[n] = truncation;
            n += 1;
        }
        if n == 0 {
            return truncation;
        }
        let keep = keep.clamp(1, n);
        mean_of_smallest(&mut costs[..n], keep)
    }

    /// Sum over the window and channels of `min(|ref - sample|, truncation)`, or `None` when
    /// the window's centre falls outside the image.
    fn window_cost(image: &ColourImage, reference: &ReferenceWindow, u: f32, v: f32, truncation: f32) -> Option<f32> {
        let wmax = (image.width() - 1) as f32;
        let hmax = (image.height() - 1) as f32;
        if !(u >= 0.0 && v >= 0.0 && u <= wmax && v <= hmax) {
            return None;
        }
        if reference.step == 1 {
            if let Some(cost) = window_cost_interior(image, reference, u, v, truncation) {
                return Some(cost);
            }
        }
        Some(window_cost_clamped(image, reference, u, v, truncation))
    }

    /// The interior window of one point, or `None` where its texel patch leaves the image.
    fn window_cost_interior(
        image: &ColourImage,
        reference: &ReferenceWindow,
        u: f32,
        v: f32,
        truncation: f32,
    ) -> Option<f32> {
        match reference.radius {
            1 => window_cost_interior_fixed::<1, 3, 4>(image, reference, u, v, truncation),
            2 => window_cost_interior_fixed::<2, 5, 6>(image, reference, u, v, truncation),
            _ => None,
        }
    }

    fn window_cost_interior_fixed<const R: usize, const SIDE: usize, const TEXELS: usize>(
        image: &ColourImage,
        reference: &ReferenceWindow,
        u: f32,
        v: f32,
        truncation: f32,
    ) -> Option<f32> {
        let (w, h) = (image.width(), image.height());
        // u, v >= 0 here, so truncation is floor (and avoids a libm call without SSE4.1).
        let (cx, cy) = (u as usize, v as usize);
        if cx < R || cy < R || cx + R + 1 >= w || cy + R + 1 >= h {
            return None;
        }
        let (fx, fy) = (u - cx as f32, v - cy as f32);
        Some(window_cost_at::<SIDE, TEXELS>(image, reference, (cy - R) * w + (cx - R), fx, fy, truncation))
    }

    fn uniform_image(value: [f32; 3]) -> ColourImage {
        let mut img = ColourImage::new(4, 4);
        for p in img.pixels_mut() {
            *p = [value[0], value[1], value[2], 0.0];
        }
        img
    }

    #[test]
    fn variance_likelihood_equals_the_hand_computed_value() {
        // Three flat images of colours a, b, c: every projection sees its image's colour.
        let a = uniform_image([0.0, 0.0, 0.0]);
        let b = uniform_image([1.0, 0.0, 0.0]);
        let c = uniform_image([2.0, 1.0, 0.0]);
        let (pa, pb, pc) = (camera_at(0.0), camera_at(0.1), camera_at(-0.1));
        let images = [
            MatchImage { offset: 0.0, image: &a, projection: &pa, is_reference_now: true, window_turns: 0 },
            MatchImage { offset: -1.0, image: &b, projection: &pb, is_reference_now: false, window_turns: 0 },
            MatchImage { offset: 0.0, image: &c, projection: &pc, is_reference_now: false, window_turns: 0 },
        ];
        // Mean (1, 1/3, 0); squared deviations: (1 + 1/9) + (0 + 1/9) + (1 + 4/9) = 8/3;
        // variance = 8/9. Likelihood = 1 / sqrt((8/9)^2 + 0.001^2).
        let expected = 1.0 / ((8.0f32 / 9.0).powi(2) + 1e-6).sqrt();
        let got = variance_likelihood(&images, None, [0.0, 0.0, 2.0], [0.0; 3], 0.001);
        assert!((got - expected).abs() < 1e-4, "{got} vs {expected}");
        // Identical colours: the likelihood is 1/epsilon.
        let same = [images[0], MatchImage { image: &a, ..images[1] }];
        let got = variance_likelihood(&same, None, [0.0, 0.0, 2.0], [0.0; 3], 0.001);
        assert!((got - 1000.0).abs() < 1e-2);
        // Passing the reference colour instead of sampling it gives the same value.
        let cached = variance_likelihood(&images, Some([0.0; 4]), [0.0, 0.0, 2.0], [0.0; 3], 0.001);
        assert!((cached - expected).abs() < 1e-4);
    }

    #[test]
    fn points_outside_every_other_view_get_no_evidence() {
        let a = uniform_image([0.0, 0.0, 0.0]);
        let pa = camera_at(0.0);
        let images = [MatchImage { offset: 0.0, image: &a, projection: &pa, is_reference_now: true, window_turns: 0 }];
        let got = variance_likelihood(&images, None, [0.0, 0.0, 2.0], [0.0; 3], 0.001);
        assert!((got - 1.0 / 3.0).abs() < 1e-4);
    }

    #[test]
    fn interior_window_cost_equals_the_per_sample_cost() {
        let mut img = ColourImage::new(12, 10);
        for (i, p) in img.pixels_mut().iter_mut().enumerate() {
            let f = i as f32;
            *p = [(f * 0.37).sin(), (f * 0.11).cos(), (f * 0.05).sin() * 2.0, 0.0];
        }
        for radius in [1usize, 2] {
            let reference = ReferenceWindow::gather(&img, 5, 4, radius, 1);
            for (u, v) in [(5.3f32, 4.7f32), (4.0, 4.0), (6.99, 5.01)] {
                let fast = window_cost_interior(&img, &reference, u, v, 0.7).expect("interior");
                let slow = window_cost_clamped(&img, &reference, u, v, 0.7);
                assert!((fast - slow).abs() < 1e-4, "radius {radius} at ({u}, {v}): {fast} vs {slow}");
            }
        }
        // Near the border the fast path declines and the clamped one answers.
        let reference = ReferenceWindow::gather(&img, 5, 4, 1, 1);
        assert!(window_cost_interior(&img, &reference, 0.5, 4.0, 0.7).is_none());
        assert!(window_cost(&img, &reference, 0.5, 4.0, 0.7).is_some());
    }

    #[test]
    fn batched_costs_equal_one_at_a_time_to_the_bit() {
        let textured = |seed: f32| {
            let mut img = ColourImage::new(16, 16);
            for (i, p) in img.pixels_mut().iter_mut().enumerate() {
                let f = i as f32 + seed;
                *p = [(f * 0.37).sin(), (f * 0.11).cos(), (f * 0.05).sin() * 2.0, 0.0];
            }
            img
        };
        let wide = |x: f64, distortion: Distortion| {
            let cam = Camera::new(
                "c",
                16,
                16,
                Matrix3::new(8.0, 0.0, 7.5, 0.0, 8.0, 7.5, 0.0, 0.0, 1.0),
                distortion,
                Rotation3::identity(),
                Vector3::new(-x, 0.0, 0.0),
            )
            .expect("valid");
            LevelProjection::new(&cam, 0)
        };
        let (a, b, c, d) = (textured(0.0), textured(3.0), textured(7.0), textured(11.0));
        let pa = wide(0.0, Distortion::default());
        let pb = wide(0.2, Distortion { k1: -0.1, k2: 0.01, p1: 0.002, p2: -0.001, k3: 0.0 });
        let pc = wide(-0.2, Distortion::default());
        let images = [
            MatchImage { offset: 0.0, image: &a, projection: &pa, is_reference_now: true, window_turns: 0 },
            MatchImage { offset: -1.0, image: &b, projection: &pa, is_reference_now: false, window_turns: 0 },
            MatchImage { offset: 1.0, image: &c, projection: &pa, is_reference_now: false, window_turns: 0 },
            MatchImage { offset: -1.0, image: &d, projection: &pb, is_reference_now: false, window_turns: 0 },
            MatchImage { offset: 0.0, image: &b, projection: &pb, is_reference_now: false, window_turns: 0 },
            MatchImage { offset: 1.0, image: &a, projection: &pc, is_reference_now: false, window_turns: 0 },
        ];
        let reference = ReferenceWindow::gather(&a, 7, 8, 1, 1);
        // Points inside every view, near a border, outside one frame, behind the cameras.
        let points: [([f32; 3], [f32; 3]); COST_LANES] = [
            ([0.0, 0.0, 2.0], [0.0; 3]),
            ([0.1, -0.2, 1.5], [0.02, 0.01, -0.05]),
            ([1.7, 0.0, 2.0], [0.3, 0.0, 0.0]),
            ([-0.3, 0.4, 1.0], [-0.1, 0.0, 0.2]),
            ([0.05, 0.05, 0.8], [0.0, 0.0, -0.9]),
            ([0.0, 0.0, -1.0], [0.0; 3]),
            ([0.4, 0.1, 3.0], [0.01, -0.02, 0.03]),
            ([-0.9, -0.9, 1.2], [0.05, 0.05, 0.0]),
        ];
        // Twenty other images: more costs than the sorting network takes.
        let many: Vec<MatchImage<'_>> = images.iter().cycle().take(24).copied().collect();
        for (images, count, keep) in [1, 5, COST_LANES]
            .into_iter()
            .flat_map(|count| [1, 3, 5].map(|keep| (&images[..], count, keep)))
            .chain([(&many[..], COST_LANES, 12)])
        {
            let position = std::array::from_fn(|axis| std::array::from_fn(|l| points[l].0[axis]));
            let velocity = std::array::from_fn(|axis| std::array::from_fn(|l| points[l].1[axis]));
            let mut out = [f32::NAN; COST_LANES];
            robust_window_costs(images, &reference, &position, &velocity, count, 0.7, keep, &mut out);
            for (l, (pos, vel)) in points.iter().enumerate().take(count) {
                let one = robust_window_cost(images, &reference, *pos, *vel, 0.7, keep);
                assert_eq!(out[l].to_bits(), one.to_bits(), "lane {l} of {count}, keep {keep}: {} vs {one}", out[l]);
            }
            assert!(out[count..].iter().all(|c| c.is_nan()), "lanes past the count are left alone");
            if count == COST_LANES {
                // The lanes took different paths: a point seen everywhere matches better
                // than the truncation, one behind every camera costs it exactly.
                assert!(out[0] < 0.7, "{}", out[0]);
                assert_eq!(out[5], 0.7);
            }
        }
    }

    #[test]
    fn the_sorting_network_sorts_every_input() {
        // Every 0-1 input of 16 values sorted means every input is (the 0-1 principle).
        for bits in 0u32..(1 << SORTED_ROWS) {
            let mut v: [u8; SORTED_ROWS] = std::array::from_fn(|i| ((bits >> i) & 1) as u8);
            for &(a, b) in SORT_NETWORK.iter() {
                let (a, b) = (usize::from(a), usize::from(b));
                if v[a] > v[b] {
                    v.swap(a, b);
                }
            }
            assert!(v.windows(2).all(|w| w[0] <= w[1]), "{bits:#x}: {v:?}");
        }
    }

    #[test]
    fn robust_cost_ignores_the_worst_views() {
        let good = uniform_image([0.5, 0.5, 0.5]);
        let bad = uniform_image([-2.0, 2.0, -2.0]);
        let p = camera_at(0.0);
        let reference = ReferenceWindow::gather(&good, 1, 1, 1, 1);
        let images = [
            MatchImage { offset: 0.0, image: &good, projection: &p, is_reference_now: true, window_turns: 0 },
            MatchImage { offset: -1.0, image: &good, projection: &p, is_reference_now: false, window_turns: 0 },
            MatchImage { offset: 0.0, image: &good, projection: &p, is_reference_now: false, window_turns: 0 },
            MatchImage { offset: 0.0, image: &bad, projection: &p, is_reference_now: false, window_turns: 0 },
        ];
        // One particle at (0, 0, 2), at rest, in the first lane.
        let cost = |keep: usize| {
            let (mut position, velocity) = ([[0.0; COST_LANES]; 3], [[0.0; COST_LANES]; 3]);
            position[2][0] = 2.0;
            let mut out = [f32::NAN; COST_LANES];
            robust_window_costs(&images, &reference, &position, &velocity, 1, 1.0, keep, &mut out);
            out[0]
        };
        assert_eq!(cost(2), 0.0);
        // Keeping all three: the bad view costs the truncation on every channel.
        let all = cost(3);
        assert!((all - 1.0 / 3.0).abs() < 1e-6, "{all}");
    }

    #[test]
    fn a_view_turned_by_a_quarter_matches_the_reference_only_with_the_window_turned() {
        // The reference and a view from the same centre, the view rolled by a quarter turn
        // about the optical axis: its image is the reference's turned (pixel (u, v) of
        // the reference lands on (2c - v, u) of the view).
        let (n, f, c) = (21usize, 20.0, 10.0);
        let k = Matrix3::new(f, 0.0, c, 0.0, f, c, 0.0, 0.0, 1.0);
        let camera =
            |rotation| Camera::new("c", n as u32, n as u32, k, Distortion::default(), rotation, Vector3::zeros());
        let reference_camera = camera(Rotation3::identity()).expect("valid");
        let view_camera =
            camera(Rotation3::from_axis_angle(&Vector3::z_axis(), std::f64::consts::FRAC_PI_2)).expect("valid");
        let texture = |u: usize, v: usize| {
            let h = (u * 7919 + v * 104_729 + 13).wrapping_mul(2_654_435_761) % 1000;
            [h as f32 / 1000.0, ((h * 31) % 1000) as f32 / 1000.0, ((h * 17) % 1000) as f32 / 1000.0, 0.0]
        };
        let (mut reference_image, mut view_image) = (ColourImage::new(n, n), ColourImage::new(n, n));
        for v in 0..n {
            for u in 0..n {
                reference_image.pixels_mut()[v * n + u] = texture(u, v);
                view_image.pixels_mut()[v * n + u] = texture(v, 2 * c as usize - u);
            }
        }
        let (x, y, depth) = (8usize, 12usize, 1.0f32);
        let point = [(x as f32 - c as f32) / f as f32 * depth, (y as f32 - c as f32) / f as f32 * depth, depth];
        let turns = crate::matching::camera::window_quarter_turns(&reference_camera, &view_camera, 1.0);
        assert_eq!(turns, 1);
        let (pr, pv) = (LevelProjection::new(&reference_camera, 0), LevelProjection::new(&view_camera, 0));
        let window = ReferenceWindow::gather(&reference_image, x, y, 1, 1);
        let cost = |window_turns: u8| {
            let images = [
                MatchImage {
                    offset: 0.0,
                    image: &reference_image,
                    projection: &pr,
                    is_reference_now: true,
                    window_turns: 0,
                },
                MatchImage { offset: 0.0, image: &view_image, projection: &pv, is_reference_now: false, window_turns },
            ];
            let position = [[point[0]; COST_LANES], [point[1]; COST_LANES], [point[2]; COST_LANES]];
            let mut out = [0f32; COST_LANES];
            robust_window_costs(&images, &window, &position, &[[0.0; COST_LANES]; 3], 1, 1.0, 1, &mut out);
            out[0]
        };
        assert!(cost(turns) < 1e-3, "turned window: {}", cost(turns));
        assert!(cost(0) > 0.05, "window as in the reference: {}", cost(0));
        // Four quarter turns are none; a turn and its inverse undo each other.
        let colours = |w: &ReferenceWindow| w.colours[..w.len].to_vec();
        assert_eq!(colours(&window.turned(4)), colours(&window));
        assert_eq!(colours(&window.turned(1).turned(3)), colours(&window));
        assert_eq!(colours(&window.turned(2).turned(2)), colours(&window));
        assert_ne!(colours(&window.turned(1)), colours(&window));
    }
}
