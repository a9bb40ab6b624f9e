//! The sample budget of one plan: how long a planned trajectory may last and how much memory
//! its samples may take, checked before a planner samples anything (`docs/jobs.md`,
//! "Limits"). A plan sampled at the stream's period takes samples x axes x
//! [`BYTES_PER_AXIS_SAMPLE`]; a curve sampled on demand takes its knots
//! ([`SampleBudget::check_curve`]). Owns the arithmetic and its error; the caps'
//! defaults and the `[limits]` keys that override them are the job layer's.

use crate::motion::{HermiteCurve, Trajectory};
use std::time::Duration;
use thiserror::Error;

/// What one axis of one stored sample takes: a position and a velocity, `f64` each.
pub const BYTES_PER_AXIS_SAMPLE: u64 = 16;

/// Bytes in a megabyte, as the caps and messages count them (MiB).
pub const BYTES_PER_MB: f64 = 1024.0 * 1024.0;

/// The longest plan by default (s): two hours. The longest jobs shipped plan 90 minutes (a
/// 32-wall room, `job.walls`' cap) and 51 minutes (a 1000-lap star, `job.laps`' cap);
/// longer work is several jobs, each stoppable and logged on its own. Override:
/// `[limits] max_job_duration_s`.
pub const DEFAULT_MAX_DURATION_S: f64 = 7_200.0;

/// The most memory one plan's samples may take by default (MB): the 32-wall room's ten axes
/// at its 100 Hz take 82 MB, an hour of six axes at 250 Hz 82 MB, so 128 MB holds them while
/// a daemon with a few cells stays far inside a small controller PC's memory (planning holds
/// a plan up to twice). Override: `[limits] max_plan_mb`.
pub const DEFAULT_MAX_PLAN_MB: f64 = 128.0;

/// How much one plan may take: its duration and its samples' memory. `spent` counts the
/// samples already planned by the pieces of the same job before this one.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SampleBudget {
    pub max_duration_s: f64,
    pub max_plan_mb: f64,
    pub spent: usize,
}

impl Default for SampleBudget {
    fn default() -> Self {
        SampleBudget {
            max_duration_s: DEFAULT_MAX_DURATION_S,
            max_plan_mb: DEFAULT_MAX_PLAN_MB,
            spent: 0,
        }
    }
}

/// A plan that would break its budget, refused before it is sampled.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum OverBudget {
    #[error(
        "the plan would last {duration_s:.1} s, longer than the cap of {max_duration_s} s \
         (`[limits] max_job_duration_s`)"
    )]
    Duration {
        duration_s: f64,
        max_duration_s: f64,
    },
    #[error(
        "the plan's {samples} samples of {dof} axes would take {mb:.1} MB, more than the cap \
         of {max_plan_mb} MB (`[limits] max_plan_mb`)"
    )]
    Memory {
        samples: u64,
        dof: usize,
        mb: f64,
        max_plan_mb: f64,
    },
}

/// Memory (MB) of `samples` stored samples of `dof` axes.
pub fn plan_mb(samples: u64, dof: usize) -> f64 {
    samples as f64 * dof as f64 * BYTES_PER_AXIS_SAMPLE as f64 / BYTES_PER_MB
}

impl SampleBudget {
    /// This budget once `samples` more are planned.
    pub fn after(self, samples: usize) -> Self {
        SampleBudget {
            spent: self.spent.saturating_add(samples),
            ..self
        }
    }

    /// Whether `more` samples every `period` of `dof` axes, after those spent, stay within
    /// the budget. Counts in `f64` and `u64`, so a hostile length cannot overflow it.
    pub fn check(&self, more: u64, period: Duration, dof: usize) -> Result<(), OverBudget> {
        let samples = self.check_duration(more, period)?;
        let mb = plan_mb(samples, dof);
        if mb > self.max_plan_mb {
            return Err(OverBudget::Memory {
                samples,
                dof,
                mb,
                max_plan_mb: self.max_plan_mb,
            });
        }
        Ok(())
    }

    /// Whether `more` samples every `period`, after those spent, stay within the duration
    /// cap: the samples in all, when they do.
    fn check_duration(&self, more: u64, period: Duration) -> Result<u64, OverBudget> {
        let samples = (self.spent as u64).saturating_add(more);
        let duration_s = samples.saturating_sub(1) as f64 * period.as_secs_f64();
        if duration_s > self.max_duration_s {
            return Err(OverBudget::Duration {
                duration_s,
                max_duration_s: self.max_duration_s,
            });
        }
        Ok(samples)
    }

    /// [`Self::check`] for a trajectory lasting `seconds` sampled every `period`: its
    /// samples, first and last included.
    pub fn check_seconds(
        &self,
        seconds: f64,
        period: Duration,
        dof: usize,
    ) -> Result<(), OverBudget> {
        self.check(samples_in(seconds, period), period, dof)
    }

    /// A curve lasting `seconds` through `knots` knots of `dof` axes, sampled on demand
    /// every `period` ([`crate::motion::HermiteCurve`]): its samples count against the
    /// duration cap, its knots (not its samples) against the memory cap, beside the samples
    /// spent before it, stored.
    pub fn check_curve(
        &self,
        seconds: f64,
        knots: usize,
        period: Duration,
        dof: usize,
    ) -> Result<(), OverBudget> {
        let samples = self.check_duration(samples_in(seconds, period), period)?;
        self.check_stored(samples, dof, HermiteCurve::bytes_for(knots, dof))
    }

    /// A planned trajectory within the budget: its samples against the duration cap, what
    /// it stores (not its samples, for a curve sampled on demand) against the memory cap.
    pub fn check_trajectory(&self, trajectory: &Trajectory) -> Result<(), OverBudget> {
        let samples = self.check_duration(trajectory.len() as u64, trajectory.period)?;
        self.check_stored(samples, trajectory.dof(), trajectory.stored_bytes())
    }

    /// `bytes` stored beside the samples spent (of `dof` axes) within the memory cap;
    /// `samples` in all, for the refusal.
    fn check_stored(&self, samples: u64, dof: usize, bytes: usize) -> Result<(), OverBudget> {
        let mb = plan_mb(self.spent as u64, dof) + bytes as f64 / BYTES_PER_MB;
        if mb > self.max_plan_mb {
            return Err(OverBudget::Memory {
                samples,
                dof,
                mb,
                max_plan_mb: self.max_plan_mb,
            });
        }
        Ok(())
    }
}

/// The samples of a trajectory lasting `seconds` every `period`, first and last included;
/// saturates for a hostile `seconds`, which the checks then refuse.
fn samples_in(seconds: f64, period: Duration) -> u64 {
    let periods = (seconds / period.as_secs_f64()).ceil();
    let samples = if periods.is_finite() && periods >= 0.0 {
        periods as u64
    } else {
        u64::MAX
    };
    samples.saturating_add(1)
}

#[cfg(test)]
mod tests {
    use super::*;

    const PERIOD: Duration = Duration::from_millis(4);

    #[test]
    fn a_day_at_250_hz_is_refused_an_hour_is_not() {
        let budget = SampleBudget::default();
        assert!(budget.check_seconds(3_600.0, PERIOD, 6).is_ok());
        let refused = budget.check_seconds(86_400.0, PERIOD, 6).unwrap_err();
        assert!(
            matches!(refused, OverBudget::Duration { duration_s, .. } if duration_s == 86_400.0)
        );
        assert!(
            refused.to_string().contains("max_job_duration_s"),
            "{refused}"
        );
    }

    #[test]
    fn memory_counts_axes_and_what_was_spent() {
        // 900,001 samples (an hour at 250 Hz) of 10 axes: 137.3 MB, over 128.
        let budget = SampleBudget::default();
        assert!(budget.check_seconds(7_200.0, PERIOD, 1).is_ok());
        let longer = budget.check_seconds(7_201.0, PERIOD, 1).unwrap_err();
        assert!(matches!(longer, OverBudget::Duration { .. }), "{longer}");
        let refused = budget.check_seconds(3_600.0, PERIOD, 10).unwrap_err();
        assert!(
            matches!(
                refused,
                OverBudget::Memory {
                    samples: 900_001,
                    ..
                }
            ),
            "{refused}"
        );
        let hour = SampleBudget {
            max_duration_s: 3_600.0,
            ..budget
        };
        let half = hour.after(450_000);
        assert!(half.check(450_001, PERIOD, 6).is_ok());
        assert!(
            half.check(450_002, PERIOD, 6).is_err(),
            "one sample past the hour"
        );
        assert!(budget.check_seconds(f64::INFINITY, PERIOD, 6).is_err());
    }
}
