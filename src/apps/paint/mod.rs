//! The painting task (issue 5, after seed 000): a generated room, a painter (the IRB 120 on
//! a mobile base and lift), a coverage planner that turns the room into one trajectory, the
//! twin's world that paints from the actual joint positions, and the report and picture.
//!
//! Owns the task's geometry, plan and measurements. Streaming, logging and the twin itself
//! are the pipeline's; this module only plans and measures.

mod app;
pub mod body;
pub mod config;
pub mod job;
pub mod planner;
pub mod report;
pub mod room;
pub mod run;
pub mod scene;
pub mod world;

pub use app::PaintApp;
pub use config::{EXTRA_AXES, LIFT_AXIS, PaintSettings, load_paint_settings};
pub use job::Paint;
pub use planner::{PaintPlan, PaintPlanError, plan_paint};
pub use report::{PaintReport, build_report, write_svg};
pub use room::{Room, RoomError, generate_room};
pub use scene::PaintScene;
pub use world::PaintWorld;

use crate::trajectory::PlanSettings;
use thiserror::Error;

#[derive(Debug, Error)]
pub enum PaintError {
    #[error("room")]
    Room(#[from] RoomError),
    #[error("plan")]
    Plan(#[from] PaintPlanError),
}

/// The room for `walls` and `seed` under `settings`.
pub fn room_for(settings: &PaintSettings, walls: u32, seed: u64) -> Result<Room, RoomError> {
    generate_room(
        walls,
        seed,
        &settings.config.room,
        settings.config.brush.width_m,
    )
}

/// Generates the room and plans the job from `start`.
pub fn plan_room(
    settings: &PaintSettings,
    walls: u32,
    seed: u64,
    start: &[f64],
    plan: &PlanSettings,
) -> Result<(Room, PaintPlan), PaintError> {
    let room = room_for(settings, walls, seed)?;
    let planned = plan_paint(settings, &room, start, plan)?;
    Ok((room, planned))
}

/// The twin's world for `room`, ready to be shared with the twin.
pub fn world_for(
    settings: &PaintSettings,
    room: &Room,
) -> Result<PaintWorld, crate::cell::CellError> {
    Ok(PaintWorld::new(
        &settings.rig,
        room,
        &body::Body::new(&settings.rig, room, &settings.config)?,
        settings.config.brush.contact_tolerance_m,
        settings.config.coverage.cell_m,
    ))
}
