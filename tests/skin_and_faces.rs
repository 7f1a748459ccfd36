//! The face detector and the adaptive skin model on rendered signer scenes: the detector
//! finds the synthetic face, and adapting to it makes the skin decision separate head and
//! hands from everything else better than the generic prior, more so with more frames.
//! (The target of 0.9 precision and recall is not reached yet: see the README.)

use handflow_flow::faces::FaceDetector;
use handflow_flow::skin::SkinModel;
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
fn the_detector_finds_the_rendered_face_and_adaptation_beats_the_generic_prior() {
    let spec = SceneSpec::preset("signer-3cam").expect("preset");
    let renderer = Renderer::new(&spec).expect("renderer");
    let views = spec.cameras.angles_deg.len();
    let view = renderer.view_len();
    let pixels = view / 3;
    let mut rgb = vec![0u8; view * views];
    let mut masks = vec![0u8; pixels * views];
    renderer.render_into(0, &mut rgb, &mut masks);
    let truth = renderer.truth(0, &masks);
    let head_pixel = truth[0].1.pixel[1].expect("head projects into the front camera");
    let front = &rgb[view..2 * view];
    let mut detector = FaceDetector::new().expect("model loads");
    let faces = detector.detect(front, spec.width, spec.height);
    eprintln!("faces in the front camera: {faces:?}");
    let face = faces
        .iter()
        .find(|f| f.contains(head_pixel[0] as f32, head_pixel[1] as f32))
        .expect("the front camera's face is found around the head's projection");
    let generic = SkinModel::generic(0.3);
    let mut adapted = generic.clone();
    assert!(adapted.adapt(front, spec.width, spec.height, &[*face]));
    let mut many = adapted.clone();
    for frame in 1..10 {
        renderer.render_into(frame * 5, &mut rgb, &mut masks);
        let front = &rgb[view..2 * view];
        let faces = detector.detect(front, spec.width, spec.height);
        many.adapt(front, spec.width, spec.height, &faces);
    }
    renderer.render_into(0, &mut rgb, &mut masks);
    let front = &rgb[view..2 * view];
    let mask = &masks[pixels..2 * pixels];
    let m = score(&many, front, mask);
    eprintln!(
        "after {} adaptations: precision {:.3} recall {:.3} alpha {:.2}",
        many.adaptations(),
        m.precision,
        m.recall,
        many.alpha()
    );
    let g = score(&generic, front, mask);
    let a = score(&adapted, front, mask);
    eprintln!(
        "generic precision {:.3} recall {:.3}; adapted precision {:.3} recall {:.3}",
        g.precision, g.recall, a.precision, a.recall
    );
    assert!(a.precision > g.precision, "adaptation improves precision");
    assert!(a.precision + a.recall > g.precision + g.recall, "and the decision overall");
    assert!(m.precision > a.precision && m.recall > 0.7, "more frames keep improving it");
    assert!(many.adaptations() >= 8, "the face is found in most frames: {}", many.adaptations());
}
