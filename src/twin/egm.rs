//! The EGM twin: plays an ABB robot controller running EGM in joint mode, for the bridge's
//! EGM link or any other EGM sensor (abb_libegm, abb-robot-client).
//!
//! Every cycle (4 ms) it sends an EgmRobot from an ephemeral UDP port to the sensor, and
//! moves by the EGM position law, speed = speed_ref + k (ref - pos), the correction bounded
//! by MaxSpeedDeviation and the motion by each axis' max speed and acceleration. It checks
//! every reference itself (inside the limits, step within max speed, second difference
//! within max acceleration, one reference per cycle) and ends the session with MCI_ERROR at
//! the first bad one, as a controller's supervision would. A rig with more axes than the
//! robot's six carries the others as external axes (`externalJoints`, [`EgmAxes`]), checked
//! the same way; MaxSpeedDeviation bounds the robot's joints' correction, an external
//! axis' correction is bounded by its own max speed. Without a reply for CommTimeout
//! the session ends in the HOLD stop mode (decelerate, stay); motors can go off and on.
//! The header seqno restarts at 0 with every EGM session, which abb_libegm reads as a
//! session's first message; feedBack.time is the host's clock, which goes on.
//! It owns the simulated robot only; it must not know about trajectories or jobs.

use crate::clock::{Clock, WallClock};
use crate::protocol::egm::{
    EgmAxes, EgmClock, EgmFeedBack, EgmHeader, EgmMciState, EgmMotorState, EgmPlanned,
    EgmRapidCtrlExecState, EgmRobot, EgmSensor, MciState, MessageType, MotorState, RapidState,
};
use crate::rig::{JointKind, JointLimits, Rig};
use prost::Message;
use std::net::{SocketAddr, UdpSocket};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};
use thiserror::Error;

/// References cross the wire in degrees: a conversion there and back may move a value by
/// a few ulps, far below any real violation.
const WIRE_TOLERANCE: f64 = 1e-9;
/// Convergence, as EGMActJoint's J1..J6 bounds would say: within 0.1 deg.
const CONVERGED_RAD: f64 = 0.1 * std::f64::consts::PI / 180.0;
/// Largest datagram read: an EgmSensor is a few hundred bytes.
const DATAGRAM: usize = 2048;
/// Round-trip histogram: 1 us buckets up to 10 ms.
const ROUND_TRIP_BUCKETS: usize = 10_000;

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EgmTwinSettings {
    /// The EGM cycle (EGMActJoint \SampleRate): 4 ms.
    pub period: Duration,
    /// EGMSetupUC \CommTimeout: no reply for this long ends the session.
    pub comm_timeout: Duration,
    /// k of the position law, 1/s.
    pub gain_per_s: f64,
    /// EGMActJoint MaxSpeedDeviation: the largest correction speed, rad/s.
    pub max_speed_deviation: f64,
    pub motors_on: bool,
}

impl Default for EgmTwinSettings {
    fn default() -> Self {
        Self {
            period: Duration::from_millis(4),
            comm_timeout: Duration::from_secs(1),
            // 20 Hz, the bandwidth the loopback twin uses for EGM-like filtering.
            gain_per_s: std::f64::consts::TAU * 20.0,
            max_speed_deviation: 25f64.to_radians(),
            motors_on: true,
        }
    }
}

#[derive(Debug, Clone, PartialEq, Error)]
pub enum EgmTwinError {
    #[error("initial position has {got} values, the rig has {expected} axes")]
    InitialLength { expected: usize, got: usize },
    #[error("the EGM axis layout has {got} axes, the rig has {expected}")]
    AxisLayout { expected: usize, got: usize },
    #[error("initial position of {joint} is outside its limits")]
    InitialOutsideLimits { joint: String },
    #[error("EGM twin setting {0} must be finite and positive")]
    BadSetting(&'static str),
    #[error("EGM twin socket")]
    Io(String),
}

/// What the twin saw, for summaries and tests.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct EgmTwinCounters {
    pub messages_sent: u64,
    pub replies: u64,
    /// Cycles (while a sensor answered) with exactly one, none, or several replies.
    pub cycles_one_reply: u64,
    pub cycles_no_reply: u64,
    pub cycles_several_replies: u64,
    /// Replies that were not EgmSensor corrections (undecodable or another type).
    pub ignored: u64,
    pub outside_limits: u64,
    pub over_speed: u64,
    pub over_acceleration: u64,
    pub axis_count: u64,
    pub comm_timeouts: u64,
    pub sessions: u64,
    /// Cycles whose message went out over half a period late (the host held the twin): each
    /// stretched.
    pub host_stalls: u64,
    /// Largest |reference - actual| seen while running, rad (m on a linear axis).
    pub tracking_max_rad: f64,
}

impl EgmTwinCounters {
    pub fn violations(&self) -> u64 {
        self.outside_limits + self.over_speed + self.over_acceleration + self.axis_count
    }
}

/// Operator actions, from another thread: motors, session start, shut down.
#[derive(Debug, Default)]
pub struct EgmTwinControl {
    motors_off: AtomicBool,
    motors_on: AtomicBool,
    start: AtomicBool,
    pub stop: AtomicBool,
}

impl EgmTwinControl {
    pub fn motors_off(&self) {
        self.motors_off.store(true, Ordering::SeqCst);
    }
    pub fn motors_on(&self) {
        self.motors_on.store(true, Ordering::SeqCst);
    }
    /// Runs EGM again after a session ended (RAPID calling EGMRunJoint again).
    pub fn start_session(&self) {
        self.start.store(true, Ordering::SeqCst);
    }
}

/// Why a reference was refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Refusal {
    AxisCount,
    OutsideLimits(usize),
    OverSpeed(usize),
    OverAcceleration(usize),
}

/// The simulated robot: positions, speeds, states and the references it follows.
pub struct EgmRobotModel {
    axes: EgmAxes,
    limits: Vec<JointLimits>,
    /// Per axis: its correction is bounded by MaxSpeedDeviation (the robot's revolute
    /// joints) rather than by its own max speed.
    deviation_bounded: Vec<bool>,
    settings: EgmTwinSettings,
    position: Vec<f64>,
    speed: Vec<f64>,
    /// The reference in force and its speed, rad and rad/s.
    reference: Option<(Vec<f64>, Vec<f64>)>,
    /// The two references before the newest, for the step and acceleration checks.
    history: [Option<Vec<f64>>; 2],
    motors: MotorState,
    mci: MciState,
    rapid: RapidState,
    utilization: f64,
    pub counters: EgmTwinCounters,
}

impl EgmRobotModel {
    /// The robot of `rig` at `initial` (rad, m), its axes laid out on the wire as `axes`.
    pub fn new(
        rig: &Rig,
        axes: EgmAxes,
        settings: EgmTwinSettings,
        initial: &[f64],
    ) -> Result<Self, EgmTwinError> {
        if axes.dof() != rig.dof() {
            return Err(EgmTwinError::AxisLayout {
                expected: rig.dof(),
                got: axes.dof(),
            });
        }
        if initial.len() != rig.dof() {
            return Err(EgmTwinError::InitialLength {
                expected: rig.dof(),
                got: initial.len(),
            });
        }
        if let Some((index, _)) = rig.first_limit_violation(initial) {
            return Err(EgmTwinError::InitialOutsideLimits {
                joint: rig.joints[index].name.clone(),
            });
        }
        for (name, value) in [
            ("period", settings.period.as_secs_f64()),
            ("comm_timeout", settings.comm_timeout.as_secs_f64()),
            ("gain_per_s", settings.gain_per_s),
            ("max_speed_deviation", settings.max_speed_deviation),
        ] {
            if !(value.is_finite() && value > 0.0) {
                return Err(EgmTwinError::BadSetting(name));
            }
        }
        let external = axes.external_indices();
        let deviation_bounded = rig
            .joints
            .iter()
            .enumerate()
            .map(|(i, j)| j.kind == JointKind::Revolute && !external.contains(&i))
            .collect();
        let mut model = Self {
            axes,
            deviation_bounded,
            limits: rig.joints.iter().map(|j| j.limits).collect(),
            settings,
            position: initial.to_vec(),
            speed: vec![0.0; initial.len()],
            reference: None,
            history: [None, None],
            motors: MotorState::Off,
            mci: MciState::Stopped,
            rapid: RapidState::Stopped,
            utilization: 0.0,
            counters: EgmTwinCounters::default(),
        };
        if settings.motors_on {
            model.set_motors(true);
        }
        Ok(model)
    }

    pub fn position(&self) -> &[f64] {
        &self.position
    }

    pub fn mci(&self) -> MciState {
        self.mci
    }

    pub fn motors(&self) -> MotorState {
        self.motors
    }

    /// Motors on starts the RAPID program and an EGM session; off stops both at once.
    pub fn set_motors(&mut self, on: bool) {
        if on {
            self.motors = MotorState::On;
            self.start_session();
        } else {
            self.motors = MotorState::Off;
            self.rapid = RapidState::Stopped;
            self.mci = MciState::Stopped;
            self.speed.iter_mut().for_each(|v| *v = 0.0);
            self.reference = None;
        }
    }

    /// EGMRunJoint again: a session from where the robot is.
    pub fn start_session(&mut self) {
        if self.motors != MotorState::On {
            return;
        }
        self.rapid = RapidState::Running;
        self.mci = MciState::Running;
        self.reference = None;
        self.history = [None, None];
        self.counters.sessions += 1;
    }

    /// The session ends in the HOLD stop mode: no reference, decelerate and stay.
    pub fn end_session(&mut self, state: MciState) {
        self.mci = state;
        self.reference = None;
    }

    /// The EgmRobot for this cycle.
    pub fn robot_message(&self, seqno: u32, tm_ms: u32, wall: Duration) -> EgmRobot {
        let planned = self
            .reference
            .as_ref()
            .map_or(self.position.as_slice(), |(p, _)| p.as_slice());
        let time = EgmClock {
            sec: wall.as_secs(),
            usec: u64::from(wall.subsec_micros()),
        };
        let converged = planned
            .iter()
            .zip(&self.position)
            .all(|(r, p)| (r - p).abs() <= CONVERGED_RAD);
        let (feedback, feedback_external) = self.axes.split(&self.position);
        let (planned, planned_external) = self.axes.split(planned);
        EgmRobot {
            header: Some(EgmHeader {
                seqno: Some(seqno),
                tm: Some(tm_ms),
                mtype: Some(MessageType::Data as i32),
            }),
            feed_back: Some(EgmFeedBack {
                joints: Some(feedback),
                external_joints: feedback_external,
                time: Some(time.clone()),
            }),
            planned: Some(EgmPlanned {
                joints: Some(planned),
                external_joints: planned_external,
                time: Some(time),
            }),
            motor_state: Some(EgmMotorState {
                state: self.motors as i32,
            }),
            mci_state: Some(EgmMciState {
                state: self.mci as i32,
            }),
            mci_convergence_met: Some(converged),
            rapid_exec_state: Some(EgmRapidCtrlExecState {
                state: self.rapid as i32,
            }),
            utilization_rate: Some(self.utilization),
        }
    }

    /// Takes one EgmSensor; a bad reference ends the session with MCI_ERROR. Returns the
    /// refusal as text for the event log.
    pub fn take_sensor(&mut self, sensor: &EgmSensor) -> Option<String> {
        let (Some(planned), MessageType::Correction) =
            (sensor.planned_joints(), sensor.message_type())
        else {
            self.counters.ignored += 1;
            return None;
        };
        if self.mci != MciState::Running {
            return None;
        }
        let Some(positions) = self.wire_positions(planned, sensor.planned_external()) else {
            self.count(Refusal::AxisCount);
            self.end_session(MciState::Error);
            return Some(describe(Refusal::AxisCount));
        };
        let speeds = sensor
            .speed_joints()
            .filter(|s| s.len() == planned.len())
            .and_then(|s| self.axes.join(s, sensor.speed_external()))
            .unwrap_or_else(|| vec![0.0; positions.len()]);
        match self.check(&positions, &speeds) {
            Some(refusal) => {
                self.count(refusal);
                self.end_session(MciState::Error);
                Some(describe(refusal))
            }
            None => {
                self.history = [self.history[1].take(), Some(positions.clone())];
                self.reference = Some((positions, speeds));
                None
            }
        }
    }

    /// A reference's positions (rad, m) from its joints and external joints: `None` unless
    /// it has exactly the robot's joints and external axes.
    fn wire_positions(&self, joints: &[f64], external: Option<&[f64]>) -> Option<Vec<f64>> {
        let external_count = external.map_or(0, <[f64]>::len);
        if joints.len() + external_count != self.limits.len()
            || external_count != self.axes.external_indices().len()
        {
            return None;
        }
        self.axes.join(joints, external)
    }

    fn count(&mut self, refusal: Refusal) {
        let counter = match refusal {
            Refusal::AxisCount => &mut self.counters.axis_count,
            Refusal::OutsideLimits(_) => &mut self.counters.outside_limits,
            Refusal::OverSpeed(_) => &mut self.counters.over_speed,
            Refusal::OverAcceleration(_) => &mut self.counters.over_acceleration,
        };
        *counter += 1;
    }

    /// A reference's own limits, its step from the last one (or from where the robot is,
    /// at a session's first) and its second difference: one reference per cycle.
    fn check(&self, positions: &[f64], speeds: &[f64]) -> Option<Refusal> {
        if positions.len() != self.limits.len() {
            return Some(Refusal::AxisCount);
        }
        let dt = self.settings.period.as_secs_f64();
        let last = self.history[1].as_deref().unwrap_or(&self.position);
        let before = self.history[0].as_deref().or(self.history[1].as_deref());
        for (axis, limits) in self.limits.iter().enumerate() {
            let p = positions[axis];
            if !p.is_finite()
                || p < limits.lower - WIRE_TOLERANCE
                || p > limits.upper + WIRE_TOLERANCE
            {
                return Some(Refusal::OutsideLimits(axis));
            }
            let step = (p - last[axis]).abs() - WIRE_TOLERANCE;
            let speed = speeds[axis].abs() - WIRE_TOLERANCE;
            if !speeds[axis].is_finite() || !limits.speed_ok(speed) || !limits.step_ok(step, dt) {
                return Some(Refusal::OverSpeed(axis));
            }
            if let Some(before) = before {
                let second = (p - 2.0 * last[axis] + before[axis]).abs() - 2.0 * WIRE_TOLERANCE;
                if !limits.second_difference_ok(second.max(0.0), dt) {
                    return Some(Refusal::OverAcceleration(axis));
                }
            }
        }
        None
    }

    /// One cycle of motion: the position law while running, a stop otherwise.
    pub fn step(&mut self) {
        if self.motors != MotorState::On {
            return;
        }
        let dt = self.settings.period.as_secs_f64();
        let mut utilization: f64 = 0.0;
        for axis in 0..self.limits.len() {
            let limits = self.limits[axis];
            let wanted = match &self.reference {
                Some((reference, speed_ref)) if self.mci == MciState::Running => {
                    let error = reference[axis] - self.position[axis];
                    self.counters.tracking_max_rad =
                        self.counters.tracking_max_rad.max(error.abs());
                    let deviation = if self.deviation_bounded[axis] {
                        self.settings.max_speed_deviation
                    } else {
                        limits.max_speed
                    };
                    let correction =
                        (self.settings.gain_per_s * error).clamp(-deviation, deviation);
                    utilization = utilization.max(correction.abs() / deviation);
                    speed_ref[axis] + correction
                }
                _ => 0.0,
            };
            let braking = limits.max_acceleration * dt;
            let speed = self.speed[axis];
            let next = wanted
                .clamp(speed - braking, speed + braking)
                .clamp(-limits.max_speed, limits.max_speed);
            let moved = self.position[axis] + next * dt;
            self.position[axis] = moved.clamp(limits.lower, limits.upper);
            self.speed[axis] = if moved == self.position[axis] {
                next
            } else {
                0.0
            };
        }
        self.utilization = 100.0 * utilization;
    }
}

fn describe(refusal: Refusal) -> String {
    match refusal {
        Refusal::AxisCount => "reference with the wrong number of joints".into(),
        Refusal::OutsideLimits(axis) => {
            format!("reference outside the limits of axis {}", axis + 1)
        }
        Refusal::OverSpeed(axis) => format!("reference over the max speed of axis {}", axis + 1),
        Refusal::OverAcceleration(axis) => {
            format!("reference over the max acceleration of axis {}", axis + 1)
        }
    }
}

/// A running EGM twin: its socket and round-trip measurements.
pub struct EgmTwin {
    model: EgmRobotModel,
    socket: UdpSocket,
    sensor: SocketAddr,
    round_trip: Vec<u64>,
}

impl EgmTwin {
    /// Binds an ephemeral port of `sensor`'s family; sends nothing until [`EgmTwin::run`].
    pub fn new(model: EgmRobotModel, sensor: SocketAddr) -> Result<Self, EgmTwinError> {
        let any: SocketAddr = if sensor.is_ipv4() {
            (std::net::Ipv4Addr::UNSPECIFIED, 0).into()
        } else {
            (std::net::Ipv6Addr::UNSPECIFIED, 0).into()
        };
        let socket = UdpSocket::bind(any).map_err(|e| EgmTwinError::Io(e.to_string()))?;
        Ok(Self {
            model,
            socket,
            sensor,
            round_trip: vec![0; ROUND_TRIP_BUCKETS],
        })
    }

    pub fn local_address(&self) -> Option<SocketAddr> {
        self.socket.local_addr().ok()
    }

    pub fn model(&self) -> &EgmRobotModel {
        &self.model
    }

    /// Sensor round trip (EgmRobot sent to its EgmSensor received): the `q` quantile, us.
    pub fn round_trip_quantile_us(&self, q: f64) -> Option<f64> {
        let total: u64 = self.round_trip.iter().sum();
        let rank = ((q.clamp(0.0, 1.0) * total as f64).ceil() as u64).max(1);
        let mut seen = 0;
        for (micros, count) in self.round_trip.iter().enumerate() {
            seen += count;
            if total > 0 && seen >= rank {
                return Some(micros as f64 + 1.0);
            }
        }
        None
    }

    /// Runs cycles until `control.stop`, logging each event.
    pub fn run(&mut self, control: &EgmTwinControl) {
        let clock = WallClock::new();
        let period = self.model.settings.period;
        let mut last_reply = Instant::now();
        let mut seqno: u32 = 0;
        // The sessions the last message went out in: a new one restarts the seqno at 0, the
        // first message of an EGM session as abb_libegm reads it (docs/egm.md).
        let mut session_of_seqno = 0;
        let mut deadline = clock.now();
        while !control.stop.load(Ordering::SeqCst) {
            self.operator(control, &mut last_reply);
            self.model.step();
            if self.model.mci == MciState::Running
                && last_reply.elapsed() >= self.model.settings.comm_timeout
            {
                self.model.end_session(MciState::Stopped);
                self.model.counters.comm_timeouts += 1;
                tracing::warn!("comm timeout: EGM session ended in HOLD");
            }
            seqno = if self.model.counters.sessions == session_of_seqno {
                seqno.wrapping_add(1)
            } else {
                session_of_seqno = self.model.counters.sessions;
                0
            };
            let wall = std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .unwrap_or_default();
            let tm = u32::try_from(deadline.as_millis() % (1 << 32)).unwrap_or(0);
            let message = self.model.robot_message(seqno, tm, wall).encode_to_vec();
            let sent = Instant::now();
            if self.socket.send_to(&message, self.sensor).is_ok() {
                self.model.counters.messages_sent += 1;
            }
            deadline += period;
            let now = clock.now();
            if deadline.saturating_sub(now) < period / 2 {
                // The host held this thread and the message went out late. A controller's
                // cycle is its own clock: it stretches instead of sending the missed ones in
                // a burst (which no robot does and which would starve any sensor's
                // play-out), and the sensor keeps at least half a cycle to answer, so that
                // the twin's own lateness is not counted as a missing reply.
                deadline = now + period;
                self.model.counters.host_stalls += 1;
            }
            let replies = self.collect(&clock, deadline, sent);
            if replies > 0 {
                last_reply = Instant::now();
            }
            let counters = &mut self.model.counters;
            match replies {
                0 => counters.cycles_no_reply += 1,
                1 => counters.cycles_one_reply += 1,
                _ => counters.cycles_several_replies += 1,
            }
        }
    }

    fn operator(&mut self, control: &EgmTwinControl, last_reply: &mut Instant) {
        if control.motors_off.swap(false, Ordering::SeqCst) {
            self.model.set_motors(false);
            tracing::info!("motors off");
        }
        if control.motors_on.swap(false, Ordering::SeqCst) {
            self.model.set_motors(true);
            *last_reply = Instant::now();
            tracing::info!("motors on: EGM session started");
        }
        if control.start.swap(false, Ordering::SeqCst) && self.model.mci != MciState::Running {
            self.model.start_session();
            *last_reply = Instant::now();
            tracing::info!("EGM session started");
        }
    }

    /// Reads replies until `deadline`; returns how many this cycle brought.
    fn collect(&mut self, clock: &WallClock, deadline: Duration, sent: Instant) -> u32 {
        let mut buffer = [0u8; DATAGRAM];
        let mut replies = 0;
        loop {
            let left = deadline.saturating_sub(clock.now());
            if left.is_zero() {
                return replies;
            }
            // ppoll, not a socket timeout: those round up to whole 4 ms scheduler ticks.
            if !super::server::wait_readable(&self.socket, left).unwrap_or(false) {
                continue;
            }
            let Ok((len, _)) = self.socket.recv_from(&mut buffer) else {
                continue;
            };
            let Ok(sensor) = EgmSensor::decode(&buffer[..len]) else {
                self.model.counters.ignored += 1;
                continue;
            };
            replies += 1;
            self.model.counters.replies += 1;
            if replies == 1 {
                let micros = sent.elapsed().as_micros() as usize;
                self.round_trip[micros.min(ROUND_TRIP_BUCKETS - 1)] += 1;
            }
            if let Some(refusal) = self.model.take_sensor(&sensor) {
                tracing::warn!("EGM error: {refusal}; session ended");
            }
        }
    }
}

/// Starts a twin on its own thread; the handle returns the twin when `control.stop` is set.
pub fn spawn_egm_twin(
    mut twin: EgmTwin,
    control: Arc<EgmTwinControl>,
) -> std::io::Result<std::thread::JoinHandle<EgmTwin>> {
    std::thread::Builder::new()
        .name("rigbridge-egm-twin".into())
        .spawn(move || {
            twin.run(&control);
            twin
        })
}
