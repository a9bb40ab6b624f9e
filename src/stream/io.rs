//! A trajectory's I/O points as the stream meets them (a program's grip, release,
//! set_output and wait_input; protocol v3, docs/protocol.md 6.10). At a point the arm is at
//! rest: the stream holds it there, sending the same target every cycle, asks the link
//! (one request at a time), and goes on once the controller's answer says it is done. A
//! refusal, a missing output or input, or no answer in time ends the job faulted.
//!
//! Owns the requests and the waiting; it must not move the arm (the cycle holds the path
//! at the point) or know what an output drives. Time is counted in stream cycles.

use crate::link::Link;
use crate::motion::{IoAction, IoPoint, Trajectory};
use crate::protocol::{IoKind, IoMessage, IoResult};
use std::time::Duration;

/// Why an I/O step ended the job, naming the step as written.
#[derive(Debug, thiserror::Error)]
pub enum IoStepFailed {
    /// No answer, or the input never had the value, in time.
    #[error("{step}: {why}within {limit_s:.3} s")]
    TimedOut {
        step: String,
        why: String,
        limit_s: f64,
    },
    #[error("{step}: {error}")]
    NotSent {
        step: String,
        error: crate::link::LinkError,
    },
    #[error("{step}: the controller set output `{name}` to {}, not {}", u8::from(*got), u8::from(*wanted))]
    OtherValue {
        step: String,
        name: String,
        got: bool,
        wanted: bool,
    },
    #[error("{step}: {kind} `{name}` (request {request}): {result}")]
    Refused {
        step: String,
        kind: &'static str,
        name: String,
        request: u32,
        result: &'static str,
    },
}

/// How long the controller may take to answer a SetOutput: longer than any gripper's travel
/// (the twin's closes in 0.2 s), short enough that a controller that lost the request is
/// noticed while someone still watches.
pub const SET_OUTPUT_TIMEOUT: Duration = Duration::from_secs(5);

pub(super) struct IoRun {
    points: Vec<IoPoint>,
    next: usize,
    /// The last request number used (docs/protocol.md 6.10: from 1, +1 per request).
    request: u32,
    /// The request outstanding, if one is.
    asked: Option<u32>,
    /// Cycles spent at the current point.
    waited: u64,
    period: Duration,
}

impl IoRun {
    pub(super) fn new(trajectory: &Trajectory) -> Self {
        IoRun {
            points: trajectory.io_points().to_vec(),
            next: 0,
            request: 0,
            asked: None,
            waited: 0,
            period: trajectory.period,
        }
    }

    /// The points done so far.
    pub(super) fn done(&self) -> usize {
        self.next
    }

    /// The sample the path must not pass yet: the next point not done.
    pub(super) fn hold_at(&self) -> Option<usize> {
        self.points.get(self.next).map(|point| point.sample)
    }

    /// One cycle with the path at `path` (in samples): at a point, take the controller's
    /// answer or ask again. `Err` names the step and what went wrong.
    pub(super) fn step(
        &mut self,
        path: f64,
        link: &mut dyn Link,
        stopping: bool,
    ) -> Result<(), IoStepFailed> {
        let Some(point) = self.points.get(self.next) else {
            return Ok(());
        };
        if path < point.sample as f64 {
            return Ok(());
        }
        // Cloned only while at a point, where the arm rests and cycles have time.
        let point = point.clone();
        self.waited += 1;
        if self.answered(&point, link)? {
            self.next += 1;
            self.waited = 0;
            return Ok(());
        }
        let (limit, why) = match &point.action {
            IoAction::SetOutput { name, .. } => (
                SET_OUTPUT_TIMEOUT,
                format!("the controller did not say output `{name}` was set"),
            ),
            IoAction::WaitInput {
                name,
                value,
                timeout,
            } => (
                *timeout,
                format!("input `{name}` was not {} ", u8::from(*value)),
            ),
        };
        if self.waited as f64 * self.period.as_secs_f64() > limit.as_secs_f64() {
            return Err(IoStepFailed::TimedOut {
                step: point.step,
                why,
                limit_s: limit.as_secs_f64(),
            });
        }
        if self.asked.is_none() && !stopping {
            self.request = self.request.wrapping_add(1).max(1);
            let message = match &point.action {
                IoAction::SetOutput { name, value } => IoMessage::SetOutput {
                    request: self.request,
                    name: name.clone(),
                    value: *value,
                },
                IoAction::WaitInput { name, .. } => IoMessage::ReadInput {
                    request: self.request,
                    name: name.clone(),
                },
            };
            link.send_io(&message)
                .map_err(|error| IoStepFailed::NotSent {
                    step: point.step.clone(),
                    error,
                })?;
            self.asked = Some(self.request);
        }
        Ok(())
    }

    /// Whether the controller's answers so far finish `point`. Answers to anything but the
    /// request outstanding are late ones (before a reconnect): ignored.
    fn answered(&mut self, point: &IoPoint, link: &mut dyn Link) -> Result<bool, IoStepFailed> {
        let (name, kind, wanted) = match &point.action {
            IoAction::SetOutput { name, value } => (name, IoKind::Output, *value),
            IoAction::WaitInput { name, value, .. } => (name, IoKind::Input, *value),
        };
        while let Some(state) = link.take_io() {
            if Some(state.request) != self.asked || state.kind != kind || state.name != *name {
                continue;
            }
            self.asked = None;
            match state.result {
                IoResult::Done if state.value == wanted => return Ok(true),
                // An input not yet as wanted is read again next cycle.
                IoResult::Done if kind == IoKind::Input => {}
                IoResult::Done => {
                    return Err(IoStepFailed::OtherValue {
                        step: point.step.clone(),
                        name: name.clone(),
                        got: state.value,
                        wanted,
                    });
                }
                refused => {
                    return Err(IoStepFailed::Refused {
                        step: point.step.clone(),
                        kind: kind.word(),
                        name: name.clone(),
                        request: state.request,
                        result: refused.words(),
                    });
                }
            }
        }
        Ok(false)
    }
}
