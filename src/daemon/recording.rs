//! The bridge from the streaming cycle to the recorder: each cycle's command and the
//! controller's measured state, as log records; and [`BothSinks`], so the recorder and the
//! live view see the same cycles. Allocation-free, like the cycle itself. With `[log]
//! on_error = "stop"`, the sink is also where a failed log stops the job: it looks at the
//! log's health every cycle (one atomic load) and asks the stream to stop along its path
//! the first cycle after a write failed. Also [`ActionLog`], through which an operator's
//! actions (pause, stop, ...) reach the log of the job they act on from another thread, and
//! through which the control API learns that the job's log failed.

use crate::log::{EventSender, LogFailure, LogHealth, LogRecord, Recorder};
use crate::protocol::AxisValues;
use crate::stream::{CycleRecord, CycleSink, StreamControl};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;

pub struct RecorderSink<'a> {
    recorder: &'a Recorder,
    period: Duration,
    previous_actual: Option<AxisValues>,
    /// The job's controls, when a failed log must stop it (`on_error = "stop"`).
    stop_on_failure: Option<&'a StreamControl>,
    /// The failure was seen (and acted on): the sink looks no more.
    failure_seen: bool,
    /// The failure is what stopped the job (it was neither stopping nor e-stopped then).
    stopped_job: bool,
}

impl<'a> RecorderSink<'a> {
    pub fn new(recorder: &'a Recorder, period: Duration) -> Self {
        Self {
            recorder,
            period,
            previous_actual: None,
            stop_on_failure: None,
            failure_seen: false,
            stopped_job: false,
        }
    }

    /// Stops the job through `control` (along its path) once a log write fails.
    pub fn stopping_on_failure(mut self, control: &'a StreamControl) -> Self {
        self.stop_on_failure = Some(control);
        self
    }

    /// Whether the log's failure brought the job to rest.
    pub fn stopped_job(&self) -> bool {
        self.stopped_job
    }

    /// The first cycle after a write failed: asks the stream to stop, unless it is already
    /// stopping or e-stopped (an operator's stop stays the operator's).
    fn check_log(&mut self) {
        if self.failure_seen || !self.recorder.failed() {
            return;
        }
        self.failure_seen = true;
        if let Some(control) = self.stop_on_failure
            && !control.is_stopping()
            && !control.is_estopped()
        {
            control.stop();
            self.stopped_job = true;
        }
    }

    /// Controllers report positions only: velocity is the difference over one cycle.
    fn estimated_velocity(&self, actual: &AxisValues) -> AxisValues {
        let mut velocity = AxisValues::zeros(actual.len());
        if let Some(previous) = &self.previous_actual {
            let dt = self.period.as_secs_f64();
            for ((v, now), before) in velocity
                .as_mut_slice()
                .iter_mut()
                .zip(actual.as_slice())
                .zip(previous.as_slice())
            {
                *v = (now - before) / dt;
            }
        }
        velocity
    }
}

impl CycleSink for RecorderSink<'_> {
    fn record(&mut self, cycle: &CycleRecord) {
        self.check_log();
        let target = &cycle.target;
        self.recorder.record(LogRecord::Command {
            seq: target.seq,
            t: target.t.as_secs_f64(),
            positions: target.positions,
            velocities: target.velocities,
            late_us: cycle.late_us,
        });
        if let Some(feedback) = &cycle.feedback {
            let velocities = self.estimated_velocity(&feedback.positions);
            self.recorder.record(LogRecord::State {
                seq: target.seq,
                t: target.t.as_secs_f64(),
                positions: feedback.positions,
                velocities,
            });
            self.previous_actual = Some(feedback.positions);
        }
    }
}

/// Hands every cycle to two sinks, in order.
pub struct BothSinks<'a>(
    pub &'a mut (dyn CycleSink + Send),
    pub &'a mut (dyn CycleSink + Send),
);

impl CycleSink for BothSinks<'_> {
    fn record(&mut self, cycle: &CycleRecord) {
        self.0.record(cycle);
        self.1.record(cycle);
    }
}

/// Where actions taken from outside the job (the control API's pause, resume, stop,
/// e-stop) reach the job's log: the job's thread opens it once its recorder exists and
/// closes it before the log's last event, `job_ended`; any thread may write in between.
#[derive(Default)]
pub struct ActionLog {
    sender: Mutex<Option<EventSender>>,
    /// The job's log's health, kept after `close`: whether it failed stays known.
    health: Mutex<Option<Arc<LogHealth>>>,
}

impl ActionLog {
    fn slot(&self) -> std::sync::MutexGuard<'_, Option<EventSender>> {
        self.sender.lock().unwrap_or_else(PoisonError::into_inner)
    }

    pub(super) fn open(&self, recorder: &Recorder) {
        *self.slot() = recorder.event_sender();
        *self.health.lock().unwrap_or_else(PoisonError::into_inner) = Some(recorder.health());
    }

    /// The first write the job's log failed, as soon as the writer met it; `None` while
    /// the log is sound (or not opened yet).
    pub fn log_failure(&self) -> Option<LogFailure> {
        self.health
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .as_ref()
            .and_then(|health| health.failure())
    }

    pub(super) fn close(&self) {
        *self.slot() = None;
    }

    /// Logs `kind` at job time `t` (s); `false` when the job has no log open (not started
    /// streaming yet, or ended).
    pub fn record(&self, t: f64, kind: &str, detail: serde_json::Value) -> bool {
        self.hold_open().record(t, kind, detail)
    }

    /// Keeps the log as it is (open or not) until the guard is dropped: an action applied
    /// while it is held is recorded before the job can close its log (an e-stop ends a job
    /// within a cycle, faster than the control API writes its event).
    pub fn hold_open(&self) -> HeldActions<'_> {
        HeldActions(self.slot())
    }
}

/// The job's action log held open, from [`ActionLog::hold_open`].
pub struct HeldActions<'a>(std::sync::MutexGuard<'a, Option<EventSender>>);

impl HeldActions<'_> {
    /// As [`ActionLog::record`].
    pub fn record(&self, t: f64, kind: &str, detail: serde_json::Value) -> bool {
        self.0
            .as_ref()
            .is_some_and(|sender| sender.event(t, kind, detail))
    }
}
