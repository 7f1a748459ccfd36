//! Photometric matching: the engine's normalised images and pyramids, each camera's
//! projection onto them, and the costs that score a Scene Particle against them.

pub mod camera;
pub mod image;
pub mod isa;
pub mod likelihood;
