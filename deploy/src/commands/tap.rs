//! `handflow tap SERVICE`: prints what flows on one of a running pipeline's services, one
//! line per message (like `ros2 topic echo`), for debugging.

use std::io::Write;
use std::time::Duration;

use anyhow::{bail, Result};
use handflow_protocol::ipc::{self, Next, ServiceNames, SERVICE_SUFFIXES};
use handflow_protocol::messages::{
    camera_state, track_state, FrameHeader, TrajectoryObject, TrajectorySample, OBJECT_LABELS,
};

/// Prints up to `count` messages (all, until interrupted, when `None`) of service `suffix`
/// (`rig`, `frames`, `particles`, `clusters` or `trajectories`) of the pipeline `prefix`.
pub fn tap(suffix: &str, prefix: &str, count: Option<u64>, out: &mut dyn Write) -> Result<()> {
    let names = ServiceNames::new(prefix);
    let name = names.full(suffix);
    let node = ipc::create_node("handflow-tap")?;
    let mut seen = 0u64;
    let idle = Duration::from_millis(500);
    let mut line = |text: String| -> Result<Next> {
        writeln!(out, "{text}")?;
        seen += 1;
        Ok(if count.is_some_and(|n| seen >= n) { Next::Stop } else { Next::Continue })
    };
    match suffix {
        "rig" => {
            let input = open_when_ready(&node, &name, ipc::tap_rig)?;
            ipc::serve(&input, idle, |s| {
                let h = *s.user_header();
                let check = h.validate(s.payload().len()).map_or_else(|e| format!(" INVALID: {e}"), |_| String::new());
                line(format!(
                    "rig version {} at {:.2} frames/s, {} bytes of TOML{check}",
                    h.rig_version, h.frame_rate_hz, h.text_len
                ))
            })
        }
        "cameras" => {
            let input = open_when_ready(&node, &name, ipc::tap_cameras)?;
            ipc::serve(&input, idle, |s| {
                let set = *s.payload();
                let check = set.validate().map_or_else(|e| format!(" INVALID: {e}"), |_| String::new());
                let cameras: Vec<String> = set.cameras[..(set.camera_count as usize).min(set.cameras.len())]
                    .iter()
                    .map(|c| {
                        let age = if c.last_capture_unix_ns == 0 {
                            "no frame yet".to_string()
                        } else {
                            format!("last frame {:.0} ms ago", ms_since(c.last_capture_unix_ns))
                        };
                        let state = match c.state {
                            camera_state::RUNNING => "running",
                            camera_state::ENDED => "ended",
                            camera_state::RECONNECTING => "reconnecting",
                            _ => "FAILED",
                        };
                        format!(
                            "{} {state} {:.1} frames/s, {} delivered, {} dropped, {} sets missed, {age}",
                            c.name(),
                            c.rate_hz,
                            c.delivered,
                            c.dropped,
                            c.missed_sets
                        )
                    })
                    .collect();
                line(format!("cameras after {} frame sets: {}{check}", set.frame_sets, cameras.join(" | ")))
            })
        }
        "frames" => {
            let input = open_when_ready(&node, &name, ipc::tap_frames)?;
            ipc::serve(&input, idle, |s| {
                let h = *s.user_header();
                let check = h.validate(s.payload().len()).map_or_else(|e| format!(" INVALID: {e}"), |_| String::new());
                let age = ms_since(h.capture_unix_ns);
                if h.is_end_of_stream() {
                    return line(format!("frames seq {} END OF STREAM{check}", h.sequence));
                }
                // A live camera that stopped or fell behind: which views the set goes without.
                let missing: Vec<String> =
                    (0..h.view_count as usize).filter(|&k| !h.has_view(k)).map(|k| k.to_string()).collect();
                let missing =
                    if missing.is_empty() { String::new() } else { format!(", views missing: {}", missing.join(", ")) };
                let sizes = FrameHeader::describe_sizes(h.sizes());
                line(format!(
                    "frames seq {} frame {} t {:.3} s: {} x {sizes} RGB8, {} bytes, captured {age:.1} ms ago{missing}{check}",
                    h.sequence, h.frame, h.timestamp_s, h.view_count, h.payload_len
                ))
            })
        }
        "particles" => {
            let input = open_when_ready(&node, &name, ipc::tap_particles)?;
            ipc::serve(&input, idle, |s| {
                let h = *s.user_header();
                let check = h.validate(s.payload().len()).map_or_else(|e| format!(" INVALID: {e}"), |_| String::new());
                if h.is_end_of_stream() {
                    return line(format!("particles seq {} END OF STREAM{check}", h.sequence));
                }
                let weight: f64 = s.payload().iter().map(|p| f64::from(p.weight)).sum();
                line(format!(
                    "particles seq {} frame {} t {:.3} s: {} points, total weight {weight:.1}, flow {:.1} ms, captured {:.1} ms ago{check}",
                    h.sequence,
                    h.frame,
                    h.timestamp_s,
                    h.point_count,
                    h.flow_seconds * 1e3,
                    ms_since(h.capture_unix_ns)
                ))
            })
        }
        "clusters" => {
            let input = open_when_ready(&node, &name, ipc::tap_clusters)?;
            ipc::serve(&input, idle, |s| {
                let c = *s.payload();
                let check = c.validate().map_or_else(|e| format!(" INVALID: {e}"), |_| String::new());
                if c.is_end_of_stream() {
                    return line(format!("clusters seq {} END OF STREAM{check}", c.sequence));
                }
                let objects: Vec<String> = OBJECT_LABELS
                    .iter()
                    .zip(&c.objects)
                    .map(|(l, o)| format!("{l} {} mass {:.2} {}", fmt_pos(o.position), o.mass, state_name(o.state)))
                    .collect();
                line(format!("clusters seq {} frame {}: {}{check}", c.sequence, c.frame, objects.join(" | ")))
            })
        }
        "trajectories" => {
            let input = open_when_ready(&node, &name, ipc::tap_trajectories)?;
            ipc::serve(&input, idle, |s| {
                let t = *s.payload();
                let check = t.validate().map_or_else(|e| format!(" INVALID: {e}"), |_| String::new());
                line(format!("{}{check}", trajectory_line(&t)))
            })
        }
        other => bail!("unknown service `{other}` (services: {})", SERVICE_SUFFIXES.join(", ")),
    }
}

/// One trajectory sample as a line.
fn trajectory_line(t: &TrajectorySample) -> String {
    if t.is_end_of_stream() {
        return format!("trajectories seq {} END OF STREAM", t.sequence);
    }
    let objects: Vec<String> = OBJECT_LABELS.iter().zip(&t.objects).map(|(l, o)| fmt_object(l, o)).collect();
    // A live camera that stopped or fell behind: the views this estimate went without.
    let missing: Vec<String> = (0..32).filter(|k| t.missing_views & (1 << k) != 0).map(|k| k.to_string()).collect();
    let missing = if missing.is_empty() { String::new() } else { format!(", views missing: {}", missing.join(", ")) };
    format!(
        "trajectories seq {} frame {} t {:.3} s: {} | latency {:.1} ms, {} dropped{missing}",
        t.sequence,
        t.frame,
        t.timestamp_s,
        objects.join(" | "),
        t.published_unix_ns.saturating_sub(t.capture_unix_ns) as f64 * 1e-6,
        t.dropped_frames
    )
}

/// Prints up to `count` trajectory samples (all, until interrupted, when `None`) of a
/// pipeline on another machine, read through the Zenoh bridge at `endpoint`; `rig` picks one
/// rig when several publish there. A sample that does not decode is reported and skipped.
pub fn tap_zenoh(endpoint: &str, rig: Option<&str>, count: Option<u64>, out: &mut dyn Write) -> Result<()> {
    let remote = handflow_bridge::remote::RemoteTrajectories::connect(endpoint, rig)?;
    eprintln!("subscribed to the trajectories behind `{endpoint}`; waiting for samples");
    let mut seen = 0u64;
    while !ipc::stop_requested() && count.is_none_or(|n| seen < n) {
        match remote.next(Duration::from_millis(200)) {
            Ok(Some(t)) => {
                writeln!(out, "{}", trajectory_line(&t))?;
                seen += 1;
            }
            Ok(None) => {}
            Err(e) => eprintln!("skipped: {e:#}"),
        }
    }
    Ok(())
}

/// Opens the service, waiting for the pipeline to create it.
fn open_when_ready<T>(
    node: &ipc::IpcNode,
    name: &str,
    open: impl Fn(&ipc::IpcNode, &str) -> Result<T, ipc::IpcError>,
) -> Result<T> {
    let mut announced = false;
    loop {
        match open(node, name) {
            Ok(input) => return Ok(input),
            Err(e) if !announced => {
                eprintln!("waiting for `{name}` ({})", e.what);
                announced = true;
            }
            Err(_) => {}
        }
        if !ipc::nap(node, Duration::from_millis(100)) {
            bail!("interrupted before `{name}` appeared");
        }
    }
}

fn ms_since(unix_ns: u64) -> f64 {
    ipc::unix_now_ns().saturating_sub(unix_ns) as f64 * 1e-6
}

fn fmt_pos(p: [f64; 3]) -> String {
    format!("({:+.3} {:+.3} {:+.3})", p[0], p[1], p[2])
}

fn state_name(state: u32) -> &'static str {
    match state {
        track_state::TRACKED => "tracked",
        track_state::PREDICTED => "predicted",
        _ => "lost",
    }
}

fn fmt_object(label: &str, o: &TrajectoryObject) -> String {
    format!("{label} {} {} {:.2}", fmt_pos(o.position), state_name(o.state), o.confidence)
}
