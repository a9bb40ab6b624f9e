//! `rigbridge fk`, `rigbridge ik` and `rigbridge check`: files or stdin/stdout, a progress bar on long batches,
//! and a closing summary on stderr. An output file is written beside itself under a
//! temporary name and renamed over the target only once the batch ended, so a failed batch
//! leaves the old file whole; an input that is also the output is refused before anything
//! is opened for writing.

use super::Usage;
use anyhow::Context;
use clap::{Args, ValueEnum};
use indicatif::{ProgressBar, ProgressStyle};
use rigbridge::batch::check::{CheckSummary, check_batch};
use rigbridge::batch::{BatchSummary, fk_batch, ik_batch};
use rigbridge::cell::{Cell, CollisionModel};
use rigbridge::clock::{Clock, WallClock};
use rigbridge::daemon::config::load_run_settings;
use rigbridge::ik::{CcdSolver, FabrikSolver, GradientDescentSolver, IkSolver};
use rigbridge::rig::{Rig, load_rig_with_tool, shipped};
use std::fs::File;
use std::io::{BufReader, Read, Write};
use std::path::{Path, PathBuf};
use std::process::ExitCode;

/// Where the rig comes from and where its chain ends.
#[derive(Args)]
struct RigArgs {
    /// Rig description: a TOML or URDF file (recognised by its content); the default is the
    /// built-in IRB 120.
    #[arg(long, default_value = shipped::DEFAULT_RIG, conflicts_with = "config")]
    rig: PathBuf,
    /// The tool frame of a URDF rig: the link its chain ends at [default: the only leaf
    /// link a moving joint leads to; with several, the error lists them].
    #[arg(long, value_name = "NAME", conflicts_with = "config")]
    tool_frame: Option<String>,
    /// Run settings: their rig, and their cell's tool (instead of --rig).
    #[arg(long)]
    config: Option<PathBuf>,
    /// The frame poses are of: the cell's tool (its name: poses at its TCP) or the rig's
    /// tool frame (tool0 for the IRB 120) [default: the cell's tool when --config names a
    /// cell with one, as jobs do; else the rig's tool frame].
    #[arg(long, value_name = "NAME", requires = "config")]
    tool: Option<String>,
}

#[derive(Args)]
pub struct FkArgs {
    #[command(flatten)]
    rig: RigArgs,
    /// Joint rows, header j1..jN in degrees (metres for prismatic axes); `-` reads stdin.
    #[arg(long, default_value = "-")]
    input: PathBuf,
    /// Where the poses go (x,y,z,qw,qx,qy,qz,status); `-` writes stdout.
    #[arg(long, default_value = "-")]
    output: PathBuf,
}

#[derive(Args)]
pub struct CheckArgs {
    /// Run settings naming the rig and its cell [default: the built-in IRB 120 on its
    /// floor].
    #[arg(long, env = super::CONFIG_VAR)]
    config: Option<PathBuf>,
    /// Joint rows, header j1..jN in degrees (metres for prismatic axes); `-` reads stdin.
    #[arg(long, default_value = "-")]
    input: PathBuf,
    /// Where the rows go (min_clearance_m,body_a,body_b,status); `-` writes stdout.
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
    #[command(flatten)]
    rig: RigArgs,
    /// Tool poses, header x,y,z,qw,qx,qy,qz (metres, unit quaternion w first); `-` reads stdin.
    #[arg(long, default_value = "-")]
    input: PathBuf,
    /// Where the joints go (j1..jN in degrees, metres for prismatic axes, pos_err_m,
    /// rot_err_rad, iterations, status); `-` writes stdout.
    #[arg(long, default_value = "-")]
    output: PathBuf,
    /// Seed for the first row, comma-separated degrees (metres for prismatic axes; default
    /// all zeros). Later rows are seeded by the previous row's solution.
    #[arg(long, value_delimiter = ',', allow_negative_numbers = true)]
    seed: Option<Vec<f64>>,
    /// The IK solver: fabrik (six-axis arms with a spherical wrist; the planner), ccd or gd
    /// (comparisons, for other chains too; docs/kinematics.md).
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

/// Where a batch writes: stdout, or a temporary file beside the output that [`Output::finish`]
/// renames over it (dropped unfinished, the temporary file is removed and the target kept).
enum Output {
    Stdout,
    File { temporary: PathBuf, target: PathBuf },
}

impl Output {
    /// Refuses `output` = `input` (the same file by canonical path, links followed) before
    /// creating anything, then opens the temporary file.
    fn open(input: &Path, output: &Path) -> anyhow::Result<(Output, Box<dyn Write>)> {
        if output == Path::new("-") {
            return Ok((Output::Stdout, Box::new(super::stdout())));
        }
        if input != Path::new("-")
            && let (Ok(a), Ok(b)) = (input.canonicalize(), output.canonicalize())
            && a == b
        {
            anyhow::bail!(Usage(format!(
                "--output {} is the input file: writing it would destroy the input; choose another output",
                output.display()
            )));
        }
        let dir = match output.parent() {
            Some(dir) if !dir.as_os_str().is_empty() => dir,
            _ => Path::new("."),
        };
        let name = output
            .file_name()
            .with_context(|| format!("--output {}: not a file name", output.display()))?;
        // Hidden, beside the target (a rename within one directory is atomic), and unique to
        // this process so two batches never share one.
        let temporary = dir.join(format!(
            ".{}.{}.tmp",
            name.to_string_lossy(),
            std::process::id()
        ));
        let file = File::create_new(&temporary)
            .with_context(|| format!("cannot create output {}", temporary.display()))?;
        let target = output.to_path_buf();
        Ok((Output::File { temporary, target }, Box::new(file)))
    }

    /// The batch ended: the output file takes the batch's rows.
    fn finish(self) -> anyhow::Result<()> {
        if let Output::File { temporary, target } = &self {
            std::fs::rename(temporary, target).with_context(|| {
                format!(
                    "cannot move {} to {}",
                    temporary.display(),
                    target.display()
                )
            })?;
            std::mem::forget(self);
        }
        Ok(())
    }
}

impl Drop for Output {
    fn drop(&mut self) {
        if let Output::File { temporary, .. } = self {
            // Best effort: the batch already failed and says why; a leftover is only litter.
            let _ = std::fs::remove_file(temporary);
        }
    }
}

/// Row counts on the bar, every 1,000 rows (formatting each row would cost more than it shows).
fn show_rows(bar: &ProgressBar, rows: usize) {
    if rows.is_multiple_of(1000) {
        bar.set_message(format!("{rows} rows"));
    }
}

fn load(args: &RigArgs) -> anyhow::Result<Rig> {
    let Some(config) = &args.config else {
        return load_rig_with_tool(&args.rig, args.tool_frame.as_deref())
            .context("cannot load the rig");
    };
    let (rig, cell) = rig_and_cell(Some(config))?;
    let tcp = cell.tool.as_ref().map(|tool| tool.name.as_str());
    match args.tool.as_deref() {
        None if tcp.is_some() => Ok(cell.rig_at_tcp(&rig)),
        None => Ok(rig),
        Some(name) if Some(name) == tcp => Ok(cell.rig_at_tcp(&rig)),
        Some(name) if name == rig.tool_frame => Ok(rig),
        Some(name) => anyhow::bail!(Usage(format!(
            "--tool {name}: {} has {}",
            config.display(),
            match tcp {
                Some(tool) => format!("the tool {tool} and the tool frame {}", rig.tool_frame),
                None => format!("no tool, only the tool frame {}", rig.tool_frame),
            }
        ))),
    }
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
        ExitCode::from(super::EXIT_FAILED_ROWS)
    }
}

pub fn fk(args: FkArgs) -> anyhow::Result<ExitCode> {
    let rig = load(&args.rig)?;
    let (input, bar) = open_input(&args.input)?;
    let (output, writer) = Output::open(&args.input, &args.output)?;
    let start = WallClock::new();
    let summary = fk_batch(&rig, input, writer, |n| show_rows(&bar, n))
        .with_context(|| format!("fk batch on {}", args.input.display()))?;
    output.finish()?;
    bar.finish_and_clear();
    report(&summary, start.now(), false);
    Ok(exit_code(&summary))
}

pub fn ik(args: IkArgs) -> anyhow::Result<ExitCode> {
    let rig = load(&args.rig)?;
    let seed = match args.seed {
        Some(values) if values.len() != rig.dof() => {
            anyhow::bail!(Usage(format!(
                "--seed has {} values, rig {} has {} joints",
                values.len(),
                rig.name,
                rig.dof()
            )))
        }
        Some(values) => values
            .iter()
            .zip(&rig.joints)
            .map(|(v, joint)| joint.kind.from_user(*v))
            .collect(),
        None => vec![0.0; rig.dof()],
    };
    let solver: Box<dyn IkSolver> = match args.solver {
        SolverChoice::Fabrik => Box::new(FabrikSolver::new(rig).context(
            "the FABRIK planner cannot drive this rig (it needs a six-axis arm with a \
             spherical wrist); try --solver ccd",
        )?),
        SolverChoice::Ccd => Box::new(CcdSolver::new(rig)),
        SolverChoice::Gd => Box::new(GradientDescentSolver::new(rig)),
    };
    let (input, bar) = open_input(&args.input)?;
    let (output, writer) = Output::open(&args.input, &args.output)?;
    let start = WallClock::new();
    let summary = ik_batch(solver.as_ref(), &seed, input, writer, |n| {
        show_rows(&bar, n)
    })
    .with_context(|| format!("ik batch on {}", args.input.display()))?;
    output.finish()?;
    bar.finish_and_clear();
    report(&summary, start.now(), true);
    Ok(exit_code(&summary))
}

/// The rig and cell of `config` (run settings), or the built-in IRB 120 on its floor.
pub fn rig_and_cell(config: Option<&Path>) -> anyhow::Result<(Rig, Cell)> {
    match config {
        Some(path) => {
            let settings =
                load_run_settings(path).with_context(|| super::settings_context(path))?;
            Ok((settings.rig, settings.cell))
        }
        None => {
            let rig = load_rig_with_tool(Path::new(shipped::DEFAULT_RIG), None)
                .context("cannot load the built-in IRB 120")?;
            Ok((rig, Cell::builtin()))
        }
    }
}

fn report_check(summary: &CheckSummary, elapsed: std::time::Duration) {
    let per_row = if summary.rows > 0 {
        elapsed.as_secs_f64() * 1e6 / summary.rows as f64
    } else {
        0.0
    };
    let counts = summary
        .counts
        .iter()
        .map(|(k, n)| format!("{n} {k}"))
        .collect::<Vec<_>>()
        .join(", ");
    let closest = summary.closest.as_ref().map_or(String::new(), |c| {
        format!(
            "; smallest clearance {:.4} m ({} - {}) at row {}",
            c.distance_m, c.body_a, c.body_b, c.row
        )
    });
    eprintln!(
        "{} rows: {}{closest}; {:.3} s, {per_row:.2} us per row",
        summary.rows,
        if counts.is_empty() {
            "none".to_string()
        } else {
            counts
        },
        elapsed.as_secs_f64(),
    );
    if let Some(problem) = &summary.first_problem {
        eprintln!("first row not checked as given: {problem}");
    }
}

pub fn check(args: CheckArgs) -> anyhow::Result<ExitCode> {
    let (rig, cell) = rig_and_cell(args.config.as_deref())?;
    let model = CollisionModel::new(&rig, &cell).context("cannot build the collision model")?;
    let (input, bar) = open_input(&args.input)?;
    let (output, writer) = Output::open(&args.input, &args.output)?;
    let start = WallClock::new();
    let summary = check_batch(&model, &rig, input, writer, |n| show_rows(&bar, n))
        .with_context(|| format!("check batch on {}", args.input.display()))?;
    output.finish()?;
    bar.finish_and_clear();
    report_check(&summary, start.now());
    Ok(if summary.all_free() {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(super::EXIT_FAILED_ROWS)
    })
}
