//! The `Trajectory` every stage hands down (joint samples at a fixed period, positions and
//! velocities per axis, generic over the rig) and `validate`, the check every trajectory
//! passes after it is planned, before it is streamed and before it is replayed.
//!
//! A leaf beside the chain, as `protocol` is beside the link: the planners above
//! (`trajectory`, `ik`, `job`, `task`) build it and the streamer below runs it, so it
//! lives under both (`docs/architecture.md`, "Layers"). Owns the type, its errors and the
//! validator, and the I/O points a program puts on it (where the stream stops at rest
//! until an output is set or an input read); must not plan, stream or import anything but
//! `rig`.

use crate::rig::{JointKind, Rig};
use std::time::Duration;
use thiserror::Error;

/// Relative slack on speed checks, for rounding only: the rig's [`crate::rig::LIMIT_SLACK`].
pub const SPEED_SLACK: f64 = crate::rig::LIMIT_SLACK;

#[derive(Debug, Clone, PartialEq, Error)]
pub enum TrajectoryError {
    #[error("trajectory has {got} axes ({}), rig {rig} has {expected}", names.join(", "))]
    AxisMismatch {
        rig: String,
        expected: usize,
        got: usize,
        names: Vec<String>,
    },
    #[error("trajectory axis {index} is `{got}`, rig joint is `{expected}`")]
    NameMismatch {
        index: usize,
        expected: String,
        got: String,
    },
    #[error("trajectory data has {values} values, not a whole number of {dof}-axis samples")]
    Ragged { values: usize, dof: usize },
    #[error("period {} s must be positive", period.as_secs_f64())]
    BadPeriod { period: Duration },
    #[error("time scale {speed} must be positive and finite")]
    BadTimeScale { speed: f64 },
    #[error(
        "bringing the axes to rest from the last sample within their accelerations takes {samples:.0} samples, more than {max}"
    )]
    RampTooLong { samples: f64, max: usize },
    #[error("sample {sample}: {joint} = {value} is not finite")]
    NotFinite {
        sample: usize,
        joint: String,
        value: f64,
    },
    #[error(
        "sample {sample}: {joint} = {:.3} {unit} is outside its limits [{:.3}, {:.3}] {unit}",
        kind.to_user(*value), kind.to_user(*lower), kind.to_user(*upper), unit = kind.unit()
    )]
    OutsideLimits {
        sample: usize,
        joint: String,
        /// SI units (radians or metres); the message shows them in the user's unit.
        value: f64,
        lower: f64,
        upper: f64,
        kind: crate::rig::JointKind,
    },
    #[error(
        "sample {sample}: {joint} steps {step:.6} in one period, more than its max {max_step:.6}"
    )]
    OverSpeed {
        sample: usize,
        joint: String,
        step: f64,
        max_step: f64,
    },
    #[error(
        "the trajectory ends moving: {joint} at {:.4} {unit}/s over its last period; it must end \
         at rest (its last step within one period's deceleration), since the stream holds the \
         last sample and the safety gate would refuse that hold with the arm still moving",
        kind.to_user(*speed), unit = kind.unit()
    )]
    EndsMoving {
        joint: String,
        /// SI units per second (rad/s or m/s).
        speed: f64,
        kind: JointKind,
    },
    #[error(
        "sample {sample}: {joint} velocity {velocity:.6} is above its max speed {max_speed:.6}"
    )]
    VelocityOverSpeed {
        sample: usize,
        joint: String,
        velocity: f64,
        max_speed: f64,
    },
    #[error(
        "sample {sample}: {joint} accelerates at {acceleration:.6} {unit} (its positions' second difference over the period squared), above its max acceleration {max_acceleration:.6} {unit}"
    )]
    OverAcceleration {
        sample: usize,
        joint: String,
        acceleration: f64,
        max_acceleration: f64,
        unit: &'static str,
    },
    #[error(
        "sample {sample}: {joint} velocity changes at {acceleration:.6} {unit} from the sample before, above its max acceleration {max_acceleration:.6} {unit}"
    )]
    VelocityOverAcceleration {
        sample: usize,
        joint: String,
        acceleration: f64,
        max_acceleration: f64,
        unit: &'static str,
    },
}

/// The SI unit of an acceleration of `joint`.
fn acceleration_unit(joint: &crate::rig::Joint) -> &'static str {
    match joint.kind {
        JointKind::Revolute => "rad/s^2",
        JointKind::Prismatic => "m/s^2",
    }
}

/// What the stream does at an I/O point, the arm at rest there.
#[derive(Debug, Clone, PartialEq)]
pub enum IoAction {
    /// Set a digital output and wait until the controller says it took effect.
    SetOutput { name: String, value: bool },
    /// Read a digital input until it has `value`, at most `timeout`.
    WaitInput {
        name: String,
        value: bool,
        timeout: Duration,
    },
}

/// An I/O step on a trajectory: at `sample` (at rest), the stream holds the arm still until
/// `action` is done.
#[derive(Debug, Clone, PartialEq)]
pub struct IoPoint {
    pub sample: usize,
    pub action: IoAction,
    /// The step as written (`job.steps[2].steps[2] (grip)`), for refusals.
    pub step: String,
}

/// Samples `0..len` at times `i * period`, row-major: sample `i` holds `dof` values; and
/// the I/O points on them, in order.
#[derive(Debug, Clone, PartialEq)]
pub struct Trajectory {
    pub rig: String,
    pub joint_names: Vec<String>,
    pub period: Duration,
    positions: Vec<f64>,
    velocities: Vec<f64>,
    io: Vec<IoPoint>,
}

impl Trajectory {
    pub fn new(
        rig: String,
        joint_names: Vec<String>,
        period: Duration,
        positions: Vec<f64>,
        velocities: Vec<f64>,
    ) -> Result<Self, TrajectoryError> {
        let dof = joint_names.len();
        if period.is_zero() {
            return Err(TrajectoryError::BadPeriod { period });
        }
        for values in [&positions, &velocities] {
            if dof == 0 || values.len() % dof != 0 || values.len() != positions.len() {
                return Err(TrajectoryError::Ragged {
                    values: values.len(),
                    dof,
                });
            }
        }
        Ok(Self {
            rig,
            joint_names,
            period,
            positions,
            velocities,
            io: Vec::new(),
        })
    }

    /// The same samples with `points` (sorted by sample, each within the trajectory).
    pub fn with_io(mut self, points: Vec<IoPoint>) -> Self {
        let last = self.len().saturating_sub(1);
        self.io = points
            .into_iter()
            .map(|p| IoPoint {
                sample: p.sample.min(last),
                ..p
            })
            .collect();
        self
    }

    /// The I/O points, in order.
    pub fn io_points(&self) -> &[IoPoint] {
        &self.io
    }

    pub fn dof(&self) -> usize {
        self.joint_names.len()
    }

    pub fn len(&self) -> usize {
        self.positions.len() / self.dof()
    }

    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }

    pub fn position(&self, sample: usize) -> &[f64] {
        let dof = self.dof();
        &self.positions[sample * dof..(sample + 1) * dof]
    }

    pub fn velocity(&self, sample: usize) -> &[f64] {
        let dof = self.dof();
        &self.velocities[sample * dof..(sample + 1) * dof]
    }

    /// Seconds from the first sample to the last, for maths and reports: samples x period
    /// in f64, the value the reports' `duration_s` fields have always carried.
    pub fn duration_s(&self) -> f64 {
        self.len().saturating_sub(1) as f64 * self.period.as_secs_f64()
    }

    /// Samples `from..` as a trajectory of their own (where a resumed job picks up).
    pub fn tail(&self, from: usize) -> Trajectory {
        let dof = self.dof();
        let from = from.min(self.len().saturating_sub(1));
        Trajectory {
            rig: self.rig.clone(),
            joint_names: self.joint_names.clone(),
            period: self.period,
            positions: self.positions[from * dof..].to_vec(),
            velocities: self.velocities[from * dof..].to_vec(),
            // A point at `from` itself runs again: setting an output twice is setting it.
            io: self
                .io
                .iter()
                .filter(|p| p.sample >= from)
                .map(|p| IoPoint {
                    sample: p.sample - from,
                    ..p.clone()
                })
                .collect(),
        }
    }

    /// Joins `next` on the end; it must start where this one ends (same rig and period).
    pub fn append(&mut self, next: &Trajectory) {
        debug_assert_eq!(self.joint_names, next.joint_names);
        let dof = self.dof();
        let skip = if self.is_empty() { 0 } else { dof };
        let offset = self.len().saturating_sub(1);
        self.io.extend(next.io.iter().map(|p| IoPoint {
            sample: p.sample + offset,
            ..p.clone()
        }));
        self.positions
            .extend_from_slice(&next.positions[skip.min(next.positions.len())..]);
        self.velocities
            .extend_from_slice(&next.velocities[skip.min(next.velocities.len())..]);
    }
}

/// Checks every sample against the rig: same axes, finite, inside the position limits, no
/// step between samples beyond max speed x period, no velocity above max speed, and, on
/// every axis, no acceleration above its max: neither the positions' second difference
/// `p[k+1] - 2 p[k] + p[k-1]` beyond max acceleration x period^2, nor the sampled
/// velocities' change `v[k+1] - v[k]` beyond max acceleration x period; and it ends at
/// rest, its last step within one period's deceleration, since the stream holds the last
/// sample once the path is done.
pub fn validate(trajectory: &Trajectory, rig: &Rig) -> Result<(), TrajectoryError> {
    validate_motion(trajectory, rig)?;
    check_ends_at_rest(trajectory, rig)
}

/// [`validate`] but for the end: for a motion that is not streamed as it is, but first
/// brought to rest (a recorded run cut short, which replay ends with a ramp to rest and
/// then validates whole).
pub fn validate_motion(trajectory: &Trajectory, rig: &Rig) -> Result<(), TrajectoryError> {
    check_axes(trajectory, rig)?;
    let dt = trajectory.period.as_secs_f64();
    for sample in 0..trajectory.len() {
        check_sample(trajectory, rig, sample, dt)?;
    }
    check_accelerations(trajectory, rig)
}

/// Once the path is done the stream holds the last sample: from the step before it, that
/// hold is a second difference the gate checks against each axis's acceleration.
fn check_ends_at_rest(trajectory: &Trajectory, rig: &Rig) -> Result<(), TrajectoryError> {
    let len = trajectory.len();
    if len < 2 {
        return Ok(());
    }
    let dt = trajectory.period.as_secs_f64();
    let (last, before) = (trajectory.position(len - 1), trajectory.position(len - 2));
    for (axis, joint) in rig.joints.iter().enumerate() {
        let step = last[axis] - before[axis];
        if !joint.limits.second_difference_ok(step, dt) {
            return Err(TrajectoryError::EndsMoving {
                joint: joint.name.clone(),
                speed: step.abs() / dt,
                kind: joint.kind,
            });
        }
    }
    Ok(())
}

fn check_axes(trajectory: &Trajectory, rig: &Rig) -> Result<(), TrajectoryError> {
    if trajectory.dof() != rig.dof() {
        return Err(TrajectoryError::AxisMismatch {
            rig: rig.name.clone(),
            expected: rig.dof(),
            got: trajectory.dof(),
            names: trajectory.joint_names.clone(),
        });
    }
    for (index, (joint, name)) in rig.joints.iter().zip(&trajectory.joint_names).enumerate() {
        if &joint.name != name {
            return Err(TrajectoryError::NameMismatch {
                index,
                expected: joint.name.clone(),
                got: name.clone(),
            });
        }
    }
    Ok(())
}

/// Sample `sample` alone (and its step from the one before): finite, in limits, in speed
/// (`dt`: the period in seconds).
fn check_sample(
    trajectory: &Trajectory,
    rig: &Rig,
    sample: usize,
    dt: f64,
) -> Result<(), TrajectoryError> {
    let positions = trajectory.position(sample);
    let velocities = trajectory.velocity(sample);
    let previous = (sample > 0).then(|| trajectory.position(sample - 1));
    for (axis, joint) in rig.joints.iter().enumerate() {
        let (value, velocity) = (positions[axis], velocities[axis]);
        let limits = joint.limits;
        if !value.is_finite() || !velocity.is_finite() {
            return Err(TrajectoryError::NotFinite {
                sample,
                joint: joint.name.clone(),
                value: if value.is_finite() { velocity } else { value },
            });
        }
        if !limits.contains(value) {
            return Err(TrajectoryError::OutsideLimits {
                sample,
                joint: joint.name.clone(),
                value,
                lower: limits.lower,
                upper: limits.upper,
                kind: joint.kind,
            });
        }
        if !limits.speed_ok(velocity) {
            return Err(TrajectoryError::VelocityOverSpeed {
                sample,
                joint: joint.name.clone(),
                velocity,
                max_speed: limits.max_speed,
            });
        }
        if let Some(previous) = previous {
            let step = value - previous[axis];
            if !limits.step_ok(step, dt) {
                return Err(TrajectoryError::OverSpeed {
                    sample,
                    joint: joint.name.clone(),
                    step: step.abs(),
                    max_step: limits.max_speed * dt,
                });
            }
        }
    }
    Ok(())
}

/// The raw differences behind `axis`' two accelerations at `sample`: the positions' second
/// difference around it (none at either end) and the velocity change since the sample
/// before (none at the first).
fn differences_at(trajectory: &Trajectory, sample: usize, axis: usize) -> [Option<f64>; 2] {
    Neighbours::at(trajectory, sample).differences(axis)
}

/// The rows around one sample, looked up once for all its axes (validation walks every
/// sample of long plans).
struct Neighbours<'t> {
    /// Positions and velocities of the sample before, if any.
    before: Option<(&'t [f64], &'t [f64])>,
    here: (&'t [f64], &'t [f64]),
    /// Positions of the sample after, if any.
    after: Option<&'t [f64]>,
}

impl<'t> Neighbours<'t> {
    fn at(trajectory: &'t Trajectory, sample: usize) -> Self {
        let row = |k: usize| (trajectory.position(k), trajectory.velocity(k));
        Self {
            before: (sample > 0).then(|| row(sample - 1)),
            here: row(sample),
            after: (sample + 1 < trajectory.len()).then(|| trajectory.position(sample + 1)),
        }
    }

    /// [`differences_at`] for `axis`.
    fn differences(&self, axis: usize) -> [Option<f64>; 2] {
        let (p, v) = (self.here.0[axis], self.here.1[axis]);
        let second = self
            .before
            .zip(self.after)
            .map(|((before, _), after)| after[axis] - 2.0 * p + before[axis]);
        let change = self.before.map(|(_, velocities)| v - velocities[axis]);
        [second, change]
    }
}

/// Both accelerations of `axis` at `sample` (axis unit per second squared), from
/// [`differences_at`], over the period `dt` in seconds.
fn accelerations_at(
    trajectory: &Trajectory,
    sample: usize,
    axis: usize,
    dt: f64,
) -> [Option<f64>; 2] {
    let [second, change] = differences_at(trajectory, sample, axis);
    [second.map(|d| d / (dt * dt)), change.map(|d| d / dt)]
}

fn check_accelerations(trajectory: &Trajectory, rig: &Rig) -> Result<(), TrajectoryError> {
    let dt = trajectory.period.as_secs_f64();
    for sample in 1..trajectory.len() {
        let neighbours = Neighbours::at(trajectory, sample);
        for (axis, joint) in rig.joints.iter().enumerate() {
            let limits = joint.limits;
            let [second, change] = neighbours.differences(axis);
            let max_acceleration = limits.max_acceleration;
            if let Some(d) = second.filter(|d| !limits.second_difference_ok(*d, dt)) {
                return Err(TrajectoryError::OverAcceleration {
                    sample,
                    joint: joint.name.clone(),
                    acceleration: d / (dt * dt),
                    max_acceleration,
                    unit: acceleration_unit(joint),
                });
            }
            if let Some(d) = change.filter(|d| !limits.velocity_change_ok(*d, dt)) {
                return Err(TrajectoryError::VelocityOverAcceleration {
                    sample,
                    joint: joint.name.clone(),
                    acceleration: d / dt,
                    max_acceleration,
                    unit: acceleration_unit(joint),
                });
            }
        }
    }
    Ok(())
}

/// Where a trajectory comes nearest its axes' max accelerations.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PeakAcceleration {
    pub sample: usize,
    pub axis: usize,
    /// Signed, in the axis' unit per second squared.
    pub acceleration: f64,
    /// |acceleration| / the axis' max acceleration: at most 1 for a valid trajectory.
    pub ratio: f64,
}

/// Per axis, the sample where its acceleration (either of `validate`'s two measures) is
/// largest against its max, or `None` for an axis that never accelerates (fewer than two
/// samples, or a standstill). The axes must match `rig`'s (as `validate` checks).
pub fn peak_accelerations(trajectory: &Trajectory, rig: &Rig) -> Vec<Option<PeakAcceleration>> {
    let mut peaks = vec![None; rig.dof().min(trajectory.dof())];
    let dt = trajectory.period.as_secs_f64();
    for sample in 1..trajectory.len() {
        for (axis, peak) in peaks.iter_mut().enumerate() {
            let max = rig.joints[axis].limits.max_acceleration;
            for acceleration in accelerations_at(trajectory, sample, axis, dt)
                .into_iter()
                .flatten()
            {
                let ratio = acceleration.abs() / max;
                if ratio > 0.0 && peak.is_none_or(|p: PeakAcceleration| ratio > p.ratio) {
                    *peak = Some(PeakAcceleration {
                        sample,
                        axis,
                        acceleration,
                        ratio,
                    });
                }
            }
        }
    }
    peaks
}
