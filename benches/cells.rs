//! Many cells in one daemon (issue 18): N copies of the IRB 120 arm cell on the loopback
//! twin, served by `rigbridge::server::run` in this process and driven over its
//! HTTP API, every cell streaming a steady joint job at once, at 250 Hz and at 1 kHz, with
//! the cells' cycles on the shared executor and on a thread per cell (`[serve] executor`),
//! both in one run. Each (design, rate, N) runs in a child process of its own, so its CPU
//! time and memory are its own. Prints per cell jitter p50/p99/max (median cell and worst
//! cell, from each job's report), missed cycles, overruns, CPU time per cell-cycle
//! (getrusage of the process over a window in which every cell streams, divided by the
//! cycles the cells ran in it) and memory per cell (resident set growth from before the
//! daemon started, divided by N), then the ratios of the two designs.
//!
//! Beside the cells, one idle witness thread per CPU (pinned, SCHED_FIFO above the
//! streams) wakes every millisecond and does nothing else. The wakes it gets later than a
//! 1 kHz period, and later than a cell's period, are stalls of the machine itself (a shared
//! VM's host taking its CPU, a kernel thread that the kernel does not preempt), which no
//! design can avoid; they are counted for each CPU. A cell's missed cycles beside as many
//! witness stalls over the cell's period on the executor's CPU are the machine's; beyond
//! them, the design's.
//!
//! The shared executor runs as `rigbridge serve` runs it by default: its thread on the last
//! CPU and the daemon's other threads kept off it (`[serve] pin_executor`); `CELLS_UNPINNED=1`
//! adds the design `shared_unpinned`, which leaves them all where the scheduler puts them.
//! Other processes still run on that CPU: the VM's own agent does, and on this kernel a
//! thread in a system call keeps the CPU until it yields. `CELLS_SHIELD=1` moves every
//! thread of other processes that may move off the executor's CPU for the run, and back at
//! the end: what `isolcpus` or a cpuset does on a machine set up for real time.
//!
//! `cargo bench --bench cells`; sizes: `CELLS=1,8,32,128` (250 Hz), `CELLS_1KHZ=1,8,16`;
//! the shared executor's thread counts to compare: `CELLS_THREADS=1,2` (default 1, the
//! `[serve] executor_threads` default; a design `shared_x2` is the executor with two).

#[path = "../tests/common/flood.rs"]
mod flood;
#[path = "../tests/common/in_process.rs"]
mod in_process;
#[path = "../tests/common/shield.rs"]
mod shield;

use rigbridge::daemon::config::{ExecutorKind, RunSettings, load_run_settings};
use rigbridge::server::ServeOptions;
use serde_json::{Value, json};
use std::net::SocketAddr;
use std::path::Path;
use std::time::{Duration, Instant};

const CHILD: &str = "RIGBRIDGE_CELLS_BENCH_CHILD";
/// Every axis moves between these, about 0.6 s a move: a job of cheap planning that
/// streams long enough for the window.
const A: [f64; 6] = [20.0, 10.0, 10.0, 0.0, 40.0, 10.0];
const B: [f64; 6] = [-20.0, -5.0, -10.0, 10.0, 20.0, -10.0];
const MOVES: usize = 24;
/// CPU and cycles are counted over this window, once every cell streams.
const WINDOW: Duration = Duration::from_secs(4);
const ANSWERED_WITHIN: Duration = Duration::from_secs(30);
const JSON: &str = "Content-Type: application/json\r\n";

fn main() {
    if std::env::args().any(|a| a == "--list") {
        return;
    }
    if let Ok(spec) = std::env::var(CHILD) {
        child(&spec);
        return;
    }
    let sizes = |var: &str, default: &str| -> Vec<usize> {
        std::env::var(var)
            .unwrap_or_else(|_| default.into())
            .split(',')
            .filter_map(|n| n.trim().parse().ok())
            .collect()
    };
    let unpinned = std::env::var("CELLS_UNPINNED").is_ok_and(|v| v == "1");
    let designs: Vec<String> = std::iter::once("thread_per_cell".to_string())
        .chain(sizes("CELLS_THREADS", "1").into_iter().map(shared_design))
        .chain(unpinned.then(|| "shared_unpinned".to_string()))
        .collect();
    let load = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    println!("load average (1, 5, 15 min) at start: {}", load.trim());
    let shield = std::env::var("CELLS_SHIELD")
        .is_ok_and(|v| v == "1")
        .then(rigbridge::realtime::streaming_cpu)
        .flatten()
        .map(shield::Shield::raise);
    let mut rows = Vec::new();
    for (rate, sizes) in [
        (250.0, sizes("CELLS", "1,8,32,128")),
        (1000.0, sizes("CELLS_1KHZ", "1,8,16")),
    ] {
        for n in sizes {
            for design in &designs {
                let row = spawn_child(design, n, rate);
                print_row(&row);
                rows.push(row);
            }
        }
    }
    print_ratios(&rows);
    drop(shield);
    let load = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    println!("load average at end: {}", load.trim());
}

/// The shared executor's design name with `threads` workers: `shared` for the default one.
fn shared_design(threads: usize) -> String {
    match threads {
        1 => "shared".into(),
        n => format!("shared_x{n}"),
    }
}

/// The executor kind, thread count and pinning a design name stands for.
fn executor_of(design: &str) -> (ExecutorKind, usize, bool) {
    match design.strip_prefix("shared") {
        Some("") => (ExecutorKind::Shared, 1, true),
        Some("_unpinned") => (ExecutorKind::Shared, 1, false),
        Some(threads) => (
            ExecutorKind::Shared,
            threads.trim_start_matches("_x").parse().unwrap_or(1),
            true,
        ),
        None => (ExecutorKind::ThreadPerCell, 1, false),
    }
}

fn spawn_child(design: &str, n: usize, rate: f64) -> Value {
    let output = std::process::Command::new(std::env::current_exe().expect("own path"))
        .env(CHILD, format!("{design} {n} {rate}"))
        .stderr(std::process::Stdio::null())
        .output()
        .expect("child bench");
    let text = String::from_utf8_lossy(&output.stdout);
    text.lines()
        .rev()
        .find_map(|line| serde_json::from_str(line).ok())
        .unwrap_or_else(|| json!({"design": design, "cells": n, "rate_hz": rate, "error": text}))
}

fn print_row(row: &Value) {
    if let Some(error) = row.get("error") {
        println!("{row}: FAILED {error}");
        return;
    }
    println!(
        "{:>6} Hz {:>4} cells {:>16}: jitter p50 {:>5} us, p99 {:>5} us (worst cell {:>5} us = {:>5.1} % of the cycle), max {:>6} us; missed {:>5} of {:>7} (per cell {}..{}); overruns {:>3}; log records dropped {}; CPU {:>6.1} us per cell-cycle; {:>5.2} MB per cell; {} of {} completed; machine stalls seen by the idle witnesses, by CPU: {} over 1 ms, {} over the cells' period (longest {} us); executor's own CPUs {}",
        row["rate_hz"],
        row["cells"],
        row["design"].as_str().unwrap_or(""),
        row["p50_median_us"],
        row["p99_median_us"],
        row["p99_worst_us"],
        row["p99_worst_share"].as_f64().unwrap_or(0.0) * 100.0,
        row["max_worst_us"],
        row["missed"],
        row["cycles"],
        row["missed_cell_min"],
        row["missed_cell_max"],
        row["overruns"],
        row["log_dropped"],
        row["cpu_us_per_cell_cycle"].as_f64().unwrap_or(f64::NAN),
        row["mb_per_cell"].as_f64().unwrap_or(f64::NAN),
        row["completed"],
        row["cells"],
        row["witness_stalls"],
        row["witness_over_period"],
        row["witness_max_us"],
        row["executor_cpus"],
    );
}

fn print_ratios(rows: &[Value]) {
    println!("thread per cell / shared, same run:");
    let shared_rows = rows.iter().filter(|r| {
        r["design"]
            .as_str()
            .is_some_and(|d| d.starts_with("shared"))
    });
    for shared in shared_rows {
        let Some(thread) = rows.iter().find(|r| {
            r["design"] == "thread_per_cell"
                && r["cells"] == shared["cells"]
                && r["rate_hz"] == shared["rate_hz"]
        }) else {
            continue;
        };
        let ratio = |key: &str| {
            thread[key].as_f64().unwrap_or(f64::NAN) / shared[key].as_f64().unwrap_or(f64::NAN)
        };
        println!(
            "{:>6} Hz {:>4} cells {:>10}: CPU per cell-cycle x{:.1}, memory per cell x{:.1}, worst p99 jitter x{:.1}",
            shared["rate_hz"],
            shared["cells"],
            shared["design"].as_str().unwrap_or(""),
            ratio("cpu_us_per_cell_cycle"),
            ratio("mb_per_cell"),
            ratio("p99_worst_us"),
        );
    }
}

// ------------------------------------------------------------------ child --

fn child(spec: &str) {
    let mut parts = spec.split(' ');
    let design = parts.next().unwrap_or("shared").to_string();
    let n: usize = parts.next().and_then(|p| p.parse().ok()).unwrap_or(1);
    let rate: f64 = parts.next().and_then(|p| p.parse().ok()).unwrap_or(250.0);
    let base = load_run_settings(Path::new(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/config/rigbridge.toml"
    )))
    .expect("run settings");
    let (executor, threads, pinned) = executor_of(&design);
    let cells: Vec<RunSettings> = (0..n)
        .map(|i| {
            let mut cell = base.clone();
            cell.rig.name = format!("arm{i:03}");
            cell.config.stream.rate_hz = rate;
            cell.config.serve.executor = executor;
            cell.config.serve.executor_threads = threads;
            cell.config.serve.pin_executor = pinned;
            cell
        })
        .collect();
    // Every CPU gets a witness, counted before this thread keeps off some.
    let cpus = std::thread::available_parallelism().map_or(1, |n| n.get());
    // As `rigbridge serve` does before it starts its runtime: this thread, and every thread
    // the daemon starts from it, keeps off the executor's CPUs.
    let executor_cpus = cells[0].config.serve.executor_cpus();
    if !executor_cpus.is_empty() {
        rigbridge::realtime::keep_off_all(&executor_cpus).expect("keep off the executor's CPUs");
    }
    let runs = std::env::temp_dir().join(format!("rigbridge-cells-bench-{}", std::process::id()));
    let rss_before = rss_bytes();
    // Only the cycles are measured: no Foxglove server beside them.
    let options = ServeOptions {
        executor_cpus: executor_cpus.clone(),
        ..in_process::options(runs.clone())
    };
    let served = in_process::start(cells, options);
    let witnesses = Witnesses::start(Duration::from_secs_f64(1.0 / rate), cpus);
    let figures = measure(served.address, n, rate);
    let stalls = witnesses.stop();
    let _ = served.stop();
    let _ = std::fs::remove_dir_all(&runs);
    let mut row = figures.finish(n);
    row["design"] = design.into();
    row["executor_cpus"] = json!(executor_cpus);
    row["rate_hz"] = rate.into();
    let by_cpu = |f: &dyn Fn(&Stalls) -> u64| json!(stalls.iter().map(f).collect::<Vec<_>>());
    row["witness_stalls"] = by_cpu(&|s| s.count);
    row["witness_over_period"] = by_cpu(&|s| s.over_period);
    row["witness_max_us"] = by_cpu(&|s| s.max.as_micros() as u64);
    row["mb_per_cell"] =
        ((figures.rss_streaming.saturating_sub(rss_before)) as f64 / n as f64 / 1e6).into();
    println!("{row}");
}

struct Figures {
    cpu: Duration,
    window_cycles: u64,
    rss_streaming: u64,
    reports: Vec<Value>,
}

fn measure(address: SocketAddr, n: usize, rate: f64) -> Figures {
    let body = job_body();
    for i in 0..n {
        let (code, answer) = call(
            address,
            "POST",
            &format!("/api/cells/arm{i:03}/jobs"),
            &body,
        );
        assert_eq!(code, 202, "{answer}");
    }
    // Every cell streaming: then the window.
    let deadline = Instant::now() + Duration::from_secs(60);
    let first = loop {
        let cycles = cycles_now(address);
        if cycles.len() == n && cycles.iter().all(|c| *c > 0) {
            break cycles;
        }
        assert!(Instant::now() < deadline, "cells did not all start");
        std::thread::sleep(Duration::from_millis(20));
    };
    let cpu_before = cpu_time();
    std::thread::sleep(WINDOW);
    let cpu = cpu_time() - cpu_before;
    let last = cycles_now(address);
    let rss_streaming = rss_bytes();
    assert_eq!(
        last.len(),
        n,
        "a job ended inside the window: make the job longer"
    );
    let window_cycles = last.iter().zip(&first).map(|(b, a)| b - a).sum();
    let _ = rate;
    let reports = (0..n)
        .map(|i| {
            let path = format!("/api/cells/arm{i:03}/status");
            let deadline = Instant::now() + Duration::from_secs(120);
            loop {
                let (_, status) = call(address, "GET", &path, "");
                if status["state"] == "idle" && !status["last"].is_null() {
                    break status["last"].clone();
                }
                assert!(Instant::now() < deadline, "{path} did not end: {status}");
                std::thread::sleep(Duration::from_millis(100));
            }
        })
        .collect();
    Figures {
        cpu,
        window_cycles,
        rss_streaming,
        reports,
    }
}

impl Figures {
    fn finish(&self, n: usize) -> Value {
        let field = |key: &str| -> Vec<f64> {
            let mut values: Vec<f64> = self
                .reports
                .iter()
                .map(|r| r["report"][key].as_f64().unwrap_or(f64::NAN))
                .collect();
            values.sort_by(f64::total_cmp);
            values
        };
        let (p50, p99, max) = (
            field("jitter_p50_us"),
            field("jitter_p99_us"),
            field("jitter_max_us"),
        );
        let rate_cycle_us = |r: &Value| 1e6 / r["report"]["rate_hz"].as_f64().unwrap_or(1.0);
        let worst_share = self
            .reports
            .iter()
            .map(|r| r["report"]["jitter_p99_us"].as_f64().unwrap_or(f64::NAN) / rate_cycle_us(r))
            .fold(0.0, f64::max);
        let sum = |key: &str| -> u64 {
            self.reports
                .iter()
                .map(|r| r["report"][key].as_u64().unwrap_or(0))
                .sum()
        };
        let completed = self
            .reports
            .iter()
            .filter(|r| r["report"]["outcome"] == "completed")
            .count();
        json!({
            "cells": n,
            "p50_median_us": p50[p50.len() / 2],
            "p99_median_us": p99[p99.len() / 2],
            "p99_worst_us": p99[p99.len() - 1],
            "p99_worst_share": worst_share,
            "max_worst_us": max[max.len() - 1],
            "missed": sum("missed_cycles"),
            "missed_cell_min": field("missed_cycles")[0],
            "missed_cell_max": field("missed_cycles")[n - 1],
            "cycles": sum("cycles"),
            "overruns": sum("overruns"),
            // Records the job logs could not keep (a full ring): 0 means every log is whole.
            "log_dropped": self
                .reports
                .iter()
                .map(|r| r["report"]["log"]["dropped"].as_u64().unwrap_or(0))
                .sum::<u64>(),
            "completed": completed,
            "cpu_us_per_cell_cycle": self.cpu.as_secs_f64() * 1e6 / self.window_cycles.max(1) as f64,
        })
    }
}

/// The witness' period, and the lateness that counts as a stall: a 1 kHz cycle's.
const WITNESS_PERIOD: Duration = Duration::from_millis(1);
/// Above the streams' SCHED_FIFO priority (50), so that no cell's work delays a witness.
const WITNESS_PRIORITY: i32 = 51;

/// One idle thread per CPU that only wakes on time (see the module doc).
struct Witnesses {
    stop: std::sync::Arc<std::sync::atomic::AtomicBool>,
    threads: Vec<std::thread::JoinHandle<Stalls>>,
}

/// A witness' late wakes: over a 1 kHz period, over the cells' period, and the latest.
#[derive(Default)]
struct Stalls {
    count: u64,
    over_period: u64,
    max: Duration,
}

impl Witnesses {
    /// A witness on each of CPUs `0..cpus`.
    fn start(cell_period: Duration, cpus: usize) -> Witnesses {
        let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
        let threads = (0..cpus)
            .map(|cpu| {
                let stop = stop.clone();
                std::thread::spawn(move || {
                    let _ = rigbridge::realtime::pin_to(cpu);
                    let _ = rigbridge::realtime::raise_priority(WITNESS_PRIORITY);
                    witness(&stop, cell_period)
                })
            })
            .collect();
        Witnesses { stop, threads }
    }

    /// Each CPU's stalls, in the order of the CPUs.
    fn stop(self) -> Vec<Stalls> {
        self.stop.store(true, std::sync::atomic::Ordering::SeqCst);
        self.threads
            .into_iter()
            .map(|thread| thread.join().unwrap_or_default())
            .collect()
    }
}

/// Wakes every period until told to stop; counts the wakes more than a period late, and
/// more than a cell's period late (a missed cycle's lateness).
fn witness(stop: &std::sync::atomic::AtomicBool, cell_period: Duration) -> Stalls {
    let mut stalls = Stalls::default();
    let mut deadline = Instant::now() + WITNESS_PERIOD;
    while !stop.load(std::sync::atomic::Ordering::SeqCst) {
        std::thread::sleep(deadline.saturating_duration_since(Instant::now()));
        let now = Instant::now();
        let late = now - deadline;
        stalls.count += u64::from(late > WITNESS_PERIOD);
        stalls.over_period += u64::from(late > cell_period);
        stalls.max = stalls.max.max(late);
        deadline = now.max(deadline) + WITNESS_PERIOD;
    }
    stalls
}

fn job_body() -> String {
    let waypoints: Vec<[f64; 6]> = (0..MOVES).map(|i| if i % 2 == 0 { A } else { B }).collect();
    json!({"job": {"kind": "joint_waypoints", "waypoints_deg": waypoints}}).to_string()
}

/// Each streaming cell's cycles so far (cells without a running job are left out).
fn cycles_now(address: SocketAddr) -> Vec<u64> {
    let (_, cells) = call(address, "GET", "/api/cells", "");
    cells["cells"]
        .as_array()
        .map(|cells| {
            cells
                .iter()
                .filter_map(|c| c["job"]["cycles"].as_u64())
                .collect()
        })
        .unwrap_or_default()
}

fn call(address: SocketAddr, method: &str, path: &str, body: &str) -> (u16, Value) {
    let headers = if method == "POST" { JSON } else { "" };
    let (answer, _) = flood::http(address, method, path, headers, body, ANSWERED_WITHIN);
    let (code, body) = answer.unwrap_or_else(|| panic!("{method} {path}: no answer"));
    (code, serde_json::from_str(&body).unwrap_or(Value::Null))
}

/// User and system CPU time of this process so far.
fn cpu_time() -> Duration {
    // SAFETY: getrusage fills the struct it is given; a zeroed rusage is a valid value.
    let usage = unsafe {
        let mut usage: libc::rusage = std::mem::zeroed();
        libc::getrusage(libc::RUSAGE_SELF, &mut usage);
        usage
    };
    let time = |t: libc::timeval| {
        Duration::from_secs(t.tv_sec as u64) + Duration::from_micros(t.tv_usec as u64)
    };
    time(usage.ru_utime) + time(usage.ru_stime)
}

/// This process' resident set, from /proc/self/status.
fn rss_bytes() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .unwrap_or_default()
        .lines()
        .find_map(|line| line.strip_prefix("VmRSS:"))
        .and_then(|kb| kb.trim().trim_end_matches("kB").trim().parse::<u64>().ok())
        .map_or(0, |kb| kb * 1024)
}
