//! Reset (docs/protocol.md 3.3 and 6.7): asks the controller to clear a latched fault or
//! e-stop and reports what it says, cleared or the fault it keeps. Owns that exchange
//! only; the new session a cleared controller asks for (its unprompted Hello, the bridge's
//! answer) is the link's, and it never sends a target.

use super::DaemonError;
use crate::clock::{self, Clock};
use crate::link::{Link, LinkEvent};
use crate::protocol::{Command, ControllerStatus, Feedback};
use crate::stream::fault_text;
use std::time::Duration;

/// How long a Reset waits for a session, a first feedback and the controller's answer: a
/// controller answers within a cycle or two (6.7); this leaves room for a reconnect.
pub const RESET_TIMEOUT: Duration = Duration::from_secs(3);

/// What the controller said to a Reset.
#[derive(Debug, Clone, PartialEq)]
pub enum ResetOutcome {
    /// It had a fault latched and cleared it: it now reports this (non-fault) status.
    Cleared {
        fault: String,
        status: ControllerStatus,
    },
    /// No fault was latched (nothing was sent): it reports this status.
    NothingLatched { status: ControllerStatus },
    /// It keeps its fault: the fault, and its words for why (or its Feedback's code).
    Kept(String),
}

impl ResetOutcome {
    /// True when the controller reports no fault now.
    pub fn is_clear(&self) -> bool {
        !matches!(self, ResetOutcome::Kept(_))
    }
}

impl std::fmt::Display for ResetOutcome {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ResetOutcome::Cleared { fault, status } => {
                write!(
                    f,
                    "cleared ({fault}); the controller is {}",
                    status_word(*status)
                )
            }
            ResetOutcome::NothingLatched { status } => write!(
                f,
                "no fault latched, nothing to clear; the controller is {}",
                status_word(*status)
            ),
            ResetOutcome::Kept(words) => write!(f, "the controller keeps its fault: {words}"),
        }
    }
}

/// The controller's status in words, for people (never "ok" for a fault).
pub fn status_word(status: ControllerStatus) -> String {
    match status {
        ControllerStatus::Ok => "ok (following targets)".into(),
        ControllerStatus::Holding => "holding".into(),
        ControllerStatus::Fault(fault) => format!("faulted: {fault}"),
    }
}

/// Sends Reset over `link` when the controller reports a latched fault, and waits (up to
/// `timeout`, real time: this is I/O with a controller, whatever clock jobs run on) for its
/// answer: a non-fault Feedback (cleared) or a Fault message (kept).
pub fn reset_controller(
    link: &mut dyn Link,
    timeout: Duration,
) -> Result<ResetOutcome, DaemonError> {
    let deadline = clock::real().now() + timeout;
    let before = first_feedback(link, deadline)?;
    // Notices of the fault as it latched are old news, not the answer to this Reset.
    while link.next_event().is_some() {}
    let ControllerStatus::Fault(fault) = before.status else {
        return Ok(ResetOutcome::NothingLatched {
            status: before.status,
        });
    };
    link.send(&Command::Reset)?;
    while clock::real().now() < deadline {
        while let Some(event) = link.next_event() {
            if let LinkEvent::Fault(report) = event {
                return Ok(ResetOutcome::Kept(fault_text(&report.fault, &report.text)));
            }
        }
        if let Some(feedback) = poll(link)?
            && !matches!(feedback.status, ControllerStatus::Fault(_))
        {
            return Ok(ResetOutcome::Cleared {
                fault: fault.to_string(),
                status: feedback.status,
            });
        }
    }
    Err(DaemonError::Unavailable(format!(
        "{} did not answer the Reset within {:.1} s; it still reports {fault}",
        link.describe(),
        timeout.as_secs_f64()
    )))
}

/// The wait between two Heartbeats while waiting for an answer: about a cycle of a 250 Hz
/// controller, which answers every cycle.
const POLL: Duration = Duration::from_millis(4);

/// One Heartbeat, and the feedback that answers it within [`POLL`] (the newest, if more).
fn poll(link: &mut dyn Link) -> Result<Option<Feedback>, DaemonError> {
    if !link.is_up() {
        std::thread::sleep(POLL);
        return Ok(None);
    }
    link.send(&Command::Heartbeat)?;
    let mut latest = link.receive(POLL)?;
    while let Some(feedback) = link.receive(Duration::ZERO)? {
        latest = Some(feedback);
    }
    Ok(latest)
}

/// The controller's status before anything is sent: the first feedback of the session.
fn first_feedback(link: &mut dyn Link, deadline: Duration) -> Result<Feedback, DaemonError> {
    while clock::real().now() < deadline {
        if let Some(feedback) = poll(link)? {
            return Ok(feedback);
        }
    }
    Err(DaemonError::NoFeedback(link.describe()))
}
