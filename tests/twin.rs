//! The twin polices its inputs like a real controller (docs/protocol.md 6): it drops
//! targets until a bridge Hello binds it; out-of-limit, over-speed and over-acceleration
//! targets are faults with no motion and one notice; silence trips the watchdog into a
//! hold within the limits; a reset clears a fault and unbinds it.

use crate::common;

use common::irb120;
use proptest::prelude::*;
use rigbridge::protocol::{AxisValues, Command, ControllerStatus, Fault, JointTarget};
use rigbridge::twin::{Twin, TwinSettings};

const START: [f64; 6] = [0.0, 0.0, 0.0, 0.0, 0.5, 0.0];

/// A twin bound by a bridge Hello, holding at START.
fn twin() -> Twin {
    let mut twin = Twin::new(&irb120(), TwinSettings::default(), &START).unwrap();
    twin.bridge_hello();
    twin
}

/// Axis `axis` from START, accelerating at `accel` rad/s² up to `speed` rad/s: positions
/// and velocities of `cycles` targets 4 ms apart (exact integration of the velocity).
fn ramp(axis: usize, accel: f64, speed: f64, cycles: usize) -> Vec<([f64; 6], [f64; 6])> {
    let mut q = START;
    let mut v = 0.0f64;
    (0..cycles)
        .map(|_| {
            let next = (v + accel * 0.004).min(speed);
            q[axis] += (v + next) / 2.0 * 0.004;
            v = next;
            let mut velocities = [0.0; 6];
            velocities[axis] = v;
            (q, velocities)
        })
        .collect()
}

fn target(seq: u32, positions: &[f64], velocities: &[f64]) -> Command {
    Command::Target(JointTarget {
        seq,
        t: std::time::Duration::from_millis(4) * seq,
        positions: AxisValues::from_slice(positions).unwrap(),
        velocities: AxisValues::from_slice(velocities).unwrap(),
    })
}

#[test]
fn an_initial_position_outside_the_limits_names_the_value_and_the_limits_in_degrees() {
    // joint_3 of the IRB 120 is +70 / -110 deg (config/irb120.toml).
    let initial = [0.0, 0.0, 80.0_f64.to_radians(), 0.0, 0.5, 0.0];
    let refused = Twin::new(&irb120(), TwinSettings::default(), &initial)
        .err()
        .expect("refused")
        .to_string();
    assert_eq!(
        refused,
        "initial position: joint_3 = 80.000 deg is outside its limits [-110.000, 70.000] deg"
    );
}

#[test]
fn tracks_a_slow_ramp_with_lag_and_reports_ok() {
    let mut twin = twin();
    let mut last = None;
    // 10 rad/s² up to 0.5 rad/s: well under axis 1's 17.45 rad/s² and 4.36 rad/s.
    let targets = ramp(0, 10.0, 0.5, 500);
    for (seq, (q, v)) in (1..).zip(&targets) {
        twin.handle(&target(seq, q, v));
        last = Some(twin.tick());
    }
    let feedback = last.unwrap();
    assert_eq!(feedback.status, ControllerStatus::Ok);
    assert_eq!(feedback.seq, 500);
    let lag = targets[499].0[0] - feedback.positions.as_slice()[0];
    // Delay 12 ms + first-order lag 1/(2 pi 20 Hz) = 20 ms at 0.5 rad/s: about 0.01 rad.
    assert!(lag > 0.005 && lag < 0.015, "lag {lag}");
}

#[test]
fn watchdog_holds_after_silence_within_limits() {
    let mut twin = twin();
    for (seq, (q, v)) in (1..).zip(&ramp(1, 15.0, 0.75, 100)) {
        twin.handle(&target(seq, q, v));
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

#[test]
fn targets_before_a_hello_are_dropped_without_motion() {
    let mut twin = Twin::new(&irb120(), TwinSettings::default(), &START).unwrap();
    let before = twin.tick();
    let (q, v) = ramp(0, 10.0, 0.5, 1)[0];
    twin.handle(&target(1, &q, &v));
    let after = twin.tick();
    assert_eq!((after.seq, after.positions), (0, before.positions));
    assert_eq!(after.status, ControllerStatus::Holding);
    assert_eq!(twin.counters().unbound_targets, 1);
    twin.bridge_hello();
    twin.handle(&target(2, &q, &v));
    assert_eq!(
        twin.tick().seq,
        2,
        "accepted after the Hello, whatever its seq"
    );
    twin.link_lost();
    twin.handle(&target(3, &q, &v));
    assert_eq!(
        twin.counters().unbound_targets,
        2,
        "unbound again after link loss"
    );
}

#[test]
fn a_velocity_jump_from_rest_is_an_acceleration_fault_with_one_notice() {
    let mut twin = twin();
    let before = twin.tick().positions;
    // Axis 2 (index 1) allows 1000 deg/s² = 17.4533 rad/s²: 0.0698 rad/s in one 4 ms cycle.
    // 0.08 rad/s at once is beyond it; the step (0.32 mrad) is within speed.
    let mut q = START;
    q[1] += 0.08 * 0.004;
    twin.handle(&target(1, &q, &[0.0, 0.08, 0.0, 0.0, 0.0, 0.0]));
    let feedback = twin.tick();
    assert_eq!(
        feedback.status,
        ControllerStatus::Fault(Fault::OverAcceleration { axis: 1 })
    );
    assert_eq!(feedback.positions, before);
    let notice = twin.take_fault_notice().expect("a Fault notice");
    assert_eq!(notice.fault, Fault::OverAcceleration { axis: 1 });
    assert!(notice.text.contains("joint_2"), "{}", notice.text);
    assert_eq!(twin.take_fault_notice(), None, "sent once");
}

#[test]
fn a_position_kink_within_speed_is_an_acceleration_fault() {
    let mut twin = twin();
    // Axis 1: a_max T² = 17.4533 * 16e-6 = 279 µrad. From rest, a first step of 200 µrad
    // passes (zero velocity claimed, so no velocity change); a second of 600 µrad is a
    // second difference of 400 µrad: refused.
    let mut q = START;
    q[0] += 200e-6;
    twin.handle(&target(1, &q, &[0.0; 6]));
    assert_eq!(twin.tick().status, ControllerStatus::Ok);
    q[0] += 600e-6;
    twin.handle(&target(2, &q, &[0.0; 6]));
    assert_eq!(
        twin.tick().status,
        ControllerStatus::Fault(Fault::OverAcceleration { axis: 0 })
    );
}

#[test]
fn a_reset_clears_an_estop_and_needs_a_new_hello() {
    let mut twin = twin();
    twin.handle(&Command::EStop);
    assert_eq!(twin.tick().status, ControllerStatus::Fault(Fault::EStop));
    twin.handle(&Command::Reset);
    let held = twin.tick();
    assert_eq!(held.status, ControllerStatus::Holding);
    assert!(
        !twin.is_bound(),
        "a reset unbinds the twin until the bridge's Hello"
    );
    let (q, v) = ramp(0, 10.0, 0.5, 1)[0];
    twin.handle(&target(1, &q, &v));
    assert_eq!(twin.tick().seq, 0);
    twin.bridge_hello();
    twin.handle(&target(2, &q, &v));
    let moving = twin.tick();
    assert_eq!((moving.status, moving.seq), (ControllerStatus::Ok, 2));
}
