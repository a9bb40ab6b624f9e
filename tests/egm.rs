//! EGM end to end over real UDP on 127.0.0.1: the bridge's EGM link against our EGM twin
//! (the default job completes, the twin refuses nothing), the twin's sessions (motors,
//! CommTimeout), and the twin against abb-robot-client's `EGM` sensor (tests/peers/).

mod common;

use common::cycles::{one_at_a_time, real_time, wait_for};
use common::shipped_run_settings;

use prost::Message;
use rigbridge::clock::Clock;
use rigbridge::daemon::config::{RunSettings, load_run_settings};
use rigbridge::daemon::{RunReport, run_job};
use rigbridge::link::{EgmLink, EgmLinkSettings, Link, bind_egm};
use rigbridge::protocol::egm::{EgmAxes, EgmRobot, EgmSensor, MciState, MotorState};
use rigbridge::stream::{Outcome, StreamControl};
use rigbridge::twin::egm::{
    EgmRobotModel, EgmTwin, EgmTwinControl, EgmTwinSettings, spawn_egm_twin,
};
use std::net::{SocketAddr, UdpSocket};
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

/// Patience for conditions that take a few robot cycles on an idle machine.
const PATIENCE: Duration = Duration::from_secs(10);

/// Where the settings' axes travel in EGM: `[egm]`, or the rig's last six as the robot's.
fn axes(settings: &RunSettings) -> EgmAxes {
    settings
        .config
        .egm
        .axes(&settings.file, &settings.rig)
        .expect("the EGM axes")
}

fn twin_towards(settings: &RunSettings, sensor: SocketAddr, egm: EgmTwinSettings) -> EgmTwin {
    let model =
        EgmRobotModel::new(&settings.rig, axes(settings), egm, &settings.initial()).expect("model");
    EgmTwin::new(model, sensor).expect("twin socket")
}

/// A UDP socket on loopback in the sensor's place (reads time out after a second), and a
/// twin with `egm` sending to it on its own thread: the socket, the twin's control and its
/// thread.
fn twin_towards_a_socket(
    settings: &RunSettings,
    egm: EgmTwinSettings,
) -> (
    UdpSocket,
    Arc<EgmTwinControl>,
    std::thread::JoinHandle<EgmTwin>,
) {
    let sensor = UdpSocket::bind("127.0.0.1:0").expect("sensor socket");
    sensor
        .set_read_timeout(Some(Duration::from_secs(1)))
        .expect("timeout");
    let control = Arc::new(EgmTwinControl::default());
    let twin = twin_towards(settings, sensor.local_addr().expect("addr"), egm);
    let twin = spawn_egm_twin(twin, control.clone()).expect("twin thread");
    (sensor, control, twin)
}

/// The settings' job over an EGM link bound on loopback, against a twin started towards
/// it, to its end; asserts it `completed`. The report, the stopped twin and the link.
fn job_against_the_twin(settings: &RunSettings) -> (RunReport, EgmTwin, EgmLink) {
    let period = settings.period();
    let egm = EgmLinkSettings::for_rig(&settings.rig, axes(settings), period, None);
    let mut link = bind_egm("127.0.0.1:0", egm).expect("bind");
    let control = Arc::new(EgmTwinControl::default());
    let twin = twin_towards(settings, link.local_address(), EgmTwinSettings::default());
    let twin = spawn_egm_twin(twin, control.clone()).expect("twin thread");
    wait_for("the EGM session", PATIENCE, || link.is_up());
    let clock = link.pacing().expect("an EGM link paces the streamer");
    let job = settings.config.job.clone();
    let report = run_job(
        settings,
        &job,
        &mut link,
        clock.as_ref(),
        None,
        &StreamControl::default(),
    )
    .expect("the job runs");
    control.stop.store(true, Ordering::SeqCst);
    let twin = twin.join().expect("twin thread");
    assert_eq!(
        report.stream.outcome,
        Outcome::Completed,
        "{report:?} {:?}",
        twin.model().counters
    );
    (report, twin, link)
}

#[test]
fn bridge_streams_the_default_job_to_the_egm_twin_within_its_limits() {
    let _cycles = one_at_a_time();
    real_time();
    let settings = shipped_run_settings();
    let (report, twin, link) = job_against_the_twin(&settings);
    let counters = twin.model().counters;
    assert_eq!(report.stream.limit_violations, 0);
    assert_eq!(counters.outside_limits, 0, "{counters:?}");
    assert_eq!(counters.over_speed, 0, "{counters:?}");
    assert_eq!(counters.over_acceleration, 0, "{counters:?}");
    assert_eq!(counters.axis_count, 0, "{counters:?}");
    assert_eq!(counters.comm_timeouts, 0);
    assert_eq!(counters.sessions, 1);
    let state = link.state();
    assert_eq!(state.replies, state.messages, "one reply per EgmRobot");
    assert!(state.messages > report.stream.cycles, "{state:?}");
    assert_eq!(state.malformed, 0);
    // The twin ends where the job does (the star returns home): within 0.1 deg.
    let end = report.stream.cycles;
    assert!(end > 0);
    let home = settings.initial();
    for (actual, planned) in twin.model().position().iter().zip(&home) {
        assert!(
            (actual - planned).abs().to_degrees() < 0.1,
            "{actual} vs {planned}"
        );
    }
}

#[test]
fn the_link_holds_until_motors_are_on_and_the_clock_follows_the_robot() {
    let _cycles = one_at_a_time();
    let settings = shipped_run_settings();
    let period = settings.period();
    let egm = EgmLinkSettings::for_rig(&settings.rig, axes(&settings), period, None);
    let mut link = bind_egm("127.0.0.1:0", egm).expect("bind");
    let egm = EgmTwinSettings {
        motors_on: false,
        ..EgmTwinSettings::default()
    };
    let control = Arc::new(EgmTwinControl::default());
    let twin = twin_towards(&settings, link.local_address(), egm);
    let twin = spawn_egm_twin(twin, control.clone()).expect("twin thread");
    wait_for("robot messages", PATIENCE, || link.state().replies >= 25);
    let state = link.state();
    assert_eq!(state.motors, MotorState::Off);
    assert!(!link.is_up(), "no motion while the motors are off");
    let clock = link.clock();
    control.motors_on();
    wait_for("motors on and EGM running", PATIENCE, || link.is_up());
    // Device time: one period per EgmRobot, so a wait of 10 periods spans 10 messages.
    let before = link.state().messages;
    let start = clock.now();
    clock.sleep_until(start + period * 10);
    let spanned = link.state().messages - before;
    assert!(
        (10..=11).contains(&spanned),
        "{spanned} messages in 10 periods"
    );
    // The answer is the feedback position at rest, the very position the robot reports.
    link.send(&rigbridge::protocol::Command::Heartbeat)
        .expect("heartbeat");
    let feedback = link.receive(PATIENCE).expect("link").expect("feedback");
    for (actual, initial) in feedback.positions.as_slice().iter().zip(settings.initial()) {
        assert!((actual - initial).abs() < 1e-9);
    }
    control.stop.store(true, Ordering::SeqCst);
    let counters = twin.join().expect("twin").model().counters;
    assert_eq!(counters.violations(), 0, "{counters:?}");
    assert_eq!(counters.sessions, 1);
}

#[test]
fn without_replies_the_twin_ends_the_session_in_hold_after_comm_timeout() {
    let _cycles = one_at_a_time();
    let settings = shipped_run_settings();
    let egm = EgmTwinSettings {
        comm_timeout: Duration::from_millis(200),
        ..EgmTwinSettings::default()
    };
    let (sensor, control, twin) = twin_towards_a_socket(&settings, egm);
    let read_from = |sensor: &UdpSocket| {
        let mut buffer = [0u8; 2048];
        let (len, from) = sensor.recv_from(&mut buffer).expect("an EgmRobot");
        (EgmRobot::decode(&buffer[..len]).expect("decodes"), from)
    };
    let read = || read_from(&sensor).0;
    assert_eq!(read().mci(), MciState::Running);
    let started = Instant::now();
    wait_for("the comm timeout", PATIENCE, || {
        read().mci() == MciState::Stopped
    });
    assert!(started.elapsed() >= Duration::from_millis(150));
    // Still streaming state, motors on, at the same position: HOLD, not a motors-off stop.
    let held = read();
    assert_eq!(held.motors(), MotorState::On);
    let joints = held.feedback_joints().expect("joints").to_vec();
    for (actual, initial) in joints.iter().zip(settings.initial()) {
        assert!((actual.to_radians() - initial).abs() < 1e-9);
    }
    // A sensor answering again does not restart it: RAPID must run EGMRunJoint again.
    let reply = EgmSensor::joint_correction(1, 0, &axes(&settings), &settings.initial(), &[0.0; 6]);
    let twin_address = read_from(&sensor).1;
    sensor
        .send_to(&reply.encode_to_vec(), twin_address)
        .expect("send");
    assert_eq!(read().mci(), MciState::Stopped);
    control.start_session();
    wait_for("a new session", PATIENCE, || {
        read().mci() == MciState::Running
    });
    control.stop.store(true, Ordering::SeqCst);
    let counters = twin.join().expect("twin").model().counters;
    assert_eq!(counters.comm_timeouts, 1);
    assert_eq!(counters.sessions, 2);
}

#[test]
fn a_reference_jump_is_refused_with_mci_error_and_no_motion() {
    let _cycles = one_at_a_time();
    let settings = shipped_run_settings();
    let (sensor, control, twin) = twin_towards_a_socket(&settings, EgmTwinSettings::default());
    let mut buffer = [0u8; 2048];
    let (_, twin_address) = sensor.recv_from(&mut buffer).expect("an EgmRobot");
    // 5 degrees in one 4 ms cycle is 1250 deg/s: far over joint 1's 250 deg/s.
    let mut jump = settings.initial();
    jump[0] += 5f64.to_radians();
    let reply = EgmSensor::joint_correction(1, 0, &axes(&settings), &jump, &[0.0; 6]);
    sensor
        .send_to(&reply.encode_to_vec(), twin_address)
        .expect("send");
    wait_for("the refusal", PATIENCE, || {
        let (len, _) = sensor.recv_from(&mut buffer).expect("an EgmRobot");
        EgmRobot::decode(&buffer[..len]).expect("decodes").mci() == MciState::Error
    });
    control.stop.store(true, Ordering::SeqCst);
    let twin = twin.join().expect("twin");
    assert_eq!(twin.model().counters.over_speed, 1);
    for (actual, initial) in twin.model().position().iter().zip(settings.initial()) {
        assert!((actual - initial).abs() < 1e-9, "the robot did not move");
    }
}

/// The Python with abb-robot-client (RIGBRIDGE_EGM_PYTHON, set by scripts/test.sh).
fn peer_python() -> Result<String, String> {
    common::peer_python(
        "RIGBRIDGE_EGM_PYTHON",
        "abb_robot_client.egm",
        "abb_robot_client",
    )
}

#[test]
fn the_egm_twin_serves_abb_robot_clients_egm_sensor() {
    let _cycles = one_at_a_time();
    real_time();
    let python = match peer_python() {
        Ok(python) => python,
        Err(reason) => {
            println!("skipping the abb-robot-client peer test: {reason}");
            return;
        }
    };
    use std::io::BufRead;
    let script = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/peers/egm_sensor.py");
    let mut peer = std::process::Command::new(python)
        .arg(script)
        .stdout(std::process::Stdio::piped())
        .spawn()
        .expect("the peer starts");
    let mut lines = std::io::BufReader::new(peer.stdout.take().expect("stdout")).lines();
    let port: u16 = lines
        .next()
        .expect("a port line")
        .expect("readable")
        .trim()
        .parse()
        .expect("a port");
    let settings = shipped_run_settings();
    let control = Arc::new(EgmTwinControl::default());
    let sensor: SocketAddr = ([127, 0, 0, 1], port).into();
    let twin = twin_towards(&settings, sensor, EgmTwinSettings::default());
    let twin = spawn_egm_twin(twin, control.clone()).expect("twin thread");
    let report = lines.next().expect("a report line").expect("readable");
    let status = peer.wait().expect("the peer ends");
    control.stop.store(true, Ordering::SeqCst);
    let twin = twin.join().expect("twin");
    assert!(status.success(), "peer failed: {report}");
    let report: serde_json::Value = serde_json::from_str(&report).expect("JSON report");
    let degrees = |key: &str| -> Vec<f64> {
        report[key]
            .as_array()
            .unwrap_or_else(|| panic!("{key} in {report}"))
            .iter()
            .map(|v| v.as_f64().expect("a number"))
            .collect()
    };
    assert_eq!(report["motors_on"], true);
    assert_eq!(report["rapid_running"], true);
    let initial: Vec<f64> = settings.initial().iter().map(|r| r.to_degrees()).collect();
    for (seen, initial) in degrees("first").iter().zip(&initial) {
        assert!((seen - initial).abs() < 1e-6, "{seen} vs {initial}");
    }
    let (commanded, planned, last) = (degrees("commanded"), degrees("planned"), degrees("final"));
    assert!((commanded[0] - initial[0] - 10.0).abs() < 1e-9);
    for axis in 0..6 {
        assert!(
            (planned[axis] - commanded[axis]).abs() < 1e-9,
            "planned echoes"
        );
        assert!(
            (last[axis] - commanded[axis]).abs() < 0.05,
            "axis {axis}: {last:?}"
        );
    }
    let counters = twin.model().counters;
    assert_eq!(counters.violations(), 0, "{counters:?}");
    assert_eq!(counters.comm_timeouts, 0);
}

/// Run settings for the painter rig (base_x, base_y, base_yaw, lift, then the IRB 120)
/// with `job` and `section`, written to a file of their own.
fn painter_settings(name: &str, section: &str, job: &str) -> RunSettings {
    let rig = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("config/painter.toml");
    let dir = std::env::temp_dir().join(format!("rigbridge-egm-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    let file = dir.join(name);
    let text = format!(
        "rig = {rig:?}\n[twin]\ninitial_deg = [0, 0, 0, 0, 0, 0, 0, 0, 30, 0]\n{section}\n[job]\n{job}\n"
    );
    std::fs::write(&file, text).expect("write");
    load_run_settings(&file).expect("the painter settings load")
}

#[test]
fn the_painter_s_base_and_lift_travel_as_external_axes_and_its_job_completes() {
    let _cycles = one_at_a_time();
    real_time();
    // Metres on base_x, base_y and lift, degrees elsewhere.
    let job = "kind = \"move_joints\"\ntargets_deg = [[0.3, -0.2, 20.0, 0.4, 20.0, 10.0, 10.0, 0.0, 40.0, 5.0]]";
    let settings = painter_settings("painter-egm.toml", "", job);
    let (_, twin, link) = job_against_the_twin(&settings);
    let counters = twin.model().counters;
    assert_eq!(counters.violations(), 0, "{counters:?}");
    assert_eq!(counters.sessions, 1, "{counters:?}");
    assert_eq!(link.state().malformed, 0);
    // The twin got there: within 1 mm on the linear axes, 0.1 deg on the others.
    let target = [
        0.3,
        -0.2,
        20f64.to_radians(),
        0.4,
        20f64.to_radians(),
        10f64.to_radians(),
        10f64.to_radians(),
        0.0,
        40f64.to_radians(),
        5f64.to_radians(),
    ];
    let linear = [0, 1, 3];
    for (axis, (actual, wanted)) in twin.model().position().iter().zip(target).enumerate() {
        let within = if linear.contains(&axis) {
            1e-3
        } else {
            0.1f64.to_radians()
        };
        assert!(
            (actual - wanted).abs() < within,
            "axis {axis}: {actual} vs {wanted}"
        );
    }
}

#[test]
fn external_axes_that_leave_more_than_six_robot_joints_are_refused_on_load() {
    let rig = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("config/painter.toml");
    let dir = std::env::temp_dir().join(format!("rigbridge-egm-bad-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    let file = dir.join("short-list.toml");
    let text = format!(
        "rig = {rig:?}\n[stream]\nlink = \"egm://127.0.0.1:6510\"\n[egm]\nexternal_axes = [\"base_x\", \"lift\"]\n[twin]\ninitial_deg = [0, 0, 0, 0, 0, 0, 0, 0, 30, 0]\n[job]\nkind = \"move_joints\"\ntargets_deg = [[0, 0, 0, 0, 0, 0, 0, 0, 30, 0]]\n"
    );
    std::fs::write(&file, text).expect("write");
    let error = load_run_settings(&file).expect_err("refused").to_string();
    for part in [
        "short-list.toml",
        "egm.external_axes",
        "[base_x, lift]",
        "8 robot joints",
    ] {
        assert!(error.contains(part), "{part} in {error}");
    }
}
