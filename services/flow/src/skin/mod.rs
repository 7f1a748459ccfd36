//! The skin-colour term: per-camera skin models, and the face detections, checked across
//! the cameras, that adapt them.

pub mod adapt;
pub mod face_fusion;
pub mod faces;
pub mod model;
