//! The exact solve of a spherical wrist: three revolute axes, the first and last parallel,
//! the middle one perpendicular to both, meeting in one point. Given the orientation the
//! wrist must add, it returns both wrist branches (flip and no flip) as principal angles;
//! adding turns within the limits is the caller's choice.

use glam::{DMat3, DVec3};

/// Below this |sin q5| the first and last axes line up and only their sum is determined.
const SINGULAR_SINE: f64 = 1e-9;

#[derive(Debug, Clone, PartialEq)]
pub(super) struct SphericalWrist {
    /// Columns: axis 4, axis 5, and their cross product, in the frame where the wrist
    /// factors as Rot(axis 4) Rot(axis 5) Rot(axis 6).
    basis: DMat3,
    /// +1 when axis 6 points like axis 4, -1 when opposite.
    last_axis_sign: f64,
    /// Fixed rotations of the wrist joints' origins, combined (O4 O5 O6).
    origins: DMat3,
    /// The tool's fixed rotation on the last link.
    tool: DMat3,
}

impl SphericalWrist {
    /// `origins` are the fixed rotations of joints 4, 5, 6; `axes` their axes in their own
    /// frames. Returns `None` unless axes 4 and 6 are parallel and axis 5 perpendicular.
    pub(super) fn new(origins: [DMat3; 3], axes: [DVec3; 3], tool: DMat3) -> Option<Self> {
        let [o4, o5, o6] = origins;
        let axis4 = (o5 * o6).transpose() * axes[0];
        let axis5 = o6.transpose() * axes[1];
        let axis6 = axes[2];
        let parallel = axis4.dot(axis6);
        if (parallel.abs() - 1.0).abs() > 1e-9 || axis4.dot(axis5).abs() > 1e-9 {
            return None;
        }
        Some(Self {
            basis: DMat3::from_cols(axis4, axis5, axis4.cross(axis5)),
            last_axis_sign: parallel.signum(),
            origins: o4 * o5 * o6,
            tool,
        })
    }

    /// Both wrist branches `[q4, q5, q6]` that turn `arm` (the rotation up to joint 3) into
    /// `target` (the tool orientation). In the singular case q4 is taken from `seed_q4`.
    pub(super) fn solve(&self, arm: DMat3, target: DMat3, seed_q4: f64) -> [[f64; 3]; 2] {
        let wrist = self.origins.transpose() * arm.transpose() * target * self.tool.transpose();
        let k = self.basis.transpose() * wrist * self.basis;
        // K = Rx(q4) Ry(q5) Rx(s q6): first column is (cos q5, sin q4 sin q5, -cos q4 sin q5).
        let (k10, k20) = (k.x_axis.y, k.x_axis.z);
        let first = if k10.hypot(k20) < SINGULAR_SINE {
            seed_q4
        } else {
            k10.atan2(-k20)
        };
        [first, first + std::f64::consts::PI].map(|q4| self.complete(&k, q4))
    }

    /// Given q4, the remaining Ry(q5) Rx(s q6) = Rx(-q4) K is read off exactly.
    fn complete(&self, k: &DMat3, q4: f64) -> [f64; 3] {
        let n = DMat3::from_rotation_x(-q4) * *k;
        let q5 = (-n.x_axis.z).atan2(n.x_axis.x);
        let q6 = (-n.z_axis.y).atan2(n.y_axis.y) * self.last_axis_sign;
        [q4, q5, q6]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn wrist_rotation(q: [f64; 3]) -> DMat3 {
        DMat3::from_rotation_x(q[0]) * DMat3::from_rotation_y(q[1]) * DMat3::from_rotation_x(q[2])
    }

    fn irb_style() -> SphericalWrist {
        SphericalWrist::new(
            [DMat3::IDENTITY; 3],
            [DVec3::X, DVec3::Y, DVec3::X],
            DMat3::IDENTITY,
        )
        .expect("the axes form a spherical wrist")
    }

    #[test]
    fn both_branches_reproduce_the_rotation() {
        let wrist = irb_style();
        let arm = DMat3::from_rotation_z(0.4) * DMat3::from_rotation_y(-0.2);
        let q = [0.7, -1.1, 2.5];
        let target = arm * wrist_rotation(q);
        for solution in wrist.solve(arm, target, 0.0) {
            let back = arm * wrist_rotation(solution);
            assert!(
                (back - target).abs_diff_eq(DMat3::ZERO, 1e-12),
                "{solution:?}"
            );
        }
    }

    #[test]
    fn singular_wrist_keeps_the_seed_on_axis_4() {
        let wrist = irb_style();
        let target = wrist_rotation([0.3, 0.0, 0.5]);
        let [solution, _] = wrist.solve(DMat3::IDENTITY, target, 1.0);
        assert_eq!(solution[0], 1.0);
        assert!(solution[1].abs() < 1e-12);
        assert!((solution[2] - (-0.2)).abs() < 1e-12, "{solution:?}");
    }

    #[test]
    fn refuses_a_wrist_whose_axes_do_not_form_one() {
        assert!(
            SphericalWrist::new(
                [DMat3::IDENTITY; 3],
                [DVec3::X, DVec3::X, DVec3::Y],
                DMat3::IDENTITY
            )
            .is_none()
        );
    }
}
