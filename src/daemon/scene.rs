//! Which live scene (and which twin world) a cell shows for a job: the arm before its wall,
//! or the scene the job's app brings ([`crate::apps::App::scene`]). Owns only that choice;
//! the scenes themselves live in `src/view` and in the apps, and planning stays with the
//! job. A job's log gets the same world, fed by the log's writer thread
//! ([`log_scene_for_job`]).

use crate::apps::JobScene;
use crate::daemon::config::{JobConfig, RunSettings};
use crate::log::{LoggedScene, SceneSource};
use crate::scene::{ClosestView, PaintQuad, SceneView};
use crate::twin::ViewOnly;
use crate::view::{ArmScene, CellDrawing, ToolTrace};
use std::sync::{Arc, Mutex};

/// The scene of `job` for the cell of `settings`, and the world the twin must feed for it.
/// An app's job whose world cannot be built shows the bare rig: planning the same job fails
/// and reports why.
pub fn scene_for_job(settings: &RunSettings, job: &JobConfig) -> JobScene {
    let Some(app) = crate::apps::app_of(job) else {
        let trace = Arc::new(Mutex::new(ToolTrace::new(settings.tcp_rig.clone())));
        let scene = ArmScene::for_job(settings.rig.clone(), job, Some(trace.clone()));
        // The trace is drawn, not measured: a cycle skips it rather than wait for the view.
        return (Box::new(scene), Some(Box::new(ViewOnly(trace))));
    };
    app.scene(job, &settings.rig, settings.app_rig.as_ref())
        .unwrap_or_else(|| (Box::new(ArmScene::new(settings.rig.clone())), None))
}

/// The world of `job` for its run log's `/scene`: its app's world (a room's paint, the
/// branches), and the cell (its objects, the tool, the rig's collision bodies, the closest pair within
/// the margin), over a world of its own that the log's writer thread feeds the logged
/// states, so the paint in the log is the paint at each logged state. An arm's job without
/// a cell has none.
pub fn log_scene_for_job(settings: &RunSettings, job: &JobConfig) -> Option<SceneSource> {
    // A cell whose model cannot be built is refused when the job plans; the log goes without.
    let cell = crate::daemon::cell_drawing(settings).ok().flatten();
    if cell.is_none() && crate::apps::app_of(job).is_none() {
        return None;
    }
    let scene = SceneForLog {
        job: scene_for_job(settings, job),
        cell,
        last: Vec::with_capacity(settings.rig.dof()),
    };
    Some(SceneSource::new(Box::new(scene), &settings.rig.base_frame))
}

/// A job's live scene and its world, and the cell's drawing, as a [`LoggedScene`].
struct SceneForLog {
    job: JobScene,
    cell: Option<CellDrawing>,
    /// The last observed positions: the closest pair is found only when the log asks.
    last: Vec<f64>,
}

impl LoggedScene for SceneForLog {
    fn observe(&mut self, actual: &[f64]) {
        if let Some(world) = self.job.1.as_mut() {
            world.observe(actual);
        }
        self.last.clear();
        self.last.extend_from_slice(actual);
    }

    fn scene(&self) -> SceneView {
        let mut view = self.job.0.scene();
        if let Some(cell) = &self.cell {
            view.solids.extend(cell.solids.iter().cloned());
            view.bodies.extend(cell.bodies.iter().cloned());
        }
        view
    }

    fn drain_paint(&mut self) -> Vec<PaintQuad> {
        self.job.0.drain_paint()
    }

    fn closest(&mut self) -> Option<ClosestView> {
        self.cell.as_mut()?.closest(&self.last)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::daemon::config::load_run_settings;
    use std::path::Path;

    fn shipped(file: &str) -> RunSettings {
        let path = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("config")
            .join(file);
        load_run_settings(&path).expect("a shipped run settings file loads")
    }

    #[test]
    fn each_kind_of_job_gets_its_own_scene() {
        let paint = shipped("paint-run.toml");
        let (scene, world) = scene_for_job(&paint, &paint.config.job);
        assert_eq!(scene.scene().walls.len(), 4, "the room of [job] walls = 4");
        assert!(world.is_some(), "the twin paints the room");

        let gait = shipped("gait-run.toml");
        let (scene, world) = scene_for_job(&gait, &gait.config.job);
        assert!(!scene.scene().cylinders.is_empty(), "the sloth's branch");
        assert_eq!(
            scene.chains(&gait.initial()).len(),
            5,
            "spine and four limbs"
        );
        assert!(world.is_none());

        let arm = shipped("rigbridge.toml");
        let (scene, world) = scene_for_job(&arm, &arm.config.job);
        assert_eq!(scene.scene().walls.len(), 1, "the star's wall");
        assert!(world.is_some(), "the tool's trace");
    }

    #[test]
    fn a_room_that_cannot_be_built_shows_the_bare_rig() {
        let paint = shipped("paint-run.toml");
        let job = JobConfig::Paint(crate::job::Paint {
            walls: 2,
            seed: 0,
            paint_config: Path::new(env!("CARGO_MANIFEST_DIR")).join("config/paint.toml"),
        });
        let (scene, world) = scene_for_job(&paint, &job);
        assert!(scene.scene().walls.is_empty());
        assert!(world.is_none());
        assert!(
            !scene.chains(&paint.initial()).is_empty(),
            "the painter still shows"
        );
    }
}
