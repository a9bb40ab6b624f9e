//! The running job's plan as the page draws it: the tool's path (forward kinematics of the
//! rig's TCP over the planned trajectory, subsampled to a bounded size) and the targets (the
//! tool where each stretch of the plan ends, named as its job wrote it). Derived from the
//! trajectory and its origins alone, so every kind of job (posted, configured, a ROS 2
//! JointTrajectory, a program) shows the same way. Reads the plan; must not plan, stream or
//! touch the cycle.

use crate::motion::Trajectory;
use crate::rig::Rig;
use crate::scene::Point;
use crate::trajectory::Origins;
use serde::Serialize;

/// Most points of the drawn tool path: a ten-minute job at 250 Hz has 150 000 samples; 2 000
/// points are about 60 KB of JSON in the scene message and one canvas path per frame, and
/// still 0.3 s apart on that job, closer than the eye follows a moving tool.
pub const MAX_PATH_POINTS: usize = 2_000;
/// Most targets drawn: a program or a long trajectory file can name thousands of rows;
/// past this the marks would cover the path they are on. Evenly spread, the last kept.
pub const MAX_TARGETS_DRAWN: usize = 500;

/// The plan of the running job, in the scene's world frame (m).
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct PlanView {
    /// The tool's (TCP's) positions along the plan, first sample to last, in order.
    pub tool_path: Vec<Point>,
    /// Where each stretch of the plan ends, and what the job called it.
    pub targets: Vec<TargetView>,
    /// The samples the plan holds (the path is a subsample of them).
    pub samples: usize,
}

/// One target of the plan: the tool's position there and the job's words for it
/// (`the joint move to job.poses[1]`, a row of a trajectory file).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TargetView {
    pub at: Point,
    pub what: String,
}

impl PlanView {
    /// The plan of `trajectory` on `rig` (the rig at its TCP, the frame jobs are written
    /// in); `origins` mark its stretches. Empty when the trajectory does not fit the rig.
    pub fn of(rig: &Rig, trajectory: &Trajectory, origins: &Origins) -> PlanView {
        let samples = trajectory.len();
        if samples == 0 || trajectory.dof() != rig.dof() {
            return PlanView::default();
        }
        let last = samples - 1;
        let ends = target_samples(origins, last);
        let tool_at = |sample: usize| {
            rig.forward(&trajectory.position(sample))
                .map(|pose| pose.translation.to_array())
                .ok()
        };
        let tool_path = path_samples(last, &ends)
            .into_iter()
            .filter_map(tool_at)
            .collect();
        let targets = ends
            .into_iter()
            .filter_map(|sample| {
                tool_at(sample).map(|at| TargetView {
                    at,
                    what: origins.at(sample).to_string(),
                })
            })
            .collect();
        PlanView {
            tool_path,
            targets,
            samples,
        }
    }
}

/// The last sample of each stretch (within `0..=last`), at most [`MAX_TARGETS_DRAWN`] of
/// them evenly spread with the final one kept, in order and without repeats.
fn target_samples(origins: &Origins, last: usize) -> Vec<usize> {
    let mut ends: Vec<usize> = origins.ends().map(|end| end.min(last)).collect();
    ends.dedup();
    if ends.len() > MAX_TARGETS_DRAWN {
        let stride = ends.len().div_ceil(MAX_TARGETS_DRAWN);
        let kept_last = ends.last().copied();
        ends = ends.into_iter().step_by(stride).collect();
        if ends.last().copied() != kept_last {
            ends.extend(kept_last);
        }
    }
    ends
}

/// Every k-th sample of `0..=last` (at most [`MAX_PATH_POINTS`]), the last one, and the
/// targets' samples (so the path turns where the tool does), sorted without repeats.
fn path_samples(last: usize, targets: &[usize]) -> Vec<usize> {
    let stride = (last + 1).div_ceil(MAX_PATH_POINTS).max(1);
    let mut samples: Vec<usize> = (0..=last).step_by(stride).collect();
    samples.push(last);
    samples.extend_from_slice(targets);
    samples.sort_unstable();
    samples.dedup();
    samples
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rig::{Joint, JointKind, JointLimits};
    use glam::{DAffine3, DVec3};
    use std::time::Duration;

    /// One slide along x carrying the tool 0.1 m above it: the tool's path is the slide's
    /// position, read off by hand.
    fn slide() -> Rig {
        Rig {
            name: "slide".into(),
            base_frame: "base".into(),
            tool_frame: "tool".into(),
            joints: vec![Joint {
                name: "x".into(),
                kind: JointKind::Prismatic,
                origin: DAffine3::IDENTITY,
                axis: DVec3::X,
                limits: JointLimits {
                    lower: -10.0,
                    upper: 10.0,
                    max_speed: 1.0,
                    max_acceleration: 10.0,
                },
            }],
            tool: DAffine3::from_translation(DVec3::new(0.0, 0.0, 0.1)),
            bodies: Vec::new(),
            allowed_pairs: Vec::new(),
        }
    }

    fn ramp(samples: usize) -> Trajectory {
        let positions: Vec<f64> = (0..samples).map(|k| k as f64 * 0.001).collect();
        Trajectory::new(
            "slide".into(),
            vec!["x".into()],
            Duration::from_millis(4),
            positions,
            vec![0.25; samples],
        )
        .expect("a one-axis ramp")
    }

    #[test]
    fn a_short_plan_is_drawn_whole_with_its_targets_where_their_stretches_end() {
        let mut origins = Origins::default();
        origins.push(4, "job.targets_deg[0]");
        origins.push(9, "job.targets_deg[1]");
        let plan = PlanView::of(&slide(), &ramp(10), &origins);
        assert_eq!(plan.samples, 10);
        assert_eq!(plan.tool_path.len(), 10);
        for (k, point) in plan.tool_path.iter().enumerate() {
            let want = [k as f64 * 0.001, 0.0, 0.1];
            assert!(
                point.iter().zip(want).all(|(a, b)| (a - b).abs() < 1e-12),
                "sample {k}: {point:?}"
            );
        }
        assert_eq!(plan.targets.len(), 2);
        assert!((plan.targets[0].at[0] - 0.004).abs() < 1e-12);
        assert_eq!(plan.targets[0].what, "job.targets_deg[0]");
        assert!((plan.targets[1].at[0] - 0.009).abs() < 1e-12);
        assert_eq!(plan.targets[1].what, "job.targets_deg[1]");
    }

    #[test]
    fn a_long_plan_is_subsampled_within_its_bound_keeping_ends_and_targets() {
        let samples = 150_001;
        let mut origins = Origins::default();
        // A corner off the stride (a prime sample) and a whole-job stretch past the end.
        origins.push(100_003, "the corner");
        origins.push(usize::MAX, "the rest");
        let plan = PlanView::of(&slide(), &ramp(samples), &origins);
        assert!(
            plan.tool_path.len() <= MAX_PATH_POINTS + 2,
            "{} points",
            plan.tool_path.len()
        );
        assert!(plan.tool_path.len() >= MAX_PATH_POINTS / 2);
        let xs: Vec<f64> = plan.tool_path.iter().map(|p| p[0]).collect();
        assert_eq!(xs[0], 0.0);
        assert!((xs[xs.len() - 1] - 150.0).abs() < 1e-9, "the last sample");
        assert!(
            xs.iter().any(|x| (x - 100.003).abs() < 1e-9),
            "the corner's sample is on the path"
        );
        assert!(xs.windows(2).all(|w| w[0] < w[1]), "in order");
        assert_eq!(plan.targets.len(), 2);
        assert!((plan.targets[1].at[0] - 150.0).abs() < 1e-9);
    }

    #[test]
    fn thousands_of_targets_are_thinned_to_the_bound_keeping_the_last() {
        let mut origins = Origins::default();
        for k in 0..5_000 {
            origins.push(k * 2 + 1, format!("row {k}"));
        }
        let plan = PlanView::of(&slide(), &ramp(10_000), &origins);
        assert!(
            plan.targets.len() <= MAX_TARGETS_DRAWN + 1,
            "{}",
            plan.targets.len()
        );
        assert!(plan.targets.len() >= MAX_TARGETS_DRAWN / 2);
        assert_eq!(
            plan.targets.last().map(|t| t.what.as_str()),
            Some("row 4999")
        );
    }

    #[test]
    fn a_plan_for_another_rig_draws_nothing() {
        let two_axes = Trajectory::new(
            "other".into(),
            vec!["a".into(), "b".into()],
            Duration::from_millis(4),
            vec![0.0; 4],
            vec![0.0; 4],
        )
        .expect("a two-axis trajectory");
        assert_eq!(
            PlanView::of(&slide(), &two_axes, &Origins::default()),
            PlanView::default()
        );
    }
}
