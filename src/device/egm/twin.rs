//! The EGM twin: plays an ABB robot controller running EGM, in joint mode (EGMActJoint) or
//! pose mode (EGMActPose), for the bridge's EGM link or any other EGM sensor (abb_libegm,
//! abb-robot-client).
//!
//! Every cycle (4 ms) it sends an EgmRobot from an ephemeral UDP port to the sensor, with
//! every field abb_libegm's parser requires (docs/egm.md): the header (seqno from 0 in each
//! EGM session, `tm`, MSGTYPE_DATA), feedBack and planned each with joints, the tool's pose
//! (mm and a unit quaternion, robot base frame) and the robot time, and the motor, EGM and
//! RAPID states. The robot time is the twin's own: one cycle per message, never the host's
//! clock, so a late cycle does not make it jump.
//!
//! References follow ABB's path: the sensor's reference reaches motion control after the
//! configured delay, passes the \LpFilter low-pass, and the arm moves by
//! speed = speed_ref + PosCorrGain k (ref - pos), the correction bounded by
//! MaxSpeedDeviation, the motion by each axis' max speed and acceleration. A reference
//! outside an axis' limits, with the wrong axis count, or (pose mode) a pose the robot
//! cannot reach ends the session with MCI_ERROR and stops RAPID, as a controller's motion
//! error does. A step or a second difference over an axis' limits is counted, not refused:
//! a real controller filters and caps; a sensor late with its write repeats its last
//! reference (abb_libegm does) and the session goes on. In pose mode the twin solves the
//! pose itself with the IK it is given ([`PoseSolver`]), seeded where its last reference
//! was. A rig with more axes than the robot's six carries the others as external axes
//! (`externalJoints`, [`EgmAxes`]); MaxSpeedDeviation bounds the robot's joints' correction,
//! an external axis' correction is bounded by its own max speed. Without a reply for
//! CommTimeout the session ends in the HOLD stop mode (decelerate, stay) and EGMRunJoint
//! raises ERR_UDPUC_COMM, which stops RAPID; motors can go off and on.
//! It owns the simulated robot only; it must not know about trajectories or jobs.

use crate::clock::{Clock, WallClock};
use crate::device::egm::wire::{
    EgmAxes, EgmClock, EgmFeedBack, EgmHeader, EgmKinematics, EgmMciState, EgmMotorState,
    EgmPlanned, EgmPose, EgmRapidCtrlExecState, EgmRobot, EgmSensor, MciState, MessageType,
    MotorState, RapidState,
};
use crate::rig::{JointKind, JointLimits, Pose, Rig};
use prost::Message;
use std::collections::VecDeque;
use std::net::{SocketAddr, UdpSocket};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};
use thiserror::Error;

pub use crate::device::egm::wire::EgmMode;

/// References cross the wire in degrees: a conversion there and back may move a value by
/// a few ulps, far below any real violation.
const WIRE_TOLERANCE: f64 = 1e-9;
/// Convergence, as EGMActJoint's J1..J6 bounds would say: within 0.1 deg.
const CONVERGED_RAD: f64 = 0.1 * std::f64::consts::PI / 180.0;
/// Largest datagram read: an EgmSensor is a few hundred bytes.
const DATAGRAM: usize = 2048;
/// Round-trip histogram: 1 us buckets up to 10 ms.
const ROUND_TRIP_BUCKETS: usize = 10_000;
/// Microseconds a second, for EgmClock.
const US_PER_S: u64 = 1_000_000;

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
    /// EGMActJoint \LpFilter: the reference low-pass' bandwidth, Hz; 0: no filter.
    pub lp_filter_hz: f64,
    /// EGMRunJoint \PosCorrGain: 0 follows the speed reference only, 1 corrects position.
    pub pos_corr_gain: f64,
    /// `[twin] delay_ms`: from a reference's arrival to motion control taking it.
    pub delay: Duration,
    pub mode: EgmMode,
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
            // docs/egm.md's RAPID: \LpFilter:=20 \PosCorrGain:=1.
            lp_filter_hz: 20.0,
            pos_corr_gain: 1.0,
            // `[twin] delay_ms`'s default.
            delay: Duration::from_millis(12),
            mode: EgmMode::Joint,
            motors_on: true,
        }
    }
}

#[derive(Debug, Error)]
pub enum EgmTwinError {
    #[error("initial position has {got} values, the rig has {expected} axes")]
    InitialLength { expected: usize, got: usize },
    #[error("the EGM axis layout has {got} axes, the rig has {expected}")]
    AxisLayout { expected: usize, got: usize },
    #[error("initial position: {0}")]
    InitialOutsideLimits(crate::rig::OutsideLimits),
    #[error("EGM twin setting {name} is {value}: it must be finite and {rule}")]
    BadSetting {
        name: &'static str,
        value: f64,
        rule: &'static str,
    },
    #[error(
        "EGM pose mode needs the controller's IK and a rig without external axes ({external} here): the twin solves the robot's six joints only"
    )]
    PoseMode { external: usize },
    #[error("EGM twin socket: {0}")]
    Io(#[from] std::io::Error),
}

/// Joint positions for a tool pose, as the controller's own kinematics find them: the
/// solution nearest `seed` (the reference before), every axis within its limits.
pub trait PoseSolver: Send {
    fn solve_pose(
        &self,
        pose: &Pose,
        seed: &[f64],
    ) -> Result<Vec<f64>, Box<dyn std::error::Error + Send + Sync>>;
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
    /// References refused (the session ended with MCI_ERROR): outside an axis' limits, the
    /// wrong axis count, a pose the robot cannot reach.
    pub outside_limits: u64,
    pub axis_count: u64,
    pub unreachable: u64,
    /// References whose step from the one before is over an axis' max speed, or whose second
    /// difference is over its max acceleration: counted, not refused (filtered and capped).
    pub over_speed: u64,
    pub over_acceleration: u64,
    /// References equal to the one before while the one before moved (a sensor repeating
    /// its last reply): counted, followed.
    pub repeated: u64,
    pub comm_timeouts: u64,
    pub sessions: u64,
    /// Cycles whose message went out over half a period late (the host held the twin): each
    /// stretched.
    pub host_stalls: u64,
    /// Largest |reference in force - actual| seen while running, rad (m on a linear axis).
    pub tracking_max_rad: f64,
}

impl EgmTwinCounters {
    /// References refused, and those over a speed or an acceleration (counted only).
    pub fn violations(&self) -> u64 {
        self.outside_limits
            + self.over_speed
            + self.over_acceleration
            + self.axis_count
            + self.unreachable
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
#[derive(Debug, Clone, PartialEq)]
enum Refusal {
    AxisCount,
    OutsideLimits(usize),
    Unreachable(String),
}

/// A reference: positions (rad, m) and speeds (per s).
type Reference = (Vec<f64>, Vec<f64>);

/// The simulated robot: positions, speeds, states and the references it follows.
pub struct EgmRobotModel {
    kinematics: EgmKinematics,
    limits: Vec<JointLimits>,
    /// Per axis: its correction is bounded by MaxSpeedDeviation (the robot's revolute
    /// joints) rather than by its own max speed.
    deviation_bounded: Vec<bool>,
    settings: EgmTwinSettings,
    solver: Option<Box<dyn PoseSolver>>,
    position: Vec<f64>,
    speed: Vec<f64>,
    /// References received, with the cycle motion control takes each (the delay).
    pending: VecDeque<(u64, Reference)>,
    /// The reference motion control took last, and its \LpFilter output.
    reference: Option<Reference>,
    filtered: Option<Reference>,
    /// The two references received before the newest, for the step and acceleration counts
    /// and pose mode's speed.
    history: [Option<Vec<f64>>; 2],
    motors: MotorState,
    mci: MciState,
    rapid: RapidState,
    utilization: f64,
    /// The robot's cycles since it started: its clock.
    cycle: u64,
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
        rig.check_limits(initial)
            .map_err(|(_, outside)| EgmTwinError::InitialOutsideLimits(outside))?;
        check_settings(&settings)?;
        let external = axes.external_indices();
        if settings.mode == EgmMode::Pose && !external.is_empty() {
            return Err(EgmTwinError::PoseMode {
                external: external.len(),
            });
        }
        let deviation_bounded = rig
            .joints
            .iter()
            .enumerate()
            .map(|(i, j)| j.kind == JointKind::Revolute && !external.contains(&i))
            .collect();
        let mut model = Self {
            kinematics: EgmKinematics {
                rig: rig.clone(),
                axes,
            },
            deviation_bounded,
            limits: rig.joints.iter().map(|j| j.limits).collect(),
            settings,
            solver: None,
            position: initial.to_vec(),
            speed: vec![0.0; initial.len()],
            pending: VecDeque::new(),
            reference: None,
            filtered: None,
            history: [None, None],
            motors: MotorState::Off,
            mci: MciState::Stopped,
            rapid: RapidState::Stopped,
            utilization: 0.0,
            cycle: 0,
            counters: EgmTwinCounters::default(),
        };
        if settings.motors_on {
            model.set_motors(true);
        }
        Ok(model)
    }

    /// Pose mode's IK: the controller's own kinematics.
    pub fn with_pose_solver(mut self, solver: Box<dyn PoseSolver>) -> Self {
        self.solver = Some(solver);
        self
    }

    pub fn position(&self) -> &[f64] {
        &self.position
    }

    pub fn mci(&self) -> MciState {
        self.mci
    }

    pub fn rapid(&self) -> RapidState {
        self.rapid
    }

    pub fn motors(&self) -> MotorState {
        self.motors
    }

    /// The robot's clock: one period per cycle since it started.
    pub fn robot_time(&self) -> Duration {
        self.settings.period * u32::try_from(self.cycle).unwrap_or(u32::MAX)
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
            self.clear_references();
        }
    }

    /// EGMRunJoint (or EGMRunPose) again: RAPID runs, a session from where the robot is.
    pub fn start_session(&mut self) {
        if self.motors != MotorState::On {
            return;
        }
        self.rapid = RapidState::Running;
        self.mci = MciState::Running;
        self.clear_references();
        self.counters.sessions += 1;
    }

    /// The session ends in the HOLD stop mode: no reference, decelerate and stay. `rapid`:
    /// the RAPID state after it (stopped by an error EGMRunJoint raised, or running on).
    pub fn end_session(&mut self, state: MciState, rapid: RapidState) {
        self.mci = state;
        self.rapid = rapid;
        self.clear_references();
    }

    fn clear_references(&mut self) {
        self.pending.clear();
        self.reference = None;
        self.filtered = None;
        self.history = [None, None];
    }

    /// The EgmRobot for this cycle; `epoch` is the controller's calendar time when it
    /// started (EgmClock counts from 1970), to which its own cycles are added.
    pub fn robot_message(&self, seqno: u32, epoch: Duration) -> EgmRobot {
        let planned = self
            .reference
            .as_ref()
            .map_or(self.position.as_slice(), |(p, _)| p.as_slice());
        let now = epoch + self.robot_time();
        let time = EgmClock {
            sec: now.as_secs(),
            usec: u64::from(now.subsec_micros()),
        };
        let converged = planned
            .iter()
            .zip(&self.position)
            .all(|(r, p)| (r - p).abs() <= CONVERGED_RAD);
        let axes = &self.kinematics.axes;
        let (feedback, feedback_external) = axes.split(&self.position);
        let (planned_joints, planned_external) = axes.split(planned);
        let tm = u32::try_from(self.robot_time().as_millis() % (1 << 32)).unwrap_or(0);
        EgmRobot {
            header: Some(EgmHeader {
                seqno: Some(seqno),
                tm: Some(tm),
                mtype: Some(MessageType::Data as i32),
            }),
            feed_back: Some(EgmFeedBack {
                joints: Some(feedback),
                cartesian: Some(EgmPose::from_pose(&self.kinematics.pose(&self.position))),
                external_joints: feedback_external,
                time: Some(time.clone()),
            }),
            planned: Some(EgmPlanned {
                joints: Some(planned_joints),
                cartesian: Some(EgmPose::from_pose(&self.kinematics.pose(planned))),
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

    /// Takes one EgmSensor; a reference the controller refuses ends the session with
    /// MCI_ERROR and stops RAPID. Returns the refusal as text for the event log.
    pub fn take_sensor(&mut self, sensor: &EgmSensor) -> Option<String> {
        if sensor.message_type() != MessageType::Correction {
            self.counters.ignored += 1;
            return None;
        }
        let reference = match self.settings.mode {
            EgmMode::Joint => sensor.planned_joints().map(|planned| {
                let positions = self
                    .wire_positions(planned, sensor.planned_external())
                    .ok_or(Refusal::AxisCount)?;
                let speeds = sensor
                    .speed_joints()
                    .filter(|s| s.len() == planned.len())
                    .and_then(|s| self.kinematics.axes.join(s, sensor.speed_external()))
                    .unwrap_or_else(|| vec![0.0; positions.len()]);
                Ok((positions, speeds))
            }),
            EgmMode::Pose => sensor.planned_pose().map(|pose| self.solve(&pose)),
        };
        let Some(reference) = reference else {
            self.counters.ignored += 1;
            return None;
        };
        if self.mci != MciState::Running {
            return None;
        }
        match reference.and_then(|r| self.check(&r.0).map(|()| r)) {
            Err(refusal) => {
                self.count(&refusal);
                self.end_session(MciState::Error, RapidState::Stopped);
                Some(describe(&refusal))
            }
            Ok((positions, speeds)) => {
                self.observe(&positions);
                self.history = [self.history[1].take(), Some(positions.clone())];
                let due = self.cycle + self.delay_cycles();
                self.pending.push_back((due, (positions, speeds)));
                None
            }
        }
    }

    /// Pose mode: the joints for `pose`, nearest the last reference (or where the arm is),
    /// and their speed from that reference over one cycle (the twin does not read
    /// speedRef.cartesians: the step between solutions is the same speed).
    fn solve(&self, pose: &Pose) -> Result<Reference, Refusal> {
        let seed = self.history[1].as_deref().unwrap_or(&self.position);
        let solver = self
            .solver
            .as_ref()
            .ok_or_else(|| Refusal::Unreachable("the twin was given no IK".into()))?;
        let pose = pose
            .validated()
            .map_err(|e| Refusal::Unreachable(e.to_string()))?;
        let positions = solver
            .solve_pose(&pose, seed)
            .map_err(|e| Refusal::Unreachable(format!("{pose}: {e}")))?;
        let dt = self.settings.period.as_secs_f64();
        let speeds = match &self.history[1] {
            Some(last) => positions
                .iter()
                .zip(last)
                .map(|(p, l)| (p - l) / dt)
                .collect(),
            None => vec![0.0; positions.len()],
        };
        Ok((positions, speeds))
    }

    /// Cycles from a reference's arrival to motion control taking it.
    fn delay_cycles(&self) -> u64 {
        (self.settings.delay.as_secs_f64() / self.settings.period.as_secs_f64()).round() as u64
    }

    /// A reference's positions (rad, m) from its joints and external joints: `None` unless
    /// it has exactly the robot's joints and external axes.
    fn wire_positions(&self, joints: &[f64], external: Option<&[f64]>) -> Option<Vec<f64>> {
        let external_count = external.map_or(0, <[f64]>::len);
        let axes = &self.kinematics.axes;
        if joints.len() + external_count != self.limits.len()
            || external_count != axes.external_indices().len()
        {
            return None;
        }
        axes.join(joints, external)
    }

    fn count(&mut self, refusal: &Refusal) {
        let counter = match refusal {
            Refusal::AxisCount => &mut self.counters.axis_count,
            Refusal::OutsideLimits(_) => &mut self.counters.outside_limits,
            Refusal::Unreachable(_) => &mut self.counters.unreachable,
        };
        *counter += 1;
    }

    /// What a controller refuses: a position outside an axis' limits.
    fn check(&self, positions: &[f64]) -> Result<(), Refusal> {
        if positions.len() != self.limits.len() {
            return Err(Refusal::AxisCount);
        }
        for (axis, (p, limits)) in positions.iter().zip(&self.limits).enumerate() {
            if !p.is_finite()
                || *p < limits.lower - WIRE_TOLERANCE
                || *p > limits.upper + WIRE_TOLERANCE
            {
                return Err(Refusal::OutsideLimits(axis));
            }
        }
        Ok(())
    }

    /// Counts a reference's step over an axis' max speed, its second difference over its max
    /// acceleration and a repeat of a moving reference: what the sensor sent, not refused.
    fn observe(&mut self, positions: &[f64]) {
        let dt = self.settings.period.as_secs_f64();
        // A session's first reference steps from where the arm is.
        let last = self.history[1].as_deref().unwrap_or(&self.position);
        let before = self.history[1].as_deref().and(self.history[0].as_deref());
        let mut over_speed = false;
        let mut over_acceleration = false;
        for (axis, limits) in self.limits.iter().enumerate() {
            let step = (positions[axis] - last[axis]).abs() - WIRE_TOLERANCE;
            over_speed |= !limits.step_ok(step.max(0.0), dt);
            if let Some(before) = before {
                let second = (positions[axis] - 2.0 * last[axis] + before[axis]).abs()
                    - 2.0 * WIRE_TOLERANCE;
                over_acceleration |= !limits.second_difference_ok(second.max(0.0), dt);
            }
        }
        let repeated = positions == last && before.is_some_and(|b| b != last);
        self.counters.over_speed += u64::from(over_speed);
        self.counters.over_acceleration += u64::from(over_acceleration);
        self.counters.repeated += u64::from(repeated);
    }

    /// Motion control takes the references due, and low-passes them (\LpFilter).
    fn take_due(&mut self) {
        while self
            .pending
            .front()
            .is_some_and(|(due, _)| *due <= self.cycle)
        {
            self.reference = self.pending.pop_front().map(|(_, r)| r);
        }
        let Some((target, target_speed)) = &self.reference else {
            return;
        };
        let dt = self.settings.period.as_secs_f64();
        let alpha = if self.settings.lp_filter_hz > 0.0 {
            1.0 - (-std::f64::consts::TAU * self.settings.lp_filter_hz * dt).exp()
        } else {
            1.0
        };
        // The filter starts where the arm is, at rest: the session's ramp in.
        let (filtered, filtered_speed) = self
            .filtered
            .get_or_insert_with(|| (self.position.clone(), vec![0.0; self.position.len()]));
        for axis in 0..target.len() {
            filtered[axis] += alpha * (target[axis] - filtered[axis]);
            filtered_speed[axis] += alpha * (target_speed[axis] - filtered_speed[axis]);
        }
    }

    /// One cycle of motion: the position law while running, a stop otherwise; the robot's
    /// clock advances a cycle.
    pub fn step(&mut self) {
        self.cycle += 1;
        if self.motors != MotorState::On {
            return;
        }
        if self.mci == MciState::Running {
            self.take_due();
        }
        let dt = self.settings.period.as_secs_f64();
        let mut utilization: f64 = 0.0;
        for axis in 0..self.limits.len() {
            let limits = self.limits[axis];
            let wanted = match (&self.filtered, &self.reference) {
                (Some((filtered, speed_ref)), Some((reference, _)))
                    if self.mci == MciState::Running =>
                {
                    let error = filtered[axis] - self.position[axis];
                    let behind = reference[axis] - self.position[axis];
                    self.counters.tracking_max_rad =
                        self.counters.tracking_max_rad.max(behind.abs());
                    let deviation = if self.deviation_bounded[axis] {
                        self.settings.max_speed_deviation
                    } else {
                        limits.max_speed
                    };
                    let correction =
                        (self.settings.pos_corr_gain * self.settings.gain_per_s * error)
                            .clamp(-deviation, deviation);
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

/// Every setting finite, the times and gains positive, the filter and PosCorrGain in range.
fn check_settings(settings: &EgmTwinSettings) -> Result<(), EgmTwinError> {
    let positive = [
        ("period", settings.period.as_secs_f64()),
        ("comm_timeout", settings.comm_timeout.as_secs_f64()),
        ("gain_per_s", settings.gain_per_s),
        ("max_speed_deviation", settings.max_speed_deviation),
    ];
    for (name, value) in positive {
        if !(value.is_finite() && value > 0.0) {
            return Err(EgmTwinError::BadSetting {
                name,
                value,
                rule: "positive",
            });
        }
    }
    let ranges = [
        (
            "lp_filter_hz",
            settings.lp_filter_hz,
            0.0,
            f64::MAX,
            "0 or more",
        ),
        (
            "pos_corr_gain",
            settings.pos_corr_gain,
            0.0,
            1.0,
            "from 0 to 1",
        ),
        (
            "delay",
            settings.delay.as_secs_f64(),
            0.0,
            1.0,
            "from 0 to 1 s",
        ),
    ];
    for (name, value, low, high, rule) in ranges {
        if !(value.is_finite() && (low..=high).contains(&value)) {
            return Err(EgmTwinError::BadSetting { name, value, rule });
        }
    }
    Ok(())
}

/// The refusal as the controller's event log would put it.
fn describe(refusal: &Refusal) -> String {
    match refusal {
        Refusal::AxisCount => "reference with the wrong number of joints".into(),
        Refusal::OutsideLimits(axis) => {
            format!("joint {} reference outside its working range", axis + 1)
        }
        Refusal::Unreachable(why) => format!("pose reference out of reach: {why}"),
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
        let socket = UdpSocket::bind(any)?;
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
        // The controller's calendar time when it started, read once: its EgmClock then
        // advances by its own cycles (the host's clock may step, and stretched cycles would
        // make the robot time jump).
        let epoch = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap_or_default();
        let epoch = Duration::from_micros(
            u64::try_from(epoch.as_micros()).unwrap_or(0) / US_PER_S * US_PER_S,
        );
        let mut last_reply = clock.now();
        let mut seqno: u32 = 0;
        // The sessions the last message went out in: a new one restarts the seqno at 0, the
        // first message of an EGM session as abb_libegm reads it (docs/egm.md).
        let mut session_of_seqno = 0;
        let mut deadline = clock.now();
        while !control.stop.load(Ordering::SeqCst) {
            self.operator(control, &mut last_reply, &clock);
            self.model.step();
            if self.model.mci == MciState::Running
                && clock.now().saturating_sub(last_reply) >= self.model.settings.comm_timeout
            {
                // EGMRunJoint raises ERR_UDPUC_COMM; unhandled, it stops RAPID.
                self.model
                    .end_session(MciState::Stopped, RapidState::Stopped);
                self.model.counters.comm_timeouts += 1;
                tracing::warn!(
                    "comm timeout: EGM session ended in HOLD, ERR_UDPUC_COMM stopped RAPID"
                );
            }
            seqno = if self.model.counters.sessions == session_of_seqno {
                seqno.wrapping_add(1)
            } else {
                session_of_seqno = self.model.counters.sessions;
                0
            };
            let message = self.model.robot_message(seqno, epoch).encode_to_vec();
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
                last_reply = clock.now();
            }
            let counters = &mut self.model.counters;
            match replies {
                0 => counters.cycles_no_reply += 1,
                1 => counters.cycles_one_reply += 1,
                _ => counters.cycles_several_replies += 1,
            }
        }
    }

    fn operator(&mut self, control: &EgmTwinControl, last_reply: &mut Duration, clock: &WallClock) {
        if control.motors_off.swap(false, Ordering::SeqCst) {
            self.model.set_motors(false);
            tracing::info!("motors off");
        }
        if control.motors_on.swap(false, Ordering::SeqCst) {
            self.model.set_motors(true);
            *last_reply = clock.now();
            tracing::info!("motors on: EGM session started");
        }
        if control.start.swap(false, Ordering::SeqCst) && self.model.mci != MciState::Running {
            self.model.start_session();
            *last_reply = clock.now();
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
            if !crate::twin::server::wait_readable(&self.socket, left).unwrap_or(false) {
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
