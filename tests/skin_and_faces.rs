//! The face detector and the adaptive skin model on rendered signer scenes: the detector
//! finds the synthetic face, and adapting to it makes the skin decision separate head and
//! hands from everything else better than the generic prior, more so with more frames.

use handflow_flow::skin::face_fusion::fuse_faces;
use handflow_flow::skin::faces::FaceDetector;
use handflow_flow::skin::model::SkinModel;
use handflow_ingest::synthetic::{ids, Renderer, SceneSpec};

struct Scores {
    precision: f64,
    recall: f64,
}

fn score(model: &SkinModel, rgb: &[u8], mask: &[u8]) -> Scores {
    let (mut tp, mut fp, mut fn_) = (0f64, 0f64, 0f64);
    for (px, &m) in rgb.chunks_exact(3).zip(mask) {
        let truth = m == ids::HEAD || m == ids::LEFT_HAND || m == ids::RIGHT_HAND;
        let said = model.is_skin([px[0], px[1], px[2]]);
        match (said, truth) {
            (true, true) => tp += 1.0,
            (true, false) => fp += 1.0,
            (false, true) => fn_ += 1.0,
            _ => {}
        }
    }
    Scores { precision: tp / (tp + fp).max(1.0), recall: tp / (tp + fn_).max(1.0) }
}

#[test]
fn faces_found_in_frontal_views_and_lent_to_the_others_make_the_skin_decision_precise() {
    let spec = SceneSpec::preset("signer-3cam").expect("preset");
    let renderer = Renderer::new(&spec).expect("renderer");
    let cameras = &renderer.rig().cameras;
    let views = cameras.len();
    let view = renderer.view_len();
    let pixels = view / 3;
    let mut rgb = vec![0u8; view * views];
    let mut masks = vec![0u8; pixels * views];
    let mut detector = FaceDetector::new().expect("model loads");
    let generic = SkinModel::generic(0.3);
    let mut models = vec![generic.clone(); views];
    let mut detected = vec![0; views];
    let mut lent = vec![0; views];
    for frame in (0..40).step_by(5) {
        renderer.render_into(frame, &mut rgb, &mut masks);
        let truth = renderer.truth(frame, &masks);
        let found: Vec<_> =
            (0..views).map(|c| detector.detect(&rgb[c * view..(c + 1) * view], spec.width, spec.height)).collect();
        // The frontal cameras (-35 and 0 degrees) find the face around the head's projection.
        for c in 0..2 {
            let head = truth[0].1.pixel[c].expect("head projects");
            let hit = found[c].iter().any(|f| f.contains(head[0] as f32, head[1] as f32 + 10.0));
            detected[c] += usize::from(hit);
        }
        let fused = fuse_faces(cameras, &found);
        for c in 0..views {
            let faces: Vec<_> = fused.boxes[c].into_iter().collect();
            models[c].adapt(&rgb[c * view..(c + 1) * view], spec.width, spec.height, &faces);
            lent[c] += usize::from(fused.transferred[c]);
        }
    }
    eprintln!("frames with the face detected per camera: {detected:?}; lent: {lent:?}");
    assert!(detected[0] >= 6 && detected[1] >= 7, "frontal cameras find the face: {detected:?}");
    assert!(lent[2] >= 6, "the +35 degree camera is lent the face the others agree on: {lent:?}");
    // Frames long after the last detection: the model keeps its adapted state.
    for frame in [70, 100] {
        renderer.render_into(frame, &mut rgb, &mut masks);
        for c in 0..views {
            let (colour, mask) = (&rgb[c * view..(c + 1) * view], &masks[c * pixels..(c + 1) * pixels]);
            let a = score(&models[c], colour, mask);
            let g = score(&generic, colour, mask);
            eprintln!(
                "frame {frame} camera {c}: adapted {:.3}/{:.3}, generic {:.3}/{:.3}",
                a.precision, a.recall, g.precision, g.recall
            );
            assert!(a.precision > 0.85 && a.recall > 0.85, "camera {c}, frame {frame}");
            assert!(a.precision + a.recall > g.precision + g.recall, "adaptation beats the prior");
        }
    }
}

/// A three-camera scene's renderer, the size of its front camera (`cam1`, the second) and
/// buffers for a frame set and its masks.
struct FrontCamera {
    renderer: Renderer,
    width: u32,
    height: u32,
    view: usize,
    rgb: Vec<u8>,
    masks: Vec<u8>,
}

impl FrontCamera {
    fn new(spec: &SceneSpec) -> Self {
        let renderer = Renderer::new(spec).expect("renderer");
        let cam = &renderer.rig().cameras[1];
        let (width, height) = (cam.width, cam.height);
        let view = renderer.view_len();
        Self { renderer, width, height, view, rgb: vec![0u8; view * 3], masks: vec![0u8; view] }
    }
}

#[test]
fn a_camera_mounted_sideways_finds_the_face_once_its_frames_are_turned_upright() {
    use handflow_flow::skin::faces::Region;
    for turns in [1u8, 2, 3] {
        let mut spec = SceneSpec::preset("signer-3cam").expect("preset");
        spec.cameras.mount_quarter_turns = vec![0, turns, 0];
        let FrontCamera { renderer, width: w, height: h, view, mut rgb, mut masks } = FrontCamera::new(&spec);
        let mut detector = FaceDetector::new().expect("model loads");
        let (mut turned, mut raw) = (0, 0);
        for frame in (0..40).step_by(5) {
            renderer.render_into(frame, &mut rgb, &mut masks);
            let head = renderer.truth(frame, &masks)[0].1.pixel[1].expect("head projects");
            let image = &rgb[view..2 * view];
            let whole = Region { x: 0, y: 0, width: w, height: h };
            let on_head = |faces: &[handflow_flow::skin::faces::FaceBox]| {
                faces.iter().any(|f| f.contains(head[0] as f32, head[1] as f32))
            };
            turned += usize::from(on_head(&detector.detect_in_turned(image, w, h, whole, turns)));
            raw += usize::from(on_head(&detector.detect_in(image, w, h, whole)));
        }
        eprintln!("turns {turns}: face on the head in {turned} of 8 frames turned upright, {raw} as delivered");
        assert!(turned >= 6, "turns {turns}: the upright frames show a frontal face ({turned} of 8)");
        if turns % 2 == 1 {
            assert!(raw < turned, "turns {turns}: a sideways face is beyond a frontal detector");
        }
    }
}

#[test]
fn a_face_of_known_size_is_found_as_well_on_binned_pixels() {
    use handflow_flow::skin::faces::{detection_bin, Region};
    // The signer seen by 1280x960 cameras with a narrower lens: faces over 128 px wide.
    let mut spec = SceneSpec::preset("signer-3cam").expect("preset");
    (spec.width, spec.height) = (1280, 960);
    spec.cameras.fov_deg = 34.0;
    let FrontCamera { renderer, width: w, height: h, view, mut rgb, mut masks } = FrontCamera::new(&spec);
    let mut detector = FaceDetector::new().expect("model loads");
    let mut binned_frames = 0;
    for frame in (0..40).step_by(5) {
        renderer.render_into(frame, &mut rgb, &mut masks);
        let image = &rgb[view..2 * view];
        let full = detector.detect(image, w, h);
        let Some(face) = full.iter().max_by(|a, b| a.score.total_cmp(&b.score)).copied() else { continue };
        let bin = detection_bin(face.width);
        assert!(bin >= 2.0, "frame {frame}: a {} px face is searched on binned pixels", face.width);
        let region = Region::around(&face, handflow_flow::skin::adapt::SEARCH_SCALE, w, h);
        let binned = detector.detect_in_binned(image, w, h, region, 0, bin);
        let same = binned.iter().find(|f| f.contains(face.x + 0.5 * face.width, face.y + 0.5 * face.height));
        let Some(same) = same else { panic!("frame {frame}: the {} px face is not found at bin {bin}", face.width) };
        let shift = ((same.x + 0.5 * same.width - face.x - 0.5 * face.width).powi(2)
            + (same.y + 0.5 * same.height - face.y - 0.5 * face.height).powi(2))
        .sqrt();
        eprintln!(
            "frame {frame}: {:.0} px face, bin {bin}: {:.0} px, centre {shift:.1} px away",
            face.width, same.width
        );
        assert!(shift < 0.15 * face.width, "frame {frame}: the box centre moved {shift} px");
        assert!((same.width / face.width - 1.0).abs() < 0.3, "frame {frame}: {} px against {}", same.width, face.width);
        binned_frames += 1;
    }
    assert!(binned_frames >= 6, "the front camera finds the face at full resolution: {binned_frames} of 8");
}
