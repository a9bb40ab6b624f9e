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

use crate::device::bus::{BusError, Device, DeviceLink, Hub, Job, id_list};
use crate::device::canopen::wire::{
    CSP_MODE, DRIVE_PROFILE, PDO_INVALID, PowerState, RPDO1_ENTRIES, STATUS_FAULT,
    SYNCHRONOUS_EVERY_SYNC, SdoAnswer, TPDO1_ENTRIES, Value, cob, controlword,
    interpolation_period, nmt_command, nmt_state, object, rpdo1, sdo_download, sdo_upload, tpdo1,
};
use crate::device::dynamixel::wire::AxisTicks;
use crate::link::{LinkError, LinkEvent};
use crate::protocol::codec::FaultReport;
use crate::protocol::{CanPayload, ControllerStatus, Fault};
use crate::transport::{CanBus, SEND_PATIENCE};
use std::sync::atomic::{AtomicU64, Ordering};
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

/// The drives as the link's [`Device`]: one SYNC a cycle, and the SYNCs counted.
pub struct Canopen {
    settings: CanopenSettings,
    /// SYNCs sent, and those more than [`OVERRUN_PERIODS`] after the one before while
    /// streaming.
    syncs: AtomicU64,
    overruns: AtomicU64,
}

/// The link to a bus of CiA 402 drives.
pub type CanopenLink = DeviceLink<Canopen>;
type Shared = Hub<Canopen>;

impl Device for Canopen {
    type Bus = Bus;
    type Start = Vec<i32>;
    const NAME: &'static str = "CANopen";
    const TARGET_FIELD: &'static str = "target position (0x607A) counts";
    const TARGET_RANGE: &'static str = "a drive's 32-bit position range";
    /// A synchronous TPDO samples the position at the SYNC (CiA 301 7.3.2.2), the SYNC at
    /// which the drive takes the cycle's target: it was measured under the target before.
    const MEASURED_CYCLES_BEHIND: u32 = 1;

    fn axes(&self) -> &[AxisTicks] {
        &self.settings.axes
    }

    fn open(&self) -> Result<Bus, BusError> {
        Bus::open(&self.settings.interface)
    }

    fn set_up(&self, bus: &mut Bus, hub: &Shared) -> Result<Vec<i32>, BusError> {
        set_up(bus, hub)
    }

    /// Enables every drive (a fault stays latched, for a Reset), publishes the session
    /// and runs the cycles.
    fn run(&self, bus: &mut Bus, hub: &Shared, present: Vec<i32>) {
        let fault = enable_all(bus, hub);
        // Any 32-bit count fits a drive's target (checked against the limits at connect).
        let ranges = vec![(i64::from(i32::MIN), i64::from(i32::MAX)); present.len()];
        hub.begin_session(ranges, &present, fault);
        run_cycles(bus, hub, present);
    }

    /// Latches the first fault only (later ones are its consequences), and marks the
    /// feedback last published with it.
    fn latch(hub: &Shared, fault: Fault, text: &str) {
        if hub.lock().latched.is_some() {
            return;
        }
        hub.latch(fault, text);
        let mut state = hub.lock();
        if let Some(feedback) = state.feedback.as_mut() {
            feedback.status = ControllerStatus::Fault(fault);
        }
    }
}

/// Checks `settings` and starts the I/O thread, which opens the interface and sets the
/// drives up in the background (and again after every loss).
pub fn connect_canopen(settings: CanopenSettings) -> Result<CanopenLink, LinkError> {
    check_settings(&settings).map_err(|e| LinkError::Closed(e.to_string()))?;
    let description = format!(
        "canopen://{}?nodes={}",
        settings.interface,
        id_list(&settings.nodes)
    );
    let device = Canopen {
        settings,
        syncs: AtomicU64::new(0),
        overruns: AtomicU64::new(0),
    };
    crate::device::bus::start(device, description, "rigbridge-canopen")
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

impl CanopenLink {
    /// SYNCs sent so far, and the overruns among them (a SYNC more than 1.5 periods after
    /// the one before while streaming).
    pub fn syncs(&self) -> (u64, u64) {
        let device = self.device();
        (
            device.syncs.load(Ordering::Relaxed),
            device.overruns.load(Ordering::Relaxed),
        )
    }
}

/// The socket, and what the bus said besides the answers being waited for.
pub struct Bus {
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
    /// Node ids heard booting (a heartbeat with NMT state 0) since the bus opened.
    booted: Vec<u8>,
    /// The last SDO request went unanswered (all its attempts): the node is silent.
    unanswered: bool,
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
            booted: Vec::new(),
            unanswered: false,
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
            .send_patiently(&frame, SEND_PATIENCE)
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

    /// Reads whatever has arrived, noting EMCYs and heartbeats and dropping the rest: what
    /// answers a SYNC arrives after it.
    fn discard_stale(&mut self, shared: &Shared) -> Result<(), BusError> {
        let now = Instant::now();
        while self.next_frame(shared, now)?.is_some() {}
        Ok(())
    }

    /// Notes an EMCY or heartbeat of one of our drives; true when the frame was one.
    fn observe(&mut self, shared: &Shared, frame: &CanPayload) -> bool {
        let (function, node) = cob::split(frame.id);
        let Some(axis) = shared.device.settings.nodes.iter().position(|&n| n == node) else {
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
                if state == nmt_state::BOOT_UP && !self.booted.contains(&node) {
                    self.booted.push(node);
                }
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
        let node = shared.device.settings.nodes[axis];
        self.unanswered = false;
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
        self.unanswered = true;
        Err(BusError::Lost(format!(
            "node {node} (axis {}) did not answer: SDO timeout on {:#06x}:{} ({SDO_ATTEMPTS} tries of {} ms)",
            axis + 1,
            at.0,
            at.1,
            SDO_TIMEOUT.as_millis()
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
    format!(
        "node {} (axis {})",
        shared.device.settings.nodes[axis],
        axis + 1
    )
}

/// A node that said nothing within [`BOOT_PATIENCE`] of NMT reset communication, in words:
/// whether it booted, and that it left its SDO unanswered.
fn silent_node(bus: &Bus, shared: &Shared, axis: usize) -> BusError {
    let node = shared.device.settings.nodes[axis];
    let boot = if bus.booted.contains(&node) {
        "booted, then"
    } else {
        "no boot-up and"
    };
    BusError::Lost(format!(
        "node {node} (axis {}) did not answer on {}: {boot} no SDO answer to {:#06x}:0 within {:.1} s of NMT reset communication (SDO timeout)",
        axis + 1,
        shared.device.settings.interface,
        object::DEVICE_TYPE,
        BOOT_PATIENCE.as_secs_f64()
    ))
}

/// NMT reset communication, then each drive read until it answers, its device type checked.
fn reset_communication(bus: &mut Bus, shared: &Shared) -> Result<(), BusError> {
    bus.operational = false;
    for &node in &shared.device.settings.nodes {
        bus.send(shared, cob::NMT, &[nmt_command::RESET_COMMUNICATION, node])?;
    }
    let started = Instant::now();
    for axis in 0..shared.device.settings.nodes.len() {
        let device_type = loop {
            match bus.read(shared, axis, (object::DEVICE_TYPE, 0), false) {
                Ok(value) => break value,
                Err(BusError::Lost(_)) if bus.unanswered && started.elapsed() < BOOT_PATIENCE => {}
                Err(BusError::Lost(_)) if bus.unanswered => {
                    return Err(silent_node(bus, shared, axis));
                }
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
    let settings = &shared.device.settings;
    let node = u32::from(settings.nodes[axis]);
    bus.write(
        shared,
        axis,
        (object::MODES_OF_OPERATION, 0),
        Value::Integer8(CSP_MODE),
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
    if mode != i64::from(CSP_MODE) {
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
    let axes = shared.device.settings.nodes.len();
    reset_communication(bus, shared)?;
    for axis in 0..axes {
        configure(bus, shared, axis)?;
    }
    bus.heartbeats = vec![(Instant::now(), false); axes];
    for &node in &shared.device.settings.nodes {
        bus.send(shared, cob::NMT, &[nmt_command::START, node])?;
    }
    bus.operational = true;
    bus.started = Instant::now();
    hold_where_standing(bus, shared)
}

/// Each drive's target seeded from its position actual, so that it holds where it stands;
/// the positions (counts).
fn hold_where_standing(bus: &mut Bus, shared: &Shared) -> Result<Vec<i32>, BusError> {
    let axes = shared.device.settings.nodes.len();
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

/// Enables every drive; the first that cannot be enabled, and why (its fault stays
/// latched for a Reset).
fn enable_all(bus: &mut Bus, shared: &Shared) -> Option<(usize, String)> {
    for axis in 0..shared.device.settings.nodes.len() {
        match enable(bus, shared, axis, false) {
            Ok(()) => {}
            Err(BusError::Drive { axis, text }) => return Some((axis, text)),
            Err(BusError::Lost(text)) => return Some((axis, text)),
        }
    }
    None
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
    for (axis, &node) in shared.device.settings.nodes.iter().enumerate() {
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
    let period = shared.device.settings.period;
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
        let Ok(job) = shared.next_job(Some(idle)) else {
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
                Canopen::latch(shared, Fault::Drive { axis: axis as u8 }, &text)
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
    let nodes = &shared.device.settings.nodes;
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
        Job::Cycle { holding } => {
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
            Canopen::latch(
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
    for axis in 0..shared.device.settings.nodes.len() {
        if let Err(BusError::Drive { axis, text }) = enable(bus, shared, axis, true) {
            let mut state = shared.lock();
            state.events.push_back(LinkEvent::Fault(FaultReport {
                fault: Fault::Drive { axis: axis as u8 },
                text,
            }));
            return Ok(());
        }
    }
    hold_where_standing(bus, shared)?;
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
    let settings = &shared.device.settings;
    let now = Instant::now();
    if let Some(last) = cycle.last_sync
        && cycle.streaming
        && now.duration_since(last).as_secs_f64() > OVERRUN_PERIODS * settings.period.as_secs_f64()
    {
        shared.device.overruns.fetch_add(1, Ordering::Relaxed);
    }
    // A TPDO still queued answered an earlier SYNC (its cycle counted it missing): read as
    // this SYNC's, every later cycle's feedback would be one SYNC older than it says.
    bus.discard_stale(shared)?;
    bus.send(shared, cob::SYNC, &[])?;
    shared.device.syncs.fetch_add(1, Ordering::Relaxed);
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
        Canopen::latch(shared, Fault::Drive { axis: axis as u8 }, &text);
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
    shared.publish_cycle(cycle.last_seq, &cycle.present, cycle.holding && settled);
    Ok(true)
}

/// A drive whose statusword shows a fault, or any state but operation enabled, latches.
fn check_statuswords(shared: &Shared, answers: &[(u16, i32)]) {
    for (axis, &(word, _)) in answers.iter().enumerate() {
        let state = PowerState::of(word);
        if word & STATUS_FAULT != 0 || state != Some(PowerState::OperationEnabled) {
            let name = state.map_or("no CiA 402 state", PowerState::name);
            Canopen::latch(
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
        u64::from(shared.device.settings.heartbeat_ms) * u64::from(HEARTBEAT_LOST_FACTOR),
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
                    shared.device.settings.heartbeat_ms
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
