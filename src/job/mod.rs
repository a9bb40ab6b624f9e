//! Jobs: what a user asks a rig to do. One enum, [`Job`], with one file per kind (the shape
//! of mini-redis's `Command`): each kind parses its own keys, validates them (`validate`,
//! which also resolves the files it names against the config's directory), plans its
//! trajectory from the rig's current position (`plan`), and says how it is shown (`scene`)
//! and named (`name`). The TOML loader and the HTTP API both go through [`Job::validate`],
//! so both refuse the same jobs with the same text.
//!
//! Adding a kind is one file and one arm of [`Job`]. A job never streams, never opens a link
//! and never knows where its description came from; a target it cannot reach fails the
//! whole job before motion.

mod files;
mod follow_trajectory;
mod joint_waypoints;
mod limits;
mod move_joints;
mod move_linear;
mod move_poses;
mod pasted;
mod poses;
mod program;
mod wall_figure;

pub use crate::apps::gait::Gait;
pub use crate::apps::paint::Paint;
pub use files::resolve_file;
pub use follow_trajectory::{FollowTrajectory, RowCaps, TrajectoryFileError, read_trajectory_csv};
pub use joint_waypoints::JointWaypoints;
pub use limits::{
    CEILING_DURATION_S, CEILING_PLAN_MB, CEILING_POINTS, DEFAULT_MAX_JOB_POINTS, JobLimits,
    planned_mb,
};
pub use move_joints::MoveJoints;
pub use move_linear::{LINE_TOLERANCE_M, LineRefused, Lines, MoveLinear, top_tool_speed};
pub use move_poses::MovePoses;
pub use pasted::{PastedJobError, job_from_toml};
pub use poses::PoseSpec;
pub use program::{
    CycleTimes, LapTime, Move as ProgramMove, NoKeys, Over, Program, ProgramError, Repeat,
    SetOutput, Step, StepLabel, StepSpans, StepTime, StepTimer, Wait, WaitInput, free_move_path,
};
pub use wall_figure::{WallFigure, star_poses};

use crate::cell::CollisionModel;
use crate::ik::{CartesianError, IkError, StructureError};
use crate::rig::Rig;
use crate::trajectory::{Origins, PlanError, PlanSettings, Trajectory};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use std::path::Path;
use std::time::Duration;
use thiserror::Error;

/// Most targets, poses or trajectory rows one job may hold: far more than a hand-written job
/// needs, few enough that planning a hostile job cannot exhaust the daemon's memory.
pub const MAX_TARGETS: usize = 10_000;

/// A job, as `[job]` in a run settings file or `{"job": {...}}` in `POST /api/jobs`.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize, JsonSchema)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Job {
    /// The demo: a five-pointed star on a wall, tool normal to the wall, then back home.
    WallFigure(WallFigure),
    /// Joint moves through configurations, then back to where the job started.
    JointWaypoints(JointWaypoints),
    /// Joint moves through configurations, staying at the last.
    MoveJoints(MoveJoints),
    /// Straight tool lines through poses, staying at the last.
    MoveLinear(MoveLinear),
    /// Joint moves to poses (inverse kinematics nearest the current position), staying at
    /// the last.
    MovePoses(MovePoses),
    /// A timed joint trajectory from a CSV file next to the config.
    FollowTrajectory(FollowTrajectory),
    /// The sloth's gait over a scenario (the rig must be a sloth file).
    Gait(Gait),
    /// Paint a generated room with the painter rig.
    Paint(Paint),
    /// Steps over the cell's named targets: moves with zones, dwells, I/O, repeats
    /// (docs/programs.md).
    Program(Program),
}

/// What an app loads beside the rig it streams (`apps::App::load_rig`: the gait's model
/// behind its streamed axes), handed to its jobs as is: only the app knows its type.
pub type AppRig = dyn std::any::Any + Send + Sync;

/// What validating a job needs: the rig it runs on, what its app loaded beside it, the
/// cell (a program's named targets), the directory files are named relative to, and the
/// caps on its cost (`[limits]`) with the stream period its plan will be sampled at.
#[derive(Clone, Copy)]
pub struct JobContext<'a> {
    pub rig: &'a Rig,
    pub cell: &'a crate::cell::Cell,
    pub app_rig: Option<&'a AppRig>,
    pub base_dir: &'a Path,
    pub limits: &'a JobLimits,
    pub period: Duration,
}

/// What planning a job needs: the rig, what its app loaded beside it, where the rig is,
/// how the planner may use it, and the cell's collision model (what a move that goes
/// around the cell plans around; `None` where no cell is known, as in [`plan_job`]).
#[derive(Clone, Copy)]
pub struct PlanContext<'a> {
    pub rig: &'a Rig,
    pub app_rig: Option<&'a AppRig>,
    pub start: &'a [f64],
    pub settings: &'a PlanSettings,
    pub model: Option<&'a CollisionModel>,
}

/// How a job of the core's kinds is shown in the live view: the bare rig, or the rig before
/// the wall it draws on. An app's job is shown by its app (`apps::App::scene`).
pub enum Scene<'a> {
    Arm,
    Wall(&'a WallFigure),
}

/// A job refused before planning: the key, the value given and why. The same text comes
/// back from the config loader (after the file's name) and from the HTTP API. A `cause`
/// (a file that would not load) is kept as the error's source, never in its text: the API
/// answers with the text alone, so it never quotes a file.
#[derive(Debug, Error)]
#[error("key `{key}` = {value}: {reason}")]
pub struct JobInvalid {
    pub key: String,
    pub value: String,
    pub reason: String,
    #[source]
    pub cause: Option<Box<dyn std::error::Error + Send + Sync>>,
}

/// Longest rendering of a refused value in a message: enough to recognise it, short enough
/// that a hostile body is not echoed back whole.
const MAX_VALUE_CHARS: usize = 80;

impl JobInvalid {
    /// `key` holds `value` (shown as JSON, shortened), refused for `reason`.
    pub fn new(key: impl Into<String>, value: impl Serialize, reason: impl Into<String>) -> Self {
        let mut value = serde_json::to_string(&value).unwrap_or_else(|_| "?".into());
        if value.chars().count() > MAX_VALUE_CHARS {
            value = value.chars().take(MAX_VALUE_CHARS).collect::<String>() + "...";
        }
        JobInvalid {
            key: key.into(),
            value,
            reason: reason.into(),
            cause: None,
        }
    }

    pub fn with_cause(mut self, cause: impl std::error::Error + Send + Sync + 'static) -> Self {
        self.cause = Some(Box::new(cause));
        self
    }
}

#[derive(Debug, Error)]
pub enum JobError {
    #[error("job target {index} ({what}) cannot be reached: {error}")]
    Unreachable {
        index: usize,
        what: String,
        error: IkError,
    },
    #[error(transparent)]
    Plan(#[from] PlanError),
    #[error(transparent)]
    Cartesian(#[from] CartesianError),
    /// Boxed to keep every `Result<_, JobError>` small.
    #[error(transparent)]
    Line(Box<LineRefused>),
    #[error(transparent)]
    Structure(#[from] StructureError),
    #[error("a gait job needs the sloth rig: run it with a sloth file as the rig")]
    NeedsSloth,
    #[error("paint settings")]
    PaintConfig(#[from] crate::rig::ConfigError),
    #[error("paint job")]
    Paint(#[from] crate::apps::paint::PaintError),
    #[error("gait")]
    Gait(#[from] crate::apps::gait::GaitError),
    #[error("trajectory file")]
    TrajectoryFile(#[from] TrajectoryFileError),
    #[error("{0}")]
    Invalid(#[from] JobInvalid),
    /// Boxed to keep every `Result<_, JobError>` small.
    #[error(transparent)]
    Program(Box<ProgramError>),
    /// A move asked to go around the cell (`plan_around = true`) that could not be
    /// planned: its key and the free planner's reason (boxed: it carries its words).
    #[error("{key}: {error}")]
    FreeMove {
        key: String,
        error: Box<crate::trajectory::free::FreePlanError>,
    },
    /// `plan_around = true` where the planner was given no cell to plan around.
    #[error("{key} = true needs the cell's collision model, and this plan was given none")]
    NoCell { key: &'static str },
}

impl Job {
    /// The job's keys checked against the rig, every number in range and every file it
    /// names resolved inside `context.base_dir` (so the returned job holds usable paths).
    pub fn validate(self, context: &JobContext) -> Result<Job, JobInvalid> {
        Ok(match self {
            Job::WallFigure(job) => Job::WallFigure(job.validate(context)?),
            Job::JointWaypoints(job) => Job::JointWaypoints(job.validate(context)?),
            Job::MoveJoints(job) => Job::MoveJoints(job.validate(context)?),
            Job::MoveLinear(job) => Job::MoveLinear(job.validate(context)?),
            Job::MovePoses(job) => Job::MovePoses(job.validate(context)?),
            Job::FollowTrajectory(job) => Job::FollowTrajectory(job.validate(context)?),
            Job::Gait(job) => Job::Gait(job.validate(context)?),
            Job::Paint(job) => Job::Paint(job.validate(context)?),
            Job::Program(job) => Job::Program(job.validate(context)?),
        })
    }

    /// The whole job's trajectory from `context.start`, within `context.settings.budget`:
    /// the planners check it before each piece they sample; a gait's or a room's plan is
    /// checked whole, once planned (their sizes are bounded by their keys' ranges).
    pub fn plan(&self, context: &PlanContext) -> Result<Trajectory, JobError> {
        self.plan_traced(context).map(|(trajectory, _)| trajectory)
    }

    /// [`Job::plan`], with where each stretch of the trajectory came from in the job's own
    /// words (`job.targets_deg[2]`, a row of its file): what a refusal of the motion names.
    pub fn plan_traced(&self, context: &PlanContext) -> Result<(Trajectory, Origins), JobError> {
        let (trajectory, origins) = self.plan_unchecked(context)?;
        let settings = context.settings;
        settings
            .budget
            .check_trajectory(&trajectory)
            .map_err(PlanError::from)?;
        Ok((trajectory, origins))
    }

    fn plan_unchecked(&self, context: &PlanContext) -> Result<(Trajectory, Origins), JobError> {
        match self {
            Job::WallFigure(job) => job.plan(context),
            Job::JointWaypoints(job) => job.plan(context),
            Job::MoveJoints(job) => job.plan(context),
            Job::MoveLinear(job) => job.plan(context),
            Job::MovePoses(job) => job.plan(context),
            Job::FollowTrajectory(job) => job.plan(context),
            Job::Gait(job) => Ok((job.plan(context)?, Origins::whole("the gait's plan"))),
            Job::Paint(job) => Ok((job.plan(context)?, Origins::whole("the painting plan"))),
            Job::Program(job) => job.plan(context),
        }
    }

    /// The `kind` key of the job.
    pub fn kind(&self) -> &'static str {
        match self {
            Job::WallFigure(_) => "wall_figure",
            Job::JointWaypoints(_) => "joint_waypoints",
            Job::MoveJoints(_) => "move_joints",
            Job::MoveLinear(_) => "move_linear",
            Job::MovePoses(_) => "move_poses",
            Job::FollowTrajectory(_) => "follow_trajectory",
            Job::Gait(_) => "gait",
            Job::Paint(_) => "paint",
            Job::Program(_) => "program",
        }
    }

    /// The first step that needs I/O (`job.steps[4]: grip`), for a link that carries none
    /// to refuse the job before motion.
    pub fn first_io_step(&self) -> Option<String> {
        match self {
            Job::Program(program) => program.first_io_step(),
            _ => None,
        }
    }

    /// A program's planned cycle time per step and per pass of each repeat, from its
    /// trajectory's stretches; `None` for other kinds.
    pub fn cycle_times(&self, origins: &Origins, period: Duration) -> Option<CycleTimes> {
        match self {
            Job::Program(program) => program.cycle_times(origins, period),
            _ => None,
        }
    }

    /// A program's steps on its trajectory (`origins` its plan's), to find the step a
    /// cycle is in and time them as they stream; `None` for other kinds.
    pub fn step_spans(&self, origins: &Origins) -> Option<StepSpans> {
        match self {
            Job::Program(program) => program.step_spans(origins),
            _ => None,
        }
    }

    /// The job's name in reports and status: its kind, with the settings that tell two
    /// jobs of that kind apart.
    pub fn name(&self) -> String {
        match self {
            Job::Gait(job) => job.name(),
            Job::Paint(job) => job.name(),
            other => other.kind().to_string(),
        }
    }

    pub fn scene(&self) -> Scene<'_> {
        match self {
            Job::WallFigure(job) => Scene::Wall(job),
            _ => Scene::Arm,
        }
    }
}

/// The JSON Schema of a job request's body, `{"job": {...}}`, served at `GET /api/schema`.
pub fn request_schema() -> serde_json::Value {
    #[derive(JsonSchema)]
    #[allow(dead_code)]
    #[schemars(deny_unknown_fields)]
    /// A job request: the job (as JSON or as TOML text, one of the two), or an empty body
    /// for the cell's configured job.
    struct JobRequest {
        job: Option<Job>,
        /// The job as TOML text instead: a run settings file's `[job]` table or its keys.
        toml: Option<String>,
    }
    serde_json::to_value(schemars::schema_for!(JobRequest)).unwrap_or_default()
}

/// Plans `job` from `start` on `rig` (a job whose app loads nothing beside the rig; kept
/// for callers that plan without one).
pub fn plan_job(
    job: &Job,
    rig: &Rig,
    start: &[f64],
    settings: &PlanSettings,
) -> Result<Trajectory, JobError> {
    job.plan(&PlanContext {
        rig,
        app_rig: None,
        start,
        settings,
        model: None,
    })
}

/// `value` when it is finite and within `[low, high]`, else the refusal naming `key`.
pub(crate) fn in_range(key: &str, value: f64, low: f64, high: f64) -> Result<f64, JobInvalid> {
    if value.is_finite() && (low..=high).contains(&value) {
        Ok(value)
    } else {
        Err(JobInvalid::new(
            key,
            value,
            format!("must lie in [{low}, {high}]"),
        ))
    }
}

/// Config joint values in SI units: revolute axes are written in degrees, prismatic ones in
/// metres.
pub fn to_si(values: &[f64], rig: &Rig) -> Vec<f64> {
    values
        .iter()
        .zip(&rig.joints)
        .map(|(v, joint)| joint.kind.from_user(*v))
        .collect()
}

/// One configuration of `rig` in config units (degrees, metres for prismatic axes): one
/// finite value per axis, inside the axis' limits.
pub fn check_joints(key: &str, values: &[f64], rig: &Rig) -> Result<(), JobInvalid> {
    if values.len() != rig.dof() {
        return Err(JobInvalid::new(
            key,
            values,
            format!("needs {} values for rig {}", rig.dof(), rig.name),
        ));
    }
    if values.iter().any(|d| !d.is_finite()) {
        return Err(JobInvalid::new(key, values, "values must be finite"));
    }
    rig.check_limits(&to_si(values, rig))
        .map_err(|(index, outside)| {
            JobInvalid::new(
                format!("{key}[{index}]"),
                values[index],
                outside.to_string(),
            )
        })
}

/// A list of configurations: at least one, at most [`MAX_TARGETS`], each checked.
pub(crate) fn check_targets(key: &str, targets: &[Vec<f64>], rig: &Rig) -> Result<(), JobInvalid> {
    check_count(key, targets.len())?;
    for (i, target) in targets.iter().enumerate() {
        check_joints(&format!("{key}[{i}]"), target, rig)?;
    }
    Ok(())
}

/// At least one and at most [`MAX_TARGETS`] items.
pub(crate) fn check_count(key: &str, count: usize) -> Result<(), JobInvalid> {
    if count == 0 {
        return Err(JobInvalid::new(key, "[]", "needs at least one entry"));
    }
    if count > MAX_TARGETS {
        return Err(JobInvalid::new(
            key,
            format!("{count} entries"),
            format!("at most {MAX_TARGETS} entries"),
        ));
    }
    Ok(())
}
