//! The remote end: a subscriber of a bridge's trajectory samples on another machine.

use std::time::Duration;

use anyhow::{anyhow, Result};
use handflow_protocol::messages::TrajectorySample;
use handflow_protocol::wire;
use zenoh::handlers::FifoChannelHandler;
use zenoh::pubsub::Subscriber;
use zenoh::sample::Sample;
use zenoh::{Session, Wait};

use crate::{check_rig_name, key, subscriber_config, Topic, KEY_ROOT};

/// Trajectory samples of the pipelines behind a Zenoh endpoint, in the binary layout.
pub struct RemoteTrajectories {
    // Declared on the session below; dropped before it.
    subscriber: Subscriber<FifoChannelHandler<Sample>>,
    _session: Session,
}

impl RemoteTrajectories {
    /// Connects to `endpoint` (retrying in the background until a bridge answers) and
    /// subscribes to the trajectories of rig `rig`, or of every rig when `None`.
    pub fn connect(endpoint: &str, rig: Option<&str>) -> Result<Self> {
        let key_expr = match rig {
            Some(rig) => {
                check_rig_name(rig)?;
                key(rig, Topic::Trajectories)
            }
            None => format!("{KEY_ROOT}/*/{}", Topic::Trajectories),
        };
        let session = zenoh::open(subscriber_config(endpoint)?)
            .wait()
            .map_err(|e| anyhow!("opening a Zenoh session to `{endpoint}`: {e}"))?;
        let subscriber = session
            .declare_subscriber(key_expr.clone())
            .wait()
            .map_err(|e| anyhow!("subscribing to `{key_expr}`: {e}"))?;
        Ok(Self { subscriber, _session: session })
    }

    /// The next sample, waiting at most `timeout`; `Ok(None)` if none came. A sample that does
    /// not decode is an error naming its key (the caller may go on).
    pub fn next(&self, timeout: Duration) -> Result<Option<TrajectorySample>> {
        let Some(sample) = self.subscriber.recv_timeout(timeout).map_err(|e| anyhow!("receiving: {e}"))? else {
            return Ok(None);
        };
        let bytes = sample.payload().to_bytes();
        wire::decode_trajectory_sample(&bytes).map(Some).map_err(|e| anyhow!("sample on `{}`: {e}", sample.key_expr()))
    }
}
