//! Following (`docs/protocol.md` 6.9): whether the controller does what the bridge sends.
//! Every cycle it checks that the echoed seq advances, that the status is ok once a target
//! was echoed, and that the measured position is within the path tolerance of the target;
//! at the end, that the goal tolerance is reached within the goal time, as ros2_control's
//! JointTrajectoryController does. It judges feedback only; it must not send anything.

use super::StreamSettings;
use crate::protocol::{AxisValues, ControllerStatus, Feedback, MAX_AXES};
use crate::rig::{JointKind, Rig};
use std::time::Duration;

/// How far the arm may be from what was commanded, per axis (rad or m).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Tolerances {
    /// While moving: measured against the target the controller held when it measured
    /// (the one its feedback echoes, or the one before on a link whose devices measure
    /// before taking the next), so it must cover the servo's lag (the twin's 12 ms delay
    /// and 20 Hz servo reach about 6 deg at 250 deg/s), not the pipeline's.
    pub path: AxisValues,
    /// At the end, against the last target.
    pub goal: AxisValues,
    pub goal_time: Duration,
}

/// Defaults: 10 deg (0.05 m) on the path, 0.1 deg (1 mm) at the goal, within 1 s.
pub const DEFAULT_PATH_RAD: f64 = 10.0 * std::f64::consts::PI / 180.0;
pub const DEFAULT_PATH_M: f64 = 0.05;
pub const DEFAULT_GOAL_RAD: f64 = 0.1 * std::f64::consts::PI / 180.0;
pub const DEFAULT_GOAL_M: f64 = 0.001;
pub const DEFAULT_GOAL_TIME: Duration = Duration::from_secs(1);

impl Tolerances {
    /// The defaults for each of `rig`'s axes, by its kind.
    pub fn for_rig(rig: &Rig) -> Self {
        let by_kind = |rad: f64, m: f64| {
            let values: Vec<f64> = rig
                .joints
                .iter()
                .map(|j| match j.kind {
                    JointKind::Revolute => rad,
                    JointKind::Prismatic => m,
                })
                .collect();
            AxisValues::from_slice(&values).unwrap_or(AxisValues::zeros(0))
        };
        Self {
            path: by_kind(DEFAULT_PATH_RAD, DEFAULT_PATH_M),
            goal: by_kind(DEFAULT_GOAL_RAD, DEFAULT_GOAL_M),
            goal_time: DEFAULT_GOAL_TIME,
        }
    }
}

/// Without a rig: the revolute defaults on every axis.
impl Default for Tolerances {
    fn default() -> Self {
        let mut path = AxisValues::zeros(MAX_AXES);
        let mut goal = AxisValues::zeros(MAX_AXES);
        path.as_mut_slice().fill(DEFAULT_PATH_RAD);
        goal.as_mut_slice().fill(DEFAULT_GOAL_RAD);
        Self {
            path,
            goal,
            goal_time: DEFAULT_GOAL_TIME,
        }
    }
}

/// What one cycle's feedback says about following.
#[derive(Debug, Clone, PartialEq)]
pub enum Verdict {
    Following,
    GoalReached,
    NotFollowing(String),
    OffPath(String),
    GoalMissed(String),
}

pub(super) struct Follow {
    tolerances: Tolerances,
    names: Vec<String>,
    revolute: Vec<bool>,
    first_seq: u32,
    last_echo: Option<u32>,
    stale_cycles: u32,
    patience: u32,
    goal_since: Option<Duration>,
}

impl Follow {
    pub(super) fn new(rig: &Rig, settings: &StreamSettings) -> Self {
        Self {
            tolerances: settings.tolerances,
            names: rig.joint_names().map(String::from).collect(),
            revolute: rig
                .joints
                .iter()
                .map(|j| j.kind == JointKind::Revolute)
                .collect(),
            first_seq: settings.first_seq,
            last_echo: None,
            stale_cycles: 0,
            patience: settings.echo_patience_cycles.max(1),
            goal_since: None,
        }
    }

    /// `target`: what the controller held when it measured `feedback` (the streamer's
    /// `held_when_measured`). `finished`: the path's end was reached and the last target is
    /// being held.
    pub(super) fn check(
        &mut self,
        feedback: Option<&Feedback>,
        target: &AxisValues,
        finished: bool,
        now: Duration,
    ) -> Verdict {
        let Some(feedback) = feedback else {
            return Verdict::Following;
        };
        if let Some(verdict) = self.echo(feedback) {
            return verdict;
        }
        if finished {
            return self.goal(feedback, target, now);
        }
        let limit = &self.tolerances.path;
        match self.worst_axis(feedback, target, limit) {
            Some(axis) => Verdict::OffPath(format!(
                "{} (path tolerance)",
                self.describe(axis, feedback, target, limit)
            )),
            None => Verdict::Following,
        }
    }

    /// The echo must advance, and once it has echoed this stream's targets the
    /// controller must not hold.
    fn echo(&mut self, feedback: &Feedback) -> Option<Verdict> {
        if self.last_echo != Some(feedback.seq) {
            self.last_echo = Some(feedback.seq);
            self.stale_cycles = 0;
        } else {
            self.stale_cycles += 1;
        }
        if self.stale_cycles >= self.patience {
            return Some(Verdict::NotFollowing(format!(
                "the controller accepted no target for {} cycles (its echo stays at seq {})",
                self.stale_cycles, feedback.seq
            )));
        }
        let echoed_ours = feedback.seq.wrapping_sub(self.first_seq).wrapping_sub(1) < 1 << 31;
        if echoed_ours && feedback.status == ControllerStatus::Holding {
            return Some(Verdict::NotFollowing(
                "the controller holds instead of following".into(),
            ));
        }
        None
    }

    fn goal(&mut self, feedback: &Feedback, target: &AxisValues, now: Duration) -> Verdict {
        let since = *self.goal_since.get_or_insert(now);
        let limit = &self.tolerances.goal;
        // Words only once they end the stream: the cycles of settling at the goal allocate
        // nothing.
        match self.worst_axis(feedback, target, limit) {
            None => Verdict::GoalReached,
            Some(axis) if now.saturating_sub(since) >= self.tolerances.goal_time => {
                Verdict::GoalMissed(format!(
                    "{} {:.2} s after the end (goal tolerance)",
                    self.describe(axis, feedback, target, limit),
                    self.tolerances.goal_time.as_secs_f64()
                ))
            }
            Some(_) => Verdict::Following,
        }
    }

    /// The axis furthest beyond its tolerance; None when all are within.
    fn worst_axis(
        &self,
        feedback: &Feedback,
        target: &AxisValues,
        limit: &AxisValues,
    ) -> Option<usize> {
        let actual = feedback.positions.as_slice();
        let commanded = target.as_slice();
        let mut worst: Option<(usize, f64)> = None;
        for axis in 0..commanded.len().min(actual.len()) {
            let off = (actual[axis] - commanded[axis]).abs();
            let allowed = limit.as_slice().get(axis).copied().unwrap_or(0.0);
            let excess = off - allowed;
            if excess > 0.0 && worst.is_none_or(|(_, e)| excess > e) {
                worst = Some((axis, excess));
            }
        }
        worst.map(|(axis, _)| axis)
    }

    /// How far `axis` is from its target, beyond its tolerance, in words.
    fn describe(
        &self,
        axis: usize,
        feedback: &Feedback,
        target: &AxisValues,
        limit: &AxisValues,
    ) -> String {
        let actual = feedback.positions.as_slice();
        let commanded = target.as_slice();
        let off = (actual[axis] - commanded[axis]).abs();
        let allowed = limit.as_slice().get(axis).copied().unwrap_or(0.0);
        if self.revolute.get(axis).copied().unwrap_or(true) {
            format!(
                "{} is {:.3} deg from its target, beyond {:.3} deg",
                self.names[axis],
                off.to_degrees(),
                allowed.to_degrees()
            )
        } else {
            format!(
                "{} is {:.4} m from its target, beyond {:.4} m",
                self.names[axis], off, allowed
            )
        }
    }
}
