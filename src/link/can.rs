//! CAN link (Linux SocketCAN): the bridge's end of the protocol's CAN mapping
//! (`docs/protocol.md`, section 7). Each command goes out as the frames of
//! [`can_frames`]; the controller's frames are rebuilt into feedback by a [`CanAssembler`],
//! which delivers a multi-frame message only when it is complete and its CRC holds.
//!
//! The session of `docs/protocol.md` 6 is the shared [`BridgeSession`]: a Hello on every
//! open, nothing streamed before the controller's answer, Heartbeats, and silence as link
//! loss. CAN has no connection: the link is open while its socket is open on an interface
//! that is up, and up once the controller has answered. When the interface goes down (or away), the I/O thread closes the socket and reopens
//! it with exponential backoff, like the TCP link reconnects; commands queued meanwhile are
//! discarded, never sent late. The thread runs a current-thread tokio runtime that waits on
//! the command channel and the socket at once, so neither direction adds latency.
//!
//! [`CanBus`] is the socket part on its own, shared with the twin's CAN port. Counters are
//! in CAN frames (`frames_sent`, `frames_received`: 8 and 5 a cycle for 6 axes on classic
//! CAN); gaps and duplicates are counted on the sequence numbers the feedback echoes.

use super::session::{BridgeSession, Due, Outgoing};
use super::{ChannelLink, IoEnds, LinkShared};
use crate::protocol::can::CAN_ID_BLOCK;
use crate::protocol::{
    CanAssembler, CanMapping, CanPayload, CanSender, Command, Hello, Message, can_frames,
};
use socketcan::{
    CanDataFrame, CanFdFrame, CanFdSocket, CanFilter, CanRawFrame, CanSocket, EmbeddedFrame,
    Socket, SocketOptions, StandardId,
};
use std::io::{self, ErrorKind};
use std::os::fd::{AsRawFd, RawFd};
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};
use tokio::io::Interest;
use tokio::io::unix::AsyncFd;

const BACKOFF_INITIAL: Duration = Duration::from_millis(10);
const BACKOFF_MAX: Duration = Duration::from_secs(1);
/// A session shorter than this does not reset the backoff (an interface that flaps).
const STABLE_SESSION: Duration = Duration::from_secs(1);
/// How often the I/O thread looks at the interface's state and the link's closed flag.
const WATCH_PERIOD: Duration = Duration::from_millis(50);
/// How long a frame may wait for room in a full transmit queue before its message is given
/// up (half a cycle at 1 kHz; the receiver then drops the incomplete message).
pub const SEND_PATIENCE: Duration = Duration::from_micros(500);

/// The MTU of an interface that carries CAN FD frames (`struct canfd_frame`).
const CANFD_MTU: usize = 72;
const IFF_UP: u32 = 0x1;

/// A non-blocking SocketCAN raw socket bound to one interface for one side of a mapping:
/// classic (`CanSocket`) or FD (`CanFdSocket`) as the mapping says, receiving only standard
/// data frames in the peer's half of the mapping's identifier block (kernel filters).
pub struct CanBus {
    socket: BusSocket,
    interface: String,
}

enum BusSocket {
    Classic(CanSocket),
    Fd(CanFdSocket),
}

impl CanBus {
    /// Opens `interface` for `mapping`'s sender. Errors name the interface and say what to do:
    /// `NetworkDown` for an interface that exists but is down (worth retrying), `NotFound`
    /// for a missing one, `Unsupported` for a kernel without SocketCAN, `InvalidInput` for
    /// an FD mapping on an interface that cannot carry FD frames.
    pub fn open(interface: &str, mapping: &CanMapping) -> io::Result<Self> {
        Self::open_with(interface, mapping.fd(), &receive_filters(mapping))
    }

    /// Opens `interface` for classic CAN receiving every standard data frame: a CANopen
    /// master or device, which reads the whole bus (NMT, SYNC, EMCY, PDOs, SDOs, heartbeats).
    pub fn open_classic(interface: &str) -> io::Result<Self> {
        // One filter with an empty mask takes every identifier; extended, remote and error
        // frames are skipped on reading.
        Self::open_with(interface, false, &[CanFilter::new(0, 0)])
    }

    fn open_with(interface: &str, fd: bool, filters: &[CanFilter]) -> io::Result<Self> {
        let fail = |kind: ErrorKind, why: String| {
            Err(io::Error::new(kind, format!("can://{interface}: {why}")))
        };
        if interface_up(interface) == Some(false) {
            return fail(ErrorKind::NetworkDown, "the interface is down".into());
        }
        if fd
            && let Some(mtu) = interface_mtu(interface)
            && mtu < CANFD_MTU
        {
            return fail(
                ErrorKind::InvalidInput,
                format!(
                    "MTU {mtu}: not a CAN FD interface, but the mapping is CAN FD \
                     (ip link set {interface} mtu 72, or can_fd = false)"
                ),
            );
        }
        let opened = if fd {
            CanFdSocket::open(interface).map(BusSocket::Fd)
        } else {
            CanSocket::open(interface).map(BusSocket::Classic)
        };
        let socket = match opened {
            Ok(socket) => socket,
            // The interface is looked up first: a kernel without CAN says "no such device".
            Err(e) if e.raw_os_error() == Some(libc::ENODEV) => {
                let e = socketcan_supported().err().unwrap_or(e);
                return fail(kind_of(&e), explain(&e));
            }
            Err(e) => return fail(kind_of(&e), explain(&e)),
        };
        let configured = match &socket {
            BusSocket::Classic(s) => s
                .set_filters(filters)
                .and_then(|()| s.set_nonblocking(true)),
            BusSocket::Fd(s) => s
                .set_filters(filters)
                .and_then(|()| s.set_nonblocking(true)),
        };
        if let Err(e) = configured {
            return fail(e.kind(), format!("cannot configure the socket: {e}"));
        }
        Ok(Self {
            socket,
            interface: interface.to_string(),
        })
    }

    pub fn interface(&self) -> &str {
        &self.interface
    }

    /// Writes one frame. `WouldBlock` when the transmit queue is full (the kernel's
    /// ENOBUFS, or a full socket buffer).
    pub fn send(&self, frame: &CanPayload) -> io::Result<()> {
        let invalid = || io::Error::new(ErrorKind::InvalidInput, "frame does not fit CAN");
        let id = u16::try_from(frame.id)
            .ok()
            .and_then(StandardId::new)
            .ok_or_else(invalid)?;
        let written = match (&self.socket, frame.fd) {
            (BusSocket::Classic(s), false) => {
                s.write_frame(&CanDataFrame::new(id, frame.data()).ok_or_else(invalid)?)
            }
            (BusSocket::Classic(_), true) => return Err(invalid()),
            (BusSocket::Fd(s), false) => {
                s.write_frame(&CanDataFrame::new(id, frame.data()).ok_or_else(invalid)?)
            }
            (BusSocket::Fd(s), true) => {
                s.write_frame(&CanFdFrame::new(id, frame.data()).ok_or_else(invalid)?)
            }
        };
        written.map_err(|e| {
            if e.raw_os_error() == Some(libc::ENOBUFS) {
                io::Error::new(ErrorKind::WouldBlock, e)
            } else {
                e
            }
        })
    }

    /// [`send`](Self::send), retrying a full transmit queue for up to `patience`.
    pub fn send_patiently(&self, frame: &CanPayload, patience: Duration) -> io::Result<()> {
        let deadline = Instant::now() + patience;
        loop {
            match self.send(frame) {
                Err(e) if e.kind() == ErrorKind::WouldBlock && Instant::now() < deadline => {
                    std::thread::sleep(Duration::from_micros(50));
                }
                other => return other,
            }
        }
    }

    /// The next frame waiting, without blocking; `None` when there is none. Frames a
    /// payload cannot describe (extended IDs, remote and error frames) are skipped.
    pub fn try_receive(&self) -> io::Result<Option<CanPayload>> {
        loop {
            let raw = match &self.socket {
                BusSocket::Classic(s) => s.read_raw_frame().map(CanRawFrame::Classic),
                BusSocket::Fd(s) => s.read_raw_frame(),
            };
            match raw {
                Ok(raw) => {
                    if let Some(payload) = payload_of(&raw) {
                        return Ok(Some(payload));
                    }
                }
                Err(e) if e.kind() == ErrorKind::WouldBlock => return Ok(None),
                Err(e) if e.kind() == ErrorKind::Interrupted => {}
                Err(e) => return Err(e),
            }
        }
    }

    /// Waits up to `timeout` until a frame (or an error, such as the interface going down)
    /// is waiting; true when one is.
    pub fn wait_readable(&self, timeout: Duration) -> io::Result<bool> {
        let mut poll = libc::pollfd {
            fd: self.as_raw_fd(),
            events: libc::POLLIN,
            revents: 0,
        };
        let timeout = libc::timespec {
            tv_sec: timeout.as_secs().min(i32::MAX as u64) as libc::time_t,
            tv_nsec: timeout.subsec_nanos() as libc::c_long,
        };
        // SAFETY: one valid pollfd and a valid timespec, both outliving the call.
        let ready = unsafe { libc::ppoll(&mut poll, 1, &timeout, std::ptr::null()) };
        match ready {
            n if n > 0 => Ok(true),
            0 => Ok(false),
            _ => {
                let e = io::Error::last_os_error();
                if e.kind() == ErrorKind::Interrupted {
                    Ok(false)
                } else {
                    Err(e)
                }
            }
        }
    }
}

impl AsRawFd for CanBus {
    fn as_raw_fd(&self) -> RawFd {
        match &self.socket {
            BusSocket::Classic(s) => s.as_raw_fd(),
            BusSocket::Fd(s) => s.as_raw_fd(),
        }
    }
}

fn payload_of(raw: &CanRawFrame) -> Option<CanPayload> {
    let (can_id, len, data, fd) = match raw {
        CanRawFrame::Classic(f) => (f.can_id, usize::from(f.can_dlc).min(8), &f.data[..], false),
        CanRawFrame::Fd(f) => (f.can_id, usize::from(f.len).min(64), &f.data[..], true),
    };
    if can_id & (libc::CAN_EFF_FLAG | libc::CAN_RTR_FLAG | libc::CAN_ERR_FLAG) != 0 {
        return None;
    }
    let mut payload = CanPayload {
        id: can_id & libc::CAN_SFF_MASK,
        data: [0; 64],
        len: len as u8,
        fd,
    };
    payload.data[..len].copy_from_slice(&data[..len]);
    Some(payload)
}

/// Kernel filters for the frames `mapping`'s sender receives: the other half of the ID
/// block (the controller's offsets 0x40..0x80 for the bridge, the bridge's 0x00..0x40 for
/// the controller), standard data frames only, as few aligned mask filters as cover it
/// (one when the base is a multiple of 0x40).
fn receive_filters(mapping: &CanMapping) -> Vec<CanFilter> {
    let half = u32::from(CAN_ID_BLOCK / 2);
    let first = u32::from(mapping.base_id())
        + match mapping.sender() {
            CanSender::Bridge => half,
            CanSender::Controller => 0,
        };
    let end = first + half;
    let mut filters = Vec::new();
    let mut start = first;
    while start < end {
        let mut size = 1;
        while start.is_multiple_of(size * 2) && start + size * 2 <= end {
            size *= 2;
        }
        let mask = (libc::CAN_SFF_MASK & !(size - 1)) | libc::CAN_EFF_FLAG | libc::CAN_RTR_FLAG;
        filters.push(CanFilter::new(start, mask));
        start += size;
    }
    filters
}

fn sysfs(interface: &str, file: &str) -> Option<String> {
    std::fs::read_to_string(format!("/sys/class/net/{interface}/{file}")).ok()
}

/// Whether the interface is administratively up; `None` when that cannot be read.
pub fn interface_up(interface: &str) -> Option<bool> {
    let flags = sysfs(interface, "flags")?;
    let flags = u32::from_str_radix(flags.trim().trim_start_matches("0x"), 16).ok()?;
    Some(flags & IFF_UP != 0)
}

/// The interface's MTU: 16 for classic CAN only, 72 for CAN FD; `None` when unknown.
pub fn interface_mtu(interface: &str) -> Option<usize> {
    sysfs(interface, "mtu")?.trim().parse().ok()
}

/// Whether this kernel offers SocketCAN raw sockets at all.
fn socketcan_supported() -> io::Result<()> {
    // SAFETY: socket(2) with constant arguments; the descriptor is closed at once.
    let fd = unsafe { libc::socket(libc::PF_CAN, libc::SOCK_RAW, libc::CAN_RAW) };
    if fd < 0 {
        return Err(io::Error::last_os_error());
    }
    // SAFETY: fd is the descriptor socket(2) just returned, closed once.
    unsafe { libc::close(fd) };
    Ok(())
}

fn kind_of(e: &io::Error) -> ErrorKind {
    match e.raw_os_error() {
        Some(libc::ENODEV) => ErrorKind::NotFound,
        Some(libc::EAFNOSUPPORT) => ErrorKind::Unsupported,
        Some(libc::ENETDOWN) => ErrorKind::NetworkDown,
        _ => e.kind(),
    }
}

fn explain(e: &io::Error) -> String {
    match e.raw_os_error() {
        Some(libc::ENODEV) => format!("no such network interface ({e})"),
        Some(libc::EAFNOSUPPORT) => {
            format!("this kernel has no SocketCAN (modules can, can-raw) ({e})")
        }
        _ => e.to_string(),
    }
}

/// Starts the I/O thread and returns the link. An interface that is missing, not CAN FD
/// for an FD mapping, or on a kernel without SocketCAN is an error now; one that is down
/// is waited for in the background (`is_up` is false until it comes up).
/// `hello` is the bridge's, sent on every open.
pub fn connect_can(interface: &str, mapping: CanMapping, hello: Hello) -> io::Result<ChannelLink> {
    if mapping.sender() != CanSender::Bridge {
        return Err(io::Error::new(
            ErrorKind::InvalidInput,
            "a bridge's CAN link needs a mapping with the bridge as sender",
        ));
    }
    let first = match CanBus::open(interface, &mapping) {
        Ok(bus) => Some(bus),
        Err(e) if e.kind() == ErrorKind::NetworkDown => None,
        Err(e) => return Err(e),
    };
    let (link, ends, session) = ChannelLink::pair(describe(interface, &mapping), hello);
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    let interface = interface.to_string();
    std::thread::Builder::new()
        .name("rigbridge-can".into())
        .spawn(move || runtime.block_on(keep_open(interface, mapping, ends, session, first)))?;
    Ok(link)
}

fn describe(interface: &str, mapping: &CanMapping) -> String {
    format!(
        "can://{interface} ({}, base {:#x})",
        if mapping.fd() {
            "CAN FD"
        } else {
            "classic CAN"
        },
        mapping.base_id()
    )
}

async fn keep_open(
    interface: String,
    mapping: CanMapping,
    mut ends: IoEnds,
    mut bridge: BridgeSession,
    mut first: Option<CanBus>,
) {
    let mut backoff = BACKOFF_INITIAL;
    let mut sessions = 0u64;
    let mut assembler = CanAssembler::new(mapping);
    while !ends.shared.closed.load(Ordering::SeqCst) {
        let opened = match first.take() {
            Some(bus) => Ok(bus),
            None => CanBus::open(&interface, &mapping),
        };
        if let Ok(bus) = opened {
            if sessions > 0 {
                LinkShared::count(&ends.shared.reconnects);
            }
            sessions += 1;
            while ends.commands.try_recv().is_ok() {}
            assembler.reset();
            let started = Instant::now();
            ends.shared.connected.store(true, Ordering::SeqCst);
            let ended_by_bridge =
                session(bus, &mut ends, &mapping, &mut assembler, &mut bridge).await;
            bridge.closed(&ends.shared);
            ends.shared.connected.store(false, Ordering::SeqCst);
            if ended_by_bridge {
                return;
            }
            if started.elapsed() >= STABLE_SESSION {
                backoff = BACKOFF_INITIAL;
            }
        }
        tokio::time::sleep(backoff).await;
        backoff = (backoff * 2).min(BACKOFF_MAX);
    }
}

/// Sends `message` as its CAN frames; false when the bus failed. A message that does not
/// fit the wire is reported and skipped; one the bus has no room for is dropped whole
/// (the controller drops the incomplete one).
fn send_message(bus: &CanBus, message: &Message, mapping: &CanMapping, ends: &IoEnds) -> bool {
    let mut frames: Vec<CanPayload> = Vec::with_capacity(64);
    if let Err(error) = can_frames(message, mapping, &mut frames) {
        ends.encode_failed(error);
        return true;
    }
    for frame in &frames {
        // Blocks this thread for at most SEND_PATIENCE: it has nothing else to do.
        match bus.send_patiently(frame, SEND_PATIENCE) {
            Ok(()) => LinkShared::count(&ends.shared.frames_sent),
            Err(e) if e.kind() == ErrorKind::WouldBlock => {
                LinkShared::count(&ends.shared.dropped_commands);
                break;
            }
            Err(_) => return false,
        }
    }
    true
}

fn outgoing(what: Outgoing, bridge: &BridgeSession) -> Message {
    match what {
        Outgoing::Hello => bridge.hello_message(),
        Outgoing::Heartbeat => Message::Command(Command::Heartbeat),
    }
}

/// One socket's life. True when the bridge closed the link (stop for good).
async fn session(
    bus: CanBus,
    ends: &mut IoEnds,
    mapping: &CanMapping,
    assembler: &mut CanAssembler,
    bridge: &mut BridgeSession,
) -> bool {
    let interface = bus.interface().to_string();
    // ERROR too: the kernel reports an interface going down as a socket error alone.
    // SAFETY: the CanBus owns its socket and never replaces it, so its fd stays open and
    // the same for as long as the AsyncFd holds it.
    let registered =
        unsafe { AsyncFd::register_with_interest(bus, Interest::READABLE | Interest::ERROR) };
    let Ok(bus) = registered else {
        return false;
    };
    let hello = bridge.opened(Instant::now(), &ends.shared);
    if !send_message(bus.get_ref(), &outgoing(hello, bridge), mapping, ends) {
        return false;
    }
    bridge.sent(Instant::now());
    let mut watch = tokio::time::interval(WATCH_PERIOD);
    watch.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    let mut tick = tokio::time::interval(bridge.period());
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    loop {
        tokio::select! {
            command = ends.commands.recv() => {
                let Some(command) = command else { return true };
                if !bridge.may_send(&command, &ends.shared) {
                    LinkShared::count(&ends.shared.dropped_commands);
                    continue;
                }
                if !send_message(bus.get_ref(), &Message::Command(command), mapping, ends) {
                    return false;
                }
                bridge.sent(Instant::now());
            }
            ready = bus.ready(Interest::READABLE | Interest::ERROR) => {
                let Ok(mut guard) = ready else { return false };
                loop {
                    match guard.get_inner().try_receive() {
                        Ok(Some(frame)) => {
                            LinkShared::count(&ends.shared.frames_received);
                            let Some(message) = assembler.push(&frame) else { continue };
                            let Some(answer) = bridge.received(message, Instant::now(), ends) else {
                                continue;
                            };
                            if !send_message(guard.get_inner(), &outgoing(answer, bridge), mapping, ends) {
                                return false;
                            }
                            bridge.sent(Instant::now());
                        }
                        Ok(None) => {
                            guard.clear_ready();
                            break;
                        }
                        Err(_) => return false,
                    }
                }
                ends.shared
                    .crc_errors
                    .store(assembler.counters().crc_errors, Ordering::Relaxed);
            }
            _ = tick.tick() => {
                let what = match bridge.due(Instant::now()) {
                    Due::Nothing => continue,
                    Due::Lost => return false,
                    Due::Send(what) => what,
                };
                if !send_message(bus.get_ref(), &outgoing(what, bridge), mapping, ends) {
                    return false;
                }
                bridge.sent(Instant::now());
            }
            _ = watch.tick() => {
                if ends.shared.closed.load(Ordering::SeqCst) {
                    return true;
                }
                if interface_up(&interface) == Some(false) {
                    return false;
                }
            }
            _ = ends.shared.restart.notified() => return false,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn covered(filters: &[CanFilter]) -> Vec<u32> {
        let raw: Vec<libc::can_filter> = filters
            .iter()
            .map(|f| *AsRef::<libc::can_filter>::as_ref(f))
            .collect();
        (0..0x800u32)
            .filter(|id| raw.iter().any(|f| id & f.can_mask == f.can_id & f.can_mask))
            .collect()
    }

    #[test]
    fn filters_cover_exactly_the_peers_half_of_the_block() {
        for base in [0x000u16, 0x100, 0x140, 0x123, 0x780] {
            for (sender, offset) in [(CanSender::Bridge, 0x40), (CanSender::Controller, 0)] {
                let mapping = CanMapping::new(base, false, sender).unwrap();
                let filters = receive_filters(&mapping);
                let first = u32::from(base) + offset;
                assert_eq!(
                    covered(&filters),
                    (first..first + 0x40).collect::<Vec<_>>(),
                    "base {base:#x}, {sender:?}"
                );
                if base % 0x40 == 0 {
                    assert_eq!(filters.len(), 1);
                }
                // Extended and remote frames never pass.
                let raw = *AsRef::<libc::can_filter>::as_ref(&filters[0]);
                assert_ne!(raw.can_mask & libc::CAN_EFF_FLAG, 0);
                assert_ne!(raw.can_mask & libc::CAN_RTR_FLAG, 0);
            }
        }
    }

    #[test]
    fn received_frames_become_payloads_and_others_are_skipped() {
        let mut classic: libc::can_frame = unsafe { std::mem::zeroed() };
        classic.can_id = 0x142;
        classic.can_dlc = 8;
        classic.data = [1, 2, 3, 4, 5, 6, 7, 8];
        let payload = payload_of(&CanRawFrame::Classic(classic)).unwrap();
        assert_eq!((payload.id, payload.len, payload.fd), (0x142, 8, false));
        assert_eq!(payload.data(), &[1, 2, 3, 4, 5, 6, 7, 8]);
        classic.can_id = 0x142 | libc::CAN_EFF_FLAG;
        assert!(payload_of(&CanRawFrame::Classic(classic)).is_none());
        classic.can_id = 0x142 | libc::CAN_RTR_FLAG;
        assert!(payload_of(&CanRawFrame::Classic(classic)).is_none());
        let mut fd: libc::canfd_frame = unsafe { std::mem::zeroed() };
        fd.can_id = 0x141;
        fd.len = 48;
        fd.data[0] = 42;
        let payload = payload_of(&CanRawFrame::Fd(fd)).unwrap();
        assert_eq!((payload.id, payload.len, payload.fd), (0x141, 48, true));
        assert_eq!(payload.data()[0], 42);
    }

    #[test]
    fn a_controller_mapping_is_refused_for_the_bridge() {
        let mapping = CanMapping::new(0x100, false, CanSender::Controller).unwrap();
        let hello = crate::protocol::Hello {
            axis_names: vec![],
            lower: vec![],
            upper: vec![],
            max_speed: vec![],
            max_acceleration: vec![],
            cycle_us: 4000,
            watchdog_cycles: 25,
            answer: false,
        };
        let Err(error) = connect_can("vcan0", mapping, hello) else {
            panic!("a controller-side mapping was accepted");
        };
        assert_eq!(error.kind(), ErrorKind::InvalidInput);
    }
}
