//! handflow's bridge to other machines: what a pipeline publishes on shared memory, on
//! Zenoh.
//!
//! Key expressions are `handflow/<rig>/<topic>` for the fixed binary layout of
//! [`handflow_protocol::wire`] and `handflow/<rig>/<topic>/json` for the same message as
//! JSON (particle sets go out in binary only: tens of thousands of points a frame).
//! [`session_config`] builds the bridge's Zenoh configuration and
//! [`subscriber_config`] the one a remote subscriber opens; [`json`] holds the JSON forms.

#![cfg_attr(test, allow(clippy::unwrap_used))]

use std::fmt;
use std::str::FromStr;

use anyhow::{bail, Context, Result};

pub mod json;
pub mod remote;

/// First chunk of every key expression.
pub const KEY_ROOT: &str = "handflow";

/// The default endpoint: TCP on loopback, port 7447 (Zenoh's usual port).
pub const DEFAULT_ENDPOINT: &str = "tcp/127.0.0.1:7447";

/// What the bridge can forward.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Topic {
    /// Trajectory samples (always forwarded).
    Trajectories,
    /// Labelled clusters.
    Clusters,
    /// Particle sets (binary only).
    Particles,
}

impl Topic {
    /// Every topic, in pipeline order.
    pub const ALL: [Topic; 3] = [Topic::Particles, Topic::Clusters, Topic::Trajectories];

    /// The topic's name: the last chunk of its key expression.
    pub fn name(self) -> &'static str {
        match self {
            Topic::Trajectories => "trajectories",
            Topic::Clusters => "clusters",
            Topic::Particles => "particles",
        }
    }

    /// Whether the topic also goes out as JSON.
    pub fn has_json(self) -> bool {
        self != Topic::Particles
    }
}

impl fmt::Display for Topic {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Topic {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Topic::ALL
            .into_iter()
            .find(|t| t.name() == s)
            .ok_or_else(|| format!("unknown topic `{s}` (expected `trajectories`, `clusters` or `particles`)"))
    }
}

/// Checks that `rig` can be one chunk of a key expression: not empty, no `/`, none of
/// Zenoh's wildcard and verbatim characters (`*`, `$`, `?`, `#`), no whitespace.
pub fn check_rig_name(rig: &str) -> Result<()> {
    if rig.is_empty() {
        bail!("the rig name is empty");
    }
    if let Some(c) = rig.chars().find(|c| matches!(c, '/' | '*' | '$' | '?' | '#' | '@') || c.is_whitespace()) {
        bail!("the rig name `{rig}` contains `{c}`, which a key expression chunk cannot (use letters, digits, `-`, `_`, `.`)");
    }
    Ok(())
}

/// A rig name made from any text (a folder's name, a preset): characters a key expression
/// chunk cannot hold become `_`.
pub fn rig_name_from(text: &str) -> String {
    let name: String =
        text.chars().map(|c| if c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.') { c } else { '_' }).collect();
    if name.is_empty() {
        "rig".into()
    } else {
        name
    }
}

/// `handflow/<rig>/<topic>`, the key of the binary layout.
pub fn key(rig: &str, topic: Topic) -> String {
    format!("{KEY_ROOT}/{rig}/{topic}")
}

/// `handflow/<rig>/<topic>/json`.
pub fn json_key(rig: &str, topic: Topic) -> String {
    format!("{}/json", key(rig, topic))
}

/// Checks a Zenoh endpoint: this build speaks TCP only, `tcp/<host>:<port>`.
pub fn check_endpoint(endpoint: &str) -> Result<()> {
    let Some(address) = endpoint.strip_prefix("tcp/") else {
        bail!("endpoint `{endpoint}`: expected `tcp/<host>:<port>` (this build speaks Zenoh over TCP only)");
    };
    let Some((host, port)) = address.rsplit_once(':') else {
        bail!("endpoint `{endpoint}`: no port (expected `tcp/<host>:<port>`)");
    };
    if host.is_empty() {
        bail!("endpoint `{endpoint}`: no host (expected `tcp/<host>:<port>`, for example `{DEFAULT_ENDPOINT}`)");
    }
    port.parse::<u16>().with_context(|| format!("endpoint `{endpoint}`: port `{port}`"))?;
    Ok(())
}

/// Whether an endpoint listens on loopback only.
pub fn is_loopback(endpoint: &str) -> bool {
    let host = endpoint.strip_prefix("tcp/").and_then(|a| a.rsplit_once(':')).map_or("", |(h, _)| h);
    let host = host.trim_start_matches('[').trim_end_matches(']');
    host == "localhost" || host.parse::<std::net::IpAddr>().is_ok_and(|ip| ip.is_loopback())
}

fn json_list(items: &[String]) -> String {
    serde_json::Value::from(items.to_vec()).to_string()
}

/// A peer session without multicast scouting (a pipeline talks to the endpoints it is
/// given, never to whatever else is on the network), listening on `listen` and connecting
/// to `connect`; connections that drop are retried every 250 ms to 1 s, so a bridge or
/// subscriber that restarts is found again within a second.
fn peer_config(listen: &[String], connect: &[String]) -> Result<zenoh::Config> {
    for endpoint in listen.iter().chain(connect) {
        check_endpoint(endpoint)?;
    }
    let mut config = zenoh::Config::default();
    let mut set = |path: &str, value: String| {
        config.insert_json5(path, &value).map_err(|e| anyhow::anyhow!("Zenoh configuration `{path}`: {e}"))
    };
    set("mode", "\"peer\"".into())?;
    set("scouting/multicast/enabled", "false".into())?;
    set("listen/endpoints", json_list(listen))?;
    set("connect/endpoints", json_list(connect))?;
    // Open at once even if no endpoint answers yet and keep trying in the background (a
    // timeout of 0 would try once only; -1 with no exit on failure hands the endpoint to a
    // background connector).
    set("connect/timeout_ms", "-1".into())?;
    set("connect/exit_on_failure", "false".into())?;
    set("connect/retry", "{ period_init_ms: 250, period_max_ms: 1000, period_increase_factor: 2 }".into())?;
    Ok(config)
}

/// The bridge's session: listening on `listen`, connecting to `connect` (a router, or a
/// subscriber that listens).
pub fn session_config(listen: &[String], connect: &[String]) -> Result<zenoh::Config> {
    if listen.is_empty() && connect.is_empty() {
        bail!("no Zenoh endpoint: give one to listen on or to connect to");
    }
    peer_config(listen, connect)
}

/// A remote subscriber's session: connecting to the bridge's endpoint, and reconnecting
/// whenever the bridge comes back.
pub fn subscriber_config(connect: &str) -> Result<zenoh::Config> {
    peer_config(&[], &[connect.to_owned()])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_name_the_rig_and_the_topic() {
        assert_eq!(key("studio-a", Topic::Trajectories), "handflow/studio-a/trajectories");
        assert_eq!(json_key("studio-a", Topic::Clusters), "handflow/studio-a/clusters/json");
        assert_eq!("particles".parse::<Topic>().unwrap(), Topic::Particles);
        assert!("frames".parse::<Topic>().unwrap_err().contains("`frames`"));
        assert!(!Topic::Particles.has_json());
    }

    #[test]
    fn rig_names_that_would_be_wildcards_are_refused_or_made_safe() {
        check_rig_name("caliscope-hands").unwrap();
        for bad in ["", "a/b", "a*", "$x", "a b", "a?b"] {
            assert!(check_rig_name(bad).is_err(), "{bad:?}");
        }
        assert_eq!(rig_name_from("my session (2)"), "my_session__2_");
        check_rig_name(&rig_name_from("**/$*")).unwrap();
        assert_eq!(rig_name_from(""), "rig");
    }

    #[test]
    fn endpoints_must_be_tcp_with_a_host_and_a_port() {
        check_endpoint("tcp/127.0.0.1:7447").unwrap();
        check_endpoint("tcp/[::1]:7447").unwrap();
        check_endpoint("tcp/studio.local:7447").unwrap();
        for (bad, says) in [
            ("udp/127.0.0.1:7447", "TCP only"),
            ("tcp/127.0.0.1", "no port"),
            ("tcp/:7447", "no host"),
            ("tcp/h:99999", "port"),
        ] {
            let e = format!("{:#}", check_endpoint(bad).unwrap_err());
            assert!(e.contains(says), "{bad}: {e}");
        }
        assert!(is_loopback("tcp/127.0.0.1:7447") && is_loopback("tcp/[::1]:1") && is_loopback("tcp/localhost:1"));
        assert!(!is_loopback("tcp/0.0.0.0:7447") && !is_loopback("tcp/192.168.1.4:7447"));
    }

    #[test]
    fn configurations_need_an_endpoint_and_turn_multicast_scouting_off() {
        assert!(session_config(&[], &[]).is_err());
        let config = session_config(&[DEFAULT_ENDPOINT.into()], &[]).unwrap();
        let text = format!("{config}");
        assert!(text.contains("7447"), "{text}");
        assert_eq!(config.get_json("scouting/multicast/enabled").unwrap(), "false");
        assert!(subscriber_config("udp/1.2.3.4:1").is_err());
    }
}
