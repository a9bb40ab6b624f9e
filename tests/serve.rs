//! `rigbridge serve`: the control API over real HTTP on 127.0.0.1, against the twin.

mod common;

use common::repo_path;
use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

struct Server {
    child: Child,
    address: String,
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn start_server() -> Server {
    let runs = std::env::temp_dir().join(format!("rigbridge-serve-{}", std::process::id()));
    let mut child = Command::new(env!("CARGO_BIN_EXE_rigbridge"))
        .args(["serve", "--port", "0", "--runs-dir", runs.to_str().unwrap()])
        .current_dir(repo_path(""))
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    let address = line
        .trim()
        .strip_prefix("http://")
        .and_then(|a| a.strip_suffix('/'))
        .unwrap_or_else(|| panic!("first line should be the address, got {line:?}"))
        .to_string();
    assert!(address.starts_with("127.0.0.1:"), "{address}");
    Server { child, address }
}

/// One HTTP/1.1 request; returns the status code and the body as JSON.
fn request(
    server: &Server,
    method: &str,
    path: &str,
    body: Option<&str>,
) -> (u16, serde_json::Value) {
    let mut stream = TcpStream::connect(&server.address).unwrap();
    stream
        .set_read_timeout(Some(Duration::from_secs(30)))
        .unwrap();
    let body = body.unwrap_or("");
    write!(
        stream,
        "{method} {path} HTTP/1.1\r\nHost: {}\r\nContent-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
        server.address,
        body.len()
    )
    .unwrap();
    let mut response = String::new();
    stream.read_to_string(&mut response).unwrap();
    let status = response[9..12].parse().unwrap();
    let json = response.split("\r\n\r\n").nth(1).unwrap_or("");
    (
        status,
        serde_json::from_str(json).unwrap_or(serde_json::Value::Null),
    )
}

fn wait_for(
    server: &Server,
    what: &str,
    test: impl Fn(&serde_json::Value) -> bool,
) -> serde_json::Value {
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        let (_, status) = request(server, "GET", "/api/status", None);
        if test(&status) {
            return status;
        }
        assert!(
            Instant::now() < deadline,
            "timed out waiting for {what}: {status}"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

#[test]
fn jobs_can_be_submitted_paused_resumed_and_stopped() {
    let server = start_server();
    let (code, idle) = request(&server, "GET", "/api/status", None);
    assert_eq!((code, idle["state"].as_str()), (200, Some("idle")));
    assert_eq!(idle["actual_deg"].as_array().unwrap().len(), 6);

    let (code, accepted) = request(&server, "POST", "/api/jobs", None);
    assert_eq!(code, 202, "{accepted}");
    let (code, _) = request(&server, "POST", "/api/jobs", None);
    assert_eq!(code, 409, "one job at a time");
    wait_for(&server, "progress", |s| {
        s["job"]["progress"].as_f64().unwrap_or(0.0) > 0.1
    });

    assert_eq!(request(&server, "POST", "/api/pause", None).0, 200);
    let paused = wait_for(&server, "pause", |s| s["state"] == "paused");
    std::thread::sleep(Duration::from_millis(1500));
    let (_, later) = request(&server, "GET", "/api/status", None);
    let progress = |s: &serde_json::Value| s["job"]["progress"].as_f64().unwrap();
    assert!(
        progress(&later) - progress(&paused) < 0.1,
        "stands still once paused"
    );
    assert_eq!(request(&server, "POST", "/api/resume", None).0, 200);
    wait_for(&server, "resume", |s| s["state"] == "running");

    assert_eq!(request(&server, "POST", "/api/stop", None).0, 200);
    let done = wait_for(&server, "stop", |s| s["state"] == "idle");
    assert_eq!(done["last"]["report"]["outcome"], "stopped", "{done}");
    assert_eq!(done["last"]["report"]["limit_violations"], 0);
    assert_eq!(
        request(&server, "POST", "/api/stop", None).0,
        409,
        "nothing left to stop"
    );
}

#[test]
fn estop_halts_the_job_and_a_bad_job_is_refused_before_motion() {
    let server = start_server();
    let far = r#"{"job": {"kind": "wall_figure", "wall_x_m": 1.5, "centre_yz_m": [0.0, 0.45], "radius_m": 0.1, "laps": 1}}"#;
    let (code, refused) = request(&server, "POST", "/api/jobs", Some(far));
    assert_eq!(code, 422, "{refused}");
    assert!(
        refused["error"].as_str().unwrap().contains("out of reach"),
        "{refused}"
    );

    assert_eq!(request(&server, "POST", "/api/jobs", None).0, 202);
    wait_for(&server, "motion", |s| {
        s["job"]["cycles"].as_u64().unwrap_or(0) > 100
    });
    assert_eq!(request(&server, "POST", "/api/estop", None).0, 200);
    let done = wait_for(&server, "e-stop", |s| s["state"] == "idle");
    assert_eq!(done["last"]["report"]["outcome"], "e_stopped", "{done}");
}
