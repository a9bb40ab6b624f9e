//! `rigbridge serve` under hostile input, over real HTTP on 127.0.0.1: 10 000 random and
//! mutated job bodies (no job starts, the daemon stays up, no answer quotes a file's
//! content), the Host allowlist, the JSON content type, and the schema route.

use crate::common;

use common::repo_path;
use common::serve::{Served, serve_command, start_serve};
use rand::{Rng, RngExt};
use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::PathBuf;
use std::process::Stdio;
use std::time::Duration;

/// How many bodies the fuzz sends.
const BODIES: usize = 10_000;
/// The secret next to the cell's config: no answer may contain it.
const SECRET: &str = "SECRET-LINE-d41d8cd98f00b204";

struct Server {
    daemon: Served,
    address: String,
    runs: PathBuf,
}

/// A daemon on a config in a fresh directory that also holds a secret file.
fn start() -> Server {
    // One directory per daemon: the tests run in parallel, and each daemon writes its
    // cells' journals there as it starts.
    static DAEMONS: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
    let n = DAEMONS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let dir = std::env::temp_dir().join(format!("rigbridge-hardening-{}-{n}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::copy(repo_path("config/irb120.toml"), dir.join("irb120.toml")).unwrap();
    std::fs::copy(
        repo_path("config/cell-star.toml"),
        dir.join("cell-star.toml"),
    )
    .unwrap();
    std::fs::copy(
        repo_path("config/rigbridge.toml"),
        dir.join("rigbridge.toml"),
    )
    .unwrap();
    std::fs::write(dir.join("secret.toml"), format!("{SECRET} = 1\n[x\n")).unwrap();
    std::fs::write(dir.join("secret.csv"), format!("t,j1\n{SECRET}\n")).unwrap();
    let runs = dir.join("runs");
    let daemon = start_serve(
        serve_command(&runs)
            .args(["--clock", "virtual", "--config"])
            .arg(dir.join("rigbridge.toml"))
            .stderr(Stdio::null()),
    );
    Server {
        address: daemon.address.clone(),
        daemon,
        runs,
    }
}

/// One request; the status code and the whole response.
fn send(server: &Server, method: &str, path: &str, headers: &str, body: &[u8]) -> (u16, String) {
    let mut stream = TcpStream::connect(&server.address).unwrap();
    stream
        .set_read_timeout(Some(Duration::from_secs(30)))
        .unwrap();
    let head = format!(
        "{method} {path} HTTP/1.1\r\n{headers}Content-Length: {}\r\nConnection: close\r\n\r\n",
        body.len()
    );
    stream.write_all(head.as_bytes()).unwrap();
    let _ = stream.write_all(body);
    let mut response = Vec::new();
    let _ = stream.read_to_end(&mut response);
    let response = String::from_utf8_lossy(&response).to_string();
    let status = response
        .get(9..12)
        .and_then(|s| s.parse().ok())
        .unwrap_or(0);
    (status, response)
}

fn json_post(server: &Server, body: &[u8]) -> (u16, String) {
    let headers = format!(
        "Host: {}\r\nContent-Type: application/json\r\n",
        server.address
    );
    send(server, "POST", "/api/jobs", &headers, body)
}

/// Valid job bodies, each to be broken before it is sent.
const VALID: [&str; 4] = [
    r#"{"job": {"kind": "wall_figure", "wall_x_m": 0.45, "centre_yz_m": [0.0, 0.45], "radius_m": 0.12, "laps": 2}}"#,
    r#"{"job": {"kind": "move_joints", "targets_deg": [[10.0, 0.0, 0.0, 0.0, 30.0, 0.0]]}}"#,
    r#"{"job": {"kind": "move_linear", "speed_m_s": 0.1, "poses": [{"xyz_m": [0.4, 0.0, 0.45], "quat_wxyz": [0.7071, 0.0, 0.7071, 0.0]}]}}"#,
    r#"{"job": {"kind": "joint_waypoints", "waypoints_deg": [[0.0, 0.0, 0.0, 0.0, 30.0, 0.0]]}}"#,
];

/// Values that no key of any kind accepts where a number, list or file belongs.
const BAD_VALUES: [&str; 14] = [
    "4294967295",
    "0",
    "-1",
    "1e300",
    "-1e300",
    "null",
    "[]",
    "\"/etc/passwd\"",
    "\"../Cargo.toml\"",
    "\"secret.toml\"",
    "{}",
    "true",
    "[[1e9, 0, 0, 0, 0, 0]]",
    "18446744073709551616",
];

/// A body that must be refused: random bytes, or a valid body broken in one of the ways
/// that always break it (no wrapper, an unknown key, a value replaced by one out of range,
/// cut short, a file outside or unreadable).
fn invalid_body(rng: &mut impl Rng) -> Vec<u8> {
    let valid = VALID[rng.random_range(0..VALID.len())];
    let inner = &valid[8..valid.len() - 1];
    match rng.random_range(0..9) {
        0 => (0..rng.random_range(1..200))
            .map(|_| rng.random::<u8>())
            .collect(),
        // The job without its wrapper.
        1 => inner.as_bytes().to_vec(),
        // An unknown key in the job or beside it.
        2 => valid
            .replacen("\"kind\"", "\"speed_scale\": 0.1, \"kind\"", 1)
            .into_bytes(),
        3 => format!("{{\"extra\": 1, {}", &valid[1..]).into_bytes(),
        // Cut short anywhere after the first byte.
        4 => valid.as_bytes()[..rng.random_range(1..valid.len())].to_vec(),
        // A value replaced by one nothing accepts.
        5 => {
            let bad = BAD_VALUES[rng.random_range(0..BAD_VALUES.len())];
            let keys = [
                "\"laps\": 2",
                "[[10.0, 0.0, 0.0, 0.0, 30.0, 0.0]]",
                "\"speed_m_s\": 0.1",
                "[0.7071, 0.0, 0.7071, 0.0]",
                "[[0.0, 0.0, 0.0, 0.0, 30.0, 0.0]]",
                "\"radius_m\": 0.12",
            ];
            let mut body = valid.to_string();
            for key in keys {
                if let Some((name, _)) = key.split_once(": ") {
                    body = body.replacen(key, &format!("{name}: {bad}"), 1);
                } else {
                    body = body.replacen(key, bad, 1);
                }
            }
            if body == valid {
                format!("{{\"job\": {bad}}}")
            } else {
                body
            }
            .into_bytes()
        }
        // Files outside the config's directory, or inside but not what the kind reads.
        6 => {
            let files = [
                "/etc/passwd",
                "../rigbridge.toml",
                "secret.toml",
                "secret.csv",
                "runs/../../x",
                "",
            ];
            let file = files[rng.random_range(0..files.len())];
            let kinds = [
                format!(
                    r#"{{"job": {{"kind": "paint", "walls": 4, "seed": 1, "paint_config": "{file}"}}}}"#
                ),
                format!(r#"{{"job": {{"kind": "follow_trajectory", "file": "{file}"}}}}"#),
                format!(
                    r#"{{"job": {{"kind": "gait", "scenario": "straight", "forest": "{file}"}}}}"#
                ),
            ];
            kinds[rng.random_range(0..kinds.len())].clone().into_bytes()
        }
        // Whitespace is not an empty body.
        7 => vec![b' '; rng.random_range(1..4096)],
        // Random bytes spliced into a valid body at a structural place.
        _ => {
            let junk: String = (0..rng.random_range(1..8))
                .map(|_| char::from(rng.random_range(b'a'..=b'z')))
                .collect();
            valid.replacen('{', &format!("{{{junk}"), 1).into_bytes()
        }
    }
}

#[test]
fn ten_thousand_invalid_bodies_start_nothing_crash_nothing_and_quote_no_file() {
    let mut server = start();
    let mut rng = common::rng(15);
    let passwd = std::fs::read_to_string("/etc/passwd").unwrap_or_default();
    let passwd_lines: Vec<&str> = passwd.lines().filter(|l| l.len() >= 12).collect();
    let mut codes = std::collections::BTreeMap::new();
    for n in 0..BODIES {
        let body = invalid_body(&mut rng);
        let (code, response) = json_post(&server, &body);
        *codes.entry(code).or_insert(0) += 1;
        assert!(
            (400..500).contains(&code),
            "body {n} answered {code}: {}\n{response}",
            String::from_utf8_lossy(&body)
        );
        assert!(
            !response.contains(SECRET),
            "body {n} quoted the secret: {response}"
        );
        for line in &passwd_lines {
            assert!(
                !response.contains(line),
                "body {n} quoted /etc/passwd: {response}"
            );
        }
    }
    println!("{BODIES} invalid bodies: status codes {codes:?}");
    assert!(
        server.daemon.child.try_wait().unwrap().is_none(),
        "the daemon is still running"
    );
    let headers = format!("Host: {}\r\n", server.address);
    let (code, status) = send(&server, "GET", "/api/status", &headers, b"");
    assert_eq!(code, 200);
    let json: serde_json::Value =
        serde_json::from_str(status.split("\r\n\r\n").nth(1).unwrap()).unwrap();
    assert!(
        json["job"].is_null() && json["last"].is_null(),
        "no job ever ran: {json}"
    );
    // The cell's journal (control actions) is there from the start; no job's log is.
    let logs = std::fs::read_dir(&server.runs)
        .map(|d| {
            d.filter_map(Result::ok)
                .filter(|e| e.file_name().to_string_lossy().starts_with("job-"))
                .count()
        })
        .unwrap_or(0);
    assert_eq!(logs, 0, "no job log was started");
    // And the same daemon still takes a valid job.
    let (code, response) = json_post(&server, VALID[1].as_bytes());
    assert_eq!(code, 202, "{response}");
}

#[test]
fn rebinding_hosts_plain_text_and_unwrapped_bodies_are_refused_and_the_schema_is_served() {
    let server = start();
    let valid = VALID[1].as_bytes();
    let rebinding = "Host: attacker.example\r\nContent-Type: application/json\r\n";
    assert_eq!(send(&server, "POST", "/api/jobs", rebinding, valid).0, 421);
    let plain = format!("Host: {}\r\nContent-Type: text/plain\r\n", server.address);
    assert_eq!(send(&server, "POST", "/api/jobs", &plain, valid).0, 415);
    assert_eq!(send(&server, "POST", "/api/pause", &plain, b"").0, 415);
    // A reset re-arms a controller: it takes JSON or no content type at all (it has no
    // body), never a form or text a page of another site could send without asking.
    assert_eq!(send(&server, "POST", "/api/reset", &plain, b"").0, 415);
    let cross = format!(
        "Host: {}\r\nOrigin: http://evil.example\r\nContent-Type: application/json\r\n",
        server.address
    );
    assert_eq!(send(&server, "POST", "/api/reset", &cross, b"").0, 403);
    // An e-stop needs no content type: it only ever stops.
    let bare = format!("Host: {}\r\n", server.address);
    assert_eq!(
        send(&server, "POST", "/api/estop", &bare, b"").0,
        409,
        "no job to stop"
    );
    let big = vec![b' '; 2 * 1024 * 1024];
    assert_eq!(json_post(&server, &big).0, 413);
    let (code, schema) = send(&server, "GET", "/api/schema", &bare, b"");
    assert_eq!(code, 200);
    for kind in [
        "move_joints",
        "move_linear",
        "move_poses",
        "follow_trajectory",
        "wall_figure",
    ] {
        assert!(schema.contains(kind), "{kind} missing from the schema");
    }
    let (_, status) = send(&server, "GET", "/api/status", &bare, b"");
    assert!(
        status.contains("\"estop\""),
        "the e-stop is logged as an event: {status}"
    );
    assert!(status.contains("\"link\":\"loopback\""), "{status}");
}
