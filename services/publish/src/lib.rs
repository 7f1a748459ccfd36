//! handflow's trajectory-publisher stage: trajectory records and their file sinks.
//!
//! For now this is the record of one frame's trajectory estimates and the JSON Lines sink
//! that writes them, one object per frame; shared-memory publishing builds on it.

#![cfg_attr(test, allow(clippy::unwrap_used))]

use std::collections::BTreeMap;
use std::io::Write;

use serde::{Deserialize, Serialize};

/// Tracking state of one object.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TrackState {
    /// Measured this frame.
    Tracked,
    /// Extrapolated by the motion model.
    Predicted,
    /// No usable estimate.
    Lost,
}

/// One object's estimate at one frame.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ObjectSample {
    /// World position, metres.
    pub pos: [f64; 3],
    /// World velocity, metres per second.
    pub vel: [f64; 3],
    /// Confidence in [0, 1].
    pub confidence: f64,
    /// Tracking state.
    pub state: TrackState,
}

/// Every object's estimate at one frame: one line of the trajectory file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrajectoryRecord {
    /// Frame number.
    pub frame: u64,
    /// Capture time, seconds.
    pub t: f64,
    /// Objects by label (`head`, `left_hand`, `right_hand`).
    pub objects: BTreeMap<String, ObjectSample>,
}

/// Writes records as JSON Lines, one object per line, flushed per record so a reader
/// following the file sees whole lines.
pub struct JsonLinesSink<W: Write> {
    out: W,
}

impl<W: Write> JsonLinesSink<W> {
    /// A sink writing to `out`.
    pub fn new(out: W) -> Self {
        Self { out }
    }

    /// Appends one record.
    pub fn write(&mut self, record: &TrajectoryRecord) -> std::io::Result<()> {
        serde_json::to_writer(&mut self.out, record)?;
        self.out.write_all(b"\n")?;
        self.out.flush()
    }

    /// The underlying writer.
    pub fn into_inner(self) -> W {
        self.out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn records_are_one_json_object_per_line_with_the_documented_keys() {
        let mut objects = BTreeMap::new();
        objects.insert(
            "head".to_string(),
            ObjectSample { pos: [0.0, 1.6, 2.0], vel: [0.0; 3], confidence: 0.9, state: TrackState::Tracked },
        );
        objects.insert(
            "left_hand".to_string(),
            ObjectSample { pos: [0.2, 1.0, 1.8], vel: [0.1, 0.0, 0.0], confidence: 0.5, state: TrackState::Predicted },
        );
        let mut sink = JsonLinesSink::new(Vec::new());
        sink.write(&TrajectoryRecord { frame: 0, t: 0.0, objects: objects.clone() }).expect("write");
        sink.write(&TrajectoryRecord { frame: 1, t: 1.0 / 30.0, objects }).expect("write");
        let text = String::from_utf8(sink.into_inner()).expect("utf8");
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines.len(), 2);
        let v: serde_json::Value = serde_json::from_str(lines[1]).expect("json");
        assert_eq!(v["frame"], 1);
        assert_eq!(v["objects"]["head"]["state"], "tracked");
        assert_eq!(v["objects"]["left_hand"]["state"], "predicted");
        assert_eq!(v["objects"]["left_hand"]["pos"][0], 0.2);
        let back: TrajectoryRecord = serde_json::from_str(lines[0]).expect("round trip");
        assert_eq!(back.objects.len(), 2);
    }
}
