//! The calibration's unit of length. handflow works in metres (depth ranges, palm and face
//! sizes, hand speeds), and caliscope's and Pose2Sim's calibrations are in metres; anipose's,
//! FreeMoCap's and OpenCV's are in the unit the board's squares were measured in, often
//! millimetres. Read as metres, such a rig is a thousand times too wide, and every search
//! runs in the wrong place: nothing is ever tracked.

use super::Camera;

/// Widest rig, camera centre to camera centre, that can still track hands, metres: beyond
/// 30 m an 8.5 cm palm spans a few pixels in any camera. A rig wider than this in the file's
/// unit is read as millimetres (a rig of cameras 3 cm apart would be too narrow for depth
/// at a person's distance, so the two readings never compete).
pub const WIDEST_RIG_M: f64 = 30.0;

/// Metres per millimetre.
const MILLIMETRE: f64 = 1e-3;

/// Converts the cameras' translations to metres when the rig is wider than [`WIDEST_RIG_M`]
/// read in metres; returns a note saying so, naming the widest pair. Rotations and
/// intrinsics carry no length. Running it again changes nothing: a converted rig is narrow.
pub(crate) fn millimetres_to_metres(cameras: &mut [Camera]) -> Option<String> {
    let mut widest: Option<(f64, usize, usize)> = None;
    for i in 0..cameras.len() {
        for j in i + 1..cameras.len() {
            let d = (cameras[i].centre() - cameras[j].centre()).norm();
            if widest.is_none_or(|(w, _, _)| d > w) {
                widest = Some((d, i, j));
            }
        }
    }
    let (width, i, j) = widest.filter(|(w, _, _)| *w > WIDEST_RIG_M)?;
    for camera in cameras.iter_mut() {
        camera.translation *= MILLIMETRE;
    }
    Some(format!(
        "the calibration's cameras `{}` and `{}` are {width:.1} units apart: too wide for a rig in metres (at most \
         {WIDEST_RIG_M} m), so its translations are read as millimetres and converted to metres ({:.3} m apart); \
         trajectories are in metres",
        cameras[i].name,
        cameras[j].name,
        width * MILLIMETRE
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rig::Distortion;
    use nalgebra::{Matrix3, Rotation3, Vector3};

    /// A camera at `x` along the rig, `distance` in front of the world's origin.
    fn camera(name: &str, x: f64, distance: f64) -> Camera {
        let k = Matrix3::new(800.0, 0.0, 320.0, 0.0, 800.0, 240.0, 0.0, 0.0, 1.0);
        Camera::new(name, 640, 480, k, Distortion::default(), Rotation3::identity(), Vector3::new(-x, 0.0, distance))
            .expect("valid camera")
    }

    #[test]
    fn a_rig_in_metres_is_left_as_it_is() {
        let mut cameras = vec![camera("a", 0.0, 2.0), camera("b", 1.5, 2.0), camera("c", -4.0, 2.0)];
        let before = cameras.clone();
        assert_eq!(millimetres_to_metres(&mut cameras), None);
        assert_eq!(cameras, before);
    }

    #[test]
    fn a_rig_in_millimetres_is_converted_to_metres_once() {
        let mut cameras = vec![camera("a", 0.0, 2000.0), camera("b", 600.0, 2000.0), camera("c", -400.0, 2000.0)];
        let note = millimetres_to_metres(&mut cameras).expect("converted");
        assert!(note.contains("`b` and `c` are 1000.0 units apart"), "{note}");
        let metres = [camera("a", 0.0, 2.0), camera("b", 0.6, 2.0), camera("c", -0.4, 2.0)];
        for (got, want) in cameras.iter().zip(&metres) {
            assert!((got.centre() - want.centre()).norm() < 1e-12, "{} at {:?}", got.name, got.centre());
            assert_eq!(got.rotation, want.rotation);
            assert_eq!(got.matrix, want.matrix);
        }
        let converted = cameras.clone();
        assert_eq!(millimetres_to_metres(&mut cameras), None, "a second reading converts nothing");
        assert_eq!(cameras, converted);
    }

    #[test]
    fn a_single_camera_has_no_width_to_judge() {
        let mut cameras = vec![camera("a", 2500.0, 2000.0)];
        assert_eq!(millimetres_to_metres(&mut cameras), None);
    }
}
