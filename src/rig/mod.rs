//! Rig models: joints, limits and forward kinematics, generic over the number of joints.
//!
//! Owns the description of a robot (what its joints are, where they sit, how far and how
//! fast they may move) and the forward kinematics built on it. It must not know about
//! solvers, trajectories or links: those stages read a [`Rig`], they never change it.

mod config;
mod fk;
pub mod geometry;
mod mesh;
mod pose;
pub mod shipped;
mod urdf;
mod urdf_out;

pub use config::{ConfigError, Shown, Verbatim, check_range, load_rig, load_rig_with_tool};
pub(crate) use config::{
    RawJoint, RawOrigin, joints_from_raw, origin_from_raw, origin_from_xyz_rpy,
};
pub use fk::{DofMismatch, JointAxis};
pub use geometry::{Collision, LinkBody, Shape};
pub use pose::{Pose, PoseError, UNIT_QUATERNION_TOLERANCE, rotation_angle_between};
pub use urdf::{MAX_URDF_BYTES, MAX_URDF_JOINTS, rig_from_urdf, rig_from_urdf_to};
pub(crate) use urdf::{UrdfTree, check_size as check_urdf_size};
pub use urdf_out::{
    FixedLink, HullMesh, UrdfExport, export, export_with_reach, generated_link_names,
    half_space_as_box, reach_bound_m, rig_to_urdf,
};

use glam::{DAffine3, DQuat, DVec3};

/// Joint values as a user reads them: `[a, b, ...]` (rad or m, as each axis is).
#[derive(Debug, Clone, PartialEq)]
pub struct JointList(pub Vec<f64>);

impl std::fmt::Display for JointList {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("[")?;
        for (i, q) in self.0.iter().enumerate() {
            if i > 0 {
                f.write_str(", ")?;
            }
            write!(f, "{q}")?;
        }
        f.write_str("]")
    }
}

/// How a joint moves its child link.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum JointKind {
    /// Rotation about the axis; positions in radians.
    Revolute,
    /// Translation along the axis; positions in metres.
    Prismatic,
}

impl JointKind {
    /// The unit people read and write this kind of axis' positions in (CSV files, configs,
    /// summaries, plots, the live view): degrees for a revolute axis, metres for a prismatic
    /// one. The library works in radians and metres; this is the one place that decides.
    pub fn unit(self) -> &'static str {
        match self {
            JointKind::Revolute => "deg",
            JointKind::Prismatic => "m",
        }
    }

    /// A position (or a speed, an acceleration, a tolerance) in SI units, in [`Self::unit`].
    pub fn to_user(self, si: f64) -> f64 {
        match self {
            JointKind::Revolute => si.to_degrees(),
            JointKind::Prismatic => si,
        }
    }

    /// A value given in [`Self::unit`], in SI units (radians or metres).
    pub fn from_user(self, value: f64) -> f64 {
        match self {
            JointKind::Revolute => value.to_radians(),
            JointKind::Prismatic => value,
        }
    }
}

/// Position, speed and acceleration bounds of one joint, in SI units (rad or m).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct JointLimits {
    pub lower: f64,
    pub upper: f64,
    pub max_speed: f64,
    pub max_acceleration: f64,
}

/// Relative slack on speed and acceleration checks, for float rounding only (1e-9 of the
/// limit): a plan made exactly at a limit must pass, nothing measurably above it may.
pub const LIMIT_SLACK: f64 = 1e-9;

impl JointLimits {
    pub fn contains(&self, position: f64) -> bool {
        position >= self.lower && position <= self.upper
    }

    /// A velocity within max speed.
    pub fn speed_ok(&self, velocity: f64) -> bool {
        velocity.abs() <= self.max_speed * (1.0 + LIMIT_SLACK)
    }

    /// A position step over `dt` seconds within max speed.
    pub fn step_ok(&self, step: f64, dt: f64) -> bool {
        step.abs() <= self.max_speed * dt * (1.0 + LIMIT_SLACK)
    }

    /// The second difference `p[k+1] - 2 p[k] + p[k-1]` of positions sampled every `dt`
    /// within max acceleration: for any motion whose acceleration stays within `a`, it is
    /// at most `a dt^2` (the integral of the acceleration against a triangle of area dt^2).
    pub fn second_difference_ok(&self, second_difference: f64, dt: f64) -> bool {
        second_difference.abs() <= self.max_acceleration * dt * dt * (1.0 + LIMIT_SLACK)
    }

    /// A velocity change over `dt` seconds within max acceleration.
    pub fn velocity_change_ok(&self, change: f64, dt: f64) -> bool {
        change.abs() <= self.max_acceleration * dt * (1.0 + LIMIT_SLACK)
    }
}

/// A joint value outside its position limits, as every refusal of one says it: the joint,
/// the value and the limits in the unit the user writes ([`JointKind::unit`]), e.g.
/// `joint_3 = 80.000 deg is outside its limits [-110.000, 70.000] deg`.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error(
    "{joint} = {:.3} {unit} is outside its limits [{:.3}, {:.3}] {unit}",
    kind.to_user(*value), kind.to_user(*lower), kind.to_user(*upper), unit = kind.unit()
)]
pub struct OutsideLimits {
    pub joint: String,
    /// SI units (radians or metres), as are the limits.
    pub value: f64,
    pub lower: f64,
    pub upper: f64,
    pub kind: JointKind,
}

/// One actuated joint: a fixed origin relative to its parent, then motion along `axis`.
#[derive(Debug, Clone, PartialEq)]
pub struct Joint {
    pub name: String,
    pub kind: JointKind,
    pub origin: DAffine3,
    /// Unit vector in the joint's own frame (after `origin`).
    pub axis: DVec3,
    pub limits: JointLimits,
}

impl Joint {
    /// `value` (SI units) refused when it is outside this joint's limits.
    pub fn check_limits(&self, value: f64) -> Result<(), OutsideLimits> {
        if self.limits.contains(value) {
            return Ok(());
        }
        Err(OutsideLimits {
            joint: self.name.clone(),
            value,
            lower: self.limits.lower,
            upper: self.limits.upper,
            kind: self.kind,
        })
    }

    /// The transform this joint adds at `position` (origin, then motion).
    pub fn transform(&self, position: f64) -> DAffine3 {
        match self.kind {
            JointKind::Revolute => {
                self.origin * DAffine3::from_quat(DQuat::from_axis_angle(self.axis, position))
            }
            JointKind::Prismatic => self.origin * DAffine3::from_translation(self.axis * position),
        }
    }
}

/// A serial chain from a base frame to a tool frame.
#[derive(Debug, Clone, PartialEq)]
pub struct Rig {
    pub name: String,
    pub base_frame: String,
    pub tool_frame: String,
    pub joints: Vec<Joint>,
    /// Fixed transform from the last joint's frame to the tool frame.
    pub tool: DAffine3,
    /// Collision geometry of the links (empty: the rig has no body to check).
    pub bodies: Vec<LinkBody>,
    /// Pairs of body names never checked against each other (adjacent links, pairs found
    /// by sampling never or always to touch).
    pub allowed_pairs: Vec<(String, String)>,
}

impl Rig {
    pub fn dof(&self) -> usize {
        self.joints.len()
    }

    pub fn joint_names(&self) -> impl Iterator<Item = &str> {
        self.joints.iter().map(|j| j.name.as_str())
    }

    /// The chain from joint `first` on, with the same tool: the arm of a rig that rides on
    /// extra axes (a mobile base, a lift). `None` when `first` leaves no joint.
    pub fn sub_chain(&self, first: usize) -> Option<Rig> {
        (first < self.dof()).then(|| Rig {
            name: format!("{}[{first}..]", self.name),
            base_frame: match first {
                0 => self.base_frame.clone(),
                _ => self.joints[first - 1].name.clone(),
            },
            tool_frame: self.tool_frame.clone(),
            joints: self.joints[first..].to_vec(),
            tool: self.tool,
            bodies: self.sub_chain_bodies(first),
            allowed_pairs: self
                .allowed_pairs
                .iter()
                .filter(|(a, b)| [a, b].iter().all(|name| self.body_on_or_after(name, first)))
                .cloned()
                .collect(),
        })
    }

    /// The bodies riding on joint `first` + 1 or later, with frames counted from there (the
    /// frame after joint `first` is the sub-chain's base, frame 0).
    fn sub_chain_bodies(&self, first: usize) -> Vec<LinkBody> {
        self.bodies
            .iter()
            .filter(|body| body.frame >= first)
            .map(|body| LinkBody {
                frame: body.frame - first,
                ..body.clone()
            })
            .collect()
    }

    fn body_on_or_after(&self, name: &str, first: usize) -> bool {
        self.bodies
            .iter()
            .any(|body| body.name == name && body.frame >= first)
    }

    /// The frame the first `leading.len()` joints place at `leading`: where a sub-chain
    /// starting after them is mounted.
    pub fn frame_after(&self, leading: &[f64]) -> DAffine3 {
        self.joints
            .iter()
            .zip(leading)
            .fold(DAffine3::IDENTITY, |frame, (joint, q)| {
                frame * joint.transform(*q)
            })
    }

    /// The first joint whose limit `positions` (SI units) breaks, as (index, the refusal).
    pub fn check_limits(&self, positions: &[f64]) -> Result<(), (usize, OutsideLimits)> {
        match self.first_limit_violation(positions) {
            Some((index, value)) => self.joints[index]
                .check_limits(value)
                .map_err(|outside| (index, outside)),
            None => Ok(()),
        }
    }

    /// The first joint whose limit `positions` breaks, as (index, position).
    pub fn first_limit_violation(&self, positions: &[f64]) -> Option<(usize, f64)> {
        self.joints
            .iter()
            .zip(positions)
            .enumerate()
            .find(|(_, (joint, q))| !joint.limits.contains(**q))
            .map(|(index, (_, q))| (index, *q))
    }
}
