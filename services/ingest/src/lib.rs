//! handflow's camera-ingest stage: getting camera images into frame buffers.
//!
//! Image decoding (a PNG, JPEG, PPM or BMP file decoded as RGB8 straight into a
//! caller-provided buffer, which will be a loaned shared-memory sample, with errors that name
//! the file) and [`recording`]s: folders of per-camera images or videos with a calibration and
//! capture times, checked on opening and read as synchronised frame sets, cameras decoded in
//! parallel (videos through GStreamer, [`recording::video`]).

#![cfg_attr(test, allow(clippy::unwrap_used))]

use std::path::{Path, PathBuf};

pub mod camera_match;
pub mod live;
pub mod recording;
pub mod synthetic;

pub use recording::{FrameEntry, FrameInfo, Layout, OpenOptions, Recording, RecordingError};

/// Why an image could not be ingested.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum IngestError {
    /// The file could not be opened or decoded.
    #[error("image `{path}`: {source}")]
    Decode {
        /// The file.
        path: PathBuf,
        /// What the decoder said.
        source: image::ImageError,
    },
    /// The image does not have the size the caller (the rig) expects.
    #[error("image `{path}`: size {got_width}x{got_height}, expected {width}x{height}")]
    Size {
        /// The file.
        path: PathBuf,
        /// Expected width.
        width: u32,
        /// Expected height.
        height: u32,
        /// Actual width.
        got_width: u32,
        /// Actual height.
        got_height: u32,
    },
    /// The destination buffer has the wrong length.
    #[error("image `{path}`: destination holds {got} bytes, {expected} needed for RGB8")]
    Buffer {
        /// The file.
        path: PathBuf,
        /// Needed bytes.
        expected: usize,
        /// Buffer length.
        got: usize,
    },
}

/// Decodes `path` as RGB8 into `dst` (exactly `width * height * 3` bytes), refusing an image
/// of another size. Whatever the file's colour type, `dst` receives interleaved RGB.
pub fn decode_rgb8_into(path: &Path, width: u32, height: u32, dst: &mut [u8]) -> Result<(), IngestError> {
    let expected = width as usize * height as usize * 3;
    if dst.len() != expected {
        return Err(IngestError::Buffer { path: path.to_path_buf(), expected, got: dst.len() });
    }
    let decoded = image::open(path).map_err(|source| IngestError::Decode { path: path.to_path_buf(), source })?;
    if decoded.width() != width || decoded.height() != height {
        return Err(IngestError::Size {
            path: path.to_path_buf(),
            width,
            height,
            got_width: decoded.width(),
            got_height: decoded.height(),
        });
    }
    match decoded {
        // The common case needs no conversion buffer.
        image::DynamicImage::ImageRgb8(rgb) => dst.copy_from_slice(rgb.as_raw()),
        other => dst.copy_from_slice(other.to_rgb8().as_raw()),
    }
    Ok(())
}

/// Decodes `path` as RGB8 into a new buffer; returns `(width, height, pixels)`.
pub fn read_rgb8(path: &Path) -> Result<(u32, u32, Vec<u8>), IngestError> {
    let decoded = image::open(path).map_err(|source| IngestError::Decode { path: path.to_path_buf(), source })?;
    let rgb = decoded.into_rgb8();
    Ok((rgb.width(), rgb.height(), rgb.into_raw()))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write_png(dir: &Path, name: &str, w: u32, h: u32) -> PathBuf {
        let img = image::RgbImage::from_fn(w, h, |x, y| image::Rgb([x as u8, y as u8, 7]));
        let path = dir.join(name);
        img.save(&path).expect("write png");
        path
    }

    #[test]
    fn decodes_into_the_callers_buffer() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = write_png(dir.path(), "a.png", 4, 3);
        let mut buf = vec![0u8; 4 * 3 * 3];
        decode_rgb8_into(&path, 4, 3, &mut buf).expect("decodes");
        assert_eq!(&buf[..6], &[0, 0, 7, 1, 0, 7]);
        assert_eq!(read_rgb8(&path).expect("reads").2, buf);
    }

    #[test]
    fn refuses_wrong_size_wrong_buffer_and_garbage_naming_the_file() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = write_png(dir.path(), "b.png", 4, 3);
        let mut buf = vec![0u8; 5 * 3 * 3];
        let err = decode_rgb8_into(&path, 5, 3, &mut buf).unwrap_err().to_string();
        assert!(err.contains("b.png") && err.contains("4x3") && err.contains("5x3"), "{err}");
        let err = decode_rgb8_into(&path, 4, 3, &mut buf).unwrap_err().to_string();
        assert!(err.contains("destination"), "{err}");
        let garbage = dir.path().join("c.png");
        std::fs::write(&garbage, b"not an image").expect("write");
        let mut buf = vec![0u8; 36];
        let err = decode_rgb8_into(&garbage, 4, 3, &mut buf).unwrap_err().to_string();
        assert!(err.contains("c.png"), "{err}");
    }
}
