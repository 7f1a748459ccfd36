//! C3D (c3d.org), the binary marker file of biomechanics and animation packages: a 512-byte
//! header, parameter blocks (groups `POINT`, `ANALOG`, `TRIAL` with their parameters), then
//! per frame X Y Z and a residual word per marker, as 32-bit floats, little-endian (Intel).
//!
//! Written here rather than through a C3D crate: the one maintained Rust C3D library at the
//! time of writing (c3dio 0.8) panics when writing a file it did not read, and its float
//! writer cannot mark a point invalid. The tests read what this writes with c3dio and with
//! the Python `c3d` package.
//!
//! A marker's residual is `(1 - confidence) x 0.1 m` (0 at full confidence), in whole
//! millimetres (`POINT:SCALE` = -0.001: float data, residual unit 1 mm); a frame where a
//! marker was lost or skipped has it invalid (residual word -1, coordinates 0). Frames are
//! numbered from 1 at the first exported frame.

use std::io::Write;

use super::{MarkerSeries, MARKERS, MARKER_DESCRIPTIONS};

/// Residual written for confidence 0, metres.
pub const RESIDUAL_AT_ZERO_CONFIDENCE_M: f64 = 0.1;
/// `POINT:SCALE`: negative for float data; its magnitude is the residual's unit (metres).
const SCALE: f32 = -0.001;
const BLOCK: usize = 512;
const KEY: u8 = 0x50;
const INTEL: u8 = 84;

/// A parameter's data.
enum Data {
    Int(i16),
    Float(f32),
    Text(String),
    Texts(Vec<String>),
}

struct Group {
    id: i8,
    name: &'static str,
    description: &'static str,
    parameters: Vec<(&'static str, Data, &'static str)>,
}

/// Writes `series` as C3D.
pub fn write_c3d(series: &MarkerSeries, out: &mut impl Write) -> std::io::Result<()> {
    let frames = series.rows.len();
    let rate = series.rate_hz as f32;
    // The parameter section's size does not depend on the numbers in it: lay it out once
    // to learn where the data starts, then with that number.
    let blocks = parameter_section(series, 0).len() / BLOCK;
    let data_start = 2 + blocks;
    let parameters = parameter_section(series, data_start);

    let mut header = [0u8; BLOCK];
    header[0] = 2;
    header[1] = KEY;
    put_u16(&mut header, 2, MARKERS.len() as u16);
    put_u16(&mut header, 6, 1);
    put_u16(&mut header, 8, frames as u16);
    put_f32(&mut header, 12, SCALE);
    put_u16(&mut header, 16, data_start as u16);
    put_f32(&mut header, 20, rate);
    out.write_all(&header)?;
    out.write_all(&parameters)?;

    let mut data = Vec::with_capacity(frames * MARKERS.len() * 16);
    for row in &series.rows {
        for marker in row {
            let (position, residual) = match marker {
                Some(m) => {
                    let metres = (1.0 - m.confidence) * RESIDUAL_AT_ZERO_CONFIDENCE_M;
                    let units = (metres / f64::from(SCALE.abs())).round().clamp(0.0, 255.0);
                    (m.position.map(|v| v as f32), units as f32)
                }
                None => ([0.0; 3], -1.0),
            };
            for v in position.iter().chain([&residual]) {
                data.extend_from_slice(&v.to_le_bytes());
            }
        }
    }
    let padding = (BLOCK - data.len() % BLOCK) % BLOCK;
    data.resize(data.len() + padding, 0);
    out.write_all(&data)?;
    out.flush()
}

/// The parameter section, whole blocks, with `POINT:DATA_START` = `data_start`.
fn parameter_section(series: &MarkerSeries, data_start: usize) -> Vec<u8> {
    let frames = series.rows.len();
    let rate = series.rate_hz as f32;
    let groups = [
        Group {
            id: 1,
            name: "POINT",
            description: "3D point parameters",
            parameters: vec![
                ("USED", Data::Int(MARKERS.len() as i16), "markers per frame"),
                ("FRAMES", Data::Int(frames as u16 as i16), "frames"),
                ("DATA_START", Data::Int(data_start as i16), "first block of the data"),
                ("SCALE", Data::Float(SCALE), "float data; residual unit, metres"),
                ("RATE", Data::Float(rate), "frames per second"),
                ("UNITS", Data::Text("m".into()), "units of the coordinates"),
                ("LABELS", Data::Texts(MARKERS.iter().map(|m| m.to_string()).collect()), "marker names"),
                (
                    "DESCRIPTIONS",
                    Data::Texts(MARKER_DESCRIPTIONS.iter().map(|m| m.to_string()).collect()),
                    "what each marker is",
                ),
            ],
        },
        Group {
            id: 2,
            name: "ANALOG",
            description: "analog data",
            parameters: vec![
                ("USED", Data::Int(0), "no analog channels"),
                ("RATE", Data::Float(0.0), "no analog samples"),
                ("GEN_SCALE", Data::Float(1.0), "general scale"),
            ],
        },
        Group {
            id: 3,
            name: "TRIAL",
            description: "trial",
            parameters: vec![("CAMERA_RATE", Data::Float(rate), "frames per second of the cameras")],
        },
    ];
    let mut records: Vec<Vec<u8>> = Vec::new();
    for group in &groups {
        let mut r = name_bytes(group.name, -group.id);
        let body_len = 1 + group.description.len();
        r.extend_from_slice(&((2 + body_len) as i16).to_le_bytes());
        r.push(group.description.len() as u8);
        r.extend_from_slice(group.description.as_bytes());
        records.push(r);
    }
    for group in &groups {
        for (name, data, description) in &group.parameters {
            let (kind, dims, bytes): (i8, Vec<u8>, Vec<u8>) = match data {
                Data::Int(v) => (2, vec![], v.to_le_bytes().to_vec()),
                Data::Float(v) => (4, vec![], v.to_le_bytes().to_vec()),
                Data::Text(s) => (-1, vec![s.len() as u8], s.as_bytes().to_vec()),
                Data::Texts(list) => {
                    let width = list.iter().map(String::len).max().unwrap_or(1).max(1);
                    let bytes = list.iter().flat_map(|s| format!("{s:<width$}").into_bytes()).collect();
                    (-1, vec![width as u8, list.len() as u8], bytes)
                }
            };
            let mut r = name_bytes(name, group.id);
            let body_len = 2 + dims.len() + bytes.len() + 1 + description.len();
            r.extend_from_slice(&((2 + body_len) as i16).to_le_bytes());
            r.push(kind as u8);
            r.push(dims.len() as u8);
            r.extend_from_slice(&dims);
            r.extend_from_slice(&bytes);
            r.push(description.len() as u8);
            r.extend_from_slice(description.as_bytes());
            records.push(r);
        }
    }
    let mut section = vec![1, KEY, 0, INTEL];
    let count = records.len();
    for (k, mut record) in records.into_iter().enumerate() {
        if k + 1 == count {
            // The last record says so with a zero offset.
            let at = 2 + record[0] as usize;
            record[at..at + 2].copy_from_slice(&0i16.to_le_bytes());
        }
        section.extend_from_slice(&record);
    }
    // Zeros after the records end the list for readers that read on.
    section.extend_from_slice(&[0, 0]);
    let blocks = section.len().div_ceil(BLOCK);
    section.resize(blocks * BLOCK, 0);
    section[2] = blocks as u8;
    section
}

fn name_bytes(name: &str, id: i8) -> Vec<u8> {
    let mut r = vec![name.len() as u8, id as u8];
    r.extend_from_slice(name.as_bytes());
    r
}

fn put_u16(block: &mut [u8], at: usize, v: u16) {
    block[at..at + 2].copy_from_slice(&v.to_le_bytes());
}

fn put_f32(block: &mut [u8], at: usize, v: f32) {
    block[at..at + 4].copy_from_slice(&v.to_le_bytes());
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::export::tests::record;

    #[test]
    fn c3dio_reads_labels_rate_and_points_back() {
        let records: Vec<_> = [3, 4, 6].map(record).to_vec();
        let series = MarkerSeries::from_records(&records, None).unwrap();
        let mut bytes = Vec::new();
        write_c3d(&series, &mut bytes).unwrap();
        assert_eq!(bytes.len() % BLOCK, 0);
        let c3d = c3dio::C3d::from_bytes(&bytes).expect("c3dio parses it");
        assert_eq!(c3d.points.labels, MARKERS.map(String::from).to_vec());
        assert_eq!(c3d.points.frame_rate, 30.0);
        assert_eq!(c3d.points.size(), (4, 3), "four frames (one skipped) of three markers");
        let head = c3d.points[(1, 0)];
        assert_eq!(head.point, [0.04, 1.5, -0.25]);
        // Confidence 0.8: a residual of 2 cm.
        assert!((head.residual - 0.02).abs() < 1e-6, "{head:?}");
    }
}
