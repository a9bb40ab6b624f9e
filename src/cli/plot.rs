//! `rigbridge log plot`: one PNG of a run log: per axis, commanded against actual position
//! over time; the tracking error over time; a histogram of the per-cycle wake lateness
//! (jitter) the log holds, stalls included, with the figures `log info` and the run's
//! summary give (`rigbridge::log::jitter`).
//!
//! Text is drawn with DejaVu Sans embedded in the binary (the `dejavu` crate), so plotting
//! needs no system fonts.

use anyhow::Context;
use clap::Args;
use plotters::coord::Shift;
use plotters::prelude::*;
use rigbridge::log::{RunLog, jitter, read_log, wake_lateness};
use rigbridge::rig::JointKind;
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

#[derive(Args)]
pub struct PlotArgs {
    /// The MCAP log of a run.
    log: PathBuf,
    /// The PNG to write.
    #[arg(short, long)]
    output: PathBuf,
    /// Image width in pixels.
    #[arg(long, default_value_t = 1600)]
    width: u32,
    /// Image height in pixels.
    #[arg(long, default_value_t = 1200)]
    height: u32,
}

pub fn plot_command(args: PlotArgs) -> anyhow::Result<ExitCode> {
    anyhow::ensure!(
        args.width >= 400 && args.height >= 300,
        "--width/--height: at least 400x300 pixels"
    );
    let run = read_log(&args.log).with_context(|| format!("cannot read {}", args.log.display()))?;
    if run.truncated {
        eprintln!(
            "note: {} ends early (a killed run?); plotting what it holds",
            args.log.display()
        );
    }
    // Before drawing: inside it, only the backend's failure is reported.
    register_font()?;
    write_picture(&args.output, |path| {
        plot(&run, path, (args.width, args.height))
    })?;
    say!(
        "{}: {} commands, {} states -> {}",
        args.log.display(),
        run.commands.len(),
        run.states.len(),
        args.output.display()
    );
    if let Some(jitter) = jitter(&run) {
        say!("  {jitter} over {} cycles", jitter.cycles);
    }
    Ok(ExitCode::SUCCESS)
}

/// Draws a picture with `draw` into a temporary file beside `path`, then renames it over
/// `path`. The temporary file is created here first, so a directory that is missing or not
/// writable gets a plain I/O error (the plotting backend's own errors print Rust debug
/// text), and a failed drawing leaves `path` as it was.
pub(super) fn write_picture(
    path: &Path,
    draw: impl FnOnce(&Path) -> anyhow::Result<()>,
) -> anyhow::Result<()> {
    let dir = match path.parent() {
        Some(dir) if !dir.as_os_str().is_empty() => dir,
        _ => Path::new("."),
    };
    let name = path
        .file_name()
        .with_context(|| format!("{}: not a file name", path.display()))?;
    // The backend picks the format by extension: keep it last.
    let temporary = dir.join(format!(
        ".{}.{}",
        std::process::id(),
        name.to_string_lossy()
    ));
    std::fs::File::create_new(&temporary)
        .with_context(|| format!("cannot write {} (in {})", path.display(), dir.display()))?;
    let drawn = draw(&temporary).map_err(|_| {
        anyhow::anyhow!(
            "cannot draw {}: the plotting backend failed to render or encode it",
            path.display()
        )
    });
    let moved = drawn.and_then(|()| {
        std::fs::rename(&temporary, path)
            .with_context(|| format!("cannot move {} to {}", temporary.display(), path.display()))
    });
    if moved.is_err() {
        // Best effort: the error says what failed; a leftover would only be litter.
        let _ = std::fs::remove_file(&temporary);
    }
    moved
}

pub(super) const FONT: &str = "sans-serif";

pub(super) fn register_font() -> anyhow::Result<()> {
    static REGISTERED: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    let ok = *REGISTERED.get_or_init(|| {
        plotters::style::register_font(FONT, FontStyle::Normal, dejavu::sans::regular()).is_ok()
    });
    anyhow::ensure!(ok, "the embedded DejaVu Sans font did not load");
    Ok(())
}

/// How one axis' values are shown: the factor from the log's unit and the label.
fn axis_unit(kinds: Option<&[JointKind]>, axis: usize) -> (f64, &'static str) {
    match kinds.and_then(|k| k.get(axis)) {
        Some(kind) => (kind.to_user(1.0), kind.unit()),
        None => (1.0, "rad|m"),
    }
}

/// The label of a chart that shows every axis at once.
fn common_unit(run: &RunLog, dof: usize) -> &'static str {
    let mut units: Vec<&str> = (0..dof)
        .map(|a| axis_unit(run.joint_kinds.as_deref(), a).1)
        .collect();
    units.dedup();
    match units.as_slice() {
        [one] => one,
        [] => "",
        _ => "deg | m",
    }
}

type Series = Vec<(f64, f64)>;

/// Per axis: (commanded, actual, |error|) in display units, NaNs left out.
fn series(run: &RunLog, dof: usize) -> Vec<(Series, Series, Series)> {
    let by_seq: HashMap<u32, usize> = run
        .commands
        .iter()
        .enumerate()
        .map(|(i, c)| (c.seq, i))
        .collect();
    (0..dof)
        .map(|axis| {
            let (scale, _) = axis_unit(run.joint_kinds.as_deref(), axis);
            let pick = |samples: &[rigbridge::log::LoggedSample]| -> Series {
                samples
                    .iter()
                    .filter_map(|s| Some((s.t, s.positions.get(axis)? * scale)))
                    .filter(|(t, q)| t.is_finite() && q.is_finite())
                    .collect()
            };
            let error = run
                .states
                .iter()
                .filter_map(|s| {
                    let command = &run.commands[*by_seq.get(&s.seq)?];
                    let e = (command.positions.get(axis)? - s.positions.get(axis)?).abs() * scale;
                    (s.t.is_finite() && e.is_finite()).then_some((s.t, e))
                })
                .collect();
            (pick(&run.commands), pick(&run.states), error)
        })
        .collect()
}

/// The smallest span a joint's chart shows (deg for a revolute axis, m for a prismatic one):
/// an axis that holds still varies by float noise only, and a chart 1e-9 wide labels every
/// tick "0.0". One degree or one centimetre shows a still axis as the flat line it is.
const MIN_SPAN_DEG: f64 = 1.0;
const MIN_SPAN_M: f64 = 0.01;

fn bounds(values: impl Iterator<Item = f64>) -> (f64, f64) {
    bounds_at_least(values, 0.0)
}

/// The values' range with 5 % padding, widened about its middle to at least `min_span`.
fn bounds_at_least(values: impl Iterator<Item = f64>, min_span: f64) -> (f64, f64) {
    let (lo, hi) = values.fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
        (lo.min(v), hi.max(v))
    });
    if !lo.is_finite() || !hi.is_finite() {
        return (0.0, 1.0);
    }
    let pad = ((hi - lo) * 0.05).max(1e-9);
    let (lo, hi) = (lo - pad, hi + pad);
    let widen = ((min_span - (hi - lo)) / 2.0).max(0.0);
    (lo - widen, hi + widen)
}

fn plot(run: &RunLog, path: &Path, size: (u32, u32)) -> anyhow::Result<()> {
    register_font()?;
    let dof = run.joint_names.len();
    let root = BitMapBackend::new(path, size).into_drawing_area();
    root.fill(&WHITE)?;
    let title = format!(
        "{}: {} commands, {} states{}",
        run.rig,
        run.commands.len(),
        run.states.len(),
        if run.truncated {
            " (log ends early)"
        } else {
            ""
        }
    );
    let root = root.titled(&title, (FONT, 24))?;
    let (top, bottom) = root.split_vertically(root.dim_in_pixel().1 * 62 / 100);
    let data = series(run, dof);
    let (t0, t1) = bounds(
        run.commands
            .iter()
            .chain(&run.states)
            .map(|s| s.t)
            .filter(|t| t.is_finite()),
    );

    let columns = if dof > 3 { 3 } else { dof.max(1) };
    let rows = dof.div_ceil(columns).max(1);
    for (axis, area) in top.split_evenly((rows, columns)).iter().enumerate() {
        let Some((commanded, actual, _)) = data.get(axis) else {
            break;
        };
        let (_, unit) = axis_unit(run.joint_kinds.as_deref(), axis);
        let min_span = match run.joint_kinds.as_deref().and_then(|k| k.get(axis)) {
            Some(JointKind::Prismatic) => MIN_SPAN_M,
            _ => MIN_SPAN_DEG,
        };
        let (y0, y1) = bounds_at_least(commanded.iter().chain(actual).map(|p| p.1), min_span);
        let mut chart = ChartBuilder::on(area)
            .caption(format!("{} [{unit}]", run.joint_names[axis]), (FONT, 16))
            .margin(6)
            .x_label_area_size(28)
            .y_label_area_size(56)
            .build_cartesian_2d(t0..t1, y0..y1)?;
        chart
            .configure_mesh()
            .x_desc("t [s]")
            .label_style((FONT, 12))
            .axis_desc_style((FONT, 12))
            .max_light_lines(2)
            .draw()?;
        chart
            .draw_series(LineSeries::new(
                commanded.iter().copied(),
                BLUE.stroke_width(2),
            ))?
            .label("commanded")
            .legend(|(x, y)| PathElement::new([(x, y), (x + 16, y)], BLUE.stroke_width(2)));
        chart
            .draw_series(LineSeries::new(actual.iter().copied(), RED.stroke_width(1)))?
            .label("actual")
            .legend(|(x, y)| PathElement::new([(x, y), (x + 16, y)], RED.stroke_width(1)));
        if axis == 0 {
            chart
                .configure_series_labels()
                .label_font((FONT, 12))
                .background_style(WHITE.mix(0.8))
                .border_style(BLACK)
                .position(SeriesLabelPosition::UpperRight)
                .draw()?;
        }
    }

    let (left, right) = bottom.split_horizontally(bottom.dim_in_pixel().0 * 55 / 100);
    draw_tracking_error(run, &data, &left, (t0, t1))?;
    draw_jitter(run, &right)?;
    root.present()?;
    Ok(())
}

fn draw_tracking_error(
    run: &RunLog,
    data: &[(Series, Series, Series)],
    area: &DrawingArea<BitMapBackend<'_>, Shift>,
    (t0, t1): (f64, f64),
) -> anyhow::Result<()> {
    let unit = common_unit(run, data.len());
    let worst = data
        .iter()
        .flat_map(|(_, _, e)| e.iter().map(|p| p.1))
        .fold(0.0_f64, f64::max);
    let mut chart = ChartBuilder::on(area)
        .caption(
            format!("tracking error |commanded - actual| per axis, max {worst:.4} {unit}"),
            (FONT, 16),
        )
        .margin(8)
        .x_label_area_size(32)
        .y_label_area_size(64)
        .build_cartesian_2d(t0..t1, 0.0..(worst * 1.1).max(1e-9))?;
    chart
        .configure_mesh()
        .x_desc("t [s]")
        .y_desc(unit)
        .label_style((FONT, 12))
        .axis_desc_style((FONT, 12))
        .max_light_lines(2)
        .draw()?;
    for (axis, (_, _, error)) in data.iter().enumerate() {
        let color = Palette99::pick(axis).to_rgba();
        chart
            .draw_series(LineSeries::new(
                error.iter().copied(),
                color.stroke_width(1),
            ))?
            .label(run.joint_names[axis].clone())
            .legend(move |(x, y)| PathElement::new([(x, y), (x + 16, y)], color.stroke_width(2)));
    }
    if !data.is_empty() {
        chart
            .configure_series_labels()
            .label_font((FONT, 12))
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .position(SeriesLabelPosition::UpperLeft)
            .draw()?;
    }
    Ok(())
}

fn draw_jitter(run: &RunLog, area: &DrawingArea<BitMapBackend<'_>, Shift>) -> anyhow::Result<()> {
    let late = wake_lateness(run);
    let Some(figures) = jitter(run) else {
        area.draw(&Text::new(
            "no per-cycle timing (late_us) in this log: no jitter histogram",
            (20, area.dim_in_pixel().1 as i32 / 2),
            (FONT, 16),
        ))?;
        return Ok(());
    };
    const BINS: usize = 40;
    let hi = figures.max_us.max(1.0);
    let width = hi / BINS as f64;
    let mut counts = [0u64; BINS];
    for v in &late {
        counts[((v / width) as usize).min(BINS - 1)] += 1;
    }
    let top = counts.iter().copied().max().unwrap_or(1) as f64 * 1.1;
    let mut chart = ChartBuilder::on(area)
        .caption(
            format!("cycle wake lateness, {} cycles: {figures}", figures.cycles),
            (FONT, 14),
        )
        .margin(8)
        .x_label_area_size(32)
        .y_label_area_size(64)
        .build_cartesian_2d(0.0..hi, (0.8..top).log_scale())?;
    chart
        .configure_mesh()
        .x_desc("late [us]")
        .y_desc("cycles (log scale)")
        .label_style((FONT, 12))
        .axis_desc_style((FONT, 12))
        .max_light_lines(2)
        .draw()?;
    chart.draw_series(
        counts
            .iter()
            .enumerate()
            .filter(|(_, n)| **n > 0)
            .map(|(i, &n)| {
                let x0 = i as f64 * width;
                Rectangle::new([(x0, 0.8), (x0 + width, n as f64)], GREEN.mix(0.7).filled())
            }),
    )?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Issue 32: a joint that holds still (joint_4 of the star job varies by float noise)
    /// got a chart 2e-9 wide whose every tick read "0.0".
    #[test]
    fn a_still_axis_gets_a_chart_a_degree_wide_about_its_value() {
        let (lo, hi) = bounds_at_least([12.0, 12.0 + 1e-12].into_iter(), MIN_SPAN_DEG);
        assert!((hi - lo - 1.0).abs() < 1e-9, "{lo}..{hi}");
        assert!(((lo + hi) / 2.0 - 12.0).abs() < 1e-9, "{lo}..{hi}");
    }

    #[test]
    fn a_moving_axis_keeps_its_own_range_with_five_percent_padding() {
        let (lo, hi) = bounds_at_least([-30.0, 50.0].into_iter(), MIN_SPAN_DEG);
        assert_eq!((lo, hi), (-34.0, 54.0));
    }
}
