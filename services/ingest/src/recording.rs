//! Recordings: a folder a user can make by hand, replayed as synchronised frame sets.
//!
//! Layout:
//!
//! ```text
//! recording/
//!   rig.toml          the calibration (anipose / Pose2Sim layout, see handflow_protocol::Rig)
//!   frames.csv        header `frame,timestamp`; one row per frame: its number and capture
//!                     time in seconds, strictly increasing
//!   <camera name>/    one folder per camera of the rig, holding one image per frame, named
//!                     by the frame number (`12.png`, `000012.jpg`, `frame_0012.png`: the last
//!                     run of digits in the name); PNG or JPEG
//!   truth.json        optional ground truth
//! ```
//!
//! [`Recording::open`] checks everything that can be checked without decoding pixels: the
//! rig, the frame table, every camera folder, a missing or extra image, and every image's
//! size against the rig (from its header). Decoding errors surface when a frame is read,
//! naming the camera and frame.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use handflow_protocol::{Rig, RigError};
use rayon::prelude::*;

use crate::{decode_rgb8_into, IngestError};

/// File names inside a recording.
pub const RIG_FILE: &str = "rig.toml";
/// The frame table.
pub const FRAMES_FILE: &str = "frames.csv";
/// The optional ground truth.
pub const TRUTH_FILE: &str = "truth.json";

/// Why a recording was refused or a frame could not be read.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum RecordingError {
    /// The folder does not exist or cannot be listed.
    #[error("recording `{dir}`: {error}")]
    Folder {
        /// The folder.
        dir: PathBuf,
        /// What went wrong.
        error: std::io::Error,
    },
    /// The rig file is missing or invalid.
    #[error("recording `{dir}`: {error}")]
    Rig {
        /// The recording.
        dir: PathBuf,
        /// The rig error (names file, camera and field).
        error: RigError,
    },
    /// `frames.csv` is missing or malformed.
    #[error("`{path}`, line {line}: {problem}")]
    Frames {
        /// The frame table.
        path: PathBuf,
        /// 1-based line number (0: the file as a whole).
        line: usize,
        /// What is wrong.
        problem: String,
    },
    /// A camera's folder is missing.
    #[error("recording `{dir}`, camera `{camera}`: no folder `{camera}/` with its images")]
    CameraFolder {
        /// The recording.
        dir: PathBuf,
        /// The camera.
        camera: String,
    },
    /// A frame has no image for a camera.
    #[error("recording `{dir}`, camera `{camera}`, frame {frame}: image missing")]
    MissingImage {
        /// The recording.
        dir: PathBuf,
        /// The camera.
        camera: String,
        /// The frame number.
        frame: u64,
    },
    /// An image belongs to no frame of the table, or two images claim one frame.
    #[error("recording `{dir}`, camera `{camera}`: `{file}` {problem}")]
    ExtraImage {
        /// The recording.
        dir: PathBuf,
        /// The camera.
        camera: String,
        /// The file.
        file: String,
        /// Why it is extra.
        problem: String,
    },
    /// An image's size differs from the rig's.
    #[error("recording `{dir}`, camera `{camera}`, frame {frame}: `{file}` is {got_width}x{got_height}, the rig says {width}x{height}")]
    ImageSize {
        /// The recording.
        dir: PathBuf,
        /// The camera.
        camera: String,
        /// The frame number.
        frame: u64,
        /// The file.
        file: PathBuf,
        /// Rig width.
        width: u32,
        /// Rig height.
        height: u32,
        /// Image width.
        got_width: u32,
        /// Image height.
        got_height: u32,
    },
    /// An image could not be read or decoded.
    #[error("camera `{camera}`, frame {frame}: {error}")]
    Image {
        /// The camera.
        camera: String,
        /// The frame number.
        frame: u64,
        /// The decoder's error (names the file).
        error: IngestError,
    },
    /// A frame index beyond the recording, or a destination of the wrong size.
    #[error("{0}")]
    Request(String),
}

/// One frame of a recording.
#[derive(Clone, Debug, PartialEq)]
pub struct FrameEntry {
    /// Frame number from `frames.csv`.
    pub frame: u64,
    /// Capture time, seconds.
    pub timestamp: f64,
    /// One image per camera, in rig order.
    pub images: Vec<PathBuf>,
}

/// A checked recording, ready to be read frame by frame.
#[derive(Clone, Debug)]
pub struct Recording {
    dir: PathBuf,
    rig: Rig,
    frames: Vec<FrameEntry>,
    truth: Option<PathBuf>,
    /// Every frame set decoded, back to back, after [`Recording::preload`].
    decoded: Option<Vec<u8>>,
}

/// The most [`Recording::preload`] holds in memory: 4 GiB, about 1500 frame sets of three
/// 640x480 views (50 s at 30 fps).
pub const PRELOAD_LIMIT_BYTES: usize = 4 << 30;

/// What [`Recording::read_frame_into`] read.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrameInfo {
    /// Position in the replay (counts on across loops).
    pub sequence: u64,
    /// Frame number from `frames.csv`.
    pub frame: u64,
    /// Capture time, seconds; when looping, later passes are shifted by the recording's
    /// duration plus one frame interval so time keeps increasing.
    pub timestamp: f64,
}

impl Recording {
    /// Opens and checks a recording folder.
    pub fn open(dir: impl AsRef<Path>) -> Result<Recording, RecordingError> {
        let dir = dir.as_ref().to_path_buf();
        if let Err(error) = std::fs::read_dir(&dir) {
            return Err(RecordingError::Folder { dir, error });
        }
        let rig = Rig::load(dir.join(RIG_FILE)).map_err(|error| RecordingError::Rig { dir: dir.clone(), error })?;
        let table = read_frame_table(&dir.join(FRAMES_FILE))?;
        let mut per_camera: Vec<BTreeMap<u64, PathBuf>> = Vec::with_capacity(rig.cameras.len());
        for camera in &rig.cameras {
            per_camera.push(camera_images(&dir, &camera.name)?);
        }
        let mut frames = Vec::with_capacity(table.len());
        for &(frame, timestamp) in &table {
            let mut images = Vec::with_capacity(rig.cameras.len());
            for (camera, files) in rig.cameras.iter().zip(&per_camera) {
                let Some(path) = files.get(&frame) else {
                    return Err(RecordingError::MissingImage { dir, camera: camera.name.clone(), frame });
                };
                images.push(path.clone());
            }
            frames.push(FrameEntry { frame, timestamp, images });
        }
        let known: std::collections::BTreeSet<u64> = table.iter().map(|&(f, _)| f).collect();
        for (camera, files) in rig.cameras.iter().zip(&per_camera) {
            if let Some((frame, path)) = files.iter().find(|(f, _)| !known.contains(f)) {
                return Err(RecordingError::ExtraImage {
                    dir,
                    camera: camera.name.clone(),
                    file: file_name(path),
                    problem: format!("is frame {frame}, which frames.csv does not list"),
                });
            }
        }
        // Sizes from the headers only: cheap, and a wrong size is refused before replay.
        let checks: Vec<(usize, usize)> =
            (0..frames.len()).flat_map(|f| (0..rig.cameras.len()).map(move |c| (f, c))).collect();
        checks.par_iter().try_for_each(|&(f, c)| {
            let camera = &rig.cameras[c];
            let path = &frames[f].images[c];
            let frame = frames[f].frame;
            let (w, h) = image::image_dimensions(path).map_err(|source| RecordingError::Image {
                camera: camera.name.clone(),
                frame,
                error: IngestError::Decode { path: path.clone(), source },
            })?;
            if (w, h) != (camera.width, camera.height) {
                return Err(RecordingError::ImageSize {
                    dir: dir.clone(),
                    camera: camera.name.clone(),
                    frame,
                    file: path.clone(),
                    width: camera.width,
                    height: camera.height,
                    got_width: w,
                    got_height: h,
                });
            }
            Ok(())
        })?;
        let truth = Some(dir.join(TRUTH_FILE)).filter(|p| p.is_file());
        Ok(Recording { dir, rig, frames, truth, decoded: None })
    }

    /// The recording's folder.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The rig.
    pub fn rig(&self) -> &Rig {
        &self.rig
    }

    /// Frame rate from the timestamps, frames per second (30 when there are fewer than two
    /// frames or the timestamps do not increase).
    pub fn frame_rate(&self) -> f64 {
        match (self.frames.first(), self.frames.last()) {
            (Some(a), Some(b)) if self.frames.len() > 1 && b.timestamp > a.timestamp => {
                (self.frames.len() - 1) as f64 / (b.timestamp - a.timestamp)
            }
            _ => 30.0,
        }
    }

    /// Every frame, in order.
    pub fn frames(&self) -> &[FrameEntry] {
        &self.frames
    }

    /// Number of frames.
    pub fn len(&self) -> usize {
        self.frames.len()
    }

    /// True for a recording without frames (refused by `open`, so never in practice).
    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }

    /// `truth.json`, when the recording has one.
    pub fn truth_path(&self) -> Option<&Path> {
        self.truth.as_deref()
    }

    /// Bytes of one frame set: every camera's RGB8 view, back to back in rig order.
    pub fn frame_set_len(&self) -> usize {
        self.view_lengths().iter().sum()
    }

    /// The views of a frame set buffer filled by [`Recording::read_frame_into`], in rig
    /// order (a shorter buffer gives only the views it holds).
    pub fn views<'a>(&self, frame_set: &'a [u8]) -> Vec<&'a [u8]> {
        let mut rest = frame_set;
        let mut views = Vec::with_capacity(self.rig.cameras.len());
        for len in self.view_lengths() {
            if rest.len() < len {
                break;
            }
            let (view, tail) = rest.split_at(len);
            views.push(view);
            rest = tail;
        }
        views
    }

    fn view_lengths(&self) -> Vec<usize> {
        self.rig.cameras.iter().map(|c| c.width as usize * c.height as usize * 3).collect()
    }

    /// Decodes every frame set into memory now, so that [`Recording::read_frame_into`]
    /// becomes one copy: fake cameras that deliver raw frames, as real ones do, with no
    /// decoding on the pipeline's path. Refuses a recording larger than
    /// [`PRELOAD_LIMIT_BYTES`]; a frame that does not decode is named as when it is read.
    pub fn preload(&mut self) -> Result<(), RecordingError> {
        let set_len = self.frame_set_len();
        let total = set_len.checked_mul(self.frames.len()).filter(|&t| t <= PRELOAD_LIMIT_BYTES);
        let Some(total) = total else {
            return Err(RecordingError::Request(format!(
                "recording `{}`: {} frame sets of {} bytes do not fit the preload limit of {} MiB; replay it \
                 without preloading",
                self.dir.display(),
                self.frames.len(),
                set_len,
                PRELOAD_LIMIT_BYTES >> 20
            )));
        };
        let mut decoded = vec![0u8; total];
        for (index, dst) in decoded.chunks_exact_mut(set_len.max(1)).enumerate() {
            self.decode_into(index, dst)?;
        }
        self.decoded = Some(decoded);
        Ok(())
    }

    /// Whether [`Recording::preload`] has run.
    pub fn is_preloaded(&self) -> bool {
        self.decoded.is_some()
    }

    /// Reads replay position `sequence` (frame `sequence % len` when `looped`) into `dst`,
    /// every camera's view back to back in rig order: copied from memory when preloaded,
    /// else decoded, cameras in parallel.
    pub fn read_frame_into(&self, sequence: u64, looped: bool, dst: &mut [u8]) -> Result<FrameInfo, RecordingError> {
        let n = self.frames.len() as u64;
        if n == 0 || (!looped && sequence >= n) {
            return Err(RecordingError::Request(format!(
                "recording `{}` has {n} frames; frame {sequence} does not exist",
                self.dir.display()
            )));
        }
        let expected = self.frame_set_len();
        if dst.len() != expected {
            return Err(RecordingError::Request(format!(
                "frame set buffer holds {} bytes, {expected} needed for {} views",
                dst.len(),
                self.rig.cameras.len()
            )));
        }
        let index = (sequence % n) as usize;
        let pass = sequence / n;
        match &self.decoded {
            Some(decoded) => dst.copy_from_slice(&decoded[index * expected..(index + 1) * expected]),
            None => self.decode_into(index, dst)?,
        }
        let entry = &self.frames[index];
        Ok(FrameInfo { sequence, frame: entry.frame, timestamp: entry.timestamp + pass as f64 * self.loop_period() })
    }

    /// Decodes frame set `index` into `dst` (its exact size), cameras in parallel.
    fn decode_into(&self, index: usize, dst: &mut [u8]) -> Result<(), RecordingError> {
        let entry = &self.frames[index];
        let mut views: Vec<&mut [u8]> = Vec::with_capacity(self.rig.cameras.len());
        let mut rest = dst;
        for len in self.view_lengths() {
            let (view, tail) = rest.split_at_mut(len);
            views.push(view);
            rest = tail;
        }
        views.into_par_iter().zip(self.rig.cameras.par_iter()).zip(entry.images.par_iter()).try_for_each(
            |((view, camera), path)| {
                decode_rgb8_into(path, camera.width, camera.height, view).map_err(|error| RecordingError::Image {
                    camera: camera.name.clone(),
                    frame: entry.frame,
                    error,
                })
            },
        )?;
        Ok(())
    }

    /// Time shift between loop passes: the duration plus one mean frame interval.
    fn loop_period(&self) -> f64 {
        match (self.frames.first(), self.frames.last()) {
            (Some(a), Some(b)) if self.frames.len() > 1 => {
                let span = b.timestamp - a.timestamp;
                span + span / (self.frames.len() - 1) as f64
            }
            _ => 1.0,
        }
    }
}

/// Parses `frames.csv`: a `frame,timestamp` header, then rows with a frame number and a
/// finite timestamp in seconds, both strictly increasing.
fn read_frame_table(path: &Path) -> Result<Vec<(u64, f64)>, RecordingError> {
    let err = |line: usize, problem: String| RecordingError::Frames { path: path.to_path_buf(), line, problem };
    let text = std::fs::read_to_string(path).map_err(|e| err(0, format!("cannot be read: {e}")))?;
    let mut lines = text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty());
    match lines.next() {
        Some((_, header)) => {
            let cols: Vec<String> = header.split(',').map(|c| c.trim().to_ascii_lowercase()).collect();
            if cols != ["frame", "timestamp"] {
                return Err(err(1, format!("expected the header `frame,timestamp`, found `{}`", header.trim())));
            }
        }
        None => return Err(err(0, "is empty (expected a `frame,timestamp` header and one row per frame)".into())),
    }
    let mut rows: Vec<(u64, f64)> = Vec::new();
    for (i, line) in lines {
        let n = i + 1;
        let fields: Vec<&str> = line.split(',').map(str::trim).collect();
        let [frame, timestamp] = fields[..] else {
            return Err(err(n, format!("expected 2 fields (frame,timestamp), found {}", fields.len())));
        };
        let frame: u64 = frame.parse().map_err(|_| err(n, format!("frame `{frame}` is not a non-negative integer")))?;
        let timestamp: f64 =
            timestamp.parse().map_err(|_| err(n, format!("timestamp `{timestamp}` is not a number")))?;
        if !timestamp.is_finite() {
            return Err(err(n, format!("frame {frame}: timestamp {timestamp} is not finite")));
        }
        if let Some(&(prev_frame, prev_time)) = rows.last() {
            if frame <= prev_frame {
                return Err(err(
                    n,
                    format!("frame {frame} does not follow frame {prev_frame} (frame numbers must increase)"),
                ));
            }
            if timestamp <= prev_time {
                return Err(err(
                    n,
                    format!("frame {frame}: timestamp {timestamp} is not after frame {prev_frame}'s {prev_time} (timestamps must increase)"),
                ));
            }
        }
        rows.push((frame, timestamp));
    }
    if rows.is_empty() {
        return Err(err(0, "lists no frame".into()));
    }
    Ok(rows)
}

/// The images of one camera folder, by frame number.
fn camera_images(dir: &Path, camera: &str) -> Result<BTreeMap<u64, PathBuf>, RecordingError> {
    let folder = dir.join(camera);
    let entries = std::fs::read_dir(&folder)
        .map_err(|_| RecordingError::CameraFolder { dir: dir.to_path_buf(), camera: camera.to_string() })?;
    let mut images = BTreeMap::new();
    for entry in entries {
        let entry = entry.map_err(|error| RecordingError::Folder { dir: folder.clone(), error })?;
        let path = entry.path();
        let ext = path.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase);
        if !matches!(ext.as_deref(), Some("png" | "jpg" | "jpeg")) {
            continue; // masks, notes and other files live beside the images
        }
        let extra = |problem: String| RecordingError::ExtraImage {
            dir: dir.to_path_buf(),
            camera: camera.to_string(),
            file: file_name(&path),
            problem,
        };
        let Some(frame) = frame_number(&path) else {
            return Err(extra("has no frame number in its name".into()));
        };
        if let Some(other) = images.insert(frame, path.clone()) {
            return Err(extra(format!("is frame {frame}, as is `{}`", file_name(&other))));
        }
    }
    Ok(images)
}

/// The last run of digits in a file's stem.
fn frame_number(path: &Path) -> Option<u64> {
    let stem = path.file_stem()?.to_str()?;
    let end = stem.rfind(|c: char| c.is_ascii_digit())? + 1;
    let start = stem[..end].rfind(|c: char| !c.is_ascii_digit()).map_or(0, |i| i + 1);
    stem[start..end].parse().ok()
}

fn file_name(path: &Path) -> String {
    path.file_name().map_or_else(|| path.display().to_string(), |n| n.to_string_lossy().into_owned())
}

#[cfg(test)]
mod tests {
    use super::*;
    use handflow_protocol::{Camera, Distortion};
    use nalgebra::{Matrix3, Rotation3, Vector3};

    const W: u32 = 8;
    const H: u32 = 6;

    fn rig() -> Rig {
        let cam = |name: &str, x: f64| {
            Camera::new(
                name,
                W,
                H,
                Matrix3::new(10.0, 0.0, 3.5, 0.0, 10.0, 2.5, 0.0, 0.0, 1.0),
                Distortion::default(),
                Rotation3::identity(),
                Vector3::new(x, 0.0, 0.0),
            )
            .expect("camera")
        };
        Rig { cameras: vec![cam("left", 0.0), cam("right", -0.2)] }
    }

    /// A valid 3-frame recording; the pixel (0, 0) of camera c at frame f is (f, c, 7).
    fn make(dir: &Path) {
        rig().save(dir.join(RIG_FILE)).expect("rig");
        std::fs::write(dir.join(FRAMES_FILE), "frame,timestamp\n0,0.0\n1,0.04\n2,0.08\n").expect("csv");
        for (c, name) in ["left", "right"].iter().enumerate() {
            std::fs::create_dir_all(dir.join(name)).expect("folder");
            for f in 0..3u8 {
                let img = image::RgbImage::from_fn(W, H, |x, y| image::Rgb([f, c as u8, (x + y) as u8 + 7]));
                img.save(dir.join(name).join(format!("{:06}.png", f))).expect("png");
            }
        }
    }

    fn open_err(edit: impl FnOnce(&Path)) -> String {
        let tmp = tempfile::tempdir().expect("tempdir");
        make(tmp.path());
        edit(tmp.path());
        Recording::open(tmp.path()).expect_err("refused").to_string()
    }

    #[test]
    fn a_recording_reads_frame_sets_in_rig_order_and_loops() {
        let tmp = tempfile::tempdir().expect("tempdir");
        make(tmp.path());
        let rec = Recording::open(tmp.path()).expect("opens");
        assert_eq!(rec.len(), 3);
        assert!(rec.truth_path().is_none());
        let mut buf = vec![0u8; rec.frame_set_len()];
        let info = rec.read_frame_into(2, false, &mut buf).expect("reads");
        assert_eq!((info.frame, info.timestamp), (2, 0.08));
        let view = (W * H * 3) as usize;
        assert_eq!(&buf[..3], &[2, 0, 7], "left view first");
        assert_eq!(&buf[view..view + 3], &[2, 1, 7], "then right");
        let views = rec.views(&buf);
        assert_eq!(views.len(), 2);
        assert_eq!((views[0].len(), &views[1][..3]), (view, &[2u8, 1, 7][..]));
        assert_eq!(rec.views(&buf[..view + 1]).len(), 1, "a short buffer gives the views it holds");
        // Not looped, the end is an error; looped, time keeps increasing.
        assert!(rec.read_frame_into(3, false, &mut buf).is_err());
        let info = rec.read_frame_into(4, true, &mut buf).expect("loops");
        assert_eq!(info.frame, 1);
        assert!((info.timestamp - (0.04 + 0.12)).abs() < 1e-12, "{}", info.timestamp);
        assert_eq!(&buf[..3], &[1, 0, 7]);
        let mut short = vec![0u8; 10];
        assert!(rec.read_frame_into(0, false, &mut short).unwrap_err().to_string().contains("buffer"));
    }

    #[test]
    fn frame_numbers_come_from_the_last_digits_of_the_name() {
        assert_eq!(frame_number(Path::new("000012.png")), Some(12));
        assert_eq!(frame_number(Path::new("cam2_frame_0034.jpg")), Some(34));
        assert_eq!(frame_number(Path::new("frame.png")), None);
    }

    #[test]
    fn every_bad_recording_is_refused_naming_camera_and_frame() {
        let e = open_err(|d| std::fs::remove_file(d.join("right/000001.png")).expect("rm"));
        assert!(e.contains("camera `right`") && e.contains("frame 1") && e.contains("missing"), "{e}");
        let e =
            open_err(|d| std::fs::copy(d.join("left/000000.png"), d.join("left/000007.png")).map(|_| ()).expect("cp"));
        assert!(e.contains("camera `left`") && e.contains("000007.png") && e.contains("frame 7"), "{e}");
        let e = open_err(|d| std::fs::copy(d.join("left/000000.png"), d.join("left/0.png")).map(|_| ()).expect("cp"));
        assert!(e.contains("is frame 0, as is"), "{e}");
        let e = open_err(|d| {
            image::RgbImage::new(W + 1, H).save(d.join("right/000002.png")).expect("png");
        });
        assert!(e.contains("camera `right`") && e.contains("frame 2") && e.contains("9x6") && e.contains("8x6"), "{e}");
        let e = open_err(|d| std::fs::write(d.join("left/000001.png"), b"not a png").expect("write"));
        assert!(e.contains("camera `left`") && e.contains("frame 1") && e.contains("000001.png"), "{e}");
        let e =
            open_err(|d| std::fs::write(d.join(FRAMES_FILE), "frame,timestamp\n0,0.0\n1,0.04\n2,0.04\n").expect("csv"));
        assert!(
            e.contains("frames.csv")
                && e.contains("line 4")
                && e.contains("frame 2")
                && e.contains("timestamps must increase"),
            "{e}"
        );
        let e = open_err(|d| std::fs::write(d.join(FRAMES_FILE), "frame,time\n0,0\n").expect("csv"));
        assert!(e.contains("header"), "{e}");
        let e = open_err(|d| std::fs::write(d.join(FRAMES_FILE), "frame,timestamp\n0,abc\n").expect("csv"));
        assert!(e.contains("line 2") && e.contains("abc"), "{e}");
        let e = open_err(|d| std::fs::remove_dir_all(d.join("right")).expect("rm"));
        assert!(e.contains("camera `right`") && e.contains("folder"), "{e}");
        let e = open_err(|d| std::fs::remove_file(d.join(RIG_FILE)).expect("rm"));
        assert!(e.contains("rig.toml"), "{e}");
        let e = open_err(|d| std::fs::remove_file(d.join(FRAMES_FILE)).expect("rm"));
        assert!(e.contains("frames.csv"), "{e}");
    }

    #[test]
    fn an_image_broken_after_opening_fails_its_frame_only() {
        let tmp = tempfile::tempdir().expect("tempdir");
        make(tmp.path());
        let rec = Recording::open(tmp.path()).expect("opens");
        std::fs::write(tmp.path().join("right/000001.png"), b"broken later").expect("write");
        let mut buf = vec![0u8; rec.frame_set_len()];
        let e = rec.read_frame_into(1, false, &mut buf).unwrap_err().to_string();
        assert!(e.contains("camera `right`") && e.contains("frame 1"), "{e}");
        // The other frames still read: nothing already accepted is lost.
        rec.read_frame_into(2, false, &mut buf).expect("frame 2 still reads");
    }

    #[test]
    fn a_preloaded_recording_reads_the_same_frame_sets_and_names_a_broken_frame() {
        let tmp = tempfile::tempdir().expect("tempdir");
        make(tmp.path());
        let decoding = Recording::open(tmp.path()).expect("opens");
        let mut preloaded = Recording::open(tmp.path()).expect("opens");
        preloaded.preload().expect("preloads");
        assert!(preloaded.is_preloaded() && !decoding.is_preloaded());
        let (mut a, mut b) = (vec![0u8; decoding.frame_set_len()], vec![1u8; decoding.frame_set_len()]);
        for sequence in [0, 1, 2, 4, 7] {
            let expected = decoding.read_frame_into(sequence, true, &mut a).expect("decodes");
            assert_eq!(preloaded.read_frame_into(sequence, true, &mut b).expect("copies"), expected);
            assert_eq!(a, b, "replay position {sequence}");
        }
        assert!(preloaded.read_frame_into(3, false, &mut b).is_err(), "the end is still the end");
        let mut broken = Recording::open(tmp.path()).expect("opens");
        std::fs::write(tmp.path().join("left/000002.png"), b"broken after opening").expect("write");
        let e = broken.preload().unwrap_err().to_string();
        assert!(e.contains("camera `left`") && e.contains("frame 2"), "{e}");
    }
}
