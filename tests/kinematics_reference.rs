//! Forward kinematics against 1,000 configurations whose tool0 poses were computed
//! independently from the ROS-Industrial URDF.

use crate::common;

use common::{irb120, reference_path, reference_rows};
use rigbridge::rig::{Rig, load_rig};

fn assert_matches_reference(rig: &Rig) {
    let rows = reference_rows();
    assert_eq!(rows.len(), 1000);
    let (mut worst_position, mut worst_rotation) = (0.0f64, 0.0f64);
    for row in &rows {
        let joints: Vec<f64> = row.joints_deg.iter().map(|d| d.to_radians()).collect();
        let pose = rig.tool_pose(&joints).unwrap();
        worst_position = worst_position.max(pose.position_error(&row.pose));
        worst_rotation = worst_rotation.max(pose.orientation_error(&row.pose));
    }
    assert!(
        worst_position <= 1e-9,
        "worst position error {worst_position} m"
    );
    assert!(
        worst_rotation <= 1e-9,
        "worst orientation error {worst_rotation} rad"
    );
}

#[test]
fn toml_rig_matches_reference_poses() {
    assert_matches_reference(&irb120());
}

#[test]
fn urdf_rig_matches_reference_poses() {
    let rig = load_rig(&reference_path("irb120_3_58.urdf")).unwrap();
    assert_eq!(rig.dof(), 6);
    assert_eq!(rig.tool_frame, "tool0");
    assert_eq!(rig.base_frame, "base_link");
    assert_matches_reference(&rig);
}

#[test]
fn toml_limits_are_the_manuals() {
    let rig = irb120();
    let expected = [
        (-165.0, 165.0, 250.0),
        (-110.0, 110.0, 250.0),
        (-110.0, 70.0, 250.0),
        (-160.0, 160.0, 320.0),
        (-120.0, 120.0, 320.0),
        (-400.0, 400.0, 420.0),
    ];
    for (joint, (lower, upper, speed)) in rig.joints.iter().zip(expected) {
        assert!(
            (joint.limits.lower.to_degrees() - lower).abs() < 1e-9,
            "{}",
            joint.name
        );
        assert!(
            (joint.limits.upper.to_degrees() - upper).abs() < 1e-9,
            "{}",
            joint.name
        );
        assert!(
            (joint.limits.max_speed.to_degrees() - speed).abs() < 1e-9,
            "{}",
            joint.name
        );
    }
}
