//! For tests that hold real-time cycles (4 ms at 250 Hz) against a twin in the same
//! process: one at a time, at real-time priority, looking at a condition about once a
//! cycle.

use std::sync::{Mutex, MutexGuard};
use std::time::{Duration, Instant};

/// How often [`wait_for`] looks again: about once a 4 ms cycle, so a test that reads one of
/// the twin's messages per look keeps up with them.
const POLL: Duration = Duration::from_millis(5);

/// The tests that take this run one at a time: each holds 4 ms cycles in real time, and on
/// a 2-core machine a neighbour (the Python peer starting, another twin) would take them.
pub fn one_at_a_time() -> MutexGuard<'static, ()> {
    static CYCLES: Mutex<()> = Mutex::new(());
    CYCLES.lock().unwrap_or_else(|p| p.into_inner())
}

/// SCHED_FIFO for this thread and the threads it starts (the link's I/O thread, the twin),
/// as `rigbridge run` and `rigbridge twin` do: on a loaded 2-core machine an ordinary thread
/// is preempted for milliseconds, longer than a cycle.
pub fn real_time() {
    if let Err(e) = rigbridge::stream::raise_priority(rigbridge::realtime::CYCLE_PRIORITY) {
        println!("note: normal priority (real-time scheduling refused: {e})");
    }
}

/// Looks at `condition` every [`POLL`] until it holds; fails the test, naming `what`, when
/// `within` has passed first.
pub fn wait_for(what: &str, within: Duration, mut condition: impl FnMut() -> bool) {
    let start = Instant::now();
    while !condition() {
        assert!(start.elapsed() < within, "timed out waiting for {what}");
        std::thread::sleep(POLL);
    }
}
