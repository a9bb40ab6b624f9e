//! The full painting sweep: every room of 3..=32 walls with several seeds, each planned and
//! painted against the in-process twin under the virtual clock; prints one line per room
//! and the worst case. `cargo run --release --example paint_sweep -- [FIRST_N LAST_N SEEDS]`

use rigbridge::apps::paint::load_paint_settings;
use rigbridge::apps::paint::run::run_paint;
use rigbridge::clock::VirtualClock;
use rigbridge::daemon::config::load_run_settings;
use rigbridge::stream::StreamControl;
use std::path::Path;

fn main() -> anyhow::Result<()> {
    let args: Vec<u64> = std::env::args()
        .skip(1)
        .map(|a| a.parse())
        .collect::<Result<_, _>>()?;
    let (first, last, seeds) = match args.as_slice() {
        [f, l, s] => (*f as u32, *l as u32, *s),
        [] => (3, 32, 3),
        _ => anyhow::bail!("usage: paint_sweep [FIRST_N LAST_N SEEDS]"),
    };
    let settings = load_run_settings(Path::new("config/paint-run.toml"))?;
    let paint = load_paint_settings(Path::new("config/paint.toml"))?;
    let mut worst: Option<(f64, u32, u64)> = None;
    let mut failures = 0;
    println!(
        "walls seed coverage_% openings_m2 collisions limit_violations unreachable strokes duration_s plan_s wall_s"
    );
    for walls in first..=last {
        for seed in 0..seeds {
            let started = std::time::Instant::now();
            let clock = VirtualClock::new();
            let control = StreamControl::default();
            let mut plan_s = 0.0;
            let run = run_paint(
                &settings,
                &paint,
                walls,
                seed,
                &clock,
                None,
                &control,
                &mut |_| {
                    plan_s = started.elapsed().as_secs_f64();
                },
            );
            let run = match run {
                Ok(run) => run,
                Err(e) => {
                    failures += 1;
                    println!(
                        "{walls} {seed} FAILED: {}",
                        rigbridge::daemon::error_chain(&e)
                    );
                    continue;
                }
            };
            let t = &run.paint.totals;
            let worst_wall = run
                .paint
                .walls
                .iter()
                .map(|w| w.coverage)
                .fold(f64::INFINITY, f64::min);
            println!(
                "{walls} {seed} {:.3} {:.3} {:.4} {} {} {} {} {:.0} {:.2} {:.2}",
                t.coverage * 100.0,
                worst_wall * 100.0,
                t.paint_in_openings_m2,
                t.collisions,
                t.limit_violations,
                run.paint.unreachable.len(),
                run.paint.strokes.len(),
                t.duration_s,
                plan_s,
                started.elapsed().as_secs_f64()
            );
            let bad = t.paint_in_openings_m2 > 0.0 || t.collisions > 0 || t.limit_violations > 0;
            let unreachable = !run.paint.unreachable.is_empty();
            failures += usize::from(bad || unreachable || t.coverage < 0.995);
            if worst.is_none_or(|(c, _, _)| t.coverage < c) {
                worst = Some((t.coverage, walls, seed));
            }
        }
    }
    if let Some((coverage, walls, seed)) = worst {
        println!(
            "worst: {walls} walls, seed {seed}: coverage {:.3} %; rooms failing a figure: {failures}",
            coverage * 100.0
        );
    }
    Ok(())
}
