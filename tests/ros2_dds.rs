//! ROS 2 over DDS against a peer we did not write: a real ROS 2 Jazzy node, PyPI's
//! `ros-jazzy-rclpy` on Fast DDS (tests/peers/ros2_dds_peer.py). `run` streams joint states
//! that rclpy receives at 100 Hz or more without a gap, and the ROS 2 graph shows the rig's
//! node publishing `/tf`, `/tf_static` and its robot description with ROS 2's QoS; under
//! `serve`, a subscriber that comes late still gets the robot description, the very URDF
//! `rigbridge config urdf` writes. Also the `[ros2] middleware` settings.
//!
//! Loopback only: rigbridge's `discovery_range = "localhost"` (the default) keeps its DDS
//! participant on 127.0.0.1, and Fast DDS is kept there by tests/peers/fastdds_loopback.xml
//! (with `ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`, Jazzy's Fast DDS still advertises the
//! host's other addresses, docs/ros2.md). Each test has a DDS domain of its own.

use crate::common;

use common::cli::{assert_succeeded, rigbridge};
use common::line_peer::LinePeer;
use common::repo_path;
use common::serve::{serve_command, start_serve};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Duration;

/// JointState messages a second the issue asks for.
const MIN_JOINT_STATE_HZ: f64 = 100.0;
/// `[ros2] joint_states_hz` when absent (`rigbridge::ros2::DEFAULT_JOINT_STATES_HZ`): the
/// rate the peer measures gaps against, written here as docs/ros2.md states it.
const JOINT_STATES_HZ: f64 = 125.0;
/// How long `serve` has published before the late subscriber comes: long past discovery,
/// so the description it gets was kept for it, not sent while it joined.
const LATE_BY: Duration = Duration::from_secs(3);

/// The Python with rclpy (RIGBRIDGE_RCLPY_PYTHON, set by scripts/test.sh), or `None` with a
/// note; on CI a missing peer fails.
fn peer_python() -> Option<String> {
    match common::peer_python(
        "RIGBRIDGE_RCLPY_PYTHON",
        "rclpy, sensor_msgs.msg, std_msgs.msg",
        "ros-jazzy-rclpy, ros-jazzy-sensor-msgs and ros-jazzy-std-msgs",
    ) {
        Ok(python) => Some(python),
        Err(reason) if std::env::var("CI").as_deref() == Ok("true") => {
            panic!("CI must test ROS 2 over DDS against PyPI's rclpy: {reason}")
        }
        Err(reason) => {
            println!("skipping the ROS 2 DDS peer test: {reason}");
            None
        }
    }
}

/// The Python with rclpy and control_msgs' FollowJointTrajectory (built by scripts/test.sh
/// with the rosidl generators), or `None` with a note; on CI a missing peer fails.
fn action_python() -> Option<String> {
    match common::peer_python(
        "RIGBRIDGE_RCLPY_PYTHON",
        "rclpy, control_msgs.action, trajectory_msgs.msg, sensor_msgs.msg",
        "ros-jazzy-rclpy with control_msgs built from tests/peers/control_msgs",
    ) {
        Ok(python) => Some(python),
        Err(reason) if std::env::var("CI").as_deref() == Ok("true") => {
            panic!("CI must test FollowJointTrajectory against PyPI's rclpy: {reason}")
        }
        Err(reason) => {
            println!("skipping the FollowJointTrajectory peer test: {reason}");
            None
        }
    }
}

fn scratch(name: &str) -> PathBuf {
    common::scratch_dir("ros2-dds", name)
}

/// The shipped run settings (the IRB 120 tracing its star) with `ros2` as the body of a
/// `[ros2]` table.
fn settings(dir: &Path, ros2: &str) -> PathBuf {
    let text = common::with_absolute_cell(
        &std::fs::read_to_string(repo_path("config/rigbridge.toml")).unwrap(),
    )
    .replacen(
        "rig = \"irb120.toml\"",
        &format!("rig = \"{}\"", repo_path("config/irb120.toml").display()),
        1,
    ) + &format!("\n[ros2]\n{ros2}");
    let file = dir.join("run.toml");
    std::fs::write(&file, text).unwrap();
    file
}

/// The rclpy peer in DDS domain `domain`, on loopback, once its subscriptions exist.
fn start_peer(python: &str, domain: u32, dir: &Path, args: &[&str]) -> LinePeer {
    start_rclpy(python, "tests/peers/ros2_dds_peer.py", domain, dir, args)
}

/// The rclpy action client (tests/peers/ros2_fjt_client.py) in DDS domain `domain`, once
/// it has found the rig's action server or trajectory subscriber.
fn start_client(python: &str, domain: u32, dir: &Path, args: &[&str]) -> LinePeer {
    start_rclpy(python, "tests/peers/ros2_fjt_client.py", domain, dir, args)
}

/// The rclpy `script` in DDS domain `domain`, its discovery kept to loopback by Fast DDS's
/// profile, its ROS logs in `dir`.
fn start_rclpy(python: &str, script: &str, domain: u32, dir: &Path, args: &[&str]) -> LinePeer {
    let mut command = Command::new(python);
    command
        .arg(repo_path(script))
        .args(args)
        .env("ROS_DOMAIN_ID", domain.to_string())
        .env("ROS_AUTOMATIC_DISCOVERY_RANGE", "SYSTEM_DEFAULT")
        .env(
            "FASTRTPS_DEFAULT_PROFILES_FILE",
            repo_path("tests/peers/fastdds_loopback.xml"),
        )
        .env("ROS_LOG_DIR", dir.join("ros-log"));
    LinePeer::start(command)
}

/// `serve` with motion over DDS consented to, in domain `domain`.
fn serve_with_motion(dir: &Path, domain: u32) -> common::serve::Served {
    let ros2 = format!(
        "domain_id = {domain}\naccept_motion = true\nallow_unauthenticated_motion = true\n"
    );
    let config = settings(dir, &ros2);
    let mut command = serve_command(&dir.join("runs"));
    start_serve(command.arg("--config").arg(&config).stderr(Stdio::null()))
}

/// FollowJointTrajectory's result codes and action_msgs' goal statuses, as control_msgs
/// and action_msgs define them (the client reports the numbers).
const SUCCESSFUL: i64 = 0;
const INVALID_GOAL: i64 = -1;
const INVALID_JOINTS: i64 = -2;
const STATUS_SUCCEEDED: i64 = 4;
const STATUS_CANCELED: i64 = 5;
const STATUS_ABORTED: i64 = 6;
/// The feedback rate the issue asks for.
const MIN_FEEDBACK_HZ: f64 = 50.0;
/// How far from its path an arm braked to rest may be (rad): the stream brakes along the
/// path, so only the controller's following error remains.
const ON_PATH_RAD: f64 = 1e-3;

#[test]
fn rclpy_follow_joint_trajectory_goals_complete_and_a_cancel_rests_on_the_path() {
    let Some(python) = action_python() else {
        return;
    };
    const DOMAIN: u32 = 44;
    let dir = scratch("fjt-motion");
    let _daemon = serve_with_motion(&dir, DOMAIN);
    let client = start_client(&python, DOMAIN, &dir, &["motion", "--rig", "irb120"]);
    let result = client.result();
    let complete = &result["complete"];
    println!(
        "10 s goal: status {}, code {}, {} feedback messages at {:.1} Hz (longest gap {:.4} s), \
         {:.2} s",
        complete["status"],
        complete["error_code"],
        complete["feedback"],
        complete["feedback_hz"].as_f64().unwrap_or(0.0),
        complete["feedback_max_gap_s"].as_f64().unwrap_or(0.0),
        complete["seconds"].as_f64().unwrap_or(0.0)
    );
    assert_eq!(complete["accepted"], true, "{result}");
    assert_eq!(complete["status"], STATUS_SUCCEEDED, "{result}");
    assert_eq!(complete["error_code"], SUCCESSFUL, "{result}");
    let hz = complete["feedback_hz"].as_f64().unwrap();
    assert!(hz >= MIN_FEEDBACK_HZ, "feedback at {hz} Hz");
    let names: Vec<String> = common::irb120().joint_names().map(String::from).collect();
    assert_eq!(complete["feedback_names"], serde_json::json!(names));
    let end: Vec<f64> = serde_json::from_value(result["end"].clone()).unwrap();
    let reached: Vec<f64> = serde_json::from_value(result["reached"].clone()).unwrap();
    let missed = end
        .iter()
        .zip(&reached)
        .map(|(e, r)| (e - r).abs())
        .fold(0.0, f64::max);
    println!("  reached the last point within {missed:.2e} rad");
    assert!(missed <= 0.01, "the default goal tolerance: {missed}");
    let cancel = &result["cancel"];
    let along = result["rest_along"].as_f64().unwrap();
    let off = result["rest_off_rad"].as_f64().unwrap();
    println!(
        "cancel at 50 %: status {}, code {}, cancel return code {}; at rest {:.1} % along the \
         way back, {off:.2e} rad off the path",
        cancel["status"],
        cancel["error_code"],
        cancel["cancel_return_code"],
        100.0 * along
    );
    assert_eq!(cancel["status"], STATUS_CANCELED, "{result}");
    assert_eq!(cancel["cancel_return_code"], 0, "ERROR_NONE: {result}");
    assert_eq!(cancel["canceling"], 1, "{result}");
    assert!((0.3..0.8).contains(&along), "halfway, braked: {along}");
    assert!(off < ON_PATH_RAD, "{off} rad off the path");
    let _ = std::fs::remove_dir_all(&dir);
}

/// How slow the arm may go at the slowest between a goal's preemption and the second goal's
/// easing out (rad/s, the fastest axis): far above what rounding leaves of an arm at rest,
/// far below the goals' speeds there (0.1 rad/s and more).
const MOVING_RAD_S: f64 = 1e-3;
/// Cycles the arm's speed is measured over (20 ms at 250 Hz): the twin reports a new
/// position every cycle.
const SPEED_WINDOW: usize = 5;
/// The second goal's last stretch, where it eases out to rest (s), left out of the
/// no-stop check.
const EASING_TO_REST_S: f64 = 0.6;

/// The arm's speed (the fastest axis', rad/s) at each measured state from `SPEED_WINDOW`
/// on, with its job time.
fn speeds(log: &rigbridge::log::RunLog) -> Vec<(f64, f64)> {
    log.states
        .windows(SPEED_WINDOW + 1)
        .map(|w| {
            let (a, b) = (&w[0], &w[SPEED_WINDOW]);
            let speed = a
                .positions
                .iter()
                .zip(&b.positions)
                .map(|(p, q)| (q - p).abs() / (b.t - a.t))
                .fold(0.0, f64::max);
            (b.t, speed)
        })
        .collect()
}

/// The commanded targets' largest share of each axis' speed and acceleration limit (the
/// positions' first and second differences), and the largest third difference (rad/s^3).
fn command_shares(log: &rigbridge::log::RunLog, rig: &rigbridge::rig::Rig) -> (f64, f64, f64) {
    let dt = 1.0 / 250.0;
    let (mut speed, mut accel, mut jerk) = (0.0_f64, 0.0_f64, 0.0_f64);
    for w in log.commands.windows(4) {
        for (axis, joint) in rig.joints.iter().enumerate() {
            let p: Vec<f64> = w.iter().map(|c| c.positions[axis]).collect();
            let v = (p[1] - p[0]) / dt;
            let a = (p[2] - 2.0 * p[1] + p[0]) / (dt * dt);
            let j = (p[3] - 3.0 * p[2] + 3.0 * p[1] - p[0]) / (dt * dt * dt);
            speed = speed.max(v.abs() / joint.limits.max_speed);
            accel = accel.max(a.abs() / joint.limits.max_acceleration);
            jerk = jerk.max(j.abs());
        }
    }
    (speed, accel, jerk)
}

#[test]
fn rclpy_a_new_goal_preempts_the_running_one_and_the_arm_goes_on_into_it_without_stopping() {
    let Some(python) = action_python() else {
        return;
    };
    const DOMAIN: u32 = 47;
    let dir = scratch("fjt-preempt");
    let daemon = serve_with_motion(&dir, DOMAIN);
    let client = start_client(
        &python,
        DOMAIN,
        &dir,
        &["preempt", "--rig", "irb120", "--duration-s", "6"],
    );
    let result = client.result();
    let (first, second) = (&result["first"], &result["second"]);
    println!(
        "first goal (6 s): {} / {} ({}); the second sent at {:.2} s: answered in {:.3} s, {} / \
         {} ({}), {:.2} s",
        first["status"],
        first["error_code"],
        first["error_string"],
        result["second_sent_s"].as_f64().unwrap_or(0.0),
        second["answered_s"].as_f64().unwrap_or(0.0),
        second["status"],
        second["error_code"],
        second["error_string"],
        second["seconds"].as_f64().unwrap_or(0.0)
    );
    // As JointTrajectoryController on Jazzy since ros2_controllers#2423.
    assert_eq!(first["status"], STATUS_ABORTED, "{result}");
    assert_eq!(first["error_code"], INVALID_GOAL, "{result}");
    assert_eq!(
        first["error_string"],
        "Current goal preempted by new incoming action."
    );
    assert_eq!(second["status"], STATUS_SUCCEEDED, "{result}");
    assert_eq!(second["error_code"], SUCCESSFUL, "{result}");
    let other: Vec<f64> = serde_json::from_value(result["other_end"].clone()).unwrap();
    let ended: Vec<f64> = serde_json::from_value(result["second_end"].clone()).unwrap();
    let missed = other
        .iter()
        .zip(&ended)
        .map(|(o, e)| (o - e).abs())
        .fold(0.0, f64::max);
    println!("  the second goal ended {missed:.2e} rad from its last point");
    assert!(missed <= 0.01, "the second goal's end: {missed}");
    drop(daemon);
    // One job carried both goals: its log has every cycle of both.
    let logs: Vec<PathBuf> = std::fs::read_dir(dir.join("runs"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| {
            p.file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.starts_with("job-") && n.ends_with(".mcap"))
        })
        .collect();
    assert_eq!(logs.len(), 1, "one job: {logs:?}");
    let log = rigbridge::log::read_log(&logs[0]).expect("the job's log reads");
    let preempted_at = log
        .events
        .iter()
        .find(|e| e.kind == "ros2_goal_preempted")
        .map(|e| e.t)
        .expect("the preemption is in the job's log");
    let ended_at = log.states.last().unwrap().t;
    let moving = speeds(&log);
    let (slowest_t, slowest) = moving
        .iter()
        .filter(|(t, _)| *t >= preempted_at - 0.5 && *t <= ended_at - EASING_TO_REST_S)
        .copied()
        .fold((0.0, f64::INFINITY), |a, b| if b.1 < a.1 { b } else { a });
    let rig = common::irb120();
    let (speed, accel, jerk) = command_shares(&log, &rig);
    let report = log
        .events
        .iter()
        .find(|e| e.kind == "job_ended")
        .map(|e| e.detail.clone())
        .unwrap_or_default();
    println!(
        "  preempted at {preempted_at:.3} s of the job; the arm's slowest from 0.5 s before to \
         {EASING_TO_REST_S} s before the end: {slowest:.4} rad/s at {slowest_t:.3} s; the \
         commands' largest share of an axis' speed {speed:.3} and acceleration {accel:.3}, \
         third difference up to {jerk:.1} rad/s^3; limit violations {}",
        report["limit_violations"]
    );
    assert!(
        slowest > MOVING_RAD_S,
        "the arm stopped ({slowest} rad/s at {slowest_t} s) between the goals"
    );
    assert!(
        speed <= 1.0 && accel <= 1.0,
        "within limits: {speed}, {accel}"
    );
    assert_eq!(report["limit_violations"], 0, "{report}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// FollowJointTrajectory's tolerance codes, as control_msgs defines them.
const PATH_TOLERANCE_VIOLATED: i64 = -4;
const GOAL_TOLERANCE_VIOLATED: i64 = -5;

#[test]
fn rclpy_goals_whose_path_or_goal_tolerance_the_twin_cannot_meet_end_with_their_codes() {
    let Some(python) = action_python() else {
        return;
    };
    const DOMAIN: u32 = 48;
    let dir = scratch("fjt-tolerances");
    let _daemon = serve_with_motion(&dir, DOMAIN);
    let client = start_client(&python, DOMAIN, &dir, &["tolerances", "--rig", "irb120"]);
    let result = client.result();
    let (path, goal) = (&result["path"], &result["goal"]);
    let along = result["path_rest_along"].as_f64().unwrap();
    let off = result["path_rest_off_rad"].as_f64().unwrap();
    println!(
        "path tolerance 1 mrad on joint_6: {} / {} ({}) after {:.2} s; at rest {:.1} % along, \
         {off:.2e} rad off the line",
        path["status"],
        path["error_code"],
        path["error_string"],
        path["seconds"].as_f64().unwrap_or(0.0),
        100.0 * along
    );
    assert_eq!(path["status"], STATUS_ABORTED, "{result}");
    assert_eq!(path["error_code"], PATH_TOLERANCE_VIOLATED, "{result}");
    let text = path["error_string"].as_str().unwrap();
    assert!(text.starts_with("joint_6 is "), "{text}");
    assert!(
        (0.0..1.0).contains(&along) && off < ON_PATH_RAD,
        "braked to rest on the path before its end: {along}, {off}"
    );
    let target: Vec<f64> = serde_json::from_value(result["goal_target"].clone()).unwrap();
    let rest: Vec<f64> = serde_json::from_value(result["goal_rest"].clone()).unwrap();
    println!(
        "goal tolerance 0.1 urad on joint_1: {} / {} ({}); joint_1 at rest {:.2e} rad from the \
         last point",
        goal["status"],
        goal["error_code"],
        goal["error_string"],
        (rest[0] - target[0]).abs()
    );
    assert_eq!(goal["status"], STATUS_ABORTED, "{result}");
    assert_eq!(goal["error_code"], GOAL_TOLERANCE_VIOLATED, "{result}");
    let text = goal["error_string"].as_str().unwrap();
    assert!(text.starts_with("joint_1 ended "), "{text}");
    assert!(
        (rest[0] - target[0]).abs() < 1e-3,
        "the arm went to the goal's end"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn rclpy_goals_with_a_wrong_joint_nan_bad_times_or_a_million_points_are_refused_and_nothing_moves()
{
    let Some(python) = action_python() else {
        return;
    };
    const DOMAIN: u32 = 45;
    let dir = scratch("fjt-refusals");
    let daemon = serve_with_motion(&dir, DOMAIN);
    let client = start_client(&python, DOMAIN, &dir, &["refusals", "--rig", "irb120"]);
    let result = client.result();
    for (case, code) in [
        ("wrong_joint", INVALID_JOINTS),
        ("nan", INVALID_GOAL),
        ("non_increasing", INVALID_GOAL),
        ("million", INVALID_GOAL),
    ] {
        let goal = &result[case];
        println!(
            "{case}: status {}, code {}, answered in {:.3} s: {}",
            goal["status"],
            goal["error_code"],
            goal["seconds"].as_f64().unwrap_or(f64::NAN),
            goal["error_string"]
        );
        assert_eq!(goal["status"], STATUS_ABORTED, "{case}: {goal}");
        assert_eq!(goal["error_code"], code, "{case}: {goal}");
        assert_eq!(goal["feedback"], 0, "{case}: no feedback, it never ran");
    }
    assert!(
        result["million"]["error_string"]
            .as_str()
            .unwrap()
            .contains("1000000 points"),
        "{result}"
    );
    let moved = result["moved_rad"].as_f64().unwrap();
    println!("the arm moved {moved:e} rad over the four refusals");
    assert_eq!(moved, 0.0, "nothing moves");
    let (status, jobs) = common::serve::request_json(&daemon.address, "GET", "/api/jobs", "", "");
    assert_eq!(status, 200);
    assert_eq!(
        jobs["jobs"].as_array().map(Vec::len),
        Some(0),
        "no job started: {jobs}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn rclpy_joint_trajectory_over_dds_moves_the_arm_with_consent() {
    let Some(python) = action_python() else {
        return;
    };
    const DOMAIN: u32 = 46;
    let dir = scratch("fjt-topic");
    let _daemon = serve_with_motion(&dir, DOMAIN);
    let client = start_client(&python, DOMAIN, &dir, &["topic", "--rig", "irb120"]);
    let result = client.result();
    let target: Vec<f64> = serde_json::from_value(result["target"].clone()).unwrap();
    let after: Vec<f64> = serde_json::from_value(result["after"].clone()).unwrap();
    let missed = target
        .iter()
        .zip(&after)
        .map(|(t, a)| (t - a).abs())
        .fold(0.0, f64::max);
    println!("JointTrajectory over DDS: the arm ended {missed:.2e} rad from the target");
    assert!(missed < 1e-3, "{result}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// The one publisher the graph shows on `topic`: the rig's node, with `type_name`.
fn assert_published(graph: &serde_json::Value, topic: &str, type_name: &str, latched: bool) {
    let publishers = graph[topic]
        .as_array()
        .unwrap_or_else(|| panic!("{topic}: {graph}"));
    assert_eq!(publishers.len(), 1, "{topic}: {publishers:?}");
    let publisher = &publishers[0];
    assert_eq!(publisher["node"], "/irb120/rigbridge", "{topic}");
    assert_eq!(publisher["type"], type_name, "{topic}");
    assert_eq!(publisher["reliable"], true, "{topic}");
    assert_eq!(publisher["transient_local"], latched, "{topic}");
}

#[test]
fn rclpy_receives_runs_joint_states_over_dds_at_100_hz_without_a_gap() {
    let Some(python) = peer_python() else { return };
    const DOMAIN: u32 = 41;
    let dir = scratch("run");
    let config = settings(&dir, &format!("domain_id = {DOMAIN}\n"));
    let hz = JOINT_STATES_HZ.to_string();
    // A gap is a message a subscriber at the rate the issue asks for would miss: two of its
    // periods (20 ms) without one. The 25 % headroom of the publishing rate is what absorbs
    // a publisher woken late on a loaded machine; the gaps at the publishing rate's own two
    // periods (16 ms) are printed beside.
    let gap_hz = MIN_JOINT_STATE_HZ.to_string();
    let peer = start_peer(
        &python,
        DOMAIN,
        &dir,
        &[
            "listen", "--rig", "irb120", "--hz", &hz, "--gap-hz", &gap_hz,
        ],
    );
    let log = dir.join("run.mcap");
    let output = rigbridge()
        .args(["run", "--config"])
        .arg(&config)
        .arg("--log")
        .arg(&log)
        .output()
        .unwrap();
    assert_succeeded(&output);
    let result = peer.result();
    let rate = result["rate_hz"].as_f64().unwrap();
    println!(
        "JointState over DDS to rclpy: {rate:.2} Hz, {} messages, {} gaps at 100 Hz ({} at the \
         publishing rate), longest interval {} s",
        result["count"], result["gaps"], result["gaps_at_publish_rate"], result["max_interval_s"]
    );
    assert!(rate >= MIN_JOINT_STATE_HZ, "{rate} Hz");
    assert_eq!(result["gaps"], 0, "{result}");
    assert_eq!(result["increasing"], true, "stamps in order");
    let names: Vec<String> = common::irb120().joint_names().map(String::from).collect();
    assert_eq!(result["names"], serde_json::json!(names));
    assert!(
        result["distinct_positions"].as_u64().unwrap() > 100,
        "the arm moved: {result}"
    );
    // The last message is where the run ended, as its log says.
    let logged = rigbridge::log::read_log(&log).unwrap();
    let last = &logged.states.last().unwrap().positions;
    let published: Vec<f64> = serde_json::from_value(result["last_position"].clone()).unwrap();
    assert_eq!(published.len(), last.len());
    for (p, l) in published.iter().zip(last) {
        assert!((p - l).abs() < 1e-12, "{published:?} vs {last:?}");
    }
    // The ROS 2 graph, as rclpy reads it: who publishes what, with which QoS.
    let graph = &result["graph"];
    assert_published(
        graph,
        "/irb120/joint_states",
        "sensor_msgs/msg/JointState",
        false,
    );
    assert_published(graph, "/tf", "tf2_msgs/msg/TFMessage", false);
    assert_published(graph, "/tf_static", "tf2_msgs/msg/TFMessage", true);
    assert_published(
        graph,
        "/irb120/robot_description",
        "std_msgs/msg/String",
        true,
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_late_rclpy_subscriber_gets_the_cells_urdf_as_robot_description() {
    let Some(python) = peer_python() else { return };
    const DOMAIN: u32 = 42;
    let dir = scratch("late");
    let config = settings(&dir, &format!("domain_id = {DOMAIN}\n"));
    let mut command = serve_command(&dir.join("runs"));
    let _daemon = start_serve(command.arg("--config").arg(&config).stderr(Stdio::null()));
    std::thread::sleep(LATE_BY);
    let peer = start_peer(
        &python,
        DOMAIN,
        &dir,
        &["late", "--rig", "irb120", "--timeout-s", "20"],
    );
    let result = peer.result();
    let urdf = rigbridge()
        .args(["config", "urdf", "--config"])
        .arg(&config)
        .output()
        .unwrap();
    assert_succeeded(&urdf);
    let expected = String::from_utf8(urdf.stdout).unwrap();
    println!("robot_description after {} s", result["waited_s"]);
    assert_eq!(
        result["description"].as_str(),
        Some(expected.as_str()),
        "the description is `rigbridge config urdf`'s"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// Loads `ros2` as the `[ros2]` table and returns the error's text.
fn load_error(dir: &Path, ros2: &str) -> String {
    let file = settings(dir, ros2);
    match rigbridge::daemon::config::load_run_settings(&file) {
        Ok(_) => panic!("[ros2] {ros2:?} should be refused"),
        Err(e) => e.to_string(),
    }
}

#[test]
fn the_middleware_settings_are_checked_and_motion_over_dds_needs_consent() {
    let dir = scratch("settings");
    let dds_with_zenoh = load_error(
        &dir,
        "middleware = \"dds\"\nzenoh_connect = \"tcp/127.0.0.1:7447\"\n",
    );
    assert!(
        dds_with_zenoh.contains("ros2.zenoh_connect")
            && dds_with_zenoh.contains("tcp/127.0.0.1:7447"),
        "{dds_with_zenoh}"
    );
    let zenoh_without = load_error(&dir, "middleware = \"zenoh\"\n");
    assert!(
        zenoh_without.contains("ros2.middleware") && zenoh_without.contains("zenoh_connect"),
        "{zenoh_without}"
    );
    let range_on_zenoh = load_error(
        &dir,
        "zenoh_connect = \"tcp/127.0.0.1:7447\"\ndiscovery_range = \"subnet\"\n",
    );
    assert!(
        range_on_zenoh.contains("ros2.discovery_range") && range_on_zenoh.contains("subnet"),
        "{range_on_zenoh}"
    );
    // Over DDS there is no login: motion needs the explicit consent to go without one
    // (refused on load without it), and a Zenoh login does not stand in for it (refused
    // when the node starts, before anything streams).
    let unconsented = load_error(&dir, "accept_motion = true\n");
    assert!(
        unconsented.contains("ros2.accept_motion")
            && unconsented.contains("allow_unauthenticated_motion"),
        "{unconsented}"
    );
    std::fs::write(dir.join("pw"), "secret\n").unwrap();
    let config = settings(
        &dir,
        "domain_id = 43\naccept_motion = true\nuser = \"arm\"\npassword_file = \"pw\"\n",
    );
    let output = serve_command(&dir.join("runs"))
        .arg("--config")
        .arg(&config)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(!output.status.success(), "{stderr}");
    assert!(
        stderr.contains("Zenoh login") && stderr.contains("allow_unauthenticated_motion"),
        "{stderr}"
    );
    let tolerance = load_error(&dir, "path_tolerance = -0.1\n");
    assert!(
        tolerance.contains("ros2.path_tolerance") && tolerance.contains("-0.1"),
        "{tolerance}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
