//! The one adapter between our geometry (glam 0.34) and parry3d-f64 (glamx, on glam 0.33):
//! every vector, rotation and shape crosses here, through plain arrays, so the two glam
//! versions never meet anywhere else. Owns the conversion, the signed distance and the
//! distance of two segments (the broad phase's bounding capsules); it knows nothing of rigs
//! or cells.

use crate::rig::Shape;
use glam::{DAffine3, DQuat, DVec3};
use parry3d_f64::math::{Pose, Rotation, Vector};
use parry3d_f64::query;
use parry3d_f64::shape::{Capsule, HalfSpace, Segment, Shape as ParryShape, SharedShape};

fn vector(v: DVec3) -> Vector {
    Vector::from_array(v.to_array())
}

/// `frame` (a rigid transform) as parry's pose.
pub(super) fn pose(frame: &DAffine3) -> Pose {
    let rotation = DQuat::from_mat3(&frame.matrix3).normalize();
    Pose::from_parts(
        vector(frame.translation),
        Rotation::from_array(rotation.to_array()),
    )
}

/// A rotation of +90 deg about x, which takes y to z: parry's cylinder stands on its y
/// axis, ours on its z axis.
fn y_to_z() -> DAffine3 {
    DAffine3::from_rotation_x(std::f64::consts::FRAC_PI_2)
}

/// A parry solid for `shape`, and the frame it must be placed in within the shape's own
/// frame (identity but for the cylinder). `None` when a hull's points span no volume.
pub(super) fn solid(shape: &Shape) -> Option<(SharedShape, DAffine3)> {
    let placed = match shape {
        Shape::Box { half_extents } => (
            SharedShape::cuboid(half_extents.x, half_extents.y, half_extents.z),
            DAffine3::IDENTITY,
        ),
        Shape::Cylinder {
            radius,
            half_length,
        } => (SharedShape::cylinder(*half_length, *radius), y_to_z()),
        Shape::Sphere { radius } => (SharedShape::ball(*radius), DAffine3::IDENTITY),
        Shape::Capsule { a, b, radius } => (
            SharedShape::capsule(vector(*a), vector(*b), *radius),
            DAffine3::IDENTITY,
        ),
        Shape::HalfSpace { normal } => {
            (SharedShape::halfspace(vector(*normal)), DAffine3::IDENTITY)
        }
        Shape::ConvexHull { points } => {
            let points: Vec<Vector> = points.iter().map(|p| vector(*p)).collect();
            (SharedShape::convex_hull(&points)?, DAffine3::IDENTITY)
        }
    };
    Some(placed)
}

/// The signed distance between two placed solids: the gap when apart, minus the
/// penetration depth when they overlap.
pub(super) fn signed_distance(
    pose1: &Pose,
    solid1: &SharedShape,
    pose2: &Pose,
    solid2: &SharedShape,
) -> f64 {
    // parry 0.31.1's contact of a support map against a half-space, in that order, gives
    // a wrong depth (a capsule 0.03 m into a floor came back 0.07 m); the half-space first
    // gives the right one. Distance is symmetric, so the half-space always goes first.
    let is_half_space = |s: &SharedShape| s.as_shape::<HalfSpace>().is_some();
    if is_half_space(solid2) && !is_half_space(solid1) {
        return signed_distance(pose2, solid2, pose1, solid1);
    }
    if let (Some(c1), Some(c2)) = (solid1.as_capsule(), solid2.as_capsule()) {
        return capsule_capsule(pose1, c1, pose2, c2);
    }
    // Every pair we query is supported: each solid is a support map or a half-space, and
    // two half-spaces are never a checked pair (both static). Should parry ever refuse a
    // pair, the answer is "collision" (fail closed), not "free".
    let ((core1, radius1), (core2, radius2)) = (core(solid1), core(solid2));
    let Ok(gap) = query::distance(pose1, core1, pose2, core2) else {
        return f64::NEG_INFINITY;
    };
    if gap.distance > 0.0 {
        return gap.distance - radius1 - radius2;
    }
    // The cores touch: the depth is the solids' own. Not the cores' depth less the radii:
    // parry's EPA is not reliable on a bare segment (one into a cylinder came back 0.19 m
    // deep where their bounding spheres allow 0.16 m at most).
    match query::contact(pose1, solid1.as_ref(), pose2, solid2.as_ref(), 0.0) {
        Ok(Some(contact)) => contact.dist.min(0.0),
        Ok(None) => 0.0,
        Err(_) => f64::NEG_INFINITY,
    }
}

/// The solid a shape is measured from, and the radius it is grown by: a capsule's segment
/// and radius (a capsule is its segment grown by its radius, and so is its distance from
/// anything: the segment's less the radius); any other shape itself, grown by nothing.
///
/// Against a box or a hull the segment's distance is exact (GJK on two polytopes ends on
/// their closest features) where the capsule's stopped up to 13 um above it; against a
/// ball or a half-space parry's query is a closed form either way; against a cylinder GJK
/// keeps its tolerance on the round solid, about 10 um either way (src/cell/broad_tests.rs
/// measures it against the closed form). And a capsule that overlaps a solid less deeply
/// than its radius needs no penetration query (EPA) at all.
fn core(solid: &SharedShape) -> (&dyn ParryShape, f64) {
    match solid.as_capsule() {
        Some(capsule) => (&capsule.segment, capsule.radius),
        None => (solid.as_ref(), 0.0),
    }
}

/// Two capsules' signed distance in closed form: their segments' distance less both radii.
/// GJK (parry's general path) stops within a few micrometres above the true distance,
/// which put rows right at the margin on the wrong side of it against an independent
/// checker (tests/cell_agreement.rs); the segments' distance is exact. When the segments
/// themselves cross, the depth given (the radii's sum) is the least it can be.
fn capsule_capsule(pose1: &Pose, c1: &Capsule, pose2: &Pose, c2: &Capsule) -> f64 {
    let pos12 = pose1.inv_mul(pose2);
    query::details::distance_segment_segment(&pos12, &c1.segment, &c2.segment)
        - c1.radius
        - c2.radius
}

/// The distance between the segments `a1`-`b1` and `a2`-`b2` (the broad phase's bounding
/// capsules), from parry's closest points of two segments.
pub(super) fn segment_distance(a1: DVec3, b1: DVec3, a2: DVec3, b2: DVec3) -> f64 {
    let (s1, s2) = (
        Segment::new(vector(a1), vector(b1)),
        Segment::new(vector(a2), vector(b2)),
    );
    let (at1, at2) = query::details::closest_points_segment_segment_with_locations_nD(
        (&s1.a, &s1.b),
        (&s2.a, &s2.b),
    );
    s1.point_at(&at1).distance(s2.point_at(&at2))
}
