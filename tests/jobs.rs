//! The job kinds users write (docs/jobs.md): every example there runs end to end with the
//! installed binary's `run`, a ten-line config runs, `move_linear` keeps the tool on its
//! lines by forward kinematics of the commanded joints, `follow_trajectory` follows its
//! file, and TOML refuses what HTTP refuses with the same text.

mod common;

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
        sloth: None,
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
            sloth: None,
            start: &start,
            settings: &rigbridge::daemon::plan_settings(settings),
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
        .find(|&k| (tool(trajectory.position(k)).position - corners[0]).length() <= 1e-6)
        .expect("the first pose is reached");
    let mut worst: f64 = 0.0;
    for k in reached..trajectory.len() {
        let p = tool(trajectory.position(k)).position;
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
    let last = tool(trajectory.position(trajectory.len() - 1)).position;
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
        sloth: None,
        start: &settings.initial(),
        settings: &rigbridge::daemon::plan_settings(&settings),
    });
    let message = rigbridge::daemon::error_chain(&too_fast.unwrap_err());
    assert!(
        message.contains("limit") || message.contains("max"),
        "{message}"
    );
}
