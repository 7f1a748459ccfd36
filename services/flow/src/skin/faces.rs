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
    /// One row of the region in grey.
    grey_row: Vec<f32>,
    /// The region's rows binned across.
    across: Vec<f32>,
    /// How each detector column and row averages image columns and rows.
    column_taps: Vec<Taps>,
    row_taps: Vec<Taps>,
}

/// Faces smaller than this many pixels are below the model's window and never found.
pub const MIN_FACE_PX: u32 = 40;
/// A face expected this many pixels wide or more is searched for on binned pixels
/// ([`detection_bin`]): 1.6 times the model's window, so the face may shrink by a third
/// between rounds (a head moving from 1 m to 1.5 m away) and still be found.
pub const DETECTION_FACE_PX: f32 = 64.0;

/// The bin for a face expected `face_px` pixels wide: the one that makes it
/// [`DETECTION_FACE_PX`] wide (fractional: a whole bin would leave a face 1.99 times that
/// size searched at full resolution, for four times the work), at most
/// [`MAX_DETECTION_BIN`]; 1 when its size is unknown (not a positive number) or smaller.
pub fn detection_bin(face_px: f32) -> f32 {
    if face_px.is_finite() && face_px > 0.0 {
        (face_px / DETECTION_FACE_PX).clamp(1.0, MAX_DETECTION_BIN)
    } else {
        1.0
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
        Ok(Self {
            detector,
            gray: Vec::new(),
            upright: Vec::new(),
            grey_row: Vec::new(),
            across: Vec::new(),
            column_taps: Vec::new(),
            row_taps: Vec::new(),
        })
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
        self.detect_in_binned(rgb, width, height, region, turns, 1.0)
    }

    /// [`FaceDetector::detect_in_turned`] on the region binned by `bin` (at least 1): each
    /// detector pixel is the mean grey of a square `bin` image pixels wide, weighted by
    /// overlap where `bin` is not whole. The detector scans every scale from its 40 px window
    /// up to the whole image, and the largest scales cost the most: a face known to be 130
    /// px wide is found as well at half the resolution, for a quarter of the work
    /// ([`detection_bin`] chooses the bin). Boxes come back in raw image pixels.
    pub fn detect_in_binned(
        &mut self,
        rgb: &[u8],
        width: u32,
        height: u32,
        region: Region,
        turns: u8,
        bin: f32,
    ) -> Vec<FaceBox> {
        let region = region.clamped(width, height);
        let bin = if bin.is_finite() { bin.clamp(1.0, MAX_DETECTION_BIN) } else { 1.0 };
        // Whole detector pixels only: the region's last pixels that do not fill one are
        // left out.
        let (rw, rh) = ((region.width as f32 / bin) as u32, (region.height as f32 / bin) as u32);
        if rw < MIN_FACE_PX || rh < MIN_FACE_PX || rgb.len() != width as usize * height as usize * 3 {
            return Vec::new();
        }
        self.binned_grey(rgb, width, region, bin, rw as usize, rh as usize);
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

    /// Fills `self.gray` (`out_w` x `out_h`) with the grey of `region` averaged over
    /// squares `bin` pixels wide: one pass along each row of the region, then one down the
    /// columns. A whole `bin` gives each square's rounded mean.
    fn binned_grey(&mut self, rgb: &[u8], width: u32, region: Region, bin: f32, out_w: usize, out_h: usize) {
        fill_taps(bin, out_w, &mut self.column_taps);
        fill_taps(bin, out_h, &mut self.row_taps);
        // The region's rows binned across (sums of whole grey levels with weights that are
        // whole for a whole bin: exact in f32).
        let rows = self.row_taps.last().map_or(0, |t| t.first + t.weights.len());
        self.across.clear();
        self.across.resize(rows * out_w, 0.0);
        self.grey_row.resize(region.width as usize, 0.0);
        for (y, out) in self.across.chunks_exact_mut(out_w).enumerate() {
            let start = ((region.y as usize + y) * width as usize + region.x as usize) * 3;
            let row = &rgb[start..start + region.width as usize * 3];
            for (g, p) in self.grey_row.iter_mut().zip(row.chunks_exact(3)) {
                *g = ((u32::from(p[0]) * 77 + u32::from(p[1]) * 150 + u32::from(p[2]) * 29) >> 8) as f32;
            }
            for (o, taps) in out.iter_mut().zip(&self.column_taps) {
                *o = taps.apply(|x| self.grey_row[x]);
            }
        }
        let area = bin * bin;
        self.gray.clear();
        self.gray.resize(out_w * out_h, 0);
        for (out, taps) in self.gray.chunks_exact_mut(out_w).zip(&self.row_taps) {
            for (x, g) in out.iter_mut().enumerate() {
                *g = (taps.apply(|y| self.across[y * out_w + x]) / area).round().min(255.0) as u8;
            }
        }
    }
}

/// Largest bin a face is searched at (a face 512 px wide is still searched at 64).
pub const MAX_DETECTION_BIN: f32 = 8.0;

/// The image pixels one detector pixel averages along one axis: `weights.len()` pixels from
/// `first`, each weighted by how much of it the bin covers.
#[derive(Clone, Debug, Default, PartialEq)]
struct Taps {
    first: usize,
    weights: Vec<f32>,
}

impl Taps {
    #[inline]
    fn apply(&self, value: impl Fn(usize) -> f32) -> f32 {
        self.weights.iter().enumerate().map(|(k, w)| w * value(self.first + k)).sum()
    }
}

/// The taps of `count` bins `bin` pixels wide laid end to end from pixel 0.
fn fill_taps(bin: f32, count: usize, taps: &mut Vec<Taps>) {
    taps.resize_with(count, Taps::default);
    for (i, t) in taps.iter_mut().enumerate() {
        // In f64 so a whole bin's edges fall exactly on pixel edges.
        let (a, b) = (i as f64 * f64::from(bin), (i + 1) as f64 * f64::from(bin));
        t.first = a.floor() as usize;
        let last = (b.ceil() as usize).max(t.first + 1);
        t.weights.clear();
        t.weights.extend((t.first..last).map(|p| (b.min(p as f64 + 1.0) - a.max(p as f64)).max(0.0) as f32));
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
    fn the_bin_makes_a_face_the_detection_size() {
        assert_eq!(detection_bin(0.0), 1.0, "unknown size: full resolution");
        assert_eq!(detection_bin(f32::NAN), 1.0);
        assert_eq!(detection_bin(-5.0), 1.0);
        assert_eq!(detection_bin(63.0), 1.0, "never upsampled");
        assert_eq!(detection_bin(64.0), 1.0);
        assert_eq!(detection_bin(100.0), 1.5625);
        assert_eq!(detection_bin(128.0), 2.0);
        assert_eq!(detection_bin(5000.0), MAX_DETECTION_BIN, "bounded");
        for px in [64.0f32, 100.0, 150.0, 300.0, 512.0] {
            assert!((px / detection_bin(px) - DETECTION_FACE_PX).abs() < 1e-3);
        }
    }

    #[test]
    fn whole_bins_average_squares_and_fractional_bins_weigh_by_overlap() {
        let mut detector = FaceDetector::new().expect("model loads");
        // A 6x4 grey ramp (R = G = B, so grey equals the level up to the luma rounding).
        let (w, h) = (6u32, 4u32);
        let level = |x: u32, y: u32| (10 * x + 60 * y) as u8;
        let rgb: Vec<u8> = (0..h).flat_map(|y| (0..w).flat_map(move |x| [level(x, y); 3])).collect();
        let grey = |x: u32, y: u32| f32::from(((u32::from(level(x, y)) * 256) >> 8) as u8);
        let region = Region { x: 0, y: 0, width: w, height: h };
        detector.binned_grey(&rgb, w, region, 2.0, 3, 2);
        for (i, &g) in detector.gray.iter().enumerate() {
            let (bx, by) = (i as u32 % 3, i as u32 / 3);
            let mean = (0..2).flat_map(|dy| (0..2).map(move |dx| grey(2 * bx + dx, 2 * by + dy))).sum::<f32>() / 4.0;
            assert_eq!(g, mean.round() as u8, "bin ({bx}, {by})");
        }
        // Bins 1.5 wide: the second column bin covers half of pixel 1 and all of pixel 2.
        detector.binned_grey(&rgb, w, region, 1.5, 4, 2);
        let second = (0.5 * grey(1, 0) + grey(2, 0) + 0.5 * (0.5 * grey(1, 1) + grey(2, 1))) / 2.25;
        assert_eq!(detector.gray[1], second.round() as u8);
    }

    #[test]
    fn a_region_too_small_once_binned_finds_nothing() {
        let mut detector = FaceDetector::new().expect("model loads");
        let rgb = vec![128u8; 100 * 100 * 3];
        let region = Region { x: 0, y: 0, width: 100, height: 100 };
        assert!(detector.detect_in_binned(&rgb, 100, 100, region, 0, 3.0).is_empty());
        assert!(detector.detect_in_binned(&rgb, 100, 99, region, 0, 1.0).is_empty(), "wrong buffer size");
    }
}
