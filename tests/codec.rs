//! The byte protocol, version 1 (`src/protocol/codec.rs`, `src/protocol/can.rs`): round
//! trips over byte streams and CAN, resynchronisation, corruption never delivered, no panic
//! on any input, no allocation on the hot path, and docs/protocol.md's worked examples and
//! figures equal to what the code produces (a drift fails here).
//!
//! To regenerate the doc's blocks after a deliberate change:
//! `cargo test --test codec print_doc_examples -- --ignored --nocapture`.

use proptest::collection::vec;
use proptest::prelude::*;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rigbridge::protocol::can::{
    CanAssembler, CanMapping, CanPayload, CanSender, OFFSET_TARGET_COMMIT, OFFSET_TARGET_HEADER,
    OFFSET_TARGET_POSITIONS, can_frames, classic_frame_bits,
};
use rigbridge::protocol::codec::{
    DECODER_INPUT_CAPACITY, EncodeError, FaultReport, FrameDecoder, Hello, MAX_BODY_LEN,
    MAX_FRAME_LEN, MAX_TIME_US, Message, cobs_decode, cobs_encode, crc32, decode_body, encode_body,
    encode_frame,
};
use rigbridge::protocol::{
    AxisValues, Command, ControllerStatus, Fault, Feedback, IoKind, IoMessage, IoResult, IoState,
    JointTarget, MAX_AXES,
};
use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::f64::consts::{FRAC_PI_2, PI};
use std::time::Duration;

// ---------------------------------------------------------------------------------------
// Allocation counting, per thread (tests run in parallel).

struct Counting;

thread_local! {
    static ALLOCATIONS: Cell<usize> = const { Cell::new(0) };
}

// SAFETY: forwards to the system allocator unchanged; only counts calls on this thread.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let _ = ALLOCATIONS.try_with(|count| count.set(count.get() + 1));
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let _ = ALLOCATIONS.try_with(|count| count.set(count.get() + 1));
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

fn allocations() -> usize {
    ALLOCATIONS.with(Cell::get)
}

// ---------------------------------------------------------------------------------------
// The worked examples of docs/protocol.md.

const BASE_ID: u16 = 0x100;

fn values(values: &[f64]) -> AxisValues {
    AxisValues::from_slice(values).unwrap()
}

fn whole_urad(value: f64) -> f64 {
    (value * 1e6).round() / 1e6
}

fn target6() -> Message {
    Message::Command(Command::Target(JointTarget {
        seq: 42,
        t: Duration::from_millis(1500),
        // pi/2 and -pi, rounded to whole urad: 1.570796 and -3.141593.
        positions: values(&[0.1, -0.5, 0.25, 0.0, whole_urad(FRAC_PI_2), whole_urad(-PI)]),
        velocities: values(&[0.01, -0.02, 0.0, 0.5, 0.0, -1.0]),
    }))
}

fn feedback6() -> Message {
    Message::Feedback(Feedback {
        seq: 42,
        positions: values(&[0.099512, -0.499007, 0.249875, 0.0, 1.570013, -3.140911]),
        status: ControllerStatus::Ok,
    })
}

fn heartbeat() -> Message {
    Message::Command(Command::Heartbeat)
}

/// The IRB 120's limits (config/irb120.toml), as a controller would announce them.
fn hello6() -> Message {
    let deg = |d: f64| (d.to_radians() * 1e6).round() / 1e6;
    Message::Hello(Hello {
        axis_names: (1..=6).map(|i| format!("joint_{i}")).collect(),
        lower: [-165.0, -110.0, -110.0, -160.0, -120.0, -400.0]
            .map(deg)
            .to_vec(),
        upper: [165.0, 110.0, 70.0, 160.0, 120.0, 400.0].map(deg).to_vec(),
        max_speed: [250.0, 250.0, 250.0, 320.0, 320.0, 420.0].map(deg).to_vec(),
        max_acceleration: [1000.0, 1000.0, 1000.0, 1280.0, 1280.0, 1680.0]
            .map(deg)
            .to_vec(),
        cycle_us: 4000,
        watchdog_cycles: 25,
        answer: true,
        version: 2,
    })
}

fn fault_example() -> Message {
    Message::Fault(FaultReport {
        fault: Fault::OverSpeed { axis: 2 },
        text: "axis 3 step".to_string(),
    })
}

/// docs/protocol.md 4's I/O examples: the gripper closed by request 7, `part_held` read by 8.
fn set_output_example() -> Message {
    Message::Io(IoMessage::SetOutput {
        request: 7,
        name: "gripper".into(),
        value: true,
    })
}

fn io_state_output_example() -> Message {
    Message::Io(IoMessage::State(IoState {
        request: 7,
        kind: IoKind::Output,
        result: IoResult::Done,
        value: true,
        name: "gripper".into(),
    }))
}

fn read_input_example() -> Message {
    Message::Io(IoMessage::ReadInput {
        request: 8,
        name: "part_held".into(),
    })
}

fn io_state_input_example() -> Message {
    Message::Io(IoMessage::State(IoState {
        request: 8,
        kind: IoKind::Input,
        result: IoResult::Done,
        value: true,
        name: "part_held".into(),
    }))
}

fn body(message: &Message) -> Vec<u8> {
    let mut out = Vec::new();
    encode_body(message, &mut out).unwrap();
    out
}

fn frame(message: &Message) -> Vec<u8> {
    let mut out = Vec::new();
    encode_frame(message, &mut out).unwrap();
    out
}

fn sender_of(message: &Message) -> CanSender {
    match message {
        Message::Feedback(_) | Message::Fault(_) | Message::Io(IoMessage::State(_)) => {
            CanSender::Controller
        }
        Message::Hello(_) | Message::Command(_) | Message::Io(_) => CanSender::Bridge,
    }
}

fn can(message: &Message, fd: bool) -> Vec<CanPayload> {
    let mapping = CanMapping::new(BASE_ID, fd, sender_of(message)).unwrap();
    let mut out = Vec::new();
    can_frames(message, &mapping, &mut out).unwrap();
    out
}

fn hex(bytes: &[u8]) -> String {
    bytes
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect::<Vec<_>>()
        .join(" ")
}

/// A frame in candump/cansend syntax: `103#2A00...` classic, `102##0...` FD (no flags).
fn candump(frame: &CanPayload) -> String {
    let data: String = frame.data().iter().map(|b| format!("{b:02X}")).collect();
    if frame.fd {
        format!("{:03X}##0{data}", frame.id)
    } else {
        format!("{:03X}#{data}", frame.id)
    }
}

/// Hex, 16 bytes a line: how the doc shows wire bytes.
fn hex_lines(bytes: &[u8]) -> String {
    bytes.chunks(16).map(hex).collect::<Vec<_>>().join("\n")
}

/// A body as the doc shows it: each field's bytes, then `# what it is`.
fn annotated(message: &Message) -> String {
    let bytes = body(message);
    let mut fields: Vec<(usize, String)> = vec![
        (1, format!("version {}", bytes[0])),
        (
            1,
            format!("type 0x{:02x} {}", bytes[1], type_name(bytes[1])),
        ),
    ];
    let micro = |v: f64| (v * 1e6).round() as i64;
    match message {
        Message::Command(Command::Target(t)) => {
            fields.push((4, format!("seq = {}", t.seq)));
            fields.push((8, format!("t = {} us", t.t.as_micros())));
            fields.push((1, format!("{} axes", t.positions.len())));
            for (i, p) in t.positions.as_slice().iter().enumerate() {
                fields.push((4, format!("position {} = {} urad", i + 1, micro(*p))));
            }
            for (i, v) in t.velocities.as_slice().iter().enumerate() {
                fields.push((4, format!("velocity {} = {} urad/s", i + 1, micro(*v))));
            }
        }
        Message::Feedback(f) => {
            fields.push((4, format!("seq = {} (last accepted target)", f.seq)));
            fields.push((4, "status 0 ok, fault code 0, a 0, b 0".to_string()));
            fields.push((1, format!("{} axes", f.positions.len())));
            for (i, p) in f.positions.as_slice().iter().enumerate() {
                fields.push((4, format!("actual position {} = {} urad", i + 1, micro(*p))));
            }
        }
        Message::Hello(h) => {
            fields.push((1, format!("{} axes", h.axis_names.len())));
            for name in &h.axis_names {
                fields.push((
                    1 + name.len(),
                    format!("name: length {}, {name:?}", name.len()),
                ));
            }
            for i in 0..h.axis_names.len() {
                fields.push((
                    8,
                    format!(
                        "axis {}: lower {}, upper {} urad",
                        i + 1,
                        micro(h.lower[i]),
                        micro(h.upper[i]),
                    ),
                ));
                fields.push((
                    8,
                    format!(
                        "  max speed {} urad/s, max accel {} urad/s2",
                        micro(h.max_speed[i]),
                        micro(h.max_acceleration[i])
                    ),
                ));
            }
            fields.push((4, format!("cycle = {} us", h.cycle_us)));
            fields.push((4, format!("watchdog = {} cycles", h.watchdog_cycles)));
            let flags = if h.answer { "1 (an answer)" } else { "0" };
            fields.push((1, format!("flags = {flags}")));
        }
        Message::Fault(r) => {
            fields.push((3, format!("{}", r.fault)));
            fields.push((
                1 + r.text.len(),
                format!("text: length {}, {:?}", r.text.len(), r.text),
            ));
        }
        Message::Io(io) => {
            fields.push((4, format!("request = {}", io.request())));
            let name = match io {
                IoMessage::SetOutput { value, name, .. } => {
                    fields.push((1, format!("value = {}", u8::from(*value))));
                    name
                }
                IoMessage::ReadInput { name, .. } => name,
                IoMessage::State(state) => {
                    let (kind, result) = (state.kind, state.result);
                    fields.push((1, format!("kind {} ({})", kind as u8, kind.word())));
                    fields.push((1, format!("result {} ({})", result as u8, result.words())));
                    fields.push((1, format!("value = {}", u8::from(state.value))));
                    &state.name
                }
            };
            fields.push((
                1 + name.len(),
                format!("name: length {}, {name:?}", name.len()),
            ));
        }
        Message::Command(_) => {}
    }
    let crc = u32::from_le_bytes(bytes[bytes.len() - 4..].try_into().unwrap());
    fields.push((4, format!("CRC-32 0x{crc:08x}, little-endian")));
    let mut at = 0;
    let mut lines = Vec::new();
    for (len, comment) in fields {
        // Long fields (names) wrap at 16 bytes; the comment goes on the first line.
        for (i, chunk) in bytes[at..at + len].chunks(16).enumerate() {
            let text = hex(chunk);
            lines.push(if i == 0 {
                format!("{text:<36}# {comment}")
            } else {
                text
            });
        }
        at += len;
    }
    assert_eq!(at, bytes.len(), "annotation covers the body");
    lines.join("\n")
}

fn type_name(code: u8) -> &'static str {
    match code {
        0x01 => "Hello",
        0x02 => "Target",
        0x03 => "Stop",
        0x04 => "EStop",
        0x05 => "Heartbeat",
        0x06 => "Feedback",
        0x08 => "Reset",
        0x09 => "SetOutput",
        0x0a => "ReadInput",
        0x0b => "IoState",
        _ => "Fault",
    }
}

fn can_block(message: &Message, fd: bool) -> String {
    can(message, fd)
        .iter()
        .map(candump)
        .collect::<Vec<_>>()
        .join("\n")
}

/// Every block and table the doc carries, generated: (marker name, content).
fn doc_blocks() -> Vec<(&'static str, String)> {
    vec![
        ("target-6-body", annotated(&target6())),
        ("target-6-frame", hex_lines(&frame(&target6()))),
        ("feedback-6-body", annotated(&feedback6())),
        ("feedback-6-frame", hex_lines(&frame(&feedback6()))),
        ("heartbeat-body", annotated(&heartbeat())),
        ("heartbeat-frame", hex_lines(&frame(&heartbeat()))),
        ("hello-6-body", annotated(&hello6())),
        ("hello-6-frame", hex_lines(&frame(&hello6()))),
        ("fault-body", annotated(&fault_example())),
        ("set-output-body", annotated(&set_output_example())),
        ("set-output-frame", hex_lines(&frame(&set_output_example()))),
        (
            "io-state-output-body",
            annotated(&io_state_output_example()),
        ),
        ("read-input-body", annotated(&read_input_example())),
        ("io-state-input-body", annotated(&io_state_input_example())),
        (
            "io-state-input-frame",
            hex_lines(&frame(&io_state_input_example())),
        ),
        ("set-output-can", can_block(&set_output_example(), false)),
        ("target-6-can", can_block(&target6(), false)),
        ("feedback-6-can", can_block(&feedback6(), false)),
        ("target-6-canfd", can_block(&target6(), true)),
        ("feedback-6-canfd", can_block(&feedback6(), true)),
        ("frame-sizes", frame_size_table()),
        ("serial-load", serial_table()),
        ("can-load", can_load_table()),
    ]
}

fn target_n(axes: usize) -> Message {
    Message::Command(Command::Target(JointTarget {
        seq: 1,
        t: Duration::ZERO,
        positions: AxisValues::zeros(axes),
        velocities: AxisValues::zeros(axes),
    }))
}

fn feedback_n(axes: usize) -> Message {
    Message::Feedback(Feedback {
        seq: 1,
        positions: AxisValues::zeros(axes),
        status: ControllerStatus::Ok,
    })
}

fn frame_size_table() -> String {
    let mut rows = vec![
        "| message | body (bytes) | on the wire, COBS + 0x00 (bytes) |".to_string(),
        "|---|---|---|".to_string(),
    ];
    let longest_hello = Message::Hello(Hello {
        axis_names: vec!["x".repeat(32); 32],
        lower: vec![0.0; 32],
        upper: vec![0.0; 32],
        max_speed: vec![0.0; 32],
        max_acceleration: vec![0.0; 32],
        cycle_us: 0,
        watchdog_cycles: 0,
        answer: false,
        version: 2,
    });
    let cases = [
        ("Target, n axes", None),
        ("Target, 6 axes", Some(target6())),
        ("Target, 32 axes", Some(target_n(32))),
        ("Feedback, n axes", None),
        ("Feedback, 6 axes", Some(feedback6())),
        ("Feedback, 32 axes", Some(feedback_n(32))),
        ("Stop, EStop, Heartbeat", Some(heartbeat())),
        ("Hello, 6 axes named joint_1..joint_6", Some(hello6())),
        (
            "Hello, longest (32 axes, 32-byte names)",
            Some(longest_hello),
        ),
    ];
    for (name, message) in cases {
        rows.push(match (name, message) {
            ("Target, n axes", _) => {
                "| Target, n axes | 19 + 8n | 21 + 8n (up to 29 axes; above, COBS may add 1) |"
                    .to_string()
            }
            ("Feedback, n axes", _) => "| Feedback, n axes | 15 + 4n | 17 + 4n |".to_string(),
            (name, Some(message)) => format!(
                "| {name} | {} | {} |",
                body(&message).len(),
                frame(&message).len()
            ),
            _ => unreachable!(),
        });
    }
    rows.join("\n")
}

fn serial_table() -> String {
    let target = frame(&target6()).len() as f64;
    let feedback = frame(&feedback6()).len() as f64;
    let mut rows = vec![
        "| baud (8N1) | bytes/s | bridge -> controller, Target 6 axes at 250 Hz | controller -> bridge, Feedback 6 axes at 250 Hz | highest Target rate at 80 % |".to_string(),
        "|---|---|---|---|---|".to_string(),
    ];
    for baud in [115_200.0, 230_400.0, 460_800.0, 921_600.0] {
        let bytes_per_s: f64 = baud / 10.0;
        rows.push(format!(
            "| {baud} | {bytes_per_s} | {} B/s = {:.1} % | {} B/s = {:.1} % | {:.0} Hz |",
            target * 250.0,
            100.0 * target * 250.0 / bytes_per_s,
            feedback * 250.0,
            100.0 * feedback * 250.0 / bytes_per_s,
            (0.8 * bytes_per_s / target).floor(),
        ));
    }
    rows.join("\n")
}

fn can_load_table() -> String {
    let target = can(&target6(), false);
    let feedback = can(&feedback6(), false);
    let bits = |frames: &[CanPayload], worst: bool| -> u32 {
        frames
            .iter()
            .map(|f| classic_frame_bits(f.data().len(), worst))
            .sum()
    };
    let mut rows = vec![
        "| 6 axes at 250 Hz, classic CAN at 1 Mbit/s | frames per cycle | bits per cycle, no stuffing | bits per cycle, worst-case stuffing | bus load, worst case |".to_string(),
        "|---|---|---|---|---|".to_string(),
    ];
    let both: Vec<CanPayload> = target.iter().chain(&feedback).copied().collect();
    for (name, frames) in [
        ("Target", &target),
        ("Feedback", &feedback),
        ("both directions", &both),
    ] {
        let worst = bits(frames, true);
        rows.push(format!(
            "| {name} | {} | {} | {worst} | {:.1} % |",
            frames.len(),
            bits(frames, false),
            100.0 * f64::from(worst) * 250.0 / 1e6
        ));
    }
    rows.join("\n")
}

/// The content after `<!-- example: NAME -->` (a fenced block) or `<!-- table: NAME -->` (a
/// table, up to the next blank line).
fn doc_section(doc: &str, name: &str) -> Option<String> {
    for marker in [
        format!("<!-- example: {name} -->"),
        format!("<!-- table: {name} -->"),
    ] {
        let Some(at) = doc.find(&marker) else {
            continue;
        };
        let rest = doc[at + marker.len()..].trim_start_matches('\n');
        if marker.contains("example") {
            let rest = rest.strip_prefix("```text\n")?;
            return Some(rest[..rest.find("\n```")?].to_string());
        }
        let end = rest.find("\n\n").unwrap_or(rest.len());
        return Some(rest[..end].to_string());
    }
    None
}

/// What must agree: for hex blocks the bytes (comments after `#` are prose); for CAN blocks
/// the first token of each line; for tables the whole text.
fn normalise(name: &str, text: &str) -> Vec<String> {
    let lines = text.lines().map(str::trim).filter(|l| !l.is_empty());
    if name.ends_with("-can") || name.ends_with("-canfd") {
        lines
            .map(|l| l.split_whitespace().next().unwrap_or("").to_string())
            .collect()
    } else if name.ends_with("-body") || name.ends_with("-frame") {
        lines
            .flat_map(|l| l.split('#').next().unwrap_or("").split_whitespace())
            .map(str::to_lowercase)
            .collect()
    } else {
        lines.map(str::to_string).collect()
    }
}

/// Where `name`'s block lies in `doc` (byte range of its content, as [`doc_section`] reads it).
fn section_range(doc: &str, name: &str) -> Option<std::ops::Range<usize>> {
    let content = doc_section(doc, name)?;
    let at = doc.find(&format!(" {name} -->"))?;
    let start = at + doc[at..].find(&content)?;
    Some(start..start + content.len())
}

/// `doc` with every block replaced by what the code generates, and nothing else changed:
/// the text between the blocks is copied from `doc` as it is.
fn regenerated(doc: &str) -> String {
    let mut blocks: Vec<(std::ops::Range<usize>, String)> = doc_blocks()
        .into_iter()
        .filter_map(|(name, generated)| {
            let range = section_range(doc, name)?;
            let content = if name.ends_with("-body") || name.ends_with("-frame") {
                // Hex blocks keep their prose comments: only tables are rewritten whole.
                doc[range.clone()].to_string()
            } else {
                generated
            };
            Some((range, content))
        })
        .collect();
    blocks.sort_by_key(|(range, _)| range.start);
    let mut out = String::with_capacity(doc.len());
    let mut copied = 0;
    for (range, content) in blocks {
        out.push_str(&doc[copied..range.start]);
        out.push_str(&content);
        copied = range.end;
    }
    out.push_str(&doc[copied..]);
    out
}

/// What a test runner prints, which must never land in the doc (it once did, in section 5).
const RUNNER_OUTPUT: [&str; 5] = [
    "stack backtrace:",
    "panicked at",
    "rust_begin_unwind",
    "RUST_BACKTRACE",
    " stdout ----",
];

/// The doc's tables can be rewritten from the code (`RIGBRIDGE_REGENERATE_DOC=1`): only the
/// blocks change, from the generator's strings, through a file renamed into place; the doc
/// never holds anything a test runner prints.
#[test]
fn doc_tables_regenerate_in_place_and_hold_nothing_else() {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/docs/protocol.md");
    let doc = std::fs::read_to_string(path).expect("docs/protocol.md");
    for mark in RUNNER_OUTPUT {
        assert!(
            !doc.contains(mark),
            "docs/protocol.md holds test output: {mark}"
        );
    }
    let again = regenerated(&doc);
    for (name, _) in doc_blocks() {
        assert!(section_range(&again, name).is_some(), "{name} lost");
    }
    // Regenerating what is already regenerated changes nothing: the blocks are the only
    // thing written.
    assert_eq!(regenerated(&again), again);
    if std::env::var("RIGBRIDGE_REGENERATE_DOC").as_deref() == Ok("1") && again != doc {
        let temporary = format!("{path}.regenerated");
        std::fs::write(&temporary, &again).unwrap();
        std::fs::rename(&temporary, path).unwrap();
    }
}

#[test]
fn doc_examples_and_figures_match_the_code() {
    let doc = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/docs/protocol.md"))
        .expect("docs/protocol.md");
    for mark in RUNNER_OUTPUT {
        assert!(
            !doc.contains(mark),
            "docs/protocol.md holds test output: {mark}"
        );
    }
    let mut drifted = Vec::new();
    for (name, generated) in doc_blocks() {
        let in_doc = doc_section(&doc, name);
        if in_doc.as_deref().map(|d| normalise(name, d)) != Some(normalise(name, &generated)) {
            drifted.push(format!("--- {name}: the code gives\n{generated}\n"));
        }
    }
    assert!(
        drifted.is_empty(),
        "docs/protocol.md has drifted from the encoder:\n{}",
        drifted.join("\n")
    );
}

// ---------------------------------------------------------------------------------------
// Fixed vectors.

#[test]
fn crc32_is_the_ieee_crc_with_its_check_value() {
    assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
    assert_eq!(crc32(b""), 0);
}

#[test]
fn cobs_matches_the_published_examples() {
    // Cheshire and Baker's scheme; these are the examples on Wikipedia's COBS page.
    let long: Vec<u8> = (1..=255).collect();
    let cases: Vec<(Vec<u8>, Vec<u8>)> = vec![
        (vec![0x00], vec![0x01, 0x01]),
        (vec![0x00, 0x00], vec![0x01, 0x01, 0x01]),
        (vec![0x00, 0x11, 0x00], vec![0x01, 0x02, 0x11, 0x01]),
        (
            vec![0x11, 0x22, 0x00, 0x33],
            vec![0x03, 0x11, 0x22, 0x02, 0x33],
        ),
        (
            vec![0x11, 0x22, 0x33, 0x44],
            vec![0x05, 0x11, 0x22, 0x33, 0x44],
        ),
        (
            vec![0x11, 0x00, 0x00, 0x00],
            vec![0x02, 0x11, 0x01, 0x01, 0x01],
        ),
        (long[..254].to_vec(), [&[0xFF][..], &long[..254]].concat()),
        (
            long.clone(),
            [&[0xFF][..], &long[..254], &[0x02, 0xFF]].concat(),
        ),
        (
            [&[0x00][..], &long[..254]].concat(),
            [&[0x01, 0xFF][..], &long[..254]].concat(),
        ),
    ];
    for (data, encoded) in cases {
        let mut out = Vec::new();
        cobs_encode(&data, &mut out);
        assert_eq!(out, encoded, "encoding {data:02x?}");
        let mut back = Vec::new();
        cobs_decode(&encoded, &mut back).unwrap();
        assert_eq!(back, data);
    }
    assert!(cobs_decode(&[0x05, 0x11], &mut Vec::new()).is_err());
}

#[test]
fn bus_bit_counts_follow_the_classic_frame_layout() {
    assert_eq!(classic_frame_bits(8, false), 111);
    assert_eq!(classic_frame_bits(8, true), 135);
    assert_eq!(classic_frame_bits(0, true), 55);
}

// ---------------------------------------------------------------------------------------
// Strategies: values are whole micro-units, so a round trip must be exact.

fn micro() -> impl Strategy<Value = f64> {
    prop_oneof![
        any::<i32>().prop_map(|k| f64::from(k) / 1e6),
        (-4_000_000i32..4_000_000).prop_map(|k| f64::from(k) / 1e6),
        Just(f64::from(i32::MIN) / 1e6),
        Just(f64::from(i32::MAX) / 1e6),
    ]
}

fn time() -> impl Strategy<Value = Duration> {
    prop_oneof![
        (0..MAX_TIME_US).prop_map(Duration::from_micros),
        (0u64..3_600_000_000).prop_map(Duration::from_micros),
        Just(Duration::from_micros(MAX_TIME_US - 1)),
    ]
}

fn target() -> impl Strategy<Value = JointTarget> {
    (0..=MAX_AXES)
        .prop_flat_map(|n| (any::<u32>(), time(), vec(micro(), n), vec(micro(), n)))
        .prop_map(|(seq, t, p, v)| JointTarget {
            seq,
            t,
            positions: values(&p),
            velocities: values(&v),
        })
}

fn fault() -> impl Strategy<Value = Fault> {
    prop_oneof![
        any::<u8>().prop_map(|axis| Fault::OutsideLimits { axis }),
        any::<u8>().prop_map(|axis| Fault::OverSpeed { axis }),
        (any::<u8>(), any::<u8>()).prop_map(|(expected, got)| Fault::AxisCount { expected, got }),
        Just(Fault::EStop),
        any::<u8>().prop_map(|axis| Fault::OverAcceleration { axis }),
    ]
}

fn feedback() -> impl Strategy<Value = Feedback> {
    let status = prop_oneof![
        Just(ControllerStatus::Ok),
        Just(ControllerStatus::Holding),
        fault().prop_map(ControllerStatus::Fault),
    ];
    (any::<u32>(), vec(micro(), 0..=MAX_AXES), status).prop_map(|(seq, p, status)| Feedback {
        seq,
        positions: values(&p),
        status,
    })
}

fn hello() -> impl Strategy<Value = Hello> {
    (0..=MAX_AXES)
        .prop_flat_map(|n| {
            (
                // At most 8 characters of at most 4 bytes: within the 32-byte limit.
                vec("\\PC{0,8}", n),
                vec(micro(), n),
                vec(micro(), n),
                (vec(micro(), n), vec(micro(), n)),
                (any::<u32>(), any::<u32>(), any::<bool>(), 2u8..=3),
            )
        })
        .prop_map(
            |(
                axis_names,
                lower,
                upper,
                (max_speed, max_acceleration),
                (cycle_us, watchdog_cycles, answer, version),
            )| Hello {
                axis_names,
                lower,
                upper,
                max_speed,
                max_acceleration,
                cycle_us,
                watchdog_cycles,
                answer,
                version,
            },
        )
}

fn io_name() -> impl Strategy<Value = String> {
    "[A-Za-z0-9_]{1,32}"
}

fn io_message() -> impl Strategy<Value = IoMessage> {
    prop_oneof![
        (1..=u32::MAX, io_name(), any::<bool>()).prop_map(|(request, name, value)| {
            IoMessage::SetOutput {
                request,
                name,
                value,
            }
        }),
        (1..=u32::MAX, io_name())
            .prop_map(|(request, name)| IoMessage::ReadInput { request, name }),
        (
            1..=u32::MAX,
            io_name(),
            any::<bool>(),
            any::<bool>(),
            0u8..3
        )
            .prop_map(|(request, name, value, input, result)| {
                let result =
                    [IoResult::Done, IoResult::NoSuch, IoResult::Refused][usize::from(result)];
                IoMessage::State(IoState {
                    request,
                    kind: if input { IoKind::Input } else { IoKind::Output },
                    value: value && result == IoResult::Done,
                    result,
                    name,
                })
            }),
    ]
}

fn message() -> impl Strategy<Value = Message> {
    prop_oneof![
        4 => target().prop_map(|t| Message::Command(Command::Target(t))),
        1 => Just(Message::Command(Command::Stop)),
        1 => Just(Message::Command(Command::EStop)),
        1 => Just(Message::Command(Command::Heartbeat)),
        1 => Just(Message::Command(Command::Reset)),
        4 => feedback().prop_map(Message::Feedback),
        1 => (fault(), "\\PC{0,32}").prop_map(|(fault, text)| Message::Fault(FaultReport { fault, text })),
        1 => hello().prop_map(Message::Hello),
        2 => io_message().prop_map(Message::Io),
    ]
}

fn decode_all(decoder: &mut FrameDecoder) -> Vec<Message> {
    std::iter::from_fn(|| decoder.next_message()).collect()
}

fn assemble(assembler: &mut CanAssembler, frames: &[CanPayload]) -> Vec<Message> {
    frames.iter().filter_map(|f| assembler.push(f)).collect()
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(2000))]

    #[test]
    fn messages_round_trip_over_a_byte_stream(messages in vec(message(), 1..8), cuts in vec(1usize..300, 1..40)) {
        let mut wire = Vec::new();
        for message in &messages {
            encode_frame(message, &mut wire).unwrap();
        }
        // Pushed in pieces of arbitrary sizes, read out between pushes.
        let mut decoder = FrameDecoder::new();
        let mut got = Vec::new();
        let mut rest: &[u8] = &wire;
        for cut in cuts.iter().cycle() {
            if rest.is_empty() {
                break;
            }
            let (piece, tail) = rest.split_at((*cut).min(rest.len()));
            decoder.push(piece);
            got.extend(decode_all(&mut decoder));
            rest = tail;
        }
        prop_assert_eq!(&got, &messages);
        let counters = decoder.counters();
        prop_assert_eq!(counters.frames, messages.len() as u64);
        prop_assert_eq!(counters.bytes_discarded, 0);
        for message in &messages {
            let body = body(message);
            prop_assert!(body.len() <= MAX_BODY_LEN);
            prop_assert_eq!(&decode_body(&body).unwrap(), message);
        }
    }

    #[test]
    fn messages_round_trip_over_can(message in message(), fd in any::<bool>()) {
        let mapping = CanMapping::new(BASE_ID, fd, sender_of(&message)).unwrap();
        let mut frames = Vec::new();
        can_frames(&message, &mapping, &mut frames).unwrap();
        for frame in &frames {
            let room = if fd { 64 } else { 8 };
            prop_assert!(usize::from(frame.len) <= room);
            prop_assert!(frame.id >= u32::from(BASE_ID) && frame.id < u32::from(BASE_ID) + 0x80);
        }
        let mut assembler = CanAssembler::new(mapping);
        let got = assemble(&mut assembler, &frames);
        prop_assert_eq!(got, vec![message]);
        let counters = assembler.counters();
        prop_assert_eq!(counters.messages, 1);
        prop_assert_eq!(counters.incomplete + counters.crc_errors + counters.malformed + counters.orphans, 0);
    }

    /// Any one lost classic frame of a Target or Feedback: nothing delivered, and the loss
    /// is counted; the next message comes through.
    #[test]
    fn a_lost_can_frame_is_counted_never_delivered(
        message in prop_oneof![
            target().prop_map(|t| Message::Command(Command::Target(t))),
            feedback().prop_map(Message::Feedback),
        ],
        lose in any::<prop::sample::Index>(),
    ) {
        let mapping = CanMapping::new(BASE_ID, false, sender_of(&message)).unwrap();
        let mut frames = Vec::new();
        can_frames(&message, &mapping, &mut frames).unwrap();
        let lost = lose.index(frames.len());
        let mut kept = frames.clone();
        kept.remove(lost);
        let mut assembler = CanAssembler::new(mapping);
        prop_assert!(assemble(&mut assembler, &kept).is_empty());
        let counters = assembler.counters();
        prop_assert!(counters.incomplete + counters.orphans + counters.crc_errors >= 1 || lost == kept.len(),
            "loss of frame {} not counted: {:?}", lost, counters);
        // The next message, whole, is delivered (and an unfinished one before it counted).
        let got = assemble(&mut assembler, &frames);
        prop_assert_eq!(got, vec![message]);
        prop_assert!(assembler.counters().incomplete + assembler.counters().orphans >= 1);
    }

    /// A single flipped bit anywhere in a body is a CRC error: dropped, counted, and the
    /// next frame decodes.
    #[test]
    fn a_flipped_bit_is_a_counted_crc_error(message in message(), bit in any::<prop::sample::Index>()) {
        let mut corrupt = body(&message);
        let bit = bit.index(corrupt.len() * 8);
        corrupt[bit / 8] ^= 1 << (bit % 8);
        let mut wire = Vec::new();
        cobs_encode(&corrupt, &mut wire);
        wire.push(0);
        encode_frame(&heartbeat(), &mut wire).unwrap();
        let mut decoder = FrameDecoder::new();
        decoder.push(&wire);
        prop_assert_eq!(decode_all(&mut decoder), vec![heartbeat()]);
        prop_assert_eq!(decoder.counters().crc_errors, 1);
    }

    /// Corruption on the wire (bits flipped anywhere, delimiters included): whatever comes
    /// out is one of the messages sent, in order.
    #[test]
    fn wire_corruption_never_delivers_a_wrong_message(
        messages in vec(message(), 1..6),
        flips in vec(any::<prop::sample::Index>(), 1..6),
    ) {
        let mut wire = Vec::new();
        for message in &messages {
            encode_frame(message, &mut wire).unwrap();
        }
        for flip in &flips {
            let bit = flip.index(wire.len() * 8);
            wire[bit / 8] ^= 1 << (bit % 8);
        }
        let mut decoder = FrameDecoder::new();
        decoder.push(&wire);
        let mut remaining = messages.iter();
        for got in decode_all(&mut decoder) {
            prop_assert!(remaining.any(|m| *m == got), "delivered a message that was not sent");
        }
    }

    #[test]
    fn random_bytes_deliver_nothing_and_never_panic(bytes in vec(any::<u8>(), 0..8192), cut in 1usize..2000) {
        let mut decoder = FrameDecoder::new();
        for piece in bytes.chunks(cut) {
            decoder.push(piece);
            prop_assert!(decode_all(&mut decoder).is_empty());
        }
        prop_assert_eq!(decoder.counters().frames, 0);
    }

    /// Random CAN frames on the protocol's IDs: no panic, and nothing that needs a CRC
    /// (a multi-frame Target or Feedback, a Hello, a Fault) comes out.
    #[test]
    fn random_can_frames_deliver_no_checked_message(
        raw in vec((0u32..0x90, 0usize..=64, vec(any::<u8>(), 64), prop::bool::weighted(0.9)), 0..400),
    ) {
        let mapping = CanMapping::new(BASE_ID, false, CanSender::Bridge).unwrap();
        let mut assembler = CanAssembler::new(mapping);
        for (offset, len, data, classic) in raw {
            let mut frame = CanPayload::new(u32::from(BASE_ID) + offset, &data, !classic);
            frame.len = len as u8;
            if let Some(message) = assembler.push(&frame) {
                prop_assert!(matches!(message, Message::Command(Command::Stop | Command::EStop | Command::Heartbeat | Command::Reset)),
                    "{:?}", message);
            }
        }
    }
}

// ---------------------------------------------------------------------------------------
// Streams.

#[test]
fn a_megabyte_stream_of_noise_delivers_nothing() {
    // Zeros made common so the noise splits into many short candidate frames.
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let mut decoder = FrameDecoder::new();
    let mut chunk = vec![0u8; 4096];
    for _ in 0..2048 {
        rng.fill_bytes(&mut chunk);
        for byte in &mut chunk {
            if *byte < 24 {
                *byte = 0;
            }
        }
        decoder.push(&chunk);
        assert!(decode_all(&mut decoder).is_empty());
    }
    let counters = decoder.counters();
    assert_eq!(counters.frames, 0);
    assert!(
        counters.crc_errors + counters.malformed > 100_000,
        "{counters:?}"
    );
}

#[test]
fn garbage_between_frames_costs_at_most_the_frame_it_runs_into() {
    let mut wire = frame(&target6());
    wire.extend_from_slice(&[0x13, 0x37, 0xFF, 0x42, 0x01]);
    wire.extend(frame(&feedback6()));
    wire.extend(frame(&heartbeat()));
    wire.extend_from_slice(&[0x55, 0x00, 0x66, 0x00, 0xAA, 0xBB]);
    wire.extend(frame(&hello6()));
    let mut decoder = FrameDecoder::new();
    decoder.push(&wire);
    // The garbage without a 0x00 joins the Feedback's frame (which is lost); garbage with
    // 0x00 ends itself; the leftover AA BB joins the Hello's frame.
    assert_eq!(decode_all(&mut decoder), vec![target6(), heartbeat()]);
    let counters = decoder.counters();
    assert_eq!(counters.frames, 2);
    assert_eq!(counters.crc_errors + counters.malformed, 4);

    // A sender that leads with 0x00 (as it must when it opens the link) loses nothing.
    let mut decoder = FrameDecoder::new();
    decoder.push(&[0x13, 0x37, 0xFF]);
    decoder.push(&[0x00]);
    decoder.push(&frame(&feedback6()));
    assert_eq!(decode_all(&mut decoder), vec![feedback6()]);
}

#[test]
fn a_frame_split_into_single_bytes_arrives_once() {
    let wire = frame(&hello6());
    let mut decoder = FrameDecoder::new();
    let mut got = Vec::new();
    for byte in &wire {
        decoder.push(std::slice::from_ref(byte));
        got.extend(decode_all(&mut decoder));
    }
    assert_eq!(got, vec![hello6()]);
}

#[test]
fn an_endless_frame_is_dropped_and_memory_stays_bounded() {
    let mut decoder = FrameDecoder::new();
    for _ in 0..1000 {
        decoder.push(&[0x07; 1000]);
        assert!(decode_all(&mut decoder).is_empty());
    }
    decoder.push(&[0x00]);
    decoder.push(&frame(&target6()));
    assert_eq!(decode_all(&mut decoder), vec![target6()]);
    let counters = decoder.counters();
    assert_eq!(counters.oversized, 1);
    assert_eq!(counters.bytes_discarded, 1_000_000);
    const { assert!(MAX_FRAME_LEN < 2048) };
}

#[test]
fn unread_input_past_the_capacity_is_an_overrun_then_decoding_resumes() {
    let one = frame(&target6());
    let mut wire = Vec::new();
    while wire.len() < 2 * DECODER_INPUT_CAPACITY {
        wire.extend_from_slice(&one);
    }
    let mut decoder = FrameDecoder::new();
    decoder.push(&wire); // without reading: the oldest half is dropped
    let got = decode_all(&mut decoder);
    assert!(got.iter().all(|m| *m == target6()));
    let counters = decoder.counters();
    assert_eq!(counters.overruns, 1);
    // All but the frame cut by the overrun come through.
    let kept = DECODER_INPUT_CAPACITY / one.len();
    assert!(got.len() >= kept - 1, "{} of {kept}", got.len());
    assert_eq!(counters.crc_errors + counters.malformed, 0);
}

#[test]
fn another_version_with_a_good_crc_is_counted_as_such() {
    // A version 1 frame (the version before this one), with a good CRC.
    let mut body = body(&heartbeat());
    body[0] = 1;
    let crc = crc32(&body[..body.len() - 4]);
    let n = body.len();
    body[n - 4..].copy_from_slice(&crc.to_le_bytes());
    let mut wire = Vec::new();
    cobs_encode(&body, &mut wire);
    wire.push(0);
    let mut decoder = FrameDecoder::new();
    decoder.push(&wire);
    assert!(decode_all(&mut decoder).is_empty());
    assert_eq!(decoder.counters().unsupported_version, 1);
    assert_eq!(decoder.counters().crc_errors, 0);
}

#[test]
fn trailing_bytes_and_bad_fields_are_malformed() {
    let tampers: [fn(&mut Vec<u8>); 4] = [
        |b| b.push(0),    // a byte after the payload
        |b| b[1] = 0x7F,  // unknown type
        |b| b[14] = 33,   // 33 axes
        |b| b[13] = 0xFF, // t >= 2^48 us
    ];
    for tamper in tampers {
        let mut covered = body(&target6());
        covered.truncate(covered.len() - 4);
        tamper(&mut covered);
        let crc = crc32(&covered);
        covered.extend_from_slice(&crc.to_le_bytes());
        assert!(matches!(
            decode_body(&covered),
            Err(rigbridge::protocol::DecodeError::Malformed(_))
        ));
    }
}

// ---------------------------------------------------------------------------------------
// Encoding errors: out of range is refused, never saturated; nothing half-written.

fn target_with(position: f64, velocity: f64, t: Duration) -> Message {
    Message::Command(Command::Target(JointTarget {
        seq: 1,
        t,
        positions: values(&[0.0, position]),
        velocities: values(&[0.0, velocity]),
    }))
}

#[test]
fn values_outside_the_wire_range_are_errors() {
    let refused = [
        target_with(2147.483648, 0.0, Duration::ZERO),
        target_with(-2147.4836485, 0.0, Duration::ZERO),
        target_with(f64::NAN, 0.0, Duration::ZERO),
        target_with(0.0, f64::INFINITY, Duration::ZERO),
        target_with(0.0, -3000.0, Duration::ZERO),
        // A negative or NaN time is no longer a value: `t` is a Duration.
        target_with(0.0, 0.0, Duration::from_micros(MAX_TIME_US)),
    ];
    for message in &refused {
        let mut out = vec![0xAB];
        let error = encode_frame(message, &mut out).unwrap_err();
        assert!(matches!(error, EncodeError::OutOfRange { .. }), "{error}");
        assert_eq!(out, [0xAB], "nothing appended");
        assert!(encode_body(message, &mut out).is_err());
        let mapping = CanMapping::new(BASE_ID, false, CanSender::Bridge).unwrap();
        let mut frames = Vec::new();
        assert!(can_frames(message, &mapping, &mut frames).is_err());
        assert!(frames.is_empty());
    }
    // The extremes themselves fit.
    for message in [
        target_with(2147.483647, -2147.483648, Duration::ZERO),
        target_with(0.0, 0.0, Duration::from_micros(MAX_TIME_US - 1)),
    ] {
        assert_eq!(decode_body(&body(&message)).unwrap(), message);
    }
}

#[test]
fn malformed_messages_are_refused_before_encoding() {
    let mismatched = Message::Command(Command::Target(JointTarget {
        seq: 1,
        t: Duration::ZERO,
        positions: AxisValues::zeros(3),
        velocities: AxisValues::zeros(2),
    }));
    assert!(matches!(
        encode_frame(&mismatched, &mut Vec::new()),
        Err(EncodeError::AxisMismatch { .. })
    ));
    let Message::Hello(mut hello) = hello6() else {
        unreachable!()
    };
    hello.axis_names[0] = "a".repeat(33);
    assert!(matches!(
        encode_frame(&Message::Hello(hello.clone()), &mut Vec::new()),
        Err(EncodeError::NameTooLong { .. })
    ));
    hello.axis_names[0] = "joint_1".into();
    hello.lower.pop();
    assert!(matches!(
        encode_frame(&Message::Hello(hello), &mut Vec::new()),
        Err(EncodeError::HelloLengths { .. })
    ));
    let long_text = Message::Fault(FaultReport {
        fault: Fault::EStop,
        text: "x".repeat(129),
    });
    assert!(matches!(
        encode_frame(&long_text, &mut Vec::new()),
        Err(EncodeError::TextTooLong { .. })
    ));
    let controller = CanMapping::new(BASE_ID, false, CanSender::Controller).unwrap();
    assert!(matches!(
        can_frames(&target6(), &controller, &mut Vec::new()),
        Err(EncodeError::WrongSender { .. })
    ));
    assert!(CanMapping::new(0x781, false, CanSender::Bridge).is_err());
}

// ---------------------------------------------------------------------------------------
// CAN reassembly.

#[test]
fn two_targets_mixed_by_a_lost_header_are_a_crc_error() {
    let mapping = CanMapping::new(BASE_ID, false, CanSender::Bridge).unwrap();
    let first = can(&target6(), false);
    let Message::Command(Command::Target(mut next)) = target6() else {
        unreachable!()
    };
    next.seq = 43;
    next.positions.as_mut_slice()[0] = 0.2;
    let second = can(&Message::Command(Command::Target(next)), false);
    // First: header and positions, its velocities and commit lost. Second: header lost,
    // the rest arrives and lands in the first's slots.
    let mut frames: Vec<CanPayload> = first
        .iter()
        .filter(|f| f.id <= u32::from(BASE_ID + OFFSET_TARGET_POSITIONS + 2))
        .copied()
        .collect();
    frames.extend(second.iter().skip(1));
    let mut assembler = CanAssembler::new(mapping);
    assert!(assemble(&mut assembler, &frames).is_empty());
    assert_eq!(assembler.counters().crc_errors, 1);
    // And whole messages still come through afterwards.
    assert_eq!(assemble(&mut assembler, &first), vec![target6()]);
}

#[test]
fn frames_after_a_commit_or_without_a_header_are_orphans() {
    let mapping = CanMapping::new(BASE_ID, false, CanSender::Bridge).unwrap();
    let frames = can(&target6(), false);
    let mut assembler = CanAssembler::new(mapping);
    let without_header: Vec<_> = frames
        .iter()
        .filter(|f| f.id != u32::from(BASE_ID + OFFSET_TARGET_HEADER))
        .copied()
        .collect();
    assert!(assemble(&mut assembler, &without_header).is_empty());
    assert_eq!(
        assembler.counters().orphans,
        without_header.len() as u64,
        "{:?}",
        assembler.counters()
    );
    let mut foreign = frames[0];
    foreign.id = 0x7FF;
    assert!(assembler.push(&foreign).is_none());
    assert_eq!(assembler.counters().foreign, 1);
    let mut wrong_kind = frames[0];
    wrong_kind.fd = true;
    assert!(assembler.push(&wrong_kind).is_none());
    assert_eq!(assembler.counters().malformed, 1);
    let commit = frames
        .iter()
        .find(|f| f.id == u32::from(BASE_ID + OFFSET_TARGET_COMMIT))
        .unwrap();
    assert!(assembler.push(commit).is_none());
}

#[test]
fn hello_and_fault_segments_survive_only_whole() {
    for fd in [false, true] {
        for message in [hello6(), fault_example()] {
            let mapping = CanMapping::new(BASE_ID, fd, sender_of(&message)).unwrap();
            let frames = can(&message, fd);
            let mut assembler = CanAssembler::new(mapping);
            if frames.len() > 1 {
                let mut gap = frames.clone();
                gap.remove(1);
                assert!(assemble(&mut assembler, &gap).is_empty());
                assert!(assembler.counters().incomplete + assembler.counters().orphans >= 1);
            }
            assert_eq!(assemble(&mut assembler, &frames), vec![message.clone()]);
        }
    }
    // A controller's Hello has its own ID, so both Hellos can be in flight at once.
    let bridge = can(&hello6(), false);
    let mapping = CanMapping::new(BASE_ID, false, CanSender::Controller).unwrap();
    let mut controller = Vec::new();
    can_frames(&hello6(), &mapping, &mut controller).unwrap();
    assert_ne!(bridge[0].id, controller[0].id);
    let interleaved: Vec<_> = bridge
        .iter()
        .zip(&controller)
        .flat_map(|(a, b)| [*a, *b])
        .collect();
    let mut assembler = CanAssembler::new(mapping);
    assert_eq!(
        assemble(&mut assembler, &interleaved),
        vec![hello6(), hello6()]
    );
}

#[test]
fn the_longest_hello_fits_every_transport() {
    let longest = Message::Hello(Hello {
        axis_names: vec!["ü".repeat(16); MAX_AXES],
        lower: vec![-1.0; MAX_AXES],
        upper: vec![1.0; MAX_AXES],
        max_speed: vec![2.0; MAX_AXES],
        max_acceleration: vec![20.0; MAX_AXES],
        cycle_us: 1000,
        watchdog_cycles: 3,
        answer: true,
        version: 2,
    });
    assert_eq!(body(&longest).len(), 1584);
    assert!(body(&longest).len() <= MAX_BODY_LEN);
    for fd in [false, true] {
        let frames = can(&longest, fd);
        let mapping = CanMapping::new(BASE_ID, fd, CanSender::Bridge).unwrap();
        assert_eq!(
            assemble(&mut CanAssembler::new(mapping), &frames),
            vec![longest.clone()]
        );
    }
}

// ---------------------------------------------------------------------------------------
// The hot path allocates nothing once buffers are warm.

#[test]
fn targets_and_feedback_encode_and_decode_without_allocating() {
    let mut decoder = FrameDecoder::new();
    let mut wire = Vec::with_capacity(4096);
    let bridge = CanMapping::new(BASE_ID, false, CanSender::Bridge).unwrap();
    let controller = CanMapping::new(BASE_ID, false, CanSender::Controller).unwrap();
    let mut frames = Vec::with_capacity(64);
    let mut assembler = CanAssembler::new(bridge);
    let (target, feedback) = (target6(), feedback6());
    let before = allocations();
    let mut delivered = 0;
    for _ in 0..1000 {
        wire.clear();
        encode_frame(&target, &mut wire).unwrap();
        encode_frame(&feedback, &mut wire).unwrap();
        decoder.push(&wire);
        while let Some(message) = decoder.next_message() {
            delivered += usize::from(message == target || message == feedback);
        }
        frames.clear();
        can_frames(&target, &bridge, &mut frames).unwrap();
        can_frames(&feedback, &controller, &mut frames).unwrap();
        for frame in &frames {
            delivered += usize::from(assembler.push(frame).is_some());
        }
    }
    assert_eq!(allocations() - before, 0);
    assert_eq!(delivered, 4000);
}

/// Issue 19: a Hello's `cycle_us` is the period in whole microseconds, rounded to the
/// nearest, as `(period_s * 1e6).round()` gave it before periods were `Duration`s.
#[test]
fn a_hello_cycle_is_the_period_in_whole_microseconds() {
    use rigbridge::protocol::cycle_us;
    use std::time::Duration;
    assert_eq!(cycle_us(Duration::from_millis(4)), 4000);
    assert_eq!(cycle_us(Duration::from_millis(10)), 10_000);
    assert_eq!(cycle_us(Duration::from_nanos(1_499)), 1);
    assert_eq!(cycle_us(Duration::from_nanos(1_500)), 2);
    for rate_hz in [1.0, 7.0, 100.0, 250.0, 300.0, 333.0, 1000.0] {
        let period_s: f64 = 1.0 / rate_hz;
        assert_eq!(
            cycle_us(Duration::from_secs_f64(period_s)),
            (period_s * 1e6).round() as u32,
            "{rate_hz} Hz"
        );
    }
    assert_eq!(cycle_us(Duration::MAX), u32::MAX);
}

/// A body of `version`, `kind` and `payload` with its good CRC.
fn body_with_crc(version: u8, kind: u8, payload: &[u8]) -> Vec<u8> {
    let mut body = vec![version, kind];
    body.extend_from_slice(payload);
    let crc = crc32(&body);
    body.extend_from_slice(&crc.to_le_bytes());
    body
}

#[test]
fn io_messages_are_strict_on_the_wire_and_refused_by_the_encoder() {
    // The SetOutput of section 4 decodes; the same bytes in a version 2 frame do not.
    let payload = [7, 0, 0, 0, 1, 7, b'g', b'r', b'i', b'p', b'p', b'e', b'r'];
    assert_eq!(
        decode_body(&body_with_crc(3, 0x09, &payload)),
        Ok(set_output_example())
    );
    let malformed = |version: u8, kind: u8, payload: &[u8]| {
        matches!(
            decode_body(&body_with_crc(version, kind, payload)),
            Err(rigbridge::protocol::DecodeError::Malformed(_))
        )
    };
    assert!(malformed(2, 0x09, &payload), "an I/O message in a v2 frame");
    // Value 2, request 0, a name with `-`, an empty name, a name of 33 bytes.
    assert!(malformed(3, 0x09, &[7, 0, 0, 0, 2, 1, b'g']));
    assert!(malformed(3, 0x09, &[0, 0, 0, 0, 1, 1, b'g']));
    assert!(malformed(3, 0x0A, &[8, 0, 0, 0, 3, b'a', b'-', b'b']));
    assert!(malformed(3, 0x0A, &[8, 0, 0, 0, 0]));
    let mut long = vec![8, 0, 0, 0, 33];
    long.extend_from_slice(&[b'x'; 33]);
    assert!(malformed(3, 0x0A, &long));
    // IoState: kind 2 and result 3 are unknown.
    assert!(malformed(3, 0x0B, &[8, 0, 0, 0, 2, 0, 1, 1, b'x']));
    assert!(malformed(3, 0x0B, &[8, 0, 0, 0, 1, 3, 1, 1, b'x']));
    // Version 4 is another version, counted apart.
    assert!(matches!(
        decode_body(&body_with_crc(4, 0x09, &payload)),
        Err(rigbridge::protocol::DecodeError::UnsupportedVersion(4))
    ));
    // The encoder writes no name the wire refuses, and no request 0.
    let mut out = Vec::new();
    let bad_name = Message::Io(IoMessage::ReadInput {
        request: 1,
        name: "a-b".into(),
    });
    assert!(matches!(
        encode_frame(&bad_name, &mut out),
        Err(EncodeError::IoName { .. })
    ));
    let request_zero = Message::Io(IoMessage::ReadInput {
        request: 0,
        name: "ab".into(),
    });
    assert_eq!(
        encode_frame(&request_zero, &mut out),
        Err(EncodeError::IoRequestZero)
    );
    assert!(out.is_empty(), "nothing written for a refused message");
}
