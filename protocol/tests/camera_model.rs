//! The camera model: projection, distortion, back-projection, validation.

use std::f64::consts::FRAC_PI_2;

use handflow_protocol::{Camera, Distortion, Fisheye, RigError};
use nalgebra::{Matrix3, Point2, Point3, Rotation3, Vector2, Vector3};
use proptest::prelude::*;

/// A camera with the given pose and a 1920x1080 image.
fn camera(matrix: Matrix3<f64>, distortion: Distortion, rotation: Rotation3<f64>, translation: Vector3<f64>) -> Camera {
    Camera::new("test", 1920, 1080, matrix, distortion, rotation, translation).expect("valid camera")
}

fn distortion(k1: f64, k2: f64, p1: f64, p2: f64, k3: f64) -> Distortion {
    Distortion { k1, k2, p1, p2, k3 }
}

#[test]
fn hand_computed_projection_follows_opencv() {
    // K with a small skew, a quarter turn about z, and all five coefficients.
    let k = Matrix3::new(800.0, 2.0, 320.0, 0.0, 820.0, 240.0, 0.0, 0.0, 1.0);
    let d = distortion(-0.2, 0.05, 0.001, -0.002, 0.01);
    let rotation = Rotation3::new(Vector3::new(0.0, 0.0, FRAC_PI_2));
    let cam = camera(k, d, rotation, Vector3::new(0.1, -0.2, 2.0));

    // By hand: R = [[0, -1, 0], [1, 0, 0], [0, 0, 1]], so for p = (0.3, 0.2, 1.0)
    // R p = (-0.2, 0.3, 1.0) and R p + t = (-0.1, 0.1, 3.0).
    let p = Point3::new(0.3, 0.2, 1.0);
    let p_cam = cam.world_to_camera(&p);
    assert!((p_cam - Point3::new(-0.1, 0.1, 3.0)).norm() < 1e-15);

    // Normalised: x = -1/30, y = 1/30, r² = 2/900 = 1/450.
    // radial = 1 − 0.2/450 + 0.05/450² + 0.01/450³ = 0.99955580257887...
    // x' = x·radial + 2·p1·x·y + p2·(r² + 2x²)
    //    = −0.0333185267526... − 0.0000022222... − 0.0000088888... = −0.0333296378637...
    // y' = y·radial + p1·(r² + 2y²) + 2·p2·x·y
    //    = 0.0333185267526... + 0.0000044444... + 0.0000044444... = 0.0333274156415...
    // u = 800·x' + 2·y' + 320 = 293.402944540...,  v = 820·y' + 240 = 267.328480826...
    let distorted = cam.distort(Vector2::new(-1.0 / 30.0, 1.0 / 30.0));
    assert!((distorted - Vector2::new(-0.03332963786374028, 0.03332741564151806)).norm() < 1e-15);
    let pixel = cam.project(&p).expect("in front of the camera");
    assert!((pixel - Point2::new(293.40294454029083, 267.3284808260448)).norm() < 1e-9, "{pixel}");

    // And back: the pixel's ray passes through p at distance |p − centre|.
    assert!((cam.pixel_to_normalised(&pixel) - Vector2::new(-1.0 / 30.0, 1.0 / 30.0)).norm() < 1e-14);
    let ray = cam.back_project(&pixel);
    let distance = (p - cam.centre()).norm();
    assert!((ray.at(distance) - p).norm() < 1e-12);
}

#[test]
fn the_fisheye_model_follows_opencv() {
    // cv::fisheye::projectPoints: a = x/z, b = y/z, r² = a² + b², θ = atan(r),
    // θd = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸), (x', y') = (θd / r) (a, b).
    let lens = Fisheye { k1: 0.05, k2: -0.02, k3: 0.004, k4: -0.001 };
    let (a, b) = (0.6, -0.8); // r = 1, θ = π/4
    let theta = std::f64::consts::FRAC_PI_4;
    let t2 = theta * theta;
    let theta_d = theta * (1.0 + t2 * (0.05 + t2 * (-0.02 + t2 * (0.004 - t2 * 0.001))));
    let distorted = lens.distort(Vector2::new(a, b));
    assert!((distorted - Vector2::new(a, b) * theta_d).norm() < 1e-15, "{distorted}");
    assert!((lens.undistort(distorted) - Vector2::new(a, b)).norm() < 1e-12);
    // A pinhole's zero point stays put; the equidistant lens (all k zero) images θ at r = θ.
    assert_eq!(lens.distort(Vector2::zeros()), Vector2::zeros());
    let equidistant = Fisheye::default();
    assert!((equidistant.distort(Vector2::new(1.0, 0.0)).x - theta).abs() < 1e-15);
    // A camera with the model projects through it and validates its coefficients.
    let k = Matrix3::new(500.0, 0.0, 640.0, 0.0, 500.0, 360.0, 0.0, 0.0, 1.0);
    let cam = Camera::new("bad", 1280, 720, k, Distortion::default(), Rotation3::identity(), Vector3::zeros())
        .and_then(|c| c.with_fisheye(lens))
        .expect("a fisheye camera");
    let pixel = cam.project(&Point3::new(0.6, -0.8, 1.0)).expect("in front");
    assert!((pixel - Point2::new(640.0 + 500.0 * 0.6 * theta_d, 360.0 - 500.0 * 0.8 * theta_d)).norm() < 1e-9);
    let bad = Fisheye { k4: f64::NAN, ..lens };
    let (field, problem) = field_of(cam.clone().with_fisheye(bad));
    assert_eq!(field, "distortions");
    assert!(problem.contains("k4"), "{problem}");
    let pinhole_distorted =
        Camera::new("bad", 1280, 720, k, distortion(-0.1, 0.0, 0.0, 0.0, 0.0), Rotation3::identity(), Vector3::zeros())
            .expect("valid");
    let (field, _) = field_of(pinhole_distorted.with_fisheye(lens));
    assert_eq!(field, "distortions");
}

#[test]
fn centre_maps_to_camera_origin() {
    let cam = camera(
        Matrix3::new(1000.0, 0.0, 960.0, 0.0, 1000.0, 540.0, 0.0, 0.0, 1.0),
        Distortion::default(),
        Rotation3::new(Vector3::new(0.3, -1.0, 2.0)),
        Vector3::new(0.4, 1.5, -3.0),
    );
    assert!(cam.world_to_camera(&cam.centre()).coords.norm() < 1e-14);
    assert_eq!(cam.back_project(&Point2::new(960.0, 540.0)).origin, cam.centre());
}

#[test]
fn project_refuses_points_not_in_front() {
    let cam = camera(
        Matrix3::new(1000.0, 0.0, 960.0, 0.0, 1000.0, 540.0, 0.0, 0.0, 1.0),
        Distortion::default(),
        Rotation3::identity(),
        Vector3::zeros(),
    );
    assert_eq!(cam.project(&Point3::new(0.0, 0.0, -1.0)), None);
    assert_eq!(cam.project(&Point3::new(1.0, 1.0, 0.0)), None);
    assert_eq!(cam.project(&Point3::new(0.0, 0.0, f64::NAN)), None);
    assert_eq!(cam.project(&Point3::new(0.0, 0.0, 1.0)), Some(Point2::new(960.0, 540.0)));
}

#[test]
fn undistort_is_identity_without_distortion_and_bounded_without_preimage() {
    let zero = Distortion::default();
    assert!(zero.is_zero());
    assert_eq!(zero.undistort(Vector2::new(0.3, -0.2)), Vector2::new(0.3, -0.2));

    // Strong barrel distortion folds back: r_d = r (1 − r²) never exceeds
    // 0.385, so 1.0 has no preimage. It must still return, finite.
    let folding = distortion(-1.0, 0.0, 0.0, 0.0, 0.0);
    assert!(!folding.is_zero());
    let x = folding.undistort(Vector2::new(1.0, 0.0));
    assert!(x.iter().all(|c| c.is_finite()), "{x}");
    assert!(folding.undistort(Vector2::new(f64::NAN, 0.0)).x.is_nan());
}

#[test]
fn distortion_as_array_is_opencv_order() {
    assert_eq!(distortion(1.0, 2.0, 3.0, 4.0, 5.0).as_array(), [1.0, 2.0, 3.0, 4.0, 5.0]);
}

/// The `field` of a [`RigError::Field`], or a panic.
fn field_of(result: Result<Camera, RigError>) -> (String, String) {
    match result {
        Err(RigError::Field { camera, field, problem, .. }) => {
            assert_eq!(camera, "bad");
            (field, problem)
        }
        other => panic!("expected a field error, got {other:?}"),
    }
}

#[test]
fn new_validates_every_field() {
    let k = Matrix3::new(1000.0, 0.0, 960.0, 0.0, 1000.0, 540.0, 0.0, 0.0, 1.0);
    let d = Distortion::default();
    let r = Rotation3::identity();
    let t = Vector3::zeros();
    let new = |w, h, k, d, r, t| Camera::new("bad", w, h, k, d, r, t);
    assert!(new(1920, 1080, k, d, r, t).is_ok());

    assert_eq!(field_of(new(0, 1080, k, d, r, t)).0, "size");
    assert_eq!(field_of(new(1920, 0, k, d, r, t)).0, "size");

    let mut nan_k = k;
    nan_k[(0, 2)] = f64::NAN;
    assert_eq!(field_of(new(1920, 1080, nan_k, d, r, t)).0, "matrix");
    let mut last_row = k;
    last_row[(2, 0)] = 0.1;
    let (field, problem) = field_of(new(1920, 1080, last_row, d, r, t));
    assert_eq!(field, "matrix");
    assert!(problem.contains("last row"), "{problem}");
    let mut negative_fy = k;
    negative_fy[(1, 1)] = -1000.0;
    let (field, problem) = field_of(new(1920, 1080, negative_fy, d, r, t));
    assert_eq!(field, "matrix");
    assert!(problem.contains("singular"), "{problem}");
    // fx, fy > 0 but fx·fy = skew·K[1][0]: singular all the same.
    let singular = Matrix3::new(1.0, 2.0, 0.0, 0.5, 1.0, 0.0, 0.0, 0.0, 1.0);
    let (field, problem) = field_of(new(1920, 1080, singular, d, r, t));
    assert_eq!(field, "matrix");
    assert!(problem.contains("singular"), "{problem}");

    let bad_d = Distortion { p2: f64::INFINITY, ..d };
    let (field, problem) = field_of(new(1920, 1080, k, bad_d, r, t));
    assert_eq!(field, "distortions");
    assert!(problem.contains("p2"), "{problem}");

    let sheared = Rotation3::from_matrix_unchecked(Matrix3::new(1.0, 0.1, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0));
    let (field, problem) = field_of(new(1920, 1080, k, d, sheared, t));
    assert_eq!(field, "rotation");
    assert!(problem.contains("not orthonormal"), "{problem}");
    let reflection = Rotation3::from_matrix_unchecked(Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, -1.0)));
    let (field, problem) = field_of(new(1920, 1080, k, d, reflection, t));
    assert_eq!(field, "rotation");
    assert!(problem.contains("determinant"), "{problem}");

    let (field, problem) = field_of(new(1920, 1080, k, d, r, Vector3::new(0.0, f64::NEG_INFINITY, 0.0)));
    assert_eq!(field, "translation");
    assert!(problem.contains("y is not finite"), "{problem}");
}

#[test]
fn field_error_display_names_camera_and_field() {
    let error =
        Camera::new("left", 0, 1, Matrix3::identity(), Distortion::default(), Rotation3::identity(), Vector3::zeros())
            .expect_err("zero width");
    assert_eq!(error.to_string(), "camera `left`, field `size`: width and height must be positive, found [0, 1]");
}

/// Lens distortion of realistic magnitude for machine-vision lenses.
fn realistic_distortion() -> impl Strategy<Value = Distortion> {
    (-0.3..0.3, -0.1..0.1, -0.005..0.005, -0.005..0.005, -0.02..0.02).prop_map(|(k1, k2, p1, p2, k3)| Distortion {
        k1,
        k2,
        p1,
        p2,
        k3,
    })
}

/// OpenCV fisheye coefficients of wide webcam and action-camera lenses.
fn realistic_fisheye() -> impl Strategy<Value = Fisheye> {
    (-0.1..0.1, -0.05..0.05, -0.01..0.01, -0.005..0.005).prop_map(|(k1, k2, k3, k4)| Fisheye { k1, k2, k3, k4 })
}

fn rotation() -> impl Strategy<Value = Rotation3<f64>> {
    (-3.2..3.2, -3.2..3.2, -3.2..3.2).prop_map(|(x, y, z)| Rotation3::new(Vector3::new(x, y, z)))
}

fn translation() -> impl Strategy<Value = Vector3<f64>> {
    (-5.0..5.0, -5.0..5.0, -5.0..5.0).prop_map(|(x, y, z)| Vector3::new(x, y, z))
}

/// Realistic cameras: focal length 1.1-2.5 image diagonals (so pixels inside
/// the image stay within the lens's invertible field for the distortions
/// above), principal point near the centre, tiny skew.
fn realistic_camera() -> impl Strategy<Value = Camera> {
    (
        (320u32..4096, 240u32..3072, 1.1..2.5, 0.95..1.05, -0.05..0.05, -0.05..0.05, -1.0..1.0),
        realistic_distortion(),
        rotation(),
        translation(),
    )
        .prop_map(|((w, h, f, aspect, dx, dy, skew), distortion, rotation, translation)| {
            let fx = f * f64::from(w).hypot(f64::from(h));
            let (cx, cy) = (f64::from(w) * (0.5 + dx), f64::from(h) * (0.5 + dy));
            let k = Matrix3::new(fx, skew, cx, 0.0, fx * aspect, cy, 0.0, 0.0, 1.0);
            Camera::new("cam", w, h, k, distortion, rotation, translation).expect("valid camera")
        })
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(2000))]

    #[test]
    fn back_projected_points_project_to_their_pixel(
        cam in realistic_camera(),
        (fu, fv) in (0.0..1.0, 0.0..1.0),
        depth in 0.1..100.0,
    ) {
        let pixel = Point2::new(fu * f64::from(cam.width), fv * f64::from(cam.height));
        let point = cam.back_project(&pixel).at(depth);
        let projected = cam.project(&point).expect("in front of the camera");
        prop_assert!((projected - pixel).norm() < 1e-6, "{pixel} -> {projected}");
    }

    #[test]
    fn projected_points_lie_on_their_pixel_ray(cam in realistic_camera(), (x, y, z) in (-0.25..0.25, -0.25..0.25, 0.2..50.0)) {
        let point = cam.camera_to_world(&Point3::new(x * z, y * z, z));
        let pixel = cam.project(&point).expect("in front of the camera");
        let ray = cam.back_project(&pixel);
        let along = (point - ray.origin).dot(&ray.direction);
        prop_assert!((ray.at(along) - point).norm() < 1e-9 * (1.0 + along), "{} off the ray", (ray.at(along) - point).norm());
    }

    #[test]
    fn undistort_inverts_distort(d in realistic_distortion(), (x, y) in (-0.45..0.45, -0.45..0.45)) {
        let normalised = Vector2::new(x, y);
        let back = d.undistort(d.distort(normalised));
        prop_assert!((back - normalised).norm() < 1e-12, "{normalised} -> {back}");
    }

    #[test]
    fn fisheye_undistort_inverts_distort(lens in realistic_fisheye(), (x, y) in (-1.2..1.2, -1.2..1.2)) {
        // Up to 60 degrees from the optical axis, where these lenses' images still grow with
        // the angle.
        let normalised = Vector2::new(x, y);
        let back = lens.undistort(lens.distort(normalised));
        prop_assert!((back - normalised).norm() < 1e-10 * (1.0 + normalised.norm_squared()), "{normalised} -> {back}");
    }

    #[test]
    fn fisheye_cameras_back_project_to_their_pixel(
        cam in realistic_camera(),
        lens in realistic_fisheye(),
        (fu, fv) in (0.0..1.0, 0.0..1.0),
        depth in 0.1..100.0,
    ) {
        let cam = Camera { distortion: Distortion::default(), ..cam }.with_fisheye(lens).expect("valid");
        let pixel = Point2::new(fu * f64::from(cam.width), fv * f64::from(cam.height));
        let point = cam.back_project(&pixel).at(depth);
        let projected = cam.project(&point).expect("in front of the camera");
        prop_assert!((projected - pixel).norm() < 1e-6, "{pixel} -> {projected}");
    }

    #[test]
    fn world_and_camera_frames_round_trip(
        rotation in rotation(),
        translation in translation(),
        (x, y, z) in (-100.0..100.0, -100.0..100.0, -100.0..100.0),
    ) {
        let k = Matrix3::new(1000.0, 0.0, 960.0, 0.0, 1000.0, 540.0, 0.0, 0.0, 1.0);
        let cam = Camera::new("cam", 1920, 1080, k, Distortion::default(), rotation, translation).expect("valid");
        let p = Point3::new(x, y, z);
        prop_assert!((cam.camera_to_world(&cam.world_to_camera(&p)) - p).norm() < 1e-12 * (1.0 + p.coords.norm()));
        prop_assert!((cam.world_to_camera(&cam.camera_to_world(&p)) - p).norm() < 1e-12 * (1.0 + p.coords.norm()));
        // Distances are preserved: the transform is rigid.
        let c = cam.centre();
        prop_assert!(((cam.world_to_camera(&p).coords.norm()) - (p - c).norm()).abs() < 1e-12 * (1.0 + p.coords.norm()));
    }
}
