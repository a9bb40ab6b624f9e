//! How fast `POST /api/estop` is answered while 500 idle and 50 slowloris connections
//! hold `rigbridge serve`, whose descriptor limit is set to 256 (issue 15's load; target:
//! p99 <= 50 ms over 100 tries). Each try is a fresh connection, as an operator's
//! `curl -X POST` makes, timed from connect to the status line; the first e-stops a
//! running job, the others find none (409): the same route, the same path through the
//! server. Prints p50, p99 and max, and the figures without the flood for comparison.
//! `tests/serve_load.rs` checks that the e-stop is answered at all, and what happens next.
//!
//! `cargo bench --bench serve_load`

#[path = "../tests/common/flood.rs"]
mod flood;

use flood::{Flood, http, open_descriptors, quantile, serve_with_nofile, timed_post};
use std::io::{BufRead, BufReader};
use std::net::SocketAddr;
use std::process::Stdio;
use std::time::{Duration, Instant};

const IDLE: usize = 500;
const SLOW: usize = 50;
const NOFILE: u64 = 256;
const TRIES: usize = 100;
/// Between tries: an operator does not hammer the button.
const PAUSE: Duration = Duration::from_millis(20);
/// An e-stop not answered within this counts as unanswered.
const GIVE_UP: Duration = Duration::from_secs(5);

fn main() {
    // `cargo bench` passes `--bench`; `cargo test --benches` passes nothing to run it with.
    if !std::env::args().any(|a| a == "--bench") {
        return;
    }
    let runs = std::env::temp_dir().join(format!("rigbridge-bench-load-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&runs);
    let mut child = serve_with_nofile(env!("CARGO_BIN_EXE_rigbridge"), NOFILE)
        .args(["serve", "--port", "0", "--runs-dir"])
        .arg(&runs)
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .env_remove("RIGBRIDGE_TOKEN")
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("rigbridge serve starts");
    let mut line = String::new();
    BufReader::new(child.stdout.take().expect("stdout"))
        .read_line(&mut line)
        .expect("its address");
    let address: SocketAddr = line
        .trim()
        .trim_start_matches("http://")
        .trim_end_matches('/')
        .parse()
        .expect("an address");

    let quiet = tries(address);
    report("no load", &quiet);

    let flood = Flood::start(address, IDLE, SLOW);
    let deadline = Instant::now() + Duration::from_secs(30);
    while flood.connects() < (IDLE + SLOW) as u64 && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(20));
    }
    std::thread::sleep(Duration::from_secs(1));
    let held = open_descriptors(child.id());
    let (started, _) = http(
        address,
        "POST",
        "/api/jobs",
        "Content-Type: application/json\r\n",
        "",
        GIVE_UP,
    );
    let loaded = tries(address);
    println!(
        "flood: {} connections opened, {} closed by the server; server descriptors {held} \
         (limit {NOFILE}); job started: {}",
        flood.connects(),
        flood.closed_by_server(),
        started.map_or("no answer".to_string(), |(code, _)| code.to_string()),
    );
    report(
        &format!("{IDLE} idle + {SLOW} slow connections, {NOFILE} descriptors"),
        &loaded,
    );
    drop(flood);
    let _ = child.kill();
    let _ = child.wait();
    let _ = std::fs::remove_dir_all(&runs);
}

/// [`TRIES`] e-stops: each one's status (`None`: unanswered) and time.
fn tries(address: SocketAddr) -> Vec<(Option<u16>, Duration)> {
    (0..TRIES)
        .map(|_| {
            let answer = timed_post(address, "/api/estop", GIVE_UP);
            std::thread::sleep(PAUSE);
            answer
        })
        .collect()
}

fn report(label: &str, tries: &[(Option<u16>, Duration)]) {
    // An unanswered try counts as at least GIVE_UP, never as fast.
    let times: Vec<Duration> = tries
        .iter()
        .map(|(code, took)| {
            if code.is_some() {
                *took
            } else {
                (*took).max(GIVE_UP)
            }
        })
        .collect();
    let answered = tries.iter().filter(|(code, _)| code.is_some()).count();
    let ms = |d: Duration| d.as_secs_f64() * 1e3;
    println!(
        "estop_latency [{label}]: {} of {} answered; p50 {:.2} ms, p99 {:.2} ms, max {:.2} ms \
         (target p99 <= 50 ms)",
        answered,
        tries.len(),
        ms(quantile(&times, 0.5)),
        ms(quantile(&times, 0.99)),
        ms(quantile(&times, 1.0)),
    );
}
