//! Rig calibration: cameras, their projection model and the rig file formats.
//!
//! [`Rig::load`] reads anipose / Pose2Sim TOML (below, ours), caliscope's
//! `camera_array.toml` (and the `config.toml` of its older versions) and OpenCV FileStorage
//! YAML and XML, recognised from the content
//! ([`RigFormat`]); [`Rig::find_in_dir`] picks a folder's calibration. [`Rig::world_up`]
//! says which way is up and why ([`UpSource`]).
//!
//! Our file format is the one anipose and Pose2Sim write: one TOML table per
//! camera, in rig order, each with `name`, `size = [width, height]`, `matrix`
//! (3x3 K), `distortions` (`k1 k2 p1 p2 [k3]`; four numbers mean `k3 = 0`),
//! `rotation` (Rodrigues vector, world to camera; a 3x3 rotation matrix is
//! accepted too), `translation` (world to camera) and optionally
//! `fisheye` (`true`: OpenCV's fisheye model, [`Fisheye`], whose four `distortions` are
//! `k1 k2 k3 k4`):
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
//! A table named `metadata` without a `matrix` holds no camera; its `up = [x, y, z]` (or
//! `world_up`) declares the world's up, with `up_source = "calibration"` (default) or
//! `"configured"`. A camera's optional `mount_quarter_turns` (0..=3) is
//! [`Camera::mount_quarter_turns`].
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

mod caliscope;
mod camera;
mod error;
mod format;
mod opencv;
mod toml_format;
mod units;
mod up;

use std::path::{Path, PathBuf};

/// The calibration file of a recording folder, in our format.
pub const RIG_FILE: &str = "rig.toml";
/// caliscope's calibration file name.
pub const CALISCOPE_FILE: &str = "camera_array.toml";
/// Where older caliscope versions keep a project's calibration, among its other settings.
pub const CALISCOPE_CONFIG_FILE: &str = "config.toml";
/// File extensions (lower case) [`Rig::find_in_dir`] considers calibration files.
const CALIBRATION_EXTENSIONS: [&str; 4] = ["toml", "yml", "yaml", "xml"];

pub use camera::{Camera, Distortion, Fisheye, Ray};
pub use error::RigError;
pub use format::RigFormat;
pub use up::{parse_direction, UpSource, WorldUp};

/// The calibrated cameras of a capture rig, in a fixed order.
#[derive(Clone, Debug, PartialEq, Default)]
pub struct Rig {
    /// The cameras, in file order. Names are unique in a rig read from a file.
    pub cameras: Vec<Camera>,
    /// The world's up when a calibration file or the user states it (source
    /// [`UpSource::Calibration`] or [`UpSource::Configured`]); `None` lets
    /// [`Rig::world_up`] estimate it from the cameras.
    pub declared_up: Option<WorldUp>,
    /// What loading noticed and did without, for the user (a camera marked ignored and
    /// left out, ...). Each was also logged as a warning. Not written by
    /// [`Rig::to_toml_string`].
    pub notes: Vec<String>,
    /// Per camera (rig order; missing entries count as false), whether its mount was set by
    /// [`Rig::infer_mounts`] rather than recorded in the file: an up declared later judges
    /// such a mount again, where a recorded one is the user's word.
    pub mounts_inferred: Vec<bool>,
}

impl Rig {
    /// A rig of `cameras`, with no declared up and no notes (not validated: build the
    /// cameras with [`Camera::new`]).
    pub fn new(cameras: Vec<Camera>) -> Rig {
        Rig { cameras, declared_up: None, notes: Vec::new(), mounts_inferred: Vec::new() }
    }

    /// Parses a rig file's text (see the [module documentation](self) for the format).
    ///
    /// Every camera is validated as by [`Camera::new`]; duplicate names and a rig without
    /// cameras are errors too.
    pub fn from_toml_str(text: &str) -> Result<Rig, RigError> {
        toml_format::parse(text)
    }

    /// The rig in the file format: tables `cam_0`, `cam_1`, ... in rig order,
    /// rotations as Rodrigues vectors, numbers written to round-trip exactly.
    pub fn to_toml_string(&self) -> String {
        toml_format::write(self)
    }

    /// Parses calibration text in any format [`Rig::load`] reads, recognised from the
    /// content ([`RigFormat::sniff`], then caliscope's layouts told from anipose's). An OpenCV file of one camera without a `name` entry names it
    /// `file_stem`.
    pub fn from_str_detect(text: &str, file_stem: &str) -> Result<(Rig, RigFormat), RigError> {
        match RigFormat::sniff(text) {
            RigFormat::OpenCvYaml => opencv::parse_yaml_rig(text, file_stem).map(|rig| (rig, RigFormat::OpenCvYaml)),
            RigFormat::OpenCvXml => opencv::parse_xml_rig(text, file_stem).map(|rig| (rig, RigFormat::OpenCvXml)),
            RigFormat::AniposeToml | RigFormat::Caliscope | RigFormat::CaliscopeConfig => {
                toml_format::parse_detect(text)
            }
        }
    }

    /// Reads a calibration file in any supported format (see [`Rig::from_str_detect`])
    /// and says which it was. Every error names the file; notes (ignored cameras, a rig in
    /// millimetres converted to metres) are logged as warnings and kept in [`Rig::notes`].
    pub fn load_detected(path: impl AsRef<Path>) -> Result<(Rig, RigFormat), RigError> {
        let path = path.as_ref();
        let text = crate::read_text_capped(path).map_err(|error| RigError::Io {
            action: "read",
            path: path.to_owned(),
            error,
        })?;
        let stem = path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
        let (mut rig, format) = Rig::from_str_detect(&text, &stem)
            .map_err(|error| RigError::InFile { path: path.to_owned(), error: Box::new(error) })?;
        rig.infer_units();
        rig.infer_mounts();
        Ok((rig, format))
    }

    /// Reads a calibration file in any supported format: the anipose / Pose2Sim TOML,
    /// caliscope's `camera_array.toml`, or OpenCV FileStorage YAML or XML. Every error
    /// names the file.
    pub fn load(path: impl AsRef<Path>) -> Result<Rig, RigError> {
        Rig::load_detected(path).map(|(rig, _)| rig)
    }

    /// Reads the cameras of several calibration files into one rig, in the order of
    /// `paths` (typically OpenCV files of one camera each, named by their stems). The
    /// first declared up wins; a camera name used twice is an error naming both files.
    pub fn load_files(paths: &[PathBuf]) -> Result<Rig, RigError> {
        let mut rig = Rig::new(Vec::new());
        let mut origins: Vec<&PathBuf> = Vec::new();
        for path in paths {
            let part = Rig::load(path)?;
            for camera in part.cameras {
                if let Some(first) = rig.cameras.iter().position(|c| c.name == camera.name) {
                    return Err(RigError::DuplicateCamera {
                        name: camera.name,
                        first: origins[first].clone(),
                        second: path.clone(),
                    });
                }
                rig.cameras.push(camera);
                origins.push(path);
            }
            rig.declared_up = rig.declared_up.take().or(part.declared_up);
            rig.notes.extend(part.notes);
        }
        if rig.cameras.is_empty() {
            return Err(RigError::NoCameras);
        }
        // Each file's cameras were judged alone (one camera per file has no width to judge a
        // unit by); together they may outvote differently.
        rig.infer_units();
        rig.infer_mounts();
        Ok(rig)
    }

    /// The calibration of a recording folder: `rig.toml`, else `camera_array.toml`
    /// (caliscope's), else the folder's only calibration file (`*.toml`, `*.yml`,
    /// `*.yaml`, `*.xml`), else, when every such file is an OpenCV file, all of them (one
    /// camera each, in name order). Anything else is [`RigError::NoCalibration`] listing
    /// what was found.
    pub fn find_in_dir(dir: impl AsRef<Path>) -> Result<Vec<PathBuf>, RigError> {
        let dir = dir.as_ref();
        for preferred in [RIG_FILE, CALISCOPE_FILE] {
            let path = dir.join(preferred);
            if path.is_file() {
                return Ok(vec![path]);
            }
        }
        let entries =
            std::fs::read_dir(dir).map_err(|error| RigError::Io { action: "list", path: dir.to_owned(), error })?;
        let mut candidates: Vec<PathBuf> = entries
            .filter_map(Result::ok)
            .map(|entry| entry.path())
            .filter(|path| path.is_file())
            .filter(|path| {
                let extension = path.extension().map(|e| e.to_string_lossy().to_ascii_lowercase());
                extension.is_some_and(|e| CALIBRATION_EXTENSIONS.contains(&e.as_str()))
            })
            .collect();
        candidates.sort();
        if candidates.len() == 1 {
            return Ok(candidates);
        }
        // Several: acceptable only as OpenCV files of one camera each.
        let formats: Vec<Option<RigFormat>> = candidates
            .iter()
            .map(|path| crate::read_text_capped(path).ok().map(|text| RigFormat::sniff(&text)))
            .collect();
        if !candidates.is_empty() && formats.iter().all(|f| f.is_some_and(RigFormat::is_opencv)) {
            return Ok(candidates);
        }
        let found = candidates
            .iter()
            .zip(&formats)
            .map(|(path, format)| {
                let name = path.file_name().map_or_else(String::new, |n| n.to_string_lossy().into_owned());
                match format {
                    Some(RigFormat::AniposeToml) => format!("{name} (TOML)"),
                    Some(format) => format!("{name} ({format})"),
                    None => format!("{name} (unreadable)"),
                }
            })
            .collect();
        Err(RigError::NoCalibration { dir: dir.to_owned(), found })
    }

    /// [`Rig::find_in_dir`], then [`Rig::load`] or [`Rig::load_files`] on what it found.
    pub fn load_dir(dir: impl AsRef<Path>) -> Result<Rig, RigError> {
        match Rig::find_in_dir(dir)?.as_slice() {
            [one] => Rig::load(one),
            several => Rig::load_files(several),
        }
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

    /// The world's up and where it came from: the declared one ([`Rig::declared_up`],
    /// from the calibration file or [`Rig::set_up`]) if any, else estimated from every
    /// camera's upright image up (see [`UpSource::Estimated`]'s `how`).
    pub fn world_up(&self) -> WorldUp {
        match &self.declared_up {
            Some(up) => up.clone(),
            None => up::estimate(&self.cameras),
        }
    }

    /// Sets the world's up as configured by the user (normalised); it travels with
    /// [`Rig::to_toml_string`]. Errors on a zero or non-finite vector.
    /// The cameras' mounts are then judged again under that up ([`Rig::infer_mounts`]).
    pub fn set_up(&mut self, direction: nalgebra::Vector3<f64>) -> Result<(), RigError> {
        self.declared_up = Some(WorldUp::declared(direction, UpSource::Configured)?);
        self.infer_mounts();
        Ok(())
    }

    /// The cameras' estimate of the world's up (as [`Rig::world_up`] makes it without a
    /// declared up) once every mount the file did not record is judged under `rough`, as
    /// [`Rig::set_up`] would judge it: a rough up picks the mounts, the calibrated rotations
    /// say precisely where up is. Changes and logs nothing; errors as [`Rig::set_up`] does.
    pub fn estimate_up_under(&self, rough: nalgebra::Vector3<f64>) -> Result<WorldUp, RigError> {
        let declared = WorldUp::declared(rough, UpSource::Configured)?;
        let (mut cameras, mut inferred) = (self.cameras.clone(), self.mounts_inferred.clone());
        up::infer_mounts(&mut cameras, &mut inferred, &declared);
        Ok(up::estimate(&cameras))
    }

    /// Sets each camera's [`Camera::mount_quarter_turns`] from the geometry where the file
    /// did not record one (most formats cannot: Pose2Sim's, anipose's, OpenCV's; a recorded
    /// mount is kept, one inferred before is judged again): the quarter turns that bring the
    /// world's up to the top of its frames. The
    /// face detector finds upright faces only, so a sideways camera whose mount is unknown
    /// sees no face. Judged only when most cameras agree with the world's up as they are
    /// (always with a declared up); a camera looking along the up, or rolled by about 45
    /// degrees, keeps its mount. Each change is logged and kept in [`Rig::notes`].
    pub fn infer_mounts(&mut self) {
        let up = self.world_up();
        for note in up::infer_mounts(&mut self.cameras, &mut self.mounts_inferred, &up) {
            tracing::info!("{note}");
            self.notes.push(note);
        }
    }

    /// Converts a calibration in millimetres to metres ([`units::millimetres_to_metres`]),
    /// logged and kept in [`Rig::notes`]. A rig in metres is left as it is.
    pub fn infer_units(&mut self) {
        if let Some(note) = units::millimetres_to_metres(&mut self.cameras) {
            tracing::warn!("{note}");
            self.notes.push(note);
        }
    }

    /// The camera called `name`, if any.
    pub fn camera(&self, name: &str) -> Option<&Camera> {
        self.cameras.iter().find(|camera| camera.name == name)
    }
}

/// The cameras of a calibration file as they are read, under their keys in the file: every
/// format refuses a name used twice and a file without cameras the same way.
#[derive(Default)]
pub(crate) struct CameraList {
    cameras: Vec<Camera>,
    keys: Vec<String>,
}

impl CameraList {
    /// Adds the camera read from the file's entry `key`, unless its name is taken.
    pub(crate) fn push(&mut self, key: &str, camera: Camera) -> Result<(), RigError> {
        if let Some(first) = self.cameras.iter().position(|c| c.name == camera.name) {
            return Err(RigError::Field {
                problem: format!(
                    "duplicate camera name `{}`, already used by camera `{}`",
                    camera.name, self.keys[first]
                ),
                camera: key.to_owned(),
                name: Some(camera.name),
                field: "name".to_owned(),
            });
        }
        self.cameras.push(camera);
        self.keys.push(key.to_owned());
        Ok(())
    }

    /// The cameras in file order; a file without any is an error.
    pub(crate) fn finish(self) -> Result<Vec<Camera>, RigError> {
        if self.cameras.is_empty() {
            return Err(RigError::NoCameras);
        }
        Ok(self.cameras)
    }
}
