//! Debug: plans one room (no streaming) and prints the planning time.
use rigbridge::task::paint::{load_paint_settings, plan_room};
use rigbridge::trajectory::PlanSettings;
use std::path::Path;
fn main() -> anyhow::Result<()> {
    let a: Vec<u64> = std::env::args().skip(1).map(|a| a.parse().unwrap()).collect();
    let paint = load_paint_settings(Path::new("config/paint.toml"))?;
    let mut start = vec![0.0; 10];
    start[8] = 30f64.to_radians();
    let plan = PlanSettings { period_s: 0.01, ..PlanSettings::default() };
    let t = std::time::Instant::now();
    let (_, p) = plan_room(&paint, a[0] as u32, a[1], &start, &plan)?;
    println!("{} strokes, {} samples, {:.2} s", p.strokes.len(), p.trajectory.len(), t.elapsed().as_secs_f64());
    Ok(())
}
