//! Portable Float Map, the float image format of the Middlebury and scene-flow benchmarks:
//! `Pf` (1 channel) or `PF` (3 channels), `width height`, a scale whose sign gives the byte
//! order (negative: little-endian), then rows of `f32` from bottom to top.

use std::fs;
use std::io::{self, Write};
use std::path::Path;

fn invalid(path: &Path, reason: impl std::fmt::Display) -> io::Error {
    io::Error::new(io::ErrorKind::InvalidData, format!("`{}`: {reason}", path.display()))
}

/// Writes `data` (row-major from the top row, channels interleaved) as a little-endian PFM.
/// `channels` must be 1 or 3 and `data` hold `width * height * channels` values.
pub fn write_pfm(path: &Path, width: u32, height: u32, channels: usize, data: &[f32]) -> io::Result<()> {
    let magic = match channels {
        1 => "Pf",
        3 => "PF",
        _ => {
            let reason = format!("PFM holds 1 or 3 channels, not {channels}");
            return Err(io::Error::new(io::ErrorKind::InvalidInput, format!("`{}`: {reason}", path.display())));
        }
    };
    let row = width as usize * channels;
    if data.len() != row * height as usize {
        let reason = format!("{} values for {width}x{height}x{channels}", data.len());
        return Err(io::Error::new(io::ErrorKind::InvalidInput, format!("`{}`: {reason}", path.display())));
    }
    let mut bytes = Vec::with_capacity(32 + data.len() * 4);
    bytes.extend_from_slice(format!("{magic}\n{width} {height}\n-1.0\n").as_bytes());
    // row > 0 unless the image is empty, when there is nothing to write.
    for line in data.chunks(row.max(1)).rev() {
        for v in line {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
    }
    let mut file = fs::File::create(path)?;
    file.write_all(&bytes)?;
    file.flush()
}

/// Reads a PFM: `(width, height, channels, data)`, data row-major from the top row with
/// channels interleaved. Either byte order; malformed files are `InvalidData` errors.
pub fn read_pfm(path: &Path) -> io::Result<(u32, u32, usize, Vec<f32>)> {
    let bytes = fs::read(path)?;
    let mut pos = 0usize;
    let channels = match next_token(&bytes, &mut pos) {
        Some(b"Pf") => 1,
        Some(b"PF") => 3,
        _ => return Err(invalid(path, "not a PFM (no `Pf` or `PF` magic)")),
    };
    let width: u32 = header_field(&bytes, &mut pos, path, "width")?;
    let height: u32 = header_field(&bytes, &mut pos, path, "height")?;
    let scale: f64 = header_field(&bytes, &mut pos, path, "scale")?;
    if scale == 0.0 || !scale.is_finite() {
        return Err(invalid(path, format!("PFM scale {scale} (its sign gives the byte order)")));
    }
    // Exactly one whitespace byte separates the header from the samples.
    if !bytes.get(pos).is_some_and(u8::is_ascii_whitespace) {
        return Err(invalid(path, "PFM header not followed by whitespace"));
    }
    let data = &bytes[pos + 1..];
    let row = width as usize * channels;
    let expected = row.checked_mul(height as usize).and_then(|n| n.checked_mul(4));
    if expected != Some(data.len()) {
        return Err(invalid(path, format!("{} bytes of samples for {width}x{height}x{channels} floats", data.len())));
    }
    let little = scale < 0.0;
    let values: Vec<f32> = data
        .chunks_exact(4)
        .map(|c| {
            let b = [c[0], c[1], c[2], c[3]];
            if little {
                f32::from_le_bytes(b)
            } else {
                f32::from_be_bytes(b)
            }
        })
        .collect();
    let top_first = values.chunks(row.max(1)).rev().flatten().copied().collect();
    Ok((width, height, channels, top_first))
}

/// The next whitespace-separated header token from `pos`, advancing `pos` past it.
fn next_token<'a>(bytes: &'a [u8], pos: &mut usize) -> Option<&'a [u8]> {
    while bytes.get(*pos).is_some_and(u8::is_ascii_whitespace) {
        *pos += 1;
    }
    let start = *pos;
    while bytes.get(*pos).is_some_and(|b| !b.is_ascii_whitespace()) {
        *pos += 1;
    }
    (*pos > start).then(|| &bytes[start..*pos])
}

/// The next header token parsed as `T`.
fn header_field<T: std::str::FromStr>(bytes: &[u8], pos: &mut usize, path: &Path, name: &str) -> io::Result<T> {
    next_token(bytes, pos)
        .and_then(|t| std::str::from_utf8(t).ok())
        .and_then(|t| t.parse().ok())
        .ok_or_else(|| invalid(path, format!("PFM header without a valid {name}")))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_one_and_three_channels() {
        let dir = tempfile::tempdir().expect("tempdir");
        for channels in [1usize, 3] {
            let (w, h) = (5u32, 3u32);
            let mut data: Vec<f32> = (0..w as usize * h as usize * channels).map(|i| i as f32 * 0.5 - 3.0).collect();
            data[1] = f32::NAN;
            data[2] = f32::INFINITY;
            let path = dir.path().join(format!("map{channels}.pfm"));
            write_pfm(&path, w, h, channels, &data).expect("write");
            let (rw, rh, rc, back) = read_pfm(&path).expect("read");
            assert_eq!((rw, rh, rc), (w, h, channels));
            assert_eq!(back.len(), data.len());
            for (a, b) in back.iter().zip(&data) {
                assert!(a == b || (a.is_nan() && b.is_nan()), "{a} != {b}");
            }
        }
    }

    #[test]
    fn rows_are_stored_bottom_to_top_little_endian() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("rows.pfm");
        write_pfm(&path, 1, 2, 1, &[1.0, 2.0]).expect("write");
        let bytes = fs::read(&path).expect("read");
        let header = b"Pf\n1 2\n-1.0\n";
        assert_eq!(&bytes[..header.len()], header);
        assert_eq!(&bytes[header.len()..], [2.0f32.to_le_bytes(), 1.0f32.to_le_bytes()].concat());
    }

    #[test]
    fn big_endian_files_are_read() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("be.pfm");
        let mut bytes = b"Pf\n2 1\n1.0\n".to_vec();
        bytes.extend_from_slice(&[1.5f32.to_be_bytes(), (-2.0f32).to_be_bytes()].concat());
        fs::write(&path, bytes).expect("write");
        assert_eq!(read_pfm(&path).expect("read"), (2, 1, 1, vec![1.5, -2.0]));
    }

    #[test]
    fn malformed_files_are_errors() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("bad.pfm");
        for bytes in
            [&b"P6\n1 1\n255\nabc"[..], b"Pf\n2 2\n-1.0\n\0\0\0\0", b"Pf\nx 1\n-1.0\n", b"Pf\n1 1\n0\n\0\0\0\0", b""]
        {
            fs::write(&path, bytes).expect("write");
            let err = read_pfm(&path).expect_err("malformed");
            assert_eq!(err.kind(), io::ErrorKind::InvalidData);
            assert!(err.to_string().contains("bad.pfm"), "{err}");
        }
        assert_eq!(write_pfm(&path, 1, 1, 2, &[0.0, 0.0]).expect_err("2 channels").kind(), io::ErrorKind::InvalidInput);
        assert_eq!(write_pfm(&path, 2, 1, 1, &[0.0]).expect_err("short").kind(), io::ErrorKind::InvalidInput);
    }
}
