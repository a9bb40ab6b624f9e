//! The twin's collision watch (issue 27): from the actual joint positions the twin reaches,
//! every cycle, the smallest clearance of every checked pair of the cell's collision model
//! that comes within a cutoff, and the collision episodes (a pair in contact from one cycle
//! to the last, with its deepest penetration). A contact that begins while the twin moves
//! is what a controller's collision detection stops the arm for: the watch says so, and the
//! twin latches the fault.
//!
//! Cheap per cycle: most cycles are not measured. A bound on how far any point of any body
//! can have moved since the last measured cycle tells when no pair can have come closer than
//! its minimum so far, crossed the cutoff or touched or left a contact; only other cycles
//! measure, so the minima and episodes are those of every cycle. Owns the measurements and
//! their report; it must not change the twin (the twin acts on what it is told), allocate
//! in a cycle, or know about links, jobs or logs.

use crate::cell::{BodyId, Cell, Clearance, CollisionModel, Scratch};
use crate::rig::{JointKind, Rig};
use serde::Serialize;
use std::sync::{Arc, Mutex, PoisonError};

/// Pairs closer than this (or than two margins, when the margin is wider) are listed with
/// their smallest clearance: five times the default 0.01 m margin, the pairs a person
/// commissioning a cell wants to see; farther pairs are only said to stay beyond it.
pub const REPORT_CUTOFF_M: f64 = 0.05;
/// The watch asks the model for the pairs this much beyond the cutoff: a pair it did not
/// return must move this far before it matters, so cycles between can be skipped (the
/// larger, the longer the skips and the more pairs each measurement returns).
pub const LOOKAHEAD_M: f64 = 0.05;
/// Closed episodes kept for the report; beyond them episodes are counted only (a cycle must
/// not allocate, and a report of a thousand contacts says no more than its count).
pub const KEPT_EPISODES: usize = 64;
/// Rounding allowance (m) on the skip bound: clearances and bounds are sums of a few
/// products of metres, off by about 1e-15 m each.
const BOUND_ROUNDING_M: f64 = 1e-9;
/// What the reported minima and depths may be off by: motion below this since the last
/// measured cycle is not measured again (an arm settling on its goal creeps by nanometres
/// every cycle, each a possible new minimum of the pair it rests nearest).
pub const RESOLUTION_M: f64 = 1e-6;

/// How far (at most) any point of any body of a rig moves between two joint positions:
/// per joint, its lever (every body after a revolute joint lies within it of the joint's
/// axis whatever the other joints do; a prismatic joint moves them by its own travel).
#[derive(Debug, Clone)]
pub struct Reach {
    levers: Vec<f64>,
}

impl Reach {
    /// The levers of `rig` carrying `tool` (bodies in tool0, which is the rig's tool frame).
    pub fn new(rig: &Rig, cell: &Cell) -> Self {
        let body_radius = |frame_min: usize| {
            rig.bodies
                .iter()
                .filter(|body| body.frame >= frame_min)
                .flat_map(|body| &body.collisions)
                .map(|c| c.origin.translation.length() + c.shape.bounding_radius().unwrap_or(0.0))
                .fold(0.0, f64::max)
        };
        let tool_radius = cell
            .tool
            .iter()
            .flat_map(|tool| &tool.bodies)
            .map(|c| c.origin.translation.length() + c.shape.bounding_radius().unwrap_or(0.0))
            .fold(0.0, f64::max)
            // tool0 lies within the rig's tool transform and the TCP of it (a rig may end
            // at either).
            + rig.tool.translation.length()
            + cell.tool.as_ref().map_or(0.0, |tool| tool.tcp.translation.length());
        let levers = (0..rig.dof())
            .map(|j| {
                let joint = &rig.joints[j];
                if joint.kind == JointKind::Prismatic {
                    return joint.axis.length();
                }
                // Every link after joint j, at its longest (prismatic strokes at their limits).
                let links: f64 = rig.joints[j + 1..]
                    .iter()
                    .map(|link| {
                        let stroke = match link.kind {
                            JointKind::Prismatic => {
                                link.limits.lower.abs().max(link.limits.upper.abs())
                                    * link.axis.length()
                            }
                            JointKind::Revolute => 0.0,
                        };
                        link.origin.translation.length() + stroke
                    })
                    .sum();
                links + body_radius(j + 1).max(tool_radius)
            })
            .collect();
        Reach { levers }
    }

    /// At least how far (m) any point of any body moves from positions `a` to `b`.
    pub fn between(&self, a: &[f64], b: &[f64]) -> f64 {
        self.levers
            .iter()
            .zip(a.iter().zip(b))
            .map(|(lever, (x, y))| lever * (y - x).abs())
            .sum()
    }
}

/// One pair's smallest clearance so far, and the cycle it was measured at.
#[derive(Debug, Clone, Copy)]
struct PairMinimum {
    a: BodyId,
    b: BodyId,
    distance_m: f64,
    cycle: u64,
}

/// A collision episode: the pair, its first and last cycle in contact (open while `end` is
/// `None`), and its deepest penetration (m, positive).
#[derive(Debug, Clone, Copy)]
struct RawEpisode {
    a: BodyId,
    b: BodyId,
    start: u64,
    end: Option<u64>,
    depth_m: f64,
}

/// What the status and the live view read while the twin runs: copied out of the cycle
/// when nobody holds it (never waited for).
#[derive(Debug, Clone, Copy, Default)]
pub struct ContactSnapshot {
    pub cycles: u64,
    pub episodes: u64,
    pub in_contact: bool,
    /// The smallest clearance so far within the cutoff: pair, metres, cycle.
    pub min: Option<(BodyId, BodyId, f64, u64)>,
}

/// What the twin must do after a cycle's measurement.
#[derive(Debug, Clone, PartialEq)]
pub struct NewContact {
    /// The Fault notice's words: the two bodies and the depth.
    pub text: String,
}

pub struct ContactWatch {
    model: Arc<CollisionModel>,
    scratch: Scratch,
    reach: Reach,
    period_s: f64,
    cutoff_m: f64,
    found: Vec<Clearance>,
    minima: Vec<PairMinimum>,
    /// Episodes in contact now (open), then closed ones up to [`KEPT_EPISODES`].
    open: Vec<RawEpisode>,
    closed: Vec<RawEpisode>,
    episodes: u64,
    cycle: u64,
    measured: u64,
    /// The positions of the last measured cycle, and how far bodies may move from them
    /// before the next cycle must be measured.
    anchor: Vec<f64>,
    slack_m: f64,
    started: bool,
    shared: Arc<Mutex<ContactSnapshot>>,
}

impl ContactWatch {
    /// A watch of `model` (built from `rig` in `cell`) for a twin of cycle `period_s`.
    pub fn new(model: Arc<CollisionModel>, rig: &Rig, cell: &Cell, period_s: f64) -> Self {
        let pairs = model.checked_pairs().len();
        let cutoff_m = REPORT_CUTOFF_M.max(2.0 * model.margin());
        ContactWatch {
            scratch: model.scratch(),
            reach: Reach::new(rig, cell),
            period_s,
            cutoff_m,
            found: Vec::with_capacity(pairs),
            minima: Vec::with_capacity(pairs),
            open: Vec::with_capacity(pairs),
            closed: Vec::with_capacity(KEPT_EPISODES),
            episodes: 0,
            cycle: 0,
            measured: 0,
            anchor: Vec::with_capacity(rig.dof()),
            slack_m: 0.0,
            started: false,
            shared: Arc::new(Mutex::new(ContactSnapshot::default())),
            model,
        }
    }

    pub fn model(&self) -> &Arc<CollisionModel> {
        &self.model
    }

    /// The live snapshot, for readers outside the cycle.
    pub fn shared(&self) -> Arc<Mutex<ContactSnapshot>> {
        self.shared.clone()
    }

    /// One cycle's actual positions. A contact that began at a cycle measured after the
    /// first (the arm moved into it) is returned: the twin stops the arm. A contact there
    /// from the first cycle is an episode, not an impact.
    pub fn observe(&mut self, actual: &[f64]) -> Option<NewContact> {
        self.cycle += 1;
        let moved = if self.started {
            2.0 * self.reach.between(&self.anchor, actual)
        } else {
            f64::INFINITY
        };
        if moved + BOUND_ROUNDING_M < self.slack_m.max(RESOLUTION_M) {
            return None;
        }
        let first = !self.started;
        self.started = true;
        self.anchor.clear();
        self.anchor.extend_from_slice(actual);
        self.measure(actual, first)
    }

    fn measure(&mut self, actual: &[f64], first: bool) -> Option<NewContact> {
        self.measured += 1;
        let lookahead = self.cutoff_m + LOOKAHEAD_M;
        self.model
            .pairs_within(actual, lookahead, &mut self.scratch, &mut self.found);
        let mut slack = LOOKAHEAD_M;
        let mut impact = None;
        for index in 0..self.found.len() {
            let c = self.found[index];
            let least = self.record_minimum(c);
            slack = slack.min(match c.distance_m {
                d if d >= self.cutoff_m => d - self.cutoff_m,
                d if d > 0.0 => d - least,
                d => (d - least).min(-d),
            });
            if c.distance_m <= 0.0 && self.touch(c) && !first && impact.is_none() {
                impact = Some(self.contact_text(c));
            }
        }
        self.close_episodes();
        self.slack_m = slack.max(0.0);
        self.publish();
        impact.map(|text| NewContact { text })
    }

    /// Keeps `c` as its pair's minimum when it is one (within the cutoff); the pair's
    /// minimum after it, or the cutoff for a pair beyond it.
    fn record_minimum(&mut self, c: Clearance) -> f64 {
        if c.distance_m >= self.cutoff_m {
            return self.cutoff_m;
        }
        let cycle = self.cycle;
        match self.minima.iter_mut().find(|m| (m.a, m.b) == (c.a, c.b)) {
            Some(m) => {
                if c.distance_m < m.distance_m {
                    m.distance_m = c.distance_m;
                    m.cycle = cycle;
                }
                m.distance_m
            }
            None => {
                if self.minima.len() < self.minima.capacity() {
                    self.minima.push(PairMinimum {
                        a: c.a,
                        b: c.b,
                        distance_m: c.distance_m,
                        cycle,
                    });
                }
                c.distance_m
            }
        }
    }

    /// A pair in contact this cycle: deepens its open episode, or opens one (true).
    fn touch(&mut self, c: Clearance) -> bool {
        let cycle = self.cycle;
        if let Some(open) = self.open.iter_mut().find(|e| (e.a, e.b) == (c.a, c.b)) {
            open.end = Some(cycle);
            open.depth_m = open.depth_m.max(-c.distance_m);
            return false;
        }
        self.episodes += 1;
        if self.open.len() < self.open.capacity() {
            self.open.push(RawEpisode {
                a: c.a,
                b: c.b,
                start: cycle,
                end: Some(cycle),
                depth_m: -c.distance_m,
            });
        }
        true
    }

    /// Episodes whose pair was not in contact this cycle end at their last contact cycle.
    fn close_episodes(&mut self) {
        let cycle = self.cycle;
        let mut i = 0;
        while i < self.open.len() {
            if self.open[i].end == Some(cycle) {
                i += 1;
                continue;
            }
            // Skipped cycles could not have left the contact: it lasted until the last one.
            let mut done = self.open.swap_remove(i);
            done.end = Some(cycle - 1);
            if self.closed.len() < self.closed.capacity() {
                self.closed.push(done);
            }
        }
    }

    fn contact_text(&self, c: Clearance) -> String {
        format!(
            "collision: {} and {} touch, {:.4} m deep",
            self.model.body_name(c.a),
            self.model.body_name(c.b),
            -c.distance_m
        )
    }

    fn publish(&self) {
        // Never waits: a reader holding it gets the next measured cycle's.
        if let Ok(mut shared) = self.shared.try_lock() {
            *shared = self.snapshot();
        }
    }

    fn snapshot(&self) -> ContactSnapshot {
        ContactSnapshot {
            cycles: self.cycle,
            episodes: self.episodes,
            in_contact: !self.open.is_empty(),
            min: self
                .minima
                .iter()
                .min_by(|x, y| x.distance_m.total_cmp(&y.distance_m))
                .map(|m| (m.a, m.b, m.distance_m, m.cycle)),
        }
    }

    /// The report of everything measured since the last call (or the start), times in
    /// seconds from then; measuring starts again from now (episodes in contact now go on
    /// as new ones, without an impact).
    pub fn take_report(&mut self) -> ContactReport {
        let report = self.report();
        self.minima.clear();
        self.open.clear();
        self.closed.clear();
        self.episodes = 0;
        self.cycle = 0;
        self.measured = 0;
        self.started = false;
        self.slack_m = 0.0;
        if let Ok(mut shared) = self.shared.lock() {
            *shared = ContactSnapshot::default();
        } else {
            self.shared.clear_poison();
        }
        report
    }

    fn report(&self) -> ContactReport {
        let t = |cycle: u64| cycle as f64 * self.period_s;
        let name = |id: BodyId| self.model.body_name(id).to_string();
        let mut pairs: Vec<PairClearance> = self
            .minima
            .iter()
            .map(|m| PairClearance {
                a: name(m.a),
                b: name(m.b),
                min_clearance_m: m.distance_m,
                at_s: t(m.cycle),
                status: self.model.status(m.distance_m).to_string(),
            })
            .collect();
        pairs.sort_by(|x, y| x.min_clearance_m.total_cmp(&y.min_clearance_m));
        let mut episodes: Vec<Episode> = self
            .closed
            .iter()
            .map(|e| (e, false))
            .chain(self.open.iter().map(|e| (e, true)))
            .map(|(e, open)| Episode {
                a: name(e.a),
                b: name(e.b),
                start_s: t(e.start),
                end_s: (!open).then(|| t(e.end.unwrap_or(e.start))),
                depth_m: e.depth_m,
            })
            .collect();
        episodes.sort_by(|x, y| x.start_s.total_cmp(&y.start_s));
        ContactReport {
            checked_pairs: self.model.checked_pairs().len(),
            margin_m: self.model.margin(),
            cutoff_m: self.cutoff_m,
            min_clearance: pairs.first().cloned(),
            collisions: self.episodes,
            episodes_left_out: self.episodes.saturating_sub(episodes.len() as u64),
            episodes,
            pairs,
            cycles: self.cycle,
            measured_cycles: self.measured,
        }
    }

    /// The live summary for a status: the snapshot with body names.
    pub fn describe(
        model: &CollisionModel,
        snapshot: &ContactSnapshot,
        period_s: f64,
    ) -> ContactStatus {
        ContactStatus {
            cycles: snapshot.cycles,
            collisions: snapshot.episodes,
            in_contact: snapshot.in_contact,
            min_clearance: snapshot.min.map(|(a, b, d, cycle)| PairClearance {
                a: model.body_name(a).to_string(),
                b: model.body_name(b).to_string(),
                min_clearance_m: d,
                at_s: cycle as f64 * period_s,
                status: model.status(d).to_string(),
            }),
        }
    }
}

/// One pair's smallest clearance: negative is a penetration's depth.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PairClearance {
    pub a: String,
    pub b: String,
    pub min_clearance_m: f64,
    /// Time of the minimum (s, from the start of the measurement: the job's start).
    pub at_s: f64,
    /// `free`, `within_margin` or `collision`.
    pub status: String,
}

/// A collision episode: `end_s` is `null` while the pair is still in contact.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Episode {
    pub a: String,
    pub b: String,
    pub start_s: f64,
    pub end_s: Option<f64>,
    pub depth_m: f64,
}

/// What the twin measured of the cell over a job (`contacts` in the run report).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ContactReport {
    /// Pairs of bodies the model checks.
    pub checked_pairs: usize,
    pub margin_m: f64,
    /// Pairs that came closer than this are in `pairs`; the others stayed beyond it.
    pub cutoff_m: f64,
    /// The closest pair over the job, when it came within the cutoff.
    pub min_clearance: Option<PairClearance>,
    /// Every pair that came within the cutoff, closest first.
    pub pairs: Vec<PairClearance>,
    /// Collision episodes (a pair in contact over consecutive cycles counts once).
    pub collisions: u64,
    /// The first [`KEPT_EPISODES`] episodes, by start time.
    pub episodes: Vec<Episode>,
    pub episodes_left_out: u64,
    /// Cycles watched, and those measured (the others provably changed nothing).
    pub cycles: u64,
    pub measured_cycles: u64,
}

/// The live part of a cell's status: `contacts` of `GET /api/status`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ContactStatus {
    pub cycles: u64,
    pub collisions: u64,
    pub in_contact: bool,
    pub min_clearance: Option<PairClearance>,
}

impl ContactReport {
    /// Locks a shared snapshot for a reader (never poisoned for long: the cycle only
    /// copies into it).
    pub fn read(shared: &Mutex<ContactSnapshot>) -> ContactSnapshot {
        *shared.lock().unwrap_or_else(PoisonError::into_inner)
    }
}
