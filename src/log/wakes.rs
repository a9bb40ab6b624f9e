//! The streaming cycle's wakes, one way for everyone (issue 32): how late each cycle woke,
//! counted in a [`MicrosHistogram`] by the stream as it runs and rebuilt from a run log by
//! [`wake_lateness`], and the jitter figures [`Jitter::of`] reads off either histogram. The
//! run's summary, `rigbridge log info` and `log plot` all go through [`Jitter::of`], so
//! they agree on one log to the microsecond. Also the stalls a log records
//! ([`LoggedStall`]). Owns the histogram, the jitter figures and reading stalls back; must
//! not time cycles itself or write files. The histogram records without allocating, so the
//! cycle may use it.

use super::{LoggedEvent, RunLog};
use serde::Serialize;
use std::fmt;

/// The event kind of a stall in a log (`docs/logs.md`, "Stalls").
pub const STALL_EVENT: &str = "stalled";
/// The jitter histogram's ceiling: later wakes share its last bin (their percentiles read
/// as this, a lower bound; the maximum stays exact). A tenth of a second is 25 cycles at
/// 250 Hz, the controller's watchdog: past it the figure that matters is the stall's own.
pub const JITTER_CEILING_US: usize = 100_000;

/// Values below this get a bin of 1 us each: every cycle's jitter and latency that
/// matters to a percentile (a tenth of a 1 kHz cycle is 100 us, a 250 Hz cycle 4,000 us).
const FINE_CEILING_US: usize = 5_000;
/// Above [`FINE_CEILING_US`], bins this wide: a stall's length to a tenth of a millisecond.
const COARSE_BIN_US: usize = 100;

/// Counts of microsecond values: 1 us bins up to [`FINE_CEILING_US`], then
/// [`COARSE_BIN_US`] bins up to a ceiling, each standing for its upper edge; larger values
/// share the last bin (and are counted as the ceiling in the percentiles, a lower bound). Small enough (about 48 KB at a
/// 100 ms ceiling, not 800 KB of 1 us bins) to be written through when made, so a cycle
/// later than any before never takes a page fault on a fresh bin: a fault waits for the
/// process's memory map, which another thread may be changing.
#[derive(Debug, Clone, PartialEq)]
pub struct MicrosHistogram {
    bins: Vec<u64>,
    ceiling_us: usize,
    count: u64,
    max_us: f64,
}

impl MicrosHistogram {
    pub fn new(ceiling_us: usize) -> Self {
        let fine = ceiling_us.min(FINE_CEILING_US);
        let coarse = ceiling_us
            .saturating_sub(FINE_CEILING_US)
            .div_ceil(COARSE_BIN_US);
        let len = fine + 1 + coarse;
        // Zeroed memory may come as pages the kernel maps on first touch, and a compiler
        // may drop plain zero writes to it: `black_box` makes each write one it must do.
        let mut bins = vec![0; len];
        for bin in &mut bins {
            *bin = std::hint::black_box(0);
        }
        Self {
            bins,
            ceiling_us,
            count: 0,
            max_us: 0.0,
        }
    }

    /// The bin of a value (us), and the value a bin stands for: its own microsecond, or a
    /// coarse bin's upper edge (so a percentile never understates a late cycle).
    fn bin_of(&self, micros: f64) -> usize {
        let us = (micros.max(0.0).round() as usize).min(self.ceiling_us);
        if us <= FINE_CEILING_US {
            us
        } else {
            FINE_CEILING_US + (us - FINE_CEILING_US).div_ceil(COARSE_BIN_US)
        }
        .min(self.bins.len() - 1)
    }

    fn value_of(&self, bin: usize) -> f64 {
        if bin <= FINE_CEILING_US {
            bin as f64
        } else {
            let value = FINE_CEILING_US + (bin - FINE_CEILING_US) * COARSE_BIN_US;
            value.min(self.ceiling_us) as f64
        }
    }

    pub fn record(&mut self, micros: f64) {
        let bin = self.bin_of(micros);
        self.bins[bin] += 1;
        self.count += 1;
        self.max_us = self.max_us.max(micros);
    }

    /// Adds `other`'s counts to these: one histogram for a job streamed in several parts.
    /// Both must share a ceiling (every jitter histogram has [`JITTER_CEILING_US`]).
    pub fn add(&mut self, other: &MicrosHistogram) {
        for (mine, theirs) in self.bins.iter_mut().zip(&other.bins) {
            *mine += theirs;
        }
        self.count += other.count;
        self.max_us = self.max_us.max(other.max_us);
    }

    pub fn count(&self) -> u64 {
        self.count
    }

    pub fn max_us(&self) -> f64 {
        self.max_us
    }

    /// The smallest bin value at or below which `fraction` of the samples lie (0 if empty).
    pub fn percentile(&self, fraction: f64) -> f64 {
        if self.count == 0 {
            return 0.0;
        }
        let wanted = (fraction * self.count as f64).ceil().max(1.0) as u64;
        let mut seen = 0;
        for (bin, n) in self.bins.iter().enumerate() {
            seen += n;
            if seen >= wanted {
                return self.value_of(bin);
            }
        }
        self.value_of(self.bins.len() - 1)
    }
}

/// The jitter figures of a stream: how late its cycles woke after their deadlines. Counted
/// over every wake that sent a target, and every stalled wake (which sent nothing it had
/// planned); the wake that ends a stream without sending (an e-stop, a refusal) is not.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct Jitter {
    /// Wakes counted.
    pub cycles: u64,
    pub p50_us: f64,
    pub p99_us: f64,
    pub max_us: f64,
}

impl Jitter {
    /// The figures of `histogram`: the one computation behind the run's summary,
    /// `log info` and `log plot`.
    pub fn of(histogram: &MicrosHistogram) -> Jitter {
        Jitter {
            cycles: histogram.count(),
            p50_us: histogram.percentile(0.5),
            p99_us: histogram.percentile(0.99),
            max_us: histogram.max_us(),
        }
    }
}

impl fmt::Display for Jitter {
    /// `jitter p50 3 us, p99 14 us, max 300000 us`: as `run` has always printed it.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "jitter p50 {:.0} us, p99 {:.0} us, max {:.0} us",
            self.p50_us, self.p99_us, self.max_us
        )
    }
}

/// The lateness (us) of every wake the log holds, in file order: each command's (format 2)
/// and each stall's. A log written before format 2 holds it on the states instead, and no
/// stall's; that is what it gives then.
pub fn wake_lateness(log: &RunLog) -> Vec<f64> {
    let on_commands = log.commands.iter().any(|c| c.late_us.is_some());
    let samples = if on_commands {
        &log.commands
    } else {
        &log.states
    };
    let stalls = stalls(log).into_iter().filter_map(|s| s.late_us);
    samples
        .iter()
        .filter_map(|s| s.late_us)
        .chain(stalls)
        .filter(|v| v.is_finite())
        .collect()
}

/// The jitter figures of a log, counted as the stream counted them; `None` when the log
/// holds no wake's lateness.
pub fn jitter(log: &RunLog) -> Option<Jitter> {
    let wakes = wake_lateness(log);
    if wakes.is_empty() {
        return None;
    }
    let mut histogram = MicrosHistogram::new(JITTER_CEILING_US);
    for late in wakes {
        histogram.record(late);
    }
    Some(Jitter::of(&histogram))
}

/// A stall as its log records it (`docs/logs.md`, "Stalls").
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LoggedStall {
    /// Seconds of streaming before it (the report's `at_s`).
    pub t: f64,
    /// How late the cycle woke (us); `None` in logs written before format 2.
    pub late_us: Option<f64>,
    /// The last seq sent before it; `None` before format 2.
    pub seq: Option<u32>,
    /// The stream's words for it.
    pub why: String,
    /// What the bridge did then (`resumed`, `ended`); `None` before format 2.
    pub then: Option<String>,
}

impl LoggedStall {
    fn of(event: &LoggedEvent) -> LoggedStall {
        let detail = &event.detail;
        LoggedStall {
            t: event.t,
            late_us: detail["late_us"].as_f64(),
            seq: detail["seq"].as_u64().and_then(|s| u32::try_from(s).ok()),
            why: detail["why"].as_str().unwrap_or_default().to_owned(),
            then: None,
        }
    }
}

impl fmt::Display for LoggedStall {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "stall at {:.3} s: {}", self.t, self.why)?;
        match &self.then {
            Some(then) => write!(f, "; then {then}"),
            None => Ok(()),
        }
    }
}

/// The event the bridge logs when it goes back to the path after an interruption.
const RESUMED_EVENT: &str = "resumed";
/// The event of a link loss, the other interruption.
const LINK_LOST_EVENT: &str = "link_lost";

/// Every stall the log records, in file order. A stall is logged as it happens; what the
/// bridge did then is the `resumed` event after it, before the next interruption, or
/// else the job's end (format 2; a format 1 log's stalls say only their words).
pub fn stalls(log: &RunLog) -> Vec<LoggedStall> {
    let events = &log.events;
    events
        .iter()
        .enumerate()
        .filter(|(_, e)| e.kind == STALL_EVENT)
        .map(|(k, event)| {
            let mut stall = LoggedStall::of(event);
            if stall.seq.is_some() {
                let resumed = events[k + 1..]
                    .iter()
                    .find(|e| {
                        [RESUMED_EVENT, STALL_EVENT, LINK_LOST_EVENT].contains(&e.kind.as_str())
                    })
                    .is_some_and(|e| e.kind == RESUMED_EVENT);
                stall.then = Some(if resumed { "resumed" } else { "ended" }.to_owned());
            }
            stall
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn percentiles_of_a_known_spread() {
        let mut histogram = MicrosHistogram::new(1000);
        for v in 1..=100 {
            histogram.record(v as f64);
        }
        assert_eq!(histogram.percentile(0.5), 50.0);
        assert_eq!(histogram.percentile(0.99), 99.0);
        assert_eq!(histogram.percentile(1.0), 100.0);
        histogram.record(5000.0);
        assert_eq!(histogram.percentile(1.0), 1000.0);
        assert_eq!(histogram.max_us(), 5000.0);
    }

    #[test]
    fn late_values_share_coarse_bins_up_to_the_ceiling() {
        let mut histogram = MicrosHistogram::new(100_000);
        // Fine to 5 ms: every microsecond its own bin.
        histogram.record(4_999.0);
        assert_eq!(histogram.percentile(1.0), 4_999.0);
        histogram.record(5_000.0);
        assert_eq!(histogram.percentile(1.0), 5_000.0);
        // Then 100 us bins, each standing for its upper edge: 5,001..=5,100 is one bin.
        histogram.record(5_001.0);
        assert_eq!(histogram.percentile(1.0), 5_100.0);
        histogram.record(12_345.0);
        assert_eq!(histogram.percentile(1.0), 12_400.0);
        histogram.record(250_000.0);
        assert_eq!(histogram.percentile(1.0), 100_000.0);
        assert_eq!(histogram.percentile(0.2), 4_999.0);
        assert_eq!(histogram.count(), 5);
        // About 48 KB, against 800 KB of 1 us bins to 100 ms.
        assert_eq!(histogram.bins.len(), 5_001 + 950);
    }

    #[test]
    fn parts_added_give_the_figures_of_the_whole() {
        let (mut first, mut second, mut whole) = (
            MicrosHistogram::new(JITTER_CEILING_US),
            MicrosHistogram::new(JITTER_CEILING_US),
            MicrosHistogram::new(JITTER_CEILING_US),
        );
        // A short part that ends in a stall, a long calm one after it.
        for late in [3.0, 4.0, 300_000.0] {
            first.record(late);
            whole.record(late);
        }
        for k in 0..200 {
            let late = f64::from(k % 7);
            second.record(late);
            whole.record(late);
        }
        // The worst part's p99 is the stall (100 ms, the ceiling); the whole's is not.
        assert_eq!(Jitter::of(&first).p99_us, 100_000.0);
        first.add(&second);
        assert_eq!(first, whole);
        let jitter = Jitter::of(&first);
        assert_eq!(
            (jitter.cycles, jitter.p99_us, jitter.max_us),
            (203, 6.0, 300_000.0)
        );
        assert_eq!(
            jitter.to_string(),
            "jitter p50 3 us, p99 6 us, max 300000 us"
        );
    }

    fn sample(seq: u32, late_us: Option<f64>) -> super::super::LoggedSample {
        super::super::LoggedSample {
            seq,
            t: f64::from(seq) * 0.004,
            positions: vec![0.0],
            velocities: vec![0.0],
            late_us,
        }
    }

    fn event(kind: &str, detail: serde_json::Value) -> LoggedEvent {
        LoggedEvent {
            t: 0.8,
            kind: kind.to_owned(),
            detail,
        }
    }

    #[test]
    fn a_format_2_log_counts_its_commands_and_stalls_a_format_1_log_its_states() {
        let mut log = RunLog {
            commands: vec![sample(1, Some(2.0)), sample(2, Some(7.0))],
            // A state without feedback's command: no state, the command still counts.
            states: vec![sample(1, None)],
            events: vec![
                event(
                    STALL_EVENT,
                    serde_json::json!({"seq": 2, "late_us": 300000.0, "why": "the cycle woke 300.0 ms late"}),
                ),
                event(RESUMED_EVENT, serde_json::json!({})),
                event(
                    STALL_EVENT,
                    serde_json::json!({"seq": 2, "late_us": 200000.0, "why": "the cycle woke 200.0 ms late"}),
                ),
            ],
            ..RunLog::default()
        };
        assert_eq!(wake_lateness(&log), vec![2.0, 7.0, 300_000.0, 200_000.0]);
        let all = stalls(&log);
        let stall = &all[0];
        assert_eq!(
            (stall.seq, stall.late_us, stall.then.as_deref()),
            (Some(2), Some(300_000.0), Some("resumed"))
        );
        // No `resumed` after the last: the job ended there.
        assert_eq!(all[1].then.as_deref(), Some("ended"));
        assert_eq!(
            stall.to_string(),
            "stall at 0.800 s: the cycle woke 300.0 ms late; then resumed"
        );
        // Format 1: lateness on the states, stalls with their words only.
        log.commands = vec![sample(1, None), sample(2, None)];
        log.states = vec![sample(1, Some(5.0)), sample(2, Some(9.0))];
        log.events = vec![event(
            STALL_EVENT,
            serde_json::json!({"at_sample": 10, "why": "the cycle woke 23.2 ms late"}),
        )];
        assert_eq!(wake_lateness(&log), vec![5.0, 9.0]);
        let stall = &stalls(&log)[0];
        assert_eq!(
            (stall.seq, stall.late_us, stall.then.clone()),
            (None, None, None)
        );
        assert_eq!(jitter(&log).map(|j| j.max_us), Some(9.0));
        log.states.clear();
        assert_eq!(jitter(&log), None);
    }
}
