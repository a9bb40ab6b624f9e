//! Named targets of a cell (issue 29): `[[target]]` (a joint configuration or a tool pose,
//! named once, used by any number of program steps) and `[[target_grid]]` (a tray's slots,
//! `slot[0]` .. `slot[n-1]`). Owns their format and their checks on load, every error naming
//! the file, the key and the value. Joint values are checked against the rig's limits by the
//! job that uses them (a cell does not know its rig); poses are in the cell frame.

use crate::rig::{ConfigError, origin_from_xyz_rpy};
use glam::{DAffine3, DVec3};
use serde::Deserialize;
use std::path::Path;

/// Largest coordinate (m) of a target or a grid step: far beyond any cell we drive, so it
/// only catches millimetres written as metres.
const MAX_COORDINATE_M: f64 = 10.0;

/// Most joint values a joint target may hold: the wire protocol's axis count (32; `cell`
/// sits below `protocol`, so the number is repeated here).
const MAX_JOINTS: usize = 32;

/// Most slots a grid may generate along one direction: a tray of 100 x 100 is more than
/// any gripper empties; more is a typo.
const MAX_GRID_SIDE: usize = 100;

/// Most targets a cell may name, plain and generated together: one program's cap.
const MAX_TARGETS: usize = 10_000;

/// Where a named target is.
#[derive(Debug, Clone, PartialEq)]
pub enum Spot {
    /// A joint configuration, in config units as written (degrees, metres for prismatic
    /// axes).
    Joints(Vec<f64>),
    /// A tool pose (the TCP of the tool a step uses) in the cell frame.
    Pose(DAffine3),
}

/// One named target.
#[derive(Debug, Clone, PartialEq)]
pub struct NamedTarget {
    pub name: String,
    pub spot: Spot,
    /// Where it was written: `target[2]`, or `target_grid[0]` for a generated slot.
    pub key: String,
}

/// A grid's name and how many targets it generated (`name[0]` .. `name[count - 1]`).
#[derive(Debug, Clone, PartialEq)]
pub struct GridNames {
    pub name: String,
    pub count: usize,
}

/// Every named target of a cell, in the order written (a grid's slots in slot order).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Targets {
    pub targets: Vec<NamedTarget>,
    pub grids: Vec<GridNames>,
}

impl Targets {
    /// The target called `name`.
    pub fn get(&self, name: &str) -> Option<&NamedTarget> {
        self.targets.iter().find(|t| t.name == name)
    }

    /// The names of grid `name`'s slots, in order.
    pub fn grid(&self, name: &str) -> Option<Vec<String>> {
        self.grids
            .iter()
            .find(|g| g.name == name)
            .map(|g| (0..g.count).map(|k| format!("{name}[{k}]")).collect())
    }

    /// Every name a step may use, for a refusal to list (the grids as `slot[0..11]`).
    pub fn known(&self) -> String {
        let plain = self
            .targets
            .iter()
            .filter(|t| !t.key.starts_with("target_grid"))
            .map(|t| t.name.clone());
        let grids = self
            .grids
            .iter()
            .map(|g| format!("{}[0..{}]", g.name, g.count.saturating_sub(1)));
        let all: Vec<String> = plain.chain(grids).collect();
        if all.is_empty() {
            "none: the cell names no targets".to_string()
        } else {
            all.join(", ")
        }
    }
}

/// A pose as a cell file writes it, in the cell frame: `{ xyz_m = [...], rpy_deg = [...] }`
/// (roll, pitch, yaw about fixed x, y, z, as every origin of a cell or rig file).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct RawPose {
    xyz_m: [f64; 3],
    #[serde(default)]
    rpy_deg: [f64; 3],
}

/// `[[target]]`: a name and exactly one of `joints_deg` and `pose`.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct RawTarget {
    name: String,
    joints_deg: Option<Vec<f64>>,
    pose: Option<RawPose>,
}

/// `[[target_grid]]`: `rows` x `columns` poses from the first slot's `origin`, a row apart
/// by `row_step_m` and a column apart by `column_step_m` (cell frame), every slot with the
/// first's orientation; slot `row * columns + column` is `name[row * columns + column]`.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct RawGrid {
    name: String,
    origin: RawPose,
    rows: usize,
    columns: usize,
    row_step_m: [f64; 3],
    column_step_m: [f64; 3],
}

/// The targets and grids of a cell file, checked; `prefix` is `""` for a cell file and
/// `cell.` for a run settings' section.
pub(crate) fn targets_from_raw(
    file: &Path,
    prefix: &str,
    targets: &[RawTarget],
    grids: &[RawGrid],
) -> Result<Targets, ConfigError> {
    let mut out = Targets::default();
    for (i, raw) in targets.iter().enumerate() {
        let key = format!("{prefix}target[{i}]");
        check_name(file, &key, &raw.name, &out)?;
        let spot = match (&raw.joints_deg, &raw.pose) {
            (Some(joints), None) => Spot::Joints(check_joints(file, &key, joints)?),
            (None, Some(pose)) => Spot::Pose(pose_of(file, &format!("{key}.pose"), pose)?),
            _ => {
                return Err(ConfigError::invalid(
                    file,
                    &key,
                    raw.name.as_str(),
                    "needs exactly one of `joints_deg` and `pose`",
                ));
            }
        };
        out.targets.push(NamedTarget {
            name: raw.name.clone(),
            spot,
            key,
        });
    }
    for (i, raw) in grids.iter().enumerate() {
        let key = format!("{prefix}target_grid[{i}]");
        grid_into(file, &key, raw, &mut out)?;
    }
    if out.targets.len() > MAX_TARGETS {
        return Err(ConfigError::invalid(
            file,
            &format!("{prefix}target_grid"),
            out.targets.len(),
            &format!("a cell names at most {MAX_TARGETS} targets"),
        ));
    }
    Ok(out)
}

/// A name steps can write: letters, digits, `_` and `-`, unused so far. Brackets are a
/// grid's (`slot[3]`), `$` a repeat's variable, so a plain name never looks like either.
fn check_name(file: &Path, key: &str, name: &str, so_far: &Targets) -> Result<(), ConfigError> {
    let key = format!("{key}.name");
    let allowed = |c: char| c.is_ascii_alphanumeric() || c == '_' || c == '-';
    if name.is_empty() || !name.chars().all(allowed) {
        return Err(ConfigError::invalid(
            file,
            &key,
            name,
            "a target's name is letters, digits, `_` and `-` (at least one)",
        ));
    }
    let taken = so_far.get(name).is_some() || so_far.grids.iter().any(|g| g.name == name);
    if taken {
        return Err(ConfigError::invalid(
            file,
            &key,
            name,
            "another target or grid has this name",
        ));
    }
    Ok(())
}

fn check_joints(file: &Path, key: &str, joints: &[f64]) -> Result<Vec<f64>, ConfigError> {
    let key = format!("{key}.joints_deg");
    if joints.is_empty() || joints.len() > MAX_JOINTS {
        return Err(ConfigError::invalid(
            file,
            &key,
            joints,
            &format!("needs 1 to {MAX_JOINTS} values, one per axis"),
        ));
    }
    if let Some(i) = joints.iter().position(|v| !v.is_finite()) {
        return Err(ConfigError::invalid(
            file,
            &format!("{key}[{i}]"),
            joints[i],
            "must be a finite number",
        ));
    }
    Ok(joints.to_vec())
}

/// A finite vector within [`MAX_COORDINATE_M`] (a position or a step).
fn coordinates(file: &Path, key: &str, v: [f64; 3]) -> Result<DVec3, ConfigError> {
    if v.iter()
        .all(|x| x.is_finite() && x.abs() <= MAX_COORDINATE_M)
    {
        Ok(DVec3::from_array(v))
    } else {
        Err(ConfigError::invalid(
            file,
            key,
            v,
            &format!("every component must lie in [-{MAX_COORDINATE_M}, {MAX_COORDINATE_M}] m"),
        ))
    }
}

fn pose_of(file: &Path, key: &str, pose: &RawPose) -> Result<DAffine3, ConfigError> {
    let xyz = coordinates(file, &format!("{key}.xyz_m"), pose.xyz_m)?;
    if !pose.rpy_deg.iter().all(|a| a.is_finite()) {
        return Err(ConfigError::invalid(
            file,
            &format!("{key}.rpy_deg"),
            pose.rpy_deg,
            "every angle must be a finite number",
        ));
    }
    let rpy = DVec3::from_array(pose.rpy_deg) * (std::f64::consts::PI / 180.0);
    Ok(origin_from_xyz_rpy(xyz, rpy))
}

/// Checks grid `raw` and adds its slots to `out`.
fn grid_into(file: &Path, key: &str, raw: &RawGrid, out: &mut Targets) -> Result<(), ConfigError> {
    check_name(file, key, &raw.name, out)?;
    for (field, count) in [("rows", raw.rows), ("columns", raw.columns)] {
        if !(1..=MAX_GRID_SIDE).contains(&count) {
            return Err(ConfigError::invalid(
                file,
                &format!("{key}.{field}"),
                count,
                &format!("must lie in [1, {MAX_GRID_SIDE}]"),
            ));
        }
    }
    let origin = pose_of(file, &format!("{key}.origin"), &raw.origin)?;
    let row_step = coordinates(file, &format!("{key}.row_step_m"), raw.row_step_m)?;
    let column_step = coordinates(file, &format!("{key}.column_step_m"), raw.column_step_m)?;
    for row in 0..raw.rows {
        for column in 0..raw.columns {
            let shift = row_step * row as f64 + column_step * column as f64;
            let pose = DAffine3 {
                translation: origin.translation + shift,
                ..origin
            };
            out.targets.push(NamedTarget {
                name: format!("{}[{}]", raw.name, row * raw.columns + column),
                spot: Spot::Pose(pose),
                key: key.to_string(),
            });
        }
    }
    out.grids.push(GridNames {
        name: raw.name.clone(),
        count: raw.rows * raw.columns,
    });
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cell::{CellError, cell_from_toml};

    fn load(text: &str) -> Result<Targets, CellError> {
        cell_from_toml(text, Path::new("c.toml")).map(|cell| cell.targets)
    }

    #[test]
    fn a_grid_names_its_slots_row_by_row_from_its_first() {
        let targets = load(
            "[[target_grid]]\nname = \"slot\"\nrows = 2\ncolumns = 3\n\
             origin = { xyz_m = [0.1, 0.2, 0.3], rpy_deg = [180.0, 0.0, 0.0] }\n\
             row_step_m = [0.05, 0.0, 0.0]\ncolumn_step_m = [0.0, 0.04, 0.0]\n",
        )
        .unwrap();
        assert_eq!(targets.grid("slot").unwrap().len(), 6);
        // slot[5]: row 1, column 2: 0.1 + 0.05, 0.2 + 2 x 0.04.
        let Spot::Pose(pose) = &targets.get("slot[5]").unwrap().spot else {
            panic!("a grid slot is a pose");
        };
        assert!((pose.translation - DVec3::new(0.15, 0.28, 0.3)).length() < 1e-12);
        // Roll 180 deg: the tool's z points down.
        assert!((pose.matrix3.z_axis - DVec3::new(0.0, 0.0, -1.0)).length() < 1e-12);
        assert_eq!(targets.known(), "slot[0..5]");
    }

    #[test]
    fn bad_targets_are_refused_naming_file_key_and_value() {
        let cases = [
            (
                "[[target]]\nname = \"a b\"\njoints_deg = [0.0]\n",
                "c.toml: key `target[0].name` = \"a b\": a target's name is letters, digits, `_` and `-` (at least one)",
            ),
            (
                "[[target]]\nname = \"home\"\n",
                "c.toml: key `target[0]` = \"home\": needs exactly one of `joints_deg` and `pose`",
            ),
            (
                "[[target]]\nname = \"a\"\njoints_deg = [0.0]\n[[target]]\nname = \"a\"\njoints_deg = [1.0]\n",
                "c.toml: key `target[1].name` = \"a\": another target or grid has this name",
            ),
            (
                "[[target]]\nname = \"p\"\npose = { xyz_m = [0.3, 0.0, 300.0] }\n",
                "c.toml: key `target[0].pose.xyz_m` = [0.3, 0.0, 300.0]: every component must lie in [-10, 10] m",
            ),
            (
                "[[target_grid]]\nname = \"slot\"\nrows = 0\ncolumns = 3\norigin = { xyz_m = [0.0, 0.0, 0.0] }\nrow_step_m = [0.05, 0.0, 0.0]\ncolumn_step_m = [0.0, 0.05, 0.0]\n",
                "c.toml: key `target_grid[0].rows` = 0: must lie in [1, 100]",
            ),
        ];
        for (text, expected) in cases {
            let refused = load(text).unwrap_err().to_string();
            assert!(
                refused.contains(expected),
                "{text}: got {refused}, expected {expected}"
            );
        }
    }
}
