//! `rigbridge paint`: generate a room, plan its painting, stream it to the in-process twin
//! (which measures the paint), with progress, then print a summary and write the report
//! (JSON) and the picture (SVG).

use super::run::{ClockChoice, default_log_path, exit_code, make_clock, print_stream_summary};
use anyhow::Context;
use clap::Args;
use rigbridge::daemon::config::load_run_settings;
use rigbridge::daemon::paint::run_paint;
use rigbridge::stream::StreamControl;
use rigbridge::task::paint::{load_paint_settings, write_svg};
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::{Arc, PoisonError};

#[derive(Args)]
pub struct PaintArgs {
    /// Number of walls (3..=32).
    #[arg(long)]
    walls: u32,
    /// Seed of the room generator.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Run settings (stream rate, twin, plan shares); its rig must be the painter.
    #[arg(long, default_value = "config/paint-run.toml")]
    config: PathBuf,
    /// Room, brush and coverage settings.
    #[arg(long, default_value = "config/paint.toml")]
    paint_config: PathBuf,
    #[arg(long, value_enum, default_value = "wall")]
    clock: ClockChoice,
    /// Record the run to this MCAP file (default: runs/paint-<unix time>.mcap).
    #[arg(long)]
    log: Option<PathBuf>,
    /// Write the paint report (JSON) here.
    #[arg(long)]
    report: Option<PathBuf>,
    /// Write the picture of the unrolled walls (SVG) here.
    #[arg(long)]
    picture: Option<PathBuf>,
}

pub fn paint(args: PaintArgs) -> anyhow::Result<ExitCode> {
    let settings = load_run_settings(&args.config).context("cannot load run settings")?;
    let paint = load_paint_settings(&args.paint_config).context("cannot load paint settings")?;
    if let Some(picture) = &args.picture
        && picture.extension().is_none_or(|e| e != "svg")
    {
        anyhow::bail!(
            "--picture {}: only .svg pictures are written",
            picture.display()
        );
    }
    let log = args.log.unwrap_or_else(|| default_log_path("paint"));
    if let Some(dir) = log.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    }
    let control = Arc::new(StreamControl::default());
    let clock = make_clock(args.clock);
    let (walls, seed) = (args.walls, args.seed);
    let job_control = control.clone();
    let job_log = log.clone();
    // Planning time as the user waits for it (the library never reads the clock).
    let started = std::time::Instant::now();
    let job = super::run::spawn_streaming(move || {
        Ok(run_paint(
            &settings,
            &paint,
            walls,
            seed,
            clock.as_ref(),
            Some(&job_log),
            &job_control,
            &mut |plan| {
                println!(
                    "planned {} strokes ({:.0} s of motion) in {:.2} s{}",
                    plan.strokes.len(),
                    plan.trajectory.duration_s(),
                    started.elapsed().as_secs_f64(),
                    if plan.unreachable.is_empty() {
                        String::new()
                    } else {
                        format!(
                            "; {} strokes unreachable, left out:",
                            plan.unreachable.len()
                        )
                    }
                );
                for stroke in &plan.unreachable {
                    println!(
                        "  wall {} at s = {:.3} m, v {:.3}..{:.3} m: {}",
                        stroke.wall, stroke.s_m, stroke.v_from_m, stroke.v_to_m, stroke.reason
                    );
                }
            },
        )?)
    })?;
    let run = super::run::wait(&control, job)?;
    let r = &run.run;
    print_stream_summary(&r.job, &r.rig, r.rate_hz, r.clock, &r.stream);
    let t = &run.paint.totals;
    println!(
        "  paint: coverage {:.3} % of {:.3} m2 ({:.3} m2 painted), paint in openings {:.4} m2, collisions {}, limit violations {}",
        t.coverage * 100.0,
        t.paintable_m2,
        t.painted_m2,
        t.paint_in_openings_m2,
        t.collisions,
        t.limit_violations
    );
    println!("  log: {}", log.display());
    super::run::write_report(args.report.as_deref(), &run.paint)?;
    if let Some(picture) = &args.picture {
        let world = run.world.lock().unwrap_or_else(PoisonError::into_inner);
        std::fs::write(picture, write_svg(&world, &run.paint))
            .with_context(|| format!("cannot write picture {}", picture.display()))?;
    }
    Ok(exit_code(r.stream.outcome))
}
