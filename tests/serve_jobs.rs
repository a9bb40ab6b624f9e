//! Jobs through `rigbridge serve` beyond the in-process twin: a cell whose `[stream] link`
//! is a twin in its own process over TCP (the job completes there, the report and
//! `/api/cells` name that link), job numbers and logs that survive a restart on the same
//! runs directory, control actions (pause, resume, stop, e-stop, reset) read back as events
//! from the job's MCAP log and the cell's journal (with rigbridge's reader and PyPI's
//! `mcap`), and a panicking job that takes down neither the daemon nor another cell.
//! Traffic only ever goes to 127.0.0.1.

use crate::common;
use crate::flood;
use crate::in_process;

use common::cli::assert_succeeded;
use common::repo_path;
use common::serve::write_pan_tilt_rig;
use flood::http;
use rigbridge::log::read_log;
use std::io::{BufRead, BufReader, Read};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

const ANSWERED_WITHIN: Duration = Duration::from_secs(30);
const JSON: &str = "Content-Type: application/json\r\n";
/// A short job: one joint move and stay.
const MOVE_TO_10: &str =
    r#"{"job": {"kind": "move_joints", "targets_deg": [[10.0, 0.0, 0.0, 0.0, 30.0, 0.0]]}}"#;
const MOVE_HOME: &str =
    r#"{"job": {"kind": "move_joints", "targets_deg": [[0.0, 0.0, 0.0, 0.0, 30.0, 0.0]]}}"#;

struct Process {
    child: Child,
    /// Its first line on stdout: where to connect.
    first_line: String,
}

impl Drop for Process {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Process {
    /// Sends SIGTERM and waits for the process to end; its stderr.
    fn terminate(mut self) -> String {
        // SAFETY: kill only sends a signal to our own child.
        unsafe { libc::kill(self.child.id() as i32, libc::SIGTERM) };
        let _ = self.child.wait();
        let mut stderr = String::new();
        if let Some(mut pipe) = self.child.stderr.take() {
            let _ = pipe.read_to_string(&mut stderr);
        }
        stderr
    }
}

fn spawn(args: &[&str]) -> Process {
    let mut child = Command::new(env!("CARGO_BIN_EXE_rigbridge"))
        .args(args)
        .current_dir(repo_path(""))
        .env_remove("RIGBRIDGE_TOKEN")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut stdout = BufReader::new(child.stdout.take().unwrap());
    let mut first_line = String::new();
    stdout.read_line(&mut first_line).unwrap();
    // Keep reading, so the process never blocks on a full pipe.
    std::thread::spawn(move || for _ in stdout.lines().map_while(Result::ok) {});
    Process {
        child,
        first_line: first_line.trim().to_string(),
    }
}

fn scratch(name: &str) -> PathBuf {
    common::scratch_dir("jobs", name)
}

/// The shipped arm cell, copied to `dir`, streaming over `link`.
fn arm_cell(dir: &Path, link: &str) -> PathBuf {
    std::fs::copy(repo_path("config/irb120.toml"), dir.join("irb120.toml")).unwrap();
    let shipped = common::with_absolute_cell(
        &std::fs::read_to_string(repo_path("config/rigbridge.toml")).unwrap(),
    );
    assert!(shipped.contains("link = \"loopback\""));
    let settings = shipped.replace("link = \"loopback\"", &format!("link = \"{link}\""));
    let file = dir.join("rigbridge.toml");
    std::fs::write(&file, settings).unwrap();
    file
}

fn serve(config: &Path, runs: &Path) -> (Process, SocketAddr) {
    let process = spawn(&[
        "serve",
        "--port",
        "0",
        "--foxglove-port",
        "0",
        "--config",
        config.to_str().unwrap(),
        "--runs-dir",
        runs.to_str().unwrap(),
    ]);
    let address = process
        .first_line
        .trim_start_matches("http://")
        .trim_end_matches('/')
        .parse()
        .unwrap_or_else(|e| panic!("not an address: {:?}: {e}", process.first_line));
    (process, address)
}

fn call(address: SocketAddr, method: &str, path: &str, body: &str) -> (u16, serde_json::Value) {
    let headers = if method == "POST" { JSON } else { "" };
    let (answer, _) = http(address, method, path, headers, body, ANSWERED_WITHIN);
    let (code, body) = answer.unwrap_or_else(|| panic!("{method} {path}: no answer"));
    (
        code,
        serde_json::from_str(&body).unwrap_or(serde_json::Value::Null),
    )
}

fn wait_for(
    address: SocketAddr,
    path: &str,
    what: &str,
    done: impl Fn(&serde_json::Value) -> bool,
) -> serde_json::Value {
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let (_, status) = call(address, "GET", path, "");
        if done(&status) {
            return status;
        }
        assert!(
            Instant::now() < deadline,
            "timed out waiting for {what}: {status}"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// Submits `body`, waits for the job to end; its id and the cell's status then.
fn run_job(address: SocketAddr, cell: &str, body: &str) -> (u64, serde_json::Value) {
    let (code, started) = call(address, "POST", &format!("/api/cells/{cell}/jobs"), body);
    assert_eq!(code, 202, "{started}");
    let id = started["id"].as_u64().unwrap();
    let status = wait_for(
        address,
        &format!("/api/cells/{cell}/status"),
        "the job to end",
        |s| s["state"] == "idle" && s["last"]["id"] == id,
    );
    (id, status)
}

// ------------------------------------------------------------------ TCP twin --

#[test]
fn a_job_over_serve_to_a_tcp_twin_reports_that_link_and_numbers_survive_a_restart() {
    let twin = spawn(&["twin", "--listen", "tcp://127.0.0.1:0"]);
    let link = twin.first_line.clone();
    assert!(link.starts_with("tcp://127.0.0.1:"), "{link}");
    let dir = scratch("tcp");
    let (config, runs) = (arm_cell(&dir, &link), dir.join("runs"));
    let (server, address) = serve(&config, &runs);

    let (_, cells) = call(address, "GET", "/api/cells", "");
    assert_eq!(cells["cells"][0]["link"], link.as_str(), "{cells}");
    let (first, status) = run_job(address, "irb120", MOVE_TO_10);
    let report = &status["last"]["report"];
    assert_eq!(status["last"]["result"], "finished", "{status}");
    assert_eq!(report["outcome"], "completed", "{status}");
    let described = report["link"].as_str().unwrap();
    assert!(
        described.contains(link.trim_start_matches("tcp://")),
        "the report names {described}, not {link}"
    );
    let cycles = report["cycles"].as_u64().unwrap();
    // The twin moved: the next job starts from where the first one left the remote arm.
    let (second, _) = run_job(address, "irb120", MOVE_HOME);
    let start = start_of(&runs.join(format!("job-{second}.mcap")));
    let expected = [10.0f64, 0.0, 0.0, 0.0, 30.0, 0.0].map(f64::to_radians);
    for (got, want) in start.iter().zip(expected) {
        assert!((got - want).abs() < 1e-3, "started at {start:?}");
    }

    // A restart on the same runs directory: numbering continues, nothing is overwritten.
    let before = log_sizes(&runs);
    assert_eq!(before.len(), 2, "{before:?}");
    server.terminate();
    let (server, address) = serve(&config, &runs);
    let (third, status) = run_job(address, "irb120", MOVE_TO_10);
    assert_eq!(status["last"]["report"]["outcome"], "completed", "{status}");
    assert!(third > second && second > first, "{first} {second} {third}");
    let after = log_sizes(&runs);
    for (name, size) in &before {
        assert_eq!(after.get(name), Some(size), "{name} changed");
    }
    assert_eq!(after.len(), 3, "{after:?}");
    server.terminate();

    // The twin received every target the first job streamed (and the others').
    let summary = twin.terminate();
    let frames: u64 = summary
        .split("cycles: ")
        .nth(1)
        .and_then(|rest| rest.split(' ').next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("no frame count in the twin's summary: {summary}"));
    assert!(
        frames >= cycles,
        "the twin got {frames} frames for {cycles} cycles"
    );
}

fn start_of(log: &Path) -> Vec<f64> {
    let run = read_log(log).unwrap();
    run.metadata["start"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect()
}

fn log_sizes(runs: &Path) -> std::collections::BTreeMap<String, u64> {
    std::fs::read_dir(runs)
        .unwrap()
        .filter_map(|e| {
            let e = e.ok()?;
            let name = e.file_name().into_string().ok()?;
            name.starts_with("job-")
                .then(|| (name, e.metadata().unwrap().len()))
        })
        .collect()
}

// ------------------------------------------------------------------- events --

/// An action as the client saw it: when it was sent and answered (Unix seconds).
#[derive(Clone, Copy)]
struct Sent {
    action: &'static str,
    from_s: f64,
    to_s: f64,
}

fn unix_now() -> f64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_secs_f64()
}

fn act(address: SocketAddr, action: &'static str, code: u16) -> Sent {
    let from_s = unix_now();
    let (got, body) = call(address, "POST", &format!("/api/{action}"), "");
    assert_eq!(got, code, "{action}: {body}");
    Sent {
        action,
        from_s,
        to_s: unix_now(),
    }
}

/// Events of `log` by rigbridge's reader: (t, kind, detail).
fn events(log: &Path) -> Vec<(f64, String, serde_json::Value)> {
    read_log(log)
        .unwrap()
        .events
        .into_iter()
        .map(|e| (e.t, e.kind, e.detail))
        .collect()
}

/// Each action found once in `events`, in order, with its Unix time inside the request
/// and its log time non-decreasing; the log times.
fn find_actions(events: &[(f64, String, serde_json::Value)], sent: &[Sent]) -> Vec<f64> {
    let mut times = Vec::new();
    let mut rest = events.iter();
    for action in sent {
        let (t, _, detail) = rest
            .find(|(_, kind, _)| kind == action.action)
            .unwrap_or_else(|| panic!("no {} after the earlier ones in {events:?}", action.action));
        let unix_s = detail["unix_s"].as_f64().unwrap();
        assert!(
            unix_s >= action.from_s - 1e-3 && unix_s <= action.to_s + 1e-3,
            "{}: logged at {unix_s}, sent {} .. {}",
            action.action,
            action.from_s,
            action.to_s
        );
        assert!(times.last().is_none_or(|last| *t >= *last), "{events:?}");
        times.push(*t);
    }
    times
}

/// The PyPI `mcap` reader's Python (RIGBRIDGE_MCAP_PYTHON, set by scripts/test.sh).
fn mcap_python() -> Result<String, String> {
    common::peer_python("RIGBRIDGE_MCAP_PYTHON", "mcap.reader", "mcap")
}

/// Events of `log` by PyPI's reader: (log time in s, t, kind), checked to agree.
fn events_by_python(python: &str, log: &Path) -> Vec<(f64, String)> {
    let output = Command::new(python)
        .arg(repo_path("tests/peers/mcap_events.py"))
        .arg(log)
        .output()
        .unwrap();
    assert_succeeded(&output);
    String::from_utf8(output.stdout)
        .unwrap()
        .lines()
        .map(|line| {
            let e: serde_json::Value = serde_json::from_str(line).unwrap();
            assert_eq!(e["encoding"], "json");
            let t = e["t"].as_f64().unwrap();
            let log_time_s = e["log_time"].as_u64().unwrap() as f64 * 1e-9;
            assert!((log_time_s - t).abs() < 1e-6, "{line}");
            (t, e["kind"].as_str().unwrap().to_string())
        })
        .collect()
}

/// Both readers find the same events, times included.
fn both_readers_agree(log: &Path, ours: &[(f64, String, serde_json::Value)]) {
    match mcap_python() {
        Ok(python) => {
            let theirs = events_by_python(&python, log);
            let ours: Vec<(f64, String)> = ours.iter().map(|(t, k, _)| (*t, k.clone())).collect();
            assert_eq!(theirs.len(), ours.len(), "{theirs:?} vs {ours:?}");
            for ((t1, k1), (t2, k2)) in theirs.iter().zip(&ours) {
                assert_eq!(k1, k2);
                assert!((t1 - t2).abs() < 1e-9, "{t1} vs {t2}");
            }
        }
        Err(why) => eprintln!("skipping PyPI's mcap reader: {why}"),
    }
}

#[test]
fn control_actions_are_events_of_the_job_log_and_the_cell_journal_with_their_times() {
    let dir = scratch("events");
    let runs = dir.join("runs");
    let (server, address) = serve(&repo_path("config/rigbridge.toml"), &runs);
    // The star demo, long enough to pause, resume and stop along the way.
    let (code, started) = call(address, "POST", "/api/jobs", "");
    assert_eq!(code, 202, "{started}");
    let first = started["id"].as_u64().unwrap();
    let progressed = |fraction: f64| {
        move |s: &serde_json::Value| s["job"]["progress"].as_f64().is_some_and(|p| p > fraction)
    };
    wait_for(address, "/api/status", "the job to move", progressed(0.05));
    let mut sent = vec![act(address, "pause", 200)];
    wait_for(address, "/api/status", "the pause", |s| {
        s["state"] == "paused"
    });
    sent.push(act(address, "resume", 200));
    wait_for(address, "/api/status", "more progress", progressed(0.2));
    sent.push(act(address, "estop", 200));
    wait_for(address, "/api/status", "the e-stop", |s| {
        s["state"] == "idle"
    });
    sent.push(act(address, "reset", 200));
    let (code, started) = call(address, "POST", "/api/jobs", "");
    assert_eq!(code, 202, "{started}");
    let second = started["id"].as_u64().unwrap();
    wait_for(address, "/api/status", "the second job", progressed(0.05));
    let stop = act(address, "stop", 200);
    wait_for(address, "/api/status", "the stop", |s| s["state"] == "idle");
    server.terminate();

    // The job's log: its actions between job_started and job_ended, at its own times.
    let job_actions = [sent[0], sent[1], sent[2]];
    let log = runs.join(format!("job-{first}.mcap"));
    let logged = events(&log);
    let times = find_actions(&logged, &job_actions);
    let ended = logged.iter().find(|(_, k, _)| k == "job_ended").unwrap().0;
    assert!(
        times[0] > 0.0 && *times.last().unwrap() <= ended,
        "{logged:?}"
    );
    for (_, kind, detail) in &logged {
        if ["pause", "resume", "estop"].contains(&kind.as_str()) {
            assert_eq!(detail["job"], first, "{detail}");
        }
    }
    both_readers_agree(&log, &logged);
    let log = runs.join(format!("job-{second}.mcap"));
    let logged = events(&log);
    find_actions(&logged, std::slice::from_ref(&stop));
    both_readers_agree(&log, &logged);

    // The cell's journal: all five, the reset (no job) included.
    let journal = std::fs::read_dir(&runs)
        .unwrap()
        .filter_map(|e| e.ok().map(|e| e.path()))
        .find(|p| {
            p.file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.starts_with("cell-irb120-"))
        })
        .expect("the cell's journal");
    let logged = events(&journal);
    sent.push(stop);
    find_actions(&logged, &sent);
    let reset_event = logged.iter().find(|(_, k, _)| k == "reset").unwrap();
    assert!(reset_event.2["job"].is_null(), "{reset_event:?}");
    assert!(reset_event.2["result"].is_string(), "{reset_event:?}");
    both_readers_agree(&journal, &logged);
}

// -------------------------------------------------------------------- panics --

/// A slow three-axis rig named `pan_tilt` in `dir`, whose default job lasts seconds.
fn pan_tilt_cell(dir: &Path) -> PathBuf {
    write_pan_tilt_rig(dir, "pan_tilt");
    let settings = "rig = \"pan_tilt.toml\"\n\n[twin]\ninitial_deg = [0.0, 0.0, 0.0]\n\n\
         [job]\nkind = \"joint_waypoints\"\n\
         waypoints_deg = [[50.0, 20.0, -20.0], [-50.0, -20.0, 20.0], [0.0, 0.0, 0.0]]\n";
    let file = dir.join("pan_tilt_cell.toml");
    std::fs::write(&file, settings).unwrap();
    file
}

#[test]
fn a_panicking_job_fails_alone_while_the_daemon_and_the_other_cell_go_on() {
    use rigbridge::daemon::config::load_run_settings;
    use rigbridge::server::ServeOptions;
    use std::sync::Arc;
    use std::sync::atomic::{AtomicBool, Ordering};

    let dir = scratch("panic");
    let cells = vec![
        load_run_settings(&repo_path("config/rigbridge.toml")).unwrap(),
        load_run_settings(&pan_tilt_cell(&dir)).unwrap(),
    ];
    // The arm's first job panics on its own thread, as a bug in a job would.
    let armed = Arc::new(AtomicBool::new(true));
    let trigger = armed.clone();
    let options = ServeOptions {
        before_job: Some(Arc::new(move |cell: &str, id: u64| {
            if cell == "irb120" && trigger.swap(false, Ordering::SeqCst) {
                panic!("injected panic in job {id}");
            }
        })),
        ..in_process::options(dir.join("runs"))
    };
    let served = in_process::start(cells, options);
    let address = served.address;

    let (code, other) = call(address, "POST", "/api/cells/pan_tilt/jobs", "");
    assert_eq!(code, 202, "{other}");
    let other = other["id"].as_u64().unwrap();
    let (code, refused) = call(address, "POST", "/api/cells/irb120/jobs", MOVE_TO_10);
    assert_eq!(code, 500, "{refused}");
    assert!(!armed.load(Ordering::SeqCst), "the hook ran");
    let arm = wait_for(address, "/api/cells/irb120/status", "the failure", |s| {
        s["last"]["result"] == "failed"
    });
    assert!(
        arm["last"]["error"]
            .as_str()
            .unwrap()
            .contains("injected panic"),
        "{arm}"
    );
    // The other cell's job streams on, and ends as planned.
    let (_, pan_tilt) = call(address, "GET", "/api/cells/pan_tilt/status", "");
    assert_eq!(pan_tilt["state"], "running", "{pan_tilt}");
    // The arm's cell takes its next job and completes it, meanwhile.
    let (_, arm) = run_job(address, "irb120", MOVE_TO_10);
    assert_eq!(arm["last"]["report"]["outcome"], "completed", "{arm}");
    let pan_tilt = wait_for(address, "/api/cells/pan_tilt/status", "its end", |s| {
        s["state"] == "idle"
    });
    assert_eq!(pan_tilt["last"]["id"], other);
    assert_eq!(
        pan_tilt["last"]["report"]["outcome"], "completed",
        "{pan_tilt}"
    );
    let result = served.stop().expect("the server task did not panic");
    assert!(result.is_ok(), "the daemon stopped cleanly");
}
