//! Debug: prints clusters of unpainted paintable cells of a room's walls.
use rigbridge::clock::VirtualClock;
use rigbridge::daemon::config::load_run_settings;
use rigbridge::daemon::paint::run_paint;
use rigbridge::stream::StreamControl;
use rigbridge::task::paint::load_paint_settings;
use std::path::Path;
fn main() -> anyhow::Result<()> {
    let a: Vec<u64> = std::env::args().skip(1).map(|a| a.parse().unwrap()).collect();
    let settings = load_run_settings(Path::new("config/paint-run.toml"))?;
    let paint = load_paint_settings(Path::new("config/paint.toml"))?;
    let run = run_paint(&settings, &paint, a[0] as u32, a[1], &VirtualClock::new(), None, &StreamControl::default(), &mut |_| {})?;
    let world = run.world.lock().unwrap();
    let g = &world.grids()[a[2] as usize];
    let mut by_col = std::collections::BTreeMap::new();
    for r in 0..g.rows { for c in 0..g.cols { let i = r*g.cols+c; if !g.painted[i] && !g.opening[i] { by_col.entry(c).or_insert_with(Vec::new).push(r); } } }
    for (c, rows) in by_col { println!("col {c}: {} cells, rows {:?}", rows.len(), if rows.len() > 12 { rows[..12].to_vec() } else { rows }); }
    Ok(())
}
