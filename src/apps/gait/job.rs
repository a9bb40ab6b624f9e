//! `kind = "gait"`: the sloth's gait over a scenario, built in or a walk of a forest file
//! next to the config. Owns the job's keys and their checks; the gait itself is
//! `apps::gait`'s. Needs the sloth rig (the config's `rig` a sloth file).

use super::{Forest, Scenario, forest::scenario_named, plan_gait_job};
use crate::job::{JobContext, JobError, JobInvalid, PlanContext, resolve_file};
use crate::trajectory::Trajectory;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use std::path::PathBuf;

#[derive(Debug, Clone, PartialEq, Deserialize, Serialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Gait {
    /// A built-in scenario (`straight`, `branch-turn`, `parallel`, ...), or a walk of `forest`.
    pub scenario: String,
    /// The scenario's angle (deg), for the scenarios that take one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub angle_deg: Option<f64>,
    /// The scenario's gap (m), for the scenarios that take one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gap_m: Option<f64>,
    /// A forest file relative to the config's directory: `scenario` is then one of its walks.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub forest: Option<PathBuf>,
}

impl Gait {
    pub fn validate(self, context: &JobContext) -> Result<Self, JobInvalid> {
        let Some(sloth) = super::sloth_of(context.app_rig) else {
            return Err(JobInvalid::new(
                "job.kind",
                "gait",
                "a gait job needs a sloth rig: the config's `rig` must be a sloth file",
            ));
        };
        let Some(forest) = &self.forest else {
            if let Err(e) = Scenario::build(&self.scenario, self.angle_deg, self.gap_m) {
                return Err(JobInvalid::new(
                    "job.scenario",
                    &self.scenario,
                    e.to_string(),
                ));
            }
            return Ok(self);
        };
        let geometry = "a walk from `forest` takes its geometry from that file";
        if let Some(angle) = self.angle_deg {
            return Err(JobInvalid::new("job.angle_deg", angle, geometry));
        }
        if let Some(gap) = self.gap_m {
            return Err(JobInvalid::new("job.gap_m", gap, geometry));
        }
        let file = resolve_file(context.base_dir, "job.forest", forest)?;
        let shown = forest.display().to_string();
        let loaded = Forest::load(&file, sloth.gait.trunk_tilt_rad).map_err(|e| {
            JobInvalid::new("job.forest", &shown, "is not a valid forest file").with_cause(e)
        })?;
        if let Err(e) = loaded.scenario(&self.scenario) {
            return Err(JobInvalid::new(
                "job.scenario",
                &self.scenario,
                e.to_string(),
            ));
        }
        Ok(Gait {
            forest: Some(file),
            ..self
        })
    }

    pub fn plan(&self, context: &PlanContext) -> Result<Trajectory, JobError> {
        let sloth = super::sloth_of(context.app_rig).ok_or(JobError::NeedsSloth)?;
        let scenario = scenario_named(
            &self.scenario,
            self.angle_deg,
            self.gap_m,
            self.forest.as_deref(),
            sloth.gait.trunk_tilt_rad,
        )
        .map_err(super::GaitError::from)?;
        Ok(plan_gait_job(
            sloth,
            &scenario,
            context.start,
            context.settings,
        )?)
    }

    pub fn name(&self) -> String {
        format!("gait {}", self.scenario)
    }
}
