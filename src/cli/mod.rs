//! Command-line edge of the binary: argument parsing, files, progress and summaries.
//! Everything it runs lives in the library; errors gain their context here.

mod batch;
mod dynamixel;
mod gait;
mod paint;
mod plot;
mod replay;
mod reset;
mod run;
mod serve;
mod twin;

use clap::{Parser, Subcommand};
use std::process::ExitCode;

#[derive(Parser)]
#[command(
    name = "rigbridge",
    version,
    about = "Plans joint motion for robot rigs (ABB IRB 120 first) and streams it to controllers or a simulated twin.",
    long_about = "Plans joint motion for robot rigs (ABB IRB 120 first) and streams it to controllers or a simulated twin.\n\nAngles on the command line and in CSV files are in degrees, lengths in metres. Rigs are TOML files in config/ or URDF files."
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
}

pub fn run() -> anyhow::Result<ExitCode> {
    match Cli::parse().command {
        Command::Fk(args) => batch::fk(args),
        Command::Ik(args) => batch::ik(args),
        Command::Run(args) => run::run(args),
        Command::Serve(args) => serve::serve(args),
        Command::Replay(args) => replay::replay_command(args),
        Command::Log(command) => replay::log_command(command),
        Command::Reset(args) => reset::reset(args),
        Command::Twin(args) => twin::twin(args),
        Command::Gait(args) => gait::gait(args),
        Command::Paint(args) => paint::paint(args),
    }
}
