//! A solver for an arm riding on extra axes (a mobile base, a lift): the leading axes are
//! held where the seed puts them and the six-axis arm after them is solved by the FABRIK
//! planner for the tool pose expressed in the arm's mount frame.
//!
//! Owns only the change of frame; choosing where the extra axes go is the caller's job (a
//! coverage planner picks base stations). Must not move the held axes: a target the arm
//! cannot reach from there is an [`IkError`], never a base move.

use super::{
    FabrikSolver, IkError, IkSolution, IkSolver, StructureError, StructureProblem, verified,
};
use crate::rig::{Pose, Rig};

pub struct BaseHeldSolver {
    rig: Rig,
    held: usize,
    arm: FabrikSolver,
}

impl BaseHeldSolver {
    /// `held` leading axes of `rig` are held; the rest must suit [`FabrikSolver`].
    pub fn new(rig: Rig, held: usize) -> Result<Self, StructureError> {
        let arm_rig = rig.sub_chain(held).ok_or_else(|| StructureError {
            rig: rig.name.clone(),
            reason: StructureProblem::NoArmLeft {
                held,
                dof: rig.dof(),
            },
        })?;
        let arm = FabrikSolver::new(arm_rig)?;
        Ok(Self { rig, held, arm })
    }

    /// How many leading axes are held.
    pub fn held(&self) -> usize {
        self.held
    }
}

impl IkSolver for BaseHeldSolver {
    fn name(&self) -> &'static str {
        "fabrik_base_held"
    }

    fn rig(&self) -> &Rig {
        &self.rig
    }

    fn solve(&self, target: &Pose, seed: &[f64]) -> Result<IkSolution, IkError> {
        let target = self.checked_input(target, seed)?;
        let (leading, arm_seed) = seed.split_at(self.held);
        let mount = self.rig.frame_after(leading);
        let local = Pose::from_affine(&(mount.inverse() * target.to_affine()));
        let arm = self.arm.solve(&local, arm_seed)?;
        let joints: Vec<f64> = leading.iter().chain(&arm.joints).copied().collect();
        verified(
            &self.rig,
            &target,
            joints,
            arm.iterations,
            super::Tolerance::default(),
        )
    }
}
