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
fn rclpy_follow_joint_trajectory_goals_complete_a_cancel_rests_on_the_path_and_a_new_goal_preempts()
{
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
    // A new goal preempts the running one, as JointTrajectoryController's does.
    let preempted = &result["preempted"];
    let preempting = &result["preempting"];
    println!(
        "preemption: the first goal {} / {} ({}), the second {} / {}",
        preempted["status"],
        preempted["error_code"],
        preempted["error_string"],
        preempting["status"],
        preempting["error_code"]
    );
    assert_eq!(preempted["status"], STATUS_CANCELED, "{result}");
    assert_eq!(preempted["error_code"], INVALID_GOAL, "{result}");
    assert_eq!(
        preempted["error_string"],
        "Current goal cancelled due to new incoming action."
    );
    assert_eq!(preempting["status"], STATUS_SUCCEEDED, "{result}");
    let start: Vec<f64> = serde_json::from_value(result["start"].clone()).unwrap();
    let ended: Vec<f64> = serde_json::from_value(result["preempting_end"].clone()).unwrap();
    let missed = start
        .iter()
        .zip(&ended)
        .map(|(s, e)| (s - e).abs())
        .fold(0.0, f64::max);
    assert!(missed <= 0.01, "the second goal's end: {missed}");
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
