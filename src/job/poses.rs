//! Tool poses as jobs write them (`{ xyz_m = [x, y, z], quat_wxyz = [w, x, y, z] }`, in the
//! rig's base frame), shared by `move_linear` and `move_poses`. Owns their checks: finite,
//! within reach of any rig we drive, and a quaternion of unit norm (a near-unit one, as
//! written with a few decimals, is normalised).

use super::{JobInvalid, check_count};
use crate::rig::{Pose, Shown};
use glam::{DQuat, DVec3};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// How far a quaternion's norm may be from 1 and still be normalised: four written decimals
/// put it within about 1e-4; farther means it is not a rotation someone meant.
pub const QUATERNION_NORM_TOLERANCE: f64 = 1e-3;

/// Largest coordinate (m) of a pose: far beyond any rig we drive, so it only catches typos
/// (millimetres written as metres).
const MAX_COORDINATE_M: f64 = 10.0;

#[derive(Debug, Clone, Copy, PartialEq, Deserialize, Serialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct PoseSpec {
    /// The tool's position in the base frame (m).
    pub xyz_m: [f64; 3],
    /// The tool's orientation, w first; its norm must be within 1e-3 of 1.
    pub quat_wxyz: [f64; 4],
}

impl PoseSpec {
    /// The pose, its quaternion normalised; `key` names it in a refusal.
    pub fn to_pose(&self, key: &str) -> Result<Pose, JobInvalid> {
        for (i, v) in self.xyz_m.iter().enumerate() {
            if !(v.is_finite() && v.abs() <= MAX_COORDINATE_M) {
                return Err(JobInvalid::new(
                    format!("{key}.xyz_m[{i}]"),
                    v,
                    format!("must lie in [-{MAX_COORDINATE_M}, {MAX_COORDINATE_M}]"),
                ));
            }
        }
        let [w, x, y, z] = self.quat_wxyz;
        let q = DQuat::from_xyzw(x, y, z, w);
        let norm = q.length();
        if !(norm.is_finite() && (norm - 1.0).abs() <= QUATERNION_NORM_TOLERANCE) {
            return Err(JobInvalid::new(
                format!("{key}.quat_wxyz"),
                self.quat_wxyz,
                format!("norm {norm:.6} is not within {QUATERNION_NORM_TOLERANCE} of 1"),
            ));
        }
        Ok(Pose::new(DVec3::from_array(self.xyz_m), q / norm))
    }
}

/// The pose as a job writes it, every number as given (as TOML writes it):
/// `{ xyz_m = [0.9, 0.0, 0.45], quat_wxyz = [0.7071, 0.0, 0.7071, 0.0] }`.
impl std::fmt::Display for PoseSpec {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{{ xyz_m = {}, quat_wxyz = {} }}",
            self.xyz_m.shown(),
            self.quat_wxyz.shown()
        )
    }
}

/// Every pose of `key` checked: at least one, at most [`super::MAX_TARGETS`].
pub fn check_poses(key: &str, poses: &[PoseSpec]) -> Result<Vec<Pose>, JobInvalid> {
    check_count(key, poses.len())?;
    poses
        .iter()
        .enumerate()
        .map(|(i, p)| p.to_pose(&format!("{key}[{i}]")))
        .collect()
}

/// A position as a user reads it: `[0.450, 0.000, 0.570] m`.
pub fn show_xyz(p: DVec3) -> String {
    format!("[{:.3}, {:.3}, {:.3}] m", p.x, p.y, p.z)
}
