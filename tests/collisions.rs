//! Every trajectory is checked against the cell before any motion (issue 27): each job
//! kind through `run`, the issue's two jobs through `run` and HTTP, a ROS 2 trajectory's
//! job (inline rows, no approach) through HTTP, `replay` (also with `--link`), and the
//! streaming gate's own check of a trajectory handed over unchecked. Each refusal must
//! name the two bodies, the time, where the stretch came from as the user wrote it, the
//! joints in degrees and the clearance against the margin; nothing moves.

use crate::common;
use crate::in_process;

use common::repo_path;
use common::serve::request_json;
use rigbridge::cell::CollisionModel;
use rigbridge::clock::VirtualClock;
use rigbridge::daemon::config::{RunSettings, load_run_settings};
use rigbridge::daemon::{collision_model, loopback_twin, plan_settings, stream_settings};
use rigbridge::stream::{CycleRecord, CycleSink, Outcome, StreamControl, stream_in_cell};
use rigbridge::trajectory::plan_joint_moves;
use std::path::{Path, PathBuf};
use std::process::Command;

/// The issue's first job: the wrist folded into the arm's own base.
const WRIST_INTO_BASE_DEG: [f64; 6] = [0.0, 100.0, 60.0, 0.0, 90.0, 0.0];
/// The twin's start in every settings file here: the demo's.
const INITIAL: &str = "[twin]\ninitial_deg = [0.0, 0.0, 0.0, 0.0, 30.0, 0.0]\n";
/// The issue's second job as a line: from above the floor to 0.10 m below it, tool down.
const LINE_BELOW_THE_FLOOR: &str = r#"[job]
kind = "move_linear"
poses = [
  { xyz_m = [0.40, 0.0, 0.30], quat_wxyz = [0.0, 0.0, 1.0, 0.0] },
  { xyz_m = [0.40, 0.0, -0.10], quat_wxyz = [0.0, 0.0, 1.0, 0.0] },
]
"#;

/// A fresh directory holding a copy of the IRB 120 rig file.
fn dir(name: &str) -> PathBuf {
    let dir = common::scratch_dir("collisions", name);
    std::fs::copy(repo_path("config/irb120.toml"), dir.join("irb120.toml")).unwrap();
    dir
}

/// `dir/job.toml`: the IRB 120 on its built-in cell (the floor), the demo's start, `job`.
fn settings_file(dir: &Path, job: &str) -> PathBuf {
    let file = dir.join("job.toml");
    std::fs::write(&file, format!("rig = \"irb120.toml\"\n{INITIAL}\n{job}")).unwrap();
    file
}

fn move_joints(target: [f64; 6]) -> String {
    format!("[job]\nkind = \"move_joints\"\ntargets_deg = [{target:?}]\n")
}

/// `rigbridge run` of `dir/job.toml` that must be refused: its stderr and its report.
fn run_refused(dir: &Path) -> (String, serde_json::Value) {
    let output = Command::new(env!("CARGO_BIN_EXE_rigbridge"))
        .args(["run", "--config", "job.toml", "--clock", "virtual"])
        .args(["--report", "report.json", "--log", "run.mcap"])
        .current_dir(dir)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr).to_string();
    assert!(!output.status.success(), "not refused: {stderr}");
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("report.json")).unwrap()).unwrap();
    assert_eq!(report["outcome"], "refused", "{report}");
    assert_eq!(report["cycles"], 0, "{report}");
    assert!(!dir.join("run.mcap").exists(), "a refused job has no log");
    (stderr, report)
}

/// How far apart `settings`' cell's closest pair is at `deg`.
fn clearance_at(settings: &RunSettings, deg: &[f64]) -> f64 {
    let model = collision_model(settings);
    let si: Vec<f64> = deg.iter().map(|d| d.to_radians()).collect();
    model.clearance(&si, &mut model.scratch()).distance_m
}

/// The IRB 120's bodies as config/irb120.toml names them: the base and the first link,
/// and the wrist's links (the issue's first job folds these into those).
const BASE_BODIES: [&str; 2] = ["base_link", "link_1"];
const WRIST_BODIES: [&str; 3] = ["link_4", "link_5", "link_6"];

/// A refusal names one body of each group.
fn assert_base_and_wrist(text: &str) {
    assert!(
        BASE_BODIES
            .iter()
            .any(|b| text.contains(&format!("{b} and "))),
        "{text}"
    );
    assert!(
        WRIST_BODIES
            .iter()
            .any(|b| text.contains(&format!(" and {b} "))),
        "{text}"
    );
}

/// What every refusal says: the time in the job, the origin, the clearance against the
/// margin, the joints in degrees.
fn assert_names(text: &str, origin: &str) {
    for needle in [origin, "t = ", " s of the job", "margin", " deg"] {
        assert!(text.contains(needle), "`{needle}` missing from: {text}");
    }
    assert!(
        text.contains("collision") || text.contains("within the margin"),
        "{text}"
    );
    assert!(!text.contains("Some(") && !text.contains("[\""), "{text}");
}

#[test]
fn run_refuses_the_wrist_folded_into_the_base_naming_the_bodies_and_the_joints() {
    let dir = dir("wrist");
    let file = settings_file(&dir, &move_joints(WRIST_INTO_BASE_DEG));
    let settings = load_run_settings(&file).unwrap();
    // The issue's figure: tool0 at x = -0.02 m, z = 0.14 m, inside the base.
    let distance = clearance_at(&settings, &WRIST_INTO_BASE_DEG);
    assert!(distance <= 0.0, "the target is {distance} m clear");
    let (stderr, report) = run_refused(&dir);
    let fault = report["fault"].as_str().unwrap();
    // Refused on the way, where the wrist first comes within the margin of the base.
    assert_names(fault, "the joint move to job.targets_deg[0]");
    assert_base_and_wrist(fault);
    assert!(
        stderr.contains(fault.split(" at t = ").next().unwrap()),
        "{stderr}"
    );
}

#[test]
fn run_refuses_the_line_below_the_floor_naming_the_line() {
    let dir = dir("floor");
    settings_file(&dir, LINE_BELOW_THE_FLOOR);
    let (_, report) = run_refused(&dir);
    let fault = report["fault"].as_str().unwrap();
    assert!(fault.contains("the line to job.poses[1]"), "{fault}");
    assert!(fault.contains("floor"), "{fault}");
}

#[test]
fn http_refuses_both_of_the_issues_jobs_and_a_ros2_trajectory_with_422() {
    let dir = dir("http");
    let file = settings_file(&dir, &move_joints([0.0, 10.0, 10.0, 0.0, 30.0, 0.0]));
    let settings = load_run_settings(&file).unwrap();
    let server = in_process::start(vec![settings], in_process::options(dir.join("runs")));
    let address = server.address.to_string();
    let post = |job: &str| request_json(&address, "POST", "/api/jobs", "", job);

    let (code, answer) = post(&format!(
        r#"{{"job": {{"kind": "move_joints", "targets_deg": [{WRIST_INTO_BASE_DEG:?}]}}}}"#
    ));
    assert_eq!(code, 422, "{answer}");
    let error = answer["error"].as_str().unwrap();
    assert_names(error, "job.targets_deg[0]");
    assert_base_and_wrist(error);

    let below = r#"{"job": {"kind": "move_linear", "poses": [
        {"xyz_m": [0.40, 0.0, 0.30], "quat_wxyz": [0.0, 0.0, 1.0, 0.0]},
        {"xyz_m": [0.40, 0.0, -0.10], "quat_wxyz": [0.0, 0.0, 1.0, 0.0]}]}}"#;
    let (code, answer) = post(below);
    assert_eq!(code, 422, "{answer}");
    let error = answer["error"].as_str().unwrap();
    assert!(
        error.contains("floor") && error.contains("the line to job.poses[1]"),
        "{error}"
    );

    // A ROS 2 JointTrajectory becomes this job (docs/ros2.md): rows, no approach.
    let ros2 = format!(
        r#"{{"job": {{"kind": "follow_trajectory", "approach": false,
            "rows": [[0.0, 0.0, 0.0, 0.0, 0.0, 30.0, 0.0], [4.0, {}]]}}}}"#,
        WRIST_INTO_BASE_DEG.map(|d| d.to_string()).join(", ")
    );
    let (code, answer) = post(&ros2);
    assert_eq!(code, 422, "{answer}");
    let error = answer["error"].as_str().unwrap();
    assert_names(error, "job.rows[0] (t = 0.000 s) to job.rows[1]");
    assert_base_and_wrist(error);

    let (_, status) = request_json(&address, "GET", "/api/status", "", "");
    assert_eq!(status["state"], "idle", "{status}");
    server.stop().unwrap().unwrap();
    // Nothing moved: no job log holds a command.
    let logs = std::fs::read_dir(dir.join("runs")).map_or(0, |d| {
        d.filter(|e| {
            e.as_ref()
                .is_ok_and(|e| e.file_name().to_string_lossy().starts_with("job-"))
        })
        .count()
    });
    assert_eq!(logs, 0, "a refused job left a log");
}

#[test]
fn each_job_kind_is_refused_before_motion_naming_where_it_came_from() {
    let bad = WRIST_INTO_BASE_DEG.map(|d| d.to_string()).join(", ");
    let cases = [
        (
            "joint_waypoints".to_string(),
            format!("[job]\nkind = \"joint_waypoints\"\nwaypoints_deg = [[0.0, 10.0, 0.0, 0.0, 30.0, 0.0], [{bad}]]\n"),
            "the joint move to job.waypoints_deg[1]".to_string(),
        ),
        (
            "move_poses".to_string(),
            "[job]\nkind = \"move_poses\"\nposes = [{ xyz_m = [0.40, 0.0, 0.30], quat_wxyz = [0.0, 0.0, 1.0, 0.0] }, \
             { xyz_m = [0.40, 0.0, -0.10], quat_wxyz = [0.0, 0.0, 1.0, 0.0] }]\n"
                .to_string(),
            "the joint move to job.poses[1]".to_string(),
        ),
        (
            "wall_figure".to_string(),
            "[job]\nkind = \"wall_figure\"\nwall_x_m = 0.45\ncentre_yz_m = [0.0, 0.02]\nradius_m = 0.1\nlaps = 1\n"
                .to_string(),
            "the star's corner".to_string(),
        ),
        (
            "follow_trajectory".to_string(),
            "[job]\nkind = \"follow_trajectory\"\nfile = \"t.csv\"\n".to_string(),
            // Line 1 the header, line 2 a comment: the rows are lines 3 and 4.
            "the piece from row 3 of t.csv (t = 0.000 s) to row 4 of t.csv".to_string(),
        ),
    ];
    for (kind, job, origin) in cases {
        let dir = dir(&kind);
        std::fs::write(
            dir.join("t.csv"),
            format!("t,j1,j2,j3,j4,j5,j6\n# into the base\n0,0,0,0,0,30,0\n4,{bad}\n"),
        )
        .unwrap();
        settings_file(&dir, &job);
        let (_, report) = run_refused(&dir);
        let fault = report["fault"].as_str().unwrap();
        assert!(fault.contains(&origin), "{kind}: {fault}");
        assert!(
            fault.contains(" and ") && fault.contains("margin"),
            "{fault}"
        );
    }
}

/// Records every target the stream sent.
#[derive(Default)]
struct Sent(Vec<Vec<f64>>);

impl CycleSink for Sent {
    fn record(&mut self, cycle: &CycleRecord) {
        self.0.push(cycle.target.positions.as_slice().to_vec());
    }
}

fn streamed_in_cell(
    settings: &RunSettings,
    model: &CollisionModel,
    target_deg: [f64; 6],
) -> (rigbridge::stream::StreamReport, Sent) {
    let target: Vec<f64> = target_deg.iter().map(|d| d.to_radians()).collect();
    let trajectory = plan_joint_moves(
        &settings.rig,
        &settings.initial(),
        &[target],
        &plan_settings(settings),
    )
    .unwrap();
    let mut link = loopback_twin(settings).unwrap();
    let mut sent = Sent::default();
    let report = stream_in_cell(
        &trajectory,
        &settings.rig,
        model,
        &mut link,
        &VirtualClock::new(),
        &mut sent,
        &StreamControl::default(),
        &stream_settings(settings),
    )
    .unwrap();
    (report, sent)
}

#[test]
fn the_gate_checks_each_target_of_a_trajectory_handed_over_unchecked() {
    let dir = dir("gate");
    let settings =
        load_run_settings(&settings_file(&dir, &move_joints(WRIST_INTO_BASE_DEG))).unwrap();
    let model = collision_model(&settings);
    let (report, sent) = streamed_in_cell(&settings, &model, WRIST_INTO_BASE_DEG);
    assert_eq!(report.outcome, Outcome::GateRefused, "{report:?}");
    let fault = report.fault.clone().unwrap();
    assert!(
        fault.contains("the safety gate refused a target"),
        "{fault}"
    );
    assert!(
        fault.contains("margin") && fault.contains(" deg"),
        "{fault}"
    );
    // It moved up to the margin and no further: every target it sent is clear of it.
    assert!(sent.0.len() > 10, "{} targets", sent.0.len());
    let mut scratch = model.scratch();
    for target in &sent.0 {
        let clearance = model.clearance(target, &mut scratch);
        assert!(
            clearance.distance_m >= model.margin(),
            "a target {} m from the next body went out",
            clearance.distance_m
        );
    }
    // A clear move through the same gate completes.
    let (report, _) = streamed_in_cell(&settings, &model, [30.0, 20.0, 10.0, 0.0, 30.0, 0.0]);
    assert_eq!(report.outcome, Outcome::Completed, "{report:?}");
}

/// `rigbridge` with `args` in `dir`: its exit status and stderr.
fn rigbridge_in(dir: &Path, args: &[&str]) -> (bool, String) {
    let output = Command::new(env!("CARGO_BIN_EXE_rigbridge"))
        .args(args)
        .current_dir(dir)
        .output()
        .unwrap();
    (
        output.status.success(),
        String::from_utf8_lossy(&output.stderr).to_string(),
    )
}

#[test]
fn replay_refuses_a_log_whose_path_now_hits_the_cell() {
    let dir = dir("replay");
    // Joint 1 sweeps the forearm (0.63 m up) through 60 deg; recorded in the built-in cell.
    settings_file(&dir, &move_joints([60.0, 0.0, 0.0, 0.0, 30.0, 0.0]));
    let (ok, stderr) = rigbridge_in(
        &dir,
        &[
            "run", "--config", "job.toml", "--clock", "virtual", "--log", "run.mcap",
        ],
    );
    assert!(ok, "{stderr}");
    // The same rig with a box on the forearm's arc, at 30 deg, 0.26 m out: a static body
    // of its base frame (as a cell object would be).
    let boxed = dir.join("boxed");
    std::fs::create_dir_all(&boxed).unwrap();
    let rig = std::fs::read_to_string(dir.join("irb120.toml")).unwrap();
    std::fs::write(
        boxed.join("irb120.toml"),
        format!(
            "{rig}\n[[body]]\nname = \"obstacle\"\nframe = 0\n[[body.collision]]\nshape = \"box\"\n\
             size_m = [0.1, 0.1, 0.1]\norigin_xyz_m = [0.225, 0.13, 0.63]\n"
        ),
    )
    .unwrap();
    settings_file(&boxed, &move_joints([0.0, 10.0, 0.0, 0.0, 30.0, 0.0]));
    let replay = ["replay", "run.mcap", "--config", "boxed/job.toml"];
    for link in [None, Some("tcp://127.0.0.1:9")] {
        let mut args = replay.to_vec();
        match link {
            Some(link) => args.extend(["--link", link]),
            None => args.extend(["--clock", "virtual"]),
        }
        let (ok, stderr) = rigbridge_in(&dir, &args);
        assert!(!ok, "replayed into the box: {stderr}");
        for needle in [
            "obstacle",
            "the log's command seq",
            "t = ",
            " deg",
            "margin",
        ] {
            assert!(stderr.contains(needle), "`{needle}` missing: {stderr}");
        }
        // Refused before any link was opened: nothing listens on port 9.
        assert!(!stderr.contains("connect"), "{stderr}");
    }
}
