//! The Middlebury evaluation end to end on a cropped Teddy: scene folder on disk, the
//! protocol's problem, the engine, the metrics. Debug builds; the crop keeps it quick.

use handflow::eval::middlebury::Layout;
use handflow::eval::middlebury_run::{engine_config, load_problem, run_once, EvalOptions};
use handflow_e2e::cropped_teddy;
use handflow_flow::Variant;

fn evaluate(layout: Layout, variant: Variant) -> Option<handflow::eval::middlebury::Metrics> {
    let tmp = tempfile::tempdir().expect("tempdir");
    // The teddy bear and the roof: depth edges, texture and a textureless patch.
    let dir = cropped_teddy(tmp.path(), 130, 90, 200, 150)?;
    let (scene, problem) = load_problem(&dir, layout).expect("cropped scene poses a problem");
    let options = EvalOptions { variant, seed: 1, ..EvalOptions::default() };
    let config = engine_config(&problem, layout, &options).expect("config");
    let result = run_once(&scene, &problem, config).expect("engine runs");
    let m = result.metrics;
    eprintln!("{layout} {}: {m:?}", variant.name());
    assert!(m.pixels > 20_000, "most of the crop has truth: {}", m.pixels);
    for v in [m.of_rmse_px, m.zflow_rmse, m.structure_rmse_px, m.aae_deg] {
        assert!(v.is_finite());
    }
    Some(m)
}

#[test]
fn handflow_multiview_on_cropped_teddy_is_accurate() {
    let Some(m) = evaluate(Layout::Multiview, Variant::Handflow) else { return };
    // The full-image targets are 1.0 px / 1.0 px / 10 deg; a crop has more border.
    assert!(m.of_rmse_px < 1.5, "optical flow RMSE {}", m.of_rmse_px);
    assert!(m.structure_rmse_px < 1.5, "structure RMSE {}", m.structure_rmse_px);
    assert!(m.aae_deg < 15.0, "AAE {}", m.aae_deg);
}

#[test]
fn handflow_fb_on_cropped_teddy_is_accurate() {
    let Some(m) = evaluate(Layout::Fb, Variant::Handflow) else { return };
    assert!(m.of_rmse_px < 1.5, "optical flow RMSE {}", m.of_rmse_px);
    assert!(m.structure_rmse_px < 1.5, "structure RMSE {}", m.structure_rmse_px);
    assert!(m.aae_deg < 15.0, "AAE {}", m.aae_deg);
}

#[test]
fn paper_variant_runs_and_handflow_beats_it() {
    // The reference method has no accuracy target (on Teddy it is about as far off as zero
    // motion, see the note on the prototype); it must run, recover structure roughly, and
    // lose clearly to the default engine.
    let Some(paper) = evaluate(Layout::Multiview, Variant::Paper) else { return };
    let Some(handflow) = evaluate(Layout::Multiview, Variant::Handflow) else { return };
    assert!(paper.structure_rmse_px < 4.0, "paper structure RMSE {}", paper.structure_rmse_px);
    assert!(
        handflow.of_rmse_px * 3.0 < paper.of_rmse_px,
        "handflow {} vs paper {}",
        handflow.of_rmse_px,
        paper.of_rmse_px
    );
}
