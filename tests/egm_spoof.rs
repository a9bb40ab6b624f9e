//! An EGM session is bound to one robot (docs/egm.md, "Who the bridge answers"): forged
//! EgmRobot datagrams from other ports (replayed copies of real ones, motors off, far
//! feedback, a "ready" at 90 deg) during a job move nothing and are counted in the status
//! and the report; a replay from the robot's own address is dropped; a far jump from it
//! stops the job; a second robot on an unnamed session stops the job; an EGM restart
//! (seqno 0) is a new session, not a replay. Everything over real UDP on 127.0.0.1 against
//! the EGM twin, judged from the twin's side (the references it received) and from the
//! forgers' (the answers they got).

use crate::common;
use crate::flood;
use crate::in_process;

use common::cycles::{one_at_a_time, real_time, wait_for};
use common::shipped_run_settings;

use prost::Message;
use rigbridge::daemon::config::{RunSettings, load_run_settings};
use rigbridge::daemon::{RunReport, run_job};
use rigbridge::device::egm::twin::{
    EgmRobotModel, EgmTwin, EgmTwinControl, EgmTwinCounters, EgmTwinSettings, spawn_egm_twin,
};
use rigbridge::device::egm::wire::{
    EgmAxes, EgmClock, EgmMciState, EgmMotorState, EgmRobot, MciState, MotorState,
};
use rigbridge::device::egm::{EgmLink, EgmLinkSettings, bind_egm};
use rigbridge::link::Link;
use rigbridge::stream::{Outcome, StreamControl};
use std::collections::VecDeque;
use std::net::{SocketAddr, UdpSocket};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// Patience for conditions that take a few robot cycles on an idle machine.
const PATIENCE: Duration = Duration::from_secs(10);
/// The figure: forged datagrams sent during one job.
const FORGED: u64 = 10_000;
/// Forged datagrams sent together, and the pause between bursts: 10,000 in about 4 s, well
/// inside the default job's 7 s, a few per robot cycle (a burst far smaller than the
/// socket's receive buffer, so the kernel keeps them all).
const BURST: u64 = 5;
const BURST_PAUSE: Duration = Duration::from_millis(2);
/// Sockets the forgeries come from.
const FORGER_PORTS: usize = 8;
/// Real messages kept for replaying: 4 s of robot cycles.
const CAPTURED: usize = 1000;
/// The default star job's cycles at 250 Hz (docs/egm.md's figures).
const STAR_CYCLES: u64 = 1774;
/// Cycles into the job before the forgeries start, so they land while it streams.
const FORGE_AFTER_CYCLES: u64 = 100;
/// A revolute axis' value far from anywhere the star job goes: joint_1 at 90 deg.
const FAR_DEG: f64 = 90.0;

fn axes(settings: &RunSettings) -> EgmAxes {
    settings
        .config
        .egm
        .axes(&settings.file, &settings.rig)
        .expect("the EGM axes")
}

/// A twin of the settings' robot sending to `sensor`; its session outlives any start-up
/// wait of a test (the CommTimeout case is tests/egm.rs').
fn twin_towards(settings: &RunSettings, sensor: SocketAddr) -> (EgmTwin, Arc<EgmTwinControl>) {
    let egm = EgmTwinSettings {
        comm_timeout: Duration::from_secs(30),
        ..EgmTwinSettings::default()
    };
    let model =
        EgmRobotModel::new(&settings.rig, axes(settings), egm, &settings.initial()).expect("model");
    (
        EgmTwin::new(model, sensor).expect("twin socket"),
        Arc::new(EgmTwinControl::default()),
    )
}

fn spawn(twin: EgmTwin, control: &Arc<EgmTwinControl>) -> std::thread::JoinHandle<EgmTwin> {
    spawn_egm_twin(twin, control.clone()).expect("twin thread")
}

fn stop(twin: std::thread::JoinHandle<EgmTwin>, control: &EgmTwinControl) -> EgmTwin {
    control.stop.store(true, Ordering::SeqCst);
    twin.join().expect("twin thread")
}

/// From the twin's side: no reference it received was outside a limit, over a speed or an
/// acceleration, or of the wrong axis count, and it got no more answers than it sent
/// messages (an answer to a forgery from the robot's address would reach it too; one cycle's
/// answer landing in the next on a loaded host is not one).
fn assert_no_bad_reference(counters: &EgmTwinCounters) {
    assert_eq!(counters.violations(), 0, "{counters:?}");
    assert!(counters.replies <= counters.messages_sent, "{counters:?}");
}

/// A UDP relay between the twin and the bridge, so that the test holds real EgmRobot
/// messages to replay and can send from the robot's own address: the twin sends to
/// `twin_side`, the bridge sees the robot at `robot_side`.
struct Relay {
    robot_side: UdpSocket,
    bridge: SocketAddr,
    captured: Arc<Mutex<VecDeque<Vec<u8>>>>,
    forwarded: Arc<AtomicU64>,
    stop: Arc<AtomicBool>,
    threads: Vec<std::thread::JoinHandle<()>>,
    twin_side: SocketAddr,
}

impl Relay {
    fn start(bridge: SocketAddr) -> Relay {
        let bind = || {
            let socket = UdpSocket::bind("127.0.0.1:0").expect("relay socket");
            socket
                .set_read_timeout(Some(Duration::from_millis(50)))
                .expect("timeout");
            socket
        };
        let (robot_side, twin_facing) = (bind(), bind());
        let twin_side = twin_facing.local_addr().expect("address");
        let captured = Arc::new(Mutex::new(VecDeque::with_capacity(CAPTURED)));
        let forwarded = Arc::new(AtomicU64::new(0));
        let stop = Arc::new(AtomicBool::new(false));
        let twin_address = Arc::new(Mutex::new(None::<SocketAddr>));
        let up = {
            let (to_bridge, from_twin) = (
                robot_side.try_clone().expect("clone"),
                twin_facing.try_clone().expect("clone"),
            );
            let (captured, forwarded, stop, twin_address) = (
                captured.clone(),
                forwarded.clone(),
                stop.clone(),
                twin_address.clone(),
            );
            std::thread::spawn(move || {
                let mut buffer = [0u8; 2048];
                while !stop.load(Ordering::SeqCst) {
                    let Ok((len, from)) = from_twin.recv_from(&mut buffer) else {
                        continue;
                    };
                    *twin_address.lock().expect("lock") = Some(from);
                    if to_bridge.send_to(&buffer[..len], bridge).is_ok() {
                        forwarded.fetch_add(1, Ordering::SeqCst);
                    }
                    let mut kept = captured.lock().expect("lock");
                    if kept.len() == CAPTURED {
                        kept.pop_front();
                    }
                    kept.push_back(buffer[..len].to_vec());
                }
            })
        };
        let down = {
            let (from_bridge, to_twin) = (robot_side.try_clone().expect("clone"), twin_facing);
            let stop = stop.clone();
            std::thread::spawn(move || {
                let mut buffer = [0u8; 2048];
                while !stop.load(Ordering::SeqCst) {
                    let Ok((len, _)) = from_bridge.recv_from(&mut buffer) else {
                        continue;
                    };
                    if let Some(twin) = *twin_address.lock().expect("lock") {
                        let _ = to_twin.send_to(&buffer[..len], twin);
                    }
                }
            })
        };
        Relay {
            robot_side,
            bridge,
            captured,
            forwarded,
            stop,
            threads: vec![up, down],
            twin_side,
        }
    }

    /// The robot's address as the bridge sees it.
    fn robot(&self) -> SocketAddr {
        self.robot_side.local_addr().expect("address")
    }

    /// The real message `back` messages before the newest (0: the newest).
    fn real(&self, back: usize) -> EgmRobot {
        let kept = self.captured.lock().expect("lock");
        let bytes = &kept[kept.len().saturating_sub(1 + back)];
        EgmRobot::decode(&bytes[..]).expect("a real EgmRobot")
    }

    /// Real messages passed on to the bridge so far.
    fn forwarded(&self) -> u64 {
        self.forwarded.load(Ordering::SeqCst)
    }

    fn captured(&self) -> usize {
        self.captured.lock().expect("lock").len()
    }

    /// Sends `message` to the bridge from the robot's own address.
    fn inject(&self, message: &EgmRobot) {
        self.robot_side
            .send_to(&message.encode_to_vec(), self.bridge)
            .expect("send");
    }

    fn finish(self) {
        self.stop.store(true, Ordering::SeqCst);
        for thread in self.threads {
            thread.join().expect("relay thread");
        }
    }
}

/// The kinds of forgery, in turn.
#[derive(Clone, Copy)]
enum Forgery {
    /// A real message from up to 4 s ago, as it was.
    Replay,
    /// The newest real message with the motors off and EGM stopped.
    MotorsOff,
    /// The newest real message, one step on, with joint_1 at 90 deg.
    FarFeedback,
    /// A new EGM session (seqno 0), motors on and running, at 90 deg.
    ReadyFar,
}

const FORGERIES: [Forgery; 4] = [
    Forgery::Replay,
    Forgery::MotorsOff,
    Forgery::FarFeedback,
    Forgery::ReadyFar,
];

/// `message` `ahead` robot cycles on (seqno, tm and robot time), with joint_1 at
/// [`FAR_DEG`].
fn far(mut message: EgmRobot, ahead: u32) -> EgmRobot {
    let header = message.header.as_mut().expect("a header");
    header.seqno = header.seqno.map(|seqno| seqno.wrapping_add(ahead));
    header.tm = header.tm.map(|tm| tm.wrapping_add(4 * ahead));
    let feedback = message.feed_back.as_mut().expect("feedback");
    if let Some(time) = feedback.time.as_mut() {
        let us = time.sec * 1_000_000 + time.usec + 4_000 * u64::from(ahead);
        *time = EgmClock {
            sec: us / 1_000_000,
            usec: us % 1_000_000,
        };
    }
    feedback.joints.as_mut().expect("joints").joints[0] = FAR_DEG;
    message
}

fn forge(relay: &Relay, kind: Forgery, n: u64) -> EgmRobot {
    match kind {
        Forgery::Replay => relay.real(25 + (n as usize * 7) % (relay.captured() - 26)),
        Forgery::MotorsOff => {
            let mut message = relay.real(0);
            message.motor_state = Some(EgmMotorState {
                state: MotorState::Off as i32,
            });
            message.mci_state = Some(EgmMciState {
                state: MciState::Stopped as i32,
            });
            message
        }
        Forgery::FarFeedback => far(relay.real(0), 1),
        Forgery::ReadyFar => {
            let mut message = far(relay.real(0), 1);
            message.header.as_mut().expect("a header").seqno = Some(0);
            message.motor_state = Some(EgmMotorState {
                state: MotorState::On as i32,
            });
            message.mci_state = Some(EgmMciState {
                state: MciState::Running as i32,
            });
            message
        }
    }
}

/// Sends [`FORGED`] forgeries to the bridge from [`FORGER_PORTS`] other ports; the number of
/// datagrams the bridge sent back to them (it must send none).
fn forge_from_other_ports(relay: &Relay) -> u64 {
    let forgers: Vec<UdpSocket> = (0..FORGER_PORTS)
        .map(|_| {
            let socket = UdpSocket::bind("127.0.0.1:0").expect("forger socket");
            socket.set_nonblocking(true).expect("nonblocking");
            socket
        })
        .collect();
    let mut answered = 0;
    let mut buffer = [0u8; 2048];
    for n in 0..FORGED {
        let message = forge(relay, FORGERIES[n as usize % FORGERIES.len()], n);
        let socket = &forgers[n as usize % FORGER_PORTS];
        socket
            .send_to(&message.encode_to_vec(), relay.bridge)
            .expect("send");
        if n % BURST == BURST - 1 {
            std::thread::sleep(BURST_PAUSE);
        }
        answered += forgers
            .iter()
            .map(|s| std::iter::from_fn(|| s.recv_from(&mut buffer).ok()).count() as u64)
            .sum::<u64>();
    }
    std::thread::sleep(Duration::from_millis(50));
    answered
        + forgers
            .iter()
            .map(|s| std::iter::from_fn(|| s.recv_from(&mut buffer).ok()).count() as u64)
            .sum::<u64>()
}

/// Datagrams the kernel dropped for full receive buffers, machine-wide (/proc/net/snmp's
/// Udp RcvbufErrors): what the bridge could not have counted.
fn udp_receive_buffer_errors() -> u64 {
    let snmp = std::fs::read_to_string("/proc/net/snmp").unwrap_or_default();
    let mut udp = snmp.lines().filter(|l| l.starts_with("Udp:"));
    let (Some(names), Some(values)) = (udp.next(), udp.next()) else {
        return 0;
    };
    names
        .split_whitespace()
        .zip(values.split_whitespace())
        .find(|(name, _)| *name == "RcvbufErrors")
        .and_then(|(_, v)| v.parse().ok())
        .unwrap_or(0)
}

/// A loopback UDP port free a moment ago, for a link that binds later.
fn free_udp_port() -> SocketAddr {
    UdpSocket::bind("127.0.0.1:0")
        .expect("probe")
        .local_addr()
        .expect("address")
}

/// The shipped settings with `[stream] link = link`, written to a file of their own.
fn settings_with_link(name: &str, link: &str) -> RunSettings {
    let path = common::scratch_file("egm_spoof", name);
    let text = common::shipped_settings_text()
        .replace("link = \"loopback\"", &format!("link = \"{link}\""));
    assert!(text.contains(link), "the shipped settings name their link");
    std::fs::write(&path, text).expect("write");
    load_run_settings(&path).expect("the settings load")
}

fn call(address: SocketAddr, method: &str, path: &str) -> (u16, serde_json::Value) {
    let headers = if method == "POST" {
        "Content-Type: application/json\r\n"
    } else {
        ""
    };
    let (answer, _) = flood::http(address, method, path, headers, "", PATIENCE);
    let (code, body) = answer.expect("an answer");
    (
        code,
        serde_json::from_str(&body).unwrap_or(serde_json::Value::Null),
    )
}

fn count(value: &serde_json::Value, key: &str) -> u64 {
    value[key]
        .as_u64()
        .unwrap_or_else(|| panic!("{key} in {value}"))
}

#[test]
fn ten_thousand_forged_datagrams_from_other_ports_move_nothing_and_are_counted() {
    if !common::in_full_tier(
        "egm_spoof::ten_thousand_forged_datagrams_from_other_ports_move_nothing_and_are_counted",
    ) {
        return;
    }
    let _cycles = one_at_a_time();
    real_time();
    let bridge = free_udp_port();
    let relay = Relay::start(bridge);
    let link = format!("egm://{bridge}?robot={}", relay.robot());
    let settings = settings_with_link("forged.toml", &link);
    let (twin, control) = twin_towards(&settings, relay.twin_side);
    let twin = spawn(twin, &control);
    let runs = common::scratch_dir("egm_spoof", "forged-runs");
    let served = in_process::start(vec![settings.clone()], in_process::options(runs));
    let address = served.address;
    let (code, started) = call(address, "POST", "/api/jobs");
    assert_eq!(code, 202, "{started}");
    wait_for("the job to stream", PATIENCE, || {
        let (_, status) = call(address, "GET", "/api/status");
        status["job"]["cycles"].as_u64().unwrap_or(0) >= FORGE_AFTER_CYCLES
    });
    let dropped_before = udp_receive_buffer_errors();
    let answered = forge_from_other_ports(&relay);
    let kernel_dropped = udp_receive_buffer_errors() - dropped_before;
    // While the job streams, the status shows the counts.
    let (_, during) = call(address, "GET", "/api/status");
    assert_eq!(
        during["state"], "running",
        "the forgeries outlasted the job: {during}"
    );
    let shown = count(&during["link_counters"], "foreign_dropped");
    wait_for("the job's end", Duration::from_secs(30), || {
        call(address, "GET", "/api/status").1["state"] == "idle"
    });
    let (_, after) = call(address, "GET", "/api/status");
    served.stop().expect("server task").expect("server");
    let twin = stop(twin, &control);
    let real = relay.forwarded();
    relay.finish();

    let report = &after["last"]["report"];
    assert_eq!(report["outcome"], "completed", "{after}");
    let counted = count(report, "foreign_dropped");
    println!(
        "forged {FORGED}: counted {counted} in the report ({} in the status during the job, {} after), kernel dropped {kernel_dropped}, answered {answered}; twin {:?}",
        shown,
        count(&after["link_counters"], "foreign_dropped"),
        twin.model().counters
    );
    assert!(
        counted <= FORGED && counted + kernel_dropped >= FORGED,
        "{report}"
    );
    assert!(shown > 0 && shown <= counted, "{during}");
    assert_eq!(count(&after["link_counters"], "foreign_dropped"), counted);
    // 0 adopted: no forgery was answered, none of their motor states or positions taken
    // (no session restarted, the arm stayed on its path), nothing from the robot's own
    // source was out of order or out of reach.
    assert_eq!(answered, 0, "the bridge answered forgeries");
    let taken = count(&after["link_counters"], "frames_received");
    assert!(
        taken <= real,
        "{taken} messages taken, {real} real ones sent"
    );
    assert_eq!(count(report, "reconnects"), 0, "{report}");
    assert_eq!(count(report, "replays_dropped"), 0, "{report}");
    assert_eq!(count(report, "feedback_jumps"), 0, "{report}");
    assert_eq!(
        count(report, "second_robots"),
        0,
        "a named robot's intruders are only counted"
    );
    let tracking = report["tracking_error_max_deg"].as_f64().expect("tracking");
    assert!(
        tracking < 5.0,
        "{tracking} deg: a forged position was taken"
    );
    // 0 references over a limit, from the twin's side.
    let counters = twin.model().counters;
    assert_no_bad_reference(&counters);
    assert_eq!(counters.sessions, 1, "{counters:?}");
    assert_eq!(counters.comm_timeouts, 0, "{counters:?}");
}

/// A link on loopback bound as `robot` says, its twin's relay, and the twin.
struct Bench {
    link: EgmLink,
    relay: Relay,
    twin: std::thread::JoinHandle<EgmTwin>,
    control: Arc<EgmTwinControl>,
}

fn bench(settings: &RunSettings, named: bool) -> Bench {
    let socket = free_udp_port();
    let relay = Relay::start(socket);
    let robot = named.then(|| relay.robot());
    let egm = EgmLinkSettings::for_rig(&settings.rig, axes(settings), settings.period(), robot);
    let link = bind_egm(&socket.to_string(), egm).expect("bind");
    let (twin, control) = twin_towards(settings, relay.twin_side);
    let twin = spawn(twin, &control);
    wait_for("the EGM session", PATIENCE, || link.is_up());
    Bench {
        link,
        relay,
        twin,
        control,
    }
}

/// Runs the settings' job over `link` on a thread of its own; its control and handle.
fn job_on_a_thread(
    settings: &RunSettings,
    mut link: EgmLink,
) -> (
    Arc<StreamControl>,
    std::thread::JoinHandle<(RunReport, EgmLink)>,
) {
    let control = Arc::new(StreamControl::default());
    let (settings, job_control) = (settings.clone(), control.clone());
    let handle = std::thread::spawn(move || {
        let clock = link.pacing().expect("an EGM link paces the streamer");
        let job = settings.config.job.clone();
        let report = run_job(
            &settings,
            &job,
            &mut link,
            clock.as_ref(),
            None,
            &job_control,
        )
        .expect("the job runs");
        (report, link)
    });
    (control, handle)
}

#[test]
fn a_replay_from_the_robot_s_own_address_is_dropped_and_the_job_completes() {
    if !common::in_full_tier(
        "egm_spoof::a_replay_from_the_robot_s_own_address_is_dropped_and_the_job_completes",
    ) {
        return;
    }
    let _cycles = one_at_a_time();
    real_time();
    let settings = shipped_run_settings();
    let Bench {
        link,
        relay,
        twin,
        control,
    } = bench(&settings, false);
    let (job, handle) = job_on_a_thread(&settings, link);
    wait_for("the job to stream", PATIENCE, || {
        job.cycles() >= FORGE_AFTER_CYCLES
    });
    wait_for("1.2 s of real messages", PATIENCE, || {
        relay.captured() >= 300
    });
    // Real messages of 0.1 .. 1 s ago, from the robot's own address, one a cycle.
    let replays: Vec<EgmRobot> = (25..250).step_by(9).map(|back| relay.real(back)).collect();
    for message in &replays {
        relay.inject(message);
        std::thread::sleep(Duration::from_millis(4));
    }
    let (report, link) = handle.join().expect("job thread");
    let twin = stop(twin, &control);
    relay.finish();
    assert_eq!(report.stream.outcome, Outcome::Completed, "{report:?}");
    let counters = link.counters();
    assert_eq!(
        counters.replays_dropped,
        replays.len() as u64,
        "{counters:?}"
    );
    assert_eq!(
        report.stream.counters.replays_dropped,
        counters.replays_dropped
    );
    assert_eq!(counters.feedback_jumps, 0, "{counters:?}");
    // Not answered: an answer would have reached the twin as a second one in its cycle.
    assert_no_bad_reference(&twin.model().counters);
}

#[test]
fn a_far_jump_from_the_robot_s_own_address_stops_the_job_at_rest() {
    if !common::in_full_tier(
        "egm_spoof::a_far_jump_from_the_robot_s_own_address_stops_the_job_at_rest",
    ) {
        return;
    }
    let _cycles = one_at_a_time();
    real_time();
    let settings = shipped_run_settings();
    let Bench {
        link,
        relay,
        twin,
        control,
    } = bench(&settings, true);
    let (job, handle) = job_on_a_thread(&settings, link);
    wait_for("the job to stream", PATIENCE, || {
        job.cycles() >= FORGE_AFTER_CYCLES
    });
    // A message of the robot's, numbered 0.4 s ahead (so it is in order whenever it comes),
    // with joint_1 at 90 deg.
    relay.inject(&far(relay.real(0), 100));
    let (report, link) = handle.join().expect("job thread");
    let twin = stop(twin, &control);
    relay.finish();
    assert_eq!(report.stream.outcome, Outcome::Faulted, "{report:?}");
    let fault = report.stream.fault.clone().unwrap_or_default();
    assert!(
        fault.contains("joint_1") && fault.contains("jumped"),
        "{fault}"
    );
    assert!(report.stream.cycles < STAR_CYCLES, "{report:?}");
    assert_eq!(link.counters().feedback_jumps, 1);
    assert_eq!(report.stream.counters.feedback_jumps, 1);
    // Brought to rest along the path, every reference within the limits.
    assert_no_bad_reference(&twin.model().counters);
    assert!(
        twin.model().position()[0].to_degrees() < FAR_DEG / 2.0,
        "the arm went where the forgery said"
    );
}

#[test]
fn a_second_robot_on_an_unnamed_session_is_reported_and_stops_the_job_at_rest() {
    if !common::in_full_tier(
        "egm_spoof::a_second_robot_on_an_unnamed_session_is_reported_and_stops_the_job_at_rest",
    ) {
        return;
    }
    let _cycles = one_at_a_time();
    real_time();
    let settings = shipped_run_settings();
    let Bench {
        link,
        relay,
        twin,
        control,
    } = bench(&settings, false);
    let bridge = relay.bridge;
    let (job, handle) = job_on_a_thread(&settings, link);
    wait_for("the job to stream", PATIENCE, || {
        job.cycles() >= FORGE_AFTER_CYCLES
    });
    // Another robot, a whole twin of its own, sends to the same sensor port.
    let (other, other_control) = twin_towards(&settings, bridge);
    let other_address = other.local_address().expect("address");
    let other = spawn(other, &other_control);
    let (report, link) = handle.join().expect("job thread");
    let other = stop(other, &other_control);
    let twin = stop(twin, &control);
    relay.finish();
    assert_eq!(report.stream.outcome, Outcome::Faulted, "{report:?}");
    let fault = report.stream.fault.clone().unwrap_or_default();
    let port = format!(":{}", other_address.port());
    assert!(
        fault.contains("second robot") && fault.contains(&port),
        "{fault}"
    );
    assert!(report.stream.cycles < STAR_CYCLES, "{report:?}");
    let counters = link.counters();
    assert_eq!(counters.second_robots, 1, "{counters:?}");
    assert!(counters.foreign_dropped > 0, "{counters:?}");
    assert_eq!(report.stream.counters.second_robots, 1);
    // The other robot got no answer; ours was brought to rest within its limits.
    assert_eq!(other.model().counters.replies, 0);
    assert_no_bad_reference(&twin.model().counters);
}

#[test]
fn an_egm_restart_at_seqno_zero_is_a_new_session_not_a_replay() {
    if !common::in_full_tier(
        "egm_spoof::an_egm_restart_at_seqno_zero_is_a_new_session_not_a_replay",
    ) {
        return;
    }
    let _cycles = one_at_a_time();
    let settings = shipped_run_settings();
    let Bench {
        link,
        relay,
        twin,
        control,
    } = bench(&settings, true);
    wait_for("0.2 s of messages", PATIENCE, || relay.captured() >= 50);
    let before = relay.real(0).seqno().expect("a seqno");
    control.motors_off();
    wait_for("motors off", PATIENCE, || !link.is_up());
    control.motors_on();
    wait_for("the new EGM session", PATIENCE, || link.is_up());
    // The twin numbered the new session from 0 again (as abb_libegm expects).
    let after = relay.real(0).seqno().expect("a seqno");
    let twin = stop(twin, &control);
    relay.finish();
    assert!(
        after < before,
        "seqno {after} after the restart, {before} before"
    );
    assert_eq!(link.counters().replays_dropped, 0, "{:?}", link.counters());
    assert_eq!(link.state().sessions, 2, "{:?}", link.state());
    assert_eq!(twin.model().counters.sessions, 2);
}
