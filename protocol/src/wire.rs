//! The messages as bytes for networks: each fixed-size message in the byte layout of its
//! `#[repr(C)]` type on a little-endian machine (the layout subscribers in other languages
//! already mirror for shared memory), written field by field so that it is the same on any
//! machine. A particle set is its header's bytes followed by its points'.
//!
//! Decoding checks the length before anything else and then the message's own `validate`,
//! so a truncated or corrupt datagram is an error naming the field, never a panic.

use crate::messages::{
    ClusterSet, LabelledCluster, MessageError, ParticleHeader, ScenePoint, TrajectoryObject, TrajectorySample,
};

/// Bytes of a [`TrajectorySample`] on the wire.
pub const TRAJECTORY_SAMPLE_BYTES: usize = 64 + 3 * 64;
/// Bytes of a [`ClusterSet`] on the wire.
pub const CLUSTER_SET_BYTES: usize = 56 + 3 * 72;
/// Bytes of a [`ParticleHeader`] on the wire (its points follow).
pub const PARTICLE_HEADER_BYTES: usize = 128;
/// Bytes of a [`ScenePoint`] on the wire.
pub const SCENE_POINT_BYTES: usize = 32;

/// A message that cannot be decoded from its bytes.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum WireError {
    /// The bytes are not as long as the message.
    #[error("{message}: {got} bytes, expected {expected}")]
    Length {
        /// Message kind.
        message: &'static str,
        /// Bytes received.
        got: usize,
        /// Bytes the layout has.
        expected: usize,
    },
    /// The message decoded but disagrees with itself.
    #[error(transparent)]
    Invalid(#[from] MessageError),
}

struct Writer(Vec<u8>);

impl Writer {
    fn u32(&mut self, v: u32) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn u64(&mut self, v: u64) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn f64(&mut self, v: f64) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn f64s(&mut self, v: &[f64]) {
        v.iter().for_each(|&x| self.f64(x));
    }
    fn f32(&mut self, v: f32) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
}

/// Reads fields in order from bytes whose length the caller has checked.
struct Reader<'a>(&'a [u8]);

impl Reader<'_> {
    fn take<const N: usize>(&mut self) -> [u8; N] {
        let mut out = [0u8; N];
        let (head, rest) = self.0.split_at(N.min(self.0.len()));
        out[..head.len()].copy_from_slice(head);
        self.0 = rest;
        out
    }
    fn u32(&mut self) -> u32 {
        u32::from_le_bytes(self.take())
    }
    fn u64(&mut self) -> u64 {
        u64::from_le_bytes(self.take())
    }
    fn f64(&mut self) -> f64 {
        f64::from_le_bytes(self.take())
    }
    fn f64x3(&mut self) -> [f64; 3] {
        [self.f64(), self.f64(), self.f64()]
    }
    fn f32(&mut self) -> f32 {
        f32::from_le_bytes(self.take())
    }
}

fn check_length(message: &'static str, got: usize, expected: usize) -> Result<(), WireError> {
    if got == expected {
        Ok(())
    } else {
        Err(WireError::Length { message, got, expected })
    }
}

/// A trajectory sample's bytes.
pub fn encode_trajectory_sample(s: &TrajectorySample) -> Vec<u8> {
    let mut w = Writer(Vec::with_capacity(TRAJECTORY_SAMPLE_BYTES));
    w.u32(s.protocol_version);
    w.u32(s.flags);
    w.u64(s.sequence);
    w.u64(s.frame);
    w.f64(s.timestamp_s);
    w.u64(s.capture_unix_ns);
    w.u64(s.published_unix_ns);
    w.u64(s.dropped_frames);
    w.u32(s.missing_views);
    w.u32(s.reserved);
    for o in &s.objects {
        w.f64s(&o.position);
        w.f64s(&o.velocity);
        w.f64(o.confidence);
        w.u32(o.state);
        w.u32(o.reserved);
    }
    w.0
}

/// The trajectory sample in `bytes`, checked.
pub fn decode_trajectory_sample(bytes: &[u8]) -> Result<TrajectorySample, WireError> {
    check_length("trajectory sample", bytes.len(), TRAJECTORY_SAMPLE_BYTES)?;
    let mut r = Reader(bytes);
    let mut s = TrajectorySample {
        protocol_version: r.u32(),
        flags: r.u32(),
        sequence: r.u64(),
        frame: r.u64(),
        timestamp_s: r.f64(),
        capture_unix_ns: r.u64(),
        published_unix_ns: r.u64(),
        dropped_frames: r.u64(),
        missing_views: r.u32(),
        reserved: r.u32(),
        ..TrajectorySample::default()
    };
    for o in &mut s.objects {
        *o = TrajectoryObject {
            position: r.f64x3(),
            velocity: r.f64x3(),
            confidence: r.f64(),
            state: r.u32(),
            reserved: r.u32(),
        };
    }
    s.validate()?;
    Ok(s)
}

/// A cluster set's bytes.
pub fn encode_cluster_set(c: &ClusterSet) -> Vec<u8> {
    let mut w = Writer(Vec::with_capacity(CLUSTER_SET_BYTES));
    w.u32(c.protocol_version);
    w.u32(c.flags);
    w.u64(c.sequence);
    w.u64(c.frame);
    w.f64(c.timestamp_s);
    w.u64(c.capture_unix_ns);
    w.f64(c.cluster_seconds);
    w.u32(c.missing_views);
    w.u32(c.reserved);
    for o in &c.objects {
        w.f64s(&o.position);
        w.f64s(&o.velocity);
        w.f64(o.confidence);
        w.f64(o.mass);
        w.u32(o.state);
        w.u32(o.reserved);
    }
    w.0
}

/// The cluster set in `bytes`, checked.
pub fn decode_cluster_set(bytes: &[u8]) -> Result<ClusterSet, WireError> {
    check_length("cluster set", bytes.len(), CLUSTER_SET_BYTES)?;
    let mut r = Reader(bytes);
    let mut c = ClusterSet {
        protocol_version: r.u32(),
        flags: r.u32(),
        sequence: r.u64(),
        frame: r.u64(),
        timestamp_s: r.f64(),
        capture_unix_ns: r.u64(),
        cluster_seconds: r.f64(),
        missing_views: r.u32(),
        reserved: r.u32(),
        ..ClusterSet::default()
    };
    for o in &mut c.objects {
        *o = LabelledCluster {
            position: r.f64x3(),
            velocity: r.f64x3(),
            confidence: r.f64(),
            mass: r.f64(),
            state: r.u32(),
            reserved: r.u32(),
        };
    }
    c.validate()?;
    Ok(c)
}

/// A particle set's bytes: the header, then every point.
pub fn encode_particle_set(h: &ParticleHeader, points: &[ScenePoint]) -> Vec<u8> {
    let mut w = Writer(Vec::with_capacity(PARTICLE_HEADER_BYTES + points.len() * SCENE_POINT_BYTES));
    w.u32(h.protocol_version);
    w.u32(h.flags);
    w.u64(h.sequence);
    w.u64(h.frame);
    w.f64(h.timestamp_s);
    w.u64(h.capture_unix_ns);
    w.f64(h.frame_rate_hz);
    w.f64(h.ray_spread_var);
    w.u64(h.point_count);
    w.f64(h.flow_seconds);
    w.u32(h.rig_version);
    w.u32(h.reference_camera);
    w.u32(h.face_known);
    w.u32(h.missing_views);
    w.f64s(&h.face_centre_m);
    w.f64(h.face_width_m);
    w.u64(h.face_age_frames);
    for p in points {
        p.position.iter().chain(&p.velocity).for_each(|&v| w.f32(v));
        w.f32(p.weight);
        w.f32(p.skin);
    }
    w.0
}

/// The particle set in `bytes`, checked (the point count must match the bytes that follow
/// the header).
pub fn decode_particle_set(bytes: &[u8]) -> Result<(ParticleHeader, Vec<ScenePoint>), WireError> {
    if bytes.len() < PARTICLE_HEADER_BYTES || !(bytes.len() - PARTICLE_HEADER_BYTES).is_multiple_of(SCENE_POINT_BYTES) {
        let whole = bytes.len().saturating_sub(PARTICLE_HEADER_BYTES) / SCENE_POINT_BYTES;
        return Err(WireError::Length {
            message: "particle set",
            got: bytes.len(),
            expected: PARTICLE_HEADER_BYTES + whole * SCENE_POINT_BYTES,
        });
    }
    let mut r = Reader(bytes);
    let h = ParticleHeader {
        protocol_version: r.u32(),
        flags: r.u32(),
        sequence: r.u64(),
        frame: r.u64(),
        timestamp_s: r.f64(),
        capture_unix_ns: r.u64(),
        frame_rate_hz: r.f64(),
        ray_spread_var: r.f64(),
        point_count: r.u64(),
        flow_seconds: r.f64(),
        rig_version: r.u32(),
        reference_camera: r.u32(),
        face_known: r.u32(),
        missing_views: r.u32(),
        face_centre_m: r.f64x3(),
        face_width_m: r.f64(),
        face_age_frames: r.u64(),
    };
    let count = (bytes.len() - PARTICLE_HEADER_BYTES) / SCENE_POINT_BYTES;
    // The header's count is checked against the bytes before any point is read.
    h.validate(count)?;
    let points = (0..count)
        .map(|_| {
            let mut f = || r.f32();
            ScenePoint { position: [f(), f(), f()], velocity: [f(), f(), f()], weight: f(), skin: f() }
        })
        .collect();
    Ok((h, points))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::messages::{track_state, END_OF_STREAM, PROTOCOL_VERSION};
    use proptest::prelude::*;

    fn finite() -> impl Strategy<Value = f64> {
        -1e6f64..1e6
    }

    fn trajectory_sample() -> impl Strategy<Value = TrajectorySample> {
        let object = (prop::array::uniform3(finite()), prop::array::uniform3(finite()), 0.0f64..=1.0, 0u32..=2)
            .prop_map(|(position, velocity, confidence, state)| TrajectoryObject {
                position,
                velocity,
                confidence,
                state,
                reserved: 0,
            });
        (
            (any::<u64>(), any::<u64>(), 0.0f64..1e6, any::<u64>()),
            (any::<u64>(), any::<u64>(), any::<u32>()),
            prop::array::uniform3(object),
        )
            .prop_map(
                |(
                    (sequence, frame, timestamp_s, capture_unix_ns),
                    (published_unix_ns, dropped_frames, missing_views),
                    objects,
                )| {
                    TrajectorySample {
                        protocol_version: PROTOCOL_VERSION,
                        flags: 0,
                        sequence,
                        frame,
                        timestamp_s,
                        capture_unix_ns,
                        published_unix_ns,
                        dropped_frames,
                        missing_views,
                        reserved: 0,
                        objects,
                    }
                },
            )
    }

    proptest! {
        #[test]
        fn trajectory_samples_round_trip(s in trajectory_sample()) {
            let bytes = encode_trajectory_sample(&s);
            prop_assert_eq!(bytes.len(), TRAJECTORY_SAMPLE_BYTES);
            prop_assert_eq!(decode_trajectory_sample(&bytes).unwrap(), s);
        }

        #[test]
        fn any_bytes_decode_to_a_message_or_an_error(bytes in prop::collection::vec(any::<u8>(), 0..600)) {
            let _ = decode_trajectory_sample(&bytes);
            let _ = decode_cluster_set(&bytes);
            let _ = decode_particle_set(&bytes);
        }

        #[test]
        fn particle_sets_round_trip(n in 0usize..20, seed in any::<u32>()) {
            let points: Vec<ScenePoint> = (0..n)
                .map(|i| {
                    let v = (seed as f32 + i as f32) * 1e-3;
                    ScenePoint { position: [v, -v, 2.0 * v], velocity: [0.1, v, 0.0], weight: 0.5, skin: 0.25 }
                })
                .collect();
            let h = ParticleHeader {
                protocol_version: PROTOCOL_VERSION,
                sequence: u64::from(seed),
                frame_rate_hz: 30.0,
                point_count: n as u64,
                face_known: 1,
                face_centre_m: [0.1, 1.6, 0.0],
                face_width_m: 0.15,
                ..Default::default()
            };
            let bytes = encode_particle_set(&h, &points);
            prop_assert_eq!(bytes.len(), PARTICLE_HEADER_BYTES + n * SCENE_POINT_BYTES);
            prop_assert_eq!(decode_particle_set(&bytes).unwrap(), (h, points));
        }
    }

    #[test]
    fn the_layouts_are_those_of_the_shared_memory_types() {
        assert_eq!(TRAJECTORY_SAMPLE_BYTES, std::mem::size_of::<TrajectorySample>());
        assert_eq!(CLUSTER_SET_BYTES, std::mem::size_of::<ClusterSet>());
        assert_eq!(PARTICLE_HEADER_BYTES, std::mem::size_of::<ParticleHeader>());
        assert_eq!(SCENE_POINT_BYTES, std::mem::size_of::<ScenePoint>());
        let c = ClusterSet { protocol_version: PROTOCOL_VERSION, sequence: 3, ..Default::default() };
        let bytes = encode_cluster_set(&c);
        assert_eq!(bytes.len(), CLUSTER_SET_BYTES);
        assert_eq!(decode_cluster_set(&bytes).unwrap(), c);
        // Little-endian, version first: what a Python reader unpacks with "<II".
        assert_eq!(&bytes[..4], &PROTOCOL_VERSION.to_le_bytes());
    }

    #[test]
    fn truncated_or_corrupt_bytes_are_refused_naming_what_is_wrong() {
        let s = TrajectorySample { protocol_version: PROTOCOL_VERSION, flags: END_OF_STREAM, ..Default::default() };
        let bytes = encode_trajectory_sample(&s);
        let e = decode_trajectory_sample(&bytes[..100]).unwrap_err();
        assert_eq!(e, WireError::Length { message: "trajectory sample", got: 100, expected: TRAJECTORY_SAMPLE_BYTES });
        let mut wrong = TrajectorySample { protocol_version: PROTOCOL_VERSION, ..Default::default() };
        wrong.objects[1].state = track_state::LOST + 5;
        let e = decode_trajectory_sample(&encode_trajectory_sample(&wrong)).unwrap_err();
        assert!(e.to_string().contains("left_hand"), "{e}");
        let h = ParticleHeader {
            protocol_version: PROTOCOL_VERSION,
            frame_rate_hz: 30.0,
            point_count: 2,
            ..Default::default()
        };
        let one_point = encode_particle_set(&h, &[ScenePoint::default()]);
        let e = decode_particle_set(&one_point).unwrap_err();
        assert!(e.to_string().contains("point_count"), "{e}");
        let e = decode_particle_set(&one_point[..PARTICLE_HEADER_BYTES + 5]).unwrap_err();
        assert!(matches!(e, WireError::Length { .. }), "{e}");
    }
}
