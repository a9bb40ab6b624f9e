//! The painter's body and brush from its joint positions: the brush's contact line, and
//! capsules for the arm's links, the handle and a cylinder for the base, with their
//! clearance from the walls.
//!
//! Owns the geometry both the planner and the twin's world use, so the planner checks
//! exactly what the twin measures. Must not decide what is acceptable: callers compare the
//! clearance with zero (the twin) or a margin (the planner).

use super::config::{EXTRA_AXES, PaintConfig};
use super::room::Room;
use crate::rig::{JointAxis, JointKind, Rig};
use glam::{DAffine3, DVec2, DVec3};

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

/// How far the body, the brush's contact line and the base's axis can move over the floor
/// plan between two joint positions of the rig (both within its limits): every clearance
/// the planner measures is the distance of such points from wall planes in the floor plan,
/// so it changes by no more than that. Lets a sweep over a trajectory measure only the
/// samples a bound from the last measured one cannot place clear.
#[derive(Debug, Clone)]
pub struct Travel {
    /// Per joint: how far (m) the farthest point after it moves in the floor plan per unit
    /// of its motion.
    levers: Vec<f64>,
}

impl Travel {
    /// A revolute joint moves a point by at most the angle times its distance from the
    /// joint's origin, which the links, prismatic strokes (at their limits), tool and brush
    /// after it bound whatever the other joints do; a prismatic joint by its stroke, or not
    /// at all in the floor plan when its axis is vertical whatever the joints before it do.
    pub fn new(rig: &Rig, brush: &Brush) -> Self {
        let vertical = vertical_axes(rig);
        let brush_reach = brush.handle.hypot(brush.width / 2.0);
        let tool_reach = rig.tool.translation.length() + brush_reach;
        let levers = (0..rig.dof())
            .map(|j| {
                let joint = &rig.joints[j];
                if joint.kind == JointKind::Prismatic {
                    return if vertical[j] {
                        0.0
                    } else {
                        joint.axis.length()
                    };
                }
                let after: f64 = (j + 1..rig.dof())
                    .map(|k| {
                        let link = &rig.joints[k];
                        let stroke = match link.kind {
                            // Along a vertical axis it never leaves a vertical one.
                            JointKind::Prismatic if !(vertical[j] && vertical[k]) => {
                                link.limits.lower.abs().max(link.limits.upper.abs())
                                    * link.axis.length()
                            }
                            _ => 0.0,
                        };
                        link.origin.translation.length() + stroke
                    })
                    .sum();
                after + tool_reach
            })
            .collect();
        Self { levers }
    }

    /// At least how far (m) any point of the body or brush moves in the floor plan from
    /// joint positions `a` to `b`.
    pub fn between(&self, a: &[f64], b: &[f64]) -> f64 {
        let joints: f64 = self
            .levers
            .iter()
            .zip(a.iter().zip(b))
            .map(|(lever, (x, y))| lever * (y - x).abs())
            .sum();
        // The base's axis is (x, y) = the first two positions, outside the chain.
        let base = (b[0] - a[0]).abs() + (b[1] - a[1]).abs();
        joints.max(base)
    }

    /// The least `measure` (a clearance: moving a point by d changes it by at most d) of
    /// `samples`, exactly, when that is at most `needed`; otherwise some value above
    /// `needed`. Samples the bound from the last measured one places above both `needed`
    /// and the least so far are not measured: they can change neither answer.
    pub fn lowest<'s>(
        &self,
        samples: impl IntoIterator<Item = &'s [f64]>,
        needed: f64,
        mut measure: impl FnMut(&[f64]) -> f64,
    ) -> f64 {
        let mut worst = f64::INFINITY;
        let mut anchor: Option<(f64, &[f64])> = None;
        for sample in samples {
            if self.rules_out(anchor, sample, needed.min(worst)) {
                continue;
            }
            let value = measure(sample);
            worst = worst.min(value);
            anchor = Some((value, sample));
        }
        worst
    }

    /// The first of `samples` (index, positions) whose `measure` is below `needed`, with
    /// that value; samples the bound places above it are not measured.
    pub fn first_below<'s>(
        &self,
        samples: impl IntoIterator<Item = (usize, &'s [f64])>,
        needed: f64,
        mut measure: impl FnMut(&[f64]) -> f64,
    ) -> Option<(usize, f64)> {
        let mut anchor: Option<(f64, &[f64])> = None;
        for (index, sample) in samples {
            if self.rules_out(anchor, sample, needed) {
                continue;
            }
            let value = measure(sample);
            if value < needed {
                return Some((index, value));
            }
            anchor = Some((value, sample));
        }
        None
    }

    /// True when `sample` surely measures above `floor`, measured `anchor` being known.
    fn rules_out(&self, anchor: Option<(f64, &[f64])>, sample: &[f64], floor: f64) -> bool {
        anchor
            .is_some_and(|(value, at)| value - self.between(at, sample) > floor + BOUND_ROUNDING_M)
    }
}

/// Per joint: whether its axis is vertical in the room whatever the joints before it do
/// (every frame up to it keeps the vertical, every revolute joint before it turns about it).
fn vertical_axes(rig: &Rig) -> Vec<bool> {
    let mut upright = true;
    rig.joints
        .iter()
        .map(|joint| {
            upright &= joint.origin.matrix3 * DVec3::Z == DVec3::Z;
            let vertical = upright && joint.axis.normalize_or_zero() == DVec3::Z;
            if joint.kind == JointKind::Revolute {
                upright &= vertical;
            }
            vertical
        })
        .collect()
}
