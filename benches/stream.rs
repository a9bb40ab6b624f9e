//! Streaming timing on this machine: the loopback twin at 250 Hz for 60 s and at 1 kHz for
//! 10 s, wall clock. Prints missed cycles and jitter percentiles, and checks them against
//! the targets (missed <= 0.1 %, jitter p99 <= 20 % of the period).
//!
//! `cargo bench --bench stream` (add `-- --quick` for 5 s runs).

use rigbridge::clock::WallClock;
use rigbridge::link::LoopbackLink;
use rigbridge::rig::{Rig, load_rig};
use rigbridge::stream::{StreamControl, StreamSettings, slowdown_rate, stream};
use rigbridge::trajectory::Trajectory;
use rigbridge::twin::{Twin, TwinSettings};
use std::path::Path;

const START: [f64; 6] = [0.0, 0.0, 0.0, 0.0, 0.5, 0.0];

/// Every axis swinging gently (0.3 rad amplitude, 0.25 Hz) for `seconds`.
fn swing(rig: &Rig, period: f64, seconds: f64) -> Trajectory {
    let samples = (seconds / period).round() as usize + 1;
    let mut positions = Vec::with_capacity(samples * 6);
    let mut velocities = Vec::with_capacity(samples * 6);
    let omega = std::f64::consts::TAU * 0.25;
    for i in 0..samples {
        let t = i as f64 * period;
        for start in START {
            let amplitude = 0.3 * (1.0 - (omega * t).cos()) / 2.0;
            positions.push(start + amplitude);
            velocities.push(0.3 * omega * (omega * t).sin() / 2.0);
        }
    }
    let names = rig.joint_names().map(String::from).collect();
    Trajectory::new(rig.name.clone(), names, period, positions, velocities).expect("well-formed")
}

fn run(rig: &Rig, rate_hz: f64, seconds: f64) -> bool {
    let period = 1.0 / rate_hz;
    let twin = Twin::new(
        rig,
        TwinSettings {
            period_s: period,
            ..TwinSettings::default()
        },
        &START,
    )
    .expect("twin");
    let settings = StreamSettings::new(period, slowdown_rate(rig, 0.9, 0.8));
    let report = stream(
        &swing(rig, period, seconds),
        rig,
        &mut LoopbackLink::new(twin),
        &WallClock::new(),
        &mut (),
        &StreamControl::default(),
        &settings,
    )
    .expect("stream");
    let missed_share = report.missed_cycles as f64 / report.cycles as f64;
    let p99_share = report.jitter_p99_us / (period * 1e6);
    let ok = missed_share <= 0.001 && p99_share <= 0.2;
    println!(
        "{rate_hz:>6.0} Hz x {seconds:>4.0} s: {} cycles, missed {} ({:.3} %), jitter p50 {:.0} us, p99 {:.0} us ({:.1} % of period), max {:.0} us -> {}",
        report.cycles,
        report.missed_cycles,
        missed_share * 100.0,
        report.jitter_p50_us,
        report.jitter_p99_us,
        p99_share * 100.0,
        report.jitter_max_us,
        if ok {
            "within target"
        } else {
            "OUTSIDE TARGET"
        }
    );
    ok
}

fn main() {
    match rigbridge::stream::raise_priority(50) {
        Ok(()) => println!("streaming at SCHED_FIFO priority 50"),
        Err(e) => println!("streaming at normal priority (SCHED_FIFO refused: {e})"),
    }
    let quick = std::env::args().any(|a| a == "--quick");
    let rig = load_rig(Path::new(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/config/irb120.toml"
    )))
    .expect("rig");
    let (long, short) = if quick { (5.0, 5.0) } else { (60.0, 10.0) };
    let results = [run(&rig, 250.0, long), run(&rig, 1000.0, short)];
    if results.contains(&false) {
        std::process::exit(1);
    }
}
