//! Inverse kinematics: one [`IkSolver`] trait and its solvers, one file each.
//!
//! Owns the question "which joint positions put the tool at this pose?", for one pose and
//! along a Cartesian line (`cartesian.rs`, whose joint path the `trajectory` stage below
//! times). Solvers read a [`Rig`](crate::rig::Rig) and never return a position outside its
//! limits: a target they cannot reach within limits is a typed [`IkError`], never a
//! clamped, different motion.

mod base_held;
mod cartesian;
mod ccd;
pub mod chain;
mod fabrik;
mod fabrik_position;
mod gradient;
mod wrist;

pub use base_held::BaseHeldSolver;
pub use cartesian::{CartesianError, line_joint_path, plan_cartesian, plan_cartesian_marked};
pub use ccd::CcdSolver;
pub use fabrik::{FabrikSolver, StructureError, StructureProblem};
pub use fabrik_position::PositionFabrikSolver;
pub use gradient::GradientDescentSolver;

use crate::rig::{DofMismatch, Pose, PoseError, Rig};
use thiserror::Error;

/// Tolerances every solver must meet before it calls a solution `ok`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Tolerance {
    pub position_m: f64,
    pub orientation_rad: f64,
}

impl Default for Tolerance {
    fn default() -> Self {
        Self {
            position_m: 1e-6,
            orientation_rad: 1e-6,
        }
    }
}

/// A solution, verified by forward kinematics against the target.
#[derive(Debug, Clone, PartialEq)]
pub struct IkSolution {
    pub joints: Vec<f64>,
    pub position_error_m: f64,
    pub orientation_error_rad: f64,
    pub iterations: u32,
}

#[derive(Debug, Clone, PartialEq, Error)]
pub enum IkError {
    #[error(
        "target is out of reach by {excess_m:.6} m (distance {distance_m:.6} m, reach {reach_m:.6} m)"
    )]
    OutOfReach {
        excess_m: f64,
        distance_m: f64,
        reach_m: f64,
    },
    #[error(
        "target is too close to axis 2 by {shortfall_m:.6} m (distance {distance_m:.6} m, the folded arm reaches no nearer than {min_reach_m:.6} m)"
    )]
    TooClose {
        shortfall_m: f64,
        distance_m: f64,
        min_reach_m: f64,
    },
    #[error("no solution within limits: axis {axis} ({joint}) blocks")]
    NoSolutionWithinLimits { axis: usize, joint: String },
    #[error(
        "not converged after {iterations} iterations: position error {position_error_m:.3e} m, orientation error {orientation_error_rad:.3e} rad"
    )]
    NotConverged {
        iterations: u32,
        position_error_m: f64,
        orientation_error_rad: f64,
    },
    #[error("invalid target: {0}")]
    InvalidTarget(#[from] PoseError),
    #[error("invalid seed: {0}")]
    InvalidSeed(String),
}

impl IkError {
    /// A short machine-readable name, used as the `status` column of the CSV tools.
    pub fn kind(&self) -> &'static str {
        match self {
            IkError::OutOfReach { .. } => "out_of_reach",
            IkError::TooClose { .. } => "too_close",
            IkError::NoSolutionWithinLimits { .. } => "no_solution_within_limits",
            IkError::NotConverged { .. } => "not_converged",
            IkError::InvalidTarget(_) => "invalid_target",
            IkError::InvalidSeed(_) => "invalid_seed",
        }
    }
}

impl From<DofMismatch> for IkError {
    fn from(e: DofMismatch) -> Self {
        IkError::InvalidSeed(e.to_string())
    }
}

/// An inverse-kinematics solver for one rig.
pub trait IkSolver {
    fn name(&self) -> &'static str;
    fn rig(&self) -> &Rig;
    /// Joint positions placing the tool at `target`, nearest `seed` where the solver can
    /// choose (the current configuration, so a smooth path gives smooth joint motion).
    fn solve(&self, target: &Pose, seed: &[f64]) -> Result<IkSolution, IkError>;

    /// The checks every solve opens with, in one place: the target finite with a unit
    /// orientation (returned normalised), then the seed of the rig's joint count and finite.
    fn checked_input(&self, target: &Pose, seed: &[f64]) -> Result<Pose, IkError> {
        let target = target.validated()?;
        check_seed(self.rig(), seed)?;
        Ok(target)
    }
}

/// Any solver is the EGM twin's controller kinematics in pose mode: the joints nearest the
/// reference before, within limits, verified by forward kinematics.
impl<T: IkSolver + Send> crate::device::egm::twin::PoseSolver for T {
    fn solve_pose(
        &self,
        pose: &Pose,
        seed: &[f64],
    ) -> Result<Vec<f64>, Box<dyn std::error::Error + Send + Sync>> {
        Ok(self.solve(pose, seed)?.joints)
    }
}

/// Checks a seed has the rig's joint count and finite values. Seeds outside the limits are
/// accepted: they only say where to search from.
fn check_seed(rig: &Rig, seed: &[f64]) -> Result<(), IkError> {
    if seed.len() != rig.dof() {
        return Err(IkError::InvalidSeed(format!(
            "rig {} has {} joints, seed has {} values",
            rig.name,
            rig.dof(),
            seed.len()
        )));
    }
    if let Some(bad) = seed.iter().find(|q| !q.is_finite()) {
        return Err(IkError::InvalidSeed(format!(
            "seed value {bad} is not finite"
        )));
    }
    Ok(())
}

/// The final gate of every solver: in limits as raw numbers, and the forward kinematics of
/// the answer within `tolerance` of the target.
pub(crate) fn verified(
    rig: &Rig,
    target: &Pose,
    joints: Vec<f64>,
    iterations: u32,
    tolerance: Tolerance,
) -> Result<IkSolution, IkError> {
    if let Some((index, _)) = rig.first_limit_violation(&joints) {
        return Err(IkError::NoSolutionWithinLimits {
            axis: index + 1,
            joint: rig.joints[index].name.clone(),
        });
    }
    let reached = rig.tool_pose(&joints)?;
    let position_error_m = reached.position_error(target);
    let orientation_error_rad = reached.orientation_error(target);
    if position_error_m <= tolerance.position_m
        && orientation_error_rad <= tolerance.orientation_rad
    {
        Ok(IkSolution {
            joints,
            position_error_m,
            orientation_error_rad,
            iterations,
        })
    } else {
        Err(IkError::NotConverged {
            iterations,
            position_error_m,
            orientation_error_rad,
        })
    }
}
