//! `handflow eval skin`: per-pixel precision and recall of the skin decision against a
//! recording's object masks, for the generic prior and for the model adapted from face
//! detections.

use std::path::Path;

use anyhow::{Context, Result};
use handflow_flow::skin::adapt::{SkinAdapter, DEFAULT_ADAPTATION_RATE, DEFAULT_DETECT_EVERY};
use handflow_flow::skin::model::SkinModel;
use handflow_ingest::synthetic::MASKS_DIR;
use handflow_ingest::Recording;

/// Adaptation rate of the skin model per face detection.
pub const ADAPTATION_RATE: f32 = DEFAULT_ADAPTATION_RATE;
/// Every how many frames faces are detected (off the hot path in the live pipeline).
pub const DETECT_EVERY: u64 = DEFAULT_DETECT_EVERY;
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
    /// Detections dropped because no other view agreed with them.
    pub faces_rejected: usize,
    /// Frames scored (per camera).
    pub frames_scored: usize,
    /// Per camera (rig order): adapted precision and recall.
    pub cameras: Vec<CameraScores>,
    /// Per skin-coloured object (`head`, `left_hand`, `right_hand`): adapted recall.
    pub objects: Vec<ObjectRecall>,
}

/// The share of one object's pixels the adapted model calls skin.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct ObjectRecall {
    /// Object name.
    pub object: String,
    /// Adapted model: recall on this object's pixels.
    pub recall: f64,
    /// Pixels of this object scored.
    pub pixels: u64,
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
    /// Face detections (confirmed by another view) used to adapt this camera's model.
    pub face_detections: usize,
    /// Faces lent by the other views (their detector missed) used to adapt this model.
    pub faces_transferred: usize,
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

const SKIN_OBJECTS: [&str; 3] = ["head", "left_hand", "right_hand"];

/// Mask ids of the skin-coloured objects (`head`, `left_hand`, `right_hand`) from
/// `truth.json`'s `mask_ids` when it has them, else the renderer's 1, 2, 3.
fn skin_ids(rec: &Recording) -> Result<[u8; 3]> {
    let renderer = [1, 2, 3];
    let Some(path) = rec.truth_path() else { return Ok(renderer) };
    let text = std::fs::read_to_string(path).with_context(|| format!("reading `{}`", path.display()))?;
    let truth: serde_json::Value = serde_json::from_str(&text).with_context(|| format!("`{}`", path.display()))?;
    let mut ids = renderer;
    for (id, key) in ids.iter_mut().zip(SKIN_OBJECTS) {
        if let Some(v) = truth["mask_ids"][key].as_u64() {
            *id =
                u8::try_from(v).with_context(|| format!("`{}`: mask_ids.{key} = {v} is not a byte", path.display()))?;
        }
    }
    Ok(ids)
}

/// Runs the evaluation on a recording with masks (`masks/<camera>/<frame>.png`).
pub fn evaluate_skin(dir: &Path) -> Result<SkinScores> {
    let rec = Recording::open(dir)?;
    let skin = skin_ids(&rec)?;
    let cameras = &rec.rig().cameras;
    let mut buf = vec![0u8; rec.frame_set_len()];
    let generic = SkinModel::generic(ADAPTATION_RATE);
    let mut adapter = SkinAdapter::new(cameras, ADAPTATION_RATE, DETECT_EVERY).map_err(anyhow::Error::msg)?;
    let mut per_camera: Vec<Counts> = cameras.iter().map(|_| Counts::default()).collect();
    let (mut adapted, mut prior) = (Counts::default(), Counts::default());
    let mut scored = 0;
    let mut object_counts = [(0u64, 0u64); 3];
    for (k, entry) in rec.frames().iter().enumerate() {
        let detect = (k as u64).is_multiple_of(DETECT_EVERY);
        let score = k % SCORE_EVERY == 0;
        if !detect && !score {
            continue;
        }
        rec.read_frame_into(k as u64, false, &mut buf)?;
        let views = rec.views(&buf);
        if detect {
            adapter.adapt_now(&views);
        }
        for (c, cam) in cameras.iter().enumerate() {
            let view = views[c];
            if score {
                let mask_path = dir.join(MASKS_DIR).join(&cam.name).join(
                    rec.image_path(k, c)
                        .and_then(Path::file_name)
                        .context("masks belong to image-folder recordings")?,
                );
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
                    let object = skin.iter().position(|id| id == m);
                    let truth = object.is_some();
                    let said = adapter.models()[c].is_skin(rgb);
                    if let Some(o) = object {
                        object_counts[o].0 += u64::from(said);
                        object_counts[o].1 += 1;
                    }
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
    let stats = adapter.stats();
    Ok(SkinScores {
        precision: adapted.precision(),
        recall: adapted.recall(),
        precision_generic: prior.precision(),
        recall_generic: prior.recall(),
        face_detections: stats.detected.iter().sum::<u64>() as usize,
        faces_rejected: stats.rejected as usize,
        frames_scored: scored,
        cameras: cameras
            .iter()
            .zip(&per_camera)
            .zip(stats.detected.iter().zip(&stats.lent))
            .map(|((cam, counts), (&d, &t))| CameraScores {
                camera: cam.name.clone(),
                precision: counts.precision(),
                recall: counts.recall(),
                face_detections: d as usize,
                faces_transferred: t as usize,
            })
            .collect(),
        objects: SKIN_OBJECTS
            .iter()
            .zip(object_counts)
            .map(|(name, (hit, total))| ObjectRecall {
                object: (*name).to_owned(),
                recall: hit as f64 / total.max(1) as f64,
                pixels: total,
            })
            .collect(),
    })
}
