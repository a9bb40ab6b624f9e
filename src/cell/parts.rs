//! The cell's parts and its gripper (issue 29): `[[part]]` (a solid lying at a named pose
//! target, and the pose target it must end at) and `[gripper]` (how long the tool takes to
//! close or open and how near a part must lie to be grasped). Owns their format and their
//! checks on load, every error naming the file, the key and the value. What the parts do
//! (grasped, carried, released, judged, obstacles while they rest) is the twin's
//! (`twin::gripper`); a part is no object of the cell's own collision model (it moves).

use super::targets::{Spot, Targets};
use crate::rig::ConfigError;
use crate::rig::geometry::{Collision, MeshReader, RawSolid};
use glam::DAffine3;
use serde::Deserialize;
use std::path::Path;

/// The gripper's closing (and opening) time when `[gripper]` does not say: a pneumatic
/// parallel gripper of this size closes in about a fifth of a second.
pub const DEFAULT_CLOSING_S: f64 = 0.2;
/// How far (m) a part's grasp point may lie from the TCP to be grasped, by default: the
/// play a parallel gripper's fingers centre a part from.
pub const DEFAULT_GRASP_ZONE_M: f64 = 0.005;
/// How far (deg) a part's orientation may differ from the TCP's to be grasped, by default.
pub const DEFAULT_GRASP_ZONE_DEG: f64 = 5.0;
/// A part placed on its goal is taken in there by default: the goal of a pick-and-place
/// cell is most often a machine's fixture that takes each part in (the demo's), and parts
/// left there would stack at one pose.
pub const DEFAULT_TAKEN_AT_GOAL: bool = true;
/// Most parts a cell may hold: a tray of 100 x 100 (as a grid's side).
const MAX_PARTS: usize = 10_000;
/// Longest closing time (s) accepted: slower is a typo for milliseconds.
const MAX_CLOSING_S: f64 = 10.0;
/// Widest grasp zone accepted (m, deg): beyond, "grasped" would mean nothing.
const MAX_GRASP_ZONE_M: f64 = 0.1;
const MAX_GRASP_ZONE_DEG: f64 = 45.0;

/// The tool's gripper as the twin plays it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Gripper {
    /// Seconds from a close (or open) request to closed (open).
    pub closing_s: f64,
    /// A part is grasped when its grasp point lies within this of the TCP ...
    pub grasp_zone_m: f64,
    /// ... and its orientation within this angle (rad) of the TCP's.
    pub grasp_zone_rad: f64,
}

impl Default for Gripper {
    fn default() -> Self {
        Gripper {
            closing_s: DEFAULT_CLOSING_S,
            grasp_zone_m: DEFAULT_GRASP_ZONE_M,
            grasp_zone_rad: DEFAULT_GRASP_ZONE_DEG.to_radians(),
        }
    }
}

/// One part of the cell.
#[derive(Debug, Clone, PartialEq)]
pub struct Part {
    pub name: String,
    /// Its grasp frame in the cell frame where it lies at the start: the TCP's pose that
    /// grasps it.
    pub start: DAffine3,
    /// Where its grasp frame must end (cell frame), and that target's name.
    pub goal: DAffine3,
    pub goal_name: String,
    /// Its solid, in its grasp frame.
    pub solid: Collision,
    /// Whether its goal takes it in once it is placed there (a machine's fixture, a
    /// conveyor): it is then no obstacle; otherwise it rests there as one (a pallet).
    pub taken_at_goal: bool,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct RawGripper {
    closing_s: Option<f64>,
    grasp_zone_m: Option<f64>,
    grasp_zone_deg: Option<f64>,
}

/// `[[part]]`: a name, the pose target it lies at (`at`), the one it must end at (`goal`),
/// and its solid in its grasp frame.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct RawPart {
    name: String,
    at: String,
    goal: String,
    solid: RawSolid,
    taken_at_goal: Option<bool>,
}

pub(crate) fn gripper_of(
    file: &Path,
    prefix: &str,
    raw: &RawGripper,
) -> Result<Gripper, ConfigError> {
    let within = |field: &str, value: Option<f64>, default: f64, max: f64| {
        let Some(value) = value else {
            return Ok(default);
        };
        if value.is_finite() && value > 0.0 && value <= max {
            Ok(value)
        } else {
            Err(ConfigError::invalid(
                file,
                &format!("{prefix}gripper.{field}"),
                value,
                &format!("must lie in (0, {max}]"),
            ))
        }
    };
    Ok(Gripper {
        closing_s: within("closing_s", raw.closing_s, DEFAULT_CLOSING_S, MAX_CLOSING_S)?,
        grasp_zone_m: within(
            "grasp_zone_m",
            raw.grasp_zone_m,
            DEFAULT_GRASP_ZONE_M,
            MAX_GRASP_ZONE_M,
        )?,
        grasp_zone_rad: within(
            "grasp_zone_deg",
            raw.grasp_zone_deg,
            DEFAULT_GRASP_ZONE_DEG,
            MAX_GRASP_ZONE_DEG,
        )?
        .to_radians(),
    })
}

/// The parts of a cell file, checked against its targets (`at` and `goal` name pose
/// targets).
pub(crate) fn parts_of(
    file: &Path,
    prefix: &str,
    raw: &[RawPart],
    targets: &Targets,
    read_mesh: &MeshReader<'_>,
) -> Result<Vec<Part>, ConfigError> {
    if raw.len() > MAX_PARTS {
        return Err(ConfigError::invalid(
            file,
            &format!("{prefix}part"),
            raw.len(),
            &format!("at most {MAX_PARTS} parts"),
        ));
    }
    let mut parts: Vec<Part> = Vec::with_capacity(raw.len());
    for (i, part) in raw.iter().enumerate() {
        let key = format!("{prefix}part[{i}]");
        if part.name.is_empty() || parts.iter().any(|p| p.name == part.name) {
            return Err(ConfigError::invalid(
                file,
                &format!("{key}.name"),
                &part.name,
                "every part needs a name of its own",
            ));
        }
        let pose = |field: &str, name: &str| match targets.get(name).map(|t| &t.spot) {
            Some(Spot::Pose(pose)) => Ok(*pose),
            Some(Spot::Joints(_)) => Err(ConfigError::invalid(
                file,
                &format!("{key}.{field}"),
                name,
                "a part lies at a pose target, not a joint one",
            )),
            None => Err(ConfigError::invalid(
                file,
                &format!("{key}.{field}"),
                name,
                &format!("no target of this name (targets: {})", targets.known()),
            )),
        };
        parts.push(Part {
            name: part.name.clone(),
            start: pose("at", &part.at)?,
            goal: pose("goal", &part.goal)?,
            goal_name: part.goal.clone(),
            solid: part
                .solid
                .validate(file, &format!("{key}.solid"), read_mesh)?,
            taken_at_goal: part.taken_at_goal.unwrap_or(DEFAULT_TAKEN_AT_GOAL),
        });
    }
    Ok(parts)
}
