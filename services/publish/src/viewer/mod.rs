//! The live viewer served by the publisher stage: a page with a 3D view of head and hands,
//! per-camera thumbnails with the tracks drawn, each track's state and the pipeline's health.
//!
//! It never slows the pipeline: the publisher hands each sample over without waiting
//! ([`Viewer::publish`]), the HTTP side runs on its own thread ([`server`]), a thread of its
//! own reads the rig, frames and cameras' health from shared memory ([`monitor`]), and a
//! client that reads too slowly skips samples.

pub mod figures;
pub mod monitor;
pub mod server;
pub mod thumbnails;

use std::net::{SocketAddr, TcpListener};
use std::sync::atomic::AtomicUsize;
use std::sync::{mpsc, Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use axum::body::Bytes;
use axum::extract::ws::Utf8Bytes;
use handflow_protocol::ipc::{Mode, ServiceNames};
use handflow_protocol::messages::TrajectorySample;
use handflow_protocol::Rig;
use serde_json::{json, Value};
use tokio::sync::broadcast;

use figures::StreamFigures;

use crate::TrajectoryRecord;

/// Default address of the viewer: loopback only.
pub const DEFAULT_ADDRESS: &str = "127.0.0.1:8787";
/// Samples a client may fall behind before it skips some.
const SAMPLE_BACKLOG: usize = 256;
/// Thumbnails a client may fall behind before it skips some.
const THUMBNAIL_BACKLOG: usize = 16;

/// How the viewer runs.
#[derive(Clone, Debug)]
pub struct ViewerOptions {
    /// Where to listen.
    pub address: SocketAddr,
    /// Thumbnails per second per camera (0: none).
    pub thumbnail_hz: f64,
    /// The pipeline's services.
    pub services: String,
    /// Delivery mode of the pipeline.
    pub mode: Mode,
}

/// What the HTTP side and the monitor share.
pub struct Shared {
    address: SocketAddr,
    services: String,
    mode: Mode,
    started: Instant,
    thumbnail_hz: f64,
    figures: Mutex<StreamFigures>,
    rig: Mutex<Option<Value>>,
    cameras: Mutex<Vec<Value>>,
    stages: Mutex<Vec<(&'static str, bool)>>,
    latest_thumbnails: Mutex<Vec<Option<Bytes>>>,
    /// Connected WebSocket clients.
    pub clients: AtomicUsize,
    samples: broadcast::Sender<Utf8Bytes>,
    thumbnails: broadcast::Sender<Bytes>,
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    // A panic elsewhere must not take the viewer down with it.
    m.lock().unwrap_or_else(PoisonError::into_inner)
}

impl Shared {
    fn new(address: SocketAddr, options: &ViewerOptions) -> Self {
        Self {
            address,
            services: options.services.clone(),
            mode: options.mode,
            started: Instant::now(),
            thumbnail_hz: options.thumbnail_hz,
            figures: Mutex::default(),
            rig: Mutex::default(),
            cameras: Mutex::default(),
            stages: Mutex::default(),
            latest_thumbnails: Mutex::default(),
            clients: AtomicUsize::new(0),
            samples: broadcast::channel(SAMPLE_BACKLOG).0,
            thumbnails: broadcast::channel(THUMBNAIL_BACKLOG).0,
        }
    }

    /// The body of `/api/status`.
    pub fn status_json(&self) -> Value {
        let now = Instant::now();
        let (stream, tracks) = lock(&self.figures).to_json(now);
        let stages: Vec<Value> =
            lock(&self.stages).iter().map(|(name, alive)| json!({ "name": name, "alive": alive })).collect();
        json!({
            "pipeline": self.services,
            "mode": self.mode.to_string(),
            "uptime_s": now.duration_since(self.started).as_secs_f64(),
            "stream": stream,
            "tracks": tracks,
            "cameras": *lock(&self.cameras),
            "stages": stages,
            "viewer": {
                "address": format!("http://{}/", self.address),
                "clients": self.clients.load(std::sync::atomic::Ordering::Relaxed),
                "thumbnail_hz": self.thumbnail_hz,
            },
        })
    }

    /// The body of `/api/rig`, once the rig is known.
    pub fn rig_json(&self) -> Option<Value> {
        lock(&self.rig).clone()
    }

    fn latest_thumbnails(&self) -> Vec<Bytes> {
        lock(&self.latest_thumbnails).iter().flatten().cloned().collect()
    }

    fn set_rig(&self, rig: &Rig, frame_rate_hz: f64) {
        *lock(&self.rig) = Some(rig_json(rig, frame_rate_hz));
        *lock(&self.cameras) = rig
            .cameras
            .iter()
            .map(|c| {
                json!({ "name": c.name, "state": self.mode.to_string(), "rate_hz": null, "delivered": null,
                             "dropped": null, "missed_sets": null, "last_frame_age_s": null })
            })
            .collect();
        lock(&self.latest_thumbnails).clear();
    }

    fn send_thumbnail(&self, index: usize, message: Bytes) {
        {
            let mut latest = lock(&self.latest_thumbnails);
            if latest.len() <= index {
                latest.resize(index + 1, None);
            }
            latest[index] = Some(message.clone());
        }
        // No client connected is not an error.
        let _ = self.thumbnails.send(message);
    }
}

/// The rig as the page draws it: each camera's centre, axes and fields of view in the world.
pub fn rig_json(rig: &Rig, frame_rate_hz: f64) -> Value {
    let cameras: Vec<Value> = rig
        .cameras
        .iter()
        .map(|c| {
            let to_world = c.rotation.inverse();
            let axis = |v: nalgebra::Vector3<f64>| {
                let w = to_world * v;
                [w.x, w.y, w.z]
            };
            let (fx, fy) = (c.matrix[(0, 0)], c.matrix[(1, 1)]);
            let centre = c.centre();
            json!({
                "name": c.name,
                "width": c.width,
                "height": c.height,
                "centre": [centre.x, centre.y, centre.z],
                "forward": axis(nalgebra::Vector3::z()),
                "up": axis(-nalgebra::Vector3::y()),
                "right": axis(nalgebra::Vector3::x()),
                "fov_x_deg": (2.0 * (f64::from(c.width) / (2.0 * fx)).atan()).to_degrees(),
                "fov_y_deg": (2.0 * (f64::from(c.height) / (2.0 * fy)).atan()).to_degrees(),
            })
        })
        .collect();
    let up = rig.world_up().direction;
    json!({ "cameras": cameras, "up": [up.x, up.y, up.z], "frame_rate_hz": frame_rate_hz })
}

/// The running viewer, as the publisher holds it.
pub struct Viewer {
    shared: Arc<Shared>,
    to_monitor: mpsc::SyncSender<TrajectoryRecord>,
    address: SocketAddr,
}

impl Viewer {
    /// Listens on `options.address` and starts the viewer's threads. Fails only when the
    /// address cannot be listened on.
    pub fn start(options: &ViewerOptions) -> Result<Viewer> {
        let listener = TcpListener::bind(options.address)
            .with_context(|| format!("listening on {} for the viewer", options.address))?;
        let address = listener.local_addr().context("the viewer's address")?;
        let shared = Arc::new(Shared::new(address, options));
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .context("starting the viewer's runtime")?;
        let server_shared = Arc::clone(&shared);
        std::thread::Builder::new()
            .name("viewer-http".into())
            .spawn(move || {
                if let Err(e) = runtime.block_on(server::serve(listener, server_shared)) {
                    tracing::error!("viewer: the HTTP server stopped: {e}");
                }
            })
            .context("starting the viewer's HTTP thread")?;
        // Samples for the thumbnails' tracks: bounded, and dropped rather than waited for.
        let (to_monitor, from_publisher) = mpsc::sync_channel(SAMPLE_BACKLOG);
        let monitor_shared = Arc::clone(&shared);
        let names = ServiceNames::new(&options.services);
        let interval = (options.thumbnail_hz > 0.0).then(|| Duration::from_secs_f64(1.0 / options.thumbnail_hz));
        std::thread::Builder::new()
            .name("viewer-monitor".into())
            .spawn(move || monitor::run(&monitor_shared, &names, interval, &from_publisher))
            .context("starting the viewer's monitor thread")?;
        Ok(Viewer { shared, to_monitor, address })
    }

    /// The address the viewer listens on.
    pub fn address(&self) -> SocketAddr {
        self.address
    }

    /// Hands a published sample (and its record) to the viewer; never waits.
    pub fn publish(&self, sample: &TrajectorySample, record: &TrajectoryRecord) {
        lock(&self.shared.figures).on_sample(sample, record, Instant::now());
        let _ = self.shared.samples.send(Utf8Bytes::from(figures::sample_message(sample, record)));
        if !sample.is_end_of_stream() {
            let _ = self.to_monitor.try_send(record.clone());
        }
    }
}
