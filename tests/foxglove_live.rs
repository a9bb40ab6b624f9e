//! `rigbridge serve`'s live Foxglove server, against clients we did not write: PyPI's
//! `websockets` speaking ws-protocol (tests/peers/foxglove_ws.py: serverInfo, advertise,
//! subscribe, decoding with the advertised protobuf schemas, fetchAsset, a refused publish,
//! an oversized message) while a job streams at 250 Hz, and tungstenite for the topics of
//! two cells. Also the settings: `foxglove_port = 0` turns it off, and off loopback it is
//! refused without `foxglove_allow_remote`. Traffic only ever goes to 127.0.0.1.

use crate::common;

use common::cli::{assert_succeeded_as, numbers};
use common::serve::{Served, request_json, serve_args, start_serve};
use common::{irb120, repo_path};
use rigbridge::daemon::config::load_run_settings;
use rigbridge::rig::{rig_from_urdf, rig_from_urdf_to};
use rigbridge::server::{FOXGLOVE_BACKLOG, FOXGLOVE_IDLE_TIMEOUT};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

/// The issue's figure: live /tf at 30 messages a second or more while a job streams.
const MIN_LIVE_TF_RATE_HZ: f64 = 30.0;
/// /tf and our FK of the /joint_states of the same stamp agree to rounding at tool0.
const MAX_TOOL_DEVIATION_M: f64 = 1e-9;
/// How long the peer counts.
const WINDOW_S: f64 = 3.0;
/// A five-lap star: about 17 s at 250 Hz, longer than the peer's start and window.
const LONG_STAR: &str = r#"{"job": {"kind": "wall_figure", "wall_x_m": 0.45, "centre_yz_m": [0.0, 0.45], "radius_m": 0.12, "laps": 5}}"#;

/// The Python with websockets and protobuf (RIGBRIDGE_FOXGLOVE_PYTHON, set by
/// scripts/test.sh); on CI a missing peer fails.
fn peer_python() -> Option<String> {
    match common::peer_python(
        "RIGBRIDGE_FOXGLOVE_PYTHON",
        "websockets, google.protobuf.message_factory",
        "websockets and protobuf",
    ) {
        Ok(python) => Some(python),
        Err(reason) if std::env::var("CI").as_deref() == Ok("true") => {
            panic!("CI must test the live server against PyPI's websockets: {reason}")
        }
        Err(reason) => {
            println!("skipping the websockets peer test: {reason}");
            None
        }
    }
}

fn scratch(name: &str) -> PathBuf {
    common::scratch_dir("fxlive", name)
}

/// A port nothing listens on right now.
fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

fn serve(dir: &Path, args: &[&str]) -> Served {
    let mut command = Command::new(env!("CARGO_BIN_EXE_rigbridge"));
    serve_args(&mut command, &dir.join("runs"))
        .args(["--clock", "wall"])
        .args(args)
        .stderr(Stdio::null());
    let server = start_serve(&mut command);
    // The API answers once the daemon runs, and it binds the Foxglove port before that.
    let (code, _) = call(&server, "GET", "/api/status", "");
    assert_eq!(code, 200);
    server
}

/// One HTTP/1.1 request to the control API; the status and the JSON body.
fn call(server: &Served, method: &str, path: &str, body: &str) -> (u16, serde_json::Value) {
    request_json(&server.address, method, path, "", body)
}

/// The handshake a tungstenite client gets: serverInfo and advertise, or the refusal.
fn handshake(port: u16) -> Result<(serde_json::Value, serde_json::Value), tungstenite::Error> {
    use tungstenite::client::IntoClientRequest;
    let mut request = format!("ws://127.0.0.1:{port}/").into_client_request()?;
    request.headers_mut().insert(
        "Sec-WebSocket-Protocol",
        "foxglove.websocket.v1".parse().unwrap(),
    );
    let (mut socket, response) = tungstenite::connect(request)?;
    assert_eq!(
        response.headers()["sec-websocket-protocol"],
        "foxglove.websocket.v1"
    );
    let mut text = || -> serde_json::Value {
        serde_json::from_str(socket.read().unwrap().to_text().unwrap()).unwrap()
    };
    let info = text();
    let advertise = text();
    Ok((info, advertise))
}

fn topics(advertise: &serde_json::Value) -> Vec<String> {
    advertise["channels"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c["topic"].as_str().unwrap().to_owned())
        .collect()
}

#[test]
fn a_websockets_client_gets_live_tf_while_a_job_streams() {
    let Some(python) = peer_python() else {
        return;
    };
    let dir = scratch("peer");
    let port = free_port();
    let server = serve(&dir, &["--foxglove-port", &port.to_string()]);
    let (code, job) = call(&server, "POST", "/api/jobs", LONG_STAR);
    assert_eq!(code, 202, "{job}");
    let output = Command::new(&python)
        .arg(repo_path("tests/peers/foxglove_ws.py"))
        .arg(format!("ws://127.0.0.1:{port}/"))
        .arg(WINDOW_S.to_string())
        .args(["base_link", "tool0", "package://rigbridge/irb120.urdf"])
        .output()
        .unwrap();
    assert_succeeded_as(&output, "the peer");
    // The job streamed through the whole window.
    let (_, status) = call(&server, "GET", "/api/status", "");
    assert_eq!(status["state"], "running", "{status}");
    let peer: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();

    assert_eq!(peer["subprotocol"], "foxglove.websocket.v1");
    assert_eq!(peer["server_info"]["op"], "serverInfo");
    assert_eq!(
        peer["server_info"]["capabilities"],
        serde_json::json!(["assets"])
    );
    assert_eq!(
        peer["topics"],
        serde_json::json!(["/tf", "/joint_states", "/scene"])
    );

    let count = peer["tf_count"].as_u64().unwrap();
    let span = peer["tf_span_s"].as_f64().unwrap();
    let rate = (count - 1) as f64 / span;
    let rows = peer["rows"].as_array().unwrap();
    let rig = irb120();
    let mut deviation = 0.0_f64;
    let (mut low, mut high) = (glam::DVec3::splat(f64::MAX), glam::DVec3::splat(f64::MIN));
    for row in rows {
        let tool = numbers(&row["tool"]);
        let tool = glam::DVec3::new(tool[0], tool[1], tool[2]);
        let ours = rig
            .forward(&numbers(&row["positions"]))
            .unwrap()
            .translation;
        deviation = deviation.max((ours - tool).length());
        (low, high) = (low.min(tool), high.max(tool));
    }
    println!(
        "live /tf: {count} messages over {span:.3} s = {rate:.1} Hz while streaming at 250 Hz; \
         {} paired with /joint_states, max deviation from our FK at tool0 {deviation:.2e} m, \
         tool swept {:.3} m",
        rows.len(),
        (high - low).length()
    );
    let largest = &peer["largest_message_bytes"];
    let biggest = ["tf", "joint_states", "scene"]
        .iter()
        .filter_map(|c| largest[*c].as_u64())
        .max()
        .unwrap();
    println!(
        "largest messages (bytes): {largest}; the shared backlog of {FOXGLOVE_BACKLOG} holds at \
         most {} KiB of such messages",
        FOXGLOVE_BACKLOG as u64 * biggest / 1024
    );
    assert!(rate >= MIN_LIVE_TF_RATE_HZ, "live /tf at {rate} Hz");
    assert!(
        span >= WINDOW_S * 0.8,
        "/tf came for {span} s of {WINDOW_S}"
    );
    assert!(
        rows.len() as u64 >= count * 9 / 10,
        "each /tf has its joint states"
    );
    assert!(deviation <= MAX_TOOL_DEVIATION_M, "{deviation} m at tool0");
    assert!(peer["max_quaternion_norm_error"].as_f64().unwrap() < 1e-12);
    assert!((high - low).length() > 0.05, "the tool moves with the star");
    let entities = peer["scene_entities"].as_array().unwrap();
    assert!(
        entities.contains(&"walls".into()),
        "the star's wall: {entities:?}"
    );

    let asset = &peer["asset"];
    assert_eq!(asset["status"], 0, "{asset}");
    assert!(peer["missing_asset"]["status"] == 1);
    assert_eq!(peer["publish_reply"]["level"], 2, "a publish is refused");
    assert_eq!(peer["oversized_close_code"], 1009);
    let _ = std::fs::remove_dir_all(&dir);
}

/// The URDF the server hands out through fetchAsset is the rig's.
#[test]
fn the_urdf_asset_is_the_rig() {
    let dir = scratch("asset");
    let port = free_port();
    let _server = serve(&dir, &["--foxglove-port", &port.to_string()]);
    use tungstenite::client::IntoClientRequest;
    let mut request = format!("ws://127.0.0.1:{port}/")
        .into_client_request()
        .unwrap();
    request.headers_mut().insert(
        "Sec-WebSocket-Protocol",
        "foxglove.websocket.v1".parse().unwrap(),
    );
    let (mut socket, _) = tungstenite::connect(request).unwrap();
    let fetch = r#"{"op": "fetchAsset", "uri": "package://rigbridge/irb120.urdf", "requestId": 5}"#;
    socket.send(tungstenite::Message::text(fetch)).unwrap();
    let data = loop {
        if let tungstenite::Message::Binary(data) = socket.read().unwrap()
            && data[0] == 4
        {
            break data;
        }
    };
    assert_eq!(&data[1..6], &[5, 0, 0, 0, 0], "request 5, success");
    let text = std::str::from_utf8(&data[10..]).unwrap();
    // The chain to tool0 is the rig's; the URDF's one moving leaf is the cell tool's TCP
    // (serve runs config/rigbridge.toml: the pen), the frame jobs are planned for.
    let rig = irb120();
    let to_flange = rig_from_urdf_to(text, Path::new("irb120.urdf"), Some(&rig.tool_frame));
    let at_tcp = rig_from_urdf(text, Path::new("irb120.urdf")).unwrap();
    let settings = load_run_settings(&repo_path("config/rigbridge.toml")).unwrap();
    let q = [0.4, -0.3, 0.2, 1.0, -0.8, 2.5];
    let pairs = [(to_flange.unwrap(), &rig), (at_tcp, &settings.tcp_rig)];
    for (back, ours) in pairs {
        let (a, b) = (back.forward(&q).unwrap(), ours.forward(&q).unwrap());
        assert!(
            (a.translation - b.translation).length() <= 1e-12,
            "{}: URDF {} vs ours {}",
            back.tool_frame,
            a.translation,
            b.translation
        );
    }
    assert_ne!(
        settings.tcp_rig.tool, rig.tool,
        "the shipped settings carry a tool"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn several_cells_get_their_topics_prefixed() {
    let dir = scratch("cells");
    let port = free_port();
    let _server = serve(
        &dir,
        &[
            "--foxglove-port",
            &port.to_string(),
            "--config",
            "config/rigbridge.toml",
            "--config",
            "config/gait-run.toml",
        ],
    );
    let (info, advertise) = handshake(port).unwrap();
    assert_eq!(info["op"], "serverInfo");
    let sloth = load_run_settings(&repo_path("config/gait-run.toml"))
        .unwrap()
        .rig
        .name;
    let expected = [
        "/irb120/tf".to_string(),
        "/irb120/joint_states".into(),
        "/irb120/scene".into(),
        // The sloth is no serial chain: no /tf, as in its logs.
        format!("/{sloth}/joint_states"),
        format!("/{sloth}/scene"),
    ];
    assert_eq!(topics(&advertise), expected);
    for channel in advertise["channels"].as_array().unwrap() {
        assert_eq!(channel["encoding"], "protobuf");
        assert!(
            channel["schemaName"]
                .as_str()
                .unwrap()
                .starts_with("foxglove.")
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// The default run settings with absolute paths and `serve` appended as a `[serve]` table.
fn settings_with_serve(dir: &Path, serve: &str) -> PathBuf {
    let path = dir.join("settings.toml");
    common::write_settings_with_serve(&path, serve);
    path
}

#[test]
fn foxglove_port_0_turns_the_server_off() {
    let dir = scratch("port0");
    let port = free_port();
    let settings = settings_with_serve(&dir, &format!("foxglove_port = {port}"));
    let settings = settings.to_str().unwrap();
    {
        let _on = serve(&dir, &["--config", settings]);
        assert!(
            handshake(port).is_ok(),
            "[serve] foxglove_port = {port} listens"
        );
    }
    let off = serve(&dir, &["--config", settings, "--foxglove-port", "0"]);
    let (code, _) = call(&off, "GET", "/api/status", "");
    assert_eq!(code, 200, "the daemon runs");
    assert!(
        TcpStream::connect(("127.0.0.1", port)).is_err(),
        "nothing listens on {port}"
    );
    drop(off);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn off_loopback_the_foxglove_server_needs_foxglove_allow_remote() {
    let dir = scratch("remote");
    // The settings file: refused on load, naming the key.
    let exposed = settings_with_serve(&dir, "bind = \"0.0.0.0\"\ntoken = \"a-long-random-secret\"");
    let error = load_run_settings(&exposed).unwrap_err().to_string();
    assert!(error.contains("serve.foxglove_allow_remote"), "{error}");
    assert!(error.contains("without authentication"), "{error}");
    for allowed in ["foxglove_port = 0", "foxglove_allow_remote = true"] {
        let file = settings_with_serve(
            &dir,
            &format!("bind = \"0.0.0.0\"\ntoken = \"a-long-random-secret\"\n{allowed}"),
        );
        assert!(load_run_settings(&file).is_ok(), "{allowed} is accepted");
    }
    // `--bind` on the command line: refused before anything listens.
    let output = Command::new(env!("CARGO_BIN_EXE_rigbridge"))
        .args(["serve", "--bind", "0.0.0.0", "--port", "0", "--runs-dir"])
        .arg(dir.join("runs"))
        .current_dir(repo_path(""))
        .env("RIGBRIDGE_TOKEN", "a-long-random-secret")
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(!output.status.success(), "serve must refuse: {stderr}");
    assert!(stderr.contains("foxglove_allow_remote = true"), "{stderr}");
    assert!(stderr.contains("0.0.0.0:8765"), "{stderr}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// A ws-protocol client socket on the Foxglove port, with read timeouts.
type Socket = tungstenite::WebSocket<TcpStream>;

/// A handshake to the Foxglove server on 127.0.0.1:`port` as a browser on `origin` would
/// send it (none: not a browser), to the host name `host`: the socket, or the refusal's
/// status and body.
fn open(port: u16, origin: Option<&str>, host: &str) -> Result<Socket, (u16, String)> {
    use tungstenite::client::IntoClientRequest;
    let mut request = format!("ws://{host}:{port}/")
        .into_client_request()
        .unwrap();
    let headers = request.headers_mut();
    headers.insert(
        "Sec-WebSocket-Protocol",
        "foxglove.websocket.v1".parse().unwrap(),
    );
    if let Some(origin) = origin {
        headers.insert("Origin", origin.parse().unwrap());
    }
    let stream = TcpStream::connect(("127.0.0.1", port)).unwrap();
    stream
        .set_read_timeout(Some(std::time::Duration::from_secs(10)))
        .unwrap();
    match tungstenite::client(request, stream) {
        Ok((socket, _)) => Ok(socket),
        Err(tungstenite::HandshakeError::Failure(tungstenite::Error::Http(response))) => {
            let body = response.body().clone().unwrap_or_default();
            Err((
                response.status().as_u16(),
                String::from_utf8_lossy(&body).into_owned(),
            ))
        }
        Err(e) => panic!("handshake with {origin:?}: {e}"),
    }
}

/// serverInfo and advertise, then a subscription to the first `/joint_states`; its channel.
fn subscribe_joint_states(socket: &mut Socket) -> u64 {
    let mut text = || -> serde_json::Value {
        serde_json::from_str(socket.read().unwrap().to_text().unwrap()).unwrap()
    };
    assert_eq!(text()["op"], "serverInfo");
    let advertise = text();
    let channel = advertise["channels"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["topic"].as_str().unwrap().ends_with("/joint_states"))
        .unwrap()["id"]
        .as_u64()
        .unwrap();
    let subscribe =
        format!(r#"{{"op": "subscribe", "subscriptions": [{{"id": 9, "channelId": {channel}}}]}}"#);
    socket.send(tungstenite::Message::text(subscribe)).unwrap();
    channel
}

/// Message Data frames (opcode 1, subscription 9) read from `socket` within `window`.
fn count_messages(socket: &mut Socket, window: std::time::Duration) -> usize {
    let end = std::time::Instant::now() + window;
    let mut count = 0;
    while std::time::Instant::now() < end {
        if let tungstenite::Message::Binary(data) = socket.read().unwrap()
            && data[0] == 1
            && data[1..5] == [9, 0, 0, 0]
        {
            count += 1;
        }
    }
    count
}

/// The close frame `socket` gets (after the hello), waiting out read timeouts for at most
/// a minute.
fn wait_for_close(socket: &mut Socket) -> (u16, String) {
    let end = std::time::Instant::now() + std::time::Duration::from_secs(60);
    loop {
        match socket.read() {
            Err(tungstenite::Error::Io(e))
                if e.kind() == std::io::ErrorKind::WouldBlock
                    && std::time::Instant::now() < end => {}
            Ok(tungstenite::Message::Close(Some(frame))) => {
                return (u16::from(frame.code), frame.reason.to_string());
            }
            Ok(tungstenite::Message::Close(None)) => return (0, String::new()),
            Ok(_) => {}
            Err(e) => panic!("no close frame: {e}"),
        }
    }
}

/// A page of another site is refused before any message, as on the HTTP API; the Foxglove
/// app's origins, and a client with no origin, get in. A Host the daemon does not answer
/// to (DNS rebinding) is refused too.
#[test]
fn a_foreign_origin_is_refused_and_the_apps_get_in() {
    let dir = scratch("origin");
    let port = free_port();
    let _server = serve(&dir, &["--foxglove-port", &port.to_string()]);
    for foreign in ["https://attacker.example", "null", "http://127.0.0.1:1"] {
        let (code, body) = open(port, Some(foreign), "127.0.0.1")
            .err()
            .unwrap_or_else(|| panic!("{foreign} was let in"));
        println!("Origin {foreign}: {code} {body}");
        assert_eq!(code, 403, "{foreign}: {body}");
        assert!(
            body.contains(foreign) && body.contains("foxglove_origins"),
            "{body}"
        );
    }
    let (code, body) = open(port, None, "attacker.example").err().unwrap();
    assert_eq!(code, 421, "an unknown Host: {body}");
    for app in [Some("https://app.foxglove.dev"), Some("file://"), None] {
        let mut socket = open(port, app, "localhost").unwrap_or_else(|e| panic!("{app:?}: {e:?}"));
        subscribe_joint_states(&mut socket);
        let got = count_messages(&mut socket, std::time::Duration::from_millis(500));
        println!("Origin {app:?}: {got} /joint_states in 0.5 s");
        assert!(got > 5, "{app:?}: {got}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// Idle clients hold no place against the app: with 100 connected (each past the
/// handshake, none subscribing), a newcomer takes the place of the one idle longest, and the
/// app connects and receives messages.
#[test]
fn with_100_idle_clients_the_app_still_connects() {
    let dir = scratch("idle100");
    let port = free_port();
    let _server = serve(&dir, &["--foxglove-port", &port.to_string()]);
    let mut idle = Vec::new();
    for i in 0..100 {
        match open(port, None, "127.0.0.1") {
            Ok(socket) => idle.push(socket),
            Err((code, body)) => panic!("idle client {i} refused: {code} {body}"),
        }
    }
    let start = std::time::Instant::now();
    let mut app = open(port, Some("https://app.foxglove.dev"), "localhost")
        .unwrap_or_else(|e| panic!("the app is refused: {e:?}"));
    subscribe_joint_states(&mut app);
    let got = count_messages(&mut app, std::time::Duration::from_secs(1));
    println!(
        "with 100 idle clients: the app connected and subscribed, {got} /joint_states in its \
         first second ({:.3} s from its handshake)",
        start.elapsed().as_secs_f64()
    );
    assert!(got >= 25, "50 a second expected, got {got}");
    // The first idle client was told why it went.
    let (code, reason) = wait_for_close(&mut idle[0]);
    println!("the first idle client: closed {code}: {reason}");
    assert_eq!(code, 1000);
    assert!(reason.contains("new client"), "{reason}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// A client with no subscription is closed after FOXGLOVE_IDLE_TIMEOUT; a subscribed one
/// that reads stays.
#[test]
fn an_idle_client_is_closed_and_a_subscribed_one_stays() {
    let dir = scratch("idletime");
    let port = free_port();
    let _server = serve(&dir, &["--foxglove-port", &port.to_string()]);
    let mut idle = open(port, None, "127.0.0.1").unwrap();
    let opened = std::time::Instant::now();
    let watcher = std::thread::spawn(move || {
        let closed = wait_for_close(&mut idle);
        (closed, opened.elapsed())
    });
    let mut reader = open(port, None, "127.0.0.1").unwrap();
    subscribe_joint_states(&mut reader);
    let window = FOXGLOVE_IDLE_TIMEOUT + std::time::Duration::from_secs(3);
    let got = count_messages(&mut reader, window);
    let ((code, reason), after) = watcher.join().unwrap();
    println!(
        "idle client closed after {:.1} s ({code}: {reason}); the subscribed one read {got} \
         messages in {:.0} s",
        after.as_secs_f64(),
        window.as_secs_f64()
    );
    assert_eq!(code, 1000);
    assert!(reason.contains("idle"), "{reason}");
    assert!(after >= FOXGLOVE_IDLE_TIMEOUT, "{after:?}");
    assert!(
        after < FOXGLOVE_IDLE_TIMEOUT + std::time::Duration::from_secs(3),
        "{after:?}"
    );
    assert!(got as f64 >= 25.0 * window.as_secs_f64(), "{got}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// `[serve] foxglove_origins` is checked on load (naming the key and the value) and lets its
/// origins in.
#[test]
fn foxglove_origins_are_checked_on_load_and_let_in() {
    let dir = scratch("origins");
    for bad in ["https://x.example/path", "x.example", "https://a b"] {
        let file = settings_with_serve(&dir, &format!("foxglove_origins = [\"{bad}\"]"));
        let error = load_run_settings(&file).unwrap_err().to_string();
        assert!(error.contains("serve.foxglove_origins"), "{error}");
        assert!(error.contains(bad), "{error}");
    }
    let port = free_port();
    let file = settings_with_serve(
        &dir,
        &format!(
            "foxglove_port = {port}\nfoxglove_origins = [\"https://viewer.example:8443\", \"null\"]"
        ),
    );
    let _server = serve(&dir, &["--config", file.to_str().unwrap()]);
    for allowed in [
        "https://viewer.example:8443",
        "null",
        "https://app.foxglove.dev",
    ] {
        assert!(open(port, Some(allowed), "127.0.0.1").is_ok(), "{allowed}");
    }
    let (code, _) = open(port, Some("https://attacker.example"), "127.0.0.1")
        .err()
        .unwrap();
    assert_eq!(code, 403);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_websockets_client_follows_the_program_topic_through_the_demo() {
    let Some(python) = peer_python() else {
        return;
    };
    let dir = scratch("program");
    let port = free_port();
    let server = serve(
        &dir,
        &[
            "--config",
            "config/pick-place.toml",
            "--foxglove-port",
            &port.to_string(),
        ],
    );
    let (code, job) = call(
        &server,
        "POST",
        "/api/jobs",
        &serde_json::json!({ "job": common::two_part_demo_job() }).to_string(),
    );
    assert_eq!(code, 202, "{job}");
    // The two passes take about 7 s; the peer listens through them and past the end.
    let output = Command::new(&python)
        .arg(repo_path("tests/peers/foxglove_program.py"))
        .arg(format!("ws://127.0.0.1:{port}/"))
        .arg("12")
        .output()
        .unwrap();
    assert_succeeded_as(&output, "the peer");
    let peer: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    assert_eq!(peer["channel"]["encoding"], "json", "{}", peer["channel"]);
    assert_eq!(peer["channel"]["schemaEncoding"], "jsonschema");
    assert_eq!(peer["schema"]["title"], "rigbridge.Program");
    let steps: Vec<&str> = peer["steps"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s.as_str().unwrap())
        .collect();
    for expected in [
        "job.steps[2] repeat, pass 0 (slot[0]): job.steps[2].steps[2] grip",
        "job.steps[2] repeat, pass 1 (slot[1]): job.steps[2].steps[8] release",
        "job.steps[3] move_joints to home",
    ] {
        assert!(steps.contains(&expected), "{expected} not among {steps:#?}");
    }
    let last = &peer["last"];
    assert_eq!(last["parts"].as_array().unwrap().len(), 12, "{last}");
    // /scene draws the 12 parts; part_0 moved with the tool (tray to fixture, over 0.4 m
    // apart), part_11 never did.
    let positions = &peer["part_positions"];
    assert_eq!(positions.as_object().unwrap().len(), 12, "{positions}");
    let moved = |id: &str| positions[id].as_array().unwrap().len();
    assert!(moved("part-part_0") > 10, "{}", positions["part-part_0"]);
    assert_eq!(moved("part-part_11"), 1, "{}", positions["part-part_11"]);
    assert_eq!(last["judgement"]["placed"], 2, "{last}");
    println!(
        "/program: {} messages, {} steps seen",
        peer["messages"],
        steps.len()
    );
}
