//! Links carry [`Command`]s to a controller and [`Feedback`] back: one trait, one file per
//! backend. A link owns its transport and framing; it never interprets motion (that is the
//! streamer's job) and never changes a command's values.

mod can;
mod channel;
mod egm;
pub mod egm_wire;
mod loopback;
mod serial;
mod spec;
mod tcp;

pub use can::{CanBus, SEND_PATIENCE, connect_can, interface_mtu, interface_up};
pub use channel::{CHANNEL_DEPTH, ChannelLink, IoEnds, LinkShared};
pub use egm::{EgmClock, EgmLink, EgmState, LINK_SILENCE, PLAYOUT_DEPTH, bind_egm};
pub use loopback::LoopbackLink;
pub use serial::{SerialSettings, connect_serial};
pub use spec::{DEFAULT_BAUD, LinkSpec, LinkSpecError};
pub use tcp::{TcpSettings, connect_tcp};

use crate::protocol::{Command, Feedback};
use std::time::Duration;
use thiserror::Error;

#[derive(Debug, Error)]
pub enum LinkError {
    #[error("link is closed: {0}")]
    Closed(String),
    #[error("link I/O error")]
    Io(#[from] std::io::Error),
}

/// Counters every link keeps, shown in summaries and logged.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct LinkCounters {
    pub frames_sent: u64,
    pub frames_received: u64,
    pub crc_errors: u64,
    pub duplicates: u64,
    pub gaps: u64,
    pub reconnects: u64,
}

pub trait Link: Send {
    fn send(&mut self, command: &Command) -> Result<(), LinkError>;
    /// The next feedback, waiting at most `timeout`; `Ok(None)` when none came in time.
    fn receive(&mut self, timeout: Duration) -> Result<Option<Feedback>, LinkError>;
    fn counters(&self) -> LinkCounters;
    /// A short description for summaries, such as `loopback` or `tcp://127.0.0.1:7000`.
    fn describe(&self) -> String;
    /// False while the transport is down (a link that reconnects is between attempts).
    fn is_up(&self) -> bool {
        true
    }
    /// Discards feedback that arrived before now (stale after a reconnect).
    fn drain(&mut self) {}
    /// The clock a device-paced link (EGM: the robot's messages) makes the streamer follow.
    fn pacing(&self) -> Option<std::sync::Arc<dyn crate::clock::Clock>> {
        None
    }
}
