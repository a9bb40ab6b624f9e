//! A fault-injecting TCP proxy for the tests, on loopback only, between the bridge (which
//! connects to it) and the twin (which it connects to): it closes both sides, black-holes
//! and delays either direction, duplicates and corrupts whole frames (split at the 0x00
//! delimiters of docs/protocol.md 2), and SIGSTOPs the bridge process. It records every
//! frame each side sent, decoded, with the time it reached the proxy and whether it was
//! delivered intact, for the tests to judge the bridge independently of its own report.
//! Owns the bytes between the two processes only: it must not start, stop or judge them.
#![allow(dead_code)]

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rigbridge::protocol::{FrameDecoder, Message};
use std::io::{ErrorKind, Read, Write};
use std::net::{Shutdown, TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use std::sync::mpsc;
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// How often blocked reads and the accept loop look at the stop flag.
const POLL: Duration = Duration::from_millis(5);
/// How long the proxy waits for the twin to drop the previous connection before it opens
/// the next one (the twin serves one bridge at a time and refuses a second as busy).
const TWIN_DETACH_TIMEOUT: Duration = Duration::from_secs(3);

#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum FaultKind {
    Close,
    BlackHole,
    Delay,
    Duplicate,
    Corrupt,
    SigStop,
}

pub const FAULT_KINDS: [FaultKind; 6] = [
    FaultKind::Close,
    FaultKind::BlackHole,
    FaultKind::Delay,
    FaultKind::Duplicate,
    FaultKind::Corrupt,
    FaultKind::SigStop,
];

impl FaultKind {
    pub fn name(self) -> &'static str {
        match self {
            FaultKind::Close => "close",
            FaultKind::BlackHole => "black-hole",
            FaultKind::Delay => "delay",
            FaultKind::Duplicate => "duplicate",
            FaultKind::Corrupt => "corrupt",
            FaultKind::SigStop => "sigstop",
        }
    }
}

/// One fault to inject: which, in which directions (bridge to twin, twin to bridge), and
/// for how long (black-hole, delay, SIGSTOP).
#[derive(Debug, Clone, Copy)]
pub struct Injection {
    pub kind: FaultKind,
    pub up: bool,
    pub down: bool,
    pub millis: u64,
}

impl Injection {
    /// A random fault of `kind` within the ranges of the suite: black-holes 20-300 ms,
    /// delays 5-80 ms, SIGSTOPs 50-300 ms.
    pub fn random(kind: FaultKind, rng: &mut ChaCha8Rng) -> Self {
        let (up, down) = match rng.random_range(0..3) {
            0 => (true, false),
            1 => (false, true),
            _ => (true, true),
        };
        let millis = match kind {
            FaultKind::BlackHole => rng.random_range(20..=300),
            FaultKind::Delay => rng.random_range(5..=80),
            FaultKind::SigStop => rng.random_range(50..=300),
            _ => 0,
        };
        // A frame is duplicated or corrupted in one direction only.
        let one_way = matches!(kind, FaultKind::Duplicate | FaultKind::Corrupt);
        Self {
            kind,
            up,
            down: down && !(one_way && up),
            millis,
        }
    }

    /// The inverse of `describe`: a fault as a failure message prints it.
    pub fn parse(text: &str) -> Option<Self> {
        let words: Vec<&str> = text.split_whitespace().collect();
        let name = *words.first()?;
        let kind = *FAULT_KINDS.iter().find(|k| k.name() == name)?;
        let millis = match words.get(2) {
            Some(&"ms") => words.get(1)?.parse().ok()?,
            _ => 0,
        };
        let (up, down) = match words.last() {
            Some(&"bridge->twin") => (true, false),
            Some(&"twin->bridge") => (false, true),
            Some(&"ways") => (true, true),
            _ => (false, false),
        };
        Some(Self {
            kind,
            up,
            down,
            millis,
        })
    }

    pub fn describe(&self) -> String {
        let dirs = match (self.up, self.down) {
            (true, true) => "both ways",
            (true, false) => "bridge->twin",
            (false, true) => "twin->bridge",
            (false, false) => "-",
        };
        match self.kind {
            FaultKind::Close | FaultKind::SigStop if self.millis == 0 => self.kind.name().into(),
            FaultKind::Close => "close".into(),
            FaultKind::SigStop => format!("sigstop {} ms", self.millis),
            FaultKind::BlackHole | FaultKind::Delay => {
                format!("{} {} ms {}", self.kind.name(), self.millis, dirs)
            }
            _ => format!("{} {}", self.kind.name(), dirs),
        }
    }
}

/// One frame as a side sent it, before the proxy touched it.
#[derive(Debug, Clone)]
pub struct Entry {
    /// When it reached the proxy, since the proxy started.
    pub at: Duration,
    /// Sent by the bridge (true) or the twin.
    pub up: bool,
    /// The connection it travelled on (1, 2, ...).
    pub conn: u32,
    /// `None` for the opening 0x00 and anything that does not decode.
    pub message: Option<Message>,
    /// Forwarded intact (not dropped by a black-hole, not corrupted, connection open).
    pub delivered: bool,
}

#[derive(Default, Clone, Copy)]
struct DirFaults {
    drop_from: Option<Instant>,
    drop_until: Option<Instant>,
    hold_until: Option<Instant>,
    duplicate: u32,
    corrupt: u32,
}

struct Shared {
    epoch: Instant,
    faults: Mutex<[DirFaults; 2]>,
    entries: Mutex<Vec<Entry>>,
    sockets: Mutex<Option<(TcpStream, TcpStream)>>,
    conn: AtomicU32,
    stop: AtomicBool,
    /// How many times the twin said it lost a link (its stdout), fed by the test.
    twin_detached: Arc<AtomicU64>,
    /// When each SIGSTOP ended (SIGCONT), since the proxy started.
    continued: Mutex<Vec<Duration>>,
    rng: Mutex<ChaCha8Rng>,
}

pub struct FaultProxy {
    pub address: String,
    shared: Arc<Shared>,
    accept: Option<JoinHandle<()>>,
}

impl FaultProxy {
    /// Listens on 127.0.0.1 and forwards each connection to `twin` (tcp://127.0.0.1:PORT).
    pub fn start(twin: &str, twin_detached: Arc<AtomicU64>, seed: u64) -> Self {
        let twin = twin.trim_start_matches("tcp://").to_string();
        assert!(twin.starts_with("127.0.0.1:"), "loopback only: {twin}");
        let listener = TcpListener::bind("127.0.0.1:0").expect("a loopback port");
        listener.set_nonblocking(true).unwrap();
        let address = format!("tcp://{}", listener.local_addr().unwrap());
        let shared = Arc::new(Shared {
            epoch: Instant::now(),
            faults: Mutex::new([DirFaults::default(); 2]),
            entries: Mutex::new(Vec::new()),
            sockets: Mutex::new(None),
            conn: AtomicU32::new(0),
            stop: AtomicBool::new(false),
            twin_detached,
            continued: Mutex::new(Vec::new()),
            rng: Mutex::new(ChaCha8Rng::seed_from_u64(seed)),
        });
        let inner = shared.clone();
        let accept = std::thread::spawn(move || accept_loop(&listener, &twin, &inner));
        Self {
            address,
            shared,
            accept: Some(accept),
        }
    }

    pub fn now(&self) -> Duration {
        self.shared.epoch.elapsed()
    }

    /// Targets the bridge has sent so far, and when the latest reached the proxy.
    pub fn targets_seen(&self) -> (usize, Option<Duration>) {
        let entries = self.shared.entries.lock().unwrap();
        let targets = entries.iter().filter(|e| is_target(e));
        let (mut count, mut last) = (0, None);
        for entry in targets {
            count += 1;
            last = Some(entry.at);
        }
        (count, last)
    }

    /// Targets the bridge sent after `since`.
    pub fn targets_since(&self, since: Duration) -> usize {
        let entries = self.shared.entries.lock().unwrap();
        entries
            .iter()
            .rev()
            .take_while(|e| e.at > since)
            .filter(|e| is_target(e))
            .count()
    }

    /// Injects one fault. Returns once it is set up (close, duplicate, corrupt, black-hole
    /// and delay windows) or over (SIGSTOP, which SIGCONTs `bridge_pid` after its time).
    pub fn inject(&self, injection: &Injection, bridge_pid: u32) {
        let now = Instant::now();
        let span = Duration::from_millis(injection.millis);
        match injection.kind {
            FaultKind::Close => self.close(),
            FaultKind::SigStop => {
                let pid = bridge_pid as libc::pid_t;
                // SAFETY: kill(2) on our own child's pid; no memory is shared.
                unsafe { libc::kill(pid, libc::SIGSTOP) };
                std::thread::sleep(span);
                unsafe { libc::kill(pid, libc::SIGCONT) };
                self.shared.continued.lock().unwrap().push(self.now());
            }
            kind => {
                let mut faults = self.shared.faults.lock().unwrap();
                for (index, on) in [injection.up, injection.down].into_iter().enumerate() {
                    if !on {
                        continue;
                    }
                    let dir = &mut faults[index];
                    match kind {
                        FaultKind::BlackHole => {
                            dir.drop_from = Some(now);
                            dir.drop_until = Some(now + span);
                        }
                        FaultKind::Delay => dir.hold_until = Some(now + span),
                        FaultKind::Duplicate => dir.duplicate += 1,
                        FaultKind::Corrupt => dir.corrupt += 1,
                        _ => unreachable!("handled above"),
                    }
                }
            }
        }
    }

    fn close(&self) {
        if let Some((a, b)) = self.shared.sockets.lock().unwrap().take() {
            let _ = a.shutdown(Shutdown::Both);
            let _ = b.shutdown(Shutdown::Both);
        }
    }

    /// Stops forwarding and hands over the record: every frame, and the SIGCONT times.
    pub fn finish(mut self) -> (Vec<Entry>, Vec<Duration>) {
        self.shared.stop.store(true, Ordering::SeqCst);
        self.close();
        if let Some(accept) = self.accept.take() {
            let _ = accept.join();
        }
        let entries = std::mem::take(&mut *self.shared.entries.lock().unwrap());
        let continued = std::mem::take(&mut *self.shared.continued.lock().unwrap());
        (entries, continued)
    }
}

impl Drop for FaultProxy {
    fn drop(&mut self) {
        self.shared.stop.store(true, Ordering::SeqCst);
        self.close();
    }
}

fn is_target(entry: &Entry) -> bool {
    entry.up
        && matches!(
            entry.message,
            Some(Message::Command(rigbridge::protocol::Command::Target(_)))
        )
}

fn accept_loop(listener: &TcpListener, twin: &str, shared: &Arc<Shared>) {
    let mut detaches_expected = 0u64;
    while !shared.stop.load(Ordering::SeqCst) {
        let bridge = match listener.accept() {
            Ok((stream, _)) => stream,
            Err(e) if e.kind() == ErrorKind::WouldBlock => {
                std::thread::sleep(POLL);
                continue;
            }
            Err(_) => return,
        };
        // The twin takes one bridge at a time: wait until it has let the last one go.
        let waited = Instant::now();
        while shared.twin_detached.load(Ordering::SeqCst) < detaches_expected
            && waited.elapsed() < TWIN_DETACH_TIMEOUT
        {
            std::thread::sleep(Duration::from_millis(1));
        }
        let Ok(twin_side) = TcpStream::connect(twin) else {
            return;
        };
        detaches_expected += 1;
        serve_pair(bridge, twin_side, shared);
    }
}

/// Forwards one connection pair until either side closes (or the proxy closes both).
fn serve_pair(bridge: TcpStream, twin: TcpStream, shared: &Arc<Shared>) {
    let conn = shared.conn.fetch_add(1, Ordering::SeqCst) + 1;
    for s in [&bridge, &twin] {
        s.set_nonblocking(false).unwrap();
        s.set_nodelay(true).unwrap();
        s.set_read_timeout(Some(POLL)).unwrap();
    }
    *shared.sockets.lock().unwrap() =
        Some((bridge.try_clone().unwrap(), twin.try_clone().unwrap()));
    let pumps = [
        (bridge.try_clone().unwrap(), twin.try_clone().unwrap(), true),
        (twin, bridge, false),
    ]
    .map(|(from, to, up)| {
        let shared = shared.clone();
        std::thread::spawn(move || pump(from, to, up, conn, &shared))
    });
    for pump in pumps {
        let _ = pump.join();
    }
    shared.sockets.lock().unwrap().take();
}

fn shut(a: &TcpStream, b: &TcpStream) {
    let _ = a.shutdown(Shutdown::Both);
    let _ = b.shutdown(Shutdown::Both);
}

/// Reads `from`, cuts whole frames, records them and hands them to a writer for `to`.
fn pump(mut from: TcpStream, to: TcpStream, up: bool, conn: u32, shared: &Arc<Shared>) {
    let (tx, rx) = mpsc::channel::<(usize, Instant, Vec<u8>)>();
    let writer = {
        let (shared, to, from) = (
            shared.clone(),
            to.try_clone().unwrap(),
            from.try_clone().unwrap(),
        );
        std::thread::spawn(move || write_frames(rx, to, &from, up, &shared))
    };
    let mut decoder = FrameDecoder::default();
    let mut pending = Vec::new();
    let mut buffer = [0u8; 4096];
    loop {
        let n = match from.read(&mut buffer) {
            Ok(0) => break,
            Ok(n) => n,
            Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => {
                if shared.stop.load(Ordering::SeqCst) {
                    break;
                }
                continue;
            }
            Err(_) => break,
        };
        for &byte in &buffer[..n] {
            pending.push(byte);
            if byte != 0 {
                continue;
            }
            let frame = std::mem::take(&mut pending);
            decoder.push(&frame);
            let message = decoder.next_message();
            let arrived = Instant::now();
            let index = {
                let mut entries = shared.entries.lock().unwrap();
                entries.push(Entry {
                    at: arrived - shared.epoch,
                    up,
                    conn,
                    message,
                    delivered: true,
                });
                entries.len() - 1
            };
            if tx.send((index, arrived, frame)).is_err() {
                break;
            }
        }
    }
    shut(&from, &to);
    drop(tx);
    let _ = writer.join();
}

/// Writes frames to `to` through the faults of this direction.
fn write_frames(
    rx: mpsc::Receiver<(usize, Instant, Vec<u8>)>,
    mut to: TcpStream,
    from: &TcpStream,
    up: bool,
    shared: &Arc<Shared>,
) {
    let dir = usize::from(!up);
    for (index, arrived, mut frame) in rx {
        let (faults, copies) = {
            let mut all = shared.faults.lock().unwrap();
            let faults = all[dir];
            let protocol_frame = frame.len() > 1;
            let duplicate = protocol_frame && faults.duplicate > 0;
            let corrupt = protocol_frame && !duplicate && faults.corrupt > 0;
            all[dir].duplicate -= u32::from(duplicate);
            all[dir].corrupt -= u32::from(corrupt);
            let mut faults = faults;
            faults.corrupt = u32::from(corrupt);
            (faults, 1 + usize::from(duplicate))
        };
        let dropped = faults.drop_from.is_some_and(|from| arrived >= from)
            && faults.drop_until.is_some_and(|until| arrived < until);
        if dropped {
            shared.entries.lock().unwrap()[index].delivered = false;
            continue;
        }
        if let Some(until) = faults.hold_until {
            let now = Instant::now();
            if until > now {
                std::thread::sleep(until - now);
            }
        }
        if faults.corrupt > 0 {
            let mut rng = shared.rng.lock().unwrap();
            let byte = rng.random_range(0..frame.len() - 1);
            frame[byte] ^= 1 << rng.random_range(0..8);
            shared.entries.lock().unwrap()[index].delivered = false;
        }
        for _ in 0..copies {
            if to.write_all(&frame).is_err() {
                shared.entries.lock().unwrap()[index].delivered = false;
                shut(from, &to);
                return;
            }
        }
    }
}
