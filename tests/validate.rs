//! The validator's promise, checked independently: a trajectory it accepts has no sample
//! outside the limits and no step above max speed x period.

mod common;

use common::irb120;
use proptest::prelude::*;
use rigbridge::trajectory::{Trajectory, validate};

fn independently_safe(trajectory: &Trajectory) -> bool {
    let rig = irb120();
    (0..trajectory.len()).all(|i| {
        let q = trajectory.position(i);
        rig.joints.iter().enumerate().all(|(axis, joint)| {
            let inside = q[axis] >= joint.limits.lower && q[axis] <= joint.limits.upper;
            let slow = i == 0
                || (q[axis] - trajectory.position(i - 1)[axis]).abs()
                    <= joint.limits.max_speed * trajectory.period_s * (1.0 + 1e-9);
            inside && slow
        })
    })
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(1000))]

    #[test]
    fn accepted_trajectories_are_safe(
        start in prop::array::uniform6(-2.0f64..2.0),
        steps in prop::collection::vec(prop::array::uniform6(-0.03f64..0.03), 1..60),
        period in prop::sample::select(vec![0.001, 0.004, 0.01]),
        poison in prop::option::of((0usize..60, 0usize..6, prop::sample::select(vec![f64::NAN, f64::INFINITY, 7.5]))),
    ) {
        let rig = irb120();
        let mut positions = start.to_vec();
        let mut q = start;
        for step in &steps {
            for (v, s) in q.iter_mut().zip(step) {
                *v += s;
            }
            positions.extend_from_slice(&q);
        }
        if let Some((sample, axis, value)) = poison {
            let index = (sample % (steps.len() + 1)) * 6 + axis;
            positions[index] = value;
        }
        let velocities = vec![0.0; positions.len()];
        let names = rig.joint_names().map(String::from).collect();
        let trajectory = Trajectory::new(rig.name.clone(), names, period, positions, velocities).unwrap();
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
            0.004,
            positions,
            vec![0.0; 12],
        )
        .unwrap()
    };
    assert!(validate(&make(max_step * 0.999), &rig).is_ok());
    assert!(validate(&make(max_step * 1.001), &rig).is_err());
}
