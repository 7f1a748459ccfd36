//! handflow's clustering stage: grouping weighted scene points in the 6D space of position
//! and velocity.
//!
//! [`em`] fits a mixture of full-covariance Gaussians by expectation maximisation to a
//! frame's weighted scene points; [`tracks`] labels the clusters as head, left hand and
//! right hand and predicts them with a constant-velocity model; [`velocity`] fuses a track's
//! velocity with its published positions' motion into the velocity it is published with.

#![cfg_attr(test, allow(clippy::unwrap_used))]

pub mod em;
pub mod hand;
pub mod stage;
pub mod tracks;
pub mod velocity;

use nalgebra::{Matrix6, Vector3, Vector6};

/// A scene point as clustering sees it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WeightedPoint {
    /// World position, metres.
    pub position: Vector3<f64>,
    /// World velocity, metres per second.
    pub velocity: Vector3<f64>,
    /// Non-negative weight.
    pub weight: f64,
}

impl WeightedPoint {
    /// Whether the point can take part in clustering: a positive, finite weight and finite
    /// coordinates (external input may carry anything).
    pub fn is_usable(&self) -> bool {
        self.weight > 0.0
            && self.weight.is_finite()
            && self.position.iter().chain(self.velocity.iter()).all(|v| v.is_finite())
    }

    /// The point in the 6D clustering space: velocity multiplied by `velocity_scale` (in
    /// seconds) so that both halves are lengths and one metric compares them.
    pub fn feature(&self, velocity_scale: f64) -> Vector6<f64> {
        let v = self.velocity * velocity_scale;
        Vector6::new(self.position.x, self.position.y, self.position.z, v.x, v.y, v.z)
    }
}

/// Weighted mean and covariance in the 6D space.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Moments {
    /// Weighted mean.
    pub mean: Vector6<f64>,
    /// Weighted (biased) covariance.
    pub covariance: Matrix6<f64>,
    /// Sum of weights.
    pub total_weight: f64,
}

/// Weighted moments of `points`; `None` when there is no positive, finite weight.
/// Non-finite points and negative weights are skipped (they carry no evidence).
pub fn weighted_moments(points: &[WeightedPoint], velocity_scale: f64) -> Option<Moments> {
    let usable = |p: &&WeightedPoint| p.is_usable();
    let total: f64 = points.iter().filter(usable).map(|p| p.weight).sum();
    if total.is_nan() || total <= 0.0 {
        return None;
    }
    let mean = points.iter().filter(usable).fold(Vector6::zeros(), |acc, p| acc + p.feature(velocity_scale) * p.weight)
        / total;
    let covariance = points.iter().filter(usable).fold(Matrix6::zeros(), |acc, p| {
        let d = p.feature(velocity_scale) - mean;
        acc + d * d.transpose() * p.weight
    }) / total;
    Some(Moments { mean, covariance, total_weight: total })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn point(x: f64, vx: f64, weight: f64) -> WeightedPoint {
        WeightedPoint { position: Vector3::new(x, 0.0, 1.0), velocity: Vector3::new(vx, 0.0, 0.0), weight }
    }

    #[test]
    fn moments_use_the_weights_and_the_velocity_scale() {
        let pts = [point(0.0, 0.0, 1.0), point(1.0, 0.1, 3.0)];
        let m = weighted_moments(&pts, 10.0).expect("has weight");
        assert!((m.mean[0] - 0.75).abs() < 1e-12);
        assert!((m.mean[3] - 0.75).abs() < 1e-12, "velocity scaled by 10");
        // Var of x: 0.25*0.75^2 + 0.75*0.25^2 = 0.1875.
        assert!((m.covariance[(0, 0)] - 0.1875).abs() < 1e-12);
        assert!((m.covariance[(0, 3)] - 0.1875).abs() < 1e-12);
        assert_eq!(m.total_weight, 4.0);
    }

    #[test]
    fn empty_or_weightless_sets_have_no_moments_and_nan_points_are_skipped() {
        assert!(weighted_moments(&[], 1.0).is_none());
        assert!(weighted_moments(&[point(1.0, 0.0, 0.0)], 1.0).is_none());
        let pts = [point(f64::NAN, 0.0, 1.0), point(2.0, 0.0, 1.0)];
        let m = weighted_moments(&pts, 1.0).expect("one usable point");
        assert_eq!(m.mean[0], 2.0);
        assert!(m.covariance.iter().all(|v| v.is_finite()));
    }

    proptest::proptest! {
        #[test]
        fn covariance_is_symmetric_positive_semidefinite(xs in proptest::collection::vec((-5.0f64..5.0, -1.0f64..1.0, 0.01f64..2.0), 1..40)) {
            let pts: Vec<WeightedPoint> = xs.iter().map(|&(x, v, w)| WeightedPoint { position: Vector3::new(x, x * 0.5, -x), velocity: Vector3::new(v, 0.0, v * x), weight: w }).collect();
            let m = weighted_moments(&pts, 3.0).expect("positive weights");
            proptest::prop_assert!((m.covariance - m.covariance.transpose()).norm() < 1e-9);
            let eig = m.covariance.symmetric_eigen();
            proptest::prop_assert!(eig.eigenvalues.iter().all(|&e| e > -1e-9));
        }
    }
}
