//! The collision model: the rig's link bodies, the tool and the cell's objects, the pairs
//! that are checked, and the queries at one configuration (the closest pair, every pair
//! within a distance, the bodies' poses for drawing). Owns the placing of bodies and the
//! broad phase; exact distances come from [`super::parry`].
//!
//! Broad phase ([`super::bound`]): every checked pair gets a quick lower bound on its
//! distance; the lowest is measured exactly first, the pairs whose quick bound is below
//! that get a tight bound, and those still below are measured in the order of their bounds
//! until the next bound cannot beat the best. Static solids are placed once, when the
//! scratch is made.

use super::bound::{self, Placed, Volumes};
use super::parry::{pose, signed_distance, solid};
use super::{Cell, CellError};
use crate::rig::{JointKind, Rig, Shape};
use glam::DAffine3;
use parry3d_f64::math::Pose;
use parry3d_f64::shape::SharedShape;
use std::collections::HashSet;

/// A body of the model: a rig link, the tool, or a cell object, by its index.
pub type BodyId = usize;

/// The body of a [`Clearance`] when no pair is checked at all (its distance is infinite).
pub const NO_BODY: BodyId = usize::MAX;

/// How a clearance compares with the cell's margin.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Status {
    /// At least the margin away.
    Free,
    /// Apart, but closer than the margin.
    WithinMargin,
    /// Touching or overlapping.
    Collision,
}

impl std::fmt::Display for Status {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Status::Free => "free",
            Status::WithinMargin => "within_margin",
            Status::Collision => "collision",
        })
    }
}

/// The distance between two bodies: the gap, or (negative) the penetration depth.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Clearance {
    pub distance_m: f64,
    pub a: BodyId,
    pub b: BodyId,
}

impl Clearance {
    /// Nothing checked: infinitely far.
    pub const NONE: Clearance = Clearance {
        distance_m: f64::INFINITY,
        a: NO_BODY,
        b: NO_BODY,
    };
}

/// One solid of the model placed at a configuration (cell frame).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlacedShape {
    pub body: BodyId,
    /// Index of the solid: [`CollisionModel::shape`] gives its geometry.
    pub shape: usize,
    /// The solid's own frame in the cell frame.
    pub pose: DAffine3,
}

/// Per-caller buffers, so a query allocates nothing.
#[derive(Debug, Clone)]
pub struct Scratch {
    /// Cell-frame pose of frame k of the rig (0: the base, as mounted).
    frames: Vec<DAffine3>,
    placed: Vec<PlacedShape>,
    /// parry's pose of each solid, computed when an exact query first needs it (a static
    /// solid's once, with the scratch).
    solid_poses: Vec<Option<Pose>>,
    /// Each solid's bounding volumes in the cell frame.
    volumes: Vec<Placed>,
    /// Per checked pair, its quick bound.
    quick: Vec<f64>,
    /// The pairs still to measure exactly, with their tight bounds, lowest first.
    candidates: Vec<(f64, usize)>,
}

/// Where a body's solids hang: fixed in the cell, or on a frame of the rig that moves.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Attach {
    Fixed,
    Frame(usize),
}

#[derive(Debug, Clone)]
pub(super) struct Body {
    pub(super) name: String,
    pub(super) attach: Attach,
    pub(super) shapes: std::ops::Range<usize>,
}

#[derive(Clone)]
pub(super) struct ModelShape {
    pub(super) body: BodyId,
    /// The solid's frame in its body's frame (the cell frame for a fixed body).
    pub(super) local: DAffine3,
    pub(super) shape: Shape,
    solid: SharedShape,
    /// parry's solid frame within ours (the cylinder's axis turn).
    solid_frame: DAffine3,
    /// The broad phase's bounding volumes, in the solid's frame.
    volumes: Volumes,
}

/// The rig's bodies, the tool and the cell's objects, with the pairs that are checked.
#[derive(Clone)]
pub struct CollisionModel {
    pub(super) dof: usize,
    pub(super) mount: DAffine3,
    pub(super) joints: Vec<crate::rig::Joint>,
    pub(super) bodies: Vec<Body>,
    pub(super) shapes: Vec<ModelShape>,
    /// Checked pairs of bodies, `a < b`.
    pub(super) pairs: Vec<(BodyId, BodyId)>,
    pub(super) margin: f64,
    /// Per joint, how far a point of any body can move per unit of that joint's motion
    /// (m/rad or m/m): the continuous check's bound.
    pub(super) reach: Vec<f64>,
}

impl std::fmt::Debug for CollisionModel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CollisionModel")
            .field("bodies", &self.bodies.len())
            .field("shapes", &self.shapes.len())
            .field("pairs", &self.pairs.len())
            .field("margin", &self.margin)
            .finish()
    }
}

/// What kind of body a name belongs to, for the duplicate-name message.
const RIG: &str = "a rig link";
const TOOL: &str = "the tool";
const OBJECT: &str = "a cell object";

impl CollisionModel {
    /// The model of `rig` (as loaded, ending at its flange frame such as tool0; a rig from
    /// [`Cell::rig_at_tcp`] is taken back to it) in `cell`. Checked pairs: every pair of
    /// bodies except those on one rigid frame (two static bodies; the tool and the link of
    /// the last frame, its flange, which it always touches) and the rig's and the cell's
    /// allowed pairs.
    pub fn new(rig: &Rig, cell: &Cell) -> Result<Self, CellError> {
        let dof = rig.dof();
        let flange_to_tool0 = match &cell.tool {
            Some(tool) if rig.tool_frame == tool.name => rig.tool * tool.tcp.inverse(),
            _ => rig.tool,
        };
        let mut builder = Builder::default();
        for body in &rig.bodies {
            let attach = match body.frame {
                0 => Attach::Fixed,
                k => Attach::Frame(k),
            };
            let base = match attach {
                Attach::Fixed => cell.mount,
                Attach::Frame(_) => DAffine3::IDENTITY,
            };
            let solids = body.collisions.iter().map(|c| (base * c.origin, &c.shape));
            builder.add(&body.name, RIG, attach, solids)?;
        }
        if let Some(tool) = cell.tool.as_ref().filter(|t| !t.bodies.is_empty()) {
            let solids = tool
                .bodies
                .iter()
                .map(|c| (flange_to_tool0 * c.origin, &c.shape));
            builder.add(&tool.name, TOOL, Attach::Frame(dof), solids)?;
        }
        for object in &cell.objects {
            let solids = std::iter::once((object.pose, &object.shape));
            builder.add(&object.name, OBJECT, Attach::Fixed, solids)?;
        }
        let allowed = allowed_ids(&builder.bodies, rig, cell)?;
        let pairs = checked_pairs(&builder.bodies, &allowed);
        let reach = reach_per_joint(rig, &builder.bodies, &builder.shapes);
        Ok(CollisionModel {
            dof,
            mount: cell.mount,
            joints: rig.joints.clone(),
            bodies: builder.bodies,
            shapes: builder.shapes,
            pairs,
            margin: cell.margin_m,
            reach,
        })
    }

    /// Buffers for queries on this model, with its static solids placed (a moving solid's
    /// place is its body frame's until the first query).
    pub fn scratch(&self) -> Scratch {
        let placed: Vec<PlacedShape> = self
            .shapes
            .iter()
            .enumerate()
            .map(|(index, s)| PlacedShape {
                body: s.body,
                shape: index,
                pose: s.local,
            })
            .collect();
        let solid_poses = self
            .shapes
            .iter()
            .map(|s| {
                (self.bodies[s.body].attach == Attach::Fixed)
                    .then(|| pose(&(s.local * s.solid_frame)))
            })
            .collect();
        Scratch {
            frames: vec![self.mount; self.dof + 1],
            volumes: self
                .shapes
                .iter()
                .map(|s| s.volumes.place(&s.local))
                .collect(),
            placed,
            solid_poses,
            quick: vec![0.0; self.pairs.len()],
            candidates: Vec::with_capacity(self.pairs.len()),
        }
    }

    pub fn margin(&self) -> f64 {
        self.margin
    }

    /// The same bodies and pairs, refusing below `margin_m` instead: a planner that must
    /// leave room beyond the cell's margin (the free planner keeps an allowance, so that
    /// a path proven at its margin is clear by the cell's at every point, not only at its
    /// samples). The solids are shared, not copied.
    pub fn with_margin(&self, margin_m: f64) -> CollisionModel {
        CollisionModel {
            margin: margin_m,
            ..self.clone()
        }
    }

    /// The name of body `id` (empty for [`NO_BODY`]).
    pub fn body_name(&self, id: BodyId) -> &str {
        self.bodies.get(id).map_or("", |b| b.name.as_str())
    }

    /// The body named `name`.
    pub fn body_id(&self, name: &str) -> Option<BodyId> {
        self.bodies.iter().position(|b| b.name == name)
    }

    pub fn body_count(&self) -> usize {
        self.bodies.len()
    }

    /// True for a body that never moves (a cell object, a link on the rig's base).
    pub fn is_static(&self, id: BodyId) -> bool {
        self.bodies
            .get(id)
            .is_some_and(|b| b.attach == Attach::Fixed)
    }

    /// The geometry of solid `index` (of [`PlacedShape::shape`]), in its own frame.
    pub fn shape(&self, index: usize) -> &Shape {
        &self.shapes[index].shape
    }

    /// The pairs of bodies that are checked.
    pub fn checked_pairs(&self) -> &[(BodyId, BodyId)] {
        &self.pairs
    }

    pub fn status(&self, distance_m: f64) -> Status {
        if distance_m <= 0.0 {
            Status::Collision
        } else if distance_m < self.margin {
            Status::WithinMargin
        } else {
            Status::Free
        }
    }

    /// The closest checked pair at `positions` (joint positions of the rig, SI units).
    ///
    /// # Panics
    /// When `positions` does not hold one value per joint (callers hold validated
    /// trajectories of the rig).
    pub fn clearance(&self, positions: &[f64], scratch: &mut Scratch) -> Clearance {
        self.place(positions, scratch);
        let mut best = Clearance::NONE;
        // The pair whose quick bound is lowest is most likely the closest: measured first,
        // its distance rules out most other pairs on their quick bound alone.
        let Some(likeliest) = self.quick_bounds(scratch) else {
            return best;
        };
        self.measure_pair(likeliest, &mut best, scratch);
        self.gather_candidates(likeliest, best.distance_m, scratch);
        let candidates = std::mem::take(&mut scratch.candidates);
        for &(bound, index) in &candidates {
            if bound >= best.distance_m {
                break;
            }
            self.measure_pair(index, &mut best, scratch);
        }
        scratch.candidates = candidates;
        best
    }

    /// Fills the scratch's quick bound of every checked pair; the index of the lowest.
    fn quick_bounds(&self, scratch: &mut Scratch) -> Option<usize> {
        let mut lowest: Option<(f64, usize)> = None;
        for (index, &(a, b)) in self.pairs.iter().enumerate() {
            let bound = self.pair_bound(a, b, scratch, bound::quick);
            scratch.quick[index] = bound;
            if lowest.is_none_or(|(low, _)| bound < low) {
                lowest = Some((bound, index));
            }
        }
        lowest.map(|(_, index)| index)
    }

    /// The pairs besides `measured` that may still beat `best`: every pair that neither its
    /// quick nor its tight bound rules out (a bound that is not a number rules out nothing),
    /// sorted by tight bound (ties by pair, so the answer does not depend on the sort).
    fn gather_candidates(&self, measured: usize, best: f64, scratch: &mut Scratch) {
        let mut candidates = std::mem::take(&mut scratch.candidates);
        candidates.clear();
        for (index, &(a, b)) in self.pairs.iter().enumerate() {
            if index == measured || scratch.quick[index] >= best {
                continue;
            }
            let bound = self.pair_bound(a, b, scratch, bound::tight);
            if bound >= best {
                continue;
            }
            candidates.push((bound, index));
        }
        candidates.sort_unstable_by(|p, q| p.0.total_cmp(&q.0).then(p.1.cmp(&q.1)));
        scratch.candidates = candidates;
    }

    /// Measures checked pair `index` exactly, and makes it `best` when it is closer.
    fn measure_pair(&self, index: usize, best: &mut Clearance, scratch: &mut Scratch) {
        let (a, b) = self.pairs[index];
        if let Some(d) = self.pair_distance(a, b, best.distance_m, scratch) {
            *best = Clearance {
                distance_m: d,
                a,
                b,
            };
        }
    }

    /// Every checked pair closer than `cutoff_m` at `positions`, into `out` (cleared first).
    pub fn pairs_within(
        &self,
        positions: &[f64],
        cutoff_m: f64,
        scratch: &mut Scratch,
        out: &mut Vec<Clearance>,
    ) {
        out.clear();
        self.place(positions, scratch);
        for &(a, b) in &self.pairs {
            if let Some(d) = self.pair_distance(a, b, cutoff_m, scratch) {
                out.push(Clearance {
                    distance_m: d,
                    a,
                    b,
                });
            }
        }
    }

    /// Every solid placed at `positions`, in the cell frame (for drawing).
    pub fn body_poses<'s>(&self, positions: &[f64], scratch: &'s mut Scratch) -> &'s [PlacedShape] {
        self.place(positions, scratch);
        &scratch.placed
    }

    /// Places every moving solid at `positions`: frames, poses, bounding volumes; parry's
    /// poses are left to be computed on demand. Static solids stay where the scratch put
    /// them.
    fn place(&self, positions: &[f64], scratch: &mut Scratch) {
        assert_eq!(
            positions.len(),
            self.dof,
            "the collision model's rig has {} joints",
            self.dof
        );
        let mut frame = self.mount;
        for (k, (joint, q)) in self.joints.iter().zip(positions).enumerate() {
            frame *= joint.transform(*q);
            scratch.frames[k + 1] = frame;
        }
        for (index, shape) in self.shapes.iter().enumerate() {
            let Attach::Frame(k) = self.bodies[shape.body].attach else {
                continue;
            };
            let pose = scratch.frames[k] * shape.local;
            scratch.placed[index].pose = pose;
            scratch.volumes[index] = shape.volumes.place(&pose);
            scratch.solid_poses[index] = None;
        }
    }

    /// The smallest signed distance between the solids of `a` and `b`, when below `beat`.
    fn pair_distance(&self, a: BodyId, b: BodyId, beat: f64, scratch: &mut Scratch) -> Option<f64> {
        let mut best = beat;
        let mut found = false;
        for i in self.bodies[a].shapes.clone() {
            for j in self.bodies[b].shapes.clone() {
                let (si, sj) = (self.solid(i, scratch), self.solid(j, scratch));
                let d = match bound::plane_exact(&si, &sj) {
                    Some(d) => d,
                    None if bound::quick(&si, &sj) >= best || bound::tight(&si, &sj) >= best => {
                        continue;
                    }
                    None => self.exact(i, j, scratch),
                };
                if d < best {
                    best = d;
                    found = true;
                }
            }
        }
        found.then_some(best)
    }

    /// The lowest of `bound` over the solid pairs of bodies `a` and `b`.
    fn pair_bound(
        &self,
        a: BodyId,
        b: BodyId,
        scratch: &Scratch,
        bound: impl Fn(&bound::Solid<'_>, &bound::Solid<'_>) -> f64,
    ) -> f64 {
        let mut low = f64::INFINITY;
        for i in self.bodies[a].shapes.clone() {
            for j in self.bodies[b].shapes.clone() {
                low = low.min(bound(&self.solid(i, scratch), &self.solid(j, scratch)));
            }
        }
        low
    }

    /// Solid `index` as placed in `scratch`, for the bounds.
    fn solid<'s>(&'s self, index: usize, scratch: &'s Scratch) -> bound::Solid<'s> {
        let shape = &self.shapes[index];
        bound::Solid {
            shape: &shape.shape,
            volumes: &shape.volumes,
            pose: &scratch.placed[index].pose,
            placed: &scratch.volumes[index],
        }
    }

    fn exact(&self, i: usize, j: usize, scratch: &mut Scratch) -> f64 {
        let pi = self.solid_pose(i, scratch);
        let pj = self.solid_pose(j, scratch);
        signed_distance(&pi, &self.shapes[i].solid, &pj, &self.shapes[j].solid)
    }

    fn solid_pose(&self, index: usize, scratch: &mut Scratch) -> Pose {
        *scratch.solid_poses[index].get_or_insert_with(|| {
            pose(&(scratch.placed[index].pose * self.shapes[index].solid_frame))
        })
    }
}

#[derive(Default)]
struct Builder {
    bodies: Vec<Body>,
    kinds: Vec<&'static str>,
    shapes: Vec<ModelShape>,
}

impl Builder {
    fn add<'a>(
        &mut self,
        name: &str,
        kind: &'static str,
        attach: Attach,
        solids: impl Iterator<Item = (DAffine3, &'a Shape)>,
    ) -> Result<BodyId, CellError> {
        if let Some(i) = self.bodies.iter().position(|b| b.name == name) {
            return Err(CellError::DuplicateName {
                name: name.to_string(),
                first: self.kinds[i],
                second: kind,
            });
        }
        let id = self.bodies.len();
        let start = self.shapes.len();
        for (local, shape) in solids {
            let Some((solid_shape, solid_frame)) = solid(shape) else {
                return Err(CellError::DegenerateHull {
                    body: name.to_string(),
                });
            };
            let plane = match shape {
                Shape::HalfSpace { normal } if attach == Attach::Fixed => {
                    let n = local.transform_vector3(*normal).normalize();
                    Some((n, n.dot(local.translation)))
                }
                Shape::HalfSpace { .. } => {
                    return Err(CellError::UnboundedMovingBody {
                        body: name.to_string(),
                    });
                }
                _ => None,
            };
            self.shapes.push(ModelShape {
                body: id,
                local,
                shape: shape.clone(),
                solid: solid_shape,
                solid_frame,
                volumes: Volumes::new(shape, plane),
            });
        }
        self.bodies.push(Body {
            name: name.to_string(),
            attach,
            shapes: start..self.shapes.len(),
        });
        self.kinds.push(kind);
        Ok(id)
    }
}

/// The allowed pairs of the rig and the cell, as body ids; a name that is no body is an
/// error (a typo would otherwise silently check a pair the user meant to allow, or the
/// reverse).
fn allowed_ids(
    bodies: &[Body],
    rig: &Rig,
    cell: &Cell,
) -> Result<HashSet<(BodyId, BodyId)>, CellError> {
    let find = |source_name: &'static str, index: usize, name: &str| {
        bodies
            .iter()
            .position(|b| b.name == name)
            .ok_or_else(|| CellError::UnknownPairBody {
                source_name,
                index,
                name: name.to_string(),
                known: bodies
                    .iter()
                    .map(|b| b.name.as_str())
                    .collect::<Vec<_>>()
                    .join(", "),
            })
    };
    let mut allowed = HashSet::new();
    for (source_name, pairs) in [("rig", &rig.allowed_pairs), ("cell", &cell.allowed_pairs)] {
        for (index, (a, b)) in pairs.iter().enumerate() {
            let (a, b) = (find(source_name, index, a)?, find(source_name, index, b)?);
            allowed.insert((a.min(b), a.max(b)));
        }
    }
    Ok(allowed)
}

fn checked_pairs(bodies: &[Body], allowed: &HashSet<(BodyId, BodyId)>) -> Vec<(BodyId, BodyId)> {
    let mut pairs = Vec::new();
    for a in 0..bodies.len() {
        for b in a + 1..bodies.len() {
            // One rigid frame: two static bodies, or the tool and the flange's link.
            let same_frame = bodies[a].attach == bodies[b].attach;
            if !same_frame && !allowed.contains(&(a, b)) {
                pairs.push((a, b));
            }
        }
    }
    pairs
}

/// Per joint j, a bound on how far any point of a body moved by it travels per unit of
/// its motion: for a revolute joint the largest distance of such a point from the joint's
/// origin (it moves on a circle about an axis through that origin, so its arc is at most
/// that radius times the angle), for a prismatic joint 1 (everything after it translates
/// with it). The distance sums the lengths of the links between (a prismatic joint's
/// farthest extension added) and the solid's bounding sphere.
fn reach_per_joint(rig: &Rig, bodies: &[Body], shapes: &[ModelShape]) -> Vec<f64> {
    let joints = &rig.joints;
    let link_length = |i: usize| {
        let joint = &joints[i];
        let extension = match joint.kind {
            JointKind::Revolute => 0.0,
            JointKind::Prismatic => joint.limits.lower.abs().max(joint.limits.upper.abs()),
        };
        joint.origin.translation.length() + extension
    };
    (0..joints.len())
        .map(|j| match joints[j].kind {
            JointKind::Prismatic => 1.0,
            JointKind::Revolute => shapes
                .iter()
                .filter_map(|s| match bodies[s.body].attach {
                    Attach::Frame(k) if k > j => {
                        let between: f64 = (j + 1..k).map(link_length).sum();
                        let sphere = &s.volumes;
                        Some(
                            between
                                + s.local.transform_point3(sphere.centre).length()
                                + sphere.radius,
                        )
                    }
                    _ => None,
                })
                .fold(0.0, f64::max),
        })
        .collect()
}
