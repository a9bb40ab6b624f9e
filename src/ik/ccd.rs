//! Cyclic coordinate descent on the rig's joints, the sloth thesis's limb solver: from the
//! last joint to the first, each joint takes the angle that best aligns the tool with the
//! target (position and orientation together), clamped to its limits as it goes.
//! Kept for comparison and for short limbs; it makes no promise of nearest-branch answers.

use super::{IkError, IkSolution, IkSolver, Tolerance, verified};
use crate::rig::{JointAxis, JointKind, Pose, Rig};
use glam::DVec3;

pub struct CcdSolver {
    rig: Rig,
    tolerance: Tolerance,
    max_iterations: u32,
    /// Half-length of the tool's frame markers: weighs orientation against position.
    frame_size_m: f64,
    /// Solve for the tool's position only (a limb placing a foot), ignoring orientation.
    position_only: bool,
}

impl CcdSolver {
    pub fn new(rig: Rig) -> Self {
        Self {
            rig,
            tolerance: Tolerance::default(),
            max_iterations: 500,
            frame_size_m: 0.1,
            position_only: false,
        }
    }

    /// Places the tool origin only; the target's orientation is ignored (any is accepted).
    pub fn position_only(mut self) -> Self {
        self.position_only = true;
        self
    }

    /// How many of the markers take part: the origin alone when only position counts.
    fn marker_count(&self) -> usize {
        if self.position_only { 1 } else { 3 }
    }

    pub fn with_tolerance(mut self, tolerance: Tolerance) -> Self {
        self.tolerance = tolerance;
        self
    }

    pub fn with_max_iterations(mut self, max_iterations: u32) -> Self {
        self.max_iterations = max_iterations;
        self
    }

    /// The tool origin and two points along its x and y axes: aligning these three with
    /// the target's aligns position and orientation at once.
    fn markers(&self, pose: &Pose) -> [DVec3; 3] {
        let s = self.frame_size_m;
        [
            pose.position,
            pose.position + pose.orientation * DVec3::X * s,
            pose.position + pose.orientation * DVec3::Y * s,
        ]
    }

    /// Moves `markers` with a change `delta` of the joint on `axis`.
    fn follow(axis: &JointAxis, delta: f64, markers: &mut [DVec3; 3]) {
        match axis.kind {
            JointKind::Revolute => {
                let turn = glam::DQuat::from_axis_angle(axis.direction, delta);
                for marker in markers.iter_mut() {
                    *marker = axis.point + turn * (*marker - axis.point);
                }
            }
            JointKind::Prismatic => {
                for marker in markers.iter_mut() {
                    *marker += axis.direction * delta;
                }
            }
        }
    }

    /// The change of one joint that best moves `current` markers onto `wanted` ones.
    fn best_step(axis: &JointAxis, current: &[DVec3], wanted: &[DVec3]) -> f64 {
        match axis.kind {
            JointKind::Revolute => {
                let (mut sine, mut cosine) = (0.0, 0.0);
                for (c, w) in current.iter().zip(wanted) {
                    let from = (*c - axis.point).reject_from_normalized(axis.direction);
                    let to = (*w - axis.point).reject_from_normalized(axis.direction);
                    sine += axis.direction.dot(from.cross(to));
                    cosine += from.dot(to);
                }
                sine.atan2(cosine)
            }
            JointKind::Prismatic => {
                let shift: DVec3 = current.iter().zip(wanted).map(|(c, w)| *w - *c).sum();
                shift.dot(axis.direction) / current.len() as f64
            }
        }
    }
}

impl IkSolver for CcdSolver {
    fn name(&self) -> &'static str {
        "ccd"
    }

    fn rig(&self) -> &Rig {
        &self.rig
    }

    fn solve(&self, target: &Pose, seed: &[f64]) -> Result<IkSolution, IkError> {
        let target = self.checked_input(target, seed)?;
        let used = self.marker_count();
        let wanted = self.markers(&target);
        let tolerance = if self.position_only {
            Tolerance {
                orientation_rad: std::f64::consts::PI,
                ..self.tolerance
            }
        } else {
            self.tolerance
        };
        let mut joints: Vec<f64> = seed
            .iter()
            .zip(&self.rig.joints)
            .map(|(q, j)| q.clamp(j.limits.lower, j.limits.upper))
            .collect();
        let mut axes = Vec::with_capacity(joints.len());
        let mut iterations = 0;
        while iterations < self.max_iterations {
            let tool = self.rig.forward_with_axes(&joints, &mut axes)?;
            let reached = Pose::from_affine(&tool);
            if reached.position_error(&target) <= tolerance.position_m
                && reached.orientation_error(&target) <= tolerance.orientation_rad
            {
                break;
            }
            iterations += 1;
            // Turning joint `index` moves only what lies beyond it: the axes of the joints
            // before it stay put, so one forward pass per sweep serves the whole sweep, the
            // markers following each joint's change.
            let mut current = self.markers(&reached);
            for index in (0..joints.len()).rev() {
                let step = Self::best_step(&axes[index], &current[..used], &wanted[..used]);
                let limits = self.rig.joints[index].limits;
                let moved = (joints[index] + step).clamp(limits.lower, limits.upper);
                Self::follow(&axes[index], moved - joints[index], &mut current);
                joints[index] = moved;
            }
        }
        verified(&self.rig, &target, joints, iterations, tolerance)
    }
}
