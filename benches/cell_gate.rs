//! The streaming gate's collision check, per cycle (issue 27): what `stream::CellGate`
//! adds to a cycle for a target that was not checked as part of a whole trajectory, the
//! continuous check of the step from the previous target (`CollisionModel::check_step`).
//! The targets are the shipped demo's (the star on its wall, 250 Hz) in its own cell, each
//! step checked in turn, so each reported time is per cycle (a mean over the steps a sample
//! covered). Before timing, prints (stderr) the per-step p50/p99/max measured with
//! `Instant` over the whole job and their share of the 4 ms cycle.
//!
//! ```text
//! cargo bench --bench cell_gate
//! ```

use criterion::{Criterion, criterion_group, criterion_main};
use rigbridge::daemon::collision_model;
use rigbridge::daemon::config::load_run_settings;
use rigbridge::job::PlanContext;
use rigbridge::protocol::AxisValues;
use rigbridge::stream::CellGate;
use std::hint::black_box;
use std::path::Path;
use std::time::Instant;

fn main_bench(c: &mut Criterion) {
    let config = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/rigbridge.toml");
    let settings = load_run_settings(&config).expect("the shipped demo settings");
    let trajectory = settings
        .config
        .job
        .plan(&PlanContext {
            rig: &settings.rig,
            app_rig: None,
            start: &settings.initial(),
            settings: &rigbridge::daemon::plan_settings(&settings),
            model: Some(&settings.collision),
        })
        .expect("the demo plans");
    let model = collision_model(&settings);
    let targets: Vec<AxisValues> = (0..trajectory.len())
        .map(|k| AxisValues::from_slice(&trajectory.position(k)).expect("six axes"))
        .collect();
    let mut gate = CellGate::new(&model);
    let mut refused = 0;
    let mut times: Vec<f64> = (1..targets.len())
        .map(|k| {
            let start = Instant::now();
            let verdict = gate.check(Some(&targets[k - 1]), &targets[k]);
            let elapsed = start.elapsed().as_secs_f64() * 1e6;
            refused += usize::from(verdict.is_err());
            elapsed
        })
        .collect();
    // Timed whatever the verdict: a refused step costs what a passed one does, or less.
    eprintln!("cell gate: {refused} of the demo's steps within the margin");
    times.sort_by(f64::total_cmp);
    let at = |q: f64| times[((times.len() - 1) as f64 * q) as usize];
    let cycle_us = settings.period().as_secs_f64() * 1e6;
    eprintln!(
        "cell gate, {} steps of the demo: p50 {:.2} us, p99 {:.2} us, max {:.2} us per cycle \
         ({:.2} % / {:.2} % of the {cycle_us:.0} us cycle at p50 / p99)",
        times.len(),
        at(0.5),
        at(0.99),
        at(1.0),
        100.0 * at(0.5) / cycle_us,
        100.0 * at(0.99) / cycle_us,
    );
    let mut k = 0;
    c.bench_function("cell_gate_step", |b| {
        b.iter(|| {
            k = k % (targets.len() - 1) + 1;
            black_box(gate.check(Some(&targets[k - 1]), black_box(&targets[k])))
        })
    });
}

criterion_group!(benches, main_bench);
criterion_main!(benches);
