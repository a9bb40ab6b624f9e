//! A connection flood against a daemon on 127.0.0.1, shared by `tests/serve_load.rs` and
//! `benches/serve_load.rs`: idle clients (connect, send nothing) and slowloris clients
//! (a request's headers trickled one byte at a time, never finished). Each client opens
//! its connection again as soon as the server closes it, so the load lasts as long as the
//! flood. Also the server process' side of it: spawning `rigbridge serve` under a lowered
//! descriptor limit, counting its descriptors, and timing one `POST` as an operator's
//! `curl` would send it. Owns no assertion: the callers judge.
#![allow(dead_code)]

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::os::unix::process::CommandExt;
use std::process::Command;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

/// What a slowloris client sends, one byte per [`SLOW_BYTE_EVERY`]: a request whose headers
/// never end (the last header line is never terminated).
const SLOW_REQUEST: &[u8] = b"POST /api/jobs HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\nX-Padding: aaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaa";
/// How often a slowloris client sends its next byte.
const SLOW_BYTE_EVERY: Duration = Duration::from_millis(100);
/// A client whose connection could not even be opened waits this long before trying again
/// (the server's accept queue is full).
const RECONNECT_PAUSE: Duration = Duration::from_millis(5);

/// Counts of what the flood did.
#[derive(Default)]
pub struct FloodStats {
    /// Connections opened, idle and slow together.
    pub connects: AtomicU64,
    /// Connections the server closed (or reset).
    pub closed_by_server: AtomicU64,
    /// Bytes the slowloris clients got through.
    pub slow_bytes: AtomicU64,
}

/// A running flood; dropping it closes every connection.
pub struct Flood {
    runtime: Option<tokio::runtime::Runtime>,
    pub stats: Arc<FloodStats>,
}

impl Flood {
    /// Starts `idle` idle and `slow` slowloris clients against `address`.
    pub fn start(address: SocketAddr, idle: usize, slow: usize) -> Flood {
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .enable_all()
            .build()
            .expect("the flood's runtime starts");
        let stats = Arc::new(FloodStats::default());
        for _ in 0..idle {
            runtime.spawn(idle_client(address, stats.clone()));
        }
        for _ in 0..slow {
            runtime.spawn(slow_client(address, stats.clone()));
        }
        Flood {
            runtime: Some(runtime),
            stats,
        }
    }

    pub fn connects(&self) -> u64 {
        self.stats.connects.load(Ordering::Relaxed)
    }

    pub fn closed_by_server(&self) -> u64 {
        self.stats.closed_by_server.load(Ordering::Relaxed)
    }
}

impl Drop for Flood {
    fn drop(&mut self) {
        if let Some(runtime) = self.runtime.take() {
            runtime.shutdown_background();
        }
    }
}

async fn connect(address: SocketAddr, stats: &FloodStats) -> tokio::net::TcpStream {
    loop {
        if let Ok(stream) = tokio::net::TcpStream::connect(address).await {
            stats.connects.fetch_add(1, Ordering::Relaxed);
            return stream;
        }
        tokio::time::sleep(RECONNECT_PAUSE).await;
    }
}

async fn idle_client(address: SocketAddr, stats: Arc<FloodStats>) {
    let mut buffer = [0u8; 512];
    loop {
        let mut stream = connect(address, &stats).await;
        // Sends nothing; reads until the server gives up on it.
        while let Ok(n) = stream.read(&mut buffer).await {
            if n == 0 {
                break;
            }
        }
        stats.closed_by_server.fetch_add(1, Ordering::Relaxed);
    }
}

async fn slow_client(address: SocketAddr, stats: Arc<FloodStats>) {
    loop {
        let mut stream = connect(address, &stats).await;
        let (mut reader, mut writer) = stream.split();
        let mut answer = [0u8; 512];
        // Whatever the server answers (a 408), it ends the trickle: then it closes.
        let trickle = async {
            for byte in SLOW_REQUEST {
                if writer.write_all(std::slice::from_ref(byte)).await.is_err() {
                    return;
                }
                stats.slow_bytes.fetch_add(1, Ordering::Relaxed);
                tokio::time::sleep(SLOW_BYTE_EVERY).await;
            }
            std::future::pending::<()>().await
        };
        tokio::select! {
            _ = trickle => {}
            _ = reader.read(&mut answer) => {}
        }
        stats.closed_by_server.fetch_add(1, Ordering::Relaxed);
    }
}

/// `rigbridge serve` with its descriptor limit (soft and hard) at `nofile`, set in the child
/// before it runs.
pub fn serve_with_nofile(binary: &str, nofile: u64) -> Command {
    let mut command = Command::new(binary);
    let limit = libc::rlimit {
        rlim_cur: nofile,
        rlim_max: nofile,
    };
    // SAFETY: setrlimit is async-signal-safe and touches only the child's own limits.
    unsafe {
        command.pre_exec(move || {
            if libc::setrlimit(libc::RLIMIT_NOFILE, &limit) == 0 {
                Ok(())
            } else {
                Err(std::io::Error::last_os_error())
            }
        });
    }
    command
}

/// Open descriptors of process `pid`.
pub fn open_descriptors(pid: u32) -> usize {
    std::fs::read_dir(format!("/proc/{pid}/fd")).map_or(0, |dir| dir.count())
}

/// One request on a fresh connection, `Connection: close`: the status code and the body
/// (`None`: no whole answer within `timeout`), and how long it took, connecting included.
/// `headers` are extra header lines, each ending in `\r\n`.
pub fn http(
    address: SocketAddr,
    method: &str,
    path: &str,
    headers: &str,
    body: &str,
    timeout: Duration,
) -> (Option<(u16, String)>, Duration) {
    let started = Instant::now();
    let answer = (|| {
        let mut stream = TcpStream::connect_timeout(&address, timeout).ok()?;
        stream.set_read_timeout(Some(timeout)).ok()?;
        stream.set_nodelay(true).ok()?;
        write!(
            stream,
            "{method} {path} HTTP/1.1\r\nHost: {address}\r\n{headers}Content-Length: {}\r\nConnection: close\r\n\r\n{body}",
            body.len()
        )
        .ok()?;
        let mut response = Vec::new();
        stream.read_to_end(&mut response).ok()?;
        let response = String::from_utf8_lossy(&response);
        let status = response.get(9..12)?.parse().ok()?;
        let body = response.split_once("\r\n\r\n").map_or("", |(_, b)| b);
        Some((status, body.to_string()))
    })();
    (answer, started.elapsed())
}

/// `POST path` with an empty body, as an operator's `curl -X POST` sends it.
pub fn timed_post(address: SocketAddr, path: &str, timeout: Duration) -> (Option<u16>, Duration) {
    let (answer, took) = http(address, "POST", path, "", "", timeout);
    (answer.map(|(status, _)| status), took)
}

/// The `q` quantile (0..=1) of `samples`, nearest rank.
pub fn quantile(samples: &[Duration], q: f64) -> Duration {
    let mut sorted = samples.to_vec();
    sorted.sort();
    if sorted.is_empty() {
        return Duration::ZERO;
    }
    let rank = ((q * sorted.len() as f64).ceil() as usize).clamp(1, sorted.len());
    sorted[rank - 1]
}
