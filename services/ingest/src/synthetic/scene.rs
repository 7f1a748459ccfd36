//! Synthetic signer scenes: what a scene file says, the built-in presets, and the motion of
//! head and hands.
//!
//! World frame: metres, Y up, the signer stands at the origin facing +Z (towards the
//! cameras), so the signer's own left is +X.

use serde::{Deserialize, Serialize};

/// The tracked objects, by their truth labels (the signer's own sides).
pub const OBJECTS: [&str; 3] = ["head", "left_hand", "right_hand"];

/// A synthetic scene: cameras, image formation and motion.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SceneSpec {
    /// Cameras on an arc around the signer.
    pub cameras: CameraArc,
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Frames per second.
    pub fps: f64,
    /// Number of frames.
    pub frames: u32,
    /// Standard deviation of sensor noise, grey levels.
    #[serde(default = "default_noise")]
    pub noise: f64,
    /// Skin colour, RGB 0-255.
    #[serde(default = "default_skin")]
    pub skin_tone: [f64; 3],
    /// Clothing colour, RGB 0-255.
    #[serde(default = "default_clothing")]
    pub clothing: [f64; 3],
    /// Seed of the background texture and the noise.
    #[serde(default)]
    pub seed: u64,
    /// Motion of head and hands.
    pub motion: Motion,
}

fn default_noise() -> f64 {
    2.0
}
/// The skin of the face photograph (its cheeks and forehead average about (212, 180, 155)):
/// a person's hands share their face's tone.
fn default_skin() -> [f64; 3] {
    [212.0, 178.0, 152.0]
}
fn default_clothing() -> [f64; 3] {
    [40.0, 60.0, 110.0]
}

/// Cameras on a horizontal arc centred on the signer's chest, all looking at it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraArc {
    /// Distance from the chest point, metres.
    pub radius: f64,
    /// Azimuth of each camera, degrees (0 in front, positive towards the signer's left).
    pub angles_deg: Vec<f64>,
    /// Camera height above the chest point, metres.
    #[serde(default)]
    pub height: f64,
    /// Horizontal field of view, degrees.
    #[serde(default = "default_fov")]
    pub fov_deg: f64,
    /// Per-camera gain (default 1 each): exercises normalisation.
    #[serde(default)]
    pub gain: Vec<f64>,
    /// Per-camera offset, grey levels (default 0 each).
    #[serde(default)]
    pub offset: Vec<f64>,
    /// Per-camera colour cast, RGB multipliers (default [1, 1, 1] each).
    #[serde(default)]
    pub colour_cast: Vec<[f64; 3]>,
}

fn default_fov() -> f64 {
    50.0
}

/// How head and hands move.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "kind")]
pub enum Motion {
    /// A built-in sign-like motion.
    Preset {
        /// `signing`, `hands_cross` or `hide_right_hand`.
        name: String,
    },
    /// Keyframes (time in seconds, position in metres) per object, interpolated smoothly
    /// (Catmull-Rom); positions hold before the first and after the last keyframe.
    Keyframes {
        /// Head keyframes.
        head: Vec<Keyframe>,
        /// The signer's left hand.
        left_hand: Vec<Keyframe>,
        /// The signer's right hand.
        right_hand: Vec<Keyframe>,
    },
}

/// One keyframe.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Keyframe {
    /// Time, seconds.
    pub t: f64,
    /// Position, metres.
    pub pos: [f64; 3],
}

/// Names of the built-in scenes.
pub const PRESETS: [&str; 4] = ["signer-3cam", "signer-2cam-narrow", "hands-cross", "occluded-side"];

impl SceneSpec {
    /// A built-in scene by name.
    pub fn preset(name: &str) -> Option<SceneSpec> {
        let arc = |radius: f64, angles: &[f64]| CameraArc {
            radius,
            angles_deg: angles.to_vec(),
            height: 0.15,
            fov_deg: 50.0,
            gain: vec![1.0, 0.85, 1.15][..angles.len().min(3)].to_vec(),
            offset: vec![0.0, 12.0, -8.0][..angles.len().min(3)].to_vec(),
            colour_cast: vec![[1.0, 1.0, 1.0], [1.05, 1.0, 0.92], [0.94, 1.0, 1.06]][..angles.len().min(3)].to_vec(),
        };
        let base = |cameras: CameraArc, motion: &str| SceneSpec {
            cameras,
            width: 640,
            height: 480,
            fps: 30.0,
            frames: 150,
            noise: default_noise(),
            skin_tone: default_skin(),
            clothing: default_clothing(),
            seed: 7,
            motion: Motion::Preset { name: motion.to_string() },
        };
        match name {
            "signer-3cam" => Some(base(arc(1.8, &[-35.0, 0.0, 35.0]), "signing")),
            // About 25 cm between the cameras at 1.8 m: the paper's failure case in depth.
            "signer-2cam-narrow" => Some(base(arc(1.8, &[-4.0, 4.0]), "signing")),
            "hands-cross" => Some(base(arc(1.8, &[-35.0, 0.0, 35.0]), "hands_cross")),
            // The camera far on the signer's left loses the right hand behind the torso.
            "occluded-side" => Some(base(arc(1.8, &[-30.0, 0.0, 70.0]), "hide_right_hand")),
            _ => None,
        }
    }

    /// Checks the fields; the message names the one at fault.
    pub fn validate(&self) -> Result<(), String> {
        let n = self.cameras.angles_deg.len();
        if n == 0 || n > 8 {
            return Err(format!("`cameras.angles_deg` must list 1 to 8 cameras, got {n}"));
        }
        for (field, len) in [
            ("gain", self.cameras.gain.len()),
            ("offset", self.cameras.offset.len()),
            ("colour_cast", self.cameras.colour_cast.len()),
        ] {
            if len != 0 && len != n {
                return Err(format!("`cameras.{field}` must have one entry per camera ({n}) or none, got {len}"));
            }
        }
        if !(self.cameras.radius.is_finite() && self.cameras.radius > 0.5) {
            return Err(format!("`cameras.radius` must be more than 0.5 m, got {}", self.cameras.radius));
        }
        if !(self.cameras.fov_deg > 5.0 && self.cameras.fov_deg < 150.0) {
            return Err(format!("`cameras.fov_deg` must be between 5 and 150, got {}", self.cameras.fov_deg));
        }
        if self.width < 16 || self.height < 16 || self.width > 8192 || self.height > 8192 {
            return Err(format!("`width` x `height` must be between 16 and 8192, got {}x{}", self.width, self.height));
        }
        if !(self.fps.is_finite() && self.fps > 0.0) {
            return Err(format!("`fps` must be positive, got {}", self.fps));
        }
        if self.frames == 0 {
            return Err("`frames` must be at least 1".into());
        }
        if !(self.noise.is_finite() && self.noise >= 0.0) {
            return Err(format!("`noise` must be non-negative, got {}", self.noise));
        }
        match &self.motion {
            Motion::Preset { name } if !["signing", "hands_cross", "hide_right_hand"].contains(&name.as_str()) => {
                Err(format!("`motion.name`: unknown preset motion `{name}` (signing, hands_cross, hide_right_hand)"))
            }
            Motion::Keyframes { head, left_hand, right_hand } => {
                for (object, keys) in [("head", head), ("left_hand", left_hand), ("right_hand", right_hand)] {
                    if keys.is_empty() {
                        return Err(format!("`motion.{object}` needs at least one keyframe"));
                    }
                    if keys.windows(2).any(|w| w[1].t <= w[0].t) {
                        return Err(format!("`motion.{object}`: keyframe times must increase"));
                    }
                    if keys.iter().any(|k| !k.t.is_finite() || k.pos.iter().any(|v| !v.is_finite())) {
                        return Err(format!("`motion.{object}`: keyframes must be finite numbers"));
                    }
                }
                Ok(())
            }
            Motion::Preset { .. } => Ok(()),
        }
    }

    /// Position and velocity (metres, metres per second) of each object at time `t`.
    pub fn object_states(&self, t: f64) -> [([f64; 3], [f64; 3]); 3] {
        let h = 1e-3;
        let at = |t: f64| self.positions(t);
        let (a, b, c) = (at(t - h), at(t), at(t + h));
        std::array::from_fn(|i| (b[i], std::array::from_fn(|k| (c[i][k] - a[i][k]) / (2.0 * h))))
    }

    fn positions(&self, t: f64) -> [[f64; 3]; 3] {
        match &self.motion {
            Motion::Keyframes { head, left_hand, right_hand } => {
                [catmull_rom(head, t), catmull_rom(left_hand, t), catmull_rom(right_hand, t)]
            }
            Motion::Preset { name } => preset_motion(name, t),
        }
    }
}

/// Sign-like motions: smooth, hands 20-50 cm in front of the body, about one cycle per
/// 2-3 seconds, head moving a little.
fn preset_motion(name: &str, t: f64) -> [[f64; 3]; 3] {
    use std::f64::consts::TAU;
    let head = [0.02 * (TAU * t / 3.1).sin(), 1.62 + 0.01 * (TAU * t / 1.7).sin(), 0.01 * (TAU * t / 2.3).sin()];
    match name {
        "hands_cross" => {
            // Each hand sweeps across the body and back; they pass at different depths.
            let s = (TAU * t / 2.4).sin();
            let left = [0.05 + 0.22 * s, 1.18 + 0.05 * (TAU * t / 1.2).sin(), 0.32];
            let right = [-0.05 - 0.22 * s, 1.12 - 0.05 * (TAU * t / 1.2).sin(), 0.22];
            [head, left, right]
        }
        "hide_right_hand" => {
            // The right hand (world -X) swings back beside the torso for over a second per
            // cycle: the front camera still sees it, a camera far on the signer's left does not.
            let behind = (TAU * t / 3.0).sin().max(0.0);
            let right = [-0.26 - 0.06 * behind, 1.05, 0.25 - 0.37 * behind];
            let left = [0.22 + 0.08 * (TAU * t / 2.0).sin(), 1.2 + 0.12 * (TAU * t / 2.0).cos(), 0.3];
            [head, left, right]
        }
        _ => {
            let left = [
                0.2 + 0.1 * (TAU * t / 2.2).sin(),
                1.2 + 0.14 * (TAU * t / 2.2 + 1.0).cos(),
                0.28 + 0.06 * (TAU * t / 1.6).sin(),
            ];
            let right = [
                -0.18 - 0.12 * (TAU * t / 2.7).cos(),
                1.25 + 0.12 * (TAU * t / 2.7).sin(),
                0.3 + 0.05 * (TAU * t / 1.9).cos(),
            ];
            [head, left, right]
        }
    }
}

/// Catmull-Rom interpolation through keyframes; clamped at both ends.
fn catmull_rom(keys: &[Keyframe], t: f64) -> [f64; 3] {
    let (Some(first), Some(last)) = (keys.first(), keys.last()) else { return [0.0; 3] };
    if t <= first.t {
        return first.pos;
    }
    if t >= last.t {
        return last.pos;
    }
    let i = keys.windows(2).position(|w| t >= w[0].t && t < w[1].t).unwrap_or(0);
    let p1 = keys[i];
    let p2 = keys[i + 1];
    let p0 = if i > 0 { keys[i - 1] } else { p1 };
    let p3 = keys.get(i + 2).copied().unwrap_or(p2);
    let s = (t - p1.t) / (p2.t - p1.t);
    let (s2, s3) = (s * s, s * s * s);
    std::array::from_fn(|k| {
        0.5 * (2.0 * p1.pos[k]
            + (-p0.pos[k] + p2.pos[k]) * s
            + (2.0 * p0.pos[k] - 5.0 * p1.pos[k] + 4.0 * p2.pos[k] - p3.pos[k]) * s2
            + (-p0.pos[k] + 3.0 * p1.pos[k] - 3.0 * p2.pos[k] + p3.pos[k]) * s3)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn presets_are_valid() {
        for name in PRESETS {
            let spec = SceneSpec::preset(name).expect("preset exists");
            spec.validate().expect("valid");
            assert!(spec.frames >= 150);
        }
        assert!(SceneSpec::preset("nope").is_none());
    }

    #[test]
    fn keyframes_interpolate_through_their_points_and_velocity_is_the_derivative() {
        let keys = vec![
            Keyframe { t: 0.0, pos: [0.0, 1.0, 0.0] },
            Keyframe { t: 1.0, pos: [1.0, 1.0, 0.0] },
            Keyframe { t: 2.0, pos: [2.0, 1.0, 0.0] },
        ];
        assert_eq!(catmull_rom(&keys, 1.0), [1.0, 1.0, 0.0]);
        assert_eq!(catmull_rom(&keys, -1.0), [0.0, 1.0, 0.0]);
        let spec = SceneSpec {
            motion: Motion::Keyframes { head: keys.clone(), left_hand: keys.clone(), right_hand: keys },
            ..SceneSpec::preset("signer-3cam").expect("preset")
        };
        spec.validate().expect("valid");
        let [(pos, vel), _, _] = spec.object_states(1.0);
        assert!((pos[0] - 1.0).abs() < 1e-9);
        assert!((vel[0] - 1.0).abs() < 1e-3, "uniform keyframes move at 1 m/s: {vel:?}");
    }

    #[test]
    fn bad_scene_fields_are_named() {
        let mut spec = SceneSpec::preset("signer-3cam").expect("preset");
        spec.cameras.gain = vec![1.0];
        assert!(spec.validate().unwrap_err().contains("cameras.gain"));
        let mut spec = SceneSpec::preset("signer-3cam").expect("preset");
        spec.motion = Motion::Preset { name: "dance".into() };
        assert!(spec.validate().unwrap_err().contains("dance"));
        let mut spec = SceneSpec::preset("signer-3cam").expect("preset");
        spec.motion = Motion::Keyframes {
            head: vec![Keyframe { t: 1.0, pos: [0.0; 3] }, Keyframe { t: 0.5, pos: [0.0; 3] }],
            left_hand: vec![],
            right_hand: vec![],
        };
        assert!(spec.validate().unwrap_err().contains("motion.head"));
    }
}
