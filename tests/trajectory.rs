//! The trajectory planners against the shipped IRB 120: joint moves (limits, exact
//! waypoints, synchronised jerk-limited profiles), linear Cartesian moves (the tool stays
//! on the line), and the errors for input a plan must refuse rather than bend.

use glam::{DQuat, DVec3};
use proptest::prelude::*;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rigbridge::ik::{CartesianError, FabrikSolver, IkError, IkSolution, IkSolver, plan_cartesian};
use rigbridge::rig::{Pose, Rig, load_rig};
use rigbridge::trajectory::{
    InvalidValue, PlanError, PlanSettings, Trajectory, plan_joint_moves, validate,
};
use std::f64::consts::{FRAC_PI_2, TAU};
use std::path::Path;
use std::time::Instant;

/// Rounding slack on the speed checks of planned (not sampled) quantities.
const ROUNDING: f64 = 1e-9;
/// The second difference of positions averages acceleration over two periods; this covers
/// the rounding of that average.
const FD_ACCEL_SLACK: f64 = 1e-6;

fn irb120() -> Rig {
    load_rig(Path::new(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/config/irb120.toml"
    )))
    .expect("shipped IRB 120 config loads")
}

fn random_in_limits(rig: &Rig, rng: &mut ChaCha8Rng) -> Vec<f64> {
    rig.joints
        .iter()
        .map(|j| rng.random_range(j.limits.lower..=j.limits.upper))
        .collect()
}

/// Largest |velocity| and |second difference / period^2| per axis, over the whole trajectory.
fn peak_velocity_and_acceleration(trajectory: &Trajectory) -> (Vec<f64>, Vec<f64>) {
    let dof = trajectory.dof();
    let dt = trajectory.period.as_secs_f64();
    let mut velocity = vec![0.0f64; dof];
    let mut acceleration = vec![0.0f64; dof];
    for k in 0..trajectory.len() {
        for axis in 0..dof {
            velocity[axis] = velocity[axis].max(trajectory.velocity(k)[axis].abs());
            if k > 0 && k + 1 < trajectory.len() {
                let (a, b, c) = (
                    trajectory.position(k - 1)[axis],
                    trajectory.position(k)[axis],
                    trajectory.position(k + 1)[axis],
                );
                acceleration[axis] = acceleration[axis].max((c - 2.0 * b + a).abs() / (dt * dt));
            }
        }
    }
    (velocity, acceleration)
}

fn assert_within_scaled_limits(rig: &Rig, trajectory: &Trajectory, settings: &PlanSettings) {
    let (velocity, acceleration) = peak_velocity_and_acceleration(trajectory);
    for (axis, joint) in rig.joints.iter().enumerate() {
        let max_speed = joint.limits.max_speed * settings.speed_scale;
        let max_accel = joint.limits.max_acceleration * settings.accel_scale;
        assert!(
            velocity[axis] <= max_speed * (1.0 + ROUNDING),
            "{}: velocity {} above {max_speed}",
            joint.name,
            velocity[axis]
        );
        assert!(
            acceleration[axis] <= max_accel * (1.0 + FD_ACCEL_SLACK),
            "{}: acceleration {} above {max_accel}",
            joint.name,
            acceleration[axis]
        );
    }
}

#[test]
fn joint_moves_pass_exactly_through_random_waypoints_within_the_scaled_limits() {
    let rig = irb120();
    let settings = PlanSettings::default();
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    for trial in 0..40 {
        let start = random_in_limits(&rig, &mut rng);
        let count = rng.random_range(1..=4);
        let waypoints: Vec<Vec<f64>> = (0..count)
            .map(|_| random_in_limits(&rig, &mut rng))
            .collect();
        let began = Instant::now();
        let trajectory = plan_joint_moves(&rig, &start, &waypoints, &settings).unwrap();
        let planning = began.elapsed();
        validate(&trajectory, &rig).unwrap();
        assert_eq!(trajectory.period, settings.period);
        assert_eq!(trajectory.position(0), start.as_slice());
        assert_eq!(
            trajectory.position(trajectory.len() - 1),
            waypoints[count - 1].as_slice()
        );
        // Every waypoint is a sample, exactly, in order, and the arm is at rest there.
        let mut from = 0;
        for waypoint in &waypoints {
            let at = (from..trajectory.len())
                .find(|&k| trajectory.position(k) == waypoint.as_slice())
                .unwrap_or_else(|| panic!("trial {trial}: waypoint {waypoint:?} is no sample"));
            assert!(trajectory.velocity(at).iter().all(|v| *v == 0.0));
            from = at;
        }
        assert_within_scaled_limits(&rig, &trajectory, &settings);
        if trial < 3 {
            println!(
                "joint moves, trial {trial}: {count} waypoints, {:.3} s, {} samples, planned in {planning:?}",
                trajectory.duration_s(),
                trajectory.len()
            );
        }
    }
}

#[test]
fn a_joint_move_synchronises_its_axes() {
    let rig = irb120();
    let settings = PlanSettings::default();
    let start = vec![0.0; 6];
    // Axis 1 moves far, axis 2 a little: both must still arrive on the same sample.
    let goal = vec![2.0, 0.1, 0.0, 0.0, 0.0, 0.0];
    let trajectory =
        plan_joint_moves(&rig, &start, std::slice::from_ref(&goal), &settings).unwrap();
    let arrived = |axis: usize| {
        (0..trajectory.len())
            .find(|&k| (trajectory.position(k)[axis] - goal[axis]).abs() < 1e-12)
            .unwrap()
    };
    assert!(
        arrived(1) + 1 >= trajectory.len() - 1,
        "axis 2 arrived early"
    );
    assert_eq!(arrived(0), trajectory.len() - 1);
    // 2 rad at 0.9 x 250 deg/s takes at least 0.51 s; the jerk limit adds to it.
    println!("2 rad on axis 1: {:.3} s", trajectory.duration_s());
    assert!(trajectory.duration_s() > 2.0 / (250f64.to_radians() * 0.9));
}

#[test]
fn a_waypoint_equal_to_the_start_adds_nothing() {
    let rig = irb120();
    let start = vec![0.1; 6];
    let trajectory = plan_joint_moves(
        &rig,
        &start,
        std::slice::from_ref(&start),
        &PlanSettings::default(),
    )
    .unwrap();
    assert_eq!(trajectory.len(), 1);
}

/// Corners of a vertical 10 cm square on the plane x = 0.45 m in front of the robot, tool z
/// pointing +x (into the wall).
fn wall_square() -> Vec<Pose> {
    let orientation = DQuat::from_rotation_y(FRAC_PI_2);
    [(-0.05, 0.45), (0.05, 0.45), (0.05, 0.55), (-0.05, 0.55)]
        .iter()
        .map(|&(y, z)| Pose::new(DVec3::new(0.45, y, z), orientation))
        .collect()
}

fn distance_to_segment(point: DVec3, a: DVec3, b: DVec3) -> f64 {
    let along = (point - a).dot(b - a) / (b - a).length_squared();
    point.distance(a + (b - a) * along.clamp(0.0, 1.0))
}

#[test]
fn a_square_on_a_wall_stays_on_its_edges() {
    let rig = irb120();
    let solver = FabrikSolver::new(rig.clone()).unwrap();
    let corners = wall_square();
    let start = solver.solve(&corners[0], &[0.0; 6]).unwrap().joints;
    let settings = PlanSettings::default();
    let route = [corners[1], corners[2], corners[3], corners[0]];
    let began = Instant::now();
    let trajectory = plan_cartesian(&solver, &start, &route, &settings).unwrap();
    let planning = began.elapsed();
    validate(&trajectory, &rig).unwrap();
    assert_eq!(trajectory.position(0), start.as_slice());

    let mut worst_position = 0.0f64;
    let mut worst_orientation = 0.0f64;
    for k in 0..trajectory.len() {
        let pose = rig.tool_pose(&trajectory.position(k)).unwrap();
        let off_edges = (0..4)
            .map(|i| {
                distance_to_segment(
                    pose.position,
                    corners[i].position,
                    corners[(i + 1) % 4].position,
                )
            })
            .fold(f64::INFINITY, f64::min);
        worst_position = worst_position.max(off_edges);
        worst_orientation = worst_orientation.max(pose.orientation_error(&corners[0]));
    }
    let end = rig
        .tool_pose(&trajectory.position(trajectory.len() - 1))
        .unwrap();
    assert!(end.position_error(&corners[0]) < 1e-6);
    let (velocity, acceleration) = peak_velocity_and_acceleration(&trajectory);
    let ratio = |values: &[f64], limit: fn(&rigbridge::rig::JointLimits) -> f64| {
        values
            .iter()
            .zip(&rig.joints)
            .map(|(v, j)| v / limit(&j.limits))
            .fold(0.0, f64::max)
    };
    println!(
        "square: {:.3} s, {} samples, planned in {planning:?}; off the edges {worst_position:.2e} m, \
         {worst_orientation:.2e} rad; peak speed {:.3} and finite-difference acceleration {:.3} of the rig's limits",
        trajectory.duration_s(),
        trajectory.len(),
        ratio(&velocity, |l| l.max_speed),
        ratio(&acceleration, |l| l.max_acceleration),
    );
    assert!(worst_position <= 1e-6, "{worst_position}");
    assert!(worst_orientation <= 1e-6, "{worst_orientation}");
    assert_within_scaled_limits(&rig, &trajectory, &settings);
}

#[test]
fn an_unreachable_waypoint_fails_the_whole_plan_naming_it() {
    let rig = irb120();
    let solver = FabrikSolver::new(rig.clone()).unwrap();
    let corners = wall_square();
    let start = solver.solve(&corners[0], &[0.0; 6]).unwrap().joints;
    let far = Pose::new(DVec3::new(2.0, 0.0, 0.5), corners[0].orientation);
    let result = plan_cartesian(
        &solver,
        &start,
        &[corners[1], far, corners[2]],
        &PlanSettings::default(),
    );
    let Err(CartesianError::Unreachable {
        waypoint,
        sample_pose,
        u,
        error,
    }) = result
    else {
        panic!("expected Unreachable, got {result:?}");
    };
    assert_eq!(waypoint, 1);
    assert!(matches!(error, IkError::OutOfReach { .. }), "{error:?}");
    // The first bad sample lies on the line from corner 1 toward the far pose, near the
    // edge of the workspace, not at the far pose itself.
    let off_line = distance_to_segment(sample_pose.position, corners[1].position, far.position);
    assert!(off_line < 1e-9, "{sample_pose:?}");
    assert!(sample_pose.position.x < 1.0, "{sample_pose:?}");
    // `u` says how far along the line it lies.
    let along = corners[1].position.lerp(far.position, u);
    assert!(
        (sample_pose.position - along).length() < 1e-9,
        "{u} {sample_pose:?}"
    );
}

#[test]
fn waypoints_outside_the_limits_or_not_finite_are_refused_not_clamped() {
    let rig = irb120();
    let settings = PlanSettings::default();
    let start = vec![0.0; 6];
    let fine = vec![0.2; 6];
    let mut beyond = vec![0.1; 6];
    beyond[2] = 80f64.to_radians(); // joint_3 stops at +70 deg
    match plan_joint_moves(&rig, &start, &[fine.clone(), beyond.clone()], &settings) {
        Err(PlanError::InvalidWaypoint {
            waypoint: 1,
            joint,
            value,
            reason: InvalidValue::OutsideLimits { upper, .. },
        }) => {
            assert_eq!(joint, "joint_3");
            assert_eq!(value, beyond[2]);
            assert!((upper - 70f64.to_radians()).abs() < 1e-12);
        }
        other => panic!("expected InvalidWaypoint, got {other:?}"),
    }
    let mut nan = fine.clone();
    nan[4] = f64::NAN;
    assert!(matches!(
        plan_joint_moves(&rig, &start, &[nan], &settings),
        Err(PlanError::InvalidWaypoint { waypoint: 0, ref joint, reason: InvalidValue::NotFinite, .. }) if joint == "joint_5"
    ));
    assert!(matches!(
        plan_joint_moves(&rig, &start, &[fine.clone(), vec![0.0; 5]], &settings),
        Err(PlanError::WaypointAxisCount {
            waypoint: 1,
            expected: 6,
            got: 5,
            ..
        })
    ));
    assert!(matches!(
        plan_joint_moves(&rig, &beyond, &[fine], &settings),
        Err(PlanError::InvalidStart { ref joint, .. }) if joint == "joint_3"
    ));
}

#[test]
fn bad_settings_and_poses_are_refused() {
    let rig = irb120();
    let solver = FabrikSolver::new(rig.clone()).unwrap();
    let settings = PlanSettings {
        speed_scale: 1.5,
        ..PlanSettings::default()
    };
    assert!(matches!(
        plan_joint_moves(&rig, &[0.0; 6], &[vec![0.1; 6]], &settings),
        Err(PlanError::InvalidSettings {
            setting: "speed_scale",
            ..
        })
    ));
    let corners = wall_square();
    let start = solver.solve(&corners[0], &[0.0; 6]).unwrap().joints;
    let bent = Pose::new(corners[1].position, DQuat::from_xyzw(0.0, 0.0, 0.0, 2.0));
    assert!(matches!(
        plan_cartesian(
            &solver,
            &start,
            &[corners[1], bent],
            &PlanSettings::default()
        ),
        Err(CartesianError::InvalidPose { waypoint: 1, .. })
    ));
}

/// FABRIK, except that it answers on the other turn of axis 6 once the target is past
/// y = 0: the same tool pose, reached by a joint jump of a full turn.
struct TurningSolver(FabrikSolver);

impl IkSolver for TurningSolver {
    fn name(&self) -> &'static str {
        "turning"
    }

    fn rig(&self) -> &Rig {
        self.0.rig()
    }

    fn solve(&self, target: &Pose, seed: &[f64]) -> Result<IkSolution, IkError> {
        let mut solution = self.0.solve(target, seed)?;
        if target.position.y > 0.0 {
            let q6 = solution.joints[5];
            solution.joints[5] = if q6 + TAU <= 400f64.to_radians() {
                q6 + TAU
            } else {
                q6 - TAU
            };
        }
        Ok(solution)
    }
}

#[test]
fn a_branch_switch_between_samples_is_a_discontinuity() {
    let rig = irb120();
    let solver = TurningSolver(FabrikSolver::new(rig.clone()).unwrap());
    let corners = wall_square();
    let start = solver.solve(&corners[0], &[0.0; 6]).unwrap().joints;
    let result = plan_cartesian(&solver, &start, &corners[1..2], &PlanSettings::default());
    match result {
        Err(CartesianError::Discontinuity {
            waypoint: 0,
            joint,
            jump,
            ..
        }) => {
            assert_eq!(joint, "joint_6");
            assert!((jump.abs() - TAU).abs() < 0.1, "{jump}");
        }
        other => panic!("expected Discontinuity, got {other:?}"),
    }
}

/// A joint value that is usually in the limits, sometimes outside them or NaN.
fn joint_value(lower: f64, upper: f64) -> BoxedStrategy<f64> {
    prop_oneof![
        12 => lower..=upper,
        1 => (upper + 1e-6)..(upper + 1.0),
        1 => (lower - 1.0)..(lower - 1e-6),
        1 => Just(f64::NAN),
    ]
    .boxed()
}

fn waypoint(rig: &Rig) -> Vec<BoxedStrategy<f64>> {
    rig.joints
        .iter()
        .map(|j| joint_value(j.limits.lower, j.limits.upper))
        .collect::<Vec<_>>()
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    #[test]
    fn joint_plans_are_refused_or_stay_within_limits(
        waypoints in prop::collection::vec(waypoint(&irb120()), 1..4),
        start_fraction in 0.0f64..=1.0,
    ) {
        let rig = irb120();
        let start: Vec<f64> = rig
            .joints
            .iter()
            .map(|j| j.limits.lower + start_fraction * (j.limits.upper - j.limits.lower))
            .collect();
        let any_bad = waypoints.iter().flatten().zip(rig.joints.iter().cycle()).any(|(q, j)| !j.limits.contains(*q));
        let settings = PlanSettings::default();
        match plan_joint_moves(&rig, &start, &waypoints, &settings) {
            Err(e) => prop_assert!(any_bad, "good waypoints refused: {e}"),
            Ok(trajectory) => {
                prop_assert!(!any_bad, "bad waypoints planned");
                // Checked here from first principles, not with `validate`.
                for k in 0..trajectory.len() {
                    for (axis, joint) in rig.joints.iter().enumerate() {
                        let q = trajectory.position(k)[axis];
                        prop_assert!(q.is_finite() && q >= joint.limits.lower && q <= joint.limits.upper,
                            "sample {k}: {} = {q}", joint.name);
                        if k > 0 {
                            let step = (q - trajectory.position(k - 1)[axis]).abs();
                            let max_step = joint.limits.max_speed * trajectory.period.as_secs_f64();
                            prop_assert!(step <= max_step, "sample {k}: {} steps {step} > {max_step}", joint.name);
                        }
                    }
                }
                prop_assert_eq!(trajectory.position(trajectory.len() - 1), waypoints[waypoints.len() - 1].as_slice());
            }
        }
    }
}

/// Random short lines (up to 15 cm and 0.3 rad) from random configurations: many cross a
/// singularity, a limit or the edge of the workspace and must be refused; the rest must
/// keep the tool on the line and every axis within the scaled limits.
#[test]
fn random_lines_stay_on_the_line_within_the_scaled_limits() {
    let rig = irb120();
    let solver = FabrikSolver::new(rig.clone()).unwrap();
    let settings = PlanSettings::default();
    let mut rng = ChaCha8Rng::seed_from_u64(21);
    let mut planned = 0;
    let mut refused = std::collections::BTreeMap::new();
    let (mut off_line, mut off_orientation) = (0.0f64, 0.0f64);
    for _ in 0..200 {
        let start = random_in_limits(&rig, &mut rng);
        let from = rig.tool_pose(&start).unwrap();
        let mut offset = || rng.random_range(-0.15..0.15);
        let offset = DVec3::new(offset(), offset(), offset());
        let mut turn = || rng.random_range(-0.3..0.3);
        let turn = DQuat::from_scaled_axis(DVec3::new(turn(), turn(), turn()));
        let to = Pose::new(
            from.position + offset,
            (turn * from.orientation).normalize(),
        );
        match plan_cartesian(&solver, &start, &[to], &settings) {
            Err(
                e @ (CartesianError::Unreachable { .. } | CartesianError::Discontinuity { .. }),
            ) => {
                let kind = format!("{e:?}").split(' ').next().unwrap().to_string();
                *refused.entry(kind).or_insert(0) += 1;
            }
            Err(e) => panic!("unexpected refusal: {e}"),
            Ok(trajectory) => {
                planned += 1;
                validate(&trajectory, &rig).unwrap();
                assert_within_scaled_limits(&rig, &trajectory, &settings);
                for k in 0..trajectory.len() {
                    let pose = rig.tool_pose(&trajectory.position(k)).unwrap();
                    let line = to.position - from.position;
                    let u = (pose.position - from.position).dot(line) / line.length_squared();
                    off_line = off_line.max(distance_to_segment(
                        pose.position,
                        from.position,
                        to.position,
                    ));
                    let expected = from.orientation.slerp(to.orientation, u.clamp(0.0, 1.0));
                    off_orientation = off_orientation
                        .max(pose.orientation_error(&Pose::new(pose.position, expected)));
                }
            }
        }
    }
    println!(
        "random lines: {planned} planned, refused {refused:?}; worst {off_line:.2e} m off the line, {off_orientation:.2e} rad off the slerp"
    );
    assert!(off_line <= 1e-6 && off_orientation <= 1e-6);
    assert!(planned >= 50, "only {planned} of 200 planned");
}
