//! A long plan stored compactly (issue 26, item 4): the audit's day-long JointTrajectory,
//! two points at t = 0 and t = 86,400 s, accepted under `[limits] max_job_duration_s =
//! 86400` and streamed by a child `rigbridge serve` on 127.0.0.1 whose peak memory
//! (`VmHWM` in `/proc/<pid>/status`) stays under the figure: the plan stores its two rows,
//! not 21.6 M samples.

use crate::common;

use common::serve::{request_json, serve_command, start_serve};
use common::{scratch_dir, shipped_settings_text, wait_until};
use std::time::{Duration, Instant};

/// The audit's message as an HTTP job: two rows, t = 0 and t = 86,400 s, a 10 degree move
/// of joint 1 (degrees, as a job's rows are written), taken as a ROS 2 trajectory is: from
/// where the rig holds (the shipped twin's `initial_deg`), no approach, so the job lasts
/// the day and no more, at the cap.
const DAY_LONG_JOB: &str = r#"{"job": {"kind": "follow_trajectory", "approach": false, "rows": [[0, 0, 0, 0, 0, 30, 0], [86400, 10, 0, 0, 0, 30, 0]]}}"#;

/// The figure: the daemon running the day-long plan stays under 64 MB (the audit saw
/// 4.07 GB at peak before the caps).
const MAX_DAEMON_PEAK_KB: u64 = 64 * 1024;

/// How long the day-long job streams before its memory is read: past its approach and
/// into the curve.
const STREAM_FOR: Duration = Duration::from_secs(3);

/// How long the test waits for a state: far beyond any, only to fail rather than hang.
const WAIT: Duration = Duration::from_secs(120);

/// `VmHWM` (peak resident memory, kB) of process `pid`.
fn peak_kb(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    status
        .lines()
        .find_map(|line| line.strip_prefix("VmHWM:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .expect("VmHWM in /proc/<pid>/status")
}

/// The daemon's `/api/status` at `address`, once `done` holds of it.
fn wait_for(
    address: &str,
    what: &str,
    done: impl Fn(&serde_json::Value) -> bool,
) -> serde_json::Value {
    wait_until(what, WAIT, || {
        let (_, status) = request_json(address, "GET", "/api/status", "", "");
        done(&status).then_some(status)
    })
}

#[test]
fn a_day_long_two_point_trajectory_runs_with_the_daemon_under_64_mb() {
    if !common::in_full_tier(
        "long_plan::a_day_long_two_point_trajectory_runs_with_the_daemon_under_64_mb",
    ) {
        return;
    }
    if !std::path::Path::new("/proc/self/status").exists() {
        println!("skipping: no /proc/<pid>/status on this machine to read the peak memory from");
        return;
    }
    let dir = scratch_dir("long_plan", "day");
    let config = dir.join("day.toml");
    let limits = "\n[limits]\nmax_job_duration_s = 86400.0\n";
    std::fs::write(&config, format!("{}{limits}", shipped_settings_text())).unwrap();
    let mut command = serve_command(&dir.join("runs"));
    command.arg("--config").arg(&config);
    let served = start_serve(command.stderr(std::process::Stdio::null()));
    let address = served.address.as_str();

    let started = Instant::now();
    let (code, body) = request_json(address, "POST", "/api/jobs", "", DAY_LONG_JOB);
    assert_eq!(code, 202, "{body}");
    let moving = wait_for(address, "the day-long job to stream", |s| {
        s["state"] == "running" && s["job"]["progress"].as_f64().is_some_and(|p| p > 0.0)
    });
    let planned_in = started.elapsed();
    std::thread::sleep(STREAM_FOR);
    let (_, streaming) = request_json(address, "GET", "/api/status", "", "");
    assert_eq!(streaming["state"], "running", "{streaming}");
    let progress = streaming["job"]["progress"].as_f64().unwrap_or_default();
    assert!(
        progress > moving["job"]["progress"].as_f64().unwrap_or_default(),
        "the job streams on: {streaming}"
    );
    let peak = peak_kb(served.child.id());
    println!(
        "day-long trajectory: planned and streaming in {:.1} s, progress {progress:.2e} after \
         {} s more, daemon peak {:.1} MB",
        planned_in.as_secs_f64(),
        STREAM_FOR.as_secs(),
        peak as f64 / 1024.0
    );
    let (code, body) = request_json(address, "POST", "/api/stop", "", "");
    assert_eq!(code, 200, "{body}");
    wait_for(address, "the stop", |s| s["state"] == "idle");
    assert!(
        peak < MAX_DAEMON_PEAK_KB,
        "daemon peaked at {peak} kB, over {MAX_DAEMON_PEAK_KB} kB"
    );
}
