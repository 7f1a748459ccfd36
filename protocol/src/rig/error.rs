//! Errors from building, reading and writing rigs.

use std::fmt;
use std::path::PathBuf;

/// Why a rig or camera could not be built, read or written.
///
/// Every message is self-contained (it already includes the underlying cause),
/// so the variants deliberately do not chain a `source()`: printing the chain
/// would repeat the cause.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum RigError {
    /// A camera's field is missing, has the wrong shape or an invalid value.
    #[error("{}, field `{field}`: {problem}", CameraLabel { camera, name: name.as_deref() })]
    Field {
        /// Which camera: its table key when read from a file (`cam_1`),
        /// otherwise its name.
        camera: String,
        /// The camera's `name`, when it is known and differs from `camera`.
        name: Option<String>,
        /// The field, spelled as in the file (`matrix`, `distortions`, ...).
        field: String,
        /// What is wrong with it.
        problem: String,
    },
    /// A top-level entry of the rig file is not a camera table.
    #[error("top-level key `{key}`: expected a camera table, found {found}")]
    NotATable {
        /// The offending key.
        key: String,
        /// The TOML type found instead (`integer`, `string`, ...).
        found: String,
    },
    /// An up direction (declared in a file's `metadata` table or set by the user) is not
    /// a direction.
    #[error("up direction: {problem}")]
    Up {
        /// What is wrong with it.
        problem: String,
    },
    /// A field of the rig file's `metadata` table has the wrong shape or value.
    #[error("table `metadata`, field `{field}`: {problem}")]
    Metadata {
        /// The field, spelled as in the file (`up`, `up_source`).
        field: String,
        /// What is wrong with it.
        problem: String,
    },
    /// The rig has no cameras.
    #[error("the rig has no cameras (expected one table per camera, e.g. `[cam_0]`)")]
    NoCameras,
    /// The text is not valid TOML.
    #[error("TOML syntax error{}: {message}", Location { line: *line, column: *column })]
    Syntax {
        /// 1-based line of the error, when toml reports where it is.
        line: Option<usize>,
        /// 1-based column (in characters) of the error, when known.
        column: Option<usize>,
        /// toml's description of the error.
        message: String,
    },
    /// The text is not valid in its format (OpenCV YAML or XML).
    #[error("{format} syntax error at line {line}: {message}")]
    FormatSyntax {
        /// `OpenCV YAML` or `OpenCV XML`.
        format: &'static str,
        /// 1-based line of the error.
        line: usize,
        /// What is wrong.
        message: String,
    },
    /// Reading or writing the rig file failed.
    #[error("cannot {action} rig file `{}`: {error}", path.display())]
    Io {
        /// `read`, `write` or `list` (a folder).
        action: &'static str,
        /// The file.
        path: PathBuf,
        /// The underlying error.
        error: std::io::Error,
    },
    /// A folder has no calibration [`super::Rig::find_in_dir`] can choose.
    #[error(
        "no calibration found in `{}`: expected rig.toml, camera_array.toml, a single calibration file \
         (*.toml, *.yml, *.yaml, *.xml) or OpenCV files one per camera; {}",
        dir.display(),
        if found.is_empty() { "found no calibration files".to_owned() } else { format!("found {}", found.join(", ")) }
    )]
    NoCalibration {
        /// The folder.
        dir: PathBuf,
        /// What it holds that looks like calibration, each file with its format or why it
        /// does not fit (`a.toml (anipose/Pose2Sim TOML)`).
        found: Vec<String>,
    },
    /// Two files of one rig define a camera of the same name.
    #[error("camera `{name}` is defined both in `{}` and in `{}`", first.display(), second.display())]
    DuplicateCamera {
        /// The camera's name.
        name: String,
        /// The file that defined it first.
        first: PathBuf,
        /// The file that defined it again.
        second: PathBuf,
    },
    /// Any other error, found in the rig file at `path`.
    #[error("rig file `{}`: {error}", path.display())]
    InFile {
        /// The file.
        path: PathBuf,
        /// What is wrong in it.
        error: Box<RigError>,
    },
}

impl RigError {
    /// Shorthand for [`RigError::Field`] on a camera known only by its name.
    pub(crate) fn field(camera: &str, field: &str, problem: impl Into<String>) -> RigError {
        RigError::Field { camera: camera.to_owned(), name: None, field: field.to_owned(), problem: problem.into() }
    }
}

/// "camera `cam_1` (name `left`)" or "camera `left`".
struct CameraLabel<'a> {
    camera: &'a str,
    name: Option<&'a str>,
}

impl fmt::Display for CameraLabel<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "camera `{}`", self.camera)?;
        match self.name {
            Some(name) if name != self.camera => write!(f, " (name `{name}`)"),
            _ => Ok(()),
        }
    }
}

/// " at line 3, column 7", or nothing when toml gave no position.
struct Location {
    line: Option<usize>,
    column: Option<usize>,
}

impl fmt::Display for Location {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match (self.line, self.column) {
            (Some(line), Some(column)) => write!(f, " at line {line}, column {column}"),
            (Some(line), None) => write!(f, " at line {line}"),
            _ => Ok(()),
        }
    }
}
