//! The `Trajectory` every stage hands down (joint samples at a fixed period, positions and
//! velocities per axis, generic over the rig; stored as the samples themselves or as a
//! curve through few knots sampled on demand, read alike as [`Sample`]s held inline) and
//! `validate`, the check every trajectory passes after it is planned, before it is streamed
//! and before it is replayed.
//!
//! A leaf beside the chain, as `protocol` is beside the link: the planners above
//! (`trajectory`, `ik`, `job`, `task`) build it and the streamer below runs it, so it
//! lives under both (`docs/architecture.md`, "Layers"). Owns the type, its errors and the
//! validator, and the I/O points a program puts on it (where the stream stops at rest
//! until an output is set or an input read); must not plan, stream or import anything but
//! `rig` and `protocol`'s axis values.

use crate::protocol::{AxisValues, MAX_AXES};
use crate::rig::{JointKind, Rig};
use std::sync::Arc;
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
    #[error("trajectory has {dof} axes, more than the {max} a sample holds")]
    TooManyAxes { dof: usize, max: usize },
    #[error(
        "a curve's {knots} knot times must start at 0, be finite and increase from knot to knot"
    )]
    BadKnots { knots: usize },
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

/// The most axes a trajectory may have: what one sample's inline storage holds, the most
/// the stream sends ([`MAX_AXES`]).
pub const MAX_TRAJECTORY_AXES: usize = MAX_AXES;

/// One sample's values, one per axis, held inline: a sample evaluated on demand cannot be
/// borrowed from the trajectory, and the stream reads one every cycle without allocating.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sample(AxisValues);

impl Sample {
    /// The values as the protocol carries them.
    pub fn values(&self) -> AxisValues {
        self.0
    }
}

impl std::ops::Deref for Sample {
    type Target = [f64];
    fn deref(&self) -> &[f64] {
        self.0.as_slice()
    }
}

impl AsRef<[f64]> for Sample {
    fn as_ref(&self) -> &[f64] {
        self.0.as_slice()
    }
}

impl PartialEq<&[f64]> for Sample {
    fn eq(&self, other: &&[f64]) -> bool {
        self.0.as_slice() == *other
    }
}

impl PartialEq<Sample> for &[f64] {
    fn eq(&self, other: &Sample) -> bool {
        *self == other.0.as_slice()
    }
}

/// A curve through knots, sampled on demand: cubic Hermite pieces between consecutive
/// knots, each with its knots' positions and tangents (per second). Sample `k` lies at
/// `t = min(k x period, last knot's time)`, on the piece that starts at the last knot not
/// after `t` (the last piece for `t` at or past the knot before the last).
#[derive(Debug, Clone, PartialEq)]
pub struct HermiteCurve {
    /// Seconds from the first knot (0), strictly increasing.
    times: Vec<f64>,
    /// Row-major: knot `k` holds `dof` values.
    positions: Vec<f64>,
    tangents: Vec<f64>,
    dof: usize,
    period_s: f64,
}

impl HermiteCurve {
    /// Knots at `times` (from 0, strictly increasing, finite) with `positions` and
    /// `tangents` row-major, `dof` per knot, sampled every `period`.
    pub fn new(
        times: Vec<f64>,
        positions: Vec<f64>,
        tangents: Vec<f64>,
        dof: usize,
        period: Duration,
    ) -> Result<Self, TrajectoryError> {
        if period.is_zero() {
            return Err(TrajectoryError::BadPeriod { period });
        }
        for values in [&positions, &tangents] {
            if dof == 0 || values.len() != times.len() * dof {
                return Err(TrajectoryError::Ragged {
                    values: values.len(),
                    dof,
                });
            }
        }
        let increasing = times.first() == Some(&0.0)
            && times.iter().all(|t| t.is_finite())
            && times.windows(2).all(|w| w[0] < w[1]);
        if !increasing {
            return Err(TrajectoryError::BadKnots { knots: times.len() });
        }
        Ok(Self {
            times,
            positions,
            tangents,
            dof,
            period_s: period.as_secs_f64(),
        })
    }

    /// The samples it makes: every period from 0 to its last knot, the last knot exactly.
    fn samples(&self) -> usize {
        (self.end() / self.period_s).ceil() as usize + 1
    }

    fn end(&self) -> f64 {
        self.times[self.times.len() - 1]
    }

    /// Bytes it stores.
    fn stored_bytes(&self) -> usize {
        Self::bytes_for(self.times.len(), self.dof)
    }

    /// Bytes a curve through `knots` knots of `dof` axes stores: a time, and a position and
    /// a tangent per axis, for each knot (what a plan's memory cap counts, before planning).
    pub fn bytes_for(knots: usize, dof: usize) -> usize {
        knots.saturating_mul(dof.saturating_mul(2).saturating_add(1)) * F64_BYTES
    }

    /// Position and velocity of `axis` at sample `k`, into `positions` and `velocities`.
    fn evaluate(&self, k: usize, positions: &mut [f64], velocities: &mut [f64]) {
        let t = (k as f64 * self.period_s).min(self.end());
        let last = self.times.len() - 1;
        // The piece starts at the last inner knot not after `t` (knot 0 before them).
        let piece = self.times[1..last.max(1)].partition_point(|time| *time <= t);
        let next = (piece + 1).min(last);
        let (ta, tb) = (self.times[piece], self.times[next]);
        let h = (tb - ta).max(f64::MIN_POSITIVE);
        let s = ((t - ta) / h).clamp(0.0, 1.0);
        let (a, b) = (piece * self.dof, next * self.dof);
        for axis in 0..self.dof {
            let (p, d) = hermite(
                self.positions[a + axis],
                self.positions[b + axis],
                self.tangents[a + axis] * h,
                self.tangents[b + axis] * h,
                s,
            );
            positions[axis] = p;
            velocities[axis] = d / h;
        }
    }
}

/// Position and derivative (per unit `s`) of the cubic Hermite piece from `p0` (slope `m0`)
/// to `p1` (slope `m1`) at `s` in [0, 1].
pub fn hermite(p0: f64, p1: f64, m0: f64, m1: f64, s: f64) -> (f64, f64) {
    let (s2, s3) = (s * s, s * s * s);
    let p = (2.0 * s3 - 3.0 * s2 + 1.0) * p0
        + (s3 - 2.0 * s2 + s) * m0
        + (-2.0 * s3 + 3.0 * s2) * p1
        + (s3 - s2) * m1;
    let d = (6.0 * s2 - 6.0 * s) * p0
        + (3.0 * s2 - 4.0 * s + 1.0) * m0
        + (-6.0 * s2 + 6.0 * s) * p1
        + (3.0 * s2 - 2.0 * s) * m1;
    (p, d)
}

/// Bytes of one stored `f64`.
const F64_BYTES: usize = std::mem::size_of::<f64>();

/// A stretch of consecutive samples, stored as planned or evaluated on demand.
#[derive(Debug, Clone, PartialEq)]
enum Part {
    /// Row-major samples: sample `i` holds `dof` values.
    Dense {
        positions: Vec<f64>,
        velocities: Vec<f64>,
    },
    /// Samples `first..first + len` of a curve, shared between a plan and its tails.
    Curve {
        curve: Arc<HermiteCurve>,
        first: usize,
        len: usize,
    },
}

impl Part {
    fn len(&self, dof: usize) -> usize {
        match self {
            Part::Dense { positions, .. } => positions.len() / dof,
            Part::Curve { len, .. } => *len,
        }
    }

    /// Samples `from..` of this part (`from` below its length).
    fn from(&self, from: usize, dof: usize) -> Part {
        match self {
            Part::Dense {
                positions,
                velocities,
            } => Part::Dense {
                positions: positions[from * dof..].to_vec(),
                velocities: velocities[from * dof..].to_vec(),
            },
            Part::Curve { curve, first, len } => Part::Curve {
                curve: Arc::clone(curve),
                first: first + from,
                len: len - from,
            },
        }
    }

    /// Sample `i` of this part into `positions` and `velocities`.
    fn read(&self, i: usize, dof: usize, positions: &mut [f64], velocities: &mut [f64]) {
        match self {
            Part::Dense {
                positions: p,
                velocities: v,
            } => {
                positions.copy_from_slice(&p[i * dof..(i + 1) * dof]);
                velocities.copy_from_slice(&v[i * dof..(i + 1) * dof]);
            }
            Part::Curve { curve, first, .. } => curve.evaluate(first + i, positions, velocities),
        }
    }

    fn stored_bytes(&self) -> usize {
        match self {
            Part::Dense {
                positions,
                velocities,
            } => (positions.len() + velocities.len()) * F64_BYTES,
            Part::Curve { curve, .. } => curve.stored_bytes(),
        }
    }
}

/// Samples `0..len` at times `i * period`, `dof` values each: stored in parts, each either
/// the samples themselves (what most planners make) or a curve through few knots sampled
/// on demand (a long `follow_trajectory`), so a day-long plan through two points stores two
/// points. Every reader sees samples alike: [`Trajectory::position`], [`Trajectory::velocity`].
/// And the I/O points on them, in order.
#[derive(Debug, Clone, PartialEq)]
pub struct Trajectory {
    pub rig: String,
    pub joint_names: Vec<String>,
    pub period: Duration,
    parts: Vec<Part>,
    /// The first sample of each part.
    starts: Vec<usize>,
    len: usize,
    io: Vec<IoPoint>,
}

impl Trajectory {
    /// A trajectory of samples as given: row-major positions and velocities, `dof` each.
    pub fn new(
        rig: String,
        joint_names: Vec<String>,
        period: Duration,
        positions: Vec<f64>,
        velocities: Vec<f64>,
    ) -> Result<Self, TrajectoryError> {
        let dof = joint_names.len();
        for values in [&positions, &velocities] {
            if dof == 0 || values.len() % dof != 0 || values.len() != positions.len() {
                return Err(TrajectoryError::Ragged {
                    values: values.len(),
                    dof,
                });
            }
        }
        check_shape(dof, period)?;
        let mut trajectory = Self::empty(rig, joint_names, period);
        trajectory.push(Part::Dense {
            positions,
            velocities,
        });
        Ok(trajectory)
    }

    /// A trajectory of `curve`'s samples, evaluated on demand.
    pub fn from_curve(
        rig: String,
        joint_names: Vec<String>,
        period: Duration,
        curve: HermiteCurve,
    ) -> Result<Self, TrajectoryError> {
        let dof = joint_names.len();
        check_shape(dof, period)?;
        if dof == 0 || curve.dof != dof || curve.period_s != period.as_secs_f64() {
            return Err(TrajectoryError::Ragged {
                values: curve.positions.len(),
                dof,
            });
        }
        let mut trajectory = Self::empty(rig, joint_names, period);
        let len = curve.samples();
        trajectory.push(Part::Curve {
            curve: Arc::new(curve),
            first: 0,
            len,
        });
        Ok(trajectory)
    }

    fn empty(rig: String, joint_names: Vec<String>, period: Duration) -> Self {
        Self {
            rig,
            joint_names,
            period,
            parts: Vec::new(),
            starts: Vec::new(),
            len: 0,
            io: Vec::new(),
        }
    }

    /// Adds `part` at the end, unless it holds no samples.
    fn push(&mut self, part: Part) {
        let len = part.len(self.dof());
        if len == 0 {
            return;
        }
        self.starts.push(self.len);
        self.len += len;
        self.parts.push(part);
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
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Bytes its samples take as stored (curves count their knots, not their samples).
    pub fn stored_bytes(&self) -> usize {
        self.parts.iter().map(Part::stored_bytes).sum()
    }

    /// Positions and velocities of sample `sample`, evaluated once for both.
    ///
    /// # Panics
    /// When `sample` is not below [`Trajectory::len`].
    pub fn sample(&self, sample: usize) -> (Sample, Sample) {
        assert!(
            sample < self.len,
            "sample {sample} of a {}-sample trajectory",
            self.len
        );
        let dof = self.dof();
        let mut positions = AxisValues::zeros(dof);
        let mut velocities = AxisValues::zeros(dof);
        let part = self.starts.partition_point(|start| *start <= sample) - 1;
        self.parts[part].read(
            sample - self.starts[part],
            dof,
            positions.as_mut_slice(),
            velocities.as_mut_slice(),
        );
        (Sample(positions), Sample(velocities))
    }

    pub fn position(&self, sample: usize) -> Sample {
        self.sample(sample).0
    }

    pub fn velocity(&self, sample: usize) -> Sample {
        self.sample(sample).1
    }

    /// Seconds from the first sample to the last, for maths and reports: samples x period
    /// in f64, the value the reports' `duration_s` fields have always carried.
    pub fn duration_s(&self) -> f64 {
        self.len().saturating_sub(1) as f64 * self.period.as_secs_f64()
    }

    /// Samples `from..` as a trajectory of their own (where a resumed job picks up).
    pub fn tail(&self, from: usize) -> Trajectory {
        let from = from.min(self.len().saturating_sub(1));
        let dof = self.dof();
        let mut tail = Self::empty(self.rig.clone(), self.joint_names.clone(), self.period);
        for (part, start) in self.parts.iter().zip(&self.starts) {
            let end = start + part.len(dof);
            if end > from {
                tail.push(part.from(from.saturating_sub(*start), dof));
            }
        }
        // A point at `from` itself runs again: setting an output twice is setting it.
        tail.io = self
            .io
            .iter()
            .filter(|p| p.sample >= from)
            .map(|p| IoPoint {
                sample: p.sample - from,
                ..p.clone()
            })
            .collect();
        tail
    }

    /// Joins `next` on the end; it must start where this one ends (same rig and period).
    pub fn append(&mut self, next: &Trajectory) {
        debug_assert_eq!(self.joint_names, next.joint_names);
        let (dof, skip) = (self.dof(), usize::from(!self.is_empty()));
        let offset = self.len().saturating_sub(1);
        self.io.extend(next.io.iter().map(|p| IoPoint {
            sample: p.sample + offset,
            ..p.clone()
        }));
        let mut parts = next.parts.iter();
        if skip == 1 {
            let Some(first) = parts.next() else {
                return;
            };
            if first.len(dof) > 1 {
                self.join(first.from(1, dof));
            }
        }
        for part in parts {
            self.join(part.clone());
        }
    }

    /// Adds `part` at the end, into the last part when both are dense.
    fn join(&mut self, part: Part) {
        if let (
            Some(Part::Dense {
                positions,
                velocities,
            }),
            Part::Dense {
                positions: more_positions,
                velocities: more_velocities,
            },
        ) = (self.parts.last_mut(), &part)
        {
            positions.extend_from_slice(more_positions);
            velocities.extend_from_slice(more_velocities);
            self.len += more_positions.len() / self.joint_names.len();
            return;
        }
        self.push(part);
    }
}

/// A trajectory needs at most [`MAX_TRAJECTORY_AXES`] axes and a positive period.
fn check_shape(dof: usize, period: Duration) -> Result<(), TrajectoryError> {
    if period.is_zero() {
        return Err(TrajectoryError::BadPeriod { period });
    }
    if dof > MAX_TRAJECTORY_AXES {
        return Err(TrajectoryError::TooManyAxes {
            dof,
            max: MAX_TRAJECTORY_AXES,
        });
    }
    Ok(())
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
    let mut previous = None;
    for sample in 0..trajectory.len() {
        let here = trajectory.sample(sample);
        check_sample(rig, sample, &here, previous.as_ref(), dt)?;
        previous = Some(here.0);
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

/// Sample `sample` alone (its positions and velocities `here`), and its step from the
/// positions `previous` of the one before: finite, in limits, in speed (`dt`: the period in
/// seconds).
fn check_sample(
    rig: &Rig,
    sample: usize,
    here: &(Sample, Sample),
    previous: Option<&Sample>,
    dt: f64,
) -> Result<(), TrajectoryError> {
    let (positions, velocities) = here;
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
struct Neighbours {
    /// Positions and velocities of the sample before, if any.
    before: Option<(Sample, Sample)>,
    here: (Sample, Sample),
    /// Positions of the sample after, if any.
    after: Option<Sample>,
}

impl Neighbours {
    fn at(trajectory: &Trajectory, sample: usize) -> Self {
        Self {
            before: (sample > 0).then(|| trajectory.sample(sample - 1)),
            here: trajectory.sample(sample),
            after: (sample + 1 < trajectory.len()).then(|| trajectory.position(sample + 1)),
        }
    }

    /// The neighbours of sample `sample + 1`, these being `sample`'s: one more evaluation,
    /// of the sample after it (none past the end).
    fn next(self, trajectory: &Trajectory, sample: usize) -> Option<Self> {
        let here = (sample + 1 < trajectory.len()).then(|| trajectory.sample(sample + 1))?;
        Some(Self {
            before: Some(self.here),
            here,
            after: (sample + 2 < trajectory.len()).then(|| trajectory.position(sample + 2)),
        })
    }

    /// [`differences_at`] for `axis`.
    fn differences(&self, axis: usize) -> [Option<f64>; 2] {
        let (p, v) = (self.here.0[axis], self.here.1[axis]);
        let second = self
            .before
            .as_ref()
            .zip(self.after.as_ref())
            .map(|((before, _), after)| after[axis] - 2.0 * p + before[axis]);
        let change = self
            .before
            .as_ref()
            .map(|(_, velocities)| v - velocities[axis]);
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
    let mut window = (trajectory.len() > 1).then(|| Neighbours::at(trajectory, 1));
    for sample in 1..trajectory.len() {
        let Some(neighbours) = window.take() else {
            break;
        };
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
        window = neighbours.next(trajectory, sample);
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

#[cfg(test)]
mod tests {
    use super::*;

    const PERIOD: Duration = Duration::from_millis(4);

    /// Knots of a two-axis curve: (t in s, positions), rows at uneven times.
    const KNOTS: [(f64, [f64; 2]); 4] = [
        (0.0, [0.0, 0.1]),
        (0.31, [0.2, -0.1]),
        (0.5, [0.25, 0.0]),
        (1.013, [-0.1, 0.3]),
    ];

    /// The knots' tangents: the slope over the knots either side, zero at the ends.
    fn tangents() -> Vec<f64> {
        let mut tangents = vec![0.0; 2];
        for k in 1..KNOTS.len() - 1 {
            let (before, after) = (KNOTS[k - 1], KNOTS[k + 1]);
            for axis in 0..2 {
                tangents.push((after.1[axis] - before.1[axis]) / (after.0 - before.0));
            }
        }
        tangents.extend([0.0; 2]);
        tangents
    }

    fn names() -> Vec<String> {
        vec!["a".into(), "b".into()]
    }

    fn compact() -> Trajectory {
        let times = KNOTS.iter().map(|k| k.0).collect();
        let positions = KNOTS.iter().flat_map(|k| k.1).collect();
        let curve = HermiteCurve::new(times, positions, tangents(), 2, PERIOD).unwrap();
        Trajectory::from_curve("r".into(), names(), PERIOD, curve).unwrap()
    }

    /// The same curve sampled densely, the way the planner sampled it before it was stored
    /// compactly: walk the pieces in time, the textbook Hermite basis at each sample.
    fn dense() -> Trajectory {
        let tangents = tangents();
        let end = KNOTS[KNOTS.len() - 1].0;
        let (mut positions, mut velocities) = (Vec::new(), Vec::new());
        let mut piece = 0;
        for k in 0..=(end / PERIOD.as_secs_f64()).ceil() as usize {
            let t = (k as f64 * PERIOD.as_secs_f64()).min(end);
            while piece + 2 < KNOTS.len() && KNOTS[piece + 1].0 <= t {
                piece += 1;
            }
            let h = KNOTS[piece + 1].0 - KNOTS[piece].0;
            let s = (t - KNOTS[piece].0) / h;
            for axis in 0..2 {
                let (p0, p1) = (KNOTS[piece].1[axis], KNOTS[piece + 1].1[axis]);
                let m0 = tangents[piece * 2 + axis] * h;
                let m1 = tangents[(piece + 1) * 2 + axis] * h;
                let (h00, h10) = (
                    2.0 * s.powi(3) - 3.0 * s * s + 1.0,
                    s.powi(3) - 2.0 * s * s + s,
                );
                let (h01, h11) = (-2.0 * s.powi(3) + 3.0 * s * s, s.powi(3) - s * s);
                positions.push(h00 * p0 + h10 * m0 + h01 * p1 + h11 * m1);
                let d00 = 6.0 * s * s - 6.0 * s;
                let d10 = 3.0 * s * s - 4.0 * s + 1.0;
                let d11 = 3.0 * s * s - 2.0 * s;
                velocities.push((d00 * p0 + d10 * m0 - d00 * p1 + d11 * m1) / h);
            }
        }
        Trajectory::new("r".into(), names(), PERIOD, positions, velocities).unwrap()
    }

    fn assert_same_samples(a: &Trajectory, b: &Trajectory) {
        assert_eq!(a.len(), b.len());
        for k in 0..a.len() {
            let ((pa, va), (pb, vb)) = (a.sample(k), b.sample(k));
            for axis in 0..a.dof() {
                assert!(
                    (pa[axis] - pb[axis]).abs() <= 1e-12,
                    "sample {k} axis {axis}"
                );
                assert!(
                    (va[axis] - vb[axis]).abs() <= 1e-12,
                    "sample {k} axis {axis}"
                );
            }
        }
    }

    #[test]
    fn a_curve_sampled_on_demand_yields_the_samples_the_dense_form_holds() {
        let (compact, dense) = (compact(), dense());
        // 1.013 s at 4 ms: 254 periods, the last knot exactly as the last sample.
        assert_eq!(compact.len(), 255);
        assert_eq!(compact.position(254), &[-0.1, 0.3][..]);
        assert_same_samples(&compact, &dense);
        assert!(compact.stored_bytes() < dense.stored_bytes() / 20);
    }

    #[test]
    fn tails_and_joins_of_both_forms_hold_the_same_samples() {
        let (compact, dense) = (compact(), dense());
        for from in [0, 1, 77, 254] {
            assert_same_samples(&compact.tail(from), &dense.tail(from));
        }
        // A dense approach, then the curve: the join drops the curve's first sample.
        let approach = dense.tail(200);
        let mut joined = Trajectory::new(
            "r".into(),
            names(),
            PERIOD,
            vec![0.0, 0.1, 0.0, 0.1],
            vec![0.0; 4],
        )
        .unwrap();
        let mut expected = joined.clone();
        joined.append(&compact);
        expected.append(&dense);
        assert_eq!(joined.len(), 256);
        assert_same_samples(&joined, &expected);
        assert_same_samples(&joined.tail(100), &expected.tail(100));
        let mut twice = approach.clone();
        twice.append(&approach);
        assert_eq!(twice.len(), 2 * approach.len() - 1);
    }
}
