//! Timing a free path, and joint moves that go around the cell where they must.
//!
//! A free path is timed along its own polyline by `path.rs`'s timing (the fastest speed
//! profile within every axis' scaled speed and acceleration, slowing through the bends),
//! not by the jerk-limited joint planner: rsruckig synchronises the axes in time, not in
//! phase, so its rest-to-rest moves leave the straight line between waypoints, and only
//! that line was proven clear. The timed trajectory is checked again whole against the
//! cell (`check_clear`) and the limits (`validate`, in `Samples::finish`). Where the
//! samples that cut a bend's corner come too close, or a bend is too sharp to slow through
//! within the limits, the path is timed again stopping at every waypoint, which keeps
//! every sample on a proven stretch. Owns that choice and the
//! joining of moves; the speed profile is `path.rs`'s.

use super::super::clearance::check_clear;
use super::super::path::{JointPath, PathNode, PathTiming};
use super::super::plan::{
    AxisLimits, PlanError, PlanSettings, Samples, check_waypoint, plan_joint_move,
};
use super::{FreePlanError, distance, plan_free};
use crate::cell::CollisionModel;
use crate::motion::Trajectory;
use crate::rig::Rig;
use crate::trajectory::Origins;
use thiserror::Error;

/// How a timed path passes its inner waypoints.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Through {
    /// Without stopping, as fast as each bend allows.
    Blended,
    /// At rest at each: every sample on the polyline.
    Stopping,
}

/// `waypoints` (from [`plan_free`]: the first where the arm is, at rest) timed within the
/// scaled limits of `settings`, and checked again against `model` and the limits. Errors
/// name the last waypoint as waypoint `target`.
pub fn time_free(
    rig: &Rig,
    model: &CollisionModel,
    waypoints: &[Vec<f64>],
    target: usize,
    settings: &PlanSettings,
) -> Result<Trajectory, FreePlanError> {
    let origins = Origins::whole("the free move");
    // A bend too sharp for the timing to slow through within its limits, or whose cut
    // corner comes too close, is passed at rest instead.
    let blended = time_polyline(rig, waypoints, target, settings, Through::Blended);
    if let Ok(blended) = blended
        && check_clear(&blended, rig, model, &origins).is_ok()
    {
        return Ok(blended);
    }
    let stopping = time_polyline(rig, waypoints, target, settings, Through::Stopping)?;
    check_clear(&stopping, rig, model, &origins).map_err(FreePlanError::Timed)?;
    Ok(stopping)
}

/// [`plan_free`] from `start` to `goal` with `settings.free`, then [`time_free`].
pub fn plan_free_move(
    model: &CollisionModel,
    rig: &Rig,
    start: &[f64],
    goal: &[f64],
    settings: &PlanSettings,
) -> Result<Trajectory, FreePlanError> {
    settings.check()?;
    let waypoints = plan_free(model, rig, start, goal, &settings.free)?;
    time_free(rig, model, &waypoints, 0, settings)
}

/// `waypoints` timed along their polyline, at rest at both ends.
fn time_polyline(
    rig: &Rig,
    waypoints: &[Vec<f64>],
    target: usize,
    settings: &PlanSettings,
    through: Through,
) -> Result<Trajectory, PlanError> {
    let limits = AxisLimits::new(rig, settings)?;
    let timing = PathTiming {
        rig,
        settings,
        limits: &limits,
        waypoint: target,
    };
    let mut samples = Samples::at_rest(&waypoints[0], settings.budget, settings.period);
    // The path's own points: the polyline is the true path.
    let on_path = |_: f64, seed: &[f64]| Ok::<_, PlanError>(seed.to_vec());
    match through {
        Through::Blended => timing.append(&polyline(waypoints), on_path, &mut samples)?,
        Through::Stopping => {
            for stretch in waypoints.windows(2).filter(|w| w[0] != w[1]) {
                timing.append(&polyline(stretch), on_path, &mut samples)?;
            }
        }
    }
    samples.finish_differenced(rig, settings.period)
}

/// The polyline through `waypoints`, its parameter the share of its joint-space length.
fn polyline(waypoints: &[Vec<f64>]) -> JointPath {
    let total = super::path_length(waypoints);
    let mut path = JointPath::starting_at(PathNode {
        u: 0.0,
        joints: waypoints[0].clone(),
    });
    let mut along = 0.0;
    for pair in waypoints.windows(2) {
        along += distance(&pair[0], &pair[1]);
        path.push(along / total, pair[1].clone());
    }
    path
}

/// Joint moves through targets, each the jerk-limited joint move where that is clear of
/// the cell and a free move around it where it is not.
#[derive(Debug, Clone)]
pub struct MovesAround {
    pub trajectory: Trajectory,
    /// The sample each target sits at, in order.
    pub marks: Vec<usize>,
    /// Per target, whether its move went around the cell.
    pub around: Vec<bool>,
}

/// A move to one target that could not be planned, around the cell or not.
#[derive(Debug, Clone, PartialEq, Error)]
#[error("the move to target {target}: {error}")]
pub struct MoveAroundRefused {
    pub target: usize,
    /// Boxed: it carries its words, and errors travel up by value.
    pub error: Box<FreePlanError>,
}

/// From `start` through each of `targets` in turn, at rest at each: the jerk-limited joint
/// move of [`plan_joint_moves`](super::super::plan_joint_moves) where it keeps clear of
/// `model`'s cell by its margin, else a free move ([`plan_free`] with `settings.free`, then
/// [`time_free`]). Every target is checked against the limits before anything is planned.
pub fn plan_joint_moves_around(
    rig: &Rig,
    model: &CollisionModel,
    start: &[f64],
    targets: &[Vec<f64>],
    settings: &PlanSettings,
) -> Result<MovesAround, MoveAroundRefused> {
    for (target, values) in targets.iter().enumerate() {
        check_waypoint(rig, target, values).map_err(|e| MoveAroundRefused {
            target,
            error: Box::new(e.into()),
        })?;
    }
    let mut planned: Option<Trajectory> = None;
    let mut marks = Vec::with_capacity(targets.len());
    let mut around = Vec::with_capacity(targets.len());
    let mut from = start.to_vec();
    for (target, to) in targets.iter().enumerate() {
        let refused = |error: FreePlanError| MoveAroundRefused {
            target,
            error: Box::new(error),
        };
        let leg_settings = planned
            .as_ref()
            .map_or(*settings, |done| settings.after(done));
        let direct = plan_joint_move(rig, &from, to, target, &leg_settings)
            .map_err(|e| refused(e.into()))?;
        let clear = check_clear(&direct, rig, model, &Origins::default()).is_ok();
        let leg = if clear {
            direct
        } else {
            let waypoints =
                plan_free(model, rig, &from, to, &leg_settings.free).map_err(refused)?;
            time_free(rig, model, &waypoints, target, &leg_settings).map_err(refused)?
        };
        around.push(!clear);
        match planned.as_mut() {
            Some(done) => done.append(&leg),
            None => planned = Some(leg),
        }
        marks.push(planned.as_ref().map_or(0, |t| t.len() - 1));
        from = to.clone();
    }
    let trajectory = match planned {
        Some(trajectory) => trajectory,
        // No target: the arm stays where it is.
        None => Samples::at_rest(start, settings.budget, settings.period)
            .finish(rig, settings.period)
            .map_err(|e| MoveAroundRefused {
                target: 0,
                error: Box::new(e.into()),
            })?,
    };
    Ok(MovesAround {
        trajectory,
        marks,
        around,
    })
}
