//! A small ray tracer for the synthetic signer: exact images, object masks and truth.

use handflow_protocol::{Camera, Distortion, Fisheye, Rig};
use nalgebra::{Matrix3, Point3, Rotation3, Vector3};
use rayon::prelude::*;

use super::scene::{SceneSpec, FOREARM_M, OBJECTS};

/// Object ids written into masks.
pub mod ids {
    /// Background wall.
    pub const BACKGROUND: u8 = 0;
    /// Head (face in front).
    pub const HEAD: u8 = 1;
    /// The signer's left hand.
    pub const LEFT_HAND: u8 = 2;
    /// The signer's right hand.
    pub const RIGHT_HAND: u8 = 3;
    /// Torso.
    pub const TORSO: u8 = 4;
    /// Arms.
    pub const ARMS: u8 = 5;
    /// The hair on the head (part of the head for visibility, not skin-coloured).
    pub const HAIR: u8 = 6;
    /// Bare forearms below short sleeves: skin-coloured like the hands, not tracked.
    pub const FOREARMS: u8 = 7;
}

/// The face photograph mapped on the front of the head (see assets/ATTRIBUTION.md).
const FACE_PNG: &[u8] = include_bytes!("../../assets/face.png");

/// The chest point the cameras look at.
const CHEST: [f64; 3] = [0.0, 1.3, 0.0];
/// The background wall's plane, z = this.
const WALL_Z: f64 = -0.7;
/// The shoulders (the signer's left, +X, first).
const SHOULDERS: [V3; 2] = [[0.19, 1.4, 0.0], [-0.19, 1.4, 0.0]];
/// From a hand's centre to its wrist, where the forearm begins, metres.
const WRIST_M: f64 = 0.06;
/// Upper arm, shoulder to elbow, metres.
const UPPER_ARM_M: f64 = 0.29;

/// The cluttered room's furniture, all background: boxes of wood near skin in colour.
const FURNITURE: [Furniture; 2] = [
    // A low sideboard behind the signer's right and middle, planks running along X.
    Furniture { min: [-1.1, 0.0, WALL_Z], max: [0.3, 0.8, -0.32], albedo: [192.0, 140.0, 100.0], along: 0 },
    // A tall cabinet behind the signer's left: in the front camera the left hand passes in
    // front of its edge, in the camera on the signer's right the head and left hand do.
    // Planks upright.
    Furniture { min: [0.34, 0.0, WALL_Z], max: [0.9, 1.62, -0.36], albedo: [204.0, 158.0, 122.0], along: 1 },
];
/// The cluttered room's plank floor (y = 0, planks running along Z).
const FLOOR_ALBEDO: [f64; 3] = [168.0, 112.0, 74.0];

/// A box of furniture, axis-aligned, metres.
struct Furniture {
    min: V3,
    max: V3,
    albedo: [f64; 3],
    /// The axis the planks' grain runs along.
    along: usize,
}

type V3 = [f64; 3];

#[derive(Clone, Copy)]
enum Shape {
    Ellipsoid { centre: V3, radii: V3 },
    Capsule { a: V3, b: V3, radius: f64 },
}

#[derive(Clone, Copy)]
struct Object {
    id: u8,
    shape: Shape,
    /// Texture origin: textures move with the object.
    anchor: V3,
    /// Screen bounding box per camera: (x0, y0, x1, y1), pixels.
    bounds: [(f64, f64, f64, f64); 8],
}

/// Renders frames of a [`SceneSpec`].
pub struct Renderer {
    spec: SceneSpec,
    rig: Rig,
    /// Per camera, the world direction of each pixel's ray.
    rays: Vec<Vec<V3>>,
    face: image::RgbImage,
}

/// One object's truth at one frame.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ObjectTruth {
    /// Position, metres.
    pub pos: [f64; 3],
    /// Velocity, metres per second.
    pub vel: [f64; 3],
    /// Per camera (rig order): projection in pixels, or null behind the camera.
    pub pixel: Vec<Option<[f64; 2]>>,
    /// Per camera: whether the object is what the camera sees at that pixel.
    pub visible: Vec<bool>,
}

impl Renderer {
    /// A renderer for `spec` (validated).
    pub fn new(spec: &SceneSpec) -> Result<Renderer, String> {
        spec.validate()?;
        let face = image::load_from_memory(FACE_PNG).map_err(|e| format!("built-in face texture: {e}"))?.into_rgb8();
        let rig = make_rig(spec)?;
        let rays = rig
            .cameras
            .iter()
            .map(|cam| {
                let (w, h) = (cam.width, cam.height);
                (0..h)
                    .flat_map(|y| (0..w).map(move |x| (x, y)))
                    .map(|(x, y)| {
                        let d = cam.back_project(&nalgebra::Point2::new(f64::from(x), f64::from(y))).direction;
                        [d.x, d.y, d.z]
                    })
                    .collect()
            })
            .collect();
        Ok(Renderer { spec: spec.clone(), rig, rays, face })
    }

    /// The rig of the scene's cameras.
    pub fn rig(&self) -> &Rig {
        &self.rig
    }

    /// The scene.
    pub fn spec(&self) -> &SceneSpec {
        &self.spec
    }

    /// Capture time of a frame, seconds.
    pub fn time(&self, frame: u32) -> f64 {
        f64::from(frame) / self.spec.fps
    }

    /// Bytes of one view (RGB8), the same for every camera (a camera mounted a quarter turn
    /// has width and height swapped, [`handflow_protocol::Camera::width`] says which).
    pub fn view_len(&self) -> usize {
        self.spec.width as usize * self.spec.height as usize * 3
    }

    /// Renders frame `frame` of every camera: `rgb` holds the views back to back (rig
    /// order), `masks` one object id per pixel, views back to back. Every view has
    /// [`Renderer::view_len`] bytes (a camera mounted a quarter turn has width and height
    /// swapped). With motion blur the colours average the shutter's sub-frame renders; the
    /// masks are the middle one's, at the frame's time, as the truth is.
    pub fn render_into(&self, frame: u32, rgb_all: &mut [u8], masks: &mut [u8]) {
        let rgb = &mut *rgb_all;
        let scenes: Vec<Vec<Object>> = self.exposure_times(frame).into_iter().map(|t| self.objects_at(t)).collect();
        let middle = scenes.len() / 2;
        let light = normalise([0.3, 0.6, 1.0]);
        // Every camera's rows, back to back: one task each.
        let mut rows = Vec::new();
        let (mut rgb_rest, mut mask_rest) = (rgb, masks);
        for (cam, camera) in self.rig.cameras.iter().enumerate() {
            let (w, h) = (camera.width as usize, camera.height as usize);
            let (view, rest) = std::mem::take(&mut rgb_rest).split_at_mut(w * h * 3);
            rgb_rest = rest;
            let (mask, rest) = std::mem::take(&mut mask_rest).split_at_mut(w * h);
            mask_rest = rest;
            rows.extend(
                view.chunks_mut(w * 3).zip(mask.chunks_mut(w)).enumerate().map(|(y, (row, m))| (cam, y, row, m)),
            );
        }
        rows.into_par_iter().for_each(|(cam, y, row, mask_row)| {
            let camera = &self.rig.cameras[cam];
            let w = camera.width as usize;
            let origin = camera.centre();
            let origin = [origin.x, origin.y, origin.z];
            let gain = self.spec.cameras.gain.get(cam).copied().unwrap_or(1.0);
            let offset = self.spec.cameras.offset.get(cam).copied().unwrap_or(0.0);
            let cast = self.spec.cameras.colour_cast.get(cam).copied().unwrap_or([1.0; 3]);
            for x in 0..w {
                let dir = self.rays[cam][y * w + x];
                let shade = |objects: &[Object]| self.shade(origin, dir, objects, cam, x as f64, y as f64, light);
                let (id, colour) = if scenes.len() == 1 {
                    shade(&scenes[0])
                } else {
                    let mut sum = [0.0; 3];
                    let mut id = ids::BACKGROUND;
                    for (i, objects) in scenes.iter().enumerate() {
                        let (seen, colour) = shade(objects);
                        sum = add(sum, colour);
                        if i == middle {
                            id = seen;
                        }
                    }
                    (id, scale(sum, 1.0 / scenes.len() as f64))
                };
                mask_row[x] = id;
                for c in 0..3 {
                    let n = noise(self.spec.seed, frame, cam as u32, (y * w + x) as u32, c as u32) * self.spec.noise;
                    row[x * 3 + c] = (colour[c] * gain * cast[c] + offset + n).round().clamp(0.0, 255.0) as u8;
                }
            }
        });
        if self.spec.jpeg_quality > 0 {
            let mut offset = 0;
            for camera in &self.rig.cameras {
                let len = camera.width as usize * camera.height as usize * 3;
                Self::through_jpeg(
                    &mut rgb_all[offset..offset + len],
                    camera.width,
                    camera.height,
                    self.spec.jpeg_quality,
                );
                offset += len;
            }
        }
    }

    /// Replaces an RGB8 view by what a JPEG of it at `quality` decodes to. Encoding an image
    /// this renderer made cannot fail (the sizes match the buffer); should it, the view stays
    /// lossless rather than the frame being lost.
    fn through_jpeg(view: &mut [u8], width: u32, height: u32, quality: u8) {
        let mut bytes = Vec::new();
        let encoder = image::codecs::jpeg::JpegEncoder::new_with_quality(&mut bytes, quality);
        if image::ImageEncoder::write_image(encoder, view, width, height, image::ExtendedColorType::Rgb8).is_err() {
            return;
        }
        if let Ok(decoded) = image::load_from_memory_with_format(&bytes, image::ImageFormat::Jpeg) {
            let decoded = decoded.into_rgb8();
            if decoded.as_raw().len() == view.len() {
                view.copy_from_slice(decoded.as_raw());
            }
        }
    }

    /// The times a frame's exposure samples, seconds: the frame's time alone, or with motion
    /// blur `motion_blur_samples` times spread evenly over the open shutter centred on it.
    fn exposure_times(&self, frame: u32) -> Vec<f64> {
        let t = self.time(frame);
        let n = self.spec.motion_blur_samples;
        if self.spec.motion_blur <= 0.0 || n < 2 {
            return vec![t];
        }
        let open = self.spec.motion_blur / self.spec.fps;
        (0..n).map(|i| t + open * (f64::from(i) / f64::from(n - 1) - 0.5)).collect()
    }

    /// Truth of every object at `frame`, given that frame's masks (as rendered).
    pub fn truth(&self, frame: u32, masks: &[u8]) -> Vec<(&'static str, ObjectTruth)> {
        let states = self.spec.object_states(self.time(frame));
        let object_ids = [ids::HEAD, ids::LEFT_HAND, ids::RIGHT_HAND];
        OBJECTS
            .iter()
            .zip(states)
            .zip(object_ids)
            .map(|((name, (pos, vel)), id)| {
                let mut pixel = Vec::new();
                let mut visible = Vec::new();
                let mut view_start = 0;
                for cam in &self.rig.cameras {
                    let (w, h) = (cam.width as usize, cam.height as usize);
                    let p = cam.project(&Point3::new(pos[0], pos[1], pos[2]));
                    pixel.push(p.map(|p| [p.x, p.y]));
                    let seen = p.is_some_and(|p| {
                        let (x, y) = (p.x.round(), p.y.round());
                        x >= 0.0 && y >= 0.0 && (x as usize) < w && (y as usize) < h && {
                            let seen = masks[view_start + y as usize * w + x as usize];
                            seen == id || (id == ids::HEAD && seen == ids::HAIR)
                        }
                    });
                    visible.push(seen);
                    view_start += w * h;
                }
                (*name, ObjectTruth { pos, vel, pixel, visible })
            })
            .collect()
    }

    /// The scene's objects at time `t`, with their screen bounds per camera.
    fn objects_at(&self, t: f64) -> Vec<Object> {
        let [(head, _), (left, _), (right, _)] = self.spec.object_states(t);
        let mut objects = vec![
            (ids::HEAD, Shape::Ellipsoid { centre: head, radii: [0.075, 0.1, 0.085] }, head),
            (ids::LEFT_HAND, Shape::Ellipsoid { centre: left, radii: [0.045, 0.07, 0.025] }, left),
            (ids::RIGHT_HAND, Shape::Ellipsoid { centre: right, radii: [0.045, 0.07, 0.025] }, right),
            (ids::TORSO, Shape::Ellipsoid { centre: [0.0, 1.15, -0.03], radii: [0.2, 0.32, 0.11] }, [0.0, 1.15, -0.03]),
        ];
        for (hand, shoulder) in [left, right].into_iter().zip(SHOULDERS) {
            let bare = self.spec.bare_forearm_m;
            if bare <= 0.0 {
                // Long sleeves: one straight clothed arm from the shoulder to the wrist.
                objects.push((
                    ids::ARMS,
                    Shape::Capsule { a: shoulder, b: towards(hand, shoulder, WRIST_M), radius: 0.04 },
                    shoulder,
                ));
                continue;
            }
            // Short sleeves: the arm bends at the elbow; the sleeve covers the upper arm and
            // what of the forearm is not bare, skin runs from the wrist up the rest.
            let elbow = elbow(shoulder, hand);
            let wrist = towards(hand, elbow, WRIST_M);
            let cuff = towards(hand, elbow, WRIST_M + bare);
            objects.push((ids::ARMS, Shape::Capsule { a: shoulder, b: elbow, radius: 0.04 }, shoulder));
            if bare < FOREARM_M {
                objects.push((ids::ARMS, Shape::Capsule { a: elbow, b: cuff, radius: 0.035 }, shoulder));
            }
            objects.push((ids::FOREARMS, Shape::Capsule { a: wrist, b: cuff, radius: 0.03 }, wrist));
        }
        let mut objects = objects
            .into_iter()
            .map(|(id, shape, anchor)| Object { id, shape, anchor, bounds: [(0.0, 0.0, -1.0, -1.0); 8] })
            .collect::<Vec<_>>();
        for object in &mut objects {
            let (centre, radius) = match object.shape {
                Shape::Ellipsoid { centre, radii } => (centre, radii[0].max(radii[1]).max(radii[2])),
                Shape::Capsule { a, b, radius } => {
                    let mid = std::array::from_fn(|k| 0.5 * (a[k] + b[k]));
                    (mid, 0.5 * length(sub(b, a)) + radius)
                }
            };
            for (c, cam) in self.rig.cameras.iter().enumerate() {
                let pc = cam.world_to_camera(&Point3::new(centre[0], centre[1], centre[2]));
                if pc.z - radius <= 0.01 {
                    // Too close to bound on screen: test every pixel.
                    object.bounds[c] = (f64::MIN, f64::MIN, f64::MAX, f64::MAX);
                    continue;
                }
                let f = cam.matrix[(0, 0)];
                let r_px = f * radius / (pc.z - radius) + 2.0;
                let u = f * pc.x / pc.z + cam.matrix[(0, 2)];
                let v = cam.matrix[(1, 1)] * pc.y / pc.z + cam.matrix[(1, 2)];
                object.bounds[c] = (u - r_px, v - r_px, u + r_px, v + r_px);
            }
        }
        objects
    }

    #[allow(clippy::too_many_arguments)]
    fn shade(&self, origin: V3, dir: V3, objects: &[Object], cam: usize, x: f64, y: f64, light: V3) -> (u8, [f64; 3]) {
        let mut nearest: Option<(f64, &Object)> = None;
        for object in objects {
            let (x0, y0, x1, y1) = object.bounds[cam];
            if x < x0 || x > x1 || y < y0 || y > y1 {
                continue;
            }
            if let Some(t) = intersect(&object.shape, origin, dir) {
                if nearest.is_none_or(|(best, _)| t < best) {
                    nearest = Some((t, object));
                }
            }
        }
        if self.spec.clutter {
            if let Some((t, colour)) = furniture(origin, dir, light) {
                if nearest.is_none_or(|(best, _)| t < best) {
                    return (ids::BACKGROUND, colour);
                }
            }
        }
        match nearest {
            Some((t, object)) => {
                let p = add(origin, scale(dir, t));
                let n = normal(&object.shape, p);
                let shade = 0.45 + 0.55 * dot(n, light).max(0.0);
                let (id, colour) = self.albedo(object, p, n);
                (id, scale(colour, shade))
            }
            None => {
                // The wall behind the signer; rays that never reach it see a dim grey.
                if dir[2] >= -1e-6 {
                    return (ids::BACKGROUND, [60.0; 3]);
                }
                let t = (WALL_Z - origin[2]) / dir[2];
                let p = add(origin, scale(dir, t));
                (ids::BACKGROUND, scale(wall(p, self.spec.seed), 0.9))
            }
        }
    }

    /// Surface colour: face photograph on the front of the head, textured skin, cloth.
    fn albedo(&self, object: &Object, p: V3, n: V3) -> (u8, [f64; 3]) {
        let local = sub(p, object.anchor);
        let skin = self.spec.skin_tone;
        let grain =
            |scale_m: f64, salt: u64| value_noise(local[0] / scale_m, local[1] / scale_m, local[2] / scale_m, salt);
        match object.id {
            ids::HEAD => {
                if let Shape::Ellipsoid { radii, .. } = object.shape {
                    if n[2] > 0.15 {
                        // Orthographic along the face's normal (+Z) over the front of the head.
                        let u = 0.5 + local[0] / (2.0 * radii[0] * 0.75);
                        let v = 0.5 - (local[1] + 0.005) / (2.0 * radii[1] * 0.78);
                        if (0.0..1.0).contains(&u) && (0.0..1.0).contains(&v) {
                            return (ids::HEAD, self.face_texel(u, v));
                        }
                    }
                }
                if n[1] > 0.35 || n[2] < -0.2 || local[1] > 0.045 {
                    let g = 0.8 + 0.4 * grain(0.01, 11);
                    return (ids::HAIR, [95.0 * g, 65.0 * g, 40.0 * g]);
                }
                (ids::HEAD, skin.map(|c| c * (0.9 + 0.2 * grain(0.008, 5))))
            }
            ids::LEFT_HAND | ids::RIGHT_HAND | ids::FOREARMS => {
                let g = 0.82 + 0.36 * grain(0.006, u64::from(object.id));
                (object.id, skin.map(|c| c * g))
            }
            _ => {
                let stripes = 0.85 + 0.15 * ((local[1] / 0.03).sin() * (local[0] / 0.05).cos());
                let g = stripes * (0.8 + 0.4 * grain(0.015, 21));
                (object.id, self.spec.clothing.map(|c| c * g))
            }
        }
    }

    fn face_texel(&self, u: f64, v: f64) -> [f64; 3] {
        // Bilinear, so the texture is smooth at every distance.
        let (w, h) = (f64::from(self.face.width()), f64::from(self.face.height()));
        let x = (u * w - 0.5).clamp(0.0, w - 1.0);
        let y = (v * h - 0.5).clamp(0.0, h - 1.0);
        let (x0, y0) = (x.floor() as u32, y.floor() as u32);
        let (x1, y1) = ((x0 + 1).min(self.face.width() - 1), (y0 + 1).min(self.face.height() - 1));
        let (fx, fy) = (x - f64::from(x0), y - f64::from(y0));
        let px = |x: u32, y: u32| self.face.get_pixel(x, y).0.map(f64::from);
        let (a, b, c, d) = (px(x0, y0), px(x1, y0), px(x0, y1), px(x1, y1));
        std::array::from_fn(|k| {
            let top = a[k] + (b[k] - a[k]) * fx;
            let bottom = c[k] + (d[k] - c[k]) * fx;
            top + (bottom - top) * fy
        })
    }
}

/// Cameras on the arc, looking at the chest point, with OpenCV conventions.
fn make_rig(spec: &SceneSpec) -> Result<Rig, String> {
    let arc = &spec.cameras;
    // The lens: `fov_deg` across the sensor's width, however the camera is mounted. A
    // fisheye lens images the edge's angle at radius f θd(θ) instead of f tan θ.
    let half = 0.5 * arc.fov_deg.to_radians();
    let fisheye = arc.fisheye.map(|[k1, k2, k3, k4]| Fisheye { k1, k2, k3, k4 });
    let edge = match &fisheye {
        Some(lens) => lens.distort(nalgebra::Vector2::new(half.tan(), 0.0)).x,
        None => half.tan(),
    };
    let f = 0.5 * f64::from(spec.width) / edge;
    let target = Vector3::from(CHEST);
    let cameras = arc
        .angles_deg
        .iter()
        .enumerate()
        .map(|(i, angle)| {
            let a = angle.to_radians();
            let pos = target + Vector3::new(arc.radius * a.sin(), arc.height, arc.radius * a.cos());
            let z = (target - pos).normalize();
            let x = z.cross(&Vector3::y()).normalize();
            let y = z.cross(&x);
            // Mounted turned `turns` quarter turns clockwise (seen from behind it), the camera
            // shows the scene turned anticlockwise, and its frames need as many clockwise
            // quarter turns to be upright: the world's up, -y of the upright camera, is raw -x
            // after one turn, +y after two, +x after three (`Camera::image_up`).
            let turns = arc.mount_quarter_turns.get(i).copied().unwrap_or(0);
            let (x, y) = match turns {
                0 => (x, y),
                1 => (y, -x),
                2 => (-x, -y),
                _ => (-y, x),
            };
            let (w, h) = if turns % 2 == 1 { (spec.height, spec.width) } else { (spec.width, spec.height) };
            let k = Matrix3::new(f, 0.0, f64::from(w - 1) / 2.0, 0.0, f, f64::from(h - 1) / 2.0, 0.0, 0.0, 1.0);
            let r =
                Rotation3::from_matrix_unchecked(Matrix3::from_rows(&[x.transpose(), y.transpose(), z.transpose()]));
            let t = -(r * pos);
            Camera::new(format!("cam{i}"), w, h, k, Distortion::default(), r, t)
                .and_then(|camera| match fisheye {
                    Some(lens) => camera.with_fisheye(lens),
                    None => Ok(camera),
                })
                .map(|camera| camera.with_mount_quarter_turns(turns))
                .map_err(|e| e.to_string())
        })
        .collect::<Result<Vec<_>, _>>()?;
    Ok(Rig::new(cameras))
}

fn towards(hand: V3, shoulder: V3, back: f64) -> V3 {
    // The forearm ends a little before the hand's centre, at the wrist.
    let d = sub(shoulder, hand);
    let len = length(d).max(1e-9);
    add(hand, scale(d, back / len))
}

/// Where the elbow of the arm from `shoulder` to `hand` is: the two-bone arm (upper arm
/// [`UPPER_ARM_M`], elbow to hand centre [`WRIST_M`] + [`FOREARM_M`]) bent with the elbow
/// down, out to the arm's side and a little back, as a signer's elbows hang by the body.
fn elbow(shoulder: V3, hand: V3) -> V3 {
    let (upper, lower) = (UPPER_ARM_M, WRIST_M + FOREARM_M);
    let d = sub(hand, shoulder);
    let reach = length(d).clamp((upper - lower).abs() + 1e-3, upper + lower - 1e-3);
    let u = normalise(d);
    // Along the shoulder-hand line, then out from it.
    let along = (upper * upper - lower * lower + reach * reach) / (2.0 * reach);
    let out = (upper * upper - along * along).max(0.0).sqrt();
    let side = shoulder[0].signum();
    let pole = [0.35 * side, -1.0, -0.1];
    let mut bend = sub(pole, scale(u, dot(pole, u)));
    if length(bend) < 1e-6 {
        // The hand straight below the shoulder along the pole: bend outwards.
        bend = sub([side, 0.0, 0.0], scale(u, u[0] * side));
    }
    add(add(shoulder, scale(u, along)), scale(normalise(bend), out))
}

/// The nearest furniture of the cluttered room along a ray (the floor in front of the
/// wall and the boxes of [`FURNITURE`]): distance and shaded colour.
fn furniture(o: V3, d: V3, light: V3) -> Option<(f64, [f64; 3])> {
    // Distance, the axis of the face hit, the albedo and the axis the grain runs along.
    let mut nearest: Option<(f64, usize, &[f64; 3], usize)> = None;
    // The floor, y = 0, up to the wall; planks run along Z.
    if d[1] < -1e-9 {
        let t = -o[1] / d[1];
        if t > 1e-6 && o[2] + t * d[2] > WALL_Z {
            nearest = Some((t, 1, &FLOOR_ALBEDO, 2));
        }
    }
    for f in &FURNITURE {
        // Slabs: the entry distance and the axis entered through.
        let (mut t0, mut t1, mut axis) = (f64::MIN, f64::MAX, 0);
        for k in 0..3 {
            if d[k].abs() < 1e-12 {
                if o[k] < f.min[k] || o[k] > f.max[k] {
                    t0 = f64::MAX;
                }
                continue;
            }
            let (a, b) = ((f.min[k] - o[k]) / d[k], (f.max[k] - o[k]) / d[k]);
            let (near, far) = if a < b { (a, b) } else { (b, a) };
            if near > t0 {
                t0 = near;
                axis = k;
            }
            t1 = t1.min(far);
        }
        if t0 <= t1 && t0 > 1e-6 && nearest.is_none_or(|(best, ..)| t0 < best) {
            let along = if axis == f.along { (f.along + 1) % 3 } else { f.along };
            nearest = Some((t0, axis, &f.albedo, along));
        }
    }
    let (t, axis, albedo, along) = nearest?;
    let mut n = [0.0; 3];
    n[axis] = -d[axis].signum();
    let shade = 0.45 + 0.55 * dot(n, light).max(0.0);
    Some((t, scale(wood(add(o, scale(d, t)), albedo, along, 3 - axis - along), shade)))
}

/// Wood: planks 14 cm wide, each a little lighter or darker, with a wavy grain along them.
fn wood(p: V3, albedo: &[f64; 3], along: usize, across: usize) -> [f64; 3] {
    let plank = (p[across] / 0.14).floor();
    let tint = 0.9 + 0.2 * lattice(plank, 0.0, along as f64, 41);
    let wave = 4.0 * value_noise_2d(p[along] / 0.25, p[across] / 0.03, 43);
    let grain = 0.9 + 0.1 * (p[across] / 0.004 + wave).sin();
    let fine = 0.92 + 0.16 * value_noise_2d(p[along] / 0.02, p[across] / 0.005, 47);
    albedo.map(|c| c * tint * grain * fine)
}

fn intersect(shape: &Shape, o: V3, d: V3) -> Option<f64> {
    match *shape {
        Shape::Ellipsoid { centre, radii } => {
            let oc: V3 = std::array::from_fn(|k| (o[k] - centre[k]) / radii[k]);
            let dd: V3 = std::array::from_fn(|k| d[k] / radii[k]);
            let a = dot(dd, dd);
            let b = dot(oc, dd);
            let c = dot(oc, oc) - 1.0;
            let disc = b * b - a * c;
            if disc < 0.0 {
                return None;
            }
            let t = (-b - disc.sqrt()) / a;
            (t > 1e-6).then_some(t)
        }
        Shape::Capsule { a, b, radius } => {
            // Ray against a capsule (a cylinder capped by spheres), after Inigo Quilez.
            let ba = sub(b, a);
            let oa = sub(o, a);
            let baba = dot(ba, ba);
            let bard = dot(ba, d);
            let baoa = dot(ba, oa);
            let rdoa = dot(d, oa);
            let oaoa = dot(oa, oa);
            let qa = baba - bard * bard;
            let qb = baba * rdoa - baoa * bard;
            let qc = baba * oaoa - baoa * baoa - radius * radius * baba;
            let h = qb * qb - qa * qc;
            if h < 0.0 {
                return None;
            }
            let t = (-qb - h.sqrt()) / qa;
            let y = baoa + t * bard;
            if y > 0.0 && y < baba && t > 1e-6 {
                return Some(t);
            }
            let oc = if y <= 0.0 { oa } else { sub(o, b) };
            let b2 = dot(d, oc);
            let c2 = dot(oc, oc) - radius * radius;
            let h2 = b2 * b2 - c2;
            if h2 < 0.0 {
                return None;
            }
            let t = -b2 - h2.sqrt();
            (t > 1e-6).then_some(t)
        }
    }
}

fn normal(shape: &Shape, p: V3) -> V3 {
    match *shape {
        Shape::Ellipsoid { centre, radii } => {
            normalise(std::array::from_fn(|k| (p[k] - centre[k]) / (radii[k] * radii[k])))
        }
        Shape::Capsule { a, b, .. } => {
            let ba = sub(b, a);
            let h = (dot(sub(p, a), ba) / dot(ba, ba)).clamp(0.0, 1.0);
            normalise(sub(p, add(a, scale(ba, h))))
        }
    }
}

/// The wall: colourful blotches at two scales, so every patch has texture. Three 2D noise
/// fields mixed into the channels (the wall covers most pixels, so it is kept cheap).
fn wall(p: V3, seed: u64) -> [f64; 3] {
    let a = value_noise_2d(p[0] / 0.09, p[1] / 0.09, seed ^ 1);
    let b = value_noise_2d(p[0] / 0.09, p[1] / 0.09, seed ^ 3);
    let c = value_noise_2d(p[0] / 0.025, p[1] / 0.025, seed ^ 5);
    // An office-like palette of greys, greens and blues: richly textured, but not
    // skin-coloured (a wall of skin tones would defeat any colour-based method).
    [30.0 + 70.0 * a + 40.0 * c, 50.0 + 110.0 * b + 50.0 * c, 70.0 + 120.0 * (1.0 - a) + 40.0 * c]
}

/// Smooth 2D value noise in [0, 1] on a unit lattice.
fn value_noise_2d(x: f64, y: f64, salt: u64) -> f64 {
    let (ix, iy) = (x.floor(), y.floor());
    let s = |t: f64| t * t * (3.0 - 2.0 * t);
    let (sx, sy) = (s(x - ix), s(y - iy));
    let h = |dx: f64, dy: f64| lattice(ix + dx, iy + dy, 0.0, salt);
    let top = h(0.0, 0.0) + (h(1.0, 0.0) - h(0.0, 0.0)) * sx;
    let bottom = h(0.0, 1.0) + (h(1.0, 1.0) - h(0.0, 1.0)) * sx;
    top + (bottom - top) * sy
}

/// Smooth value noise in [0, 1] on a unit lattice.
fn value_noise(x: f64, y: f64, z: f64, salt: u64) -> f64 {
    let (ix, iy, iz) = (x.floor(), y.floor(), z.floor());
    let (fx, fy, fz) = (x - ix, y - iy, z - iz);
    let s = |t: f64| t * t * (3.0 - 2.0 * t);
    let (sx, sy, sz) = (s(fx), s(fy), s(fz));
    let h = |dx: f64, dy: f64, dz: f64| lattice(ix + dx, iy + dy, iz + dz, salt);
    let lerp = |a: f64, b: f64, t: f64| a + (b - a) * t;
    let z0 = lerp(lerp(h(0.0, 0.0, 0.0), h(1.0, 0.0, 0.0), sx), lerp(h(0.0, 1.0, 0.0), h(1.0, 1.0, 0.0), sx), sy);
    let z1 = lerp(lerp(h(0.0, 0.0, 1.0), h(1.0, 0.0, 1.0), sx), lerp(h(0.0, 1.0, 1.0), h(1.0, 1.0, 1.0), sx), sy);
    lerp(z0, z1, sz)
}

fn lattice(x: f64, y: f64, z: f64, salt: u64) -> f64 {
    let mut h = (x as i64 as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ (y as i64 as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F)
        ^ (z as i64 as u64).wrapping_mul(0x1656_67B1_9E37_79F9)
        ^ salt.wrapping_mul(0xD6E8_FEB8_6659_FD93);
    h = (h ^ (h >> 31)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    h ^= h >> 29;
    (h >> 11) as f64 / (1u64 << 53) as f64
}

/// Zero-mean, unit-variance sensor noise for one sample, reproducible from its indices.
fn noise(seed: u64, frame: u32, cam: u32, pixel: u32, channel: u32) -> f64 {
    let key = seed ^ (u64::from(frame) << 40) ^ (u64::from(cam) << 34) ^ (u64::from(pixel) << 2) ^ u64::from(channel);
    let mut h = key.wrapping_mul(0x9E37_79B9_7F4A_7C15);
    h = (h ^ (h >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    h = (h ^ (h >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    h ^= h >> 31;
    let sum = (h & 0xFFFF) + ((h >> 16) & 0xFFFF) + ((h >> 32) & 0xFFFF) + (h >> 48);
    (sum as f64 - 131_070.0) * (3.0f64.sqrt() / 65_536.0)
}

fn add(a: V3, b: V3) -> V3 {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}
fn sub(a: V3, b: V3) -> V3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn scale(a: V3, s: f64) -> V3 {
    [a[0] * s, a[1] * s, a[2] * s]
}
fn dot(a: V3, b: V3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn length(a: V3) -> f64 {
    dot(a, a).sqrt()
}
fn normalise(a: V3) -> V3 {
    scale(a, 1.0 / length(a).max(1e-12))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn small(name: &str) -> SceneSpec {
        let mut spec = SceneSpec::preset(name).expect("preset");
        spec.width = 160;
        spec.height = 120;
        spec.frames = 5;
        spec
    }

    /// Every preset, and signer-3cam with each rendering option.
    fn scenes() -> Vec<(String, SceneSpec)> {
        let mut scenes: Vec<(String, SceneSpec)> =
            super::super::scene::PRESETS.iter().map(|name| (name.to_string(), small(name))).collect();
        let mut blurred = small("signer-3cam");
        blurred.motion_blur = 1.0;
        scenes.push(("signer-3cam with motion blur".into(), blurred));
        for turns in [vec![1, 0, 3], vec![0, 1, 0], vec![2, 3, 0]] {
            let mut turned = small("signer-3cam");
            turned.cameras.mount_quarter_turns = turns.clone();
            scenes.push((format!("signer-3cam mounted {turns:?}"), turned));
        }
        scenes.push(("signer-3cam through fisheye lenses".into(), fisheye(small("signer-3cam"))));
        scenes
    }

    /// `spec` through wide fisheye lenses, moved closer (as `tests/scenes/options`' fisheye scene).
    fn fisheye(mut spec: SceneSpec) -> SceneSpec {
        spec.cameras.fisheye = Some([0.03, -0.01, 0.002, 0.0]);
        spec.cameras.fov_deg = 100.0;
        spec.cameras.radius = 1.1;
        spec
    }

    #[test]
    fn a_fisheye_lens_spans_the_field_across_the_width_and_the_rig_says_so() {
        let spec = fisheye(small("signer-3cam"));
        let r = Renderer::new(&spec).expect("renderer");
        for cam in &r.rig().cameras {
            assert_eq!(cam.fisheye.map(|lens| lens.as_array()), Some([0.03, -0.01, 0.002, 0.0]));
            // The ray through the right edge of the image (x = width - 1/2 from the centre
            // at (width - 1) / 2) is half the field from the optical axis.
            let edge = cam.back_project(&nalgebra::Point2::new(f64::from(cam.width) - 0.5, cam.matrix[(1, 2)]));
            let angle = edge.direction.dot(&cam.viewing_direction()).acos().to_degrees();
            assert!((angle - 50.0).abs() < 0.01, "{}: {angle} degrees at the edge", cam.name);
        }
        let mut bad = spec.clone();
        bad.cameras.fisheye = Some([0.03, f64::NAN, 0.0, 0.0]);
        let error = bad.validate().expect_err("a NaN coefficient");
        assert!(error.contains("cameras.fisheye"), "{error}");
    }

    /// Renders frame `frame`: every view's colours and masks, and the truth.
    fn render(r: &Renderer, frame: u32) -> (Vec<u8>, Vec<u8>, Vec<(&'static str, ObjectTruth)>) {
        let views = r.rig().cameras.len();
        let mut rgb = vec![0u8; r.view_len() * views];
        let mut masks = vec![0u8; r.view_len() / 3 * views];
        r.render_into(frame, &mut rgb, &mut masks);
        let truth = r.truth(frame, &masks);
        (rgb, masks, truth)
    }

    /// The mask id at a truth pixel of camera `c`, if it is in the image.
    fn mask_at(r: &Renderer, masks: &[u8], c: usize, px: [f64; 2]) -> Option<u8> {
        let cams = &r.rig().cameras;
        let start: usize = cams[..c].iter().map(|cam| (cam.width * cam.height) as usize).sum();
        let (w, h) = (cams[c].width as usize, cams[c].height as usize);
        let (x, y) = (px[0].round(), px[1].round());
        (x >= 0.0 && y >= 0.0 && (x as usize) < w && (y as usize) < h)
            .then(|| masks[start + y as usize * w + x as usize])
    }

    /// The rule of Kovac, Peer and Solina (2003) for skin under daylight, in RGB.
    fn skin_rule(px: &[u8]) -> bool {
        let (r, g, b) = (i32::from(px[0]), i32::from(px[1]), i32::from(px[2]));
        r > 95 && g > 40 && b > 20 && r.max(g).max(b) - r.min(g).min(b) > 15 && (r - g).abs() > 15 && r > g && r > b
    }

    #[test]
    fn truth_points_project_onto_pixels_of_their_object() {
        for (name, spec) in scenes() {
            let r = Renderer::new(&spec).expect("renderer");
            let object_ids = [ids::HEAD, ids::LEFT_HAND, ids::RIGHT_HAND];
            let views = spec.cameras.angles_deg.len();
            let mut rgb = vec![0u8; r.view_len() * views];
            let mut masks = vec![0u8; r.view_len() / 3 * views];
            let mut visible = 0;
            for frame in 0..spec.frames {
                r.render_into(frame, &mut rgb, &mut masks);
                for ((object, truth), id) in r.truth(frame, &masks).into_iter().zip(object_ids) {
                    for (c, seen) in truth.visible.iter().enumerate() {
                        let Some(px) = truth.pixel[c] else { continue };
                        let there = mask_at(&r, &masks, c, px);
                        let on_it = there == Some(id) || (id == ids::HEAD && there == Some(ids::HAIR));
                        assert_eq!(*seen, on_it, "{name}: {object} camera {c} frame {frame} sees {there:?}");
                        visible += usize::from(*seen);
                    }
                    assert!(truth.visible[1], "{name}: the front camera sees the {object} at frame {frame}");
                }
            }
            // The front camera sees head and both hands in every frame of every preset.
            assert!(visible >= 3 * spec.frames as usize, "{name}: {visible} visible object-views");
        }
    }

    #[test]
    fn the_front_camera_sees_the_face_photograph_and_skin_coloured_hands() {
        let spec = small("signer-3cam");
        let r = Renderer::new(&spec).expect("renderer");
        let mut rgb = vec![0u8; r.view_len() * 3];
        let mut masks = vec![0u8; r.view_len()];
        r.render_into(0, &mut rgb, &mut masks);
        let (w, h) = (160usize, 120usize);
        let front = w * h; // camera 1 of 3 is the front one
        let count = |id: u8| masks[front..2 * front].iter().filter(|&&m| m == id).count();
        assert!(count(ids::HEAD) > 100, "head pixels {}", count(ids::HEAD));
        assert!(count(ids::LEFT_HAND) > 20 && count(ids::RIGHT_HAND) > 20);
        assert!(count(ids::BACKGROUND) > w * h / 3);
        // Hand pixels are skin-coloured: red above blue.
        let hand: Vec<usize> = (0..front).filter(|&i| masks[front + i] == ids::LEFT_HAND).collect();
        let (mut red, mut blue) = (0.0, 0.0);
        for i in &hand {
            red += f64::from(rgb[3 * (front + i)]);
            blue += f64::from(rgb[3 * (front + i) + 2]);
        }
        assert!(red > blue * 1.2, "skin is reddish: {red} vs {blue}");
    }

    #[test]
    fn the_side_camera_loses_the_right_hand_in_occluded_side() {
        let mut spec = SceneSpec::preset("occluded-side").expect("preset");
        spec.width = 160;
        spec.height = 120;
        let r = Renderer::new(&spec).expect("renderer");
        let mut rgb = vec![0u8; r.view_len() * 3];
        let mut masks = vec![0u8; r.view_len()];
        let mut hidden_run = 0;
        let mut longest = 0;
        for frame in 0..spec.frames {
            r.render_into(frame, &mut rgb, &mut masks);
            let truth = r.truth(frame, &masks);
            let right = &truth[2].1;
            if !right.visible[2] {
                hidden_run += 1;
                longest = longest.max(hidden_run);
            } else {
                hidden_run = 0;
            }
            assert!(right.visible[1], "the front camera keeps the right hand, frame {frame}");
        }
        assert!(longest >= 10, "hidden from the side camera for {longest} consecutive frames");
    }

    #[test]
    fn short_sleeves_show_skin_coloured_forearms_while_the_truth_stays_on_the_hands() {
        let mut spec = SceneSpec::preset("signer-short-sleeves").expect("preset");
        (spec.width, spec.height) = (320, 240);
        let sleeved = Renderer::new(&SceneSpec { bare_forearm_m: 0.0, ..spec.clone() }).expect("renderer");
        let r = Renderer::new(&spec).expect("renderer");
        let (w, pixels) = (320usize, 320 * 240);
        for frame in [0, 20, 45, 80, 130] {
            let (rgb, masks, truth) = render(&r, frame);
            let (_, long_masks, long_truth) = render(&sleeved, frame);
            // The truth of each hand is its centre, with sleeves long or short.
            assert_eq!(
                truth.iter().map(|(_, t)| t.pos).collect::<Vec<_>>(),
                long_truth.iter().map(|(_, t)| t.pos).collect::<Vec<_>>()
            );
            assert!(!long_masks.contains(&ids::FOREARMS));
            let front = &masks[pixels..2 * pixels];
            let front_rgb = &rgb[3 * pixels..6 * pixels];
            for ((object, t), id) in truth.iter().zip([ids::HEAD, ids::LEFT_HAND, ids::RIGHT_HAND]).skip(1) {
                let at = mask_at(&r, &masks, 1, t.pixel[1].expect("projects"));
                assert_eq!(at, Some(id), "frame {frame}: the {object}'s truth projects onto the hand, not the forearm");
            }
            // Forearm pixels, both arms together: many, skin-coloured as the hands are, and
            // touching the hands (the skin runs on from the hand up the arm).
            let mean = |id: u8| {
                let px: Vec<&[u8]> =
                    front_rgb.chunks_exact(3).zip(front).filter(|(_, &m)| m == id).map(|(p, _)| p).collect();
                let sum = px
                    .iter()
                    .fold([0.0; 3], |s, p| [s[0] + f64::from(p[0]), s[1] + f64::from(p[1]), s[2] + f64::from(p[2])]);
                (px.len(), sum.map(|c| c / px.len().max(1) as f64), px.iter().filter(|p| skin_rule(p)).count())
            };
            let (n, forearm, skin) = mean(ids::FOREARMS);
            let (_, hand, _) = mean(ids::LEFT_HAND);
            assert!(n > 150, "frame {frame}: {n} forearm pixels in the front camera");
            // The rest are its shaded underside, too dark for the rule (a round forearm is
            // lit less evenly than a flat hand facing the light).
            assert!(skin as f64 > 0.7 * n as f64, "frame {frame}: {skin} of {n} forearm pixels skin-coloured");
            let chroma = |c: [f64; 3]| [c[0] / (c[0] + c[1] + c[2]), c[1] / (c[0] + c[1] + c[2])];
            let (f, h) = (chroma(forearm), chroma(hand));
            assert!(
                (f[0] - h[0]).abs() < 0.015 && (f[1] - h[1]).abs() < 0.015,
                "frame {frame}: forearm {forearm:?} and hand {hand:?} differ in colour"
            );
            let touching = (0..pixels).filter(|&i| front[i] == ids::FOREARMS).any(|i| {
                [i.wrapping_sub(1), i + 1, i.wrapping_sub(w), i + w]
                    .iter()
                    .any(|&j| j < pixels && (front[j] == ids::LEFT_HAND || front[j] == ids::RIGHT_HAND))
            });
            assert!(touching, "frame {frame}: a forearm joins its hand");
        }
    }

    #[test]
    fn the_elbow_is_a_forearm_from_the_hand_below_and_beside_the_shoulder() {
        let spec = SceneSpec::preset("signer-short-sleeves").expect("preset");
        for frame in (0..spec.frames).step_by(7) {
            let [_, (left, _), (right, _)] = spec.object_states(f64::from(frame) / spec.fps);
            for (hand, shoulder) in [left, right].into_iter().zip(SHOULDERS) {
                let e = elbow(shoulder, hand);
                assert!((length(sub(e, shoulder)) - UPPER_ARM_M).abs() < 1e-9);
                assert!((length(sub(e, hand)) - (WRIST_M + FOREARM_M)).abs() < 1e-9);
                assert!(e[1] < shoulder[1] - 0.2, "frame {frame}: elbow {e:?} hangs low");
                assert!(e[2] < hand[2] - 0.15, "frame {frame}: elbow {e:?} behind the hand {hand:?}");
                assert!(e[0] * shoulder[0] > 0.0 && e[0].abs() > 0.2, "frame {frame}: elbow {e:?} beside the body");
            }
        }
    }

    #[test]
    fn the_cluttered_room_has_skin_coloured_background_and_the_signer_unchanged() {
        let room = Renderer::new(&small("cluttered-room")).expect("renderer");
        let plain = Renderer::new(&small("signer-3cam")).expect("renderer");
        let pixels = 160 * 120;
        for frame in 0..5 {
            let (rgb, masks, truth) = render(&room, frame);
            let (plain_rgb, plain_masks, plain_truth) = render(&plain, frame);
            // The furniture is background: the same masks and truth as without it.
            assert_eq!(masks, plain_masks, "frame {frame}");
            assert_eq!(truth, plain_truth, "frame {frame}");
            let skin_background = |rgb: &[u8], c: usize| {
                let view = &rgb[3 * c * pixels..3 * (c + 1) * pixels];
                let mask = &masks[c * pixels..(c + 1) * pixels];
                let background = mask.iter().filter(|&&m| m == ids::BACKGROUND).count();
                let skin =
                    view.chunks_exact(3).zip(mask).filter(|(p, &m)| m == ids::BACKGROUND && skin_rule(p)).count();
                skin as f64 / background as f64
            };
            for c in 0..3 {
                let (cluttered, bare) = (skin_background(&rgb, c), skin_background(&plain_rgb, c));
                assert!(cluttered > 0.12, "frame {frame} camera {c}: {cluttered:.3} of the background skin-coloured");
                assert!(bare < 0.01, "frame {frame} camera {c}: the plain wall {bare:.3} skin-coloured");
            }
            // The rule takes the hands for skin, and the wood is near their colour, not it.
            let front = &rgb[3 * pixels..6 * pixels];
            let hand: Vec<&[u8]> = front
                .chunks_exact(3)
                .zip(&masks[pixels..2 * pixels])
                .filter(|(_, &m)| m == ids::LEFT_HAND)
                .map(|(p, _)| p)
                .collect();
            assert!(hand.iter().filter(|p| skin_rule(p)).count() as f64 > 0.9 * hand.len() as f64);
        }
        for f in FURNITURE.iter().map(|f| f.albedo).chain([FLOOR_ALBEDO]) {
            let skin = room.spec().skin_tone;
            let diff = (0..3).map(|c| (f[c] - skin[c]).abs()).fold(0.0, f64::max);
            assert!(diff > 15.0 && diff < 100.0, "wood {f:?} against skin {skin:?}");
        }
    }

    #[test]
    fn a_camera_mounted_a_quarter_turn_sees_the_upright_view_turned_with_its_truth_on_its_objects() {
        let mut upright = small("signer-3cam");
        upright.noise = 0.0;
        let reference = Renderer::new(&upright).expect("renderer");
        let (w, h) = (160usize, 120usize);
        for turns in [1u8, 2, 3] {
            let mut spec = upright.clone();
            spec.cameras.mount_quarter_turns = vec![0, turns, 0];
            let r = Renderer::new(&spec).expect("renderer");
            let cam = &r.rig().cameras[1];
            let (rw, rh) = (cam.width as usize, cam.height as usize);
            assert_eq!((rw, rh), if turns % 2 == 1 { (h, w) } else { (w, h) });
            assert_eq!(cam.mount_quarter_turns, turns);
            // Turned upright by its mount, the camera's up is the world's.
            assert!(cam.image_up().dot(&Vector3::y()) > 0.99, "turns {turns}: up {:?}", cam.image_up());
            assert_eq!(r.rig().world_up().direction, Vector3::y());
            // Raw pixel (x, y) of the turned camera is this pixel of the upright one.
            let upright_pixel = |x: usize, y: usize| match turns {
                1 => (w - 1 - y, x),
                2 => (w - 1 - x, h - 1 - y),
                _ => (y, h - 1 - x),
            };
            for frame in [0, 3] {
                let (rgb, masks, truth) = render(&r, frame);
                let (up_rgb, up_masks, up_truth) = render(&reference, frame);
                let (mut mask_differs, mut colour_differs) = (0, 0);
                for y in 0..rh {
                    for x in 0..rw {
                        let (ux, uy) = upright_pixel(x, y);
                        let (i, j) = (w * h + y * rw + x, w * h + uy * w + ux);
                        mask_differs += usize::from(masks[i] != up_masks[j]);
                        colour_differs += usize::from((0..3).any(|c| rgb[3 * i + c].abs_diff(up_rgb[3 * j + c]) > 2));
                    }
                }
                // Only rays grazing an edge may round the other way.
                assert!(mask_differs <= w * h / 500, "turns {turns}: {mask_differs} mask pixels differ");
                assert!(colour_differs <= w * h / 200, "turns {turns}: {colour_differs} colours differ");
                for ((object, t), (_, u)) in truth.iter().zip(&up_truth) {
                    assert_eq!((t.pos, t.visible[1]), (u.pos, u.visible[1]), "{object}");
                    assert!(t.visible[1], "turns {turns}: the turned front camera sees the {object}");
                    let [px, py] = t.pixel[1].expect("projects");
                    let [ux, uy] = u.pixel[1].expect("projects");
                    let expected = match turns {
                        1 => (uy, (w - 1) as f64 - ux),
                        2 => ((w - 1) as f64 - ux, (h - 1) as f64 - uy),
                        _ => ((h - 1) as f64 - uy, ux),
                    };
                    assert!((px - expected.0).abs() < 1e-6 && (py - expected.1).abs() < 1e-6, "{object}: {px}, {py}");
                }
            }
        }
    }

    #[test]
    fn motion_blur_smears_moving_hands_and_keeps_the_masks_and_truth_of_the_frame_time() {
        let mut sharp = small("signer-3cam");
        sharp.noise = 0.0;
        let blurred_spec = SceneSpec { motion_blur: 1.0, ..sharp.clone() };
        let (r, blurred) = (Renderer::new(&sharp).expect("renderer"), Renderer::new(&blurred_spec).expect("renderer"));
        assert_eq!(blurred.exposure_times(3).len(), 5);
        assert!(
            (blurred.exposure_times(3)[2] - blurred.time(3)).abs() < 1e-12,
            "the middle sample is the frame's time"
        );
        let (w, pixels) = (160usize, 160 * 120);
        for frame in [0, 2, 4] {
            let (rgb, masks, truth) = render(&r, frame);
            let (blur_rgb, blur_masks, blur_truth) = render(&blurred, frame);
            assert_eq!(masks, blur_masks);
            assert_eq!(truth, blur_truth);
            // The wall above the head does not move; the hands' edges do.
            assert_eq!(rgb[..3 * 5 * w], blur_rgb[..3 * 5 * w], "frame {frame}: the top rows are still wall");
            let smeared = (0..3 * pixels)
                .filter(|&i| {
                    let m = masks[i];
                    (m == ids::LEFT_HAND || m == ids::RIGHT_HAND)
                        && (0..3).any(|c| rgb[3 * i + c].abs_diff(blur_rgb[3 * i + c]) > 8)
                })
                .count();
            assert!(smeared > 10, "frame {frame}: {smeared} hand pixels smeared");
        }
    }

    #[test]
    fn jpeg_compression_degrades_the_colours_a_little_and_keeps_masks_and_truth() {
        let lossless = small("signer-3cam");
        let mean_abs_diff = |quality: u8| {
            let spec = SceneSpec { jpeg_quality: quality, ..lossless.clone() };
            let (a, b) = (Renderer::new(&lossless).expect("renderer"), Renderer::new(&spec).expect("renderer"));
            let ((rgb, masks, truth), (jpeg, jpeg_masks, jpeg_truth)) = (render(&a, 2), render(&b, 2));
            assert_eq!((masks, truth), (jpeg_masks, jpeg_truth), "quality {quality}");
            assert_eq!(rgb.len(), jpeg.len());
            rgb.iter().zip(&jpeg).map(|(x, y)| f64::from(x.abs_diff(*y))).sum::<f64>() / rgb.len() as f64
        };
        let (good, poor) = (mean_abs_diff(90), mean_abs_diff(20));
        // Lossy but close: a few grey levels on average, more at a lower quality.
        assert!(good > 0.2 && good < 4.0, "quality 90: {good}");
        assert!(poor > good && poor < 12.0, "quality 20: {poor} against {good}");
    }

    #[test]
    fn six_frames_per_second_sample_the_same_motion_less_often() {
        let slow = Renderer::new(&small("signer-6fps")).expect("renderer");
        let fast = Renderer::new(&small("signer-3cam")).expect("renderer");
        assert_eq!(slow.spec().fps, 6.0);
        assert!((slow.time(1) - 1.0 / 6.0).abs() < 1e-12);
        let (_, _, slow_truth) = render(&slow, 1);
        let (_, _, fast_truth) = render(&fast, 5);
        for ((object, s), (_, f)) in slow_truth.iter().zip(&fast_truth) {
            assert_eq!(s.pos, f.pos, "{object}");
        }
    }
}
