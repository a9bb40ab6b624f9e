//! Which threads run at the cycles' priority, seen from the kernel (`/proc/self/task`,
//! `sched_getscheduler`): a `serve` job that streams to a remote controller rises to
//! SCHED_FIFO at `realtime::CYCLE_PRIORITY` once planned (a twin cell's with a thread per
//! cell does not), so does a link's I/O thread whoever opens
//! the link, and the log writer a cycle's thread starts steps aside to normal priority,
//! off the CPU the cycle keeps to. Without permission for
//! real-time scheduling there is nothing to see, and the tests say they skip.

mod common;
#[path = "common/flood.rs"]
mod flood;
#[path = "common/in_process.rs"]
mod in_process;

use common::{irb120, repo_path, scratch_dir, scratch_file, wait_until};
use rigbridge::daemon::config::{ExecutorKind, load_run_settings};
use rigbridge::log::Recorder;
use rigbridge::realtime::{CYCLE_PRIORITY, pin_to, raise_priority, streaming_cpu};
use std::time::Duration;

/// A thread of this process as the kernel sees it.
#[derive(Debug)]
struct Task {
    tid: i32,
    name: String,
    policy: i32,
    priority: i32,
    cpus: Vec<usize>,
}

/// Every thread of this process named `name` (the kernel keeps 15 bytes of a name).
fn tasks_named(name: &str) -> Vec<Task> {
    let Ok(entries) = std::fs::read_dir("/proc/self/task") else {
        return Vec::new();
    };
    entries
        .filter_map(|entry| entry.ok()?.file_name().to_str()?.parse().ok())
        .filter_map(task)
        .filter(|task| task.name == name)
        .collect()
}

/// The threads named `name` that are not among `before`.
fn new_tasks_named(name: &str, before: &[Task]) -> Vec<Task> {
    tasks_named(name)
        .into_iter()
        .filter(|t| !before.iter().any(|b| b.tid == t.tid))
        .collect()
}

/// Thread `tid`, or `None` once it has ended.
fn task(tid: i32) -> Option<Task> {
    let name = std::fs::read_to_string(format!("/proc/self/task/{tid}/comm")).ok()?;
    let mut param = libc::sched_param { sched_priority: 0 };
    // SAFETY: the kernel reads `tid` and writes one sched_param into `param`, and at most
    // size_of::<cpu_set_t>() bytes into `set`; CPU_ISSET reads within it.
    let (policy, cpus) = unsafe {
        let policy = libc::sched_getscheduler(tid);
        if policy < 0 || libc::sched_getparam(tid, &mut param) != 0 {
            return None;
        }
        let mut set: libc::cpu_set_t = std::mem::zeroed();
        if libc::sched_getaffinity(tid, std::mem::size_of::<libc::cpu_set_t>(), &mut set) != 0 {
            return None;
        }
        let cpus = (0..libc::CPU_SETSIZE as usize)
            .filter(|&cpu| libc::CPU_ISSET(cpu, &set))
            .collect();
        (policy, cpus)
    };
    Some(Task {
        tid,
        name: name.trim_end().to_owned(),
        policy,
        priority: param.sched_priority,
        cpus,
    })
}

/// The tests that start a `serve` job or a log look at every `rigbridge-job` or
/// `rigbridge-log` thread of this process: one at a time, so that each sees its own.
fn one_job_at_a_time() -> std::sync::MutexGuard<'static, ()> {
    static JOBS: std::sync::Mutex<()> = std::sync::Mutex::new(());
    JOBS.lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// Whether this process may use real-time scheduling, asked on a thread of its own, which
/// ends with its answer; when not, says that the calling test skips and why.
fn real_time_allowed() -> bool {
    let asked = std::thread::spawn(|| raise_priority(CYCLE_PRIORITY))
        .join()
        .expect("the asking thread does not panic");
    if let Err(e) = &asked {
        eprintln!("skipped: real-time scheduling refused here ({e})");
    }
    asked.is_ok()
}

/// Asks the server at `address` for a move to `target_deg`; fails the test unless accepted.
fn start_move(address: std::net::SocketAddr, target_deg: [f64; 6]) {
    let job = serde_json::json!({"job": {"kind": "move_joints", "targets_deg": [target_deg]}});
    let (answer, _) = flood::http(
        address,
        "POST",
        "/api/jobs",
        "Content-Type: application/json\r\n",
        &job.to_string(),
        Duration::from_secs(30),
    );
    let (code, body) = answer.expect("the job is answered");
    assert_eq!(code, 202, "{body}");
}

#[test]
fn a_log_writer_started_by_a_pinned_cycle_thread_steps_aside() {
    if !real_time_allowed() {
        return;
    }
    let _one = one_job_at_a_time();
    let cpu = streaming_cpu();
    let path = scratch_file("realtime", "writer.mcap");
    let writers = std::thread::spawn(move || {
        raise_priority(CYCLE_PRIORITY).expect("allowed above");
        if let Some(cpu) = cpu {
            pin_to(cpu).expect("the cycle's thread pins to the streaming CPU");
        }
        let before = tasks_named("rigbridge-log");
        let recorder =
            Recorder::for_rig(&path, &irb120(), serde_json::json!({})).expect("the log opens");
        // The writer steps aside first thing: look until it has.
        let writers = wait_until(
            "the log writer at normal priority",
            Duration::from_secs(10),
            || {
                let new: Vec<Task> = tasks_named("rigbridge-log")
                    .into_iter()
                    .filter(|t| !before.iter().any(|b| b.tid == t.tid))
                    .collect();
                new.iter()
                    .all(|t| t.policy == libc::SCHED_OTHER)
                    .then_some(new)
                    .filter(|new| !new.is_empty())
            },
        );
        recorder.finish().expect("the log closes");
        writers
    })
    .join()
    .expect("the cycle's thread does not panic");
    for writer in writers {
        assert_eq!(writer.priority, 0, "{writer:?}");
        if let Some(cpu) = cpu {
            assert!(
                !writer.cpus.contains(&cpu),
                "on the cycle's CPU: {writer:?}"
            );
        }
    }
}

#[test]
fn a_serve_job_streaming_to_a_remote_controller_runs_at_the_cycle_priority() {
    if !real_time_allowed() {
        return;
    }
    let _one = one_job_at_a_time();
    let twin =
        common::twin::start_listening(&mut common::twin::listen_command("tcp://127.0.0.1:0"));
    let mut settings = load_run_settings(&repo_path("config/rigbridge.toml")).expect("settings");
    // A controller of its own: the job's own thread runs the cycles.
    settings.config.stream.link = twin.address.clone();
    let runs = scratch_dir("realtime", "serve-runs");
    let served = in_process::start(vec![settings], in_process::options(runs));
    // A job thread of an earlier test may still be ending: this test looks at its own.
    let before = tasks_named("rigbridge-job");
    start_move(served.address, [40.0, -20.0, 20.0, 0.0, 50.0, -40.0]);
    // Planned, the job's thread streams at the cycles' priority; its log writer does not.
    let (job, writers) = wait_until(
        "the job's thread at real-time priority, its log writer at normal priority",
        Duration::from_secs(20),
        || {
            let job = new_tasks_named("rigbridge-job", &before)
                .into_iter()
                .find(|t| t.policy == libc::SCHED_FIFO)?;
            // A writer steps aside first thing, but after it has started: look until it has.
            let writers = tasks_named("rigbridge-log");
            let aside =
                !writers.is_empty() && writers.iter().all(|w| w.policy == libc::SCHED_OTHER);
            aside.then_some((job, writers))
        },
    );
    assert_eq!(job.priority, CYCLE_PRIORITY, "{job:?}");
    for writer in writers {
        assert_eq!(writer.priority, 0, "{writer:?}");
    }
    served.stop().expect("the server stops").expect("cleanly");
}

#[test]
fn a_serve_job_on_the_twin_with_a_thread_per_cell_stays_at_normal_priority() {
    let _one = one_job_at_a_time();
    let mut settings = load_run_settings(&repo_path("config/rigbridge.toml")).expect("settings");
    settings.config.serve.executor = ExecutorKind::ThreadPerCell;
    let runs = scratch_dir("realtime", "per-cell-runs");
    let served = in_process::start(vec![settings], in_process::options(runs));
    let before = tasks_named("rigbridge-job");
    start_move(served.address, [-40.0, -20.0, 20.0, 0.0, 40.0, 40.0]);
    // Well into its cycles (as the cell's status counts them), its thread is still at
    // normal priority.
    let streaming = wait_until("the job streaming", Duration::from_secs(20), || {
        let (answer, _) = flood::http(
            served.address,
            "GET",
            "/api/status",
            "",
            "",
            Duration::from_secs(30),
        );
        let status: serde_json::Value = serde_json::from_str(&answer?.1).ok()?;
        (status["job"]["cycles"].as_u64()? > 50).then(|| new_tasks_named("rigbridge-job", &before))
    });
    assert!(!streaming.is_empty(), "the job's thread is there");
    for job in streaming {
        assert_eq!(job.policy, libc::SCHED_OTHER, "{job:?}");
    }
    served.stop().expect("the server stops").expect("cleanly");
}

#[test]
fn a_link_opened_at_normal_priority_carries_its_feedback_at_the_cycle_priority() {
    if !real_time_allowed() {
        return;
    }
    // A `serve` job opens a remote link before it rises: so does this test's thread.
    let listener = std::net::TcpListener::bind("127.0.0.1:0").expect("a free loopback port");
    let address = listener
        .local_addr()
        .expect("the port's address")
        .to_string();
    let before = tasks_named("rigbridge-tcp");
    let hello = rigbridge::link::bridge_hello(&irb120(), Duration::from_millis(4), 25);
    let link = rigbridge::device::ours::connect_tcp(
        rigbridge::device::ours::TcpSettings::new(address),
        hello,
    )
    .expect("the link starts");
    let io = wait_until("the link's I/O thread", Duration::from_secs(10), || {
        new_tasks_named("rigbridge-tcp", &before)
            .into_iter()
            .find(|t| t.policy == libc::SCHED_FIFO)
    });
    assert_eq!(io.priority, CYCLE_PRIORITY, "{io:?}");
    drop(link);
}
