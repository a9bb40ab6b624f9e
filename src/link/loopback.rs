//! The in-process link to a [`Twin`]: commands go straight to the twin, and each
//! `receive` advances it by one cycle and returns its feedback. No bytes, no threads; the
//! streamer's clock is the twin's clock.

use super::{Link, LinkCounters, LinkError};
use crate::protocol::{Command, Feedback};
use crate::twin::Twin;
use std::time::Duration;

pub struct LoopbackLink {
    twin: Twin,
    counters: LinkCounters,
}

impl LoopbackLink {
    pub fn new(twin: Twin) -> Self {
        Self {
            twin,
            counters: LinkCounters::default(),
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
        Ok(())
    }

    fn receive(&mut self, _timeout: Duration) -> Result<Option<Feedback>, LinkError> {
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
