//! The twin: a simulated controller for any rig, the far side of every link.
//!
//! Per axis it models what real servo loops do to a stream of targets: a transport delay
//! and a first-order lag of configurable bandwidth. It polices its own inputs like a real
//! controller must: a target outside the limits, a step faster than an axis allows, or a
//! wrong axis count is answered with a latched fault and no motion. Without targets for
//! `watchdog_cycles` it decelerates within the limits and holds. It owns the simulated arm
//! state only; it must not know about trajectories, jobs or logs.

pub mod can_port;
pub mod serial_port;
pub mod server;
mod world;

pub use world::{SharedWorld, TwinWorld};

use crate::protocol::{
    AxisValues, Command, ControllerStatus, Fault, Feedback, JointTarget, MAX_AXES,
};
use crate::rig::LIMIT_SLACK as SPEED_SLACK;
use crate::rig::{JointLimits, Rig};
use std::collections::VecDeque;

/// Positions cross the wire as whole micro-radians: two roundings may add 1 µrad to a step.
const WIRE_ROUNDING: f64 = 1e-6;
use thiserror::Error;

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TwinSettings {
    /// The controller's cycle (s).
    pub period_s: f64,
    /// Servo bandwidth (Hz): first-order lag from setpoint to actual position.
    pub bandwidth_hz: f64,
    /// Transport delay from a target's arrival to its use (s), rounded to whole cycles.
    pub delay_s: f64,
    /// Cycles without a target before the twin decelerates and holds.
    pub watchdog_cycles: u32,
}

impl Default for TwinSettings {
    fn default() -> Self {
        Self {
            period_s: 0.004,
            bandwidth_hz: 20.0,
            delay_s: 0.012,
            watchdog_cycles: 25,
        }
    }
}

#[derive(Debug, Clone, PartialEq, Error)]
pub enum TwinError {
    #[error("rig {rig} has {dof} axes; the twin handles at most {max}")]
    TooManyAxes { rig: String, dof: usize, max: usize },
    #[error("initial position has {got} values, rig has {expected} axes")]
    InitialLength { expected: usize, got: usize },
    #[error("initial position of {joint} = {value} is outside its limits")]
    InitialOutsideLimits { joint: String, value: f64 },
    #[error("twin setting {name} = {value} is invalid: {reason}")]
    BadSetting {
        name: &'static str,
        value: f64,
        reason: &'static str,
    },
}

pub struct Twin {
    limits: Vec<JointLimits>,
    settings: TwinSettings,
    /// The position the servo loop tracks (after the transport delay).
    setpoint: AxisValues,
    /// How fast the setpoint moves: the last target's velocity, or the watchdog's ramp.
    setpoint_velocity: AxisValues,
    actual: AxisValues,
    /// The last accepted target's position: the next one is checked against it.
    last_accepted: AxisValues,
    last_seq: u32,
    in_transit: VecDeque<AxisValues>,
    delay_cycles: usize,
    cycles_without_target: u32,
    status: ControllerStatus,
    smoothing: f64,
    stale_targets: u64,
    world: Option<Box<dyn TwinWorld>>,
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
        if let Some((index, value)) = rig.first_limit_violation(initial) {
            return Err(TwinError::InitialOutsideLimits {
                joint: rig.joints[index].name.clone(),
                value,
            });
        }
        check_setting("period_s", settings.period_s, settings.period_s > 0.0)?;
        check_setting(
            "bandwidth_hz",
            settings.bandwidth_hz,
            settings.bandwidth_hz > 0.0,
        )?;
        check_setting("delay_s", settings.delay_s, settings.delay_s >= 0.0)?;
        let positions = AxisValues::from_slice(initial).expect("dof checked against MAX_AXES");
        let delay_cycles = (settings.delay_s / settings.period_s).round() as usize;
        Ok(Self {
            limits: rig.joints.iter().map(|j| j.limits).collect(),
            settings,
            setpoint: positions,
            setpoint_velocity: AxisValues::zeros(rig.dof()),
            actual: positions,
            last_accepted: positions,
            last_seq: 0,
            in_transit: VecDeque::with_capacity(delay_cycles + 2),
            delay_cycles,
            cycles_without_target: 0,
            status: ControllerStatus::Holding,
            stale_targets: 0,
            world: None,
            smoothing: 1.0
                - (-std::f64::consts::TAU * settings.bandwidth_hz * settings.period_s).exp(),
        })
    }

    /// Puts the twin's body in a world that watches every cycle's actual positions.
    pub fn with_world(mut self, world: Box<dyn TwinWorld>) -> Self {
        self.world = Some(world);
        self
    }

    /// Targets dropped because their seq was not newer than the last accepted one.
    pub fn stale_targets(&self) -> u64 {
        self.stale_targets
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
            Command::EStop => {
                self.setpoint = self.actual;
                self.setpoint_velocity = AxisValues::zeros(self.actual.len());
                self.in_transit.clear();
                self.status = ControllerStatus::Fault(Fault::EStop);
            }
            Command::Heartbeat => {}
        }
    }

    fn hold(&mut self) {
        if !matches!(self.status, ControllerStatus::Fault(_)) {
            self.status = ControllerStatus::Holding;
        }
        self.in_transit.clear();
    }

    fn accept(&mut self, target: &JointTarget) {
        if matches!(self.status, ControllerStatus::Fault(_)) {
            return;
        }
        // A repeated or older target (a duplicate on the wire) is dropped, not applied twice.
        if self.status == ControllerStatus::Ok && target.seq <= self.last_seq && self.last_seq != 0
        {
            self.stale_targets += 1;
            return;
        }
        if let Some(fault) = self.check(target) {
            self.status = ControllerStatus::Fault(fault);
            self.in_transit.clear();
            self.setpoint_velocity = AxisValues::zeros(self.actual.len());
            return;
        }
        self.last_accepted = target.positions;
        self.last_seq = target.seq;
        self.cycles_without_target = 0;
        self.status = ControllerStatus::Ok;
        self.in_transit.push_back(target.positions);
        // Velocities are for feed-forward; the setpoint moves by the delayed positions.
        self.setpoint_velocity = target.velocities;
    }

    /// A reason to refuse `target`, checked against limits and against the last accepted
    /// position (or the held position, after a watchdog hold).
    fn check(&self, target: &JointTarget) -> Option<Fault> {
        if target.positions.len() != self.limits.len()
            || target.velocities.len() != self.limits.len()
        {
            return Some(Fault::AxisCount {
                expected: self.limits.len() as u8,
                got: target.positions.len() as u8,
            });
        }
        let (reference, elapsed_cycles) = if self.status == ControllerStatus::Holding {
            (self.setpoint, 1)
        } else {
            // A target after a gap of d seqs may have travelled d cycles (docs/protocol.md 6.3).
            let gap = target
                .seq
                .wrapping_sub(self.last_seq)
                .clamp(1, self.settings.watchdog_cycles.max(1));
            (self.last_accepted, gap)
        };
        for (axis, limits) in self.limits.iter().enumerate() {
            let value = target.positions.as_slice()[axis];
            if !value.is_finite() || !limits.contains(value) {
                return Some(Fault::OutsideLimits { axis: axis as u8 });
            }
            let step = (value - reference.as_slice()[axis]).abs();
            let velocity = target.velocities.as_slice()[axis];
            let max_step = limits.max_speed
                * self.settings.period_s
                * f64::from(elapsed_cycles)
                * (1.0 + SPEED_SLACK)
                + WIRE_ROUNDING;
            if step > max_step
                || !velocity.is_finite()
                || velocity.abs() > limits.max_speed * (1.0 + SPEED_SLACK)
            {
                return Some(Fault::OverSpeed { axis: axis as u8 });
            }
        }
        None
    }

    /// Advances one cycle and reports.
    pub fn tick(&mut self) -> Feedback {
        if self.status == ControllerStatus::Ok {
            self.cycles_without_target += 1;
            if self.cycles_without_target > self.settings.watchdog_cycles {
                self.hold();
            }
        }
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
        if let Some(world) = self.world.as_mut() {
            world.observe(self.actual.as_slice());
        }
        Feedback {
            seq: self.last_seq,
            positions: self.actual,
            status: self.status,
        }
    }

    /// Brings the setpoint to rest from its last velocity at each axis' max deceleration,
    /// never past a limit.
    fn decelerate(&mut self) {
        let dt = self.settings.period_s;
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
