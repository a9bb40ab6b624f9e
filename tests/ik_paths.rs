//! Nearest-branch and continuity behaviour of the FABRIK planner along smooth paths.

use crate::common;

use common::{irb120, random_configuration, rng};
use glam::{DQuat, DVec3};
use rand::RngExt;
use rigbridge::ik::{FabrikSolver, IkSolver};
use rigbridge::rig::{Pose, Rig};

const STEP_M: f64 = 0.001;
const STEP_RAD: f64 = 0.5 * std::f64::consts::PI / 180.0;
const MAX_JUMP_RAD: f64 = 2.0 * std::f64::consts::PI / 180.0;
const NEAR_RAD: f64 = 5.0 * std::f64::consts::PI / 180.0;

#[test]
fn seeded_with_the_answer_returns_the_answer() {
    let rig = irb120();
    let solver = FabrikSolver::new(rig.clone()).unwrap();
    let mut rng = rng(11);
    for _ in 0..5_000 {
        let q = random_configuration(&rig, &mut rng);
        let solution = solver.solve(&rig.tool_pose(&q).unwrap(), &q).unwrap();
        let worst = q
            .iter()
            .zip(&solution.joints)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        assert!(
            worst < 1e-6,
            "seed {q:?} came back as {:?}",
            solution.joints
        );
    }
}

/// Steps where some joint moved more than 2 deg. A step that stays on its branch is the
/// arm's own Jacobian at work (joint speed per Cartesian step grows near a singularity);
/// a step that changes branch is a jump, allowed only near a singularity or a limit.
#[derive(Debug, Default)]
struct LargeSteps {
    steps: usize,
    same_branch: usize,
    switch_wrist_singular: usize,
    switch_elbow_stretched: usize,
    switch_over_axis_1: usize,
    switch_at_limit: usize,
    unexplained_switches: Vec<String>,
}

fn stretched_elbow() -> f64 {
    -(0.302f64.atan2(0.07))
}

fn wrist_centre(rig: &Rig, q: &[f64]) -> DVec3 {
    let tool = rig.forward(q).unwrap();
    tool.translation - tool.matrix3 * DVec3::new(0.0, 0.0, 0.072)
}

/// Front or back, elbow side, wrist flip.
fn branch(rig: &Rig, q: &[f64]) -> (bool, bool, bool) {
    let centre = wrist_centre(rig, q);
    let reach = centre.x * q[0].cos() + centre.y * q[0].sin();
    (reach >= 0.0, q[2] >= stretched_elbow(), q[4] >= 0.0)
}

fn classify(rig: &Rig, before: &[f64], after: &[f64], counts: &mut LargeSteps) {
    let same_turn = (before[5] - after[5]).abs() < std::f64::consts::PI
        && (before[3] - after[3]).abs() < std::f64::consts::PI;
    if branch(rig, before) == branch(rig, after) && same_turn {
        counts.same_branch += 1;
        return;
    }
    let near_limit = |q: &[f64]| {
        q.iter()
            .zip(&rig.joints)
            .any(|(v, j)| v - j.limits.lower < NEAR_RAD || j.limits.upper - v < NEAR_RAD)
    };
    let either = |test: &dyn Fn(&[f64]) -> bool| test(before) || test(after);
    if either(&|q| q[4].abs() < NEAR_RAD) {
        counts.switch_wrist_singular += 1;
    } else if either(&|q| (q[2] - stretched_elbow()).abs() < NEAR_RAD) {
        counts.switch_elbow_stretched += 1;
    } else if either(&|q| wrist_centre(rig, q).truncate().length() < 0.05) {
        counts.switch_over_axis_1 += 1;
    } else if near_limit(before) {
        counts.switch_at_limit += 1;
    } else {
        counts.unexplained_switches.push(format!(
            "{:?} -> {:?}",
            common::degrees(before),
            common::degrees(after)
        ));
    }
}

#[test]
fn smooth_paths_give_smooth_joint_motion() {
    let rig = irb120();
    let solver = FabrikSolver::new(rig.clone()).unwrap();
    let mut rng = rng(12);
    let mut counts = LargeSteps::default();
    let mut ended_unreachable = 0;
    for _ in 0..1_000 {
        let mut joints = random_configuration(&rig, &mut rng);
        let mut pose = rig.tool_pose(&joints).unwrap();
        let direction = DVec3::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        )
        .normalize_or(DVec3::X);
        let axis = DVec3::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        )
        .normalize_or(DVec3::Z);
        for _ in 0..100 {
            pose = Pose::new(
                pose.position + direction * STEP_M,
                (DQuat::from_axis_angle(axis, STEP_RAD) * pose.orientation).normalize(),
            );
            let Ok(solution) = solver.solve(&pose, &joints) else {
                ended_unreachable += 1;
                break;
            };
            counts.steps += 1;
            let jump = joints
                .iter()
                .zip(&solution.joints)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f64::max);
            if jump > MAX_JUMP_RAD {
                classify(&rig, &joints, &solution.joints, &mut counts);
            }
            joints = solution.joints;
        }
    }
    eprintln!(
        "continuity over 1,000 paths: {counts:?}, paths ended by an unreachable pose: {ended_unreachable}"
    );
    assert!(
        counts.steps > 50_000,
        "too few steps solved: {}",
        counts.steps
    );
    assert!(
        counts.unexplained_switches.is_empty(),
        "{} branch switches away from singularities and limits, first: {:?}",
        counts.unexplained_switches.len(),
        &counts.unexplained_switches[..counts.unexplained_switches.len().min(3)]
    );
}
