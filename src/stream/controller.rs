//! Whether a controller admits what the bridge will stream (`docs/protocol.md` 6.1, step 6):
//! the same axes in the same order, limits at least as wide, speeds and accelerations at
//! least as high, and the same cycle, compared as the wire integers both sides see. It
//! reads the controller's Hello only; it must not talk to the link.

use crate::protocol::{Hello, cycle_us};
use crate::rig::{JointKind, Rig};
use std::time::Duration;
use thiserror::Error;

/// The first thing the controller's Hello does not admit, naming the axis (1-based in
/// words), the bridge's value and the controller's.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum Incompatible {
    #[error("the controller has {controller} axes, the rig {rig} has {bridge}")]
    AxisCount {
        rig: String,
        bridge: usize,
        controller: usize,
    },
    #[error("axis {axis} is {bridge} in the rig but {controller} on the controller")]
    Name {
        axis: usize,
        bridge: String,
        controller: String,
    },
    #[error("{joint}: the rig's {what} is {bridge} but the controller admits {controller}")]
    Limit {
        joint: String,
        what: &'static str,
        bridge: String,
        controller: String,
    },
    #[error(
        "the bridge streams every {bridge_us} us but the controller's cycle is {controller_us} us"
    )]
    Cycle { bridge_us: u32, controller_us: u32 },
}

/// A value as the wire carries it: whole micro-units.
fn wire(value: f64) -> i64 {
    (value * 1e6).round() as i64
}

pub fn check_controller(hello: &Hello, rig: &Rig, period: Duration) -> Result<(), Incompatible> {
    if hello.axis_names.len() != rig.dof() {
        return Err(Incompatible::AxisCount {
            rig: rig.name.clone(),
            bridge: rig.dof(),
            controller: hello.axis_names.len(),
        });
    }
    for (index, joint) in rig.joints.iter().enumerate() {
        if hello.axis_names[index] != joint.name {
            return Err(Incompatible::Name {
                axis: index + 1,
                bridge: joint.name.clone(),
                controller: hello.axis_names[index].clone(),
            });
        }
        let unit = Unit::of(joint.kind);
        let l = joint.limits;
        let checks = [
            (
                "lower limit",
                l.lower,
                hello.lower[index],
                wire(hello.lower[index]) <= wire(l.lower),
            ),
            (
                "upper limit",
                l.upper,
                hello.upper[index],
                wire(l.upper) <= wire(hello.upper[index]),
            ),
            (
                "max speed",
                l.max_speed,
                hello.max_speed[index],
                wire(l.max_speed) <= wire(hello.max_speed[index]),
            ),
            (
                "max acceleration",
                l.max_acceleration,
                hello.max_acceleration[index],
                wire(l.max_acceleration) <= wire(hello.max_acceleration[index]),
            ),
        ];
        if let Some((what, bridge, controller, _)) = checks.iter().find(|c| !c.3) {
            return Err(Incompatible::Limit {
                joint: joint.name.clone(),
                what,
                bridge: unit.show(what, *bridge),
                controller: unit.show(what, *controller),
            });
        }
    }
    let bridge_us = cycle_us(period);
    if bridge_us != hello.cycle_us {
        return Err(Incompatible::Cycle {
            bridge_us,
            controller_us: hello.cycle_us,
        });
    }
    Ok(())
}

/// Degrees for revolute axes, metres for prismatic ones, in messages.
#[derive(Clone, Copy)]
enum Unit {
    Degrees,
    Metres,
}

impl Unit {
    fn of(kind: JointKind) -> Self {
        match kind {
            JointKind::Revolute => Unit::Degrees,
            JointKind::Prismatic => Unit::Metres,
        }
    }

    fn show(self, what: &str, value: f64) -> String {
        let suffix = match what {
            "max speed" => "/s",
            "max acceleration" => "/s²",
            _ => "",
        };
        // The wire integer too: two values may differ by 1 µrad only.
        let micro = wire(value);
        match self {
            Unit::Degrees => format!(
                "{:.4} deg{suffix} ({micro} µrad{suffix})",
                value.to_degrees()
            ),
            Unit::Metres => format!("{value:.6} m{suffix} ({micro} µm{suffix})"),
        }
    }
}
