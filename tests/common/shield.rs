//! A CPU kept for the bench's real-time threads, shared by `benches/cells.rs` and
//! `benches/stream.rs` (their `..._SHIELD=1`): every thread of every other process that may
//! move keeps off that CPU for as long as the shield is up, and gets its CPUs back after.
//! What `isolcpus` or a cpuset does on a machine set up for real time; here the VM's own
//! agent and its kernel threads would otherwise run beside the cycles, and on this kernel a
//! thread in a system call keeps its CPU until it yields. Per-CPU kernel threads may not
//! move and stay. Owns no measurement. Its `Drop` puts the threads back: a bench that
//! leaves by `std::process::exit` drops it first, and one killed before its end leaves them
//! moved (`taskset -a -p -c 0-N PID` puts one back).
#![allow(dead_code)]

use std::collections::HashMap;

pub struct Shield {
    /// Each moved thread and the CPUs it had.
    moved: HashMap<i32, libc::cpu_set_t>,
}

impl Shield {
    /// Moves every other process' movable threads off `cpu`; says how many on stdout.
    pub fn raise(cpu: usize) -> Shield {
        let own = std::process::id() as i32;
        let mut moved = HashMap::new();
        let mut stayed = 0;
        for tid in other_threads(own) {
            match move_off(tid, cpu) {
                Move::Moved(before) => {
                    moved.insert(tid, before);
                }
                Move::NotThere => {}
                Move::Stuck => stayed += 1,
            }
        }
        println!(
            "shield: {} threads of other processes moved off CPU {cpu} for the bench; {stayed} may not move (per-CPU kernel threads)",
            moved.len()
        );
        Shield { moved }
    }
}

/// Puts every moved thread back on the CPUs it had.
impl Drop for Shield {
    fn drop(&mut self) {
        for (tid, set) in &self.moved {
            // SAFETY: `set` is a cpu_set_t read by sched_getaffinity; a thread gone
            // meanwhile only makes the call fail.
            unsafe {
                libc::sched_setaffinity(*tid, std::mem::size_of::<libc::cpu_set_t>(), set);
            }
        }
    }
}

fn other_threads(own: i32) -> Vec<i32> {
    let numbers = |dir: &str| -> Vec<i32> {
        std::fs::read_dir(dir)
            .map(|entries| {
                entries
                    .filter_map(|e| e.ok()?.file_name().to_str()?.parse().ok())
                    .collect()
            })
            .unwrap_or_default()
    };
    numbers("/proc")
        .into_iter()
        .filter(|&pid| pid != own)
        .flat_map(|pid| numbers(&format!("/proc/{pid}/task")))
        .collect()
}

/// What [`move_off`] did with a thread.
enum Move {
    /// Off `cpu` now; the CPUs it had.
    Moved(libc::cpu_set_t),
    /// Not on `cpu` (or gone): left alone.
    NotThere,
    /// Bound to `cpu` alone, or the move was refused.
    Stuck,
}

/// Takes `cpu` out of the thread's CPUs.
fn move_off(tid: i32, cpu: usize) -> Move {
    let size = std::mem::size_of::<libc::cpu_set_t>();
    // SAFETY: an all-zero cpu_set_t is a valid empty set; the calls read and write at
    // most `size` bytes of the sets they are given, and CPU_ISSET/CPU_CLR/CPU_COUNT
    // stay within them (`cpu` is below CPU_SETSIZE: it came from sched_getaffinity).
    unsafe {
        let mut before: libc::cpu_set_t = std::mem::zeroed();
        if libc::sched_getaffinity(tid, size, &mut before) != 0 {
            return Move::NotThere;
        }
        if !libc::CPU_ISSET(cpu, &before) {
            return Move::NotThere;
        }
        if libc::CPU_COUNT(&before) < 2 {
            return Move::Stuck;
        }
        let mut after = before;
        libc::CPU_CLR(cpu, &mut after);
        if libc::sched_setaffinity(tid, size, &after) != 0 {
            return Move::Stuck;
        }
        Move::Moved(before)
    }
}
