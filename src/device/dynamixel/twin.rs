//! The Dynamixel twin: N servos on one Protocol 2.0 bus (a serial port or a pty), one per
//! axis of the rig, for the bridge's Dynamixel link or any other master (dynamixel-sdk).
//!
//! Each servo keeps a subset of the X-series control table (docs/dynamixel.md): Model
//! Number (0), Firmware Version (6), ID (7), Operating Mode (11), Max/Min Position Limit
//! (48, 52), Torque Enable (64), Hardware Error Status (70), Goal Position (116) and
//! Present Position (132). It answers Ping, Read, Write, Sync Read, Sync Write and Reboot,
//! and is strict: an instruction it does not know gets the Instruction error, a write to
//! the EEPROM area while torque is on or to a read-only or unknown address the Access
//! error, a value outside a register's range the Data Range error, a goal outside the
//! axis' limits the Data Limit error (Sync Write has no status of its own: the next status
//! packet carries it), a wrong length the Data Length error; a packet with a bad CRC gets
//! no answer. With torque on it moves toward its goal within the axis' speed and
//! acceleration, and counts every goal whose step is over the axis' speed, or whose second
//! difference is over its acceleration, beyond what rounding to ticks explains (one tick
//! for a step, two for a second difference), as the EGM twin counts references. It owns
//! the simulated servos only; it must not know about trajectories or jobs.

use crate::device::dynamixel::wire::{
    AxisTicks, BROADCAST_ID, EXTENDED_POSITION_MODE, EXTENDED_RANGE, POSITION_MODE, Packet,
    PacketDecoder, address, encode_status, error, instruction,
};
use crate::rig::{JointLimits, LIMIT_SLACK, Rig};
use crate::twin::server::ControllerPort;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};
use thiserror::Error;

/// The model the twin's servos report: XM430-W210, the e-manual's Ping example (1030).
pub const MODEL_NUMBER: u16 = 1030;
/// The firmware version of the same example (0x26).
pub const FIRMWARE_VERSION: u8 = 0x26;
/// The single-turn Goal Position range of position control mode (XM430 e-manual,
/// "Max/Min Position Limit (48, 52)": 0 to 4095).
/// Periods of motion a held twin thread simulates at once when it wakes: 0.1 s at 250 Hz,
/// the bridge's own patience for a silent link; a longer hold is the host's, not a servo's.
const MAX_CATCH_UP_PERIODS: u32 = 25;
const SINGLE_TURN_MAX: i64 = 4095;
/// A bus without a goal for this many periods is at rest: the next goal's step and second
/// difference are judged from the goal in force (25, the streamer's patience).
const REST_PERIODS: u32 = 25;
/// A goal after at least this many periods without one may also be a start from rest (a
/// master resuming after a hold): it passes if it passes either way, by order or from the
/// goal in force, since a late goal of a moving stream is judged by order.
const PAUSE_PERIODS: u32 = 2;
/// Rounding to ticks moves a goal by up to half a tick: a step by up to one, a second
/// difference by up to two.
const STEP_ROUNDING_TICKS: f64 = 1.0;
const SECOND_DIFFERENCE_ROUNDING_TICKS: f64 = 2.0;
/// Bytes read at once from the port.
const READ_CHUNK: usize = 1024;

#[derive(Debug, Clone, PartialEq, Error)]
pub enum DynamixelTwinError {
    #[error("{ids} servo ids for a rig of {axes} axes")]
    IdCount { ids: usize, axes: usize },
    #[error("servo id {0} is not a servo id (0 to 252) or appears twice")]
    BadId(u8),
    #[error("initial position: {0}")]
    InitialOutsideLimits(crate::rig::OutsideLimits),
    #[error("Dynamixel twin setting {0} must be finite and positive")]
    BadSetting(&'static str),
}

/// What the twin saw, for summaries and tests.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct DynamixelTwinCounters {
    pub packets: u64,
    pub crc_errors: u64,
    pub statuses_sent: u64,
    /// Status packets with a non-zero error byte.
    pub errors_answered: u64,
    pub unknown_instructions: u64,
    pub access_errors: u64,
    pub pings: u64,
    pub sync_writes: u64,
    pub sync_reads: u64,
    /// Goals accepted (each servo's own).
    pub goals: u64,
    pub outside_limits: u64,
    pub over_speed: u64,
    pub over_acceleration: u64,
    /// Torque switched on with the goal more than a tick from the present position: the
    /// servo would jump there.
    pub stale_goal_at_torque_on: u64,
}

impl DynamixelTwinCounters {
    pub fn violations(&self) -> u64 {
        self.outside_limits
            + self.over_speed
            + self.over_acceleration
            + self.stale_goal_at_torque_on
    }
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DynamixelTwinSettings {
    /// The bridge's cycle: one goal per period is how steps are judged.
    pub period: Duration,
    /// Position loop bandwidth, Hz: speed = 2 pi f (goal - present), within the limits.
    pub bandwidth_hz: f64,
}

struct Servo {
    id: u8,
    ticks: AxisTicks,
    limits: JointLimits,
    mode: u8,
    torque: bool,
    hardware_error: u8,
    max_limit: i64,
    min_limit: i64,
    goal: i64,
    /// Present position (ticks, continuous) and speed (ticks/s).
    present: f64,
    speed: f64,
    /// The goals before the newest, for the step and second difference.
    history: [i64; 2],
    periods_since_goal: u32,
    /// An error a sync-written goal met, for the next status packet.
    pending: u8,
}

impl Servo {
    /// The axis' limits in ticks, rounded as the master rounds targets.
    fn axis_range(&self) -> (i64, i64) {
        let (a, b) = (
            self.ticks.tick(self.limits.lower) as i64,
            self.ticks.tick(self.limits.upper) as i64,
        );
        (a.min(b), a.max(b))
    }

    fn goal_range(&self) -> (i64, i64) {
        let (low, high) = self.axis_range();
        if self.mode == EXTENDED_POSITION_MODE {
            (low.max(-EXTENDED_RANGE), high.min(EXTENDED_RANGE))
        } else {
            (low.max(self.min_limit), high.min(self.max_limit))
        }
    }

    fn error_byte(&mut self, code: u8) -> u8 {
        let code = if code == 0 {
            std::mem::take(&mut self.pending)
        } else {
            code
        };
        if self.hardware_error != 0 {
            code | error::ALERT
        } else {
            code
        }
    }

    fn present_tick(&self) -> i64 {
        self.present.round() as i64
    }
}

/// The registers the twin keeps: address, size, writable, EEPROM.
const REGISTERS: [(u16, u16, bool); 10] = [
    (address::MODEL_NUMBER, 2, false),
    (address::FIRMWARE_VERSION, 1, false),
    (address::ID, 1, true),
    (address::OPERATING_MODE, 1, true),
    (address::MAX_POSITION_LIMIT, 4, true),
    (address::MIN_POSITION_LIMIT, 4, true),
    (address::TORQUE_ENABLE, 1, true),
    (address::HARDWARE_ERROR_STATUS, 1, false),
    (address::GOAL_POSITION, 4, true),
    (address::PRESENT_POSITION, 4, false),
];

fn register_at(at: u16) -> Option<(u16, u16, bool)> {
    REGISTERS.iter().copied().find(|(a, _, _)| *a == at)
}

/// The simulated bus: servos in axis order and what they counted.
pub struct DynamixelBus {
    servos: Vec<Servo>,
    settings: DynamixelTwinSettings,
    pub counters: DynamixelTwinCounters,
}

impl DynamixelBus {
    /// Servos `ids` (axis order) of `rig` at `initial` (rad), torque off, position mode,
    /// position limits set to the axes' own.
    pub fn new(
        rig: &Rig,
        ids: &[u8],
        ticks: &[AxisTicks],
        initial: &[f64],
        settings: DynamixelTwinSettings,
    ) -> Result<Self, DynamixelTwinError> {
        if ids.len() != rig.dof() || ticks.len() != rig.dof() || initial.len() != rig.dof() {
            return Err(DynamixelTwinError::IdCount {
                ids: ids.len(),
                axes: rig.dof(),
            });
        }
        for (i, id) in ids.iter().enumerate() {
            if *id > crate::device::dynamixel::wire::MAX_SERVO_ID || ids[..i].contains(id) {
                return Err(DynamixelTwinError::BadId(*id));
            }
        }
        rig.check_limits(initial)
            .map_err(|(_, outside)| DynamixelTwinError::InitialOutsideLimits(outside))?;
        for (name, value) in [
            ("period", settings.period.as_secs_f64()),
            ("bandwidth_hz", settings.bandwidth_hz),
        ] {
            if !(value.is_finite() && value > 0.0) {
                return Err(DynamixelTwinError::BadSetting(name));
            }
        }
        let servos = rig
            .joints
            .iter()
            .zip(ids)
            .zip(ticks.iter().zip(initial))
            .map(|((joint, &id), (&ticks, &rad))| {
                let present = ticks.tick(rad);
                let mut servo = Servo {
                    id,
                    ticks,
                    limits: joint.limits,
                    mode: POSITION_MODE,
                    torque: false,
                    hardware_error: 0,
                    max_limit: SINGLE_TURN_MAX,
                    min_limit: 0,
                    // A goal register left elsewhere, as after an earlier session: a master
                    // that turns torque on without writing it sees the servo jump.
                    goal: present as i64 + 100,
                    present,
                    speed: 0.0,
                    history: [0, 0],
                    periods_since_goal: REST_PERIODS,
                    pending: 0,
                };
                let (low, high) = servo.axis_range();
                servo.min_limit = low.clamp(0, SINGLE_TURN_MAX);
                servo.max_limit = high.clamp(0, SINGLE_TURN_MAX);
                servo
            })
            .collect();
        Ok(Self {
            servos,
            settings,
            counters: DynamixelTwinCounters::default(),
        })
    }

    /// Present positions, rad, in axis order.
    pub fn positions(&self) -> Vec<f64> {
        self.servos
            .iter()
            .map(|s| s.ticks.radians(s.present_tick()))
            .collect()
    }

    pub fn torque(&self) -> Vec<bool> {
        self.servos.iter().map(|s| s.torque).collect()
    }

    pub fn modes(&self) -> Vec<u8> {
        self.servos.iter().map(|s| s.mode).collect()
    }

    /// Sets a servo's Hardware Error Status (overload, overheating...): its statuses carry
    /// the alert bit from then on, and torque goes off, as a real servo's would.
    pub fn inject_hardware_error(&mut self, axis: usize, bits: u8) {
        if let Some(servo) = self.servos.get_mut(axis) {
            servo.hardware_error = bits;
            servo.torque = false;
        }
    }

    fn index_of(&self, id: u8) -> Option<usize> {
        self.servos.iter().position(|s| s.id == id)
    }

    /// One period of motion: each servo with torque on moves toward its goal.
    pub fn step(&mut self) {
        let dt = self.settings.period.as_secs_f64();
        let gain = std::f64::consts::TAU * self.settings.bandwidth_hz;
        for servo in &mut self.servos {
            servo.periods_since_goal = servo.periods_since_goal.saturating_add(1);
            if !servo.torque {
                servo.speed = 0.0;
                continue;
            }
            let scale = servo.ticks.per_unit();
            let max_speed = servo.limits.max_speed * scale;
            let braking = servo.limits.max_acceleration * scale * dt;
            let wanted = gain * (servo.goal as f64 - servo.present);
            let next = wanted
                .clamp(servo.speed - braking, servo.speed + braking)
                .clamp(-max_speed, max_speed);
            servo.present += next * dt;
            servo.speed = next;
        }
    }

    /// Answers one packet, appending any status packets to `out`.
    pub fn handle(&mut self, packet: &Packet, out: &mut Vec<u8>) {
        self.counters.packets += 1;
        let unicast = self.index_of(packet.id);
        if packet.id != BROADCAST_ID && unicast.is_none() {
            return;
        }
        let params = packet.params.as_slice();
        match packet.instruction {
            instruction::STATUS => {}
            instruction::PING => self.ping(unicast, out),
            instruction::READ => {
                if let Some(index) = unicast {
                    let (code, data) = self.read(index, params);
                    self.answer(index, code, &data, out);
                }
            }
            instruction::WRITE => self.write_instruction(unicast, params, out),
            instruction::SYNC_READ => self.sync_read(params, out),
            instruction::SYNC_WRITE => self.sync_write(params),
            instruction::REBOOT => {
                if let Some(index) = unicast {
                    let servo = &mut self.servos[index];
                    servo.hardware_error = 0;
                    servo.torque = false;
                    self.answer(index, 0, &[], out);
                }
            }
            _ => {
                self.counters.unknown_instructions += 1;
                if let Some(index) = unicast {
                    self.answer(index, error::INSTRUCTION, &[], out);
                }
            }
        }
    }

    fn answer(&mut self, index: usize, code: u8, data: &[u8], out: &mut Vec<u8>) {
        let servo = &mut self.servos[index];
        let byte = servo.error_byte(code);
        let mut packet = Vec::new();
        encode_status(servo.id, byte, data, &mut packet);
        out.extend_from_slice(&packet);
        self.counters.statuses_sent += 1;
        if byte != 0 {
            self.counters.errors_answered += 1;
        }
        if code == error::ACCESS {
            self.counters.access_errors += 1;
        }
    }

    fn ping(&mut self, unicast: Option<usize>, out: &mut Vec<u8>) {
        self.counters.pings += 1;
        let [m0, m1] = MODEL_NUMBER.to_le_bytes();
        let answering: Vec<usize> = match unicast {
            Some(index) => vec![index],
            None => (0..self.servos.len()).collect(),
        };
        for index in answering {
            self.answer(index, 0, &[m0, m1, FIRMWARE_VERSION], out);
        }
    }

    /// Read: the bytes of `length` at `at`, every one in a register the twin keeps.
    fn read(&self, index: usize, params: &[u8]) -> (u8, Vec<u8>) {
        let [a0, a1, l0, l1] = params else {
            return (error::DATA_LENGTH, Vec::new());
        };
        let at = u16::from_le_bytes([*a0, *a1]);
        let length = u16::from_le_bytes([*l0, *l1]);
        let servo = &self.servos[index];
        let mut data = Vec::with_capacity(usize::from(length));
        for cursor in u32::from(at)..u32::from(at) + u32::from(length) {
            let Some((start, _, _)) = REGISTERS
                .iter()
                .copied()
                .find(|(a, s, _)| (u32::from(*a)..u32::from(*a + *s)).contains(&cursor))
            else {
                return (error::ACCESS, Vec::new());
            };
            let bytes = register_value(servo, start).to_le_bytes();
            data.push(bytes[(cursor - u32::from(start)) as usize]);
        }
        (0, data)
    }

    fn write_instruction(&mut self, unicast: Option<usize>, params: &[u8], out: &mut Vec<u8>) {
        let Some((at, data)) = params
            .split_at_checked(2)
            .map(|(a, d)| (u16::from_le_bytes([a[0], a[1]]), d))
        else {
            if let Some(index) = unicast {
                self.answer(index, error::DATA_LENGTH, &[], out);
            }
            return;
        };
        match unicast {
            Some(index) => {
                let code = self.write(index, at, data);
                self.answer(index, code, &[], out);
            }
            None => {
                for index in 0..self.servos.len() {
                    let code = self.write(index, at, data);
                    self.servos[index].pending = code;
                }
            }
        }
    }

    fn sync_read(&mut self, params: &[u8], out: &mut Vec<u8>) {
        self.counters.sync_reads += 1;
        let Some((head, ids)) = params.split_at_checked(4) else {
            return;
        };
        for &id in ids {
            if let Some(index) = self.index_of(id) {
                let (code, data) = self.read(index, head);
                self.answer(index, code, &data, out);
            }
        }
    }

    fn sync_write(&mut self, params: &[u8]) {
        self.counters.sync_writes += 1;
        let Some(([a0, a1, l0, l1], rest)) = params.split_first_chunk::<4>() else {
            return;
        };
        let at = u16::from_le_bytes([*a0, *a1]);
        let length = usize::from(u16::from_le_bytes([*l0, *l1]));
        for entry in rest.chunks(length + 1) {
            let Some((&id, data)) = entry.split_first() else {
                continue;
            };
            let Some(index) = self.index_of(id) else {
                continue;
            };
            let code = if data.len() == length {
                self.write(index, at, data)
            } else {
                error::DATA_LENGTH
            };
            if code != 0 {
                self.servos[index].pending = code;
            }
        }
    }

    /// Writes `data` at `at` on one servo: the status error number, 0 when done.
    fn write(&mut self, index: usize, at: u16, data: &[u8]) -> u8 {
        let Some((_, size, writable)) = register_at(at) else {
            return error::ACCESS;
        };
        if !writable {
            return error::ACCESS;
        }
        if data.len() != usize::from(size) {
            return error::DATA_LENGTH;
        }
        let mut bytes = [0u8; 4];
        bytes[..data.len()].copy_from_slice(data);
        let value = if size == 4 {
            i64::from(i32::from_le_bytes(bytes))
        } else {
            i64::from(data[0])
        };
        let torque = self.servos[index].torque;
        if at < address::RAM_START && torque {
            return error::ACCESS;
        }
        self.apply(index, at, value)
    }

    fn apply(&mut self, index: usize, at: u16, value: i64) -> u8 {
        if at == address::GOAL_POSITION {
            return self.goal(index, value);
        }
        let servo = &mut self.servos[index];
        match at {
            address::ID
                if (0..=i64::from(crate::device::dynamixel::wire::MAX_SERVO_ID))
                    .contains(&value) =>
            {
                servo.id = value as u8
            }
            address::OPERATING_MODE
                if [POSITION_MODE, EXTENDED_POSITION_MODE].contains(&(value as u8)) =>
            {
                servo.mode = value as u8
            }
            address::MAX_POSITION_LIMIT if (0..=SINGLE_TURN_MAX).contains(&value) => {
                servo.max_limit = value
            }
            address::MIN_POSITION_LIMIT if (0..=SINGLE_TURN_MAX).contains(&value) => {
                servo.min_limit = value
            }
            address::TORQUE_ENABLE if value == 0 || value == 1 => {
                if value == 1 && servo.hardware_error != 0 {
                    return error::RESULT_FAIL;
                }
                if value == 1 && !servo.torque && (servo.goal as f64 - servo.present).abs() > 1.0 {
                    self.counters.stale_goal_at_torque_on += 1;
                }
                servo.torque = value == 1;
                servo.speed = 0.0;
            }
            _ => return error::DATA_RANGE,
        }
        0
    }

    /// A new goal: refused outside the limits, counted when its step or second
    /// difference is over the axis' speed or acceleration.
    fn goal(&mut self, index: usize, goal: i64) -> u8 {
        let dt = self.settings.period.as_secs_f64();
        let servo = &mut self.servos[index];
        let (low, high) = servo.goal_range();
        if goal < low || goal > high {
            self.counters.outside_limits += 1;
            return error::DATA_LIMIT;
        }
        if servo.periods_since_goal >= REST_PERIODS {
            // At rest: the goal in force was held every period since.
            servo.history = [servo.goal, servo.goal];
        }
        let scale = servo.ticks.per_unit();
        let max_step =
            servo.limits.max_speed * scale * dt * (1.0 + LIMIT_SLACK) + STEP_ROUNDING_TICKS;
        let max_second = servo.limits.max_acceleration * scale * dt * dt * (1.0 + LIMIT_SLACK)
            + SECOND_DIFFERENCE_ROUNDING_TICKS;
        let judge = |[before, last]: [i64; 2]| {
            let (g, last, before) = (goal as f64, last as f64, before as f64);
            ((g - last).abs(), (g - 2.0 * last + before).abs())
        };
        let (mut step, mut second) = judge(servo.history);
        if servo.periods_since_goal >= PAUSE_PERIODS {
            let (rest_step, rest_second) = judge([servo.goal, servo.goal]);
            if rest_step <= max_step && rest_second <= max_second {
                (step, second) = (rest_step, rest_second);
            }
        }
        if servo.torque {
            if step > max_step {
                self.counters.over_speed += 1;
            }
            if second > max_second {
                self.counters.over_acceleration += 1;
            }
        }
        // Without torque nothing follows the goal: the next one is judged from it at rest.
        servo.history = if servo.torque {
            [servo.history[1], goal]
        } else {
            [goal, goal]
        };
        servo.goal = goal;
        servo.periods_since_goal = 0;
        self.counters.goals += 1;
        0
    }
}

/// A register's value as the wire carries it (little endian, 4 bytes wide).
fn register_value(servo: &Servo, at: u16) -> i32 {
    match at {
        address::MODEL_NUMBER => i32::from(MODEL_NUMBER),
        address::FIRMWARE_VERSION => i32::from(FIRMWARE_VERSION),
        address::ID => i32::from(servo.id),
        address::OPERATING_MODE => i32::from(servo.mode),
        address::MAX_POSITION_LIMIT => servo.max_limit as i32,
        address::MIN_POSITION_LIMIT => servo.min_limit as i32,
        address::TORQUE_ENABLE => i32::from(servo.torque),
        address::HARDWARE_ERROR_STATUS => i32::from(servo.hardware_error),
        address::GOAL_POSITION => servo.goal as i32,
        address::PRESENT_POSITION => servo.present_tick() as i32,
        _ => 0,
    }
}

/// Operator actions from another thread: a servo's hardware error, shut down.
#[derive(Debug, Default)]
pub struct DynamixelTwinControl {
    hardware_errors: std::sync::Mutex<Vec<(usize, u8)>>,
    pub stop: AtomicBool,
}

impl DynamixelTwinControl {
    /// Sets Hardware Error Status `bits` on `axis`' servo at its next period.
    pub fn hardware_error(&self, axis: usize, bits: u8) {
        self.hardware_errors
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .push((axis, bits));
    }

    fn take(&self) -> Vec<(usize, u8)> {
        std::mem::take(
            &mut *self
                .hardware_errors
                .lock()
                .unwrap_or_else(|p| p.into_inner()),
        )
    }
}

/// Serves the bus on `port` until `control.stop`: answers every packet at once, and moves
/// the servos one period at a time on its own clock. Logs peers and faults.
pub fn serve_dynamixel(
    bus: &mut DynamixelBus,
    port: &mut dyn ControllerPort,
    control: &DynamixelTwinControl,
) {
    let stop = &control.stop;
    let period = bus.settings.period;
    let mut decoder = PacketDecoder::default();
    let mut buffer = vec![0u8; READ_CHUNK];
    let mut out = Vec::with_capacity(READ_CHUNK);
    let mut next_tick = Instant::now() + period;
    let mut attached = false;
    while !stop.load(Ordering::SeqCst) {
        let now = Instant::now();
        if now >= next_tick {
            for (axis, bits) in control.take() {
                bus.inject_hardware_error(axis, bits);
                tracing::warn!("hardware error status {bits:#04x} on axis {}", axis + 1);
            }
            // A servo moves in real time whatever the host does to this thread: the periods
            // it was held past are simulated now (motion only, no message), up to a bound.
            let mut steps = 0;
            while next_tick <= now && steps < MAX_CATCH_UP_PERIODS {
                bus.step();
                next_tick += period;
                steps += 1;
            }
            if next_tick <= now {
                next_tick = now + period;
            }
        }
        let wait = next_tick.saturating_duration_since(Instant::now());
        match port.read_within(&mut buffer, wait) {
            Ok(0) => continue,
            Ok(n) => {
                if !attached {
                    attached = true;
                    tracing::info!("master attached");
                }
                decoder.push(&buffer[..n]);
            }
            Err(_) => {
                if attached {
                    attached = false;
                    decoder.clear();
                    tracing::info!("master detached");
                }
                continue;
            }
        }
        out.clear();
        while let Some(decoded) = decoder.next_packet() {
            match decoded {
                Ok(packet) => bus.handle(&packet, &mut out),
                // No answer to a corrupted packet: its id may be corrupted too.
                Err(_) => bus.counters.crc_errors += 1,
            }
        }
        if !out.is_empty() && port.write_frame(&out).is_err() {
            tracing::warn!("write failed");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::device::dynamixel::wire::{encode_packet, read_params, write_params};

    fn bus() -> DynamixelBus {
        let path = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("config/irb120.toml");
        let rig = crate::rig::load_rig(&path).expect("the IRB 120 loads");
        DynamixelBus::new(
            &rig,
            &[1, 2, 3, 4, 5, 6],
            &[AxisTicks::default(); 6],
            &[0.0; 6],
            DynamixelTwinSettings {
                period: Duration::from_millis(4),
                bandwidth_hz: 20.0,
            },
        )
        .expect("a bus")
    }

    fn exchange(bus: &mut DynamixelBus, id: u8, instruction: u8, params: &[u8]) -> Vec<Packet> {
        let mut bytes = Vec::new();
        encode_packet(id, instruction, params, &mut bytes);
        let mut decoder = PacketDecoder::default();
        decoder.push(&bytes);
        let packet = decoder.next_packet().expect("one").expect("valid");
        let mut out = Vec::new();
        bus.handle(&packet, &mut out);
        decoder.push(&out);
        std::iter::from_fn(|| decoder.next_packet().map(|p| p.expect("valid status"))).collect()
    }

    fn error_of(packets: &[Packet]) -> u8 {
        packets[0].status().expect("a status").0
    }

    #[test]
    fn ping_reports_the_model_and_firmware() {
        let mut bus = bus();
        let answer = exchange(&mut bus, 3, instruction::PING, &[]);
        assert_eq!(answer.len(), 1);
        assert_eq!(answer[0].status(), Some((0, &[0x06, 0x04, 0x26][..])));
        assert!(exchange(&mut bus, 9, instruction::PING, &[]).is_empty());
        assert_eq!(
            exchange(&mut bus, BROADCAST_ID, instruction::PING, &[]).len(),
            6
        );
    }

    #[test]
    fn eeprom_is_locked_while_torque_is_on_and_bad_values_are_refused() {
        let mut bus = bus();
        let mode = write_params(address::OPERATING_MODE, &[EXTENDED_POSITION_MODE]);
        assert_eq!(
            error_of(&exchange(&mut bus, 6, instruction::WRITE, &mode)),
            0
        );
        let torque_on = write_params(address::TORQUE_ENABLE, &[1]);
        // The goal register was left 100 ticks away: torque on makes the servo jump.
        exchange(&mut bus, 6, instruction::WRITE, &torque_on);
        assert_eq!(bus.counters.stale_goal_at_torque_on, 1);
        let back = write_params(address::OPERATING_MODE, &[POSITION_MODE]);
        assert_eq!(
            error_of(&exchange(&mut bus, 6, instruction::WRITE, &back)),
            error::ACCESS
        );
        assert_eq!(bus.modes()[5], EXTENDED_POSITION_MODE);
        let bad = write_params(address::TORQUE_ENABLE, &[2]);
        assert_eq!(
            error_of(&exchange(&mut bus, 1, instruction::WRITE, &bad)),
            error::DATA_RANGE
        );
        let present = write_params(address::PRESENT_POSITION, &[0, 0, 0, 0]);
        assert_eq!(
            error_of(&exchange(&mut bus, 1, instruction::WRITE, &present)),
            error::ACCESS
        );
        let short = write_params(address::GOAL_POSITION, &[0, 8]);
        assert_eq!(
            error_of(&exchange(&mut bus, 1, instruction::WRITE, &short)),
            error::DATA_LENGTH
        );
        assert_eq!(
            error_of(&exchange(&mut bus, 1, 0x92, &[])),
            error::INSTRUCTION
        );
    }

    #[test]
    fn a_goal_outside_the_limits_is_refused_and_a_jump_is_counted() {
        let mut bus = bus();
        // Joint 2 is +-110 deg: 2048 +- 1252 ticks.
        let far = write_params(address::GOAL_POSITION, &3400i32.to_le_bytes());
        assert_eq!(
            error_of(&exchange(&mut bus, 2, instruction::WRITE, &far)),
            error::DATA_LIMIT
        );
        assert_eq!(bus.counters.outside_limits, 1);
        let hold = write_params(address::GOAL_POSITION, &2048i32.to_le_bytes());
        exchange(&mut bus, 2, instruction::WRITE, &hold);
        exchange(
            &mut bus,
            2,
            instruction::WRITE,
            &write_params(address::TORQUE_ENABLE, &[1]),
        );
        // 250 deg/s is 11.4 ticks a 4 ms period: 40 ticks is over speed.
        let jump = write_params(address::GOAL_POSITION, &2088i32.to_le_bytes());
        assert_eq!(
            error_of(&exchange(&mut bus, 2, instruction::WRITE, &jump)),
            0
        );
        assert_eq!(bus.counters.over_speed, 1);
        assert_eq!(bus.counters.over_acceleration, 1);
        let read = exchange(
            &mut bus,
            2,
            instruction::READ,
            &read_params(address::GOAL_POSITION, 4),
        );
        assert_eq!(read[0].status(), Some((0, &2088i32.to_le_bytes()[..])));
    }

    #[test]
    fn a_hardware_error_sets_the_alert_bit_until_a_reboot() {
        let mut bus = bus();
        bus.inject_hardware_error(0, 0x20);
        let answer = exchange(&mut bus, 1, instruction::PING, &[]);
        assert_eq!(error_of(&answer), error::ALERT);
        let bits = exchange(
            &mut bus,
            1,
            instruction::READ,
            &read_params(address::HARDWARE_ERROR_STATUS, 1),
        );
        assert_eq!(bits[0].status(), Some((error::ALERT, &[0x20][..])));
        exchange(&mut bus, 1, instruction::REBOOT, &[]);
        assert_eq!(error_of(&exchange(&mut bus, 1, instruction::PING, &[])), 0);
    }
}
