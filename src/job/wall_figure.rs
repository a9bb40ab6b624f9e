//! `kind = "wall_figure"`, the demo: a five-pointed star traced on the wall plane
//! x = `wall_x_m`, tool normal to the wall, then back to where the job started. Owns the
//! star's geometry and its keys; the straight strokes are the Cartesian planner's.

use super::{JobContext, JobError, JobInvalid, PlanContext, in_range};
use crate::ik::{FabrikSolver, IkSolver, plan_cartesian_marked};
use crate::rig::Pose;
use crate::trajectory::{Origins, Trajectory, plan_joint_moves};
use glam::{DQuat, DVec3};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// Most laps of the star: 1000 laps are hours of motion already.
const MAX_LAPS: u32 = 1000;

#[derive(Debug, Clone, PartialEq, Deserialize, Serialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct WallFigure {
    /// The wall plane's x (m), in [-2, 2].
    pub wall_x_m: f64,
    /// The star's centre on the wall, y and z (m), each in [-2, 2].
    pub centre_yz_m: [f64; 2],
    /// The star's radius (m), in [0.001, 1].
    pub radius_m: f64,
    /// How many times the star is traced, in [1, 1000].
    pub laps: u32,
}

impl WallFigure {
    pub fn validate(self, _: &JobContext) -> Result<Self, JobInvalid> {
        in_range("job.wall_x_m", self.wall_x_m, -2.0, 2.0)?;
        in_range("job.centre_yz_m[0]", self.centre_yz_m[0], -2.0, 2.0)?;
        in_range("job.centre_yz_m[1]", self.centre_yz_m[1], -2.0, 2.0)?;
        in_range("job.radius_m", self.radius_m, 0.001, 1.0)?;
        if !(1..=MAX_LAPS).contains(&self.laps) {
            return Err(JobInvalid::new(
                "job.laps",
                self.laps,
                format!("must lie in [1, {MAX_LAPS}]"),
            ));
        }
        Ok(self)
    }

    /// The star, each stroke named by its corner (five a lap, from 0), and the way back.
    pub fn plan(&self, context: &PlanContext) -> Result<(Trajectory, Origins), JobError> {
        let (rig, start, settings) = (context.rig, context.start, context.settings);
        let solver = FabrikSolver::new(rig.clone())?;
        let poses = star_poses(self.wall_x_m, self.centre_yz_m, self.radius_m, self.laps);
        let first = solver
            .solve(&poses[0], start)
            .map_err(|error| JobError::Unreachable {
                index: 0,
                what: format!(
                    "star corner at {}",
                    super::poses::show_xyz(poses[0].position)
                ),
                error,
            })?;
        let mut trajectory =
            plan_joint_moves(rig, start, std::slice::from_ref(&first.joints), settings)?;
        let mut origins = Origins::default();
        origins.push(
            trajectory.len() - 1,
            "the joint move to the star's corner 0",
        );
        let (figure, marks) = plan_cartesian_marked(
            &solver,
            &first.joints,
            &poses[1..],
            &settings.after(&trajectory),
        )?;
        origins.push_marks(&marks, trajectory.len() - 1, |k| {
            format!("the stroke to the star's corner {}", k + 1)
        });
        trajectory.append(&figure);
        let end = figure.position(figure.len() - 1).to_vec();
        let back = plan_joint_moves(rig, &end, &[start.to_vec()], &settings.after(&trajectory))?;
        trajectory.append(&back);
        origins.push(
            trajectory.len() - 1,
            "the joint move back to where the job started",
        );
        Ok((trajectory, origins))
    }
}

/// The points of a five-pointed star (as one closed stroke) on the wall plane x = `wall_x`,
/// tool z axis into the wall.
pub fn star_poses(wall_x: f64, centre_yz: [f64; 2], radius: f64, laps: u32) -> Vec<Pose> {
    let facing_wall = DQuat::from_rotation_y(std::f64::consts::FRAC_PI_2);
    let corner = |k: u64| {
        // Every second vertex of a pentagon draws the star in one stroke.
        let angle =
            std::f64::consts::FRAC_PI_2 + ((2 * k) % 5) as f64 * std::f64::consts::TAU / 5.0;
        Pose::new(
            DVec3::new(
                wall_x,
                centre_yz[0] + radius * angle.cos(),
                centre_yz[1] + radius * angle.sin(),
            ),
            facing_wall,
        )
    };
    // u64: five corners per lap cannot overflow for any u32 lap count.
    (0..u64::from(laps) * 5)
        .map(|k| corner(k % 5))
        .chain(std::iter::once(corner(0)))
        .collect()
}
