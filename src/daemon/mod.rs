//! The daemon: runs jobs end to end (plan, stream to the twin or a controller, record,
//! report) for the `run` and `serve` commands. Owns the wiring between stages and the
//! run report; the stages themselves live in their own modules.

pub mod config;
mod line_check;
mod recording;
pub mod replay;
pub mod reset;
pub mod resume;
pub mod scene;

pub use line_check::LineAfterStall;
pub use recording::{ActionLog, HeldActions, RecorderSink};

use crate::clock::Clock;
use crate::job::JobError;
use crate::link::{Link, LinkError, LoopbackLink};
use crate::log::{LogError, Recorder, RecorderStats};
use crate::stream::{
    Outcome, Phase, StreamControl, StreamError, StreamReport, StreamSettings, slowdown_rate,
};
use crate::trajectory::{CollisionRefusal, Origins, PlanSettings, check_clear};
use crate::twin::{Twin, TwinError, TwinSettings};
use config::RunSettings;
use serde::Serialize;
use std::time::Duration;
use thiserror::Error;

#[derive(Debug, Error)]
pub enum DaemonError {
    #[error("twin")]
    Twin(#[from] TwinError),
    #[error("job refused before motion")]
    Job(#[from] JobError),
    #[error("streaming")]
    Stream(#[from] StreamError),
    #[error("link")]
    Link(#[from] LinkError),
    #[error("no feedback from {0}")]
    NoFeedback(String),
    #[error("before motion: {0}")]
    NotHeld(String),
    #[error("log")]
    Log(#[from] LogError),
    #[error("log")]
    Recorded(#[from] crate::trajectory::RecordedError),
    #[error("replay")]
    Replay(#[from] replay::ReplayError),
    #[error("{0}")]
    Unavailable(String),
    /// The trajectory comes closer to something in the cell than its margin.
    #[error("refused before motion")]
    Collision(#[from] Box<CollisionRefusal>),
    #[error("the cell's collision model")]
    CollisionModel(#[from] crate::cell::CellError),
    /// A stop or e-stop ended the job before any motion.
    #[error("{0}")]
    Halted(Halted),
    /// A program needs I/O the link does not carry: refused before motion.
    #[error("refused before motion: {step} needs I/O, and the link {link} carries none: {why}")]
    NoIo {
        step: String,
        link: String,
        why: &'static str,
    },
}

/// A job a stop or e-stop ended before any motion: how, and in which phase.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Halted {
    pub outcome: Outcome,
    pub phase: Phase,
}

impl std::fmt::Display for Halted {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} while {}, before any motion",
            self.outcome, self.phase
        )
    }
}

impl Halted {
    /// The stop or e-stop `control` had acknowledged (an e-stop wins), in the phase it found.
    pub fn of(control: &StreamControl) -> Halted {
        Halted {
            outcome: if control.is_estopped() {
                Outcome::EStopped
            } else {
                Outcome::Stopped
            },
            phase: control.halted_in().unwrap_or_else(|| control.phase()),
        }
    }

    /// Tells the controller (an EStop or a Stop: the arm is at rest, nothing else goes
    /// out) when the link is up, and ends the job with this.
    fn told(self, link: &mut dyn Link) -> DaemonError {
        if link.is_up() {
            let command = match self.outcome {
                Outcome::EStopped => crate::protocol::Command::EStop,
                _ => crate::protocol::Command::Stop,
            };
            // Ending anyway: a link that fails now has nothing to stop.
            let _ = link.send(&command);
        }
        DaemonError::Halted(self)
    }

    /// The report of the job it ended: no cycles, the outcome and the phase.
    pub fn report(
        self,
        settings: &RunSettings,
        job: &str,
        link: &dyn Link,
        clock: &dyn Clock,
    ) -> RunReport {
        RunReport {
            rig: settings.rig.name.clone(),
            job: job.to_string(),
            rate_hz: settings.config.stream.rate_hz,
            clock: clock_name(clock),
            planned_duration_s: 0.0,
            stream: StreamReport {
                stopped_in: Some(self.phase),
                ..StreamReport::without_motion(
                    self.outcome,
                    self.to_string(),
                    link.describe(),
                    link.counters(),
                )
            },
            log: None,
            log_error: None,
            contacts: None,
            cycle_times: None,
            measured_cycle_times: None,
            parts: None,
            line_after_stalls: Vec::new(),
        }
    }
}

fn clock_name(clock: &dyn Clock) -> &'static str {
    if clock.is_virtual() {
        "virtual"
    } else {
        "wall"
    }
}

/// An error and all its sources, as one line: [`crate::log::error_chain`], which the log's
/// own failures need too and `log` sits below this layer.
pub use crate::log::error_chain;

/// What `run` prints and writes with `--report`.
#[derive(Debug, Clone, Serialize)]
pub struct RunReport {
    pub rig: String,
    pub job: String,
    pub rate_hz: f64,
    pub clock: &'static str,
    pub planned_duration_s: f64,
    #[serde(flatten)]
    pub stream: StreamReport,
    /// The MCAP log of this run, and what the recorder wrote.
    pub log: Option<LogReport>,
    /// Why the log ended early, when it did (docs/logs.md, "When the log cannot be
    /// written"); `null` otherwise. The outcome and cycles beside it stay what the arm did.
    pub log_error: Option<LogErrorReport>,
    /// What the in-process twin measured of the cell's clearances over the job (closest
    /// pairs, collision episodes); `null` for a remote controller.
    pub contacts: Option<crate::twin::ContactReport>,
    /// A program's planned cycle time per step and per pass of each repeat
    /// (docs/programs.md); absent for other jobs.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub cycle_times: Option<crate::job::CycleTimes>,
    /// The same steps and passes as the stream passed them, measured on the clock from one
    /// step's end to the next: pauses, stalls, resumptions and I/O waits included; steps
    /// not reached are absent (docs/programs.md, "Cycle times").
    #[serde(skip_serializing_if = "Option::is_none")]
    pub measured_cycle_times: Option<crate::job::CycleTimes>,
    /// The in-process twin's judgement of the cell's parts when the cell has some
    /// (docs/programs.md, "Parts and the judge"): each part's final pose against its goal,
    /// parts dropped or never picked, carried parts' collisions, the measured time from one
    /// pick to the next; absent otherwise.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub parts: Option<crate::twin::CellJudgement>,
    /// A `move_linear` job that stalled: per stall, how far the tool left its lines after
    /// it, measured from the log, and whether that broke the job's 0.5 mm (issue 32);
    /// absent otherwise.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub line_after_stalls: Vec<LineAfterStall>,
}

impl RunReport {
    /// The warnings a finished run gives besides its interruptions: each broken promise,
    /// with its figure.
    pub fn warnings(&self) -> Vec<String> {
        self.line_after_stalls
            .iter()
            .filter(|line| line.broken)
            .map(ToString::to_string)
            .collect()
    }
}

/// A log that failed during a run: what failed, from when, and what the job did about it.
#[derive(Debug, Clone, Serialize)]
pub struct LogErrorReport {
    /// The file, what was being written and the cause.
    pub error: String,
    /// Job time (s) of the latest record taken when the write failed: the log holds
    /// nothing from about then on.
    pub at_s: f64,
    /// `[log] on_error` for this run.
    pub on_error: config::OnLogError,
    /// Whether the failure brought the job to rest (`on_error = "stop"`, with no stop or
    /// e-stop under way then): the outcome is then `stopped` for this reason alone.
    pub stopped_job: bool,
}

#[derive(Debug, Clone, Serialize)]
pub struct LogReport {
    pub path: String,
    pub commands: u64,
    pub states: u64,
    pub events: u64,
    pub dropped: u64,
}

impl LogReport {
    fn new(path: &std::path::Path, stats: RecorderStats) -> Self {
        Self {
            path: path.display().to_string(),
            commands: stats.commands,
            states: stats.states,
            events: stats.events,
            dropped: stats.dropped,
        }
    }
}

pub fn twin_settings(settings: &RunSettings) -> TwinSettings {
    let twin = &settings.config.twin;
    TwinSettings {
        period: settings.period(),
        bandwidth_hz: twin.bandwidth_hz,
        delay: settings.twin_delay(),
        watchdog_cycles: twin.watchdog_cycles,
        protocol_version: twin.protocol_version,
    }
}

pub fn plan_settings(settings: &RunSettings) -> PlanSettings {
    PlanSettings {
        period: settings.period(),
        speed_scale: settings.config.plan.speed_scale,
        accel_scale: settings.config.plan.accel_scale,
        budget: settings.config.limits.budget(),
        free: crate::trajectory::free::FreePlanOptions {
            seed: settings.config.plan.free_seed,
            max_samples: settings.config.plan.free_max_samples,
            ..Default::default()
        },
        ..PlanSettings::default()
    }
}

pub fn stream_settings(settings: &RunSettings) -> StreamSettings {
    let mut streaming = StreamSettings::new(
        settings.period(),
        slowdown_rate(
            &settings.rig,
            settings.config.plan.speed_scale,
            settings.config.plan.accel_scale,
        ),
    );
    // Validated on load: only a file changed since could fail here.
    if let Ok(tolerances) = settings
        .config
        .stream
        .tolerances(&settings.file, &settings.rig)
    {
        streaming.tolerances = tolerances;
    }
    streaming
}

/// The bridge's Hello for these settings' rig and stream rate.
pub fn bridge_hello(settings: &RunSettings) -> crate::protocol::Hello {
    crate::link::bridge_hello(
        &settings.rig,
        settings.period(),
        settings.config.twin.watchdog_cycles,
    )
}

/// The in-process twin at the configured initial position, behind a loopback link.
pub fn loopback_twin(settings: &RunSettings) -> Result<LoopbackLink, DaemonError> {
    Ok(LoopbackLink::new(settings_twin(settings)?))
}

/// The twin of `settings` at its initial position, watching its cell's clearances.
pub fn settings_twin(settings: &RunSettings) -> Result<Twin, DaemonError> {
    let twin = Twin::new(&settings.rig, twin_settings(settings), &settings.initial())?.with_io(
        crate::twin::TwinIo::in_cell(
            &settings.rig,
            &settings.cell,
            settings.period().as_secs_f64(),
        ),
    );
    Ok(match contact_watch(settings)? {
        Some(watch) => twin.with_contacts(watch),
        None => twin,
    })
}

/// What the live page, the live Foxglove server and the log draw of the rig's cell; nothing
/// for streamed axes that are not one chain ([`one_chain`]).
pub fn cell_drawing(
    settings: &RunSettings,
) -> Result<Option<crate::view::CellDrawing>, DaemonError> {
    if !one_chain(settings) {
        return Ok(None);
    }
    let model = crate::cell::CollisionModel::new(&settings.rig, &settings.cell)?;
    Ok(Some(crate::view::CellDrawing::new(
        &settings.rig,
        &settings.cell,
        std::sync::Arc::new(model),
        tool0_of(settings),
    )))
}

/// tool0 in the last joint's frame, where the tool's bodies are given from: the rig's own
/// tool transform, or, for a rig ending at the tool's TCP ([`crate::cell::Cell::rig_at_tcp`]),
/// that transform less the TCP (as the collision model takes it back).
fn tool0_of(settings: &RunSettings) -> glam::DAffine3 {
    match &settings.cell.tool {
        Some(tool) if settings.rig.tool_frame == tool.name => {
            settings.rig.tool * tool.tcp.inverse()
        }
        _ => settings.rig.tool,
    }
}

/// Whether the rig's streamed axes are one serial chain, which forward kinematics and the
/// collision model pose: not when they stand for a model an app loaded beside them
/// ([`crate::apps::App::load_rig`]).
fn one_chain(settings: &RunSettings) -> bool {
    settings.app_rig.is_none()
}

/// The twin's collision watch over the rig in its cell; none for streamed axes that are not
/// one chain ([`one_chain`]): no collision model poses them.
pub fn contact_watch(
    settings: &RunSettings,
) -> Result<Option<crate::twin::ContactWatch>, DaemonError> {
    if !one_chain(settings) {
        return Ok(None);
    }
    let model = crate::cell::CollisionModel::new(&settings.rig, &settings.cell)?;
    Ok(Some(crate::twin::ContactWatch::new(
        std::sync::Arc::new(model),
        &settings.rig,
        &settings.cell,
        settings.period().as_secs_f64(),
    )))
}

/// Opens the link `spec` names: the in-process twin for `loopback`, a real transport
/// otherwise (the controller on its far side is someone else's, or `rigbridge twin`),
/// given until the reconnect timeout to come up.
pub fn open_link(
    spec: &crate::device::LinkSpec,
    settings: &RunSettings,
) -> Result<Box<dyn Link>, DaemonError> {
    open_link_for(spec, settings, &StreamControl::default())
}

/// [`open_link`] for a job: the wait for the link ends early on the job's stop or e-stop
/// (the job then ends before any motion, in [`plan_for`]).
pub fn open_link_for(
    spec: &crate::device::LinkSpec,
    settings: &RunSettings,
    control: &StreamControl,
) -> Result<Box<dyn Link>, DaemonError> {
    let link = connect_link(spec, settings)?;
    let mut timeout = settings.reconnect_timeout();
    // CANopen drives are set up over SDO before the session starts.
    if let crate::device::LinkSpec::Canopen { .. } = spec {
        timeout += crate::device::canopen::SETUP_PATIENCE;
    }
    wait_for_link(
        link.as_ref(),
        &crate::clock::WallClock::new(),
        timeout,
        control,
    );
    Ok(link)
}

/// The link `spec` names, connected: the in-process twin is up at once, a transport's
/// session may still be coming up.
fn connect_link(
    spec: &crate::device::LinkSpec,
    settings: &RunSettings,
) -> Result<Box<dyn Link>, DaemonError> {
    use crate::device::LinkSpec;
    Ok(match spec {
        LinkSpec::Loopback => Box::new(loopback_twin(settings)?),
        LinkSpec::Tcp { address } => Box::new(
            crate::device::ours::connect_tcp(
                crate::device::ours::TcpSettings::new(address.clone()),
                bridge_hello(settings),
            )
            .map_err(LinkError::Io)?,
        ),
        LinkSpec::Serial {
            path,
            baud,
            dynamixel: Some(ids),
        } => Box::new(crate::device::dynamixel::connect_dynamixel(
            dynamixel_settings(settings, path, *baud, ids)?,
        )?),
        LinkSpec::Serial {
            path,
            baud,
            dynamixel: None,
        } => {
            let serial = settings.config.stream.serial_settings(path, *baud);
            Box::new(
                crate::device::ours::connect_serial(serial, bridge_hello(settings))
                    .map_err(LinkError::Io)?,
            )
        }
        LinkSpec::Can { interface } => {
            let mapping = settings
                .config
                .stream
                .can_mapping(crate::protocol::CanSender::Bridge)
                .map_err(|e| DaemonError::Unavailable(e.to_string()))?;
            Box::new(
                crate::device::ours::connect_can(interface, mapping, bridge_hello(settings))
                    .map_err(LinkError::Io)?,
            )
        }
        LinkSpec::Canopen {
            interface,
            nodes,
            counts_per_turn,
        } => Box::new(crate::device::canopen::connect_canopen(canopen_settings(
            settings,
            interface,
            nodes,
            *counts_per_turn,
        )?)?),
        LinkSpec::Egm {
            address,
            robot,
            mode,
        } => {
            let axes = settings
                .config
                .egm
                .axes(&settings.file, &settings.rig)
                .map_err(|e| DaemonError::Unavailable(e.to_string()))?;
            let egm = crate::device::egm::EgmLinkSettings::for_rig(
                &settings.rig,
                axes,
                settings.period(),
                *robot,
            )
            .in_mode(*mode);
            Box::new(crate::device::egm::bind_egm(address, egm).map_err(LinkError::Io)?)
        }
    })
}

/// The Dynamixel link's settings for servos `ids` on `path`: the axes' tick maps from
/// `[dynamixel]`, their limits, and a cycle that fits the line (docs/dynamixel.md).
pub fn dynamixel_settings(
    settings: &RunSettings,
    path: &str,
    baud: u32,
    ids: &[u8],
) -> Result<crate::device::dynamixel::DynamixelSettings, DaemonError> {
    let rig = &settings.rig;
    let axes = settings
        .config
        .dynamixel
        .axes(&settings.file, rig)
        .map_err(|e| DaemonError::Unavailable(e.to_string()))?;
    // The best case, servos answering at once: a rate above it cannot be kept.
    let budget = crate::device::dynamixel::wire::line_budget(ids.len(), baud, 0.0);
    if settings.config.stream.rate_hz > budget.max_rate_hz {
        return Err(DaemonError::Unavailable(format!(
            "{} Hz does not fit a Dynamixel bus of {} servos at {baud} baud: one cycle takes up to {:.2} ms, {:.0} Hz at most (docs/dynamixel.md)",
            settings.config.stream.rate_hz,
            ids.len(),
            budget.cycle.as_secs_f64() * 1e3,
            budget.max_rate_hz
        )));
    }
    Ok(crate::device::dynamixel::DynamixelSettings {
        serial: settings.config.stream.serial_settings(path, baud),
        ids: ids.to_vec(),
        axes,
        limits: axis_limits(rig),
        cycle_timeout: settings.period(),
    })
}

/// The CANopen link's settings for drives `nodes` on `interface`: the axes' count maps
/// from the link's `counts_per_turn` and `[canopen]`, their limits, the stream period as
/// the SYNC period, the heartbeat (docs/canopen.md).
pub fn canopen_settings(
    settings: &RunSettings,
    interface: &str,
    nodes: &[u8],
    counts_per_turn: Option<u32>,
) -> Result<crate::device::canopen::CanopenSettings, DaemonError> {
    let rig = &settings.rig;
    let canopen = &settings.config.canopen;
    let unavailable = |e: crate::rig::ConfigError| DaemonError::Unavailable(e.to_string());
    let axes = canopen
        .axes(&settings.file, rig, counts_per_turn)
        .map_err(unavailable)?;
    let heartbeat_ms = canopen.heartbeat_ms(&settings.file).map_err(unavailable)?;
    Ok(crate::device::canopen::CanopenSettings {
        interface: interface.to_string(),
        nodes: nodes.to_vec(),
        axes,
        limits: axis_limits(rig),
        period: settings.period(),
        heartbeat_ms,
    })
}

/// Each axis' lower and upper limit (rad).
fn axis_limits(rig: &crate::rig::Rig) -> Vec<(f64, f64)> {
    rig.joints
        .iter()
        .map(|j| (j.limits.lower, j.limits.upper))
        .collect()
}

/// Where the controller holds at rest, read before planning so the plan starts there
/// (docs/protocol.md 6.6: the first target after a hold starts from the held position).
pub fn held_position(
    settings: &RunSettings,
    link: &mut dyn Link,
    clock: &dyn Clock,
    control: &StreamControl,
) -> Result<Vec<f64>, DaemonError> {
    if let Some(hello) = link.controller_hello() {
        crate::stream::check_controller(&hello, &settings.rig, settings.period())
            .map_err(StreamError::from)?;
    }
    match resume::wait_for_hold(settings, link, clock, control, resume::START_HOLD_TIMEOUT)? {
        resume::Hold::At(position) => Ok(position),
        // The wait told the controller already.
        resume::Hold::Stopped | resume::Hold::EStopped => {
            Err(DaemonError::Halted(Halted::of(control)))
        }
        resume::Hold::Faulted(text) | resume::Hold::TimedOut(text) => {
            Err(DaemonError::NotHeld(text))
        }
    }
}

/// A trajectory that holds the arm at `position` (two samples, at rest): what an online
/// session streams until its commands take over.
pub fn hold_at(
    settings: &RunSettings,
    position: &[f64],
) -> Result<crate::trajectory::Trajectory, DaemonError> {
    let rig = &settings.rig;
    let positions = [position, position].concat();
    let velocities = vec![0.0; positions.len()];
    let trajectory = crate::trajectory::Trajectory::new(
        rig.name.clone(),
        rig.joint_names().map(String::from).collect(),
        settings.period(),
        positions,
        velocities,
    )
    .map_err(StreamError::from)?;
    Ok(trajectory)
}

/// A job planned from where the rig is: nothing has moved yet. A job with a bad target
/// never gets this far.
pub struct PlannedJob {
    pub job: config::JobConfig,
    pub start: Vec<f64>,
    pub trajectory: crate::trajectory::Trajectory,
    /// Where each stretch of the trajectory came from, for a refusal to name.
    pub origins: Origins,
    /// Whether the trajectory was checked against the cell already ([`clear`]); if not,
    /// streaming it checks it first.
    pub cleared: bool,
}

/// The cell's collision model for `settings` (built when they loaded): the rig's bodies,
/// the tool and the objects.
pub fn collision_model(settings: &RunSettings) -> std::sync::Arc<crate::cell::CollisionModel> {
    settings.collision.clone()
}

/// Checks `trajectory` whole against the cell before any motion: every sample and the
/// motion between them (docs/faults.md, "Collisions"). A refusal names the two bodies, the
/// time, where the stretch came from (`origins`), the joints and the clearance.
pub fn clear(
    settings: &RunSettings,
    trajectory: &crate::trajectory::Trajectory,
    origins: &Origins,
) -> Result<(), DaemonError> {
    check_clear(trajectory, &settings.rig, &settings.collision, origins)?;
    Ok(())
}

/// [`clear`] for `job`'s trajectory, against the cell of the job: the run's, or the one its
/// app checks it in ([`crate::apps::App::gate_cell`]).
fn clear_job(
    settings: &RunSettings,
    job: Option<&config::JobConfig>,
    trajectory: &crate::trajectory::Trajectory,
    origins: &Origins,
) -> Result<(), DaemonError> {
    let app = job.and_then(|job| crate::apps::app_of(job).map(|app| (app, job)));
    let Some(cell) = app
        .map(|(app, job)| app.gate_cell(job, &settings.rig, &settings.cell))
        .transpose()?
        .flatten()
    else {
        return clear(settings, trajectory, origins);
    };
    let collision = crate::cell::CollisionModel::new(&settings.rig, &cell)?;
    let gated = RunSettings {
        cell,
        collision: std::sync::Arc::new(collision),
        ..settings.clone()
    };
    clear(&gated, trajectory, origins)
}

/// Refuses `job` before anything else when it needs I/O that `link` does not carry,
/// naming its first such step, the link and why.
fn check_io(job: &config::JobConfig, link: &dyn Link) -> Result<(), DaemonError> {
    let (Some(step), crate::link::Io::NotCarried(why)) = (job.first_io_step(), link.io()) else {
        return Ok(());
    };
    Err(DaemonError::NoIo {
        step,
        link: link.describe(),
        why,
    })
}

pub fn plan_for(
    settings: &RunSettings,
    job: &config::JobConfig,
    link: &mut dyn Link,
    clock: &dyn Clock,
    control: &StreamControl,
) -> Result<PlannedJob, DaemonError> {
    // Checked once the controller has answered: its Hello's version says whether a remote
    // link carries I/O (docs/protocol.md 6.10). Still before any motion.
    let start = held_position(settings, link, clock, control)?;
    check_io(job, link)?;
    if control.enter(Phase::Planning) {
        return Err(Halted::of(control).told(link));
    }
    let (trajectory, origins) = job.plan_traced(&crate::job::PlanContext {
        rig: &settings.tcp_rig,
        app_rig: settings.app_rig.as_deref(),
        start: &start,
        settings: &plan_settings(settings),
        model: Some(&settings.collision),
    })?;
    // A stop asked for while planning ends the job now, before any motion.
    if control.is_halted() {
        return Err(Halted::of(control).told(link));
    }
    // Checked here, not only when streamed: `serve` answers a job refused here in the
    // request that asked for it.
    clear_job(settings, Some(job), &trajectory, &origins)?;
    Ok(PlannedJob {
        job: job.clone(),
        start,
        trajectory,
        origins,
        cleared: true,
    })
}

/// `job` planned from `start` and checked clear of the cell, as [`plan_for`] plans once the
/// controller holds: for a trajectory spliced into a running job (a preempting
/// FollowJointTrajectory goal, docs/ros2.md).
pub fn plan_from(
    settings: &RunSettings,
    job: &config::JobConfig,
    start: &[f64],
) -> Result<crate::trajectory::Trajectory, DaemonError> {
    let (trajectory, origins) = job.plan_traced(&crate::job::PlanContext {
        rig: &settings.tcp_rig,
        app_rig: settings.app_rig.as_deref(),
        start,
        settings: &plan_settings(settings),
        model: Some(&settings.collision),
    })?;
    clear_job(settings, Some(job), &trajectory, &origins)?;
    Ok(trajectory)
}

/// Plans `job`, then streams it to the end (or until `control` stops it), recording to
/// `log` when given.
pub fn run_job(
    settings: &RunSettings,
    job: &config::JobConfig,
    link: &mut dyn Link,
    clock: &dyn Clock,
    log: Option<&std::path::Path>,
    control: &StreamControl,
) -> Result<RunReport, DaemonError> {
    let planned = plan_for(settings, job, link, clock, control)?;
    stream_planned(settings, &planned, link, clock, log, control)
}

pub fn stream_planned(
    settings: &RunSettings,
    planned: &PlannedJob,
    link: &mut dyn Link,
    clock: &dyn Clock,
    log: Option<&std::path::Path>,
    control: &StreamControl,
) -> Result<RunReport, DaemonError> {
    let sinks = Sinks {
        live: &mut (),
        actions: None,
        executor: None,
    };
    stream_planned_with(settings, planned, link, clock, log, control, sinks)
}

/// Where a stream's cycles go besides its log: the live view's sink, the slot through which
/// other threads' actions reach the log, and the executor that runs the cycles (none: the
/// job's own thread).
pub struct Sinks<'a> {
    pub live: &'a mut (dyn crate::stream::CycleSink + Send),
    pub actions: Option<&'a recording::ActionLog>,
    pub executor: Option<&'a crate::stream::Executor>,
}

/// [`stream_planned`], also handing every cycle to `sinks.live` (the live view's sink),
/// opening `sinks.actions` on the job's log while it streams, on `sinks.executor`.
pub fn stream_planned_with(
    settings: &RunSettings,
    planned: &PlannedJob,
    link: &mut dyn Link,
    clock: &dyn Clock,
    log: Option<&std::path::Path>,
    control: &StreamControl,
    sinks: Sinks<'_>,
) -> Result<RunReport, DaemonError> {
    let job = JobToStream {
        name: job_name(&planned.job),
        description: serde_json::to_value(&planned.job).unwrap_or_default(),
        start: &planned.start,
        trajectory: &planned.trajectory,
        job: Some(&planned.job),
        origins: &planned.origins,
        cleared: planned.cleared,
    };
    stream_job_with(settings, &job, link, clock, log, control, sinks)
}

/// What the resuming stream needs of a job, whatever made its trajectory (a planned job, a
/// replayed log): its name and description for the log and report, the held position it
/// was planned from, and the trajectory.
pub struct JobToStream<'a> {
    pub name: String,
    pub description: serde_json::Value,
    pub start: &'a [f64],
    pub trajectory: &'a crate::trajectory::Trajectory,
    /// The job's config, when it has one (a replayed log has not): its world (paint room,
    /// branches) goes in the log as `/scene`.
    pub job: Option<&'a config::JobConfig>,
    /// Where each stretch of the trajectory came from, for a refusal to name.
    pub origins: &'a Origins,
    /// Whether the trajectory was checked against the cell already ([`clear`]).
    pub cleared: bool,
}

/// Streams `job` through [`resume::stream_resuming`] (link loss and stalls resume from the
/// held position), recording to `log` and handing every cycle to `sinks.live`;
/// `sinks.actions` writes to the log from other threads while the job streams.
pub fn stream_job_with(
    settings: &RunSettings,
    job: &JobToStream<'_>,
    link: &mut dyn Link,
    clock: &dyn Clock,
    log: Option<&std::path::Path>,
    control: &StreamControl,
    sinks: Sinks<'_>,
) -> Result<RunReport, DaemonError> {
    let Sinks {
        live,
        actions,
        executor,
    } = sinks;
    // Every trajectory the daemon streams passes here: one not checked yet is, now.
    if !job.cleared {
        clear_job(settings, job.job, job.trajectory, job.origins)?;
    }
    let metadata = job_metadata(settings, job, link.describe());
    let recorder = log
        .map(|path| create_recorder(settings, job.job, path, &metadata, clock.is_virtual()))
        .transpose()?;
    // The twin measures the job from its first cycle on.
    let _ = link.take_contacts();
    let mut timed = Timed {
        live,
        timer: job
            .job
            .and_then(|j| j.step_spans(job.origins))
            .map(crate::job::StepTimer::new),
    };
    let io = resume::Streaming {
        settings,
        link: &mut *link,
        clock,
        sink: &mut timed,
        control,
        events: None,
        executor,
    };
    let on_error = settings.config.log.on_error;
    let (mut report, stopped_job) = match &recorder {
        Some(recorder) => {
            stream_recorded(io, job.trajectory, recorder, metadata, actions, on_error)
        }
        None => (resume::stream_resuming(io, job.trajectory), false),
    };
    report.stopped_in = control.halted_in();
    control.end();
    let contacts = link.take_contacts();
    let (log_report, log_error) = match (recorder, log) {
        (Some(recorder), Some(path)) => {
            let (written, failure) = close_log(recorder, actions, &report, contacts.as_ref(), path);
            let log_error = failure.map(|failure| LogErrorReport {
                error: failure.error,
                at_s: failure.at_s,
                on_error,
                stopped_job,
            });
            (Some(written), log_error)
        }
        _ => (None, None),
    };
    let line_after_stalls = match (job.job, log) {
        (Some(config::JobConfig::MoveLinear(linear)), Some(path)) => {
            line_after_stalls(settings, linear, &report, path)
        }
        _ => Vec::new(),
    };
    Ok(RunReport {
        rig: settings.rig.name.clone(),
        job: job.name.clone(),
        rate_hz: settings.config.stream.rate_hz,
        clock: clock_name(clock),
        planned_duration_s: job.trajectory.duration_s(),
        stream: report,
        log: log_report,
        log_error,
        contacts,
        cycle_times: job
            .job
            .and_then(|j| j.cycle_times(job.origins, job.trajectory.period)),
        measured_cycle_times: timed.timer.and_then(|timer| timer.measured()),
        parts: link.judgement(),
        line_after_stalls,
    })
}

/// [`line_check::after_stalls`] of the closed log at `path`, when the run stalled. A log
/// that cannot be read back (its failure is reported already) measures nothing.
fn line_after_stalls(
    settings: &RunSettings,
    job: &crate::job::MoveLinear,
    report: &StreamReport,
    path: &std::path::Path,
) -> Vec<LineAfterStall> {
    let stalled = report
        .interruptions
        .iter()
        .any(|i| i.outcome == Outcome::Stalled);
    if !stalled {
        return Vec::new();
    }
    match crate::log::read_log(path) {
        Ok(log) => line_check::after_stalls(settings, job, &log),
        Err(_) => Vec::new(),
    }
}

/// The live sink, with a program's steps timed as the stream passes them.
struct Timed<'a> {
    live: &'a mut (dyn crate::stream::CycleSink + Send),
    timer: Option<crate::job::StepTimer>,
}

impl crate::stream::CycleSink for Timed<'_> {
    fn record(&mut self, cycle: &crate::stream::CycleRecord) {
        if let Some(timer) = &mut self.timer {
            timer.observe(cycle.at, cycle.on_job);
        }
        self.live.record(cycle);
    }
}

/// What the log's metadata and its `job_started` event say of the job and the stream.
fn job_metadata(settings: &RunSettings, job: &JobToStream<'_>, link: String) -> serde_json::Value {
    serde_json::json!({
        "job": job.description,
        "config": settings.file.display().to_string(),
        "rate_hz": settings.config.stream.rate_hz,
        "period_s": settings.period().as_secs_f64(),
        "start": job.start,
        "link": link,
    })
}

/// [`resume::stream_resuming`] with every cycle and event also going to `recorder`, and
/// `actions` open on it while the job streams. With `on_error = "stop"`, the first cycle
/// after a failed write stops the job along its path; the report, and whether that stop
/// was the log's.
fn stream_recorded(
    io: resume::Streaming<'_>,
    trajectory: &crate::trajectory::Trajectory,
    recorder: &Recorder,
    metadata: serde_json::Value,
    actions: Option<&ActionLog>,
    on_error: config::OnLogError,
) -> (StreamReport, bool) {
    recorder.event(0.0, "job_started", metadata);
    if let Some(actions) = actions {
        actions.open(recorder);
    }
    let mut recording = RecorderSink::new(recorder, io.settings.period());
    if on_error == config::OnLogError::Stop {
        recording = recording.stopping_on_failure(io.control);
    }
    let mut sink = recording::BothSinks(&mut recording, io.sink);
    let io = resume::Streaming {
        settings: io.settings,
        link: io.link,
        clock: io.clock,
        sink: &mut sink,
        control: io.control,
        events: Some(recorder),
        executor: io.executor,
    };
    let report = resume::stream_resuming(io, trajectory);
    (report, recording.stopped_job())
}

/// The log's event with the twin's collision measurements of the job (`contacts` of the
/// run report), written just before `job_ended`.
pub const CONTACTS_EVENT: &str = "contacts";

/// Closes `actions`, writes the twin's collision measurements, ends the log with `job_ended` and the report, and says what the
/// recorder wrote to `path`, and the log's first failure, if it failed (while the job
/// streamed or as it closed): a failed log never takes the run's report with it.
fn close_log(
    recorder: Recorder,
    actions: Option<&ActionLog>,
    report: &StreamReport,
    contacts: Option<&crate::twin::ContactReport>,
    path: &std::path::Path,
) -> (LogReport, Option<crate::log::LogFailure>) {
    if let Some(actions) = actions {
        actions.close();
    }
    if let Some(contacts) = contacts {
        let measured = serde_json::to_value(contacts).unwrap_or_default();
        recorder.event(report.duration_s, CONTACTS_EVENT, measured);
    }
    let ended = serde_json::to_value(report).unwrap_or_default();
    recorder.event(report.duration_s, "job_ended", ended);
    let health = recorder.health();
    let closed = recorder.close();
    // A failure is in `health` as soon as the writer meets it, one at closing included.
    (LogReport::new(path, closed.stats), health.failure())
}

/// The job's recorder at `path`, its metadata written first. Under a virtual clock nothing
/// is real time: the cycle waits for the log writer rather than dropping records, so the
/// log holds every cycle.
fn create_recorder(
    settings: &RunSettings,
    job: Option<&config::JobConfig>,
    path: &std::path::Path,
    metadata: &serde_json::Value,
    virtual_clock: bool,
) -> Result<Recorder, DaemonError> {
    let options = crate::log::RecorderOptions {
        wait_when_full: virtual_clock,
        robot: robot_description(settings)?,
        scene: job.and_then(|job| scene::log_scene_for_job(settings, job)),
        capacity: crate::log::capacity_for_rate(settings.config.stream.rate_hz),
        ..crate::log::RecorderOptions::for_rig(&settings.rig)
    };
    let names: Vec<String> = settings.rig.joint_names().map(str::to_owned).collect();
    Ok(Recorder::create_with(
        path,
        &settings.rig.name,
        &names,
        metadata.clone(),
        options,
    )?)
}

/// The rig's links and URDF behind `/tf` (logs and the live Foxglove server): its URDF file
/// when it was loaded from one, else the rig in its cell as `rigbridge config urdf` writes it
/// (collision geometry, tool, cell objects).
pub fn robot_description(
    settings: &RunSettings,
) -> Result<Option<std::sync::Arc<crate::log::RobotDescription>>, DaemonError> {
    if !one_chain(settings) {
        // Axes that are not one chain ([`one_chain`]) have no serial FK that poses the rig:
        // no /tf rather than a wrong one.
        return Ok(None);
    }
    let robot = match rig_urdf(settings)? {
        Some(urdf) => crate::log::RobotDescription::from_urdf(&settings.rig, urdf)?,
        None => crate::log::RobotDescription::generated(&settings.rig, &settings.cell),
    };
    Ok(Some(std::sync::Arc::new(robot)))
}

/// The text of the rig's URDF file, when the rig was loaded from one (the log attaches it
/// as is; other rigs get a URDF generated from the model).
fn rig_urdf(settings: &RunSettings) -> Result<Option<String>, DaemonError> {
    let path = config::config_dir(&settings.file).join(&settings.config.rig);
    if path.extension().and_then(|e| e.to_str()) != Some("urdf") {
        return Ok(None);
    }
    std::fs::read_to_string(&path).map(Some).map_err(|source| {
        DaemonError::Log(LogError::Io {
            context: format!("reading the rig's URDF {} to attach it", path.display()),
            source,
        })
    })
}

/// Polls the link until it is up again, `timeout` passes or `control` is stopped.
pub fn wait_for_link(
    link: &dyn Link,
    clock: &dyn Clock,
    timeout: Duration,
    control: &StreamControl,
) -> bool {
    let deadline = clock.now() + timeout;
    while !link.is_up() {
        if clock.now() >= deadline || control.is_halted() {
            return false;
        }
        clock.sleep_until(clock.now() + Duration::from_millis(10));
    }
    true
}

fn job_name(job: &config::JobConfig) -> String {
    job.name()
}

#[cfg(test)]
mod tests {
    use super::{DaemonError, error_chain};
    use crate::log::LogError;

    #[test]
    fn a_chain_names_a_cause_once_when_the_message_already_ends_with_it() {
        let io = std::io::Error::new(std::io::ErrorKind::AlreadyExists, "File exists");
        let error = DaemonError::Log(LogError::Io {
            context: "creating log x.mcap".into(),
            source: io,
        });
        let text = error_chain(&error);
        assert_eq!(text.matches("File exists").count(), 1, "{text}");
        assert!(text.contains("creating log x.mcap: File exists"), "{text}");
    }
}
