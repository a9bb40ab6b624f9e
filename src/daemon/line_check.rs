//! After a `move_linear` run that stalled: how far the tool left its lines after each stall,
//! measured from the log's reported states (issue 32). A stall sends the controller a Stop;
//! it brakes each axis on its own, off the line, and the way back to the path is a joint
//! move: the line's promise (`job::LINE_TOLERANCE_M`, `docs/jobs.md`) may break, and the
//! run must say so with the figure. Owns this measurement and its words; reads the log
//! after it is closed, never during the run, and must not change the job's outcome.

use super::config::RunSettings;
use crate::job::{LINE_TOLERANCE_M, MoveLinear};
use crate::log::{RunLog, STALL_EVENT};
use crate::stream::Outcome;
use serde::Serialize;
use std::fmt;

/// Lines start at the first command whose tool is this close to the first pose (m): the
/// joint move ends on it, to the inverse kinematics' precision (a micrometre,
/// `tests/jobs.rs`), with room for rounding.
const LINE_START_M: f64 = 1e-5;

/// How far the tool left its line after one stall, until the next interruption or the end.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LineAfterStall {
    /// The stall's time (the report's `interruptions[].at_s`).
    pub stall_at_s: f64,
    /// The largest distance of the measured tool from the lines, in mm.
    pub off_line_mm: f64,
    /// When it was measured (s, the same time base).
    pub at_s: f64,
    /// What `move_linear` promises (mm).
    pub promised_mm: f64,
    /// Whether `off_line_mm` breaks the promise.
    pub broken: bool,
}

impl fmt::Display for LineAfterStall {
    /// `after the stall at 3.21 s the tool left its line by 1.14 mm (move_linear promises
    /// 0.5 mm)`, or that it kept within it.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.broken {
            write!(
                f,
                "after the stall at {:.2} s the tool left its line by {:.2} mm (move_linear promises {} mm)",
                self.stall_at_s, self.off_line_mm, self.promised_mm
            )
        } else {
            write!(
                f,
                "after the stall at {:.2} s the tool kept within {:.2} mm of its line (move_linear promises {} mm)",
                self.stall_at_s, self.off_line_mm, self.promised_mm
            )
        }
    }
}

/// An interruption as the log records it: its time and the last seq sent before it.
struct Window {
    at_s: f64,
    seq: u32,
    stall: bool,
    worst: Option<(f64, u32)>,
}

/// For each stall `log` records (format 2: with its seq), the tool's largest distance from
/// `job`'s lines, by forward kinematics of the reported states from the stall to the next
/// interruption (or the end). Empty when the job has no line or the log holds no stall.
pub fn after_stalls(settings: &RunSettings, job: &MoveLinear, log: &RunLog) -> Vec<LineAfterStall> {
    let Ok(Some(mut lines)) = job.lines() else {
        return Vec::new();
    };
    let mut windows = interruptions(log);
    if !windows.iter().any(|w| w.stall) {
        return Vec::new();
    }
    let rig = &settings.tcp_rig;
    let tool = |q: &[f64]| rig.tool_pose(q).ok().map(|pose| pose.position);
    let start = lines.start();
    let Some(first) = log
        .commands
        .iter()
        .find(|c| tool(&c.positions).is_some_and(|p| (p - start).length() <= LINE_START_M))
        .map(|c| c.seq)
    else {
        return Vec::new();
    };
    for state in log.states.iter().filter(|s| s.seq >= first) {
        let Some(window) = windows.iter_mut().rev().find(|w| w.seq < state.seq) else {
            continue;
        };
        let Some(p) = tool(&state.positions) else {
            continue;
        };
        let distance = lines.distance(p);
        if distance.is_finite() && window.worst.is_none_or(|(worst, _)| distance > worst) {
            window.worst = Some((distance, state.seq));
        }
    }
    let period = settings.period().as_secs_f64();
    let promised_mm = LINE_TOLERANCE_M * 1e3;
    windows
        .into_iter()
        .filter(|w| w.stall)
        .filter_map(|w| {
            let (worst, seq) = w.worst?;
            let off_line_mm = worst * 1e3;
            Some(LineAfterStall {
                stall_at_s: w.at_s,
                off_line_mm,
                at_s: w.at_s + f64::from(seq.wrapping_sub(w.seq)) * period,
                promised_mm,
                broken: off_line_mm > promised_mm,
            })
        })
        .collect()
}

/// The log's stalls and link losses that say their seq (format 2), in seq order.
fn interruptions(log: &RunLog) -> Vec<Window> {
    let link_lost = Outcome::LinkLost.to_string();
    let mut windows: Vec<Window> = log
        .events
        .iter()
        .filter(|e| e.kind == STALL_EVENT || e.kind == link_lost)
        .filter_map(|e| {
            Some(Window {
                at_s: e.t,
                seq: u32::try_from(e.detail["seq"].as_u64()?).ok()?,
                stall: e.kind == STALL_EVENT,
                worst: None,
            })
        })
        .collect();
    windows.sort_by_key(|w| w.seq);
    windows
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_stall_is_logged_under_the_kind_the_measurement_reads() {
        // resume.rs names the event after the outcome; the log reads stalls by this kind.
        assert_eq!(Outcome::Stalled.to_string(), STALL_EVENT);
    }

    #[test]
    fn says_a_broken_promise_with_its_figure() {
        let line = LineAfterStall {
            stall_at_s: 3.2104,
            off_line_mm: 1.1372,
            at_s: 3.3,
            promised_mm: 0.5,
            broken: true,
        };
        assert_eq!(
            line.to_string(),
            "after the stall at 3.21 s the tool left its line by 1.14 mm (move_linear promises 0.5 mm)"
        );
    }
}
