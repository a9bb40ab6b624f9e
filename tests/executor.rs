//! The shared executor (issue 18): many cells of one daemon whose cycles run on one
//! real-time thread each complete their job, reported as on a thread of their own; and a
//! stream whose cycle work overruns its budget is counted and handed back to its own thread
//! while its neighbours on the executor complete theirs. Outcomes and counts only: the
//! timing figures are `cargo bench --bench cells`'s. Traffic only ever goes to 127.0.0.1.

use crate::common;
use crate::flood;
use crate::in_process;

use common::repo_path;
use rigbridge::clock::WallClock;
use rigbridge::daemon::config::{ExecutorKind, RunSettings, load_run_settings};
use rigbridge::link::LoopbackLink;
use rigbridge::rig::Rig;
use rigbridge::stream::{
    CycleRecord, CycleSink, Executor, ExecutorSettings, Outcome, StreamControl, StreamReport,
    StreamSettings, slowdown_rate, stream_shared,
};
use rigbridge::trajectory::{PlanSettings, Trajectory, plan_joint_moves};
use rigbridge::twin::{Twin, TwinSettings};
use serde_json::Value;
use std::net::SocketAddr;
use std::time::{Duration, Instant};

const CELLS: usize = 8;
const JSON: &str = "Content-Type: application/json\r\n";
const ANSWERED_WITHIN: Duration = Duration::from_secs(30);

fn call(address: SocketAddr, method: &str, path: &str, body: &str) -> (u16, Value) {
    let headers = if method == "POST" { JSON } else { "" };
    let (answer, _) = flood::http(address, method, path, headers, body, ANSWERED_WITHIN);
    let (code, body) = answer.unwrap_or_else(|| panic!("{method} {path}: no answer"));
    (code, serde_json::from_str(&body).unwrap_or(Value::Null))
}

/// Cell `i`'s target: each cell its own, so a mix-up between cells would show.
fn target_deg(i: usize) -> [f64; 6] {
    let a = 5.0 + 3.0 * i as f64;
    [a, -a / 2.0, a / 3.0, 0.0, 30.0 + a / 2.0, -a]
}

fn arm_cells(executor: ExecutorKind) -> Vec<RunSettings> {
    let base = load_run_settings(&repo_path("config/rigbridge.toml")).unwrap();
    (0..CELLS)
        .map(|i| {
            let mut cell = base.clone();
            cell.rig.name = format!("arm{i}");
            cell.config.serve.executor = executor;
            cell
        })
        .collect()
}

#[test]
fn many_cells_on_the_shared_executor_each_complete_their_job_and_reach_its_target() {
    let runs = std::env::temp_dir().join(format!("rigbridge-executor-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&runs);
    let served = in_process::start(
        arm_cells(ExecutorKind::Shared),
        in_process::options(runs.clone()),
    );
    let address = served.address;
    for i in 0..CELLS {
        let job =
            serde_json::json!({"job": {"kind": "move_joints", "targets_deg": [target_deg(i)]}});
        let (code, answer) = call(
            address,
            "POST",
            &format!("/api/cells/arm{i}/jobs"),
            &job.to_string(),
        );
        assert_eq!(code, 202, "{answer}");
    }
    for i in 0..CELLS {
        let status = wait_idle(address, i);
        let report = &status["last"]["report"];
        assert_eq!(report["outcome"], "completed", "cell {i}: {status}");
        assert_eq!(report["limit_violations"], 0, "cell {i}: {report}");
        assert_eq!(report["rig"], format!("arm{i}"), "{report}");
        // Every planned sample went out, and the log holds a command per cycle sent.
        let planned = report["planned_duration_s"].as_f64().unwrap();
        let cycles = report["cycles"].as_u64().unwrap();
        // (The planned duration is a float: 0.412 s x 250 Hz is 103.00000000000001.)
        assert!(
            cycles >= (planned * 250.0).round() as u64,
            "cell {i}: {report}"
        );
        let log = &report["log"];
        let (commands, dropped) = (
            log["commands"].as_u64().unwrap(),
            log["dropped"].as_u64().unwrap(),
        );
        assert!(
            commands <= cycles && commands + dropped >= cycles,
            "cell {i}: {report}"
        );
        // Completed means the arm got there: the twin holds the cell's own target.
        for (axis, want) in status["actual"]
            .as_array()
            .unwrap()
            .iter()
            .zip(target_deg(i))
        {
            let got = axis["value"].as_f64().unwrap();
            assert!((got - want).abs() <= 0.1, "cell {i}: {axis} against {want}");
        }
    }
    assert!(served.stop().unwrap().is_ok());
    let _ = std::fs::remove_dir_all(&runs);
}

fn wait_idle(address: SocketAddr, i: usize) -> Value {
    let path = format!("/api/cells/arm{i}/status");
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let (_, status) = call(address, "GET", &path, "");
        if status["state"] == "idle" && !status["last"].is_null() {
            return status;
        }
        assert!(Instant::now() < deadline, "{path}: no end: {status}");
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// A sink whose every record takes `work`, as a cell with a slow live view or log would.
struct Slow(Duration);

impl CycleSink for Slow {
    fn record(&mut self, _: &CycleRecord) {
        let start = Instant::now();
        while start.elapsed() < self.0 {
            std::hint::spin_loop();
        }
    }
}

const START: [f64; 6] = [0.0, 0.0, 0.0, 0.0, 0.5, 0.0];
const PERIOD: f64 = 0.004;

fn period() -> std::time::Duration {
    std::time::Duration::from_secs_f64(PERIOD)
}

fn one_move(rig: &Rig, i: usize) -> Trajectory {
    let target: Vec<f64> = target_deg(i).iter().map(|d| d.to_radians()).collect();
    let settings = PlanSettings {
        period: period(),
        ..PlanSettings::default()
    };
    plan_joint_moves(rig, &START, &[target], &settings).unwrap()
}

fn stream_one(
    executor: &Executor,
    rig: &Rig,
    i: usize,
    sink: &mut (dyn CycleSink + Send),
) -> (StreamReport, u64) {
    let twin = Twin::new(
        rig,
        TwinSettings {
            period: period(),
            ..TwinSettings::default()
        },
        &START,
    )
    .unwrap();
    let control = StreamControl::default();
    let settings = StreamSettings::new(period(), slowdown_rate(rig, 0.9, 0.8));
    let report = stream_shared(
        executor,
        &one_move(rig, i),
        rig,
        &mut LoopbackLink::new(twin),
        &WallClock::new(),
        sink,
        &control,
        &settings,
    )
    .unwrap();
    (report, control.overruns())
}

#[test]
fn an_overrunning_stream_is_reported_and_handed_back_while_its_neighbours_complete() {
    let rig = load_run_settings(&repo_path("config/rigbridge.toml"))
        .unwrap()
        .rig;
    let executor = Executor::new(ExecutorSettings::default()).unwrap();
    // Half a cycle of work in every cycle: five times the budget (a tenth of the cycle).
    let slow_work = Duration::from_secs_f64(PERIOD / 2.0);
    let results: Vec<(StreamReport, u64)> = std::thread::scope(|scope| {
        let handles: Vec<_> = (0..CELLS)
            .map(|i| {
                let (executor, rig) = (&executor, &rig);
                scope.spawn(move || {
                    if i == 0 {
                        stream_one(executor, rig, i, &mut Slow(slow_work))
                    } else {
                        stream_one(executor, rig, i, &mut ())
                    }
                })
            })
            .collect();
        handles.into_iter().map(|h| h.join().unwrap()).collect()
    });
    let (slow, slow_overruns) = &results[0];
    // Counted three times in a row, then handed back: its job's thread runs it on (how far
    // it gets on a thread of its own, with half of every cycle spent, is the machine's).
    assert_eq!(slow.overruns, 3, "{slow:?}");
    assert_eq!(*slow_overruns, 3, "the cell's status counts them too");
    assert!(slow.cycles > 3, "it went on after its overrun: {slow:?}");
    assert_eq!(slow.limit_violations, 0, "{slow:?}");
    for (i, (report, _)) in results.iter().enumerate().skip(1) {
        assert_eq!(
            report.outcome,
            Outcome::Completed,
            "neighbour {i}: {report:?}"
        );
        assert_eq!(report.limit_violations, 0, "neighbour {i}: {report:?}");
    }
}

/// `config/rigbridge.toml` with `serve` appended as its `[serve]` table, in a scratch file.
fn settings_with_serve(name: &str, serve: &str) -> std::path::PathBuf {
    let file = common::scratch_file("executor-config", name);
    common::write_settings_with_serve(&file, serve);
    file
}

#[test]
fn the_executor_settings_are_read_and_checked() {
    let shared = load_run_settings(&repo_path("config/rigbridge.toml")).unwrap();
    assert_eq!(
        shared.config.serve.executor,
        ExecutorKind::Shared,
        "the default"
    );
    assert_eq!(shared.config.serve.executor_threads, 1, "the default");
    let file = settings_with_serve(
        "threads.toml",
        "executor = \"thread_per_cell\"\nexecutor_threads = 2",
    );
    let chosen = load_run_settings(&file).unwrap();
    assert_eq!(chosen.config.serve.executor, ExecutorKind::ThreadPerCell);
    assert_eq!(chosen.config.serve.executor_threads, 2);
    let file = settings_with_serve("none.toml", "executor_threads = 0");
    let message = load_run_settings(&file).unwrap_err().to_string();
    assert!(
        message.contains("serve.executor_threads") && message.contains("none.toml"),
        "{message}"
    );
    let file = settings_with_serve("pooled.toml", "executor = \"pooled\"");
    let message = rigbridge::daemon::error_chain(&load_run_settings(&file).unwrap_err());
    assert!(message.contains("pooled"), "{message}");
}
