//! Tool poses: a position in metres and a unit quaternion, both in the rig's base frame.

use glam::{DAffine3, DQuat, DVec3};
use thiserror::Error;

/// How far a quaternion's norm may stray from 1 before it is refused rather than normalised:
/// 1e-3 admits a unit quaternion written with 4 decimals (each component off by up to
/// 5e-5, the norm by at most 1e-4), while a scaled or mistyped one (a component dropped,
/// a digit wrong) is off by far more and is refused.
pub const UNIT_QUATERNION_TOLERANCE: f64 = 1e-3;

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    pub position: DVec3,
    pub orientation: DQuat,
}

#[derive(Debug, Clone, PartialEq, Error)]
pub enum PoseError {
    #[error("pose row has a missing or unparsable value")]
    Unparsable,
    #[error(
        "pose has a non-finite component: position ({}, {}, {}) m, quaternion (w {}, x {}, y {}, z {})",
        position.x, position.y, position.z, orientation.w, orientation.x, orientation.y, orientation.z
    )]
    NotFinite { position: DVec3, orientation: DQuat },
    #[error(
        "quaternion (w {}, x {}, y {}, z {}) has norm {norm:.6}, not 1 within {UNIT_QUATERNION_TOLERANCE}",
        orientation.w, orientation.x, orientation.y, orientation.z
    )]
    NotUnitQuaternion { orientation: DQuat, norm: f64 },
}

/// As messages show a pose: position in metres, quaternion w first.
impl std::fmt::Display for Pose {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let (p, q) = (self.position, self.orientation);
        write!(
            f,
            "position ({:.4}, {:.4}, {:.4}) m, quaternion (w {:.4}, x {:.4}, y {:.4}, z {:.4})",
            p.x, p.y, p.z, q.w, q.x, q.y, q.z
        )
    }
}

impl Pose {
    pub fn new(position: DVec3, orientation: DQuat) -> Self {
        Self {
            position,
            orientation,
        }
    }

    /// Checks the pose is usable as a target; renormalises a quaternion that is unit to
    /// within [`UNIT_QUATERNION_TOLERANCE`] so printed values round-trip exactly enough.
    pub fn validated(self) -> Result<Self, PoseError> {
        if !self.position.is_finite() || !self.orientation.is_finite() {
            return Err(PoseError::NotFinite {
                position: self.position,
                orientation: self.orientation,
            });
        }
        let norm = self.orientation.length();
        if (norm - 1.0).abs() > UNIT_QUATERNION_TOLERANCE {
            return Err(PoseError::NotUnitQuaternion {
                orientation: self.orientation,
                norm,
            });
        }
        Ok(Self {
            position: self.position,
            orientation: self.orientation / norm,
        })
    }

    pub fn from_affine(transform: &DAffine3) -> Self {
        Self {
            position: transform.translation,
            orientation: DQuat::from_mat3(&transform.matrix3),
        }
    }

    pub fn to_affine(&self) -> DAffine3 {
        DAffine3::from_rotation_translation(self.orientation, self.position)
    }

    pub fn position_error(&self, other: &Pose) -> f64 {
        self.position.distance(other.position)
    }

    pub fn orientation_error(&self, other: &Pose) -> f64 {
        rotation_angle_between(self.orientation, other.orientation)
    }
}

/// The angle of the rotation taking `a` to `b`, in [0, pi]. Uses atan2 so that angles near
/// zero keep full precision (acos of a dot product near 1 would not).
pub fn rotation_angle_between(a: DQuat, b: DQuat) -> f64 {
    let delta = a.conjugate() * b;
    let sine_half = delta.xyz().length();
    2.0 * sine_half.atan2(delta.w.abs())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rotation_angle_keeps_precision_near_zero() {
        let a = DQuat::from_rotation_z(0.3);
        let b = a * DQuat::from_rotation_x(1e-10);
        let angle = rotation_angle_between(a, b);
        assert!((angle - 1e-10).abs() < 1e-16, "{angle}");
    }

    #[test]
    fn rotation_angle_treats_q_and_minus_q_alike() {
        let a = DQuat::from_rotation_y(0.5);
        assert!(rotation_angle_between(a, -a) < 1e-15);
    }

    #[test]
    fn a_nearly_unit_quaternion_is_normalised_and_a_far_one_refused() {
        // 4 decimals of a unit quaternion: norm about 1 + 2e-5.
        let rounded = Pose::new(
            DVec3::ZERO,
            DQuat::from_xyzw(0.1830, 0.1830, 0.6830, 0.6830),
        );
        let fixed = rounded.validated().expect("within 1e-3 of unit");
        assert!((fixed.orientation.length() - 1.0).abs() < 1e-12);
        let off = Pose::new(DVec3::ZERO, DQuat::from_xyzw(0.0, 0.0, 0.0, 1.002));
        let refused = off.validated().unwrap_err().to_string();
        assert!(refused.contains("norm 1.002000"), "{refused}");
        assert!(!refused.contains("DQuat"), "{refused}");
    }

    #[test]
    fn refuses_non_unit_and_non_finite() {
        let bad = Pose::new(DVec3::ZERO, DQuat::from_xyzw(0.0, 0.0, 0.0, 2.0));
        assert!(matches!(
            bad.validated(),
            Err(PoseError::NotUnitQuaternion { .. })
        ));
        let nan = Pose::new(DVec3::new(f64::NAN, 0.0, 0.0), DQuat::IDENTITY);
        assert!(matches!(nan.validated(), Err(PoseError::NotFinite { .. })));
    }
}
