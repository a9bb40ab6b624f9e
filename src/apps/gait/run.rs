//! A gait run end to end: plan the sloth's walk over a scenario, stream it through the
//! loopback twin (whose world measures the sloth's actual contact, slip and clearance) with
//! the same streamer and recorder as every job, then judge. Owns that wiring only.

use super::{GaitPlan, GaitReport, GaitWorld, Scenario, SlothRig, judge, plan_gait};
use crate::clock::Clock;
use crate::daemon::config::{JobConfig, RunSettings};
use crate::daemon::{DaemonError, PlannedJob, RunReport, stream_planned, twin_settings};
use crate::link::LoopbackLink;
use crate::stream::{Outcome, StreamControl};
use crate::twin::Twin;
use glam::DVec3;
use std::sync::{Arc, Mutex, PoisonError};

/// What a gait run produced: the verdict, the stream's report, the plan and the body's
/// actual path (for the picture).
pub struct GaitRun {
    pub verdict: GaitReport,
    pub run: RunReport,
    pub plan: GaitPlan,
    pub body_path: Vec<DVec3>,
    pub sloth: Arc<SlothRig>,
}

/// Plans, streams and judges `scenario` on the sloth of `settings` (a gait run config).
pub fn run_gait(
    settings: &RunSettings,
    scenario: &Scenario,
    clock: &dyn Clock,
    log: Option<&std::path::Path>,
    control: &StreamControl,
) -> Result<GaitRun, DaemonError> {
    let sloth = super::shared_sloth(settings.app_rig.as_ref()).ok_or_else(|| {
        DaemonError::Unavailable(format!(
            "{}: a gait run needs `[job] kind = \"gait\"` and a sloth rig",
            settings.file.display()
        ))
    })?;
    let (plan, trajectory) =
        plan_gait(&sloth, scenario, settings.period()).map_err(crate::job::JobError::Gait)?;
    let start = trajectory.position(0).to_vec();
    let twin = twin_settings(settings);
    let lag_frames = (twin.delay.as_secs_f64() / twin.period.as_secs_f64()).round() as usize;
    let world = Arc::new(Mutex::new(GaitWorld::new(
        &sloth, scenario, &plan, lag_frames,
    )));
    let mut link = LoopbackLink::new(
        Twin::new(&settings.rig, twin, &start)?.with_world(Box::new(world.clone())),
    );
    let planned = PlannedJob {
        job: JobConfig::Gait(crate::job::Gait {
            scenario: scenario.name.clone(),
            angle_deg: scenario.angle_deg,
            gap_m: scenario.gap_m,
            // The job is recorded by its scenario's name: a walk's forest file is the caller's.
            forest: None,
        }),
        start,
        trajectory,
        origins: crate::trajectory::Origins::whole("the gait's plan"),
        cleared: false,
    };
    let run = stream_planned(settings, &planned, &mut link, clock, log, control)?;
    let world = world.lock().unwrap_or_else(PoisonError::into_inner);
    let verdict = judge(
        &sloth,
        scenario,
        &plan,
        &world,
        run.stream.outcome == Outcome::Completed,
    );
    Ok(GaitRun {
        verdict,
        run,
        body_path: world.body_path.clone(),
        plan,
        sloth,
    })
}
