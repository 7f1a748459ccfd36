//! The messages the stages exchange over shared memory: `#[repr(C)]` types that iceoryx2
//! sends without copying or serialising (DESIGN.md, "Data flow").
//!
//! Variable-sized messages are a fixed header (an iceoryx2 user header) in front of a slice
//! payload: the rig as TOML text, a frame set as the RGB8 bytes of every view, a particle set
//! as [`ScenePoint`]s. Labelled clusters and trajectory samples are fixed-size. Every header
//! carries [`PROTOCOL_VERSION`]; its `validate` method checks the version and that the header
//! agrees with the payload it came with, and must pass before the payload is used.
//!
//! Each message also carries the ingest `sequence` of the frame set it derives from, so the
//! last stage sees every frame lost anywhere upstream as a gap, and the capture time on the
//! wall clock (`capture_unix_ns`), so it can measure glass-to-trajectory latency.

// The derive emits `unsafe impl ZeroCopySend`: the types are `#[repr(C)]` plain data
// without pointers, which is what the trait's contract asks for.
#![allow(unsafe_code)]

use iceoryx2::prelude::ZeroCopySend;
use thiserror::Error;

/// Version of the wire format; a stage refuses messages of any other version.
pub const PROTOCOL_VERSION: u32 = 4;

/// `flags` bit: the stream has ended; the message carries no data (an empty payload).
pub const END_OF_STREAM: u32 = 1;

/// Pixel format of frame payloads: 8-bit RGB, row-major, views one after another.
pub const PIXEL_FORMAT_RGB8: u32 = 1;

/// Most views a frame set carries (the size of [`FrameHeader::view_sizes`]).
pub const MAX_FRAME_VIEWS: usize = 16;

/// Objects of the trajectory messages, in the order of their `objects` arrays.
pub const OBJECT_LABELS: [&str; 3] = ["head", "left_hand", "right_hand"];

/// A message that disagrees with itself or with this build.
#[derive(Debug, Error, PartialEq)]
pub enum MessageError {
    /// Sent by a build speaking another protocol version.
    #[error("{message}: protocol version {got}, this build speaks version {expected}")]
    Version {
        /// Message kind.
        message: &'static str,
        /// Version in the header.
        got: u32,
        /// [`PROTOCOL_VERSION`].
        expected: u32,
    },
    /// A header field disagrees with the payload or is out of range.
    #[error("{message} {sequence}: {field} {detail}")]
    Field {
        /// Message kind.
        message: &'static str,
        /// The message's sequence number.
        sequence: u64,
        /// The header field at fault.
        field: &'static str,
        /// What is wrong with it.
        detail: String,
    },
}

fn check_version(message: &'static str, got: u32) -> Result<(), MessageError> {
    if got == PROTOCOL_VERSION {
        Ok(())
    } else {
        Err(MessageError::Version { message, got, expected: PROTOCOL_VERSION })
    }
}

/// A frame's time: finite and not negative.
fn check_time(message: &'static str, sequence: u64, timestamp_s: f64) -> Result<(), MessageError> {
    if timestamp_s.is_finite() && timestamp_s >= 0.0 {
        Ok(())
    } else {
        Err(field_error(message, sequence, "timestamp_s", format!("{timestamp_s} is not a time")))
    }
}

fn field_error(message: &'static str, sequence: u64, field: &'static str, detail: String) -> MessageError {
    MessageError::Field { message, sequence, field, detail }
}

/// Header of the rig calibration message; the payload is the rig file's TOML text
/// ([`crate::Rig::to_toml_string`]). Published with history 1, so a stage that starts late
/// still gets it.
#[derive(Clone, Copy, Debug, Default, PartialEq, ZeroCopySend)]
#[repr(C)]
#[type_name("HandflowRigHeader")]
pub struct RigHeader {
    /// [`PROTOCOL_VERSION`].
    pub protocol_version: u32,
    /// Incremented whenever the calibration changes; frame sets name the version they need.
    pub rig_version: u32,
    /// Nominal frame rate of the stream, frames per second.
    pub frame_rate_hz: f64,
    /// Length of the TOML text in bytes.
    pub text_len: u64,
}

impl RigHeader {
    /// Checks the version, the frame rate and the text length against a payload of
    /// `payload_len` bytes.
    pub fn validate(&self, payload_len: usize) -> Result<(), MessageError> {
        const KIND: &str = "rig message";
        check_version(KIND, self.protocol_version)?;
        if !(self.frame_rate_hz.is_finite() && self.frame_rate_hz > 0.0) {
            return Err(field_error(
                KIND,
                u64::from(self.rig_version),
                "frame_rate_hz",
                format!("is {}", self.frame_rate_hz),
            ));
        }
        if self.text_len != payload_len as u64 {
            return Err(field_error(
                KIND,
                u64::from(self.rig_version),
                "text_len",
                format!("says {} bytes, the payload has {payload_len}", self.text_len),
            ));
        }
        Ok(())
    }
}

/// Header of a synchronised frame set; the payload holds every view's RGB8 pixels, in rig
/// order, one after another, each view at its own size (a camera mounted sideways records
/// portrait frames among the others' landscape ones).
#[derive(Clone, Copy, Debug, Default, PartialEq, ZeroCopySend)]
#[repr(C)]
#[type_name("HandflowFrameHeader")]
pub struct FrameHeader {
    /// [`PROTOCOL_VERSION`].
    pub protocol_version: u32,
    /// [`PIXEL_FORMAT_RGB8`].
    pub pixel_format: u32,
    /// Position in the ingest stream, from 0, without gaps: gaps downstream are losses.
    pub sequence: u64,
    /// Frame number of the source (the recording's `frame` column).
    pub frame: u64,
    /// Stream time of the capture, seconds (the recording's `timestamp` column).
    pub timestamp_s: f64,
    /// Wall-clock time the frame set was captured (decoded or rendered), nanoseconds since
    /// the Unix epoch.
    pub capture_unix_ns: u64,
    /// The rig calibration version the views belong to.
    pub rig_version: u32,
    /// Views in the payload.
    pub view_count: u32,
    /// Width and height of each view in pixels, in rig order; the slots from `view_count` on
    /// are zero.
    pub view_sizes: [[u32; 2]; MAX_FRAME_VIEWS],
    /// [`END_OF_STREAM`] or 0.
    pub flags: u32,
    /// Bit `k` set: camera `k` delivered no view for this set (a live camera that stopped or
    /// fell behind); its bytes in the payload are zero and carry nothing. 0 for a full set.
    pub missing_views: u32,
    /// Payload length, bytes.
    pub payload_len: u64,
}

impl FrameHeader {
    /// Whether camera `k`'s view is in the set.
    pub fn has_view(&self, k: usize) -> bool {
        k >= 32 || self.missing_views & (1 << k) == 0
    }

    /// [`FrameHeader::view_sizes`] of views of these sizes (width, height), in order; `None`
    /// beyond [`MAX_FRAME_VIEWS`] views.
    pub fn sizes_of(sizes: impl IntoIterator<Item = (u32, u32)>) -> Option<[[u32; 2]; MAX_FRAME_VIEWS]> {
        let mut out = [[0; 2]; MAX_FRAME_VIEWS];
        for (k, (w, h)) in sizes.into_iter().enumerate() {
            *out.get_mut(k)? = [w, h];
        }
        Some(out)
    }

    /// Views' sizes for a message: `640x480` when all are that size, else each in turn
    /// (`640x480 / 480x640 / 640x480`).
    pub fn describe_sizes(sizes: impl IntoIterator<Item = (u32, u32)>) -> String {
        let sizes: Vec<String> = sizes.into_iter().map(|(w, h)| format!("{w}x{h}")).collect();
        match sizes.first() {
            Some(first) if sizes.iter().all(|s| s == first) => first.clone(),
            _ => sizes.join(" / "),
        }
    }

    /// Width and height of view `k` (zero beyond the set's views).
    pub fn view_size(&self, k: usize) -> (u32, u32) {
        self.view_sizes.get(k).map_or((0, 0), |&[w, h]| (w, h))
    }

    /// The views' sizes, in order.
    pub fn sizes(&self) -> impl Iterator<Item = (u32, u32)> + '_ {
        (0..(self.view_count as usize).min(MAX_FRAME_VIEWS)).map(|k| self.view_size(k))
    }

    /// Bytes of view `k`.
    pub fn view_len(&self, k: usize) -> usize {
        let (w, h) = self.view_size(k);
        (w as usize).saturating_mul(h as usize).saturating_mul(3)
    }

    /// Whether this message ends the stream.
    pub fn is_end_of_stream(&self) -> bool {
        self.flags & END_OF_STREAM != 0
    }

    /// Checks the version, the pixel format, that the payload length is the header's and that
    /// the views' sizes (`view_sizes`, 3 bytes a pixel) fill it (no payload at the end of a
    /// stream).
    pub fn validate(&self, payload_len: usize) -> Result<(), MessageError> {
        const KIND: &str = "frame set";
        check_version(KIND, self.protocol_version)?;
        let err = |field, detail| Err(field_error(KIND, self.sequence, field, detail));
        if self.payload_len != payload_len as u64 {
            return err("payload_len", format!("says {} bytes, the payload has {payload_len}", self.payload_len));
        }
        if self.is_end_of_stream() {
            return if payload_len == 0 { Ok(()) } else { err("flags", "end of stream with a payload".into()) };
        }
        if self.pixel_format != PIXEL_FORMAT_RGB8 {
            return err("pixel_format", format!("is {}, only RGB8 ({PIXEL_FORMAT_RGB8}) is known", self.pixel_format));
        }
        if self.view_count == 0 || self.view_count as usize > MAX_FRAME_VIEWS {
            return err("view_count", format!("is {}, must be 1 to {MAX_FRAME_VIEWS}", self.view_count));
        }
        let used = self.view_count as usize;
        if let Some(k) = (0..used).find(|&k| self.view_sizes[k].contains(&0)) {
            let [w, h] = self.view_sizes[k];
            return err("view_sizes", format!("gives view {k} a size of {w}x{h}"));
        }
        if self.view_sizes[used..].iter().any(|s| *s != [0, 0]) {
            return err("view_sizes", format!("has sizes beyond the {used} views"));
        }
        let expected =
            self.sizes().try_fold(0u64, |sum, (w, h)| (u64::from(w) * u64::from(h)).checked_mul(3)?.checked_add(sum));
        if expected != Some(payload_len as u64) {
            return err(
                "view_sizes",
                format!(
                    "views of {} RGB8 do not fill a payload of {payload_len} bytes",
                    Self::describe_sizes(self.sizes())
                ),
            );
        }
        if !self.timestamp_s.is_finite() {
            return err("timestamp_s", format!("is {}", self.timestamp_s));
        }
        let all = if self.view_count >= 32 { u32::MAX } else { (1u32 << self.view_count) - 1 };
        if self.missing_views & !all != 0 || self.missing_views == all {
            return err(
                "missing_views",
                format!(
                    "{:#b} for {} views: names a view beyond them or leaves none",
                    self.missing_views, self.view_count
                ),
            );
        }
        Ok(())
    }

    /// The views of a validated payload.
    pub fn views<'a>(&self, payload: &'a [u8]) -> Vec<&'a [u8]> {
        let mut rest = payload;
        let mut views = Vec::with_capacity(self.view_count as usize);
        for k in 0..(self.view_count as usize).min(MAX_FRAME_VIEWS) {
            let Some((view, tail)) = rest.split_at_checked(self.view_len(k)) else { break };
            views.push(view);
            rest = tail;
        }
        views
    }
}

/// One weighted particle of the scene flow: a 3D point on a ray of the reference camera and
/// its motion.
#[derive(Clone, Copy, Debug, Default, PartialEq, ZeroCopySend)]
#[repr(C)]
#[type_name("HandflowScenePoint")]
pub struct ScenePoint {
    /// World position, metres.
    pub position: [f32; 3],
    /// World velocity, metres per frame.
    pub velocity: [f32; 3],
    /// The particle's weight times its ray's confidence.
    pub weight: f32,
    /// Skin probability of the ray's reference pixel under the adapted model, in [0, 1].
    pub skin: f32,
}

/// Header of one frame's particle set; the payload is its [`ScenePoint`]s.
#[derive(Clone, Copy, Debug, Default, PartialEq, ZeroCopySend)]
#[repr(C)]
#[type_name("HandflowParticleHeader")]
pub struct ParticleHeader {
    /// [`PROTOCOL_VERSION`].
    pub protocol_version: u32,
    /// [`END_OF_STREAM`] or 0.
    pub flags: u32,
    /// Ingest sequence of the frame the estimate is for.
    pub sequence: u64,
    /// Source frame number.
    pub frame: u64,
    /// Stream time, seconds.
    pub timestamp_s: f64,
    /// Capture wall-clock time, nanoseconds since the Unix epoch.
    pub capture_unix_ns: u64,
    /// Frame rate the velocities are per frame of, frames per second.
    pub frame_rate_hz: f64,
    /// Mean variance of a ray's particles along the ray, square metres: the filter's own
    /// depth uncertainty, which clustering takes out of the objects' depth spread.
    pub ray_spread_var: f64,
    /// Points in the payload.
    pub point_count: u64,
    /// Seconds the scene-flow estimate took.
    pub flow_seconds: f64,
    /// The rig calibration version.
    pub rig_version: u32,
    /// Reference camera (index in the rig) whose rays the particles lie on.
    pub reference_camera: u32,
    /// 1 when the face fields hold a face the detection rounds placed in 3D, else 0.
    pub face_known: u32,
    /// Views the frame set went without ([`FrameHeader::missing_views`]): a live camera
    /// that stopped or fell behind.
    pub missing_views: u32,
    /// Centre of that face, world metres.
    pub face_centre_m: [f64; 3],
    /// Physical width of the face detector's box, metres.
    pub face_width_m: f64,
    /// Frame sets between the one the face was detected on and this estimate's.
    pub face_age_frames: u64,
}

impl ParticleHeader {
    /// Whether this message ends the stream.
    pub fn is_end_of_stream(&self) -> bool {
        self.flags & END_OF_STREAM != 0
    }

    /// Checks the version, the frame rate, and the point count against a payload of
    /// `points` points.
    pub fn validate(&self, points: usize) -> Result<(), MessageError> {
        const KIND: &str = "particle set";
        check_version(KIND, self.protocol_version)?;
        let err = |field, detail| Err(field_error(KIND, self.sequence, field, detail));
        if self.point_count != points as u64 {
            return err("point_count", format!("says {} points, the payload has {points}", self.point_count));
        }
        if self.is_end_of_stream() {
            return Ok(());
        }
        if !(self.frame_rate_hz.is_finite() && self.frame_rate_hz > 0.0) {
            return err("frame_rate_hz", format!("is {}", self.frame_rate_hz));
        }
        if !(self.ray_spread_var.is_finite() && self.ray_spread_var >= 0.0) {
            return err("ray_spread_var", format!("is {}", self.ray_spread_var));
        }
        if !self.timestamp_s.is_finite() {
            return err("timestamp_s", format!("is {}", self.timestamp_s));
        }
        if self.face_known > 1 {
            return err("face_known", format!("is {}, expected 0 or 1", self.face_known));
        }
        if self.face_known == 1 && !self.face_centre_m.iter().all(|v| v.is_finite()) {
            return err("face_centre_m", format!("is {:?}", self.face_centre_m));
        }
        if self.face_known == 1 && !(self.face_width_m.is_finite() && self.face_width_m > 0.0) {
            return err("face_width_m", format!("is {}", self.face_width_m));
        }
        Ok(())
    }
}

/// Most cameras a [`CameraStatusSet`] describes.
pub const MAX_STATUS_CAMERAS: usize = 16;

/// Camera states on the wire.
pub mod camera_state {
    /// Delivering frames.
    pub const RUNNING: u32 = 0;
    /// Its source ended (a video played as a camera).
    pub const ENDED: u32 = 1;
    /// It failed for good (a video played as a camera that broke); the stream goes on
    /// without it.
    pub const FAILED: u32 = 2;
    /// Lost (unplugged, off the network, silent) and being opened again; the stream goes
    /// on without it meanwhile.
    pub const RECONNECTING: u32 = 3;
}

/// One live camera's health since the stream started.
#[derive(Clone, Copy, Debug, Default, PartialEq, ZeroCopySend)]
#[repr(C)]
#[type_name("HandflowCameraStatus")]
pub struct CameraStatus {
    /// The camera's name in the calibration, UTF-8, padded with zeros (cut at 32 bytes).
    pub name: [u8; 32],
    /// Frames per second delivered since the previous status.
    pub rate_hz: f64,
    /// Frames delivered.
    pub delivered: u64,
    /// Frames that went into frame sets.
    pub used: u64,
    /// Frames dropped: no frame set could take them, or they waited too long.
    pub dropped: u64,
    /// Frame sets that went on without this camera, or were dropped for the lack of it.
    pub missed_sets: u64,
    /// Capture time of its newest frame, nanoseconds since the Unix epoch (0: none yet).
    pub last_capture_unix_ns: u64,
    /// A [`camera_state`] constant.
    pub state: u32,
    /// Reserved, 0.
    pub reserved: u32,
}

impl CameraStatus {
    /// The name as text (up to the first zero byte; invalid UTF-8 replaced).
    pub fn name(&self) -> String {
        let end = self.name.iter().position(|&b| b == 0).unwrap_or(self.name.len());
        String::from_utf8_lossy(&self.name[..end]).into_owned()
    }

    /// Sets the name, cut at 32 bytes on a character boundary.
    pub fn set_name(&mut self, name: &str) {
        let mut end = name.len().min(self.name.len());
        while !name.is_char_boundary(end) {
            end -= 1;
        }
        self.name = [0; 32];
        self.name[..end].copy_from_slice(&name.as_bytes()[..end]);
    }
}

/// The health of every live camera, published by ingest about once a second (history 1:
/// a late subscriber gets the last one).
#[derive(Clone, Copy, Debug, Default, PartialEq, ZeroCopySend)]
#[repr(C)]
#[type_name("HandflowCameraStatusSet")]
pub struct CameraStatusSet {
    /// [`PROTOCOL_VERSION`].
    pub protocol_version: u32,
    /// Cameras described, at most [`MAX_STATUS_CAMERAS`] (rig order).
    pub camera_count: u32,
    /// When the status was taken, nanoseconds since the Unix epoch.
    pub published_unix_ns: u64,
    /// Frame sets published so far.
    pub frame_sets: u64,
    /// The first `camera_count` cameras.
    pub cameras: [CameraStatus; MAX_STATUS_CAMERAS],
}

impl CameraStatusSet {
    /// Checks the version, the count, and every camera's numbers and state.
    pub fn validate(&self) -> Result<(), MessageError> {
        const KIND: &str = "camera status";
        check_version(KIND, self.protocol_version)?;
        if self.camera_count as usize > MAX_STATUS_CAMERAS {
            return Err(field_error(
                KIND,
                self.frame_sets,
                "camera_count",
                format!("is {}, at most {MAX_STATUS_CAMERAS}", self.camera_count),
            ));
        }
        for c in &self.cameras[..self.camera_count as usize] {
            if !(c.rate_hz.is_finite() && c.rate_hz >= 0.0) {
                return Err(field_error(KIND, self.frame_sets, "cameras", format!("{}: rate {}", c.name(), c.rate_hz)));
            }
            if c.state > camera_state::RECONNECTING {
                return Err(field_error(KIND, self.frame_sets, "cameras", format!("{}: state {}", c.name(), c.state)));
            }
        }
        Ok(())
    }
}

/// Track states on the wire.
pub mod track_state {
    /// Measured this frame.
    pub const TRACKED: u32 = 0;
    /// Extrapolated by the motion model.
    pub const PREDICTED: u32 = 1;
    /// No usable estimate.
    pub const LOST: u32 = 2;
}

/// One labelled cluster: a tracked object's state after this frame's measurement.
#[derive(Clone, Copy, Debug, Default, PartialEq, ZeroCopySend)]
#[repr(C)]
#[type_name("HandflowLabelledCluster")]
pub struct LabelledCluster {
    /// World position of the object's middle, metres.
    pub position: [f64; 3],
    /// World velocity, metres per second.
    pub velocity: [f64; 3],
    /// Confidence in [0, 1].
    pub confidence: f64,
    /// Share of the frame's particle weight in the cluster assigned to the object (0 when
    /// none was).
    pub mass: f64,
    /// A [`track_state`] constant.
    pub state: u32,
    /// Reserved, 0.
    pub reserved: u32,
}

/// The labelled clusters of one frame, in [`OBJECT_LABELS`] order.
#[derive(Clone, Copy, Debug, Default, PartialEq, ZeroCopySend)]
#[repr(C)]
#[type_name("HandflowClusterSet")]
pub struct ClusterSet {
    /// [`PROTOCOL_VERSION`].
    pub protocol_version: u32,
    /// [`END_OF_STREAM`] or 0.
    pub flags: u32,
    /// Ingest sequence of the frame.
    pub sequence: u64,
    /// Source frame number.
    pub frame: u64,
    /// Stream time, seconds.
    pub timestamp_s: f64,
    /// Capture wall-clock time, nanoseconds since the Unix epoch.
    pub capture_unix_ns: u64,
    /// Seconds clustering and labelling took.
    pub cluster_seconds: f64,
    /// Views the frame set went without ([`FrameHeader::missing_views`]).
    pub missing_views: u32,
    /// Reserved, 0.
    pub reserved: u32,
    /// Head, left hand, right hand.
    pub objects: [LabelledCluster; 3],
}

fn validate_objects(
    kind: &'static str,
    sequence: u64,
    objects: impl Iterator<Item = ([f64; 3], [f64; 3], f64, u32)>,
) -> Result<(), MessageError> {
    for (label, (position, velocity, confidence, state)) in OBJECT_LABELS.iter().zip(objects) {
        if !position.iter().chain(&velocity).all(|v| v.is_finite()) {
            return Err(field_error(kind, sequence, "objects", format!("{label}: a non-finite position or velocity")));
        }
        if !(0.0..=1.0).contains(&confidence) {
            return Err(field_error(kind, sequence, "objects", format!("{label}: confidence {confidence}")));
        }
        if state > track_state::LOST {
            return Err(field_error(kind, sequence, "objects", format!("{label}: unknown state {state}")));
        }
    }
    Ok(())
}

impl ClusterSet {
    /// Whether this message ends the stream.
    pub fn is_end_of_stream(&self) -> bool {
        self.flags & END_OF_STREAM != 0
    }

    /// Checks the version and every object's numbers and state.
    pub fn validate(&self) -> Result<(), MessageError> {
        const KIND: &str = "cluster set";
        check_version(KIND, self.protocol_version)?;
        if self.is_end_of_stream() {
            return Ok(());
        }
        check_time(KIND, self.sequence, self.timestamp_s)?;
        validate_objects(
            KIND,
            self.sequence,
            self.objects.iter().map(|o| (o.position, o.velocity, o.confidence, o.state)),
        )
    }
}

/// One object's trajectory sample.
#[derive(Clone, Copy, Debug, Default, PartialEq, ZeroCopySend)]
#[repr(C)]
#[type_name("HandflowTrajectoryObject")]
pub struct TrajectoryObject {
    /// World position, metres.
    pub position: [f64; 3],
    /// World velocity, metres per second.
    pub velocity: [f64; 3],
    /// Confidence in [0, 1].
    pub confidence: f64,
    /// A [`track_state`] constant.
    pub state: u32,
    /// Reserved, 0.
    pub reserved: u32,
}

/// How far a stage has got in the stream, kept by the launcher so that a stage it restarts
/// goes on from there: ingest's next frame set to publish; the publisher's next sequence
/// expected and the frames it has counted lost.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, ZeroCopySend)]
#[repr(C)]
#[type_name("HandflowStreamProgress")]
pub struct StreamProgress {
    /// The next sequence.
    pub next: u64,
    /// Frames lost so far (the publisher's count; 0 from ingest).
    pub lost: u64,
}

/// What subscribers (recognisers, viewers) receive: every object's estimate at one frame.
#[derive(Clone, Copy, Debug, Default, PartialEq, ZeroCopySend)]
#[repr(C)]
#[type_name("HandflowTrajectorySample")]
pub struct TrajectorySample {
    /// [`PROTOCOL_VERSION`].
    pub protocol_version: u32,
    /// [`END_OF_STREAM`] or 0.
    pub flags: u32,
    /// Ingest sequence of the frame.
    pub sequence: u64,
    /// Source frame number.
    pub frame: u64,
    /// Stream time, seconds.
    pub timestamp_s: f64,
    /// Capture wall-clock time, nanoseconds since the Unix epoch.
    pub capture_unix_ns: u64,
    /// Wall-clock time this sample was published, nanoseconds since the Unix epoch.
    pub published_unix_ns: u64,
    /// Frame sets lost anywhere upstream since the stream started (live mode drops, frames
    /// lost while a stage restarted).
    pub dropped_frames: u64,
    /// Cameras (bit k: camera k of the rig) whose view this frame set went without: a live
    /// camera that stopped or fell behind; 0 when every camera contributed.
    pub missing_views: u32,
    /// Reserved, 0.
    pub reserved: u32,
    /// Head, left hand, right hand ([`OBJECT_LABELS`]).
    pub objects: [TrajectoryObject; 3],
}

impl TrajectorySample {
    /// Whether this message ends the stream.
    pub fn is_end_of_stream(&self) -> bool {
        self.flags & END_OF_STREAM != 0
    }

    /// Checks the version and every object's numbers and state.
    pub fn validate(&self) -> Result<(), MessageError> {
        const KIND: &str = "trajectory sample";
        check_version(KIND, self.protocol_version)?;
        if self.is_end_of_stream() {
            return Ok(());
        }
        check_time(KIND, self.sequence, self.timestamp_s)?;
        validate_objects(
            KIND,
            self.sequence,
            self.objects.iter().map(|o| (o.position, o.velocity, o.confidence, o.state)),
        )
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn clusters_and_trajectory_samples_of_no_time_are_refused() {
        let set = super::ClusterSet {
            protocol_version: super::PROTOCOL_VERSION,
            timestamp_s: f64::NAN,
            ..Default::default()
        };
        assert!(matches!(set.validate(), Err(super::MessageError::Field { field: "timestamp_s", .. })));
        let sample = super::TrajectorySample {
            protocol_version: super::PROTOCOL_VERSION,
            timestamp_s: f64::INFINITY,
            ..Default::default()
        };
        assert!(matches!(sample.validate(), Err(super::MessageError::Field { field: "timestamp_s", .. })));
    }

    use super::*;

    fn frame_header(views: u32, w: u32, h: u32) -> FrameHeader {
        FrameHeader {
            protocol_version: PROTOCOL_VERSION,
            pixel_format: PIXEL_FORMAT_RGB8,
            sequence: 7,
            view_count: views,
            view_sizes: FrameHeader::sizes_of((0..views).map(|_| (w, h))).unwrap(),
            payload_len: u64::from(views * w * h * 3),
            ..FrameHeader::default()
        }
    }

    #[test]
    fn a_frame_header_that_matches_its_payload_passes_and_splits_into_views() {
        let h = frame_header(3, 4, 2);
        let payload: Vec<u8> = (0..72).collect();
        h.validate(payload.len()).unwrap();
        let views = h.views(&payload);
        assert_eq!(views.len(), 3);
        assert_eq!(views[1][0], 24);
    }

    #[test]
    fn a_frame_header_disagreeing_with_its_payload_names_the_field() {
        let h = frame_header(3, 4, 2);
        let e = h.validate(71).unwrap_err();
        assert!(matches!(e, MessageError::Field { field: "payload_len", sequence: 7, .. }), "{e}");
        let mut lying = h;
        lying.view_count = 2;
        let e = lying.validate(72).unwrap_err();
        assert!(matches!(e, MessageError::Field { field: "view_sizes", .. }), "{e}");
        let mut huge = h;
        huge.view_sizes[0] = [u32::MAX, u32::MAX];
        assert!(huge.validate(72).is_err());
        let mut empty_view = h;
        empty_view.view_sizes[2] = [4, 0];
        let e = empty_view.validate(72).unwrap_err();
        assert!(
            matches!(e, MessageError::Field { field: "view_sizes", .. }) && e.to_string().contains("view 2"),
            "{e}"
        );
        let mut too_many = h;
        too_many.view_count = MAX_FRAME_VIEWS as u32 + 1;
        assert!(matches!(too_many.validate(72).unwrap_err(), MessageError::Field { field: "view_count", .. }));
        assert_eq!(FrameHeader::sizes_of((0..MAX_FRAME_VIEWS as u32 + 1).map(|_| (1, 1))), None);
    }

    #[test]
    fn views_of_different_sizes_split_at_their_own_lengths() {
        // A landscape view, one mounted sideways (portrait), a landscape one.
        let sizes = [(4, 2), (2, 4), (4, 2)];
        let h = FrameHeader {
            view_count: 3,
            view_sizes: FrameHeader::sizes_of(sizes).unwrap(),
            payload_len: 72,
            ..frame_header(3, 4, 2)
        };
        let payload: Vec<u8> = (0..72).collect();
        h.validate(payload.len()).unwrap();
        let views = h.views(&payload);
        assert_eq!(views.iter().map(|v| (v.len(), v[0])).collect::<Vec<_>>(), [(24, 0), (24, 24), (24, 48)]);
        assert_eq!((h.view_size(1), h.view_len(1)), ((2, 4), 24));
        assert_eq!(FrameHeader::describe_sizes(h.sizes()), "4x2 / 2x4 / 4x2");
        assert_eq!(FrameHeader::describe_sizes([(4, 2); 3]), "4x2");
        let longer = FrameHeader { view_sizes: FrameHeader::sizes_of([(4, 2), (2, 5), (4, 2)]).unwrap(), ..h };
        assert!(matches!(longer.validate(72).unwrap_err(), MessageError::Field { field: "view_sizes", .. }));
    }

    #[test]
    fn missing_views_must_name_views_of_the_set_and_leave_one() {
        let mut h = frame_header(3, 4, 2);
        h.missing_views = 0b010;
        h.validate(72).unwrap();
        assert!(h.has_view(0) && !h.has_view(1) && h.has_view(2));
        h.missing_views = 0b1000;
        assert!(matches!(h.validate(72).unwrap_err(), MessageError::Field { field: "missing_views", .. }));
        h.missing_views = 0b111;
        assert!(matches!(h.validate(72).unwrap_err(), MessageError::Field { field: "missing_views", .. }));
    }

    #[test]
    fn another_protocol_version_is_refused_with_both_versions_in_the_message() {
        let mut h = frame_header(1, 1, 1);
        h.protocol_version = PROTOCOL_VERSION + 1;
        let e = h.validate(3).unwrap_err();
        assert_eq!(
            e,
            MessageError::Version { message: "frame set", got: PROTOCOL_VERSION + 1, expected: PROTOCOL_VERSION }
        );
        assert!(e.to_string().contains(&format!("version {}", PROTOCOL_VERSION + 1)));
    }

    #[test]
    fn end_of_stream_carries_no_payload() {
        let h = FrameHeader { protocol_version: PROTOCOL_VERSION, flags: END_OF_STREAM, ..FrameHeader::default() };
        h.validate(0).unwrap();
        let p = ParticleHeader { protocol_version: PROTOCOL_VERSION, flags: END_OF_STREAM, ..Default::default() };
        p.validate(0).unwrap();
        assert!(p.validate(1).is_err());
    }

    #[test]
    fn particle_headers_check_count_and_numbers() {
        let p = ParticleHeader {
            protocol_version: PROTOCOL_VERSION,
            frame_rate_hz: 30.0,
            point_count: 5,
            ..Default::default()
        };
        p.validate(5).unwrap();
        assert!(p.validate(4).is_err());
        let nan = ParticleHeader { ray_spread_var: f64::NAN, ..p };
        assert!(matches!(nan.validate(5), Err(MessageError::Field { field: "ray_spread_var", .. })));
        let face = ParticleHeader { face_known: 1, face_centre_m: [0.1, 1.6, 0.0], face_width_m: 0.15, ..p };
        face.validate(5).unwrap();
        let bad = ParticleHeader { face_centre_m: [f64::NAN, 0.0, 0.0], ..face };
        assert!(matches!(bad.validate(5), Err(MessageError::Field { field: "face_centre_m", .. })));
        let bad = ParticleHeader { face_width_m: 0.0, ..face };
        assert!(matches!(bad.validate(5), Err(MessageError::Field { field: "face_width_m", .. })));
        let bad = ParticleHeader { face_known: 7, ..face };
        assert!(matches!(bad.validate(5), Err(MessageError::Field { field: "face_known", .. })));
    }

    #[test]
    fn trajectory_samples_reject_non_finite_objects_and_unknown_states() {
        let mut s = TrajectorySample { protocol_version: PROTOCOL_VERSION, ..Default::default() };
        s.validate().unwrap();
        s.objects[2].position[1] = f64::INFINITY;
        assert!(s.validate().unwrap_err().to_string().contains("right_hand"));
        s.objects[2].position[1] = 0.0;
        s.objects[0].state = 9;
        assert!(s.validate().is_err());
    }

    #[test]
    fn camera_names_are_cut_on_a_character_boundary_and_statuses_are_checked() {
        let mut c = CameraStatus::default();
        c.set_name("cam_0");
        assert_eq!(c.name(), "cam_0");
        c.set_name(&"é".repeat(20));
        assert_eq!(c.name(), "é".repeat(16));
        let mut set = CameraStatusSet { protocol_version: PROTOCOL_VERSION, camera_count: 1, ..Default::default() };
        set.cameras[0] = c;
        set.validate().unwrap();
        set.cameras[0].rate_hz = f64::NAN;
        assert!(set.validate().unwrap_err().to_string().contains("rate"));
        set.cameras[0].rate_hz = 30.0;
        set.camera_count = 17;
        assert!(matches!(set.validate(), Err(MessageError::Field { field: "camera_count", .. })));
    }

    #[test]
    fn fixed_size_messages_have_stable_sizes() {
        // Subscribers in other languages mirror these layouts.
        assert_eq!(std::mem::size_of::<ScenePoint>(), 32);
        assert_eq!(std::mem::size_of::<TrajectoryObject>(), 64);
        assert_eq!(std::mem::size_of::<TrajectorySample>(), 64 + 3 * 64);
        assert_eq!(std::mem::size_of::<ClusterSet>(), 56 + 3 * 72);
        assert_eq!(std::mem::size_of::<LabelledCluster>(), 72);
    }
}
