//! handflow's front door: the command line that runs the pipeline (the launcher), taps its
//! services, evaluates and benchmarks. The library half holds everything the commands do, so
//! tests can call it without spawning processes.
//!
//! Rooms by concern:
//! - [`commands`]: what a user runs on footage and pipelines (`run`, `tap`, `track`,
//!   `overlay`, ...), one module per command;
//! - [`eval`]: scoring against ground truth or another tracker (Middlebury, skin masks,
//!   trajectories);
//! - [`export`]: trajectories as the files other tools read (TRC, C3D, CSV);
//! - [`bench`]: speed measurements that report ratios against a baseline of the same run;
//! - [`recording_engine`] and [`engine_overrides`]: the engine's configuration on a recording,
//!   shared by the commands, the evaluations and the benchmarks.

#![cfg_attr(test, allow(clippy::unwrap_used))]

pub mod bench;
pub mod cli;
pub mod commands;
pub mod engine_overrides;
pub mod eval;
pub mod export;
pub mod face_up;
pub mod recording_engine;
