//! Bounded resources for every input (issue 26, item 4): a job's duration, points and plan
//! memory are capped before planning, whatever the job came from (a run settings file, a
//! trajectory CSV, `POST /api/jobs`, a ROS 2 JointTrajectory), and refusals are logged
//! rate-limited, with counts, in a journal that stays under its size cap. The daemon is a
//! child `rigbridge serve` on 127.0.0.1; its memory is read from `/proc/<pid>/status`.

use crate::common;

use common::serve::{request_json, serve_command, start_serve};
use common::{repo_path, scratch_dir, shipped_settings_text};
use rigbridge::daemon::config::load_run_settings;
use rigbridge::job::{JobContext, JobLimits};
use rigbridge::ros2::messages::{Duration as RosDuration, JointTrajectory, JointTrajectoryPoint};
use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::process::Stdio;
use std::time::{Duration, Instant};

/// The audit's message: two points, t = 0 and t = 86,400 s (a day), as rows in degrees.
const DAY_LONG_JOB: &str = r#"{"job": {"kind": "follow_trajectory", "rows": [[0, 0, 0, 0, 0, 30, 0], [86400, 10, 0, 0, 0, 30, 0]]}}"#;

/// The figure: the daemon that refused the day-long trajectory peaked under this (it took
/// 4.07 GB before the caps).
const MAX_DAEMON_PEAK_KB: u64 = 64 * 1024;

/// The journal's cap: four files of 4 MiB (`docs/jobs.md`, "Limits").
const JOURNAL_CAP_BYTES: u64 = 16 * 1024 * 1024;

/// How many refused jobs the flood posts.
const REFUSED_POSTS: u64 = 100_000;

/// A job every cell refuses at validation: no lap.
const BAD_JOB: &str = r#"{"job": {"kind": "wall_figure", "wall_x_m": 0.45, "centre_yz_m": [0.0, 0.45], "radius_m": 0.12, "laps": 0}}"#;

/// `VmHWM` (peak resident memory, kB) of process `pid`.
fn peak_kb(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    status
        .lines()
        .find_map(|line| line.strip_prefix("VmHWM:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .expect("VmHWM in /proc/<pid>/status")
}

fn contains_all(text: &str, parts: &[&str]) {
    for part in parts {
        assert!(text.contains(part), "`{part}` missing from: {text}");
    }
}

#[test]
fn a_day_long_trajectory_over_http_is_refused_before_planning_and_the_daemon_stays_small() {
    let runs = scratch_dir("bounds", "http-day");
    let served = start_serve(serve_command(&runs).stderr(Stdio::null()));
    let started = Instant::now();
    let (status, body) = request_json(&served.address, "POST", "/api/jobs", "", DAY_LONG_JOB);
    let answered = started.elapsed();
    assert_eq!(status, 422, "{body}");
    let error = body["error"].as_str().unwrap_or_default();
    contains_all(
        error,
        &["job.rows[1]", "86400 s", "7200 s", "max_job_duration_s"],
    );
    let peak = peak_kb(served.child.id());
    println!(
        "day-long trajectory over HTTP: refused in {:.1} ms, daemon peak {:.1} MB",
        answered.as_secs_f64() * 1e3,
        peak as f64 / 1024.0
    );
    assert!(peak < MAX_DAEMON_PEAK_KB, "daemon peaked at {peak} kB");
    // Refused before planning: no job was started, so no job's log exists.
    let (_, state) = request_json(&served.address, "GET", "/api/status", "", "");
    assert_eq!(state["state"], "idle", "{state}");
    assert!(state["last"].is_null(), "no job ran: {state}");
}

/// `dir/job.toml`: the shipped settings with `job` as its `[job]` and `limits` appended.
fn write_config(dir: &std::path::Path, job: &str, limits: &str) -> std::path::PathBuf {
    let text = shipped_settings_text();
    let (head, _) = text
        .split_once("[job]")
        .expect("the shipped settings have a [job]");
    let file = dir.join("job.toml");
    std::fs::write(&file, format!("{head}[job]\n{job}\n{limits}")).unwrap();
    file
}

#[test]
fn a_day_long_trajectory_file_is_refused_by_the_config_loader_naming_the_cap() {
    let dir = scratch_dir("bounds", "file-day");
    let csv = "t,j1,j2,j3,j4,j5,j6\n0,0,0,0,0,30,0\n86400,10,0,0,0,30,0\n";
    std::fs::write(dir.join("day.csv"), csv).unwrap();
    let job = "kind = \"follow_trajectory\"\nfile = \"day.csv\"";
    let refused = load_run_settings(&write_config(&dir, job, ""))
        .unwrap_err()
        .to_string();
    contains_all(
        &refused,
        &[
            "job.toml",
            "job.file",
            "86400 s",
            "7200 s",
            "max_job_duration_s",
        ],
    );
    // A day allowed, its plan fits: a curve through the two rows, sampled on demand, stores
    // the rows, not 21.6 M samples (tests/long_plan.rs runs it).
    let wider = "[limits]\nmax_job_duration_s = 86400.0\n";
    load_run_settings(&write_config(&dir, job, wider)).expect("a day allowed loads");
    // An hour fits the defaults.
    std::fs::write(
        dir.join("day.csv"),
        "t,j1,j2,j3,j4,j5,j6\n0,0,0,0,0,30,0\n3600,10,0,0,0,30,0\n",
    )
    .unwrap();
    load_run_settings(&write_config(&dir, job, "")).expect("an hour-long trajectory loads");
    let narrow = "[limits]\nmax_job_points = 1\n";
    let refused = load_run_settings(&write_config(&dir, job, narrow))
        .unwrap_err()
        .to_string();
    contains_all(
        &refused,
        &["limits.max_job_points", "must lie in [2, 10000000]"],
    );
}

/// A ROS 2 JointTrajectory over the IRB 120's joints: `points` as (seconds, joint_1 in rad).
fn joint_trajectory(points: &[(i32, f64)]) -> JointTrajectory {
    let names = (1..=6).map(|i| format!("joint_{i}")).collect();
    JointTrajectory {
        joint_names: names,
        points: points
            .iter()
            .map(|&(sec, q1)| JointTrajectoryPoint {
                positions: vec![q1, 0.0, 0.0, 0.0, 30f64.to_radians(), 0.0],
                time_from_start: RosDuration { sec, nanosec: 0 },
                ..Default::default()
            })
            .collect(),
        ..Default::default()
    }
}

#[test]
fn a_ros2_trajectory_goes_through_the_same_caps_as_a_job_from_http_or_a_file() {
    let settings = load_run_settings(&repo_path("config/rigbridge.toml")).unwrap();
    let dir = repo_path("config");
    let context = JobContext {
        rig: &settings.rig,
        cell: &settings.cell,
        app_rig: None,
        base_dir: &dir,
        limits: &settings.config.limits,
        period: settings.period(),
    };
    let day = joint_trajectory(&[(0, 0.0), (86_400, 0.1)]);
    let job = rigbridge::server::ros2::trajectory_job(&day, &settings.rig).unwrap();
    let refused = job.validate(&context).unwrap_err().to_string();
    contains_all(
        &refused,
        &["job.rows[1]", "86400 s", "7200 s", "max_job_duration_s"],
    );
    // The points' cap, lowered: three points refused, naming the cap.
    let few = JobLimits {
        max_job_points: 2,
        ..JobLimits::default()
    };
    let three = joint_trajectory(&[(0, 0.0), (1, 0.1), (2, 0.2)]);
    let job = rigbridge::server::ros2::trajectory_job(&three, &settings.rig).unwrap();
    let refused = job
        .validate(&JobContext {
            limits: &few,
            ..context
        })
        .unwrap_err()
        .to_string();
    contains_all(&refused, &["cap of 2 rows", "max_job_points"]);
}

/// One request on a kept-alive connection: its status code (the body is read and dropped).
fn post_kept_alive(stream: &mut BufReader<TcpStream>, address: &str, body: &str) -> u16 {
    // One write: a request split over several segments waits out the peer's delayed ACK.
    let request = format!(
        "POST /api/jobs HTTP/1.1\r\nHost: {address}\r\nContent-Type: application/json\r\nContent-Length: {}\r\n\r\n{body}",
        body.len()
    );
    stream.get_mut().write_all(request.as_bytes()).unwrap();
    let mut line = String::new();
    stream.read_line(&mut line).unwrap();
    let status = line.get(9..12).and_then(|s| s.parse().ok()).unwrap_or(0);
    let mut length = 0;
    loop {
        line.clear();
        stream.read_line(&mut line).unwrap();
        if line == "\r\n" || line.is_empty() {
            break;
        }
        if let Some((name, value)) = line.split_once(':')
            && name.eq_ignore_ascii_case("content-length")
        {
            length = value.trim().parse().unwrap();
        }
    }
    let mut skipped = vec![0; length];
    stream.read_exact(&mut skipped).unwrap();
    status
}

/// The refusals one journal event tells: a summary ("refused 4312 more in ...") its count,
/// a refusal logged in full one.
fn counted(result: &str) -> u64 {
    result
        .strip_prefix("refused ")
        .and_then(|rest| rest.split(' ').next())
        .and_then(|n| n.parse().ok())
        .unwrap_or(1)
}

#[test]
fn a_hundred_thousand_refused_jobs_leave_the_journal_under_its_cap_and_are_counted() {
    let runs = scratch_dir("bounds", "refusals");
    let mut command = serve_command(&runs);
    let mut served = start_serve(command.stderr(Stdio::piped()));
    let stderr = served.child.stderr.take().unwrap();
    let logged = std::thread::spawn(move || {
        let mut text = String::new();
        let _ = BufReader::new(stderr).read_to_string(&mut text);
        text
    });
    let started = Instant::now();
    let mut stream = BufReader::new(TcpStream::connect(&served.address).unwrap());
    let socket = stream.get_ref();
    socket
        .set_read_timeout(Some(Duration::from_secs(30)))
        .unwrap();
    socket.set_nodelay(true).unwrap();
    for _ in 0..REFUSED_POSTS {
        assert_eq!(post_kept_alive(&mut stream, &served.address, BAD_JOB), 422);
    }
    let flood = started.elapsed();
    drop(stream);
    let peak = peak_kb(served.child.id());
    // SAFETY: kill only sends SIGTERM to our own child; it then closes its journal.
    unsafe { libc::kill(served.child.id() as i32, libc::SIGTERM) };
    let _ = served.child.wait();
    let stderr = logged.join().unwrap();
    let journals: Vec<_> = std::fs::read_dir(&runs)
        .unwrap()
        .filter_map(Result::ok)
        .filter(|e| e.file_name().to_string_lossy().starts_with("cell-irb120-"))
        .map(|e| e.path())
        .collect();
    let bytes: u64 = journals
        .iter()
        .map(|p| std::fs::metadata(p).unwrap().len())
        .sum();
    let mut refusals = 0;
    let mut events = 0;
    for journal in &journals {
        let log = rigbridge::log::read_log(journal).expect("the journal reads back");
        for event in log.events.iter().filter(|e| e.kind == "job_refused") {
            events += 1;
            let result = event.detail["result"].as_str().unwrap_or_default();
            refusals += counted(result);
        }
    }
    let lines = stderr.lines().filter(|l| l.contains("job_refused")).count();
    println!(
        "{REFUSED_POSTS} refused posts in {:.1} s: journal {} file(s), {bytes} bytes, {events} \
         events counting {refusals}; {lines} stderr lines; daemon peak {:.1} MB",
        flood.as_secs_f64(),
        journals.len(),
        peak as f64 / 1024.0
    );
    assert!(bytes < JOURNAL_CAP_BYTES, "journal {bytes} bytes");
    assert_eq!(refusals, REFUSED_POSTS, "every refusal counted once");
    // One full line and one summary a 10 s window, and the last summary at the stop.
    let windows = (flood.as_secs_f64() / 10.0).ceil() as usize + 1;
    assert!(
        events <= 2 * windows,
        "{events} events for {windows} windows"
    );
    assert!(
        lines <= 2 * windows,
        "{lines} stderr lines for {windows} windows"
    );
}
