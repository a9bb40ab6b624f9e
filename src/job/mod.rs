//! Jobs: sources of targets. A job turns its description into waypoints and hands them to
//! the planner; the result is one trajectory from the rig's current position back to rest.
//! A job never streams, and a target it cannot reach fails the whole job before motion.

use crate::daemon::config::JobConfig;
use crate::ik::{FabrikSolver, IkError, IkSolver, StructureError};
use crate::rig::{Pose, Rig};
use crate::trajectory::{PlanError, PlanSettings, Trajectory, plan_cartesian, plan_joint_moves};
use glam::{DQuat, DVec3};
use thiserror::Error;

#[derive(Debug, Error)]
pub enum JobError {
    #[error("job target {index} ({what}) cannot be reached: {error}")]
    Unreachable {
        index: usize,
        what: String,
        error: IkError,
    },
    #[error(transparent)]
    Plan(#[from] PlanError),
    #[error(transparent)]
    Structure(#[from] StructureError),
    #[error("a gait job needs the sloth rig: run it with a sloth file as the rig")]
    NeedsSloth,
    #[error("paint settings")]
    PaintConfig(#[from] crate::rig::ConfigError),
    #[error("paint job")]
    Paint(#[from] crate::task::paint::PaintError),
}

/// The points of a five-pointed star (as one closed stroke) on the wall plane x = `wall_x`,
/// tool z axis into the wall.
pub fn star_poses(wall_x: f64, centre_yz: [f64; 2], radius: f64, laps: u32) -> Vec<Pose> {
    let facing_wall = DQuat::from_rotation_y(std::f64::consts::FRAC_PI_2);
    let corner = |k: u32| {
        // Every second vertex of a pentagon draws the star in one stroke.
        let angle =
            std::f64::consts::FRAC_PI_2 + f64::from(2 * k % 5) * std::f64::consts::TAU / 5.0;
        Pose::new(
            DVec3::new(
                wall_x,
                centre_yz[0] + radius * angle.cos(),
                centre_yz[1] + radius * angle.sin(),
            ),
            facing_wall,
        )
    };
    (0..laps * 5)
        .map(|k| corner(k % 5))
        .chain(std::iter::once(corner(0)))
        .collect()
}

/// Plans the whole job from `start` (the controller's position) back to `start`.
pub fn plan_job(
    job: &JobConfig,
    rig: &Rig,
    start: &[f64],
    settings: &PlanSettings,
) -> Result<Trajectory, JobError> {
    match job {
        JobConfig::WallFigure {
            wall_x_m,
            centre_yz_m,
            radius_m,
            laps,
        } => {
            let solver = FabrikSolver::new(rig.clone())?;
            let poses = star_poses(*wall_x_m, *centre_yz_m, *radius_m, *laps);
            let first = solver
                .solve(&poses[0], start)
                .map_err(|error| JobError::Unreachable {
                    index: 0,
                    what: format!("star corner at {:?}", poses[0].position),
                    error,
                })?;
            let mut trajectory =
                plan_joint_moves(rig, start, std::slice::from_ref(&first.joints), settings)?;
            let figure = plan_cartesian(&solver, &first.joints, &poses[1..], settings)?;
            trajectory.append(&figure);
            let end = figure.position(figure.len() - 1).to_vec();
            trajectory.append(&plan_joint_moves(rig, &end, &[start.to_vec()], settings)?);
            Ok(trajectory)
        }
        JobConfig::Paint {
            walls,
            seed,
            paint_config,
        } => {
            let paint = crate::task::paint::load_paint_settings(paint_config)?;
            let (_, planned) =
                crate::task::paint::plan_room(&paint, *walls, *seed, start, settings)?;
            Ok(planned.trajectory)
        }
        JobConfig::JointWaypoints { waypoints_deg } => {
            let mut waypoints: Vec<Vec<f64>> = waypoints_deg
                .iter()
                .map(|w| w.iter().map(|d| d.to_radians()).collect())
                .collect();
            waypoints.push(start.to_vec());
            Ok(plan_joint_moves(rig, start, &waypoints, settings)?)
        }
        JobConfig::Gait { .. } => Err(JobError::NeedsSloth),
    }
}
