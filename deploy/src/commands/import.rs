//! `handflow import`: a recording of videos (or any recording) written out in the
//! image-folder layout, for tools that want images, or to look at single frames.

use std::path::Path;

use anyhow::{bail, Context, Result};
use handflow_ingest::recording::image_folders::{write_image_folders, ImageFoldersReport};
use handflow_ingest::{OpenOptions, Recording};

/// Writes `recording` (as `options` select it) into `out`, which must be empty or absent.
pub fn import_recording(
    recording: &Path,
    options: &OpenOptions,
    out: &Path,
    on_frame: impl FnMut(usize, usize),
) -> Result<ImageFoldersReport> {
    if out.exists() {
        let mut entries = std::fs::read_dir(out).with_context(|| format!("reading `{}`", out.display()))?;
        if entries.next().is_some() {
            bail!("`{}` is not empty: give a new or empty folder", out.display());
        }
    }
    let rec = Recording::open_with(recording, options)?;
    tracing::info!("recording `{}`: {}", recording.display(), rec.summary());
    Ok(write_image_folders(&rec, out, on_frame)?)
}
