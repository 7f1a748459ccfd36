//! Which calibration format a file is in, recognised from its content.

use std::fmt;

/// A calibration file format [`super::Rig::load`] reads.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[non_exhaustive]
pub enum RigFormat {
    /// The anipose / Pose2Sim / FreeMoCap TOML layout (ours): one table per camera.
    AniposeToml,
    /// caliscope's `camera_array.toml`: `[cameras.N]` tables.
    Caliscope,
    /// The project `config.toml` of older caliscope versions: `[cam_N]` tables with a `port`.
    CaliscopeConfig,
    /// OpenCV FileStorage YAML (`%YAML:1.0`, `!!opencv-matrix`).
    OpenCvYaml,
    /// OpenCV FileStorage XML (`<opencv_storage>`, `type_id="opencv-matrix"`).
    OpenCvXml,
}

impl RigFormat {
    /// Short human name of the format.
    pub fn name(self) -> &'static str {
        match self {
            RigFormat::AniposeToml => "anipose/Pose2Sim TOML",
            RigFormat::Caliscope => "caliscope camera_array.toml",
            RigFormat::CaliscopeConfig => "caliscope config.toml (older versions)",
            RigFormat::OpenCvYaml => "OpenCV FileStorage YAML",
            RigFormat::OpenCvXml => "OpenCV FileStorage XML",
        }
    }

    /// True for the OpenCV formats, which may hold one camera per file.
    pub fn is_opencv(self) -> bool {
        matches!(self, RigFormat::OpenCvYaml | RigFormat::OpenCvXml)
    }

    /// The format of `text` from its first lines: OpenCV YAML starts with a `%YAML`
    /// directive (or uses `!!opencv-matrix` tags), OpenCV XML with `<?xml` or
    /// `<opencv_storage>`; anything else is TOML, whose layout (anipose or caliscope's) is
    /// told apart when it is parsed, so this says [`RigFormat::AniposeToml`] for all.
    pub fn sniff(text: &str) -> RigFormat {
        let start = text.trim_start_matches('\u{feff}').trim_start();
        if start.starts_with("%YAML") || text.contains("!!opencv-matrix") {
            RigFormat::OpenCvYaml
        } else if start.starts_with("<?xml") || start.starts_with("<opencv_storage") {
            RigFormat::OpenCvXml
        } else {
            RigFormat::AniposeToml
        }
    }
}

impl fmt::Display for RigFormat {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}
