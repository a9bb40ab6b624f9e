//! Positional solvers on chains of points: FABRIK (Aristidou & Lasenby 2011) with optional
//! per-joint constraints, and point-chain CCD. The arm planner runs its positional FABRIK
//! here; the FABRIK paper's experiment (10 ball joints, no limits) uses both directly.
//!
//! Works on positions only: turning the points back into joint angles is the caller's job.

use glam::DVec3;

/// Restricts the direction of one segment relative to its neighbour, as a joint's limits do.
///
/// Joint `j` sits at point `j` and joins segment `j - 1` (its parent, toward the root) to
/// segment `j` (its child); for joint 0 the parent direction is a fixed reference chosen by
/// the implementor. Directions are unit vectors pointing from root to tip.
pub trait JointConstraint {
    /// The allowed child direction nearest `child`, given the parent direction.
    fn clamp_child(&self, joint: usize, parent: DVec3, child: DVec3) -> DVec3;
    /// The allowed parent direction nearest `parent`, given the child direction (used on
    /// the pass from tip to root). Never called for joint 0.
    fn clamp_parent(&self, joint: usize, parent: DVec3, child: DVec3) -> DVec3;
}

/// No limits: a chain of ball joints.
pub struct Unconstrained;

impl JointConstraint for Unconstrained {
    fn clamp_child(&self, _: usize, _: DVec3, child: DVec3) -> DVec3 {
        child
    }
    fn clamp_parent(&self, _: usize, parent: DVec3, _: DVec3) -> DVec3 {
        parent
    }
}

/// Iterations without progress before FABRIK gives up (constraints can make the error
/// rise for a few iterations before it falls again).
pub const STALL_PATIENCE: u32 = 3;

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ChainOutcome {
    pub iterations: u32,
    /// Distance from the tip to the target when the solver stopped.
    pub error: f64,
    pub converged: bool,
    /// Stopped because the error stopped falling (a constraint holds the chain), as
    /// opposed to running out of iterations while still converging.
    pub stalled: bool,
}

/// Settings shared by the chain solvers.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ChainSettings {
    pub tolerance: f64,
    pub max_iterations: u32,
    /// Stop early when [`STALL_PATIENCE`] iterations in a row fail to improve the best
    /// error by this fraction: the chain is held by a constraint and will not get closer.
    pub min_improvement: f64,
}

impl Default for ChainSettings {
    fn default() -> Self {
        Self {
            tolerance: 1e-3,
            max_iterations: 1000,
            min_improvement: 0.0,
        }
    }
}

fn direction(from: DVec3, to: DVec3, fallback: DVec3) -> DVec3 {
    (to - from).try_normalize().unwrap_or(fallback)
}

/// FABRIK on `points` (root first), segment `i` of length `lengths[i]` joining point `i`
/// to point `i + 1`. The root stays where it is. A target beyond the chain's reach leaves
/// the chain stretched toward it, not converged.
pub fn fabrik(
    points: &mut [DVec3],
    lengths: &[f64],
    target: DVec3,
    settings: ChainSettings,
    constraint: &impl JointConstraint,
    root_reference: DVec3,
) -> ChainOutcome {
    debug_assert_eq!(points.len(), lengths.len() + 1);
    let last = lengths.len();
    let root = points[0];
    let mut error = points[last].distance(target);
    let mut best = error;
    let mut since_best = 0;
    let mut iterations = 0;
    let mut stalled = false;
    while error > settings.tolerance && iterations < settings.max_iterations {
        iterations += 1;
        forward_reaching(points, lengths, target, constraint);
        points[0] = root;
        backward_reaching(points, lengths, constraint, root_reference);
        error = points[last].distance(target);
        if error < best * (1.0 - settings.min_improvement) {
            best = error;
            since_best = 0;
        } else {
            since_best += 1;
            if since_best >= STALL_PATIENCE {
                stalled = true;
                break;
            }
        }
    }
    ChainOutcome {
        iterations,
        error,
        converged: error <= settings.tolerance,
        stalled,
    }
}

/// FABRIK's forward reaching, tip to root: put the tip on the target, then each point on
/// the line toward where it was, at its segment's length from the point after it, its
/// direction clamped by `constraint`. The one forward pass of both FABRIK solvers (this
/// file's point chain and `fabrik_position`'s joint-space one). A point that lands exactly
/// on the one after it keeps the child segment's direction (the tip's: +z), so every
/// segment keeps its length.
pub(crate) fn forward_reaching(
    points: &mut [DVec3],
    lengths: &[f64],
    target: DVec3,
    constraint: &impl JointConstraint,
) {
    let last = lengths.len();
    points[last] = target;
    let mut child = DVec3::ZERO;
    for i in (0..last).rev() {
        let fallback = if child == DVec3::ZERO {
            DVec3::Z
        } else {
            child
        };
        let mut along = direction(points[i], points[i + 1], fallback);
        if i + 1 < last {
            along = constraint.clamp_parent(i + 1, along, child);
        }
        points[i] = points[i + 1] - along * lengths[i];
        child = along;
    }
}

/// Root to tip: each point at its segment's length from the one before it.
fn backward_reaching(
    points: &mut [DVec3],
    lengths: &[f64],
    constraint: &impl JointConstraint,
    root_reference: DVec3,
) {
    let mut parent = root_reference;
    for i in 0..lengths.len() {
        let along = direction(points[i], points[i + 1], parent);
        let along = constraint.clamp_child(i, parent, along);
        points[i + 1] = points[i] + along * lengths[i];
        parent = along;
    }
}

/// Cyclic coordinate descent on a chain of ball joints: from the last joint to the first,
/// turn the rest of the chain about the joint so that the tip points at the target.
pub fn ccd(points: &mut [DVec3], target: DVec3, settings: ChainSettings) -> ChainOutcome {
    let last = points.len() - 1;
    let mut error = points[last].distance(target);
    let mut iterations = 0;
    while error > settings.tolerance && iterations < settings.max_iterations {
        iterations += 1;
        for joint in (0..last).rev() {
            let pivot = points[joint];
            let to_tip = points[last] - pivot;
            let to_target = target - pivot;
            let Some(rotation) = shortest_arc(to_tip, to_target) else {
                continue;
            };
            for point in &mut points[joint + 1..] {
                *point = pivot + rotation * (*point - pivot);
            }
        }
        error = points[last].distance(target);
    }
    ChainOutcome {
        iterations,
        error,
        converged: error <= settings.tolerance,
        stalled: false,
    }
}

fn shortest_arc(from: DVec3, to: DVec3) -> Option<glam::DQuat> {
    let from = from.try_normalize()?;
    let to = to.try_normalize()?;
    Some(glam::DQuat::from_rotation_arc(from, to))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn straight_chain(n: usize) -> (Vec<DVec3>, Vec<f64>) {
        let points = (0..=n).map(|i| DVec3::new(0.0, 0.0, i as f64)).collect();
        (points, vec![1.0; n])
    }

    fn segment_lengths(points: &[DVec3]) -> Vec<f64> {
        points.windows(2).map(|w| w[0].distance(w[1])).collect()
    }

    #[test]
    fn fabrik_reaches_a_reachable_target_and_keeps_lengths() {
        let (mut points, lengths) = straight_chain(4);
        let target = DVec3::new(2.0, 1.0, 1.5);
        let settings = ChainSettings {
            tolerance: 1e-9,
            ..Default::default()
        };
        let outcome = fabrik(
            &mut points,
            &lengths,
            target,
            settings,
            &Unconstrained,
            DVec3::Z,
        );
        assert!(outcome.converged, "{outcome:?}");
        assert!(points[4].distance(target) <= 1e-9);
        assert_eq!(points[0], DVec3::ZERO);
        for l in segment_lengths(&points) {
            assert!((l - 1.0).abs() < 1e-12);
        }
    }

    #[test]
    fn fabrik_stretches_toward_an_unreachable_target() {
        let (mut points, lengths) = straight_chain(3);
        let target = DVec3::new(10.0, 0.0, 0.0);
        let outcome = fabrik(
            &mut points,
            &lengths,
            target,
            ChainSettings::default(),
            &Unconstrained,
            DVec3::Z,
        );
        assert!(!outcome.converged);
        assert!((outcome.error - 7.0).abs() < 1e-6, "{outcome:?}");
    }

    #[test]
    fn ccd_reaches_a_reachable_target_and_keeps_lengths() {
        let (mut points, _) = straight_chain(4);
        let target = DVec3::new(1.0, -2.0, 1.0);
        let outcome = ccd(&mut points, target, ChainSettings::default());
        assert!(outcome.converged, "{outcome:?}");
        for l in segment_lengths(&points) {
            assert!((l - 1.0).abs() < 1e-9);
        }
    }
}
