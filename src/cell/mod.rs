//! The workcell (issue 27): the robot's mounting pose, the static objects around it, the
//! tool on its flange, and the one collision model every check in the project uses.
//!
//! Owns the cell file (`cell.toml`, or a `[cell]` section of the run settings) and the
//! checker: [`CollisionModel`] places the rig's link bodies, the tool and the objects at a
//! configuration and measures the closest checked pair with parry3d (f64). It reads
//! [`crate::rig`] and nothing above it: jobs, the streamer, the twin and the views call it,
//! it never calls them.

mod allowed;
mod bound;
mod file;
mod model;
mod parry;
mod parts;
mod path;
mod targets;
pub mod urdf;

pub use allowed::{
    AllowedPair, DEFAULT_SAMPLES, NEVER_CLEARANCE_M, Reason, allowed_pairs_toml,
    find_allowed_pairs, replace_allowed_pairs,
};
pub(crate) use file::{RawCell, cell_from_raw};
pub use file::{cell_from_toml, load_cell};
pub use model::{BodyId, Clearance, CollisionModel, NO_BODY, PlacedShape, Scratch, Status};
pub use parts::{Gripper, Part};
pub use path::{PathClearance, PathCollision};
pub use targets::{GridNames, NamedTarget, Spot, Targets};

use crate::rig::{Collision, ConfigError, Rig, Shape};
use glam::{DAffine3, DVec3};
use thiserror::Error;

/// The clearance below which a motion is refused unless a cell says otherwise: 10 mm, the
/// issue's default, room for the difference between our envelopes and the real arm.
pub const DEFAULT_MARGIN_M: f64 = 0.01;

/// The name of the built-in cell's floor.
pub const FLOOR: &str = "floor";

/// A robot cell: where the robot stands, what stands around it, what it holds.
#[derive(Debug, Clone, PartialEq)]
pub struct Cell {
    /// The robot's base frame in the cell frame.
    pub mount: DAffine3,
    /// Static solids, in the cell frame.
    pub objects: Vec<CellObject>,
    pub tool: Option<Tool>,
    /// Clearance below which a motion is refused (metres).
    pub margin_m: f64,
    /// Pairs of body names never checked, besides the rig's own.
    pub allowed_pairs: Vec<(String, String)>,
    /// Named targets and grids of them, for programs (`[[target]]`, `[[target_grid]]`).
    pub targets: Targets,
    /// The parts the twin's gripper picks and places (`[[part]]`), and the gripper
    /// (`[gripper]`, defaults when absent).
    pub parts: Vec<Part>,
    pub gripper: Gripper,
}

/// A named static solid of the cell.
#[derive(Debug, Clone, PartialEq)]
pub struct CellObject {
    pub name: String,
    /// The solid's frame in the cell frame.
    pub pose: DAffine3,
    pub shape: Shape,
}

/// What the flange carries: its solids (in the tool0 frame) and its TCP.
#[derive(Debug, Clone, PartialEq)]
pub struct Tool {
    pub name: String,
    /// Solids in the rig's tool frame (tool0 for the IRB 120).
    pub bodies: Vec<Collision>,
    /// The tool centre point in the rig's tool frame.
    pub tcp: DAffine3,
}

impl Cell {
    /// The IRB 120 (or any rig) standing on its floor: a half-space below the base frame's
    /// z = 0, no tool, the default margin.
    pub fn builtin() -> Cell {
        Cell {
            mount: DAffine3::IDENTITY,
            objects: vec![CellObject {
                name: FLOOR.to_string(),
                pose: DAffine3::IDENTITY,
                shape: Shape::HalfSpace { normal: DVec3::Z },
            }],
            tool: None,
            margin_m: DEFAULT_MARGIN_M,
            allowed_pairs: Vec::new(),
            targets: Targets::default(),
            parts: Vec::new(),
            gripper: Gripper::default(),
        }
    }

    /// `rig` ending at the tool's TCP (its tool frame named after the tool), so IK and
    /// every Cartesian job work at the TCP; `rig` itself keeps tool0. Without a tool, `rig`
    /// as it is.
    pub fn rig_at_tcp(&self, rig: &Rig) -> Rig {
        let mut at_tcp = rig.clone();
        // A rig already at the TCP stays there: applying the TCP twice would move it.
        if let Some(tool) = self
            .tool
            .as_ref()
            .filter(|tool| rig.tool_frame != tool.name)
        {
            at_tcp.tool = rig.tool * tool.tcp;
            at_tcp.tool_frame = tool.name.clone();
        }
        at_tcp
    }
}

/// A cell that cannot be loaded, or cannot be checked with the rig it is given.
#[derive(Debug, Error)]
pub enum CellError {
    /// The cell file (or section) itself: names the file, the key and the value.
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error("body `{name}` appears twice ({first} and {second}): every body needs its own name")]
    DuplicateName {
        name: String,
        first: &'static str,
        second: &'static str,
    },
    #[error(
        "{source_name} allowed_pairs[{index}]: `{name}` names no body of the rig, the tool or \
         the cell (bodies: {known})"
    )]
    UnknownPairBody {
        source_name: &'static str,
        index: usize,
        name: String,
        known: String,
    },
    #[error(
        "body `{body}` moves with the arm but holds a half-space: only static solids may be \
         unbounded"
    )]
    UnboundedMovingBody { body: String },
    #[error("body `{body}`: its hull points span no volume, so it cannot be checked")]
    DegenerateHull { body: String },
}

#[cfg(test)]
mod broad_tests;
#[cfg(test)]
mod tests;
