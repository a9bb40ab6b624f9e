//! `rigbridge serve`: the control API over real HTTP on 127.0.0.1, against the twin, and its
//! access control (bind address, bearer token). Traffic only ever goes to 127.0.0.1.

use crate::common;

use common::repo_path;
use common::serve::{Served, request_bare, request_json, start_serve, write_pan_tilt_rig};
use std::io::{Read, Write};
use std::net::TcpStream;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// 1.5 s of the default job's 250 Hz cycles: long enough for a paused job that crept on
/// to show it.
const CYCLES_PAUSED: u64 = 375;

struct Server {
    daemon: Served,
    /// Where to connect: always 127.0.0.1:PORT.
    address: String,
    /// What the server printed as its address.
    listening: String,
    /// Sent as `Authorization: Bearer <token>` when set.
    token: Option<String>,
}

fn serve_command(extra: &[&str], env_token: Option<&str>) -> Command {
    // One runs directory per server: tests run in parallel and every server numbers its
    // jobs from 1.
    static SERVERS: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
    let n = SERVERS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let runs = std::env::temp_dir().join(format!("rigbridge-serve-{}-{n}", std::process::id()));
    let _ = std::fs::remove_dir_all(&runs);
    let mut command = common::serve::serve_command(&runs);
    command.args(extra);
    if let Some(token) = env_token {
        command.env("RIGBRIDGE_TOKEN", token);
    }
    command
}

fn start_server() -> Server {
    start_server_with(&[], None)
}

fn start_server_with(extra: &[&str], env_token: Option<&str>) -> Server {
    started(serve_command(extra, env_token), env_token)
}

/// The server `command` starts, once it printed where it listens.
fn started(mut command: Command, env_token: Option<&str>) -> Server {
    let daemon = start_serve(command.stderr(Stdio::piped()));
    let port = daemon.address.rsplit_once(':').unwrap().1;
    Server {
        address: format!("127.0.0.1:{port}"),
        listening: daemon.address.clone(),
        token: env_token.map(String::from),
        daemon,
    }
}

/// One HTTP/1.1 request; returns the status code and the body as JSON.
fn request(
    server: &Server,
    method: &str,
    path: &str,
    body: Option<&str>,
) -> (u16, serde_json::Value) {
    let authorization = server
        .token
        .as_ref()
        .map(|t| format!("Authorization: Bearer {t}\r\n"))
        .unwrap_or_default();
    request_json(
        &server.address,
        method,
        path,
        &authorization,
        body.unwrap_or(""),
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
    assert_eq!(idle["actual"].as_array().unwrap().len(), 6);

    let (code, accepted) = request(&server, "POST", "/api/jobs", None);
    assert_eq!(code, 202, "{accepted}");
    let (code, _) = request(&server, "POST", "/api/jobs", None);
    assert_eq!(code, 409, "one job at a time");
    wait_for(&server, "progress", |s| {
        s["job"]["progress"].as_f64().unwrap_or(0.0) > 0.1
    });

    assert_eq!(request(&server, "POST", "/api/pause", None).0, 200);
    let paused = wait_for(&server, "pause", |s| s["state"] == "paused");
    // A paused job still streams a cycle each period (holding its place on the path).
    let cycles = |s: &serde_json::Value| {
        s["job"]["cycles"]
            .as_u64()
            .unwrap_or_else(|| panic!("a running job's status counts its cycles: {s}"))
    };
    let later = wait_for(&server, "cycles streamed while paused", |s| {
        cycles(s) >= cycles(&paused) + CYCLES_PAUSED
    });
    let progress = |s: &serde_json::Value| s["job"]["progress"].as_f64().unwrap();
    assert!(
        progress(&later) - progress(&paused) < 0.1,
        "stands still once paused"
    );
    assert_eq!(request(&server, "POST", "/api/resume", None).0, 200);
    wait_for(&server, "resume", |s| s["state"] == "running");
    // Moving again (a resumed job's first cycles may still hold the arm): the stop below
    // meets targets that move it.
    wait_for(&server, "moving after the resume", |s| {
        progress(s) > progress(&later) + 0.01
    });

    let (code, stopped) = request(&server, "POST", "/api/stop", None);
    assert_eq!(code, 200, "{stopped}");
    assert_eq!(stopped["phase"], "streaming", "{stopped}");
    let done = wait_for(&server, "stop", |s| s["state"] == "idle");
    assert_eq!(done["last"]["report"]["outcome"], "stopped", "{done}");
    assert_eq!(done["last"]["report"]["stopped_in"], "streaming", "{done}");
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
    let (code, estopped) = request(&server, "POST", "/api/estop", None);
    assert_eq!(code, 200, "{estopped}");
    assert_eq!(estopped["phase"], "streaming", "{estopped}");
    let done = wait_for(&server, "e-stop", |s| s["state"] == "idle");
    assert_eq!(done["last"]["report"]["outcome"], "e_stopped", "{done}");
    assert_eq!(done["last"]["report"]["stopped_in"], "streaming", "{done}");
}

#[test]
fn after_an_estop_jobs_are_refused_until_a_reset_then_a_job_completes() {
    let server = start_server();
    let (code, idle) = request(&server, "POST", "/api/reset", None);
    assert_eq!(code, 200, "{idle}");
    assert_eq!(idle["result"], "nothing_latched", "{idle}");

    assert_eq!(request(&server, "POST", "/api/jobs", None).0, 202);
    wait_for(&server, "motion", |s| {
        s["job"]["cycles"].as_u64().unwrap_or(0) > 100
    });
    let (code, busy) = request(&server, "POST", "/api/reset", None);
    assert_eq!(code, 409, "no reset while a job runs: {busy}");
    assert_eq!(request(&server, "POST", "/api/estop", None).0, 200);
    let stopped = wait_for(&server, "e-stop", |s| s["state"] == "idle");
    assert_eq!(stopped["last"]["report"]["outcome"], "e_stopped");
    assert_eq!(stopped["controller"]["status"], "fault", "{stopped}");
    assert_eq!(stopped["controller"]["fault"], "e-stop", "{stopped}");

    for path in ["/api/jobs", "/api/cells/irb120/jobs"] {
        let (code, refused) = request(&server, "POST", path, None);
        assert_eq!(code, 409, "{path}: {refused}");
        let text = refused["error"].as_str().unwrap();
        assert!(text.contains("e-stop") && text.contains("reset"), "{text}");
    }

    let (code, cleared) = request(&server, "POST", "/api/cells/irb120/reset", None);
    assert_eq!(code, 200, "{cleared}");
    assert_eq!(cleared["result"], "cleared", "{cleared}");
    assert!(
        cleared["message"].as_str().unwrap().contains("holding"),
        "{cleared}"
    );
    let (_, status) = request(&server, "GET", "/api/status", None);
    assert_eq!(status["controller"]["status"], "holding", "{status}");
    assert!(status["controller"]["fault"].is_null(), "{status}");
    let logged: Vec<&str> = status["events"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(|e| e["action"].as_str())
        .collect();
    assert_eq!(logged, ["reset", "estop", "reset"], "{status}");

    let short =
        r#"{"job": {"kind": "move_joints", "targets_deg": [[10.0, 0.0, 0.0, 0.0, 30.0, 0.0]]}}"#;
    let (code, accepted) = request(&server, "POST", "/api/jobs", Some(short));
    assert_eq!(code, 202, "{accepted}");
    let done = wait_for(&server, "the job after the reset", |s| {
        s["state"] == "idle" && s["last"]["id"] == accepted["id"]
    });
    assert_eq!(done["last"]["report"]["outcome"], "completed", "{done}");
}

/// One request with exactly these extra header lines (no token of the server's own).
fn request_with(server: &Server, method: &str, path: &str, headers: &str) -> (u16, String) {
    assert!(server.address.starts_with("127.0.0.1:"));
    request_bare(
        &server.address,
        method,
        path,
        headers,
        Duration::from_secs(30),
    )
}

fn assert_unauthorized((code, response): (u16, String)) {
    assert_eq!(code, 401, "{response}");
    let lower = response.to_ascii_lowercase();
    assert!(lower.contains("www-authenticate: bearer"), "{response}");
    let body = response.split("\r\n\r\n").nth(1).unwrap_or("");
    let json: serde_json::Value = serde_json::from_str(body).unwrap();
    assert!(json["error"].as_str().unwrap().contains("token"), "{json}");
}

#[test]
fn default_bind_is_loopback_and_needs_no_token() {
    let server = start_server();
    assert!(
        server.listening.starts_with("127.0.0.1:"),
        "{}",
        server.listening
    );
    assert_eq!(request(&server, "GET", "/api/status", None).0, 200);
    assert_eq!(request_with(&server, "GET", "/", "").0, 200);
    // No job: 409 from the handler itself, not 401.
    assert_eq!(request(&server, "POST", "/api/stop", None).0, 409);
}

#[test]
fn a_token_guards_the_control_routes_on_loopback() {
    let token = "s3cret-token-for-tests";
    let server = start_server_with(&[], Some(token));
    assert!(
        server.listening.starts_with("127.0.0.1:"),
        "{}",
        server.listening
    );
    for path in [
        "/api/stop",
        "/api/jobs",
        "/api/pause",
        "/api/resume",
        "/api/estop",
        "/api/reset",
        "/api/cells/irb120/reset",
    ] {
        assert_unauthorized(request_with(&server, "POST", path, ""));
    }
    assert_unauthorized(request_with(
        &server,
        "POST",
        "/api/stop",
        "Authorization: Bearer wrong-token\r\n",
    ));
    assert_unauthorized(request_with(
        &server,
        "POST",
        "/api/stop",
        "Authorization: Bearer s3cret-token-for-test\r\n",
    ));
    assert_unauthorized(request_with(
        &server,
        "POST",
        "/api/stop",
        &format!("Authorization: Basic {token}\r\n"),
    ));
    let (code, response) = request_with(
        &server,
        "POST",
        "/api/stop",
        &format!("Authorization: Bearer {token}\r\n"),
    );
    assert_ne!(code, 401, "{response}");
    assert_eq!(code, 409, "no job to stop: {response}");
    // Status and the job history stay open on loopback.
    assert_eq!(request_with(&server, "GET", "/api/status", "").0, 200);
    assert_eq!(request_with(&server, "GET", "/api/jobs", "").0, 200);
    assert_eq!(request_with(&server, "GET", "/api/jobs/1", "").0, 404);
    assert_eq!(request_with(&server, "GET", "/", "").0, 200);
}

/// Everything a daemon said on stderr up to a stop asked with no job running, its
/// environment's RUST_LOG set to `rust_log` (or unset).
fn stderr_up_to_a_stop(rust_log: Option<&str>) -> String {
    let mut command = serve_command(&[], None);
    match rust_log {
        Some(directives) => command.env("RUST_LOG", directives),
        None => command.env_remove("RUST_LOG"),
    };
    let mut server = started(command, None);
    assert_eq!(request(&server, "POST", "/api/stop", None).0, 409);
    server.daemon.child.kill().unwrap();
    server.daemon.child.wait().unwrap();
    let mut stderr = String::new();
    let mut pipe = server.daemon.child.stderr.take().unwrap();
    pipe.read_to_string(&mut stderr).unwrap();
    stderr
}

#[test]
fn diagnostics_are_plain_lines_unless_rust_log_asks_for_more() {
    let plain = stderr_up_to_a_stop(None);
    let lines: Vec<&str> = plain.lines().collect();
    assert!(
        lines
            .iter()
            .any(|line| line.starts_with("cell irb120: control actions logged to ")),
        "{plain}"
    );
    assert!(lines.contains(&"cell irb120: stop (no job)"), "{plain}");
    // Level, target, message and the event's fields, after a timestamp.
    let detailed = stderr_up_to_a_stop(Some("rigbridge=info"));
    assert!(
        detailed.lines().any(|line| line.ends_with(
            " INFO rigbridge::server::cell: cell irb120: stop (no job) cell=irb120 action=stop"
        )),
        "{detailed}"
    );
}

#[test]
fn a_non_loopback_bind_without_a_token_refuses_to_start() {
    let output = serve_command(&["--bind", "0.0.0.0"], None)
        .stdin(Stdio::null())
        .output()
        .unwrap();
    assert!(!output.status.success());
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(stderr.contains("0.0.0.0"), "{stderr}");
    assert!(stderr.contains("token"), "{stderr}");
    assert!(stderr.contains("RIGBRIDGE_TOKEN"), "{stderr}");
    assert!(
        output.stdout.is_empty(),
        "never listened: {:?}",
        output.stdout
    );
}

#[test]
fn a_non_loopback_bind_with_a_token_guards_status_too() {
    let token = "another-s3cret-for-tests";
    let server = start_server_with(&["--bind", "0.0.0.0"], Some(token));
    assert!(
        server.listening.starts_with("0.0.0.0:"),
        "{}",
        server.listening
    );
    // Only ever connect to 127.0.0.1.
    assert_unauthorized(request_with(&server, "GET", "/api/status", ""));
    assert_unauthorized(request_with(&server, "GET", "/api/jobs", ""));
    assert_unauthorized(request_with(&server, "GET", "/api/cells/irb120/jobs/1", ""));
    assert_unauthorized(request_with(&server, "POST", "/api/stop", ""));
    assert_unauthorized(request_with(&server, "GET", "/api/live", ""));
    // The page is static code without state: a browser must be able to load it.
    let (code, page) = request_with(&server, "GET", "/", "");
    assert_eq!(code, 200, "{page}");
    assert!(!page.contains("\"actual\":"), "no state in the page");
    assert_unauthorized(request_with(
        &server,
        "GET",
        "/api/status",
        "Authorization: Bearer nope\r\n",
    ));
    let (code, status) = request(&server, "GET", "/api/status", None);
    assert_eq!((code, status["state"].as_str()), (200, Some("idle")));
    let (code, jobs) = request(&server, "GET", "/api/jobs", None);
    assert_eq!(
        (code, &jobs["jobs"]),
        (200, &serde_json::json!([])),
        "{jobs}"
    );
    assert_eq!(request(&server, "GET", "/api/jobs/1", None).0, 404);
    assert_eq!(request(&server, "POST", "/api/stop", None).0, 409);
}

#[test]
fn a_cross_site_request_from_a_browser_page_is_refused() {
    let server = start_server();
    let mut stream = TcpStream::connect(&server.address).unwrap();
    write!(
        stream,
        "POST /api/estop HTTP/1.1\r\nHost: {}\r\nOrigin: http://evil.example\r\nContent-Length: 0\r\nConnection: close\r\n\r\n",
        server.address
    )
    .unwrap();
    let mut response = String::new();
    stream.read_to_string(&mut response).unwrap();
    assert!(response.starts_with("HTTP/1.1 403"), "{response}");
    let mut stream = TcpStream::connect(&server.address).unwrap();
    write!(
        stream,
        "POST /api/estop HTTP/1.1\r\nHost: {0}\r\nOrigin: http://{0}\r\nContent-Length: 0\r\nConnection: close\r\n\r\n",
        server.address
    )
    .unwrap();
    let mut response = String::new();
    stream.read_to_string(&mut response).unwrap();
    assert!(
        response.starts_with("HTTP/1.1 409"),
        "same origin passes (no job to stop): {response}"
    );
}

// ------------------------------------------------------------------ live view --

type LiveSocket = tungstenite::WebSocket<tungstenite::stream::MaybeTlsStream<TcpStream>>;

/// Opens `/api/live` with these extra headers (`path_and_query` after the host).
fn open_live(
    server: &Server,
    path_and_query: &str,
    headers: &[(&str, &str)],
) -> Result<(LiveSocket, tungstenite::handshake::client::Response), tungstenite::Error> {
    use tungstenite::client::IntoClientRequest;
    assert!(server.address.starts_with("127.0.0.1:"));
    let mut request = format!("ws://{}{path_and_query}", server.address)
        .into_client_request()
        .unwrap();
    for (name, value) in headers {
        request.headers_mut().insert(
            tungstenite::http::HeaderName::from_bytes(name.as_bytes()).unwrap(),
            value.parse().unwrap(),
        );
    }
    tungstenite::connect(request)
}

fn refused_with(result: Result<(LiveSocket, impl std::fmt::Debug), tungstenite::Error>) -> u16 {
    match result {
        Err(tungstenite::Error::Http(response)) => response.status().as_u16(),
        Err(other) => panic!("expected an HTTP refusal, got {other}"),
        Ok((_, response)) => panic!("expected a refusal, got {response:?}"),
    }
}

fn next_json(socket: &mut LiveSocket) -> serde_json::Value {
    loop {
        match socket.read().unwrap() {
            tungstenite::Message::Text(text) => return serde_json::from_str(&text).unwrap(),
            tungstenite::Message::Ping(_) | tungstenite::Message::Pong(_) => {}
            other => panic!("unexpected message {other:?}"),
        }
    }
}

#[test]
fn the_live_view_sends_the_scene_then_frames_of_the_moving_twin_and_its_paint() {
    let server = start_server();
    let (code, page) = request_with(&server, "GET", "/", "");
    assert_eq!(code, 200);
    assert!(
        page.contains("<canvas") && page.contains("/live.js"),
        "{page}"
    );
    assert!(
        !page.contains("http://") && !page.contains("https://"),
        "nothing fetched from elsewhere"
    );
    let (code, script) = request_with(&server, "GET", "/live.js", "");
    assert_eq!(code, 200);
    assert!(script.contains("text/javascript"));

    let (mut socket, response) = open_live(&server, "/api/live", &[]).unwrap();
    assert_eq!(response.status().as_u16(), 101);
    let scene = next_json(&mut socket);
    assert_eq!(scene["type"], "scene", "{scene}");
    assert_eq!(scene["joints"].as_array().unwrap().len(), 6);
    let wall = &scene["scene"]["walls"][0]["corners"];
    for corner in wall.as_array().unwrap() {
        assert_eq!(
            corner[0], 0.45,
            "the star job's wall at x = wall_x_m: {wall}"
        );
    }
    // At rest, before any job: the twin at its configured initial position.
    let rest = next_json(&mut socket);
    assert_eq!(rest["type"], "frame");
    assert_eq!(rest["job"]["state"], "idle");
    assert!(
        (rest["actual"][4].as_f64().unwrap() - 30.0).abs() < 1e-9,
        "{rest}"
    );
    let chain = rest["chains"][0].as_array().unwrap();
    assert!(chain.len() >= 2, "{rest}");
    assert_eq!(chain[0], serde_json::json!([0.0, 0.0, 0.0]), "the base");

    assert_eq!(request(&server, "POST", "/api/jobs", None).0, 202);
    let mut seqs = Vec::new();
    let mut painted = 0;
    let mut tips = std::collections::HashSet::new();
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        let message = next_json(&mut socket);
        if message["type"] != "frame" {
            continue;
        }
        seqs.push(message["seq"].as_u64().unwrap());
        painted += message["paint"].as_array().unwrap().len();
        let chain = message["chains"][0].as_array().unwrap();
        tips.insert(chain.last().unwrap().to_string());
        if message["job"]["state"] == "idle" && seqs.len() > 10 {
            assert_eq!(message["job"]["last"], "completed", "{message}");
            break;
        }
        assert!(Instant::now() < deadline, "the job should end: {message}");
    }
    assert!(
        seqs.windows(2).all(|w| w[0] <= w[1]),
        "frames in cycle order"
    );
    assert!(
        tips.len() > 50,
        "the tool moved: {} distinct positions",
        tips.len()
    );
    // The star is drawn on the wall: the tool's trace shows as paint, once, on wall 0.
    assert!(painted > 20, "paint quads during the star: {painted}");
    let (mut late, _) = open_live(&server, "/api/live", &[]).unwrap();
    let scene = next_json(&mut late);
    assert_eq!(
        scene["scene"]["paint"].as_array().unwrap().len(),
        painted,
        "a page that connects later sees all the paint"
    );
}

#[test]
fn the_live_view_refuses_a_websocket_without_the_token() {
    // '/' and '+' must be percent-encoded in a query, as the page does (encodeURIComponent).
    let token = "live/s3cret+token_1";
    let encoded = "live%2Fs3cret%2Btoken_1";
    let server = start_server_with(&[], Some(token));
    assert_eq!(refused_with(open_live(&server, "/api/live", &[])), 401);
    assert_eq!(
        refused_with(open_live(&server, "/api/live?token=wrong", &[])),
        401
    );
    assert_eq!(
        refused_with(open_live(
            &server,
            "/api/live",
            &[(
                "sec-websocket-protocol",
                "rigbridge.live, rigbridge.token.wrong"
            )]
        )),
        401
    );
    assert_eq!(
        refused_with(open_live(&server, "/api/live?token=live%2Fs3cret%2", &[])),
        401,
        "a broken escape"
    );
    // Right token from another site's page: refused all the same.
    assert_eq!(
        refused_with(open_live(
            &server,
            &format!("/api/live?token={encoded}"),
            &[("origin", "http://evil.example")]
        )),
        403
    );
    let (mut socket, _) =
        open_live(&server, &format!("/api/live?x=1&token={encoded}"), &[]).unwrap();
    assert_eq!(next_json(&mut socket)["type"], "scene");
    let (mut socket, response) = open_live(
        &server,
        "/api/live",
        &[(
            "sec-websocket-protocol",
            &format!("rigbridge.live, rigbridge.token.{token}"),
        )],
    )
    .unwrap();
    assert_eq!(
        response.headers()["sec-websocket-protocol"],
        "rigbridge.live",
        "the token is never echoed back"
    );
    assert_eq!(next_json(&mut socket)["type"], "scene");
    let bearer = format!("Bearer {token}");
    let (mut socket, _) = open_live(&server, "/api/live", &[("authorization", &bearer)]).unwrap();
    assert_eq!(next_json(&mut socket)["type"], "scene");
}

#[test]
fn off_loopback_the_live_view_needs_the_token_too() {
    let token = "exposed-live-token";
    let server = start_server_with(&["--bind", "0.0.0.0"], Some(token));
    assert_eq!(refused_with(open_live(&server, "/api/live", &[])), 401);
    let (mut socket, _) = open_live(&server, &format!("/api/live?token={token}"), &[]).unwrap();
    assert_eq!(next_json(&mut socket)["type"], "scene");
}

// ---------------------------------------------------------------------- cells --

/// A second cell's run settings in a fresh directory: a three-axis pan-tilt rig named
/// `name` (joints `pan`, `tilt`, `elbow`, slow enough that a job lasts seconds) on `link`,
/// whose default job is a few joint moves.
fn pan_tilt_cell(name: &str, link: &str) -> std::path::PathBuf {
    static CELLS: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
    let n = CELLS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let dir = std::env::temp_dir().join(format!("rigbridge-cell-{}-{n}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    write_pan_tilt_rig(&dir, name);
    let settings = format!(
        "rig = \"pan_tilt.toml\"\n\n[stream]\nrate_hz = 250.0\nlink = \"{link}\"\n\n\
         [twin]\nbandwidth_hz = 20.0\ndelay_ms = 12.0\nwatchdog_cycles = 25\n\
         initial_deg = [0.0, 0.0, 0.0]\n\n[plan]\nspeed_scale = 0.9\naccel_scale = 0.8\n\n\
         [job]\nkind = \"joint_waypoints\"\n\
         waypoints_deg = [[50.0, 20.0, -20.0], [-50.0, -20.0, 20.0], [0.0, 0.0, 0.0]]\n"
    );
    let file = dir.join("pan_tilt_cell.toml");
    std::fs::write(&file, settings).unwrap();
    file
}

fn two_cells(second: &std::path::Path, env_token: Option<&str>) -> Server {
    start_server_with(
        &[
            "--config",
            "config/rigbridge.toml",
            "--config",
            second.to_str().unwrap(),
        ],
        env_token,
    )
}

/// A few joint moves of the arm, about 2 s at 250 Hz.
const ARM_MOVES: &str = r#"{"job": {"kind": "joint_waypoints", "waypoints_deg": [[60, 0, 0, 0, 30, 0], [-60, 0, 0, 0, 30, 0], [0, 0, 0, 0, 30, 0]]}}"#;

fn cell_states(server: &Server) -> Vec<(String, String)> {
    let (code, list) = request(server, "GET", "/api/cells", None);
    assert_eq!(code, 200, "{list}");
    list["cells"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| {
            (
                c["name"].as_str().unwrap().to_string(),
                c["state"].as_str().unwrap().to_string(),
            )
        })
        .collect()
}

/// Waits until one `/api/cells` listing shows every cell running (both jobs at one
/// instant), then until every cell is idle again, within `to_end`.
fn both_run_then_end(server: &Server, to_end: Duration) {
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let states = cell_states(server);
        if states.iter().all(|(_, state)| state == "running") {
            break;
        }
        assert!(Instant::now() < deadline, "never both running: {states:?}");
        std::thread::sleep(Duration::from_millis(20));
    }
    let deadline = Instant::now() + to_end;
    while cell_states(server).iter().any(|(_, state)| state != "idle") {
        assert!(Instant::now() < deadline, "jobs should end");
        std::thread::sleep(Duration::from_millis(50));
    }
}

#[test]
fn two_cells_run_their_jobs_at_the_same_time_each_on_its_own_rig() {
    let server = two_cells(&pan_tilt_cell("pan_tilt", "loopback"), None);
    let (code, list) = request(&server, "GET", "/api/cells", None);
    assert_eq!(code, 200, "{list}");
    let cells = list["cells"].as_array().unwrap();
    assert_eq!(cells.len(), 2, "{list}");
    assert_eq!(cells[0]["name"], "irb120", "the first file's cell first");
    assert_eq!(cells[0]["dof"], 6);
    assert_eq!(cells[1]["name"], "pan_tilt");
    assert_eq!(cells[1]["dof"], 3);
    assert_eq!(
        cells[1]["joints"],
        serde_json::json!(["pan", "tilt", "elbow"])
    );
    let (_, status) = request(&server, "GET", "/api/cells/pan_tilt/status", None);
    assert_eq!(status["cell"], "pan_tilt");
    assert_eq!(status["actual"].as_array().unwrap().len(), 3);

    let (code, arm) = request(&server, "POST", "/api/cells/irb120/jobs", Some(ARM_MOVES));
    assert_eq!(code, 202, "{arm}");
    let (code, pan) = request(&server, "POST", "/api/cells/pan_tilt/jobs", None);
    assert_eq!(code, 202, "{pan}");
    assert_eq!(pan["cell"], "pan_tilt");
    assert_ne!(arm["id"], pan["id"], "job numbers are daemon-wide");
    let (code, busy) = request(&server, "POST", "/api/cells/pan_tilt/jobs", None);
    assert_eq!(code, 409, "one job at a time in a cell: {busy}");

    both_run_then_end(&server, Duration::from_secs(30));
    for (cell, rig, joints) in [("irb120", "irb120", 6), ("pan_tilt", "pan_tilt", 3)] {
        let (_, status) = request(&server, "GET", &format!("/api/cells/{cell}/status"), None);
        let report = &status["last"]["report"];
        assert_eq!(report["outcome"], "completed", "{status}");
        assert_eq!(report["rig"], rig, "{status}");
        assert_eq!(report["limit_violations"], 0, "{status}");
        assert_eq!(status["actual"].as_array().unwrap().len(), joints);
        let log = rigbridge::log::read_log(std::path::Path::new(
            report["log"]["path"].as_str().unwrap(),
        ))
        .unwrap();
        assert_eq!(log.rig, rig);
        assert_eq!(log.joint_names.len(), joints, "{:?}", log.joint_names);
        assert!(!log.commands.is_empty() && !log.states.is_empty());
        for sample in log.commands.iter().chain(&log.states) {
            assert_eq!(sample.positions.len(), joints, "seq {}", sample.seq);
        }
    }
    // The routes without a cell name are the first cell's.
    let (_, first) = request(&server, "GET", "/api/status", None);
    assert_eq!(first["cell"], "irb120");
    assert_eq!(first["last"]["report"]["rig"], "irb120");
}

/// One daemon, the arm's cell and the sloth's (`config/gait-run.toml`): both jobs stream at
/// once, the sloth's through the same pipeline (26 axes, its own log), and the sloth's live
/// view shows its branch and its bones.
#[test]
fn one_daemon_runs_the_arm_and_the_sloth_at_the_same_time() {
    let server = two_cells(&repo_path("config/gait-run.toml"), None);
    let (mut live, _) = open_live(&server, "/api/cells/sloth/live", &[]).unwrap();
    let scene = next_json(&mut live);
    assert_eq!(scene["type"], "scene", "{scene}");
    assert_eq!(scene["rig"], "sloth");
    assert_eq!(scene["joints"].as_array().unwrap().len(), 26);
    let branches = scene["scene"]["cylinders"].as_array().unwrap();
    assert!(!branches.is_empty(), "the straight branch: {scene}");
    let frame = next_json(&mut live);
    let chains = frame["chains"].as_array().unwrap();
    assert_eq!(chains.len(), 5, "the spine and four limbs: {frame}");
    // Status in each axis' own unit: the body's position in metres, its bones in degrees.
    let (_, status) = request(&server, "GET", "/api/cells/sloth/status", None);
    let actual = status["actual"].as_array().unwrap();
    assert_eq!(actual.len(), 26, "{status}");
    assert_eq!(actual[0]["joint"], "body_x");
    assert_eq!(actual[0]["unit"], "m");
    assert!(
        (actual[0]["value"].as_f64().unwrap() - -0.3).abs() < 1e-6,
        "{status}"
    );
    assert_eq!(actual[6]["unit"], "deg");
    assert!(
        (actual[6]["value"].as_f64().unwrap() - 4.2).abs() < 1e-6,
        "{status}"
    );

    let (code, arm) = request(&server, "POST", "/api/cells/irb120/jobs", Some(ARM_MOVES));
    assert_eq!(code, 202, "{arm}");
    let (code, gait) = request(&server, "POST", "/api/cells/sloth/jobs", None);
    assert_eq!(code, 202, "{gait}");
    both_run_then_end(&server, Duration::from_secs(40));
    for (cell, job, joints) in [
        ("irb120", "joint_waypoints", 6),
        ("sloth", "gait straight", 26),
    ] {
        let (_, status) = request(&server, "GET", &format!("/api/cells/{cell}/status"), None);
        let report = &status["last"]["report"];
        assert_eq!(report["outcome"], "completed", "{status}");
        assert_eq!(report["job"], job, "{status}");
        assert_eq!(report["limit_violations"], 0, "{status}");
        let log = rigbridge::log::read_log(std::path::Path::new(
            report["log"]["path"].as_str().unwrap(),
        ))
        .unwrap();
        assert_eq!(log.rig, cell);
        assert_eq!(log.joint_names.len(), joints, "{:?}", log.joint_names);
        assert!(
            log.states.len() > 250,
            "{cell}: {} states",
            log.states.len()
        );
    }
}

#[test]
fn an_unknown_cell_is_404_and_the_cell_routes_need_the_token() {
    let token = "cells-s3cret-token";
    let server = two_cells(&pan_tilt_cell("pan_tilt", "loopback"), Some(token));
    for path in [
        "/api/cells/pan_tilt/jobs",
        "/api/cells/pan_tilt/pause",
        "/api/cells/pan_tilt/resume",
        "/api/cells/pan_tilt/stop",
        "/api/cells/pan_tilt/estop",
        "/api/cells/nowhere/stop",
    ] {
        assert_unauthorized(request_with(&server, "POST", path, ""));
    }
    assert_eq!(
        refused_with(open_live(&server, "/api/cells/pan_tilt/live", &[])),
        401
    );
    let (code, missing) = request(&server, "POST", "/api/cells/nowhere/stop", None);
    assert_eq!(code, 404, "{missing}");
    let message = missing["error"].as_str().unwrap();
    assert!(
        message.contains("nowhere") && message.contains("pan_tilt"),
        "{message}"
    );
    let (code, missing) = request(&server, "GET", "/api/cells/nowhere/status", None);
    assert_eq!(code, 404, "{missing}");
    assert_eq!(
        request(&server, "POST", "/api/cells/pan_tilt/stop", None).0,
        409
    );
    let (mut socket, _) = open_live(
        &server,
        &format!("/api/cells/pan_tilt/live?token={token}"),
        &[],
    )
    .unwrap();
    let scene = next_json(&mut socket);
    assert_eq!(scene["rig"], "pan_tilt", "{scene}");
    assert_eq!(scene["joints"].as_array().unwrap().len(), 3);
    let (mut socket, _) = open_live(&server, &format!("/api/live?token={token}"), &[]).unwrap();
    assert_eq!(next_json(&mut socket)["rig"], "irb120", "the first cell's");
    let mut stream = TcpStream::connect(&server.address).unwrap();
    write!(
        stream,
        "POST /api/cells/pan_tilt/estop HTTP/1.1\r\nHost: {}\r\nAuthorization: Bearer {token}\r\nOrigin: http://evil.example\r\nContent-Length: 0\r\nConnection: close\r\n\r\n",
        server.address
    )
    .unwrap();
    let mut response = String::new();
    stream.read_to_string(&mut response).unwrap();
    assert!(response.starts_with("HTTP/1.1 403"), "{response}");
}

fn refused_at_start(configs: &[&std::path::Path]) -> String {
    let mut args = Vec::new();
    for config in configs {
        args.extend(["--config", config.to_str().unwrap()]);
    }
    let output = serve_command(&args, None)
        .stdin(Stdio::null())
        .output()
        .unwrap();
    assert!(!output.status.success());
    assert!(
        output.stdout.is_empty(),
        "never listened: {:?}",
        output.stdout
    );
    String::from_utf8_lossy(&output.stderr).into_owned()
}

#[test]
fn two_cells_with_one_name_or_one_link_refuse_to_start() {
    let first = pan_tilt_cell("pan_tilt", "loopback");
    let second = pan_tilt_cell("pan_tilt", "loopback");
    let stderr = refused_at_start(&[&first, &second]);
    assert!(stderr.contains("`pan_tilt`"), "{stderr}");
    for file in [&first, &second] {
        assert!(stderr.contains(file.to_str().unwrap()), "{stderr}");
    }
    let first = pan_tilt_cell("left", "tcp://127.0.0.1:7000");
    let second = pan_tilt_cell("right", "tcp://127.0.0.1:7000");
    let stderr = refused_at_start(&[&first, &second]);
    assert!(stderr.contains("tcp://127.0.0.1:7000"), "{stderr}");
    for file in [&first, &second] {
        assert!(stderr.contains(file.to_str().unwrap()), "{stderr}");
    }
}
