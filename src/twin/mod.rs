//! The twin: a simulated controller for any rig, the far side of every link.
//!
//! Per axis it models what real servo loops do to a stream of targets: a transport delay
//! and a first-order lag of configurable bandwidth. It is a strict controller of
//! `docs/protocol.md` (version 3, or 2 when told to speak it): it drops targets until a bridge Hello binds it (and
//! again after link loss or a reset), and answers a target outside the limits, a step or
//! velocity faster than an axis allows, a velocity change or position second difference
//! above its acceleration, or a wrong axis count with a latched fault, no motion and one
//! Fault notice. Without targets for `watchdog_cycles` it decelerates within the limits
//! and holds. Given the cell's collision model, it measures clearances from the positions
//! it reaches and stops with a latched collision fault when a contact begins (`contact`).
//! Its I/O (a gripper, the cell's parts and the judge of them) is `gripper`'s; a twin that
//! speaks version 2 has none.
//! It owns the simulated arm state only; it must not know about trajectories,
//! jobs, logs or bytes (the session over a transport is `server`'s).

pub mod contact;
pub mod gripper;
pub mod serial_port;
pub mod server;
mod world;

pub use contact::{ContactReport, ContactWatch};
pub use gripper::{CellJudgement, PartJudgement, PartsBoard, PartsNow, TwinIo};
pub use world::{SharedWorld, TwinWorld, ViewOnly};

use crate::protocol::{
    AxisValues, Command, ControllerStatus, Fault, FaultReport, Feedback, Hello, JointTarget,
    MAX_AXES,
};
use crate::rig::{JointLimits, LIMIT_SLACK, Rig};
use std::collections::VecDeque;
use std::time::Duration;
use thiserror::Error;

/// Values cross the wire as whole micro-units: two roundings may add 1 µrad to a step or
/// 1 µrad/s to a velocity change (docs/protocol.md 6.6).
const WIRE_ROUNDING: f64 = 1e-6;
/// Three rounded positions in a second difference: up to 2 µrad (docs/protocol.md 6.6).
const WIRE_ROUNDING_SECOND_DIFFERENCE: f64 = 2e-6;

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TwinSettings {
    /// The controller's cycle.
    pub period: Duration,
    /// Servo bandwidth (Hz): first-order lag from setpoint to actual position.
    pub bandwidth_hz: f64,
    /// Transport delay from a target's arrival to its use, rounded to whole cycles.
    pub delay: Duration,
    /// Cycles without a target before the twin decelerates and holds.
    pub watchdog_cycles: u32,
    /// The protocol version it speaks: 3 (with I/O) or 2 (none), docs/protocol.md 6.10.
    pub protocol_version: u8,
}

impl Default for TwinSettings {
    fn default() -> Self {
        Self {
            period: Duration::from_millis(4),
            bandwidth_hz: 20.0,
            delay: Duration::from_millis(12),
            watchdog_cycles: 25,
            protocol_version: crate::protocol::PROTOCOL_VERSION_IO,
        }
    }
}

#[derive(Debug, Clone, PartialEq, Error)]
pub enum TwinError {
    #[error("rig {rig} has {dof} axes; the twin handles at most {max}")]
    TooManyAxes { rig: String, dof: usize, max: usize },
    #[error("initial position has {got} values, rig has {expected} axes")]
    InitialLength { expected: usize, got: usize },
    #[error("initial position: {0}")]
    InitialOutsideLimits(crate::rig::OutsideLimits),
    #[error("twin setting {name} = {value} is invalid: {reason}")]
    BadSetting {
        name: &'static str,
        value: f64,
        reason: &'static str,
    },
}

/// What the twin counted of the targets it did not take.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct TwinCounters {
    /// Dropped because their seq was not newer than the last accepted one.
    pub stale_targets: u64,
    /// Dropped because no bridge Hello had bound the twin (docs/protocol.md 6.1).
    pub unbound_targets: u64,
    /// Dropped because a fault was latched.
    pub faulted_targets: u64,
    /// Targets that were accepted.
    pub accepted_targets: u64,
}

pub struct Twin {
    limits: Vec<JointLimits>,
    names: Vec<String>,
    settings: TwinSettings,
    /// The position the servo loop tracks (after the transport delay).
    setpoint: AxisValues,
    /// How fast the setpoint moves: the last target's velocity, or the watchdog's ramp.
    setpoint_velocity: AxisValues,
    actual: AxisValues,
    /// The last accepted target's position and velocity: the next one is checked against
    /// them; and the position accepted before (for the second difference).
    last_accepted: AxisValues,
    last_velocity: AxisValues,
    before_last: AxisValues,
    /// Whether `before_last` is one cycle before `last_accepted` (or both are the hold).
    second_difference_known: bool,
    /// 0 after a bridge Hello until a target is accepted (docs/protocol.md 6.3).
    last_seq: u32,
    bound: bool,
    in_transit: VecDeque<AxisValues>,
    delay_cycles: usize,
    cycles_without_target: u32,
    accepted_this_cycle: bool,
    status: ControllerStatus,
    smoothing: f64,
    counters: TwinCounters,
    /// A fault that latched and has not been announced yet.
    notice: Option<FaultReport>,
    world: Option<Box<dyn TwinWorld>>,
    /// The cell's collision model watching the actual positions (none: no cell given).
    contacts: Option<ContactWatch>,
    /// The gripper and the cell's parts (protocol v3's I/O).
    io: TwinIo,
}

impl Twin {
    pub fn new(rig: &Rig, settings: TwinSettings, initial: &[f64]) -> Result<Self, TwinError> {
        if rig.dof() > MAX_AXES {
            return Err(TwinError::TooManyAxes {
                rig: rig.name.clone(),
                dof: rig.dof(),
                max: MAX_AXES,
            });
        }
        if initial.len() != rig.dof() {
            return Err(TwinError::InitialLength {
                expected: rig.dof(),
                got: initial.len(),
            });
        }
        rig.check_limits(initial)
            .map_err(|(_, outside)| TwinError::InitialOutsideLimits(outside))?;
        let dt = settings.period.as_secs_f64();
        check_setting("period_s", dt, !settings.period.is_zero())?;
        check_setting(
            "bandwidth_hz",
            settings.bandwidth_hz,
            settings.bandwidth_hz > 0.0,
        )?;
        let positions = AxisValues::from_slice(initial).expect("dof checked against MAX_AXES");
        let delay_cycles = (settings.delay.as_secs_f64() / dt).round() as usize;
        Ok(Self {
            limits: rig.joints.iter().map(|j| j.limits).collect(),
            names: rig.joint_names().map(String::from).collect(),
            settings,
            setpoint: positions,
            setpoint_velocity: AxisValues::zeros(rig.dof()),
            actual: positions,
            last_accepted: positions,
            last_velocity: AxisValues::zeros(rig.dof()),
            before_last: positions,
            second_difference_known: true,
            last_seq: 0,
            bound: false,
            in_transit: VecDeque::with_capacity(delay_cycles + 2),
            delay_cycles,
            cycles_without_target: 0,
            accepted_this_cycle: false,
            status: ControllerStatus::Holding,
            counters: TwinCounters::default(),
            notice: None,
            world: None,
            contacts: None,
            io: TwinIo::bare(dt),
            smoothing: 1.0 - (-std::f64::consts::TAU * settings.bandwidth_hz * dt).exp(),
        })
    }

    /// Puts the twin's body in a world that watches every cycle's actual positions.
    pub fn with_world(mut self, world: Box<dyn TwinWorld>) -> Self {
        self.world = Some(world);
        self
    }

    /// Measures the cell's clearances from every cycle's actual positions, and stops the
    /// arm with a latched collision fault when a contact begins (`contact`).
    pub fn with_contacts(mut self, watch: ContactWatch) -> Self {
        self.contacts = Some(watch);
        self
    }

    /// Gives the twin the gripper and the parts of its cell.
    pub fn with_io(mut self, io: TwinIo) -> Self {
        self.io = io;
        self
    }

    /// Whether it speaks protocol v3 (and so carries I/O).
    pub fn carries_io(&self) -> bool {
        self.settings.protocol_version >= crate::protocol::PROTOCOL_VERSION_IO
    }

    /// An I/O request from the bridge (docs/protocol.md 6.10): a SetOutput changes nothing
    /// while the twin is unbound or faulted. A twin that speaks v2 never gets one (its
    /// server drops the frames as another version's).
    pub fn handle_io(&mut self, message: &crate::protocol::IoMessage) {
        let may_change = self.bound && !matches!(self.status, ControllerStatus::Fault(_));
        self.io.request(message, may_change);
    }

    /// The next I/O answer due.
    pub fn take_io_answer(&mut self) -> Option<crate::protocol::IoState> {
        self.io.take_answer()
    }

    /// The judge's verdict on the cell's parts so far (none without parts).
    pub fn judgement(&self) -> Option<CellJudgement> {
        self.io.judgement()
    }

    /// Where the cell's parts are and their judgement, as the twin goes (for the live page
    /// and Foxglove); `None` for a cell without parts.
    pub fn parts_board(&self) -> Option<std::sync::Arc<PartsBoard>> {
        self.io.board()
    }

    /// The collision watch, when the twin has a cell.
    pub fn contacts(&self) -> Option<&ContactWatch> {
        self.contacts.as_ref()
    }

    /// What the collision watch measured since the last call, and a fresh start.
    pub fn take_contacts(&mut self) -> Option<ContactReport> {
        self.contacts.as_mut().map(ContactWatch::take_report)
    }

    /// Targets dropped because their seq was not newer than the last accepted one.
    pub fn stale_targets(&self) -> u64 {
        self.counters.stale_targets
    }

    pub fn settings(&self) -> &TwinSettings {
        &self.settings
    }

    pub fn counters(&self) -> TwinCounters {
        self.counters
    }

    /// The twin's own Hello (docs/protocol.md 3.1): its rig's limits, its cycle and
    /// watchdog. `answer` marks a Hello sent in answer to a bridge Hello.
    pub fn hello(&self, answer: bool) -> Hello {
        Hello {
            axis_names: self.names.clone(),
            lower: self.limits.iter().map(|l| l.lower).collect(),
            upper: self.limits.iter().map(|l| l.upper).collect(),
            max_speed: self.limits.iter().map(|l| l.max_speed).collect(),
            max_acceleration: self.limits.iter().map(|l| l.max_acceleration).collect(),
            cycle_us: crate::protocol::cycle_us(self.settings.period),
            watchdog_cycles: self.settings.watchdog_cycles,
            answer,
            version: self.settings.protocol_version,
        }
    }

    /// A bridge Hello arrived: the twin is bound, forgets its sequence tracking and holds
    /// (docs/protocol.md 6.1).
    pub fn bridge_hello(&mut self) {
        self.hold();
        self.bound = true;
        self.last_seq = 0;
    }

    /// The link was lost (or a session ended): hold, and drop targets until a Hello.
    pub fn link_lost(&mut self) {
        // Answers are owed to the session that asked (docs/protocol.md 6.10 rule 2).
        self.io.end_session();
        self.hold();
        self.bound = false;
    }

    pub fn is_bound(&self) -> bool {
        self.bound
    }

    /// The Fault notice of a fault that latched since the last call (sent once).
    pub fn take_fault_notice(&mut self) -> Option<FaultReport> {
        self.notice.take()
    }

    pub fn status(&self) -> ControllerStatus {
        self.status
    }

    pub fn actual(&self) -> &[f64] {
        self.actual.as_slice()
    }

    /// Takes one command from the bridge.
    pub fn handle(&mut self, command: &Command) {
        match command {
            Command::Target(target) => self.accept(target),
            Command::Stop => self.hold(),
            Command::EStop => self.estop(),
            Command::Reset => {
                self.reset();
            }
            Command::Heartbeat => {}
        }
    }

    fn estop(&mut self) {
        self.setpoint = self.actual;
        self.setpoint_velocity = AxisValues::zeros(self.actual.len());
        self.in_transit.clear();
        self.latch(Fault::EStop, "e-stop from the bridge");
    }

    /// Clears a latched fault: every fault of the twin's is caused by a command, so its
    /// cause is gone once the command is. The twin then holds where it stands, unbound,
    /// and must announce itself with an unprompted Hello (docs/protocol.md 6.7). True when
    /// a fault was cleared.
    pub fn reset(&mut self) -> bool {
        if !matches!(self.status, ControllerStatus::Fault(_)) {
            return false;
        }
        self.setpoint = self.actual;
        self.setpoint_velocity = AxisValues::zeros(self.actual.len());
        self.status = ControllerStatus::Holding;
        self.notice = None;
        self.link_lost();
        true
    }

    fn latch(&mut self, fault: Fault, text: &str) {
        self.status = ControllerStatus::Fault(fault);
        self.notice = Some(FaultReport {
            fault,
            text: text.to_string(),
        });
    }

    /// Discards queued targets and decelerates to rest from the setpoint's velocity
    /// (docs/protocol.md 6.5).
    fn hold(&mut self) {
        if !matches!(self.status, ControllerStatus::Fault(_)) {
            self.status = ControllerStatus::Holding;
        }
        self.in_transit.clear();
    }

    fn accept(&mut self, target: &JointTarget) {
        if matches!(self.status, ControllerStatus::Fault(_)) {
            self.counters.faulted_targets += 1;
            return;
        }
        if !self.bound {
            self.counters.unbound_targets += 1;
            return;
        }
        let first_after_hello = self.last_seq == 0 && self.status == ControllerStatus::Holding;
        let gap = target.seq.wrapping_sub(self.last_seq);
        // A repeated or older target (a duplicate on the wire) is dropped, not applied twice.
        if !first_after_hello && (gap == 0 || gap >= 1 << 31) {
            self.counters.stale_targets += 1;
            return;
        }
        let gap = if first_after_hello { 1 } else { gap };
        if let Some((fault, text)) = self.check(target, gap) {
            self.in_transit.clear();
            self.setpoint_velocity = AxisValues::zeros(self.actual.len());
            self.latch(fault, &text);
            return;
        }
        self.remember(target, gap);
    }

    fn remember(&mut self, target: &JointTarget, gap: u32) {
        let holding = self.status == ControllerStatus::Holding;
        self.before_last = if holding {
            self.setpoint
        } else {
            self.last_accepted
        };
        self.second_difference_known = gap == 1;
        self.last_accepted = target.positions;
        self.last_velocity = target.velocities;
        self.last_seq = target.seq;
        self.cycles_without_target = 0;
        self.accepted_this_cycle = true;
        self.counters.accepted_targets += 1;
        self.status = ControllerStatus::Ok;
        self.in_transit.push_back(target.positions);
        // Velocities are for feed-forward; the setpoint moves by the delayed positions.
        self.setpoint_velocity = target.velocities;
    }

    /// A reason to refuse `target` after a seq gap of `gap`, checked against limits and
    /// against the last accepted target (or the held position, at rest): the checks of
    /// docs/protocol.md 6.6, in its order.
    fn check(&self, target: &JointTarget, gap: u32) -> Option<(Fault, String)> {
        if target.positions.len() != self.limits.len()
            || target.velocities.len() != self.limits.len()
        {
            let fault = Fault::AxisCount {
                expected: self.limits.len() as u8,
                got: target.positions.len() as u8,
            };
            return Some((
                fault,
                format!("{} axes in a target", target.positions.len()),
            ));
        }
        let holding = self.status == ControllerStatus::Holding;
        let reference = References {
            position: if holding {
                self.setpoint
            } else {
                self.last_accepted
            },
            velocity: if holding {
                AxisValues::zeros(self.limits.len())
            } else {
                self.last_velocity
            },
            before: if holding {
                self.setpoint
            } else {
                self.before_last
            },
            second_difference: gap == 1 && (holding || self.second_difference_known),
        };
        let cycles = f64::from(gap.min(self.settings.watchdog_cycles.max(1)));
        (0..self.limits.len()).find_map(|axis| self.check_axis(target, axis, &reference, cycles))
    }

    fn check_axis(
        &self,
        target: &JointTarget,
        axis: usize,
        reference: &References,
        cycles: f64,
    ) -> Option<(Fault, String)> {
        let limits = &self.limits[axis];
        let dt = self.settings.period.as_secs_f64();
        let name = &self.names[axis];
        let index = axis as u8;
        let value = target.positions.as_slice()[axis];
        let velocity = target.velocities.as_slice()[axis];
        // On the wire integers (docs/protocol.md 6.6): a target planned exactly at a limit
        // passes whatever the float rounding of its decoding.
        let wire = |v: f64| (v * 1e6).round();
        if !value.is_finite()
            || wire(value) < wire(limits.lower)
            || wire(value) > wire(limits.upper)
        {
            let text = format!("{name} target {value:.6} outside its limits");
            return Some((Fault::OutsideLimits { axis: index }, text));
        }
        let step = (value - reference.position.as_slice()[axis]).abs();
        let max_step = limits.max_speed * dt * cycles * (1.0 + LIMIT_SLACK) + WIRE_ROUNDING;
        if !velocity.is_finite() || !limits.speed_ok(velocity) || step > max_step {
            let text = format!("{name} step {step:.6} or velocity {velocity:.6} over speed");
            return Some((Fault::OverSpeed { axis: index }, text));
        }
        let change = (velocity - reference.velocity.as_slice()[axis]).abs();
        let max_change =
            limits.max_acceleration * dt * cycles * (1.0 + LIMIT_SLACK) + WIRE_ROUNDING;
        let second =
            value - 2.0 * reference.position.as_slice()[axis] + reference.before.as_slice()[axis];
        let max_second = limits.max_acceleration * dt * dt * (1.0 + LIMIT_SLACK)
            + WIRE_ROUNDING_SECOND_DIFFERENCE;
        if change > max_change || (reference.second_difference && second.abs() > max_second) {
            let text = format!(
                "{name} velocity change {change:.6} or second difference {second:.7} over acceleration"
            );
            return Some((Fault::OverAcceleration { axis: index }, text));
        }
        None
    }

    /// Advances one cycle and reports.
    pub fn tick(&mut self) -> Feedback {
        if self.status == ControllerStatus::Ok {
            if std::mem::take(&mut self.accepted_this_cycle) {
                self.cycles_without_target = 0;
            } else {
                // The w-th cycle in a row without a target holds (docs/protocol.md 6.5).
                self.cycles_without_target += 1;
                if self.cycles_without_target >= self.settings.watchdog_cycles {
                    self.hold();
                }
            }
        }
        self.accepted_this_cycle = false;
        if self.in_transit.len() > self.delay_cycles {
            if let Some(next) = self.in_transit.pop_front() {
                self.setpoint = next;
            }
        } else if self.status == ControllerStatus::Holding {
            self.decelerate();
        }
        let smoothing = self.smoothing;
        for (actual, setpoint) in self
            .actual
            .as_mut_slice()
            .iter_mut()
            .zip(self.setpoint.as_slice())
        {
            *actual += smoothing * (setpoint - *actual);
        }
        self.watch_contacts();
        self.io.tick(self.actual.as_slice());
        if let Some(world) = self.world.as_mut() {
            world.observe(self.actual.as_slice());
        }
        Feedback {
            seq: self.last_seq,
            positions: self.actual,
            status: self.status,
        }
    }

    /// Measures this cycle's clearances; a contact that begins stops the arm where it is, as
    /// an e-stop does, with a latched collision fault (one Fault notice naming the bodies).
    fn watch_contacts(&mut self) {
        let Some(watch) = self.contacts.as_mut() else {
            return;
        };
        let Some(contact) = watch.observe(self.actual.as_slice()) else {
            return;
        };
        if matches!(self.status, ControllerStatus::Fault(_)) {
            return;
        }
        self.setpoint = self.actual;
        self.setpoint_velocity = AxisValues::zeros(self.actual.len());
        self.in_transit.clear();
        self.latch(Fault::Collision, &contact.text);
    }

    /// Brings the setpoint to rest from its last velocity at each axis' max deceleration,
    /// never past a limit.
    fn decelerate(&mut self) {
        let dt = self.settings.period.as_secs_f64();
        for ((position, velocity), limits) in self
            .setpoint
            .as_mut_slice()
            .iter_mut()
            .zip(self.setpoint_velocity.as_mut_slice())
            .zip(&self.limits)
        {
            let braking = limits.max_acceleration * dt;
            *velocity = if velocity.abs() <= braking {
                0.0
            } else {
                *velocity - braking.copysign(*velocity)
            };
            *position = (*position + *velocity * dt).clamp(limits.lower, limits.upper);
        }
    }
}

/// What a target is checked against (docs/protocol.md 6.6).
struct References {
    position: AxisValues,
    velocity: AxisValues,
    before: AxisValues,
    /// Whether the second difference applies (in-order target after an in-order one).
    second_difference: bool,
}

fn check_setting(name: &'static str, value: f64, ok: bool) -> Result<(), TwinError> {
    if value.is_finite() && ok {
        Ok(())
    } else {
        Err(TwinError::BadSetting {
            name,
            value,
            reason: "must be finite and positive",
        })
    }
}
