//! Ctrl-C at any moment of a run stops it: `rigbridge run` of the star job on the loopback
//! twin, in real time, gets SIGINT at a random moment of its motion, many times over, and
//! must each time bring the arm to rest along its path, report `stopped` and exit 130.
//!
//! A SIGINT that fell in the same turn of the supervisor's loop as its progress tick was
//! once lost (the job ran on to its end): rare per signal, so the test sends many.

use crate::common;

use common::{repo_path, scratch_file};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// Runs, each stopped once: enough that a loss one signal in a hundred shows often.
const RUNS: u64 = 40;
/// Two runs at once: the machine has two cores.
const LANES: u64 = 2;
/// The signal falls this long after the process starts: the star job plans in well under
/// 0.3 s and streams for about 7 s, so every moment lands in its motion.
const EARLIEST_MS: u64 = 300;
const LATEST_MS: u64 = 2_000;
/// From the signal to the process's exit: the stop ramp of the star job takes well under a
/// second; a lost signal lets the job run its remaining 5 s or more.
const STOP_WITHIN: Duration = Duration::from_secs(4);
/// The exit code of a run an operator stopped (docs/usage.md).
const EXIT_STOPPED: i32 = 130;

/// One run stopped by SIGINT `delay` after its start: how it ended, or what went wrong.
fn stopped_run(index: u64, delay: Duration) -> Result<(), String> {
    let (log, report) = (
        scratch_file("signals", &format!("run-{index}.mcap")),
        scratch_file("signals", &format!("run-{index}.json")),
    );
    let mut child = Command::new(env!("CARGO_BIN_EXE_rigbridge"))
        .args([
            "run",
            "--config",
            "config/rigbridge.toml",
            "--clock",
            "wall",
        ])
        .arg("--log")
        .arg(&log)
        .arg("--report")
        .arg(&report)
        .current_dir(repo_path(""))
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("rigbridge starts");
    std::thread::sleep(delay);
    // SAFETY: kill(2) on our own child's pid; no memory is shared.
    unsafe { libc::kill(child.id() as libc::pid_t, libc::SIGINT) };
    let signalled = Instant::now();
    let status = loop {
        if let Some(status) = child.try_wait().expect("the run is waited on") {
            break status;
        }
        if signalled.elapsed() > STOP_WITHIN {
            let _ = child.kill();
            let _ = child.wait();
            return Err(format!(
                "run {index}: still running {} s after SIGINT at {} ms",
                STOP_WITHIN.as_secs(),
                delay.as_millis()
            ));
        }
        std::thread::sleep(Duration::from_millis(10));
    };
    let text = std::fs::read_to_string(&report).map_err(|e| format!("run {index}: {e}"))?;
    let json: serde_json::Value = serde_json::from_str(&text).expect("the report is JSON");
    let outcome = json["outcome"].as_str().unwrap_or("none").to_string();
    if outcome != "stopped" || status.code() != Some(EXIT_STOPPED) {
        return Err(format!(
            "run {index}: SIGINT at {} ms ended it {outcome}, exit {:?}",
            delay.as_millis(),
            status.code()
        ));
    }
    Ok(())
}

#[test]
fn ctrl_c_at_any_moment_of_a_run_stops_it_and_reports_stopped() {
    if !common::in_full_tier("signals::ctrl_c_at_any_moment_of_a_run_stops_it_and_reports_stopped")
    {
        return;
    }
    let lanes: Vec<_> = (0..LANES)
        .map(|lane| {
            std::thread::spawn(move || {
                let mut rng = ChaCha8Rng::seed_from_u64(0x5161 + lane);
                (0..RUNS / LANES)
                    .map(|turn| {
                        let delay = rng.random_range(EARLIEST_MS..=LATEST_MS);
                        stopped_run(lane * RUNS + turn, Duration::from_millis(delay))
                    })
                    .collect::<Vec<_>>()
            })
        })
        .collect();
    let failures: Vec<String> = lanes
        .into_iter()
        .flat_map(|lane| lane.join().expect("a lane finished"))
        .filter_map(Result::err)
        .collect();
    println!("{RUNS} runs stopped by SIGINT: {} failed", failures.len());
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}
