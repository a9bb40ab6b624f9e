//! The daemon: runs jobs end to end (plan, stream to the twin or a controller, record,
//! report) for the `run` and `serve` commands. Owns the wiring between stages and the
//! run report; the stages themselves live in their own modules.

pub mod config;
pub mod gait;
pub mod paint;
mod recording;
pub mod replay;
pub mod server;

pub use recording::RecorderSink;

use crate::clock::Clock;
use crate::job::{JobError, plan_job};
use crate::link::{Link, LinkError, LoopbackLink};
use crate::log::{LogError, Recorder, RecorderStats};
use crate::protocol::Command;
use crate::stream::{
    StreamControl, StreamError, StreamReport, StreamSettings, slowdown_rate, stream,
};
use crate::trajectory::PlanSettings;
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
    #[error("gait refused before motion")]
    Gait(#[from] crate::task::gait::GaitError),
    #[error("streaming")]
    Stream(#[from] StreamError),
    #[error("link")]
    Link(#[from] LinkError),
    #[error("no feedback from {0}")]
    NoFeedback(String),
    #[error("log")]
    Log(#[from] LogError),
    #[error("replay: {0}")]
    Replay(String),
    #[error("{0}")]
    Unavailable(String),
    #[error(transparent)]
    Cells(#[from] server::CellError),
}

/// An error and all its sources, as one line ("job refused before motion: job target 0 ...").
pub fn error_chain(error: &dyn std::error::Error) -> String {
    let mut text = error.to_string();
    let mut source = error.source();
    while let Some(cause) = source {
        text.push_str(": ");
        text.push_str(&cause.to_string());
        source = cause.source();
    }
    text
}

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
        period_s: settings.period_s(),
        bandwidth_hz: twin.bandwidth_hz,
        delay_s: twin.delay_ms / 1000.0,
        watchdog_cycles: twin.watchdog_cycles,
    }
}

pub fn plan_settings(settings: &RunSettings) -> PlanSettings {
    PlanSettings {
        period_s: settings.period_s(),
        speed_scale: settings.config.plan.speed_scale,
        accel_scale: settings.config.plan.accel_scale,
        ..PlanSettings::default()
    }
}

pub fn stream_settings(settings: &RunSettings) -> StreamSettings {
    StreamSettings::new(
        settings.period_s(),
        slowdown_rate(
            &settings.rig,
            settings.config.plan.speed_scale,
            settings.config.plan.accel_scale,
        ),
    )
}

/// The in-process twin at the configured initial position, behind a loopback link.
pub fn loopback_twin(settings: &RunSettings) -> Result<LoopbackLink, DaemonError> {
    let twin = Twin::new(&settings.rig, twin_settings(settings), &settings.initial())?;
    Ok(LoopbackLink::new(twin))
}

/// Opens the link `spec` names: the in-process twin for `loopback`, a real transport
/// otherwise (the controller on its far side is someone else's, or `rigbridge twin`).
pub fn open_link(
    spec: &crate::link::LinkSpec,
    settings: &RunSettings,
) -> Result<Box<dyn Link>, DaemonError> {
    use crate::link::LinkSpec;
    match spec {
        LinkSpec::Loopback => Ok(Box::new(loopback_twin(settings)?)),
        LinkSpec::Tcp { address } => {
            let link = crate::link::connect_tcp(crate::link::TcpSettings::new(address.clone()))
                .map_err(LinkError::Io)?;
            wait_for_link(
                &link,
                &crate::clock::WallClock::new(),
                settings.config.stream.reconnect_timeout_s,
            );
            Ok(Box::new(link))
        }
        LinkSpec::Serial { path, baud } => {
            let serial = settings.config.stream.serial_settings(path, *baud);
            let link = crate::link::connect_serial(serial).map_err(LinkError::Io)?;
            wait_for_link(
                &link,
                &crate::clock::WallClock::new(),
                settings.config.stream.reconnect_timeout_s,
            );
            Ok(Box::new(link))
        }
        LinkSpec::Can { interface } => {
            let mapping = settings
                .config
                .stream
                .can_mapping(crate::protocol::CanSender::Bridge)
                .map_err(|e| DaemonError::Unavailable(e.to_string()))?;
            let link = crate::link::connect_can(interface, mapping).map_err(LinkError::Io)?;
            wait_for_link(
                &link,
                &crate::clock::WallClock::new(),
                settings.config.stream.reconnect_timeout_s,
            );
            Ok(Box::new(link))
        }
        LinkSpec::Egm { address } => {
            let period = Duration::from_secs_f64(settings.period_s());
            let link = crate::link::bind_egm(address, settings.rig.dof(), period)
                .map_err(LinkError::Io)?;
            let timeout = settings.config.stream.reconnect_timeout_s;
            wait_for_link(&link, &crate::clock::WallClock::new(), timeout);
            Ok(Box::new(link))
        }
    }
}

/// The controller's actual position, read before planning so the plan starts there.
pub fn actual_position(link: &mut dyn Link, timeout: Duration) -> Result<Vec<f64>, DaemonError> {
    link.send(&Command::Heartbeat)?;
    let mut latest = link.receive(timeout)?;
    while let Some(newer) = link.receive(Duration::ZERO)? {
        latest = Some(newer);
    }
    latest
        .map(|f| f.positions.as_slice().to_vec())
        .ok_or_else(|| DaemonError::NoFeedback(link.describe()))
}

/// How long to wait for a controller's first answer: a remote one may only just have seen
/// the link come up.
pub const FIRST_FEEDBACK_TIMEOUT: Duration = Duration::from_millis(500);

/// A job planned from where the rig is: nothing has moved yet. A job with a bad target
/// never gets this far.
pub struct PlannedJob {
    pub job: config::JobConfig,
    pub start: Vec<f64>,
    pub trajectory: crate::trajectory::Trajectory,
}

pub fn plan_for(
    settings: &RunSettings,
    job: &config::JobConfig,
    link: &mut dyn Link,
) -> Result<PlannedJob, DaemonError> {
    let start = actual_position(link, FIRST_FEEDBACK_TIMEOUT)?;
    let trajectory = match (job, &settings.sloth) {
        (
            config::JobConfig::Gait {
                scenario,
                angle_deg,
                gap_m,
                forest,
            },
            Some(sloth),
        ) => {
            let scenario = crate::task::gait::forest::scenario_named(
                scenario,
                *angle_deg,
                *gap_m,
                forest.as_deref(),
                sloth.gait.trunk_tilt_rad,
            )
            .map_err(crate::task::gait::GaitError::from)?;
            crate::task::gait::plan_gait_job(sloth, &scenario, &start, &plan_settings(settings))?
        }
        _ => plan_job(job, &settings.rig, &start, &plan_settings(settings))?,
    };
    Ok(PlannedJob {
        job: job.clone(),
        start,
        trajectory,
    })
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
    let planned = plan_for(settings, job, link)?;
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
    stream_planned_with(settings, planned, link, clock, log, control, &mut ())
}

/// [`stream_planned`], also handing every cycle to `live` (the live view's sink).
pub fn stream_planned_with(
    settings: &RunSettings,
    planned: &PlannedJob,
    link: &mut dyn Link,
    clock: &dyn Clock,
    log: Option<&std::path::Path>,
    control: &StreamControl,
    live: &mut dyn crate::stream::CycleSink,
) -> Result<RunReport, DaemonError> {
    let trajectory = &planned.trajectory;
    let metadata = serde_json::json!({
        "job": planned.job,
        "config": settings.file.display().to_string(),
        "rate_hz": settings.config.stream.rate_hz,
        "period_s": settings.period_s(),
        "start": planned.start,
        "link": link.describe(),
    });
    // Under a virtual clock nothing is real time: the cycle waits for the log writer
    // rather than dropping records, so the log holds every cycle.
    let options = crate::log::RecorderOptions {
        wait_when_full: clock.is_virtual(),
        ..crate::log::RecorderOptions::for_rig(&settings.rig)
    };
    let names: Vec<String> = settings.rig.joint_names().map(str::to_owned).collect();
    let recorder = log
        .map(|path| {
            Recorder::create_with(
                path,
                &settings.rig.name,
                &names,
                metadata.clone(),
                options.clone(),
            )
        })
        .transpose()?;
    let report = match &recorder {
        Some(recorder) => {
            recorder.event(0.0, "job_started", metadata);
            let mut recording = RecorderSink::new(recorder, settings.period_s());
            let mut sink = recording::BothSinks(&mut recording, live);
            stream_resuming(
                settings,
                trajectory,
                link,
                clock,
                &mut sink,
                control,
                Some(recorder),
            )
        }
        None => stream_resuming(settings, trajectory, link, clock, live, control, None),
    };
    let log_report = match recorder {
        Some(recorder) => {
            let ended = match &report {
                Ok(r) => serde_json::to_value(r).unwrap_or_default(),
                Err(e) => serde_json::json!({ "error": error_chain(e) }),
            };
            let t = report.as_ref().map_or(0.0, |r| r.duration_s);
            recorder.event(t, "job_ended", ended);
            let stats = recorder.finish()?;
            log.map(|path| LogReport::new(path, stats))
        }
        None => None,
    };
    Ok(RunReport {
        rig: settings.rig.name.clone(),
        job: job_name(&planned.job),
        rate_hz: settings.config.stream.rate_hz,
        clock: if clock.is_virtual() {
            "virtual"
        } else {
            "wall"
        },
        planned_duration_s: trajectory.duration_s(),
        stream: report?,
        log: log_report,
    })
}

/// Streams `trajectory`; after a link loss, waits for the link (up to the configured
/// reconnect timeout), reads where the rig actually is, moves it from there to where the
/// job was interrupted and resumes from standstill: never a jump to a stale target.
fn stream_resuming(
    settings: &RunSettings,
    trajectory: &crate::trajectory::Trajectory,
    link: &mut dyn Link,
    clock: &dyn Clock,
    sink: &mut dyn crate::stream::CycleSink,
    control: &StreamControl,
    events: Option<&Recorder>,
) -> Result<StreamReport, DaemonError> {
    let mut streaming = stream_settings(settings);
    let mut report = stream(
        trajectory,
        &settings.rig,
        link,
        clock,
        sink,
        control,
        &streaming,
    )?;
    let mut remaining = trajectory.tail(report.samples_done);
    while report.outcome == crate::stream::Outcome::LinkLost {
        let t = report.duration_s;
        streaming.first_seq += u32::try_from(report.cycles).unwrap_or(u32::MAX);
        if let Some(recorder) = events {
            recorder.event(
                t,
                "link_lost",
                serde_json::json!({ "at_sample": report.samples_done }),
            );
        }
        if !wait_for_link(link, clock, settings.config.stream.reconnect_timeout_s) {
            report.fault = Some(format!(
                "link {} lost for {} s: job aborted {:.0} % of the way",
                link.describe(),
                settings.config.stream.reconnect_timeout_s,
                100.0 * report.samples_done as f64 / trajectory.len().max(1) as f64
            ));
            return Ok(report);
        }
        link.drain();
        let actual = actual_position(link, Duration::from_millis(200))?;
        let resume_at = remaining.position(0).to_vec();
        if let Some(recorder) = events {
            recorder.event(
                t,
                "resumed",
                serde_json::json!({ "actual": actual, "resume_at": resume_at }),
            );
        }
        let approach = crate::trajectory::plan_joint_moves(
            &settings.rig,
            &actual,
            &[resume_at],
            &plan_settings(settings),
        )
        .map_err(crate::job::JobError::from)?;
        let part = stream(
            &approach,
            &settings.rig,
            link,
            clock,
            sink,
            control,
            &streaming,
        )?;
        streaming.first_seq += u32::try_from(part.cycles).unwrap_or(u32::MAX);
        let approached = part.outcome == crate::stream::Outcome::Completed;
        report = report.merge(part);
        if !approached {
            continue;
        }
        let rest = StreamSettings {
            start_scale: 0.0,
            ..streaming
        };
        let part = stream(&remaining, &settings.rig, link, clock, sink, control, &rest)?;
        remaining = remaining.tail(part.samples_done);
        report = report.merge(part);
    }
    Ok(report)
}

/// Polls the link until it is up again or `timeout_s` passes.
fn wait_for_link(link: &dyn Link, clock: &dyn Clock, timeout_s: f64) -> bool {
    let deadline = clock.now() + Duration::from_secs_f64(timeout_s);
    while !link.is_up() {
        if clock.now() >= deadline {
            return false;
        }
        clock.sleep_until(clock.now() + Duration::from_millis(10));
    }
    true
}

fn job_name(job: &config::JobConfig) -> String {
    match job {
        config::JobConfig::WallFigure { .. } => "wall_figure".into(),
        config::JobConfig::JointWaypoints { .. } => "joint_waypoints".into(),
        config::JobConfig::Gait { scenario, .. } => format!("gait {scenario}"),
        config::JobConfig::Paint { walls, seed, .. } => {
            format!("paint ({walls} walls, seed {seed})")
        }
    }
}
