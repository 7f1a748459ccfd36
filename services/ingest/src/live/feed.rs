//! A live camera that comes back: a device unplugged and plugged in again, a network camera
//! that drops off the network or restarts. A source that fails, ends when it cannot end (a
//! device or a network stream), or delivers nothing for a while in a live stream is closed
//! and opened again, at growing intervals, while the rest of the rig goes on without it.
//! A video played as a camera is not reopened: its end is the end of the recording, and its
//! failure a broken file.

use std::time::{Duration, Instant};

use super::camera::{CameraSource, LiveCamera, StartOptions};
use super::sync::TimedFrame;

/// First wait before a lost camera is opened again; doubled after each failed attempt.
const FIRST_RETRY: Duration = Duration::from_millis(250);
/// Longest wait between attempts: a camera that comes back is found within this.
const MAX_RETRY: Duration = Duration::from_secs(1);
/// A live camera that delivers nothing for this long (and at least this many of its frame
/// intervals) is taken as lost: a network stream can stall without an error.
const SILENCE: Duration = Duration::from_secs(3);
const SILENCE_INTERVALS: u32 = 30;

/// What [`CameraFeed::poll`] found.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum FeedEvent {
    /// Nothing changed.
    Unchanged,
    /// The camera was lost and will be opened again; why.
    Lost(String),
    /// A lost camera is delivering again, after this many attempts.
    Back {
        /// Attempts it took.
        attempts: u32,
        /// How long it was away.
        away: Duration,
    },
    /// The camera stopped for good: a video that failed; why.
    Failed(String),
}

/// How a camera is opened, kept to open it again.
#[derive(Clone, Debug)]
pub struct FeedSpec {
    /// The camera's name.
    pub name: String,
    /// Its source.
    pub source: CameraSource,
    /// Its calibration's frame size.
    pub width: u32,
    /// Its calibration's frame size.
    pub height: u32,
    /// Size asked of a device.
    pub size: Option<[u32; 2]>,
    /// Rate asked of a device, frames per second.
    pub fps: Option<f64>,
    /// How it is started the first time.
    pub options: StartOptions,
    /// Whether silence means loss (a live stream; a replay holds its cameras back, and a
    /// camera held back is silent).
    pub detect_silence: bool,
}

/// One camera of the rig, opened again when it is lost.
pub struct CameraFeed {
    spec: FeedSpec,
    camera: Option<LiveCamera>,
    /// Counts of the camera's earlier openings.
    delivered_before: u64,
    dropped_before: u64,
    /// Delivered count at the last check, and when it last grew.
    last_delivered: u64,
    last_growth: Instant,
    /// Lost since, the attempts made and when the next is due.
    lost_at: Option<Instant>,
    attempts: u32,
    next_attempt: Instant,
    failure: Option<String>,
    reconnections: u32,
}

impl std::fmt::Debug for CameraFeed {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CameraFeed").field("name", &self.spec.name).field("lost", &self.lost_at.is_some()).finish()
    }
}

impl CameraFeed {
    /// A feed of an already started camera.
    pub fn new(spec: FeedSpec, camera: LiveCamera) -> Self {
        let now = Instant::now();
        Self {
            spec,
            camera: Some(camera),
            delivered_before: 0,
            dropped_before: 0,
            last_delivered: 0,
            last_growth: now,
            lost_at: None,
            attempts: 0,
            next_attempt: now,
            failure: None,
            reconnections: 0,
        }
    }

    /// Whether a source of this kind is opened again when lost.
    pub fn reopens(source: &CameraSource) -> bool {
        !matches!(source, CameraSource::File { .. })
    }

    /// The camera's name.
    pub fn name(&self) -> &str {
        &self.spec.name
    }

    /// Whether the camera is lost and being opened again.
    pub fn is_lost(&self) -> bool {
        self.lost_at.is_some()
    }

    /// Times a lost camera came back.
    pub fn reconnections(&self) -> u32 {
        self.reconnections
    }

    /// The next frame if one is waiting.
    pub fn try_frame(&self) -> Option<TimedFrame> {
        self.camera.as_ref().and_then(LiveCamera::try_frame)
    }

    /// The next frame, waiting up to `timeout`.
    pub fn frame_timeout(&self, timeout: Duration) -> Option<TimedFrame> {
        self.camera.as_ref().and_then(|c| c.frame_timeout(timeout))
    }

    /// Frames delivered over every opening.
    pub fn delivered(&self) -> u64 {
        self.delivered_before + self.camera.as_ref().map_or(0, LiveCamera::delivered)
    }

    /// Frames lost in the hand-over over every opening.
    pub fn handover_dropped(&self) -> u64 {
        self.dropped_before + self.camera.as_ref().map_or(0, LiveCamera::handover_dropped)
    }

    /// Whether the source has ended for good: a video, or a GStreamer description that ends
    /// (a device or a network stream that ends was cut, and is opened again).
    pub fn ended(&self) -> bool {
        !Self::ends_when_cut(&self.spec.source) && self.camera.as_ref().is_some_and(LiveCamera::ended)
    }

    /// Whether the end of this kind of source means it was cut off.
    fn ends_when_cut(source: &CameraSource) -> bool {
        matches!(source, CameraSource::V4l2 { .. } | CameraSource::Network { .. })
    }

    /// Why the camera stopped for good, if it did.
    pub fn failure(&self) -> Option<String> {
        self.failure.clone()
    }

    /// Looks at the camera: a lost one is closed (frames still in its hand-over go with it:
    /// take them first), a lost one whose next attempt is due is opened again. Call it
    /// often; it does not block for long (closing a network source is done on a thread of
    /// its own).
    pub fn poll(&mut self, now: Instant) -> FeedEvent {
        if self.failure.is_some() {
            return FeedEvent::Unchanged;
        }
        let Some(camera) = &self.camera else {
            if now >= self.next_attempt {
                self.attempt(now);
            }
            return FeedEvent::Unchanged;
        };
        let delivered = camera.delivered();
        if delivered != self.last_delivered {
            self.last_delivered = delivered;
            self.last_growth = now;
        }
        let reopens = Self::reopens(&self.spec.source);
        let cut = Self::ends_when_cut(&self.spec.source) && camera.ended();
        if let Some(lost_at) = self.lost_at {
            // Opened again: back once it delivers (a network source opens before it
            // connects), tried again later if it fails, ends or stays silent.
            if delivered > 0 {
                self.lost_at = None;
                self.reconnections += 1;
                return FeedEvent::Back { attempts: self.attempts, away: now.duration_since(lost_at) };
            }
            if camera.failure().is_some() || cut || now.duration_since(self.last_growth) > self.silence() {
                if let Some(problem) = camera.failure() {
                    tracing::debug!("camera `{}`: attempt {} failed: {problem}", self.spec.name, self.attempts);
                }
                self.close();
                self.next_attempt = now + self.retry_wait();
            }
            return FeedEvent::Unchanged;
        }
        let why = if let Some(problem) = camera.failure() {
            Some(problem)
        } else if cut {
            // A device or a network stream does not end by itself: it was cut.
            Some("its stream ended".to_string())
        } else if reopens
            && self.spec.detect_silence
            && !camera.ended()
            && now.duration_since(self.last_growth) > self.silence()
        {
            Some(format!("no frame for {:.1} s", now.duration_since(self.last_growth).as_secs_f64()))
        } else {
            None
        };
        let Some(why) = why else { return FeedEvent::Unchanged };
        if !reopens {
            self.failure = Some(why.clone());
            return FeedEvent::Failed(why);
        }
        self.close();
        self.lost_at = Some(now);
        self.attempts = 0;
        self.next_attempt = now + FIRST_RETRY;
        FeedEvent::Lost(why)
    }

    /// Opens a lost camera again (it is back once it delivers).
    fn attempt(&mut self, now: Instant) {
        self.attempts += 1;
        // Opened again on its own timeline: a rig start long past means nothing now.
        let options = StartOptions { rig_start_ns: None, ..self.spec.options };
        let s = &self.spec;
        match LiveCamera::start_with(&s.name, &s.source, s.width, s.height, s.size, s.fps, options) {
            Ok(camera) => {
                self.camera = Some(camera);
                self.last_delivered = 0;
                self.last_growth = now;
            }
            Err(e) => {
                tracing::debug!("{e} (attempt {})", self.attempts);
                self.next_attempt = now + self.retry_wait();
            }
        }
    }

    /// The wait before the next attempt: doubling from the first, up to the longest.
    fn retry_wait(&self) -> Duration {
        FIRST_RETRY.saturating_mul(1 << self.attempts.min(8)).min(MAX_RETRY)
    }

    /// How long this camera may stay silent before it is taken as lost.
    fn silence(&self) -> Duration {
        let interval = self
            .spec
            .fps
            .filter(|f| f.is_finite() && *f > 0.0)
            .map_or(Duration::ZERO, |f| Duration::from_secs_f64(1.0 / f));
        SILENCE.max(interval * SILENCE_INTERVALS)
    }

    /// Closes the current opening, keeping its counts; the pipeline is torn down on a thread
    /// of its own (a network source can take a while to let go).
    fn close(&mut self) {
        if let Some(camera) = self.camera.take() {
            self.delivered_before += camera.delivered();
            self.dropped_before += camera.handover_dropped();
            self.last_delivered = 0;
            let _ = std::thread::Builder::new().name("closing camera".into()).spawn(move || drop(camera));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use gstreamer as gst;
    use gstreamer::prelude::*;
    use gstreamer_app as gst_app;
    use std::io::Write;
    use std::net::{SocketAddr, TcpListener};
    use std::sync::atomic::{AtomicBool, Ordering};
    use std::sync::Arc;

    /// One JPEG image of a test pattern, encoded by GStreamer.
    fn jpeg(width: u32, height: u32) -> Vec<u8> {
        crate::recording::video::init_gstreamer().expect("GStreamer");
        let description = format!(
            "videotestsrc num-buffers=1 pattern=ball ! video/x-raw,width={width},height={height} ! jpegenc ! \
             appsink name=sink"
        );
        let pipeline = gst::parse::launch(&description).expect("builds").downcast::<gst::Pipeline>().expect("pipeline");
        let sink = pipeline.by_name("sink").and_then(|e| e.downcast::<gst_app::AppSink>().ok()).expect("sink");
        pipeline.set_state(gst::State::Playing).expect("plays");
        let sample = sink.pull_sample().expect("a JPEG");
        let bytes = sample.buffer().expect("buffer").map_readable().expect("readable").to_vec();
        let _ = pipeline.set_state(gst::State::Null);
        bytes
    }

    /// A network camera as many are: MJPEG over HTTP, 30 frames/s to each client, until
    /// `on` is cleared (then it closes its connections and stops listening: gone from the
    /// network).
    fn mjpeg_camera(addr: SocketAddr, image: Arc<Vec<u8>>, on: Arc<AtomicBool>) -> std::thread::JoinHandle<()> {
        mjpeg_camera_with(addr, image, on, Arc::new(AtomicBool::new(true)))
    }

    /// [`mjpeg_camera`] that sends frames only while `sending` is set (connections stay open).
    fn mjpeg_camera_with(
        addr: SocketAddr,
        image: Arc<Vec<u8>>,
        on: Arc<AtomicBool>,
        sending: Arc<AtomicBool>,
    ) -> std::thread::JoinHandle<()> {
        std::thread::spawn(move || {
            let listener = TcpListener::bind(addr).expect("binds");
            listener.set_nonblocking(true).expect("non-blocking");
            let mut clients = Vec::new();
            while on.load(Ordering::Relaxed) {
                if let Ok((mut stream, _)) = listener.accept() {
                    let _ = stream.set_nonblocking(false);
                    let header = "HTTP/1.0 200 OK\r\nContent-Type: multipart/x-mixed-replace; boundary=frame\r\n\r\n";
                    if stream.write_all(header.as_bytes()).is_ok() {
                        clients.push(stream);
                    }
                }
                clients.retain_mut(|stream| {
                    if !sending.load(Ordering::Relaxed) {
                        return true;
                    }
                    let part =
                        format!("--frame\r\nContent-Type: image/jpeg\r\nContent-Length: {}\r\n\r\n", image.len());
                    stream
                        .write_all(part.as_bytes())
                        .and_then(|_| stream.write_all(&image))
                        .and_then(|_| stream.write_all(b"\r\n"))
                        .is_ok()
                });
                std::thread::sleep(Duration::from_millis(33));
            }
        })
    }

    /// Polls the feed, taking its frames, until `until` says yes of an event or `timeout`
    /// passes; returns the event and the frames taken.
    fn poll_until(
        feed: &mut CameraFeed,
        timeout: Duration,
        until: impl Fn(&FeedEvent) -> bool,
    ) -> (Option<FeedEvent>, usize) {
        let (start, mut frames) = (Instant::now(), 0);
        while start.elapsed() < timeout {
            while feed.try_frame().is_some() {
                frames += 1;
            }
            let event = feed.poll(Instant::now());
            if until(&event) {
                return (Some(event), frames);
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        (None, frames)
    }

    #[test]
    fn a_network_camera_that_drops_off_and_comes_back_is_opened_again_and_delivers() {
        let (width, height) = (64, 48);
        let image = Arc::new(jpeg(width, height));
        let addr = TcpListener::bind("127.0.0.1:0").and_then(|l| l.local_addr()).expect("a free port");
        let on = Arc::new(AtomicBool::new(true));
        let server = mjpeg_camera(addr, image.clone(), on.clone());
        std::thread::sleep(Duration::from_millis(200));
        let source = CameraSource::parse(&format!("http://{addr}/cam")).expect("parses");
        let spec = FeedSpec {
            name: "cam_1".into(),
            source: source.clone(),
            width,
            height,
            size: None,
            fps: Some(30.0),
            options: StartOptions::default(),
            detect_silence: true,
        };
        let camera = LiveCamera::start("cam_1", &source, width, height, None, Some(30.0)).expect("starts");
        let mut feed = CameraFeed::new(spec, camera);
        let (_, before) = poll_until(&mut feed, Duration::from_secs(2), |_| false);
        assert!(before > 20, "{before} frames in 2 s");

        // Off the network: lost, with the reason, and frames stop.
        on.store(false, Ordering::Relaxed);
        server.join().expect("server");
        let (lost, _) = poll_until(&mut feed, Duration::from_secs(10), |e| matches!(e, FeedEvent::Lost(_)));
        assert!(matches!(lost, Some(FeedEvent::Lost(_))), "{lost:?}");
        assert!(feed.is_lost());
        let (back, during) =
            poll_until(&mut feed, Duration::from_millis(1500), |e| matches!(e, FeedEvent::Back { .. }));
        assert_eq!((back, during), (None, 0), "nothing while it is away");

        // Back on the network: opened again within the longest retry interval, delivering.
        on.store(true, Ordering::Relaxed);
        let server = mjpeg_camera(addr, image, on.clone());
        let (back, _) = poll_until(&mut feed, Duration::from_secs(10), |e| matches!(e, FeedEvent::Back { .. }));
        assert!(matches!(back, Some(FeedEvent::Back { .. })), "{back:?}");
        let (_, after) = poll_until(&mut feed, Duration::from_secs(2), |_| false);
        assert!(after > 20, "{after} frames in 2 s after coming back");
        assert!(!feed.is_lost() && feed.reconnections() == 1 && feed.failure().is_none());
        assert!(feed.delivered() as usize >= before + after);
        on.store(false, Ordering::Relaxed);
        server.join().expect("server");
    }

    #[test]
    fn a_network_camera_that_stays_connected_but_goes_silent_is_taken_as_lost() {
        let (width, height) = (64, 48);
        let addr = TcpListener::bind("127.0.0.1:0").and_then(|l| l.local_addr()).expect("a free port");
        let (on, sending) = (Arc::new(AtomicBool::new(true)), Arc::new(AtomicBool::new(true)));
        let server = mjpeg_camera_with(addr, Arc::new(jpeg(width, height)), on.clone(), sending.clone());
        std::thread::sleep(Duration::from_millis(200));
        let source = CameraSource::parse(&format!("http://{addr}/cam")).expect("parses");
        let spec = FeedSpec {
            name: "cam_2".into(),
            source: source.clone(),
            width,
            height,
            size: None,
            fps: Some(30.0),
            options: StartOptions::default(),
            detect_silence: true,
        };
        let camera = LiveCamera::start("cam_2", &source, width, height, None, Some(30.0)).expect("starts");
        let mut feed = CameraFeed::new(spec, camera);
        let (_, before) = poll_until(&mut feed, Duration::from_secs(1), |_| false);
        assert!(before > 10, "{before} frames in 1 s");
        // The connection stays open; nothing comes: no error, no end, only silence.
        sending.store(false, Ordering::Relaxed);
        let silent_from = Instant::now();
        let (lost, _) = poll_until(&mut feed, Duration::from_secs(10), |e| matches!(e, FeedEvent::Lost(_)));
        let Some(FeedEvent::Lost(why)) = lost else { panic!("not lost: {lost:?}") };
        assert!(why.contains("no frame for"), "{why}");
        // Silence counts from its last frame, up to a frame interval before the server stopped.
        let silent_for = silent_from.elapsed();
        assert!(silent_for >= SILENCE - Duration::from_millis(100), "lost after {silent_for:?}");
        sending.store(true, Ordering::Relaxed);
        let (back, _) = poll_until(&mut feed, Duration::from_secs(10), |e| matches!(e, FeedEvent::Back { .. }));
        assert!(matches!(back, Some(FeedEvent::Back { .. })), "{back:?}");
        on.store(false, Ordering::Relaxed);
        server.join().expect("server");
    }
}
