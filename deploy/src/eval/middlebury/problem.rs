//! The simulated-motion problem of EVALUATION.md section 1: which real view each virtual
//! camera (viewpoint) sees at each frame, the cameras in the world frame, the estimator's
//! search space and the ground truth of the reference view.

use std::fmt;
use std::str::FromStr;

use handflow_protocol::{Camera, Distortion};
use nalgebra::{Matrix3, Point3, Rotation3, Vector3};

use super::{Scene, SceneError};

/// Views a scene must have for the layout tables (im0 .. im8).
pub const LAYOUT_VIEWS: usize = 9;

/// Frame index of the current frame `t` in [`Problem::frames`] (0 is `t-1`), both layouts.
pub const CURRENT_FRAME: usize = 1;

/// Smallest neighbour-view disparity (pixels) the estimator is told to consider when the
/// scene's `disparity_range` starts at 0: a disparity of 0 is a point at infinity, which
/// no depth range can hold. A quarter pixel is 4 times farther than the 1-pixel disparity
/// of the farthest Teddy background.
pub const MIN_D1: f64 = 0.25;

/// Bound on each velocity component told to the estimator, world units (camera spacings)
/// per frame: twice the spacing, so the true speed of 1 sits well inside the box without
/// being given away.
pub const SPEED_BOUND: f64 = 2.0;

/// How real views become frames of fixed virtual cameras (EVALUATION.md section 1).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Layout {
    /// 8 images, 4 viewpoints, 2 frames: t-1 = im1 im3 im5 im7, t = im0 im2 im4 im6.
    Multiview,
    /// 9 images, 3 viewpoints, 3 frames: t-1 = im2 im5 im8, t = im1 im4 im7, t+1 = im0 im3 im6.
    Fb,
}

/// A layout name that is neither `multiview` nor `fb`.
#[derive(thiserror::Error, Debug, Clone, PartialEq, Eq)]
#[error("unknown layout `{0}` (expected `multiview` or `fb`)")]
pub struct ParseLayoutError(pub String);

impl Layout {
    /// Both layouts.
    pub const ALL: [Layout; 2] = [Layout::Multiview, Layout::Fb];

    /// The layout's name as written on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Layout::Multiview => "multiview",
            Layout::Fb => "fb",
        }
    }

    /// `frames()[k][q]`: scene image index seen by viewpoint `q` at frame `k` (0 is `t-1`).
    pub fn frames(self) -> &'static [&'static [usize]] {
        match self {
            Layout::Multiview => &[&[1, 3, 5, 7], &[0, 2, 4, 6]],
            Layout::Fb => &[&[2, 5, 8], &[1, 4, 7], &[0, 3, 6]],
        }
    }

    /// The reference viewpoint: the one showing im2 (multiview) or im4 (fb) at `t`.
    pub fn reference(self) -> usize {
        1
    }
}

impl fmt::Display for Layout {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Layout {
    type Err = ParseLayoutError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Layout::ALL
            .into_iter()
            .find(|l| l.name().eq_ignore_ascii_case(s.trim()))
            .ok_or_else(|| ParseLayoutError(s.to_string()))
    }
}

/// Ground truth of the reference view at `t`.
#[derive(Clone, Debug, PartialEq)]
pub struct Truth {
    /// Reference image width.
    pub width: u32,
    /// Reference image height.
    pub height: u32,
    /// Neighbour-view disparity per pixel, row-major, NaN where unknown. The true depth is
    /// `f / d1`, the true optical flow from `t-1` to `t` is `(d1, 0)` and the true scene
    /// flow is `(1, 0, 0)` per frame.
    pub d1: Vec<f32>,
}

impl Truth {
    /// Pixels with known ground truth.
    pub fn known(&self) -> usize {
        self.d1.iter().filter(|d| d.is_finite() && **d > 0.0).count()
    }

    /// Largest known disparity (0 when none is known).
    pub fn max_d1(&self) -> f64 {
        self.d1.iter().filter(|d| d.is_finite()).fold(0.0f64, |m, &d| m.max(f64::from(d)))
    }
}

/// A scene posed as a scene-flow problem: cameras, frames, search space and truth.
#[derive(Clone, Debug)]
pub struct Problem {
    /// One camera per viewpoint. Viewpoint `q` sits at `X` = index of its current view,
    /// looking down `+Z` (x right, y down), `f` = image width, principal point at the image
    /// centre in the pixel-centre convention (pixel (0,0)'s centre is (0,0), so `cx = (w -
    /// 1) / 2`, `cy = (h - 1) / 2`), no distortion, `R = I`, `t = -C`.
    pub cameras: Vec<Camera>,
    /// Index of the reference viewpoint.
    pub reference: usize,
    /// `frames[k][q]`: scene image index seen by viewpoint `q` at frame `k` (0 is `t-1`,
    /// 1 is `t`, 2 is `t+1` for `fb`).
    pub frames: Vec<Vec<usize>>,
    /// `(z_near, z_far)` in world units: `f / d1` at the ends of `disparity_range /
    /// disparity_span`, a lower end of 0 becoming [`MIN_D1`].
    pub depth_range: (f64, f64),
    /// Symmetric bound on each velocity component, world units per frame
    /// ([`SPEED_BOUND`]; never the true motion).
    pub speed_bound: f64,
    /// Ground truth of the reference view at `t`.
    pub truth: Truth,
}

impl Problem {
    /// Poses `scene` (which must have [`LAYOUT_VIEWS`] views) in `layout`.
    pub fn new(scene: &Scene, layout: Layout) -> Result<Problem, SceneError> {
        if scene.images.len() != LAYOUT_VIEWS {
            return Err(SceneError::ViewCount {
                scene: scene.name.clone(),
                path: scene.dir.clone(),
                layout: layout.name().to_string(),
                views: scene.images.len(),
                expected: LAYOUT_VIEWS,
            });
        }
        let (width, height) = (scene.width, scene.height);
        let f = f64::from(width);
        let matrix = Matrix3::new(
            f,
            0.0,
            (f64::from(width) - 1.0) / 2.0,
            0.0,
            f,
            (f64::from(height) - 1.0) / 2.0,
            0.0,
            0.0,
            1.0,
        );
        let frames: Vec<Vec<usize>> = layout.frames().iter().map(|frame| frame.to_vec()).collect();
        let cameras = frames[CURRENT_FRAME]
            .iter()
            .enumerate()
            .map(|(q, &view)| {
                let name = format!("viewpoint{q}");
                let centre = Vector3::new(view as f64, 0.0, 0.0);
                Camera::new(name.clone(), width, height, matrix, Distortion::default(), Rotation3::identity(), -centre)
                    .map_err(|e| SceneError::Camera { scene: scene.name.clone(), camera: name, reason: e.to_string() })
            })
            .collect::<Result<Vec<_>, _>>()?;

        let d1_high = scene.disparity_range.1 / scene.disparity_span;
        let d1_low = scene.disparity_range.0 / scene.disparity_span;
        let d1_low = if d1_low > 0.0 { d1_low } else { MIN_D1 };
        if d1_high <= d1_low {
            return Err(SceneError::BadKey {
                path: scene.dir.join("scene.toml"),
                key: "disparity_range",
                reason: format!(
                    "neighbour-view disparities up to {d1_high} px (range / span) leave no depth range above the \
                     {d1_low} px floor"
                ),
            });
        }
        let depth_range = (f / d1_high, f / d1_low);

        let reference = layout.reference();
        let target = frames[CURRENT_FRAME][reference];
        let d1 = match scene.gt_of(target) {
            Some(d1) => d1.to_vec(),
            None => warp_disparity(width, height, &scene.gt, target),
        };
        Ok(Problem {
            cameras,
            reference,
            frames,
            depth_range,
            speed_bound: SPEED_BOUND,
            truth: Truth { width, height, d1 },
        })
    }

    /// The reference camera.
    pub fn reference_camera(&self) -> &Camera {
        &self.cameras[self.reference]
    }

    /// Focal length of the reference camera, pixels (also the neighbour-view disparity of a
    /// point at depth 1).
    pub fn focal(&self) -> f64 {
        self.reference_camera().matrix[(0, 0)]
    }

    /// The world point at camera-frame depth `z` on the ray of reference pixel `(x, y)`.
    pub fn back_project(&self, x: f64, y: f64, z: f64) -> Point3<f64> {
        let camera = self.reference_camera();
        let k = camera.matrix;
        let normalised = Vector3::new((x - k[(0, 2)]) / k[(0, 0)], (y - k[(1, 2)]) / k[(1, 1)], 1.0);
        camera.camera_to_world(&Point3::from(normalised * z))
    }
}

/// Forward-warps the disparity maps `sources` (`(view, d1)` pairs, row-major `width` x
/// `height`) into view `target`: pixel `x` of view `g` with disparity `d1` lands at
/// `x - (target - g) * d1` (views numbered left to right; a camera further right sees the
/// content further left), same row, rounded to the nearest pixel. Where several land, the
/// largest disparity (nearest point) wins; pixels reached by none are NaN.
pub fn warp_disparity(width: u32, height: u32, sources: &[(usize, Vec<f32>)], target: usize) -> Vec<f32> {
    let (w, h) = (width as usize, height as usize);
    let mut out = vec![f32::NAN; w * h];
    for (view, d1) in sources {
        let shift = target as f64 - *view as f64;
        for y in 0..h {
            for x in 0..w {
                let Some(&d) = d1.get(y * w + x) else { continue };
                if !(d.is_finite() && d > 0.0) {
                    continue;
                }
                let landed = (x as f64 - shift * f64::from(d)).round();
                if landed < 0.0 || landed >= w as f64 {
                    continue;
                }
                let slot = &mut out[y * w + landed as usize];
                // The nearer (larger disparity) point hides the farther one.
                if slot.is_nan() || d > *slot {
                    *slot = d;
                }
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval::middlebury::testing::synthetic_scene;

    #[test]
    fn layout_parses_and_prints_its_name() {
        for layout in Layout::ALL {
            assert_eq!(layout.to_string().parse::<Layout>(), Ok(layout));
        }
        assert_eq!("FB".parse::<Layout>(), Ok(Layout::Fb));
        let err = "stereo".parse::<Layout>().expect_err("not a layout");
        assert!(err.to_string().contains("stereo") && err.to_string().contains("multiview"));
    }

    #[test]
    fn forward_warp_nearer_wins_and_holes_stay_unknown() {
        // One row of view 2: background d1 = 1 everywhere except a foreground pixel of
        // d1 = 3 at x = 5. Warped into view 3 (shift 1): background x lands at x - 1, the
        // foreground at 2, where it hides the background from x = 3; pixel 4 (behind the
        // foreground) is a hole, and the last pixel is reached by none.
        let w = 8;
        let mut row = vec![1.0f32; w];
        row[5] = 3.0;
        row[0] = f32::NAN; // unknown source pixels warp nowhere
        let out = warp_disparity(w as u32, 1, &[(2, row)], 3);
        let expected = [1.0, 1.0, 3.0, 1.0, f32::NAN, 1.0, 1.0, f32::NAN];
        for (x, (got, want)) in out.iter().zip(expected).enumerate() {
            assert!(got == &want || (got.is_nan() && want.is_nan()), "pixel {x}: got {got}, want {want}");
        }
    }

    #[test]
    fn forward_warp_from_both_sides_fills_each_others_holes() {
        // View 0 and view 2 both see a row of d1 = 1; warping into view 1, view 0's content
        // shifts left (last pixel empty) and view 2's shifts right (first pixel empty).
        let w = 6;
        let out = warp_disparity(w as u32, 1, &[(0, vec![1.0; w])], 1);
        assert!(out[w - 1].is_nan() && out[..w - 1].iter().all(|&d| d == 1.0));
        let out = warp_disparity(w as u32, 1, &[(0, vec![1.0; w]), (2, vec![1.0; w])], 1);
        assert!(out.iter().all(|&d| d == 1.0), "{out:?}");
    }

    #[test]
    fn reference_truth_comes_from_its_own_map_or_a_warp() {
        let (w, h) = (10u32, 2u32);
        let pixels = (w * h) as usize;
        let scene = synthetic_scene(w, h, vec![(2, vec![2.0; pixels]), (6, vec![1.5; pixels])]);
        let multiview = Problem::new(&scene, Layout::Multiview).expect("multiview");
        assert_eq!(multiview.truth.d1, vec![2.0; pixels]);
        let fb = Problem::new(&scene, Layout::Fb).expect("fb");
        // View 4 from view 2 (d1 = 2, 4 px left: reaches 0 ..= 5) and view 6 (d1 = 1.5,
        // 3 px right: reaches 3 ..= 9); where both land the nearer (2.0) wins.
        let row: Vec<f32> = fb.truth.d1[..w as usize].to_vec();
        assert_eq!(row, [2.0, 2.0, 2.0, 2.0, 2.0, 2.0, 1.5, 1.5, 1.5, 1.5]);
        assert_eq!(fb.truth.known(), pixels);
    }

    #[test]
    fn layouts_need_nine_views() {
        let mut scene = synthetic_scene(4, 3, vec![]);
        scene.images.pop();
        let err = Problem::new(&scene, Layout::Multiview).expect_err("8 views");
        let text = err.to_string();
        assert!(text.contains("8 views") && text.contains("multiview"), "{text}");
    }

    #[test]
    fn search_space_follows_disparity_range() {
        let mut scene = synthetic_scene(450, 2, vec![]);
        scene.disparity_range = (0.0, 64.0);
        scene.disparity_span = 4.0;
        let problem = Problem::new(&scene, Layout::Multiview).expect("problem");
        assert!((problem.depth_range.0 - 450.0 / 16.0).abs() < 1e-12);
        assert!((problem.depth_range.1 - 450.0 / MIN_D1).abs() < 1e-12);
        assert_eq!(problem.speed_bound, SPEED_BOUND);
        scene.disparity_range = (8.0, 64.0);
        let problem = Problem::new(&scene, Layout::Fb).expect("problem");
        assert!((problem.depth_range.1 - 450.0 / 2.0).abs() < 1e-12);
        scene.disparity_range = (0.0, 0.5);
        let err = Problem::new(&scene, Layout::Fb).expect_err("empty depth range");
        assert!(err.to_string().contains("disparity_range"), "{err}");
    }

    /// Every viewpoint at every frame must see a truth point where the image layout puts
    /// it: a point of disparity d1 at reference pixel x appears in image `i` at
    /// `x - (i - i_ref) * d1`, and the scene moves by (1, 0, 0) per frame.
    #[test]
    fn cameras_and_motion_reproduce_the_image_layout() {
        let (w, h) = (64u32, 48u32);
        let scene = synthetic_scene(w, h, vec![]);
        for layout in Layout::ALL {
            let problem = Problem::new(&scene, layout).expect("problem");
            assert_eq!(problem.cameras.len(), problem.frames[CURRENT_FRAME].len());
            let reference_image = problem.frames[CURRENT_FRAME][problem.reference];
            assert_eq!(reference_image, if layout == Layout::Multiview { 2 } else { 4 });
            assert_eq!(problem.focal(), f64::from(w));
            let motion = Vector3::new(1.0, 0.0, 0.0);
            for (x, y, d1) in [(10.0, 5.0, 2.5), (40.0, 30.0, 0.75), (31.5, 23.5, 4.0)] {
                let p = problem.back_project(x, y, problem.focal() / d1);
                for (k, frame) in problem.frames.iter().enumerate() {
                    // Frame k is (k - 1) frames after t.
                    let at_frame = p + motion * (k as f64 - CURRENT_FRAME as f64);
                    for (q, &image) in frame.iter().enumerate() {
                        let seen = problem.cameras[q].project(&at_frame).expect("in front of the camera");
                        let expected_x = x - (image as f64 - reference_image as f64) * d1;
                        assert!(
                            (seen.x - expected_x).abs() < 1e-9 && (seen.y - y).abs() < 1e-9,
                            "{layout} frame {k} viewpoint {q} (im{image}): {seen:?}, expected ({expected_x}, {y})"
                        );
                    }
                }
            }
        }
    }
}
