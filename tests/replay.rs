//! `rigbridge replay` as a job like any other, checked from the logs alone: a 100 Hz log
//! into a 250 Hz stream, a truncated log that must end at rest, `--speed 0.5`, and a replay
//! over TCP to `rigbridge twin --listen` started away from the log's start.

use crate::common;

use common::cli::{read_json, rigbridge};
use common::runlog::resumptions;
use common::twin::{TwinProcess, listen_command, start_listening};
use common::{irb120, repo_path};
use rigbridge::log::{RunLog, read_log};
use std::path::{Path, PathBuf};
use std::process::Output;

/// Rounding slack on the limit checks below, the same as the rig's.
const SLACK: f64 = 1e-9;

fn scratch(name: &str) -> PathBuf {
    common::scratch_file("replay", name)
}

fn run(args: &[&str]) -> Output {
    rigbridge().args(args).output().unwrap()
}

fn text(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).into_owned()
}

fn succeeded(output: &Output) {
    assert!(
        output.status.success(),
        "{}{}",
        text(&output.stdout),
        text(&output.stderr)
    );
}

/// A copy of the default run settings with `edit` applied, next to it (the rig path is
/// relative to the file).
fn write_config(name: &str, edit: impl Fn(String) -> String) -> ConfigFile {
    let original = common::with_absolute_cell(
        &std::fs::read_to_string(repo_path("config/rigbridge.toml")).unwrap(),
    );
    let path = repo_path("config").join(format!(".test-replay-{}-{name}", std::process::id()));
    std::fs::write(&path, edit(original)).unwrap();
    ConfigFile(path)
}

struct ConfigFile(PathBuf);

impl Drop for ConfigFile {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.0);
    }
}

fn record_run(name: &str, config: Option<&Path>) -> PathBuf {
    let log = scratch(name);
    let mut args = vec!["run", "--clock", "virtual", "--log", log.to_str().unwrap()];
    if let Some(config) = config {
        args.extend(["--config", config.to_str().unwrap()]);
    }
    succeeded(&run(&args));
    log
}

/// `rigbridge replay SOURCE` with `args`, recording to and reporting in scratch files named
/// after `name`; it must succeed and complete. Returns the report and the recorded log.
fn replay_completes(source: &Path, args: &[&str], name: &str) -> (serde_json::Value, RunLog) {
    let again = scratch(&format!("{name}-again.mcap"));
    let json = scratch(&format!("{name}.json"));
    let mut all = vec!["replay", source.to_str().unwrap()];
    all.extend_from_slice(args);
    all.extend(["--record", again.to_str().unwrap()]);
    all.extend(["--report", json.to_str().unwrap()]);
    succeeded(&run(&all));
    let report = read_json(&json);
    assert_eq!(report["outcome"], "completed", "{report}");
    (report, read_log(&again).unwrap())
}

/// Checks every command the log holds against the IRB 120's limits from the log alone,
/// starting from the recorded start at rest (and, after a resumption, from the held
/// position it names): inside the limits, each step within one cycle's travel at max
/// speed, velocities within max speed, and the positions' second difference within max
/// acceleration x period^2. Returns the largest step as a share of one cycle's travel.
fn assert_within_limits(log: &RunLog) -> f64 {
    let rig = irb120();
    let period = log.metadata["period_s"].as_f64().unwrap();
    let start: Vec<f64> = serde_json::from_value(log.metadata["start"].clone()).unwrap();
    let mut resumed = resumptions(log).into_iter().peekable();
    let mut before = start.clone();
    let mut previous = start;
    let mut largest_step = 0.0_f64;
    for command in &log.commands {
        let seq = command.seq;
        if let Some((_, actual)) = resumed.next_if(|(t, _)| command.t > *t + 1e-9) {
            before = actual.clone();
            previous = actual;
        }
        assert_eq!(rig.first_limit_violation(&command.positions), None, "{seq}");
        for (axis, joint) in rig.joints.iter().enumerate() {
            let limits = joint.limits;
            let q = command.positions[axis];
            let step = (q - previous[axis]).abs();
            let travel = limits.max_speed * period;
            largest_step = largest_step.max(step / travel);
            assert!(step <= travel * (1.0 + SLACK), "seq {seq} {}", joint.name);
            assert!(command.velocities[axis].abs() <= limits.max_speed * (1.0 + SLACK));
            let second = (q - 2.0 * previous[axis] + before[axis]).abs();
            let max_second = limits.max_acceleration * period * period;
            assert!(
                second <= max_second * (1.0 + SLACK),
                "seq {seq} {}: {second} > {max_second}",
                joint.name
            );
        }
        before = std::mem::replace(&mut previous, command.positions.clone());
    }
    largest_step
}

#[test]
fn a_100_hz_log_replays_into_a_250_hz_stream_one_cycle_step_at_a_time() {
    let config = write_config("100hz.toml", |t| {
        t.replace("rate_hz = 250.0", "rate_hz = 100.0")
    });
    let recorded = record_run("100hz.mcap", Some(&config.0));
    let source = read_log(&recorded).unwrap();
    assert_eq!(source.metadata["period_s"], 0.01);
    let (report, replayed) = replay_completes(&recorded, &["--clock", "virtual"], "100hz");
    assert_eq!(report["resampled"], true);
    assert_eq!(replayed.metadata["period_s"], 0.004);
    let largest = assert_within_limits(&replayed);
    assert!(largest > 0.1, "the replay moved: {largest}");
    // Same motion in time: 2.5 cycles of the stream for each recorded command.
    let expected = source.commands.len() as f64 * 2.5;
    let got = replayed.commands.len() as f64;
    assert!((got - expected).abs() <= 10.0, "{got} cycles, {expected}");
    let (last, end) = (
        &source.commands.last().unwrap().positions,
        &replayed.commands.last().unwrap().positions,
    );
    for (a, b) in last.iter().zip(end) {
        assert!((a - b).abs() < 1e-9, "ends where the recording ended");
    }
}

#[test]
fn a_truncated_log_ends_with_a_stop_ramp_to_rest_within_acceleration() {
    let recorded = record_run("whole.mcap", None);
    let bytes = std::fs::read(&recorded).unwrap();
    let cut = scratch("cut.mcap");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
    let source = read_log(&cut).unwrap();
    assert!(source.truncated);
    let last = source.commands.last().unwrap();
    let moving = last.velocities.iter().map(|v| v.abs()).fold(0.0, f64::max);
    assert!(moving > 0.05, "the cut falls mid-motion: {moving} rad/s");
    let (report, replayed) = replay_completes(&cut, &["--clock", "virtual"], "cut");
    assert!(
        report["stop_ramp_samples"].as_u64().unwrap() > 1,
        "{report}"
    );
    assert_within_limits(&replayed);
    let n = replayed.commands.len();
    assert!(n > source.commands.len());
    let (end, before) = (&replayed.commands[n - 1], &replayed.commands[n - 2]);
    assert!(
        end.velocities.iter().all(|v| *v == 0.0),
        "{:?}",
        end.velocities
    );
    assert_eq!(end.positions, before.positions, "at rest: no last step");
    for (a, b) in source.commands.iter().zip(&replayed.commands) {
        assert_eq!(a.positions, b.positions, "the recorded part unchanged");
    }
}

#[test]
fn half_speed_takes_twice_as_long_at_the_same_rate() {
    let recorded = record_run("speed.mcap", None);
    let mut cycles = Vec::new();
    for speed in ["1", "0.5"] {
        let (report, replayed) = replay_completes(
            &recorded,
            &["--clock", "virtual", "--speed", speed],
            &format!("speed-{speed}"),
        );
        assert_eq!(report["rate_hz"], 250.0);
        assert_eq!(replayed.metadata["period_s"], 0.004);
        assert_within_limits(&replayed);
        cycles.push(replayed.commands.len() as f64);
    }
    let recorded_cycles = read_log(&recorded).unwrap().commands.len() as f64;
    assert!((cycles[0] - recorded_cycles).abs() <= 3.0, "{cycles:?}");
    assert!(
        (cycles[1] - 2.0 * recorded_cycles).abs() <= 6.0,
        "{cycles:?} for {recorded_cycles} recorded"
    );
}

#[test]
fn a_speed_that_breaks_an_acceleration_limit_is_refused_naming_the_axis() {
    let recorded = record_run("fast.mcap", None);
    let output = run(&[
        "replay",
        recorded.to_str().unwrap(),
        "--clock",
        "virtual",
        "--speed",
        "1.3",
    ]);
    assert_eq!(output.status.code(), Some(1));
    let stderr = text(&output.stderr);
    assert!(
        stderr.contains("above its max acceleration") && stderr.contains("joint_"),
        "{stderr}"
    );
}

/// `rigbridge twin --listen` on a free port with `config`.
fn start_twin(config: &Path) -> TwinProcess {
    start_listening(
        listen_command("tcp://127.0.0.1:0")
            .arg("--config")
            .arg(config),
    )
}

#[test]
fn a_replay_over_tcp_starts_where_the_twin_holds_and_completes() {
    let recorded = record_run("tcp-source.mcap", None);
    let bytes = std::fs::read(&recorded).unwrap();
    let cut = scratch("tcp-cut.mcap");
    // A shorter log keeps the real-time run short; it also ends mid-motion.
    std::fs::write(&cut, &bytes[..bytes.len() / 3]).unwrap();
    let elsewhere = write_config("elsewhere.toml", |t| {
        t.replace(
            "initial_deg = [0.0, 0.0, 0.0, 0.0, 30.0, 0.0]",
            "initial_deg = [20.0, -10.0, 5.0, 0.0, 45.0, 0.0]",
        )
    });
    let twin = start_twin(&elsewhere.0);
    let address = twin.address.clone();
    let (report, replayed) = replay_completes(&cut, &["--link", &address], "tcp");
    assert!(report["approach_samples"].as_u64().unwrap() > 0, "{report}");
    assert!(report["link"].as_str().unwrap().starts_with("tcp://"));
    let start: Vec<f64> = serde_json::from_value(replayed.metadata["start"].clone()).unwrap();
    for (got, deg) in start.iter().zip([20.0_f64, -10.0, 5.0, 0.0, 45.0, 0.0]) {
        assert!((got - deg.to_radians()).abs() < 1e-3, "held at {start:?}");
    }
    assert_within_limits(&replayed);
}

/// A log with `period_s` in its metadata and three commands 4 ms apart from the shipped
/// settings' start.
fn log_with_period(period_s: serde_json::Value) -> RunLog {
    let start = vec![0.0, 0.0, 0.0, 0.0, 30f64.to_radians(), 0.0];
    RunLog {
        rig: "irb120".into(),
        joint_names: irb120().joint_names().map(String::from).collect(),
        metadata: serde_json::json!({ "start": start, "period_s": period_s }),
        commands: (1..=3)
            .map(|seq| rigbridge::log::LoggedSample {
                seq,
                t: f64::from(seq) * 0.004,
                positions: start.clone(),
                velocities: vec![0.0; 6],
                late_us: None,
            })
            .collect(),
        ..rigbridge::log::RunLog::default()
    }
}

/// Issue 19: the log's `period_s` is read once, as a time; one that is no positive period
/// is refused naming the key and value (never a panic), and the recorded period comes back
/// as the same seconds the log holds.
#[test]
fn a_log_period_that_is_no_time_is_refused_naming_key_and_value() {
    use rigbridge::daemon::replay::replay_trajectory;
    let settings =
        rigbridge::daemon::config::load_run_settings(&repo_path("config/rigbridge.toml")).unwrap();
    let replayed = replay_trajectory(&log_with_period(0.004.into()), &settings, 1.0).unwrap();
    assert_eq!(
        replayed.recorded_period,
        std::time::Duration::from_millis(4)
    );
    assert_eq!(
        replayed.recorded_period.as_secs_f64().to_bits(),
        0.004f64.to_bits()
    );
    for (value, shown) in [(-0.004, "-0.004"), (0.0, "= 0 "), (1e300, "= 1000000000")] {
        let error = replay_trajectory(&log_with_period(value.into()), &settings, 1.0)
            .map(|_| ())
            .unwrap_err();
        let error = rigbridge::daemon::error_chain(&error);
        assert!(
            error.contains("`period_s`") && error.contains(shown),
            "{value}: {error}"
        );
    }
}
