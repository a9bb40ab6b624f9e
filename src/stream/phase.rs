//! Where a job is in its life, and the stop and e-stop requests that may end it there: the
//! seed of the session's state machine. A request is acknowledged under the same lock the
//! cycle holds while it decides and sends a target, so an acknowledged stop is seen by the
//! next target (never one decided before it and sent after), and each request records the
//! phase it found the job in. Owns the phase and the requests only; what each phase does
//! on a stop is its owner's (the wait for a hold, the planner's caller, the cycle).

use serde::Serialize;
use std::sync::atomic::{AtomicBool, AtomicU8, Ordering};
use std::sync::{Mutex, MutexGuard, PoisonError};

/// The phases of a job, in the order a job passes them (a link loss goes back to waiting).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Phase {
    /// No session with the controller yet: the link is connecting (or reconnecting).
    WaitingForController,
    /// A session, waiting for the controller to hold at rest (at the start, before a resume).
    WaitingForHold,
    /// The plan is being made from the held position; the arm is at rest.
    Planning,
    /// After a link loss or a stall: planning and streaming the way back to the path.
    Resuming,
    /// Targets of the job's own trajectory flow.
    Streaming,
}

impl Phase {
    const ALL: [Phase; 5] = [
        Phase::WaitingForController,
        Phase::WaitingForHold,
        Phase::Planning,
        Phase::Resuming,
        Phase::Streaming,
    ];

    /// Its name, as the HTTP API and the report spell it.
    pub fn name(self) -> &'static str {
        match self {
            Phase::WaitingForController => "waiting_for_controller",
            Phase::WaitingForHold => "waiting_for_hold",
            Phase::Planning => "planning",
            Phase::Resuming => "resuming",
            Phase::Streaming => "streaming",
        }
    }

    /// Whether targets can move the arm in this phase; in the others it is at rest.
    pub fn moves(self) -> bool {
        matches!(self, Phase::Resuming | Phase::Streaming)
    }

    /// 0 stands for "none" in the atomics below.
    fn code(self) -> u8 {
        Phase::ALL
            .iter()
            .position(|p| *p == self)
            .map_or(0, |i| i as u8 + 1)
    }

    fn from_code(code: u8) -> Option<Phase> {
        Phase::ALL.get(usize::from(code).checked_sub(1)?).copied()
    }
}

impl std::fmt::Display for Phase {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// The job's phase and its stop and e-stop requests, with the phase each one found.
#[derive(Debug)]
pub struct Halting {
    phase: AtomicU8,
    stop: AtomicBool,
    estop: AtomicBool,
    stopped_in: AtomicU8,
    estopped_in: AtomicU8,
    /// Held by a request while it is acknowledged and by the cycle while it decides and
    /// sends a target: the two never interleave.
    acknowledging: Mutex<()>,
}

impl Default for Halting {
    /// A job starts by waiting for its controller.
    fn default() -> Self {
        Self {
            phase: AtomicU8::new(Phase::WaitingForController.code()),
            stop: AtomicBool::new(false),
            estop: AtomicBool::new(false),
            stopped_in: AtomicU8::new(0),
            estopped_in: AtomicU8::new(0),
            acknowledging: Mutex::new(()),
        }
    }
}

impl Halting {
    /// Held while a target is decided and sent; a request waits for it (one cycle's send
    /// at most). Must not be held when a request is made on the same thread.
    pub fn exclusive(&self) -> MutexGuard<'_, ()> {
        self.acknowledging
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
    }

    /// Asks for a stop; the phase the job was in (the first request's, when repeated).
    pub fn stop(&self) -> Phase {
        let _acknowledging = self.exclusive();
        Self::request(&self.stop, &self.stopped_in, self.phase())
    }

    /// Asks for an e-stop; the phase the job was in (the first request's, when repeated).
    pub fn estop(&self) -> Phase {
        let _acknowledging = self.exclusive();
        Self::request(&self.estop, &self.estopped_in, self.phase())
    }

    fn request(flag: &AtomicBool, found: &AtomicU8, phase: Phase) -> Phase {
        if !flag.swap(true, Ordering::SeqCst) {
            found.store(phase.code(), Ordering::SeqCst);
        }
        Phase::from_code(found.load(Ordering::SeqCst)).unwrap_or(phase)
    }

    /// The job enters `phase`. True when a stop or e-stop was asked for already: the caller
    /// ends the job there (a request made after this sees the new phase).
    pub fn enter(&self, phase: Phase) -> bool {
        let _acknowledging = self.exclusive();
        self.phase.store(phase.code(), Ordering::SeqCst);
        self.is_stopping() || self.is_estopped()
    }

    pub fn phase(&self) -> Phase {
        Phase::from_code(self.phase.load(Ordering::SeqCst)).unwrap_or(Phase::WaitingForController)
    }

    pub fn is_stopping(&self) -> bool {
        self.stop.load(Ordering::SeqCst)
    }

    pub fn is_estopped(&self) -> bool {
        self.estop.load(Ordering::SeqCst)
    }

    /// The phase the job was in when its stop was acknowledged, if one was.
    pub fn stopped_in(&self) -> Option<Phase> {
        Phase::from_code(self.stopped_in.load(Ordering::SeqCst))
    }

    /// The phase the job was in when its e-stop was acknowledged, if one was.
    pub fn estopped_in(&self) -> Option<Phase> {
        Phase::from_code(self.estopped_in.load(Ordering::SeqCst))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_request_records_the_phase_it_found_and_a_later_entry_sees_it() {
        let halting = Halting::default();
        assert!(!halting.enter(Phase::Planning));
        assert_eq!(halting.stop(), Phase::Planning);
        assert!(halting.enter(Phase::Streaming), "the stop is seen on entry");
        assert_eq!(halting.stop(), Phase::Planning, "the first request's phase");
        assert_eq!(halting.stopped_in(), Some(Phase::Planning));
        assert_eq!(halting.estopped_in(), None);
        assert_eq!(halting.estop(), Phase::Streaming);
    }

    #[test]
    fn every_phase_survives_its_code() {
        for phase in Phase::ALL {
            assert_eq!(Phase::from_code(phase.code()), Some(phase));
        }
        assert_eq!(Phase::from_code(0), None);
    }
}
