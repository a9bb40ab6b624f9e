//! `kind = "move_joints"`: joint moves through configurations (degrees; metres for
//! prismatic axes), staying at the last. Each move is the joint planner's: jerk-limited,
//! all axes arriving together, at rest at every target.

use super::{JobContext, JobError, JobInvalid, PlanContext, check_targets, to_si};
use crate::trajectory::{Origins, Trajectory, plan_joint_moves_marked};
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

    /// The moves, and each named by its target (`job.targets_deg[k]`).
    pub fn plan(&self, context: &PlanContext) -> Result<(Trajectory, Origins), JobError> {
        let targets: Vec<Vec<f64>> = self
            .targets_deg
            .iter()
            .map(|t| to_si(t, context.rig))
            .collect();
        let (trajectory, marks) =
            plan_joint_moves_marked(context.rig, context.start, &targets, context.settings)?;
        let mut origins = Origins::default();
        origins.push_marks(&marks, 0, |k| {
            format!("the joint move to job.targets_deg[{k}]")
        });
        Ok((trajectory, origins))
    }
}
