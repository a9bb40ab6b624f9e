//! Forward kinematics of a [`Rig`] in f64: the tool frame, and every joint axis in the base
//! frame (what Jacobian and CCD solvers need).

use super::{JointKind, Pose, Rig};
use glam::{DAffine3, DVec3};
use thiserror::Error;

#[derive(Debug, Clone, Copy, PartialEq, Eq, Error)]
#[error("rig has {expected} joints but {given} positions were given")]
pub struct DofMismatch {
    pub expected: usize,
    pub given: usize,
}

/// A joint's axis at some configuration, in the base frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct JointAxis {
    pub kind: JointKind,
    /// A point on the axis (the joint's origin).
    pub point: DVec3,
    /// Unit direction.
    pub direction: DVec3,
}

impl Rig {
    fn check_dof(&self, positions: &[f64]) -> Result<(), DofMismatch> {
        if positions.len() == self.dof() {
            Ok(())
        } else {
            Err(DofMismatch {
                expected: self.dof(),
                given: positions.len(),
            })
        }
    }

    /// The tool frame in the base frame at `positions`.
    pub fn forward(&self, positions: &[f64]) -> Result<DAffine3, DofMismatch> {
        self.check_dof(positions)?;
        let flange = self
            .joints
            .iter()
            .zip(positions)
            .fold(DAffine3::IDENTITY, |frame, (joint, q)| {
                frame * joint.transform(*q)
            });
        Ok(flange * self.tool)
    }

    pub fn tool_pose(&self, positions: &[f64]) -> Result<Pose, DofMismatch> {
        self.forward(positions).map(|t| Pose::from_affine(&t))
    }

    /// The tool frame, and each joint's axis written into `axes` (cleared first).
    pub fn forward_with_axes(
        &self,
        positions: &[f64],
        axes: &mut Vec<JointAxis>,
    ) -> Result<DAffine3, DofMismatch> {
        self.check_dof(positions)?;
        axes.clear();
        let mut frame = DAffine3::IDENTITY;
        for (joint, q) in self.joints.iter().zip(positions) {
            let at_origin = frame * joint.origin;
            axes.push(JointAxis {
                kind: joint.kind,
                point: at_origin.translation,
                direction: at_origin.transform_vector3(joint.axis),
            });
            frame *= joint.transform(*q);
        }
        Ok(frame * self.tool)
    }
}
