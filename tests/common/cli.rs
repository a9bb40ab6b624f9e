//! The rigbridge binary as a test runs it to the end: the command from the repository root,
//! the check that it exited 0 (else its stderr in the failure), and the JSON reports it
//! writes. Owns no judgement of what the run did: the callers check the reports.

use super::repo_path;
use std::path::Path;
use std::process::{Command, Output};

/// The rigbridge binary, started in the repository root so that `config/...` resolves.
pub fn rigbridge() -> Command {
    let mut command = Command::new(env!("CARGO_BIN_EXE_rigbridge"));
    command.current_dir(repo_path(""));
    command
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

/// The JSON file at `path`: a `--report` the command wrote.
pub fn read_json(path: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}
