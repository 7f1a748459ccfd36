//! Linear (DLT) triangulation of one point seen in several calibrated views, with
//! inconsistent views dropped: how a 3D reference is made from 2D detections.
//!
//! Each view's pixel is undistorted to normalised coordinates `(x, y)` first, so the
//! camera is an ideal `[R | t]`; each view then gives the two linear equations
//! `(x r₃ − r₁)·X = t₁ − x t₃` and `(y r₃ − r₂)·X = t₂ − y t₃`, solved in the least-squares
//! sense by SVD (the inhomogeneous form of the DLT: the point is finite by construction).

use handflow_protocol::Camera;
use nalgebra::{DMatrix, DVector, Point2, Point3};

/// A view farther than this from the solution of the other views is dropped (while at least
/// two remain), pixels. The same bound as the `handflow-reference/1` files are made with: a
/// detector that is right is within a few pixels, one that found the other hand or the cat
/// is tens to hundreds off.
pub const OUTLIER_PX: f64 = 25.0;

/// Smallest singular value, relative to the largest, of a solvable system: below it the
/// rays are (nearly) parallel and the depth along them is undetermined.
const MIN_RELATIVE_SINGULAR_VALUE: f64 = 1e-10;

/// A triangulated point.
#[derive(Clone, Debug, PartialEq)]
pub struct Triangulation {
    /// The point, world frame, metres.
    pub point: Point3<f64>,
    /// Indices (into the observations given) of the views used, ascending.
    pub views: Vec<usize>,
    /// Mean distance between each used view's pixel and the point's projection, pixels.
    pub reprojection_px: f64,
}

/// The point seen at `pixel` in each `(camera, pixel)` view, by the linear least-squares
/// solution of every view's equations (no outlier rejection). `None` with fewer than two
/// views, parallel rays, or a solution that is not in front of every camera.
pub fn triangulate_linear(views: &[(&Camera, Point2<f64>)]) -> Option<Point3<f64>> {
    if views.len() < 2 || views.iter().any(|(_, p)| !(p.x.is_finite() && p.y.is_finite())) {
        return None;
    }
    let mut a = DMatrix::<f64>::zeros(2 * views.len(), 3);
    let mut b = DVector::<f64>::zeros(2 * views.len());
    for (v, (camera, pixel)) in views.iter().enumerate() {
        let n = camera.pixel_to_normalised(pixel);
        let r = camera.rotation.matrix();
        let t = &camera.translation;
        for (row, (coordinate, axis)) in [(n.x, 0), (n.y, 1)].into_iter().enumerate() {
            let i = 2 * v + row;
            for j in 0..3 {
                a[(i, j)] = coordinate * r[(2, j)] - r[(axis, j)];
            }
            b[i] = t[axis] - coordinate * t[2];
        }
    }
    let svd = a.svd(true, true);
    let largest = svd.singular_values.max();
    let smallest = svd.singular_values.min();
    if largest.is_nan() || largest <= 0.0 || smallest <= MIN_RELATIVE_SINGULAR_VALUE * largest {
        return None;
    }
    let x = svd.solve(&b, 0.0).ok()?;
    let point = Point3::new(x[0], x[1], x[2]);
    let in_front = views.iter().all(|(camera, _)| camera.world_to_camera(&point).z > 0.0);
    (in_front && point.coords.iter().all(|c| c.is_finite())).then_some(point)
}

/// Pixel distance between `pixel` and the projection of `point` into `camera`; infinite
/// when the point is behind the camera.
pub fn reprojection_error(camera: &Camera, point: &Point3<f64>, pixel: &Point2<f64>) -> f64 {
    camera.project(point).map_or(f64::INFINITY, |q| (q - pixel).norm())
}

/// Triangulates from every view, then drops inconsistent views one at a time while three
/// or more remain: of the subsets that leave one view out, the one whose own views agree
/// best (least largest reprojection error) is kept when the view it leaves out is more than
/// [`OUTLIER_PX`] from its solution. Judging a subset by its own consistency, rather than
/// dropping the view worst explained by all, keeps one bad view from dragging the solution
/// towards itself and a good view out. With three views a bad one is found only when its
/// error crosses the epipolar lines: an error along them (every camera and the point in one
/// plane, the error in that plane) leaves each pair consistent, and no rule can tell which
/// view is wrong. `None` when fewer than two views triangulate.
pub fn triangulate(views: &[(&Camera, Point2<f64>)]) -> Option<Triangulation> {
    let mut used: Vec<usize> = (0..views.len()).collect();
    let subset = |indices: &[usize]| -> Vec<(&Camera, Point2<f64>)> { indices.iter().map(|&i| views[i]).collect() };
    let worst_error = |indices: &[usize], point: &Point3<f64>| {
        indices.iter().map(|&i| reprojection_error(views[i].0, point, &views[i].1)).fold(0.0, f64::max)
    };
    let mut point = triangulate_linear(&subset(&used));
    while used.len() >= 3 {
        let mut best: Option<(f64, usize, Point3<f64>)> = None;
        for k in 0..used.len() {
            let rest: Vec<usize> = used.iter().enumerate().filter(|(j, _)| *j != k).map(|(_, &i)| i).collect();
            let Some(candidate) = triangulate_linear(&subset(&rest)) else { continue };
            let spread = worst_error(&rest, &candidate);
            if best.as_ref().is_none_or(|(s, _, _)| spread < *s) {
                best = Some((spread, k, candidate));
            }
        }
        let Some((_, k, candidate)) = best else { break };
        let left_out = used[k];
        if reprojection_error(views[left_out].0, &candidate, &views[left_out].1) <= OUTLIER_PX {
            break;
        }
        used.remove(k);
        point = Some(candidate);
    }
    let point = point?;
    let reprojection_px =
        used.iter().map(|&i| reprojection_error(views[i].0, &point, &views[i].1)).sum::<f64>() / used.len() as f64;
    Some(Triangulation { point, views: used, reprojection_px })
}

/// Cameras for tests: looking at the origin from `centre`, with focal length `focal` and a
/// 1280x720 image.
#[cfg(test)]
pub(crate) fn camera_looking_at_origin(name: &str, centre: nalgebra::Vector3<f64>, focal: f64) -> Camera {
    use nalgebra::{Matrix3, Rotation3, Vector3};
    let forward = (-centre).normalize();
    // World up is +y here; image y points down.
    let right = Vector3::new(0.0, -1.0, 0.0).cross(&forward).normalize();
    let down = forward.cross(&right);
    let rotation = Rotation3::from_matrix_unchecked(Matrix3::from_rows(&[
        right.transpose(),
        down.transpose(),
        forward.transpose(),
    ]));
    let translation = -(rotation * centre);
    let matrix = Matrix3::new(focal, 0.0, 639.5, 0.0, focal, 359.5, 0.0, 0.0, 1.0);
    let distortion = handflow_protocol::Distortion { k1: -0.05, k2: 0.01, p1: 0.001, p2: -0.0005, k3: 0.0 };
    Camera::new(name, 1280, 720, matrix, distortion, rotation, translation).unwrap()
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;
    use proptest::prelude::*;

    /// A camera 2 to 4 m from the origin, within 70 degrees of +z in azimuth and 30 in
    /// elevation: the front of a rig, where no two views are opposite (rays through the
    /// point would then be nearly parallel).
    fn camera_strategy() -> impl Strategy<Value = (f64, f64, f64, f64)> {
        (-70.0f64..70.0, -30.0f64..30.0, 2.0f64..4.0, 500.0f64..1500.0)
    }

    fn make_camera(i: usize, (azimuth, elevation, distance, focal): (f64, f64, f64, f64)) -> Camera {
        let (az, el) = (azimuth.to_radians(), elevation.to_radians());
        let centre = Vector3::new(az.sin() * el.cos(), el.sin(), az.cos() * el.cos()) * distance;
        camera_looking_at_origin(&format!("cam_{i}"), centre, focal)
    }

    fn separated(params: &[(f64, f64, f64, f64)]) -> bool {
        // At least 8 degrees between any two viewing directions.
        params
            .iter()
            .enumerate()
            .all(|(i, a)| params[..i].iter().all(|b| (a.0 - b.0).abs() >= 8.0 || (a.1 - b.1).abs() >= 8.0))
    }

    proptest! {
        #[test]
        fn projecting_then_triangulating_gives_the_point_back(
            params in prop::collection::vec(camera_strategy(), 2..=5),
            point in (-0.4f64..0.4, -0.4f64..0.4, -0.4f64..0.4),
        ) {
            prop_assume!(separated(&params));
            let cameras: Vec<Camera> = params.iter().enumerate().map(|(i, p)| make_camera(i, *p)).collect();
            let truth = Point3::new(point.0, point.1, point.2);
            let views: Vec<(&Camera, Point2<f64>)> =
                cameras.iter().map(|c| (c, c.project(&truth).unwrap())).collect();
            let t = triangulate(&views).unwrap();
            prop_assert!((t.point - truth).norm() < 1e-6, "{} m off", (t.point - truth).norm());
            prop_assert_eq!(t.views.len(), cameras.len());
            prop_assert!(t.reprojection_px < 1e-6);
        }

        // Four or more views: with three, an error along the epipolar lines cannot be
        // told from the others' (see `triangulate`); a fixed three-view case is below.
        #[test]
        fn one_view_far_off_is_dropped(
            params in prop::collection::vec(camera_strategy(), 4..=6),
            point in (-0.4f64..0.4, -0.4f64..0.4, -0.4f64..0.4),
            bad in 0usize..6,
            shift in 60.0f64..300.0,
            angle in 0.0f64..std::f64::consts::TAU,
        ) {
            prop_assume!(separated(&params));
            let cameras: Vec<Camera> = params.iter().enumerate().map(|(i, p)| make_camera(i, *p)).collect();
            let bad = bad % cameras.len();
            let truth = Point3::new(point.0, point.1, point.2);
            let views: Vec<(&Camera, Point2<f64>)> = cameras
                .iter()
                .enumerate()
                .map(|(i, c)| {
                    let p = c.project(&truth).unwrap();
                    let off = if i == bad { Vector2::new(angle.cos(), angle.sin()) * shift } else { Vector2::zeros() };
                    (c, p + off)
                })
                .collect();
            let t = triangulate(&views).unwrap();
            prop_assert!(!t.views.contains(&bad), "kept the bad view {bad}: {:?}", t.views);
            prop_assert_eq!(t.views.len(), cameras.len() - 1);
            prop_assert!((t.point - truth).norm() < 1e-6);
        }
    }

    use nalgebra::Vector2;

    #[test]
    fn of_three_views_the_one_off_its_epipolar_lines_is_dropped() {
        let cameras = [
            camera_looking_at_origin("a", Vector3::new(-1.5, 0.2, 3.0), 900.0),
            camera_looking_at_origin("b", Vector3::new(0.0, 1.2, 3.2), 900.0),
            camera_looking_at_origin("c", Vector3::new(1.5, 0.2, 3.0), 900.0),
        ];
        let p = Point3::new(0.1, 0.2, 0.05);
        for bad in 0..3 {
            let views: Vec<(&Camera, Point2<f64>)> = cameras
                .iter()
                .enumerate()
                .map(|(i, c)| {
                    let off = if i == bad { Vector2::new(40.0, -50.0) } else { Vector2::zeros() };
                    (c, c.project(&p).unwrap() + off)
                })
                .collect();
            let t = triangulate(&views).unwrap();
            assert!(!t.views.contains(&bad), "bad view {bad} kept: {:?}", t.views);
            assert!((t.point - p).norm() < 1e-6);
        }
    }

    #[test]
    fn two_views_are_kept_whatever_they_say_and_one_is_not_enough() {
        let a = camera_looking_at_origin("a", Vector3::new(-1.0, 0.0, 3.0), 1000.0);
        let b = camera_looking_at_origin("b", Vector3::new(1.0, 0.0, 3.0), 1000.0);
        let p = Point3::new(0.1, 0.2, 0.0);
        let pa = a.project(&p).unwrap();
        let pb = b.project(&p).unwrap() + Vector2::new(0.0, 80.0);
        let t = triangulate(&[(&a, pa), (&b, pb)]).unwrap();
        assert_eq!(t.views, vec![0, 1]);
        assert!(t.reprojection_px > 10.0);
        assert!(triangulate(&[(&a, pa)]).is_none());
        // The same pixel twice from one camera: parallel rays, no depth.
        assert!(triangulate_linear(&[(&a, pa), (&a, pa)]).is_none());
    }
}
