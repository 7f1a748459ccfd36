//! One camera's video file, decoded frame by frame with GStreamer.
//!
//! Why GStreamer: the same library opens files (mp4, mkv, avi, mov; H.264, H.265, VP9, MJPEG,
//! FFV1 through Debian's `gstreamer1.0-libav` and `-good` plugins), V4L2 webcams and RTSP
//! cameras, and writes recordings, so one decoding path serves replays and live rigs.
//!
//! Hardware-independent results: hardware decoders are never picked (their rank is lowered
//! once per process), the software decoders are bit-exact by their codecs' specifications,
//! and the conversion to RGB is ours ([`super::yuv`]), in integer arithmetic, written
//! straight into the caller's buffer (the loaned shared-memory sample): no RGB image in
//! between.
//!
//! Frames are shown as players show them: a video tagged to be turned for display (a phone's
//! portrait video is stored landscape with an orientation tag) is turned by GStreamer's
//! `videoflip` as `ffmpeg` and OpenCV, the calibration tools' readers, turn it by default
//! ([`Orientation`]); the recording keeps the stored frames only when its calibration is of
//! their size.
//!
//! Frames are identified by their presentation time, not by counting decoder output: a probe
//! pass over the demuxed packets (no decoding) lists every frame's time, so a frame the
//! decoder drops (a corrupt packet) is reported as that frame, and the next one still lands
//! on its own number. Reading frames in order decodes straight on; jumping elsewhere seeks.

use std::path::{Path, PathBuf};
use std::sync::{Mutex, Once};

use gstreamer as gst;
use gstreamer::prelude::*;
use gstreamer_app as gst_app;
use gstreamer_video as gst_video;
use gstreamer_video::prelude::*;

use super::yuv::{self, ColourMatrix};

/// How long a pull may wait for the decoder before the file is declared stuck.
const PULL_TIMEOUT_S: u64 = 20;
/// Pulls wait in slices this long and look at the bus between them: a demuxer that failed
/// (a file cut before its index) says so on the bus at once and delivers nothing, so a pull
/// that only waited would take the whole timeout to notice.
const PULL_SLICE_MS: u64 = 50;
/// How long a probe waits for a video's first packet: a local file's come within
/// milliseconds, but a demuxer inside `parsebin` that fails at once sometimes has its error
/// swallowed by the bin (seen with MP4 files cut before their index), and then nothing at
/// all arrives.
const FIRST_PACKET_TIMEOUT_S: u64 = 5;
/// Forward jumps up to this many frames are decoded through rather than seeked: cheaper
/// than a seek, which decodes from the previous key frame anyway.
const MAX_DECODE_THROUGH: usize = 48;

/// Why a video could not be opened or a frame read. Messages name the file; the recording
/// adds the camera and frame.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum VideoError {
    /// GStreamer or a plugin is missing, or the file cannot be opened as a video.
    #[error("video `{}`: {problem}", path.display())]
    Open {
        /// The file.
        path: PathBuf,
        /// What went wrong.
        problem: String,
    },
    /// The frame could not be decoded (corrupt or missing packet, or the file ends early).
    #[error("video `{}`: {problem}", path.display())]
    Frame {
        /// The file.
        path: PathBuf,
        /// What went wrong.
        problem: String,
    },
}

/// How a video's container says its frames are to be turned for display: GStreamer's
/// `image-orientation` tag (`rotate-90` is a quarter turn clockwise; `flip-` mirrors first).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Orientation {
    /// The tag, `None` when the video has none or says `rotate-0`.
    pub tag: Option<String>,
}

impl Orientation {
    /// From the tag's value: upright for `rotate-0`.
    pub fn from_tag(tag: &str) -> Orientation {
        Orientation { tag: (tag != "rotate-0").then(|| tag.to_string()) }
    }

    /// Whether the frames are shown as stored.
    pub fn is_upright(&self) -> bool {
        self.tag.is_none()
    }

    /// Whether showing the frames swaps their width and height (a quarter turn).
    pub fn swaps_sides(&self) -> bool {
        self.tag.as_deref().is_some_and(|t| t.ends_with("-90") || t.ends_with("-270"))
    }
}

/// Which frames a reader delivers: as shown by players, or as stored in the file.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FrameTurn {
    /// Turned as the video's [`Orientation`] tag says (no turn without one).
    AsShown,
    /// As stored, whatever the tag says.
    AsStored,
}

/// What a probe learned of a video without decoding it.
#[derive(Clone, Debug, PartialEq)]
pub struct VideoProbe {
    /// Width of the stored frames, pixels.
    pub width: u32,
    /// Height of the stored frames, pixels.
    pub height: u32,
    /// How the frames are to be turned for display.
    pub orientation: Orientation,
    /// Presentation time of every frame, seconds, increasing.
    pub frame_times: Vec<f64>,
    /// The codec as GStreamer names its caps (`video/x-h264`, `image/jpeg`, ...).
    pub codec: String,
}

impl VideoProbe {
    /// Width and height of the frames `turn` delivers.
    pub fn frame_size(&self, turn: FrameTurn) -> (u32, u32) {
        match turn {
            FrameTurn::AsShown if self.orientation.swaps_sides() => (self.height, self.width),
            _ => (self.width, self.height),
        }
    }
}

/// Starts GStreamer once per process and makes sure no hardware decoder is autoplugged.
pub(crate) fn init_gstreamer() -> Result<(), String> {
    static START: Once = Once::new();
    static FAILED: Mutex<Option<String>> = Mutex::new(None);
    START.call_once(|| match gst::init() {
        Ok(()) => {
            let registry = gst::Registry::get();
            for feature in registry.features(gst::ElementFactory::static_type()) {
                let Ok(factory) = feature.clone().downcast::<gst::ElementFactory>() else { continue };
                if factory.klass().contains("Hardware") {
                    feature.set_rank(gst::Rank::NONE);
                }
                // libav's MJPEG decoder keeps 4:4:4 chroma; GStreamer's jpegdec turned
                // ffmpeg-written MJPEG into 4:2:0 with shifted colours (mean error 11.7
                // levels against 1.3 for libav, measured on a test pattern).
                if factory.name() == "jpegdec" {
                    feature.set_rank(gst::Rank::MARGINAL);
                }
            }
        }
        Err(error) => {
            if let Ok(mut failed) = FAILED.lock() {
                *failed = Some(format!("GStreamer could not start: {error}"));
            }
        }
    });
    match FAILED.lock() {
        Ok(failed) => failed.clone().map_or(Ok(()), Err),
        Err(_) => Err("GStreamer's start-up panicked".into()),
    }
}

fn make(factory: &str, path: &Path) -> Result<gst::Element, VideoError> {
    gst::ElementFactory::make(factory).build().map_err(|_| VideoError::Open {
        path: path.to_owned(),
        problem: format!(
            "GStreamer element `{factory}` is missing (Debian: apt-get install gstreamer1.0-plugins-base \
             gstreamer1.0-plugins-good gstreamer1.0-libav)"
        ),
    })
}

/// Whether a stream's caps are video (MJPEG's are `image/jpeg`).
fn is_video(caps: &gst::CapsRef) -> bool {
    caps.structure(0).is_some_and(|s| s.name().starts_with("video/") || s.name().starts_with("image/"))
}

/// The first error message on the bus, if any.
pub(crate) fn bus_error(pipeline: &gst::Pipeline) -> Option<String> {
    let bus = pipeline.bus()?;
    while let Some(message) = bus.pop_filtered(&[gst::MessageType::Error]) {
        if let gst::MessageView::Error(error) = message.view() {
            let detail = error.debug().map(|d| format!(" ({d})")).unwrap_or_default();
            return Some(format!("{}{detail}", error.error()));
        }
    }
    None
}

/// What a pull got: a sample, the end of the stream, or nothing, with the pipeline's error
/// when it reported one.
enum Pulled {
    Sample(gst::Sample),
    Eos,
    Stopped(Option<String>),
}

/// Pulls the next sample, giving up as soon as the pipeline reports an error or after
/// `timeout_s` without one.
fn pull_sample(pipeline: &gst::Pipeline, sink: &gst_app::AppSink, timeout_s: u64) -> Pulled {
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(timeout_s);
    loop {
        if let Some(sample) = sink.try_pull_sample(gst::ClockTime::from_mseconds(PULL_SLICE_MS)) {
            return Pulled::Sample(sample);
        }
        if sink.is_eos() {
            return Pulled::Eos;
        }
        if let Some(problem) = bus_error(pipeline) {
            // Samples queued before the error are still the video's.
            return match sink.try_pull_sample(gst::ClockTime::ZERO) {
                Some(sample) => {
                    pending_error(pipeline, problem);
                    Pulled::Sample(sample)
                }
                None => Pulled::Stopped(Some(problem)),
            };
        }
        if std::time::Instant::now() >= deadline {
            return Pulled::Stopped(None);
        }
    }
}

/// Puts an error back on the bus for the next pull to find.
fn pending_error(pipeline: &gst::Pipeline, problem: String) {
    if let Some(bus) = pipeline.bus() {
        let error = gst::message::Error::builder(gst::CoreError::Failed, &problem).build();
        let _ = bus.post(error);
    }
}

/// A source and a demuxing or decoding bin whose video pad is linked to `sink` once known.
fn source_into(
    pipeline: &gst::Pipeline,
    path: &Path,
    bin_factory: &str,
    sink: &gst::Element,
) -> Result<gst::Element, VideoError> {
    let src = make("filesrc", path)?;
    src.set_property("location", path.to_string_lossy().as_ref());
    let bin = make(bin_factory, path)?;
    let link_error = |e: gst::glib::BoolError| VideoError::Open { path: path.to_owned(), problem: e.to_string() };
    pipeline.add_many([&src, &bin]).map_err(link_error)?;
    src.link(&bin).map_err(link_error)?;
    let sink_weak = sink.downgrade();
    bin.connect_pad_added(move |_, pad| {
        let Some(sink) = sink_weak.upgrade() else { return };
        let Some(target) = sink.static_pad("sink") else { return };
        let caps = pad.current_caps().unwrap_or_else(|| pad.query_caps(None));
        if !target.is_linked() && is_video(&caps) {
            // A failure leaves the sink unlinked; the pull then reports the file as unreadable.
            let _ = pad.link(&target);
        }
    });
    Ok(bin)
}

/// A buffer time in stream time, the time seeks are expressed in: the segment maps buffer
/// times to it (an mp4 with B-frames has buffer times shifted by its decoding delay).
fn stream_time(sample: &gst::Sample, pts: gst::ClockTime) -> gst::ClockTime {
    sample
        .segment()
        .and_then(|segment| segment.downcast_ref::<gst::ClockTime>())
        .and_then(|segment| segment.to_stream_time(pts))
        .unwrap_or(pts)
}

/// Lists a video's frames from its demuxed packets, without decoding: size, codec and the
/// presentation time of every frame.
pub fn probe(path: &Path) -> Result<VideoProbe, VideoError> {
    init_gstreamer().map_err(|problem| VideoError::Open { path: path.to_owned(), problem })?;
    let open_error = |problem: String| VideoError::Open { path: path.to_owned(), problem };
    if !path.is_file() {
        return Err(open_error("no such file".into()));
    }
    let pipeline = gst::Pipeline::new();
    let sink = gst_app::AppSink::builder().sync(false).max_buffers(64).build();
    pipeline.add(&sink).map_err(|e| open_error(e.to_string()))?;
    source_into(&pipeline, path, "parsebin", sink.upcast_ref())?;
    // The demuxer sends the container's tags downstream ahead of the first packet.
    let orientation_tag = std::sync::Arc::new(Mutex::new(None::<String>));
    if let Some(pad) = sink.static_pad("sink") {
        let found = orientation_tag.clone();
        pad.add_probe(gst::PadProbeType::EVENT_DOWNSTREAM, move |_, info| {
            if let Some(gst::EventView::Tag(tag)) = info.event().map(|e| e.view()) {
                if let Some(value) = tag.tag().get::<gst::tags::ImageOrientation>() {
                    if let Ok(mut slot) = found.lock() {
                        *slot = Some(value.get().to_string());
                    }
                }
            }
            gst::PadProbeReturn::Ok
        });
    }
    let stop = |pipeline: &gst::Pipeline| {
        let _ = pipeline.set_state(gst::State::Null);
    };
    if pipeline.set_state(gst::State::Playing).is_err() {
        let problem = bus_error(&pipeline).unwrap_or_else(|| "cannot be opened".into());
        stop(&pipeline);
        return Err(open_error(format!("not a readable video: {problem}")));
    }
    let mut times: Vec<gst::ClockTime> = Vec::new();
    let mut codec = String::new();
    let mut fallback_interval: Option<gst::ClockTime> = None;
    loop {
        let timeout_s = if times.is_empty() && codec.is_empty() { FIRST_PACKET_TIMEOUT_S } else { PULL_TIMEOUT_S };
        match pull_sample(&pipeline, &sink, timeout_s) {
            Pulled::Sample(sample) => {
                if codec.is_empty() {
                    if let Some(s) = sample.caps().and_then(|c| c.structure(0)) {
                        codec = s.name().to_string();
                        if let Ok(rate) = s.get::<gst::Fraction>("framerate") {
                            if rate.numer() > 0 && rate.denom() > 0 {
                                fallback_interval = Some(gst::ClockTime::from_nseconds(
                                    1_000_000_000 * rate.denom() as u64 / rate.numer() as u64,
                                ));
                            }
                        }
                    }
                }
                let Some(buffer) = sample.buffer() else { continue };
                // Codec headers travel as buffers of their own in some containers.
                if buffer.flags().contains(gst::BufferFlags::HEADER) && buffer.pts().is_none() {
                    continue;
                }
                let time = buffer.pts().or(buffer.dts()).or_else(|| {
                    fallback_interval.map(|step| gst::ClockTime::from_nseconds(step.nseconds() * times.len() as u64))
                });
                match time {
                    Some(time) => times.push(stream_time(&sample, time)),
                    None => {
                        stop(&pipeline);
                        return Err(open_error("its packets carry no timestamps and no frame rate".into()));
                    }
                }
            }
            Pulled::Eos => break,
            Pulled::Stopped(problem) => {
                let problem = problem.unwrap_or_else(|| {
                    if times.is_empty() {
                        format!(
                            "no packet within {FIRST_PACKET_TIMEOUT_S} s (an MP4 or MOV file cut before its index has \
                             none)"
                        )
                    } else {
                        "the demuxer stopped delivering packets".into()
                    }
                });
                stop(&pipeline);
                if times.is_empty() {
                    return Err(open_error(format!("not a readable video: {problem}")));
                }
                // A file cut short: the frames before the cut are the video.
                tracing::warn!("video `{}`: read up to frame {}: {problem}", path.display(), times.len());
                break;
            }
        }
    }
    let caps = sink.static_pad("sink").and_then(|p| p.current_caps());
    stop(&pipeline);
    if times.is_empty() {
        return Err(open_error("holds no video frame".into()));
    }
    // Packets come in decoding order; frames are shown in presentation order.
    times.sort_unstable();
    times.dedup();
    let (width, height) = caps
        .as_ref()
        .and_then(|c| c.structure(0))
        .and_then(|s| Some((s.get::<i32>("width").ok()?, s.get::<i32>("height").ok()?)))
        .filter(|&(w, h)| w > 0 && h > 0)
        .ok_or_else(|| open_error("the stream does not say its frame size".into()))?;
    let orientation = orientation_tag.lock().ok().and_then(|t| t.clone()).map(|t| Orientation::from_tag(&t));
    Ok(VideoProbe {
        width: width as u32,
        height: height as u32,
        orientation: orientation.unwrap_or_default(),
        frame_times: times.iter().map(|t| t.nseconds() as f64 * 1e-9).collect(),
        codec,
    })
}

/// A decoding pipeline positioned somewhere in one video.
pub struct VideoReader {
    path: PathBuf,
    pipeline: gst::Pipeline,
    sink: gst_app::AppSink,
    /// Presentation time of every frame in stream time, nanoseconds, as the probe found them.
    frame_times: Vec<u64>,
    width: u32,
    height: u32,
    /// Index of the frame the next pulled buffer is expected to be.
    position: usize,
    /// A decoded frame pulled ahead of its turn (the one after a frame the decoder dropped).
    pending: Option<(usize, gst::Sample)>,
    /// Whether the pipeline has been started.
    started: bool,
}

impl std::fmt::Debug for VideoReader {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("VideoReader").field("path", &self.path).field("position", &self.position).finish()
    }
}

impl VideoReader {
    /// A decoder for `path`, whose frames the probe listed, delivering them as `turn` says.
    pub fn open(path: &Path, probe: &VideoProbe, turn: FrameTurn) -> Result<VideoReader, VideoError> {
        init_gstreamer().map_err(|problem| VideoError::Open { path: path.to_owned(), problem })?;
        let open_error = |problem: String| VideoError::Open { path: path.to_owned(), problem };
        let pipeline = gst::Pipeline::new();
        // Formats our conversion reads; videoconvert passes them through untouched and turns
        // anything else (NV12, BGRx, GBR planar, ...) into one of them.
        let caps =
            gst::Caps::builder("video/x-raw").field("format", gst::List::new(["I420", "Y42B", "Y444", "RGB"])).build();
        let sink = gst_app::AppSink::builder().caps(&caps).sync(false).max_buffers(3).drop(false).build();
        let convert = make("videoconvert", path)?;
        pipeline.add_many([&convert, sink.upcast_ref()]).map_err(|e| open_error(e.to_string()))?;
        convert.link(&sink).map_err(|e| open_error(e.to_string()))?;
        // `auto` follows the orientation tag the decoder passes on, as players do. The flip
        // takes fewer formats than decoders give (not 4:2:2 or planar RGB): a conversion
        // ahead of it passes the usual 4:2:0 through.
        let first = if turn == FrameTurn::AsShown && !probe.orientation.is_upright() {
            let to_flip = make("videoconvert", path)?;
            let flip = make("videoflip", path)?;
            flip.set_property_from_str("video-direction", "auto");
            pipeline.add_many([&to_flip, &flip]).map_err(|e| open_error(e.to_string()))?;
            gst::Element::link_many([&to_flip, &flip, &convert]).map_err(|e| open_error(e.to_string()))?;
            to_flip
        } else {
            convert
        };
        let decode = source_into(&pipeline, path, "decodebin", &first)?;
        let (width, height) = probe.frame_size(turn);
        // A corrupt packet must cost its frame, not the stream: decoders give up after 10
        // errors in a row by default.
        if let Some(bin) = decode.downcast_ref::<gst::Bin>() {
            bin.connect_deep_element_added(|_, _, element| {
                if element.find_property("max-errors").is_some() {
                    element.set_property("max-errors", -1i32);
                }
                // One decoding thread per camera: the cameras already decode in parallel
                // (on the shared session 0.72-0.76x of PNG reading speed, against 0.71x with
                // libav's default of a thread per core for each camera).
                if element.find_property("max-threads").is_some() {
                    element.set_property("max-threads", 1i32);
                }
            });
        }
        Ok(VideoReader {
            path: path.to_owned(),
            pipeline,
            sink,
            frame_times: probe.frame_times.iter().map(|&t| (t * 1e9).round() as u64).collect(),
            width,
            height,
            position: 0,
            pending: None,
            started: false,
        })
    }

    /// Number of frames.
    pub fn len(&self) -> usize {
        self.frame_times.len()
    }

    /// True for a video without frames (refused by the probe, so never in practice).
    pub fn is_empty(&self) -> bool {
        self.frame_times.is_empty()
    }

    fn frame_error(&self, problem: String) -> VideoError {
        VideoError::Frame { path: self.path.clone(), problem }
    }

    fn start(&mut self) -> Result<(), VideoError> {
        if self.started {
            return Ok(());
        }
        if self.pipeline.set_state(gst::State::Paused).is_err() {
            let problem = bus_error(&self.pipeline).unwrap_or_else(|| "the decoder would not start".into());
            return Err(VideoError::Open { path: self.path.clone(), problem });
        }
        // Prerolled, so that a seek can follow at once.
        let (result, _, _) = self.pipeline.state(gst::ClockTime::from_seconds(PULL_TIMEOUT_S));
        if result.is_err() {
            let problem = bus_error(&self.pipeline).unwrap_or_else(|| "the decoder did not preroll".into());
            return Err(VideoError::Open { path: self.path.clone(), problem });
        }
        if self.pipeline.set_state(gst::State::Playing).is_err() {
            let problem = bus_error(&self.pipeline).unwrap_or_else(|| "the decoder would not play".into());
            return Err(VideoError::Open { path: self.path.clone(), problem });
        }
        self.started = true;
        Ok(())
    }

    fn seek(&mut self, index: usize) -> Result<(), VideoError> {
        self.pending = None;
        let time = gst::ClockTime::from_nseconds(self.frame_times[index]);
        self.pipeline
            .seek_simple(gst::SeekFlags::FLUSH | gst::SeekFlags::ACCURATE, time)
            .map_err(|e| self.frame_error(format!("cannot seek to frame {index}: {e}")))?;
        self.position = index;
        Ok(())
    }

    /// The frame index of a decoded buffer's presentation time: the listed frame nearest to
    /// it, if within half a frame interval.
    fn index_of(&self, pts: u64) -> Option<usize> {
        let i = self.frame_times.partition_point(|&t| t < pts);
        let candidates = [i.checked_sub(1), Some(i)];
        let nearest = candidates
            .into_iter()
            .flatten()
            .filter(|&k| k < self.frame_times.len())
            .min_by_key(|&k| self.frame_times[k].abs_diff(pts))?;
        let interval = if self.frame_times.len() > 1 {
            (self.frame_times[self.frame_times.len() - 1] - self.frame_times[0]) / (self.frame_times.len() as u64 - 1)
        } else {
            u64::MAX
        };
        (self.frame_times[nearest].abs_diff(pts) <= interval / 2).then_some(nearest)
    }

    fn pull(&mut self) -> Result<Option<(usize, gst::Sample)>, VideoError> {
        if let Some(pending) = self.pending.take() {
            return Ok(Some(pending));
        }
        loop {
            let sample = match pull_sample(&self.pipeline, &self.sink, PULL_TIMEOUT_S) {
                Pulled::Sample(sample) => sample,
                Pulled::Eos => return Ok(None),
                Pulled::Stopped(problem) => {
                    let problem = problem.unwrap_or_else(|| "the decoder stopped delivering frames".into());
                    return Err(self.frame_error(problem));
                }
            };
            let Some(pts) = sample.buffer().and_then(|b| b.pts()) else { continue };
            let pts = stream_time(&sample, pts);
            match self.index_of(pts.nseconds()) {
                Some(index) => return Ok(Some((index, sample))),
                None => tracing::debug!("video `{}`: a decoded frame at {pts} is not listed", self.path.display()),
            }
        }
    }

    /// Decodes frame `index` as RGB8 straight into `dst` (exactly `width * height * 3`
    /// bytes). A frame the decoder could not produce is an error naming it; the next call
    /// goes on from there.
    pub fn read_into(&mut self, index: usize, dst: &mut [u8]) -> Result<(), VideoError> {
        if index >= self.frame_times.len() {
            return Err(self.frame_error(format!("has {} frames; frame {index} does not exist", self.len())));
        }
        self.start()?;
        if index < self.position || index > self.position + MAX_DECODE_THROUGH {
            self.seek(index)?;
        }
        loop {
            let Some((at, sample)) = self.pull()? else {
                self.position = self.frame_times.len();
                return Err(self.frame_error(format!("ends before frame {index}")));
            };
            if at < index {
                continue;
            }
            self.position = at + 1;
            if at > index {
                self.pending = Some((at, sample));
                self.position = at;
                return Err(self.frame_error(format!("frame {index} could not be decoded (corrupt or missing)")));
            }
            return self.convert(&sample, index, dst);
        }
    }

    fn convert(&self, sample: &gst::Sample, index: usize, dst: &mut [u8]) -> Result<(), VideoError> {
        let (Some(buffer), Some(caps)) = (sample.buffer(), sample.caps()) else {
            return Err(self.frame_error(format!("frame {index}: the decoder gave no image")));
        };
        if buffer.flags().contains(gst::BufferFlags::CORRUPTED) {
            return Err(self.frame_error(format!("frame {index} is corrupt (the decoder concealed damage)")));
        }
        let info = gst_video::VideoInfo::from_caps(caps)
            .map_err(|e| self.frame_error(format!("frame {index}: unusable caps: {e}")))?;
        if (info.width(), info.height()) != (self.width, self.height) {
            return Err(self.frame_error(format!(
                "frame {index} is {}x{}, the video started at {}x{}",
                info.width(),
                info.height(),
                self.width,
                self.height
            )));
        }
        let frame = gst_video::VideoFrameRef::from_buffer_ref_readable(buffer, &info)
            .map_err(|e| self.frame_error(format!("frame {index}: cannot map the decoded image: {e}")))?;
        let plane = |k: u32| -> Result<(&[u8], usize), VideoError> {
            let data = frame.plane_data(k).map_err(|e| self.frame_error(format!("frame {index}: plane {k}: {e}")))?;
            Ok((data, frame.plane_stride()[k as usize] as usize))
        };
        let (w, h) = (self.width as usize, self.height as usize);
        match info.format() {
            gst_video::VideoFormat::Rgb => {
                let (data, stride) = plane(0)?;
                yuv::copy_rgb_rows(data, stride, w, h, dst).map_err(|p| self.frame_error(format!("frame {index}: {p}")))
            }
            format => {
                let (sx, sy) = match format {
                    gst_video::VideoFormat::I420 => (1, 1),
                    gst_video::VideoFormat::Y42b => (1, 0),
                    gst_video::VideoFormat::Y444 => (0, 0),
                    other => return Err(self.frame_error(format!("frame {index}: unexpected pixel format {other:?}"))),
                };
                // A stream that does not say its colorimetry gets GStreamer's guess from its
                // size (BT.709 from 720 lines up), but such files are mostly written by
                // OpenCV and ffmpeg, whose default is BT.601 limited range, which is also
                // how ffmpeg (and the tools built on it) decode them.
                let signalled = caps.structure(0).is_some_and(|s| s.has_field("colorimetry"));
                let colorimetry = info.colorimetry();
                let matrix = match colorimetry.matrix() {
                    _ if !signalled => ColourMatrix::Bt601,
                    gst_video::VideoColorMatrix::Bt709 => ColourMatrix::Bt709,
                    gst_video::VideoColorMatrix::Bt2020 => ColourMatrix::Bt2020,
                    _ => ColourMatrix::Bt601,
                };
                let full_range = signalled && colorimetry.range() == gst_video::VideoColorRange::Range0_255;
                let planes = [plane(0)?, plane(1)?, plane(2)?];
                yuv::planar_to_rgb(
                    &yuv::Planes { planes, chroma_shift: (sx, sy) },
                    w,
                    h,
                    &yuv::Conversion::new(matrix, full_range),
                    dst,
                )
                .map_err(|p| self.frame_error(format!("frame {index}: {p}")))
            }
        }
    }
}

impl Drop for VideoReader {
    fn drop(&mut self) {
        let _ = self.pipeline.set_state(gst::State::Null);
    }
}
