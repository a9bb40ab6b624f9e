//! A test's child that forks children of its own (chromedriver starting Chromium, which forks
//! its renderers): started as the leader of a process group of its own, and the whole group
//! killed and the leader reaped when the test lets go of it, however the test ends (a panic
//! unwinds through the guard too). Also the check that a group is empty. Owns the processes
//! only: the callers judge what they say.

use std::path::Path;
use std::process::{Child, Command};
use std::time::Duration;

/// How long a killed group's processes may take to be gone: SIGKILL is delivered at once,
/// but a loaded machine may take a while to tear down a browser's memory.
pub const GONE_WITHIN: Duration = Duration::from_secs(10);

/// A process group led by a child of the test, killed (SIGKILL to every member) when dropped.
pub struct ProcessGroup {
    pub leader: Child,
}

impl ProcessGroup {
    /// Starts `command` as the leader of a new process group (its id is the leader's pid).
    pub fn spawn(command: &mut Command) -> std::io::Result<ProcessGroup> {
        use std::os::unix::process::CommandExt;
        let leader = command.process_group(0).spawn()?;
        Ok(ProcessGroup { leader })
    }

    /// The group's id: the leader's pid.
    pub fn id(&self) -> u32 {
        self.leader.id()
    }
}

impl Drop for ProcessGroup {
    fn drop(&mut self) {
        let group = self.id() as libc::pid_t;
        // SAFETY: kill(2) with a negative pid signals the group; it touches no memory of ours.
        // The leader is our unreaped child, so its pid (the group's id) cannot have been reused.
        unsafe { libc::kill(-group, libc::SIGKILL) };
        let _ = self.leader.wait();
    }
}

/// The live processes (not zombies: those run nothing and wait only to be reaped by whoever
/// adopted them) of process group `group`, or whose command line contains `marker` (a path
/// unique to the run, to catch one that left the group), by pid.
pub fn live_members(group: u32, marker: Option<&Path>) -> Vec<u32> {
    let Ok(entries) = std::fs::read_dir("/proc") else {
        return Vec::new();
    };
    entries
        .filter_map(|e| e.ok()?.file_name().to_str()?.parse::<u32>().ok())
        .filter(|&pid| is_live_member(pid, group, marker))
        .collect()
}

fn is_live_member(pid: u32, group: u32, marker: Option<&Path>) -> bool {
    let Ok(stat) = std::fs::read_to_string(format!("/proc/{pid}/stat")) else {
        return false; // gone between listing and reading
    };
    // After the command name's closing parenthesis (which may itself hold spaces): state,
    // ppid, pgrp.
    let Some((_, rest)) = stat.rsplit_once(')') else {
        return false;
    };
    let fields: Vec<&str> = rest.split_whitespace().collect();
    if fields.first() == Some(&"Z") {
        return false;
    }
    if fields.get(2).and_then(|g| g.parse::<u32>().ok()) == Some(group) {
        return true;
    }
    marker.is_some_and(|marker| {
        let marker = marker.as_os_str().as_encoded_bytes();
        std::fs::read(format!("/proc/{pid}/cmdline"))
            .is_ok_and(|line| line.windows(marker.len()).any(|w| w == marker))
    })
}
