//! The bridge from the streaming cycle to the recorder: each cycle's command and the
//! controller's measured state, as log records; and [`BothSinks`], so the recorder and the
//! live view see the same cycles. Allocation-free, like the cycle itself. Also
//! [`ActionLog`], through which an operator's actions (pause, stop, ...) reach the log of
//! the job they act on from another thread.

use crate::log::{EventSender, LogRecord, Recorder};
use crate::protocol::AxisValues;
use crate::stream::{CycleRecord, CycleSink};
use std::sync::{Mutex, PoisonError};
use std::time::Duration;

pub struct RecorderSink<'a> {
    recorder: &'a Recorder,
    period: Duration,
    previous_actual: Option<AxisValues>,
}

impl<'a> RecorderSink<'a> {
    pub fn new(recorder: &'a Recorder, period: Duration) -> Self {
        Self {
            recorder,
            period,
            previous_actual: None,
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
        let target = &cycle.target;
        self.recorder.record(LogRecord::Command {
            seq: target.seq,
            t: target.t,
            positions: target.positions,
            velocities: target.velocities,
        });
        if let Some(feedback) = &cycle.feedback {
            let velocities = self.estimated_velocity(&feedback.positions);
            self.recorder.record(LogRecord::State {
                seq: target.seq,
                t: target.t,
                positions: feedback.positions,
                velocities,
                late_us: cycle.late_us,
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
}

impl ActionLog {
    fn slot(&self) -> std::sync::MutexGuard<'_, Option<EventSender>> {
        self.sender.lock().unwrap_or_else(PoisonError::into_inner)
    }

    pub(super) fn open(&self, recorder: &Recorder) {
        *self.slot() = recorder.event_sender();
    }

    pub(super) fn close(&self) {
        *self.slot() = None;
    }

    /// Logs `kind` at job time `t` (s); `false` when the job has no log open (not started
    /// streaming yet, or ended).
    pub fn record(&self, t: f64, kind: &str, detail: serde_json::Value) -> bool {
        self.slot()
            .as_ref()
            .is_some_and(|sender| sender.event(t, kind, detail))
    }
}
