//! The free planner's figure (issue 29): seeded random start and goal pairs in the demo
//! cell (config/pick-place.toml), each end drawn uniformly within the joint limits and
//! kept only when it is clear of the cell by its margin. Shared by tests/free_plan.rs and
//! benches/free_plan.rs, so both measure the same pairs.

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rigbridge::cell::CollisionModel;
use rigbridge::daemon::config::{RunSettings, load_run_settings};
use rigbridge::rig::Rig;
use std::path::PathBuf;

/// How many pairs the figure is measured over: the issue's.
pub const PAIRS: usize = 100;

/// The pairs' seed (the number): fixed, so every run measures the same pairs.
pub const PAIRS_SEED: u64 = 29;

/// The demo cell's run settings.
pub fn demo_settings() -> RunSettings {
    let file = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("config/pick-place.toml");
    load_run_settings(&file).expect("config/pick-place.toml loads")
}

/// A configuration drawn uniformly within `rig`'s limits until one is clear of `model`'s
/// cell by its margin.
pub fn clear_configuration(rig: &Rig, model: &CollisionModel, rng: &mut ChaCha8Rng) -> Vec<f64> {
    let mut scratch = model.scratch();
    loop {
        let q: Vec<f64> = rig
            .joints
            .iter()
            .map(|j| rng.random_range(j.limits.lower..=j.limits.upper))
            .collect();
        if model.clearance(&q, &mut scratch).distance_m >= model.margin() {
            return q;
        }
    }
}

/// A start and goal pair, both ends clear.
pub type Pair = (Vec<f64>, Vec<f64>);

/// [`PAIRS`] pairs, both ends clear (most of them, in this cell, joined by a clear direct
/// move).
pub fn pairs(rig: &Rig, model: &CollisionModel) -> Vec<Pair> {
    let mut rng = ChaCha8Rng::seed_from_u64(PAIRS_SEED);
    (0..PAIRS)
        .map(|_| {
            let start = clear_configuration(rig, model, &mut rng);
            let goal = clear_configuration(rig, model, &mut rng);
            (start, goal)
        })
        .collect()
}

/// Points measured along a direct move to find it blocked: a quick test that only keeps
/// pairs certainly blocked (a pair blocked only between them is left out, not misfiled);
/// proving the rest clear, which the search does not need, costs far more.
const DIRECT_POINTS: usize = 32;

/// `count` pairs, both ends clear and the direct move between them blocked (some point on
/// it closer than the margin): the pairs that need the search. Drawn as [`pairs`] are,
/// keeping only those.
pub fn blocked_pairs(rig: &Rig, model: &CollisionModel, count: usize) -> Vec<Pair> {
    let mut rng = ChaCha8Rng::seed_from_u64(PAIRS_SEED);
    let mut scratch = model.scratch();
    let mut kept = Vec::with_capacity(count);
    while kept.len() < count {
        let start = clear_configuration(rig, model, &mut rng);
        let goal = clear_configuration(rig, model, &mut rng);
        let blocked = (1..DIRECT_POINTS).any(|i| {
            let s = i as f64 / DIRECT_POINTS as f64;
            let q: Vec<f64> = start
                .iter()
                .zip(&goal)
                .map(|(a, b)| a + s * (b - a))
                .collect();
            model.clearance(&q, &mut scratch).distance_m < model.margin()
        });
        if blocked {
            kept.push((start, goal));
        }
    }
    kept
}

/// True when the straight joint move from `start` to `goal` is proven clear.
pub fn direct_is_clear(model: &CollisionModel, start: &[f64], goal: &[f64]) -> bool {
    model.check_step(start, goal, &mut model.scratch()).is_ok()
}
