//! The in-process link to a [`Twin`]: commands go straight to the twin, and the first
//! `receive` after a command advances it by one cycle and returns its feedback. No bytes,
//! no threads; the streamer's clock is the twin's clock. The session of
//! `docs/protocol.md` 6.1 is immediate: the link binds the twin as the bridge's Hello
//! would, at once and again after a reset, and passes on the twin's Fault notices.

use super::{Link, LinkCounters, LinkError, LinkEvent};
use crate::protocol::{Command, Feedback, Hello};
use crate::twin::Twin;
use std::collections::VecDeque;
use std::time::Duration;

pub struct LoopbackLink {
    twin: Twin,
    counters: LinkCounters,
    /// One cycle of the twin per command: extra `receive` calls find nothing new.
    tick_due: bool,
    events: VecDeque<LinkEvent>,
}

impl LoopbackLink {
    pub fn new(mut twin: Twin) -> Self {
        twin.bridge_hello();
        Self {
            twin,
            counters: LinkCounters::default(),
            tick_due: false,
            events: VecDeque::with_capacity(4),
        }
    }

    pub fn twin(&self) -> &Twin {
        &self.twin
    }
}

impl Link for LoopbackLink {
    fn take_contacts(&mut self) -> Option<crate::twin::ContactReport> {
        self.twin.take_contacts()
    }

    fn send(&mut self, command: &Command) -> Result<(), LinkError> {
        self.counters.frames_sent += 1;
        self.twin.handle(command);
        if *command == Command::Reset && !self.twin.is_bound() {
            // The twin announced itself after the reset; the bridge's Hello answers.
            self.twin.bridge_hello();
        }
        if let Some(notice) = self.twin.take_fault_notice() {
            self.events.push_back(LinkEvent::Fault(notice));
        }
        self.tick_due = true;
        Ok(())
    }

    fn receive(&mut self, _timeout: Duration) -> Result<Option<Feedback>, LinkError> {
        if !std::mem::take(&mut self.tick_due) {
            return Ok(None);
        }
        self.counters.frames_received += 1;
        Ok(Some(self.twin.tick()))
    }

    fn counters(&self) -> LinkCounters {
        self.counters
    }

    fn describe(&self) -> String {
        "loopback".to_string()
    }

    fn io(&self) -> super::Io {
        super::Io::NotCarried(
            "the loopback twin carries no I/O yet (protocol v2 has no I/O messages; a later version adds them, with the twin's gripper); EGM, CiA 402 and Dynamixel carry none",
        )
    }

    fn next_event(&mut self) -> Option<LinkEvent> {
        self.events.pop_front()
    }

    fn controller_hello(&self) -> Option<Hello> {
        Some(self.twin.hello(true))
    }
}
