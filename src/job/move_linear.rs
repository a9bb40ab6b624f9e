//! `kind = "move_linear"`: a joint move to the first pose (inverse kinematics nearest the
//! rig's position), then straight tool lines from pose to pose, orientation slerped, solved sample by sample with the FABRIK planner (seeded by the
//! sample before, so the joints stay continuous across lines), staying at the last pose.
//! Owns the tool speed cap `speed_m_s`: the Cartesian planner times each line as fast as
//! the axes allow, and this kind slows the whole plan down until the tool keeps under it.

use super::poses::{PoseSpec, check_poses, show_xyz};
use super::{JobContext, JobError, JobInvalid, PlanContext, in_range};
use crate::ik::{CartesianError, FabrikSolver, IkError, IkSolver, plan_cartesian_marked};
use crate::rig::{JointKind, Pose, Rig};
use crate::trajectory::{Origins, PlanSettings, Trajectory, plan_joint_moves};
use glam::DVec3;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use thiserror::Error;

/// The fastest tool speed a job may ask for (m/s): above the IRB 120's 6.2 m/s TCP speed
/// (ABB, IRB 120 product specification, 3HAC035960-001, "Performance") nothing is gained.
const MAX_TOOL_SPEED_M_S: f64 = 6.2;
const MIN_TOOL_SPEED_M_S: f64 = 0.001;

/// How often the plan is slowed down to meet `speed_m_s`, and the extra margin each time so
/// that the sampled speed, a hair above after rounding, does not need another round.
const MAX_SLOWDOWNS: u32 = 6;
const SLOWDOWN_MARGIN: f64 = 1.01;

/// A line of a `move_linear` job refused, in the job's own words: the pose it goes to by its
/// index in `job.poses` and as written, and where along the line from the pose before it
/// failed (the point, and the fraction of the line).
#[derive(Debug, Error)]
pub enum LineRefused {
    /// The pose the line goes to is out of the arm's reach itself.
    #[error(
        "job.poses[{index}] = {written} cannot be reached: {error}; the line to it from job.poses[{}] first fails {:.1}% of the way along, at {}",
        index - 1, fraction * 100.0, show_xyz(*point)
    )]
    PoseUnreachable {
        index: usize,
        written: PoseSpec,
        error: IkError,
        fraction: f64,
        point: DVec3,
    },
    /// Both poses are reachable, a point of the line between them is not.
    #[error(
        "the line from job.poses[{}] to job.poses[{index}] = {written} first fails {:.1}% of the way along, at {}: {error}; both poses are reachable, the straight line between them is not: add a pose between them, or use move_poses",
        index - 1, fraction * 100.0, show_xyz(*point)
    )]
    LineUnreachable {
        index: usize,
        written: PoseSpec,
        error: IkError,
        fraction: f64,
        point: DVec3,
    },
    /// The joints solved along the line jump: the arm would switch branch or pass a
    /// singularity there.
    #[error(
        "the line from job.poses[{}] to job.poses[{index}] = {written}: {joint} jumps {:.3} {unit} between two samples {:.1}% of the way (at most {:.3} {unit}): a branch switch or a singularity; add a pose between them, or use move_poses",
        index - 1, kind.to_user(*jump), fraction * 100.0, kind.to_user(*max_jump), unit = kind.unit()
    )]
    Jumps {
        index: usize,
        written: PoseSpec,
        joint: String,
        /// SI units (radians or metres).
        jump: f64,
        max_jump: f64,
        kind: JointKind,
        fraction: f64,
    },
}

/// The default tool speed (m/s): a careful 0.1 m/s, the speed of a hand-guided move.
fn default_speed() -> f64 {
    0.1
}

#[derive(Debug, Clone, PartialEq, Deserialize, Serialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct MoveLinear {
    /// The tool poses the lines go through, in order. At least one, at most 10000.
    pub poses: Vec<PoseSpec>,
    /// The tool's top speed along the lines (m/s), in [0.001, 6.2]; 0.1 when absent. The
    /// axes' limits may keep it slower.
    #[serde(default = "default_speed")]
    pub speed_m_s: f64,
}

impl MoveLinear {
    pub fn validate(self, _: &JobContext) -> Result<Self, JobInvalid> {
        check_poses("job.poses", &self.poses)?;
        in_range(
            "job.speed_m_s",
            self.speed_m_s,
            MIN_TOOL_SPEED_M_S,
            MAX_TOOL_SPEED_M_S,
        )?;
        Ok(self)
    }

    /// The approach and the lines, each named by the pose it goes to (`job.poses[k]`).
    pub fn plan(&self, context: &PlanContext) -> Result<(Trajectory, Origins), JobError> {
        let poses = check_poses("job.poses", &self.poses)?;
        let solver = FabrikSolver::new(context.rig.clone())?;
        let first =
            solver
                .solve(&poses[0], context.start)
                .map_err(|error| JobError::Unreachable {
                    index: 0,
                    what: format!("pose at {}", show_xyz(poses[0].position)),
                    error,
                })?;
        let approach = plan_joint_moves(
            context.rig,
            context.start,
            std::slice::from_ref(&first.joints),
            context.settings,
        )?;
        let mut settings = context.settings.after(&approach);
        let mut attempt = 0;
        loop {
            let mut trajectory = approach.clone();
            let (lines, marks) =
                plan_cartesian_marked(&solver, &first.joints, &poses[1..], &settings)
                    .map_err(|error| self.line_refused(error, &solver, &poses, &first.joints))?;
            let ratio = top_tool_speed(context.rig, &lines) / self.speed_m_s;
            trajectory.append(&lines);
            attempt += 1;
            if ratio <= 1.0 {
                let mut origins = Origins::default();
                let joined = approach.len() - 1;
                origins.push(joined, "the joint move to job.poses[0]");
                origins.push_marks(&marks, joined, |k| {
                    format!("the line to job.poses[{}]", k + 1)
                });
                return Ok((trajectory, origins));
            }
            if attempt > MAX_SLOWDOWNS {
                return Err(JobInvalid::new(
                    "job.speed_m_s",
                    self.speed_m_s,
                    format!(
                        "the lines cannot be slowed down to this speed (still {ratio:.2} times it)"
                    ),
                )
                .into());
            }
            // Scaling speeds by r and accelerations by r^2 is the same path, 1/r as fast.
            let r = 1.0 / (ratio * SLOWDOWN_MARGIN);
            settings = PlanSettings {
                speed_scale: settings.speed_scale * r,
                accel_scale: settings.accel_scale * r * r,
                ..settings
            };
        }
    }

    /// `error` of the lines (planned from `job.poses[0]` on, so their waypoint `w` is
    /// `job.poses[w + 1]`) in the job's words; other errors as they are. An unreachable
    /// point of a line is told with whether the pose it goes to is reachable itself
    /// (solved from `seed`), since that decides what the user should change.
    fn line_refused(
        &self,
        error: CartesianError,
        solver: &FabrikSolver,
        poses: &[Pose],
        seed: &[f64],
    ) -> JobError {
        let refused = match error {
            CartesianError::Unreachable {
                waypoint,
                sample_pose,
                u,
                error,
            } => {
                let index = waypoint + 1;
                let (written, point) = (self.poses[index], sample_pose.position);
                match solver.solve(&poses[index], seed) {
                    Err(error) => LineRefused::PoseUnreachable {
                        index,
                        written,
                        error,
                        fraction: u,
                        point,
                    },
                    Ok(_) => LineRefused::LineUnreachable {
                        index,
                        written,
                        error,
                        fraction: u,
                        point,
                    },
                }
            }
            CartesianError::Discontinuity {
                waypoint,
                joint,
                jump,
                max_jump,
                kind,
                u,
            } => LineRefused::Jumps {
                index: waypoint + 1,
                written: self.poses[waypoint + 1],
                joint,
                jump,
                max_jump,
                kind,
                fraction: u,
            },
            other => return other.into(),
        };
        JobError::Line(Box::new(refused))
    }
}

/// How close to its lines `move_linear` keeps the tool (m), by forward kinematics of the
/// commanded joints (`docs/jobs.md`; `tests/jobs.rs` measures it).
pub const LINE_TOLERANCE_M: f64 = 0.5e-3;

/// The tool lines of a `move_linear` job, to measure a tool path against (issue 32: how far
/// the arm strayed after a stall). Walked in order: each distance is to the nearest of the
/// line the tool was last nearest and its neighbours, so a path of 10,000 poses costs a few
/// segments a sample, not all of them.
pub struct Lines {
    corners: Vec<DVec3>,
    /// The line the tool was last nearest (index of its first corner).
    at: usize,
}

impl Lines {
    /// Where the lines start: the first pose, which the joint move reaches.
    pub fn start(&self) -> DVec3 {
        self.corners[0]
    }

    /// The tool position `p`'s distance from the lines (m), walking on from the line it
    /// was last nearest.
    pub fn distance(&mut self, p: DVec3) -> f64 {
        let last = self.corners.len() - 2;
        let (from, to) = (self.at.saturating_sub(1), (self.at + 2).min(last));
        let (nearest, distance) = (from..=to)
            .map(|k| (k, to_segment(p, self.corners[k], self.corners[k + 1])))
            .fold((self.at, f64::INFINITY), |best, next| {
                if next.1 < best.1 { next } else { best }
            });
        self.at = nearest;
        distance
    }
}

/// The distance from `p` to the segment `a`-`b`.
fn to_segment(p: DVec3, a: DVec3, b: DVec3) -> f64 {
    let ab = b - a;
    let u = ((p - a).dot(ab) / ab.length_squared().max(f64::MIN_POSITIVE)).clamp(0.0, 1.0);
    (a + ab * u - p).length()
}

impl MoveLinear {
    /// The job's lines; `None` for a single pose (no line, nothing promised).
    pub fn lines(&self) -> Result<Option<Lines>, JobInvalid> {
        let poses = check_poses("job.poses", &self.poses)?;
        let corners: Vec<DVec3> = poses.iter().map(|p| p.position).collect();
        Ok((corners.len() >= 2).then_some(Lines { corners, at: 0 }))
    }
}

/// The tool's fastest speed between two samples (m/s), by forward kinematics.
pub fn top_tool_speed(rig: &Rig, trajectory: &Trajectory) -> f64 {
    let tool = |k: usize| rig.tool_pose(&trajectory.position(k)).map(|p| p.position);
    (1..trajectory.len())
        .filter_map(|k| Some((tool(k).ok()? - tool(k - 1).ok()?).length()))
        .fold(0.0, f64::max)
        / trajectory.period.as_secs_f64()
}
