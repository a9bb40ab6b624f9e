//! The painting job end to end: generate the room, plan it, put the in-process twin in a
//! [`PaintWorld`] and its room's cell (the twin's collision watch), stream through the normal pipeline (validate, stream, record), then build
//! the paint report from what the twin's world measured. Owns the wiring only.

use super::config::{JobConfig, RunSettings};
use super::{DaemonError, PlannedJob, RunReport, held_position, twin_settings};
use crate::clock::Clock;
use crate::job::JobError;
use crate::link::LoopbackLink;
use crate::stream::StreamControl;
use crate::task::paint::{
    PaintPlanError, PaintReport, PaintSettings, PaintWorld, build_report, plan_room, world_for,
};
use crate::twin::Twin;
use std::sync::{Arc, Mutex, PoisonError};

/// Everything a paint run produced.
pub struct PaintRun {
    pub run: RunReport,
    pub paint: PaintReport,
    pub world: Arc<Mutex<PaintWorld>>,
}

/// Plans and paints the room of `walls` walls for `seed` against the in-process twin.
/// `planned` is told the plan's size before motion starts (for progress and messages).
#[allow(clippy::too_many_arguments)]
pub fn run_paint(
    settings: &RunSettings,
    paint: &PaintSettings,
    walls: u32,
    seed: u64,
    clock: &dyn Clock,
    log: Option<&std::path::Path>,
    control: &StreamControl,
    planned: &mut dyn FnMut(&crate::task::paint::PaintPlan),
) -> Result<PaintRun, DaemonError> {
    let room =
        crate::task::paint::room_for(paint, walls, seed).map_err(|e| JobError::Paint(e.into()))?;
    let world = Arc::new(Mutex::new(
        world_for(paint, &room).map_err(|e| JobError::Paint(PaintPlanError::Cell(e).into()))?,
    ));
    // The twin measures the painter against the room it paints: the room's cell.
    let cell = crate::task::paint::body::room_cell(&settings.rig, &room, &paint.config);
    let model = crate::cell::CollisionModel::new(&settings.rig, &cell)?;
    let watch = crate::twin::ContactWatch::new(
        Arc::new(model),
        &settings.rig,
        &cell,
        settings.period().as_secs_f64(),
    );
    let twin = Twin::new(&settings.rig, twin_settings(settings), &settings.initial())?
        .with_contacts(watch)
        .with_world(Box::new(world.clone()));
    let mut link = LoopbackLink::new(twin);
    let start = held_position(settings, &mut link, clock, control)?;
    let (_, plan) = plan_room(paint, walls, seed, &start, &super::plan_settings(settings))
        .map_err(JobError::Paint)?;
    planned(&plan);
    let job = PlannedJob {
        job: JobConfig::Paint(crate::job::Paint {
            walls,
            seed,
            paint_config: paint.file.clone(),
        }),
        start,
        trajectory: plan.trajectory.clone(),
        origins: crate::trajectory::Origins::whole("the painting plan"),
        cleared: false,
    };
    // Not checked yet: streaming checks it against the run's cell and this room's walls.
    let run = super::stream_planned(settings, &job, &mut link, clock, log, control)?;
    let report = {
        let measured = world.lock().unwrap_or_else(PoisonError::into_inner);
        build_report(paint, &plan, &measured, run.stream.duration_s)
    };
    Ok(PaintRun {
        run,
        paint: report,
        world,
    })
}

/// `settings` with the cell a paint job's plan is checked against before motion: the run's
/// own cell objects and pairs, plus the walls, floor and brush of the room the job
/// generates (a cell file cannot know a generated room's walls), at the run cell's margin. That margin
/// must lie below the planner's clearance, which the planner keeps at its samples only.
pub fn gate_settings(
    settings: &RunSettings,
    job: &crate::job::Paint,
) -> Result<RunSettings, DaemonError> {
    let paint =
        crate::task::paint::load_paint_settings(&job.paint_config).map_err(JobError::from)?;
    let (margin_m, clearance_m) = (
        settings.cell.margin_m,
        paint.config.body.planning_clearance_m,
    );
    if margin_m >= clearance_m {
        let refused = PaintPlanError::MarginNotBelowClearance {
            margin_m,
            clearance_m,
        };
        return Err(JobError::Paint(refused.into()).into());
    }
    let room = crate::task::paint::room_for(&paint, job.walls, job.seed)
        .map_err(|e| JobError::Paint(e.into()))?;
    let room = crate::task::paint::body::room_cell(&settings.rig, &room, &paint.config);
    let cell = crate::task::paint::body::merge_room(&settings.cell, &room);
    let collision = crate::cell::CollisionModel::new(&settings.rig, &cell)?;
    Ok(RunSettings {
        cell,
        collision: Arc::new(collision),
        ..settings.clone()
    })
}
