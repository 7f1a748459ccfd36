//! Face detection on the CPU: SeetaFace's frontal cascade through the `rustface` crate,
//! whose crates.io package carries the model (found at build time, see `build.rs`).
//! Runs periodically to adapt the skin model, off the particle filter's hot path.

use rustface::{Detector, ImageData};

/// The SeetaFace frontal model shipped inside the `rustface` package.
const MODEL: &[u8] = include_bytes!(env!("HANDFLOW_FACE_MODEL_PATH"));

/// A detected face, in pixels of the image given to [`FaceDetector::detect`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FaceBox {
    /// Left edge.
    pub x: f32,
    /// Top edge.
    pub y: f32,
    /// Width.
    pub width: f32,
    /// Height.
    pub height: f32,
    /// Detector score (higher is surer).
    pub score: f64,
}

impl FaceBox {
    /// The central region whose colours are the face's skin: the middle half in width and
    /// the middle 60% in height, below the hairline and around the nose and cheeks.
    pub fn skin_region(&self) -> (f32, f32, f32, f32) {
        (self.x + 0.25 * self.width, self.y + 0.25 * self.height, 0.5 * self.width, 0.6 * self.height)
    }

    /// Whether a point lies inside the box.
    pub fn contains(&self, u: f32, v: f32) -> bool {
        u >= self.x && v >= self.y && u <= self.x + self.width && v <= self.y + self.height
    }
}

/// A frontal face detector (one per thread: the underlying detector is not `Send`).
pub struct FaceDetector {
    detector: Box<dyn Detector>,
    gray: Vec<u8>,
    /// The grey region turned upright, for cameras mounted sideways.
    upright: Vec<u8>,
    /// Grey sums of one row of bins.
    row_sums: Vec<u32>,
}

/// Faces smaller than this many pixels are below the model's window and never found.
pub const MIN_FACE_PX: u32 = 40;
/// A face expected this many pixels wide or more is searched for on binned pixels
/// ([`detection_bin`]): 1.6 times the model's window, so the face may shrink by a third
/// between rounds (a head moving from 1 m to 1.5 m away) and still be found.
pub const DETECTION_FACE_PX: f32 = 64.0;

/// The bin for a face expected `face_px` pixels wide: the largest that keeps it
/// [`DETECTION_FACE_PX`] wide, 1 when its size is unknown (not a positive number).
pub fn detection_bin(face_px: f32) -> u32 {
    if face_px.is_finite() && face_px > 0.0 {
        ((face_px / DETECTION_FACE_PX).floor() as u32).clamp(1, 8)
    } else {
        1
    }
}

impl FaceDetector {
    /// A detector with the shipped model.
    pub fn new() -> Result<Self, String> {
        let model = rustface::read_model(MODEL).map_err(|e| format!("face model: {e}"))?;
        let mut detector = rustface::create_detector_with_model(model);
        detector.set_score_thresh(2.0);
        detector.set_pyramid_scale_factor(0.8);
        detector.set_slide_window_step(4, 4);
        Ok(Self { detector, gray: Vec::new(), upright: Vec::new(), row_sums: Vec::new() })
    }

    /// Frontal faces in an RGB8 image. Images smaller than a face window give none.
    pub fn detect(&mut self, rgb: &[u8], width: u32, height: u32) -> Vec<FaceBox> {
        self.detect_in(rgb, width, height, Region { x: 0, y: 0, width, height })
    }

    /// Frontal faces inside `region` of an RGB8 image (boxes in whole-image pixels). The
    /// detector's cost grows with the area searched: a region around the last face costs a
    /// few percent of the frame.
    pub fn detect_in(&mut self, rgb: &[u8], width: u32, height: u32, region: Region) -> Vec<FaceBox> {
        self.detect_in_turned(rgb, width, height, region, 0)
    }

    /// [`FaceDetector::detect_in`] on a camera mounted `turns` clockwise quarter turns from
    /// upright ([`handflow_protocol::Camera::mount_quarter_turns`]): the region is turned
    /// upright before detection, since the model finds upright frontal faces only, and the
    /// boxes come back in the raw image's pixels.
    pub fn detect_in_turned(&mut self, rgb: &[u8], width: u32, height: u32, region: Region, turns: u8) -> Vec<FaceBox> {
        self.detect_in_binned(rgb, width, height, region, turns, 1)
    }

    /// [`FaceDetector::detect_in_turned`] on the region binned `bin` x `bin` (each detector
    /// pixel the mean of that many image pixels; 1 is none). The detector scans every scale
    /// from its 40 px window up to the whole image, and the largest scales cost the most: a
    /// face known to be 130 px wide is found as well at half the resolution, for a quarter
    /// of the work ([`detection_bin`] chooses the bin). Boxes come back in raw image pixels.
    pub fn detect_in_binned(
        &mut self,
        rgb: &[u8],
        width: u32,
        height: u32,
        region: Region,
        turns: u8,
        bin: u32,
    ) -> Vec<FaceBox> {
        let region = region.clamped(width, height);
        let bin = bin.max(1);
        if region.width / bin < MIN_FACE_PX
            || region.height / bin < MIN_FACE_PX
            || rgb.len() != width as usize * height as usize * 3
        {
            return Vec::new();
        }
        // Whole bins only: the region's last pixels that do not fill one are left out.
        let (rw, rh) = (region.width / bin, region.height / bin);
        self.gray.clear();
        self.gray.resize(rw as usize * rh as usize, 0);
        let (b, area) = (bin as usize, bin * bin);
        for (by, out) in self.gray.chunks_exact_mut(rw as usize).enumerate() {
            self.row_sums.clear();
            self.row_sums.resize(rw as usize, 0);
            for y in by * b..(by + 1) * b {
                let start = ((region.y as usize + y) * width as usize + region.x as usize) * 3;
                let row = &rgb[start..start + rw as usize * b * 3];
                for (sum, pixels) in self.row_sums.iter_mut().zip(row.chunks_exact(3 * b)) {
                    *sum += pixels
                        .chunks_exact(3)
                        .map(|p| (u32::from(p[0]) * 77 + u32::from(p[1]) * 150 + u32::from(p[2]) * 29) >> 8)
                        .sum::<u32>();
                }
            }
            for (g, &sum) in out.iter_mut().zip(&self.row_sums) {
                *g = ((sum + area / 2) / area) as u8;
            }
        }
        let turns = turns % 4;
        let (uw, uh) = if turns % 2 == 1 { (rh, rw) } else { (rw, rh) };
        if turns != 0 {
            self.upright.clear();
            self.upright.resize(self.gray.len(), 0);
            let (w, h) = (rw as usize, rh as usize);
            for y in 0..h {
                for x in 0..w {
                    // Clockwise turns: one brings raw (x, y) to (h - 1 - y, x).
                    let (u, v) = match turns {
                        1 => (h - 1 - y, x),
                        2 => (w - 1 - x, h - 1 - y),
                        _ => (y, w - 1 - x),
                    };
                    self.upright[v * uw as usize + u] = self.gray[y * w + x];
                }
            }
            std::mem::swap(&mut self.gray, &mut self.upright);
        }
        let image = ImageData::new(&self.gray, uw, uh);
        let (rw, rh) = (rw as f32, rh as f32);
        self.detector
            .detect(&image)
            .into_iter()
            .map(|f| {
                let b = f.bbox();
                let (u0, v0, bw, bh) = (b.x() as f32, b.y() as f32, b.width() as f32, b.height() as f32);
                // The upright box back in the region's raw pixels.
                let (x, y, width, height) = match turns {
                    0 => (u0, v0, bw, bh),
                    1 => (v0, rh - u0 - bw, bh, bw),
                    2 => (rw - u0 - bw, rh - v0 - bh, bw, bh),
                    _ => (rw - v0 - bh, u0, bh, bw),
                };
                let bin = bin as f32;
                FaceBox {
                    x: x * bin + region.x as f32,
                    y: y * bin + region.y as f32,
                    width: width * bin,
                    height: height * bin,
                    score: f.score(),
                }
            })
            .collect()
    }
}

/// A rectangle of an image, in whole pixels.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Region {
    /// Left edge.
    pub x: u32,
    /// Top edge.
    pub y: u32,
    /// Width.
    pub width: u32,
    /// Height.
    pub height: u32,
}

impl Region {
    /// The square around a face box, `scale` times its size, inside a `width` x `height`
    /// image.
    pub fn around(face: &FaceBox, scale: f32, width: u32, height: u32) -> Region {
        let side = face.width.max(face.height) * scale;
        let (cx, cy) = (face.x + 0.5 * face.width, face.y + 0.5 * face.height);
        let x0 = (cx - 0.5 * side).max(0.0) as u32;
        let y0 = (cy - 0.5 * side).max(0.0) as u32;
        Region { x: x0, y: y0, width: side.max(0.0) as u32, height: side.max(0.0) as u32 }.clamped(width, height)
    }

    fn clamped(self, width: u32, height: u32) -> Region {
        let x = self.x.min(width);
        let y = self.y.min(height);
        Region { x, y, width: self.width.min(width - x), height: self.height.min(height - y) }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_bin_keeps_a_face_at_least_the_detection_size() {
        assert_eq!(detection_bin(0.0), 1, "unknown size: full resolution");
        assert_eq!(detection_bin(f32::NAN), 1);
        assert_eq!(detection_bin(-5.0), 1);
        assert_eq!(detection_bin(63.0), 1);
        assert_eq!(detection_bin(64.0), 1);
        assert_eq!(detection_bin(128.0), 2);
        assert_eq!(detection_bin(191.0), 2);
        assert_eq!(detection_bin(5000.0), 8, "bounded");
        for px in [64.0f32, 100.0, 150.0, 300.0, 512.0] {
            let bin = detection_bin(px);
            assert!(px / bin as f32 >= DETECTION_FACE_PX && px / bin as f32 >= MIN_FACE_PX as f32);
        }
    }

    #[test]
    fn a_region_too_small_once_binned_finds_nothing() {
        let mut detector = FaceDetector::new().expect("model loads");
        let rgb = vec![128u8; 100 * 100 * 3];
        let region = Region { x: 0, y: 0, width: 100, height: 100 };
        assert!(detector.detect_in_binned(&rgb, 100, 100, region, 0, 3).is_empty());
        assert!(detector.detect_in_binned(&rgb, 100, 99, region, 0, 1).is_empty(), "wrong buffer size");
    }
}
