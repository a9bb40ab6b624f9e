//! Planning from waypoints: the settings and errors both planners share, the input checks,
//! and point-to-point joint moves (jerk-limited and time-synchronised by rsruckig).
//!
//! Owns turning joint waypoints into a validated [`Trajectory`]. Must not touch links,
//! controllers or the rig model, and never clamps a waypoint: input outside the limits is a
//! typed [`PlanError`], never a different motion. Cartesian lines are solved in
//! `ik/cartesian.rs` and timed in `path.rs`.

use super::budget::{OverBudget, SampleBudget};
use super::{Trajectory, TrajectoryError, validate};
use crate::rig::Rig;
use rsruckig::prelude::{
    DataArrayOrVec, DurationDiscretization, InputParameter, Ruckig, RuckigResult, Synchronization,
    ThrowErrorHandler,
};
use std::fmt;
use std::time::Duration;
use thiserror::Error;

/// Planned values within this of a limit are rounding from the profile maths and are
/// snapped onto it; anything farther out is left for [`validate`] to report as a bug.
const LIMIT_ROUNDING: f64 = 1e-9;

/// How a planner may use the rig: how finely to sample, and how much of each axis' speed and
/// acceleration to take.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlanSettings {
    /// Sample period: the streaming cycle.
    pub period: Duration,
    /// Fraction of each axis' max speed a plan may use. Below 1 so the streamer can scale
    /// time (pause, stop) without the scaled motion breaking the limit.
    pub speed_scale: f64,
    /// Fraction of each axis' max acceleration a plan may use.
    pub accel_scale: f64,
    /// Max jerk = (scaled) max acceleration x this, in 1/s: 10 builds up full acceleration
    /// in 0.1 s. Joint moves and a program's moves (`smooth.rs`); a standalone Cartesian
    /// move is acceleration-limited.
    pub jerk_per_accel_s: f64,
    /// Largest Cartesian step (m) between two IK samples of a linear move.
    pub cartesian_step_m: f64,
    /// Largest rotation (rad) between two IK samples of a linear move.
    pub cartesian_step_rad: f64,
    /// Largest joint change (rad, or m for prismatic axes) allowed between two IK samples
    /// of a linear move; more means the solver switched branch (or a singularity is in the
    /// way), which the arm cannot follow at a bounded speed.
    pub max_joint_jump: f64,
    /// How long the plan may last and how much memory its samples may take, checked
    /// before each piece is sampled (`[limits]`, docs/jobs.md).
    pub budget: SampleBudget,
    /// How a move that goes around the cell is searched for (`free.rs`; `[plan]`'s
    /// `free_*` keys, docs/jobs.md).
    pub free: super::free::FreePlanOptions,
}

impl Default for PlanSettings {
    fn default() -> Self {
        Self {
            period: Duration::from_millis(4),
            speed_scale: 0.9,
            accel_scale: 0.8,
            jerk_per_accel_s: 10.0,
            cartesian_step_m: 0.001,
            cartesian_step_rad: 0.5_f64.to_radians(),
            max_joint_jump: 5.0_f64.to_radians(),
            budget: SampleBudget::default(),
            free: super::free::FreePlanOptions::default(),
        }
    }
}

impl PlanSettings {
    /// These settings for the next piece of a job that has planned `done` already: what is
    /// left of the budget.
    pub fn after(&self, done: &Trajectory) -> PlanSettings {
        PlanSettings {
            budget: self.budget.after(done.len()),
            ..*self
        }
    }

    /// Every field must be positive and finite, the scales at most 1.
    pub fn check(&self) -> Result<(), PlanError> {
        let positive = [
            ("period_s", self.period.as_secs_f64()),
            ("jerk_per_accel_s", self.jerk_per_accel_s),
            ("cartesian_step_m", self.cartesian_step_m),
            ("cartesian_step_rad", self.cartesian_step_rad),
            ("max_joint_jump", self.max_joint_jump),
        ];
        check_positive(&positive)?;
        for (setting, value) in [
            ("speed_scale", self.speed_scale),
            ("accel_scale", self.accel_scale),
        ] {
            if !(value > 0.0 && value <= 1.0) {
                return Err(PlanError::InvalidSettings {
                    setting,
                    value,
                    reason: "must be in (0, 1]",
                });
            }
        }
        self.free.check()
    }
}

/// Why one joint value of a start or waypoint is refused.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum InvalidValue {
    NotFinite,
    /// Limits in SI units; `kind` says how a message shows them (degrees or metres).
    OutsideLimits {
        lower: f64,
        upper: f64,
        kind: crate::rig::JointKind,
    },
}

impl InvalidValue {
    /// The refused `value` (SI units) as a message shows it: in the unit the user wrote.
    pub fn shown(&self, value: f64) -> String {
        match self {
            InvalidValue::NotFinite => value.to_string(),
            InvalidValue::OutsideLimits { kind, .. } => {
                format!("{:.3} {}", kind.to_user(value), kind.unit())
            }
        }
    }
}

impl fmt::Display for InvalidValue {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            InvalidValue::NotFinite => write!(f, "is not finite"),
            InvalidValue::OutsideLimits { lower, upper, kind } => write!(
                f,
                "is outside its limits [{:.3}, {:.3}] {}",
                kind.to_user(*lower),
                kind.to_user(*upper),
                kind.unit()
            ),
        }
    }
}

#[derive(Debug, Clone, PartialEq, Error)]
pub enum PlanError {
    #[error("setting {setting} = {value} {reason}")]
    InvalidSettings {
        setting: &'static str,
        value: f64,
        reason: &'static str,
    },
    #[error(
        "rig joint {joint} has unusable limits: max speed {max_speed}, max acceleration {max_acceleration}"
    )]
    RigLimits {
        joint: String,
        max_speed: f64,
        max_acceleration: f64,
    },
    #[error("start has {got} joint values, rig {rig} has {expected} joints")]
    StartAxisCount {
        rig: String,
        expected: usize,
        got: usize,
    },
    #[error("start: {joint} = {} {reason}", reason.shown(*value))]
    InvalidStart {
        joint: String,
        value: f64,
        reason: InvalidValue,
    },
    #[error("waypoint {waypoint} has {got} joint values, rig {rig} has {expected} joints")]
    WaypointAxisCount {
        waypoint: usize,
        rig: String,
        expected: usize,
        got: usize,
    },
    #[error("waypoint {waypoint}: {joint} = {} {reason}", reason.shown(*value))]
    InvalidWaypoint {
        waypoint: usize,
        joint: String,
        value: f64,
        reason: InvalidValue,
    },
    #[error(
        "move to waypoint {waypoint}: {joint} still needs {ratio:.3} x its allowed {limit} after slowing down; the path bends too sharply (singularity?)"
    )]
    OverLimits {
        waypoint: usize,
        joint: String,
        ratio: f64,
        /// The limit broken, as a message names it: `speed or acceleration`, `jerk`.
        limit: &'static str,
    },
    #[error("move to waypoint {waypoint}: profile generator failed: {message}")]
    Profile { waypoint: usize, message: String },
    #[error("refused before planning: {0}")]
    OverBudget(#[from] OverBudget),
    #[error("planned trajectory is invalid (a planner bug): {0}")]
    Trajectory(#[from] TrajectoryError),
}

/// Per-axis speed, acceleration and jerk a plan may use: the rig's, scaled by the settings.
#[derive(Debug, Clone)]
pub(crate) struct AxisLimits {
    pub speed: Vec<f64>,
    pub acceleration: Vec<f64>,
    pub jerk: Vec<f64>,
}

impl AxisLimits {
    pub fn new(rig: &Rig, settings: &PlanSettings) -> Result<Self, PlanError> {
        let mut limits = Self {
            speed: Vec::with_capacity(rig.dof()),
            acceleration: Vec::with_capacity(rig.dof()),
            jerk: Vec::with_capacity(rig.dof()),
        };
        for joint in &rig.joints {
            let (speed, acceleration) = (joint.limits.max_speed, joint.limits.max_acceleration);
            // Loaders refuse these already; a hand-built rig could still carry them, and a
            // zero limit would mean an endless move.
            let usable = |v: f64| v.is_finite() && v > 0.0;
            if !usable(speed) || !usable(acceleration) {
                return Err(PlanError::RigLimits {
                    joint: joint.name.clone(),
                    max_speed: speed,
                    max_acceleration: acceleration,
                });
            }
            let acceleration = acceleration * settings.accel_scale;
            limits.speed.push(speed * settings.speed_scale);
            limits.acceleration.push(acceleration);
            limits.jerk.push(acceleration * settings.jerk_per_accel_s);
        }
        Ok(limits)
    }
}

/// The first bad value of `values` (as joint index and reason), if any.
fn first_invalid(rig: &Rig, values: &[f64]) -> Option<(usize, InvalidValue)> {
    rig.joints
        .iter()
        .zip(values)
        .enumerate()
        .find_map(|(index, (joint, &value))| {
            let limits = joint.limits;
            if !value.is_finite() {
                Some((index, InvalidValue::NotFinite))
            } else if !limits.contains(value) {
                Some((
                    index,
                    InvalidValue::OutsideLimits {
                        lower: limits.lower,
                        upper: limits.upper,
                        kind: joint.kind,
                    },
                ))
            } else {
                None
            }
        })
}

/// Each named setting positive and finite, else the first that is not, by its name.
pub(crate) fn check_positive(settings: &[(&'static str, f64)]) -> Result<(), PlanError> {
    for &(setting, value) in settings {
        if !(value.is_finite() && value > 0.0) {
            return Err(PlanError::InvalidSettings {
                setting,
                value,
                reason: "must be positive and finite",
            });
        }
    }
    Ok(())
}

pub(crate) fn check_start(rig: &Rig, start: &[f64]) -> Result<(), PlanError> {
    if start.len() != rig.dof() {
        return Err(PlanError::StartAxisCount {
            rig: rig.name.clone(),
            expected: rig.dof(),
            got: start.len(),
        });
    }
    match first_invalid(rig, start) {
        Some((index, reason)) => Err(PlanError::InvalidStart {
            joint: rig.joints[index].name.clone(),
            value: start[index],
            reason,
        }),
        None => Ok(()),
    }
}

pub(crate) fn check_waypoint(rig: &Rig, waypoint: usize, values: &[f64]) -> Result<(), PlanError> {
    if values.len() != rig.dof() {
        return Err(PlanError::WaypointAxisCount {
            waypoint,
            rig: rig.name.clone(),
            expected: rig.dof(),
            got: values.len(),
        });
    }
    match first_invalid(rig, values) {
        Some((index, reason)) => Err(PlanError::InvalidWaypoint {
            waypoint,
            joint: rig.joints[index].name.clone(),
            value: values[index],
            reason,
        }),
        None => Ok(()),
    }
}

/// Samples collected by a planner, row-major like [`Trajectory`].
#[derive(Debug, Clone)]
pub(crate) struct Samples {
    positions: Vec<f64>,
    velocities: Vec<f64>,
    /// Axes per sample (the start's), fixed for the plan.
    dof: usize,
    budget: SampleBudget,
    period: Duration,
}

impl Samples {
    /// At rest at `start`, to be sampled every `period` within `budget`.
    pub fn at_rest(start: &[f64], budget: SampleBudget, period: Duration) -> Self {
        Self {
            positions: start.to_vec(),
            velocities: vec![0.0; start.len()],
            dof: start.len(),
            budget,
            period,
        }
    }

    /// Refuses `more` samples that would break the budget, before they are sampled.
    pub fn ensure_room(&self, more: usize) -> Result<(), OverBudget> {
        let held = self.positions.len() / self.dof.max(1);
        self.budget
            .after(held)
            .check(more as u64, self.period, self.dof)
    }

    pub fn push(&mut self, positions: &[f64], velocities: &[f64]) {
        self.positions.extend_from_slice(positions);
        self.velocities.extend_from_slice(velocities);
    }

    /// The index of the last sample held: where a waypoint just sampled sits.
    pub fn last_index(&self) -> usize {
        (self.positions.len() / self.dof.max(1)).saturating_sub(1)
    }

    /// [`Samples::finish`] with each sample's velocity replaced by the central difference
    /// of its neighbours' positions (at rest at both ends). For paths with corners (a free
    /// move's polyline): the timing's velocities point along a piece and turn at once at
    /// its end, while the positions bend within the accelerations; the differences keep the
    /// velocities' changes within them too.
    pub fn finish_differenced(
        mut self,
        rig: &Rig,
        period: Duration,
    ) -> Result<Trajectory, PlanError> {
        let dof = self.dof.max(1);
        let count = self.positions.len() / dof;
        let two_periods = 2.0 * period.as_secs_f64();
        for k in 1..count.saturating_sub(1) {
            for axis in 0..dof {
                let (before, after) = (
                    self.positions[(k - 1) * dof + axis],
                    self.positions[(k + 1) * dof + axis],
                );
                self.velocities[k * dof + axis] = (after - before) / two_periods;
            }
        }
        self.finish(rig, period)
    }

    /// The trajectory, after the same check every streamed trajectory gets.
    pub fn finish(self, rig: &Rig, period: Duration) -> Result<Trajectory, PlanError> {
        let trajectory = Trajectory::new(
            rig.name.clone(),
            rig.joint_names().map(str::to_owned).collect(),
            period,
            self.positions,
            self.velocities,
        )?;
        validate(&trajectory, rig)?;
        Ok(trajectory)
    }
}

/// Snaps each of `positions` that overshoots a limit by rounding only back onto it.
pub(crate) fn snap_to_limits(rig: &Rig, positions: &mut [f64]) {
    for (value, joint) in positions.iter_mut().zip(&rig.joints) {
        let (lower, upper) = (joint.limits.lower, joint.limits.upper);
        if *value < lower && *value > lower - LIMIT_ROUNDING {
            *value = lower;
        } else if *value > upper && *value < upper + LIMIT_ROUNDING {
            *value = upper;
        }
    }
}

/// Point-to-point moves from `start` through each waypoint in turn, stopping at each:
/// every move is jerk-limited, time-synchronised (all axes start and arrive together) and
/// as fast as the scaled limits allow, sampled every `settings.period` with the profile's
/// velocities. Each move's duration is a whole number of periods, so every waypoint is a
/// sample, exactly.
///
/// Waypoints (and `start`) are checked before anything is planned: a wrong axis count, a
/// non-finite value or one outside the limits fails the whole plan, naming the waypoint,
/// joint and value.
pub fn plan_joint_moves(
    rig: &Rig,
    start: &[f64],
    waypoints: &[Vec<f64>],
    settings: &PlanSettings,
) -> Result<Trajectory, PlanError> {
    plan_joint_moves_marked(rig, start, waypoints, settings).map(|(trajectory, _)| trajectory)
}

/// [`plan_joint_moves`], with the sample each waypoint sits at (one per waypoint, in
/// order): what a refusal of the planned motion names as its source.
pub fn plan_joint_moves_marked(
    rig: &Rig,
    start: &[f64],
    waypoints: &[Vec<f64>],
    settings: &PlanSettings,
) -> Result<(Trajectory, Vec<usize>), PlanError> {
    settings.check()?;
    let limits = AxisLimits::new(rig, settings)?;
    check_start(rig, start)?;
    for (waypoint, values) in waypoints.iter().enumerate() {
        check_waypoint(rig, waypoint, values)?;
    }
    let mut samples = Samples::at_rest(start, settings.budget, settings.period);
    let mut from = start;
    let mut marks = Vec::with_capacity(waypoints.len());
    for (waypoint, to) in waypoints.iter().enumerate() {
        let mov = JointMove {
            rig,
            limits: &limits,
            period: settings.period,
            waypoint,
        };
        mov.sample(from, to, &mut samples)?;
        marks.push(samples.last_index());
        from = to;
    }
    Ok((samples.finish(rig, settings.period)?, marks))
}

/// One jerk-limited rest-to-rest move from `from` to `to` alone, as [`plan_joint_moves`]
/// plans each, its errors naming `to` as waypoint `waypoint`: what a move that may go
/// around the cell tries first (`free.rs`).
pub(crate) fn plan_joint_move(
    rig: &Rig,
    from: &[f64],
    to: &[f64],
    waypoint: usize,
    settings: &PlanSettings,
) -> Result<Trajectory, PlanError> {
    settings.check()?;
    let limits = AxisLimits::new(rig, settings)?;
    check_start(rig, from)?;
    check_waypoint(rig, waypoint, to)?;
    let mut samples = Samples::at_rest(from, settings.budget, settings.period);
    let mov = JointMove {
        rig,
        limits: &limits,
        period: settings.period,
        waypoint,
    };
    mov.sample(from, to, &mut samples)?;
    samples.finish(rig, settings.period)
}

/// One rest-to-rest move to waypoint `waypoint`.
struct JointMove<'a> {
    rig: &'a Rig,
    limits: &'a AxisLimits,
    period: Duration,
    waypoint: usize,
}

impl JointMove<'_> {
    fn profile_error(&self, message: String) -> PlanError {
        PlanError::Profile {
            waypoint: self.waypoint,
            message,
        }
    }

    fn input(&self, from: &[f64], to: &[f64]) -> InputParameter<0> {
        let heap = |values: &[f64]| DataArrayOrVec::Heap(values.to_vec());
        let dof = from.len();
        let mut input = InputParameter::<0>::new(Some(dof));
        input.synchronization = Synchronization::Time;
        // Whole periods: the last sample is then the waypoint itself, at rest.
        input.duration_discretization = DurationDiscretization::Discrete;
        input.current_position = heap(from);
        input.target_position = heap(to);
        input.max_velocity = heap(&self.limits.speed);
        input.max_acceleration = heap(&self.limits.acceleration);
        input.max_jerk = heap(&self.limits.jerk);
        let lower: Vec<f64> = self.rig.joints.iter().map(|j| j.limits.lower).collect();
        let upper: Vec<f64> = self.rig.joints.iter().map(|j| j.limits.upper).collect();
        input.min_position = Some(heap(&lower));
        input.max_position = Some(heap(&upper));
        input
    }

    /// Appends the samples after `from` up to and including `to`.
    fn sample(&self, from: &[f64], to: &[f64], samples: &mut Samples) -> Result<(), PlanError> {
        let dof = from.len();
        let dt = self.period.as_secs_f64();
        let input = self.input(from, to);
        let mut otg = Ruckig::<0, ThrowErrorHandler>::new(Some(dof), dt);
        let mut profile = rsruckig::prelude::Trajectory::<0>::new(Some(dof));
        match otg.calculate(&input, &mut profile) {
            Ok(RuckigResult::Working | RuckigResult::Finished) => {}
            Ok(other) => {
                let code = other as i32;
                return Err(self.profile_error(format!("the profile generator's result {code}")));
            }
            Err(e) => return Err(self.profile_error(e.to_string())),
        }
        let duration = profile.get_duration();
        if !duration.is_finite() {
            return Err(self.profile_error(format!("duration {duration} s")));
        }
        // Discrete durations are whole periods up to rounding.
        let periods = (duration / dt).round() as usize;
        samples.ensure_room(periods)?;
        let mut position = DataArrayOrVec::<f64, 0>::new(Some(dof), 0.0);
        let mut velocity = DataArrayOrVec::<f64, 0>::new(Some(dof), 0.0);
        for k in 1..periods {
            let mut section = None;
            profile.at_time(
                k as f64 * dt,
                &mut Some(&mut position),
                &mut Some(&mut velocity),
                &mut None,
                &mut None,
                &mut section,
            );
            snap_to_limits(self.rig, &mut position);
            samples.push(&position, &velocity);
        }
        if periods > 0 {
            samples.push(to, &vec![0.0; dof]);
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// 10,000 held samples of 6 axes and 1,000 more: 11,000 x 6 x 16 B = 1.007 MiB, counted
    /// by hand. The room a planner asks for counts samples and axes, not the values held.
    #[test]
    fn room_counts_the_samples_held_and_their_axes() {
        const HELD: usize = 10_000;
        let period = Duration::from_millis(4);
        let budget = |max_plan_mb| SampleBudget {
            max_plan_mb,
            ..SampleBudget::default()
        };
        let filled = |budget| {
            let mut samples = Samples::at_rest(&[0.0; 6], budget, period);
            for _ in 1..HELD {
                samples.push(&[0.0; 6], &[0.0; 6]);
            }
            samples
        };
        assert!(filled(budget(1.01)).ensure_room(1_000).is_ok());
        assert!(matches!(
            filled(budget(1.0)).ensure_room(1_000),
            Err(OverBudget::Memory {
                samples: 11_000,
                dof: 6,
                ..
            })
        ));
    }
}
