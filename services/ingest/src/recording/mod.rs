//! Recordings: a folder a user can make by hand, or as capture tools write it, replayed as
//! synchronised frame sets.
//!
//! Two layouts, told apart by what the folder holds:
//!
//! ```text
//! recording/                      recording/
//!   rig.toml                        camera_array.toml (or rig.toml, or another calibration)
//!   frames.csv                      cam_0.mp4 cam_1.mp4 ...   one video per camera
//!   <camera name>/000012.png ...    timestamps.csv            optional: caliscope's capture times
//!   truth.json (optional)           frames.csv                optional: `frame,timestamp`
//! ```
//!
//! - **Image folders**: one folder per camera of the rig, one image per frame named by the
//!   frame number (`12.png`, `000012.jpg`, `frame_0012.png`: the last run of digits), PNG or
//!   JPEG, and `frames.csv` (`frame,timestamp` header, one row per frame, seconds, both
//!   increasing).
//! - **Videos**: one video per camera (mp4, mkv, avi, mov, webm; any codec GStreamer's
//!   plugins decode: H.264, H.265, VP9, MPEG-4, MJPEG, FFV1...), matched to the rig's cameras
//!   by name, else by the number in the name ([`crate::camera_match`]). Frame times come from
//!   `frames.csv` when present (row r is frame r of every video); else from a caliscope
//!   `timestamps.csv` (frames with one `sync_index` form a set; frame numbers count
//!   `sync_index` from the first; a set some camera lacks, a webcam's dropped frame, is read
//!   without that view, as a live stream gets it, while two views remain); else from
//!   the containers' timestamps (frame k of every video is set k). A video up to 15 pixels
//!   narrower or shorter than its calibration (encoders pad to multiples of 16) is accepted
//!   with a note and the intrinsics unchanged.
//!
//! Where the tools people use put things is looked for too: Pose2Sim's `videos/` and
//! `calibration/` folders of a session, FreeMoCap's `synchronized_videos/` and
//! `<session>_camera_calibration.toml`, caliscope's older `frame_time_history.csv` (cameras
//! as `port`, sets grouped by capture time when it has no `sync_index`), and a caliscope
//! `camera_array.toml` (or an older version's `config.toml`) up to two folders above a
//! recording (`recordings/<name>/`).
//!
//! The calibration is the folder's `rig.toml` or `camera_array.toml`, else its
//! `calibration/` folder's, else its only calibration file (see
//! [`handflow_protocol::Rig::find_in_dir`]), else one up to two folders above, unless
//! [`OpenOptions::calibration`] names one.
//!
//! [`Recording::open`] checks everything that can be checked without decoding pixels (the
//! calibration, the frame table, every camera's images or video, sizes from headers).
//! Decoding errors surface when a frame is read, naming the camera and frame, and leave the
//! other frames readable.

use std::path::{Path, PathBuf};
use std::sync::Mutex;

use handflow_protocol::{Camera, Rig, RigError, RigFormat};
use rayon::prelude::*;

use crate::{camera_match, decode_rgb8_into, IngestError};

pub mod image_folders;
mod images;
mod timing;
pub mod video;
pub mod yuv;

pub use timing::{
    read_caliscope_timestamps, read_frame_table, SyncedSet, CALISCOPE_FRAME_HISTORY_FILE, CALISCOPE_TIMESTAMPS_FILE,
    FRAMES_FILE,
};
use video::{FrameTurn, VideoError, VideoProbe, VideoReader};

/// The calibration of the image-folder layout.
pub const RIG_FILE: &str = "rig.toml";
/// The optional ground truth.
pub const TRUTH_FILE: &str = "truth.json";
/// Where Pose2Sim keeps a session's videos.
pub const VIDEOS_DIR: &str = "videos";
/// Where FreeMoCap keeps a recording's videos (one per camera, cut to the same frames).
pub const FREEMOCAP_VIDEOS_DIR: &str = "synchronized_videos";
/// How FreeMoCap names a recording's calibration: `<session>_camera_calibration.toml`.
pub const FREEMOCAP_CALIBRATION_SUFFIX: &str = "_camera_calibration.toml";
/// Where Pose2Sim keeps a session's calibration.
pub const CALIBRATION_DIR: &str = "calibration";
/// Video file extensions a recording's folder is searched for (lower case).
pub const VIDEO_EXTENSIONS: [&str; 5] = ["mp4", "mkv", "avi", "mov", "webm"];
/// Encoders pad frame sizes to multiples of 16: a video this much smaller than its
/// calibration, or less, in each dimension is the calibrated image without the padding.
pub const MAX_PADDING_PX: u32 = 15;

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
    /// A video is missing, unreadable, or of the wrong size; or a frame of it cannot be decoded.
    #[error("camera `{camera}`{}: {error}", frame.map(|f| format!(", frame {f}")).unwrap_or_default())]
    Video {
        /// The camera.
        camera: String,
        /// The frame number, when one frame is at fault.
        frame: Option<u64>,
        /// What the decoder said (names the file).
        error: VideoError,
    },
    /// The folder's cameras and videos (or other per-camera items) do not match.
    #[error("recording `{dir}`: {problem}")]
    Layout {
        /// The recording.
        dir: PathBuf,
        /// What does not match, listing both sides.
        problem: String,
    },
    /// A frame that failed when the recording was preloaded.
    #[error("frame {frame}: {message}")]
    Preloaded {
        /// The frame number.
        frame: u64,
        /// The error met when preloading it.
        message: String,
    },
    /// A frame index beyond the recording, or a destination of the wrong size.
    #[error("{0}")]
    Request(String),
}

/// One frame of a recording.
impl RecordingError {
    /// True when one frame set could not be read and the rest of the recording can: the
    /// caller skips it (counted as dropped) and goes on.
    pub fn is_bad_frame(&self) -> bool {
        matches!(self, RecordingError::Image { .. } | RecordingError::Preloaded { .. })
            || matches!(self, RecordingError::Video { frame: Some(_), .. })
    }
}

/// One frame set of a recording.
#[derive(Clone, Debug, PartialEq)]
pub struct FrameEntry {
    /// Frame number: from `frames.csv`, or counted from 0 at the first frame set.
    pub frame: u64,
    /// Capture time, seconds (the mean of the cameras' capture times when each has its own).
    pub timestamp: f64,
    /// Largest difference between the cameras' capture times of this set, seconds, when the
    /// recording says each camera's time.
    pub capture_spread_s: Option<f64>,
    /// Bit `k` set: camera `k` (rig order) has no frame in this set (a webcam dropped it).
    /// Its view reads as zeros, and the stages leave it out as a live camera's missing view.
    pub missing_views: u32,
}

/// Which layout a recording has.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Layout {
    /// One folder of images per camera.
    ImageFolders,
    /// One video per camera.
    Videos,
}

/// How to open a recording: which calibration, and which part of it.
#[derive(Clone, Debug, Default)]
pub struct OpenOptions {
    /// The calibration file to use instead of the folder's own.
    pub calibration: Option<PathBuf>,
    /// First frame number to read (seeks in videos); frames before it are left out.
    pub start: Option<u64>,
    /// Read at most this many frame sets.
    pub frames: Option<usize>,
}

/// Per camera of a frame set, the position of its frame in the camera's video (`None`: the
/// camera has no frame in the set).
pub type SetPositions = Vec<Option<usize>>;

/// Where a recording's pixels are.
enum Pixels {
    /// Per frame set, per camera, the image file.
    Images(Vec<Vec<PathBuf>>),
    /// Per camera a decoder; per frame set, per camera, the frame's position in its video
    /// (`None`: the camera has no frame in the set).
    Videos { readers: Vec<Mutex<VideoReader>>, positions: Vec<SetPositions>, codecs: Vec<String> },
}

/// A checked recording, ready to be read frame by frame.
pub struct Recording {
    dir: PathBuf,
    calibration: Vec<PathBuf>,
    rig: Rig,
    frames: Vec<FrameEntry>,
    truth: Option<PathBuf>,
    pixels: Pixels,
    notes: Vec<String>,
    /// Every frame set decoded, back to back, after [`Recording::preload`], and the error of
    /// each set that did not decode.
    decoded: Option<(Vec<u8>, Vec<Option<String>>)>,
}

impl std::fmt::Debug for Recording {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Recording")
            .field("dir", &self.dir)
            .field("layout", &self.layout())
            .field("frames", &self.frames.len())
            .finish()
    }
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
    /// Cameras without a frame in this set ([`FrameEntry::missing_views`]).
    pub missing_views: u32,
}

/// Capture-time spread within frame sets, over a recording.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CaptureSpread {
    /// Median over sets, seconds.
    pub median_s: f64,
    /// Largest, seconds.
    pub max_s: f64,
}

impl Recording {
    /// Opens and checks a recording folder with its own calibration, every frame.
    pub fn open(dir: impl AsRef<Path>) -> Result<Recording, RecordingError> {
        Recording::open_with(dir, &OpenOptions::default())
    }

    /// Opens and checks a recording folder as `options` say.
    pub fn open_with(dir: impl AsRef<Path>, options: &OpenOptions) -> Result<Recording, RecordingError> {
        let dir = dir.as_ref().to_path_buf();
        let mut entries = list_dir(&dir)?;
        let rig_error = |error| RecordingError::Rig { dir: dir.clone(), error };
        let calibration = match &options.calibration {
            Some(path) => vec![path.clone()],
            None => find_calibration(&dir).map_err(rig_error)?,
        };
        let rig = match &calibration[..] {
            [one] => Rig::load(one),
            several => Rig::load_files(several),
        }
        .map_err(rig_error)?;
        let mut notes: Vec<String> = rig.notes.clone();
        // Pose2Sim keeps a session's videos in `videos/`, FreeMoCap in `synchronized_videos/`.
        let mut video_dir = dir.clone();
        if !entries.iter().any(|p| is_video(p)) {
            if let Some(found) = [VIDEOS_DIR, FREEMOCAP_VIDEOS_DIR].iter().map(|d| dir.join(d)).find(|d| d.is_dir()) {
                video_dir = found;
                entries = list_dir(&video_dir)?;
            }
        }
        let videos: Vec<PathBuf> = entries.iter().filter(|p| is_video(p)).cloned().collect();
        let has_camera_folders = rig.cameras.iter().any(|c| dir.join(&c.name).is_dir());
        if videos.is_empty() && !has_camera_folders && !dir.join(FRAMES_FILE).is_file() {
            let names: Vec<&str> = rig.cameras.iter().map(|c| c.name.as_str()).collect();
            return Err(RecordingError::Layout {
                dir,
                problem: format!(
                    "no video ({}) here or in `{VIDEOS_DIR}/` or `{FREEMOCAP_VIDEOS_DIR}/`, and no image folder named \
                     after a camera of the calibration ({})",
                    VIDEO_EXTENSIONS.join(", "),
                    names.join(", ")
                ),
            });
        }
        let mut recording = if !videos.is_empty() && !has_camera_folders {
            open_videos(&dir, &video_dir, rig, &videos, &mut notes)?
        } else {
            let (rig, frames, images) = open_images(&dir, rig)?;
            (rig, frames, Pixels::Images(images))
        };
        // The part asked for.
        let (_, frames, pixels) = &mut recording;
        let first =
            options.start.map_or(0, |start| frames.iter().position(|f| f.frame >= start).unwrap_or(frames.len()));
        let count = options.frames.unwrap_or(usize::MAX).min(frames.len() - first);
        if count == 0 {
            return Err(RecordingError::Request(format!(
                "recording `{}`: no frame set from frame {} on (it has {} frame sets, frames {}..={})",
                dir.display(),
                options.start.unwrap_or(0),
                frames.len(),
                frames.first().map_or(0, |f| f.frame),
                frames.last().map_or(0, |f| f.frame)
            )));
        }
        frames.drain(..first);
        frames.truncate(count);
        match pixels {
            Pixels::Images(images) => {
                images.drain(..first);
                images.truncate(count);
            }
            Pixels::Videos { positions, .. } => {
                positions.drain(..first);
                positions.truncate(count);
            }
        }
        let (rig, frames, pixels) = recording;
        for note in &notes {
            tracing::warn!("recording `{}`: {note}", dir.display());
        }
        let truth = Some(dir.join(TRUTH_FILE)).filter(|p| p.is_file());
        Ok(Recording { dir, calibration, rig, frames, truth, pixels, notes, decoded: None })
    }

    /// The recording's folder.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The calibration file(s) the rig was read from (several: one per camera).
    pub fn calibration_paths(&self) -> &[PathBuf] {
        &self.calibration
    }

    /// The rig (camera sizes as the frames have them: see [`MAX_PADDING_PX`]).
    pub fn rig(&self) -> &Rig {
        &self.rig
    }

    /// Which layout the folder has.
    pub fn layout(&self) -> Layout {
        match self.pixels {
            Pixels::Images(_) => Layout::ImageFolders,
            Pixels::Videos { .. } => Layout::Videos,
        }
    }

    /// What opening noticed and accepted: padded videos, frame sets some camera lacks,
    /// cameras the calibration leaves out.
    pub fn notes(&self) -> &[String] {
        &self.notes
    }

    /// One line on what was opened: layout, codecs, frame sets, rate and capture spread.
    pub fn summary(&self) -> String {
        let what = match &self.pixels {
            Pixels::Images(_) => format!("{} image folders", self.rig.cameras.len()),
            Pixels::Videos { codecs, .. } => {
                let mut codecs = codecs.clone();
                codecs.dedup();
                format!("{} videos ({})", self.rig.cameras.len(), codecs.join(", "))
            }
        };
        let size = self.rig.cameras.first().map_or(String::new(), |c| format!(" of {}x{}", c.width, c.height));
        let spread = self.capture_spread().map_or(String::new(), |s| {
            format!(
                "; capture times within a set differ by {:.0} ms median, {:.0} ms at most",
                s.median_s * 1e3,
                s.max_s * 1e3
            )
        });
        format!(
            "{what}{size}, {} frame sets ({}..={}) at {:.2} fps, calibration {}{spread}",
            self.frames.len(),
            self.frames.first().map_or(0, |f| f.frame),
            self.frames.last().map_or(0, |f| f.frame),
            self.frame_rate(),
            self.calibration.iter().map(|p| format!("`{}`", p.display())).collect::<Vec<_>>().join(", ")
        )
    }

    /// The spread of capture times within frame sets, when the recording gives each
    /// camera's time.
    pub fn capture_spread(&self) -> Option<CaptureSpread> {
        let mut spreads: Vec<f64> = self.frames.iter().filter_map(|f| f.capture_spread_s).collect();
        if spreads.is_empty() {
            return None;
        }
        spreads.sort_by(f64::total_cmp);
        Some(CaptureSpread { median_s: spreads[spreads.len() / 2], max_s: spreads[spreads.len() - 1] })
    }

    /// Frame rate from the timestamps, frames per second (30 when there are fewer than two
    /// frames or the timestamps do not increase).
    pub fn frame_rate(&self) -> f64 {
        match (self.frames.first(), self.frames.last()) {
            // Frame sets per second, as the stages see them arrive (sets left out widen the
            // mean interval, as they do in the stream).
            (Some(a), Some(b)) if self.frames.len() > 1 && b.timestamp > a.timestamp => {
                (self.frames.len() - 1) as f64 / (b.timestamp - a.timestamp)
            }
            _ => 30.0,
        }
    }

    /// Every frame set, in order.
    pub fn frames(&self) -> &[FrameEntry] {
        &self.frames
    }

    /// Per frame set (in the order of [`Recording::frames`]), per camera, the frame's position
    /// in that camera's video, in the video layout: where a caliscope session's cameras
    /// dropped different frames, a set's positions differ between cameras.
    pub fn video_positions(&self) -> Option<&[SetPositions]> {
        match &self.pixels {
            Pixels::Videos { positions, .. } => Some(positions),
            Pixels::Images(_) => None,
        }
    }

    /// The image file of frame set `index` for camera `camera`, in the image-folder layout.
    pub fn image_path(&self, index: usize, camera: usize) -> Option<&Path> {
        match &self.pixels {
            Pixels::Images(images) => images.get(index)?.get(camera).map(PathBuf::as_path),
            Pixels::Videos { .. } => None,
        }
    }

    /// Number of frame sets.
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
    /// [`PRELOAD_LIMIT_BYTES`]; a frame set that does not decode is remembered and reported,
    /// naming camera and frame, when it is read.
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
        let mut broken = vec![None; self.frames.len()];
        for (index, dst) in decoded.chunks_exact_mut(set_len.max(1)).enumerate() {
            match self.decode_into(index, dst) {
                Ok(()) => {}
                Err(error) if error.is_bad_frame() => broken[index] = Some(error.to_string()),
                Err(error) => return Err(error),
            }
        }
        self.decoded = Some((decoded, broken));
        Ok(())
    }

    /// Whether [`Recording::preload`] has run.
    pub fn is_preloaded(&self) -> bool {
        self.decoded.is_some()
    }

    /// Reads replay position `sequence` (frame set `sequence % len` when `looped`) into
    /// `dst`, every camera's view back to back in rig order: copied from memory when
    /// preloaded, else decoded, cameras in parallel. A frame set that cannot be read is an
    /// error for which [`RecordingError::is_bad_frame`] holds; the next one reads as usual.
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
        let entry = &self.frames[index];
        match &self.decoded {
            Some((decoded, broken)) => {
                if let Some(message) = &broken[index] {
                    return Err(RecordingError::Preloaded { frame: entry.frame, message: message.clone() });
                }
                dst.copy_from_slice(&decoded[index * expected..(index + 1) * expected]);
            }
            None => self.decode_into(index, dst)?,
        }
        Ok(FrameInfo {
            sequence,
            frame: entry.frame,
            timestamp: entry.timestamp + pass as f64 * self.loop_period(),
            missing_views: entry.missing_views,
        })
    }

    /// Decodes frame set `index` into `dst` (its exact size), cameras in parallel.
    fn decode_into(&self, index: usize, dst: &mut [u8]) -> Result<(), RecordingError> {
        let frame = self.frames[index].frame;
        let mut views: Vec<&mut [u8]> = Vec::with_capacity(self.rig.cameras.len());
        let mut rest = dst;
        for len in self.view_lengths() {
            let (view, tail) = rest.split_at_mut(len);
            views.push(view);
            rest = tail;
        }
        match &self.pixels {
            Pixels::Images(images) => {
                views.into_par_iter().zip(self.rig.cameras.par_iter()).zip(images[index].par_iter()).try_for_each(
                    |((view, camera), path)| {
                        decode_rgb8_into(path, camera.width, camera.height, view)
                            .map_err(|error| RecordingError::Image { camera: camera.name.clone(), frame, error })
                    },
                )
            }
            Pixels::Videos { readers, positions, .. } => {
                // Every camera is read even when one fails, so all decoders stay in step.
                let results: Vec<Result<(), RecordingError>> = views
                    .into_par_iter()
                    .zip(self.rig.cameras.par_iter())
                    .zip(readers.par_iter())
                    .zip(positions[index].par_iter())
                    .map(|(((view, camera), reader), &position)| {
                        // A frame the camera dropped: its view says nothing (the set's
                        // `missing_views` tells the stages so).
                        let Some(position) = position else {
                            view.fill(0);
                            return Ok(());
                        };
                        let video_error =
                            |error| RecordingError::Video { camera: camera.name.clone(), frame: Some(frame), error };
                        let mut reader = reader.lock().map_err(|_| {
                            video_error(VideoError::Frame {
                                path: PathBuf::from(&camera.name),
                                problem: "its decoder failed earlier".into(),
                            })
                        })?;
                        reader.read_into(position, view).map_err(video_error)
                    })
                    .collect();
                results.into_iter().collect()
            }
        }
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

/// Whether `path` is a file with a video extension.
fn is_video(path: &Path) -> bool {
    path.is_file()
        && path
            .extension()
            .and_then(|e| e.to_str())
            .is_some_and(|e| VIDEO_EXTENSIONS.contains(&e.to_ascii_lowercase().as_str()))
}

/// A recording's calibration, where the tools people use leave it: the folder's `rig.toml`
/// or `camera_array.toml`; else its `calibration/` folder's (Pose2Sim); else its one
/// `<session>_camera_calibration.toml` (FreeMoCap); else the folder's
/// only calibration file ([`Rig::find_in_dir`]); else a `rig.toml` or `camera_array.toml`
/// up to two folders above, or an older caliscope project's `config.toml` that holds its
/// cameras (caliscope keeps recordings in `recordings/<name>/` below the session's
/// calibration).
fn find_calibration(dir: &Path) -> Result<Vec<PathBuf>, RigError> {
    for name in [RIG_FILE, handflow_protocol::rig::CALISCOPE_FILE] {
        if dir.join(name).is_file() {
            return Ok(vec![dir.join(name)]);
        }
    }
    let pose2sim = dir.join(CALIBRATION_DIR);
    if pose2sim.is_dir() {
        if let Ok(found) = Rig::find_in_dir(&pose2sim) {
            return Ok(found);
        }
    }
    // FreeMoCap's `<session>_camera_calibration.toml`, when there is one.
    let freemocap: Vec<PathBuf> = list_dir(dir)
        .unwrap_or_default()
        .into_iter()
        .filter(|p| {
            p.is_file() && p.file_name().is_some_and(|n| n.to_string_lossy().ends_with(FREEMOCAP_CALIBRATION_SUFFIX))
        })
        .collect();
    if let [one] = &freemocap[..] {
        return Ok(vec![one.clone()]);
    }
    let own = Rig::find_in_dir(dir);
    if own.is_err() {
        for ancestor in dir.ancestors().skip(1).take(2) {
            for name in [RIG_FILE, handflow_protocol::rig::CALISCOPE_FILE] {
                if ancestor.join(name).is_file() {
                    return Ok(vec![ancestor.join(name)]);
                }
            }
            // An older caliscope project's settings, taken only when they hold its cameras
            // (`config.toml` is a common name).
            let config = ancestor.join(handflow_protocol::rig::CALISCOPE_CONFIG_FILE);
            if config.is_file()
                && Rig::load_detected(&config).is_ok_and(|(_, format)| format == RigFormat::CaliscopeConfig)
            {
                return Ok(vec![config]);
            }
        }
    }
    own
}

/// The folder's entries, sorted.
fn list_dir(dir: &Path) -> Result<Vec<PathBuf>, RecordingError> {
    let entries = std::fs::read_dir(dir).map_err(|error| RecordingError::Folder { dir: dir.to_owned(), error })?;
    let mut paths = Vec::new();
    for entry in entries {
        paths.push(entry.map_err(|error| RecordingError::Folder { dir: dir.to_owned(), error })?.path());
    }
    paths.sort();
    Ok(paths)
}

/// Per frame set, per camera, an image file.
type ImageSets = Vec<Vec<PathBuf>>;

/// The image-folder layout: the rig, the frame table and each frame set's images.
fn open_images(dir: &Path, rig: Rig) -> Result<(Rig, Vec<FrameEntry>, ImageSets), RecordingError> {
    let dir = dir.to_path_buf();
    let table = read_frame_table(&dir.join(FRAMES_FILE))?;
    let mut per_camera = Vec::with_capacity(rig.cameras.len());
    for camera in &rig.cameras {
        per_camera.push(images::camera_images(&dir, &camera.name)?);
    }
    let mut images = Vec::with_capacity(table.len());
    for &(frame, _) in &table {
        let mut set = Vec::with_capacity(rig.cameras.len());
        for (camera, files) in rig.cameras.iter().zip(&per_camera) {
            let Some(path) = files.get(&frame) else {
                return Err(RecordingError::MissingImage { dir, camera: camera.name.clone(), frame });
            };
            set.push(path.clone());
        }
        images.push(set);
    }
    let known: std::collections::BTreeSet<u64> = table.iter().map(|&(f, _)| f).collect();
    for (camera, files) in rig.cameras.iter().zip(&per_camera) {
        if let Some((frame, path)) = files.iter().find(|(f, _)| !known.contains(f)) {
            return Err(RecordingError::ExtraImage {
                dir,
                camera: camera.name.clone(),
                file: images::file_name(path),
                problem: format!("is frame {frame}, which frames.csv does not list"),
            });
        }
    }
    // Sizes from the headers only: cheap, and a wrong size is refused before replay. A
    // header that cannot be read is a broken frame, not a broken recording: reading that
    // frame set reports it and the stream goes on without it.
    let checks: Vec<(usize, usize)> =
        (0..images.len()).flat_map(|f| (0..rig.cameras.len()).map(move |c| (f, c))).collect();
    checks.par_iter().try_for_each(|&(f, c)| {
        let camera = &rig.cameras[c];
        let path = &images[f][c];
        let frame = table[f].0;
        let Ok((w, h)) = image::image_dimensions(path) else {
            return Ok(());
        };
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
    let frames = table
        .iter()
        .map(|&(frame, timestamp)| FrameEntry { frame, timestamp, capture_spread_s: None, missing_views: 0 })
        .collect();
    Ok((rig, frames, images))
}

/// The video layout: cameras matched to videos, each probed and sized against its
/// calibration, and frame sets from the best timing source the folder has.
fn open_videos(
    dir: &Path,
    video_dir: &Path,
    mut rig: Rig,
    videos: &[PathBuf],
    notes: &mut Vec<String>,
) -> Result<(Rig, Vec<FrameEntry>, Pixels), RecordingError> {
    let layout_error = |problem: String| RecordingError::Layout { dir: dir.to_owned(), problem };
    let names: Vec<String> = rig.cameras.iter().map(|c| c.name.clone()).collect();
    let files: Vec<String> = videos.iter().map(|p| images::file_name(p)).collect();
    let matched =
        camera_match::match_cameras(&names, &files).map_err(|problem| layout_error(format!("videos: {problem}")))?;
    let mut paths: Vec<PathBuf> = matched.iter().map(|&k| videos[k].clone()).collect();
    let probed: Vec<Result<VideoProbe, RecordingError>> = paths
        .par_iter()
        .zip(rig.cameras.par_iter())
        .map(|(path, camera)| {
            video::probe(path).map_err(|error| RecordingError::Video {
                camera: camera.name.clone(),
                frame: None,
                error,
            })
        })
        .collect();
    let probes = leave_out_unreadable_cameras(&mut rig, &mut paths, probed, notes)?;
    let mut turns = Vec::with_capacity(probes.len());
    for (camera, (probe, path)) in rig.cameras.iter_mut().zip(probes.iter().zip(&paths)) {
        let turn = frame_turn(camera, probe, path, notes)?;
        turns.push(turn);
        let (w, h) = probe.frame_size(turn);
        if (w, h) == (camera.width, camera.height) {
            continue;
        }
        notes.push(format!(
            "camera `{}`: video `{}` is {w}x{h}, the calibration {}x{}: taken as encoder padding, intrinsics unchanged",
            camera.name,
            images::file_name(path),
            camera.width,
            camera.height
        ));
        camera.width = w;
        camera.height = h;
    }
    let lengths: Vec<usize> = probes.iter().map(|p| p.frame_times.len()).collect();
    let shortest = lengths.iter().copied().min().unwrap_or(0);
    // Timing files beside the videos, else in the recording's folder.
    let timing_file = |name: &str| [video_dir, dir].iter().map(|d| d.join(name)).find(|p| p.is_file());
    let caliscope = timing_file(CALISCOPE_TIMESTAMPS_FILE).or_else(|| timing_file(CALISCOPE_FRAME_HISTORY_FILE));
    let (frames, positions) = if let Some(path) = timing_file(FRAMES_FILE) {
        let table = read_frame_table(&path)?;
        if table.len() > shortest {
            notes.push(format!(
                "{FRAMES_FILE} lists {} frames, the shortest video holds {shortest}: the rows beyond are left out",
                table.len()
            ));
        }
        let rows = table.len().min(shortest);
        let frames = table[..rows]
            .iter()
            .map(|&(frame, timestamp)| FrameEntry { frame, timestamp, capture_spread_s: None, missing_views: 0 })
            .collect();
        (frames, (0..rows).map(|r| vec![Some(r); rig.cameras.len()]).collect())
    } else if let Some(path) = caliscope {
        let sets = read_caliscope_timestamps(&path)?;
        synced_frames(&rig, &sets, &lengths, notes).map_err(|problem| RecordingError::Frames {
            path,
            line: 0,
            problem,
        })?
    } else {
        if lengths.iter().any(|&l| l != shortest) {
            notes.push(format!(
                "the videos hold {lengths:?} frames; without a timestamp file frame k of every video is set k, so the                  first {shortest} are used"
            ));
        }
        let frames = (0..shortest)
            .map(|k| {
                let times: Vec<f64> = probes.iter().map(|p| p.frame_times[k]).collect();
                let (lo, hi) = times.iter().fold((f64::MAX, f64::MIN), |(lo, hi), &t| (lo.min(t), hi.max(t)));
                FrameEntry {
                    frame: k as u64,
                    timestamp: times.iter().sum::<f64>() / times.len() as f64,
                    capture_spread_s: Some(hi - lo),
                    missing_views: 0,
                }
            })
            .collect();
        (frames, (0..shortest).map(|k| vec![Some(k); rig.cameras.len()]).collect())
    };
    if frames.is_empty() {
        return Err(layout_error(format!("no frame set has frames from {MIN_CAMERAS} cameras")));
    }
    let readers = paths
        .iter()
        .zip(probes.iter().zip(&turns))
        .zip(&rig.cameras)
        .map(|((path, (probe, &turn)), camera)| {
            VideoReader::open(path, probe, turn).map(Mutex::new).map_err(|error| RecordingError::Video {
                camera: camera.name.clone(),
                frame: None,
                error,
            })
        })
        .collect::<Result<_, _>>()?;
    let codecs = probes.iter().map(|p| p.codec.clone()).collect();
    Ok((rig, frames, Pixels::Videos { readers, positions, codecs }))
}

/// Whether frames of `width` x `height` are those `camera` was calibrated on: the same size,
/// or up to [`MAX_PADDING_PX`] smaller in each side (encoders pad sizes to multiples of 16).
fn fits_calibration(camera: &Camera, width: u32, height: u32) -> bool {
    (camera.width.saturating_sub(MAX_PADDING_PX)..=camera.width).contains(&width)
        && (camera.height.saturating_sub(MAX_PADDING_PX)..=camera.height).contains(&height)
}

/// Whether `camera`'s video is read as players show it or as stored. Shown, as the
/// calibration tools' readers (OpenCV, ffmpeg) turn a video by its orientation tag by
/// default, unless only the stored frames fit the calibration (a tool that read them
/// unturned); either choice of a tagged video is a note. Frames of neither size are an
/// error naming both.
fn frame_turn(
    camera: &Camera,
    probe: &VideoProbe,
    path: &Path,
    notes: &mut Vec<String>,
) -> Result<FrameTurn, RecordingError> {
    let (sw, sh) = probe.frame_size(FrameTurn::AsShown);
    let (w, h) = (probe.width, probe.height);
    let tag = probe.orientation.tag.as_deref();
    let file = images::file_name(path);
    let turn = if fits_calibration(camera, sw, sh) {
        FrameTurn::AsShown
    } else if tag.is_some() && fits_calibration(camera, w, h) {
        FrameTurn::AsStored
    } else {
        let tagged = tag.map_or_else(String::new, |t| format!(" (stored {w}x{h}, tagged `{t}`)"));
        return Err(RecordingError::Video {
            camera: camera.name.clone(),
            frame: None,
            error: VideoError::Open {
                path: path.to_owned(),
                problem: format!(
                    "frames are {sw}x{sh}{tagged}, the calibration says {}x{} (only up to {MAX_PADDING_PX} px of \
                     encoder padding is accepted)",
                    camera.width, camera.height
                ),
            },
        });
    };
    if let Some(tag) = tag {
        notes.push(match turn {
            FrameTurn::AsShown => format!(
                "camera `{}`: video `{file}` is stored {w}x{h} and tagged `{tag}`: its frames are turned as players \
                 show them, {sw}x{sh}",
                camera.name
            ),
            FrameTurn::AsStored => format!(
                "camera `{}`: video `{file}` is tagged `{tag}`, but its calibration is of the stored {w}x{h} frames: \
                 they are read as stored",
                camera.name
            ),
        });
    }
    Ok(turn)
}

/// The fewest cameras a recording is replayed with: depth needs a second view.
const MIN_CAMERAS: usize = 2;

/// Leaves the cameras whose video cannot be opened (a file cut before its index, not a video
/// at all) out of the rig, as a live rig goes on without a camera that fails, while at least
/// [`MIN_CAMERAS`] remain; each one left out is a note naming camera, file and cause. With
/// fewer left, the first camera's error is the recording's.
fn leave_out_unreadable_cameras(
    rig: &mut Rig,
    paths: &mut Vec<PathBuf>,
    probed: Vec<Result<VideoProbe, RecordingError>>,
    notes: &mut Vec<String>,
) -> Result<Vec<VideoProbe>, RecordingError> {
    let readable = probed.iter().filter(|p| p.is_ok()).count();
    let mut probes = Vec::with_capacity(readable);
    let mut kept = Vec::with_capacity(readable);
    let mut left_out = Vec::new();
    for (index, result) in probed.into_iter().enumerate() {
        match result {
            Ok(probe) => {
                probes.push(probe);
                kept.push(index);
            }
            Err(error) if readable < MIN_CAMERAS => return Err(error),
            Err(error) => left_out.push(error.to_string()),
        }
    }
    if left_out.is_empty() {
        return Ok(probes);
    }
    for problem in left_out {
        notes.push(format!(
            "{problem}: this camera is left out, the recording is replayed with the other {readable} of {}",
            rig.cameras.len()
        ));
    }
    keep_indices(&mut rig.cameras, &kept);
    keep_indices(paths, &kept);
    Ok(probes)
}

/// Keeps the items at `kept` (ascending indices), in order.
fn keep_indices<T>(items: &mut Vec<T>, kept: &[usize]) {
    let mut index = 0;
    items.retain(|_| {
        index += 1;
        kept.binary_search(&(index - 1)).is_ok()
    });
}

/// Frame sets of a caliscope session: camera `cam_N` (or the camera matched to the number N)
/// is caliscope's `cam_id` N. Frame numbers count `sync_index` from the first set, so left
/// out sets keep their place in time. A set some cameras lack (a webcam dropped its frame)
/// is kept with those views missing while [`MIN_CAMERAS`] have theirs: with four webcams each
/// dropping a few percent of frames, leaving such sets out loses one set in every few, and
/// every object's estimate with it.
fn synced_frames(
    rig: &Rig,
    sets: &[SyncedSet],
    lengths: &[usize],
    notes: &mut Vec<String>,
) -> Result<(Vec<FrameEntry>, Vec<SetPositions>), String> {
    let mut ids: Vec<u64> = sets.iter().flat_map(|s| s.frames.keys().copied()).collect();
    ids.sort_unstable();
    ids.dedup();
    let id_names: Vec<String> = ids.iter().map(|id| format!("cam_{id}")).collect();
    let names: Vec<String> = rig.cameras.iter().map(|c| c.name.clone()).collect();
    let matched = camera_match::match_cameras(&names, &id_names).map_err(|p| format!("cam_id values: {p}"))?;
    let camera_ids: Vec<u64> = matched.iter().map(|&k| ids[k]).collect();
    let first = sets.first().map_or(0, |s| s.sync_index);
    let (mut frames, mut positions) = (Vec::new(), Vec::new());
    let (mut partial, mut left_out) = (vec![0usize; camera_ids.len()], 0usize);
    for set in sets {
        let per_camera: Vec<Option<(usize, f64)>> = camera_ids
            .iter()
            .zip(lengths)
            .map(|(id, &len)| set.frames.get(id).copied().filter(|&(position, _)| position < len))
            .collect();
        let times: Vec<f64> = per_camera.iter().flatten().map(|&(_, t)| t).collect();
        if times.len() < MIN_CAMERAS {
            left_out += 1;
            continue;
        }
        let mut missing_views = 0u32;
        for (k, frame) in per_camera.iter().enumerate() {
            if frame.is_none() {
                partial[k] += 1;
                missing_views |= 1 << k;
            }
        }
        let (lo, hi) = times.iter().fold((f64::MAX, f64::MIN), |(lo, hi), &t| (lo.min(t), hi.max(t)));
        frames.push(FrameEntry {
            frame: set.sync_index - first,
            timestamp: times.iter().sum::<f64>() / times.len() as f64,
            capture_spread_s: Some(hi - lo),
            missing_views,
        });
        positions.push(per_camera.iter().map(|frame| frame.map(|(position, _)| position)).collect());
    }
    let lacking: Vec<String> = partial
        .iter()
        .zip(&rig.cameras)
        .filter(|(&n, _)| n > 0)
        .map(|(n, camera)| format!("`{}` {n}", camera.name))
        .collect();
    if !lacking.is_empty() {
        notes.push(format!(
            "frame sets without a camera's frame (dropped in capture, or beyond its video), read with the other \
             cameras: {}",
            lacking.join(", ")
        ));
    }
    if left_out > 0 {
        notes.push(format!(
            "{left_out} of {} frame sets have frames from fewer than {MIN_CAMERAS} cameras and are left out",
            sets.len()
        ));
    }
    Ok((frames, positions))
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
        Rig::new(vec![cam("left", 0.0), cam("right", -0.2)])
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
        use images::frame_number;
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
        broken.preload().expect("a broken frame does not stop preloading");
        let e = broken.read_frame_into(2, false, &mut b).unwrap_err();
        assert!(e.is_bad_frame(), "{e}");
        let e = e.to_string();
        assert!(e.contains("camera `left`") && e.contains("frame 2"), "{e}");
        broken.read_frame_into(1, false, &mut b).expect("the frames around it are kept");
    }

    #[test]
    fn an_image_broken_before_opening_costs_its_frame_set_only() {
        let tmp = tempfile::tempdir().expect("tempdir");
        make(tmp.path());
        std::fs::write(tmp.path().join("left/000001.png"), b"not a png").expect("write");
        let rec = Recording::open(tmp.path()).expect("a broken image does not refuse the recording");
        let mut buf = vec![0u8; rec.frame_set_len()];
        let e = rec.read_frame_into(1, false, &mut buf).unwrap_err();
        assert!(e.is_bad_frame(), "{e}");
        let e = e.to_string();
        assert!(e.contains("camera `left`") && e.contains("frame 1") && e.contains("000001.png"), "{e}");
        rec.read_frame_into(0, false, &mut buf).expect("frame 0 reads");
        rec.read_frame_into(2, false, &mut buf).expect("frame 2 reads");
    }
}
