//! Multi-view agreement of face detections: a face seen by two calibrated cameras must
//! triangulate to one 3D point with one physical size. Detections that agree are kept, the
//! rest (a fist or a patterned shirt the detector mistook for a face) are dropped, and the
//! agreed face is projected into the cameras whose detector missed it (a face turned 35
//! degrees away is beyond a frontal detector but its cheeks still show the skin colour).
//! When only one view detects the face, the last agreed face supplies its depth: a head
//! moves little between detection rounds, so one view's box on the remembered depth is
//! still a 3D face that can be lent to the others.

use handflow_protocol::Camera;
use nalgebra::{Point2, Point3};

use crate::skin::faces::FaceBox;

/// Largest reprojection error of a box centre, as a share of the box width, for two
/// detections to be the same face.
pub const MAX_CENTRE_ERROR: f64 = 0.3;
/// Largest ratio between the physical widths two detections imply.
pub const MAX_SIZE_RATIO: f64 = 1.5;
/// A face is lent only to cameras within this angle of the direction it faces (estimated as
/// the mean direction to the cameras that detected it): beyond it the lent box's centre
/// falls on the side of the head, on hair or past the silhouette.
pub const MAX_TRANSFER_ANGLE_DEG: f64 = 60.0;
/// Without a second view to agree with, a detection needs at least this score (the
/// detector's own threshold is 2; false detections seen on synthetic and real frames stay
/// below 4).
pub const SINGLE_VIEW_MIN_SCORE: f64 = 5.0;
/// A single view's detection placed at the remembered face's depth is the same face only
/// if it lies within this distance of it, metres (a head moves far less between detection
/// rounds, a fist or a second face is usually farther).
pub const MAX_ANCHOR_SHIFT_M: f64 = 0.25;

/// A face placed in 3D by agreeing views: where later single-view detections find their
/// depth.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct KnownFace {
    /// Centre, world metres.
    pub centre: [f64; 3],
    /// Physical width of the detector's box, metres.
    pub width_m: f64,
}

/// The faces to adapt each camera's skin model with, and where they came from.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct FusedFaces {
    /// Per camera (rig order): the face box to use, if any.
    pub boxes: Vec<Option<FaceBox>>,
    /// Per camera: whether the box was projected from other views (not detected there).
    pub transferred: Vec<bool>,
    /// Detections dropped because no other view agreed with them.
    pub rejected: usize,
    /// The face in 3D, when two or more views agreed (or one view agreed with a remembered
    /// face): to remember for the next round.
    pub known: Option<KnownFace>,
}

impl FusedFaces {
    /// Face centre in the world, world metres, when the face was placed in 3D.
    pub fn centre(&self) -> Option<[f64; 3]> {
        self.known.map(|k| k.centre)
    }
}

/// Fuses per-camera detections (`detections[c]` for `cameras[c]`, all of one frame set).
pub fn fuse_faces(cameras: &[Camera], detections: &[Vec<FaceBox>]) -> FusedFaces {
    fuse_faces_remembering(cameras, detections, None)
}

/// [`fuse_faces`], with the face the last rounds placed in 3D: when no two views agree, a
/// detection at that face's depth and near it is the face, and is lent to the other views.
pub fn fuse_faces_remembering(
    cameras: &[Camera],
    detections: &[Vec<FaceBox>],
    known: Option<&KnownFace>,
) -> FusedFaces {
    let total: usize = detections.iter().map(Vec::len).sum();
    let mut out = FusedFaces {
        boxes: vec![None; cameras.len()],
        transferred: vec![false; cameras.len()],
        rejected: 0,
        known: None,
    };
    if cameras.len() != detections.len() {
        out.rejected = total;
        return out;
    }
    let agreed = best_agreement(cameras, detections)
        .or_else(|| known.and_then(|k| anchored_on_known_face(cameras, detections, k)));
    if let Some(best) = agreed {
        let towards = |cam: &Camera| (cam.centre() - best.centre).normalize();
        let facing = best
            .support
            .iter()
            .zip(cameras)
            .filter(|(pick, _)| pick.is_some())
            .fold(nalgebra::Vector3::zeros(), |acc, (_, cam)| acc + towards(cam))
            .normalize();
        let max_cos = MAX_TRANSFER_ANGLE_DEG.to_radians().cos();
        for (c, pick) in best.support.iter().enumerate() {
            if let Some(k) = pick {
                out.boxes[c] = Some(detections[c][*k]);
            } else if towards(&cameras[c]).dot(&facing) < max_cos {
                continue;
            } else if let Some(b) = project_face(&cameras[c], &best.centre, best.width_m) {
                out.boxes[c] = Some(b);
                out.transferred[c] = true;
            }
        }
        let used = best.support.iter().filter(|s| s.is_some()).count();
        out.rejected = total - used;
        out.known = Some(KnownFace { centre: [best.centre.x, best.centre.y, best.centre.z], width_m: best.width_m });
        return out;
    }
    // No two views agree: a lone camera, or only one camera sees the face frontally. Keep
    // each camera's most confident detection if it is confident enough on its own.
    let mut used = 0;
    for (c, dets) in detections.iter().enumerate() {
        let best = dets.iter().copied().max_by(|a, b| a.score.total_cmp(&b.score));
        if let Some(b) = best.filter(|b| cameras.len() == 1 || b.score >= SINGLE_VIEW_MIN_SCORE) {
            out.boxes[c] = Some(b);
            used += 1;
        }
    }
    out.rejected = total - used;
    out
}

struct Agreement {
    centre: Point3<f64>,
    width_m: f64,
    /// Per camera: the index of its supporting detection.
    support: Vec<Option<usize>>,
    score: f64,
}

/// The 3D face most cameras agree on (ties: the higher summed score).
fn best_agreement(cameras: &[Camera], detections: &[Vec<FaceBox>]) -> Option<Agreement> {
    let mut best: Option<Agreement> = None;
    for a in 0..cameras.len() {
        for b in a + 1..cameras.len() {
            for da in &detections[a] {
                for db in &detections[b] {
                    let Some(centre) = triangulate(&cameras[a], da, &cameras[b], db) else { continue };
                    let (Some(wa), Some(wb)) =
                        (implied_width(&cameras[a], da, &centre), implied_width(&cameras[b], db, &centre))
                    else {
                        continue;
                    };
                    if wa.max(wb) / wa.min(wb) > MAX_SIZE_RATIO {
                        continue;
                    }
                    let width_m = 0.5 * (wa + wb);
                    // Every camera's detection that agrees with this point joins it.
                    let mut support = vec![None; cameras.len()];
                    let mut score = 0.0;
                    for (c, dets) in detections.iter().enumerate() {
                        let pick = dets
                            .iter()
                            .enumerate()
                            .filter(|(_, d)| agrees(&cameras[c], d, &centre, width_m))
                            .max_by(|x, y| x.1.score.total_cmp(&y.1.score));
                        if let Some((k, d)) = pick {
                            support[c] = Some(k);
                            score += d.score;
                        }
                    }
                    let count = support.iter().filter(|s| s.is_some()).count();
                    if count < 2 {
                        continue;
                    }
                    let better = best.as_ref().is_none_or(|o| {
                        let o_count = o.support.iter().filter(|s| s.is_some()).count();
                        (count, score) > (o_count, o.score)
                    });
                    if better {
                        best = Some(Agreement { centre, width_m, support, score });
                    }
                }
            }
        }
    }
    best
}

/// The best single-view detection that, placed on its ray at the known face's depth in
/// that camera, has the known face's size and lies near it.
fn anchored_on_known_face(cameras: &[Camera], detections: &[Vec<FaceBox>], known: &KnownFace) -> Option<Agreement> {
    let remembered = Point3::from(known.centre);
    let mut best: Option<Agreement> = None;
    for (c, (cam, dets)) in cameras.iter().zip(detections).enumerate() {
        let depth = cam.world_to_camera(&remembered).z;
        if depth <= 0.0 {
            continue;
        }
        for (k, d) in dets.iter().enumerate() {
            let ray = cam.back_project(&box_centre(d));
            // The point of the box centre's ray at the remembered depth in this camera.
            let along = cam.world_to_camera(&ray.at(1.0)).z - cam.world_to_camera(&ray.origin).z;
            if along <= 1e-9 {
                continue;
            }
            let centre = ray.at(depth / along);
            if (centre - remembered).norm() > MAX_ANCHOR_SHIFT_M {
                continue;
            }
            let Some(width_m) = implied_width(cam, d, &centre) else { continue };
            if width_m.max(known.width_m) / width_m.min(known.width_m) > MAX_SIZE_RATIO {
                continue;
            }
            if best.as_ref().is_none_or(|b| d.score > b.score) {
                let mut support = vec![None; cameras.len()];
                support[c] = Some(k);
                best = Some(Agreement { centre, width_m, support, score: d.score });
            }
        }
    }
    best
}

fn box_centre(b: &FaceBox) -> Point2<f64> {
    Point2::new(f64::from(b.x + 0.5 * b.width), f64::from(b.y + 0.5 * b.height))
}

/// Midpoint of the closest approach of the two box centres' rays, if both views agree on it.
fn triangulate(ca: &Camera, a: &FaceBox, cb: &Camera, b: &FaceBox) -> Option<Point3<f64>> {
    let (ra, rb) = (ca.back_project(&box_centre(a)), cb.back_project(&box_centre(b)));
    let (da, db) = (ra.direction.into_inner(), rb.direction.into_inner());
    let w0 = ra.origin - rb.origin;
    let (aa, ab, bb) = (da.dot(&da), da.dot(&db), db.dot(&db));
    let (d, e) = (da.dot(&w0), db.dot(&w0));
    let denom = aa * bb - ab * ab;
    if denom.abs() < 1e-12 {
        return None; // parallel rays
    }
    let s = (ab * e - bb * d) / denom;
    let t = (aa * e - ab * d) / denom;
    if s <= 0.0 || t <= 0.0 {
        return None;
    }
    let p = Point3::from((ra.at(s).coords + rb.at(t).coords) * 0.5);
    let ok = centre_error(ca, a, &p).is_some_and(|e| e <= MAX_CENTRE_ERROR)
        && centre_error(cb, b, &p).is_some_and(|e| e <= MAX_CENTRE_ERROR);
    ok.then_some(p)
}

/// Distance from the box centre to the point's projection, in box widths.
fn centre_error(cam: &Camera, b: &FaceBox, p: &Point3<f64>) -> Option<f64> {
    let q = cam.project(p)?;
    Some((q - box_centre(b)).norm() / f64::from(b.width).max(1.0))
}

/// The physical width a box implies at the point's depth.
fn implied_width(cam: &Camera, b: &FaceBox, p: &Point3<f64>) -> Option<f64> {
    let depth = cam.world_to_camera(p).z;
    (depth > 0.0).then(|| f64::from(b.width) * depth / cam.matrix[(0, 0)])
}

fn agrees(cam: &Camera, b: &FaceBox, centre: &Point3<f64>, width_m: f64) -> bool {
    let size_ok = implied_width(cam, b, centre).is_some_and(|w| w.max(width_m) / w.min(width_m) <= MAX_SIZE_RATIO);
    size_ok && centre_error(cam, b, centre).is_some_and(|e| e <= MAX_CENTRE_ERROR)
}

/// Width in `cam`'s pixels of a face `width_m` wide at `centre` (`None` behind the camera).
pub fn face_width_px(cam: &Camera, centre: &Point3<f64>, width_m: f64) -> Option<f64> {
    let depth = cam.world_to_camera(centre).z;
    (depth > 0.0).then(|| width_m * cam.matrix[(0, 0)] / depth)
}

/// The box a face of `width_m` at `centre` covers in `cam`, if wholly inside the image.
fn project_face(cam: &Camera, centre: &Point3<f64>, width_m: f64) -> Option<FaceBox> {
    let q = cam.project(centre)?;
    let side = face_width_px(cam, centre, width_m)?;
    let (x, y) = (q.x - 0.5 * side, q.y - 0.5 * side);
    let inside = x >= 0.0 && y >= 0.0 && x + side <= f64::from(cam.width) && y + side <= f64::from(cam.height);
    inside.then_some(FaceBox { x: x as f32, y: y as f32, width: side as f32, height: side as f32, score: 0.0 })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Matrix3, Rotation3, Vector3};

    /// A camera at `angle_deg` on a 2 m arc around the origin, looking at it.
    fn arc_camera(name: &str, angle_deg: f64) -> Camera {
        let a = angle_deg.to_radians();
        let centre = Vector3::new(2.0 * a.sin(), 0.0, 2.0 * a.cos());
        let forward = -centre.normalize();
        let down = Vector3::new(0.0, -1.0, 0.0);
        let right = down.cross(&forward).normalize();
        let down = forward.cross(&right);
        let r = Rotation3::from_matrix_unchecked(Matrix3::from_rows(&[
            right.transpose(),
            down.transpose(),
            forward.transpose(),
        ]));
        let t = -(r * centre);
        let k = Matrix3::new(600.0, 0.0, 320.0, 0.0, 600.0, 240.0, 0.0, 0.0, 1.0);
        Camera::new(name, 640, 480, k, Default::default(), r, t).unwrap()
    }

    fn face_in(cam: &Camera, centre: &Point3<f64>, width_m: f64, score: f64) -> FaceBox {
        FaceBox { score, ..project_face(cam, centre, width_m).unwrap() }
    }

    #[test]
    fn agreeing_views_keep_their_boxes_and_lend_one_to_the_camera_that_missed() {
        let cams = [arc_camera("a", -30.0), arc_camera("b", 0.0), arc_camera("c", 40.0)];
        let face = Point3::new(0.05, 0.3, 0.1);
        let dets = vec![vec![face_in(&cams[0], &face, 0.15, 3.0)], vec![face_in(&cams[1], &face, 0.15, 9.0)], vec![]];
        let fused = fuse_faces(&cams, &dets);
        assert_eq!(fused.rejected, 0);
        assert_eq!(fused.transferred, vec![false, false, true]);
        let c = fused.centre().unwrap();
        assert!((Point3::from(c) - face).norm() < 0.01, "{c:?}");
        let lent = fused.boxes[2].unwrap();
        let expected = project_face(&cams[2], &face, 0.15).unwrap();
        assert!((lent.x - expected.x).abs() < 2.0 && (lent.width - expected.width).abs() < 2.0);
    }

    #[test]
    fn a_face_is_not_lent_to_a_camera_that_sees_it_in_profile() {
        let cams = [arc_camera("a", -30.0), arc_camera("b", 0.0), arc_camera("c", 80.0)];
        let face = Point3::new(0.0, 0.3, 0.1);
        let dets = vec![vec![face_in(&cams[0], &face, 0.15, 3.0)], vec![face_in(&cams[1], &face, 0.15, 9.0)], vec![]];
        let fused = fuse_faces(&cams, &dets);
        assert!(fused.centre().is_some());
        assert_eq!(fused.boxes[2], None);
        assert!(!fused.transferred[2]);
    }

    #[test]
    fn a_detection_no_other_view_confirms_is_dropped() {
        let cams = [arc_camera("a", -30.0), arc_camera("b", 0.0), arc_camera("c", 40.0)];
        let face = Point3::new(0.0, 0.3, 0.0);
        let fist = Point3::new(0.3, -0.2, 0.2);
        let dets = vec![
            vec![face_in(&cams[0], &face, 0.15, 3.0)],
            vec![face_in(&cams[1], &face, 0.15, 9.0)],
            vec![face_in(&cams[2], &fist, 0.09, 2.5)],
        ];
        let fused = fuse_faces(&cams, &dets);
        assert_eq!(fused.rejected, 1);
        assert!(fused.transferred[2], "the real face is lent to camera c instead");
    }

    #[test]
    fn lone_detections_need_a_confident_score() {
        let cams = [arc_camera("a", -30.0), arc_camera("b", 30.0)];
        let face = Point3::new(0.0, 0.3, 0.0);
        let weak = vec![vec![face_in(&cams[0], &face, 0.15, 3.0)], vec![]];
        assert_eq!(fuse_faces(&cams, &weak).boxes, vec![None, None]);
        let strong = vec![vec![face_in(&cams[0], &face, 0.15, 8.0)], vec![]];
        let fused = fuse_faces(&cams, &strong);
        assert!(fused.boxes[0].is_some() && fused.boxes[1].is_none());
        // One camera: nothing to agree with, the detector's own threshold decides.
        let one = [arc_camera("a", 0.0)];
        assert!(fuse_faces(&one, &[vec![face_in(&one[0], &face, 0.15, 2.1)]]).boxes[0].is_some());
    }

    #[test]
    fn sizes_that_disagree_are_not_the_same_face() {
        let cams = [arc_camera("a", -30.0), arc_camera("b", 30.0)];
        let face = Point3::new(0.0, 0.3, 0.0);
        let dets = vec![vec![face_in(&cams[0], &face, 0.15, 3.0)], vec![face_in(&cams[1], &face, 0.40, 3.0)]];
        let fused = fuse_faces(&cams, &dets);
        assert!(fused.centre().is_none());
        assert_eq!(fused.rejected, 2);
    }

    #[test]
    fn a_lone_detection_near_the_remembered_face_is_lent_to_the_other_views() {
        let cams = [arc_camera("a", -40.0), arc_camera("b", 5.0), arc_camera("c", 45.0)];
        let before = Point3::new(0.0, 0.3, 0.1);
        let known = KnownFace { centre: [before.x, before.y, before.z], width_m: 0.15 };
        // The head moved 5 cm sideways; only the front camera finds it, with a weak score.
        let now = Point3::new(0.05, 0.3, 0.1);
        let dets = vec![vec![], vec![face_in(&cams[1], &now, 0.15, 3.0)], vec![]];
        assert_eq!(fuse_faces(&cams, &dets).boxes, vec![None, None, None], "weak and alone: dropped");
        let fused = fuse_faces_remembering(&cams, &dets, Some(&known));
        assert_eq!(fused.transferred, vec![true, false, true]);
        let c = Point3::from(fused.centre().unwrap());
        assert!((c - now).norm() < 0.01, "{c:?}");
        let lent = fused.boxes[2].unwrap();
        let expected = project_face(&cams[2], &now, 0.15).unwrap();
        assert!((lent.x - expected.x).abs() < 2.0 && (lent.width - expected.width).abs() < 2.0);
        assert!(fused.known.is_some_and(|k| (k.width_m - 0.15).abs() < 0.005), "{:?}", fused.known);
    }

    #[test]
    fn a_lone_detection_far_from_the_remembered_face_is_not_anchored() {
        let cams = [arc_camera("a", -40.0), arc_camera("b", 5.0), arc_camera("c", 45.0)];
        let known = KnownFace { centre: [0.0, 0.3, 0.1], width_m: 0.15 };
        // A fist-sized box low in the image: at the face's depth it is 40 cm away and too small.
        let fist = Point3::new(0.3, -0.2, 0.1);
        let dets = vec![vec![], vec![face_in(&cams[1], &fist, 0.09, 3.0)], vec![]];
        let fused = fuse_faces_remembering(&cams, &dets, Some(&known));
        assert_eq!(fused.boxes, vec![None, None, None]);
        assert_eq!(fused.known, None);
        assert_eq!(fused.rejected, 1);
    }
}
