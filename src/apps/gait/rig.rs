//! The sloth rig (`config/sloth.toml`): a body posed by six virtual axes and four limbs of
//! four bones, every chain in the kinematic core's joint format and every limb a core
//! [`Rig`]. Owns loading and validating the file, the streamed joint vector's layout and the
//! world-space geometry of a joint vector (feet, girdles, bone polylines). It must not plan
//! steps or solve IK: the walker does, on the chains built here.

use super::config::{GaitConfig, RawGait};
use crate::rig::{
    ConfigError, DofMismatch, Joint, RawJoint, RawOrigin, Rig, check_range, joints_from_raw,
    origin_from_raw,
};
use glam::{DAffine3, DVec3};
use serde::Deserialize;
use std::path::Path;

/// The wire protocol's axis count (`protocol::MAX_AXES`).
const MAX_STREAMED_AXES: usize = crate::protocol::MAX_AXES;

/// Fore or hind: which girdle a limb hangs from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Girdle {
    Fore,
    Hind,
}

/// The body side a limb is on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Side {
    Left,
    Right,
}

impl Side {
    /// +1 on the left (the body's +y), -1 on the right.
    pub fn sign(self) -> f64 {
        match self {
            Side::Left => 1.0,
            Side::Right => -1.0,
        }
    }
}

/// One limb: a chain from its girdle attachment (in the body frame) to the end of the
/// hand or foot; the claw reaches from there to the surface.
#[derive(Debug, Clone)]
pub struct Limb {
    pub name: String,
    pub girdle: Girdle,
    pub side: Side,
    pub claw_m: f64,
    /// The limb's joints on their own, based in the body frame (what limb IK solves).
    pub chain: Rig,
    /// Where this limb's joints start in the streamed joint vector.
    pub first_axis: usize,
    /// Sum of the bone lengths: the farthest the hand or foot gets from the girdle.
    pub reach_m: f64,
}

impl Limb {
    /// The girdle attachment (the first joint's origin) in the body frame.
    pub fn attachment(&self) -> DVec3 {
        self.chain.joints[0].origin.translation
    }

    pub fn axes(&self) -> std::ops::Range<usize> {
        self.first_axis..self.first_axis + self.chain.dof()
    }
}

/// The whole sloth: body axes, limbs, gait settings and the streamed rig.
#[derive(Debug, Clone)]
pub struct SlothRig {
    /// The body's virtual axes as a chain: its tool frame is the body frame.
    pub body: Rig,
    pub body_radius_m: f64,
    pub vertical_offset_m: f64,
    pub limbs: Vec<Limb>,
    pub gait: GaitConfig,
    /// Every streamed axis (body, then each limb's joints in file order): what the
    /// validator, the streamer, the twin and the log see.
    pub streamed: Rig,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawSloth {
    name: String,
    body: RawBody,
    gait: RawGait,
    limb: Vec<RawLimb>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawBody {
    radius_m: f64,
    vertical_offset_m: f64,
    joint: Vec<RawJoint>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawLimb {
    name: String,
    girdle: Girdle,
    side: Side,
    claw_m: f64,
    joint: Vec<RawJoint>,
    tool: RawOrigin,
}

const BODY_AXES: [&str; 6] = [
    "body_x",
    "body_y",
    "body_z",
    "body_yaw",
    "body_roll",
    "body_pitch",
];

impl SlothRig {
    /// Reads and validates a sloth description; errors name the file, the key and the value.
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        let text = crate::rig::shipped::read(path)?;
        Self::from_toml(&text, path)
    }

    pub fn from_toml(text: &str, file: &Path) -> Result<Self, ConfigError> {
        let raw: RawSloth = toml::from_str(text).map_err(|e| ConfigError::Parse {
            file: file.to_path_buf(),
            message: e.to_string().trim_end().to_string(),
        })?;
        let body_joints = joints_from_raw(file, "body.", &raw.body.joint)?;
        check_body_axes(file, &body_joints)?;
        let body_radius_m = check_range(file, "body.radius_m", raw.body.radius_m, 0.001, 1.0)?;
        let vertical_offset_m = check_range(
            file,
            "body.vertical_offset_m",
            raw.body.vertical_offset_m,
            0.0,
            2.0,
        )?;
        let mut limbs = Vec::with_capacity(raw.limb.len());
        let mut first_axis = body_joints.len();
        for (index, raw_limb) in raw.limb.iter().enumerate() {
            let limb = limb_from_raw(file, index, raw_limb, first_axis)?;
            first_axis += limb.chain.dof();
            limbs.push(limb);
        }
        check_limb_set(file, &limbs)?;
        let gait = raw.gait.validate(file, &limbs)?;
        let mut streamed_joints: Vec<Joint> = body_joints.clone();
        for limb in &limbs {
            streamed_joints.extend(limb.chain.joints.iter().cloned());
        }
        if streamed_joints.len() > MAX_STREAMED_AXES {
            return Err(ConfigError::invalid(
                file,
                "limb",
                streamed_joints.len(),
                &format!("body and limbs together have more than {MAX_STREAMED_AXES} axes"),
            ));
        }
        if let Some(name) = duplicate_name(&streamed_joints) {
            return Err(ConfigError::invalid(
                file,
                "limb.joint.name",
                name,
                "duplicate joint name",
            ));
        }
        let body = Rig {
            name: format!("{}_body", raw.name),
            base_frame: "world".into(),
            tool_frame: "body".into(),
            joints: body_joints,
            tool: DAffine3::IDENTITY,
            bodies: Vec::new(),
            allowed_pairs: Vec::new(),
        };
        let streamed = Rig {
            name: raw.name,
            base_frame: "world".into(),
            tool_frame: "body".into(),
            joints: streamed_joints,
            tool: DAffine3::IDENTITY,
            bodies: Vec::new(),
            allowed_pairs: Vec::new(),
        };
        Ok(Self {
            body,
            body_radius_m,
            vertical_offset_m,
            limbs,
            gait,
            streamed,
        })
    }

    pub fn dof(&self) -> usize {
        self.streamed.dof()
    }

    /// The body frame in the world for a streamed joint vector (of the rig's length).
    pub(crate) fn body_frame(&self, joints: &[f64]) -> DAffine3 {
        let body_dof = self.body.dof();
        self.body
            .joints
            .iter()
            .zip(&joints[..body_dof])
            .fold(DAffine3::IDENTITY, |frame, (joint, q)| {
                frame * joint.transform(*q)
            })
    }

    /// Every joint origin of `limb` and the end of its hand or foot, in the world.
    pub(crate) fn limb_points(&self, body: &DAffine3, limb: &Limb, joints: &[f64]) -> Vec<DVec3> {
        let mut frame = *body;
        let mut points = Vec::with_capacity(limb.chain.dof() + 1);
        for (joint, q) in limb.chain.joints.iter().zip(&joints[limb.axes()]) {
            frame *= joint.transform(*q);
            points.push(frame.translation);
        }
        points.push((frame * limb.chain.tool).translation);
        points
    }

    /// The end of `limb`'s hand or foot in the world (where the claw starts).
    pub(crate) fn limb_tip(&self, body: &DAffine3, limb: &Limb, joints: &[f64]) -> DVec3 {
        let frame = limb
            .chain
            .joints
            .iter()
            .zip(&joints[limb.axes()])
            .fold(*body, |frame, (joint, q)| frame * joint.transform(*q));
        (frame * limb.chain.tool).translation
    }

    /// The spine: from the hind girdle's middle to the fore girdle's, in the body frame.
    pub fn spine(&self) -> (DVec3, DVec3) {
        let middle = |girdle: Girdle| {
            let points: Vec<DVec3> = self
                .limbs
                .iter()
                .filter(|l| l.girdle == girdle)
                .map(Limb::attachment)
                .collect();
            points.iter().sum::<DVec3>() / points.len().max(1) as f64
        };
        (middle(Girdle::Hind), middle(Girdle::Fore))
    }

    /// World-space polylines of the sloth at `joints` (a streamed joint vector): the spine
    /// first, then each limb from its girdle to the end of its hand or foot (for a 3D view).
    pub fn bone_polylines(&self, joints: &[f64]) -> Result<Vec<Vec<DVec3>>, DofMismatch> {
        if joints.len() != self.dof() {
            return Err(DofMismatch {
                expected: self.dof(),
                given: joints.len(),
            });
        }
        let body = self.body_frame(joints);
        let (hind, fore) = self.spine();
        let mut lines = vec![vec![
            body.transform_point3(hind),
            body.transform_point3(fore),
        ]];
        for limb in &self.limbs {
            let mut line = vec![body.transform_point3(limb.attachment())];
            for point in self.limb_points(&body, limb, joints) {
                if line.last().is_none_or(|last| last.distance(point) > 1e-9) {
                    line.push(point);
                }
            }
            lines.push(line);
        }
        Ok(lines)
    }

    pub fn limb_index(&self, name: &str) -> Option<usize> {
        self.limbs.iter().position(|l| l.name == name)
    }
}

fn check_body_axes(file: &Path, joints: &[Joint]) -> Result<(), ConfigError> {
    let names: Vec<&str> = joints.iter().map(|j| j.name.as_str()).collect();
    if names != BODY_AXES {
        return Err(ConfigError::invalid(
            file,
            "body.joint",
            names,
            &format!(
                "the body's virtual axes must be {}, in that order",
                BODY_AXES.join(", ")
            ),
        ));
    }
    Ok(())
}

fn limb_from_raw(
    file: &Path,
    index: usize,
    raw: &RawLimb,
    first_axis: usize,
) -> Result<Limb, ConfigError> {
    let prefix = format!("limb[{index}].");
    if raw.name.trim().is_empty() {
        return Err(ConfigError::invalid(
            file,
            &format!("{prefix}name"),
            &raw.name,
            "must not be empty",
        ));
    }
    let claw_m = check_range(file, &format!("{prefix}claw_m"), raw.claw_m, 0.0, 0.2)?;
    let joints = joints_from_raw(file, &prefix, &raw.joint)?;
    let tool = origin_from_raw(file, &format!("{prefix}tool."), &raw.tool)?;
    let reach_m = joints
        .iter()
        .skip(1)
        .map(|j| j.origin.translation.length())
        .sum::<f64>()
        + tool.translation.length();
    if reach_m <= 0.0 {
        return Err(ConfigError::invalid(
            file,
            &format!("{prefix}joint"),
            reach_m,
            "the limb's bones have no length",
        ));
    }
    Ok(Limb {
        name: raw.name.clone(),
        girdle: raw.girdle,
        side: raw.side,
        claw_m,
        chain: Rig {
            name: raw.name.clone(),
            base_frame: "body".into(),
            tool_frame: format!("{}_tip", raw.name),
            joints,
            tool,
            bodies: Vec::new(),
            allowed_pairs: Vec::new(),
        },
        first_axis,
        reach_m,
    })
}

/// Four limbs, one per girdle and side, uniquely named.
fn check_limb_set(file: &Path, limbs: &[Limb]) -> Result<(), ConfigError> {
    if limbs.len() != 4 {
        return Err(ConfigError::invalid(
            file,
            "limb",
            limbs.len(),
            "a sloth has 4 limbs",
        ));
    }
    for (index, limb) in limbs.iter().enumerate() {
        let twin = limbs[..index]
            .iter()
            .any(|other| other.girdle == limb.girdle && other.side == limb.side);
        if twin || limbs[..index].iter().any(|other| other.name == limb.name) {
            return Err(ConfigError::invalid(
                file,
                &format!("limb[{index}].name"),
                &limb.name,
                "each girdle and side has exactly one limb, each with its own name",
            ));
        }
    }
    Ok(())
}

fn duplicate_name(joints: &[Joint]) -> Option<String> {
    let mut seen = std::collections::HashSet::new();
    joints
        .iter()
        .find(|j| !seen.insert(j.name.as_str()))
        .map(|j| j.name.clone())
}
