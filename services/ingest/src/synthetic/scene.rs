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
    /// Short sleeves: metres of each forearm left bare, skin-coloured like the hands, from
    /// the wrist towards the elbow (at most [`FOREARM_M`], the whole forearm). 0, the default,
    /// is long sleeves down to the wrists. The truth of a hand stays its centre.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub bare_forearm_m: f64,
    /// A cluttered room: a plank floor, a low sideboard and a tall cabinet behind the signer
    /// in warm wood tones close to (not equal to) skin. They are background (mask 0), never
    /// tracked.
    #[serde(default, skip_serializing_if = "is_false")]
    pub clutter: bool,
    /// Motion blur: the shutter is open for this fraction of the frame interval (0 to 1),
    /// centred on the frame's time; 0, the default, is an instantaneous exposure.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub motion_blur: f64,
    /// Sub-frame renders averaged over the open shutter when `motion_blur` > 0: odd (3 to
    /// 15), so that the middle one is at the frame's time; the masks and truth are that one's.
    #[serde(default = "default_blur_samples", skip_serializing_if = "is_default_blur_samples")]
    pub motion_blur_samples: u32,
    /// Lossy compression, as an MJPEG webcam (most USB webcams at 720p and above) delivers
    /// frames: every view is encoded as a JPEG at this quality (1 to 100) and decoded back
    /// before it is written or sent, so block edges, ringing and coarser colour reach the
    /// engine. 0, the default, is lossless.
    #[serde(default, skip_serializing_if = "is_zero_u8")]
    pub jpeg_quality: u8,
    /// Motion of head and hands.
    pub motion: Motion,
}

/// Length of a forearm from the wrist to the elbow, metres (the longest bare forearm).
pub const FOREARM_M: f64 = 0.25;

fn is_zero(v: &f64) -> bool {
    *v == 0.0
}
fn is_zero_u8(v: &u8) -> bool {
    *v == 0
}

fn is_false(v: &bool) -> bool {
    !*v
}
fn default_blur_samples() -> u32 {
    5
}
fn is_default_blur_samples(v: &u32) -> bool {
    *v == default_blur_samples()
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
    /// Per camera, clockwise quarter turns (0 to 3) that make its frames upright: the camera
    /// is mounted rotated about its optical axis (a phone held sideways is 1 or 3), so its
    /// frames show the scene turned and odd turns swap width and height. Its lens stays
    /// the same (`fov_deg` spans the sensor's `width`). The rig records the turns
    /// (`mount_quarter_turns` in `rig.toml`); its calibration is of the raw frames. Default 0
    /// each.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub mount_quarter_turns: Vec<u8>,
    /// Every camera's lens as OpenCV's fisheye model with these coefficients `k1 k2 k3 k4`
    /// (a wide lens calibrated so), `fov_deg` still spanning the width; default: pinhole.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fisheye: Option<[f64; 4]>,
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
pub const PRESETS: [&str; 7] = [
    "signer-3cam",
    "signer-2cam-narrow",
    "hands-cross",
    "occluded-side",
    "signer-short-sleeves",
    "signer-6fps",
    "cluttered-room",
];

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
            mount_quarter_turns: Vec::new(),
            fisheye: None,
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
            bare_forearm_m: 0.0,
            clutter: false,
            motion_blur: 0.0,
            motion_blur_samples: default_blur_samples(),
            jpeg_quality: 0,
            motion: Motion::Preset { name: motion.to_string() },
        };
        let signer = || base(arc(1.8, &[-35.0, 0.0, 35.0]), "signing");
        match name {
            "signer-3cam" => Some(signer()),
            // About 25 cm between the cameras at 1.8 m: the paper's failure case in depth.
            "signer-2cam-narrow" => Some(base(arc(1.8, &[-4.0, 4.0]), "signing")),
            "hands-cross" => Some(base(arc(1.8, &[-35.0, 0.0, 35.0]), "hands_cross")),
            // The camera far on the signer's left loses the right hand behind the torso.
            "occluded-side" => Some(base(arc(1.8, &[-30.0, 0.0, 70.0]), "hide_right_hand")),
            // Failure modes of real footage, each otherwise signer-3cam. A T-shirt: skin runs
            // from each hand a forearm's length up the arm.
            "signer-short-sleeves" => Some(SceneSpec { bare_forearm_m: FOREARM_M, ..signer() }),
            // The shared real session's webcams: the same 5 s at 6 frames per second, so hands
            // move five times as far between frames.
            "signer-6fps" => Some(SceneSpec { fps: 6.0, frames: 30, ..signer() }),
            // Wooden furniture near skin in colour behind the signer.
            "cluttered-room" => Some(SceneSpec { clutter: true, ..signer() }),
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
            ("mount_quarter_turns", self.cameras.mount_quarter_turns.len()),
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
        if let Some(k) = self.cameras.fisheye {
            if !k.iter().all(|c| c.is_finite() && c.abs() < 1.0) {
                return Err(format!("`cameras.fisheye` must be 4 coefficients between -1 and 1, got {k:?}"));
            }
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
        if let Some(turns) = self.cameras.mount_quarter_turns.iter().find(|&&t| t > 3) {
            return Err(format!("`cameras.mount_quarter_turns` must be 0 to 3 per camera, got {turns}"));
        }
        if !(0.0..=FOREARM_M).contains(&self.bare_forearm_m) {
            return Err(format!(
                "`bare_forearm_m` must be between 0 (long sleeves) and {FOREARM_M} m (the whole forearm), got {}",
                self.bare_forearm_m
            ));
        }
        if !(0.0..=1.0).contains(&self.motion_blur) {
            return Err(format!(
                "`motion_blur` (the open shutter's share of the frame interval) must be between 0 and 1, got {}",
                self.motion_blur
            ));
        }
        if self.jpeg_quality > 100 {
            return Err(format!("`jpeg_quality` must be 0 (lossless) or 1 to 100, got {}", self.jpeg_quality));
        }
        if self.motion_blur_samples.is_multiple_of(2) || !(3..=15).contains(&self.motion_blur_samples) {
            return Err(format!(
                "`motion_blur_samples` must be odd, 3 to 15 (the middle one is at the frame's time), got {}",
                self.motion_blur_samples
            ));
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
            // Five seconds each, whatever the frame rate.
            assert!((f64::from(spec.frames) / spec.fps - 5.0).abs() < 1e-9, "{name}");
        }
        assert!(SceneSpec::preset("nope").is_none());
    }

    #[test]
    fn the_failure_mode_presets_are_signer_3cam_with_one_change() {
        let reference = SceneSpec::preset("signer-3cam").expect("preset");
        assert_eq!(reference.bare_forearm_m, 0.0, "long sleeves by default");
        assert!(!reference.clutter);
        assert_eq!(reference.motion_blur, 0.0);
        let sleeves = SceneSpec::preset("signer-short-sleeves").expect("preset");
        assert_eq!(sleeves, SceneSpec { bare_forearm_m: FOREARM_M, ..reference.clone() });
        let slow = SceneSpec::preset("signer-6fps").expect("preset");
        assert_eq!(slow.fps, 6.0);
        assert_eq!(slow.frames, 30);
        assert_eq!(slow, SceneSpec { fps: 6.0, frames: 30, ..reference.clone() });
        // The same motion: frame k at 6 fps is frame 5k at 30 fps.
        assert_eq!(slow.object_states(12.0 / slow.fps), reference.object_states(60.0 / reference.fps));
        let room = SceneSpec::preset("cluttered-room").expect("preset");
        assert_eq!(room, SceneSpec { clutter: true, ..reference });
    }

    #[test]
    fn scene_files_without_the_new_fields_still_parse_and_defaults_are_not_written() {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/scenes");
        let mut parsed = 0;
        for entry in std::fs::read_dir(&dir).expect("tests/scenes") {
            let path = entry.expect("entry").path();
            if path.extension().is_some_and(|e| e == "toml") {
                let text = std::fs::read_to_string(&path).expect("read");
                let spec: SceneSpec = toml::from_str(&text).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
                spec.validate().unwrap_or_else(|e| panic!("{}: {e}", path.display()));
                assert_eq!((spec.bare_forearm_m, spec.clutter, spec.motion_blur), (0.0, false, 0.0));
                assert!(spec.cameras.mount_quarter_turns.is_empty());
                parsed += 1;
            }
        }
        assert!(parsed >= 5, "{parsed} scene files in {}", dir.display());
        // A scene written without the options reads as before; one with them round-trips.
        let plain = toml::to_string(&SceneSpec::preset("signer-3cam").expect("preset")).expect("toml");
        for key in ["bare_forearm_m", "clutter", "motion_blur", "mount_quarter_turns", "jpeg_quality"] {
            assert!(!plain.contains(key), "`{key}` written at its default:\n{plain}");
        }
        let mut spec = SceneSpec::preset("cluttered-room").expect("preset");
        spec.bare_forearm_m = 0.2;
        spec.motion_blur = 0.5;
        spec.motion_blur_samples = 7;
        spec.jpeg_quality = 40;
        spec.cameras.mount_quarter_turns = vec![0, 1, 3];
        let text = toml::to_string(&spec).expect("toml");
        assert_eq!(toml::from_str::<SceneSpec>(&text).expect("parses"), spec);
        let from_file: SceneSpec = toml::from_str(
            r#"
                width = 160
                height = 120
                fps = 30.0
                frames = 5
                clutter = true
                bare_forearm_m = 0.25
                motion_blur = 0.5

                [cameras]
                radius = 1.8
                angles_deg = [-35.0, 0.0, 35.0]
                mount_quarter_turns = [0, 1, 0]

                [motion]
                kind = "preset"
                name = "signing"
            "#,
        )
        .expect("a hand-written scene with the options parses");
        from_file.validate().expect("valid");
        assert_eq!(from_file.motion_blur_samples, 5);
        assert_eq!(from_file.cameras.mount_quarter_turns, vec![0, 1, 0]);
        assert!(from_file.clutter && from_file.bare_forearm_m == 0.25);
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
        let bad = |edit: &dyn Fn(&mut SceneSpec), field: &str| {
            let mut spec = SceneSpec::preset("signer-3cam").expect("preset");
            edit(&mut spec);
            let message = spec.validate().expect_err(field);
            assert!(message.contains(field), "{message}");
        };
        bad(&|s| s.bare_forearm_m = 0.4, "bare_forearm_m");
        bad(&|s| s.bare_forearm_m = f64::NAN, "bare_forearm_m");
        bad(&|s| s.motion_blur = 1.5, "motion_blur");
        bad(&|s| s.motion_blur_samples = 4, "motion_blur_samples");
        bad(&|s| s.jpeg_quality = 101, "jpeg_quality");
        bad(&|s| s.cameras.mount_quarter_turns = vec![0, 1], "cameras.mount_quarter_turns");
        bad(&|s| s.cameras.mount_quarter_turns = vec![0, 4, 0], "cameras.mount_quarter_turns");
    }
}
