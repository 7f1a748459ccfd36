//! `handflow overlay`: the last positions of each trajectory drawn on every camera's images
//! (the paper's figure 2), for checking a result by eye.

use std::path::Path;

use anyhow::{Context, Result};
use handflow_cluster::tracks::OBJECTS;
use handflow_ingest::Recording;
use handflow_publish::{TrackState, TrajectoryRecord};
use nalgebra::Point3;

/// Positions drawn per trajectory: the current one and the four before it.
pub const TAIL: usize = 5;
/// Colours of head, left hand and right hand.
const COLOURS: [[u8; 3]; 3] = [[255, 220, 0], [0, 230, 80], [255, 40, 40]];

/// Writes `out/<camera>/<frame number>.png` for every frame of `records`, drawn on the
/// recording's own frames (decoded from its images or videos). A frame that cannot be read
/// is reported and skipped. Returns the images written.
pub fn write_overlays(rec: &Recording, records: &[TrajectoryRecord], out: &Path) -> Result<usize> {
    let cameras = &rec.rig().cameras;
    let by_frame: std::collections::BTreeMap<u64, usize> =
        rec.frames().iter().enumerate().map(|(i, f)| (f.frame, i)).collect();
    for cam in cameras {
        let dir = out.join(&cam.name);
        std::fs::create_dir_all(&dir).with_context(|| format!("creating `{}`", dir.display()))?;
    }
    let mut written = 0;
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
        for ((c, cam), view) in cameras.iter().enumerate().zip(rec.views(&buf)) {
            let mut img = image::RgbImage::from_raw(cam.width, cam.height, view.to_vec())
                .with_context(|| format!("camera `{}`: frame buffer of the wrong size", cam.name))?;
            draw_tracks(&mut img, cam, tail);
            let name = match rec.image_path(index, c).and_then(Path::file_name) {
                Some(name) => Path::new(name).with_extension("png"),
                None => format!("{:06}.png", record.frame).into(),
            };
            let target = out.join(&cam.name).join(name);
            img.save(&target).with_context(|| format!("writing `{}`", target.display()))?;
            written += 1;
        }
    }
    Ok(written)
}

/// Draws the positions of `tail` (oldest first) of every object as `cam` sees them.
pub fn draw_tracks(img: &mut image::RgbImage, cam: &handflow_protocol::Camera, tail: &[TrajectoryRecord]) {
    for (k, name) in OBJECTS.iter().enumerate() {
        let points: Vec<(f64, f64, bool)> = tail
            .iter()
            .filter_map(|r| r.objects.get(*name))
            .filter(|o| o.state != TrackState::Lost)
            .filter_map(|o| cam.project(&Point3::from(o.pos)).map(|q| (q.x, q.y, o.state == TrackState::Tracked)))
            .collect();
        for w in points.windows(2) {
            draw_line(img, (w[0].0, w[0].1), (w[1].0, w[1].1), COLOURS[k]);
        }
        for (i, &(x, y, tracked)) in points.iter().enumerate() {
            // The newest position largest; predicted positions hollow.
            let radius = 2.0 + 4.0 * (i + 1) as f64 / points.len() as f64;
            draw_disc(img, x, y, radius, COLOURS[k], !tracked);
        }
    }
}

pub(crate) fn put(img: &mut image::RgbImage, x: i64, y: i64, colour: [u8; 3]) {
    if x >= 0 && y >= 0 && (x as u32) < img.width() && (y as u32) < img.height() {
        img.put_pixel(x as u32, y as u32, image::Rgb(colour));
    }
}

pub(crate) fn draw_disc(img: &mut image::RgbImage, cx: f64, cy: f64, r: f64, colour: [u8; 3], hollow: bool) {
    let (x0, x1) = ((cx - r).floor() as i64, (cx + r).ceil() as i64);
    let (y0, y1) = ((cy - r).floor() as i64, (cy + r).ceil() as i64);
    for y in y0..=y1 {
        for x in x0..=x1 {
            let d = (x as f64 - cx).hypot(y as f64 - cy);
            if d <= r && (!hollow || d >= r - 1.5) {
                put(img, x, y, colour);
            }
        }
    }
}

pub(crate) fn draw_line(img: &mut image::RgbImage, a: (f64, f64), b: (f64, f64), colour: [u8; 3]) {
    let steps = (b.0 - a.0).abs().max((b.1 - a.1).abs()).ceil().clamp(1.0, 4096.0) as usize;
    for s in 0..=steps {
        let t = s as f64 / steps as f64;
        let (x, y) = (a.0 + (b.0 - a.0) * t, a.1 + (b.1 - a.1) * t);
        put(img, x.round() as i64, y.round() as i64, colour);
    }
}
