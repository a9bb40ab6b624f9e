//! The session's state machine: where a streaming session (a planned job, a replay, a jog,
//! a retargeted motion) is in its life, and the stop and e-stop requests that end it. Every
//! mode passes through the same [`Phase`]s, and a request means the same in each: at rest
//! (waiting for the controller or the hold, planning) the session ends before any target;
//! moving (resuming, streaming, holding) it enters `Stopping` and the cycle brings the arm
//! to rest along its path; at the end it is `Ended`. A request is acknowledged under the
//! same lock the cycle holds while it decides and sends a target, so an acknowledged stop
//! is seen by the next target (never one decided before it and sent after), and each
//! request records the phase it found the session in. Owns the phase, its transitions and
//! the requests only; what each phase does is its owner's (the wait for a hold, the
//! planner's caller, the cycle).

use serde::Serialize;
use std::sync::atomic::{AtomicBool, AtomicU8, Ordering};
use std::sync::{Mutex, MutexGuard, PoisonError};

/// The phases of a session, in the order it passes them (a link loss goes back to
/// waiting; streaming and holding alternate; a stop leads through stopping to the end).
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
    /// Targets of the session's motion flow.
    Streaming,
    /// Targets flow but hold the arm at rest: paused, a speed override of 0 %, or an online
    /// session waiting for its next command.
    Holding,
    /// A stop (or e-stop) was acknowledged while targets flowed: braking to rest.
    Stopping,
    /// Nothing more is sent in this session.
    Ended,
}

impl Phase {
    const ALL: [Phase; 8] = [
        Phase::WaitingForController,
        Phase::WaitingForHold,
        Phase::Planning,
        Phase::Resuming,
        Phase::Streaming,
        Phase::Holding,
        Phase::Stopping,
        Phase::Ended,
    ];

    /// Its name, as the HTTP API and the report spell it.
    pub fn name(self) -> &'static str {
        match self {
            Phase::WaitingForController => "waiting_for_controller",
            Phase::WaitingForHold => "waiting_for_hold",
            Phase::Planning => "planning",
            Phase::Resuming => "resuming",
            Phase::Streaming => "streaming",
            Phase::Holding => "holding",
            Phase::Stopping => "stopping",
            Phase::Ended => "ended",
        }
    }

    /// Whether targets flow (and may move the arm) in this phase; in the others it is at
    /// rest and nothing is sent.
    pub fn moves(self) -> bool {
        matches!(
            self,
            Phase::Resuming | Phase::Streaming | Phase::Holding | Phase::Stopping
        )
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
        self.request(&self.stop, &self.stopped_in)
    }

    /// Asks for an e-stop; the phase the job was in (the first request's, when repeated).
    pub fn estop(&self) -> Phase {
        let _acknowledging = self.exclusive();
        self.request(&self.estop, &self.estopped_in)
    }

    /// Sets the flag, records the phase found (the first request's), and moves a session
    /// whose targets flow to `Stopping`; one at rest ends at its next [`Halting::enter`].
    fn request(&self, flag: &AtomicBool, found: &AtomicU8) -> Phase {
        let phase = self.phase();
        if !flag.swap(true, Ordering::SeqCst) {
            found.store(phase.code(), Ordering::SeqCst);
        }
        if phase.moves() {
            self.phase.store(Phase::Stopping.code(), Ordering::SeqCst);
        }
        Phase::from_code(found.load(Ordering::SeqCst)).unwrap_or(phase)
    }

    /// The session enters `phase`. True when a stop or e-stop was asked for already: the
    /// caller ends the session there, so it is `Ended` for any later request instead (a
    /// request made after this sees the new phase).
    pub fn enter(&self, phase: Phase) -> bool {
        let _acknowledging = self.exclusive();
        let halted = self.is_stopping() || self.is_estopped();
        let phase = match phase {
            _ if halted && self.phase() == Phase::Stopping => Phase::Stopping,
            _ if halted => Phase::Ended,
            phase => phase,
        };
        self.phase.store(phase.code(), Ordering::SeqCst);
        halted
    }

    /// The cycle, holding [`Halting::exclusive`], says whether its targets move the arm
    /// (`Streaming`) or hold it (`Holding`); any other phase (resuming, stopping, ended)
    /// stays.
    pub fn streaming(&self, _held: &MutexGuard<'_, ()>, moving: bool) {
        if !matches!(self.phase(), Phase::Streaming | Phase::Holding) {
            return;
        }
        let phase = if moving {
            Phase::Streaming
        } else {
            Phase::Holding
        };
        self.phase.store(phase.code(), Ordering::SeqCst);
    }

    /// The session is over: nothing more is sent.
    pub fn end(&self) {
        let _acknowledging = self.exclusive();
        self.phase.store(Phase::Ended.code(), Ordering::SeqCst);
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
        assert_eq!(
            halting.phase(),
            Phase::Ended,
            "a stopped session at rest ends"
        );
        assert_eq!(halting.estop(), Phase::Ended);
    }

    #[test]
    fn a_stop_while_targets_flow_brakes_and_then_ends() {
        let halting = Halting::default();
        assert!(!halting.enter(Phase::Streaming));
        halting.streaming(&halting.exclusive(), false);
        assert_eq!(halting.phase(), Phase::Holding);
        assert_eq!(halting.stop(), Phase::Holding, "the phase the stop found");
        assert_eq!(halting.phase(), Phase::Stopping);
        halting.streaming(&halting.exclusive(), true);
        assert_eq!(
            halting.phase(),
            Phase::Stopping,
            "the cycle cannot undo a stop"
        );
        assert!(halting.enter(Phase::Streaming));
        assert_eq!(halting.phase(), Phase::Stopping);
        halting.end();
        assert_eq!(halting.phase(), Phase::Ended);
    }

    #[test]
    fn every_phase_survives_its_code() {
        for phase in Phase::ALL {
            assert_eq!(Phase::from_code(phase.code()), Some(phase));
        }
        assert_eq!(Phase::from_code(0), None);
    }
}
