//! A rig's world as data: walls with their openings, cylinders (branches, trunks, a lift's
//! column), paint ([`SceneView`], [`PaintQuad`]), the cell's solids and the rig's collision
//! bodies as triangle meshes ([`SolidView`], [`BodyView`]), and its translation into
//! Foxglove's `SceneUpdate` ([`foxglove`]).
//!
//! A leaf beside the chain: the live view (`view`) builds these for the page, the run log
//! (`log`) writes them on `/scene`, the daemon's live Foxglove server sends them, so the
//! types live below all three (`docs/architecture.md`, "Layers"). Owns the types and the
//! translation; must not build, measure or change a world, nor import any other module of
//! the crate.

pub mod foxglove;

use serde::Serialize;

/// A point in world coordinates (metres, z up).
pub type Point = [f64; 3];

/// The static part of a scene, sent to the page once and again when the job changes.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct SceneView {
    pub walls: Vec<WallView>,
    pub cylinders: Vec<CylinderView>,
    /// Paint already on the walls when the scene is (re)sent.
    pub paint: Vec<PaintQuad>,
    /// The cell's static objects, in the scene's frame.
    pub solids: Vec<SolidView>,
    /// The rig's collision bodies (its links' and its tool's), each in a frame of the rig:
    /// they move with it.
    pub bodies: Vec<BodyView>,
}

/// A convex solid as triangles: `triangles` holds three points a triangle, counter-
/// clockwise seen from outside, in the solid's frame, which `pose` places.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SolidView {
    /// The name the collision model gives it (a cell object's, a body's, the tool's).
    pub name: String,
    pub pose: PoseView,
    pub triangles: Vec<Point>,
}

/// A rigid placement: position (m) and unit quaternion `[x, y, z, w]`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct PoseView {
    pub position: Point,
    pub orientation: [f64; 4],
}

impl PoseView {
    pub const IDENTITY: PoseView = PoseView {
        position: [0.0; 3],
        orientation: [0.0, 0.0, 0.0, 1.0],
    };
}

/// A solid riding on the rig: `frame` 0 is the rig's base, k the frame after joint k; its
/// `solid.pose` is in that frame.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct BodyView {
    pub frame: usize,
    pub solid: SolidView,
}

/// The closest checked pair of the cell at an instant, when it is within the margin.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ClosestView {
    pub a: String,
    pub b: String,
    /// Negative: penetration depth.
    pub distance_m: f64,
    /// `within_margin` or `collision`.
    pub status: String,
}

/// A flat wall: four corners around its outline, counter-clockwise seen from its front (the
/// side the rig works on, the painted side: `(c1 - c0) x (c2 - c0)` points out of it), and
/// holes in it (doors, windows), each four corners in the wall's plane. Seen from behind,
/// the page draws a wall as an outline only, so a room shows what is inside.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct WallView {
    pub corners: [Point; 4],
    pub openings: Vec<[Point; 4]>,
}

/// A solid cylinder from `from` to `to` (a branch, a trunk, a lift's column).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CylinderView {
    pub from: Point,
    pub to: Point,
    pub radius: f64,
}

/// A patch of paint on wall `wall` (an index into [`SceneView::walls`]), as four corners in
/// the wall's plane.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct PaintQuad {
    pub wall: usize,
    pub quad: [Point; 4],
}
