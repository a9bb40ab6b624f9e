//! EGM end to end over real UDP on 127.0.0.1: the bridge's EGM link against our EGM twin
//! (the default job completes, the twin refuses nothing), the twin's sessions (motors,
//! CommTimeout), and the twin against abb-robot-client's `EGM` sensor (tests/peers/).

use crate::common;

use common::cycles::{one_at_a_time, real_time, wait_for};
use common::shipped_run_settings;

use prost::Message;
use rigbridge::clock::Clock;
use rigbridge::daemon::config::{RunSettings, load_run_settings};
use rigbridge::daemon::{RunReport, run_job};
use rigbridge::device::egm::twin::{
    EgmRobotModel, EgmTwin, EgmTwinControl, EgmTwinSettings, spawn_egm_twin,
};
use rigbridge::device::egm::wire::{
    EgmAxes, EgmKinematics, EgmMode, EgmRobot, EgmSensor, MciState, MotorState, RapidState,
};
use rigbridge::device::egm::{EgmLink, EgmLinkSettings, bind_egm};
use rigbridge::link::Link;
use rigbridge::stream::{Outcome, StreamControl};
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
    job_in_mode(settings, EgmMode::Joint)
}

/// The twin's settings as `settings` configure them: its delay, in `mode`.
fn configured(settings: &RunSettings, mode: EgmMode) -> EgmTwinSettings {
    EgmTwinSettings {
        delay: settings.twin_delay(),
        mode,
        ..EgmTwinSettings::default()
    }
}

/// A twin in pose mode, with the project's IK as its controller's kinematics.
fn pose_twin_towards(settings: &RunSettings, sensor: SocketAddr) -> EgmTwin {
    let solver = rigbridge::ik::FabrikSolver::new(settings.rig.clone()).expect("FABRIK");
    let model = EgmRobotModel::new(
        &settings.rig,
        axes(settings),
        configured(settings, EgmMode::Pose),
        &settings.initial(),
    )
    .expect("model")
    .with_pose_solver(Box::new(solver));
    EgmTwin::new(model, sensor).expect("twin socket")
}

/// [`job_against_the_twin`] with the link and the twin in `mode`.
fn job_in_mode(settings: &RunSettings, mode: EgmMode) -> (RunReport, EgmTwin, EgmLink) {
    let period = settings.period();
    let egm = EgmLinkSettings::for_rig(&settings.rig, axes(settings), period, None).in_mode(mode);
    let mut link = bind_egm("127.0.0.1:0", egm).expect("bind");
    let control = Arc::new(EgmTwinControl::default());
    let twin = match mode {
        EgmMode::Joint => twin_towards(settings, link.local_address(), configured(settings, mode)),
        EgmMode::Pose => pose_twin_towards(settings, link.local_address()),
    };
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
    // EGMRunJoint raised ERR_UDPUC_COMM, which stops RAPID (the program has no handler).
    let held = read();
    assert_eq!(held.motors(), MotorState::On);
    assert_eq!(held.rapid(), RapidState::Stopped);
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
        let robot = read();
        robot.mci() == MciState::Running && robot.rapid() == RapidState::Running
    });
    control.stop.store(true, Ordering::SeqCst);
    let counters = twin.join().expect("twin").model().counters;
    assert_eq!(counters.comm_timeouts, 1);
    assert_eq!(counters.sessions, 2);
}

/// Sends `reply` to the twin every time an EgmRobot comes, `cycles` times; the last EgmRobot.
fn answer_with(
    sensor: &UdpSocket,
    cycles: usize,
    mut reply: impl FnMut(usize, &EgmRobot) -> EgmSensor,
) -> EgmRobot {
    let mut buffer = [0u8; 2048];
    let mut last = None;
    for cycle in 0..cycles {
        let (len, from) = sensor.recv_from(&mut buffer).expect("an EgmRobot");
        let robot = EgmRobot::decode(&buffer[..len]).expect("decodes");
        let message = reply(cycle, &robot);
        sensor
            .send_to(&message.encode_to_vec(), from)
            .expect("send");
        last = Some(robot);
    }
    last.expect("at least one cycle")
}

#[test]
fn a_reference_step_is_followed_within_max_speed_deviation_not_refused() {
    let _cycles = one_at_a_time();
    let settings = shipped_run_settings();
    let (sensor, control, twin) = twin_towards_a_socket(&settings, EgmTwinSettings::default());
    // 5 degrees in one 4 ms cycle is 1250 deg/s, far over joint 1's 250 deg/s: a real
    // controller filters the reference and caps the correction at MaxSpeedDeviation.
    let mut step = settings.initial();
    step[0] += 5f64.to_radians();
    let reply = EgmSensor::joint_correction(1, 0, &axes(&settings), &step, &[0.0; 6]);
    // 0.1 s: at 25 deg/s at most, joint 1 moves no more than 2.5 deg.
    let early = answer_with(&sensor, 25, |_, _| reply.clone());
    assert_eq!(early.mci(), MciState::Running, "a step is not refused");
    let moved = early.feedback_joints().expect("joints")[0] - settings.initial()[0].to_degrees();
    assert!(
        moved > 0.5 && moved <= 25.0 * 0.1 + 0.01,
        "joint 1 moved {moved} deg in 0.1 s"
    );
    // 0.6 s more: there, within 0.1 deg.
    let late = answer_with(&sensor, 150, |_, _| reply.clone());
    assert_eq!(late.mci(), MciState::Running);
    let error = late.feedback_joints().expect("joints")[0] - step[0].to_degrees();
    assert!(error.abs() < 0.1, "joint 1 is {error} deg from the step");
    control.stop.store(true, Ordering::SeqCst);
    let counters = twin.join().expect("twin").model().counters;
    assert_eq!(counters.over_speed, 1, "{counters:?}");
    assert_eq!(counters.outside_limits, 0);
}

#[test]
fn a_reference_outside_the_limits_ends_the_session_with_mci_error_and_stops_rapid() {
    let _cycles = one_at_a_time();
    let settings = shipped_run_settings();
    let (sensor, control, twin) = twin_towards_a_socket(&settings, EgmTwinSettings::default());
    // Joint 3's upper limit is 70 deg: 70.5 is outside, however slowly it is approached.
    let mut outside = settings.initial();
    outside[2] = 70.5f64.to_radians();
    let reply = EgmSensor::joint_correction(1, 0, &axes(&settings), &outside, &[0.0; 6]);
    let mut buffer = [0u8; 2048];
    let (_, twin_address) = sensor.recv_from(&mut buffer).expect("an EgmRobot");
    sensor
        .send_to(&reply.encode_to_vec(), twin_address)
        .expect("send");
    wait_for("the refusal", PATIENCE, || {
        let (len, _) = sensor.recv_from(&mut buffer).expect("an EgmRobot");
        let robot = EgmRobot::decode(&buffer[..len]).expect("decodes");
        robot.mci() == MciState::Error && robot.rapid() == RapidState::Stopped
    });
    control.stop.store(true, Ordering::SeqCst);
    let twin = twin.join().expect("twin");
    assert_eq!(twin.model().counters.outside_limits, 1);
    for (actual, initial) in twin.model().position().iter().zip(settings.initial()) {
        assert!((actual - initial).abs() < 1e-9, "the robot did not move");
    }
}

#[test]
fn pose_mode_follows_a_20_mm_sine_along_x_at_0_2_hz() {
    let _cycles = one_at_a_time();
    real_time();
    let settings = shipped_run_settings();
    let sensor = UdpSocket::bind("127.0.0.1:0").expect("sensor socket");
    sensor
        .set_read_timeout(Some(Duration::from_secs(1)))
        .expect("timeout");
    let control = Arc::new(EgmTwinControl::default());
    let twin = pose_twin_towards(&settings, sensor.local_addr().expect("addr"));
    let twin = spawn_egm_twin(twin, control.clone()).expect("twin thread");
    let kinematics = EgmKinematics {
        rig: settings.rig.clone(),
        axes: axes(&settings),
    };
    let start = kinematics.pose(&settings.initial());
    const AMPLITUDE_M: f64 = 0.020;
    const FREQUENCY_HZ: f64 = 0.2;
    let dt = settings.period().as_secs_f64();
    // One period of the sine, 5 s; then 0.5 s at its end.
    let cycles = (1.0 / FREQUENCY_HZ / dt).round() as usize;
    // x = A (1 - cos wt): a sine of amplitude A about x + A, starting and ending at rest
    // (a sine cut at full speed would ask for a step in speed).
    let x_at = |cycle: usize| {
        let t = (cycle.min(cycles) as f64) * dt;
        AMPLITUDE_M * (1.0 - (std::f64::consts::TAU * FREQUENCY_HZ * t).cos())
    };
    let mut worst_m: f64 = 0.0;
    let mut worst_rad: f64 = 0.0;
    let mut sum_squares = 0.0;
    let mut samples = 0;
    let end = answer_with(&sensor, cycles + 125, |cycle, robot| {
        assert_eq!(robot.mci(), MciState::Running, "cycle {cycle}");
        let actual = robot.feedback_pose().expect("the feedback pose");
        if cycle > 0 {
            // The pose commanded the cycle before: this reply answers that message.
            let mut wanted = start;
            wanted.position.x += x_at(cycle - 1);
            let error = actual.position_error(&wanted);
            worst_m = worst_m.max(error);
            worst_rad = worst_rad.max(actual.orientation_error(&wanted));
            sum_squares += error * error;
            samples += 1;
        }
        let mut target = start;
        target.position.x += x_at(cycle);
        let mut message = EgmSensor::pose_correction(1, 0, &kinematics, &[0.0; 6], &[0.0; 6]);
        message.planned.as_mut().expect("planned").cartesian =
            Some(rigbridge::device::egm::wire::EgmPose::from_pose(&target));
        message
    });
    control.stop.store(true, Ordering::SeqCst);
    let twin = twin.join().expect("twin");
    let counters = twin.model().counters;
    let rms = (sum_squares / f64::from(samples)).sqrt();
    println!(
        "pose mode, 20 mm amplitude sine along x at 0.2 Hz for 5 s: tracking error max {:.3} mm, rms {:.3} mm, orientation max {:.2e} rad; refused {}, over speed {}, over acceleration {}",
        worst_m * 1e3,
        rms * 1e3,
        worst_rad,
        counters.outside_limits + counters.unreachable,
        counters.over_speed,
        counters.over_acceleration
    );
    assert_eq!(
        counters.unreachable + counters.outside_limits,
        0,
        "{counters:?}"
    );
    assert_eq!(
        counters.over_speed + counters.over_acceleration,
        0,
        "{counters:?}"
    );
    // 25 mm/s at most; the delay (12 ms), the filter and the servo lag keep it ~30 ms behind.
    assert!(worst_m < 2e-3, "tracking error {worst_m} m");
    assert!(worst_rad < 1e-3, "orientation error {worst_rad} rad");
    // At the end, at rest: within 0.1 mm of the last pose.
    let mut last = start;
    last.position.x += x_at(cycles);
    let settled = end.feedback_pose().expect("pose").position_error(&last);
    assert!(settled < 1e-4, "{settled} m from the last pose");
}

#[test]
fn pose_mode_refuses_an_unreachable_pose_with_mci_error() {
    let _cycles = one_at_a_time();
    let settings = shipped_run_settings();
    let sensor = UdpSocket::bind("127.0.0.1:0").expect("sensor socket");
    sensor
        .set_read_timeout(Some(Duration::from_secs(1)))
        .expect("timeout");
    let control = Arc::new(EgmTwinControl::default());
    let twin = pose_twin_towards(&settings, sensor.local_addr().expect("addr"));
    let twin = spawn_egm_twin(twin, control.clone()).expect("twin thread");
    let kinematics = EgmKinematics {
        rig: settings.rig.clone(),
        axes: axes(&settings),
    };
    // 2 m in front of the base: the IRB 120 reaches 0.58 m.
    let mut far = kinematics.pose(&settings.initial());
    far.position.x = 2.0;
    let mut message = EgmSensor::pose_correction(1, 0, &kinematics, &[0.0; 6], &[0.0; 6]);
    message.planned.as_mut().expect("planned").cartesian =
        Some(rigbridge::device::egm::wire::EgmPose::from_pose(&far));
    let mut refused = false;
    for _ in 0..250 {
        let robot = answer_with(&sensor, 1, |_, _| message.clone());
        if robot.mci() == MciState::Error {
            assert_eq!(robot.rapid(), RapidState::Stopped);
            refused = true;
            break;
        }
    }
    control.stop.store(true, Ordering::SeqCst);
    let twin = twin.join().expect("twin");
    assert!(refused, "the session ended with MCI_ERROR");
    assert_eq!(twin.model().counters.unreachable, 1);
    for (actual, initial) in twin.model().position().iter().zip(settings.initial()) {
        assert!((actual - initial).abs() < 1e-9, "the robot did not move");
    }
}

#[test]
fn a_cartesian_job_runs_in_pose_mode_and_the_controller_s_joints_stay_within_limits() {
    let _cycles = one_at_a_time();
    real_time();
    let job = "kind = \"move_linear\"\nspeed_m_s = 0.1\nposes = [{ xyz_m = [0.40, -0.05, 0.45], quat_wxyz = [0.7071068, 0.0, 0.7071068, 0.0] }, { xyz_m = [0.40, 0.05, 0.40], quat_wxyz = [0.7071068, 0.0, 0.7071068, 0.0] }]";
    let settings = irb120_settings("pose-mode.toml", job);
    let (report, twin, link) = job_in_mode(&settings, EgmMode::Pose);
    let counters = twin.model().counters;
    println!(
        "pose mode move_linear: {} cycles, tracking max {:.4} deg, twin: {counters:?}",
        report.stream.cycles,
        counters.tracking_max_rad.to_degrees()
    );
    assert_eq!(report.stream.limit_violations, 0);
    // The controller's own IK found joints within limits, speed and acceleration throughout.
    assert_eq!(counters.violations(), 0, "{counters:?}");
    assert_eq!(counters.sessions, 1);
    assert_eq!(link.state().malformed, 0);
    let kinematics = EgmKinematics {
        rig: settings.rig.clone(),
        axes: axes(&settings),
    };
    let end = kinematics.pose(twin.model().position());
    let wanted = glam::DVec3::new(0.40, 0.05, 0.40);
    assert!(
        end.position.distance(wanted) < 1e-3,
        "the tool ended at {}",
        end
    );
}

/// Run settings for the IRB 120 with `job`, written to a file of their own.
fn irb120_settings(name: &str, job: &str) -> RunSettings {
    let rig = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("config/irb120.toml");
    let dir = std::env::temp_dir().join(format!("rigbridge-egm-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    let file = dir.join(name);
    let text = format!("rig = {rig:?}\n[twin]\ninitial_deg = [0, 0, 0, 0, 30, 0]\n[job]\n{job}\n");
    std::fs::write(&file, text).expect("write");
    load_run_settings(&file).expect("the IRB 120 settings load")
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

/// The seconds of the libegm peer's joint-mode session: `RIGBRIDGE_EGM_SOAK_S` when set (the
/// figure in docs/egm.md is a 30 s run), else 8 s to keep the suite short.
fn libegm_session_seconds() -> f64 {
    std::env::var("RIGBRIDGE_EGM_SOAK_S")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(8.0)
}

#[test]
fn the_egm_twin_gives_abb_libegm_all_it_requires_and_survives_a_repeated_reply_every_10th_cycle() {
    let _cycles = one_at_a_time();
    real_time();
    let python = match peer_python() {
        Ok(python) => python,
        Err(reason) => {
            println!("skipping the abb_libegm peer test: {reason}");
            return;
        }
    };
    use std::io::BufRead;
    let seconds = libegm_session_seconds();
    let script = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/peers/libegm_sensor.py");
    let dump = std::env::temp_dir().join(format!("rigbridge-libegm-{}.jsonl", std::process::id()));
    // Joint 1 on a 30 deg sine (47 deg/s at most): a repeated reply is a speed step far
    // over the IRB 120's acceleration, which a controller filters.
    let mut peer = std::process::Command::new(python)
        .arg(script)
        .args([seconds.to_string(), "10".into(), "30".into()])
        .arg(&dump)
        .stdout(std::process::Stdio::piped())
        .spawn()
        .expect("the peer starts");
    let mut lines = std::io::BufReader::new(peer.stdout.take().expect("stdout")).lines();
    let mut line = || lines.next().expect("a line").expect("readable");
    let port: u16 = line().trim().parse().expect("a port");
    let settings = shipped_run_settings();
    let control = Arc::new(EgmTwinControl::default());
    let sensor: SocketAddr = ([127, 0, 0, 1], port).into();
    let egm = EgmTwinSettings {
        comm_timeout: Duration::from_millis(200),
        ..configured(&settings, EgmMode::Joint)
    };
    let twin = twin_towards(&settings, sensor, egm);
    let twin = spawn_egm_twin(twin, control.clone()).expect("twin thread");
    assert_eq!(line(), "timed out");
    control.start_session();
    let report = line();
    let status = peer.wait().expect("the peer ends");
    control.stop.store(true, Ordering::SeqCst);
    let twin = twin.join().expect("twin");
    assert!(status.success(), "peer failed: {report}");
    let report: serde_json::Value = serde_json::from_str(&report).expect("JSON report");
    let counters = twin.model().counters;
    println!("abb_libegm peer, {seconds} s: {report}\ntwin: {counters:?}");
    // Every message passes abb_libegm's parse checks.
    assert_eq!(report["refused"], 0, "{report}");
    assert!(report["messages"].as_u64().expect("a count") as f64 > seconds / 0.004);
    // Each session's first message is numbered 0; numbers go up by one within a session.
    let sessions = report["sessions"].as_array().expect("sessions");
    assert_eq!(sessions.len(), 2, "{report}");
    for session in sessions {
        assert_eq!(session["first_seqno"], 0, "{report}");
    }
    assert_eq!(report["seqno_gaps"], 0, "{report}");
    // The robot time advances one 4 ms cycle a message (abb_libegm's sample time estimate).
    assert_eq!(report["time_not_advancing"], 0, "{report}");
    for bound in [0, 1] {
        assert_eq!(
            report["sample_time_ms"][bound].as_f64(),
            Some(4.0),
            "{report}"
        );
    }
    // The repeated replies: the session stayed running throughout.
    assert!(report["repeats"].as_u64().expect("a count") as f64 >= seconds / 0.004 / 10.0 - 2.0);
    assert_eq!(report["not_running_while_replying"], 0, "{report}");
    assert!(counters.repeated > 0, "{counters:?}");
    assert_eq!(
        counters.outside_limits + counters.axis_count,
        0,
        "{counters:?}"
    );
    assert_eq!(counters.comm_timeouts, 1, "{counters:?}");
    assert_eq!(counters.sessions, 2, "{counters:?}");
    // After the CommTimeout: EGM stopped, RAPID stopped (ERR_UDPUC_COMM), motors on.
    assert_eq!(report["after_timeout"]["mci"], MciState::Stopped as i32);
    assert_eq!(report["after_timeout"]["rapid"], RapidState::Stopped as i32);
    assert_eq!(report["after_timeout"]["motors"], MotorState::On as i32);
    // Every EgmRobot carries the FK pose of its joints: within 1e-6 m and 1e-6 rad.
    let (mut worst_m, mut worst_rad, mut checked) = (0f64, 0f64, 0);
    for line in std::fs::read_to_string(&dump).expect("the dump").lines() {
        let message: serde_json::Value = serde_json::from_str(line).expect("a JSON line");
        for part in ["feedback", "planned"] {
            let numbers = |key: String| -> Vec<f64> {
                message[&key]
                    .as_array()
                    .expect("numbers")
                    .iter()
                    .map(|v| v.as_f64().expect("a number"))
                    .collect()
            };
            let joints: Vec<f64> = numbers(format!("{part}_joints"))
                .iter()
                .map(|d| d.to_radians())
                .collect();
            let pose = numbers(format!("{part}_pose"));
            // The IRB 120's base frame is the rig's: our FK is the rig's tool pose.
            let ours = settings.rig.tool_pose(&joints).expect("six joints");
            let position = glam::DVec3::new(pose[0], pose[1], pose[2]) / 1000.0;
            let orientation = glam::DQuat::from_xyzw(pose[4], pose[5], pose[6], pose[3]);
            assert!(
                (orientation.length() - 1.0).abs() < 1e-9,
                "a unit quaternion"
            );
            worst_m = worst_m.max(position.distance(ours.position));
            worst_rad = worst_rad.max(rigbridge::rig::rotation_angle_between(
                orientation,
                ours.orientation,
            ));
            checked += 1;
        }
    }
    let _ = std::fs::remove_file(&dump);
    println!(
        "FK in {checked} poses: position within {worst_m:.2e} m, orientation {worst_rad:.2e} rad"
    );
    assert!(checked > 0);
    assert!(worst_m < 1e-6, "{worst_m} m");
    assert!(worst_rad < 1e-6, "{worst_rad} rad");
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
