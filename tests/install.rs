//! The binary as `cargo install` leaves it: run from an empty directory with an empty HOME and
//! no RIGBRIDGE_CONFIG, so nothing of the checkout is in reach. The built-in settings run a
//! job, the batch tools find their rig, `config dump` writes files that load back, and a
//! missing file's error says where it looked.

use crate::common;

use common::output_with_stdin;
use rigbridge::apps::paint::load_paint_settings;
use rigbridge::daemon::config::load_run_settings;
use rigbridge::rig::load_rig;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// A fresh empty directory under the system's temporary directory.
fn empty_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("rigbridge-install-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// Runs the binary in `cwd` with HOME pointed at an empty directory and RIGBRIDGE_CONFIG unset.
fn rigbridge(cwd: &Path, args: &[&str], stdin: &str) -> Output {
    let home = cwd.join("home");
    std::fs::create_dir_all(&home).unwrap();
    output_with_stdin(
        Command::new(env!("CARGO_BIN_EXE_rigbridge"))
            .args(args)
            .current_dir(cwd)
            .env("HOME", &home)
            .env_remove("RIGBRIDGE_CONFIG"),
        stdin,
    )
}

fn stderr(output: &Output) -> String {
    String::from_utf8_lossy(&output.stderr).into_owned()
}

#[test]
fn run_completes_with_the_built_in_settings() {
    let dir = empty_dir("run");
    let output = rigbridge(&dir, &["run", "--clock", "virtual", "--log", "r.mcap"], "");
    assert!(output.status.success(), "{}", stderr(&output));
    let text = String::from_utf8_lossy(&output.stdout);
    assert!(
        text.contains("wall_figure on irb120 over loopback: completed"),
        "{text}"
    );
    assert!(dir.join("r.mcap").is_file());
}

#[test]
fn the_batch_tools_find_the_built_in_rig() {
    let dir = empty_dir("fk");
    let output = rigbridge(&dir, &["fk"], "j1,j2,j3,j4,j5,j6\n0,0,0,0,30,0\n");
    assert!(output.status.success(), "{}", stderr(&output));
    let text = String::from_utf8_lossy(&output.stdout);
    let row: Vec<&str> = text.lines().nth(1).unwrap().split(',').collect();
    // The IRB 120 with joint 5 at 30 deg: the wrist centre 0.302 m forward and 0.63 m up,
    // tool0 0.072 m beyond it along the tilted axis 6 (the ROS-Industrial abb_irb120
    // geometry the README cites).
    let x: f64 = row[0].parse().unwrap();
    let z: f64 = row[2].parse().unwrap();
    let expected_x = 0.302 + 0.072 * 30f64.to_radians().cos();
    let expected_z = 0.630 - 0.072 * 30f64.to_radians().sin();
    assert!((x - expected_x).abs() < 1e-9, "{text}");
    assert!((z - expected_z).abs() < 1e-9, "{text}");
    assert_eq!(row[7], "ok");
}

#[test]
fn config_dump_writes_files_that_load_back() {
    let dir = empty_dir("dump");
    let output = rigbridge(&dir, &["config", "dump", "cfg"], "");
    assert!(output.status.success(), "{}", stderr(&output));
    let said = String::from_utf8_lossy(&output.stdout);
    for name in ["rigbridge.toml", "irb120.toml", "paint.toml", "sloth.toml"] {
        assert!(dir.join("cfg").join(name).is_file(), "{name}");
        assert!(said.contains(&format!("wrote cfg/{name}")), "{said}");
    }
    // The written files are the settings: a run from them, after an edit, uses the edit.
    let settings = dir.join("cfg/rigbridge.toml");
    let text = std::fs::read_to_string(&settings).unwrap();
    std::fs::write(&settings, text.replace("laps = 2", "laps = 1")).unwrap();
    let planned = |config: &str, log: &str| -> f64 {
        let report = format!("{log}.json");
        let mut args = vec![
            "run", "--clock", "virtual", "--log", log, "--report", &report,
        ];
        if !config.is_empty() {
            args.extend(["--config", config]);
        }
        let output = rigbridge(&dir, &args, "");
        assert!(output.status.success(), "{}", stderr(&output));
        let report: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(dir.join(&report)).unwrap()).unwrap();
        report["planned_duration_s"].as_f64().unwrap()
    };
    // One lap of the star instead of the built-in two: a shorter plan.
    let (edited, built_in) = (
        planned("cfg/rigbridge.toml", "edited.mcap"),
        planned("", "built-in.mcap"),
    );
    assert!(
        edited < 0.75 * built_in,
        "edited {edited} s, built-in {built_in} s"
    );
    let cfg = dir.join("cfg");
    for name in ["rigbridge.toml", "gait-run.toml", "paint-run.toml"] {
        let loaded = load_run_settings(&cfg.join(name));
        assert!(loaded.is_ok(), "{name}: {}", loaded.unwrap_err());
    }
    assert_eq!(load_rig(&cfg.join("irb120.toml")).unwrap().dof(), 6);
    let paint = load_paint_settings(&cfg.join("paint.toml"));
    assert!(
        paint.is_ok(),
        "{}",
        paint.err().map(|e| e.to_string()).unwrap_or_default()
    );
    // A second dump keeps the user's edit and says so.
    let again = rigbridge(&dir, &["config", "dump", "cfg"], "");
    assert_eq!(again.status.code(), Some(2), "{}", stderr(&again));
    assert!(stderr(&again).contains("--force"), "{}", stderr(&again));
    assert!(
        std::fs::read_to_string(&settings)
            .unwrap()
            .contains("laps = 1")
    );
    let forced = rigbridge(&dir, &["config", "dump", "cfg", "--force"], "");
    assert!(forced.status.success(), "{}", stderr(&forced));
    assert!(
        std::fs::read_to_string(&settings)
            .unwrap()
            .contains("laps = 2")
    );
}

#[test]
fn a_missing_config_names_where_it_looked() {
    let dir = empty_dir("missing");
    let output = rigbridge(&dir, &["run", "--config", "elsewhere/rigbridge.toml"], "");
    assert_eq!(output.status.code(), Some(1));
    let message = stderr(&output);
    let looked = dir.canonicalize().unwrap().join("elsewhere/rigbridge.toml");
    let looked_plain = dir.join("elsewhere/rigbridge.toml");
    assert!(
        message.contains(&looked.display().to_string())
            || message.contains(&looked_plain.display().to_string()),
        "{message}"
    );
    assert!(message.contains("embedded:/rigbridge.toml"), "{message}");
    // From the environment, the error says so.
    let output = Command::new(env!("CARGO_BIN_EXE_rigbridge"))
        .args(["run"])
        .current_dir(&dir)
        .env("RIGBRIDGE_CONFIG", "nowhere.toml")
        .output()
        .unwrap();
    let message = stderr(&output);
    assert!(message.contains("RIGBRIDGE_CONFIG"), "{message}");
    assert!(message.contains("nowhere.toml"), "{message}");
}

#[test]
fn relative_paths_in_a_config_resolve_against_its_directory() {
    let dir = empty_dir("relative");
    let output = rigbridge(&dir, &["config", "dump", "a/b"], "");
    assert!(output.status.success(), "{}", stderr(&output));
    std::fs::remove_file(dir.join("a/b/irb120.toml")).unwrap();
    // From another directory: the rig is looked for beside the settings, not in the cwd.
    std::fs::create_dir_all(dir.join("c")).unwrap();
    std::fs::copy(dir.join("a/b/rigbridge.toml"), dir.join("c/irb120.toml")).unwrap();
    let output = rigbridge(
        &dir.join("c"),
        &["run", "--config", "../a/b/rigbridge.toml"],
        "",
    );
    assert_eq!(output.status.code(), Some(1));
    let message = stderr(&output);
    assert!(message.contains("a/b/irb120.toml"), "{message}");
}
