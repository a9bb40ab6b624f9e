//! The cell file (`cell.toml`) and the run settings' `[cell]` section: one schema, validated
//! on load, every error naming the file, the key and the bad value. Owns the format only;
//! whether the named bodies exist is the collision model's question (it knows the rig).

use super::parts::{RawGripper, RawPart, gripper_of, parts_of};
use super::targets::{RawGrid, RawTarget, targets_from_raw};
use super::{Cell, CellError, CellObject, DEFAULT_MARGIN_M, Tool};
use crate::rig::geometry::{RawSolid, check_pairs};
use crate::rig::{ConfigError, check_range, origin_from_xyz_rpy, shipped};
use glam::{DAffine3, DVec3};
use serde::Deserialize;
use std::path::Path;

/// The margin's bounds: at least 1 mm (the continuous check proves clearance between
/// samples to within 1 mm of the margin, so a smaller one would prove nothing), at most 1 m
/// (more would refuse any motion of an arm this size).
const MARGIN_RANGE_M: (f64, f64) = (0.001, 1.0);

/// A cell file, or a run settings' `[cell]` table.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct RawCell {
    margin_m: Option<f64>,
    #[serde(default)]
    allowed_pairs: Vec<(String, String)>,
    mount: Option<RawFrame>,
    #[serde(default)]
    object: Vec<RawSolid>,
    tool: Option<RawTool>,
    #[serde(default)]
    target: Vec<RawTarget>,
    #[serde(default)]
    target_grid: Vec<RawGrid>,
    #[serde(default)]
    part: Vec<RawPart>,
    gripper: Option<RawGripper>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawFrame {
    #[serde(default)]
    origin_xyz_m: [f64; 3],
    #[serde(default)]
    origin_rpy_deg: [f64; 3],
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawTool {
    name: String,
    tcp: Option<RawFrame>,
    #[serde(default)]
    body: Vec<RawSolid>,
}

/// Reads a cell file (a shipped one, `embedded:/...`, or one on disk).
pub fn load_cell(path: &Path) -> Result<Cell, CellError> {
    let text = shipped::read(path)?;
    cell_from_toml(&text, path)
}

/// Parses a cell file's text; `file` names the source in errors and is where relative mesh
/// paths start.
pub fn cell_from_toml(text: &str, file: &Path) -> Result<Cell, CellError> {
    let raw: RawCell = toml::from_str(text).map_err(|e| ConfigError::Parse {
        file: file.to_path_buf(),
        message: e.to_string().trim_end().to_string(),
    })?;
    Ok(cell_from_raw(&raw, file, "")?)
}

/// Validates a cell found at `prefix` in `file` (`""` for a cell file, `cell.` for a run
/// settings' section).
pub(crate) fn cell_from_raw(raw: &RawCell, file: &Path, prefix: &str) -> Result<Cell, ConfigError> {
    let key = |field: &str| format!("{prefix}{field}");
    let read_mesh = |key: &str, name: &str| crate::rig::geometry::read_hull_points(file, key, name);
    let margin_m = match raw.margin_m {
        Some(m) => check_range(
            file,
            &key("margin_m"),
            m,
            MARGIN_RANGE_M.0,
            MARGIN_RANGE_M.1,
        )?,
        None => DEFAULT_MARGIN_M,
    };
    let mount = match &raw.mount {
        Some(frame) => frame_of(file, &key("mount."), frame)?,
        None => DAffine3::IDENTITY,
    };
    let mut objects: Vec<CellObject> = Vec::with_capacity(raw.object.len());
    for (i, solid) in raw.object.iter().enumerate() {
        let object_key = key(&format!("object[{i}]"));
        let name = solid.name.clone().unwrap_or_default();
        if name.trim().is_empty() {
            return Err(ConfigError::invalid(
                file,
                &format!("{object_key}.name"),
                solid.name.as_deref(),
                "every object needs a name (refusals and the scene show it)",
            ));
        }
        if objects.iter().any(|o| o.name == name) {
            return Err(ConfigError::invalid(
                file,
                &format!("{object_key}.name"),
                &name,
                "duplicate object name",
            ));
        }
        let collision = solid.validate(file, &object_key, &read_mesh)?;
        objects.push(CellObject {
            name,
            pose: collision.origin,
            shape: collision.shape,
        });
    }
    let tool = match &raw.tool {
        Some(tool) => Some(tool_of(file, &key("tool."), tool, &read_mesh)?),
        None => None,
    };
    // Names are checked against the rig by the collision model; here only their form.
    check_pairs(file, &key("allowed_pairs"), &raw.allowed_pairs, |name| {
        !name.trim().is_empty()
    })?;
    let targets = targets_from_raw(file, prefix, &raw.target, &raw.target_grid)?;
    let parts = parts_of(file, prefix, &raw.part, &targets, &read_mesh)?;
    let gripper = gripper_of(
        file,
        prefix,
        raw.gripper.as_ref().unwrap_or(&RawGripper::default()),
    )?;
    Ok(Cell {
        mount,
        objects,
        tool,
        margin_m,
        allowed_pairs: raw.allowed_pairs.clone(),
        targets,
        parts,
        gripper,
    })
}

fn frame_of(file: &Path, prefix: &str, frame: &RawFrame) -> Result<DAffine3, ConfigError> {
    let finite = |field: &str, v: [f64; 3]| -> Result<DVec3, ConfigError> {
        if v.iter().all(|x| x.is_finite()) {
            Ok(DVec3::from_array(v))
        } else {
            Err(ConfigError::invalid(
                file,
                &format!("{prefix}{field}"),
                v,
                "every component must be a finite number",
            ))
        }
    };
    let xyz = finite("origin_xyz_m", frame.origin_xyz_m)?;
    let rpy = finite("origin_rpy_deg", frame.origin_rpy_deg)?;
    Ok(origin_from_xyz_rpy(
        xyz,
        rpy * (std::f64::consts::PI / 180.0),
    ))
}

fn tool_of(
    file: &Path,
    prefix: &str,
    raw: &RawTool,
    read_mesh: &crate::rig::geometry::MeshReader<'_>,
) -> Result<Tool, ConfigError> {
    if raw.name.trim().is_empty() {
        return Err(ConfigError::invalid(
            file,
            &format!("{prefix}name"),
            &raw.name,
            "must not be empty (it names the tool's body and its TCP frame)",
        ));
    }
    let tcp = match &raw.tcp {
        Some(frame) => frame_of(file, &format!("{prefix}tcp."), frame)?,
        None => DAffine3::IDENTITY,
    };
    let mut bodies = Vec::with_capacity(raw.body.len());
    for (i, solid) in raw.body.iter().enumerate() {
        let key = format!("{prefix}body[{i}]");
        if solid.name.is_some() {
            return Err(ConfigError::invalid(
                file,
                &format!("{key}.name"),
                solid.name.as_deref(),
                "a tool's solids are one body, named by the tool's `name`",
            ));
        }
        let collision = solid.validate(file, &key, read_mesh)?;
        if matches!(collision.shape, crate::rig::Shape::HalfSpace { .. }) {
            return Err(ConfigError::invalid(
                file,
                &format!("{key}.shape"),
                "half_space",
                "a tool moves with the arm: it cannot be unbounded",
            ));
        }
        bodies.push(collision);
    }
    Ok(Tool {
        name: raw.name.clone(),
        bodies,
        tcp,
    })
}
