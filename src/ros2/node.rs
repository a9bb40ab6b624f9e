//! One rig as a ROS 2 node over Zenoh, the way rmw_zenoh makes one: a Zenoh session (peer
//! mode, connected to the configured endpoint, multicast scouting off), liveliness tokens
//! for the node, its JointState publisher and, when asked, its JointTrajectory subscription
//! and its servo key (`<rig>/servo`, docs/online.md), a thread that publishes the rig's
//! latest state at a fixed rate, and a thread for each subscription that hands every
//! message received to a handler.
//!
//! The publishing thread reads the cell's latest-value slot (`view::LiveSlot`), the same the
//! live view samples: the streaming cycle only offers to that slot with a `try_lock`, so
//! nothing here can delay a cycle. Every Zenoh object lives and dies on these threads.
//! This module must not plan, validate or start jobs: the handler does that.

use super::graph::{self, NodeNames, TopicType};
use super::messages::{self, CdrError, Header, JointState, JointTrajectory, Time};
use super::type_hash;
use super::{Ros2Error, Ros2Settings};
use crate::clock::{self, Clock};
use crate::view::LiveSlot;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::thread::JoinHandle;
use std::time::Duration;
use zenoh::Wait;

/// How often the trajectory thread looks at the stop flag while no sample comes.
const POLL: Duration = Duration::from_millis(100);

/// What a node does with each JointTrajectory it receives (or why one could not be read).
pub type TrajectoryHandler = Box<dyn FnMut(Result<JointTrajectory, CdrError>) + Send>;

/// What a node does with each servo message's payload on `<rig>/servo` (`Some`), and after
/// [`POLL`] without one (`None`: a stream's end is seen without a message).
pub type ServoHandler = Box<dyn FnMut(Option<&[u8]>) + Send>;

/// The motion a node takes (`[ros2] accept_motion`): trajectories and servo targets.
pub struct Motion {
    pub trajectories: TrajectoryHandler,
    pub servo: ServoHandler,
}

/// The servo key of rig `rig`: one plain Zenoh key, not a ROS 2 topic (a servo target is
/// rigbridge's JSON, as on the WebSocket route).
pub fn servo_key(rig: &str) -> String {
    format!("{rig}/servo")
}

/// A running node; dropping it removes the node from the graph (its tokens go) and closes
/// the session.
pub struct Ros2Node {
    stop: Arc<AtomicBool>,
    published: Arc<AtomicU64>,
    thread: Option<JoinHandle<()>>,
    names: NodeNames,
}

impl Ros2Node {
    /// Opens the session and declares the node of rig `rig` (its joints `joints`),
    /// publishing `/<rig>/joint_states` from `slot` and, with `motion`, subscribing to
    /// `/<rig>/joint_trajectory` and `<rig>/servo`. `known_at_rest`: the slot's position is the rig's before
    /// any cycle (the in-process twin); otherwise nothing is published until the first
    /// cycle's feedback. Returns once the node is declared.
    pub fn start(
        settings: &Ros2Settings,
        rig: &str,
        joints: Vec<String>,
        slot: Arc<LiveSlot>,
        known_at_rest: bool,
        motion: Option<Motion>,
    ) -> Result<Ros2Node, Ros2Error> {
        graph::check_namespace(rig)?;
        let stop = Arc::new(AtomicBool::new(false));
        let published = Arc::new(AtomicU64::new(0));
        let publishing = Publishing {
            stop: stop.clone(),
            published: published.clone(),
            period: Duration::from_secs_f64(1.0 / settings.joint_states_hz),
            joints,
            slot,
            known_at_rest,
        };
        let (settings, rig_name) = (settings.clone(), rig.to_string());
        let (ready, declared) = std::sync::mpsc::sync_channel(1);
        let thread = std::thread::Builder::new()
            .name(format!("ros2-{rig}"))
            .spawn(move || {
                // Zenoh starts its runtime's threads from the thread that opens the first
                // session, and they inherit its policy: opened from a SCHED_FIFO thread
                // (`run`'s streaming thread, a benchmark's main), all of Zenoh would compete
                // with the cycle. Stepping down can only fail for a thread that is gone.
                let _ = crate::realtime::normal_priority();
                // Off the CPU a streaming thread keeps to (`realtime::streaming_cpu`): the
                // node's sends and the loopback's soft interrupts then run elsewhere.
                if let Some(cpu) = crate::realtime::streaming_cpu() {
                    let _ = crate::realtime::keep_off(cpu);
                }
                match open_node(&settings, &rig_name, motion.is_some()) {
                    Ok((session, declared, names)) => {
                        let _ = ready.send(Ok(names));
                        run_node(session, declared, publishing, motion);
                    }
                    Err(e) => {
                        let _ = ready.send(Err(e));
                    }
                }
            })
            .map_err(Ros2Error::Thread)?;
        let names = declared.recv().unwrap_or_else(|_| {
            Err(Ros2Error::Thread(std::io::Error::other(
                "the node's thread ended before the node was declared",
            )))
        })?;
        Ok(Ros2Node {
            stop,
            published,
            thread: Some(thread),
            names,
        })
    }

    /// JointState messages published so far.
    pub fn published(&self) -> u64 {
        self.published.load(Ordering::Relaxed)
    }

    /// The key expression the joint states go out on.
    pub fn joint_states_key(&self) -> String {
        let topic = self.names.topic("joint_states");
        self.names.topic_key(&topic, joint_state_type())
    }
}

impl Drop for Ros2Node {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

fn joint_state_type() -> TopicType {
    static HASH: std::sync::OnceLock<String> = std::sync::OnceLock::new();
    TopicType {
        dds_type: graph::JOINT_STATE_DDS,
        hash: HASH.get_or_init(|| type_hash::JOINT_STATE.rihs01()),
    }
}

fn joint_trajectory_type() -> TopicType {
    static HASH: std::sync::OnceLock<String> = std::sync::OnceLock::new();
    TopicType {
        dds_type: graph::JOINT_TRAJECTORY_DDS,
        hash: HASH.get_or_init(|| type_hash::JOINT_TRAJECTORY.rihs01()),
    }
}

/// Opens the session and declares the node; on failure the session is closed again.
fn open_node(
    settings: &Ros2Settings,
    rig: &str,
    subscribe: bool,
) -> Result<(zenoh::Session, Declared, NodeNames), Ros2Error> {
    let session = open_session(settings)?;
    let names = NodeNames::new(settings.domain_id, session.zid().to_string(), rig);
    match Declared::new(&session, &names, subscribe) {
        Ok(declared) => Ok((session, declared, names)),
        Err(e) => {
            let _ = session.close().wait();
            Err(e)
        }
    }
}

/// A peer session like rmw_zenoh's default one: it connects to `endpoint` (a router, or
/// any peer) and keeps retrying in the background while that is down; no multicast
/// scouting, and it listens on nothing (everything goes through the endpoint). With a
/// login it authenticates with Zenoh's `usrpwd` (a challenge: the password itself does not
/// travel), and Zenoh then also refuses an endpoint that does not ask for one.
fn open_session(settings: &Ros2Settings) -> Result<zenoh::Session, Ros2Error> {
    let super::Middleware::Zenoh { connect: endpoint } = &settings.middleware else {
        return Err(Ros2Error::NoZenohEndpoint);
    };
    let mut config = zenoh::Config::default();
    let entries = [
        ("mode", "\"peer\"".to_string()),
        ("connect/endpoints", format!("[\"{endpoint}\"]")),
        ("listen/endpoints", "[]".to_string()),
        ("scouting/multicast/enabled", "false".to_string()),
    ];
    // User and password in one insertion: Zenoh refuses a user without a password.
    let login = settings.login.as_ref().map(|login| {
        let value = serde_json::json!({ "user": login.user, "password": login.password });
        ("transport/auth/usrpwd", value.to_string())
    });
    for (key, value) in entries.into_iter().chain(login) {
        config
            .insert_json5(key, &value)
            .map_err(|cause| Ros2Error::Config {
                key,
                cause: cause.to_string(),
            })?;
    }
    zenoh::open(config).wait().map_err(|cause| Ros2Error::Open {
        endpoint: endpoint.clone(),
        cause: cause.to_string(),
    })
}

/// What the node declared: its tokens (kept alive), the publisher and the subscriber.
struct Declared {
    _tokens: Vec<zenoh::liveliness::LivelinessToken>,
    publisher: zenoh::pubsub::Publisher<'static>,
    gid: [u8; 16],
    subscriber: Option<(Subscriber, Subscriber)>,
}

impl Declared {
    fn new(
        session: &zenoh::Session,
        names: &NodeNames,
        subscribe: bool,
    ) -> Result<Self, Ros2Error> {
        let states = names.topic("joint_states");
        let publisher_token =
            names.topic_token(names.node_id + 1, "MP", &states, joint_state_type());
        let mut tokens = vec![declare(
            "the node's liveliness token",
            session
                .liveliness()
                .declare_token(names.node_token())
                .wait(),
        )?];
        let key = names.topic_key(&states, joint_state_type());
        let publisher = declare(&key, session.declare_publisher(key.clone()).wait())?;
        tokens.push(declare(
            "the publisher's liveliness token",
            session
                .liveliness()
                .declare_token(publisher_token.clone())
                .wait(),
        )?);
        let subscriber = if subscribe {
            let topic = names.topic("joint_trajectory");
            let key = names.topic_key(&topic, joint_trajectory_type());
            let subscriber = declare(&key, session.declare_subscriber(key.clone()).wait())?;
            let token = names.topic_token(names.node_id + 2, "MS", &topic, joint_trajectory_type());
            tokens.push(declare(
                "the subscription's liveliness token",
                session.liveliness().declare_token(token).wait(),
            )?);
            let servo = servo_key(names.namespace.trim_start_matches('/'));
            let servo = declare(&servo, session.declare_subscriber(servo.clone()).wait())?;
            Some((subscriber, servo))
        } else {
            None
        };
        Ok(Declared {
            _tokens: tokens,
            publisher,
            gid: graph::gid(&publisher_token),
            subscriber,
        })
    }
}

fn declare<T>(what: &str, result: zenoh::Result<T>) -> Result<T, Ros2Error> {
    result.map_err(|cause| Ros2Error::Declare {
        what: what.to_string(),
        cause: cause.to_string(),
    })
}

/// What the publishing loop needs besides the Zenoh objects.
struct Publishing {
    stop: Arc<AtomicBool>,
    published: Arc<AtomicU64>,
    period: Duration,
    joints: Vec<String>,
    slot: Arc<LiveSlot>,
    known_at_rest: bool,
}

/// The node's thread: the trajectory thread beside it, then the publishing loop until the
/// stop flag; then everything is undeclared and the session closed, here.
fn run_node(
    session: zenoh::Session,
    declared: Declared,
    publishing: Publishing,
    motion: Option<Motion>,
) {
    let Declared {
        _tokens,
        publisher,
        gid,
        subscriber,
    } = declared;
    let receiving = match (subscriber, motion) {
        (Some((trajectories, servo)), Some(motion)) => {
            let Motion {
                trajectories: mut on_trajectory,
                servo: on_servo,
            } = motion;
            let stop = publishing.stop.clone();
            let trajectory_thread = std::thread::spawn(move || {
                receive(trajectories, &stop, |payload| {
                    if let Some(payload) = payload {
                        on_trajectory(messages::decode_joint_trajectory(payload));
                    }
                })
            });
            let stop = publishing.stop.clone();
            let servo_thread = std::thread::spawn(move || receive(servo, &stop, on_servo));
            vec![trajectory_thread, servo_thread]
        }
        _ => Vec::new(),
    };
    publish_states(&publisher, &gid, &publishing);
    for thread in receiving {
        let _ = thread.join();
    }
    drop(_tokens);
    let _ = publisher.undeclare().wait();
    let _ = session.close().wait();
}

/// Every period: the slot's latest actual position as a JointState, stamped with the Unix
/// time ROS 2 uses, its attachment numbering it. A late wake publishes once and keeps the
/// rate from there (no burst of catch-up messages).
fn publish_states(publisher: &zenoh::pubsub::Publisher<'_>, gid: &[u8; 16], io: &Publishing) {
    let mut message = JointState {
        header: Header::default(),
        name: io.joints.clone(),
        position: Vec::with_capacity(io.joints.len()),
        velocity: Vec::new(),
        effort: Vec::new(),
    };
    let mut sequence: i64 = 0;
    let mut next = clock::real().now();
    let mut failing = false;
    while !io.stop.load(Ordering::Relaxed) {
        let sample = io.slot.latest();
        if sample.cycles == 0 && !io.known_at_rest {
            next = pace(next, io.period);
            continue;
        }
        message.position.clear();
        message.position.extend_from_slice(sample.actual.as_slice());
        let now = clock::real().unix_time();
        message.header.stamp = Time {
            sec: i32::try_from(now.as_secs()).unwrap_or(i32::MAX),
            nanosec: now.subsec_nanos(),
        };
        sequence += 1;
        let stamp_ns = i64::try_from(now.as_nanos()).unwrap_or(i64::MAX);
        let sent = messages::encode(&message)
            .map_err(|e| e.to_string())
            .and_then(|payload| {
                publisher
                    .put(payload)
                    .attachment(graph::attachment(sequence, stamp_ns, gid))
                    .wait()
                    .map_err(|e| e.to_string())
            });
        match sent {
            Ok(()) => {
                io.published.fetch_add(1, Ordering::Relaxed);
                failing = false;
            }
            // Said once per run of failures, not at the publishing rate.
            Err(e) if !failing => {
                tracing::warn!("ros2: publishing joint states: {e}");
                failing = true;
            }
            Err(_) => {}
        }
        next = pace(next, io.period);
    }
}

/// Sleeps until `next` plus one period and returns that time; a late wake keeps the rate
/// from now on.
pub(super) fn pace(next: Duration, period: Duration) -> Duration {
    let mut next = next + period;
    let now = clock::real().now();
    if next <= now {
        next = now + period;
    }
    std::thread::sleep(next - now);
    next
}

type Subscriber =
    zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>;

/// Every sample's payload to `handler` (and `None` after [`POLL`] without one) until the
/// stop flag or the session's end.
fn receive(subscriber: Subscriber, stop: &AtomicBool, mut handler: impl FnMut(Option<&[u8]>)) {
    while !stop.load(Ordering::Relaxed) {
        match subscriber.recv_timeout(POLL) {
            Ok(Some(sample)) => {
                let payload = sample.payload().to_bytes();
                handler(Some(&payload));
            }
            Ok(None) => handler(None),
            // The session is closing.
            Err(_) => break,
        }
    }
    let _ = subscriber.undeclare().wait();
}
