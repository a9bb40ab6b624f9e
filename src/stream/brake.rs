//! Braking along the path: once a stop is acknowledged (or the stream aborts), each cycle
//! advances along the trajectory by the smallest rate that keeps every axis within its
//! acceleration (the second difference of positions and the change of commanded velocity)
//! and that moves the arm no faster than the cycle before. The arm's speed is measured as
//! the fastest axis' share of its own speed limit, of the position step and of the
//! commanded velocity alike, so it never rises after the stop, and the arm comes to rest
//! as soon as the accelerations allow, not a path length later. Owns this choice of rate
//! only; the cycle sends the target and the gate checks it.

use super::gate::Sent;
use crate::motion::Trajectory;
use crate::protocol::AxisValues;
use crate::rig::Rig;

/// The share of each axis' acceleration the brake plans with: the rest keeps its targets
/// clear of the gate's own check by more than rounding.
const ACCELERATION_SHARE: f64 = 0.98;
/// Rates tried evenly between standstill and the last rate before narrowing down.
const GRID: u32 = 32;
/// Halvings of the interval between the last rate that did not fit and the first that did:
/// 2^-16 of a grid step, far below a micro-radian of motion.
const REFINE: u32 = 16;
/// Speeds compared with this relative slack: one rounding of the interpolation.
const SPEED_SLACK: f64 = 1e-9;

/// Where the stream is: its trajectory and rig, the path position (samples) and the rate
/// (samples per cycle) of the last target.
pub(super) struct Motion<'a> {
    pub trajectory: &'a Trajectory,
    pub rig: &'a Rig,
    pub path: f64,
    pub rate: f64,
}

/// The positions and the commanded velocities at `path` (samples) moving at `rate`
/// (samples per cycle), interpolated between the trajectory's samples.
pub(super) fn sample_at(trajectory: &Trajectory, path: f64, rate: f64) -> (AxisValues, AxisValues) {
    let dof = trajectory.dof();
    let last = trajectory.len() - 1;
    let path = path.clamp(0.0, last as f64);
    let index = (path.floor() as usize).min(last);
    let next = (index + 1).min(last);
    let fraction = path - index as f64;
    let mut positions = AxisValues::zeros(dof);
    let mut velocities = AxisValues::zeros(dof);
    // Each sample read once: one on a curve is evaluated on demand.
    let ((pa, va), (pb, vb)) = (trajectory.sample(index), trajectory.sample(next));
    for axis in 0..dof {
        positions.as_mut_slice()[axis] = pa[axis] + fraction * (pb[axis] - pa[axis]);
        velocities.as_mut_slice()[axis] = rate * (va[axis] + fraction * (vb[axis] - va[axis]));
    }
    (positions, velocities)
}

/// The rate of the next braking cycle: the smallest that fits (see the module doc). When
/// none up to the last rate fits (a path whose curvature asks more of an axis than the
/// brake's share), the last rate is kept: the plan's own motion, which the gate checks.
pub(super) fn rate(motion: &Motion<'_>, sent: &Sent) -> f64 {
    let Some(last) = Last::of(motion, sent) else {
        // Nothing was sent: the arm is at rest.
        return 0.0;
    };
    let fits = |rate: f64| last.fits(motion, rate);
    if fits(0.0) {
        return 0.0;
    }
    let mut too_slow = 0.0;
    for i in 1..=GRID {
        let candidate = motion.rate * f64::from(i) / f64::from(GRID);
        if fits(candidate) {
            let mut fitting = candidate;
            for _ in 0..REFINE {
                let middle = 0.5 * (too_slow + fitting);
                if fits(middle) {
                    fitting = middle;
                } else {
                    too_slow = middle;
                }
            }
            return fitting;
        }
        too_slow = candidate;
    }
    motion.rate
}

/// The last target sent, the step that led to it and the speeds it moved at.
struct Last {
    positions: AxisValues,
    velocities: AxisValues,
    step: AxisValues,
    step_speed: f64,
    commanded_speed: f64,
}

impl Last {
    fn of(motion: &Motion<'_>, sent: &Sent) -> Option<Last> {
        let (positions, velocities) = sent.previous?;
        let dt = motion.trajectory.period.as_secs_f64();
        let mut step = AxisValues::zeros(positions.as_slice().len());
        for (axis, value) in step.as_mut_slice().iter_mut().enumerate() {
            *value = match sent.before_previous {
                Some(before) => positions.as_slice()[axis] - before.as_slice()[axis],
                // One target sent, from rest: its commanded velocity is the step's.
                None => velocities.as_slice()[axis] * dt,
            };
        }
        Some(Last {
            step_speed: speed_share(motion.rig, &step, dt),
            commanded_speed: speed_share(motion.rig, &velocities, 1.0),
            positions,
            velocities,
            step,
        })
    }

    /// Whether moving on by `rate` keeps every axis within the brake's acceleration and
    /// the arm no faster than the last target.
    fn fits(&self, motion: &Motion<'_>, rate: f64) -> bool {
        let dt = motion.trajectory.period.as_secs_f64();
        let (positions, velocities) = sample_at(motion.trajectory, motion.path + rate, rate);
        let mut step = AxisValues::zeros(positions.as_slice().len());
        for (axis, joint) in motion.rig.joints.iter().enumerate() {
            let now = positions.as_slice()[axis] - self.positions.as_slice()[axis];
            step.as_mut_slice()[axis] = now;
            let acceleration = ACCELERATION_SHARE * joint.limits.max_acceleration;
            let second = now - self.step.as_slice()[axis];
            let change = velocities.as_slice()[axis] - self.velocities.as_slice()[axis];
            if second.abs() > acceleration * dt * dt || change.abs() > acceleration * dt {
                return false;
            }
        }
        not_faster(speed_share(motion.rig, &step, dt), self.step_speed)
            && not_faster(
                speed_share(motion.rig, &velocities, 1.0),
                self.commanded_speed,
            )
    }
}

fn not_faster(now: f64, before: f64) -> bool {
    now <= before * (1.0 + SPEED_SLACK)
}

/// The fastest axis' share of its speed limit, `values` per `per` seconds.
fn speed_share(rig: &Rig, values: &AxisValues, per: f64) -> f64 {
    rig.joints
        .iter()
        .zip(values.as_slice())
        .map(|(joint, value)| (value / per).abs() / joint.limits.max_speed)
        .fold(0.0, f64::max)
}
