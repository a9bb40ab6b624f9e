//! The sloth's gait as an app ([`App`]): the sloth loaded from the config's `rig` file (its
//! streamed axes the rig), and the sloth on the scenario's branches as a job's live scene.
//! Owns only what the core asks of the gait; the walk, its rules and its judging are this
//! folder's other files.

use super::{SlothRig, SlothScene, forest::scenario_named};
use crate::apps::{App, JobScene, LoadedRig};
use crate::job::{AppRig, Job};
use crate::rig::{ConfigError, Rig};
use std::path::Path;
use std::sync::Arc;

/// `kind = "gait"`.
pub struct GaitApp;

impl App for GaitApp {
    fn kind(&self) -> &'static str {
        "gait"
    }

    /// The sloth at `path`: its streamed axes (body and limbs side by side) are the rig.
    fn load_rig(&self, path: &Path) -> Result<LoadedRig, ConfigError> {
        let sloth = SlothRig::load(path)?;
        Ok((sloth.streamed.clone(), Some(Arc::new(sloth))))
    }

    /// The sloth on its scenario's branches; the twin measures nothing for the view (the
    /// gait's own run judges the walk).
    fn scene(&self, job: &Job, _rig: &Rig, app_rig: Option<&Arc<AppRig>>) -> Option<JobScene> {
        let Job::Gait(gait) = job else { return None };
        let sloth = shared_sloth(app_rig)?;
        let scenario = scenario_named(
            &gait.scenario,
            gait.angle_deg,
            gait.gap_m,
            gait.forest.as_deref(),
            sloth.gait.trunk_tilt_rad,
        )
        .ok()?;
        Some((Box::new(SlothScene::new(sloth, &scenario)), None))
    }
}

/// The sloth a run loaded beside its rig ([`GaitApp::load_rig`]), if it did.
pub fn sloth_of(app_rig: Option<&AppRig>) -> Option<&SlothRig> {
    app_rig?.downcast_ref()
}

/// [`sloth_of`], shared.
pub fn shared_sloth(app_rig: Option<&Arc<AppRig>>) -> Option<Arc<SlothRig>> {
    Arc::clone(app_rig?).downcast().ok()
}
