//! The bridge from the streaming cycle to the recorder: each cycle's command and the
//! controller's measured state, as log records; and [`BothSinks`], so the recorder and the
//! live view see the same cycles. Allocation-free, like the cycle itself.

use crate::log::{LogRecord, Recorder};
use crate::protocol::AxisValues;
use crate::stream::{CycleRecord, CycleSink};

pub struct RecorderSink<'a> {
    recorder: &'a Recorder,
    period_s: f64,
    previous_actual: Option<AxisValues>,
}

impl<'a> RecorderSink<'a> {
    pub fn new(recorder: &'a Recorder, period_s: f64) -> Self {
        Self {
            recorder,
            period_s,
            previous_actual: None,
        }
    }

    /// Controllers report positions only: velocity is the difference over one cycle.
    fn estimated_velocity(&self, actual: &AxisValues) -> AxisValues {
        let mut velocity = AxisValues::zeros(actual.len());
        if let Some(previous) = &self.previous_actual {
            for ((v, now), before) in velocity
                .as_mut_slice()
                .iter_mut()
                .zip(actual.as_slice())
                .zip(previous.as_slice())
            {
                *v = (now - before) / self.period_s;
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
pub struct BothSinks<'a>(pub &'a mut dyn CycleSink, pub &'a mut dyn CycleSink);

impl CycleSink for BothSinks<'_> {
    fn record(&mut self, cycle: &CycleRecord) {
        self.0.record(cycle);
        self.1.record(cycle);
    }
}
