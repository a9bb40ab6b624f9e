//! `rigbridge gait`: the sloth walks a scenario through the same pipeline as the arm (plan,
//! validate, stream to the loopback twin, MCAP log); the twin's world measures contact,
//! slip and clearance from its actual positions, and the verdict is printed and written.

use super::run::{ClockChoice, default_log_path, make_clock, spawn_streaming, wait, write_report};
use anyhow::Context;
use clap::Args;
use rigbridge::apps::gait::run::{GaitRun, run_gait};
use rigbridge::apps::gait::{
    FootfallSequence, Forest, GaitReport, LimbSolver, Scenario, picture, sloth_of,
};
use rigbridge::daemon::RunReport;
use rigbridge::daemon::config::{RunSettings, load_run_settings};
use rigbridge::stream::StreamControl;
use serde::Serialize;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;

#[derive(Args)]
pub struct GaitArgs {
    /// straight, branch-turn, parallel, height-change, trunk (= trunk-up), trunk-up,
    /// trunk-down (tail first, head up), trunk-around (side steps at one height),
    /// trunk-spiral (climbs a helix), transfer (climbs the trunk, then onto a branch, head
    /// first) or transfer-to-trunk (the other way: tail first, head up, along the branch and
    /// down the trunk). With --forest: the name of one of that file's walks (config/forest.toml: fork,
    /// climb, rise).
    #[arg(long)]
    scenario: String,
    /// Terrain and walks from this file (config/forest.toml): --scenario names a walk in it,
    /// whose supports and route the file holds (no --angle or --gap).
    #[arg(long)]
    forest: Option<PathBuf>,
    /// Angle between the branches in degrees (180: straight on): branch-turn, height-change;
    /// for trunk-around, trunk-spiral and trunk-down, degrees around the trunk per metre of
    /// route (trunk-down: 0 by default, a descending helix otherwise); for
    /// transfer and transfer-to-trunk, between the trunk below the junction and the branch
    /// (90: a level branch).
    #[arg(long)]
    angle: Option<f64>,
    /// Distance between the parallel branches' axes (m): parallel.
    #[arg(long)]
    gap: Option<f64>,
    /// Run settings naming the sloth rig (stream rate, twin).
    #[arg(long, default_value = "embedded:/gait-run.toml")]
    config: PathBuf,
    /// Record the run to this MCAP file (default: runs/gait-<unix time>-<pid>.mcap).
    #[arg(long)]
    log: Option<PathBuf>,
    /// Write the gait report (JSON) here.
    #[arg(long)]
    report: Option<PathBuf>,
    /// Write the picture (SVG: side and top views, gait diagram) here.
    #[arg(long)]
    picture: Option<PathBuf>,
    /// Whose time the cycles run on: wall (real time) or virtual (the same cycles without
    /// waiting).
    #[arg(long, value_enum, default_value = "wall")]
    clock: ClockChoice,
    /// Limb IK solver, ccd or fabrik (default: the sloth file's `[gait] solver`).
    #[arg(long)]
    solver: Option<String>,
    /// Footfall sequence, diagonal (rh lf lh rf) or lateral (rh rf lh lf, the seed's for
    /// transfers); the report judges the order against it (default: the sloth file's
    /// `[gait] footfall_order`).
    #[arg(long)]
    sequence: Option<String>,
}

/// What `--report` holds: the verdict and the stream's own report.
#[derive(Serialize)]
struct GaitRunReport {
    #[serde(flatten)]
    gait: GaitReport,
    run: RunReport,
}

pub fn gait(args: GaitArgs) -> anyhow::Result<ExitCode> {
    let mut settings = load_run_settings(&args.config).context("cannot load run settings")?;
    if args.solver.is_some() || args.sequence.is_some() {
        let mut sloth = sloth_of(settings.app_rig.as_deref())
            .cloned()
            .with_context(|| format!("{} names no sloth rig", args.config.display()))?;
        if let Some(name) = &args.solver {
            sloth.gait.solver = LimbSolver::from_name(name).with_context(|| {
                format!(
                    "--solver {name}: must be one of {}",
                    LimbSolver::NAMES.join(", ")
                )
            })?;
        }
        if let Some(name) = &args.sequence {
            let sequence = FootfallSequence::from_name(name).with_context(|| {
                format!(
                    "--sequence {name}: must be one of {}",
                    FootfallSequence::NAMES.join(", ")
                )
            })?;
            sloth.gait.footfall_order = sequence
                .limb_names()
                .iter()
                .map(|limb| {
                    sloth.limb_index(limb).with_context(|| {
                        format!("--sequence {name}: the sloth rig has no limb {limb}")
                    })
                })
                .collect::<anyhow::Result<_>>()?;
        }
        settings.app_rig = Some(Arc::new(sloth));
    }
    let scenario = match &args.forest {
        None => Scenario::build(&args.scenario, args.angle, args.gap)?,
        Some(forest) => walk_from(forest, &args, &settings)?,
    };
    let log = args.log.unwrap_or_else(|| default_log_path("gait"));
    if let Some(dir) = log.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    }
    let control = Arc::new(StreamControl::default());
    let clock = make_clock(args.clock);
    let (job_control, job_log, job_scenario) = (control.clone(), log.clone(), scenario.clone());
    let job = spawn_streaming(move || {
        Ok(run_gait(
            &settings,
            &job_scenario,
            clock.as_ref(),
            Some(&job_log),
            &job_control,
        )?)
    })?;
    let GaitRun {
        verdict,
        run,
        plan,
        body_path,
        sloth,
    } = wait(&control, job)?;
    print_verdict(&verdict)?;
    say!("  log: {}", log.display());
    if let Some(path) = &args.picture {
        std::fs::write(path, picture::render(&sloth, &scenario, &plan, &body_path))
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

/// The walk `--scenario` of the forest file `forest`, whose supports decide trunk or branch
/// by the sloth's `[gait] trunk_tilt_deg`.
fn walk_from(
    forest: &std::path::Path,
    args: &GaitArgs,
    settings: &RunSettings,
) -> anyhow::Result<Scenario> {
    if args.angle.is_some() || args.gap.is_some() {
        anyhow::bail!(
            "--angle and --gap shape the built-in scenarios: walk {} of {} takes its geometry \
             from that file",
            args.scenario,
            forest.display()
        );
    }
    let sloth = sloth_of(settings.app_rig.as_deref())
        .with_context(|| format!("{} names no sloth rig", args.config.display()))?;
    let forest = Forest::load(forest, sloth.gait.trunk_tilt_rad)?;
    Ok(forest.scenario(&args.scenario)?)
}

fn print_verdict(r: &GaitReport) -> anyhow::Result<()> {
    let shown = |value: Option<f64>, unit: &str| {
        value.map_or("none".to_string(), |v| format!("{v} {unit}"))
    };
    say!(
        "gait {} (angle {}, gap {}, {} limbs): {} over {} judged cycles, {:.3} m/s",
        r.scenario,
        shown(r.angle_deg, "deg"),
        shown(r.gap_m, "m"),
        r.solver.name(),
        if r.passed { "PASSED" } else { "FAILED" },
        r.cycles_judged,
        r.speed_mps
    );
    if let Some(reason) = &r.reason {
        say!("  reason: {reason}");
    }
    say!(
        "  footfalls: {}; min body clearance {:.1} mm; max IK residual {:.3} mm",
        r.footfall_order.join(" "),
        r.min_body_clearance_mm,
        r.max_ik_residual_mm
    );
    say!(
        "  body rose {:.3} m; head at least {:.3} m above the tail, heading at least {:.1} deg \
         above level{}",
        r.body_rise_m,
        r.min_head_above_tail_m,
        r.min_heading_elevation_deg,
        r.around_trunk_deg
            .map_or(String::new(), |d| format!("; {d:.1} deg around the trunk"))
    );
    for l in &r.limbs {
        say!(
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
    Ok(())
}
