//! The batch tools and the messages users read: prismatic axes in metres, nearly unit
//! quaternions, outputs that a failed batch leaves whole, closed pipes, URDF tool frames
//! and content, the solver hint, exit codes, and no Rust debug text.

use crate::common;

use common::{output_with_stdin, repo_path};
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};

fn scratch(name: &str) -> PathBuf {
    common::scratch_dir("batch", name)
}

fn rigbridge_in(cwd: &Path, args: &[&str], stdin: &str) -> Output {
    output_with_stdin(
        Command::new(env!("CARGO_BIN_EXE_rigbridge"))
            .args(args)
            .current_dir(cwd)
            .env_remove("RIGBRIDGE_CONFIG"),
        stdin,
    )
}

fn rigbridge(args: &[&str], stdin: &str) -> Output {
    rigbridge_in(&repo_path(""), args, stdin)
}

fn text(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).into_owned()
}

/// A slider along x (metres) carrying a revolute joint about z, then a fixed tool 0.1 m
/// along the arm. With `camera`, a second moving branch ends at another leaf.
fn slider_urdf(camera: bool) -> String {
    let camera = if camera {
        r#"<link name="camera"/>
  <joint name="pan" type="revolute"><parent link="arm"/><child link="camera"/>
    <origin xyz="0 0 0.05" rpy="0 0 0"/><axis xyz="0 0 1"/>
    <limit lower="-1" upper="1" velocity="1" effort="1"/></joint>"#
    } else {
        ""
    };
    format!(
        r#"<?xml version="1.0"?>
<robot name="slider">
  <link name="base"/><link name="carriage"/><link name="arm"/><link name="tip"/>
  <joint name="slide" type="prismatic"><parent link="base"/><child link="carriage"/>
    <origin xyz="0 0 0" rpy="0 0 0"/><axis xyz="1 0 0"/>
    <limit lower="-1" upper="1" velocity="0.5" effort="1"/></joint>
  <joint name="turn" type="revolute"><parent link="carriage"/><child link="arm"/>
    <origin xyz="0 0 0" rpy="0 0 0"/><axis xyz="0 0 1"/>
    <limit lower="-3" upper="3" velocity="1" effort="1"/></joint>
  <joint name="tool" type="fixed"><parent link="arm"/><child link="tip"/>
    <origin xyz="0.1 0 0" rpy="0 0 0"/></joint>
  {camera}
</robot>
"#
    )
}

/// The slider rig, written without a `.urdf` extension: recognised by its content.
fn slider_file(dir: &Path, camera: bool) -> PathBuf {
    let path = dir.join("slider.description");
    std::fs::write(&path, slider_urdf(camera)).unwrap();
    path
}

fn fields(line: &str) -> Vec<String> {
    line.split(',').map(str::to_string).collect()
}

#[test]
fn prismatic_axes_are_metres_in_and_out() {
    let dir = scratch("prismatic");
    let rig = slider_file(&dir, false);
    let rig = rig.to_str().unwrap();
    // 0.5 m along the slide, 90 deg about z: the tip is 0.1 m along y from the carriage.
    let output = rigbridge(&["fk", "--rig", rig], "j1,j2\n0.5,90\n");
    assert!(output.status.success(), "{}", text(&output.stderr));
    let out = text(&output.stdout);
    let row = fields(out.lines().nth(1).unwrap());
    let (x, y): (f64, f64) = (row[0].parse().unwrap(), row[1].parse().unwrap());
    assert!((x - 0.5).abs() < 1e-9 && (y - 0.1).abs() < 1e-9, "{out}");
    // Back through ik: the slide comes out in metres.
    let poses = out.lines().take(2).collect::<Vec<_>>().join("\n") + "\n";
    let output = rigbridge(
        &["ik", "--rig", rig, "--solver", "ccd", "--seed", "0.4,80"],
        &poses,
    );
    assert!(output.status.success(), "{}", text(&output.stderr));
    let out = text(&output.stdout);
    let row = fields(out.lines().nth(1).unwrap());
    let slide: f64 = row[0].parse().unwrap();
    let turn: f64 = row[1].parse().unwrap();
    assert!((slide - 0.5).abs() < 1e-4, "{out}");
    assert!((turn - 90.0).abs() < 0.1, "{out}");
}

#[test]
fn fabriks_refusal_suggests_ccd() {
    let dir = scratch("fabrik");
    let rig = slider_file(&dir, false);
    let output = rigbridge(
        &["ik", "--rig", rig.to_str().unwrap()],
        "x,y,z,qw,qx,qy,qz\n",
    );
    assert_eq!(output.status.code(), Some(1));
    let message = text(&output.stderr);
    assert!(message.contains("--solver ccd"), "{message}");
}

#[test]
fn a_urdf_with_several_leaves_names_them_and_takes_a_tool_frame() {
    let dir = scratch("leaves");
    let rig = slider_file(&dir, true);
    let rig = rig.to_str().unwrap();
    let output = rigbridge(&["fk", "--rig", rig], "j1,j2\n0,0\n");
    assert_eq!(output.status.code(), Some(1));
    let message = text(&output.stderr);
    assert!(
        message.contains("tip") && message.contains("camera") && message.contains("--tool-frame"),
        "{message}"
    );
    let output = rigbridge(
        &["fk", "--rig", rig, "--tool-frame", "tip"],
        "j1,j2\n0.2,0\n",
    );
    assert!(output.status.success(), "{}", text(&output.stderr));
    let x: f64 = fields(text(&output.stdout).lines().nth(1).unwrap())[0]
        .parse()
        .unwrap();
    assert!(
        (x - 0.3).abs() < 1e-9,
        "tip: 0.2 m slide + 0.1 m tool, got {x}"
    );
    let output = rigbridge(
        &["fk", "--rig", rig, "--tool-frame", "camera"],
        "j1,j2,j3\n0.2,0,0\n",
    );
    assert!(output.status.success(), "{}", text(&output.stderr));
    let z: f64 = fields(text(&output.stdout).lines().nth(1).unwrap())[2]
        .parse()
        .unwrap();
    assert!((z - 0.05).abs() < 1e-9, "camera 0.05 m up, got {z}");
    let output = rigbridge(&["fk", "--rig", rig, "--tool-frame", "nose"], "j1\n0\n");
    let message = text(&output.stderr);
    assert!(
        message.contains("nose") && message.contains("camera"),
        "{message}"
    );
}

#[test]
fn a_nearly_unit_quaternion_is_used_and_a_far_one_refused_with_its_norm() {
    // tool0 at zero joints points along x: the quaternion of a 90 deg turn about y, written
    // with 4 decimals (norm 0.99999 or so).
    let input =
        "x,y,z,qw,qx,qy,qz\n0.374,0,0.63,0.7071,0,0.7071,0\n0.374,0,0.63,0.7086,0,0.7086,0\n";
    let output = rigbridge(&["ik"], input);
    assert_eq!(output.status.code(), Some(3), "{}", text(&output.stderr));
    let out = text(&output.stdout);
    let statuses: Vec<&str> = out
        .lines()
        .skip(1)
        .map(|l| l.rsplit(',').next().unwrap())
        .collect();
    assert_eq!(statuses[0], "ok", "{out}");
    assert!(statuses[1].starts_with("invalid_target"), "{out}");
    let norm = format!("norm {:.6}", 0.7086 * 2f64.sqrt());
    assert!(statuses[1].contains(&norm), "{norm}: {out}");
}

#[test]
fn a_failed_batch_leaves_the_output_file_whole() {
    let dir = scratch("whole");
    let output_file = dir.join("poses.csv");
    std::fs::write(&output_file, "earlier results\n").unwrap();
    let output = rigbridge(
        &["fk", "--output", output_file.to_str().unwrap()],
        "a,b,c\n1,2,3\n",
    );
    assert_eq!(output.status.code(), Some(1));
    assert!(text(&output.stderr).contains("no column `j1`"));
    assert_eq!(
        std::fs::read_to_string(&output_file).unwrap(),
        "earlier results\n"
    );
    let left: Vec<_> = std::fs::read_dir(&dir).unwrap().collect();
    assert_eq!(left.len(), 1, "no temporary file left behind");
    // A good batch replaces it.
    let output = rigbridge(
        &["fk", "--output", output_file.to_str().unwrap()],
        "j1,j2,j3,j4,j5,j6\n0,0,0,0,0,0\n",
    );
    assert!(output.status.success(), "{}", text(&output.stderr));
    assert!(
        std::fs::read_to_string(&output_file)
            .unwrap()
            .starts_with("x,y,z")
    );
}

#[test]
fn the_input_as_output_is_refused_before_writing() {
    let dir = scratch("same");
    let file = dir.join("joints.csv");
    let joints = "j1,j2,j3,j4,j5,j6\n0,0,0,0,30,0\n";
    std::fs::write(&file, joints).unwrap();
    std::os::unix::fs::symlink(&file, dir.join("alias.csv")).unwrap();
    for output_name in ["joints.csv", "./joints.csv", "alias.csv"] {
        let output = rigbridge_in(
            &dir,
            &["fk", "--input", "joints.csv", "--output", output_name],
            "",
        );
        assert_eq!(output.status.code(), Some(2), "{output_name}");
        assert!(
            text(&output.stderr).contains("is the input file"),
            "{output_name}"
        );
        assert_eq!(std::fs::read_to_string(&file).unwrap(), joints);
    }
}

/// Runs with stdout a pipe whose reader is already gone: the first write finds it closed.
fn with_closed_stdout(args: &[&str], stdin: &str) -> Output {
    use std::io::Write;
    let mut child = Command::new(env!("CARGO_BIN_EXE_rigbridge"))
        .args(args)
        .current_dir(repo_path(""))
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    drop(child.stdout.take());
    let mut pipe = child.stdin.take().unwrap();
    let _ = pipe.write_all(stdin.as_bytes());
    drop(pipe);
    child.wait_with_output().unwrap()
}

#[test]
fn a_closed_pipe_ends_the_output_cleanly() {
    let dir = scratch("pipe");
    let log = dir.join("run.mcap");
    let output = rigbridge(
        &["run", "--clock", "virtual", "--log", log.to_str().unwrap()],
        "",
    );
    assert!(output.status.success(), "{}", text(&output.stderr));
    let info = with_closed_stdout(&["log", "info", log.to_str().unwrap()], "");
    assert_eq!(info.status.code(), Some(0), "{}", text(&info.stderr));
    assert!(
        !text(&info.stderr).contains("panicked"),
        "{}",
        text(&info.stderr)
    );
    let rows: String = std::iter::once("j1,j2,j3,j4,j5,j6\n".to_string())
        .chain((0..20_000).map(|i| format!("{},0,0,0,30,0\n", i % 90)))
        .collect();
    let fk = with_closed_stdout(&["fk"], &rows);
    assert_eq!(fk.status.code(), Some(0), "{}", text(&fk.stderr));
    assert!(
        !text(&fk.stderr).contains("panicked"),
        "{}",
        text(&fk.stderr)
    );
}

#[test]
fn exit_codes_tell_usage_from_failed_rows_and_help_says_so() {
    let help = rigbridge(&["--help"], "");
    let help = text(&help.stdout);
    assert!(
        help.contains("2 usage error") && help.contains("3 a batch"),
        "{help}"
    );
    let unknown = rigbridge(&["fk", "--no-such-flag"], "");
    assert_eq!(unknown.status.code(), Some(2));
    let seed = rigbridge(&["ik", "--seed", "1,2"], "x,y,z,qw,qx,qy,qz\n");
    assert_eq!(seed.status.code(), Some(2), "{}", text(&seed.stderr));
    let failed = rigbridge(&["fk"], "j1,j2,j3,j4,j5,j6\n0,0,0,0,130,0\n");
    assert_eq!(failed.status.code(), Some(3), "{}", text(&failed.stderr));
    assert!(text(&failed.stdout).contains("outside_limits"));
}

/// Rust's debug forms that must never reach a user.
fn assert_no_debug_text(message: &str) {
    for debug in [
        "DVec3(",
        "DQuat(",
        "Some(",
        "None",
        "Os {",
        "ImageError",
        "\\\"",
    ] {
        assert!(!message.contains(debug), "{debug} in: {message}");
    }
}

#[test]
fn messages_carry_no_debug_text_and_degrees_for_degree_inputs() {
    let dir = scratch("messages");
    // A zero URDF axis.
    let broken = slider_urdf(false).replace(r#"<axis xyz="0 0 1"/>"#, r#"<axis xyz="0 0 0"/>"#);
    let rig = dir.join("zero-axis.urdf");
    std::fs::write(&rig, broken).unwrap();
    let output = rigbridge(&["fk", "--rig", rig.to_str().unwrap()], "j1,j2\n0,0\n");
    let message = text(&output.stderr);
    assert!(message.contains("[0, 0, 0]"), "{message}");
    assert_no_debug_text(&message);
    // A joint without its limit.
    let toml = std::fs::read_to_string(repo_path("config/irb120.toml")).unwrap();
    let rig = dir.join("no-limit.toml");
    std::fs::write(&rig, toml.replacen("lower_deg = -165.0", "", 1)).unwrap();
    let output = rigbridge(&["fk", "--rig", rig.to_str().unwrap()], "j1\n0\n");
    let message = text(&output.stderr);
    assert!(message.contains("lower_deg` = missing"), "{message}");
    assert_no_debug_text(&message);
    // A picture that cannot be written.
    let log = dir.join("run.mcap");
    let output = rigbridge(
        &["run", "--clock", "virtual", "--log", log.to_str().unwrap()],
        "",
    );
    assert!(output.status.success(), "{}", text(&output.stderr));
    let output = rigbridge(
        &[
            "log",
            "plot",
            log.to_str().unwrap(),
            "-o",
            "/nonexistent-dir/p.png",
        ],
        "",
    );
    let message = text(&output.stderr);
    assert!(message.contains("/nonexistent-dir/p.png"), "{message}");
    assert_no_debug_text(&message);
}

#[test]
fn a_waypoint_beyond_a_limit_is_reported_in_degrees() {
    use rigbridge::trajectory::{PlanSettings, plan_joint_moves};
    let rig = common::irb120();
    let mut beyond = vec![0.0; 6];
    beyond[2] = 80f64.to_radians(); // joint_3 stops at +70 deg
    let error = plan_joint_moves(&rig, &[0.0; 6], &[beyond], &PlanSettings::default())
        .unwrap_err()
        .to_string();
    assert!(
        error.contains("joint_3 = 80.000 deg is outside its limits [-110.000, 70.000] deg"),
        "{error}"
    );
}
