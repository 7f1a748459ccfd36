//! Where a hand is within its cluster. In short sleeves a hand's skin runs on to the bare
//! forearm, and the cluster's centroid lands on the wrist or the forearm. The hand is the
//! distal end of that skin: the end of the arm away from the elbow, a hand's length long.

use nalgebra::{Matrix3, SymmetricEigen, Vector3};

use crate::em::{weighted_median, Component};
use crate::{weighted_moments, WeightedPoint};

/// Length of an adult hand from the fingertips to the wrist, metres (16-20 cm); the part of
/// an arm's skin taken as the hand. Its points' centroid is near the palm centre (the mean
/// of wrist and knuckles).
pub const HAND_LENGTH_M: f64 = 0.17;
/// A cluster whose skin is no longer than this along its main axis is a hand alone, metres:
/// a hand's length plus the spread depth noise and a bent wrist add.
pub const HAND_ONLY_EXTENT_M: f64 = 0.22;
/// A cluster longer than this along its main axis is more than a bare arm, metres (a
/// T-shirt leaves the hand, the forearm and part of the upper arm bare, about 0.65 m):
/// a skin-coloured shirt joined it, its ends say nothing about where the hand is, and its
/// centroid is kept. 0.5 m cost the shared real session's left hand 13 points of frames
/// within 5 cm.
pub const MAX_ARM_EXTENT_M: f64 = 0.75;
/// A distal end closer than this to the head's centre is the head's own skin (a face or a
/// neck the hand's component reached into when the hand came near it), not a hand, metres:
/// about a head's radius plus a finger's width. The centroid is kept then.
pub const HEAD_CLEARANCE_M: f64 = 0.15;
/// Least share of the cluster's weight the distal hand's length must hold, for a hand and a
/// forearm (the hand is wider than the forearm and holds about half): less is a few stray
/// depths the cluster's spread took in, and the centroid is kept.
pub const MIN_HAND_SHARE: f64 = 0.15;
/// Weight of the distance from where the track expects the hand in choosing the distal end
/// (per metre, against the ends' height and reach in metres). A forearm held level and
/// pointing at the cameras has its ends at about the same height and reach, and from frame
/// to frame the rule alone flipped between hand and elbow (`signer-short-sleeves`: the left
/// hand 21-24 cm off in 7 frames of 149); the hand does not jump a forearm's length between
/// frames, so the end nearer the prediction wins such ties. Scaled down by
/// [`continuity_weight`] as the frame interval grows.
pub const CONTINUITY_WEIGHT: f64 = 1.0;
/// Length of a forearm, metres: a prediction that can miss by this much cannot tell the
/// hand's end of an arm from the elbow's.
pub const FOREARM_LENGTH_M: f64 = 0.26;

/// The continuity weight for a prediction that the constant-velocity model can miss by
/// `miss_m` metres (what the largest acceleration moves a hand over the frame interval):
/// [`CONTINUITY_WEIGHT`] less its share of a forearm, none at a forearm or more. With the
/// tracker's 20 m/s^2, 0.96 at 30 fps and none at 6 fps (a hand moves 20-40 cm between
/// frames there; measured on the shared real session at full weight: the left hand's
/// shares within 5 / 10 cm fell from 80.7 / 92.7 % to 75.7 / 84.3 %, a wrong end kept).
pub fn continuity_weight(miss_m: f64) -> f64 {
    CONTINUITY_WEIGHT * (1.0 - miss_m.max(0.0) / FOREARM_LENGTH_M).max(0.0)
}
/// Radius of the hand's skin around its centre, metres: half a hand's length, so a window
/// of it holds the palm and the fingers' roots (the palm is 8-9 cm wide, 10 cm long).
pub const HAND_RADIUS_M: f64 = HAND_LENGTH_M / 2.0;
/// Most mean-shift steps towards the densest skin of the hand.
const MEAN_SHIFT_STEPS: usize = 10;
/// A mean-shift step shorter than this has settled, metres.
const MEAN_SHIFT_TOLERANCE_M: f64 = 0.001;
/// Squared Mahalanobis distance (3 degrees of freedom, 99 %) within which a point belongs
/// to the cluster whose Gaussian explains it best.
const MEMBER_CHI2: f64 = 11.34;
/// Share of the members' weight ignored at each end of the main axis (stray depths).
const END_TRIM: f64 = 0.03;

/// A component's position Gaussian prepared for scoring points: mean, inverse covariance,
/// and log mixing weight less half the log determinant.
type PositionGaussian = (Vector3<f64>, Matrix3<f64>, f64);

/// How a cluster's hand was located.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HandLocation {
    /// The hand's centre, world metres.
    pub position: Vector3<f64>,
    /// Length of the cluster's skin along its main axis, metres (between the trimmed ends).
    pub extent_m: f64,
    /// Whether the skin was longer than a hand and its distal end was taken.
    pub arm: bool,
}

/// Locates the hand in component `cluster` of `components` (the frame's fit), given the
/// head's position and the world's up. Points belong to the component whose position
/// Gaussian explains them best, within 99 % of it. When they reach farther than
/// [`HAND_ONLY_EXTENT_M`] along their main axis, the hand lies in the [`HAND_LENGTH_M`] at
/// the distal end: along the axis at their centroid, across it at their densest skin
/// ([`densest_across`]). The distal end is the one that is higher plus
/// farther out from the vertical axis through the head: an elbow hangs below the hand and
/// stays by the body while the hand signs, reaches or rests in the lap in front of it; less
/// a weight times its distance from `expected`, where the track predicts the hand, with the
/// weight ([`continuity_weight`]; `None` for a track that starts or was not measured in the
/// last frame).
/// `None` when the cluster has no member points.
pub fn locate_hand(
    points: &[WeightedPoint],
    components: &[Component],
    cluster: usize,
    head: Vector3<f64>,
    up: Vector3<f64>,
    expected: Option<(Vector3<f64>, f64)>,
) -> Option<HandLocation> {
    let target = components.get(cluster)?;
    let gaussians: Vec<Option<PositionGaussian>> = components
        .iter()
        .map(|c| {
            if c.empty {
                return None;
            }
            let cov: Matrix3<f64> = c.covariance.fixed_view::<3, 3>(0, 0).into_owned();
            let inverse = cov.try_inverse()?;
            let log_det = cov.determinant().max(1e-300).ln();
            Some((c.position, inverse, (c.mixing.max(1e-300)).ln() - 0.5 * log_det))
        })
        .collect();
    let own_gaussian = gaussians[cluster]?;
    let target_inverse = own_gaussian.1;
    let members: Vec<WeightedPoint> = points
        .iter()
        .filter(|p| p.is_usable())
        .filter(|p| {
            let d = p.position - target.position;
            if (d.transpose() * target_inverse * d)[(0, 0)] > MEMBER_CHI2 {
                return false;
            }
            let score = |g: &PositionGaussian| {
                let d = p.position - g.0;
                g.2 - 0.5 * (d.transpose() * g.1 * d)[(0, 0)]
            };
            let own = score(&own_gaussian);
            gaussians.iter().enumerate().all(|(j, g)| j == cluster || g.as_ref().is_none_or(|g| score(g) <= own))
        })
        .copied()
        .collect();
    // Positions only: velocities weigh nothing in the moments.
    let moments = weighted_moments(&members, 0.0)?;
    let total = moments.total_weight;
    let mean: Vector3<f64> = moments.mean.fixed_rows::<3>(0).into_owned();
    let eigen = SymmetricEigen::new(moments.covariance.fixed_view::<3, 3>(0, 0).into_owned());
    let main = eigen.eigenvalues.imax();
    let axis: Vector3<f64> = eigen.eigenvectors.column(main).into_owned();
    let mut along: Vec<(f64, &WeightedPoint)> = members.iter().map(|p| ((p.position - mean).dot(&axis), p)).collect();
    along.sort_by(|a, b| a.0.total_cmp(&b.0));
    let quantile = |share: f64| {
        let mut acc = 0.0;
        for (s, p) in &along {
            acc += p.weight;
            if acc >= share * total {
                return *s;
            }
        }
        along.last().map_or(0.0, |(s, _)| *s)
    };
    let (low, high) = (quantile(END_TRIM), quantile(1.0 - END_TRIM));
    let extent_m = high - low;
    if extent_m <= HAND_ONLY_EXTENT_M || extent_m > MAX_ARM_EXTENT_M {
        return Some(HandLocation { position: mean, extent_m, arm: false });
    }
    let up = up.try_normalize(1e-12).unwrap_or_else(Vector3::y);
    let distal_score = |s: f64| {
        let end = mean + axis * s;
        let rel = end - head;
        let height = rel.dot(&up);
        let continuity = expected.map_or(0.0, |(e, w)| w * (end - e).norm());
        height + (rel - up * height).norm() - continuity
    };
    let high_is_distal = distal_score(high) >= distal_score(low);
    let (mut sum, mut weight) = (Vector3::zeros(), 0.0);
    let mut window: Vec<&WeightedPoint> = Vec::new();
    for (s, p) in &along {
        let in_hand = if high_is_distal { *s >= high - HAND_LENGTH_M } else { *s <= low + HAND_LENGTH_M };
        let within = *s >= low && *s <= high;
        if in_hand && within {
            sum += p.position * p.weight;
            weight += p.weight;
            window.push(p);
        }
    }
    if weight < MIN_HAND_SHARE * total || (sum / weight - head).norm() < HEAD_CLEARANCE_M {
        return Some(HandLocation { position: mean, extent_m, arm: false });
    }
    // Along the arm, the window's centroid: a hand's length from the distal end. Across it,
    // the window's median, then its densest skin ([`densest_across`]).
    let mut start = sum / weight;
    for across in (0..3).filter(|&i| i != main).map(|i| eigen.eigenvectors.column(i).into_owned()) {
        let median = weighted_median(&window, |p| p.position.dot(&across));
        start += across * (median - start.dot(&across));
    }
    let position = densest_across(&window, start, axis);
    Some(HandLocation { position, extent_m, arm: true })
}

/// Moves `start` across the arm's `axis` to where the most of `window`'s skin within
/// [`HAND_RADIUS_M`] of it lies (mean shift with a flat kernel, each step's move along the
/// axis taken away). A hand's window, a slab across the arm, also takes in whatever else the
/// cluster holds beside the hand (a piece of the body, a depth ghost): its centroid lands
/// between them, while the palm, wider than the wrist, is where the skin is densest. Along
/// the arm the place stays where the hand's length puts it: there the densest skin is often
/// the fingers. Measured on a replay of the shared real session: a second blob 20 cm beside
/// the right hand held 37 % of its window, whose centroid was 7.6 cm off; the median across
/// the arm was 3.5 cm off, the densest place from there 1.8 cm.
fn densest_across(window: &[&WeightedPoint], start: Vector3<f64>, axis: Vector3<f64>) -> Vector3<f64> {
    let mut at = start;
    for _ in 0..MEAN_SHIFT_STEPS {
        let (mut sum, mut weight) = (Vector3::zeros(), 0.0);
        for p in window {
            if (p.position - at).norm() <= HAND_RADIUS_M {
                sum += p.position * p.weight;
                weight += p.weight;
            }
        }
        if weight <= 0.0 {
            break;
        }
        let shift = sum / weight - at;
        let shift = shift - axis * shift.dot(&axis);
        at += shift;
        if shift.norm() < MEAN_SHIFT_TOLERANCE_M {
            break;
        }
    }
    at
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::em::{fit_mixture, EmConfig};

    /// Points on the surface of a capsule from `a` to `b` of radius `r`, `n` along and 8
    /// around, weight 1.
    fn capsule(a: Vector3<f64>, b: Vector3<f64>, r: f64, n: usize) -> Vec<WeightedPoint> {
        let axis = (b - a).normalize();
        let side = axis.cross(&Vector3::z()).try_normalize(1e-9).unwrap_or_else(Vector3::x);
        let other = axis.cross(&side);
        let mut out = Vec::new();
        for i in 0..n {
            let c = a + (b - a) * (i as f64 / (n - 1) as f64);
            for k in 0..8 {
                let angle = k as f64 * std::f64::consts::TAU / 8.0;
                out.push(WeightedPoint {
                    position: c + (side * angle.cos() + other * angle.sin()) * r,
                    velocity: Vector3::zeros(),
                    weight: 1.0,
                });
            }
        }
        out
    }

    fn centroid(points: &[WeightedPoint]) -> Vector3<f64> {
        points.iter().fold(Vector3::zeros(), |s, p| s + p.position) / points.len() as f64
    }

    fn locate(points: &[WeightedPoint], seed: Vector3<f64>, head: Vector3<f64>) -> HandLocation {
        let fit =
            fit_mixture(points, &[(seed, Vector3::zeros())], &EmConfig { outliers: false, ..EmConfig::default() })
                .expect("fit");
        locate_hand(points, &fit.components, 0, head, Vector3::y(), None).expect("members")
    }

    #[test]
    fn a_bare_forearm_raised_to_sign_gives_the_hand_not_the_forearm() {
        // Head at 1.6 m; the elbow by the body at 1.1 m, the forearm rising forwards to a
        // hand at 1.35 m: skin from the elbow to the fingertips.
        let head = Vector3::new(0.0, 1.6, 0.0);
        let elbow = Vector3::new(0.2, 1.1, 0.05);
        let wrist = Vector3::new(0.22, 1.32, 0.25);
        let tips = wrist + (wrist - elbow).normalize() * 0.18;
        let hand_centre = wrist + (tips - wrist) * 0.45;
        let mut points = capsule(elbow, wrist, 0.03, 30);
        points.extend(capsule(wrist, tips, 0.04, 20));
        let whole = centroid(&points);
        assert!((whole - hand_centre).norm() > 0.1, "the centroid is on the forearm");
        let found = locate(&points, whole, head);
        assert!(found.arm);
        assert!((found.position - hand_centre).norm() < 0.035, "{:?} vs {hand_centre:?}", found.position);
    }

    #[test]
    fn skin_beside_the_hand_that_the_cluster_took_in_does_not_pull_the_hand_sideways() {
        // A raised bare forearm and hand, and beside the hand (13 cm across the arm) a patch
        // of skin the hand's cluster took in: a piece of the body, or a depth ghost.
        let head = Vector3::new(0.0, 1.6, 0.0);
        let elbow = Vector3::new(0.2, 1.1, 0.05);
        let wrist = Vector3::new(0.22, 1.32, 0.25);
        let along = (wrist - elbow).normalize();
        let tips = wrist + along * 0.18;
        let hand_centre = wrist + (tips - wrist) * 0.45;
        let across = along.cross(&Vector3::y()).normalize();
        let patch = hand_centre + across * 0.13;
        let mut points = capsule(elbow, wrist, 0.03, 30);
        points.extend(capsule(wrist, tips, 0.04, 20));
        points.extend(capsule(patch - along * 0.02, patch + along * 0.02, 0.015, 13));
        // What the distal hand's length alone gives: its centroid, pulled towards the patch.
        let fit = fit_mixture(
            &points,
            &[(centroid(&points), Vector3::zeros())],
            &EmConfig { outliers: false, ..EmConfig::default() },
        )
        .expect("fit");
        let window: Vec<WeightedPoint> = points
            .iter()
            .filter(|p| (p.position - tips).dot(&-along) <= HAND_LENGTH_M && (p.position - tips).dot(&along) <= 0.0)
            .copied()
            .collect();
        assert!((centroid(&window) - hand_centre).norm() > 0.03, "the patch pulls the window's centroid");
        let found = locate_hand(&points, &fit.components, 0, head, Vector3::y(), None).expect("members");
        assert!(found.arm);
        assert!((found.position - hand_centre).norm() < 0.02, "{:?} vs {hand_centre:?}", found.position);
    }

    #[test]
    fn a_forearm_resting_forwards_in_the_lap_gives_the_hand_in_front() {
        let head = Vector3::new(0.0, 1.6, 0.0);
        let elbow = Vector3::new(0.22, 1.0, 0.0);
        let wrist = Vector3::new(0.2, 0.98, 0.26);
        let tips = wrist + (wrist - elbow).normalize() * 0.18;
        let hand_centre = wrist + (tips - wrist) * 0.45;
        let mut points = capsule(elbow, wrist, 0.03, 30);
        points.extend(capsule(wrist, tips, 0.04, 20));
        let whole = centroid(&points);
        let found = locate(&points, whole, head);
        assert!((found.position - hand_centre).norm() < 0.035, "{:?} vs {hand_centre:?}", found.position);
    }

    #[test]
    fn a_level_forearm_pointing_forwards_takes_the_end_nearer_the_expected_hand() {
        // The elbow by the body a little higher than the hand, which points at the cameras:
        // height and reach alone score the two ends nearly alike.
        let head = Vector3::new(0.0, 1.6, 0.0);
        let elbow = Vector3::new(0.28, 1.13, 0.02);
        let wrist = Vector3::new(0.27, 1.09, 0.2);
        let tips = wrist + (wrist - elbow).normalize() * 0.18;
        let hand_centre = wrist + (tips - wrist) * 0.45;
        let elbow_end = elbow + (wrist - elbow).normalize() * 0.085;
        let mut points = capsule(elbow, wrist, 0.03, 30);
        points.extend(capsule(wrist, tips, 0.04, 20));
        let whole = centroid(&points);
        let fit =
            fit_mixture(&points, &[(whole, Vector3::zeros())], &EmConfig { outliers: false, ..EmConfig::default() })
                .expect("fit");
        let at = |expected| locate_hand(&points, &fit.components, 0, head, Vector3::y(), expected).expect("members");
        // Expected at the hand (last frame's hand, 2 cm off): the hand.
        let found = at(Some((hand_centre + Vector3::new(0.0, 0.02, 0.0), continuity_weight(0.01))));
        assert!(found.arm);
        assert!((found.position - hand_centre).norm() < 0.035, "{:?} vs {hand_centre:?}", found.position);
        // Expected at the elbow (a track that sits there): the continuity term decides, so
        // it must be what moved the choice.
        let found = at(Some((elbow_end, continuity_weight(0.01))));
        assert!((found.position - hand_centre).norm() > 0.1, "the expected end wins a tie");
        // At 6 fps the prediction says nothing of which end: the rule alone.
        assert_eq!(continuity_weight(0.28), 0.0);
        let found = at(None);
        assert!(found.arm);
    }

    #[test]
    fn skin_longer_than_an_arm_keeps_its_centroid() {
        // A skin-coloured shirt from the other shoulder to the fingertips: 0.95 m of "skin",
        // more than a bare arm.
        let head = Vector3::new(0.0, 1.6, 0.0);
        let shoulder = Vector3::new(-0.2, 1.4, 0.0);
        let tips = Vector3::new(0.4, 1.2, 0.7);
        let points = capsule(shoulder, tips, 0.04, 60);
        let whole = centroid(&points);
        let found = locate(&points, whole, head);
        assert!(!found.arm);
        assert!(found.extent_m > MAX_ARM_EXTENT_M);
        assert!((found.position - whole).norm() < 0.01);
    }

    #[test]
    fn a_hand_whose_cluster_reached_into_the_face_keeps_its_centroid() {
        // A hand below the chin whose component took in the chin and neck: the upper end is
        // the head's skin, not the hand.
        let head = Vector3::new(0.0, 1.6, 0.0);
        let hand = Vector3::new(-0.05, 1.3, 0.15);
        let mut points = capsule(hand - Vector3::y() * 0.08, hand + Vector3::y() * 0.08, 0.04, 20);
        points.extend(capsule(Vector3::new(0.0, 1.45, 0.08), Vector3::new(0.0, 1.56, 0.06), 0.04, 15));
        let whole = centroid(&points);
        let found = locate(&points, whole, head);
        assert!(!found.arm, "{found:?}");
        assert!((found.position - whole).norm() < 0.01);
    }

    #[test]
    fn a_few_stray_depths_beyond_a_hand_do_not_move_it() {
        let head = Vector3::new(0.0, 1.6, 0.0);
        let hand = Vector3::new(-0.2, 1.4, 0.3);
        let mut points = capsule(hand - Vector3::y() * 0.08, hand + Vector3::y() * 0.08, 0.04, 30);
        // A thin trail of stray points above it, as ghosts on a skin-coloured shirt give.
        points.extend(capsule(hand + Vector3::y() * 0.1, hand + Vector3::y() * 0.3, 0.01, 5));
        let whole = centroid(&points);
        let found = locate(&points, whole, head);
        assert!(!found.arm, "{found:?}");
        assert!((found.position - whole).norm() < 0.01);
    }

    #[test]
    fn a_hand_alone_keeps_its_centroid() {
        let head = Vector3::new(0.0, 1.6, 0.0);
        let wrist = Vector3::new(0.2, 1.2, 0.2);
        let tips = Vector3::new(0.2, 1.38, 0.22);
        let points = capsule(wrist, tips, 0.04, 20);
        let whole = centroid(&points);
        let found = locate(&points, whole, head);
        assert!(!found.arm);
        assert!((found.position - whole).norm() < 0.01);
    }

    #[test]
    fn no_members_and_bad_indices_are_none_not_a_panic() {
        let head = Vector3::new(0.0, 1.6, 0.0);
        assert!(locate_hand(&[], &[], 0, head, Vector3::y(), None).is_none());
        let points = capsule(Vector3::new(0.2, 1.2, 0.2), Vector3::new(0.2, 1.3, 0.2), 0.04, 5);
        let fit = fit_mixture(&points, &[(Vector3::new(0.2, 1.25, 0.2), Vector3::zeros())], &EmConfig::default())
            .expect("fit");
        assert!(locate_hand(&points, &fit.components, 3, head, Vector3::y(), None).is_none());
    }
}
