//! What the live view costs: per streaming cycle (the sink that feeds the view's slot, and
//! the tool's trace in the twin: both inside the 4 ms cycle at 250 Hz, targets < 5 us each)
//! and per page frame (the hub's sample, FK chains and JSON, 50 times a second: target
//! < 200 us, 1 % of the 20 ms between frames).
//!
//! `cargo bench --bench live -- --measurement-time 3`

use criterion::{Criterion, criterion_group, criterion_main};
use rigbridge::daemon::config::JobConfig;
use rigbridge::link::LinkCounters;
use rigbridge::protocol::{AxisValues, ControllerStatus, Feedback, JointTarget};
use rigbridge::rig::load_rig;
use rigbridge::stream::{CycleRecord, CycleSink};
use rigbridge::twin::TwinWorld;
use rigbridge::view::{ArmScene, JobView, LiveHub, LiveSample, LiveSink, LiveSlot, ToolTrace};
use std::hint::black_box;
use std::path::Path;
use std::sync::{Arc, Mutex};
use std::time::Duration;

const HOME: [f64; 6] = [0.0, 0.0, 0.0, 0.0, 0.5, 0.0];

fn star_job() -> JobConfig {
    JobConfig::WallFigure(rigbridge::job::WallFigure {
        wall_x_m: 0.45,
        centre_yz_m: [0.0, 0.45],
        radius_m: 0.12,
        laps: 1,
    })
}

fn live(c: &mut Criterion) {
    let rig = load_rig(Path::new("config/irb120.toml")).expect("shipped rig loads");
    let slot = Arc::new(LiveSlot::new(LiveSample::at_rest(&HOME)));
    let positions = AxisValues::from_slice(&HOME).expect("6 axes");
    let mut record = CycleRecord {
        target: JointTarget {
            seq: 0,
            t: Duration::ZERO,
            positions,
            velocities: AxisValues::zeros(6),
        },
        feedback: Some(Feedback {
            seq: 0,
            positions,
            status: ControllerStatus::Ok,
        }),
        late_us: 12.0,
        latency_us: Some(30.0),
        counters: LinkCounters::default(),
        at: std::time::Duration::ZERO,
        on_job: None,
    };
    {
        let mut sink = LiveSink::new(&slot, 250);
        c.bench_function("live_sink_record_per_cycle", |b| {
            b.iter(|| {
                record.target.seq = record.target.seq.wrapping_add(1);
                sink.record(black_box(&record));
            })
        });
    }

    // As the twin holds it: a shared world, the star job's wall set; the tool off the wall
    // (the common case: forward kinematics and a distance).
    let trace = Arc::new(Mutex::new(ToolTrace::new(rig.clone())));
    let _scene = ArmScene::for_job(rig.clone(), &star_job(), Some(trace.clone()));
    let mut world: Box<dyn TwinWorld> = Box::new(trace);
    c.bench_function("tool_trace_observe_per_twin_cycle", |b| {
        b.iter(|| world.observe(black_box(&HOME)))
    });

    let trace = Arc::new(Mutex::new(ToolTrace::new(rig.clone())));
    let scene = ArmScene::for_job(rig.clone(), &star_job(), Some(trace));
    let hub = LiveHub::new(rig, 250.0, 50.0, slot, Box::new(scene));
    let mut now = Duration::ZERO;
    c.bench_function("hub_frame_per_page_frame", |b| {
        b.iter(|| {
            now += Duration::from_millis(20);
            black_box(hub.tick(now, JobView::default()))
        })
    });
}

criterion_group! {
    name = benches;
    // No plots: with plotters' ab_glyph feature (the crate's own plots) criterion's plots
    // find no font and panic.
    config = Criterion::default().without_plots();
    targets = live
}
criterion_main!(benches);
