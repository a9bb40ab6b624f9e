//! `kind = "paint"`: paint a generated room of `walls` walls (seed `seed`) with the painter
//! rig, its settings in `paint_config` next to the config. Owns the job's keys and their
//! checks; the room and its painting are `apps::paint`'s.

use super::{load_paint_settings, plan_room, room::MAX_WALLS};
use crate::job::{JobContext, JobError, JobInvalid, PlanContext, resolve_file};
use crate::trajectory::Trajectory;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use std::path::PathBuf;

#[derive(Debug, Clone, PartialEq, Deserialize, Serialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Paint {
    /// How many walls the generated room has, at least 3.
    pub walls: u32,
    /// The room generator's seed.
    pub seed: u64,
    /// The paint settings file (config/paint.toml), relative to the config's directory.
    pub paint_config: PathBuf,
}

impl Paint {
    pub fn validate(self, context: &JobContext) -> Result<Self, JobInvalid> {
        if !(3..=MAX_WALLS).contains(&self.walls) {
            return Err(JobInvalid::new(
                "job.walls",
                self.walls,
                format!("must lie in [3, {MAX_WALLS}]"),
            ));
        }
        let file = resolve_file(context.base_dir, "job.paint_config", &self.paint_config)?;
        let shown = self.paint_config.display().to_string();
        let paint = load_paint_settings(&file).map_err(|e| {
            JobInvalid::new(
                "job.paint_config",
                &shown,
                "is not a valid paint settings file",
            )
            .with_cause(e)
        })?;
        if paint.rig != *context.rig {
            return Err(JobInvalid::new(
                "rig",
                &context.rig.name,
                format!(
                    "must be the painter rig {} named by {shown}",
                    paint.rig.name
                ),
            ));
        }
        Ok(Paint {
            paint_config: file,
            ..self
        })
    }

    pub fn plan(&self, context: &PlanContext) -> Result<Trajectory, JobError> {
        let paint = load_paint_settings(&self.paint_config)?;
        let (_, planned) = plan_room(
            &paint,
            self.walls,
            self.seed,
            context.start,
            context.settings,
        )?;
        Ok(planned.trajectory)
    }

    pub fn name(&self) -> String {
        format!("paint ({} walls, seed {})", self.walls, self.seed)
    }
}
