//! Out-of-reach and invalid targets give typed errors, never a panic; whatever a solver
//! calls a solution is inside the limits and verified.

use crate::common;

use common::irb120;
use glam::{DQuat, DVec3};
use proptest::prelude::*;
use rigbridge::ik::{CcdSolver, FabrikSolver, GradientDescentSolver, IkError, IkSolver};
use rigbridge::rig::{Pose, PoseError};
use std::sync::OnceLock;

fn fabrik() -> &'static FabrikSolver {
    static SOLVER: OnceLock<FabrikSolver> = OnceLock::new();
    SOLVER.get_or_init(|| FabrikSolver::new(irb120()).unwrap())
}

fn assert_sound(
    solver: &dyn IkSolver,
    target: &Pose,
    result: &Result<rigbridge::ik::IkSolution, IkError>,
) {
    if let Ok(solution) = result {
        let rig = solver.rig();
        assert_eq!(rig.first_limit_violation(&solution.joints), None);
        let reached = rig.tool_pose(&solution.joints).unwrap();
        assert!(reached.position_error(target) <= 1e-6);
        assert!(reached.orientation_error(target) <= 1e-6);
    }
}

#[test]
fn far_target_is_out_of_reach_by_the_right_amount() {
    let target = Pose::new(DVec3::new(2.0, 0.0, 0.29), DQuat::IDENTITY);
    match fabrik().solve(&target, &[0.0; 6]) {
        Err(IkError::OutOfReach {
            excess_m, reach_m, ..
        }) => {
            assert!(
                (reach_m - (0.27 + 0.302f64.hypot(0.07))).abs() < 1e-9,
                "{reach_m}"
            );
            assert!(excess_m > 1.3 && excess_m < 1.5, "{excess_m}");
        }
        other => panic!("expected OutOfReach, got {other:?}"),
    }
}

#[test]
fn invalid_targets_and_seeds_are_refused() {
    let nan = Pose::new(DVec3::new(f64::NAN, 0.0, 0.5), DQuat::IDENTITY);
    assert!(matches!(
        fabrik().solve(&nan, &[0.0; 6]),
        Err(IkError::InvalidTarget(PoseError::NotFinite { .. }))
    ));
    let scaled = Pose::new(
        DVec3::new(0.4, 0.0, 0.5),
        DQuat::from_xyzw(0.0, 0.0, 0.0, 1.1),
    );
    assert!(matches!(
        fabrik().solve(&scaled, &[0.0; 6]),
        Err(IkError::InvalidTarget(PoseError::NotUnitQuaternion { .. }))
    ));
    let fine = irb120().tool_pose(&[0.1; 6]).unwrap();
    assert!(matches!(
        fabrik().solve(&fine, &[0.0; 5]),
        Err(IkError::InvalidSeed(_))
    ));
    assert!(matches!(
        fabrik().solve(&fine, &[0.0, f64::INFINITY, 0.0, 0.0, 0.0, 0.0]),
        Err(IkError::InvalidSeed(_))
    ));
}

#[test]
fn a_pose_only_reachable_past_a_limit_names_the_blocking_axis() {
    // Axis 3 narrowed to +-10 deg: a pose made with axis 3 at 40 deg has, on every branch,
    // axis 3 at 40 deg or at the other elbow's -194 deg.
    let full = irb120();
    let target = full
        .tool_pose(&[0.3, 0.2, 40f64.to_radians(), 0.5, 0.6, 0.7])
        .unwrap();
    let mut narrowed = full.clone();
    narrowed.joints[2].limits.lower = -10f64.to_radians();
    narrowed.joints[2].limits.upper = 10f64.to_radians();
    let solver = FabrikSolver::new(narrowed).unwrap();
    match solver.solve(&target, &[0.0; 6]) {
        Err(IkError::NoSolutionWithinLimits { axis, joint }) => {
            assert_eq!((axis, joint.as_str()), (3, "joint_3"));
        }
        other => panic!("expected NoSolutionWithinLimits, got {other:?}"),
    }
}

fn any_float() -> impl Strategy<Value = f64> {
    prop_oneof![
        8 => -2.0f64..2.0,
        1 => Just(f64::NAN),
        1 => Just(f64::INFINITY),
        1 => Just(-1e300),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(2000))]

    #[test]
    fn fabrik_never_panics_and_every_ok_is_sound(
        position in prop::array::uniform3(any_float()),
        quaternion in prop::array::uniform4(any_float()),
        seed in prop::array::uniform6(-8.0f64..8.0),
        normalise in any::<bool>(),
    ) {
        let mut orientation = DQuat::from_array(quaternion);
        if normalise && orientation.is_finite() && orientation.length() > 1e-6 {
            orientation = orientation.normalize();
        }
        let target = Pose::new(DVec3::from_array(position), orientation);
        let result = fabrik().solve(&target, &seed);
        assert_sound(fabrik(), &target, &result);
    }
}

#[test]
fn ccd_and_gradient_descent_answers_are_sound() {
    let rig = irb120();
    let ccd = CcdSolver::new(rig.clone());
    let gd = GradientDescentSolver::new(rig.clone()).with_max_iterations(300);
    let mut rng = common::rng(21);
    for _ in 0..30 {
        let q = common::random_configuration(&rig, &mut rng);
        let target = rig.tool_pose(&q).unwrap();
        let seed: Vec<f64> = q.iter().map(|v| v * 0.9).collect();
        assert_sound(&ccd, &target, &ccd.solve(&target, &seed));
        assert_sound(&gd, &target, &gd.solve(&target, &seed));
    }
}
