//! The JSON forms of an object's estimate, shared by the trajectory file and the messages
//! sent as JSON to other machines.

use serde::{Deserialize, Serialize};

use crate::messages::track_state;

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

impl TrackState {
    /// The state of a wire [`track_state`] constant (unknown values are `Lost`).
    pub fn from_wire(state: u32) -> Self {
        match state {
            track_state::TRACKED => TrackState::Tracked,
            track_state::PREDICTED => TrackState::Predicted,
            _ => TrackState::Lost,
        }
    }

    /// The state's name as the trajectory file writes it (`tracked`, `predicted`, `lost`),
    /// for the tables and CSV files that spell it out.
    pub fn name(self) -> &'static str {
        match self {
            TrackState::Tracked => "tracked",
            TrackState::Predicted => "predicted",
            TrackState::Lost => "lost",
        }
    }
}

impl ObjectSample {
    /// The estimate a trajectory sample holds for one object.
    pub fn from_wire(o: &crate::messages::TrajectoryObject) -> Self {
        Self { pos: o.position, vel: o.velocity, confidence: o.confidence, state: TrackState::from_wire(o.state) }
    }
}

/// A trajectory sample's objects by label (`head`, `left_hand`, `right_hand`), as the
/// trajectory file and the JSON messages hold them.
pub fn objects_by_label(
    objects: &[crate::messages::TrajectoryObject; 3],
) -> std::collections::BTreeMap<String, ObjectSample> {
    crate::messages::OBJECT_LABELS
        .iter()
        .zip(objects)
        .map(|(l, o)| ((*l).to_owned(), ObjectSample::from_wire(o)))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_states_name_is_the_one_the_trajectory_file_writes() {
        for state in [TrackState::Tracked, TrackState::Predicted, TrackState::Lost] {
            assert_eq!(serde_json::to_value(state).unwrap(), state.name());
        }
    }
}
