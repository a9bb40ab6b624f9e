//! No tunnelling (issue 27): a trajectory whose samples straddle a 5 mm plate at full speed
//! is refused, though every sample on its own is clear of it by more than the margin. Through
//! the collision model's public API: the whole-path check (`check_path`) and the streaming
//! gate's step check (`check_step`).

use crate::common;

use glam::{DAffine3, DQuat, DVec3};
use rigbridge::cell::{Cell, CellObject, CollisionModel, DEFAULT_MARGIN_M, Tool};
use rigbridge::rig::{Collision, Shape};

/// The plate's thickness: the figure.
const PLATE_M: f64 = 0.005;
/// Time between samples: joint 1 at full speed moves 5 degrees in it (250 deg/s).
const SAMPLE_DT_S: f64 = 0.02;
/// The stylus: a 4 mm radius rod from 0.02 m to 0.2 m out along tool0's z axis (at the
/// IRB 120's zero configuration that is radially out along the base's x, at z = 0.63 m).
const STYLUS_RADIUS_M: f64 = 0.004;
const STYLUS_FROM_M: f64 = 0.02;
const STYLUS_TO_M: f64 = 0.2;
/// The plate: vertical, radial, from 0.47 m to 0.62 m from joint 1's axis, 0.1 m tall
/// around the stylus' height; beyond the wrist's bodies, within the stylus' reach.
const PLATE_RADIAL_M: (f64, f64) = (0.47, 0.62);
const PLATE_HEIGHT_M: f64 = 0.1;
const STYLUS_Z_M: f64 = 0.63;
/// Samples of joint 1: from -20 deg every 5 deg to +20 deg; the plate stands half-way
/// between the samples at 0 and 5 deg, at 2.5 deg.
const FIRST_DEG: f64 = -20.0;
const SAMPLES: usize = 9;
const PLATE_DEG: f64 = 2.5;

fn plate_at(angle_deg: f64) -> CellObject {
    let (inner, outer) = PLATE_RADIAL_M;
    let rotation = DQuat::from_rotation_z(angle_deg.to_radians());
    let centre = rotation * DVec3::new((inner + outer) / 2.0, 0.0, STYLUS_Z_M);
    CellObject {
        name: "plate".into(),
        pose: DAffine3::from_rotation_translation(rotation, centre),
        shape: Shape::Box {
            half_extents: DVec3::new((outer - inner) / 2.0, PLATE_M / 2.0, PLATE_HEIGHT_M / 2.0),
        },
    }
}

fn cell_with_plate_at(angle_deg: f64) -> Cell {
    let half = (STYLUS_TO_M - STYLUS_FROM_M) / 2.0;
    let mut cell = Cell::builtin();
    cell.objects.push(plate_at(angle_deg));
    cell.tool = Some(Tool {
        name: "stylus".into(),
        bodies: vec![Collision {
            origin: DAffine3::from_translation(DVec3::Z * (STYLUS_FROM_M + half)),
            shape: Shape::Cylinder {
                radius: STYLUS_RADIUS_M,
                half_length: half,
            },
        }],
        tcp: DAffine3::from_translation(DVec3::Z * STYLUS_TO_M),
    });
    cell
}

/// Joint 1 sweeping at full speed, the other joints at zero: (t, positions) per sample.
fn sweep(rig: &rigbridge::rig::Rig) -> Vec<(f64, Vec<f64>)> {
    let step = rig.joints[0].limits.max_speed * SAMPLE_DT_S;
    assert!(
        (step.to_degrees() - 5.0).abs() < 1e-9,
        "joint 1's full speed is 250 deg/s"
    );
    (0..SAMPLES)
        .map(|k| {
            let mut q = vec![0.0; rig.dof()];
            q[0] = FIRST_DEG.to_radians() + step * k as f64;
            (SAMPLE_DT_S * k as f64, q)
        })
        .collect()
}

#[test]
fn a_full_speed_sweep_whose_samples_straddle_a_5_mm_plate_is_refused() {
    let rig = common::irb120();
    let cell = cell_with_plate_at(PLATE_DEG);
    assert_eq!(cell.margin_m, DEFAULT_MARGIN_M);
    let model = CollisionModel::new(&rig, &cell).expect("the model builds");
    let mut scratch = model.scratch();
    let samples = sweep(&rig);
    // Every sample on its own is clear by more than the margin: only a check between
    // samples can see the plate.
    for (t, q) in &samples {
        let c = model.clearance(q, &mut scratch);
        assert!(
            c.distance_m >= model.margin(),
            "sample at {t} s is already within the margin: {} m ({} - {})",
            c.distance_m,
            model.body_name(c.a),
            model.body_name(c.b)
        );
    }
    let refused = model
        .check_path(
            samples.iter().map(|(t, q)| (*t, q.as_slice())),
            &mut scratch,
        )
        .expect_err("the path passes through the plate");
    let mut pair = [
        model.body_name(refused.clearance.a),
        model.body_name(refused.clearance.b),
    ];
    pair.sort_unstable();
    assert_eq!(pair, ["plate", "stylus"]);
    // Between the samples at 0 deg (index 4, 0.08 s) and 5 deg (index 5, 0.10 s).
    assert!(
        (0.08 - 1e-9..=0.10 + 1e-9).contains(&refused.t),
        "refused at {} s",
        refused.t
    );
    assert!(refused.clearance.distance_m < model.margin());
    // The streaming gate's check of that one step refuses it too.
    let step = model.check_step(&samples[4].1, &samples[5].1, &mut scratch);
    let blocked = step.expect_err("the step passes through the plate");
    assert!(blocked.distance_m < model.margin());
}

#[test]
fn the_same_sweep_with_the_plate_out_of_its_way_passes() {
    let rig = common::irb120();
    // At 60 deg the plate is 40 deg beyond the sweep's end.
    let model = CollisionModel::new(&rig, &cell_with_plate_at(60.0)).expect("the model builds");
    let mut scratch = model.scratch();
    let samples = sweep(&rig);
    let clear = model
        .check_path(
            samples.iter().map(|(t, q)| (*t, q.as_slice())),
            &mut scratch,
        )
        .unwrap_or_else(|c| {
            panic!(
                "refused at {} s: {} - {}",
                c.t,
                model.body_name(c.clearance.a),
                model.body_name(c.clearance.b)
            )
        });
    assert!(clear.min.distance_m >= model.margin());
    assert!(
        model
            .check_step(&samples[4].1, &samples[5].1, &mut scratch)
            .is_ok()
    );
}
