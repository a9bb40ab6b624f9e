//! `rigbridge twin`: the simulated controller as its own process, on the far side of a real
//! transport. Prints where to connect as its first line of stdout, then one line per event.

use anyhow::Context;
use clap::Args;
use rigbridge::clock::WallClock;
use rigbridge::daemon::config::{RunSettings, load_run_settings};
use rigbridge::daemon::twin_settings;
use rigbridge::device::ours::can_port::{CanPort, CanPortStats};
use rigbridge::protocol::CanSender;
use rigbridge::twin::Twin;
use rigbridge::twin::serial_port::SerialControllerPort;
use rigbridge::twin::server::{ControllerPort, TcpPort, serve_twin};
use std::io::Write;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

/// How often a signal's stop flag is looked at on the twin's behalf: well under what a
/// person notices after Ctrl-C.
const STOP_POLL: Duration = Duration::from_millis(20);

#[derive(Args)]
#[command(group(clap::ArgGroup::new("transport").required(true).args(["listen", "serial", "pty", "can", "egm", "canopen"])))]
pub struct TwinArgs {
    /// Rig and twin settings (servo model, initial position, cycle).
    #[arg(long, env = "RIGBRIDGE_CONFIG", default_value = rigbridge::rig::shipped::DEFAULT_RUN_SETTINGS)]
    config: PathBuf,
    /// Serve TCP: tcp://HOST:PORT (port 0 picks a free one).
    #[arg(long)]
    listen: Option<String>,
    /// Serve on a serial device.
    #[arg(long)]
    serial: Option<PathBuf>,
    /// The serial line's baud rate, with --serial.
    #[arg(long, default_value_t = rigbridge::device::ours::DEFAULT_BAUD)]
    baud: u32,
    /// Open a pseudo-terminal pair and serve on it; its path is the first line printed.
    #[arg(long)]
    pty: bool,
    /// Serve on a SocketCAN interface.
    #[arg(long)]
    can: Option<String>,
    /// Play an ABB controller running EGM joint mode for the sensor at udp://ADDR:PORT.
    /// Reads `motors off`, `motors on` and `start` (EGMRunJoint again) from stdin.
    #[arg(long)]
    egm: Option<String>,
    /// EGM: EGMSetupUC \CommTimeout, ms.
    #[arg(long, default_value_t = 1000)]
    comm_timeout_ms: u64,
    /// EGM: EGMActJoint MaxSpeedDeviation, deg/s.
    #[arg(long, default_value_t = 25.0)]
    max_speed_deviation_deg_s: f64,
    /// EGM: EGMActJoint \LpFilter, Hz (0: no filter).
    #[arg(long, default_value_t = 20.0)]
    lp_filter_hz: f64,
    /// EGM: EGMRunJoint \PosCorrGain, 0 to 1.
    #[arg(long, default_value_t = 1.0)]
    pos_corr_gain: f64,
    /// EGM: pose mode (EGMActPose): follow planned.cartesian, solving the joints with the
    /// project's IK, instead of joint mode.
    #[arg(long)]
    pose: bool,
    /// EGM: start with the motors off.
    #[arg(long)]
    motors_off: bool,
    /// Play Dynamixel Protocol 2.0 servos, one per axis, on --pty or --serial
    /// (docs/dynamixel.md), instead of rigbridge's protocol.
    #[arg(long)]
    pub dynamixel: bool,
    /// Dynamixel: the servo ids in axis order (default 1, 2, ... one per axis).
    #[arg(long, value_delimiter = ',')]
    pub ids: Vec<u8>,
    /// Play CiA 402 drives in cyclic synchronous position mode, one per axis, on this
    /// SocketCAN interface (docs/canopen.md), instead of rigbridge's protocol. Reads
    /// `fault AXIS` from stdin.
    #[arg(long)]
    pub canopen: Option<String>,
    /// CANopen: the node ids in axis order (default 1, 2, ... one per axis).
    #[arg(long, value_delimiter = ',')]
    pub nodes: Vec<u8>,
    /// CANopen: counts a turn of every axis unless `[canopen]` says otherwise.
    #[arg(long)]
    pub counts_per_turn: Option<u32>,
    /// Cycles without a target before holding, and cycles of silence that count as link
    /// loss (docs/protocol.md 6.5); default: the config's `[twin] watchdog_cycles`.
    #[arg(long)]
    watchdog_cycles: Option<u32>,
}

pub fn stop_on_signals() -> anyhow::Result<Arc<AtomicBool>> {
    let stop = Arc::new(AtomicBool::new(false));
    let flag = stop.clone();
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    std::thread::spawn(move || {
        runtime.block_on(async {
            let mut terminate =
                match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
                    Ok(signal) => signal,
                    Err(_) => return,
                };
            tokio::select! {
                _ = tokio::signal::ctrl_c() => {}
                _ = terminate.recv() => {}
            }
            flag.store(true, Ordering::SeqCst);
        });
    });
    Ok(stop)
}

/// The ids a bus twin serves: `given`, or 1, 2, ... one per axis of the rig (`what` names
/// them in the error: a rig with more axes than ids).
pub fn bus_ids(settings: &RunSettings, given: &[u8], what: &str) -> anyhow::Result<Vec<u8>> {
    if !given.is_empty() {
        return Ok(given.to_vec());
    }
    (1..=settings.rig.dof())
        .map(|i| u8::try_from(i).with_context(|| format!("too many axes for {what}")))
        .collect()
}

/// Real-time scheduling for the twin's loop, or a note that it runs without.
pub fn raise_twin_priority() {
    if let Err(e) = rigbridge::stream::raise_priority(rigbridge::realtime::CYCLE_PRIORITY) {
        eprintln!("note: twin at normal priority (real-time scheduling refused: {e})");
    }
}

/// Sets the twin's own stop flag (`twin_stop`, which its loop reads) once `stop` is set.
pub fn relay_stop(stop: Arc<AtomicBool>, twin_stop: impl FnOnce() + Send + 'static) {
    std::thread::spawn(move || {
        while !stop.load(Ordering::SeqCst) {
            std::thread::sleep(STOP_POLL);
        }
        twin_stop();
    });
}

pub fn say(line: &str) {
    let mut out = std::io::stdout().lock();
    let _ = writeln!(out, "{line}");
    let _ = out.flush();
}

pub fn twin(args: TwinArgs) -> anyhow::Result<ExitCode> {
    let settings =
        load_run_settings(&args.config).with_context(|| super::settings_context(&args.config))?;
    if let Some(sensor) = &args.egm {
        return egm_twin(&args, sensor, &settings);
    }
    if let Some(interface) = &args.canopen {
        return super::canopen::canopen_twin(
            &settings,
            interface,
            &args.nodes,
            args.counts_per_turn,
            stop_on_signals()?,
        );
    }
    if args.dynamixel {
        let serial = args
            .serial
            .as_ref()
            .map(|p| (p.display().to_string(), args.baud));
        return super::dynamixel::dynamixel_twin(&settings, &args.ids, serial, stop_on_signals()?);
    }
    protocol_twin(&args, &settings)
}

/// The twin speaking rigbridge's protocol on the transport `args` names, until a signal.
fn protocol_twin(
    args: &TwinArgs,
    settings: &rigbridge::daemon::config::RunSettings,
) -> anyhow::Result<ExitCode> {
    let mut twin_config = twin_settings(settings);
    if let Some(cycles) = args.watchdog_cycles {
        anyhow::ensure!(
            cycles >= 1,
            "--watchdog-cycles must be at least 1, not {cycles}"
        );
        twin_config.watchdog_cycles = cycles;
    }
    let mut twin = Twin::new(&settings.rig, twin_config, &settings.initial())?.with_io(
        rigbridge::twin::TwinIo::in_cell(
            &settings.rig,
            &settings.cell,
            settings.period().as_secs_f64(),
        ),
    );
    if let Some(watch) = rigbridge::daemon::contact_watch(settings)? {
        twin = twin.with_contacts(watch);
    }
    let (mut port, can_stats) = open_port(args, settings)?;
    let stop = stop_on_signals()?;
    raise_twin_priority();
    let counters = serve_twin(
        &mut twin,
        port.as_mut(),
        settings.period(),
        &WallClock::new(),
        &stop,
    );
    eprintln!(
        "twin stopped after {} cycles: {} frames, {} CRC errors, {} malformed, {} connections, {} link losses, {} hellos, {} targets dropped before a hello",
        counters.cycles,
        counters.frames_received,
        counters.crc_errors,
        counters.malformed,
        counters.connections,
        counters.link_losses,
        counters.hellos,
        counters.unbound_targets
    );
    if let Some(contacts) = twin.take_contacts() {
        eprintln!("contacts: {}", serde_json::to_string(&contacts)?);
    }
    if let Some(stats) = can_stats {
        eprintln!("{}", stats.summary());
    }
    Ok(ExitCode::SUCCESS)
}

/// A controller port, and a CAN port's statistics.
type OpenedPort = (Box<dyn ControllerPort>, Option<Arc<CanPortStats>>);

/// The controller's end of the transport `args` names, its address said on stdout; a CAN
/// port's statistics too, for the summary.
fn open_port(
    args: &TwinArgs,
    settings: &rigbridge::daemon::config::RunSettings,
) -> anyhow::Result<OpenedPort> {
    let opened: OpenedPort = match (&args.listen, &args.serial, args.pty, &args.can) {
        (Some(listen), ..) => {
            let address = listen.strip_prefix("tcp://").unwrap_or(listen);
            let port =
                TcpPort::bind(address).with_context(|| format!("cannot listen on {listen}"))?;
            say(&format!("tcp://{}", port.local_address()?));
            (Box::new(port), None)
        }
        (None, Some(path), ..) => {
            let settings = settings
                .config
                .stream
                .serial_settings(&path.display().to_string(), args.baud);
            let port = SerialControllerPort::open(&settings)
                .with_context(|| format!("cannot open {}", path.display()))?;
            say(&port.describe());
            (Box::new(port), None)
        }
        (None, None, true, _) => {
            let (port, path) =
                SerialControllerPort::pty().context("cannot open a pseudo-terminal")?;
            say(&path);
            (Box::new(port), None)
        }
        (None, None, false, Some(interface)) => {
            let mapping = settings.config.stream.can_mapping(CanSender::Controller)?;
            let port = CanPort::open(interface, mapping)
                .with_context(|| format!("cannot open CAN interface {interface}"))?;
            say(&port.describe());
            let stats = port.stats();
            (Box::new(port), Some(stats))
        }
        _ => anyhow::bail!(
            "choose what the twin plays: one of {}",
            rigbridge::device::twin_flags()
        ),
    };
    Ok(opened)
}

/// `--egm`: the EGM twin, with operator commands on stdin.
fn egm_twin(
    args: &TwinArgs,
    sensor: &str,
    settings: &rigbridge::daemon::config::RunSettings,
) -> anyhow::Result<ExitCode> {
    use rigbridge::device::egm::twin::{
        EgmMode, EgmRobotModel, EgmTwin, EgmTwinControl, EgmTwinSettings,
    };
    let address = sensor.strip_prefix("udp://").unwrap_or(sensor);
    let sensor: std::net::SocketAddr = address
        .parse()
        .with_context(|| format!("--egm needs udp://ADDR:PORT, got {sensor}"))?;
    let egm = EgmTwinSettings {
        period: settings.period(),
        comm_timeout: Duration::from_millis(args.comm_timeout_ms),
        gain_per_s: std::f64::consts::TAU * settings.config.twin.bandwidth_hz,
        max_speed_deviation: args.max_speed_deviation_deg_s.to_radians(),
        lp_filter_hz: args.lp_filter_hz,
        pos_corr_gain: args.pos_corr_gain,
        delay: settings.twin_delay(),
        mode: if args.pose {
            EgmMode::Pose
        } else {
            EgmMode::Joint
        },
        motors_on: !args.motors_off,
    };
    let axes = settings.config.egm.axes(&settings.file, &settings.rig)?;
    let solver = rigbridge::ik::FabrikSolver::new(settings.rig.clone())?;
    let model = EgmRobotModel::new(&settings.rig, axes, egm, &settings.initial())?
        .with_pose_solver(Box::new(solver));
    let mut twin = EgmTwin::new(model, sensor)?;
    let local = twin.local_address().context("no local address")?;
    say(&format!("udp://{local} -> udp://{sensor}"));
    let control = Arc::new(EgmTwinControl::default());
    let stop = stop_on_signals()?;
    let watcher = control.clone();
    relay_stop(stop, move || watcher.stop.store(true, Ordering::SeqCst));
    let operator = control.clone();
    std::thread::spawn(move || {
        for line in std::io::stdin().lines().map_while(Result::ok) {
            match line.trim() {
                "motors off" => operator.motors_off(),
                "motors on" => operator.motors_on(),
                "start" => operator.start_session(),
                other => eprintln!("unknown command `{other}` (motors off, motors on, start)"),
            }
        }
    });
    raise_twin_priority();
    twin.run(&control);
    let c = twin.model().counters;
    eprintln!(
        "EGM twin stopped: {} messages, {} replies; cycles with one reply {}, none {}, several {}; refused: {} outside limits, {} wrong axis count, {} poses out of reach; followed: {} over speed, {} over acceleration, {} repeated; {} comm timeouts, {} sessions, {} host stalls",
        c.messages_sent,
        c.replies,
        c.cycles_one_reply,
        c.cycles_no_reply,
        c.cycles_several_replies,
        c.outside_limits,
        c.axis_count,
        c.unreachable,
        c.over_speed,
        c.over_acceleration,
        c.repeated,
        c.comm_timeouts,
        c.sessions,
        c.host_stalls
    );
    Ok(ExitCode::SUCCESS)
}

#[cfg(test)]
mod tests {
    use super::TwinArgs;
    use clap::Args;

    /// Every flag the device backends list for the twin is one of its arguments, so the
    /// twin's command line and the one list of protocols agree.
    #[test]
    fn every_backend_flag_is_a_twin_argument() {
        let command = TwinArgs::augment_args(clap::Command::new("twin"));
        let longs: Vec<&str> = command
            .get_arguments()
            .filter_map(|argument| argument.get_long())
            .collect();
        for backend in rigbridge::device::BACKENDS {
            for flag in backend.twin_flags() {
                let name = flag.trim_start_matches("--");
                assert!(longs.contains(&name), "rigbridge twin has no {flag}");
            }
        }
    }
}
