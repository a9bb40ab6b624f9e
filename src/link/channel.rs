//! The cycle's side of every byte link: commands go to the link's I/O thread through a
//! bounded channel, feedback and events come back through others, so the cycle never
//! blocks on a socket or a serial port and never allocates. The I/O threads (one file per
//! backend) own the transport, the framing, the session ([`BridgeSession`]) and the
//! reconnects.

use super::session::BridgeSession;
use super::{Link, LinkCounters, LinkError, LinkEvent};
use crate::protocol::{Command, Feedback, Hello, IoMessage, IoState};
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use std::sync::mpsc::{Receiver, RecvTimeoutError, SyncSender};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::sync::mpsc::error::TrySendError;

/// Frames in flight each way: a few cycles' worth; more would only add latency.
pub const CHANNEL_DEPTH: usize = 16;

/// Counters and state shared between the cycle and an I/O thread.
#[derive(Debug, Default)]
pub struct LinkShared {
    pub frames_sent: AtomicU64,
    pub frames_received: AtomicU64,
    pub crc_errors: AtomicU64,
    pub duplicates: AtomicU64,
    pub gaps: AtomicU64,
    pub reconnects: AtomicU64,
    /// Commands the cycle could not hand over (I/O thread behind or disconnected).
    pub dropped_commands: AtomicU64,
    /// Commands that could not be encoded for the wire (each also an event).
    pub encode_failures: AtomicU64,
    pub connected: AtomicBool,
    /// Connected, and the controller answered the bridge's Hello.
    pub established: AtomicBool,
    pub sessions: AtomicU64,
    /// The session the streamer streams in (see `Link::adopt_session`).
    pub adopted: AtomicU64,
    /// Targets up to this seq were planned before a Stop or EStop: any still queued for
    /// the I/O thread are stale and never sent.
    pub stale_up_to: AtomicU32,
    pub controller_hello: Mutex<Option<Hello>>,
    /// Why the transport did not open or connect the last time it was tried (cleared when
    /// it does): what [`Link::down_reason`] says.
    pub problem: Mutex<Option<String>>,
    /// The cycle asks the I/O thread to close and reopen the transport.
    pub restart: tokio::sync::Notify,
    pub closed: AtomicBool,
}

impl LinkShared {
    /// Records why the transport did not open (or `None`: it did).
    pub fn set_problem(&self, problem: Option<String>) {
        if let Ok(mut slot) = self.problem.lock() {
            *slot = problem;
        }
    }

    pub fn counters(&self) -> LinkCounters {
        let get = |c: &AtomicU64| c.load(Ordering::Relaxed);
        LinkCounters {
            frames_sent: get(&self.frames_sent),
            frames_received: get(&self.frames_received),
            crc_errors: get(&self.crc_errors),
            duplicates: get(&self.duplicates),
            gaps: get(&self.gaps),
            reconnects: get(&self.reconnects),
            ..LinkCounters::default()
        }
    }

    pub fn count(counter: &AtomicU64) {
        counter.fetch_add(1, Ordering::Relaxed);
    }

    /// Feedback bookkeeping for I/O threads. A jump in the echoed seq is a gap (a target
    /// lost on the way: the controller answers every target it gets). A repeated echo is
    /// counted as a duplicate: a duplicated frame, or a controller cycle that had no new
    /// target (protocol v1 feedback carries no sequence of its own to tell them apart).
    pub fn note_feedback(&self, last: &mut Option<u32>, feedback: &Feedback) {
        if let Some(previous) = *last {
            if feedback.seq == previous && feedback.seq != 0 {
                Self::count(&self.duplicates);
            } else if feedback.seq > previous.wrapping_add(1) {
                Self::count(&self.gaps);
            }
        }
        *last = Some(feedback.seq);
    }
}

/// What an I/O thread gets: the commands to write, where to put feedback, the counters.
pub struct IoEnds {
    /// tokio's channel: an async I/O task can await it, a thread can `blocking_recv` it,
    /// and the cycle's `try_send` needs no runtime.
    pub commands: tokio::sync::mpsc::Receiver<Command>,
    pub feedback: SyncSender<Feedback>,
    pub events: SyncSender<LinkEvent>,
    /// I/O requests to write (protocol v3), and the controller's answers.
    pub io_requests: tokio::sync::mpsc::Receiver<IoMessage>,
    pub io_states: SyncSender<IoState>,
    pub shared: Arc<LinkShared>,
}

impl IoEnds {
    /// A command that does not fit the wire: counted and reported, never sent.
    pub fn encode_failed(&self, error: crate::protocol::EncodeError) {
        LinkShared::count(&self.shared.encode_failures);
        let _ = self.events.try_send(LinkEvent::EncodeFailed(error));
    }
}

pub struct ChannelLink {
    /// The seq of the last target handed to the I/O thread.
    last_target: u32,
    commands: tokio::sync::mpsc::Sender<Command>,
    feedback: Receiver<Feedback>,
    events: Receiver<LinkEvent>,
    io_requests: tokio::sync::mpsc::Sender<IoMessage>,
    io_states: Receiver<IoState>,
    shared: Arc<LinkShared>,
    description: String,
}

impl ChannelLink {
    /// A link, the ends its I/O thread works with, and the session it keeps, which opens
    /// with the bridge's `hello`.
    pub fn pair(description: String, hello: Hello) -> (Self, IoEnds, BridgeSession) {
        let (command_tx, command_rx) = tokio::sync::mpsc::channel(CHANNEL_DEPTH);
        let (feedback_tx, feedback_rx) = std::sync::mpsc::sync_channel(CHANNEL_DEPTH);
        let (event_tx, event_rx) = std::sync::mpsc::sync_channel(CHANNEL_DEPTH);
        let (io_tx, io_rx) = tokio::sync::mpsc::channel(CHANNEL_DEPTH);
        let (io_state_tx, io_state_rx) = std::sync::mpsc::sync_channel(CHANNEL_DEPTH);
        let shared = Arc::new(LinkShared::default());
        (
            Self {
                last_target: 0,
                commands: command_tx,
                feedback: feedback_rx,
                events: event_rx,
                io_requests: io_tx,
                io_states: io_state_rx,
                shared: shared.clone(),
                description,
            },
            IoEnds {
                commands: command_rx,
                feedback: feedback_tx,
                events: event_tx,
                io_requests: io_rx,
                io_states: io_state_tx,
                shared,
            },
            BridgeSession::new(hello),
        )
    }

    pub fn is_connected(&self) -> bool {
        self.shared.connected.load(Ordering::SeqCst)
    }

    pub fn shared(&self) -> &LinkShared {
        &self.shared
    }
}

impl Drop for ChannelLink {
    fn drop(&mut self) {
        self.shared.closed.store(true, Ordering::SeqCst);
    }
}

impl Link for ChannelLink {
    fn send(&mut self, command: &Command) -> Result<(), LinkError> {
        match command {
            Command::Target(target) => self.last_target = target.seq,
            // Targets still queued behind a Stop were planned before it: stale.
            Command::Stop | Command::EStop => {
                self.shared
                    .stale_up_to
                    .store(self.last_target, Ordering::SeqCst);
            }
            _ => {}
        }
        match self.commands.try_send(*command) {
            Ok(()) => Ok(()),
            Err(TrySendError::Full(_)) => {
                LinkShared::count(&self.shared.dropped_commands);
                Ok(())
            }
            Err(TrySendError::Closed(_)) => Err(LinkError::Closed(format!(
                "{}: I/O thread ended",
                self.description
            ))),
        }
    }

    fn receive(&mut self, timeout: Duration) -> Result<Option<Feedback>, LinkError> {
        match self.feedback.recv_timeout(timeout) {
            Ok(feedback) => Ok(Some(feedback)),
            Err(RecvTimeoutError::Timeout) => Ok(None),
            Err(RecvTimeoutError::Disconnected) => Err(LinkError::Closed(format!(
                "{}: I/O thread ended",
                self.description
            ))),
        }
    }

    fn counters(&self) -> LinkCounters {
        self.shared.counters()
    }

    fn describe(&self) -> String {
        self.description.clone()
    }

    fn is_up(&self) -> bool {
        self.is_connected() && self.shared.established.load(Ordering::SeqCst)
    }

    fn drain(&mut self) {
        while self.feedback.try_recv().is_ok() {}
    }

    fn next_event(&mut self) -> Option<LinkEvent> {
        self.events.try_recv().ok()
    }

    fn controller_hello(&self) -> Option<Hello> {
        self.shared.controller_hello.lock().ok()?.clone()
    }

    /// Carried when the controller's latest Hello was version 3 (docs/protocol.md 6.10).
    fn io(&self) -> super::Io {
        match self.controller_hello() {
            Some(hello) if hello.version >= crate::protocol::PROTOCOL_VERSION_IO => {
                super::Io::Carried
            }
            Some(_) => super::Io::NotCarried(super::NO_IO_V2),
            None => super::Io::NotCarried(super::NO_IO_UNKNOWN),
        }
    }

    fn send_io(&mut self, request: &IoMessage) -> Result<(), LinkError> {
        if let super::Io::NotCarried(why) = self.io() {
            return Err(LinkError::NoIo {
                link: self.describe(),
                why,
            });
        }
        match self.io_requests.try_send(request.clone()) {
            // A request lost to a full queue is not answered: the streamer's wait for the
            // answer runs out and says so.
            Ok(()) | Err(TrySendError::Full(_)) => Ok(()),
            Err(TrySendError::Closed(_)) => Err(LinkError::Closed(format!(
                "{}: I/O thread ended",
                self.description
            ))),
        }
    }

    fn take_io(&mut self) -> Option<IoState> {
        self.io_states.try_recv().ok()
    }

    fn down_reason(&self) -> Option<String> {
        self.shared.problem.lock().ok()?.clone()
    }

    fn sessions(&self) -> u64 {
        self.shared.sessions.load(Ordering::SeqCst)
    }

    fn adopt_session(&mut self) {
        let current = self.shared.sessions.load(Ordering::SeqCst);
        self.shared.adopted.store(current, Ordering::SeqCst);
    }

    fn restart(&mut self) {
        self.shared.established.store(false, Ordering::SeqCst);
        self.shared.restart.notify_one();
    }
}
