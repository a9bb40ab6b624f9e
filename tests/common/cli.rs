//! The rigbridge binary as a test runs it to the end: the command from the repository root,
//! the check that it exited 0 (else its stderr in the failure), the JSON reports it writes
//! and the numbers in them (or in a peer's JSON). Owns no judgement of what the run did:
//! the callers check the reports.

use super::repo_path;
use std::path::Path;
use std::process::{Child, Command, Output, Stdio};

/// The rigbridge binary, started in the repository root so that `config/...` resolves.
pub fn rigbridge() -> Command {
    let mut command = Command::new(env!("CARGO_BIN_EXE_rigbridge"));
    command.current_dir(repo_path(""));
    command
}

/// `rigbridge run ARGS --log LOG --report REPORT` from the repository root, started with its
/// stdout and stderr piped (for `wait_with_output`).
pub fn spawn_run(args: &[&str], log: &Path, report: &Path) -> Child {
    rigbridge()
        .arg("run")
        .args(args)
        .arg("--log")
        .arg(log)
        .arg("--report")
        .arg(report)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap()
}

/// Fails the test, showing the command's stderr, unless it exited 0.
#[track_caller]
pub fn assert_succeeded(output: &Output) {
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
}

/// Fails the test, saying "`who` failed: " and showing the command's stderr, unless it
/// exited 0.
#[track_caller]
pub fn assert_succeeded_as(output: &Output, who: &str) {
    assert!(
        output.status.success(),
        "{who} failed: {}",
        String::from_utf8_lossy(&output.stderr)
    );
}

/// The JSON file at `path`: a `--report` the command wrote.
pub fn read_json(path: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

/// The number under `key` in `report`; fails the test, naming the key, where there is none.
#[track_caller]
pub fn number(report: &serde_json::Value, key: &str) -> f64 {
    report[key]
        .as_f64()
        .unwrap_or_else(|| panic!("no {key} in {report}"))
}

/// `rigbridge paint` of three walls (seed 2, virtual clock) with `config/paint-run.toml`,
/// run in `dir` (not the repository root: its paint settings resolve next to the run
/// settings), writing `dir/p.mcap` and `dir/p.json`. It must succeed; returns the report.
pub fn paint_three_walls_in(dir: &Path) -> serde_json::Value {
    let output = Command::new(env!("CARGO_BIN_EXE_rigbridge"))
        .args(["paint", "--walls", "3", "--seed", "2", "--clock", "virtual"])
        .arg("--config")
        .arg(repo_path("config/paint-run.toml"))
        .args(["--log", "p.mcap", "--report", "p.json"])
        .current_dir(dir)
        .output()
        .unwrap();
    assert_succeeded(&output);
    read_json(&dir.join("p.json"))
}

/// The JSON array `value` as numbers; fails the test where it is not one of numbers.
#[track_caller]
pub fn numbers(value: &serde_json::Value) -> Vec<f64> {
    value
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect()
}
