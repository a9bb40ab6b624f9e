//! One cell of `rigbridge serve`: one run settings file, so one rig with its own twin behind
//! its own loopback link, its own job slot (one job at a time, on its own thread with its
//! own clock), its latest jobs and how they ended, and its own live hub and twin world.
//! Cells share nothing but the daemon's options and its job numbering; jobs in different
//! cells run concurrently. This file owns a cell's state and its job lifecycle and the startup check
//! that cells do not clash; HTTP routing and access control stay in `server.rs`, the choice
//! of a job's live scene in `scene.rs`.

use super::scene::scene_for_job;
use super::{JobWorld, LIVE_FRAME_RATE_HZ, ServeOptions};
use crate::clock::{Clock, VirtualClock, WallClock};
use crate::daemon::config::{JobConfig, RunSettings};
use crate::daemon::reset::{RESET_TIMEOUT, ResetOutcome, reset_controller};
use crate::daemon::{
    ActionLog, DaemonError, HeldActions, JobToStream, RunReport, Sinks, error_chain, held_position,
    plan_for, stream_job_with, stream_planned_with,
};
use crate::device::LinkSpec;
use crate::link::{Link, LinkCounters, LoopbackLink};
use crate::log::Recorder;
use crate::protocol::ControllerStatus;
use crate::stream::Phase;
use crate::stream::{
    Executor, Frame, Jog, ModelCheck, OnlineCommand, Outcome, SpeedOverride, StreamControl,
};
use crate::trajectory::Origins;
use crate::twin::SharedWorld;
use crate::view::{JobView, LiveHub, LiveSample, LiveSink, LiveSlot, PlanView};
use serde::Serialize;
use std::path::PathBuf;
use std::sync::{Arc, Mutex, OnceLock, PoisonError};
use thiserror::Error;
use tokio::sync::{oneshot, watch};

/// Why a set of run settings files cannot be served together.
#[derive(Debug, Error)]
pub enum CellError {
    #[error("no run settings: a daemon needs at least one cell")]
    Empty,
    #[error(
        "two cells named `{name}` ({first} and {second}): a cell is named by its rig's \
         `name`, give one of the rigs another name"
    )]
    DuplicateName {
        name: String,
        first: PathBuf,
        second: PathBuf,
    },
    #[error(
        "cells `{first_cell}` ({first}) and `{second_cell}` ({second}) both use the link \
         `{link}`: two rigs cannot share one controller connection"
    )]
    SharedLink {
        link: String,
        first_cell: String,
        first: PathBuf,
        second_cell: String,
        second: PathBuf,
    },
}

/// The device or address a link occupies ([`LinkSpec::occupied_resource`]).
fn occupied_resource(link: &str) -> Option<String> {
    link.parse::<LinkSpec>().ok()?.occupied_resource()
}

/// Refuses cells that cannot run side by side: none at all, two with the same name (their
/// routes would collide), or two on the same non-loopback link.
pub fn check_cells(cells: &[RunSettings]) -> Result<(), CellError> {
    if cells.is_empty() {
        return Err(CellError::Empty);
    }
    for (i, second) in cells.iter().enumerate() {
        for first in &cells[..i] {
            if first.rig.name == second.rig.name {
                return Err(CellError::DuplicateName {
                    name: second.rig.name.clone(),
                    first: first.file.clone(),
                    second: second.file.clone(),
                });
            }
            let link = occupied_resource(&second.config.stream.link);
            if link.is_some() && link == occupied_resource(&first.config.stream.link) {
                return Err(CellError::SharedLink {
                    link: second.config.stream.link.clone(),
                    first_cell: first.rig.name.clone(),
                    first: first.file.clone(),
                    second_cell: second.rig.name.clone(),
                    second: second.file.clone(),
                });
            }
        }
    }
    Ok(())
}

struct ActiveJob {
    id: u64,
    name: String,
    control: Arc<StreamControl>,
    /// The job's log while it streams, for the actions taken on it.
    actions: Arc<ActionLog>,
    /// Where its cycles count from and its planned duration, for its status.
    figures: Arc<JobFigures>,
    handle: std::thread::JoinHandle<()>,
}

impl ActiveJob {
    /// The job's status as of `latest`, the cell's latest streamed cycle; `period_s` the
    /// cell's cycle period.
    fn status(&self, latest: &LiveSample, period_s: f64) -> JobStatus {
        let cycles = self.figures.cycles_in(latest);
        let progress = self.control.progress();
        JobStatus {
            id: self.id,
            name: self.name.clone(),
            progress,
            cycles,
            elapsed_s: cycles as f64 * period_s,
            remaining_s: self.figures.remaining_s(progress),
            overruns: self.control.overruns(),
            paused: self.control.is_paused(),
            phase: self.control.phase(),
            log_error: self.actions.log_failure(),
        }
    }
}

/// What a job's status needs besides its controls: the cell's live slot's cycle count
/// when the job started (the slot counts every job's cycles; the job's own are those
/// since), and the planned duration of its path, set by the job's thread once planned
/// (never for an online session, which has no planned end). The cycle writes nothing here.
#[derive(Debug)]
struct JobFigures {
    first_cycle: u64,
    planned_s: OnceLock<f64>,
}

impl From<u64> for JobFigures {
    /// A job starting when the cell's slot has counted `first_cycle` cycles.
    fn from(first_cycle: u64) -> Self {
        JobFigures {
            first_cycle,
            planned_s: OnceLock::new(),
        }
    }
}

impl JobFigures {
    /// The cycles this job has streamed as of `latest`: 0 until its first.
    fn cycles_in(&self, latest: &LiveSample) -> u64 {
        latest.cycles.saturating_sub(self.first_cycle)
    }

    /// The planned duration less where the job is on its path (`progress` of it, 0..=1),
    /// at full speed: neither a pause nor the speed override is counted in.
    fn remaining_s(&self, progress: f64) -> Option<f64> {
        let planned = self.planned_s.get()?;
        Some((planned * (1.0 - progress.clamp(0.0, 1.0))).max(0.0))
    }
}

#[derive(Debug, Clone, Serialize)]
#[serde(tag = "result", rename_all = "snake_case")]
enum JobResult {
    Finished { id: u64, report: Box<RunReport> },
    Failed { id: u64, error: String },
}

/// `GET .../status`: the cell's job and its rig's actual position.
#[derive(Debug, Serialize)]
pub struct Status {
    cell: String,
    /// The link the cell streams over (`[stream] link`).
    link: String,
    state: &'static str,
    /// The latest control events (pause, resume, stop, e-stop, reset), oldest first.
    events: Vec<ControlEvent>,
    /// The controller's state as the cell knows it: a latched fault shows here until a
    /// reset clears it, whatever the last streamed cycle said.
    controller: ControllerView,
    job: Option<JobStatus>,
    last: Option<JobResult>,
    /// The rig's actual position per axis, in the axis' unit: while a job streams, as of
    /// its latest cycle; otherwise the in-process twin's own when the link is free (empty
    /// for a remote controller, and while a job holds the link before its first cycle).
    actual: Vec<AxisValue>,
    /// The position commanded in the running job's latest streamed cycle, per axis like
    /// `actual`; empty between jobs and until a job's first cycle.
    commanded: Vec<AxisValue>,
    /// The link's counters (as in the run report): the link's own while it is free, as of
    /// the last streamed cycle while a job holds it.
    link_counters: LinkCounters,
    /// The speed override every motion of the cell runs under, 0..=100 %.
    speed_percent: f64,
    /// What the in-process twin has measured of the cell since the running job started (or
    /// the last one ended): collision episodes, the closest pair within the cutoff. `null`
    /// for a remote controller; the last job's whole measurement is `last.report.contacts`.
    contacts: Option<crate::twin::contact::ContactStatus>,
}

/// The controller's state: `status` is `ok`, `holding`, `fault` or `unknown` (a remote
/// controller between jobs, with no fault known); `fault` says which, in words.
#[derive(Debug, Clone, Serialize)]
pub struct ControllerView {
    pub status: &'static str,
    pub fault: Option<String>,
}

/// One axis' value in its own unit: degrees for a revolute axis, metres for a prismatic one.
#[derive(Debug, Serialize)]
pub struct AxisValue {
    joint: String,
    value: f64,
    unit: &'static str,
}

/// One line of `GET /api/cells`.
#[derive(Debug, Serialize)]
pub struct CellSummary {
    name: String,
    link: String,
    dof: usize,
    joints: Vec<String>,
    state: &'static str,
    job: Option<JobStatus>,
}

#[derive(Debug, Clone, Serialize)]
pub struct JobStatus {
    id: u64,
    name: String,
    /// The share of the path done, 0..=1; after a resume (a link loss, a stall), of the
    /// part being streamed: the way back to the path, then the rest of it.
    progress: f64,
    /// Cycles this job has streamed (from 0 for each job; none while it plans or waits for
    /// the controller).
    cycles: u64,
    /// `cycles` in seconds of the job's clock: how long it has streamed, pauses included.
    elapsed_s: f64,
    /// The planned duration less where the job is on its path (`progress` of it), at full
    /// speed; `null` for an online session (no planned end) and until the job is planned.
    /// After a resume it counts from the part being streamed, so it overstates what is left.
    remaining_s: Option<f64>,
    /// Cycles that overran their budget on the shared executor (the job then went on on
    /// its own thread).
    overruns: u64,
    paused: bool,
    /// Where the session is in its life (docs/online.md): `streaming`, `holding`, ...
    phase: Phase,
    /// The job's log's first failed write, as soon as it failed (docs/logs.md); `null`
    /// while the log is sound.
    log_error: Option<crate::log::LogFailure>,
}

fn state_of(job: Option<&JobStatus>) -> &'static str {
    match job {
        Some(j) if j.paused => "paused",
        Some(_) => "running",
        None => "idle",
    }
}

/// Why a cell did not start a job.
#[derive(Debug)]
pub enum StartRefused {
    Busy,
    Poisoned,
    /// The job's thread could not be started (the system's thread limit, say).
    Spawn(std::io::Error),
    /// The controller has this fault latched: it must be reset first.
    Faulted(String),
}

/// A job handed to its thread: its number and kind, and whether planning succeeded (a bad
/// target is refused before any motion).
pub struct StartedJob {
    pub id: u64,
    pub name: String,
    pub planned: oneshot::Receiver<Result<(), NotPlanned>>,
}

/// A control request as the cell logged it.
#[derive(Debug, Clone, Serialize)]
pub struct ControlEvent {
    /// Seconds since the Unix epoch.
    at_s: f64,
    action: &'static str,
    /// The job it acted on; `None` when no job was running.
    job: Option<u64>,
    /// What came of it, where that is more than "applied" (a reset: the controller's words).
    #[serde(skip_serializing_if = "Option::is_none")]
    result: Option<String>,
}

/// The event of a job refused before it started (`POST /api/jobs`), logged rate-limited.
pub const JOB_REFUSED: &str = "job_refused";

/// The event of a JointTrajectory refused (docs/ros2.md), logged rate-limited.
pub const ROS2_REFUSED: &str = "ros2_trajectory_refused";

/// The name of an online session (jog, goal) in the status, the report and the log.
pub const ONLINE_SESSION: &str = "online";

/// An online command in words, for the cell's events.
fn describe(command: &OnlineCommand, rig: &crate::rig::Rig) -> String {
    match command {
        OnlineCommand::Goal(goal) => {
            let shown: Vec<String> = rig
                .joints
                .iter()
                .zip(goal.as_slice())
                .map(|(joint, q)| format!("{:.3}", joint.kind.to_user(*q)))
                .collect();
            format!("goal [{}]", shown.join(", "))
        }
        OnlineCommand::Jog(Jog::Joint { axis, direction }) => {
            let name = rig.joints.get(*axis).map_or("?", |j| j.name.as_str());
            format!(
                "joint jog {name} {}",
                if *direction > 0.0 { "+" } else { "-" }
            )
        }
        OnlineCommand::Jog(Jog::Cartesian { frame, direction }) => {
            let frame = match frame {
                Frame::Base => "base",
                Frame::Tool => "tool",
            };
            format!(
                "cartesian jog in the {frame} frame toward [{:.3}, {:.3}, {:.3}]",
                direction.x, direction.y, direction.z
            )
        }
        OnlineCommand::Release => "released".to_string(),
        OnlineCommand::Servo(target) => {
            let shown: Vec<String> = rig
                .joints
                .iter()
                .zip(target.joints.as_slice())
                .map(|(joint, q)| format!("{:.3}", joint.kind.to_user(*q)))
                .collect();
            format!("servo from [{}]", shown.join(", "))
        }
    }
}

/// How many control events a cell keeps for its status.
const KEPT_EVENTS: usize = 32;

/// How many jobs a cell remembers for `GET .../jobs`: enough for a client chaining a batch
/// of jobs to read each one's result well after it ended, while a daemon up for months
/// keeps a bounded memory (a finished `move_joints` job's record is about 1.5 kB of JSON,
/// so some 100 kB a cell).
pub const KEPT_JOBS: usize = 64;

/// One job of a cell's history: running until its thread records how it ended.
struct JobRecord {
    id: u64,
    name: String,
    ended: Option<JobResult>,
}

impl JobRecord {
    fn view(&self) -> RecordView<'_> {
        let (result, report, error) = match &self.ended {
            None => ("running", None, None),
            Some(JobResult::Finished { report, .. }) => ("finished", Some(&**report), None),
            Some(JobResult::Failed { error, .. }) => ("failed", None, Some(error.as_str())),
        };
        RecordView {
            id: self.id,
            name: &self.name,
            result,
            report,
            error,
        }
    }
}

/// A job as `GET .../jobs` and `GET .../jobs/{id}` show it: its number and name, `result`
/// (`running`, `finished`, `failed`) and, once it ended, its `report` or `error` as the
/// status' `last` has them.
#[derive(Serialize)]
struct RecordView<'a> {
    id: u64,
    name: &'a str,
    result: &'static str,
    #[serde(skip_serializing_if = "Option::is_none")]
    report: Option<&'a RunReport>,
    #[serde(skip_serializing_if = "Option::is_none")]
    error: Option<&'a str>,
}

/// A job of a cell's history as JSON ([`RecordView`]), and whether it still runs.
pub struct JobEntry {
    pub running: bool,
    pub json: serde_json::Value,
}

/// Where a cell's jobs stream: its own in-process twin, or a real link (`[stream] link`),
/// opened at the first job and kept (it reconnects by itself after a loss).
enum CellLink {
    Twin(Box<LoopbackLink>),
    Remote(Option<Box<dyn Link>>),
}

pub struct Cell {
    settings: RunSettings,
    link: Arc<Mutex<CellLink>>,
    /// The link's address as configured.
    link_name: String,
    events: Mutex<std::collections::VecDeque<ControlEvent>>,
    job: Mutex<Option<ActiveJob>>,
    last: Mutex<Option<JobResult>>,
    hub: LiveHub,
    /// The twin's world for the current job (the twin outlives jobs; its world does not).
    world: SharedWorld<JobWorld>,
    /// The cell's journal: every control action (reset included, which acts on no job) as an
    /// event, in `runs/cell-<name>-<time>-<pid>.mcap`; `None` until the daemon opens it.
    journal: Mutex<Option<Journal>>,
    /// Refusals logged rate-limited (in the journal too), with counts.
    refusals: Mutex<Refusals>,
    /// The fault the controller latched, as last learnt (a job that ended e-stopped or
    /// faulted, a reset it refused); cleared by a reset it carried out. The in-process
    /// twin's own status wins whenever the link is free to read it.
    latched: Mutex<Option<String>>,
    /// The daemon's shared executor, if it has one: the cycles of jobs on the in-process
    /// twin run there (a remote link's cycle waits for its echo, so it keeps its thread).
    executor: Option<Arc<Executor>>,
    /// The speed override of every session of the cell (`POST .../speed`).
    speed: Arc<SpeedOverride>,
    /// The in-process twin's collision watch, as its status reads it.
    contacts: Option<LiveContacts>,
    /// The latest jobs, newest first, at most [`KEPT_JOBS`].
    history: Mutex<std::collections::VecDeque<JobRecord>>,
    /// How many jobs have ended: a lookup that waits for a job's end wakes on its change.
    ended: watch::Sender<u64>,
    /// The servo client streaming to the cell, if one is (its address): one at a time.
    servo_client: Mutex<Option<String>>,
}

/// A servo client refused because another holds the cell's servo slot: one at a time.
#[derive(Debug, thiserror::Error)]
#[error("{holder} streams to cell `{cell}`: one servo client at a time")]
pub struct ServoTaken {
    pub holder: String,
    pub cell: String,
}

/// The cell's servo slot while a client holds it; dropping it frees the slot.
pub struct ServoClaim {
    cell: Arc<Cell>,
}

impl Drop for ServoClaim {
    fn drop(&mut self) {
        *self
            .cell
            .servo_client
            .lock()
            .unwrap_or_else(PoisonError::into_inner) = None;
    }
}

/// What a cell's status reads of its twin's collision watch while the twin runs.
struct LiveContacts {
    model: Arc<crate::cell::CollisionModel>,
    snapshot: Arc<Mutex<crate::twin::contact::ContactSnapshot>>,
    period_s: f64,
}

/// What a job's thread runs: a planned job, or an online session (jog, goal) from where
/// the arm holds.
pub enum Work {
    Job(JobConfig),
    Online,
}

/// Why an online command was not taken.
#[derive(Debug)]
pub enum OnlineRefused {
    /// A planned job runs: it takes a new goal, not a jog.
    JobRunning(u64),
    /// A keep-alive or a release with no session to act on.
    NoSession,
    Start(StartRefused),
}

/// Why a cell did not reset its controller.
#[derive(Debug)]
pub enum ResetRefused {
    /// A job is running (or holds the link).
    Busy,
    /// The link did not open, or the controller did not answer.
    Failed(String),
}

impl Cell {
    /// The cell of `settings`: its twin at the configured initial position, showing the
    /// configured job's scene until a job starts.
    pub fn new(
        settings: RunSettings,
        executor: Option<Arc<Executor>>,
    ) -> Result<Cell, DaemonError> {
        let (scene, job_world) = scene_for_job(&settings, &settings.config.job);
        let world = Arc::new(Mutex::new(JobWorld(job_world)));
        let twin = crate::daemon::settings_twin(&settings)?.with_world(Box::new(world.clone()));
        let contacts = twin.contacts().map(|watch| LiveContacts {
            model: watch.model().clone(),
            snapshot: watch.shared(),
            period_s: settings.period().as_secs_f64(),
        });
        let slot = Arc::new(LiveSlot::new(LiveSample::at_rest(&settings.initial())));
        let hub = LiveHub::new(
            settings.rig.clone(),
            settings.config.stream.rate_hz,
            LIVE_FRAME_RATE_HZ,
            slot,
            scene,
        );
        let hub = match crate::daemon::cell_drawing(&settings)? {
            Some(cell) => hub.with_cell(cell),
            None => hub,
        };
        let link_name = settings.config.stream.link.clone();
        let in_process = matches!(
            link_name.parse::<LinkSpec>(),
            Ok(LinkSpec::Loopback) | Err(_)
        );
        // The parts are the in-process twin's: a remote controller does not tell them.
        let hub = match twin.parts_board().filter(|_| in_process) {
            Some(board) => hub.with_parts(crate::view::PartsDrawing::new(&settings.cell, board)),
            None => hub,
        };
        let link = if in_process {
            CellLink::Twin(Box::new(LoopbackLink::new(twin)))
        } else {
            CellLink::Remote(None)
        };
        // A remote controller's clearances are its own: the in-process twin is not used.
        let contacts = contacts.filter(|_| matches!(link, CellLink::Twin(_)));
        Ok(Cell {
            settings,
            link: Arc::new(Mutex::new(link)),
            link_name,
            events: Mutex::default(),
            job: Mutex::new(None),
            last: Mutex::new(None),
            hub,
            world,
            journal: Mutex::new(None),
            refusals: Mutex::new(Refusals::new()),
            latched: Mutex::new(None),
            executor,
            speed: Arc::default(),
            contacts,
            history: Mutex::default(),
            ended: watch::Sender::new(0),
            servo_client: Mutex::new(None),
        })
    }

    /// Opens the cell's journal in `runs_dir` (see [`Journal`]); its path.
    pub fn open_journal(&self, runs_dir: &std::path::Path) -> Result<PathBuf, DaemonError> {
        let journal = Journal::create(runs_dir, &self.settings)?;
        let path = journal.path.clone();
        *self.journal.lock().unwrap_or_else(PoisonError::into_inner) = Some(journal);
        Ok(path)
    }

    /// Writes out and closes the journal (the daemon is stopping), after the refusals still
    /// being counted.
    pub fn close_journal(&self) {
        let pending = self.refusal_lock().drain(true);
        for summary in pending {
            self.log_summary(summary);
        }
        let journal = self
            .journal
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .take();
        if let Some(journal) = journal
            && let Err(e) = journal.finish()
        {
            tracing::error!(
                cell = %self.name(),
                "cell {}: closing its journal: {}",
                self.name(),
                error_chain(&e)
            );
        }
    }

    /// The rig's name: the cell's name in routes.
    pub fn name(&self) -> &str {
        &self.settings.rig.name
    }

    /// The run settings the cell was made from.
    pub fn settings(&self) -> &RunSettings {
        &self.settings
    }

    pub fn hub(&self) -> &LiveHub {
        &self.hub
    }

    /// The job of the cell's config (validated when it was loaded).
    pub fn configured_job(&self) -> JobConfig {
        self.settings.config.job.clone()
    }

    /// `job` checked for this cell's rig exactly as its config's `[job]` was, files resolved
    /// in the config's directory. The refusal is the text a config would get; why a named
    /// file would not load goes to the daemon's log only, never to the client.
    pub fn validate(&self, job: JobConfig) -> Result<JobConfig, crate::job::JobInvalid> {
        let base_dir = crate::daemon::config::config_dir(&self.settings.file);
        let context = crate::job::JobContext {
            rig: &self.settings.tcp_rig,
            cell: &self.settings.cell,
            sloth: self.settings.sloth.as_deref(),
            base_dir: &base_dir,
            limits: &self.settings.config.limits,
            period: self.settings.period(),
        };
        job.validate(&context).map_err(|mut refused| {
            if let Some(cause) = refused.cause.take() {
                tracing::warn!(
                    cell = %self.name(),
                    "cell {}: job refused: {refused}: {}",
                    self.name(),
                    error_chain(cause.as_ref())
                );
            }
            refused
        })
    }

    /// Logs a control action: on stderr, in the status' events, in the cell's journal, and
    /// (`on_job`: the job it acted on) in that job's log, at the job's time (its cycle).
    fn log_event(
        &self,
        action: &'static str,
        job: Option<u64>,
        result: Option<String>,
        on_job: Option<(&HeldActions<'_>, &StreamControl)>,
    ) {
        let at_s = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0.0, |d| d.as_secs_f64());
        let shown = job.map_or("no job".to_string(), |id| format!("job {id}"));
        let cell = self.name();
        match &result {
            Some(result) => tracing::info!(
                cell = %cell,
                action = %action,
                job,
                "cell {cell}: {action} ({shown}): {result}"
            ),
            None => {
                tracing::info!(cell = %cell, action = %action, job, "cell {cell}: {action} ({shown})")
            }
        }
        let mut detail = serde_json::json!({ "job": job, "unix_s": at_s });
        if let Some(result) = &result {
            detail["result"] = result.clone().into();
        }
        if let Some((actions, control)) = on_job {
            // The cycle it reached: the time base of the log's `job_ended` (cycles x period).
            let seq = control.cycles();
            detail["seq"] = seq.into();
            actions.record(
                seq as f64 * self.settings.period().as_secs_f64(),
                action,
                detail.clone(),
            );
        }
        if let Some(journal) = &mut *self.journal.lock().unwrap_or_else(PoisonError::into_inner) {
            journal.record(action, detail);
        }
        let mut events = self.events.lock().unwrap_or_else(PoisonError::into_inner);
        if events.len() == KEPT_EVENTS {
            events.pop_front();
        }
        events.push_back(ControlEvent {
            at_s,
            action,
            job,
            result,
        });
    }

    /// Logs what came of a JointTrajectory received over ROS 2 (docs/ros2.md) the way a
    /// control action is logged: on stderr, in the status' events and in the journal. Its
    /// refusals ([`ROS2_REFUSED`]) arrive already rate-limited and numbered by the ROS 2
    /// side (`daemon::ros2::Refusals`, at most one a second), so they are not limited twice.
    pub fn log_ros2(&self, action: &'static str, job: Option<u64>, result: String) {
        self.log_event(action, job, Some(result), None);
    }

    /// Logs a refused job (`action`: [`JOB_REFUSED`]) like a
    /// control action, but rate-limited: the first of each [`REFUSAL_WINDOW`] in full, the
    /// rest counted and told as one summary with the last reason once the window is over.
    pub fn log_refusal(&self, action: &'static str, job: Option<u64>, reason: String) {
        let (full, closed) = self.refusal_lock().admit(action, &reason);
        if let Some(summary) = closed {
            self.log_summary(summary);
        }
        if full {
            self.log_event(action, job, Some(reason), None);
        }
    }

    /// Summaries of the refusal windows that are over: the status asks, so a flood that
    /// stopped is still told.
    fn flush_refusals(&self) {
        let over = self.refusal_lock().drain(false);
        for summary in over {
            self.log_summary(summary);
        }
    }

    fn log_summary(&self, summary: RefusalSummary) {
        self.log_event(summary.action, None, Some(summary.to_string()), None);
    }

    fn refusal_lock(&self) -> std::sync::MutexGuard<'_, Refusals> {
        self.refusals.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Whether the cell streams to its in-process twin, whose position is known before any
    /// job (a remote controller's is known only once it answers).
    pub fn streams_to_twin(&self) -> bool {
        matches!(
            self.link_name.parse::<LinkSpec>(),
            Ok(LinkSpec::Loopback) | Err(_)
        )
    }

    fn running(&self) -> Option<JobStatus> {
        self.running_as_of(&self.hub.slot().latest())
    }

    /// The running job's status, its cycles counted as of `latest` (the cell's latest
    /// streamed cycle, read before the job slot is locked: the slot's lock is never held
    /// inside the job's).
    fn running_as_of(&self, latest: &LiveSample) -> Option<JobStatus> {
        let period_s = self.settings.period().as_secs_f64();
        let job = self.job.lock().unwrap_or_else(PoisonError::into_inner);
        job.as_ref()
            .filter(|j| !j.handle.is_finished())
            .map(|j| j.status(latest, period_s))
    }

    /// `values` (rad or m, in the rig's joint order) per axis in the axis' unit.
    fn axis_values(&self, values: &[f64]) -> Vec<AxisValue> {
        self.settings
            .rig
            .joints
            .iter()
            .zip(values)
            .map(|(joint, q)| AxisValue {
                joint: joint.name.clone(),
                value: joint.kind.to_user(*q),
                unit: joint.kind.unit(),
            })
            .collect()
    }

    /// The actual and the commanded position: a running job's from its latest streamed
    /// cycle (the live view's slot: the cycle only ever `try_lock`s it, so this read never
    /// holds a cycle up); between jobs the in-process twin's actual position.
    fn positions(
        &self,
        job: Option<&JobStatus>,
        latest: &LiveSample,
    ) -> (Vec<AxisValue>, Vec<AxisValue>) {
        if job.is_some_and(|job| job.cycles > 0) {
            return (
                self.axis_values(latest.actual.as_slice()),
                self.axis_values(latest.commanded.as_slice()),
            );
        }
        // A job holds the link from its start until it ends: before its first cycle its
        // position is not known here.
        match self.link.try_lock().as_deref() {
            Ok(CellLink::Twin(link)) => (self.axis_values(link.twin().actual()), Vec::new()),
            _ => (Vec::new(), Vec::new()),
        }
    }

    pub fn status(&self) -> Status {
        self.flush_refusals();
        let latest = self.hub.slot().latest();
        let job = self.running_as_of(&latest);
        let controller = self.controller();
        let (actual, commanded) = self.positions(job.as_ref(), &latest);
        Status {
            cell: self.name().to_string(),
            link: self.link_name.clone(),
            events: self
                .events
                .lock()
                .unwrap_or_else(PoisonError::into_inner)
                .iter()
                .cloned()
                .collect(),
            controller,
            state: state_of(job.as_ref()),
            job,
            last: self.last().clone(),
            actual,
            commanded,
            link_counters: self.link_counters(),
            speed_percent: 100.0 * self.speed.fraction(),
            contacts: self.contacts.as_ref().map(|live| {
                let snapshot = crate::twin::ContactReport::read(&live.snapshot);
                crate::twin::ContactWatch::describe(&live.model, &snapshot, live.period_s)
            }),
        }
    }

    fn link_counters(&self) -> LinkCounters {
        match self.link.try_lock().as_deref() {
            Ok(CellLink::Twin(link)) => link.counters(),
            Ok(CellLink::Remote(Some(link))) => link.counters(),
            _ => self.hub.slot().latest().counters,
        }
    }

    /// The controller's state: the in-process twin's own when the link is free, otherwise
    /// the fault last learnt (none known: `ok` while a job streams, `unknown` between jobs
    /// on a remote link).
    pub fn controller(&self) -> ControllerView {
        if let Ok(guard) = self.link.try_lock()
            && let CellLink::Twin(link) = &*guard
        {
            let status = link.twin().status();
            return ControllerView {
                status: match status {
                    ControllerStatus::Ok => "ok",
                    ControllerStatus::Holding => "holding",
                    ControllerStatus::Fault(_) => "fault",
                },
                fault: match status {
                    ControllerStatus::Fault(fault) => Some(fault.to_string()),
                    _ => None,
                },
            };
        }
        let latched = self.latched_fault();
        ControllerView {
            status: match (&latched, self.running()) {
                (Some(_), _) => "fault",
                (None, Some(_)) => "ok",
                (None, None) => "unknown",
            },
            fault: latched,
        }
    }

    fn latched_fault(&self) -> Option<String> {
        self.latched
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }

    fn set_latched(&self, fault: Option<String>) {
        *self.latched.lock().unwrap_or_else(PoisonError::into_inner) = fault;
    }

    /// Sends Reset to the cell's controller when no job runs, and waits for its answer
    /// (docs/protocol.md 6.7). Logged like the other control actions.
    pub fn reset(&self) -> Result<ResetOutcome, ResetRefused> {
        if self.running().is_some() {
            return Err(ResetRefused::Busy);
        }
        let result = {
            let Ok(mut guard) = self.link.try_lock() else {
                return Err(ResetRefused::Busy);
            };
            match &mut *guard {
                CellLink::Twin(twin) => reset_controller(twin.as_mut(), RESET_TIMEOUT),
                CellLink::Remote(remote) => self
                    .remote(remote, &StreamControl::default())
                    .and_then(|link| reset_controller(link, RESET_TIMEOUT)),
            }
        };
        match result {
            Ok(outcome) => {
                self.set_latched(match &outcome {
                    ResetOutcome::Kept(words) => Some(words.clone()),
                    _ => None,
                });
                self.log_event("reset", None, Some(outcome.to_string()), None);
                Ok(outcome)
            }
            Err(error) => {
                let text = error_chain(&error);
                self.log_event("reset", None, Some(format!("failed: {text}")), None);
                Err(ResetRefused::Failed(text))
            }
        }
    }

    pub fn summary(&self) -> CellSummary {
        let job = self.running();
        CellSummary {
            name: self.name().to_string(),
            link: self.link_name.clone(),
            dof: self.settings.rig.dof(),
            joints: self
                .settings
                .rig
                .joints
                .iter()
                .map(|j| j.name.clone())
                .collect(),
            state: state_of(job.as_ref()),
            job,
        }
    }

    fn last(&self) -> std::sync::MutexGuard<'_, Option<JobResult>> {
        self.last.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// The job as the live view shows it.
    pub fn job_view(&self) -> JobView {
        let last = self.last().as_ref().map(|result| match result {
            JobResult::Finished { report, .. } => serde_json::to_value(report.stream.outcome)
                .ok()
                .and_then(|v| v.as_str().map(String::from))
                .unwrap_or_default(),
            JobResult::Failed { error, .. } => format!("failed: {error}"),
        });
        let controller = self.controller().fault;
        let last_log_error = self.last().as_ref().and_then(|result| match result {
            JobResult::Finished { report, .. } => {
                report.log_error.as_ref().map(|e| e.error.clone())
            }
            JobResult::Failed { .. } => None,
        });
        match self.running() {
            Some(job) => JobView {
                state: state_of(Some(&job)),
                id: Some(job.id),
                name: Some(job.name),
                progress: job.progress,
                last,
                controller,
                log_error: job.log_error.map(|failure| failure.error),
            },
            None => JobView {
                state: "idle",
                last,
                controller,
                log_error: last_log_error,
                ..JobView::default()
            },
        }
    }

    /// Starts `job` as number `id` on its own thread, unless one is running here: the check
    /// and the start hold the job slot together, so two requests cannot both start.
    pub fn start(
        self: &Arc<Self>,
        id: u64,
        job: JobConfig,
        options: &ServeOptions,
    ) -> Result<StartedJob, StartRefused> {
        self.start_work(id, Work::Job(job), None, options)
    }

    /// Starts `work` as number `id` (an online session with its `first` command), unless a
    /// job is running here.
    fn start_work(
        self: &Arc<Self>,
        id: u64,
        work: Work,
        first: Option<OnlineCommand>,
        options: &ServeOptions,
    ) -> Result<StartedJob, StartRefused> {
        // Asked before the job slot is taken: for a remote link `controller` reads the slot
        // itself, and a second lock of it on this thread would never return.
        let fault = self.controller().fault;
        let Ok(mut slot) = self.job.lock() else {
            return Err(StartRefused::Poisoned);
        };
        if slot.as_ref().is_some_and(|j| !j.handle.is_finished()) {
            return Err(StartRefused::Busy);
        }
        if let Some(fault) = fault {
            return Err(StartRefused::Faulted(fault));
        }
        let name = match &work {
            Work::Job(job) => job.kind().to_string(),
            Work::Online => ONLINE_SESSION.to_string(),
        };
        let control = Arc::new(StreamControl::with_speed(self.speed.clone()));
        // Jog and goal targets are made in the cycle, never checked as a whole trajectory:
        // the cell's model checks each step before it is sent.
        control.set_cell_check(Arc::new(ModelCheck::new(self.settings.collision.clone())));
        if let Some(command) = first {
            control.online().open_session();
            control.online().give(command);
        }
        let actions = Arc::new(ActionLog::default());
        // No job streams now (the last one's thread is done): the slot's count is final.
        let figures = Arc::new(JobFigures::from(self.hub.slot().latest().cycles));
        let (planned_tx, planned) = oneshot::channel();
        let job_io = JobIo {
            control: control.clone(),
            actions: actions.clone(),
            figures: figures.clone(),
            planned: planned_tx,
        };
        // In the history before the thread starts, so its end always finds it there.
        self.remember(id, &name);
        let handle = match self.spawn_job(id, work, job_io, options) {
            Ok(handle) => handle,
            Err(e) => {
                self.forget(id);
                return Err(StartRefused::Spawn(e));
            }
        };
        *slot = Some(ActiveJob {
            id,
            name: name.clone(),
            control,
            actions,
            figures,
            handle,
        });
        Ok(StartedJob { id, name, planned })
    }

    fn history(&self) -> std::sync::MutexGuard<'_, std::collections::VecDeque<JobRecord>> {
        self.history.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Job `id` starts: the newest of the history, which forgets its oldest beyond
    /// [`KEPT_JOBS`].
    fn remember(&self, id: u64, name: &str) {
        let mut history = self.history();
        history.push_front(JobRecord {
            id,
            name: name.to_string(),
            ended: None,
        });
        history.truncate(KEPT_JOBS);
    }

    /// Job `id` never started (its thread did not).
    fn forget(&self, id: u64) {
        self.history().retain(|record| record.id != id);
    }

    /// How job `id` ended: in its history record and as the cell's last result, then told
    /// to whoever waits for a job's end.
    fn record_end(&self, id: u64, result: JobResult) {
        if let Some(record) = self.history().iter_mut().find(|r| r.id == id) {
            record.ended = Some(result.clone());
        }
        *self.last() = Some(result);
        self.ended
            .send_modify(|ended| *ended = ended.wrapping_add(1));
    }

    /// A receiver whose value changes whenever a job of the cell ends.
    pub fn job_ends(&self) -> watch::Receiver<u64> {
        self.ended.subscribe()
    }

    /// The cell's remembered jobs, newest first, as JSON ([`RecordView`]).
    pub fn jobs(&self) -> Result<Vec<serde_json::Value>, serde_json::Error> {
        self.history()
            .iter()
            .map(|record| serde_json::to_value(record.view()))
            .collect()
    }

    /// Job `id` as JSON ([`RecordView`]); `None` when it never ran in this cell or is
    /// older than the [`KEPT_JOBS`] the cell remembers.
    pub fn job_entry(&self, id: u64) -> Option<Result<JobEntry, serde_json::Error>> {
        let history = self.history();
        let record = history.iter().find(|record| record.id == id)?;
        Some(serde_json::to_value(record.view()).map(|json| JobEntry {
            running: record.ended.is_none(),
            json,
        }))
    }

    /// Frees the job slot once the running job's end is recorded: its thread is then
    /// returning, so the join is short. A client told that a job ended can start the next
    /// at once, never to be answered "busy" by a thread still on its way out.
    pub fn settle(&self) {
        let mut slot = self.job.lock().unwrap_or_else(PoisonError::into_inner);
        let Some(id) = slot.as_ref().map(|job| job.id) else {
            return;
        };
        let ended = self
            .history()
            .iter()
            .any(|record| record.id == id && record.ended.is_some());
        if ended && let Some(job) = slot.take() {
            let _ = job.handle.join();
        }
    }

    /// Plans and streams one job on its own thread, reporting through `last`. A panic in
    /// the job (or in `options.before_job`) ends only this job.
    fn spawn_job(
        self: &Arc<Self>,
        id: u64,
        job: Work,
        io: JobIo,
        options: &ServeOptions,
    ) -> std::io::Result<std::thread::JoinHandle<()>> {
        let cell = self.clone();
        let virtual_clock = options.virtual_clock;
        let before_job = options.before_job.clone();
        let log = options.runs_dir.join(job_log_name(id));
        // Named for `ps -L`: docs/realtime.md checks the job's priority by this name.
        std::thread::Builder::new()
            .name("rigbridge-job".into())
            .spawn(move || {
                let clock: Box<dyn Clock> = if virtual_clock {
                    Box::new(VirtualClock::new())
                } else {
                    Box::new(WallClock::new())
                };
                let result = contain_panic(|| {
                    if let Some(hook) = &before_job {
                        hook(cell.name(), id);
                    }
                    cell.run_job(&job, io, clock.as_ref(), &log)
                });
                let outcome = cell.job_result(id, result);
                cell.record_end(id, outcome);
            })
    }

    /// How job `id` ended, from what its thread returned: the controller's latched fault
    /// learnt from a report, a panic logged and the link made usable for the next job.
    fn job_result(
        &self,
        id: u64,
        result: Result<Result<RunReport, DaemonError>, Panicked>,
    ) -> JobResult {
        match result {
            Ok(Ok(report)) => {
                self.learn_from(&report);
                JobResult::Finished {
                    id,
                    report: Box::new(report),
                }
            }
            Ok(Err(e)) => JobResult::Failed {
                id,
                error: error_chain(&e),
            },
            Err(panic) => {
                let name = self.name();
                tracing::error!(
                    cell = %name,
                    job = id,
                    "cell {name}: job {id} panicked: {panic}"
                );
                // The job is gone; the next one must still find the link.
                self.link.clear_poison();
                JobResult::Failed {
                    id,
                    error: format!("the job failed unexpectedly: {panic}"),
                }
            }
        }
    }

    fn run_job(
        &self,
        work: &Work,
        io: JobIo,
        clock: &dyn Clock,
        log: &std::path::Path,
    ) -> Result<RunReport, DaemonError> {
        let JobIo {
            control,
            actions,
            figures,
            planned,
        } = io;
        let control = &*control;
        let Ok(mut guard) = self.link.lock() else {
            let _ = planned.send(Err(NotPlanned("twin lock poisoned".into())));
            return Err(DaemonError::Unavailable("twin lock poisoned".into()));
        };
        let executor = match &*guard {
            CellLink::Twin(_) if !clock.is_virtual() => self.executor.as_deref(),
            _ => None,
        };
        let remote = matches!(&*guard, CellLink::Remote(_));
        let link: &mut dyn Link = match &mut *guard {
            CellLink::Twin(twin) => twin.as_mut(),
            CellLink::Remote(remote) => match self.remote(remote, control) {
                Ok(link) => link,
                Err(e) => {
                    let _ = planned.send(Err(NotPlanned(error_chain(&e))));
                    return Err(e);
                }
            },
        };
        // A device-paced link (EGM) brings the clock the cycle must follow, as in `run`.
        let pacing = link.pacing();
        let clock: &dyn Clock = pacing.as_deref().unwrap_or(clock);
        let job = match work {
            Work::Job(job) => job,
            Work::Online => {
                let _ = planned.send(Ok(()));
                return self.run_online(link, clock, control, &actions, executor, log);
            }
        };
        let plan = plan_for(&self.settings, job, link, clock, control);
        let _ = planned.send(match &plan {
            // The job was taken; a stop ended it before any motion (its report says so).
            Ok(_) | Err(DaemonError::Halted(_)) => Ok(()),
            Err(e) => Err(NotPlanned(error_chain(e))),
        });
        let plan = match plan {
            Err(DaemonError::Halted(halted)) => {
                return Ok(halted.report(&self.settings, &job.name(), link, clock));
            }
            plan => plan?,
        };
        let _ = figures.planned_s.set(plan.trajectory.duration_s());
        let (scene, world) = scene_for_job(&self.settings, job);
        // Nothing streams yet: the twin is not observing.
        self.world.lock().unwrap_or_else(PoisonError::into_inner).0 = world;
        // Drawn from the plan itself, whatever kind of job made it: jobs are planned at
        // the tool's TCP, so that is the path shown.
        let plan_view = PlanView::of(&self.settings.tcp_rig, &plan.trajectory, &plan.origins);
        self.hub.set_job_scene(scene, Some(plan_view));
        self.hub.set_steps(job.step_spans(&plan.origins));
        let rate = self.settings.config.stream.rate_hz.round() as u64;
        let mut live = LiveSink::new(self.hub.slot(), rate);
        // A device-paced link keeps its own pacing, on this thread.
        let executor = executor.filter(|_| pacing.is_none());
        if remote && !clock.is_virtual() {
            self.rise_for_cycles();
        }
        let sinks = Sinks {
            live: &mut live,
            actions: Some(&actions),
            executor,
        };
        stream_planned_with(
            &self.settings,
            &plan,
            link,
            clock,
            Some(log),
            control,
            sinks,
        )
    }

    /// An online session: from where the arm holds, its motion is the online commands'
    /// (docs/online.md); it ends stopped, or once it has been at rest with nothing to do
    /// for [`crate::stream::IDLE_END`].
    fn run_online(
        &self,
        link: &mut dyn Link,
        clock: &dyn Clock,
        control: &StreamControl,
        actions: &ActionLog,
        executor: Option<&Executor>,
        log: &std::path::Path,
    ) -> Result<RunReport, DaemonError> {
        let start = match held_position(&self.settings, link, clock, control) {
            Err(DaemonError::Halted(halted)) => {
                return Ok(halted.report(&self.settings, ONLINE_SESSION, link, clock));
            }
            start => start?,
        };
        let trajectory = crate::daemon::hold_at(&self.settings, &start)?;
        let rate = self.settings.config.stream.rate_hz.round() as u64;
        let mut live = LiveSink::new(self.hub.slot(), rate);
        let origins = Origins::whole("the online session's hold");
        let job = JobToStream {
            name: ONLINE_SESSION.to_string(),
            description: serde_json::json!({ "kind": ONLINE_SESSION }),
            start: &start,
            trajectory: &trajectory,
            job: None,
            origins: &origins,
            // The hold is where the arm already is (checking it could only keep an arm
            // that stopped within the margin from being jogged out); every step the
            // session then makes is checked by the cell's ModelCheck before it is sent.
            cleared: true,
        };
        let sinks = Sinks {
            live: &mut live,
            actions: Some(actions),
            executor: executor.filter(|_| link.pacing().is_none()),
        };
        stream_job_with(&self.settings, &job, link, clock, Some(log), control, sinks)
    }

    /// Sets the speed override of every motion of the cell (0..=1), logged with the job it
    /// acted on; false when `fraction` is outside 0..=1.
    pub fn set_speed(&self, fraction: f64) -> bool {
        if !self.speed.set(fraction) {
            return false;
        }
        let job = self.job.lock().unwrap_or_else(PoisonError::into_inner);
        let running = job.as_ref().filter(|j| !j.handle.is_finished());
        let held = running.map(|j| (j.actions.hold_open(), &*j.control));
        let on_job = held.as_ref().map(|(actions, control)| (actions, *control));
        let result = Some(format!("{:.1} %", 100.0 * fraction));
        self.log_event("speed", running.map(|j| j.id), result, on_job);
        true
    }

    /// The id of the planned job running here, if one is (it refuses a servo client).
    pub fn planned_job(&self) -> Option<u64> {
        let job = self.job.lock().unwrap_or_else(PoisonError::into_inner);
        job.as_ref()
            .filter(|j| !j.handle.is_finished() && j.name != ONLINE_SESSION)
            .map(|j| j.id)
    }

    /// Hands an online command to the running session, or starts a session for it (a jog
    /// or a goal, numbered by `next_id`); a planned job takes a goal (it blends from where
    /// the arm is) but not a jog. `log`: the action to log it as (keep-alives are not).
    pub fn online(
        self: &Arc<Self>,
        command: Option<OnlineCommand>,
        log: Option<&'static str>,
        next_id: impl FnOnce() -> u64,
        options: &ServeOptions,
    ) -> Result<u64, OnlineRefused> {
        let job = self.job.lock().unwrap_or_else(PoisonError::into_inner);
        let running = job.as_ref().filter(|j| !j.handle.is_finished());
        if let Some(running) = running {
            let online = running.control.online();
            match command {
                Some(OnlineCommand::Jog(_)) if !online.given() => {
                    return Err(OnlineRefused::JobRunning(running.id));
                }
                // A planned job's motion is not a servo client's, even after a new goal.
                Some(OnlineCommand::Servo(_)) if running.name != ONLINE_SESSION => {
                    return Err(OnlineRefused::JobRunning(running.id));
                }
                Some(command) => online.give(command),
                None => online.keep_alive(),
            }
            if let Some(action) = log {
                let held = (running.actions.hold_open(), &*running.control);
                let result = command.map(|c| describe(&c, &self.settings.rig));
                self.log_event(action, Some(running.id), result, Some((&held.0, held.1)));
            }
            return Ok(running.id);
        }
        drop(job);
        let Some(
            command @ (OnlineCommand::Jog(_) | OnlineCommand::Goal(_) | OnlineCommand::Servo(_)),
        ) = command
        else {
            return Err(OnlineRefused::NoSession);
        };
        let id = next_id();
        self.start_work(id, Work::Online, Some(command), options)
            .map_err(OnlineRefused::Start)?;
        if let Some(action) = log {
            let result = Some(describe(&command, &self.settings.rig));
            self.log_event(action, Some(id), result, None);
        }
        Ok(id)
    }

    /// Takes the cell's servo slot for `client` (its address), or names the client that
    /// holds it.
    pub fn claim_servo(self: &Arc<Self>, client: &str) -> Result<ServoClaim, ServoTaken> {
        let mut slot = self
            .servo_client
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        if let Some(holder) = slot.as_ref() {
            return Err(ServoTaken {
                holder: holder.clone(),
                cell: self.name().to_string(),
            });
        }
        *slot = Some(client.to_string());
        Ok(ServoClaim { cell: self.clone() })
    }

    /// Where the arm is commanded (SI units): the running session's latest target, else
    /// the in-process twin's position; `None` when neither is known (a remote controller
    /// between jobs).
    pub fn current_position(&self) -> Option<Vec<f64>> {
        let latest = self.hub.slot().latest();
        if self
            .running_as_of(&latest)
            .is_some_and(|job| job.cycles > 0)
        {
            return Some(latest.commanded.as_slice().to_vec());
        }
        match self.link.try_lock().as_deref() {
            Ok(CellLink::Twin(link)) => Some(link.twin().actual().to_vec()),
            _ => None,
        }
    }

    /// Moves the job's thread, planning done, to the cycles' priority, for the cycles of a
    /// remote (or device-paced) link: a real controller's. The twin's cycles are the shared
    /// executor's; with a thread per cell, or handed back by the executor, they stay at
    /// normal priority, since a hundred real-time threads that spin would starve the
    /// control API (an e-stop among its requests) once they outgrow the CPUs.
    fn rise_for_cycles(&self) {
        if let Err(e) = crate::realtime::raise_priority(crate::realtime::CYCLE_PRIORITY) {
            let name = self.name();
            tracing::warn!(
                cell = %name,
                "cell {name}: the job streams at normal priority (real-time scheduling refused: {e})"
            );
        }
    }

    /// What a finished job tells of the controller: an e-stop or a fault it latched.
    fn learn_from(&self, report: &RunReport) {
        let stream = &report.stream;
        match stream.outcome {
            Outcome::EStopped => self.set_latched(Some("e-stop".into())),
            Outcome::Faulted => self.set_latched(Some(
                stream
                    .fault
                    .clone()
                    .unwrap_or_else(|| "controller fault".into()),
            )),
            _ => {}
        }
    }

    /// The remote link, opened now if it is not yet (or its last opening failed).
    /// The wait for it ends early on `control`'s stop (a reset's control is never stopped).
    fn remote<'a>(
        &self,
        remote: &'a mut Option<Box<dyn Link>>,
        control: &StreamControl,
    ) -> Result<&'a mut dyn Link, DaemonError> {
        if remote.is_none() {
            let spec = self
                .link_name
                .parse::<LinkSpec>()
                .map_err(|e| DaemonError::Unavailable(e.reason))?;
            *remote = Some(crate::daemon::open_link_for(
                &spec,
                &self.settings,
                control,
            )?);
        }
        match remote.as_deref_mut() {
            Some(link) => Ok(link),
            None => Err(DaemonError::Unavailable("the link did not open".into())),
        }
    }

    /// Applies `act` (called `action` in the cell's events) to the running job; its number,
    /// or `None` when no job runs.
    pub fn control(&self, action: &'static str, act: impl Fn(&StreamControl)) -> Option<u64> {
        self.act_on_job(action, |control| {
            act(control);
            None
        })
        .map(|(id, _)| id)
    }

    /// Asks the running job to stop or e-stop (`request`, called `action` in the cell's
    /// events): its number and the phase it was in when the request was acknowledged, or
    /// `None` when no job runs.
    pub fn halt(
        &self,
        action: &'static str,
        request: impl Fn(&StreamControl) -> Phase,
    ) -> Option<(u64, Phase)> {
        let (id, phase) = self.act_on_job(action, |control| Some(request(control)))?;
        phase.map(|phase| (id, phase))
    }

    /// Applies `act` to the running job and logs it with what `act` returned, the phase of
    /// a stop (in words: `while planning`).
    fn act_on_job(
        &self,
        action: &'static str,
        act: impl Fn(&StreamControl) -> Option<Phase>,
    ) -> Option<(u64, Option<Phase>)> {
        let job = self.job.lock().unwrap_or_else(PoisonError::into_inner);
        let running = job.as_ref().filter(|j| !j.handle.is_finished());
        // Held across the act and its record: the job it ends cannot close its log between.
        let held = running.map(|j| (j.actions.hold_open(), &*j.control));
        let phase = running.and_then(|running| act(&running.control));
        let id = running.map(|j| j.id);
        let on_job = held.as_ref().map(|(actions, control)| (actions, *control));
        let result = phase.map(|phase| format!("while {phase}"));
        self.log_event(action, id, result, on_job);
        id.map(|id| (id, phase))
    }

    /// Waits for the thread of job `id` (refused at planning, so about to end) and frees
    /// the cell's job slot.
    pub fn reap(&self, id: u64) {
        let mut slot = self.job.lock().unwrap_or_else(PoisonError::into_inner);
        if slot.as_ref().is_some_and(|job| job.id == id)
            && let Some(job) = slot.take()
        {
            let _ = job.handle.join();
        }
    }

    /// Stops any job (decelerating along its path) and waits for its thread.
    pub fn stop_and_wait(&self) {
        let active = self
            .job
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .take();
        if let Some(job) = active {
            job.control.stop();
            let _ = job.handle.join();
        }
    }
}

/// What a job's thread shares with the cell: its controls, its log's action slot, and
/// where to say whether planning succeeded (a bad target is refused before any motion).
struct JobIo {
    control: Arc<StreamControl>,
    actions: Arc<ActionLog>,
    figures: Arc<JobFigures>,
    planned: oneshot::Sender<Result<(), NotPlanned>>,
}

/// A cell's journal: MCAP logs (`docs/logs.md`) holding only events, one per control
/// action on the cell (`pause`, `resume`, `stop`, `estop`, `reset`) and per refusal
/// (rate-limited, [`Refusals`]), at seconds since the daemon started, with the job acted
/// on, the Unix time and the result. Unlike a job's log it also holds the resets, which act
/// on no job. It rotates: once a file has taken [`JournalCap::file_bytes`] a new one is
/// begun (`cell-<rig>-<unix>-<pid>-<part>.mcap`), and only the newest
/// [`JournalCap::files`] are kept, so a flood of events cannot fill the disk.
struct Journal {
    /// The file being written.
    path: PathBuf,
    recorder: Recorder,
    clock: WallClock,
    /// What the journal needs to begin its next file.
    setup: JournalSetup,
    /// Bytes the current file has taken, as counted by [`event_bytes`] (at least what it
    /// holds on disk).
    written: u64,
    /// The files kept, oldest first, the current one last.
    kept: std::collections::VecDeque<PathBuf>,
    cap: JournalCap,
}

/// How much journal a cell keeps.
#[derive(Debug, Clone, Copy, PartialEq)]
struct JournalCap {
    file_bytes: u64,
    files: usize,
}

/// Each journal file up to 4 MB (about 10,000 events) and four of them: 16 MB a cell at
/// most, for months of control actions at any human pace, while a flood of events
/// (rate-limited refusals are one a window) rotates rather than fills the disk.
const JOURNAL_CAP: JournalCap = JournalCap {
    file_bytes: 4 * 1024 * 1024,
    files: 4,
};

/// Room counted in each file before its first event: the MCAP header, the journal's
/// metadata, and the summary and footer written when it is closed.
const JOURNAL_FILE_RESERVE: u64 = 16 * 1024;

/// What an event costs a journal file beyond its kind and detail: its message record, its
/// index entry and, since the journal's chunks close on a timer, a chunk of its own with
/// that chunk's index in the summary. An over-count: rotation comes early, never late.
const JOURNAL_EVENT_OVERHEAD: u64 = 512;

/// A journal records no cycles: the smallest record channel will do.
const JOURNAL_RECORD_CAPACITY: usize = 1;

/// Bytes an event of kind `action` with `detail` takes in a journal file, at most.
fn event_bytes(action: &str, detail: &serde_json::Value) -> u64 {
    let detail = serde_json::to_string(detail).map_or(0, |text| text.len());
    (action.len() + detail) as u64 + JOURNAL_EVENT_OVERHEAD
}

/// Where a cell's journal files go and what each begins with.
struct JournalSetup {
    runs_dir: PathBuf,
    /// `cell-<rig>-<unix>-<pid>`: the first file's name without `.mcap`.
    stem: String,
    rig: String,
    joint_names: Vec<String>,
    metadata: serde_json::Value,
    options: crate::log::RecorderOptions,
    /// The part the next file is (the first is 1).
    next_part: u32,
}

impl JournalSetup {
    fn new(runs_dir: &std::path::Path, settings: &RunSettings) -> JournalSetup {
        let unix_s = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_secs());
        // The rig's name, as a file name: anything but letters, digits, `-` and `_` is `_`.
        let name: String = settings
            .rig
            .name
            .chars()
            .map(|c| {
                if c.is_ascii_alphanumeric() || c == '-' || c == '_' {
                    c
                } else {
                    '_'
                }
            })
            .collect();
        let options = crate::log::RecorderOptions {
            capacity: JOURNAL_RECORD_CAPACITY,
            // A handful of events: compressing them saves nothing and would keep a zstd
            // context per cell for the daemon's lifetime.
            compressed: false,
            // The rig in its cell, as every log attaches it (`rigbridge config urdf`).
            robot: Some(std::sync::Arc::new(
                crate::log::RobotDescription::generated(&settings.rig, &settings.cell),
            )),
            ..crate::log::RecorderOptions::for_rig(&settings.rig)
        };
        JournalSetup {
            runs_dir: runs_dir.to_path_buf(),
            stem: format!("cell-{name}-{unix_s}-{}", std::process::id()),
            rig: settings.rig.name.clone(),
            joint_names: settings.rig.joint_names().map(str::to_owned).collect(),
            metadata: serde_json::json!({
                "journal": settings.rig.name,
                "config": settings.file.display().to_string(),
                "link": settings.config.stream.link,
                "unix_s": unix_s,
            }),
            options,
            next_part: 1,
        }
    }

    /// The next file: its path and recorder.
    fn open_next(&mut self) -> Result<(PathBuf, Recorder), DaemonError> {
        let part = self.next_part;
        let name = match part {
            1 => format!("{}.mcap", self.stem),
            _ => format!("{}-{part}.mcap", self.stem),
        };
        let path = self.runs_dir.join(name);
        let mut metadata = self.metadata.clone();
        metadata["part"] = part.into();
        let recorder = Recorder::create_with(
            &path,
            &self.rig,
            &self.joint_names,
            metadata,
            self.options.clone(),
        )?;
        self.next_part = part.saturating_add(1);
        Ok((path, recorder))
    }
}

impl Journal {
    fn create(runs_dir: &std::path::Path, settings: &RunSettings) -> Result<Journal, DaemonError> {
        Journal::create_capped(runs_dir, settings, JOURNAL_CAP)
    }

    fn create_capped(
        runs_dir: &std::path::Path,
        settings: &RunSettings,
        cap: JournalCap,
    ) -> Result<Journal, DaemonError> {
        let mut setup = JournalSetup::new(runs_dir, settings);
        let (path, recorder) = setup.open_next()?;
        Ok(Journal {
            kept: std::collections::VecDeque::from([path.clone()]),
            path,
            recorder,
            clock: WallClock::new(),
            setup,
            written: JOURNAL_FILE_RESERVE,
            cap,
        })
    }

    fn record(&mut self, action: &str, detail: serde_json::Value) {
        let bytes = event_bytes(action, &detail);
        if self.written + bytes > self.cap.file_bytes {
            self.rotate();
        }
        self.written += bytes;
        self.recorder
            .event(self.clock.now().as_secs_f64(), action, detail);
    }

    /// Closes the current file, begins the next and deletes the oldest beyond the cap. A
    /// file that will not open leaves the journal on the one it has (logged), rather than
    /// losing events.
    fn rotate(&mut self) {
        let (path, recorder) = match self.setup.open_next() {
            Ok(next) => next,
            Err(e) => {
                tracing::error!(
                    "journal {}: cannot begin its next file: {}",
                    self.path.display(),
                    error_chain(&e)
                );
                return;
            }
        };
        let full = std::mem::replace(&mut self.recorder, recorder);
        if let Err(e) = full.finish() {
            tracing::error!(
                "journal {}: closing it: {}",
                self.path.display(),
                error_chain(&e)
            );
        }
        self.path = path.clone();
        self.kept.push_back(path);
        self.written = JOURNAL_FILE_RESERVE;
        while self.kept.len() > self.cap.files {
            if let Some(old) = self.kept.pop_front()
                && let Err(e) = std::fs::remove_file(&old)
            {
                tracing::warn!("journal {}: removing it: {e}", old.display());
            }
        }
    }

    fn finish(self) -> Result<crate::log::RecorderStats, crate::log::LogError> {
        self.recorder.finish()
    }
}

/// The summary of `action`'s `window`, over after `seconds`, if it counted any refusal
/// beyond its first.
fn summarise(
    action: &'static str,
    window: RefusalWindow,
    seconds: std::time::Duration,
) -> Option<RefusalSummary> {
    (window.more > 0).then_some(RefusalSummary {
        action,
        more: window.more,
        seconds: seconds.as_secs_f64(),
        last: window.last,
    })
}

/// How long refusals of one kind are counted before they are told again: one full line,
/// then one summary with the count, per window, whatever the flood.
const REFUSAL_WINDOW: std::time::Duration = std::time::Duration::from_secs(10);

/// Refusals (a job over HTTP, a ROS 2 trajectory) logged rate-limited: the first of a
/// window in full; the others counted, with the last reason kept, and told as one summary
/// once the window is over ("refused 4312 more ... in the last 10.0 s; the last: ...").
struct Refusals {
    clock: WallClock,
    windows: std::collections::HashMap<&'static str, RefusalWindow>,
}

struct RefusalWindow {
    opened: std::time::Duration,
    more: u64,
    last: String,
}

/// A summary of refusals counted in a window that is over.
struct RefusalSummary {
    action: &'static str,
    more: u64,
    seconds: f64,
    last: String,
}

impl std::fmt::Display for RefusalSummary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "refused {} more in the last {:.1} s; the last: {}",
            self.more, self.seconds, self.last
        )
    }
}

impl Refusals {
    fn new() -> Refusals {
        Refusals {
            clock: WallClock::new(),
            windows: std::collections::HashMap::new(),
        }
    }

    /// A refusal of kind `action`: whether to log it in full (the first of its window),
    /// and the summary of the window it closed, if that counted any.
    fn admit(&mut self, action: &'static str, reason: &str) -> (bool, Option<RefusalSummary>) {
        let now = self.clock.now();
        let closed = self.close_if_over(action, now);
        match self.windows.get_mut(action) {
            Some(window) => {
                window.more += 1;
                window.last.clear();
                window.last.push_str(reason);
                (false, closed)
            }
            None => {
                let window = RefusalWindow {
                    opened: now,
                    more: 0,
                    last: String::new(),
                };
                self.windows.insert(action, window);
                (true, closed)
            }
        }
    }

    /// Ends `action`'s window if it is over at `now`: its summary if it counted any.
    fn close_if_over(
        &mut self,
        action: &'static str,
        now: std::time::Duration,
    ) -> Option<RefusalSummary> {
        let window = self.windows.get(action)?;
        let seconds = now.saturating_sub(window.opened);
        if seconds < REFUSAL_WINDOW {
            return None;
        }
        let window = self.windows.remove(action)?;
        summarise(action, window, seconds)
    }

    /// Every window that is over (`all`: every window, the daemon is stopping), summarised.
    fn drain(&mut self, all: bool) -> Vec<RefusalSummary> {
        let now = self.clock.now();
        let actions: Vec<&'static str> = self.windows.keys().copied().collect();
        actions
            .into_iter()
            .filter_map(|action| {
                if all {
                    let window = self.windows.remove(action)?;
                    let seconds = now.saturating_sub(window.opened);
                    summarise(action, window, seconds)
                } else {
                    self.close_if_over(action, now)
                }
            })
            .collect()
    }
}

/// `work`'s result, or the message of the panic that ended it: one job's bug must not take
/// the daemon (or another cell) down.
fn contain_panic<T>(work: impl FnOnce() -> T) -> Result<T, Panicked> {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(work)).map_err(|payload| {
        Panicked(
            payload
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| payload.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "a panic without a message".into()),
        )
    })
}

/// Why a job was not planned: its error chain, as the planner's thread told it.
#[derive(Debug, Clone, thiserror::Error)]
#[error("{0}")]
pub struct NotPlanned(pub String);

/// A job's panic, by its message.
#[derive(Debug, Clone, thiserror::Error)]
#[error("{0}")]
pub struct Panicked(pub String);

/// The file name of job `id`'s log in the runs directory.
pub fn job_log_name(id: u64) -> String {
    format!("job-{id}.mcap")
}

/// The first job number of a daemon logging to `runs_dir`: one past the highest
/// `job-<n>.mcap` already there, so a restarted daemon neither collides with nor overwrites
/// an earlier one's logs.
pub fn first_job_id(runs_dir: &std::path::Path) -> u64 {
    let highest = std::fs::read_dir(runs_dir)
        .into_iter()
        .flatten()
        .filter_map(|entry| {
            let name = entry.ok()?.file_name();
            let name = name.to_str()?;
            name.strip_prefix("job-")?
                .strip_suffix(".mcap")?
                .parse::<u64>()
                .ok()
        })
        .max()
        .unwrap_or(0);
    highest.saturating_add(1)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_panicking_job_is_contained() {
        let result: Result<(), Panicked> = contain_panic(|| panic!("boom {}", 7));
        assert_eq!(result.unwrap_err().0, "boom 7");
        assert_eq!(contain_panic(|| 3).ok(), Some(3));
    }

    #[test]
    fn a_journal_rotates_under_its_cap_keeping_the_newest_files() {
        let dir = std::env::temp_dir().join(format!("rigbridge-journal-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).expect("the temporary journal directory is created");
        let settings = crate::daemon::config::load_run_settings(std::path::Path::new(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/config/rigbridge.toml"
        )))
        .expect("the shipped settings load");
        let cap = JournalCap {
            file_bytes: 64 * 1024,
            files: 3,
        };
        let mut journal = Journal::create_capped(&dir, &settings, cap).expect("journal opens");
        let events = 5_000;
        for n in 0..events {
            let detail = serde_json::json!({ "job": n, "result": "refused: laps = 0" });
            journal.record("job_refused", detail);
        }
        let newest = journal.path.clone();
        journal.finish().expect("the journal closes");
        let files: Vec<_> = std::fs::read_dir(&dir)
            .expect("the directory lists")
            .map(|e| e.expect("an entry").path())
            .collect();
        assert_eq!(files.len(), cap.files, "{files:?}");
        for file in &files {
            let bytes = std::fs::metadata(file).expect("a kept file").len();
            assert!(bytes <= cap.file_bytes, "{}: {bytes} bytes", file.display());
        }
        // The newest file holds the last events, readable.
        let log = crate::log::read_log(&newest).expect("the newest journal file reads");
        let last = log.events.last().expect("it holds events");
        assert_eq!(last.detail["job"], events - 1);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn refusals_are_told_once_a_window_then_counted() {
        let mut refusals = Refusals::new();
        assert!(matches!(refusals.admit(JOB_REFUSED, "a"), (true, None)));
        for reason in ["b", "c"] {
            assert!(matches!(refusals.admit(JOB_REFUSED, reason), (false, None)));
        }
        // Another kind has its own window.
        assert!(matches!(refusals.admit(ROS2_REFUSED, "r"), (true, None)));
        let pending = refusals.drain(true);
        let summary = pending
            .iter()
            .find(|s| s.action == JOB_REFUSED)
            .expect("the counted refusals are summarised");
        assert_eq!(summary.more, 2);
        assert!(
            summary
                .to_string()
                .starts_with("refused 2 more in the last")
        );
        assert!(summary.to_string().ends_with("the last: c"));
        assert_eq!(
            pending.len(),
            1,
            "the ROS 2 window counted none beyond its first"
        );
    }

    #[test]
    fn a_cell_remembers_its_latest_jobs_newest_first_and_forgets_the_oldest() {
        let settings = crate::daemon::config::load_run_settings(std::path::Path::new(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/config/rigbridge.toml"
        )))
        .expect("the shipped settings load");
        let cell = Cell::new(settings, None).expect("the shipped cell starts");
        let ends = cell.job_ends();
        let newest = KEPT_JOBS as u64 + 1;
        for id in 1..=newest {
            cell.remember(id, "move_joints");
        }
        assert!(
            !ends.has_changed().expect("the cell is alive"),
            "none ended"
        );
        let error = "refused: out of reach".to_string();
        cell.record_end(2, JobResult::Failed { id: 2, error });
        assert!(
            ends.has_changed().expect("the cell is alive"),
            "an end is told"
        );
        assert!(cell.job_entry(1).is_none(), "the oldest is forgotten");
        let jobs = cell.jobs().expect("the jobs show");
        assert_eq!(jobs.len(), KEPT_JOBS);
        assert_eq!(jobs[0]["id"], newest);
        assert_eq!(jobs[KEPT_JOBS - 1]["id"], 2);
        let failed = cell
            .job_entry(2)
            .expect("job 2 is remembered")
            .expect("it shows");
        assert!(!failed.running);
        assert_eq!(
            failed.json,
            serde_json::json!({
                "id": 2,
                "name": "move_joints",
                "result": "failed",
                "error": "refused: out of reach",
            })
        );
        let running = cell
            .job_entry(3)
            .expect("job 3 is remembered")
            .expect("it shows");
        assert!(running.running);
        assert_eq!(
            running.json,
            serde_json::json!({ "id": 3, "name": "move_joints", "result": "running" })
        );
        assert!(matches!(
            *cell.last(),
            Some(JobResult::Failed { id: 2, .. })
        ));
        cell.forget(3);
        assert!(
            cell.job_entry(3).is_none(),
            "a job whose thread never started"
        );
    }

    #[test]
    fn job_numbers_continue_after_the_logs_already_there() {
        let dir = std::env::temp_dir().join(format!("rigbridge-ids-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        assert_eq!(first_job_id(&dir), 1, "no directory yet");
        std::fs::create_dir_all(&dir).expect("the temporary log directory is created");
        for name in ["job-3.mcap", "job-12.mcap", "job-x.mcap", "run-99.mcap"] {
            std::fs::write(dir.join(name), b"").expect("the empty log file is written");
        }
        assert_eq!(first_job_id(&dir), 13);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
