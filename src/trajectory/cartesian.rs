//! Linear Cartesian moves: the tool goes in a straight line (orientation by slerp) from pose
//! to pose, and the joint path that does it is timed within the rig's speed and
//! acceleration limits.
//!
//! Owns sampling the line, solving every sample (seeded by the previous one, so the arm
//! stays on one branch), refusing lines the arm cannot follow, and the speed profile along
//! the resulting joint path. Must not change the rig or the solver, and never bends a line
//! to make it fit: an unreachable sample or a branch switch fails the whole plan.

use super::Trajectory;
use super::plan::{AxisLimits, PlanError, PlanSettings, Samples, check_start, snap_to_limits};
use crate::ik::IkSolver;
use crate::rig::{Pose, Rig, rotation_angle_between};

/// Share of each axis' (scaled) acceleration spent speeding up and slowing down along the
/// path; the rest is kept for the acceleration the path's own bending costs at speed
/// (joint paths of straight tool lines are curved).
const TANGENTIAL_SHARE: f64 = 0.75;

/// Joint deviation (rad, or m) from a piece's chord above which the piece is halved, at
/// most [`MAX_HALVINGS`] times. Small enough that the profile's picture of the path's
/// bends is close to the truth; the sampled check in `resample` covers what is left.
const CHORD_TOLERANCE: f64 = 1e-5;
const MAX_HALVINGS: u32 = 6;

/// How often a move is slowed down before it is refused, and the extra factor each time so
/// that rounding cannot keep it a hair over the limit.
const MAX_SLOWDOWNS: u32 = 8;
const SLOWDOWN_MARGIN: f64 = 1.001;

/// Linear moves from the tool pose at `start` through each waypoint in turn, stopping at
/// each (a stop costs time but keeps every corner exact and the profile simple).
///
/// Each line is split into samples no farther apart than `settings.cartesian_step_m` and
/// `settings.cartesian_step_rad` (whichever needs more), each solved by `solver` seeded with
/// the previous sample's joints. The joint path through them is timed with the fastest
/// speed profile that keeps every axis within its max speed x `speed_scale` and max
/// acceleration x `accel_scale` (forward and backward passes over the path, at rest at both
/// ends; acceleration-limited, not jerk-limited), then sampled every `settings.period`.
/// Every output sample is solved again on the line itself, so the tool never leaves the
/// line by more than the solver's tolerance. Velocities are the profile's.
///
/// Nothing is returned unless the whole plan works: the first unreachable sample is
/// [`PlanError::Unreachable`], a joint jumping more than `settings.max_joint_jump` between
/// samples is [`PlanError::Discontinuity`].
pub fn plan_cartesian(
    solver: &dyn IkSolver,
    start: &[f64],
    waypoints: &[Pose],
    settings: &PlanSettings,
) -> Result<Trajectory, PlanError> {
    settings.check()?;
    let rig = solver.rig();
    let limits = AxisLimits::new(rig, settings)?;
    check_start(rig, start)?;
    let targets = waypoints
        .iter()
        .enumerate()
        .map(|(waypoint, pose)| {
            pose.validated()
                .map_err(|error| PlanError::InvalidPose { waypoint, error })
        })
        .collect::<Result<Vec<_>, _>>()?;
    let mut from = start_pose(rig, start)?;
    let mut joints = start.to_vec();
    let mut samples = Samples::at_rest(start);
    for (waypoint, to) in targets.into_iter().enumerate() {
        let line = Line { from, to };
        let mov = LinearMove {
            solver,
            settings,
            limits: &limits,
            waypoint,
            line,
        };
        let path = mov.dense_path(&joints)?;
        if path.nodes.len() > 1 {
            let profile = SpeedProfile::new(&path, &limits);
            mov.resample(&path, &profile, &mut samples)?;
            joints = path.end().to_vec();
        }
        from = to;
    }
    samples.finish(rig, settings.period)
}

/// The tool pose at `start` (whose axis count `check_start` has already confirmed).
fn start_pose(rig: &Rig, start: &[f64]) -> Result<Pose, PlanError> {
    rig.tool_pose(start).map_err(|e| PlanError::StartAxisCount {
        rig: rig.name.clone(),
        expected: e.expected,
        got: e.given,
    })
}

/// The straight line between two poses, parameterised by `u` in [0, 1].
#[derive(Debug, Clone, Copy)]
struct Line {
    from: Pose,
    to: Pose,
}

impl Line {
    /// Exact at both ends, so consecutive moves meet on the waypoint itself.
    fn at(&self, u: f64) -> Pose {
        if u <= 0.0 {
            self.from
        } else if u >= 1.0 {
            self.to
        } else {
            Pose::new(
                self.from.position.lerp(self.to.position, u),
                self.from.orientation.slerp(self.to.orientation, u),
            )
        }
    }

    fn steps(&self, settings: &PlanSettings) -> usize {
        let distance = self.from.position_error(&self.to) / settings.cartesian_step_m;
        let angle = rotation_angle_between(self.from.orientation, self.to.orientation)
            / settings.cartesian_step_rad;
        distance.max(angle).ceil() as usize
    }
}

/// A joint configuration on the line at parameter `u`.
#[derive(Debug, Clone)]
struct Node {
    u: f64,
    joints: Vec<f64>,
}

/// The joint path of one line as a polyline through solved samples. Consecutive nodes
/// always differ (a sample that leaves every joint where it was extends the previous node's
/// stretch of the line instead), so every piece has a direction.
#[derive(Debug, Clone)]
struct DensePath {
    nodes: Vec<Node>,
}

impl DensePath {
    fn push(&mut self, u: f64, joints: Vec<f64>) {
        let count = self.nodes.len();
        let last = &mut self.nodes[count - 1];
        if last.joints != joints {
            self.nodes.push(Node { u, joints });
        } else if count > 1 {
            last.u = u;
        }
    }

    fn end(&self) -> &[f64] {
        &self.nodes[self.nodes.len() - 1].joints
    }

    /// Joint change per unit `u` along piece `piece` (node `piece` to `piece + 1`).
    fn direction(&self, piece: usize) -> Vec<f64> {
        let (a, b) = (&self.nodes[piece], &self.nodes[piece + 1]);
        let du = b.u - a.u;
        a.joints
            .iter()
            .zip(&b.joints)
            .map(|(qa, qb)| (qb - qa) / du)
            .collect()
    }
}

/// One line of the plan, ending at waypoint `waypoint`.
struct LinearMove<'a> {
    solver: &'a dyn IkSolver,
    settings: &'a PlanSettings,
    limits: &'a AxisLimits,
    waypoint: usize,
    line: Line,
}

/// Samples of one move after its first (which is the previous move's last).
type Rows = Vec<(Vec<f64>, Vec<f64>)>;

impl LinearMove<'_> {
    fn solve(&self, u: f64, seed: &[f64]) -> Result<Vec<f64>, PlanError> {
        let pose = self.line.at(u);
        self.solver
            .solve(&pose, seed)
            .map(|solution| solution.joints)
            .map_err(|error| PlanError::Unreachable {
                waypoint: self.waypoint,
                sample_pose: Box::new(pose),
                error,
            })
    }

    fn check_jump(&self, from: &[f64], to: &[f64]) -> Result<(), PlanError> {
        let max_jump = self.settings.max_joint_jump;
        let rig = self.solver.rig();
        match from
            .iter()
            .zip(to)
            .position(|(a, b)| (b - a).abs() > max_jump)
        {
            Some(axis) => Err(PlanError::Discontinuity {
                waypoint: self.waypoint,
                joint: rig.joints[axis].name.clone(),
                jump: to[axis] - from[axis],
                max_jump,
            }),
            None => Ok(()),
        }
    }

    /// The joint path of the line from `start` (the joints at `u` = 0): the line's samples,
    /// then pieces split where the joint path bends away from their chord.
    fn dense_path(&self, start: &[f64]) -> Result<DensePath, PlanError> {
        let samples = self.line_samples(start)?;
        let mut path = DensePath {
            nodes: vec![samples[0].clone()],
        };
        for pair in samples.windows(2) {
            self.refine(&pair[0], &pair[1], 0, &mut path)?;
        }
        Ok(path)
    }

    /// Solves the line sample by sample from `start`. A jump is reported only once the rest
    /// of the line proves reachable: joint rates grow without bound as the arm stretches
    /// toward the edge of its workspace, so a line that leaves the workspace jumps just
    /// before it, and the useful answer is where reach ends.
    fn line_samples(&self, start: &[f64]) -> Result<Vec<Node>, PlanError> {
        let steps = self.line.steps(self.settings);
        let mut nodes = Vec::with_capacity(steps + 1);
        nodes.push(Node {
            u: 0.0,
            joints: start.to_vec(),
        });
        let mut first_jump = None;
        for step in 1..=steps {
            let u = step as f64 / steps as f64;
            let previous = &nodes[nodes.len() - 1].joints;
            let joints = self.solve(u, previous)?;
            if let Err(jump) = self.check_jump(previous, &joints) {
                first_jump.get_or_insert(jump);
            }
            nodes.push(Node { u, joints });
        }
        match first_jump {
            Some(jump) => Err(jump),
            None => Ok(nodes),
        }
    }

    /// Appends the nodes after `a` up to `b`, halving the piece while the joints solved at
    /// its middle stray from the chord: the speed profile reads the path's bends from the
    /// polyline, and near a singularity one line step hides most of a bend.
    fn refine(
        &self,
        a: &Node,
        b: &Node,
        depth: u32,
        path: &mut DensePath,
    ) -> Result<(), PlanError> {
        if depth < MAX_HALVINGS {
            let u = (a.u + b.u) / 2.0;
            let chord: Vec<f64> = a
                .joints
                .iter()
                .zip(&b.joints)
                .map(|(p, q)| (p + q) / 2.0)
                .collect();
            let joints = self.solve(u, &chord)?;
            self.check_jump(&chord, &joints)?;
            let stray = joints
                .iter()
                .zip(&chord)
                .map(|(p, q)| (p - q).abs())
                .fold(0.0, f64::max);
            if stray > CHORD_TOLERANCE {
                let middle = Node { u, joints };
                self.refine(a, &middle, depth + 1, path)?;
                return self.refine(&middle, b, depth + 1, path);
            }
        }
        path.push(b.u, b.joints.clone());
        Ok(())
    }

    /// Appends samples every period along `profile`, the last one at the path's end. The
    /// samples are solved on the line itself, so they follow the true joint path rather than
    /// the polyline the profile was planned on; where that costs more speed or acceleration
    /// than the scaled limits allow, the whole move is slowed down until it does not.
    fn resample(
        &self,
        path: &DensePath,
        profile: &SpeedProfile,
        samples: &mut Samples,
    ) -> Result<(), PlanError> {
        let mut slowdown = 1.0;
        let mut attempts = 0;
        let rows = loop {
            let rows = self.sample(path, profile, slowdown)?;
            let excess = self.excess(&path.nodes[0].joints, &rows);
            attempts += 1;
            if excess.ratio <= 1.0 {
                break rows;
            }
            if attempts == MAX_SLOWDOWNS {
                return Err(PlanError::OverLimits {
                    waypoint: self.waypoint,
                    joint: self.solver.rig().joints[excess.axis].name.clone(),
                    ratio: excess.ratio,
                });
            }
            // Slowing a path down by s divides speeds by s and accelerations by s^2.
            slowdown *= excess.ratio * SLOWDOWN_MARGIN;
        };
        for (positions, velocities) in &rows {
            samples.push(positions, velocities);
        }
        Ok(())
    }

    /// One sampling of the profile, `slowdown` times slower.
    fn sample(
        &self,
        path: &DensePath,
        profile: &SpeedProfile,
        slowdown: f64,
    ) -> Result<Rows, PlanError> {
        let period_s = self.settings.period.as_secs_f64();
        // Whole periods: stretch the profile (slower, so still within limits) to end on one;
        // the 1e-9 keeps a duration a rounding hair over a whole number from adding a period.
        let duration = profile.duration * slowdown;
        let periods = ((duration / period_s - 1e-9).ceil() as usize).max(1);
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
            let mut joints = self.solve(node.u + along, &seed)?;
            self.check_jump(&seed, &joints)?;
            snap_to_limits(self.solver.rig(), &mut joints);
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
    fn new(path: &DensePath, limits: &AxisLimits) -> Self {
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
            .map(|d| allowed(d, &limits.speed))
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
