//! The live view: what the browser page draws, and how it gets there.
//!
//! A [`LiveScene`] describes a rig's world for the page: static geometry ([`SceneView`]:
//! walls with openings, cylinders such as branches, paint already on), the rig as
//! world-space polylines at given joint values, and paint added since the last call. The arm
//! has one from its rig model ([`ArmScene`]); the painting room and the sloth bring theirs.
//! The streaming cycle feeds a [`LiveSlot`] through a [`LiveSink`] without allocating or
//! blocking; the [`LiveHub`] samples the slot at the page's frame rate and builds the
//! WebSocket messages ([`frame`]); [`scene_update`] gives a scene to Foxglove. The page itself
//! is in `page/`, embedded in the binary.
//!
//! This module reads the rig and the cycle's records; it must not move the arm, talk to a
//! link or touch the cycle's timing.

mod arm;
pub mod frame;
mod hub;
mod live;
pub mod page;
mod paint;
pub mod scene_update;
mod sloth;
mod trace;

pub use arm::{ArmScene, joint_origins, joint_origins_from};
pub use hub::{JobView, LiveHub, SceneChange, SceneCursor};
pub use live::{LiveSample, LiveSink, LiveSlot};
pub use paint::PaintScene;
pub use sloth::SlothScene;
pub use trace::ToolTrace;

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

/// What a rig's world shows the page. Called from the view's sampling task (about 50 times
/// a second), never from the streaming cycle: implementations may allocate and lock.
pub trait LiveScene: Send + Sync {
    /// The static geometry (and all paint so far).
    fn scene(&self) -> SceneView;
    /// The rig at the joint values `actual` (rad or m, in the rig's joint order), as
    /// world-space polylines the page draws as links: for a serial rig, the origin of every
    /// joint frame and then the tool; a branching rig (the sloth) returns one per limb.
    fn chains(&self, actual: &[f64]) -> Vec<Vec<Point>>;
    /// Paint added since the previous call.
    fn drain_paint(&mut self) -> Vec<PaintQuad> {
        Vec::new()
    }
}

/// One joint as the page labels it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct JointLabel {
    pub name: String,
    /// `deg` (revolute) or `m` (prismatic): the unit of the values the page receives.
    pub unit: &'static str,
}

impl JointLabel {
    pub fn for_rig(rig: &crate::rig::Rig) -> Vec<JointLabel> {
        rig.joints
            .iter()
            .map(|joint| JointLabel {
                name: joint.name.clone(),
                unit: joint.kind.unit(),
            })
            .collect()
    }
}
