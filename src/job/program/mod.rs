//! `kind = "program"` (issue 29): a sequence of steps over the cell's named targets, as a
//! RAPID program is: joint, pose and linear moves to targets or offsets from them, each
//! with its speed, tool and zone (`zone_m`: pass near the point without stopping, as
//! RAPID's zones do; absent: `fine`, at rest there), dwells, I/O steps, and repeats over a
//! list or a grid of targets. One file per concern: `steps.rs` (the keys and their
//! validation into ops), `timing.rs` (the ops into one trajectory, corners blended), this
//! file (the job, zone checks, cycle times).
//!
//! A program compiles to one trajectory before motion like every job, and the daemon's
//! gate checks it against the cell. An I/O step is an I/O point on the trajectory, where
//! the arm is at rest and the stream waits until the controller has done it; a link that
//! carries no I/O refuses a program that uses one before motion
//! ([`Program::first_io_step`]). Must not stream, open a link or drive I/O itself.

mod progress;
mod steps;
mod timing;

pub use progress::{StepLabel, StepSpans, StepTimer};
pub use steps::{Move, NoKeys, Over, Repeat, SetOutput, Step, Wait, WaitInput};
pub use timing::{ProgramError, free_move_path};

use super::{JobContext, JobError, JobInvalid, PlanContext};
use crate::rig::Rig;
use crate::trajectory::{Origins, Trajectory};
use glam::DVec3;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use std::time::Duration;
use steps::{Action, Op, Scope};

/// A program: its steps as written, and once validated, the ops they resolve to.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Program {
    /// The steps, in order. At least one; a program unrolls (each repeat's steps once per
    /// target) to at most 10000.
    pub steps: Vec<Step>,
    /// The steps resolved against the cell by [`Program::validate`].
    #[serde(skip)]
    #[schemars(skip)]
    compiled: Option<Vec<Op>>,
}

impl Program {
    /// Every step's keys checked, its targets resolved against `context.cell`'s named
    /// targets (poses into the base frame, offsets applied), repeats unrolled, and every
    /// zone checked against its neighbouring points.
    pub fn validate(self, context: &JobContext) -> Result<Self, JobInvalid> {
        let scope = Scope::new(context);
        let ops = steps::unroll(&self.steps, &scope)?;
        check_zones(&ops, scope.rig)?;
        Ok(Program {
            compiled: Some(ops),
            ..self
        })
    }

    /// The program's trajectory from `context.start`, and each step's stretch of it named
    /// `job.steps[3] (move_linear to slot[2] + [0, 0, -0.05] m)`.
    pub fn plan(&self, context: &PlanContext) -> Result<(Trajectory, Origins), JobError> {
        let ops = self.ops()?;
        timing::plan_ops(ops, context)
    }

    fn ops(&self) -> Result<&[Op], JobInvalid> {
        self.compiled.as_deref().ok_or_else(|| {
            JobInvalid::new(
                "job.steps",
                format!("{} steps", self.steps.len()),
                "the program was not validated against its cell before planning",
            )
        })
    }

    /// The first step that needs I/O, as `job.steps[4]: grip`, if any: what a link that
    /// carries no I/O refuses before motion.
    pub fn first_io_step(&self) -> Option<String> {
        fn first(steps: &[Step], prefix: &str) -> Option<String> {
            steps.iter().enumerate().find_map(|(i, step)| {
                let key = format!("{prefix}[{i}]");
                let kind = match step {
                    Step::SetOutput(_) => "set_output",
                    Step::WaitInput(_) => "wait_input",
                    Step::Grip(_) => "grip",
                    Step::Release(_) => "release",
                    Step::Repeat(repeat) => return first(&repeat.steps, &format!("{key}.steps")),
                    _ => return None,
                };
                Some(format!("{key}: {kind}"))
            })
        }
        first(&self.steps, "job.steps")
    }

    /// Each op's end on the program's trajectory (`origins`, one stretch per op as
    /// [`Program::plan`] names them): what finds the step a streamed cycle is in, and
    /// times the steps as they stream.
    pub fn step_spans(&self, origins: &Origins) -> Option<StepSpans> {
        StepSpans::new(self.compiled.as_deref()?, origins)
    }

    /// The cycle time of each step and of each pass of each repeat, from the planned
    /// trajectory's stretches (`origins`, one per op as [`Program::plan`] names them).
    pub fn cycle_times(&self, origins: &Origins, period: Duration) -> Option<CycleTimes> {
        let ops = self.compiled.as_deref()?;
        let ends: Vec<usize> = origins.ends().collect();
        if ends.len() != ops.len() {
            return None;
        }
        let dt = period.as_secs_f64();
        let mut times = CycleTimes::default();
        let mut start = 0;
        for (op, &end) in ops.iter().zip(&ends) {
            let time = StepTime {
                step: op.key.clone(),
                what: op.what.clone(),
                start_s: start as f64 * dt,
                duration_s: end.saturating_sub(start) as f64 * dt,
            };
            times.add(op, time);
            start = end;
        }
        Some(times)
    }
}

/// One stretch's planned time: when it starts and how long it takes (s).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct StepTime {
    /// `job.steps[3]`.
    pub step: String,
    /// `move_linear to slot[2] + [0, 0, -0.05] m`; for a repeat, `repeat over 12 targets`.
    pub what: String,
    pub start_s: f64,
    pub duration_s: f64,
}

/// One pass of a repeat: its target and the time of each of its steps.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LapTime {
    /// The repeat's key, `job.steps[2]`.
    pub repeat: String,
    pub index: usize,
    /// The pass' target, `slot[4]`.
    pub target: String,
    pub start_s: f64,
    pub duration_s: f64,
    pub steps: Vec<StepTime>,
}

/// A program's cycle times: per step as written (a repeat whole) and per pass of each
/// repeat. Planned ([`Program::cycle_times`]): at full speed override without pauses, what
/// the arm takes when the job streams as planned. Measured ([`StepTimer::measured`]): the
/// clock's time from one step's end to the next as the stream passed them.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct CycleTimes {
    pub steps: Vec<StepTime>,
    pub laps: Vec<LapTime>,
}

impl CycleTimes {
    /// Adds `time`, op `op`'s, to its step and its pass.
    fn add(&mut self, op: &Op, time: StepTime) {
        let Some(lap) = &op.lap else {
            self.steps.push(time);
            return;
        };
        let end = time.start_s + time.duration_s;
        match self.steps.last_mut() {
            Some(step) if step.step == lap.repeat => step.duration_s = end - step.start_s,
            _ => self.steps.push(StepTime {
                step: lap.repeat.clone(),
                what: "repeat".to_string(),
                start_s: time.start_s,
                duration_s: time.duration_s,
            }),
        }
        match self.laps.last_mut() {
            Some(last) if last.repeat == lap.repeat && last.index == lap.index => {
                last.duration_s = end - last.start_s;
                last.steps.push(time);
            }
            _ => self.laps.push(LapTime {
                repeat: lap.repeat.clone(),
                index: lap.index,
                target: lap.item.clone(),
                start_s: time.start_s,
                duration_s: time.duration_s,
                steps: vec![time],
            }),
        }
    }
}

/// The tool's position at each op's point, for the moves (`None` for other ops).
fn points(ops: &[Op], rig: &Rig) -> Result<Vec<Option<DVec3>>, JobInvalid> {
    ops.iter()
        .map(|op| match &op.action {
            Action::Move(m) => steps::goal_position(m, rig).map(Some),
            _ => Ok(None),
        })
        .collect()
}

/// Every zone checked where its neighbours are known: a zoned point needs a move after it
/// (the arm stops for a dwell, an I/O step or the end), and its zone may be at most half
/// of the distance to the point before and to the point after (the first move's point
/// before is the start, checked when planned).
fn check_zones(ops: &[Op], rig: &Rig) -> Result<(), JobInvalid> {
    let points = points(ops, rig)?;
    let mut before: Option<(usize, DVec3)> = None;
    for (i, op) in ops.iter().enumerate() {
        let (Action::Move(m), Some(here)) = (&op.action, points[i]) else {
            continue;
        };
        if let Some(zone) = m.zone_m {
            let next = ops.get(i + 1);
            let after = match (next, points.get(i + 1).copied().flatten()) {
                (Some(next), Some(point)) => (next, point),
                (Some(next), None) => {
                    return Err(zone_refused(
                        op,
                        zone,
                        format!(
                            "the arm stops at rest for {} ({}): a point before it must be fine (leave zone_m out)",
                            next.key, next.what
                        ),
                    ));
                }
                (None, _) => {
                    return Err(zone_refused(
                        op,
                        zone,
                        "a program ends at rest: its last move must be fine (leave zone_m out)"
                            .to_string(),
                    ));
                }
            };
            let from = before.map(|(k, point)| (ops[k].key.as_str(), ops[k].what.as_str(), point));
            check_zone_room(op, zone, here, from, (&after.0.key, &after.0.what, after.1))?;
        }
        before = Some((i, here));
    }
    Ok(())
}

/// A neighbouring point of a zone: its step's key and words, and the tool's position.
pub(crate) type Neighbour<'a> = (&'a str, &'a str, DVec3);

/// RAPID's rule, refused rather than applied: a zone may be at most half the distance to
/// the point before and to the point after (ABB, RAPID Reference Manual, "zonedata": "The
/// zone size cannot be larger than half the distance to the closest position (forwards or
/// backwards)"). RAPID then reduces the zone itself; rigbridge never moves otherwise than
/// written, so it refuses, naming both neighbours and the largest zone that fits.
pub(crate) fn check_zone_room(
    op: &Op,
    zone: f64,
    here: DVec3,
    before: Option<Neighbour>,
    after: Neighbour,
) -> Result<(), JobInvalid> {
    let to_after = (after.2 - here).length();
    let to_before = before.map(|b| (here - b.2).length());
    let room = to_before.map_or(to_after, |d| d.min(to_after)) / 2.0;
    if zone <= room {
        return Ok(());
    }
    let before_text = match (before, to_before) {
        (Some((key, what, _)), Some(d)) => format!("{d:.3} m from {key} ({what})"),
        _ => "the job's start (checked when planned)".to_string(),
    };
    Err(zone_refused(
        op,
        zone,
        format!(
            "larger than half a neighbouring segment: {before_text} to this point, {to_after:.3} m from it to {} ({}); at most {room:.3} m fits (RAPID would shrink the zone, rigbridge refuses to move otherwise than written)",
            after.0, after.1
        ),
    ))
}

fn zone_refused(op: &Op, zone: f64, reason: String) -> JobInvalid {
    JobInvalid::new(format!("{}.zone_m", op.key), zone, reason)
}
