//! The painter's body and brush from its joint positions: the brush's contact line, and
//! capsules for the arm's links, the handle and a cylinder for the base, with their
//! clearance from the walls.
//!
//! Owns the geometry both the planner and the twin's world use, so the planner checks
//! exactly what the twin measures. Must not decide what is acceptable: callers compare the
//! clearance with zero (the twin) or a margin (the planner).

use super::config::{EXTRA_AXES, PaintConfig};
use super::room::Room;
use crate::rig::{JointAxis, Rig};
use glam::{DAffine3, DVec2, DVec3};

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

/// A segment with a radius.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Capsule {
    pub a: DVec3,
    pub b: DVec3,
    pub radius: f64,
}

/// The painter's collision envelope.
#[derive(Debug, Clone)]
pub struct Body {
    pub brush: Brush,
    pub base_radius: f64,
    pub link_radii: [f64; 5],
}

impl Body {
    pub fn from_config(config: &PaintConfig) -> Self {
        Self {
            brush: Brush::from_config(config),
            base_radius: config.body.base_radius_m,
            link_radii: config.body.link_radii_m,
        }
    }

    /// Capsules of the arm's links and the handle (bristles excluded) at `positions`;
    /// `axes` is scratch space. Returns tool0 too.
    pub fn capsules(
        &self,
        rig: &Rig,
        positions: &[f64],
        axes: &mut Vec<JointAxis>,
        out: &mut Vec<Capsule>,
    ) -> DAffine3 {
        out.clear();
        let tool0 = rig
            .forward_with_axes(positions, axes)
            .unwrap_or(DAffine3::IDENTITY);
        for (link, radius) in self.link_radii.iter().enumerate() {
            let first = EXTRA_AXES + link;
            if let (Some(a), Some(b)) = (axes.get(first), axes.get(first + 1)) {
                out.push(Capsule {
                    a: a.point,
                    b: b.point,
                    radius: *radius,
                });
            }
        }
        let handle_end = self.brush.handle - self.brush.bristle;
        out.push(Capsule {
            a: tool0.translation,
            b: tool0.transform_point3(DVec3::Z * handle_end),
            radius: self.brush.handle_radius,
        });
        tool0
    }

    /// The smallest distance between the body's surface and any wall (negative when it
    /// pierces one), and tool0. The room is convex, so inside every wall's plane is inside
    /// the room.
    pub fn clearance(
        &self,
        room: &Room,
        positions: &[f64],
        scratch: &mut Scratch,
    ) -> (f64, DAffine3) {
        let base = DVec2::new(positions[0], positions[1]);
        let mut worst = room.clearance(base) - self.base_radius;
        let Scratch {
            rig,
            axes,
            capsules,
        } = scratch;
        let tool0 = self.capsules(rig, positions, axes, capsules);
        for capsule in capsules.iter() {
            let ends = room
                .clearance(capsule.a.truncate())
                .min(room.clearance(capsule.b.truncate()));
            worst = worst.min(ends - capsule.radius);
        }
        (worst, tool0)
    }
}

/// Reusable buffers for body checks (no allocation per call), with the rig they use.
pub struct Scratch {
    pub rig: Rig,
    pub axes: Vec<JointAxis>,
    pub capsules: Vec<Capsule>,
}

impl Scratch {
    pub fn new(rig: &Rig) -> Self {
        Self {
            rig: rig.clone(),
            axes: Vec::with_capacity(rig.dof()),
            capsules: Vec::with_capacity(8),
        }
    }
}

impl Body {
    /// The wall nearest the capsules (and base) left in `scratch` by the last
    /// [`Body::clearance`] call at base position `base`.
    pub fn nearest_wall(&self, room: &Room, scratch: &Scratch) -> usize {
        scratch
            .capsules
            .iter()
            .flat_map(|c| {
                [
                    room.nearest_wall(c.a.truncate()),
                    room.nearest_wall(c.b.truncate()),
                ]
                .map(|(wall, d)| (wall, d - c.radius))
            })
            .fold((0, f64::INFINITY), |best, next| {
                if next.1 < best.1 { next } else { best }
            })
            .0
    }
}
