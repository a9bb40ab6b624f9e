//! The live scene of the painting task: the room's walls with their openings, the painter
//! rig (base, lift, arm) from its rig model, the brush, and the paint as the twin's
//! [`PaintWorld`] measures it. Paint is sampled from the world's contact line at the view's
//! frame rate and sent as one quad per [`PAINT_QUAD_M`] of stroke: the page draws strokes,
//! not the 1 cm coverage grid (the report and the picture have that). It must not plan,
//! move the rig or change the world's measurements.

use super::{PaintWorld, Room};
use crate::rig::Rig;
use crate::scene::{PaintQuad, Point, SceneView, WallView};
use crate::twin::SharedWorld;
use crate::view::{LiveScene, joint_origins_from};
#[cfg(test)]
use glam::DVec3;
use glam::{DAffine3, DVec2};
use std::sync::PoisonError;

/// Length of stroke each paint quad covers (m): a 2.5 m stroke is ten quads.
pub const PAINT_QUAD_M: f64 = 0.25;
/// The painter rig's joints that carry the arm around the room (x, y, yaw): drawn as the
/// base's position, not as links from the world origin.
const BASE_AXES: usize = 3;

/// The stroke being painted: where its last quad ended, and where the brush is now.
#[derive(Debug, Clone, Copy)]
struct OpenStroke {
    contact: u64,
    wall: usize,
    emitted: [DVec2; 2],
    latest: [DVec2; 2],
}

pub struct PaintScene {
    rig: Rig,
    room: Room,
    world: SharedWorld<PaintWorld>,
    open: Option<OpenStroke>,
    painted: Vec<PaintQuad>,
}

impl PaintScene {
    pub fn new(rig: Rig, world: SharedWorld<PaintWorld>) -> Self {
        let room = world
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .room()
            .clone();
        PaintScene {
            rig,
            room,
            world,
            open: None,
            painted: Vec::new(),
        }
    }

    /// The quad from contact line `from` to `to`, always wound the same way on its wall
    /// (counter-clockwise in wall coordinates): the page fills a wall's paint as one path, and
    /// overlapping quads of opposite windings (an up stroke beside a down stroke) would cancel.
    fn quad(&self, wall: usize, from: [DVec2; 2], to: [DVec2; 2]) -> PaintQuad {
        let wall_geometry = &self.room.walls[wall];
        let at = |p: DVec2| wall_geometry.point(p.x, p.y, 0.0).to_array();
        let corners = [from[0], from[1], to[1], to[0]];
        let twice_area: f64 = (0..4)
            .map(|i| corners[i].perp_dot(corners[(i + 1) % 4]))
            .sum();
        let [a, b, c, d] = corners.map(at);
        PaintQuad {
            wall,
            quad: if twice_area >= 0.0 {
                [a, b, c, d]
            } else {
                [d, c, b, a]
            },
        }
    }

    fn close(&mut self, stroke: OpenStroke, fresh: &mut Vec<PaintQuad>) {
        if stroke.latest != stroke.emitted {
            fresh.push(self.quad(stroke.wall, stroke.emitted, stroke.latest));
        }
    }
}

fn wall_view(room: &Room, wall: usize) -> WallView {
    let w = &room.walls[wall];
    let (width, height) = (room.wall_width_m, room.wall_height_m);
    let rect = |left: f64, right: f64, bottom: f64, top: f64| -> [Point; 4] {
        [
            w.point(left, bottom, 0.0).to_array(),
            w.point(right, bottom, 0.0).to_array(),
            w.point(right, top, 0.0).to_array(),
            w.point(left, top, 0.0).to_array(),
        ]
    };
    WallView {
        // Left to right along the wall, then up: counter-clockwise seen from inside the room.
        corners: rect(0.0, width, 0.0, height),
        openings: w
            .openings
            .iter()
            .map(|o| rect(o.left_m, o.right_m, o.bottom_m, o.top_m))
            .collect(),
    }
}

impl LiveScene for PaintScene {
    fn scene(&self) -> SceneView {
        SceneView {
            walls: (0..self.room.walls.len())
                .map(|wall| wall_view(&self.room, wall))
                .collect(),
            paint: self.painted.clone(),
            ..SceneView::default()
        }
    }

    /// The base and lift column, the arm to tool0, then the brush: handle and contact line.
    fn chains(&self, actual: &[f64]) -> Vec<Vec<Point>> {
        let arm = joint_origins_from(&self.rig, actual, BASE_AXES);
        let Ok(tool0) = self.rig.forward(actual) else {
            return vec![arm];
        };
        let world = self.world.lock().unwrap_or_else(PoisonError::into_inner);
        let [a, b] = world.body().brush.contact(&tool0);
        let handle_end = (a + b) / 2.0;
        vec![
            arm,
            vec![tool0_point(&tool0), handle_end.to_array()],
            vec![a.to_array(), b.to_array()],
        ]
    }

    fn drain_paint(&mut self) -> Vec<PaintQuad> {
        let contact = self
            .world
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .contact();
        let mut fresh = Vec::new();
        match (self.open, contact) {
            (Some(open), Some((episode, wall, ends))) if open.contact == episode => {
                let mut open = OpenStroke {
                    latest: ends,
                    ..open
                };
                if open.emitted[0].distance(ends[0]) >= PAINT_QUAD_M {
                    fresh.push(self.quad(wall, open.emitted, ends));
                    open.emitted = ends;
                }
                self.open = Some(open);
            }
            (open, contact) => {
                if let Some(open) = open {
                    self.close(open, &mut fresh);
                }
                self.open = contact.map(|(contact, wall, ends)| OpenStroke {
                    contact,
                    wall,
                    emitted: ends,
                    latest: ends,
                });
            }
        }
        self.painted.extend_from_slice(&fresh);
        fresh
    }
}

fn tool0_point(tool0: &DAffine3) -> Point {
    tool0.translation.to_array()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::apps::paint::{load_paint_settings, plan_room, world_for};
    use crate::trajectory::PlanSettings;
    use crate::twin::TwinWorld;
    use std::path::Path;
    use std::sync::{Arc, Mutex};

    /// The planned motion of a 3-wall room, fed straight to the world (two samples per
    /// view frame, as at 100 Hz), with the view draining paint as it goes.
    #[test]
    fn paint_quads_follow_the_measured_paint_and_stay_out_of_openings() {
        let file = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/paint.toml");
        let paint = load_paint_settings(&file).expect("config/paint.toml loads");
        let start = vec![0.0; paint.rig.dof()];
        let settings = PlanSettings {
            period: std::time::Duration::from_millis(10),
            ..PlanSettings::default()
        };
        let (room, plan) = plan_room(&paint, 3, 0, &start, &settings).expect("room plans");
        let world = Arc::new(Mutex::new(
            world_for(&paint, &room).expect("the painter's model builds"),
        ));
        let mut scene = PaintScene::new(paint.rig.clone(), world.clone());
        assert_eq!(scene.scene().walls.len(), 3);
        let mut quads = Vec::new();
        for sample in 0..plan.trajectory.len() {
            world
                .lock()
                .expect("the world lock is not poisoned")
                .observe(&plan.trajectory.position(sample));
            if sample % 2 == 1 {
                quads.extend(scene.drain_paint());
            }
        }
        quads.extend(scene.drain_paint());
        assert_eq!(scene.scene().paint, quads);
        let quad_area: f64 = quads.iter().map(|q| area(&q.quad)).sum();
        let painted: f64 = world
            .lock()
            .expect("the world lock is not poisoned")
            .grids()
            .iter()
            .map(|g| g.stats().painted_m2)
            .sum();
        assert!(painted > 10.0, "painted {painted} m2");
        // Neighbouring strokes overlap, so the quads cover more than the paint, never less.
        assert!(
            quad_area >= 0.98 * painted && quad_area <= 1.6 * painted,
            "quads {quad_area} m2 against {painted} m2 painted"
        );
        for quad in &quads {
            let wall = &room.walls[quad.wall];
            let local: Vec<_> = quad
                .quad
                .iter()
                .map(|p| wall.local(DVec3::from_array(*p)))
                .collect();
            assert!(local.iter().all(|(_, _, off)| off.abs() < 1e-6));
            // One winding for all (the page fills a wall's quads as one nonzero path).
            let twice_area: f64 = (0..4)
                .map(|i| {
                    let (a, b) = (local[i], local[(i + 1) % 4]);
                    a.0 * b.1 - a.1 * b.0
                })
                .sum();
            assert!(twice_area >= 0.0, "quad wound clockwise: {quad:?}");
            let centre_s = local.iter().map(|l| l.0).sum::<f64>() / 4.0;
            let centre_v = local.iter().map(|l| l.1).sum::<f64>() / 4.0;
            assert!(
                !wall.in_opening(centre_s, centre_v),
                "quad in an opening: {quad:?}"
            );
        }
    }

    fn area(quad: &[Point; 4]) -> f64 {
        let [a, b, c, d] = quad.map(DVec3::from_array);
        ((c - a).cross(d - b)).length() / 2.0
    }
}
