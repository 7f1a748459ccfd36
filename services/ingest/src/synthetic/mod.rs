//! Synthetic signer scenes rendered with exact ground truth: the test material of
//! tracking. [`SceneSpec`] describes a scene (or names a preset), [`Renderer`] ray-traces
//! its frames, object masks and truth.

mod render;
mod scene;
mod write;

pub use render::{ids, ObjectTruth, Renderer};
pub use scene::{CameraArc, Keyframe, Motion, SceneSpec, FOREARM_M, OBJECTS, PRESETS};
pub use write::{write_recording, WriteError, MASKS_DIR, SCENE_FILE};
