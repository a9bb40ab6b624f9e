//! `rigbridge twin --canopen IFACE`: the twin's CiA 402 drives as their own process. Prints
//! where they serve first, then one line per event, and what the drives counted when
//! stopped. Owns the arguments' meaning only; the drives are the library's.

use anyhow::Context;
use rigbridge::daemon::config::RunSettings;
use rigbridge::device::canopen::twin::{
    CanopenBus, CanopenPort, CanopenTwinControl, CanopenTwinSettings, serve_canopen,
};
use rigbridge::twin::server::ControllerPort;
use std::process::ExitCode;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

/// Serves drives `nodes` (default 1, 2, ...) on `interface` until `stop`.
pub fn canopen_twin(
    settings: &RunSettings,
    interface: &str,
    nodes: &[u8],
    counts_per_turn: Option<u32>,
    stop: Arc<AtomicBool>,
) -> anyhow::Result<ExitCode> {
    let nodes = super::twin::bus_ids(settings, nodes, "CANopen node ids")?;
    let counts = settings
        .config
        .canopen
        .axes(&settings.file, &settings.rig, counts_per_turn)?;
    let twin = CanopenTwinSettings {
        period: settings.period(),
        bandwidth_hz: settings.config.twin.bandwidth_hz,
    };
    let mut bus = CanopenBus::new(&settings.rig, &nodes, &counts, &settings.initial(), twin)?;
    let mut port = CanopenPort::open(interface)
        .with_context(|| format!("cannot open CAN interface {interface}"))?;
    super::twin::say(&format!(
        "{} nodes {}",
        port.describe(),
        nodes
            .iter()
            .map(u8::to_string)
            .collect::<Vec<_>>()
            .join(",")
    ));
    super::twin::raise_twin_priority();
    let control = Arc::new(CanopenTwinControl::default());
    let watcher = control.clone();
    super::twin::relay_stop(stop, move || watcher.stop.store(true, Ordering::SeqCst));
    read_operator(control.clone());
    serve_canopen(&mut bus, &mut port, &control);
    eprintln!("{}", bus.counters.summary());
    Ok(ExitCode::SUCCESS)
}

/// Operator commands on stdin: `fault AXIS` (axis from 1), a drive's own fault.
fn read_operator(operator: Arc<CanopenTwinControl>) {
    std::thread::spawn(move || {
        for line in std::io::stdin().lines().map_while(Result::ok) {
            let words: Vec<&str> = line.split_whitespace().collect();
            match words.as_slice() {
                ["fault", axis] => match axis.parse::<usize>() {
                    Ok(axis) if axis >= 1 => operator.fault(axis - 1),
                    _ => eprintln!("unknown axis `{axis}` (from 1)"),
                },
                _ => eprintln!("unknown command `{line}` (fault AXIS)"),
            }
        }
    });
}
