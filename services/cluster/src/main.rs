//! `handflow-cluster`: the clustering stage. Particle sets in, labelled clusters (head, left
//! hand, right hand) out.

use std::time::Duration;

use anyhow::{Context, Result};
use clap::Parser;
use handflow_cluster::stage::{labelled_clusters, ClusterStage, FaceCue};
use handflow_protocol::ipc::{self, Mode, Next, ServiceNames};
use handflow_protocol::messages::{ClusterSet, END_OF_STREAM, PROTOCOL_VERSION};

#[derive(Parser, Debug)]
#[command(
    name = "handflow-cluster",
    about = "EM clustering in 6D and labelling: particle sets in, labelled clusters out"
)]
struct Args {
    /// Delivery mode: `replay` (nothing dropped) or `live` (latest wins).
    #[arg(long, default_value = "replay")]
    mode: Mode,
    /// Keep cluster centres on the visible surface instead of the objects' middles.
    #[arg(long)]
    no_centre_correction: bool,
    /// Prefix of the service names.
    #[arg(long, default_value = ipc::DEFAULT_PREFIX)]
    services: String,
}

fn main() {
    ipc::init_logging();
    ipc::exit_with(run(Args::parse()))
}

fn run(args: Args) -> Result<()> {
    let names = ServiceNames::new(&args.services);
    let node = ipc::stage_node("handflow-cluster")?;
    let Some((_, rig)) = ipc::wait_for_rig(&node, &names)? else { return Ok(()) };
    let reference = rig.most_frontal_camera();
    let world_up = rig.world_up();
    let up = world_up.direction;
    let particles = ipc::particles_input(&node, &names, args.mode)?;
    let clusters = ipc::clusters_output(&node, &names, args.mode)?;
    let new_stage = || ClusterStage::new(&rig.cameras[reference], up, !args.no_centre_correction);
    let mut stage = new_stage();
    let mut connected = false;
    tracing::info!(
        "ready: reference `{}`, world up {:?} ({}), {} mode",
        rig.cameras[reference].name,
        up.as_slice(),
        world_up.source,
        args.mode
    );
    ipc::serve(&particles, Duration::from_millis(100), |sample| -> Result<Next> {
        let header = *sample.user_header();
        if let Err(e) = header.validate(sample.payload().len()) {
            tracing::error!("skipping a malformed particle set: {e}");
            return Ok(Next::Continue);
        }
        if header.reference_camera as usize != reference && !header.is_end_of_stream() {
            tracing::error!(
                "skipping particle set {}: on the rays of camera {}, this stage expects camera {reference}",
                header.sequence,
                header.reference_camera
            );
            return Ok(Next::Continue);
        }
        if !connected {
            clusters.connect_downstream(&node, args.mode);
            connected = true;
        }
        let mut set = ClusterSet {
            protocol_version: PROTOCOL_VERSION,
            sequence: header.sequence,
            frame: header.frame,
            timestamp_s: header.timestamp_s,
            capture_unix_ns: header.capture_unix_ns,
            missing_views: header.missing_views,
            ..ClusterSet::default()
        };
        if header.is_end_of_stream() {
            set.flags = END_OF_STREAM;
            // The next stream is unrelated: start tracking afresh.
            stage = new_stage();
        } else {
            let objects = stage.update(
                header.timestamp_s,
                header.frame_rate_hz,
                header.ray_spread_var,
                sample.payload(),
                FaceCue::from_header(&header),
            );
            set.objects = labelled_clusters(&objects);
            set.cluster_seconds = stage.last_seconds();
        }
        drop(sample);
        clusters.publisher.send_copy(set).context("sending clusters")?;
        clusters.notify()?;
        Ok(Next::Continue)
    })?;
    tracing::info!("stopped");
    Ok(())
}
