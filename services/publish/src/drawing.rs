//! Trajectories drawn on a camera's image: the paper's figure 2, shared by `handflow
//! overlay`, `handflow inspect` and the live viewer's thumbnails.

use handflow_protocol::messages::OBJECT_LABELS;
use nalgebra::Point3;

use crate::{TrackState, TrajectoryRecord};

/// Colours of head, left hand and right hand (the viewer page uses the same).
pub const COLOURS: [[u8; 3]; 3] = [[255, 220, 0], [0, 230, 80], [255, 40, 40]];

/// Draws the positions of `tail` (oldest first) of every object as `cam` sees them, on an
/// image `scale` times the camera's size (a thumbnail).
pub fn draw_tracks_scaled(
    img: &mut image::RgbImage,
    cam: &handflow_protocol::Camera,
    tail: &[TrajectoryRecord],
    scale: f64,
) {
    let detail = scale.clamp(0.25, 1.0);
    for (k, name) in OBJECT_LABELS.iter().enumerate() {
        let points: Vec<(f64, f64, bool)> = tail
            .iter()
            .filter_map(|r| r.objects.get(*name))
            .filter(|o| o.state != TrackState::Lost)
            .filter_map(|o| {
                cam.project(&Point3::from(o.pos)).map(|q| (q.x * scale, q.y * scale, o.state == TrackState::Tracked))
            })
            .collect();
        for w in points.windows(2) {
            draw_line(img, (w[0].0, w[0].1), (w[1].0, w[1].1), COLOURS[k]);
        }
        for (i, &(x, y, tracked)) in points.iter().enumerate() {
            // The newest position largest; predicted positions hollow.
            let radius = (2.0 + 4.0 * (i + 1) as f64 / points.len() as f64) * detail;
            draw_disc(img, x, y, radius.max(1.5), COLOURS[k], !tracked);
        }
    }
}

/// [`draw_tracks_scaled`] at the camera's own size.
pub fn draw_tracks(img: &mut image::RgbImage, cam: &handflow_protocol::Camera, tail: &[TrajectoryRecord]) {
    draw_tracks_scaled(img, cam, tail, 1.0);
}

/// Sets one pixel, if it is inside the image.
pub fn put(img: &mut image::RgbImage, x: i64, y: i64, colour: [u8; 3]) {
    if x >= 0 && y >= 0 && (x as u32) < img.width() && (y as u32) < img.height() {
        img.put_pixel(x as u32, y as u32, image::Rgb(colour));
    }
}

/// A disc of radius `r` centred on (`cx`, `cy`); only its rim when `hollow`.
pub fn draw_disc(img: &mut image::RgbImage, cx: f64, cy: f64, r: f64, colour: [u8; 3], hollow: bool) {
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

/// A one-pixel line from `a` to `b`.
pub fn draw_line(img: &mut image::RgbImage, a: (f64, f64), b: (f64, f64), colour: [u8; 3]) {
    let steps = (b.0 - a.0).abs().max((b.1 - a.1).abs()).ceil().clamp(1.0, 4096.0) as usize;
    for s in 0..=steps {
        let t = s as f64 / steps as f64;
        let (x, y) = (a.0 + (b.0 - a.0) * t, a.1 + (b.1 - a.1) * t);
        put(img, x.round() as i64, y.round() as i64, colour);
    }
}
