//! The body's pose from the feet (seed 004): rotation from the mean of the two hind-to-fore
//! directions (formula 6), position at the mean of the four feet minus up x the vertical
//! offset (formula 7). Owns that rule and its conversion to the six virtual body axes; it
//! must not move feet.

use super::rig::{Girdle, Side, SlothRig};
use glam::{DAffine3, DMat3, DQuat, DVec3, EulerRot};

/// The world's up: the sloth hangs under its branches, so its belly faces this way.
pub const WORLD_UP: DVec3 = DVec3::Z;

/// The body frame (x forward, y left, z toward the supports) for feet at `feet` (one point
/// per limb, in the rig's limb order). `toward_supports` is the side the supports are on:
/// the world's up under a branch, toward the trunk's axis on a trunk; the body's z is it
/// made square to the forward direction.
pub fn body_from_feet(sloth: &SlothRig, feet: &[DVec3], toward_supports: DVec3) -> DAffine3 {
    let foot = |girdle: Girdle, side: Side| {
        sloth
            .limbs
            .iter()
            .position(|l| l.girdle == girdle && l.side == side)
            .map_or(DVec3::ZERO, |i| feet[i])
    };
    let right = foot(Girdle::Fore, Side::Right) - foot(Girdle::Hind, Side::Right);
    let left = foot(Girdle::Fore, Side::Left) - foot(Girdle::Hind, Side::Left);
    let forward = (right.normalize_or_zero() + left.normalize_or_zero()).normalize_or(DVec3::X);
    let up = (toward_supports - forward * forward.dot(toward_supports)).normalize_or(DVec3::Z);
    let side = up.cross(forward);
    let mean = feet.iter().sum::<DVec3>() / feet.len() as f64;
    DAffine3::from_mat3_translation(
        DMat3::from_cols(forward, side, up),
        mean - up * sloth.vertical_offset_m,
    )
}

/// The six virtual body axes (x, y, z, yaw, roll, pitch: the rig's chain order) of a body
/// frame; yaw is taken within half a turn of `previous_yaw` so that it never jumps by a
/// turn. Roll before pitch: a body heading straight up a trunk (pitch -90 deg) keeps a
/// well-defined yaw (which side of the trunk it faces) and roll (how far it leans sideways).
pub fn body_axes(frame: &DAffine3, previous_yaw: f64) -> [f64; 6] {
    let rotation = DQuat::from_mat3(&frame.matrix3);
    let (yaw, roll, pitch) = rotation.to_euler(EulerRot::ZXY);
    let turns = ((previous_yaw - yaw) / std::f64::consts::TAU).round();
    let p = frame.translation;
    [
        p.x,
        p.y,
        p.z,
        yaw + turns * std::f64::consts::TAU,
        roll,
        pitch,
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Rebuilds the rotation the rig's chain turns through: yaw, then roll, then pitch.
    fn chain_rotation(axes: &[f64; 6]) -> DMat3 {
        DMat3::from_rotation_z(axes[3])
            * DMat3::from_rotation_x(axes[4])
            * DMat3::from_rotation_y(axes[5])
    }

    #[test]
    fn a_body_heading_up_a_trunk_keeps_its_facing_in_yaw() {
        // Head up, belly toward a trunk on its +y side: forward +z, up +y, left = up x forward.
        let (forward, up) = (DVec3::Z, DVec3::Y);
        let frame = DAffine3::from_mat3_translation(
            DMat3::from_cols(forward, up.cross(forward), up),
            DVec3::new(0.1, -0.2, 0.3),
        );
        let axes = body_axes(&frame, 0.0);
        // Pitched -90 deg, the body's z is (-cos yaw, -sin yaw, 0): +y at yaw -90 deg.
        assert!(
            (axes[3] + std::f64::consts::FRAC_PI_2).abs() < 1e-9,
            "{axes:?}"
        );
        assert!(axes[4].abs() < 1e-9, "no roll: {axes:?}");
        assert!(
            (axes[5] + std::f64::consts::FRAC_PI_2).abs() < 1e-9,
            "{axes:?}"
        );
        assert!(chain_rotation(&axes).abs_diff_eq(frame.matrix3, 1e-9));
        assert_eq!(&axes[..3], &[0.1, -0.2, 0.3]);
    }

    #[test]
    fn a_level_body_turned_and_pitched_round_trips() {
        let forward = DVec3::new(
            0.3f64.cos() * 0.2f64.cos(),
            0.3f64.sin() * 0.2f64.cos(),
            0.2f64.sin(),
        );
        let up = (WORLD_UP - forward * forward.dot(WORLD_UP)).normalize();
        let frame = DAffine3::from_mat3_translation(
            DMat3::from_cols(forward, up.cross(forward), up),
            DVec3::ZERO,
        );
        let axes = body_axes(&frame, 0.0);
        assert!(
            axes[4].abs() < 1e-9,
            "a body under branches never rolls: {axes:?}"
        );
        assert!(chain_rotation(&axes).abs_diff_eq(frame.matrix3, 1e-9));
    }
}
