//! `rigbridge run`: one job against the twin, with a progress bar, Ctrl-C handling (the
//! rig is brought to rest along its path, then the log is closed and the report written),
//! and a summary at the end.

use anyhow::Context;
use clap::{Args, ValueEnum};
use indicatif::{ProgressBar, ProgressStyle};
use rigbridge::clock::{Clock, VirtualClock, WallClock};
use rigbridge::daemon::config::{RunSettings, load_run_settings};
use rigbridge::daemon::{RunReport, loopback_twin, run_job};
use rigbridge::stream::{Outcome, StreamControl};
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;
use std::time::Duration;

#[derive(Clone, Copy, ValueEnum)]
pub enum ClockChoice {
    /// Real time: the job takes as long as the motion.
    Wall,
    /// Simulated time: the same cycles, without waiting.
    Virtual,
}

#[derive(Args)]
pub struct RunArgs {
    /// Run settings: rig, stream rate, twin, plan and job.
    #[arg(long, default_value = "config/rigbridge.toml")]
    config: PathBuf,
    /// Write the run report (JSON) here.
    #[arg(long)]
    report: Option<PathBuf>,
    #[arg(long, value_enum, default_value = "wall")]
    clock: ClockChoice,
}

fn make_clock(choice: ClockChoice) -> Arc<dyn Clock> {
    match choice {
        ClockChoice::Wall => Arc::new(WallClock::new()),
        ClockChoice::Virtual => Arc::new(VirtualClock::new()),
    }
}

fn spawn_job(
    settings: RunSettings,
    clock: Arc<dyn Clock>,
    control: Arc<StreamControl>,
) -> std::thread::JoinHandle<anyhow::Result<RunReport>> {
    std::thread::Builder::new()
        .name("rigbridge-stream".into())
        .spawn(move || {
            let mut link = loopback_twin(&settings)?;
            let report = run_job(&settings, &mut link, clock.as_ref(), &mut (), &control)?;
            Ok(report)
        })
        .expect("the OS can start one thread")
}

/// Waits for the job, drawing progress and turning SIGINT/SIGTERM into a stop.
async fn supervise(control: &StreamControl, job: &std::thread::JoinHandle<anyhow::Result<RunReport>>) -> anyhow::Result<()> {
    let bar = ProgressBar::new(1000).with_style(
        ProgressStyle::with_template("{bar:40} {percent:>3}% {msg}").expect("static template"),
    );
    let mut terminate = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())?;
    let mut tick = tokio::time::interval(Duration::from_millis(100));
    while !job.is_finished() {
        tokio::select! {
            _ = tokio::signal::ctrl_c() => stop(control, &bar),
            _ = terminate.recv() => stop(control, &bar),
            _ = tick.tick() => {
                bar.set_position((control.progress() * 1000.0) as u64);
                bar.set_message(format!("{} cycles", control.cycles()));
            }
        }
    }
    bar.finish_and_clear();
    Ok(())
}

fn stop(control: &StreamControl, bar: &ProgressBar) {
    bar.println("stopping: bringing the rig to rest along its path");
    control.stop();
}

pub fn run(args: RunArgs) -> anyhow::Result<ExitCode> {
    let settings = load_run_settings(&args.config).context("cannot load run settings")?;
    let control = Arc::new(StreamControl::default());
    let job = spawn_job(settings, make_clock(args.clock), control.clone());
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?
        .block_on(supervise(&control, &job))?;
    let report = job.join().map_err(|_| anyhow::anyhow!("the streaming thread panicked"))??;
    print_summary(&report);
    if let Some(path) = &args.report {
        let json = serde_json::to_string_pretty(&report)?;
        std::fs::write(path, json + "\n").with_context(|| format!("cannot write report {}", path.display()))?;
    }
    Ok(match report.stream.outcome {
        Outcome::Completed => ExitCode::SUCCESS,
        Outcome::Stopped => ExitCode::from(130),
        _ => ExitCode::from(3),
    })
}

fn print_summary(report: &RunReport) {
    let s = &report.stream;
    println!(
        "{} on {} over {}: {:?} after {} cycles ({:.2} s at {} Hz, {} clock)",
        report.job, report.rig, s.link, s.outcome, s.cycles, s.duration_s, report.rate_hz, report.clock
    );
    println!(
        "  missed cycles {}, limit violations {}, feedback timeouts {}",
        s.missed_cycles, s.limit_violations, s.feedback_timeouts
    );
    println!(
        "  jitter p50 {:.0} us, p99 {:.0} us, max {:.0} us; latency p99 {:.0} us; tracking error max {:.3} deg",
        s.jitter_p50_us, s.jitter_p99_us, s.jitter_max_us, s.latency_p99_us, s.tracking_error_max_deg
    );
    if let Some(fault) = &s.fault {
        println!("  fault: {fault}");
    }
}
