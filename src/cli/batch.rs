//! `rigbridge fk` and `rigbridge ik`: files or stdin/stdout, a progress bar on long batches,
//! and a closing summary on stderr.

use anyhow::{Context, bail};
use clap::{Args, ValueEnum};
use indicatif::{ProgressBar, ProgressStyle};
use rigbridge::batch::{BatchSummary, fk_batch, ik_batch};
use rigbridge::ik::{CcdSolver, FabrikSolver, GradientDescentSolver, IkSolver};
use rigbridge::rig::{Rig, load_rig};
use std::fs::File;
use std::io::{BufReader, Read, Write};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

#[derive(Args)]
pub struct FkArgs {
    /// Rig description: a TOML file from config/ or a URDF file.
    #[arg(long, default_value = "config/irb120.toml")]
    rig: PathBuf,
    /// Joint rows, header j1..jN in degrees; `-` reads stdin.
    #[arg(long, default_value = "-")]
    input: PathBuf,
    /// Where the poses go (x,y,z,qw,qx,qy,qz,status); `-` writes stdout.
    #[arg(long, default_value = "-")]
    output: PathBuf,
}

#[derive(Clone, Copy, ValueEnum)]
enum SolverChoice {
    /// The planner: FABRIK with axis limits, nearest solution to the seed over all branches.
    Fabrik,
    /// Cyclic coordinate descent (comparison; may not converge).
    Ccd,
    /// Gradient descent (baseline; slow, may not converge).
    Gd,
}

#[derive(Args)]
pub struct IkArgs {
    /// Rig description: a TOML file from config/ or a URDF file.
    #[arg(long, default_value = "config/irb120.toml")]
    rig: PathBuf,
    /// Tool poses, header x,y,z,qw,qx,qy,qz (metres, unit quaternion w first); `-` reads stdin.
    #[arg(long, default_value = "-")]
    input: PathBuf,
    /// Where the joints go (j1..jN in degrees, pos_err_m, rot_err_rad, iterations, status); `-` writes stdout.
    #[arg(long, default_value = "-")]
    output: PathBuf,
    /// Seed for the first row, comma-separated degrees (default all zeros). Later rows are
    /// seeded by the previous row's solution.
    #[arg(long, value_delimiter = ',', allow_negative_numbers = true)]
    seed: Option<Vec<f64>>,
    #[arg(long, value_enum, default_value = "fabrik")]
    solver: SolverChoice,
}

/// The input, read through the progress bar so it advances with the bytes consumed (the
/// file is read once; its size gives the bar its length). Stdin gets a spinner.
fn open_input(path: &Path) -> anyhow::Result<(Box<dyn Read>, ProgressBar)> {
    if path == Path::new("-") {
        let bar = ProgressBar::new_spinner().with_style(
            ProgressStyle::with_template("{spinner} {msg}, {elapsed}").expect("static template"),
        );
        bar.enable_steady_tick(std::time::Duration::from_millis(250));
        return Ok((Box::new(std::io::stdin().lock()), bar));
    }
    let file = File::open(path).with_context(|| format!("cannot open input {}", path.display()))?;
    let size = file.metadata().map(|m| m.len()).unwrap_or(0);
    let bar = ProgressBar::new(size).with_style(
        ProgressStyle::with_template("{bar:40} {percent:>3}% {msg}, eta {eta}")
            .expect("static template"),
    );
    // Batches shorter than a second finish before a bar would help.
    bar.enable_steady_tick(std::time::Duration::from_millis(250));
    Ok((Box::new(bar.wrap_read(BufReader::new(file))), bar))
}

fn open_output(path: &Path) -> anyhow::Result<Box<dyn Write>> {
    if path == Path::new("-") {
        return Ok(Box::new(std::io::stdout().lock()));
    }
    let file =
        File::create(path).with_context(|| format!("cannot create output {}", path.display()))?;
    Ok(Box::new(file))
}

/// Row counts on the bar, every 1,000 rows (formatting each row would cost more than it shows).
fn show_rows(bar: &ProgressBar, rows: usize) {
    if rows.is_multiple_of(1000) {
        bar.set_message(format!("{rows} rows"));
    }
}

fn load(rig: &Path) -> anyhow::Result<Rig> {
    load_rig(rig).context("cannot load the rig")
}

fn report(summary: &BatchSummary, elapsed: std::time::Duration, with_errors: bool) {
    let per_row = if summary.rows > 0 {
        elapsed.as_secs_f64() * 1e6 / summary.rows as f64
    } else {
        0.0
    };
    let errors = if with_errors {
        format!(
            "; max error {:.3e} m, {:.3e} rad",
            summary.max_position_error_m, summary.max_orientation_error_rad
        )
    } else {
        String::new()
    };
    eprintln!(
        "{} rows: {} ok, {} failed ({}); {:.3} s, {per_row:.2} us per row{errors}",
        summary.rows,
        summary.solved,
        summary.failed.values().sum::<usize>(),
        if summary.failed.is_empty() {
            "none".to_string()
        } else {
            summary
                .failed
                .iter()
                .map(|(k, n)| format!("{k}: {n}"))
                .collect::<Vec<_>>()
                .join(", ")
        },
        elapsed.as_secs_f64(),
    );
}

fn exit_code(summary: &BatchSummary) -> ExitCode {
    if summary.failed.is_empty() {
        ExitCode::SUCCESS
    } else {
        // Distinct from 1 (could not run at all): the batch ran, some rows failed.
        ExitCode::from(2)
    }
}

pub fn fk(args: FkArgs) -> anyhow::Result<ExitCode> {
    let rig = load(&args.rig)?;
    let (input, bar) = open_input(&args.input)?;
    let output = open_output(&args.output)?;
    let start = Instant::now();
    let summary = fk_batch(&rig, input, output, |n| show_rows(&bar, n))
        .with_context(|| format!("fk batch on {}", args.input.display()))?;
    bar.finish_and_clear();
    report(&summary, start.elapsed(), false);
    Ok(exit_code(&summary))
}

pub fn ik(args: IkArgs) -> anyhow::Result<ExitCode> {
    let rig = load(&args.rig)?;
    let seed = match args.seed {
        Some(degrees) if degrees.len() != rig.dof() => {
            bail!(
                "--seed has {} values, rig {} has {} joints",
                degrees.len(),
                rig.name,
                rig.dof()
            )
        }
        Some(degrees) => degrees.iter().map(|d| d.to_radians()).collect(),
        None => vec![0.0; rig.dof()],
    };
    let solver: Box<dyn IkSolver> = match args.solver {
        SolverChoice::Fabrik => {
            Box::new(FabrikSolver::new(rig).context("the FABRIK planner cannot drive this rig")?)
        }
        SolverChoice::Ccd => Box::new(CcdSolver::new(rig)),
        SolverChoice::Gd => Box::new(GradientDescentSolver::new(rig)),
    };
    let (input, bar) = open_input(&args.input)?;
    let output = open_output(&args.output)?;
    let start = Instant::now();
    let summary = ik_batch(solver.as_ref(), &seed, input, output, |n| {
        show_rows(&bar, n)
    })
    .with_context(|| format!("ik batch on {}", args.input.display()))?;
    bar.finish_and_clear();
    report(&summary, start.elapsed(), true);
    Ok(exit_code(&summary))
}
