//! Image-folder recordings: one folder of numbered images per camera.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use super::RecordingError;

/// The images of one camera folder, by frame number.
pub(super) fn camera_images(dir: &Path, camera: &str) -> Result<BTreeMap<u64, PathBuf>, RecordingError> {
    let folder = dir.join(camera);
    let entries = std::fs::read_dir(&folder)
        .map_err(|_| RecordingError::CameraFolder { dir: dir.to_path_buf(), camera: camera.to_string() })?;
    let mut images = BTreeMap::new();
    for entry in entries {
        let entry = entry.map_err(|error| RecordingError::Folder { dir: folder.clone(), error })?;
        let path = entry.path();
        let ext = path.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase);
        if !matches!(ext.as_deref(), Some("png" | "jpg" | "jpeg")) {
            continue; // masks, notes and other files live beside the images
        }
        let extra = |problem: String| RecordingError::ExtraImage {
            dir: dir.to_path_buf(),
            camera: camera.to_string(),
            file: file_name(&path),
            problem,
        };
        let Some(frame) = frame_number(&path) else {
            return Err(extra("has no frame number in its name".into()));
        };
        if let Some(other) = images.insert(frame, path.clone()) {
            return Err(extra(format!("is frame {frame}, as is `{}`", file_name(&other))));
        }
    }
    Ok(images)
}

/// The last run of digits in a file's stem (`frame_é0012.png` is 12), read as a camera's
/// number is.
pub(super) fn frame_number(path: &Path) -> Option<u64> {
    crate::camera_match::camera_number(path.file_stem()?.to_str()?)
}

pub(super) fn file_name(path: &Path) -> String {
    path.file_name().map_or_else(|| path.display().to_string(), |n| n.to_string_lossy().into_owned())
}
