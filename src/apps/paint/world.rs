//! The twin paints: a [`TwinWorld`] that, every controller cycle, takes the twin's actual
//! joint positions (base, lift and arm), finds where the brush's contact line touches a
//! wall, and marks the coverage grid swept since the previous cycle. It also checks the
//! body against the walls and the floor on the one collision model (collisions, counted as episodes;
//! `body.rs`) and the positions against the axis limits.
//!
//! Sweeping, not point sampling: each cycle marks every cell whose centre lies in the area
//! the contact line swept since the last cycle, so the result does not depend on the
//! brush's speed or the cycle rate. Owns the measurements; must not change the twin.

use super::body::{Body, Scratch};
use super::room::Room;
use crate::rig::Rig;
use crate::twin::TwinWorld;
use glam::DVec2;
use serde::Serialize;

/// One wall's coverage grid: `cols` x `rows` cells of `cell` metres, row-major from the
/// bottom-left (s = 0, v = 0).
#[derive(Debug, Clone)]
pub struct WallGrid {
    pub cols: usize,
    pub rows: usize,
    pub cell: f64,
    pub painted: Vec<bool>,
    pub opening: Vec<bool>,
}

impl WallGrid {
    fn new(room: &Room, wall: usize, cell: f64) -> Self {
        let cols = (room.wall_width_m / cell).round() as usize;
        let rows = (room.wall_height_m / cell).round() as usize;
        let mut opening = vec![false; cols * rows];
        for row in 0..rows {
            for col in 0..cols {
                let (s, v) = ((col as f64 + 0.5) * cell, (row as f64 + 0.5) * cell);
                opening[row * cols + col] = room.walls[wall].in_opening(s, v);
            }
        }
        Self {
            cols,
            rows,
            cell,
            painted: vec![false; cols * rows],
            opening,
        }
    }

    /// Marks every cell whose centre lies inside the convex polygon `hull` (counter-
    /// clockwise, wall coordinates).
    fn fill(&mut self, hull: &[DVec2]) {
        if hull.len() < 3 {
            return;
        }
        let (lo, hi) = hull.iter().fold(
            (DVec2::splat(f64::INFINITY), DVec2::splat(f64::NEG_INFINITY)),
            |(lo, hi), p| (lo.min(*p), hi.max(*p)),
        );
        let index = |x: f64, count: usize| (x / self.cell - 0.5).clamp(0.0, count as f64);
        let (c0, c1) = (
            index(lo.x, self.cols).ceil() as usize,
            index(hi.x, self.cols).floor() as usize,
        );
        let (r0, r1) = (
            index(lo.y, self.rows).ceil() as usize,
            index(hi.y, self.rows).floor() as usize,
        );
        for row in r0..=r1.min(self.rows.saturating_sub(1)) {
            for col in c0..=c1.min(self.cols.saturating_sub(1)) {
                let centre = DVec2::new(
                    (col as f64 + 0.5) * self.cell,
                    (row as f64 + 0.5) * self.cell,
                );
                if inside(hull, centre) {
                    self.painted[row * self.cols + col] = true;
                }
            }
        }
    }

    pub fn stats(&self) -> CoverageStats {
        let area = self.cell * self.cell;
        let (mut paintable, mut painted, mut in_openings) = (0u64, 0u64, 0u64);
        for (p, o) in self.painted.iter().zip(&self.opening) {
            match (*p, *o) {
                (true, true) => in_openings += 1,
                (true, false) => {
                    painted += 1;
                    paintable += 1;
                }
                (false, false) => paintable += 1,
                (false, true) => {}
            }
        }
        CoverageStats {
            paintable_m2: paintable as f64 * area,
            painted_m2: painted as f64 * area,
            coverage: if paintable == 0 {
                1.0
            } else {
                painted as f64 / paintable as f64
            },
            paint_in_openings_m2: in_openings as f64 * area,
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct CoverageStats {
    pub paintable_m2: f64,
    pub painted_m2: f64,
    pub coverage: f64,
    pub paint_in_openings_m2: f64,
}

/// Inside (or on the edge of) a counter-clockwise convex polygon.
fn inside(hull: &[DVec2], p: DVec2) -> bool {
    hull.iter()
        .zip(hull.iter().cycle().skip(1))
        .all(|(a, b)| (*b - *a).perp_dot(p - *a) >= -1e-12)
}

/// Convex hull, counter-clockwise, of a few points (Andrew's monotone chain).
fn convex_hull(points: &mut [DVec2]) -> Vec<DVec2> {
    points.sort_by(|a, b| a.x.total_cmp(&b.x).then(a.y.total_cmp(&b.y)));
    let mut hull: Vec<DVec2> = Vec::with_capacity(points.len() * 2);
    for pass in 0..2 {
        let start = hull.len();
        let ordered: Box<dyn Iterator<Item = &DVec2>> = if pass == 0 {
            Box::new(points.iter())
        } else {
            Box::new(points.iter().rev())
        };
        for &p in ordered {
            while hull.len() >= start + 2 {
                let (a, b) = (hull[hull.len() - 2], hull[hull.len() - 1]);
                if (b - a).perp_dot(p - a) <= 1e-15 {
                    hull.pop();
                } else {
                    break;
                }
            }
            hull.push(p);
        }
        hull.pop();
    }
    hull
}

/// What the twin measured.
#[derive(Debug, Clone, Serialize)]
pub struct Measurements {
    pub cycles: u64,
    pub painting_cycles: u64,
    /// Episodes: runs of consecutive cycles in which some part of the body pierced a wall
    /// or the floor.
    pub collisions: u64,
    pub collision_cycles: u64,
    /// The smallest clearance between the body and any wall or the floor over the run (m).
    pub min_clearance_m: f64,
    /// Cycles whose actual position lay outside some axis limit.
    pub limit_violations: u64,
    /// Collision episodes by the wall pierced.
    pub collisions_by_wall: Vec<u64>,
    /// Collision episodes that began with the floor pierced.
    pub floor_collisions: u64,
    /// Limit violations by the wall the base faced (nearest heading to its yaw).
    pub limit_violations_by_wall: Vec<u64>,
}

pub struct PaintWorld {
    rig: Rig,
    room: Room,
    body: Body,
    scratch: Scratch,
    tolerance: f64,
    grids: Vec<WallGrid>,
    previous: Option<(usize, [DVec2; 2])>,
    /// Contact episodes so far: a new one starts whenever the brush lands on a wall.
    contacts: u64,
    in_collision: bool,
    measured: Measurements,
}

impl PaintWorld {
    pub fn new(rig: &Rig, room: &Room, body: &Body, tolerance: f64, cell: f64) -> Self {
        Self {
            rig: rig.clone(),
            room: room.clone(),
            body: body.clone(),
            scratch: Scratch::new(rig, body),
            tolerance,
            grids: (0..room.walls.len())
                .map(|w| WallGrid::new(room, w, cell))
                .collect(),
            previous: None,
            contacts: 0,
            in_collision: false,
            measured: Measurements {
                cycles: 0,
                painting_cycles: 0,
                collisions: 0,
                collision_cycles: 0,
                min_clearance_m: f64::INFINITY,
                limit_violations: 0,
                collisions_by_wall: vec![0; room.walls.len()],
                floor_collisions: 0,
                limit_violations_by_wall: vec![0; room.walls.len()],
            },
        }
    }

    pub fn grids(&self) -> &[WallGrid] {
        &self.grids
    }

    pub fn measurements(&self) -> &Measurements {
        &self.measured
    }

    pub fn room(&self) -> &Room {
        &self.room
    }

    pub fn body(&self) -> &Body {
        &self.body
    }

    /// The brush's contact line as of the last cycle (its wall, and its ends in that wall's
    /// coordinates), with the number of the contact episode it belongs to.
    pub fn contact(&self) -> Option<(u64, usize, [DVec2; 2])> {
        self.previous
            .map(|(wall, ends)| (self.contacts, wall, ends))
    }

    /// The wall the contact line lies on (both ends within the tolerance of its plane,
    /// and within its extent), with the ends in its coordinates.
    fn contact_wall(&self, ends: [glam::DVec3; 2]) -> Option<(usize, [DVec2; 2])> {
        let extent = self.room.wall_width_m;
        self.room.walls.iter().find_map(|wall| {
            let a = wall.local(ends[0]);
            let b = wall.local(ends[1]);
            let touching = a.2.abs() <= self.tolerance && b.2.abs() <= self.tolerance;
            let within = [a.0, b.0]
                .iter()
                .all(|s| *s >= -self.tolerance && *s <= extent + self.tolerance);
            (touching && within).then(|| (wall.index, [DVec2::new(a.0, a.1), DVec2::new(b.0, b.1)]))
        })
    }
}

impl TwinWorld for PaintWorld {
    fn observe(&mut self, actual: &[f64]) {
        self.measured.cycles += 1;
        if self.rig.first_limit_violation(actual).is_some() {
            self.measured.limit_violations += 1;
            let facing = self.room.facing_wall(actual[2]);
            self.measured.limit_violations_by_wall[facing] += 1;
        }
        let (clearance, tool0) = self.body.clearance(actual, &mut self.scratch);
        self.measured.min_clearance_m = self.measured.min_clearance_m.min(clearance);
        let colliding = clearance < 0.0;
        if colliding {
            self.measured.collision_cycles += 1;
            if !self.in_collision {
                self.measured.collisions += 1;
                match self.body.nearest_wall(&self.scratch) {
                    Some(pierced) => self.measured.collisions_by_wall[pierced] += 1,
                    None => self.measured.floor_collisions += 1,
                }
            }
        }
        self.in_collision = colliding;
        let contact = self.contact_wall(self.body.brush.contact(&tool0));
        if let (Some((wall, now)), Some((before_wall, before))) = (contact, self.previous)
            && wall == before_wall
        {
            self.measured.painting_cycles += 1;
            let mut corners = [before[0], before[1], now[0], now[1]];
            let hull = convex_hull(&mut corners);
            self.grids[wall].fill(&hull);
        }
        if contact.is_some_and(|(wall, _)| self.previous.is_none_or(|(before, _)| before != wall)) {
            self.contacts += 1;
        }
        self.previous = contact;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hull_of_a_swept_segment_is_its_parallelogram() {
        let mut points = [
            DVec2::new(0.0, 0.0),
            DVec2::new(1.0, 0.0),
            DVec2::new(0.0, 0.5),
            DVec2::new(1.0, 0.5),
        ];
        let hull = convex_hull(&mut points);
        assert_eq!(hull.len(), 4);
        assert!(inside(&hull, DVec2::new(0.5, 0.25)));
        assert!(!inside(&hull, DVec2::new(0.5, 0.6)));
    }
}
