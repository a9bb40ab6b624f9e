//! The continuous check: a path between samples (joint-space linear) is proven clear, not
//! only its samples. Between two configurations no point of any body moves farther than
//! the sum over joints of reach times step ([`CollisionModel`]'s per-joint reach), so the
//! clearance of a pair changes by at most twice that (both bodies may move). A stretch whose
//! end clearances leave room for that change is clear; one that does not is bisected, and
//! a sample the bound already vouches for is not measured at all. Owns only this proof; the
//! distances come from the model.

use super::model::{Clearance, CollisionModel, Scratch, Status};

/// How far below the margin the clearance between measured configurations may be proven
/// to stay, at most: 1 mm, well under any envelope's own error, and the resolution that
/// keeps the bisection finite (it stops when a stretch's motion bound is within twice this).
const PROOF_SLACK_M: f64 = 0.001;

/// A path checked clear: its smallest measured clearance and when.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PathClearance {
    /// The smallest clearance among the configurations measured (samples the motion bound
    /// could not vouch for, and bisection points); every other point of the path is proven
    /// at least the margin at samples and the margin less 1 mm between them.
    pub min: Clearance,
    pub at_t: f64,
}

/// The first configuration of a path found closer than the margin.
#[derive(Debug, Clone, PartialEq)]
pub struct PathCollision {
    /// The sample at or just before `t` (the start of the stretch it lies in).
    pub index: usize,
    pub t: f64,
    pub positions: Vec<f64>,
    pub clearance: Clearance,
    pub status: Status,
}

/// One stretch being proven: its end configurations and the bound on a pair's change of
/// clearance over the whole stretch.
struct Stretch<'q> {
    from: &'q [f64],
    to: &'q [f64],
    change: f64,
}

impl CollisionModel {
    /// The floor the clearance is proven to stay above between measured configurations.
    fn proof_floor(&self) -> f64 {
        self.margin - PROOF_SLACK_M.min(self.margin / 2.0)
    }

    /// A bound on how much any pair's clearance changes between `from` and `to`.
    fn clearance_change(&self, from: &[f64], to: &[f64]) -> f64 {
        let travel: f64 = self
            .reach
            .iter()
            .zip(from.iter().zip(to))
            .map(|(reach, (a, b))| reach * (b - a).abs())
            .sum();
        2.0 * travel
    }

    /// Continuous check of a sampled path (joint-space linear between samples). Ok with
    /// the smallest measured clearance, or the first configuration whose clearance is
    /// below the margin.
    ///
    /// # Panics
    /// When a sample does not hold one value per joint.
    pub fn check_path<Q: AsRef<[f64]>>(
        &self,
        samples: impl IntoIterator<Item = (f64, Q)>,
        scratch: &mut Scratch,
    ) -> Result<PathClearance, PathCollision> {
        let mut best = PathClearance {
            min: Clearance::NONE,
            at_t: 0.0,
        };
        let mut previous: Option<(f64, Q, f64)> = None;
        for (index, (t, sample)) in samples.into_iter().enumerate() {
            let q = sample.as_ref();
            let Some((t0, held, floor0)) = previous.take() else {
                let c = self.measure(q, t, &mut best, scratch);
                if c.distance_m < self.margin {
                    return Err(self.collision(index, t, q.to_vec(), c));
                }
                previous = Some((t, sample, c.distance_m));
                continue;
            };
            let q0 = held.as_ref();
            let change = self.clearance_change(q0, q);
            // The bound alone keeps this sample, and the way to it, above the margin.
            if floor0 - change >= self.margin {
                previous = Some((t, sample, floor0 - change));
                continue;
            }
            let c = self.measure(q, t, &mut best, scratch);
            let stretch = Stretch {
                from: q0,
                to: q,
                change,
            };
            let inside = self.bisect(&stretch, (0.0, floor0), (1.0, c.distance_m), scratch);
            if let Some((s, clearance, positions)) = inside {
                let at = t0 + s * (t - t0);
                best_of(&mut best, clearance, at);
                return Err(self.collision(index - 1, at, positions, clearance));
            }
            if c.distance_m < self.margin {
                return Err(self.collision(index, t, q.to_vec(), c));
            }
            previous = Some((t, sample, c.distance_m));
        }
        Ok(best)
    }

    /// Continuous check of one step (the streaming gate: previous target -> this target):
    /// Ok with the smaller end clearance, or the first clearance found below the margin.
    pub fn check_step(
        &self,
        from: &[f64],
        to: &[f64],
        scratch: &mut Scratch,
    ) -> Result<Clearance, Clearance> {
        let start = self.clearance(from, scratch);
        if start.distance_m < self.margin {
            return Err(start);
        }
        let end = self.clearance(to, scratch);
        let stretch = Stretch {
            from,
            to,
            change: self.clearance_change(from, to),
        };
        let ends = ((0.0, start.distance_m), (1.0, end.distance_m));
        if let Some((_, clearance, _)) = self.bisect(&stretch, ends.0, ends.1, scratch) {
            return Err(clearance);
        }
        if end.distance_m < self.margin {
            return Err(end);
        }
        Ok(if end.distance_m < start.distance_m {
            end
        } else {
            start
        })
    }

    /// Whether one step from `from`, already closer to something than the margin (but not
    /// touching it), moves away: the end clearance grows and no point between comes into
    /// contact (the lower bound along the step, from both ends' clearances and the change
    /// bound, stays above zero). What lets an arm that was left inside the margin (by a job
    /// that ended there, or a cell edited under it) be jogged out, where
    /// [`Self::check_step`] refuses every step that starts inside.
    pub fn step_leaves_margin(&self, from: &[f64], to: &[f64], scratch: &mut Scratch) -> bool {
        let start = self.clearance(from, scratch).distance_m;
        if start >= self.margin || start <= 0.0 {
            return false;
        }
        let end = self.clearance(to, scratch).distance_m;
        let lowest = (start + end - self.clearance_change(from, to)) / 2.0;
        end > start && lowest > 0.0
    }

    /// The first measured configuration strictly inside `(s0, s1)` of `stretch` whose
    /// clearance is below the margin, given lower bounds `c0`, `c1` on the clearance at
    /// the ends; `None` once every point is proven above [`Self::proof_floor`] (or, when an
    /// end itself is below the margin, once the stretch is too short to hold anything
    /// earlier: the caller reports that end).
    fn bisect(
        &self,
        stretch: &Stretch<'_>,
        (s0, c0): (f64, f64),
        (s1, c1): (f64, f64),
        scratch: &mut Scratch,
    ) -> Option<(f64, Clearance, Vec<f64>)> {
        let change = stretch.change * (s1 - s0);
        let floor = self.proof_floor();
        // Any point is reached from one end or the other within the change bound: the
        // lowest the clearance can be is where the two cones meet.
        if (c0 + c1 - change) / 2.0 >= floor || change <= 2.0 * (self.margin - floor) {
            return None;
        }
        let s = (s0 + s1) / 2.0;
        let mid: Vec<f64> = stretch
            .from
            .iter()
            .zip(stretch.to)
            .map(|(a, b)| a + s * (b - a))
            .collect();
        let c = self.clearance(&mid, scratch);
        if let Some(found) = self.bisect(stretch, (s0, c0), (s, c.distance_m), scratch) {
            return Some(found);
        }
        if c.distance_m < self.margin {
            return Some((s, c, mid));
        }
        self.bisect(stretch, (s, c.distance_m), (s1, c1), scratch)
    }

    fn measure(
        &self,
        q: &[f64],
        t: f64,
        best: &mut PathClearance,
        scratch: &mut Scratch,
    ) -> Clearance {
        let c = self.clearance(q, scratch);
        best_of(best, c, t);
        c
    }

    fn collision(
        &self,
        index: usize,
        t: f64,
        positions: Vec<f64>,
        clearance: Clearance,
    ) -> PathCollision {
        PathCollision {
            index,
            t,
            positions,
            clearance,
            status: self.status(clearance.distance_m),
        }
    }
}

fn best_of(best: &mut PathClearance, c: Clearance, t: f64) {
    if c.distance_m < best.min.distance_m {
        *best = PathClearance { min: c, at_t: t };
    }
}
