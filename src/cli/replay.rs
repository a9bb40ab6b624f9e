//! `rigbridge replay` and `rigbridge log info`: re-stream a recorded run over any link (from
//! where its controller holds, at the stream's rate), and summarise a log.

use super::run::{
    ClockChoice, make_clock, print_stream_summary, spawn_streaming, wait, write_report,
};
use anyhow::Context;
use clap::{Args, Subcommand};
use rigbridge::daemon::config::load_run_settings;
use rigbridge::daemon::open_link;
use rigbridge::daemon::replay::{replay, replay_trajectory};
use rigbridge::device::LinkSpec;
use rigbridge::log::{read_log, summarize};
use rigbridge::stream::StreamControl;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;

#[derive(Args)]
pub struct ReplayArgs {
    /// The MCAP log of a run.
    log: PathBuf,
    /// Run settings for the rig and the twin (the log's rig must match).
    #[arg(long, env = "RIGBRIDGE_CONFIG", default_value = rigbridge::rig::shipped::DEFAULT_RUN_SETTINGS)]
    config: PathBuf,
    /// Where to stream (overrides the config's `[stream] link`); `--help` lists every form.
    #[arg(long, long_help = format!("Where to stream (overrides the config's `[stream] link`), as for `run`: {}", rigbridge::device::link_forms()))]
    link: Option<String>,
    /// Time factor at the stream's own rate: 0.5 takes twice as long, 2 half as long
    /// (refused, naming the axis, if that breaks a speed or acceleration limit).
    #[arg(long, default_value_t = 1.0)]
    speed: f64,
    /// Record the replay to this MCAP file.
    #[arg(long)]
    record: Option<PathBuf>,
    /// Write the replay's report here as JSON (outcome, cycles, what was replayed), like
    /// `run --report`; written to a temporary file and renamed.
    #[arg(long)]
    report: Option<PathBuf>,
    /// Whose time the cycles run on: wall (real time) or virtual (the same cycles without
    /// waiting).
    #[arg(long, value_enum, default_value = "wall")]
    clock: ClockChoice,
}

#[derive(Subcommand)]
pub enum LogCommand {
    /// Summarise a run log: rig, channels, duration, sequence gaps, events, tracking error.
    Info {
        /// The run log (an MCAP file `run`, `serve` or `replay --record` wrote).
        log: PathBuf,
        /// Print JSON instead of text.
        #[arg(long)]
        json: bool,
    },
    /// Draw a run log to a PNG: commanded vs actual per axis, tracking error, cycle jitter.
    Plot(super::plot::PlotArgs),
}

pub fn replay_command(args: ReplayArgs) -> anyhow::Result<ExitCode> {
    let settings =
        load_run_settings(&args.config).with_context(|| super::settings_context(&args.config))?;
    let log = read_log(&args.log).with_context(|| format!("cannot read {}", args.log.display()))?;
    if log.truncated {
        eprintln!(
            "note: {} ends early (a killed run?); replaying what it holds",
            args.log.display()
        );
    }
    let spec: LinkSpec = args
        .link
        .as_deref()
        .unwrap_or(&settings.config.stream.link)
        .parse()?;
    // Refused before any link is opened when the log cannot be replayed at all.
    replay_trajectory(&log, &settings, args.speed)
        .with_context(|| format!("cannot replay {}", args.log.display()))?;
    let control = Arc::new(StreamControl::default());
    let clock = make_clock(args.clock);
    let job_control = control.clone();
    let speed = args.speed;
    let record = args.record.clone();
    let job = spawn_streaming(move || {
        let mut link = open_link(&spec, &settings)?;
        // A device-paced link (EGM) brings the clock the cycle must follow.
        let clock = link.pacing().unwrap_or(clock);
        Ok(replay(
            &log,
            &settings,
            speed,
            link.as_mut(),
            clock.as_ref(),
            record.as_deref(),
            &job_control,
        )?)
    })?;
    let report = wait(&control, job)?;
    let run = &report.run;
    print_stream_summary("replay", &run.rig, run.rate_hz, run.clock, &run.stream)?;
    say!(
        "  {} recorded commands every {:.3} ms at {} x speed{}; approach {} samples, stop ramp {} samples",
        report.recorded_commands,
        report.recorded_period_s * 1e3,
        report.speed,
        if report.resampled { ", resampled" } else { "" },
        report.approach_samples,
        report.stop_ramp_samples
    );
    match report.max_deviation_from_recording_deg {
        Some(deviation) => say!(
            "  same sequence: {}, max deviation from the recording {deviation:.6} deg",
            report.same_sequence
        ),
        None => say!("  resampled: no cycle to compare one for one with the recording"),
    }
    write_report(args.report.as_deref(), &report)?;
    Ok(super::run::run_exit_code(run))
}

pub fn log_command(command: LogCommand) -> anyhow::Result<ExitCode> {
    match command {
        LogCommand::Info { log, json } => {
            let run = read_log(&log).with_context(|| format!("cannot read {}", log.display()))?;
            let summary = summarize(&run);
            if json {
                say!("{}", serde_json::to_string_pretty(&summary)?);
            } else {
                say!("{summary}");
            }
            Ok(ExitCode::SUCCESS)
        }
        LogCommand::Plot(args) => super::plot::plot_command(args),
    }
}
