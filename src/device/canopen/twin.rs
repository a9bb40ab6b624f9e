//! The CANopen twin: N CiA 402 drives on one CAN bus, one per axis of the rig, for the
//! bridge's CANopen link or any other master (python `canopen`).
//!
//! Each drive keeps the objects a CSP drive's master sets up (docs/canopen.md): device
//! type 0x1000 (402), error register 0x1001, heartbeat 0x1017, RPDO1/TPDO1 communication
//! and mapping (0x1400, 0x1600, 0x1800, 0x1A00), controlword 0x6040, statusword 0x6041,
//! modes 0x6060/0x6061, position actual 0x6064, target 0x607A and the interpolation
//! period 0x60C2. It is an NMT slave (boot-up after a reset, heartbeat producer), an SDO
//! server for expedited transfers, and strict: an unknown object, a read-only one, a
//! wrong length, a mode other than CSP, a mapping written while its PDO is valid or with
//! sub-index 0 not 0 first, an entry that cannot be mapped, a PDO longer than 8 bytes, or a
//! PDO changed while operational is an SDO abort. PDOs work in operational only: an RPDO
//! is taken at the next SYNC (synchronous), a TPDO goes out at each SYNC with the objects
//! mapped. The CiA 402 power state machine follows the controlword, from RPDO or SDO.
//! In operation enabled and CSP, each SYNC takes 0x607A as the next point of the path,
//! judged against the axis' limits, its speed (the step over one interpolation period)
//! and acceleration (the second difference) beyond what rounding to counts explains; a
//! violation latches a fault (statusword bit 3, an EMCY, the error register) and nothing
//! moves until a fault reset (controlword bit 7 edge). It owns the simulated drives only;
//! it must not know about trajectories or jobs.

use crate::device::canopen::wire::{
    CSP_MODE, DRIVE_PROFILE, PDO_BYTES, PDO_INVALID, PowerState, SdoAbortCode, SdoRequest, Value,
    abort, cob, emcy_code, mapping_entry, nmt_command, nmt_state, object, period_of,
};
use crate::device::dynamixel::wire::AxisTicks;
use crate::protocol::CanPayload;
use crate::protocol::can::classic_frame_bits;
use crate::rig::{JointLimits, LIMIT_SLACK, Rig};
use crate::twin::server::ControllerPort;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};
use thiserror::Error;

/// Rounding to counts moves a target by up to half a count: a step by up to one, a second
/// difference by up to two.
const STEP_ROUNDING_COUNTS: f64 = 1.0;
const SECOND_DIFFERENCE_ROUNDING_COUNTS: f64 = 2.0;
/// A SYNC more than this many interpolation periods after the one before, both carrying
/// new targets, is an overrun of the master's cycle.
const OVERRUN_PERIODS: f64 = 1.5;
/// The 11-bit identifier in a PDO COB-ID (bits 29-31 are flags: CiA 301 7.5.2.35).
const COB_ID_MASK: u32 = 0x7FF;
/// Statusword bit 9: remote (the controlword is obeyed).
const STATUS_REMOTE: u16 = 0x0200;
/// Error register bit 0: generic error (CiA 301 7.5.2.2).
const GENERIC_ERROR: u8 = 0x01;
/// A classic CAN bus at 1 Mbit/s, the rate bus loads are given for.
pub const BUS_BITRATE: f64 = 1e6;
/// Bytes of a frame as the port hands it over: identifier (2, little endian), length, data.
pub const FRAME_HEADER: usize = 3;

#[derive(Debug, Clone, PartialEq, Error)]
pub enum CanopenTwinError {
    #[error("{nodes} node ids for a rig of {axes} axes")]
    NodeCount { nodes: usize, axes: usize },
    #[error("node id {0} is not a CANopen node id (1 to 127) or appears twice")]
    BadNode(u8),
    #[error("initial position: {0}")]
    InitialOutsideLimits(crate::rig::OutsideLimits),
}

/// What the drives saw, for summaries and tests.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct CanopenTwinCounters {
    pub frames_received: u64,
    pub frames_sent: u64,
    /// Bits on the bus (worst-case stuffing) from the first SYNC on, both directions.
    pub bus_bits: u64,
    pub syncs: u64,
    /// SYNCs that came with new targets (RPDOs since the SYNC before).
    pub streamed_syncs: u64,
    pub overruns: u64,
    /// The longest SYNC interval while streaming.
    pub longest_interval: Duration,
    /// From the first SYNC to the last.
    pub sync_span: Duration,
    pub sdo_requests: u64,
    pub sdo_aborts: u64,
    pub rpdos: u64,
    pub tpdos: u64,
    pub emcys: u64,
    pub targets: u64,
    pub outside_limits: u64,
    pub over_speed: u64,
    pub over_acceleration: u64,
    pub faults: u64,
    /// SYNCs with new targets after a fault latched (before any reset).
    pub streamed_after_fault: u64,
}

impl CanopenTwinCounters {
    pub fn violations(&self) -> u64 {
        self.outside_limits + self.over_speed + self.over_acceleration
    }

    /// Share of a 1 Mbit/s bus the traffic took between the first and last SYNC.
    pub fn bus_load(&self) -> f64 {
        if !self.sync_span.is_zero() {
            self.bus_bits as f64 / self.sync_span.as_secs_f64() / BUS_BITRATE
        } else {
            0.0
        }
    }

    /// One line for the twin's exit summary (tests read its numbers).
    pub fn summary(&self) -> String {
        format!(
            "CANopen twin: {} frames received, {} sent; {} SYNCs, {} streamed, longest interval {:.2} ms, {} overruns; bus load {:.1} % at 1 Mbit/s; {} SDO requests, {} SDO aborts, {} RPDOs, {} TPDOs, {} EMCYs; {} targets, {} outside limits, {} over speed, {} over acceleration, {} faults, {} streamed after a fault",
            self.frames_received,
            self.frames_sent,
            self.syncs,
            self.streamed_syncs,
            self.longest_interval.as_secs_f64() * 1e3,
            self.overruns,
            100.0 * self.bus_load(),
            self.sdo_requests,
            self.sdo_aborts,
            self.rpdos,
            self.tpdos,
            self.emcys,
            self.targets,
            self.outside_limits,
            self.over_speed,
            self.over_acceleration,
            self.faults,
            self.streamed_after_fault,
        )
    }
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CanopenTwinSettings {
    /// The period targets are judged over until a master sets 0x60C2.
    pub period: Duration,
    /// Position loop bandwidth, Hz: each SYNC the actual position closes this share of
    /// the distance to the target, 1 - exp(-2 pi f T).
    pub bandwidth_hz: f64,
}

/// A PDO's communication and mapping parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Pdo {
    cob_id: u32,
    transmission: u8,
    count: u8,
    entries: [u32; 8],
}

impl Pdo {
    /// CiA 402 defaults (the predefined connection set): valid, event driven (255),
    /// mapping `first` only.
    fn default_for(cob_id: u32, first: u32) -> Self {
        let mut entries = [0; 8];
        entries[0] = first;
        Self {
            cob_id,
            transmission: 255,
            count: 1,
            entries,
        }
    }

    fn valid(&self) -> bool {
        self.cob_id & PDO_INVALID == 0
    }

    fn mapped(&self) -> &[u32] {
        &self.entries[..usize::from(self.count)]
    }
}

struct Drive {
    node: u8,
    counts: AxisTicks,
    limits: JointLimits,
    nmt: u8,
    power: PowerState,
    controlword: u16,
    mode: i8,
    /// 0x60C2 sub 1 and 2.
    ip: (u8, i8),
    heartbeat_ms: u16,
    error_register: u8,
    rpdo: Pdo,
    tpdo: Pdo,
    target: i32,
    /// An RPDO taken since the last SYNC: applied at the next one.
    pending: Option<[u8; 8]>,
    /// Actual position, counts (continuous).
    actual: f64,
    /// The targets followed at the two SYNCs before: for the step and second difference.
    history: [i32; 2],
    /// History holds targets actually followed (not the hold before enabling).
    following: bool,
    next_heartbeat: Instant,
}

/// The simulated bus: drives in axis order and what they counted.
pub struct CanopenBus {
    drives: Vec<Drive>,
    settings: CanopenTwinSettings,
    pub counters: CanopenTwinCounters,
    first_sync: Option<Instant>,
    last_sync: Option<Instant>,
    /// RPDOs since the last SYNC (the master streams when it sends some).
    rpdos_since_sync: u64,
    last_streamed: bool,
    faulted: bool,
    /// Why the last fault latched, for the operator (taken by [`Self::take_fault_text`]).
    fault_text: Option<String>,
}

impl CanopenBus {
    /// Drives `nodes` (axis order) of `rig` at `initial` (rad): pre-operational after their
    /// boot-up, switch on disabled, no mode, PDOs at their defaults.
    pub fn new(
        rig: &Rig,
        nodes: &[u8],
        counts: &[AxisTicks],
        initial: &[f64],
        settings: CanopenTwinSettings,
    ) -> Result<Self, CanopenTwinError> {
        if nodes.len() != rig.dof() || counts.len() != rig.dof() || initial.len() != rig.dof() {
            return Err(CanopenTwinError::NodeCount {
                nodes: nodes.len(),
                axes: rig.dof(),
            });
        }
        for (i, &node) in nodes.iter().enumerate() {
            if !(1..=127).contains(&node) || nodes[..i].contains(&node) {
                return Err(CanopenTwinError::BadNode(node));
            }
        }
        let mut drives = Vec::with_capacity(nodes.len());
        for (axis, joint) in rig.joints.iter().enumerate() {
            joint
                .check_limits(initial[axis])
                .map_err(CanopenTwinError::InitialOutsideLimits)?;
            let actual = counts[axis].tick(initial[axis]);
            let node = nodes[axis];
            drives.push(Drive {
                node,
                counts: counts[axis],
                limits: joint.limits,
                nmt: nmt_state::PRE_OPERATIONAL,
                power: PowerState::SwitchOnDisabled,
                controlword: 0,
                mode: 0,
                ip: (0, 0),
                heartbeat_ms: 0,
                error_register: 0,
                rpdo: Pdo::default_for(
                    cob::RPDO1 + u32::from(node),
                    mapping_entry(object::CONTROLWORD, 0, 16),
                ),
                tpdo: Pdo::default_for(
                    cob::TPDO1 + u32::from(node),
                    mapping_entry(object::STATUSWORD, 0, 16),
                ),
                target: actual as i32,
                pending: None,
                actual,
                history: [actual as i32; 2],
                following: false,
                next_heartbeat: Instant::now(),
            });
        }
        Ok(Self {
            drives,
            settings,
            counters: CanopenTwinCounters::default(),
            first_sync: None,
            last_sync: None,
            rpdos_since_sync: 0,
            last_streamed: false,
            faulted: false,
            fault_text: None,
        })
    }

    /// Each drive's actual position, rad.
    pub fn positions(&self) -> Vec<f64> {
        self.drives
            .iter()
            .map(|d| d.counts.radians(d.actual.round() as i64))
            .collect()
    }

    /// Why the last fault latched, once.
    pub fn take_fault_text(&mut self) -> Option<String> {
        self.fault_text.take()
    }

    /// Each drive's power state.
    pub fn power_states(&self) -> Vec<PowerState> {
        self.drives.iter().map(|d| d.power).collect()
    }

    /// Each drive's NMT state (heartbeat value).
    pub fn nmt_states(&self) -> Vec<u8> {
        self.drives.iter().map(|d| d.nmt).collect()
    }

    /// A drive fault on `axis` (a hardware error), as the drive itself would raise it.
    pub fn inject_fault(&mut self, axis: usize, out: &mut Vec<CanPayload>) {
        if axis < self.drives.len() {
            self.fault(axis, emcy_code::HARDWARE, out);
        }
    }

    /// Takes one frame off the bus at `now`; answers go to `out`.
    pub fn handle(&mut self, frame: &CanPayload, now: Instant, out: &mut Vec<CanPayload>) {
        self.counters.frames_received += 1;
        self.count_bits(frame);
        let data = &frame.data[..usize::from(frame.len)];
        if frame.id == cob::NMT {
            if let [command, node] = data {
                self.nmt(*command, *node, now, out);
            }
            return;
        }
        if frame.id == cob::SYNC {
            self.sync(now, out);
            return;
        }
        let (function, node) = cob::split(frame.id);
        let Some(axis) = self.drives.iter().position(|d| d.node == node) else {
            return;
        };
        // A client's abort (command specifier 4) ends its transfer: no answer.
        if function == cob::SDO_RX && data.first().is_some_and(|c| c & 0xE0 == 0x80) {
            return;
        }
        if function == cob::SDO_RX && self.drives[axis].nmt != nmt_state::STOPPED {
            self.counters.sdo_requests += 1;
            let answer = self.sdo(axis, data, out);
            if answer[0] == 0x80 {
                self.counters.sdo_aborts += 1;
            }
            self.push(out, cob::SDO_TX + u32::from(node), &answer);
            return;
        }
        let drive = &mut self.drives[axis];
        if drive.nmt == nmt_state::OPERATIONAL
            && drive.rpdo.valid()
            && frame.id == drive.rpdo.cob_id & COB_ID_MASK
        {
            let mut bytes = [0u8; 8];
            bytes[..data.len().min(8)].copy_from_slice(&data[..data.len().min(8)]);
            if data.len() >= pdo_length(drive.rpdo.mapped()) {
                // A quick stop or other power command is not a target being streamed.
                let command = drive.rpdo.mapped().first()
                    == Some(&mapping_entry(object::CONTROLWORD, 0, 16))
                    && u16::from_le_bytes([bytes[0], bytes[1]]) & 0x8F != 0x0F;
                drive.pending = Some(bytes);
                self.counters.rpdos += 1;
                if !command {
                    self.rpdos_since_sync += 1;
                }
            }
        }
    }

    /// Heartbeats due at `now`.
    pub fn heartbeats(&mut self, now: Instant, out: &mut Vec<CanPayload>) {
        for axis in 0..self.drives.len() {
            let drive = &mut self.drives[axis];
            if drive.heartbeat_ms == 0 || now < drive.next_heartbeat {
                continue;
            }
            drive.next_heartbeat = now + Duration::from_millis(u64::from(drive.heartbeat_ms));
            let (id, state) = (cob::HEARTBEAT + u32::from(drive.node), drive.nmt);
            self.push(out, id, &[state]);
        }
    }

    /// When the next heartbeat is due, if any drive produces one.
    pub fn next_heartbeat(&self) -> Option<Instant> {
        self.drives
            .iter()
            .filter(|d| d.heartbeat_ms > 0)
            .map(|d| d.next_heartbeat)
            .min()
    }

    fn push(&mut self, out: &mut Vec<CanPayload>, id: u32, data: &[u8]) {
        let mut frame = CanPayload {
            id,
            data: [0; 64],
            len: data.len() as u8,
            fd: false,
        };
        frame.data[..data.len()].copy_from_slice(data);
        self.counters.frames_sent += 1;
        self.count_bits(&frame);
        out.push(frame);
    }

    fn count_bits(&mut self, frame: &CanPayload) {
        if self.first_sync.is_some() || frame.id == cob::SYNC {
            self.counters.bus_bits += u64::from(classic_frame_bits(usize::from(frame.len), true));
        }
    }

    fn nmt(&mut self, command: u8, node: u8, now: Instant, out: &mut Vec<CanPayload>) {
        for axis in 0..self.drives.len() {
            if node != 0 && self.drives[axis].node != node {
                continue;
            }
            let drive = &mut self.drives[axis];
            match command {
                nmt_command::START => drive.nmt = nmt_state::OPERATIONAL,
                nmt_command::STOP => drive.nmt = nmt_state::STOPPED,
                nmt_command::ENTER_PRE_OPERATIONAL => drive.nmt = nmt_state::PRE_OPERATIONAL,
                nmt_command::RESET_NODE | nmt_command::RESET_COMMUNICATION => {
                    let id = u32::from(drive.node);
                    // Communication objects to their defaults (CiA 301 7.2.8.2.2.4); a
                    // node reset also restarts the application: power off, no fault.
                    drive.rpdo = Pdo::default_for(
                        cob::RPDO1 + id,
                        mapping_entry(object::CONTROLWORD, 0, 16),
                    );
                    drive.tpdo =
                        Pdo::default_for(cob::TPDO1 + id, mapping_entry(object::STATUSWORD, 0, 16));
                    drive.heartbeat_ms = 0;
                    drive.pending = None;
                    if command == nmt_command::RESET_NODE {
                        drive.power = PowerState::SwitchOnDisabled;
                        drive.error_register = 0;
                        drive.mode = 0;
                    }
                    drive.nmt = nmt_state::PRE_OPERATIONAL;
                    drive.next_heartbeat = now;
                    self.push(out, cob::HEARTBEAT + id, &[nmt_state::BOOT_UP]);
                }
                _ => {}
            }
        }
    }

    /// The SDO server (expedited transfers): the answer to one request.
    fn sdo(&mut self, axis: usize, request: &[u8], out: &mut Vec<CanPayload>) -> [u8; 8] {
        let address = |at: (u16, u8)| crate::device::canopen::wire::Address::new(at.0, at.1);
        let aborted = |at: (u16, u8), code: u32| {
            let mut p = [0u8; 8];
            p[0] = 0x80;
            p[1..3].copy_from_slice(&at.0.to_le_bytes());
            p[3] = at.1;
            p[4..].copy_from_slice(&code.to_le_bytes());
            p
        };
        match SdoRequest::parse(request) {
            Some(SdoRequest::Upload { at }) => match self.read(axis, at) {
                Ok(value) => canopen_rs::sdo::encode_upload_expedited_response(address(at), &value)
                    .unwrap_or_else(|_| aborted(at, abort::LENGTH_MISMATCH)),
                Err(code) => aborted(at, code),
            },
            Some(SdoRequest::Download { at, data, len }) => {
                match self.write(axis, at, &data[..len], out) {
                    Ok(()) => canopen_rs::sdo::encode_download_response(address(at)),
                    Err(code) => aborted(at, code),
                }
            }
            Some(SdoRequest::Unsupported { at }) => aborted(at, abort::COMMAND_INVALID),
            None => canopen_rs::sdo::encode_abort(address((0, 0)), SdoAbortCode::CommandInvalid),
        }
    }

    fn statusword(drive: &Drive) -> u16 {
        drive.power.bits() | STATUS_REMOTE
    }

    fn read(&self, axis: usize, at: (u16, u8)) -> Result<Value, u32> {
        let drive = &self.drives[axis];
        let pdo_param = |pdo: &Pdo, sub: u8| match sub {
            0 => Ok(Value::Unsigned8(2)),
            1 => Ok(Value::Unsigned32(pdo.cob_id)),
            2 => Ok(Value::Unsigned8(pdo.transmission)),
            _ => Err(abort::NO_SUB_INDEX),
        };
        let mapping = |pdo: &Pdo, sub: u8| match sub {
            0 => Ok(Value::Unsigned8(pdo.count)),
            1..=8 => Ok(Value::Unsigned32(pdo.entries[usize::from(sub) - 1])),
            _ => Err(abort::NO_SUB_INDEX),
        };
        match at {
            (object::DEVICE_TYPE, 0) => Ok(Value::Unsigned32(DRIVE_PROFILE)),
            (object::ERROR_REGISTER, 0) => Ok(Value::Unsigned8(drive.error_register)),
            (object::HEARTBEAT_PRODUCER, 0) => Ok(Value::Unsigned16(drive.heartbeat_ms)),
            (object::RPDO1_COMM, sub) => pdo_param(&drive.rpdo, sub),
            (object::TPDO1_COMM, sub) => pdo_param(&drive.tpdo, sub),
            (object::RPDO1_MAP, sub) => mapping(&drive.rpdo, sub),
            (object::TPDO1_MAP, sub) => mapping(&drive.tpdo, sub),
            (object::CONTROLWORD, 0) => Ok(Value::Unsigned16(drive.controlword)),
            (object::STATUSWORD, 0) => Ok(Value::Unsigned16(Self::statusword(drive))),
            (object::MODES_OF_OPERATION, 0) => Ok(Value::Integer8(drive.mode)),
            (object::MODES_OF_OPERATION_DISPLAY, 0) => Ok(Value::Integer8(drive.mode)),
            (object::POSITION_ACTUAL, 0) => Ok(Value::Integer32(drive.actual.round() as i32)),
            (object::TARGET_POSITION, 0) => Ok(Value::Integer32(drive.target)),
            (object::INTERPOLATION_PERIOD, 0) => Ok(Value::Unsigned8(2)),
            (object::INTERPOLATION_PERIOD, 1) => Ok(Value::Unsigned8(drive.ip.0)),
            (object::INTERPOLATION_PERIOD, 2) => Ok(Value::Integer8(drive.ip.1)),
            (
                object::DEVICE_TYPE
                | object::ERROR_REGISTER
                | object::HEARTBEAT_PRODUCER
                | object::CONTROLWORD
                | object::STATUSWORD
                | object::MODES_OF_OPERATION
                | object::MODES_OF_OPERATION_DISPLAY
                | object::POSITION_ACTUAL
                | object::TARGET_POSITION
                | object::INTERPOLATION_PERIOD,
                _,
            ) => Err(abort::NO_SUB_INDEX),
            _ => Err(abort::NO_OBJECT),
        }
    }

    /// An SDO download: the value's length must be the object's.
    fn write(
        &mut self,
        axis: usize,
        at: (u16, u8),
        data: &[u8],
        out: &mut Vec<CanPayload>,
    ) -> Result<(), u32> {
        let size = match self.read(axis, at)? {
            Value::Unsigned8(_) | Value::Integer8(_) => 1,
            Value::Unsigned16(_) => 2,
            _ => 4,
        };
        if data.len() != size {
            return Err(abort::LENGTH_MISMATCH);
        }
        let mut wide = [0u8; 4];
        wide[..size].copy_from_slice(data);
        let raw = u32::from_le_bytes(wide);
        if at == (object::CONTROLWORD, 0) {
            self.controlword(axis, raw as u16, out);
            return Ok(());
        }
        let drive = &mut self.drives[axis];
        match at {
            (object::DEVICE_TYPE | object::ERROR_REGISTER, _)
            | (object::STATUSWORD | object::MODES_OF_OPERATION_DISPLAY, _)
            | (object::POSITION_ACTUAL, _)
            | (object::INTERPOLATION_PERIOD, 0)
            | (object::RPDO1_COMM | object::TPDO1_COMM, 0) => Err(abort::WRITE_READ_ONLY),
            (object::HEARTBEAT_PRODUCER, 0) => {
                drive.heartbeat_ms = raw as u16;
                drive.next_heartbeat = Instant::now();
                Ok(())
            }
            (object::RPDO1_COMM, sub) => write_pdo_param(&mut drive.rpdo, drive.nmt, sub, raw),
            (object::TPDO1_COMM, sub) => write_pdo_param(&mut drive.tpdo, drive.nmt, sub, raw),
            (object::RPDO1_MAP, sub) => write_mapping(&mut drive.rpdo, sub, raw, true),
            (object::TPDO1_MAP, sub) => write_mapping(&mut drive.tpdo, sub, raw, false),
            (object::MODES_OF_OPERATION, 0) if raw as u8 as i8 == CSP_MODE => {
                drive.mode = CSP_MODE;
                Ok(())
            }
            (object::MODES_OF_OPERATION, 0) => Err(abort::INVALID_VALUE),
            (object::TARGET_POSITION, 0) => {
                drive.target = raw as i32;
                Ok(())
            }
            (object::INTERPOLATION_PERIOD, 1) => {
                drive.ip.0 = raw as u8;
                Ok(())
            }
            (object::INTERPOLATION_PERIOD, 2) if period_of(1, raw as u8 as i8).is_some() => {
                drive.ip.1 = raw as u8 as i8;
                Ok(())
            }
            _ => Err(abort::INVALID_VALUE),
        }
    }

    /// The power state machine (CiA 402-2 figure 6, table 7) on a new controlword.
    fn controlword(&mut self, axis: usize, word: u16, out: &mut Vec<CanPayload>) {
        let drive = &mut self.drives[axis];
        let rising_reset = word & 0x80 != 0 && drive.controlword & 0x80 == 0;
        drive.controlword = word;
        let shutdown = word & 0x87 == 0x06;
        let switch_on = word & 0x8F == 0x07;
        let enable = word & 0x8F == 0x0F;
        let disable_voltage = word & 0x82 == 0x00;
        let quick_stop = word & 0x86 == 0x02;
        use PowerState::*;
        let next = match drive.power {
            Fault if rising_reset => SwitchOnDisabled,
            Fault | FaultReactionActive | NotReadyToSwitchOn => drive.power,
            SwitchOnDisabled if shutdown => ReadyToSwitchOn,
            ReadyToSwitchOn if switch_on || enable => SwitchedOn,
            ReadyToSwitchOn | SwitchedOn if disable_voltage || quick_stop => SwitchOnDisabled,
            SwitchedOn if enable => OperationEnabled,
            SwitchedOn if shutdown => ReadyToSwitchOn,
            OperationEnabled if switch_on => SwitchedOn,
            OperationEnabled if shutdown => ReadyToSwitchOn,
            OperationEnabled if disable_voltage => SwitchOnDisabled,
            OperationEnabled if quick_stop => QuickStopActive,
            QuickStopActive if disable_voltage => SwitchOnDisabled,
            other => other,
        };
        if next == OperationEnabled && drive.power != OperationEnabled {
            // The path starts where the drive stands: the first target is judged from it.
            let here = drive.actual.round() as i32;
            drive.history = [here, here];
            drive.following = true;
        }
        if next != OperationEnabled {
            drive.following = false;
        }
        let was_fault = drive.power == Fault;
        drive.power = next;
        if was_fault && next == SwitchOnDisabled {
            drive.error_register = 0;
            let id = cob::EMCY + u32::from(drive.node);
            let reset = canopen_rs::EmergencyMessage::error_reset().encode();
            self.counters.emcys += 1;
            self.push(out, id, &reset);
        }
    }

    /// A latched fault: the fault state, the error register, an EMCY.
    fn fault(&mut self, axis: usize, code: u16, out: &mut Vec<CanPayload>) {
        let drive = &mut self.drives[axis];
        if drive.power == PowerState::Fault {
            return;
        }
        drive.power = PowerState::Fault;
        drive.following = false;
        drive.error_register |= GENERIC_ERROR;
        let register = canopen_rs::ErrorRegister(drive.error_register);
        let emcy = canopen_rs::EmergencyMessage::new(code, register, [0; 5]).encode();
        let id = cob::EMCY + u32::from(drive.node);
        self.counters.faults += 1;
        self.counters.emcys += 1;
        self.faulted = true;
        self.push(out, id, &emcy);
    }

    /// One SYNC: RPDOs taken, each enabled drive one period along its path, TPDOs out.
    fn sync(&mut self, now: Instant, out: &mut Vec<CanPayload>) {
        let streamed = self.rpdos_since_sync > 0;
        self.rpdos_since_sync = 0;
        self.note_sync(now, streamed);
        for axis in 0..self.drives.len() {
            if self.drives[axis].nmt != nmt_state::OPERATIONAL {
                continue;
            }
            if let Some(bytes) = self.drives[axis].pending.take() {
                self.apply_rpdo(axis, &bytes, out);
            }
            self.follow(axis, out);
            let drive = &self.drives[axis];
            if drive.tpdo.valid() && (1..=240).contains(&drive.tpdo.transmission) {
                let data = self.tpdo_data(axis);
                let id = self.drives[axis].tpdo.cob_id & COB_ID_MASK;
                self.counters.tpdos += 1;
                self.push(out, id, &data);
            }
        }
    }

    fn note_sync(&mut self, now: Instant, streamed: bool) {
        self.counters.syncs += 1;
        let first = *self.first_sync.get_or_insert(now);
        self.counters.sync_span = now.duration_since(first);
        if streamed {
            self.counters.streamed_syncs += 1;
            if self.faulted {
                self.counters.streamed_after_fault += 1;
            }
        }
        if let Some(last) = self.last_sync
            && streamed
            && self.last_streamed
        {
            let interval = now.duration_since(last);
            self.counters.longest_interval = self.counters.longest_interval.max(interval);
            if interval.as_secs_f64() > OVERRUN_PERIODS * self.period(0).as_secs_f64() {
                self.counters.overruns += 1;
            }
        }
        self.last_sync = Some(now);
        self.last_streamed = streamed;
    }

    /// The period a drive judges targets over: its 0x60C2, else the settings'.
    fn period(&self, axis: usize) -> Duration {
        let (value, exponent) = self.drives.get(axis).map_or((0, 0), |d| d.ip);
        period_of(value, exponent)
            .filter(|p| !p.is_zero())
            .unwrap_or(self.settings.period)
    }

    fn apply_rpdo(&mut self, axis: usize, bytes: &[u8; 8], out: &mut Vec<CanPayload>) {
        let mut offset = 0;
        let entries: Vec<u32> = self.drives[axis].rpdo.mapped().to_vec();
        for entry in entries {
            let len = (entry & 0xFF) as usize / 8;
            let mut wide = [0u8; 4];
            wide[..len].copy_from_slice(&bytes[offset..offset + len]);
            let raw = u32::from_le_bytes(wide);
            offset += len;
            match (entry >> 16) as u16 {
                object::CONTROLWORD => self.controlword(axis, raw as u16, out),
                object::TARGET_POSITION => self.drives[axis].target = raw as i32,
                _ => {}
            }
        }
    }

    /// In operation enabled and CSP: 0x607A is the next point, judged, then followed.
    fn follow(&mut self, axis: usize, out: &mut Vec<CanPayload>) {
        let dt = self.period(axis).as_secs_f64();
        let smoothing = 1.0 - (-std::f64::consts::TAU * self.settings.bandwidth_hz * dt).exp();
        let drive = &self.drives[axis];
        if !drive.following || drive.mode != CSP_MODE {
            return;
        }
        let target = drive.target;
        self.counters.targets += 1;
        if let Some((code, why)) = self.judge(axis, target, dt) {
            self.fault(axis, code, out);
            self.fault_text = Some(format!(
                "node {} (axis {}): {why}",
                self.drives[axis].node,
                axis + 1
            ));
            return;
        }
        let drive = &mut self.drives[axis];
        drive.history = [drive.history[1], target];
        drive.actual += smoothing * (f64::from(target) - drive.actual);
    }

    /// The EMCY code of what is wrong with `target` as the next point, if anything is.
    fn judge(&mut self, axis: usize, target: i32, dt: f64) -> Option<(u16, String)> {
        let drive = &self.drives[axis];
        let (a, b) = (
            drive.counts.tick(drive.limits.lower),
            drive.counts.tick(drive.limits.upper),
        );
        let t = f64::from(target);
        if t < a.min(b) || t > a.max(b) {
            self.counters.outside_limits += 1;
            let why = format!("target {target} outside the limits, counts {a} .. {b}");
            return Some((emcy_code::REFERENCE_LIMIT, why));
        }
        let scale = drive.counts.per_unit();
        let max_step =
            drive.limits.max_speed * scale * dt * (1.0 + LIMIT_SLACK) + STEP_ROUNDING_COUNTS;
        let max_second = drive.limits.max_acceleration * scale * dt * dt * (1.0 + LIMIT_SLACK)
            + SECOND_DIFFERENCE_ROUNDING_COUNTS;
        let [before, last] = drive.history.map(f64::from);
        let (step, second) = ((t - last).abs(), (t - 2.0 * last + before).abs());
        if step > max_step {
            self.counters.over_speed += 1;
            let why = format!(
                "target {target}: a step of {step} counts over one period, above {max_step:.0} (speed)"
            );
            return Some((emcy_code::SPEED, why));
        }
        if second > max_second {
            self.counters.over_acceleration += 1;
            let why = format!(
                "target {target}: a second difference of {second} counts, above {max_second:.0} (acceleration)"
            );
            return Some((emcy_code::POSITIONING, why));
        }
        None
    }

    fn tpdo_data(&self, axis: usize) -> Vec<u8> {
        let drive = &self.drives[axis];
        let mut data = Vec::with_capacity(PDO_BYTES);
        for entry in drive.tpdo.mapped() {
            let len = (entry & 0xFF) as usize / 8;
            let at = ((entry >> 16) as u16, ((entry >> 8) & 0xFF) as u8);
            let raw: u32 = match self.read(axis, at) {
                Ok(Value::Unsigned16(v)) => u32::from(v),
                Ok(Value::Integer32(v)) => v as u32,
                Ok(Value::Integer8(v)) => u32::from(v as u8),
                _ => 0,
            };
            data.extend_from_slice(&raw.to_le_bytes()[..len]);
        }
        data
    }
}

/// Bytes a mapping's entries take.
fn pdo_length(entries: &[u32]) -> usize {
    entries.iter().map(|e| (e & 0xFF) as usize / 8).sum()
}

/// A PDO communication parameter: the COB-ID only switching validity (or, while invalid,
/// to a new identifier), the transmission type only while invalid, neither while
/// operational (CiA 301 7.5.2.35).
fn write_pdo_param(pdo: &mut Pdo, nmt: u8, sub: u8, raw: u32) -> Result<(), u32> {
    if nmt == nmt_state::OPERATIONAL {
        return Err(abort::DEVICE_STATE);
    }
    match sub {
        1 => {
            let validating = raw & PDO_INVALID == 0;
            if pdo.valid() && validating && raw != pdo.cob_id {
                return Err(abort::INVALID_VALUE);
            }
            if validating && pdo_length(pdo.mapped()) > PDO_BYTES {
                return Err(abort::MAPPING_TOO_LONG);
            }
            pdo.cob_id = raw;
            Ok(())
        }
        2 if pdo.valid() => Err(abort::DEVICE_STATE),
        2 => {
            pdo.transmission = raw as u8;
            Ok(())
        }
        _ => Err(abort::NO_SUB_INDEX),
    }
}

/// A PDO mapping write by the CiA 301 procedure (7.4.8): only while the PDO is invalid,
/// entries only while sub-index 0 is 0, sub-index 0 only up to the entries written, each
/// entry an object this drive maps in that direction, 8 bytes at most.
fn write_mapping(pdo: &mut Pdo, sub: u8, raw: u32, receive: bool) -> Result<(), u32> {
    if pdo.valid() {
        return Err(abort::DEVICE_STATE);
    }
    match sub {
        0 => {
            let n = raw as u8;
            if n > 8 {
                return Err(abort::MAPPING_TOO_LONG);
            }
            let entries = &pdo.entries[..usize::from(n)];
            if entries.iter().any(|e| !mappable(*e, receive)) {
                return Err(abort::CANNOT_MAP);
            }
            if pdo_length(entries) > PDO_BYTES {
                return Err(abort::MAPPING_TOO_LONG);
            }
            pdo.count = n;
            Ok(())
        }
        1..=8 if pdo.count != 0 => Err(abort::DEVICE_STATE),
        1..=8 if !mappable(raw, receive) => Err(abort::CANNOT_MAP),
        1..=8 => {
            pdo.entries[usize::from(sub) - 1] = raw;
            Ok(())
        }
        _ => Err(abort::NO_SUB_INDEX),
    }
}

/// Objects this drive maps: controlword, mode and target into an RPDO; statusword, mode
/// display and position actual into a TPDO; each whole.
fn mappable(entry: u32, receive: bool) -> bool {
    let objects: [(u16, u8); 3] = if receive {
        [
            (object::CONTROLWORD, 16),
            (object::MODES_OF_OPERATION, 8),
            (object::TARGET_POSITION, 32),
        ]
    } else {
        [
            (object::STATUSWORD, 16),
            (object::MODES_OF_OPERATION_DISPLAY, 8),
            (object::POSITION_ACTUAL, 32),
        ]
    };
    objects
        .iter()
        .any(|&(index, bits)| entry == mapping_entry(index, 0, bits))
}

/// Operator actions from another thread: a drive fault, shut down.
#[derive(Debug, Default)]
pub struct CanopenTwinControl {
    faults: std::sync::Mutex<Vec<usize>>,
    pub stop: AtomicBool,
}

impl CanopenTwinControl {
    /// Raises a drive fault on `axis` (from 0) at once.
    pub fn fault(&self, axis: usize) {
        self.faults
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .push(axis);
    }

    fn take(&self) -> Vec<usize> {
        std::mem::take(&mut *self.faults.lock().unwrap_or_else(|p| p.into_inner()))
    }
}

/// One CAN frame in the byte framing a [`ControllerPort`] carries: identifier (2 bytes,
/// little endian), length, data.
pub fn frame_bytes(frame: &CanPayload, out: &mut Vec<u8>) {
    out.extend_from_slice(&(frame.id as u16).to_le_bytes());
    out.push(frame.len);
    out.extend_from_slice(&frame.data[..usize::from(frame.len)]);
}

/// The frame at the start of `bytes` (as [`frame_bytes`] wrote it) and its length.
pub fn frame_of(bytes: &[u8]) -> Option<(CanPayload, usize)> {
    let id = u32::from(u16::from_le_bytes(bytes.get(..2)?.try_into().ok()?));
    let len = usize::from(*bytes.get(2)?);
    let data = bytes.get(FRAME_HEADER..FRAME_HEADER + len.min(8))?;
    let mut frame = CanPayload {
        id,
        data: [0; 64],
        len: data.len() as u8,
        fd: false,
    };
    frame.data[..data.len()].copy_from_slice(data);
    Some((frame, FRAME_HEADER + data.len()))
}

/// How long the loop waits for a frame when no heartbeat is due sooner.
const IDLE_WAIT: Duration = Duration::from_millis(10);

/// Serves the drives on `port` until `control.stop`: answers every frame at once, sends
/// heartbeats when due. Logs faults and the first master's frames.
pub fn serve_canopen(
    bus: &mut CanopenBus,
    port: &mut dyn ControllerPort,
    control: &CanopenTwinControl,
) {
    let mut buffer = vec![0u8; 4096];
    let mut out: Vec<CanPayload> = Vec::with_capacity(64);
    let mut bytes = Vec::with_capacity(256);
    let mut attached = false;
    while !control.stop.load(Ordering::SeqCst) {
        let now = Instant::now();
        for axis in control.take() {
            bus.inject_fault(axis, &mut out);
            tracing::warn!("drive fault on axis {}", axis + 1);
        }
        bus.heartbeats(now, &mut out);
        let (faults_before, streamed_before) = (bus.counters.faults, bus.counters.streamed_syncs);
        if send_all(port, &mut out, &mut bytes).is_err() {
            tracing::warn!("write failed");
        }
        let wait = bus
            .next_heartbeat()
            .map_or(IDLE_WAIT, |t| t.saturating_duration_since(Instant::now()))
            .min(IDLE_WAIT);
        let n = match port.read_within(&mut buffer, wait) {
            Ok(n) => n,
            Err(_) => {
                std::thread::sleep(wait);
                continue;
            }
        };
        let mut at = 0;
        while let Some((frame, used)) = frame_of(&buffer[at..n]) {
            at += used;
            if !attached {
                attached = true;
                tracing::info!("master attached");
            }
            bus.handle(&frame, Instant::now(), &mut out);
        }
        if send_all(port, &mut out, &mut bytes).is_err() {
            tracing::warn!("write failed");
        }
        if streamed_before == 0 && bus.counters.streamed_syncs > 0 {
            tracing::info!("targets arriving");
        }
        if bus.counters.faults > faults_before {
            let why = bus.take_fault_text();
            tracing::warn!(
                "drive fault latched{}",
                why.map(|w| format!(": {w}")).unwrap_or_default()
            );
        }
    }
}

fn send_all(
    port: &mut dyn ControllerPort,
    out: &mut Vec<CanPayload>,
    bytes: &mut Vec<u8>,
) -> std::io::Result<()> {
    for frame in out.drain(..) {
        bytes.clear();
        frame_bytes(&frame, bytes);
        port.write_frame(bytes)?;
    }
    Ok(())
}

/// The drives' end of a SocketCAN interface as a [`ControllerPort`]: each read hands over
/// the frames waiting, each write sends one frame (both in [`frame_bytes`] framing).
pub struct CanopenPort {
    bus: crate::transport::CanBus,
}

impl CanopenPort {
    pub fn open(interface: &str) -> std::io::Result<Self> {
        Ok(Self {
            bus: crate::transport::CanBus::open_classic(interface)?,
        })
    }
}

impl ControllerPort for CanopenPort {
    fn attached(&mut self) -> bool {
        true
    }

    fn read_within(&mut self, buffer: &mut [u8], timeout: Duration) -> std::io::Result<usize> {
        if !self.bus.wait_readable(timeout)? {
            return Ok(0);
        }
        let mut bytes = Vec::with_capacity(64);
        let mut n = 0;
        // Whole frames only, as many as fit.
        while n + FRAME_HEADER + 8 <= buffer.len() {
            let Some(frame) = self.bus.try_receive()? else {
                break;
            };
            bytes.clear();
            frame_bytes(&frame, &mut bytes);
            buffer[n..n + bytes.len()].copy_from_slice(&bytes);
            n += bytes.len();
        }
        Ok(n)
    }

    fn write_frame(&mut self, frame: &[u8]) -> std::io::Result<()> {
        let (frame, _) = frame_of(frame).ok_or_else(|| {
            std::io::Error::new(std::io::ErrorKind::InvalidInput, "not a CAN frame")
        })?;
        self.bus
            .send_patiently(&frame, crate::transport::SEND_PATIENCE)
    }

    fn detach(&mut self) {}

    fn describe(&self) -> String {
        format!("canopen://{}", self.bus.interface())
    }
}
