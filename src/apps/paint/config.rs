//! `config/paint.toml`: room sizes, brush, body envelope, stroke settings and the coverage
//! grid, validated on load (every error names the file, the key and the value). Owns the
//! file format only.

use crate::rig::{ConfigError, Rig, check_range, load_rig};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct PaintConfig {
    pub rig: PathBuf,
    pub room: RoomConfig,
    pub brush: BrushConfig,
    pub body: BodyConfig,
    pub strokes: StrokeConfig,
    pub coverage: CoverageConfig,
}

#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct RoomConfig {
    pub wall_width_m: f64,
    pub wall_height_m: f64,
    pub door_width_m: f64,
    pub door_height_m: f64,
    pub window_width_m: f64,
    pub window_height_m: f64,
    pub window_sill_m: f64,
    pub layout_grid_m: f64,
}

#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct BrushConfig {
    pub width_m: f64,
    pub handle_m: f64,
    pub bristle_m: f64,
    pub handle_radius_m: f64,
    pub overlap_m: f64,
    pub contact_tolerance_m: f64,
    pub edge_inset_m: f64,
}

#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct BodyConfig {
    /// The clearance the planner keeps between the painter's bodies (its rig's, and the
    /// brush's handle) and the walls.
    pub planning_clearance_m: f64,
}

#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct StrokeConfig {
    pub reach_m: f64,
    pub low_lift_m: f64,
    pub hold_height_m: f64,
    pub retract_m: f64,
    pub travel_arm_deg: [f64; 6],
}

#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct CoverageConfig {
    pub cell_m: f64,
}

/// A loaded, validated paint configuration with its rig.
#[derive(Debug, Clone)]
pub struct PaintSettings {
    pub file: PathBuf,
    pub config: PaintConfig,
    pub rig: Rig,
}

/// Axes before the arm: base x, base y, base yaw, lift.
pub const EXTRA_AXES: usize = 4;
/// The lift's place among the extra axes (after base x, y and yaw): the axis that carries
/// the held arm up a stroke.
pub const LIFT_AXIS: usize = 3;

/// True when `value` is a whole multiple of `grid` (to rounding).
fn on_grid(value: f64, grid: f64) -> bool {
    let steps = value / grid;
    (steps - steps.round()).abs() < 1e-6
}

/// Reads and validates `config/paint.toml` and the rig it names.
pub fn load_paint_settings(file: &Path) -> Result<PaintSettings, ConfigError> {
    let text = crate::rig::shipped::read(file)?;
    let config: PaintConfig = toml::from_str(&text).map_err(|e| ConfigError::Parse {
        file: file.to_path_buf(),
        message: e.to_string().trim_end().to_string(),
    })?;
    let rig = load_rig(&file.parent().unwrap_or(Path::new(".")).join(&config.rig))?;
    check(file, &config, &rig)?;
    Ok(PaintSettings {
        file: file.to_path_buf(),
        config,
        rig,
    })
}

fn check(file: &Path, c: &PaintConfig, rig: &Rig) -> Result<(), ConfigError> {
    check_room(file, c)?;
    check_brush(file, c)?;
    check_body(file, c)?;
    check_strokes(file, c, rig)
}

/// The room's sizes: in range and on the layout grid, the windows inside the walls.
fn check_room(file: &Path, c: &PaintConfig) -> Result<(), ConfigError> {
    let r = &c.room;
    check_range(file, "room.layout_grid_m", r.layout_grid_m, 0.001, 0.1)?;
    for (key, value, low, high) in [
        ("room.wall_width_m", r.wall_width_m, 0.5, 20.0),
        ("room.wall_height_m", r.wall_height_m, 0.5, 2.8),
        ("room.door_width_m", r.door_width_m, 0.1, 10.0),
        ("room.door_height_m", r.door_height_m, 0.1, r.wall_height_m),
        ("room.window_width_m", r.window_width_m, 0.1, 10.0),
        (
            "room.window_height_m",
            r.window_height_m,
            0.1,
            r.wall_height_m,
        ),
        ("room.window_sill_m", r.window_sill_m, 0.0, r.wall_height_m),
    ] {
        check_range(file, key, value, low, high)?;
        if !on_grid(value, r.layout_grid_m) {
            return Err(ConfigError::invalid(
                file,
                key,
                value,
                &format!(
                    "must be a multiple of room.layout_grid_m = {}",
                    r.layout_grid_m
                ),
            ));
        }
    }
    if r.window_sill_m + r.window_height_m > r.wall_height_m {
        return Err(ConfigError::invalid(
            file,
            "room.window_sill_m",
            r.window_sill_m,
            &format!(
                "sill + window height {} exceeds the wall height {}",
                r.window_sill_m + r.window_height_m,
                r.wall_height_m
            ),
        ));
    }
    Ok(())
}

/// The brush and the coverage grid it is measured on.
fn check_brush(file: &Path, c: &PaintConfig) -> Result<(), ConfigError> {
    let r = &c.room;
    let b = &c.brush;
    check_range(file, "brush.width_m", b.width_m, 0.02, 0.5)?;
    check_range(file, "brush.handle_m", b.handle_m, 0.05, 0.5)?;
    check_range(file, "brush.bristle_m", b.bristle_m, 0.0, b.handle_m)?;
    check_range(
        file,
        "brush.handle_radius_m",
        b.handle_radius_m,
        0.001,
        0.05,
    )?;
    check_range(file, "brush.overlap_m", b.overlap_m, 0.0, b.width_m / 2.0)?;
    check_range(
        file,
        "brush.contact_tolerance_m",
        b.contact_tolerance_m,
        1e-4,
        0.01,
    )?;
    check_range(
        file,
        "brush.edge_inset_m",
        b.edge_inset_m,
        0.0,
        c.coverage.cell_m / 2.0,
    )?;
    check_range(file, "coverage.cell_m", c.coverage.cell_m, 0.001, 0.02)?;
    if !on_grid(r.layout_grid_m, c.coverage.cell_m) {
        return Err(ConfigError::invalid(
            file,
            "coverage.cell_m",
            c.coverage.cell_m,
            &format!("must divide room.layout_grid_m = {}", r.layout_grid_m),
        ));
    }
    Ok(())
}

/// The planning clearance (the envelope itself is the rig's bodies, checked with the rig).
fn check_body(file: &Path, c: &PaintConfig) -> Result<(), ConfigError> {
    let body = &c.body;
    check_range(
        file,
        "body.planning_clearance_m",
        body.planning_clearance_m,
        0.0,
        0.2,
    )?;
    Ok(())
}

/// The strokes against the rig: its axes, the lift's range and the arm's travel pose.
fn check_strokes(file: &Path, c: &PaintConfig, rig: &Rig) -> Result<(), ConfigError> {
    let r = &c.room;
    let s = &c.strokes;
    check_range(file, "strokes.reach_m", s.reach_m, 0.2, 1.0)?;
    check_range(file, "strokes.retract_m", s.retract_m, 0.005, 0.2)?;
    check_range(file, "strokes.hold_height_m", s.hold_height_m, -0.5, 1.0)?;
    if rig.dof() != EXTRA_AXES + 6 {
        return Err(ConfigError::invalid(
            file,
            "rig",
            c.rig.display().to_string(),
            &format!(
                "the painter needs {EXTRA_AXES} extra axes and a six-axis arm, rig {} has {} axes",
                rig.name,
                rig.dof()
            ),
        ));
    }
    let lift = rig.joints[LIFT_AXIS].limits;
    check_range(
        file,
        "strokes.low_lift_m",
        s.low_lift_m,
        lift.lower,
        lift.upper,
    )?;
    let top_lift = r.wall_height_m - s.hold_height_m;
    if top_lift > lift.upper || s.low_lift_m + s.hold_height_m >= r.wall_height_m {
        return Err(ConfigError::invalid(
            file,
            "strokes.hold_height_m",
            s.hold_height_m,
            &format!(
                "the lift must carry the brush from {} m to the ceiling at {} m; lift range is [{}, {}]",
                s.low_lift_m + s.hold_height_m,
                r.wall_height_m,
                lift.lower,
                lift.upper
            ),
        ));
    }
    let travel: Vec<f64> = s.travel_arm_deg.iter().map(|d| d.to_radians()).collect();
    for (i, (q, joint)) in travel.iter().zip(&rig.joints[EXTRA_AXES..]).enumerate() {
        if let Err(outside) = joint.check_limits(*q) {
            return Err(ConfigError::invalid(
                file,
                &format!("strokes.travel_arm_deg[{i}]"),
                s.travel_arm_deg[i],
                &outside.to_string(),
            ));
        }
    }
    Ok(())
}
