//! The EGM figures: the bridge's EGM link against the EGM twin over UDP on 127.0.0.1 for N
//! seconds (default 60), streaming the default job again and again. Prints the share of
//! robot cycles answered by exactly one EgmSensor, the bridge turnaround (EgmRobot in,
//! EgmSensor out) p50/p99 and the twin's round trip. `cargo run --release --example
//! egm_soak -- 60`. Runs at SCHED_FIFO when allowed, as `rigbridge run` and `twin` do.

use rigbridge::daemon::config::load_run_settings;
use rigbridge::daemon::run_job;
use rigbridge::device::egm::twin::{
    EgmRobotModel, EgmTwin, EgmTwinControl, EgmTwinSettings, spawn_egm_twin,
};
use rigbridge::device::egm::{EgmLinkSettings, bind_egm};
use rigbridge::link::Link;
use rigbridge::stream::StreamControl;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

fn main() -> anyhow::Result<()> {
    let seconds: u64 = std::env::args().nth(1).map_or(Ok(60), |a| a.parse())?;
    if let Err(e) = rigbridge::stream::raise_priority(50) {
        eprintln!("note: normal priority ({e})");
    }
    let settings = load_run_settings(std::path::Path::new("config/rigbridge.toml"))?;
    let period = settings.period();
    let axes = settings.config.egm.axes(&settings.file, &settings.rig)?;
    let egm = EgmLinkSettings::for_rig(&settings.rig, axes.clone(), period, None);
    let mut link = bind_egm("127.0.0.1:0", egm)?;
    let model = EgmRobotModel::new(
        &settings.rig,
        axes,
        EgmTwinSettings::default(),
        &settings.initial(),
    )?;
    let twin = EgmTwin::new(model, link.local_address())?;
    let control = Arc::new(EgmTwinControl::default());
    let twin = spawn_egm_twin(twin, control.clone())?;
    let started = Instant::now();
    while !link.is_up() && started.elapsed() < Duration::from_secs(5) {
        std::thread::sleep(Duration::from_millis(5));
    }
    let clock = link.pacing().ok_or_else(|| anyhow::anyhow!("no pacing"))?;
    let mut jobs = 0;
    while started.elapsed() < Duration::from_secs(seconds) {
        let report = run_job(
            &settings,
            &settings.config.job,
            &mut link,
            clock.as_ref(),
            None,
            &StreamControl::default(),
        )?;
        jobs += 1;
        println!(
            "job {jobs}: {:?}, {} cycles",
            report.stream.outcome, report.stream.cycles
        );
    }
    control.stop.store(true, Ordering::SeqCst);
    let twin = twin.join().map_err(|_| anyhow::anyhow!("twin panicked"))?;
    let c = twin.model().counters;
    let cycles = c.cycles_one_reply + c.cycles_no_reply + c.cycles_several_replies;
    let state = link.state();
    println!(
        "{:.1} s: {} robot messages, {} replies; cycles with exactly one reply {} of {} ({:.3} %), none {}, several {}",
        started.elapsed().as_secs_f64(),
        c.messages_sent,
        c.replies,
        c.cycles_one_reply,
        cycles,
        100.0 * c.cycles_one_reply as f64 / cycles.max(1) as f64,
        c.cycles_no_reply,
        c.cycles_several_replies
    );
    println!(
        "bridge: {} robot messages answered by {} replies; turnaround p50 {:.0} us, p99 {:.0} us, max {:.0} us; underruns {}",
        state.messages,
        state.replies,
        link.turnaround_quantile_us(0.5).unwrap_or(f64::NAN),
        link.turnaround_quantile_us(0.99).unwrap_or(f64::NAN),
        link.turnaround_quantile_us(1.0).unwrap_or(f64::NAN),
        state.underruns
    );
    println!(
        "twin: round trip p99 {:.0} us; its own thread sent late (cycle stretched) {} times",
        twin.round_trip_quantile_us(0.99).unwrap_or(f64::NAN),
        c.host_stalls
    );
    println!(
        "twin refusals: {} outside limits, {} over speed, {} over acceleration, {} axis count; {} comm timeouts",
        c.outside_limits, c.over_speed, c.over_acceleration, c.axis_count, c.comm_timeouts
    );
    Ok(())
}
