//! The cell as the page and Foxglove draw it (issue 27): the cell's objects, the tool and
//! the rig's collision bodies as triangle meshes, the bodies' poses at given joint values,
//! and the closest pair of the collision model when it is within the margin.
//!
//! Built once per cell from the rig and its cell (meshes are computed here, not per frame);
//! posed and checked about 50 times a second from the view's sampling task, never from the
//! streaming cycle. Owns only drawing: what is checked, and how, is the collision model's.

use crate::cell::{Cell, CollisionModel, Scratch, Status};
use crate::rig::{Collision, Rig, Shape};
use crate::scene::{BodyView, ClosestView, Point, PoseView, SolidView};
use glam::{DAffine3, DQuat, DVec3};
use std::sync::Arc;

/// Segments around a drawn cylinder, capsule or sphere: round enough at the page's scale,
/// few enough triangles (a capsule is about 150) for 50 frames a second on a canvas.
const ROUND_SEGMENTS: usize = 12;
/// Rings from pole to pole of a drawn sphere (a capsule's two caps share them).
const SPHERE_RINGS: usize = 6;
/// A half-space (a floor, a wall) is drawn as a square of this side around the point of
/// its plane nearest its frame's origin: a cell's extent, not infinity.
const HALF_SPACE_DRAWN_M: f64 = 2.4;

/// What the page and Foxglove draw of a cell, and the model that finds its closest pair.
pub struct CellDrawing {
    rig: Rig,
    model: Arc<CollisionModel>,
    scratch: Scratch,
    /// The cell's objects, in the rig's base frame.
    pub solids: Vec<SolidView>,
    /// The rig's bodies and the tool's, each on a frame of the rig.
    pub bodies: Vec<BodyView>,
}

impl CellDrawing {
    /// The drawing of `rig` in `cell`, with the collision model built from them. `tool0`
    /// is the flange-to-tool0 transform the tool's bodies are given from (the rig's own
    /// tool transform before any TCP).
    pub fn new(rig: &Rig, cell: &Cell, model: Arc<CollisionModel>, tool0: DAffine3) -> Self {
        let base_from_cell = cell.mount.inverse();
        let solids = cell
            .objects
            .iter()
            .map(|object| solid(&object.name, base_from_cell * object.pose, &object.shape))
            .collect();
        let mut bodies: Vec<BodyView> = rig
            .bodies
            .iter()
            .flat_map(|body| {
                body.collisions.iter().map(|c| BodyView {
                    frame: body.frame,
                    solid: solid(&body.name, c.origin, &c.shape),
                })
            })
            .collect();
        if let Some(tool) = &cell.tool {
            bodies.extend(tool.bodies.iter().map(|c: &Collision| BodyView {
                frame: rig.dof(),
                solid: solid(&tool.name, tool0 * c.origin, &c.shape),
            }));
        }
        CellDrawing {
            rig: rig.clone(),
            scratch: model.scratch(),
            model,
            solids,
            bodies,
        }
    }

    /// Every body's pose in the rig's base frame at `positions`, in [`Self::bodies`]
    /// order; empty when `positions` does not fit the rig.
    pub fn body_poses(&self, positions: &[f64]) -> Vec<PoseView> {
        if positions.len() != self.rig.dof() {
            return Vec::new();
        }
        let mut frames = Vec::with_capacity(self.rig.dof() + 1);
        let mut frame = DAffine3::IDENTITY;
        frames.push(frame);
        for (joint, q) in self.rig.joints.iter().zip(positions) {
            frame *= joint.transform(*q);
            frames.push(frame);
        }
        self.bodies
            .iter()
            .map(|body| {
                let local = affine(&body.solid.pose);
                pose_view(frames.get(body.frame).copied().unwrap_or(frame) * local)
            })
            .collect()
    }

    /// The closest checked pair at `positions` when it is within the margin (or touching).
    pub fn closest(&mut self, positions: &[f64]) -> Option<ClosestView> {
        if positions.len() != self.rig.dof() {
            return None;
        }
        let clearance = self.model.clearance(positions, &mut self.scratch);
        let status = self.model.status(clearance.distance_m);
        (status != Status::Free).then(|| ClosestView {
            a: self.model.body_name(clearance.a).to_string(),
            b: self.model.body_name(clearance.b).to_string(),
            distance_m: clearance.distance_m,
            status: status.to_string(),
        })
    }
}

/// A named solid at `pose` as triangles in its own frame.
pub fn solid(name: &str, pose: DAffine3, shape: &Shape) -> SolidView {
    SolidView {
        name: name.to_string(),
        pose: pose_view(pose),
        triangles: shape_triangles(shape).into_iter().flatten().collect(),
    }
}

pub(super) fn pose_view(pose: DAffine3) -> PoseView {
    let (_, rotation, translation) = pose.to_scale_rotation_translation();
    PoseView {
        position: translation.to_array(),
        orientation: rotation.normalize().to_array(),
    }
}

fn affine(pose: &PoseView) -> DAffine3 {
    DAffine3::from_rotation_translation(
        DQuat::from_array(pose.orientation),
        DVec3::from_array(pose.position),
    )
}

type Triangle = [Point; 3];

fn tri(a: DVec3, b: DVec3, c: DVec3) -> Triangle {
    [a.to_array(), b.to_array(), c.to_array()]
}

/// The shape's surface as triangles, counter-clockwise seen from outside.
pub fn shape_triangles(shape: &Shape) -> Vec<Triangle> {
    match shape {
        Shape::Box { half_extents } => box_triangles(*half_extents),
        Shape::Cylinder {
            radius,
            half_length,
        } => capsule_like(
            DVec3::NEG_Z * *half_length,
            DVec3::Z * *half_length,
            *radius,
            false,
        ),
        Shape::Sphere { radius } => capsule_like(DVec3::ZERO, DVec3::ZERO, *radius, true),
        Shape::Capsule { a, b, radius } => capsule_like(*a, *b, *radius, true),
        Shape::HalfSpace { normal } => half_space(*normal),
        Shape::ConvexHull { points } => hull(points),
    }
}

fn box_triangles(h: DVec3) -> Vec<Triangle> {
    let corner = |x: f64, y: f64, z: f64| DVec3::new(x * h.x, y * h.y, z * h.z);
    let mut out = Vec::with_capacity(12);
    // Each face: its outward axis, and two axes spanning it (u x v = outward).
    for (n, u, v) in [
        (DVec3::X, DVec3::Y, DVec3::Z),
        (DVec3::Y, DVec3::Z, DVec3::X),
        (DVec3::Z, DVec3::X, DVec3::Y),
    ] {
        for sign in [1.0, -1.0] {
            let (n, u) = (n * sign, u * sign);
            let at = |a: f64, b: f64| {
                let p = n + u * a + v * b;
                corner(p.x, p.y, p.z)
            };
            let quad = [at(-1.0, -1.0), at(1.0, -1.0), at(1.0, 1.0), at(-1.0, 1.0)];
            out.push(tri(quad[0], quad[1], quad[2]));
            out.push(tri(quad[0], quad[2], quad[3]));
        }
    }
    out
}

/// Unit vectors `x`, `y` perpendicular to `axis` (and each other), right-handed with it.
fn frame_of(axis: DVec3) -> (DVec3, DVec3, DVec3) {
    let z = axis.normalize_or(DVec3::Z);
    let x = z.any_orthonormal_vector();
    (x, z.cross(x), z)
}

/// A cylinder of `radius` from `a` to `b`, with flat ends, or with round ones (`caps`: a
/// capsule; a sphere when `a` = `b`).
fn capsule_like(a: DVec3, b: DVec3, radius: f64, caps: bool) -> Vec<Triangle> {
    let (x, y, z) = frame_of(b - a);
    let around = |k: usize| {
        let angle = std::f64::consts::TAU * k as f64 / ROUND_SEGMENTS as f64;
        x * angle.cos() + y * angle.sin()
    };
    let mut out = Vec::new();
    if a != b {
        for k in 0..ROUND_SEGMENTS {
            let (u, v) = (around(k) * radius, around(k + 1) * radius);
            out.push(tri(a + u, a + v, b + v));
            out.push(tri(a + u, b + v, b + u));
            if !caps {
                out.push(tri(b, b + u, b + v));
                out.push(tri(a, a + v, a + u));
            }
        }
    }
    if caps {
        // The cap beyond b (rings from the +z pole to the equator), then the one beyond a.
        let half = SPHERE_RINGS / 2;
        for (centre, rings) in [(b, 0..half), (a, half..SPHERE_RINGS)] {
            for r in rings {
                let at = |r: usize, k: usize| {
                    let polar = std::f64::consts::PI * r as f64 / SPHERE_RINGS as f64;
                    centre + (z * polar.cos() + around(k) * polar.sin()) * radius
                };
                for k in 0..ROUND_SEGMENTS {
                    out.push(tri(at(r, k), at(r + 1, k), at(r + 1, k + 1)));
                    out.push(tri(at(r, k), at(r + 1, k + 1), at(r, k + 1)));
                }
            }
        }
    }
    out
}

/// The plane's square: the solid is below it (`p . normal <= 0`), the square faces out.
fn half_space(normal: DVec3) -> Vec<Triangle> {
    let (x, y, _) = frame_of(normal);
    let h = HALF_SPACE_DRAWN_M / 2.0;
    let corner = |a: f64, b: f64| (x * a + y * b) * h;
    let quad = [
        corner(-1.0, -1.0),
        corner(1.0, -1.0),
        corner(1.0, 1.0),
        corner(-1.0, 1.0),
    ];
    vec![
        tri(quad[0], quad[1], quad[2]),
        tri(quad[0], quad[2], quad[3]),
    ]
}

/// The hull's faces (parry's convex hull of the points); none for a degenerate set.
fn hull(points: &[DVec3]) -> Vec<Triangle> {
    use parry3d_f64::math::Vector3;
    let input: Vec<Vector3> = points.iter().map(|p| Vector3::new(p.x, p.y, p.z)).collect();
    let Ok((vertices, faces)) = parry3d_f64::transformation::try_convex_hull(&input) else {
        return Vec::new();
    };
    let at = |i: u32| {
        let v = vertices[i as usize];
        DVec3::new(v.x, v.y, v.z)
    };
    faces
        .iter()
        .map(|[a, b, c]| tri(at(*a), at(*b), at(*c)))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn volume(triangles: &[Triangle]) -> f64 {
        // Divergence theorem: the sum of signed tetrahedra from the origin.
        triangles
            .iter()
            .map(|[a, b, c]| {
                let [a, b, c] = [a, b, c].map(|p| DVec3::from_array(*p));
                a.dot(b.cross(c)) / 6.0
            })
            .sum()
    }

    #[test]
    fn meshes_enclose_their_solids_outward() {
        let cube = shape_triangles(&Shape::Box {
            half_extents: DVec3::new(0.1, 0.2, 0.3),
        });
        assert_eq!(cube.len(), 12);
        assert!((volume(&cube) - 0.2 * 0.4 * 0.6).abs() < 1e-12);
        // A polygon of 12 sides holds cos(15 deg) x sin(15 deg) x 12 / pi of its circle.
        let polygon =
            12.0 * (std::f64::consts::PI / 12.0).sin() * (std::f64::consts::PI / 12.0).cos()
                / std::f64::consts::PI;
        let cylinder = shape_triangles(&Shape::Cylinder {
            radius: 0.1,
            half_length: 0.5,
        });
        let exact = std::f64::consts::PI * 0.01 * 1.0;
        assert!(
            (volume(&cylinder) - exact * polygon).abs() < 1e-9,
            "{}",
            volume(&cylinder)
        );
        let capsule = shape_triangles(&Shape::Capsule {
            a: DVec3::ZERO,
            b: DVec3::new(0.0, 0.0, 1.0),
            radius: 0.1,
        });
        let round = exact + 4.0 / 3.0 * std::f64::consts::PI * 0.001;
        let v = volume(&capsule);
        assert!(v > 0.8 * round && v < round, "capsule {v} of {round}");
        let hull = shape_triangles(&Shape::ConvexHull {
            points: vec![DVec3::ZERO, DVec3::X, DVec3::Y, DVec3::Z, DVec3::splat(0.1)],
        });
        assert_eq!(hull.len(), 4, "the inner point is no vertex");
        assert!((volume(&hull) - 1.0 / 6.0).abs() < 1e-12);
    }
}
