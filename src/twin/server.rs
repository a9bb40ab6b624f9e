//! The twin as a separate process: the controller side of the wire protocol over a byte
//! transport (TCP server, serial port or pty). Each cycle it reads whatever arrived,
//! applies the commands, advances the twin and answers with feedback. When the link is
//! lost it holds at once (the watchdog covers transports without a connection notion).
//! It prints one line per event (connected, lost, holding, fault) for people and tests.

use super::Twin;
use crate::clock::Clock;
use crate::protocol::codec::{FrameDecoder, Hello, Message, encode_frame};
use crate::protocol::{Command, ControllerStatus};
use std::io::{ErrorKind, Read, Write};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

/// How often a port without a peer looks for one.
pub const DETACHED_POLL: Duration = Duration::from_millis(1);

/// The Hello a twin of `rig` sends each new peer.
pub fn hello_for_rig(rig: &crate::rig::Rig, period_s: f64, watchdog_cycles: u32) -> Hello {
    Hello {
        axis_names: rig.joint_names().map(String::from).collect(),
        lower: rig.joints.iter().map(|j| j.limits.lower).collect(),
        upper: rig.joints.iter().map(|j| j.limits.upper).collect(),
        max_speed: rig.joints.iter().map(|j| j.limits.max_speed).collect(),
        cycle_us: (period_s * 1e6).round() as u32,
        watchdog_cycles,
    }
}

/// A byte transport seen from the controller: non-blocking reads, whole-frame writes.
pub trait ControllerPort {
    /// Makes sure a peer is attached if the transport has such a notion (accepts a TCP
    /// client); returns whether one is.
    fn attached(&mut self) -> bool;
    /// Waits up to `timeout` for bytes; Ok(0) when none came. Err when the link broke.
    fn read_within(&mut self, buffer: &mut [u8], timeout: Duration) -> std::io::Result<usize>;
    fn write_frame(&mut self, frame: &[u8]) -> std::io::Result<()>;
    /// Forget the peer after a failure.
    fn detach(&mut self);
    fn describe(&self) -> String;
}

/// TCP: one client at a time; a new client replaces a lost one.
pub struct TcpPort {
    listener: std::net::TcpListener,
    client: Option<std::net::TcpStream>,
}

impl TcpPort {
    pub fn bind(address: &str) -> std::io::Result<Self> {
        let listener = std::net::TcpListener::bind(address)?;
        listener.set_nonblocking(true)?;
        Ok(Self {
            listener,
            client: None,
        })
    }

    pub fn local_address(&self) -> std::io::Result<std::net::SocketAddr> {
        self.listener.local_addr()
    }
}

impl ControllerPort for TcpPort {
    fn attached(&mut self) -> bool {
        if self.client.is_none()
            && let Ok((stream, _)) = self.listener.accept()
        {
            let _ = stream.set_nodelay(true);
            self.client = Some(stream);
        }
        self.client.is_some()
    }

    fn read_within(&mut self, buffer: &mut [u8], timeout: Duration) -> std::io::Result<usize> {
        let Some(client) = &mut self.client else {
            std::thread::sleep(timeout.min(DETACHED_POLL));
            return Ok(0);
        };
        client.set_read_timeout(Some(timeout.max(Duration::from_micros(1))))?;
        match client.read(buffer) {
            Ok(0) => Err(std::io::Error::new(
                ErrorKind::UnexpectedEof,
                "peer closed the connection",
            )),
            Ok(n) => Ok(n),
            Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => Ok(0),
            Err(e) => Err(e),
        }
    }

    fn write_frame(&mut self, frame: &[u8]) -> std::io::Result<()> {
        let Some(client) = &mut self.client else {
            return Ok(());
        };
        // A frame that does not fit the socket buffer means the peer stopped reading.
        match client.write(frame) {
            Ok(n) if n == frame.len() => Ok(()),
            Ok(_) => Err(std::io::Error::new(
                ErrorKind::WriteZero,
                "peer stopped reading",
            )),
            Err(e) => Err(e),
        }
    }

    fn detach(&mut self) {
        self.client = None;
    }

    fn describe(&self) -> String {
        self.listener
            .local_addr()
            .map_or_else(|_| "tcp".into(), |a| format!("tcp://{a}"))
    }
}

/// What the twin process did, for its exit summary.
#[derive(Debug, Default, Clone, Copy)]
pub struct TwinServeCounters {
    pub cycles: u64,
    pub frames_received: u64,
    pub crc_errors: u64,
    pub malformed: u64,
    pub connections: u64,
    pub link_losses: u64,
}

/// Runs the controller loop until `stop` is set. `hello` is sent to each new peer.
///
/// The twin advances one cycle per target, as soon as the target arrives, and answers at
/// once: command-to-feedback latency is the transport's, not up to a cycle more. Without
/// targets it still advances every `period` (1.5 periods after the last target), so the
/// watchdog and holds run on time.
pub fn serve_twin(
    twin: &mut Twin,
    port: &mut dyn ControllerPort,
    hello: &Hello,
    period: Duration,
    clock: &dyn Clock,
    stop: &AtomicBool,
    mut say: impl FnMut(&str),
) -> TwinServeCounters {
    let mut session = Session {
        counters: TwinServeCounters::default(),
        decoder: FrameDecoder::default(),
        frame: Vec::with_capacity(1024),
        attached: false,
        last_status: twin.status(),
    };
    let mut buffer = [0u8; 4096];
    let mut next_tick = clock.now() + period;
    while !stop.load(Ordering::SeqCst) {
        session.attach(port, hello, &mut say);
        let wait = next_tick.saturating_sub(clock.now()).min(period);
        match port.read_within(&mut buffer, wait) {
            Ok(n) => session.decoder.push(&buffer[..n]),
            Err(e) => session.lose(twin, port, &mut say, &e.to_string()),
        }
        let targeted = session.attached && session.apply(twin, port, &mut say);
        let now = clock.now();
        if targeted {
            next_tick = now + period + period / 2;
        } else if now >= next_tick {
            session.tick(twin, port, &mut say);
            next_tick += period;
        }
    }
    session.counters
}

struct Session {
    counters: TwinServeCounters,
    decoder: FrameDecoder,
    frame: Vec<u8>,
    attached: bool,
    last_status: ControllerStatus,
}

impl Session {
    fn attach(&mut self, port: &mut dyn ControllerPort, hello: &Hello, say: &mut impl FnMut(&str)) {
        let attached = port.attached();
        if attached && !self.attached {
            self.counters.connections += 1;
            self.decoder = FrameDecoder::default();
            say(&format!("connected at cycle {}", self.counters.cycles));
            self.frame.clear();
            if encode_frame(&Message::Hello(hello.clone()), &mut self.frame).is_ok()
                && port.write_frame(&self.frame).is_err()
            {
                port.detach();
                self.attached = false;
                return;
            }
        }
        self.attached = attached;
    }

    /// Hands every decoded command to the twin; each target is one cycle, answered at once
    /// (two targets that arrive together are still two cycles, two answers). True when one
    /// was a target.
    fn apply(
        &mut self,
        twin: &mut Twin,
        port: &mut dyn ControllerPort,
        say: &mut impl FnMut(&str),
    ) -> bool {
        let mut targeted = false;
        while let Some(message) = self.decoder.next_message() {
            self.counters.frames_received += 1;
            if let Message::Command(command) = message {
                twin.handle(&command);
                if matches!(command, Command::Target(_)) {
                    targeted = true;
                    self.tick(twin, port, say);
                }
            }
        }
        let decoded = self.decoder.counters();
        self.counters.crc_errors = decoded.crc_errors;
        self.counters.malformed = decoded.malformed;
        targeted
    }

    fn tick(&mut self, twin: &mut Twin, port: &mut dyn ControllerPort, say: &mut impl FnMut(&str)) {
        self.counters.cycles += 1;
        let feedback = twin.tick();
        if self.attached {
            self.frame.clear();
            let sent = encode_frame(&Message::Feedback(feedback), &mut self.frame).is_ok()
                && port.write_frame(&self.frame).is_ok();
            if !sent {
                self.lose(twin, port, say, "write failed");
            }
        }
        if feedback.status != self.last_status {
            say(&format!(
                "status {} at cycle {}",
                status_name(feedback.status),
                self.counters.cycles
            ));
            self.last_status = feedback.status;
        }
    }

    fn lose(
        &mut self,
        twin: &mut Twin,
        port: &mut dyn ControllerPort,
        say: &mut impl FnMut(&str),
        why: &str,
    ) {
        twin.handle(&Command::Stop);
        port.detach();
        self.attached = false;
        self.counters.link_losses += 1;
        say(&format!(
            "link lost at cycle {} ({why}): holding",
            self.counters.cycles
        ));
    }
}

fn status_name(status: ControllerStatus) -> String {
    match status {
        ControllerStatus::Ok => "ok".into(),
        ControllerStatus::Holding => "holding".into(),
        ControllerStatus::Fault(fault) => format!("fault {fault:?}"),
    }
}
