//! Recorder and reader figures for docs/logs.md: bytes per cycle, time to queue a record
//! (what the streaming cycle pays), writer and reader throughput.
//!
//! `cargo bench --bench log`

use rigbridge::log::{LogRecord, Recorder, RecorderOptions, read_log};
use rigbridge::protocol::AxisValues;
use std::time::Instant;

const JOINTS: usize = 6;
const PERIOD: f64 = 0.001;

fn cycle(i: u32) -> (LogRecord, LogRecord) {
    let t = f64::from(i) * PERIOD;
    let q: Vec<f64> = (0..JOINTS)
        .map(|j| 0.9 * ((0.7 + 0.31 * j as f64) * t).sin())
        .collect();
    let v: Vec<f64> = (0..JOINTS)
        .map(|j| 0.9 * (0.7 + 0.31 * j as f64) * ((0.7 + 0.31 * j as f64) * t).cos())
        .collect();
    let measured: Vec<f64> = (0..JOINTS)
        .map(|j| 0.9 * ((0.7 + 0.31 * j as f64) * (t - 0.003)).sin())
        .collect();
    let axes = |values: &[f64]| AxisValues::from_slice(values).expect("6 axes");
    (
        LogRecord::Command {
            seq: i,
            t,
            positions: axes(&q),
            velocities: axes(&v),
            late_us: 0.0,
        },
        LogRecord::State {
            seq: i,
            t,
            positions: axes(&measured),
            velocities: axes(&v),
        },
    )
}

fn main() {
    let path =
        std::env::temp_dir().join(format!("rigbridge-log-bench-{}.mcap", std::process::id()));
    let _ = std::fs::remove_file(&path);
    let cycles = 50_000u32;
    let names: Vec<String> = (1..=JOINTS).map(|i| format!("joint_{i}")).collect();
    let options = RecorderOptions {
        // Room for the whole run, so the figure is the writer's pace, not the drop rate.
        capacity: 2 * cycles as usize + 16,
        ..RecorderOptions::default()
    };
    let recorder = Recorder::create_with(
        &path,
        "arm6",
        &names,
        serde_json::json!({ "bench": true }),
        options,
    )
    .expect("recorder");
    let records: Vec<(LogRecord, LogRecord)> = (0..cycles).map(cycle).collect();
    let start = Instant::now();
    for (command, state) in &records {
        recorder.record(*command);
        recorder.record(*state);
    }
    let queued = start.elapsed();
    let stats = recorder.finish().expect("finish");
    let written = start.elapsed();
    let read_start = Instant::now();
    let log = read_log(&path).expect("read");
    let read = read_start.elapsed();
    assert_eq!(log.commands.len(), cycles as usize);
    let records_n = f64::from(2 * cycles);
    println!(
        "{cycles} cycles ({JOINTS} joints, command + state): {} bytes, {:.1} bytes/cycle",
        stats.bytes,
        stats.bytes as f64 / f64::from(cycles)
    );
    println!(
        "queue {:.0} ns/record; write {:.0} records/s; read {:.0} records/s; dropped {}",
        queued.as_nanos() as f64 / records_n,
        records_n / written.as_secs_f64(),
        records_n / read.as_secs_f64(),
        stats.dropped
    );
    let _ = std::fs::remove_file(&path);
}
