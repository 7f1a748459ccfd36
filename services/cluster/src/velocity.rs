//! The velocity an object is published with: its track's velocity (the scene flow's, taken
//! through the tracker) fused with the motion of its published positions.
//!
//! The flow measures a point's displacement between frames; how far it can be off in metres
//! per second grows quickly with the frame interval (at 6 fps the engine searches 125 times
//! the volume of velocities it searches at 30 fps, with the same particles). The published
//! positions' differences are off by their noise divided by the interval, so they say more
//! the longer it is. A constant-velocity Kalman filter per object weighs the two by those
//! errors. Measured with `eval tracks` against rendered truth (BENCHMARKS.md): at 6 fps the
//! hands' velocity errors fall two- to threefold and point the right way, at 30 and 60 fps
//! they stay as they were or improve a little. The tracker's own velocity, which predicts
//! the next frame's clusters, is left as it is: the positions do not change.

use nalgebra::{Matrix2, Vector2, Vector3};

/// Frame interval at which the flow's velocity is off by [`FLOW_VELOCITY_STD_M_S`], seconds.
pub const REFERENCE_INTERVAL_S: f64 = 1.0 / 30.0;
/// How far the flow's velocity of an object is off at [`REFERENCE_INTERVAL_S`], metres per
/// second (the hands of the rendered 30 fps scenes: 0.06-0.12 m/s RMS).
pub const FLOW_VELOCITY_STD_M_S: f64 = 0.2;
/// Power of the interval ratio the flow velocity's error grows with (2 measured best on the
/// rendered 6, 30 and 60 fps scenes; 1 left the 6 fps left hand 0.47 m/s off instead of 0.32).
pub const FLOW_VELOCITY_INTERVAL_POWER: i32 = 2;
/// How far a published position is off, metres.
pub const POSITION_STD_M: f64 = 0.015;
/// White-noise acceleration density of a head, m^2/s^3: a head moves slowly and smoothly.
pub const HEAD_ACCELERATION_DENSITY: f64 = 0.2;
/// White-noise acceleration density of a hand, m^2/s^3: hands start and stop within a tenth
/// of a second.
pub const HAND_ACCELERATION_DENSITY: f64 = 10.0;
/// A gap longer than this starts the filter afresh, seconds (as long as a track may coast).
pub const MAX_GAP_S: f64 = 0.5;
/// A position this far from the filter's prediction is a track started again elsewhere, not
/// motion: the filter starts afresh there, metres.
pub const RESTART_JUMP_M: f64 = 0.5;

/// The flow velocity's standard deviation for frames `dt` seconds apart.
pub fn flow_velocity_std(dt: f64) -> f64 {
    FLOW_VELOCITY_STD_M_S * (dt / REFERENCE_INTERVAL_S).powi(FLOW_VELOCITY_INTERVAL_POWER)
}

#[derive(Clone, Copy, Debug)]
struct State {
    t: f64,
    position: Vector3<f64>,
    velocity: Vector3<f64>,
    /// Covariance of (position, velocity) along one axis; the axes share it (their noises
    /// are alike and independent).
    cov: Matrix2<f64>,
}

/// One object's published velocity.
#[derive(Clone, Debug)]
pub struct VelocityFilter {
    acceleration_density: f64,
    state: Option<State>,
}

impl VelocityFilter {
    /// A filter for an object whose acceleration has white-noise density
    /// `acceleration_density` (m^2/s^3).
    pub fn new(acceleration_density: f64) -> Self {
        Self { acceleration_density, state: None }
    }

    /// Forgets the object (its track was lost).
    pub fn reset(&mut self) {
        self.state = None;
    }

    /// The velocity to publish at time `t` (seconds) for an object published at `position`
    /// whose track carries `velocity`; `nominal_dt` is the stream's frame interval, which
    /// sizes the first frame's uncertainty. Non-finite input starts the filter afresh and
    /// is passed through.
    pub fn update(&mut self, t: f64, position: Vector3<f64>, velocity: Vector3<f64>, nominal_dt: f64) -> Vector3<f64> {
        let finite = t.is_finite() && position.iter().chain(velocity.iter()).all(|v| v.is_finite());
        let previous = self.state.filter(|s| {
            let dt = t - s.t;
            finite && dt > 0.0 && dt <= MAX_GAP_S && (s.position + s.velocity * dt - position).norm() <= RESTART_JUMP_M
        });
        let Some(s) = previous else {
            let sv = flow_velocity_std(nominal_dt.clamp(1e-3, MAX_GAP_S));
            self.state = finite.then_some(State {
                t,
                position,
                velocity,
                cov: Matrix2::from_diagonal(&Vector2::new(POSITION_STD_M.powi(2), sv * sv)),
            });
            return velocity;
        };
        let dt = t - s.t;
        let q = self.acceleration_density;
        // Predict: x' = F x, P' = F P F^T + Q (white-noise acceleration).
        let f = Matrix2::new(1.0, dt, 0.0, 1.0);
        let noise = Matrix2::new(dt.powi(3) / 3.0, dt * dt / 2.0, dt * dt / 2.0, dt) * q;
        let p = f * s.cov * f.transpose() + noise;
        let predicted_position = s.position + s.velocity * dt;
        // Update with both measurements: K = P (P + R)^-1, R = diag(position, flow velocity).
        let r = Matrix2::from_diagonal(&Vector2::new(POSITION_STD_M.powi(2), flow_velocity_std(dt).powi(2)));
        // P + R is positive definite (R is), so it inverts.
        let k = p * (p + r).try_inverse().unwrap_or_else(Matrix2::zeros);
        let innovation_p = position - predicted_position;
        let innovation_v = velocity - s.velocity;
        let new_position = predicted_position + innovation_p * k[(0, 0)] + innovation_v * k[(0, 1)];
        let new_velocity = s.velocity + innovation_p * k[(1, 0)] + innovation_v * k[(1, 1)];
        let cov = (Matrix2::identity() - k) * p;
        // Kept symmetric against rounding.
        let cov = (cov + cov.transpose()) * 0.5;
        self.state = Some(State { t, position: new_position, velocity: new_velocity, cov });
        new_velocity
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A hand moving at `true_v` sampled every `dt` with a flow velocity `flow` and positions
    /// off by `noise(i)`: the published velocity after `n` frames.
    fn run(dt: f64, true_v: Vector3<f64>, flow: Vector3<f64>, n: usize, noise: impl Fn(usize) -> f64) -> Vector3<f64> {
        let mut f = VelocityFilter::new(HAND_ACCELERATION_DENSITY);
        let mut out = Vector3::zeros();
        for i in 0..n {
            let t = i as f64 * dt;
            let p = true_v * t + Vector3::repeat(noise(i));
            out = f.update(t, p, flow, dt);
        }
        out
    }

    #[test]
    fn at_a_low_rate_the_positions_correct_a_wrong_flow_velocity() {
        let true_v = Vector3::new(0.5, 0.0, 0.0);
        let wrong = Vector3::new(-0.5, 0.2, 0.0);
        // Positions 1 cm off on every axis, flipping each frame (0.12 m/s of difference noise).
        let v = run(1.0 / 6.0, true_v, wrong, 12, |i| if i % 2 == 0 { 0.01 } else { -0.01 });
        assert!((wrong - true_v).norm() > 1.0);
        assert!((v - true_v).norm() < 0.35 && v.x > 0.25, "6 fps: {v}");
        // Exact positions: the wrong flow is all but ignored.
        let v = run(1.0 / 6.0, true_v, wrong, 12, |_| 0.0);
        assert!((v - true_v).norm() < 0.05, "6 fps, exact positions: {v}");
    }

    #[test]
    fn at_a_high_rate_the_flow_velocity_outweighs_noisy_position_differences() {
        let true_v = Vector3::new(0.5, 0.0, 0.0);
        // Position noise of 1 cm flipping every frame: differences at 60 fps are 1.2 m/s off.
        let v = run(1.0 / 60.0, true_v, true_v, 60, |i| if i % 2 == 0 { 0.01 } else { -0.01 });
        assert!((v - true_v).norm() < 0.1, "60 fps: {v}");
        let rate_of_positions = 0.02 * 60.0;
        assert!(rate_of_positions > 1.0, "the differences alone would be this far off");
    }

    #[test]
    fn an_exact_measurement_stays_exact_and_gaps_jumps_and_nan_start_afresh() {
        let v = Vector3::new(0.3, -0.2, 0.1);
        let exact = run(1.0 / 30.0, v, v, 30, |_| 0.0);
        assert!((exact - v).norm() < 1e-9, "{exact}");
        let mut f = VelocityFilter::new(HAND_ACCELERATION_DENSITY);
        f.update(0.0, Vector3::zeros(), v, 1.0 / 30.0);
        // After a gap longer than a track may coast, the track's velocity is taken as it is.
        let fresh = Vector3::new(-1.0, 0.0, 0.0);
        assert_eq!(f.update(1.0, Vector3::new(0.3, -0.2, 0.1), fresh, 1.0 / 30.0), fresh);
        // So it is after a jump no motion explains (a track started again elsewhere).
        assert_eq!(f.update(1.0 + 1.0 / 30.0, Vector3::new(2.0, 0.0, 0.0), v, 1.0 / 30.0), v);
        // Non-finite input passes through and leaves nothing behind.
        let nan = Vector3::new(f64::NAN, 0.0, 0.0);
        assert!(f.update(1.1, nan, v, 1.0 / 30.0).iter().all(|x| x.is_finite()));
        assert_eq!(f.update(1.2, Vector3::zeros(), fresh, 1.0 / 30.0), fresh);
    }

    #[test]
    fn the_flow_velocitys_error_grows_with_the_interval() {
        assert!((flow_velocity_std(REFERENCE_INTERVAL_S) - FLOW_VELOCITY_STD_M_S).abs() < 1e-12);
        assert!((flow_velocity_std(1.0 / 6.0) - 25.0 * FLOW_VELOCITY_STD_M_S).abs() < 1e-9);
        assert!(flow_velocity_std(1.0 / 60.0) < FLOW_VELOCITY_STD_M_S);
    }
}
