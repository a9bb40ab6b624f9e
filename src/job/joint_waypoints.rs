//! `kind = "joint_waypoints"`: joint moves through configurations (degrees; metres for
//! prismatic axes), then back to where the job started. `move_joints` is the same without
//! the return.

use super::{JobContext, JobError, JobInvalid, PlanContext, check_targets, to_si};
use crate::trajectory::{Origins, Trajectory, plan_joint_moves_marked};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, PartialEq, Deserialize, Serialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct JointWaypoints {
    /// One configuration per waypoint, one value per axis: degrees, metres for prismatic
    /// axes. At least one, at most 10000.
    pub waypoints_deg: Vec<Vec<f64>>,
}

impl JointWaypoints {
    pub fn validate(self, context: &JobContext) -> Result<Self, JobInvalid> {
        check_targets("job.waypoints_deg", &self.waypoints_deg, context.rig)?;
        Ok(self)
    }

    /// The moves, each named by its waypoint (`job.waypoints_deg[k]`), and the way back.
    pub fn plan(&self, context: &PlanContext) -> Result<(Trajectory, Origins), JobError> {
        let mut waypoints: Vec<Vec<f64>> = self
            .waypoints_deg
            .iter()
            .map(|w| to_si(w, context.rig))
            .collect();
        waypoints.push(context.start.to_vec());
        let (trajectory, marks) =
            plan_joint_moves_marked(context.rig, context.start, &waypoints, context.settings)?;
        let given = self.waypoints_deg.len();
        let mut origins = Origins::default();
        origins.push_marks(&marks, 0, |k| {
            if k < given {
                format!("the joint move to job.waypoints_deg[{k}]")
            } else {
                "the joint move back to where the job started".to_string()
            }
        });
        Ok((trajectory, origins))
    }
}
