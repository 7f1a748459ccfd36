//! Expectation maximisation of a Gaussian mixture with full covariances in the 6D space of
//! position and scaled velocity (section 4.2), on weighted points.

use nalgebra::{Cholesky, Matrix3, Matrix6, Vector3, Vector6};

use crate::WeightedPoint;

/// Parameters of the EM fit.
#[derive(Clone, Debug, PartialEq)]
pub struct EmConfig {
    /// Iterations at most (default 25).
    pub max_iterations: usize,
    /// Stop when the mean log-likelihood per unit weight changes less than this (default 1e-3).
    pub tolerance: f64,
    /// Seconds: velocity (m/s) times this becomes metres (default 0.1). A hand moving 1 m/s
    /// is then as far from a still one as 10 cm of position: hands close together are about
    /// that far apart and signs move them at 0.5 to 2 m/s, so both halves count alike.
    pub velocity_scale: f64,
    /// Points used at most (default 4000): larger sets are subsampled in proportion to their
    /// weights (systematic resampling), which keeps every cluster's share of the weight and
    /// bounds the time per frame.
    pub max_points: usize,
    /// Standard deviation added to every dimension's variance, metres in the scaled space
    /// (default 0.01): covariances never become singular, even for a cluster of one point.
    pub min_std: f64,
    /// Largest standard deviation of the starting components in every dimension, metres in
    /// the scaled space (default 0.05, about the spread of a hand's points): each component
    /// starts on the points near its initial mean. Starting with the spread of the whole scene instead (clutter
    /// metres away included) made the components nearly identical at first, and two hands
    /// 25 cm apart could end up in one component while the other wandered off to the neck.
    pub start_std: f64,
    /// Largest standard deviation of the first component's position along any direction,
    /// metres (default infinite: no bound). The cluster stage seeds the head there and bounds
    /// it by a head's size, so that a hand raised near the face, or the skin of a neck and
    /// chest, cannot stretch the head's Gaussian over itself and pull its centre away.
    pub first_max_std: f64,
    /// Seed of the subsampling offset (default 0).
    pub seed: u64,
    /// Model points no Gaussian explains with a uniform density over the points' bounding
    /// box (default true): false skin on the wall or a stray depth must not drag a head or
    /// hand cluster metres away.
    pub outliers: bool,
}

impl Default for EmConfig {
    fn default() -> Self {
        Self {
            max_iterations: 25,
            tolerance: 1e-4,
            velocity_scale: 0.1,
            max_points: 4000,
            min_std: 0.01,
            start_std: 0.05,
            first_max_std: f64::INFINITY,
            seed: 0,
            outliers: true,
        }
    }
}

/// `cov` with its position block's spread bounded to `max_std` along every direction: the
/// position block's eigenvalues above `max_std²` are brought down to it, and the
/// position-velocity blocks scaled with them (`T C T` with `T` acting on positions only, so
/// the result stays positive semi-definite).
fn bounded_position_spread(cov: &Matrix6<f64>, max_std: f64) -> Matrix6<f64> {
    let position: Matrix3<f64> = cov.fixed_view::<3, 3>(0, 0).into_owned();
    let (eigenvalues, eigenvectors) = symmetric_eigen3(&position);
    let limit = max_std * max_std;
    if eigenvalues.iter().all(|&l| l <= limit) {
        return *cov;
    }
    let shrink = Matrix3::from_diagonal(&eigenvalues.map(|l| if l > limit { (limit / l).sqrt() } else { 1.0 }));
    let t3 = eigenvectors * shrink * eigenvectors.transpose();
    let mut t = Matrix6::identity();
    t.fixed_view_mut::<3, 3>(0, 0).copy_from(&t3);
    let bounded = t * cov * t;
    0.5 * (bounded + bounded.transpose())
}

/// Eigenvalues and eigenvectors (columns) of a symmetric 3x3 matrix by cyclic Jacobi
/// rotations, accurate to rounding: `V diag(λ) Vᵀ` gives `m` back within a few ulps of its
/// norm. nalgebra's `SymmetricEigen` solves the last 2x2 block in closed form, whose
/// eigenvector loses digits when two eigenvalues nearly coincide (a residual of 1e-8 of the
/// norm was seen), and the spread bound is only as tight as its eigenvectors diagonalise `m`.
fn symmetric_eigen3(m: &Matrix3<f64>) -> (Vector3<f64>, Matrix3<f64>) {
    let mut a = *m;
    let mut v = Matrix3::identity();
    let scale = a.norm();
    for _sweep in 0..32 {
        let off = a[(0, 1)].powi(2) + a[(0, 2)].powi(2) + a[(1, 2)].powi(2);
        if off <= (f64::EPSILON * 1e-3 * scale).powi(2) {
            break;
        }
        for (p, q) in [(0, 1), (0, 2), (1, 2)] {
            let apq = a[(p, q)];
            if apq == 0.0 {
                continue;
            }
            // The smaller of the two rotation angles that zero `a[(p, q)]` (Rutishauser).
            let theta = (a[(q, q)] - a[(p, p)]) / (2.0 * apq);
            let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
            let c = 1.0 / (t * t + 1.0).sqrt();
            let s = t * c;
            let mut rotation = Matrix3::identity();
            rotation[(p, p)] = c;
            rotation[(q, q)] = c;
            rotation[(p, q)] = s;
            rotation[(q, p)] = -s;
            a = rotation.transpose() * a * rotation;
            a[(p, q)] = 0.0;
            a[(q, p)] = 0.0;
            v *= rotation;
        }
    }
    (a.diagonal(), v)
}

/// One fitted component, in the caller's units.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Component {
    /// Mean position, metres.
    pub position: Vector3<f64>,
    /// Mean velocity, metres per second.
    pub velocity: Vector3<f64>,
    /// Covariance in the scaled 6D space (position block in square metres).
    pub covariance: Matrix6<f64>,
    /// Mixing proportion (the components' sum to 1).
    pub mixing: f64,
    /// Weight of the points it explains, in the caller's weight units.
    pub mass: f64,
    /// Whether it ended explaining (almost) nothing; its mean is then where it started.
    pub empty: bool,
}

/// The result of a fit.
#[derive(Clone, Debug, PartialEq)]
pub struct EmFit {
    /// One per initial mean, in the same order.
    pub components: Vec<Component>,
    /// Iterations run.
    pub iterations: usize,
    /// Mean log-likelihood per unit weight at the end.
    pub log_likelihood: f64,
    /// Points used (after subsampling and dropping unusable ones).
    pub points_used: usize,
    /// Share of the weight the outlier class took (0 without it): the components' masses and
    /// this share of the total weight add up to the total.
    pub outlier_share: f64,
}

/// A component's share of the total weight under which it counts as empty.
const EMPTY_SHARE: f64 = 1e-6;

/// Fits one Gaussian per initial mean (position m, velocity m/s) to the weighted points.
/// `None` when no point is usable (finite, positive weight) or no initial mean is given.
pub fn fit_mixture(
    points: &[WeightedPoint],
    initial: &[(Vector3<f64>, Vector3<f64>)],
    config: &EmConfig,
) -> Option<EmFit> {
    let s = config.velocity_scale;
    let usable: Vec<&WeightedPoint> = points.iter().filter(|p| p.is_usable()).collect();
    if usable.is_empty() || initial.is_empty() {
        return None;
    }
    let total: f64 = usable.iter().map(|p| p.weight).sum();
    let (features, weights) = subsample(&usable, total, s, config.max_points.max(1), config.seed);
    let wsum: f64 = weights.iter().sum();
    let k = initial.len();
    let floor = config.min_std * config.min_std;
    // The start: every dimension with the data's mean positional variance, at most
    // `start_std` squared.
    let mean_all = features.iter().zip(&weights).fold(Vector6::zeros(), |a, (f, w)| a + f * *w) / wsum;
    let spread = features
        .iter()
        .zip(&weights)
        .map(|(f, w)| w * (0..3).map(|d| (f[d] - mean_all[d]).powi(2)).sum::<f64>() / 3.0)
        .sum::<f64>()
        / wsum;
    let start_cov = Matrix6::identity() * (spread.min(config.start_std * config.start_std) + floor);
    let start_means: Vec<Vector6<f64>> =
        initial.iter().map(|(p, v)| Vector6::new(p.x, p.y, p.z, v.x * s, v.y * s, v.z * s)).collect();
    let mut means = start_means.clone();
    let mut covs = vec![start_cov; k];
    let mut mixing = vec![1.0 / k as f64; k];
    let mut masses = vec![0.0; k];
    let mut empty = vec![false; k];
    let mut resp = vec![0.0; features.len() * k];
    // Uniform outlier density over the bounding box (each side at least 10 cm).
    let log_volume: f64 = (0..6)
        .map(|d| {
            let (lo, hi) =
                features.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), f| (a.min(f[d]), b.max(f[d])));
            (hi - lo).max(0.1).ln()
        })
        .sum();
    let mut outlier_share: f64 = if config.outliers { 0.05 } else { 0.0 };
    let mut unexplained = 0.0;
    let mut previous = f64::NEG_INFINITY;
    let mut log_likelihood = f64::NEG_INFINITY;
    let mut iterations = 0;
    for _ in 0..config.max_iterations.max(1) {
        iterations += 1;
        // E-step in the log domain.
        // Per component: the inverse Cholesky factor (so a point costs one 6x6 product) and
        // the constant part of its log density.
        let prepared: Vec<(Matrix6<f64>, f64)> = covs
            .iter()
            .zip(&mixing)
            .map(|(c, m)| {
                let (chol, log_det) = robust_cholesky(c, floor);
                // Lower-triangular, with exact zeros above the diagonal (the E-step relies on it).
                let inverse = chol.l().solve_lower_triangular(&Matrix6::identity()).unwrap_or_else(Matrix6::identity);
                let constant = m.max(1e-300).ln() - 0.5 * (log_det + 6.0 * (2.0 * std::f64::consts::PI).ln());
                (inverse, constant)
            })
            .collect();
        let log_out = if config.outliers { outlier_share.ln() - log_volume } else { f64::NEG_INFINITY };
        let mut ll = 0.0;
        for (i, f) in features.iter().enumerate() {
            let row = &mut resp[i * k..(i + 1) * k];
            let mut best = log_out;
            for (j, r) in row.iter_mut().enumerate() {
                let (inverse, constant) = &prepared[j];
                *r = constant - 0.5 * lower_product_norm_squared(inverse, &(f - means[j]));
                best = best.max(*r);
            }
            let mut sum = (log_out - best).exp();
            for r in row.iter_mut() {
                *r = (*r - best).exp();
                sum += *r;
            }
            for r in row.iter_mut() {
                *r /= sum;
            }
            let log_norm = best + sum.ln();
            ll += weights[i] * log_norm;
        }
        log_likelihood = ll / wsum;
        // M-step: one pass accumulating each component's weight, first and second moments
        // (f64 keeps the centred second moment exact enough at metre scale).
        // Second moments are symmetric: only the lower triangle is accumulated.
        let mut acc = vec![(0.0f64, Vector6::<f64>::zeros(), [0.0f64; TRIANGLE]); k];
        for (i, f) in features.iter().enumerate() {
            let outer = LOWER.map(|(r, c)| f[r] * f[c]);
            for (j, (m, first, second)) in acc.iter_mut().enumerate() {
                let w = weights[i] * resp[i * k + j];
                *m += w;
                *first += f * w;
                for (s, o) in second.iter_mut().zip(&outer) {
                    *s += o * w;
                }
            }
        }
        for (j, (mass, first, lower)) in acc.into_iter().enumerate() {
            let second = symmetric_from_lower(&lower);
            masses[j] = mass;
            if mass <= EMPTY_SHARE * wsum {
                // Nothing to explain: stay where it started, broad, able to recapture points.
                empty[j] = true;
                means[j] = start_means[j];
                covs[j] = start_cov;
                mixing[j] = EMPTY_SHARE;
                continue;
            }
            empty[j] = false;
            let mean = first / mass;
            let cov = second / mass - mean * mean.transpose() + Matrix6::identity() * floor;
            means[j] = mean;
            covs[j] = 0.5 * (cov + cov.transpose());
            if j == 0 && config.first_max_std.is_finite() {
                covs[j] = bounded_position_spread(&covs[j], config.first_max_std);
            }
            mixing[j] = mass / wsum;
        }
        let explained: f64 = masses.iter().sum::<f64>() / wsum;
        unexplained = (1.0 - explained).max(0.0);
        if config.outliers {
            // What the Gaussians leave is the outlier class's; bounded so that it can neither
            // vanish nor swallow the scene.
            outlier_share = (1.0 - explained).clamp(1e-3, 0.5);
        }
        let norm: f64 = mixing.iter().sum::<f64>() / (1.0 - outlier_share);
        mixing.iter_mut().for_each(|m| *m /= norm);
        if (log_likelihood - previous).abs() < config.tolerance {
            break;
        }
        previous = log_likelihood;
    }
    // Masses in the caller's units (subsampling rescaled the weights).
    let scale = total / wsum;
    let components = (0..k)
        .map(|j| Component {
            position: Vector3::new(means[j][0], means[j][1], means[j][2]),
            velocity: Vector3::new(means[j][3], means[j][4], means[j][5]) / s,
            covariance: covs[j],
            mixing: if empty[j] { 0.0 } else { mixing[j] },
            mass: if empty[j] { 0.0 } else { masses[j] * scale },
            empty: empty[j],
        })
        .collect::<Vec<_>>();
    // Empty components report mixing 0: renormalise the others.
    let live: f64 = components.iter().map(|c| c.mixing).sum();
    let components = components
        .into_iter()
        .map(|c| Component { mixing: if live > 0.0 { c.mixing / live } else { 1.0 / k as f64 }, ..c })
        .collect();
    Some(EmFit {
        components,
        iterations,
        log_likelihood: if log_likelihood.is_finite() { log_likelihood } else { f64::MIN },
        points_used: features.len(),
        outlier_share: if config.outliers { unexplained } else { 0.0 },
    })
}

/// Entries in the lower triangle of a 6x6 matrix.
const TRIANGLE: usize = 21;

/// (row, column) of each entry of the lower triangle of a 6x6 matrix, row by row: the
/// entries a symmetric matrix is stored by.
const LOWER: [(usize, usize); TRIANGLE] = {
    let mut entries = [(0, 0); TRIANGLE];
    let (mut r, mut t) = (0, 0);
    while r < 6 {
        let mut c = 0;
        while c <= r {
            entries[t] = (r, c);
            (c, t) = (c + 1, t + 1);
        }
        r += 1;
    }
    entries
};

/// The symmetric matrix whose lower triangle is `lower` (in [`LOWER`]'s order).
fn symmetric_from_lower(lower: &[f64; TRIANGLE]) -> Matrix6<f64> {
    let mut m = Matrix6::zeros();
    for (&(r, c), &v) in LOWER.iter().zip(lower) {
        m[(r, c)] = v;
        m[(c, r)] = v;
    }
    m
}

/// `|L d|^2` for a lower-triangular `L`: the terms above the diagonal are zero, so they are
/// skipped (21 products instead of 36; the sums are the same, in the same order).
#[inline]
fn lower_product_norm_squared(l: &Matrix6<f64>, d: &Vector6<f64>) -> f64 {
    let mut sum = 0.0;
    for r in 0..6 {
        let mut y = 0.0;
        for c in 0..=r {
            y += l[(r, c)] * d[c];
        }
        sum += y * y;
    }
    sum
}

/// Cholesky factor and log-determinant, regularising the diagonal until it factors.
fn robust_cholesky(c: &Matrix6<f64>, floor: f64) -> (Cholesky<f64, nalgebra::Const<6>>, f64) {
    let mut m = *c;
    let mut add = floor.max(1e-12);
    loop {
        if let Some(ch) = Cholesky::new(m) {
            let log_det = 2.0 * ch.l().diagonal().iter().map(|d| d.ln()).sum::<f64>();
            if log_det.is_finite() {
                return (ch, log_det);
            }
        }
        m = Matrix6::identity() * add + if m.iter().all(|v| v.is_finite()) { m } else { Matrix6::zeros() };
        add *= 10.0;
        if add > 1e6 {
            let ch = Cholesky::new(Matrix6::identity());
            if let Some(ch) = ch {
                return (ch, 0.0);
            }
        }
    }
}

/// The points as 6D features with weights; above `max` points, a systematic resample in
/// proportion to weight, each kept point carrying `total / max`.
fn subsample(
    points: &[&WeightedPoint],
    total: f64,
    scale: f64,
    max: usize,
    seed: u64,
) -> (Vec<Vector6<f64>>, Vec<f64>) {
    if points.len() <= max {
        return (points.iter().map(|p| p.feature(scale)).collect(), points.iter().map(|p| p.weight).collect());
    }
    let step = total / max as f64;
    // A deterministic offset in [0, step) from the seed (splitmix64).
    let mut z = seed.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^= z >> 31;
    let mut next = (z >> 11) as f64 / (1u64 << 53) as f64 * step;
    let mut features = Vec::with_capacity(max);
    let mut cumulative = 0.0;
    for p in points {
        cumulative += p.weight;
        while next < cumulative && features.len() < max {
            features.push(p.feature(scale));
            next += step;
        }
    }
    let weights = vec![step; features.len()];
    (features, weights)
}

/// Extends `seeds` with `extra` means at the usable points farthest (in position) from every
/// seed so far, one after another (farthest-point seeding): components for whatever else
/// shows as skin (a neck, a ghost behind the head, a second blob of one hand), so the three
/// objects' components are not stretched over it. Fewer are added when no point lies
/// farther than `min_distance_m` from the seeds.
pub fn farthest_point_seeds(
    points: &[WeightedPoint],
    seeds: &mut Vec<(Vector3<f64>, Vector3<f64>)>,
    extra: usize,
    min_distance_m: f64,
) {
    for _ in 0..extra {
        // Squared distances: the same order without a square root per point and seed.
        let farthest = points
            .iter()
            .filter(|p| p.is_usable())
            .map(|p| (p, seeds.iter().map(|(s, _)| (p.position - s).norm_squared()).fold(f64::INFINITY, f64::min)))
            .max_by(|a, b| a.1.total_cmp(&b.1));
        match farthest {
            Some((p, d_sq)) if d_sq > min_distance_m * min_distance_m => seeds.push((p.position, p.velocity)),
            _ => break,
        }
    }
}

/// Initial means for a first frame without predictions: the top, bottom-left and
/// bottom-right extremities of the scene (section 4.2). `up` is the world's up and `right`
/// the direction that is right as the observer sees it. Top: the mean of the highest tenth
/// of the weight; bottom-left and bottom-right: of the lowest and highest fifth along
/// `right` among the lower half. `None` without usable points.
pub fn extremity_means(
    points: &[WeightedPoint],
    up: Vector3<f64>,
    right: Vector3<f64>,
) -> Option<[(Vector3<f64>, Vector3<f64>); 3]> {
    let usable: Vec<&WeightedPoint> = points.iter().filter(|p| p.is_usable()).collect();
    if usable.is_empty() {
        return None;
    }
    // Clutter (false skin on a wall, stray depths) must not become an extremity: only points
    // within a person's reach of the weighted median take part.
    let median: Vector3<f64> = Vector3::from_fn(|d, _| weighted_median(&usable, |p| p.position[d]));
    let near: Vec<&WeightedPoint> =
        usable.iter().copied().filter(|p| (p.position - median).norm() <= EXTREMITY_RADIUS_M).collect();
    let usable = if near.is_empty() { usable } else { near };
    let top = extreme(&usable, up, 0.1, true);
    let lower = extreme(&usable, up, 0.5, false);
    let left = extreme(&lower, right, 0.2, false);
    let right_side = extreme(&lower, right, 0.2, true);
    Some([mean_of(&top), mean_of(&left), mean_of(&right_side)])
}

/// Where to look again for a hand whose track was lost: the mean of the points holding a
/// fifth of the weight at the `side` end (along `side`) of the lower half of the points
/// within `reach_m` of the head. A lost track's last position is stale: a component seeded
/// there stays empty while the hand, back in view, is swallowed by the head's or the other
/// hand's component, so the hand would never come back. `None` without usable points there.
pub fn side_extremity(
    points: &[WeightedPoint],
    head: Vector3<f64>,
    reach_m: f64,
    up: Vector3<f64>,
    side: Vector3<f64>,
) -> Option<(Vector3<f64>, Vector3<f64>)> {
    let near: Vec<&WeightedPoint> =
        points.iter().filter(|p| p.is_usable() && (p.position - head).norm() <= reach_m).collect();
    if near.is_empty() {
        return None;
    }
    let lower = extreme(&near, up, 0.5, false);
    Some(mean_of(&extreme(&lower, side, 0.2, true)))
}

/// Weighted mean position and velocity of a non-empty set.
fn mean_of(set: &[&WeightedPoint]) -> (Vector3<f64>, Vector3<f64>) {
    let w: f64 = set.iter().map(|p| p.weight).sum();
    let pos = set.iter().fold(Vector3::zeros(), |a, p| a + p.position * p.weight) / w;
    let vel = set.iter().fold(Vector3::zeros(), |a, p| a + p.velocity * p.weight) / w;
    (pos, vel)
}

/// Radius around the points' weighted median within which extremities are looked for,
/// metres: head and hands of a person lie within about a metre of their middle.
pub const EXTREMITY_RADIUS_M: f64 = 1.0;

/// The value at half of `points`' weight, in the order of `value`.
pub(crate) fn weighted_median(points: &[&WeightedPoint], value: impl Fn(&WeightedPoint) -> f64) -> f64 {
    let mut v: Vec<(f64, f64)> = points.iter().map(|p| (value(p), p.weight)).collect();
    v.sort_by(|a, b| a.0.total_cmp(&b.0));
    let half = v.iter().map(|x| x.1).sum::<f64>() / 2.0;
    let mut acc = 0.0;
    for (x, w) in &v {
        acc += w;
        if acc >= half {
            return *x;
        }
    }
    v.last().map_or(0.0, |x| x.0)
}

/// The points holding `share` of the weight from the high (or low) end along `axis`.
fn extreme<'a>(set: &[&'a WeightedPoint], axis: Vector3<f64>, share: f64, high: bool) -> Vec<&'a WeightedPoint> {
    let mut sorted = set.to_vec();
    sorted.sort_by(|a, b| {
        let (x, y) = (a.position.dot(&axis), b.position.dot(&axis));
        if high {
            y.total_cmp(&x)
        } else {
            x.total_cmp(&y)
        }
    });
    let total: f64 = sorted.iter().map(|p| p.weight).sum();
    let mut acc = 0.0;
    let mut out = Vec::new();
    for p in sorted {
        if acc >= share * total && !out.is_empty() {
            break;
        }
        acc += p.weight;
        out.push(p);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Deterministic standard normal draws (Box-Muller on a splitmix64 stream).
    struct Normal(u64);
    impl Normal {
        fn uniform(&mut self) -> f64 {
            self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
        }
        fn sample(&mut self) -> f64 {
            let (u, v) = (self.uniform().max(1e-12), self.uniform());
            (-2.0 * u.ln()).sqrt() * (2.0 * std::f64::consts::PI * v).cos()
        }
    }

    /// `n` points around `pos`/`vel` with per-axis standard deviations `sp` (m) and `sv` (m/s).
    fn blob(rng: &mut Normal, n: usize, pos: [f64; 3], vel: [f64; 3], sp: f64, sv: f64) -> Vec<WeightedPoint> {
        (0..n)
            .map(|i| WeightedPoint {
                position: Vector3::new(
                    pos[0] + sp * rng.sample(),
                    pos[1] + sp * rng.sample(),
                    pos[2] + sp * rng.sample(),
                ),
                velocity: Vector3::new(
                    vel[0] + sv * rng.sample(),
                    vel[1] + sv * rng.sample(),
                    vel[2] + sv * rng.sample(),
                ),
                weight: 0.5 + (i % 3) as f64 * 0.5,
            })
            .collect()
    }

    fn signer(rng: &mut Normal, scale: usize) -> Vec<WeightedPoint> {
        let mut pts = blob(rng, 2000 * scale, [0.0, 1.6, 0.0], [0.0, 0.0, 0.0], 0.04, 0.05);
        pts.extend(blob(rng, 1000 * scale, [0.25, 1.1, 0.3], [1.0, 0.0, 0.0], 0.03, 0.1));
        pts.extend(blob(rng, 1000 * scale, [-0.25, 1.1, 0.3], [-1.0, 0.0, 0.0], 0.03, 0.1));
        pts
    }

    #[test]
    fn recovers_a_known_mixture() {
        let mut rng = Normal(1);
        let pts = signer(&mut rng, 1);
        let init = [
            (Vector3::new(0.05, 1.55, 0.05), Vector3::zeros()),
            (Vector3::new(0.2, 1.15, 0.25), Vector3::new(0.5, 0.0, 0.0)),
            (Vector3::new(-0.3, 1.05, 0.35), Vector3::zeros()),
        ];
        let fit = fit_mixture(&pts, &init, &EmConfig::default()).unwrap();
        let truth = [
            ([0.0, 1.6, 0.0], [0.0; 3], 0.5, 0.04),
            ([0.25, 1.1, 0.3], [1.0, 0.0, 0.0], 0.25, 0.03),
            ([-0.25, 1.1, 0.3], [-1.0, 0.0, 0.0], 0.25, 0.03),
        ];
        for (c, (p, v, mix, sp)) in fit.components.iter().zip(truth) {
            assert!((c.position - Vector3::from(p)).norm() < 0.01, "{:?}", c.position);
            assert!((c.velocity - Vector3::from(v)).norm() < 0.05, "{:?}", c.velocity);
            assert!((c.mixing - mix).abs() < 0.03, "{}", c.mixing);
            // Position variance: the true one plus the documented floor.
            let expected = sp * sp + 0.01f64.powi(2);
            assert!((c.covariance[(0, 0)] / expected - 1.0).abs() < 0.2, "{} vs {expected}", c.covariance[(0, 0)]);
            assert!(!c.empty);
        }
        let total: f64 = pts.iter().map(|p| p.weight).sum();
        let mass: f64 = fit.components.iter().map(|c| c.mass).sum();
        assert!((mass / total + fit.outlier_share - 1.0).abs() < 1e-9);
        assert!(fit.outlier_share < 0.01, "clean data: {}", fit.outlier_share);
    }

    #[test]
    fn two_close_hands_stay_apart_beside_a_neck_and_distant_clutter() {
        let mut rng = Normal(9);
        // Head, two hands 27 cm apart moving towards each other, a neck blob between head
        // and hands, and skin-like clutter 1-3 m away that widens the scene's spread to
        // metres: the layout of a frame where both hands once ended in one component.
        let mut pts = blob(&mut rng, 2000, [0.0, 1.61, 0.05], [0.0; 3], 0.04, 0.05);
        pts.extend(blob(&mut rng, 800, [0.17, 1.16, 0.22], [-0.25, 0.25, 0.0], 0.04, 0.15));
        pts.extend(blob(&mut rng, 800, [-0.07, 1.29, 0.27], [0.14, -0.26, 0.0], 0.04, 0.15));
        pts.extend(blob(&mut rng, 300, [0.05, 1.45, -0.02], [0.0; 3], 0.04, 0.05));
        pts.extend(blob(&mut rng, 300, [-0.7, 0.55, -0.7], [0.0; 3], 0.05, 0.05));
        pts.extend(blob(&mut rng, 300, [1.3, 0.7, -2.1], [0.0; 3], 0.3, 0.5));
        // Predictions a few centimetres off, as a constant-velocity model gives them, and
        // two clutter seeds.
        let init = [
            (Vector3::new(0.01, 1.6, 0.05), Vector3::zeros()),
            (Vector3::new(0.19, 1.15, 0.2), Vector3::new(-0.25, 0.25, 0.0)),
            (Vector3::new(-0.06, 1.31, 0.27), Vector3::new(0.14, -0.26, 0.0)),
            (Vector3::new(-0.7, 0.55, -0.7), Vector3::zeros()),
            (Vector3::new(1.3, 0.7, -2.1), Vector3::zeros()),
        ];
        let fit = fit_mixture(&pts, &init, &EmConfig::default()).unwrap();
        for (c, p) in fit.components.iter().zip([[0.0, 1.61, 0.05], [0.17, 1.16, 0.22], [-0.07, 1.29, 0.27]]) {
            assert!((c.position - Vector3::from(p)).norm() < 0.03, "{:?} for {p:?}", c.position);
        }
    }

    #[test]
    fn clutter_far_from_the_clusters_goes_to_the_outlier_class() {
        let mut rng = Normal(6);
        let mut pts = signer(&mut rng, 1);
        // A tenth of the weight on skin-coloured wall patches 3 m behind, and stray depths.
        pts.extend(blob(&mut rng, 300, [0.4, 2.7, -3.3], [0.0; 3], 0.05, 0.05));
        pts.extend(blob(&mut rng, 150, [0.0, 1.4, 1.2], [0.0; 3], 0.3, 0.5));
        let init = [
            (Vector3::new(0.0, 1.6, 0.0), Vector3::zeros()),
            (Vector3::new(0.25, 1.1, 0.3), Vector3::zeros()),
            (Vector3::new(-0.25, 1.1, 0.3), Vector3::zeros()),
        ];
        let fit = fit_mixture(&pts, &init, &EmConfig::default()).unwrap();
        for (c, p) in fit.components.iter().zip([[0.0, 1.6, 0.0], [0.25, 1.1, 0.3], [-0.25, 1.1, 0.3]]) {
            assert!((c.position - Vector3::from(p)).norm() < 0.015, "{:?}", c.position);
        }
        assert!(fit.outlier_share > 0.05, "{}", fit.outlier_share);
        let without = fit_mixture(&pts, &init, &EmConfig { outliers: false, ..EmConfig::default() }).unwrap();
        let worst = without
            .components
            .iter()
            .zip([[0.0, 1.6, 0.0], [0.25, 1.1, 0.3], [-0.25, 1.1, 0.3]])
            .map(|(c, p)| (c.position - Vector3::from(p)).norm())
            .fold(0.0, f64::max);
        assert!(worst > 0.05, "without the outlier class the clutter drags a cluster: {worst}");
    }

    #[test]
    fn hands_in_one_place_moving_apart_are_two_clusters() {
        let mut rng = Normal(2);
        let mut pts = blob(&mut rng, 800, [0.0, 1.1, 0.3], [1.0, 0.0, 0.0], 0.03, 0.1);
        pts.extend(blob(&mut rng, 800, [0.0, 1.1, 0.3], [-1.0, 0.0, 0.0], 0.03, 0.1));
        let init = [
            (Vector3::new(0.0, 1.1, 0.3), Vector3::new(0.5, 0.0, 0.0)),
            (Vector3::new(0.0, 1.1, 0.3), Vector3::new(-0.5, 0.0, 0.0)),
        ];
        let fit = fit_mixture(&pts, &init, &EmConfig::default()).unwrap();
        assert!((fit.components[0].velocity.x - 1.0).abs() < 0.05);
        assert!((fit.components[1].velocity.x + 1.0).abs() < 0.05);
    }

    #[test]
    fn weights_count() {
        let p = |x: f64, w: f64| WeightedPoint {
            position: Vector3::new(x, 0.0, 0.0),
            velocity: Vector3::zeros(),
            weight: w,
        };
        let init = [(Vector3::zeros(), Vector3::zeros())];
        let fit = fit_mixture(&[p(0.0, 1.0), p(1.0, 3.0)], &init, &EmConfig { outliers: false, ..EmConfig::default() })
            .unwrap();
        assert!((fit.components[0].position.x - 0.75).abs() < 1e-9);
        assert!((fit.components[0].mass - 4.0).abs() < 1e-9);
    }

    #[test]
    fn degenerate_inputs_give_finite_answers() {
        let cfg = EmConfig::default();
        let init = [
            (Vector3::zeros(), Vector3::zeros()),
            (Vector3::new(5.0, 5.0, 5.0), Vector3::zeros()),
            (Vector3::new(0.1, 0.0, 0.0), Vector3::zeros()),
        ];
        assert!(fit_mixture(&[], &init, &cfg).is_none());
        let one = WeightedPoint { position: Vector3::new(0.1, 0.2, 0.3), velocity: Vector3::zeros(), weight: 1.0 };
        let nan = WeightedPoint { position: Vector3::new(f64::NAN, 0.0, 0.0), ..one };
        assert!(fit_mixture(&[nan], &init, &cfg).is_none());
        for pts in [vec![one], vec![one; 50], vec![one, nan, WeightedPoint { weight: 0.0, ..one }]] {
            let fit = fit_mixture(&pts, &init, &cfg).unwrap();
            assert!(fit.log_likelihood.is_finite());
            let mixing: f64 = fit.components.iter().map(|c| c.mixing).sum();
            assert!((mixing - 1.0).abs() < 1e-9);
            for c in &fit.components {
                assert!(c.position.iter().chain(c.velocity.iter()).chain(c.covariance.iter()).all(|v| v.is_finite()));
            }
            assert!(fit.components[1].empty, "the far component explains nothing");
            assert_eq!(fit.components[1].position, Vector3::new(5.0, 5.0, 5.0));
        }
    }

    #[test]
    fn subsampling_keeps_the_answer_and_the_total_weight() {
        let mut rng = Normal(3);
        let pts = signer(&mut rng, 25); // 100k points
        let init = [
            (Vector3::new(0.0, 1.6, 0.0), Vector3::zeros()),
            (Vector3::new(0.25, 1.1, 0.3), Vector3::zeros()),
            (Vector3::new(-0.25, 1.1, 0.3), Vector3::zeros()),
        ];
        let cfg = EmConfig::default();
        let fit = fit_mixture(&pts, &init, &cfg).unwrap();
        assert_eq!(fit.points_used, cfg.max_points);
        for (c, p) in fit.components.iter().zip([[0.0, 1.6, 0.0], [0.25, 1.1, 0.3], [-0.25, 1.1, 0.3]]) {
            assert!((c.position - Vector3::from(p)).norm() < 0.01);
        }
        let total: f64 = pts.iter().map(|p| p.weight).sum();
        let mass: f64 = fit.components.iter().map(|c| c.mass).sum();
        assert!((mass / total + fit.outlier_share - 1.0).abs() < 1e-6);
    }

    #[test]
    fn extremities_are_head_and_the_two_lower_sides() {
        let mut rng = Normal(4);
        let pts = signer(&mut rng, 1);
        let [top, left, right] = extremity_means(&pts, Vector3::y(), Vector3::x()).unwrap();
        assert!((top.0.y - 1.6).abs() < 0.1);
        assert!(left.0.x < -0.15 && right.0.x > 0.15, "{left:?} {right:?}");
        // Clutter high on the wall behind and low near the floor is not an extremity.
        let mut cluttered = pts.clone();
        cluttered.extend(blob(&mut rng, 200, [0.4, 2.7, -3.3], [0.0; 3], 0.05, 0.05));
        cluttered.extend(blob(&mut rng, 200, [-0.8, 0.3, -2.8], [0.0; 3], 0.05, 0.05));
        let [top, left, right] = extremity_means(&cluttered, Vector3::y(), Vector3::x()).unwrap();
        assert!((top.0 - Vector3::new(0.0, 1.6, 0.0)).norm() < 0.1, "{top:?}");
        assert!(left.0.x < -0.15 && left.0.y > 0.9 && right.0.x > 0.15, "{left:?} {right:?}");
        assert!(extremity_means(&[], Vector3::y(), Vector3::x()).is_none());
    }

    /// `cargo test --release -p handflow-cluster -- --ignored --nocapture`
    #[test]
    #[ignore]
    fn time_per_fit_for_100k_points() {
        let mut rng = Normal(5);
        let pts = signer(&mut rng, 25);
        let init = [
            (Vector3::new(0.0, 1.6, 0.0), Vector3::zeros()),
            (Vector3::new(0.25, 1.1, 0.3), Vector3::zeros()),
            (Vector3::new(-0.25, 1.1, 0.3), Vector3::zeros()),
        ];
        let started = std::time::Instant::now();
        let runs = 20;
        let mut iterations = 0;
        for _ in 0..runs {
            iterations = fit_mixture(&pts, &init, &EmConfig::default()).unwrap().iterations;
        }
        let ms = started.elapsed().as_secs_f64() * 1e3 / runs as f64;
        eprintln!("{ms:.2} ms per fit of 100k points ({iterations} iterations)");
    }

    proptest::proptest! {
        #[test]
        fn a_bounded_spread_stays_a_covariance_within_its_bound(
            entries in proptest::collection::vec(-0.5f64..0.5, 36),
            max_std in 0.01f64..0.3,
        ) {
            // Any positive definite matrix: A Aᵀ plus a floor.
            let a = Matrix6::from_iterator(entries);
            let cov = a * a.transpose() + Matrix6::identity() * 1e-4;
            let bounded = bounded_position_spread(&cov, max_std);
            proptest::prop_assert!((bounded - bounded.transpose()).norm() < 1e-12);
            // Positive definite, and no positional spread above the limit: `limit I - P` is
            // positive semi-definite. Cholesky decides both to rounding, where an eigensolver
            // near coinciding eigenvalues need not.
            proptest::prop_assert!(Cholesky::new(bounded).is_some());
            let position: Matrix3<f64> = bounded.fixed_view::<3, 3>(0, 0).into_owned();
            let limit = max_std * max_std;
            proptest::prop_assert!(Cholesky::new(Matrix3::identity() * limit * (1.0 + 1e-9) - position).is_some());
            // Velocities keep their spread.
            let velocity: Matrix3<f64> = bounded.fixed_view::<3, 3>(3, 3).into_owned();
            proptest::prop_assert!((velocity - cov.fixed_view::<3, 3>(3, 3)).norm() < 1e-12);
        }

        #[test]
        fn jacobi_eigenvectors_give_the_matrix_back_to_rounding(
            entries in proptest::collection::vec(-0.5f64..0.5, 9),
            nearly_equal in proptest::bool::ANY,
        ) {
            let a = Matrix3::from_iterator(entries);
            let mut m = a * a.transpose();
            if nearly_equal {
                // Two eigenvalues 1e-9 (relative) apart: where a closed-form 2x2 step loses digits.
                let (values, vectors) = symmetric_eigen3(&m);
                let close = Vector3::new(values[0], values[0] * (1.0 + 1e-9), values[2]);
                m = vectors * Matrix3::from_diagonal(&close) * vectors.transpose();
                m = 0.5 * (m + m.transpose());
            }
            let (values, vectors) = symmetric_eigen3(&m);
            let scale = m.norm().max(1e-300);
            proptest::prop_assert!((vectors * vectors.transpose() - Matrix3::identity()).norm() < 1e-14);
            let back = vectors * Matrix3::from_diagonal(&values) * vectors.transpose();
            proptest::prop_assert!((back - m).norm() <= 1e-14 * scale, "residual {:e}", (back - m).norm() / scale);
        }

        #[test]
        fn any_small_set_fits_finitely(xs in proptest::collection::vec((-2.0f64..2.0, -1.0f64..1.0, 0.01f64..3.0), 1..50), c in -2.0f64..2.0) {
            let pts: Vec<WeightedPoint> = xs.iter().map(|&(x, v, w)| WeightedPoint { position: Vector3::new(x, x * x, 1.0), velocity: Vector3::new(v, 0.0, 0.0), weight: w }).collect();
            let init = [(Vector3::new(c, 0.0, 1.0), Vector3::zeros()), (Vector3::new(-c, 1.0, 1.0), Vector3::zeros()), (Vector3::new(0.0, 2.0, 1.0), Vector3::zeros())];
            let fit = fit_mixture(&pts, &init, &EmConfig::default()).unwrap();
            let mixing: f64 = fit.components.iter().map(|c| c.mixing).sum();
            proptest::prop_assert!((mixing - 1.0).abs() < 1e-9);
            for comp in &fit.components {
                proptest::prop_assert!(comp.covariance.iter().all(|v| v.is_finite()));
                proptest::prop_assert!((comp.covariance - comp.covariance.transpose()).norm() < 1e-9);
                // Positive definite, decided by Cholesky (exact to rounding, unlike an
                // eigensolver's smallest eigenvalue).
                proptest::prop_assert!(Cholesky::new(comp.covariance).is_some());
            }
        }
    }

    /// The head's component after a fit of a face, the neck below it, a hand raised beside
    /// the chin that no seed is on (its track sat elsewhere) and the other hand with its seed,
    /// the head bounded to `first_max_std`: its largest positional standard deviation.
    fn head_spread_beside_a_raised_hand(first_max_std: f64) -> f64 {
        let mut rng = Normal(7);
        let mut pts = blob(&mut rng, 1500, [0.0, 1.6, 0.0], [0.0; 3], 0.04, 0.05);
        pts.extend(blob(&mut rng, 400, [0.0, 1.47, 0.0], [0.0; 3], 0.03, 0.05));
        pts.extend(blob(&mut rng, 700, [0.2, 1.35, 0.15], [0.0, 0.5, 0.0], 0.03, 0.1));
        pts.extend(blob(&mut rng, 700, [-0.3, 1.1, 0.3], [0.0; 3], 0.03, 0.1));
        // Stray depths metres away, as every real scene has: the outlier class's uniform
        // density over their box is then too thin to claim the raised hand.
        pts.extend(blob(&mut rng, 20, [2.0, 0.5, 2.5], [0.0; 3], 1.0, 2.0));
        let init = [(Vector3::new(0.0, 1.6, 0.0), Vector3::zeros()), (Vector3::new(-0.3, 1.1, 0.3), Vector3::zeros())];
        let config = EmConfig { first_max_std, ..EmConfig::default() };
        let head = fit_mixture(&pts, &init, &config).unwrap().components[0];
        let position: Matrix3<f64> = head.covariance.fixed_view::<3, 3>(0, 0).into_owned();
        symmetric_eigen3(&position).0.max().sqrt()
    }

    #[test]
    fn a_head_bounded_to_its_size_does_not_stretch_over_a_raised_hand() {
        let unbounded = head_spread_beside_a_raised_hand(f64::INFINITY);
        assert!(unbounded > 0.14, "unbounded, the head's Gaussian stretches over the hand: {unbounded}");
        let bounded = head_spread_beside_a_raised_hand(0.1);
        assert!(bounded <= 0.1 + 1e-9, "{bounded}");
    }

    #[test]
    fn a_bounded_spread_keeps_small_covariances_and_caps_large_ones() {
        let small = Matrix6::from_diagonal(&Vector6::new(0.004, 0.002, 0.001, 0.01, 0.01, 0.01));
        assert_eq!(bounded_position_spread(&small, 0.1), small);
        let mut stretched = small;
        stretched[(0, 0)] = 0.09;
        stretched[(0, 3)] = 0.02;
        stretched[(3, 0)] = 0.02;
        let capped = bounded_position_spread(&stretched, 0.1);
        assert!((capped[(0, 0)] - 0.01).abs() < 1e-12, "{capped}");
        assert!((capped[(1, 1)] - 0.002).abs() < 1e-12 && (capped[(3, 3)] - 0.01).abs() < 1e-12);
        assert!((capped[(0, 3)] - 0.02 / 3.0).abs() < 1e-12, "the cross term scaled with the spread: {capped}");
    }

    #[test]
    fn a_lost_hand_is_looked_for_at_its_side_of_the_body_within_reach() {
        let at = |x: f64, y: f64| WeightedPoint {
            position: Vector3::new(x, y, 0.0),
            velocity: Vector3::new(0.0, 0.5, 0.0),
            weight: 1.0,
        };
        // Head at the top, a neck below it, the hands low on either side, and skin-like
        // clutter far to the left, out of reach.
        let mut points: Vec<WeightedPoint> = Vec::new();
        for (cx, cy, n) in [(0.0, 1.6, 40), (0.0, 1.4, 10), (-0.3, 1.1, 20), (0.3, 1.1, 20), (2.5, 1.0, 30)] {
            points.extend((0..n).map(|i| at(cx + 0.002 * f64::from(i), cy)));
        }
        let head = Vector3::new(0.0, 1.6, 0.0);
        let up = Vector3::y();
        let (left, vel) = side_extremity(&points, head, 1.0, up, Vector3::x()).expect("points in reach");
        assert!((left - Vector3::new(0.3, 1.1, 0.0)).norm() < 0.05, "{left:?}");
        assert!((vel.y - 0.5).abs() < 1e-9);
        let (right, _) = side_extremity(&points, head, 1.0, up, -Vector3::x()).expect("points in reach");
        assert!((right - Vector3::new(-0.3, 1.1, 0.0)).norm() < 0.05, "{right:?}");
        assert!(side_extremity(&points, Vector3::new(9.0, 9.0, 0.0), 1.0, up, Vector3::x()).is_none());
    }

    #[test]
    fn farthest_point_seeds_go_to_unexplained_blobs_only() {
        let at = |x: f64, y: f64| WeightedPoint {
            position: Vector3::new(x, y, 0.0),
            velocity: Vector3::zeros(),
            weight: 1.0,
        };
        let mut points: Vec<WeightedPoint> = Vec::new();
        for (cx, cy) in [(0.0, 1.6), (-0.3, 1.1), (0.3, 1.1)] {
            points.extend((0..20).map(|i| at(cx + 0.002 * f64::from(i), cy)));
        }
        let objects: Vec<(Vector3<f64>, Vector3<f64>)> = [(0.0, 1.6), (-0.3, 1.1), (0.3, 1.1)]
            .iter()
            .map(|&(x, y)| (Vector3::new(x, y, 0.0), Vector3::zeros()))
            .collect();
        // Every point is explained: no seed is added.
        let mut seeds = objects.clone();
        farthest_point_seeds(&points, &mut seeds, 2, 0.12);
        assert_eq!(seeds.len(), 3);
        // A neck blob gets one; the second extra seed finds nothing far enough.
        points.extend((0..10).map(|i| at(0.001 * f64::from(i), 1.4)));
        let mut seeds = objects.clone();
        farthest_point_seeds(&points, &mut seeds, 2, 0.12);
        assert_eq!(seeds.len(), 4);
        assert!((seeds[3].0 - Vector3::new(0.0, 1.4, 0.0)).norm() < 0.02, "{:?}", seeds[3].0);
        // Unusable points never seed.
        let mut seeds = objects;
        farthest_point_seeds(&[WeightedPoint { weight: f64::NAN, ..at(5.0, 5.0) }], &mut seeds, 2, 0.12);
        assert_eq!(seeds.len(), 3);
    }
}
