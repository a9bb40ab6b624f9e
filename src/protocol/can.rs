//! The CAN mapping of protocol versions 2 and 3: which 11-bit identifiers carry which message, how
//! a Target or Feedback is split over classic CAN (8-byte) or CAN FD (up to 64-byte) frames,
//! and [`CanAssembler`], which rebuilds messages and delivers a multi-frame one only when
//! every frame arrived and its CRC-32 holds (never a half-updated target).
//! `docs/protocol.md` ("CAN mapping") is the normative description.
//!
//! It owns frame payloads only: it must not touch a CAN socket or driver (a link does,
//! with socketcan or a vendor API), judge motion, or change the in-memory types. Values,
//! bodies and CRCs come from `codec.rs`, so both transports agree bit for bit.

use super::codec::{
    DecodeError, EncodeError, MAX_BODY_LEN, Message, Reader, Sink, WireFeedback, WireTarget,
    decode_body, encode_body,
};
use super::io::IoMessage;
use super::{Command, MAX_AXES};
use thiserror::Error;

/// Identifiers the protocol uses from the base: `base..base + CAN_ID_BLOCK`.
pub const CAN_ID_BLOCK: u16 = 0x80;
/// The highest base that keeps the block inside the 11-bit range.
pub const MAX_CAN_BASE_ID: u16 = 0x800 - CAN_ID_BLOCK;

// Offsets from the base ID. Lower IDs win arbitration, so the bridge's stop commands come
// first, and every ID has exactly one sender (two nodes sending one ID corrupt the bus).
// Sent by the bridge:
pub const OFFSET_ESTOP: u16 = 0x00;
pub const OFFSET_STOP: u16 = 0x01;
/// A whole Target in one CAN FD frame (when it fits: up to 6 axes).
pub const OFFSET_TARGET_FD: u16 = 0x02;
pub const OFFSET_TARGET_HEADER: u16 = 0x03;
/// 16 IDs: position frame j carries axes `j*k ..` (k = 2 classic, 16 FD).
pub const OFFSET_TARGET_POSITIONS: u16 = 0x04;
/// 16 IDs, as the positions.
pub const OFFSET_TARGET_VELOCITIES: u16 = 0x14;
pub const OFFSET_TARGET_COMMIT: u16 = 0x24;
pub const OFFSET_HEARTBEAT_BRIDGE: u16 = 0x25;
pub const OFFSET_HELLO_BRIDGE: u16 = 0x26;
/// Protocol v2's Reset, after the bridge's other IDs (it is never urgent).
pub const OFFSET_RESET: u16 = 0x27;
/// Version 3: SetOutput or ReadInput, segmented (docs/protocol.md 7.1, 7.4).
pub const OFFSET_IO_REQUEST: u16 = 0x28;
// Sent by the controller:
pub const OFFSET_FAULT: u16 = 0x40;
/// A whole Feedback in one CAN FD frame (when it fits: up to 13 axes).
pub const OFFSET_FEEDBACK_FD: u16 = 0x41;
pub const OFFSET_FEEDBACK_HEADER: u16 = 0x42;
/// 16 IDs, as the Target's positions.
pub const OFFSET_FEEDBACK_POSITIONS: u16 = 0x43;
pub const OFFSET_FEEDBACK_COMMIT: u16 = 0x53;
pub const OFFSET_HEARTBEAT_CONTROLLER: u16 = 0x54;
pub const OFFSET_HELLO_CONTROLLER: u16 = 0x55;
/// Version 3: IoState, segmented.
pub const OFFSET_IO_STATE: u16 = 0x56;

/// Position or velocity frames per message, at most (32 axes at 2 per classic frame).
const DATA_FRAMES: u16 = 16;
const CLASSIC_PAYLOAD: usize = 8;
const FD_PAYLOAD: usize = 64;
/// The payload lengths a CAN FD frame can have (its DLC codes 0..=15).
const FD_LENGTHS: [usize; 16] = [0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64];
/// seq u32 | t u64 | axes u8, before the values of a one-frame FD Target.
const TARGET_FD_FIXED: usize = 13;
/// seq u32 | status 4 | axes u8, before the positions of a one-frame FD Feedback.
const FEEDBACK_FD_FIXED: usize = 9;

/// Which end of the link a mapping encodes for. Hello and Heartbeat have one ID per
/// sender; the other messages only ever go one way.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CanSender {
    Bridge,
    Controller,
}

impl CanSender {
    fn name(self) -> &'static str {
        match self {
            CanSender::Bridge => "bridge",
            CanSender::Controller => "controller",
        }
    }
}

#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum CanMappingError {
    #[error("CAN base ID {0:#x} leaves no room for the 0x80 IDs (at most {MAX_CAN_BASE_ID:#x})")]
    BaseId(u16),
}

/// Where the protocol sits on a bus: its base ID, classic or FD, and who is sending.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CanMapping {
    base_id: u16,
    fd: bool,
    sender: CanSender,
}

impl CanMapping {
    /// `base_id` at most [`MAX_CAN_BASE_ID`] (a multiple of 0x80 lets one mask filter take
    /// each direction). `fd`: every frame is a CAN FD frame, 64-byte payloads.
    pub fn new(base_id: u16, fd: bool, sender: CanSender) -> Result<Self, CanMappingError> {
        if base_id > MAX_CAN_BASE_ID {
            return Err(CanMappingError::BaseId(base_id));
        }
        Ok(Self {
            base_id,
            fd,
            sender,
        })
    }

    pub fn base_id(&self) -> u16 {
        self.base_id
    }

    pub fn fd(&self) -> bool {
        self.fd
    }

    pub fn sender(&self) -> CanSender {
        self.sender
    }

    fn id(&self, offset: u16) -> u32 {
        u32::from(self.base_id + offset)
    }

    fn payload_len(&self) -> usize {
        if self.fd { FD_PAYLOAD } else { CLASSIC_PAYLOAD }
    }

    /// Values (i32) per position or velocity frame: 2 classic, 16 FD.
    fn values_per_frame(&self) -> usize {
        self.payload_len() / 4
    }

    fn offset_of(&self, id: u32) -> Option<u16> {
        let offset = id.checked_sub(u32::from(self.base_id))?;
        u16::try_from(offset).ok().filter(|&o| o < CAN_ID_BLOCK)
    }
}

/// One CAN frame's identifier and payload, independent of the driver that sends it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CanPayload {
    /// 11-bit standard identifier.
    pub id: u32,
    pub data: [u8; 64],
    /// Payload bytes used: 0..=8 classic; a CAN FD length (0..=8, 12, 16, 20, 24, 32, 48, 64).
    pub len: u8,
    pub fd: bool,
}

impl CanPayload {
    /// A frame of `bytes` (cut at 64), padded with zeros to the next CAN FD length when `fd`.
    pub fn new(id: u32, bytes: &[u8], fd: bool) -> Self {
        let used = bytes.len().min(FD_PAYLOAD);
        let mut data = [0u8; 64];
        data[..used].copy_from_slice(&bytes[..used]);
        let len = if fd { fd_len(used) } else { used };
        Self {
            id,
            data,
            len: len as u8,
            fd,
        }
    }

    /// The used payload bytes.
    pub fn data(&self) -> &[u8] {
        &self.data[..usize::from(self.len).min(FD_PAYLOAD)]
    }
}

/// The shortest CAN FD payload length that holds `len` bytes.
fn fd_len(len: usize) -> usize {
    FD_LENGTHS
        .iter()
        .copied()
        .find(|&l| l >= len)
        .unwrap_or(FD_PAYLOAD)
}

/// Builds one payload on the stack; bytes past 64 are dropped (callers size them to fit).
struct FrameBuf {
    data: [u8; 64],
    len: usize,
}

impl FrameBuf {
    fn new() -> Self {
        Self {
            data: [0; 64],
            len: 0,
        }
    }

    fn payload(&self, id: u32, fd: bool) -> CanPayload {
        CanPayload::new(id, &self.data[..self.len], fd)
    }
}

impl Sink for FrameBuf {
    fn put(&mut self, bytes: &[u8]) {
        let room = FD_PAYLOAD - self.len;
        let used = bytes.len().min(room);
        self.data[self.len..self.len + used].copy_from_slice(&bytes[..used]);
        self.len += used;
    }
}

// ---------------------------------------------------------------------------------------
// Encoding.

/// Appends the frames that carry `message` from `mapping`'s sender, in sending order (which
/// is also ID order, so a controller with several transmit mailboxes keeps it). On error
/// `out` is left as it was. Allocates only for Hello and Fault.
pub fn can_frames(
    message: &Message,
    mapping: &CanMapping,
    out: &mut Vec<CanPayload>,
) -> Result<(), EncodeError> {
    let start = out.len();
    let result = push_frames(message, mapping, out);
    if result.is_err() {
        out.truncate(start);
    }
    result
}

fn push_frames(
    message: &Message,
    mapping: &CanMapping,
    out: &mut Vec<CanPayload>,
) -> Result<(), EncodeError> {
    let fd = mapping.fd;
    match message {
        Message::Command(Command::Heartbeat) => {
            let offset = match mapping.sender {
                CanSender::Bridge => OFFSET_HEARTBEAT_BRIDGE,
                CanSender::Controller => OFFSET_HEARTBEAT_CONTROLLER,
            };
            out.push(CanPayload::new(mapping.id(offset), &[], fd));
        }
        Message::Command(command) => {
            require(mapping, CanSender::Bridge, "command")?;
            match command {
                Command::Target(target) => {
                    target_frames(&WireTarget::from_target(target)?, mapping, out)
                }
                Command::Stop => out.push(CanPayload::new(mapping.id(OFFSET_STOP), &[], fd)),
                Command::EStop => out.push(CanPayload::new(mapping.id(OFFSET_ESTOP), &[], fd)),
                Command::Reset => out.push(CanPayload::new(mapping.id(OFFSET_RESET), &[], fd)),
                Command::Heartbeat => {}
            }
        }
        Message::Feedback(feedback) => {
            require(mapping, CanSender::Controller, "feedback")?;
            feedback_frames(&WireFeedback::from_feedback(feedback)?, mapping, out);
        }
        Message::Fault(_) => {
            require(mapping, CanSender::Controller, "fault")?;
            segment_frames(message, mapping.id(OFFSET_FAULT), mapping, out)?;
        }
        Message::Hello(_) => {
            let offset = match mapping.sender {
                CanSender::Bridge => OFFSET_HELLO_BRIDGE,
                CanSender::Controller => OFFSET_HELLO_CONTROLLER,
            };
            segment_frames(message, mapping.id(offset), mapping, out)?;
        }
        Message::Io(IoMessage::State(_)) => {
            require(mapping, CanSender::Controller, "I/O state")?;
            segment_frames(message, mapping.id(OFFSET_IO_STATE), mapping, out)?;
        }
        Message::Io(_) => {
            require(mapping, CanSender::Bridge, "I/O request")?;
            segment_frames(message, mapping.id(OFFSET_IO_REQUEST), mapping, out)?;
        }
    }
    Ok(())
}

fn require(
    mapping: &CanMapping,
    sender: CanSender,
    message: &'static str,
) -> Result<(), EncodeError> {
    if mapping.sender == sender {
        Ok(())
    } else {
        Err(EncodeError::WrongSender {
            message,
            sender: mapping.sender.name(),
        })
    }
}

fn target_frames(wire: &WireTarget, mapping: &CanMapping, out: &mut Vec<CanPayload>) {
    let fd = mapping.fd;
    if fd && TARGET_FD_FIXED + 8 * usize::from(wire.axes) <= FD_PAYLOAD {
        let mut frame = FrameBuf::new();
        wire.write_payload(&mut frame);
        out.push(frame.payload(mapping.id(OFFSET_TARGET_FD), fd));
        return;
    }
    let mut header = [0u8; 8];
    header[..4].copy_from_slice(&wire.seq.to_le_bytes());
    header[4..].copy_from_slice(&(wire.t_us as u32).to_le_bytes());
    out.push(CanPayload::new(
        mapping.id(OFFSET_TARGET_HEADER),
        &header,
        fd,
    ));
    value_frames(wire.positions(), OFFSET_TARGET_POSITIONS, mapping, out);
    value_frames(wire.velocities(), OFFSET_TARGET_VELOCITIES, mapping, out);
    let mut commit = [0u8; 8];
    commit[..4].copy_from_slice(&wire.crc().to_le_bytes());
    // t is below 2^48 us (checked when the wire form was made), so its top is 16 bits.
    commit[4..6].copy_from_slice(&((wire.t_us >> 32) as u16).to_le_bytes());
    commit[6] = wire.axes;
    out.push(CanPayload::new(
        mapping.id(OFFSET_TARGET_COMMIT),
        &commit,
        fd,
    ));
}

fn feedback_frames(wire: &WireFeedback, mapping: &CanMapping, out: &mut Vec<CanPayload>) {
    let fd = mapping.fd;
    if fd && FEEDBACK_FD_FIXED + 4 * usize::from(wire.axes) <= FD_PAYLOAD {
        let mut frame = FrameBuf::new();
        wire.write_payload(&mut frame);
        out.push(frame.payload(mapping.id(OFFSET_FEEDBACK_FD), fd));
        return;
    }
    let mut header = [0u8; 8];
    header[..4].copy_from_slice(&wire.seq.to_le_bytes());
    header[4..].copy_from_slice(&wire.status);
    out.push(CanPayload::new(
        mapping.id(OFFSET_FEEDBACK_HEADER),
        &header,
        fd,
    ));
    value_frames(wire.positions(), OFFSET_FEEDBACK_POSITIONS, mapping, out);
    let mut commit = [0u8; 8];
    commit[..4].copy_from_slice(&wire.crc().to_le_bytes());
    commit[4] = wire.axes;
    out.push(CanPayload::new(
        mapping.id(OFFSET_FEEDBACK_COMMIT),
        &commit,
        fd,
    ));
}

/// Position or velocity frames: frame j on `first + j` holds values `j*k ..` (k per frame).
fn value_frames(values: &[i32], first: u16, mapping: &CanMapping, out: &mut Vec<CanPayload>) {
    for (index, chunk) in values.chunks(mapping.values_per_frame()).enumerate() {
        let mut frame = FrameBuf::new();
        for value in chunk {
            frame.put(&value.to_le_bytes());
        }
        // At most 16 chunks: there are at most 32 values, and 2 or 16 per frame.
        out.push(frame.payload(mapping.id(first + index as u16), mapping.fd));
    }
}

/// Hello and Fault: the byte-stream frame body (version through CRC-32), cut into frames
/// that each start with a segment index; segment 0 then gives the body's length (u16).
fn segment_frames(
    message: &Message,
    id: u32,
    mapping: &CanMapping,
    out: &mut Vec<CanPayload>,
) -> Result<(), EncodeError> {
    let mut body = Vec::with_capacity(MAX_BODY_LEN);
    encode_body(message, &mut body)?;
    let room = mapping.payload_len();
    let mut rest: &[u8] = &body;
    let mut index: u8 = 0;
    loop {
        let mut frame = FrameBuf::new();
        frame.put(&[index]);
        if index == 0 {
            frame.put(&(body.len() as u16).to_le_bytes());
        }
        let take = rest.len().min(room - frame.len);
        frame.put(&rest[..take]);
        rest = &rest[take..];
        out.push(frame.payload(id, mapping.fd));
        if rest.is_empty() {
            return Ok(());
        }
        // A v1 body (at most 1536 bytes) needs at most 220 classic segments.
        index = index
            .checked_add(1)
            .ok_or(EncodeError::TooLongForCan { len: body.len() })?;
    }
}

// ---------------------------------------------------------------------------------------
// Reassembly.

/// What a [`CanAssembler`] has seen since it was made.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct CanCounters {
    /// Messages delivered.
    pub messages: u64,
    /// Multi-frame messages dropped because a frame was missing: a new header or segment 0
    /// came before the commit, a commit found an axis missing, or a segment was skipped.
    pub incomplete: u64,
    /// Complete messages whose CRC-32 did not hold (frames of two messages mixed, or
    /// corruption CAN's own CRC missed).
    pub crc_errors: u64,
    /// Frames that break the layout: a wrong length or FD flag, an unassigned ID in the
    /// block, a bad value; or a reassembled body that does not decode.
    pub malformed: u64,
    /// Data, commit or later-segment frames with no message open (its start was lost).
    pub orphans: u64,
    /// Reassembled bodies with a good CRC and a version other than 1.
    pub unsupported_version: u64,
    /// Frames outside this mapping's ID block (other traffic on the bus): ignored.
    pub foreign: u64,
}

/// A Target or Feedback being collected: the header, then values by axis, until the commit.
struct Slots {
    open: bool,
    header: [u8; 8],
    /// Positions, then velocities (Feedback uses only positions).
    values: [[i32; MAX_AXES]; 2],
    /// One bit per axis received since the header, for positions and velocities.
    have: [u32; 2],
}

impl Slots {
    fn new() -> Self {
        Self {
            open: false,
            header: [0; 8],
            values: [[0; MAX_AXES]; 2],
            have: [0; 2],
        }
    }

    fn has_all(&self, which: usize, axes: u8) -> bool {
        let needed = if axes >= 32 {
            u32::MAX
        } else {
            (1u32 << axes) - 1
        };
        self.have[which] & needed == needed
    }
}

/// A Hello or Fault being collected segment by segment.
struct Segments {
    open: bool,
    expected: usize,
    next: u8,
    body: Vec<u8>,
}

impl Segments {
    fn new() -> Self {
        Self {
            open: false,
            expected: 0,
            next: 0,
            body: Vec::with_capacity(MAX_BODY_LEN),
        }
    }
}

/// What one frame did to the assembler's state.
// Delivering a target by value keeps the assembler free of allocation; the size is fine.
#[allow(clippy::large_enum_variant)]
enum Step {
    Nothing,
    Deliver(Message),
    Incomplete,
    Crc,
    Malformed,
    Orphan,
    Version,
}

/// Rebuilds messages from the frames of one mapping's ID block, both directions (so one
/// assembler also serves a bus monitor). Keeps fixed buffers; allocates only to deliver a
/// Hello or Fault.
pub struct CanAssembler {
    mapping: CanMapping,
    target: Slots,
    feedback: Slots,
    hello_bridge: Segments,
    hello_controller: Segments,
    fault: Segments,
    io_request: Segments,
    io_state: Segments,
    counters: CanCounters,
}

impl CanAssembler {
    pub fn new(mapping: CanMapping) -> Self {
        Self {
            mapping,
            target: Slots::new(),
            feedback: Slots::new(),
            hello_bridge: Segments::new(),
            hello_controller: Segments::new(),
            fault: Segments::new(),
            io_request: Segments::new(),
            io_state: Segments::new(),
            counters: CanCounters::default(),
        }
    }

    pub fn counters(&self) -> CanCounters {
        self.counters
    }

    /// Forgets every message in progress (after bus-off or a reconnect); keeps the counters.
    pub fn reset(&mut self) {
        self.target.open = false;
        self.feedback.open = false;
        self.hello_bridge.open = false;
        self.hello_controller.open = false;
        self.fault.open = false;
        self.io_request.open = false;
        self.io_state.open = false;
    }

    /// Takes one received frame; returns a message when this frame completes one.
    pub fn push(&mut self, frame: &CanPayload) -> Option<Message> {
        let Some(offset) = self.mapping.offset_of(frame.id) else {
            self.counters.foreign += 1;
            return None;
        };
        let step = if self.frame_shape_ok(frame) {
            self.step(offset, frame.data())
        } else {
            Step::Malformed
        };
        self.count(step)
    }

    fn count(&mut self, step: Step) -> Option<Message> {
        let counters = &mut self.counters;
        match step {
            Step::Nothing => return None,
            Step::Deliver(message) => {
                counters.messages += 1;
                return Some(message);
            }
            Step::Incomplete => counters.incomplete += 1,
            Step::Crc => counters.crc_errors += 1,
            Step::Malformed => counters.malformed += 1,
            Step::Orphan => counters.orphans += 1,
            Step::Version => counters.unsupported_version += 1,
        }
        None
    }

    /// The FD flag must match the mapping, and the length must be one the bus can carry.
    fn frame_shape_ok(&self, frame: &CanPayload) -> bool {
        let len = usize::from(frame.len);
        frame.fd == self.mapping.fd
            && if frame.fd {
                FD_LENGTHS.contains(&len)
            } else {
                len <= CLASSIC_PAYLOAD
            }
    }

    /// What `data` on `offset` does. A message that a new start cuts short is counted in
    /// `incomplete` at once, since the same frame may also deliver the next one.
    fn step(&mut self, offset: u16, data: &[u8]) -> Step {
        let lost = &mut self.counters.incomplete;
        let fd = self.mapping.fd;
        let per_frame = self.mapping.values_per_frame();
        match offset {
            OFFSET_ESTOP => empty(data, Command::EStop),
            OFFSET_STOP => empty(data, Command::Stop),
            OFFSET_RESET => empty(data, Command::Reset),
            OFFSET_HEARTBEAT_BRIDGE | OFFSET_HEARTBEAT_CONTROLLER => {
                empty(data, Command::Heartbeat)
            }
            OFFSET_TARGET_FD if fd => target_fd(data),
            OFFSET_FEEDBACK_FD if fd => feedback_fd(data),
            OFFSET_TARGET_HEADER => open_slots(&mut self.target, data, lost),
            OFFSET_FEEDBACK_HEADER => open_slots(&mut self.feedback, data, lost),
            o if in_range(o, OFFSET_TARGET_POSITIONS) => fill(
                &mut self.target,
                0,
                o - OFFSET_TARGET_POSITIONS,
                per_frame,
                data,
            ),
            o if in_range(o, OFFSET_TARGET_VELOCITIES) => fill(
                &mut self.target,
                1,
                o - OFFSET_TARGET_VELOCITIES,
                per_frame,
                data,
            ),
            o if in_range(o, OFFSET_FEEDBACK_POSITIONS) => fill(
                &mut self.feedback,
                0,
                o - OFFSET_FEEDBACK_POSITIONS,
                per_frame,
                data,
            ),
            OFFSET_TARGET_COMMIT => commit_target(&mut self.target, data),
            OFFSET_FEEDBACK_COMMIT => commit_feedback(&mut self.feedback, data),
            OFFSET_HELLO_BRIDGE => segment(&mut self.hello_bridge, data, is_hello, lost),
            OFFSET_HELLO_CONTROLLER => segment(&mut self.hello_controller, data, is_hello, lost),
            OFFSET_FAULT => segment(&mut self.fault, data, is_fault, lost),
            OFFSET_IO_REQUEST => segment(&mut self.io_request, data, is_io_request, lost),
            OFFSET_IO_STATE => segment(&mut self.io_state, data, is_io_state, lost),
            _ => Step::Malformed,
        }
    }
}

fn in_range(offset: u16, first: u16) -> bool {
    (first..first + DATA_FRAMES).contains(&offset)
}

fn empty(data: &[u8], command: Command) -> Step {
    if data.is_empty() {
        Step::Deliver(Message::Command(command))
    } else {
        Step::Malformed
    }
}

/// A one-frame FD message: the payload, then zeros up to the frame's FD length exactly.
fn fd_payload_ok(data: &[u8], used: usize) -> bool {
    data.len() == fd_len(used) && data[used.min(data.len())..].iter().all(|&b| b == 0)
}

fn target_fd(data: &[u8]) -> Step {
    let mut reader = Reader::new(data);
    let Ok(wire) = WireTarget::read_payload(&mut reader) else {
        return Step::Malformed;
    };
    if !fd_payload_ok(data, TARGET_FD_FIXED + 8 * usize::from(wire.axes)) {
        return Step::Malformed;
    }
    Step::Deliver(Message::Command(Command::Target(wire.joint_target())))
}

fn feedback_fd(data: &[u8]) -> Step {
    let mut reader = Reader::new(data);
    let Ok(wire) = WireFeedback::read_payload(&mut reader) else {
        return Step::Malformed;
    };
    if !fd_payload_ok(data, FEEDBACK_FD_FIXED + 4 * usize::from(wire.axes)) {
        return Step::Malformed;
    }
    match wire.feedback() {
        Some(feedback) => Step::Deliver(Message::Feedback(feedback)),
        None => Step::Malformed,
    }
}

/// A header starts a message; one still open lost a frame (at least its commit).
fn open_slots(slots: &mut Slots, data: &[u8], lost: &mut u64) -> Step {
    let Ok(header) = <[u8; 8]>::try_from(data) else {
        return Step::Malformed;
    };
    if slots.open {
        *lost += 1;
    }
    slots.open = true;
    slots.header = header;
    slots.have = [0; 2];
    Step::Nothing
}

/// A position (`which` 0) or velocity (1) frame: `frame` counts from the first such ID.
fn fill(slots: &mut Slots, which: usize, frame: u16, per_frame: usize, data: &[u8]) -> Step {
    let first = usize::from(frame) * per_frame;
    let count = data.len() / 4;
    if data.is_empty() || !data.len().is_multiple_of(4) || count > per_frame || first >= MAX_AXES {
        return Step::Malformed;
    }
    if !slots.open {
        return Step::Orphan;
    }
    for (index, bytes) in data.chunks_exact(4).enumerate() {
        let axis = first + index;
        if axis < MAX_AXES {
            slots.values[which][axis] =
                i32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]]);
            slots.have[which] |= 1 << axis;
        }
    }
    Step::Nothing
}

fn commit_target(slots: &mut Slots, data: &[u8]) -> Step {
    let Ok(commit) = <[u8; 8]>::try_from(data) else {
        return Step::Malformed;
    };
    if !std::mem::replace(&mut slots.open, false) {
        return Step::Orphan;
    }
    let axes = commit[6];
    if usize::from(axes) > MAX_AXES || commit[7] != 0 {
        return Step::Malformed;
    }
    if !slots.has_all(0, axes) || !slots.has_all(1, axes) {
        return Step::Incomplete;
    }
    let [s0, s1, s2, s3, t0, t1, t2, t3] = slots.header;
    let t_hi = u64::from(u16::from_le_bytes([commit[4], commit[5]]));
    let wire = WireTarget {
        seq: u32::from_le_bytes([s0, s1, s2, s3]),
        t_us: t_hi << 32 | u64::from(u32::from_le_bytes([t0, t1, t2, t3])),
        axes,
        positions: slots.values[0],
        velocities: slots.values[1],
    };
    if wire.crc() != u32::from_le_bytes([commit[0], commit[1], commit[2], commit[3]]) {
        return Step::Crc;
    }
    Step::Deliver(Message::Command(Command::Target(wire.joint_target())))
}

fn commit_feedback(slots: &mut Slots, data: &[u8]) -> Step {
    let Ok(commit) = <[u8; 8]>::try_from(data) else {
        return Step::Malformed;
    };
    if !std::mem::replace(&mut slots.open, false) {
        return Step::Orphan;
    }
    let axes = commit[4];
    if usize::from(axes) > MAX_AXES || commit[5..] != [0, 0, 0] {
        return Step::Malformed;
    }
    if !slots.has_all(0, axes) {
        return Step::Incomplete;
    }
    let [s0, s1, s2, s3, status @ ..] = slots.header;
    let wire = WireFeedback {
        seq: u32::from_le_bytes([s0, s1, s2, s3]),
        status,
        axes,
        positions: slots.values[0],
    };
    if wire.crc() != u32::from_le_bytes([commit[0], commit[1], commit[2], commit[3]]) {
        return Step::Crc;
    }
    match wire.feedback() {
        Some(feedback) => Step::Deliver(Message::Feedback(feedback)),
        None => Step::Malformed,
    }
}

fn is_hello(message: &Message) -> bool {
    matches!(message, Message::Hello(_))
}

fn is_fault(message: &Message) -> bool {
    matches!(message, Message::Fault(_))
}

fn is_io_request(message: &Message) -> bool {
    matches!(
        message,
        Message::Io(IoMessage::SetOutput { .. } | IoMessage::ReadInput { .. })
    )
}

fn is_io_state(message: &Message) -> bool {
    matches!(message, Message::Io(IoMessage::State(_)))
}

/// One segment of a Hello or Fault; the last one decodes the body like a stream frame.
fn segment(
    state: &mut Segments,
    data: &[u8],
    expected_kind: fn(&Message) -> bool,
    lost: &mut u64,
) -> Step {
    let Some((&index, rest)) = data.split_first() else {
        return Step::Malformed;
    };
    let rest = if index == 0 {
        let Some((len, rest)) = rest.split_first_chunk::<2>() else {
            return Step::Malformed;
        };
        let expected = usize::from(u16::from_le_bytes(*len));
        if !(6..=MAX_BODY_LEN).contains(&expected) {
            state.open = false;
            return Step::Malformed;
        }
        if state.open {
            *lost += 1;
        }
        state.open = true;
        state.expected = expected;
        state.next = 0;
        state.body.clear();
        rest
    } else if !state.open {
        return Step::Orphan;
    } else if index != state.next {
        state.open = false;
        return Step::Incomplete;
    } else {
        rest
    };
    let take = rest.len().min(state.expected - state.body.len());
    state.body.extend_from_slice(&rest[..take]);
    state.next = state.next.wrapping_add(1);
    if state.body.len() < state.expected {
        return Step::Nothing;
    }
    state.open = false;
    match decode_body(&state.body) {
        Ok(message) if expected_kind(&message) => Step::Deliver(message),
        Ok(_) => Step::Malformed,
        Err(DecodeError::Crc { .. }) => Step::Crc,
        Err(DecodeError::UnsupportedVersion(_)) => Step::Version,
        Err(_) => Step::Malformed,
    }
}

// ---------------------------------------------------------------------------------------
// Bus load.

/// Bits one classic CAN data frame with an 11-bit ID and `data_len` bytes (cut at 8) takes
/// on the bus, with the 3-bit interframe space. Fixed part: SOF 1, ID 11, RTR 1, IDE 1,
/// r0 1, DLC 4, CRC 15, CRC delimiter 1, ACK 2, EOF 7, IFS 3 = 47. Stuffing applies to the
/// 34 + 8n bits from SOF to the CRC; the worst case is one stuff bit per 4 after the first
/// (Davis, Burns, Bril, Lukkien 2007: (34 + 8n - 1) / 4).
pub fn classic_frame_bits(data_len: usize, worst_case_stuffing: bool) -> u32 {
    let data_bits = 8 * data_len.min(CLASSIC_PAYLOAD) as u32;
    let stuff = if worst_case_stuffing {
        (34 + data_bits - 1) / 4
    } else {
        0
    };
    47 + data_bits + stuff
}
