//! What `rigbridge log info` shows about a run log: counts, time span, seq gaps, events by
//! kind, the jitter (as the run counted it, `wakes`), each stall, and tracking error
//! (command vs reported state, matched by seq). Pure arithmetic on a [`RunLog`]; must not
//! read files or change the log.

use super::wakes::{Jitter, LoggedStall, jitter, stalls};
use super::wire::{EVENTS_TOPIC, command_topic, state_topic};
use super::{LoggedSample, ReadStop, RunLog};
use crate::rig::JointKind;
use serde::Serialize;
use std::collections::{BTreeMap, HashMap};
use std::fmt;

/// Gaps listed one by one; the rest are only counted.
const LISTED_GAPS: usize = 20;

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LogSummary {
    pub rig: String,
    pub joints: Vec<String>,
    pub truncated: bool,
    pub stopped: Option<ReadStop>,
    /// Messages per topic, rigbridge's three always present.
    pub messages: BTreeMap<String, u64>,
    /// Earliest and latest job time over commands, states and events (s).
    pub first_t: Option<f64>,
    pub last_t: Option<f64>,
    pub duration_s: f64,
    pub commands: ChannelSummary,
    pub states: ChannelSummary,
    pub events_by_kind: BTreeMap<String, u64>,
    /// How late the cycles woke, counted as the run's own summary counts it; `None` when
    /// the log holds no lateness.
    pub jitter: Option<Jitter>,
    /// Every stall, in file order.
    pub stalls: Vec<LoggedStall>,
    /// Commands that have a state with the same seq: what `tracking` compares.
    pub tracking_pairs: u64,
    /// Per joint, in joint order.
    pub tracking: Vec<TrackingError>,
    pub other_messages: u64,
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ChannelSummary {
    pub topic: String,
    pub count: u64,
    /// In file order.
    pub first_seq: Option<u32>,
    pub last_seq: Option<u32>,
    /// Places where a seq is not the previous one plus 1 (forward jumps, repeats, going back).
    pub gap_count: u64,
    /// Seq numbers skipped by forward jumps.
    pub missing: u64,
    /// The first gaps.
    pub gaps: Vec<SeqGap>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct SeqGap {
    pub after: u32,
    pub next: u32,
}

/// Largest |command - state| of one joint over the matched cycles.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TrackingError {
    pub joint: String,
    /// `deg` (revolute), `m` (prismatic) or `rad|m` when the log does not say which.
    pub unit: &'static str,
    pub max_abs: f64,
    /// The cycle where the maximum occurred.
    pub seq: Option<u32>,
    pub t: Option<f64>,
}

pub fn summarize(log: &RunLog) -> LogSummary {
    let commands = channel_summary(command_topic(&log.rig), &log.commands);
    let states = channel_summary(state_topic(&log.rig), &log.states);
    let mut messages = BTreeMap::new();
    messages.insert(commands.topic.clone(), commands.count);
    messages.insert(states.topic.clone(), states.count);
    messages.insert(EVENTS_TOPIC.to_owned(), log.events.len() as u64);
    let mut events_by_kind = BTreeMap::new();
    for event in &log.events {
        *events_by_kind.entry(event.kind.clone()).or_insert(0) += 1;
    }
    let (first_t, last_t) = time_span(log);
    let (tracking_pairs, tracking) = tracking(log);
    LogSummary {
        rig: log.rig.clone(),
        joints: log.joint_names.clone(),
        truncated: log.truncated,
        stopped: log.stopped.clone(),
        messages,
        first_t,
        last_t,
        duration_s: match (first_t, last_t) {
            (Some(first), Some(last)) => last - first,
            _ => 0.0,
        },
        commands,
        states,
        events_by_kind,
        jitter: jitter(log),
        stalls: stalls(log),
        tracking_pairs,
        tracking,
        other_messages: log.other_messages,
    }
}

fn channel_summary(topic: String, samples: &[LoggedSample]) -> ChannelSummary {
    let mut summary = ChannelSummary {
        topic,
        count: samples.len() as u64,
        first_seq: samples.first().map(|s| s.seq),
        last_seq: samples.last().map(|s| s.seq),
        gap_count: 0,
        missing: 0,
        gaps: Vec::new(),
    };
    for pair in samples.windows(2) {
        let (after, next) = (pair[0].seq, pair[1].seq);
        if next == after.wrapping_add(1) {
            continue;
        }
        summary.gap_count += 1;
        if next > after {
            summary.missing += u64::from(next - after - 1);
        }
        if summary.gaps.len() < LISTED_GAPS {
            summary.gaps.push(SeqGap { after, next });
        }
    }
    summary
}

fn time_span(log: &RunLog) -> (Option<f64>, Option<f64>) {
    let times = log
        .commands
        .iter()
        .chain(&log.states)
        .map(|s| s.t)
        .chain(log.events.iter().map(|e| e.t))
        .filter(|t| t.is_finite());
    times.fold(
        (None, None),
        |(first, last): (Option<f64>, Option<f64>), t| {
            (
                Some(first.map_or(t, |f| f.min(t))),
                Some(last.map_or(t, |l| l.max(t))),
            )
        },
    )
}

fn tracking(log: &RunLog) -> (u64, Vec<TrackingError>) {
    let mut errors: Vec<TrackingError> = log
        .joint_names
        .iter()
        .enumerate()
        .map(|(axis, joint)| TrackingError {
            joint: joint.clone(),
            unit: unit(log, axis),
            max_abs: 0.0,
            seq: None,
            t: None,
        })
        .collect();
    let states: HashMap<u32, &LoggedSample> = log.states.iter().map(|s| (s.seq, s)).collect();
    let mut pairs = 0;
    for command in &log.commands {
        let Some(state) = states.get(&command.seq) else {
            continue;
        };
        pairs += 1;
        let deltas = command.positions.iter().zip(&state.positions);
        for (axis, (error, (c, s))) in errors.iter_mut().zip(deltas).enumerate() {
            let delta = in_unit(log, axis, (c - s).abs());
            if delta > error.max_abs {
                error.max_abs = delta;
                error.seq = Some(command.seq);
                error.t = Some(command.t);
            }
        }
    }
    (pairs, errors)
}

fn kind(log: &RunLog, axis: usize) -> Option<JointKind> {
    log.joint_kinds.as_ref()?.get(axis).copied()
}

fn unit(log: &RunLog, axis: usize) -> &'static str {
    kind(log, axis).map_or("rad|m", JointKind::unit)
}

fn in_unit(log: &RunLog, axis: usize, value: f64) -> f64 {
    kind(log, axis).map_or(value, |kind| kind.to_user(value))
}

impl fmt::Display for LogSummary {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "rig {}, {} joints: {}",
            self.rig,
            self.joints.len(),
            self.joints.join(", ")
        )?;
        match &self.stopped {
            Some(stop) => writeln!(
                f,
                "file: TRUNCATED at byte {}: {}",
                stop.offset, stop.reason
            )?,
            None => writeln!(f, "file: complete")?,
        }
        match (self.first_t, self.last_t) {
            (Some(first), Some(last)) => writeln!(
                f,
                "job time: {first:.6} .. {last:.6} s ({:.3} s)",
                self.duration_s
            )?,
            _ => writeln!(f, "job time: no messages")?,
        }
        write_channel(f, &self.commands)?;
        write_channel(f, &self.states)?;
        self.write_events(f)?;
        self.write_wakes(f)?;
        if self.other_messages > 0 {
            writeln!(f, "other messages: {}", self.other_messages)?;
        }
        self.write_tracking(f)
    }
}

impl LogSummary {
    fn write_events(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let count: u64 = self.events_by_kind.values().sum();
        let kinds: Vec<String> = self
            .events_by_kind
            .iter()
            .map(|(kind, n)| format!("{kind} {n}"))
            .collect();
        let kinds = if kinds.is_empty() {
            String::new()
        } else {
            format!(": {}", kinds.join(", "))
        };
        writeln!(f, "{EVENTS_TOPIC:<28} {count} messages{kinds}")
    }

    fn write_wakes(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match &self.jitter {
            Some(jitter) => writeln!(f, "{jitter} over {} cycles", jitter.cycles)?,
            None => writeln!(f, "jitter: no per-cycle timing (late_us) in this log")?,
        }
        for (k, stall) in self.stalls.iter().enumerate() {
            writeln!(f, "  stall {} of {}: {stall}", k + 1, self.stalls.len())?;
        }
        Ok(())
    }

    fn write_tracking(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "tracking error, max |command - state| over {} cycles with both:",
            self.tracking_pairs
        )?;
        if self.tracking_pairs == 0 {
            return Ok(());
        }
        let width = self.joints.iter().map(String::len).max().unwrap_or(0);
        for error in &self.tracking {
            write!(
                f,
                "  {:<width$}  {:>12.6} {:<5}",
                error.joint, error.max_abs, error.unit
            )?;
            match (error.seq, error.t) {
                (Some(seq), Some(t)) => writeln!(f, " at seq {seq} (t {t:.3} s)")?,
                _ => writeln!(f)?,
            }
        }
        Ok(())
    }
}

fn write_channel(f: &mut fmt::Formatter<'_>, channel: &ChannelSummary) -> fmt::Result {
    write!(f, "{:<28} {} messages", channel.topic, channel.count)?;
    if let (Some(first), Some(last)) = (channel.first_seq, channel.last_seq) {
        write!(f, ", seq {first}..{last}")?;
    }
    if channel.gap_count == 0 {
        return writeln!(f, ", no seq gaps");
    }
    let listed: Vec<String> = channel
        .gaps
        .iter()
        .map(|g| format!("{} -> {}", g.after, g.next))
        .collect();
    let more = channel.gap_count - channel.gaps.len() as u64;
    let more = if more > 0 {
        format!(" and {more} more")
    } else {
        String::new()
    };
    writeln!(
        f,
        ", {} seq gaps ({} missing): {}{more}",
        channel.gap_count,
        channel.missing,
        listed.join(", ")
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::log::LoggedEvent;

    fn sample(seq: u32, t: f64, q: [f64; 2]) -> LoggedSample {
        LoggedSample {
            seq,
            t,
            positions: q.to_vec(),
            velocities: vec![0.0; 2],
            late_us: None,
        }
    }

    #[test]
    fn counts_gaps_events_and_tracking_in_degrees_for_revolute_joints() {
        let log = RunLog {
            rig: "arm".into(),
            joint_names: vec!["j1".into(), "slide".into()],
            joint_kinds: Some(vec![JointKind::Revolute, JointKind::Prismatic]),
            metadata: serde_json::Value::Null,
            commands: vec![
                sample(0, 0.0, [0.0, 0.0]),
                sample(1, 0.004, [0.1, 0.5]),
                sample(4, 0.016, [0.2, 0.5]),
            ],
            states: vec![sample(0, 0.0, [0.0, 0.0]), sample(1, 0.004, [0.09, 0.49])],
            events: vec![
                LoggedEvent {
                    t: 0.0,
                    kind: "job_started".into(),
                    detail: serde_json::Value::Null,
                },
                LoggedEvent {
                    t: 0.02,
                    kind: "job_ended".into(),
                    detail: serde_json::Value::Null,
                },
            ],
            other_messages: 0,
            truncated: false,
            stopped: None,
        };
        let summary = summarize(&log);
        assert_eq!(summary.commands.gap_count, 1);
        assert_eq!(summary.commands.missing, 2);
        assert_eq!(summary.commands.gaps, vec![SeqGap { after: 1, next: 4 }]);
        assert_eq!(summary.states.gap_count, 0);
        assert_eq!(summary.tracking_pairs, 2);
        assert!((summary.tracking[0].max_abs - 0.01_f64.to_degrees()).abs() < 1e-9);
        assert_eq!(summary.tracking[0].unit, "deg");
        assert!((summary.tracking[1].max_abs - 0.01).abs() < 1e-12);
        assert_eq!(summary.tracking[1].seq, Some(1));
        assert_eq!(summary.duration_s, 0.02);
        assert_eq!(summary.events_by_kind.get("job_ended"), Some(&1));
        assert_eq!(summary.messages.get("/arm/joint_command"), Some(&3));
        let text = summary.to_string();
        assert!(text.contains("1 seq gaps (2 missing): 1 -> 4"), "{text}");
        assert!(text.contains("file: complete"), "{text}");
        serde_json::to_string(&summary).expect("the summary serialises to JSON");
    }
}
