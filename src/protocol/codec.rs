//! The byte encoding of protocol versions 2 and 3 for byte streams (serial, TCP): message bodies,
//! CRC-32, COBS framing, and a resynchronising [`FrameDecoder`]. `docs/protocol.md` is the
//! normative description; this file must agree with it (tests/codec.rs checks the examples).
//!
//! It owns the wire layout only: it must not open transports (links do), judge motion
//! (limits, speeds and sequence rules are the controller's and the streamer's), or change
//! the in-memory types of `protocol`. The CAN mapping in `can.rs` reuses the wire forms and
//! the CRC here.
//!
//! Hot path: encoding appends to the caller's `Vec<u8>` and decoding reuses the decoder's
//! buffers, so a Target or Feedback allocates nothing once the buffers have grown. Hello
//! and Fault carry strings and may allocate; they are rare.

use super::io::{IoKind, IoMessage, IoResult, IoState, MAX_IO_NAME_LEN, io_name_ok};
use super::{AxisValues, Command, ControllerStatus, Fault, Feedback, JointTarget, MAX_AXES};
use thiserror::Error;

/// The version byte of messages 0x01-0x08 (version 2's layouts), in every session.
pub const PROTOCOL_VERSION: u8 = 2;
/// The version byte of the I/O messages, and of a controller's Hello that says it speaks
/// version 3 (docs/protocol.md 2, 6.10).
pub const PROTOCOL_VERSION_IO: u8 = 3;
/// The longest frame body (version through CRC) a v2 receiver accepts. The longest v2
/// message, a Hello of 32 axes with 32-byte names, is 1584 bytes.
pub const MAX_BODY_LEN: usize = 1600;
/// The longest delimited frame on the wire: the body after COBS (one byte per 254) plus
/// the 0x00 delimiter.
pub const MAX_FRAME_LEN: usize = MAX_BODY_LEN + MAX_BODY_LEN.div_ceil(254) + 1;
/// The longest axis name in a Hello, in bytes of UTF-8.
pub const MAX_NAME_LEN: usize = 32;
/// The longest text in a Fault message, in bytes of UTF-8.
pub const MAX_TEXT_LEN: usize = 128;
/// Times are sent as u64 microseconds but must stay below 2^48 us (8.9 years): the CAN
/// mapping carries 48 bits, and below this an f64 of seconds converts back exactly.
pub const MAX_TIME_US: u64 = 1 << 48;
/// Raw bytes a [`FrameDecoder`] holds between `push` and `next_message` before it drops
/// the oldest (counted as an overrun, like a UART's receive buffer).
pub const DECODER_INPUT_CAPACITY: usize = 64 * 1024;

/// Version byte, message type byte, and the CRC-32.
const BODY_OVERHEAD: usize = 2 + 4;

pub(super) const TYPE_HELLO: u8 = 0x01;
pub(super) const TYPE_TARGET: u8 = 0x02;
pub(super) const TYPE_STOP: u8 = 0x03;
pub(super) const TYPE_ESTOP: u8 = 0x04;
pub(super) const TYPE_HEARTBEAT: u8 = 0x05;
pub(super) const TYPE_FEEDBACK: u8 = 0x06;
pub(super) const TYPE_FAULT: u8 = 0x07;
pub(super) const TYPE_RESET: u8 = 0x08;
pub(super) const TYPE_SET_OUTPUT: u8 = 0x09;
pub(super) const TYPE_READ_INPUT: u8 = 0x0A;
pub(super) const TYPE_IO_STATE: u8 = 0x0B;
/// Hello flags bit 0: this Hello answers a bridge Hello (docs/protocol.md 6.1).
const HELLO_ANSWER: u8 = 0x01;

/// A controller's or bridge's description of itself, sent when a link (re)connects.
/// Limits are rad (revolute) or m (prismatic), speeds rad/s or m/s, in joint order.
#[derive(Debug, Clone, PartialEq)]
pub struct Hello {
    pub axis_names: Vec<String>,
    pub lower: Vec<f64>,
    pub upper: Vec<f64>,
    pub max_speed: Vec<f64>,
    /// rad/s² or m/s²: the most the sender plans with (bridge) or admits and brakes with
    /// (controller).
    pub max_acceleration: Vec<f64>,
    /// The sender's cycle (us).
    pub cycle_us: u32,
    /// Cycles without a target before the controller decelerates and holds; also the
    /// cycles of silence that count as link loss.
    pub watchdog_cycles: u32,
    /// True when this Hello answers a bridge Hello (controllers only).
    pub answer: bool,
    /// The frame's version byte: 2, or 3 from a controller that speaks version 3 (I/O).
    /// The bridge's Hello is always 2 (docs/protocol.md 6.10).
    pub version: u8,
}

/// `period` as a Hello's `cycle_us`: whole microseconds, rounded to the nearest.
pub fn cycle_us(period: std::time::Duration) -> u32 {
    u32::try_from((period.as_nanos() + 500) / 1000).unwrap_or(u32::MAX)
}

/// A controller's notice that it latched a fault, with its own words for it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FaultReport {
    pub fault: Fault,
    /// Up to [`MAX_TEXT_LEN`] bytes of UTF-8; may be empty.
    pub text: String,
}

/// Everything that travels between the bridge and a controller.
// A target is large next to the other variants, but boxing it would allocate every cycle.
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Clone, PartialEq)]
pub enum Message {
    Hello(Hello),
    /// Bridge to controller (a Heartbeat may go either way).
    Command(Command),
    /// Controller to bridge, every cycle.
    Feedback(Feedback),
    /// Controller to bridge, once when a fault latches.
    Fault(FaultReport),
    /// Version 3's I/O: a request from the bridge or the controller's answer.
    Io(IoMessage),
}

#[derive(Debug, Clone, PartialEq, Error)]
pub enum EncodeError {
    #[error("{field} = {value} does not fit the wire range {range}")]
    OutOfRange {
        field: &'static str,
        value: f64,
        range: &'static str,
    },
    #[error("a target has {positions} positions but {velocities} velocities")]
    AxisMismatch { positions: usize, velocities: usize },
    #[error(
        "a Hello has {names} names, {lower} lower, {upper} upper limits, {max_speed} speeds and {max_acceleration} accelerations (at most {MAX_AXES}, all equal)"
    )]
    HelloLengths {
        names: usize,
        lower: usize,
        upper: usize,
        max_speed: usize,
        max_acceleration: usize,
    },
    #[error("axis name `{name}` is {len} bytes; at most {MAX_NAME_LEN}")]
    NameTooLong { name: String, len: usize },
    #[error("fault text is {len} bytes; at most {MAX_TEXT_LEN}")]
    TextTooLong { len: usize },
    #[error("a body of {len} bytes needs more than 256 CAN segments")]
    TooLongForCan { len: usize },
    #[error(
        "I/O name `{name}` is not 1 to {MAX_IO_NAME_LEN} letters, digits or `_` (docs/protocol.md 3.6)"
    )]
    IoName { name: String },
    #[error("an I/O request is numbered 0; requests count from 1")]
    IoRequestZero,
    #[error("a Hello of version {0}: a Hello is version 2 or 3")]
    HelloVersion(u8),
    #[error("a {message} is not sent by the {sender} on CAN")]
    WrongSender {
        message: &'static str,
        sender: &'static str,
    },
}

/// Why one frame body was refused. The [`FrameDecoder`] counts these rather than
/// returning them.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum DecodeError {
    #[error("frame body of {0} bytes is shorter than the 6-byte minimum")]
    TooShort(usize),
    #[error("frame body of {0} bytes is longer than {MAX_BODY_LEN}")]
    TooLong(usize),
    #[error("CRC mismatch: frame says {sent:#010x}, bytes give {computed:#010x}")]
    Crc { sent: u32, computed: u32 },
    #[error("protocol version {0} is not supported (this is versions 2 and 3)")]
    UnsupportedVersion(u8),
    #[error("COBS encoding is broken")]
    Cobs,
    #[error("malformed message: {0}")]
    Malformed(&'static str),
}

// ---------------------------------------------------------------------------------------
// CRC-32 (IEEE 802.3): poly 0x04C11DB7 reflected (0xEDB88320), init and xorout 0xFFFFFFFF.

const CRC_TABLE: [u32; 256] = crc_table();

const fn crc_table() -> [u32; 256] {
    let mut table = [0u32; 256];
    let mut index = 0;
    while index < 256 {
        let mut crc = index as u32;
        let mut bit = 0;
        while bit < 8 {
            crc = if crc & 1 == 1 {
                (crc >> 1) ^ 0xEDB8_8320
            } else {
                crc >> 1
            };
            bit += 1;
        }
        table[index] = crc;
        index += 1;
    }
    table
}

/// A running CRC-32; `finish` gives the value sent on the wire.
#[derive(Debug, Clone, Copy)]
pub(super) struct Crc32(u32);

impl Crc32 {
    pub(super) fn new() -> Self {
        Self(0xFFFF_FFFF)
    }

    pub(super) fn update(&mut self, bytes: &[u8]) {
        for &byte in bytes {
            self.0 = (self.0 >> 8) ^ CRC_TABLE[usize::from((self.0 as u8) ^ byte)];
        }
    }

    pub(super) fn finish(self) -> u32 {
        !self.0
    }
}

/// CRC-32/ISO-HDLC (the IEEE 802.3 CRC) of `bytes`; `crc32(b"123456789") == 0xCBF43926`.
pub fn crc32(bytes: &[u8]) -> u32 {
    let mut crc = Crc32::new();
    crc.update(bytes);
    crc.finish()
}

// ---------------------------------------------------------------------------------------
// COBS (Cheshire and Baker, 1999): no 0x00 inside a frame, so 0x00 can delimit.

/// Appends the COBS encoding of `data` (without a delimiter) to `out`.
pub fn cobs_encode(data: &[u8], out: &mut Vec<u8>) {
    let mut sink = CobsSink::new(out);
    sink.put(data);
    sink.finish();
}

/// Appends the bytes that `data` (one COBS-encoded frame, without its delimiter) stands for.
/// On error `out` may hold part of the frame.
pub fn cobs_decode(data: &[u8], out: &mut Vec<u8>) -> Result<(), DecodeError> {
    let mut at = 0;
    while at < data.len() {
        let code = usize::from(data[at]);
        if code == 0 {
            return Err(DecodeError::Cobs);
        }
        let end = at + code;
        let Some(block) = data.get(at + 1..end) else {
            return Err(DecodeError::Cobs);
        };
        out.extend_from_slice(block);
        at = end;
        // A block of 254 bytes (code 0xFF) is not followed by a zero; nor is the last block.
        if code < 0xFF && at < data.len() {
            out.push(0);
        }
    }
    Ok(())
}

/// Where a body is written: a plain buffer, a CRC, or a COBS frame being built.
pub(super) trait Sink {
    fn put(&mut self, bytes: &[u8]);
}

impl Sink for Vec<u8> {
    fn put(&mut self, bytes: &[u8]) {
        self.extend_from_slice(bytes);
    }
}

impl Sink for Crc32 {
    fn put(&mut self, bytes: &[u8]) {
        self.update(bytes);
    }
}

/// COBS-encodes straight into the caller's buffer, so a frame needs no scratch copy:
/// each block's code byte is reserved and filled in when the block ends.
struct CobsSink<'a> {
    out: &'a mut Vec<u8>,
    code_at: usize,
    block_len: usize,
}

impl<'a> CobsSink<'a> {
    fn new(out: &'a mut Vec<u8>) -> Self {
        let code_at = out.len();
        out.push(0);
        Self {
            out,
            code_at,
            block_len: 0,
        }
    }

    fn end_block(&mut self, code: u8) {
        self.out[self.code_at] = code;
        self.code_at = self.out.len();
        self.out.push(0);
        self.block_len = 0;
    }

    fn finish(self) {
        self.out[self.code_at] = (self.block_len + 1) as u8;
    }
}

impl Sink for CobsSink<'_> {
    fn put(&mut self, bytes: &[u8]) {
        for &byte in bytes {
            // A full block is closed only when more data follows, which keeps the encoding
            // canonical (no empty trailing block after 254 non-zero bytes).
            if self.block_len == 254 {
                self.end_block(0xFF);
            }
            if byte == 0 {
                self.end_block((self.block_len + 1) as u8);
            } else {
                self.out.push(byte);
                self.block_len += 1;
            }
        }
    }
}

// ---------------------------------------------------------------------------------------
// Units: f64 in memory, integers on the wire. Round to nearest; never saturate.

const MICRO: f64 = 1e6;
const I32_RANGE: &str = "-2147.483648..=2147.483647 (i32 of 1e-6 units)";
const TIME_RANGE: &str = "0..2^48 us (0 to 8.9 years)";

/// rad -> urad (or m -> um, rad/s -> urad/s).
fn to_micro(field: &'static str, value: f64) -> Result<i32, EncodeError> {
    let scaled = (value * MICRO).round();
    if scaled >= f64::from(i32::MIN) && scaled <= f64::from(i32::MAX) {
        Ok(scaled as i32)
    } else {
        // NaN fails both comparisons and lands here too.
        Err(EncodeError::OutOfRange {
            field,
            value,
            range: I32_RANGE,
        })
    }
}

pub(super) fn from_micro(value: i32) -> f64 {
    f64::from(value) / MICRO
}

/// s -> us since job start.
fn time_to_us(t: f64) -> Result<u64, EncodeError> {
    let scaled = (t * MICRO).round();
    if scaled >= 0.0 && scaled < MAX_TIME_US as f64 {
        Ok(scaled as u64)
    } else {
        Err(EncodeError::OutOfRange {
            field: "t",
            value: t,
            range: TIME_RANGE,
        })
    }
}

pub(super) fn time_from_us(us: u64) -> std::time::Duration {
    std::time::Duration::from_micros(us)
}

fn values_to_micro(
    field: &'static str,
    values: &[f64],
    out: &mut [i32; MAX_AXES],
) -> Result<(), EncodeError> {
    for (slot, &value) in out.iter_mut().zip(values) {
        *slot = to_micro(field, value)?;
    }
    Ok(())
}

fn values_from_micro(values: &[i32]) -> AxisValues {
    let mut out = AxisValues::zeros(values.len());
    for (slot, &value) in out.as_mut_slice().iter_mut().zip(values) {
        *slot = from_micro(value);
    }
    out
}

// ---------------------------------------------------------------------------------------
// Wire forms: the integers a Target or Feedback is sent as. Shared with the CAN mapping,
// whose per-message CRC is the CRC of the byte-stream body.

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct WireTarget {
    pub seq: u32,
    pub t_us: u64,
    pub axes: u8,
    pub positions: [i32; MAX_AXES],
    pub velocities: [i32; MAX_AXES],
}

impl WireTarget {
    pub(super) fn empty() -> Self {
        Self {
            seq: 0,
            t_us: 0,
            axes: 0,
            positions: [0; MAX_AXES],
            velocities: [0; MAX_AXES],
        }
    }

    pub(super) fn from_target(target: &JointTarget) -> Result<Self, EncodeError> {
        let (positions, velocities) = (target.positions.as_slice(), target.velocities.as_slice());
        if positions.len() != velocities.len() {
            return Err(EncodeError::AxisMismatch {
                positions: positions.len(),
                velocities: velocities.len(),
            });
        }
        let mut wire = Self::empty();
        wire.seq = target.seq;
        wire.t_us = time_to_us(target.t.as_secs_f64())?;
        // AxisValues holds at most MAX_AXES (32) values, so this fits a u8.
        wire.axes = positions.len() as u8;
        values_to_micro("position", positions, &mut wire.positions)?;
        values_to_micro("velocity", velocities, &mut wire.velocities)?;
        Ok(wire)
    }

    pub(super) fn joint_target(&self) -> JointTarget {
        let axes = usize::from(self.axes).min(MAX_AXES);
        JointTarget {
            seq: self.seq,
            t: time_from_us(self.t_us),
            positions: values_from_micro(&self.positions[..axes]),
            velocities: values_from_micro(&self.velocities[..axes]),
        }
    }

    pub(super) fn positions(&self) -> &[i32] {
        &self.positions[..usize::from(self.axes).min(MAX_AXES)]
    }

    pub(super) fn velocities(&self) -> &[i32] {
        &self.velocities[..usize::from(self.axes).min(MAX_AXES)]
    }

    /// seq u32 | t u64 | axes u8 | positions i32 x axes | velocities i32 x axes
    pub(super) fn write_payload<S: Sink>(&self, sink: &mut S) {
        sink.put(&self.seq.to_le_bytes());
        sink.put(&self.t_us.to_le_bytes());
        sink.put(&[self.axes]);
        write_i32s(sink, self.positions());
        write_i32s(sink, self.velocities());
    }

    pub(super) fn read_payload(reader: &mut Reader<'_>) -> Result<Self, DecodeError> {
        let mut wire = Self::empty();
        wire.seq = reader.u32()?;
        wire.t_us = reader.u64()?;
        if wire.t_us >= MAX_TIME_US {
            return Err(DecodeError::Malformed("t is 2^48 us or more"));
        }
        wire.axes = reader.axis_count()?;
        let axes = usize::from(wire.axes);
        reader.i32s(&mut wire.positions[..axes])?;
        reader.i32s(&mut wire.velocities[..axes])?;
        Ok(wire)
    }

    /// The CRC-32 this target's byte-stream frame carries (the CAN commit frame repeats it).
    pub(super) fn crc(&self) -> u32 {
        let mut crc = Crc32::new();
        crc.put(&[PROTOCOL_VERSION, TYPE_TARGET]);
        self.write_payload(&mut crc);
        crc.finish()
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct WireFeedback {
    pub seq: u32,
    pub status: [u8; 4],
    pub axes: u8,
    pub positions: [i32; MAX_AXES],
}

impl WireFeedback {
    pub(super) fn empty() -> Self {
        Self {
            seq: 0,
            status: [0; 4],
            axes: 0,
            positions: [0; MAX_AXES],
        }
    }

    pub(super) fn from_feedback(feedback: &Feedback) -> Result<Self, EncodeError> {
        let positions = feedback.positions.as_slice();
        let mut wire = Self::empty();
        wire.seq = feedback.seq;
        wire.status = status_to_wire(feedback.status);
        wire.axes = positions.len() as u8;
        values_to_micro("position", positions, &mut wire.positions)?;
        Ok(wire)
    }

    /// `None` when the status bytes name no v1 status.
    pub(super) fn feedback(&self) -> Option<Feedback> {
        let axes = usize::from(self.axes).min(MAX_AXES);
        Some(Feedback {
            seq: self.seq,
            positions: values_from_micro(&self.positions[..axes]),
            status: status_from_wire(self.status)?,
        })
    }

    pub(super) fn positions(&self) -> &[i32] {
        &self.positions[..usize::from(self.axes).min(MAX_AXES)]
    }

    /// seq u32 | status u8 | fault code u8 | fault arg a u8 | fault arg b u8 | axes u8 |
    /// positions i32 x axes
    pub(super) fn write_payload<S: Sink>(&self, sink: &mut S) {
        sink.put(&self.seq.to_le_bytes());
        sink.put(&self.status);
        sink.put(&[self.axes]);
        write_i32s(sink, self.positions());
    }

    pub(super) fn read_payload(reader: &mut Reader<'_>) -> Result<Self, DecodeError> {
        let mut wire = Self::empty();
        wire.seq = reader.u32()?;
        wire.status.copy_from_slice(reader.take(4)?);
        wire.axes = reader.axis_count()?;
        let axes = usize::from(wire.axes);
        reader.i32s(&mut wire.positions[..axes])?;
        Ok(wire)
    }

    pub(super) fn crc(&self) -> u32 {
        let mut crc = Crc32::new();
        crc.put(&[PROTOCOL_VERSION, TYPE_FEEDBACK]);
        self.write_payload(&mut crc);
        crc.finish()
    }
}

fn write_i32s<S: Sink>(sink: &mut S, values: &[i32]) {
    for value in values {
        sink.put(&value.to_le_bytes());
    }
}

const STATUS_OK: u8 = 0;
const STATUS_HOLDING: u8 = 1;
const STATUS_FAULT: u8 = 2;

const FAULT_OUTSIDE_LIMITS: u8 = 1;
const FAULT_OVER_SPEED: u8 = 2;
const FAULT_AXIS_COUNT: u8 = 3;
const FAULT_ESTOP: u8 = 4;
const FAULT_OVER_ACCELERATION: u8 = 5;
const FAULT_BUSY: u8 = 6;
const FAULT_DRIVE: u8 = 7;
const FAULT_COLLISION: u8 = 8;

/// code, a, b: a is the axis (or the expected axis count), b the axis count received.
fn fault_to_wire(fault: Fault) -> [u8; 3] {
    match fault {
        Fault::OutsideLimits { axis } => [FAULT_OUTSIDE_LIMITS, axis, 0],
        Fault::OverSpeed { axis } => [FAULT_OVER_SPEED, axis, 0],
        Fault::AxisCount { expected, got } => [FAULT_AXIS_COUNT, expected, got],
        Fault::EStop => [FAULT_ESTOP, 0, 0],
        Fault::OverAcceleration { axis } => [FAULT_OVER_ACCELERATION, axis, 0],
        Fault::Busy => [FAULT_BUSY, 0, 0],
        Fault::Drive { axis } => [FAULT_DRIVE, axis, 0],
        Fault::Collision => [FAULT_COLLISION, 0, 0],
    }
}

/// Strict: unused argument bytes must be zero, so every fault has exactly one encoding.
fn fault_from_wire([code, a, b]: [u8; 3]) -> Option<Fault> {
    match (code, b) {
        (FAULT_OUTSIDE_LIMITS, 0) => Some(Fault::OutsideLimits { axis: a }),
        (FAULT_OVER_SPEED, 0) => Some(Fault::OverSpeed { axis: a }),
        (FAULT_AXIS_COUNT, got) => Some(Fault::AxisCount { expected: a, got }),
        (FAULT_ESTOP, 0) if a == 0 => Some(Fault::EStop),
        (FAULT_OVER_ACCELERATION, 0) => Some(Fault::OverAcceleration { axis: a }),
        (FAULT_BUSY, 0) if a == 0 => Some(Fault::Busy),
        (FAULT_DRIVE, 0) => Some(Fault::Drive { axis: a }),
        (FAULT_COLLISION, 0) if a == 0 => Some(Fault::Collision),
        _ => None,
    }
}

fn status_to_wire(status: ControllerStatus) -> [u8; 4] {
    match status {
        ControllerStatus::Ok => [STATUS_OK, 0, 0, 0],
        ControllerStatus::Holding => [STATUS_HOLDING, 0, 0, 0],
        ControllerStatus::Fault(fault) => {
            let [code, a, b] = fault_to_wire(fault);
            [STATUS_FAULT, code, a, b]
        }
    }
}

fn status_from_wire([status, code, a, b]: [u8; 4]) -> Option<ControllerStatus> {
    match (status, [code, a, b]) {
        (STATUS_OK, [0, 0, 0]) => Some(ControllerStatus::Ok),
        (STATUS_HOLDING, [0, 0, 0]) => Some(ControllerStatus::Holding),
        // Busy is a notice for a Fault message, never a latched status.
        (STATUS_FAULT, fault) => fault_from_wire(fault)
            .filter(|f| *f != Fault::Busy)
            .map(ControllerStatus::Fault),
        _ => None,
    }
}

// ---------------------------------------------------------------------------------------
// Bodies: version u8 | type u8 | payload | CRC-32 (LE) over version..payload.

/// Writes version, type and payload (not the CRC). On error the sink may hold part of it.
fn write_message<S: Sink>(message: &Message, sink: &mut S) -> Result<(), EncodeError> {
    match message {
        Message::Hello(hello) => write_hello(hello, sink),
        Message::Command(Command::Target(target)) => {
            let wire = WireTarget::from_target(target)?;
            sink.put(&[PROTOCOL_VERSION, TYPE_TARGET]);
            wire.write_payload(sink);
            Ok(())
        }
        Message::Command(Command::Stop) => {
            sink.put(&[PROTOCOL_VERSION, TYPE_STOP]);
            Ok(())
        }
        Message::Command(Command::EStop) => {
            sink.put(&[PROTOCOL_VERSION, TYPE_ESTOP]);
            Ok(())
        }
        Message::Command(Command::Heartbeat) => {
            sink.put(&[PROTOCOL_VERSION, TYPE_HEARTBEAT]);
            Ok(())
        }
        Message::Command(Command::Reset) => {
            sink.put(&[PROTOCOL_VERSION, TYPE_RESET]);
            Ok(())
        }
        Message::Feedback(feedback) => {
            let wire = WireFeedback::from_feedback(feedback)?;
            sink.put(&[PROTOCOL_VERSION, TYPE_FEEDBACK]);
            wire.write_payload(sink);
            Ok(())
        }
        Message::Fault(report) => write_fault(report, sink),
        Message::Io(io) => write_io(io, sink),
    }
}

/// request u32 | [SetOutput: value u8] | [IoState: kind u8 | result u8 | value u8] |
/// name length u8 | name
fn write_io<S: Sink>(io: &IoMessage, sink: &mut S) -> Result<(), EncodeError> {
    let (kind, name) = match io {
        IoMessage::SetOutput { name, .. } => (TYPE_SET_OUTPUT, name),
        IoMessage::ReadInput { name, .. } => (TYPE_READ_INPUT, name),
        IoMessage::State(state) => (TYPE_IO_STATE, &state.name),
    };
    if !io_name_ok(name) {
        return Err(EncodeError::IoName { name: name.clone() });
    }
    if io.request() == 0 {
        return Err(EncodeError::IoRequestZero);
    }
    sink.put(&[PROTOCOL_VERSION_IO, kind]);
    sink.put(&io.request().to_le_bytes());
    match io {
        IoMessage::SetOutput { value, .. } => sink.put(&[u8::from(*value)]),
        IoMessage::ReadInput { .. } => {}
        IoMessage::State(state) => sink.put(&[
            io_kind_to_wire(state.kind),
            io_result_to_wire(state.result),
            u8::from(state.value),
        ]),
    }
    sink.put(&[name.len() as u8]);
    sink.put(name.as_bytes());
    Ok(())
}

fn io_kind_to_wire(kind: IoKind) -> u8 {
    match kind {
        IoKind::Output => 0,
        IoKind::Input => 1,
    }
}

fn io_result_to_wire(result: IoResult) -> u8 {
    match result {
        IoResult::Done => 0,
        IoResult::NoSuch => 1,
        IoResult::Refused => 2,
    }
}

/// axes u8 | axes x (name length u8 | UTF-8) | axes x (lower i32 | upper i32 | max speed
/// i32 | max acceleration i32) | cycle us u32 | watchdog cycles u32 | flags u8
fn write_hello<S: Sink>(hello: &Hello, sink: &mut S) -> Result<(), EncodeError> {
    let axes = hello.axis_names.len();
    if axes > MAX_AXES
        || hello.lower.len() != axes
        || hello.upper.len() != axes
        || hello.max_speed.len() != axes
        || hello.max_acceleration.len() != axes
    {
        return Err(EncodeError::HelloLengths {
            names: axes,
            lower: hello.lower.len(),
            upper: hello.upper.len(),
            max_speed: hello.max_speed.len(),
            max_acceleration: hello.max_acceleration.len(),
        });
    }
    if let Some(name) = hello.axis_names.iter().find(|n| n.len() > MAX_NAME_LEN) {
        return Err(EncodeError::NameTooLong {
            name: name.clone(),
            len: name.len(),
        });
    }
    if hello.version != PROTOCOL_VERSION && hello.version != PROTOCOL_VERSION_IO {
        return Err(EncodeError::HelloVersion(hello.version));
    }
    sink.put(&[hello.version, TYPE_HELLO, axes as u8]);
    for name in &hello.axis_names {
        sink.put(&[name.len() as u8]);
        sink.put(name.as_bytes());
    }
    for axis in 0..axes {
        sink.put(&to_micro("lower limit", hello.lower[axis])?.to_le_bytes());
        sink.put(&to_micro("upper limit", hello.upper[axis])?.to_le_bytes());
        sink.put(&to_micro("max speed", hello.max_speed[axis])?.to_le_bytes());
        sink.put(&to_micro("max acceleration", hello.max_acceleration[axis])?.to_le_bytes());
    }
    sink.put(&hello.cycle_us.to_le_bytes());
    sink.put(&hello.watchdog_cycles.to_le_bytes());
    sink.put(&[if hello.answer { HELLO_ANSWER } else { 0 }]);
    Ok(())
}

/// code u8 | a u8 | b u8 | text length u8 | UTF-8
fn write_fault<S: Sink>(report: &FaultReport, sink: &mut S) -> Result<(), EncodeError> {
    if report.text.len() > MAX_TEXT_LEN {
        return Err(EncodeError::TextTooLong {
            len: report.text.len(),
        });
    }
    sink.put(&[PROTOCOL_VERSION, TYPE_FAULT]);
    sink.put(&fault_to_wire(report.fault));
    sink.put(&[report.text.len() as u8]);
    sink.put(report.text.as_bytes());
    Ok(())
}

/// Appends one complete frame body (version, type, payload, CRC-32) to `out`, without
/// COBS or delimiter: for transports that frame by themselves (datagrams, CAN segments).
/// On error `out` is left as it was.
pub fn encode_body(message: &Message, out: &mut Vec<u8>) -> Result<(), EncodeError> {
    let start = out.len();
    if let Err(error) = write_message(message, out) {
        out.truncate(start);
        return Err(error);
    }
    let crc = crc32(&out[start..]);
    out.extend_from_slice(&crc.to_le_bytes());
    Ok(())
}

/// Appends one complete delimited frame (COBS of the body, then 0x00) to `out`. On error
/// `out` is left as it was.
pub fn encode_frame(message: &Message, out: &mut Vec<u8>) -> Result<(), EncodeError> {
    let start = out.len();
    let mut cobs = CobsSink::new(out);
    let mut body = Tee {
        sink: &mut cobs,
        crc: Crc32::new(),
    };
    if let Err(error) = write_message(message, &mut body) {
        out.truncate(start);
        return Err(error);
    }
    let crc = body.crc.finish();
    cobs.put(&crc.to_le_bytes());
    cobs.finish();
    out.push(0);
    Ok(())
}

/// Writes to a sink while keeping the CRC of what passed.
struct Tee<'a, S: Sink> {
    sink: &'a mut S,
    crc: Crc32,
}

impl<S: Sink> Sink for Tee<'_, S> {
    fn put(&mut self, bytes: &[u8]) {
        self.crc.update(bytes);
        self.sink.put(bytes);
    }
}

/// Decodes one frame body (version through CRC, COBS already undone). The CRC is checked
/// before anything else, so corruption is never mistaken for another version.
pub fn decode_body(body: &[u8]) -> Result<Message, DecodeError> {
    if body.len() < BODY_OVERHEAD {
        return Err(DecodeError::TooShort(body.len()));
    }
    if body.len() > MAX_BODY_LEN {
        return Err(DecodeError::TooLong(body.len()));
    }
    let (covered, sent) = body.split_at(body.len() - 4);
    let sent = u32::from_le_bytes([sent[0], sent[1], sent[2], sent[3]]);
    let computed = crc32(covered);
    if sent != computed {
        return Err(DecodeError::Crc { sent, computed });
    }
    let (version, kind) = (covered[0], covered[1]);
    if version != PROTOCOL_VERSION && version != PROTOCOL_VERSION_IO {
        return Err(DecodeError::UnsupportedVersion(version));
    }
    let mut reader = Reader {
        bytes: &covered[2..],
    };
    let mut message = match kind {
        TYPE_SET_OUTPUT | TYPE_READ_INPUT | TYPE_IO_STATE if version == PROTOCOL_VERSION => {
            return Err(DecodeError::Malformed(
                "an I/O message in a version 2 frame",
            ));
        }
        TYPE_SET_OUTPUT | TYPE_READ_INPUT | TYPE_IO_STATE => {
            Message::Io(read_io(kind, &mut reader)?)
        }
        _ => read_message(kind, &mut reader)?,
    };
    reader.finish()?;
    if let Message::Hello(hello) = &mut message {
        hello.version = version;
    }
    Ok(message)
}

/// The payload of SetOutput, ReadInput or IoState (`kind`), strict as 3.6 says.
fn read_io(kind: u8, reader: &mut Reader<'_>) -> Result<IoMessage, DecodeError> {
    let request = reader.u32()?;
    if request == 0 {
        return Err(DecodeError::Malformed("I/O request 0"));
    }
    let io = match kind {
        TYPE_SET_OUTPUT => {
            let value = read_bit(reader)?;
            IoMessage::SetOutput {
                request,
                value,
                name: read_io_name(reader)?,
            }
        }
        TYPE_READ_INPUT => IoMessage::ReadInput {
            request,
            name: read_io_name(reader)?,
        },
        _ => {
            let kind = match reader.u8()? {
                0 => IoKind::Output,
                1 => IoKind::Input,
                _ => return Err(DecodeError::Malformed("unknown I/O kind")),
            };
            let result = match reader.u8()? {
                0 => IoResult::Done,
                1 => IoResult::NoSuch,
                2 => IoResult::Refused,
                _ => return Err(DecodeError::Malformed("unknown I/O result")),
            };
            let value = read_bit(reader)?;
            IoMessage::State(IoState {
                request,
                kind,
                result,
                value,
                name: read_io_name(reader)?,
            })
        }
    };
    Ok(io)
}

fn read_bit(reader: &mut Reader<'_>) -> Result<bool, DecodeError> {
    match reader.u8()? {
        0 => Ok(false),
        1 => Ok(true),
        _ => Err(DecodeError::Malformed("a digital value other than 0 or 1")),
    }
}

fn read_io_name(reader: &mut Reader<'_>) -> Result<String, DecodeError> {
    let len = usize::from(reader.u8()?);
    let name = reader.text(len)?;
    if io_name_ok(&name) {
        Ok(name)
    } else {
        Err(DecodeError::Malformed(
            "an I/O name that is not 1 to 32 letters, digits or _",
        ))
    }
}

fn read_message(kind: u8, reader: &mut Reader<'_>) -> Result<Message, DecodeError> {
    Ok(match kind {
        TYPE_HELLO => Message::Hello(read_hello(reader)?),
        TYPE_TARGET => Message::Command(Command::Target(
            WireTarget::read_payload(reader)?.joint_target(),
        )),
        TYPE_STOP => Message::Command(Command::Stop),
        TYPE_ESTOP => Message::Command(Command::EStop),
        TYPE_HEARTBEAT => Message::Command(Command::Heartbeat),
        TYPE_RESET => Message::Command(Command::Reset),
        TYPE_FEEDBACK => Message::Feedback(
            WireFeedback::read_payload(reader)?
                .feedback()
                .ok_or(DecodeError::Malformed("unknown status or fault"))?,
        ),
        TYPE_FAULT => Message::Fault(read_fault(reader)?),
        _ => return Err(DecodeError::Malformed("unknown message type")),
    })
}

fn read_hello(reader: &mut Reader<'_>) -> Result<Hello, DecodeError> {
    let axes = usize::from(reader.axis_count()?);
    let mut hello = Hello {
        axis_names: Vec::with_capacity(axes),
        lower: Vec::with_capacity(axes),
        upper: Vec::with_capacity(axes),
        max_speed: Vec::with_capacity(axes),
        max_acceleration: Vec::with_capacity(axes),
        cycle_us: 0,
        watchdog_cycles: 0,
        answer: false,
        version: PROTOCOL_VERSION,
    };
    for _ in 0..axes {
        let len = usize::from(reader.u8()?);
        if len > MAX_NAME_LEN {
            return Err(DecodeError::Malformed("axis name longer than 32 bytes"));
        }
        hello.axis_names.push(reader.text(len)?);
    }
    for _ in 0..axes {
        hello.lower.push(from_micro(reader.i32()?));
        hello.upper.push(from_micro(reader.i32()?));
        hello.max_speed.push(from_micro(reader.i32()?));
        hello.max_acceleration.push(from_micro(reader.i32()?));
    }
    hello.cycle_us = reader.u32()?;
    hello.watchdog_cycles = reader.u32()?;
    hello.answer = match reader.u8()? {
        0 => false,
        HELLO_ANSWER => true,
        _ => return Err(DecodeError::Malformed("unknown Hello flag")),
    };
    Ok(hello)
}

fn read_fault(reader: &mut Reader<'_>) -> Result<FaultReport, DecodeError> {
    let mut code = [0u8; 3];
    code.copy_from_slice(reader.take(3)?);
    let fault = fault_from_wire(code).ok_or(DecodeError::Malformed("unknown fault"))?;
    let len = usize::from(reader.u8()?);
    if len > MAX_TEXT_LEN {
        return Err(DecodeError::Malformed("fault text longer than 128 bytes"));
    }
    Ok(FaultReport {
        fault,
        text: reader.text(len)?,
    })
}

/// Reads little-endian fields off a payload; running short is a malformed message.
pub(super) struct Reader<'a> {
    bytes: &'a [u8],
}

impl<'a> Reader<'a> {
    pub(super) fn new(bytes: &'a [u8]) -> Self {
        Self { bytes }
    }

    pub(super) fn take(&mut self, len: usize) -> Result<&'a [u8], DecodeError> {
        if len > self.bytes.len() {
            return Err(DecodeError::Malformed("payload ends early"));
        }
        let (head, rest) = self.bytes.split_at(len);
        self.bytes = rest;
        Ok(head)
    }

    fn array<const N: usize>(&mut self) -> Result<[u8; N], DecodeError> {
        let mut out = [0u8; N];
        out.copy_from_slice(self.take(N)?);
        Ok(out)
    }

    pub(super) fn u8(&mut self) -> Result<u8, DecodeError> {
        Ok(self.array::<1>()?[0])
    }

    pub(super) fn u32(&mut self) -> Result<u32, DecodeError> {
        Ok(u32::from_le_bytes(self.array()?))
    }

    fn u64(&mut self) -> Result<u64, DecodeError> {
        Ok(u64::from_le_bytes(self.array()?))
    }

    pub(super) fn i32(&mut self) -> Result<i32, DecodeError> {
        Ok(i32::from_le_bytes(self.array()?))
    }

    pub(super) fn i32s(&mut self, out: &mut [i32]) -> Result<(), DecodeError> {
        for slot in out {
            *slot = self.i32()?;
        }
        Ok(())
    }

    pub(super) fn axis_count(&mut self) -> Result<u8, DecodeError> {
        let axes = self.u8()?;
        if usize::from(axes) > MAX_AXES {
            return Err(DecodeError::Malformed("more than 32 axes"));
        }
        Ok(axes)
    }

    fn text(&mut self, len: usize) -> Result<String, DecodeError> {
        let bytes = self.take(len)?;
        let text = std::str::from_utf8(bytes).map_err(|_| DecodeError::Malformed("bad UTF-8"))?;
        Ok(text.to_owned())
    }

    pub(super) fn finish(&self) -> Result<(), DecodeError> {
        if self.bytes.is_empty() {
            Ok(())
        } else {
            Err(DecodeError::Malformed("bytes after the payload"))
        }
    }
}

// ---------------------------------------------------------------------------------------
// Stream decoding.

/// What a [`FrameDecoder`] has seen since it was made.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct DecoderCounters {
    /// Frames decoded into a message.
    pub frames: u64,
    /// Frames whose CRC-32 did not hold (corruption, or garbage before the frame).
    pub crc_errors: u64,
    /// Frames with a good CRC but a broken COBS, layout or value, or too short to hold one.
    pub malformed: u64,
    /// Frames with a good CRC and a version other than 1.
    pub unsupported_version: u64,
    /// Frames longer than [`MAX_FRAME_LEN`], dropped without decoding.
    pub oversized: u64,
    /// Times pushed input outgrew [`DECODER_INPUT_CAPACITY`] before it was read.
    pub overruns: u64,
    /// Bytes of every dropped frame and overrun (delimiters excluded).
    pub bytes_discarded: u64,
}

/// Splits a byte stream into frames at 0x00 and decodes them. Garbage costs at most the
/// frame it runs into: decoding starts afresh after every delimiter. Memory is fixed at
/// construction: an unterminated frame is dropped once it passes [`MAX_FRAME_LEN`].
pub struct FrameDecoder {
    /// Pushed bytes not yet looked at, from `read` on.
    input: Vec<u8>,
    read: usize,
    /// The COBS bytes of the frame in progress.
    frame: Vec<u8>,
    /// The frame in progress is too long: skip to the next delimiter.
    skipping: bool,
    /// The decoded body of the last frame (reused).
    body: Vec<u8>,
    counters: DecoderCounters,
}

impl Default for FrameDecoder {
    fn default() -> Self {
        Self::new()
    }
}

impl FrameDecoder {
    pub fn new() -> Self {
        Self {
            input: Vec::with_capacity(DECODER_INPUT_CAPACITY),
            read: 0,
            frame: Vec::with_capacity(MAX_FRAME_LEN),
            skipping: false,
            body: Vec::with_capacity(MAX_BODY_LEN),
            counters: DecoderCounters::default(),
        }
    }

    pub fn counters(&self) -> DecoderCounters {
        self.counters
    }

    /// Forgets any partial frame and unread input (after a reconnect); keeps the counters.
    pub fn reset(&mut self) {
        self.input.clear();
        self.read = 0;
        self.frame.clear();
        self.skipping = false;
    }

    /// Queues bytes as they came off the transport, in any pieces. Read them out with
    /// [`next_message`](Self::next_message) before pushing more than
    /// [`DECODER_INPUT_CAPACITY`]: past that the oldest unread bytes are dropped.
    pub fn push(&mut self, bytes: &[u8]) {
        self.input.drain(..self.read);
        self.read = 0;
        let lost = (self.input.len() + bytes.len()).saturating_sub(DECODER_INPUT_CAPACITY);
        if lost == 0 {
            self.input.extend_from_slice(bytes);
            return;
        }
        // Keep the newest bytes: the oldest are the ones a controller no longer needs.
        self.overrun(lost);
        let from_input = lost.min(self.input.len());
        self.input.drain(..from_input);
        self.input.extend_from_slice(&bytes[lost - from_input..]);
    }

    /// `lost` unread bytes were dropped, so the frame in progress has a hole: abandon it
    /// and wait for the next delimiter.
    fn overrun(&mut self, lost: usize) {
        self.counters.overruns += 1;
        self.counters.bytes_discarded += lost as u64;
        self.abandon_frame();
        self.skipping = true;
    }

    /// The next complete, valid message, or `None` once the pushed bytes hold no more.
    pub fn next_message(&mut self) -> Option<Message> {
        loop {
            let pending = &self.input[self.read..];
            let Some(end) = pending.iter().position(|&b| b == 0) else {
                self.collect(self.input.len());
                return None;
            };
            self.collect(self.read + end);
            self.read += 1; // the delimiter
            if self.skipping {
                self.skipping = false;
                continue;
            }
            if self.frame.is_empty() {
                // Back-to-back delimiters: senders may lead with 0x00 to cut off garbage.
                continue;
            }
            if let Some(message) = self.decode_frame() {
                return Some(message);
            }
        }
    }

    /// Moves input up to `end` into the frame in progress, dropping a frame that grows
    /// past the limit.
    fn collect(&mut self, end: usize) {
        let bytes = &self.input[self.read..end];
        self.read = end;
        if self.skipping {
            self.counters.bytes_discarded += bytes.len() as u64;
        } else if self.frame.len() + bytes.len() > MAX_FRAME_LEN - 1 {
            self.counters.oversized += 1;
            self.counters.bytes_discarded += (self.frame.len() + bytes.len()) as u64;
            self.frame.clear();
            self.skipping = true;
        } else {
            self.frame.extend_from_slice(bytes);
        }
    }

    fn abandon_frame(&mut self) {
        self.counters.bytes_discarded += self.frame.len() as u64;
        self.frame.clear();
    }

    /// Decodes the completed frame and clears it; counts it if it is refused.
    fn decode_frame(&mut self) -> Option<Message> {
        self.body.clear();
        let result =
            cobs_decode(&self.frame, &mut self.body).and_then(|()| decode_body(&self.body));
        match result {
            Ok(message) => {
                self.counters.frames += 1;
                self.frame.clear();
                Some(message)
            }
            Err(error) => {
                match error {
                    DecodeError::Crc { .. } => self.counters.crc_errors += 1,
                    DecodeError::UnsupportedVersion(_) => self.counters.unsupported_version += 1,
                    DecodeError::TooLong(_) => self.counters.oversized += 1,
                    DecodeError::TooShort(_) | DecodeError::Cobs | DecodeError::Malformed(_) => {
                        self.counters.malformed += 1
                    }
                }
                self.abandon_frame();
                None
            }
        }
    }
}
