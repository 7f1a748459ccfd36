//! A small ray tracer for the synthetic signer: exact images, object masks and truth.

use handflow_protocol::{Camera, Distortion, Rig};
use nalgebra::{Matrix3, Point3, Rotation3, Vector3};
use rayon::prelude::*;

use super::scene::{SceneSpec, OBJECTS};

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
}

/// The face photograph mapped on the front of the head (see assets/ATTRIBUTION.md).
const FACE_PNG: &[u8] = include_bytes!("../../assets/face.png");

/// The chest point the cameras look at.
const CHEST: [f64; 3] = [0.0, 1.3, 0.0];
/// The background wall's plane, z = this.
const WALL_Z: f64 = -0.7;

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

    /// Bytes of one view (RGB8).
    pub fn view_len(&self) -> usize {
        self.spec.width as usize * self.spec.height as usize * 3
    }

    /// Renders frame `frame` of every camera: `rgb` holds the views back to back (rig
    /// order), `masks` one object id per pixel, views back to back.
    pub fn render_into(&self, frame: u32, rgb: &mut [u8], masks: &mut [u8]) {
        let (w, h) = (self.spec.width as usize, self.spec.height as usize);
        let objects = self.objects(frame);
        let light = normalise([0.3, 0.6, 1.0]);
        rgb.par_chunks_mut(w * 3).zip(masks.par_chunks_mut(w)).enumerate().for_each(|(row_index, (row, mask_row))| {
            let cam = row_index / h;
            let y = row_index % h;
            let camera = &self.rig.cameras[cam];
            let origin = camera.centre();
            let origin = [origin.x, origin.y, origin.z];
            let gain = self.spec.cameras.gain.get(cam).copied().unwrap_or(1.0);
            let offset = self.spec.cameras.offset.get(cam).copied().unwrap_or(0.0);
            let cast = self.spec.cameras.colour_cast.get(cam).copied().unwrap_or([1.0; 3]);
            for x in 0..w {
                let dir = self.rays[cam][y * w + x];
                let (id, colour) = self.shade(origin, dir, &objects, cam, x as f64, y as f64, light);
                mask_row[x] = id;
                for c in 0..3 {
                    let n = noise(self.spec.seed, frame, cam as u32, (y * w + x) as u32, c as u32) * self.spec.noise;
                    row[x * 3 + c] = (colour[c] * gain * cast[c] + offset + n).round().clamp(0.0, 255.0) as u8;
                }
            }
        });
    }

    /// Truth of every object at `frame`, given that frame's masks (as rendered).
    pub fn truth(&self, frame: u32, masks: &[u8]) -> Vec<(&'static str, ObjectTruth)> {
        let states = self.spec.object_states(self.time(frame));
        let (w, h) = (self.spec.width as usize, self.spec.height as usize);
        let object_ids = [ids::HEAD, ids::LEFT_HAND, ids::RIGHT_HAND];
        OBJECTS
            .iter()
            .zip(states)
            .zip(object_ids)
            .map(|((name, (pos, vel)), id)| {
                let mut pixel = Vec::new();
                let mut visible = Vec::new();
                for (c, cam) in self.rig.cameras.iter().enumerate() {
                    let p = cam.project(&Point3::new(pos[0], pos[1], pos[2]));
                    pixel.push(p.map(|p| [p.x, p.y]));
                    let seen = p.is_some_and(|p| {
                        let (x, y) = (p.x.round(), p.y.round());
                        x >= 0.0 && y >= 0.0 && (x as usize) < w && (y as usize) < h && {
                            let seen = masks[c * w * h + y as usize * w + x as usize];
                            seen == id || (id == ids::HEAD && seen == ids::HAIR)
                        }
                    });
                    visible.push(seen);
                }
                (*name, ObjectTruth { pos, vel, pixel, visible })
            })
            .collect()
    }

    /// The scene's objects at `frame`, with their screen bounds per camera.
    fn objects(&self, frame: u32) -> Vec<Object> {
        let [(head, _), (left, _), (right, _)] = self.spec.object_states(self.time(frame));
        let shoulder_l = [0.19, 1.4, 0.0];
        let shoulder_r = [-0.19, 1.4, 0.0];
        let mut objects = vec![
            (ids::HEAD, Shape::Ellipsoid { centre: head, radii: [0.075, 0.1, 0.085] }, head),
            (ids::LEFT_HAND, Shape::Ellipsoid { centre: left, radii: [0.045, 0.07, 0.025] }, left),
            (ids::RIGHT_HAND, Shape::Ellipsoid { centre: right, radii: [0.045, 0.07, 0.025] }, right),
            (ids::TORSO, Shape::Ellipsoid { centre: [0.0, 1.15, -0.03], radii: [0.2, 0.32, 0.11] }, [0.0, 1.15, -0.03]),
            (ids::ARMS, Shape::Capsule { a: shoulder_l, b: towards(left, shoulder_l, 0.06), radius: 0.04 }, shoulder_l),
            (
                ids::ARMS,
                Shape::Capsule { a: shoulder_r, b: towards(right, shoulder_r, 0.06), radius: 0.04 },
                shoulder_r,
            ),
        ]
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
            ids::LEFT_HAND | ids::RIGHT_HAND => {
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
    let (w, h) = (f64::from(spec.width), f64::from(spec.height));
    let f = 0.5 * w / (0.5 * arc.fov_deg.to_radians()).tan();
    let k = Matrix3::new(f, 0.0, (w - 1.0) / 2.0, 0.0, f, (h - 1.0) / 2.0, 0.0, 0.0, 1.0);
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
            let r =
                Rotation3::from_matrix_unchecked(Matrix3::from_rows(&[x.transpose(), y.transpose(), z.transpose()]));
            let t = -(r * pos);
            Camera::new(format!("cam{i}"), spec.width, spec.height, k, Distortion::default(), r, t)
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

    #[test]
    fn truth_points_project_onto_pixels_of_their_object() {
        for name in super::super::scene::PRESETS {
            let spec = small(name);
            let r = Renderer::new(&spec).expect("renderer");
            let views = spec.cameras.angles_deg.len();
            let mut rgb = vec![0u8; r.view_len() * views];
            let mut masks = vec![0u8; r.view_len() / 3 * views];
            let mut visible = 0;
            for frame in 0..spec.frames {
                r.render_into(frame, &mut rgb, &mut masks);
                for (name, truth) in r.truth(frame, &masks) {
                    for (c, seen) in truth.visible.iter().enumerate() {
                        if *seen {
                            visible += 1;
                            let [u, v] = truth.pixel[c].expect("projects");
                            assert!(u >= 0.0 && v >= 0.0, "{name} camera {c} frame {frame}");
                        }
                    }
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
}
