//! The bridge's side of the session rules of `docs/protocol.md` (version 2, section 6),
//! shared by every byte and CAN link: the `0x00` and Hello on every open, waiting for the
//! controller's answer before anything moves, answering an unprompted Hello, a Heartbeat
//! in every cycle with nothing else to send, and `watchdog` cycles of silence as link loss.
//!
//! It is a state machine without I/O: the link's I/O thread tells it what arrived and
//! what it sent, and writes what it asks for. It owns no transport and never looks inside
//! a target.

use super::LinkEvent;
use super::channel::{IoEnds, LinkShared};
use crate::protocol::{Command, Hello, Message};
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

/// Before the controller's Hello says how long its silence may last, the bridge's own
/// watchdog applies; without that either, this.
const DEFAULT_SILENCE: Duration = Duration::from_millis(100);
/// Hellos sent without any answer before the link is closed and reopened.
const AWAIT_TRIES: u32 = 3;

/// What the session asks its link to send now.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Outgoing {
    /// The bridge's Hello (after a `0x00` on byte streams when the link just opened).
    Hello,
    Heartbeat,
}

/// What time did to the session.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Due {
    Nothing,
    Send(Outgoing),
    /// No valid frame for the controller's watchdog: close the link and reopen it.
    Lost,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum State {
    Awaiting { since: Instant },
    Established,
}

pub struct BridgeSession {
    hello: Hello,
    state: State,
    last_heard: Instant,
    last_sent: Instant,
    last_seq: Option<u32>,
    period: Duration,
    silence: Duration,
}

impl BridgeSession {
    pub fn new(hello: Hello) -> Self {
        let period = Duration::from_micros(u64::from(hello.cycle_us.max(1)));
        let silence = watchdog_time(period, hello.watchdog_cycles);
        let now = Instant::now();
        Self {
            hello,
            state: State::Awaiting { since: now },
            last_heard: now,
            last_sent: now,
            last_seq: None,
            period,
            silence,
        }
    }

    /// The bridge's Hello, for the link to encode.
    pub fn hello_message(&self) -> Message {
        Message::Hello(self.hello.clone())
    }

    /// The link (re)opened: it must send `0x00` (byte streams) and the bridge's Hello.
    pub fn opened(&mut self, now: Instant, shared: &LinkShared) -> Outgoing {
        self.state = State::Awaiting { since: now };
        self.last_heard = now;
        self.last_seq = None;
        shared.established.store(false, Ordering::SeqCst);
        Outgoing::Hello
    }

    /// The link closed: nothing may be streamed until the next Hello exchange.
    pub fn closed(&mut self, shared: &LinkShared) {
        self.state = State::Awaiting {
            since: Instant::now(),
        };
        shared.established.store(false, Ordering::SeqCst);
    }

    /// Whether an I/O request may go out now: only once the controller has answered (a
    /// request before it would reach a controller that is not bound).
    pub fn may_send_io(&self) -> bool {
        self.state == State::Established
    }

    /// Whether `command` may go out now: only Heartbeat, Stop, EStop and Reset before
    /// the controller's answer (docs/protocol.md 6.1, step 5), and targets only in the
    /// session the streamer adopted.
    pub fn may_send(&self, command: &Command, shared: &LinkShared) -> bool {
        let adopted =
            shared.adopted.load(Ordering::SeqCst) == shared.sessions.load(Ordering::SeqCst);
        match command {
            // Targets queued behind a Stop or EStop were planned before it: stale.
            Command::Target(target) => {
                self.state == State::Established
                    && adopted
                    && target.seq > shared.stale_up_to.load(Ordering::SeqCst)
            }
            _ => true,
        }
    }

    pub fn sent(&mut self, now: Instant) {
        self.last_sent = now;
    }

    /// A message from the controller. Returns what the link must answer, if anything.
    pub fn received(&mut self, message: Message, now: Instant, ends: &IoEnds) -> Option<Outgoing> {
        self.last_heard = now;
        match message {
            Message::Hello(hello) => self.controller_hello(hello, now, ends),
            Message::Feedback(feedback) => {
                if self.state == State::Established {
                    ends.shared.note_feedback(&mut self.last_seq, &feedback);
                    let _ = ends.feedback.try_send(feedback);
                }
                None
            }
            Message::Fault(report) => {
                let _ = ends.events.try_send(LinkEvent::Fault(report));
                None
            }
            Message::Io(crate::protocol::IoMessage::State(state)) => {
                if self.state == State::Established {
                    let _ = ends.io_states.try_send(state);
                }
                None
            }
            // Commands and I/O requests come from the bridge's side; a Heartbeat only
            // proves the link.
            Message::Command(_) | Message::Io(_) => None,
        }
    }

    fn controller_hello(&mut self, hello: Hello, now: Instant, ends: &IoEnds) -> Option<Outgoing> {
        match (self.state, hello.answer) {
            (State::Awaiting { .. }, true) => {
                self.silence = watchdog_time(
                    Duration::from_micros(u64::from(hello.cycle_us.max(1))),
                    hello.watchdog_cycles,
                );
                self.state = State::Established;
                self.last_seq = None;
                if let Ok(mut slot) = ends.shared.controller_hello.lock() {
                    *slot = Some(hello.clone());
                }
                ends.shared.sessions.fetch_add(1, Ordering::SeqCst);
                ends.shared.established.store(true, Ordering::SeqCst);
                let _ = ends.events.try_send(LinkEvent::Session(hello));
                None
            }
            // The controller restarted or was reset: it is unbound, answer it.
            (State::Established, false) => {
                self.state = State::Awaiting { since: now };
                ends.shared.established.store(false, Ordering::SeqCst);
                let _ = ends.events.try_send(LinkEvent::ControllerRestarted);
                Some(Outgoing::Hello)
            }
            // An unprompted Hello while the answer to ours is on its way, or a stray
            // answer: the exchange in progress settles it (docs/protocol.md 6.1, step 5).
            _ => None,
        }
    }

    /// What the passing of time asks for: a resent Hello, a Heartbeat, or link loss.
    pub fn due(&mut self, now: Instant) -> Due {
        let quiet = now.saturating_duration_since(self.last_heard);
        match self.state {
            State::Established if quiet >= self.silence => return Due::Lost,
            // A Hello may be lost on the way: resend it, and give up on the link only
            // after a few tries.
            State::Awaiting { .. } if quiet >= self.silence * AWAIT_TRIES => return Due::Lost,
            State::Awaiting { since } if now.saturating_duration_since(since) >= self.silence => {
                self.state = State::Awaiting { since: now };
                return Due::Send(Outgoing::Hello);
            }
            _ => {}
        }
        // A quarter cycle of grace: a target a little late in its cycle needs no
        // Heartbeat ahead of it (on a slow serial line that would delay it).
        if now.saturating_duration_since(self.last_sent) >= self.period + self.period / 4 {
            return Due::Send(Outgoing::Heartbeat);
        }
        Due::Nothing
    }

    /// The cycle: how often `due` should be asked.
    pub fn period(&self) -> Duration {
        self.period
    }
}

fn watchdog_time(period: Duration, cycles: u32) -> Duration {
    if cycles == 0 {
        DEFAULT_SILENCE
    } else {
        period * cycles
    }
}
