//! What a FollowJointTrajectory goal over DDS becomes in a cell (docs/ros2.md): a
//! `follow_trajectory` job validated and started exactly like a job from `POST /api/jobs`
//! (the limits, the cell's collision check), stopped the way `POST .../stop` stops one
//! (braking to rest along its path), and followed through the cell's job history and its
//! live slot. Owns only that bridge; the action's protocol and checks are `crate::ros2::fjt`.

use super::cell::Cell;
use super::{Daemon, start_refusal};
use crate::ros2::fjt::{CheckedGoal, GoalRefused, GoalRunner, JobState, Progress};
use crate::stream::StreamControl;
use std::sync::Arc;

/// A cell's goals: the job of the goal being carried out, if one is.
pub struct CellGoals {
    daemon: Arc<Daemon>,
    cell: Arc<Cell>,
    job: Option<u64>,
}

impl CellGoals {
    pub fn new(daemon: Arc<Daemon>, cell: Arc<Cell>) -> CellGoals {
        CellGoals {
            daemon,
            cell,
            job: None,
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
                Ok(())
            }
            Ok(Err(message)) => {
                cell.reap(id);
                Err(GoalRefused::Refused(message.to_string()))
            }
            Err(_) => Err(GoalRefused::JobThreadEnded),
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

impl CellGoals {
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
