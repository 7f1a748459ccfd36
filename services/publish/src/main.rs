//! `handflow-publish`: the trajectory-publisher stage. Labelled clusters in; trajectory
//! samples out on shared memory for any number of subscribers, and as a JSON Lines file.

use std::path::PathBuf;
use std::time::Duration;

use anyhow::{Context, Result};
use clap::Parser;
use handflow_protocol::ipc::{self, Mode, Next, ServiceNames};
use handflow_protocol::messages::StreamProgress;
use handflow_publish::file::TrajectoryFile;
use handflow_publish::latency::LatencyHistogram;
use handflow_publish::viewer::{Viewer, ViewerOptions};
use handflow_publish::{trajectory_sample, SequenceGaps, TrajectoryRecord};

#[derive(Parser, Debug)]
#[command(name = "handflow-publish", about = "Trajectory samples for subscribers and a JSON Lines file")]
struct Args {
    /// Delivery mode: `replay` (nothing dropped) or `live` (latest wins).
    #[arg(long, default_value = "replay")]
    mode: Mode,
    /// JSON Lines file to write the trajectories to (one object per frame).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Exit (status 0) after the end of the stream has been published.
    #[arg(long)]
    exit_at_end: bool,
    /// Before the first sample, wait (at most 10 s) for this many subscribers of the
    /// trajectories: the launcher's Zenoh bridge in a replay, which must not miss the start.
    #[arg(long, default_value_t = 0)]
    subscribers: usize,
    /// Prefix of the service names.
    #[arg(long, default_value = ipc::DEFAULT_PREFIX)]
    services: String,
    /// Serve the live viewer on this address (for example 127.0.0.1:8787; port 0 picks a
    /// free one). Off when not given.
    #[arg(long)]
    viewer: Option<std::net::SocketAddr>,
    /// Thumbnails per second per camera in the viewer (0: none).
    #[arg(long, default_value_t = 2.0)]
    thumbnail_hz: f64,
    /// Go on where a previous publisher of this stream stopped (the launcher restarting
    /// it): the next sequence it expected and the frames it had counted lost, as
    /// `NEXT,LOST`. The file is then appended to, not emptied.
    #[arg(long, value_parser = parse_resume)]
    resume: Option<(u64, u64)>,
}

/// `NEXT,LOST` of `--resume`.
fn parse_resume(text: &str) -> Result<(u64, u64), String> {
    let (next, lost) = text.split_once(',').ok_or("expected NEXT,LOST")?;
    Ok((next.parse().map_err(|e| format!("NEXT: {e}"))?, lost.parse().map_err(|e| format!("LOST: {e}"))?))
}

/// How long the publisher waits for the subscribers it was told to expect.
const SUBSCRIBER_WAIT: Duration = Duration::from_secs(10);

fn main() {
    ipc::init_logging();
    ipc::exit_with(run(Args::parse()))
}

fn run(args: Args) -> Result<()> {
    let names = ServiceNames::new(&args.services);
    let node = ipc::stage_node("handflow-publish")?;
    let clusters = ipc::clusters_input(&node, &names, args.mode)?;
    let trajectories = ipc::trajectories_output(&node, &names, args.mode)?;
    let resume = args.resume;
    let mut sink = match &args.out {
        Some(path) => Some(TrajectoryFile::open(path, resume.is_some()).map_err(anyhow::Error::msg)?),
        None => None,
    };
    let progress = ipc::progress_output(&node, &names, "publish")?;
    // The viewer is a window on the stream: if its address is taken, the stream goes on.
    let viewer = args.viewer.and_then(|address| {
        let options = ViewerOptions {
            address,
            thumbnail_hz: args.thumbnail_hz.max(0.0),
            services: args.services.clone(),
            mode: args.mode,
        };
        match Viewer::start(&options) {
            Ok(viewer) => {
                tracing::info!("viewer on http://{}/", viewer.address());
                Some(viewer)
            }
            Err(e) => {
                tracing::error!("no viewer: {e:#}");
                None
            }
        }
    });
    tracing::info!(
        "ready: trajectories on `{}`{}, {} mode",
        trajectories.name(),
        args.out.as_ref().map(|p| format!(" and in `{}`", p.display())).unwrap_or_default(),
        args.mode
    );
    if args.subscribers > 0
        && !trajectories.wait_for_subscribers(&node, args.subscribers, SUBSCRIBER_WAIT)
        && !ipc::stop_requested()
    {
        tracing::warn!(
            "{} of {} expected subscriber(s) of `{}` after {SUBSCRIBER_WAIT:?}: publishing without them",
            trajectories.subscribers(),
            args.subscribers,
            trajectories.name()
        );
    }
    let mut gaps = match resume {
        Some((next, lost)) => {
            tracing::info!("going on from sequence {next} ({lost} frames lost before; restarted)");
            SequenceGaps::continuing(next, lost)
        }
        None => SequenceGaps::default(),
    };
    let mut published = 0u64;
    let mut latencies = LatencyHistogram::default();
    ipc::serve(&clusters, Duration::from_millis(100), |sample| -> Result<Next> {
        let set = *sample.payload();
        drop(sample);
        if let Err(e) = set.validate() {
            tracing::error!("skipping malformed clusters: {e}");
            return Ok(Next::Continue);
        }
        let end = set.is_end_of_stream();
        // The end of stream carries the sequence after the last frame: frames lost just
        // before it count too.
        {
            let lost = gaps.arrive(set.sequence);
            if !lost.is_empty() {
                tracing::warn!(
                    "frames lost upstream: sequence {}..={} ({} in all so far)",
                    lost.start,
                    lost.end - 1,
                    gaps.lost()
                );
            }
        }
        let now = ipc::unix_now_ns();
        let out = trajectory_sample(&set, gaps.lost(), now);
        trajectories.publisher.send_copy(out).context("sending the trajectory sample")?;
        trajectories.notify()?;
        let record = TrajectoryRecord::from_sample(&out);
        if let Some(viewer) = &viewer {
            viewer.publish(&out, &record);
        }
        if end {
            tracing::info!(
                "end of stream: {published} trajectory samples, {} frames lost upstream, glass-to-trajectory p50 {:.1} ms, p99 {:.1} ms",
                gaps.lost(),
                latencies.percentile(0.5) * 1e3,
                latencies.percentile(0.99) * 1e3,
            );
            if args.exit_at_end {
                return Ok(Next::Stop);
            }
            gaps = SequenceGaps::default();
            published = 0;
            latencies = LatencyHistogram::default();
            return Ok(Next::Continue);
        }
        published += 1;
        if set.capture_unix_ns > 0 {
            latencies.add(now.saturating_sub(set.capture_unix_ns) as f64 * 1e-9);
        }
        if let Some(sink) = sink.as_mut() {
            sink.write(&record);
        }
        // After the record is out: a publisher killed in between makes its successor report
        // this frame lost as well, never leave a frame neither written nor reported.
        progress.report(StreamProgress { next: gaps.next(), lost: gaps.lost() });
        Ok(Next::Continue)
    })?;
    // Keep the last samples readable until subscribers have had them.
    std::thread::sleep(Duration::from_millis(100));
    Ok(())
}
