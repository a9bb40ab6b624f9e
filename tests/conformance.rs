//! Conformance: the bridge against a strict controller written from `docs/protocol.md`
//! alone (`tests/peers/doc_controller.py`, Python standard library only), over TCP.
//!
//! The controller checks every target on the wire integers (6.6), counts what it drops,
//! and writes a JSON summary when the bridge disconnects; the assertions below read that
//! summary (what the controller saw), the bridge's exit code, its stderr and its report.
//!
//! The last two tests run a `program` job with I/O steps (protocol version 3, 6.10) against
//! the controller as version 3 (completes, outputs recorded in order) and as version 2
//! (refused before motion, naming the version).
//!
//! Needs `python3` (3.11, for `tomllib`); without it every test here says it skips.

use crate::common;

use serde_json::Value;
use std::io::{BufRead, BufReader};
use std::path::PathBuf;
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::Mutex;
use std::sync::mpsc;
use std::time::{Duration, Instant};

/// One run at a time: the strict run is on the wall clock and the machines are small.
static SERIAL: Mutex<()> = Mutex::new(());

const CYCLE_US: i64 = 4000;

fn manifest_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// `Some(reason)` when python3 (with `tomllib`) is not there.
fn python_missing() -> Option<String> {
    match Command::new("python3")
        .args(["-c", "import tomllib, zlib, selectors"])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
    {
        Ok(s) if s.success() => None,
        Ok(s) => Some(format!(
            "python3 has no tomllib (needs 3.11 or later): exit {s}"
        )),
        Err(e) => Some(format!("python3 not found: {e}")),
    }
}

macro_rules! skip_without_python {
    ($test:expr) => {
        if let Some(why) = python_missing() {
            println!("conformance::{}: skipping: {why}", $test);
            return;
        }
    };
}

struct TempDir(PathBuf);

impl TempDir {
    fn new(name: &str) -> TempDir {
        let path = std::env::temp_dir().join(format!(
            "rigbridge-conformance-{}-{name}",
            std::process::id()
        ));
        let _ = std::fs::remove_dir_all(&path);
        std::fs::create_dir_all(&path).unwrap();
        TempDir(path)
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        if !std::thread::panicking() {
            let _ = std::fs::remove_dir_all(&self.0);
        } else {
            eprintln!("conformance: files kept in {}", self.0.display());
        }
    }
}

/// Waits for `child` to exit, up to `limit`; kills it past that.
fn wait_for(child: &mut Child, limit: Duration, what: &str) -> ExitStatus {
    let start = Instant::now();
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            return status;
        }
        if start.elapsed() > limit {
            let _ = child.kill();
            let _ = child.wait();
            panic!("{what} still running after {limit:?}: killed");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

struct Outcome {
    bridge: ExitStatus,
    /// The bridge's stderr and stdout.
    bridge_text: String,
    /// The bridge's report, when it wrote one.
    report: Option<Value>,
    /// The controller's summary.
    summary: Value,
    controller_log: String,
    /// `resumed` events in the bridge's log.
    resumes: i64,
}

impl Outcome {
    /// Everything the bridge said: stderr, stdout and the report.
    fn said(&self) -> String {
        let mut s = self.bridge_text.clone();
        if let Some(r) = &self.report {
            s.push('\n');
            s.push_str(&r.to_string());
        }
        s
    }

    fn outcome(&self) -> Option<&str> {
        self.report.as_ref()?.get("outcome")?.as_str()
    }

    fn context(&self) -> String {
        format!(
            "bridge: {}\n{}\nreport: {}\ncontroller summary: {}\ncontroller log:\n{}",
            self.bridge,
            self.bridge_text,
            self.report
                .as_ref()
                .map(|r| r.to_string())
                .unwrap_or_else(|| "(none)".into()),
            self.summary,
            self.controller_log
        )
    }

    fn count(&self, key: &str) -> i64 {
        self.summary[key]
            .as_i64()
            .unwrap_or_else(|| panic!("summary has no integer {key}: {}", self.summary))
    }
}

/// Starts the controller with `controller_args`, runs `rigbridge run` against it (default
/// job, wall clock) and collects what both said.
fn run_against(name: &str, controller_args: &[&str], bridge_limit: Duration) -> Outcome {
    run_against_with(name, controller_args, &[], bridge_limit)
}

/// [`run_against`] with `bridge_args` added to the bridge's `rigbridge run`.
fn run_against_with(
    name: &str,
    controller_args: &[&str],
    bridge_args: &[&str],
    bridge_limit: Duration,
) -> Outcome {
    let _guard = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let dir = TempDir::new(name);
    let summary_path = dir.0.join("summary.json");
    let ctl_err = dir.0.join("controller.err");
    let mut controller = Command::new("python3")
        .current_dir(manifest_dir())
        .arg("tests/peers/doc_controller.py")
        .args([
            "--rig",
            "config/irb120.toml",
            "--max-sessions",
            "0",
            "--realtime",
        ])
        .arg("--summary")
        .arg(&summary_path)
        .args(controller_args)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(std::fs::File::create(&ctl_err).unwrap())
        .spawn()
        .expect("spawn python3 tests/peers/doc_controller.py");
    // The first stdout line is the port.
    let stdout = controller.stdout.take().unwrap();
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        let mut reader = BufReader::new(stdout);
        let mut line = String::new();
        let _ = tx.send(reader.read_line(&mut line).map(|_| line));
        // Drain the rest so the controller never blocks on a full pipe.
        let mut rest = String::new();
        while reader.read_line(&mut rest).map(|n| n > 0).unwrap_or(false) {
            rest.clear();
        }
    });
    let line = match rx.recv_timeout(Duration::from_secs(20)) {
        Ok(Ok(line)) => line,
        other => {
            let _ = controller.kill();
            let _ = controller.wait();
            panic!(
                "controller printed no port ({other:?}); its stderr:\n{}",
                std::fs::read_to_string(&ctl_err).unwrap_or_default()
            );
        }
    };
    let port: u16 = line.trim().parse().unwrap_or_else(|_| {
        let _ = controller.kill();
        panic!("controller's first line is not a port: {line:?}")
    });

    let report_path = dir.0.join("report.json");
    let bridge_out = dir.0.join("bridge.out");
    let bridge_err = dir.0.join("bridge.err");
    let mut bridge = Command::new(env!("CARGO_BIN_EXE_rigbridge"))
        .current_dir(manifest_dir())
        .args([
            "run",
            "--link",
            &format!("tcp://127.0.0.1:{port}"),
            "--report",
        ])
        .arg(&report_path)
        .arg("--log")
        .arg(dir.0.join("run.mcap"))
        .args(bridge_args)
        .stdin(Stdio::null())
        .stdout(std::fs::File::create(&bridge_out).unwrap())
        .stderr(std::fs::File::create(&bridge_err).unwrap())
        .spawn()
        .expect("spawn rigbridge");
    let bridge_status = wait_for(&mut bridge, bridge_limit, "rigbridge run");

    // SIGTERM makes the controller write its summary and exit (it serves any number of
    // sessions, so a bridge that reconnects finds it).
    // SAFETY: kill(2) on the pid of a child we spawned and have not reaped.
    let rc = unsafe { libc::kill(controller.id() as libc::pid_t, libc::SIGTERM) };
    assert_eq!(rc, 0, "kill(SIGTERM) of the controller failed");
    let ctl_status = wait_for(&mut controller, Duration::from_secs(10), "doc_controller");
    let controller_log = std::fs::read_to_string(&ctl_err).unwrap_or_default();
    assert!(
        ctl_status.success(),
        "controller failed: {ctl_status}\n{controller_log}"
    );
    let summary: Value = serde_json::from_str(
        &std::fs::read_to_string(&summary_path)
            .unwrap_or_else(|e| panic!("no controller summary ({e}):\n{controller_log}")),
    )
    .expect("controller summary is JSON");
    let report = std::fs::read_to_string(&report_path)
        .ok()
        .map(|s| serde_json::from_str(&s).expect("bridge report is JSON"));
    let bridge_text = format!(
        "{}{}",
        std::fs::read_to_string(&bridge_err).unwrap_or_default(),
        std::fs::read_to_string(&bridge_out).unwrap_or_default()
    );
    // Resumptions the bridge logged (after a stall of a loaded host, say): each may leave
    // one gap at the controller, the targets queued behind its Stop (protocol 6.8).
    let resumes = rigbridge::log::read_log(&dir.0.join("run.mcap"))
        .map(|log| log.events.iter().filter(|e| e.kind == "resumed").count())
        .unwrap_or(0) as i64;
    Outcome {
        bridge: bridge_status,
        bridge_text,
        report,
        summary,
        controller_log,
        resumes,
    }
}

fn ceil_div(num: i64, den: i64) -> i64 {
    num.div_euclid(den) + i64::from(num.rem_euclid(den) != 0)
}

fn rig_joint_names() -> Vec<String> {
    let text = std::fs::read_to_string(manifest_dir().join("config/irb120.toml")).unwrap();
    let rig: toml::Value = toml::from_str(&text).unwrap();
    rig["joint"]
        .as_array()
        .unwrap()
        .iter()
        .map(|j| j["name"].as_str().unwrap().to_string())
        .collect()
}

#[test]
fn strict_controller_accepts_every_target_of_the_default_job() {
    if !common::in_full_tier(
        "conformance::strict_controller_accepts_every_target_of_the_default_job",
    ) {
        return;
    }
    skip_without_python!("strict_controller_accepts_every_target_of_the_default_job");
    let run = run_against("strict", &[], Duration::from_secs(90));
    let ctx = run.context();
    assert!(run.bridge.success(), "bridge exit code: {ctx}");
    assert_eq!(run.outcome(), Some("completed"), "{ctx}");

    // 6.1: a bridge Hello (flags 0) stating the rig and the stream cycle, answered; no
    // target before the answer and a Feedback after it. (More than one Hello only if the
    // bridge had to reconnect, a stall on a loaded machine: it then resumes, 6.8.)
    assert!(run.count("bridge_hellos") >= 1, "{ctx}");
    assert_eq!(
        run.count("answers_sent"),
        run.count("bridge_hellos"),
        "{ctx}"
    );
    assert_eq!(run.count("busy_refusals"), 0, "{ctx}");
    assert_eq!(run.count("bridge_hellos_malformed_or_answer"), 0, "{ctx}");
    let hello = &run.summary["last_bridge_hello"];
    let names: Vec<String> = hello["names"]
        .as_array()
        .unwrap()
        .iter()
        .map(|n| n.as_str().unwrap().to_string())
        .collect();
    assert_eq!(names, rig_joint_names(), "bridge Hello names: {ctx}");
    assert_eq!(hello["cycle_us"].as_i64(), Some(CYCLE_US), "{ctx}");
    assert_eq!(run.count("targets_before_answer"), 0, "{ctx}");
    assert_eq!(run.count("dropped_unbound"), 0, "{ctx}");

    // 100 % of the targets after the Hello accepted, none refused or dropped.
    let bound = run.count("targets_received_bound");
    assert!(bound > 1000, "only {bound} targets for a 7 s job: {ctx}");
    assert_eq!(run.count("targets_received"), bound, "{ctx}");
    assert_eq!(run.count("accepted"), bound, "{ctx}");
    assert!(
        run.summary["refused"].as_array().unwrap().is_empty(),
        "{ctx}"
    );
    println!(
        "conformance: the doc-only controller accepted {} of {bound} targets after the bridge's Hello",
        run.count("accepted")
    );
    // A resumption starts from a hold after the targets queued behind its Stop were
    // discarded: at most one gap and one watchdog hold each. None on a quiet machine.
    for key in ["gaps", "watchdog_holds"] {
        assert!(run.count(key) <= run.resumes, "{key}: {ctx}");
    }
    for key in [
        "dropped_duplicate",
        "dropped_older",
        "dropped_faulted",
        "link_losses_silence",
        // 6.2: t advances by exactly one cycle per seq step.
        "t_irregular",
    ] {
        assert_eq!(run.count(key), 0, "{key}: {ctx}");
    }
    assert_eq!(run.summary["final_fault"][0].as_i64(), Some(0), "{ctx}");
    // 2.3: every frame the bridge sent decoded.
    let decoder = &run.summary["decoder"];
    for key in [
        "crc_errors",
        "unsupported_version",
        "malformed",
        "oversized",
        "bytes_discarded",
    ] {
        assert_eq!(decoder[key].as_i64(), Some(0), "decoder {key}: {ctx}");
    }

    // 6.6 on the wire integers, recomputed here from the controller's Hello.
    let limits = &run.summary["controller_hello"];
    let cycle = limits["cycle_us"].as_i64().unwrap();
    for (k, axis) in run.summary["axes"].as_array().unwrap().iter().enumerate() {
        let get = |key: &str| {
            axis[key]
                .as_i64()
                .unwrap_or_else(|| panic!("axis {k} {key}: {axis}"))
        };
        let vmax = limits["vmax"][k].as_i64().unwrap();
        let amax = limits["amax"][k].as_i64().unwrap();
        let lower = limits["lower"][k].as_i64().unwrap();
        let upper = limits["upper"][k].as_i64().unwrap();
        let step = ceil_div(vmax * cycle, 1_000_000) + 1;
        let dv = ceil_div(amax * cycle, 1_000_000) + 1;
        let dd = ceil_div(amax * cycle * cycle, 1_000_000_000_000) + 2;
        let name = axis["name"].as_str().unwrap();
        assert!(get("max_step") <= step, "{name} step > {step}: {axis}");
        assert!(get("max_step_excess") <= 0, "{name}: {axis}");
        assert!(get("max_vel_change") <= dv, "{name} dv > {dv}: {axis}");
        assert!(get("max_vel_change_excess") <= 0, "{name}: {axis}");
        assert!(get("second_diff_checked") > 1000, "{name}: {axis}");
        assert!(get("max_second_diff") <= dd, "{name} dd > {dd}: {axis}");
        assert!(get("max_abs_velocity") <= vmax, "{name}: {axis}");
        assert!(
            lower <= get("min_position") && get("max_position") <= upper,
            "{name} outside [{lower}, {upper}]: {axis}"
        );
    }
    // The job moved every axis of the arm at least a little.
    let moved = run.summary["axes"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|a| a["max_step"].as_i64().unwrap() > 0)
        .count();
    assert!(moved >= 5, "{ctx}");
}

/// A controller narrower than the rig: the bridge must refuse before any motion and say
/// which axis or value. `needles`: every group must match one of its alternatives in what
/// the bridge said (its stderr, stdout and report).
fn refused_before_motion(name: &str, controller_args: &[&str], needles: &[&[&str]]) {
    let run = run_against(name, controller_args, Duration::from_secs(30));
    let ctx = run.context();
    assert!(!run.bridge.success(), "bridge exited 0: {ctx}");
    assert_ne!(run.outcome(), Some("completed"), "{ctx}");
    // The Hello exchange took place (the refusal is about its contents) ...
    assert!(run.count("bridge_hellos") >= 1, "{ctx}");
    assert!(run.count("answers_sent") >= 1, "{ctx}");
    // ... and not one target reached the controller.
    assert_eq!(run.count("targets_received"), 0, "{ctx}");
    assert_eq!(run.count("accepted"), 0, "{ctx}");
    let said = run.said();
    for group in needles {
        assert!(
            group.iter().any(|n| said.contains(n)),
            "the bridge's words name none of {group:?}: {ctx}"
        );
    }
}

#[test]
fn narrower_lower_limit_is_refused_before_motion() {
    if !common::in_full_tier("conformance::narrower_lower_limit_is_refused_before_motion") {
        return;
    }
    skip_without_python!("narrower_lower_limit_is_refused_before_motion");
    refused_before_motion(
        "lower",
        &["--lower-deg", "2", "-100"],
        &[&["joint_2"], &["-100", "-1745329"]],
    );
}

#[test]
fn narrower_upper_limit_is_refused_before_motion() {
    if !common::in_full_tier("conformance::narrower_upper_limit_is_refused_before_motion") {
        return;
    }
    skip_without_python!("narrower_upper_limit_is_refused_before_motion");
    refused_before_motion(
        "upper",
        &["--upper-deg", "3", "69.9"],
        &[&["joint_3"], &["69.9", "1220025"]],
    );
}

#[test]
fn scaled_down_limits_are_refused_before_motion() {
    if !common::in_full_tier("conformance::scaled_down_limits_are_refused_before_motion") {
        return;
    }
    skip_without_python!("scaled_down_limits_are_refused_before_motion");
    refused_before_motion(
        "scale",
        &["--limit-scale-axis", "1", "0.05"],
        &[&["joint_1"], &["8.25", "143990"]],
    );
}

/// 6.1.6 compares wire integers: one µrad narrower is narrower, and the bridge's words
/// must show the controller's value as it differs from the rig's.
#[test]
fn upper_limit_one_microradian_narrower_is_refused_and_shown() {
    if !common::in_full_tier(
        "conformance::upper_limit_one_microradian_narrower_is_refused_and_shown",
    ) {
        return;
    }
    skip_without_python!("upper_limit_one_microradian_narrower_is_refused_and_shown");
    // joint_3's upper limit is 70 deg = 1221730 urad on the wire.
    refused_before_motion(
        "upper-1urad",
        &["--set-urad", "upper", "3", "1221729"],
        &[&["joint_3"], &["1221729", "69.99994", "69.9999"]],
    );
}

#[test]
fn narrower_speed_is_refused_before_motion() {
    if !common::in_full_tier("conformance::narrower_speed_is_refused_before_motion") {
        return;
    }
    skip_without_python!("narrower_speed_is_refused_before_motion");
    refused_before_motion(
        "speed",
        &["--speed-deg-s", "4", "300"],
        &[&["joint_4"], &["300", "5235988"]],
    );
}

#[test]
fn narrower_acceleration_is_refused_before_motion() {
    if !common::in_full_tier("conformance::narrower_acceleration_is_refused_before_motion") {
        return;
    }
    skip_without_python!("narrower_acceleration_is_refused_before_motion");
    refused_before_motion(
        "accel",
        &["--accel-deg-s2", "6", "1600"],
        &[&["joint_6"], &["1600", "27925268"]],
    );
}

#[test]
fn renamed_axis_is_refused_before_motion() {
    if !common::in_full_tier("conformance::renamed_axis_is_refused_before_motion") {
        return;
    }
    skip_without_python!("renamed_axis_is_refused_before_motion");
    refused_before_motion(
        "rename",
        &["--rename", "5", "wrist_bend"],
        &[&["wrist_bend"]],
    );
}

#[test]
fn fewer_axes_are_refused_before_motion() {
    if !common::in_full_tier("conformance::fewer_axes_are_refused_before_motion") {
        return;
    }
    skip_without_python!("fewer_axes_are_refused_before_motion");
    refused_before_motion("axes5", &["--axes", "5"], &[&["axes", "axis"], &["5"]]);
}

#[test]
fn more_axes_are_refused_before_motion() {
    if !common::in_full_tier("conformance::more_axes_are_refused_before_motion") {
        return;
    }
    skip_without_python!("more_axes_are_refused_before_motion");
    refused_before_motion("axes7", &["--axes", "7"], &[&["axes", "axis"], &["7"]]);
}

#[test]
fn other_cycle_is_refused_before_motion() {
    if !common::in_full_tier("conformance::other_cycle_is_refused_before_motion") {
        return;
    }
    skip_without_python!("other_cycle_is_refused_before_motion");
    refused_before_motion("cycle", &["--cycle-us", "2000"], &[&["2000"]]);
}

#[test]
fn axis_held_twenty_degrees_off_never_completes() {
    if !common::in_full_tier("conformance::axis_held_twenty_degrees_off_never_completes") {
        return;
    }
    skip_without_python!("axis_held_twenty_degrees_off_never_completes");
    let run = run_against(
        "offset",
        &["--hold-axis-offset-deg", "2", "20"],
        Duration::from_secs(30),
    );
    let ctx = run.context();
    assert!(!run.bridge.success(), "bridge exited 0: {ctx}");
    let outcome = run.outcome();
    assert!(
        matches!(outcome, Some("tolerance_exceeded") | Some("not_following")),
        "outcome {outcome:?}: {ctx}"
    );
    // It did start moving, and stopped along its path within every limit.
    assert!(run.count("accepted") > 0, "{ctx}");
    assert!(
        run.summary["refused"].as_array().unwrap().is_empty(),
        "{ctx}"
    );
    assert!(run.said().contains("joint_2"), "{ctx}");
    let report = run.report.as_ref().expect("a report");
    println!(
        "conformance: an axis held 20 deg off: {} after {} samples of the path, {} cycles with the stop ramp: {}",
        report["outcome"], report["samples_done"], report["cycles"], report["fault"]
    );
}

#[test]
fn controller_dropping_every_target_never_completes() {
    if !common::in_full_tier("conformance::controller_dropping_every_target_never_completes") {
        return;
    }
    skip_without_python!("controller_dropping_every_target_never_completes");
    let run = run_against("ignore", &["--ignore-targets"], Duration::from_secs(30));
    let ctx = run.context();
    assert!(!run.bridge.success(), "bridge exited 0: {ctx}");
    assert_ne!(run.outcome(), Some("completed"), "{ctx}");
    assert!(run.report.is_some(), "no report: {ctx}");
    assert_eq!(run.count("accepted"), 0, "{ctx}");
    assert!(run.count("dropped_ignored") > 0, "{ctx}");
    // 6.9: no new echo for w cycles while targets go out; w = 25 here, so the bridge
    // cannot have streamed long.
    assert!(
        run.count("targets_received") < 400,
        "the bridge streamed {} targets to a controller that echoes 0: {ctx}",
        run.count("targets_received")
    );
}

/// 6.7 and 6.1.7: a controller reset locally mid-job (holding, unbound, unprompted Hello)
/// is answered with a bridge Hello, and the job resumes from the held position (6.8)
/// within every check of 6.6, and completes.
#[test]
fn controller_reset_mid_job_is_resumed_from_the_held_position() {
    if !common::in_full_tier(
        "conformance::controller_reset_mid_job_is_resumed_from_the_held_position",
    ) {
        return;
    }
    skip_without_python!("controller_reset_mid_job_is_resumed_from_the_held_position");
    let run = run_against(
        "local-reset",
        &["--local-reset-after", "600"],
        Duration::from_secs(90),
    );
    let ctx = run.context();
    assert_eq!(run.count("local_resets"), 1, "{ctx}");
    assert!(run.bridge.success(), "bridge exit code: {ctx}");
    assert_eq!(run.outcome(), Some("completed"), "{ctx}");
    assert!(run.count("bridge_hellos") >= 2, "{ctx}");
    assert_eq!(run.count("busy_refusals"), 0, "{ctx}");
    assert!(
        run.summary["refused"].as_array().unwrap().is_empty(),
        "{ctx}"
    );
    // The bridge stops streaming at once: at most the targets already on the way reach
    // the unbound controller.
    assert!(run.count("dropped_unbound") <= 3, "{ctx}");
    assert!(run.count("accepted") > 1000, "{ctx}");
}

/// 6.5/6.6/6.8 read as one rule: after a hold the reference is the held setpoint. A
/// strict controller whose servo lags by 50 ms (a 3.18 Hz first-order servo: its measured
/// position settles onto the setpoint for 12 cycles) accepts every first target after the
/// resume, since the bridge plans from a position at rest within 6.8's test.
#[test]
fn a_50_ms_servo_lag_refuses_no_first_target_after_a_resume() {
    if !common::in_full_tier(
        "conformance::a_50_ms_servo_lag_refuses_no_first_target_after_a_resume",
    ) {
        return;
    }
    skip_without_python!("a_50_ms_servo_lag_refuses_no_first_target_after_a_resume");
    // 1 / (2 pi 50 ms).
    let bandwidth_hz = format!("{:.4}", 1.0 / (std::f64::consts::TAU * 0.050));
    // The shipped settings with a path tolerance that covers a 50 ms servo and the
    // controller's 12 ms transport delay on the star's fastest axis (3.4 rad/s: 12 deg).
    let config = std::env::temp_dir().join(format!(
        "rigbridge-conformance-{}-lagging.toml",
        std::process::id()
    ));
    let shipped = std::fs::read_to_string(manifest_dir().join("config/rigbridge.toml")).unwrap();
    let rig = manifest_dir().join("config/irb120.toml");
    std::fs::write(
        &config,
        shipped
            .replacen(
                "rig = \"irb120.toml\"",
                &format!("rig = {:?}", rig.display().to_string()),
                1,
            )
            .replacen(
                "cell = \"cell-star.toml\"",
                &format!(
                    "cell = {:?}",
                    manifest_dir()
                        .join("config/cell-star.toml")
                        .display()
                        .to_string()
                ),
                1,
            )
            .replacen("[stream]\n", "[stream]\npath_tolerance_deg = 20.0\n", 1),
    )
    .unwrap();
    let run = run_against_with(
        "lagging-reset",
        &[
            "--local-reset-after",
            "600",
            "--bandwidth-hz",
            &bandwidth_hz,
        ],
        &["--config", config.to_str().unwrap()],
        Duration::from_secs(90),
    );
    let _ = std::fs::remove_file(&config);
    let ctx = run.context();
    assert_eq!(run.count("local_resets"), 1, "{ctx}");
    assert_eq!(run.outcome(), Some("completed"), "{ctx}");
    assert!(
        run.summary["refused"].as_array().unwrap().is_empty(),
        "{ctx}"
    );
    assert!(run.bridge.success(), "bridge exit code: {ctx}");
}

/// The controller's self-test: COBS and CRC-32 (2.1, 2.2), the decoder's counters (2.3),
/// every worked example of docs/protocol.md read from the doc itself (sections 4 and 7.4:
/// versions 2 and 3, the I/O messages, the version 3 Hello, the SetOutput's CAN segments)
/// encoded and decoded byte for byte, the I/O names and fields a version 3 receiver drops
/// (3.6), and 6.10's rules on a controller without a socket.
#[test]
fn doc_controller_framing_matches_the_spec_examples() {
    if !common::in_full_tier("conformance::doc_controller_framing_matches_the_spec_examples") {
        return;
    }
    skip_without_python!("doc_controller_framing_matches_the_spec_examples");
    let out = Command::new("python3")
        .current_dir(manifest_dir())
        .args(["tests/peers/doc_controller.py", "--self-test"])
        .output()
        .unwrap();
    let said = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(out.status.success(), "{said}");
    // The doc's examples were found and checked (16 when version 3 came: target, feedback,
    // heartbeat and hello bodies and frames, fault, set-output body and frame, both
    // io-state bodies, the io-state-input frame, read-input, set-output-can).
    let checked: usize = said
        .split("self-test ok (")
        .nth(1)
        .and_then(|rest| rest.split(' ').next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("no count of worked examples: {said}"));
    assert!(
        checked >= 16,
        "only {checked} worked examples checked: {said}"
    );
}

// ----------------------------------------------------------------------------------------
// Version 3: digital I/O (docs/protocol.md 3.6, 6.10), a `program` job's `set_output`,
// `wait_input`, `grip` and `release` steps (docs/programs.md) against the doc-only
// controller.

/// The program both I/O tests run: a move, the lamp on, a wait for the part sensor (which
/// the controller raises 0.3 s after the lamp came on), grip, the lamp off, release, and a
/// move back. `grip` and `release` set the output `gripper` (6.10, last paragraph); the
/// controller's gripper is an actuator answered 0.25 s after its SetOutput.
const IO_PROGRAM: &str = r#"
[[job.steps]]
kind = "move_joints"
to = "reach"

[[job.steps]]
kind = "set_output"
output = "lamp"
value = true

[[job.steps]]
kind = "wait_input"
input = "part_held"
value = true
timeout_s = 5.0

[[job.steps]]
kind = "grip"

[[job.steps]]
kind = "set_output"
output = "lamp"
value = false

[[job.steps]]
kind = "release"

[[job.steps]]
kind = "move_joints"
to = "back"
"#;

/// The outputs the program sets, in order, with their values, as the controller must have
/// carried them out.
const IO_PROGRAM_OUTPUTS: [(&str, i64); 4] =
    [("lamp", 1), ("gripper", 1), ("lamp", 0), ("gripper", 0)];

/// A directory with the rig, a cell naming the program's two joint targets, and run
/// settings holding [`IO_PROGRAM`]; removed on drop.
fn io_program_settings(name: &str) -> (TempDir, PathBuf) {
    let dir = TempDir::new(&format!("{name}-settings"));
    std::fs::copy(
        manifest_dir().join("config/irb120.toml"),
        dir.0.join("irb120.toml"),
    )
    .unwrap();
    // The controller starts at [0, 0, 0, 0, 30, 0] deg (its --initial-deg default); the
    // move is docs/jobs.md's first example.
    std::fs::write(
        dir.0.join("cell.toml"),
        "[[target]]\nname = \"reach\"\njoints_deg = [20.0, 10.0, 10.0, 0.0, 40.0, 0.0]\n\n\
         [[target]]\nname = \"back\"\njoints_deg = [0.0, 0.0, 0.0, 0.0, 30.0, 0.0]\n",
    )
    .unwrap();
    let settings = dir.0.join("program.toml");
    std::fs::write(
        &settings,
        format!(
            "rig = \"irb120.toml\"\ncell = \"cell.toml\"\n\n[stream]\nrate_hz = 250.0\n\n\
             [job]\nkind = \"program\"\n{IO_PROGRAM}"
        ),
    )
    .unwrap();
    (dir, settings)
}

/// `outputs_done` of the controller's summary, consecutive repeats merged (a SetOutput sent
/// again after a resume, 6.10, sets the same value twice).
fn outputs_done(summary: &Value) -> Vec<(String, i64)> {
    let mut out: Vec<(String, i64)> = Vec::new();
    for entry in summary["outputs_done"]
        .as_array()
        .unwrap_or_else(|| panic!("summary has no outputs_done: {summary}"))
    {
        let item = (
            entry[0].as_str().unwrap().to_string(),
            entry[1].as_i64().unwrap(),
        );
        if out.last() != Some(&item) {
            out.push(item);
        }
    }
    out
}

/// 6.10 against a version 3 controller: the program completes; the controller carried out
/// every SetOutput (lamp on, gripper closed, lamp off, gripper open, in this order), the
/// bridge read the part sensor until it came on, one request at a time, and kept the arm
/// following with Targets at rest meanwhile (no watchdog hold, no refusal).
#[test]
fn program_with_io_steps_completes_against_a_version_3_controller() {
    if !common::in_full_tier(
        "conformance::program_with_io_steps_completes_against_a_version_3_controller",
    ) {
        return;
    }
    skip_without_python!("program_with_io_steps_completes_against_a_version_3_controller");
    let (_settings_dir, settings) = io_program_settings("io-v3");
    let run = run_against_with(
        "io-v3",
        &["--version", "3", "--input", "part_held=1@lamp=1+0.3"],
        &["--config", settings.to_str().unwrap()],
        Duration::from_secs(90),
    );
    let ctx = run.context();
    assert!(run.bridge.success(), "bridge exit code: {ctx}");
    assert_eq!(run.outcome(), Some("completed"), "{ctx}");
    assert_eq!(run.count("protocol_version"), 3, "{ctx}");

    // 6.1 and 6.10: the bridge's Hello stays version 2, and is answered (with version 3).
    assert!(run.count("bridge_hellos") >= 1, "{ctx}");
    assert_eq!(run.count("bridge_hellos_v3"), 0, "{ctx}");
    assert_eq!(
        run.count("answers_sent"),
        run.count("bridge_hellos"),
        "{ctx}"
    );

    // The outputs, in order, with their values; every SetOutput and ReadInput answered
    // done (no unknown name, no refusal), one request outstanding at a time, numbered
    // from 1 in each session.
    let want: Vec<(String, i64)> = IO_PROGRAM_OUTPUTS
        .iter()
        .map(|(n, v)| (n.to_string(), *v))
        .collect();
    assert_eq!(outputs_done(&run.summary), want, "{ctx}");
    let results = &run.summary["io_results"];
    assert_eq!(results["no_such"].as_i64(), Some(0), "{ctx}");
    assert_eq!(results["refused"].as_i64(), Some(0), "{ctx}");
    assert_eq!(run.count("io_overlapping"), 0, "{ctx}");
    assert_eq!(run.count("io_request_irregular"), 0, "{ctx}");
    assert_eq!(run.summary["outputs"]["lamp"].as_i64(), Some(0), "{ctx}");
    assert_eq!(run.summary["outputs"]["gripper"].as_i64(), Some(0), "{ctx}");

    // wait_input: ReadInputs of part_held, off while the sensor was off (0.3 s after the
    // lamp came on), then on, and the wait ended there.
    let reads = run.summary["inputs_read"].as_array().unwrap();
    assert!(!reads.is_empty(), "no ReadInput: {ctx}");
    assert!(
        reads
            .iter()
            .all(|r| r["name"] == "part_held" && r["result"] == 0),
        "{ctx}"
    );
    assert_eq!(reads.first().unwrap()["value"].as_i64(), Some(0), "{ctx}");
    assert_eq!(reads.last().unwrap()["value"].as_i64(), Some(1), "{ctx}");
    assert_eq!(reads.last().unwrap()["count"].as_i64(), Some(1), "{ctx}");

    // The arm kept following through the I/O steps (6.10: Targets at rest): every target
    // accepted, no watchdog hold beyond what a resumption explains.
    assert!(run.count("accepted") > 250, "{ctx}");
    assert!(
        run.summary["refused"].as_array().unwrap().is_empty(),
        "{ctx}"
    );
    assert!(run.count("watchdog_holds") <= run.resumes, "{ctx}");
    assert_eq!(run.summary["final_fault"][0].as_i64(), Some(0), "{ctx}");
    let decoder = &run.summary["decoder"];
    for key in [
        "crc_errors",
        "unsupported_version",
        "malformed",
        "oversized",
    ] {
        assert_eq!(decoder[key].as_i64(), Some(0), "decoder {key}: {ctx}");
    }
    println!(
        "conformance: a program's I/O against the doc-only v3 controller: outputs {:?}, reads {}",
        outputs_done(&run.summary),
        run.summary["inputs_read"]
    );
}

/// 6.10: the same program against a version 2 controller is refused before any motion,
/// after the Hello exchange (the session's version is the controller's Hello's), naming
/// the controller's version; the bridge sends it no I/O message.
#[test]
fn program_with_io_steps_is_refused_by_version_before_motion_against_a_version_2_controller() {
    if !common::in_full_tier(
        "conformance::program_with_io_steps_is_refused_by_version_before_motion_against_a_version_2_controller",
    ) {
        return;
    }
    skip_without_python!(
        "program_with_io_steps_is_refused_by_version_before_motion_against_a_version_2_controller"
    );
    let (_settings_dir, settings) = io_program_settings("io-v2");
    let run = run_against_with(
        "io-v2",
        &["--version", "2", "--input", "part_held=1@lamp=1+0.3"],
        &["--config", settings.to_str().unwrap()],
        Duration::from_secs(30),
    );
    let ctx = run.context();
    assert_eq!(run.count("protocol_version"), 2, "{ctx}");
    assert!(!run.bridge.success(), "bridge exited 0: {ctx}");
    assert_ne!(run.outcome(), Some("completed"), "{ctx}");
    // The refusal comes from the controller's answer: the exchange took place ...
    assert!(run.count("bridge_hellos") >= 1, "{ctx}");
    assert!(run.count("answers_sent") >= 1, "{ctx}");
    // ... and not one target, not one I/O message (a version 3 frame would be counted
    // unsupported_version by this version 2 controller) reached it.
    assert_eq!(run.count("targets_received"), 0, "{ctx}");
    assert_eq!(run.count("accepted"), 0, "{ctx}");
    assert_eq!(
        run.summary["decoder"]["unsupported_version"].as_i64(),
        Some(0),
        "{ctx}"
    );
    assert_eq!(
        run.summary["decoder"]["malformed"].as_i64(),
        Some(0),
        "{ctx}"
    );
    assert!(
        run.summary["outputs_done"].as_array().unwrap().is_empty(),
        "{ctx}"
    );
    // The words name the controller's version (rigbridge's, 6.10: "the controller speaks
    // protocol v2, which carries no I/O (v3 adds it)").
    let said = run.said();
    assert!(said.contains("controller"), "{ctx}");
    assert!(
        ["v2", "version 2"].iter().any(|n| said.contains(n)),
        "the bridge's words name no controller version: {ctx}"
    );
}
