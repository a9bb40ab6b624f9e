//! The CANopen link: rigbridge as the NMT master, SYNC producer and SDO client of one
//! CiA 402 drive per axis in cyclic synchronous position mode, on SocketCAN
//! (`canopen://vcan0?nodes=1,2,3,4,5,6&counts_per_turn=1048576`).
//!
//! An I/O thread owns the socket. On every open it sets the drives up (docs/canopen.md):
//! NMT reset communication (a drive that booted before the bridge is never waited for: it
//! is reset, and read until it answers), device type 0x1000 checked, 0x6060 = 8 (CSP),
//! 0x60C2 = the stream period, RPDO1 = controlword 0x6040 + target 0x607A and TPDO1 =
//! statusword 0x6041 + position actual 0x6064, both synchronous, remapped by the CiA 301
//! procedure, heartbeat 0x1017 asked of each drive and consumed here; then NMT start,
//! 0x607A seeded from 0x6064, and the power state machine stepped (0x06, 0x07, 0x0F) with
//! the statusword checked at each step.
//!
//! Each command from the streamer is one SYNC cycle: a Target sends every drive its RPDO1
//! (controlword 0x0F and the target in counts), then the SYNC; the drives' TPDO1s are the
//! feedback. So the SYNC period is the stream period and the stream's cycle is the SYNC's
//! clock. Between jobs the thread sends a SYNC each period on its own, as a CSP drive
//! expects. A statusword with the fault bit or out of operation enabled, an EMCY, a
//! heartbeat missing for [`HEARTBEAT_LOST_FACTOR`] producer times or a drive leaving
//! operational latches a drive fault (`LinkEvent::Fault` and a faulted status) until a
//! Reset: a fault-reset edge on controlword bit 7 and the power steps again. A target
//! whose counts do not fit a drive's range is refused before anything is written, never
//! clamped. It owns the bus and the cycle; it must not plan or check speeds.

use super::canopen_wire::{
    DRIVE_PROFILE, PDO_INVALID, PowerState, RPDO1_ENTRIES, STATUS_FAULT, SYNCHRONOUS_EVERY_SYNC,
    SdoAnswer, TPDO1_ENTRIES, Value, cob, controlword, interpolation_period, nmt_command,
    nmt_state, object, rpdo1, sdo_download, sdo_upload, tpdo1,
};
use super::dynamixel_wire::AxisTicks;
use super::{CanBus, Link, LinkCounters, LinkError, LinkEvent};
use crate::protocol::codec::{EncodeError, FaultReport};
use crate::protocol::{AxisValues, CanPayload, Command, ControllerStatus, Fault, Feedback};
use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};
use thiserror::Error;

/// Cycles in a row with a TPDO missing that mean the bus is lost: 25, the streamer's own
/// patience (0.1 s at 250 Hz) for a silent controller.
pub const LOST_AFTER_CYCLES: u32 = 25;
/// A drive whose heartbeat is missing for this many producer times is lost (CiA 301
/// 7.2.8.3.2.1: the consumer time must exceed the producer time; 3 leaves room for two
/// late heartbeats on a loaded host).
pub const HEARTBEAT_LOST_FACTOR: u32 = 3;
/// How long an SDO request waits for its answer (CiA 301 leaves it to the client): set-up
/// is not cyclic, and a drive simulated in Python under emulation answers in tens of ms.
const SDO_TIMEOUT: Duration = Duration::from_millis(300);
/// SDO requests are retried this often before the open counts as failed.
const SDO_ATTEMPTS: u32 = 3;
/// How long opening a link may wait for the set-up beyond the usual reconnect timeout:
/// six drives take about 400 SDO exchanges (a few seconds on a host under load).
pub const SETUP_PATIENCE: Duration = Duration::from_secs(30);
/// How long a drive may take to answer after NMT reset communication (its boot-up).
const BOOT_PATIENCE: Duration = Duration::from_secs(3);
/// How long a power step may take to show in the statusword.
const STEP_PATIENCE: Duration = Duration::from_millis(500);
/// Between jobs a SYNC goes out every period; while streaming only after this many periods
/// without a command: [`LOST_AFTER_CYCLES`], when the streamer has given up on the link
/// (a SYNC without a new target in the middle of a motion would be a stop at full speed).
const IDLE_SYNC_PERIODS_STREAMING: u32 = LOST_AFTER_CYCLES;
/// Share of a period the thread waits for the TPDOs after a SYNC.
const COLLECT_SHARE: f64 = 0.8;
/// A SYNC interval over this many periods while streaming is an overrun (a SYNC slot was
/// missed).
const OVERRUN_PERIODS: f64 = 1.5;
/// A drive within this of its target has settled (rad): a few counts of a 20-bit encoder,
/// well under the streamer's goal tolerance.
const SETTLED_RAD: f64 = 5e-5;
/// How often the I/O thread wakes without commands to notice the link was dropped.
const POLL: Duration = Duration::from_millis(50);
const BACKOFF_INITIAL: Duration = Duration::from_millis(10);
const BACKOFF_MAX: Duration = Duration::from_secs(1);
/// Commands waiting for the bus: the streamer sends one a cycle and waits for its answer.
const QUEUE_CAPACITY: usize = 16;
/// Power steps at most from any state to operation enabled (quick stop, disabled, ready,
/// switched on, enabled).
const MAX_POWER_STEPS: usize = 5;

/// What the link needs to know: the interface, the drives in axis order and their count
/// maps, the axes' limits (to check each target fits a drive's range) and the cycle.
#[derive(Debug, Clone, PartialEq)]
pub struct CanopenSettings {
    pub interface: String,
    pub nodes: Vec<u8>,
    /// Per axis: counts = zero + rad * counts_per_turn / 2 pi.
    pub axes: Vec<AxisTicks>,
    /// Per axis (lower, upper), rad.
    pub limits: Vec<(f64, f64)>,
    /// The stream period: the SYNC period and 0x60C2.
    pub period: Duration,
    /// The heartbeat producer time asked of each drive (0x1017), ms.
    pub heartbeat_ms: u16,
}

#[derive(Debug, Clone, PartialEq, Error)]
pub enum CanopenError {
    #[error("{nodes} node ids for {axes} axes: give one node id per axis, in axis order")]
    NodeCount { nodes: usize, axes: usize },
    #[error("node id {0} is not a CANopen node id (1 to 127) or appears twice")]
    BadNode(u8),
    #[error(
        "axis {axis}: its limits are counts {low} .. {high}, outside a drive's 32-bit position range"
    )]
    OutOfRange { axis: usize, low: f64, high: f64 },
    #[error(
        "a {period_us} us period has no interpolation period 0x60C2 (1 to 255 ms, 100 us, 10 us or us)"
    )]
    Period { period_us: u128 },
    #[error("heartbeat_ms must be at least 1")]
    Heartbeat,
}

/// Why a set-up or a cycle could not go on.
#[derive(Debug)]
enum BusError {
    /// The socket failed or a drive did not answer: reopen and set up again.
    Lost(String),
    /// A drive refused or reported an error: latch a fault on this axis.
    Drive { axis: usize, text: String },
}

#[derive(Debug, Clone, Copy)]
enum Job {
    /// RPDO1 of these targets (counts) then SYNC; the target's seq.
    Targets(u32, [i32; crate::protocol::MAX_AXES]),
    /// SYNC only; true for Stop (the drives hold their target).
    Sync { holding: bool },
    /// Quick stop on every drive, and latch the e-stop.
    EStop,
    /// Fault reset (controlword bit 7 edge) and the power steps again.
    Reset,
}

struct State {
    queue: VecDeque<Job>,
    up: bool,
    sessions: u64,
    adopted: u64,
    feedback: Option<Feedback>,
    generation: u64,
    events: VecDeque<LinkEvent>,
    counters: LinkCounters,
    latched: Option<Fault>,
    restart: bool,
    problem: Option<String>,
}

struct Shared {
    state: Mutex<State>,
    feedback: Condvar,
    command: Condvar,
    closed: AtomicBool,
    settings: CanopenSettings,
    /// SYNCs sent, and those more than [`OVERRUN_PERIODS`] after the one before while
    /// streaming.
    syncs: AtomicU64,
    overruns: AtomicU64,
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, State> {
        // A panicking holder leaves plain data behind: keep using it.
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }
}

pub struct CanopenLink {
    shared: Arc<Shared>,
    seen: u64,
    description: String,
    thread: Option<std::thread::JoinHandle<()>>,
}

/// Checks `settings` and starts the I/O thread, which opens the interface and sets the
/// drives up in the background (and again after every loss).
pub fn connect_canopen(settings: CanopenSettings) -> Result<CanopenLink, LinkError> {
    check_settings(&settings).map_err(|e| LinkError::Closed(e.to_string()))?;
    let description = format!(
        "canopen://{}?nodes={}",
        settings.interface,
        settings
            .nodes
            .iter()
            .map(u8::to_string)
            .collect::<Vec<_>>()
            .join(",")
    );
    let shared = Arc::new(Shared {
        state: Mutex::new(State {
            queue: VecDeque::with_capacity(QUEUE_CAPACITY),
            up: false,
            sessions: 0,
            adopted: 0,
            feedback: None,
            generation: 0,
            events: VecDeque::new(),
            counters: LinkCounters::default(),
            latched: None,
            restart: false,
            problem: None,
        }),
        feedback: Condvar::new(),
        command: Condvar::new(),
        closed: AtomicBool::new(false),
        settings,
        syncs: AtomicU64::new(0),
        overruns: AtomicU64::new(0),
    });
    let io = shared.clone();
    let thread = std::thread::Builder::new()
        .name("rigbridge-canopen".into())
        .spawn(move || keep_open(&io))?;
    Ok(CanopenLink {
        shared,
        seen: 0,
        description,
        thread: Some(thread),
    })
}

pub fn check_settings(settings: &CanopenSettings) -> Result<(), CanopenError> {
    let axes = settings.axes.len();
    if settings.nodes.len() != axes || settings.limits.len() != axes {
        return Err(CanopenError::NodeCount {
            nodes: settings.nodes.len(),
            axes,
        });
    }
    for (i, &node) in settings.nodes.iter().enumerate() {
        if !(1..=127).contains(&node) || settings.nodes[..i].contains(&node) {
            return Err(CanopenError::BadNode(node));
        }
    }
    for (axis, (counts, (lower, upper))) in settings.axes.iter().zip(&settings.limits).enumerate() {
        let (low, high) = (counts.tick(*lower), counts.tick(*upper));
        if low.min(high) < f64::from(i32::MIN) || low.max(high) > f64::from(i32::MAX) {
            return Err(CanopenError::OutOfRange {
                axis: axis + 1,
                low,
                high,
            });
        }
    }
    if interpolation_period(settings.period).is_none() {
        return Err(CanopenError::Period {
            period_us: settings.period.as_micros(),
        });
    }
    if settings.heartbeat_ms == 0 {
        return Err(CanopenError::Heartbeat);
    }
    Ok(())
}

impl Drop for CanopenLink {
    fn drop(&mut self) {
        self.shared.closed.store(true, Ordering::SeqCst);
        self.shared.command.notify_all();
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

impl CanopenLink {
    /// Why the last open or set-up failed, if one did.
    pub fn problem(&self) -> Option<String> {
        self.shared.lock().problem.clone()
    }

    /// SYNCs sent so far, and the overruns among them (a SYNC more than 1.5 periods after
    /// the one before while streaming).
    pub fn syncs(&self) -> (u64, u64) {
        (
            self.shared.syncs.load(Ordering::Relaxed),
            self.shared.overruns.load(Ordering::Relaxed),
        )
    }

    fn push(&mut self, job: Job) -> Result<(), LinkError> {
        let mut state = self.shared.lock();
        if state.queue.len() >= QUEUE_CAPACITY {
            return Err(LinkError::Io(std::io::Error::other(
                "CANopen command queue full: the bus is behind the streamer",
            )));
        }
        if matches!(job, Job::EStop | Job::Sync { holding: true }) {
            // Targets planned before a Stop or EStop are stale: never sent.
            state.queue.retain(|j| !matches!(j, Job::Targets(..)));
        }
        state.queue.push_back(job);
        drop(state);
        self.shared.command.notify_all();
        Ok(())
    }

    /// The targets of `positions` in counts, or the first that does not fit (never clamped).
    fn targets(&self, positions: &[f64]) -> Result<[i32; crate::protocol::MAX_AXES], EncodeError> {
        let mut counts = [0i32; crate::protocol::MAX_AXES];
        for (axis, (map, &rad)) in self.shared.settings.axes.iter().zip(positions).enumerate() {
            let count = map.tick(rad);
            if !count.is_finite() || count < f64::from(i32::MIN) || count > f64::from(i32::MAX) {
                return Err(EncodeError::OutOfRange {
                    field: "target position (0x607A) counts",
                    value: count,
                    range: "a drive's 32-bit position range",
                });
            }
            counts[axis] = count as i32;
        }
        Ok(counts)
    }
}

impl Link for CanopenLink {
    fn send(&mut self, command: &Command) -> Result<(), LinkError> {
        match command {
            Command::Target(target) => {
                let state = self.shared.lock();
                // A target for another session (planned before the drives were set up
                // anew), or while a fault is latched, is never written.
                if !state.up || state.sessions != state.adopted || state.latched.is_some() {
                    return Ok(());
                }
                drop(state);
                match self.targets(target.positions.as_slice()) {
                    Ok(counts) => self.push(Job::Targets(target.seq, counts)),
                    Err(e) => {
                        let mut state = self.shared.lock();
                        state.events.push_back(LinkEvent::EncodeFailed(e));
                        Ok(())
                    }
                }
            }
            Command::Stop => self.push(Job::Sync { holding: true }),
            Command::EStop => self.push(Job::EStop),
            Command::Reset => self.push(Job::Reset),
            Command::Heartbeat => {
                self.adopt_session();
                self.push(Job::Sync { holding: false })
            }
        }
    }

    fn receive(&mut self, timeout: Duration) -> Result<Option<Feedback>, LinkError> {
        let deadline = Instant::now() + timeout;
        let mut state = self.shared.lock();
        loop {
            if state.generation > self.seen {
                self.seen = state.generation;
                return Ok(state.feedback);
            }
            let now = Instant::now();
            if now >= deadline {
                return Ok(None);
            }
            state = self
                .shared
                .feedback
                .wait_timeout(state, deadline - now)
                .unwrap_or_else(|p| p.into_inner())
                .0;
        }
    }

    fn counters(&self) -> LinkCounters {
        self.shared.lock().counters
    }

    fn describe(&self) -> String {
        self.description.clone()
    }

    fn is_up(&self) -> bool {
        self.shared.lock().up
    }

    fn drain(&mut self) {
        self.seen = self.shared.lock().generation;
    }

    fn next_event(&mut self) -> Option<LinkEvent> {
        self.shared.lock().events.pop_front()
    }

    fn sessions(&self) -> u64 {
        self.shared.lock().sessions
    }

    fn restart(&mut self) {
        self.shared.lock().restart = true;
        self.shared.command.notify_all();
    }

    fn adopt_session(&mut self) {
        let mut state = self.shared.lock();
        state.adopted = state.sessions;
    }
}

/// The socket, and what the bus said besides the answers being waited for.
struct Bus {
    can: CanBus,
    /// Per axis: when its heartbeat was last heard, and whether one has said operational
    /// since NMT start (a heartbeat sent before the start may still be read after it).
    heartbeats: Vec<(Instant, bool)>,
    /// When the drives were started (NMT start).
    started: Instant,
    /// Faults heard in passing (EMCY, a heartbeat out of operational), per axis.
    heard: Vec<(usize, String)>,
    /// Whether the drives should be operational (after NMT start).
    operational: bool,
}

impl Bus {
    fn open(interface: &str) -> Result<Self, BusError> {
        let can = CanBus::open_classic(interface)
            .map_err(|e| BusError::Lost(format!("cannot open {interface}: {e}")))?;
        Ok(Self {
            can,
            heartbeats: Vec::new(),
            started: Instant::now(),
            heard: Vec::new(),
            operational: false,
        })
    }

    fn send(&self, shared: &Shared, id: u32, data: &[u8]) -> Result<(), BusError> {
        let mut frame = CanPayload {
            id,
            data: [0; 64],
            len: data.len() as u8,
            fd: false,
        };
        frame.data[..data.len()].copy_from_slice(data);
        self.can
            .send_patiently(&frame, super::SEND_PATIENCE)
            .map_err(|e| BusError::Lost(format!("cannot send {id:#05x}: {e}")))?;
        shared.lock().counters.frames_sent += 1;
        Ok(())
    }

    /// The next frame before `deadline` that is not an EMCY or a heartbeat (those are
    /// noted); `None` when none came.
    fn next_frame(
        &mut self,
        shared: &Shared,
        deadline: Instant,
    ) -> Result<Option<CanPayload>, BusError> {
        loop {
            let frame = self
                .can
                .try_receive()
                .map_err(|e| BusError::Lost(format!("cannot read: {e}")))?;
            if let Some(frame) = frame {
                shared.lock().counters.frames_received += 1;
                if !self.observe(shared, &frame) {
                    return Ok(Some(frame));
                }
                continue;
            }
            let now = Instant::now();
            if now >= deadline {
                return Ok(None);
            }
            self.can
                .wait_readable(deadline - now)
                .map_err(|e| BusError::Lost(format!("cannot wait for frames: {e}")))?;
        }
    }

    /// Notes an EMCY or heartbeat of one of our drives; true when the frame was one.
    fn observe(&mut self, shared: &Shared, frame: &CanPayload) -> bool {
        let (function, node) = cob::split(frame.id);
        let Some(axis) = shared.settings.nodes.iter().position(|&n| n == node) else {
            return false;
        };
        let data = &frame.data[..usize::from(frame.len)];
        match function {
            cob::EMCY if !data.is_empty() => {
                if let Ok(emcy) = canopen_rs::EmergencyMessage::decode(data)
                    && !emcy.is_error_reset()
                {
                    self.heard.push((
                        axis,
                        format!(
                            "node {node} (axis {}): EMCY {:#06x}, error register {:#04x}",
                            axis + 1,
                            emcy.error_code,
                            emcy.error_register.0
                        ),
                    ));
                }
                true
            }
            cob::HEARTBEAT if data.len() == 1 => {
                let state = data[0] & 0x7F;
                let confirmed = match self.heartbeats.get_mut(axis) {
                    Some(entry) => {
                        let was = entry.1;
                        entry.0 = Instant::now();
                        entry.1 |= state == nmt_state::OPERATIONAL;
                        was
                    }
                    None => false,
                };
                if self.operational && confirmed && state != nmt_state::OPERATIONAL {
                    let what = if state == nmt_state::BOOT_UP {
                        "booted (boot-up message)".to_string()
                    } else {
                        format!("left operational (NMT state {state:#04x})")
                    };
                    self.heard
                        .push((axis, format!("node {node} (axis {}): {what}", axis + 1)));
                }
                true
            }
            _ => false,
        }
    }

    /// One SDO exchange with `axis`' drive, retried on silence; aborts are drive errors.
    fn sdo(
        &mut self,
        shared: &Shared,
        axis: usize,
        request: [u8; 8],
        at: (u16, u8),
    ) -> Result<SdoAnswer, BusError> {
        let node = shared.settings.nodes[axis];
        for _ in 0..SDO_ATTEMPTS {
            self.send(shared, cob::SDO_RX + u32::from(node), &request)?;
            let deadline = Instant::now() + SDO_TIMEOUT;
            while let Some(frame) = self.next_frame(shared, deadline)? {
                if frame.id != cob::SDO_TX + u32::from(node) {
                    continue;
                }
                match SdoAnswer::parse(&frame.data[..usize::from(frame.len)]) {
                    Some(SdoAnswer::Aborted(got, code)) if got == at => {
                        return Err(BusError::Drive {
                            axis,
                            text: format!(
                                "node {node} (axis {}): SDO abort {code:#010x} on {:#06x}:{}",
                                axis + 1,
                                at.0,
                                at.1
                            ),
                        });
                    }
                    Some(answer @ (SdoAnswer::Written(got) | SdoAnswer::Read(got, ..)))
                        if got == at =>
                    {
                        return Ok(answer);
                    }
                    _ => {}
                }
            }
        }
        Err(BusError::Lost(format!(
            "node {node} (axis {}): no SDO answer for {:#06x}:{}",
            axis + 1,
            at.0,
            at.1
        )))
    }

    fn write(
        &mut self,
        shared: &Shared,
        axis: usize,
        at: (u16, u8),
        value: Value,
    ) -> Result<(), BusError> {
        let request = sdo_download(at, &value).ok_or_else(|| BusError::Drive {
            axis,
            text: format!(
                "{:#06x}:{}: value too long for an expedited SDO",
                at.0, at.1
            ),
        })?;
        self.sdo(shared, axis, request, at).map(|_| ())
    }

    /// Reads `at` as a little-endian integer (sign-extended when `signed`).
    fn read(
        &mut self,
        shared: &Shared,
        axis: usize,
        at: (u16, u8),
        signed: bool,
    ) -> Result<i64, BusError> {
        match self.sdo(shared, axis, sdo_upload(at), at)? {
            SdoAnswer::Read(_, data, len) => {
                let mut wide = [0u8; 8];
                wide[..len].copy_from_slice(&data[..len]);
                let raw = u64::from_le_bytes(wide);
                let shift = 64 - 8 * len as u32;
                Ok(if signed {
                    ((raw << shift) as i64) >> shift
                } else {
                    raw as i64
                })
            }
            _ => Err(BusError::Lost(format!(
                "{:#06x}:{}: a write answer to a read",
                at.0, at.1
            ))),
        }
    }
}

fn node_text(shared: &Shared, axis: usize) -> String {
    format!("node {} (axis {})", shared.settings.nodes[axis], axis + 1)
}

/// NMT reset communication, then each drive read until it answers, its device type checked.
fn reset_communication(bus: &mut Bus, shared: &Shared) -> Result<(), BusError> {
    bus.operational = false;
    for &node in &shared.settings.nodes {
        bus.send(shared, cob::NMT, &[nmt_command::RESET_COMMUNICATION, node])?;
    }
    let started = Instant::now();
    for axis in 0..shared.settings.nodes.len() {
        let device_type = loop {
            match bus.read(shared, axis, (object::DEVICE_TYPE, 0), false) {
                Ok(value) => break value,
                Err(BusError::Lost(_)) if started.elapsed() < BOOT_PATIENCE => {}
                Err(e) => return Err(e),
            }
        };
        if device_type & 0xFFFF != i64::from(DRIVE_PROFILE) {
            return Err(BusError::Drive {
                axis,
                text: format!(
                    "{}: device type {device_type:#010x} is not a CiA 402 drive",
                    node_text(shared, axis)
                ),
            });
        }
    }
    Ok(())
}

/// A PDO remapped by the CiA 301 procedure (7.4.8): COB-ID invalid, transmission type,
/// sub-index 0 = 0, the entries, sub-index 0 = n, COB-ID valid.
fn remap(
    bus: &mut Bus,
    shared: &Shared,
    axis: usize,
    (comm, map, cob_id): (u16, u16, u32),
    entries: &[u32],
) -> Result<(), BusError> {
    bus.write(
        shared,
        axis,
        (comm, 1),
        Value::Unsigned32(PDO_INVALID | cob_id),
    )?;
    bus.write(
        shared,
        axis,
        (comm, 2),
        Value::Unsigned8(SYNCHRONOUS_EVERY_SYNC),
    )?;
    bus.write(shared, axis, (map, 0), Value::Unsigned8(0))?;
    for (sub, entry) in entries.iter().enumerate() {
        bus.write(
            shared,
            axis,
            (map, sub as u8 + 1),
            Value::Unsigned32(*entry),
        )?;
    }
    bus.write(
        shared,
        axis,
        (map, 0),
        Value::Unsigned8(entries.len() as u8),
    )?;
    bus.write(shared, axis, (comm, 1), Value::Unsigned32(cob_id))
}

/// The pre-operational set-up of one drive: CSP, the period, the PDOs, the heartbeat.
fn configure(bus: &mut Bus, shared: &Shared, axis: usize) -> Result<(), BusError> {
    let settings = &shared.settings;
    let node = u32::from(settings.nodes[axis]);
    bus.write(
        shared,
        axis,
        (object::MODES_OF_OPERATION, 0),
        Value::Integer8(super::canopen_wire::CSP_MODE),
    )?;
    // Checked in check_settings: every accepted period has one.
    let (value, exponent) = interpolation_period(settings.period).unwrap_or((0, 0));
    bus.write(
        shared,
        axis,
        (object::INTERPOLATION_PERIOD, 1),
        Value::Unsigned8(value),
    )?;
    bus.write(
        shared,
        axis,
        (object::INTERPOLATION_PERIOD, 2),
        Value::Integer8(exponent),
    )?;
    remap(
        bus,
        shared,
        axis,
        (object::RPDO1_COMM, object::RPDO1_MAP, cob::RPDO1 + node),
        &RPDO1_ENTRIES,
    )?;
    remap(
        bus,
        shared,
        axis,
        (object::TPDO1_COMM, object::TPDO1_MAP, cob::TPDO1 + node),
        &TPDO1_ENTRIES,
    )?;
    bus.write(
        shared,
        axis,
        (object::HEARTBEAT_PRODUCER, 0),
        Value::Unsigned16(settings.heartbeat_ms),
    )?;
    let mode = bus.read(shared, axis, (object::MODES_OF_OPERATION_DISPLAY, 0), true)?;
    if mode != i64::from(super::canopen_wire::CSP_MODE) {
        return Err(BusError::Drive {
            axis,
            text: format!(
                "{}: mode of operation display {mode}, not 8 (CSP)",
                node_text(shared, axis)
            ),
        });
    }
    Ok(())
}

fn power_state(bus: &mut Bus, shared: &Shared, axis: usize) -> Result<PowerState, BusError> {
    let word = bus.read(shared, axis, (object::STATUSWORD, 0), false)? as u16;
    PowerState::of(word).ok_or_else(|| BusError::Drive {
        axis,
        text: format!(
            "{}: statusword {word:#06x} shows no CiA 402 state",
            node_text(shared, axis)
        ),
    })
}

/// Writes controlword `command` and waits for the statusword to show `expected`.
fn power_step(
    bus: &mut Bus,
    shared: &Shared,
    axis: usize,
    command: u16,
    expected: PowerState,
) -> Result<(), BusError> {
    bus.write(
        shared,
        axis,
        (object::CONTROLWORD, 0),
        Value::Unsigned16(command),
    )?;
    let deadline = Instant::now() + STEP_PATIENCE;
    loop {
        let state = power_state(bus, shared, axis)?;
        if state == expected {
            return Ok(());
        }
        if Instant::now() >= deadline {
            return Err(BusError::Drive {
                axis,
                text: format!(
                    "{}: controlword {command:#06x} left it {}, not {}",
                    node_text(shared, axis),
                    state.name(),
                    expected.name()
                ),
            });
        }
    }
}

/// Steps `axis`' drive to operation enabled (CiA 402-2 figure 6: transitions 2, 3, 4),
/// clearing a fault with a bit 7 edge only when `clear_fault`.
fn enable(bus: &mut Bus, shared: &Shared, axis: usize, clear_fault: bool) -> Result<(), BusError> {
    for _ in 0..MAX_POWER_STEPS {
        let (command, next) = match power_state(bus, shared, axis)? {
            PowerState::OperationEnabled => return Ok(()),
            PowerState::Fault | PowerState::FaultReactionActive if clear_fault => {
                // The edge: bit 7 low, then high (transition 15).
                bus.write(
                    shared,
                    axis,
                    (object::CONTROLWORD, 0),
                    Value::Unsigned16(controlword::DISABLE_VOLTAGE),
                )?;
                (controlword::FAULT_RESET, PowerState::SwitchOnDisabled)
            }
            PowerState::Fault | PowerState::FaultReactionActive => {
                return Err(BusError::Drive {
                    axis,
                    text: format!(
                        "{}: in fault (rigbridge reset clears it)",
                        node_text(shared, axis)
                    ),
                });
            }
            PowerState::NotReadyToSwitchOn => {
                std::thread::sleep(Duration::from_millis(10));
                continue;
            }
            PowerState::SwitchOnDisabled => (controlword::SHUTDOWN, PowerState::ReadyToSwitchOn),
            PowerState::ReadyToSwitchOn => (controlword::SWITCH_ON, PowerState::SwitchedOn),
            PowerState::SwitchedOn => (controlword::ENABLE_OPERATION, PowerState::OperationEnabled),
            PowerState::QuickStopActive => {
                (controlword::DISABLE_VOLTAGE, PowerState::SwitchOnDisabled)
            }
        };
        power_step(bus, shared, axis, command, next)?;
    }
    Err(BusError::Drive {
        axis,
        text: format!(
            "{}: not operation enabled after {MAX_POWER_STEPS} steps",
            node_text(shared, axis)
        ),
    })
}

/// The whole set-up of docs/canopen.md; returns each drive's position actual (counts).
fn set_up(bus: &mut Bus, shared: &Shared) -> Result<Vec<i32>, BusError> {
    let axes = shared.settings.nodes.len();
    reset_communication(bus, shared)?;
    for axis in 0..axes {
        configure(bus, shared, axis)?;
    }
    bus.heartbeats = vec![(Instant::now(), false); axes];
    for &node in &shared.settings.nodes {
        bus.send(shared, cob::NMT, &[nmt_command::START, node])?;
    }
    bus.operational = true;
    bus.started = Instant::now();
    let mut present = Vec::with_capacity(axes);
    for axis in 0..axes {
        let actual = bus.read(shared, axis, (object::POSITION_ACTUAL, 0), true)? as i32;
        bus.write(
            shared,
            axis,
            (object::TARGET_POSITION, 0),
            Value::Integer32(actual),
        )?;
        present.push(actual);
    }
    Ok(present)
}

/// Opens, sets up and runs the bus until the link is dropped, again after every loss.
fn keep_open(shared: &Shared) {
    let mut backoff = BACKOFF_INITIAL;
    while !shared.closed.load(Ordering::SeqCst) {
        let mut bus = match Bus::open(&shared.settings.interface) {
            Ok(bus) => bus,
            Err(BusError::Lost(problem) | BusError::Drive { text: problem, .. }) => {
                shared.lock().problem = Some(problem);
                std::thread::sleep(backoff);
                backoff = (backoff * 2).min(BACKOFF_MAX);
                continue;
            }
        };
        match set_up(&mut bus, shared) {
            Ok(present) => {
                backoff = BACKOFF_INITIAL;
                begin_session(&mut bus, shared, &present);
                run_cycles(&mut bus, shared, present);
            }
            Err(BusError::Drive { axis, text }) => {
                latch(shared, Fault::Drive { axis: axis as u8 }, &text);
                shared.lock().problem = Some(text);
                wait_for_reset(shared);
            }
            Err(BusError::Lost(problem)) => {
                shared.lock().problem = Some(problem);
                std::thread::sleep(backoff);
                backoff = (backoff * 2).min(BACKOFF_MAX);
            }
        }
        let mut state = shared.lock();
        state.up = false;
        state.queue.clear();
    }
}

/// Enables every drive (a fault stays latched, for a Reset) and publishes the session.
fn begin_session(bus: &mut Bus, shared: &Shared, present: &[i32]) {
    let mut fault = None;
    for axis in 0..shared.settings.nodes.len() {
        match enable(bus, shared, axis, false) {
            Ok(()) => {}
            Err(BusError::Drive { axis, text }) => {
                fault = Some((axis, text));
                break;
            }
            Err(BusError::Lost(text)) => {
                fault = Some((axis, text));
                break;
            }
        }
    }
    let mut state = shared.lock();
    state.up = true;
    state.sessions += 1;
    state.counters.reconnects = state.sessions - 1;
    state.latched = None;
    state.restart = false;
    state.queue.clear();
    state.problem = None;
    // A drive in fault is latched before the first feedback: none may say holding.
    let status = match fault {
        Some((axis, text)) => {
            let fault = Fault::Drive { axis: axis as u8 };
            state.latched = Some(fault);
            state
                .events
                .push_back(LinkEvent::Fault(FaultReport { fault, text }));
            ControllerStatus::Fault(fault)
        }
        None => ControllerStatus::Holding,
    };
    let positions = radians(shared, present);
    publish(
        shared,
        &mut state,
        Feedback {
            seq: 0,
            positions,
            status,
        },
    );
}

fn radians(shared: &Shared, counts: &[i32]) -> AxisValues {
    let values: Vec<f64> = shared
        .settings
        .axes
        .iter()
        .zip(counts)
        .map(|(axis, &c)| axis.radians(i64::from(c)))
        .collect();
    AxisValues::from_slice(&values).unwrap_or(AxisValues::zeros(0))
}

fn publish(shared: &Shared, state: &mut State, feedback: Feedback) {
    state.feedback = Some(feedback);
    state.generation += 1;
    shared.feedback.notify_all();
}

/// Latches `fault` with `text` (the first one only: later ones are its consequences).
fn latch(shared: &Shared, fault: Fault, text: &str) {
    let mut state = shared.lock();
    if state.latched.is_some() {
        return;
    }
    state.latched = Some(fault);
    state.events.push_back(LinkEvent::Fault(FaultReport {
        fault,
        text: text.to_string(),
    }));
    if let Some(feedback) = state.feedback.as_mut() {
        feedback.status = ControllerStatus::Fault(fault);
    }
}

/// After a fault at set-up: nothing moves until a Reset (or the link is dropped).
fn wait_for_reset(shared: &Shared) {
    let mut state = shared.lock();
    while !shared.closed.load(Ordering::SeqCst) {
        if let Some(index) = state.queue.iter().position(|j| matches!(j, Job::Reset)) {
            state.queue.drain(..=index);
            return;
        }
        state.queue.clear();
        state = shared
            .command
            .wait_timeout(state, POLL)
            .unwrap_or_else(|p| p.into_inner())
            .0;
    }
}

/// The next command, `Ok(None)` when a SYNC is due without one (`idle` has passed), or
/// `Err(())` when the link was dropped or asked to restart.
fn next_job(shared: &Shared, idle: Instant) -> Result<Option<Job>, ()> {
    let mut state = shared.lock();
    loop {
        if shared.closed.load(Ordering::SeqCst) || state.restart {
            return Err(());
        }
        if let Some(job) = state.queue.pop_front() {
            return Ok(Some(job));
        }
        let now = Instant::now();
        if now >= idle {
            return Ok(None);
        }
        state = shared
            .command
            .wait_timeout(state, (idle - now).min(POLL))
            .unwrap_or_else(|p| p.into_inner())
            .0;
    }
}

/// What the cycle loop keeps between SYNCs.
struct Cycle {
    last_seq: u32,
    holding: bool,
    streaming: bool,
    present: Vec<i32>,
    /// The targets last written: a drive not streamed holds them.
    targets: Option<Vec<i32>>,
    last_sync: Option<Instant>,
    missing_cycles: u32,
    /// Quick stop sent since the fault latched.
    quick_stopped: bool,
}

/// Quick stop (controlword 0x02, CiA 402-2 transition 11) to every drive, taken at a SYNC.
fn quick_stop(bus: &mut Bus, shared: &Shared, cycle: &Cycle) -> Result<(), BusError> {
    for (axis, &node) in shared.settings.nodes.iter().enumerate() {
        let hold = cycle
            .targets
            .as_ref()
            .and_then(|t| t.get(axis))
            .or(cycle.present.get(axis))
            .copied()
            .unwrap_or_default();
        let data = rpdo1(controlword::QUICK_STOP, hold);
        bus.send(shared, cob::RPDO1 + u32::from(node), &data)?;
    }
    bus.send(shared, cob::SYNC, &[])
}

/// SYNC cycles, one per command (and one a period between jobs), until loss or the link
/// is dropped.
fn run_cycles(bus: &mut Bus, shared: &Shared, present: Vec<i32>) {
    let period = shared.settings.period;
    let mut cycle = Cycle {
        last_seq: 0,
        holding: true,
        streaming: false,
        present,
        targets: None,
        last_sync: None,
        missing_cycles: 0,
        quick_stopped: false,
    };
    loop {
        let idle_periods = if cycle.streaming {
            IDLE_SYNC_PERIODS_STREAMING
        } else {
            1
        };
        let idle = cycle.last_sync.unwrap_or_else(Instant::now) + period * idle_periods;
        let Ok(job) = next_job(shared, idle) else {
            return;
        };
        let done = match job {
            Some(Job::Reset) => reset_faults(bus, shared),
            Some(job) => write_job(bus, shared, &mut cycle, job),
            None => {
                cycle.streaming = false;
                Ok(())
            }
        };
        if matches!(job, Some(Job::Reset)) {
            cycle.quick_stopped = false;
        }
        let result = done.and_then(|()| sync_cycle(bus, shared, &mut cycle));
        match result {
            Ok(true) => {}
            Ok(false) | Err(BusError::Lost(_)) => return,
            Err(BusError::Drive { axis, text }) => {
                latch(shared, Fault::Drive { axis: axis as u8 }, &text)
            }
        }
        // One drive's fault stops the others on their own quick-stop ramps, never by
        // holding a target mid-motion (a stop over their acceleration).
        if !cycle.quick_stopped && shared.lock().latched.is_some() {
            cycle.quick_stopped = true;
            if quick_stop(bus, shared, &cycle).is_err() {
                return;
            }
        }
    }
}

/// The RPDOs of a command (none for a plain SYNC).
fn write_job(bus: &mut Bus, shared: &Shared, cycle: &mut Cycle, job: Job) -> Result<(), BusError> {
    let latched = shared.lock().latched.is_some();
    let nodes = &shared.settings.nodes;
    match job {
        Job::Targets(seq, counts) if !latched => {
            for (axis, &node) in nodes.iter().enumerate() {
                let data = rpdo1(controlword::ENABLE_OPERATION, counts[axis]);
                bus.send(shared, cob::RPDO1 + u32::from(node), &data)?;
            }
            cycle.last_seq = seq;
            cycle.holding = false;
            cycle.streaming = true;
            cycle.targets = Some(counts[..nodes.len()].to_vec());
        }
        Job::Targets(..) | Job::Reset => {}
        Job::Sync { holding } => {
            cycle.holding |= holding;
            cycle.streaming &= !holding;
        }
        Job::EStop => {
            // Quick stop (CiA 402-2 transition 11): each drive brakes on its own ramp.
            for (axis, &node) in nodes.iter().enumerate() {
                let hold = cycle.present.get(axis).copied().unwrap_or_default();
                let data = rpdo1(controlword::QUICK_STOP, hold);
                bus.send(shared, cob::RPDO1 + u32::from(node), &data)?;
            }
            cycle.holding = true;
            cycle.streaming = false;
            latch(
                shared,
                Fault::EStop,
                "e-stop: quick stop (controlword 0x0002) sent to every drive",
            );
        }
    }
    Ok(())
}

/// Reset: with a fault latched, a fault-reset edge and the power steps on every drive; a
/// drive that keeps its fault is a Fault event (the Reset's answer).
fn reset_faults(bus: &mut Bus, shared: &Shared) -> Result<(), BusError> {
    if shared.lock().latched.is_none() {
        return Ok(());
    }
    bus.heard.clear();
    for axis in 0..shared.settings.nodes.len() {
        if let Err(BusError::Drive { axis, text }) = enable(bus, shared, axis, true) {
            let mut state = shared.lock();
            state.events.push_back(LinkEvent::Fault(FaultReport {
                fault: Fault::Drive { axis: axis as u8 },
                text,
            }));
            return Ok(());
        }
    }
    // Each drive holds where it stands: its target seeded from its position.
    for axis in 0..shared.settings.nodes.len() {
        let actual = bus.read(shared, axis, (object::POSITION_ACTUAL, 0), true)? as i32;
        bus.write(
            shared,
            axis,
            (object::TARGET_POSITION, 0),
            Value::Integer32(actual),
        )?;
    }
    bus.heard.clear();
    let now = Instant::now();
    for entry in &mut bus.heartbeats {
        entry.0 = now;
    }
    bus.started = now;
    let mut state = shared.lock();
    state.latched = None;
    Ok(())
}

/// One SYNC and the TPDOs it asks for; publishes the feedback. `Ok(false)` on link loss.
fn sync_cycle(bus: &mut Bus, shared: &Shared, cycle: &mut Cycle) -> Result<bool, BusError> {
    let settings = &shared.settings;
    let now = Instant::now();
    if let Some(last) = cycle.last_sync
        && cycle.streaming
        && now.duration_since(last).as_secs_f64() > OVERRUN_PERIODS * settings.period.as_secs_f64()
    {
        shared.overruns.fetch_add(1, Ordering::Relaxed);
    }
    bus.send(shared, cob::SYNC, &[])?;
    shared.syncs.fetch_add(1, Ordering::Relaxed);
    cycle.last_sync = Some(now);
    let deadline = now + settings.period.mul_f64(COLLECT_SHARE);
    let axes = settings.nodes.len();
    let mut answers: Vec<Option<(u16, i32)>> = vec![None; axes];
    while answers.iter().any(Option::is_none) {
        let Some(frame) = bus.next_frame(shared, deadline)? else {
            break;
        };
        let (function, node) = cob::split(frame.id);
        if function != cob::TPDO1 {
            continue;
        }
        if let Some(axis) = settings.nodes.iter().position(|&n| n == node) {
            answers[axis] = tpdo1(&frame.data[..usize::from(frame.len)]);
        }
    }
    check_heartbeats(bus, shared);
    if let Some((axis, text)) = bus.heard.drain(..).next() {
        latch(shared, Fault::Drive { axis: axis as u8 }, &text);
    }
    let missing = answers.iter().filter(|a| a.is_none()).count();
    if missing > 0 {
        shared.lock().counters.gaps += missing as u64;
        cycle.missing_cycles += 1;
        return Ok(cycle.missing_cycles < LOST_AFTER_CYCLES);
    }
    cycle.missing_cycles = 0;
    let answers: Vec<(u16, i32)> = answers.into_iter().flatten().collect();
    check_statuswords(shared, &answers);
    cycle.present = answers.iter().map(|(_, p)| *p).collect();
    let settled = cycle.targets.as_ref().is_none_or(|targets| {
        targets
            .iter()
            .zip(&cycle.present)
            .zip(&settings.axes)
            .all(|((t, p), map)| f64::from(t.abs_diff(*p)) * map.resolution() <= SETTLED_RAD)
    });
    let mut state = shared.lock();
    let status = match state.latched {
        Some(fault) => ControllerStatus::Fault(fault),
        None if cycle.holding && settled => ControllerStatus::Holding,
        None => ControllerStatus::Ok,
    };
    let positions = radians(shared, &cycle.present);
    publish(
        shared,
        &mut state,
        Feedback {
            seq: cycle.last_seq,
            positions,
            status,
        },
    );
    Ok(true)
}

/// A drive whose statusword shows a fault, or any state but operation enabled, latches.
fn check_statuswords(shared: &Shared, answers: &[(u16, i32)]) {
    for (axis, &(word, _)) in answers.iter().enumerate() {
        let state = PowerState::of(word);
        if word & STATUS_FAULT != 0 || state != Some(PowerState::OperationEnabled) {
            let name = state.map_or("no CiA 402 state", PowerState::name);
            latch(
                shared,
                Fault::Drive { axis: axis as u8 },
                &format!(
                    "{}: statusword {word:#06x} ({name})",
                    node_text(shared, axis)
                ),
            );
            return;
        }
    }
}

/// A drive whose heartbeat is overdue, or that has not said operational within the
/// consumer time of its start, is noted as lost.
fn check_heartbeats(bus: &mut Bus, shared: &Shared) {
    let consumer = Duration::from_millis(
        u64::from(shared.settings.heartbeat_ms) * u64::from(HEARTBEAT_LOST_FACTOR),
    );
    for (axis, &(heard, confirmed)) in bus.heartbeats.iter().enumerate() {
        if !confirmed && bus.started.elapsed() > consumer {
            bus.heard.push((
                axis,
                format!(
                    "{}: not operational {} ms after NMT start",
                    node_text(shared, axis),
                    bus.started.elapsed().as_millis()
                ),
            ));
            continue;
        }
        let silent = heard.elapsed();
        if silent > consumer {
            bus.heard.push((
                axis,
                format!(
                    "{}: no heartbeat for {} ms (producer time {} ms)",
                    node_text(shared, axis),
                    silent.as_millis(),
                    shared.settings.heartbeat_ms
                ),
            ));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn settings() -> CanopenSettings {
        CanopenSettings {
            interface: "vcan0".into(),
            nodes: vec![1, 2],
            axes: vec![
                AxisTicks {
                    ticks_per_turn: 1_048_576.0,
                    zero_tick: 0.0,
                    ticks_per_metre: None,
                };
                2
            ],
            limits: vec![(-1.0, 1.0); 2],
            period: Duration::from_millis(4),
            heartbeat_ms: 100,
        }
    }

    #[test]
    fn settings_are_refused_with_bad_nodes_ranges_or_periods() {
        assert_eq!(check_settings(&settings()), Ok(()));
        for nodes in [vec![0, 1], vec![1, 128], vec![3, 3]] {
            let bad = CanopenSettings {
                nodes,
                ..settings()
            };
            assert!(matches!(
                check_settings(&bad),
                Err(CanopenError::BadNode(_))
            ));
        }
        let short = CanopenSettings {
            nodes: vec![1],
            ..settings()
        };
        assert!(matches!(
            check_settings(&short),
            Err(CanopenError::NodeCount { nodes: 1, axes: 2 })
        ));
        // 5000 turns at 2^20 counts a turn: beyond 32 bits.
        let far = CanopenSettings {
            limits: vec![(-1.0, 1.0), (0.0, 5000.0 * std::f64::consts::TAU)],
            ..settings()
        };
        assert!(matches!(
            check_settings(&far),
            Err(CanopenError::OutOfRange { axis: 2, .. })
        ));
        let slow = CanopenSettings {
            period: Duration::from_secs(1),
            ..settings()
        };
        assert!(matches!(
            check_settings(&slow),
            Err(CanopenError::Period { .. })
        ));
    }
}
