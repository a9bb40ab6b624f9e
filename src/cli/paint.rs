//! `rigbridge paint`: generate a room, plan its painting, stream it to the in-process twin
//! (which measures the paint), with progress, then print a summary and write the report
//! (JSON) and the picture (SVG).

use super::run::{ClockChoice, default_log_path, make_clock, print_stream_summary};
use anyhow::Context;
use clap::Args;
use rigbridge::apps::paint::run::run_paint;
use rigbridge::apps::paint::{PaintPlan, PaintReport, PaintWorld, load_paint_settings, write_svg};
use rigbridge::clock::{Clock, WallClock};
use rigbridge::daemon::config::{JobConfig, load_run_settings};
use rigbridge::stream::StreamControl;
use std::path::{Path, PathBuf};
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
    #[arg(long, default_value = "embedded:/paint-run.toml")]
    config: PathBuf,
    /// Room, brush and coverage settings [default: the run settings' `[job] paint_config`
    /// when its job paints, else embedded:/paint.toml].
    #[arg(long)]
    paint_config: Option<PathBuf>,
    /// Whose time the cycles run on: wall (real time) or virtual (the same cycles without
    /// waiting).
    #[arg(long, value_enum, default_value = "wall")]
    clock: ClockChoice,
    /// Record the run to this MCAP file (default: runs/paint-<unix time>-<pid>.mcap).
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
    let paint_config = match (args.paint_config, &settings.config.job) {
        (Some(file), _) => file,
        (None, JobConfig::Paint(job)) => job.paint_config.clone(),
        (None, _) => rigbridge::rig::shipped::path("paint.toml"),
    };
    let paint = load_paint_settings(&paint_config).context("cannot load paint settings")?;
    let picture_kind = args.picture.as_deref().map(Picture::of).transpose()?;
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
    let started = WallClock::new();
    let job = super::run::spawn_streaming(move || {
        Ok(run_paint(
            &settings,
            &paint,
            walls,
            seed,
            clock.as_ref(),
            Some(&job_log),
            &job_control,
            &mut |plan| print_plan(plan, &started),
        )?)
    })?;
    let run = super::run::wait(&control, job)?;
    let r = &run.run;
    print_stream_summary(&r.job, &r.rig, r.rate_hz, r.clock, &r.stream)?;
    let t = &run.paint.totals;
    say!(
        "  paint: coverage {:.3} % of {:.3} m2 ({:.3} m2 painted), paint in openings {:.4} m2, collisions {}, limit violations {}",
        t.coverage * 100.0,
        t.paintable_m2,
        t.painted_m2,
        t.paint_in_openings_m2,
        t.collisions,
        t.limit_violations
    );
    say!("  log: {}", log.display());
    super::run::write_report(args.report.as_deref(), &run.paint)?;
    if let (Some(picture), Some(kind)) = (&args.picture, picture_kind) {
        let world = run.world.lock().unwrap_or_else(PoisonError::into_inner);
        kind.write(picture, &world, &run.paint)?;
        say!("  picture: {}", picture.display());
    }
    Ok(super::run::run_exit_code(r))
}

#[derive(Clone, Copy)]
enum Picture {
    Svg,
    Png,
}

impl Picture {
    /// The picture `--picture` asks for, by its extension.
    fn of(path: &Path) -> anyhow::Result<Picture> {
        match path.extension().and_then(|e| e.to_str()) {
            Some("svg") => Ok(Picture::Svg),
            Some("png") => Ok(Picture::Png),
            _ => anyhow::bail!("--picture {}: write a .svg or a .png", path.display()),
        }
    }

    fn write(self, path: &Path, world: &PaintWorld, report: &PaintReport) -> anyhow::Result<()> {
        let written = match self {
            Picture::Svg => std::fs::write(path, write_svg(world, report)).map_err(Into::into),
            Picture::Png => {
                super::plot::register_font()?;
                super::plot::write_picture(path, |path| write_png(world, report, path))
            }
        };
        written.with_context(|| format!("cannot write picture {}", path.display()))
    }
}

/// What the plan holds, printed on the streaming thread as soon as it is planned: a closed
/// stdout must not stop the job here; the summary after it ends the output.
fn print_plan(plan: &PaintPlan, started: &WallClock) {
    use std::io::Write as _;
    let mut out = super::stdout();
    let unreachable = if plan.unreachable.is_empty() {
        String::new()
    } else {
        format!(
            "; {} strokes unreachable, left out:",
            plan.unreachable.len()
        )
    };
    let _ = writeln!(
        out,
        "planned {} strokes ({:.0} s of motion) in {:.2} s{unreachable}",
        plan.strokes.len(),
        plan.trajectory.duration_s(),
        started.now().as_secs_f64(),
    );
    for stroke in &plan.unreachable {
        let _ = writeln!(
            out,
            "  wall {} at s = {:.3} m, v {:.3}..{:.3} m: {}",
            stroke.wall, stroke.s_m, stroke.v_from_m, stroke.v_to_m, stroke.reason
        );
    }
}

/// The unrolled walls as a PNG, one pixel per coverage cell: paint green, paint inside an
/// opening red, unpainted wall grey, openings light blue (windows) or brown (doors).
fn write_png(world: &PaintWorld, report: &PaintReport, path: &Path) -> anyhow::Result<()> {
    use plotters::prelude::*;
    super::plot::register_font()?;
    let grids = world.grids();
    let (cols, rows) = (grids[0].cols as i32, grids[0].rows as i32);
    let (gap, label, per_row) = (30, 24, 8);
    let walls = grids.len() as i32;
    let width = per_row.min(walls) * (cols + gap) + gap;
    let height = (walls + per_row - 1) / per_row * (rows + gap + label) + gap + label;
    let root = BitMapBackend::new(path, (width as u32, height as u32)).into_drawing_area();
    root.fill(&WHITE)?;
    let font = (super::plot::FONT, 16).into_font();
    let t = &report.totals;
    root.draw_text(
        &format!(
            "{} walls, seed {}: coverage {:.3} %, paint in openings {:.4} m2, collisions {}, limit violations {}",
            report.walls_count,
            report.seed,
            t.coverage * 100.0,
            t.paint_in_openings_m2,
            t.collisions,
            t.limit_violations
        ),
        &font.color(&BLACK),
        (gap, 6),
    )?;
    let door = world.room().walls.iter().map(|w| {
        w.openings
            .iter()
            .map(|o| (o.kind, o.left_m, o.right_m, o.bottom_m, o.top_m))
            .collect::<Vec<_>>()
    });
    for ((index, grid), (openings, wall)) in grids.iter().enumerate().zip(door.zip(&report.walls)) {
        let (x0, top) = (
            gap + (index as i32 % per_row) * (cols + gap),
            gap + label + (index as i32 / per_row) * (rows + gap + label),
        );
        root.draw_text(
            &format!(
                "wall {} ({}): {:.2} %",
                wall.index,
                wall.wall_type,
                wall.coverage * 100.0
            ),
            &(super::plot::FONT, 13).into_font().color(&BLACK),
            (x0, top - 16),
        )?;
        for row in 0..rows {
            for col in 0..cols {
                let i = (row * cols + col) as usize;
                let colour = match (grid.painted[i], grid.opening[i]) {
                    (true, false) => RGBColor(44, 160, 44),
                    (true, true) => RGBColor(214, 39, 40),
                    (false, false) => RGBColor(200, 200, 200),
                    (false, true) => {
                        let s = (f64::from(col) + 0.5) * grid.cell;
                        let v = (f64::from(row) + 0.5) * grid.cell;
                        let is_door = openings.iter().any(|(kind, l, r, b, t)| {
                            *kind == rigbridge::apps::paint::room::OpeningKind::Door
                                && s > *l
                                && s < *r
                                && v > *b
                                && v < *t
                        });
                        if is_door {
                            RGBColor(196, 156, 148)
                        } else {
                            RGBColor(198, 219, 239)
                        }
                    }
                };
                root.draw_pixel((x0 + col, top + rows - 1 - row), &colour)?;
            }
        }
    }
    root.present()?;
    Ok(())
}
