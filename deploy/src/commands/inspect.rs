//! `handflow inspect`: what the tracker saw at one frame, as pictures per camera and a short
//! text summary, for finding out why tracking goes wrong on new footage.
//!
//! It runs exactly what `handflow track` runs (the same engine configuration, the same flow
//! stream with its face-detection schedule, the same cluster stage) from the first frame
//! read up to the chosen frame, and stops there. Starting part-way through would be faster
//! but would show something `track` never computes: the skin models adapt to the first
//! frames of a stream (0, 10 and 20 frames in) and the tracks carry their history from
//! frame to frame. Pass `--start` to inspect a `track --start` run.
//!
//! Per camera, in `out/<camera>/`: `skin.png` (the engine's skin map), `faces.png` (the face
//! detections behind the skin models in use), `rays.png` (where particles are), `clusters.png`
//! (the EM components, labelled), `tracks.png` (the last positions of the tracks); and
//! `out/montage.png`, every camera's layers side by side, downscaled; `out/points.csv`, the
//! scene points the clusters were fitted to.

use std::collections::VecDeque;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use handflow_cluster::em::EmFit;
use handflow_cluster::stage::{labelled_clusters, ClusterStage, StartStatus};
use handflow_cluster::tracks::OBJECTS;
use handflow_flow::stream::{
    ray_spread_variance, scene_points, skin_share, FaceCue, FaceRound, FaceStatus, SetOutcome, StreamError,
};
use handflow_flow::SceneFlowEngine;
use handflow_ingest::Recording;
use handflow_protocol::messages::{ClusterSet, ScenePoint, PROTOCOL_VERSION};
use handflow_protocol::Camera;
use handflow_publish::{trajectory_sample, TrajectoryRecord};
use image::RgbImage;
use nalgebra::Point3;

use crate::commands::overlay::TAIL;
use crate::commands::track::{tracker_stages, TrackOptions};
use handflow_publish::drawing::{draw_disc, draw_line, draw_tracks, put};

/// The picture layers written per camera, in montage column order.
pub const LAYERS: [&str; 5] = ["skin", "faces", "rays", "clusters", "tracks"];
/// Width of one montage tile, pixels: five layers of a 1280-wide camera fit a 1600-pixel
/// screen.
pub const MONTAGE_TILE_WIDTH: u32 = 320;
/// Colours of head, left hand and right hand (as `handflow overlay` draws them), then of
/// clusters no track took.
const LABEL_COLOURS: [[u8; 3]; 4] = [[255, 220, 0], [0, 230, 80], [255, 40, 40], [150, 150, 255]];
/// Dimming of the camera image under the drawings of `rays`, `clusters` and `tracks`: the
/// drawings must stand out from a busy room.
const BACKGROUND_DIM: f32 = 0.45;

/// What was inspected, for the caller to print or check.
#[derive(Clone, Debug, Default)]
pub struct InspectSummary {
    /// The summary text (one line per camera, clusters, tracks), as printed.
    pub text: String,
    /// Files written.
    pub files: Vec<PathBuf>,
}

/// Why the stream stopped being pushed: the inspected frame's estimate is ready (the
/// stream is left as it was then), or something failed.
enum Halt {
    Reached,
    Failed(anyhow::Error),
}

impl From<StreamError> for Halt {
    fn from(e: StreamError) -> Self {
        Halt::Failed(e.into())
    }
}

impl From<anyhow::Error> for Halt {
    fn from(e: anyhow::Error) -> Self {
        Halt::Failed(e)
    }
}

/// Runs the tracker over `dir` up to frame number `frame` (as in the recording's frame
/// table) and writes the pictures of that frame into `out`.
pub fn inspect_recording(dir: &Path, options: &TrackOptions, frame: u64, out: &Path) -> Result<InspectSummary> {
    let rec = Recording::open_with(dir, &options.recording)?;
    let rig = crate::recording_engine::tracking_rig(&rec, options.up)?;
    let up = rig.world_up();
    let fps = rec.frame_rate();
    let index = rec.frames().iter().position(|f| f.frame == frame).with_context(|| {
        let (first, last) = (rec.frames().first().map_or(0, |f| f.frame), rec.frames().last().map_or(0, |f| f.frame));
        format!("frame {frame} is not in recording `{}` (frames {first} to {last} read)", dir.display())
    })?;
    let (mut flow, mut stage, reference) = tracker_stages::<usize>(options, &rig, up.direction, fps)?;
    anyhow::ensure!(
        index > 0 || flow.engine().config().estimates_first_frame(),
        "frame {frame} is the first frame read: it has no estimate with `estimate_first_frame=false` (the engine \
         needs the frame before); choose a later one"
    );
    let mut tail: VecDeque<TrajectoryRecord> = VecDeque::with_capacity(TAIL);
    let mut points: Vec<ScenePoint> = Vec::new();
    let mut inspected: Option<Vec<u8>> = None;
    let mut reached = false;
    // The same work per estimate as `track`: points, clustering and labelling, a record;
    // the sets before it without a frame of the reference camera clustered empty, first.
    let mut cluster = |k: usize, engine: Option<&SceneFlowEngine>, face: Option<FaceCue>| -> Result<(), Halt> {
        let entry = rec.frames().get(k).with_context(|| format!("estimate for frame set {k} beyond the recording"))?;
        points.clear();
        points.extend(engine.into_iter().flat_map(scene_points));
        let face = crate::recording_engine::cluster_face_cue(face, fps);
        let spread = engine.map_or(0.0, ray_spread_variance);
        let objects = stage.update(entry.timestamp, fps, spread, &points, face);
        let set = ClusterSet {
            protocol_version: PROTOCOL_VERSION,
            frame: entry.frame,
            sequence: k as u64,
            timestamp_s: entry.timestamp,
            objects: labelled_clusters(&objects),
            missing_views: entry.missing_views,
            ..ClusterSet::default()
        };
        if tail.len() == TAIL {
            tail.pop_front();
        }
        tail.push_back(TrajectoryRecord::from_sample(&trajectory_sample(&set, 0, 0)));
        if k == index {
            Err(Halt::Reached)
        } else {
            Ok(())
        }
    };
    let mut on_estimate = |k: usize, outcome: SetOutcome<'_>| -> Result<(), Halt> {
        match outcome {
            SetOutcome::Estimated { engine, face } => cluster(k, Some(engine), face),
            SetOutcome::PassedOver => cluster(k, None, None),
        }
    };
    let mut buf = vec![0u8; rec.frame_set_len()];
    for k in 0..rec.len() {
        let missing = match rec.read_frame_into(k as u64, false, &mut buf) {
            Ok(info) => info.missing_views,
            Err(error) if error.is_bad_frame() && k != index => {
                // `track` skips such a frame set too.
                tracing::error!("frame set {k} skipped: {error}");
                continue;
            }
            Err(error) => return Err(anyhow::Error::from(error).context(format!("frame {}", rec.frames()[k].frame))),
        };
        if k == index {
            // The rays start in the reference view: without it the set is passed over.
            let camera = &rig.cameras[reference].name;
            anyhow::ensure!(
                missing & (1 << reference) == 0,
                "frame {frame} has no view of the reference camera `{camera}`: no estimate"
            );
            inspected = Some(buf.clone());
        }
        match flow.push_partial_at(k, &buf, missing, k as u64, &mut on_estimate) {
            Ok(()) => {}
            Err(Halt::Reached) => {
                reached = true;
                break;
            }
            Err(Halt::Failed(e)) => return Err(e.context(format!("frame {}", rec.frames()[k].frame))),
        }
    }
    if !reached {
        match flow.finish(&mut on_estimate) {
            Ok(()) => {}
            Err(Halt::Reached) => reached = true,
            Err(Halt::Failed(e)) => return Err(e.context("end of the recording")),
        }
    }
    anyhow::ensure!(reached, "frame {frame} got no estimate");
    let frame_set = inspected.context("the inspected frame was not read")?;
    let entry = &rec.frames()[index];
    let engine = flow.engine();
    let faces = flow.faces_of_last_estimate();
    let views = rec.views(&frame_set);
    let tail: Vec<TrajectoryRecord> = tail.into_iter().collect();

    let mut summary = InspectSummary::default();
    let text = &mut summary.text;
    writeln!(
        text,
        "frame {frame} (t {:.3} s), reference camera `{}`, {} points",
        entry.timestamp,
        rig.cameras[reference].name,
        points.len()
    )?;
    let mut tiles: Vec<Vec<RgbImage>> = Vec::new();
    for (c, (cam, view)) in rig.cameras.iter().zip(&views).enumerate() {
        let photo = RgbImage::from_raw(cam.width, cam.height, view.to_vec())
            .with_context(|| format!("camera `{}`: frame buffer of the wrong size", cam.name))?;
        let share = skin_share(engine, c, 1);
        let status = faces.map_or(FaceStatus::None, |f| f.status(c));
        let own = faces.and_then(|f| f.detections.get(c)).map_or(0, Vec::len);
        let round =
            faces.map_or_else(|| "no detection round yet".to_string(), |f| format!("round of frame set {}", f.frame));
        let skin = match share {
            _ if entry.missing_views & (1 << c) != 0 => "no frame in this set (the camera dropped it)".to_string(),
            Some(s) => format!("skin {:.1} % of the image", 100.0 * s),
            None => "skin unknown".to_string(),
        };
        writeln!(text, "camera `{}`: {skin}; face {} ({own} own detection(s), {round})", cam.name, status.name())?;
        let layers = [
            skin_picture(engine, c, cam, share),
            faces_picture(&photo, faces, c),
            rays_picture(&photo, engine, c),
            clusters_picture(&photo, cam, stage.last_fit(), &stage),
            tracks_picture(&photo, cam, &tail, stage.start_status()),
        ];
        let folder = out.join(folder_name(c, &cam.name));
        std::fs::create_dir_all(&folder).with_context(|| format!("creating `{}`", folder.display()))?;
        for (layer, picture) in LAYERS.iter().zip(&layers) {
            let path = folder.join(format!("{layer}.png"));
            picture.save(&path).with_context(|| format!("writing `{}`", path.display()))?;
            summary.files.push(path);
        }
        tiles.push(layers.into_iter().collect());
    }
    describe_clusters(text, stage.last_fit(), &stage)?;
    describe_tracks(text, tail.last(), stage.start_status())?;
    let montage = montage(&tiles, &rig.cameras);
    let path = out.join("montage.png");
    montage.save(&path).with_context(|| format!("writing `{}`", path.display()))?;
    summary.files.push(path);
    let path = out.join("points.csv");
    std::fs::write(&path, points_csv(&points)).with_context(|| format!("writing `{}`", path.display()))?;
    summary.files.push(path);
    Ok(summary)
}

/// The frame's scene points as the cluster stage received them, one CSV row each: world
/// position (m), velocity (m per frame), weight and skin probability.
fn points_csv(points: &[ScenePoint]) -> String {
    let mut csv = String::from("x,y,z,vx,vy,vz,weight,skin\n");
    for p in points {
        let [x, y, z] = p.position;
        let [vx, vy, vz] = p.velocity;
        // Writing into a String cannot fail.
        let _ = writeln!(csv, "{x},{y},{z},{vx},{vy},{vz},{},{}", p.weight, p.skin);
    }
    csv
}

/// A folder name for camera `index` named `camera`: its name with path separators
/// replaced (a rig file is external input), or `camera_<index>` for a name that would still
/// not be a folder of its own (empty, `.`, `..`).
fn folder_name(index: usize, camera: &str) -> String {
    let name: String = camera.chars().map(|c| if matches!(c, '/' | '\\' | ':') { '_' } else { c }).collect();
    if name.chars().all(|c| c == '.') {
        format!("camera_{index}")
    } else {
        name
    }
}

fn describe_clusters(text: &mut String, fit: Option<&EmFit>, stage: &ClusterStage) -> Result<()> {
    let Some(fit) = fit else {
        writeln!(text, "clusters: none (no usable point or EM failed)")?;
        return Ok(());
    };
    writeln!(
        text,
        "clusters: {} components, {} points used, outlier share {:.1} %",
        fit.components.len(),
        fit.points_used,
        100.0 * fit.outlier_share
    )?;
    for (i, c) in fit.components.iter().enumerate() {
        let p = c.position;
        writeln!(
            text,
            "  cluster {i} {:<10} at ({:.3}, {:.3}, {:.3}) m, weight {:.2}{}",
            cluster_label(stage, i).0,
            p.x,
            p.y,
            p.z,
            c.mixing,
            if c.empty { " (empty)" } else { "" }
        )?;
    }
    Ok(())
}

fn describe_tracks(text: &mut String, last: Option<&TrajectoryRecord>, status: StartStatus) -> Result<()> {
    let Some(record) = last else { return Ok(()) };
    let mut line = String::from("tracks:");
    for name in OBJECTS {
        if let Some(o) = record.objects.get(name) {
            let state = serde_json::to_value(o.state)?.as_str().unwrap_or("?").to_string();
            write!(
                line,
                " {name} {state} ({:.3}, {:.3}, {:.3}) conf {:.2};",
                o.pos[0], o.pos[1], o.pos[2], o.confidence
            )?;
        }
    }
    writeln!(text, "{}", line.trim_end_matches(';'))?;
    match status {
        StartStatus::Running => {}
        StartStatus::NoSkin => writeln!(text, "tracks not started: no skin points in the reference view")?,
        StartStatus::NotStarted(why) => writeln!(text, "tracks not started: {why}")?,
    }
    Ok(())
}

/// The label of cluster `i` and its colour: the object whose track took it, or `clutter`.
fn cluster_label(stage: &ClusterStage, i: usize) -> (&'static str, [u8; 3]) {
    stage
        .assigned()
        .iter()
        .position(|m| m.is_some_and(|m| m.cluster == i))
        .map_or(("clutter", LABEL_COLOURS[3]), |k| (OBJECTS[k], LABEL_COLOURS[k]))
}

/// The skin map in false colour: not skin in greys (darker the less skin-like), skin from
/// orange to white as the clamped ratio rises to its ceiling.
fn skin_picture(engine: &SceneFlowEngine, camera: usize, cam: &Camera, share: Option<f32>) -> RgbImage {
    let mut img = RgbImage::new(cam.width, cam.height);
    let threshold = engine.config().skin_threshold;
    if let Some(map) = engine.skin_map(camera) {
        let ceiling = engine.skin_models().get(camera).map_or(1.0, |m| m.alpha()).max(threshold + 1e-3);
        for (pixel, &r) in img.pixels_mut().zip(map) {
            *pixel = image::Rgb(if r > threshold {
                let t = ((r - threshold) / (ceiling - threshold)).clamp(0.0, 1.0);
                [255, (120.0 + 135.0 * t) as u8, (40.0 + 215.0 * t * t) as u8]
            } else {
                // Ratios below -3 (a thousand times likelier background) are all black.
                let t = ((r - threshold + 3.0) / 3.0).clamp(0.0, 1.0);
                let v = (20.0 + 120.0 * t) as u8;
                [v, v, v]
            });
        }
    }
    let label = match share {
        Some(s) => format!("SKIN {:.1} %  {}", 100.0 * s, cam.name),
        None => format!("NO SKIN MAP  {}", cam.name),
    };
    draw_label(&mut img, 4, 4, &label, [255, 255, 255]);
    img
}

/// The camera image with the face boxes of the round in use: each own detection (thin,
/// grey, with its score) and the box the model was adapted with (green when its own, cyan
/// when lent by the other views).
fn faces_picture(photo: &RgbImage, round: Option<&FaceRound>, camera: usize) -> RgbImage {
    let mut img = photo.clone();
    let scale = text_scale(img.width());
    let Some(round) = round else {
        draw_label(&mut img, 4, 4, "NO FACE ROUND YET", [255, 255, 255]);
        return img;
    };
    for det in round.detections.get(camera).into_iter().flatten() {
        draw_box(&mut img, det.x, det.y, det.width, det.height, [170, 170, 170], 1);
        let y = (det.y + det.height) as i64 + 2;
        draw_label(&mut img, det.x as i64, y, &format!("DET {:.1}", det.score), [200, 200, 200]);
    }
    let status = round.status(camera);
    if let Some(Some(face)) = round.fused.boxes.get(camera) {
        let colour = if status == FaceStatus::Lent { [0, 220, 255] } else { [0, 255, 80] };
        draw_box(&mut img, face.x, face.y, face.width, face.height, colour, scale as i64 + 1);
        let y = face.y as i64 - 9 * scale as i64 - 4;
        draw_label(&mut img, face.x as i64, y.max(0), &format!("FACE {}", status.name()), colour);
    }
    let own = round.detections.get(camera).map_or(0, Vec::len);
    draw_label(
        &mut img,
        4,
        4,
        &format!("FACE {}  {own} OWN DET  ROUND {}", status.name(), round.frame),
        [255, 255, 255],
    );
    img
}

/// Where particles are: on the reference camera the pixels of rays holding particles,
/// shaded by confidence; on the others each such ray's estimate projected.
fn rays_picture(photo: &RgbImage, engine: &SceneFlowEngine, camera: usize) -> RgbImage {
    let mut img = dimmed(photo);
    let reference_rays = draw_field(&mut img, engine, camera, [255, 0, 255], |_| true);
    let mut label = format!(
        "{reference_rays} {}",
        if camera == engine.reference() { "RAYS WITH PARTICLES" } else { "POINTS PROJECTED" }
    );
    // The second reference's rays, where it adds what the reference cannot see (the points
    // `track` keeps of it).
    if let Some(companion) = engine.companion() {
        let kept = |p: [f32; 3]| !engine.reference_sees(p);
        let rays = draw_field(&mut img, companion, camera, [0, 230, 255], kept);
        let name = engine.cameras().get(companion.reference()).map_or("?", |c| c.name.as_str());
        label.push_str(&format!(", {rays} FROM {}", name.to_uppercase()));
    }
    draw_label(&mut img, 4, 4, &label, [255, 255, 255]);
    img
}

/// Draws the rays of `engine`'s field that hold particles and whose position passes `keep`
/// on `camera`'s picture: as blocks on the engine's reference camera, as the estimated
/// points projected on any other, in `colour` (paler where a ray is less confident).
/// Returns how many it drew.
fn draw_field(
    img: &mut RgbImage,
    engine: &SceneFlowEngine,
    camera: usize,
    colour: [u8; 3],
    keep: impl Fn([f32; 3]) -> bool,
) -> usize {
    let field = engine.field();
    let cams = engine.cameras();
    let (Some(cam), Some(reference)) = (cams.get(camera), cams.get(engine.reference())) else { return 0 };
    let scale = (reference.width as usize / field.width.max(1)).max(1);
    let mut rays = 0usize;
    for ray in (0..field.width * field.height).filter(|&r| field.confidence.get(r).is_some_and(|&c| c > 0.0)) {
        let Some(&p) = field.position.get(ray).filter(|p| p.iter().all(|v| v.is_finite())) else { continue };
        if !keep(p) {
            continue;
        }
        rays += 1;
        let pale = (60.0 * (1.0 - field.confidence[ray])) as u8;
        let colour = colour.map(|c| c.max(pale));
        if camera == engine.reference() {
            let (x0, y0) = ((ray % field.width) * scale, (ray / field.width) * scale);
            for y in y0..y0 + scale {
                for x in x0..x0 + scale {
                    put(img, x as i64, y as i64, colour);
                }
            }
        } else {
            let world = Point3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
            if let Some(q) = cam.project(&world) {
                draw_disc(img, q.x, q.y, 1.0, colour, false);
            }
        }
    }
    rays
}

/// The EM components projected: a circle of one standard deviation of position around each
/// mean, labelled with the object whose track took it (or `clutter`) and its weight.
fn clusters_picture(photo: &RgbImage, cam: &Camera, fit: Option<&EmFit>, stage: &ClusterStage) -> RgbImage {
    let mut img = dimmed(photo);
    let Some(fit) = fit else {
        draw_label(&mut img, 4, 4, "NO CLUSTERS", [255, 255, 255]);
        return img;
    };
    let focal = cam.matrix[(0, 0)];
    for (i, c) in fit.components.iter().enumerate() {
        let (label, colour) = cluster_label(stage, i);
        let world = Point3::from(c.position);
        let Some(q) = cam.project(&world) else { continue };
        let depth = (world - cam.centre()).norm().max(1e-3);
        let std = (c.covariance.fixed_view::<3, 3>(0, 0).trace() / 3.0).max(0.0).sqrt();
        let radius = (focal * std / depth).clamp(4.0, 2.0 * f64::from(img.width()));
        draw_disc(&mut img, q.x, q.y, radius, colour, true);
        draw_disc(&mut img, q.x, q.y, 4.0, colour, c.empty);
        let text = format!("{i} {label} {:.2}", c.mixing);
        draw_label(&mut img, (q.x + radius * 0.7) as i64, (q.y - radius * 0.7) as i64, &text, colour);
    }
    draw_label(&mut img, 4, 4, &format!("{} CLUSTERS", fit.components.len()), [255, 255, 255]);
    img
}

/// The last positions of the tracks (as `handflow overlay` draws them) and their states.
fn tracks_picture(photo: &RgbImage, cam: &Camera, tail: &[TrajectoryRecord], status: StartStatus) -> RgbImage {
    let mut img = dimmed(photo);
    draw_tracks(&mut img, cam, tail);
    let line = match status {
        StartStatus::Running => tail.last().map_or_else(String::new, |r| {
            OBJECTS
                .iter()
                .filter_map(|name| {
                    let o = r.objects.get(*name)?;
                    let state = serde_json::to_value(o.state).ok()?.as_str()?.to_string();
                    Some(format!("{name} {state}"))
                })
                .collect::<Vec<_>>()
                .join("  ")
        }),
        StartStatus::NoSkin => "NOT STARTED: NO SKIN".to_string(),
        StartStatus::NotStarted(why) => format!("NOT STARTED: {}", why.cause()),
    };
    draw_label(&mut img, 4, 4, &line, [255, 255, 255]);
    img
}

/// Every camera's layers (a row per camera, a column per layer), each downscaled to
/// [`MONTAGE_TILE_WIDTH`] and labelled.
fn montage(tiles: &[Vec<RgbImage>], cameras: &[Camera]) -> RgbImage {
    let tile_height = |cam: &Camera| {
        (f64::from(cam.height) * f64::from(MONTAGE_TILE_WIDTH) / f64::from(cam.width.max(1))).round().max(1.0) as u32
    };
    let row_height = cameras.iter().map(tile_height).max().unwrap_or(1);
    let columns = LAYERS.len() as u32;
    let mut out = RgbImage::new(MONTAGE_TILE_WIDTH * columns, row_height * tiles.len().max(1) as u32);
    for (row, (layers, cam)) in tiles.iter().zip(cameras).enumerate() {
        for (col, layer) in layers.iter().enumerate() {
            let mut tile = image::imageops::resize(
                layer,
                MONTAGE_TILE_WIDTH,
                tile_height(cam),
                image::imageops::FilterType::Triangle,
            );
            let bottom = i64::from(tile.height()) - 10;
            draw_label(&mut tile, 2, bottom, &format!("{} {}", cam.name, LAYERS[col]), [255, 255, 0]);
            image::imageops::replace(
                &mut out,
                &tile,
                i64::from(col as u32 * MONTAGE_TILE_WIDTH),
                (row as u32 * row_height).into(),
            );
        }
    }
    out
}

fn dimmed(photo: &RgbImage) -> RgbImage {
    let mut img = photo.clone();
    for p in img.pixels_mut() {
        p.0 = p.0.map(|v| (f32::from(v) * BACKGROUND_DIM) as u8);
    }
    img
}

fn draw_box(img: &mut RgbImage, x: f32, y: f32, w: f32, h: f32, colour: [u8; 3], thickness: i64) {
    for t in 0..thickness.max(1) {
        let t = t as f64;
        let (x0, y0, x1, y1) = (f64::from(x) - t, f64::from(y) - t, f64::from(x + w) + t, f64::from(y + h) + t);
        draw_line(img, (x0, y0), (x1, y0), colour);
        draw_line(img, (x1, y0), (x1, y1), colour);
        draw_line(img, (x1, y1), (x0, y1), colour);
        draw_line(img, (x0, y1), (x0, y0), colour);
    }
}

/// Text size multiple for an image this wide: legible on a 1280-wide frame, one pixel per
/// font dot on a montage tile.
fn text_scale(width: u32) -> u32 {
    (width / 480).clamp(1, 4)
}

/// Draws `text` (upper-cased; characters without a glyph as `?`) with its top-left corner
/// at (`x`, `y`) on a dark band, so it reads on any background.
fn draw_label(img: &mut RgbImage, x: i64, y: i64, text: &str, colour: [u8; 3]) {
    let scale = i64::from(text_scale(img.width()));
    let advance = 6 * scale;
    let width = advance * text.chars().count() as i64 + scale;
    for yy in y..y + 9 * scale {
        for xx in x..x + width {
            if xx >= 0 && yy >= 0 && (xx as u32) < img.width() && (yy as u32) < img.height() {
                let p = img.get_pixel_mut(xx as u32, yy as u32);
                p.0 = p.0.map(|v| v / 4);
            }
        }
    }
    for (n, ch) in text.chars().enumerate() {
        let rows = glyph(ch.to_ascii_uppercase());
        let left = x + scale + n as i64 * advance;
        for (r, bits) in rows.iter().enumerate() {
            for col in 0..5 {
                if bits & (0b10000 >> col) != 0 {
                    for dy in 0..scale {
                        for dx in 0..scale {
                            let (px, py) = (left + col * scale + dx, y + scale + r as i64 * scale + dy);
                            put(img, px, py, colour);
                        }
                    }
                }
            }
        }
    }
}

/// A 5x7 bitmap glyph, one row per byte, the leftmost column in bit 4.
fn glyph(ch: char) -> [u8; 7] {
    match ch {
        '0' => [0b01110, 0b10001, 0b10011, 0b10101, 0b11001, 0b10001, 0b01110],
        '1' => [0b00100, 0b01100, 0b00100, 0b00100, 0b00100, 0b00100, 0b01110],
        '2' => [0b01110, 0b10001, 0b00001, 0b00010, 0b00100, 0b01000, 0b11111],
        '3' => [0b11111, 0b00010, 0b00100, 0b00010, 0b00001, 0b10001, 0b01110],
        '4' => [0b00010, 0b00110, 0b01010, 0b10010, 0b11111, 0b00010, 0b00010],
        '5' => [0b11111, 0b10000, 0b11110, 0b00001, 0b00001, 0b10001, 0b01110],
        '6' => [0b00110, 0b01000, 0b10000, 0b11110, 0b10001, 0b10001, 0b01110],
        '7' => [0b11111, 0b00001, 0b00010, 0b00100, 0b01000, 0b01000, 0b01000],
        '8' => [0b01110, 0b10001, 0b10001, 0b01110, 0b10001, 0b10001, 0b01110],
        '9' => [0b01110, 0b10001, 0b10001, 0b01111, 0b00001, 0b00010, 0b01100],
        'A' => [0b01110, 0b10001, 0b10001, 0b11111, 0b10001, 0b10001, 0b10001],
        'B' => [0b11110, 0b10001, 0b10001, 0b11110, 0b10001, 0b10001, 0b11110],
        'C' => [0b01110, 0b10001, 0b10000, 0b10000, 0b10000, 0b10001, 0b01110],
        'D' => [0b11100, 0b10010, 0b10001, 0b10001, 0b10001, 0b10010, 0b11100],
        'E' => [0b11111, 0b10000, 0b10000, 0b11110, 0b10000, 0b10000, 0b11111],
        'F' => [0b11111, 0b10000, 0b10000, 0b11110, 0b10000, 0b10000, 0b10000],
        'G' => [0b01110, 0b10001, 0b10000, 0b10111, 0b10001, 0b10001, 0b01111],
        'H' => [0b10001, 0b10001, 0b10001, 0b11111, 0b10001, 0b10001, 0b10001],
        'I' => [0b01110, 0b00100, 0b00100, 0b00100, 0b00100, 0b00100, 0b01110],
        'J' => [0b00111, 0b00010, 0b00010, 0b00010, 0b00010, 0b10010, 0b01100],
        'K' => [0b10001, 0b10010, 0b10100, 0b11000, 0b10100, 0b10010, 0b10001],
        'L' => [0b10000, 0b10000, 0b10000, 0b10000, 0b10000, 0b10000, 0b11111],
        'M' => [0b10001, 0b11011, 0b10101, 0b10101, 0b10001, 0b10001, 0b10001],
        'N' => [0b10001, 0b10001, 0b11001, 0b10101, 0b10011, 0b10001, 0b10001],
        'O' => [0b01110, 0b10001, 0b10001, 0b10001, 0b10001, 0b10001, 0b01110],
        'P' => [0b11110, 0b10001, 0b10001, 0b11110, 0b10000, 0b10000, 0b10000],
        'Q' => [0b01110, 0b10001, 0b10001, 0b10001, 0b10101, 0b10010, 0b01101],
        'R' => [0b11110, 0b10001, 0b10001, 0b11110, 0b10100, 0b10010, 0b10001],
        'S' => [0b01111, 0b10000, 0b10000, 0b01110, 0b00001, 0b00001, 0b11110],
        'T' => [0b11111, 0b00100, 0b00100, 0b00100, 0b00100, 0b00100, 0b00100],
        'U' => [0b10001, 0b10001, 0b10001, 0b10001, 0b10001, 0b10001, 0b01110],
        'V' => [0b10001, 0b10001, 0b10001, 0b10001, 0b10001, 0b01010, 0b00100],
        'W' => [0b10001, 0b10001, 0b10001, 0b10101, 0b10101, 0b10101, 0b01010],
        'X' => [0b10001, 0b10001, 0b01010, 0b00100, 0b01010, 0b10001, 0b10001],
        'Y' => [0b10001, 0b10001, 0b10001, 0b01010, 0b00100, 0b00100, 0b00100],
        'Z' => [0b11111, 0b00001, 0b00010, 0b00100, 0b01000, 0b10000, 0b11111],
        ' ' => [0; 7],
        '.' => [0, 0, 0, 0, 0, 0b01100, 0b01100],
        ',' => [0, 0, 0, 0, 0b01100, 0b00100, 0b01000],
        ':' => [0, 0b01100, 0b01100, 0, 0b01100, 0b01100, 0],
        '-' => [0, 0, 0, 0b11111, 0, 0, 0],
        '_' => [0, 0, 0, 0, 0, 0, 0b11111],
        '%' => [0b11000, 0b11001, 0b00010, 0b00100, 0b01000, 0b10011, 0b00011],
        '/' => [0, 0b00001, 0b00010, 0b00100, 0b01000, 0b10000, 0],
        '(' => [0b00010, 0b00100, 0b01000, 0b01000, 0b01000, 0b00100, 0b00010],
        ')' => [0b01000, 0b00100, 0b00010, 0b00010, 0b00010, 0b00100, 0b01000],
        '=' => [0, 0, 0b11111, 0, 0b11111, 0, 0],
        '+' => [0, 0b00100, 0b00100, 0b11111, 0b00100, 0b00100, 0],
        '`' | '\'' => [0b01000, 0b00100, 0, 0, 0, 0, 0],
        _ => [0b01110, 0b10001, 0b00001, 0b00010, 0b00100, 0, 0b00100],
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn labels_stay_inside_the_image_and_mark_pixels() {
        let mut img = RgbImage::new(40, 12);
        // Partly outside on every side: clipped, never a panic.
        draw_label(&mut img, -5, -3, "SKIN 12.5 % cam_0 ~", [255, 255, 255]);
        draw_label(&mut img, 30, 8, "X", [255, 255, 255]);
        assert!(img.pixels().any(|p| p.0 == [255, 255, 255]));
    }

    #[test]
    fn camera_folders_never_leave_the_output_folder() {
        assert_eq!(folder_name(0, "cam_0"), "cam_0");
        assert_eq!(folder_name(1, "../a/b"), ".._a_b");
        assert_eq!(folder_name(2, ".."), "camera_2");
        assert_eq!(folder_name(3, ""), "camera_3");
    }
}
