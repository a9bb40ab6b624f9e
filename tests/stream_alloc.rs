//! The streaming cycle allocates nothing: a run ten times longer makes exactly as many
//! allocations as a short one (all of them before the first cycle or after the last). The
//! same holds with the live view attached: its sink and the tool's trace in the twin.

mod common;

use common::irb120;
use rigbridge::clock::VirtualClock;
use rigbridge::daemon::config::JobConfig;
use rigbridge::job::plan_job;
use rigbridge::link::LoopbackLink;
use rigbridge::rig::Rig;
use rigbridge::stream::{
    CycleSink, StreamControl, StreamReport, StreamSettings, slowdown_rate, stream,
};
use rigbridge::trajectory::PlanSettings;
use rigbridge::trajectory::Trajectory;
use rigbridge::twin::{Twin, TwinSettings};
use rigbridge::view::{ArmScene, LiveSample, LiveScene, LiveSink, LiveSlot, ToolTrace};
use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::sync::{Arc, Mutex};

struct Counting;

thread_local! {
    /// Allocations on this thread: tests run in parallel (and the harness allocates on its
    /// own threads), each measures only what its own thread does.
    static ALLOCATIONS: Cell<usize> = const { Cell::new(0) };
}

fn allocations() -> usize {
    ALLOCATIONS.with(Cell::get)
}

// SAFETY: forwards to the system allocator unchanged; only counts calls.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        // Ignored while the thread's locals are being torn down.
        let _ = ALLOCATIONS.try_with(|count| count.set(count.get() + 1));
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

const START: [f64; 6] = [0.0, 0.0, 0.0, 0.0, 0.5, 0.0];

fn hold(samples: usize) -> Trajectory {
    let rig = irb120();
    let positions = START.repeat(samples);
    let velocities = vec![0.0; samples * 6];
    let names = rig.joint_names().map(String::from).collect();
    Trajectory::new(
        rig.name,
        names,
        std::time::Duration::from_millis(4),
        positions,
        velocities,
    )
    .unwrap()
}

/// Streams `trajectory` over `link` into `sink` under the virtual clock, then drops the
/// sink: the report and the allocations this thread made meanwhile (the clock, the control
/// and the settings are made before counting starts).
fn stream_counting_allocations(
    rig: &Rig,
    trajectory: &Trajectory,
    link: &mut LoopbackLink,
    mut sink: impl CycleSink,
) -> (StreamReport, usize) {
    let clock = VirtualClock::new();
    let control = StreamControl::default();
    let settings = StreamSettings::new(
        std::time::Duration::from_millis(4),
        slowdown_rate(rig, 0.9, 0.8),
    );
    let before = allocations();
    let report = stream(
        trajectory, rig, link, &clock, &mut sink, &control, &settings,
    )
    .unwrap();
    drop(sink);
    let after = allocations();
    (report, after - before)
}

fn allocations_while_streaming(samples: usize) -> usize {
    let rig = irb120();
    let trajectory = hold(samples);
    let mut link = LoopbackLink::new(Twin::new(&rig, TwinSettings::default(), &START).unwrap());
    let (report, allocated) = stream_counting_allocations(&rig, &trajectory, &mut link, ());
    assert_eq!(report.cycles as usize, samples - 1);
    allocated
}

#[test]
fn the_cycle_does_not_allocate() {
    let short = allocations_while_streaming(1_000);
    let long = allocations_while_streaming(10_000);
    assert_eq!(short, long, "allocations grew with the number of cycles");
}

/// Streams the star job (`laps` laps) to a twin whose tool traces paint on the job's wall,
/// feeding the live view's slot; returns the allocations while streaming and the paint.
fn allocations_while_streaming_live(laps: u32) -> (usize, usize) {
    let rig = irb120();
    let job = JobConfig::WallFigure(rigbridge::job::WallFigure {
        wall_x_m: 0.45,
        centre_yz_m: [0.0, 0.45],
        radius_m: 0.12,
        laps,
    });
    let trajectory = plan_job(&job, &rig, &START, &PlanSettings::default()).unwrap();
    let trace = Arc::new(Mutex::new(ToolTrace::new(rig.clone())));
    let mut scene = ArmScene::for_job(rig.clone(), &job, Some(trace.clone()));
    let twin = Twin::new(&rig, TwinSettings::default(), &START)
        .unwrap()
        .with_world(Box::new(trace));
    let mut link = LoopbackLink::new(twin);
    let slot = LiveSlot::new(LiveSample::at_rest(&START));
    let sink = LiveSink::new(&slot, 250);
    let (report, allocated) = stream_counting_allocations(&rig, &trajectory, &mut link, sink);
    assert_eq!(report.cycles as usize, trajectory.len() - 1);
    assert_eq!(
        slot.latest().cycles,
        report.cycles,
        "the view saw the last cycle"
    );
    (allocated, scene.drain_paint().len())
}

#[test]
fn the_cycle_feeding_the_live_view_does_not_allocate() {
    let (short, paint_short) = allocations_while_streaming_live(1);
    let (long, paint_long) = allocations_while_streaming_live(4);
    assert!(
        paint_short > 100,
        "the star leaves paint: {paint_short} strokes"
    );
    assert!(
        paint_long > 3 * paint_short,
        "{paint_long} strokes for 4 laps"
    );
    assert_eq!(short, long, "allocations grew with the number of cycles");
}
