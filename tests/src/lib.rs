//! Helpers for handflow's end-to-end tests: where the shared test data lives, and how to
//! make small scenes from it.

use std::path::PathBuf;

/// The Middlebury Teddy scene (`../shared/data/middlebury/teddy` from the repository root),
/// or `None` with a message when this clone does not have it.
pub fn teddy_dir() -> Option<PathBuf> {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/middlebury/teddy");
    if dir.join("scene.toml").is_file() {
        Some(dir)
    } else {
        eprintln!("skipped: {} is absent (shared test data not present in this clone)", dir.display());
        None
    }
}

/// Writes a `width x height` crop of Teddy at `(x0, y0)` as a scene folder in `dir`.
pub fn cropped_teddy(dir: &std::path::Path, x0: u32, y0: u32, width: u32, height: u32) -> Option<PathBuf> {
    let teddy = teddy_dir()?;
    let scene = handflow::middlebury::Scene::load(&teddy).expect("Teddy loads");
    let crop = scene.crop(x0, y0, width, height).expect("crop inside the image");
    let out = dir.join("teddy-crop");
    crop.save(&out).expect("cropped scene saves");
    Some(out)
}
