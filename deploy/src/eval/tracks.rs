//! `handflow eval tracks`: trajectories against a recording's ground truth, as in
//! EVALUATION.md section 2: per object the agreement rate (projection within a third of a
//! palm width of the true position in every view that sees it), RMS image distance in palm
//! widths (X and Y), 3D RMS error, and identity switches; and of the published velocity (what
//! 2D keypoint pipelines do not give), its RMS error and the share of the true velocity it
//! carries. A `lost` estimate is a miss, as
//! against a reference tracker (section 2b): it never agrees, and the RMS figures are over
//! the frames with an estimate (a lost track's published position is a placeholder, and an
//! error measured from it would say where the world's origin is, not how far off the track
//! is).

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::{Context, Result};
use handflow_cluster::tracks::OBJECTS;
use handflow_ingest::Recording;
use handflow_protocol::Camera;
use handflow_publish::{TrackState, TrajectoryRecord};
use nalgebra::Point3;
use serde::Deserialize;

/// Palm width, metres (EVALUATION.md).
pub const PALM_WIDTH_M: f64 = 0.085;
/// Agreement radius, palm widths.
pub const AGREEMENT_PALMS: f64 = 1.0 / 3.0;

/// One object's scores.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct ObjectScores {
    /// Share of scored frames whose estimate projects within a third of a palm width of the
    /// truth in every view that sees the object.
    pub agreement: f64,
    /// RMS horizontal image distance, palm widths (over the views that see it in frames
    /// with an estimate).
    pub rms_palm_x: f64,
    /// RMS vertical image distance, palm widths.
    pub rms_palm_y: f64,
    /// RMS 3D distance over the frames with an estimate, metres (`NaN`, `null` in JSON,
    /// when every frame is a miss).
    pub rmse_3d_m: f64,
    /// RMS error of the published velocity over the frames with an estimate, metres per
    /// second (`null` without an estimate, or a truth that gives no velocity).
    pub rmse_velocity_m_s: f64,
    /// Share of the true velocity the published one carries: the least-squares gain `g` of
    /// `published ~ g x true` over the same frames (1 unbiased, below 1 shrunk towards rest;
    /// `null` when the object never moves).
    pub velocity_gain: f64,
    /// Frames scored (the object is visible in at least one view).
    pub frames: usize,
    /// Scored frames whose estimate is `lost`: they count against `agreement`.
    pub misses: usize,
}

/// Scores of a whole run.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct TrackScores {
    /// The head.
    pub head: ObjectScores,
    /// The signer's left hand.
    pub left_hand: ObjectScores,
    /// The signer's right hand.
    pub right_hand: ObjectScores,
    /// Frames where the labels that best match the truth change (two labels swap), judged on
    /// the frames where no track is lost.
    pub identity_switches: usize,
    /// Frames compared.
    pub frames: usize,
}

#[derive(Deserialize)]
struct Truth {
    frames: Vec<TruthFrame>,
}

#[derive(Deserialize)]
struct TruthFrame {
    frame: u64,
    objects: BTreeMap<String, TruthObject>,
}

#[derive(Deserialize)]
struct TruthObject {
    pos: [f64; 3],
    /// Metres per second; older recordings' truth has none.
    #[serde(default)]
    vel: Option<[f64; 3]>,
    pixel: Vec<Option<[f64; 2]>>,
    visible: Vec<bool>,
}

#[derive(Default)]
struct Sums {
    agreed: usize,
    frames: usize,
    dx2: f64,
    dy2: f64,
    views: usize,
    e2: f64,
    measured: usize,
    misses: usize,
    /// Velocity: squared error, estimate . truth and truth . truth summed, and the frames.
    ve2: f64,
    v_cross: f64,
    v_true2: f64,
    v_measured: usize,
}

/// Reads a trajectory file (JSON Lines), naming the line of any error.
pub fn read_tracks(path: &Path) -> Result<Vec<TrajectoryRecord>> {
    let text = handflow_protocol::read_text_capped(path).with_context(|| format!("reading `{}`", path.display()))?;
    text.lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty())
        .map(|(i, l)| {
            serde_json::from_str(l)
                .with_context(|| format!("`{}` line {}: not a trajectory record", path.display(), i + 1))
        })
        .collect()
}

/// Scores `records` against the recording's `truth.json`.
pub fn evaluate_tracks(rec: &Recording, records: &[TrajectoryRecord]) -> Result<TrackScores> {
    let path = rec.truth_path().with_context(|| format!("recording `{}` has no truth.json", rec.dir().display()))?;
    let text = handflow_protocol::read_text_capped(path).with_context(|| format!("reading `{}`", path.display()))?;
    let truth: Truth = serde_json::from_str(&text).with_context(|| format!("`{}`", path.display()))?;
    score_tracks(&rec.rig().cameras, &truth.frames, records, path)
}

/// Scores `records` against the truth's frames (`path` names the truth in errors).
fn score_tracks(
    cameras: &[Camera],
    truth: &[TruthFrame],
    records: &[TrajectoryRecord],
    path: &Path,
) -> Result<TrackScores> {
    let by_frame: BTreeMap<u64, &TruthFrame> = truth.iter().map(|f| (f.frame, f)).collect();
    let mut sums: [Sums; 3] = Default::default();
    let mut switches = 0;
    let mut labelling = [0usize, 1, 2];
    let mut frames = 0;
    for record in records {
        let truth_frame = by_frame
            .get(&record.frame)
            .with_context(|| format!("trajectory frame {} is not in `{}`", record.frame, path.display()))?;
        let mut estimates = [[f64::NAN; 3]; 3];
        let mut truths = [[f64::NAN; 3]; 3];
        let mut all_estimated = true;
        for (k, name) in OBJECTS.iter().enumerate() {
            let est =
                record.objects.get(*name).with_context(|| format!("trajectory frame {}: no `{name}`", record.frame))?;
            let truth = truth_frame
                .objects
                .get(*name)
                .with_context(|| format!("`{}` frame {}: no `{name}`", path.display(), record.frame))?;
            estimates[k] = est.pos;
            truths[k] = truth.pos;
            let lost = est.state == TrackState::Lost;
            all_estimated &= !lost;
            let p = Point3::from(est.pos);
            let mut seen = false;
            let mut agrees = true;
            for (c, cam) in cameras.iter().enumerate() {
                let (Some(true), Some(Some(px))) = (truth.visible.get(c), truth.pixel.get(c)) else { continue };
                let depth = cam.world_to_camera(&Point3::from(truth.pos)).z;
                if depth <= 0.0 {
                    continue;
                }
                let palm_px = PALM_WIDTH_M * cam.matrix[(0, 0)] / depth;
                seen = true;
                if lost {
                    agrees = false;
                    continue;
                }
                let (dx, dy) = match cam.project(&p) {
                    Some(q) => ((q.x - px[0]) / palm_px, (q.y - px[1]) / palm_px),
                    // Behind the camera: as far off as the image is wide.
                    None => (f64::from(cam.width) / palm_px, f64::from(cam.height) / palm_px),
                };
                agrees &= dx.hypot(dy) <= AGREEMENT_PALMS;
                sums[k].dx2 += dx * dx;
                sums[k].dy2 += dy * dy;
                sums[k].views += 1;
            }
            if seen {
                sums[k].frames += 1;
                sums[k].agreed += usize::from(agrees);
                if lost {
                    sums[k].misses += 1;
                } else {
                    sums[k].e2 += (p - Point3::from(truth.pos)).norm_squared();
                    sums[k].measured += 1;
                    if let Some(true_vel) = truth.vel {
                        let (e, t) = (nalgebra::Vector3::from(est.vel), nalgebra::Vector3::from(true_vel));
                        sums[k].ve2 += (e - t).norm_squared();
                        sums[k].v_cross += e.dot(&t);
                        sums[k].v_true2 += t.norm_squared();
                        sums[k].v_measured += 1;
                    }
                }
            }
        }
        // The labelling that matches the truth best; a change is an identity switch.
        if all_estimated {
            let best = best_labelling(&estimates, &truths);
            if best != labelling {
                switches += 1;
                labelling = best;
            }
        }
        frames += 1;
    }
    let scores = |s: &Sums| ObjectScores {
        agreement: s.agreed as f64 / s.frames.max(1) as f64,
        rms_palm_x: (s.dx2 / s.views.max(1) as f64).sqrt(),
        rms_palm_y: (s.dy2 / s.views.max(1) as f64).sqrt(),
        rmse_3d_m: if s.measured == 0 { f64::NAN } else { (s.e2 / s.measured as f64).sqrt() },
        rmse_velocity_m_s: if s.v_measured == 0 { f64::NAN } else { (s.ve2 / s.v_measured as f64).sqrt() },
        velocity_gain: if s.v_true2 > 0.0 { s.v_cross / s.v_true2 } else { f64::NAN },
        frames: s.frames,
        misses: s.misses,
    };
    Ok(TrackScores {
        head: scores(&sums[0]),
        left_hand: scores(&sums[1]),
        right_hand: scores(&sums[2]),
        identity_switches: switches,
        frames,
    })
}

/// The permutation `p` (estimate k labelled as truth p[k]) with the least total 3D
/// distance; identity on ties.
pub(crate) fn best_labelling(estimates: &[[f64; 3]; 3], truths: &[[f64; 3]; 3]) -> [usize; 3] {
    const PERMUTATIONS: [[usize; 3]; 6] = [[0, 1, 2], [0, 2, 1], [1, 0, 2], [1, 2, 0], [2, 0, 1], [2, 1, 0]];
    let d = |a: &[f64; 3], b: &[f64; 3]| ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt();
    let cost = |p: &[usize; 3]| (0..3).map(|k| d(&estimates[k], &truths[p[k]])).sum::<f64>();
    let mut best = PERMUTATIONS[0];
    for p in PERMUTATIONS {
        // A swap must be clearly better: 1 cm of slack keeps noise from counting as switches.
        if cost(&p) + 0.01 < cost(&best) {
            best = p;
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval::reference::tests::rig3;
    use handflow_publish::ObjectSample;

    const TRUE: [[f64; 3]; 3] = [[0.0, 0.5, 0.0], [0.25, 0.0, 0.1], [-0.25, 0.0, 0.1]];

    fn truth_frame(cameras: &[Camera], frame: u64) -> TruthFrame {
        let objects = OBJECTS
            .iter()
            .zip(TRUE)
            .map(|(name, pos)| {
                let pixel = cameras.iter().map(|c| c.project(&Point3::from(pos)).map(|q| [q.x, q.y])).collect();
                let vel = Some([0.4, 0.0, 0.0]);
                ((*name).to_owned(), TruthObject { pos, vel, pixel, visible: vec![true; cameras.len()] })
            })
            .collect();
        TruthFrame { frame, objects }
    }

    fn record(frame: u64, objects: [([f64; 3], TrackState); 3]) -> TrajectoryRecord {
        record_moving(frame, objects, [0.0; 3])
    }

    /// A record whose every object is published with velocity `vel`.
    fn record_moving(frame: u64, objects: [([f64; 3], TrackState); 3], vel: [f64; 3]) -> TrajectoryRecord {
        TrajectoryRecord {
            frame,
            t: frame as f64 / 30.0,
            objects: OBJECTS
                .iter()
                .zip(objects)
                .map(|(n, (pos, state))| ((*n).to_owned(), ObjectSample { pos, vel, confidence: 1.0, state }))
                .collect(),
            dropped_frames: 0,
            missing_views: 0,
        }
    }

    #[test]
    fn a_lost_track_is_a_miss_not_an_error_from_the_worlds_origin() {
        let rig = rig3();
        let truth: Vec<TruthFrame> = (0..4).map(|f| truth_frame(&rig.cameras, f)).collect();
        let tracked = |k: usize, dz: f64| ([TRUE[k][0], TRUE[k][1], TRUE[k][2] + dz], TrackState::Tracked);
        // The head 2 cm off throughout; the left hand exact but lost in the first two frames,
        // published at the origin, as the tracker does before a track starts; the right hand
        // exact.
        let records: Vec<TrajectoryRecord> = (0..4)
            .map(|f| {
                let left = if f < 2 { ([0.0; 3], TrackState::Lost) } else { tracked(1, 0.0) };
                record(f, [tracked(0, 0.02), left, tracked(2, 0.0)])
            })
            .collect();
        let s = score_tracks(&rig.cameras, &truth, &records, Path::new("truth.json")).expect("scores");
        assert_eq!(s.frames, 4);
        assert!((s.head.rmse_3d_m - 0.02).abs() < 1e-12, "{s:?}");
        assert_eq!((s.head.misses, s.head.agreement), (0, 1.0));
        assert_eq!((s.left_hand.frames, s.left_hand.misses), (4, 2));
        assert_eq!(s.left_hand.agreement, 0.5);
        assert!(s.left_hand.rmse_3d_m < 1e-12 && s.left_hand.rms_palm_x < 1e-9, "{s:?}");
        // A lost hand at the origin is not a swap with the other.
        assert_eq!(s.identity_switches, 0);
        // Every frame lost: no error to report, and never a division by zero.
        let lost: Vec<TrajectoryRecord> =
            (0..4).map(|f| record(f, [tracked(0, 0.0), ([0.0; 3], TrackState::Lost), tracked(2, 0.0)])).collect();
        let s = score_tracks(&rig.cameras, &truth, &lost, Path::new("truth.json")).expect("scores");
        assert!(s.left_hand.rmse_3d_m.is_nan() && s.left_hand.agreement == 0.0, "{s:?}");
    }

    #[test]
    fn the_velocity_is_scored_by_its_error_and_the_share_of_the_truth_it_carries() {
        let rig = rig3();
        // Every object truly moves at 0.4 m/s along x.
        let truth: Vec<TruthFrame> = (0..4).map(|f| truth_frame(&rig.cameras, f)).collect();
        let at = |k: usize| (TRUE[k], TrackState::Tracked);
        // Published at three quarters of the speed, and 0.1 m/s upwards besides.
        let records: Vec<TrajectoryRecord> =
            (0..4).map(|f| record_moving(f, [at(0), at(1), at(2)], [0.3, 0.1, 0.0])).collect();
        let s = score_tracks(&rig.cameras, &truth, &records, Path::new("truth.json")).expect("scores");
        for o in [&s.head, &s.left_hand, &s.right_hand] {
            assert!((o.rmse_velocity_m_s - 0.02f64.sqrt()).abs() < 1e-12, "{o:?}");
            assert!((o.velocity_gain - 0.75).abs() < 1e-12, "{o:?}");
        }
        // Lost frames say nothing of the velocity; an exact one scores zero and a gain of one.
        let records: Vec<TrajectoryRecord> = (0..4)
            .map(|f| {
                let left = if f < 2 { ([0.0; 3], TrackState::Lost) } else { at(1) };
                record_moving(f, [at(0), left, at(2)], [0.4, 0.0, 0.0])
            })
            .collect();
        let s = score_tracks(&rig.cameras, &truth, &records, Path::new("truth.json")).expect("scores");
        assert!(s.left_hand.rmse_velocity_m_s.abs() < 1e-12 && (s.left_hand.velocity_gain - 1.0).abs() < 1e-12);
        // A truth without velocities leaves both unscored.
        let mut still = truth;
        for frame in &mut still {
            for object in frame.objects.values_mut() {
                object.vel = None;
            }
        }
        let s = score_tracks(&rig.cameras, &still, &records, Path::new("truth.json")).expect("scores");
        assert!(s.head.rmse_velocity_m_s.is_nan() && s.head.velocity_gain.is_nan(), "{s:?}");
    }

    #[test]
    fn the_labelling_follows_a_swap_and_ignores_noise() {
        let truths = [[0.0, 1.6, 0.0], [0.2, 1.0, 0.0], [-0.2, 1.0, 0.0]];
        assert_eq!(best_labelling(&truths, &truths), [0, 1, 2]);
        let swapped = [truths[0], truths[2], truths[1]];
        assert_eq!(best_labelling(&swapped, &truths), [0, 2, 1]);
        // Hands 4 mm apart: no confident swap either way.
        let close = [[0.0, 1.6, 0.0], [0.002, 1.0, 0.0], [-0.002, 1.0, 0.0]];
        let est = [close[0], close[2], close[1]];
        assert_eq!(best_labelling(&est, &close), [0, 1, 2]);
    }
}
