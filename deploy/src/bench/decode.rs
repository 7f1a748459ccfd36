//! `handflow bench decode`: reading a recording's videos into frame sets against reading the
//! same frames from PNG folders, in one run.

use std::path::Path;
use std::time::Instant;

use anyhow::{Context, Result};
use handflow_ingest::recording::image_folders::write_image_folders;
use handflow_ingest::{Layout, Recording};

/// What `bench decode` measured.
#[derive(Clone, Debug, serde::Serialize)]
pub struct DecodeBench {
    /// The recording.
    pub recording: String,
    /// Cameras per frame set.
    pub cameras: usize,
    /// Frame size (first camera).
    pub width: u32,
    /// Frame size (first camera).
    pub height: u32,
    /// Frame sets read per pass.
    pub frame_sets: usize,
    /// Passes over each source; the figures are of the fastest.
    pub passes: usize,
    /// Frame sets per second read from the videos (GStreamer, cameras in parallel).
    pub video_sets_per_second: f64,
    /// Frame sets per second read from the same frames as PNGs (fast compression, Up filter,
    /// as `handflow import` and `render` write them), cameras in parallel.
    pub png_sets_per_second: f64,
    /// `video_sets_per_second / png_sets_per_second`.
    pub video_vs_png: f64,
    /// Threads of the pool (cores).
    pub threads: usize,
}

/// Seconds to read every frame set of `rec` once, in order.
fn read_all(rec: &Recording) -> Result<f64> {
    let mut buf = vec![0u8; rec.frame_set_len()];
    let started = Instant::now();
    for k in 0..rec.len() {
        rec.read_frame_into(k as u64, false, &mut buf).with_context(|| format!("frame set {k}"))?;
    }
    Ok(started.elapsed().as_secs_f64())
}

/// Writes the recording's frames as PNGs into a temporary folder (untimed), then reads both
/// `passes` times, alternating, and keeps each source's fastest pass.
pub fn bench_decode(recording: &Path, frames: Option<usize>, passes: usize) -> Result<DecodeBench> {
    let options = handflow_ingest::OpenOptions { frames, ..Default::default() };
    let videos = Recording::open_with(recording, &options)?;
    anyhow::ensure!(
        videos.layout() == Layout::Videos,
        "`{}` holds image folders, not videos: nothing to compare",
        recording.display()
    );
    let scratch = std::env::temp_dir().join(format!("handflow-bench-decode-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&scratch);
    let written = write_image_folders(&videos, &scratch, |_, _| {});
    let result = written.map_err(anyhow::Error::from).and_then(|_| {
        let pngs = Recording::open(&scratch)?;
        anyhow::ensure!(pngs.len() == videos.len(), "the PNG copy lost frame sets");
        let (mut video_best, mut png_best) = (f64::INFINITY, f64::INFINITY);
        // A fresh decoder per pass: each starts at frame 0 as a replay does.
        for _ in 0..passes.max(1) {
            let again = Recording::open_with(recording, &options)?;
            video_best = video_best.min(read_all(&again)?);
            png_best = png_best.min(read_all(&pngs)?);
        }
        let n = videos.len() as f64;
        let camera = &videos.rig().cameras[0];
        Ok(DecodeBench {
            recording: recording.display().to_string(),
            cameras: videos.rig().cameras.len(),
            width: camera.width,
            height: camera.height,
            frame_sets: videos.len(),
            passes: passes.max(1),
            video_sets_per_second: n / video_best,
            png_sets_per_second: n / png_best,
            video_vs_png: png_best / video_best,
            threads: rayon::current_num_threads(),
        })
    });
    let _ = std::fs::remove_dir_all(&scratch);
    result
}
