//! CSV with a header: frame, time, then per object (`head`, `left_hand`, `right_hand`)
//! position, velocity, confidence and state, one line per trajectory record.

use std::io::Write;

use anyhow::{Context, Result};
use handflow_protocol::messages::OBJECT_LABELS;
use handflow_publish::TrajectoryRecord;

/// Per-object columns, after `frame,t`.
const FIELDS: [&str; 8] = ["x", "y", "z", "vx", "vy", "vz", "confidence", "state"];

/// The header line: `frame,t,head_x,...,right_hand_state`.
pub fn csv_header() -> String {
    let mut header = String::from("frame,t");
    for label in OBJECT_LABELS {
        for field in FIELDS {
            header.push_str(&format!(",{label}_{field}"));
        }
    }
    header
}

/// One record as a CSV line (no newline).
pub fn csv_line(record: &TrajectoryRecord) -> Result<String> {
    let mut line = format!("{},{}", record.frame, record.t);
    for label in OBJECT_LABELS {
        let o = record.objects.get(label).with_context(|| format!("frame {}: no `{label}`", record.frame))?;
        let state = o.state.name();
        line.push_str(&format!(
            ",{},{},{},{},{},{},{},{state}",
            o.pos[0], o.pos[1], o.pos[2], o.vel[0], o.vel[1], o.vel[2], o.confidence
        ));
    }
    Ok(line)
}

/// Writes `records` as CSV with its header.
pub fn write_csv(records: &[TrajectoryRecord], out: &mut impl Write) -> Result<()> {
    writeln!(out, "{}", csv_header())?;
    for record in records {
        writeln!(out, "{}", csv_line(record)?)?;
    }
    out.flush()?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::export::tests::record;

    #[test]
    fn the_header_names_every_column_and_each_line_fills_them() {
        let mut bytes = Vec::new();
        write_csv(&[record(3), record(4)], &mut bytes).unwrap();
        let text = String::from_utf8(bytes).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        let header: Vec<&str> = lines[0].split(',').collect();
        assert_eq!(header.len(), 2 + 3 * 8);
        assert_eq!(&header[..4], ["frame", "t", "head_x", "head_y"]);
        assert_eq!(header[25], "right_hand_state");
        let first: Vec<&str> = lines[1].split(',').collect();
        assert_eq!(first.len(), header.len());
        assert_eq!((first[0], first[2], first[17]), ("3", "0.03", "lost"));
        assert_eq!(first[25], "predicted");
    }
}
