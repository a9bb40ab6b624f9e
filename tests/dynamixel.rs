//! Dynamixel Protocol 2.0 end to end over a real pty pair: the bridge's Dynamixel link (the
//! master) against our twin's six servos running the default job (completed, nothing
//! refused or counted by the servos), a servo's hardware error stopping a job, and our
//! twin's servos against PyPI's dynamixel-sdk as the master (tests/peers/dxl_master.py).

use crate::common;

use common::cycles::{one_at_a_time, real_time, wait_for};
use common::shipped_run_settings;

use rigbridge::daemon::config::{RunSettings, load_run_settings};
use rigbridge::daemon::{dynamixel_settings, run_job};
use rigbridge::device::dynamixel::twin::{
    DynamixelBus, DynamixelTwinControl, DynamixelTwinCounters, DynamixelTwinSettings,
    serve_dynamixel,
};
use rigbridge::device::dynamixel::{DynamixelLink, connect_dynamixel};
use rigbridge::link::Link;
use rigbridge::stream::{Outcome, STALL_CYCLES, StreamControl};
use rigbridge::twin::serial_port::SerialControllerPort;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

const IDS: [u8; 6] = [1, 2, 3, 4, 5, 6];
/// Patience for conditions that take a few cycles on an idle machine.
const PATIENCE: Duration = Duration::from_secs(10);

/// The twin's bus on a new pty, served on its own thread: the pty's path, the operator's
/// control, and the thread that returns the bus's counters, positions and torque.
struct TwinBus {
    path: String,
    control: Arc<DynamixelTwinControl>,
    thread: std::thread::JoinHandle<(DynamixelTwinCounters, Vec<f64>, Vec<bool>)>,
}

fn twin_bus(settings: &RunSettings) -> TwinBus {
    twin_bus_of(settings, &IDS)
}

/// The twin's bus of servos `ids` (one per axis, in axis order).
fn twin_bus_of(settings: &RunSettings, ids: &[u8]) -> TwinBus {
    let ticks = settings
        .config
        .dynamixel
        .axes(&settings.file, &settings.rig)
        .expect("ticks");
    let twin = DynamixelTwinSettings {
        period: settings.period(),
        bandwidth_hz: settings.config.twin.bandwidth_hz,
    };
    let mut bus =
        DynamixelBus::new(&settings.rig, ids, &ticks, &settings.initial(), twin).expect("bus");
    let (mut port, path) = SerialControllerPort::pty().expect("a pty pair");
    let control = Arc::new(DynamixelTwinControl::default());
    let serving = control.clone();
    let thread = std::thread::spawn(move || {
        serve_dynamixel(&mut bus, &mut port, &serving);
        (bus.counters, bus.positions(), bus.torque())
    });
    TwinBus {
        path,
        control,
        thread,
    }
}

/// The bridge's Dynamixel link to `twin`'s six servos at 1 Mbaud, once it has set the bus up.
fn link_to(settings: &RunSettings, twin: &TwinBus) -> DynamixelLink {
    let link_settings =
        dynamixel_settings(settings, &twin.path, 1_000_000, &IDS).expect("link settings");
    let link = connect_dynamixel(link_settings).expect("link");
    wait_for("the bus set up", PATIENCE, || link.is_up());
    link
}

#[test]
fn the_bridge_drives_six_twin_servos_through_the_default_job_over_a_pty() {
    let _cycles = one_at_a_time();
    real_time();
    let settings = shipped_run_settings();
    let twin = twin_bus(&settings);
    let mut link = link_to(&settings, &twin);
    let clock = rigbridge::clock::WallClock::new();
    let control = StreamControl::default();
    let job = settings.config.job.clone();
    let report = run_job(&settings, &job, &mut link, &clock, None, &control).expect("the job runs");
    twin.control.stop.store(true, Ordering::SeqCst);
    let (counters, positions, torque) = twin.thread.join().expect("twin thread");
    assert_eq!(
        report.stream.outcome,
        Outcome::Completed,
        "{report:?} {counters:?}"
    );
    assert_eq!(report.stream.limit_violations, 0);
    assert_eq!(counters.outside_limits, 0, "{counters:?}");
    assert_eq!(counters.over_speed, 0, "{counters:?}");
    assert_eq!(counters.over_acceleration, 0, "{counters:?}");
    assert_eq!(counters.stale_goal_at_torque_on, 0, "{counters:?}");
    assert_eq!(counters.errors_answered, 0, "{counters:?}");
    assert_eq!(counters.crc_errors, 0, "{counters:?}");
    // Set-up pinged every servo once; then one sync write per target, each followed by
    // a sync read, and a sync read per heartbeat.
    assert_eq!(counters.pings, 6);
    // A host stall (a wake 5 cycles late) ends a part with a Stop, and the targets queued
    // behind it are stale and never written (docs/faults.md): only a run without one
    // must have written every target it sent.
    let period_us = 1e6 / settings.config.stream.rate_hz;
    if report.stream.jitter_max_us < STALL_CYCLES as f64 * period_us {
        assert!(
            counters.sync_writes >= report.stream.cycles,
            "{} cycles: {counters:?}",
            report.stream.cycles
        );
    } else {
        println!(
            "a host stall ({:.1} ms late): {} sync writes over {} cycles",
            report.stream.jitter_max_us / 1e3,
            counters.sync_writes,
            report.stream.cycles
        );
    }
    assert!(counters.sync_reads >= counters.sync_writes, "{counters:?}");
    assert_eq!(counters.goals, 6 * counters.sync_writes + 6, "{counters:?}");
    assert!(torque.iter().all(|on| *on), "torque stays on after the job");
    // The star returns home: every servo within a tick of where it started.
    for (actual, home) in positions.iter().zip(settings.initial()) {
        assert!(
            (actual - home).abs() <= std::f64::consts::TAU / 4096.0,
            "{actual} vs {home}"
        );
    }
    let link_counters = link.counters();
    assert_eq!(link_counters.crc_errors, 0);
    // The cycle's figures at 250 Hz over the pty.
    println!(
        "dynamixel 250 Hz, 6 servos: {} cycles, feedback timeouts {}, latency p99 {:.0} us, missing statuses {}, jitter p99 {:.0} us",
        report.stream.cycles,
        report.stream.feedback_timeouts,
        report.stream.latency_p99_us,
        link_counters.gaps,
        report.stream.jitter_p99_us
    );
    // A feedback later than half a cycle (2 ms) is a timeout, used the next cycle. How
    // many there are is the host's scheduling, a figure printed above, not a pass mark:
    // the job completing with nothing refused at the servos is.
}

/// A servo id that is not on the bus: the link says which id did not answer its ping, and
/// on which line (not that a controller kept silent).
#[test]
fn an_absent_servo_id_is_named_by_its_ping() {
    let _cycles = one_at_a_time();
    let settings = shipped_run_settings();
    // The bus has 1 to 5 and 7; the link asks for 1 to 6.
    let twin = twin_bus_of(&settings, &[1, 2, 3, 4, 5, 7]);
    let link_settings =
        dynamixel_settings(&settings, &twin.path, 1_000_000, &IDS).expect("link settings");
    let link = connect_dynamixel(link_settings).expect("link");
    let reason = common::wait_until("the link's reason", PATIENCE, || link.down_reason());
    println!("{reason}");
    assert!(!link.is_up());
    assert!(
        reason.contains("id 6 (axis 6) did not answer its ping") && reason.contains(&twin.path),
        "{reason}"
    );
    drop(link);
    twin.control.stop.store(true, Ordering::SeqCst);
    let _ = twin.thread.join();
}

#[test]
fn a_servo_hardware_error_stops_the_job_with_a_drive_fault() {
    let _cycles = one_at_a_time();
    real_time();
    let settings = shipped_run_settings();
    let twin = twin_bus(&settings);
    let mut link = link_to(&settings, &twin);
    let control = Arc::new(StreamControl::default());
    let injector = twin.control.clone();
    let watched = control.clone();
    // Overload (bit 5) on axis 3 once the job is well under way.
    let fault = std::thread::spawn(move || {
        let start = Instant::now();
        while watched.cycles() < 200 && start.elapsed() < PATIENCE {
            std::thread::sleep(Duration::from_millis(2));
        }
        injector.hardware_error(2, 0x20);
    });
    let clock = rigbridge::clock::WallClock::new();
    let job = settings.config.job.clone();
    let report = run_job(&settings, &job, &mut link, &clock, None, &control).expect("the job runs");
    fault.join().expect("injector");
    twin.control.stop.store(true, Ordering::SeqCst);
    let (counters, _, torque) = twin.thread.join().expect("twin thread");
    assert_eq!(report.stream.outcome, Outcome::Faulted, "{report:?}");
    let text = report.stream.fault.clone().unwrap_or_default();
    assert!(text.contains("axis 3"), "{text}");
    assert!(
        text.contains("0x20"),
        "the hardware error status is named: {text}"
    );
    assert!(!torque[2], "the faulted servo's torque went off");
    assert_eq!(
        counters.over_speed + counters.over_acceleration,
        0,
        "{counters:?}"
    );
    assert!(report.stream.cycles > 200);
}

#[test]
fn a_rate_the_line_cannot_carry_is_refused_before_anything_opens() {
    let settings = shipped_run_settings();
    // Six servos at 57600 baud: 34.7 Hz at most (docs/dynamixel.md), not 250.
    let error = dynamixel_settings(&settings, "/dev/null", 57_600, &IDS).expect_err("refused");
    let text = error.to_string();
    assert!(text.contains("250 Hz") && text.contains("35 Hz"), "{text}");
    assert!(dynamixel_settings(&settings, "/dev/null", 1_000_000, &IDS).is_ok());
}

#[test]
fn tick_settings_are_checked_on_load_and_errors_name_the_file_key_and_value() {
    let rig = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("config/irb120.toml");
    let dir = std::env::temp_dir().join(format!("rigbridge-dxl-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    let write = |name: &str, section: &str| {
        let file = dir.join(name);
        let text = format!(
            "rig = {rig:?}\n[job]\nkind = \"move_joints\"\ntargets_deg = [[0, 0, 0, 0, 30, 0]]\n{section}\n"
        );
        std::fs::write(&file, text).expect("write");
        file
    };
    let good = write(
        "good.toml",
        "[dynamixel]\nticks_per_turn = 4096\nzero_tick = [2048, 2048, 2048, 2048, 1024, 2048]",
    );
    let settings = load_run_settings(&good).expect("loads");
    let axes = settings
        .config
        .dynamixel
        .axes(&settings.file, &settings.rig)
        .expect("axes");
    assert_eq!(axes[4].zero_tick, 1024.0);
    assert_eq!(axes[0].ticks_per_turn, 4096.0);
    for (name, section, key, value) in [
        (
            "fraction.toml",
            "[dynamixel]\nticks_per_turn = 4096.5",
            "dynamixel.ticks_per_turn",
            "4096.5",
        ),
        (
            "zero.toml",
            "[dynamixel]\nticks_per_turn = 0",
            "dynamixel.ticks_per_turn",
            "0",
        ),
        (
            "count.toml",
            "[dynamixel]\nzero_tick = [2048, 2048]",
            "dynamixel.zero_tick",
            "2",
        ),
    ] {
        let file = write(name, section);
        let error = load_run_settings(&file).expect_err("refused").to_string();
        assert!(error.contains(name), "{error}");
        assert!(error.contains(key), "{error}");
        assert!(error.contains(value), "{error}");
    }
}

/// The Python with dynamixel-sdk (RIGBRIDGE_DXL_PYTHON, set by scripts/test.sh).
fn peer_python() -> Result<String, String> {
    common::peer_python("RIGBRIDGE_DXL_PYTHON", "dynamixel_sdk", "dynamixel_sdk")
}

#[test]
fn the_twin_servos_answer_dynamixel_sdk_as_master() {
    let _cycles = one_at_a_time();
    let python = match peer_python() {
        Ok(python) => python,
        Err(reason) => {
            println!("skipping the dynamixel-sdk peer test: {reason}");
            return;
        }
    };
    let settings = shipped_run_settings();
    let twin = twin_bus(&settings);
    let script = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/peers/dxl_master.py");
    let output = std::process::Command::new(python)
        .arg(script)
        .arg(&twin.path)
        .output()
        .expect("the peer runs");
    twin.control.stop.store(true, Ordering::SeqCst);
    let (counters, _, torque) = twin.thread.join().expect("twin thread");
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(
        output.status.success(),
        "peer failed: {stdout} {}",
        String::from_utf8_lossy(&output.stderr)
    );
    let report: serde_json::Value =
        serde_json::from_str(stdout.lines().last().unwrap_or("")).expect("a JSON report");
    let ints = |key: &str| -> Vec<i64> {
        report[key]
            .as_array()
            .unwrap_or_else(|| panic!("{key} in {report}"))
            .iter()
            .map(|v| v.as_i64().expect("an integer"))
            .collect()
    };
    // Ping: every id, the model and firmware the twin plays.
    assert_eq!(ints("models"), vec![1030; 6]);
    assert_eq!(ints("firmware"), vec![0x26; 6]);
    // Present positions at the start: the configured initial position in ticks.
    let start = ints("start");
    let expected: Vec<i64> = settings
        .initial()
        .iter()
        .map(|r| (2048.0 + r * 4096.0 / std::f64::consts::TAU).round() as i64)
        .collect();
    assert_eq!(start, expected);
    // Torque on/off as the SDK reads it back, and the EEPROM lock it meets.
    assert_eq!(report["torque_read"], serde_json::json!([1, 1, 1, 1, 1, 1]));
    assert_eq!(report["eeprom_with_torque_error"], 7);
    // Sync writes ramping the goals 20 ticks over, sync reads until the servos are there.
    let (goals, last) = (ints("goals"), ints("final"));
    for axis in 0..6 {
        assert_eq!(goals[axis], start[axis] + 20);
        assert_eq!(last[axis], goals[axis], "axis {axis}: {last:?}");
    }
    assert_eq!(counters.sync_writes, 8, "{counters:?}");
    assert_eq!(report["sync_writes"], 8);
    assert!(counters.sync_reads >= 1, "{counters:?}");
    assert_eq!(counters.crc_errors, 0, "{counters:?}");
    assert_eq!(counters.violations(), 0, "{counters:?}");
    assert_eq!(
        counters.access_errors, 1,
        "only the EEPROM write: {counters:?}"
    );
    assert_eq!(counters.errors_answered, 1, "{counters:?}");
    assert!(
        torque.iter().all(|on| !on),
        "the peer turned torque off at the end"
    );
}

/// Run settings for the painter rig (base_x, base_y, base_yaw, lift, then the IRB 120) with
/// `section` and `job`, written to a file of their own.
fn painter_file(name: &str, section: &str, job: &str) -> PathBuf {
    let rig = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("config/painter.toml");
    let dir = std::env::temp_dir().join(format!("rigbridge-dxl-painter-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    let file = dir.join(name);
    let text = format!(
        "rig = {rig:?}\n[twin]\ninitial_deg = [0, 0, 0, 0, 0, 0, 0, 0, 30, 0]\n{section}\n[job]\n{job}\n"
    );
    std::fs::write(&file, text).expect("write");
    file
}

/// base_x and base_y on racks with a pinion of 0.1 m a turn (40960 ticks a metre at 4096 a
/// turn), the lift on a lead screw of 20 mm (204800).
const PAINTER_TICKS: &str =
    "[dynamixel]\nticks_per_metre = [40960, 40960, 0, 204800, 0, 0, 0, 0, 0, 0]";

#[test]
fn the_bridge_drives_the_painter_s_linear_axes_and_arm_over_a_pty() {
    let _cycles = one_at_a_time();
    real_time();
    let job = "kind = \"move_joints\"\ntargets_deg = [[0.3, -0.2, 20.0, 0.4, 20.0, 10.0, 10.0, 0.0, 40.0, 5.0]]";
    let file = painter_file("painter-dxl.toml", PAINTER_TICKS, job);
    let settings = load_run_settings(&file).expect("the painter settings load");
    let ids: Vec<u8> = (1..=10).collect();
    let twin = twin_bus_of(&settings, &ids);
    let link_settings =
        dynamixel_settings(&settings, &twin.path, 1_000_000, &ids).expect("link settings");
    let mut link = connect_dynamixel(link_settings).expect("link");
    wait_for("the bus set up", PATIENCE, || link.is_up());
    let clock = rigbridge::clock::WallClock::new();
    let job = settings.config.job.clone();
    let report = run_job(
        &settings,
        &job,
        &mut link,
        &clock,
        None,
        &StreamControl::default(),
    )
    .expect("the job runs");
    twin.control.stop.store(true, Ordering::SeqCst);
    let (counters, positions, _) = twin.thread.join().expect("twin thread");
    assert_eq!(
        report.stream.outcome,
        Outcome::Completed,
        "{report:?} {counters:?}"
    );
    assert_eq!(counters.violations(), 0, "{counters:?}");
    assert_eq!(counters.errors_answered, 0, "{counters:?}");
    assert_eq!(counters.pings, 10);
    // The servos got there: within 1 mm on the linear axes, 0.1 deg on the others.
    let target = [0.3, -0.2, 20.0, 0.4, 20.0, 10.0, 10.0, 0.0, 40.0, 5.0];
    for (axis, (actual, wanted)) in positions.iter().zip(target).enumerate() {
        let (wanted, within) = if [0, 1, 3].contains(&axis) {
            (wanted, 1e-3)
        } else {
            (f64::to_radians(wanted), 0.1f64.to_radians())
        };
        assert!(
            (actual - wanted).abs() < within,
            "axis {axis}: {actual} vs {wanted}"
        );
    }
}

#[test]
fn a_prismatic_axis_needs_ticks_per_metre_and_errors_name_the_file_key_and_value() {
    let job = "kind = \"move_joints\"\ntargets_deg = [[0, 0, 0, 0, 0, 0, 0, 0, 30, 0]]";
    let file = painter_file("no-metre.toml", "", job);
    let settings = load_run_settings(&file).expect("loads: the link is not Dynamixel");
    let error = dynamixel_settings(
        &settings,
        "/dev/null",
        1_000_000,
        &[1, 2, 3, 4, 5, 6, 7, 8, 9, 10],
    )
    .expect_err("refused")
    .to_string();
    for part in [
        "no-metre.toml",
        "dynamixel.ticks_per_metre",
        "required for prismatic axes (base_x, base_y, lift)",
    ] {
        assert!(error.contains(part), "{part} in {error}");
    }
    for (name, section, value) in [
        (
            "revolute-entry.toml",
            "[dynamixel]\nticks_per_metre = [40960, 40960, 5, 204800, 0, 0, 0, 0, 0, 0]",
            "base_yaw is revolute",
        ),
        ("zero-metre.toml", "[dynamixel]\nticks_per_metre = 0", "= 0"),
        (
            "dxl-link.toml",
            "[stream]\nlink = \"dynamixel:///dev/null?baud=1000000&ids=1,2,3,4,5,6,7,8,9,10\"",
            "required for prismatic axes",
        ),
    ] {
        let file = painter_file(name, section, job);
        let error = load_run_settings(&file).expect_err("refused").to_string();
        assert!(error.contains(name), "{error}");
        assert!(error.contains("dynamixel.ticks_per_metre"), "{error}");
        assert!(error.contains(value), "{value} in {error}");
    }
}
