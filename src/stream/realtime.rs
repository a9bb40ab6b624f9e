//! Real-time scheduling for the streaming thread. On a shared 2-core machine an ordinary
//! thread is preempted for milliseconds by whatever else runs (a compiler, say); a
//! SCHED_FIFO thread is not. Needs root or CAP_SYS_NICE; without it streaming goes on at
//! normal priority and the caller says so.

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
