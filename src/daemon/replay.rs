//! Replay: a recorded run's commands as a job like any other. The recorded path is taken
//! at the stream's own rate and `speed` x its pace (resampled when that is not the log's
//! period), ended with a stop ramp when the recording ends with the axes moving, approached
//! from where the controller holds, validated against the rig, and streamed through the same
//! resuming path as `run` over any link. Owns that construction and the comparison of what
//! the controller does now with what it did then; reading the log is `log`'s job, the
//! cycle `stream`'s, the limits `trajectory::validate`'s.

use super::{
    DaemonError, JobToStream, RunReport, clear, held_position, plan_settings, stream_job_with,
};
use crate::clock::Clock;
use crate::daemon::config::RunSettings;
use crate::link::Link;
use crate::log::RunLog;
use crate::stream::{CycleRecord, CycleSink, StreamControl};
use crate::trajectory::{
    Origins, PlanError, RecordedError, Trajectory, TrajectoryError, check_clear, plan_joint_moves,
    ramp_to_rest, resample, validate, validate_motion,
};
use serde::Serialize;
use std::collections::HashMap;
use std::path::Path;
use std::time::Duration;
use thiserror::Error;

/// The held position counts as the recorded start when every axis is this share of
/// `a_max T^2` from it: the first step then stays within the axis' acceleration from rest
/// (docs/protocol.md 6.6), so no approach is needed. Farther, an approach is planned.
const SAME_START_SHARE: f64 = 0.01;
/// What a refusal of the move to the log's first command calls it.
const APPROACH: &str = "the approach from where the controller holds to the log's start";

#[derive(Debug, Error)]
pub enum ReplayError {
    #[error("speed {speed} must be a positive number")]
    BadSpeed { speed: f64 },
    #[error(
        "the log's metadata has no start position or period (was it written by `rigbridge run`?)"
    )]
    NoMetadata,
    #[error("the log's metadata key `period_s` = {value} is not a positive period in seconds")]
    BadPeriod { value: f64 },
    #[error("the log records rig `{log}`, the run settings describe `{settings}`")]
    RigMismatch { log: String, settings: String },
    #[error(
        "the log ({:.3} ms a command) replayed at {speed} x speed every {:.3} ms is refused",
        recorded.as_secs_f64() * 1e3,
        period.as_secs_f64() * 1e3
    )]
    Refused {
        recorded: Duration,
        period: Duration,
        speed: f64,
        #[source]
        source: TrajectoryError,
    },
    #[error("the log replayed at {speed} x speed is refused before it is resampled")]
    OverBudget {
        speed: f64,
        #[source]
        source: crate::trajectory::OverBudget,
    },
    #[error("the stop ramp after the log's last command is refused")]
    Ramp(#[source] TrajectoryError),
    #[error("cannot plan the approach from where the controller holds to the log's start")]
    Approach(#[source] PlanError),
}

#[derive(Debug, Clone, Serialize)]
pub struct ReplayReport {
    pub speed: f64,
    pub recorded_commands: usize,
    /// The log's period (s), and whether the path was resampled to the stream's.
    pub recorded_period_s: f64,
    pub resampled: bool,
    /// Samples of the planned approach from the held position to the log's start (0: it
    /// held there), and of the stop ramp after the log's last command (0: it ended at rest).
    pub approach_samples: usize,
    pub stop_ramp_samples: usize,
    /// True when every recorded command was sent again, one a cycle, in order and unchanged
    /// (the numbering shifted by the approach); false when resampled, resumed or cut short.
    pub same_sequence: bool,
    /// Largest difference between the actual positions now and in the recording (deg), over
    /// the cycles that sent a recorded command again; none when resampled (no cycle of the
    /// replay is one of the recording's).
    pub max_deviation_from_recording_deg: Option<f64>,
    #[serde(flatten)]
    pub run: RunReport,
}

/// The recorded path at the stream's rate, ready to be approached and streamed.
#[derive(Debug, Clone)]
pub struct Replayed {
    pub trajectory: Trajectory,
    pub recorded_period: Duration,
    pub resampled: bool,
    pub stop_ramp_samples: usize,
    /// The seq the recording gave its trajectory's sample 0 (its first command's, less 1).
    pub recorded_first_seq: u32,
}

/// Where the recorded run started and its period, from the log's metadata.
fn recorded_start(log: &RunLog) -> Result<(Vec<f64>, Duration), ReplayError> {
    let start: Option<Vec<f64>> = log
        .metadata
        .get("start")
        .and_then(|v| serde_json::from_value(v.clone()).ok());
    let period = log
        .metadata
        .get("period_s")
        .and_then(serde_json::Value::as_f64);
    match (start, period) {
        (Some(start), Some(value)) if start.len() == log.joint_names.len() => {
            match Duration::try_from_secs_f64(value) {
                Ok(period) if !period.is_zero() => Ok((start, period)),
                _ => Err(ReplayError::BadPeriod { value }),
            }
        }
        _ => Err(ReplayError::NoMetadata),
    }
}

/// The log's path (its start, then every recorded command) at `settings`' stream period and
/// `speed` x the recorded pace, ending at rest, validated against the rig.
pub fn replay_trajectory(
    log: &RunLog,
    settings: &RunSettings,
    speed: f64,
) -> Result<Replayed, DaemonError> {
    if !(speed.is_finite() && speed > 0.0) {
        return Err(ReplayError::BadSpeed { speed }.into());
    }
    if log.rig != settings.rig.name {
        return Err(ReplayError::RigMismatch {
            log: log.rig.clone(),
            settings: settings.rig.name.clone(),
        }
        .into());
    }
    let (start, recorded_period) = recorded_start(log)?;
    let commands = log.to_trajectory(recorded_period)?;
    let mut positions = start.clone();
    let mut velocities = vec![0.0; start.len()];
    for sample in 0..commands.len() {
        let (at, moving) = commands.sample(sample);
        positions.extend_from_slice(&at);
        velocities.extend_from_slice(&moving);
    }
    let recorded = Trajectory::new(
        log.rig.clone(),
        log.joint_names.clone(),
        recorded_period,
        positions,
        velocities,
    )
    .map_err(RecordedError::from)?;
    let period = settings.period();
    let refused = |source| ReplayError::Refused {
        recorded: recorded_period,
        period,
        speed,
        source,
    };
    // Resampling at a low speed multiplies the samples: the same caps as any job's plan.
    settings
        .config
        .limits
        .budget()
        .check_seconds(recorded.duration_s() / speed, period, recorded.dof())
        .map_err(|source| ReplayError::OverBudget { speed, source })?;
    let resampled = resample(&recorded, period, speed).map_err(refused)?;
    // Whole but for its end: a run cut short ends moving until the ramp brings it to rest.
    validate_motion(&resampled, &settings.rig).map_err(refused)?;
    let accel_share = settings.config.plan.accel_scale;
    let (trajectory, ramp) =
        ramp_to_rest(&resampled, &settings.rig, accel_share).map_err(ReplayError::Ramp)?;
    validate(&trajectory, &settings.rig).map_err(ReplayError::Ramp)?;
    let verbatim = resampled.len() == recorded.len()
        && (0..recorded.len()).all(|k| resampled.position(k) == recorded.position(k));
    let replayed = Replayed {
        trajectory,
        recorded_period,
        resampled: !verbatim,
        stop_ramp_samples: ramp,
        recorded_first_seq: log.commands.first().map_or(0, |c| c.seq.wrapping_sub(1)),
    };
    check_log_path(settings, &replayed, resampled.len(), speed)?;
    Ok(replayed)
}

/// The replayed path checked against the cell before any motion; a refusal names the log's
/// command (its seq) when the path is the log's commands one for one, else the time in the
/// recording (`resampled_len`: samples before the stop ramp).
fn check_log_path(
    settings: &RunSettings,
    replayed: &Replayed,
    resampled_len: usize,
    speed: f64,
) -> Result<(), DaemonError> {
    let mut origins = Origins::default();
    origins.push(0, "the log's start position");
    origins.push(resampled_len - 1, "the log's commands");
    origins.push(usize::MAX, "the stop ramp after the log's last command");
    let refused = check_clear(
        &replayed.trajectory,
        &settings.rig,
        &settings.collision,
        &origins,
    );
    let Err(mut refusal) = refused else {
        return Ok(());
    };
    let sample = refusal.sample;
    if (1..resampled_len).contains(&sample) {
        refusal.origin = if replayed.resampled {
            format!(
                "the log's commands at t = {:.3} s of the recording",
                sample as f64 * settings.period().as_secs_f64() * speed
            )
        } else {
            format!(
                "the log's command seq {}",
                replayed.recorded_first_seq.wrapping_add(sample as u32)
            )
        };
    }
    Err(refusal.into())
}

/// The move from `held` to the replay's first sample, when they differ (else `None`).
fn approach(
    settings: &RunSettings,
    held: &[f64],
    first: &[f64],
) -> Result<Option<Trajectory>, ReplayError> {
    let dt = settings.period().as_secs_f64();
    let same = settings
        .rig
        .joints
        .iter()
        .zip(held.iter().zip(first))
        .all(|(joint, (h, f))| {
            (h - f).abs() <= SAME_START_SHARE * joint.limits.max_acceleration * dt * dt
        });
    if same {
        return Ok(None);
    }
    plan_joint_moves(
        &settings.rig,
        held,
        &[first.to_vec()],
        &plan_settings(settings),
    )
    .map(Some)
    .map_err(ReplayError::Approach)
}

/// Compares the replayed cycles with the recording's, matched by seq (shifted by the
/// approach): whether the recorded commands went out again one for one, and how far the
/// controller is from where it was then on those cycles.
struct Comparison<'a> {
    log: &'a RunLog,
    states: HashMap<u32, &'a [f64]>,
    /// Replay seq minus recording seq, for the same sample of the recorded path.
    offset: u32,
    /// Recorded commands sent again, in order and unchanged, so far.
    matched: usize,
    /// A cycle inside the recorded range sent something else (resampled, or resumed).
    broken: bool,
    max_deviation: f64,
}

impl CycleSink for Comparison<'_> {
    fn record(&mut self, cycle: &CycleRecord) {
        let Some(first) = self.log.commands.first() else {
            return;
        };
        let seq = cycle.target.seq.wrapping_sub(self.offset);
        let index = seq.wrapping_sub(first.seq) as usize;
        if self.broken || index >= self.log.commands.len() {
            return;
        }
        let recorded = &self.log.commands[index];
        if index != self.matched || cycle.target.positions.as_slice() != recorded.positions {
            self.broken = true;
            return;
        }
        self.matched += 1;
        if let (Some(feedback), Some(then)) = (&cycle.feedback, self.states.get(&seq)) {
            for (now, then) in feedback.positions.as_slice().iter().zip(then.iter()) {
                self.max_deviation = self.max_deviation.max((now - then).abs().to_degrees());
            }
        }
    }
}

/// Replays `log` over `link`: from where its controller holds, at `settings`' stream rate
/// and `speed` x the recorded pace, recording to `record_to` when given.
pub fn replay(
    log: &RunLog,
    settings: &RunSettings,
    speed: f64,
    link: &mut dyn Link,
    clock: &dyn Clock,
    record_to: Option<&Path>,
    control: &StreamControl,
) -> Result<ReplayReport, DaemonError> {
    let replayed = replay_trajectory(log, settings, speed)?;
    let held = held_position(settings, link, clock, control)?;
    let trajectory = match approach(settings, &held, &replayed.trajectory.position(0))? {
        Some(mut moved) => {
            clear(settings, &moved, &Origins::whole(APPROACH))?;
            moved.append(&replayed.trajectory);
            moved
        }
        None => replayed.trajectory.clone(),
    };
    let approach_samples = trajectory.len() - replayed.trajectory.len();
    validate(&trajectory, &settings.rig).map_err(|source| ReplayError::Refused {
        recorded: replayed.recorded_period,
        period: settings.period(),
        speed,
        source,
    })?;
    let mut comparison = Comparison {
        log,
        states: log
            .states
            .iter()
            .map(|s| (s.seq, s.positions.as_slice()))
            .collect(),
        offset: (approach_samples as u32).wrapping_sub(replayed.recorded_first_seq),
        matched: 0,
        broken: false,
        max_deviation: 0.0,
    };
    let job = JobToStream {
        name: "replay".into(),
        description: serde_json::json!({
            "kind": "replay",
            "speed": speed,
            "recorded_period_s": replayed.recorded_period.as_secs_f64(),
            "recorded_job": log.metadata.get("job"),
        }),
        start: &held,
        trajectory: &trajectory,
        job: None,
        // Both parts were checked: the log's path with its commands' seqs, the approach.
        origins: &Origins::whole("the replay"),
        cleared: true,
    };
    let run = stream_job_with(
        settings,
        &job,
        link,
        clock,
        record_to,
        control,
        super::Sinks {
            live: &mut comparison,
            actions: None,
            executor: None,
        },
    )?;
    let same_sequence = !comparison.broken && comparison.matched == log.commands.len();
    Ok(ReplayReport {
        speed,
        recorded_commands: log.commands.len(),
        recorded_period_s: replayed.recorded_period.as_secs_f64(),
        resampled: replayed.resampled,
        approach_samples,
        stop_ramp_samples: replayed.stop_ramp_samples,
        same_sequence,
        max_deviation_from_recording_deg: (!replayed.resampled).then_some(comparison.max_deviation),
        run,
    })
}
