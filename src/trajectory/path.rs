//! Timing a joint path: the fastest speed profile along a path of joint positions (given
//! as a polyline over a path parameter `u` in [0, 1]) within the rig's scaled speeds and
//! accelerations, sampled every period. The `ik` stage's Cartesian lines are such paths
//! (`ik/cartesian.rs` solves them); the samples of the timed path are solved again on the
//! true path by the caller's `solve_at`, so they follow it rather than the polyline.
//!
//! Owns the speed profile, the sampling, the check of the samples' own speeds and
//! accelerations and the slowing down until they pass. Must not solve IK (the caller does,
//! through `solve_at`) nor change the path: a path that cannot be timed within the limits
//! fails with [`PlanError::OverLimits`].

use super::plan::{AxisLimits, PlanError, PlanSettings, Samples, snap_to_limits};
use crate::rig::Rig;

/// Share of each axis' (scaled) acceleration spent speeding up and slowing down along the
/// path; the rest is kept for the acceleration the path's own bending costs at speed
/// (joint paths of straight tool lines are curved).
const TANGENTIAL_SHARE: f64 = 0.75;

/// How often a move is slowed down before it is refused, and the extra factor each time so
/// that rounding cannot keep it a hair over the limit.
const MAX_SLOWDOWNS: u32 = 8;
const SLOWDOWN_MARGIN: f64 = 1.001;

/// A joint configuration on the path at parameter `u`.
#[derive(Debug, Clone)]
pub(crate) struct PathNode {
    pub u: f64,
    pub joints: Vec<f64>,
}

/// A joint path as a polyline through solved samples. Consecutive nodes always differ (a
/// sample that leaves every joint where it was extends the previous node's stretch of the
/// path instead), so every piece has a direction.
#[derive(Debug, Clone)]
pub(crate) struct JointPath {
    nodes: Vec<PathNode>,
    /// Per node, the share of the scaled speed limits the piece ending at it may use (a
    /// program step's `speed`); 1 for a path that asks for no less. The first is unused.
    shares: Vec<f64>,
}

impl JointPath {
    /// The path of its first node alone.
    pub fn starting_at(first: PathNode) -> Self {
        Self {
            nodes: vec![first],
            shares: vec![1.0],
        }
    }

    pub fn push(&mut self, u: f64, joints: Vec<f64>) {
        self.push_at_share(u, joints, 1.0);
    }

    /// [`JointPath::push`], the piece to the new node at `share` (in (0, 1]) of the scaled
    /// speed limits.
    pub fn push_at_share(&mut self, u: f64, joints: Vec<f64>, share: f64) {
        let count = self.nodes.len();
        let last = &mut self.nodes[count - 1];
        if last.joints != joints {
            self.nodes.push(PathNode { u, joints });
            self.shares.push(share);
        } else if count > 1 {
            last.u = u;
        }
    }

    pub fn nodes(&self) -> &[PathNode] {
        &self.nodes
    }

    pub fn end(&self) -> &[f64] {
        &self.nodes[self.nodes.len() - 1].joints
    }

    /// The share of the scaled speed limits the piece ending at node `node` may use.
    pub(super) fn share(&self, node: usize) -> f64 {
        self.shares[node]
    }

    /// Joint change per unit `u` along piece `piece` (node `piece` to `piece + 1`).
    pub(super) fn direction(&self, piece: usize) -> Vec<f64> {
        let (a, b) = (&self.nodes[piece], &self.nodes[piece + 1]);
        let du = b.u - a.u;
        a.joints
            .iter()
            .zip(&b.joints)
            .map(|(qa, qb)| (qb - qa) / du)
            .collect()
    }
}

/// The timing of one move of a plan along a path, ending at waypoint `waypoint`.
pub(crate) struct PathTiming<'a> {
    pub rig: &'a Rig,
    pub settings: &'a PlanSettings,
    pub limits: &'a AxisLimits,
    pub waypoint: usize,
}

/// Samples of one move after its first (which is the previous move's last).
type Rows = Vec<(Vec<f64>, Vec<f64>)>;

impl PathTiming<'_> {
    /// Appends samples every period along the fastest profile of `path` (at rest at both
    /// ends), the last one at the path's end. Each sample is `solve_at(u, seed)`: the joints
    /// on the true path at `u`, near `seed` (the polyline's point there), so the samples
    /// follow the true path rather than the polyline the profile was planned on; where that
    /// costs more speed or acceleration than the scaled limits allow, the whole move is
    /// slowed down until it does not. `path` must have two nodes or more.
    pub fn append<E: From<PlanError>>(
        &self,
        path: &JointPath,
        solve_at: impl Fn(f64, &[f64]) -> Result<Vec<f64>, E>,
        samples: &mut Samples,
    ) -> Result<(), E> {
        for (positions, velocities) in &self.timed_rows(path, solve_at, samples)? {
            samples.push(positions, velocities);
        }
        Ok(())
    }

    /// The samples of the fastest profile of `path` that keeps within the limits (after
    /// its first node, the last at its end, at rest), not yet appended: a caller that
    /// combines moves (a program's zones) takes them from here.
    pub(crate) fn timed_rows<E: From<PlanError>>(
        &self,
        path: &JointPath,
        solve_at: impl Fn(f64, &[f64]) -> Result<Vec<f64>, E>,
        samples: &Samples,
    ) -> Result<Rows, E> {
        let profile = SpeedProfile::new(path, self.limits);
        let mut slowdown = 1.0;
        let mut attempts = 0;
        loop {
            let rows = self.sample(path, &profile, slowdown, &solve_at, samples)?;
            let excess = self.excess(&path.nodes[0].joints, &rows);
            attempts += 1;
            if excess.ratio <= 1.0 {
                return Ok(rows);
            }
            if attempts == MAX_SLOWDOWNS {
                return Err(PlanError::OverLimits {
                    waypoint: self.waypoint,
                    joint: self.rig.joints[excess.axis].name.clone(),
                    ratio: excess.ratio,
                    limit: "speed or acceleration",
                }
                .into());
            }
            // Slowing a path down by s divides speeds by s and accelerations by s^2.
            slowdown *= excess.ratio * SLOWDOWN_MARGIN;
        }
    }

    /// One sampling of the profile, `slowdown` times slower.
    fn sample<E>(
        &self,
        path: &JointPath,
        profile: &SpeedProfile,
        slowdown: f64,
        solve_at: &impl Fn(f64, &[f64]) -> Result<Vec<f64>, E>,
        samples: &Samples,
    ) -> Result<Rows, E>
    where
        E: From<PlanError>,
    {
        let period_s = self.settings.period.as_secs_f64();
        // Whole periods: stretch the profile (slower, so still within limits) to end on one;
        // the 1e-9 keeps a duration a rounding hair over a whole number from adding a period.
        let duration = profile.duration * slowdown;
        let periods = ((duration / period_s - 1e-9).ceil() as usize).max(1);
        samples.ensure_room(periods).map_err(PlanError::from)?;
        let stretch = periods as f64 * period_s / profile.duration;
        let mut rows = Vec::with_capacity(periods);
        let mut cursor = 0;
        for k in 1..periods {
            let time = k as f64 * period_s / stretch;
            while cursor + 1 < profile.pieces.len() && profile.pieces[cursor + 1].start_s <= time {
                cursor += 1;
            }
            let piece = &profile.pieces[cursor];
            let (along, speed) = piece.at(time - piece.start_s);
            let direction = path.direction(cursor);
            let node = &path.nodes[cursor];
            let seed: Vec<f64> = node
                .joints
                .iter()
                .zip(&direction)
                .map(|(q, d)| q + d * along)
                .collect();
            let mut joints = solve_at(node.u + along, &seed)?;
            snap_to_limits(self.rig, &mut joints);
            let velocity = direction.iter().map(|d| d * speed / stretch).collect();
            rows.push((joints, velocity));
        }
        rows.push((path.end().to_vec(), vec![0.0; path.end().len()]));
        Ok(rows)
    }

    /// How far the samples' own speed (step / period) and acceleration (second difference /
    /// period^2) go past the scaled limits, as the slowdown that would cure it (at most 1
    /// when they stay within). The move starts and ends at rest; its first and last steps
    /// may use half the acceleration, as the neighbouring move may use the other half.
    fn excess(&self, start: &[f64], rows: &Rows) -> Excess {
        let period_s = self.settings.period.as_secs_f64();
        let mut positions: Vec<&[f64]> = vec![start, start];
        positions.extend(rows.iter().map(|(p, _)| p.as_slice()));
        let end = positions[positions.len() - 1];
        positions.push(end);
        let mut worst = Excess {
            ratio: 0.0,
            axis: 0,
        };
        let last = positions.len() - 3;
        for (k, window) in positions.windows(3).enumerate() {
            let (before, here, after) = (window[0], window[1], window[2]);
            let accel_share = if k == 0 || k == last { 0.5 } else { 1.0 };
            for (axis, ((b, h), a)) in before.iter().zip(here).zip(after).enumerate() {
                let speed = (a - h).abs() / period_s / self.limits.speed[axis];
                let accel = (a - 2.0 * h + b).abs()
                    / (period_s * period_s)
                    / (self.limits.acceleration[axis] * accel_share);
                let ratio = speed.max(accel.sqrt());
                if ratio > worst.ratio {
                    worst = Excess { ratio, axis };
                }
            }
        }
        worst
    }
}

/// The worst overshoot of a sampled move and the axis it is on.
struct Excess {
    ratio: f64,
    axis: usize,
}

/// Motion along one piece of the path in `u`: accelerate, cruise, decelerate (any phase
/// may be empty).
#[derive(Debug, Clone, Copy)]
struct Piece {
    start_s: f64,
    length: f64,
    entry: f64,
    peak: f64,
    exit: f64,
    accel: f64,
}

impl Piece {
    fn new(start_s: f64, length: f64, entry: f64, exit: f64, cap: f64, accel: f64) -> Self {
        let unlimited = ((entry * entry + exit * exit + 2.0 * accel * length) / 2.0).sqrt();
        // The passes keep entry and exit reachable from each other; max() only absorbs rounding.
        let peak = unlimited.min(cap).max(entry).max(exit);
        Self {
            start_s,
            length,
            entry,
            peak,
            exit,
            accel,
        }
    }

    fn accel_time(&self) -> f64 {
        (self.peak - self.entry) / self.accel
    }

    fn decel_time(&self) -> f64 {
        (self.peak - self.exit) / self.accel
    }

    fn accel_length(&self) -> f64 {
        (self.peak * self.peak - self.entry * self.entry) / (2.0 * self.accel)
    }

    fn cruise_length(&self) -> f64 {
        let decel_length = (self.peak * self.peak - self.exit * self.exit) / (2.0 * self.accel);
        (self.length - self.accel_length() - decel_length).max(0.0)
    }

    fn duration(&self) -> f64 {
        self.accel_time() + self.cruise_length() / self.peak + self.decel_time()
    }

    /// Distance along the piece and path speed, `time` after its start.
    fn at(&self, time: f64) -> (f64, f64) {
        let (accel_time, cruise_time) = (self.accel_time(), self.cruise_length() / self.peak);
        let (along, speed) = if time <= accel_time {
            (
                self.entry * time + 0.5 * self.accel * time * time,
                self.entry + self.accel * time,
            )
        } else if time <= accel_time + cruise_time {
            (
                self.accel_length() + self.peak * (time - accel_time),
                self.peak,
            )
        } else {
            let t = (time - accel_time - cruise_time).min(self.decel_time());
            (
                self.accel_length() + self.cruise_length() + self.peak * t
                    - 0.5 * self.accel * t * t,
                self.peak - self.accel * t,
            )
        };
        (along.clamp(0.0, self.length), speed.max(0.0))
    }
}

/// The fastest path speed (in `u` per second) that keeps every axis within its limits,
/// as one [`Piece`] per polyline piece.
#[derive(Debug, Clone)]
struct SpeedProfile {
    pieces: Vec<Piece>,
    duration: f64,
}

impl SpeedProfile {
    fn new(path: &JointPath, limits: &AxisLimits) -> Self {
        let directions: Vec<Vec<f64>> = (0..path.nodes.len() - 1)
            .map(|p| path.direction(p))
            .collect();
        let lengths: Vec<f64> = path.nodes.windows(2).map(|w| w[1].u - w[0].u).collect();
        // Path speed and acceleration an axis allows along a direction: its limit over its
        // share of the motion (axes that do not move allow anything).
        let allowed = |direction: &[f64], axis_limits: &[f64]| {
            direction
                .iter()
                .zip(axis_limits)
                .filter(|(d, _)| **d != 0.0)
                .map(|(d, limit)| limit / d.abs())
                .fold(f64::INFINITY, f64::min)
        };
        let caps: Vec<f64> = directions
            .iter()
            .zip(&path.shares[1..])
            .map(|(d, share)| allowed(d, &limits.speed) * share)
            .collect();
        let accels: Vec<f64> = directions
            .iter()
            .map(|d| TANGENTIAL_SHARE * allowed(d, &limits.acceleration))
            .collect();
        let speeds = node_speeds(&directions, &lengths, &caps, &accels, limits);
        let mut pieces = Vec::with_capacity(lengths.len());
        let mut start_s = 0.0;
        for (p, &length) in lengths.iter().enumerate() {
            let piece = Piece::new(
                start_s,
                length,
                speeds[p],
                speeds[p + 1],
                caps[p],
                accels[p],
            );
            start_s += piece.duration();
            pieces.push(piece);
        }
        Self {
            pieces,
            duration: start_s,
        }
    }
}

/// Path speed at each node: at rest at both ends, within both neighbouring pieces' speed
/// caps and the bend's acceleration budget, then reachable under each piece's acceleration
/// from the node before (forward pass) and the node after (backward pass).
fn node_speeds(
    directions: &[Vec<f64>],
    lengths: &[f64],
    caps: &[f64],
    accels: &[f64],
    limits: &AxisLimits,
) -> Vec<f64> {
    let pieces = lengths.len();
    let mut speeds = vec![0.0; pieces + 1];
    for node in 1..pieces {
        let half_span = (lengths[node - 1] + lengths[node]) / 2.0;
        // A direction change of c per unit u at path speed v costs c v^2 of acceleration.
        let bend = directions[node]
            .iter()
            .zip(&directions[node - 1])
            .zip(&limits.acceleration)
            .map(|((after, before), limit)| {
                let curvature = (after - before).abs() / half_span;
                ((1.0 - TANGENTIAL_SHARE) * limit / curvature).sqrt()
            })
            .fold(f64::INFINITY, f64::min);
        speeds[node] = caps[node - 1].min(caps[node]).min(bend);
    }
    for p in 0..pieces {
        let reachable = (speeds[p] * speeds[p] + 2.0 * accels[p] * lengths[p]).sqrt();
        speeds[p + 1] = speeds[p + 1].min(reachable);
    }
    for p in (0..pieces).rev() {
        let reachable = (speeds[p + 1] * speeds[p + 1] + 2.0 * accels[p] * lengths[p]).sqrt();
        speeds[p] = speeds[p].min(reachable);
    }
    speeds
}
