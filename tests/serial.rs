//! The daemon and the twin as separate processes over a real serial line: a pseudo-terminal
//! pair opened by `rigbridge twin --pty`, the daemon on its slave side at 115200 baud.

use crate::common;

use common::cli::{assert_succeeded, read_json, rigbridge};
use common::scratch_file;
use rigbridge::log::read_log;
use std::io::{BufRead, BufReader};
use std::process::{Child, Stdio};

struct TwinProcess(Child);

impl Drop for TwinProcess {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// A serial device that does not exist: the run ends naming it, not a silent controller.
#[test]
fn a_missing_serial_device_is_named() {
    let path = format!("/dev/rigbridge-no-such-tty-{}", std::process::id());
    let (log, report) = (
        scratch_file("serial", "missing.mcap"),
        scratch_file("serial", "missing.json"),
    );
    let output = common::cli::spawn_run(
        &["--link", &format!("serial://{path}?baud=115200")],
        &log,
        &report,
    )
    .wait_with_output()
    .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    println!("{}", stderr.trim());
    assert_eq!(output.status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains(&format!("no such device {path}")),
        "{stderr}"
    );
    assert!(!stderr.contains("Hello"), "{stderr}");
}

#[test]
fn a_job_over_a_pty_at_115200_baud_completes_within_limits() {
    let mut child = rigbridge()
        .args(["twin", "--pty"])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut first = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut first)
        .unwrap();
    let _twin = TwinProcess(child);
    let pty = first.trim().to_string();
    assert!(
        pty.starts_with("/dev/"),
        "the twin prints its pty first: {pty:?}"
    );

    let (log, report) = (
        scratch_file("serial", "pty.mcap"),
        scratch_file("serial", "pty.json"),
    );
    let link = format!("serial://{pty}?baud=115200");
    let output = rigbridge()
        .args([
            "run",
            "--link",
            &link,
            "--log",
            log.to_str().unwrap(),
            "--report",
            report.to_str().unwrap(),
        ])
        .output()
        .unwrap();
    assert_succeeded(&output);
    let report = read_json(&report);
    assert_eq!(report["outcome"], "completed", "{report}");
    assert_eq!(report["limit_violations"], 0);
    assert_eq!(report["gaps"], 0, "{report}");
    assert_eq!(report["crc_errors"], 0);
    let cycles = report["cycles"].as_u64().unwrap();
    // A feedback later than half a cycle is a timeout (used the next cycle): how many is
    // the host's scheduling, a figure, not a pass mark (benches measure timing).
    println!(
        "pty at 115200 baud: {} of {cycles} cycles with a late feedback",
        report["feedback_timeouts"]
    );
    let run = read_log(&log).unwrap();
    assert_eq!(run.commands.len() as u64, cycles);
}
