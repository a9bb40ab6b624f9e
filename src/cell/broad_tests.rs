//! The broad phase against parry's exact distances, on seeded random solids and poses: no
//! bound ever stands above the exact distance it prunes, and the pruned search finds the
//! same closest pair and distance as measuring every pair. And a capsule measured from its
//! segment against the closed form of its distance from a box and from a cylinder.

use super::bound::{self, Volumes};
use super::parry::{pose, signed_distance, solid};
use super::*;
use crate::rig::load_rig;
use glam::DQuat;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Random poses tried for each pair of kinds.
const TRIALS: usize = 3000;

/// How far the closed form of a half-space pair may lie from parry's query: both are exact,
/// computed in another order, so only rounding (about 1e-15 m on metres) separates them.
const PLANE_AGREEMENT_M: f64 = 1e-12;

fn random_vector(rng: &mut ChaCha8Rng, half: f64) -> DVec3 {
    DVec3::new(
        rng.random_range(-half..half),
        rng.random_range(-half..half),
        rng.random_range(-half..half),
    )
}

fn random_pose(rng: &mut ChaCha8Rng) -> DAffine3 {
    let axis = random_vector(rng, 1.0).try_normalize().unwrap_or(DVec3::Z);
    let turn = DQuat::from_axis_angle(axis, rng.random_range(-3.2..3.2));
    DAffine3::from_rotation_translation(turn, random_vector(rng, 0.4))
}

/// One solid of every kind, its sizes up to `largest` (m).
fn every_kind(rng: &mut ChaCha8Rng, largest: f64) -> Vec<Shape> {
    let mut size = || rng.random_range(0.01..largest);
    let (x, y, z, r, h) = (size(), size(), size(), size(), size());
    let hull = (0..8).map(|_| random_vector(rng, largest)).collect();
    vec![
        Shape::Box {
            half_extents: DVec3::new(x, y, z),
        },
        Shape::Cylinder {
            radius: r,
            half_length: h,
        },
        Shape::Sphere { radius: r },
        Shape::Capsule {
            a: random_vector(rng, largest),
            b: random_vector(rng, largest),
            radius: r / 2.0,
        },
        Shape::ConvexHull { points: hull },
        Shape::HalfSpace {
            normal: random_vector(rng, 1.0).normalize(),
        },
    ]
}

/// A solid placed at `at`, with what the bounds and the exact query read.
struct Placed {
    shape: Shape,
    pose: DAffine3,
    volumes: Volumes,
    placed: bound::Placed,
    solid: parry3d_f64::shape::SharedShape,
    solid_pose: parry3d_f64::math::Pose,
}

fn placed(shape: &Shape, at: DAffine3) -> Placed {
    let plane = match shape {
        Shape::HalfSpace { normal } => {
            let n = at.transform_vector3(*normal).normalize();
            Some((n, n.dot(at.translation)))
        }
        _ => None,
    };
    let volumes = Volumes::new(shape, plane);
    let (solid, frame) = solid(shape).expect("the random hull spans a volume");
    Placed {
        shape: shape.clone(),
        pose: at,
        placed: volumes.place(&at),
        volumes,
        solid,
        solid_pose: pose(&(at * frame)),
    }
}

fn view(p: &Placed) -> bound::Solid<'_> {
    bound::Solid {
        shape: &p.shape,
        volumes: &p.volumes,
        pose: &p.pose,
        placed: &p.placed,
    }
}

#[test]
fn no_bound_is_above_the_exact_distance_for_any_pair_of_kinds() {
    let mut rng = ChaCha8Rng::seed_from_u64(27);
    let (mut pruned, mut overlapping, mut plane_pairs) = (0, 0, 0);
    for _ in 0..TRIALS {
        let kinds = every_kind(&mut rng, 0.2);
        for (i, first) in kinds.iter().enumerate() {
            for second in &kinds[i..] {
                let both_planes = [first, second]
                    .iter()
                    .all(|s| matches!(s, Shape::HalfSpace { .. }));
                if both_planes {
                    continue;
                }
                let (p, q) = (
                    placed(first, random_pose(&mut rng)),
                    placed(second, random_pose(&mut rng)),
                );
                let exact = signed_distance(&p.solid_pose, &p.solid, &q.solid_pose, &q.solid);
                let (quick, tight) = (
                    bound::quick(&view(&p), &view(&q)),
                    bound::tight(&view(&p), &view(&q)),
                );
                assert!(
                    quick <= exact && tight <= exact,
                    "{} / {}: quick {quick}, tight {tight} above the exact {exact}",
                    first.kind(),
                    second.kind()
                );
                assert!(tight >= quick, "the tight bound is never looser");
                // The closed form the model measures a half-space pair by is parry's figure.
                if let Some(closed) = bound::plane_exact(&view(&p), &view(&q)) {
                    assert!(
                        (closed - exact).abs() < PLANE_AGREEMENT_M,
                        "{} / {}: closed form {closed}, parry {exact}",
                        first.kind(),
                        second.kind()
                    );
                    plane_pairs += 1;
                }
                pruned += usize::from(tight > 0.0);
                overlapping += usize::from(exact < 0.0);
            }
        }
    }
    // The draw holds both gaps the bounds prune on and overlaps, and every bounded kind
    // but the hull against a half-space.
    assert!(
        pruned > TRIALS && overlapping > TRIALS,
        "{pruned} {overlapping}"
    );
    assert_eq!(plane_pairs, 4 * TRIALS);
}

/// The IRB 120 on its floor with a tool of a box, a cylinder and a hull beyond its flange,
/// and objects of every bounded kind, turned at random, around it within its reach.
fn crowded_model(rng: &mut ChaCha8Rng) -> CollisionModel {
    let rig = load_rig(&crate::rig::shipped::path("irb120.toml")).unwrap();
    let mut cell = Cell::builtin();
    let tool_solids = every_kind(rng, 0.04);
    cell.tool = Some(Tool {
        name: "tool".into(),
        bodies: [0, 1, 4]
            .iter()
            .map(|&k| Collision {
                origin: DAffine3::from_translation(DVec3::Z * 0.1),
                shape: tool_solids[k].clone(),
            })
            .collect(),
        tcp: DAffine3::IDENTITY,
    });
    for i in 0..15 {
        let shape = every_kind(rng, 0.1).swap_remove(i % 5);
        let mut at = random_pose(rng);
        let angle = rng.random_range(-3.2..3.2);
        let reach = rng.random_range(0.35..0.75);
        at.translation = DVec3::new(
            reach * f64::cos(angle),
            reach * f64::sin(angle),
            rng.random_range(0.05..0.8),
        );
        cell.objects.push(CellObject {
            name: format!("object_{i}"),
            pose: at,
            shape,
        });
    }
    CollisionModel::new(&rig, &cell).unwrap()
}

#[test]
fn the_pruned_search_finds_what_measuring_every_pair_finds() {
    let mut rng = ChaCha8Rng::seed_from_u64(2027);
    let model = crowded_model(&mut rng);
    let rig = load_rig(&crate::rig::shipped::path("irb120.toml")).unwrap();
    let mut scratch = model.scratch();
    let mut every = Vec::new();
    let mut statuses = [0usize; 3];
    for _ in 0..TRIALS {
        let q: Vec<f64> = rig
            .joints
            .iter()
            .map(|j| rng.random_range(j.limits.lower..j.limits.upper))
            .collect();
        let found = model.clearance(&q, &mut scratch);
        model.pairs_within(&q, f64::INFINITY, &mut scratch, &mut every);
        assert_eq!(
            every.len(),
            model.checked_pairs().len(),
            "every pair measured"
        );
        let closest = every
            .iter()
            .min_by(|p, q| p.distance_m.total_cmp(&q.distance_m))
            .unwrap();
        assert_eq!(found.distance_m, closest.distance_m, "at {q:?}");
        assert_eq!((found.a, found.b), (closest.a, closest.b), "at {q:?}");
        statuses[model.status(found.distance_m) as usize] += 1;
    }
    // Free, within the margin and in collision all occur.
    assert!(statuses.iter().all(|&n| n > 0), "{statuses:?}");
}

/// The distance of the segment `a`-`b` from a convex solid, given the distance of a point
/// from it: the point distance is convex along the segment, so a ternary search finds its
/// least to rounding.
fn least_along(a: DVec3, b: DVec3, distance: impl Fn(DVec3) -> f64) -> f64 {
    let at = |t: f64| distance(a + (b - a) * t);
    let (mut low, mut high) = (0.0, 1.0);
    for _ in 0..200 {
        let (t1, t2) = (low + (high - low) / 3.0, high - (high - low) / 3.0);
        if at(t1) < at(t2) {
            high = t2;
        } else {
            low = t1;
        }
    }
    at((low + high) / 2.0).min(at(0.0)).min(at(1.0))
}

/// The distance of a capsule apart from a box or a cylinder in closed form: its segment's
/// distance (in the other's frame, a point's distance from a box or a cylinder is a
/// formula) less its radius. `None` for another kind.
fn closed_form(capsule: &Placed, other: &Placed) -> Option<f64> {
    let Shape::Capsule { a, b, radius } = &capsule.shape else {
        return None;
    };
    let into_other = other.pose.inverse() * capsule.pose;
    let (a, b) = (
        into_other.transform_point3(*a),
        into_other.transform_point3(*b),
    );
    let segment = match other.shape {
        Shape::Box { half_extents } => {
            least_along(a, b, |p| (p.abs() - half_extents).max(DVec3::ZERO).length())
        }
        Shape::Cylinder {
            radius,
            half_length,
        } => least_along(a, b, |p| {
            let out = (p.truncate().length() - radius).max(0.0);
            out.hypot((p.z.abs() - half_length).max(0.0))
        }),
        _ => return None,
    };
    Some(segment - radius)
}

#[test]
fn a_capsule_apart_from_a_box_is_measured_exactly_and_from_a_cylinder_to_gjk_tolerance() {
    let mut rng = ChaCha8Rng::seed_from_u64(120);
    let (mut largest, mut measured) = ([0.0f64; 2], 0);
    while measured < TRIALS {
        let kinds = every_kind(&mut rng, 0.2);
        let capsule = placed(&kinds[3], random_pose(&mut rng));
        for (k, other) in [0, 1].into_iter().enumerate() {
            let other = placed(&kinds[other], random_pose(&mut rng));
            let truth = closed_form(&capsule, &other).unwrap();
            if truth <= 0.0 {
                continue;
            }
            let ours = signed_distance(
                &capsule.solid_pose,
                &capsule.solid,
                &other.solid_pose,
                &other.solid,
            );
            largest[k] = largest[k].max((ours - truth).abs());
            measured += 1;
        }
    }
    // The box is a polytope: exact but for rounding. The cylinder is round: GJK's own
    // tolerance on it, measured on the whole capsule about as large (9 um).
    assert!(largest[0] < 1e-12 && largest[1] < 2e-5, "{largest:?}");
}
