//! The daemon: runs jobs end to end (plan, stream to the twin or a controller, record,
//! report) for the `run` and `serve` commands. Owns the wiring between stages and the
//! run report; the stages themselves live in their own modules.

pub mod config;

use crate::clock::Clock;
use crate::job::{JobError, plan_job};
use crate::link::{Link, LinkError, LoopbackLink};
use crate::protocol::Command;
use crate::stream::{CycleSink, StreamControl, StreamError, StreamReport, StreamSettings, slowdown_rate, stream};
use crate::trajectory::PlanSettings;
use crate::twin::{Twin, TwinError, TwinSettings};
use config::RunSettings;
use serde::Serialize;
use std::time::Duration;
use thiserror::Error;

#[derive(Debug, Error)]
pub enum DaemonError {
    #[error("twin: {0}")]
    Twin(#[from] TwinError),
    #[error("job refused before motion: {0}")]
    Job(#[from] JobError),
    #[error("streaming: {0}")]
    Stream(#[from] StreamError),
    #[error("link: {0}")]
    Link(#[from] LinkError),
    #[error("no feedback from {0}")]
    NoFeedback(String),
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
    StreamSettings {
        feedback_timeout: Duration::from_secs_f64(settings.period_s() / 2.0),
        slowdown_rate_per_s: slowdown_rate(&settings.rig, settings.config.plan.speed_scale, settings.config.plan.accel_scale),
    }
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

/// Plans the configured job from where the rig is, then streams it to the end (or until
/// `control` stops it).
pub fn run_job(
    settings: &RunSettings,
    link: &mut dyn Link,
    clock: &dyn Clock,
    sink: &mut dyn CycleSink,
    control: &StreamControl,
) -> Result<RunReport, DaemonError> {
    let streaming = stream_settings(settings);
    let start = actual_position(link, streaming.feedback_timeout)?;
    let trajectory = plan_job(&settings.config.job, &settings.rig, &start, &plan_settings(settings))?;
    let report = stream(&trajectory, &settings.rig, link, clock, sink, control, &streaming)?;
    Ok(RunReport {
        rig: settings.rig.name.clone(),
        job: job_name(settings),
        rate_hz: settings.config.stream.rate_hz,
        clock: if clock.is_virtual() { "virtual" } else { "wall" },
        planned_duration_s: trajectory.duration_s(),
        stream: report,
    })
}

fn job_name(settings: &RunSettings) -> String {
    match &settings.config.job {
        config::JobConfig::WallFigure { .. } => "wall_figure".into(),
        config::JobConfig::JointWaypoints { .. } => "joint_waypoints".into(),
    }
}
