//! The validator's promise, checked independently: a trajectory it accepts has no sample
//! outside the limits, no step above max speed x period and no acceleration above max
//! acceleration (positions' second differences and velocity changes); hand-built
//! trajectories just over and exactly at an acceleration limit.

use crate::common;

use common::irb120;
use glam::{DAffine3, DVec3};
use proptest::prelude::*;
use rigbridge::rig::{Joint, JointKind, JointLimits, Rig};
use rigbridge::trajectory::{Trajectory, TrajectoryError, validate, validate_motion};
use std::time::Duration;

fn independently_safe(trajectory: &Trajectory) -> bool {
    let rig = irb120();
    (0..trajectory.len()).all(|i| {
        let q = trajectory.position(i);
        rig.joints.iter().enumerate().all(|(axis, joint)| {
            let inside = q[axis] >= joint.limits.lower && q[axis] <= joint.limits.upper;
            let dt = trajectory.period.as_secs_f64();
            let slow = i == 0
                || (q[axis] - trajectory.position(i - 1)[axis]).abs()
                    <= joint.limits.max_speed * dt * (1.0 + 1e-9);
            let smooth = i == 0
                || i + 1 == trajectory.len()
                || (trajectory.position(i + 1)[axis] - 2.0 * q[axis]
                    + trajectory.position(i - 1)[axis])
                    .abs()
                    <= joint.limits.max_acceleration * dt * dt * (1.0 + 1e-9);
            inside && slow && smooth
        })
    })
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(1000))]

    #[test]
    fn accepted_trajectories_are_safe(
        start in prop::array::uniform6(-2.0f64..2.0),
        first_step in prop::array::uniform6(-0.03f64..0.03),
        // Changes of step: up to 1e-4 rad per sample is 100 rad/s^2 at 1 ms, 6.25 at 4 ms,
        // 1 at 10 ms, against the IRB 120's 17.5-29.3 rad/s^2: some accepted, some not.
        bends in prop::collection::vec(prop::array::uniform6(-1e-4f64..1e-4), 1..60),
        period in prop::sample::select(vec![0.001, 0.004, 0.01]),
        poison in prop::option::of((0usize..60, 0usize..6, prop::sample::select(vec![f64::NAN, f64::INFINITY, 7.5]))),
    ) {
        let rig = irb120();
        let mut positions = start.to_vec();
        let (mut q, mut step) = (start, first_step);
        for bend in &bends {
            for ((v, s), b) in q.iter_mut().zip(step.iter_mut()).zip(bend) {
                *s += b;
                *v += *s;
            }
            positions.extend_from_slice(&q);
        }
        if let Some((sample, axis, value)) = poison {
            let index = (sample % (bends.len() + 1)) * 6 + axis;
            positions[index] = value;
        }
        let velocities = vec![0.0; positions.len()];
        let names = rig.joint_names().map(String::from).collect();
        let trajectory = Trajectory::new(rig.name.clone(), names, Duration::from_secs_f64(period), positions, velocities).unwrap();
        if validate(&trajectory, &rig).is_ok() {
            prop_assert!(independently_safe(&trajectory));
        }
    }
}

#[test]
fn a_step_just_over_max_speed_is_refused() {
    let rig = irb120();
    let max_step = rig.joints[0].limits.max_speed * 0.004;
    let names: Vec<String> = rig.joint_names().map(String::from).collect();
    let make = |step: f64| {
        let mut positions = vec![0.0; 12];
        positions[6] = step;
        Trajectory::new(
            rig.name.clone(),
            names.clone(),
            Duration::from_millis(4),
            positions,
            vec![0.0; 12],
        )
        .unwrap()
    };
    // The step alone (`validate_motion`): two samples, a step at almost full speed...
    assert!(validate_motion(&make(max_step * 0.999), &rig).is_ok());
    assert!(matches!(
        validate_motion(&make(max_step * 1.001), &rig),
        Err(TrajectoryError::OverSpeed { sample: 1, .. })
    ));
    // ...which, as a whole trajectory, ends moving: the hold after it would stop the axis
    // within one period.
    assert!(matches!(
        validate(&make(max_step * 0.999), &rig),
        Err(TrajectoryError::EndsMoving { .. })
    ));
}

/// One prismatic axis, limits chosen so that the arithmetic below is exact by hand:
/// 0.5 m/s and 2 m/s^2, sampled every 4 ms: a step of at most 2 mm, a second difference of
/// at most 2 x 0.004^2 = 3.2e-5 m, a velocity change of at most 2 x 0.004 = 0.008 m/s.
fn slide() -> Rig {
    Rig {
        name: "slide".into(),
        base_frame: "base".into(),
        tool_frame: "tool".into(),
        joints: vec![Joint {
            name: "carriage".into(),
            kind: JointKind::Prismatic,
            origin: DAffine3::IDENTITY,
            axis: DVec3::X,
            limits: JointLimits {
                lower: -1.0,
                upper: 1.0,
                max_speed: 0.5,
                max_acceleration: 2.0,
            },
        }],
        tool: DAffine3::IDENTITY,
        bodies: Vec::new(),
        allowed_pairs: Vec::new(),
    }
}

fn on_slide(positions: &[f64], velocities: &[f64]) -> Trajectory {
    Trajectory::new(
        "slide".into(),
        vec!["carriage".into()],
        Duration::from_millis(4),
        positions.to_vec(),
        velocities.to_vec(),
    )
    .unwrap()
}

#[test]
fn an_acceleration_exactly_at_the_limit_is_accepted() {
    // From rest, second differences of +L, +L, -L, -L with L = 3.2e-5 m (the limit): steps
    // of 0, L, 2L, L, 0, so positions 0, 0, L, 3L, 4L, 4L; sampled velocities step / period,
    // changing by exactly 0.008 m/s at a time.
    let positions = [0.0, 0.0, 3.2e-5, 9.6e-5, 1.28e-4, 1.28e-4];
    let velocities = [0.0, 0.0, 0.008, 0.016, 0.008, 0.0];
    assert_eq!(
        validate(&on_slide(&positions, &velocities), &slide()),
        Ok(())
    );
    // The same backwards, braking first.
    let back: Vec<f64> = positions.iter().map(|p| -p).collect();
    let back_v: Vec<f64> = velocities.iter().map(|v| -v).collect();
    assert_eq!(validate(&on_slide(&back, &back_v), &slide()), Ok(()));
}

#[test]
fn an_acceleration_over_the_limit_is_refused_naming_sample_joint_and_values() {
    // 3.3e-5 m of second difference at sample 2: 3.3e-5 / 0.004^2 = 2.0625 m/s^2. The speed
    // (3.3e-5 m in 4 ms, 8 mm/s) is far below 0.5 m/s.
    let positions = [0.0, 0.0, 0.0, 3.3e-5, 6.6e-5];
    let velocities = [0.0; 5];
    let error = validate(&on_slide(&positions, &velocities), &slide()).unwrap_err();
    let TrajectoryError::OverAcceleration {
        sample,
        ref joint,
        acceleration,
        max_acceleration,
        unit,
    } = error
    else {
        panic!("expected an acceleration error, got: {error}");
    };
    assert_eq!((sample, joint.as_str(), unit), (2, "carriage", "m/s^2"));
    assert!((acceleration - 2.0625).abs() < 1e-9, "{acceleration}");
    assert_eq!(max_acceleration, 2.0);
    let message = error.to_string();
    assert!(message.contains("sample 2: carriage"), "{message}");
    assert!(message.contains("2.062500 m/s^2"), "{message}");
    assert!(
        message.contains("max acceleration 2.000000 m/s^2"),
        "{message}"
    );
    // Braking as hard is refused too, at the sample where it happens.
    let braking = [6.6e-5, 6.6e-5, 6.6e-5, 3.3e-5, 0.0];
    let error = validate(&on_slide(&braking, &velocities), &slide()).unwrap_err();
    assert!(
        matches!(error, TrajectoryError::OverAcceleration { sample: 2, acceleration, .. }
            if (acceleration + 2.0625).abs() < 1e-9),
        "{error}"
    );
}

#[test]
fn a_velocity_change_over_the_limit_is_refused() {
    // Positions that never accelerate, with a sampled velocity jumping 0.0081 m/s in one
    // period: 0.0081 / 0.004 = 2.025 m/s^2.
    let positions = [0.0; 4];
    let velocities = [0.0, 0.0, 0.0081, 0.0081];
    let error = validate(&on_slide(&positions, &velocities), &slide()).unwrap_err();
    let TrajectoryError::VelocityOverAcceleration {
        sample,
        acceleration,
        max_acceleration,
        ..
    } = error
    else {
        panic!("expected a velocity change error, got: {error}");
    };
    assert_eq!(sample, 2);
    assert!((acceleration - 2.025).abs() < 1e-9, "{acceleration}");
    assert_eq!(max_acceleration, 2.0);
    assert!(error.to_string().contains("2.025000 m/s^2"), "{error}");
    // 0.008 m/s is exactly the limit.
    let velocities = [0.0, 0.0, 0.008, 0.008];
    assert_eq!(
        validate(&on_slide(&positions, &velocities), &slide()),
        Ok(())
    );
}

#[test]
fn a_revolute_axis_over_its_acceleration_is_refused_in_rad_per_s2() {
    // IRB 120 joint 1: 1000 deg/s^2 = 17.4533 rad/s^2; a second difference of 3e-4 rad in
    // 4 ms periods is 3e-4 / 1.6e-5 = 18.75 rad/s^2.
    let rig = irb120();
    let mut positions = vec![0.0; 18];
    positions[12] = 3e-4;
    let names = rig.joint_names().map(String::from).collect();
    let trajectory = Trajectory::new(
        rig.name.clone(),
        names,
        Duration::from_millis(4),
        positions,
        vec![0.0; 18],
    )
    .unwrap();
    let error = validate(&trajectory, &rig).unwrap_err();
    assert!(
        matches!(error, TrajectoryError::OverAcceleration { sample: 1, ref joint, acceleration, unit: "rad/s^2", .. }
            if joint == "joint_1" && (acceleration - 18.75).abs() < 1e-9),
        "{error}"
    );
}
