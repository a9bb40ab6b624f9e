//! The in-process link to a [`Twin`]: commands go straight to the twin, and the first
//! `receive` after a command advances it by one cycle and returns its feedback. No bytes, no threads; the
//! streamer's clock is the twin's clock.

use super::{Link, LinkCounters, LinkError};
use crate::protocol::{Command, Feedback};
use crate::twin::Twin;
use std::time::Duration;

pub struct LoopbackLink {
    twin: Twin,
    counters: LinkCounters,
    /// One cycle of the twin per command: extra `receive` calls find nothing new.
    tick_due: bool,
}

impl LoopbackLink {
    pub fn new(twin: Twin) -> Self {
        Self {
            twin,
            counters: LinkCounters::default(),
            tick_due: false,
        }
    }

    pub fn twin(&self) -> &Twin {
        &self.twin
    }
}

impl Link for LoopbackLink {
    fn send(&mut self, command: &Command) -> Result<(), LinkError> {
        self.counters.frames_sent += 1;
        self.twin.handle(command);
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
}
