//! TRC, the marker file of Motion Analysis that OpenSim and Pose2Sim read: five header
//! lines, then per frame its number, its time and X Y Z of each marker, tab-separated. A
//! marker without a position leaves its three fields empty, which OpenSim reads as missing.

use std::io::Write;

use super::{MarkerSeries, MARKERS};

/// Writes `series` as TRC; `file_name` goes in the first line, as OpenSim's writer puts it.
pub fn write_trc(series: &MarkerSeries, file_name: &str, out: &mut impl Write) -> std::io::Result<()> {
    let frames = series.rows.len();
    // Micro-hertz: a rate implied by capture times prints without float noise.
    let rate = (series.rate_hz * 1e6).round() / 1e6;
    writeln!(out, "PathFileType\t4\t(X/Y/Z)\t{file_name}")?;
    writeln!(
        out,
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames"
    )?;
    writeln!(out, "{rate}\t{rate}\t{frames}\t{}\tm\t{rate}\t{}\t{frames}", MARKERS.len(), series.first_frame)?;
    let names: Vec<String> = MARKERS.iter().map(|m| format!("{m}\t\t")).collect();
    writeln!(out, "Frame#\tTime\t{}", names.join("\t"))?;
    let axes: Vec<String> = (1..=MARKERS.len()).map(|k| format!("X{k}\tY{k}\tZ{k}")).collect();
    writeln!(out, "\t\t{}", axes.join("\t"))?;
    writeln!(out)?;
    for (k, row) in series.rows.iter().enumerate() {
        write!(out, "{}\t{:.6}", series.first_frame + k as u64, series.time_s(k))?;
        for marker in row {
            match marker {
                Some(m) => write!(out, "\t{:.6}\t{:.6}\t{:.6}", m.position[0], m.position[1], m.position[2])?,
                None => write!(out, "\t\t\t")?,
            }
        }
        writeln!(out)?;
    }
    out.flush()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::export::tests::record;

    #[test]
    fn the_header_names_rate_frames_markers_and_units_and_rows_follow_it() {
        let records: Vec<_> = [3, 4, 6].map(record).to_vec();
        let series = MarkerSeries::from_records(&records, None).unwrap();
        let mut bytes = Vec::new();
        write_trc(&series, "take.trc", &mut bytes).unwrap();
        let text = String::from_utf8(bytes).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines[0], "PathFileType\t4\t(X/Y/Z)\ttake.trc");
        assert_eq!(lines[2].split('\t').collect::<Vec<_>>(), ["30", "30", "4", "3", "m", "30", "3", "4"]);
        assert_eq!(
            lines[3].split('\t').filter(|f| !f.is_empty()).collect::<Vec<_>>(),
            ["Frame#", "Time", "Head", "LHand", "RHand"]
        );
        assert_eq!(lines[4].split('\t').count(), 2 + 9);
        assert!(lines[5].is_empty());
        // Every data row has 2 + 9 fields, blank where a marker is missing.
        let rows = &lines[6..];
        assert_eq!(rows.len(), 4);
        assert!(rows.iter().all(|r| r.split('\t').count() == 11), "{rows:?}");
        assert_eq!(
            &rows[1].split('\t').collect::<Vec<_>>()[..5],
            ["4", "0.133333", "0.040000", "1.500000", "-0.250000"]
        );
        assert_eq!(rows[2], "5\t0.166667\t\t\t\t\t\t\t\t\t", "a skipped frame");
        assert_eq!(rows[0].split('\t').nth(5), Some(""), "the left hand is lost at frame 3");
    }
}
