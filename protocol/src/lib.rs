//! The wire of handflow: what the services agree on.
//!
//! The rig calibration: [`Camera`] (OpenCV pinhole model with
//! k1 k2 p1 p2 k3 distortion, world-to-camera pose) and [`Rig`] with its TOML
//! file format (the per-camera tables written by anipose and Pose2Sim).
//! [`messages`] are the zero-copy message types the stages exchange and [`ipc`] the
//! services they travel on (names, settings per delivery mode, ports); [`wire`] is the same
//! messages as bytes for networks.
//!
//! Conventions (see DESIGN.md, "Coordinates and units"): the world frame is
//! right-handed in metres, `x_cam = R x_world + t`, and pixels are `K` applied
//! to the distorted normalised point `(x/z, y/z)`.

#![cfg_attr(test, allow(clippy::unwrap_used))]

pub mod ipc;
pub mod messages;
pub mod records;
pub mod rig;
pub mod wire;

pub use rig::{Camera, Distortion, Ray, Rig, RigError, RigFormat, UpSource, WorldUp};
