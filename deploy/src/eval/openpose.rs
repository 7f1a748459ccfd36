//! OpenPose JSON keypoints as a [`Reference`]: the layout Pose2Sim and anipose use, one
//! folder per camera holding one `*_keypoints.json` per frame.
//!
//! ```text
//! REF/
//!   cam01_json/                              one folder per camera, matched to the rig's
//!     cam01_000000000000_keypoints.json      cameras by `match_cameras` (`cam01` is camera 1,
//!     cam01_000000000001_keypoints.json      or camera 0 of a rig numbered from 0)
//!   cam02_json/ ...
//! ```
//!
//! Rules:
//! - **Frame numbers**: the last run of digits in a file's name, minus the smallest such
//!   number over all camera folders, so that numbering from 1 (or from a video's first
//!   frame, 120) still gives frame 0 at the first file, and the cameras stay aligned when
//!   one of them has no file for the first frames. A number that appears twice in one folder
//!   is an error.
//! - **Keypoints**: `pose_keypoints_2d` is `[x, y, c, ...]`; BODY_25 and BODY_25B both
//!   have 25 keypoints (in different orders) so the order is given ([`KeypointOrder`]),
//!   COCO has 18; Pose2Sim's RTMPose models write COCO_17 (17), HALPE_26 (26) and COCO_133
//!   (133, both hands included) the same way, AlphaPose HALPE_136 (136, both hands). A
//!   keypoint with confidence 0 is missing.
//! - **Head and hands** ([`OpenPosePoints`]): by default the points handflow publishes, as the
//!   `handflow-reference/1` files define them: the head is the ear midpoint (the nose where an
//!   ear is not visible), a hand its palm centre (the mean of hand keypoints 0, 5, 9, 13, 17
//!   from `hand_left_keypoints_2d` / `hand_right_keypoints_2d`, or COCO_133's hands) where
//!   the files hold hand keypoints, else estimated from its wrist and elbow
//!   ([`PALM_BEYOND_WRIST`]); or the nose and the wrists. The person's
//!   own sides (OpenPose's `LWrist` is the person's left, as handflow's `left_hand`).
//! - **The person**: the one with the highest summed confidence over all keypoints in
//!   that view and frame (the first on a tie): the subject in front of a rig is the most
//!   completely detected; a passer-by or a poster is partial. Frames with empty `people` are
//!   empty.
//! - 3D points are triangulated from two or more views ([`super::triangulation`]).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{bail, ensure, Context, Result};
use handflow_ingest::camera_match::{camera_number, match_cameras};
use handflow_protocol::Rig;
use nalgebra::Point2;
use serde::Deserialize;

use super::reference::{read_capped, Reference, ReferenceDefinition, ReferenceFrame, ReferenceObject};
use super::tracks::PALM_WIDTH_M;

/// Largest keypoint file read, bytes (one frame of BODY_135 with 100 people is ~1 MB).
pub const MAX_KEYPOINT_FILE_BYTES: u64 = 16 << 20;

/// Most keypoint files read per camera folder (an hour at 30 frames/s is 108 000).
pub const MAX_FILES_PER_CAMERA: usize = 1_000_000;

/// The name every keypoint file ends with.
const KEYPOINTS_SUFFIX: &str = "_keypoints.json";

/// The keypoint order of `pose_keypoints_2d`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum KeypointOrder {
    /// OpenPose's default BODY_25: nose 0, right wrist 4, left wrist 7, right ear 17, left
    /// ear 18.
    Body25,
    /// OpenPose's experimental BODY_25B (COCO order first): nose 0, left ear 3, right ear 4,
    /// left wrist 9, right wrist 10.
    Body25b,
    /// OpenPose's COCO, 18 keypoints: nose 0, right wrist 4, left wrist 7, right ear 16, left
    /// ear 17.
    Coco,
    /// COCO's own 17 keypoints (RTMPose and other top-down models as Pose2Sim writes them):
    /// nose 0, left ear 3, right ear 4, left wrist 9, right wrist 10.
    Coco17,
    /// HALPE_26 (Pose2Sim's default body model, RTMPose or AlphaPose): COCO's 17 first, then
    /// head, neck, hip and feet.
    Halpe26,
    /// COCO-WholeBody's 133 (Pose2Sim's whole-body model): COCO's 17, feet, 68 face points,
    /// then each hand's 21 (left from 91, right from 112).
    Coco133,
    /// HALPE_136 (AlphaPose's full body): HALPE_26, 68 face points, then each hand's 21 (left
    /// from 94, right from 115).
    Halpe136,
}

/// Where a model keeps the keypoints the reference is made of.
struct BodyKeypoints {
    nose: usize,
    /// Left, right.
    ears: [usize; 2],
    /// Left, right.
    wrists: [usize; 2],
    /// Left, right.
    elbows: [usize; 2],
}

impl KeypointOrder {
    /// Number of keypoints of this order.
    pub fn keypoint_count(self) -> usize {
        match self {
            KeypointOrder::Body25 | KeypointOrder::Body25b => 25,
            KeypointOrder::Coco => 18,
            KeypointOrder::Coco17 => 17,
            KeypointOrder::Halpe26 => 26,
            KeypointOrder::Coco133 => 133,
            KeypointOrder::Halpe136 => 136,
        }
    }

    fn body_keypoints(self) -> BodyKeypoints {
        match self {
            KeypointOrder::Body25 => BodyKeypoints { nose: 0, ears: [18, 17], wrists: [7, 4], elbows: [6, 3] },
            KeypointOrder::Coco => BodyKeypoints { nose: 0, ears: [17, 16], wrists: [7, 4], elbows: [6, 3] },
            KeypointOrder::Body25b
            | KeypointOrder::Coco17
            | KeypointOrder::Halpe26
            | KeypointOrder::Coco133
            | KeypointOrder::Halpe136 => BodyKeypoints { nose: 0, ears: [3, 4], wrists: [9, 10], elbows: [7, 8] },
        }
    }

    /// The first of each hand's 21 keypoints (left, right) when `pose_keypoints_2d` holds
    /// them.
    fn hands_in_pose(self) -> Option<[usize; 2]> {
        match self {
            KeypointOrder::Coco133 => Some([91, 112]),
            KeypointOrder::Halpe136 => Some([94, 115]),
            _ => None,
        }
    }

    /// The model's name (`BODY_25`, `BODY_25B`, `COCO`, `COCO_17`, `HALPE_26`, `COCO_133`,
    /// `HALPE_136`).
    pub fn model_name(self) -> &'static str {
        match self {
            KeypointOrder::Body25 => "BODY_25",
            KeypointOrder::Body25b => "BODY_25B",
            KeypointOrder::Coco => "COCO",
            KeypointOrder::Coco17 => "COCO_17",
            KeypointOrder::Halpe26 => "HALPE_26",
            KeypointOrder::Coco133 => "COCO_133",
            KeypointOrder::Halpe136 => "HALPE_136",
        }
    }

    /// The order of `count` keypoints when none was given: 25 is BODY_25 (BODY_25B has to
    /// be named), the other counts are one model each.
    fn from_count(count: usize) -> Option<KeypointOrder> {
        match count {
            17 => Some(KeypointOrder::Coco17),
            18 => Some(KeypointOrder::Coco),
            25 => Some(KeypointOrder::Body25),
            26 => Some(KeypointOrder::Halpe26),
            133 => Some(KeypointOrder::Coco133),
            136 => Some(KeypointOrder::Halpe136),
            _ => None,
        }
    }
}

/// Which points of an OpenPose person stand for the head and the hands.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum OpenPosePoints {
    /// What handflow publishes: the head's centre as the ear midpoint (the nose where an ear
    /// is not visible) and each hand's palm centre (the mean of hand keypoints 0, 5, 9, 13,
    /// 17: the wrist and the four knuckles) where the files hold hand keypoints, else
    /// estimated from the wrist and the elbow ([`PALM_BEYOND_WRIST`]). The
    /// `handflow-reference/1` files define head and hands the same way.
    #[default]
    Centres,
    /// The nose and the wrists (EVALUATION.md's OpenPose definition): a nose lies about
    /// 10 cm in front of the head's centre and a wrist 6 to 7 cm behind the palm's.
    NoseAndWrists,
}

/// Least mean confidence of a hand's five palm keypoints: OpenPose's default threshold for
/// drawing hand keypoints (`--hand_render_threshold`); a hand hidden or out of its crop
/// still gets keypoints, at lower confidence.
pub const HAND_MIN_CONFIDENCE: f64 = 0.2;

/// How far beyond the wrist the palm centre lies along the forearm, as a share of the
/// forearm (elbow to wrist), for files without hand keypoints. The palm centre (the mean of
/// the wrist and four knuckles) lies about 6.6 cm beyond an adult's wrist, whose forearm is
/// 23 to 27 cm long: 0.25 to 0.29. On the shared real session MediaPipe's own joints give
/// 0.32 (median of 763 views; quartiles 0.27 and 0.40: a bent wrist). Projected, the share is
/// the same in every view when the hand continues the forearm.
pub const PALM_BEYOND_WRIST: f64 = 0.3;

/// Hand keypoints of the palm centre (OpenPose's and MediaPipe's hand numbering alike).
const PALM_KEYPOINTS: [usize; 5] = [0, 5, 9, 13, 17];

/// Keypoints of one hand.
const HAND_KEYPOINTS: usize = 21;

#[derive(Deserialize)]
struct KeypointFile {
    people: Vec<Person>,
}

#[derive(Deserialize)]
struct Person {
    #[serde(default)]
    pose_keypoints_2d: Vec<f64>,
    #[serde(default)]
    hand_left_keypoints_2d: Vec<f64>,
    #[serde(default)]
    hand_right_keypoints_2d: Vec<f64>,
}

/// What one view's main person says of head and hands.
struct PersonPoints {
    head: Option<Point2<f64>>,
    /// Left, right.
    wrists: [Option<Point2<f64>>; 2],
    /// Left, right: the palm centre estimated from the wrist and the elbow
    /// ([`PALM_BEYOND_WRIST`]), for files without hand keypoints.
    forearm_palms: [Option<Point2<f64>>; 2],
    /// Left, right; `None` also where the files hold no hand keypoints.
    palms: [Option<Point2<f64>>; 2],
    /// Whether the person has hand keypoints at all (OpenPose run with `--hand`, or a
    /// whole-body model), detected or not.
    has_hand_keypoints: bool,
}

/// Keypoint `k` of `(x, y, confidence)` triples, when detected (confidence above 0).
fn keypoint(values: &[f64], k: usize) -> Option<(Point2<f64>, f64)> {
    let triple = values.get(3 * k..3 * k + 3)?;
    (triple[2] > 0.0).then(|| (Point2::new(triple[0], triple[1]), triple[2]))
}

/// The palm centre of a hand's 21 keypoints (`hand`), kept as the shared session's
/// reference keeps MediaPipe's: its five palm keypoints detected with a mean confidence of
/// [`HAND_MIN_CONFIDENCE`] or more, and its wrist within the hand's own size (the widest
/// distance between two of the five) of the body model's wrist of that side, so a hand
/// found on the wrong arm or on a background is left out.
fn palm_centre(hand: &[f64], body_wrist: Option<Point2<f64>>) -> Option<Point2<f64>> {
    let points: Vec<(Point2<f64>, f64)> = PALM_KEYPOINTS.iter().map(|&k| keypoint(hand, k)).collect::<Option<_>>()?;
    let confidence = points.iter().map(|(_, c)| c).sum::<f64>() / points.len() as f64;
    if confidence < HAND_MIN_CONFIDENCE {
        return None;
    }
    let size = points.iter().flat_map(|(a, _)| points.iter().map(move |(b, _)| (a - b).norm())).fold(0.0, f64::max);
    if (points[0].0 - body_wrist?).norm() > size {
        return None;
    }
    let sum = points.iter().fold(nalgebra::Vector2::zeros(), |acc, (p, _)| acc + p.coords);
    Some(Point2::from(sum / points.len() as f64))
}

impl PersonPoints {
    fn of(person: &Person, order: KeypointOrder, points: OpenPosePoints) -> PersonPoints {
        let body = order.body_keypoints();
        let pose = &person.pose_keypoints_2d;
        let at = |k: usize| keypoint(pose, k).map(|(p, _)| p);
        let nose = at(body.nose);
        let head = match (points, at(body.ears[0]), at(body.ears[1])) {
            (OpenPosePoints::Centres, Some(left), Some(right)) => Some(nalgebra::center(&left, &right)),
            _ => nose,
        };
        let wrists = body.wrists.map(at);
        let elbows = body.elbows.map(at);
        let forearm_palms =
            [0, 1].map(|side| Some(wrists[side]? + PALM_BEYOND_WRIST * (wrists[side]? - elbows[side]?)));
        let hands: [&[f64]; 2] = match order.hands_in_pose() {
            Some(first) => first.map(|f| pose.get(3 * f..3 * (f + HAND_KEYPOINTS)).unwrap_or(&[])),
            None => [&person.hand_left_keypoints_2d, &person.hand_right_keypoints_2d],
        };
        let has_hand_keypoints = hands.iter().any(|h| h.len() == 3 * HAND_KEYPOINTS);
        let palms = [0, 1].map(|side| match points {
            OpenPosePoints::Centres => palm_centre(hands[side], wrists[side]),
            OpenPosePoints::NoseAndWrists => None,
        });
        PersonPoints { head, wrists, forearm_palms, palms, has_hand_keypoints }
    }
}

/// Reads an OpenPose folder (see the [module documentation](self)) as a reference for
/// `rig`'s cameras. `order` is the keypoint order; `None` takes it from the keypoint count
/// (17 COCO_17, 18 COCO, 25 BODY_25, 26 HALPE_26, 133 COCO_133, 136 HALPE_136); a count
/// that does not fit the order is an error. `points` says which points stand for head and
/// hands.
/// `video_frames` maps, per rig camera, a position in that camera's video to the recording's
/// frame number ([`video_frames_of`]): OpenPose numbers a video's frames, and where a
/// caliscope session's cameras dropped different frames, position k is not frame k in every
/// camera; a file whose position is in no frame set is not read. `None`: file k is frame k.
pub fn read_openpose(
    dir: &Path,
    rig: &Rig,
    order: Option<KeypointOrder>,
    points: OpenPosePoints,
    video_frames: Option<&[BTreeMap<usize, u64>]>,
) -> Result<Reference> {
    let at = dir.display();
    let mut folders: Vec<(String, PathBuf)> = Vec::new();
    let mut loose_keypoint_files = 0;
    for entry in std::fs::read_dir(dir).with_context(|| format!("reading the OpenPose folder `{at}`"))? {
        let entry = entry.with_context(|| format!("reading the OpenPose folder `{at}`"))?;
        let path = entry.path();
        let name = entry.file_name().to_string_lossy().into_owned();
        if path.is_dir() {
            folders.push((name, path));
        } else if name.ends_with(KEYPOINTS_SUFFIX) {
            loose_keypoint_files += 1;
        }
    }
    ensure!(
        loose_keypoint_files == 0 || !folders.is_empty(),
        "`{at}` holds {loose_keypoint_files} keypoint files itself: expected one folder per camera, each holding \
         that camera's `*{KEYPOINTS_SUFFIX}` files"
    );
    ensure!(
        !folders.is_empty(),
        "`{at}` has no camera folders: expected one per camera holding `*{KEYPOINTS_SUFFIX}` files"
    );
    folders.sort();
    let rig_names: Vec<String> = rig.cameras.iter().map(|c| c.name.clone()).collect();
    let folder_names: Vec<String> = folders.iter().map(|(n, _)| n.clone()).collect();
    let matched =
        match_cameras(&rig_names, &folder_names).map_err(|e| anyhow::anyhow!("`{at}` camera folders: {e}"))?;

    // Per rig camera: (file number, path), sorted.
    let mut files: Vec<Vec<(u64, PathBuf)>> = Vec::with_capacity(matched.len());
    for &i in &matched {
        files.push(keypoint_files(&folders[i].1)?);
    }
    let first = files.iter().filter_map(|f| f.first().map(|(n, _)| *n)).min().unwrap_or(0);

    let mut order = order;
    let mut frames: BTreeMap<u64, ReferenceFrame> = BTreeMap::new();
    // Per frame: the head's, the wrists' and the palms' pixel per camera (wrists and palms
    // left, right); which of the two stand for the hands is decided once every file is read.
    type Views = Vec<Option<Point2<f64>>>;
    let mut pixels: BTreeMap<u64, [Views; 7]> = BTreeMap::new();
    let mut hand_keypoints = false;
    for (c, camera_files) in files.iter().enumerate() {
        for (number, path) in camera_files {
            let position = number - first;
            let frame = match video_frames {
                Some(maps) => match usize::try_from(position).ok().and_then(|p| maps.get(c)?.get(&p)) {
                    Some(&frame) => frame,
                    None => continue,
                },
                None => position,
            };
            let people = read_keypoint_file(path)?;
            let Some(person) = main_person(path, &people, &mut order)? else {
                frames.entry(frame).or_default();
                continue;
            };
            let Some(order) = order else { continue };
            let found = PersonPoints::of(person, order, points);
            hand_keypoints |= found.has_hand_keypoints;
            let slots = pixels.entry(frame).or_insert_with(|| std::array::from_fn(|_| vec![None; rig.cameras.len()]));
            let views = [
                found.head,
                found.wrists[0],
                found.wrists[1],
                found.forearm_palms[0],
                found.forearm_palms[1],
                found.palms[0],
                found.palms[1],
            ];
            for (slot, pixel) in slots.iter_mut().zip(views) {
                slot[c] = pixel;
            }
        }
    }
    let palms = hand_keypoints && points == OpenPosePoints::Centres;
    for (frame, [head, left_wrist, right_wrist, left_forearm, right_forearm, left_palm, right_palm]) in pixels {
        let entry = frames.entry(frame).or_default();
        let hands = match (points, palms) {
            (OpenPosePoints::NoseAndWrists, _) => [left_wrist, right_wrist],
            (OpenPosePoints::Centres, true) => [left_palm, right_palm],
            (OpenPosePoints::Centres, false) => [left_forearm, right_forearm],
        };
        for (k, views) in std::iter::once(head).chain(hands).enumerate() {
            if views.iter().any(Option::is_some) {
                entry[k] = Some(ReferenceObject::new(rig, views, None));
            }
        }
    }
    let model = order.map_or("unknown keypoints (no person detected)", KeypointOrder::model_name);
    let (head, hands) = match (points, palms) {
        (OpenPosePoints::NoseAndWrists, _) => ("nose", "wrist"),
        (OpenPosePoints::Centres, true) => {
            ("ear midpoint (nose where an ear is not visible)", "palm centre (hand keypoints 0, 5, 9, 13, 17)")
        }
        (OpenPosePoints::Centres, false) => (
            "ear midpoint (nose where an ear is not visible)",
            "palm centre estimated as the wrist plus 0.3 of the forearm (the files hold no hand keypoints)",
        ),
    };
    Ok(Reference {
        definition: ReferenceDefinition {
            format: format!("openpose {model}"),
            head: head.to_owned(),
            hands: hands.to_owned(),
        },
        palm_width_m: PALM_WIDTH_M,
        frames,
    })
}

/// Per camera, the recording's frame number of each position in that camera's video, from
/// the frame sets' `positions` (per set, per camera; `None` where the camera has no frame in
/// the set) and their frame numbers.
pub fn video_frames_of(frames: &[u64], positions: &[Vec<Option<usize>>], cameras: usize) -> Vec<BTreeMap<usize, u64>> {
    let mut maps = vec![BTreeMap::new(); cameras];
    for (&frame, set) in frames.iter().zip(positions) {
        for (map, position) in maps.iter_mut().zip(set) {
            if let Some(position) = *position {
                map.insert(position, frame);
            }
        }
    }
    maps
}

/// The `*_keypoints.json` files of one camera folder with their numbers, sorted.
fn keypoint_files(folder: &Path) -> Result<Vec<(u64, PathBuf)>> {
    let at = folder.display();
    let mut files = Vec::new();
    for entry in std::fs::read_dir(folder).with_context(|| format!("reading `{at}`"))? {
        let entry = entry.with_context(|| format!("reading `{at}`"))?;
        let name = entry.file_name().to_string_lossy().into_owned();
        let Some(stem) = name.strip_suffix(KEYPOINTS_SUFFIX) else { continue };
        let Some(number) = camera_number(stem) else {
            bail!("`{}`: no frame number in the name", entry.path().display())
        };
        files.push((number, entry.path()));
        ensure!(files.len() <= MAX_FILES_PER_CAMERA, "`{at}`: more than {MAX_FILES_PER_CAMERA} keypoint files");
    }
    ensure!(!files.is_empty(), "`{at}` holds no `*{KEYPOINTS_SUFFIX}` files");
    files.sort();
    for pair in files.windows(2) {
        ensure!(
            pair[0].0 != pair[1].0,
            "`{}` and `{}` have the same frame number {}",
            pair[0].1.display(),
            pair[1].1.display(),
            pair[0].0
        );
    }
    Ok(files)
}

fn read_keypoint_file(path: &Path) -> Result<Vec<Person>> {
    let text = read_capped(path, MAX_KEYPOINT_FILE_BYTES)?;
    let file: KeypointFile =
        serde_json::from_str(&text).with_context(|| format!("`{}`: not an OpenPose keypoint file", path.display()))?;
    Ok(file.people)
}

/// The keypoints of the person with the highest summed confidence, after checking every
/// person's keypoints against `order` (set from the count when `None`).
fn main_person<'a>(path: &Path, people: &'a [Person], order: &mut Option<KeypointOrder>) -> Result<Option<&'a Person>> {
    let mut best: Option<(f64, &Person)> = None;
    for (p, person) in people.iter().enumerate() {
        let values = &person.pose_keypoints_2d;
        let at = || format!("`{}` person {p} pose_keypoints_2d", path.display());
        let count = values.len() / 3;
        ensure!(count * 3 == values.len(), "{}: {} numbers, not (x, y, confidence) triples", at(), values.len());
        let expected = match *order {
            Some(o) => o,
            None => {
                let Some(o) = KeypointOrder::from_count(count) else {
                    bail!(
                        "{}: {count} keypoints; BODY_25 and BODY_25B (25), COCO (18), COCO_17 (17), HALPE_26 (26) and \
                         COCO_133 (133), HALPE_136 (136) are read",
                        at()
                    )
                };
                *order = Some(o);
                o
            }
        };
        ensure!(
            count == expected.keypoint_count(),
            "{}: {count} keypoints, but {} has {}",
            at(),
            expected.model_name(),
            expected.keypoint_count()
        );
        ensure!(values.iter().all(|v| v.is_finite()), "{}: a number is not finite", at());
        for (name, hand) in [
            ("hand_left_keypoints_2d", &person.hand_left_keypoints_2d),
            ("hand_right_keypoints_2d", &person.hand_right_keypoints_2d),
        ] {
            ensure!(
                hand.is_empty() || hand.len() == 3 * HAND_KEYPOINTS,
                "`{}` person {p} {name}: {} numbers, expected none or {} ({HAND_KEYPOINTS} keypoints)",
                path.display(),
                hand.len(),
                3 * HAND_KEYPOINTS
            );
            ensure!(
                hand.iter().all(|v| v.is_finite()),
                "`{}` person {p} {name}: a number is not finite",
                path.display()
            );
        }
        let total: f64 = values.iter().skip(2).step_by(3).sum();
        if best.as_ref().is_none_or(|(b, _)| total > *b) {
            best = Some((total, person));
        }
    }
    Ok(best.map(|(_, person)| person))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval::reference::tests::{fixtures, rig3};
    use nalgebra::{Point3, Vector3};

    #[test]
    fn reads_the_fixture_choosing_the_main_person_and_skipping_missing_keypoints() {
        let rig = rig3();
        let r = read_openpose(&fixtures().join("openpose/body25"), &rig, None, OpenPosePoints::NoseAndWrists, None)
            .unwrap();
        assert_eq!(r.definition.format, "openpose BODY_25");
        assert_eq!((r.definition.head.as_str(), r.definition.hands.as_str()), ("nose", "wrist"));
        // Files numbered from 1 give frames 0, 1, 2.
        assert_eq!(r.frames.keys().copied().collect::<Vec<_>>(), vec![0, 1, 2]);
        // Frame 0: in cam01 (rig cam_0) two people; the second, more confident, is chosen.
        let head = r.frames[&0][0].as_ref().unwrap();
        assert_eq!(head.pixels[0], Some(Point2::new(600.0, 200.0)));
        // Left hand is OpenPose's LWrist (7), right hand RWrist (4).
        assert_eq!(r.frames[&0][1].as_ref().unwrap().pixels[0], Some(Point2::new(700.0, 400.0)));
        assert_eq!(r.frames[&0][2].as_ref().unwrap().pixels[0], Some(Point2::new(500.0, 410.0)));
        // cam02 (rig cam_1): the right wrist has confidence 0.
        assert_eq!(r.frames[&0][2].as_ref().unwrap().pixels[1], None);
        assert!(r.frames[&0][1].as_ref().unwrap().pixels[1].is_some());
        // Frame 1: empty `people` in every view.
        assert!(r.frames[&1].iter().all(Option::is_none));
        // Frame 2: only cam03 (rig cam_2) has a file.
        let head = r.frames[&2][0].as_ref().unwrap();
        assert_eq!(head.pixels, vec![None, None, Some(Point2::new(640.0, 210.0))]);
        assert_eq!(head.point, None);
    }

    #[test]
    fn body25b_and_coco_take_their_own_wrists() {
        let rig = rig3();
        let r = read_openpose(
            &fixtures().join("openpose/body25b"),
            &rig,
            Some(KeypointOrder::Body25b),
            OpenPosePoints::NoseAndWrists,
            None,
        )
        .unwrap();
        assert_eq!(r.definition.format, "openpose BODY_25B");
        let frame = &r.frames[&0];
        assert_eq!(frame[1].as_ref().unwrap().pixels[0], Some(Point2::new(709.0, 409.0)));
        assert_eq!(frame[2].as_ref().unwrap().pixels[0], Some(Point2::new(510.0, 410.0)));
        // The same files read as BODY_25 take other keypoints; as COCO they are refused.
        let as_body25 =
            read_openpose(&fixtures().join("openpose/body25b"), &rig, None, OpenPosePoints::NoseAndWrists, None)
                .unwrap();
        assert_ne!(as_body25.frames[&0][1], r.frames[&0][1]);
        let err = format!(
            "{:#}",
            read_openpose(
                &fixtures().join("openpose/body25b"),
                &rig,
                Some(KeypointOrder::Coco),
                OpenPosePoints::Centres,
                None,
            )
            .unwrap_err()
        );
        assert!(err.contains("25 keypoints, but COCO has 18"), "{err}");
        let coco =
            read_openpose(&fixtures().join("openpose/coco"), &rig, None, OpenPosePoints::NoseAndWrists, None).unwrap();
        assert_eq!(coco.definition.format, "openpose COCO");
        assert_eq!(coco.frames[&0][1].as_ref().unwrap().pixels[0], Some(Point2::new(707.0, 407.0)));
        assert_eq!(coco.frames[&0][2].as_ref().unwrap().pixels[0], Some(Point2::new(504.0, 404.0)));
    }

    #[test]
    fn bad_folders_and_files_give_their_errors() {
        let rig = rig3();
        let cases = [
            ("bad_flat", "keypoint files itself: expected one folder per camera"),
            ("bad_count", "20 keypoints"),
            ("bad_json", "not an OpenPose keypoint file"),
            ("bad_duplicate", "the same frame number 1"),
            ("bad_empty_camera", "holds no `*_keypoints.json` files"),
            ("bad_cameras", "cannot match the rig's cameras"),
        ];
        for (folder, expected) in cases {
            let dir = fixtures().join("openpose").join(folder);
            let err = format!("{:#}", read_openpose(&dir, &rig, None, OpenPosePoints::Centres, None).unwrap_err());
            assert!(err.contains(folder), "{folder}: {err}");
            assert!(err.contains(expected), "{folder}: expected `{expected}` in {err}");
        }
    }

    /// A person at the origin of [`rig3`]: 3D points of the nose, the ears, the wrists and each
    /// hand's palm keypoints (wrist and four knuckles), metres.
    struct Subject {
        nose: Point3<f64>,
        /// Left, right.
        ears: [Point3<f64>; 2],
        /// Left, right: the hand's wrist, then its index, middle, ring and little knuckles.
        hands: [[Point3<f64>; 5]; 2],
    }

    fn subject() -> Subject {
        let hand = |x: f64, side: f64| {
            [
                Point3::new(x, -0.3, 0.05),
                Point3::new(x + side * 0.03, -0.21, 0.06),
                Point3::new(x + side * 0.01, -0.205, 0.06),
                Point3::new(x - side * 0.01, -0.21, 0.06),
                Point3::new(x - side * 0.03, -0.22, 0.055),
            ]
        };
        Subject {
            nose: Point3::new(0.0, 0.3, 0.1),
            // The person faces the cameras (+z): their left is the world's +x.
            ears: [Point3::new(0.075, 0.31, 0.0), Point3::new(-0.075, 0.31, 0.0)],
            hands: [hand(0.25, 1.0), hand(-0.25, -1.0)],
        }
    }

    /// `(x, y, confidence)` numbers of `count` keypoints, every one missing but those given.
    fn keypoint_values(count: usize, given: &[(usize, Point2<f64>, f64)]) -> Vec<f64> {
        let mut values = vec![0.0; 3 * count];
        for &(k, p, c) in given {
            values[3 * k..3 * k + 3].copy_from_slice(&[p.x, p.y, c]);
        }
        values
    }

    /// Writes one frame of `people` (JSON objects) for camera `camera` into `dir`.
    fn write_frame(dir: &Path, camera: &str, frame: u64, people: Vec<serde_json::Value>) {
        let folder = dir.join(format!("{camera}_json"));
        std::fs::create_dir_all(&folder).unwrap();
        let file = folder.join(format!("{camera}_{frame:012}_keypoints.json"));
        std::fs::write(file, serde_json::json!({ "version": 1.3, "people": people }).to_string()).unwrap();
    }

    #[test]
    fn the_head_is_the_ear_midpoint_and_a_hand_its_palm_centre_where_the_files_have_hands() {
        let rig = rig3();
        let s = subject();
        let dir = tempfile::tempdir().unwrap();
        for (c, camera) in rig.cameras.iter().enumerate() {
            let px = |p: &Point3<f64>| camera.project(p).unwrap();
            // BODY_25: nose 0, right wrist 4, left wrist 7, right ear 17, left ear 18.
            let mut body = vec![(0, px(&s.nose), 0.9), (4, px(&s.hands[1][0]), 0.8), (7, px(&s.hands[0][0]), 0.8)];
            // cam_2 sees only the left ear (a profile): its head is the nose.
            body.push((18, px(&s.ears[0]), 0.7));
            if c != 2 {
                body.push((17, px(&s.ears[1]), 0.7));
            }
            let hand = |side: usize, confidence: f64| {
                let given: Vec<_> =
                    PALM_KEYPOINTS.iter().zip(&s.hands[side]).map(|(&k, p)| (k, px(p), confidence)).collect();
                keypoint_values(HAND_KEYPOINTS, &given)
            };
            // cam_1's right hand is barely detected (a hand out of its crop): left out there.
            let right = hand(1, if c == 1 { 0.1 } else { 0.6 });
            // A passer-by with fewer keypoints is never the main person.
            let passer_by = keypoint_values(25, &[(0, Point2::new(5.0, 5.0), 0.3)]);
            let people = vec![
                serde_json::json!({ "pose_keypoints_2d": passer_by, "hand_left_keypoints_2d": [], "hand_right_keypoints_2d": [] }),
                serde_json::json!({
                    "pose_keypoints_2d": keypoint_values(25, &body),
                    "hand_left_keypoints_2d": hand(0, 0.6),
                    "hand_right_keypoints_2d": right,
                }),
            ];
            write_frame(dir.path(), &format!("cam{:02}", c + 1), 0, people);
        }
        let r = read_openpose(dir.path(), &rig, None, OpenPosePoints::Centres, None).unwrap();
        assert_eq!(r.definition.head, "ear midpoint (nose where an ear is not visible)");
        assert_eq!(r.definition.hands, "palm centre (hand keypoints 0, 5, 9, 13, 17)");
        let frame = &r.frames[&0];
        let head = frame[0].as_ref().unwrap();
        let ears_px = |c: usize| {
            let cam = &rig.cameras[c];
            nalgebra::center(&cam.project(&s.ears[0]).unwrap(), &cam.project(&s.ears[1]).unwrap())
        };
        assert_eq!(head.pixels[0], Some(ears_px(0)));
        assert_eq!(head.pixels[2], rig.cameras[2].project(&s.nose));
        for (side, object) in frame[1..].iter().enumerate() {
            let object = object.as_ref().unwrap();
            let centre = Point3::from(s.hands[side].iter().fold(Vector3::zeros(), |a, p| a + p.coords) / 5.0);
            let error = (object.point.unwrap() - centre).norm();
            assert!(error < 2e-3, "hand {side} triangulated {error} m from its palm centre");
            // The wrist is 8 cm or more from the palm centre: what the old definition scored.
            assert!((s.hands[side][0] - centre).norm() > 0.07);
        }
        assert_eq!(frame[2].as_ref().unwrap().pixels[1], None, "a hand under the confidence bound is left out");
        // The same files scored by the nose and the wrists.
        let old = read_openpose(dir.path(), &rig, None, OpenPosePoints::NoseAndWrists, None).unwrap();
        assert_eq!((old.definition.head.as_str(), old.definition.hands.as_str()), ("nose", "wrist"));
        let wrist = old.frames[&0][1].as_ref().unwrap().point.unwrap();
        assert!((wrist - s.hands[0][0]).norm() < 2e-3);
        assert!((old.frames[&0][0].as_ref().unwrap().point.unwrap() - s.nose).norm() < 2e-3);
    }

    #[test]
    fn whole_body_models_carry_their_hands_and_body_models_extend_the_forearm() {
        let rig = rig3();
        let s = subject();
        let [whole, body, halpe136] = [(); 3].map(|_| tempfile::tempdir().unwrap());
        // Left, right: forearms 25 cm long, hanging down and forwards to the wrists.
        let elbows = [0, 1].map(|side| s.hands[side][0] + Vector3::new(0.0, 0.24, -0.07));
        for (c, camera) in rig.cameras.iter().enumerate() {
            let px = |p: &Point3<f64>| camera.project(p).unwrap();
            // COCO order: nose 0, left ear 3, right ear 4, left wrist 9, right wrist 10.
            let mut given = vec![
                (0, px(&s.nose), 0.9),
                (3, px(&s.ears[0]), 0.8),
                (4, px(&s.ears[1]), 0.8),
                (7, px(&elbows[0]), 0.8),
                (8, px(&elbows[1]), 0.8),
                (9, px(&s.hands[0][0]), 0.8),
                (10, px(&s.hands[1][0]), 0.8),
            ];
            let name = format!("cam{:02}", c + 1);
            // HALPE_26: no hands.
            write_frame(
                body.path(),
                &name,
                0,
                vec![serde_json::json!({ "pose_keypoints_2d": keypoint_values(26, &given) })],
            );
            // COCO_133: the left hand from 91, the right from 112. The right hand's keypoints
            // in cam_0 lie on the left arm (a hand found on the wrong arm): left out there.
            for (side, first) in [(0, 91), (1, 112)] {
                let points = if side == 1 && c == 0 { &s.hands[0] } else { &s.hands[side] };
                given.extend(PALM_KEYPOINTS.iter().zip(points).map(|(&k, p)| (first + k, px(p), 0.7)));
            }
            write_frame(
                whole.path(),
                &name,
                0,
                vec![serde_json::json!({ "pose_keypoints_2d": keypoint_values(133, &given) })],
            );
            // The same person in HALPE_136: the hands from 94 and 115.
            let halpe: Vec<_> = given.iter().map(|&(k, p, c)| (if k >= 91 { k + 3 } else { k }, p, c)).collect();
            let people = vec![serde_json::json!({ "pose_keypoints_2d": keypoint_values(136, &halpe) })];
            write_frame(halpe136.path(), &name, 0, people);
        }
        let r = read_openpose(whole.path(), &rig, None, OpenPosePoints::Centres, None).unwrap();
        assert_eq!(r.definition.format, "openpose COCO_133");
        assert_eq!(r.definition.hands, "palm centre (hand keypoints 0, 5, 9, 13, 17)");
        let frame = &r.frames[&0];
        let ears = nalgebra::center(&s.ears[0], &s.ears[1]);
        assert!((frame[0].as_ref().unwrap().point.unwrap() - ears).norm() < 2e-3);
        let right = frame[2].as_ref().unwrap();
        assert_eq!(right.pixels[0], None, "a hand whose wrist is not the body's wrist of its side");
        let centre = Point3::from(s.hands[1].iter().fold(Vector3::zeros(), |a, p| a + p.coords) / 5.0);
        assert!((right.point.unwrap() - centre).norm() < 2e-3);

        let halpe = read_openpose(halpe136.path(), &rig, None, OpenPosePoints::Centres, None).unwrap();
        assert_eq!(halpe.definition.format, "openpose HALPE_136");
        assert_eq!(halpe.frames, r.frames, "the same person read from either whole-body order");

        let r = read_openpose(body.path(), &rig, None, OpenPosePoints::Centres, None).unwrap();
        assert_eq!(r.definition.format, "openpose HALPE_26");
        assert!(r.definition.hands.starts_with("palm centre estimated"), "{}", r.definition.hands);
        for (side, elbow) in elbows.iter().enumerate() {
            let wrist = s.hands[side][0];
            let estimate = wrist + PALM_BEYOND_WRIST * (wrist - elbow);
            let error = (r.frames[&0][1 + side].as_ref().unwrap().point.unwrap() - estimate).norm();
            assert!(error < 3e-3, "hand {side}: {error} m from the wrist plus 0.3 of the forearm");
        }
        assert!((r.frames[&0][0].as_ref().unwrap().point.unwrap() - ears).norm() < 2e-3);
    }

    #[test]
    fn hand_keypoints_of_the_wrong_length_name_the_file_and_the_field() {
        let rig = rig3();
        let dir = tempfile::tempdir().unwrap();
        for camera in ["cam02", "cam03"] {
            write_frame(dir.path(), camera, 0, vec![serde_json::json!({ "pose_keypoints_2d": vec![1.0; 75] })]);
        }
        let person = serde_json::json!({ "pose_keypoints_2d": vec![1.0; 75], "hand_left_keypoints_2d": vec![1.0; 60] });
        write_frame(dir.path(), "cam01", 0, vec![person]);
        let err = format!("{:#}", read_openpose(dir.path(), &rig, None, OpenPosePoints::Centres, None).unwrap_err());
        assert!(err.contains("cam01_000000000000_keypoints.json"), "{err}");
        assert!(err.contains("hand_left_keypoints_2d: 60 numbers, expected none or 63"), "{err}");
    }

    #[test]
    fn files_of_cameras_that_dropped_frames_go_to_their_frame_sets() {
        let rig = rig3();
        // A caliscope session whose `cam_1` dropped a frame: its video's position 1 was
        // captured with frame set 2, and set 1 has no frame of `cam_1`.
        let frames = [0, 1, 2, 3];
        let positions = vec![
            vec![Some(0), Some(0), Some(0)],
            vec![Some(1), None, Some(1)],
            vec![Some(2), Some(1), Some(2)],
            vec![Some(3), Some(2), Some(3)],
        ];
        let maps = video_frames_of(&frames, &positions, 3);
        let dir = tempfile::tempdir().unwrap();
        for (c, camera) in ["cam01", "cam02", "cam03"].into_iter().enumerate() {
            let video_length = if c == 1 { 3 } else { 4 };
            for position in 0..video_length {
                // The frame set this file was captured with, in the nose's x.
                let frame = maps[c].get(&position).copied().unwrap_or(1);
                let nose = Point2::new(100.0 * frame as f64 + c as f64, 50.0);
                let person = serde_json::json!({ "pose_keypoints_2d": keypoint_values(25, &[(0, nose, 0.9)]) });
                write_frame(dir.path(), camera, position as u64, vec![person]);
            }
        }
        let read = |maps: Option<&[BTreeMap<usize, u64>]>| {
            read_openpose(dir.path(), &rig, None, OpenPosePoints::NoseAndWrists, maps).unwrap()
        };
        let r = read(Some(&maps));
        assert_eq!(r.frames.keys().copied().collect::<Vec<_>>(), frames);
        for &frame in &frames {
            let head = r.frames[&frame][0].as_ref().unwrap();
            let xs: Vec<Option<f64>> = head.pixels.iter().map(|p| p.map(|p| p.x)).collect();
            let want: Vec<Option<f64>> =
                (0..3).map(|c| (frame != 1 || c != 1).then_some(100.0 * frame as f64 + c as f64)).collect();
            assert_eq!(xs, want, "frame {frame}: every view's file of that instant, none of `cam_1` in set 1");
        }
        // Read as file k = frame k, `cam_1`'s files after the drop are a frame early.
        let naive = read(None);
        assert_eq!(naive.frames[&2][0].as_ref().unwrap().pixels[1].unwrap().x, 301.0);
    }
}
