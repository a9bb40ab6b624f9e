//! `kind = "move_joints"`: joint moves through configurations (degrees; metres for
//! prismatic axes), staying at the last. Each move is the joint planner's: jerk-limited,
//! all axes arriving together, at rest at every target.

use super::{JobContext, JobError, JobInvalid, PlanContext, check_targets, to_si};
use crate::trajectory::{Trajectory, plan_joint_moves};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, PartialEq, Deserialize, Serialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct MoveJoints {
    /// One configuration per target, one value per axis: degrees, metres for prismatic
    /// axes. At least one, at most 10000.
    pub targets_deg: Vec<Vec<f64>>,
}

impl MoveJoints {
    pub fn validate(self, context: &JobContext) -> Result<Self, JobInvalid> {
        check_targets("job.targets_deg", &self.targets_deg, context.rig)?;
        Ok(self)
    }

    pub fn plan(&self, context: &PlanContext) -> Result<Trajectory, JobError> {
        let targets: Vec<Vec<f64>> = self
            .targets_deg
            .iter()
            .map(|t| to_si(t, context.rig))
            .collect();
        Ok(plan_joint_moves(
            context.rig,
            context.start,
            &targets,
            context.settings,
        )?)
    }
}
