//! Where a streaming program is, and how long its steps took (issue 29): each op's end on
//! the program's trajectory (the last sample of its stretch, or for an I/O step, the
//! trajectory's I/O point it is), the step whose span holds a cycle's place on the
//! trajectory ([`StepSpans::current`]), and the clock times at which the stream passed
//! each op's end ([`StepTimer`]): the measured cycle times, pauses, stalls and I/O waits
//! included, beside the planned ones.
//!
//! Owns the mapping from a cycle's place to a step and the measured times; it must not
//! stream, read a link or guess a place the stream did not report.

use super::steps::{Action, Op};
use super::{CycleTimes, StepTime};
use crate::stream::JobPosition;
use crate::trajectory::Origins;
use serde::Serialize;
use std::time::Duration;

/// Where an op ends on the trajectory.
#[derive(Debug, Clone, Copy, PartialEq)]
enum End {
    /// A motion or a dwell: passed once the path is at its last sample.
    Sample(f64),
    /// The job's I/O point of this index: passed once the stream has done it.
    Io(usize),
}

/// One op of a program as the page and the report name it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct StepLabel {
    /// The op's place among the program's unrolled steps.
    pub index: usize,
    /// `job.steps[1].steps[2]`.
    pub step: String,
    /// `move_linear to slot[3] + [0, 0, -0.05] m`.
    pub what: String,
    /// The repeat, the pass and its target, when the op is inside one.
    pub repeat: Option<String>,
    pub pass: Option<usize>,
    pub target: Option<String>,
    /// All of it in one line: `job.steps[1] repeat, pass 3 (slot[3]): job.steps[1].steps[2]
    /// move_linear to slot[3] + [0, 0, -0.05] m`.
    pub text: String,
}

/// Each op's end on the program's trajectory and its label.
#[derive(Debug, Clone, PartialEq)]
pub struct StepSpans {
    ends: Vec<End>,
    labels: Vec<StepLabel>,
    /// The ops, for the measured times' grouping into steps and passes.
    ops: Vec<Op>,
}

impl StepSpans {
    /// The spans of `ops` on a trajectory whose stretches are `origins` (one per op, as
    /// the program's plan names them); `None` when they do not match.
    pub(super) fn new(ops: &[Op], origins: &Origins) -> Option<Self> {
        let lasts: Vec<usize> = origins.ends().collect();
        if lasts.len() != ops.len() {
            return None;
        }
        let mut io = 0;
        let ends = ops
            .iter()
            .zip(&lasts)
            .map(|(op, &last)| match op.action {
                Action::Io(_) => {
                    io += 1;
                    End::Io(io - 1)
                }
                _ => End::Sample(last as f64),
            })
            .collect();
        let labels = ops.iter().enumerate().map(|(i, op)| label(i, op)).collect();
        Some(StepSpans {
            ends,
            labels,
            ops: ops.to_vec(),
        })
    }

    pub fn len(&self) -> usize {
        self.ends.len()
    }

    pub fn is_empty(&self) -> bool {
        self.ends.is_empty()
    }

    /// Whether op `k` is behind the stream at `at`.
    fn passed(&self, k: usize, at: JobPosition) -> bool {
        match self.ends[k] {
            End::Sample(last) => at.sample >= last,
            End::Io(point) => at.io_done > point,
        }
    }

    /// The op whose span holds `at`: the first not passed (the last once all are). Ops
    /// end in order on the trajectory, so the passed ones are a prefix.
    pub fn current(&self, at: JobPosition) -> usize {
        let first_open = (0..self.len()).find(|&k| !self.passed(k, at));
        first_open.unwrap_or(self.len().saturating_sub(1))
    }

    pub fn label(&self, k: usize) -> Option<&StepLabel> {
        self.labels.get(k)
    }
}

fn label(index: usize, op: &Op) -> StepLabel {
    let text = match &op.lap {
        Some(lap) => format!(
            "{} repeat, pass {} ({}): {} {}",
            lap.repeat, lap.index, lap.item, op.key, op.what
        ),
        None => format!("{} {}", op.key, op.what),
    };
    StepLabel {
        index,
        step: op.key.clone(),
        what: op.what.clone(),
        repeat: op.lap.as_ref().map(|lap| lap.repeat.clone()),
        pass: op.lap.as_ref().map(|lap| lap.index),
        target: op.lap.as_ref().map(|lap| lap.item.clone()),
        text,
    }
}

/// The clock times at which a stream passed each op's end: fed every cycle, it allocates
/// nothing after it is made.
#[derive(Debug, Clone)]
pub struct StepTimer {
    spans: StepSpans,
    /// The clock reading of the job's first cycle.
    start: Option<Duration>,
    /// When each op's end was passed, in order.
    passed: Vec<Duration>,
}

impl StepTimer {
    pub fn new(spans: StepSpans) -> Self {
        let passed = Vec::with_capacity(spans.len());
        StepTimer {
            spans,
            start: None,
            passed,
        }
    }

    /// One cycle: its clock reading and its place on the job's trajectory (none on an
    /// approach back to it, which counts toward the op under way).
    pub fn observe(&mut self, at: Duration, on_job: Option<JobPosition>) {
        self.start.get_or_insert(at);
        let Some(position) = on_job else {
            return;
        };
        while self.passed.len() < self.spans.len() && self.spans.passed(self.passed.len(), position)
        {
            self.passed.push(at);
        }
    }

    /// The measured cycle times of the ops passed so far, grouped as the planned ones are
    /// (per step as written, per pass of each repeat), from the job's first cycle.
    pub fn measured(&self) -> Option<CycleTimes> {
        let start = self.start?;
        let mut times = CycleTimes::default();
        let mut from = start;
        for (op, &end) in self.spans.ops.iter().zip(&self.passed) {
            times.add(
                op,
                StepTime {
                    step: op.key.clone(),
                    what: op.what.clone(),
                    start_s: from.saturating_sub(start).as_secs_f64(),
                    duration_s: end.saturating_sub(from).as_secs_f64(),
                },
            );
            from = end;
        }
        Some(times)
    }
}
