//! `[limits]`: the caps on what one job may cost the daemon, whatever it came from (a run
//! settings file, `POST /api/jobs`, a ROS 2 JointTrajectory, a trajectory CSV): how long it
//! may last, how many points it may hold, and how much memory its plan may take. Checked in
//! [`super::Job::validate`], before anything is planned, from what the job's keys say; the
//! planners check the same budget again before each piece they sample
//! (`crate::trajectory::SampleBudget`), for the jobs whose length only planning tells.
//! Owns the keys, their defaults and the refusals' text (`docs/jobs.md`, "Limits").

use super::JobInvalid;
use crate::trajectory::{
    DEFAULT_MAX_DURATION_S, DEFAULT_MAX_PLAN_MB, OverBudget, SampleBudget, plan_mb,
};
use serde::Deserialize;
use std::time::Duration;

/// The most points (rows of a trajectory, a ROS 2 message's points) one job may hold by
/// default: over an hour at 50 points a second. Each is parsed and checked before planning,
/// so the cap bounds that work as well as the plan. Override: `[limits] max_job_points`.
pub const DEFAULT_MAX_JOB_POINTS: usize = 200_000;

/// The widest `[limits]` a config may set: a week of motion, ten million points, 16 GB of
/// plan. Beyond that a typo, not an integrator's need, is the likelier cause.
pub const CEILING_DURATION_S: f64 = 604_800.0;
pub const CEILING_POINTS: usize = 10_000_000;
pub const CEILING_PLAN_MB: f64 = 16_384.0;

/// `[limits]`; every key optional.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct JobLimits {
    /// Longest job (s): [`DEFAULT_MAX_DURATION_S`] when absent.
    pub max_job_duration_s: f64,
    /// Most points a job's trajectory may hold: [`DEFAULT_MAX_JOB_POINTS`] when absent.
    pub max_job_points: usize,
    /// Most memory a job's plan may take (MB): [`DEFAULT_MAX_PLAN_MB`] when absent.
    pub max_plan_mb: f64,
}

impl Default for JobLimits {
    fn default() -> Self {
        JobLimits {
            max_job_duration_s: DEFAULT_MAX_DURATION_S,
            max_job_points: DEFAULT_MAX_JOB_POINTS,
            max_plan_mb: DEFAULT_MAX_PLAN_MB,
        }
    }
}

impl JobLimits {
    /// The planners' budget for one job under these limits.
    pub fn budget(&self) -> SampleBudget {
        SampleBudget {
            max_duration_s: self.max_job_duration_s,
            max_plan_mb: self.max_plan_mb,
            spent: 0,
        }
    }

    /// `count` points under `key` within `max_job_points`.
    pub fn check_points(&self, key: &str, count: usize) -> Result<(), JobInvalid> {
        if count <= self.max_job_points {
            return Ok(());
        }
        Err(JobInvalid::new(
            key,
            format!("{count} points"),
            format!(
                "more than the cap of {} points (`[limits] max_job_points`)",
                self.max_job_points
            ),
        ))
    }

    /// A trajectory under `key` lasting `seconds`, sampled every `period` on `dof` axes,
    /// within the duration and memory caps: refused here, before any of it is planned.
    pub fn check_duration(
        &self,
        key: &str,
        seconds: f64,
        period: Duration,
        dof: usize,
    ) -> Result<(), JobInvalid> {
        let refuse = |reason: OverBudget| {
            JobInvalid::new(key, format!("{seconds} s"), refusal_reason(&reason))
        };
        self.budget()
            .check_seconds(seconds, period, dof)
            .map_err(refuse)
    }
}

impl JobLimits {
    /// A curve under `key` lasting `seconds` through `knots` points, sampled on demand every
    /// `period` on `dof` axes (a `follow_trajectory`'s rows): within the duration cap, and
    /// its knots within the memory cap; refused here, before any of it is planned.
    pub fn check_curve(
        &self,
        key: &str,
        seconds: f64,
        knots: usize,
        period: Duration,
        dof: usize,
    ) -> Result<(), JobInvalid> {
        let refuse = |reason: OverBudget| {
            JobInvalid::new(key, format!("{seconds} s"), refusal_reason(&reason))
        };
        self.budget()
            .check_curve(seconds, knots, period, dof)
            .map_err(refuse)
    }
}

/// The reason a job over budget is refused, naming the value and the cap.
fn refusal_reason(over: &OverBudget) -> String {
    match over {
        OverBudget::Duration {
            duration_s,
            max_duration_s,
        } => format!(
            "lasts {duration_s:.1} s, longer than the cap of {max_duration_s} s \
             (`[limits] max_job_duration_s`)"
        ),
        OverBudget::Memory {
            samples,
            dof,
            mb,
            max_plan_mb,
        } => format!(
            "its plan would be {samples} samples of {dof} axes, {mb:.1} MB, more than the \
             cap of {max_plan_mb} MB (`[limits] max_plan_mb`)"
        ),
    }
}

/// Memory (MB) the plan of a job lasting `seconds` at `period` on `dof` axes takes: what
/// `docs/jobs.md` tells an integrator sizing `[limits]`.
pub fn planned_mb(seconds: f64, period: Duration, dof: usize) -> f64 {
    let samples = (seconds / period.as_secs_f64()).ceil().max(0.0) as u64 + 1;
    plan_mb(samples, dof)
}

#[cfg(test)]
mod tests {
    use super::*;

    const PERIOD: Duration = Duration::from_millis(4);

    #[test]
    fn a_day_long_trajectory_is_refused_naming_the_value_the_cap_and_the_key() {
        let refused = JobLimits::default()
            .check_duration("job.rows", 86_400.0, PERIOD, 6)
            .unwrap_err();
        let text = refused.to_string();
        for part in ["job.rows", "86400 s", "7200 s", "max_job_duration_s"] {
            assert!(text.contains(part), "{part} missing from: {text}");
        }
    }

    #[test]
    fn the_memory_cap_counts_the_rate_and_the_axes() {
        // An hour on 6 axes at 250 Hz is 82.4 MB: under 128 MB, refused under 64 MB.
        assert!((planned_mb(3_600.0, PERIOD, 6) - 82.4).abs() < 0.1);
        let tight = JobLimits {
            max_plan_mb: 64.0,
            ..JobLimits::default()
        };
        assert!(
            JobLimits::default()
                .check_duration("k", 3_600.0, PERIOD, 6)
                .is_ok()
        );
        let refused = tight.check_duration("k", 3_600.0, PERIOD, 6).unwrap_err();
        assert!(refused.reason.contains("max_plan_mb"), "{refused}");
        let points = JobLimits::default().check_points("job.rows", 200_001);
        assert!(points.unwrap_err().reason.contains("200000 points"));
    }
}
