//! A program's ops timed into one trajectory. Each move is timed alone, at rest at both
//! ends, by one jerk-limited S-curve along its joint path (`trajectory/smooth.rs`: every
//! axis within its scaled speed, times the step's `speed`, acceleration and jerk; a move
//! blended at a zone takes half the acceleration and jerk, so that two overlapping moves
//! add up within the limits). A fine point is reached at rest. At a zoned point the next
//! move starts before this one has ended: from the sample where the tool enters the
//! point's zone, the two moves' displacements are added, so the arm turns the corner
//! without stopping, as RAPID starts its corner path where the tool enters the zone (ABB,
//! RAPID Reference Manual, "zonedata"). The overlap is shortened (the corner starts nearer
//! the point) until the sum keeps within every axis' speed, acceleration and jerk; each
//! sample's velocity is the central difference of the positions either side. Every sample
//! passes `validate` before the program is handed on.
//!
//! Owns the joining, the overlaps and the marks that name each step's stretch. Must not
//! change a point a step names (a fine point is reached exactly, a zoned one passed within
//! its zone) nor clamp anything: what does not fit is refused.

use super::steps::{Action, Goal, How, MoveOp, Op, goal_position};
use super::{Neighbour, check_zone_room};
use crate::ik::{CartesianError, FabrikSolver, IkError, IkSolver, line_joint_path};
use crate::job::{JobError, JobInvalid, PlanContext};
use crate::motion::IoPoint;
use crate::rig::{Pose, Rig};
use crate::trajectory::free::plan_free;
use crate::trajectory::{
    AxisLimits, BLENDED_SHARE, JointPath, Origins, PathNode, PlanError, REST_TO_REST_SHARE,
    Samples, SmoothTiming, Trajectory, check_start, differences,
};
use glam::DAffine3;
use std::time::Duration;
use thiserror::Error;

/// A program refused while it is planned, naming the step as written.
#[derive(Debug, Error)]
pub enum ProgramError {
    #[error("{key} ({what}): the target cannot be reached: {error}")]
    Unreachable {
        key: String,
        what: String,
        error: IkError,
    },
    #[error("{key} ({what}): {error}")]
    Line {
        key: String,
        what: String,
        error: CartesianError,
    },
    #[error("{key} ({what}): {error}")]
    Timing {
        key: String,
        what: String,
        error: PlanError,
    },
}

impl From<ProgramError> for JobError {
    fn from(error: ProgramError) -> Self {
        JobError::Program(Box::new(error))
    }
}

/// The joint path of a free move (`move_joints`, `move_poses`) from `from` to `to`: the
/// configurations it passes after `from`, the last `to`. The straight line in joint space
/// when it is clear of the cell (or no cell was given: the gate before motion still checks
/// the whole program); otherwise the free-move planner's way round the cell's objects
/// (`trajectory::free`, issue 29), whose via configurations are then joined, and blended
/// where a step has a zone, like any other point. `key` names the step in a refusal.
pub fn free_move_path(
    context: &PlanContext,
    key: &str,
    from: &[f64],
    to: &[f64],
) -> Result<Vec<Vec<f64>>, JobError> {
    let Some(model) = context.model else {
        return Ok(vec![to.to_vec()]);
    };
    let waypoints =
        plan_free(model, context.rig, from, to, &context.settings.free).map_err(|error| {
            JobError::FreeMove {
                key: key.to_string(),
                error: Box::new(error),
            }
        })?;
    Ok(waypoints.into_iter().skip(1).collect())
}

/// One move of a run: its op, the configurations after the move's start, and how it may go.
struct Piece {
    op: usize,
    nodes: Vec<Vec<f64>>,
    share: f64,
    zone_m: Option<f64>,
    tool: DAffine3,
    /// A `move_linear`: its path is the line's, never split at its nodes.
    linear: bool,
}

/// `ops` timed from `context.start` into one trajectory, each op's stretch named.
pub fn plan_ops(ops: &[Op], context: &PlanContext) -> Result<(Trajectory, Origins), JobError> {
    let settings = context.settings;
    settings.check()?;
    check_start(context.rig, context.start)?;
    let mut planner = Planner {
        context,
        ops,
        solvers: Vec::new(),
        limits: AxisLimits::new(context.rig, settings)?,
        samples: Samples::at_rest(context.start, settings.budget, settings.period),
        marks: Vec::with_capacity(ops.len()),
        io: Vec::new(),
    };
    let mut q = context.start.to_vec();
    let mut run_start = q.clone();
    let mut run: Vec<Piece> = Vec::new();
    for (index, op) in ops.iter().enumerate() {
        match &op.action {
            Action::Move(m) => {
                let nodes = planner.path_to(index, op, m, &q)?;
                if let Some(last) = nodes.last() {
                    q.clone_from(last);
                }
                run.push(Piece {
                    op: index,
                    nodes,
                    share: m.speed,
                    zone_m: m.zone_m,
                    tool: m.tool,
                    linear: m.how == How::Linear,
                });
                if m.zone_m.is_none() {
                    planner.flush(&run_start, std::mem::take(&mut run))?;
                    run_start.clone_from(&q);
                }
            }
            Action::Dwell(duration) => {
                planner.flush(&run_start, std::mem::take(&mut run))?;
                run_start.clone_from(&q);
                planner.dwell(&q, *duration)?;
            }
            Action::Io(action) => {
                planner.flush(&run_start, std::mem::take(&mut run))?;
                run_start.clone_from(&q);
                let sample = planner.samples.last_index();
                planner.io.push(IoPoint {
                    sample,
                    action: action.clone(),
                    step: format!("{} ({})", op.key, op.what),
                });
                planner.marks.push(sample);
            }
        }
    }
    planner.flush(&run_start, run)?;
    let mut origins = Origins::default();
    for (op, mark) in ops.iter().zip(&planner.marks) {
        origins.push(*mark, format!("{} ({})", op.key, op.what));
    }
    let trajectory = planner
        .samples
        .finish(context.rig, settings.period)?
        .with_io(planner.io);
    Ok((trajectory, origins))
}

struct Planner<'a> {
    context: &'a PlanContext<'a>,
    ops: &'a [Op],
    /// One solver per tool a step uses, made when first needed.
    solvers: Vec<(DAffine3, FabrikSolver)>,
    limits: AxisLimits,
    samples: Samples,
    /// Per op, in order: the sample its stretch ends at.
    marks: Vec<usize>,
    /// The I/O steps' points, in order.
    io: Vec<IoPoint>,
}

impl Planner<'_> {
    fn rig_with(&self, tool: DAffine3) -> Rig {
        Rig {
            tool,
            ..self.context.rig.clone()
        }
    }

    fn solver(&mut self, tool: DAffine3) -> Result<&FabrikSolver, JobError> {
        let index = match self.solvers.iter().position(|(t, _)| *t == tool) {
            Some(index) => index,
            None => {
                let solver = FabrikSolver::new(self.rig_with(tool))?;
                self.solvers.push((tool, solver));
                self.solvers.len() - 1
            }
        };
        Ok(&self.solvers[index].1)
    }

    /// The configurations after `q` that move `op` (the `index`-th) passes, to its goal.
    fn path_to(
        &mut self,
        index: usize,
        op: &Op,
        m: &MoveOp,
        q: &[f64],
    ) -> Result<Vec<Vec<f64>>, JobError> {
        let context = self.context;
        let settings = context.settings;
        let refused = |error: String| JobInvalid::new(op.key.clone(), op.what.clone(), error);
        match (m.how, &m.goal) {
            (How::Linear, goal) => {
                let solver = self.solver(m.tool)?;
                let pose_at = |joints: &[f64]| {
                    solver
                        .rig()
                        .tool_pose(joints)
                        .map_err(|e| refused(e.to_string()))
                };
                let from = pose_at(q)?;
                let to: Pose = match goal {
                    Goal::Pose(pose) => *pose,
                    Goal::Joints(joints) => pose_at(joints)?,
                };
                let nodes =
                    line_joint_path(solver, q, from, to, settings, index).map_err(|error| {
                        ProgramError::Line {
                            key: op.key.clone(),
                            what: op.what.clone(),
                            error,
                        }
                    })?;
                Ok(nodes.into_iter().skip(1).collect())
            }
            (_, Goal::Joints(joints)) => free_move_path(context, &op.key, q, joints),
            (_, Goal::Pose(pose)) => {
                let solution = self.solver(m.tool)?.solve(pose, q).map_err(|error| {
                    ProgramError::Unreachable {
                        key: op.key.clone(),
                        what: op.what.clone(),
                        error,
                    }
                })?;
                free_move_path(context, &op.key, q, &solution.joints)
            }
        }
    }

    /// Holds `q` at rest for `duration` (whole periods, rounded up).
    fn dwell(&mut self, q: &[f64], duration: Duration) -> Result<(), JobError> {
        let period = self.context.settings.period.as_secs_f64();
        let count = (duration.as_secs_f64() / period).ceil() as usize;
        self.samples.ensure_room(count).map_err(PlanError::from)?;
        let rest = vec![0.0; q.len()];
        for _ in 0..count {
            self.samples.push(q, &rest);
        }
        self.marks.push(self.samples.last_index());
        Ok(())
    }

    /// Times the run `pieces` from `start` (at rest at both ends): each move alone, the
    /// next starting where the tool enters a zoned point's zone, and marks where each of
    /// its ops ends.
    fn flush(&mut self, start: &[f64], pieces: Vec<Piece>) -> Result<(), JobError> {
        if pieces.is_empty() {
            return Ok(());
        }
        self.check_first_zone(start, &pieces)?;
        let mut from = start.to_vec();
        let mut moves = Vec::with_capacity(pieces.len());
        for (k, piece) in pieces.iter().enumerate() {
            // Blended at its end (its own zone) or its start (the zone before it).
            let blended = piece.zone_m.is_some() || k > 0 && pieces[k - 1].zone_m.is_some();
            let rows = self.time_move(&from, piece, blended)?;
            moves.push(Displacement::of(&from, &rows));
            if let Some(last) = rows.last() {
                from.clone_from(last);
            }
        }
        let mut starts = vec![0usize];
        let mut overlaps = vec![0usize];
        for k in 0..pieces.len() - 1 {
            let entered = match pieces[k].zone_m {
                Some(zone) => self.inside_zone(&moves[k], zone, &pieces[k]),
                None => 0,
            };
            // A move's head and tail overlaps stay apart.
            let room = moves[k].len().saturating_sub(overlaps[k]);
            let mut overlap = entered.min(room).min(moves[k + 1].len());
            let next_start = |overlap: usize| starts[k] + moves[k].len() - overlap;
            while overlap > 0
                && !self.within_limits(
                    start,
                    &moves[..k + 2],
                    &starts,
                    next_start(overlap),
                    next_start(overlap) + overlap,
                )
            {
                // One sample at a time, none skipped: the corner starts as far out in the
                // zone as the limits allow (whether the sum keeps within them does not
                // change in step with the overlap, so a search by halves could miss it).
                overlap -= 1;
            }
            starts.push(next_start(overlap));
            overlaps.push(overlap);
        }
        overlaps.push(0);
        let positions = sum_of(start, &moves, &starts);
        let before = self.samples.last_index();
        let dt = self.context.settings.period.as_secs_f64();
        self.samples
            .ensure_room(positions.len())
            .map_err(PlanError::from)?;
        for k in 0..positions.len() {
            let previous = if k == 0 { start } else { &positions[k - 1] };
            let velocity: Vec<f64> = match positions.get(k + 1) {
                Some(next) => next
                    .iter()
                    .zip(previous)
                    .map(|(n, p)| (n - p) / (2.0 * dt))
                    .collect(),
                None => vec![0.0; start.len()],
            };
            self.samples.push(&positions[k], &velocity);
        }
        for (k, moved) in moves.iter().enumerate() {
            // A fine point's op ends where its move does; a zoned one's in the middle of
            // the overlap, where the arm passes nearest the point.
            let end = (starts[k] + moved.len()).saturating_sub(overlaps[k + 1] / 2);
            self.marks.push(before + end);
        }
        Ok(())
    }

    /// The samples of one move from `from` alone, at rest at both ends (none when it does
    /// not move): one S-curve along its whole path, or where a free move's way round the
    /// cell bends too sharply for that, one from each of its via configurations to the next,
    /// at rest at each (every sample still on the proven path).
    fn time_move(
        &self,
        from: &[f64],
        piece: &Piece,
        blended: bool,
    ) -> Result<Vec<Vec<f64>>, JobError> {
        let share = if blended {
            BLENDED_SHARE
        } else {
            REST_TO_REST_SHARE
        };
        let op = &self.ops[piece.op];
        let refused = |error: PlanError| ProgramError::Timing {
            key: op.key.clone(),
            what: op.what.clone(),
            error,
        };
        match self.time_legs(from, &piece.nodes, piece, share) {
            Err(PlanError::OverLimits { .. }) if !piece.linear && piece.nodes.len() > 1 => {
                let mut rows = Vec::new();
                let mut leg_from = from.to_vec();
                for node in &piece.nodes {
                    let leg = std::slice::from_ref(node);
                    let timed = self.time_legs(&leg_from, leg, piece, share);
                    rows.extend(timed.map_err(refused)?);
                    leg_from.clone_from(node);
                }
                Ok(rows)
            }
            timed => Ok(timed.map_err(refused)?),
        }
    }

    /// The samples of the path from `from` through `nodes` along one S-curve, at rest at
    /// both ends (none when it does not move).
    fn time_legs(
        &self,
        from: &[f64],
        nodes: &[Vec<f64>],
        piece: &Piece,
        share: f64,
    ) -> Result<Vec<Vec<f64>>, PlanError> {
        let mut path = JointPath::starting_at(PathNode {
            u: 0.0,
            joints: from.to_vec(),
        });
        let mut u = 0.0;
        let mut previous = from.to_vec();
        for node in nodes {
            u += distance(&previous, node);
            path.push_at_share(u, node.clone(), piece.share);
            previous.clone_from(node);
        }
        if path.nodes().len() < 2 {
            return Ok(Vec::new());
        }
        let timing = SmoothTiming {
            rig: self.context.rig,
            period: self.context.settings.period,
            limits: &self.limits,
            waypoint: piece.op,
            share,
        };
        timing.rows(&path, &self.samples)
    }

    /// How many of `moved`'s last samples have the tool within `zone` of where the move
    /// ends (its end included): the overlap a zone asks for.
    fn inside_zone(&self, moved: &Displacement, zone: f64, piece: &Piece) -> usize {
        let rig = self.rig_with(piece.tool);
        let tcp = |q: &[f64]| rig.tool_pose(q).map(|p| p.position).ok();
        let Some(end) = moved.end().and_then(|q| tcp(&q)) else {
            return 0;
        };
        (0..moved.len())
            .rev()
            .take_while(|&j| tcp(&moved.absolute(j)).is_some_and(|p| (p - end).length() < zone))
            .count()
    }

    /// Whether the sum of `moves` (each from its start in `starts`, the last from
    /// `last_start`) keeps within every axis' scaled speed, acceleration and jerk over
    /// samples `last_start - 1 ..= until + 1`.
    fn within_limits(
        &self,
        start: &[f64],
        moves: &[Displacement],
        starts: &[usize],
        last_start: usize,
        until: usize,
    ) -> bool {
        let mut all_starts = starts[..moves.len() - 1].to_vec();
        all_starts.push(last_start);
        let at = |t: isize| -> Vec<f64> {
            let mut q = start.to_vec();
            for (moved, &begin) in moves.iter().zip(&all_starts) {
                moved.add_at(t - begin as isize, &mut q);
            }
            q
        };
        let dt = self.context.settings.period.as_secs_f64();
        let window: Vec<Vec<f64>> = (last_start as isize - 3..=until as isize + 3)
            .map(at)
            .collect();
        let limits = &self.limits;
        window.windows(4).all(|w| {
            let w: Vec<&[f64]> = w.iter().map(Vec::as_slice).collect();
            (0..start.len()).all(|axis| {
                let [speed, accel, jerk] = differences(&w, axis, dt);
                speed <= limits.speed[axis]
                    && accel <= limits.acceleration[axis]
                    && jerk <= limits.jerk[axis]
            })
        })
    }

    /// The first move's zone against where the job starts (validation could not know it).
    fn check_first_zone(&self, start: &[f64], pieces: &[Piece]) -> Result<(), JobError> {
        let first_move = self
            .ops
            .iter()
            .position(|op| matches!(op.action, Action::Move(_)));
        let (Some(zone), true) = (pieces[0].zone_m, first_move == Some(pieces[0].op)) else {
            return Ok(());
        };
        let op = &self.ops[pieces[0].op];
        let (Action::Move(here), Some(next)) = (&op.action, self.ops.get(pieces[0].op + 1)) else {
            return Ok(());
        };
        let Action::Move(after) = &next.action else {
            return Ok(());
        };
        let rig = self.context.rig;
        let start_at = self
            .rig_with(here.tool)
            .tool_pose(start)
            .map_err(|e| JobInvalid::new(op.key.clone(), op.what.clone(), e.to_string()))?
            .position;
        let before: Neighbour = ("the start", "where the arm holds", start_at);
        let after_at = goal_position(after, rig)?;
        check_zone_room(
            op,
            zone,
            goal_position(here, rig)?,
            Some(before),
            (&next.key, &next.what, after_at),
        )?;
        Ok(())
    }
}

/// One move of a run as displacements from where it starts: sample `j` of the move is
/// its start plus `steps[j]`; before its first sample it adds nothing, after its last the
/// whole move.
struct Displacement {
    from: Vec<f64>,
    steps: Vec<Vec<f64>>,
}

impl Displacement {
    fn of(from: &[f64], rows: &[Vec<f64>]) -> Displacement {
        let steps = rows
            .iter()
            .map(|q| q.iter().zip(from).map(|(a, b)| a - b).collect())
            .collect();
        Displacement {
            from: from.to_vec(),
            steps,
        }
    }

    fn len(&self) -> usize {
        self.steps.len()
    }

    /// The configuration of sample `j` of the move alone.
    fn absolute(&self, j: usize) -> Vec<f64> {
        self.from
            .iter()
            .zip(&self.steps[j])
            .map(|(a, d)| a + d)
            .collect()
    }

    fn end(&self) -> Option<Vec<f64>> {
        self.steps.last().map(|_| self.absolute(self.len() - 1))
    }

    /// Adds the move's displacement at its own sample `j` (0 is its first) to `q`.
    fn add_at(&self, j: isize, q: &mut [f64]) {
        let Some(last) = self.steps.len().checked_sub(1) else {
            return;
        };
        if j < 0 {
            return;
        }
        let step = &self.steps[(j as usize).min(last)];
        q.iter_mut().zip(step).for_each(|(q, d)| *q += d);
    }
}

/// The run's samples (after its start): the sum of every move's displacement, each from its
/// start sample (sample 1 of the run is each move's sample 0 when it starts at 0).
fn sum_of(start: &[f64], moves: &[Displacement], starts: &[usize]) -> Vec<Vec<f64>> {
    let length = moves
        .iter()
        .zip(starts)
        .map(|(m, s)| s + m.len())
        .max()
        .unwrap_or(0);
    (0..length)
        .map(|t| {
            let mut q = start.to_vec();
            for (moved, &begin) in moves.iter().zip(starts) {
                moved.add_at(t as isize - begin as isize, &mut q);
            }
            q
        })
        .collect()
}

fn distance(a: &[f64], b: &[f64]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(a, b)| (b - a) * (b - a))
        .sum::<f64>()
        .sqrt()
}
