//! The `control_msgs/action/FollowJointTrajectory` action of a rig over DDS, at
//! `/<rig>/follow_joint_trajectory`, behaving like ros2_controllers' JointTrajectoryController
//! (docs/ros2.md): a goal's checks and their error codes, path and goal tolerances (the goal's,
//! else `[ros2]`'s), feedback (desired, actual, error) every [`TICK`], cancel (the arm brakes
//! to rest along its path), and a new goal preempting the running one.
//!
//! Owns the action's messages, the goal's checks and the goals' life (accepted, executing,
//! canceling, ended, with results kept for late requests). What a goal becomes is not its
//! business: a [`GoalRunner`] (the daemon's) makes it a job through the same validation as
//! every job and tells how it goes. It never touches the stream or the cycle.

use super::messages::{
    Duration, Header, JointTrajectory, JointTrajectoryPoint, Time, Transform, Vector3,
};
use crate::clock::{self, Clock};
use ros2_client::action::{GetResultRequest, GetResultResponse, SendGoalResponse};
use ros2_client::action_msgs::{
    CancelGoalRequest, CancelGoalResponse, CancelGoalResponseEnum, GoalId, GoalInfo, GoalStatus,
    GoalStatusArray, GoalStatusEnum,
};
use ros2_client::dds::ActionServer;
use ros2_client::{Message, RmwRequestId, builtin_interfaces};
use serde::{Deserialize, Serialize};
use std::collections::VecDeque;

/// How often the server reads requests and, while a goal runs, publishes its feedback and
/// checks its tolerances: 100 Hz, twice the 50 Hz a client is promised, so a late wake of
/// one tick still keeps feedback above it.
pub const TICK: std::time::Duration = std::time::Duration::from_millis(10);
/// Ended goals whose results are kept for a client that asks late (rclpy asks at once; a
/// slow client finds its result among the last this many goals).
const KEPT_RESULTS: usize = 32;
/// A nonzero `header.stamp` within this of now means "start now" (a client stamping its goal
/// with its clock, as rclpy examples do); further in the future is refused (this server
/// does not delay a start), and in the past with its last point passed is
/// OLD_HEADER_TIMESTAMP, as JointTrajectoryController says it.
pub const STAMP_SKEW_S: f64 = 0.5;

/// What a preempted goal's result says: ros2_controllers' JointTrajectoryController's words
/// since ros-controls/ros2_controllers#2422 (on Jazzy by #2423, June 2026), with status
/// ABORTED and INVALID_GOAL; before, "Current goal cancelled due to new incoming action."
/// with status CANCELED.
pub const PREEMPTED: &str = "Current goal preempted by new incoming action.";

/// The result codes of `FollowJointTrajectory` (control_msgs 5.x, Jazzy).
pub mod code {
    pub const SUCCESSFUL: i32 = 0;
    pub const INVALID_GOAL: i32 = -1;
    pub const INVALID_JOINTS: i32 = -2;
    pub const OLD_HEADER_TIMESTAMP: i32 = -3;
    pub const PATH_TOLERANCE_VIOLATED: i32 = -4;
    pub const GOAL_TOLERANCE_VIOLATED: i32 = -5;
}

/// `geometry_msgs/msg/Twist`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Twist {
    pub linear: Vector3,
    pub angular: Vector3,
}

/// `trajectory_msgs/msg/MultiDOFJointTrajectoryPoint`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct MultiDofPoint {
    pub transforms: Vec<Transform>,
    pub velocities: Vec<Twist>,
    pub accelerations: Vec<Twist>,
    pub time_from_start: Duration,
}

/// `trajectory_msgs/msg/MultiDOFJointTrajectory`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct MultiDofTrajectory {
    pub header: Header,
    pub joint_names: Vec<String>,
    pub points: Vec<MultiDofPoint>,
}

/// `control_msgs/msg/JointTolerance`: 0 is the server's default, -1 no limit.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct JointTolerance {
    pub name: String,
    pub position: f64,
    pub velocity: f64,
    pub acceleration: f64,
}

/// `control_msgs/msg/JointComponentTolerance` (for multi-DOF joints, which a rig has none of).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct JointComponentTolerance {
    pub joint_name: String,
    pub component: u16,
    pub position: f64,
    pub velocity: f64,
    pub acceleration: f64,
}

/// The action's goal.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Goal {
    pub trajectory: JointTrajectory,
    pub multi_dof_trajectory: MultiDofTrajectory,
    pub path_tolerance: Vec<JointTolerance>,
    pub component_path_tolerance: Vec<JointComponentTolerance>,
    pub goal_tolerance: Vec<JointTolerance>,
    pub component_goal_tolerance: Vec<JointComponentTolerance>,
    pub goal_time_tolerance: Duration,
}

/// The action's result.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Outcome {
    pub error_code: i32,
    pub error_string: String,
}

/// The action's feedback.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Feedback {
    pub header: Header,
    pub joint_names: Vec<String>,
    pub desired: JointTrajectoryPoint,
    pub actual: JointTrajectoryPoint,
    pub error: JointTrajectoryPoint,
    pub multi_dof_joint_names: Vec<String>,
    pub multi_dof_desired: MultiDofPoint,
    pub multi_dof_actual: MultiDofPoint,
    pub multi_dof_error: MultiDofPoint,
}

impl Message for Goal {}
impl Message for Outcome {}
impl Message for Feedback {}

/// The tolerances of a goal that names none: `[ros2]`'s (docs/ros2.md). Positions in the
/// joint's SI unit (rad, m), as ROS 2's JointTolerance; 0 checks nothing.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Tolerances {
    pub path: f64,
    pub goal: f64,
    /// Seconds after the trajectory's last point by which the goal tolerance must hold.
    pub goal_time_s: f64,
}

/// A goal that passed this module's checks, in the rig's joint order.
#[derive(Debug, Clone, PartialEq)]
pub struct CheckedGoal {
    /// The trajectory as sent (the runner makes it a job, with its own validation).
    pub trajectory: JointTrajectory,
    /// Per rig joint (rad, m); 0: not checked.
    pub path_tolerance: Vec<f64>,
    pub goal_tolerance: Vec<f64>,
    /// The last point, per rig joint.
    pub end: Vec<f64>,
    /// The last point's time from the start (s) and the goal time tolerance (s; 0: none).
    pub duration_s: f64,
    pub goal_time_s: f64,
}

/// A goal refused: the code and the reason, as the result carries them.
#[derive(Debug, Clone, PartialEq)]
pub struct Refusal {
    pub code: i32,
    pub text: String,
}

fn refuse(code: i32, text: String) -> Refusal {
    Refusal { code, text }
}

fn seconds(d: &Duration) -> f64 {
    f64::from(d.sec) + f64::from(d.nanosec) * 1e-9
}

/// Checks `goal` for a rig with `joints`, at `now_s` (Unix seconds), with `max_points` at
/// most, as JointTrajectoryController checks a goal before it runs: the joint names
/// (INVALID_JOINTS), the points (INVALID_GOAL: none, too many, a count of positions that is
/// not the joints', NaN or infinity, times that do not increase) and the stamp
/// (OLD_HEADER_TIMESTAMP). The count is checked before anything is read from the points.
pub fn check_goal(
    goal: &Goal,
    joints: &[String],
    defaults: Tolerances,
    max_points: usize,
    now_s: f64,
) -> Result<CheckedGoal, Refusal> {
    let trajectory = &goal.trajectory;
    let order = joint_order(&trajectory.joint_names, joints)?;
    if !goal.multi_dof_trajectory.points.is_empty()
        || !goal.multi_dof_trajectory.joint_names.is_empty()
    {
        return Err(refuse(
            code::INVALID_JOINTS,
            "multi_dof_trajectory names multi-DOF joints; the rig has none".into(),
        ));
    }
    let points = &trajectory.points;
    if points.is_empty() {
        return Err(refuse(
            code::INVALID_GOAL,
            "trajectory.points is empty".into(),
        ));
    }
    if points.len() > max_points {
        return Err(refuse(
            code::INVALID_GOAL,
            format!(
                "trajectory.points has {} points; at most {max_points} are taken ([limits] \
                 max_job_points)",
                points.len()
            ),
        ));
    }
    check_points(points, joints.len())?;
    let duration_s = points.last().map_or(0.0, |p| seconds(&p.time_from_start));
    check_stamp(&trajectory.header.stamp, duration_s, now_s)?;
    let path_tolerance = tolerances(
        &goal.path_tolerance,
        joints,
        defaults.path,
        "path_tolerance",
    )?;
    let goal_tolerance = tolerances(
        &goal.goal_tolerance,
        joints,
        defaults.goal,
        "goal_tolerance",
    )?;
    let last = &points[points.len() - 1];
    let end = order.iter().map(|&i| last.positions[i]).collect();
    let goal_time = seconds(&goal.goal_time_tolerance);
    Ok(CheckedGoal {
        trajectory: trajectory.clone(),
        path_tolerance,
        goal_tolerance,
        end,
        duration_s,
        goal_time_s: if goal_time > 0.0 {
            goal_time
        } else {
            defaults.goal_time_s
        },
    })
}

/// For each of the rig's joints, where `names` has it: each exactly once, nothing else.
fn joint_order(names: &[String], joints: &[String]) -> Result<Vec<usize>, Refusal> {
    let wrong = || {
        refuse(
            code::INVALID_JOINTS,
            format!(
                "trajectory.joint_names [{}] must name each of the rig's joints once: {}",
                names.join(", "),
                joints.join(", ")
            ),
        )
    };
    if names.len() != joints.len() {
        return Err(wrong());
    }
    joints
        .iter()
        .map(|joint| {
            let mut found = names.iter().enumerate().filter(|(_, n)| *n == joint);
            match (found.next(), found.next()) {
                (Some((index, _)), None) => Ok(index),
                _ => Err(wrong()),
            }
        })
        .collect()
}

/// Each point: one position per joint, velocities and accelerations empty or one per joint,
/// every number finite, times from start increasing.
fn check_points(points: &[JointTrajectoryPoint], dof: usize) -> Result<(), Refusal> {
    let mut previous = f64::NEG_INFINITY;
    for (index, point) in points.iter().enumerate() {
        if point.positions.len() != dof {
            return Err(refuse(
                code::INVALID_GOAL,
                format!(
                    "trajectory.points[{index}].positions has {} values; the rig has {dof} joints",
                    point.positions.len()
                ),
            ));
        }
        for (field, values) in [
            ("positions", &point.positions),
            ("velocities", &point.velocities),
            ("accelerations", &point.accelerations),
        ] {
            if !values.is_empty() && values.len() != dof {
                return Err(refuse(
                    code::INVALID_GOAL,
                    format!(
                        "trajectory.points[{index}].{field} has {} values: none or one per \
                         joint ({dof})",
                        values.len()
                    ),
                ));
            }
            if let Some(bad) = values.iter().position(|v| !v.is_finite()) {
                return Err(refuse(
                    code::INVALID_GOAL,
                    format!(
                        "trajectory.points[{index}].{field}[{bad}] is {}: every value must be \
                         a finite number",
                        values[bad]
                    ),
                ));
            }
        }
        let t = seconds(&point.time_from_start);
        if t <= previous {
            return Err(refuse(
                code::INVALID_GOAL,
                format!(
                    "trajectory.points[{index}].time_from_start is {t} s, not after the point \
                     before's {previous} s: times must increase"
                ),
            ));
        }
        previous = t;
    }
    Ok(())
}

/// A zero stamp, or one within [`STAMP_SKEW_S`] of now, starts now; an earlier one whose
/// last point has passed is old; anything else asks for a start this server does not make.
fn check_stamp(stamp: &Time, duration_s: f64, now_s: f64) -> Result<(), Refusal> {
    if *stamp == Time::default() {
        return Ok(());
    }
    let start = f64::from(stamp.sec) + f64::from(stamp.nanosec) * 1e-9;
    if (start - now_s).abs() <= STAMP_SKEW_S {
        return Ok(());
    }
    if start + duration_s < now_s {
        return Err(refuse(
            code::OLD_HEADER_TIMESTAMP,
            format!(
                "trajectory.header.stamp {start:.3} s plus its last point's {duration_s} s is \
                 before now ({now_s:.3} s): the trajectory is over"
            ),
        ));
    }
    Err(refuse(
        code::INVALID_GOAL,
        format!(
            "trajectory.header.stamp {start:.3} s is {:.3} s from now: this server starts a \
             goal when it takes it (send a zero stamp, or now)",
            start - now_s
        ),
    ))
}

/// Per rig joint: the goal's position tolerance when it names one (> 0), none for -1, else
/// `default`. A name that is not a joint's, or a velocity or acceleration tolerance (which
/// this server does not check, and will not pretend to), is refused.
fn tolerances(
    given: &[JointTolerance],
    joints: &[String],
    default: f64,
    field: &str,
) -> Result<Vec<f64>, Refusal> {
    let mut out = vec![default; joints.len()];
    for (index, tolerance) in given.iter().enumerate() {
        let Some(axis) = joints.iter().position(|j| *j == tolerance.name) else {
            return Err(refuse(
                code::INVALID_JOINTS,
                format!(
                    "{field}[{index}].name `{}` is not one of the rig's joints: {}",
                    tolerance.name,
                    joints.join(", ")
                ),
            ));
        };
        if tolerance.velocity > 0.0 || tolerance.acceleration > 0.0 {
            return Err(refuse(
                code::INVALID_GOAL,
                format!(
                    "{field}[{index}] ({}) sets a velocity or acceleration tolerance ({}, {}): \
                     this server checks positions only (0 or -1 there)",
                    tolerance.name, tolerance.velocity, tolerance.acceleration
                ),
            ));
        }
        let position = tolerance.position;
        if !position.is_finite() || (position < 0.0 && position != -1.0) {
            return Err(refuse(
                code::INVALID_GOAL,
                format!(
                    "{field}[{index}].position ({}) is {position}: a tolerance is > 0, 0 (the \
                     default) or -1 (none)",
                    tolerance.name
                ),
            ));
        }
        if position > 0.0 {
            out[axis] = position;
        } else if position == -1.0 {
            out[axis] = 0.0;
        }
    }
    Ok(out)
}

/// How the goal's job goes, as its runner sees it.
#[derive(Debug, Clone, PartialEq)]
pub enum JobState {
    /// Planning or streaming.
    Running,
    /// The trajectory was streamed to its end, the arm there by the stream's own check.
    Completed,
    /// It ended otherwise (stopped, e-stopped, a fault, a lost link): in words.
    Ended(String),
}

/// The running goal's job now: the position commanded and the arm's, per rig joint.
#[derive(Debug, Clone, PartialEq)]
pub struct Progress {
    pub state: JobState,
    pub desired: Vec<f64>,
    pub actual: Vec<f64>,
}

/// Why a goal's job did not start (nothing then moved): its text is the result's
/// `error_string`.
#[derive(Debug, thiserror::Error)]
pub enum GoalRefused {
    /// The job's validation or its planning refused it (limits, the cell, the rig), in
    /// the words it refuses a job from a file or HTTP with.
    #[error("{0}")]
    Refused(String),
    /// The job's thread ended before it had planned.
    #[error("the job thread ended before planning")]
    JobThreadEnded,
    /// A preempting goal whose first point is at t = 0: the arm is moving, so it cannot be
    /// where the arm is.
    #[error(
        "trajectory.points[0].time_from_start is 0 while the arm moves for the running goal: \
         a preempting goal's first point must come later (the arm goes on from its present \
         motion into it by then)"
    )]
    FirstPointNow,
    /// The running job's stream refused to go on into the new trajectory.
    #[error(
        "the arm cannot go on into this goal from the running one's motion: {0}; the running \
         goal goes on"
    )]
    NotJoined(crate::stream::SpliceRefusal),
    /// The running job's stream did not answer (it was not streaming).
    #[error("the running goal's job did not take the new trajectory within {0} ms")]
    NoAnswer(u64),
}

/// What came of a goal preempting the running one's job.
#[derive(Debug)]
pub enum Preemption {
    /// The arm went on into the new goal's trajectory without stopping: the running job
    /// carries the new goal from here.
    Continued,
    /// The new goal was refused (nothing of it moved); the running goal goes on.
    Refused(GoalRefused),
    /// The running job cannot take a new trajectory (it is not streaming a goal): the new
    /// goal waits for it to be stopped and at rest.
    Unavailable,
}

/// What runs a goal: the daemon's, which makes it a job through the same validation as
/// every job.
pub trait GoalRunner: Send {
    /// Starts `goal` as a job, once the previous one is at rest; the validation's text when
    /// it is refused (nothing then moved).
    fn start(&mut self, goal: &CheckedGoal) -> Result<(), GoalRefused>;
    /// Hands `goal`, validated and planned as a job, to the running goal's job, which goes
    /// on into it from its present motion (as JointTrajectoryController starts a new
    /// trajectory from the state it commands).
    fn preempt(&mut self, goal: &CheckedGoal) -> Preemption;
    /// Asks the running job to stop: it brakes to rest along its path. Returns at once.
    fn stop(&mut self);
    /// How the job goes.
    fn progress(&mut self) -> Progress;
}

/// The largest number of points a goal may have: the runner's `[limits] max_job_points`.
pub struct ServerSettings {
    pub joints: Vec<String>,
    pub tolerances: Tolerances,
    pub max_points: usize,
}

type Server = ActionServer<Goal, Outcome, Feedback>;

/// A goal the server knows: its status, and its result once it ended.
struct Known {
    info: GoalInfo,
    status: GoalStatusEnum,
    result: Option<Outcome>,
    /// Result requests waiting for the end.
    waiting: Vec<RmwRequestId>,
}

/// The goal being carried out.
struct Active {
    id: GoalId,
    goal: CheckedGoal,
    /// When its job started (for the goal time), and whether it is being stopped (a cancel,
    /// a preemption, a violated tolerance) with the result it then gets.
    started: std::time::Duration,
    stopping: Option<(GoalStatusEnum, Outcome)>,
}

/// The action server's state between ticks.
pub struct Goals {
    settings: ServerSettings,
    runner: Box<dyn GoalRunner>,
    known: VecDeque<Known>,
    active: Option<Active>,
    /// A goal waiting for the active one to come to rest (a preemption).
    next: Option<(GoalId, CheckedGoal)>,
    status_changed: bool,
}

fn now_s() -> f64 {
    clock::real().unix_time().as_secs_f64()
}

fn outcome(error_code: i32, error_string: impl Into<String>) -> Outcome {
    Outcome {
        error_code,
        error_string: error_string.into(),
    }
}

impl Goals {
    pub fn new(settings: ServerSettings, runner: Box<dyn GoalRunner>) -> Goals {
        Goals {
            settings,
            runner,
            known: VecDeque::new(),
            active: None,
            next: None,
            status_changed: false,
        }
    }

    fn known(&mut self, id: &GoalId) -> Option<&mut Known> {
        self.known.iter_mut().find(|k| k.info.goal_id == *id)
    }

    fn set_status(&mut self, id: &GoalId, status: GoalStatusEnum) {
        if let Some(known) = self.known(id) {
            known.status = status;
        }
        self.status_changed = true;
    }

    /// Goal `id` ended with `status` and `result`: answered to whoever waits for it.
    fn end(&mut self, server: &Server, id: &GoalId, status: GoalStatusEnum, result: Outcome) {
        if let Some(known) = self.known(id) {
            known.status = status;
            for request in known.waiting.drain(..) {
                let response = GetResultResponse {
                    status,
                    result: result.clone(),
                };
                if let Err(e) = server.send_result(request, response) {
                    tracing::warn!("ros2: answering a FollowJointTrajectory result: {e}");
                }
            }
            known.result = Some(result);
        }
        self.status_changed = true;
    }

    /// A new goal: accepted (so its result can carry why it is refused), checked, then run
    /// (after the active one, stopped, is at rest) or ended at once with its refusal.
    pub fn take_goal(&mut self, server: &Server, request: RmwRequestId, id: GoalId, goal: &Goal) {
        let stamp = builtin_interfaces::Time::now();
        let response = SendGoalResponse {
            accepted: true,
            stamp,
        };
        if let Err(e) = server.send_goal_response(request, response) {
            tracing::warn!("ros2: answering a FollowJointTrajectory goal: {e}");
            return;
        }
        if self.known.len() == KEPT_RESULTS
            && let Some(oldest) = self.known.iter().position(|k| k.result.is_some())
        {
            self.known.remove(oldest);
        }
        self.known.push_back(Known {
            info: GoalInfo { goal_id: id, stamp },
            status: GoalStatusEnum::Accepted,
            result: None,
            waiting: Vec::new(),
        });
        let s = &self.settings;
        match check_goal(goal, &s.joints, s.tolerances, s.max_points, now_s()) {
            Err(refusal) => {
                tracing::info!("ros2: FollowJointTrajectory goal refused: {}", refusal.text);
                self.end(
                    server,
                    &id,
                    GoalStatusEnum::Aborted,
                    outcome(refusal.code, refusal.text),
                );
            }
            Ok(checked) => {
                if let Some((old, _)) = self.next.take() {
                    let why = "preempted by a newer goal before it started";
                    self.end(
                        server,
                        &old,
                        GoalStatusEnum::Canceled,
                        outcome(code::INVALID_GOAL, why),
                    );
                }
                match self.active.as_ref().map(|a| a.stopping.is_none()) {
                    Some(true) => self.preempt(server, id, checked),
                    // Being stopped already (a cancel, a violation), with its own result:
                    // the new goal starts once the arm is at rest.
                    Some(false) => self.next = Some((id, checked)),
                    None => self.begin(server, id, checked),
                }
            }
        }
    }

    /// A new goal while the active one runs: the arm goes on into it without stopping and
    /// the active goal ends ABORTED with INVALID_GOAL and JointTrajectoryController's words
    /// (its `preempt_active_goal`); a new goal that cannot be joined is refused and the
    /// active one goes on; a job that takes no new trajectory is stopped first.
    fn preempt(&mut self, server: &Server, id: GoalId, goal: CheckedGoal) {
        match self.runner.preempt(&goal) {
            Preemption::Continued => {
                if let Some(old) = self.active.take() {
                    self.end(
                        server,
                        &old.id,
                        GoalStatusEnum::Aborted,
                        outcome(code::INVALID_GOAL, PREEMPTED),
                    );
                }
                self.execute(id, goal);
            }
            Preemption::Refused(refused) => {
                tracing::info!("ros2: preempting FollowJointTrajectory goal refused: {refused}");
                self.end(
                    server,
                    &id,
                    GoalStatusEnum::Aborted,
                    outcome(code::INVALID_GOAL, refused.to_string()),
                );
            }
            Preemption::Unavailable => {
                if let Some(active) = &mut self.active {
                    active.stopping = Some((
                        GoalStatusEnum::Aborted,
                        outcome(code::INVALID_GOAL, PREEMPTED),
                    ));
                    self.runner.stop();
                }
                self.next = Some((id, goal));
            }
        }
    }

    /// `goal`, whose job now runs (started or spliced in), as the executing goal from now.
    fn execute(&mut self, id: GoalId, goal: CheckedGoal) {
        self.set_status(&id, GoalStatusEnum::Executing);
        self.active = Some(Active {
            id,
            goal,
            started: clock::real().now(),
            stopping: None,
        });
    }

    /// Starts `goal`'s job, or ends the goal with the validation's refusal.
    fn begin(&mut self, server: &Server, id: GoalId, goal: CheckedGoal) {
        match self.runner.start(&goal) {
            Ok(()) => {
                self.execute(id, goal);
            }
            Err(text) => {
                tracing::info!("ros2: FollowJointTrajectory goal refused: {text}");
                self.end(
                    server,
                    &id,
                    GoalStatusEnum::Aborted,
                    outcome(code::INVALID_GOAL, text.to_string()),
                );
            }
        }
    }

    /// A cancel request: the active goal (and a waiting one) it names are canceled, the arm
    /// braking to rest along its path; the result comes when it is at rest.
    pub fn take_cancel(
        &mut self,
        server: &Server,
        request: RmwRequestId,
        cancel: &CancelGoalRequest,
    ) {
        let Some(info) = cancel_info(cancel) else {
            let response = CancelGoalResponse {
                return_code: CancelGoalResponseEnum::Rejected,
                goals_canceling: Vec::new(),
            };
            let _ = server.send_cancel_response(request, response);
            return;
        };
        let every = info.goal_id == GoalId::ZERO;
        let named = |id: &GoalId| every || *id == info.goal_id;
        let mut canceling = Vec::new();
        if let Some((id, _)) = self.next.as_ref().filter(|(id, _)| named(id)) {
            let id = *id;
            self.next = None;
            if let Some(known) = self.known(&id) {
                canceling.push(known.info.clone());
            }
            self.end(
                server,
                &id,
                GoalStatusEnum::Canceled,
                outcome(code::SUCCESSFUL, "canceled before it started"),
            );
        }
        let active_id = self.active.as_ref().map(|a| a.id).filter(named);
        if let Some(id) = active_id {
            if let Some(active) = &mut self.active
                && active.stopping.is_none()
            {
                active.stopping = Some((
                    GoalStatusEnum::Canceled,
                    outcome(code::SUCCESSFUL, "canceled"),
                ));
                self.runner.stop();
            }
            self.set_status(&id, GoalStatusEnum::Canceling);
            if let Some(known) = self.known(&id) {
                canceling.push(known.info.clone());
            }
        }
        let return_code = if !canceling.is_empty() {
            CancelGoalResponseEnum::None
        } else if !every && self.known(&info.goal_id).is_some() {
            CancelGoalResponseEnum::GoalTerminated
        } else {
            CancelGoalResponseEnum::UnknownGoal
        };
        let response = CancelGoalResponse {
            return_code,
            goals_canceling: canceling,
        };
        if let Err(e) = server.send_cancel_response(request, response) {
            tracing::warn!("ros2: answering a FollowJointTrajectory cancel: {e}");
        }
    }

    /// A result request: answered now if the goal ended, else when it does.
    pub fn take_result_request(&mut self, server: &Server, request: RmwRequestId, id: GoalId) {
        let Some(known) = self.known(&id) else {
            let response = GetResultResponse {
                status: GoalStatusEnum::Unknown,
                result: outcome(code::INVALID_GOAL, "no such goal (or too old a result)"),
            };
            let _ = server.send_result(request, response);
            return;
        };
        match &known.result {
            Some(result) => {
                let response = GetResultResponse {
                    status: known.status,
                    result: result.clone(),
                };
                if let Err(e) = server.send_result(request, response) {
                    tracing::warn!("ros2: answering a FollowJointTrajectory result: {e}");
                }
            }
            None => known.waiting.push(request),
        }
    }

    /// One tick of the active goal: feedback, tolerances, its end; then the waiting goal.
    pub fn tick(&mut self, server: &Server) {
        let Some(active) = &mut self.active else {
            return;
        };
        let progress = self.runner.progress();
        let feedback = feedback(&self.settings.joints, &progress);
        if !progress.desired.is_empty()
            && let Err(e) = server.send_feedback(active.id, feedback)
        {
            tracing::debug!("ros2: publishing FollowJointTrajectory feedback: {e}");
        }
        let id = active.id;
        match (&progress.state, active.stopping.clone()) {
            (JobState::Running, None) => {
                if let Some(violation) = violated(
                    &self.settings.joints,
                    &active.goal,
                    &progress,
                    active.started,
                ) {
                    active.stopping = Some((GoalStatusEnum::Aborted, violation));
                    self.runner.stop();
                }
            }
            (JobState::Running, Some(_)) => {}
            (JobState::Completed, None) => {
                let result = at_goal(&self.settings.joints, &active.goal, &progress.actual);
                let status = if result.error_code == code::SUCCESSFUL {
                    GoalStatusEnum::Succeeded
                } else {
                    GoalStatusEnum::Aborted
                };
                self.active = None;
                self.end(server, &id, status, result);
            }
            (JobState::Completed | JobState::Ended(_), Some((status, result))) => {
                self.active = None;
                self.end(server, &id, status, result);
            }
            (JobState::Ended(why), None) => {
                let result = outcome(code::INVALID_GOAL, format!("the job ended: {why}"));
                self.active = None;
                self.end(server, &id, GoalStatusEnum::Aborted, result);
            }
        }
        if self.active.is_none()
            && let Some((id, goal)) = self.next.take()
        {
            self.begin(server, id, goal);
        }
    }

    /// The status of every known goal, when it changed since the last call.
    pub fn statuses(&mut self) -> Option<GoalStatusArray> {
        if !std::mem::take(&mut self.status_changed) {
            return None;
        }
        Some(GoalStatusArray {
            status_list: self
                .known
                .iter()
                .map(|k| GoalStatus {
                    goal_info: k.info.clone(),
                    status: k.status,
                })
                .collect(),
        })
    }
}

/// The goal a cancel request names. ros2-client keeps the request's one field private; it
/// is read back through its own serde form, which both sides of the copy share.
fn cancel_info(cancel: &CancelGoalRequest) -> Option<GoalInfo> {
    #[derive(Deserialize)]
    struct Cancel {
        goal_info: GoalInfo,
    }
    let value = serde_json::to_value(cancel).ok()?;
    serde_json::from_value::<Cancel>(value)
        .ok()
        .map(|c| c.goal_info)
}

/// A path tolerance the arm left, or a goal time passed: the result, as
/// JointTrajectoryController gives it.
fn violated(
    joints: &[String],
    goal: &CheckedGoal,
    progress: &Progress,
    started: std::time::Duration,
) -> Option<Outcome> {
    let errors = progress
        .desired
        .iter()
        .zip(&progress.actual)
        .map(|(d, a)| d - a);
    for ((joint, error), tolerance) in joints.iter().zip(errors).zip(&goal.path_tolerance) {
        if *tolerance > 0.0 && error.abs() > *tolerance {
            return Some(outcome(
                code::PATH_TOLERANCE_VIOLATED,
                format!(
                    "{joint} is {error:.5} from its desired position, over its path \
                     tolerance {tolerance}; the arm was brought to rest"
                ),
            ));
        }
    }
    let late = clock::real().now().saturating_sub(started).as_secs_f64() - goal.duration_s;
    if goal.goal_time_s > 0.0 && late > goal.goal_time_s {
        return Some(outcome(
            code::GOAL_TOLERANCE_VIOLATED,
            format!(
                "the goal was not reached {:.3} s after the trajectory's end (goal time \
                 tolerance {} s); the arm was brought to rest",
                late, goal.goal_time_s
            ),
        ));
    }
    None
}

/// At the end: every joint within its goal tolerance of the last point, or which is not.
fn at_goal(joints: &[String], goal: &CheckedGoal, actual: &[f64]) -> Outcome {
    let checks = joints
        .iter()
        .zip(&goal.end)
        .zip(actual)
        .zip(&goal.goal_tolerance);
    for (((joint, end), actual), tolerance) in checks {
        let error = end - actual;
        if *tolerance > 0.0 && error.abs() > *tolerance {
            return outcome(
                code::GOAL_TOLERANCE_VIOLATED,
                format!(
                    "{joint} ended {error:.5} from the last point, over its goal tolerance {tolerance}"
                ),
            );
        }
    }
    outcome(code::SUCCESSFUL, "")
}

fn feedback(joints: &[String], progress: &Progress) -> Feedback {
    let now = clock::real().unix_time();
    let point = |positions: Vec<f64>| JointTrajectoryPoint {
        positions,
        ..Default::default()
    };
    let error = progress
        .desired
        .iter()
        .zip(&progress.actual)
        .map(|(d, a)| d - a)
        .collect();
    Feedback {
        header: Header {
            stamp: Time {
                sec: i32::try_from(now.as_secs()).unwrap_or(i32::MAX),
                nanosec: now.subsec_nanos(),
            },
            frame_id: String::new(),
        },
        joint_names: joints.to_vec(),
        desired: point(progress.desired.clone()),
        actual: point(progress.actual.clone()),
        error: point(error),
        ..Default::default()
    }
}

/// Reads every waiting request of `server` into `goals`, ticks it, and publishes the goals'
/// statuses when they changed.
pub fn serve_tick(server: &Server, goals: &mut Goals) {
    loop {
        match server.receive_goal() {
            Ok(Some((request, goal))) => goals.take_goal(server, request, goal.goal_id, &goal.goal),
            Ok(None) => break,
            Err(e) => {
                tracing::warn!("ros2: reading a FollowJointTrajectory goal: {e}");
                break;
            }
        }
    }
    while let Ok(Some((request, cancel))) = server.receive_cancel_request() {
        goals.take_cancel(server, request, &cancel);
    }
    while let Ok(Some((request, GetResultRequest { goal_id }))) = server.receive_result_request() {
        goals.take_result_request(server, request, goal_id);
    }
    goals.tick(server);
    if let Some(statuses) = goals.statuses()
        && let Err(e) = server.send_goal_statuses(statuses)
    {
        tracing::warn!("ros2: publishing FollowJointTrajectory statuses: {e}");
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const NOW_S: f64 = 1_800_000_000.0;

    fn joints() -> Vec<String> {
        (1..=6).map(|i| format!("joint_{i}")).collect()
    }

    fn defaults() -> Tolerances {
        Tolerances {
            path: 0.05,
            goal: 0.01,
            goal_time_s: 0.0,
        }
    }

    fn point(positions: Vec<f64>, t: f64) -> JointTrajectoryPoint {
        JointTrajectoryPoint {
            positions,
            time_from_start: Duration {
                sec: t.trunc() as i32,
                nanosec: (t.fract() * 1e9).round() as u32,
            },
            ..Default::default()
        }
    }

    fn goal(points: Vec<JointTrajectoryPoint>) -> Goal {
        Goal {
            trajectory: JointTrajectory {
                joint_names: joints(),
                points,
                ..Default::default()
            },
            ..Default::default()
        }
    }

    fn code_of(goal: &Goal) -> i32 {
        check_goal(goal, &joints(), defaults(), 1000, NOW_S)
            .expect_err("the goal is refused")
            .code
    }

    #[test]
    fn a_sound_goal_is_taken_in_the_rigs_order_with_the_default_tolerances() {
        let mut sound = goal(vec![
            point(vec![0.0; 6], 0.5),
            point(vec![0.1, 0.2, 0.3, 0.4, 0.5, 0.6], 2.0),
        ]);
        sound.trajectory.joint_names.reverse();
        sound.goal_tolerance.push(JointTolerance {
            name: "joint_2".into(),
            position: 0.002,
            ..Default::default()
        });
        sound.path_tolerance.push(JointTolerance {
            name: "joint_3".into(),
            position: -1.0,
            ..Default::default()
        });
        let checked = check_goal(&sound, &joints(), defaults(), 1000, NOW_S).expect("taken");
        assert_eq!(
            checked.end,
            vec![0.6, 0.5, 0.4, 0.3, 0.2, 0.1],
            "the rig's order"
        );
        assert_eq!(checked.duration_s, 2.0);
        assert_eq!(
            checked.goal_tolerance,
            vec![0.01, 0.002, 0.01, 0.01, 0.01, 0.01]
        );
        assert_eq!(
            checked.path_tolerance,
            vec![0.05, 0.05, 0.0, 0.05, 0.05, 0.05]
        );
    }

    #[test]
    fn a_wrong_missing_or_repeated_joint_name_is_invalid_joints() {
        let mut wrong = goal(vec![point(vec![0.0; 6], 1.0)]);
        wrong.trajectory.joint_names[2] = "elbow".into();
        assert_eq!(code_of(&wrong), code::INVALID_JOINTS);
        let mut missing = goal(vec![point(vec![0.0; 5], 1.0)]);
        missing.trajectory.joint_names.pop();
        assert_eq!(code_of(&missing), code::INVALID_JOINTS);
        let mut repeated = goal(vec![point(vec![0.0; 6], 1.0)]);
        repeated.trajectory.joint_names[5] = "joint_1".into();
        assert_eq!(code_of(&repeated), code::INVALID_JOINTS);
        let mut tolerance = goal(vec![point(vec![0.0; 6], 1.0)]);
        tolerance.path_tolerance.push(JointTolerance {
            name: "wrist".into(),
            ..Default::default()
        });
        assert_eq!(code_of(&tolerance), code::INVALID_JOINTS);
    }

    #[test]
    fn nan_non_increasing_times_too_many_or_no_points_are_invalid_goals() {
        let mut nan = vec![0.0; 6];
        nan[4] = f64::NAN;
        let refusal = check_goal(
            &goal(vec![point(nan, 1.0)]),
            &joints(),
            defaults(),
            1000,
            NOW_S,
        )
        .expect_err("NaN is refused");
        assert_eq!(refusal.code, code::INVALID_GOAL);
        assert!(
            refusal.text.contains("points[0].positions[4] is NaN"),
            "{}",
            refusal.text
        );
        let same = goal(vec![point(vec![0.0; 6], 1.0), point(vec![0.1; 6], 1.0)]);
        assert_eq!(code_of(&same), code::INVALID_GOAL);
        let back = goal(vec![point(vec![0.0; 6], 1.0), point(vec![0.1; 6], 0.5)]);
        assert_eq!(code_of(&back), code::INVALID_GOAL);
        let many = goal(
            (0..1001)
                .map(|i| point(vec![0.0; 6], 0.01 * f64::from(i + 1)))
                .collect(),
        );
        let refusal = check_goal(&many, &joints(), defaults(), 1000, NOW_S).expect_err("too many");
        assert_eq!(refusal.code, code::INVALID_GOAL);
        assert!(
            refusal.text.contains("1001 points; at most 1000"),
            "{}",
            refusal.text
        );
        assert_eq!(code_of(&goal(vec![])), code::INVALID_GOAL);
        let short = goal(vec![point(vec![0.0; 5], 1.0)]);
        assert_eq!(code_of(&short), code::INVALID_GOAL);
        let mut velocity = goal(vec![point(vec![0.0; 6], 1.0)]);
        velocity.goal_tolerance.push(JointTolerance {
            name: "joint_1".into(),
            velocity: 0.1,
            ..Default::default()
        });
        assert_eq!(
            code_of(&velocity),
            code::INVALID_GOAL,
            "velocity tolerances are not checked"
        );
    }

    #[test]
    fn a_stamp_whose_trajectory_is_over_is_old_and_one_far_ahead_is_refused() {
        let mut old = goal(vec![point(vec![0.0; 6], 1.0)]);
        old.trajectory.header.stamp = Time {
            sec: (NOW_S - 10.0) as i32,
            nanosec: 0,
        };
        assert_eq!(code_of(&old), code::OLD_HEADER_TIMESTAMP);
        let mut ahead = old.clone();
        ahead.trajectory.header.stamp.sec = (NOW_S + 10.0) as i32;
        assert_eq!(code_of(&ahead), code::INVALID_GOAL);
        let mut now = old.clone();
        now.trajectory.header.stamp = Time {
            sec: NOW_S as i32,
            nanosec: 200_000_000,
        };
        assert!(
            check_goal(&now, &joints(), defaults(), 1000, NOW_S).is_ok(),
            "now starts now"
        );
    }

    #[test]
    fn the_goal_is_judged_on_each_joints_tolerance_and_the_path_on_desired_less_actual() {
        let checked = check_goal(
            &goal(vec![point(vec![0.5; 6], 1.0)]),
            &joints(),
            defaults(),
            1000,
            NOW_S,
        )
        .expect("taken");
        let mut actual = vec![0.5; 6];
        assert_eq!(
            at_goal(&joints(), &checked, &actual).error_code,
            code::SUCCESSFUL
        );
        actual[3] = 0.52;
        let missed = at_goal(&joints(), &checked, &actual);
        assert_eq!(missed.error_code, code::GOAL_TOLERANCE_VIOLATED);
        assert!(
            missed.error_string.starts_with("joint_4 ended -0.02"),
            "{}",
            missed.error_string
        );
        let progress = Progress {
            state: JobState::Running,
            desired: vec![0.2; 6],
            actual: vec![0.2, 0.2, 0.2, 0.2, 0.2, 0.26],
        };
        let started = clock::real().now();
        let off = violated(&joints(), &checked, &progress, started).expect("off the path");
        assert_eq!(off.error_code, code::PATH_TOLERANCE_VIOLATED);
        assert!(
            off.error_string.starts_with("joint_6"),
            "{}",
            off.error_string
        );
        let on = Progress {
            actual: vec![0.24; 6],
            ..progress
        };
        assert_eq!(violated(&joints(), &checked, &on, started), None);
    }
}
