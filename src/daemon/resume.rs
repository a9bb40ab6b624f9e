//! Starting and resuming from where the arm holds (`docs/protocol.md` 6.8): before a job
//! and after a link loss, a stall or a controller restart, the bridge sends nothing it
//! planned before. It waits for a session, asks the controller to hold, waits until the
//! arm is at rest, reads that position, plans a move from it to where the job was
//! interrupted and streams the rest from standstill. Stop and e-stop are honoured at every
//! point of the wait. Owns this choreography only: the cycle is `stream`'s, the plan
//! `trajectory`'s.

use super::config::RunSettings;
use super::{DaemonError, plan_settings, stream_settings};
use crate::clock::Clock;
use crate::link::{Link, LinkEvent};
use crate::log::Recorder;
use crate::protocol::{Command, ControllerStatus, Feedback};
use crate::stream::{
    AfterInterruption, CycleSink, Executor, Interruption, JobOffset, OnlineCommand, Outcome, Phase,
    StreamControl, StreamError, StreamReport, StreamSettings, check_controller, fault_text, stream,
    stream_shared,
};
use crate::trajectory::Trajectory;
use std::time::Duration;

/// How long a job waits at its start for the controller to hold at rest.
pub const START_HOLD_TIMEOUT: Duration = Duration::from_secs(2);
/// The arm counts as at rest when two feedbacks in a row differ by at most this share of
/// `a_max T^2` on every axis: the first target after a hold must lie within `a_max T^2`
/// of the held position (docs/protocol.md 6.6), and a settling servo is that close then.
const AT_REST_SHARE: f64 = 0.01;
/// Positions travel as integers of 1e-6 rad (or m) (docs/protocol.md 1): an axis held on
/// its limit is reported as the integer nearest it, up to half of this beyond.
const WIRE_QUANTUM: f64 = 1e-6;

/// How the wait for a hold ended.
#[derive(Debug, Clone, PartialEq)]
pub enum Hold {
    /// The controller holds at rest here.
    At(Vec<f64>),
    Stopped,
    EStopped,
    Faulted(String),
    TimedOut(String),
}

/// Waits up to `timeout` for a session and a controller that holds at rest, sending Stop
/// once per session and Heartbeats otherwise (one a cycle).
pub fn wait_for_hold(
    settings: &RunSettings,
    link: &mut dyn Link,
    clock: &dyn Clock,
    control: &StreamControl,
    timeout: Duration,
) -> Result<Hold, DaemonError> {
    let period = settings.period();
    let deadline = clock.now() + timeout;
    let mut stopped_session = None;
    let mut previous: Option<Feedback> = None;
    let mut was_up = false;
    loop {
        control.enter(if link.is_up() {
            Phase::WaitingForHold
        } else {
            Phase::WaitingForController
        });
        if let Some(end) = requested_end(link, control)? {
            return Ok(end);
        }
        if clock.now() >= deadline {
            return Ok(Hold::TimedOut(timed_out(link, was_up, timeout)));
        }
        let next = clock.now() + period;
        was_up |= link.is_up();
        if !link.is_up() {
            previous = None;
            clock.sleep_until(next);
            continue;
        }
        while let Some(event) = link.next_event() {
            match event {
                LinkEvent::Fault(report) => {
                    return Ok(Hold::Faulted(fault_text(&report.fault, &report.text)));
                }
                // Never a hold from a link that stopped trusting what it hears.
                LinkEvent::Untrusted(words) => return Ok(Hold::Faulted(words)),
                _ => previous = None,
            }
        }
        let command = if stopped_session == Some(link.sessions()) {
            Command::Heartbeat
        } else {
            stopped_session = Some(link.sessions());
            Command::Stop
        };
        link.send(&command)?;
        if let Some(feedback) = link.receive(period)? {
            if let ControllerStatus::Fault(fault) = feedback.status {
                return Ok(Hold::Faulted(format!("controller fault: {fault}")));
            }
            if previous.is_some_and(|p| at_rest(settings, &p, &feedback)) {
                return Ok(Hold::At(held_on_the_wire(
                    settings,
                    feedback.positions.as_slice(),
                )));
            }
            previous = Some(feedback);
        }
        clock.sleep_until(next);
    }
}

/// Why the wait for a hold at rest ended: the link's own reason when it never came up
/// (connection refused, no such device, a node that did not answer), a silent controller
/// only when the transport opened and nothing answered the Hello.
fn timed_out(link: &dyn Link, was_up: bool, timeout: Duration) -> String {
    if let Some(reason) = link.down_reason().filter(|_| !link.is_up()) {
        format!(
            "no session with {} for {:.1} s: {reason}",
            link.describe(),
            timeout.as_secs_f64()
        )
    } else if was_up {
        format!(
            "{} did not hold at rest within {:.1} s",
            link.describe(),
            timeout.as_secs_f64()
        )
    } else {
        format!(
            "no session with {} for {:.1} s: the controller did not answer the bridge's Hello",
            link.describe(),
            timeout.as_secs_f64()
        )
    }
}

/// A stop or e-stop asked for while waiting. An e-stop goes out as soon as the link is up.
fn requested_end(
    link: &mut dyn Link,
    control: &StreamControl,
) -> Result<Option<Hold>, DaemonError> {
    if control.is_estopped() {
        if link.is_up() {
            link.send(&Command::EStop)?;
            return Ok(Some(Hold::EStopped));
        }
        return Ok(None);
    }
    if control.is_stopping() {
        if link.is_up() {
            link.send(&Command::Stop)?;
        }
        return Ok(Some(Hold::Stopped));
    }
    Ok(None)
}

/// The held position, read as the controller compares it (docs/protocol.md 6.6: on the
/// wire integers): an axis reported within half a wire quantum beyond a limit is on that
/// limit, which the wire cannot tell apart from it (a rig whose first pose sits on a limit,
/// like the sloth's pelvis at 4.2 deg, is read back 0.2 urad outside it). Anything farther
/// out is kept as it is, for the planner to refuse.
fn held_on_the_wire(settings: &RunSettings, positions: &[f64]) -> Vec<f64> {
    settings
        .rig
        .joints
        .iter()
        .zip(positions)
        .map(|(joint, &p)| {
            let limits = joint.limits;
            if p > limits.upper && p - limits.upper <= WIRE_QUANTUM / 2.0 {
                limits.upper
            } else if p < limits.lower && limits.lower - p <= WIRE_QUANTUM / 2.0 {
                limits.lower
            } else {
                p
            }
        })
        .collect()
}

fn at_rest(settings: &RunSettings, before: &Feedback, now: &Feedback) -> bool {
    now.status == ControllerStatus::Holding
        && before.status == ControllerStatus::Holding
        && settings
            .rig
            .joints
            .iter()
            .zip(before.positions.as_slice())
            .zip(now.positions.as_slice())
            .all(|((joint, a), b)| {
                let dt = settings.period().as_secs_f64();
                (a - b).abs() <= AT_REST_SHARE * joint.limits.max_acceleration * dt * dt
            })
}

/// The report of a stream that ended while waiting for a hold.
fn ended_waiting(mut report: StreamReport, hold: Hold) -> StreamReport {
    let (outcome, fault) = match hold {
        Hold::At(_) => return report,
        Hold::Stopped => (Outcome::Stopped, None),
        Hold::EStopped => (Outcome::EStopped, None),
        Hold::Faulted(text) => (Outcome::Faulted, Some(text)),
        Hold::TimedOut(text) => (report.outcome, Some(text)),
    };
    report.outcome = outcome;
    if fault.is_some() {
        report.fault = fault;
    }
    report
}

/// Everything a stream needs besides its trajectory and settings.
pub struct Streaming<'a> {
    pub settings: &'a RunSettings,
    pub link: &'a mut dyn Link,
    pub clock: &'a dyn Clock,
    pub sink: &'a mut (dyn CycleSink + Send),
    pub control: &'a StreamControl,
    pub events: Option<&'a Recorder>,
    /// Runs the cycles beside other streams' when given; otherwise this thread does.
    pub executor: Option<&'a Executor>,
}

impl Streaming<'_> {
    /// Streams one part; the next part's sequence numbers follow this one's.
    fn run(&mut self, trajectory: &Trajectory, settings: &mut StreamSettings) -> StreamReport {
        let report = self.run_part(trajectory, settings);
        settings.first_seq = report.last_seq;
        report
    }

    fn run_part(&mut self, trajectory: &Trajectory, settings: &StreamSettings) -> StreamReport {
        let rig = &self.settings.rig;
        let result = match self.executor {
            Some(executor) => stream_shared(
                executor,
                trajectory,
                rig,
                self.link,
                self.clock,
                self.sink,
                self.control,
                settings,
            ),
            None => stream(
                trajectory,
                rig,
                self.link,
                self.clock,
                self.sink,
                self.control,
                settings,
            ),
        };
        result.unwrap_or_else(|error| {
            // A link that fails before the first target (no session, no feedback) is lost,
            // and resumed like any loss; a trajectory or controller refused is final.
            let outcome = match error {
                StreamError::NoFeedback { .. }
                | StreamError::NoSession { .. }
                | StreamError::Link(_) => Outcome::LinkLost,
                _ => Outcome::Refused,
            };
            StreamReport {
                // Nothing was sent: the numbering goes on from where it was.
                last_seq: settings.first_seq,
                ..StreamReport::without_motion(
                    outcome,
                    super::error_chain(&error),
                    self.link.describe(),
                    self.link.counters(),
                )
            }
        })
    }

    fn event(&self, t: f64, name: &str, detail: serde_json::Value) {
        if let Some(recorder) = self.events {
            recorder.event(t, name, detail);
        }
    }

    /// The log's record of `report`'s last interruption (`stalled` or `link_lost`,
    /// `docs/logs.md` "Stalls"), written as it happens; what the bridge did then is the
    /// `resumed` event that follows it, or the job's end.
    fn interrupted(&self, report: &StreamReport) {
        let Some(last) = report.interruptions.last() else {
            return;
        };
        self.event(
            last.at_s,
            &last.outcome.to_string(),
            serde_json::json!({
                "at_sample": report.samples_done,
                "seq": report.last_seq,
                "why": last.why,
                "late_us": last.late_us,
            }),
        );
    }
}

/// Streams `trajectory`; after a link loss or a stall, waits (up to the configured
/// reconnect timeout) for the controller to hold at rest, moves the arm from there to
/// where the job was interrupted and resumes from standstill: never a jump to a stale
/// target. Always returns a report.
pub fn stream_resuming(mut io: Streaming<'_>, trajectory: &Trajectory) -> StreamReport {
    let mut streaming = stream_settings(io.settings);
    // A stop asked for already is the stream's to honour: it sends no target.
    io.control.enter(Phase::Streaming);
    let mut report = io.run(trajectory, &mut streaming);
    // Where `remaining` begins on the job's trajectory (a program's steps are found by it).
    let mut base = report.samples_done.min(trajectory.len().saturating_sub(1));
    let mut remaining = trajectory.tail(report.samples_done);
    while matches!(report.outcome, Outcome::LinkLost | Outcome::Stalled) {
        report.interruptions.push(Interruption {
            at_s: report.duration_s,
            outcome: report.outcome,
            why: report.fault.clone().unwrap_or_default(),
            late_us: report
                .stall_late_us
                .filter(|_| report.outcome == Outcome::Stalled),
            then: AfterInterruption::Resumed,
        });
        // Logged at once, as it happens: a log read live (the page, Foxglove, an operator
        // waiting to restart a controller) sees the link go before the bridge waits on it.
        io.interrupted(&report);
        // What streams from here until the rest of the path is not the job's path.
        streaming.job_offset = None;
        if io.control.online().given() {
            // Online motion has no path to return to: from where the arm holds, the goal
            // it was moving to is given again (a jog waits for its next command).
            match resume_online(&mut io, &mut streaming, &report) {
                Resumed::Ended(report) => return ended_after_interruption(report),
                Resumed::Approach(part, _) => report = part,
            }
            continue;
        }
        let (part, approached) =
            match resume_once(&mut io, &remaining, &mut streaming, trajectory, &report) {
                Resumed::Ended(report) => return ended_after_interruption(report),
                Resumed::Approach(part, approached) => (part, approached),
            };
        report = part;
        if !approached {
            continue;
        }
        io.control.enter(Phase::Streaming);
        let mut rest = StreamSettings {
            start_scale: 0.0,
            job_offset: Some(job_offset(trajectory, base)),
            ..streaming
        };
        let part = io.run(&remaining, &mut rest);
        streaming.first_seq = rest.first_seq;
        base += part.samples_done.min(remaining.len().saturating_sub(1));
        remaining = remaining.tail(part.samples_done);
        report = report.merge(part);
    }
    report
}

/// Where a tail of `whole` from sample `from` begins on it: the sample, and the I/O points
/// before it (a point at `from` itself runs again, as [`Trajectory::tail`] keeps it).
fn job_offset(whole: &Trajectory, from: usize) -> JobOffset {
    JobOffset {
        sample: from,
        io_done: whole.io_points().iter().filter(|p| p.sample < from).count(),
    }
}

/// `report`, ended while resuming from its last interruption: that one says so.
fn ended_after_interruption(mut report: StreamReport) -> StreamReport {
    if let Some(last) = report.interruptions.last_mut() {
        last.then = AfterInterruption::Ended;
    }
    report
}

/// How one resumption went.
enum Resumed {
    /// The job ends here, with this report.
    Ended(StreamReport),
    /// The approach to the path was streamed (merged report; whether it completed).
    Approach(StreamReport, bool),
}

/// One resumption of an online session: the wait for a hold, then a session from there
/// with the goal it had (merged report).
fn resume_online(
    io: &mut Streaming<'_>,
    streaming: &mut StreamSettings,
    report: &StreamReport,
) -> Resumed {
    let timeout = io.settings.reconnect_timeout();
    let hold = match wait_for_hold(io.settings, io.link, io.clock, io.control, timeout) {
        Ok(hold) => hold,
        Err(error) => Hold::TimedOut(super::error_chain(&error)),
    };
    let Hold::At(actual) = hold else {
        return Resumed::Ended(ended_waiting(report.clone(), hold));
    };
    let hold = match super::hold_at(io.settings, &actual) {
        Ok(hold) => hold,
        Err(error) => {
            let mut ended = report.clone();
            ended.outcome = Outcome::Refused;
            ended.fault = Some(super::error_chain(&error));
            return Resumed::Ended(ended);
        }
    };
    io.control.enter(Phase::Resuming);
    if let Some(goal) = io.control.online().goal() {
        io.control.online().give(OnlineCommand::Goal(goal));
    }
    io.event(
        report.duration_s,
        "resumed",
        serde_json::json!({ "actual": actual, "online": true }),
    );
    let part = io.run(&hold, streaming);
    Resumed::Approach(report.clone().merge(part), true)
}

/// One resumption: the wait for a hold, then the approach to where the job stopped.
fn resume_once(
    io: &mut Streaming<'_>,
    remaining: &Trajectory,
    streaming: &mut StreamSettings,
    whole: &Trajectory,
    report: &StreamReport,
) -> Resumed {
    let timeout = io.settings.reconnect_timeout();
    let hold = match wait_for_hold(io.settings, io.link, io.clock, io.control, timeout) {
        Ok(hold) => hold,
        Err(error) => Hold::TimedOut(super::error_chain(&error)),
    };
    let Hold::At(actual) = hold else {
        let mut ended = ended_waiting(report.clone(), hold);
        if ended.outcome == report.outcome {
            ended.fault = Some(format!(
                "{}: job aborted {:.0} % of the way",
                ended.fault.unwrap_or_default(),
                100.0 * report.samples_done as f64 / whole.len().max(1) as f64
            ));
        }
        return Resumed::Ended(ended);
    };
    if let Some(hello) = io.link.controller_hello()
        && let Err(error) = check_controller(&hello, &io.settings.rig, io.settings.period())
    {
        let mut ended = report.clone();
        ended.outcome = Outcome::Refused;
        ended.fault = Some(format!("the controller no longer admits this job: {error}"));
        return Resumed::Ended(ended);
    }
    // A stop asked for already is the approach stream's to honour: it sends no target.
    io.control.enter(Phase::Resuming);
    let resume_at = remaining.position(0).to_vec();
    io.event(
        report.duration_s,
        "resumed",
        serde_json::json!({ "actual": actual, "resume_at": resume_at }),
    );
    let approach = match crate::trajectory::plan_joint_moves(
        &io.settings.rig,
        &actual,
        &[resume_at],
        &plan_settings(io.settings),
    ) {
        Ok(approach) => approach,
        Err(error) => {
            let mut ended = report.clone();
            ended.outcome = Outcome::Refused;
            ended.fault = Some(format!("cannot plan the way back to the path: {error}"));
            return Resumed::Ended(ended);
        }
    };
    let back = crate::trajectory::Origins::whole("the way back to the path after the interruption");
    if let Err(error) = super::clear(io.settings, &approach, &back) {
        let mut ended = report.clone();
        ended.outcome = Outcome::Refused;
        ended.fault = Some(super::error_chain(&error));
        return Resumed::Ended(ended);
    }
    let part = io.run(&approach, streaming);
    let approached = part.outcome == Outcome::Completed;
    Resumed::Approach(report.clone().merge(part), approached)
}
