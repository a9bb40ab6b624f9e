//! Command-line edge of the binary: argument parsing, files, progress and summaries.
//! Everything it runs lives in the library; errors gain their context here, and so do the
//! exit codes ([`EXIT_USAGE`], [`EXIT_FAILED_ROWS`]) and the end of output on a closed pipe.

/// Writes one line to stdout like `println!`, but a closed pipe is an error the command
/// returns (and `main` ends on quietly), never a panic.
macro_rules! say {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        writeln!($crate::cli::stdout(), $($arg)*)?;
    }};
}

mod batch;
mod canopen;
mod config;
mod dynamixel;
mod gait;
mod logging;
mod paint;
mod plot;
mod replay;
mod reset;
mod run;
mod serve;
mod twin;

use clap::{Parser, Subcommand};
use std::io::Write;
use std::path::Path;
use std::process::ExitCode;
use std::sync::atomic::{AtomicBool, Ordering};

/// The exit code of a command used wrongly (what clap also returns for a bad argument).
pub const EXIT_USAGE: u8 = 2;
/// The exit code of a batch that ran to the end with some rows failed (their status says
/// why); 1 stays "could not run at all".
pub const EXIT_FAILED_ROWS: u8 = 3;

/// The variable naming the run settings when `--config` does not.
pub const CONFIG_VAR: &str = "RIGBRIDGE_CONFIG";

const EXIT_CODES_HELP: &str = "Exit codes: 0 done; 1 could not run (a file, the rig, a link, a job that failed); 2 usage error (a bad argument or combination of arguments); 3 a batch (fk, ik) ran but some rows failed, or a check found a row that is not free, their status column says why.";

/// A command used wrongly: exit code [`EXIT_USAGE`], whatever the context added to it.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct Usage(pub String);

/// Set once a write to stdout found the reader gone (`rigbridge log info | head -1`).
static STDOUT_CLOSED: AtomicBool = AtomicBool::new(false);

/// True once stdout's reader has gone: the command's error is then the end of its output,
/// not a failure.
pub fn stdout_closed() -> bool {
    STDOUT_CLOSED.load(Ordering::Relaxed)
}

/// Stdout that remembers a closed pipe (see [`stdout_closed`]).
pub struct Stdout(std::io::StdoutLock<'static>);

pub fn stdout() -> Stdout {
    Stdout(std::io::stdout().lock())
}

fn note_closed<T>(result: std::io::Result<T>) -> std::io::Result<T> {
    if let Err(e) = &result
        && e.kind() == std::io::ErrorKind::BrokenPipe
    {
        STDOUT_CLOSED.store(true, Ordering::Relaxed);
    }
    result
}

impl Write for Stdout {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        note_closed(self.0.write(buf))
    }

    fn flush(&mut self) -> std::io::Result<()> {
        note_closed(self.0.flush())
    }
}

/// The context of a run settings file that did not load, naming where its path came from
/// when it was the environment's.
pub fn settings_context(path: &Path) -> String {
    match std::env::var_os(CONFIG_VAR) {
        Some(value) if Path::new(&value) == path => {
            format!("cannot load run settings (from {CONFIG_VAR})")
        }
        _ => "cannot load run settings".to_string(),
    }
}

/// The exit code for an error a command returned.
pub fn exit_code_for(error: &anyhow::Error) -> ExitCode {
    if error.chain().any(|e| e.is::<Usage>()) {
        ExitCode::from(EXIT_USAGE)
    } else {
        ExitCode::FAILURE
    }
}

#[derive(Parser)]
#[command(
    name = "rigbridge",
    version,
    about = "Plans joint motion for robot rigs (ABB IRB 120 first) and streams it to controllers or a simulated twin.",
    long_about = "Plans joint motion for robot rigs (ABB IRB 120 first) and streams it to controllers or a simulated twin.\n\nAngles on the command line and in CSV files are in degrees (metres for prismatic axes), lengths in metres. Rigs are TOML or URDF files. The IRB 120 rig and the demo settings are built in (embedded:/rigbridge.toml, embedded:/irb120.toml, ...): `rigbridge config dump DIR` writes them out for editing; --config, RIGBRIDGE_CONFIG and --rig name other files, and paths inside a config file are relative to that file's directory.",
    after_help = EXIT_CODES_HELP
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Forward kinematics over a CSV of joint rows (j1..jN, degrees) -> tool poses.
    Fk(batch::FkArgs),
    /// Inverse kinematics over a CSV of tool poses (x,y,z,qw,qx,qy,qz) -> joint rows.
    Ik(batch::IkArgs),
    /// Collision check over a CSV of joint rows (j1..jN, degrees) -> the closest pair of
    /// bodies per row: min_clearance_m,body_a,body_b,status (free, within_margin, collision).
    Check(batch::CheckArgs),
    /// Run a job against the twin and exit: plan, stream, record (MCAP), report.
    Run(run::RunArgs),
    /// Stay up with a control API on 127.0.0.1: submit jobs, status, pause/resume, stop, e-stop.
    Serve(serve::ServeArgs),
    /// Re-stream a recorded run over any link, from where the controller holds, at the
    /// stream's rate, validated again against the rig.
    Replay(replay::ReplayArgs),
    /// Ask a controller to clear its latched fault or e-stop (exit 0 once it reports none).
    Reset(reset::ResetArgs),
    /// The simulated controller as its own process, on a TCP port, a serial line, a pty or CAN.
    Twin(twin::TwinArgs),
    /// The sloth gait over a scenario, streamed to the twin and judged from what it did.
    Gait(gait::GaitArgs),
    /// Paint a generated room of N walls against the twin, which measures the paint.
    Paint(paint::PaintArgs),
    /// Inspect run logs.
    #[command(subcommand)]
    Log(replay::LogCommand),
    /// The built-in configuration files: write them out for editing.
    #[command(subcommand)]
    Config(config::ConfigCommand),
}

pub fn run() -> anyhow::Result<ExitCode> {
    let cli = Cli::parse();
    logging::init();
    match cli.command {
        Command::Fk(args) => batch::fk(args),
        Command::Ik(args) => batch::ik(args),
        Command::Check(args) => batch::check(args),
        Command::Run(args) => run::run(args),
        Command::Serve(args) => serve::serve(args),
        Command::Replay(args) => replay::replay_command(args),
        Command::Log(command) => replay::log_command(command),
        Command::Reset(args) => reset::reset(args),
        Command::Twin(args) => twin::twin(args),
        Command::Gait(args) => gait::gait(args),
        Command::Paint(args) => paint::paint(args),
        Command::Config(command) => config::config_command(command),
    }
}
