//! Plans painting rooms (no streaming) and prints, per room, its size, the planning time and
//! a fingerprint of every bit of the plan: the tool for profiling the planner under
//! callgrind and for checking that a speed-up left the plan unchanged.
//! `cargo run --release --example paint_plan -- [FIRST_N LAST_N SEEDS THREADS]`
//! (default: the 32-wall room of seed 0 on one thread, as in `benches/paint.rs`).

use rigbridge::apps::paint::planner::Planner;
use rigbridge::apps::paint::{PaintPlan, load_paint_settings, room_for};
use rigbridge::trajectory::PlanSettings;
use std::hash::{DefaultHasher, Hash, Hasher};
use std::num::NonZeroUsize;
use std::path::Path;

/// Every number of the plan, bit for bit, and the reasons for the unreachable bands.
fn fingerprint(plan: &PaintPlan) -> u64 {
    let mut hasher = DefaultHasher::new();
    let bits = |values: &[f64], hasher: &mut DefaultHasher| {
        values.iter().for_each(|v| v.to_bits().hash(hasher))
    };
    for stroke in &plan.strokes {
        (stroke.wall, stroke.samples).hash(&mut hasher);
        let figures = [stroke.s_m, stroke.v_from_m, stroke.v_to_m];
        bits(&figures, &mut hasher);
        bits(&[stroke.turn_deg, stroke.tilt_deg], &mut hasher);
    }
    for band in &plan.unreachable {
        (band.wall, &band.reason).hash(&mut hasher);
        bits(&[band.s_m, band.v_from_m, band.v_to_m], &mut hasher);
    }
    let trajectory = &plan.trajectory;
    bits(&[trajectory.period.as_secs_f64()], &mut hasher);
    for i in 0..trajectory.len() {
        bits(&trajectory.position(i), &mut hasher);
        bits(&trajectory.velocity(i), &mut hasher);
    }
    hasher.finish()
}

fn main() -> anyhow::Result<()> {
    let args: Vec<u64> = std::env::args()
        .skip(1)
        .map(|a| a.parse())
        .collect::<Result<_, _>>()?;
    let (first, last, seeds, threads) = match args.as_slice() {
        [f, l, s, t] => (*f as u32, *l as u32, *s, *t as usize),
        [] => (32, 32, 1, 1),
        _ => anyhow::bail!("usage: paint_plan [FIRST_N LAST_N SEEDS THREADS]"),
    };
    let threads = NonZeroUsize::new(threads).ok_or_else(|| anyhow::anyhow!("0 threads"))?;
    let settings = load_paint_settings(Path::new("config/paint.toml"))?;
    // The bench's start and period (benches/paint.rs).
    let mut start = vec![0.0; 10];
    start[8] = 30f64.to_radians();
    let plan = PlanSettings {
        period: std::time::Duration::from_millis(10),
        ..PlanSettings::default()
    };
    println!("walls seed samples strokes unreachable plan_s fingerprint");
    for walls in first..=last {
        for seed in 0..seeds {
            let room = room_for(&settings, walls, seed)?;
            let started = std::time::Instant::now();
            let planned = Planner::new(&settings, &room, plan)?
                .with_threads(threads)
                .plan(&start)?;
            println!(
                "{walls} {seed} {} {} {} {:.3} {:016x}",
                planned.trajectory.len(),
                planned.strokes.len(),
                planned.unreachable.len(),
                started.elapsed().as_secs_f64(),
                fingerprint(&planned)
            );
        }
    }
    Ok(())
}
