//! The SocketCAN socket ([`CanBus`]) both sides of a CAN link use: the bridge's CAN and
//! CANopen links and the twin's CAN and CANopen ports. It opens a raw socket on one
//! interface (classic or FD, with kernel filters for a mapping's peer), writes and reads
//! single frames, waits for frames, and reads the interface's state from sysfs.
//!
//! It owns the socket and the frame conversion only: it must not assemble messages, keep a
//! session or decide when to reopen (its callers do, each with its own backoff).

use crate::protocol::can::CAN_ID_BLOCK;
use crate::protocol::{CanMapping, CanPayload, CanSender};
use socketcan::{
    CanDataFrame, CanFdFrame, CanFdSocket, CanFilter, CanRawFrame, CanSocket, EmbeddedFrame,
    Socket, SocketOptions, StandardId,
};
use std::io::{self, ErrorKind};
use std::os::fd::{AsRawFd, RawFd};
use std::time::{Duration, Instant};

/// How long a frame may wait for room in a full transmit queue before its message is given
/// up (half a cycle at 1 kHz; the receiver then drops the incomplete message).
pub const SEND_PATIENCE: Duration = Duration::from_micros(500);

/// The receive buffer each socket asks for. The kernel's default (rmem_default, about
/// 208 KiB) holds some 230 frames at the memory each frame costs a socket (about 900 bytes
/// with its bookkeeping): 115 ms of a classic link's targets at 250 Hz (8 frames each). A
/// host that holds the reading thread longer than that, as the software-emulated test VM
/// does, would drop frames, and a message short of a frame is lost whole. 2 MiB rides out
/// about a second. Root may go past rmem_max (SO_RCVBUFFORCE); others get what rmem_max
/// allows.
const RECEIVE_BUFFER_BYTES: libc::c_int = 2 << 20;

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
        let fd = match &socket {
            BusSocket::Classic(s) => s.as_raw_fd(),
            BusSocket::Fd(s) => s.as_raw_fd(),
        };
        enlarge_receive_buffer(fd);
        Ok(Self {
            socket,
            interface: interface.to_string(),
        })
    }

    /// The bytes the socket's receive buffer holds (as the kernel reports it: double what
    /// was asked, for its bookkeeping).
    pub fn receive_buffer_bytes(&self) -> io::Result<usize> {
        let mut size: libc::c_int = 0;
        let mut len = std::mem::size_of::<libc::c_int>() as libc::socklen_t;
        // SAFETY: getsockopt writes at most `len` bytes into `size`, an int, and `len` says so.
        let result = unsafe {
            libc::getsockopt(
                self.as_raw_fd(),
                libc::SOL_SOCKET,
                libc::SO_RCVBUF,
                (&mut size as *mut libc::c_int).cast(),
                &mut len,
            )
        };
        if result == 0 {
            Ok(usize::try_from(size).unwrap_or(0))
        } else {
            Err(io::Error::last_os_error())
        }
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

/// Asks for [`RECEIVE_BUFFER_BYTES`]: past rmem_max when allowed (SO_RCVBUFFORCE), else up
/// to it. A refusal keeps the default, which works on an unloaded host.
fn enlarge_receive_buffer(fd: RawFd) {
    let size = RECEIVE_BUFFER_BYTES;
    let set = |option: libc::c_int| {
        // SAFETY: setsockopt reads one int from `size`, whose length is passed.
        unsafe {
            libc::setsockopt(
                fd,
                libc::SOL_SOCKET,
                option,
                (&size as *const libc::c_int).cast(),
                std::mem::size_of::<libc::c_int>() as libc::socklen_t,
            )
        }
    };
    if set(libc::SO_RCVBUFFORCE) != 0 {
        let _ = set(libc::SO_RCVBUF);
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
                let mapping =
                    CanMapping::new(base, false, sender).expect("the base ID is a valid mapping");
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
        let payload =
            payload_of(&CanRawFrame::Classic(classic)).expect("the classic frame gives a payload");
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
        let payload = payload_of(&CanRawFrame::Fd(fd)).expect("the FD frame gives a payload");
        assert_eq!((payload.id, payload.len, payload.fd), (0x141, 48, true));
        assert_eq!(payload.data()[0], 42);
    }
}
