//! RRT-Connect (Kuffner and LaValle 2000, "RRT-Connect: An efficient approach to
//! single-query path planning", ICRA): two trees of clear configurations, one rooted at
//! the start and one at the goal. Each round draws a random configuration within the joint
//! limits, grows one tree a step towards it (EXTEND), then grows the other tree straight
//! at the new configuration for as long as it stays clear (CONNECT); the trees swap roles
//! every round. Every new edge is proven clear continuously by the [`Checker`].
//!
//! Nearest neighbours are found by a linear scan: the trees stay at a few thousand
//! configurations at most within the budget, and one continuous edge check costs more
//! than scanning them all, so a k-d tree would not pay for itself. Owns the trees and the
//! sampling; the checks are the checker's.

use super::checker::Checker;
use super::{FreePlanOptions, distance, lerp};
use crate::rig::Rig;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// The sampler: ChaCha8, whose output for a seed is fixed across platforms and versions
/// of the crate (rand_chacha's value-stability promise), so a seed names one path.
pub(super) type Sampler = ChaCha8Rng;

pub(super) fn rng(seed: u64) -> Sampler {
    ChaCha8Rng::seed_from_u64(seed)
}

/// What a search found: the waypoints from start to goal (every stretch checked clear), or
/// none when the budget ran out; and what it spent.
pub(super) struct Found {
    pub path: Option<Vec<Vec<f64>>>,
    /// Random configurations drawn.
    pub samples: usize,
    /// Configurations in both trees.
    pub nodes: usize,
}

/// A tree of clear configurations, each but the root joined to its parent by a clear edge.
struct Tree {
    dof: usize,
    /// Row-major: configuration `i` is `positions[i * dof..(i + 1) * dof]`.
    positions: Vec<f64>,
    parents: Vec<usize>,
}

/// How an EXTEND ended: at the target, a step towards it, or blocked.
enum Extend {
    Reached(usize),
    Advanced(usize),
    Trapped,
}

impl Tree {
    fn rooted_at(root: &[f64]) -> Self {
        Self {
            dof: root.len(),
            positions: root.to_vec(),
            parents: vec![0],
        }
    }

    fn len(&self) -> usize {
        self.parents.len()
    }

    fn at(&self, index: usize) -> &[f64] {
        &self.positions[index * self.dof..(index + 1) * self.dof]
    }

    fn add(&mut self, q: &[f64], parent: usize) -> usize {
        self.positions.extend_from_slice(q);
        self.parents.push(parent);
        self.len() - 1
    }

    /// The configuration nearest `q` (joint-space Euclidean; the first on a tie).
    fn nearest(&self, q: &[f64]) -> usize {
        let mut best = (f64::INFINITY, 0);
        for index in 0..self.len() {
            let d: f64 = self
                .at(index)
                .iter()
                .zip(q)
                .map(|(a, b)| (a - b) * (a - b))
                .sum();
            if d < best.0 {
                best = (d, index);
            }
        }
        best.1
    }

    /// Configurations from `index` back to the root.
    fn branch(&self, mut index: usize) -> Vec<Vec<f64>> {
        let mut branch = vec![self.at(index).to_vec()];
        while index != 0 {
            index = self.parents[index];
            branch.push(self.at(index).to_vec());
        }
        branch
    }

    /// One step from `from` towards `target`, at most `step` long, kept when its edge is
    /// clear.
    fn extend_from(&mut self, from: usize, target: &[f64], step: f64, checker: &Checker) -> Extend {
        let near = self.at(from).to_vec();
        let gap = distance(&near, target);
        let (new, reaches) = if gap <= step {
            (target.to_vec(), true)
        } else {
            (lerp(&near, target, step / gap), false)
        };
        if !checker.edge(&near, &new) {
            return Extend::Trapped;
        }
        let index = self.add(&new, from);
        if reaches {
            Extend::Reached(index)
        } else {
            Extend::Advanced(index)
        }
    }

    fn extend(&mut self, target: &[f64], step: f64, checker: &Checker) -> Extend {
        self.extend_from(self.nearest(target), target, step, checker)
    }

    /// Steps towards `target` until it is reached or blocked. After each step the new
    /// configuration is the tree's nearest to `target` (it is a step closer than the one
    /// it grew from, which was the nearest), so the next step grows from it.
    fn connect(&mut self, target: &[f64], step: f64, checker: &Checker) -> Extend {
        let mut outcome = self.extend(target, step, checker);
        while let Extend::Advanced(index) = outcome {
            outcome = self.extend_from(index, target, step, checker);
        }
        outcome
    }
}

/// RRT-Connect from `start` to `goal` (both clear), drawing at most `options.max_samples`
/// configurations uniformly within `rig`'s joint limits from `rng`.
pub(super) fn connect(
    checker: &Checker,
    rig: &Rig,
    start: &[f64],
    goal: &[f64],
    options: &FreePlanOptions,
    rng: &mut Sampler,
) -> Found {
    let mut trees = [Tree::rooted_at(start), Tree::rooted_at(goal)];
    // Which of `trees` grows towards the sample this round; the other connects.
    let mut growing = 0;
    let mut sample = vec![0.0; start.len()];
    for drawn in 1..=options.max_samples {
        for (value, joint) in sample.iter_mut().zip(&rig.joints) {
            *value = rng.random_range(joint.limits.lower..=joint.limits.upper);
        }
        let [first, second] = &mut trees;
        let (grow, other) = if growing == 0 {
            (first, second)
        } else {
            (second, first)
        };
        let new = match grow.extend(&sample, options.step, checker) {
            Extend::Reached(index) | Extend::Advanced(index) => index,
            Extend::Trapped => {
                growing = 1 - growing;
                continue;
            }
        };
        let q_new = grow.at(new).to_vec();
        if let Extend::Reached(joined) = other.connect(&q_new, options.step, checker) {
            let (from_start, to_goal) = if growing == 0 {
                (trees[0].branch(new), trees[1].branch(joined))
            } else {
                (trees[0].branch(joined), trees[1].branch(new))
            };
            return Found {
                path: Some(join(from_start, to_goal)),
                samples: drawn,
                nodes: trees[0].len() + trees[1].len(),
            };
        }
        growing = 1 - growing;
    }
    Found {
        path: None,
        samples: options.max_samples,
        nodes: trees[0].len() + trees[1].len(),
    }
}

/// The start tree's branch (meeting point back to the start) reversed, then the goal
/// tree's (meeting point to the goal) without its first configuration, the meeting point
/// both hold.
fn join(mut from_start: Vec<Vec<f64>>, to_goal: Vec<Vec<f64>>) -> Vec<Vec<f64>> {
    from_start.reverse();
    from_start.extend(to_goal.into_iter().skip(1));
    from_start
}
