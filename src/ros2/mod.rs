//! ROS 2, over DDS (a stock install's middleware, `dds`) or over Zenoh as rmw_zenoh speaks
//! it (docs/ros2.md). Over Zenoh, each rig is a node in its own
//! namespace (`/<rig>`) that publishes `sensor_msgs/msg/JointState` on `/<rig>/joint_states`
//! and, under `serve` with `[ros2] accept_motion`, takes `trajectory_msgs/msg/JointTrajectory`
//! on `/<rig>/joint_trajectory`. Any ROS 2 node on rmw_zenoh (or any Zenoh session) that
//! reaches the same router or peer sees it, so several daemons form one fleet; with a
//! [`Login`], only sessions the router admits by user and password reach it.
//!
//! Over DDS, the same node also publishes `/tf`, `/tf_static` and `/<rig>/robot_description`,
//! and with `[ros2] accept_motion` takes JointTrajectory on `/<rig>/joint_trajectory` and
//! serves the `control_msgs/action/FollowJointTrajectory` action at
//! `/<rig>/follow_joint_trajectory` (`fjt`).
//!
//! `type_hash` computes the RIHS01 hashes, `messages` encodes CDR, `graph` names keys,
//! tokens and attachments, `node` runs the Zenoh session, `dds` the DDS participant. This module sits beside the live
//! view after the stream: it reads the cycle's states through the view's latest-value slot
//! and never touches the cycle; turning a received trajectory into a job is the daemon's.

mod dds;
pub mod fjt;
pub mod graph;
pub mod messages;
mod node;
pub mod type_hash;

pub use dds::{DdsMotion, DdsNode, PublishedRig, WORLD_FRAME};
pub use node::{Motion, Ros2Node, ServoHandler, TrajectoryHandler, servo_key};

use thiserror::Error;

/// JointState messages a second when `[ros2] joint_states_hz` is absent: above the 100 Hz a
/// robot_state_publisher user expects, every other cycle of the 250 Hz stream.
pub const DEFAULT_JOINT_STATES_HZ: f64 = 125.0;
/// Highest ROS 2 domain id (the DDS port mapping's limit, which rmw_zenoh keeps).
pub const MAX_DOMAIN_ID: u32 = 232;
/// `[ros2] path_tolerance` when absent (rad, m): how far the arm may be from the position
/// commanded while a FollowJointTrajectory goal runs. The twin follows within a cycle's
/// step (under 0.02 rad at the IRB 120's fastest axis); a real controller's lag is larger,
/// and this still stops an arm that does not follow well before it strays a hand's width.
pub const DEFAULT_PATH_TOLERANCE: f64 = 0.05;
/// `[ros2] goal_tolerance` when absent (rad, m): how close to the last point a goal must
/// end; the stream's own settle check already holds a completed job to its goal tolerance.
pub const DEFAULT_GOAL_TOLERANCE: f64 = 0.01;

/// Where and how a rig joins ROS 2.
#[derive(Debug, Clone, PartialEq)]
pub struct Ros2Settings {
    pub middleware: Middleware,
    pub domain_id: u32,
    pub joint_states_hz: f64,
    /// The user and password the session logs in to its router with (Zenoh's `usrpwd`
    /// authentication); `None`: it connects anonymously.
    pub login: Option<Login>,
    /// Whether `serve` subscribes to `/<rig>/joint_trajectory` and runs what comes as jobs
    /// (and, over DDS, serves the FollowJointTrajectory action).
    pub accept_motion: bool,
    /// A FollowJointTrajectory goal's tolerances where it names none.
    pub tolerances: fjt::Tolerances,
}

/// Which middleware a rig's node speaks.
#[derive(Debug, Clone, PartialEq)]
pub enum Middleware {
    /// DDS (RTPS), a stock ROS 2 install's default (Fast DDS), found within `range`.
    Dds { range: DiscoveryRange },
    /// Zenoh as rmw_zenoh: a peer session connected to `connect`, `tcp/HOST:PORT`.
    Zenoh { connect: String },
}

/// Whom DDS discovery reaches, as ROS 2's `ROS_AUTOMATIC_DISCOVERY_RANGE` says it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DiscoveryRange {
    /// Nodes on this machine only: everything on 127.0.0.1, no multicast.
    Localhost,
    /// Every interface, multicast discovery (the DDS default).
    Subnet,
}

impl std::fmt::Display for Middleware {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Middleware::Dds {
                range: DiscoveryRange::Localhost,
            } => f.write_str("DDS on this machine (127.0.0.1)"),
            Middleware::Dds {
                range: DiscoveryRange::Subnet,
            } => f.write_str("DDS on every interface"),
            Middleware::Zenoh { connect } => write!(f, "Zenoh through {connect}"),
        }
    }
}

/// A rig's node on either middleware.
pub enum RigNode {
    Dds(DdsNode),
    Zenoh(Ros2Node),
}

impl RigNode {
    /// JointState messages published so far.
    pub fn published(&self) -> u64 {
        match self {
            RigNode::Dds(node) => node.published(),
            RigNode::Zenoh(node) => node.published(),
        }
    }

    /// Where its joint states go, for a log line: the topic, or Zenoh's key expression.
    pub fn joint_states_at(&self, rig: &str) -> String {
        match self {
            RigNode::Dds(_) => {
                format!("/{rig}/joint_states, /tf, /tf_static, /{rig}/robot_description")
            }
            RigNode::Zenoh(node) => node.joint_states_key(),
        }
    }
}

/// Starts `rig`'s node on the middleware `settings` name, publishing from `slot`
/// (`known_at_rest` as [`Ros2Node::start`]), taking `motion` (its servo targets over Zenoh
/// only) and, over DDS, serving FollowJointTrajectory `goals`; a DDS node asked to take
/// motion without both is refused.
pub fn start_node(
    settings: &Ros2Settings,
    rig: PublishedRig,
    slot: std::sync::Arc<crate::view::LiveSlot>,
    known_at_rest: bool,
    motion: Option<Motion>,
    goals: Option<fjt::Goals>,
) -> Result<RigNode, Ros2Error> {
    match &settings.middleware {
        Middleware::Dds { range } => {
            // The settings let motion on with a login or the lab opt-out; a login is
            // Zenoh's, so over DDS only the opt-out lets it on.
            if motion.is_some() && settings.login.is_some() {
                return Err(Ros2Error::LoginOverDds);
            }
            let motion = match (motion, goals) {
                (Some(motion), Some(goals)) => Some(DdsMotion {
                    trajectories: motion.trajectories,
                    goals,
                }),
                (None, None) => None,
                _ => return Err(Ros2Error::HalfMotionOverDds),
            };
            let hz = settings.joint_states_hz;
            let node = DdsNode::start(
                settings.domain_id,
                *range,
                hz,
                rig,
                slot,
                known_at_rest,
                motion,
            )?;
            Ok(RigNode::Dds(node))
        }
        Middleware::Zenoh { .. } => {
            let PublishedRig { name, joints, .. } = rig;
            let node = Ros2Node::start(settings, &name, joints, slot, known_at_rest, motion)?;
            Ok(RigNode::Zenoh(node))
        }
    }
}

/// A Zenoh user and password. The password is never shown: not by `Debug`, not in an
/// error; it goes only into the session's configuration.
#[derive(Clone, PartialEq)]
pub struct Login {
    pub user: String,
    password: String,
}

impl Login {
    pub fn new(user: String, password: String) -> Login {
        Login { user, password }
    }
}

impl std::fmt::Debug for Login {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Login {{ user: {}, password: (hidden) }}", self.user)
    }
}

#[derive(Debug, Error)]
pub enum Ros2Error {
    #[error(transparent)]
    Namespace(#[from] graph::BadNamespace),
    #[error("Zenoh configuration key {key}: {cause}")]
    Config { key: &'static str, cause: String },
    #[error("opening a Zenoh session to {endpoint}: {cause}")]
    Open { endpoint: String, cause: String },
    #[error("declaring {what}: {cause}")]
    Declare { what: String, cause: String },
    #[error("starting the ROS 2 node's thread")]
    Thread(#[source] std::io::Error),
    #[error("creating {what} over DDS: {cause}")]
    Dds { what: String, cause: String },
    #[error(
        "a DDS node takes motion with both a trajectory handler and a FollowJointTrajectory \
         goal runner, or neither"
    )]
    HalfMotionOverDds,
    #[error(
        "[ros2] accept_motion over DDS: user and password_file are a Zenoh login, and DDS \
         has none here (no DDS Security); over DDS motion needs \
         allow_unauthenticated_motion = true, on an isolated network only (docs/ros2.md)"
    )]
    LoginOverDds,
    #[error("this node speaks Zenoh, and the settings name no Zenoh endpoint")]
    NoZenohEndpoint,
}

/// Why `text` is not a Zenoh endpoint rigbridge can connect to, if it is not: only
/// `tcp/HOST:PORT` (the TCP transport is the only one built in).
pub fn endpoint_problem(text: &str) -> Option<&'static str> {
    let Some(address) = text.strip_prefix("tcp/") else {
        return Some("must be tcp/HOST:PORT (TCP is the only Zenoh transport built in)");
    };
    let Some((host, port)) = address.rsplit_once(':') else {
        return Some("must be tcp/HOST:PORT: the port is missing");
    };
    let host = host.trim_start_matches('[').trim_end_matches(']');
    if host.is_empty() || host.contains(['/', '?', '#', '"', ' ']) {
        return Some("must be tcp/HOST:PORT: the host is empty or holds a character a host cannot");
    }
    match port.parse::<u16>() {
        Ok(port) if port > 0 => None,
        _ => Some("must be tcp/HOST:PORT with a port from 1 to 65535"),
    }
}

#[cfg(test)]
mod tests {
    use super::endpoint_problem;

    #[test]
    fn only_tcp_endpoints_with_a_host_and_port_are_taken() {
        for good in ["tcp/127.0.0.1:7447", "tcp/localhost:1", "tcp/[::1]:7447"] {
            assert_eq!(endpoint_problem(good), None, "{good}");
        }
        for bad in [
            "127.0.0.1:7447",
            "udp/127.0.0.1:7447",
            "quic/host:7447",
            "tcp/127.0.0.1",
            "tcp/:7447",
            "tcp/host:0",
            "tcp/host:70000",
            "tcp/host:74a",
        ] {
            assert!(endpoint_problem(bad).is_some(), "{bad}");
        }
    }
}
