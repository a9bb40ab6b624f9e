//! Hand-computed geometry: each expected distance is worked out in its comment from the
//! solids' sizes and places, never taken from the code under test.

use super::*;
use crate::rig::{Joint, JointKind, JointLimits, LinkBody};
use std::path::Path;

const TOL: f64 = 1e-6;

/// A rig of one prismatic joint along `axis` (limits ±2 m) carrying `solids` on frame 1.
fn slider(axis: DVec3, solids: Vec<Collision>) -> Rig {
    Rig {
        name: "slider".into(),
        base_frame: "base".into(),
        tool_frame: "tip".into(),
        joints: vec![Joint {
            name: "slide".into(),
            kind: JointKind::Prismatic,
            origin: DAffine3::IDENTITY,
            axis,
            limits: JointLimits {
                lower: -2.0,
                upper: 2.0,
                max_speed: 1.0,
                max_acceleration: 1.0,
            },
        }],
        tool: DAffine3::IDENTITY,
        bodies: vec![LinkBody {
            name: "mover".into(),
            frame: 1,
            collisions: solids,
        }],
        allowed_pairs: Vec::new(),
    }
}

fn cell_of(objects: Vec<CellObject>) -> Cell {
    Cell {
        objects,
        ..Cell::builtin()
    }
}

fn object(name: &str, pose: DAffine3, shape: Shape) -> CellObject {
    CellObject {
        name: name.into(),
        pose,
        shape,
    }
}

fn at(origin: DAffine3, shape: Shape) -> Collision {
    Collision { origin, shape }
}

fn distance(model: &CollisionModel, q: f64) -> f64 {
    model.clearance(&[q], &mut model.scratch()).distance_m
}

#[test]
fn two_spheres_gap_and_penetration() {
    // A 0.1 m ball sliding along x, a 0.2 m ball fixed at x = 1: gap = 1 - q - 0.3.
    let rig = slider(
        DVec3::X,
        vec![at(DAffine3::IDENTITY, Shape::Sphere { radius: 0.1 })],
    );
    let fixed = object(
        "ball",
        DAffine3::from_translation(DVec3::new(1.0, 0.0, 0.0)),
        Shape::Sphere { radius: 0.2 },
    );
    let cell = cell_of(vec![fixed]);
    let model = CollisionModel::new(&rig, &cell).unwrap();
    let c = model.clearance(&[0.0], &mut model.scratch());
    assert!((c.distance_m - 0.7).abs() < TOL, "{}", c.distance_m);
    assert_eq!(
        (model.body_name(c.a), model.body_name(c.b)),
        ("mover", "ball")
    );
    assert_eq!(model.status(c.distance_m), Status::Free);
    // At q = 0.75 the centres are 0.25 apart: 0.05 m of penetration.
    assert!((distance(&model, 0.75) + 0.05).abs() < TOL);
    assert_eq!(model.status(distance(&model, 0.75)), Status::Collision);
    // At q = 0.695 the gap is 0.005 m: inside the 0.01 m margin.
    assert_eq!(model.status(distance(&model, 0.695)), Status::WithinMargin);
}

#[test]
fn capsule_over_the_floor() {
    // A capsule from (0,0,0) to (0.3,0,0.4), radius 0.05, lifted by q along z over the
    // built-in floor (z = 0): its lowest point is the end at height q, so the gap is
    // q - 0.05.
    let capsule = Shape::Capsule {
        a: DVec3::ZERO,
        b: DVec3::new(0.3, 0.0, 0.4),
        radius: 0.05,
    };
    let rig = slider(DVec3::Z, vec![at(DAffine3::IDENTITY, capsule)]);
    let model = CollisionModel::new(&rig, &Cell::builtin()).unwrap();
    assert!((distance(&model, 0.2) - 0.15).abs() < TOL);
    // At q = 0.02 it reaches 0.03 m below the floor.
    let d = distance(&model, 0.02);
    assert!((d + 0.03).abs() < TOL, "{d}");
    let c = model.clearance(&[0.02], &mut model.scratch());
    assert_eq!(model.body_name(c.b), FLOOR);
}

#[test]
fn box_and_cylinder_along_its_axis_and_across_it() {
    // A 0.2 m cube at the origin (half side 0.1), and no floor.
    let cell = cell_of(vec![object(
        "cube",
        DAffine3::IDENTITY,
        Shape::Box {
            half_extents: DVec3::splat(0.1),
        },
    )]);
    let cylinder = Shape::Cylinder {
        radius: 0.05,
        half_length: 0.2,
    };
    // Axis along z, slid along x: the side faces the cube, gap = q - 0.1 - 0.05.
    let upright = slider(DVec3::X, vec![at(DAffine3::IDENTITY, cylinder.clone())]);
    let model = CollisionModel::new(&upright, &cell).unwrap();
    assert!((distance(&model, 0.5) - 0.35).abs() < TOL);
    // Turned +90 deg about y its axis lies along x: the end cap faces the cube,
    // gap = q - 0.1 - 0.2.
    let turned = DAffine3::from_rotation_y(std::f64::consts::FRAC_PI_2);
    let lying = slider(DVec3::X, vec![at(turned, cylinder)]);
    let model = CollisionModel::new(&lying, &cell).unwrap();
    assert!((distance(&model, 0.5) - 0.2).abs() < TOL);
}

#[test]
fn a_thin_plate_between_two_samples_is_found() {
    // A 0.1 m ball jumps from x = -0.5 to x = +0.5 in one step; a 5 mm plate stands at
    // x = 0. Both samples are 0.3975 m clear of it, the way between is not.
    let rig = slider(
        DVec3::X,
        vec![at(DAffine3::IDENTITY, Shape::Sphere { radius: 0.1 })],
    );
    let plate = object(
        "plate",
        DAffine3::IDENTITY,
        Shape::Box {
            half_extents: DVec3::new(0.0025, 0.5, 0.5),
        },
    );
    let cell = cell_of(vec![plate]);
    let model = CollisionModel::new(&rig, &cell).unwrap();
    let mut scratch = model.scratch();
    let samples: [(f64, &[f64]); 2] = [(0.0, &[-0.5]), (0.004, &[0.5])];
    let hit = model.check_path(samples, &mut scratch).unwrap_err();
    assert_eq!(model.body_name(hit.clearance.b), "plate");
    assert!(hit.t > 0.0 && hit.t < 0.004, "{}", hit.t);
    assert!(hit.clearance.distance_m < model.margin());
    assert!(model.check_step(&[-0.5], &[0.5], &mut scratch).is_err());
    // The same jump beside the plate (2 m away, clear of it) passes.
    let clear: [(f64, &[f64]); 2] = [(0.0, &[-1.9]), (0.004, &[-0.9])];
    let ok = model.check_path(clear, &mut scratch).unwrap();
    assert!(ok.min.distance_m >= model.margin());
}

#[test]
fn a_step_out_of_the_margin_is_admitted_and_a_step_deeper_or_along_is_not() {
    // A 0.1 m ball on a slider along x; a wall's face at x = 0 (a box from -1 to 0). At
    // q the gap is q - 0.1: at q = 0.105 the ball is 5 mm from the wall, inside the
    // default 10 mm margin.
    let rig = slider(
        DVec3::X,
        vec![at(DAffine3::IDENTITY, Shape::Sphere { radius: 0.1 })],
    );
    let wall = object(
        "wall",
        DAffine3::from_translation(DVec3::new(-0.5, 0.0, 0.0)),
        Shape::Box {
            half_extents: DVec3::new(0.5, 0.5, 0.5),
        },
    );
    let model = CollisionModel::new(&rig, &cell_of(vec![wall])).unwrap();
    let mut scratch = model.scratch();
    assert!(model.margin() > 0.005, "the start is inside the margin");
    assert!(model.check_step(&[0.105], &[0.106], &mut scratch).is_err());
    assert!(model.step_leaves_margin(&[0.105], &[0.106], &mut scratch));
    assert!(!model.step_leaves_margin(&[0.105], &[0.104], &mut scratch));
    assert!(!model.step_leaves_margin(&[0.105], &[0.105], &mut scratch));
    // Outside the margin the rule has nothing to say: check_step decides there.
    assert!(!model.step_leaves_margin(&[0.2], &[0.3], &mut scratch));
    // In contact it admits nothing.
    assert!(!model.step_leaves_margin(&[0.09], &[0.2], &mut scratch));
}

fn irb120() -> Rig {
    crate::rig::load_rig(&crate::rig::shipped::path("irb120.toml")).unwrap()
}

fn deg(values: [f64; 6]) -> Vec<f64> {
    values.iter().map(|v| v.to_radians()).collect()
}

#[test]
fn the_irb120_folded_into_its_base_collides_with_it() {
    // Issue 27's first job: [0, 100, 60, 0, 90, 0] deg puts tool0 at x = -0.02, z = 0.14
    // (and the wrist centre at x = 0.006, z = 0.074), inside the base.
    let rig = irb120();
    let model = CollisionModel::new(&rig, &Cell::builtin()).unwrap();
    let mut scratch = model.scratch();
    let c = model.clearance(&deg([0.0, 100.0, 60.0, 0.0, 90.0, 0.0]), &mut scratch);
    assert_eq!(model.status(c.distance_m), Status::Collision);
    let names = [model.body_name(c.a), model.body_name(c.b)];
    assert!(
        names.contains(&"base_link") || names.contains(&"link_1"),
        "{names:?}"
    );
    // At home the arm stands clear of itself and of the floor.
    let home = model.clearance(&[0.0; 6], &mut scratch);
    assert_eq!(model.status(home.distance_m), Status::Free, "{home:?}");
}

#[test]
fn a_cell_file_loads_and_its_errors_name_key_and_value() {
    let text = r#"
margin_m = 0.02
allowed_pairs = [["pen", "wall"]]
[mount]
origin_xyz_m = [0.0, 0.0, 0.5]
[[object]]
name = "wall"
shape = "box"
size_m = [0.02, 1.0, 1.0]
origin_xyz_m = [0.6, 0.0, 0.5]
[tool]
name = "pen"
[tool.tcp]
origin_xyz_m = [0.0, 0.0, 0.1]
[[tool.body]]
shape = "cylinder"
radius_m = 0.01
length_m = 0.08
origin_xyz_m = [0.0, 0.0, 0.04]
"#;
    let cell = cell_from_toml(text, Path::new("cell.toml")).unwrap();
    assert_eq!(cell.margin_m, 0.02);
    assert_eq!(cell.mount.translation, DVec3::new(0.0, 0.0, 0.5));
    assert_eq!(
        cell.objects[0].shape,
        Shape::Box {
            half_extents: DVec3::new(0.01, 0.5, 0.5)
        }
    );
    let tool = cell.tool.as_ref().unwrap();
    assert_eq!(tool.tcp.translation, DVec3::new(0.0, 0.0, 0.1));
    let rig = irb120();
    let at_tcp = cell.rig_at_tcp(&rig);
    assert_eq!(at_tcp.tool_frame, "pen");
    let home_tool0 = rig.forward(&[0.0; 6]).unwrap().translation;
    let home_tcp = at_tcp.forward(&[0.0; 6]).unwrap().translation;
    // tool0's z points along the base x at home: the TCP is 0.1 m further out.
    assert!((home_tcp - home_tool0 - DVec3::new(0.1, 0.0, 0.0)).length() < TOL);
    CollisionModel::new(&rig, &cell).unwrap();

    let bad = text.replace("radius_m = 0.01", "radius_m = -0.01");
    let err = cell_from_toml(&bad, Path::new("cell.toml"))
        .unwrap_err()
        .to_string();
    assert_eq!(
        err,
        "cell.toml: key `tool.body[0].radius_m` = -0.01: must be a positive number"
    );
    let typo = text.replace("[[\"pen\", \"wall\"]]", "[[\"pen\", \"wal\"]]");
    let cell = cell_from_toml(&typo, Path::new("cell.toml")).unwrap();
    let err = CollisionModel::new(&rig, &cell).unwrap_err().to_string();
    assert!(err.contains("`wal` names no body"), "{err}");
}
