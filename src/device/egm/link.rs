//! The EGM link: rigbridge as the sensor of ABB's Externally Guided Motion, in joint mode
//! or (`egm://...?mode=pose`) pose mode.
//!
//! The robot controller sends an EgmRobot every EGM cycle (4 ms) to the address this link
//! binds; an I/O thread answers each one at once with exactly one EgmSensor, sent to the
//! EgmRobot's source address: header seqno +1 per message, `tm` in ms, MSGTYPE_CORRECTION,
//! `planned.joints` in degrees and `speedRef.joints` in deg/s (docs/egm.md). A rig with
//! more axes than the robot's six sends the others as external axes (`externalJoints`,
//! degrees or mm) as [`EgmAxes`] lays them out. In pose mode the answer carries the
//! tool's pose at the target instead (`planned.cartesian`, mm and a unit quaternion in the
//! robot's base frame, with `speedRef.cartesians`): the forward kinematics of the very
//! joint target the streamer's gate checked (limits, speed, acceleration), so the joints
//! behind every pose sent are within the limits; the controller's IK, seeded where its last
//! reference was, finds those joints again.
//!
//! The robot's messages are the clock: [`EgmLink::pacing`] hands out an [`EgmClock`] whose
//! time advances one stream period per EgmRobot, so the streamer's cycle follows the
//! controller's (4.032 ms on real ones) and never a host timer. Targets wait in a short
//! play-out queue ([`PLAYOUT_DEPTH`]); each EgmRobot takes the next one. With no target
//! (before a job, while one is planned, after it) the answer holds the last target, or the
//! feedback position at the start of a session, with zero speed.
//!
//! Motion needs motors on and EGM running: until then the link answers with the feedback
//! position, drops targets and reports itself down, so a job waits for it or resumes from
//! where the arm is. It owns the socket and the EGM session state; it must not plan, check
//! limits (the streamer's gate does) or change a target's values.
//!
//! Every datagram passes the [`RobotGuard`] first (src/link/egm_guard.rs): only the robot
//! the session is bound to is answered, in order, with feedback the arm could have reached.
//! A second robot (unless the robot was named) and a feedback jump are a
//! [`LinkEvent::Untrusted`]: the job is brought to rest and ends, never resumed from them.

use super::guard::{RobotGuard, Verdict};
use crate::clock::Clock;
use crate::device::egm::wire::{
    EgmAxes, EgmKinematics, EgmMode, EgmRobot, EgmSensor, MciState, MotorState, RapidState,
};
use crate::link::{Link, LinkCounters, LinkError, LinkEvent};
use crate::protocol::{AxisValues, Command, ControllerStatus, Feedback, JointTarget};
use prost::Message;
use std::collections::VecDeque;
use std::net::{SocketAddr, UdpSocket};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

/// Targets queued before the first is played: the streamer may then wake up to two robot
/// cycles late without starving the robot (each starved cycle repeats a position: a speed
/// step, which the twin refuses as over acceleration). Measured under a full load of both
/// cores: depth 2 starved the default job in 1 run of 5, depth 3 in none of 10; the cost is
/// 4 ms more latency (12 ms in all), while an EStop still clears the queue at once.
pub const PLAYOUT_DEPTH: usize = 3;
/// Room in the queue: the device-paced streamer runs at most a cycle or two ahead.
const QUEUE_CAPACITY: usize = 64;
/// No EgmRobot for this long ends the session: 25 missed 4 ms cycles, the streamer's own
/// patience (0.1 s) for a silent controller.
pub const LINK_SILENCE: Duration = Duration::from_millis(100);
/// How often the I/O thread wakes without traffic to notice the link was dropped.
const POLL: Duration = Duration::from_millis(50);
/// The streamer's deadlines are f64 seconds turned into nanoseconds: a rounding either way.
const DEADLINE_ROUNDING: Duration = Duration::from_micros(1);
/// Turnaround histogram: 1 us buckets up to 10 ms.
const TURNAROUND_BUCKETS: usize = 10_000;
/// Largest datagram read: an EgmRobot is a few hundred bytes.
const DATAGRAM: usize = 2048;
/// An Untrusted event nobody took within this long happened while no job ran (a job reads
/// the link's events every cycle): it is dropped, its counts stay.
const EVENT_MEMORY: Duration = Duration::from_secs(1);

/// What the EGM link needs to know besides the address it binds.
#[derive(Debug, Clone)]
pub struct EgmLinkSettings {
    /// Where each rig axis travels in EGM.
    pub axes: EgmAxes,
    /// The stream period: one EgmRobot is one period.
    pub period: Duration,
    /// Each rig axis' name and max speed (rad/s, m/s): feedback that moved further than
    /// this between two robot messages is a jump.
    pub names: Vec<String>,
    pub max_speeds: Vec<f64>,
    /// The robot named by `?robot=`: the only source taken. `None`: the first to send.
    pub robot: Option<SocketAddr>,
    /// Joint references, or (`?mode=pose`) the tool's poses.
    pub mode: EgmMode,
    /// The rig, for pose mode's forward kinematics.
    pub rig: crate::rig::Rig,
}

impl EgmLinkSettings {
    /// The settings for `rig` laid out as `axes`, streamed every `period`, bound to `robot`
    /// when given.
    pub fn for_rig(
        rig: &crate::rig::Rig,
        axes: EgmAxes,
        period: Duration,
        robot: Option<SocketAddr>,
    ) -> Self {
        Self {
            axes,
            period,
            names: rig.joint_names().map(String::from).collect(),
            max_speeds: rig.joints.iter().map(|j| j.limits.max_speed).collect(),
            robot,
            mode: EgmMode::Joint,
            rig: rig.clone(),
        }
    }

    /// The same settings streaming in `mode`.
    pub fn in_mode(self, mode: EgmMode) -> Self {
        Self { mode, ..self }
    }
}

/// What the robot last said about itself, and the session's bookkeeping.
#[derive(Debug, Clone, PartialEq)]
pub struct EgmState {
    /// The robot the session is bound to (the named one, or the first to send).
    pub robot: Option<SocketAddr>,
    pub motors: MotorState,
    pub mci: MciState,
    pub rapid: RapidState,
    pub utilization_rate: Option<f64>,
    /// EgmRobot messages taken (the robot's, in order, within reach: src/link/egm_guard.rs)
    /// and EgmSensor replies sent.
    pub messages: u64,
    pub replies: u64,
    /// Robot seqno jumps (lost EgmRobot messages).
    pub robot_gaps: u64,
    /// Datagrams from the robot (or before there was one) that were not an EgmRobot with a
    /// seqno and this rig's joints and external axes.
    pub malformed: u64,
    /// Robot cycles in a job with no target ready (the position was held).
    pub underruns: u64,
    /// Sessions begun: motors on and EGM running after being otherwise or silent, or a new
    /// EGM run (seqno 0) while running.
    pub sessions: u64,
}

impl EgmState {
    /// Motion is allowed: motors on and EGM running.
    pub fn ready(&self) -> bool {
        self.motors == MotorState::On && self.mci == MciState::Running
    }
}

/// Device time: one stream period per EgmRobot while the robot is ready; real time while
/// it is not (or silent), so waits with a deadline still end.
#[derive(Debug, Clone, Copy)]
struct DeviceTime {
    base: Duration,
    at: Instant,
    ticking: bool,
}

impl DeviceTime {
    fn now(&self) -> Duration {
        let elapsed = self.at.elapsed();
        if self.ticking && elapsed < LINK_SILENCE {
            self.base
        } else {
            self.base + elapsed
        }
    }

    fn tick(&mut self, ready: bool, period: Duration, at: Instant) {
        let continuing = self.ticking && at.duration_since(self.at) < LINK_SILENCE;
        self.base = if ready && continuing {
            self.base + period
        } else {
            self.base + at.duration_since(self.at)
        };
        self.at = at;
        self.ticking = ready;
    }
}

struct Session {
    state: EgmState,
    queue: VecDeque<(u64, JointTarget)>,
    playing: bool,
    /// The job ended (Stop): play out what is queued without waiting for more.
    flush: bool,
    /// The position answered with no target to play, rad.
    hold: Option<AxisValues>,
    last_played: u32,
    /// The last target played had a speed: holding after it is a speed step (an underrun).
    moving: bool,
    /// Bumped at each session start: targets and feedback of an older one are stale.
    id: u64,
    /// The session the streamer's last heartbeat saw.
    adopted: u64,
    feedback: Option<Feedback>,
    generation: u64,
    last_message: Option<Instant>,
    last_seqno: Option<u32>,
    time: DeviceTime,
    turnaround: Vec<u64>,
    /// Who may be answered, and what was dropped.
    guard: RobotGuard,
    /// Untrusted events not yet taken, with when they happened.
    events: VecDeque<(Instant, LinkEvent)>,
}

struct Shared {
    session: Mutex<Session>,
    changed: Condvar,
    closed: AtomicBool,
    period: Duration,
    kinematics: EgmKinematics,
    mode: EgmMode,
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, Session> {
        // A panicking holder leaves plain data behind: keep using it.
        self.session.lock().unwrap_or_else(|p| p.into_inner())
    }
}

pub struct EgmLink {
    shared: Arc<Shared>,
    seen: u64,
    local: SocketAddr,
    description: String,
    thread: Option<std::thread::JoinHandle<()>>,
}

/// Binds `address` (such as `0.0.0.0:6510`) for a rig as `settings` say, and starts
/// answering the robot.
pub fn bind_egm(address: &str, settings: EgmLinkSettings) -> std::io::Result<EgmLink> {
    let EgmLinkSettings {
        axes,
        period,
        names,
        max_speeds,
        robot,
        mode,
        rig,
    } = settings;
    let socket = UdpSocket::bind(address)?;
    socket.set_read_timeout(Some(POLL))?;
    let local = socket.local_addr()?;
    let shared = Arc::new(Shared {
        session: Mutex::new(Session {
            state: EgmState {
                robot: None,
                motors: MotorState::Undefined,
                mci: MciState::Undefined,
                rapid: RapidState::Undefined,
                utilization_rate: None,
                messages: 0,
                replies: 0,
                robot_gaps: 0,
                malformed: 0,
                underruns: 0,
                sessions: 0,
            },
            queue: VecDeque::with_capacity(QUEUE_CAPACITY),
            playing: false,
            flush: false,
            hold: None,
            last_played: 0,
            moving: false,
            id: 0,
            adopted: 0,
            feedback: None,
            generation: 0,
            last_message: None,
            last_seqno: None,
            time: DeviceTime {
                base: Duration::ZERO,
                at: Instant::now(),
                ticking: false,
            },
            turnaround: vec![0; TURNAROUND_BUCKETS],
            guard: RobotGuard::new(robot, names, max_speeds),
            events: VecDeque::new(),
        }),
        changed: Condvar::new(),
        closed: AtomicBool::new(false),
        period,
        kinematics: EgmKinematics { rig, axes },
        mode,
    });
    let io = shared.clone();
    let thread = crate::link::spawn_io_thread("rigbridge-egm", move || serve(&socket, &io))?;
    Ok(EgmLink {
        shared,
        seen: 0,
        local,
        description: describe(address, robot, mode),
        thread: Some(thread),
    })
}

/// The link as `egm://` writes it.
fn describe(address: &str, robot: Option<SocketAddr>, mode: EgmMode) -> String {
    let mut options = Vec::new();
    if let Some(robot) = robot {
        options.push(format!("robot={robot}"));
    }
    if mode == EgmMode::Pose {
        options.push("mode=pose".to_string());
    }
    if options.is_empty() {
        format!("egm://{address}")
    } else {
        format!("egm://{address}?{}", options.join("&"))
    }
}

impl EgmLink {
    /// The bound address (the port the robot must send to).
    pub fn local_address(&self) -> SocketAddr {
        self.local
    }

    pub fn state(&self) -> EgmState {
        self.shared.lock().state.clone()
    }

    /// The device-paced clock the streamer must run on.
    pub fn clock(&self) -> EgmClock {
        EgmClock {
            shared: self.shared.clone(),
        }
    }

    /// Bridge turnaround (EgmRobot received to EgmSensor sent): the `q` quantile, us.
    pub fn turnaround_quantile_us(&self, q: f64) -> Option<f64> {
        let session = self.shared.lock();
        let total: u64 = session.turnaround.iter().sum();
        if total == 0 {
            return None;
        }
        let rank = ((q.clamp(0.0, 1.0) * total as f64).ceil() as u64).max(1);
        let mut seen = 0;
        for (micros, count) in session.turnaround.iter().enumerate() {
            seen += count;
            if seen >= rank {
                return Some(micros as f64 + 1.0);
            }
        }
        Some(TURNAROUND_BUCKETS as f64)
    }

    fn fresh(session: &Session) -> bool {
        session
            .last_message
            .is_some_and(|t| t.elapsed() < LINK_SILENCE)
    }
}

impl Drop for EgmLink {
    fn drop(&mut self) {
        self.shared.closed.store(true, Ordering::SeqCst);
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

impl Link for EgmLink {
    fn send(&mut self, command: &Command) -> Result<(), LinkError> {
        let mut session = self.shared.lock();
        match command {
            Command::Target(target) => {
                // A target for a session that ended, or while motion is not allowed, is
                // never played: the robot may have moved since it was planned.
                if session.id != session.adopted || !session.state.ready() {
                    return Ok(());
                }
                if session.queue.len() >= QUEUE_CAPACITY {
                    // Dropping one would make the next a double step: refuse instead.
                    return Err(LinkError::Io(std::io::Error::other(
                        "EGM play-out queue full: the streamer ran ahead of the robot",
                    )));
                }
                let id = session.id;
                session.queue.push_back((id, *target));
            }
            Command::Stop => session.flush = true,
            Command::EStop => {
                // EGM has no e-stop message: stop at the last position sent, at once.
                session.queue.clear();
                session.playing = false;
            }
            // EGM has no fault to clear from the sensor's side: a reset is the pendant's.
            Command::Reset => {}
            Command::Heartbeat => {
                session.adopted = session.id;
                session.flush = false;
                // A job starting while a second robot still sends hears of it again.
                if let Some(words) = session.guard.second_robot_words(Instant::now()) {
                    raise(&mut session, words);
                }
            }
        }
        Ok(())
    }

    fn receive(&mut self, timeout: Duration) -> Result<Option<Feedback>, LinkError> {
        let deadline = Instant::now() + timeout;
        let mut session = self.shared.lock();
        loop {
            if session.generation > self.seen && session.id == session.adopted {
                self.seen = session.generation;
                return Ok(session.feedback);
            }
            let now = Instant::now();
            if now >= deadline {
                return Ok(None);
            }
            session = self
                .shared
                .changed
                .wait_timeout(session, deadline - now)
                .unwrap_or_else(|p| p.into_inner())
                .0;
        }
    }

    fn counters(&self) -> LinkCounters {
        let session = self.shared.lock();
        LinkCounters {
            frames_sent: session.state.replies,
            frames_received: session.state.messages,
            crc_errors: session.state.malformed,
            duplicates: 0,
            gaps: session.state.robot_gaps,
            reconnects: session.state.sessions.saturating_sub(1),
            foreign_dropped: session.guard.counters.foreign,
            replays_dropped: session.guard.counters.replays,
            feedback_jumps: session.guard.counters.jumps,
            second_robots: session.guard.counters.second_robots,
        }
    }

    fn next_event(&mut self) -> Option<LinkEvent> {
        let mut session = self.shared.lock();
        while let Some((at, event)) = session.events.pop_front() {
            if at.elapsed() < EVENT_MEMORY {
                return Some(event);
            }
        }
        None
    }

    fn describe(&self) -> String {
        self.description.clone()
    }

    fn is_up(&self) -> bool {
        let session = self.shared.lock();
        Self::fresh(&session) && session.state.ready()
    }

    fn drain(&mut self) {
        self.seen = self.shared.lock().generation;
    }

    fn pacing(&self) -> Option<Arc<dyn Clock>> {
        Some(Arc::new(self.clock()))
    }
}

/// The streamer's clock on an EGM link: one period per EgmRobot while motion is allowed.
#[derive(Clone)]
pub struct EgmClock {
    shared: Arc<Shared>,
}

impl Clock for EgmClock {
    fn now(&self) -> Duration {
        self.shared.lock().time.now()
    }

    fn sleep_until(&self, deadline: Duration) {
        let mut session = self.shared.lock();
        loop {
            let now = session.time.now();
            if now + DEADLINE_ROUNDING >= deadline {
                return;
            }
            let wait = if session.time.ticking {
                LINK_SILENCE.saturating_sub(session.time.at.elapsed())
            } else {
                deadline - now
            };
            session = self
                .shared
                .changed
                .wait_timeout(session, wait.max(DEADLINE_ROUNDING))
                .unwrap_or_else(|p| p.into_inner())
                .0;
        }
    }

    fn is_virtual(&self) -> bool {
        false
    }
}

/// The I/O thread: one EgmSensor per EgmRobot, until the link is dropped.
fn serve(socket: &UdpSocket, shared: &Shared) {
    let started = Instant::now();
    let mut buffer = [0u8; DATAGRAM];
    let mut out = Vec::with_capacity(DATAGRAM);
    let mut seqno: u32 = 0;
    while !shared.closed.load(Ordering::SeqCst) {
        let (len, from) = match socket.recv_from(&mut buffer) {
            Ok(got) => got,
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) =>
            {
                continue;
            }
            // ICMP errors from an earlier send surface here on some systems: keep serving.
            Err(_) => continue,
        };
        let arrived = Instant::now();
        let Some(reply) = answer(shared, &buffer[..len], from, arrived) else {
            continue;
        };
        seqno = seqno.wrapping_add(1);
        let tm = u32::try_from(started.elapsed().as_millis() % (1 << 32)).unwrap_or(0);
        out.clear();
        let message = match shared.mode {
            EgmMode::Joint => {
                EgmSensor::joint_correction(seqno, tm, &shared.kinematics.axes, &reply.0, &reply.1)
            }
            EgmMode::Pose => {
                EgmSensor::pose_correction(seqno, tm, &shared.kinematics, &reply.0, &reply.1)
            }
        };
        if message.encode(&mut out).is_ok() && socket.send_to(&out, from).is_ok() {
            let micros = arrived.elapsed().as_micros() as usize;
            let mut session = shared.lock();
            session.state.replies += 1;
            session.turnaround[micros.min(TURNAROUND_BUCKETS - 1)] += 1;
        }
    }
}

/// Reads one EgmRobot and decides the answer (positions rad, speeds rad/s); `None` for a
/// datagram that is not answered: not the robot's, not one this rig can answer, a replay or
/// a jump (docs/egm.md).
fn answer(
    shared: &Shared,
    bytes: &[u8],
    from: SocketAddr,
    arrived: Instant,
) -> Option<(Vec<f64>, Vec<f64>)> {
    let robot = EgmRobot::decode(bytes).ok();
    let actual = robot
        .as_ref()
        .and_then(|r| {
            shared
                .kinematics
                .axes
                .join(r.feedback_joints()?, r.feedback_external())
        })
        .filter(|values| values.iter().all(|v| v.is_finite()))
        .and_then(|values| AxisValues::from_slice(&values));
    let mut session = shared.lock();
    let message = robot.as_ref().zip(actual.as_ref());
    let verdict = session
        .guard
        .judge(from, message.map(|(r, a)| (r, a.as_slice())), arrived);
    let new_run = match verdict {
        Verdict::Accept { new_run } => new_run,
        Verdict::Malformed => {
            session.state.malformed += 1;
            return None;
        }
        Verdict::Foreign {
            second_robot: Some(words),
        }
        | Verdict::Jump(words) => {
            raise(&mut session, words);
            return None;
        }
        Verdict::Foreign { second_robot: None } | Verdict::Replay => return None,
    };
    let (robot, actual) = message?;
    note_robot(&mut session, robot, arrived, new_run);
    let ready = session.state.ready();
    let (positions, speeds) =
        next_reference(&mut session, ready, *actual, shared.kinematics.axes.dof());
    session.time.tick(ready, shared.period, arrived);
    session.feedback = Some(Feedback {
        seq: session.last_played,
        positions: *actual,
        // Holding (docs/protocol.md 3.4): the robot keeps the last reference, at rest, when
        // no target is playing or motion is not allowed.
        status: if ready && session.playing {
            ControllerStatus::Ok
        } else {
            ControllerStatus::Holding
        },
    });
    session.generation += 1;
    drop(session);
    shared.changed.notify_all();
    Some((positions, speeds))
}

/// Says that what the link hears cannot be trusted (a second robot, a feedback jump): on
/// stderr at once, and as an event for the job, unless one is already waiting.
fn raise(session: &mut Session, words: String) {
    tracing::error!("EGM: {words}");
    if !session
        .events
        .iter()
        .any(|(_, e)| matches!(e, LinkEvent::Untrusted(_)))
    {
        session
            .events
            .push_back((Instant::now(), LinkEvent::Untrusted(words)));
    }
}

/// Takes in the robot's states and starts a new session when motion becomes allowed, or
/// when the robot starts a new EGM run (`new_run`) while it is.
fn note_robot(session: &mut Session, robot: &EgmRobot, arrived: Instant, new_run: bool) {
    let was_ready = session.state.ready()
        && session
            .last_message
            .is_some_and(|t| arrived.duration_since(t) < LINK_SILENCE);
    let state = &mut session.state;
    state.messages += 1;
    state.robot = session.guard.robot();
    state.motors = robot.motors();
    state.mci = robot.mci();
    state.rapid = robot.rapid();
    state.utilization_rate = robot.utilization_rate;
    if let (Some(last), Some(now)) = (session.last_seqno, robot.seqno())
        && now.wrapping_sub(last) > 1
    {
        state.robot_gaps += 1;
    }
    session.last_seqno = robot.seqno();
    session.last_message = Some(arrived);
    if state.ready() && (!was_ready || new_run) {
        state.sessions += 1;
        session.id += 1;
        session.queue.clear();
        session.playing = false;
        session.hold = None;
    }
}

/// The position and speed to answer with: the next queued target while playing, else the
/// held position at rest.
fn next_reference(
    session: &mut Session,
    ready: bool,
    actual: AxisValues,
    axes: usize,
) -> (Vec<f64>, Vec<f64>) {
    let rest = vec![0.0; axes];
    if !ready {
        session.queue.clear();
        session.playing = false;
        session.hold = None;
        return (actual.as_slice().to_vec(), rest);
    }
    let id = session.id;
    session.queue.retain(|(from, _)| *from == id);
    let hold = *session.hold.get_or_insert(actual);
    if !session.playing
        && (session.queue.len() >= PLAYOUT_DEPTH || (session.flush && !session.queue.is_empty()))
    {
        session.playing = true;
    }
    if !session.playing {
        return (hold.as_slice().to_vec(), rest);
    }
    match session.queue.pop_front() {
        Some((_, target)) => {
            session.hold = Some(target.positions);
            session.last_played = target.seq;
            session.moving = target.velocities.as_slice().iter().any(|v| *v != 0.0);
            (
                target.positions.as_slice().to_vec(),
                target.velocities.as_slice().to_vec(),
            )
        }
        None => {
            if !session.flush && session.moving {
                session.state.underruns += 1;
            }
            session.moving = false;
            session.playing = false;
            (hold.as_slice().to_vec(), rest)
        }
    }
}
