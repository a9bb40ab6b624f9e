//! A program's ops timed into one trajectory. Moves join into runs: a run ends at a fine
//! point (or before a dwell), and within it each zoned point's corner is blended: from
//! where the tool enters the point's zone on the way in to where it leaves it on the way
//! out, the path is a parabola in joint space (a quadratic Bézier through the point's
//! configuration as its control point), as RAPID's corner path is a parabola begun at the
//! edge of the zone (ABB, RAPID Reference Manual, "zonedata"). Each run is timed as one
//! path, at rest at both ends, by the path timing of `trajectory/path.rs`: the fastest speed
//! along it within every axis' scaled speed (times the step's `speed`) and acceleration,
//! the corners' bends included; acceleration-limited, not jerk-limited, as the Cartesian
//! lines are. Every sample passes `validate` before the program is handed on.
//!
//! Owns the joining, the corners and the marks that name each step's stretch. Must not
//! change a point a step names (a fine point is reached exactly, a zoned one passed within
//! its zone) nor clamp anything: what does not fit is refused.

use super::steps::{Action, Goal, How, MoveOp, Op, goal_position};
use super::{Neighbour, check_zone_room};
use crate::ik::{CartesianError, FabrikSolver, IkError, IkSolver, line_joint_path};
use crate::job::{JobError, JobInvalid, PlanContext};
use crate::rig::{Pose, Rig};
use crate::trajectory::{
    AxisLimits, JointPath, Origins, PathNode, PathTiming, PlanError, Samples, Trajectory,
    check_start,
};
use glam::{DAffine3, DVec3};
use std::time::Duration;
use thiserror::Error;

/// Pieces a corner's parabola is drawn with: the path timing reads a bend from the
/// direction change between pieces, so each piece turns by 1/32 of the corner.
const CORNER_PIECES: usize = 32;

/// Bisection steps for where the tool crosses a zone's edge: 2^-40 of a path piece.
const EDGE_STEPS: usize = 40;

/// A sample's path parameter within this of a mark's counts as passing it (rounding).
const PASS_TOLERANCE: f64 = 1e-12;

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
    #[error(
        "{key}: {kind}: a planned motion has no place for I/O and no link carries it yet (docs/programs.md)"
    )]
    Io { key: String, kind: &'static str },
}

impl From<ProgramError> for JobError {
    fn from(error: ProgramError) -> Self {
        JobError::Program(Box::new(error))
    }
}

/// The joint path of a free move (`move_joints`, `move_poses`) from `from` to `to`: the
/// configurations it passes after `from`, the last `to`. Today the straight line in joint
/// space, `[to]`: the one place a planner of free moves around the cell's objects plugs in
/// (its via configurations are then joined, and blended where a step has a zone, like any
/// other point).
pub fn free_move_path(
    _context: &PlanContext,
    _from: &[f64],
    to: &[f64],
) -> Result<Vec<Vec<f64>>, JobError> {
    Ok(vec![to.to_vec()])
}

/// One move of a run: its op, the configurations after the move's start, and how it may go.
struct Piece {
    op: usize,
    nodes: Vec<Vec<f64>>,
    share: f64,
    zone_m: Option<f64>,
    tool: DAffine3,
}

/// A configuration of a run's path and the speed share of the piece that ends at it.
#[derive(Clone)]
struct Point {
    joints: Vec<f64>,
    share: f64,
}

/// Where along a run's polyline: piece `segment` (point `segment` to `segment + 1`),
/// `fraction` of the way.
#[derive(Clone, Copy)]
struct At {
    segment: usize,
    fraction: f64,
}

impl At {
    fn along(&self) -> f64 {
        self.segment as f64 + self.fraction
    }
}

/// A corner's parabola: where it leaves the path in (entry) and joins the path out (exit).
struct Blend {
    entry: At,
    exit: At,
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
            Action::Io(kind) => {
                return Err(ProgramError::Io {
                    key: op.key.clone(),
                    kind,
                }
                .into());
            }
        }
    }
    planner.flush(&run_start, run)?;
    let mut origins = Origins::default();
    for (op, mark) in ops.iter().zip(&planner.marks) {
        origins.push(*mark, format!("{} ({})", op.key, op.what));
    }
    let trajectory = planner.samples.finish(context.rig, settings.period)?;
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
                let nodes = line_joint_path(solver, q, from, to, settings, index).map_err(
                    |error| ProgramError::Line {
                        key: op.key.clone(),
                        what: op.what.clone(),
                        error,
                    },
                )?;
                Ok(nodes.into_iter().skip(1).collect())
            }
            (_, Goal::Joints(joints)) => free_move_path(context, q, joints),
            (_, Goal::Pose(pose)) => {
                let solution =
                    self.solver(m.tool)?
                        .solve(pose, q)
                        .map_err(|error| ProgramError::Unreachable {
                            key: op.key.clone(),
                            what: op.what.clone(),
                            error,
                        })?;
                free_move_path(context, q, &solution.joints)
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

    /// Times the run `pieces` from `start` (at rest at both ends), its zoned corners
    /// blended, and marks where each of its ops ends.
    fn flush(&mut self, start: &[f64], pieces: Vec<Piece>) -> Result<(), JobError> {
        if pieces.is_empty() {
            return Ok(());
        }
        let mut points = vec![Point {
            joints: start.to_vec(),
            share: pieces[0].share,
        }];
        let mut corners = Vec::with_capacity(pieces.len());
        for piece in &pieces {
            for node in &piece.nodes {
                points.push(Point {
                    joints: node.clone(),
                    share: piece.share,
                });
            }
            corners.push(points.len() - 1);
        }
        self.check_first_zone(start, &pieces)?;
        let mut blends: Vec<Option<Blend>> = Vec::with_capacity(pieces.len());
        for k in 0..pieces.len() {
            let blend = match (pieces[k].zone_m, k + 1 < pieces.len()) {
                (Some(zone), true) => {
                    let low = if k == 0 { 0 } else { corners[k - 1] };
                    let blend = self.blend(&points, corners[k], low, corners[k + 1], zone, &pieces[k])?;
                    let previous_exit = blends.iter().rev().flatten().next().map(|b| b.exit.along());
                    if previous_exit.is_some_and(|exit| exit > blend.entry.along()) {
                        return Err(self.zone_refused(
                            &pieces[k],
                            zone,
                            "it overlaps the zone of the point before along the tool's path: make one of them smaller",
                        ));
                    }
                    Some(blend)
                }
                _ => None,
            };
            blends.push(blend);
        }
        let (path_points, mark_points) = rounded(&points, &corners, &pieces, &blends);
        self.time_run(&path_points, &mark_points, &pieces)
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

    fn zone_refused(&self, piece: &Piece, zone: f64, reason: &str) -> JobError {
        let op = &self.ops[piece.op];
        JobInvalid::new(format!("{}.zone_m", op.key), zone, reason).into()
    }

    /// The corner at `points[corner]` blended within `zone` of the tool's position there:
    /// the path in is left where the tool enters the zone (searched back to `low`), the
    /// path out joined where it leaves it (searched on to `high`).
    fn blend(
        &self,
        points: &[Point],
        corner: usize,
        low: usize,
        high: usize,
        zone: f64,
        piece: &Piece,
    ) -> Result<Blend, JobError> {
        let rig = self.rig_with(piece.tool);
        let tcp = |q: &[f64]| rig.tool_pose(q).map(|p| p.position).unwrap_or(DVec3::NAN);
        let centre = tcp(&points[corner].joints);
        // NaN (no position) counts as outside, so a blend never starts from one.
        let outside = |q: &[f64]| !((tcp(q) - centre).length() < zone);
        let lerp_outside = |segment: usize, f: f64| {
            outside(&lerp(&points[segment].joints, &points[segment + 1].joints, f))
        };
        let never_leaves = "the tool's path from the point before never leaves this zone (the points' straight distance allows it, the path bends back): make the zone smaller";
        let entry = (low..corner)
            .rev()
            .find(|&i| outside(&points[i].joints))
            .map(|segment| At {
                segment,
                fraction: edge(|f| lerp_outside(segment, f), true),
            })
            .ok_or_else(|| self.zone_refused(piece, zone, never_leaves))?;
        let exit = (corner + 1..=high)
            .find(|&i| outside(&points[i].joints))
            .map(|i| At {
                segment: i - 1,
                fraction: edge(|f| lerp_outside(i - 1, f), false),
            })
            .ok_or_else(|| {
                self.zone_refused(
                    piece,
                    zone,
                    "the tool's path to the point after never leaves this zone (the points' straight distance allows it, the path bends back): make the zone smaller",
                )
            })?;
        Ok(Blend { entry, exit })
    }

    /// Times the path through `points` and marks, for each piece's op, the sample where
    /// the path passes `points[marks[k]]`.
    fn time_run(
        &mut self,
        points: &[Point],
        marks: &[usize],
        pieces: &[Piece],
    ) -> Result<(), JobError> {
        let mut path = JointPath::starting_at(PathNode {
            u: 0.0,
            joints: points[0].joints.clone(),
        });
        let mut along = vec![0.0; points.len()];
        for k in 1..points.len() {
            along[k] = along[k - 1] + distance(&points[k - 1].joints, &points[k].joints);
            path.push_at_share(along[k], points[k].joints.clone(), points[k].share);
        }
        if path.nodes().len() < 2 {
            let here = self.samples.last_index();
            self.marks.extend(pieces.iter().map(|_| here));
            return Ok(());
        }
        let first = &self.ops[pieces[0].op];
        let timing = PathTiming {
            rig: self.context.rig,
            settings: self.context.settings,
            limits: &self.limits,
            waypoint: pieces[0].op,
        };
        let before = self.samples.last_index();
        let passed = timing
            .append_traced(
                &path,
                |_, seed| Ok::<_, PlanError>(seed.to_vec()),
                &mut self.samples,
            )
            .map_err(|error| ProgramError::Timing {
                key: first.key.clone(),
                what: first.what.clone(),
                error,
            })?;
        for &mark in marks {
            let u = along[mark] - PASS_TOLERANCE;
            let k = passed
                .iter()
                .position(|&p| p >= u)
                .unwrap_or(passed.len() - 1);
            self.marks.push(before + 1 + k);
        }
        Ok(())
    }
}

/// The run's points with each blended corner's stretch replaced by its parabola, and per
/// piece the point that marks its end: the corner for a fine point, the parabola's middle
/// (where it passes nearest the point) for a zoned one.
fn rounded(
    points: &[Point],
    corners: &[usize],
    pieces: &[Piece],
    blends: &[Option<Blend>],
) -> (Vec<Point>, Vec<usize>) {
    let mut out = vec![points[0].clone()];
    let mut marks = Vec::with_capacity(pieces.len());
    let mut next = 1;
    for (k, blend) in blends.iter().enumerate() {
        let Some(blend) = blend else {
            out.extend_from_slice(&points[next..=corners[k]]);
            next = corners[k] + 1;
            marks.push(out.len() - 1);
            continue;
        };
        let (entry, exit) = (blend.entry, blend.exit);
        if next <= entry.segment {
            out.extend_from_slice(&points[next..=entry.segment]);
        }
        let a = lerp(
            &points[entry.segment].joints,
            &points[entry.segment + 1].joints,
            entry.fraction,
        );
        let b = lerp(
            &points[exit.segment].joints,
            &points[exit.segment + 1].joints,
            exit.fraction,
        );
        let control = &points[corners[k]].joints;
        let share = pieces[k].share.min(pieces[k + 1].share);
        for s in 0..=CORNER_PIECES {
            let t = s as f64 / CORNER_PIECES as f64;
            let joints = a
                .iter()
                .zip(control)
                .zip(&b)
                .map(|((a, c), b)| (1.0 - t) * (1.0 - t) * a + 2.0 * t * (1.0 - t) * c + t * t * b)
                .collect();
            out.push(Point {
                joints,
                share: if s == 0 { pieces[k].share } else { share },
            });
            if s == CORNER_PIECES / 2 {
                marks.push(out.len() - 1);
            }
        }
        next = exit.segment + 1;
    }
    (out, marks)
}

/// Where along `[0, 1]` `outside(f)` changes: from outside to inside (`leaving_outside`,
/// the entry: the last fraction still outside) or from inside to outside (the exit: the
/// first fraction outside), by bisection.
fn edge(outside: impl Fn(f64) -> bool, leaving_outside: bool) -> f64 {
    let (mut low, mut high) = (0.0, 1.0);
    for _ in 0..EDGE_STEPS {
        let middle = (low + high) / 2.0;
        if outside(middle) == leaving_outside {
            low = middle;
        } else {
            high = middle;
        }
    }
    if leaving_outside { low } else { high }
}

fn lerp(a: &[f64], b: &[f64], f: f64) -> Vec<f64> {
    a.iter().zip(b).map(|(a, b)| a + (b - a) * f).collect()
}

fn distance(a: &[f64], b: &[f64]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(a, b)| (b - a) * (b - a))
        .sum::<f64>()
        .sqrt()
}
