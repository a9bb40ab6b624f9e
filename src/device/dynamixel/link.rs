//! The Dynamixel link: rigbridge as the Protocol 2.0 master of a bus of servos, one per
//! axis, on a serial line (`dynamixel:///dev/ttyUSB0?baud=1000000&ids=1,2,3,4,5,6`).
//!
//! An I/O thread owns the port. On every open it sets the servos up (docs/dynamixel.md):
//! ping each id, torque off, Hardware Error Status (70) read, Operating Mode (11) = 4 when
//! an axis' range exceeds +-180 deg (else 3), the position limits checked against the
//! axes, Present Position (132) read as the start, Goal Position (116) = Present Position
//! (a servo drives to a stale goal register when torque comes on), torque on. Then each
//! command from the streamer is one bus cycle: a Target is a Sync Write of Goal Position
//! followed by a Sync Read of Present Position, anything else the Sync Read alone; the
//! positions read are the feedback.
//!
//! A status packet with a non-zero error byte, or a non-zero Hardware Error Status (read
//! when the alert bit is set), latches a drive fault: a `LinkEvent::Fault` and a faulted
//! status in every feedback until a Reset sets the bus up again. Missing status packets
//! are counted (`gaps`); [`LOST_AFTER_CYCLES`] cycles in a row with one missing are link
//! loss, and the bus is opened and set up anew. A target whose tick falls outside a
//! servo's range is refused before anything is written, never clamped. It owns the port
//! and the bus cycle; it must not plan or check speeds (the streamer's gate does).

use crate::device::bus::{BusError, Device, DeviceLink, Hub, Job, id_list};
use crate::device::dynamixel::wire::{
    AxisTicks, EXTENDED_POSITION_MODE, EXTENDED_RANGE, POSITION_MODE, Packet, PacketDecoder,
    address, describe_error, encode_packet, encode_sync_read, encode_sync_write_i32, error,
    instruction, read_params, write_params,
};
use crate::link::LinkError;
use crate::protocol::Fault;
use crate::transport::SerialSettings;
use serialport::SerialPort;
use std::time::{Duration, Instant};
use thiserror::Error;

/// Cycles in a row with a status packet missing that mean the bus is lost: 25, the
/// streamer's own patience (0.1 s at 250 Hz) for a silent controller.
pub const LOST_AFTER_CYCLES: u32 = 25;
/// A servo within this many ticks of its goal has reached it: the encoder's own rounding
/// and the position controller's dead band.
const SETTLED_TICKS: i32 = 2;
/// How long a set-up request waits for its status packet: generous, set-up is not cyclic.
const SETUP_TIMEOUT: Duration = Duration::from_millis(100);
/// Set-up requests are retried this often before the open counts as failed (a servo
/// still booting, a packet lost to noise).
const SETUP_ATTEMPTS: u32 = 3;
/// Degrees beyond which an axis needs extended position mode (issue 16): one turn is
/// +-180 deg about the centre tick.
const HALF_TURN: f64 = std::f64::consts::PI;

/// What the link needs to know: the port, the servos in axis order and their tick maps,
/// the axes' limits (to choose the mode and check each servo's range) and the cycle.
#[derive(Debug, Clone, PartialEq)]
pub struct DynamixelSettings {
    pub serial: SerialSettings,
    pub ids: Vec<u8>,
    pub axes: Vec<AxisTicks>,
    /// Per axis (lower, upper), rad.
    pub limits: Vec<(f64, f64)>,
    /// How long a cycle waits for its status packets: the stream period.
    pub cycle_timeout: Duration,
}

#[derive(Debug, Clone, PartialEq, Error)]
pub enum DynamixelError {
    #[error("{ids} servo ids for {axes} axes: give one id per axis, in axis order")]
    IdCount { ids: usize, axes: usize },
    #[error("servo id {0} appears twice")]
    DuplicateId(u8),
    #[error(
        "axis {axis}: its limits are ticks {low} .. {high}, outside the extended position range +-{EXTENDED_RANGE}"
    )]
    OutOfRange { axis: usize, low: f64, high: f64 },
}

/// The servos as the link's [`Device`]: a Sync Write and a Sync Read a cycle.
pub struct Dynamixel {
    settings: DynamixelSettings,
}

/// The link to a bus of Dynamixel servos.
pub type DynamixelLink = DeviceLink<Dynamixel>;
type Shared = Hub<Dynamixel>;

impl Device for Dynamixel {
    type Bus = Bus;
    type Start = SetUp;
    const NAME: &'static str = "Dynamixel";
    const TARGET_FIELD: &'static str = "goal position tick";
    const TARGET_RANGE: &'static str = "the servo's position range";

    fn axes(&self) -> &[AxisTicks] {
        &self.settings.axes
    }

    fn open(&self) -> Result<Bus, BusError> {
        Bus::open(&self.settings.serial)
    }

    fn set_up(&self, bus: &mut Bus, hub: &Shared) -> Result<SetUp, BusError> {
        set_up(bus, hub)
    }

    /// Publishes the session and its first feedback (holding), then runs the cycles.
    fn run(&self, bus: &mut Bus, hub: &Shared, (ranges, present): SetUp) {
        hub.begin_session(ranges, &present, None);
        run_cycles(bus, hub);
    }
}

/// Checks `settings` and starts the I/O thread, which opens the port and sets the bus up
/// in the background (and again after every loss).
pub fn connect_dynamixel(settings: DynamixelSettings) -> Result<DynamixelLink, LinkError> {
    check_settings(&settings).map_err(|e| LinkError::Closed(e.to_string()))?;
    let description = format!(
        "dynamixel://{}?baud={}&ids={}",
        settings.serial.path,
        settings.serial.baud,
        id_list(&settings.ids)
    );
    crate::device::bus::start(Dynamixel { settings }, description, "rigbridge-dynamixel")
}

fn check_settings(settings: &DynamixelSettings) -> Result<(), DynamixelError> {
    if settings.ids.len() != settings.axes.len() || settings.ids.len() != settings.limits.len() {
        return Err(DynamixelError::IdCount {
            ids: settings.ids.len(),
            axes: settings.axes.len(),
        });
    }
    for (i, id) in settings.ids.iter().enumerate() {
        if settings.ids[..i].contains(id) {
            return Err(DynamixelError::DuplicateId(*id));
        }
    }
    for (axis, (ticks, (lower, upper))) in settings.axes.iter().zip(&settings.limits).enumerate() {
        let (low, high) = (ticks.tick(*lower), ticks.tick(*upper));
        if low.min(high) < -(EXTENDED_RANGE as f64) || low.max(high) > EXTENDED_RANGE as f64 {
            return Err(DynamixelError::OutOfRange {
                axis: axis + 1,
                low,
                high,
            });
        }
    }
    Ok(())
}

/// Operating Mode for an axis: extended position when its range turns the servo's shaft
/// beyond +-180 deg from the zero tick (on a linear axis, the screw's or pinion's turns).
pub fn operating_mode(ticks: &AxisTicks, lower: f64, upper: f64) -> u8 {
    let (low, high) = (ticks.shaft_angle(lower), ticks.shaft_angle(upper));
    if low.min(high) < -HALF_TURN || low.max(high) > HALF_TURN {
        EXTENDED_POSITION_MODE
    } else {
        POSITION_MODE
    }
}

/// The port and the bytes in flight on it.
pub struct Bus {
    port: Box<dyn SerialPort>,
    decoder: PacketDecoder,
    out: Vec<u8>,
    read: Vec<u8>,
    /// An answer came late (a status wait ran out): its bytes may still sit in the port's
    /// input, where the next exchange would take them for its own answers, one exchange
    /// behind from then on. The next write flushes the input first.
    late_answer_possible: bool,
}

impl Bus {
    fn open(settings: &SerialSettings) -> Result<Self, BusError> {
        let port = settings
            .open()
            .map_err(|e| BusError::Lost(settings.open_failure(&e)))?;
        Ok(Self {
            port,
            decoder: PacketDecoder::default(),
            out: Vec::with_capacity(256),
            read: vec![0; 512],
            late_answer_possible: false,
        })
    }

    fn write_out(&mut self, shared: &Shared) -> Result<(), BusError> {
        // Anything unread belongs to an earlier exchange: a late answer is not this one's.
        // (Dropped from the decoder only: flushing the port's input is a syscall a cycle,
        // and draining its output (tcdrain) waits on the far side.)
        self.decoder.clear();
        if std::mem::take(&mut self.late_answer_possible) {
            self.port
                .clear(serialport::ClearBuffer::Input)
                .map_err(|e| BusError::Lost(format!("port: {e}")))?;
        }
        self.port
            .write_all(&self.out)
            .map_err(|e| BusError::Lost(format!("write failed: {e}")))?;
        shared.lock().counters.frames_sent += 1;
        Ok(())
    }

    /// The next status packet from `id` before `deadline`; `None` when none came.
    fn status_from(
        &mut self,
        shared: &Shared,
        id: u8,
        deadline: Instant,
    ) -> Result<Option<Packet>, BusError> {
        loop {
            while let Some(decoded) = self.decoder.next_packet() {
                let mut state = shared.lock();
                match decoded {
                    Ok(packet) if packet.instruction == instruction::STATUS => {
                        state.counters.frames_received += 1;
                        if packet.id == id {
                            return Ok(Some(packet));
                        }
                    }
                    Ok(_) => {}
                    Err(_) => state.counters.crc_errors += 1,
                }
            }
            let now = Instant::now();
            if now >= deadline {
                self.late_answer_possible = true;
                return Ok(None);
            }
            let wait = (deadline - now).max(Duration::from_micros(100));
            self.port
                .set_timeout(wait)
                .map_err(|e| BusError::Lost(format!("port: {e}")))?;
            match self.port.read(&mut self.read) {
                Ok(n) => self.decoder.push(&self.read[..n]),
                Err(e)
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::TimedOut | std::io::ErrorKind::WouldBlock
                    ) => {}
                Err(e) => return Err(BusError::Lost(format!("read failed: {e}"))),
            }
        }
    }

    /// One instruction to `id` and its status parameters, retried; a status error is a
    /// drive fault of `axis`.
    fn request(
        &mut self,
        shared: &Shared,
        axis: usize,
        instruction: u8,
        params: &[u8],
    ) -> Result<Vec<u8>, BusError> {
        let id = shared.device.settings.ids[axis];
        for _ in 0..SETUP_ATTEMPTS {
            encode_packet(id, instruction, params, &mut self.out);
            self.write_out(shared)?;
            let Some(packet) = self.status_from(shared, id, Instant::now() + SETUP_TIMEOUT)? else {
                shared.lock().counters.gaps += 1;
                continue;
            };
            let (code, data) = packet.status().unwrap_or((error::RESULT_FAIL, &[]));
            if code != 0 {
                return Err(self.drive_error(shared, axis, code));
            }
            return Ok(data.to_vec());
        }
        let asked = if instruction == instruction::PING {
            "its ping".to_string()
        } else {
            format!("instruction {instruction:#04x}")
        };
        Err(BusError::Lost(format!(
            "id {id} (axis {}) did not answer {asked} ({SETUP_ATTEMPTS} tries) on {}",
            axis + 1,
            shared.device.settings.serial.path
        )))
    }

    fn read_register(
        &mut self,
        shared: &Shared,
        axis: usize,
        at: u16,
        size: u16,
    ) -> Result<Vec<u8>, BusError> {
        let data = self.request(shared, axis, instruction::READ, &read_params(at, size))?;
        if data.len() != usize::from(size) {
            return Err(BusError::Lost(format!(
                "servo id {} answered {} bytes for {size} at address {at}",
                shared.device.settings.ids[axis],
                data.len()
            )));
        }
        Ok(data)
    }

    fn write_register(
        &mut self,
        shared: &Shared,
        axis: usize,
        at: u16,
        data: &[u8],
    ) -> Result<(), BusError> {
        self.request(shared, axis, instruction::WRITE, &write_params(at, data))
            .map(|_| ())
    }

    /// The drive fault for status error `code` of `axis`: with the alert bit, its
    /// Hardware Error Status says why.
    fn drive_error(&mut self, shared: &Shared, axis: usize, code: u8) -> BusError {
        let id = shared.device.settings.ids[axis];
        let mut text = format!(
            "servo id {id} (axis {}): {}",
            axis + 1,
            describe_error(code)
        );
        if code & error::ALERT != 0 {
            match self.hardware_error_status(shared, id) {
                Ok(bits) => text.push_str(&format!("; hardware error status {bits:#04x}")),
                Err(BusError::Lost(why) | BusError::Drive { text: why, .. }) => {
                    text.push_str(&format!("; hardware error status not read: {why}"))
                }
            }
        }
        BusError::Drive { axis, text }
    }

    /// Reads `id`'s Hardware Error Status. A status of `id` with other than one byte is
    /// a late answer to an earlier exchange (the position of a Sync Read), skipped.
    fn hardware_error_status(&mut self, shared: &Shared, id: u8) -> Result<u8, BusError> {
        encode_packet(
            id,
            instruction::READ,
            &read_params(address::HARDWARE_ERROR_STATUS, 1),
            &mut self.out,
        );
        self.write_out(shared)?;
        let deadline = Instant::now() + SETUP_TIMEOUT;
        loop {
            let Some(packet) = self.status_from(shared, id, deadline)? else {
                return Err(BusError::Lost(format!(
                    "servo id {id} did not answer within {} ms",
                    SETUP_TIMEOUT.as_millis()
                )));
            };
            if let Some((_, [bits])) = packet.status() {
                return Ok(*bits);
            }
        }
    }
}

fn i32_of(data: &[u8]) -> Option<i32> {
    Some(i32::from_le_bytes(data.get(..4)?.try_into().ok()?))
}

/// Each servo's Goal Position range and present position, ticks.
pub type SetUp = (Vec<(i64, i64)>, Vec<i32>);

/// The set-up of docs/dynamixel.md; returns each servo's Goal Position range and the
/// present positions (ticks).
fn set_up(bus: &mut Bus, shared: &Shared) -> Result<SetUp, BusError> {
    let settings = &shared.device.settings;
    let axes = settings.ids.len();
    for axis in 0..axes {
        bus.request(shared, axis, instruction::PING, &[])?;
    }
    for axis in 0..axes {
        bus.write_register(shared, axis, address::TORQUE_ENABLE, &[0])?;
        let [bits] = bus.read_register(shared, axis, address::HARDWARE_ERROR_STATUS, 1)?[..] else {
            return Err(BusError::Lost("short hardware error status".into()));
        };
        if bits != 0 {
            return Err(BusError::Drive {
                axis,
                text: format!(
                    "servo id {} (axis {}): hardware error status {bits:#04x}",
                    settings.ids[axis],
                    axis + 1
                ),
            });
        }
    }
    let mut ranges = Vec::with_capacity(axes);
    for axis in 0..axes {
        let (lower, upper) = settings.limits[axis];
        let mode = operating_mode(&settings.axes[axis], lower, upper);
        bus.write_register(shared, axis, address::OPERATING_MODE, &[mode])?;
        ranges.push(servo_range(bus, shared, axis, mode)?);
    }
    let mut present = Vec::with_capacity(axes);
    for axis in 0..axes {
        let data = bus.read_register(shared, axis, address::PRESENT_POSITION, 4)?;
        let tick = i32_of(&data).ok_or_else(|| BusError::Lost("short position".into()))?;
        bus.write_register(shared, axis, address::GOAL_POSITION, &tick.to_le_bytes())?;
        present.push(tick);
    }
    for axis in 0..axes {
        bus.write_register(shared, axis, address::TORQUE_ENABLE, &[1])?;
    }
    Ok((ranges, present))
}

/// The Goal Position range of `axis`' servo in `mode`: its position limits (48, 52) in
/// position mode, which must cover the axis' limits, or the extended range.
fn servo_range(
    bus: &mut Bus,
    shared: &Shared,
    axis: usize,
    mode: u8,
) -> Result<(i64, i64), BusError> {
    if mode == EXTENDED_POSITION_MODE {
        return Ok((-EXTENDED_RANGE, EXTENDED_RANGE));
    }
    let read = |bus: &mut Bus, at| -> Result<i64, BusError> {
        let data = bus.read_register(shared, axis, at, 4)?;
        i32_of(&data)
            .map(i64::from)
            .ok_or_else(|| BusError::Lost("short position limit".into()))
    };
    let max = read(bus, address::MAX_POSITION_LIMIT)?;
    let min = read(bus, address::MIN_POSITION_LIMIT)?;
    let ticks = shared.device.settings.axes[axis];
    let (lower, upper) = shared.device.settings.limits[axis];
    let (low, high) = (ticks.tick(lower), ticks.tick(upper));
    if low.min(high) < min as f64 || low.max(high) > max as f64 {
        return Err(BusError::Drive {
            axis,
            text: format!(
                "servo id {} (axis {}): its position limits {min} .. {max} do not cover the axis' limits, ticks {low} .. {high}",
                shared.device.settings.ids[axis],
                axis + 1
            ),
        });
    }
    Ok((min, max))
}

/// Bus cycles, one per command, until loss, a fault reset or the link is dropped.
fn run_cycles(bus: &mut Bus, shared: &Shared) {
    let mut missing_cycles = 0u32;
    let mut last_seq = 0u32;
    let mut holding = true;
    let mut present: Vec<i32> = Vec::new();
    // The goals last written: a servo that stops being streamed goes on to them.
    let mut goals_written: Option<Vec<i32>> = None;
    while let Ok(Some(job)) = shared.next_job(None) {
        let latched = shared.lock().latched.is_some();
        match job {
            Job::Reset => return,
            Job::Targets(seq, goals) if !latched => {
                let goals = &goals[..shared.device.settings.ids.len()];
                if write_goals(bus, shared, goals).is_err() {
                    return;
                }
                last_seq = seq;
                holding = false;
                goals_written = Some(goals.to_vec());
            }
            Job::Targets(..) => {}
            Job::Cycle { holding: hold } => holding |= hold,
            Job::EStop => {
                estop(bus, shared, &present);
                holding = true;
            }
        }
        match sync_read(bus, shared) {
            Ok(Some(ticks)) => {
                missing_cycles = 0;
                // Holding means at rest on the goal: until the servos reach the goals last
                // written they still move, too slowly, perhaps, for a tick to show it.
                let settled = goals_written.as_ref().is_none_or(|goals| {
                    goals
                        .iter()
                        .zip(&ticks)
                        .all(|(g, t)| (g - t).abs() <= SETTLED_TICKS)
                });
                shared.publish_cycle(last_seq, &ticks, holding && settled);
                present = ticks;
            }
            Ok(None) => {
                missing_cycles += 1;
                if missing_cycles >= LOST_AFTER_CYCLES {
                    return;
                }
            }
            Err(BusError::Drive { axis, text }) => {
                shared.latch(Fault::Drive { axis: axis as u8 }, &text)
            }
            Err(BusError::Lost(_)) => return,
        }
    }
}

/// One Sync Write of Goal Position: `goals` (ticks) in axis order.
fn write_goals(bus: &mut Bus, shared: &Shared, goals: &[i32]) -> Result<(), BusError> {
    let ids = shared.device.settings.ids.iter().copied();
    let values: Vec<(u8, i32)> = ids.zip(goals.iter().copied()).collect();
    encode_sync_write_i32(address::GOAL_POSITION, &values, &mut bus.out);
    bus.write_out(shared)
}

/// E-stop: every goal set to where its servo is, and the fault latched until a Reset.
fn estop(bus: &mut Bus, shared: &Shared, present: &[i32]) {
    if present.len() == shared.device.settings.ids.len() {
        let _ = write_goals(bus, shared, present);
    }
    shared.latch(
        Fault::EStop,
        "e-stop: every servo's goal set to its present position",
    );
}

/// Sync Read of Present Position: every servo's ticks, `None` when a status is missing
/// (each counted as a gap), a drive error for a status with an error byte.
fn sync_read(bus: &mut Bus, shared: &Shared) -> Result<Option<Vec<i32>>, BusError> {
    let ids = &shared.device.settings.ids;
    encode_sync_read(address::PRESENT_POSITION, 4, ids, &mut bus.out);
    bus.write_out(shared)?;
    let deadline = Instant::now() + shared.device.settings.cycle_timeout;
    let mut ticks = Vec::with_capacity(ids.len());
    for (axis, &id) in ids.iter().enumerate() {
        let Some(packet) = bus.status_from(shared, id, deadline)? else {
            shared.lock().counters.gaps += (ids.len() - axis) as u64;
            return Ok(None);
        };
        match packet.status() {
            Some((0, data)) => match i32_of(data) {
                Some(tick) => ticks.push(tick),
                None => return Err(BusError::Lost(format!("servo id {id}: short position"))),
            },
            Some((code, _)) => return Err(bus.drive_error(shared, axis, code)),
            None => return Ok(None),
        }
    }
    Ok(Some(ticks))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn extended_mode_only_beyond_half_a_turn() {
        let turn = AxisTicks::default();
        assert_eq!(operating_mode(&turn, -2.88, 2.88), POSITION_MODE);
        assert_eq!(operating_mode(&turn, -HALF_TURN, HALF_TURN), POSITION_MODE);
        assert_eq!(
            operating_mode(&turn, -400f64.to_radians(), 400f64.to_radians()),
            EXTENDED_POSITION_MODE
        );
        // A pinion of 0.1 m a turn: +-0.05 m is half a turn, a metre is ten.
        let rack = AxisTicks {
            ticks_per_metre: Some(40960.0),
            ..turn
        };
        assert_eq!(operating_mode(&rack, -0.05, 0.05), POSITION_MODE);
        assert_eq!(operating_mode(&rack, 0.0, 1.0), EXTENDED_POSITION_MODE);
    }

    #[test]
    fn settings_are_refused_with_the_wrong_ids_or_an_axis_beyond_the_extended_range() {
        let settings = DynamixelSettings {
            serial: SerialSettings::new("/dev/null", 1_000_000),
            ids: vec![1, 2],
            axes: vec![AxisTicks::default(); 2],
            limits: vec![(-1.0, 1.0); 2],
            cycle_timeout: Duration::from_millis(4),
        };
        assert_eq!(check_settings(&settings), Ok(()));
        let twice = DynamixelSettings {
            ids: vec![3, 3],
            ..settings.clone()
        };
        assert_eq!(check_settings(&twice), Err(DynamixelError::DuplicateId(3)));
        let short = DynamixelSettings {
            ids: vec![1],
            ..settings.clone()
        };
        assert!(matches!(
            check_settings(&short),
            Err(DynamixelError::IdCount { ids: 1, axes: 2 })
        ));
        // 300 turns at 4096 ticks a turn: beyond +-256 turns.
        let far = DynamixelSettings {
            limits: vec![(-1.0, 1.0), (0.0, 300.0 * std::f64::consts::TAU)],
            ..settings
        };
        assert!(matches!(
            check_settings(&far),
            Err(DynamixelError::OutOfRange { axis: 2, .. })
        ));
    }
}
