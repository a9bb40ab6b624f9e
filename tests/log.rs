//! Run logs end to end: recording, reading back bit for bit, the MCAP crate's own reader on
//! our files, truncated / damaged / random files (never a panic, never silently wrong data),
//! a real SIGKILL mid-run, and the recorder dropping instead of blocking.

use crate::common;

use rigbridge::log::{
    LogError, LogRecord, Recorder, RecorderOptions, RunLog, command_topic, read_log, read_log_from,
    state_topic, summarize,
};
use rigbridge::protocol::AxisValues;
use rigbridge::rig::{JointKind, load_rig};
use rigbridge::trajectory::RecordedError;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

const PERIOD: f64 = 0.004;
const JOINTS: usize = 6;

fn temp_path(name: &str) -> PathBuf {
    let path = std::env::temp_dir().join(format!(
        "rigbridge-log-test-{}-{name}.mcap",
        std::process::id()
    ));
    let _ = std::fs::remove_file(&path);
    path
}

fn joint_names() -> Vec<String> {
    (1..=JOINTS).map(|i| format!("joint_{i}")).collect()
}

/// Deterministic cycle `i`: smooth commands, a state that lags them a little.
fn cycle(i: u32) -> (LogRecord, LogRecord) {
    let t = f64::from(i) * PERIOD;
    let mut q = [0.0; JOINTS];
    let mut v = [0.0; JOINTS];
    let mut measured = [0.0; JOINTS];
    for j in 0..JOINTS {
        let w = 0.7 + 0.31 * j as f64;
        let phase = 0.1 * j as f64 + std::f64::consts::FRAC_1_SQRT_2;
        q[j] = 0.9 * (w * t + phase).sin();
        v[j] = 0.9 * w * (w * t + phase).cos();
        measured[j] = 0.9 * (w * (t - 0.003) + phase).sin() + 1e-5 * (j as f64 - 2.5);
    }
    let axes = |values: &[f64]| AxisValues::from_slice(values).unwrap();
    let command = LogRecord::Command {
        seq: i,
        t,
        positions: axes(&q),
        velocities: axes(&v),
        late_us: 0.0,
    };
    let state = LogRecord::State {
        seq: i,
        t,
        positions: axes(&measured),
        velocities: axes(&v),
    };
    (command, state)
}

fn metadata() -> serde_json::Value {
    serde_json::json!({
        "job": { "name": "wall_line", "waypoints": 12 },
        "config": { "period_s": PERIOD, "link": "loopback", "nested": [1, 2.5, null, "x"] },
        "operator": "test",
    })
}

struct Recorded {
    path: PathBuf,
    bytes: Vec<u8>,
    commands: Vec<LogRecord>,
    states: Vec<LogRecord>,
}

/// Records `cycles` cycles with a job_started / pause / resume / job_ended event each.
fn record_run(name: &str, cycles: u32, options: RecorderOptions) -> Recorded {
    let path = temp_path(name);
    let recorder =
        Recorder::create_with(&path, "arm6", &joint_names(), metadata(), options).unwrap();
    recorder.event(
        0.0,
        "job_started",
        serde_json::json!({ "job": "wall_line" }),
    );
    let (mut commands, mut states) = (Vec::new(), Vec::new());
    for i in 0..cycles {
        let (command, state) = cycle(i);
        recorder.record(command);
        recorder.record(state);
        commands.push(command);
        states.push(state);
        if i == cycles / 2 {
            let t = f64::from(i) * PERIOD;
            recorder.event(t, "pause", serde_json::json!({ "by": "operator" }));
            recorder.event(t, "resume", serde_json::Value::Null);
        }
        if i % 64 == 63 {
            // Let the writer keep up, as a real 250 Hz cycle would.
            std::thread::sleep(Duration::from_micros(200));
        }
    }
    let end = f64::from(cycles) * PERIOD;
    recorder.event(end, "job_ended", serde_json::json!({ "status": "ok" }));
    let stats = recorder.finish().unwrap();
    assert_eq!(stats.dropped, 0);
    assert_eq!(stats.commands, u64::from(cycles));
    assert_eq!(stats.states, u64::from(cycles));
    assert_eq!(stats.events, 4);
    let bytes = std::fs::read(&path).unwrap();
    assert_eq!(stats.bytes, bytes.len() as u64);
    Recorded {
        path,
        bytes,
        commands,
        states,
    }
}

fn fields(record: &LogRecord) -> (u32, f64, &[f64], &[f64]) {
    match record {
        LogRecord::Command {
            seq,
            t,
            positions,
            velocities,
            ..
        }
        | LogRecord::State {
            seq,
            t,
            positions,
            velocities,
            ..
        } => (*seq, *t, positions.as_slice(), velocities.as_slice()),
    }
}

/// `read` holds the first `read.len()` of `recorded`, bit for bit.
fn assert_prefix(read: &[rigbridge::log::LoggedSample], recorded: &[LogRecord]) {
    assert!(read.len() <= recorded.len());
    for (sample, record) in read.iter().zip(recorded) {
        let (seq, t, positions, velocities) = fields(record);
        assert_eq!(sample.seq, seq);
        assert_eq!(sample.t.to_bits(), t.to_bits(), "t of seq {seq}");
        assert_eq!(sample.positions, positions, "positions of seq {seq}");
        assert_eq!(sample.velocities, velocities, "velocities of seq {seq}");
    }
}

#[test]
fn a_recorded_run_reads_back_bit_for_bit() {
    let run = record_run("round-trip", 2000, RecorderOptions::default());
    let log = read_log(&run.path).unwrap();
    assert_eq!(log.rig, "arm6");
    assert_eq!(log.joint_names, joint_names());
    assert_eq!(log.joint_kinds, None);
    assert_eq!(log.metadata, metadata());
    assert!(!log.truncated);
    assert_eq!(log.stopped, None);
    assert_eq!(log.commands.len(), 2000);
    assert_eq!(log.states.len(), 2000);
    assert_prefix(&log.commands, &run.commands);
    assert_prefix(&log.states, &run.states);
    let kinds: Vec<&str> = log.events.iter().map(|e| e.kind.as_str()).collect();
    assert_eq!(kinds, ["job_started", "pause", "resume", "job_ended"]);
    assert_eq!(log.events[3].t, 2000.0 * PERIOD);
    assert_eq!(
        log.events[1].detail,
        serde_json::json!({ "by": "operator" })
    );
    assert_eq!(log.other_messages, 0);
    let _ = std::fs::remove_file(&run.path);
}

#[test]
fn a_complete_file_is_valid_mcap_to_the_mcap_crate() {
    let run = record_run("mcap-crate", 500, RecorderOptions::default());
    let mut per_topic: BTreeMap<String, usize> = BTreeMap::new();
    let mut last_time: BTreeMap<String, u64> = BTreeMap::new();
    for message in mcap::MessageStream::new(&run.bytes).unwrap() {
        let message = message.unwrap();
        assert_eq!(message.channel.message_encoding, "json");
        let schema = message.channel.schema.as_ref().unwrap();
        assert_eq!(schema.encoding, "jsonschema");
        let json: serde_json::Value = serde_json::from_slice(&message.data).unwrap();
        assert_eq!(message.log_time, message.publish_time);
        assert_eq!(
            message.log_time,
            (json["t"].as_f64().unwrap() * 1e9).round() as u64
        );
        last_time.insert(message.channel.topic.clone(), message.log_time);
        *per_topic.entry(message.channel.topic.clone()).or_default() += 1;
    }
    assert_eq!(per_topic.get(&command_topic("arm6")), Some(&500));
    assert_eq!(per_topic.get(&state_topic("arm6")), Some(&500));
    assert_eq!(per_topic.get("/rigbridge/events"), Some(&4));
    assert_eq!(last_time.get(&command_topic("arm6")), Some(&1_996_000_000));

    let summary = mcap::Summary::read(&run.bytes).unwrap().unwrap();
    let stats = summary.stats.as_ref().unwrap();
    assert_eq!(stats.message_count, 1004);
    assert_eq!(stats.channel_count, 3);
    assert!(stats.chunk_count >= 2);
    let index = summary
        .metadata_indexes
        .iter()
        .find(|index| index.name == "rigbridge")
        .unwrap();
    let record = mcap::read::metadata(&run.bytes, index).unwrap();
    assert_eq!(record.metadata["rig"], "arm6");
    let names: Vec<String> = serde_json::from_str(&record.metadata["joint_names"]).unwrap();
    assert_eq!(names, joint_names());
    let stored: serde_json::Value = serde_json::from_str(&record.metadata["metadata"]).unwrap();
    assert_eq!(stored, metadata());
    let command = summary
        .channels
        .values()
        .find(|c| c.topic == command_topic("arm6"))
        .unwrap();
    assert_eq!(command.metadata["rig"], "arm6");
    let _ = std::fs::remove_file(&run.path);
}

#[test]
fn commands_replay_as_a_trajectory_and_summarize() {
    let rig = load_rig(&Path::new(env!("CARGO_MANIFEST_DIR")).join("config/irb120.toml")).unwrap();
    let names: Vec<String> = rig.joint_names().map(str::to_owned).collect();
    let path = temp_path("replay");
    let recorder = Recorder::for_rig(&path, &rig, serde_json::json!({})).unwrap();
    for i in 0..250u32 {
        let (command, state) = cycle(i);
        recorder.record(command);
        recorder.record(state);
    }
    recorder.finish().unwrap();
    let log = read_log(&path).unwrap();
    assert_eq!(log.joint_names, names);
    assert_eq!(log.joint_kinds, Some(vec![JointKind::Revolute; 6]));

    let trajectory = log
        .to_trajectory(std::time::Duration::from_secs_f64(PERIOD))
        .unwrap();
    assert_eq!(trajectory.len(), 250);
    assert_eq!(
        trajectory.position(100),
        log.commands[100].positions.as_slice()
    );
    // The recorded motion is within the limits; the log ends mid-motion, which replay
    // brings to rest with a ramp before it streams (`validate` alone refuses that end).
    rigbridge::trajectory::validate_motion(&trajectory, &rig).unwrap();
    assert!(matches!(
        rigbridge::trajectory::validate(&trajectory, &rig),
        Err(rigbridge::trajectory::TrajectoryError::EndsMoving { .. })
    ));
    let wrong_period = log.to_trajectory(std::time::Duration::from_millis(1));
    assert!(
        matches!(wrong_period, Err(RecordedError::Uneven { index: 1, .. })),
        "{wrong_period:?}"
    );

    let summary = summarize(&log);
    assert_eq!(summary.commands.count, 250);
    assert_eq!(summary.commands.gap_count, 0);
    assert_eq!(summary.tracking_pairs, 250);
    assert_eq!(summary.tracking[0].unit, "deg");
    let expected = log
        .commands
        .iter()
        .zip(&log.states)
        .map(|(c, s)| (c.positions[0] - s.positions[0]).abs().to_degrees())
        .fold(0.0, f64::max);
    assert_eq!(summary.tracking[0].max_abs, expected);
    assert!((summary.duration_s - 249.0 * PERIOD).abs() < 1e-12);
    println!("{summary}");
    let _ = std::fs::remove_file(&path);
}

#[test]
fn cut_files_read_up_to_the_cut_and_never_panic() {
    let options = RecorderOptions {
        chunk_bytes: 16 * 1024,
        ..RecorderOptions::default()
    };
    let run = record_run("cuts", 2000, options);
    let full = run.bytes.len();
    let data_end = data_section_end(&run.bytes);
    let mut previous = 0;
    let mut cuts: Vec<usize> = (0..4096.min(full)).collect();
    cuts.extend((4096..full).step_by(4099));
    cuts.push(full - 1);
    for cut in cuts {
        match read_log_from(&run.bytes[..cut]) {
            Ok(log) if cut >= data_end => {
                // Only the summary and footer are missing: the data is all there.
                assert!(!log.truncated, "cut at {cut} after the data section");
                assert_eq!(log.commands.len(), 2000);
            }
            Ok(log) => {
                assert!(log.truncated, "cut at {cut} of {full} reads as complete");
                assert!(log.stopped.as_ref().unwrap().offset <= cut as u64);
                assert_prefix(&log.commands, &run.commands);
                assert_prefix(&log.states, &run.states);
                let read = log.commands.len() + log.states.len();
                assert!(read >= previous, "cut at {cut} read {read} < {previous}");
                previous = read;
            }
            Err(error) => assert!(cut < 2048, "cut at {cut}: {error}"),
        }
    }
    assert!(
        previous > 3000,
        "only {previous} of 4000 samples before the last cut"
    );
    let _ = std::fs::remove_file(&run.path);
}

/// Top-level records of an MCAP file: (opcode, start offset, end offset).
fn top_level_records(bytes: &[u8]) -> Vec<(u8, usize, usize)> {
    let mut records = Vec::new();
    let mut pos = 8;
    while pos + 9 <= bytes.len() {
        let len = u64::from_le_bytes(bytes[pos + 1..pos + 9].try_into().unwrap()) as usize;
        let end = pos + 9 + len;
        if end > bytes.len() {
            break;
        }
        records.push((bytes[pos], pos, end));
        pos = end;
    }
    records
}

/// Where the Data End record ends: cutting after it loses only the summary and footer.
fn data_section_end(bytes: &[u8]) -> usize {
    top_level_records(bytes)
        .into_iter()
        .find(|(opcode, _, _)| *opcode == mcap::records::op::DATA_END)
        .map(|(_, _, end)| end)
        .unwrap()
}

/// Messages the mcap crate finds in the complete chunks of `bytes`.
fn messages_in_complete_chunks(bytes: &[u8]) -> usize {
    let mut count = 0;
    for (opcode, start, end) in top_level_records(bytes) {
        if opcode != mcap::records::op::CHUNK {
            continue;
        }
        let Ok(mcap::records::Record::Chunk { header, data }) =
            mcap::parse_record(opcode, &bytes[start + 9..end])
        else {
            panic!("chunk at {start} does not parse");
        };
        for record in mcap::read::ChunkReader::new(header, &data).unwrap() {
            if matches!(record.unwrap(), mcap::records::Record::Message { .. }) {
                count += 1;
            }
        }
    }
    count
}

#[test]
fn a_file_cut_after_a_few_chunks_keeps_every_message_of_those_chunks() {
    let options = RecorderOptions {
        chunk_bytes: 16 * 1024,
        ..RecorderOptions::default()
    };
    let run = record_run("few-chunks", 2000, options);
    let chunks: Vec<(u8, usize, usize)> = top_level_records(&run.bytes)
        .into_iter()
        .filter(|(opcode, _, _)| *opcode == mcap::records::op::CHUNK)
        .collect();
    assert!(chunks.len() > 10, "{} chunks", chunks.len());
    // Cut inside the fifth chunk: four complete ones (schemas and channels, then data).
    let (_, fifth_start, fifth_end) = chunks[4];
    let cut = (fifth_start + fifth_end) / 2;
    let expected = messages_in_complete_chunks(&run.bytes[..cut]);
    assert!(expected > 0);
    let log = read_log_from(&run.bytes[..cut]).unwrap();
    assert!(log.truncated);
    let stop = log.stopped.as_ref().unwrap();
    assert_eq!(stop.offset, fifth_start as u64);
    assert!(stop.reason.contains("cut"), "{}", stop.reason);
    assert_eq!(
        log.commands.len() + log.states.len() + log.events.len(),
        expected
    );
    assert_prefix(&log.commands, &run.commands);
    assert_prefix(&log.states, &run.states);
    let _ = std::fs::remove_file(&run.path);
}

fn small_run(name: &str) -> Recorded {
    let options = RecorderOptions {
        chunk_bytes: 2048,
        ..RecorderOptions::default()
    };
    record_run(name, 12, options)
}

fn same_data(a: &RunLog, b: &RunLog) -> bool {
    a.rig == b.rig
        && a.joint_names == b.joint_names
        && a.metadata == b.metadata
        && a.commands == b.commands
        && a.states == b.states
        && a.events == b.events
}

#[test]
fn every_cut_and_every_flipped_byte_of_a_small_file_is_survived() {
    let run = small_run("small");
    let original = read_log_from(run.bytes.as_slice()).unwrap();
    println!("small file: {} bytes", run.bytes.len());
    assert!(!original.truncated);
    let data_end = data_section_end(&run.bytes);
    for cut in 0..run.bytes.len() {
        if let Ok(log) = read_log_from(&run.bytes[..cut]) {
            assert_eq!(log.truncated, cut < data_end, "cut at {cut}");
        }
    }
    let mut damaged = run.bytes.clone();
    let (mut errors, mut truncated, mut intact) = (0, 0, 0);
    // Every byte of the data section; the summary after it is never read, so a sample will do.
    let offsets = (0..data_end).chain((data_end..damaged.len()).step_by(7));
    for offset in offsets {
        for flip in [0xFF, 0x01] {
            damaged[offset] ^= flip;
            match read_log_from(damaged.as_slice()) {
                Err(_) => errors += 1,
                Ok(log) if log.truncated => truncated += 1,
                Ok(log) => {
                    // Only bytes outside the data section (summary, footer) may go unnoticed,
                    // and they hold nothing the reader returns.
                    assert!(
                        same_data(&log, &original),
                        "flip {flip:#x} at {offset} read as intact but different"
                    );
                    intact += 1;
                }
            }
            damaged[offset] ^= flip;
        }
    }
    println!(
        "{} bytes ({data_end} of data section), 2 flips each: {errors} errors, \
         {truncated} truncated, {intact} unaffected",
        damaged.len()
    );
    let _ = std::fs::remove_file(&run.path);
}

struct XorShift(u64);

impl XorShift {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        self.0
    }

    fn bytes(&mut self, len: usize) -> Vec<u8> {
        (0..len).map(|_| self.next() as u8).collect()
    }
}

#[test]
fn random_bytes_never_panic() {
    let run = small_run("random");
    let magic = &run.bytes[..8];
    let header_end = top_level_records(&run.bytes)[0].2;
    let mut rng = XorShift(0x2545_f491_4f6c_dd1d);
    for round in 0..3000 {
        let len = (rng.next() % 3000) as usize;
        let mut bytes = match round % 3 {
            0 => Vec::new(),
            1 => magic.to_vec(),
            _ => run.bytes[..header_end].to_vec(),
        };
        bytes.extend(rng.bytes(len));
        if round % 5 == 0 && bytes.len() > 8 {
            // A record that claims to be a chunk, to reach the chunk decoder.
            let at = bytes.len().min(header_end);
            bytes.insert(at, mcap::records::op::CHUNK);
        }
        let _ = read_log_from(bytes.as_slice());
    }
    // Splices of the real file with random runs in between.
    for _ in 0..500 {
        let mut bytes = run.bytes.clone();
        let at = (rng.next() as usize) % bytes.len();
        let len = ((rng.next() % 64) as usize).min(bytes.len() - at);
        let noise = rng.bytes(len);
        bytes[at..at + len].copy_from_slice(&noise);
        if let Ok(log) = read_log_from(bytes.as_slice()) {
            assert!(log.truncated || log.commands.len() == 12);
        }
    }
    let _ = std::fs::remove_file(&run.path);
}

fn record_bytes(opcode: u8, body: &[u8]) -> Vec<u8> {
    let mut out = vec![opcode];
    out.extend((body.len() as u64).to_le_bytes());
    out.extend(body);
    out
}

#[test]
fn an_uncompressed_chunk_with_lying_lengths_and_no_crc_is_survived() {
    let run = small_run("lying-chunk");
    let header_end = top_level_records(&run.bytes)[0].2;
    for inner_len in [0u64, 1, 5, 8, 9, 100, 1 << 20, u64::MAX - 8, u64::MAX] {
        let mut records = vec![mcap::records::op::MESSAGE];
        records.extend(inner_len.to_le_bytes());
        records.extend([0u8; 6]);
        let mut chunk = Vec::new();
        chunk.extend(0u64.to_le_bytes());
        chunk.extend(0u64.to_le_bytes());
        chunk.extend((records.len() as u64).to_le_bytes());
        chunk.extend(0u32.to_le_bytes()); // no CRC: nothing vouches for the inner lengths
        chunk.extend(0u32.to_le_bytes()); // no compression
        chunk.extend((records.len() as u64).to_le_bytes());
        chunk.extend(&records);
        chunk.extend([0xAB; 64]); // padding the inner record could run into
        let mut bytes = run.bytes[..header_end].to_vec();
        bytes.extend(record_bytes(mcap::records::op::CHUNK, &chunk));
        bytes.extend(&run.bytes[header_end..]);
        let _ = read_log_from(bytes.as_slice());
    }
    let _ = std::fs::remove_file(&run.path);
}

/// A file written with the mcap crate directly, to test what rigbridge's recorder never
/// writes: a malformed message, and a file without the Metadata record.
fn foreign_file(with_metadata: bool, messages: &[&str]) -> Vec<u8> {
    let mut out = std::io::Cursor::new(Vec::new());
    let mut writer = mcap::Writer::new(&mut out).unwrap();
    let mut identity = BTreeMap::new();
    identity.insert("rig".to_owned(), "r".to_owned());
    identity.insert("joint_names".to_owned(), r#"["a","b"]"#.to_owned());
    if with_metadata {
        writer
            .write_metadata(&mcap::records::Metadata {
                name: "rigbridge".into(),
                metadata: identity.clone(),
            })
            .unwrap();
    }
    let schema = writer.add_schema("s", "jsonschema", b"{}").unwrap();
    let channel = writer
        .add_channel(schema, "/r/joint_command", "json", &identity)
        .unwrap();
    let camera = writer
        .add_channel(0, "/camera", "json", &BTreeMap::new())
        .unwrap();
    for (i, text) in messages.iter().enumerate() {
        let header = mcap::records::MessageHeader {
            channel_id: channel,
            sequence: i as u32,
            log_time: i as u64,
            publish_time: i as u64,
        };
        writer
            .write_to_known_channel(&header, text.as_bytes())
            .unwrap();
        let other = mcap::records::MessageHeader {
            channel_id: camera,
            ..header
        };
        writer.write_to_known_channel(&other, b"{}").unwrap();
    }
    writer.finish().unwrap();
    drop(writer);
    out.into_inner()
}

#[test]
fn a_malformed_message_is_an_error_naming_its_channel_and_index() {
    let good = r#"{"seq":0,"t":0.0,"name":["a","b"],"position":[1,2],"velocity":[0,0]}"#;
    let bad = r#"{"seq":2,"t":0.008,"name":["a","b"],"position":"oops","velocity":[0,0]}"#;
    let bytes = foreign_file(true, &[good, good, bad]);
    match read_log_from(bytes.as_slice()) {
        Err(LogError::BadMessage { topic, index, .. }) => {
            assert_eq!(topic, "/r/joint_command");
            assert_eq!(index, 2);
        }
        other => panic!("{other:?}"),
    }
}

#[test]
fn without_the_metadata_record_the_channels_still_name_rig_and_joints() {
    let good = r#"{"seq":0,"t":0.0,"name":["a","b"],"position":[1,2],"velocity":[0,0]}"#;
    let log = read_log_from(foreign_file(false, &[good]).as_slice()).unwrap();
    assert_eq!(log.rig, "r");
    assert_eq!(log.joint_names, ["a", "b"]);
    assert_eq!(log.metadata, serde_json::Value::Null);
    assert_eq!(log.commands.len(), 1);
    assert_eq!(log.other_messages, 1);
}

#[test]
fn a_full_channel_drops_and_counts_instead_of_blocking() {
    let path = temp_path("overflow");
    let options = RecorderOptions {
        capacity: 4,
        ..RecorderOptions::default()
    };
    let recorder =
        Recorder::create_with(&path, "arm6", &joint_names(), metadata(), options).unwrap();
    let (command, _) = cycle(0);
    let sent = 200_000u64;
    for _ in 0..sent {
        recorder.record(command);
    }
    assert!(recorder.dropped() > 0);
    let stats = recorder.finish().unwrap();
    assert!(stats.dropped > 0, "{stats:?}");
    assert_eq!(stats.commands + stats.dropped, sent);
    let log = read_log(&path).unwrap();
    assert_eq!(log.commands.len() as u64, stats.commands);
    let _ = std::fs::remove_file(&path);
}

#[test]
fn record_does_not_wait_for_the_writer_at_p99() {
    let path = temp_path("latency");
    let recorder = Recorder::create(&path, "arm6", &joint_names(), metadata()).unwrap();
    let mut latencies = Vec::with_capacity(100_000);
    for i in 0..100_000u32 {
        let (command, _) = cycle(i);
        let start = Instant::now();
        recorder.record(command);
        latencies.push(start.elapsed());
    }
    let stats = recorder.finish().unwrap();
    latencies.sort();
    let p50 = latencies[latencies.len() / 2];
    let p99 = latencies[latencies.len() * 99 / 100];
    let max = latencies[latencies.len() - 1];
    println!("record(): p50 {p50:?}, p99 {p99:?}, max {max:?}; {stats:?}");
    // A blocked send would take as long as the writer's next pass (>= 10 ms poll).
    assert!(p99 < Duration::from_millis(1), "p99 {p99:?}");
    let _ = std::fs::remove_file(&path);
}

#[test]
fn a_dropped_recorder_still_closes_its_file_and_refuses_to_overwrite() {
    let path = temp_path("dropped");
    {
        let recorder = Recorder::create(&path, "arm6", &joint_names(), metadata()).unwrap();
        recorder.record(cycle(0).0);
    }
    let bytes = std::fs::read(&path).unwrap();
    assert!(mcap::Summary::read(&bytes).unwrap().is_some());
    assert_eq!(read_log(&path).unwrap().commands.len(), 1);
    assert!(matches!(
        Recorder::create(&path, "arm6", &joint_names(), metadata()),
        Err(LogError::Io { .. })
    ));
    let _ = std::fs::remove_file(&path);
}

const CHILD_ENV: &str = "RIGBRIDGE_LOG_TEST_CHILD";
const KILLED_TEST: &str = "log::a_run_killed_with_sigkill_leaves_a_readable_file";

/// A child process killed however the test ends: the recording child never stops alone.
struct Killed(std::process::Child);

impl Drop for Killed {
    fn drop(&mut self) {
        let _ = self.0.kill(); // SIGKILL on Unix: no destructor, no finish().
        let _ = self.0.wait();
    }
}

/// The test binary runs this test again as its child, with [`CHILD_ENV`] naming the file:
/// the child records at 1 kHz until the test, once the file holds some commands, kills it.
#[test]
fn a_run_killed_with_sigkill_leaves_a_readable_file() {
    if let Some(path) = std::env::var_os(CHILD_ENV) {
        record_until_killed(Path::new(&path));
    }
    let path = temp_path("sigkill");
    let child = Killed(
        std::process::Command::new(std::env::current_exe().unwrap())
            .args(["--exact", KILLED_TEST, "--nocapture"])
            .env(CHILD_ENV, &path)
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .unwrap(),
    );
    let before_kill = common::wait_for_logged_commands(&path, 50, Duration::from_secs(30));
    drop(child);
    let log = read_log(&path).unwrap();
    assert!(log.truncated);
    assert_eq!(log.metadata, metadata());
    assert!(
        log.commands.len() > 50 && log.commands.len() >= before_kill,
        "{} commands, {before_kill} readable before the kill",
        log.commands.len()
    );
    assert_eq!(log.events.len(), 1);
    for (i, command) in log.commands.iter().enumerate() {
        assert_eq!(command.seq, i as u32);
    }
    println!(
        "killed run: {} commands, {} states, stopped {:?}",
        log.commands.len(),
        log.states.len(),
        log.stopped
    );
    let _ = std::fs::remove_file(&path);
}

/// The child's part of [`a_run_killed_with_sigkill_leaves_a_readable_file`]: records to
/// `path` at 1 kHz in 50 ms chunks until the process is killed.
fn record_until_killed(path: &Path) -> ! {
    let options = RecorderOptions {
        chunk_interval: Duration::from_millis(50),
        ..RecorderOptions::default()
    };
    let recorder =
        Recorder::create_with(path, "arm6", &joint_names(), metadata(), options).unwrap();
    recorder.event(0.0, "job_started", serde_json::Value::Null);
    let mut i = 0;
    loop {
        let (command, state) = cycle(i);
        recorder.record(command);
        recorder.record(state);
        std::thread::sleep(Duration::from_millis(1));
        i += 1;
    }
}
