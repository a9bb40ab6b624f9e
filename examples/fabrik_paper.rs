//! The FABRIK paper's chain experiment (Aristidou & Lasenby 2011, "FABRIK: A fast, iterative
//! solver for the Inverse Kinematics problem", Graphical Models 73): a chain of 10 ball
//! joints (3 DoF each), no limits, unit segments, random reachable targets; mean iterations
//! of FABRIK and CCD to reach the target. The paper reports 15.46 (FABRIK) and 26.31 (CCD).
//!
//! ```text
//! cargo run --release --example fabrik_paper            # 1,000 targets
//! cargo run --release --example fabrik_paper -- 10000   # more
//! ```
//!
//! Our setup, as far as the paper leaves it open:
//! - tolerance 1e-2 (in segment lengths) on the tip-target distance: the paper's own value was
//!   not found, so this is an assumption;
//! - every target starts from the same straight chain along +z (root at the origin), not
//!   from the previous answer;
//! - targets uniform in the ball of radius 10 (the chain's reach) around the root: all are
//!   reachable, since a chain of equal segments folds down to reach 0;
//! - at most 1,000 iterations; a solve that hits the cap counts with 1,000.
//!
//! `benches/ik.rs` includes this file as a module and reuses the experiment.

use glam::DVec3;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rigbridge::ik::chain::{ChainOutcome, ChainSettings, Unconstrained, ccd, fabrik};

pub const JOINTS: usize = 10;
pub const TOLERANCE: f64 = 1e-2;
pub const MAX_ITERATIONS: u32 = 1000;
pub const PAPER_FABRIK: f64 = 15.46;
pub const PAPER_CCD: f64 = 26.31;
pub const SEED: u64 = 2011;

pub fn settings() -> ChainSettings {
    ChainSettings {
        tolerance: TOLERANCE,
        max_iterations: MAX_ITERATIONS,
        min_improvement: 0.0,
    }
}

/// The starting chain: root at the origin, straight along +z; and the segment lengths.
pub fn straight_chain() -> ([DVec3; JOINTS + 1], [f64; JOINTS]) {
    (
        std::array::from_fn(|i| DVec3::new(0.0, 0.0, i as f64)),
        [1.0; JOINTS],
    )
}

/// `count` targets uniform in the ball of the chain's reach (rejection sampling).
pub fn targets(count: usize, seed: u64) -> Vec<DVec3> {
    let reach = JOINTS as f64;
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut targets = Vec::with_capacity(count);
    while targets.len() < count {
        let p = DVec3::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        );
        if p.length_squared() <= 1.0 {
            targets.push(p * reach);
        }
    }
    targets
}

pub fn solve_fabrik(target: DVec3) -> ChainOutcome {
    let (mut points, lengths) = straight_chain();
    fabrik(
        &mut points,
        &lengths,
        target,
        settings(),
        &Unconstrained,
        DVec3::Z,
    )
}

pub fn solve_ccd(target: DVec3) -> ChainOutcome {
    let (mut points, _) = straight_chain();
    ccd(&mut points, target, settings())
}

#[derive(Debug, Clone, Copy, Default)]
pub struct Tally {
    pub mean_iterations: f64,
    pub median_iterations: f64,
    pub converged: usize,
    pub count: usize,
}

pub fn tally(targets: &[DVec3], solve: impl Fn(DVec3) -> ChainOutcome) -> Tally {
    let outcomes: Vec<ChainOutcome> = targets.iter().map(|t| solve(*t)).collect();
    let mut iterations: Vec<u32> = outcomes.iter().map(|o| o.iterations).collect();
    iterations.sort_unstable();
    let middle = iterations.len() / 2;
    Tally {
        median_iterations: if iterations.len() % 2 == 1 {
            f64::from(iterations[middle])
        } else {
            (f64::from(iterations[middle - 1]) + f64::from(iterations[middle])) / 2.0
        },
        mean_iterations: outcomes
            .iter()
            .map(|o| f64::from(o.iterations))
            .sum::<f64>()
            / outcomes.len() as f64,
        converged: outcomes.iter().filter(|o| o.converged).count(),
        count: outcomes.len(),
    }
}

/// The comparison table, one line per solver.
pub fn table(count: usize) -> String {
    let targets = targets(count, SEED);
    let fabrik = tally(&targets, solve_fabrik);
    let ccd = tally(&targets, solve_ccd);
    let mut text = format!(
        "FABRIK paper experiment: {JOINTS} ball joints, unit segments, {count} random reachable \
         targets (seed {SEED}), tolerance {TOLERANCE:e} (assumed: paper value not found), \
         straight start, cap {MAX_ITERATIONS}\n\
         {:<8} {:>16} {:>18} {:>14} {:>12}\n",
        "solver", "mean iterations", "median iterations", "paper (2011)", "converged"
    );
    for (name, t, paper) in [("FABRIK", fabrik, PAPER_FABRIK), ("CCD", ccd, PAPER_CCD)] {
        text += &format!(
            "{name:<8} {:>16.2} {:>18.1} {paper:>14.2} {:>12}\n",
            t.mean_iterations,
            t.median_iterations,
            format!("{}/{}", t.converged, t.count)
        );
    }
    text
}

#[allow(dead_code)]
fn main() {
    let count = std::env::args()
        .nth(1)
        .map(|a| a.parse().expect("target count"))
        .unwrap_or(1000);
    print!("{}", table(count));
}
