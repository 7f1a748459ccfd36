//! One calibrated camera: OpenCV pinhole model with k1 k2 p1 p2 k3 distortion, or OpenCV's
//! fisheye model (k1 k2 k3 k4 of the angle from the optical axis).

use nalgebra::{Matrix2, Matrix3, Point2, Point3, Rotation3, Unit, Vector2, Vector3};

use super::RigError;

/// Largest tolerated deviation of `RᵀR` from the identity (max abs entry) for a
/// matrix to count as a rotation (with a positive determinant).
pub(crate) const ROTATION_TOLERANCE: f64 = 1e-6;

/// Newton iterations allowed in [`Distortion::undistort`]; converging inputs
/// need fewer than 10, the bound only stops hopeless ones (no preimage).
const UNDISTORT_MAX_ITERATIONS: usize = 50;

/// OpenCV lens distortion coefficients (`k1 k2 p1 p2 k3`), applied to
/// normalised coordinates `(x/z, y/z)`.
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct Distortion {
    /// Radial, r².
    pub k1: f64,
    /// Radial, r⁴.
    pub k2: f64,
    /// Tangential (decentring), first.
    pub p1: f64,
    /// Tangential (decentring), second.
    pub p2: f64,
    /// Radial, r⁶.
    pub k3: f64,
}

impl Distortion {
    /// True when every coefficient is zero (an ideal pinhole).
    pub fn is_zero(&self) -> bool {
        self.as_array().iter().all(|&c| c == 0.0)
    }

    /// The coefficients in OpenCV order: `[k1, k2, p1, p2, k3]`.
    pub fn as_array(&self) -> [f64; 5] {
        [self.k1, self.k2, self.p1, self.p2, self.k3]
    }

    /// Applies the distortion to a normalised point (OpenCV's formula):
    ///
    /// ```text
    /// r² = x² + y²,  radial = 1 + k1 r² + k2 r⁴ + k3 r⁶
    /// x' = x radial + 2 p1 x y + p2 (r² + 2x²)
    /// y' = y radial + p1 (r² + 2y²) + 2 p2 x y
    /// ```
    pub fn distort(&self, normalised: Vector2<f64>) -> Vector2<f64> {
        let (x, y) = (normalised.x, normalised.y);
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        Vector2::new(
            x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x),
            y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y,
        )
    }

    /// [`Self::distort`] and its Jacobian with respect to the normalised point.
    fn distort_with_jacobian(&self, p: Vector2<f64>) -> (Vector2<f64>, Matrix2<f64>) {
        let (x, y) = (p.x, p.y);
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        // d(radial)/d(r²); d(r²)/dx = 2x.
        let d = self.k1 + r2 * (2.0 * self.k2 + 3.0 * self.k3 * r2);
        let jacobian = Matrix2::new(
            radial + 2.0 * x * x * d + 2.0 * self.p1 * y + 6.0 * self.p2 * x,
            2.0 * x * y * d + 2.0 * self.p1 * x + 2.0 * self.p2 * y,
            2.0 * x * y * d + 2.0 * self.p1 * x + 2.0 * self.p2 * y,
            radial + 2.0 * y * y * d + 6.0 * self.p1 * y + 2.0 * self.p2 * x,
        );
        (self.distort(p), jacobian)
    }

    /// Inverts [`Self::distort`]: the normalised point that distorts to `distorted`.
    ///
    /// Damped Newton iterations from `distorted` (bounded; converges to ~1e-15 for
    /// realistic lenses). When no exact preimage exists (far outside the lens's
    /// valid field), returns the best point found rather than failing.
    pub fn undistort(&self, distorted: Vector2<f64>) -> Vector2<f64> {
        if self.is_zero() || !distorted.iter().all(|c| c.is_finite()) {
            return distorted;
        }
        // Stop at a residual near rounding level of the input.
        let tolerance = 1e-15 * (1.0 + distorted.norm());
        let mut x = distorted;
        let (mut value, mut jacobian) = self.distort_with_jacobian(x);
        let mut residual = (value - distorted).norm();
        for _ in 0..UNDISTORT_MAX_ITERATIONS {
            if residual.is_nan() || residual <= tolerance {
                break;
            }
            let Some(step) = jacobian.try_inverse().map(|inverse| inverse * (value - distorted)) else {
                break;
            };
            // Backtrack so that the residual never grows: plain Newton can
            // overshoot where the distortion is strongly non-linear.
            let mut scale = 1.0;
            let mut improved = false;
            while scale > 1e-6 {
                let candidate = x - step * scale;
                let (candidate_value, candidate_jacobian) = self.distort_with_jacobian(candidate);
                let candidate_residual = (candidate_value - distorted).norm();
                if candidate_residual < residual {
                    (x, value, jacobian, residual) =
                        (candidate, candidate_value, candidate_jacobian, candidate_residual);
                    improved = true;
                    break;
                }
                scale *= 0.5;
            }
            if !improved {
                break;
            }
        }
        x
    }
}

/// OpenCV's fisheye lens model (`cv::fisheye`, anipose's and caliscope's `fisheye = true`):
/// a normalised point at angle `θ = atan(r)` from the optical axis (`r² = x² + y²`) is
/// imaged at radius `θd = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸)`, in its own direction.
/// Wide lenses whose field the pinhole polynomial cannot follow are calibrated so.
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct Fisheye {
    /// θ² term.
    pub k1: f64,
    /// θ⁴ term.
    pub k2: f64,
    /// θ⁶ term.
    pub k3: f64,
    /// θ⁸ term.
    pub k4: f64,
}

/// Newton iterations allowed in [`Fisheye::undistort`] (a one-dimensional solve).
const FISHEYE_UNDISTORT_MAX_ITERATIONS: usize = 30;

impl Fisheye {
    /// The coefficients in OpenCV order: `[k1, k2, k3, k4]`.
    pub fn as_array(&self) -> [f64; 4] {
        [self.k1, self.k2, self.k3, self.k4]
    }

    /// `θd / θ`, the polynomial of the model, at `θ²`.
    fn stretch(&self, theta2: f64) -> f64 {
        1.0 + theta2 * (self.k1 + theta2 * (self.k2 + theta2 * (self.k3 + theta2 * self.k4)))
    }

    /// Applies the model to a normalised point `(x/z, y/z)` (a point in front of the camera).
    pub fn distort(&self, normalised: Vector2<f64>) -> Vector2<f64> {
        let r = normalised.norm();
        if r <= 1e-12 {
            return normalised;
        }
        let theta = r.atan();
        normalised * (theta * self.stretch(theta * theta) / r)
    }

    /// Inverts [`Self::distort`]: Newton's method on `θ` from `θd`, the distorted point's
    /// radius, kept within the front half-space (`θ < π/2`); where the polynomial has no
    /// preimage it returns the best angle found.
    pub fn undistort(&self, distorted: Vector2<f64>) -> Vector2<f64> {
        let theta_d = distorted.norm();
        if theta_d <= 1e-12 || !theta_d.is_finite() {
            return distorted;
        }
        let limit = std::f64::consts::FRAC_PI_2 - 1e-6;
        let mut theta = theta_d.min(limit);
        for _ in 0..FISHEYE_UNDISTORT_MAX_ITERATIONS {
            let t2 = theta * theta;
            let residual = theta * self.stretch(t2) - theta_d;
            let slope = 1.0 + t2 * (3.0 * self.k1 + t2 * (5.0 * self.k2 + t2 * (7.0 * self.k3 + t2 * 9.0 * self.k4)));
            if residual.abs() <= 1e-15 * (1.0 + theta_d) || slope <= 0.0 || !slope.is_finite() {
                break;
            }
            theta = (theta - residual / slope).clamp(0.0, limit);
        }
        distorted * (theta.tan() / theta_d)
    }
}

/// A half-line in the world frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ray {
    /// Where the ray starts (for [`Camera::back_project`], the camera centre).
    pub origin: Point3<f64>,
    /// Unit direction.
    pub direction: Unit<Vector3<f64>>,
}

impl Ray {
    /// The point `distance` metres along the ray from its origin.
    pub fn at(&self, distance: f64) -> Point3<f64> {
        self.origin + self.direction.into_inner() * distance
    }
}

/// One calibrated camera.
///
/// `x_cam = rotation * x_world + translation`; a camera point projects to
/// `matrix * distort(x/z, y/z, 1)`. Build with [`Camera::new`] to have the
/// parameters validated; the fields are public for reading and for tools that
/// know what they are doing.
#[derive(Clone, Debug, PartialEq)]
pub struct Camera {
    /// Camera name, unique within a rig.
    pub name: String,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Intrinsics `K`: `[[fx, s, cx], [0, fy, cy], [0, 0, 1]]`.
    pub matrix: Matrix3<f64>,
    /// Lens distortion (OpenCV k1 k2 p1 p2 k3); all zero for a fisheye lens.
    pub distortion: Distortion,
    /// The fisheye lens model, when the camera was calibrated with it (then `distortion`
    /// is unused); `None` for the pinhole model.
    pub fisheye: Option<Fisheye>,
    /// World-to-camera rotation.
    pub rotation: Rotation3<f64>,
    /// World-to-camera translation: `x_cam = R x_world + t`.
    pub translation: Vector3<f64>,
    /// Clockwise quarter turns (0..=3) that make this camera's raw frames upright: the
    /// camera is mounted rotated by that much (caliscope's `rotation_count`, taken modulo
    /// 4). Projection is unaffected (the calibration is of the raw frames); only the
    /// image's true up, [`Camera::image_up`], depends on it.
    pub mount_quarter_turns: u8,
}

impl Camera {
    /// Builds a camera after validating it: sizes > 0, every number finite,
    /// `K`'s last row `[0, 0, 1]`, `fx, fy > 0` and `K` non-singular, and the
    /// rotation orthonormal with determinant +1.
    ///
    /// Errors are [`RigError::Field`] with `camera` set to `name` and `field`
    /// spelled as in the rig file (`size`, `matrix`, `distortions`, `rotation`,
    /// `translation`).
    pub fn new(
        name: impl Into<String>,
        width: u32,
        height: u32,
        matrix: Matrix3<f64>,
        distortion: Distortion,
        rotation: Rotation3<f64>,
        translation: Vector3<f64>,
    ) -> Result<Camera, RigError> {
        let name = name.into();
        let err = |field: &str, problem: String| RigError::field(&name, field, problem);

        if width == 0 || height == 0 {
            return Err(err("size", format!("width and height must be positive, found [{width}, {height}]")));
        }

        for row in 0..3 {
            for col in 0..3 {
                let value = matrix[(row, col)];
                if !value.is_finite() {
                    return Err(err("matrix", format!("row {row}, column {col} is not finite ({value})")));
                }
            }
        }
        let last_row = [matrix[(2, 0)], matrix[(2, 1)], matrix[(2, 2)]];
        if last_row != [0.0, 0.0, 1.0] {
            return Err(err(
                "matrix",
                format!("last row must be [0, 0, 1], found [{}, {}, {}]", last_row[0], last_row[1], last_row[2]),
            ));
        }
        let (fx, fy) = (matrix[(0, 0)], matrix[(1, 1)]);
        if fx <= 0.0 || fy <= 0.0 {
            return Err(err("matrix", format!("singular: focal lengths fx = {fx}, fy = {fy} must be positive")));
        }
        // With the last row [0, 0, 1], det K is the det of the upper-left 2x2.
        let det = fx * fy - matrix[(0, 1)] * matrix[(1, 0)];
        let scale = matrix.fixed_view::<2, 2>(0, 0).amax();
        if det.abs() <= 1e-12 * scale * scale {
            return Err(err("matrix", format!("singular: determinant {det}")));
        }

        for (label, value) in ["k1", "k2", "p1", "p2", "k3"].iter().zip(distortion.as_array()) {
            if !value.is_finite() {
                return Err(err("distortions", format!("{label} is not finite ({value})")));
            }
        }

        if let Some(problem) = rotation_problem(rotation.matrix()) {
            return Err(err("rotation", problem));
        }

        for (axis, value) in ["x", "y", "z"].iter().zip(translation.iter()) {
            if !value.is_finite() {
                return Err(err("translation", format!("{axis} is not finite ({value})")));
            }
        }

        Ok(Camera {
            name,
            width,
            height,
            matrix,
            distortion,
            rotation,
            translation,
            fisheye: None,
            mount_quarter_turns: 0,
        })
    }

    /// This camera with OpenCV's fisheye lens model of coefficients `fisheye` instead of the
    /// pinhole's distortion (which must then be zero); errors name the field `distortions`.
    pub fn with_fisheye(mut self, fisheye: Fisheye) -> Result<Camera, RigError> {
        for (label, value) in ["k1", "k2", "k3", "k4"].iter().zip(fisheye.as_array()) {
            if !value.is_finite() {
                return Err(RigError::field(
                    &self.name,
                    "distortions",
                    format!("fisheye {label} is not finite ({value})"),
                ));
            }
        }
        if !self.distortion.is_zero() {
            return Err(RigError::field(
                &self.name,
                "distortions",
                "a fisheye camera has no pinhole distortion (k1 k2 p1 p2 k3)".to_owned(),
            ));
        }
        self.fisheye = Some(fisheye);
        Ok(self)
    }

    /// This camera mounted by `turns` clockwise quarter turns (taken modulo 4; see
    /// [`Camera::mount_quarter_turns`]).
    pub fn with_mount_quarter_turns(mut self, turns: u8) -> Camera {
        self.mount_quarter_turns = turns % 4;
        self
    }

    /// The world direction (unit) that is up in this camera's frames once they are turned
    /// upright by [`Camera::mount_quarter_turns`].
    ///
    /// Raw image up is the camera's `-y` axis (`-`row 1 of `R`). Turning the frame
    /// clockwise by a quarter brings the raw left edge to the top, so one turn makes up
    /// `-x`, two `+y`, three `+x`.
    pub fn image_up(&self) -> Vector3<f64> {
        let up_in_camera = match self.mount_quarter_turns % 4 {
            0 => Vector3::new(0.0, -1.0, 0.0),
            1 => Vector3::new(-1.0, 0.0, 0.0),
            2 => Vector3::new(0.0, 1.0, 0.0),
            _ => Vector3::new(1.0, 0.0, 0.0),
        };
        self.rotation.inverse() * up_in_camera
    }

    /// The world direction (unit) the camera looks along: its optical axis, row 2 of `R`.
    pub fn viewing_direction(&self) -> Vector3<f64> {
        self.rotation.matrix().row(2).transpose()
    }

    /// The camera centre in the world frame, `-Rᵀ t`.
    pub fn centre(&self) -> Point3<f64> {
        Point3::from(-(self.rotation.inverse() * self.translation))
    }

    /// World point to camera frame: `R p + t`.
    pub fn world_to_camera(&self, p: &Point3<f64>) -> Point3<f64> {
        self.rotation * p + self.translation
    }

    /// Camera-frame point to world frame: `Rᵀ (p − t)`.
    pub fn camera_to_world(&self, p: &Point3<f64>) -> Point3<f64> {
        self.rotation.inverse() * (p - self.translation)
    }

    /// Subpixel image position of a world point, with distortion; `None` when
    /// the point is not in front of the camera (camera-frame `z <= 0`).
    ///
    /// Points outside the image are projected too (the result may lie outside
    /// `[0, width) x [0, height)`).
    pub fn project(&self, p_world: &Point3<f64>) -> Option<Point2<f64>> {
        self.project_camera_point(&self.world_to_camera(p_world))
    }

    /// Like [`Self::project`] for a point already in the camera frame.
    pub fn project_camera_point(&self, p_cam: &Point3<f64>) -> Option<Point2<f64>> {
        if p_cam.z.is_nan() || p_cam.z <= 0.0 {
            return None;
        }
        let distorted = self.distort(Vector2::new(p_cam.x / p_cam.z, p_cam.y / p_cam.z));
        let k = &self.matrix;
        Some(Point2::new(
            k[(0, 0)] * distorted.x + k[(0, 1)] * distorted.y + k[(0, 2)],
            k[(1, 0)] * distorted.x + k[(1, 1)] * distorted.y + k[(1, 2)],
        ))
    }

    /// Applies this camera's lens model to normalised coordinates `(x/z, y/z)`; see
    /// [`Distortion::distort`] and [`Fisheye::distort`].
    pub fn distort(&self, normalised: Vector2<f64>) -> Vector2<f64> {
        match &self.fisheye {
            Some(fisheye) => fisheye.distort(normalised),
            None => self.distortion.distort(normalised),
        }
    }

    /// Inverse of [`Self::distort`]; see [`Distortion::undistort`] and
    /// [`Fisheye::undistort`].
    pub fn undistort(&self, distorted: Vector2<f64>) -> Vector2<f64> {
        match &self.fisheye {
            Some(fisheye) => fisheye.undistort(distorted),
            None => self.distortion.undistort(distorted),
        }
    }

    /// Undistorted normalised coordinates `(x/z, y/z)` of a pixel: `K⁻¹`, then
    /// [`Self::undistort`].
    pub fn pixel_to_normalised(&self, pixel: &Point2<f64>) -> Vector2<f64> {
        // K's last row is [0, 0, 1], so K⁻¹ reduces to a 2x2 solve.
        let k = &self.matrix;
        let a = Matrix2::new(k[(0, 0)], k[(0, 1)], k[(1, 0)], k[(1, 1)]);
        let b = Vector2::new(pixel.x - k[(0, 2)], pixel.y - k[(1, 2)]);
        let det = a.determinant();
        let distorted = Vector2::new(a[(1, 1)] * b.x - a[(0, 1)] * b.y, a[(0, 0)] * b.y - a[(1, 0)] * b.x) / det;
        self.undistort(distorted)
    }

    /// The world-frame ray from the camera centre through `pixel`.
    pub fn back_project(&self, pixel: &Point2<f64>) -> Ray {
        let normalised = self.pixel_to_normalised(pixel);
        let direction = self.rotation.inverse() * Vector3::new(normalised.x, normalised.y, 1.0);
        Ray { origin: self.centre(), direction: Unit::new_normalize(direction) }
    }
}

/// Why `m` is not a rotation matrix, or `None` if it is one (within
/// [`ROTATION_TOLERANCE`]).
pub(crate) fn rotation_problem(m: &Matrix3<f64>) -> Option<String> {
    if let Some(value) = m.iter().find(|v| !v.is_finite()) {
        return Some(format!("not finite ({value})"));
    }
    let deviation = (m.transpose() * m - Matrix3::identity()).amax();
    if deviation > ROTATION_TOLERANCE {
        return Some(format!(
            "3x3 rotation matrix is not orthonormal: |RᵀR − I| = {deviation:.3e} (tolerance {ROTATION_TOLERANCE:e})"
        ));
    }
    // Orthonormal, so det is ±1 up to the tolerance: only its sign is in question.
    let det = m.determinant();
    if det <= 0.0 {
        return Some(format!("3x3 rotation matrix has determinant {det:.6} (a reflection), expected +1"));
    }
    None
}
