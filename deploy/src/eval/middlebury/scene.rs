//! Loading, cropping and writing a Middlebury multi-baseline scene folder: `scene.toml`,
//! the views `im0 .. imN-1` and the disparity maps `dispK` of the views in `gt_views`.

use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};

use image::DynamicImage;
use rayon::prelude::*;

use super::SceneError;

/// Extensions tried for a view image, in order. The Middlebury 2003 release ships PPM;
/// later releases ship PNG, so a converted scene works without renaming.
const IMAGE_EXTENSIONS: [&str; 3] = ["ppm", "png", "bmp"];
/// Extensions tried for a disparity map, in order.
const DISPARITY_EXTENSIONS: [&str; 2] = ["pgm", "png"];

/// A multi-baseline scene: views equally spaced on a horizontal line, numbered left to
/// right, and the ground-truth disparity of some of them.
#[derive(Clone, Debug, PartialEq)]
pub struct Scene {
    /// Scene name (`name` of `scene.toml`, else the folder name).
    pub name: String,
    /// The folder the scene was loaded from.
    pub dir: PathBuf,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// RGB8 interleaved, row-major, one per view `im0 .. imN-1`.
    pub images: Vec<Vec<u8>>,
    /// Disparity map value per pixel of disparity (`disparity_scale` of `scene.toml`).
    pub disparity_scale: f64,
    /// Camera spacings spanned by the encoded disparity (`disparity_span`).
    pub disparity_span: f64,
    /// Search range of the encoded disparity, pixels over `disparity_span` spacings.
    pub disparity_range: (f64, f64),
    /// `(view index, neighbour-view disparity d1 per pixel)`, row-major, NaN where unknown.
    pub gt: Vec<(usize, Vec<f32>)>,
}

/// The keys of `scene.toml`, for [`Scene::save`].
#[derive(serde::Serialize)]
struct Description<'a> {
    name: &'a str,
    width: u32,
    height: u32,
    views: usize,
    gt_views: Vec<usize>,
    disparity_scale: f64,
    disparity_span: f64,
    disparity_range: [f64; 2],
}

impl Scene {
    /// Loads a scene folder: `scene.toml` (keys `width`, `height`, `views`, `gt_views`,
    /// `disparity_scale`, `disparity_span`, `disparity_range`; `name` optional), the views
    /// `imK.ppm` (or `.png`, `.bmp`) and the disparity maps `dispK.pgm` (or `.png`, 8 or 16
    /// bit, 0 = unknown) of the views in `gt_views`.
    pub fn load(dir: &Path) -> Result<Scene, SceneError> {
        let toml_path = dir.join("scene.toml");
        if !toml_path.is_file() {
            return Err(SceneError::MissingDescription { path: toml_path });
        }
        let text = fs::read_to_string(&toml_path).map_err(|e| SceneError::io(&toml_path, e))?;
        let table: toml::Table = text.parse().map_err(|source| SceneError::Toml { path: toml_path.clone(), source })?;
        let keys = Keys { table: &table, path: &toml_path };

        let name = match table.get("name") {
            Some(_) => keys.string("name")?,
            None => dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "scene".to_string()),
        };
        let width = keys.positive_u32("width")?;
        let height = keys.positive_u32("height")?;
        let views = keys.positive_u32("views")? as usize;
        let gt_views = keys.view_list("gt_views", views)?;
        let disparity_scale = keys.positive_f64("disparity_scale")?;
        let disparity_span = keys.positive_f64("disparity_span")?;
        let disparity_range = keys.range("disparity_range")?;

        let images = (0..views)
            .into_par_iter()
            .map(|k| {
                let path =
                    find_file(dir, &format!("im{k}"), &IMAGE_EXTENSIONS).ok_or_else(|| SceneError::MissingImage {
                        path: dir.join(format!("im{k}.{}", IMAGE_EXTENSIONS[0])),
                        views,
                        last: views - 1,
                        tried: IMAGE_EXTENSIONS.map(|e| format!(".{e}")).join(", "),
                    })?;
                let image = decode(&path)?;
                check_size(&path, &image, width, height)?;
                Ok(image.into_rgb8().into_raw())
            })
            .collect::<Result<Vec<_>, SceneError>>()?;

        let gt = gt_views
            .par_iter()
            .map(|&view| {
                let path = find_file(dir, &format!("disp{view}"), &DISPARITY_EXTENSIONS).ok_or_else(|| {
                    SceneError::MissingDisparity {
                        path: dir.join(format!("disp{view}.{}", DISPARITY_EXTENSIONS[0])),
                        view,
                    }
                })?;
                let raw = read_disparity(&path, width, height)?;
                let per_d1 = disparity_scale * disparity_span;
                let d1 =
                    raw.into_iter().map(|v| if v == 0 { f32::NAN } else { (f64::from(v) / per_d1) as f32 }).collect();
                Ok((view, d1))
            })
            .collect::<Result<Vec<_>, SceneError>>()?;

        Ok(Scene {
            name,
            dir: dir.to_path_buf(),
            width,
            height,
            images,
            disparity_scale,
            disparity_span,
            disparity_range,
            gt,
        })
    }

    /// The window `width` x `height` at column `x0`, row `y0` of every view and disparity
    /// map. Disparities are offsets between views, so they carry over unchanged.
    pub fn crop(&self, x0: u32, y0: u32, width: u32, height: u32) -> Result<Scene, SceneError> {
        let fits =
            |start: u32, size: u32, total: u32| size > 0 && start.checked_add(size).is_some_and(|end| end <= total);
        if !fits(x0, width, self.width) || !fits(y0, height, self.height) {
            return Err(SceneError::Crop {
                scene: self.name.clone(),
                x0,
                y0,
                width,
                height,
                scene_width: self.width,
                scene_height: self.height,
            });
        }
        let (x0, y0, w, h, full_w) = (x0 as usize, y0 as usize, width as usize, height as usize, self.width as usize);
        let window = |data: &[u8], channels: usize| -> Vec<u8> {
            (y0..y0 + h)
                .flat_map(|y| &data[(y * full_w + x0) * channels..(y * full_w + x0 + w) * channels])
                .copied()
                .collect()
        };
        let window_f32 = |data: &[f32]| -> Vec<f32> {
            (y0..y0 + h).flat_map(|y| &data[y * full_w + x0..y * full_w + x0 + w]).copied().collect()
        };
        Ok(Scene {
            name: format!("{}-{w}x{h}+{x0}+{y0}", self.name),
            dir: self.dir.clone(),
            width,
            height,
            images: self.images.iter().map(|image| window(image, 3)).collect(),
            disparity_scale: self.disparity_scale,
            disparity_span: self.disparity_span,
            disparity_range: self.disparity_range,
            gt: self.gt.iter().map(|(view, d1)| (*view, window_f32(d1))).collect(),
        })
    }

    /// Writes the scene into `dir` (created if needed) in the layout [`Scene::load`] reads:
    /// `scene.toml`, `imK.ppm` and `dispK.pgm` (8-bit when the encoded values fit, else
    /// 16-bit). Disparities are re-encoded as `round(d1 * disparity_scale *
    /// disparity_span)`, exact for a scene that was loaded; a known disparity never
    /// rounds to 0 (which would mean unknown).
    pub fn save(&self, dir: &Path) -> Result<(), SceneError> {
        fs::create_dir_all(dir).map_err(|e| SceneError::io(dir, e))?;
        let description = Description {
            name: &self.name,
            width: self.width,
            height: self.height,
            views: self.images.len(),
            gt_views: self.gt.iter().map(|(view, _)| *view).collect(),
            disparity_scale: self.disparity_scale,
            disparity_span: self.disparity_span,
            disparity_range: [self.disparity_range.0, self.disparity_range.1],
        };
        let toml_path = dir.join("scene.toml");
        let body = toml::to_string(&description)
            .map_err(|e| SceneError::io(&toml_path, std::io::Error::new(std::io::ErrorKind::InvalidData, e)))?;
        let text = format!(
            "# Written by handflow (Scene::save). disparity_px = pgm_value / disparity_scale,\n\
             # spanning disparity_span camera spacings; 0 = unknown.\n{body}"
        );
        fs::write(&toml_path, text).map_err(|e| SceneError::io(&toml_path, e))?;

        for (k, image) in self.images.iter().enumerate() {
            let path = dir.join(format!("im{k}.ppm"));
            write_pnm(&path, b"P6", self.width, self.height, 255, image)?;
        }
        let per_d1 = self.disparity_scale * self.disparity_span;
        for (view, d1) in &self.gt {
            let values: Vec<u16> = d1
                .iter()
                .map(|&d| {
                    if d.is_finite() && d > 0.0 {
                        (f64::from(d) * per_d1).round().clamp(1.0, 65535.0) as u16
                    } else {
                        0
                    }
                })
                .collect();
            let max = values.iter().copied().max().unwrap_or(0);
            let path = dir.join(format!("disp{view}.pgm"));
            if max <= 255 {
                let bytes: Vec<u8> = values.iter().map(|&v| v as u8).collect();
                write_pnm(&path, b"P5", self.width, self.height, 255, &bytes)?;
            } else {
                // 16-bit PNM samples are big-endian.
                let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_be_bytes()).collect();
                write_pnm(&path, b"P5", self.width, self.height, 65535, &bytes)?;
            }
        }
        Ok(())
    }

    /// The ground-truth disparity map of `view`, if the scene has one.
    pub fn gt_of(&self, view: usize) -> Option<&[f32]> {
        self.gt.iter().find(|(v, _)| *v == view).map(|(_, d1)| d1.as_slice())
    }
}

/// Typed access to the keys of `scene.toml`, each error naming the file and the key.
struct Keys<'a> {
    table: &'a toml::Table,
    path: &'a Path,
}

impl Keys<'_> {
    fn get(&self, key: &'static str) -> Result<&toml::Value, SceneError> {
        self.table.get(key).ok_or_else(|| SceneError::MissingKey { path: self.path.to_path_buf(), key })
    }

    fn bad(&self, key: &'static str, reason: impl Into<String>) -> SceneError {
        SceneError::BadKey { path: self.path.to_path_buf(), key, reason: reason.into() }
    }

    fn string(&self, key: &'static str) -> Result<String, SceneError> {
        match self.get(key)? {
            toml::Value::String(s) => Ok(s.clone()),
            other => Err(self.bad(key, format!("expected a string, found {}", other.type_str()))),
        }
    }

    fn positive_u32(&self, key: &'static str) -> Result<u32, SceneError> {
        match self.get(key)? {
            toml::Value::Integer(i) if *i > 0 && *i <= i64::from(u32::MAX) => Ok(*i as u32),
            toml::Value::Integer(i) => Err(self.bad(key, format!("expected a positive integer, found {i}"))),
            other => Err(self.bad(key, format!("expected a positive integer, found {}", other.type_str()))),
        }
    }

    fn number(&self, key: &'static str, value: &toml::Value) -> Result<f64, SceneError> {
        let x = match value {
            toml::Value::Integer(i) => *i as f64,
            toml::Value::Float(f) => *f,
            other => return Err(self.bad(key, format!("expected a number, found {}", other.type_str()))),
        };
        if x.is_finite() {
            Ok(x)
        } else {
            Err(self.bad(key, format!("expected a finite number, found {x}")))
        }
    }

    fn positive_f64(&self, key: &'static str) -> Result<f64, SceneError> {
        let x = self.number(key, self.get(key)?)?;
        if x > 0.0 {
            Ok(x)
        } else {
            Err(self.bad(key, format!("must be positive, found {x}")))
        }
    }

    /// `[low, high]` with `0 <= low < high`.
    fn range(&self, key: &'static str) -> Result<(f64, f64), SceneError> {
        let toml::Value::Array(items) = self.get(key)? else {
            return Err(self.bad(key, "expected an array [low, high]"));
        };
        let [low, high] = items.as_slice() else {
            return Err(self.bad(key, format!("expected two numbers [low, high], found {} entries", items.len())));
        };
        let (low, high) = (self.number(key, low)?, self.number(key, high)?);
        if low < 0.0 || high <= low {
            return Err(self.bad(key, format!("expected 0 <= low < high, found [{low}, {high}]")));
        }
        Ok((low, high))
    }

    /// Distinct view indices below `views`.
    fn view_list(&self, key: &'static str, views: usize) -> Result<Vec<usize>, SceneError> {
        let toml::Value::Array(items) = self.get(key)? else {
            return Err(self.bad(key, "expected an array of view indices"));
        };
        let mut list = Vec::with_capacity(items.len());
        for item in items {
            match item {
                toml::Value::Integer(i) if *i >= 0 && (*i as u64) < views as u64 => {
                    let view = *i as usize;
                    if list.contains(&view) {
                        return Err(self.bad(key, format!("view {view} listed twice")));
                    }
                    list.push(view);
                }
                toml::Value::Integer(i) => {
                    return Err(self.bad(key, format!("view {i} is not one of the {views} views (0 .. {})", views - 1)));
                }
                other => return Err(self.bad(key, format!("expected view indices, found {}", other.type_str()))),
            }
        }
        Ok(list)
    }
}

/// The first of `stem.ext` for `ext` in `extensions` that exists.
fn find_file(dir: &Path, stem: &str, extensions: &[&str]) -> Option<PathBuf> {
    extensions.iter().map(|ext| dir.join(format!("{stem}.{ext}"))).find(|p| p.is_file())
}

fn decode(path: &Path) -> Result<DynamicImage, SceneError> {
    image::open(path).map_err(|source| match source {
        image::ImageError::IoError(e) => SceneError::io(path, e),
        source => SceneError::Image { path: path.to_path_buf(), source },
    })
}

fn check_size(path: &Path, image: &DynamicImage, width: u32, height: u32) -> Result<(), SceneError> {
    if image.width() == width && image.height() == height {
        Ok(())
    } else {
        Err(SceneError::ImageSize {
            path: path.to_path_buf(),
            width,
            height,
            got_width: image.width(),
            got_height: image.height(),
        })
    }
}

/// The raw integer values of a disparity map. PGM is parsed here rather than by `image`,
/// which rescales samples whose maxval is not 255 or 65535 and would change the values.
fn read_disparity(path: &Path, width: u32, height: u32) -> Result<Vec<u16>, SceneError> {
    let is_pgm = path.extension().is_some_and(|e| e.eq_ignore_ascii_case("pgm"));
    let (got_width, got_height, raw) = if is_pgm {
        let bytes = fs::read(path).map_err(|e| SceneError::io(path, e))?;
        parse_pgm(&bytes).map_err(|reason| SceneError::DisparityFormat { path: path.to_path_buf(), kind: reason })?
    } else {
        let image = decode(path)?;
        let (w, h) = (image.width(), image.height());
        let raw = match image {
            DynamicImage::ImageLuma8(buffer) => buffer.into_raw().into_iter().map(u16::from).collect(),
            DynamicImage::ImageLuma16(buffer) => buffer.into_raw(),
            other => {
                let kind = format!("{:?}", other.color());
                return Err(SceneError::DisparityFormat { path: path.to_path_buf(), kind });
            }
        };
        (w, h, raw)
    };
    if (got_width, got_height) != (width, height) {
        return Err(SceneError::ImageSize { path: path.to_path_buf(), width, height, got_width, got_height });
    }
    Ok(raw)
}

/// A binary PGM (`P5`): width, height and the raw samples (one byte each when maxval < 256,
/// else two, big-endian).
fn parse_pgm(bytes: &[u8]) -> Result<(u32, u32, Vec<u16>), String> {
    if !bytes.starts_with(b"P5") {
        return Err("not a binary PGM (no `P5` magic)".to_string());
    }
    let mut pos = 2;
    let mut fields = [0u32; 3];
    for (i, field) in fields.iter_mut().enumerate() {
        // Whitespace and `#` comments may separate header fields.
        loop {
            match bytes.get(pos) {
                Some(b) if b.is_ascii_whitespace() => pos += 1,
                Some(b'#') => {
                    while bytes.get(pos).is_some_and(|&b| b != b'\n') {
                        pos += 1;
                    }
                }
                _ => break,
            }
        }
        let start = pos;
        while bytes.get(pos).is_some_and(u8::is_ascii_digit) {
            pos += 1;
        }
        let name = ["width", "height", "maxval"][i];
        *field = std::str::from_utf8(&bytes[start..pos])
            .ok()
            .and_then(|t| t.parse().ok())
            .ok_or_else(|| format!("a PGM header without a valid {name}"))?;
    }
    let [width, height, maxval] = fields;
    if maxval == 0 || maxval > 65535 {
        return Err(format!("a PGM with maxval {maxval} (expected 1 ..= 65535)"));
    }
    // Exactly one whitespace byte ends the header.
    if !bytes.get(pos).is_some_and(u8::is_ascii_whitespace) {
        return Err("a PGM header not followed by whitespace".to_string());
    }
    let data = &bytes[pos + 1..];
    let pixels = width as usize * height as usize;
    let sample = if maxval < 256 { 1 } else { 2 };
    if data.len() < pixels * sample {
        return Err(format!("a truncated PGM: {} bytes of samples for {width}x{height} pixels", data.len()));
    }
    let raw = if sample == 1 {
        data[..pixels].iter().map(|&v| u16::from(v)).collect()
    } else {
        data[..2 * pixels].chunks_exact(2).map(|c| u16::from_be_bytes([c[0], c[1]])).collect()
    };
    Ok((width, height, raw))
}

/// Binary PNM (`P5` grey, `P6` RGB): written by hand, since that keeps 16-bit PGM exact
/// whatever the encoder supports.
fn write_pnm(path: &Path, magic: &[u8], width: u32, height: u32, max: u16, bytes: &[u8]) -> Result<(), SceneError> {
    let file = fs::File::create(path).map_err(|e| SceneError::io(path, e))?;
    let mut out = std::io::BufWriter::new(file);
    let header = format!("{}\n{width} {height}\n{max}\n", String::from_utf8_lossy(magic));
    out.write_all(header.as_bytes())
        .and_then(|()| out.write_all(bytes))
        .and_then(|()| out.flush())
        .map_err(|e| SceneError::io(path, e))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval::middlebury::testing::synthetic_scene;
    use crate::eval::middlebury::{warp_disparity, Layout, Problem};

    const TEDDY: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../../shared/data/middlebury/teddy");

    fn teddy() -> Option<Scene> {
        let dir = Path::new(TEDDY);
        if !dir.join("scene.toml").is_file() {
            eprintln!("skipping: the Teddy scene is not at {TEDDY}");
            return None;
        }
        Some(Scene::load(dir).expect("Teddy loads"))
    }

    /// A small scene with varied pixels and disparities (some unknown), saved in `dir`.
    fn saved_scene(dir: &Path) -> Scene {
        let (w, h) = (12u32, 8u32);
        let mut scene = synthetic_scene(w, h, vec![]);
        scene.name = "tiny".to_string();
        scene.disparity_scale = 4.0;
        scene.disparity_span = 4.0;
        scene.disparity_range = (0.0, 64.0);
        for (k, image) in scene.images.iter_mut().enumerate() {
            for (i, byte) in image.iter_mut().enumerate() {
                *byte = ((i * 7 + k * 31) % 256) as u8;
            }
        }
        let d1 = |offset: u32| -> Vec<f32> {
            (0..w * h)
                .map(|i| if (i + offset).is_multiple_of(5) { f32::NAN } else { ((i + offset) % 200 + 1) as f32 / 16.0 })
                .collect()
        };
        scene.gt = vec![(2, d1(0)), (6, d1(3))];
        scene.save(dir).expect("save");
        scene.dir = dir.to_path_buf();
        scene
    }

    fn assert_same(a: &Scene, b: &Scene) {
        assert_eq!((a.width, a.height, &a.images), (b.width, b.height, &b.images));
        assert_eq!(
            (a.disparity_scale, a.disparity_span, a.disparity_range),
            (b.disparity_scale, b.disparity_span, b.disparity_range)
        );
        assert_eq!(a.gt.len(), b.gt.len());
        for ((va, da), (vb, db)) in a.gt.iter().zip(&b.gt) {
            assert_eq!(va, vb);
            for (x, y) in da.iter().zip(db) {
                assert!(x == y || (x.is_nan() && y.is_nan()), "view {va}: {x} vs {y}");
            }
        }
    }

    #[test]
    fn teddy_loads_with_sane_disparities() {
        let Some(scene) = teddy() else { return };
        assert_eq!((scene.name.as_str(), scene.width, scene.height), ("teddy", 450, 375));
        assert_eq!(scene.images.len(), 9);
        assert!(scene.images.iter().all(|im| im.len() == 450 * 375 * 3));
        assert_eq!(scene.gt.iter().map(|(v, _)| *v).collect::<Vec<_>>(), [2, 6]);
        for (view, d1) in &scene.gt {
            let known: Vec<f32> = d1.iter().copied().filter(|d| !d.is_nan()).collect();
            assert!(known.iter().all(|&d| d > 0.0 && d <= 16.0), "view {view}: d1 outside (0, 16]");
            assert!(known.len() > d1.len() * 9 / 10, "view {view}: only {} of {} known", known.len(), d1.len());
        }
    }

    /// The warp direction on real data: disp2 warped into view 6 agrees with disp6.
    #[test]
    fn teddy_disp2_warped_into_view_6_matches_disp6() {
        let Some(scene) = teddy() else { return };
        let (Some(d2), Some(d6)) = (scene.gt_of(2), scene.gt_of(6)) else { panic!("Teddy has disp2 and disp6") };
        for (from, source, to, target) in [(2, d2, 6, d6), (6, d6, 2, d2)] {
            let warped = warp_disparity(scene.width, scene.height, &[(from, source.to_vec())], to);
            let both: Vec<f32> = warped
                .iter()
                .zip(target)
                .filter(|(a, b)| a.is_finite() && b.is_finite())
                .map(|(a, b)| (a - b).abs())
                .collect();
            let close = both.iter().filter(|&&e| e <= 0.5).count();
            assert!(
                both.len() > 100_000 && close > both.len() * 95 / 100,
                "{from} -> {to}: {close} of {} agree",
                both.len()
            );
        }
    }

    /// The layout on real data: the true optical flow of the reference view (x at t
    /// minus d1 at t-1) matches the colours of im3 better than the opposite sign.
    #[test]
    fn teddy_true_flow_matches_the_images() {
        let Some(scene) = teddy() else { return };
        let problem = Problem::new(&scene, Layout::Multiview).expect("problem");
        let (w, h) = (scene.width as usize, scene.height as usize);
        let (now, before) =
            (&scene.images[problem.frames[1][problem.reference]], &scene.images[problem.frames[0][problem.reference]]);
        let mut cost = [0.0f64; 2];
        for y in 0..h {
            for x in 0..w {
                let d = problem.truth.d1[y * w + x];
                if !d.is_finite() {
                    continue;
                }
                for (sign, c) in [-1.0, 1.0].into_iter().zip(cost.iter_mut()) {
                    let xb = (x as f64 + sign * f64::from(d)).round();
                    let xb = xb.clamp(0.0, (w - 1) as f64) as usize;
                    *c += (0..3)
                        .map(|k| f64::from(now[(y * w + x) * 3 + k].abs_diff(before[(y * w + xb) * 3 + k])))
                        .sum::<f64>();
                }
            }
        }
        assert!(
            cost[0] * 3.0 < cost[1],
            "photometric cost with the protocol's sign {} vs opposite {}",
            cost[0],
            cost[1]
        );
        let fb = Problem::new(&scene, Layout::Fb).expect("fb");
        assert!(fb.truth.known() > w * h * 85 / 100, "view 4 truth: {} of {} known", fb.truth.known(), w * h);
        assert!(fb.truth.d1.iter().filter(|d| d.is_finite()).all(|&d| d > 0.0 && d <= 16.0));
    }

    #[test]
    fn crop_save_load_round_trip() {
        let dir = tempfile::tempdir().expect("tempdir");
        let scene = saved_scene(&dir.path().join("full"));
        let loaded = Scene::load(&dir.path().join("full")).expect("load");
        assert_eq!(loaded.name, "tiny");
        assert_same(&scene, &loaded);

        let crop = loaded.crop(3, 2, 6, 5).expect("crop");
        assert_eq!((crop.width, crop.height), (6, 5));
        assert_eq!(&crop.images[4][..3], &loaded.images[4][(2 * 12 + 3) * 3..(2 * 12 + 3) * 3 + 3]);
        let (Some(c6), Some(l6)) = (crop.gt_of(6), loaded.gt_of(6)) else { panic!("view 6 truth") };
        assert!(c6[5 + 4 * 6] == l6[(4 + 2) * 12 + 3 + 5] || c6[5 + 4 * 6].is_nan());
        let out = dir.path().join("crop");
        crop.save(&out).expect("save crop");
        assert_same(&crop, &Scene::load(&out).expect("load crop"));

        let err = loaded.crop(10, 0, 3, 1).expect_err("too wide");
        assert!(err.to_string().contains("crop 3x1 at (10, 0)"), "{err}");
        assert!(loaded.crop(0, 0, 0, 1).is_err(), "empty crop");
        assert!(loaded.crop(u32::MAX, 0, 2, 1).is_err(), "overflowing crop");
    }

    #[test]
    fn teddy_crop_round_trips_through_8_bit_pgm() {
        let Some(scene) = teddy() else { return };
        let crop = scene.crop(100, 100, 64, 48).expect("crop");
        let dir = tempfile::tempdir().expect("tempdir");
        crop.save(dir.path()).expect("save");
        let back = Scene::load(dir.path()).expect("load");
        assert_same(&crop, &back);
        let raw = fs::read(dir.path().join("disp2.pgm")).expect("disp2.pgm");
        assert!(raw.starts_with(b"P5\n64 48\n255\n"), "8-bit PGM when values fit");
    }

    #[test]
    fn large_disparities_save_as_16_bit() {
        let dir = tempfile::tempdir().expect("tempdir");
        let scene = synthetic_scene(3, 1, vec![(2, vec![300.0, f32::NAN, 0.2])]);
        scene.save(dir.path()).expect("save");
        let raw = fs::read(dir.path().join("disp2.pgm")).expect("disp2.pgm");
        assert!(raw.starts_with(b"P5\n3 1\n65535\n"), "16-bit PGM when values exceed 255");
        let back = Scene::load(dir.path()).expect("load");
        assert_eq!(back.gt_of(2).map(|d| (d[0], d[1].is_nan())), Some((300.0, true)));
        // 0.2 would round to 0 (unknown) at scale 1; it is kept known as 1.
        assert_eq!(back.gt_of(2).map(|d| d[2]), Some(1.0));
    }

    /// Saves the tiny scene, applies `break_it`, and returns the error text of loading it.
    fn load_broken(break_it: impl FnOnce(&Path)) -> String {
        let dir = tempfile::tempdir().expect("tempdir");
        saved_scene(dir.path());
        break_it(dir.path());
        Scene::load(dir.path()).expect_err("broken scene").to_string()
    }

    fn edit_toml(dir: &Path, edit: impl FnOnce(String) -> String) {
        let path = dir.join("scene.toml");
        let text = fs::read_to_string(&path).expect("scene.toml");
        fs::write(&path, edit(text)).expect("write scene.toml");
    }

    #[test]
    fn missing_description_is_named() {
        let text = load_broken(|dir| fs::remove_file(dir.join("scene.toml")).expect("remove"));
        assert!(text.contains("scene.toml") && text.contains("not found"), "{text}");
    }

    #[test]
    fn missing_key_names_file_and_key() {
        let text = load_broken(|dir| {
            edit_toml(dir, |t| t.lines().filter(|l| !l.starts_with("disparity_span")).collect::<Vec<_>>().join("\n"))
        });
        assert!(text.contains("scene.toml") && text.contains("missing key `disparity_span`"), "{text}");
    }

    #[test]
    fn bad_keys_name_file_and_key() {
        for (key, bad, expect) in [
            ("width", "width = -3", "`width`"),
            ("gt_views", "gt_views = [2, 9]", "view 9"),
            ("gt_views", "gt_views = [2, 2]", "listed twice"),
            ("disparity_range", "disparity_range = [10, 5]", "low < high"),
            ("disparity_scale", "disparity_scale = \"four\"", "expected a number"),
        ] {
            let text = load_broken(|dir| {
                edit_toml(dir, |t| {
                    t.lines().map(|l| if l.starts_with(key) { bad } else { l }).collect::<Vec<_>>().join("\n")
                })
            });
            assert!(text.contains("scene.toml") && text.contains(key) && text.contains(expect), "{bad}: {text}");
        }
        let text = load_broken(|dir| edit_toml(dir, |t| t + "\nwidth = [[["));
        assert!(text.contains("scene.toml") && text.contains("not valid TOML"), "{text}");
    }

    #[test]
    fn wrong_image_size_names_the_image() {
        let text = load_broken(|dir| {
            write_pnm(&dir.join("im3.ppm"), b"P6", 5, 4, 255, &[0; 5 * 4 * 3]).expect("write");
        });
        assert!(text.contains("im3.ppm") && text.contains("5x4") && text.contains("12x8"), "{text}");
        let text = load_broken(|dir| {
            write_pnm(&dir.join("disp6.pgm"), b"P5", 12, 7, 255, &[1; 12 * 7]).expect("write");
        });
        assert!(text.contains("disp6.pgm") && text.contains("12x7"), "{text}");
    }

    #[test]
    fn missing_files_are_named() {
        let text = load_broken(|dir| fs::remove_file(dir.join("disp6.pgm")).expect("remove"));
        assert!(text.contains("disp6.pgm") && text.contains("gt_views"), "{text}");
        let text = load_broken(|dir| fs::remove_file(dir.join("im8.ppm")).expect("remove"));
        assert!(text.contains("im8.ppm") && text.contains("9 views"), "{text}");
    }

    #[test]
    fn unreadable_files_are_named() {
        let text = load_broken(|dir| fs::write(dir.join("im1.ppm"), b"P6\n12 8\n255\nshort").expect("write"));
        assert!(text.contains("im1.ppm"), "{text}");
        let text = load_broken(|dir| fs::write(dir.join("disp2.pgm"), b"P5\n12 8\n255\nshort").expect("write"));
        assert!(text.contains("disp2.pgm") && text.contains("truncated"), "{text}");
        let text = load_broken(|dir| fs::write(dir.join("disp2.pgm"), b"P6\n12 8\n255\n").expect("write"));
        assert!(text.contains("disp2.pgm") && text.contains("P5"), "{text}");
    }
}
