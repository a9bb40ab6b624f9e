//! `rigbridge run`: one job against the twin, with a progress bar, Ctrl-C handling (the
//! rig is brought to rest along its path, then the log is closed and the report written),
//! and a summary at the end. A report is written whole or not at all: to a temporary file
//! beside it, then renamed over it, so a full disk leaves the previous report (never an
//! empty one) and an error naming the path and cause.

use anyhow::Context;
use clap::{Args, ValueEnum};
use indicatif::{ProgressBar, ProgressStyle};
use rigbridge::clock::{Clock, VirtualClock, WallClock};
use rigbridge::daemon::config::{RunSettings, load_run_settings};
use rigbridge::daemon::{DaemonError, RunReport, open_link, plan_for, stream_planned_with};
use rigbridge::device::LinkSpec;
use rigbridge::ros2::{PublishedRig, RigNode};
use rigbridge::stream::{Outcome, StreamControl};
use rigbridge::view::{LiveSample, LiveSink, LiveSlot};
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
    #[arg(long, env = "RIGBRIDGE_CONFIG", default_value = rigbridge::rig::shipped::DEFAULT_RUN_SETTINGS)]
    config: PathBuf,
    /// Where to stream (overrides the config's `[stream] link`); `--help` lists every form.
    #[arg(long, long_help = format!("Where to stream (overrides the config's `[stream] link`): {}. egm:// binds as an ABB EGM sensor, answering only the robot named after ?robot=, streaming joints or, with mode=pose, tool poses (docs/egm.md); dynamixel:// and canopen:// drive one servo or drive per axis (docs/dynamixel.md, docs/canopen.md)", rigbridge::device::link_forms()))]
    link: Option<String>,
    /// Record the run to this MCAP file (default: runs/run-<unix time>-<pid>.mcap).
    #[arg(long)]
    log: Option<PathBuf>,
    /// Write the run report (JSON) here.
    #[arg(long)]
    report: Option<PathBuf>,
    /// Whose time the cycles run on: wall (real time) or virtual (the same cycles without
    /// waiting).
    #[arg(long, value_enum, default_value = "wall")]
    clock: ClockChoice,
    /// Publish the rig's joint states to ROS 2 over Zenoh through this router or peer
    /// (`tcp/HOST:PORT`); overrides `[ros2] zenoh_connect`.
    #[arg(long, value_name = "ENDPOINT", value_parser = parse_zenoh_endpoint)]
    zenoh_connect: Option<String>,
}

/// `--zenoh-connect`'s value, checked like `[ros2] zenoh_connect`.
pub fn parse_zenoh_endpoint(text: &str) -> anyhow::Result<String> {
    match rigbridge::ros2::endpoint_problem(text) {
        None => Ok(text.to_string()),
        Some(reason) => Err(anyhow::anyhow!("`{text}` {reason}")),
    }
}

pub fn make_clock(choice: ClockChoice) -> Arc<dyn Clock> {
    match choice {
        ClockChoice::Wall => Arc::new(WallClock::new()),
        ClockChoice::Virtual => Arc::new(VirtualClock::new()),
    }
}

/// The default log path, unique per run: the time in seconds orders runs, the process id
/// keeps two runs started in the same second apart (the recorder never overwrites a file).
pub fn default_log_path(prefix: &str) -> PathBuf {
    let seconds = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    let process = std::process::id();
    PathBuf::from("runs").join(format!("{prefix}-{seconds}-{process}.mcap"))
}

pub fn spawn_streaming<T: Send + 'static>(
    work: impl FnOnce() -> anyhow::Result<T> + Send + 'static,
) -> anyhow::Result<std::thread::JoinHandle<anyhow::Result<T>>> {
    Ok(std::thread::Builder::new()
        .name("rigbridge-stream".into())
        .spawn(move || {
            if let Err(e) = rigbridge::stream::raise_priority(rigbridge::realtime::CYCLE_PRIORITY) {
                eprintln!("note: streaming at normal priority (real-time scheduling refused: {e})");
            }
            work()
        })?)
}

/// Waits for the streaming thread, drawing progress and turning SIGINT/SIGTERM into a stop.
pub async fn supervise<T>(
    control: &StreamControl,
    job: &std::thread::JoinHandle<anyhow::Result<T>>,
) -> anyhow::Result<()> {
    let bar = ProgressBar::new(1000).with_style(
        ProgressStyle::with_template("{bar:40} {percent:>3}% {msg}").expect("static template"),
    );
    // Both signal streams live across the loop: a `ctrl_c()` future made anew each turn
    // misses a SIGINT delivered in the same turn as the tick (the tick wins the select, the
    // dropped future's notice goes with it, the new one subscribes after it), and the job
    // ran on after a Ctrl-C (`tests/faults.rs`, a paint run left running).
    use tokio::signal::unix::{SignalKind, signal};
    let mut interrupt = signal(SignalKind::interrupt())?;
    let mut terminate = signal(SignalKind::terminate())?;
    let mut tick = tokio::time::interval(Duration::from_millis(100));
    while !job.is_finished() {
        tokio::select! {
            _ = interrupt.recv() => stop(control, &bar),
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
    let settings =
        load_run_settings(&args.config).with_context(|| super::settings_context(&args.config))?;
    let log = args.log.clone().unwrap_or_else(|| default_log_path("run"));
    if let Some(dir) = log.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    }
    let control = Arc::new(StreamControl::default());
    let clock = make_clock(args.clock);
    let job_control = control.clone();
    let job_log = log.clone();
    let spec = link_spec(&args, &settings)?;
    let slot = Arc::new(LiveSlot::new(LiveSample::at_rest(&settings.initial())));
    // Asked before any thread is pinned: the process's CPUs are remembered then.
    let streaming_cpu = rigbridge::realtime::streaming_cpu();
    let rig_name = settings.rig.name.clone();
    let ros2 = ros2_node(
        &settings,
        args.zenoh_connect.as_deref(),
        &slot,
        spec == LinkSpec::Loopback,
    )?;
    // With a ROS 2 node, the cycle keeps to the CPU the node's threads keep off.
    let cpu = ros2.as_ref().and(streaming_cpu);
    let job = spawn_streaming(move || {
        if let Some(cpu) = cpu
            && let Err(e) = rigbridge::realtime::pin_to(cpu)
        {
            eprintln!("note: streaming on any CPU (cannot keep to CPU {cpu}: {e})");
        }
        let mut link = open_link(&spec, &settings)?;
        // A device-paced link (EGM) brings the clock the cycle must follow.
        let clock = link.pacing().unwrap_or(clock);
        let job = settings.config.job.clone();
        let planned = match plan_for(&settings, &job, link.as_mut(), clock.as_ref(), &job_control) {
            Err(DaemonError::Halted(halted)) => {
                let name = job.name();
                return Ok(halted.report(&settings, &name, link.as_ref(), clock.as_ref()));
            }
            planned => planned?,
        };
        // The cycle offers each state to the slot the ROS 2 node publishes from.
        let mut live = LiveSink::new(&slot, settings.config.stream.rate_hz.round() as u64);
        Ok(stream_planned_with(
            &settings,
            &planned,
            link.as_mut(),
            clock.as_ref(),
            Some(&job_log),
            &job_control,
            rigbridge::daemon::Sinks {
                live: &mut live,
                actions: None,
                executor: None,
            },
        )?)
    })?;
    let report = wait(&control, job);
    if let Some(node) = ros2 {
        say!(
            "  ros2: {} joint states published on {}",
            node.published(),
            node.joint_states_at(&rig_name)
        );
    }
    finish(report, &args, &log)
}

/// The link `--link` names, else the settings' `[stream] link`; a virtual clock only with
/// the loopback twin.
fn link_spec(args: &RunArgs, settings: &RunSettings) -> anyhow::Result<LinkSpec> {
    let text = args.link.as_deref().unwrap_or(&settings.config.stream.link);
    let spec: LinkSpec = text.parse()?;
    // A real controller keeps real time: a virtual clock would stream faster than it runs.
    anyhow::ensure!(
        matches!(args.clock, ClockChoice::Wall) || spec == LinkSpec::Loopback,
        "--clock virtual needs the loopback twin: a controller behind --link {text} runs in real time"
    );
    Ok(spec)
}

/// Prints the summary and writes the report (a refusal before motion gets one too); the
/// exit code follows the outcome.
fn finish(
    report: anyhow::Result<rigbridge::daemon::RunReport>,
    args: &RunArgs,
    log: &std::path::Path,
) -> anyhow::Result<ExitCode> {
    let report = match report {
        Ok(report) => report,
        Err(error) => {
            // Refused before motion: the report still says so.
            let refused = serde_json::json!({
                "outcome": "refused",
                "fault": format!("{error:#}"),
                "cycles": 0,
            });
            write_report(args.report.as_deref(), &refused)?;
            return Err(error);
        }
    };
    print_summary(&report)?;
    say!("  log: {}", log.display());
    if let Some(failed) = &report.log_error {
        say!(
            "  log failed at job time {:.3} s ({}): {}",
            failed.at_s,
            if failed.stopped_job {
                "the job was brought to rest"
            } else {
                "the job went on"
            },
            failed.error
        );
    }
    write_report(args.report.as_deref(), &report)?;
    Ok(run_exit_code(&report))
}

/// The exit code of a run whose log failed, when its outcome alone would say success or
/// an operator's stop: the run's record is incomplete (docs/logs.md). Not 4, which `gait`
/// gives a walk that missed its figures.
pub const EXIT_LOG_FAILED: u8 = 5;

/// [`exit_code`] of the outcome, but [`EXIT_LOG_FAILED`] for a completed or stopped run
/// whose log failed (`run`, `replay`, `paint`).
pub fn run_exit_code(report: &RunReport) -> ExitCode {
    match (report.stream.outcome, &report.log_error) {
        (Outcome::Completed | Outcome::Stopped, Some(_)) => ExitCode::from(EXIT_LOG_FAILED),
        (outcome, _) => exit_code(outcome),
    }
}

/// The rig's ROS 2 node when the settings have `[ros2]` or `--zenoh-connect` says where to
/// connect.
fn ros2_node(
    settings: &RunSettings,
    endpoint: Option<&str>,
    slot: &Arc<LiveSlot>,
    known_at_rest: bool,
) -> anyhow::Result<Option<RigNode>> {
    let Some(ros2) = settings.config.ros2.settings(endpoint) else {
        return Ok(None);
    };
    let rig = PublishedRig {
        name: settings.rig.name.clone(),
        joints: settings.rig.joint_names().map(String::from).collect(),
        robot: Arc::new(rigbridge::log::RobotDescription::generated(
            &settings.rig,
            &settings.cell,
        )),
        mount: settings.cell.mount,
    };
    let node = rigbridge::ros2::start_node(&ros2, rig, slot.clone(), known_at_rest, None, None)
        .with_context(|| format!("cannot join ROS 2 over {}", ros2.middleware))?;
    eprintln!(
        "ros2: node /{}/{} publishing {} over {}",
        settings.rig.name,
        rigbridge::ros2::graph::NODE_NAME,
        node.joint_states_at(&settings.rig.name),
        ros2.middleware
    );
    Ok(Some(node))
}

pub fn exit_code(outcome: Outcome) -> ExitCode {
    match outcome {
        Outcome::Completed => ExitCode::SUCCESS,
        Outcome::Stopped => ExitCode::from(130),
        _ => ExitCode::from(3),
    }
}

/// Waits for the streaming thread (progress, signals) and returns what it produced.
pub fn wait<T>(
    control: &StreamControl,
    job: std::thread::JoinHandle<anyhow::Result<T>>,
) -> anyhow::Result<T> {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?
        .block_on(supervise(control, &job))?;
    job.join()
        .map_err(|_| anyhow::anyhow!("the streaming thread panicked"))?
}

/// Writes `report` as JSON to `path`, if given, whole or not at all: to a temporary file in
/// the same directory, synced, then renamed over `path`. When any step fails the temporary
/// file is removed, whatever was at `path` stays as it was, and the error names the path
/// and the cause.
pub fn write_report(
    path: Option<&std::path::Path>,
    report: &impl serde::Serialize,
) -> anyhow::Result<()> {
    if let Some(path) = path {
        let json = serde_json::to_string_pretty(report)? + "\n";
        let temporary = temporary_beside(path);
        let written = write_synced(&temporary, json.as_bytes())
            .and_then(|()| std::fs::rename(&temporary, path));
        if let Err(cause) = written {
            let _ = std::fs::remove_file(&temporary);
            return Err(cause).with_context(|| {
                format!(
                    "cannot write report {} (any earlier report there is left as it was)",
                    path.display()
                )
            });
        }
    }
    Ok(())
}

/// A name in `path`'s directory no other run uses at the same time (the process id), and
/// hidden, for the report before it is renamed to `path`.
fn temporary_beside(path: &std::path::Path) -> PathBuf {
    let name = path
        .file_name()
        .map_or_else(|| "report".into(), |n| n.to_string_lossy().into_owned());
    path.with_file_name(format!(".{name}.{}.tmp", std::process::id()))
}

/// Creates `path` with `bytes`, on disk before it returns (a rename after a crash must not
/// reveal an empty file).
fn write_synced(path: &std::path::Path, bytes: &[u8]) -> std::io::Result<()> {
    use std::io::Write;
    let mut file = std::fs::File::create(path)?;
    file.write_all(bytes)?;
    file.sync_all()
}

fn print_summary(report: &RunReport) -> anyhow::Result<()> {
    print_stream_summary(
        &report.job,
        &report.rig,
        report.rate_hz,
        report.clock,
        &report.stream,
    )?;
    if let Some(times) = &report.cycle_times {
        print_cycle_times(times, report.measured_cycle_times.as_ref())?;
    }
    if let Some(parts) = &report.parts {
        print_parts(parts)?;
    }
    for warning in report.warnings() {
        say!("  warning: {warning}");
    }
    Ok(())
}

/// The twin's judgement of the cell's parts: the tally, the worst placement, the measured
/// time per part, and every part that was not placed.
fn print_parts(parts: &rigbridge::twin::CellJudgement) -> anyhow::Result<()> {
    say!(
        "  parts (the twin's judge): {} of {} placed within {} mm and {} deg; {} dropped, {} never picked, {} still held; {} with collisions; {} struck at rest by the robot",
        parts.placed,
        parts.parts,
        parts.placed_within_mm,
        parts.placed_within_deg,
        parts.dropped,
        parts.never_picked,
        parts.carried,
        parts.collisions,
        parts.struck
    );
    say!(
        "    worst placed: {:.4} mm, {:.4} deg from the goal",
        parts.worst_position_error_mm,
        parts.worst_orientation_error_deg
    );
    let times: Vec<String> = parts
        .cycle_times_s
        .iter()
        .map(|t| format!("{t:.3}"))
        .collect();
    say!(
        "    cycle time per part (measured, pick to pick, s): {}",
        times.join(", ")
    );
    for part in parts.per_part.iter().filter(|p| p.struck_cycles > 0) {
        say!(
            "    {} struck at rest by {} ({:.2} mm deep, {} cycles)",
            part.name,
            part.struck_by.as_deref().unwrap_or("the robot"),
            part.struck_depth_mm,
            part.struck_cycles
        );
    }
    for part in parts.per_part.iter().filter(|p| p.state != "placed") {
        say!(
            "    {} ({} to {}): {}, {:.3} mm and {:.3} deg from it{}",
            part.name,
            part.state,
            part.goal,
            part.state,
            part.position_error_mm,
            part.orientation_error_deg,
            part.collided_with
                .as_deref()
                .map(|other| format!(
                    ", collided with {other} ({:.2} mm deep)",
                    part.collision_depth_mm
                ))
                .unwrap_or_default()
        );
    }
    Ok(())
}

/// A program's cycle time per step, each repeat's passes under it: planned, and measured
/// as the stream passed them (`not reached` for a step the job ended before).
fn print_cycle_times(
    times: &rigbridge::job::CycleTimes,
    measured: Option<&rigbridge::job::CycleTimes>,
) -> anyhow::Result<()> {
    let shown = |t: Option<f64>| t.map_or("not reached".to_string(), |t| format!("{t:.3} s"));
    say!("  cycle times (planned | measured on the clock, pauses and waits included):");
    for step in &times.steps {
        let took = measured
            .and_then(|m| m.steps.iter().find(|s| s.step == step.step))
            .map(|s| s.duration_s);
        say!(
            "    {} {}: {:.3} s | {}",
            step.step,
            step.what,
            step.duration_s,
            shown(took)
        );
        for lap in times.laps.iter().filter(|lap| lap.repeat == step.step) {
            let took = measured
                .and_then(|m| {
                    m.laps
                        .iter()
                        .find(|l| l.repeat == lap.repeat && l.index == lap.index)
                })
                .map(|l| l.duration_s);
            say!(
                "      pass {} ({}): {:.3} s | {}",
                lap.index,
                lap.target,
                lap.duration_s,
                shown(took)
            );
        }
    }
    Ok(())
}

pub fn print_stream_summary(
    job: &str,
    rig: &str,
    rate_hz: f64,
    clock: &str,
    s: &rigbridge::stream::StreamReport,
) -> anyhow::Result<()> {
    say!(
        "{} on {} over {}: {} after {} cycles ({:.2} s at {} Hz, {} clock)",
        job,
        rig,
        s.link,
        s.outcome,
        s.cycles,
        s.duration_s,
        rate_hz,
        clock
    );
    say!(
        "  missed cycles {}, limit violations {}, feedback timeouts {}",
        s.missed_cycles,
        s.limit_violations,
        s.feedback_timeouts
    );
    // The jitter in the words `log info` and `log plot` use for the run's log.
    say!(
        "  {}; latency p99 {:.0} us; tracking error max {:.3} deg",
        s.jitter(),
        s.latency_p99_us,
        s.tracking_error_max_deg
    );
    say!(
        "  link: {} frames sent, {} received, {} CRC errors, {} gaps, {} duplicates, {} reconnects",
        s.counters.frames_sent,
        s.counters.frames_received,
        s.counters.crc_errors,
        s.counters.gaps,
        s.counters.duplicates,
        s.counters.reconnects
    );
    for (k, interruption) in s.interruptions.iter().enumerate() {
        say!(
            "  warning: interruption {} of {}: {} at {:.3} s ({}); {}",
            k + 1,
            s.interruptions.len(),
            interruption.outcome,
            interruption.at_s,
            interruption.why,
            interruption.then
        );
    }
    if let Some(fault) = &s.fault {
        say!("  fault: {fault}");
    }
    Ok(())
}
