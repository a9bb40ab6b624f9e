//! What a FollowJointTrajectory goal over DDS becomes in a cell (docs/ros2.md): a
//! `follow_trajectory` job validated and started exactly like a job from `POST /api/jobs`
//! (the limits, the cell's collision check), stopped the way `POST .../stop` stops one
//! (braking to rest along its path), and followed through the cell's job history and its
//! live slot. Owns only that bridge; the action's protocol and checks are `crate::ros2::fjt`.

use super::cell::Cell;
use super::{Daemon, start_refusal};
use crate::ros2::fjt::{CheckedGoal, GoalRefused, GoalRunner, JobState, Preemption, Progress};
use crate::stream::{Splice, SpliceAnswer, StreamControl};
use crate::trajectory::Trajectory;
use std::sync::Arc;
use std::time::Duration;

/// How long a preempting goal waits for the running job's cycle to take or refuse its
/// trajectory: a cycle that streams answers within one period (4 ms at 250 Hz); one that
/// does not answer in this is not streaming (waiting for the controller, planning).
const SPLICE_ANSWER_WAIT: Duration = Duration::from_millis(250);
/// How often the answer is looked for meanwhile.
const SPLICE_POLL: Duration = Duration::from_millis(1);

/// A cell's goals: the job of the goal being carried out, if one is, and the trajectories
/// spliced into it (kept until the next job, so the cycle never frees one).
pub struct CellGoals {
    daemon: Arc<Daemon>,
    cell: Arc<Cell>,
    job: Option<u64>,
    spliced: Vec<Arc<Trajectory>>,
}

impl CellGoals {
    pub fn new(daemon: Arc<Daemon>, cell: Arc<Cell>) -> CellGoals {
        CellGoals {
            daemon,
            cell,
            job: None,
            spliced: Vec::new(),
        }
    }
}

impl GoalRunner for CellGoals {
    fn start(&mut self, goal: &CheckedGoal) -> Result<(), GoalRefused> {
        let cell = &self.cell;
        let held = cell.current_position();
        let job =
            crate::server::ros2::goal_job(&goal.trajectory, &cell.settings().rig, held.as_deref())
                .map_err(|e| GoalRefused::Refused(e.to_string()))?;
        let job = cell
            .validate(job)
            .map_err(|e| GoalRefused::Refused(e.to_string()))?;
        let id = self.daemon.next_job_id();
        let started = cell
            .start(id, job, &self.daemon.options)
            .map_err(|refused| GoalRefused::Refused(start_refusal(cell, refused)))?;
        match started.planned.blocking_recv() {
            Ok(Ok(())) => {
                cell.log_ros2("ros2_goal_started", Some(id), "streaming".into());
                self.job = Some(id);
                self.spliced.clear();
                Ok(())
            }
            Ok(Err(message)) => {
                cell.reap(id);
                Err(GoalRefused::Refused(message.to_string()))
            }
            Err(_) => Err(GoalRefused::JobThreadEnded),
        }
    }

    fn preempt(&mut self, goal: &CheckedGoal) -> Preemption {
        let Some(id) = self.job.filter(|id| self.cell.planned_job() == Some(*id)) else {
            return Preemption::Unavailable;
        };
        let Some(control) = self.cell.job_control(id) else {
            return Preemption::Unavailable;
        };
        let splice = match self.plan_splice(goal) {
            Ok(splice) => splice,
            Err(refused) => return Preemption::Refused(refused),
        };
        let trajectory = splice.trajectory.clone();
        control.online().splice(splice);
        match wait_for_answer(&control) {
            Ok(()) => {
                self.spliced.push(trajectory);
                self.cell
                    .control("ros2_goal_preempted", |_: &StreamControl| ());
                Preemption::Continued
            }
            Err(refused) => Preemption::Refused(refused),
        }
    }

    fn stop(&mut self) {
        // Only the goal's own job: never one an operator started since.
        if self.job.is_some() && self.cell.planned_job() == self.job {
            self.cell
                .halt("ros2_goal_stop", StreamControl::request_stop);
        }
    }

    fn progress(&mut self) -> Progress {
        let latest = self.cell.hub().slot().latest();
        Progress {
            state: self.state(),
            desired: latest.commanded.as_slice().to_vec(),
            actual: latest.actual.as_slice().to_vec(),
        }
    }
}

/// The cycle's answer to a splice: taken, refused, or withdrawn unseen after
/// [`SPLICE_ANSWER_WAIT`] (a cycle that took it meanwhile is waited for).
fn wait_for_answer(control: &StreamControl) -> Result<(), GoalRefused> {
    let polls = SPLICE_ANSWER_WAIT.as_millis() / SPLICE_POLL.as_millis();
    let mut withdrawn = false;
    loop {
        for _ in 0..polls {
            match control.online().splice_answer() {
                SpliceAnswer::Taken => return Ok(()),
                SpliceAnswer::Refused(why) => return Err(GoalRefused::NotJoined(why)),
                SpliceAnswer::Waiting => std::thread::sleep(SPLICE_POLL),
            }
        }
        if withdrawn || control.online().withdraw_splice() {
            return Err(GoalRefused::NoAnswer(SPLICE_ANSWER_WAIT.as_millis() as u64));
        }
        withdrawn = true;
    }
}

impl CellGoals {
    /// `goal` as a job from where the arm is commanded now, validated and planned like
    /// every job, and the sample its first point is on: where the arm joins it.
    fn plan_splice(&self, goal: &CheckedGoal) -> Result<Splice, GoalRefused> {
        let first = goal
            .trajectory
            .points
            .first()
            .map_or(0.0, |p| seconds(&p.time_from_start));
        if first <= 0.0 {
            return Err(GoalRefused::FirstPointNow);
        }
        let cell = &self.cell;
        let settings = cell.settings();
        let held = cell.current_position();
        let job = crate::server::ros2::goal_job(&goal.trajectory, &settings.rig, held.as_deref())
            .map_err(|e| GoalRefused::Refused(e.to_string()))?;
        let job = cell
            .validate(job)
            .map_err(|e| GoalRefused::Refused(e.to_string()))?;
        let start = held.ok_or_else(|| {
            GoalRefused::Refused("where the arm is commanded is not known".into())
        })?;
        let trajectory = crate::daemon::plan_from(settings, &job, &start)
            .map_err(|e| GoalRefused::Refused(crate::daemon::error_chain(&e)))?;
        // The rows' curve ends the plan; its first row (the held position) is at
        // `offset`, and the goal's first point `first` seconds after it.
        let period_s = trajectory.period.as_secs_f64();
        let curve = (goal.duration_s / period_s).ceil() as usize;
        let offset = (trajectory.len() - 1).saturating_sub(curve);
        let join = (offset + (first / period_s).round() as usize).min(trajectory.len() - 1);
        Ok(Splice {
            trajectory: Arc::new(trajectory),
            join,
        })
    }

    /// The goal's job as the cell's history has it.
    fn state(&self) -> JobState {
        let Some(id) = self.job else {
            return JobState::Ended("no job was started".into());
        };
        let entry = match self.cell.job_entry(id) {
            Some(Ok(entry)) => entry,
            Some(Err(e)) => return JobState::Ended(format!("its record cannot be read: {e}")),
            None => return JobState::Ended(format!("job {id} is no longer in the history")),
        };
        if entry.running {
            return JobState::Running;
        }
        let json = &entry.json;
        let outcome = json["report"]["outcome"].as_str();
        match (json["result"].as_str(), outcome) {
            (Some("finished"), Some("completed")) => JobState::Completed,
            (Some("finished"), Some(outcome)) => {
                let fault = json["report"]["fault"].as_str().unwrap_or("");
                JobState::Ended(
                    format!("job {id}: {outcome} {fault}")
                        .trim_end()
                        .to_string(),
                )
            }
            _ => JobState::Ended(format!(
                "job {id} failed: {}",
                json["error"].as_str().unwrap_or("no reason recorded")
            )),
        }
    }
}

fn seconds(duration: &crate::ros2::messages::Duration) -> f64 {
    f64::from(duration.sec) + f64::from(duration.nanosec) * 1e-9
}
