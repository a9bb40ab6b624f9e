//! `rigbridge gait`: the sloth walks a scenario through the same pipeline as the arm (plan,
//! validate, stream to the loopback twin, MCAP log); the twin's world measures contact,
//! slip and clearance from its actual positions, and the verdict is printed and written.

use super::run::{ClockChoice, default_log_path, make_clock, spawn_streaming, wait, write_report};
use anyhow::Context;
use clap::Args;
use rigbridge::daemon::config::{JobConfig, load_run_settings};
use rigbridge::daemon::{PlannedJob, RunReport, stream_planned, twin_settings};
use rigbridge::link::LoopbackLink;
use rigbridge::stream::{Outcome, StreamControl};
use rigbridge::task::gait::{GaitReport, GaitWorld, Scenario, judge, picture, plan_gait};
use rigbridge::twin::Twin;
use serde::Serialize;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::{Arc, Mutex};

#[derive(Args)]
pub struct GaitArgs {
    /// straight, branch-turn, parallel or height-change.
    #[arg(long)]
    scenario: String,
    /// Angle between the branches in degrees (180: straight on): branch-turn, height-change.
    #[arg(long)]
    angle: Option<f64>,
    /// Distance between the parallel branches' axes (m): parallel.
    #[arg(long)]
    gap: Option<f64>,
    /// Run settings naming the sloth rig (stream rate, twin).
    #[arg(long, default_value = "config/gait-run.toml")]
    config: PathBuf,
    /// Record the run to this MCAP file (default: runs/gait-<unix time>.mcap).
    #[arg(long)]
    log: Option<PathBuf>,
    /// Write the gait report (JSON) here.
    #[arg(long)]
    report: Option<PathBuf>,
    /// Write the picture (SVG: side and top views, gait diagram) here.
    #[arg(long)]
    picture: Option<PathBuf>,
    #[arg(long, value_enum, default_value = "wall")]
    clock: ClockChoice,
}

/// What `--report` holds: the verdict and the stream's own report.
#[derive(Serialize)]
struct GaitRunReport {
    #[serde(flatten)]
    gait: GaitReport,
    run: RunReport,
}

pub fn gait(args: GaitArgs) -> anyhow::Result<ExitCode> {
    let settings = load_run_settings(&args.config).context("cannot load run settings")?;
    let sloth = settings.sloth.clone().with_context(|| {
        format!(
            "{}: the job must be `kind = \"gait\"` with a sloth rig",
            args.config.display()
        )
    })?;
    let scenario = Scenario::build(&args.scenario, args.angle, args.gap)?;
    let (plan, trajectory) =
        plan_gait(&sloth, &scenario, settings.period_s()).context("cannot plan the gait")?;
    if let Some(reason) = &plan.stop_reason {
        println!("the gait stops early: {reason}");
    }
    let start = trajectory.position(0).to_vec();
    let twin = twin_settings(&settings);
    let lag_frames = (twin.delay_s / twin.period_s).round() as usize;
    let world = Arc::new(Mutex::new(GaitWorld::new(&sloth, &scenario, &plan, lag_frames)));
    let mut link = LoopbackLink::new(
        Twin::new(&settings.rig, twin, &start)?.with_world(Box::new(world.clone())),
    );
    let log = args.log.unwrap_or_else(|| default_log_path("gait"));
    if let Some(dir) = log.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    }
    let planned = PlannedJob {
        job: JobConfig::Gait {
            scenario: scenario.name.clone(),
            angle_deg: scenario.angle_deg,
            gap_m: scenario.gap_m,
        },
        start,
        trajectory,
    };
    let control = Arc::new(StreamControl::default());
    let clock = make_clock(args.clock);
    let (job_control, job_log) = (control.clone(), log.clone());
    let job = spawn_streaming(move || {
        Ok(stream_planned(
            &settings,
            &planned,
            &mut link,
            clock.as_ref(),
            Some(&job_log),
            &job_control,
        )?)
    })?;
    let run = wait(&control, job)?;
    let world = world
        .lock()
        .map_err(|_| anyhow::anyhow!("the twin's world was poisoned"))?;
    let completed = run.stream.outcome == Outcome::Completed;
    let verdict = judge(&sloth, &scenario, &plan, &world, completed);
    print_verdict(&verdict);
    println!("  log: {}", log.display());
    if let Some(path) = &args.picture {
        std::fs::write(path, picture::render(&sloth, &scenario, &plan, &world.body_path))
            .with_context(|| format!("cannot write picture {}", path.display()))?;
    }
    let passed = verdict.passed;
    write_report(
        args.report.as_deref(),
        &GaitRunReport { gait: verdict, run },
    )?;
    Ok(if passed {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(4)
    })
}

fn print_verdict(r: &GaitReport) {
    println!(
        "gait {} (angle {:?}, gap {:?}): {} over {} judged cycles, {:.3} m/s",
        r.scenario,
        r.angle_deg,
        r.gap_m,
        if r.passed { "PASSED" } else { "FAILED" },
        r.cycles_judged,
        r.speed_mps
    );
    if let Some(reason) = &r.reason {
        println!("  reason: {reason}");
    }
    println!(
        "  footfalls: {}; min body clearance {:.1} mm; max IK residual {:.3} mm",
        r.footfall_order.join(" "),
        r.min_body_clearance_mm,
        r.max_ik_residual_mm
    );
    for l in &r.limbs {
        println!(
            "  {}: duty {:.2}, foot-to-surface {:.3} mm, slip {:.3} mm, {} {:.1} of {:.1} deg",
            l.limb,
            l.duty_factor,
            l.max_foot_to_surface_mm,
            l.max_slip_mm,
            l.max_bone_excursion_joint,
            l.max_bone_excursion_deg,
            l.bone_limit_deg
        );
    }
}
