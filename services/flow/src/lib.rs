//! handflow's scene-flow stage: the Scene Particle engine of "Go With The Flow" (sections
//! 2.2, 4 and 4.1), as a library with no IPC in it.
//!
//! A [`SceneFlowEngine`] is built for a calibrated rig and a reference camera. Frames are
//! pushed one synchronised set at a time ([`SceneFlowEngine::push_frame`]); each estimate
//! holds N weighted Scene Particles per ray of the reference camera (3D position on the
//! ray, 3D velocity) and a dense per-ray field ([`DenseField`]). Two variants share the
//! particle machinery ([`Variant`]): `paper`, the method as published, and `handflow`, the
//! default, which adds spatial coupling and robust matching.
//!
//! The crate is grouped by concern: [`engine`] (the particle filter and its per-ray
//! operations), [`matching`] (images, projections and the costs that compare them), [`skin`]
//! (the skin-colour term and the face detections that adapt it), [`stream`] (the engine over
//! a stream of frame sets) and [`config`] (every parameter).

#![cfg_attr(test, allow(clippy::unwrap_used))]

pub mod config;
pub mod engine;
pub mod matching;
pub mod skin;
pub mod stream;

pub use config::{Coverage, EngineConfig, Temporal, Variant, MAX_PARTICLES_PER_RAY};
pub use engine::particles::Particle;
pub use engine::{DenseField, FlowError, FrameStats, SceneFlowEngine};
