//! URDF import: the serial chain from the root link to the deepest leaf becomes a [`Rig`].
//! Fixed joints fold into the next joint's origin (or the tool transform). URDF carries no
//! acceleration limit before version 1.2; where it is absent we assume the axis reaches full
//! speed in [`DEFAULT_TIME_TO_FULL_SPEED_S`].

use super::config::origin_from_xyz_rpy;
use super::{ConfigError, Joint, JointKind, JointLimits, Rig};
use glam::{DAffine3, DVec3};
use std::path::Path;

pub const DEFAULT_TIME_TO_FULL_SPEED_S: f64 = 0.25;

/// Builds a rig from URDF text; `file` names the source in errors.
pub fn rig_from_urdf(text: &str, file: &Path) -> Result<Rig, ConfigError> {
    let robot = urdf_rs::read_from_string(text).map_err(|e| ConfigError::Parse {
        file: file.to_path_buf(),
        message: e.to_string(),
    })?;
    let invalid = |key: String, value: String, reason: &str| ConfigError::Invalid {
        file: file.to_path_buf(),
        key,
        value,
        reason: reason.to_string(),
    };
    let is_child = |link: &str| robot.joints.iter().any(|j| j.child.link == link);
    let root = robot
        .links
        .iter()
        .find(|l| !is_child(&l.name))
        .ok_or_else(|| {
            invalid(
                "link".into(),
                "(all)".into(),
                "no root link: the links form a cycle",
            )
        })?;
    let path = deepest_path(&robot, &root.name);
    let tip = path
        .last()
        .map(|j| j.child.link.clone())
        .unwrap_or_else(|| root.name.clone());

    let mut joints = Vec::new();
    let mut pending = DAffine3::IDENTITY;
    for urdf_joint in path {
        let key = format!("joint[name={}]", urdf_joint.name);
        let origin = pending
            * origin_from_xyz_rpy(
                DVec3::from_array(*urdf_joint.origin.xyz),
                DVec3::from_array(*urdf_joint.origin.rpy),
            );
        let kind = match urdf_joint.joint_type {
            urdf_rs::JointType::Fixed => {
                pending = origin;
                continue;
            }
            urdf_rs::JointType::Revolute => JointKind::Revolute,
            urdf_rs::JointType::Prismatic => JointKind::Prismatic,
            ref other => {
                return Err(invalid(
                    format!("{key}.type"),
                    format!("{other:?}"),
                    "only revolute, prismatic and fixed joints are supported (a rig needs finite limits)",
                ));
            }
        };
        let limit = &urdf_joint.limit;
        if !(limit.lower.is_finite() && limit.upper.is_finite() && limit.lower < limit.upper) {
            return Err(invalid(
                format!("{key}.limit"),
                format!("lower={} upper={}", limit.lower, limit.upper),
                "needs finite lower < upper",
            ));
        }
        if !(limit.velocity.is_finite() && limit.velocity > 0.0) {
            return Err(invalid(
                format!("{key}.limit.velocity"),
                limit.velocity.to_string(),
                "must be positive",
            ));
        }
        let max_acceleration = if limit.acceleration.is_finite() && limit.acceleration > 0.0 {
            limit.acceleration
        } else {
            limit.velocity / DEFAULT_TIME_TO_FULL_SPEED_S
        };
        let axis = DVec3::from_array(*urdf_joint.axis.xyz);
        if !axis.is_finite() || axis.length() < 1e-9 {
            return Err(invalid(
                format!("{key}.axis"),
                format!("{axis:?}"),
                "must be a non-zero finite vector",
            ));
        }
        joints.push(Joint {
            name: urdf_joint.name.clone(),
            kind,
            origin,
            axis: axis.normalize(),
            limits: JointLimits {
                lower: limit.lower,
                upper: limit.upper,
                max_speed: limit.velocity,
                max_acceleration,
            },
        });
        pending = DAffine3::IDENTITY;
    }
    if joints.is_empty() {
        return Err(invalid(
            "joint".into(),
            "(none)".into(),
            "the chain has no revolute or prismatic joint",
        ));
    }
    Ok(Rig {
        name: robot.name.clone(),
        base_frame: root.name.clone(),
        tool_frame: tip,
        joints,
        tool: pending,
    })
}

/// The joints from `root` to the leaf reached through the most joints.
pub(crate) fn deepest_path<'a>(robot: &'a urdf_rs::Robot, root: &str) -> Vec<&'a urdf_rs::Joint> {
    robot
        .joints
        .iter()
        .filter(|j| j.parent.link == root)
        .map(|j| {
            let mut path = vec![j];
            path.extend(deepest_path(robot, &j.child.link));
            path
        })
        .max_by_key(|p| p.len())
        .unwrap_or_default()
}
