//! The broad phase's lower bounds on the signed distance of two placed solids (negative: a
//! bound on how deep they can overlap), so that parry's exact query runs only for pairs
//! that may be the closest. Two grades: a quick one for every checked pair (bounding
//! spheres, or a half-space's plane against the other's sphere: one dot product or one
//! square root), and a tight one for the pairs the quick one cannot rule out (a plane
//! against the other solid's exact extent along its normal; the solids' bounding capsules,
//! and a box's own three slabs).
//!
//! Written here rather than taken from parry's bounding volumes: parry's `BoundingSphere`
//! and `Aabb` answer overlap, not distance; an axis-aligned box around a long link turned
//! at 45 degrees is as loose as its sphere; and they need every solid's pose converted to
//! parry's types on every call, which is the cost the broad phase exists to avoid. These
//! work on the glam poses the model has already placed. The closest points of two segments
//! are parry's own ([`super::parry::segment_distance`]).
//!
//! Every bound holds for penetration too: a solid inside a bounding volume overlaps another
//! by no more than the volume does, and the distance along one unit direction (a plane's
//! normal, a box's axis) never exceeds the distance in space.

use super::parry::segment_distance;
use crate::rig::Shape;
use glam::{DAffine3, DVec3};

/// Taken off every bound: the closed forms here round differently from parry's exact
/// queries (a plane bound is the exact distance, computed in another order), by about
/// 1e-15 m on distances of metres. 1e-9 m covers that many times over, so a bound is never
/// above the exact figure it stands for, and rules out almost nothing a real gap would not.
const ROUNDING_M: f64 = 1e-9;

/// One solid's bounding volumes in its own frame, made once with the model.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct Volumes {
    /// Bounding sphere; infinite for a half-space (its plane bounds it instead).
    pub(super) centre: DVec3,
    pub(super) radius: f64,
    /// Bounding capsule: the points within `capsule_radius` of the segment `a`-`b` (the
    /// capsule itself, a ball's centre, a cylinder's axis, a box's longest axis).
    a: DVec3,
    b: DVec3,
    capsule_radius: f64,
    /// A fixed half-space's plane in the cell frame: unit outward normal and offset, the
    /// solid being `{ p : normal . p <= offset }`.
    plane: Option<(DVec3, f64)>,
}

/// The volumes' points placed in the cell frame.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub(super) struct Placed {
    centre: DVec3,
    a: DVec3,
    b: DVec3,
}

/// A placed solid as the bounds read it.
pub(super) struct Solid<'m> {
    pub(super) shape: &'m Shape,
    pub(super) volumes: &'m Volumes,
    /// The solid's own frame in the cell frame.
    pub(super) pose: &'m DAffine3,
    pub(super) placed: &'m Placed,
}

impl Volumes {
    /// The volumes of `shape`; `plane` is its plane in the cell frame when it is a fixed
    /// half-space.
    pub(super) fn new(shape: &Shape, plane: Option<(DVec3, f64)>) -> Self {
        let (centre, radius) = bounding_sphere(shape);
        let (a, b, capsule_radius) = bounding_capsule(shape, centre, radius);
        Volumes {
            centre,
            radius,
            a,
            b,
            capsule_radius,
            plane,
        }
    }

    /// The volumes' points for the solid placed at `pose`.
    pub(super) fn place(&self, pose: &DAffine3) -> Placed {
        Placed {
            centre: pose.transform_point3(self.centre),
            a: pose.transform_point3(self.a),
            b: pose.transform_point3(self.b),
        }
    }
}

/// The quick bound: the two bounding spheres, or a plane against the other's sphere.
pub(super) fn quick(i: &Solid<'_>, j: &Solid<'_>) -> f64 {
    let bound = match (i.volumes.plane, j.volumes.plane) {
        (Some((normal, offset)), None) => normal.dot(j.placed.centre) - offset - j.volumes.radius,
        (None, Some((normal, offset))) => normal.dot(i.placed.centre) - offset - i.volumes.radius,
        (None, None) => {
            i.placed.centre.distance(j.placed.centre) - i.volumes.radius - j.volumes.radius
        }
        // Never a checked pair: both are static.
        (Some(_), Some(_)) => f64::NEG_INFINITY,
    };
    bound - ROUNDING_M
}

/// The tight bound: against a plane the other solid's exact extent along its normal;
/// otherwise the highest of the quick one, the bounding capsules' distance, and for a box
/// its three slabs. Costs a few times the quick one.
pub(super) fn tight(i: &Solid<'_>, j: &Solid<'_>) -> f64 {
    let quick = quick(i, j);
    match (i.volumes.plane, j.volumes.plane) {
        (Some(plane), None) => return quick.max(plane_distance(plane, j) - ROUNDING_M),
        (None, Some(plane)) => return quick.max(plane_distance(plane, i) - ROUNDING_M),
        (Some(_), Some(_)) => return quick,
        (None, None) => {}
    }
    let capsules = segment_distance(i.placed.a, i.placed.b, j.placed.a, j.placed.b)
        - i.volumes.capsule_radius
        - j.volumes.capsule_radius
        - ROUNDING_M;
    quick
        .max(capsules)
        .max(slabs(i, j) - ROUNDING_M)
        .max(slabs(j, i) - ROUNDING_M)
}

/// The exact signed distance of a fixed half-space and a solid that is not a hull (its
/// support along the plane's normal is a closed form), when one of `i` and `j` is such a
/// pair: the distance of the solid's deepest point from the plane, which is also the depth
/// of a penetration. Cheaper than parry's query by the pose conversion and the dispatch,
/// and the same figure up to rounding (about 1e-15 m).
pub(super) fn plane_exact(i: &Solid<'_>, j: &Solid<'_>) -> Option<f64> {
    let (plane, solid) = match (i.volumes.plane, j.volumes.plane) {
        (Some(plane), None) => (plane, j),
        (None, Some(plane)) => (plane, i),
        _ => return None,
    };
    match solid.shape {
        Shape::ConvexHull { .. } => None,
        _ => Some(plane_distance(plane, solid)),
    }
}

/// The signed distance of `solid` from the half-space `{ p : normal . p <= offset }`:
/// exact but for a hull, which its bounding sphere stands for.
fn plane_distance((normal, offset): (DVec3, f64), solid: &Solid<'_>) -> f64 {
    normal.dot(solid.placed.centre) - offset - extent(solid, normal)
}

/// How far `solid` reaches from its bounding sphere's centre along the unit vector `u`
/// (its support): exact for every kind but a hull (its bounding sphere's radius).
fn extent(solid: &Solid<'_>, u: DVec3) -> f64 {
    let axes = &solid.pose.matrix3;
    match solid.shape {
        Shape::Box { half_extents } => {
            u.dot(axes.x_axis).abs() * half_extents.x
                + u.dot(axes.y_axis).abs() * half_extents.y
                + u.dot(axes.z_axis).abs() * half_extents.z
        }
        Shape::Cylinder {
            radius,
            half_length,
        } => {
            // Its axis is its frame's z: the end rim's farthest point along u.
            let along = u.dot(axes.z_axis);
            along.abs() * half_length + radius * (1.0 - along * along).max(0.0).sqrt()
        }
        Shape::Capsule { radius, .. } => {
            u.dot(solid.placed.b - solid.placed.a).abs() / 2.0 + radius
        }
        Shape::Sphere { radius } => *radius,
        Shape::ConvexHull { .. } | Shape::HalfSpace { .. } => solid.volumes.radius,
    }
}

/// A lower bound from `boxed`'s three slabs when it is a box (otherwise none): along each
/// of its axes, the gap between its own extent and `other`'s; the axes are orthonormal, so
/// the gaps' Euclidean sum bounds the distance. Where the two overlap along every axis it
/// gives nothing (the other bounds cover overlap).
fn slabs(boxed: &Solid<'_>, other: &Solid<'_>) -> f64 {
    let Shape::Box { half_extents } = boxed.shape else {
        return f64::NEG_INFINITY;
    };
    let offset = other.placed.centre - boxed.pose.translation;
    let axes = &boxed.pose.matrix3;
    let gap =
        |axis: DVec3, half: f64| (offset.dot(axis).abs() - half - extent(other, axis)).max(0.0);
    let squares = [
        gap(axes.x_axis, half_extents.x),
        gap(axes.y_axis, half_extents.y),
        gap(axes.z_axis, half_extents.z),
    ]
    .iter()
    .map(|g| g * g)
    .sum::<f64>();
    if squares > 0.0 {
        squares.sqrt()
    } else {
        f64::NEG_INFINITY
    }
}

/// A sphere around `shape` in its own frame, as (centre, radius); a half-space gets an
/// infinite one (its plane bounds it instead).
fn bounding_sphere(shape: &Shape) -> (DVec3, f64) {
    match shape {
        Shape::Capsule { a, b, radius } => ((*a + *b) / 2.0, a.distance(*b) / 2.0 + radius),
        Shape::ConvexHull { points } => {
            let (low, high) = points.iter().fold(
                (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
                |(lo, hi), p| (lo.min(*p), hi.max(*p)),
            );
            let centre = (low + high) / 2.0;
            let radius = points
                .iter()
                .map(|p| p.distance(centre))
                .fold(0.0, f64::max);
            (centre, radius)
        }
        other => (
            DVec3::ZERO,
            other.bounding_radius().unwrap_or(f64::INFINITY),
        ),
    }
}

/// A capsule around `shape` in its own frame, as (a, b, radius): a cylinder lies within
/// the capsule on its axis with its radius, a box within the one on its longest axis with
/// the radius of its cross-section's corner; others within their sphere.
fn bounding_capsule(shape: &Shape, centre: DVec3, radius: f64) -> (DVec3, DVec3, f64) {
    match shape {
        Shape::Capsule { a, b, radius } => (*a, *b, *radius),
        Shape::Cylinder {
            radius,
            half_length,
        } => (DVec3::Z * -half_length, DVec3::Z * *half_length, *radius),
        Shape::Box { half_extents } => {
            let h = *half_extents;
            let (axis, across) = if h.x >= h.y && h.x >= h.z {
                (DVec3::X * h.x, h.y.hypot(h.z))
            } else if h.y >= h.z {
                (DVec3::Y * h.y, h.x.hypot(h.z))
            } else {
                (DVec3::Z * h.z, h.x.hypot(h.y))
            };
            (-axis, axis, across)
        }
        Shape::Sphere { .. } | Shape::ConvexHull { .. } | Shape::HalfSpace { .. } => {
            (centre, centre, radius)
        }
    }
}
