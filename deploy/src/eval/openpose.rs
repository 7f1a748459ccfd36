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
//!   COCO has 18. The head is the nose, the hands the wrists, the person's own sides
//!   (OpenPose's `LWrist` is the person's left, as handflow's `left_hand`). A keypoint with
//!   confidence 0 is missing.
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
    /// OpenPose's default BODY_25: nose 0, right wrist 4, left wrist 7.
    Body25,
    /// OpenPose's experimental BODY_25B (COCO order first): nose 0, left wrist 9, right
    /// wrist 10.
    Body25b,
    /// COCO, 18 keypoints: nose 0, right wrist 4, left wrist 7.
    Coco,
}

impl KeypointOrder {
    /// Number of keypoints of this order.
    pub fn keypoint_count(self) -> usize {
        match self {
            KeypointOrder::Body25 | KeypointOrder::Body25b => 25,
            KeypointOrder::Coco => 18,
        }
    }

    /// Indices of the nose, the left wrist and the right wrist: head, left hand, right hand.
    pub fn object_keypoints(self) -> [usize; 3] {
        match self {
            KeypointOrder::Body25 | KeypointOrder::Coco => [0, 7, 4],
            KeypointOrder::Body25b => [0, 9, 10],
        }
    }

    /// The OpenPose model name (`BODY_25`, `BODY_25B`, `COCO`).
    pub fn model_name(self) -> &'static str {
        match self {
            KeypointOrder::Body25 => "BODY_25",
            KeypointOrder::Body25b => "BODY_25B",
            KeypointOrder::Coco => "COCO",
        }
    }

    /// The order of `count` keypoints when none was given: 18 is COCO, 25 BODY_25.
    fn from_count(count: usize) -> Option<KeypointOrder> {
        match count {
            18 => Some(KeypointOrder::Coco),
            25 => Some(KeypointOrder::Body25),
            _ => None,
        }
    }
}

#[derive(Deserialize)]
struct KeypointFile {
    people: Vec<Person>,
}

#[derive(Deserialize)]
struct Person {
    #[serde(default)]
    pose_keypoints_2d: Vec<f64>,
}

/// Reads an OpenPose folder (see the [module documentation](self)) as a reference for
/// `rig`'s cameras. `order` is the keypoint order; `None` takes it from the keypoint count
/// (18 COCO, 25 BODY_25); a count that does not fit the order is an error.
pub fn read_openpose(dir: &Path, rig: &Rig, order: Option<KeypointOrder>) -> Result<Reference> {
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
    // Per frame, per object: pixel per camera.
    let mut pixels: BTreeMap<u64, [Vec<Option<Point2<f64>>>; 3]> = BTreeMap::new();
    for (c, camera_files) in files.iter().enumerate() {
        for (number, path) in camera_files {
            let frame = number - first;
            let people = read_keypoint_file(path)?;
            let Some(person) = main_person(path, &people, &mut order)? else {
                frames.entry(frame).or_default();
                continue;
            };
            let Some(order) = order else { continue };
            let slots = pixels.entry(frame).or_insert_with(|| std::array::from_fn(|_| vec![None; rig.cameras.len()]));
            for (k, &keypoint) in order.object_keypoints().iter().enumerate() {
                let (x, y, confidence) = (person[3 * keypoint], person[3 * keypoint + 1], person[3 * keypoint + 2]);
                if confidence > 0.0 {
                    slots[k][c] = Some(Point2::new(x, y));
                }
            }
        }
    }
    for (frame, objects) in pixels {
        let entry = frames.entry(frame).or_default();
        for (k, views) in objects.into_iter().enumerate() {
            if views.iter().any(Option::is_some) {
                entry[k] = Some(ReferenceObject::new(rig, views, None));
            }
        }
    }
    let model = order.map_or("unknown keypoints (no person detected)", KeypointOrder::model_name);
    Ok(Reference {
        definition: ReferenceDefinition {
            format: format!("openpose {model}"),
            head: "nose".to_owned(),
            hands: "wrist".to_owned(),
        },
        palm_width_m: PALM_WIDTH_M,
        frames,
    })
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
fn main_person<'a>(path: &Path, people: &'a [Person], order: &mut Option<KeypointOrder>) -> Result<Option<&'a [f64]>> {
    let mut best: Option<(f64, &[f64])> = None;
    for (p, person) in people.iter().enumerate() {
        let values = &person.pose_keypoints_2d;
        let at = || format!("`{}` person {p} pose_keypoints_2d", path.display());
        let count = values.len() / 3;
        ensure!(count * 3 == values.len(), "{}: {} numbers, not (x, y, confidence) triples", at(), values.len());
        let expected = match *order {
            Some(o) => o,
            None => {
                let Some(o) = KeypointOrder::from_count(count) else {
                    bail!("{}: {count} keypoints; BODY_25, BODY_25B (25) and COCO (18) are read", at())
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
        let total: f64 = values.iter().skip(2).step_by(3).sum();
        if best.as_ref().is_none_or(|(b, _)| total > *b) {
            best = Some((total, values.as_slice()));
        }
    }
    Ok(best.map(|(_, values)| values))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval::reference::tests::{fixtures, rig3};

    #[test]
    fn reads_the_fixture_choosing_the_main_person_and_skipping_missing_keypoints() {
        let rig = rig3();
        let r = read_openpose(&fixtures().join("openpose/body25"), &rig, None).unwrap();
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
        let r = read_openpose(&fixtures().join("openpose/body25b"), &rig, Some(KeypointOrder::Body25b)).unwrap();
        assert_eq!(r.definition.format, "openpose BODY_25B");
        let frame = &r.frames[&0];
        assert_eq!(frame[1].as_ref().unwrap().pixels[0], Some(Point2::new(709.0, 409.0)));
        assert_eq!(frame[2].as_ref().unwrap().pixels[0], Some(Point2::new(510.0, 410.0)));
        // The same files read as BODY_25 take other keypoints; as COCO they are refused.
        let as_body25 = read_openpose(&fixtures().join("openpose/body25b"), &rig, None).unwrap();
        assert_ne!(as_body25.frames[&0][1], r.frames[&0][1]);
        let err = format!(
            "{:#}",
            read_openpose(&fixtures().join("openpose/body25b"), &rig, Some(KeypointOrder::Coco)).unwrap_err()
        );
        assert!(err.contains("25 keypoints, but COCO has 18"), "{err}");
        let coco = read_openpose(&fixtures().join("openpose/coco"), &rig, None).unwrap();
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
            let err = format!("{:#}", read_openpose(&dir, &rig, None).unwrap_err());
            assert!(err.contains(folder), "{folder}: {err}");
            assert!(err.contains(expected), "{folder}: expected `{expected}` in {err}");
        }
    }
}
