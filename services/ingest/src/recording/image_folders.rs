//! Writing a recording in the image-folder layout: `rig.toml`, `frames.csv` and one folder
//! of PNGs per camera (`handflow import`, and the synthetic renderer).

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use rayon::prelude::*;

use super::{Recording, RecordingError, FRAMES_FILE, RIG_FILE};

/// Why writing failed: the file and what went wrong.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum WriteError {
    /// A file or folder could not be written.
    #[error("writing `{path}`: {error}")]
    Io {
        /// The file.
        path: PathBuf,
        /// What went wrong.
        error: String,
    },
    /// The recording could not be read (other than one bad frame set).
    #[error("{0}")]
    Read(Box<RecordingError>),
}

/// What [`write_image_folders`] wrote.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ImageFoldersReport {
    /// Frame sets written.
    pub frame_sets: usize,
    /// Frame sets that could not be read, with the error of each (left out of
    /// `frames.csv`).
    pub skipped: Vec<String>,
}

/// Writes one PNG with fast compression and the Up filter: replaying a recording decodes
/// every frame, and such files decode 1.8x faster than the encoder's default (measured on
/// signer-3cam; the same pixels, files 3 % larger: sensor noise leaves little to compress).
/// Without a filter they decode 5x faster but are as large as the raw frames.
pub fn write_png(
    path: &Path,
    bytes: &[u8],
    w: u32,
    h: u32,
    colour: image::ExtendedColorType,
) -> Result<(), WriteError> {
    use image::codecs::png::{CompressionType, FilterType, PngEncoder};
    use image::ImageEncoder;
    let io = |error: String| WriteError::Io { path: path.to_path_buf(), error };
    let file = std::fs::File::create(path).map_err(|e| io(e.to_string()))?;
    let mut out = std::io::BufWriter::new(file);
    PngEncoder::new_with_quality(&mut out, CompressionType::Fast, FilterType::Up)
        .write_image(bytes, w, h, colour)
        .map_err(|e| io(e.to_string()))?;
    // Flushed here, so a full disk is an error rather than lost silently on drop.
    std::io::Write::flush(&mut out).map_err(|e| io(e.to_string()))
}

/// Writes every frame set of `rec` into `out` in the image-folder layout (the rig as read,
/// sizes as the frames have them; frame numbers and capture times kept). A frame set that
/// cannot be read is left out, reported in the result; `on_frame` hears of each one done.
pub fn write_image_folders(
    rec: &Recording,
    out: &Path,
    mut on_frame: impl FnMut(usize, usize),
) -> Result<ImageFoldersReport, WriteError> {
    let io = |path: &Path, error: String| WriteError::Io { path: path.to_path_buf(), error };
    let rig = rec.rig();
    for cam in &rig.cameras {
        let dir = out.join(&cam.name);
        std::fs::create_dir_all(&dir).map_err(|e| io(&dir, e.to_string()))?;
    }
    rig.save(out.join(RIG_FILE)).map_err(|e| io(&out.join(RIG_FILE), e.to_string()))?;
    let mut csv = String::from("frame,timestamp\n");
    let mut report = ImageFoldersReport::default();
    let mut buf = vec![0u8; rec.frame_set_len()];
    for (index, entry) in rec.frames().iter().enumerate() {
        match rec.read_frame_into(index as u64, false, &mut buf) {
            Ok(_) => {}
            Err(error) if error.is_bad_frame() => {
                tracing::error!("frame set {index} left out: {error}");
                report.skipped.push(error.to_string());
                continue;
            }
            Err(error) => return Err(WriteError::Read(Box::new(error))),
        }
        let name = format!("{:06}.png", entry.frame);
        rig.cameras.par_iter().zip(rec.views(&buf)).try_for_each(|(cam, view)| {
            write_png(&out.join(&cam.name).join(&name), view, cam.width, cam.height, image::ExtendedColorType::Rgb8)
        })?;
        // The shortest decimal that reads back as the same number: the imported recording
        // replays with exactly the times of the original.
        let _ = writeln!(csv, "{},{}", entry.frame, entry.timestamp);
        report.frame_sets += 1;
        on_frame(index + 1, rec.len());
    }
    std::fs::write(out.join(FRAMES_FILE), csv).map_err(|e| io(&out.join(FRAMES_FILE), e.to_string()))?;
    Ok(report)
}
