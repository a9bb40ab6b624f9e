//! The streamer: a fixed-rate cycle that sends the next joint target over a [`Link`] and
//! reads the controller's feedback, measuring jitter, missed cycles, command-to-feedback
//! latency and tracking error, and checking every cycle that the controller follows
//! (`docs/protocol.md` 6.9): the echo advances, the status is ok, the arm stays within the
//! path tolerance, and reaches the goal tolerance at the end. Only then is a job
//! `completed`.
//!
//! Pause never cuts motion short: it ramps a time scale on the trajectory down to
//! standstill (and back up on resume) at a rate that keeps every axis within its limits.
//! A stop brakes along the path (`brake`): never faster than the cycle before, to rest as
//! soon as the accelerations allow; before the first target it sends no target at all.
//! A last gate checks every outgoing target against the rig's limits, speeds and
//! accelerations. A cycle that wakes several cycles late (a stall) sends nothing it
//! planned and ends the stream for the daemon to resume from where the arm holds. The
//! cycle allocates nothing and never touches the disk: records go to a [`CycleSink`].
//! It owns the cycle only; it must not plan, encode bytes or write files.

mod brake;
mod controller;
mod executor;
mod follow;
mod gate;
mod io;
mod online;
mod phase;

pub use crate::log::MicrosHistogram;
pub use crate::realtime::raise_priority;
pub use controller::{Incompatible, check_controller};
pub use executor::{CycleTask, Executor, ExecutorSettings, Handback};
pub use follow::Tolerances;
pub use gate::{CellGate, CellRefusal, GateCheck, GateRefusal, ModelCheck};
pub use online::{
    CellCheck, DEADMAN, Frame, IDLE_END, Jog, NoCell, OnlineCommand, OnlineCommands,
    OnlineSettings, REDUCED_SPEED_M_S, SERVO_TIMEOUT, ServoTarget, Splice, SpliceAnswer,
    SpliceRefusal,
};
pub use phase::{Halting, Phase};

use crate::clock::{self, Clock};
use crate::link::{Link, LinkCounters, LinkError, LinkEvent};
use crate::log::{JITTER_CEILING_US, Jitter};
use crate::motion::{Trajectory, TrajectoryError, validate};
use crate::protocol::{AxisValues, Command, ControllerStatus, Fault, Feedback, JointTarget};
use crate::rig::{JointKind, Rig};
use follow::Follow;
use online::Online;
use serde::Serialize;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, OnceLock};
use std::time::Duration;
use thiserror::Error;

/// The latency histogram reaches 100 ms, as the jitter's does ([`JITTER_CEILING_US`]);
/// anything later is counted there.
const LATENCY_CEILING_US: usize = 100_000;
/// How long to wait for the controller's first feedback before streaming.
const START_FEEDBACK_TIMEOUT: Duration = Duration::from_millis(200);
/// Send times kept for matching feedback to its target (by seq modulo this).
const SEND_TIMES: usize = 256;
/// Targets kept for judging a feedback against the target its controller held when it
/// measured (by seq modulo this): more than any link's [`Link::measured_cycles_behind`].
const HELD_TARGETS: usize = 8;

#[derive(Debug, Error)]
pub enum StreamError {
    #[error("trajectory refused before streaming")]
    Invalid(#[from] TrajectoryError),
    #[error("trajectory starts with {joint} at {start:.6} but the controller reports {actual:.6}")]
    StartMismatch {
        joint: String,
        start: f64,
        actual: f64,
    },
    #[error("no feedback from {link} before streaming")]
    NoFeedback { link: String },
    #[error("controller is in fault before streaming: {0}")]
    FaultAtStart(Fault),
    #[error("the controller does not admit this job")]
    Incompatible(#[from] Incompatible),
    #[error("no session with {link}: the controller has not answered the bridge's Hello")]
    NoSession { link: String },
    #[error(transparent)]
    Link(#[from] LinkError),
    #[error("the shared executor stopped before the stream ended")]
    ExecutorStopped,
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Outcome {
    /// The goal was reached within tolerance: the arm got there.
    Completed,
    Stopped,
    EStopped,
    Faulted,
    /// The safety gate refused a target: a bug upstream, never sent.
    GateRefused,
    /// No feedback for `max_silent_cycles`, the link reports it is down, or the
    /// controller restarted (an unprompted Hello).
    LinkLost,
    /// The cycle woke several cycles late: nothing planned before was sent.
    Stalled,
    /// The controller stopped taking targets (its echo stood still, or it held).
    NotFollowing,
    /// The arm left the path tolerance, or missed the goal tolerance in the goal time.
    ToleranceExceeded,
    /// A command did not fit the wire; nothing was sent.
    EncodeFailed,
    /// Refused before any motion (the trajectory, the controller, or no session).
    Refused,
}

impl std::fmt::Display for Outcome {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let name = match self {
            Outcome::Completed => "completed",
            Outcome::Stopped => "stopped",
            Outcome::EStopped => "e_stopped",
            Outcome::Faulted => "faulted",
            Outcome::GateRefused => "gate_refused",
            Outcome::LinkLost => "link_lost",
            Outcome::Stalled => "stalled",
            Outcome::NotFollowing => "not_following",
            Outcome::ToleranceExceeded => "tolerance_exceeded",
            Outcome::EncodeFailed => "encode_failed",
            Outcome::Refused => "refused",
        };
        f.write_str(name)
    }
}

/// The speed override, 0..=1 of the planned speed, like a pendant's: shared by a cell's
/// sessions, read by every cycle. A change is applied at once, ramped within the
/// accelerations (the time scale of a planned motion, rsruckig's limits of an online one).
#[derive(Debug)]
pub struct SpeedOverride(AtomicU64);

impl Default for SpeedOverride {
    /// 100 %.
    fn default() -> Self {
        Self(AtomicU64::new(1.0_f64.to_bits()))
    }
}

impl SpeedOverride {
    /// Sets the override to `fraction`; false (and unchanged) unless it is in 0..=1.
    pub fn set(&self, fraction: f64) -> bool {
        if !(0.0..=1.0).contains(&fraction) {
            return false;
        }
        self.0.store(fraction.to_bits(), Ordering::SeqCst);
        true
    }

    pub fn fraction(&self) -> f64 {
        f64::from_bits(self.0.load(Ordering::SeqCst))
    }
}

/// Pause, stop and e-stop requests, the session's phase, the speed override, the online
/// commands (jog, retarget) and progress, shared with whoever runs the session.
#[derive(Debug, Default)]
pub struct StreamControl {
    paused: AtomicBool,
    halting: Halting,
    progress_bits: AtomicU64,
    cycles: AtomicU64,
    overruns: AtomicU64,
    speed: Arc<SpeedOverride>,
    online: OnlineCommands,
    /// The workcell's check of online targets (see [`CellCheck`]); none admits all.
    cell: OnceLock<Arc<dyn CellCheck>>,
}

impl StreamControl {
    /// A session under the cell's speed override.
    pub fn with_speed(speed: Arc<SpeedOverride>) -> Self {
        Self {
            speed,
            ..Self::default()
        }
    }
    /// The override the session runs under (0..=1).
    pub fn speed(&self) -> f64 {
        self.speed.fraction()
    }
    /// The online commands: a goal or a jog given here takes over the session's motion.
    pub fn online(&self) -> &OnlineCommands {
        &self.online
    }
    /// Where the workcell's collision model checks every online target (the hook for
    /// src/cell/, issue 27); false when one was set already.
    pub fn set_cell_check(&self, check: Arc<dyn CellCheck>) -> bool {
        self.cell.set(check).is_ok()
    }
    pub fn pause(&self) {
        self.paused.store(true, Ordering::SeqCst);
    }
    pub fn resume(&self) {
        self.paused.store(false, Ordering::SeqCst);
    }
    /// Brake along the path to standstill (at once when the arm is at rest), then end the
    /// job.
    pub fn stop(&self) {
        self.halting.stop();
    }
    /// [`StreamControl::stop`]; the phase the job was in when the stop was acknowledged.
    pub fn request_stop(&self) -> Phase {
        self.halting.stop()
    }
    pub fn estop(&self) {
        self.halting.estop();
    }
    /// [`StreamControl::estop`]; the phase the job was in when it was acknowledged.
    pub fn request_estop(&self) -> Phase {
        self.halting.estop()
    }
    pub fn is_stopping(&self) -> bool {
        self.halting.is_stopping()
    }
    pub fn is_estopped(&self) -> bool {
        self.halting.is_estopped()
    }
    /// Whether a stop or an e-stop was asked for.
    pub fn is_halted(&self) -> bool {
        self.is_stopping() || self.is_estopped()
    }
    pub fn is_paused(&self) -> bool {
        self.paused.load(Ordering::SeqCst)
    }
    /// The job enters `phase`; true when a stop or e-stop was asked for already (the job
    /// ends there).
    pub fn enter(&self, phase: Phase) -> bool {
        self.halting.enter(phase)
    }
    pub fn phase(&self) -> Phase {
        self.halting.phase()
    }
    /// The session is over: its phase is `Ended` (the job's report is being written).
    pub fn end(&self) {
        self.halting.end();
    }
    /// The phase the job was in when its e-stop (else its stop) was acknowledged.
    pub fn halted_in(&self) -> Option<Phase> {
        self.halting.estopped_in().or(self.halting.stopped_in())
    }
    /// Fraction of the trajectory done, 0..=1.
    pub fn progress(&self) -> f64 {
        f64::from_bits(self.progress_bits.load(Ordering::Relaxed))
    }
    pub fn cycles(&self) -> u64 {
        self.cycles.load(Ordering::Relaxed)
    }
    /// Cycles whose work overran its budget on the shared executor, so far.
    pub fn overruns(&self) -> u64 {
        self.overruns.load(Ordering::Relaxed)
    }
}

/// One cycle as it happened.
#[derive(Debug, Clone, Copy)]
pub struct CycleRecord {
    pub target: JointTarget,
    pub feedback: Option<Feedback>,
    /// How late the cycle woke after its deadline (jitter), microseconds: the very value
    /// the stream's jitter counts for this cycle (the log records it on the command).
    pub late_us: f32,
    /// Command-to-feedback latency measured this cycle (a fresh echo), microseconds.
    pub latency_us: Option<f32>,
    /// The link's counters after this cycle.
    pub counters: LinkCounters,
    /// The clock's reading when the cycle was recorded.
    pub at: Duration,
    /// Where the job's trajectory stood this cycle, when the stream follows it (none on an
    /// approach back to the path after an interruption, or for online motion).
    pub on_job: Option<JobPosition>,
}

/// A cycle's place on the job's whole trajectory (not the part streamed since the last
/// resumption): what a program's step is found by, and its measured times.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct JobPosition {
    /// The path's position, in samples from the job's first.
    pub sample: f64,
    /// The job's I/O points done so far (the path waits at the next one until it is).
    pub io_done: usize,
}

/// Where a streamed trajectory begins on its job's whole one: its first sample, and the
/// job's I/O points before it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct JobOffset {
    pub sample: usize,
    pub io_done: usize,
}

/// Where the cycle hands its records (the recorder, a live view). Must not block.
pub trait CycleSink {
    fn record(&mut self, cycle: &CycleRecord);
}

impl CycleSink for () {
    fn record(&mut self, _: &CycleRecord) {}
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StreamSettings {
    pub feedback_timeout: Duration,
    /// Cycles in a row without feedback before the link counts as lost.
    pub max_silent_cycles: u32,
    /// Sequence number of the first target (a resumed job continues its numbering).
    pub first_seq: u32,
    /// Time scale at the first cycle: 1 runs as planned; 0 starts from standstill and
    /// ramps up (a trajectory resumed mid-motion after a link loss).
    pub start_scale: f64,
    /// How fast pause and stop may change the time scale (1/s). See [`slowdown_rate`].
    pub slowdown_rate_per_s: f64,
    /// A wake this many cycles late is a stall (docs/protocol.md 6.5).
    pub stall_cycles: u32,
    /// Cycles of targets without a new echo before the controller counts as not following.
    pub echo_patience_cycles: u32,
    pub tolerances: Tolerances,
    /// How online motion (jog, retarget) may use the rig.
    pub online: OnlineSettings,
    /// Where the streamed trajectory begins on its job's (none: an approach, not the job's
    /// path). Sets [`CycleRecord::on_job`].
    pub job_offset: Option<JobOffset>,
}

/// A wake 5 cycles late (20 ms at 250 Hz) is a stall: the arm has had no new target for
/// that long, so what was planned for those cycles is stale. Short of the controller's
/// watchdog (25 cycles), long past the scheduling noise of a loaded machine (under 1 ms).
pub const STALL_CYCLES: u32 = 5;

impl StreamSettings {
    /// Feedback awaited for half a period; the link counts as lost after 0.1 s of silence,
    /// and so does a controller whose echo stands still for as long.
    pub fn new(period: Duration, slowdown_rate_per_s: f64) -> Self {
        let silent = (0.1 / period.as_secs_f64()).ceil() as u32;
        Self {
            feedback_timeout: period / 2,
            max_silent_cycles: silent,
            first_seq: 0,
            start_scale: 1.0,
            slowdown_rate_per_s,
            stall_cycles: STALL_CYCLES,
            echo_patience_cycles: silent,
            tolerances: Tolerances::default(),
            online: OnlineSettings::default(),
            job_offset: Some(JobOffset::default()),
        }
    }
}

/// The fastest time-scale change that keeps every axis within its max acceleration, given
/// the share of speed and acceleration the plan used: the extra acceleration of a scale
/// change is rate x velocity, and the plan left (1 - accel_scale) x max accel for it.
pub fn slowdown_rate(rig: &Rig, speed_scale: f64, accel_scale: f64) -> f64 {
    rig.joints
        .iter()
        .map(|j| {
            (1.0 - accel_scale) * j.limits.max_acceleration / (speed_scale * j.limits.max_speed)
        })
        .fold(f64::INFINITY, f64::min)
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct StreamReport {
    pub outcome: Outcome,
    pub fault: Option<String>,
    pub cycles: u64,
    pub missed_cycles: u64,
    pub limit_violations: u64,
    pub feedback_timeouts: u64,
    pub jitter_p50_us: f64,
    pub jitter_p99_us: f64,
    pub jitter_max_us: f64,
    pub latency_p50_us: f64,
    pub latency_p99_us: f64,
    pub tracking_error_max_deg: f64,
    /// Cycles whose work overran its budget on the shared executor (the stream then went
    /// on on a thread of its own); always 0 on a thread of its own.
    pub overruns: u64,
    pub duration_s: f64,
    /// Whole trajectory samples passed when streaming ended (where to resume after a loss).
    pub samples_done: usize,
    /// The seq of the last target sent (the first seq of a stream that continues it).
    pub last_seq: u32,
    pub link: String,
    /// The phase the job was in when a stop or e-stop was acknowledged, if one was.
    pub stopped_in: Option<Phase>,
    /// Every stall and link loss of the job, in order, and what the bridge did after each
    /// (issue 32: a completed run lists each one, not only the last).
    pub interruptions: Vec<Interruption>,
    #[serde(flatten)]
    pub counters: LinkCounters,
    /// Every wake the jitter figures count, so that the parts of a resumed job add up to
    /// the figures of the whole (as its log gives them) rather than to the worst part's.
    #[serde(skip)]
    pub wakes: Option<MicrosHistogram>,
    /// How late the stalled wake was (us), when this stream ended in a stall.
    #[serde(skip)]
    pub stall_late_us: Option<f64>,
}

/// One stall or link loss in a job's stream: when, the stream's words for it, and what the
/// bridge did then.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Interruption {
    /// Seconds of streaming before it, from the job's first target.
    pub at_s: f64,
    /// `stalled` or `link_lost`.
    pub outcome: Outcome,
    /// The stream's words (`the cycle woke 316.0 ms late`).
    pub why: String,
    /// How late the stalled wake was (us), as the jitter counts it; `null` for a link loss.
    pub late_us: Option<f64>,
    pub then: AfterInterruption,
}

/// What the bridge did after an interruption.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum AfterInterruption {
    /// Waited for the controller's hold, went back to the path and streamed on from rest.
    Resumed,
    /// The job ended there (no hold in time, a stop, a refusal: the outcome says).
    Ended,
}

impl std::fmt::Display for AfterInterruption {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            AfterInterruption::Resumed => "resumed from rest on the path",
            AfterInterruption::Ended => "the job ended there",
        })
    }
}

impl StreamReport {
    /// The jitter figures as the report holds them (`run`'s summary line); `cycles` counts
    /// the wakes when the report still carries them.
    pub fn jitter(&self) -> Jitter {
        Jitter {
            cycles: self.wakes.as_ref().map_or(0, MicrosHistogram::count),
            p50_us: self.jitter_p50_us,
            p99_us: self.jitter_p99_us,
            max_us: self.jitter_max_us,
        }
    }

    /// A report of a stream that moved nothing: refused, or ended while waiting.
    pub fn without_motion(
        outcome: Outcome,
        fault: String,
        link: String,
        counters: LinkCounters,
    ) -> Self {
        Cycle::report_empty(outcome, fault, link, counters)
    }

    /// One report for a job streamed in several parts (resumed after link losses): counts
    /// add up, worst cases are kept, the outcome is the last part's.
    pub fn merge(self, later: StreamReport) -> StreamReport {
        // A part that completed clears an earlier part's fault: the interruptions list it.
        let fault = match later.outcome {
            Outcome::Completed => later.fault,
            _ => later.fault.or(self.fault),
        };
        let mut interruptions = self.interruptions;
        interruptions.extend(later.interruptions);
        let wakes = match (self.wakes, later.wakes) {
            (Some(mut earlier), Some(later)) => {
                earlier.add(&later);
                Some(earlier)
            }
            (earlier, later) => earlier.or(later),
        };
        let jitter = wakes.as_ref().map(Jitter::of).unwrap_or_default();
        StreamReport {
            outcome: later.outcome,
            fault,
            interruptions,
            wakes,
            cycles: self.cycles + later.cycles,
            missed_cycles: self.missed_cycles + later.missed_cycles,
            limit_violations: self.limit_violations + later.limit_violations,
            feedback_timeouts: self.feedback_timeouts + later.feedback_timeouts,
            jitter_p50_us: jitter.p50_us,
            jitter_p99_us: jitter.p99_us,
            jitter_max_us: jitter.max_us,
            latency_p50_us: self.latency_p50_us.max(later.latency_p50_us),
            latency_p99_us: self.latency_p99_us.max(later.latency_p99_us),
            tracking_error_max_deg: self
                .tracking_error_max_deg
                .max(later.tracking_error_max_deg),
            overruns: self.overruns + later.overruns,
            duration_s: self.duration_s + later.duration_s,
            ..later
        }
    }
}

/// Streams `trajectory` to the controller behind `link`, one sample per period, on the
/// calling thread: it sleeps to each deadline on `clock`.
pub fn stream(
    trajectory: &Trajectory,
    rig: &Rig,
    link: &mut dyn Link,
    clock: &dyn Clock,
    sink: &mut dyn CycleSink,
    control: &StreamControl,
    settings: &StreamSettings,
) -> Result<StreamReport, StreamError> {
    let mut run = Run::prepare(trajectory, rig, link, clock, sink, control, settings)?;
    let start = clock.now();
    run.on_own_thread(clock, start);
    run.finish()
}

/// [`stream`] for a trajectory that was not checked whole against the cell before it was
/// handed over: the gate also checks each target's step from the one before against
/// `model` ([`CellGate`]), and refuses (outcome `gate_refused`, nothing of it sent) a target
/// that comes closer to anything than the margin.
#[allow(clippy::too_many_arguments)]
pub fn stream_in_cell(
    trajectory: &Trajectory,
    rig: &Rig,
    model: &crate::cell::CollisionModel,
    link: &mut dyn Link,
    clock: &dyn Clock,
    sink: &mut dyn CycleSink,
    control: &StreamControl,
    settings: &StreamSettings,
) -> Result<StreamReport, StreamError> {
    let mut run = Run::prepare(trajectory, rig, link, clock, sink, control, settings)?;
    run.cell = Some(CellGate::new(model));
    let start = clock.now();
    run.on_own_thread(clock, start);
    run.finish()
}

/// [`stream`] with its cycles run by `executor` beside other streams' (the calling thread
/// waits meanwhile). A stream whose cycle work overruns its budget is handed back and goes
/// on on the calling thread, on the executor's clock, so it delays no other stream again.
#[allow(clippy::too_many_arguments)]
pub fn stream_shared(
    executor: &Executor,
    trajectory: &Trajectory,
    rig: &Rig,
    link: &mut dyn Link,
    clock: &dyn Clock,
    sink: &mut (dyn CycleSink + Send),
    control: &StreamControl,
    settings: &StreamSettings,
) -> Result<StreamReport, StreamError> {
    let mut run = Run::prepare(trajectory, rig, link, clock, sink, control, settings)?;
    match executor.run(&mut run)? {
        Handback::Ended => {}
        Handback::Evicted { next_deadline } => run.on_own_thread(executor.clock(), next_deadline),
    }
    run.finish()
}

/// One stream between its start checks and its end: the cycle's state and what it drives.
/// Its cycle is split in two halves, so that an executor can pass every due stream's gate
/// before any stream's feedback: [`Run::send_half`] (the wake, events, the next target
/// through the gate, sent) and [`Run::receive_half`] (its feedback, the following checks).
struct Run<'a, S: CycleSink + ?Sized> {
    cycle: Cycle,
    trajectory: &'a Trajectory,
    rig: &'a Rig,
    link: &'a mut dyn Link,
    clock: &'a dyn Clock,
    sink: &'a mut S,
    control: &'a StreamControl,
    period: Duration,
    stall_after: Duration,
    /// The target the send half sent, awaiting its feedback in the receive half.
    sent: Option<Sent>,
    /// How the stream ended, once it has.
    end: Option<Result<Outcome, StreamError>>,
    /// The cell's collision model, for a trajectory not checked whole before streaming.
    cell: Option<CellGate<'a>>,
}

#[derive(Clone, Copy)]
struct Sent {
    target: JointTarget,
    finished: bool,
    /// Feedback that was already waiting before the target went out.
    late: Option<Feedback>,
}

impl<'a, S: CycleSink + ?Sized> Run<'a, S> {
    fn prepare(
        trajectory: &'a Trajectory,
        rig: &'a Rig,
        link: &'a mut dyn Link,
        clock: &'a dyn Clock,
        sink: &'a mut S,
        control: &'a StreamControl,
        settings: &StreamSettings,
    ) -> Result<Self, StreamError> {
        validate(trajectory, rig)?;
        let echo = check_start(trajectory, rig, link, settings)?;
        // Within one session the controller drops a target not newer than the last it took
        // (docs/protocol.md 6.3): a stream after another (the next job on a daemon's link)
        // numbers on from the controller's echo.
        let settings = &StreamSettings {
            first_seq: newer_seq(settings.first_seq, echo),
            // A plan starts at rest: it may start at the override's pace at once.
            start_scale: settings.start_scale.min(control.speed()),
            ..*settings
        };
        let period = trajectory.period;
        let mut cycle = Cycle::new(trajectory, rig, settings);
        cycle.behind = link.measured_cycles_behind().min(HELD_TARGETS as u32 - 1);
        Ok(Run {
            cycle,
            trajectory,
            rig,
            link,
            clock,
            sink,
            control,
            period,
            stall_after: period * settings.stall_cycles,
            sent: None,
            end: None,
            cell: None,
        })
    }

    /// Runs the cycles on the calling thread from `start` on `clock`, the first deadline;
    /// deadlines count from there (a resumed stream starts at once).
    fn on_own_thread(&mut self, clock: &dyn Clock, start: Duration) {
        let first = self.cycle.seq;
        loop {
            let deadline = start + self.period * (self.cycle.seq - first);
            clock.sleep_until(deadline);
            let late = clock.now().saturating_sub(deadline);
            if self.send_half(late) || self.receive_half() {
                return;
            }
        }
    }

    fn finish(self) -> Result<StreamReport, StreamError> {
        let outcome = self.end.unwrap_or(Err(StreamError::ExecutorStopped))?;
        Ok(self.cycle.report(
            outcome,
            self.trajectory.period,
            self.link.counters(),
            self.link.describe(),
        ))
    }

    /// The cycle woke `late` after its deadline: recorded; a stall ends the stream before
    /// anything is sent; otherwise events, the next target through the gate, and the send.
    /// True once the stream has ended.
    fn send_half(&mut self, late: Duration) -> bool {
        self.cycle.record_wake(late, self.period);
        // Checked before anything is sent: what was planned for the stalled cycles is stale.
        let result = if late > self.stall_after {
            self.link
                .send(&Command::Stop)
                .map_err(StreamError::from)
                .map(|()| {
                    self.cycle.count_wake();
                    self.cycle.stall_late_us = Some(self.cycle.wake_us());
                    self.cycle.fault = Some(format!(
                        "the cycle woke {:.1} ms late",
                        late.as_secs_f64() * 1e3
                    ));
                    Some(Outcome::Stalled)
                })
        } else {
            self.gate_and_send()
        };
        self.settle(result)
    }

    /// The second half: the sent target's feedback, the sink, the following checks.
    fn receive_half(&mut self) -> bool {
        let result = self.feedback();
        self.settle(result)
    }

    fn settle(&mut self, result: Result<Option<Outcome>, StreamError>) -> bool {
        match result {
            Ok(None) => false,
            Ok(Some(outcome)) => {
                self.end = Some(Ok(outcome));
                true
            }
            Err(error) => {
                self.end = Some(Err(error));
                true
            }
        }
    }

    /// Events, the next target through the gate, sent. `Some(outcome)` ends the stream.
    /// The target is decided and sent while a stop or e-stop cannot be acknowledged, so an
    /// acknowledged one is seen by the next target.
    fn gate_and_send(&mut self) -> Result<Option<Outcome>, StreamError> {
        let (cycle, link) = (&mut self.cycle, &mut *self.link);
        let late = latest_feedback(link)?;
        let _acknowledging = self.control.halting.exclusive();
        if self.control.is_estopped() {
            link.send(&Command::EStop)?;
            return Ok(Some(Outcome::EStopped));
        }
        if let Some(outcome) = cycle.events(link) {
            if outcome == Outcome::EncodeFailed {
                link.send(&Command::Stop)?;
            }
            return Ok(Some(outcome));
        }
        // Nothing sent yet: the arm is at rest where the controller holds it.
        if self.control.is_stopping() && cycle.sent.previous.is_none() {
            link.send(&Command::Stop)?;
            return Ok(Some(Outcome::Stopped));
        }
        let stopping = self.control.is_stopping() || cycle.aborting.is_some();
        if let Err(failed) = cycle.io.step(cycle.path, link, stopping) {
            cycle.fault.get_or_insert(failed.to_string());
            cycle.aborting = Some(Outcome::Faulted);
        }
        let (positions, velocities, finished) = cycle.next(self.control, self.trajectory, self.rig);
        self.control
            .halting
            .streaming(&_acknowledging, cycle.scale > 0.0);
        let Some(target) = cycle.target(
            positions,
            velocities,
            self.trajectory.period,
            self.rig,
            self.cell.as_mut(),
        ) else {
            link.send(&Command::Stop)?;
            return Ok(Some(Outcome::GateRefused));
        };
        link.send(&Command::Target(target))?;
        cycle.sent_at[target.seq as usize % SEND_TIMES] = self.clock.now();
        self.sent = Some(Sent {
            target,
            finished,
            late,
        });
        Ok(None)
    }

    /// The feedback of the target sent, the sink, the following checks.
    fn feedback(&mut self) -> Result<Option<Outcome>, StreamError> {
        let Some(Sent {
            target,
            finished,
            late,
        }) = self.sent.take()
        else {
            return Ok(None);
        };
        let (cycle, link, clock, control) =
            (&mut self.cycle, &mut *self.link, self.clock, self.control);
        let feedback = await_echo(link, target.seq, cycle.feedback_timeout)?.or(late);
        // What the feedback is judged against, by the tracking figure and the following
        // check alike: the target the controller held when it measured.
        let reference = feedback.map_or(target.positions, |f| cycle.held_when_measured(&f));
        let latency_us = cycle.record_feedback(feedback.as_ref(), &reference, clock.now());
        // Counted where the sink gets it: the log holds the same wakes as the figures.
        cycle.count_wake();
        self.sink.record(&CycleRecord {
            target,
            feedback,
            late_us: cycle.last_late_us,
            latency_us: latency_us.map(|us| us as f32),
            counters: link.counters(),
            at: clock.now(),
            on_job: cycle.on_job(),
        });
        control.cycles.store(cycle.seq as u64, Ordering::Relaxed);
        control
            .progress_bits
            .store(cycle.progress(self.trajectory).to_bits(), Ordering::Relaxed);
        if let Some(ControllerStatus::Fault(fault)) = feedback.map(|f| f.status) {
            cycle.fault = Some(format!("controller fault: {fault}"));
            return Ok(Some(Outcome::Faulted));
        }
        let verdict = cycle
            .follow
            .check(feedback.as_ref(), &reference, finished, clock.now());
        if let Some(outcome) = cycle.conclude(verdict, finished) {
            if outcome != Outcome::Completed {
                link.send(&Command::Stop)?;
            }
            return Ok(Some(outcome));
        }
        if cycle.silent_cycles > cycle.max_silent_cycles || !link.is_up() {
            return Ok(Some(Outcome::LinkLost));
        }
        Ok(None)
    }
}

impl<S: CycleSink + Send + ?Sized> CycleTask for Run<'_, S> {
    fn period(&self) -> Duration {
        self.period
    }

    fn send_half(&mut self, late: Duration) -> bool {
        Run::send_half(self, late)
    }

    fn receive_half(&mut self) -> bool {
        Run::receive_half(self)
    }

    fn overran(&mut self) {
        self.cycle.overruns += 1;
        self.control.overruns.fetch_add(1, Ordering::Relaxed);
    }
}

/// Whatever feedback is already waiting, newest last: read before sending, so a cycle
/// never mistakes the previous cycle's late answer for its own.
fn latest_feedback(link: &mut dyn Link) -> Result<Option<Feedback>, LinkError> {
    let mut latest = None;
    while let Some(feedback) = link.receive(Duration::ZERO)? {
        latest = Some(feedback);
    }
    Ok(latest)
}

/// Waits up to `timeout` for the feedback that echoes `seq` (or a later one). The deadline
/// is real time on purpose: it bounds a wait on a real transport, which a virtual clock
/// (which only jumps) could not.
fn await_echo(
    link: &mut dyn Link,
    seq: u32,
    timeout: Duration,
) -> Result<Option<Feedback>, LinkError> {
    let deadline = clock::real().now() + timeout;
    let mut latest = None;
    while let Some(feedback) = link.receive(deadline.saturating_sub(clock::real().now()))? {
        latest = Some(feedback);
        if feedback.seq >= seq {
            break;
        }
    }
    Ok(latest)
}

/// The newer of two wrapping sequence numbers (docs/protocol.md 6.3).
fn newer_seq(ours: u32, echo: u32) -> u32 {
    let d = echo.wrapping_sub(ours);
    if d != 0 && d < 1 << 31 { echo } else { ours }
}

/// Checks the session and the controller's Hello, asks for feedback, and checks the
/// trajectory starts where the controller is. Returns the seq the controller echoes.
fn check_start(
    trajectory: &Trajectory,
    rig: &Rig,
    link: &mut dyn Link,
    settings: &StreamSettings,
) -> Result<u32, StreamError> {
    if !link.is_up() {
        return Err(StreamError::NoSession {
            link: link.describe(),
        });
    }
    if let Some(hello) = link.controller_hello() {
        check_controller(&hello, rig, trajectory.period)?;
    }
    // Targets flow in this session only: a later one needs a new start from a hold.
    link.adopt_session();
    link.send(&Command::Heartbeat)?;
    // A remote controller answers at its next cycle: give it a few, not half of one.
    let wait = settings.feedback_timeout.max(START_FEEDBACK_TIMEOUT);
    let Some(feedback) = await_echo(link, 0, wait)?
        .map(Ok)
        .or_else(|| latest_feedback(link).transpose())
        .transpose()?
    else {
        return Err(StreamError::NoFeedback {
            link: link.describe(),
        });
    };
    if let ControllerStatus::Fault(fault) = feedback.status {
        return Err(StreamError::FaultAtStart(fault));
    }
    let first = trajectory.position(0);
    let dt = trajectory.period.as_secs_f64();
    for ((joint, start), actual) in rig
        .joints
        .iter()
        .zip(first.iter())
        .zip(feedback.positions.as_slice())
    {
        if !joint.limits.step_ok(start - actual, dt) {
            return Err(StreamError::StartMismatch {
                joint: joint.name.clone(),
                start: *start,
                actual: *actual,
            });
        }
    }
    Ok(feedback.seq)
}

/// The cycle's state and measurements.
struct Cycle {
    seq: u32,
    /// Position along the trajectory, in samples.
    path: f64,
    /// Time scale: 1 runs the trajectory as planned, 0 holds still.
    scale: f64,
    scale_step: f64,
    /// The last two targets sent: the gate checks steps and accelerations against them.
    sent: gate::Sent,
    /// The wakes that sent a target and the stalled ones (see [`Jitter`]).
    jitter: MicrosHistogram,
    latency: MicrosHistogram,
    stall_late_us: Option<f64>,
    missed: u64,
    timeouts: u64,
    violations: u64,
    tracking_max: f64,
    overruns: u64,
    revolute: Vec<bool>,
    fault: Option<String>,
    sent_at: [Duration; SEND_TIMES],
    /// The targets sent last, by seq modulo [`HELD_TARGETS`], and where the arm stood
    /// before the first (the trajectory's start, checked against the controller).
    held: [(u32, AxisValues); HELD_TARGETS],
    start: AxisValues,
    /// Cycles between the target a feedback echoes and the one its position was measured
    /// against ([`Link::measured_cycles_behind`]).
    behind: u32,
    silent_cycles: u32,
    max_silent_cycles: u32,
    first_seq: u32,
    last_echo: Option<u32>,
    last_late_us: f32,
    feedback_timeout: Duration,
    follow: Follow,
    /// Why the stream is being brought to rest, when it is not the user's stop.
    aborting: Option<Outcome>,
    /// Online motion, once a command took over from the trajectory.
    online: Online,
    /// The commanded velocities of the target before the last (its acceleration).
    velocity_before: Option<AxisValues>,
    /// The trajectory's I/O points: where the path waits for the controller.
    io: io::IoRun,
    job_offset: Option<JobOffset>,
}

impl Cycle {
    fn new(trajectory: &Trajectory, rig: &Rig, settings: &StreamSettings) -> Self {
        let start = brake::sample_at(trajectory, 0.0, 0.0).0;
        Self {
            seq: settings.first_seq,
            first_seq: settings.first_seq,
            last_echo: None,
            sent_at: [Duration::ZERO; SEND_TIMES],
            held: [(settings.first_seq, start); HELD_TARGETS],
            start,
            behind: 0,
            silent_cycles: 0,
            max_silent_cycles: settings.max_silent_cycles,
            path: 0.0,
            scale: settings.start_scale.clamp(0.0, 1.0),
            scale_step: settings.slowdown_rate_per_s * trajectory.period.as_secs_f64(),
            sent: gate::Sent::default(),
            jitter: MicrosHistogram::new(JITTER_CEILING_US),
            latency: MicrosHistogram::new(LATENCY_CEILING_US),
            stall_late_us: None,
            missed: 0,
            timeouts: 0,
            violations: 0,
            tracking_max: 0.0,
            overruns: 0,
            revolute: rig
                .joints
                .iter()
                .map(|j| j.kind == JointKind::Revolute)
                .collect(),
            fault: None,
            last_late_us: 0.0,
            feedback_timeout: settings.feedback_timeout,
            follow: Follow::new(rig, settings),
            aborting: None,
            online: Online::new(
                rig,
                trajectory.period,
                settings.online,
                settings.slowdown_rate_per_s * trajectory.period.as_secs_f64(),
            ),
            velocity_before: None,
            io: io::IoRun::new(trajectory),
            job_offset: settings.job_offset,
        }
    }

    /// This cycle's place on the job's trajectory; none once online motion took over.
    fn on_job(&self) -> Option<JobPosition> {
        let offset = self.job_offset?;
        if self.online.engaged() {
            return None;
        }
        Some(JobPosition {
            sample: offset.sample as f64 + self.path,
            io_done: offset.io_done + self.io.done(),
        })
    }

    fn progress(&self, trajectory: &Trajectory) -> f64 {
        let last = trajectory.len().saturating_sub(1).max(1) as f64;
        (self.path / last).min(1.0)
    }

    /// The wake, `late` after its deadline: kept for [`Cycle::count_wake`], counted as
    /// missed when later than a period.
    fn record_wake(&mut self, late: Duration, period: Duration) {
        self.last_late_us = (late.as_secs_f64() * 1e6) as f32;
        if late > period {
            self.missed += 1;
        }
    }

    /// The last wake's lateness (us) as the jitter counts it and the log writes it: the
    /// cycle record's `f32`, widened exactly, so the log reads back the very value.
    fn wake_us(&self) -> f64 {
        f64::from(self.last_late_us)
    }

    /// Counts the last wake in the jitter: one that sent a target, or stalled.
    fn count_wake(&mut self) {
        self.jitter.record(self.wake_us());
    }

    /// The link's events: a controller fault ends the stream with its words; a
    /// controller that restarted (or a new session) is link loss; a command that did
    /// not fit the wire ends it too; a link that no longer trusts what it hears brings the
    /// arm to rest first.
    fn events(&mut self, link: &mut dyn Link) -> Option<Outcome> {
        // One event a cycle: each of them ends the stream.
        if let Some(event) = link.next_event() {
            match event {
                LinkEvent::Fault(report) => {
                    self.fault = Some(fault_text(&report.fault, &report.text));
                    return Some(Outcome::Faulted);
                }
                LinkEvent::ControllerRestarted | LinkEvent::Session(_) => {
                    self.fault = Some("the controller restarted (unprompted Hello)".into());
                    return Some(Outcome::LinkLost);
                }
                LinkEvent::EncodeFailed(error) => {
                    self.fault = Some(format!("a command does not fit the wire: {error}"));
                    return Some(Outcome::EncodeFailed);
                }
                LinkEvent::Untrusted(words) => {
                    // The arm still follows our targets only: bring it to rest along the
                    // path, then end faulted (see `Cycle::report`: never resumed).
                    self.fault = Some(words);
                    self.aborting = Some(Outcome::Faulted);
                }
            }
        }
        None
    }

    /// The next target's positions and velocities, and whether the motion's end is reached:
    /// online once a command was given (from the last target sent, or from the start),
    /// along the trajectory before.
    fn next(
        &mut self,
        control: &StreamControl,
        trajectory: &Trajectory,
        rig: &Rig,
    ) -> (AxisValues, AxisValues, bool) {
        if !self.online.engaged()
            && !control.online.given()
            && !self.splice(control, trajectory, rig)
        {
            let finished = self.advance(control, trajectory, rig);
            let (positions, velocities) = brake::sample_at(trajectory, self.path, self.scale);
            return (positions, velocities, finished);
        }
        if !self.online.engaged() {
            self.online.start_at(&trajectory.position(0));
            self.online.engage(&self.sent, self.velocity_before);
        }
        self.seq += 1;
        let stopping = control.is_stopping() || self.aborting.is_some();
        let speed = if control.is_paused() {
            0.0
        } else {
            control.speed()
        };
        let cell: &dyn CellCheck = match control.cell.get() {
            Some(check) => check.as_ref(),
            None => &NoCell,
        };
        let step = self
            .online
            .step(rig, &control.online, stopping, speed, cell);
        self.scale = if step.moving { 1.0 } else { 0.0 };
        if stopping && !step.moving {
            self.aborting.get_or_insert(Outcome::Stopped);
        }
        (step.positions, step.velocities, step.finished && !stopping)
    }

    /// A splice waiting while the planned path streams: taken from the last target sent (at
    /// the path's time scale), or refused with the path going on as before. True when taken.
    fn splice(&mut self, control: &StreamControl, trajectory: &Trajectory, rig: &Rig) -> bool {
        if !control.online.splice_waiting() {
            return false;
        }
        self.online.start_at(&trajectory.position(0));
        self.online.engage(&self.sent, self.velocity_before);
        let stopping = control.is_stopping() || self.aborting.is_some();
        let taken = self
            .online
            .try_splice(rig, &control.online, self.scale, stopping);
        if !taken {
            self.online.disengage();
        }
        taken
    }

    /// Moves along the path by the time scale: when stopping (or aborting) by the rate of
    /// [`brake::rate`], otherwise ramping it toward 0 when paused, toward 1 otherwise. True
    /// once the path's end is reached (the goal check then decides); `Stopped` (or the
    /// abort's reason) is decided in [`Cycle::conclude`].
    fn advance(&mut self, control: &StreamControl, trajectory: &Trajectory, rig: &Rig) -> bool {
        self.seq += 1;
        let stopping = control.is_stopping() || self.aborting.is_some();
        let last = (trajectory.len() - 1) as f64;
        self.scale = if stopping {
            brake::rate(
                &brake::Motion {
                    trajectory,
                    rig,
                    path: self.path,
                    rate: self.scale,
                },
                &self.sent,
            )
        } else {
            let wanted = if control.is_paused() {
                0.0
            } else {
                control.speed()
            };
            if wanted > self.scale {
                (self.scale + self.scale_step).min(wanted)
            } else {
                (self.scale - self.scale_step).max(wanted)
            }
        };
        // An I/O point not done yet holds the path there (the arm is at rest at it).
        let hold = self
            .io
            .hold_at()
            .map_or(last, |sample| (sample as f64).min(last));
        self.path = (self.path + self.scale).min(hold);
        if stopping && self.scale == 0.0 && self.path < last {
            self.aborting.get_or_insert(Outcome::Stopped);
        }
        self.path >= last && self.io.hold_at().is_none()
    }

    /// Turns the following check's verdict into the stream's end, if it is one. A path
    /// tolerance breach brings the arm to rest along the path first.
    fn conclude(&mut self, verdict: follow::Verdict, finished: bool) -> Option<Outcome> {
        use follow::Verdict;
        match verdict {
            Verdict::Following if finished && self.aborting.is_none() => None,
            Verdict::GoalReached if self.aborting.is_none() => Some(Outcome::Completed),
            Verdict::NotFollowing(text) => {
                self.fault = Some(text);
                Some(Outcome::NotFollowing)
            }
            Verdict::OffPath(text) | Verdict::GoalMissed(text) if finished || self.scale == 0.0 => {
                self.fault.get_or_insert(text);
                Some(Outcome::ToleranceExceeded)
            }
            Verdict::OffPath(text) => {
                self.fault.get_or_insert(text);
                self.aborting = Some(Outcome::ToleranceExceeded);
                None
            }
            _ if self.scale == 0.0 && self.aborting.is_some() => self.aborting,
            _ => None,
        }
    }

    /// The target of these positions and velocities, if it passes the gate (and `cell`'s
    /// collision check, when the trajectory was not checked whole).
    fn target(
        &mut self,
        positions: AxisValues,
        velocities: AxisValues,
        period: Duration,
        rig: &Rig,
        cell: Option<&mut CellGate<'_>>,
    ) -> Option<JointTarget> {
        // The gate's maths is in seconds.
        let dt = period.as_secs_f64();
        if let Err(refusal) = gate::check(rig, &positions, &velocities, &self.sent, dt) {
            self.violations += 1;
            // The stream ends here: the words may allocate.
            self.fault.get_or_insert_with(|| refusal.to_string());
            return None;
        }
        if let Some(cell) = cell
            && let Err(clearance) =
                cell.check(self.sent.previous.as_ref().map(|(p, _)| p), &positions)
        {
            self.violations += 1;
            let words = cell.refusal(rig, &clearance, &positions).to_string();
            self.fault.get_or_insert(words);
            return None;
        }
        self.sent.before_previous = self.sent.previous.map(|(p, _)| p);
        self.velocity_before = self.sent.previous.map(|(_, v)| v);
        self.sent.previous = Some((positions, velocities));
        self.held[self.seq as usize % HELD_TARGETS] = (self.seq, positions);
        Some(JointTarget {
            seq: self.seq,
            t: period * self.seq,
            positions,
            velocities,
        })
    }

    /// The target the controller held when it measured `feedback`'s position: the one
    /// [`Cycle::behind`] before the seq it echoes (a CiA 402 drive measures at the SYNC that
    /// hands it the next target), the start before this stream's first target. A feedback
    /// older than the targets kept is judged against the newest sent.
    fn held_when_measured(&self, feedback: &Feedback) -> AxisValues {
        let wanted = feedback.seq.wrapping_sub(self.behind);
        if wanted.wrapping_sub(self.first_seq).wrapping_sub(1) >= 1 << 31 {
            return self.start;
        }
        match self.held[wanted as usize % HELD_TARGETS] {
            (seq, positions) if seq == wanted => positions,
            _ => self.held[self.seq as usize % HELD_TARGETS].1,
        }
    }

    /// Latency runs from sending the target a feedback echoes to receiving that feedback;
    /// returns it (us) when this cycle measured one. The tracking error is `feedback`
    /// against `reference`, what the following check judges it against.
    fn record_feedback(
        &mut self,
        feedback: Option<&Feedback>,
        reference: &AxisValues,
        now: Duration,
    ) -> Option<f64> {
        let Some(feedback) = feedback else {
            self.timeouts += 1;
            self.silent_cycles += 1;
            return None;
        };
        let mut latency_us = None;
        self.silent_cycles = 0;
        // Only the first echo of a target this stream sent measures its latency; repeats
        // of an older seq (a controller between cycles) would measure nothing real.
        let fresh =
            feedback.seq > self.first_seq && self.last_echo.is_none_or(|last| feedback.seq > last);
        if fresh && self.seq.wrapping_sub(feedback.seq) < SEND_TIMES as u32 {
            let sent = self.sent_at[feedback.seq as usize % SEND_TIMES];
            let micros = now.saturating_sub(sent).as_secs_f64() * 1e6;
            self.latency.record(micros);
            latency_us = Some(micros);
            self.last_echo = Some(feedback.seq);
        }
        for ((commanded, actual), revolute) in reference
            .as_slice()
            .iter()
            .zip(feedback.positions.as_slice())
            .zip(&self.revolute)
        {
            if *revolute {
                self.tracking_max = self
                    .tracking_max
                    .max((commanded - actual).abs().to_degrees());
            }
        }
        latency_us
    }

    fn report_empty(
        outcome: Outcome,
        fault: String,
        link: String,
        counters: LinkCounters,
    ) -> StreamReport {
        StreamReport {
            outcome,
            fault: Some(fault),
            cycles: 0,
            missed_cycles: 0,
            limit_violations: 0,
            feedback_timeouts: 0,
            jitter_p50_us: 0.0,
            jitter_p99_us: 0.0,
            jitter_max_us: 0.0,
            latency_p50_us: 0.0,
            latency_p99_us: 0.0,
            tracking_error_max_deg: 0.0,
            overruns: 0,
            duration_s: 0.0,
            samples_done: 0,
            last_seq: 0,
            link,
            stopped_in: None,
            interruptions: Vec::new(),
            counters,
            wakes: None,
            stall_late_us: None,
        }
    }

    fn report(
        self,
        outcome: Outcome,
        period: Duration,
        counters: LinkCounters,
        link: String,
    ) -> StreamReport {
        // A stream being brought to rest because the link stopped trusting what it hears
        // (LinkEvent::Untrusted) ends faulted even when the link then falls silent or the
        // cycle stalls: a resume would plan from that feedback.
        let outcome = match (self.aborting, outcome) {
            (Some(Outcome::Faulted), Outcome::LinkLost | Outcome::Stalled) => Outcome::Faulted,
            _ => outcome,
        };
        let jitter = Jitter::of(&self.jitter);
        StreamReport {
            outcome,
            fault: self.fault,
            cycles: u64::from(self.seq - self.first_seq),
            missed_cycles: self.missed,
            limit_violations: self.violations,
            feedback_timeouts: self.timeouts,
            jitter_p50_us: jitter.p50_us,
            jitter_p99_us: jitter.p99_us,
            jitter_max_us: jitter.max_us,
            latency_p50_us: self.latency.percentile(0.5),
            latency_p99_us: self.latency.percentile(0.99),
            tracking_error_max_deg: self.tracking_max,
            overruns: self.overruns,
            duration_s: f64::from(self.seq - self.first_seq) * period.as_secs_f64(),
            samples_done: self.path.floor() as usize,
            last_seq: self.seq,
            link,
            stopped_in: None,
            interruptions: Vec::new(),
            counters,
            wakes: Some(self.jitter),
            stall_late_us: self.stall_late_us,
        }
    }
}

/// A controller's fault in words: its code, and its own text when it gave one.
pub fn fault_text(fault: &Fault, text: &str) -> String {
    if text.is_empty() {
        format!("controller fault: {fault}")
    } else {
        format!("controller fault: {fault}: {text}")
    }
}
