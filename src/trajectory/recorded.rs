//! A run log's commands as a [`Trajectory`] to replay (read by `log`, the stage below).
//! Checks only what makes the samples a trajectory at all (every cycle present, one period
//! apart, one value per joint); limits and speeds are the caller's check against the rig
//! (`trajectory::validate`), which this must not duplicate or skip. Must not read files
//! (the log's reader does).

use super::{Trajectory, TrajectoryError};
use crate::log::{LoggedSample, RunLog};
use std::time::Duration;
use thiserror::Error;

/// How far a command's `t` may sit from `t0 + index * period`.
pub const TIME_TOLERANCE_S: f64 = 1e-6;
/// How far the period handed in may sit from the one the log was written with: a
/// `Duration` holds it to the nearest nanosecond (1/300 s is 3,333,333 ns), so a log
/// written before periods were Durations drifts from it by up to half a nanosecond a
/// command, which the grid check allows on top of its tolerance.
const PERIOD_ROUNDING_S: f64 = 0.5e-9;

/// Why a run log's commands are not a trajectory.
#[derive(Debug, Error)]
pub enum RecordedError {
    #[error("the log holds no commands to replay")]
    NoCommands,
    #[error(
        "command {index}: seq {seq} follows seq {previous}; replay needs consecutive seq numbers"
    )]
    SeqGap {
        index: usize,
        previous: u32,
        seq: u32,
    },
    #[error(
        "command {index} (seq {seq}): t = {t:.9} s, expected {expected:.9} s for period {period_s} s (tolerance 1 us)"
    )]
    Uneven {
        index: usize,
        seq: u32,
        t: f64,
        expected: f64,
        period_s: f64,
    },
    #[error(
        "command {index} (seq {seq}): {positions} positions and {velocities} velocities for {dof} joints"
    )]
    AxisCount {
        index: usize,
        seq: u32,
        positions: usize,
        velocities: usize,
        dof: usize,
    },
    #[error(transparent)]
    Trajectory(#[from] TrajectoryError),
}

// An inherent method of the log's type, defined in the stage above it: `log` must not know
// trajectories, and `log.to_trajectory(period)` reads as what it does.
impl RunLog {
    /// The recorded commands, sample `i` at `i * period` (the log's first `t` becomes 0).
    /// Errors name the first command whose seq is not the previous one plus 1, whose `t` is
    /// off the period grid by more than 1 us (measured from the first command, so a drift
    /// cannot hide in per-step slack), or whose value count is not the joint count.
    pub fn to_trajectory(&self, period: Duration) -> Result<Trajectory, RecordedError> {
        if period.is_zero() {
            return Err(TrajectoryError::BadPeriod { period }.into());
        }
        // The records' `t` are seconds: the period meets them in f64.
        let period_s = period.as_secs_f64();
        let first = self.commands.first().ok_or(RecordedError::NoCommands)?;
        let dof = self.joint_names.len();
        let mut positions = Vec::with_capacity(self.commands.len() * dof);
        let mut velocities = Vec::with_capacity(self.commands.len() * dof);
        let mut previous: Option<&LoggedSample> = None;
        for (index, sample) in self.commands.iter().enumerate() {
            check_axes(index, sample, dof)?;
            if let Some(previous) = previous {
                check_seq(index, previous.seq, sample.seq)?;
            }
            check_time(index, first.t, sample, period_s)?;
            positions.extend_from_slice(&sample.positions);
            velocities.extend_from_slice(&sample.velocities);
            previous = Some(sample);
        }
        Ok(Trajectory::new(
            self.rig.clone(),
            self.joint_names.clone(),
            period,
            positions,
            velocities,
        )?)
    }
}

fn check_axes(index: usize, sample: &LoggedSample, dof: usize) -> Result<(), RecordedError> {
    if sample.positions.len() == dof && sample.velocities.len() == dof {
        return Ok(());
    }
    Err(RecordedError::AxisCount {
        index,
        seq: sample.seq,
        positions: sample.positions.len(),
        velocities: sample.velocities.len(),
        dof,
    })
}

fn check_seq(index: usize, previous: u32, seq: u32) -> Result<(), RecordedError> {
    // Wrapping: a u32 seq at 1 kHz wraps after 49 days, and the wrap itself is no gap.
    if seq == previous.wrapping_add(1) {
        return Ok(());
    }
    Err(RecordedError::SeqGap {
        index,
        previous,
        seq,
    })
}

fn check_time(
    index: usize,
    t0: f64,
    sample: &LoggedSample,
    period_s: f64,
) -> Result<(), RecordedError> {
    let expected = t0 + index as f64 * period_s;
    let tolerance = TIME_TOLERANCE_S + index as f64 * PERIOD_ROUNDING_S;
    // Written so that a NaN time fails too.
    if (sample.t - expected).abs() <= tolerance {
        return Ok(());
    }
    Err(RecordedError::Uneven {
        index,
        seq: sample.seq,
        t: sample.t,
        expected,
        period_s,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn log(samples: &[(u32, f64)]) -> RunLog {
        RunLog {
            rig: "r".into(),
            joint_names: vec!["a".into()],
            commands: samples
                .iter()
                .map(|&(seq, t)| LoggedSample {
                    seq,
                    t,
                    positions: vec![t],
                    velocities: vec![1.0],
                    late_us: None,
                })
                .collect(),
            ..RunLog::default()
        }
    }

    #[test]
    fn consecutive_evenly_spaced_commands_make_a_trajectory() {
        let trajectory = log(&[(5, 1.0), (6, 1.004), (7, 1.008)])
            .to_trajectory(Duration::from_millis(4))
            .expect("the commands make a trajectory");
        assert_eq!(trajectory.len(), 3);
        assert_eq!(&*trajectory.position(2), &[1.008]);
    }

    #[test]
    fn gaps_drift_and_bad_periods_are_named() {
        let gap = log(&[(5, 0.0), (7, 0.004)]).to_trajectory(Duration::from_millis(4));
        assert!(matches!(
            gap,
            Err(RecordedError::SeqGap {
                index: 1,
                previous: 5,
                seq: 7
            })
        ));
        let late =
            log(&[(0, 0.0), (1, 0.004), (2, 0.0080011)]).to_trajectory(Duration::from_millis(4));
        assert!(matches!(late, Err(RecordedError::Uneven { index: 2, .. })));
        let nan = log(&[(0, 0.0), (1, f64::NAN)]).to_trajectory(Duration::from_millis(4));
        assert!(matches!(nan, Err(RecordedError::Uneven { index: 1, .. })));
        assert!(log(&[(0, 0.0)]).to_trajectory(Duration::ZERO).is_err());
        assert!(matches!(
            log(&[]).to_trajectory(Duration::from_millis(4)),
            Err(RecordedError::NoCommands)
        ));
        let wrap = log(&[(u32::MAX, 0.0), (0, 0.004)]).to_trajectory(Duration::from_millis(4));
        assert!(wrap.is_ok());
    }

    #[test]
    fn a_log_at_a_period_of_no_whole_nanoseconds_replays_to_its_end() {
        // Written with t = i / 300 s in f64, read back with the period to the nanosecond.
        let records: Vec<(u32, f64)> = (0..100_000).map(|i| (i, i as f64 / 300.0)).collect();
        let period = Duration::try_from_secs_f64(1.0 / 300.0).expect("1/300 s is a valid duration");
        assert_eq!(period, Duration::from_nanos(3_333_333));
        assert_eq!(
            log(&records)
                .to_trajectory(period)
                .expect("the log replays as a trajectory")
                .len(),
            100_000
        );
        // A command a microsecond and a half off the grid is still named, late in the log.
        let mut drifted = records.clone();
        drifted[90_000].1 += 1.5e-6 + 90_000.0 * 0.5e-9;
        assert!(matches!(
            log(&drifted).to_trajectory(period),
            Err(RecordedError::Uneven { index: 90_000, .. })
        ));
    }
}
