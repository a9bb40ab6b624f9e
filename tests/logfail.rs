//! A run log that cannot be written (issue 26, item 5): the disk under the log fills while
//! the job streams. `rigbridge run` streams through a loopback proxy (`common/proxy.rs`) to
//! `rigbridge twin`, so what was sent is counted on the twin's side of the wire, apart from
//! the bridge's own report; the bridge's stderr is read as it comes, so the first failed
//! write is timed when the bridge says it. With `[log] on_error = "stop"` (the default) the
//! job is at rest within 1 s and its report says `stopped` beside the log's error, with
//! the true cycle count; with `"continue"` it completes and says so. A report written to a
//! full disk leaves the previous report whole and an error. `serve` keeps the job's report.
//!
//! A full disk: a tmpfs of a few hundred KiB mounted in a scratch directory (root, as in
//! CI); where mounting is not allowed, the child's file size limit (RLIMIT_FSIZE, SIGXFSZ
//! ignored) makes every write past that size fail the same way (EFBIG for ENOSPC).

use crate::common;
use crate::proxy;

use common::cli::read_json;
use common::{scratch_dir, scratch_file, shipped_settings_text, wait_until};
use proxy::{Entry, FaultProxy};
use rigbridge::protocol::{Command, Message};
use std::io::{BufRead, BufReader};
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Command as Process, Stdio};
use std::sync::Arc;
use std::sync::atomic::AtomicU64;
use std::time::Duration;

/// What the log's disk holds: the log's header and a few seconds of a job (about 1.5 s of
/// the star at 250 Hz, measured), so the disk fills while the arm moves.
const DISK_BYTES: u64 = 192 * 1024;
/// The figure: at rest within 1 s of the first failed write.
const AT_REST_WITHIN: Duration = Duration::from_secs(1);
/// Bounds on waits that only catch a hang: a run of the test's star takes under 30 s.
const RUN_TIMEOUT: Duration = Duration::from_secs(120);
/// This file's scratch files' prefix.
const SUITE: &str = "logfail";
/// What the bridge says on stderr when a log write fails (src/log/recorder.rs).
const FAILED_LINE: &str = "log failed at job time";

/// A directory on a disk that is full after [`DISK_BYTES`]: a tmpfs of that size, or,
/// where mounting is not allowed, the limit set on the child's file size.
struct FullDisk {
    dir: PathBuf,
    mounted: bool,
}

impl FullDisk {
    fn new(name: &str) -> FullDisk {
        let dir = scratch_dir(SUITE, name);
        let mounted = mount_tmpfs(&dir, DISK_BYTES);
        if !mounted {
            println!(
                "note: cannot mount a tmpfs here ({}); the disk is full by RLIMIT_FSIZE = {DISK_BYTES} bytes instead",
                std::io::Error::last_os_error()
            );
        }
        FullDisk { dir, mounted }
    }

    /// `command` as a child that meets the full disk: with no tmpfs, its files stop
    /// growing at [`DISK_BYTES`].
    fn limit(&self, command: &mut Process) {
        if self.mounted {
            return;
        }
        // SAFETY: between fork and exec only async-signal-safe calls (setrlimit, signal).
        unsafe {
            command.pre_exec(|| {
                let limit = libc::rlimit {
                    rlim_cur: DISK_BYTES,
                    rlim_max: DISK_BYTES,
                };
                if libc::setrlimit(libc::RLIMIT_FSIZE, &limit) != 0 {
                    return Err(std::io::Error::last_os_error());
                }
                // A write past the limit then fails with EFBIG instead of killing.
                libc::signal(libc::SIGXFSZ, libc::SIG_IGN);
                Ok(())
            });
        }
    }
}

impl Drop for FullDisk {
    fn drop(&mut self) {
        if self.mounted {
            let dir = std::ffi::CString::new(self.dir.to_str().unwrap()).unwrap();
            // SAFETY: unmounts the tmpfs this test mounted; a path from a CString.
            unsafe { libc::umount2(dir.as_ptr(), libc::MNT_DETACH) };
        }
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

/// Mounts a tmpfs of `bytes` on `dir`; false where that is not allowed (not root).
fn mount_tmpfs(dir: &Path, bytes: u64) -> bool {
    let c = |text: &str| std::ffi::CString::new(text).unwrap();
    let (source, target, kind) = (c("tmpfs"), c(dir.to_str().unwrap()), c("tmpfs"));
    let options = c(&format!("size={bytes}"));
    // SAFETY: mount(2) with NUL-terminated strings that outlive the call.
    unsafe {
        libc::mount(
            source.as_ptr(),
            target.as_ptr(),
            kind.as_ptr(),
            0,
            options.as_ptr().cast(),
        ) == 0
    }
}

/// The shipped run settings with a star of `laps` laps, `[plan] accel_scale` and `[log]`
/// as given, written to `name` in the scratch directory.
fn settings(name: &str, laps: u32, accel_scale: f64, log: &str) -> PathBuf {
    let text = shipped_settings_text()
        .replacen("laps = 2", &format!("laps = {laps}"), 1)
        .replacen(
            "accel_scale = 0.8",
            &format!("accel_scale = {accel_scale}"),
            1,
        );
    assert!(
        text.contains(&format!("laps = {laps}")),
        "the star's laps are set"
    );
    let path = scratch_file(SUITE, name);
    std::fs::write(&path, format!("{text}\n[log]\n{log}\n")).unwrap();
    path
}

/// A line of the bridge's stderr, with when it reached the test on the proxy's clock.
type TimedLine = (Duration, String);

/// Reads `stderr`'s lines, each timed by `proxy`'s clock as it arrives, until it closes.
fn timed_lines(
    stderr: impl std::io::Read + Send + 'static,
    proxy: &FaultProxy,
) -> std::thread::JoinHandle<Vec<TimedLine>> {
    let epoch = std::time::Instant::now() - proxy.now();
    std::thread::spawn(move || {
        BufReader::new(stderr)
            .lines()
            .map_while(Result::ok)
            .map(|line| (epoch.elapsed(), line))
            .collect()
    })
}

/// What the wire showed of a run: targets the bridge sent, and when the last one that moved
/// the arm (differed from the one before) reached the twin's side.
struct Wire {
    targets: usize,
    last_motion: Option<Duration>,
}

fn wire_of(entries: &[Entry]) -> Wire {
    let mut previous: Option<Vec<f64>> = None;
    let (mut targets, mut last_motion) = (0, None);
    for entry in entries.iter().filter(|e| e.up) {
        if let Some(Message::Command(Command::Target(target))) = &entry.message {
            targets += 1;
            let positions = target.positions.as_slice().to_vec();
            if previous.as_ref().is_some_and(|p| *p != positions) {
                last_motion = Some(entry.at);
            }
            previous = Some(positions);
        }
    }
    Wire {
        targets,
        last_motion,
    }
}

/// One `rigbridge run` of `config` through a proxy to a twin process, its log on `disk`:
/// its exit code, report, timed stderr and what the wire showed.
struct Run {
    code: Option<i32>,
    report: serde_json::Value,
    stderr: Vec<TimedLine>,
    wire: Wire,
}

fn run_through_proxy(config: &Path, disk: &FullDisk, name: &str) -> Run {
    let mut twin_command = common::twin::listen_command("tcp://127.0.0.1:0");
    twin_command.args(["--config", config.to_str().unwrap()]);
    let twin = common::twin::start_listening(&mut twin_command);
    let proxy = FaultProxy::start(&twin.address, Arc::new(AtomicU64::new(0)), 26);
    let report = scratch_file(SUITE, &format!("{name}.json"));
    let _ = std::fs::remove_file(&report);
    let mut command = common::cli::rigbridge();
    command
        .args(["run", "--config", config.to_str().unwrap()])
        .args(["--link", &proxy.address])
        .arg("--log")
        .arg(disk.dir.join(format!("{name}.mcap")))
        .arg("--report")
        .arg(&report)
        .stdout(Stdio::null())
        .stderr(Stdio::piped());
    disk.limit(&mut command);
    let mut child = command.spawn().unwrap();
    let lines = timed_lines(child.stderr.take().unwrap(), &proxy);
    let status = wait_until("the run to end", RUN_TIMEOUT, || child.try_wait().unwrap());
    let stderr = lines.join().unwrap();
    let (entries, _) = proxy.finish();
    drop(twin);
    Run {
        code: status.code(),
        report: read_json(&report),
        stderr,
        wire: wire_of(&entries),
    }
}

/// When the bridge first said a log write failed.
fn failed_at(run: &Run) -> Duration {
    run.stderr
        .iter()
        .find(|(_, line)| line.contains(FAILED_LINE))
        .map(|(at, _)| *at)
        .unwrap_or_else(|| panic!("the bridge says the log failed: {:?}", run.stderr))
}

#[test]
fn a_full_log_disk_brings_the_job_to_rest_within_a_second_and_the_report_is_true() {
    if !common::in_full_tier(
        "logfail::a_full_log_disk_brings_the_job_to_rest_within_a_second_and_the_report_is_true",
    ) {
        return;
    }
    let disk = FullDisk::new("logfail-stop");
    // The shipped accel_scale: the stop brakes at the axes' acceleration (stream/brake.rs).
    let config = settings("logfail-stop.toml", 20, 0.8, "on_error = \"stop\"");
    let run = run_through_proxy(&config, &disk, "logfail-stop");
    let failed = failed_at(&run);
    let rest = run.wire.last_motion.expect("the arm moved");
    let report = &run.report;
    println!(
        "disk full ({}): first failed write said at {:.3} s, last target that moves at {:.3} s ({:.3} s later); {} targets on the wire, report: {} after {} cycles, log_error {}",
        if disk.mounted {
            "tmpfs"
        } else {
            "RLIMIT_FSIZE"
        },
        failed.as_secs_f64(),
        rest.as_secs_f64(),
        rest.saturating_sub(failed).as_secs_f64(),
        run.wire.targets,
        report["outcome"],
        report["cycles"],
        report["log_error"]
    );
    assert!(
        rest < failed + AT_REST_WITHIN,
        "the arm moved {:.3} s after the first failed write",
        (rest - failed).as_secs_f64()
    );
    assert_eq!(report["outcome"], "stopped", "{report:#}");
    assert_eq!(report["cycles"], run.wire.targets as u64, "{report:#}");
    let log_error = &report["log_error"];
    assert_eq!(log_error["on_error"], "stop", "{report:#}");
    assert_eq!(log_error["stopped_job"], true, "{report:#}");
    let error = log_error["error"].as_str().unwrap();
    assert!(error.contains("logfail-stop.mcap"), "{error}");
    assert_eq!(run.code, Some(5), "a run whose log failed exits 5");
}

#[test]
fn with_on_error_continue_the_job_completes_and_the_report_says_the_log_failed() {
    if !common::in_full_tier(
        "logfail::with_on_error_continue_the_job_completes_and_the_report_says_the_log_failed",
    ) {
        return;
    }
    let disk = FullDisk::new("logfail-continue");
    let config = settings("logfail-continue.toml", 3, 0.8, "on_error = \"continue\"");
    let run = run_through_proxy(&config, &disk, "logfail-continue");
    let failed = failed_at(&run);
    let report = &run.report;
    let rest = run.wire.last_motion.expect("the arm moved");
    println!(
        "on_error = continue: first failed write said at {:.3} s, motion until {:.3} s; {} targets on the wire, report: {} after {} cycles",
        failed.as_secs_f64(),
        rest.as_secs_f64(),
        run.wire.targets,
        report["outcome"],
        report["cycles"]
    );
    assert_eq!(report["outcome"], "completed", "{report:#}");
    assert_eq!(report["cycles"], run.wire.targets as u64, "{report:#}");
    assert!(rest > failed, "the job went on after the log failed");
    assert_eq!(report["log_error"]["on_error"], "continue", "{report:#}");
    assert_eq!(report["log_error"]["stopped_job"], false, "{report:#}");
    assert_eq!(run.code, Some(5), "a run whose log failed exits 5");
}

#[test]
fn a_report_on_a_full_disk_leaves_the_previous_one_and_says_why() {
    if !common::in_full_tier(
        "logfail::a_report_on_a_full_disk_leaves_the_previous_one_and_says_why",
    ) {
        return;
    }
    let disk = FullDisk::new("logfail-report");
    if !disk.mounted {
        println!(
            "note: skipped: without a tmpfs (not root) the report's disk cannot be filled apart from the log's"
        );
        return;
    }
    let report = disk.dir.join("report.json");
    let previous = "{\"outcome\": \"completed\", \"cycles\": 1234}\n";
    std::fs::write(&report, previous).unwrap();
    fill(&disk.dir);
    let log = scratch_file(SUITE, "logfail-report.mcap");
    let _ = std::fs::remove_file(&log);
    let mut command = common::cli::rigbridge();
    command
        .args(["run", "--clock", "virtual"])
        .arg("--log")
        .arg(&log)
        .arg("--report")
        .arg(&report);
    let output = command.output().unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    println!("exit {:?}; stderr: {stderr}", output.status.code());
    assert!(
        !output.status.success(),
        "a report not written fails the run"
    );
    assert_eq!(std::fs::read_to_string(&report).unwrap(), previous);
    assert!(stderr.contains(report.to_str().unwrap()), "{stderr}");
    assert!(stderr.contains("No space left on device"), "{stderr}");
    let left: Vec<_> = std::fs::read_dir(&disk.dir)
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .filter(|n| n.to_string_lossy().ends_with(".tmp"))
        .collect();
    assert!(left.is_empty(), "no temporary file is left: {left:?}");
}

/// Fills the file system of `dir` to its last byte.
fn fill(dir: &Path) {
    use std::io::Write;
    let mut filler = std::fs::File::create(dir.join("filler")).unwrap();
    let block = [0xA5u8; 4096];
    while filler.write_all(&block).is_ok() {}
    while filler.write_all(&block[..1]).is_ok() {}
}

#[test]
fn serve_keeps_the_report_of_a_job_whose_log_failed_and_says_it_while_it_runs() {
    if !common::in_full_tier(
        "logfail::serve_keeps_the_report_of_a_job_whose_log_failed_and_says_it_while_it_runs",
    ) {
        return;
    }
    let disk = FullDisk::new("logfail-serve");
    let config = settings("logfail-serve.toml", 20, 0.7, "");
    let mut command = common::serve::serve_command(&disk.dir);
    command.arg("--config").arg(&config).stderr(Stdio::null());
    disk.limit(&mut command);
    let served = common::serve::start_serve(&mut command);
    let status = || common::serve::request_json(&served.address, "GET", "/api/status", "", "").1;
    let (code, started) = common::serve::request_json(&served.address, "POST", "/api/jobs", "", "");
    assert_eq!(code, 202, "{started}");
    // While the job runs (it is stopping, along its path), its status says the log failed.
    let running = wait_until(
        "the running job's log error in its status",
        RUN_TIMEOUT,
        || {
            let now = status();
            let failed = !now["job"]["log_error"].is_null();
            (failed || now["state"] == "idle").then_some(now)
        },
    );
    let ended = wait_until("the job to end", RUN_TIMEOUT, || {
        let now = status();
        (now["state"] == "idle" && !now["last"].is_null()).then_some(now)
    });
    let last = &ended["last"];
    println!(
        "serve: while running, job.log_error = {}; last: {} {} after {} cycles, log_error {}",
        running["job"]["log_error"],
        last["result"],
        last["report"]["outcome"],
        last["report"]["cycles"],
        last["report"]["log_error"]
    );
    assert!(
        !running["job"]["log_error"].is_null(),
        "said while running: {running:#}"
    );
    assert_eq!(last["result"], "finished", "{ended:#}");
    let report = &last["report"];
    assert_eq!(report["outcome"], "stopped", "{report:#}");
    assert!(report["cycles"].as_u64().unwrap() > 0, "{report:#}");
    assert_eq!(report["log_error"]["stopped_job"], true, "{report:#}");
    assert!(
        report["log_error"]["error"]
            .as_str()
            .unwrap()
            .contains("job-1.mcap"),
        "{report:#}"
    );
    let shown = live_log_error(&served.address);
    println!("live page frame: job.log_error = {shown}");
    assert!(shown.contains("job-1.mcap"), "{shown}");
}

/// The log error the live page is sent in its frames' `job` (`/api/live`).
fn live_log_error(address: &str) -> String {
    let (mut socket, _) = tungstenite::connect(format!("ws://{address}/api/live")).unwrap();
    wait_until("a live frame with the job's log error", RUN_TIMEOUT, || {
        let tungstenite::Message::Text(text) = socket.read().unwrap() else {
            return None;
        };
        let frame: serde_json::Value = serde_json::from_str(&text).ok()?;
        frame["job"]["log_error"].as_str().map(String::from)
    })
}

#[test]
fn on_error_is_checked_when_the_settings_load() {
    if !common::in_full_tier("logfail::on_error_is_checked_when_the_settings_load") {
        return;
    }
    let shipped = common::shipped_run_settings();
    assert_eq!(
        shipped.config.log.on_error,
        rigbridge::daemon::config::OnLogError::Stop,
        "a job stops on a failed log unless told otherwise"
    );
    let good = settings(
        "logfail-continue-load.toml",
        2,
        0.8,
        "on_error = \"continue\"",
    );
    let loaded = rigbridge::daemon::config::load_run_settings(&good).unwrap();
    assert_eq!(
        loaded.config.log.on_error,
        rigbridge::daemon::config::OnLogError::Continue
    );
    let bad = settings("logfail-bad.toml", 2, 0.8, "on_error = \"sometimes\"");
    let error = rigbridge::daemon::config::load_run_settings(&bad)
        .unwrap_err()
        .to_string();
    for part in [
        "logfail-bad.toml",
        "on_error",
        "sometimes",
        "`stop` or `continue`",
    ] {
        assert!(error.contains(part), "{part} in: {error}");
    }
}
