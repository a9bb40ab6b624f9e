//! A rig's world as data: walls with their openings, cylinders (branches, trunks, a lift's
//! column) and paint ([`SceneView`], [`PaintQuad`]), and its translation into Foxglove's
//! `SceneUpdate` ([`foxglove`]).
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
