//! Gradient descent on the squared distance from the tool to the target (seed 003's
//! method), position and orientation weighted together, projected onto the joint limits.
//! The simplest baseline; it converges slowly and says so through `NotConverged`.

use super::{IkError, IkSolution, IkSolver, Tolerance, verified};
use crate::rig::{JointAxis, JointKind, Pose, Rig};
use glam::DVec3;

pub struct GradientDescentSolver {
    rig: Rig,
    tolerance: Tolerance,
    max_iterations: u32,
    /// Metres per radian when orientation error is added to position error.
    orientation_weight_m: f64,
}

impl GradientDescentSolver {
    pub fn new(rig: Rig) -> Self {
        Self {
            rig,
            tolerance: Tolerance::default(),
            max_iterations: 2000,
            orientation_weight_m: 0.1,
        }
    }

    pub fn with_tolerance(mut self, tolerance: Tolerance) -> Self {
        self.tolerance = tolerance;
        self
    }

    pub fn with_max_iterations(mut self, max_iterations: u32) -> Self {
        self.max_iterations = max_iterations;
        self
    }

    /// Position error and rotation-vector error from the pose at `joints` to `target`.
    fn errors(
        &self,
        joints: &[f64],
        target: &Pose,
        axes: &mut Vec<JointAxis>,
    ) -> Result<(DVec3, DVec3), IkError> {
        let reached = Pose::from_affine(&self.rig.forward_with_axes(joints, axes)?);
        let rotation = target.orientation * reached.orientation.conjugate();
        let rotation = if rotation.w < 0.0 {
            -rotation
        } else {
            rotation
        };
        Ok((
            target.position - reached.position,
            rotation.to_scaled_axis(),
        ))
    }

    fn cost(&self, (position, orientation): (DVec3, DVec3)) -> f64 {
        position.length_squared() + (orientation * self.orientation_weight_m).length_squared()
    }
}

impl IkSolver for GradientDescentSolver {
    fn name(&self) -> &'static str {
        "gd"
    }

    fn rig(&self) -> &Rig {
        &self.rig
    }

    fn solve(&self, target: &Pose, seed: &[f64]) -> Result<IkSolution, IkError> {
        let target = self.checked_input(target, seed)?;
        let limits: Vec<_> = self.rig.joints.iter().map(|j| j.limits).collect();
        let mut joints: Vec<f64> = seed
            .iter()
            .zip(&limits)
            .map(|(q, l)| q.clamp(l.lower, l.upper))
            .collect();
        let mut axes = Vec::with_capacity(joints.len());
        let mut trial = joints.clone();
        let mut gradient = vec![0.0; joints.len()];
        let mut step = 1.0;
        let mut iterations = 0;
        let weight = self.orientation_weight_m.powi(2);
        let mut errors = self.errors(&joints, &target, &mut axes)?;
        while iterations < self.max_iterations {
            if errors.0.length() <= self.tolerance.position_m
                && errors.1.length() <= self.tolerance.orientation_rad
            {
                break;
            }
            iterations += 1;
            let tool = self.rig.forward(&joints)?.translation;
            for (g, axis) in gradient.iter_mut().zip(&axes) {
                let (linear, angular) = match axis.kind {
                    JointKind::Revolute => {
                        (axis.direction.cross(tool - axis.point), axis.direction)
                    }
                    JointKind::Prismatic => (axis.direction, DVec3::ZERO),
                };
                *g = linear.dot(errors.0) + weight * angular.dot(errors.1);
            }
            let current = self.cost(errors);
            let mut improved = false;
            while step > 1e-12 {
                for ((t, q), (g, l)) in trial
                    .iter_mut()
                    .zip(&joints)
                    .zip(gradient.iter().zip(&limits))
                {
                    *t = (q + step * g).clamp(l.lower, l.upper);
                }
                let candidate = self.errors(&trial, &target, &mut axes)?;
                if self.cost(candidate) < current {
                    std::mem::swap(&mut joints, &mut trial);
                    errors = candidate;
                    step *= 2.0;
                    improved = true;
                    break;
                }
                step *= 0.5;
            }
            if !improved {
                break;
            }
            self.rig.forward_with_axes(&joints, &mut axes)?;
        }
        verified(&self.rig, &target, joints, iterations, self.tolerance)
    }
}
