//! `handflow bench inject` (hidden, for the fault campaign `scripts/faults.py`): malformed
//! samples sent on a running pipeline's service by a second publisher, as a buggy or hostile
//! process on the machine would. The stage reading the service must skip each with a logged
//! error and go on.

use std::time::Duration;

use anyhow::{bail, Context, Result};
use handflow_flow::engine::rng::RayRng;
use handflow_protocol::ipc::{self, Mode, ServiceNames};
use handflow_protocol::messages::{
    ClusterSet, FrameHeader, ParticleHeader, ScenePoint, TrajectorySample, PIXEL_FORMAT_RGB8, PROTOCOL_VERSION,
};

/// A deterministic draw below `n` (the campaign's seed picks the malformations).
fn below(rng: &mut RayRng, n: u64) -> u64 {
    rng.next_u64() % n.max(1)
}

/// Sends `count` malformed samples on `service` (`frames`, `particles`, `clusters` or
/// `trajectories`) of the pipeline under `prefix`, running in `mode`.
pub fn inject(prefix: &str, service: &str, mode: Mode, count: u32, seed: u64) -> Result<()> {
    let names = ServiceNames::new(prefix);
    let node = ipc::create_node("handflow-inject")?;
    let mut draw = RayRng::for_item(seed, 0, 0, 0);
    match service {
        "frames" => {
            let out = ipc::frames_output(&node, &names, mode, 64)?;
            for _ in 0..count {
                let len = 48usize;
                let mut sample = out.publisher.loan_slice(len).context("loaning")?;
                let mut header = FrameHeader {
                    protocol_version: PROTOCOL_VERSION,
                    pixel_format: PIXEL_FORMAT_RGB8,
                    sequence: below(&mut draw, 1 << 20),
                    view_count: 1,
                    view_sizes: FrameHeader::sizes_of([(4, 4)]).unwrap_or_default(),
                    payload_len: len as u64,
                    ..FrameHeader::default()
                };
                match below(&mut draw, 4) {
                    0 => header.protocol_version = 0xdead,
                    1 => header.payload_len = 1 << 40,
                    2 => header.view_count = 1 << 20,
                    _ => header.pixel_format = 77,
                }
                *sample.user_header_mut() = header;
                sample.send().context("sending")?;
                out.notify()?;
            }
        }
        "particles" => {
            let out = ipc::particles_output(&node, &names, mode)?;
            for _ in 0..count {
                let n = 8usize;
                let mut sample = out.publisher.loan_slice(n).context("loaning")?;
                for p in sample.payload_mut().iter_mut() {
                    *p = ScenePoint { position: [f32::NAN, 0.0, 1.0], velocity: [0.0; 3], weight: 1.0, skin: 1.0 };
                }
                let mut header = ParticleHeader {
                    protocol_version: PROTOCOL_VERSION,
                    sequence: below(&mut draw, 1 << 20),
                    frame_rate_hz: 30.0,
                    point_count: n as u64,
                    ..ParticleHeader::default()
                };
                match below(&mut draw, 3) {
                    0 => header.point_count = u64::MAX,
                    1 => header.protocol_version = 0,
                    _ => header.frame_rate_hz = f64::NAN,
                }
                *sample.user_header_mut() = header;
                sample.send().context("sending")?;
                out.notify()?;
            }
        }
        "clusters" => {
            let out = ipc::clusters_output(&node, &names, mode)?;
            for _ in 0..count {
                let mut set = ClusterSet {
                    protocol_version: PROTOCOL_VERSION,
                    sequence: below(&mut draw, 1 << 20),
                    ..ClusterSet::default()
                };
                match below(&mut draw, 2) {
                    0 => set.protocol_version = 7,
                    _ => set.timestamp_s = f64::NAN,
                }
                out.publisher.send_copy(set).context("sending")?;
                out.notify()?;
            }
        }
        "trajectories" => {
            let out = ipc::trajectories_output(&node, &names, mode)?;
            for _ in 0..count {
                let mut sample = TrajectorySample {
                    protocol_version: PROTOCOL_VERSION,
                    sequence: below(&mut draw, 1 << 20),
                    ..TrajectorySample::default()
                };
                match below(&mut draw, 2) {
                    0 => sample.protocol_version = 3,
                    _ => sample.timestamp_s = f64::INFINITY,
                }
                out.publisher.send_copy(sample).context("sending")?;
                out.notify()?;
            }
        }
        other => bail!("unknown service `{other}` (frames, particles, clusters, trajectories)"),
    }
    // Samples live in this process's memory: keep it until the readers have had them.
    std::thread::sleep(Duration::from_millis(500));
    Ok(())
}
