//! The painter's body and brush from its joint positions: the brush's contact line (the
//! geometry of coverage, the task's own), and its collision envelope on the project's one
//! collision model (issue 27): the painter rig's link bodies and the brush's handle, as
//! tool, against the room's walls and floor as cell objects ([`room_cell`]), with their
//! clearance.
//!
//! Owns the envelope both the planner and the twin's world use, so the planner checks
//! exactly what the twin measures. Must not decide what is acceptable: callers compare the
//! clearance with zero (the twin) or a margin (the planner).

use super::config::{EXTRA_AXES, PaintConfig};
use super::room::Room;
use crate::cell::{Cell, CellError, CellObject, Clearance, CollisionModel, FLOOR, Tool};
use crate::rig::{Collision, JointAxis, JointKind, Rig, Shape};
use glam::{DAffine3, DVec3};
use std::sync::Arc;

/// Rounding allowance (m) when a bound rules a sample out: clearances are sums of a few
/// products of numbers of metres, off by about 1e-15 m each, so 1e-9 m covers them many
/// times over while ruling out almost nothing a real margin would not.
const BOUND_ROUNDING_M: f64 = 1e-9;

/// The brush on tool0: contact line of `width` at `handle` along tool0's z axis, along
/// tool0's x axis.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Brush {
    pub width: f64,
    pub handle: f64,
    pub bristle: f64,
    pub handle_radius: f64,
}

impl Brush {
    pub fn from_config(config: &PaintConfig) -> Self {
        Self {
            width: config.brush.width_m,
            handle: config.brush.handle_m,
            bristle: config.brush.bristle_m,
            handle_radius: config.brush.handle_radius_m,
        }
    }

    /// The contact line's two ends, from the tool0 frame.
    pub fn contact(&self, tool0: &DAffine3) -> [DVec3; 2] {
        let centre = tool0.transform_point3(DVec3::Z * self.handle);
        let half = tool0.transform_vector3(DVec3::X) * (self.width / 2.0);
        [centre - half, centre + half]
    }

    /// tool0 for a brush with contact centre `centre`, contact line along `line` and
    /// `into_wall` from tool0 to the contact (both unit, perpendicular).
    pub fn tool0_for(&self, centre: DVec3, line: DVec3, into_wall: DVec3) -> DAffine3 {
        let y = into_wall.cross(line);
        DAffine3::from_cols(line, y, into_wall, centre - into_wall * self.handle)
    }
}

/// The name of wall `index` as a body of the paint task's cell.
pub fn wall_name(index: usize) -> String {
    format!("wall_{index}")
}

/// The floor the painter stands on: the room frame's z = 0 (the lift's zero, the walls'
/// v = 0), solid below, named as the built-in cell's floor so that a run cell giving the
/// same floor and a paint room merge into one object ([`merge_room`]).
pub fn room_floor() -> CellObject {
    CellObject {
        name: FLOOR.to_string(),
        pose: DAffine3::IDENTITY,
        shape: Shape::HalfSpace { normal: DVec3::Z },
    }
}

/// `cell` (a run's cell, whose mount places the painter's base frame, the room frame) with
/// the paint task's `room` cell added: its walls and floor placed in the cell frame, its
/// brush as the tool and its allowed pairs. An object of the room that the cell already
/// holds, the same name at the same place with the same shape (the floor a painter's cell
/// file gives), is one object and kept once; any other clash of names is left to the model,
/// which refuses it naming the name. The margin stays the cell's.
pub fn merge_room(cell: &Cell, room: &Cell) -> Cell {
    let mut merged = cell.clone();
    for object in &room.objects {
        let placed = CellObject {
            pose: cell.mount * object.pose,
            ..object.clone()
        };
        if !cell.objects.contains(&placed) {
            merged.objects.push(placed);
        }
    }
    merged
        .allowed_pairs
        .extend(room.allowed_pairs.iter().cloned());
    merged.tool = room.tool.clone();
    merged
}

/// The name of the brush's handle, the tool of the paint task's cell.
pub const BRUSH: &str = "brush";

/// The paint task's cell for `room`: its walls as half-spaces (the solid outside the room)
/// and the floor the painter stands on (the half-space below the room frame's z = 0, named
/// as every cell's floor), the brush's handle as the tool (its bristles, which touch the
/// walls on purpose, left out), the planning clearance as the margin, and every pair of
/// the painter's own bodies (the brush's included) allowed: the task checks its body
/// against its room, the walls and the floor each with its own travel bound
/// ([`RoomTravel`]).
pub fn room_cell(rig: &Rig, room: &Room, config: &PaintConfig) -> Cell {
    let handle_end = config.brush.handle_m - config.brush.bristle_m;
    let walls = room.walls.iter().map(|wall| {
        let out = wall.normal().extend(0.0);
        CellObject {
            name: wall_name(wall.index),
            pose: DAffine3::from_translation(out * room.apothem_m),
            // Solid where `p . normal <= 0`: beyond the wall's plane, outside the room.
            shape: Shape::HalfSpace { normal: -out },
        }
    });
    let objects = walls.chain([room_floor()]).collect();
    let own: Vec<&str> = rig
        .bodies
        .iter()
        .map(|b| b.name.as_str())
        .chain([BRUSH])
        .collect();
    let allowed_pairs = own
        .iter()
        .enumerate()
        .flat_map(|(i, a)| own[i + 1..].iter().map(|b| (a.to_string(), b.to_string())))
        .collect();
    Cell {
        mount: DAffine3::IDENTITY,
        objects,
        tool: Some(Tool {
            name: BRUSH.to_string(),
            bodies: vec![Collision {
                origin: DAffine3::IDENTITY,
                shape: Shape::Capsule {
                    a: DVec3::ZERO,
                    b: DVec3::Z * handle_end,
                    radius: config.brush.handle_radius_m,
                },
            }],
            tcp: DAffine3::IDENTITY,
        }),
        margin_m: config.body.planning_clearance_m,
        allowed_pairs,
        targets: crate::cell::Targets::default(),
        parts: Vec::new(),
        gripper: crate::cell::Gripper::default(),
    }
}

/// The painter's collision envelope in one room: the one collision model (issue 27) of the
/// rig's link bodies (`config/painter.toml`) and the brush's handle against the room's
/// walls and floor, and the brush's contact line.
#[derive(Debug, Clone)]
pub struct Body {
    pub brush: Brush,
    model: Arc<CollisionModel>,
    /// The same bodies against the walls alone and against the floor alone, by [`Part`]:
    /// the planner's sweeps measure each part with its own bound ([`RoomTravel`]).
    parts: [Arc<CollisionModel>; 2],
    /// The wall each body of the model is, by body id (`None`: the painter's own).
    walls: Vec<Option<usize>>,
    /// How far the base's bodies reach from its vertical axis in the floor plan.
    base_radius: f64,
}

impl Body {
    pub fn new(rig: &Rig, room: &Room, config: &PaintConfig) -> Result<Self, CellError> {
        let cell = room_cell(rig, room, config);
        let model = CollisionModel::new(rig, &cell)?;
        let part = |part: Part| {
            let objects = cell.objects.iter().filter(|o| Part::of(o) == part);
            let cell = Cell {
                objects: objects.cloned().collect(),
                ..cell.clone()
            };
            CollisionModel::new(rig, &cell).map(Arc::new)
        };
        let parts = [part(Part::Walls)?, part(Part::Floor)?];
        let walls = (0..model.body_count())
            .map(|id| {
                room.walls
                    .iter()
                    .find(|w| model.body_name(id) == wall_name(w.index))
                    .map(|w| w.index)
            })
            .collect();
        // The base's bodies ride on the frames before the lift (base x, y and heading).
        let base_radius = rig
            .bodies
            .iter()
            .filter(|body| body.frame >= 1 && body.frame < EXTRA_AXES)
            .flat_map(|body| &body.collisions)
            .map(|c| {
                c.origin.translation.truncate().length()
                    + match c.shape {
                        Shape::Cylinder { radius, .. } | Shape::Sphere { radius } => radius,
                        ref other => other.bounding_radius().unwrap_or(0.0),
                    }
            })
            .fold(0.0, f64::max);
        Ok(Self {
            brush: Brush::from_config(config),
            model: Arc::new(model),
            parts,
            walls,
            base_radius,
        })
    }

    pub fn model(&self) -> &CollisionModel {
        &self.model
    }

    /// How far the base reaches from its vertical axis in the floor plan (m): where it may
    /// stand is planned with it.
    pub fn base_radius(&self) -> f64 {
        self.base_radius
    }

    /// The closest pair of the painter and a wall or the floor (negative when it pierces
    /// one), and tool0. The room is convex, so inside every wall's plane is inside the room.
    pub fn clearance(&self, positions: &[f64], scratch: &mut Scratch) -> (f64, DAffine3) {
        let tool0 = scratch
            .rig
            .forward_with_axes(positions, &mut scratch.axes)
            .unwrap_or(DAffine3::IDENTITY);
        (self.distance(positions, scratch), tool0)
    }

    /// The closest pair's distance alone, as [`Body::clearance`] without tool0.
    pub fn distance(&self, positions: &[f64], scratch: &mut Scratch) -> f64 {
        scratch.last = self.model.clearance(positions, &mut scratch.model);
        scratch.last.distance_m
    }

    /// The closest pair's distance against one part of the room alone (the painter's
    /// distance from the room is the lower of the two parts'): what the planner's sweeps
    /// measure, each part when its own bound cannot place it clear ([`RoomTravel`]).
    pub fn part_distance(&self, part: Part, positions: &[f64], scratch: &mut Scratch) -> f64 {
        let index = part as usize;
        let model_scratch = &mut scratch.parts[index];
        self.parts[index]
            .clearance(positions, model_scratch)
            .distance_m
    }

    /// The wall of the closest pair of the last [`Body::clearance`] call; `None` when that
    /// pair is not against a wall (the floor).
    pub fn nearest_wall(&self, scratch: &Scratch) -> Option<usize> {
        let last = scratch.last;
        [last.a, last.b]
            .iter()
            .find_map(|id| self.walls.get(*id).copied().flatten())
    }
}

/// Reusable buffers for body checks (no allocation per call), with the rig they use.
pub struct Scratch {
    pub rig: Rig,
    pub axes: Vec<JointAxis>,
    model: crate::cell::Scratch,
    /// The part models' buffers, by [`Part`].
    parts: [crate::cell::Scratch; 2],
    last: Clearance,
}

impl Scratch {
    pub fn new(rig: &Rig, body: &Body) -> Self {
        Self {
            rig: rig.clone(),
            axes: Vec::with_capacity(rig.dof()),
            model: body.model.scratch(),
            parts: [body.parts[0].scratch(), body.parts[1].scratch()],
            last: Clearance::NONE,
        }
    }
}

/// A part of the room the body's clearance is measured against, each with its own bound
/// on how fast that clearance can change ([`RoomTravel`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Part {
    /// The walls: vertical half-spaces, whose distance only motion over the floor plan
    /// changes.
    Walls = 0,
    /// The floor: a horizontal half-space, whose distance only motion up or down changes.
    Floor = 1,
}

impl Part {
    /// The part `object` of a paint room's cell ([`room_cell`]) belongs to.
    fn of(object: &CellObject) -> Part {
        if object.name == FLOOR {
            Part::Floor
        } else {
            Part::Walls
        }
    }
}

/// How far the body's clearance from the room can change between two joint positions: the
/// walls' part by motion over the floor plan ([`Travel::planar`]), the floor's by motion up
/// or down ([`Travel::vertical`]). One bound for the whole room would have to count the
/// lift's stroke against the walls too, and every lift-only move (the held arm carried up a
/// stroke) would be measured every few samples; apart, a lift move leaves the walls'
/// clearance where it was measured, and carries the floor's up with it.
#[derive(Debug, Clone)]
pub struct RoomTravel {
    /// By [`Part`].
    parts: [Travel; 2],
}

impl RoomTravel {
    pub fn new(rig: &Rig, brush: &Brush) -> Self {
        Self {
            parts: [Travel::planar(rig, brush), Travel::vertical(rig, brush)],
        }
    }

    /// The least clearance from the room (`measure` of a part, the lower of the two) of
    /// `samples`, exactly, when that is at most `needed`; otherwise some value above
    /// `needed`. A part of a sample whose bound from that part's last measured sample
    /// places it above both `needed` and the least so far is not measured.
    pub fn lowest<Q: AsRef<[f64]>>(
        &self,
        samples: impl IntoIterator<Item = Q>,
        needed: f64,
        mut measure: impl FnMut(Part, &[f64]) -> f64,
    ) -> f64 {
        let mut anchors = Anchors::new(&self.parts);
        let mut worst = f64::INFINITY;
        for sample in samples {
            let least = anchors.visit(sample.as_ref(), needed.min(worst), |i, p| {
                measure(PARTS[i], p)
            });
            worst = worst.min(least);
        }
        worst
    }

    /// The first of `samples` (index, positions) whose clearance from the room is below
    /// `needed`, with that clearance; parts the bound places above it are not measured.
    pub fn first_below<Q: AsRef<[f64]>>(
        &self,
        samples: impl IntoIterator<Item = (usize, Q)>,
        needed: f64,
        mut measure: impl FnMut(Part, &[f64]) -> f64,
    ) -> Option<(usize, f64)> {
        let mut anchors = Anchors::new(&self.parts);
        samples.into_iter().find_map(|(index, sample)| {
            let least = anchors.visit(sample.as_ref(), needed, |i, p| measure(PARTS[i], p));
            (least < needed).then_some((index, least))
        })
    }
}

/// The parts in [`RoomTravel::parts`]'s order.
const PARTS: [Part; 2] = [Part::Walls, Part::Floor];

/// How far the body, the brush's contact line and the base's axis can move between two
/// joint positions of the rig (both within its limits), over the floor plan
/// ([`Travel::planar`]) or up and down ([`Travel::vertical`]): a distance from a vertical
/// plane (a wall's) changes by no more than the first, one from a horizontal plane (the
/// floor's) by no more than the second. Lets a sweep over a trajectory measure only the
/// samples a bound from the last measured one cannot place clear.
#[derive(Debug, Clone)]
pub struct Travel {
    /// Per joint: how far (m) the farthest point after it moves, in the bound's directions,
    /// per unit of its motion.
    levers: Vec<f64>,
    /// Whether the base's axis (a vertical line) counts: it moves over the floor plan only.
    base_axis: bool,
}

/// The directions a [`Travel`] bounds motion in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Directions {
    Planar,
    Vertical,
}

impl Travel {
    /// The bound on motion over the floor plan: what a distance from a wall's (vertical)
    /// plane needs (the lift moves nothing in the floor plan).
    pub fn planar(rig: &Rig, brush: &Brush) -> Self {
        Self::new(rig, brush, Directions::Planar)
    }

    /// The bound on motion up and down: what a distance from the floor's plane needs (the
    /// base's drives and its turn move nothing up or down; the lift everything on it by
    /// its stroke).
    pub fn vertical(rig: &Rig, brush: &Brush) -> Self {
        Self::new(rig, brush, Directions::Vertical)
    }

    /// A revolute joint moves a point by at most the angle times its distance from the
    /// joint's origin, which the links, prismatic strokes (at their limits), tool and brush
    /// after it bound whatever the other joints do; a prismatic joint by its stroke. Over
    /// the floor plan, a joint whose axis stays vertical whatever the joints before it do
    /// moves no point if prismatic, and a point by the angle times its distance from the
    /// axis if revolute (which a vertical stroke after it leaves alone). Up and down, a
    /// revolute joint whose axis stays vertical moves nothing, nor does a prismatic one
    /// whose axis stays level.
    fn new(rig: &Rig, brush: &Brush, directions: Directions) -> Self {
        let lie = axis_lie(rig);
        let vertical: Vec<bool> = lie.iter().map(|l| *l == Lie::Vertical).collect();
        let brush_reach = brush.handle.hypot(brush.width / 2.0);
        let tool_reach = rig.tool.translation.length() + brush_reach;
        // Each frame's bodies reach this far from its origin (a link's, a base's).
        let mut body_reach = vec![0.0f64; rig.dof() + 1];
        for body in &rig.bodies {
            for c in &body.collisions {
                let reach =
                    c.origin.translation.length() + c.shape.bounding_radius().unwrap_or(0.0);
                body_reach[body.frame] = body_reach[body.frame].max(reach);
            }
        }
        let levers = (0..rig.dof())
            .map(|j| {
                let joint = &rig.joints[j];
                let still = match (directions, joint.kind) {
                    (Directions::Planar, JointKind::Prismatic) => lie[j] == Lie::Vertical,
                    (Directions::Vertical, JointKind::Prismatic) => lie[j] == Lie::Level,
                    (Directions::Vertical, JointKind::Revolute) => lie[j] == Lie::Vertical,
                    (Directions::Planar, JointKind::Revolute) => false,
                };
                if still {
                    return 0.0;
                }
                if joint.kind == JointKind::Prismatic {
                    return joint.axis.length();
                }
                // From joint j's axis to frame k's origin (k > j), at most the links between.
                let mut along = 0.0;
                let mut farthest = 0.0f64;
                for k in j + 1..=rig.dof() {
                    let link = &rig.joints[k - 1];
                    if k > j + 1 {
                        let stroke = match link.kind {
                            // Along a vertical axis it never leaves a vertical one.
                            JointKind::Prismatic if !(vertical[j] && vertical[k - 1]) => {
                                link.limits.lower.abs().max(link.limits.upper.abs())
                                    * link.axis.length()
                            }
                            _ => 0.0,
                        };
                        along += link.origin.translation.length() + stroke;
                    }
                    farthest = farthest.max(along + body_reach[k]);
                }
                // Frame dof's origin is the last joint's: the tool hangs from it.
                let links: f64 = (j + 1..rig.dof())
                    .map(|k| {
                        let link = &rig.joints[k];
                        let stroke = match link.kind {
                            JointKind::Prismatic if !(vertical[j] && vertical[k]) => {
                                link.limits.lower.abs().max(link.limits.upper.abs())
                                    * link.axis.length()
                            }
                            _ => 0.0,
                        };
                        link.origin.translation.length() + stroke
                    })
                    .sum();
                farthest.max(links + tool_reach)
            })
            .collect();
        Self {
            levers,
            base_axis: directions == Directions::Planar,
        }
    }

    /// At least how far (m) any point of the body or brush moves (over the floor plan or up
    /// and down, as built) from joint positions `a` to `b`.
    pub fn between(&self, a: &[f64], b: &[f64]) -> f64 {
        let joints: f64 = self
            .levers
            .iter()
            .zip(a.iter().zip(b))
            .map(|(lever, (x, y))| lever * (y - x).abs())
            .sum();
        if !self.base_axis {
            return joints;
        }
        // The base's axis is (x, y) = the first two positions, outside the chain.
        let base = (b[0] - a[0]).abs() + (b[1] - a[1]).abs();
        joints.max(base)
    }

    /// The least `measure` (a clearance: moving a point by d changes it by at most d) of
    /// `samples`, exactly, when that is at most `needed`; otherwise some value above
    /// `needed`. Samples the bound from the last measured one places above both `needed`
    /// and the least so far are not measured: they can change neither answer.
    pub fn lowest<Q: AsRef<[f64]>>(
        &self,
        samples: impl IntoIterator<Item = Q>,
        needed: f64,
        mut measure: impl FnMut(&[f64]) -> f64,
    ) -> f64 {
        let mut anchors = Anchors::new(std::slice::from_ref(self));
        let mut worst = f64::INFINITY;
        for sample in samples {
            let least = anchors.visit(sample.as_ref(), needed.min(worst), |_, p| measure(p));
            worst = worst.min(least);
        }
        worst
    }

    /// True when `sample` surely measures above `floor`, measured `anchor` being known.
    fn rules_out(&self, anchor: Option<&(f64, Vec<f64>)>, sample: &[f64], floor: f64) -> bool {
        anchor
            .is_some_and(|(value, at)| value - self.between(at, sample) > floor + BOUND_ROUNDING_M)
    }
}

/// A sweep's last measured sample and value per bound: each clearance (a part of the room,
/// or one distance alone) is measured at a sample only when its own bound from its own
/// last measured sample cannot place it clear.
struct Anchors<'t> {
    travels: &'t [Travel],
    /// By travel: the value last measured and where.
    at: Vec<Option<(f64, Vec<f64>)>>,
}

impl<'t> Anchors<'t> {
    fn new(travels: &'t [Travel]) -> Self {
        Self {
            travels,
            at: vec![None; travels.len()],
        }
    }

    /// Measures at `sample` each clearance (by its travel's index) whose bound cannot place
    /// it above `floor`; the least measured, infinity when none was. A clearance left
    /// unmeasured lies above `floor`, so the least is the sample's own whenever that is at
    /// most `floor`.
    fn visit(
        &mut self,
        sample: &[f64],
        floor: f64,
        mut measure: impl FnMut(usize, &[f64]) -> f64,
    ) -> f64 {
        let mut least = f64::INFINITY;
        for (index, travel) in self.travels.iter().enumerate() {
            if travel.rules_out(self.at[index].as_ref(), sample, floor) {
                continue;
            }
            let value = measure(index, sample);
            least = least.min(value);
            let anchor = self.at[index].get_or_insert_with(|| (value, Vec::new()));
            anchor.0 = value;
            anchor.1.clear();
            anchor.1.extend_from_slice(sample);
        }
        least
    }
}

/// How a joint's axis lies in the room whatever the joints before it do.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Lie {
    /// Always vertical (+z).
    Vertical,
    /// Always level: in the floor plan.
    Level,
    /// Either or neither, as the joints before it move.
    Tilted,
}

/// Per joint: how its axis lies. Every frame up to it must keep the vertical, and every
/// revolute joint before it turn about it; such turns leave a vertical axis vertical and a
/// level one level.
fn axis_lie(rig: &Rig) -> Vec<Lie> {
    let mut upright = true;
    rig.joints
        .iter()
        .map(|joint| {
            upright &= joint.origin.matrix3 * DVec3::Z == DVec3::Z;
            let axis = joint.axis.normalize_or_zero();
            let lie = match upright {
                true if axis == DVec3::Z => Lie::Vertical,
                true if axis.z == 0.0 && axis != DVec3::ZERO => Lie::Level,
                _ => Lie::Tilted,
            };
            if joint.kind == JointKind::Revolute {
                upright &= lie == Lie::Vertical;
            }
            lie
        })
        .collect()
}
