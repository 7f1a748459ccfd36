//! The world's up from the faces the cameras see, for a rig whose calibration states no up.
//!
//! Without one, the up is estimated from the cameras' image ups ([`Rig::world_up`]): right
//! for rigs mounted upright and for a camera or two mounted sideways among them, wrong for a
//! rig whose cameras are mostly mounted sideways and whose calibration cannot say so
//! (Pose2Sim's, anipose's, OpenCV's and caliscope's files record no mount). Such a rig was
//! tracked with the world on its side: no face found in any view, the head looked for
//! beside the body, every object half a metre off. A person's face is upright, so the
//! turn at which the face detector finds it in a view says where up is in that view.

use anyhow::Result;
use handflow_flow::skin::adapt::with_detector;
use handflow_flow::skin::faces::{detection_bin, Region};
use handflow_flow::stream::{expected_palm_px, PALM_WIDTH_M};
use handflow_ingest::Recording;
use handflow_protocol::{Camera, Rig};
use nalgebra::Vector3;
use rayon::prelude::*;

/// Width of an adult's face as the detector boxes it, metres (eyebrows to chin, cheek to
/// cheek): with the palm's width, what sizes the search at the rig's distance.
pub const FACE_WIDTH_M: f64 = 0.15;

/// Views whose faces must agree on an up before it counts (one view can see a poster).
pub const AGREEING_VIEWS: usize = 2;

/// Largest angle between two views' face ups that still agree, degrees: views of one rig
/// differ in roll by a few degrees, quarter turns by 90.
pub const AGREEMENT_DEG: f64 = 30.0;

/// The faces' up replaces the cameras' estimate only when they differ by more than this,
/// degrees: a quarter turn is 90, while an upright rig's estimate can lie 20 degrees from
/// the faces' (cameras tilted down at a seated signer).
pub const DISAGREEMENT_DEG: f64 = 45.0;

/// What the faces said about the world's up.
#[derive(Clone, Debug, PartialEq)]
pub struct FaceUp {
    /// The up the agreeing views' faces give (unit, world coordinates).
    pub direction: Vector3<f64>,
    /// The views that agree on it and the clockwise quarter turns that showed each its face
    /// upright.
    pub views: Vec<(String, u8)>,
    /// The cameras' own estimate the faces overrule.
    pub estimate: Vector3<f64>,
    /// Number of the frame whose faces gave it.
    pub frame: u64,
}

impl FaceUp {
    /// One line for the log.
    pub fn summary(&self) -> String {
        let views: Vec<String> = self.views.iter().map(|(name, turns)| format!("`{name}` at {turns}")).collect();
        format!(
            "world up {:?} from the faces the views see in frame {} (upright at clockwise quarter turns {}), not the \
             cameras' estimate {:?}, {:.0}° from it: the calibration records no up and most cameras seem mounted \
             sideways",
            self.direction.as_slice(),
            self.frame,
            views.join(", "),
            self.estimate.as_slice(),
            self.direction.dot(&self.estimate).clamp(-1.0, 1.0).acos().to_degrees(),
        )
    }
}

/// Seconds into the recording of the frame sets searched for faces, in turn, until views
/// agree: a person may walk into the views, or turn to the cameras, after the recording
/// starts. A recording in which no two views ever agree costs every search (four turns per
/// view at each), so they are few.
pub const PROBE_SECONDS: [f64; 3] = [0.0, 1.0, 2.0];

/// The world's up the faces in the recording's first frame sets give, when the rig states
/// none and it differs from the cameras' estimate by more than [`DISAGREEMENT_DEG`]; `None`
/// when the faces confirm the estimate, say nothing (no face, or too few views agree, in
/// every frame set of [`PROBE_SECONDS`]) or the rig states its up. In each frame set every
/// view is searched at its mount's turn first (views in parallel: an upright rig costs one
/// search per view), then those that showed no face at the other three. A frame set that
/// cannot be read is a warning, and the next is searched.
pub fn face_up(rec: &Recording, rig: &Rig) -> Result<Option<FaceUp>> {
    if rig.declared_up.is_some() || rig.cameras.len() < AGREEING_VIEWS || rec.is_empty() {
        return Ok(None);
    }
    let estimate = rig.world_up().direction;
    let mut frame_set = vec![0u8; rec.frame_set_len()];
    for index in probe_indices(rec.len(), rec.frame_rate()) {
        let frame = match rec.read_frame_into(index as u64, false, &mut frame_set) {
            Ok(info) => info.frame,
            Err(e) => {
                tracing::warn!("frame set {index} was not searched for the faces' up: {e}");
                continue;
            }
        };
        if let Some(verdict) = face_up_in(rec, rig, estimate, &frame_set, frame)? {
            return Ok(verdict);
        }
        tracing::debug!("frame {frame}: too few views agree on the faces' up");
    }
    Ok(None)
}

/// Indices of the frame sets at [`PROBE_SECONDS`] in a recording of `len` sets at `fps`:
/// clamped to its last set, each once.
fn probe_indices(len: usize, fps: f64) -> Vec<usize> {
    let mut indices: Vec<usize> = Vec::new();
    for seconds in PROBE_SECONDS {
        let at = if fps.is_finite() && fps > 0.0 { (seconds * fps).round() as usize } else { 0 };
        let at = at.min(len.saturating_sub(1));
        if !indices.contains(&at) {
            indices.push(at);
        }
    }
    indices
}

/// What the faces in one frame set (`frame_set`, frame number `frame`) say: `Some(verdict)`
/// once views agree on an up (the faces' up, or `None` where it confirms the cameras'
/// `estimate`), `None` when too few views agree.
fn face_up_in(
    rec: &Recording,
    rig: &Rig,
    estimate: Vector3<f64>,
    frame_set: &[u8],
    frame: u64,
) -> Result<Option<Option<FaceUp>>> {
    let views = rec.views(frame_set);
    let cameras = &rig.cameras[..views.len()];
    // The first of `turns` at which view `k` shows a face.
    let face_turn = |k: usize, turns: &[u8]| -> Result<Option<u8>> {
        let camera = &cameras[k];
        let face_px = expected_palm_px(cameras, k) * FACE_WIDTH_M / PALM_WIDTH_M;
        let bin = detection_bin(face_px as f32);
        let whole = Region { x: 0, y: 0, width: camera.width, height: camera.height };
        with_detector(|detector| {
            turns
                .iter()
                .copied()
                .find(|&t| !detector.detect_in_binned(views[k], camera.width, camera.height, whole, t, bin).is_empty())
        })
        .map_err(anyhow::Error::msg)
    };
    let verdict = |turns: &[Option<u8>]| {
        let ups: Vec<(String, u8, Vector3<f64>)> = cameras
            .iter()
            .zip(turns)
            .filter_map(|(camera, t)| t.map(|t| (camera.name.clone(), t, upright_up(camera, t))))
            .collect();
        agreeing(&ups).map(|agreed| decide(agreed, estimate, frame).map(|found| refined(rig, found)))
    };
    let mount = |k: usize| cameras[k].mount_quarter_turns % 4;
    let at_mounts: Vec<Option<u8>> =
        (0..cameras.len()).into_par_iter().map(|k| face_turn(k, &[mount(k)])).collect::<Result<_>>()?;
    if let Some(found) = verdict(&at_mounts) {
        return Ok(Some(found));
    }
    let at_any: Vec<Option<u8>> = (0..cameras.len())
        .into_par_iter()
        .map(|k| match at_mounts[k] {
            Some(t) => Ok(Some(t)),
            None => face_turn(k, &[(mount(k) + 1) % 4, (mount(k) + 3) % 4, (mount(k) + 2) % 4]),
        })
        .collect::<Result<_>>()?;
    Ok(verdict(&at_any))
}

/// `found` with its direction estimated again from every camera's image up once each is
/// turned as the faces' up says (and snapped to a world axis within 10 degrees, as the
/// cameras' own estimate is): the faces pick the mounts, the calibrated rotations say
/// precisely where up is. Kept as the faces gave it if the two differ by more than
/// [`AGREEMENT_DEG`].
fn refined(rig: &Rig, mut found: FaceUp) -> FaceUp {
    if let Ok(estimate) = rig.estimate_up_under(found.direction) {
        if estimate.direction.dot(&found.direction) >= AGREEMENT_DEG.to_radians().cos() {
            found.direction = estimate.direction;
        }
    }
    found
}

/// The world direction that is up in `camera`'s frames turned `turns` clockwise quarter
/// turns.
fn upright_up(camera: &Camera, turns: u8) -> Vector3<f64> {
    camera.clone().with_mount_quarter_turns(turns).image_up()
}

/// The first [`AGREEING_VIEWS`] views whose ups lie within [`AGREEMENT_DEG`] of each other.
fn agreeing(ups: &[(String, u8, Vector3<f64>)]) -> Option<Vec<&(String, u8, Vector3<f64>)>> {
    let cos = AGREEMENT_DEG.to_radians().cos();
    ups.iter().find_map(|a| {
        let group: Vec<_> = ups.iter().filter(|b| a.2.dot(&b.2) >= cos).collect();
        (group.len() >= AGREEING_VIEWS).then_some(group)
    })
}

/// The agreeing views' mean up, kept only where it overrules `estimate`.
fn decide(agreed: Vec<&(String, u8, Vector3<f64>)>, estimate: Vector3<f64>, frame: u64) -> Option<FaceUp> {
    let direction = agreed.iter().map(|v| v.2).sum::<Vector3<f64>>().try_normalize(1e-9)?;
    if direction.dot(&estimate) >= DISAGREEMENT_DEG.to_radians().cos() {
        return None;
    }
    Some(FaceUp { direction, views: agreed.iter().map(|v| (v.0.clone(), v.1)).collect(), estimate, frame })
}

#[cfg(test)]
mod tests {
    use super::*;
    use handflow_protocol::Distortion;
    use nalgebra::{Matrix3, Rotation3};

    /// A camera 2 m in front of the origin (+Z side, Y up) looking at it, mounted `turns`
    /// clockwise quarter turns (its raw frames turned that much the other way).
    fn camera(name: &str, x: f64, turns: u8) -> Camera {
        let position = Vector3::new(x, 0.0, 2.0);
        let z = (-position).normalize();
        let xa = z.cross(&Vector3::y()).normalize();
        let y = z.cross(&xa);
        let upright =
            Rotation3::from_matrix_unchecked(Matrix3::from_rows(&[xa.transpose(), y.transpose(), z.transpose()]));
        // Each turn rolls the camera so that its raw left edge points where its top did.
        let roll = Rotation3::from_axis_angle(&Vector3::z_axis(), f64::from(turns) * std::f64::consts::FRAC_PI_2);
        let r = roll.inverse() * upright;
        let k = Matrix3::new(500.0, 0.0, 320.0, 0.0, 500.0, 240.0, 0.0, 0.0, 1.0);
        Camera::new(name, 640, 480, k, Distortion::default(), r, -(r * position)).expect("valid camera")
    }

    #[test]
    fn a_view_turned_as_its_camera_is_mounted_shows_the_world_up() {
        for turns in 0..4 {
            let cam = camera("a", 0.4, turns);
            let up = upright_up(&cam, turns);
            assert!((up - Vector3::y()).norm() < 1e-9, "{turns}: {up:?}");
            // At any other turn the world's up is not the view's.
            assert!(upright_up(&cam, (turns + 1) % 4).dot(&Vector3::y()).abs() < 1e-9);
        }
    }

    #[test]
    fn two_agreeing_views_overrule_an_estimate_a_quarter_turn_off_and_confirm_one_near() {
        let ups = vec![
            ("a".to_owned(), 1, Vector3::new(0.0, 1.0, 0.0)),
            ("b".to_owned(), 3, Vector3::new(1.0, 0.0, 0.0)),
            ("c".to_owned(), 1, Vector3::new(0.17, 0.98, 0.0).normalize()),
        ];
        let agreed = agreeing(&ups).expect("a and c agree");
        assert_eq!(agreed.iter().map(|v| v.0.as_str()).collect::<Vec<_>>(), ["a", "c"]);
        let found = decide(agreed.clone(), Vector3::x(), 7).expect("90 degrees off: overruled");
        assert!(found.direction.dot(&Vector3::y()) > 0.99, "{:?}", found.direction);
        assert_eq!(found.views, [("a".to_owned(), 1), ("c".to_owned(), 1)]);
        assert!(found.summary().contains("in frame 7"), "{}", found.summary());
        let tilted = Vector3::new(0.0, 0.94, 0.34).normalize();
        assert_eq!(decide(agreed, tilted, 7), None, "20 degrees off: the estimate stands");
        assert!(agreeing(&ups[..2]).is_none(), "one view alone says nothing");
    }

    #[test]
    fn later_frame_sets_are_searched_at_whole_seconds_within_the_recording() {
        assert_eq!(probe_indices(300, 30.0), [0, 30, 60]);
        assert_eq!(probe_indices(111, 6.0), [0, 6, 12]);
        assert_eq!(probe_indices(40, 30.0), [0, 30, 39], "clamped to the last set");
        assert_eq!(probe_indices(3, 30.0), [0, 2]);
        assert_eq!(probe_indices(1, 30.0), [0]);
        assert_eq!(probe_indices(10, f64::NAN), [0], "no rate: the first set only");
    }
}
