//! The free planner (issue 29, `trajectory::free::plan_free`) over the figure's pairs in the
//! demo cell (config/pick-place.toml): 100 seeded random pairs of clear configurations
//! whose direct move is blocked, and the 100 unfiltered random pairs of clear
//! configurations (most joined by a clear direct move). Before timing, prints (stderr)
//! per set: how many were planned, the planning time's p50, p95 and max measured with
//! `Instant` over one pass, and the median path length over the straight joint move. Then
//! criterion times one plan of a blocked pair.
//!
//! ```text
//! cargo bench --bench free_plan
//! ```

// The tests use all of it; the bench not `direct_is_clear`.
#[allow(dead_code)]
#[path = "../tests/common/free_pairs.rs"]
mod free_pairs;

use criterion::{Criterion, criterion_group, criterion_main};
use free_pairs::{PAIRS, Pair, blocked_pairs, demo_settings, pairs};
use rigbridge::cell::CollisionModel;
use rigbridge::rig::Rig;
use rigbridge::trajectory::free::{FreePlanOptions, path_length, plan_free};
use std::hint::black_box;
use std::time::Instant;

/// Plans each pair once: how many were planned, the sorted times (ms), and each planned
/// path's length over the straight move's.
fn one_pass(
    model: &CollisionModel,
    rig: &Rig,
    pairs: &[Pair],
    options: &FreePlanOptions,
) -> (usize, Vec<f64>, Vec<f64>) {
    let mut planned = 0;
    let mut times = Vec::with_capacity(pairs.len());
    let mut ratios = Vec::new();
    for (start, goal) in pairs {
        let began = Instant::now();
        let path = plan_free(model, rig, start, goal, options);
        times.push(began.elapsed().as_secs_f64() * 1e3);
        if let Ok(path) = path {
            planned += 1;
            ratios.push(path_length(&path) / path_length(&[start.clone(), goal.clone()]));
        }
    }
    times.sort_by(f64::total_cmp);
    ratios.sort_by(f64::total_cmp);
    (planned, times, ratios)
}

fn report(what: &str, count: usize, (planned, times, ratios): &(usize, Vec<f64>, Vec<f64>)) {
    let at = |q: f64| times[((times.len() - 1) as f64 * q).round() as usize];
    let median = ratios.get(ratios.len() / 2).copied().unwrap_or(f64::NAN);
    eprintln!(
        "free plan, {what}: {planned} of {count} planned ({:.0} %); planning p50 {:.1} ms, \
         p95 {:.1} ms, max {:.1} ms; median length over the straight move {median:.3}",
        100.0 * *planned as f64 / count as f64,
        at(0.5),
        at(0.95),
        at(1.0)
    );
}

fn main_bench(c: &mut Criterion) {
    let settings = demo_settings();
    let (rig, model) = (&settings.tcp_rig, settings.collision.as_ref());
    let options = rigbridge::daemon::plan_settings(&settings).free;
    let blocked = blocked_pairs(rig, model, PAIRS);
    report(
        "blocked pairs",
        blocked.len(),
        &one_pass(model, rig, &blocked, &options),
    );
    let random = pairs(rig, model);
    report(
        "random pairs",
        random.len(),
        &one_pass(model, rig, &random, &options),
    );
    let (start, goal) = &blocked[0];
    c.bench_function("free_plan/first_blocked_pair", |b| {
        b.iter(|| black_box(plan_free(model, rig, start, goal, &options)))
    });
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(20);
    targets = main_bench
}
criterion_main!(benches);
