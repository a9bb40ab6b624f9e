//! Dynamixel Protocol 2.0 on the wire, shared by the bridge's Dynamixel link (the master)
//! and the twin's servos: packet framing (header, length, byte stuffing, CRC-16), the
//! instructions and control-table addresses both sides use, the status error numbers, the
//! conversion between radians and position ticks, and the serial line budget of one cycle.
//!
//! Everything here follows the ROBOTIS e-manual: the Protocol 2.0 page
//! (<https://emanual.robotis.com/docs/en/dxl/protocol2/>) for the packet format, stuffing,
//! CRC and error numbers, and the X-series control table (XM430-W350,
//! <https://emanual.robotis.com/docs/en/dxl/x/xm430-w350/#control-table>) for addresses
//! (docs/dynamixel.md lists each with its source). It owns bytes only: it must not decide
//! what to send or judge what a servo does.

use std::time::Duration;
use thiserror::Error;

/// Every packet starts with these four bytes (Protocol 2.0: header FF FF FD, reserved 00).
pub const HEADER: [u8; 4] = [0xFF, 0xFF, 0xFD, 0x00];
/// The id every servo obeys; none answers it alone (Protocol 2.0, "Packet ID").
pub const BROADCAST_ID: u8 = 0xFE;
/// The highest id a servo may have (Protocol 2.0: 0 to 252).
pub const MAX_SERVO_ID: u8 = 252;
/// Header, id, two length bytes, instruction and CRC: a packet without parameters.
pub const PACKET_OVERHEAD: usize = 10;
/// Bits per byte on the line: start, 8 data bits, stop (Dynamixel buses are 8N1).
pub const BITS_PER_BYTE: f64 = 10.0;
/// Largest packet either side accepts: far above a sync write to 252 servos.
pub const MAX_PACKET: usize = 2048;

/// Instruction bytes (Protocol 2.0, "Instruction").
pub mod instruction {
    pub const PING: u8 = 0x01;
    pub const READ: u8 = 0x02;
    pub const WRITE: u8 = 0x03;
    pub const REBOOT: u8 = 0x08;
    /// The instruction byte of a status packet (a servo's answer).
    pub const STATUS: u8 = 0x55;
    pub const SYNC_READ: u8 = 0x82;
    pub const SYNC_WRITE: u8 = 0x83;
}

/// X-series control table addresses (XM430-W350 e-manual, "Control Table"), with sizes.
pub mod address {
    /// EEPROM, 2 bytes, read only.
    pub const MODEL_NUMBER: u16 = 0;
    /// EEPROM, 1 byte, read only.
    pub const FIRMWARE_VERSION: u16 = 6;
    /// EEPROM, 1 byte.
    pub const ID: u16 = 7;
    /// EEPROM, 1 byte: 3 position control, 4 extended position control.
    pub const OPERATING_MODE: u16 = 11;
    /// EEPROM, 4 bytes each: the Goal Position range in position control mode.
    pub const MAX_POSITION_LIMIT: u16 = 48;
    pub const MIN_POSITION_LIMIT: u16 = 52;
    /// RAM, 1 byte: 0 off, 1 on. The EEPROM area is locked while it is 1.
    pub const TORQUE_ENABLE: u16 = 64;
    /// RAM, 1 byte, read only: the hardware error bits.
    pub const HARDWARE_ERROR_STATUS: u16 = 70;
    /// RAM, 4 bytes.
    pub const GOAL_POSITION: u16 = 116;
    /// RAM, 4 bytes, read only.
    pub const PRESENT_POSITION: u16 = 132;
    /// The first address of the RAM area: below it is EEPROM.
    pub const RAM_START: u16 = 64;
}

/// Operating Mode values (XM430 e-manual, "Operating Mode (11)").
pub const POSITION_MODE: u8 = 3;
pub const EXTENDED_POSITION_MODE: u8 = 4;
/// Goal Position range in extended position mode (XM430 e-manual, "Goal Position (116)"):
/// -256 to 256 turns.
pub const EXTENDED_RANGE: i64 = 1_048_575;

/// Status error numbers, the low 7 bits of a status packet's error byte (Protocol 2.0,
/// "Error"), and its alert bit: the servo has a hardware error (see address 70).
pub mod error {
    pub const RESULT_FAIL: u8 = 0x01;
    pub const INSTRUCTION: u8 = 0x02;
    pub const CRC: u8 = 0x03;
    pub const DATA_RANGE: u8 = 0x04;
    pub const DATA_LENGTH: u8 = 0x05;
    pub const DATA_LIMIT: u8 = 0x06;
    pub const ACCESS: u8 = 0x07;
    pub const ALERT: u8 = 0x80;
}

/// The e-manual's words for a status error byte.
pub fn describe_error(byte: u8) -> String {
    let number = match byte & !error::ALERT {
        0 => "no error",
        error::RESULT_FAIL => "result fail",
        error::INSTRUCTION => "instruction error",
        error::CRC => "CRC error",
        error::DATA_RANGE => "data range error",
        error::DATA_LENGTH => "data length error",
        error::DATA_LIMIT => "data limit error",
        error::ACCESS => "access error",
        _ => "unknown error number",
    };
    if byte & error::ALERT != 0 {
        format!("{number}, alert (hardware error)")
    } else {
        number.to_string()
    }
}

/// The CRC of Protocol 2.0: CRC-16 with polynomial 0x8005, initial value 0, no
/// reflection, no final XOR, over every byte from the header to the last parameter. That
/// is CRC-16/UMTS in the crc catalogue (also known as CRC-16/BUYPASS).
const CRC: crc::Crc<u16> = crc::Crc::<u16>::new(&crc::CRC_16_UMTS);

pub fn crc16(bytes: &[u8]) -> u16 {
    CRC.checksum(bytes)
}

/// One decoded packet: an instruction (from the master) or a status (from a servo).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Packet {
    pub id: u8,
    pub instruction: u8,
    /// Parameters after unstuffing. For a status packet, the first is the error byte.
    pub params: Vec<u8>,
}

impl Packet {
    /// A status packet's error byte and parameters; `None` for an instruction or a status
    /// without its error byte.
    pub fn status(&self) -> Option<(u8, &[u8])> {
        if self.instruction != instruction::STATUS {
            return None;
        }
        self.params.split_first().map(|(e, p)| (*e, p))
    }
}

/// Appends `bytes` to `out` with Protocol 2.0 byte stuffing: FF FF FD becomes FF FF FD FD,
/// so the header never appears inside a packet.
fn stuff_into(bytes: &[u8], out: &mut Vec<u8>) {
    for &byte in bytes {
        out.push(byte);
        let n = out.len();
        if byte == 0xFD && n >= 3 && out[n - 3] == 0xFF && out[n - 2] == 0xFF {
            out.push(0xFD);
        }
    }
}

/// Writes one packet into `out` (cleared first): the instruction byte and parameters are
/// stuffed, the length counts the stuffed bytes plus instruction and CRC.
pub fn encode_packet(id: u8, instruction: u8, params: &[u8], out: &mut Vec<u8>) {
    out.clear();
    out.extend_from_slice(&HEADER);
    out.push(id);
    out.extend_from_slice(&[0, 0]);
    // Stuffing looks back at the bytes before: start it at the instruction, whose value
    // is never FF, so no pattern can span the length field.
    let body_start = out.len();
    stuff_into(&[instruction], out);
    stuff_into(params, out);
    let length = (out.len() - body_start + 2) as u16;
    out[5..7].copy_from_slice(&length.to_le_bytes());
    let crc = crc16(out);
    out.extend_from_slice(&crc.to_le_bytes());
}

/// A status packet: `error` then `params`.
pub fn encode_status(id: u8, error: u8, params: &[u8], out: &mut Vec<u8>) {
    let mut body = Vec::with_capacity(params.len() + 1);
    body.push(error);
    body.extend_from_slice(params);
    encode_packet(id, instruction::STATUS, &body, out);
}

/// Read `length` bytes from `address`.
pub fn read_params(address: u16, length: u16) -> [u8; 4] {
    let [a0, a1] = address.to_le_bytes();
    let [l0, l1] = length.to_le_bytes();
    [a0, a1, l0, l1]
}

/// Write `data` at `address`.
pub fn write_params(address: u16, data: &[u8]) -> Vec<u8> {
    let mut params = address.to_le_bytes().to_vec();
    params.extend_from_slice(data);
    params
}

/// Sync Read of `length` bytes at `address` from each of `ids`, into `out`.
pub fn encode_sync_read(address: u16, length: u16, ids: &[u8], out: &mut Vec<u8>) {
    let mut params = read_params(address, length).to_vec();
    params.extend_from_slice(ids);
    encode_packet(BROADCAST_ID, instruction::SYNC_READ, &params, out);
}

/// Sync Write of one little-endian i32 per servo at `address` (4 bytes each), into `out`.
pub fn encode_sync_write_i32(address: u16, values: &[(u8, i32)], out: &mut Vec<u8>) {
    let mut params = read_params(address, 4).to_vec();
    for (id, value) in values {
        params.push(*id);
        params.extend_from_slice(&value.to_le_bytes());
    }
    encode_packet(BROADCAST_ID, instruction::SYNC_WRITE, &params, out);
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Error)]
pub enum DecodeError {
    #[error("packet CRC mismatch")]
    Crc,
    #[error("packet length {0} is invalid")]
    Length(usize),
}

/// Reassembles packets from a byte stream: finds the header, waits for the whole packet,
/// checks the CRC and removes the stuffing. Bytes before a header are skipped.
#[derive(Debug, Default)]
pub struct PacketDecoder {
    buffer: Vec<u8>,
    /// Bytes skipped while looking for a header (noise, or the rest of a bad packet).
    pub skipped: u64,
}

impl PacketDecoder {
    pub fn push(&mut self, bytes: &[u8]) {
        self.buffer.extend_from_slice(bytes);
    }

    pub fn clear(&mut self) {
        self.buffer.clear();
    }

    /// The next complete packet, if the buffer holds one. A packet with a bad CRC or
    /// length is dropped (its header skipped) and reported once.
    pub fn next_packet(&mut self) -> Option<Result<Packet, DecodeError>> {
        let start = self.buffer.windows(4).position(|w| w == HEADER);
        let Some(start) = start else {
            // Keep a possible partial header at the end.
            let keep = self.buffer.len().min(3);
            let drop = self.buffer.len() - keep;
            self.skipped += drop as u64;
            self.buffer.drain(..drop);
            return None;
        };
        self.skipped += start as u64;
        self.buffer.drain(..start);
        if self.buffer.len() < 7 {
            return None;
        }
        let length = usize::from(u16::from_le_bytes([self.buffer[5], self.buffer[6]]));
        if !(3..=MAX_PACKET).contains(&length) {
            self.buffer.drain(..4);
            return Some(Err(DecodeError::Length(length)));
        }
        let total = 7 + length;
        if self.buffer.len() < total {
            return None;
        }
        let crc = u16::from_le_bytes([self.buffer[total - 2], self.buffer[total - 1]]);
        if crc16(&self.buffer[..total - 2]) != crc {
            self.buffer.drain(..4);
            return Some(Err(DecodeError::Crc));
        }
        let packet = unstuffed(&self.buffer[..total - 2]);
        self.buffer.drain(..total);
        Some(Ok(packet))
    }
}

/// The packet in `bytes` (header to last parameter, CRC checked), stuffing removed.
fn unstuffed(bytes: &[u8]) -> Packet {
    let mut body = Vec::with_capacity(bytes.len() - 7);
    for &byte in &bytes[7..] {
        let n = body.len();
        let stuffed = byte == 0xFD
            && n >= 3
            && body[n - 3] == 0xFF
            && body[n - 2] == 0xFF
            && body[n - 1] == 0xFD;
        if !stuffed {
            body.push(byte);
        }
    }
    Packet {
        id: bytes[4],
        instruction: body[0],
        params: body[1..].to_vec(),
    }
}

/// How an axis maps to a servo's (or drive's) position ticks: on a revolute axis
/// tick = zero_tick + rad * ticks_per_turn / 2 pi; on a linear one (a servo on a lead screw
/// or a rack, a linear drive) tick = zero_tick + m * ticks_per_metre.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AxisTicks {
    pub ticks_per_turn: f64,
    pub zero_tick: f64,
    /// Set on a linear (prismatic) axis: its positions are metres, not radians.
    pub ticks_per_metre: Option<f64>,
}

/// X-series defaults: 4096 ticks a turn (0.088 deg), 2048 at the centre of the range.
impl Default for AxisTicks {
    fn default() -> Self {
        Self {
            ticks_per_turn: 4096.0,
            zero_tick: 2048.0,
            ticks_per_metre: None,
        }
    }
}

impl AxisTicks {
    /// Ticks per unit of the axis' position: per radian, or per metre on a linear axis.
    pub fn per_unit(&self) -> f64 {
        self.ticks_per_metre
            .unwrap_or(self.ticks_per_turn / std::f64::consts::TAU)
    }

    /// The nearest tick to `position` (rad, or m on a linear axis). Rounding is monotone,
    /// so a value inside limits whose ticks are rounded the same way stays inside them.
    pub fn tick(&self, position: f64) -> f64 {
        (self.zero_tick + position * self.per_unit()).round()
    }

    /// The axis position (rad, or m on a linear axis) of `tick`.
    pub fn radians(&self, tick: i64) -> f64 {
        (tick as f64 - self.zero_tick) / self.per_unit()
    }

    /// One tick in the axis' unit: the resolution of what crosses the wire.
    pub fn resolution(&self) -> f64 {
        1.0 / self.per_unit()
    }

    /// The servo shaft's angle from the zero tick at `position`, rad: the position itself on
    /// a revolute axis, the turns of the screw or pinion on a linear one.
    pub fn shaft_angle(&self, position: f64) -> f64 {
        position * self.per_unit() * std::f64::consts::TAU / self.ticks_per_turn
    }
}

/// The serial line's load of one cycle with `servos` servos: a Sync Write of Goal Position
/// (4 bytes each), a Sync Read of Present Position and one status packet per servo.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LineBudget {
    pub baud: u32,
    pub servos: usize,
    /// Bytes without stuffing.
    pub bytes: usize,
    /// Bytes with the most stuffing the values can cause: one FF FF FD pattern fits in a
    /// 4-byte position, and none in the ids, addresses, lengths and error bytes around it.
    pub worst_case_bytes: usize,
    /// Time on the line for the worst case, plus each servo's return delay.
    pub cycle: Duration,
    pub max_rate_hz: f64,
}

/// The line budget at `baud` with each servo answering after `return_delay_us`.
pub fn line_budget(servos: usize, baud: u32, return_delay_us: f64) -> LineBudget {
    // Sync Write: address, length, then id + 4 bytes per servo.
    let sync_write = PACKET_OVERHEAD + 4 + servos * 5;
    // Sync Read: address, length, then one id per servo.
    let sync_read = PACKET_OVERHEAD + 4 + servos;
    // Status: error byte and 4 bytes of position.
    let statuses = servos * (PACKET_OVERHEAD + 1 + 4);
    let bytes = sync_write + sync_read + statuses;
    let worst_case_bytes = bytes + 2 * servos;
    let cycle_s = worst_case_bytes as f64 * BITS_PER_BYTE / f64::from(baud)
        + servos as f64 * return_delay_us * 1e-6;
    LineBudget {
        baud,
        servos,
        bytes,
        worst_case_bytes,
        // A line of 0 baud never ends a cycle: the longest time there is, and 0 Hz.
        cycle: Duration::try_from_secs_f64(cycle_s).unwrap_or(Duration::MAX),
        max_rate_hz: 1.0 / cycle_s,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The e-manual's worked examples (Protocol 2.0 page): Ping of ID 1, and its answer
    /// from an XM430-W210 (model 1030 = 0x0406, firmware 0x26).
    #[test]
    fn ping_and_its_status_match_the_e_manual() {
        let mut out = Vec::new();
        encode_packet(1, instruction::PING, &[], &mut out);
        assert_eq!(
            out,
            [0xFF, 0xFF, 0xFD, 0x00, 0x01, 0x03, 0x00, 0x01, 0x19, 0x4E]
        );
        encode_status(1, 0, &[0x06, 0x04, 0x26], &mut out);
        assert_eq!(
            out,
            [
                0xFF, 0xFF, 0xFD, 0x00, 0x01, 0x07, 0x00, 0x55, 0x00, 0x06, 0x04, 0x26, 0x65, 0x5D
            ]
        );
    }

    /// The e-manual's Sync Write (150 to ID 1, 170 to ID 2 at 116) and Sync Read (132, 4
    /// bytes, IDs 1 and 2) examples.
    #[test]
    fn sync_write_and_sync_read_match_the_e_manual() {
        let mut out = Vec::new();
        encode_sync_write_i32(address::GOAL_POSITION, &[(1, 150), (2, 170)], &mut out);
        assert_eq!(
            out,
            [
                0xFF, 0xFF, 0xFD, 0x00, 0xFE, 0x11, 0x00, 0x83, 0x74, 0x00, 0x04, 0x00, 0x01, 0x96,
                0x00, 0x00, 0x00, 0x02, 0xAA, 0x00, 0x00, 0x00, 0x82, 0x87
            ]
        );
        encode_sync_read(address::PRESENT_POSITION, 4, &[1, 2], &mut out);
        assert_eq!(
            out,
            [
                0xFF, 0xFF, 0xFD, 0x00, 0xFE, 0x09, 0x00, 0x82, 0x84, 0x00, 0x04, 0x00, 0x01, 0x02,
                0xCE, 0xFA
            ]
        );
    }

    /// CRC-16/UMTS is the Dynamixel CRC: its catalogue check value is that of BUYPASS.
    #[test]
    fn the_crc_is_crc16_buypass() {
        assert_eq!(crc16(b"123456789"), 0xFEE8);
    }

    #[test]
    fn stuffing_is_added_counted_and_removed() {
        let mut out = Vec::new();
        // Goal -131073 is FF FF FD FF little endian: one pattern, one stuffed byte.
        encode_sync_write_i32(address::GOAL_POSITION, &[(1, -131_073)], &mut out);
        let plain = PACKET_OVERHEAD + 4 + 5;
        assert_eq!(out.len(), plain + 1);
        assert_eq!(u16::from_le_bytes([out[5], out[6]]) as usize, plain + 1 - 7);
        assert!(out.windows(4).any(|w| w == [0xFF, 0xFF, 0xFD, 0xFD]));
        let mut decoder = PacketDecoder::default();
        decoder.push(&[0x00, 0xFF]);
        decoder.push(&out);
        let packet = decoder.next_packet().expect("a packet").expect("valid");
        assert_eq!(packet.instruction, instruction::SYNC_WRITE);
        assert_eq!(&packet.params[5..9], &(-131_073i32).to_le_bytes());
        assert_eq!(decoder.skipped, 2);
        assert!(decoder.next_packet().is_none());
    }

    #[test]
    fn a_corrupted_packet_is_refused_and_the_next_one_still_read() {
        let mut bad = Vec::new();
        encode_packet(3, instruction::PING, &[], &mut bad);
        bad[7] ^= 0x01;
        let mut good = Vec::new();
        encode_packet(4, instruction::PING, &[], &mut good);
        let mut decoder = PacketDecoder::default();
        decoder.push(&bad);
        decoder.push(&good[..5]);
        assert_eq!(decoder.next_packet(), Some(Err(DecodeError::Crc)));
        assert_eq!(decoder.next_packet(), None);
        decoder.push(&good[5..]);
        let packet = decoder.next_packet().expect("a packet").expect("valid");
        assert_eq!((packet.id, packet.instruction), (4, instruction::PING));
    }

    #[test]
    fn ticks_round_trip_and_the_default_centre_is_2048() {
        let axis = AxisTicks::default();
        assert_eq!(axis.tick(0.0), 2048.0);
        assert_eq!(axis.tick(std::f64::consts::PI / 2.0), 3072.0);
        assert_eq!(axis.tick(-std::f64::consts::PI), 0.0);
        assert!((axis.radians(1024) + std::f64::consts::FRAC_PI_2).abs() < 1e-12);
    }

    #[test]
    fn a_linear_axis_counts_ticks_per_metre_and_turns_its_shaft() {
        // A pinion of 0.1 m a turn: 40960 ticks a metre at 4096 ticks a turn.
        let axis = AxisTicks {
            ticks_per_metre: Some(40960.0),
            ..AxisTicks::default()
        };
        assert_eq!(axis.tick(0.0), 2048.0);
        assert_eq!(axis.tick(0.25), 2048.0 + 10240.0);
        assert!((axis.radians(2048 - 4096) + 0.1).abs() < 1e-12);
        assert!((axis.resolution() - 1.0 / 40960.0).abs() < 1e-15);
        // 0.25 m is 2.5 turns of the pinion.
        assert!((axis.shaft_angle(0.25) - 2.5 * std::f64::consts::TAU).abs() < 1e-12);
    }

    /// By hand for 6 servos: sync write 10 + 4 + 6 x 5 = 44 bytes, sync read 10 + 4 + 6 =
    /// 20, six statuses of 15 = 90: 154 bytes, 166 with one stuffed byte in each of the 12
    /// positions. At 1 Mbaud, 10 bits a byte: 1.66 ms, 602 Hz; with the X-series default
    /// return delay of 500 us each, 4.66 ms.
    #[test]
    fn the_line_budget_of_six_servos_matches_the_hand_count() {
        let budget = line_budget(6, 1_000_000, 0.0);
        assert_eq!(budget.bytes, 154);
        assert_eq!(budget.worst_case_bytes, 166);
        assert_eq!(budget.cycle, Duration::from_micros(1660));
        assert!((budget.max_rate_hz - 602.4).abs() < 0.1);
        let slow = line_budget(6, 1_000_000, 500.0);
        assert_eq!(slow.cycle, Duration::from_micros(4660));
        // 57600 baud: 1660 bits / 57600 = 28.82 ms, 34.7 Hz.
        let factory = line_budget(6, 57_600, 0.0);
        assert!((factory.max_rate_hz - 57_600.0 / 1660.0).abs() < 1e-9);
    }
}
