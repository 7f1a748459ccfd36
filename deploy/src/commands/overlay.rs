//! `handflow overlay`: the last positions of each trajectory drawn on every camera's images
//! (the paper's figure 2), for checking a result by eye.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use handflow_ingest::Recording;
use handflow_publish::drawing::draw_tracks;
use handflow_publish::TrajectoryRecord;

/// Positions drawn per trajectory: the current one and the four before it.
pub const TAIL: usize = 5;

/// Writes `out/<camera>/<frame number>.png` for every frame of `records`, drawn on the
/// recording's own frames (decoded from its images or videos). A frame that cannot be read
/// is reported and skipped. Returns the images written.
pub fn write_overlays(rec: &Recording, records: &[TrajectoryRecord], out: &Path) -> Result<usize> {
    let cameras = &rec.rig().cameras;
    for cam in cameras {
        let dir = out.join(&cam.name);
        std::fs::create_dir_all(&dir).with_context(|| format!("creating `{}`", dir.display()))?;
    }
    let mut written = 0;
    for_each_drawn_frame(rec, records, |index, images| {
        for ((c, cam), img) in cameras.iter().enumerate().zip(images) {
            let name = match rec.image_path(index, c).and_then(Path::file_name) {
                Some(name) => Path::new(name).with_extension("png"),
                None => format!("{:06}.png", rec.frames()[index].frame).into(),
            };
            let target = out.join(&cam.name).join(name);
            img.save(&target).with_context(|| format!("writing `{}`", target.display()))?;
            written += 1;
        }
        Ok(())
    })?;
    Ok(written)
}

/// Calls `each` with the recording index and every camera's image (tracks drawn) of each
/// record's frame, in order. A frame that cannot be read is reported and skipped.
fn for_each_drawn_frame(
    rec: &Recording,
    records: &[TrajectoryRecord],
    mut each: impl FnMut(usize, Vec<image::RgbImage>) -> Result<()>,
) -> Result<()> {
    let cameras = &rec.rig().cameras;
    let by_frame: std::collections::BTreeMap<u64, usize> =
        rec.frames().iter().enumerate().map(|(i, f)| (f.frame, i)).collect();
    let mut buf = vec![0u8; rec.frame_set_len()];
    for (n, record) in records.iter().enumerate() {
        let index = *by_frame
            .get(&record.frame)
            .with_context(|| format!("trajectory frame {} is not in the recording", record.frame))?;
        match rec.read_frame_into(index as u64, false, &mut buf) {
            Ok(_) => {}
            Err(error) if error.is_bad_frame() => {
                tracing::error!("overlay of frame {} skipped: {error}", record.frame);
                continue;
            }
            Err(error) => return Err(error.into()),
        }
        let tail = &records[n.saturating_sub(TAIL - 1)..=n];
        let mut images = Vec::with_capacity(cameras.len());
        for (cam, view) in cameras.iter().zip(rec.views(&buf)) {
            let mut img = image::RgbImage::from_raw(cam.width, cam.height, view.to_vec())
                .with_context(|| format!("camera `{}`: frame buffer of the wrong size", cam.name))?;
            draw_tracks(&mut img, cam, tail);
            images.push(img);
        }
        each(index, images)?;
    }
    Ok(())
}

/// Longest side of the montage video, pixels: the cameras are scaled down to fit.
const MONTAGE_MAX_WIDTH: u32 = 1920;

/// The videos `handflow overlay --video` writes.
#[derive(Debug)]
pub struct OverlayVideos {
    /// One video per camera, in rig order.
    pub cameras: Vec<PathBuf>,
    /// Every camera side by side in a grid.
    pub montage: PathBuf,
    /// Frames in each video.
    pub frames: u64,
}

/// Writes `out/<camera>.webm` per camera and `out/montage.webm` (all cameras in a grid,
/// scaled to at most 1920 pixels wide), the tracks drawn as [`write_overlays`] draws them,
/// at the recording's frame rate. A frame that cannot be read is reported and skipped.
pub fn write_overlay_videos(rec: &Recording, records: &[TrajectoryRecord], out: &Path) -> Result<OverlayVideos> {
    use handflow_ingest::live::{VideoFileWriter, WEBM_VP8};
    let cameras = &rec.rig().cameras;
    std::fs::create_dir_all(out).with_context(|| format!("creating `{}`", out.display()))?;
    let fps = rec.frame_rate();
    let mut videos = cameras
        .iter()
        .map(|cam| {
            VideoFileWriter::create(&out.join(format!("{}.webm", cam.name)), cam.width, cam.height, fps, WEBM_VP8)
        })
        .collect::<Result<Vec<_>, _>>()?;
    let layout = MontageLayout::new(cameras.iter().map(|c| (c.width, c.height)).collect());
    let mut montage = VideoFileWriter::create(&out.join("montage.webm"), layout.width, layout.height, fps, WEBM_VP8)?;
    for_each_drawn_frame(rec, records, |_, images| {
        for (video, img) in videos.iter_mut().zip(&images) {
            video.push(img.as_raw())?;
        }
        montage.push(layout.compose(&images).as_raw())?;
        Ok(())
    })?;
    let frames = montage.written();
    let cameras = videos.into_iter().map(|v| v.finish()).collect::<Result<Vec<_>, _>>()?;
    let montage = montage.finish()?;
    Ok(OverlayVideos { cameras, montage, frames })
}

/// Where each camera goes in the montage: a grid of about as many columns as rows, every
/// tile scaled by one factor so that the whole is at most [`MONTAGE_MAX_WIDTH`] wide.
#[derive(Debug)]
struct MontageLayout {
    columns: u32,
    tile: (u32, u32),
    width: u32,
    height: u32,
}

impl MontageLayout {
    fn new(sizes: Vec<(u32, u32)>) -> Self {
        let count = sizes.len().max(1) as u32;
        let columns = (f64::from(count).sqrt().ceil() as u32).max(1);
        let rows = count.div_ceil(columns);
        let (w, h) = sizes.iter().fold((1, 1), |(w, h), &(cw, ch)| (w.max(cw), h.max(ch)));
        let scale = (f64::from(MONTAGE_MAX_WIDTH) / f64::from(columns * w)).min(1.0);
        // Even sizes: the encoder works on 2x2 chroma blocks.
        let even = |v: f64| ((v as u32) & !1).max(2);
        let tile = (even(f64::from(w) * scale), even(f64::from(h) * scale));
        Self { columns, tile, width: tile.0 * columns, height: tile.1 * rows }
    }

    fn compose(&self, tiles: &[image::RgbImage]) -> image::RgbImage {
        let mut canvas = image::RgbImage::new(self.width, self.height);
        for (k, tile) in tiles.iter().enumerate() {
            let small = image::imageops::resize(tile, self.tile.0, self.tile.1, image::imageops::FilterType::Triangle);
            let (col, row) = (k as u32 % self.columns, k as u32 / self.columns);
            image::imageops::replace(&mut canvas, &small, i64::from(col * self.tile.0), i64::from(row * self.tile.1));
        }
        canvas
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_montage_is_a_near_square_grid_of_even_tiles_at_most_1920_wide() {
        let four = MontageLayout::new(vec![(1280, 720); 4]);
        assert_eq!((four.columns, four.tile, four.width, four.height), (2, (960, 540), 1920, 1080));
        let three = MontageLayout::new(vec![(640, 480); 3]);
        assert_eq!((three.columns, three.tile, three.width, three.height), (2, (640, 480), 1280, 960));
        let one = MontageLayout::new(vec![(321, 241)]);
        assert_eq!((one.tile, one.width % 2, one.height % 2), ((320, 240), 0, 0));
        let tiles = vec![image::RgbImage::from_pixel(640, 480, image::Rgb([200, 10, 10])); 3];
        let canvas = three.compose(&tiles);
        assert_eq!(canvas.get_pixel(700, 100).0, [200, 10, 10], "second tile, top right");
        assert_eq!(canvas.get_pixel(1000, 700).0, [0, 0, 0], "no fourth camera: black");
    }
}
