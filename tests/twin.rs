//! The twin polices its inputs like a real controller: out-of-limit or over-speed targets
//! are faults with no motion; silence trips the watchdog into a hold within the limits.

mod common;

use common::irb120;
use proptest::prelude::*;
use rigbridge::protocol::{AxisValues, Command, ControllerStatus, Fault, JointTarget};
use rigbridge::twin::{Twin, TwinSettings};

const START: [f64; 6] = [0.0, 0.0, 0.0, 0.0, 0.5, 0.0];

fn twin() -> Twin {
    Twin::new(&irb120(), TwinSettings::default(), &START).unwrap()
}

fn target(seq: u32, positions: &[f64], velocities: &[f64]) -> Command {
    Command::Target(JointTarget {
        seq,
        t: f64::from(seq) * 0.004,
        positions: AxisValues::from_slice(positions).unwrap(),
        velocities: AxisValues::from_slice(velocities).unwrap(),
    })
}

#[test]
fn tracks_a_slow_ramp_with_lag_and_reports_ok() {
    let mut twin = twin();
    let mut q = START;
    let mut last = None;
    for seq in 1..=500 {
        q[0] += 0.002; // 0.5 rad/s, well under axis 1's max
        twin.handle(&target(seq, &q, &[0.5, 0.0, 0.0, 0.0, 0.0, 0.0]));
        last = Some(twin.tick());
    }
    let feedback = last.unwrap();
    assert_eq!(feedback.status, ControllerStatus::Ok);
    assert_eq!(feedback.seq, 500);
    let lag = q[0] - feedback.positions.as_slice()[0];
    // Delay 12 ms + first-order lag 1/(2 pi 20 Hz) = 20 ms at 0.5 rad/s: about 0.01 rad.
    assert!(lag > 0.005 && lag < 0.015, "lag {lag}");
}

#[test]
fn watchdog_holds_after_silence_within_limits() {
    let mut twin = twin();
    let mut q = START;
    for seq in 1..=100 {
        q[1] += 0.003;
        twin.handle(&target(seq, &q, &[0.0, 0.75, 0.0, 0.0, 0.0, 0.0]));
        twin.tick();
    }
    let mut previous = twin.actual().to_vec();
    let mut holding_after = None;
    for cycle in 1..=500 {
        let feedback = twin.tick();
        let now = feedback.positions.as_slice().to_vec();
        let rig = irb120();
        assert_eq!(rig.first_limit_violation(&now), None);
        for ((a, b), joint) in now.iter().zip(&previous).zip(&rig.joints) {
            assert!((a - b).abs() <= joint.limits.max_speed * 0.004 * (1.0 + 1e-9));
        }
        if feedback.status == ControllerStatus::Holding && holding_after.is_none() {
            holding_after = Some(cycle);
        }
        previous = now;
    }
    assert_eq!(holding_after, Some(25), "holds on the 25th silent cycle");
    let settled = twin.tick().positions.as_slice()[1];
    assert!(
        (settled - twin.tick().positions.as_slice()[1]).abs() < 1e-9,
        "still moving after the hold"
    );
}

#[test]
fn estop_halts_and_latches() {
    let mut twin = twin();
    twin.handle(&Command::EStop);
    let held = twin.tick();
    assert_eq!(held.status, ControllerStatus::Fault(Fault::EStop));
    let mut q = START;
    q[0] += 0.001;
    twin.handle(&target(1, &q, &[0.0; 6]));
    let after = twin.tick();
    assert_eq!(after.positions, held.positions);
    assert_eq!(after.status, ControllerStatus::Fault(Fault::EStop));
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(500))]

    /// Any target that breaks a limit or a speed is refused with a fault, and nothing moves
    /// then or afterwards.
    #[test]
    fn bad_targets_fault_and_never_move(
        axis in 0usize..6,
        over_limit in any::<bool>(),
        excess in 1e-6f64..3.0,
    ) {
        let rig = irb120();
        let limits = rig.joints[axis].limits;
        let mut twin = twin();
        let before = twin.tick().positions;
        let mut q = START;
        if over_limit {
            q[axis] = if excess > 1.5 { limits.upper + excess } else { limits.lower - excess };
        } else {
            // Beyond the 1 µrad the wire rounding is allowed.
            q[axis] += (limits.max_speed * 0.004) * (1.0 + excess) + 2e-6;
        }
        twin.handle(&target(1, &q, &[0.0; 6]));
        for _ in 0..50 {
            let feedback = twin.tick();
            prop_assert!(matches!(feedback.status, ControllerStatus::Fault(_)));
            prop_assert_eq!(feedback.positions, before);
            prop_assert_eq!(feedback.seq, 0);
        }
        let mut fine = START;
        fine[axis] += 1e-4;
        twin.handle(&target(2, &fine, &[0.0; 6]));
        prop_assert_eq!(twin.tick().positions, before);
    }
}
