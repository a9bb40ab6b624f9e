//! The room generator (seed 000): N equal walls on a regular polygon around the start point,
//! each drawn from four types with a seeded generator, openings laid out on a grid.
//!
//! Owns the room's geometry and wall coordinates. Must not know about the robot or the
//! plan. Wall coordinates: `s` runs along the wall from its left end (seen from inside the
//! room) to its right end, `v` up from the floor; the wall's outward normal points out of
//! the room.

use super::config::RoomConfig;
use glam::{DVec2, DVec3};
use serde::Serialize;
use thiserror::Error;

#[derive(Debug, Clone, PartialEq, Error)]
pub enum RoomError {
    #[error("a room needs at least 3 walls, {walls} asked")]
    TooFewWalls { walls: u32 },
    #[error("at most {max} walls, {walls} asked (the base's x and y limits)")]
    TooManyWalls { walls: u32, max: u32 },
    #[error(
        "wall {wall} ({kind}): openings {needed_m:.3} m wide with {gaps} gaps of one brush width ({brush_m} m) do not fit a {width_m} m wall"
    )]
    OpeningsDoNotFit {
        wall: usize,
        kind: &'static str,
        needed_m: f64,
        gaps: u32,
        brush_m: f64,
        width_m: f64,
    },
}

/// The most walls a room may have: the painter's x and y axes cover a 32-wall room.
pub const MAX_WALLS: u32 = 32;

#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum WallType {
    Blank,
    Door,
    TwoWindows,
    DoorAndTwoWindows,
}

impl WallType {
    pub fn name(self) -> &'static str {
        match self {
            WallType::Blank => "blank",
            WallType::Door => "door",
            WallType::TwoWindows => "two_windows",
            WallType::DoorAndTwoWindows => "door_and_two_windows",
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum OpeningKind {
    Door,
    Window,
}

/// A rectangular opening in wall coordinates (metres).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Opening {
    pub kind: OpeningKind,
    pub left_m: f64,
    pub right_m: f64,
    pub bottom_m: f64,
    pub top_m: f64,
}

impl Opening {
    pub fn contains(&self, s: f64, v: f64) -> bool {
        s > self.left_m && s < self.right_m && v > self.bottom_m && v < self.top_m
    }

    pub fn area_m2(&self) -> f64 {
        (self.right_m - self.left_m) * (self.top_m - self.bottom_m)
    }
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Wall {
    pub index: usize,
    #[serde(rename = "type")]
    pub wall_type: WallType,
    /// Direction of the outward normal from the room's centre (rad, from world x).
    pub heading_rad: f64,
    /// The outward normal (world x, y): out of the room.
    pub normal_xy: [f64; 2],
    /// Floor corners in world x, y: the left end (s = 0), then the right end (s = width).
    pub corners_xy: [[f64; 2]; 2],
    pub openings: Vec<Opening>,
    /// Windows narrowed to fit beside a door (None when at their configured width).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub narrowed_window_m: Option<f64>,
}

impl Wall {
    pub fn normal(&self) -> DVec2 {
        DVec2::from_array(self.normal_xy)
    }

    /// Along the wall, from the left end to the right end.
    pub fn tangent(&self) -> DVec2 {
        let n = self.normal();
        DVec2::new(n.y, -n.x)
    }

    /// The world point at wall coordinates (s, v), `off` metres inside the room.
    pub fn point(&self, s: f64, v: f64, off: f64) -> DVec3 {
        let left = DVec2::from_array(self.corners_xy[0]);
        let xy = left + self.tangent() * s - self.normal() * off;
        DVec3::new(xy.x, xy.y, v)
    }

    /// World -> wall coordinates: (s, v, distance inside the room from the wall's plane).
    pub fn local(&self, p: DVec3) -> (f64, f64, f64) {
        let left = DVec2::from_array(self.corners_xy[0]);
        let rel = p.truncate() - left;
        (rel.dot(self.tangent()), p.z, -rel.dot(self.normal()))
    }

    pub fn in_opening(&self, s: f64, v: f64) -> bool {
        self.openings.iter().any(|o| o.contains(s, v))
    }
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Room {
    pub walls_count: u32,
    pub seed: u64,
    pub wall_width_m: f64,
    pub wall_height_m: f64,
    /// Distance from the centre (the start point, world origin) to every wall.
    pub apothem_m: f64,
    pub walls: Vec<Wall>,
}

impl Room {
    /// Distance of `xy` inside the room from its nearest wall plane (negative: outside).
    pub fn clearance(&self, xy: DVec2) -> f64 {
        self.nearest_wall(xy).1
    }

    /// The nearest wall plane to `xy` and the distance inside the room from it.
    pub fn nearest_wall(&self, xy: DVec2) -> (usize, f64) {
        self.walls
            .iter()
            .map(|w| (w.index, self.apothem_m - xy.dot(w.normal())))
            .fold((0, f64::INFINITY), |best, next| {
                if next.1 < best.1 { next } else { best }
            })
    }

    /// The wall whose outward normal is nearest the heading `yaw` (rad).
    pub fn facing_wall(&self, yaw: f64) -> usize {
        let step = std::f64::consts::TAU / f64::from(self.walls_count);
        (yaw / step).round().rem_euclid(f64::from(self.walls_count)) as usize
    }
}

/// SplitMix64 (Steele, Lea and Flood, "Fast splittable pseudorandom number generators",
/// OOPSLA 2014): small, fast and fully determined by the seed on every platform.
struct SplitMix64(u64);

impl SplitMix64 {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in 0..=n.
    fn up_to(&mut self, n: u64) -> u64 {
        self.next() % (n + 1)
    }
}

/// The wall distance of the seed: d = (w/2) tan((180 - 360/N)/2 deg), the apothem.
pub fn apothem(walls: u32, width: f64) -> f64 {
    let interior = std::f64::consts::PI - std::f64::consts::TAU / f64::from(walls);
    width / 2.0 * (interior / 2.0).tan()
}

/// Generates the room of `walls` walls for `seed`. Openings keep at least `brush_m` from
/// each other and from the wall's ends; positions are multiples of the layout grid.
pub fn generate_room(
    walls: u32,
    seed: u64,
    config: &RoomConfig,
    brush_m: f64,
) -> Result<Room, RoomError> {
    if walls < 3 {
        return Err(RoomError::TooFewWalls { walls });
    }
    if walls > MAX_WALLS {
        return Err(RoomError::TooManyWalls {
            walls,
            max: MAX_WALLS,
        });
    }
    let width = config.wall_width_m;
    let d = apothem(walls, width);
    let mut rng = SplitMix64(seed);
    let grid = config.layout_grid_m;
    let gap_cells = (brush_m / grid).ceil() as u64;
    let mut built = Vec::with_capacity(walls as usize);
    for index in 0..walls as usize {
        let heading = std::f64::consts::TAU * index as f64 / f64::from(walls);
        let wall_type = match rng.up_to(3) {
            0 => WallType::Blank,
            1 => WallType::Door,
            2 => WallType::TwoWindows,
            _ => WallType::DoorAndTwoWindows,
        };
        let layout = Layout {
            config,
            grid,
            gap_cells,
            wall: index,
            wall_type,
        };
        let (openings, narrowed_window_m) = layout.openings(&mut rng)?;
        let normal = DVec2::from_angle(heading);
        let tangent = DVec2::new(normal.y, -normal.x);
        let centre = normal * d;
        let left = centre - tangent * (width / 2.0);
        let right = centre + tangent * (width / 2.0);
        built.push(Wall {
            index,
            wall_type,
            heading_rad: heading,
            normal_xy: normal.to_array(),
            corners_xy: [left.to_array(), right.to_array()],
            openings,
            narrowed_window_m,
        });
    }
    Ok(Room {
        walls_count: walls,
        seed,
        wall_width_m: width,
        wall_height_m: config.wall_height_m,
        apothem_m: d,
        walls: built,
    })
}

/// Lays out one wall's openings in whole grid cells.
struct Layout<'a> {
    config: &'a RoomConfig,
    grid: f64,
    gap_cells: u64,
    wall: usize,
    wall_type: WallType,
}

impl Layout<'_> {
    fn cells(&self, metres: f64) -> u64 {
        (metres / self.grid).round() as u64
    }

    fn openings(&self, rng: &mut SplitMix64) -> Result<(Vec<Opening>, Option<f64>), RoomError> {
        let c = self.config;
        let door = (OpeningKind::Door, self.cells(c.door_width_m));
        let window = (OpeningKind::Window, self.cells(c.window_width_m));
        let wall_cells = self.cells(c.wall_width_m);
        let mut narrowed = None;
        let row: Vec<(OpeningKind, u64)> = match self.wall_type {
            WallType::Blank => Vec::new(),
            WallType::Door => vec![door],
            WallType::TwoWindows => vec![window, window],
            WallType::DoorAndTwoWindows => {
                // Windows (sill to top) overlap a door in height, so all three stand side by
                // side; where the configured windows do not fit, they are narrowed to fit.
                let free = wall_cells.saturating_sub(door.1 + 4 * self.gap_cells);
                let fitting = (free / 2).min(window.1);
                if fitting < self.gap_cells {
                    return Err(self.no_fit(door.1 + 2 * window.1, 4));
                }
                if fitting < window.1 {
                    narrowed = Some(fitting as f64 * self.grid);
                }
                let narrow = (OpeningKind::Window, fitting);
                match rng.up_to(2) {
                    0 => vec![door, narrow, narrow],
                    1 => vec![narrow, door, narrow],
                    _ => vec![narrow, narrow, door],
                }
            }
        };
        if row.is_empty() {
            return Ok((Vec::new(), narrowed));
        }
        let gaps = row.len() as u64 + 1;
        let used: u64 = row.iter().map(|(_, w)| w).sum::<u64>() + gaps * self.gap_cells;
        let Some(slack) = wall_cells.checked_sub(used) else {
            return Err(self.no_fit(used - gaps * self.gap_cells, gaps as u32));
        };
        // Spread the slack over the gaps at random: `gaps` cut points in 0..=slack.
        let mut cuts: Vec<u64> = (0..row.len()).map(|_| rng.up_to(slack)).collect();
        cuts.sort_unstable();
        let mut openings = Vec::with_capacity(row.len());
        let mut at = 0;
        let mut previous_cut = 0;
        for ((kind, width), cut) in row.into_iter().zip(cuts) {
            at += self.gap_cells + (cut - previous_cut);
            previous_cut = cut;
            let (bottom, top) = match kind {
                OpeningKind::Door => (0.0, c.door_height_m),
                OpeningKind::Window => (c.window_sill_m, c.window_sill_m + c.window_height_m),
            };
            openings.push(Opening {
                kind,
                left_m: at as f64 * self.grid,
                right_m: (at + width) as f64 * self.grid,
                bottom_m: bottom,
                top_m: top,
            });
            at += width;
        }
        Ok((openings, narrowed))
    }

    fn no_fit(&self, needed_cells: u64, gaps: u32) -> RoomError {
        RoomError::OpeningsDoNotFit {
            wall: self.wall,
            kind: self.wall_type.name(),
            needed_m: needed_cells as f64 * self.grid,
            gaps,
            brush_m: self.gap_cells as f64 * self.grid,
            width_m: self.config.wall_width_m,
        }
    }
}
