//! The demo apps: sources of targets that need more than a job description, each in one
//! folder with all its pieces (its world, its job kind, its live scene, its end-to-end
//! run): `paint/`, a generated room to paint; `gait/`, the sloth's gait over its branches.
//! An app produces geometry, a plan through the normal pipeline and the measurements that
//! judge it; it never streams by itself and never changes the rig.
//!
//! The core reaches an app only through [`App`], looked up by the job's kind in [`APPS`]:
//! adding an app is its folder and one line there (and, while the job kinds are one serde
//! enum, its arm of `job::Job`).

pub mod gait;
pub mod paint;

use crate::cell::Cell;
use crate::job::{AppRig, Job, JobError};
use crate::rig::{ConfigError, Rig};
use crate::twin::TwinWorld;
use crate::view::LiveScene;
use std::path::Path;
use std::sync::Arc;

/// A job's live scene and the twin world (if any) that measures what the scene shows.
pub type JobScene = (Box<dyn LiveScene>, Option<Box<dyn TwinWorld>>);

/// The rig a run streams to, and what its app keeps beside it.
pub type LoadedRig = (Rig, Option<Arc<AppRig>>);

/// What the core asks of an app about a job of its kind. Each method is handed a job of the
/// app's own kind ([`app_of`] chose the app by it).
pub trait App: Sync {
    /// The job kind (`kind = "paint"`), also the app's folder and its `rigbridge` command.
    fn kind(&self) -> &'static str;

    /// The rig a job of this kind streams to, from the config's `rig` file, and what the app
    /// keeps beside it: a model of its own whose streamed axes the rig is, which are then
    /// not one serial chain (no forward kinematics, collision model or `/tf` pose them).
    fn load_rig(&self, path: &Path) -> Result<LoadedRig, ConfigError> {
        Ok((crate::rig::load_rig(path)?, None))
    }

    /// `job`'s live scene on `rig` and the twin world that measures it; `None` when its
    /// world cannot be built (planning the same job fails and says why).
    fn scene(&self, job: &Job, rig: &Rig, app_rig: Option<&Arc<AppRig>>) -> Option<JobScene>;

    /// The cell `job`'s plan is checked in before motion, when it is more than `cell` (the
    /// run's): `None` keeps the run's.
    fn gate_cell(&self, _job: &Job, _rig: &Rig, _cell: &Cell) -> Result<Option<Cell>, JobError> {
        Ok(None)
    }
}

/// The one registration list of apps.
pub const APPS: &[&dyn App] = &[&paint::PaintApp, &gait::GaitApp];

/// The app whose kind `job` is; `None` for the core's own kinds.
pub fn app_of(job: &Job) -> Option<&'static dyn App> {
    APPS.iter().copied().find(|app| app.kind() == job.kind())
}
