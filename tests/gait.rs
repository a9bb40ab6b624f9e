//! The sloth gait end to end: planned, validated, streamed through the loopback twin and
//! judged from the twin's actual positions (virtual clock). Scenarios across their ranges,
//! rule stops outside them, and config errors naming file, key and value.

mod common;

use common::repo_path;
use rigbridge::clock::VirtualClock;
use rigbridge::daemon::config::{RunSettings, load_run_settings};
use rigbridge::daemon::gait::{GaitRun, run_gait};
use rigbridge::rig::ConfigError;
use rigbridge::stream::{Outcome, StreamControl};
use rigbridge::task::gait::{LimbSolver, Scenario, SlothRig};

fn settings() -> RunSettings {
    load_run_settings(&repo_path("config/gait-run.toml")).expect("config/gait-run.toml loads")
}

fn walk(name: &str, angle: Option<f64>, gap: Option<f64>) -> GaitRun {
    walk_with(settings(), name, angle, gap)
}

/// The gait's run settings with the limbs placed by `solver`.
fn settings_with(solver: LimbSolver) -> RunSettings {
    let mut settings = settings();
    let mut sloth = settings.sloth.as_deref().cloned().expect("a sloth rig");
    sloth.gait.solver = solver;
    settings.sloth = Some(std::sync::Arc::new(sloth));
    settings
}

fn walk_with(settings: RunSettings, name: &str, angle: Option<f64>, gap: Option<f64>) -> GaitRun {
    let scenario = Scenario::build(name, angle, gap).expect("scenario builds");
    let dir = std::env::temp_dir().join(format!("rigbridge-gait-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let solver = settings.sloth.as_ref().map(|s| s.gait.solver);
    let log = dir.join(format!(
        "{name}-{}-{}-{solver:?}.mcap",
        angle.unwrap_or(0.0),
        gap.unwrap_or(0.0)
    ));
    let _ = std::fs::remove_file(&log);
    let run = run_gait(
        &settings,
        &scenario,
        &VirtualClock::new(),
        Some(&log),
        &StreamControl::default(),
    )
    .expect("the gait plans and streams");
    assert!(log.exists(), "the run is logged");
    run
}

fn assert_passes(run: &GaitRun) {
    let v = &run.verdict;
    assert!(
        v.passed,
        "{} {:?} {:?}: {:?}",
        v.scenario, v.angle_deg, v.gap_m, v.reason
    );
    assert!(v.cycles_judged >= 3);
    assert_eq!(run.run.stream.outcome, Outcome::Completed);
    assert_eq!(run.run.stream.limit_violations, 0);
    for limb in &v.limbs {
        assert!(limb.max_foot_to_surface_mm <= 5.0, "{limb:?}");
        assert!(limb.max_slip_mm <= 1.0, "{limb:?}");
        assert!(
            limb.max_bone_excursion_deg <= limb.bone_limit_deg + 1e-9,
            "{limb:?}"
        );
        assert!((limb.duty_factor - 2.0 / 3.0).abs() < 0.05, "{limb:?}");
    }
    assert!(v.min_body_clearance_mm > 0.0);
    assert!(v.max_ik_residual_mm <= 1.0);
    let order = ["rh", "lf", "lh", "rf"];
    for (i, name) in v.footfall_order.iter().enumerate() {
        assert_eq!(name, order[i % 4]);
    }
}

/// A gait that stops on a rule: the reason is given, the stream still completes (the
/// swings under way land first), nothing enters a branch and no bone leaves its limits.
fn assert_stops_cleanly(run: &GaitRun, reason_contains: &str) {
    let v = &run.verdict;
    assert!(!v.passed);
    let reason = v.stopped_because.as_deref().unwrap_or_default();
    assert!(reason.contains(reason_contains), "{reason}");
    assert_eq!(run.run.stream.outcome, Outcome::Completed);
    assert!(v.min_body_clearance_mm > 0.0);
    for limb in &v.limbs {
        assert!(
            limb.max_bone_excursion_deg <= limb.bone_limit_deg + 1e-9,
            "{limb:?}"
        );
        assert!(limb.max_foot_to_surface_mm <= 5.0, "{limb:?}");
    }
    let last = run.plan.frame(run.plan.len() - 1);
    let before = run.plan.frame(run.plan.len() - 2);
    let moving = last.iter().zip(before).any(|(a, b)| (a - b).abs() > 1e-6);
    assert!(!moving, "the gait ends at rest");
}

#[test]
fn straight_branch_at_the_sloths_speed() {
    let run = walk("straight", None, None);
    assert_passes(&run);
    assert!(
        (run.verdict.speed_mps - 0.11).abs() <= 0.02,
        "{}",
        run.verdict.speed_mps
    );
}

#[test]
fn straight_branch_with_fabrik_limbs() {
    let run = walk_with(settings_with(LimbSolver::Fabrik), "straight", None, None);
    assert_eq!(run.verdict.solver, LimbSolver::Fabrik);
    assert_passes(&run);
    assert!(
        (run.verdict.speed_mps - 0.11).abs() <= 0.02,
        "{}",
        run.verdict.speed_mps
    );
}

#[test]
fn fabrik_limbs_stop_cleanly_where_their_poses_jump() {
    // At 135 deg a FABRIK pose of the left hind limb jumps (its pelvis above the axis
    // speed in one period): the gait stops there, and never streams the jump.
    let run = walk_with(
        settings_with(LimbSolver::Fabrik),
        "height-change",
        Some(135.0),
        None,
    );
    assert_stops_cleanly(&run, "above 95 % of its max speed");
    assert_eq!(run.run.stream.limit_violations, 0);
}

#[test]
fn branch_turns_from_95_to_175_degrees() {
    // 110, 150 and 160 deg stopped before the body was held back from a trailing hind foot.
    for angle in [95.0, 110.0, 115.0, 135.0, 150.0, 155.0, 160.0, 175.0] {
        assert_passes(&walk("branch-turn", Some(angle), None));
    }
}

#[test]
fn height_changes_from_135_to_200_degrees() {
    for angle in [135.0, 150.0, 155.0, 165.0, 180.0, 200.0] {
        assert_passes(&walk("height-change", Some(angle), None));
    }
}

#[test]
fn a_change_to_a_close_parallel_branch() {
    for gap in [0.10, 0.15, 0.20] {
        assert_passes(&walk("parallel", None, Some(gap)));
    }
}

#[test]
fn a_parallel_branch_too_far_for_the_limbs_stops_the_gait_cleanly() {
    assert_stops_cleanly(&walk("parallel", None, Some(0.30)), "no next step");
}

#[test]
fn too_steep_a_rise_stops_before_the_branch() {
    assert_stops_cleanly(&walk("height-change", Some(130.0), None), "rises 50.0 deg");
}

#[test]
fn head_first_descent_is_refused() {
    assert_stops_cleanly(
        &walk("height-change", Some(210.0), None),
        "head-first descent",
    );
}

#[test]
fn the_streamed_rig_fits_the_wire_protocol() {
    let sloth = SlothRig::load(&repo_path("config/sloth.toml")).unwrap();
    assert_eq!(sloth.dof(), 6 + 4 * 5);
    assert!(sloth.dof() <= rigbridge::protocol::MAX_AXES);
    let names: Vec<&str> = sloth.limbs.iter().map(|l| l.name.as_str()).collect();
    assert_eq!(names, ["rh", "lf", "lh", "rf"]);
    let polylines = sloth.bone_polylines(&vec![0.0; sloth.dof()]).unwrap();
    assert_eq!(polylines.len(), 5, "the spine and four limbs");
    assert!(
        polylines[1..].iter().all(|limb| limb.len() == 5),
        "girdle and four bone ends"
    );
    assert!(sloth.bone_polylines(&[0.0; 3]).is_err());
}

fn sloth_variant(name: &str, edit: impl Fn(String) -> String) -> Result<SlothRig, ConfigError> {
    let original = std::fs::read_to_string(repo_path("config/sloth.toml")).unwrap();
    let dir = std::env::temp_dir().join(format!("rigbridge-sloth-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join(name);
    std::fs::write(&path, edit(original)).unwrap();
    SlothRig::load(&path)
}

#[test]
fn a_bad_bone_limit_names_file_key_and_value() {
    let error = sloth_variant("inverted.toml", |t| {
        t.replacen("lower_deg = -20.8", "lower_deg = 200.0", 1)
    })
    .unwrap_err();
    match error {
        ConfigError::Invalid {
            file, key, value, ..
        } => {
            assert!(file.ends_with("inverted.toml"));
            assert!(
                key.starts_with("limb[1].joint[") && key.ends_with("upper_deg"),
                "{key}"
            );
            assert!(!value.is_empty());
        }
        other => panic!("{other}"),
    }
}

#[test]
fn a_bad_gait_setting_names_file_key_and_value() {
    let message = sloth_variant("speed.toml", |t| {
        t.replacen("speed_m_s = 0.11", "speed_m_s = -1.0", 1)
    })
    .unwrap_err()
    .to_string();
    assert!(message.contains("speed.toml"), "{message}");
    assert!(message.contains("gait.speed_m_s"), "{message}");
    assert!(message.contains("-1.0"), "{message}");
}

#[test]
fn an_unknown_limb_solver_names_file_key_and_value() {
    let message = sloth_variant("solver.toml", |t| {
        t.replacen("solver = \"ccd\"", "solver = \"jacobian\"", 1)
    })
    .unwrap_err()
    .to_string();
    assert!(message.contains("solver.toml"), "{message}");
    assert!(message.contains("gait.solver"), "{message}");
    assert!(message.contains("jacobian"), "{message}");
}

#[test]
fn fabrik_limbs_load_from_the_file() {
    let sloth = sloth_variant("fabrik.toml", |t| {
        t.replacen("solver = \"ccd\"", "solver = \"fabrik\"", 1)
    })
    .expect("solver = \"fabrik\" loads");
    assert_eq!(sloth.gait.solver, LimbSolver::Fabrik);
}

#[test]
fn an_unknown_footfall_limb_is_refused() {
    let message = sloth_variant("order.toml", |t| {
        t.replacen("\"lf\", \"lh\"", "\"lf\", \"xx\"", 1)
    })
    .unwrap_err()
    .to_string();
    assert!(message.contains("gait.footfall_order[2]"), "{message}");
    assert!(message.contains("xx"), "{message}");
}

#[test]
fn an_unknown_scenario_is_refused_by_name() {
    let error = Scenario::build("loop-the-loop", None, None).unwrap_err();
    assert!(error.to_string().contains("loop-the-loop"));
}

fn scratch(name: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("rigbridge-gait-cli-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join(name);
    let _ = std::fs::remove_file(&path);
    path
}

#[test]
fn the_gait_command_reports_and_draws() {
    let (report, picture, log) = (scratch("r.json"), scratch("p.svg"), scratch("g.mcap"));
    let output = std::process::Command::new(env!("CARGO_BIN_EXE_rigbridge"))
        .current_dir(repo_path("."))
        .args([
            "gait",
            "--scenario",
            "branch-turn",
            "--angle",
            "135",
            "--clock",
            "virtual",
        ])
        .arg("--report")
        .arg(&report)
        .arg("--picture")
        .arg(&picture)
        .arg("--log")
        .arg(&log)
        .output()
        .unwrap();
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
    assert_eq!(json["passed"], true);
    assert_eq!(json["limbs"].as_array().unwrap().len(), 4);
    assert_eq!(json["run"]["outcome"], "completed");
    let svg = std::fs::read_to_string(&picture).unwrap();
    assert!(svg.starts_with("<svg") && svg.contains("gait diagram"));
    assert!(log.exists());
    assert_eq!(json["solver"], "ccd");
}

fn gait_with_solver(solver: &str, report: &std::path::Path) -> std::process::Output {
    std::process::Command::new(env!("CARGO_BIN_EXE_rigbridge"))
        .current_dir(repo_path("."))
        .args(["gait", "--scenario", "straight", "--clock", "virtual"])
        .args(["--solver", solver])
        .arg("--report")
        .arg(report)
        .arg("--log")
        .arg(scratch(&format!("{solver}.mcap")))
        .output()
        .unwrap()
}

#[test]
fn the_gait_command_takes_the_limb_solver() {
    let report = scratch("fabrik.json");
    let output = gait_with_solver("fabrik", &report);
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
    assert_eq!(json["solver"], "fabrik");
    assert_eq!(json["passed"], true);

    let refused = gait_with_solver("newton", &scratch("newton.json"));
    assert!(!refused.status.success());
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(
        stderr.contains("--solver") && stderr.contains("newton"),
        "{stderr}"
    );
}

#[test]
fn run_takes_a_gait_job() {
    let log = scratch("run.mcap");
    let output = std::process::Command::new(env!("CARGO_BIN_EXE_rigbridge"))
        .current_dir(repo_path("."))
        .args([
            "run",
            "--config",
            "config/gait-run.toml",
            "--clock",
            "virtual",
        ])
        .arg("--log")
        .arg(&log)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(
        output.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&output.stderr)
    );
    assert!(stdout.contains("gait straight on sloth"), "{stdout}");
}
