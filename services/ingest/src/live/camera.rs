//! One live camera through GStreamer: the source a pipeline file names, decoded to RGB8,
//! each frame stamped with its capture time on the system's monotonic clock, which every
//! camera of the rig shares.
//!
//! A camera's frames are pulled on a thread of its own and handed over through a short
//! queue: a consumer that falls behind loses the oldest frames (counted), never stalls the
//! device.

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{sync_channel, Receiver, TrySendError};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::Duration;

use gstreamer as gst;
use gstreamer::prelude::*;
use gstreamer_app as gst_app;
use gstreamer_video as gst_video;
use gstreamer_video::prelude::*;

use super::sync::TimedFrame;
use crate::recording::video::bus_error;
use crate::recording::yuv;

/// Frames a camera's thread may hold for the consumer before it drops the oldest.
const HANDOVER_FRAMES: usize = 4;
/// How often the pulling thread looks up from a quiet device.
const PULL_POLL: Duration = Duration::from_millis(100);

/// Where a live camera's frames come from, as written in a pipeline file.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum CameraSource {
    /// `v4l2:///dev/videoN`: a V4L2 device (USB webcam); MJPEG and raw formats decoded,
    /// size and rate negotiated with the device.
    V4l2 {
        /// The device node.
        device: String,
    },
    /// `rtsp://`, `rtsps://`, `http://`, `https://`: a network camera or stream.
    Network {
        /// The URI.
        uri: String,
    },
    /// `file:///path/video.mp4`: a video played at its own rate, as a camera would deliver
    /// it (for tests and demonstrations; replays of recordings use `recording`).
    File {
        /// The video.
        path: PathBuf,
    },
    /// `gst:DESCRIPTION`: any GStreamer source in `gst-launch-1.0` syntax, up to the raw or
    /// encoded video it delivers, e.g. `gst:videotestsrc is-live=true pattern=ball`.
    Launch {
        /// The pipeline description.
        description: String,
    },
}

impl CameraSource {
    /// Reads a source as a pipeline file writes it.
    pub fn parse(text: &str) -> Result<CameraSource, String> {
        let text = text.trim();
        if let Some(device) = text.strip_prefix("v4l2://") {
            if !device.starts_with('/') {
                return Err(format!(
                    "source `{text}`: a V4L2 source is `v4l2:///dev/videoN` (an absolute device path)"
                ));
            }
            return Ok(CameraSource::V4l2 { device: device.to_string() });
        }
        if let Some(path) = text.strip_prefix("file://") {
            if !path.starts_with('/') {
                return Err(format!("source `{text}`: a file source is `file:///absolute/path`"));
            }
            return Ok(CameraSource::File { path: PathBuf::from(path) });
        }
        if let Some(description) = text.strip_prefix("gst:") {
            if description.trim().is_empty() {
                return Err(format!("source `{text}`: `gst:` needs a GStreamer pipeline description"));
            }
            return Ok(CameraSource::Launch { description: description.trim().to_string() });
        }
        if ["rtsp://", "rtsps://", "http://", "https://"].iter().any(|p| text.starts_with(p)) {
            return Ok(CameraSource::Network { uri: text.to_string() });
        }
        Err(format!(
            "source `{text}`: unknown kind (expected `v4l2:///dev/videoN`, `rtsp://...`, `http(s)://...`, \
             `file:///path` or `gst:<GStreamer source description>`)"
        ))
    }

    /// The GStreamer pipeline for this source, ending in an RGB8 `appsink` named `sink`.
    /// `size` and `fps` are asked of a V4L2 device; other sources deliver what they deliver.
    pub fn launch_description(&self, size: Option<[u32; 2]>, fps: Option<f64>) -> String {
        let tail = "videoconvert ! video/x-raw,format=RGB ! appsink name=sink";
        match self {
            CameraSource::V4l2 { device } => {
                let mut fields = String::new();
                if let Some([w, h]) = size {
                    fields.push_str(&format!(",width={w},height={h}"));
                }
                if let Some(fps) = fps.filter(|f| f.is_finite() && *f > 0.0) {
                    let (n, d) = rate_fraction(fps);
                    fields.push_str(&format!(",framerate={n}/{d}"));
                }
                format!(
                    "v4l2src device=\"{device}\" ! capsfilter caps=\"video/x-raw{fields}; image/jpeg{fields}\" ! \
                     decodebin ! {tail}"
                )
            }
            // uridecodebin3: the older bin holds an MJPEG stream over HTTP back (its
            // decodebin waits for more streams before it lets frames through).
            CameraSource::Network { uri } => format!("uridecodebin3 uri=\"{uri}\" ! {tail}"),
            CameraSource::File { path } => format!("uridecodebin uri=\"file://{}\" ! {tail}", path.display()),
            CameraSource::Launch { description } => format!("{description} ! decodebin ! {tail}"),
        }
    }

    /// Whether frames are paced by the pipeline's clock (a file or a source that is not
    /// live would otherwise deliver as fast as it decodes).
    pub fn paced_by_clock(&self) -> bool {
        matches!(self, CameraSource::File { .. } | CameraSource::Launch { .. })
    }
}

/// A rate as a fraction GStreamer takes: whole rates as themselves, NTSC's 29.97 as
/// 30000/1001.
fn rate_fraction(fps: f64) -> (i64, i64) {
    let whole = fps.round();
    if (fps - whole).abs() < 1e-3 {
        (whole as i64, 1)
    } else {
        ((fps * 1001.0).round() as i64, 1001)
    }
}

/// Why a live camera could not start or stopped.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum LiveCameraError {
    /// The source could not be opened.
    #[error("camera `{camera}`: {problem}")]
    Open {
        /// The camera's name.
        camera: String,
        /// What went wrong.
        problem: String,
    },
}

/// What a camera's thread reports besides frames.
#[derive(Clone, Debug, Default)]
struct CameraState {
    /// Frames delivered by the device.
    delivered: u64,
    /// Frames lost in the hand-over because the consumer was behind.
    handover_dropped: u64,
    /// The source ended (a file, or a test source with `num-buffers`).
    ended: bool,
    /// Why the camera stopped, if it failed.
    failure: Option<String>,
}

/// How a live camera is started.
#[derive(Clone, Copy, Debug, Default)]
pub struct StartOptions {
    /// A consumer that falls behind holds the source back instead of losing frames (a
    /// replay: a video played as a camera then pauses; a device still drops in its driver).
    pub lossless: bool,
    /// Clock time (ns, [`clock_now_ns`]) at which a source paced by the clock (a video, a
    /// GStreamer description) plays its first frame: the same for every camera of a rig,
    /// so videos recorded together play together. Devices and network cameras stamp their
    /// frames as they capture them and ignore it.
    pub rig_start_ns: Option<u64>,
}

/// A running live camera.
pub struct LiveCamera {
    name: String,
    pipeline: gst::Pipeline,
    frames: Receiver<TimedFrame>,
    state: Arc<Mutex<CameraState>>,
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
}

impl std::fmt::Debug for LiveCamera {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LiveCamera").field("name", &self.name).finish()
    }
}

/// Readies the clock of [`clock_now_ns`] (GStreamer's), before any camera is started.
pub fn init_clock() -> Result<(), String> {
    crate::recording::video::init_gstreamer()
}

/// Nanoseconds on the clock every live camera stamps its frames with (the system's monotonic
/// clock, as GStreamer reads it).
pub fn clock_now_ns() -> u64 {
    gst::SystemClock::obtain().time().nseconds()
}

impl LiveCamera {
    /// Starts camera `name` from `source`, expecting frames of `width` x `height` (its
    /// calibration); `size` and `fps` are asked of devices that negotiate. A frame of
    /// another size stops the camera with an error naming both sizes.
    pub fn start(
        name: &str,
        source: &CameraSource,
        width: u32,
        height: u32,
        size: Option<[u32; 2]>,
        fps: Option<f64>,
    ) -> Result<LiveCamera, LiveCameraError> {
        Self::start_with(name, source, width, height, size, fps, StartOptions::default())
    }

    /// [`LiveCamera::start`] with [`StartOptions`].
    pub fn start_with(
        name: &str,
        source: &CameraSource,
        width: u32,
        height: u32,
        size: Option<[u32; 2]>,
        fps: Option<f64>,
        options: StartOptions,
    ) -> Result<LiveCamera, LiveCameraError> {
        let StartOptions { lossless, rig_start_ns } = options;
        let open_error = |problem: String| LiveCameraError::Open { camera: name.to_string(), problem };
        crate::recording::video::init_gstreamer().map_err(open_error)?;
        let description = source.launch_description(size.or(Some([width, height])), fps);
        let element = gst::parse::launch(&description)
            .map_err(|e| open_error(format!("source `{description}` cannot be built: {e}")))?;
        let pipeline = element
            .downcast::<gst::Pipeline>()
            .map_err(|_| open_error(format!("source `{description}` is not a pipeline")))?;
        let sink = pipeline
            .by_name("sink")
            .and_then(|e| e.downcast::<gst_app::AppSink>().ok())
            .ok_or_else(|| open_error("the pipeline has no RGB sink".into()))?;
        sink.set_sync(source.paced_by_clock());
        sink.set_max_buffers(2);
        sink.set_drop(!lossless);
        // One clock for every camera: capture times compare across the rig.
        pipeline.use_clock(Some(&gst::SystemClock::obtain()));
        if let Some(start) = rig_start_ns.filter(|_| source.paced_by_clock()) {
            // Every paced source's first frame at the same instant, as a rig's recordings
            // were captured; left to itself each pipeline starts when it has prerolled, and
            // the cameras' phases would be whatever their start-up took.
            pipeline.set_start_time(gst::ClockTime::NONE);
            pipeline.set_base_time(gst::ClockTime::from_nseconds(start));
        }
        if pipeline.set_state(gst::State::Playing).is_err() {
            let problem = bus_error(&pipeline).unwrap_or_else(|| "the source would not start".into());
            let _ = pipeline.set_state(gst::State::Null);
            return Err(open_error(problem));
        }
        let (sender, frames) = sync_channel(HANDOVER_FRAMES);
        let state = Arc::new(Mutex::new(CameraState::default()));
        let stop = Arc::new(AtomicBool::new(false));
        let thread = {
            let (state, stop, pipeline, camera) = (state.clone(), stop.clone(), pipeline.clone(), name.to_string());
            std::thread::Builder::new()
                .name(format!("camera {name}"))
                .spawn(move || {
                    let set = |f: &dyn Fn(&mut CameraState)| {
                        if let Ok(mut s) = state.lock() {
                            f(&mut s);
                        }
                    };
                    while !stop.load(Ordering::Relaxed) {
                        let Some(sample) =
                            sink.try_pull_sample(gst::ClockTime::from_nseconds(PULL_POLL.as_nanos() as u64))
                        else {
                            if sink.is_eos() {
                                set(&|s| s.ended = true);
                                return;
                            }
                            if let Some(problem) = bus_error(&pipeline) {
                                set(&|s| s.failure = Some(problem.clone()));
                                return;
                            }
                            continue;
                        };
                        match timed_frame(&sample, &pipeline, width, height) {
                            Ok(Some(frame)) => {
                                set(&|s| s.delivered += 1);
                                if lossless {
                                    // Waits for room, but not past a stop: a blocking send
                                    // to a full hand-over nobody empties any more would
                                    // keep the camera (and its process) from ending.
                                    let mut pending = frame;
                                    loop {
                                        match sender.try_send(pending) {
                                            Ok(()) => break,
                                            Err(TrySendError::Full(f)) if !stop.load(Ordering::Relaxed) => {
                                                pending = f;
                                                std::thread::sleep(Duration::from_millis(2));
                                            }
                                            Err(_) => return,
                                        }
                                    }
                                    continue;
                                }
                                match sender.try_send(frame) {
                                    Ok(()) => {}
                                    Err(TrySendError::Full(_)) => set(&|s| s.handover_dropped += 1),
                                    Err(TrySendError::Disconnected(_)) => return,
                                }
                            }
                            Ok(None) => {}
                            Err(problem) => {
                                tracing::error!("camera `{camera}`: {problem}");
                                set(&|s| s.failure = Some(problem.clone()));
                                return;
                            }
                        }
                    }
                })
                .map_err(|e| open_error(format!("cannot start its thread: {e}")))?
        };
        Ok(LiveCamera { name: name.to_string(), pipeline, frames, state, stop, thread: Some(thread) })
    }

    /// The camera's name.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// The next frame if one is waiting.
    pub fn try_frame(&self) -> Option<TimedFrame> {
        self.frames.try_recv().ok()
    }

    /// The next frame, waiting up to `timeout`.
    pub fn frame_timeout(&self, timeout: Duration) -> Option<TimedFrame> {
        self.frames.recv_timeout(timeout).ok()
    }

    /// Frames the device delivered so far.
    pub fn delivered(&self) -> u64 {
        self.state.lock().map(|s| s.delivered).unwrap_or(0)
    }

    /// Frames lost because the consumer was behind.
    pub fn handover_dropped(&self) -> u64 {
        self.state.lock().map(|s| s.handover_dropped).unwrap_or(0)
    }

    /// Whether the source has ended (files, finite test sources).
    pub fn ended(&self) -> bool {
        self.state.lock().map(|s| s.ended).unwrap_or(true)
    }

    /// Why the camera stopped, if it failed.
    pub fn failure(&self) -> Option<String> {
        self.state.lock().ok().and_then(|s| s.failure.clone())
    }
}

impl Drop for LiveCamera {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
        let _ = self.pipeline.set_state(gst::State::Null);
    }
}

/// A pulled sample as a frame stamped with its capture time: the pipeline's base time plus
/// the buffer's running time, both on the shared clock (its arrival for a sample without a
/// time). `Ok(None)` for a sample without a buffer; an error for a frame of another size than the calibration's.
fn timed_frame(
    sample: &gst::Sample,
    pipeline: &gst::Pipeline,
    width: u32,
    height: u32,
) -> Result<Option<TimedFrame>, String> {
    let (Some(buffer), Some(caps)) = (sample.buffer(), sample.caps()) else { return Ok(None) };
    let info = gst_video::VideoInfo::from_caps(caps).map_err(|e| format!("unusable caps: {e}"))?;
    if (info.width(), info.height()) != (width, height) {
        return Err(format!(
            "delivers {}x{} frames, its calibration is {width}x{height}: set the device's size in the pipeline file \
             (`size = [{width}, {height}]`) or calibrate at the size it delivers",
            info.width(),
            info.height()
        ));
    }
    // A frame without a time (an MJPEG stream over HTTP has none) is stamped as it arrives.
    let capture_ns = match buffer.pts() {
        Some(pts) => {
            let running = sample
                .segment()
                .and_then(|s| s.downcast_ref::<gst::format::Time>().and_then(|s| s.to_running_time(pts)))
                .unwrap_or(pts);
            (pipeline.base_time().unwrap_or(gst::ClockTime::ZERO) + running).nseconds()
        }
        None => clock_now_ns(),
    };
    let frame = gst_video::VideoFrameRef::from_buffer_ref_readable(buffer, &info)
        .map_err(|e| format!("cannot map a frame: {e}"))?;
    let data = frame.plane_data(0).map_err(|e| format!("cannot read a frame: {e}"))?;
    let mut rgb = vec![0u8; width as usize * height as usize * 3];
    yuv::copy_rgb_rows(data, frame.plane_stride()[0] as usize, width as usize, height as usize, &mut rgb)?;
    Ok(Some(TimedFrame { capture_ns, delivered_ns: clock_now_ns(), data: rgb }))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sources_parse_as_pipeline_files_write_them_and_bad_ones_say_what_is_expected() {
        assert_eq!(
            CameraSource::parse("v4l2:///dev/video2").unwrap(),
            CameraSource::V4l2 { device: "/dev/video2".into() }
        );
        assert_eq!(
            CameraSource::parse("rtsp://10.0.0.5:554/stream1").unwrap(),
            CameraSource::Network { uri: "rtsp://10.0.0.5:554/stream1".into() }
        );
        assert_eq!(
            CameraSource::parse("file:///data/a.mp4").unwrap(),
            CameraSource::File { path: "/data/a.mp4".into() }
        );
        assert_eq!(
            CameraSource::parse("gst: videotestsrc is-live=true").unwrap(),
            CameraSource::Launch { description: "videotestsrc is-live=true".into() }
        );
        assert!(CameraSource::parse("v4l2://video0").unwrap_err().contains("/dev/videoN"));
        assert!(CameraSource::parse("/dev/video0").unwrap_err().contains("unknown kind"));
        assert!(CameraSource::parse("gst:").unwrap_err().contains("description"));
        let v4l2 =
            CameraSource::V4l2 { device: "/dev/video0".into() }.launch_description(Some([1280, 720]), Some(29.97));
        assert!(v4l2.contains("image/jpeg,width=1280,height=720,framerate=30000/1001"), "{v4l2}");
        assert!(v4l2.contains("video/x-raw,width=1280,height=720,framerate=30000/1001"), "{v4l2}");
        assert_eq!(rate_fraction(30.0), (30, 1));
    }

    fn test_source(width: u32, height: u32, pattern: &str) -> CameraSource {
        CameraSource::Launch {
            description: format!(
                "videotestsrc is-live=true pattern={pattern} ! video/x-raw,width={width},height={height},framerate=30/1"
            ),
        }
    }

    #[test]
    fn a_live_test_source_delivers_rgb_frames_stamped_a_frame_interval_apart() {
        let camera = LiveCamera::start("cam0", &test_source(64, 48, "red"), 64, 48, None, None).expect("starts");
        let frames: Vec<TimedFrame> = (0..10).filter_map(|_| camera.frame_timeout(Duration::from_secs(5))).collect();
        assert_eq!(frames.len(), 10, "failure: {:?}", camera.failure());
        // A red test pattern: every pixel red.
        assert_eq!(&frames[0].data[..3], &[255, 0, 0]);
        assert_eq!(frames[0].data.len(), 64 * 48 * 3);
        let gaps: Vec<u64> = frames.windows(2).map(|p| p[1].capture_ns - p[0].capture_ns).collect();
        for gap in &gaps {
            assert!((25_000_000..=42_000_000).contains(gap), "{gaps:?}");
        }
        // Stamped on the shared clock: in the recent past.
        let now = clock_now_ns();
        assert!(frames[9].capture_ns <= now && now - frames[9].capture_ns < 2_000_000_000);
    }

    #[test]
    fn a_lossless_camera_whose_hand_over_is_full_stops_when_dropped() {
        // Replay mode: nobody takes its frames, so its thread waits for room; dropping it
        // must still end that thread (a blocking send kept a stopping ingest alive forever).
        let options = StartOptions { lossless: true, rig_start_ns: None };
        let camera =
            LiveCamera::start_with("cam0", &test_source(32, 24, "red"), 32, 24, None, None, options).expect("starts");
        let started = std::time::Instant::now();
        while camera.delivered() <= HANDOVER_FRAMES as u64 && started.elapsed() < Duration::from_secs(10) {
            std::thread::sleep(Duration::from_millis(20));
        }
        assert!(camera.delivered() > HANDOVER_FRAMES as u64, "the hand-over filled up");
        let dropping = std::time::Instant::now();
        drop(camera);
        assert!(dropping.elapsed() < Duration::from_secs(2), "dropped in {:?}", dropping.elapsed());
    }

    #[test]
    fn a_source_of_another_size_than_its_calibration_is_refused_naming_both() {
        let camera = LiveCamera::start("cam_3", &test_source(64, 48, "ball"), 640, 480, None, None).expect("starts");
        let mut failure = None;
        for _ in 0..50 {
            failure = camera.failure();
            if failure.is_some() {
                break;
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        let failure = failure.expect("refused");
        assert!(failure.contains("64x48") && failure.contains("640x480"), "{failure}");
        assert!(camera.try_frame().is_none());
    }

    #[test]
    fn sources_paced_by_the_clock_started_apart_play_their_first_frames_at_the_rigs_start() {
        // Not live: the pattern's frames are timed by the pipeline's clock, as a video's are.
        let paced = CameraSource::Launch {
            description: "videotestsrc pattern=blue num-buffers=3 ! video/x-raw,width=32,height=24,framerate=10/1"
                .into(),
        };
        init_clock().expect("GStreamer");
        let start = clock_now_ns() + 400_000_000;
        let options = StartOptions { lossless: true, rig_start_ns: Some(start) };
        let first = LiveCamera::start_with("cam0", &paced, 32, 24, None, None, options).expect("starts");
        std::thread::sleep(Duration::from_millis(150));
        let second = LiveCamera::start_with("cam1", &paced, 32, 24, None, None, options).expect("starts");
        let times = |camera: &LiveCamera| -> Vec<u64> {
            (0..3).filter_map(|_| camera.frame_timeout(Duration::from_secs(5))).map(|f| f.capture_ns).collect()
        };
        let (a, b) = (times(&first), times(&second));
        assert_eq!(a, b, "the same instants, 150 ms of start-up apart");
        assert_eq!(a, vec![start, start + 100_000_000, start + 200_000_000]);
    }

    #[test]
    fn a_source_that_cannot_be_built_is_an_error_naming_the_camera() {
        let source = CameraSource::Launch { description: "no-such-element-anywhere".into() };
        let error = LiveCamera::start("cam_7", &source, 64, 48, None, None).unwrap_err().to_string();
        assert!(error.contains("cam_7") && error.contains("no-such-element-anywhere"), "{error}");
    }
}
