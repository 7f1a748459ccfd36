//! Keeps a rig's skin models adapted: every few frames, faces are detected in every view,
//! checked against each other ([`crate::skin::face_fusion`]) and used to adapt each camera's
//! model. Between detections, and when no face is found, the models keep their state.

use std::cell::RefCell;

use handflow_protocol::Camera;
use rayon::prelude::*;

use crate::skin::face_fusion::{face_width_px, fuse_faces_remembering, FusedFaces, KnownFace};
use crate::skin::faces::{detection_bin, FaceBox, FaceDetector, Region};
use crate::skin::model::SkinModel;

/// Adaptation rate per detection (default of [`SkinAdapter::new`]): a face seen a handful
/// of times dominates the generic prior, one odd frame does not.
pub const DEFAULT_ADAPTATION_RATE: f32 = 0.3;
/// Detect faces every this many frames by default (3 per second at 30 fps).
pub const DEFAULT_DETECT_EVERY: u64 = 10;
/// Once a camera's face is known, search only a square this many face sizes wide around it
/// (a 640x480 frame costs about 200 ms, such a region about 10).
pub const SEARCH_SCALE: f32 = 2.5;
/// Every this many rounds every camera is searched whole, so a face that moved far or a
/// second person is found again.
pub const FULL_SEARCH_EVERY: u64 = 10;

/// What adaptation has done so far.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct AdaptationStats {
    /// Detection rounds run (one per `detect_every` frames).
    pub rounds: u64,
    /// Per camera: models adapted from the camera's own (confirmed) detection.
    pub detected: Vec<u64>,
    /// Per camera: models adapted from a face lent by the other views.
    pub lent: Vec<u64>,
    /// Detections no other view agreed with, dropped.
    pub rejected: u64,
    /// Wall time spent detecting and adapting, seconds.
    pub seconds: f64,
}

thread_local! {
    /// This thread's face detector: the underlying detector is not `Send`, and its settings
    /// are fixed, so which thread searches a view does not change what is found.
    static DETECTOR: RefCell<Option<FaceDetector>> = const { RefCell::new(None) };
}

/// Runs `f` with this thread's face detector, built at its first use.
pub fn with_detector<R>(f: impl FnOnce(&mut FaceDetector) -> R) -> Result<R, String> {
    DETECTOR.with(|cell| {
        let mut slot = cell.borrow_mut();
        let detector = match slot.as_mut() {
            Some(detector) => detector,
            None => slot.insert(FaceDetector::new()?),
        };
        Ok(f(detector))
    })
}

/// Face detection and skin-model adaptation for one rig.
pub struct SkinAdapter {
    cameras: Vec<Camera>,
    models: Vec<SkinModel>,
    detect_every: u64,
    stats: AdaptationStats,
    /// Per camera: the face used at the last round, where the next search looks.
    last: Vec<Option<FaceBox>>,
    /// The face last placed in 3D: gives a lone view's detection its depth.
    known: Option<KnownFace>,
    /// The last round's detections per camera, before fusion (for diagnostics).
    last_detections: Vec<Vec<FaceBox>>,
    /// The last round's fused faces, the boxes the models were adapted with.
    last_fused: FusedFaces,
}

impl SkinAdapter {
    /// Generic models for every camera, adapted at `rate` every `detect_every` frames.
    pub fn new(cameras: &[Camera], rate: f32, detect_every: u64) -> Result<Self, String> {
        // The shipped model is checked once here; the threads that search build their own.
        with_detector(|_| ())?;
        Ok(Self {
            cameras: cameras.to_vec(),
            models: vec![SkinModel::generic(rate); cameras.len()],
            detect_every: detect_every.max(1),
            stats: AdaptationStats {
                detected: vec![0; cameras.len()],
                lent: vec![0; cameras.len()],
                ..AdaptationStats::default()
            },
            last: vec![None; cameras.len()],
            known: None,
            last_detections: vec![Vec::new(); cameras.len()],
            last_fused: FusedFaces {
                boxes: vec![None; cameras.len()],
                transferred: vec![false; cameras.len()],
                ..FusedFaces::default()
            },
        })
    }

    /// Per camera (rig order), what its own detector found in the last round, before the
    /// views were checked against each other (empty before the first round).
    pub fn last_detections(&self) -> &[Vec<FaceBox>] {
        &self.last_detections
    }

    /// The faces the last round adapted each camera's model with: a camera's own confirmed
    /// detection, a face lent by the other views (`transferred`), or none.
    pub fn last_fused(&self) -> &FusedFaces {
        &self.last_fused
    }

    /// The current models, one per camera in rig order.
    pub fn models(&self) -> &[SkinModel] {
        &self.models
    }

    /// What adaptation has done so far.
    pub fn stats(&self) -> &AdaptationStats {
        &self.stats
    }

    /// Whether any camera's model has been adapted yet.
    pub fn has_adapted(&self) -> bool {
        self.stats.detected.iter().chain(&self.stats.lent).any(|&n| n > 0)
    }

    /// Looks at frame set `frame` (RGB8 views in rig order) and, on every `detect_every`-th
    /// frame, detects faces and adapts. Returns whether any model changed.
    pub fn observe(&mut self, frame: u64, views: &[&[u8]]) -> bool {
        if !frame.is_multiple_of(self.detect_every) || views.len() != self.cameras.len() {
            return false;
        }
        self.adapt_now(views)
    }

    /// Detects faces in every view and adapts now. Returns whether any model changed.
    pub fn adapt_now(&mut self, views: &[&[u8]]) -> bool {
        self.adapt_now_partial(views, 0)
    }

    /// [`SkinAdapter::adapt_now`] on a set some cameras gave no view for (bit `k` of
    /// `missing`: camera `k`): those are not searched and their models keep their state.
    pub fn adapt_now_partial(&mut self, views: &[&[u8]], missing: u32) -> bool {
        let started = std::time::Instant::now();
        let full = self.stats.rounds.is_multiple_of(FULL_SEARCH_EVERY);
        let absent = |k: usize| k < 32 && missing & (1 << k) != 0;
        // Where each view is searched, decided from the last round; then the searches run in
        // parallel (on the caller's thread pool), each camera with its own detector.
        let searches: Vec<Option<(Region, f32)>> = self
            .cameras
            .iter()
            .zip(&self.last)
            .enumerate()
            .map(|(k, (cam, last))| {
                if absent(k) {
                    return None;
                }
                // On binned pixels where the face's size is known: the face last seen here,
                // else the face placed in 3D seen from this camera (a second person twice as
                // far away may be missed; the signer is the nearest face).
                let expected_px = match last {
                    Some(face) => face.width.min(face.height),
                    None => {
                        self.known.as_ref().and_then(|k| face_width_px(cam, &k.centre.into(), k.width_m)).unwrap_or(0.0)
                            as f32
                    }
                };
                let bin = detection_bin(expected_px);
                match last {
                    Some(face) if !full => Some((Region::around(face, SEARCH_SCALE, cam.width, cam.height), bin)),
                    // Once the face is placed in 3D, a view that neither saw it nor was lent
                    // it (turned away from it, or too far) is searched whole only on the full
                    // rounds: a whole 1280x720 view costs about 250 ms, ten regions as much.
                    None if !full && self.known.is_some() => None,
                    _ => Some((Region { x: 0, y: 0, width: cam.width, height: cam.height }, bin)),
                }
            })
            .collect();
        let found: Vec<Vec<FaceBox>> = self
            .cameras
            .par_iter()
            .zip(views.par_iter())
            .zip(searches.par_iter())
            .map(|((cam, view), search)| match *search {
                Some((region, bin)) => with_detector(|detector| {
                    detector.detect_in_binned(view, cam.width, cam.height, region, cam.mount_quarter_turns, bin)
                })
                .unwrap_or_else(|problem| {
                    tracing::error!("camera `{}`: no face detector: {problem}", cam.name);
                    Vec::new()
                }),
                None => Vec::new(),
            })
            .collect();
        let fused = fuse_faces_remembering(&self.cameras, &found, self.known.as_ref());
        self.last.clone_from(&fused.boxes);
        self.known = fused.known.or(self.known);
        self.stats.rounds += 1;
        self.stats.rejected += fused.rejected as u64;
        let adapted: Vec<bool> = self
            .models
            .par_iter_mut()
            .zip(self.cameras.par_iter())
            .zip(views.par_iter())
            .enumerate()
            .map(|(c, ((model, cam), view))| {
                let faces: Vec<_> = fused.boxes[c].into_iter().collect();
                !absent(c) && model.adapt(view, cam.width, cam.height, &faces)
            })
            .collect();
        let mut changed = false;
        for (c, &adapted) in adapted.iter().enumerate() {
            if adapted {
                changed = true;
                if fused.transferred[c] {
                    self.stats.lent[c] += 1;
                } else {
                    self.stats.detected[c] += 1;
                }
            }
        }
        self.last_detections = found;
        self.last_fused = fused;
        self.stats.seconds += started.elapsed().as_secs_f64();
        changed
    }
}
