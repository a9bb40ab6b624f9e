//! The streaming cycle allocates nothing: a run ten times longer makes exactly as many
//! allocations as a short one (all of them before the first cycle or after the last).

mod common;

use common::irb120;
use rigbridge::clock::VirtualClock;
use rigbridge::link::LoopbackLink;
use rigbridge::stream::{StreamControl, StreamSettings, slowdown_rate, stream};
use rigbridge::trajectory::Trajectory;
use rigbridge::twin::{Twin, TwinSettings};
use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};

struct Counting;

static ALLOCATIONS: AtomicUsize = AtomicUsize::new(0);

// SAFETY: forwards to the system allocator unchanged; only counts calls.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        ALLOCATIONS.fetch_add(1, Ordering::SeqCst);
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
    Trajectory::new(rig.name, names, 0.004, positions, velocities).unwrap()
}

fn allocations_while_streaming(samples: usize) -> usize {
    let rig = irb120();
    let trajectory = hold(samples);
    let mut link = LoopbackLink::new(Twin::new(&rig, TwinSettings::default(), &START).unwrap());
    let clock = VirtualClock::new();
    let control = StreamControl::default();
    let settings = StreamSettings::new(0.004, slowdown_rate(&rig, 0.9, 0.8));
    let before = ALLOCATIONS.load(Ordering::SeqCst);
    let report = stream(
        &trajectory,
        &rig,
        &mut link,
        &clock,
        &mut (),
        &control,
        &settings,
    )
    .unwrap();
    let after = ALLOCATIONS.load(Ordering::SeqCst);
    assert_eq!(report.cycles as usize, samples - 1);
    after - before
}

#[test]
fn the_cycle_does_not_allocate() {
    let short = allocations_while_streaming(1_000);
    let long = allocations_while_streaming(10_000);
    assert_eq!(short, long, "allocations grew with the number of cycles");
}
