//! Shared fixtures of the module's tests.

use std::path::PathBuf;

use super::{Scene, LAYOUT_VIEWS};

/// A 9-view scene of blank images (disparity scale and span 1, range 0 ..= 16) with one
/// ground-truth map per listed view.
pub(crate) fn synthetic_scene(width: u32, height: u32, gt: Vec<(usize, Vec<f32>)>) -> Scene {
    let pixels = (width * height) as usize;
    Scene {
        name: "synthetic".to_string(),
        dir: PathBuf::from("synthetic"),
        width,
        height,
        images: vec![vec![0; pixels * 3]; LAYOUT_VIEWS],
        disparity_scale: 1.0,
        disparity_span: 1.0,
        disparity_range: (0.0, 16.0),
        gt,
    }
}
