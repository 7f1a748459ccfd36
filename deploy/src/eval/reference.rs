//! An independent tracker's positions of head and hands on real footage (EVALUATION.md
//! section 2b), in the rig's camera order, and the `handflow-reference/1` reader (the format
//! is documented with the caliscope-hands data: MediaPipe palm centres and ear midpoints per
//! camera, triangulated).
//!
//! Readers of other trackers ([`super::openpose`]) produce the same [`Reference`].

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::{bail, ensure, Context, Result};
use handflow_cluster::tracks::OBJECTS;
use handflow_ingest::camera_match::match_cameras;
use handflow_protocol::Rig;
use nalgebra::{Point2, Point3};
use serde::Deserialize;

use super::triangulation::triangulate;

/// The `format` string of the files [`read_handflow_reference`] reads.
pub const HANDFLOW_REFERENCE_FORMAT: &str = "handflow-reference/1";

/// Largest reference file read, bytes: a 4-camera hour at 30 frames/s is about 200 MiB, and
/// the whole file is parsed in memory.
pub const MAX_REFERENCE_BYTES: u64 = 1 << 30;

/// Most frames a reference may hold (about 9 hours at 30 frames/s).
pub const MAX_REFERENCE_FRAMES: usize = 1_000_000;

/// What the reference calls each object: a figure is measured against a definition.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct ReferenceDefinition {
    /// The tracker and file format, e.g. `handflow-reference/1` or `openpose BODY_25`.
    pub format: String,
    /// Where the head is, e.g. `ear midpoint (nose where an ear is not visible)`.
    pub head: String,
    /// Where a hand is, e.g. `palm centre` or `wrist`.
    pub hands: String,
}

/// One object in one frame, as the reference has it.
#[derive(Clone, Debug, PartialEq)]
pub struct ReferenceObject {
    /// Pixel position per rig camera (rig order), raw frames, pixel (0, 0)'s centre at
    /// (0, 0); `None` where the reference has nothing in that view.
    pub pixels: Vec<Option<Point2<f64>>>,
    /// World position, metres: the file's own 3D point, else triangulated from two or more
    /// views; `None` when neither exists.
    pub point: Option<Point3<f64>>,
}

/// One frame of the reference: head, left hand, right hand (the order of
/// [`OBJECTS`]), each `None` where the reference has nothing.
pub type ReferenceFrame = [Option<ReferenceObject>; 3];

/// A reference for a whole recording.
#[derive(Clone, Debug, PartialEq)]
pub struct Reference {
    /// What was measured.
    pub definition: ReferenceDefinition,
    /// Palm width used to turn pixels into palm widths, metres.
    pub palm_width_m: f64,
    /// Frames by number (counted from 0 at the recording's first frame set).
    pub frames: BTreeMap<u64, ReferenceFrame>,
}

impl ReferenceObject {
    /// An object from its pixels per rig camera; its 3D point is `point` when given, else
    /// the triangulation of its views (see [`triangulate`]) when two or more have it.
    pub fn new(rig: &Rig, pixels: Vec<Option<Point2<f64>>>, point: Option<Point3<f64>>) -> ReferenceObject {
        let point = point.or_else(|| {
            let views: Vec<_> =
                rig.cameras.iter().zip(&pixels).filter_map(|(camera, p)| p.map(|p| (camera, p))).collect();
            triangulate(&views).map(|t| t.point)
        });
        ReferenceObject { pixels, point }
    }
}

#[derive(Deserialize)]
struct FileHeader {
    format: String,
}

/// The fields scored; others (`format`, checked first through [`FileHeader`], `source`,
/// `reprojection_px`) are ignored.
#[derive(Deserialize)]
struct ReferenceFile {
    palm_width_m: f64,
    cameras: Vec<String>,
    frames: Vec<FileFrame>,
}

#[derive(Deserialize)]
struct FileFrame {
    frame: u64,
    objects: BTreeMap<String, FileObject>,
}

#[derive(Deserialize)]
struct FileObject {
    #[serde(rename = "2d")]
    pixels: BTreeMap<String, [f64; 2]>,
    #[serde(rename = "3d", default)]
    point: Option<[f64; 3]>,
}

/// Reads a `handflow-reference/1` file, its cameras matched to `rig`'s by
/// [`match_cameras`]. Objects other than head and hands are ignored (the format may grow);
/// a 2D position of a camera not in the file's `cameras`, a non-finite number, a repeated
/// frame or a non-positive palm width are errors naming the file and the frame or field.
/// An object without `3d` but with two or more views gets a triangulated point.
pub fn read_handflow_reference(path: &Path, rig: &Rig) -> Result<Reference> {
    let text = read_capped(path, MAX_REFERENCE_BYTES)?;
    let header: FileHeader = serde_json::from_str(&text)
        .with_context(|| format!("`{}`: not a {HANDFLOW_REFERENCE_FORMAT} file", path.display()))?;
    ensure!(
        header.format == HANDFLOW_REFERENCE_FORMAT,
        "`{}`: format `{}`, expected `{HANDFLOW_REFERENCE_FORMAT}`",
        path.display(),
        header.format
    );
    let file: ReferenceFile = serde_json::from_str(&text).with_context(|| format!("`{}`", path.display()))?;
    parse_reference(path, rig, file)
}

fn parse_reference(path: &Path, rig: &Rig, file: ReferenceFile) -> Result<Reference> {
    let at = path.display();
    ensure!(
        file.palm_width_m.is_finite() && file.palm_width_m > 0.0,
        "`{at}`: palm_width_m must be a positive number of metres, found {}",
        file.palm_width_m
    );
    ensure!(
        file.frames.len() <= MAX_REFERENCE_FRAMES,
        "`{at}`: {} frames, at most {MAX_REFERENCE_FRAMES} are read",
        file.frames.len()
    );
    let rig_names: Vec<String> = rig.cameras.iter().map(|c| c.name.clone()).collect();
    let matched = match_cameras(&rig_names, &file.cameras).map_err(|e| anyhow::anyhow!("`{at}` cameras: {e}"))?;
    // File camera name -> rig camera index (cameras the rig lacks map to nothing).
    let mut rig_index: BTreeMap<&str, Option<usize>> = file.cameras.iter().map(|n| (n.as_str(), None)).collect();
    for (c, &i) in matched.iter().enumerate() {
        rig_index.insert(file.cameras[i].as_str(), Some(c));
    }
    let mut frames = BTreeMap::new();
    for frame in file.frames {
        let n = frame.frame;
        let mut objects: ReferenceFrame = Default::default();
        for (name, object) in &frame.objects {
            let Some(k) = OBJECTS.iter().position(|o| o == name) else { continue };
            let mut pixels = vec![None; rig.cameras.len()];
            for (camera, xy) in &object.pixels {
                let Some(index) = rig_index.get(camera.as_str()) else {
                    bail!("`{at}` frame {n} `{name}`: camera `{camera}` is not in the file's `cameras`")
                };
                ensure!(
                    xy.iter().all(|v| v.is_finite()),
                    "`{at}` frame {n} `{name}` 2d `{camera}`: not finite ({}, {})",
                    xy[0],
                    xy[1]
                );
                if let Some(c) = index {
                    pixels[*c] = Some(Point2::new(xy[0], xy[1]));
                }
            }
            if let Some(p) = &object.point {
                ensure!(p.iter().all(|v| v.is_finite()), "`{at}` frame {n} `{name}` 3d: not finite {p:?}");
            }
            if pixels.iter().all(Option::is_none) && object.point.is_none() {
                continue;
            }
            objects[k] = Some(ReferenceObject::new(rig, pixels, object.point.map(Point3::from)));
        }
        ensure!(frames.insert(n, objects).is_none(), "`{at}`: frame {n} appears twice");
    }
    Ok(Reference {
        definition: ReferenceDefinition {
            format: HANDFLOW_REFERENCE_FORMAT.to_owned(),
            head: "ear midpoint (nose where an ear is not visible)".to_owned(),
            hands: "palm centre".to_owned(),
        },
        palm_width_m: file.palm_width_m,
        frames,
    })
}

/// A text file of at most `max_bytes`, its error naming the file.
pub(crate) fn read_capped(path: &Path, max_bytes: u64) -> Result<String> {
    let size = std::fs::metadata(path).with_context(|| format!("reading `{}`", path.display()))?.len();
    ensure!(size <= max_bytes, "`{}`: {size} bytes, at most {max_bytes} are read", path.display());
    std::fs::read_to_string(path).with_context(|| format!("reading `{}`", path.display()))
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::eval::triangulation::camera_looking_at_origin;
    use nalgebra::Vector3;

    /// The repository's fixtures folder.
    pub(crate) fn fixtures() -> std::path::PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/fixtures")
    }

    /// Three cameras `cam_0..cam_2` in front of the origin.
    pub(crate) fn rig3() -> Rig {
        let centres = [Vector3::new(-1.5, 0.2, 3.0), Vector3::new(0.0, 0.3, 3.2), Vector3::new(1.5, 0.2, 3.0)];
        let cameras =
            centres.iter().enumerate().map(|(i, c)| camera_looking_at_origin(&format!("cam_{i}"), *c, 900.0)).collect();
        Rig { cameras, ..Default::default() }
    }

    #[test]
    fn reads_the_fixture_matching_cameras_and_triangulating_where_3d_is_missing() {
        let rig = rig3();
        let r = read_handflow_reference(&fixtures().join("reference/small.json"), &rig).unwrap();
        assert_eq!(r.palm_width_m, 0.09);
        assert_eq!(r.frames.len(), 3);
        // Frame 0: head given in 3D, seen by cam_0 and cam_2 (the file calls them cam00, cam02).
        let head = r.frames[&0][0].as_ref().unwrap();
        assert_eq!(head.point, Some(Point3::new(0.0, 0.5, 0.0)));
        assert_eq!(head.pixels[1], None);
        assert!(head.pixels[0].is_some() && head.pixels[2].is_some());
        // Frame 0: left hand without `3d` in two views: triangulated.
        let left = r.frames[&0][1].as_ref().unwrap();
        let p = left.point.unwrap();
        assert!((p - Point3::new(0.2, 0.0, 0.1)).norm() < 1e-3, "{p}");
        // Frame 1: a right hand in one view, no 3D; no head, an unknown `torso` ignored.
        let frame1 = &r.frames[&1];
        assert!(frame1[0].is_none() && frame1[1].is_none());
        assert_eq!(frame1[2].as_ref().unwrap().point, None);
        // Frame 2: nothing.
        assert!(r.frames[&2].iter().all(Option::is_none));
    }

    #[test]
    fn bad_files_name_the_file_and_the_frame_or_field() {
        let rig = rig3();
        let cases = [
            ("bad_format.json", "format `handflow-reference/0`"),
            ("bad_camera.json", "frame 3 `head`: camera `cam_9`"),
            ("bad_palm.json", "palm_width_m"),
            ("bad_duplicate_frame.json", "frame 0 appears twice"),
            ("bad_missing_field.json", "missing field `cameras`"),
            ("bad_cameras.json", "cannot match the rig's cameras"),
            ("bad_syntax.json", "line 2"),
        ];
        for (file, expected) in cases {
            let err =
                format!("{:#}", read_handflow_reference(&fixtures().join("reference").join(file), &rig).unwrap_err());
            assert!(err.contains(file), "{file}: {err}");
            assert!(err.contains(expected), "{file}: expected `{expected}` in {err}");
        }
    }

    #[test]
    fn reads_the_real_caliscope_reference() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/real/caliscope-hands");
        let path = dir.join("reference.json");
        if !path.is_file() {
            eprintln!("skipping: `{}` is absent", path.display());
            return;
        }
        // The four cameras as the caliscope rig names them; positions do not matter here
        // (every object of this file has its own `3d`, or too few views).
        let centres = [
            Vector3::new(-1.5, 0.2, 3.0),
            Vector3::new(0.0, 0.3, 3.2),
            Vector3::new(1.5, 0.2, 3.0),
            Vector3::new(0.5, 1.5, 3.0),
        ];
        let cameras =
            centres.iter().enumerate().map(|(i, c)| camera_looking_at_origin(&format!("cam_{i}"), *c, 900.0)).collect();
        let rig = Rig { cameras, ..Default::default() };
        let r = read_handflow_reference(&path, &rig).unwrap();
        assert_eq!(r.frames.len(), 111);
        assert_eq!(r.frames.keys().next(), Some(&0));
        assert_eq!(r.frames.keys().last(), Some(&110));
        assert_eq!(r.palm_width_m, 0.085);
        let head = r.frames[&10][0].as_ref().unwrap();
        assert_eq!(head.pixels.len(), 4);
        assert!(head.pixels.iter().all(Option::is_some));
        assert_eq!(head.pixels[0], Some(Point2::new(941.22, 140.12)));
        let with_head = r.frames.values().filter(|f| f[0].is_some()).count();
        assert!(with_head >= 110, "{with_head} frames with a head");
    }
}
