//! The painter as an app ([`App`]): the painting room and its paint as a job's live scene
//! and twin world, and the room's walls in the cell its plan is checked in. Owns only what
//! the core asks of the painter; the room, the plan and the measuring are this folder's
//! other files.

use super::{PaintScene, load_paint_settings, room_for, world_for};
use crate::apps::{App, JobScene};
use crate::cell::Cell;
use crate::job::{AppRig, Job, JobError};
use crate::rig::Rig;
use std::sync::{Arc, Mutex};

/// `kind = "paint"`.
pub struct PaintApp;

impl App for PaintApp {
    fn kind(&self) -> &'static str {
        "paint"
    }

    /// The generated room with the painter in it, and its paint world (what the twin paints).
    fn scene(&self, job: &Job, rig: &Rig, _app_rig: Option<&Arc<AppRig>>) -> Option<JobScene> {
        let Job::Paint(job) = job else { return None };
        let paint = load_paint_settings(&job.paint_config).ok()?;
        let room = room_for(&paint, job.walls, job.seed).ok()?;
        let world = Arc::new(Mutex::new(world_for(&paint, &room).ok()?));
        let scene = PaintScene::new(rig.clone(), world.clone());
        Some((Box::new(scene), Some(Box::new(world))))
    }

    /// The run's own cell objects and pairs, plus the walls, floor and brush of the room the job
    /// generates (a cell file cannot know a generated room's walls), at the run cell's
    /// margin. That margin must lie below the planner's clearance, which the planner keeps
    /// at its samples only.
    fn gate_cell(&self, job: &Job, rig: &Rig, cell: &Cell) -> Result<Option<Cell>, JobError> {
        let Job::Paint(job) = job else {
            return Ok(None);
        };
        let paint = load_paint_settings(&job.paint_config)?;
        let (margin_m, clearance_m) = (cell.margin_m, paint.config.body.planning_clearance_m);
        if margin_m >= clearance_m {
            let refused = super::PaintPlanError::MarginNotBelowClearance {
                margin_m,
                clearance_m,
            };
            return Err(JobError::Paint(refused.into()));
        }
        let room = room_for(&paint, job.walls, job.seed).map_err(|e| JobError::Paint(e.into()))?;
        let room = super::body::room_cell(rig, &room, &paint.config);
        Ok(Some(super::body::merge_room(cell, &room)))
    }
}
