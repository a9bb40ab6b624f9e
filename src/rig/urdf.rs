//! URDF import: the serial chain from the root link to the tool frame (named, or the only
//! leaf a moving joint leads to) becomes a [`Rig`].
//! Fixed joints fold into the next joint's origin (or the tool transform). URDF carries no
//! acceleration limit before version 1.2; where it is absent we assume the axis reaches full
//! speed in [`DEFAULT_TIME_TO_FULL_SPEED_S`].

use super::config::origin_from_xyz_rpy;
use super::{ConfigError, Joint, JointKind, JointLimits, Rig, Verbatim};
use glam::{DAffine3, DVec3};
use std::path::Path;

pub const DEFAULT_TIME_TO_FULL_SPEED_S: f64 = 0.25;

/// Builds a rig from URDF text, ending at the only leaf frame reached through a moving
/// joint; `file` names the source in errors. See [`rig_from_urdf_to`].
pub fn rig_from_urdf(text: &str, file: &Path) -> Result<Rig, ConfigError> {
    rig_from_urdf_to(text, file, None)
}

/// Builds a rig from URDF text, from the root link to `tool_frame` (any link), or when it
/// is `None` to the one leaf link that a moving joint leads to: with several, the error
/// names them all, since guessing the tool would plan for the wrong point.
pub fn rig_from_urdf_to(
    text: &str,
    file: &Path,
    tool_frame: Option<&str>,
) -> Result<Rig, ConfigError> {
    let robot = urdf_rs::read_from_string(text).map_err(|e| ConfigError::Parse {
        file: file.to_path_buf(),
        message: e.to_string(),
    })?;
    let invalid = |key: &str, value: &str, reason: &str| {
        ConfigError::invalid(file, key, Verbatim(value), reason)
    };
    let is_child = |link: &str| robot.joints.iter().any(|j| j.child.link == link);
    let root = robot
        .links
        .iter()
        .find(|l| !is_child(&l.name))
        .ok_or_else(|| invalid("link", "(all)", "no root link: the links form a cycle"))?;
    let tip = match tool_frame {
        Some(frame) => frame.to_string(),
        None => only_tool_candidate(&robot, &root.name, file)?,
    };
    let path = path_to(&robot, &root.name, &tip).ok_or_else(|| {
        let reason = format!(
            "no link `{tip}` below the root link {}; its leaf frames: {}",
            root.name,
            tool_candidates(&robot, &root.name).join(", ")
        );
        ConfigError::invalid(file, "tool frame", Verbatim(&tip), &reason)
    })?;

    let mut joints = Vec::new();
    let mut pending = DAffine3::IDENTITY;
    for urdf_joint in path {
        let origin = pending
            * origin_from_xyz_rpy(
                DVec3::from_array(*urdf_joint.origin.xyz),
                DVec3::from_array(*urdf_joint.origin.rpy),
            );
        match moving_joint(urdf_joint, origin, file)? {
            // A fixed joint folds into the next joint's origin (or the tool transform).
            None => pending = origin,
            Some(joint) => {
                joints.push(joint);
                pending = DAffine3::IDENTITY;
            }
        }
    }
    if joints.is_empty() {
        return Err(invalid(
            "joint",
            "(none)",
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

/// One URDF joint of the chain as a rig joint, with its `origin` (fixed joints before it
/// folded in); `None` for a fixed joint. Limits, speed and axis are checked here, so the
/// error names the joint's key.
fn moving_joint(
    urdf_joint: &urdf_rs::Joint,
    origin: DAffine3,
    file: &Path,
) -> Result<Option<Joint>, ConfigError> {
    let invalid = |key: &str, value: &str, reason: &str| {
        ConfigError::invalid(file, key, Verbatim(value), reason)
    };
    let key = format!("joint[name={}]", urdf_joint.name);
    let kind = match urdf_joint.joint_type {
        urdf_rs::JointType::Fixed => return Ok(None),
        urdf_rs::JointType::Revolute => JointKind::Revolute,
        urdf_rs::JointType::Prismatic => JointKind::Prismatic,
        ref other => {
            return Err(invalid(
                &format!("{key}.type"),
                joint_type_name(other),
                "only revolute, prismatic and fixed joints are supported (a rig needs finite limits)",
            ));
        }
    };
    let limit = &urdf_joint.limit;
    if !(limit.lower.is_finite() && limit.upper.is_finite() && limit.lower < limit.upper) {
        return Err(invalid(
            &format!("{key}.limit"),
            &format!("lower={} upper={}", limit.lower, limit.upper),
            "needs finite lower < upper",
        ));
    }
    if !(limit.velocity.is_finite() && limit.velocity > 0.0) {
        return Err(invalid(
            &format!("{key}.limit.velocity"),
            &limit.velocity.to_string(),
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
            &format!("{key}.axis"),
            &format!("[{}, {}, {}]", axis.x, axis.y, axis.z),
            "must be a non-zero finite vector",
        ));
    }
    Ok(Some(Joint {
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
    }))
}

/// The joints from `root` down to the link `tip`, when `tip` lies below `root`.
pub(crate) fn path_to<'a>(
    robot: &'a urdf_rs::Robot,
    root: &str,
    tip: &str,
) -> Option<Vec<&'a urdf_rs::Joint>> {
    if root == tip {
        return Some(Vec::new());
    }
    robot
        .joints
        .iter()
        .filter(|j| j.parent.link == root)
        .find_map(|j| {
            let mut rest = path_to(robot, &j.child.link, tip)?;
            rest.insert(0, j);
            Some(rest)
        })
}

/// The leaf links below `root` that a revolute or prismatic joint leads to: the frames a
/// tool may be (a leaf hanging from the base by fixed joints only moves with nothing).
fn tool_candidates(robot: &urdf_rs::Robot, root: &str) -> Vec<String> {
    fn walk(robot: &urdf_rs::Robot, link: &str, moved: bool, out: &mut Vec<String>) {
        let children: Vec<&urdf_rs::Joint> = robot
            .joints
            .iter()
            .filter(|j| j.parent.link == link)
            .collect();
        if children.is_empty() && moved {
            out.push(link.to_string());
        }
        for joint in children {
            let moving = !matches!(joint.joint_type, urdf_rs::JointType::Fixed);
            walk(robot, &joint.child.link, moved || moving, out);
        }
    }
    let mut out = Vec::new();
    walk(robot, root, false, &mut out);
    out
}

fn only_tool_candidate(
    robot: &urdf_rs::Robot,
    root: &str,
    file: &Path,
) -> Result<String, ConfigError> {
    let mut candidates = tool_candidates(robot, root);
    match candidates.len() {
        1 => Ok(candidates.remove(0)),
        0 => Err(ConfigError::invalid(
            file,
            "joint",
            Verbatim("(none)"),
            "no revolute or prismatic joint leads to a leaf link",
        )),
        _ => Err(ConfigError::invalid(
            file,
            "tool frame",
            Verbatim(candidates.join(", ")),
            "several leaf frames could be the tool: choose one with --tool-frame NAME",
        )),
    }
}

/// A URDF joint type as the file writes it.
fn joint_type_name(kind: &urdf_rs::JointType) -> &'static str {
    match kind {
        urdf_rs::JointType::Revolute => "revolute",
        urdf_rs::JointType::Continuous => "continuous",
        urdf_rs::JointType::Prismatic => "prismatic",
        urdf_rs::JointType::Fixed => "fixed",
        urdf_rs::JointType::Floating => "floating",
        urdf_rs::JointType::Planar => "planar",
        urdf_rs::JointType::Spherical => "spherical",
    }
}
