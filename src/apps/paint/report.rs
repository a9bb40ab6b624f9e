//! The paint report (JSON) and picture (SVG): totals and per-wall coverage measured by the
//! twin's world, the room's geometry and the tool's, so that anyone can recompute the
//! coverage from the run's log (docs/painting.md says how). Owns formats only; every number
//! comes from the world's measurements or the room.

use super::config::PaintSettings;
use super::planner::{PaintPlan, PlannedStroke, UnreachableStroke};
use super::room::{OpeningKind, Room, Wall};
use super::world::{Measurements, PaintWorld, WallGrid};
use serde::Serialize;
use std::fmt::Write as _;

#[derive(Debug, Clone, Serialize)]
pub struct Totals {
    pub paintable_m2: f64,
    pub painted_m2: f64,
    pub coverage: f64,
    pub paint_in_openings_m2: f64,
    pub limit_violations: u64,
    pub collisions: u64,
    pub duration_s: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct WallReport {
    pub index: usize,
    #[serde(rename = "type")]
    pub wall_type: &'static str,
    pub paintable_m2: f64,
    pub painted_m2: f64,
    pub coverage: f64,
    pub paint_in_openings_m2: f64,
    pub limit_violations: u64,
    pub collisions: u64,
    pub strokes: usize,
}

/// The brush on tool0, as the twin's world models it.
#[derive(Debug, Clone, Serialize)]
pub struct ToolReport {
    pub brush_width_m: f64,
    pub handle_m: f64,
    pub bristle_m: f64,
    pub handle_radius_m: f64,
    pub contact_tolerance_m: f64,
    pub coverage_cell_m: f64,
    /// How the contact line follows from the joints.
    pub frame: &'static str,
}

#[derive(Debug, Clone, Serialize)]
pub struct PaintReport {
    pub walls_count: u32,
    pub seed: u64,
    pub totals: Totals,
    pub walls: Vec<WallReport>,
    pub room: Room,
    pub tool: ToolReport,
    pub strokes: Vec<PlannedStroke>,
    pub unreachable: Vec<UnreachableStroke>,
    pub measurements: Measurements,
}

const TOOL_FRAME: &str = "contact centre = FK(tool0) * (0, 0, handle_m); contact line along tool0's x axis, brush_width_m long; joints in the log are base_x, base_y, base_yaw, lift, joint_1..joint_6 (config/painter.toml)";

pub fn build_report(
    settings: &PaintSettings,
    plan: &PaintPlan,
    world: &PaintWorld,
    duration_s: f64,
) -> PaintReport {
    let room = world.room();
    let measured = world.measurements();
    let walls: Vec<WallReport> = world
        .grids()
        .iter()
        .zip(&room.walls)
        .map(|(grid, wall)| {
            let stats = grid.stats();
            WallReport {
                index: wall.index,
                wall_type: wall.wall_type.name(),
                paintable_m2: stats.paintable_m2,
                painted_m2: stats.painted_m2,
                coverage: stats.coverage,
                paint_in_openings_m2: stats.paint_in_openings_m2,
                limit_violations: measured.limit_violations_by_wall[wall.index],
                collisions: measured.collisions_by_wall[wall.index],
                strokes: plan.strokes.iter().filter(|s| s.wall == wall.index).count(),
            }
        })
        .collect();
    let paintable: f64 = walls.iter().map(|w| w.paintable_m2).sum();
    let painted: f64 = walls.iter().map(|w| w.painted_m2).sum();
    let brush = &settings.config.brush;
    PaintReport {
        walls_count: room.walls_count,
        seed: room.seed,
        totals: Totals {
            paintable_m2: paintable,
            painted_m2: painted,
            coverage: if paintable > 0.0 {
                painted / paintable
            } else {
                1.0
            },
            paint_in_openings_m2: walls.iter().map(|w| w.paint_in_openings_m2).sum(),
            limit_violations: measured.limit_violations,
            collisions: measured.collisions,
            duration_s,
        },
        walls,
        room: room.clone(),
        tool: ToolReport {
            brush_width_m: brush.width_m,
            handle_m: brush.handle_m,
            bristle_m: brush.bristle_m,
            handle_radius_m: brush.handle_radius_m,
            contact_tolerance_m: brush.contact_tolerance_m,
            coverage_cell_m: settings.config.coverage.cell_m,
            frame: TOOL_FRAME,
        },
        strokes: plan.strokes.clone(),
        unreachable: plan.unreachable.clone(),
        measurements: measured.clone(),
    }
}

/// Pixels per metre in the picture.
const SVG_SCALE: f64 = 60.0;
/// Space between walls side by side (m), and above each row for the labels (m).
const SVG_GAP_M: f64 = 0.3;
const SVG_ROW_MARGIN_M: f64 = 0.6;
/// Walls per row of the picture.
const SVG_WALLS_PER_ROW: usize = 8;

/// Every wall unrolled left to right (wall 0 first), seen from inside the room: openings
/// outlined, paint in green, paint inside an opening in red, unpainted wall in grey.
pub fn write_svg(world: &PaintWorld, report: &PaintReport) -> String {
    let room = world.room();
    let mut svg = String::new();
    svg_header(&mut svg, room, report);
    for ((wall, grid), wall_report) in room.walls.iter().zip(world.grids()).zip(&report.walls) {
        let (col, row) = (
            wall.index % SVG_WALLS_PER_ROW,
            wall.index / SVG_WALLS_PER_ROW,
        );
        let x0 = (SVG_GAP_M + col as f64 * (room.wall_width_m + SVG_GAP_M)) * SVG_SCALE;
        let top =
            (SVG_ROW_MARGIN_M + row as f64 * (room.wall_height_m + SVG_ROW_MARGIN_M)) * SVG_SCALE;
        let floor = top + room.wall_height_m * SVG_SCALE;
        let _ = writeln!(
            svg,
            r##"<rect x="{x0:.1}" y="{top:.1}" width="{:.1}" height="{:.1}" fill="#d0d0d0"/>"##,
            room.wall_width_m * SVG_SCALE,
            room.wall_height_m * SVG_SCALE
        );
        svg_paint(&mut svg, grid, x0, floor);
        svg_openings(&mut svg, wall, x0, floor);
        let _ = writeln!(
            svg,
            r##"<text x="{x0:.1}" y="{:.1}">wall {} ({}): {:.2} %</text>"##,
            floor + 14.0,
            wall.index,
            wall.wall_type.name(),
            wall_report.coverage * 100.0
        );
    }
    svg.push_str("</svg>\n");
    svg
}

/// The picture's size and the title line with the totals.
fn svg_header(svg: &mut String, room: &Room, report: &PaintReport) {
    let (w, h) = (room.wall_width_m, room.wall_height_m);
    let rows = room.walls.len().div_ceil(SVG_WALLS_PER_ROW);
    let width_px =
        (SVG_WALLS_PER_ROW.min(room.walls.len()) as f64 * (w + SVG_GAP_M) + SVG_GAP_M) * SVG_SCALE;
    let height_px = (rows as f64 * (h + SVG_ROW_MARGIN_M) + SVG_ROW_MARGIN_M) * SVG_SCALE;
    let _ = writeln!(
        svg,
        r##"<svg xmlns="http://www.w3.org/2000/svg" width="{width_px:.0}" height="{height_px:.0}" font-family="sans-serif" font-size="12"><rect width="100%" height="100%" fill="white"/>"##
    );
    let _ = writeln!(
        svg,
        r##"<text x="8" y="18">{} walls, seed {}: coverage {:.3} %, paint in openings {:.4} m2, collisions {}, limit violations {}</text>"##,
        report.walls_count,
        report.seed,
        report.totals.coverage * 100.0,
        report.totals.paint_in_openings_m2,
        report.totals.collisions,
        report.totals.limit_violations
    );
}

/// One wall's painted cells, a rectangle per run of cells along a row with the same
/// colour: green on the wall, red in an opening.
fn svg_paint(svg: &mut String, grid: &WallGrid, x0: f64, floor: f64) {
    let cell = grid.cell * SVG_SCALE;
    for r in 0..grid.rows {
        let mut c = 0;
        while c < grid.cols {
            let i = r * grid.cols + c;
            if !grid.painted[i] {
                c += 1;
                continue;
            }
            let in_opening = grid.opening[i];
            let start = c;
            while c < grid.cols
                && grid.painted[r * grid.cols + c]
                && grid.opening[r * grid.cols + c] == in_opening
            {
                c += 1;
            }
            let colour = if in_opening { "#d62728" } else { "#2ca02c" };
            let _ = writeln!(
                svg,
                r##"<rect x="{:.2}" y="{:.2}" width="{:.2}" height="{:.2}" fill="{colour}"/>"##,
                x0 + start as f64 * cell,
                floor - (r + 1) as f64 * cell,
                (c - start) as f64 * cell,
                cell
            );
        }
    }
}

/// One wall's doors and windows, outlined over the paint.
fn svg_openings(svg: &mut String, wall: &Wall, x0: f64, floor: f64) {
    for o in &wall.openings {
        let fill = match o.kind {
            OpeningKind::Door => "#8c564b",
            OpeningKind::Window => "#9ecae1",
        };
        let _ = writeln!(
            svg,
            r##"<rect x="{:.1}" y="{:.1}" width="{:.1}" height="{:.1}" fill="{fill}" fill-opacity="0.35" stroke="black"/>"##,
            x0 + o.left_m * SVG_SCALE,
            floor - o.top_m * SVG_SCALE,
            (o.right_m - o.left_m) * SVG_SCALE,
            (o.top_m - o.bottom_m) * SVG_SCALE
        );
    }
}
