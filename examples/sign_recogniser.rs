//! A minimal "sign recogniser": how a downstream program plugs into handflow. It subscribes
//! to the trajectory samples of a running pipeline and reports two simple events from them:
//! a hand coming to the face, and the hands crossing. `sign_recogniser.py` beside it does
//! the same in Python.
//!
//! ```sh
//! target/release/sign-recogniser &            # before the pipeline: it sees every sample
//! target/release/handflow run --recording out/hands-cross
//! ```
//!
//! On another machine it reads the same samples through the pipeline's Zenoh bridge
//! (`[network] zenoh = { listen = "tcp/0.0.0.0:7447" }` in the pipeline file):
//!
//! ```sh
//! target/release/sign-recogniser --zenoh tcp/rig-host:7447
//! ```

use std::time::Duration;

use anyhow::Result;
use clap::Parser;
use handflow_protocol::ipc::{self, Mode, Next, ServiceNames};
use handflow_protocol::messages::{track_state, TrajectorySample};

#[derive(Parser, Debug)]
#[command(
    name = "sign-recogniser",
    about = "Reports hands at the face and crossing hands from handflow's trajectories"
)]
struct Args {
    /// Prefix of the pipeline's service names.
    #[arg(long, default_value = ipc::DEFAULT_PREFIX)]
    services: String,
    /// The pipeline's delivery mode (`replay` or `live`): the subscription must match it.
    #[arg(long, default_value = "replay")]
    mode: Mode,
    /// Read a pipeline on another machine through its Zenoh bridge at this endpoint
    /// (`tcp/<host>:<port>`) instead of shared memory on this one.
    #[arg(long)]
    zenoh: Option<String>,
    /// With `--zenoh`: the rig to follow (default: every rig behind the endpoint).
    #[arg(long, requires = "zenoh")]
    rig: Option<String>,
}

/// A hand is at the face closer than this to the head's centre, metres...
const AT_FACE_M: f64 = 0.20;
/// ...and leaves it farther than this (hysteresis: no flicker at the boundary).
const LEFT_FACE_M: f64 = 0.25;

/// Events from a stream of samples.
#[derive(Default)]
struct Recogniser {
    at_face: [bool; 2],
    /// Direction from right hand to left hand when first seen: crossed hands reverse it.
    sides: Option<[f64; 3]>,
    crossed: bool,
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

impl Recogniser {
    fn observe(&mut self, s: &TrajectorySample) -> Vec<String> {
        let mut events = Vec::new();
        let [head, left, right] = s.objects;
        let seen = |o: &handflow_protocol::messages::TrajectoryObject| o.state != track_state::LOST;
        for (k, (hand, name)) in [(left, "left hand"), (right, "right hand")].into_iter().enumerate() {
            if !(seen(&hand) && seen(&head)) {
                continue;
            }
            let d = dot(sub(hand.position, head.position), sub(hand.position, head.position)).sqrt();
            if !self.at_face[k] && d < AT_FACE_M {
                self.at_face[k] = true;
                events.push(format!("{name} at the face"));
            } else if self.at_face[k] && d > LEFT_FACE_M {
                self.at_face[k] = false;
                events.push(format!("{name} leaves the face"));
            }
        }
        if seen(&left) && seen(&right) {
            let between = sub(left.position, right.position);
            let sides = *self.sides.get_or_insert(between);
            let crossed = dot(between, sides) < 0.0;
            if crossed != self.crossed {
                self.crossed = crossed;
                events.push(if crossed { "hands crossed".into() } else { "hands uncrossed".into() });
            }
        }
        events
    }
}

/// What the recogniser has seen, for its summary.
#[derive(Default)]
struct Report {
    recogniser: Recogniser,
    samples: u64,
    events: u64,
    first: Option<u64>,
    last: u64,
    dropped: u64,
}

impl Report {
    /// Handles one sample; `Next::Stop` at the end of the stream.
    fn handle(&mut self, s: &TrajectorySample) -> Next {
        if let Err(e) = s.validate() {
            eprintln!("skipping a malformed sample: {e}");
            return Next::Continue;
        }
        if s.is_end_of_stream() {
            let range = self.first.map_or("none".to_string(), |f| format!("{f}..={}", self.last));
            println!(
                "summary: {} samples, frames {range}, {} dropped upstream, {} events",
                self.samples, self.dropped, self.events
            );
            return Next::Stop;
        }
        self.samples += 1;
        self.first.get_or_insert(s.frame);
        self.last = s.frame;
        self.dropped = s.dropped_frames;
        for event in self.recogniser.observe(s) {
            self.events += 1;
            println!("frame {} t {:.3} s: {event}", s.frame, s.timestamp_s);
        }
        Next::Continue
    }
}

fn main() -> Result<()> {
    let args = Args::parse();
    let mut report = Report::default();
    if let Some(endpoint) = &args.zenoh {
        let remote = handflow_bridge::remote::RemoteTrajectories::connect(endpoint, args.rig.as_deref())?;
        println!("listening on `{endpoint}` (Zenoh)");
        while !ipc::stop_requested() {
            match remote.next(Duration::from_millis(100)) {
                Ok(Some(s)) if report.handle(&s) == Next::Stop => break,
                Ok(_) => {}
                Err(e) => eprintln!("skipping: {e:#}"),
            }
        }
        return Ok(());
    }
    let names = ServiceNames::new(&args.services);
    let node = ipc::create_node("sign-recogniser")?;
    let input = ipc::trajectories_input(&node, &names, args.mode)?;
    println!("listening on `{}`", names.trajectories());
    ipc::serve(&input, Duration::from_millis(100), |sample| -> Result<Next> {
        let s = *sample.payload();
        Ok(report.handle(&s))
    })?;
    Ok(())
}
