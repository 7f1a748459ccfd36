//! handflow's front door: the command line that runs the pipeline (the launcher), taps its
//! services, evaluates and benchmarks. The library half holds everything the commands do, so tests can call it
//! without spawning processes.

#![cfg_attr(test, allow(clippy::unwrap_used))]

pub mod cli;
pub mod cluster_bench;
pub mod flow_eval;
pub mod launcher;
pub mod middlebury;
pub mod overlay;
pub mod recording_flow;
pub mod skin_eval;
pub mod stream_bench;
pub mod tap;
pub mod track;
pub mod track_eval;
