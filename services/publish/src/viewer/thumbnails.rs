//! The viewer's per-camera thumbnails: a view shrunk by an integer factor, the tracks drawn
//! on it, encoded as JPEG with a small header for the WebSocket.

use handflow_protocol::Camera;
use image::codecs::jpeg::JpegEncoder;
use image::RgbImage;

use crate::drawing::draw_tracks_scaled;
use crate::TrajectoryRecord;

/// Thumbnails are at most this wide.
pub const MAX_WIDTH: u32 = 320;
/// JPEG quality of a thumbnail.
const QUALITY: u8 = 75;

/// A view `width` x `height` (RGB8, rows packed), of which the camera's image is the top-left
/// `cam_width` x `cam_height` (views are padded to the largest camera), shrunk by the
/// smallest integer factor that brings it to at most [`MAX_WIDTH`] wide: each output pixel
/// is the mean of its block. Returns the image and its scale (output / input).
pub fn shrink(view: &[u8], width: u32, height: u32, cam_width: u32, cam_height: u32) -> Option<(RgbImage, f64)> {
    let (w, h) = (cam_width.min(width), cam_height.min(height));
    if w == 0 || h == 0 || view.len() < width as usize * height as usize * 3 {
        return None;
    }
    let factor = w.div_ceil(MAX_WIDTH).max(1);
    let (tw, th) = ((w / factor).max(1), (h / factor).max(1));
    let stride = width as usize * 3;
    let area = factor * factor;
    let mut out = RgbImage::new(tw, th);
    for (ty, row) in out.rows_mut().enumerate() {
        for (tx, px) in row.enumerate() {
            let mut sum = [0u32; 3];
            for dy in 0..factor as usize {
                let start = (ty * factor as usize + dy) * stride + tx * factor as usize * 3;
                for chunk in view[start..start + factor as usize * 3].chunks_exact(3) {
                    for c in 0..3 {
                        sum[c] += u32::from(chunk[c]);
                    }
                }
            }
            px.0 = sum.map(|s| ((s + area / 2) / area) as u8);
        }
    }
    Some((out, 1.0 / factor as f64))
}

/// The thumbnail of camera `index` at `frame`: the tracks' `tail` drawn on `image` (the
/// camera's view at `scale`), as a WebSocket message: camera index (u32 LE), frame (u64 LE),
/// then the JPEG.
pub fn encode(
    index: u32,
    frame: u64,
    mut image: RgbImage,
    scale: f64,
    cam: &Camera,
    tail: &[TrajectoryRecord],
) -> Result<Vec<u8>, image::ImageError> {
    draw_tracks_scaled(&mut image, cam, tail, scale);
    let mut out = Vec::with_capacity(16 * 1024);
    out.extend_from_slice(&index.to_le_bytes());
    out.extend_from_slice(&frame.to_le_bytes());
    JpegEncoder::new_with_quality(&mut out, QUALITY).encode_image(&image)?;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shrinking_averages_whole_blocks_of_the_cameras_own_pixels() {
        // A 1280x720 camera in a view padded to 1288x722: factor 4, 320x180.
        let (w, h) = (1288u32, 722u32);
        let mut view = vec![0u8; (w * h * 3) as usize];
        for y in 0..h as usize {
            for x in 0..w as usize {
                let v = if x < 1280 && y < 720 { (x % 4 * 20) as u8 } else { 255 };
                view[(y * w as usize + x) * 3..][..3].copy_from_slice(&[v, 10, 200]);
            }
        }
        let (img, scale) = shrink(&view, w, h, 1280, 720).expect("shrunk");
        assert_eq!((img.width(), img.height(), scale), (320, 180, 0.25));
        // Mean of 0, 20, 40, 60; the padding never leaks into the last column.
        assert_eq!(img.get_pixel(0, 0).0, [30, 10, 200]);
        assert_eq!(img.get_pixel(319, 179).0, [30, 10, 200]);
        assert!(shrink(&view[..10], w, h, 1280, 720).is_none());
        let (small, s) = shrink(&vec![7u8; 200 * 100 * 3], 200, 100, 200, 100).expect("small");
        assert_eq!((small.width(), s, small.get_pixel(5, 5).0), (200, 1.0, [7, 7, 7]));
    }
}
