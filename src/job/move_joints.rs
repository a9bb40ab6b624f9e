//! `kind = "move_joints"`: joint moves through configurations (degrees; metres for
//! prismatic axes), staying at the last. Each move is the joint planner's: jerk-limited,
//! all axes arriving together, at rest at every target. With `plan_around = true`, a move
//! that would come closer to the cell than its margin goes around it instead
//! (`trajectory::free`); without it, a move the user wrote stays that move, and one that
//! collides is refused, with a hint naming the key.

use super::{JobContext, JobError, JobInvalid, PlanContext, check_targets, to_si};
use crate::trajectory::free::plan_joint_moves_around;
use crate::trajectory::{Origins, Trajectory, plan_joint_moves_marked};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// The key that asks for moves around the cell, as messages name it.
const PLAN_AROUND_KEY: &str = "job.plan_around";

#[derive(Debug, Clone, PartialEq, Deserialize, Serialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct MoveJoints {
    /// One configuration per target, one value per axis: degrees, metres for prismatic
    /// axes. At least one, at most 10000.
    pub targets_deg: Vec<Vec<f64>>,
    /// When a joint move to a target would come closer to the cell than its margin, plan
    /// a collision-free path around the obstacles instead (RRT-Connect, shortened and
    /// smoothed, timed within every limit), or refuse before motion when none is found
    /// within the budget (`[plan] free_max_samples`). False when absent: each move is
    /// the straight joint move written.
    #[serde(default, skip_serializing_if = "is_false")]
    pub plan_around: bool,
}

impl MoveJoints {
    pub fn validate(self, context: &JobContext) -> Result<Self, JobInvalid> {
        check_targets("job.targets_deg", &self.targets_deg, context.rig)?;
        Ok(self)
    }

    /// The moves, and each named by its target (`job.targets_deg[k]`).
    pub fn plan(&self, context: &PlanContext) -> Result<(Trajectory, Origins), JobError> {
        let targets: Vec<Vec<f64>> = self
            .targets_deg
            .iter()
            .map(|t| to_si(t, context.rig))
            .collect();
        if self.plan_around {
            return plan_around(context, &targets);
        }
        let (trajectory, marks) =
            plan_joint_moves_marked(context.rig, context.start, &targets, context.settings)?;
        let mut origins = Origins::default();
        origins.push_marks(&marks, 0, |k| {
            format!(
                "the joint move to job.targets_deg[{k}] ({PLAN_AROUND_KEY} = true would plan \
                 around the cell)"
            )
        });
        Ok((trajectory, origins))
    }
}

/// Left out of a job's description when false, so a job written before the key existed
/// is described as it was.
fn is_false(value: &bool) -> bool {
    !value
}

/// The moves with `plan_around = true`: each the joint move where it is clear, else a
/// free move around the cell.
fn plan_around(
    context: &PlanContext,
    targets: &[Vec<f64>],
) -> Result<(Trajectory, Origins), JobError> {
    let model = context.model.ok_or(JobError::NoCell {
        key: PLAN_AROUND_KEY,
    })?;
    let planned =
        plan_joint_moves_around(context.rig, model, context.start, targets, context.settings)
            .map_err(|refused| JobError::FreeMove {
                key: format!("job.targets_deg[{}]", refused.target),
                error: refused.error,
            })?;
    let mut origins = Origins::default();
    origins.push_marks(&planned.marks, 0, |k| {
        if planned.around[k] {
            format!("the free move around the cell to job.targets_deg[{k}]")
        } else {
            format!("the joint move to job.targets_deg[{k}]")
        }
    });
    Ok((planned.trajectory, origins))
}
