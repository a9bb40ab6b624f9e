//! The in-process link to a [`Twin`]: commands go straight to the twin, and the first
//! `receive` after a command advances it by one cycle and returns its feedback. No bytes,
//! no threads; the streamer's clock is the twin's clock. The session of
//! `docs/protocol.md` 6.1 is immediate: the link binds the twin as the bridge's Hello
//! would, at once and again after a reset, and passes on the twin's Fault notices. I/O
//! requests go to the twin as they would over protocol v3, and its answers come back.

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

    fn judgement(&self) -> Option<crate::twin::CellJudgement> {
        self.twin.judgement()
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
        if self.twin.carries_io() {
            super::Io::Carried
        } else {
            super::Io::NotCarried(super::NO_IO_V2)
        }
    }

    fn send_io(&mut self, request: &crate::protocol::IoMessage) -> Result<(), LinkError> {
        if let super::Io::NotCarried(why) = self.io() {
            return Err(LinkError::NoIo {
                link: self.describe(),
                why,
            });
        }
        self.counters.frames_sent += 1;
        self.twin.handle_io(request);
        Ok(())
    }

    fn take_io(&mut self) -> Option<crate::protocol::IoState> {
        self.twin.take_io_answer()
    }

    fn next_event(&mut self) -> Option<LinkEvent> {
        self.events.pop_front()
    }

    fn controller_hello(&self) -> Option<Hello> {
        Some(self.twin.hello(true))
    }
}
