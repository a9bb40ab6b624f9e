//! Free moves around the cell (issue 29): when the direct joint move between two
//! configurations would come closer to the cell than its margin, a joint path around the
//! obstacles. RRT-Connect in joint space (`rrt.rs`), then shortcutting and corner cutting
//! (`shorten.rs`), then timing along the polyline within every axis' speed and
//! acceleration and the check of the timed result against the cell and the limits
//! (`timing.rs`); every stretch is proven clear by `checker.rs`. The same seed, start,
//! goal and cell give the same path.
//!
//! Owns the search, its budget, the shortening and the refusal when no path is found. The
//! geometry and the continuous check between configurations are `cell`'s
//! ([`CollisionModel::check_step`]), the timing `path.rs`'s, the limits `motion`'s
//! [`validate`](crate::motion::validate). Must not solve IK, touch links or clamp a
//! configuration: a start or goal outside the limits or inside an obstacle is refused.

mod checker;
mod rrt;
mod shorten;
mod timing;

pub use timing::{MovesAround, plan_free_move, plan_joint_moves_around, time_free};

use super::clearance::{JointValue, distance_words, joint_values, joint_words};
use super::plan::{PlanError, check_positive, check_start, check_waypoint};
use crate::cell::{Clearance, CollisionModel};
use crate::rig::Rig;
use checker::Checker;
use thiserror::Error;

/// How the free planner searches, and its budget.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FreePlanOptions {
    /// Seed of the random sampler: the same seed, start, goal and cell give the same path.
    pub seed: u64,
    /// The budget: random configurations drawn before the search gives up. A count, not a
    /// clock, so the answer (a path or a refusal) never depends on how busy the machine is;
    /// the default keeps the demo cell's planning time within 200 ms at the 95th
    /// percentile (docs/cell.md, "Free moves").
    pub max_samples: usize,
    /// Longest step (joint-space distance, rad; m for a prismatic axis) a tree grows by
    /// towards a sample. Edges are checked continuously, so this sets how finely the trees
    /// explore, not how finely they are checked.
    pub step: f64,
    /// Random shortcut attempts after the greedy pass.
    pub shortcut_attempts: usize,
    /// Rounds of corner cutting after the shortcuts.
    pub smoothing_rounds: usize,
    /// Clearance (m) the search keeps beyond the cell's margin. The continuous check proves
    /// a stretch only to 1 mm below the margin it is given; 2 mm more keeps every point of
    /// a planned path, and so every sample the timing puts on it, clear by the cell's own
    /// margin.
    pub allowance_m: f64,
}

/// Random configurations the default budget allows: enough that 98 % of the demo cell's
/// random pairs are planned (measured: docs/cell.md, "Free moves"), few enough that a
/// refusal comes within about a second on a loaded 2-core machine.
pub const DEFAULT_MAX_SAMPLES: usize = 2_000;

impl Default for FreePlanOptions {
    fn default() -> Self {
        Self {
            seed: 0,
            max_samples: DEFAULT_MAX_SAMPLES,
            // 0.35 rad (20 degrees): a few steps cross the IRB 120's workspace around a
            // pillar; much longer steps waste checks on edges that end inside obstacles.
            step: 0.35,
            shortcut_attempts: 30,
            smoothing_rounds: 3,
            allowance_m: 0.002,
        }
    }
}

impl FreePlanOptions {
    /// Every number usable: a budget of one sample or more, a positive finite step and
    /// allowance.
    pub fn check(&self) -> Result<(), PlanError> {
        let positive = [
            ("free.step", self.step),
            ("free.allowance_m", self.allowance_m),
        ];
        check_positive(&positive)?;
        if self.max_samples == 0 {
            return Err(PlanError::InvalidSettings {
                setting: "free.max_samples",
                value: 0.0,
                reason: "must be at least 1",
            });
        }
        Ok(())
    }
}

/// Which end of a free move.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum End {
    Start,
    Goal,
}

impl std::fmt::Display for End {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            End::Start => "start",
            End::Goal => "goal",
        })
    }
}

/// A free move refused before motion.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum FreePlanError {
    /// A start or goal outside the limits (or of the wrong length), unusable settings, or a
    /// path the timing could not keep within the limits.
    #[error(transparent)]
    Plan(#[from] PlanError),
    /// The start or goal itself is closer to the cell than its margin: no path can begin or
    /// end there.
    #[error(
        "the free move's {end} {} is not clear of the cell: {body_a} and {body_b} {}",
        joint_words(joints),
        distance_words(*distance_m, *margin_m)
    )]
    EndBlocked {
        end: End,
        joints: Vec<JointValue>,
        body_a: String,
        body_b: String,
        distance_m: f64,
        margin_m: f64,
    },
    /// The search spent its budget without joining start and goal.
    #[error(
        "no collision-free path from {} to {} within the budget: the direct move is blocked \
         by {blocked_a} and {blocked_b}; {samples} random configurations drawn (the budget, \
         free_max_samples = {max_samples}), {nodes} reached clear of the cell",
        joint_words(start),
        joint_words(goal)
    )]
    NoPath {
        start: Vec<JointValue>,
        goal: Vec<JointValue>,
        /// The pair closest on the direct move: what it would hit.
        blocked_a: String,
        blocked_b: String,
        samples: usize,
        max_samples: usize,
        /// Configurations in both trees when the search gave up.
        nodes: usize,
    },
    /// The timed path came closer than the margin: its samples are checked again against
    /// the cell, and this one failed (boxed: it carries its words).
    #[error("the timed free move: {0}")]
    Timed(Box<super::CollisionRefusal>),
}

impl FreePlanError {
    fn end_blocked(end: End, model: &CollisionModel, rig: &Rig, q: &[f64], at: Clearance) -> Self {
        FreePlanError::EndBlocked {
            end,
            joints: joint_values(rig, q),
            body_a: model.body_name(at.a).to_string(),
            body_b: model.body_name(at.b).to_string(),
            distance_m: at.distance_m,
            margin_m: model.margin(),
        }
    }
}

/// Collision-free joint waypoints from `start` to `goal` (SI units, one value per axis of
/// `rig`), the first `start` and the last `goal`: every straight joint-space stretch
/// between two of them proven clear of `model`'s cell by its margin, continuously. The
/// direct move alone when that is clear; otherwise RRT-Connect (seeded by
/// `options.seed`, within `options.max_samples`), shortcut and smoothed.
///
/// Refused before any motion: a start or goal outside the limits or not clear of the cell,
/// or no path within the budget (naming both ends in degrees, the bodies that block the
/// direct move and the budget spent).
pub fn plan_free(
    model: &CollisionModel,
    rig: &Rig,
    start: &[f64],
    goal: &[f64],
    options: &FreePlanOptions,
) -> Result<Vec<Vec<f64>>, FreePlanError> {
    options.check()?;
    check_start(rig, start)?;
    check_waypoint(rig, 0, goal)?;
    let checker = Checker::new(model, start, goal, options.allowance_m);
    for (end, q) in [(End::Start, start), (End::Goal, goal)] {
        let at = checker.point(q);
        if at.distance_m < model.margin() {
            return Err(FreePlanError::end_blocked(end, model, rig, q, at));
        }
    }
    if checker.edge(start, goal) {
        return Ok(vec![start.to_vec(), goal.to_vec()]);
    }
    let mut rng = rrt::rng(options.seed);
    let found = rrt::connect(&checker, rig, start, goal, options, &mut rng);
    let path = found.path.ok_or_else(|| {
        let blocked = checker.first_block(start, goal);
        FreePlanError::NoPath {
            start: joint_values(rig, start),
            goal: joint_values(rig, goal),
            blocked_a: model.body_name(blocked.a).to_string(),
            blocked_b: model.body_name(blocked.b).to_string(),
            samples: found.samples,
            max_samples: options.max_samples,
            nodes: found.nodes,
        }
    })?;
    let path = shorten::greedy(&checker, shorten::merge_collinear(path));
    let path = shorten::random(&checker, path, options.shortcut_attempts, &mut rng);
    Ok(shorten::cut_corners(
        &checker,
        path,
        options.smoothing_rounds,
    ))
}

/// The joint-space length of a polyline: the sum of its stretches' Euclidean lengths (rad;
/// m for a prismatic axis).
pub fn path_length(waypoints: &[Vec<f64>]) -> f64 {
    waypoints.windows(2).map(|w| distance(&w[0], &w[1])).sum()
}

/// Euclidean distance in joint space.
pub(crate) fn distance(a: &[f64], b: &[f64]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y) * (x - y))
        .sum::<f64>()
        .sqrt()
}

/// The point a fraction `s` of the way from `a` to `b`.
pub(crate) fn lerp(a: &[f64], b: &[f64], s: f64) -> Vec<f64> {
    a.iter().zip(b).map(|(x, y)| x + s * (y - x)).collect()
}
