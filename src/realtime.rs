//! Real-time scheduling: up for the threads that run cycles, back down for the threads
//! that serve them from the side. On a shared 2-core machine an ordinary thread is
//! preempted for milliseconds by whatever else runs (a compiler, say); a SCHED_FIFO thread
//! is not. Raising needs root or CAP_SYS_NICE; without it streaming goes on at normal
//! priority and the caller says so. A Linux thread inherits its creator's policy, so a
//! thread spawned from a SCHED_FIFO one (or a library's runtime started from it) competes
//! with the cycle unless it steps down. This module owns only the scheduler calls; which
//! thread runs at which priority is its callers' decision.

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
