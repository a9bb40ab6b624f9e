//! `rigbridge twin --dynamixel --pty | --serial PATH`: the twin's Dynamixel servos as
//! their own process. Prints where to connect first, then one line per event, and what the
//! servos counted when stopped. Owns the arguments' meaning only; the bus is the library's.

use anyhow::Context;
use rigbridge::daemon::config::RunSettings;
use rigbridge::device::dynamixel::twin::{
    DynamixelBus, DynamixelTwinControl, DynamixelTwinSettings, serve_dynamixel,
};
use rigbridge::twin::serial_port::SerialControllerPort;
use rigbridge::twin::server::ControllerPort;
use std::process::ExitCode;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

/// Serves the bus on `serial` (path, baud), or on a new pty when `None`.
pub fn dynamixel_twin(
    settings: &RunSettings,
    ids: &[u8],
    serial: Option<(String, u32)>,
    stop: Arc<AtomicBool>,
) -> anyhow::Result<ExitCode> {
    let ids = super::twin::bus_ids(settings, ids, "Dynamixel ids")?;
    let ticks = settings
        .config
        .dynamixel
        .axes(&settings.file, &settings.rig)?;
    let twin = DynamixelTwinSettings {
        period: settings.period(),
        bandwidth_hz: settings.config.twin.bandwidth_hz,
    };
    let mut bus = DynamixelBus::new(&settings.rig, &ids, &ticks, &settings.initial(), twin)?;
    let mut port: Box<dyn ControllerPort> = match serial {
        Some((path, baud)) => {
            let serial = settings.config.stream.serial_settings(&path, baud);
            let port = SerialControllerPort::open(&serial)
                .with_context(|| format!("cannot open {path}"))?;
            super::twin::say(&port.describe());
            Box::new(port)
        }
        None => {
            let (port, path) =
                SerialControllerPort::pty().context("cannot open a pseudo-terminal")?;
            super::twin::say(&path);
            Box::new(port)
        }
    };
    super::twin::raise_twin_priority();
    let control = Arc::new(DynamixelTwinControl::default());
    let watcher = control.clone();
    super::twin::relay_stop(stop, move || watcher.stop.store(true, Ordering::SeqCst));
    read_operator(control.clone());
    serve_dynamixel(&mut bus, port.as_mut(), &control);
    let c = bus.counters;
    eprintln!(
        "Dynamixel twin stopped: {} packets, {} CRC errors, {} statuses ({} with an error), {} pings, {} sync writes, {} sync reads, {} goals; {} outside limits, {} over speed, {} over acceleration, {} stale goals at torque on",
        c.packets,
        c.crc_errors,
        c.statuses_sent,
        c.errors_answered,
        c.pings,
        c.sync_writes,
        c.sync_reads,
        c.goals,
        c.outside_limits,
        c.over_speed,
        c.over_acceleration,
        c.stale_goal_at_torque_on
    );
    Ok(ExitCode::SUCCESS)
}

/// Operator commands on stdin: `hardware error AXIS HEXBITS` (axis from 1), as an
/// overload (0x20) or overheating (0x04) would set.
fn read_operator(operator: Arc<DynamixelTwinControl>) {
    std::thread::spawn(move || {
        // `hardware error AXIS BITS`: a servo's fault, as an overload or overheating sets.
        for line in std::io::stdin().lines().map_while(Result::ok) {
            let words: Vec<&str> = line.split_whitespace().collect();
            let parsed = match words.as_slice() {
                ["hardware", "error", axis, bits] => axis
                    .parse::<usize>()
                    .ok()
                    .filter(|a| *a >= 1)
                    .zip(u8::from_str_radix(bits.trim_start_matches("0x"), 16).ok()),
                _ => None,
            };
            match parsed {
                Some((axis, bits)) => operator.hardware_error(axis - 1, bits),
                None => eprintln!("unknown command `{line}` (hardware error AXIS HEXBITS)"),
            }
        }
    });
}
