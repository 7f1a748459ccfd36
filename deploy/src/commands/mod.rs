//! The commands a user runs on footage and pipelines, one module each.

pub mod export;
pub mod import;
pub mod inspect;
pub mod launcher;
pub mod overlay;
pub mod rig;
pub mod tap;
pub mod track;
