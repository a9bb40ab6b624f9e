//! Links carry [`Command`]s to a controller and [`Feedback`] back: one trait, the in-process
//! loopback, and what every device protocol's link shares (the session state machine, the
//! channel to an I/O thread); each protocol's own link is in its `device` folder. A link
//! owns its transport and framing; it never interprets motion (that is the streamer's job)
//! and never changes a command's values.

mod channel;
mod loopback;
mod session;

pub use channel::{CHANNEL_DEPTH, ChannelLink, IoEnds, LinkShared};
pub use loopback::LoopbackLink;
pub use session::{BridgeSession, Due, Outgoing};

use crate::protocol::{Command, EncodeError, FaultReport, Feedback, Hello};
use std::time::Duration;
use thiserror::Error;

/// Starts a link's I/O thread named `name`: at the cycles' priority whoever opens the link
/// (a `serve` job opens a remote link before it rises), since the cycle waits on the
/// feedback it carries and, for EGM, on the clock it paces. A refusal changes nothing else:
/// the cycle's own thread says so.
pub(crate) fn spawn_io_thread<T: Send + 'static>(
    name: &str,
    io: impl FnOnce() -> T + Send + 'static,
) -> std::io::Result<std::thread::JoinHandle<T>> {
    std::thread::Builder::new()
        .name(name.to_owned())
        .spawn(move || {
            let _ = crate::realtime::raise_priority(crate::realtime::CYCLE_PRIORITY);
            io()
        })
}

#[derive(Debug, Error)]
pub enum LinkError {
    #[error("link is closed: {0}")]
    Closed(String),
    #[error("link I/O error")]
    Io(#[from] std::io::Error),
    #[error("the link {link} carries no digital I/O: {why}")]
    NoIo { link: String, why: &'static str },
}

/// What a link hears from the controller besides Feedback, in the order it happened.
#[derive(Debug, Clone, PartialEq)]
pub enum LinkEvent {
    /// The controller answered the bridge's Hello: a session is established (on the first
    /// connect and after every reconnect). Its Hello says what it admits.
    Session(Hello),
    /// An unprompted controller Hello in an established session: the controller restarted
    /// or was reset and is unbound; the link has answered it and a new session follows.
    ControllerRestarted,
    /// The controller latched a fault (or could not clear one), in its own words.
    Fault(FaultReport),
    /// A command could not be encoded for the wire, so nothing was sent.
    EncodeFailed(EncodeError),
    /// What the link hears can no longer be taken as the bound controller's (EGM: a second
    /// robot on the sensor port, feedback that jumped further than the arm can move), in
    /// words. The job is brought to rest along its path and ends `faulted`, never resumed.
    Untrusted(String),
}

/// The bridge's Hello for `rig` (docs/protocol.md 3.1): the rig it plans for, the cycle
/// it streams at and the watchdog it expects.
pub fn bridge_hello(
    rig: &crate::rig::Rig,
    period: std::time::Duration,
    watchdog_cycles: u32,
) -> Hello {
    Hello {
        axis_names: rig.joint_names().map(String::from).collect(),
        lower: rig.joints.iter().map(|j| j.limits.lower).collect(),
        upper: rig.joints.iter().map(|j| j.limits.upper).collect(),
        max_speed: rig.joints.iter().map(|j| j.limits.max_speed).collect(),
        max_acceleration: rig
            .joints
            .iter()
            .map(|j| j.limits.max_acceleration)
            .collect(),
        cycle_us: crate::protocol::cycle_us(period),
        watchdog_cycles,
        answer: false,
        version: crate::protocol::codec::PROTOCOL_VERSION,
    }
}

/// Counters every link keeps, shown in summaries and logged (and flattened into reports).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct LinkCounters {
    pub frames_sent: u64,
    pub frames_received: u64,
    pub crc_errors: u64,
    pub duplicates: u64,
    pub gaps: u64,
    pub reconnects: u64,
    /// EGM (docs/egm.md; 0 on other links): datagrams from a source other than the robot the
    /// session is bound to, dropped.
    pub foreign_dropped: u64,
    /// EGM: the robot's messages whose seqno or robot time repeated or went back, dropped.
    pub replays_dropped: u64,
    /// EGM: feedback further than the arm can move since the last, dropped (the job stops).
    pub feedback_jumps: u64,
    /// EGM: second robots reported on the sensor port.
    pub second_robots: u64,
}

/// Whether a link carries digital I/O beside motion (a program's `set_output`,
/// `wait_input`, `grip`, `release`), and if not, why: what a program that needs I/O is told
/// before any motion (docs/programs.md). Our protocol carries it from version 3 (the
/// loopback twin, TCP, serial, CAN with a v3 controller); the device links carry none.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Io {
    Carried,
    NotCarried(&'static str),
}

/// Why a device link carries no I/O, told with every refusal: EGM's joint references,
/// Dynamixel's goal positions and CiA 402's cyclic positions as rigbridge drives them carry
/// none; our protocol carries it from version 3 (docs/protocol.md 6.10).
pub const NO_IO_ANYWHERE: &str = "EGM, CiA 402 and Dynamixel carry none as rigbridge drives them; our protocol v3 does (the twin, TCP, serial, CAN)";
/// Why a session with a v2 controller carries no I/O.
pub const NO_IO_V2: &str = "the controller speaks protocol v2, which has no I/O messages (v3 adds them, docs/protocol.md 6.10)";
/// Why a link whose controller has not answered yet cannot say.
pub const NO_IO_UNKNOWN: &str = "no controller has answered the bridge's Hello yet (its Hello's version says whether it carries I/O)";

pub trait Link: Send {
    fn send(&mut self, command: &Command) -> Result<(), LinkError>;
    /// The next feedback, waiting at most `timeout`; `Ok(None)` when none came in time.
    fn receive(&mut self, timeout: Duration) -> Result<Option<Feedback>, LinkError>;
    fn counters(&self) -> LinkCounters;
    /// A short description for summaries, such as `loopback` or `tcp://127.0.0.1:7000`.
    fn describe(&self) -> String;
    /// Whether this link carries digital I/O ([`Io`]).
    fn io(&self) -> Io {
        Io::NotCarried(NO_IO_ANYWHERE)
    }
    /// Sends an I/O request (protocol v3's SetOutput or ReadInput); refused by a link that
    /// carries none.
    fn send_io(&mut self, request: &crate::protocol::IoMessage) -> Result<(), LinkError> {
        let _ = request;
        let Io::NotCarried(why) = self.io() else {
            return Ok(());
        };
        Err(LinkError::NoIo {
            link: self.describe(),
            why,
        })
    }
    /// The controller's next answer to an I/O request, if one arrived (never blocks).
    fn take_io(&mut self) -> Option<crate::protocol::IoState> {
        None
    }
    /// True while a session is established: the transport is up and the controller has
    /// answered the bridge's Hello (a link that reconnects is false between attempts).
    fn is_up(&self) -> bool {
        true
    }
    /// Discards feedback that arrived before now (stale after a reconnect).
    fn drain(&mut self) {}
    /// The next event, if one is waiting (never blocks).
    fn next_event(&mut self) -> Option<LinkEvent> {
        None
    }
    /// The Hello of the controller in the current (or last) session.
    fn controller_hello(&self) -> Option<Hello> {
        None
    }
    /// Sessions established so far: a change means the controller was met anew.
    fn sessions(&self) -> u64 {
        1
    }
    /// Closes the transport and reopens it (a controller that went silent).
    fn restart(&mut self) {}
    /// The streamer starts streaming in the current session: targets go out in this one
    /// only, and are dropped in any later session until it is adopted in turn (a session
    /// that changes mid-stream must not receive targets planned for the one before).
    fn adopt_session(&mut self) {}
    /// The clock a device-paced link (EGM: the robot's messages) makes the streamer follow.
    fn pacing(&self) -> Option<std::sync::Arc<dyn crate::clock::Clock>> {
        None
    }
    /// Why the link is not up, when it knows: the transport's or a device's own failure
    /// the last time it tried (connection refused, no such device, a node that did not
    /// answer). `None` when it has none to give (a controller that accepted the
    /// connection and is silent).
    fn down_reason(&self) -> Option<String> {
        None
    }
    /// How many targets before the one a feedback echoes its position was measured
    /// against: 0 when the controller takes a target and then measures; 1 on CANopen, where
    /// a drive measures at the SYNC that hands it the next target (its pipeline delay,
    /// which is no tracking error).
    fn measured_cycles_behind(&self) -> u32 {
        0
    }
    /// What the controller measured of the cell's clearances since the last call, measuring
    /// afresh from now: the in-process twin's collision watch; `None` for a controller that
    /// does not tell (every remote one).
    fn take_contacts(&mut self) -> Option<crate::twin::ContactReport> {
        None
    }
    /// The in-process twin's judgement of the cell's parts (issue 29): where each ended
    /// against its goal; `None` for a controller that does not tell (every remote one) or a
    /// cell without parts.
    fn judgement(&self) -> Option<crate::twin::CellJudgement> {
        None
    }
}
