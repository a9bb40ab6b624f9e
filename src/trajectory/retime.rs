//! Re-timing sampled joint motion along its own path so that every axis stays within a
//! share of its max acceleration: the geometry (every position the samples pass through,
//! in order) is kept, only the time law changes, and never faster than the samples were
//! planned. Owns that time law and the resampling at the same period; it must not change
//! a path's shape beyond interpolating between its samples, and it does not validate
//! (`validate` does, afterwards).
//!
//! The samples are read as a path q(s), s = sample index, through a C1 cubic Hermite
//! interpolant. A new time law s(t) is chosen by the forward-backward pass on
//! u = (ds/dt)^2 of time-optimal path parameterisation, on a grid of the path (Pham,
//! "A General, Fast, and Robust Implementation of the Time-Optimal Path Parameterization
//! Algorithm", IEEE T-RO 30(6), 2014; here in the discretised, reachability form of
//! Pham and Pham, "A New Approach to Time-Optimal Path Parameterization Based on
//! Reachability Analysis", IEEE T-RO 34(3), 2018): each axis' acceleration
//! q_ss u + q_s u_s / 2 within the share, its speed q_s sqrt(u) within max speed, and
//! sqrt(u) at most one sample per period.

use crate::rig::Rig;
use std::time::Duration;
use thiserror::Error;

#[derive(Debug, Clone, PartialEq, Error)]
pub enum RetimeError {
    #[error("{values} values are not a whole number of {dof}-axis samples of rig {rig}")]
    Ragged {
        rig: String,
        values: usize,
        dof: usize,
    },
    #[error("period {} s must be positive", period.as_secs_f64())]
    BadPeriod { period: Duration },
    #[error("acceleration share {share} must be in (0, 1]")]
    BadShare { share: f64 },
    #[error("sample {sample}: the path turns a corner no finite acceleration follows")]
    Corner { sample: usize },
}

/// Grid points per sample interval the time law is solved on: the interpolant's second
/// derivative is linear within an interval, so four points (and both sides of every
/// sample) see it within a quarter of its change there.
const GRID_PER_SAMPLE: usize = 4;
/// Bisection steps for the largest controllable u at a grid point: 2^-48 of its bound.
const BISECTION_STEPS: usize = 48;
/// Re-solves with a smaller budget when the resampled motion's second differences still
/// overshoot the share (grid discretisation), at most this many times.
const BUDGET_ROUNDS: usize = 8;
/// Each re-solve aims this far below what the overshoot alone would ask, so that the
/// rounds converge from below rather than creep toward the share.
const BUDGET_MARGIN: f64 = 0.98;
/// Fritsch-Carlson's bound on a limited tangent over its intervals' secants (3), which
/// keeps a cubic Hermite interval monotone between its samples (Fritsch and Carlson,
/// "Monotone Piecewise Cubic Interpolation", SIAM J. Numer. Anal. 17(2), 1980).
const MONOTONE_TANGENT_BOUND: f64 = 3.0;

/// The motion re-timed: new samples at the same period, and when (s) each original sample
/// is passed.
#[derive(Debug, Clone, PartialEq)]
pub struct Retimed {
    /// Row-major, `dof` values per sample, every period.
    pub positions: Vec<f64>,
    /// Per original sample, its time in the new motion.
    pub sample_times_s: Vec<f64>,
    /// The largest acceleration of any axis (positions' second difference over the period
    /// squared) against its max.
    pub peak_ratio: f64,
}

impl Retimed {
    /// The new sample nearest original sample `sample` (the last, past the end).
    pub fn sample_of(&self, sample: usize, period: Duration, dof: usize) -> usize {
        let last = (self.positions.len() / dof).saturating_sub(1);
        let dt = period.as_secs_f64();
        self.sample_times_s
            .get(sample)
            .map_or(last, |t| ((t / dt).round() as usize).min(last))
    }
}

/// Re-times `positions` (`rig`'s axes, row-major, one sample every `period`, at rest at
/// both ends) so that no axis' acceleration exceeds `share` x its max, and resamples at
/// `period`. Where the samples already stay within it they keep their timing; the
/// motion starts and ends at rest.
pub fn retime(
    positions: &[f64],
    rig: &Rig,
    period: Duration,
    share: f64,
) -> Result<Retimed, RetimeError> {
    let dof = rig.dof();
    if dof == 0 || !positions.len().is_multiple_of(dof) {
        return Err(RetimeError::Ragged {
            rig: rig.name.clone(),
            values: positions.len(),
            dof,
        });
    }
    if period.is_zero() {
        return Err(RetimeError::BadPeriod { period });
    }
    let dt = period.as_secs_f64();
    if !(share > 0.0 && share <= 1.0) {
        return Err(RetimeError::BadShare { share });
    }
    let path = Path::new(positions, rig);
    let mut budget = share;
    let mut best: Option<Retimed> = None;
    for _ in 0..BUDGET_ROUNDS {
        let law = TimeLaw::solve(&path, rig, dt, budget)?;
        let retimed = law.resample(&path, rig, dt);
        let done = retimed.peak_ratio <= share;
        let overshoot = retimed.peak_ratio / share;
        if best
            .as_ref()
            .is_none_or(|b| retimed.peak_ratio < b.peak_ratio)
        {
            best = Some(retimed);
        }
        if done {
            break;
        }
        budget *= BUDGET_MARGIN / overshoot;
    }
    // At least one round ran (BUDGET_ROUNDS > 0).
    best.ok_or(RetimeError::BadShare { share })
}

/// The samples as a C1 cubic Hermite path per axis, with tangents that keep every
/// interval inside the axis' limits.
struct Path<'a> {
    positions: &'a [f64],
    dof: usize,
    len: usize,
    /// Per sample and axis: dq/ds.
    tangents: Vec<f64>,
}

impl<'a> Path<'a> {
    fn new(positions: &'a [f64], rig: &Rig) -> Self {
        let dof = rig.dof();
        let len = positions.len() / dof;
        let mut path = Path {
            positions,
            dof,
            len,
            tangents: vec![0.0; positions.len()],
        };
        for axis in 0..dof {
            path.fit_axis(
                axis,
                rig.joints[axis].limits.lower,
                rig.joints[axis].limits.upper,
            );
        }
        path
    }

    fn q(&self, sample: usize, axis: usize) -> f64 {
        self.positions[sample * self.dof + axis]
    }

    /// Central-difference (Catmull-Rom) tangents, zero at both ends (at rest); then,
    /// wherever an interval's cubic would leave the limits, Fritsch-Carlson's monotone
    /// tangents at both its ends, until none does (marks only grow, and an interval
    /// limited at both ends stays between its samples).
    fn fit_axis(&mut self, axis: usize, lower: f64, upper: f64) {
        let len = self.len;
        for k in 1..len.saturating_sub(1) {
            self.tangents[k * self.dof + axis] = 0.5 * (self.q(k + 1, axis) - self.q(k - 1, axis));
        }
        let mut limited = vec![false; len];
        loop {
            let mut changed = false;
            for k in 0..len.saturating_sub(1) {
                let (low, high) = self.interval_range(k, axis);
                if (low < lower || high > upper) && !(limited[k] && limited[k + 1]) {
                    for end in [k, k + 1] {
                        if !limited[end] {
                            limited[end] = true;
                            self.tangents[end * self.dof + axis] = self.monotone_tangent(end, axis);
                        }
                    }
                    changed = true;
                }
            }
            if !changed {
                break;
            }
        }
    }

    /// Fritsch-Carlson's tangent at `k`: zero at a turn or a flat, else the central one
    /// within `MONOTONE_TANGENT_BOUND` x either neighbouring secant.
    fn monotone_tangent(&self, k: usize, axis: usize) -> f64 {
        if k == 0 || k + 1 >= self.len {
            return 0.0;
        }
        let before = self.q(k, axis) - self.q(k - 1, axis);
        let after = self.q(k + 1, axis) - self.q(k, axis);
        if before * after <= 0.0 {
            return 0.0;
        }
        let central = 0.5 * (before + after);
        let bound = MONOTONE_TANGENT_BOUND * before.abs().min(after.abs());
        central.signum() * central.abs().min(bound)
    }

    /// Hermite coefficients of interval `k` (from sample k to k+1) of `axis`:
    /// (p0, secant, m0, m1).
    fn interval(&self, k: usize, axis: usize) -> [f64; 4] {
        let p0 = self.q(k, axis);
        [
            p0,
            self.q(k + 1, axis) - p0,
            self.tangents[k * self.dof + axis],
            self.tangents[(k + 1) * self.dof + axis],
        ]
    }

    /// The least and greatest value interval `k` of `axis` takes.
    fn interval_range(&self, k: usize, axis: usize) -> (f64, f64) {
        let c = self.interval(k, axis);
        let (p0, p1) = (c[0], c[0] + c[1]);
        let (mut low, mut high) = (p0.min(p1), p0.max(p1));
        // q'(t) = 6 d (t - t^2) + m0 (1 - 4 t + 3 t^2) + m1 (3 t^2 - 2 t): a quadratic.
        let (d, m0, m1) = (c[1], c[2], c[3]);
        let a = -6.0 * d + 3.0 * m0 + 3.0 * m1;
        let b = 6.0 * d - 4.0 * m0 - 2.0 * m1;
        let roots: [Option<f64>; 2] = if a.abs() < 1e-300 {
            [(b.abs() > 1e-300).then(|| -m0 / b), None]
        } else {
            let disc = b * b - 4.0 * a * m0;
            if disc < 0.0 {
                [None, None]
            } else {
                let r = disc.sqrt();
                [Some((-b - r) / (2.0 * a)), Some((-b + r) / (2.0 * a))]
            }
        };
        for t in roots.into_iter().flatten().filter(|t| *t > 0.0 && *t < 1.0) {
            let value = hermite(&c, t);
            low = low.min(value);
            high = high.max(value);
        }
        (low, high)
    }

    /// q, q_s and q_ss of `axis` at `t` in [0, 1] into interval `k`.
    fn derivatives(&self, k: usize, axis: usize, t: f64) -> [f64; 3] {
        let c = self.interval(k, axis);
        let (d, m0, m1) = (c[1], c[2], c[3]);
        let qs = 6.0 * d * (t - t * t)
            + m0 * (1.0 - 4.0 * t + 3.0 * t * t)
            + m1 * (3.0 * t * t - 2.0 * t);
        let qss = 6.0 * d * (1.0 - 2.0 * t) + m0 * (6.0 * t - 4.0) + m1 * (6.0 * t - 2.0);
        [hermite(&c, t), qs, qss]
    }

    /// The path's position of `axis` at `s`, kept within its interval's own range (the
    /// cubic's, checked inside the limits by `fit_axis`): only rounding is clipped.
    fn position(&self, s: f64, axis: usize) -> f64 {
        let last = self.len.saturating_sub(1);
        if s <= 0.0 || last == 0 {
            return self.q(0, axis);
        }
        if s >= last as f64 {
            return self.q(last, axis);
        }
        let k = (s.floor() as usize).min(last - 1);
        let (low, high) = self.interval_range(k, axis);
        hermite(&self.interval(k, axis), s - k as f64).clamp(low, high)
    }
}

/// The Hermite interval (p0, secant, m0, m1) at `t`, in a form exact at both ends.
fn hermite(c: &[f64; 4], t: f64) -> f64 {
    let (t2, t3) = (t * t, t * t * t);
    let h01 = 3.0 * t2 - 2.0 * t3;
    let h10 = t3 - 2.0 * t2 + t;
    let h11 = t3 - t2;
    c[0] + c[1] * h01 + c[2] * h10 + c[3] * h11
}

/// One acceleration row at a grid point: |q_ss u + q_s a| <= limit.
#[derive(Clone, Copy)]
struct Row {
    qs: f64,
    qss: f64,
    limit: f64,
}

/// The solved time law: u = (ds/dt)^2 on the grid, constant ds^2/dt^2 between points.
struct TimeLaw {
    /// Grid spacing in samples.
    step: f64,
    u: Vec<f64>,
    /// Time (s) at each grid point.
    times: Vec<f64>,
}

impl TimeLaw {
    fn solve(path: &Path, rig: &Rig, dt: f64, share: f64) -> Result<TimeLaw, RetimeError> {
        let step = 1.0 / GRID_PER_SAMPLE as f64;
        let points = (path.len.saturating_sub(1)) * GRID_PER_SAMPLE + 1;
        let rows = grid_rows(path, rig, share);
        let ceilings = speed_ceilings(path, rig, dt);
        // Backward: the largest u at each point from which the end, at rest, stays reachable.
        let mut high = vec![0.0; points];
        for i in (0..points.saturating_sub(1)).rev() {
            high[i] = largest_controllable(&rows[i], ceilings[i], high[i + 1], step);
        }
        // Forward: from rest, the largest acceleration the next point's bound allows.
        let mut u = vec![0.0; points];
        let mut times = vec![0.0; points];
        for i in 0..points.saturating_sub(1) {
            let (low_a, high_a) = acceleration_interval(&rows[i], u[i], high[i + 1], step);
            let a = if low_a <= high_a {
                high_a
            } else {
                low_a.min(0.0)
            };
            u[i + 1] = (u[i] + 2.0 * step * a).clamp(0.0, high[i + 1]);
            let rate = u[i].sqrt() + u[i + 1].sqrt();
            if rate <= 0.0 {
                return Err(RetimeError::Corner {
                    sample: i / GRID_PER_SAMPLE,
                });
            }
            times[i + 1] = times[i] + 2.0 * step / rate;
        }
        Ok(TimeLaw { step, u, times })
    }

    /// Samples the law every `dt` seconds (the last at the path's end, at rest) and the
    /// largest acceleration ratio of the result.
    fn resample(&self, path: &Path, rig: &Rig, dt: f64) -> Retimed {
        let dof = path.dof;
        let end = *self.times.last().unwrap_or(&0.0);
        let count = (end / dt).ceil() as usize + 1;
        let last_s = path.len.saturating_sub(1) as f64;
        let mut positions = Vec::with_capacity(count * dof);
        let mut i = 0;
        for j in 0..count {
            let t = j as f64 * dt;
            while i + 1 < self.times.len() && self.times[i + 1] <= t {
                i += 1;
            }
            let s = if i + 1 >= self.times.len() || j + 1 == count {
                last_s
            } else {
                let tau = t - self.times[i];
                let a = (self.u[i + 1] - self.u[i]) / (2.0 * self.step);
                let s0 = i as f64 * self.step;
                (s0 + self.u[i].sqrt() * tau + 0.5 * a * tau * tau).clamp(s0, s0 + self.step)
            };
            positions.extend((0..dof).map(|axis| path.position(s, axis)));
        }
        let sample_times_s = self
            .times
            .iter()
            .step_by(GRID_PER_SAMPLE)
            .copied()
            .collect();
        let peak_ratio = peak_ratio(&positions, rig, dt);
        Retimed {
            positions,
            sample_times_s,
            peak_ratio,
        }
    }
}

/// Every grid point's rows: each axis once inside an interval, twice at a sample (the
/// second derivative of either interval meeting there).
fn grid_rows(path: &Path, rig: &Rig, share: f64) -> Vec<Vec<Row>> {
    let points = (path.len.saturating_sub(1)) * GRID_PER_SAMPLE + 1;
    (0..points)
        .map(|i| {
            let (k, j) = (i / GRID_PER_SAMPLE, i % GRID_PER_SAMPLE);
            let t = j as f64 / GRID_PER_SAMPLE as f64;
            let mut rows = Vec::with_capacity(2 * path.dof);
            for (axis, joint) in rig.joints.iter().enumerate() {
                let limit = share * joint.limits.max_acceleration;
                if k + 1 < path.len {
                    let [_, qs, qss] = path.derivatives(k, axis, t);
                    rows.push(Row { qs, qss, limit });
                }
                if j == 0 && k > 0 {
                    let [_, qs, qss] = path.derivatives(k - 1, axis, 1.0);
                    rows.push(Row { qs, qss, limit });
                }
            }
            rows
        })
        .collect()
}

/// Per grid point, the largest u: one sample per period, and every axis within max speed.
fn speed_ceilings(path: &Path, rig: &Rig, dt: f64) -> Vec<f64> {
    let points = (path.len.saturating_sub(1)) * GRID_PER_SAMPLE + 1;
    let planned = 1.0 / (dt * dt);
    (0..points)
        .map(|i| {
            let (k, j) = (i / GRID_PER_SAMPLE, i % GRID_PER_SAMPLE);
            let (k, t) = if k + 1 < path.len {
                (k, j as f64 / GRID_PER_SAMPLE as f64)
            } else {
                (k.saturating_sub(1), 1.0)
            };
            rig.joints
                .iter()
                .enumerate()
                .filter(|_| path.len > 1)
                .map(|(axis, joint)| {
                    let qs = path.derivatives(k, axis, t)[1].abs();
                    let speed = joint.limits.max_speed;
                    if qs > 0.0 {
                        (speed / qs).powi(2)
                    } else {
                        f64::INFINITY
                    }
                })
                .fold(planned, f64::min)
        })
        .collect()
}

/// The accelerations a = d(u)/(2 ds) at a point with `u` that keep every row and land the
/// next point's u in [0, `next_high`], as (least, greatest); empty if least > greatest.
fn acceleration_interval(rows: &[Row], u: f64, next_high: f64, step: f64) -> (f64, f64) {
    let mut low = -u / (2.0 * step);
    let mut high = (next_high - u) / (2.0 * step);
    for row in rows {
        let rest = row.qss * u;
        if row.qs.abs() < f64::EPSILON * row.limit.max(1.0) {
            if rest.abs() > row.limit {
                return (1.0, -1.0);
            }
            continue;
        }
        let (a, b) = ((-row.limit - rest) / row.qs, (row.limit - rest) / row.qs);
        low = low.max(a.min(b));
        high = high.min(a.max(b));
    }
    (low, high)
}

/// The largest u in [0, `ceiling`] with some acceleration keeping every row and the next
/// point within [0, `next_high`]. Those u are an interval from 0 (u = 0, a = 0 keeps every
/// row), so a bisection finds its top.
fn largest_controllable(rows: &[Row], ceiling: f64, next_high: f64, step: f64) -> f64 {
    let feasible = |u: f64| {
        let (low, high) = acceleration_interval(rows, u, next_high, step);
        low <= high
    };
    if feasible(ceiling) {
        return ceiling;
    }
    let (mut low, mut high) = (0.0, ceiling);
    for _ in 0..BISECTION_STEPS {
        let middle = 0.5 * (low + high);
        if feasible(middle) {
            low = middle;
        } else {
            high = middle;
        }
    }
    low
}

/// The largest |p[k+1] - 2 p[k] + p[k-1]| / (max acceleration x `dt`^2) of any axis, `dt`
/// the period in seconds.
fn peak_ratio(positions: &[f64], rig: &Rig, dt: f64) -> f64 {
    let dof = rig.dof();
    let len = positions.len() / dof.max(1);
    let dt2 = dt * dt;
    let mut peak: f64 = 0.0;
    for k in 1..len.saturating_sub(1) {
        for (axis, joint) in rig.joints.iter().enumerate() {
            let p = |i: usize| positions[i * dof + axis];
            let second = p(k + 1) - 2.0 * p(k) + p(k - 1);
            peak = peak.max(second.abs() / (joint.limits.max_acceleration * dt2));
        }
    }
    peak
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rig::{Joint, JointKind, JointLimits};
    use crate::trajectory::{Trajectory, validate};
    use glam::{DAffine3, DVec3};

    const PERIOD_S: f64 = 0.004;
    const SHARE: f64 = 0.8;

    fn rig(axes: usize, upper: f64) -> Rig {
        Rig {
            name: "slides".into(),
            base_frame: "base".into(),
            tool_frame: "tool".into(),
            joints: (0..axes)
                .map(|axis| Joint {
                    name: format!("x{axis}"),
                    kind: JointKind::Prismatic,
                    origin: DAffine3::IDENTITY,
                    axis: DVec3::X,
                    limits: JointLimits {
                        lower: -1.0,
                        upper,
                        max_speed: 0.5,
                        max_acceleration: 2.0,
                    },
                })
                .collect(),
            tool: DAffine3::IDENTITY,
            bodies: Vec::new(),
            allowed_pairs: Vec::new(),
        }
    }

    /// `samples` with central-difference velocities, zero at both ends, as the gait builds.
    fn trajectory(rig: &Rig, positions: &[f64]) -> Trajectory {
        let dof = rig.dof();
        let len = positions.len() / dof;
        let mut velocities = vec![0.0; positions.len()];
        for k in 1..len - 1 {
            for axis in 0..dof {
                velocities[k * dof + axis] = (positions[(k + 1) * dof + axis]
                    - positions[(k - 1) * dof + axis])
                    / (2.0 * PERIOD_S);
            }
        }
        let names = rig.joints.iter().map(|j| j.name.clone()).collect();
        Trajectory::new(
            rig.name.clone(),
            names,
            Duration::from_secs_f64(PERIOD_S),
            positions.to_vec(),
            velocities,
        )
        .expect("whole samples")
    }

    /// At rest, then at `speed` from one sample to the next (an unbounded acceleration),
    /// then at rest again at `to`: axis 1 follows axis 0 at `ratio`.
    fn abrupt_line(speed: f64, to: f64, ratio: f64) -> Vec<f64> {
        let step = speed * PERIOD_S;
        let moving = (to / step).ceil() as usize;
        let mut path = Vec::new();
        for k in 0..50 + moving + 50 {
            let x = (k.saturating_sub(50) as f64 * step).min(to);
            path.extend([x, ratio * x]);
        }
        path
    }

    #[test]
    fn an_abrupt_start_and_stop_is_slowed_into_the_share_along_the_same_line() {
        let rig = rig(2, 1.0);
        let path = abrupt_line(0.4, 0.3, -0.5);
        assert!(validate(&trajectory(&rig, &path), &rig).is_err());
        let retimed =
            retime(&path, &rig, Duration::from_secs_f64(PERIOD_S), SHARE).expect("retimes");
        assert!(retimed.peak_ratio <= SHARE, "{}", retimed.peak_ratio);
        validate(&trajectory(&rig, &retimed.positions), &rig).expect("valid");
        // Past a corner of the samples the cubic may overshoot by up to 4/27 of its
        // tangent there (half a step): never more than a quarter of a step.
        let slack = 0.25 * 0.4 * PERIOD_S;
        for sample in retimed.positions.chunks(2) {
            // Every new sample lies on the planned line, between its ends.
            assert!((sample[1] + 0.5 * sample[0]).abs() < 1e-12, "{sample:?}");
            assert!((-slack..=0.3 + slack).contains(&sample[0]), "{sample:?}");
        }
        let last = retimed.positions.len() - 2;
        assert_eq!(&retimed.positions[..2], &path[..2]);
        assert_eq!(&retimed.positions[last..], &path[path.len() - 2..]);
        // 0.4 m/s reached from rest at 1.6 m/s^2 takes 0.25 s each way: longer than planned.
        let planned = (path.len() / 2 - 1) as f64 * PERIOD_S;
        let now = (retimed.positions.len() / 2 - 1) as f64 * PERIOD_S;
        assert!(now > planned + 0.2, "{now} s against {planned} s");
    }

    #[test]
    fn a_gentle_motion_keeps_its_timing() {
        let rig = rig(1, 1.0);
        // A cosine bell of 0.1 m over 2 s: peak acceleration 0.05 pi^2 / 4 = 0.12 m/s^2.
        let path: Vec<f64> = (0..=500)
            .map(|k| 0.05 * (1.0 - (std::f64::consts::PI * k as f64 / 500.0).cos()))
            .collect();
        let retimed =
            retime(&path, &rig, Duration::from_secs_f64(PERIOD_S), SHARE).expect("retimes");
        for (k, t) in retimed.sample_times_s.iter().enumerate() {
            // Never faster than planned, and at most a sample's worth of start-up later.
            assert!(*t >= k as f64 * PERIOD_S - 1e-9, "sample {k} at {t}");
            assert!(*t <= (k + 1) as f64 * PERIOD_S, "sample {k} at {t}");
        }
        assert!(retimed.positions.len().abs_diff(path.len()) <= 1);
    }

    #[test]
    fn a_path_stopping_at_a_limit_never_passes_it_between_samples() {
        let upper = 0.2;
        let rig = rig(1, upper);
        // Runs into the upper limit at full speed and stays there: a central-difference
        // interpolant would overshoot it in the first interval at the limit.
        let path: Vec<f64> = (0..200)
            .map(|k| (k as f64 * 0.45 * PERIOD_S).min(upper))
            .collect();
        let retimed =
            retime(&path, &rig, Duration::from_secs_f64(PERIOD_S), SHARE).expect("retimes");
        assert!(
            retimed.positions.iter().all(|x| *x <= upper),
            "past the limit"
        );
        validate(&trajectory(&rig, &retimed.positions), &rig).expect("valid");
    }

    #[test]
    fn ragged_samples_and_shares_outside_zero_to_one_are_refused() {
        let rig = rig(2, 1.0);
        assert!(matches!(
            retime(&[0.0; 3], &rig, Duration::from_secs_f64(PERIOD_S), SHARE),
            Err(RetimeError::Ragged {
                values: 3,
                dof: 2,
                ..
            })
        ));
        for share in [0.0, 1.5, f64::NAN] {
            assert!(matches!(
                retime(&[0.0; 4], &rig, Duration::from_secs_f64(PERIOD_S), share),
                Err(RetimeError::BadShare { .. })
            ));
        }
        assert!(matches!(
            retime(&[0.0; 4], &rig, Duration::ZERO, SHARE),
            Err(RetimeError::BadPeriod { .. })
        ));
    }
}
