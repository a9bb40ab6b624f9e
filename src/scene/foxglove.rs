//! A live scene as Foxglove draws it: [`SceneView`] (walls with their openings, cylinders,
//! paint, the cell's solids, the rig's collision bodies on their frames) and paint added
//! since, and the closest pair of bodies marked, as `foxglove.SceneUpdate` messages of the `foxglove`
//! crate (<https://docs.foxglove.dev/docs/visualization/message-schemas/scene-update>). Used by
//! the run log's writer thread and the live Foxglove server, never by the streaming cycle.
//! Owns only the translation; it must not build, measure or change a scene.

use super::{
    ClosestView, CylinderView, PaintQuad, Point, PoseView, SceneView, SolidView, WallView,
};
use foxglove::messages::{
    Color, CylinderPrimitive, LinePrimitive, Point3, Pose, Quaternion, SceneEntity,
    SceneEntityDeletion, SceneUpdate, Timestamp, TriangleListPrimitive, Vector3, line_primitive,
    scene_entity_deletion,
};
use glam::{DQuat, DVec2, DVec3};

/// Entity ids: the static scene, and one entity per batch of paint (`paint-<n>`).
pub const WALLS_ENTITY: &str = "walls";
pub const CYLINDERS_ENTITY: &str = "cylinders";
/// The cell's static objects, in the scene's frame.
pub const CELL_ENTITY: &str = "cell";
/// The rig's collision bodies on frame k of the rig: `bodies-<k>`, in that frame's tf id.
pub const BODIES_PREFIX: &str = "bodies-";
/// The closest pair when within the margin: its two solids again, marked, as `closest-0`
/// and `closest-1` (each in its own frame).
pub const CLOSEST_PREFIX: &str = "closest-";
const PAINT_PREFIX: &str = "paint-";
/// The cell's parts: one entity each (`part-part_0`), replaced when it moves or is judged.
pub const PART_PREFIX: &str = "part-";
/// A part by the twin's judgement: at rest and not picked yet, carried, placed, dropped.
const PART_AT_REST: Color = rgba(0.47, 0.47, 0.78, 0.8);
const PART_CARRIED: Color = rgba(0.16, 0.47, 0.94, 0.9);
const PART_PLACED: Color = rgba(0.16, 0.67, 0.27, 0.9);
const PART_DROPPED: Color = rgba(0.85, 0.1, 0.1, 0.9);
/// The colours of the page (`src/view/page`): pale walls, bark brown, the paint's blue.
const WALL: Color = rgba(0.85, 0.85, 0.8, 0.6);
const EDGE: Color = rgba(0.3, 0.3, 0.3, 1.0);
const BARK: Color = rgba(0.45, 0.32, 0.2, 1.0);
const PAINT: Color = rgba(0.15, 0.35, 0.85, 1.0);
/// The page's colours for the cell's objects, the rig's bodies, a pair within the margin
/// and a pair in collision.
const OBJECT: Color = rgba(0.55, 0.6, 0.65, 0.35);
const BODY: Color = rgba(0.95, 0.6, 0.2, 0.35);
const NEAR: Color = rgba(0.95, 0.75, 0.1, 0.85);
const HIT: Color = rgba(0.85, 0.1, 0.1, 0.9);
/// Outline width in pixels (scale invariant), like the page's.
const EDGE_PX: f64 = 2.0;
/// Paint sits this far in front of its wall, so it is not hidden in the wall's surface.
const PAINT_OFFSET_M: f64 = 0.002;

const fn rgba(r: f64, g: f64, b: f64, a: f64) -> Color {
    Color { r, g, b, a }
}

/// The whole scene in frame `frame_id`: every earlier entity deleted, then the walls, the
/// cylinders, the cell's solids, the rig's bodies on their frames (`body_frames[k]`: the tf
/// frame id of the rig's frame k; bodies on frames it lacks are left out) and all paint so
/// far (as entity `paint-0`, so later batches start at 1).
pub fn full_update(
    view: &SceneView,
    frame_id: &str,
    body_frames: &[String],
    stamp: Timestamp,
) -> SceneUpdate {
    let entity = |id: &str| SceneEntity {
        timestamp: Some(stamp),
        frame_id: frame_id.to_owned(),
        id: id.to_owned(),
        ..SceneEntity::default()
    };
    let mut entities = Vec::new();
    if !view.walls.is_empty() {
        let mut walls = entity(WALLS_ENTITY);
        for wall in &view.walls {
            walls.triangles.push(wall_surface(wall));
            walls.lines.extend(wall_outlines(wall));
        }
        entities.push(walls);
    }
    if !view.cylinders.is_empty() {
        let mut cylinders = entity(CYLINDERS_ENTITY);
        cylinders
            .cylinders
            .extend(view.cylinders.iter().map(cylinder));
        entities.push(cylinders);
    }
    if !view.solids.is_empty() {
        let mut cell = entity(CELL_ENTITY);
        cell.triangles
            .extend(view.solids.iter().map(|solid| triangles(solid, OBJECT)));
        entities.push(cell);
    }
    for (frame, frame_name) in body_frames.iter().enumerate() {
        let mut bodies = entity(&format!("{BODIES_PREFIX}{frame}"));
        bodies.frame_id = frame_name.clone();
        bodies.triangles.extend(
            view.bodies
                .iter()
                .filter(|body| body.frame == frame)
                .map(|body| triangles(&body.solid, BODY)),
        );
        if !bodies.triangles.is_empty() {
            entities.push(bodies);
        }
    }
    entities.extend(paint_entity(view, &view.paint, 0, frame_id, stamp));
    SceneUpdate {
        deletions: vec![SceneEntityDeletion {
            timestamp: Some(stamp),
            r#type: scene_entity_deletion::Type::All as i32,
            id: String::new(),
        }],
        entities,
    }
}

/// Paint added since the last update, as the new entity `paint-<batch>` (batches count from
/// 1 after a [`full_update`]); `None` when there is none.
pub fn paint_update(
    view: &SceneView,
    fresh: &[PaintQuad],
    batch: u64,
    frame_id: &str,
    stamp: Timestamp,
) -> Option<SceneUpdate> {
    paint_entity(view, fresh, batch, frame_id, stamp).map(|entity| SceneUpdate {
        deletions: Vec::new(),
        entities: vec![entity],
    })
}

/// The closest pair marked (`closest`, `None` when no pair is within the margin): the
/// earlier mark deleted, then each of its two solids again in the mark's colour, in its own
/// frame (a body on its rig frame's tf id, a cell object in `frame_id`).
pub fn closest_update(
    view: &SceneView,
    closest: Option<&ClosestView>,
    frame_id: &str,
    body_frames: &[String],
    stamp: Timestamp,
) -> SceneUpdate {
    let deletions = (0..2)
        .map(|i| SceneEntityDeletion {
            timestamp: Some(stamp),
            r#type: scene_entity_deletion::Type::MatchingId as i32,
            id: format!("{CLOSEST_PREFIX}{i}"),
        })
        .collect();
    let mut entities = Vec::new();
    if let Some(closest) = closest {
        let colour = if closest.distance_m <= 0.0 { HIT } else { NEAR };
        for (i, name) in [&closest.a, &closest.b].into_iter().enumerate() {
            let mut mark = SceneEntity {
                timestamp: Some(stamp),
                frame_id: frame_id.to_owned(),
                id: format!("{CLOSEST_PREFIX}{i}"),
                ..SceneEntity::default()
            };
            for solid in view.solids.iter().filter(|s| &s.name == name) {
                mark.triangles.push(triangles(solid, colour));
            }
            for body in view.bodies.iter().filter(|b| &b.solid.name == name) {
                if let Some(frame) = body_frames.get(body.frame) {
                    mark.frame_id = frame.clone();
                    mark.triangles.push(triangles(&body.solid, colour));
                }
            }
            if !mark.triangles.is_empty() {
                entities.push(mark);
            }
        }
    }
    SceneUpdate {
        deletions,
        entities,
    }
}

/// The cell's parts at `poses` (the rig's base frame, `frame_id`), each `solids[i]` (in
/// its own frame) coloured by `states[i]`, the twin's word for it (`placed`, `carried`,
/// `dropped`, else at rest).
pub fn parts_update(
    solids: &[SolidView],
    poses: &[PoseView],
    states: &[&str],
    frame_id: &str,
    stamp: Timestamp,
) -> SceneUpdate {
    let entities = solids
        .iter()
        .zip(poses)
        .enumerate()
        .map(|(i, (solid, pose))| {
            let colour = match states.get(i).copied() {
                Some("placed") => PART_PLACED,
                Some("carried") => PART_CARRIED,
                Some("dropped") => PART_DROPPED,
                _ => PART_AT_REST,
            };
            let placed = SolidView {
                pose: *pose,
                ..solid.clone()
            };
            SceneEntity {
                timestamp: Some(stamp),
                frame_id: frame_id.to_owned(),
                id: format!("{PART_PREFIX}{}", solid.name),
                triangles: vec![triangles(&placed, colour)],
                ..SceneEntity::default()
            }
        })
        .collect();
    SceneUpdate {
        deletions: Vec::new(),
        entities,
    }
}

/// A solid's triangles at its pose, in `colour`.
fn triangles(solid: &SolidView, colour: Color) -> TriangleListPrimitive {
    TriangleListPrimitive {
        pose: Some(pose(&solid.pose)),
        points: solid
            .triangles
            .iter()
            .map(|p| point(DVec3::from_array(*p)))
            .collect(),
        color: Some(colour),
        ..TriangleListPrimitive::default()
    }
}

fn pose(p: &PoseView) -> Pose {
    let [x, y, z, w] = p.orientation;
    Pose {
        position: Some(vector(DVec3::from_array(p.position))),
        orientation: Some(Quaternion { x, y, z, w }),
    }
}

fn paint_entity(
    view: &SceneView,
    quads: &[PaintQuad],
    batch: u64,
    frame_id: &str,
    stamp: Timestamp,
) -> Option<SceneEntity> {
    if quads.is_empty() {
        return None;
    }
    let mut points = Vec::with_capacity(quads.len() * 6);
    for quad in quads {
        // Lifted off the wall along its front normal (the side the rig paints).
        let lift = view
            .walls
            .get(quad.wall)
            .map_or(DVec3::ZERO, |w| normal(w) * PAINT_OFFSET_M);
        let [a, b, c, d] = quad.quad.map(|p| point(DVec3::from_array(p) + lift));
        points.extend([a, b, c, a, c, d]);
    }
    Some(SceneEntity {
        timestamp: Some(stamp),
        frame_id: frame_id.to_owned(),
        id: format!("{PAINT_PREFIX}{batch}"),
        triangles: vec![TriangleListPrimitive {
            pose: Some(identity()),
            points,
            color: Some(PAINT),
            ..TriangleListPrimitive::default()
        }],
        ..SceneEntity::default()
    })
}

/// The wall's front normal: `(c1 - c0) x (c3 - c0)`, normalised.
fn normal(wall: &WallView) -> DVec3 {
    let [c0, c1, _, c3] = wall.corners.map(DVec3::from_array);
    (c1 - c0).cross(c3 - c0).normalize_or_zero()
}

/// The wall less its openings, as triangles: the wall's rectangle cut into a grid at every
/// opening's edges, each cell kept unless it lies in an opening.
fn wall_surface(wall: &WallView) -> TriangleListPrimitive {
    let [c0, c1, _, c3] = wall.corners.map(DVec3::from_array);
    let (along, up) = (c1 - c0, c3 - c0);
    let (width, height) = (along.length(), up.length());
    let (u, v) = (
        along / width.max(f64::MIN_POSITIVE),
        up / height.max(f64::MIN_POSITIVE),
    );
    let local = |p: &Point| {
        let d = DVec3::from_array(*p) - c0;
        DVec2::new(d.dot(u), d.dot(v))
    };
    let holes: Vec<(DVec2, DVec2)> = wall
        .openings
        .iter()
        .map(|o| {
            let corners = o.map(|p| local(&p));
            let low = corners.iter().fold(DVec2::INFINITY, |m, p| m.min(*p));
            let high = corners.iter().fold(DVec2::NEG_INFINITY, |m, p| m.max(*p));
            (low.max(DVec2::ZERO), high.min(DVec2::new(width, height)))
        })
        .collect();
    let xs = breaks(0.0, width, holes.iter().flat_map(|(l, h)| [l.x, h.x]));
    let ys = breaks(0.0, height, holes.iter().flat_map(|(l, h)| [l.y, h.y]));
    let at = |x: f64, y: f64| point(c0 + u * x + v * y);
    let mut points = Vec::new();
    for x in xs.windows(2) {
        for y in ys.windows(2) {
            let centre = DVec2::new((x[0] + x[1]) / 2.0, (y[0] + y[1]) / 2.0);
            let open = holes
                .iter()
                .any(|(l, h)| centre.cmpgt(*l).all() && centre.cmplt(*h).all());
            if !open {
                points.extend([at(x[0], y[0]), at(x[1], y[0]), at(x[1], y[1])]);
                points.extend([at(x[0], y[0]), at(x[1], y[1]), at(x[0], y[1])]);
            }
        }
    }
    TriangleListPrimitive {
        pose: Some(identity()),
        points,
        color: Some(WALL),
        ..TriangleListPrimitive::default()
    }
}

/// The sorted, distinct cut positions within `[low, high]`, both ends included.
fn breaks(low: f64, high: f64, cuts: impl Iterator<Item = f64>) -> Vec<f64> {
    let mut all: Vec<f64> = [low, high]
        .into_iter()
        .chain(cuts.filter(|c| *c > low && *c < high))
        .collect();
    all.sort_by(f64::total_cmp);
    all.dedup();
    all
}

/// The wall's outline and each opening's, as closed loops.
fn wall_outlines(wall: &WallView) -> impl Iterator<Item = LinePrimitive> + '_ {
    std::iter::once(&wall.corners)
        .chain(&wall.openings)
        .map(|outline| LinePrimitive {
            r#type: line_primitive::Type::LineLoop as i32,
            pose: Some(identity()),
            thickness: EDGE_PX,
            scale_invariant: true,
            points: outline
                .iter()
                .map(|p| point(DVec3::from_array(*p)))
                .collect(),
            color: Some(EDGE),
            ..LinePrimitive::default()
        })
}

/// A cylinder from `from` to `to`: Foxglove's cylinder stands on its z axis, centred on its
/// pose, `size` x and y its diameters and z its length.
fn cylinder(c: &CylinderView) -> CylinderPrimitive {
    let (from, to) = (DVec3::from_array(c.from), DVec3::from_array(c.to));
    let axis = to - from;
    let rotation = DQuat::from_rotation_arc(DVec3::Z, axis.normalize_or(DVec3::Z));
    CylinderPrimitive {
        pose: Some(Pose {
            position: Some(vector((from + to) / 2.0)),
            orientation: Some(Quaternion {
                x: rotation.x,
                y: rotation.y,
                z: rotation.z,
                w: rotation.w,
            }),
        }),
        size: Some(Vector3 {
            x: 2.0 * c.radius,
            y: 2.0 * c.radius,
            z: axis.length(),
        }),
        bottom_scale: 1.0,
        top_scale: 1.0,
        color: Some(BARK),
    }
}

fn identity() -> Pose {
    Pose {
        position: Some(Vector3::default()),
        orientation: Some(Quaternion {
            x: 0.0,
            y: 0.0,
            z: 0.0,
            w: 1.0,
        }),
    }
}

fn point(p: DVec3) -> Point3 {
    Point3 {
        x: p.x,
        y: p.y,
        z: p.z,
    }
}

/// A Foxglove vector of a glam one; the log's transforms use it too.
pub(crate) fn vector(p: DVec3) -> Vector3 {
    Vector3 {
        x: p.x,
        y: p.y,
        z: p.z,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn wall_with_door() -> WallView {
        // 4 m x 2.5 m in the x-z plane, a 1 m x 2 m door from x = 1 m.
        let rect =
            |l: f64, r: f64, b: f64, t: f64| [[l, 0.0, b], [r, 0.0, b], [r, 0.0, t], [l, 0.0, t]];
        WallView {
            corners: rect(0.0, 4.0, 0.0, 2.5),
            openings: vec![rect(1.0, 2.0, 0.0, 2.0)],
        }
    }

    fn area(points: &[Point3]) -> f64 {
        points
            .chunks(3)
            .map(|t| {
                let [a, b, c] = [&t[0], &t[1], &t[2]].map(|p| DVec3::new(p.x, p.y, p.z));
                (b - a).cross(c - a).length() / 2.0
            })
            .sum()
    }

    #[test]
    fn a_wall_is_its_area_less_its_openings_and_outlines_them() {
        let wall = wall_with_door();
        let surface = wall_surface(&wall);
        assert_eq!(surface.points.len() % 3, 0);
        assert!((area(&surface.points) - (10.0 - 2.0)).abs() < 1e-9);
        // No triangle inside the door: every centroid is outside it.
        for t in surface.points.chunks(3) {
            let (x, z) = (
                (t[0].x + t[1].x + t[2].x) / 3.0,
                (t[0].z + t[1].z + t[2].z) / 3.0,
            );
            assert!(
                !(x > 1.0 && x < 2.0 && z < 2.0),
                "triangle in the door at {x}, {z}"
            );
        }
        assert_eq!(wall_outlines(&wall).count(), 2);
    }

    #[test]
    fn full_then_paint_updates() {
        let view = SceneView {
            walls: vec![wall_with_door()],
            cylinders: vec![CylinderView {
                from: [0.0, 0.0, 0.0],
                to: [0.0, 2.0, 0.0],
                radius: 0.1,
            }],
            paint: vec![PaintQuad {
                wall: 0,
                quad: [
                    [3.0, 0.0, 1.0],
                    [3.5, 0.0, 1.0],
                    [3.5, 0.0, 1.5],
                    [3.0, 0.0, 1.5],
                ],
            }],
            ..SceneView::default()
        };
        let stamp = Timestamp::new(1, 0);
        let full = full_update(&view, "world", &[], stamp);
        assert_eq!(full.deletions.len(), 1);
        let ids: Vec<&str> = full.entities.iter().map(|e| e.id.as_str()).collect();
        assert_eq!(ids, ["walls", "cylinders", "paint-0"]);
        let branch = &full.entities[1].cylinders[0];
        assert!((branch.size.as_ref().expect("the cylinder has a size").z - 2.0).abs() < 1e-12);
        let centre = branch
            .pose
            .as_ref()
            .expect("the cylinder has a pose")
            .position
            .as_ref()
            .expect("the pose has a position");
        assert!((centre.y - 1.0).abs() < 1e-12);
        let paint = &full.entities[2].triangles[0];
        assert!((area(&paint.points) - 0.25).abs() < 1e-9);
        // In front of the wall: its normal (x cross z) is -y.
        assert!(
            paint
                .points
                .iter()
                .all(|p| (p.y + PAINT_OFFSET_M).abs() < 1e-12)
        );
        assert!(paint_update(&view, &[], 1, "world", stamp).is_none());
        let more =
            paint_update(&view, &view.paint, 1, "world", stamp).expect("new paint gives an update");
        assert_eq!(more.entities[0].id, "paint-1");
        assert!(more.deletions.is_empty());
    }

    #[test]
    fn the_cells_solids_and_bodies_ride_on_their_frames_and_the_mark_follows_the_pair() {
        use crate::scene::{BodyView, ClosestView, PoseView, SolidView};
        let triangle = vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];
        let solid = |name: &str| SolidView {
            name: name.into(),
            pose: PoseView::IDENTITY,
            triangles: triangle.clone(),
        };
        let view = SceneView {
            solids: vec![solid("table")],
            bodies: vec![
                BodyView {
                    frame: 2,
                    solid: solid("link_2"),
                },
                BodyView {
                    frame: 6,
                    solid: solid("gripper"),
                },
            ],
            ..SceneView::default()
        };
        let frames: Vec<String> = ["base_link", "l1", "l2", "l3", "l4", "l5", "l6"]
            .map(String::from)
            .to_vec();
        let stamp = Timestamp::new(1, 0);
        let full = full_update(&view, "base_link", &frames, stamp);
        let ids: Vec<(&str, &str)> = full
            .entities
            .iter()
            .map(|e| (e.id.as_str(), e.frame_id.as_str()))
            .collect();
        assert_eq!(
            ids,
            [
                ("cell", "base_link"),
                ("bodies-2", "l2"),
                ("bodies-6", "l6")
            ]
        );
        assert_eq!(full.entities[0].triangles[0].points.len(), 3);
        // Without frames (a rig without /tf) the bodies are left out, the cell is not.
        assert_eq!(
            full_update(&view, "base_link", &[], stamp).entities.len(),
            1
        );
        let near = ClosestView {
            a: "link_2".into(),
            b: "table".into(),
            distance_m: 0.004,
            status: "within_margin".into(),
        };
        let mark = closest_update(&view, Some(&near), "base_link", &frames, stamp);
        assert_eq!(mark.deletions.len(), 2);
        let marked: Vec<(&str, &str)> = mark
            .entities
            .iter()
            .map(|e| (e.id.as_str(), e.frame_id.as_str()))
            .collect();
        assert_eq!(marked, [("closest-0", "l2"), ("closest-1", "base_link")]);
        assert_eq!(mark.entities[0].triangles[0].color, Some(NEAR));
        let cleared = closest_update(&view, None, "base_link", &frames, stamp);
        assert!(cleared.entities.is_empty());
        assert_eq!(cleared.deletions.len(), 2);
    }
}
