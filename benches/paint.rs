//! Planning a painting job (docs/painting.md): a 32-wall room (about 1,500 strokes; the
//! figure to reach is <= 2 s) and a 3-walled one (the sharpest corners, where the station
//! and attitude search does the most work). Each iteration plans the whole room from the
//! start position: strokes, stations, IK, every trajectory and the plan's collision check.
//!
//! `cargo bench --bench paint -- --measurement-time 20`

use criterion::{Criterion, criterion_group, criterion_main};
use rigbridge::apps::paint::{load_paint_settings, plan_room};
use rigbridge::trajectory::PlanSettings;
use std::path::Path;

fn planning(c: &mut Criterion) {
    let settings =
        load_paint_settings(&Path::new(env!("CARGO_MANIFEST_DIR")).join("config/paint.toml"))
            .expect("config/paint.toml loads");
    let mut start = vec![0.0; 10];
    start[8] = 30f64.to_radians();
    let plan = PlanSettings {
        period: std::time::Duration::from_millis(10),
        ..PlanSettings::default()
    };
    let mut group = c.benchmark_group("paint_plan");
    group.sample_size(10);
    for walls in [32u32, 3] {
        group.bench_function(format!("{walls}_walls"), |b| {
            b.iter(|| plan_room(&settings, walls, 0, &start, &plan).expect("room plans"))
        });
    }
    group.finish();
}

criterion_group!(benches, planning);
criterion_main!(benches);
