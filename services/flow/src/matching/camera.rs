//! Fast single-precision projection for the hot loop, one per camera and pyramid level.

use handflow_protocol::Camera;

/// A camera's projection onto one pyramid level, in `f32`.
///
/// Level `l` pixel coordinates relate to full-resolution ones by `u_l = (u + 0.5) / 2^l - 0.5`
/// (the centre convention of [`crate::matching::image::ColourImage::downsample_into`]),
/// folded into the intrinsics so projecting costs the same at every level.
#[derive(Clone, Debug)]
pub struct LevelProjection {
    rotation: [[f32; 3]; 3],
    translation: [f32; 3],
    fx: f32,
    fy: f32,
    skew: f32,
    cx: f32,
    cy: f32,
    lens: Lens,
    /// `K [R | t]` on this level, used for an ideal pinhole: one 3x4 product and one division
    /// per projection.
    matrix: [[f32; 4]; 3],
}

/// A camera's lens model in `f32`.
#[derive(Clone, Copy, Debug)]
enum Lens {
    /// No distortion.
    Pinhole,
    /// OpenCV's `k1 k2 p1 p2 k3`.
    Distorted([f32; 5]),
    /// OpenCV's fisheye `k1 k2 k3 k4` ([`handflow_protocol::Fisheye`]).
    Fisheye([f32; 4]),
}

/// The fisheye model's radial scale of a normalised point at radius² `r2`: `θd / r`. The
/// one form both projections use, so their results are the same bits.
#[inline(always)]
fn fisheye_scale([k1, k2, k3, k4]: [f32; 4], r2: f32) -> f32 {
    let r = r2.sqrt();
    let theta = r.atan();
    let t2 = theta * theta;
    let theta_d = theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))));
    if r > 1e-12 {
        theta_d / r
    } else {
        1.0
    }
}

/// Quarter turns (0..=3, clockwise on the image) that take a step along the `reference`
/// camera's image axes to the nearest step along `view`'s, for a surface facing the
/// reference at `depth` on its optical axis: 0 for cameras mounted alike, 1 or 3 where one
/// of them is mounted sideways, 2 upside down. The matching windows compare the
/// reference's pixels with the view's sample by sample, so on a view turned relative to
/// the reference the window must be turned too, or a textured patch matches best beside
/// its true position (a sideways reference on upright side views put every hand 2-3 cm
/// too deep). The turn is the rotation part of the local map between the two images (the
/// image axes alone mislead between cameras far apart: foreshortening shears them).
pub fn window_quarter_turns(reference: &Camera, view: &Camera, depth: f64) -> u8 {
    let back = |u: f64, v: f64| {
        let n = reference.pixel_to_normalised(&nalgebra::Point2::new(u, v));
        reference.camera_to_world(&nalgebra::Point3::new(n.x * depth, n.y * depth, depth))
    };
    let (cx, cy) = (reference.matrix[(0, 2)], reference.matrix[(1, 2)]);
    let project = |u: f64, v: f64| view.project(&back(u, v));
    let (Some(centre), Some(right), Some(down)) = (project(cx, cy), project(cx + 1.0, cy), project(cx, cy + 1.0))
    else {
        // The view does not see the reference's axis there: the plain window.
        return 0;
    };
    let (a, b) = (right - centre, down - centre);
    // The rotation nearest the map [a b]: its angle is atan2(a.y - b.x, a.x + b.y).
    let angle = (a.y - b.x).atan2(a.x + b.y);
    if !angle.is_finite() {
        return 0;
    }
    // Image y points down, so a positive angle turns clockwise on the image.
    ((angle / std::f64::consts::FRAC_PI_2).round() as i64).rem_euclid(4) as u8
}

/// Points closer to a camera than this (camera-frame z) do not project.
const MIN_Z: f32 = 1e-6;

impl LevelProjection {
    /// The projection of `camera` onto pyramid level `level`.
    pub fn new(camera: &Camera, level: usize) -> Self {
        let s = 0.5f64.powi(level as i32);
        let k = camera.matrix;
        let r = camera.rotation.matrix();
        let d = camera.distortion;
        let kl = nalgebra::Matrix3::new(
            k[(0, 0)] * s,
            k[(0, 1)] * s,
            (k[(0, 2)] + 0.5) * s - 0.5,
            0.0,
            k[(1, 1)] * s,
            (k[(1, 2)] + 0.5) * s - 0.5,
            0.0,
            0.0,
            1.0,
        );
        let kr = kl * r;
        let kt = kl * camera.translation;
        Self {
            matrix: std::array::from_fn(|i| [kr[(i, 0)] as f32, kr[(i, 1)] as f32, kr[(i, 2)] as f32, kt[i] as f32]),
            rotation: std::array::from_fn(|i| std::array::from_fn(|j| r[(i, j)] as f32)),
            translation: std::array::from_fn(|i| camera.translation[i] as f32),
            fx: (k[(0, 0)] * s) as f32,
            fy: (k[(1, 1)] * s) as f32,
            skew: (k[(0, 1)] * s) as f32,
            cx: ((k[(0, 2)] + 0.5) * s - 0.5) as f32,
            cy: ((k[(1, 2)] + 0.5) * s - 0.5) as f32,
            lens: match camera.fisheye {
                Some(fisheye) => Lens::Fisheye(fisheye.as_array().map(|v| v as f32)),
                None if d.is_zero() => Lens::Pinhole,
                None => Lens::Distorted(d.as_array().map(|v| v as f32)),
            },
        }
    }

    /// Camera-frame coordinates of a world point.
    #[inline(always)]
    pub fn to_camera(&self, p: [f32; 3]) -> [f32; 3] {
        let r = &self.rotation;
        [
            r[0][0] * p[0] + r[0][1] * p[1] + r[0][2] * p[2] + self.translation[0],
            r[1][0] * p[0] + r[1][1] * p[1] + r[1][2] * p[2] + self.translation[1],
            r[2][0] * p[0] + r[2][1] * p[1] + r[2][2] * p[2] + self.translation[2],
        ]
    }

    /// Subpixel position of a world point on this level, or `None` behind the camera.
    #[inline(always)]
    pub fn project(&self, p: [f32; 3]) -> Option<[f32; 2]> {
        if let Lens::Pinhole = self.lens {
            let m = &self.matrix;
            let w = m[2][0] * p[0] + m[2][1] * p[1] + m[2][2] * p[2] + m[2][3];
            if w <= MIN_Z {
                return None;
            }
            let inv = 1.0 / w;
            let u = m[0][0] * p[0] + m[0][1] * p[1] + m[0][2] * p[2] + m[0][3];
            let v = m[1][0] * p[0] + m[1][1] * p[1] + m[1][2] * p[2] + m[1][3];
            return Some([u * inv, v * inv]);
        }
        let c = self.to_camera(p);
        if c[2] <= MIN_Z {
            return None;
        }
        let inv = 1.0 / c[2];
        let (mut x, mut y) = (c[0] * inv, c[1] * inv);
        match self.lens {
            Lens::Pinhole => {}
            Lens::Distorted([k1, k2, p1, p2, k3]) => {
                let r2 = x * x + y * y;
                let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
                let xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
                let yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
                x = xd;
                y = yd;
            }
            Lens::Fisheye(k) => {
                let scale = fisheye_scale(k, x * x + y * y);
                x *= scale;
                y *= scale;
            }
        }
        Some([self.fx * x + self.skew * y + self.cx, self.fy * y + self.cy])
    }

    /// [`LevelProjection::project`] of `L` points at once, lane by lane with no branch
    /// inside the lanes, so the arithmetic vectorises across points (the lens distortion is
    /// most of a candidate's projection cost, and scalar code cannot spread it over SIMD
    /// lanes). Each lane performs `project`'s operations in its order, so the results are
    /// its bits; lanes behind the camera come back `false` and their `u`, `v` are garbage.
    #[inline(always)]
    pub fn project_lanes<const L: usize>(&self, p: &[[f32; L]; 3], u: &mut [f32; L], v: &mut [f32; L]) -> [bool; L] {
        let mut ok = [false; L];
        let [px, py, pz] = p;
        let (r, t) = (&self.rotation, &self.translation);
        if let Lens::Fisheye(k) = self.lens {
            // Rare (wide lenses); the angle's arctangent is a call per lane.
            for l in 0..L {
                let [c0, c1, c2] = self.to_camera([px[l], py[l], pz[l]]);
                ok[l] = c2 > MIN_Z || c2.is_nan();
                let inv = 1.0 / c2;
                let (mut x, mut y) = (c0 * inv, c1 * inv);
                let scale = fisheye_scale(k, x * x + y * y);
                x *= scale;
                y *= scale;
                u[l] = self.fx * x + self.skew * y + self.cx;
                v[l] = self.fy * y + self.cy;
            }
            return ok;
        }
        let Lens::Distorted([k1, k2, p1, p2, k3]) = self.lens else {
            let m = &self.matrix;
            for l in 0..L {
                let w = m[2][0] * px[l] + m[2][1] * py[l] + m[2][2] * pz[l] + m[2][3];
                ok[l] = w > MIN_Z || w.is_nan();
                let inv = 1.0 / w;
                u[l] = (m[0][0] * px[l] + m[0][1] * py[l] + m[0][2] * pz[l] + m[0][3]) * inv;
                v[l] = (m[1][0] * px[l] + m[1][1] * py[l] + m[1][2] * pz[l] + m[1][3]) * inv;
            }
            return ok;
        };
        for l in 0..L {
            let c0 = r[0][0] * px[l] + r[0][1] * py[l] + r[0][2] * pz[l] + t[0];
            let c1 = r[1][0] * px[l] + r[1][1] * py[l] + r[1][2] * pz[l] + t[1];
            let c2 = r[2][0] * px[l] + r[2][1] * py[l] + r[2][2] * pz[l] + t[2];
            ok[l] = c2 > MIN_Z || c2.is_nan();
            let inv = 1.0 / c2;
            let (x, y) = (c0 * inv, c1 * inv);
            let r2 = x * x + y * y;
            let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
            let xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
            let yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
            u[l] = self.fx * xd + self.skew * yd + self.cx;
            v[l] = self.fy * yd + self.cy;
        }
        ok
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use handflow_protocol::{Distortion, Fisheye, Rig};
    use nalgebra::{Matrix3, Point3, Rotation3, Vector3};

    /// The test camera with OpenCV's fisheye model instead.
    fn fisheye_camera() -> Camera {
        camera(Distortion::default())
            .with_fisheye(Fisheye { k1: 0.04, k2: -0.015, k3: 0.003, k4: -0.0004 })
            .expect("valid fisheye")
    }

    fn camera(distortion: Distortion) -> Camera {
        Camera::new(
            "test",
            640,
            480,
            Matrix3::new(500.0, 0.5, 320.0, 0.0, 510.0, 240.0, 0.0, 0.0, 1.0),
            distortion,
            Rotation3::from_euler_angles(0.1, -0.2, 0.05),
            Vector3::new(0.1, -0.2, 2.0),
        )
        .expect("valid camera")
    }

    #[test]
    fn level_zero_matches_the_double_precision_camera() {
        let _ = Rig::default();
        let distorted = camera(Distortion { k1: -0.2, k2: 0.05, p1: 0.001, p2: -0.002, k3: 0.0 });
        for cam in [camera(Distortion::default()), distorted, fisheye_camera()] {
            let fast = LevelProjection::new(&cam, 0);
            for p in [[0.1, 0.2, 1.0], [-0.3, 0.1, 0.5], [0.0, 0.0, 3.0]] {
                let exact = cam.project(&Point3::new(p[0], p[1], p[2])).expect("in front");
                let got = fast.project(p.map(|v| v as f32)).expect("in front");
                assert!((f64::from(got[0]) - exact.x).abs() < 1e-3);
                assert!((f64::from(got[1]) - exact.y).abs() < 1e-3);
            }
        }
    }

    #[test]
    fn coarser_levels_follow_the_pixel_centre_convention() {
        let cam = camera(Distortion::default());
        let p = [0.05f32, -0.1, 1.5];
        let full = LevelProjection::new(&cam, 0).project(p).expect("in front");
        for level in 1..4 {
            let s = 0.5f32.powi(level as i32);
            let got = LevelProjection::new(&cam, level).project(p).expect("in front");
            assert!((got[0] - ((full[0] + 0.5) * s - 0.5)).abs() < 1e-3);
            assert!((got[1] - ((full[1] + 0.5) * s - 0.5)).abs() < 1e-3);
        }
    }

    #[test]
    fn lanes_project_as_one_point_at_a_time_to_the_bit() {
        let points: [[f32; 3]; 8] = [
            [0.1, 0.2, 1.0],
            [-0.3, 0.1, 0.5],
            [0.0, 0.0, 3.0],
            [0.7, -0.4, 1.2],
            [1e-3, 2e-3, 0.8],
            [-0.05, 0.9, 2.5],
            [0.2, 0.2, 0.05],
            [0.33, -0.21, 1.7],
        ];
        let distorted = camera(Distortion { k1: -0.2, k2: 0.05, p1: 0.001, p2: -0.002, k3: 0.01 });
        for cam in [camera(Distortion::default()), distorted, fisheye_camera()] {
            let behind = cam.camera_to_world(&Point3::new(0.1, 0.0, -1.0));
            let mut lanes = points;
            lanes[5] = [behind.x as f32, behind.y as f32, behind.z as f32];
            for level in 0..3 {
                let fast = LevelProjection::new(&cam, level);
                let soa: [[f32; 8]; 3] = std::array::from_fn(|axis| std::array::from_fn(|l| lanes[l][axis]));
                let (mut u, mut v) = ([0f32; 8], [0f32; 8]);
                let ok = fast.project_lanes(&soa, &mut u, &mut v);
                for (l, p) in lanes.iter().enumerate() {
                    match fast.project(*p) {
                        Some([pu, pv]) => {
                            assert!(ok[l], "lane {l} should project");
                            assert_eq!((u[l].to_bits(), v[l].to_bits()), (pu.to_bits(), pv.to_bits()), "lane {l}");
                        }
                        None => assert!(!ok[l], "lane {l} is behind the camera"),
                    }
                }
            }
        }
    }

    #[test]
    fn points_behind_the_camera_do_not_project() {
        let cam = camera(Distortion::default());
        let fast = LevelProjection::new(&cam, 0);
        let behind = cam.camera_to_world(&Point3::new(0.0, 0.0, -1.0));
        assert!(fast.project([behind.x as f32, behind.y as f32, behind.z as f32]).is_none());
    }

    /// A 640x480 camera 2 m from the origin, looking at it from `yaw` radians about the
    /// world's y axis, rolled by `roll` about its own optical axis.
    fn looking_at_the_origin(yaw: f64, roll: f64) -> Camera {
        let rotation =
            Rotation3::from_axis_angle(&Vector3::z_axis(), roll) * Rotation3::from_axis_angle(&Vector3::y_axis(), -yaw);
        let k = Matrix3::new(500.0, 0.0, 320.0, 0.0, 500.0, 240.0, 0.0, 0.0, 1.0);
        Camera::new("c", 640, 480, k, Distortion::default(), rotation, Vector3::new(0.0, 0.0, 2.0)).expect("valid")
    }

    #[test]
    fn window_turns_follow_the_roll_between_cameras_not_their_baseline() {
        use std::f64::consts::FRAC_PI_2;
        let turns = |reference: (f64, f64), view: (f64, f64)| {
            let r = looking_at_the_origin(reference.0, reference.1);
            window_quarter_turns(&r, &looking_at_the_origin(view.0, view.1), 2.0)
        };
        // Side views of an upright rig, near and far apart: no turn.
        for yaw in [-1.1, -0.6, 0.0, 0.6, 1.1] {
            assert_eq!(turns((0.0, 0.0), (yaw, 0.0)), 0, "yaw {yaw}");
        }
        // A view mounted sideways (clockwise on its image: the reference's x axis runs
        // down it) or upside down, seen from in front or from the side.
        for yaw in [0.0, 0.6, -1.1] {
            assert_eq!(turns((0.0, 0.0), (yaw, FRAC_PI_2)), 1, "yaw {yaw}");
            assert_eq!(turns((0.0, 0.0), (yaw, -FRAC_PI_2)), 3, "yaw {yaw}");
            assert_eq!(turns((0.0, 0.0), (yaw, 2.0 * FRAC_PI_2)), 2, "yaw {yaw}");
        }
        // The nearest quarter turn, and only the difference of the two rolls counts.
        assert_eq!(turns((0.0, 0.0), (0.6, 0.5)), 0);
        assert_eq!(turns((0.0, 0.0), (0.6, 1.1)), 1);
        assert_eq!(turns((0.0, FRAC_PI_2), (0.6, FRAC_PI_2)), 0);
        assert_eq!(turns((0.0, FRAC_PI_2), (0.6, 0.0)), 3);
    }
}
