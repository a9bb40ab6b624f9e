//! `rigbridge replay` and `rigbridge log info`: re-stream a recorded run against the twin,
//! and summarise a log.

use super::run::{
    ClockChoice, make_clock, print_stream_summary, spawn_streaming, wait, write_report,
};
use anyhow::Context;
use clap::{Args, Subcommand};
use rigbridge::daemon::config::load_run_settings;
use rigbridge::daemon::replay::{replay, replay_trajectory};
use rigbridge::daemon::twin_settings;
use rigbridge::link::LoopbackLink;
use rigbridge::log::{read_log, summarize};
use rigbridge::stream::StreamControl;
use rigbridge::twin::Twin;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;

#[derive(Args)]
pub struct ReplayArgs {
    /// The MCAP log of a run.
    log: PathBuf,
    /// Run settings for the rig and the twin (the log's rig must match).
    #[arg(long, default_value = "config/rigbridge.toml")]
    config: PathBuf,
    /// Where to stream: only the in-process twin so far.
    #[arg(long, default_value = "loopback")]
    link: String,
    /// Time factor: 2 replays twice as fast (refused if that breaks a speed limit).
    #[arg(long, default_value_t = 1.0)]
    speed: f64,
    /// Record the replay to this MCAP file.
    #[arg(long)]
    record: Option<PathBuf>,
    #[arg(long)]
    report: Option<PathBuf>,
    #[arg(long, value_enum, default_value = "wall")]
    clock: ClockChoice,
}

#[derive(Subcommand)]
pub enum LogCommand {
    /// Summarise a run log: rig, channels, duration, sequence gaps, events, tracking error.
    Info {
        log: PathBuf,
        /// Print JSON instead of text.
        #[arg(long)]
        json: bool,
    },
    /// Draw a run log to a PNG: commanded vs actual per axis, tracking error, cycle jitter.
    Plot(super::plot::PlotArgs),
}

pub fn replay_command(args: ReplayArgs) -> anyhow::Result<ExitCode> {
    anyhow::ensure!(
        args.link == "loopback",
        "--link {}: only `loopback` is available so far",
        args.link
    );
    let settings = load_run_settings(&args.config).context("cannot load run settings")?;
    let log = read_log(&args.log).with_context(|| format!("cannot read {}", args.log.display()))?;
    if log.truncated {
        eprintln!(
            "note: {} ends early (a killed run?); replaying what it holds",
            args.log.display()
        );
    }
    anyhow::ensure!(
        log.rig == settings.rig.name,
        "{} records rig `{}`, {} describes `{}`",
        args.log.display(),
        log.rig,
        args.config.display(),
        settings.rig.name
    );
    let (_, start) = replay_trajectory(&log, args.speed)?;
    let twin = Twin::new(&settings.rig, twin_settings(&settings), &start)?;
    let control = Arc::new(StreamControl::default());
    let clock = make_clock(args.clock);
    let job_control = control.clone();
    let speed = args.speed;
    let clock_name = match args.clock {
        ClockChoice::Wall => "wall",
        ClockChoice::Virtual => "virtual",
    };
    let record = args.record.clone();
    let job = spawn_streaming(move || {
        let mut link = LoopbackLink::new(twin);
        Ok(replay(
            &log,
            &settings,
            speed,
            &mut link,
            clock.as_ref(),
            record.as_deref(),
            &job_control,
        )?)
    })?;
    let report = wait(&control, job)?;
    let rate_hz = report.stream.cycles as f64 / report.stream.duration_s.max(f64::MIN_POSITIVE);
    print_stream_summary("replay", &report.rig, rate_hz, clock_name, &report.stream);
    println!(
        "  {} recorded commands, same sequence: {}, max deviation from the recording {:.6} deg",
        report.recorded_commands, report.same_sequence, report.max_deviation_from_recording_deg
    );
    write_report(args.report.as_deref(), &report)?;
    Ok(super::run::exit_code(report.stream.outcome))
}

pub fn log_command(command: LogCommand) -> anyhow::Result<ExitCode> {
    match command {
        LogCommand::Info { log, json } => {
            let run = read_log(&log).with_context(|| format!("cannot read {}", log.display()))?;
            let summary = summarize(&run);
            if json {
                println!("{}", serde_json::to_string_pretty(&summary)?);
            } else {
                println!("{summary}");
            }
            Ok(ExitCode::SUCCESS)
        }
        LogCommand::Plot(args) => super::plot::plot_command(args),
    }
}
