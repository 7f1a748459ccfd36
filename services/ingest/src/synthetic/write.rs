//! Writing a rendered scene as a recording (see [`crate::recording`]) with its truth.

use std::path::Path;

use rayon::prelude::*;
use serde::Serialize;

use super::render::{ids, ObjectTruth, Renderer};
use crate::recording::image_folders::write_png;
pub use crate::recording::image_folders::WriteError;
use crate::recording::{FRAMES_FILE, RIG_FILE, TRUTH_FILE};

/// Folder of the object-id masks inside a rendered recording: `masks/<camera>/<frame>.png`.
pub const MASKS_DIR: &str = "masks";
/// The scene description a recording was rendered from.
pub const SCENE_FILE: &str = "scene.toml";

/// `truth.json`: per frame and object, position, velocity, projection and visibility.
#[derive(Serialize)]
struct TruthFile<'a> {
    fps: f64,
    cameras: Vec<&'a str>,
    mask_ids: std::collections::BTreeMap<&'static str, u8>,
    frames: Vec<FrameTruth>,
}

#[derive(Serialize)]
struct FrameTruth {
    frame: u32,
    t: f64,
    objects: std::collections::BTreeMap<&'static str, ObjectTruth>,
}

/// Renders `frames` frames of `renderer`'s scene into `out` as a recording: `rig.toml`,
/// `frames.csv`, one PNG folder per camera, `masks/<camera>/`, `truth.json`, `scene.toml`.
pub fn write_recording(renderer: &Renderer, out: &Path, frames: u32) -> Result<(), WriteError> {
    let io = |path: &Path, error: String| WriteError::Io { path: path.to_path_buf(), error };
    let rig = renderer.rig();
    for cam in &rig.cameras {
        for dir in [out.join(&cam.name), out.join(MASKS_DIR).join(&cam.name)] {
            std::fs::create_dir_all(&dir).map_err(|e| io(&dir, e.to_string()))?;
        }
    }
    rig.save(out.join(RIG_FILE)).map_err(|e| io(&out.join(RIG_FILE), e.to_string()))?;
    let scene = toml::to_string(renderer.spec()).map_err(|e| io(&out.join(SCENE_FILE), e.to_string()))?;
    std::fs::write(out.join(SCENE_FILE), scene).map_err(|e| io(&out.join(SCENE_FILE), e.to_string()))?;
    let mut csv = String::from("frame,timestamp\n");
    let views = rig.cameras.len();
    let mut rgb = vec![0u8; renderer.view_len() * views];
    let mut masks = vec![0u8; renderer.view_len() / 3 * views];
    let mut truth = Vec::with_capacity(frames as usize);
    for frame in 0..frames {
        renderer.render_into(frame, &mut rgb, &mut masks);
        let t = renderer.time(frame);
        csv.push_str(&format!("{frame},{t:.6}\n"));
        truth.push(FrameTruth { frame, t, objects: renderer.truth(frame, &masks).into_iter().collect() });
        let name = format!("{frame:06}.png");
        // Every view has as many pixels; a camera's own width and height say their layout.
        rig.cameras.par_iter().enumerate().try_for_each(|(c, cam)| {
            let (w, h) = (cam.width, cam.height);
            let view = &rgb[c * renderer.view_len()..(c + 1) * renderer.view_len()];
            let path = out.join(&cam.name).join(&name);
            write_png(&path, view, w, h, image::ExtendedColorType::Rgb8)?;
            let mask = &masks[c * (w * h) as usize..(c + 1) * (w * h) as usize];
            let path = out.join(MASKS_DIR).join(&cam.name).join(&name);
            write_png(&path, mask, w, h, image::ExtendedColorType::L8)
        })?;
    }
    std::fs::write(out.join(FRAMES_FILE), csv).map_err(|e| io(&out.join(FRAMES_FILE), e.to_string()))?;
    let file = TruthFile {
        fps: renderer.spec().fps,
        cameras: rig.cameras.iter().map(|c| c.name.as_str()).collect(),
        mask_ids: [
            ("background", ids::BACKGROUND),
            ("head", ids::HEAD),
            ("left_hand", ids::LEFT_HAND),
            ("right_hand", ids::RIGHT_HAND),
            ("torso", ids::TORSO),
            ("arms", ids::ARMS),
            ("hair", ids::HAIR),
            ("forearms", ids::FOREARMS),
        ]
        .into_iter()
        .collect(),
        frames: truth,
    };
    let json = serde_json::to_string(&file).map_err(|e| io(&out.join(TRUTH_FILE), e.to_string()))?;
    std::fs::write(out.join(TRUTH_FILE), json).map_err(|e| io(&out.join(TRUTH_FILE), e.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::recording::Recording;
    use crate::synthetic::SceneSpec;

    #[test]
    fn a_rendered_scene_is_a_valid_recording_with_truth_and_masks() {
        let tmp = tempfile::tempdir().expect("tempdir");
        let mut spec = SceneSpec::preset("signer-3cam").expect("preset");
        spec.width = 96;
        spec.height = 72;
        let renderer = Renderer::new(&spec).expect("renderer");
        write_recording(&renderer, tmp.path(), 4).expect("written");
        let rec = Recording::open(tmp.path()).expect("the output opens as a recording");
        assert_eq!(rec.len(), 4);
        assert_eq!(rec.rig().cameras.len(), 3);
        let truth: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(rec.truth_path().expect("truth.json")).expect("read"))
                .expect("json");
        assert_eq!(truth["frames"].as_array().map(Vec::len), Some(4));
        let head = &truth["frames"][2]["objects"]["head"];
        assert_eq!(head["pos"].as_array().map(Vec::len), Some(3));
        assert_eq!(head["visible"].as_array().map(Vec::len), Some(3));
        assert!(tmp.path().join("masks/cam1/000003.png").is_file());
        let mut buf = vec![0u8; rec.frame_set_len()];
        rec.read_frame_into(3, false, &mut buf).expect("frames decode");
    }

    #[test]
    fn a_camera_mounted_sideways_is_written_at_its_own_size_with_its_turns() {
        let tmp = tempfile::tempdir().expect("tempdir");
        let mut spec = SceneSpec::preset("signer-3cam").expect("preset");
        (spec.width, spec.height) = (96, 72);
        spec.cameras.mount_quarter_turns = vec![0, 1, 0];
        let renderer = Renderer::new(&spec).expect("renderer");
        write_recording(&renderer, tmp.path(), 2).expect("written");
        let rec = Recording::open(tmp.path()).expect("the output opens as a recording");
        let cam = &rec.rig().cameras[1];
        assert_eq!((cam.width, cam.height, cam.mount_quarter_turns), (72, 96, 1));
        assert_eq!(rec.rig().cameras[0].mount_quarter_turns, 0);
        let mut buf = vec![0u8; rec.frame_set_len()];
        rec.read_frame_into(1, false, &mut buf).expect("frames decode at their sizes");
        let mut rgb = vec![0u8; renderer.view_len() * 3];
        let mut masks = vec![0u8; renderer.view_len()];
        renderer.render_into(1, &mut rgb, &mut masks);
        assert_eq!(buf, rgb, "the PNGs hold the rendered views");
        let mask = image::open(tmp.path().join("masks/cam1/000001.png")).expect("mask").into_luma8();
        assert_eq!(mask.dimensions(), (72, 96));
        assert_eq!(mask.as_raw()[..], masks[96 * 72..2 * 96 * 72]);
    }
}
