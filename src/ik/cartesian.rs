//! Linear Cartesian moves: the tool goes in a straight line (orientation by slerp) from pose
//! to pose, solved into a joint path that the `trajectory` stage then times within the
//! rig's speed and acceleration limits (`trajectory/path.rs`).
//!
//! Owns sampling the line, solving every sample (seeded by the previous one, so the arm
//! stays on one branch), refining the joint path where it bends, refusing lines the arm
//! cannot follow, and solving the timed samples again on the line. Must not change the rig
//! or the solver, nor time the path itself, and never bends a line to make it fit: an
//! unreachable sample or a branch switch fails the whole plan.

use super::{IkError, IkSolver};
use crate::rig::{JointKind, Pose, PoseError, Rig, rotation_angle_between};
use crate::trajectory::{
    AxisLimits, JointPath, PathNode, PathTiming, PlanError, PlanSettings, Samples, Trajectory,
    check_start,
};
use thiserror::Error;

/// Joint deviation (rad, or m) from a piece's chord above which the piece is halved, at
/// most [`MAX_HALVINGS`] times. Small enough that the profile's picture of the path's
/// bends is close to the truth; the timing's check of its samples (`trajectory/path.rs`) covers
/// what is left.
const CHORD_TOLERANCE: f64 = 1e-5;
const MAX_HALVINGS: u32 = 6;

/// Why a Cartesian plan is refused: the line's own problems here, the timing's and the
/// input checks' as the [`PlanError`] they share with joint moves.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum CartesianError {
    #[error(transparent)]
    Plan(#[from] PlanError),
    #[error("waypoint {waypoint}: {error}")]
    InvalidPose { waypoint: usize, error: PoseError },
    #[error(
        "move to waypoint {waypoint}: target {sample_pose} ({:.1}% of the way) is unreachable: {error}",
        u * 100.0
    )]
    Unreachable {
        waypoint: usize,
        /// Boxed to keep every `Result<_, CartesianError>` small.
        sample_pose: Box<Pose>,
        /// Where on the line the sample lies: 0 at its start, 1 at the waypoint.
        u: f64,
        error: IkError,
    },
    #[error(
        "move to waypoint {waypoint}: {joint} jumps {:.3} {unit} between two samples (at most {:.3} {unit}) {:.1}% of the way: branch switch or singularity",
        kind.to_user(*jump), kind.to_user(*max_jump), u * 100.0, unit = kind.unit()
    )]
    Discontinuity {
        waypoint: usize,
        joint: String,
        /// SI units (radians or metres); the message shows them in the user's unit.
        jump: f64,
        max_jump: f64,
        kind: JointKind,
        /// Where on the line the later sample lies: 0 at its start, 1 at the waypoint.
        u: f64,
    },
}

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
/// [`CartesianError::Unreachable`], a joint jumping more than `settings.max_joint_jump`
/// between samples is [`CartesianError::Discontinuity`].
pub fn plan_cartesian(
    solver: &dyn IkSolver,
    start: &[f64],
    waypoints: &[Pose],
    settings: &PlanSettings,
) -> Result<Trajectory, CartesianError> {
    plan_cartesian_marked(solver, start, waypoints, settings).map(|(trajectory, _)| trajectory)
}

/// [`plan_cartesian`], with the sample each line ends at (one per waypoint, in order): what
/// a refusal of the planned motion names as its source.
pub fn plan_cartesian_marked(
    solver: &dyn IkSolver,
    start: &[f64],
    waypoints: &[Pose],
    settings: &PlanSettings,
) -> Result<(Trajectory, Vec<usize>), CartesianError> {
    settings.check()?;
    let rig = solver.rig();
    let limits = AxisLimits::new(rig, settings)?;
    check_start(rig, start)?;
    let targets = waypoints
        .iter()
        .enumerate()
        .map(|(waypoint, pose)| {
            pose.validated()
                .map_err(|error| CartesianError::InvalidPose { waypoint, error })
        })
        .collect::<Result<Vec<_>, _>>()?;
    let mut from = start_pose(rig, start)?;
    let mut joints = start.to_vec();
    let mut samples = Samples::at_rest(start, settings.budget, settings.period);
    let mut marks = Vec::with_capacity(targets.len());
    for (waypoint, to) in targets.into_iter().enumerate() {
        let line = Line { from, to };
        let mov = LinearMove {
            solver,
            settings,
            waypoint,
            line,
        };
        let path = mov.dense_path(&joints)?;
        if path.nodes().len() > 1 {
            let timing = PathTiming {
                rig,
                settings,
                limits: &limits,
                waypoint,
            };
            timing.append(&path, |u, seed| mov.solve_on_line(u, seed), &mut samples)?;
            joints = path.end().to_vec();
        }
        marks.push(samples.last_index());
        from = to;
    }
    Ok((samples.finish(rig, settings.period)?, marks))
}

/// The joints along the straight tool line from `from` to `to`, from `start` (the joints
/// at `from`), untimed: the line solved sample by sample and refined where it bends, as
/// [`plan_cartesian`] solves it; the first entry is `start`. `waypoint` names the line in
/// an error. A program (`job/program/`) joins such paths with others and times them
/// together, so that it can pass a point without stopping.
pub fn line_joint_path(
    solver: &dyn IkSolver,
    start: &[f64],
    from: Pose,
    to: Pose,
    settings: &PlanSettings,
    waypoint: usize,
) -> Result<Vec<Vec<f64>>, CartesianError> {
    settings.check()?;
    check_start(solver.rig(), start)?;
    let to = to
        .validated()
        .map_err(|error| CartesianError::InvalidPose { waypoint, error })?;
    let mov = LinearMove {
        solver,
        settings,
        waypoint,
        line: Line { from, to },
    };
    let path = mov.dense_path(start)?;
    Ok(path
        .nodes()
        .iter()
        .map(|node| node.joints.clone())
        .collect())
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

/// One line of the plan, ending at waypoint `waypoint`.
struct LinearMove<'a> {
    solver: &'a dyn IkSolver,
    settings: &'a PlanSettings,
    waypoint: usize,
    line: Line,
}

impl LinearMove<'_> {
    fn solve(&self, u: f64, seed: &[f64]) -> Result<Vec<f64>, CartesianError> {
        let pose = self.line.at(u);
        self.solver
            .solve(&pose, seed)
            .map(|solution| solution.joints)
            .map_err(|error| CartesianError::Unreachable {
                waypoint: self.waypoint,
                sample_pose: Box::new(pose),
                u,
                error,
            })
    }

    /// A timed sample solved on the line at `u` from `seed` (its point on the polyline the
    /// profile was planned on), refused if the solver jumped away from it.
    fn solve_on_line(&self, u: f64, seed: &[f64]) -> Result<Vec<f64>, CartesianError> {
        let joints = self.solve(u, seed)?;
        self.check_jump(u, seed, &joints)?;
        Ok(joints)
    }

    /// The step from `from` to `to`, the joints at `u`, refused if an axis jumps.
    fn check_jump(&self, u: f64, from: &[f64], to: &[f64]) -> Result<(), CartesianError> {
        let max_jump = self.settings.max_joint_jump;
        let rig = self.solver.rig();
        match from
            .iter()
            .zip(to)
            .position(|(a, b)| (b - a).abs() > max_jump)
        {
            Some(axis) => Err(CartesianError::Discontinuity {
                waypoint: self.waypoint,
                joint: rig.joints[axis].name.clone(),
                jump: to[axis] - from[axis],
                max_jump,
                kind: rig.joints[axis].kind,
                u,
            }),
            None => Ok(()),
        }
    }

    /// The joint path of the line from `start` (the joints at `u` = 0): the line's samples,
    /// then pieces split where the joint path bends away from their chord.
    fn dense_path(&self, start: &[f64]) -> Result<JointPath, CartesianError> {
        let samples = self.line_samples(start)?;
        let mut path = JointPath::starting_at(samples[0].clone());
        for pair in samples.windows(2) {
            self.refine(&pair[0], &pair[1], 0, &mut path)?;
        }
        Ok(path)
    }

    /// Solves the line sample by sample from `start`. A jump is reported only once the rest
    /// of the line proves reachable: joint rates grow without bound as the arm stretches
    /// toward the edge of its workspace, so a line that leaves the workspace jumps just
    /// before it, and the useful answer is where reach ends.
    fn line_samples(&self, start: &[f64]) -> Result<Vec<PathNode>, CartesianError> {
        let steps = self.line.steps(self.settings);
        let mut nodes = Vec::with_capacity(steps + 1);
        nodes.push(PathNode {
            u: 0.0,
            joints: start.to_vec(),
        });
        let mut first_jump = None;
        for step in 1..=steps {
            let u = step as f64 / steps as f64;
            let previous = &nodes[nodes.len() - 1].joints;
            let joints = self.solve(u, previous)?;
            if let Err(jump) = self.check_jump(u, previous, &joints) {
                first_jump.get_or_insert(jump);
            }
            nodes.push(PathNode { u, joints });
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
        a: &PathNode,
        b: &PathNode,
        depth: u32,
        path: &mut JointPath,
    ) -> Result<(), CartesianError> {
        if depth < MAX_HALVINGS {
            let u = (a.u + b.u) / 2.0;
            let chord: Vec<f64> = a
                .joints
                .iter()
                .zip(&b.joints)
                .map(|(p, q)| (p + q) / 2.0)
                .collect();
            let joints = self.solve(u, &chord)?;
            self.check_jump(u, &chord, &joints)?;
            let stray = joints
                .iter()
                .zip(&chord)
                .map(|(p, q)| (p - q).abs())
                .fold(0.0, f64::max);
            if stray > CHORD_TOLERANCE {
                let middle = PathNode { u, joints };
                self.refine(a, &middle, depth + 1, path)?;
                return self.refine(&middle, b, depth + 1, path);
            }
        }
        path.push(b.u, b.joints.clone());
        Ok(())
    }
}
