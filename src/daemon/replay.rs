//! Replay: re-streams a recorded run's commands with their timing (optionally faster or
//! slower) after validating them again against the rig, and compares what the controller
//! does now with what it did then. Owns that comparison; reading the log is `log`'s job.

use super::{DaemonError, LogReport, RecorderSink, stream_settings};
use crate::clock::Clock;
use crate::daemon::config::RunSettings;
use crate::link::Link;
use crate::log::{LogError, Recorder, RunLog};
use crate::stream::{CycleRecord, CycleSink, StreamControl, StreamReport, stream};
use crate::trajectory::Trajectory;
use serde::Serialize;
use std::collections::HashMap;
use std::path::Path;

#[derive(Debug, Clone, Serialize)]
pub struct ReplayReport {
    pub rig: String,
    pub speed: f64,
    pub recorded_commands: usize,
    /// True when every recorded command was sent again, in order, with its seq.
    pub same_sequence: bool,
    /// Largest difference between the actual positions now and in the recording (deg).
    pub max_deviation_from_recording_deg: f64,
    #[serde(flatten)]
    pub stream: StreamReport,
    pub log: Option<LogReport>,
}

/// Where the recorded run started and its period, from the log's metadata.
fn recorded_start(log: &RunLog) -> Result<(Vec<f64>, f64), DaemonError> {
    let start: Option<Vec<f64>> = log
        .metadata
        .get("start")
        .and_then(|v| serde_json::from_value(v.clone()).ok());
    let period = log
        .metadata
        .get("period_s")
        .and_then(serde_json::Value::as_f64);
    match (start, period) {
        (Some(start), Some(period)) if start.len() == log.joint_names.len() => Ok((start, period)),
        _ => Err(DaemonError::Replay(
            "the log's metadata has no start position or period (was it written by `rigbridge run`?)".into(),
        )),
    }
}

/// The start position, then every recorded command, at `period_s`.
pub fn replay_trajectory(log: &RunLog, speed: f64) -> Result<(Trajectory, Vec<f64>), DaemonError> {
    if !(speed.is_finite() && speed > 0.0) {
        return Err(DaemonError::Replay(format!(
            "speed {speed} must be a positive number"
        )));
    }
    let (start, period) = recorded_start(log)?;
    let commands = log.to_trajectory(period)?;
    let mut positions = start.clone();
    let mut velocities = vec![0.0; start.len()];
    for sample in 0..commands.len() {
        positions.extend_from_slice(commands.position(sample));
        velocities.extend(commands.velocity(sample).iter().map(|v| v * speed));
    }
    let trajectory = Trajectory::new(
        log.rig.clone(),
        log.joint_names.clone(),
        period / speed,
        positions,
        velocities,
    )
    .map_err(LogError::from)?;
    Ok((trajectory, start))
}

/// Collects the replayed cycles for the comparison, and passes them on to the recorder.
struct Comparison<'a> {
    recorded: HashMap<u32, &'a [f64]>,
    recorded_seqs: Vec<u32>,
    sent_seqs: Vec<u32>,
    max_deviation: f64,
    recorder: Option<RecorderSink<'a>>,
}

impl CycleSink for Comparison<'_> {
    fn record(&mut self, cycle: &CycleRecord) {
        self.sent_seqs.push(cycle.target.seq);
        if let (Some(feedback), Some(then)) =
            (&cycle.feedback, self.recorded.get(&cycle.target.seq))
        {
            for (now, then) in feedback.positions.as_slice().iter().zip(then.iter()) {
                self.max_deviation = self.max_deviation.max((now - then).abs().to_degrees());
            }
        }
        if let Some(recorder) = &mut self.recorder {
            recorder.record(cycle);
        }
    }
}

/// Streams `log`'s commands over `link` (whose controller must be at the recorded start).
pub fn replay(
    log: &RunLog,
    settings: &RunSettings,
    speed: f64,
    link: &mut dyn Link,
    clock: &dyn Clock,
    record_to: Option<&Path>,
    control: &StreamControl,
) -> Result<ReplayReport, DaemonError> {
    let (trajectory, _) = replay_trajectory(log, speed)?;
    let recorder = record_to
        .map(|path| Recorder::for_rig(path, &settings.rig, log.metadata.clone()))
        .transpose()?;
    let mut comparison = Comparison {
        recorded: log
            .states
            .iter()
            .map(|s| (s.seq, s.positions.as_slice()))
            .collect(),
        recorded_seqs: log.commands.iter().map(|c| c.seq).collect(),
        sent_seqs: Vec::with_capacity(log.commands.len()),
        max_deviation: 0.0,
        recorder: recorder
            .as_ref()
            .map(|r| RecorderSink::new(r, trajectory.period_s)),
    };
    let mut streaming = stream_settings(settings);
    streaming.feedback_timeout = std::time::Duration::from_secs_f64(trajectory.period_s / 2.0);
    let result = stream(
        &trajectory,
        &settings.rig,
        link,
        clock,
        &mut comparison,
        control,
        &streaming,
    );
    let same_sequence = comparison.sent_seqs == comparison.recorded_seqs;
    let max_deviation = comparison.max_deviation;
    drop(comparison);
    let log_report = match recorder {
        Some(recorder) => record_to
            .map(|path| recorder.finish().map(|stats| LogReport::new(path, stats)))
            .transpose()?,
        None => None,
    };
    let report = result?;
    Ok(ReplayReport {
        rig: settings.rig.name.clone(),
        speed,
        recorded_commands: log.commands.len(),
        same_sequence,
        max_deviation_from_recording_deg: max_deviation,
        stream: report,
        log: log_report,
    })
}
