//! Rig calibration: cameras, their projection model and the rig file format.
//!
//! The file format is the one anipose and Pose2Sim write: one TOML table per
//! camera, in rig order, each with `name`, `size = [width, height]`, `matrix`
//! (3x3 K), `distortions` (`k1 k2 p1 p2 [k3]`; four numbers mean `k3 = 0`),
//! `rotation` (Rodrigues vector, world to camera; a 3x3 rotation matrix is
//! accepted too), `translation` (world to camera) and optionally
//! `fisheye = false`:
//!
//! ```toml
//! [cam_0]
//! name = "left"
//! size = [1920, 1080]
//! matrix = [[1400.0, 0.0, 960.0], [0.0, 1400.0, 540.0], [0.0, 0.0, 1.0]]
//! distortions = [-0.1, 0.02, 0.0, 0.0, 0.0]
//! rotation = [0.0, 0.0, 0.0]
//! translation = [0.0, 0.0, 2.0]
//!
//! [metadata]
//! adjusted = false
//! ```
//!
//! A table named `metadata` without a `matrix` is ignored.
//!
//! ```
//! use handflow_protocol::Rig;
//! use nalgebra::{Point2, Point3};
//!
//! let rig = Rig::from_toml_str(r#"
//!     [cam_0]
//!     name = "left"
//!     size = [1920, 1080]
//!     matrix = [[1400.0, 0.0, 960.0], [0.0, 1400.0, 540.0], [0.0, 0.0, 1.0]]
//!     distortions = [-0.1, 0.02, 0.0, 0.0]
//!     rotation = [0.0, 0.0, 0.0]
//!     translation = [0.0, 0.0, 2.0]
//! "#)?;
//! let left = rig.camera("left").expect("defined above");
//! // The world origin is 2 m straight ahead: the principal point.
//! assert_eq!(left.project(&Point3::origin()), Some(Point2::new(960.0, 540.0)));
//! # Ok::<(), handflow_protocol::RigError>(())
//! ```

mod camera;
mod error;
mod toml_format;

use std::path::Path;

pub use camera::{Camera, Distortion, Ray};
pub use error::RigError;

/// The calibrated cameras of a capture rig, in a fixed order.
#[derive(Clone, Debug, PartialEq, Default)]
pub struct Rig {
    /// The cameras, in file order. Names are unique in a rig read from a file.
    pub cameras: Vec<Camera>,
}

impl Rig {
    /// Parses a rig file's text (see the [module documentation](self) for the format).
    ///
    /// Every camera is validated as by [`Camera::new`]; duplicate names, a
    /// `fisheye = true` camera and a rig without cameras are errors too.
    pub fn from_toml_str(text: &str) -> Result<Rig, RigError> {
        toml_format::parse(text)
    }

    /// The rig in the file format: tables `cam_0`, `cam_1`, ... in rig order,
    /// rotations as Rodrigues vectors, numbers written to round-trip exactly.
    pub fn to_toml_string(&self) -> String {
        toml_format::write(self)
    }

    /// Reads and parses a rig file. Every error names the file.
    pub fn load(path: impl AsRef<Path>) -> Result<Rig, RigError> {
        let path = path.as_ref();
        let text = std::fs::read_to_string(path).map_err(|error| RigError::Io {
            action: "read",
            path: path.to_owned(),
            error,
        })?;
        Rig::from_toml_str(&text).map_err(|error| RigError::InFile { path: path.to_owned(), error: Box::new(error) })
    }

    /// Writes [`Self::to_toml_string`] to `path`, replacing any existing file.
    pub fn save(&self, path: impl AsRef<Path>) -> Result<(), RigError> {
        let path = path.as_ref();
        std::fs::write(path, self.to_toml_string()).map_err(|error| RigError::Io {
            action: "write",
            path: path.to_owned(),
            error,
        })
    }

    /// Index of the camera whose optical axis is closest to the rig's mean viewing
    /// direction: the most frontal view of what the rig looks at, which sees most of what
    /// the others see (0 for an empty rig).
    pub fn most_frontal_camera(&self) -> usize {
        let axis = |c: &Camera| c.rotation.matrix().row(2).transpose();
        let mean: nalgebra::Vector3<f64> = self.cameras.iter().map(axis).sum();
        self.cameras
            .iter()
            .enumerate()
            .max_by(|(_, a), (_, b)| axis(a).dot(&mean).total_cmp(&axis(b).dot(&mean)))
            .map_or(0, |(i, _)| i)
    }

    /// The camera called `name`, if any.
    pub fn camera(&self, name: &str) -> Option<&Camera> {
        self.cameras.iter().find(|camera| camera.name == name)
    }
}
