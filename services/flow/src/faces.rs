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
}

/// Faces smaller than this many pixels are below the model's window and never found.
pub const MIN_FACE_PX: u32 = 40;

impl FaceDetector {
    /// A detector with the shipped model.
    pub fn new() -> Result<Self, String> {
        let model = rustface::read_model(MODEL).map_err(|e| format!("face model: {e}"))?;
        let mut detector = rustface::create_detector_with_model(model);
        detector.set_score_thresh(2.0);
        detector.set_pyramid_scale_factor(0.8);
        detector.set_slide_window_step(4, 4);
        Ok(Self { detector, gray: Vec::new() })
    }

    /// Frontal faces in an RGB8 image. Images smaller than a face window give none.
    pub fn detect(&mut self, rgb: &[u8], width: u32, height: u32) -> Vec<FaceBox> {
        self.detect_in(rgb, width, height, Region { x: 0, y: 0, width, height })
    }

    /// Frontal faces inside `region` of an RGB8 image (boxes in whole-image pixels). The
    /// detector's cost grows with the area searched: a region around the last face costs a
    /// few percent of the frame.
    pub fn detect_in(&mut self, rgb: &[u8], width: u32, height: u32, region: Region) -> Vec<FaceBox> {
        let region = region.clamped(width, height);
        if region.width < MIN_FACE_PX
            || region.height < MIN_FACE_PX
            || rgb.len() != width as usize * height as usize * 3
        {
            return Vec::new();
        }
        self.gray.clear();
        for y in region.y..region.y + region.height {
            let start = (y as usize * width as usize + region.x as usize) * 3;
            let row = &rgb[start..start + region.width as usize * 3];
            self.gray.extend(
                row.chunks_exact(3)
                    .map(|p| ((u32::from(p[0]) * 77 + u32::from(p[1]) * 150 + u32::from(p[2]) * 29) >> 8) as u8),
            );
        }
        let image = ImageData::new(&self.gray, region.width, region.height);
        self.detector
            .detect(&image)
            .into_iter()
            .map(|f| {
                let b = f.bbox();
                FaceBox {
                    x: (b.x() + region.x as i32) as f32,
                    y: (b.y() + region.y as i32) as f32,
                    width: b.width() as f32,
                    height: b.height() as f32,
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
