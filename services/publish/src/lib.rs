//! handflow's trajectory-publisher stage: labelled clusters become trajectory samples for
//! subscribers and records for files.
//!
//! [`TrajectoryRecord`] is one frame's estimates as the JSON Lines file holds them,
//! [`JsonLinesSink`] writes them, [`trajectory_sample`] turns a frame's labelled clusters
//! into the sample subscribers receive, and [`SequenceGaps`] counts the frames lost
//! upstream from the gaps in the ingest sequence. [`viewer`] serves the live viewer page;
//! [`drawing`] draws trajectories on camera images; [`file`] keeps the JSON Lines file whole
//! through restarts and a full disk.

#![cfg_attr(test, allow(clippy::unwrap_used))]

pub mod drawing;
pub mod file;
pub mod latency;
pub mod viewer;

use std::collections::BTreeMap;
use std::io::Write;

use handflow_protocol::messages::{ClusterSet, TrajectoryObject, TrajectorySample, PROTOCOL_VERSION};
use serde::{Deserialize, Serialize};

pub use handflow_protocol::records::{ObjectSample, TrackState};

/// Every object's estimate at one frame: one line of the trajectory file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrajectoryRecord {
    /// Frame number.
    pub frame: u64,
    /// Capture time, seconds.
    pub t: f64,
    /// Objects by label (`head`, `left_hand`, `right_hand`).
    pub objects: BTreeMap<String, ObjectSample>,
    /// Frame sets lost before this one since the stream began (unreadable, or dropped by a
    /// stage); files written before this field existed read as 0.
    #[serde(default)]
    pub dropped_frames: u64,
    /// Cameras (bit k: camera k) whose view this frame set went without (a live camera that
    /// stopped or fell behind); absent, and 0, when every camera contributed.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub missing_views: u32,
}

fn is_zero(v: &u32) -> bool {
    *v == 0
}

impl TrajectoryRecord {
    /// The record of a trajectory sample.
    pub fn from_sample(sample: &TrajectorySample) -> Self {
        let objects = handflow_protocol::records::objects_by_label(&sample.objects);
        Self {
            frame: sample.frame,
            t: sample.timestamp_s,
            objects,
            dropped_frames: sample.dropped_frames,
            missing_views: sample.missing_views,
        }
    }
}

/// The trajectory sample of a frame's labelled clusters.
pub fn trajectory_sample(set: &ClusterSet, dropped_frames: u64, published_unix_ns: u64) -> TrajectorySample {
    TrajectorySample {
        protocol_version: PROTOCOL_VERSION,
        flags: set.flags,
        sequence: set.sequence,
        frame: set.frame,
        timestamp_s: set.timestamp_s,
        capture_unix_ns: set.capture_unix_ns,
        published_unix_ns,
        dropped_frames,
        missing_views: set.missing_views,
        reserved: 0,
        objects: set.objects.map(|c| TrajectoryObject {
            position: c.position,
            velocity: c.velocity,
            confidence: c.confidence,
            state: c.state,
            reserved: 0,
        }),
    }
}

/// Frames lost upstream, from the ingest sequence numbers that reach the last stage. Every
/// frame of a stream has an estimate, its first (sequence 0) included, so counting expects
/// sequence 0 first.
#[derive(Clone, Debug)]
pub struct SequenceGaps {
    next: Option<u64>,
    lost: u64,
}

impl Default for SequenceGaps {
    fn default() -> Self {
        Self { next: Some(0), lost: 0 }
    }
}

impl SequenceGaps {
    /// Counting that goes on where a previous publisher left it: `next` expected, `lost`
    /// frames counted so far (a restarted publisher neither counts the frames published
    /// before it as lost nor forgets the earlier losses).
    pub fn continuing(next: u64, lost: u64) -> Self {
        Self { next: Some(next), lost }
    }

    /// The next sequence expected.
    pub fn next(&self) -> u64 {
        self.next.unwrap_or(0)
    }

    /// Notes sequence `sequence` arriving; returns the sequences lost just before it.
    pub fn arrive(&mut self, sequence: u64) -> std::ops::Range<u64> {
        let gap = match self.next {
            Some(next) if sequence > next => next..sequence,
            _ => sequence..sequence,
        };
        self.lost += gap.end - gap.start;
        self.next = Some(self.next.map_or(sequence + 1, |n| n.max(sequence + 1)));
        gap
    }

    /// Frames lost so far.
    pub fn lost(&self) -> u64 {
        self.lost
    }
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

    /// Appends one record, as one write of the whole line: a process killed meanwhile
    /// leaves the line whole or absent.
    pub fn write(&mut self, record: &TrajectoryRecord) -> std::io::Result<()> {
        self.write_line(&Self::line(record)?)
    }

    /// A record's line, newline included.
    pub fn line(record: &TrajectoryRecord) -> std::io::Result<Vec<u8>> {
        let mut line = serde_json::to_vec(record)?;
        line.push(b'\n');
        Ok(line)
    }

    /// Appends a line made by [`JsonLinesSink::line`], as one write.
    pub fn write_line(&mut self, line: &[u8]) -> std::io::Result<()> {
        self.out.write_all(line)?;
        self.out.flush()
    }

    /// The underlying writer, borrowed.
    pub fn get_ref(&self) -> &W {
        &self.out
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
    fn sequence_gaps_report_exactly_the_missing_sequences() {
        let mut gaps = SequenceGaps::default();
        assert_eq!(gaps.arrive(0), 0..0);
        assert_eq!(gaps.arrive(1), 1..1);
        assert_eq!(gaps.arrive(2), 2..2);
        assert_eq!(gaps.arrive(6), 3..6);
        // Late or repeated sequences are not losses.
        assert_eq!(gaps.arrive(4), 4..4);
        assert_eq!(gaps.arrive(7), 7..7);
        assert_eq!(gaps.lost(), 3);
        let mut late_start = SequenceGaps::default();
        assert_eq!(late_start.arrive(19), 0..19);
    }

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
        sink.write(&TrajectoryRecord {
            frame: 0,
            t: 0.0,
            objects: objects.clone(),
            dropped_frames: 0,
            missing_views: 0,
        })
        .expect("write");
        sink.write(&TrajectoryRecord { frame: 1, t: 1.0 / 30.0, objects, dropped_frames: 0, missing_views: 0 })
            .expect("write");
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
