//! The daemon's side of ROS 2 (docs/ros2.md): which settings a rig joins with (its
//! `[ros2]`, or `--zenoh-connect`), and what a JointTrajectory received by `serve` becomes:
//! a `follow_trajectory` job with the points as inline rows, validated and started exactly
//! like a job from a file or `POST /api/jobs` but with no approach move (its first point
//! must be where the arm holds), or refused with its reason counted and logged, at most
//! once a second.
//!
//! A FollowJointTrajectory goal becomes the same job ([`goal_job`]), starting from where the
//! rig holds when its first point is later than 0, as ros2_controllers' controller does.
//!
//! Owns the translation from the message to a job; the middleware side is `crate::ros2`.

use crate::clock::Clock;
use crate::job::{FollowTrajectory, Job, JobInvalid};
use crate::rig::Rig;
use crate::ros2::messages::JointTrajectory;
use std::time::Duration;

/// Nanoseconds a second, to read a `Duration`'s two fields.
const NANOS_PER_SECOND: f64 = 1e9;
/// At most one refusal is logged in this time: a peer that floods the topic with bad
/// messages must not flood stderr, the status and the journal too. Every refusal is
/// counted, and the next one logged says how many were not.
pub const REFUSAL_LOG_INTERVAL: Duration = Duration::from_secs(1);

/// The refusals of a cell's ROS 2 trajectories: all counted, logged at most once every
/// [`REFUSAL_LOG_INTERVAL`] (the first at once).
pub struct Refusals {
    clock: Box<dyn Clock>,
    total: u64,
    unlogged: u64,
    last_logged: Option<Duration>,
}

impl Refusals {
    pub fn new(clock: Box<dyn Clock>) -> Refusals {
        Refusals {
            clock,
            total: 0,
            unlogged: 0,
            last_logged: None,
        }
    }

    /// Counts a refusal for `reason`; returns what to log when one may be logged now: the
    /// reason, the count so far and how many went unlogged since the last one logged.
    pub fn refuse(&mut self, reason: &str) -> Option<String> {
        self.total += 1;
        let now = self.clock.now();
        if self
            .last_logged
            .is_some_and(|last| now.saturating_sub(last) < REFUSAL_LOG_INTERVAL)
        {
            self.unlogged += 1;
            return None;
        }
        self.last_logged = Some(now);
        let unlogged = std::mem::take(&mut self.unlogged);
        Some(format!(
            "{reason} (refusal {} from ROS 2; {unlogged} more since the last one logged, \
             not logged)",
            self.total
        ))
    }

    /// Trajectories refused so far.
    pub fn total(&self) -> u64 {
        self.total
    }
}

/// The job a JointTrajectory asks for on `rig`: its points as `follow_trajectory` rows in
/// the rig's joint order and config units (degrees, metres), times taken from the first
/// point, with no approach: the first point must be where the rig holds, or the job is
/// refused when it is planned (nothing moves to a far first point on a message from the
/// network). Only names and positions are read: the
/// points' velocities and accelerations are not, since the job joins the points with its
/// own checked curve. What is not valid for the rig is left to the job's validation.
pub fn trajectory_job(message: &JointTrajectory, rig: &Rig) -> Result<Job, JobInvalid> {
    let order = joint_order(&message.joint_names, rig)?;
    let first_t = message
        .points
        .first()
        .map_or(0.0, |p| seconds(&p.time_from_start));
    let mut rows = Vec::with_capacity(message.points.len());
    for (index, point) in message.points.iter().enumerate() {
        if point.positions.len() != rig.dof() {
            return Err(JobInvalid::new(
                format!("points[{index}].positions"),
                point.positions.len(),
                format!("needs one position per joint name ({})", rig.dof()),
            ));
        }
        let mut row = Vec::with_capacity(rig.dof() + 1);
        row.push(seconds(&point.time_from_start) - first_t);
        for (axis, joint) in rig.joints.iter().enumerate() {
            row.push(joint.kind.to_user(point.positions[order[axis]]));
        }
        rows.push(row);
    }
    Ok(Job::FollowTrajectory(FollowTrajectory {
        file: None,
        rows: Some(rows),
        approach: false,
    }))
}

/// The job a FollowJointTrajectory goal asks for: as [`trajectory_job`], but when the first
/// point is after the start and the rig's position `held` (SI, the rig's order) is known,
/// the trajectory starts from it at time 0, as JointTrajectoryController starts from the
/// state it holds; the points keep their times. With a first point at time 0 (or the
/// position unknown) that point must be where the rig holds.
pub fn goal_job(
    trajectory: &JointTrajectory,
    rig: &Rig,
    held: Option<&[f64]>,
) -> Result<Job, JobInvalid> {
    let order = joint_order(&trajectory.joint_names, rig)?;
    let first_t = trajectory
        .points
        .first()
        .map_or(0.0, |p| seconds(&p.time_from_start));
    let Some(held) = held.filter(|held| first_t > 0.0 && held.len() == rig.dof()) else {
        return trajectory_job(trajectory, rig);
    };
    let mut positions = vec![0.0; rig.dof()];
    for (axis, &index) in order.iter().enumerate() {
        positions[index] = held[axis];
    }
    let mut from_held = trajectory.clone();
    from_held.points.insert(
        0,
        crate::ros2::messages::JointTrajectoryPoint {
            positions,
            ..Default::default()
        },
    );
    trajectory_job(&from_held, rig)
}

fn seconds(duration: &crate::ros2::messages::Duration) -> f64 {
    f64::from(duration.sec) + f64::from(duration.nanosec) / NANOS_PER_SECOND
}

/// For each of the rig's joints, where the message has it: every joint named exactly once,
/// nothing else.
fn joint_order(names: &[String], rig: &Rig) -> Result<Vec<usize>, JobInvalid> {
    let expected: Vec<&str> = rig.joint_names().collect();
    let refuse = || {
        JobInvalid::new(
            "joint_names",
            names,
            format!(
                "must name each of the rig's joints once: {}",
                expected.join(", ")
            ),
        )
    };
    if names.len() != expected.len() {
        return Err(refuse());
    }
    expected
        .iter()
        .map(|joint| {
            let mut found = names.iter().enumerate().filter(|(_, n)| n == joint);
            match (found.next(), found.next()) {
                (Some((index, _)), None) => Ok(index),
                _ => Err(refuse()),
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ros2::messages::{Duration, JointTrajectoryPoint};

    fn rig() -> Rig {
        crate::rig::load_rig(std::path::Path::new(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/config/irb120.toml"
        )))
        .expect("the IRB 120 rig loads")
    }

    fn point(positions: Vec<f64>, sec: i32, nanosec: u32) -> JointTrajectoryPoint {
        JointTrajectoryPoint {
            positions,
            time_from_start: Duration { sec, nanosec },
            ..Default::default()
        }
    }

    #[test]
    fn points_become_rows_in_the_rigs_order_and_units_from_the_first_points_time() {
        let rig = rig();
        let mut names: Vec<String> = rig.joint_names().map(String::from).collect();
        names.reverse();
        let message = JointTrajectory {
            joint_names: names,
            points: vec![
                point(vec![0.6, 0.5, 0.4, 0.3, 0.2, 0.1], 1, 500_000_000),
                point(vec![0.0; 6], 3, 0),
            ],
            ..Default::default()
        };
        let Job::FollowTrajectory(job) =
            trajectory_job(&message, &rig).expect("the trajectory becomes a job")
        else {
            panic!("a follow_trajectory job");
        };
        assert!(
            !job.approach,
            "a message from the network gets no approach move"
        );
        let rows = job.rows.expect("the job carries inline rows");
        assert_eq!(rows[0][0], 0.0);
        assert_eq!(rows[1][0], 1.5);
        assert!((rows[0][1] - 0.1_f64.to_degrees()).abs() < 1e-12);
        assert!((rows[0][6] - 0.6_f64.to_degrees()).abs() < 1e-12);
    }

    #[test]
    fn a_goal_whose_first_point_is_later_starts_from_where_the_rig_holds() {
        let rig = rig();
        let mut names: Vec<String> = rig.joint_names().map(String::from).collect();
        names.swap(0, 5);
        let message = JointTrajectory {
            joint_names: names,
            points: vec![point(vec![0.6, 0.0, 0.0, 0.0, 0.0, 0.1], 2, 0)],
            ..Default::default()
        };
        let held = [0.01, 0.02, 0.03, 0.04, 0.05, 0.06];
        let Job::FollowTrajectory(job) =
            goal_job(&message, &rig, Some(&held)).expect("the goal becomes a job")
        else {
            panic!("a follow_trajectory job");
        };
        let rows = job.rows.expect("inline rows");
        assert_eq!(rows.len(), 2, "the held position, then the point");
        assert_eq!(
            (rows[0][0], rows[1][0]),
            (0.0, 2.0),
            "the point keeps its time"
        );
        for (axis, value) in held.iter().enumerate() {
            assert!((rows[0][axis + 1] - value.to_degrees()).abs() < 1e-12);
        }
        // Joint 1 is the message's last name: 0.1 rad; joint 6 its first: 0.6 rad.
        assert!((rows[1][1] - 0.1_f64.to_degrees()).abs() < 1e-12);
        assert!((rows[1][6] - 0.6_f64.to_degrees()).abs() < 1e-12);
        let Job::FollowTrajectory(at_zero) = goal_job(
            &JointTrajectory {
                points: vec![point(vec![0.0; 6], 0, 0)],
                ..message.clone()
            },
            &rig,
            Some(&held),
        )
        .expect("the goal becomes a job") else {
            panic!("a follow_trajectory job");
        };
        assert_eq!(
            at_zero.rows.map(|r| r.len()),
            Some(1),
            "nothing prepended at t = 0"
        );
    }

    #[test]
    fn refusals_are_all_counted_and_logged_at_most_once_an_interval() {
        let clock = std::sync::Arc::new(crate::clock::VirtualClock::new());
        struct Shared(std::sync::Arc<crate::clock::VirtualClock>);
        impl Clock for Shared {
            fn now(&self) -> std::time::Duration {
                self.0.now()
            }
            fn sleep_until(&self, deadline: std::time::Duration) {
                self.0.sleep_until(deadline);
            }
            fn is_virtual(&self) -> bool {
                true
            }
        }
        let mut refusals = Refusals::new(Box::new(Shared(clock.clone())));
        let first = refusals.refuse("bad").expect("the first refusal is logged");
        assert!(
            first.starts_with("bad (refusal 1 from ROS 2; 0 more"),
            "{first}"
        );
        let logged = (0..999)
            .filter(|_| {
                clock.advance(std::time::Duration::from_micros(500));
                refusals.refuse("bad").is_some()
            })
            .count();
        assert_eq!(logged, 0, "999 refusals within 0.5 s after the first");
        clock.advance(REFUSAL_LOG_INTERVAL);
        let next = refusals.refuse("worse").expect("one a second is logged");
        assert!(
            next.starts_with("worse (refusal 1001 from ROS 2; 999 more"),
            "{next}"
        );
        assert_eq!(refusals.total(), 1001);
    }

    #[test]
    fn names_that_are_not_the_rigs_joints_once_each_are_refused() {
        let rig = rig();
        let mut names: Vec<String> = rig.joint_names().map(String::from).collect();
        names[5] = names[0].clone();
        let message = JointTrajectory {
            joint_names: names,
            points: vec![point(vec![0.0; 6], 0, 0)],
            ..Default::default()
        };
        let refused = trajectory_job(&message, &rig).unwrap_err();
        assert_eq!(refused.key, "joint_names");
        let short = JointTrajectory {
            joint_names: rig.joint_names().map(String::from).collect(),
            points: vec![point(vec![0.0; 5], 0, 0)],
            ..Default::default()
        };
        assert_eq!(
            trajectory_job(&short, &rig).unwrap_err().key,
            "points[0].positions"
        );
    }
}
