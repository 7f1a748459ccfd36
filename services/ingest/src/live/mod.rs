//! Live cameras: V4L2 webcams, RTSP/HTTP network cameras, video files paced as cameras and
//! any GStreamer source, each stamped on one clock ([`camera`]), grouped into frame sets by
//! capture time ([`sync`]).

pub mod camera;
pub mod feed;
pub mod sync;
pub mod writer;

use serde::{Deserialize, Serialize};

pub use camera::{CameraSource, LiveCamera, LiveCameraError, StartOptions};
pub use feed::{CameraFeed, FeedEvent, FeedSpec};
pub use sync::{CameraSyncStats, FrameSetSync, TimedFrame};
pub use writer::{RecordingWriter, VideoFileWriter, WriteError, WEBM_VP8};

/// One camera of a live pipeline, as the pipeline file names it:
///
/// ```toml
/// [[cameras]]
/// name = "cam_0"                    # the camera's name in the calibration
/// source = "v4l2:///dev/video0"     # see `CameraSource`
/// size = [1280, 720]                # optional: negotiated with the device; default the calibration's
/// fps = 30                          # optional: negotiated with the device
/// ```
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct LiveCameraSpec {
    /// The camera's name in the calibration.
    pub name: String,
    /// Where its frames come from ([`CameraSource::parse`]).
    pub source: String,
    /// Frame size to ask the device for, pixels (default: the calibration's).
    #[serde(default)]
    pub size: Option<[u32; 2]>,
    /// Frame rate to ask the device for.
    #[serde(default)]
    pub fps: Option<f64>,
}
