//! Keeps a rig's skin models adapted: every few frames, faces are detected in every view,
//! checked against each other ([`crate::face_fusion`]) and used to adapt each camera's
//! model. Between detections, and when no face is found, the models keep their state.

use handflow_protocol::Camera;

use crate::face_fusion::fuse_faces;
use crate::faces::FaceDetector;
use crate::skin::SkinModel;

/// Adaptation rate per detection (default of [`SkinAdapter::new`]): a face seen a handful
/// of times dominates the generic prior, one odd frame does not.
pub const DEFAULT_ADAPTATION_RATE: f32 = 0.3;
/// Detect faces every this many frames by default (6 per second at 30 fps).
pub const DEFAULT_DETECT_EVERY: u64 = 5;

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

/// Face detection and skin-model adaptation for one rig.
pub struct SkinAdapter {
    detector: FaceDetector,
    cameras: Vec<Camera>,
    models: Vec<SkinModel>,
    detect_every: u64,
    stats: AdaptationStats,
}

impl SkinAdapter {
    /// Generic models for every camera, adapted at `rate` every `detect_every` frames.
    pub fn new(cameras: &[Camera], rate: f32, detect_every: u64) -> Result<Self, String> {
        Ok(Self {
            detector: FaceDetector::new()?,
            cameras: cameras.to_vec(),
            models: vec![SkinModel::generic(rate); cameras.len()],
            detect_every: detect_every.max(1),
            stats: AdaptationStats {
                detected: vec![0; cameras.len()],
                lent: vec![0; cameras.len()],
                ..AdaptationStats::default()
            },
        })
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
        if frame % self.detect_every != 0 || views.len() != self.cameras.len() {
            return false;
        }
        self.adapt_now(views)
    }

    /// Detects faces in every view and adapts now. Returns whether any model changed.
    pub fn adapt_now(&mut self, views: &[&[u8]]) -> bool {
        let started = std::time::Instant::now();
        let found: Vec<_> =
            views.iter().zip(&self.cameras).map(|(v, c)| self.detector.detect(v, c.width, c.height)).collect();
        let fused = fuse_faces(&self.cameras, &found);
        self.stats.rounds += 1;
        self.stats.rejected += fused.rejected as u64;
        let mut changed = false;
        for (c, cam) in self.cameras.iter().enumerate() {
            let faces: Vec<_> = fused.boxes[c].into_iter().collect();
            if self.models[c].adapt(views[c], cam.width, cam.height, &faces) {
                changed = true;
                if fused.transferred[c] {
                    self.stats.lent[c] += 1;
                } else {
                    self.stats.detected[c] += 1;
                }
            }
        }
        self.stats.seconds += started.elapsed().as_secs_f64();
        changed
    }
}
