//! The second reference's companion engine ([`EngineConfig::second_reference`]): the rays
//! of the camera looking from the most different direction, kept to what the reference view
//! does not see, estimated on the images the main engine lends it.

use std::time::Instant;

use handflow_protocol::Camera;

use super::{in_image, point_on_ray, ray_grid, FlowError, SceneFlowEngine};
use crate::config::{Coverage, EngineConfig};
use crate::matching::camera::LevelProjection;
use crate::skin::model::{skin_share_of, SKIN_SHARE_STRIDE};

impl SceneFlowEngine {
    /// Builds the companion engine when the rig has a second reference camera: this
    /// engine's configuration without a second reference of its own, its rays left empty
    /// where this engine's reference camera sees.
    pub(super) fn add_companion(&mut self) -> Result<(), FlowError> {
        let config = EngineConfig { second_reference: false, ..self.config.clone() };
        let reference = self.reference;
        if let Some(second) = second_reference_camera(&self.cameras, reference) {
            let mut companion = SceneFlowEngine::new(config, self.cameras.clone(), second)?;
            companion.veto = seen_by(
                &self.cameras[second],
                &self.projections[0][reference],
                self.cameras[reference].width,
                self.cameras[reference].height,
                self.config.depth_range,
            );
            self.companion = Some(Box::new(companion));
        }
        Ok(())
    }

    /// The engine of the second reference camera, if any ([`EngineConfig::second_reference`]):
    /// its last estimate is of the same frame as this one's. It works on this engine's
    /// images: its own skin maps and pyramids are empty (read them from this engine).
    pub fn companion(&self) -> Option<&SceneFlowEngine> {
        self.companion.as_deref()
    }

    /// Runs `step` on the companion engine with this engine's frames (pyramids, skin maps,
    /// which views are there) lent to it: the same images, built once. Adds its cost to
    /// this estimate's. While the newest frame lacks the companion's reference view, or its
    /// skin model cannot be trusted yet ([`Self::companion_view_trusted`]), the companion
    /// starts afresh instead.
    pub(super) fn run_companion(
        &mut self,
        started: Instant,
        step: impl FnOnce(&mut SceneFlowEngine) -> Result<bool, FlowError>,
    ) -> Result<(), FlowError> {
        let Some(second) = self.companion.as_ref().map(|c| c.reference) else { return Ok(()) };
        let present = self.present[self.ring_newest].get(second).copied().unwrap_or(true);
        let trusted = present && self.companion_view_trusted(second);
        let Some(companion) = self.companion.as_mut() else { return Ok(()) };
        if !trusted {
            companion.reset();
            return Ok(());
        }
        std::mem::swap(&mut self.ring, &mut companion.ring);
        std::mem::swap(&mut self.skin_maps, &mut companion.skin_maps);
        std::mem::swap(&mut self.present, &mut companion.present);
        let stepped = step(companion);
        std::mem::swap(&mut self.ring, &mut companion.ring);
        std::mem::swap(&mut self.skin_maps, &mut companion.skin_maps);
        std::mem::swap(&mut self.present, &mut companion.present);
        if stepped? {
            self.stats.evaluations += companion.stats.evaluations;
            self.stats.seconds = started.elapsed().as_secs_f64();
        }
        Ok(())
    }

    /// Whether the skin map of `camera`, the companion's reference, can seed rays. Its rays
    /// start where its own view sees skin; until that view's model has been adapted on a face
    /// (its own, or one the other views lend it), the generic prior decides, and under warm
    /// light it takes walls, wood and doors for skin. Measured on the shared real session
    /// under warmer light (3500 K): 60 % of the companion's view was "skin", its rays matched
    /// a lit door frame to a depth by the body, and the right hand's track followed it for
    /// thirty frames. A generic model is trusted only while it marks at most
    /// [`MAX_GENERIC_SKIN_SHARE`] of the image (the same session in its own light: 6.6 %, so
    /// its companion still places the hands that only it sees in the first frames).
    fn companion_view_trusted(&self, camera: usize) -> bool {
        if self.config.coverage != Coverage::Skin {
            return true;
        }
        if self.skin_models.get(camera).is_none_or(|m| m.adaptations() > 0) {
            return true;
        }
        let Some(map) = self.skin_maps[self.ring_newest].get(camera) else { return true };
        let share = skin_share_of(map, self.config.skin_threshold, SKIN_SHARE_STRIDE);
        let trusted = share <= MAX_GENERIC_SKIN_SHARE;
        if !trusted {
            tracing::debug!(
                "second reference `{}` waits for a face: its generic skin model marks {:.0} % of the view",
                self.cameras[camera].name,
                100.0 * share
            );
        }
        trusted
    }
}

/// Most of its image a skin model never adapted on a face may mark as skin and still seed
/// the companion's rays. People fill a few percent to a fifth of a view in short sleeves;
/// beyond a quarter the generic prior is taking the room's colours for skin.
pub const MAX_GENERIC_SKIN_SHARE: f32 = 0.25;

/// The camera looking from the most different direction than `reference`'s, under 90
/// degrees (a camera behind the person sees no more of the hands), with three or more
/// cameras: the second reference of [`EngineConfig::second_reference`].
pub(crate) fn second_reference_camera(cameras: &[Camera], reference: usize) -> Option<usize> {
    if cameras.len() < 3 {
        return None;
    }
    let axis = |c: &Camera| c.rotation.matrix().row(2).transpose();
    let a = axis(&cameras[reference]);
    (0..cameras.len())
        .filter(|&k| k != reference)
        .map(|k| (k, a.dot(&axis(&cameras[k]))))
        .filter(|&(_, cos)| cos > 0.0)
        .min_by(|x, y| x.1.total_cmp(&y.1))
        .map(|(k, _)| k)
}

/// Full-resolution pixels of `camera` whose ray, over `depth_range`, runs mostly through
/// what the other camera (`seeing`, an image `width` x `height`) sees: at least half of
/// its depths, spaced evenly in inverse depth, project inside that image.
fn seen_by(camera: &Camera, seeing: &LevelProjection, width: u32, height: u32, depth_range: (f32, f32)) -> Vec<bool> {
    const DEPTHS: usize = 16;
    // Decided per ray of level 2 (a 4x4-pixel block): the mask follows the geometry, which
    // changes slowly across the image.
    const LEVEL: usize = 2;
    let block = 1usize << LEVEL;
    let grid = ray_grid(camera, LEVEL, true);
    let centre = camera.centre();
    let origin = [centre.x as f32, centre.y as f32, centre.z as f32];
    let (near, far) = (1.0 / depth_range.0, 1.0 / depth_range.1);
    let inside = |p: [f32; 3]| in_image(seeing, width, height, p);
    let ray_seen: Vec<bool> = grid
        .dirs
        .iter()
        .map(|&dir| {
            let seen = (0..DEPTHS)
                .filter(|&k| {
                    let inverse = near + (far - near) * (k as f32 + 0.5) / DEPTHS as f32;
                    inside(point_on_ray(origin, dir, 1.0 / inverse))
                })
                .count();
            2 * seen >= DEPTHS
        })
        .collect();
    let (w, h) = (camera.width as usize, camera.height as usize);
    (0..w * h)
        .map(|i| ray_seen[((i / w) / block).min(grid.height - 1) * grid.width + ((i % w) / block).min(grid.width - 1)])
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Coverage;
    use crate::engine::tests::{camera, textured_view};
    use handflow_protocol::Distortion;
    use nalgebra::{Matrix3, Rotation3, Vector3};

    /// A camera at `x` looking along +z turned by `yaw_deg` about the vertical axis.
    fn turned_camera(name: &str, x: f64, yaw_deg: f64) -> Camera {
        let k = Matrix3::new(50.0, 0.0, 15.5, 0.0, 50.0, 11.5, 0.0, 0.0, 1.0);
        let rotation = Rotation3::from_axis_angle(&Vector3::y_axis(), yaw_deg.to_radians());
        let translation = -(rotation * Vector3::new(x, 0.0, 0.0));
        Camera::new(name, 32, 24, k, Distortion::default(), rotation, translation).expect("valid camera")
    }

    #[test]
    fn the_second_reference_looks_from_the_most_different_direction_in_front() {
        let rig = vec![
            turned_camera("front", 0.0, 0.0),
            turned_camera("a little aside", 0.2, 20.0),
            turned_camera("side", 0.5, 70.0),
            turned_camera("behind", 1.0, 150.0),
        ];
        assert_eq!(second_reference_camera(&rig, 0), Some(2), "the side camera, not the one behind");
        assert_eq!(second_reference_camera(&rig[..2], 0), None, "two cameras have no third view to match in");
        assert_eq!(second_reference_camera(&[rig[0].clone(), rig[1].clone(), rig[3].clone()], 0), Some(1));
    }

    #[test]
    fn a_second_reference_keeps_only_rays_the_reference_view_does_not_see() {
        let reference = camera("ref", 0.0);
        // 0.3 m to the right, looking the same way: its left edge looks into the reference's
        // view at every depth from 0.5 m on, its right edge never does.
        let second = camera("second", 0.3);
        let seeing = LevelProjection::new(&reference, 0);
        let seen = seen_by(&second, &seeing, 32, 24, (0.5, 5.0));
        assert_eq!(seen.len(), 32 * 24);
        assert!(seen[12 * 32], "left edge: seen by the reference");
        assert!(!seen[12 * 32 + 31], "right edge: beyond the reference's image");
        let engine = SceneFlowEngine::new(
            EngineConfig { coverage: Coverage::Skin, second_reference: true, ..EngineConfig::default() },
            vec![reference.clone(), second, camera("third", -0.1)],
            0,
        )
        .unwrap();
        let companion = engine.companion().expect("three cameras: a second reference");
        assert_eq!(companion.reference(), 1);
        assert!(engine.reference_sees([0.0, 0.0, 2.0]) && !engine.reference_sees([3.0, 0.0, 2.0]));
        assert!(!engine.reference_sees([0.0, 0.0, -2.0]), "behind the camera");
    }

    /// Three 32x24 cameras in a row, skin coverage, the second a companion's reference.
    fn engine_with_a_companion() -> SceneFlowEngine {
        let cameras = vec![camera("ref", 0.0), camera("second", 0.3), camera("third", -0.1)];
        let config = EngineConfig {
            coverage: Coverage::Skin,
            second_reference: true,
            pyramid_levels: 2,
            coarse_extra_loops: 2,
            ..EngineConfig::default()
        };
        SceneFlowEngine::new(config, cameras, 0).unwrap()
    }

    #[test]
    fn a_companion_whose_generic_model_calls_most_of_its_view_skin_waits_for_a_face() {
        use crate::skin::faces::FaceBox;
        use crate::skin::model::SkinModel;
        let mut engine = engine_with_a_companion();
        // A warm wall filling the companion's view: a colour the generic prior calls skin.
        let wall = [222u8, 170, 140];
        assert!(SkinModel::generic(0.0).is_skin(wall));
        let warm_view: Vec<u8> = wall.repeat(32 * 24);
        for f in 0..3 {
            let views = [textured_view(f, 1), warm_view.clone(), textured_view(f + 4, 1)];
            let views: Vec<&[u8]> = views.iter().map(Vec::as_slice).collect();
            engine.push_frame(&views).unwrap();
            assert_eq!(engine.companion().unwrap().ring_len, 0, "frame {f}: the companion waits");
        }
        // Once a face adapted its model, the same view seeds the companion's rays.
        let mut models = engine.skin_models().to_vec();
        let face = FaceBox { x: 8.0, y: 4.0, width: 16.0, height: 16.0, score: 9.0 };
        assert!(models[1].adapt(&textured_view(0, 1), 32, 24, &[face]));
        engine.set_skin_models(&models).unwrap();
        let views = [textured_view(3, 1), warm_view.clone(), textured_view(7, 1)];
        let views: Vec<&[u8]> = views.iter().map(Vec::as_slice).collect();
        engine.push_frame(&views).unwrap();
        assert_eq!(engine.companion().unwrap().ring_len, 1, "the companion runs once its model is adapted");
    }

    #[test]
    fn the_companion_estimates_the_same_frame_on_the_images_it_is_lent() {
        let mut engine = engine_with_a_companion();
        for f in 0..4 {
            let views = [textured_view(f, 1), textured_view(f + 2, 1), textured_view(f + 4, 1)];
            let views: Vec<&[u8]> = views.iter().map(Vec::as_slice).collect();
            let estimated = engine.push_frame(&views).unwrap().is_some();
            let companion = engine.companion().unwrap();
            assert_eq!(companion.frames_pushed, engine.frames_pushed, "frame {f}");
            if estimated {
                assert_eq!(companion.stats().frame, engine.stats().frame, "frame {f}");
            }
            // Lent for the estimate and taken back: one set of images for both.
            assert!(companion.ring.iter().all(Vec::is_empty) && companion.skin_maps.iter().all(Vec::is_empty));
        }
        // A frame without the companion's reference view starts it afresh; the main goes on.
        let views = [textured_view(5, 1), vec![0; 32 * 24 * 3], textured_view(9, 1)];
        let views: Vec<&[u8]> = views.iter().map(Vec::as_slice).collect();
        assert!(engine.push_frame_partial(&views, 0b010).unwrap().is_some());
        assert_eq!(engine.companion().unwrap().ring_len, 0);
    }
}
