//! Reading a run log back, including one cut short by SIGKILL (no summary, no footer) or
//! damaged on disk. Reads the data section front to back and keeps every chunk that arrives
//! whole and passes its CRC; the first record that does not ends the reading, and the
//! [`RunLog`] says where and why. Never panics and never allocates more than a bounded
//! record, whatever the bytes. Owns interpretation of the file as a run log; must not write
//! files or judge the run (that is `summary` and `replay`).
//!
//! Framing, decompression and CRCs come from the mcap crate's sans-io `LinearReader`: one at
//! the top level that hands over whole chunk records, and one per chunk that checks the CRC
//! of the whole chunk before any record of it is used, so a chunk counts all or nothing.

use super::records;
use super::wire::{self, Identity, LogDecodeError, METADATA_NAME, Role, key};
use super::{LogError, LoggedEvent, LoggedSample, ReadStop, RunLog};
use mcap::McapError;
use mcap::records::op;
use mcap::sans_io::{LinearReadEvent, LinearReader, LinearReaderOptions};
use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::io::Read;
use std::ops::Range;
use std::path::Path;
use thiserror::Error;

/// Bytes asked of the source at a time, whatever a damaged length field asks for: memory
/// grows with what the file really holds, not with what it claims.
const READ_BLOCK: usize = 64 * 1024;
/// The largest record (or decompressed chunk) accepted. rigbridge writes ~128 KiB chunks;
/// anything near this is damage.
const RECORD_LIMIT: usize = 64 << 20;
const MAGIC_LEN: u64 = 8;
/// Opcode byte and u64 length before every record's content.
const RECORD_PREFIX: u64 = 9;

/// Reads the run log at `path`. A truncated or damaged file gives `Ok` with
/// `truncated: true` and everything before the damage; `Err` means there is no run log to
/// speak of (not MCAP, no rig identity) or a message inside an intact chunk is malformed.
pub fn read_log(path: &Path) -> Result<RunLog, LogError> {
    let file =
        File::open(path).map_err(|e| LogError::io(format!("opening {}", path.display()), e))?;
    read_log_from(file)
}

/// [`read_log`] from any byte source (a file, a byte slice, a pipe).
pub fn read_log_from(mut source: impl Read) -> Result<RunLog, LogError> {
    let mut collector = Collector::default();
    let stop = scan(&mut source, &mut collector)?;
    collector.into_run_log(stop)
}

enum Flow {
    Continue,
    End,
    Stop(String),
}

/// Feeds the top-level reader until the data section ends or cannot go on.
fn scan(source: &mut impl Read, collector: &mut Collector) -> Result<Option<ReadStop>, LogError> {
    let mut reader = LinearReader::new_with_options(
        LinearReaderOptions::default()
            .with_emit_chunks(true)
            .with_validate_data_section_crc(true)
            .with_record_length_limit(RECORD_LIMIT),
    );
    let mut offset = MAGIC_LEN;
    let mut fed = 0u64;
    while let Some(event) = reader.next_event() {
        match event {
            Ok(LinearReadEvent::ReadRequest(want)) => {
                let got = feed(&mut reader, source, want)
                    .map_err(|e| LogError::io("reading the log", e))?;
                fed += got as u64;
            }
            Ok(LinearReadEvent::Record { opcode, data }) => {
                let start = offset;
                offset += RECORD_PREFIX + data.len() as u64;
                match collector.top_level(opcode, data, start)? {
                    Flow::Continue => {}
                    Flow::End => return Ok(None),
                    Flow::Stop(reason) => {
                        return Ok(Some(ReadStop {
                            offset: start,
                            reason,
                        }));
                    }
                }
            }
            Err(error) => return stop_at(&error, offset, fed).map(Some),
        }
    }
    // The reader only runs dry after the end magic, and Data End or the Footer come first.
    Ok(None)
}

/// Hands the reader up to `want` bytes (at least one, at most a block) from `source`.
fn feed(reader: &mut LinearReader, source: &mut impl Read, want: usize) -> std::io::Result<usize> {
    let buffer = reader.insert(want.clamp(1, READ_BLOCK));
    let got = loop {
        match source.read(buffer) {
            Ok(got) => break got,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
            Err(e) => return Err(e),
        }
    };
    // Zero tells the reader the source is exhausted.
    reader.notify_read(got);
    Ok(got)
}

fn stop_at(error: &McapError, offset: u64, fed: u64) -> Result<ReadStop, LogError> {
    let reason = match error {
        McapError::BadMagic => {
            return Err(LogError::NotARunLog("no MCAP magic at its start".into()));
        }
        McapError::UnexpectedEof if fed < MAGIC_LEN => {
            return Err(LogError::NotARunLog(format!(
                "{fed} bytes, shorter than the MCAP magic"
            )));
        }
        McapError::UnexpectedEof if fed <= offset => {
            "the file ends between records, before the Data End record (the recording was cut)"
                .to_owned()
        }
        McapError::UnexpectedEof => format!(
            "the file ends inside this record ({} of its bytes are there; the recording was cut)",
            fed - offset
        ),
        McapError::BadDataCrc { .. } => format!(
            "{error}: a record outside the chunks (metadata, header) is damaged; chunks passed their own CRCs"
        ),
        other => other.to_string(),
    };
    Ok(ReadStop { offset, reason })
}

/// A decompressed, CRC-checked chunk: its records' opcodes and their bytes in `bytes`.
#[derive(Default)]
struct ChunkContent {
    bytes: Vec<u8>,
    records: Vec<(u8, Range<usize>)>,
}

/// Why a chunk is not used: its framing, its compression or its CRC.
#[derive(Debug, Error)]
enum ChunkError {
    #[error(transparent)]
    Record(#[from] records::RecordError),
    #[error(transparent)]
    Mcap(#[from] McapError),
    #[error(transparent)]
    Io(#[from] std::io::Error),
}

/// Unpacks one chunk record body, all or nothing.
fn decode_chunk(body: &[u8]) -> Result<ChunkContent, ChunkError> {
    // Re-frame the chunk without any padding after its records, so the reader can never be
    // handed bytes beyond them (its uncompressed-chunk arithmetic relies on that).
    let len = records::chunk_len_without_padding(body)?;
    let mut prefix = [0u8; RECORD_PREFIX as usize];
    prefix[0] = op::CHUNK;
    prefix[1..].copy_from_slice(&(len as u64).to_le_bytes());
    let mut source = prefix.as_slice().chain(&body[..len]);
    let mut reader = LinearReader::new_with_options(
        LinearReaderOptions::default()
            .with_skip_start_magic(true)
            .with_skip_end_magic(true)
            .with_prevalidate_chunk_crcs(true)
            .with_record_length_limit(RECORD_LIMIT),
    );
    let mut content = ChunkContent::default();
    while let Some(event) = reader.next_event() {
        match event? {
            LinearReadEvent::ReadRequest(want) => {
                feed(&mut reader, &mut source, want)?;
            }
            LinearReadEvent::Record { opcode, data } => {
                let start = content.bytes.len();
                content.bytes.extend_from_slice(data);
                content.records.push((opcode, start..content.bytes.len()));
            }
        }
    }
    Ok(content)
}

struct ChannelInfo {
    topic: String,
    role: Role,
}

/// What the records read so far add up to.
#[derive(Default)]
struct Collector {
    metadata: Option<BTreeMap<String, String>>,
    channel_identity: Identity,
    topic_rig: Option<String>,
    channels: HashMap<u16, ChannelInfo>,
    commands: Vec<LoggedSample>,
    states: Vec<LoggedSample>,
    events: Vec<LoggedEvent>,
    other_messages: u64,
}

impl Collector {
    fn top_level(&mut self, opcode: u8, body: &[u8], offset: u64) -> Result<Flow, LogError> {
        match opcode {
            op::METADATA => Ok(self.metadata_record(body)),
            op::CHUNK => match decode_chunk(body) {
                Ok(chunk) => self.chunk(&chunk, offset),
                Err(reason) => Ok(Flow::Stop(format!("chunk: {reason}"))),
            },
            op::CHANNEL | op::MESSAGE => self.data_record(opcode, body, offset),
            op::DATA_END | op::FOOTER => Ok(Flow::End),
            _ => Ok(Flow::Continue),
        }
    }

    fn metadata_record(&mut self, body: &[u8]) -> Flow {
        match records::metadata(body) {
            Ok(record) => {
                if record.name == METADATA_NAME && self.metadata.is_none() {
                    self.metadata = Some(record.map);
                }
                Flow::Continue
            }
            Err(reason) => Flow::Stop(reason.to_string()),
        }
    }

    fn chunk(&mut self, chunk: &ChunkContent, offset: u64) -> Result<Flow, LogError> {
        for (opcode, range) in &chunk.records {
            // The ranges were made from these bytes; get() only keeps this free of indexing.
            let Some(body) = chunk.bytes.get(range.clone()) else {
                continue;
            };
            if let Flow::Stop(reason) = self.data_record(*opcode, body, offset)? {
                return Ok(Flow::Stop(reason));
            }
        }
        Ok(Flow::Continue)
    }

    /// A Channel or Message record, inside a chunk or not. Damaged framing stops the
    /// reading; a well-framed record whose content is wrong for a run log is an error.
    fn data_record(&mut self, opcode: u8, body: &[u8], offset: u64) -> Result<Flow, LogError> {
        match opcode {
            op::CHANNEL => match records::channel(body) {
                Ok(channel) => self.channel(channel).map(|()| Flow::Continue),
                Err(reason) => Ok(Flow::Stop(reason.to_string())),
            },
            op::MESSAGE => match records::message(body) {
                Ok(message) => self.message(&message, offset).map(|()| Flow::Continue),
                Err(reason) => Ok(Flow::Stop(reason.to_string())),
            },
            _ => Ok(Flow::Continue),
        }
    }

    fn channel(&mut self, channel: records::Channel) -> Result<(), LogError> {
        let role = Role::of_topic(&channel.topic);
        let bad = |reason: LogDecodeError| LogError::BadChannel {
            topic: channel.topic.clone(),
            reason,
        };
        if role != Role::Other && channel.message_encoding != wire::MESSAGE_ENCODING {
            return Err(bad(LogDecodeError::Encoding {
                found: channel.message_encoding.clone(),
            }));
        }
        if matches!(role, Role::Command | Role::State) {
            if self.topic_rig.is_none() {
                self.topic_rig = wire::rig_of_topic(&channel.topic).map(str::to_owned);
            }
            if self.channel_identity.joint_names.is_none() {
                self.channel_identity = wire::parse_identity(&channel.metadata).map_err(bad)?;
            }
        }
        self.channels.insert(
            channel.id,
            ChannelInfo {
                topic: channel.topic,
                role,
            },
        );
        Ok(())
    }

    fn message(&mut self, message: &records::Message<'_>, offset: u64) -> Result<(), LogError> {
        let Some(channel) = self.channels.get(&message.channel_id) else {
            // A message before its channel breaks the MCAP spec; there is nothing to read it as.
            self.other_messages += 1;
            return Ok(());
        };
        let (index, result) = match channel.role {
            Role::Command => (
                self.commands.len(),
                wire::decode_sample(message.data).map(|s| self.commands.push(s)),
            ),
            Role::State => (
                self.states.len(),
                wire::decode_sample(message.data).map(|s| self.states.push(s)),
            ),
            Role::Events => (
                self.events.len(),
                wire::decode_event(message.data).map(|e| self.events.push(e)),
            ),
            Role::Other => {
                self.other_messages += 1;
                (0, Ok(()))
            }
        };
        result.map_err(|reason| LogError::BadMessage {
            topic: channel.topic.clone(),
            index,
            offset,
            reason,
        })
    }

    fn into_run_log(self, stopped: Option<ReadStop>) -> Result<RunLog, LogError> {
        let (identity, metadata) = self.identity()?;
        let where_ = || match &stopped {
            Some(stop) => format!(" before byte {} ({})", stop.offset, stop.reason),
            None => String::new(),
        };
        let rig = identity.rig.or(self.topic_rig).ok_or_else(|| {
            LogError::NotARunLog(format!(
                "no `{METADATA_NAME}` metadata and no joint channel{}",
                where_()
            ))
        })?;
        let joint_names = identity.joint_names.ok_or_else(|| {
            LogError::NotARunLog(format!("no joint names for rig `{rig}`{}", where_()))
        })?;
        Ok(RunLog {
            rig,
            joint_names,
            joint_kinds: identity.joint_kinds,
            metadata,
            commands: self.commands,
            states: self.states,
            events: self.events,
            other_messages: self.other_messages,
            truncated: stopped.is_some(),
            stopped,
        })
    }

    /// Rig, joints and job metadata: from the `rigbridge` Metadata record where there is one,
    /// else from the joint channels' metadata.
    fn identity(&self) -> Result<(Identity, serde_json::Value), LogError> {
        let Some(map) = &self.metadata else {
            return Ok((self.channel_identity.clone(), serde_json::Value::Null));
        };
        let bad = |reason: LogDecodeError| LogError::BadMetadata {
            name: METADATA_NAME.to_owned(),
            reason,
        };
        let mut identity = wire::parse_identity(map).map_err(bad)?;
        let fallback = self.channel_identity.clone();
        identity.rig = identity.rig.or(fallback.rig);
        identity.joint_names = identity.joint_names.or(fallback.joint_names);
        identity.joint_kinds = identity.joint_kinds.or(fallback.joint_kinds);
        let metadata = match map.get(key::METADATA) {
            Some(text) => serde_json::from_str(text).map_err(|source| {
                bad(LogDecodeError::Entry {
                    key: key::METADATA,
                    source,
                })
            })?,
            None => serde_json::Value::Null,
        };
        Ok((identity, metadata))
    }
}
