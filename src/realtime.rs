//! Real-time scheduling: up for the threads that run cycles, back down for the threads
//! that serve them from the side. On a shared 2-core machine an ordinary thread is
//! preempted for milliseconds by whatever else runs (a compiler, say); a SCHED_FIFO thread
//! is not. Raising needs root or CAP_SYS_NICE; without it streaming goes on at normal
//! priority and the caller says so. A Linux thread inherits its creator's policy, so a
//! thread spawned from a SCHED_FIFO one (or a library's runtime started from it) competes
//! with the cycle unless it steps down. The same goes for the CPUs a thread may run on:
//! with a ROS 2 node beside the stream, the streaming thread keeps to one CPU and the
//! node's threads (Zenoh's runtime among them) keep off it, so that their system calls and
//! the loopback network's soft interrupts run on another CPU than the cycle; in `serve` the
//! shared executor's threads keep to the last CPUs and the daemon's other threads keep off
//! them (a kernel thread or another thread in a system call is not preempted on this
//! machine's kernel until it yields: a CPU of their own is what keeps the cycles on time,
//! `docs/architecture.md`, "The shared executor"). A side thread that a cycle's thread
//! starts (a log writer) inherits the cycle's priority and CPU unless it steps aside
//! ([`step_aside`]). This module owns only the scheduler calls and the CPUs cycles were
//! pinned to; which thread runs where and at which priority is its callers' decision.
//! `docs/realtime.md` says what the machine must allow.

use std::sync::{Mutex, PoisonError};

/// The SCHED_FIFO priority of every thread that runs cycles: `run`'s stream, the shared
/// executor's workers, a `serve` job streaming on its own thread, the twin's cycle. One
/// level for all, so that no cycle preempts another mid-cycle; the middle of the range,
/// level with a `PREEMPT_RT` kernel's interrupt threads (50 by default), so that a busy
/// cycle does not starve the interrupts of the link's own device.
pub const CYCLE_PRIORITY: i32 = 50;

/// The CPUs cycle threads of this process were pinned to ([`pin_to`]): side threads keep
/// off them ([`step_aside`]).
static CYCLE_CPUS: Mutex<Vec<usize>> = Mutex::new(Vec::new());

/// Moves the calling thread to SCHED_FIFO at `priority` (1-99).
pub fn raise_priority(priority: i32) -> std::io::Result<()> {
    let param = libc::sched_param {
        sched_priority: priority,
    };
    // SAFETY: sched_setscheduler reads `param` only during the call; pid 0 is this thread.
    let result = unsafe { libc::sched_setscheduler(0, libc::SCHED_FIFO, &param) };
    if result == 0 {
        Ok(())
    } else {
        Err(std::io::Error::last_os_error())
    }
}

/// Moves the calling thread back to SCHED_OTHER, normal priority. Always allowed.
pub fn normal_priority() -> std::io::Result<()> {
    let param = libc::sched_param { sched_priority: 0 };
    // SAFETY: as above; SCHED_OTHER takes priority 0.
    let result = unsafe { libc::sched_setscheduler(0, libc::SCHED_OTHER, &param) };
    if result == 0 {
        Ok(())
    } else {
        Err(std::io::Error::last_os_error())
    }
}

/// The CPU a streaming thread keeps to while side threads (a ROS 2 node's) keep off it:
/// the last of the process's CPUs. `None` when there is one only, where there is nothing
/// to keep apart.
pub fn streaming_cpu() -> Option<usize> {
    reserved_cpus(1).map(|cpus| cpus[0])
}

/// The CPUs `count` real-time threads keep to, one each: the last `count` of the process's
/// CPUs, so that the first ones stay for everything else (the runtime, the log writers, the
/// other processes a default setup starts there first). `None` when no CPU would be left
/// over, where there is nothing to keep apart.
pub fn reserved_cpus(count: usize) -> Option<Vec<usize>> {
    let cpus = process_cpus();
    if count == 0 || count >= cpus.len() {
        return None;
    }
    Some(cpus[cpus.len() - count..].to_vec())
}

/// Keeps the calling thread, a cycle's (and the threads it creates later), on `cpu` only;
/// side threads that step aside keep off `cpu` from then on.
pub fn pin_to(cpu: usize) -> std::io::Result<()> {
    set_affinity(&[cpu])?;
    let mut cycle_cpus = CYCLE_CPUS.lock().unwrap_or_else(PoisonError::into_inner);
    if !cycle_cpus.contains(&cpu) {
        cycle_cpus.push(cpu);
    }
    Ok(())
}

/// For a side thread, whoever started it: back to normal priority, and off every CPU a
/// cycle thread was pinned to. A thread inherits its creator's policy and CPUs, so a log
/// writer a cycle's thread starts would otherwise compete with the cycle at the cycle's
/// own priority, on the cycle's CPU. With no cycle pinned the CPUs stay as they are.
pub fn step_aside() -> std::io::Result<()> {
    normal_priority()?;
    let cycle_cpus = CYCLE_CPUS
        .lock()
        .unwrap_or_else(PoisonError::into_inner)
        .clone();
    if cycle_cpus.is_empty() {
        return Ok(());
    }
    keep_off_all(&cycle_cpus)
}

/// Keeps the calling thread (and the threads it creates later) on the process's CPUs but
/// `cpu`, even when it was created by a thread pinned to `cpu`. With no other CPU it is
/// left as it is.
pub fn keep_off(cpu: usize) -> std::io::Result<()> {
    keep_off_all(&[cpu])
}

/// [`keep_off`] for several CPUs: the calling thread keeps to the process's other CPUs.
pub fn keep_off_all(reserved: &[usize]) -> std::io::Result<()> {
    let others: Vec<usize> = process_cpus()
        .iter()
        .copied()
        .filter(|c| !reserved.contains(c))
        .collect();
    if others.is_empty() {
        return Ok(());
    }
    set_affinity(&others)
}

/// The process's CPUs: those the first thread to ask could run on, remembered, since
/// threads pinned later (and the threads they create) see fewer. Callers ask before they
/// pin.
fn process_cpus() -> &'static [usize] {
    static CPUS: std::sync::OnceLock<Vec<usize>> = std::sync::OnceLock::new();
    CPUS.get_or_init(|| allowed_cpus().unwrap_or_default())
}

/// The CPUs the calling thread may run on, in ascending order.
fn allowed_cpus() -> std::io::Result<Vec<usize>> {
    // SAFETY: an all-zero cpu_set_t is a valid empty set; sched_getaffinity writes at most
    // size_of::<cpu_set_t>() bytes into it, and CPU_ISSET reads within it.
    unsafe {
        let mut set: libc::cpu_set_t = std::mem::zeroed();
        if libc::sched_getaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &mut set) != 0 {
            return Err(std::io::Error::last_os_error());
        }
        Ok((0..libc::CPU_SETSIZE as usize)
            .filter(|&cpu| libc::CPU_ISSET(cpu, &set))
            .collect())
    }
}

fn set_affinity(cpus: &[usize]) -> std::io::Result<()> {
    // SAFETY: as above; CPU_SET is only given CPUs below CPU_SETSIZE (the filter), as
    // allowed_cpus and reserved_cpus return.
    unsafe {
        let mut set: libc::cpu_set_t = std::mem::zeroed();
        for &cpu in cpus.iter().filter(|&&c| c < libc::CPU_SETSIZE as usize) {
            libc::CPU_SET(cpu, &mut set);
        }
        if libc::sched_setaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &set) != 0 {
            return Err(std::io::Error::last_os_error());
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_thread_kept_off_the_streaming_cpu_runs_elsewhere_and_a_pinned_one_there() {
        let Some(cpu) = streaming_cpu() else {
            eprintln!("skipped: this machine lets the test run on one CPU only");
            return;
        };
        let off = std::thread::spawn(move || {
            keep_off(cpu).expect("the thread keeps off the streaming CPU");
            allowed_cpus().expect("the thread's CPUs are readable")
        })
        .join()
        .expect("the kept-off thread does not panic");
        assert!(
            !off.is_empty() && !off.contains(&cpu),
            "{off:?} still has {cpu}"
        );
        let (on, off_from_pinned) = std::thread::spawn(move || {
            pin_to(cpu).expect("the thread pins to the streaming CPU");
            // A thread created by a pinned one starts pinned too (what Zenoh's runtime
            // threads rely on), and can still keep off (a node started from the cycle's
            // thread).
            let on = std::thread::spawn(allowed_cpus)
                .join()
                .expect("the pinned thread's child does not panic")
                .expect("the child's CPUs are readable");
            let off = std::thread::spawn(move || {
                keep_off(cpu).expect("the child keeps off the streaming CPU");
                allowed_cpus().expect("the child's CPUs are readable")
            })
            .join()
            .expect("the kept-off child does not panic");
            (on, off)
        })
        .join()
        .expect("the pinned thread does not panic");
        assert_eq!(on, vec![cpu]);
        assert_eq!(off_from_pinned, off);
    }

    /// The calling thread's scheduling policy and CPUs.
    fn policy_and_cpus() -> (i32, Vec<usize>) {
        // SAFETY: sched_getscheduler takes no pointer; pid 0 is the calling thread.
        let policy = unsafe { libc::sched_getscheduler(0) };
        (
            policy,
            allowed_cpus().expect("the thread's CPUs are readable"),
        )
    }

    #[test]
    fn a_side_thread_of_a_pinned_cycle_thread_steps_aside_to_normal_priority_and_other_cpus() {
        let Some(cpu) = streaming_cpu() else {
            eprintln!("skipped: this machine lets the test run on one CPU only");
            return;
        };
        let threads = std::thread::spawn(move || {
            raise_priority(CYCLE_PRIORITY)?;
            pin_to(cpu).expect("the cycle's thread pins to the streaming CPU");
            let inherited = std::thread::spawn(policy_and_cpus)
                .join()
                .expect("the inheriting thread does not panic");
            let aside = std::thread::spawn(|| {
                step_aside().expect("the side thread steps aside");
                policy_and_cpus()
            })
            .join()
            .expect("the side thread does not panic");
            Ok::<_, std::io::Error>((inherited, aside))
        })
        .join()
        .expect("the cycle's thread does not panic");
        let (inherited, (policy, cpus)) = match threads {
            Ok(threads) => threads,
            Err(e) => {
                eprintln!("skipped: real-time scheduling refused here ({e})");
                return;
            }
        };
        // What a side thread is before it steps aside: the cycle's policy, on its CPU.
        assert_eq!(inherited, (libc::SCHED_FIFO, vec![cpu]));
        assert_eq!(policy, libc::SCHED_OTHER);
        assert!(
            !cpus.is_empty() && !cpus.contains(&cpu),
            "{cpus:?} has {cpu}"
        );
    }

    #[test]
    fn reserved_cpus_are_the_last_ones_and_leave_one_over() {
        let cpus = process_cpus().to_vec();
        assert_eq!(reserved_cpus(0), None);
        assert_eq!(reserved_cpus(cpus.len()), None, "no CPU would be left over");
        if cpus.len() < 2 {
            eprintln!("skipped the rest: this machine lets the test run on one CPU only");
            return;
        }
        assert_eq!(reserved_cpus(1), Some(vec![cpus[cpus.len() - 1]]));
        assert_eq!(streaming_cpu(), Some(cpus[cpus.len() - 1]));
        let reserved = reserved_cpus(cpus.len() - 1).expect("all but one CPU can be reserved");
        assert_eq!(reserved, cpus[1..]);
        let off = std::thread::spawn(move || {
            keep_off_all(&reserved).expect("the thread keeps off the reserved CPUs");
            allowed_cpus().expect("the thread's CPUs are readable")
        })
        .join()
        .expect("the kept-off thread does not panic");
        assert_eq!(off, vec![cpus[0]]);
    }
}
