//! The JSON forms of the messages, for subscribers in languages without the binary layout.
//!
//! A trajectory sample has the fields of a line of the trajectory file (`frame`, `t`,
//! `objects`, `dropped_frames`; a test reads one as the other) and those a live subscriber
//! also wants: the ingest `sequence` (gaps are lost frames), the capture and publication
//! times, and `end_of_stream`.

use std::collections::BTreeMap;

use handflow_protocol::messages::{ClusterSet, TrajectorySample, OBJECT_LABELS};
pub use handflow_protocol::records::{ObjectSample, TrackState};
use serde::{Deserialize, Serialize};

/// A trajectory sample as JSON.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrajectoryJson {
    /// Ingest sequence of the frame set.
    pub sequence: u64,
    /// The stream has ended; the other fields carry nothing.
    pub end_of_stream: bool,
    /// Capture wall-clock time, nanoseconds since the Unix epoch.
    pub capture_unix_ns: u64,
    /// Publication wall-clock time, nanoseconds since the Unix epoch.
    pub published_unix_ns: u64,
    /// Source frame number.
    pub frame: u64,
    /// Stream time, seconds.
    pub t: f64,
    /// Objects by label (`head`, `left_hand`, `right_hand`).
    pub objects: BTreeMap<String, ObjectSample>,
    /// Frame sets lost upstream since the stream began.
    pub dropped_frames: u64,
    /// Cameras (bit k: camera k) whose view this frame set went without.
    pub missing_views: u32,
}

impl TrajectoryJson {
    /// The JSON form of `s`.
    pub fn from_sample(s: &TrajectorySample) -> Self {
        Self {
            sequence: s.sequence,
            end_of_stream: s.is_end_of_stream(),
            capture_unix_ns: s.capture_unix_ns,
            published_unix_ns: s.published_unix_ns,
            frame: s.frame,
            t: s.timestamp_s,
            objects: handflow_protocol::records::objects_by_label(&s.objects),
            dropped_frames: s.dropped_frames,
            missing_views: s.missing_views,
        }
    }
}

/// One labelled cluster as JSON.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ClusterJson {
    /// World position, metres.
    pub pos: [f64; 3],
    /// World velocity, metres per second.
    pub vel: [f64; 3],
    /// Confidence in [0, 1].
    pub confidence: f64,
    /// Share of the frame's particle weight in the object's cluster.
    pub mass: f64,
    /// Tracking state.
    pub state: TrackState,
}

/// A frame's labelled clusters as JSON.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ClusterSetJson {
    /// Ingest sequence of the frame set.
    pub sequence: u64,
    /// The stream has ended.
    pub end_of_stream: bool,
    /// Source frame number.
    pub frame: u64,
    /// Stream time, seconds.
    pub t: f64,
    /// Seconds clustering and labelling took.
    pub cluster_seconds: f64,
    /// Objects by label.
    pub objects: BTreeMap<String, ClusterJson>,
}

impl ClusterSetJson {
    /// The JSON form of `c`.
    pub fn from_set(c: &ClusterSet) -> Self {
        let objects = OBJECT_LABELS
            .iter()
            .zip(&c.objects)
            .map(|(label, o)| {
                let cluster = ClusterJson {
                    pos: o.position,
                    vel: o.velocity,
                    confidence: o.confidence,
                    mass: o.mass,
                    state: TrackState::from_wire(o.state),
                };
                ((*label).to_owned(), cluster)
            })
            .collect();
        Self {
            sequence: c.sequence,
            end_of_stream: c.is_end_of_stream(),
            frame: c.frame,
            t: c.timestamp_s,
            cluster_seconds: c.cluster_seconds,
            objects,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use handflow_protocol::messages::{track_state, PROTOCOL_VERSION};
    use handflow_publish::TrajectoryRecord;

    #[test]
    fn a_trajectory_sample_reads_back_as_a_line_of_the_trajectory_file() {
        let mut s =
            TrajectorySample { protocol_version: PROTOCOL_VERSION, sequence: 9, frame: 12, ..Default::default() };
        s.objects[1].position = [0.1, 1.2, -0.3];
        s.objects[2].state = track_state::LOST;
        let text = serde_json::to_string(&TrajectoryJson::from_sample(&s)).unwrap();
        let line: TrajectoryRecord = serde_json::from_str(&text).unwrap();
        assert_eq!(line, TrajectoryRecord::from_sample(&s));
        let back: TrajectoryJson = serde_json::from_str(&text).unwrap();
        assert_eq!(back.sequence, 9);
        assert!(!back.end_of_stream);
        assert!(text.contains("\"left_hand\"") && text.contains("\"lost\""), "{text}");
    }

    #[test]
    fn cluster_sets_carry_mass_and_state() {
        let mut c = ClusterSet { protocol_version: PROTOCOL_VERSION, frame: 4, ..Default::default() };
        c.objects[0].mass = 0.4;
        c.objects[0].state = track_state::PREDICTED;
        let j = ClusterSetJson::from_set(&c);
        assert_eq!(j.objects["head"].mass, 0.4);
        assert_eq!(j.objects["head"].state, TrackState::Predicted);
        assert_eq!(j.frame, 4);
    }
}
