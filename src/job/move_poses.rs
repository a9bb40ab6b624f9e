//! `kind = "move_poses"`: tool poses reached by joint moves, each solved by inverse
//! kinematics nearest the configuration before it (the rig's current position for the
//! first), staying at the last. The tool's path between poses is whatever the joint moves
//! give; `move_linear` is the straight-line version.

use super::poses::{PoseSpec, check_poses, show_xyz};
use super::{JobContext, JobError, JobInvalid, PlanContext};
use crate::ik::{FabrikSolver, IkSolver};
use crate::trajectory::{Origins, Trajectory, plan_joint_moves_marked};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, PartialEq, Deserialize, Serialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct MovePoses {
    /// The tool poses, in order. At least one, at most 10000.
    pub poses: Vec<PoseSpec>,
}

impl MovePoses {
    pub fn validate(self, _: &JobContext) -> Result<Self, JobInvalid> {
        check_poses("job.poses", &self.poses)?;
        Ok(self)
    }

    /// The moves, each named by its pose (`job.poses[k]`).
    pub fn plan(&self, context: &PlanContext) -> Result<(Trajectory, Origins), JobError> {
        let poses = check_poses("job.poses", &self.poses)?;
        let solver = FabrikSolver::new(context.rig.clone())?;
        let mut seed = context.start.to_vec();
        let mut targets = Vec::with_capacity(poses.len());
        for (index, pose) in poses.iter().enumerate() {
            let solution = solver
                .solve(pose, &seed)
                .map_err(|error| JobError::Unreachable {
                    index,
                    what: format!("pose at {}", show_xyz(pose.position)),
                    error,
                })?;
            seed.clone_from(&solution.joints);
            targets.push(solution.joints);
        }
        let (trajectory, marks) =
            plan_joint_moves_marked(context.rig, context.start, &targets, context.settings)?;
        let mut origins = Origins::default();
        origins.push_marks(&marks, 0, |k| format!("the joint move to job.poses[{k}]"));
        Ok((trajectory, origins))
    }
}
