//! `handflow eval skin`: per-pixel precision and recall of the skin decision against a
//! recording's object masks, for the generic prior and for the model adapted from face
//! detections.

use std::path::Path;

use anyhow::{Context, Result};
use handflow_flow::faces::FaceDetector;
use handflow_flow::skin::SkinModel;
use handflow_ingest::synthetic::MASKS_DIR;
use handflow_ingest::Recording;

/// Adaptation rate of the skin model per face detection.
pub const ADAPTATION_RATE: f32 = 0.3;
/// Every how many frames faces are detected (off the hot path in the live pipeline).
pub const DETECT_EVERY: usize = 5;
/// Every how many frames the decision is scored.
pub const SCORE_EVERY: usize = 3;

/// The scores of one run.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct SkinScores {
    /// Adapted model: share of pixels called skin that are skin.
    pub precision: f64,
    /// Adapted model: share of skin pixels called skin.
    pub recall: f64,
    /// Generic prior: precision.
    pub precision_generic: f64,
    /// Generic prior: recall.
    pub recall_generic: f64,
    /// Face detections used to adapt, over all cameras.
    pub face_detections: usize,
    /// Frames scored (per camera).
    pub frames_scored: usize,
    /// Per camera (rig order): adapted precision and recall.
    pub cameras: Vec<CameraScores>,
}

/// One camera's scores.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct CameraScores {
    /// Camera name.
    pub camera: String,
    /// Adapted model: precision.
    pub precision: f64,
    /// Adapted model: recall.
    pub recall: f64,
    /// Face detections used to adapt this camera's model.
    pub face_detections: usize,
}

#[derive(Default)]
struct Counts {
    tp: f64,
    fp: f64,
    fn_: f64,
}

impl Counts {
    fn add(&mut self, said: bool, truth: bool) {
        match (said, truth) {
            (true, true) => self.tp += 1.0,
            (true, false) => self.fp += 1.0,
            (false, true) => self.fn_ += 1.0,
            _ => {}
        }
    }
    fn precision(&self) -> f64 {
        self.tp / (self.tp + self.fp).max(1.0)
    }
    fn recall(&self) -> f64 {
        self.tp / (self.tp + self.fn_).max(1.0)
    }
}

/// Mask ids of the skin-coloured objects: `head`, `left_hand`, `right_hand` from
/// `truth.json`'s `mask_ids` when it has them, else the renderer's 1, 2, 3.
fn skin_ids(rec: &Recording) -> Result<Vec<u8>> {
    let Some(path) = rec.truth_path() else { return Ok(vec![1, 2, 3]) };
    let text = std::fs::read_to_string(path).with_context(|| format!("reading `{}`", path.display()))?;
    let truth: serde_json::Value = serde_json::from_str(&text).with_context(|| format!("`{}`", path.display()))?;
    let ids = ["head", "left_hand", "right_hand"]
        .iter()
        .filter_map(|k| truth["mask_ids"][k].as_u64().and_then(|v| u8::try_from(v).ok()))
        .collect::<Vec<_>>();
    Ok(if ids.is_empty() { vec![1, 2, 3] } else { ids })
}

/// Runs the evaluation on a recording with masks (`masks/<camera>/<frame>.png`).
pub fn evaluate_skin(dir: &Path) -> Result<SkinScores> {
    let rec = Recording::open(dir)?;
    let skin = skin_ids(&rec)?;
    let cameras = &rec.rig().cameras;
    let mut buf = vec![0u8; rec.frame_set_len()];
    let mut models: Vec<SkinModel> = cameras.iter().map(|_| SkinModel::generic(ADAPTATION_RATE)).collect();
    let generic = SkinModel::generic(ADAPTATION_RATE);
    let mut detector = FaceDetector::new().map_err(anyhow::Error::msg)?;
    let mut detections = vec![0usize; cameras.len()];
    let mut per_camera: Vec<Counts> = cameras.iter().map(|_| Counts::default()).collect();
    let (mut adapted, mut prior) = (Counts::default(), Counts::default());
    let mut scored = 0;
    for (k, entry) in rec.frames().iter().enumerate() {
        let detect = k % DETECT_EVERY == 0;
        let score = k % SCORE_EVERY == 0;
        if !detect && !score {
            continue;
        }
        rec.read_frame_into(k as u64, false, &mut buf)?;
        let mut offset = 0;
        for (c, cam) in cameras.iter().enumerate() {
            let len = cam.width as usize * cam.height as usize * 3;
            let view = &buf[offset..offset + len];
            offset += len;
            if detect {
                let faces = detector.detect(view, cam.width, cam.height);
                if models[c].adapt(view, cam.width, cam.height, &faces) {
                    detections[c] += 1;
                }
            }
            if score {
                let mask_path = dir
                    .join(MASKS_DIR)
                    .join(&cam.name)
                    .join(entry.images[c].file_name().context("image without a file name")?);
                let mask = image::open(&mask_path)
                    .with_context(|| {
                        format!("camera `{}`, frame {}: mask `{}`", cam.name, entry.frame, mask_path.display())
                    })?
                    .into_luma8();
                anyhow::ensure!(
                    mask.width() == cam.width && mask.height() == cam.height,
                    "camera `{}`, frame {}: mask `{}` is {}x{}, the camera {}x{}",
                    cam.name,
                    entry.frame,
                    mask_path.display(),
                    mask.width(),
                    mask.height(),
                    cam.width,
                    cam.height
                );
                for (px, m) in view.chunks_exact(3).zip(mask.as_raw()) {
                    let rgb = [px[0], px[1], px[2]];
                    let truth = skin.contains(m);
                    let said = models[c].is_skin(rgb);
                    adapted.add(said, truth);
                    per_camera[c].add(said, truth);
                    prior.add(generic.is_skin(rgb), truth);
                }
            }
        }
        if score {
            scored += 1;
        }
    }
    Ok(SkinScores {
        precision: adapted.precision(),
        recall: adapted.recall(),
        precision_generic: prior.precision(),
        recall_generic: prior.recall(),
        face_detections: detections.iter().sum(),
        frames_scored: scored,
        cameras: cameras
            .iter()
            .zip(&per_camera)
            .zip(&detections)
            .map(|((cam, counts), &d)| CameraScores {
                camera: cam.name.clone(),
                precision: counts.precision(),
                recall: counts.recall(),
                face_detections: d,
            })
            .collect(),
    })
}
