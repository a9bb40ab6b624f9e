//! `rigbridge serve` under resource attacks, over real sockets on 127.0.0.1: an e-stop
//! answered while 500 idle and 50 slowloris connections hold a daemon whose descriptor
//! limit is 256, which then serves normally; and the live view's WebSocket flooded with
//! unfinished fragmented messages by 16 clients, the daemon's memory (VmHWM, the peak
//! resident size in /proc/PID/status) staying under 64 MB while it closes each with 1009.
//! How fast the e-stop is answered is a figure of `benches/serve_load.rs`, not a test.

use crate::common;
use crate::flood;

use common::serve::{Served, serve_args, start_serve};
use flood::{Flood, http, open_descriptors, serve_with_nofile};
use std::net::{SocketAddr, TcpStream};
use std::process::Stdio;
use std::time::{Duration, Instant};

/// The load: idle and slow connections, and the descriptor limit.
const IDLE: usize = 500;
const SLOW: usize = 50;
const NOFILE: u64 = 256;
/// How long a request may take and still count as answered (a real e-stop button gives up
/// far sooner; this only separates "answered" from "never").
const ANSWERED_WITHIN: Duration = Duration::from_secs(5);
/// The memory bound while 16 clients send unfinished WebSocket messages.
const MEMORY_LIMIT_KB: u64 = 64 * 1024;
const WS_CLIENTS: usize = 16;
/// What each flooding client tries to send per connection: 16 of them, unbounded, would
/// hold 256 MB, four times the limit.
const WS_BYTES_PER_CONNECTION: usize = 16 << 20;
/// A continuation frame: under the server's frame limit, so only the message limit stops it.
const WS_FRAME_BYTES: usize = 4000;
const WS_FLOOD_FOR: Duration = Duration::from_secs(4);

struct Server {
    daemon: Served,
    address: SocketAddr,
}

impl Server {
    fn pid(&self) -> u32 {
        self.daemon.child.id()
    }

    fn alive(&mut self) -> bool {
        matches!(self.daemon.child.try_wait(), Ok(None))
    }
}

/// The daemon on the shipped config (wall clock), with its descriptor limit at `nofile`.
fn start(name: &str, nofile: Option<u64>) -> Server {
    let runs = std::env::temp_dir().join(format!("rigbridge-load-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&runs);
    let binary = env!("CARGO_BIN_EXE_rigbridge");
    let mut command = match nofile {
        Some(nofile) => serve_with_nofile(binary, nofile),
        None => std::process::Command::new(binary),
    };
    serve_args(&mut command, &runs)
        .args(["--foxglove-port", "0"])
        .stderr(Stdio::null());
    let daemon = start_serve(&mut command);
    let address = daemon
        .address
        .parse()
        .unwrap_or_else(|e| panic!("not an address: {}: {e}", daemon.address));
    Server { daemon, address }
}

fn wait_until(what: &str, timeout: Duration, mut done: impl FnMut() -> bool) {
    let deadline = Instant::now() + timeout;
    while !done() {
        assert!(Instant::now() < deadline, "timed out waiting for {what}");
        std::thread::sleep(Duration::from_millis(20));
    }
}

const JSON: &str = "Content-Type: application/json\r\n";

/// `METHOD PATH` with `headers` and no body to `server`: its status code and body, which
/// must come within [`ANSWERED_WITHIN`]; fails with `what` where they do not.
#[track_caller]
fn answered(server: &Server, method: &str, path: &str, headers: &str, what: &str) -> (u16, String) {
    let (answer, _) = http(server.address, method, path, headers, "", ANSWERED_WITHIN);
    answer.expect(what)
}

fn status(server: &Server) -> serde_json::Value {
    let (code, body) = answered(server, "GET", "/api/status", "", "status answered");
    assert_eq!(code, 200, "{body}");
    serde_json::from_str(&body).unwrap()
}

#[test]
fn an_estop_is_answered_under_500_idle_and_50_slow_connections_at_256_descriptors() {
    let mut server = start("estop", Some(NOFILE));
    let limits = std::fs::read_to_string(format!("/proc/{}/limits", server.pid())).unwrap();
    let line = limits
        .lines()
        .find(|l| l.starts_with("Max open files"))
        .unwrap();
    assert_eq!(
        line.split_whitespace().nth(3),
        Some(NOFILE.to_string().as_str()),
        "{line}"
    );
    let flood = Flood::start(server.address, IDLE, SLOW);
    // The load is real: every client connected, and the server holds as many connections
    // as its descriptors allow, closing the oldest for newcomers.
    // (The count of held descriptors swings as the server closes the oldest and the flood
    // reconnects: the load is real once it has been seen at 150 or more.)
    let mut held = 0;
    wait_until(
        "the flood to connect and the server to hold 150 descriptors",
        Duration::from_secs(30),
        || {
            held = held.max(open_descriptors(server.pid()));
            flood.connects() >= (IDLE + SLOW) as u64
                && flood.closed_by_server() >= 100
                && held >= 150
        },
    );

    let (code, body) = answered(
        &server,
        "POST",
        "/api/jobs",
        JSON,
        "a job submitted under load is answered",
    );
    assert_eq!(code, 202, "{body}");
    let id = serde_json::from_str::<serde_json::Value>(&body).unwrap()["id"].clone();
    let (code, body) = answered(
        &server,
        "POST",
        "/api/estop",
        "",
        "the e-stop under load is answered",
    );
    // A 409 here means the job had already ended: the cell's status says how.
    let why = (code != 200).then(|| status(&server));
    assert_eq!(code, 200, "{body}; the cell: {why:?}");
    assert_eq!(
        serde_json::from_str::<serde_json::Value>(&body).unwrap()["id"],
        id
    );
    // Again and again: with the job gone, each is a 409, answered.
    for _ in 0..20 {
        let (code, body) = answered(
            &server,
            "POST",
            "/api/estop",
            "",
            "every e-stop under load is answered",
        );
        assert!(code == 200 || code == 409, "{code} {body}");
    }
    assert!(
        open_descriptors(server.pid()) <= NOFILE as usize,
        "over the limit?"
    );
    drop(flood);

    // Afterwards the daemon is up and serves as usual: the job ended e-stopped, a reset
    // clears the latched e-stop, and the next job runs.
    assert!(server.alive(), "the daemon died under load");
    wait_until("the e-stopped job to end", Duration::from_secs(10), || {
        status(&server)["state"] == "idle"
    });
    let last = status(&server);
    assert_eq!(last["last"]["report"]["outcome"], "e_stopped", "{last}");
    assert_eq!(
        answered(&server, "POST", "/api/reset", JSON, "reset answered").0,
        200
    );
    assert_eq!(
        answered(&server, "POST", "/api/jobs", JSON, "a job after the load").0,
        202
    );
    wait_until("the next job to run", Duration::from_secs(10), || {
        status(&server)["state"] == "running"
    });
    assert_eq!(
        answered(&server, "POST", "/api/stop", "", "stop answered").0,
        200
    );
    assert!(server.alive());
}

// --------------------------------------------------------------- live view --

type LiveSocket = tungstenite::WebSocket<tungstenite::stream::MaybeTlsStream<TcpStream>>;

fn open_live(address: SocketAddr) -> Option<LiveSocket> {
    tungstenite::connect(format!("ws://{address}/api/live"))
        .ok()
        .map(|(socket, _)| socket)
}

fn frame(first: bool) -> tungstenite::Message {
    use tungstenite::protocol::frame::Frame;
    use tungstenite::protocol::frame::coding::{Data, OpCode};
    let opcode = OpCode::Data(if first { Data::Text } else { Data::Continue });
    tungstenite::Message::Frame(Frame::message(vec![b'x'; WS_FRAME_BYTES], opcode, false))
}

/// One flooding client: an unfinished message as fast as the socket takes it, up to
/// [`WS_BYTES_PER_CONNECTION`], on a new connection each time the server closes one.
fn flood_live(address: SocketAddr, until: Instant) -> usize {
    let mut connections = 0;
    while Instant::now() < until {
        let Some(mut socket) = open_live(address) else {
            std::thread::sleep(Duration::from_millis(10));
            continue;
        };
        connections += 1;
        for k in 0..WS_BYTES_PER_CONNECTION / WS_FRAME_BYTES {
            if socket.send(frame(k == 0)).is_err() || Instant::now() >= until {
                break;
            }
        }
    }
    connections
}

/// A message one frame past the limit, never finished: the close code the server sends.
fn close_code_past_the_limit(address: SocketAddr) -> Option<u16> {
    let mut socket = open_live(address)?;
    socket.send(frame(true)).ok()?;
    socket.send(frame(false)).ok()?;
    loop {
        match socket.read() {
            Ok(tungstenite::Message::Close(close)) => return close.map(|c| u16::from(c.code)),
            Ok(_) => {}
            Err(_) => return None,
        }
    }
}

/// A `kB` field of /proc/PID/status.
fn status_kb(pid: u32, field: &str) -> u64 {
    let text = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    let line = text.lines().find(|l| l.starts_with(field)).unwrap();
    line.split_whitespace().nth(1).unwrap().parse().unwrap()
}

#[test]
fn sixteen_clients_sending_unfinished_websocket_messages_keep_the_daemon_under_64_mb() {
    let mut server = start("ws", None);
    let address = server.address;
    let before_kb = status_kb(server.pid(), "VmRSS:");
    let until = Instant::now() + WS_FLOOD_FOR;
    let clients: Vec<_> = (0..WS_CLIENTS)
        .map(|_| std::thread::spawn(move || flood_live(address, until)))
        .collect();
    let mut peak_kb = 0;
    while Instant::now() < until {
        peak_kb = peak_kb.max(status_kb(server.pid(), "VmRSS:"));
        std::thread::sleep(Duration::from_millis(20));
    }
    let connections: usize = clients.into_iter().map(|c| c.join().unwrap()).sum();
    let hwm_kb = status_kb(server.pid(), "VmHWM:");
    eprintln!(
        "VmRSS before {before_kb} kB, sampled peak {peak_kb} kB, VmHWM {hwm_kb} kB; \
         {connections} flooding connections"
    );
    assert!(
        connections >= WS_CLIENTS,
        "only {connections} connections opened"
    );
    assert!(
        hwm_kb < MEMORY_LIMIT_KB,
        "the daemon's peak resident memory was {hwm_kb} kB"
    );
    assert_eq!(close_code_past_the_limit(address), Some(1009));
    assert!(server.alive(), "the daemon died");
    // A well-behaved page is still served: the scene, then frames.
    let mut page = open_live(address).expect("a page connects after the flood");
    let first = page.read().expect("the scene");
    assert!(first.is_text(), "{first:?}");
}
