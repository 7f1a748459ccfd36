//! Trajectories in the files other tools read: TRC (OpenSim, Pose2Sim), C3D (biomechanics
//! and animation packages) and CSV.
//!
//! Every format holds the same three markers, `Head`, `LHand` and `RHand` (the signer's own
//! left and right), in metres, in the world frame of the rig's calibration (the axes of
//! `rig.toml`; `handflow rig show` prints which way is up). TRC and C3D hold one row per
//! frame from the first to the last tracked frame at a uniform rate: a frame the stream
//! skipped, and an object that was lost, are left blank (TRC) or marked invalid (C3D).

pub mod c3d;
pub mod csv;
pub mod trc;

use anyhow::{bail, Result};
use handflow_publish::{TrackState, TrajectoryRecord};

/// Marker names, in [`handflow_protocol::messages::OBJECT_LABELS`] order.
pub const MARKERS: [&str; 3] = ["Head", "LHand", "RHand"];

/// What each marker describes (C3D's `POINT:DESCRIPTIONS`).
pub const MARKER_DESCRIPTIONS: [&str; 3] =
    ["centre of the head", "palm centre of the left hand", "palm centre of the right hand"];

/// One marker at one frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MarkerSample {
    /// Position, metres, world frame.
    pub position: [f64; 3],
    /// The tracker's confidence in [0, 1].
    pub confidence: f64,
}

/// The markers at a uniform rate from the first tracked frame to the last.
#[derive(Clone, Debug, PartialEq)]
pub struct MarkerSeries {
    /// Frames per second.
    pub rate_hz: f64,
    /// Frame number of the first row.
    pub first_frame: u64,
    /// Stream time of the first row, seconds.
    pub start_s: f64,
    /// Per row (frame `first_frame + k`), each marker where it was tracked or predicted.
    pub rows: Vec<[Option<MarkerSample>; 3]>,
}

/// Longest series written: C3D counts frames in 16 bits (65535 frames, 36 minutes at 30 fps).
pub const MAX_FRAMES: u64 = 65_535;

impl MarkerSeries {
    /// The series of `records` (in frame order), at `rate_hz` if given or else at the rate
    /// their frame numbers and times imply.
    pub fn from_records(records: &[TrajectoryRecord], rate_hz: Option<f64>) -> Result<Self> {
        let (Some(first), Some(last)) = (records.first(), records.last()) else {
            bail!("no trajectory records to export");
        };
        if let Some(pair) = records.windows(2).find(|p| p[1].frame <= p[0].frame) {
            bail!(
                "frame {} follows frame {}: records must be in frame order, each frame once",
                pair[1].frame,
                pair[0].frame
            );
        }
        let rate_hz = match rate_hz {
            Some(rate) if rate.is_finite() && rate > 0.0 => rate,
            Some(rate) => bail!("the frame rate must be positive, not {rate}"),
            None => implied_rate(records)?,
        };
        let span = last.frame - first.frame + 1;
        if span > MAX_FRAMES {
            bail!("frames {} to {} are {span} frames; at most {MAX_FRAMES} fit in one export", first.frame, last.frame);
        }
        let mut rows = vec![[None; 3]; span as usize];
        for record in records {
            let row = &mut rows[(record.frame - first.frame) as usize];
            for (slot, label) in row.iter_mut().zip(handflow_protocol::messages::OBJECT_LABELS) {
                *slot = record.objects.get(label).and_then(|o| {
                    let usable = o.state != TrackState::Lost && o.pos.iter().all(|v| v.is_finite());
                    usable.then_some(MarkerSample { position: o.pos, confidence: o.confidence.clamp(0.0, 1.0) })
                });
            }
        }
        Ok(Self { rate_hz, first_frame: first.frame, start_s: first.t, rows })
    }

    /// Stream time of row `k`, seconds.
    pub fn time_s(&self, k: usize) -> f64 {
        self.start_s + k as f64 / self.rate_hz
    }
}

/// The frame rate the records' frame numbers and times imply: frames elapsed over seconds
/// elapsed between the first and the last record.
fn implied_rate(records: &[TrajectoryRecord]) -> Result<f64> {
    let (first, last) = (&records[0], &records[records.len() - 1]);
    let seconds = last.t - first.t;
    if records.len() < 2 || seconds.is_nan() || seconds <= 0.0 {
        bail!("cannot tell the frame rate from {} record(s) without elapsed time: give it with --rate", records.len());
    }
    Ok((last.frame - first.frame) as f64 / seconds)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use handflow_publish::ObjectSample;
    use std::collections::BTreeMap;

    /// A record at `frame` (30 fps) with the head at x = frame / 100, the left hand lost
    /// at odd frames.
    pub(crate) fn record(frame: u64) -> TrajectoryRecord {
        let sample =
            |x: f64, state| ObjectSample { pos: [x, 1.5, -0.25], vel: [0.3, 0.0, 0.0], confidence: 0.8, state };
        let left = if frame % 2 == 1 { TrackState::Lost } else { TrackState::Tracked };
        let objects = BTreeMap::from([
            ("head".to_string(), sample(frame as f64 / 100.0, TrackState::Tracked)),
            ("left_hand".to_string(), sample(0.5, left)),
            ("right_hand".to_string(), sample(-0.5, TrackState::Predicted)),
        ]);
        TrajectoryRecord { frame, t: frame as f64 / 30.0, objects, dropped_frames: 0, missing_views: 0 }
    }

    #[test]
    fn a_series_has_a_row_per_frame_with_skipped_frames_and_lost_objects_blank() {
        let records: Vec<_> = [3, 4, 6].map(record).to_vec();
        let series = MarkerSeries::from_records(&records, None).unwrap();
        assert!((series.rate_hz - 30.0).abs() < 1e-9);
        assert_eq!((series.first_frame, series.rows.len()), (3, 4));
        assert_eq!(series.rows[2], [None; 3], "frame 5 was skipped");
        assert!(series.rows[0][1].is_none(), "the left hand is lost at frame 3");
        assert_eq!(series.rows[1][0].unwrap().position, [0.04, 1.5, -0.25]);
        assert!(series.rows[1][2].is_some(), "a predicted position is written");
        assert!((series.time_s(3) - 0.2).abs() < 1e-12);
    }

    #[test]
    fn records_out_of_order_or_without_a_rate_are_refused_clearly() {
        let error = MarkerSeries::from_records(&[record(4), record(3)], None).unwrap_err().to_string();
        assert!(error.contains("frame 3 follows frame 4"), "{error}");
        let error = MarkerSeries::from_records(&[record(4)], None).unwrap_err().to_string();
        assert!(error.contains("--rate"), "{error}");
        assert_eq!(MarkerSeries::from_records(&[record(4)], Some(60.0)).unwrap().rate_hz, 60.0);
        assert!(MarkerSeries::from_records(&[], None).is_err());
        assert!(MarkerSeries::from_records(&[record(0), record(70_000)], None).is_err());
    }
}
