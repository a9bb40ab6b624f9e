//! The twin's CAN port (`rigbridge twin --can IFACE`): the controller's end of the
//! protocol's CAN mapping on a SocketCAN interface, seen by [`serve_twin`] as a
//! [`ControllerPort`]. CAN carries frames, not a byte stream, so the port rebuilds whole
//! messages from the bridge's frames with a [`CanAssembler`] (which drops any message that
//! lost a frame or fails its CRC) and hands them on in the byte-stream framing; the frames
//! serve_twin writes (Hello, Feedback) are decoded and sent as the mapping's CAN frames.
//! The values are the same wire integers either way, so nothing is rounded twice.
//!
//! CAN has no connection: the port is attached while its socket is open, and the twin
//! sends its Hello then. Link loss is silence, which the twin's watchdog turns into a hold;
//! an interface going down is a read error (the twin holds at once) and the port reopens
//! the socket with backoff once the interface is up again (and the twin says Hello again).
//!
//! [`serve_twin`]: crate::twin::server::serve_twin

use crate::protocol::{
    CanAssembler, CanCounters, CanMapping, CanPayload, CanSender, FrameDecoder, can_frames,
    encode_frame,
};
use crate::transport::{Backoff, CanBus, SEND_PATIENCE};
use crate::twin::server::ControllerPort;
use std::collections::VecDeque;
use std::io::{self, ErrorKind};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// How long a read without a socket waits before the loop looks again.
const DETACHED_WAIT: Duration = Duration::from_millis(1);

/// What the port saw, readable while the twin runs (the port itself is inside serve_twin).
#[derive(Debug, Default)]
pub struct CanPortStats {
    pub frames_sent: AtomicU64,
    pub frames_received: AtomicU64,
    /// The assembler's counters: CRC errors, incomplete, malformed, orphans and more.
    assembler: Mutex<CanCounters>,
}

impl CanPortStats {
    pub fn assembler(&self) -> CanCounters {
        *self.assembler.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// One line for the twin's exit summary.
    pub fn summary(&self) -> String {
        let c = self.assembler();
        format!(
            "CAN: {} frames received, {} sent; {} messages, {} CRC errors, {} incomplete, {} malformed, {} orphans",
            self.frames_received.load(Ordering::Relaxed),
            self.frames_sent.load(Ordering::Relaxed),
            c.messages,
            c.crc_errors,
            c.incomplete,
            c.malformed,
            c.orphans
        )
    }
}

pub struct CanPort {
    interface: String,
    mapping: CanMapping,
    bus: Option<CanBus>,
    assembler: CanAssembler,
    /// Received messages, framed for serve_twin, not yet read ...
    pending: Vec<u8>,
    /// ... and their lengths: a read hands over one message at most.
    lengths: VecDeque<usize>,
    /// Decodes the frames serve_twin writes.
    outgoing: FrameDecoder,
    frames: Vec<CanPayload>,
    retry_at: Instant,
    backoff: Backoff,
    stats: Arc<CanPortStats>,
}

impl CanPort {
    /// Opens `interface` for the controller's side of `mapping`. A missing interface, one
    /// that cannot carry the mapping, or a kernel without SocketCAN is an error now; an
    /// interface that is down is waited for.
    pub fn open(interface: &str, mapping: CanMapping) -> io::Result<Self> {
        if mapping.sender() != CanSender::Controller {
            return Err(io::Error::new(
                ErrorKind::InvalidInput,
                "the twin's CAN port needs a mapping with the controller as sender",
            ));
        }
        let bus = match CanBus::open(interface, &mapping) {
            Ok(bus) => Some(bus),
            Err(e) if e.kind() == ErrorKind::NetworkDown => None,
            Err(e) => return Err(e),
        };
        Ok(Self {
            interface: interface.to_string(),
            mapping,
            bus,
            assembler: CanAssembler::new(mapping),
            pending: Vec::with_capacity(4096),
            lengths: VecDeque::with_capacity(64),
            outgoing: FrameDecoder::default(),
            frames: Vec::with_capacity(256),
            retry_at: Instant::now(),
            backoff: Backoff::default(),
            stats: Arc::default(),
        })
    }

    /// A handle on the port's counters that outlives lending the port to serve_twin.
    pub fn stats(&self) -> Arc<CanPortStats> {
        self.stats.clone()
    }

    /// The next received message's framed bytes (as many as fit).
    fn take_pending(&mut self, buffer: &mut [u8]) -> usize {
        let Some(length) = self.lengths.front_mut() else {
            return 0;
        };
        let n = (*length).min(buffer.len());
        buffer[..n].copy_from_slice(&self.pending[..n]);
        self.pending.drain(..n);
        *length -= n;
        if *length == 0 {
            self.lengths.pop_front();
        }
        n
    }
}

impl ControllerPort for CanPort {
    fn attached(&mut self) -> bool {
        if self.bus.is_none() && Instant::now() >= self.retry_at {
            match CanBus::open(&self.interface, &self.mapping) {
                Ok(bus) => {
                    self.bus = Some(bus);
                    self.backoff.reset();
                }
                Err(_) => {
                    self.retry_at = Instant::now() + self.backoff.next_wait();
                }
            }
        }
        self.bus.is_some()
    }

    /// Hands over one message per call, as CAN delivers them: serve_twin then advances one
    /// cycle per target even when several arrived together (after a stall), so each one's
    /// seq is echoed.
    fn read_within(&mut self, buffer: &mut [u8], timeout: Duration) -> io::Result<usize> {
        if !self.lengths.is_empty() {
            return Ok(self.take_pending(buffer));
        }
        let Some(bus) = &self.bus else {
            std::thread::sleep(timeout.min(DETACHED_WAIT));
            return Ok(0);
        };
        if !bus.wait_readable(timeout)? {
            return Ok(0);
        }
        while let Some(frame) = bus.try_receive()? {
            self.stats.frames_received.fetch_add(1, Ordering::Relaxed);
            if let Some(message) = self.assembler.push(&frame) {
                let before = self.pending.len();
                // Every message the assembler delivers came from wire values: it encodes.
                if encode_frame(&message, &mut self.pending).is_ok() {
                    self.lengths.push_back(self.pending.len() - before);
                }
            }
        }
        *self
            .stats
            .assembler
            .lock()
            .unwrap_or_else(|e| e.into_inner()) = self.assembler.counters();
        Ok(self.take_pending(buffer))
    }

    fn write_frame(&mut self, frame: &[u8]) -> io::Result<()> {
        let Some(bus) = &self.bus else {
            return Ok(());
        };
        self.outgoing.push(frame);
        while let Some(message) = self.outgoing.next_message() {
            self.frames.clear();
            can_frames(&message, &self.mapping, &mut self.frames)
                .map_err(|e| io::Error::new(ErrorKind::InvalidData, e))?;
            for frame in &self.frames {
                bus.send_patiently(frame, SEND_PATIENCE)?;
                self.stats.frames_sent.fetch_add(1, Ordering::Relaxed);
            }
        }
        Ok(())
    }

    fn detach(&mut self) {
        self.bus = None;
        self.assembler.reset();
        self.pending.clear();
        self.lengths.clear();
        self.outgoing.reset();
        self.retry_at = Instant::now() + self.backoff.wait();
    }

    fn describe(&self) -> String {
        format!(
            "can://{} ({}, base {:#x})",
            self.interface,
            if self.mapping.fd() {
                "CAN FD"
            } else {
                "classic CAN"
            },
            self.mapping.base_id()
        )
    }
}
