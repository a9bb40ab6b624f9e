//! The daemon end to end, as a user runs it: `run` against the twin, the MCAP log checked
//! independently of the report, replay, Ctrl-C, SIGKILL, and bad input.

use crate::common;

use common::cli::{read_json, rigbridge, spawn_run};
use common::runlog::resumptions;
use common::{irb120, repo_path, wait_for_logged_commands};
use rigbridge::log::read_log;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::time::Duration;

/// A second of the default job's motion at 250 Hz: a job this far in is mid-motion.
const MID_JOB_COMMANDS: usize = 250;
/// Longer than the job takes to get there on a loaded machine.
const WAIT: Duration = Duration::from_secs(30);

fn scratch(name: &str) -> PathBuf {
    common::scratch_file("daemon", name)
}

fn run(args: &[&str]) -> Output {
    rigbridge().args(args).output().unwrap()
}

fn text(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).into_owned()
}

/// The default job run under the virtual clock, logged to the scratch file `name`; it must
/// succeed. Returns the log's path.
fn recorded_run(name: &str) -> PathBuf {
    let log = scratch(name);
    assert!(
        run(&["run", "--clock", "virtual", "--log", log.to_str().unwrap()])
            .status
            .success()
    );
    log
}

/// `rigbridge replay LOG --clock virtual` with `more` arguments.
fn replay(log: &Path, more: &[&str]) -> Output {
    let mut args = vec!["replay", log.to_str().unwrap(), "--clock", "virtual"];
    args.extend_from_slice(more);
    run(&args)
}

/// Every command in the log inside the limits and within max speed x period of the one
/// before, starting from the recorded start and, after a resumption (a stall on this
/// loaded machine, say), from the position the controller held: checked from the log alone.
fn assert_log_within_limits(path: &Path) -> usize {
    let rig = irb120();
    let log = read_log(path).unwrap();
    assert!(!log.truncated);
    let period = log.metadata["period_s"].as_f64().unwrap();
    let mut previous: Vec<f64> = serde_json::from_value(log.metadata["start"].clone()).unwrap();
    let resumes = resumptions(&log);
    let mut next_resume = 0;
    for command in &log.commands {
        while next_resume < resumes.len() && resumes[next_resume].0 < command.t {
            previous = resumes[next_resume].1.clone();
            next_resume += 1;
        }
        assert_eq!(
            rig.first_limit_violation(&command.positions),
            None,
            "seq {}",
            command.seq
        );
        for ((q, p), joint) in command.positions.iter().zip(&previous).zip(&rig.joints) {
            assert!(
                (q - p).abs() <= joint.limits.max_speed * period * (1.0 + 1e-9),
                "seq {}",
                command.seq
            );
        }
        for (v, joint) in command.velocities.iter().zip(&rig.joints) {
            assert!(v.abs() <= joint.limits.max_speed * (1.0 + 1e-9));
        }
        previous = command.positions.clone();
    }
    log.commands.len()
}

#[test]
fn the_main_command_runs_the_demo_and_logs_it_within_limits() {
    let log = scratch("main.mcap");
    let report = scratch("main.json");
    let output = run(&[
        "run",
        "--log",
        log.to_str().unwrap(),
        "--report",
        report.to_str().unwrap(),
    ]);
    assert!(
        output.status.success(),
        "{}{}",
        text(&output.stdout),
        text(&output.stderr)
    );
    let stdout = text(&output.stdout);
    assert!(
        stdout.contains(": completed after") && stdout.contains("limit violations 0"),
        "{stdout}"
    );
    let commands = assert_log_within_limits(&log);
    let report = read_json(&report);
    for key in [
        "cycles",
        "missed_cycles",
        "limit_violations",
        "jitter_p50_us",
        "jitter_p99_us",
        "latency_p99_us",
        "tracking_error_max_deg",
        "duration_s",
    ] {
        assert!(report[key].is_number(), "report lacks {key}: {report}");
    }
    assert_eq!(report["cycles"].as_u64().unwrap() as usize, commands);
    assert_eq!(report["limit_violations"], 0);
}

#[test]
fn replay_streams_exactly_the_recorded_targets() {
    let log = recorded_run("replay-source.mcap");
    let again = scratch("replay-again.mcap");
    let report = scratch("replay.json");
    let output = replay(
        &log,
        &[
            "--record",
            again.to_str().unwrap(),
            "--report",
            report.to_str().unwrap(),
        ],
    );
    assert!(output.status.success(), "{}", text(&output.stderr));
    let report = read_json(&report);
    assert_eq!(report["same_sequence"], true);
    assert!(
        report["max_deviation_from_recording_deg"].as_f64().unwrap() < 1e-9,
        "{report}"
    );
    let (first, second) = (read_log(&log).unwrap(), read_log(&again).unwrap());
    assert_eq!(first.commands.len(), second.commands.len());
    for (a, b) in first.commands.iter().zip(&second.commands) {
        assert_eq!((a.seq, &a.positions), (b.seq, &b.positions));
    }
}

#[test]
fn replay_refuses_a_speed_that_breaks_a_limit() {
    let log = recorded_run("fast.mcap");
    let output = replay(&log, &["--speed", "4"]);
    assert_eq!(output.status.code(), Some(1));
    assert!(
        text(&output.stderr).contains("above its max speed"),
        "{}",
        text(&output.stderr)
    );
}

fn write_config(name: &str, edit: impl Fn(String) -> String) -> PathBuf {
    let original = common::with_absolute_cell(
        &std::fs::read_to_string(repo_path("config/rigbridge.toml")).unwrap(),
    );
    let path = repo_path("config").join(format!(".test-{}-{name}", std::process::id()));
    std::fs::write(&path, edit(original)).unwrap();
    path
}

#[test]
fn an_unreachable_job_is_refused_before_motion_naming_the_target() {
    let config = write_config("far.toml", |t| {
        t.replace("wall_x_m = 0.45", "wall_x_m = 1.5")
    });
    let log = scratch("far.mcap");
    let output = run(&[
        "run",
        "--clock",
        "virtual",
        "--config",
        config.to_str().unwrap(),
        "--log",
        log.to_str().unwrap(),
    ]);
    std::fs::remove_file(&config).unwrap();
    assert_eq!(output.status.code(), Some(1));
    let stderr = text(&output.stderr);
    assert!(
        stderr.contains("job target 0") && stderr.contains("out of reach"),
        "{stderr}"
    );
    assert!(!log.exists(), "nothing was recorded because nothing moved");
}

#[test]
fn a_bad_config_names_file_key_and_value() {
    let config = write_config("bad.toml", |t| {
        t.replace("rate_hz = 250.0", "rate_hz = 5000.0")
    });
    let output = run(&["run", "--config", config.to_str().unwrap()]);
    std::fs::remove_file(&config).unwrap();
    assert_eq!(output.status.code(), Some(1));
    let stderr = text(&output.stderr);
    assert!(
        stderr.contains(".test-") && stderr.contains("stream.rate_hz") && stderr.contains("5000"),
        "{stderr}"
    );
}

#[test]
fn corrupt_or_truncated_logs_are_errors_not_panics() {
    let log = recorded_run("cut.mcap");
    let bytes = std::fs::read(&log).unwrap();
    let cut = scratch("cut-half.mcap");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
    let garbage = scratch("garbage.mcap");
    std::fs::write(&garbage, b"\x89MCAP0\r\n this is not a log at all").unwrap();
    for path in [&cut, &garbage] {
        for args in [vec!["log", "info"], vec!["replay", "--clock", "virtual"]] {
            let mut args = args.clone();
            args.insert(if args[0] == "log" { 2 } else { 1 }, path.to_str().unwrap());
            let output = run(&args);
            assert!(
                output.status.code().is_some_and(|c| c <= 3),
                "{args:?} crashed: {}",
                text(&output.stderr)
            );
            assert!(
                !text(&output.stderr).contains("panicked"),
                "{args:?}: {}",
                text(&output.stderr)
            );
        }
    }
}

#[test]
fn ctrl_c_brings_the_rig_to_rest_then_closes_log_and_report() {
    let (log, report) = (scratch("sigint.mcap"), scratch("sigint.json"));
    let child = spawn_run(&[], &log, &report);
    wait_for_logged_commands(&log, MID_JOB_COMMANDS, WAIT);
    send_signal(child.id(), "INT");
    let output = child.wait_with_output().unwrap();
    assert_eq!(output.status.code(), Some(130), "{}", text(&output.stderr));
    let report = read_json(&report);
    assert_eq!(report["outcome"], "stopped");
    assert_log_within_limits(&log);
    let last = read_log(&log).unwrap().commands.pop().unwrap();
    assert!(
        last.velocities.iter().all(|v| *v == 0.0),
        "at rest: {:?}",
        last.velocities
    );
}

#[test]
fn sigkill_leaves_a_log_readable_up_to_its_last_chunk() {
    let (log, report) = (scratch("sigkill.mcap"), scratch("sigkill.json"));
    let mut child = spawn_run(&[], &log, &report);
    let before_kill = wait_for_logged_commands(&log, MID_JOB_COMMANDS, WAIT);
    child.kill().unwrap();
    child.wait().unwrap();
    let run = read_log(&log).unwrap();
    assert!(run.truncated);
    assert!(
        run.commands.len() > 250 && run.commands.len() >= before_kill,
        "only {} commands survived, {before_kill} were readable before the kill",
        run.commands.len()
    );
    let info = self::run(&["log", "info", log.to_str().unwrap()]);
    assert!(info.status.success(), "{}", text(&info.stderr));
}

/// Sends a signal with the system's `kill`, keeping the test free of unsafe code.
fn send_signal(pid: u32, signal: &str) {
    let status = Command::new("kill")
        .args([&format!("-{signal}"), &pid.to_string()])
        .status()
        .unwrap();
    assert!(status.success());
}
