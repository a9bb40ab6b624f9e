//! `rigbridge serve` while jobs run and after (issue 32): the status of a running job (its
//! own cycles, elapsed and remaining time, the actual and commanded positions), the job
//! history (`GET /api/jobs`, `GET /api/jobs/{id}`, waiting for a job's end with `wait_s`),
//! the 404 of a job the cell does not know, the 405 of a method a route does not take, and
//! a reset without a content type. Traffic only ever goes to 127.0.0.1.

use crate::common;

use common::serve::{Served, request_bare, request_json, serve_command, start_serve};
use std::process::Stdio;
use std::time::{Duration, Instant};

/// The default config's cycle: 250 Hz.
const PERIOD_S: f64 = 0.004;
/// How long a test waits for any one thing before it fails: far beyond a job of these.
const WITHIN: Duration = Duration::from_secs(60);
/// The `wait_s` of each job lookup: below the helper's 30 s read timeout.
const WAIT_S: u32 = 10;
/// Where the default config's twin starts (deg).
const INITIAL_DEG: [f64; 6] = [0.0, 0.0, 0.0, 0.0, 30.0, 0.0];
/// Four small joint moves, each leaning back (joint_2 negative) from the arm's rest: the
/// default cell's wall stands 28 mm in front of the pen at rest. The first is the longest
/// (35 deg of joint_2), each later one shorter than those before it together, so a count of
/// cycles from the daemon's start would exceed what the later jobs streamed.
const CHAIN_DEG: [[f64; 6]; 4] = [
    [-30.0, -35.0, 10.0, 0.0, 40.0, 0.0],
    [-10.0, -25.0, 0.0, 0.0, 30.0, 0.0],
    [10.0, -15.0, 0.0, 20.0, 30.0, 0.0],
    [0.0, -10.0, 0.0, 0.0, 30.0, 0.0],
];
/// How far a commanded value may lie outside its move's target and the one before (deg):
/// a job is planned from where the arm holds, and the job before completed once the arm
/// was within the goal tolerance (0.1 deg) of its target.
const COMMANDED_SLACK_DEG: f64 = 0.1;
/// How far the twin's actual value may lie outside its move's start and end (deg): its
/// 20 Hz servo follows without overshoot, and a job completes once the arm is within the
/// goal tolerance of 0.1 deg, where the next one starts; the rest is margin.
const ACTUAL_SLACK_DEG: f64 = 0.15;

struct Server {
    _daemon: Served,
    address: String,
}

fn start() -> Server {
    static SERVERS: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
    let n = SERVERS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let runs = std::env::temp_dir().join(format!("rigbridge-history-{}-{n}", std::process::id()));
    let _ = std::fs::remove_dir_all(&runs);
    let daemon = start_serve(serve_command(&runs).stderr(Stdio::null()));
    let port = daemon.address.rsplit_once(':').unwrap().1.to_string();
    Server {
        _daemon: daemon,
        address: format!("127.0.0.1:{port}"),
    }
}

fn get(server: &Server, path: &str) -> (u16, serde_json::Value) {
    request_json(&server.address, "GET", path, "", "")
}

fn post(server: &Server, path: &str, body: &str) -> (u16, serde_json::Value) {
    request_json(&server.address, "POST", path, "", body)
}

/// One request with exactly these header lines and no body: the status code and the body.
fn bare(server: &Server, method: &str, path: &str, headers: &str) -> (u16, String) {
    let (code, response) = request_bare(&server.address, method, path, headers, WITHIN);
    let body = response.split("\r\n\r\n").nth(1).unwrap_or("").to_string();
    (code, body)
}

fn move_joints(target: &[f64; 6]) -> String {
    serde_json::json!({ "job": { "kind": "move_joints", "targets_deg": [target] } }).to_string()
}

/// The status of job `id` once it has streamed a cycle, asked back to back (each answer
/// comes at once); fails should the job end unseen.
fn running_status(server: &Server, id: u64) -> serde_json::Value {
    let deadline = Instant::now() + WITHIN;
    loop {
        let (code, status) = get(server, "/api/status");
        assert_eq!(code, 200, "{status}");
        if status["job"]["id"] == id && status["job"]["cycles"].as_u64() > Some(0) {
            return status;
        }
        assert_ne!(status["last"]["id"], id, "job {id} ended unseen: {status}");
        assert!(
            Instant::now() < deadline,
            "job {id} never streamed: {status}"
        );
    }
}

/// Job `id` once it ended, through `GET /api/jobs/{id}?wait_s=`: each lookup waits in
/// the daemon for the job's end, so the test neither sleeps nor polls.
fn ended_job(server: &Server, id: u64) -> serde_json::Value {
    let deadline = Instant::now() + WITHIN;
    let mut lookups = 0;
    loop {
        let (code, job) = get(server, &format!("/api/jobs/{id}?wait_s={WAIT_S}"));
        lookups += 1;
        assert_eq!(code, 200, "{job}");
        assert_eq!(job["id"], id, "{job}");
        assert_eq!(job["name"], "move_joints", "{job}");
        if job["result"] != "running" {
            // A job of a second or so ends within one wait.
            assert_eq!(lookups, 1, "job {id} took {lookups} waits of {WAIT_S} s");
            return job;
        }
        assert!(Instant::now() < deadline, "job {id} never ended: {job}");
    }
}

/// Each axis of `axes` (`joint`, `value`, `unit`) lies between `from` and `to` (deg), within
/// `slack`.
fn between(axes: &serde_json::Value, from: &[f64; 6], to: &[f64; 6], slack: f64, what: &str) {
    let axes = axes.as_array().unwrap_or_else(|| panic!("{what}: {axes}"));
    assert_eq!(axes.len(), 6, "{what}: {axes:?}");
    for (n, axis) in axes.iter().enumerate() {
        assert_eq!(axis["joint"], format!("joint_{}", n + 1), "{what}: {axis}");
        assert_eq!(axis["unit"], "deg", "{what}: {axis}");
        let value = axis["value"].as_f64().unwrap();
        let (low, high) = (from[n].min(to[n]) - slack, from[n].max(to[n]) + slack);
        assert!(
            (low..=high).contains(&value),
            "{what}: joint_{} at {value} deg, outside {low}..{high}",
            n + 1
        );
    }
}

/// Job `id`'s status while it ran, against its report: its own cycles (never more than
/// the report's), elapsed and remaining time, and positions on its move.
fn check_running(running: &serde_json::Value, report: &serde_json::Value, moved: [&[f64; 6]; 2]) {
    let job = &running["job"];
    assert_eq!(running["state"], "running", "{running}");
    let cycles = job["cycles"].as_u64().unwrap();
    let streamed = report["cycles"].as_u64().unwrap();
    assert!(
        cycles <= streamed,
        "the status counted {cycles} cycles of a job that streamed {streamed}: {running}"
    );
    let elapsed = job["elapsed_s"].as_f64().unwrap();
    assert!(
        (elapsed - cycles as f64 * PERIOD_S).abs() < 1e-9,
        "{elapsed} s for {cycles} cycles"
    );
    let planned = report["planned_duration_s"].as_f64().unwrap();
    let progress = job["progress"].as_f64().unwrap();
    let remaining = job["remaining_s"].as_f64().unwrap();
    assert!(
        (remaining - planned * (1.0 - progress)).abs() < 1e-9,
        "{remaining} s left of {planned} s at {progress}"
    );
    let [from, to] = moved;
    between(
        &running["commanded"],
        from,
        to,
        COMMANDED_SLACK_DEG,
        "commanded",
    );
    between(&running["actual"], from, to, ACTUAL_SLACK_DEG, "actual");
}

#[test]
fn four_chained_jobs_show_their_own_cycles_and_positions_and_are_listed_newest_first() {
    let server = start();
    let mut from = INITIAL_DEG;
    let mut ids = Vec::new();
    for (n, target) in CHAIN_DEG.iter().enumerate() {
        // Each POST follows the previous job's end at once: a 409 here would mean the
        // lookup answered "finished" before the cell was free.
        let (code, accepted) = post(&server, "/api/jobs", &move_joints(target));
        assert_eq!(code, 202, "{accepted}");
        let id = accepted["id"].as_u64().unwrap();
        let running = running_status(&server, id);
        let ended = ended_job(&server, id);
        assert_eq!(ended["result"], "finished", "{ended}");
        let report = &ended["report"];
        assert_eq!(report["outcome"], "completed", "{ended}");
        check_running(&running, report, [&from, target]);
        if n > 0 {
            // The link's numbering went on from the jobs before: counted from the daemon's
            // start, this job's status would have shown more than its report's cycles.
            let streamed = report["cycles"].as_u64().unwrap();
            let first_seq = report["last_seq"].as_u64().unwrap() - streamed;
            assert!(
                first_seq >= streamed,
                "job {id} began at seq {first_seq}: {report}"
            );
        }
        ids.push(id);
        from = *target;
    }

    let (_, status) = get(&server, "/api/status");
    assert_eq!(status["state"], "idle", "{status}");
    assert_eq!(status["commanded"], serde_json::json!([]), "{status}");
    for path in ["/api/jobs", "/api/cells/irb120/jobs"] {
        let (code, listed) = get(&server, path);
        assert_eq!(code, 200, "{path}: {listed}");
        assert_eq!(listed["cell"], "irb120");
        let jobs = listed["jobs"].as_array().unwrap();
        let listed_ids: Vec<u64> = jobs.iter().map(|j| j["id"].as_u64().unwrap()).collect();
        let newest_first: Vec<u64> = ids.iter().rev().copied().collect();
        assert_eq!(listed_ids, newest_first, "{path}");
        for job in jobs {
            assert_eq!(job["result"], "finished", "{job}");
            assert_eq!(job["report"]["outcome"], "completed", "{job}");
        }
        // The newest job's report is the status' `last`, the same JSON.
        assert_eq!(jobs[0]["report"], status["last"]["report"], "{path}");
        assert_eq!(jobs[0]["id"], status["last"]["id"], "{path}");
    }
    let (code, one) = get(&server, &format!("/api/cells/irb120/jobs/{}", ids[1]));
    assert_eq!(code, 200, "{one}");
    assert_eq!(one["id"], ids[1]);
}

#[test]
fn unknown_jobs_are_404_naming_the_id_and_a_wait_beyond_its_cap_is_400() {
    let server = start();
    for path in ["/api/jobs/987654", "/api/cells/irb120/jobs/987654"] {
        let (code, refused) = get(&server, path);
        assert_eq!(code, 404, "{path}: {refused}");
        let text = refused["error"].as_str().unwrap();
        assert!(text.contains("987654") && text.contains("irb120"), "{text}");
    }
    let (code, refused) = get(&server, "/api/jobs/first");
    assert_eq!(code, 404, "{refused}");
    assert!(
        refused["error"].as_str().unwrap().contains("`first`"),
        "{refused}"
    );
    let (code, refused) = get(&server, "/api/cells/nowhere/jobs/1");
    assert_eq!(code, 404, "{refused}");
    assert!(
        refused["error"].as_str().unwrap().contains("nowhere"),
        "{refused}"
    );

    let (code, accepted) = post(&server, "/api/jobs", &move_joints(&CHAIN_DEG[0]));
    assert_eq!(code, 202, "{accepted}");
    let id = accepted["id"].as_u64().unwrap();
    for (query, named) in [("wait_s=31", "31"), ("wait_s=-1", "-1"), ("wait=5", "wait")] {
        let (code, refused) = get(&server, &format!("/api/jobs/{id}?{query}"));
        assert_eq!(code, 400, "{query}: {refused}");
        let text = refused["error"].as_str().unwrap();
        assert!(text.contains(named), "{query}: {text}");
    }
    // Without a wait the answer comes at once, running or not.
    let (code, now) = get(&server, &format!("/api/jobs/{id}"));
    assert_eq!(code, 200, "{now}");
    assert!(
        now["result"] == "running" || now["result"] == "finished",
        "{now}"
    );
    assert_eq!(ended_job(&server, id)["result"], "finished");
}

#[test]
fn a_method_a_route_does_not_take_is_405_and_a_reset_needs_no_content_type() {
    let server = start();
    let json = "Content-Type: application/json\r\n";
    for (method, path, headers) in [
        ("DELETE", "/api/jobs", ""),
        ("PUT", "/api/jobs", json),
        ("GET", "/api/pause", ""),
        ("GET", "/api/cells/irb120/reset", ""),
        ("POST", "/api/status", json),
        ("DELETE", "/api/jobs/1", ""),
        ("POST", "/api/cells/irb120/jobs/1", json),
    ] {
        let (code, body) = bare(&server, method, path, headers);
        assert_eq!(code, 405, "{method} {path}: {body}");
    }
    let (code, body) = bare(&server, "POST", "/api/reset", "");
    assert_eq!(code, 200, "{body}");
    let answer: serde_json::Value = serde_json::from_str(&body).unwrap();
    assert_eq!(answer["result"], "nothing_latched", "{answer}");
    let (code, body) = bare(&server, "POST", "/api/cells/irb120/reset", "");
    assert_eq!(code, 200, "{body}");
    // Another content type than JSON is still refused: a form could be another site's.
    let form = "Content-Type: application/x-www-form-urlencoded\r\n";
    assert_eq!(bare(&server, "POST", "/api/reset", form).0, 415);
    // And POST /api/jobs still takes a job on the path GET lists.
    let (code, accepted) = post(&server, "/api/jobs", &move_joints(&CHAIN_DEG[0]));
    assert_eq!(code, 202, "{accepted}");
    let id = accepted["id"].as_u64().unwrap();
    assert_eq!(ended_job(&server, id)["result"], "finished");
}
