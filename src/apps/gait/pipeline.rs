//! The gait's hand-over to the bridge's pipeline: a walker's plan becomes a validated
//! [`Trajectory`] of every streamed axis, optionally led in by a jerk-limited move from
//! where the twin or controller stands. Owns that conversion only: streaming, the twin
//! and logging are the daemon's.

use super::rig::SlothRig;
use super::rule::RuleBroken;
use super::scenario::{Scenario, ScenarioError};
use super::smooth::smooth_plan;
use super::walker::{GaitPlan, WalkError, Walker};
use crate::trajectory::{
    PlanError, PlanSettings, RetimeError, Trajectory, TrajectoryError, plan_joint_moves, retime,
    validate,
};
use std::time::Duration;
use thiserror::Error;

/// Share of each axis' max acceleration the gait plans within: the plan's default
/// `accel_scale` (`PlanSettings`), so that the streamer's pause and stop ramps, sized for
/// that share, keep the total within the limit (docs/architecture.md).
pub const ACCEL_SHARE: f64 = 0.8;

#[derive(Debug, Error)]
pub enum GaitError {
    #[error(transparent)]
    Scenario(#[from] ScenarioError),
    #[error(transparent)]
    Forest(#[from] super::forest::ForestError),
    #[error(transparent)]
    Walk(#[from] WalkError),
    #[error("the gait's trajectory is refused: {0}")]
    Trajectory(#[from] TrajectoryError),
    #[error("re-timing the gait within its accelerations: {0}")]
    Retime(#[from] RetimeError),
    #[error("the move to the gait's first pose: {0}")]
    Approach(#[from] PlanError),
    #[error("scenario {scenario}: the gait stopped before its first frame{}", because(.reason))]
    Empty {
        scenario: String,
        reason: Option<RuleBroken>,
    },
}

/// `: reason`, or nothing when the walker gave none.
fn because(reason: &Option<RuleBroken>) -> String {
    reason
        .as_ref()
        .map(|r| format!(": {r}"))
        .unwrap_or_default()
}

/// The plan's samples with central-difference velocities (zero at both ends), validated
/// against the streamed rig.
pub fn trajectory_from_plan(sloth: &SlothRig, plan: &GaitPlan) -> Result<Trajectory, GaitError> {
    let (dof, len) = (plan.dof, plan.len());
    let dt = plan.period.as_secs_f64();
    let mut velocities = vec![0.0; plan.frames.len()];
    for k in 1..len.saturating_sub(1) {
        for axis in 0..dof {
            velocities[k * dof + axis] = (plan.frames[(k + 1) * dof + axis]
                - plan.frames[(k - 1) * dof + axis])
                / (2.0 * dt);
        }
    }
    let trajectory = Trajectory::new(
        sloth.streamed.name.clone(),
        sloth.streamed.joint_names().map(str::to_owned).collect(),
        plan.period,
        plan.frames.clone(),
        velocities,
    )?;
    validate(&trajectory, &sloth.streamed)?;
    Ok(trajectory)
}

/// Walks `scenario` at `period` and returns the plan with its validated trajectory.
pub fn plan_gait(
    sloth: &SlothRig,
    scenario: &Scenario,
    period: Duration,
) -> Result<(GaitPlan, Trajectory), GaitError> {
    let mut plan = Walker::new(sloth, scenario, period).plan()?;
    smooth_plan(&mut plan, sloth);
    if plan.is_empty() {
        return Err(GaitError::Empty {
            scenario: scenario.name.clone(),
            reason: plan.stop_reason,
        });
    }
    retime_plan(&mut plan, sloth)?;
    let trajectory = trajectory_from_plan(sloth, &plan)?;
    Ok((plan, trajectory))
}

/// A gait job for `run` and `serve`: a jerk-limited move from `start` (where the rig is)
/// to the gait's first pose, then the gait.
pub fn plan_gait_job(
    sloth: &SlothRig,
    scenario: &Scenario,
    start: &[f64],
    settings: &PlanSettings,
) -> Result<Trajectory, GaitError> {
    let (_, gait) = plan_gait(sloth, scenario, settings.period)?;
    let mut trajectory = plan_joint_moves(
        &sloth.streamed,
        start,
        &[gait.position(0).to_vec()],
        settings,
    )?;
    trajectory.append(&gait);
    validate(&trajectory, &sloth.streamed)?;
    Ok(trajectory)
}

/// Re-times the plan's samples along their own path so every axis stays within
/// `ACCEL_SHARE` of its max acceleration (`trajectory::retime`: never faster than planned,
/// so the same positions in the same order, slower where the motion was too abrupt), and
/// moves every frame number the plan carries (stances, touchdowns, cycles) onto the new
/// sample passing the same point of the path.
pub fn retime_plan(plan: &mut GaitPlan, sloth: &SlothRig) -> Result<(), GaitError> {
    let retimed = retime(&plan.frames, &sloth.streamed, plan.period, ACCEL_SHARE)?;
    let (old_len, dof, period) = (plan.len(), plan.dof, plan.period);
    let map = |frame: usize| {
        if frame >= old_len {
            // One past the last frame (the end of the last whole cycle): one past the new last.
            retimed.positions.len() / dof
        } else {
            retimed.sample_of(frame, period, dof)
        }
    };
    for stance in &mut plan.stances {
        stance.start = map(stance.start);
        stance.end = map(stance.end);
        stance.settled = map(stance.settled).clamp(stance.start, stance.end);
    }
    for (frame, _) in &mut plan.touchdowns {
        *frame = map(*frame);
    }
    for frame in &mut plan.cycle_starts {
        *frame = map(*frame);
    }
    plan.frames = retimed.positions;
    Ok(())
}
