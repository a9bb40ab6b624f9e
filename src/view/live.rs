//! The latest-value slot between the streaming cycle and the view: the cycle's sink writes
//! each cycle's state into a fixed-size sample and publishes it with a `try_lock` (never
//! waiting: a cycle that finds the view reading skips one publish, the next cycle's sample
//! replaces it anyway); the view copies the latest sample out about 50 times a second.
//! Nothing here allocates after construction. It must not block the cycle or keep history.

use crate::link::LinkCounters;
use crate::protocol::{AxisValues, ControllerStatus};
use crate::stream::{CycleRecord, CycleSink};
use std::sync::{Mutex, PoisonError};

/// The streamer's state as of one cycle, with timing figures over the last second.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LiveSample {
    /// Cycles streamed since the slot was made (every job, resumed parts included).
    pub cycles: u64,
    /// The cycle's sequence number and time in its job (s).
    pub seq: u32,
    pub t: f64,
    /// rad or m, in the rig's joint order.
    pub commanded: AxisValues,
    pub actual: AxisValues,
    /// The controller's status, once it has answered.
    pub status: Option<ControllerStatus>,
    /// How late this cycle woke (us), and the worst over about the last second.
    pub late_us: f32,
    pub late_max_us: f32,
    /// The last command-to-feedback latency measured (us), and the worst over about the
    /// last second.
    pub latency_us: f32,
    pub latency_max_us: f32,
    pub counters: LinkCounters,
    /// Cycles without feedback since the slot was made.
    pub feedback_timeouts: u64,
    /// The cycle's place on its job's trajectory (a program's step is found by it).
    pub on_job: Option<crate::stream::JobPosition>,
}

impl LiveSample {
    /// At rest at `actual`, before any cycle.
    pub fn at_rest(actual: &[f64]) -> Self {
        // A rig has at most MAX_AXES axes (the twin refuses more): nothing to show otherwise.
        let actual = AxisValues::from_slice(actual).unwrap_or(AxisValues::zeros(0));
        LiveSample {
            cycles: 0,
            seq: 0,
            t: 0.0,
            commanded: actual,
            actual,
            status: None,
            late_us: 0.0,
            late_max_us: 0.0,
            latency_us: 0.0,
            latency_max_us: 0.0,
            counters: LinkCounters::default(),
            feedback_timeouts: 0,
            on_job: None,
        }
    }
}

/// The latest [`LiveSample`], shared by the streaming thread and the view.
pub struct LiveSlot {
    latest: Mutex<LiveSample>,
}

impl LiveSlot {
    pub fn new(at_rest: LiveSample) -> Self {
        LiveSlot {
            latest: Mutex::new(at_rest),
        }
    }

    /// Replaces the latest sample unless the view is reading it right now.
    fn offer(&self, sample: &LiveSample) {
        if let Ok(mut latest) = self.latest.try_lock() {
            *latest = *sample;
        }
    }

    /// Replaces the latest sample, waiting for the view if it is reading (not for the cycle).
    fn publish(&self, sample: &LiveSample) {
        *self.latest.lock().unwrap_or_else(PoisonError::into_inner) = *sample;
    }

    pub fn latest(&self) -> LiveSample {
        *self.latest.lock().unwrap_or_else(PoisonError::into_inner)
    }
}

/// A running maximum over blocks of `window` values: the worst of the current block and
/// the previous one, so it covers between one and two windows.
#[derive(Debug, Clone, Copy)]
struct WindowMax {
    window: u64,
    count: u64,
    current: f32,
    previous: f32,
}

impl WindowMax {
    fn new(window: u64) -> Self {
        WindowMax {
            window: window.max(1),
            count: 0,
            current: 0.0,
            previous: 0.0,
        }
    }

    fn record(&mut self, value: f32) -> f32 {
        if self.count == self.window {
            self.previous = self.current;
            self.current = 0.0;
            self.count = 0;
        }
        self.count += 1;
        self.current = self.current.max(value);
        self.current.max(self.previous)
    }
}

/// The streaming cycle's side of the slot: a [`CycleSink`] that keeps the running figures
/// and offers every cycle's sample. Publishes its last sample (waiting if need be) when
/// dropped, after the stream, so the view always ends on the final position.
pub struct LiveSink<'a> {
    slot: &'a LiveSlot,
    sample: LiveSample,
    late: WindowMax,
    latency: WindowMax,
}

impl<'a> LiveSink<'a> {
    /// `cycles_per_window`: how many cycles the "last second" figures cover (the rate).
    pub fn new(slot: &'a LiveSlot, cycles_per_window: u64) -> Self {
        LiveSink {
            // A new stream: the last one's place on its job means nothing for this one.
            sample: LiveSample {
                on_job: None,
                ..slot.latest()
            },
            slot,
            late: WindowMax::new(cycles_per_window),
            latency: WindowMax::new(cycles_per_window),
        }
    }
}

impl CycleSink for LiveSink<'_> {
    fn record(&mut self, cycle: &CycleRecord) {
        let sample = &mut self.sample;
        sample.cycles += 1;
        sample.seq = cycle.target.seq;
        sample.t = cycle.target.t.as_secs_f64();
        sample.commanded = cycle.target.positions;
        sample.late_us = cycle.late_us;
        sample.late_max_us = self.late.record(cycle.late_us);
        if let Some(latency) = cycle.latency_us {
            sample.latency_us = latency;
            sample.latency_max_us = self.latency.record(latency);
        }
        sample.counters = cycle.counters;
        sample.on_job = cycle.on_job;
        match &cycle.feedback {
            Some(feedback) => {
                sample.actual = feedback.positions;
                sample.status = Some(feedback.status);
            }
            None => sample.feedback_timeouts += 1,
        }
        self.slot.offer(sample);
    }
}

impl Drop for LiveSink<'_> {
    fn drop(&mut self) {
        self.slot.publish(&self.sample);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::{Feedback, JointTarget};

    fn cycle(seq: u32, position: f64, late_us: f32, latency_us: Option<f32>) -> CycleRecord {
        let positions = AxisValues::from_slice(&[position]).expect("one axis fits");
        CycleRecord {
            target: JointTarget {
                seq,
                t: std::time::Duration::from_millis(4) * seq,
                positions,
                velocities: AxisValues::zeros(1),
            },
            feedback: Some(Feedback {
                seq,
                positions: AxisValues::from_slice(&[position / 2.0]).expect("one axis fits"),
                status: ControllerStatus::Ok,
            }),
            late_us,
            latency_us,
            counters: LinkCounters {
                frames_sent: u64::from(seq),
                ..LinkCounters::default()
            },
            at: std::time::Duration::from_millis(u64::from(seq) * 4),
            on_job: None,
        }
    }

    #[test]
    fn the_view_sees_the_latest_cycle_and_the_worst_of_the_last_window() {
        let slot = LiveSlot::new(LiveSample::at_rest(&[0.1]));
        assert_eq!(slot.latest().actual.as_slice(), &[0.1]);
        {
            let mut sink = LiveSink::new(&slot, 4);
            sink.record(&cycle(1, 0.2, 90.0, Some(300.0)));
            for seq in 2..=6 {
                sink.record(&cycle(seq, 0.2 * f64::from(seq), 5.0, None));
            }
            let latest = slot.latest();
            assert_eq!((latest.cycles, latest.seq), (6, 6));
            assert_eq!(latest.commanded.as_slice(), &[0.2 * 6.0]);
            assert_eq!(latest.actual.as_slice(), &[0.1 * 6.0]);
            assert_eq!(latest.late_us, 5.0);
            assert_eq!(
                latest.late_max_us, 90.0,
                "cycle 1 is in the previous window"
            );
            assert_eq!(latest.latency_us, 300.0, "no newer measurement");
            assert_eq!(latest.counters.frames_sent, 6);
            for seq in 7..=10 {
                sink.record(&cycle(seq, 0.0, 5.0, None));
            }
            assert_eq!(slot.latest().late_max_us, 5.0, "two windows later");
            // The view holds the slot: the cycle skips its publish instead of waiting.
            let reading = slot.latest.lock().expect("the slot lock is not poisoned");
            sink.record(&cycle(11, 1.0, 5.0, None));
            drop(reading);
            assert_eq!(slot.latest().seq, 10);
        }
        assert_eq!(slot.latest().seq, 11, "the last cycle is published on drop");
    }
}
