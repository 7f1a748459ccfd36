//! The wire of handflow: what the services agree on.
//!
//! The rig calibration: [`Camera`] (OpenCV pinhole model with
//! k1 k2 p1 p2 k3 distortion, world-to-camera pose) and [`Rig`] with its TOML
//! file format (the per-camera tables written by anipose and Pose2Sim).
//! [`messages`] are the zero-copy message types the stages exchange and [`ipc`] the
//! services they travel on (names, settings per delivery mode, ports); [`wire`] is the same
//! messages as bytes for networks. [`isa`] runs the services' hot loops with AVX2 where the
//! CPU has it, to the same bits.
//!
//! Conventions (see DESIGN.md, "Coordinates and units"): the world frame is
//! right-handed in metres, `x_cam = R x_world + t`, and pixels are `K` applied
//! to the distorted normalised point `(x/z, y/z)`.

#![cfg_attr(test, allow(clippy::unwrap_used))]

pub mod ipc;
pub mod isa;
pub mod messages;
pub mod records;
pub mod rig;
pub mod unfinished_shm;
pub mod wire;

/// Text files read from outside (calibrations, frame tables, pipeline and scene files) are
/// refused above this size before anything is allocated: the largest real one is a few
/// hundred kilobytes.
pub const MAX_TEXT_FILE_BYTES: u64 = 64 << 20;

/// Reads a text file of at most [`MAX_TEXT_FILE_BYTES`]; a larger one is an `InvalidData`
/// error saying its size.
pub fn read_text_capped(path: &std::path::Path) -> std::io::Result<String> {
    let size = std::fs::metadata(path)?.len();
    if size > MAX_TEXT_FILE_BYTES {
        return Err(std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!("{size} bytes, more than the {MAX_TEXT_FILE_BYTES} read from such a file"),
        ));
    }
    std::fs::read_to_string(path)
}

pub use rig::{Camera, Distortion, Fisheye, Ray, Rig, RigError, RigFormat, UpSource, WorldUp};

#[cfg(test)]
mod tests {
    #[test]
    fn a_text_file_over_the_cap_is_refused_by_its_size_before_it_is_read() {
        let dir = tempfile::tempdir().expect("temp dir");
        let path = dir.path().join("huge.toml");
        let file = std::fs::File::create(&path).expect("create");
        // Sparse: no disk is used.
        file.set_len(super::MAX_TEXT_FILE_BYTES + 1).expect("set_len");
        let e = super::read_text_capped(&path).expect_err("refused");
        assert_eq!(e.kind(), std::io::ErrorKind::InvalidData);
        assert!(e.to_string().contains("bytes"), "{e}");
        std::fs::write(&path, "a = 1\n").expect("write");
        assert_eq!(super::read_text_capped(&path).expect("read"), "a = 1\n");
    }
}
