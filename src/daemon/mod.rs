//! The daemon: runs jobs end to end (plan, stream to the twin or a controller, record,
//! report) for the `run` and `serve` commands. Owns the wiring between stages and the
//! run report; the stages themselves live in their own modules.

pub mod config;
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

/// The controller's actual position, read before planning so the plan starts there.
pub fn actual_position(link: &mut dyn Link, timeout: Duration) -> Result<Vec<f64>, DaemonError> {
    link.send(&Command::Heartbeat)?;
    link.receive(timeout)?
        .map(|f| f.positions.as_slice().to_vec())
        .ok_or_else(|| DaemonError::NoFeedback(link.describe()))
}

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
    let start = actual_position(link, stream_settings(settings).feedback_timeout)?;
    let trajectory = plan_job(job, &settings.rig, &start, &plan_settings(settings))?;
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
    let streaming = stream_settings(settings);
    let trajectory = &planned.trajectory;
    let metadata = serde_json::json!({
        "job": planned.job,
        "config": settings.file.display().to_string(),
        "rate_hz": settings.config.stream.rate_hz,
        "period_s": settings.period_s(),
        "start": planned.start,
        "link": link.describe(),
    });
    let recorder = log
        .map(|path| Recorder::for_rig(path, &settings.rig, metadata.clone()))
        .transpose()?;
    let report = match &recorder {
        Some(recorder) => {
            recorder.event(0.0, "job_started", metadata);
            let mut sink = RecorderSink::new(recorder, settings.period_s());
            stream(
                trajectory,
                &settings.rig,
                link,
                clock,
                &mut sink,
                control,
                &streaming,
            )
        }
        None => stream(
            trajectory,
            &settings.rig,
            link,
            clock,
            &mut (),
            control,
            &streaming,
        ),
    };
    let log_report = match recorder {
        Some(recorder) => {
            let ended = match &report {
                Ok(r) => serde_json::to_value(r).unwrap_or_default(),
                Err(e) => serde_json::json!({ "error": e.to_string() }),
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

fn job_name(job: &config::JobConfig) -> String {
    match job {
        config::JobConfig::WallFigure { .. } => "wall_figure".into(),
        config::JobConfig::JointWaypoints { .. } => "joint_waypoints".into(),
    }
}
