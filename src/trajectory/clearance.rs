//! The collision check before motion: a whole trajectory against the cell's
//! [`CollisionModel`], continuously (joint-space linear between samples, as the streamer
//! interpolates them: `CollisionModel::check_path`), refused at its first sample whose
//! clearance falls below the margin. The refusal names the two bodies, the time in the job,
//! where that stretch came from ([`Origins`]), the joint values in the user's units and the
//! penetration or clearance against the margin. Owns the check of a planned trajectory and
//! its words; the geometry is `cell`'s, the stream's per-target check `stream::gate`'s.

use super::Origins;
use crate::cell::{CollisionModel, PathClearance, PathCollision};
use crate::motion::Trajectory;
use crate::rig::Rig;
use thiserror::Error;

/// A trajectory refused before motion for a collision, or for coming closer than the margin.
#[derive(Debug, Clone, PartialEq, Error)]
#[error(
    "{}: {body_a} and {body_b} {} at t = {t_s:.3} s of the job (sample {sample}), on {origin}, \
     with the joints at {}",
    if *collision { "collision" } else { "within the margin" },
    distance_words(*distance_m, *margin_m),
    joint_words(joints)
)]
pub struct CollisionRefusal {
    /// True when the bodies touch or overlap; false when they only come closer than the margin.
    pub collision: bool,
    pub body_a: String,
    pub body_b: String,
    /// Seconds from the trajectory's first sample.
    pub t_s: f64,
    pub sample: usize,
    /// Where that stretch of the trajectory came from, as the user wrote it.
    pub origin: String,
    /// The configuration refused, each joint in the user's unit.
    pub joints: Vec<JointValue>,
    /// The bodies' distance (m); negative: how deep they overlap.
    pub distance_m: f64,
    pub margin_m: f64,
}

/// One joint's value as a user writes it (degrees, metres for prismatic axes).
#[derive(Debug, Clone, PartialEq)]
pub struct JointValue {
    pub joint: String,
    pub value: f64,
    pub unit: &'static str,
}

pub(super) fn distance_words(distance_m: f64, margin_m: f64) -> String {
    if distance_m <= 0.0 {
        format!("overlap by {:.4} m (margin {margin_m:.4} m)", -distance_m)
    } else {
        format!("are {distance_m:.4} m apart, less than the margin of {margin_m:.4} m")
    }
}

pub(super) fn joint_words(joints: &[JointValue]) -> String {
    let values: Vec<String> = joints
        .iter()
        .map(|j| format!("{} {:.3} {}", j.joint, j.value, j.unit))
        .collect();
    format!("[{}]", values.join(", "))
}

impl CollisionRefusal {
    /// The refusal of the path where `model` found `at` (its sample, time, joints and
    /// closest pair), on the stretch that came from `origin`.
    pub fn of(
        model: &CollisionModel,
        rig: &Rig,
        at: &PathCollision,
        origin: impl Into<String>,
    ) -> CollisionRefusal {
        let distance_m = at.clearance.distance_m;
        CollisionRefusal {
            collision: distance_m <= 0.0,
            body_a: model.body_name(at.clearance.a).to_string(),
            body_b: model.body_name(at.clearance.b).to_string(),
            t_s: at.t,
            sample: at.index,
            origin: origin.into(),
            joints: joint_values(rig, &at.positions),
            distance_m,
            margin_m: model.margin(),
        }
    }
}

/// `positions` (SI units) in the user's units, named by the rig's joints.
pub fn joint_values(rig: &Rig, positions: &[f64]) -> Vec<JointValue> {
    rig.joints
        .iter()
        .zip(positions)
        .map(|(joint, value)| JointValue {
            joint: joint.name.clone(),
            value: joint.kind.to_user(*value),
            unit: joint.kind.unit(),
        })
        .collect()
}

/// Checks every sample of `trajectory` and the motion between them against `model`: the
/// path's smallest clearance, or the refusal at the first sample below the margin, named
/// by `origins` (boxed: a refusal carries its words, and errors travel up by value). Its
/// times count from the trajectory's first sample.
pub fn check_clear(
    trajectory: &Trajectory,
    rig: &Rig,
    model: &CollisionModel,
    origins: &Origins,
) -> Result<PathClearance, Box<CollisionRefusal>> {
    let mut scratch = model.scratch();
    let period_s = trajectory.period.as_secs_f64();
    let samples = (0..trajectory.len()).map(|k| (k as f64 * period_s, trajectory.position(k)));
    model
        .check_path(samples, &mut scratch)
        .map_err(|at| Box::new(CollisionRefusal::of(model, rig, &at, origins.at(at.index))))
}
