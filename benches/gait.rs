//! Per-frame update of the whole sloth gait (swing interpolation, body pose from the feet,
//! IK of all four limbs with per-bone limits), mid-stride on the straight branch with two
//! limbs swinging, once with each limb solver: CCD (the shipped one) and position-only
//! FABRIK (for comparison). Target: median <= 20 us (issue 6; the thesis measured 12.4-14 ms
//! per frame of its animation logic in Unreal Engine 5).
//!
//! `cargo bench --bench gait -- --measurement-time 3`

use criterion::{Criterion, criterion_group, criterion_main};
use rigbridge::apps::gait::{LimbSolver, Scenario, SlothRig, Walker};
use std::hint::black_box;
use std::path::Path;

fn frame_update(c: &mut Criterion) {
    let mut sloth = SlothRig::load(Path::new(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/config/sloth.toml"
    )))
    .expect("config/sloth.toml loads");
    let scenario = Scenario::build("straight", None, None).expect("straight builds");
    for (solver, name) in [
        (LimbSolver::Ccd, "gait frame update (4 limbs CCD + body)"),
        (
            LimbSolver::Fabrik,
            "gait frame update (4 limbs FABRIK + body)",
        ),
    ] {
        sloth.gait.solver = solver;
        let walker = Walker::new(&sloth, &scenario, std::time::Duration::from_millis(4));
        let cycle = (sloth.gait.cycle_s() / 0.004).round() as usize;
        // Mid-stride in the second cycle: rh has just landed, lf is mid-swing.
        let mid_stride = 50 + cycle + cycle / 4 + cycle / 8;
        let state = walker.state_before(mid_stride).expect("the gait walks");
        c.bench_function(name, |b| {
            b.iter_batched_ref(
                || state.clone(),
                |state| {
                    black_box(walker.step_frame(state).expect("frame solves").len());
                },
                criterion::BatchSize::SmallInput,
            )
        });
    }
}

criterion_group!(benches, frame_update);
criterion_main!(benches);
