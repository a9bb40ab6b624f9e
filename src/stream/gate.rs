//! The last line of defence before a target leaves: inside the joint's limits, no velocity,
//! position step, velocity change or position second difference beyond the axis's speed
//! and acceleration. A refusal names the joint, what it broke, by how much and the limit,
//! for the stream's report. For a trajectory that was not checked whole against the cell
//! before it was handed over, [`CellGate`] also checks each target's step from the one
//! before against the cell's collision model, within the cycle (no allocation; a refusal
//! names the two bodies, the clearance and the joints). Owns only the checks; what happens
//! on a refusal (nothing of the target is sent, the controller is told to stop) is the
//! cycle's.

use super::online::CellCheck;
use crate::cell::{Clearance, CollisionModel, Scratch};
use crate::protocol::AxisValues;
use crate::rig::{Joint, JointKind, Rig};
use std::sync::{Arc, Mutex};

/// What a target broke.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum GateCheck {
    Position,
    Speed,
    /// The step from the last target, over a period: a speed.
    Step,
    /// The change of the commanded velocity over a period: an acceleration.
    VelocityChange,
    /// The second difference of the last three positions over a period squared: an
    /// acceleration (holding still right after a motion is one).
    SecondDifference,
}

/// A refused target, in words (SI values inside, the user's unit in the message).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error(
    "the safety gate refused a target: {joint}: {} {:.4} {unit}{per} beyond its limit {:.4} {unit}{per}",
    check.words(), kind.to_user(*value), kind.to_user(*limit),
    unit = kind.unit(), per = check.per()
)]
pub struct GateRefusal {
    pub joint: String,
    pub kind: JointKind,
    pub check: GateCheck,
    /// Position (rad or m), speed (per s) or acceleration (per s^2), as the check has it.
    pub value: f64,
    pub limit: f64,
}

impl GateCheck {
    fn words(self) -> &'static str {
        match self {
            GateCheck::Position => "position",
            GateCheck::Speed => "commanded speed",
            GateCheck::Step => "speed of the step from the last target",
            GateCheck::VelocityChange => "acceleration of the commanded velocity",
            GateCheck::SecondDifference => "acceleration of the last three positions",
        }
    }

    fn per(self) -> &'static str {
        match self {
            GateCheck::Position => "",
            GateCheck::Speed | GateCheck::Step => "/s",
            GateCheck::VelocityChange | GateCheck::SecondDifference => "/s^2",
        }
    }
}

/// A target refused by the cell's collision model: the two bodies, their distance against
/// the margin, and the target's joints in the user's units.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error(
    "the safety gate refused a target: {}: {body_a} and {body_b} {} on the step to the joints at \
     [{joints}]",
    if *distance_m <= 0.0 { "collision" } else { "within the margin" },
    if *distance_m <= 0.0 {
        format!("overlap by {:.4} m (margin {margin_m:.4} m)", -distance_m)
    } else {
        format!("are {distance_m:.4} m apart, less than the margin of {margin_m:.4} m")
    }
)]
pub struct CellRefusal {
    pub body_a: String,
    pub body_b: String,
    /// Negative: how deep the bodies overlap (m).
    pub distance_m: f64,
    pub margin_m: f64,
    /// `joint value unit`, comma separated.
    pub joints: String,
}

/// The cell's collision model at the gate, with its own buffers (made before the cycle, so
/// a check allocates nothing).
pub struct CellGate<'a> {
    model: &'a CollisionModel,
    scratch: Scratch,
}

impl<'a> CellGate<'a> {
    pub fn new(model: &'a CollisionModel) -> Self {
        CellGate {
            model,
            scratch: model.scratch(),
        }
    }

    /// The motion from `previous`, the last target sent (none: the first target, checked
    /// alone), to `positions`, continuously: the closest pair when it comes closer than the
    /// margin.
    pub fn check(
        &mut self,
        previous: Option<&AxisValues>,
        positions: &AxisValues,
    ) -> Result<(), Clearance> {
        let to = positions.as_slice();
        let from = previous.map_or(to, AxisValues::as_slice);
        self.model
            .check_step(from, to, &mut self.scratch)
            .map(|_| ())
    }

    /// `clearance`, refused at `positions` (SI units), in words. Allocates: the stream ends.
    pub fn refusal(&self, rig: &Rig, clearance: &Clearance, positions: &AxisValues) -> CellRefusal {
        let joints: Vec<String> = rig
            .joints
            .iter()
            .zip(positions.as_slice())
            .map(|(joint, value)| {
                format!(
                    "{} {:.3} {}",
                    joint.name,
                    joint.kind.to_user(*value),
                    joint.kind.unit()
                )
            })
            .collect();
        CellRefusal {
            body_a: self.model.body_name(clearance.a).to_string(),
            body_b: self.model.body_name(clearance.b).to_string(),
            distance_m: clearance.distance_m,
            margin_m: self.model.margin(),
            joints: joints.join(", "),
        }
    }
}

/// The cell's collision model as the online motion's [`CellCheck`] (jog, goals): each
/// step a cycle generates is checked continuously before it is sent; a step that starts
/// inside the margin is admitted only when it moves away. Only the cycle's
/// thread checks, so the lock is never contended; it is there because a session's control
/// is shared with the API that sets it.
pub struct ModelCheck {
    model: Arc<CollisionModel>,
    scratch: Mutex<Scratch>,
}

impl ModelCheck {
    pub fn new(model: Arc<CollisionModel>) -> Self {
        let scratch = Mutex::new(model.scratch());
        ModelCheck { model, scratch }
    }
}

impl std::fmt::Debug for ModelCheck {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("ModelCheck")
    }
}

impl CellCheck for ModelCheck {
    fn admits(&self, from: &[f64], to: &[f64]) -> bool {
        // A poisoned lock means a cycle panicked mid-check: refuse, the arm brakes.
        let Ok(mut scratch) = self.scratch.lock() else {
            return false;
        };
        self.model.check_step(from, to, &mut scratch).is_ok()
            || self.model.step_leaves_margin(from, to, &mut scratch)
    }

    fn room_m(&self, at: &[f64]) -> Option<f64> {
        let mut scratch = self.scratch.lock().ok()?;
        Some(self.model.clearance(at, &mut scratch).distance_m - self.model.margin())
    }
}

/// The targets sent before this one, for the checks between periods.
#[derive(Clone, Copy, Default)]
pub struct Sent {
    /// The last target's positions and velocities.
    pub previous: Option<(AxisValues, AxisValues)>,
    /// The positions of the target before it.
    pub before_previous: Option<AxisValues>,
}

/// Checks one target (`dt`: the period in seconds) against every joint of `rig`.
pub fn check(
    rig: &Rig,
    positions: &AxisValues,
    velocities: &AxisValues,
    sent: &Sent,
    dt: f64,
) -> Result<(), GateRefusal> {
    for (axis, joint) in rig.joints.iter().enumerate() {
        check_joint(joint, axis, positions, velocities, sent, dt)?;
    }
    Ok(())
}

fn check_joint(
    joint: &Joint,
    axis: usize,
    positions: &AxisValues,
    velocities: &AxisValues,
    sent: &Sent,
    dt: f64,
) -> Result<(), GateRefusal> {
    let limits = joint.limits;
    let value = positions.as_slice()[axis];
    let velocity = velocities.as_slice()[axis];
    let refuse = |check, value: f64, limit| {
        Err(GateRefusal {
            joint: joint.name.clone(),
            kind: joint.kind,
            check,
            value,
            limit,
        })
    };
    if !limits.contains(value) {
        let bound = if value < limits.lower {
            limits.lower
        } else {
            limits.upper
        };
        return refuse(GateCheck::Position, value, bound);
    }
    if !limits.speed_ok(velocity) {
        return refuse(GateCheck::Speed, velocity.abs(), limits.max_speed);
    }
    let Some((p, v)) = sent.previous else {
        return Ok(());
    };
    let step = value - p.as_slice()[axis];
    if !limits.step_ok(step, dt) {
        return refuse(GateCheck::Step, step.abs() / dt, limits.max_speed);
    }
    let change = velocity - v.as_slice()[axis];
    if !limits.velocity_change_ok(change, dt) {
        let acceleration = change.abs() / dt;
        return refuse(
            GateCheck::VelocityChange,
            acceleration,
            limits.max_acceleration,
        );
    }
    if let Some(b) = sent.before_previous {
        let second = value - 2.0 * p.as_slice()[axis] + b.as_slice()[axis];
        if !limits.second_difference_ok(second, dt) {
            let acceleration = second.abs() / (dt * dt);
            return refuse(
                GateCheck::SecondDifference,
                acceleration,
                limits.max_acceleration,
            );
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    const DT: f64 = 0.004;

    fn rig() -> Rig {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/config/irb120.toml");
        crate::rig::load_rig(std::path::Path::new(path)).expect("the IRB 120 rig loads")
    }

    fn values(first: f64) -> AxisValues {
        let mut v = AxisValues::zeros(6);
        v.as_mut_slice()[0] = first;
        v
    }

    /// Axis 1 at `q` moving at `v`, after `sent`: what the gate says.
    fn gate(q: f64, v: f64, sent: &Sent) -> Result<(), GateRefusal> {
        check(&rig(), &values(q), &values(v), sent, DT)
    }

    #[test]
    fn each_refusal_names_its_joint_check_value_and_limit() {
        let rig = rig();
        let limits = rig.joints[0].limits;
        let refused = |result: Result<(), GateRefusal>| result.unwrap_err();
        let beyond = refused(gate(limits.upper + 0.01, 0.0, &Sent::default()));
        assert_eq!(
            (beyond.joint.as_str(), beyond.check, beyond.limit),
            (
                rig.joints[0].name.as_str(),
                GateCheck::Position,
                limits.upper
            )
        );
        let fast = refused(gate(0.0, limits.max_speed * 1.01, &Sent::default()));
        assert_eq!(
            (fast.check, fast.limit),
            (GateCheck::Speed, limits.max_speed)
        );
        let from_rest = Sent {
            previous: Some((values(0.0), values(0.0))),
            before_previous: Some(values(0.0)),
        };
        let jump = refused(gate(limits.max_speed * DT * 1.01, 0.0, &from_rest));
        assert_eq!(jump.check, GateCheck::Step);
        assert!((jump.value - limits.max_speed * 1.01).abs() < 1e-9);
        let lurch = limits.max_acceleration * DT * 1.01;
        assert_eq!(
            refused(gate(0.0, lurch, &from_rest)).check,
            GateCheck::VelocityChange
        );
        let moving = Sent {
            previous: Some((values(0.001), values(0.0))),
            before_previous: Some(values(0.0)),
        };
        // Holding still right after a step of 1 mrad: 62.5 rad/s^2 at 4 ms.
        let halt = refused(gate(0.001, 0.0, &moving));
        assert_eq!(halt.check, GateCheck::SecondDifference);
        assert!((halt.value - 0.001 / (DT * DT)).abs() < 1e-6);
        let words = halt.to_string();
        assert!(
            words.contains("deg/s^2") && words.contains(&rig.joints[0].name),
            "{words}"
        );
    }

    #[test]
    fn a_target_within_every_limit_passes() {
        let rig = rig();
        let limits = rig.joints[0].limits;
        let step = limits.max_speed * DT * 0.5;
        let sent = Sent {
            previous: Some((values(step), values(limits.max_speed * 0.5))),
            before_previous: Some(values(0.0)),
        };
        assert_eq!(gate(2.0 * step, limits.max_speed * 0.5, &sent), Ok(()));
    }
}
