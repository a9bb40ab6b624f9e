//! One rig as a ROS 2 node over DDS (RTPS), the middleware a stock ROS 2 install uses (Fast
//! DDS by default): the `ros2-client` crate on RustDDS. The node `/<rig>/rigbridge` publishes
//! `sensor_msgs/msg/JointState` on `/<rig>/joint_states`, each moving link's transform on
//! `/tf`, the mount and every fixed link on `/tf_static`, and the URDF of the rig in its cell
//! on `/<rig>/robot_description`, with the QoS ROS 2's own tools use (docs/ros2.md).
//!
//! Like the Zenoh node (`node.rs`), its thread reads the cell's latest-value slot
//! (`view::LiveSlot`), which the streaming cycle only offers to with a `try_lock`: nothing
//! here can delay a cycle. Every DDS object lives and dies on this module's threads.
//!
//! Motion only with `[ros2] accept_motion` ([`DdsMotion`]): then, on a thread of its own,
//! `/<rig>/joint_trajectory` is subscribed to and the `/<rig>/follow_joint_trajectory`
//! action is served (`super::fjt`); without it neither exists, so nothing a peer sends can
//! reach a job.

use super::fjt::{self, Goals};
use super::messages::{
    Header, JointState, Quaternion, StringMessage, TfMessage, Time, Transform, TransformStamped,
    Vector3,
};
use super::{DiscoveryRange, Ros2Error, TrajectoryHandler};
use crate::clock::{self, Clock};
use crate::log::RobotDescription;
use crate::view::LiveSlot;
use glam::{DAffine3, DQuat};
use ros2_client::action::ActionServerQosPolicies;
use ros2_client::dds::{ActionServer, Context, Node, Publisher, Spinner, Subscription, rustdds};
use ros2_client::qos::{Durability, History, WhenFull};
use ros2_client::{
    ActionTypeName, MessageTypeName, Name, NodeName, NodeOptions, QosProfile, ServiceMapping,
};
use std::net::{IpAddr, Ipv4Addr};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::thread::JoinHandle;
use std::time::Duration;

/// The frame the rig's mount places its base in: the cell's frame, by the name ROS tools
/// expect of a fixed world frame (REP 105 names `map`/`odom` for mobile bases; a fixed arm's
/// cell is commonly `world`, as in MoveIt's setup assistant).
pub const WORLD_FRAME: &str = "world";
/// Depth of `/<rig>/joint_states`: ROS 2's default profile (reliable, volatile, keep last
/// 10), what robot_state_publisher subscribes with.
const JOINT_STATES_DEPTH: usize = 10;
/// Depth of `/tf`: tf2_ros's `DynamicBroadcasterQoS` (reliable, volatile, keep last 100).
const TF_DEPTH: usize = 100;
/// Depth of the latched topics (`/tf_static`, `robot_description`): the last message is the
/// whole state, kept for late subscribers (transient local), as tf2_ros's
/// `StaticBroadcasterQoS` and robot_state_publisher publish them.
const LATCHED_DEPTH: usize = 1;
/// Depth of `/<rig>/joint_trajectory`: ROS 2's default profile (reliable, volatile, keep
/// last 10), what `ros2 topic pub` and rclpy publish with.
const TRAJECTORY_DEPTH: usize = 10;

/// The motion a DDS node takes (`[ros2] accept_motion`): JointTrajectory messages, and the
/// FollowJointTrajectory action's goals.
pub struct DdsMotion {
    pub trajectories: TrajectoryHandler,
    pub goals: Goals,
}

/// What the node publishes about its rig.
pub struct PublishedRig {
    /// The rig's name: the node's namespace.
    pub name: String,
    pub joints: Vec<String>,
    /// The rig in its cell: the URDF and the links `/tf` is computed from.
    pub robot: Arc<RobotDescription>,
    /// The rig's base frame in the cell (`world`) frame.
    pub mount: DAffine3,
}

/// A running node; dropping it stops publishing and removes it from the DDS graph.
pub struct DdsNode {
    stop: Arc<AtomicBool>,
    published: Arc<AtomicU64>,
    thread: Option<JoinHandle<()>>,
}

impl DdsNode {
    /// Joins DDS domain `domain_id` (only on loopback with [`DiscoveryRange::Localhost`])
    /// and publishes `rig` from `slot` at `joint_states_hz`. `known_at_rest`: the slot's
    /// position is the rig's before any cycle (the in-process twin); otherwise nothing moving
    /// is published until the first cycle's feedback. Returns once the node is declared.
    pub fn start(
        domain_id: u32,
        range: DiscoveryRange,
        joint_states_hz: f64,
        rig: PublishedRig,
        slot: Arc<LiveSlot>,
        known_at_rest: bool,
        motion: Option<DdsMotion>,
    ) -> Result<DdsNode, Ros2Error> {
        super::graph::check_namespace(&rig.name)?;
        let stop = Arc::new(AtomicBool::new(false));
        let published = Arc::new(AtomicU64::new(0));
        let publishing = Publishing {
            stop: stop.clone(),
            published: published.clone(),
            period: Duration::from_secs_f64(1.0 / joint_states_hz),
            slot,
            known_at_rest,
        };
        let (ready, declared) = std::sync::mpsc::sync_channel(1);
        let thread = std::thread::Builder::new()
            .name(format!("ros2-dds-{}", rig.name))
            .spawn(move || {
                // As the Zenoh node: RustDDS starts its event loop's thread from here, and
                // a thread inherits its creator's policy and CPUs; off the cycle's.
                let _ = crate::realtime::normal_priority();
                if let Some(cpu) = crate::realtime::streaming_cpu() {
                    let _ = crate::realtime::keep_off(cpu);
                }
                match Declared::new(domain_id, range, &rig, motion, &publishing.stop) {
                    Ok(declared) => {
                        let _ = ready.send(Ok(()));
                        declared.run(&rig, &publishing);
                    }
                    Err(e) => {
                        let _ = ready.send(Err(e));
                    }
                }
            })
            .map_err(Ros2Error::Thread)?;
        declared.recv().unwrap_or_else(|_| {
            Err(Ros2Error::Thread(std::io::Error::other(
                "the DDS node's thread ended before the node was declared",
            )))
        })?;
        Ok(DdsNode {
            stop,
            published,
            thread: Some(thread),
        })
    }

    /// JointState messages published so far.
    pub fn published(&self) -> u64 {
        self.published.load(Ordering::Relaxed)
    }
}

impl Drop for DdsNode {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

/// What the publishing loop needs besides the DDS objects.
struct Publishing {
    stop: Arc<AtomicBool>,
    published: Arc<AtomicU64>,
    period: Duration,
    slot: Arc<LiveSlot>,
    known_at_rest: bool,
}

/// The node and its publishers; the node's spinner (graph information, ros_discovery_info)
/// runs on a thread of its own until the node goes.
struct Declared {
    node: Node,
    joint_states: Publisher<JointState>,
    tf: Publisher<TfMessage>,
    tf_static: Publisher<TfMessage>,
    description: Publisher<StringMessage>,
    spinner: Option<JoinHandle<()>>,
    /// The motion thread (`[ros2] accept_motion`), ended by the same stop flag.
    motion: Option<JoinHandle<()>>,
}

/// What could not be made, and the DDS side's reason.
fn dds_error<E: std::fmt::Display>(what: &str) -> impl FnOnce(E) -> Ros2Error + '_ {
    move |cause| Ros2Error::Dds {
        what: what.to_string(),
        cause: cause.to_string(),
    }
}

/// A participant on `domain_id`: with `Localhost`, it advertises, joins and sends on
/// 127.0.0.1 only (the loopback interface carries no multicast, so there is none) and finds
/// same-host peers by unicast on their well-known discovery ports, as a ROS 2 Jazzy node does
/// with `ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`; with `Subnet`, every interface and the
/// standard multicast discovery.
fn context(domain_id: u32, range: DiscoveryRange) -> Result<Context, Ros2Error> {
    let domain = u16::try_from(domain_id).map_err(|_| Ros2Error::Dds {
        what: "the DDS domain".into(),
        cause: format!("{domain_id} is not a domain id"),
    })?;
    let mut builder = rustdds::DomainParticipantBuilder::new(domain);
    if range == DiscoveryRange::Localhost {
        builder = builder.with_only_networks([IpAddr::V4(Ipv4Addr::LOCALHOST)]);
    }
    let participant = builder.build().map_err(|cause| Ros2Error::Dds {
        what: format!("a DDS participant on domain {domain_id}"),
        cause: cause.to_string(),
    })?;
    Context::from_domain_participant(participant).map_err(dds_error("the ROS 2 context"))
}

fn qos(durability: Durability, depth: usize) -> QosProfile {
    QosProfile::publisher_default()
        .reliability_reliable(WhenFull::DEFAULT)
        .durability(durability)
        .history(History::KeepLast { depth })
}

impl Declared {
    fn new(
        domain_id: u32,
        range: DiscoveryRange,
        rig: &PublishedRig,
        motion: Option<DdsMotion>,
        stop: &Arc<AtomicBool>,
    ) -> Result<Self, Ros2Error> {
        let context = context(domain_id, range)?;
        let namespace = format!("/{}", rig.name);
        let node_name = NodeName::new(&namespace, super::graph::NODE_NAME)
            .map_err(dds_error("the node's name"))?;
        let mut node = context
            .new_node(node_name, NodeOptions::new().enable_rosout(false))
            .map_err(dds_error("the node"))?;
        let joint_states = publisher(
            &mut node,
            (&namespace, "joint_states"),
            ("sensor_msgs", "JointState"),
            qos(Durability::Volatile, JOINT_STATES_DEPTH),
        )?;
        let tf = publisher(
            &mut node,
            ("/", "tf"),
            ("tf2_msgs", "TFMessage"),
            qos(Durability::Volatile, TF_DEPTH),
        )?;
        let tf_static = publisher(
            &mut node,
            ("/", "tf_static"),
            ("tf2_msgs", "TFMessage"),
            qos(Durability::TransientLocal, LATCHED_DEPTH),
        )?;
        let description = publisher(
            &mut node,
            (&namespace, "robot_description"),
            ("std_msgs", "String"),
            qos(Durability::TransientLocal, LATCHED_DEPTH),
        )?;
        let motion = match motion {
            Some(motion) => Some(start_motion(&mut node, &namespace, motion, stop.clone())?),
            None => None,
        };
        let spinner = node.spinner().map_err(dds_error("the node's spinner"))?;
        let spinner = std::thread::Builder::new()
            .name(format!("ros2-spin-{}", rig.name))
            .spawn(move || spin(spinner))
            .map_err(Ros2Error::Thread)?;
        Ok(Declared {
            node,
            joint_states,
            tf,
            tf_static,
            description,
            spinner: Some(spinner),
            motion,
        })
    }

    /// The latched topics once, then joint states and `/tf` every period until the stop
    /// flag; then the node stops its spinner and everything is dropped, here.
    fn run(mut self, rig: &PublishedRig, io: &Publishing) {
        let latched = self
            .description
            .publish(StringMessage {
                data: rig.robot.urdf().to_string(),
            })
            .map_err(|e| e.to_string())
            .and_then(|()| {
                self.tf_static
                    .publish(static_transforms(rig, now()))
                    .map_err(|e| e.to_string())
            });
        if let Err(e) = latched {
            tracing::warn!("ros2: publishing the robot description and /tf_static: {e}");
        }
        publish_states(&self, rig, io);
        if let Some(motion) = self.motion.take() {
            let _ = motion.join();
        }
        self.node.stop_spinner();
        if let Some(spinner) = self.spinner.take() {
            let _ = spinner.join();
        }
    }
}

fn publisher<M: serde::Serialize>(
    node: &mut Node,
    (namespace, topic): (&str, &str),
    (package, type_name): (&str, &str),
    qos: QosProfile,
) -> Result<Publisher<M>, Ros2Error> {
    let what = format!("{}/{topic}", namespace.trim_end_matches('/'));
    let name = Name::new(namespace, topic).map_err(dds_error(&what))?;
    let topic = node
        .create_topic(&name, MessageTypeName::new(package, type_name), &qos)
        .map_err(dds_error(&what))?;
    node.create_publisher(&topic, None)
        .map_err(dds_error(&what))
}

/// The trajectory subscription and the action server on `node`, served on a thread of
/// their own every [`fjt::TICK`] until `stop`.
fn start_motion(
    node: &mut Node,
    namespace: &str,
    motion: DdsMotion,
    stop: Arc<AtomicBool>,
) -> Result<JoinHandle<()>, Ros2Error> {
    let what = format!("{namespace}/joint_trajectory");
    let name = Name::new(namespace, "joint_trajectory").map_err(dds_error(&what))?;
    let qos = qos(Durability::Volatile, TRAJECTORY_DEPTH);
    let topic = node
        .create_topic(
            &name,
            MessageTypeName::new("trajectory_msgs", "JointTrajectory"),
            &qos,
        )
        .map_err(dds_error(&what))?;
    let trajectories: Subscription<super::messages::JointTrajectory> = node
        .create_subscription(&topic, None)
        .map_err(dds_error(&what))?;
    let what = format!("{namespace}/follow_joint_trajectory");
    let name = Name::new(namespace, "follow_joint_trajectory").map_err(dds_error(&what))?;
    let server = node
        .create_action_server(
            ServiceMapping::Enhanced,
            &name,
            &ActionTypeName::new("control_msgs", "FollowJointTrajectory"),
            action_qos(),
        )
        .map_err(dds_error(&what))?;
    std::thread::Builder::new()
        .name(format!("ros2-motion{}", namespace.replace('/', "-")))
        .spawn(move || serve_motion(&trajectories, &server, motion, &stop))
        .map_err(Ros2Error::Thread)
}

/// The QoS an rclpy ActionClient asks for: its services and feedback reliable and
/// volatile, its status topic transient local (rcl_action's defaults).
fn action_qos() -> ActionServerQosPolicies {
    let service = qos(Durability::Volatile, TRAJECTORY_DEPTH);
    ActionServerQosPolicies {
        goal_service: service.clone(),
        result_service: service.clone(),
        cancel_service: service.clone(),
        feedback_publisher: service,
        status_publisher: qos(Durability::TransientLocal, LATCHED_DEPTH),
    }
}

/// Every tick: each JointTrajectory received to the handler, then the action's requests,
/// feedback and statuses.
fn serve_motion(
    trajectories: &Subscription<super::messages::JointTrajectory>,
    server: &ActionServer<fjt::Goal, fjt::Outcome, fjt::Feedback>,
    mut motion: DdsMotion,
    stop: &AtomicBool,
) {
    let mut next = clock::real().now();
    while !stop.load(Ordering::Relaxed) {
        loop {
            match trajectories.take() {
                Ok(Some((message, _))) => (motion.trajectories)(Ok(message)),
                Ok(None) => break,
                Err(e) => {
                    tracing::warn!("ros2: reading a JointTrajectory over DDS: {e}");
                    break;
                }
            }
        }
        fjt::serve_tick(server, &mut motion.goals);
        next = super::node::pace(next, fjt::TICK);
    }
}

/// The spinner answers graph queries until the node stops it; it needs an executor of its
/// own, a one-thread tokio runtime here (the daemon's runtime is not entered from ours).
fn spin(spinner: Spinner) {
    match tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
    {
        Ok(runtime) => {
            if let Err(e) = runtime.block_on(spinner.spin()) {
                tracing::warn!("ros2: the DDS node's spinner stopped: {e}");
            }
        }
        Err(e) => tracing::warn!("ros2: no runtime for the DDS node's spinner: {e}"),
    }
}

/// The Unix time now, as ROS 2 stamps messages.
fn now() -> Time {
    let now = clock::real().unix_time();
    Time {
        sec: i32::try_from(now.as_secs()).unwrap_or(i32::MAX),
        nanosec: now.subsec_nanos(),
    }
}

fn transform(parent: &str, child: &str, at: DAffine3, stamp: Time) -> TransformStamped {
    let t = at.translation;
    let q = DQuat::from_mat3(&at.matrix3).normalize();
    TransformStamped {
        header: Header {
            stamp,
            frame_id: parent.to_string(),
        },
        child_frame_id: child.to_string(),
        transform: Transform {
            translation: Vector3 {
                x: t.x,
                y: t.y,
                z: t.z,
            },
            rotation: Quaternion {
                x: q.x,
                y: q.y,
                z: q.z,
                w: q.w,
            },
        },
    }
}

/// `/tf_static`: the mount (`world` to the rig's base) and every fixed link. The fixed
/// links do not depend on the positions: any vector of the right length gives them.
fn static_transforms(rig: &PublishedRig, stamp: Time) -> TfMessage {
    let zeros = vec![0.0; rig.joints.len()];
    let mut transforms = vec![];
    if let Some((base, _)) = rig.robot.frames().next() {
        transforms.push(transform(WORLD_FRAME, base, rig.mount, stamp));
    }
    if let Some(links) = rig.robot.link_transforms(&zeros) {
        let fixed = rig.robot.frames().zip(rig.robot.fixed()).zip(links);
        transforms.extend(
            fixed
                .filter(|((_, fixed), _)| *fixed)
                .map(|(((parent, child), _), at)| transform(parent, child, at, stamp)),
        );
    }
    TfMessage { transforms }
}

/// Fills `message` with each moving link's transform at `positions`.
fn moving_transforms(
    robot: &RobotDescription,
    positions: &[f64],
    stamp: Time,
    message: &mut TfMessage,
) {
    message.transforms.clear();
    let Some(links) = robot.link_transforms(positions) else {
        return;
    };
    let moving = robot.frames().zip(robot.fixed()).zip(links);
    message.transforms.extend(
        moving
            .filter(|((_, fixed), _)| !*fixed)
            .map(|(((parent, child), _), at)| transform(parent, child, at, stamp)),
    );
}

/// Every period: the slot's latest actual position as a JointState and as `/tf`, stamped
/// alike with the Unix time. A late wake publishes once and keeps the rate from there.
fn publish_states(declared: &Declared, rig: &PublishedRig, io: &Publishing) {
    let mut states = JointState {
        header: Header::default(),
        name: rig.joints.clone(),
        position: Vec::with_capacity(rig.joints.len()),
        velocity: Vec::new(),
        effort: Vec::new(),
    };
    let mut tf = TfMessage::default();
    let mut next = clock::real().now();
    let mut failing = false;
    while !io.stop.load(Ordering::Relaxed) {
        let sample = io.slot.latest();
        if sample.cycles == 0 && !io.known_at_rest {
            next = super::node::pace(next, io.period);
            continue;
        }
        let stamp = now();
        states.header.stamp = stamp;
        states.position.clear();
        states.position.extend_from_slice(sample.actual.as_slice());
        moving_transforms(&rig.robot, &states.position, stamp, &mut tf);
        let sent = declared
            .joint_states
            .publish(states.clone())
            .map_err(|e| e.to_string())
            .and_then(|()| declared.tf.publish(tf.clone()).map_err(|e| e.to_string()));
        match sent {
            Ok(()) => {
                io.published.fetch_add(1, Ordering::Relaxed);
                failing = false;
            }
            // Said once per run of failures, not at the publishing rate.
            Err(e) if !failing => {
                tracing::warn!("ros2: publishing joint states over DDS: {e}");
                failing = true;
            }
            Err(_) => {}
        }
        next = super::node::pace(next, io.period);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cell::Cell;
    use crate::rig::load_rig;
    use glam::DVec3;
    use std::collections::HashMap;
    use std::path::Path;

    fn irb120() -> crate::rig::Rig {
        load_rig(&Path::new(env!("CARGO_MANIFEST_DIR")).join("config/irb120.toml"))
            .expect("the IRB 120 rig loads")
    }

    fn published(rig: &crate::rig::Rig) -> PublishedRig {
        let cell = Cell::builtin();
        PublishedRig {
            name: rig.name.clone(),
            joints: rig.joint_names().map(String::from).collect(),
            robot: Arc::new(RobotDescription::generated(rig, &cell)),
            mount: cell.mount,
        }
    }

    fn affine(t: &Transform) -> DAffine3 {
        let r = t.rotation;
        DAffine3::from_rotation_translation(
            DQuat::from_xyzw(r.x, r.y, r.z, r.w),
            DVec3::new(t.translation.x, t.translation.y, t.translation.z),
        )
    }

    /// tf2's lookup: `tip` in `base`, walking up the parents the messages name.
    fn lookup(messages: &[&TfMessage], base: &str, tip: &str) -> DAffine3 {
        let links: HashMap<&str, (&str, DAffine3)> = messages
            .iter()
            .flat_map(|m| &m.transforms)
            .map(|t| {
                let parent = t.header.frame_id.as_str();
                (t.child_frame_id.as_str(), (parent, affine(&t.transform)))
            })
            .collect();
        let (mut pose, mut frame) = (DAffine3::IDENTITY, tip);
        while frame != base {
            let (parent, link) = links[frame];
            (pose, frame) = (link * pose, parent);
        }
        pose
    }

    #[test]
    fn tf_and_tf_static_compose_to_the_rigs_forward_kinematics() {
        let rig = irb120();
        let published = published(&rig);
        let q = [0.3, -0.4, 0.5, -1.1, 0.7, 2.0];
        let stamp = Time { sec: 7, nanosec: 9 };
        let fixed = static_transforms(&published, stamp);
        let mut moving = TfMessage::default();
        moving_transforms(&published.robot, &q, stamp, &mut moving);
        // Each frame has one parent, in one of the two topics.
        assert_eq!(moving.transforms.len(), 6, "one per joint");
        assert_eq!(fixed.transforms[0].header.frame_id, WORLD_FRAME);
        let tool = lookup(&[&fixed, &moving], "base_link", "tool0");
        let expected = rig.forward(&q).expect("six positions");
        assert!((tool.translation - expected.translation).length() < 1e-12);
        assert!(tool.matrix3.abs_diff_eq(expected.matrix3, 1e-12));
        let base = lookup(&[&fixed, &moving], WORLD_FRAME, "base_link");
        assert!(base.abs_diff_eq(published.mount, 1e-12));
        let stamps = fixed.transforms.iter().chain(&moving.transforms);
        assert!(stamps.map(|t| t.header.stamp).all(|s| s == stamp));
    }
}
