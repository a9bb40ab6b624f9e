//! The twin as a separate process: the controller side of protocol version 2
//! (`docs/protocol.md`) over a byte transport (TCP server, serial port or pty, CAN through
//! `can_port`). It owns the session rules: it answers every bridge Hello with its own,
//! sends Feedback every cycle from then on, binds the twin only on a bridge Hello, sends
//! one Fault notice when a fault latches, treats `watchdog` cycles of silence as link loss
//! (and closes a connection silent for [`IDLE_CLOSE`]), and serves one bridge at a time.
//! It logs one event per line (connected, lost, holding, fault) for people and tests (the
//! binary prints them on stdout).
//! It must not judge targets itself: that is the [`Twin`]'s.

use super::Twin;
use crate::clock::Clock;
use crate::protocol::codec::{FaultReport, FrameDecoder, Message, encode_frame};
use crate::protocol::{Command, ControllerStatus, Fault};
use std::io::{ErrorKind, Read, Write};
use std::os::fd::AsRawFd;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

/// How often a port without a peer looks for one.
pub const DETACHED_POLL: Duration = Duration::from_millis(1);
/// A connection that has sent no valid frame for this long is closed, so that a bridge
/// that vanished without closing (or a client that never speaks) frees the twin for the
/// next one. Far above any watchdog, which already made the twin hold.
pub const IDLE_CLOSE: Duration = Duration::from_secs(1);
/// A write that cannot complete within this long means the peer stopped reading: the twin
/// drops it rather than blocking its cycle.
pub const WRITE_TIMEOUT: Duration = Duration::from_millis(20);

/// A byte transport seen from the controller: non-blocking reads, whole-frame writes.
pub trait ControllerPort {
    /// Makes sure a peer is attached if the transport has such a notion (accepts a TCP
    /// client); returns whether one is.
    fn attached(&mut self) -> bool;
    /// Waits up to `timeout` for bytes; Ok(0) when none came. Err when the link broke.
    fn read_within(&mut self, buffer: &mut [u8], timeout: Duration) -> std::io::Result<usize>;
    fn write_frame(&mut self, frame: &[u8]) -> std::io::Result<()>;
    /// Forget the peer after a failure (closes a connection).
    fn detach(&mut self);
    fn describe(&self) -> String;
    /// Whether `detach` ends the transport for the peer (a TCP connection), so that
    /// closing an idle peer makes sense.
    fn has_connections(&self) -> bool {
        false
    }
    /// Which connection is attached: a change while attached is a new peer that replaced
    /// the last one. A transport without connections has one, 0.
    fn connection(&self) -> u64 {
        0
    }
}

/// Whether the peer of `stream` closed its side (or the connection broke), even with its
/// last bytes still unread: such a peer sends nothing more, a newcomer may replace it.
fn peer_closed(stream: &std::net::TcpStream) -> bool {
    let mut poll = libc::pollfd {
        fd: stream.as_raw_fd(),
        events: libc::POLLRDHUP,
        revents: 0,
    };
    // SAFETY: one valid pollfd for the call's duration; a zero timeout never blocks.
    let ready = unsafe { libc::poll(&mut poll, 1, 0) };
    ready > 0 && poll.revents & (libc::POLLRDHUP | libc::POLLHUP | libc::POLLERR) != 0
}

/// Waits until `fd` is readable or `timeout` passes, with the precision of the kernel's
/// high-resolution timers (ppoll). Socket receive timeouts are rounded up to whole
/// scheduler ticks (4 ms here), which would make a 4 ms cycle run at 125 Hz.
pub fn wait_readable(fd: &impl AsRawFd, timeout: Duration) -> std::io::Result<bool> {
    let mut poll = libc::pollfd {
        fd: fd.as_raw_fd(),
        events: libc::POLLIN,
        revents: 0,
    };
    let spec = libc::timespec {
        tv_sec: timeout.as_secs() as libc::time_t,
        tv_nsec: libc::c_long::from(timeout.subsec_nanos() as i32),
    };
    // SAFETY: one valid pollfd for the call's duration, a valid timespec, no signal mask.
    let ready = unsafe { libc::ppoll(&mut poll, 1, &spec, std::ptr::null()) };
    match ready {
        -1 => {
            let error = std::io::Error::last_os_error();
            if error.kind() == ErrorKind::Interrupted {
                Ok(false)
            } else {
                Err(error)
            }
        }
        0 => Ok(false),
        _ => Ok(true),
    }
}

/// TCP: one bridge at a time. A second one gets a Fault notice (busy) and is closed; a new
/// client replaces a lost one, and one whose peer closed its side already (a bridge that
/// gave up on a stalled twin and reconnected: its old connection is still queued here).
pub struct TcpPort {
    listener: std::net::TcpListener,
    client: Option<std::net::TcpStream>,
    busy_frame: Vec<u8>,
    /// Counts the clients taken: a change tells the session a new connection began.
    taken: u64,
}

impl TcpPort {
    pub fn bind(address: &str) -> std::io::Result<Self> {
        let listener = std::net::TcpListener::bind(address)?;
        listener.set_nonblocking(true)?;
        let mut busy_frame = vec![0];
        let busy = Message::Fault(FaultReport {
            fault: Fault::Busy,
            text: "busy: another bridge is connected".into(),
        });
        encode_frame(&busy, &mut busy_frame).map_err(std::io::Error::other)?;
        Ok(Self {
            listener,
            client: None,
            busy_frame,
            taken: 0,
        })
    }

    pub fn local_address(&self) -> std::io::Result<std::net::SocketAddr> {
        self.listener.local_addr()
    }

    /// Tells a newcomer the twin is busy and closes it; never blocks.
    fn refuse(&self, mut stream: std::net::TcpStream) {
        let _ = stream.set_nonblocking(true);
        let _ = stream.write(&self.busy_frame);
        let _ = stream.shutdown(std::net::Shutdown::Both);
    }
}

impl ControllerPort for TcpPort {
    fn attached(&mut self) -> bool {
        while let Ok((stream, _)) = self.listener.accept() {
            if self
                .client
                .as_ref()
                .is_some_and(|client| !peer_closed(client))
            {
                self.refuse(stream);
                continue;
            }
            self.detach();
            let _ = stream.set_nodelay(true);
            let _ = stream.set_write_timeout(Some(WRITE_TIMEOUT));
            self.client = Some(stream);
            self.taken += 1;
        }
        self.client.is_some()
    }

    fn connection(&self) -> u64 {
        self.taken
    }

    fn read_within(&mut self, buffer: &mut [u8], timeout: Duration) -> std::io::Result<usize> {
        let Some(client) = &mut self.client else {
            std::thread::sleep(timeout.min(DETACHED_POLL));
            return Ok(0);
        };
        if !wait_readable(client, timeout)? {
            return Ok(0);
        }
        match client.read(buffer) {
            Ok(0) => Err(std::io::Error::new(
                ErrorKind::UnexpectedEof,
                "peer closed the connection",
            )),
            Ok(n) => Ok(n),
            Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::Interrupted) => Ok(0),
            Err(e) => Err(e),
        }
    }

    fn write_frame(&mut self, frame: &[u8]) -> std::io::Result<()> {
        match &mut self.client {
            Some(client) => client.write_all(frame),
            None => Ok(()),
        }
    }

    fn detach(&mut self) {
        if let Some(client) = self.client.take() {
            let _ = client.shutdown(std::net::Shutdown::Both);
        }
    }

    fn describe(&self) -> String {
        self.listener
            .local_addr()
            .map_or_else(|_| "tcp".into(), |a| format!("tcp://{a}"))
    }

    fn has_connections(&self) -> bool {
        true
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
    pub hellos: u64,
    pub unbound_targets: u64,
}

/// Runs the controller loop until `stop` is set.
///
/// The twin advances one cycle per accepted target, as soon as it arrives, and answers at
/// once: command-to-feedback latency is the transport's, not up to a cycle more. Without
/// targets it still advances every `period` on its own clock (1.5 periods after the last
/// target), so the watchdog and holds run on time and Feedback keeps coming.
pub fn serve_twin(
    twin: &mut Twin,
    port: &mut dyn ControllerPort,
    period: Duration,
    clock: &dyn Clock,
    stop: &AtomicBool,
) -> TwinServeCounters {
    let mut session = Session::new(twin.status(), period);
    let mut buffer = [0u8; 4096];
    let mut next_tick = clock.now() + period;
    while !stop.load(Ordering::SeqCst) {
        session.attach(twin, port, clock.now());
        let wait = next_tick.saturating_sub(clock.now()).min(period);
        match port.read_within(&mut buffer, wait) {
            Ok(n) => session.decoder.push(&buffer[..n]),
            Err(e) => session.lose(twin, port, &e.to_string()),
        }
        let now = clock.now();
        let targeted = session.attached && session.apply(twin, port, now);
        if targeted {
            next_tick = now + period + period / 2;
        } else if now >= next_tick {
            session.tick(twin, port);
            session.check_silence(twin, port, now);
            // Keep to the cycle's grid; after a long stall start afresh rather than race.
            next_tick = (next_tick + period).max(now);
        }
    }
    session.counters.unbound_targets = twin.counters().unbound_targets;
    session.counters
}

struct Session {
    counters: TwinServeCounters,
    decoder: FrameDecoder,
    frame: Vec<u8>,
    attached: bool,
    /// Whether this connection has had a Hello from the twin: Feedback flows only then.
    greeted: bool,
    /// Whether the silence of `watchdog` cycles already counted as link loss.
    silent: bool,
    last_heard: Duration,
    period: Duration,
    last_status: ControllerStatus,
    /// The port's connection this session serves.
    connection: u64,
}

impl Session {
    fn new(status: ControllerStatus, period: Duration) -> Self {
        Self {
            counters: TwinServeCounters::default(),
            decoder: FrameDecoder::default(),
            frame: Vec::with_capacity(1024),
            attached: false,
            greeted: false,
            silent: false,
            last_heard: Duration::ZERO,
            period,
            last_status: status,
            connection: 0,
        }
    }

    fn attach(&mut self, twin: &mut Twin, port: &mut dyn ControllerPort, now: Duration) {
        let attached = port.attached();
        if attached && self.attached && port.connection() != self.connection {
            // The peer closed its side and a new one took its place: the old one is lost.
            self.lost_quietly(twin, "replaced by a new connection");
            self.attached = false;
        }
        self.connection = port.connection();
        if attached && !self.attached {
            self.counters.connections += 1;
            self.decoder = FrameDecoder::default();
            self.greeted = false;
            self.silent = false;
            self.last_heard = now;
            twin.link_lost();
            tracing::info!("connected at cycle {}", self.counters.cycles);
            // A sender sends one 0x00 when the link opens (docs/protocol.md 2.3).
            if port.write_frame(&[0]).is_err() {
                port.detach();
                return;
            }
        }
        self.attached = attached;
    }

    fn send(&mut self, port: &mut dyn ControllerPort, message: &Message) -> bool {
        self.frame.clear();
        encode_frame(message, &mut self.frame).is_ok() && port.write_frame(&self.frame).is_ok()
    }

    /// Hands every decoded message to the twin; each accepted target is one cycle,
    /// answered at once (two targets that arrive together are still two cycles, two
    /// answers). True when one was a target.
    fn apply(&mut self, twin: &mut Twin, port: &mut dyn ControllerPort, now: Duration) -> bool {
        let mut targeted = false;
        while let Some(message) = self.decoder.next_message() {
            self.counters.frames_received += 1;
            self.last_heard = now;
            self.silent = false;
            match message {
                Message::Hello(hello) if !hello.answer => {
                    self.counters.hellos += 1;
                    twin.bridge_hello();
                    self.greeted = self.send(port, &Message::Hello(twin.hello(true)));
                }
                Message::Command(Command::Reset) => self.reset(twin, port),
                Message::Command(command) => {
                    twin.handle(&command);
                    self.announce_fault(twin, port);
                    if matches!(command, Command::Target(_)) {
                        targeted = true;
                        self.tick(twin, port);
                    }
                }
                // A v3 request (a twin told to speak v2 takes it as another version's).
                Message::Io(request) if twin.carries_io() => {
                    twin.handle_io(&request);
                    self.answer_io(twin, port);
                }
                // Feedback, Fault or an answer Hello from the bridge's side: ignored
                // (docs/protocol.md 3).
                _ => {}
            }
        }
        let decoded = self.decoder.counters();
        self.counters.crc_errors = decoded.crc_errors;
        self.counters.malformed = decoded.malformed;
        targeted
    }

    /// docs/protocol.md 6.7: a cleared fault is announced by an unprompted Hello; one that
    /// cannot be cleared is repeated in a Fault notice. Without a fault, nothing.
    fn reset(&mut self, twin: &mut Twin, port: &mut dyn ControllerPort) {
        if twin.reset() {
            tracing::info!("reset at cycle {}", self.counters.cycles);
            self.greeted = self.send(port, &Message::Hello(twin.hello(false)));
        }
    }

    /// Sends every I/O answer that is due (docs/protocol.md 6.10).
    fn answer_io(&mut self, twin: &mut Twin, port: &mut dyn ControllerPort) {
        while let Some(answer) = twin.take_io_answer() {
            if self.attached {
                self.send(
                    port,
                    &Message::Io(crate::protocol::IoMessage::State(answer)),
                );
            }
        }
    }

    fn announce_fault(&mut self, twin: &mut Twin, port: &mut dyn ControllerPort) {
        if let Some(notice) = twin.take_fault_notice() {
            self.send(port, &Message::Fault(notice));
        }
    }

    fn tick(&mut self, twin: &mut Twin, port: &mut dyn ControllerPort) {
        self.counters.cycles += 1;
        let feedback = twin.tick();
        if self.attached && self.greeted && !self.send(port, &Message::Feedback(feedback)) {
            self.lose(twin, port, "write failed");
        }
        self.answer_io(twin, port);
        if feedback.status != self.last_status {
            tracing::info!(
                "status {} at cycle {}",
                status_name(feedback.status),
                self.counters.cycles
            );
            self.last_status = feedback.status;
        }
    }

    /// `watchdog` cycles without a valid frame are link loss (hold, unbound); a
    /// connection silent for [`IDLE_CLOSE`] is closed.
    fn check_silence(&mut self, twin: &mut Twin, port: &mut dyn ControllerPort, now: Duration) {
        if !self.attached {
            return;
        }
        let quiet = now.saturating_sub(self.last_heard);
        let watchdog = self.period * twin.settings().watchdog_cycles.max(1);
        if !self.silent && quiet >= watchdog {
            self.silent = true;
            twin.link_lost();
            tracing::warn!(
                "silent for {} ms at cycle {}: holding",
                quiet.as_millis(),
                self.counters.cycles
            );
            // Unbound now: say so, so that a bridge that still hears us knows its targets
            // will be dropped until its Hello (docs/protocol.md 6.5).
            if self.greeted {
                self.send(port, &Message::Hello(twin.hello(false)));
            }
        }
        if port.has_connections() && quiet >= IDLE_CLOSE {
            self.lose(twin, port, "idle connection closed");
        }
    }

    fn lose(&mut self, twin: &mut Twin, port: &mut dyn ControllerPort, why: &str) {
        port.detach();
        self.lost_quietly(twin, why);
    }

    /// The link is lost (the port has dropped the peer already): hold, unbound.
    fn lost_quietly(&mut self, twin: &mut Twin, why: &str) {
        twin.link_lost();
        self.attached = false;
        self.greeted = false;
        self.counters.link_losses += 1;
        tracing::warn!(
            "link lost at cycle {} ({why}): holding",
            self.counters.cycles
        );
    }
}

fn status_name(status: ControllerStatus) -> String {
    match status {
        ControllerStatus::Ok => "ok".into(),
        ControllerStatus::Holding => "holding".into(),
        ControllerStatus::Fault(fault) => format!("fault {fault}"),
    }
}
