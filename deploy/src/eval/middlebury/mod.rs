//! Scene flow on Middlebury multi-baseline scenes (EVALUATION.md section 1).
//!
//! A static scene seen by cameras stepping along a line looks, to a fixed virtual camera,
//! like a scene translating sideways. [`Scene`] loads a folder of views and ground-truth
//! disparity maps; [`Problem`] poses it in a [`Layout`] (cameras, frames, search space and
//! the truth of the reference view); [`evaluate`] scores a dense estimate and
//! [`write_maps`] draws it.
//!
//! Conventions: world units are camera spacings; viewpoint `q` sits at `X` = index of its
//! current view, looking down `+Z`; `f` = image width; the principal point is the image
//! centre with pixel (0,0)'s centre at (0,0), i.e. `((w - 1) / 2, (h - 1) / 2)`. Every
//! scene point moves by `(1, 0, 0)` per frame and has depth `f / d1`, `d1` being the
//! disparity between neighbouring views.

mod error;
mod maps;
mod metrics;
mod pfm;
mod problem;
mod scene;
#[cfg(test)]
mod testing;

pub use error::SceneError;
pub use maps::{flow_colour, turbo, write_maps, ERROR_SCALE_PX};
pub use metrics::{evaluate, Metrics};
pub use pfm::{read_pfm, write_pfm};
pub use problem::{
    warp_disparity, Layout, ParseLayoutError, Problem, Truth, CURRENT_FRAME, LAYOUT_VIEWS, MIN_D1, SPEED_BOUND,
};
pub use scene::Scene;
