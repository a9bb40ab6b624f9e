//! The job kinds users write (docs/jobs.md): every example there runs end to end with the
//! installed binary's `run`, a ten-line config runs, `move_linear` keeps the tool on its
//! lines by forward kinematics of the commanded joints, `follow_trajectory` follows its
//! file, and TOML refuses what HTTP refuses with the same text.

use crate::common;

use common::repo_path;
use rigbridge::daemon::config::load_run_settings;
use rigbridge::job::{Job, JobContext, PlanContext};
use rigbridge::trajectory::Trajectory;
use std::path::{Path, PathBuf};
use std::process::Command;

/// A fresh directory holding a copy of the IRB 120 rig file.
fn job_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("rigbridge-jobs-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::copy(repo_path("config/irb120.toml"), dir.join("irb120.toml")).unwrap();
    dir
}

/// The fenced blocks of docs/jobs.md marked `toml example`, and the files (```csv NAME).
fn doc_examples() -> (Vec<String>, Vec<(String, String)>) {
    let text = std::fs::read_to_string(repo_path("docs/jobs.md")).unwrap();
    let (mut configs, mut files) = (Vec::new(), Vec::new());
    let mut lines = text.lines();
    while let Some(line) = lines.next() {
        let Some(info) = line.strip_prefix("```") else {
            continue;
        };
        let body: Vec<&str> = lines
            .by_ref()
            .take_while(|l| !l.starts_with("```"))
            .collect();
        let body = body.join("\n") + "\n";
        match info.split_whitespace().collect::<Vec<_>>().as_slice() {
            ["toml", "example"] => configs.push(body),
            ["csv", name] => files.push((name.to_string(), body)),
            _ => {}
        }
    }
    (configs, files)
}

fn run_config(dir: &Path, config: &str) -> serde_json::Value {
    std::fs::write(dir.join("job.toml"), config).unwrap();
    let output = Command::new(env!("CARGO_BIN_EXE_rigbridge"))
        .args(["run", "--config", "job.toml", "--clock", "virtual"])
        .args(["--report", "report.json", "--log", "run.mcap"])
        .current_dir(dir)
        .output()
        .unwrap();
    assert!(
        output.status.success(),
        "{config}\n{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let report = std::fs::read_to_string(dir.join("report.json")).unwrap();
    serde_json::from_str(&report).unwrap()
}

#[test]
fn every_kind_in_docs_jobs_md_runs_its_example() {
    let (configs, files) = doc_examples();
    let kinds: Vec<String> = configs
        .iter()
        .filter_map(|c| {
            let value: toml::Value = toml::from_str(c).unwrap();
            value["job"]["kind"].as_str().map(String::from)
        })
        .collect();
    for kind in [
        "move_joints",
        "joint_waypoints",
        "move_linear",
        "move_poses",
        "follow_trajectory",
        "wall_figure",
    ] {
        assert!(kinds.iter().any(|k| k == kind), "{kind} has no example");
    }
    for (n, config) in configs.iter().enumerate() {
        let dir = job_dir(&format!("doc-{n}"));
        for (name, text) in &files {
            std::fs::write(dir.join(name), text).unwrap();
        }
        let report = run_config(&dir, config);
        assert_eq!(report["outcome"], "completed", "{config}\n{report}");
        assert_eq!(report["job"], kinds[n].as_str());
        assert!(
            report["planned_duration_s"].as_f64().unwrap() > 0.1,
            "{report}"
        );
    }
}

#[test]
fn a_config_naming_only_a_rig_and_a_job_runs() {
    let dir = job_dir("minimal");
    let config = "rig = \"irb120.toml\"\n\n[job]\nkind = \"move_joints\"\n\
                  targets_deg = [[10.0, 0.0, 0.0, 0.0, 20.0, 0.0]]\n";
    assert!(config.lines().count() <= 10);
    let report = run_config(&dir, config);
    assert_eq!(report["outcome"], "completed", "{report}");
    assert_eq!(report["rate_hz"], 250.0, "the documented default rate");
}

/// Loads `config` written into a fresh directory.
fn load(name: &str, config: &str) -> Result<rigbridge::daemon::config::RunSettings, String> {
    let dir = job_dir(name);
    std::fs::write(dir.join("job.toml"), config).unwrap();
    load_run_settings(&dir.join("job.toml")).map_err(|e| e.to_string())
}

const STAR: &str = "rig = \"irb120.toml\"\n[job]\nkind = \"wall_figure\"\nwall_x_m = 0.45\n\
                    centre_yz_m = [0.0, 0.45]\nradius_m = 0.1\n";

#[test]
fn toml_and_json_refuse_the_same_jobs_with_the_same_text() {
    let settings = load("same-text", &format!("{STAR}laps = 1\n")).unwrap();
    let dir = settings.file.parent().unwrap().to_path_buf();
    let context = JobContext {
        rig: &settings.rig,
        cell: &settings.cell,
        app_rig: None,
        base_dir: &dir,
        limits: &settings.config.limits,
        period: settings.period(),
    };
    let cases = [
        ("laps = 4294967295", r#""laps": 4294967295"#),
        ("laps = 0", r#""laps": 0"#),
        (
            "laps = 1\nspeed_scale = 0.1",
            r#""laps": 1, "speed_scale": 0.1"#,
        ),
    ];
    for (toml_line, json_keys) in cases {
        let from_toml = load("same-text", &format!("{STAR}{toml_line}\n")).unwrap_err();
        let json = format!(
            r#"{{"kind": "wall_figure", "wall_x_m": 0.45, "centre_yz_m": [0.0, 0.45], "radius_m": 0.1, {json_keys}}}"#
        );
        let from_json = match serde_json::from_str::<Job>(&json) {
            Ok(job) => job.validate(&context).unwrap_err().to_string(),
            Err(e) => e.to_string(),
        };
        assert!(
            from_toml.contains("laps") || from_toml.contains("speed_scale"),
            "{from_toml}"
        );
        if toml_line.contains("speed_scale") {
            assert!(
                from_toml.contains("unknown field `speed_scale`"),
                "{from_toml}"
            );
            assert!(
                from_json.contains("unknown field `speed_scale`"),
                "{from_json}"
            );
        } else {
            assert!(
                from_toml.ends_with(&from_json),
                "TOML: {from_toml}\nJSON: {from_json}"
            );
        }
    }
    let empty = load(
        "empty",
        "rig = \"irb120.toml\"\n[job]\nkind = \"move_joints\"\ntargets_deg = []\n",
    );
    assert!(empty.unwrap_err().contains("needs at least one entry"));
    let outside = load(
        "outside",
        "rig = \"irb120.toml\"\n[job]\nkind = \"follow_trajectory\"\nfile = \"/etc/passwd\"\n",
    );
    assert!(
        outside
            .unwrap_err()
            .contains("relative to the config's directory")
    );
}

/// The distance from `p` to the segment `a`-`b`.
fn to_segment(p: glam::DVec3, a: glam::DVec3, b: glam::DVec3) -> f64 {
    let ab = b - a;
    let u = ((p - a).dot(ab) / ab.length_squared().max(1e-300)).clamp(0.0, 1.0);
    (a + ab * u - p).length()
}

fn plan(settings: &rigbridge::daemon::config::RunSettings) -> Trajectory {
    let start = settings.initial();
    settings
        .config
        .job
        .plan(&PlanContext {
            rig: &settings.rig,
            app_rig: None,
            start: &start,
            settings: &rigbridge::daemon::plan_settings(settings),
            model: Some(&settings.collision),
        })
        .unwrap_or_else(|e| panic!("{}", rigbridge::daemon::error_chain(&e)))
}

#[test]
fn move_linear_keeps_the_tool_on_its_lines_and_ends_on_the_last_pose() {
    let (configs, _) = doc_examples();
    let config = configs.iter().find(|c| c.contains("move_linear")).unwrap();
    let settings = load("linear", config).unwrap();
    let trajectory = plan(&settings);
    let rig = &settings.rig;
    let tool = |q: &[f64]| rig.tool_pose(q).unwrap();
    // The lines: through the three poses of the example, read here from the file itself;
    // a joint move reaches the first.
    let value: toml::Value = toml::from_str(config).unwrap();
    let mut corners = Vec::new();
    for pose in value["job"]["poses"].as_array().unwrap() {
        let xyz: Vec<f64> = pose["xyz_m"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_float().unwrap())
            .collect();
        corners.push(glam::DVec3::new(xyz[0], xyz[1], xyz[2]));
    }
    let reached = (0..trajectory.len())
        .find(|&k| (tool(&trajectory.position(k)).position - corners[0]).length() <= 1e-6)
        .expect("the first pose is reached");
    let mut worst: f64 = 0.0;
    for k in reached..trajectory.len() {
        let p = tool(&trajectory.position(k)).position;
        let nearest = corners
            .windows(2)
            .map(|w| to_segment(p, w[0], w[1]))
            .fold(f64::INFINITY, f64::min);
        worst = worst.max(nearest);
    }
    println!(
        "move_linear: worst distance from the lines {:.3e} m over {} samples",
        worst,
        trajectory.len()
    );
    assert!(worst <= 0.5e-3, "{worst} m off the lines");
    let last = tool(&trajectory.position(trajectory.len() - 1)).position;
    let end = corners[corners.len() - 1];
    assert!(
        (last - end).length() <= 1e-6,
        "ends {} m from the last pose",
        (last - end).length()
    );
    // speed_m_s caps the lines, not the joint move to the first pose.
    let top = rigbridge::job::top_tool_speed(rig, &trajectory.tail(reached));
    println!("move_linear: lines from sample {reached}, top tool speed {top:.4} m/s");
    assert!(top <= 0.2 * 1.001, "tool speed {top} m/s above speed_m_s");
    assert!(top >= 0.1, "the lines are not crawling: {top} m/s");
}

#[test]
fn follow_trajectory_passes_every_row_and_refuses_a_bad_file_without_quoting_it() {
    let dir = job_dir("follow");
    let rows = [
        [0.0, 0.0, 0.0, 0.0, 0.0, 30.0, 0.0],
        [1.0, 10.0, 5.0, 0.0, 0.0, 30.0, 0.0],
        [2.0, 20.0, 5.0, 5.0, 0.0, 35.0, 0.0],
    ];
    let mut csv = String::from("t,j1,j2,j3,j4,j5,j6\n");
    for row in rows {
        let cells: Vec<String> = row.iter().map(|v| v.to_string()).collect();
        csv += &(cells.join(",") + "\n");
    }
    std::fs::write(dir.join("t.csv"), &csv).unwrap();
    let config = "rig = \"irb120.toml\"\n[twin]\ninitial_deg = [0.0, 0.0, 0.0, 0.0, 30.0, 0.0]\n\
                  [job]\nkind = \"follow_trajectory\"\nfile = \"t.csv\"\n";
    std::fs::write(dir.join("job.toml"), config).unwrap();
    let settings = load_run_settings(&dir.join("job.toml")).unwrap();
    let trajectory = plan(&settings);
    let period = trajectory.period.as_secs_f64();
    // Already at the first row, so the file's time is the trajectory's (after the one-sample
    // move to where the rig is).
    for row in rows {
        let k = (row[0] / period).round() as usize;
        let q = trajectory.position(k);
        for (axis, deg) in row[1..].iter().enumerate() {
            assert!(
                (q[axis].to_degrees() - deg).abs() < 1e-6,
                "row t = {}: {q:?}",
                row[0]
            );
        }
    }
    std::fs::write(
        dir.join("t.csv"),
        "t,j1,j2,j3,j4,j5,j6\n0,SECRETVALUE,0,0,0,0,0\n",
    )
    .unwrap();
    let refused = load_run_settings(&dir.join("job.toml"))
        .unwrap_err()
        .to_string();
    assert!(
        refused.contains("row 2") && !refused.contains("SECRETVALUE"),
        "{refused}"
    );
    std::fs::write(
        dir.join("t.csv"),
        "t,j1,j2,j3,j4,j5,j6\n0,0,0,0,0,0,0\n0.5,160,0,0,0,0,0\n",
    )
    .unwrap();
    let settings = load_run_settings(&dir.join("job.toml")).unwrap();
    let too_fast = settings.config.job.plan(&PlanContext {
        rig: &settings.rig,
        app_rig: None,
        start: &settings.initial(),
        settings: &rigbridge::daemon::plan_settings(&settings),
        model: Some(&settings.collision),
    });
    let message = rigbridge::daemon::error_chain(&too_fast.unwrap_err());
    assert!(
        message.contains("limit") || message.contains("max"),
        "{message}"
    );
}

/// Why `config`, written into a fresh directory, is refused when it is planned (it must
/// load), as `run` prints it.
fn plan_refusal(name: &str, config: &str) -> String {
    let settings = load(name, config).unwrap();
    let start = settings.initial();
    let refused = settings.config.job.plan(&PlanContext {
        rig: &settings.rig,
        app_rig: None,
        start: &start,
        settings: &rigbridge::daemon::plan_settings(&settings),
        model: Some(&settings.collision),
    });
    rigbridge::daemon::error_chain(&refused.expect_err("the job is refused"))
}

/// The numbers of `text` after `after`, up to the first `until`, in order: `0.630` and `0`
/// in `at [0.630, 0.000, ...` read as numbers.
fn numbers_after(text: &str, after: &str, until: &str) -> Vec<f64> {
    let start = text
        .find(after)
        .unwrap_or_else(|| panic!("no `{after}` in {text}"))
        + after.len();
    let rest = &text[start..];
    let end = rest.find(until).unwrap_or(rest.len());
    rest[..end]
        .split(|c: char| !(c.is_ascii_digit() || c == '.' || c == '-'))
        .filter_map(|word| word.parse().ok())
        .collect()
}

/// The IRB 120's geometry (config/irb120.toml, from ROS-Industrial's URDF): axis 2 sits
/// 0.29 m above the base, the upper arm is 0.27 m, the forearm 0.07 m up then 0.302 m out
/// to the wrist centre, and tool0 0.072 m beyond it.
const SHOULDER_Z_M: f64 = 0.29;
const UPPER_ARM_M: f64 = 0.27;
const FOREARM_RISE_M: f64 = 0.07;
const FOREARM_M: f64 = 0.302;
const WRIST_TO_TOOL_M: f64 = 0.072;

#[test]
fn move_linear_names_an_unreachable_pose_as_written_and_where_its_line_fails() {
    // Tool along +x at z = 0.45 m, from x = 0.40 m (reachable) out to x = 0.90 m.
    let config = "rig = \"irb120.toml\"\n[twin]\ninitial_deg = [0.0, 0.0, 0.0, 0.0, 30.0, 0.0]\n\
                  [job]\nkind = \"move_linear\"\nposes = [\n\
                  { xyz_m = [0.40, 0.0, 0.45], quat_wxyz = [0.7071, 0.0, 0.7071, 0.0] },\n\
                  { xyz_m = [0.90, 0.0, 0.45], quat_wxyz = [0.7071, 0.0, 0.7071, 0.0] },\n]\n";
    let message = plan_refusal("linear-far", config);
    println!("{message}");
    // The wrist centre lies 0.072 m back from the tool along x; the arm reaches it while it
    // is at most the upper arm plus the forearm from axis 2.
    let reach = UPPER_ARM_M + FOREARM_RISE_M.hypot(FOREARM_M);
    let rise = 0.45 - SHOULDER_Z_M;
    let excess = (0.90 - WRIST_TO_TOOL_M).hypot(rise) - reach;
    // The pose by its index in the job's list and as written, and by how much it is out of
    // reach (not a point of the line the user never wrote, nor the line's index).
    let named = format!(
        "job.poses[1] = {{ xyz_m = [0.9, 0.0, 0.45], quat_wxyz = [0.7071, 0.0, 0.7071, 0.0] }} \
         cannot be reached: target is out of reach by {excess:.6} m"
    );
    assert!(message.contains(&named), "{message}\nexpected: {named}");
    assert!(!message.contains("waypoint 0"), "{message}");
    // Where the line from job.poses[0] leaves reach: the first 1 mm sample
    // (`cartesian_step_m`) past the edge, with the fraction of the line that point is at.
    let along = numbers_after(
        &message,
        "the line to it from job.poses[0] first fails ",
        " m",
    );
    let [percent, x, y, z] = along[..] else {
        panic!("{message}: {along:?}")
    };
    let edge_x = WRIST_TO_TOOL_M + (reach * reach - rise * rise).sqrt();
    assert!(
        x > edge_x - 0.0005 && x <= edge_x + 0.001 + 0.0005,
        "{message}: the edge is at x = {edge_x:.4} m"
    );
    assert_eq!((y, z), (0.0, 0.45), "{message}");
    assert!(
        (percent - (x - 0.40) / (0.90 - 0.40) * 100.0).abs() <= 0.15,
        "{message}"
    );
}

/// A joint value outside its limits is named with the value and the limits in the unit it
/// was written in.
#[test]
fn a_joint_target_outside_its_limits_names_the_value_and_the_limits_in_its_unit() {
    // joint_3 of the IRB 120 is +70 / -110 deg (ABB's product manual, config/irb120.toml).
    let refused = load(
        "limits-deg",
        "rig = \"irb120.toml\"\n[job]\nkind = \"move_joints\"\n\
         targets_deg = [[0.0, 0.0, 0.0, 0.0, 30.0, 0.0], [0.0, 0.0, 80.0, 0.0, 30.0, 0.0]]\n",
    )
    .unwrap_err();
    assert!(
        refused.contains(
            "key `job.targets_deg[1][2]` = 80.0: \
             joint_3 = 80.000 deg is outside its limits [-110.000, 70.000] deg"
        ),
        "{refused}"
    );
    // The painter's lift is prismatic, 0 to 2.4 m (config/painter.toml): metres.
    let dir = job_dir("limits-m");
    std::fs::copy(repo_path("config/painter.toml"), dir.join("painter.toml")).unwrap();
    std::fs::write(
        dir.join("job.toml"),
        "rig = \"painter.toml\"\n[job]\nkind = \"move_joints\"\n\
         targets_deg = [[0.0, 0.0, 0.0, 3.0, 0.0, 0.0, 0.0, 0.0, 30.0, 0.0]]\n",
    )
    .unwrap();
    let refused = load_run_settings(&dir.join("job.toml"))
        .unwrap_err()
        .to_string();
    assert!(
        refused.contains(
            "key `job.targets_deg[0][3]` = 3.0: lift = 3.000 m is outside its limits [0.000, 2.400] m"
        ),
        "{refused}"
    );
    // A trajectory file's row: its line in the file and its column.
    let dir = job_dir("limits-row");
    std::fs::write(
        dir.join("t.csv"),
        "t,j1,j2,j3,j4,j5,j6\n0,0,0,0,0,30,0\n1,0,0,80,0,30,0\n",
    )
    .unwrap();
    std::fs::write(
        dir.join("job.toml"),
        "rig = \"irb120.toml\"\n[job]\nkind = \"follow_trajectory\"\nfile = \"t.csv\"\n",
    )
    .unwrap();
    let refused = load_run_settings(&dir.join("job.toml"))
        .unwrap_err()
        .to_string();
    assert!(
        refused.contains(
            "key `job.file` = \"t.csv\": row 3: column 4: \
             joint_3 = 80.000 deg is outside its limits [-110.000, 70.000] deg"
        ),
        "{refused}"
    );
}

/// A follow_trajectory config reading `csv` as `t.csv`, in a fresh directory.
fn follow_refusal(name: &str, csv: &str) -> String {
    let config = "rig = \"irb120.toml\"\n[twin]\ninitial_deg = [0.0, 0.0, 0.0, 0.0, 30.0, 0.0]\n\
                  [job]\nkind = \"follow_trajectory\"\nfile = \"t.csv\"\n";
    let dir = job_dir(name);
    std::fs::write(dir.join("t.csv"), csv).unwrap();
    std::fs::write(dir.join("job.toml"), config).unwrap();
    let settings = load_run_settings(&dir.join("job.toml")).unwrap();
    let refused = settings.config.job.plan(&PlanContext {
        rig: &settings.rig,
        app_rig: None,
        start: &settings.initial(),
        settings: &rigbridge::daemon::plan_settings(&settings),
        model: Some(&settings.collision),
    });
    rigbridge::daemon::error_chain(&refused.expect_err("the trajectory is refused"))
}

#[test]
fn follow_trajectory_names_the_rows_and_their_time_in_the_files_units_with_a_hint() {
    // joint_1 from 0 to 10 deg in 0.1 s, at rest at both rows: the cubic between them is
    // 10 deg x (3 s^2 - 2 s^3), s = t / 0.1 s, sampled every 4 ms (250 Hz). Its first
    // second difference, around t = 4 ms, is far above joint_1's 1000 deg/s^2.
    let message = follow_refusal(
        "follow-accel",
        "t,j1,j2,j3,j4,j5,j6\n0,0,0,0,0,30,0\n0.1,10,0,0,0,30,0\n",
    );
    println!("{message}");
    let cubic = |t: f64| {
        let s = t / 0.1;
        10.0 * (3.0 * s * s - 2.0 * s * s * s)
    };
    let dt = 0.004;
    let accel = (cubic(2.0 * dt) - 2.0 * cubic(dt) + cubic(0.0)) / (dt * dt);
    let expected = format!(
        "at t = 0.004 s, on the curve from row 2 of t.csv (t = 0.000 s) to row 3 of t.csv \
         (t = 0.100 s): joint_1 accelerates at {accel:.3} deg/s^2, above its max acceleration \
         1000.000 deg/s^2; hint: the curve starts at rest at the first row"
    );
    assert!(
        message.contains(&expected),
        "{message}\nexpected: {expected}"
    );
    assert!(
        !message.contains("rad/s^2") && !message.contains("sample 1"),
        "{message}"
    );
    // 30 deg in the 0.1 s between rows 3 and 4 of the file (lines 3 and 4): over joint_1's
    // 250 deg/s on that piece, whatever its tangents.
    let message = follow_refusal(
        "follow-speed",
        "t,j1,j2,j3,j4,j5,j6\n0,0,0,0,0,30,0\n1,10,0,0,0,30,0\n1.1,40,0,0,0,30,0\n\
         2.1,50,0,0,0,30,0\n",
    );
    println!("{message}");
    let t = numbers_after(&message, "at t = ", " s")[0];
    assert!((1.0..=1.1).contains(&t), "{message}");
    let piece = "on the curve from row 3 of t.csv (t = 1.000 s) to row 4 of t.csv (t = 1.100 s): \
                 joint_1 moves at ";
    assert!(message.contains(piece), "{message}");
    let speed = numbers_after(&message, piece, " deg/s")[0];
    assert!(speed > 250.0, "{message}");
    assert!(
        message.contains("deg/s, above its max speed 250.000 deg/s; hint: slow down"),
        "{message}"
    );
}

#[test]
fn move_linear_names_a_line_between_reachable_poses_and_where_it_fails() {
    // Tool pointing down, 0.15 m in front of the base, swept from y = 0.3 m to y = -0.3 m:
    // both ends are reachable (move_poses reaches them), the middle of the line, over the
    // base, is not within the axes' limits.
    let poses = "poses = [\n\
                 { xyz_m = [0.15, 0.3, 0.25], quat_wxyz = [0.0, 0.0, 1.0, 0.0] },\n\
                 { xyz_m = [0.15, -0.3, 0.25], quat_wxyz = [0.0, 0.0, 1.0, 0.0] },\n]\n";
    let config = |kind: &str| {
        format!(
            "rig = \"irb120.toml\"\n[twin]\ninitial_deg = [0.0, 0.0, 0.0, 0.0, 30.0, 0.0]\n\
             [job]\nkind = \"{kind}\"\n{poses}"
        )
    };
    plan(&load("line-ends", &config("move_poses")).unwrap());
    let message = plan_refusal("line-middle", &config("move_linear"));
    println!("{message}");
    let named = "the line from job.poses[0] to job.poses[1] = \
                 { xyz_m = [0.15, -0.3, 0.25], quat_wxyz = [0.0, 0.0, 1.0, 0.0] } first fails ";
    assert!(message.contains(named), "{message}");
    assert!(
        message.contains(
            "both poses are reachable, the straight line between them is not: \
             add a pose between them, or use move_poses"
        ),
        "{message}"
    );
    // The point is on the line, as far along it as the fraction says, and short of its end.
    let [percent, x, y, z] = numbers_after(&message, named, " m:")[..] else {
        panic!("{message}")
    };
    assert_eq!((x, z), (0.15, 0.25), "{message}");
    assert!(
        (y - (0.3 - 0.6 * percent / 100.0)).abs() <= 0.001,
        "{message}"
    );
    assert!(percent > 0.0 && percent < 100.0, "{message}");
}
