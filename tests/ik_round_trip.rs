//! The FABRIK planner's round trip: in-limit configuration -> FK pose -> IK from the
//! all-zero seed must come back within 1e-6 m and 1e-6 rad, with raw in-limit values.

use crate::common;

use common::{irb120, random_configuration, rng};
use rand::RngExt;
use rigbridge::ik::{FabrikSolver, IkSolver};
use rigbridge::rig::Rig;

const ZERO_SEED: [f64; 6] = [0.0; 6];

/// Solves every configuration's pose from the zero seed; returns the failures as text.
fn round_trip_failures(solver: &FabrikSolver, configurations: &[Vec<f64>]) -> Vec<String> {
    let rig = solver.rig();
    let mut failures = Vec::new();
    let (mut worst_position, mut worst_rotation) = (0.0f64, 0.0f64);
    for joints in configurations {
        let pose = rig.tool_pose(joints).unwrap();
        match solver.solve(&pose, &ZERO_SEED) {
            Ok(solution) => {
                let reached = rig.tool_pose(&solution.joints).unwrap();
                let (p, r) = (
                    reached.position_error(&pose),
                    reached.orientation_error(&pose),
                );
                let outside = rig.first_limit_violation(&solution.joints);
                worst_position = worst_position.max(p);
                worst_rotation = worst_rotation.max(r);
                if p > 1e-6 || r > 1e-6 || outside.is_some() {
                    failures.push(format!(
                        "{joints:?}: errors {p:e} m {r:e} rad, outside {outside:?}"
                    ));
                }
            }
            Err(e) => failures.push(format!("{:?}: {e}", common::degrees(joints))),
        }
    }
    eprintln!(
        "{} poses: {} failed; worst errors {worst_position:.3e} m, {worst_rotation:.3e} rad",
        configurations.len(),
        failures.len()
    );
    failures
}

fn assert_all_solved(rig: &Rig, configurations: &[Vec<f64>]) {
    let solver = FabrikSolver::new(rig.clone()).unwrap();
    let failures = round_trip_failures(&solver, configurations);
    assert!(
        failures.is_empty(),
        "{} of {} failed, first: {:#?}",
        failures.len(),
        configurations.len(),
        &failures[..failures.len().min(5)]
    );
}

#[test]
fn ten_thousand_random_configurations_round_trip() {
    let rig = irb120();
    let mut rng = rng(20261124);
    let configurations: Vec<_> = (0..10_000)
        .map(|_| random_configuration(&rig, &mut rng))
        .collect();
    assert_all_solved(&rig, &configurations);
}

#[test]
fn wrist_singularity_round_trips() {
    let rig = irb120();
    let mut rng = rng(5);
    let configurations: Vec<_> = (0..2_000)
        .map(|i| {
            let mut q = random_configuration(&rig, &mut rng);
            q[4] = [0.0, 1e-12, -1e-9, 1e-6, -1e-4, 0.01][i % 6] * rng.random_range(0.5..1.5);
            q
        })
        .collect();
    assert_all_solved(&rig, &configurations);
}

#[test]
fn stretched_elbow_round_trips() {
    let rig = irb120();
    let stretched = -(0.302f64.atan2(0.07));
    let mut rng = rng(6);
    let configurations: Vec<_> = (0..2_000)
        .map(|i| {
            let mut q = random_configuration(&rig, &mut rng);
            q[2] = stretched + [0.0, 1e-9, -1e-6, 1e-4, -1e-3, 0.02][i % 6];
            q
        })
        .collect();
    assert_all_solved(&rig, &configurations);
}

#[test]
fn axes_at_their_limits_round_trip() {
    let rig = irb120();
    let mut rng = rng(7);
    let configurations: Vec<_> = (0..3_000)
        .map(|i| {
            let mut q = random_configuration(&rig, &mut rng);
            let axis = i % 6;
            let limits = rig.joints[axis].limits;
            q[axis] = if i % 12 < 6 {
                limits.lower
            } else {
                limits.upper
            };
            if i % 5 == 0 {
                let other = (axis + 3) % 6;
                q[other] = rig.joints[other].limits.upper;
            }
            q
        })
        .collect();
    assert_all_solved(&rig, &configurations);
}

#[test]
fn axis_6_beyond_one_turn_round_trips() {
    let rig = irb120();
    let mut rng = rng(8);
    let configurations: Vec<_> = (0..2_000)
        .map(|_| {
            let mut q = random_configuration(&rig, &mut rng);
            q[5] = rng
                .random_range(1.0f64..1.111)
                .copysign(rng.random_range(-1.0..1.0))
                * std::f64::consts::TAU;
            q
        })
        .collect();
    assert_all_solved(&rig, &configurations);
}
