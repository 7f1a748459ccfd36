//! `handflow eval tracks`: trajectories against a recording's ground truth, as in
//! EVALUATION.md section 2: per object the agreement rate (projection within a third of a
//! palm width of the true position in every view that sees it), RMS image distance in palm
//! widths (X and Y), 3D RMS error, and identity switches.

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::{Context, Result};
use handflow_cluster::tracks::OBJECTS;
use handflow_ingest::Recording;
use handflow_publish::TrajectoryRecord;
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
    /// RMS horizontal image distance, palm widths (over frames and views that see it).
    pub rms_palm_x: f64,
    /// RMS vertical image distance, palm widths.
    pub rms_palm_y: f64,
    /// RMS 3D distance, metres.
    pub rmse_3d_m: f64,
    /// Frames scored (the object is visible in at least one view).
    pub frames: usize,
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
    /// Frames where the labels that best match the truth change (two labels swap).
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
    let by_frame: BTreeMap<u64, &TruthFrame> = truth.frames.iter().map(|f| (f.frame, f)).collect();
    let cameras = &rec.rig().cameras;
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
        for (k, name) in OBJECTS.iter().enumerate() {
            let est =
                record.objects.get(*name).with_context(|| format!("trajectory frame {}: no `{name}`", record.frame))?;
            let truth = truth_frame
                .objects
                .get(*name)
                .with_context(|| format!("`{}` frame {}: no `{name}`", path.display(), record.frame))?;
            estimates[k] = est.pos;
            truths[k] = truth.pos;
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
                sums[k].e2 += (p - Point3::from(truth.pos)).norm_squared();
            }
        }
        // The labelling that matches the truth best; a change is an identity switch.
        let best = best_labelling(&estimates, &truths);
        if best != labelling {
            switches += 1;
            labelling = best;
        }
        frames += 1;
    }
    let scores = |s: &Sums| ObjectScores {
        agreement: s.agreed as f64 / s.frames.max(1) as f64,
        rms_palm_x: (s.dx2 / s.views.max(1) as f64).sqrt(),
        rms_palm_y: (s.dy2 / s.views.max(1) as f64).sqrt(),
        rmse_3d_m: (s.e2 / s.frames.max(1) as f64).sqrt(),
        frames: s.frames,
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
