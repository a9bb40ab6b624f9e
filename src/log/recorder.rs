//! Recording a run without ever making the streaming cycle wait. The cycle hands over `Copy`
//! records through a preallocated ring (`ring.rs`: no allocation, no lock held across I/O, a
//! full ring drops and counts); one writer thread serialises them to JSON (and, for a rig,
//! to Foxglove protobuf: `foxglove.rs`) and writes MCAP chunks. Owns the writer thread and
//! the file it writes; must not touch the link, the controller or the cycle's timing, and
//! never blocks the caller of `record`. A write that fails is said at once (a `tracing`
//! error, and [`LogHealth`], which anyone watching the job reads without waiting); the
//! writer then drops and counts what comes after it. What the job does about it is the
//! daemon's choice (`[log] on_error`), not the recorder's.

use super::LogError;
use super::foxglove::{FoxgloveLog, RobotDescription, SceneSource};
use super::ring::{self, NoRecord, RecordReceiver, RecordSender};
use super::wire::{
    self, EVENT_SCHEMA_NAME, EVENTS_TOPIC, EventOut, MESSAGE_ENCODING, METADATA_NAME,
    SAMPLE_SCHEMA_NAME, SCHEMA_ENCODING, SampleOut, key,
};
use crate::protocol::{AxisValues, JointTarget, MAX_AXES};
use crate::rig::{JointKind, Rig};
use mcap::records::{MessageHeader, Metadata};
use mcap::{Compression, WriteOptions, Writer};
use std::collections::BTreeMap;
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::{self, Receiver, Sender};
use std::sync::{Arc, Mutex, PoisonError};
use std::thread::JoinHandle;
use std::time::Duration;

use crate::clock::{self, Clock};

/// 8192 records: command + state at 1 kHz for 4 s, twice the 2 s a stalled disk must be
/// ridden out for. About 1 MB for six axes (`ring.rs` packs a record into the words its
/// axes need), allocated once at `create`.
pub const DEFAULT_CAPACITY: usize = 8192;
/// Seconds of records the channel holds: twice the 2 s a stalled disk must be ridden out for.
const BUFFERED_S: f64 = 4.0;
/// Records per cycle: a command and a state.
const RECORDS_PER_CYCLE: f64 = 2.0;
/// The least capacity at any rate (slow rigs still get room for bursts of events' records).
const MIN_CAPACITY: usize = 256;

/// The channel capacity that holds [`BUFFERED_S`] of records at `rate_hz`, up to
/// [`DEFAULT_CAPACITY`] (1 kHz): a 250 Hz job needs a quarter of it (256 KB for six axes).
pub fn capacity_for_rate(rate_hz: f64) -> usize {
    let wanted = (RECORDS_PER_CYCLE * rate_hz * BUFFERED_S).ceil();
    if wanted.is_finite() && wanted > 0.0 {
        (wanted as usize).clamp(MIN_CAPACITY, DEFAULT_CAPACITY)
    } else {
        DEFAULT_CAPACITY
    }
}
/// Uncompressed bytes per chunk. A SIGKILL loses at most the open chunk: at 1 kHz with six
/// joints this closes a chunk about every 0.2 s.
pub const DEFAULT_CHUNK_BYTES: usize = 128 * 1024;
/// Largest chunk size accepted; `read_log` takes records up to 64 MiB, with room to spare.
pub const MAX_CHUNK_BYTES: usize = 16 << 20;
/// zstd's fastest level: its context keeps about half the memory resident that the default
/// level 3 does (0.64 MB against 1.3 MB, streaming 128 KiB chunks; a 512 KiB window and an
/// 8 K-entry hash table, not 2 MiB and 128 K + 64 K entries: zstd's `clevels.h`), and on
/// 128 KiB chunks of joint samples its output is no larger (`docs/logs.md`).
const ZSTD_LEVEL: u32 = 1;
/// Slow runs (few joints, 250 Hz, long pauses) still close a chunk at least this often.
pub const DEFAULT_CHUNK_INTERVAL: Duration = Duration::from_secs(1);

/// The writer polls rather than sleeps on the channel, so `try_send` never has a parked
/// receiver to wake: no futex call on the cycle thread. Every 10 ms: 20 records at 1 kHz,
/// half a percent of the channel; a daemon with 128 jobs wakes 12 800 times a second for
/// them, not 64 000 (issue 18).
const POLL: Duration = Duration::from_millis(10);
/// How long `record` sleeps between looks for room, when told to wait (virtual clock
/// only): short beside the writer's pass, so the writer rarely finds the ring empty.
const WAIT_FOR_ROOM: Duration = Duration::from_micros(100);
/// Records written per pass before events and chunk closing get a turn.
const BATCH: usize = 1024;

/// The first write a log failed: what and why, and when in the job.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct LogFailure {
    /// The file, what was being written and the operating system's cause, in words.
    pub error: String,
    /// Job time (s) of the latest record or event the writer had taken when it failed:
    /// nothing from about then on is in the file.
    pub at_s: f64,
}

/// Whether a recorder's file still takes writes, shared by its writer thread with whoever
/// watches the job (the cycle's sink, the control API's status). Reading it never waits on
/// the writer: the flag is an atomic, the words behind it are set once.
#[derive(Debug, Default)]
pub struct LogHealth {
    failed: AtomicBool,
    failure: Mutex<Option<LogFailure>>,
}

impl LogHealth {
    /// Whether a write has failed: one atomic load, for the cycle.
    pub fn is_failed(&self) -> bool {
        self.failed.load(Ordering::Acquire)
    }

    /// The first failure, if there was one.
    pub fn failure(&self) -> Option<LogFailure> {
        self.failure
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }

    /// Keeps the first failure and says it on stderr, at once; later ones add nothing.
    fn fail(&self, path: &Path, error: &LogError, at_s: f64) {
        let mut slot = self.failure.lock().unwrap_or_else(PoisonError::into_inner);
        if slot.is_some() {
            return;
        }
        let failure = LogFailure {
            error: format!(
                "writing log {}: {}",
                path.display(),
                super::error_chain(error)
            ),
            at_s,
        };
        tracing::error!(
            path = %path.display(),
            at_s,
            "log failed at job time {at_s:.3} s: {}; what the job records from then on is lost",
            failure.error
        );
        *slot = Some(failure);
        self.failed.store(true, Ordering::Release);
    }
}

/// One cycle's command or measured state, handed to [`Recorder::record`] by value.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum LogRecord {
    /// What the bridge sent, and how late the cycle that sent it woke (microseconds; its
    /// jitter).
    Command {
        seq: u32,
        t: f64,
        positions: AxisValues,
        velocities: AxisValues,
        late_us: f32,
    },
    /// What the controller reported (velocities may be estimated by the caller).
    State {
        seq: u32,
        t: f64,
        positions: AxisValues,
        velocities: AxisValues,
    },
}

impl LogRecord {
    /// The command of `target`, sent by a cycle that woke `late_us` late.
    pub fn command(target: &JointTarget, late_us: f32) -> Self {
        Self::Command {
            seq: target.seq,
            t: target.t.as_secs_f64(),
            positions: target.positions,
            velocities: target.velocities,
            late_us,
        }
    }
}

#[derive(Debug, Clone, PartialEq)]
pub struct RecorderOptions {
    /// Records the channel holds; [`Recorder::record`] drops (and counts) beyond this.
    pub capacity: usize,
    /// Close the open chunk once this many uncompressed message bytes are in it.
    pub chunk_bytes: usize,
    /// ... or once it has been open this long.
    pub chunk_interval: Duration,
    /// Recorded so `log info` can report revolute tracking error in degrees.
    pub joint_kinds: Option<Vec<JointKind>>,
    /// Wait for room in the channel instead of dropping. Only for cycles that are not real
    /// time (a virtual clock outruns any writer; waiting there costs no deadline and keeps
    /// the log complete).
    pub wait_when_full: bool,
    /// The rig's links and URDF: the log gains `/tf`, `/joint_states` and the URDF
    /// attachment (`docs/foxglove.md`), encoded on the writer thread.
    pub robot: Option<Arc<RobotDescription>>,
    /// The world around the rig: the log gains `/scene` (`foxglove.SceneUpdate`), fed the
    /// measured states on the writer thread.
    pub scene: Option<SceneSource>,
    /// Compress chunks with zstd (the default). A log of a few events (a cell's journal)
    /// gains nothing by it and would keep a compression context (over 0.6 MB) alive for
    /// as long as it is open.
    pub compressed: bool,
}

impl Default for RecorderOptions {
    fn default() -> Self {
        Self {
            capacity: DEFAULT_CAPACITY,
            chunk_bytes: DEFAULT_CHUNK_BYTES,
            chunk_interval: DEFAULT_CHUNK_INTERVAL,
            joint_kinds: None,
            wait_when_full: false,
            robot: None,
            scene: None,
            compressed: true,
        }
    }
}

impl RecorderOptions {
    /// Defaults plus the rig's joint kinds.
    pub fn for_rig(rig: &Rig) -> Self {
        Self {
            joint_kinds: Some(rig.joints.iter().map(|j| j.kind).collect()),
            robot: Some(Arc::new(RobotDescription::generated(
                rig,
                &crate::cell::Cell::builtin(),
            ))),
            ..Self::default()
        }
    }
}

/// What a finished recording holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RecorderStats {
    pub commands: u64,
    pub states: u64,
    pub events: u64,
    /// Records `record` could not queue (channel full) or the writer could not write.
    pub dropped: u64,
    /// File size once closed.
    pub bytes: u64,
}

struct EventMessage {
    t: f64,
    kind: String,
    detail: serde_json::Value,
}

#[derive(Default)]
struct Written {
    commands: u64,
    states: u64,
    events: u64,
    bytes: u64,
    /// Job time of the latest record or event taken.
    last_t: f64,
}

/// Queues events into a [`Recorder`] from any thread, like [`Recorder::event`]. Once the
/// recorder has finished its file, events sent through it are refused.
#[derive(Clone)]
pub struct EventSender(Sender<EventMessage>);

impl EventSender {
    /// Queues one event; `false` when the log is closed already (one sent in the very
    /// moment the writer closes the file may still be lost).
    pub fn event(&self, t: f64, kind: &str, detail: serde_json::Value) -> bool {
        self.0
            .send(EventMessage {
                t,
                kind: kind.to_owned(),
                detail,
            })
            .is_ok()
    }
}

/// Records one run to one MCAP file (layout: `docs/logs.md`).
pub struct Recorder {
    path: PathBuf,
    // Only the cycle's thread takes it (one at a time), so the lock is never contended and
    // never waits; it is there because `record` takes `&self`.
    records: Option<Mutex<RecordSender>>,
    // Unbounded: events are rare, may allocate, and must not be lost to a full channel.
    events: Option<Sender<EventMessage>>,
    dropped: Arc<AtomicU64>,
    writer: Option<JoinHandle<Result<Written, Failed>>>,
    wait_when_full: bool,
    health: Arc<LogHealth>,
}

/// How a writer thread that failed ended: what it had written, and the first error.
struct Failed {
    written: Written,
    error: LogError,
}

/// A recorder closed whatever happened: what it wrote, and the first error, if any (the
/// file then ends early; see [`LogHealth`]).
pub struct Closed {
    pub stats: RecorderStats,
    pub error: Option<LogError>,
}

impl Recorder {
    /// Creates `path` (refusing to overwrite an existing file), writes the metadata record,
    /// schemas and channels, and starts the writer thread.
    pub fn create(
        path: &Path,
        rig_name: &str,
        joint_names: &[String],
        metadata: serde_json::Value,
    ) -> Result<Self, LogError> {
        Self::create_with(
            path,
            rig_name,
            joint_names,
            metadata,
            RecorderOptions::default(),
        )
    }

    /// [`Recorder::create`] for a rig, recording its joint kinds too.
    pub fn for_rig(path: &Path, rig: &Rig, metadata: serde_json::Value) -> Result<Self, LogError> {
        let names: Vec<String> = rig.joint_names().map(str::to_owned).collect();
        Self::create_with(
            path,
            &rig.name,
            &names,
            metadata,
            RecorderOptions::for_rig(rig),
        )
    }

    pub fn create_with(
        path: &Path,
        rig_name: &str,
        joint_names: &[String],
        metadata: serde_json::Value,
        options: RecorderOptions,
    ) -> Result<Self, LogError> {
        check_setup(rig_name, joint_names, &options)?;
        let wait_when_full = options.wait_when_full;
        let sink = Sink::open(path, rig_name, joint_names, &metadata, &options)?;
        let (records_tx, mut records_rx) = ring::ring(options.capacity, joint_names.len());
        let (events_tx, events_rx) = mpsc::channel();
        let dropped = Arc::new(AtomicU64::new(0));
        let thread_dropped = Arc::clone(&dropped);
        let health = Arc::new(LogHealth::default());
        let thread_health = Arc::clone(&health);
        let writer = std::thread::Builder::new()
            .name("rigbridge-log".to_owned())
            .spawn(move || {
                // Started from the cycle's thread: it must not compete with the cycle at
                // the cycle's priority, on the cycle's CPU. Refusal changes nothing else.
                let _ = crate::realtime::step_aside();
                sink.run(&mut records_rx, &events_rx, &thread_dropped, &thread_health)
            })
            .map_err(|e| LogError::io("starting the log writer thread", e))?;
        Ok(Self {
            path: path.to_owned(),
            records: Some(Mutex::new(records_tx)),
            events: Some(events_tx),
            dropped,
            writer: Some(writer),
            wait_when_full,
            health,
        })
    }

    /// Queues one record for writing. Never allocates, never waits (unless the options
    /// ask to, for a virtual clock): when the writer is behind and the channel is full, the
    /// record is dropped and counted.
    pub fn record(&self, record: LogRecord) {
        let queued = match &self.records {
            Some(records) => {
                let mut records = records.lock().unwrap_or_else(PoisonError::into_inner);
                loop {
                    if records.try_send(&record) {
                        break true;
                    }
                    if !self.wait_when_full || records.is_closed() {
                        break false;
                    }
                    std::thread::sleep(WAIT_FOR_ROOM);
                }
            }
            None => false,
        };
        if !queued {
            self.dropped.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// Queues a job event (`job_started`, `job_ended`, `pause`, `stop`, `fault`,
    /// `link_error`, ...). Allocates; meant for events, not for every cycle.
    pub fn event(&self, t: f64, kind: &str, detail: serde_json::Value) {
        if let Some(events) = &self.events {
            // A send fails only once the writer thread has gone, which finish() reports.
            let _ = events.send(EventMessage {
                t,
                kind: kind.to_owned(),
                detail,
            });
        }
    }

    /// A handle that queues events from another thread (an operator's action arriving
    /// over HTTP while the job streams); `None` once the recorder is finishing.
    pub fn event_sender(&self) -> Option<EventSender> {
        self.events.clone().map(EventSender)
    }

    /// Records dropped so far.
    pub fn dropped(&self) -> u64 {
        self.dropped.load(Ordering::Relaxed)
    }

    /// Whether the file still takes writes, for whoever watches the job.
    pub fn health(&self) -> Arc<LogHealth> {
        Arc::clone(&self.health)
    }

    /// Whether a write has failed (one atomic load).
    pub fn failed(&self) -> bool {
        self.health.is_failed()
    }

    /// Writes everything queued, the summary and the footer, and closes the file.
    pub fn finish(self) -> Result<RecorderStats, LogError> {
        let closed = self.close();
        match closed.error {
            Some(error) => Err(error),
            None => Ok(closed.stats),
        }
    }

    /// [`Recorder::finish`], keeping what was written when it failed: the counts hold what
    /// the writer took before the first error, `dropped` everything after.
    pub fn close(mut self) -> Closed {
        let (written, error) = match self.stop_writer() {
            Ok(written) => (written, None),
            Err(failed) => (failed.written, Some(failed.error)),
        };
        Closed {
            stats: RecorderStats {
                commands: written.commands,
                states: written.states,
                events: written.events,
                dropped: self.dropped(),
                bytes: written.bytes,
            },
            error,
        }
    }

    fn stop_writer(&mut self) -> Result<Written, Failed> {
        // Closing both channels is the writer's signal to drain and finish.
        self.records = None;
        self.events = None;
        let Some(handle) = self.writer.take() else {
            return Ok(Written::default());
        };
        let result = handle.join().unwrap_or_else(|_| {
            Err(Failed {
                written: Written::default(),
                error: LogError::WriterPanicked {
                    path: self.path.clone(),
                },
            })
        });
        if let Err(failed) = &result {
            self.health
                .fail(&self.path, &failed.error, failed.written.last_t);
        }
        result
    }
}

impl Drop for Recorder {
    /// A recorder dropped without `finish` still closes its file properly.
    fn drop(&mut self) {
        let _ = self.stop_writer();
    }
}

fn check_setup(rig: &str, joints: &[String], options: &RecorderOptions) -> Result<(), LogError> {
    let problem = if rig.is_empty() {
        Some("the rig name is empty".to_owned())
    } else if joints.is_empty() || joints.len() > MAX_AXES {
        Some(format!(
            "{} joints; a log takes 1 to {MAX_AXES}",
            joints.len()
        ))
    } else if options.capacity == 0 {
        // A zero-capacity sync_channel is a rendezvous: every try_send would fail.
        Some("channel capacity 0".to_owned())
    } else if options.chunk_bytes == 0 || options.chunk_bytes > MAX_CHUNK_BYTES {
        Some(format!(
            "chunk size {} bytes; a log takes 1 to {MAX_CHUNK_BYTES}",
            options.chunk_bytes
        ))
    } else {
        options
            .joint_kinds
            .as_ref()
            .filter(|kinds| kinds.len() != joints.len())
            .map(|kinds| format!("{} joint kinds for {} joints", kinds.len(), joints.len()))
    };
    match problem {
        Some(problem) => Err(LogError::Setup(problem)),
        None => Ok(()),
    }
}

/// The writer thread's state: the MCAP writer and what it needs to encode records.
struct Sink {
    path: PathBuf,
    writer: Writer<BufWriter<File>>,
    command_channel: u16,
    state_channel: u16,
    event_channel: u16,
    joint_names: Vec<String>,
    json: Vec<u8>,
    open_chunk_bytes: usize,
    /// When the open chunk took its first record, on the process's real clock.
    chunk_opened: Option<Duration>,
    chunk_bytes: usize,
    chunk_interval: Duration,
    written: Written,
    foxglove: Option<FoxgloveLog>,
}

/// How long a log file's creation waits for a descriptor when the process has none free:
/// the control API closes its oldest connections for newcomers under a flood, and their
/// descriptors come free within milliseconds; a job should not fail to start for that.
const DESCRIPTOR_WAIT: Duration = Duration::from_millis(500);
/// How often the creation is tried again meanwhile.
const DESCRIPTOR_RETRY: Duration = Duration::from_millis(5);

/// Creates the log at `path` (never over an existing file), waiting up to
/// [`DESCRIPTOR_WAIT`] while the process is out of descriptors. A wait for the OS, not a
/// motion time: it sleeps on the thread, before the job streams.
fn create_log_file(path: &Path) -> std::io::Result<File> {
    let mut waited = Duration::ZERO;
    loop {
        match File::create_new(path) {
            Err(e)
                if matches!(e.raw_os_error(), Some(libc::EMFILE | libc::ENFILE))
                    && waited < DESCRIPTOR_WAIT =>
            {
                std::thread::sleep(DESCRIPTOR_RETRY);
                waited += DESCRIPTOR_RETRY;
            }
            result => return result,
        }
    }
}

impl Sink {
    fn open(
        path: &Path,
        rig: &str,
        joint_names: &[String],
        metadata: &serde_json::Value,
        options: &RecorderOptions,
    ) -> Result<Self, LogError> {
        let context = || format!("creating log {}", path.display());
        let file = create_log_file(path).map_err(|e| LogError::io(context(), e))?;
        let write_options = WriteOptions::new()
            .compression(options.compressed.then_some(Compression::Zstd))
            .compression_level(ZSTD_LEVEL)
            .library(format!(
                "rigbridge/{} {}",
                env!("CARGO_PKG_VERSION"),
                mcap::LIBRARY_IDENTIFIER
            ))
            // Chunks close when this sink says so (size or age), never inside `write`.
            .chunk_size(None)
            // Build each chunk in memory and write it whole: a killed run leaves complete
            // chunks and at most one partial one at the end, never a patched-up header.
            .disable_seeking(true)
            // Multi-threaded zstd would add worker threads competing with the cycle.
            .compression_threads(0);
        let mut writer = write_options.create(BufWriter::new(file))?;
        let kinds = options.joint_kinds.as_deref();
        let mut identity = wire::identity_map(rig, joint_names, kinds);
        let channel_metadata = identity.clone();
        identity.insert(key::METADATA.to_owned(), wire::json_string(metadata));
        writer.write_metadata(&Metadata {
            name: METADATA_NAME.to_owned(),
            metadata: identity,
        })?;
        let (command_channel, state_channel, event_channel) =
            add_channels(&mut writer, rig, &channel_metadata)?;
        let foxglove =
            FoxgloveLog::open(&mut writer, options.robot.clone(), options.scene.as_ref())?;
        // The first chunk holds only schemas and channels, on disk before the first cycle.
        writer.flush()?;
        Ok(Self {
            path: path.to_owned(),
            writer,
            command_channel,
            state_channel,
            event_channel,
            joint_names: joint_names.to_vec(),
            json: Vec::with_capacity(4096),
            open_chunk_bytes: 0,
            chunk_opened: None,
            chunk_bytes: options.chunk_bytes,
            chunk_interval: options.chunk_interval,
            written: Written::default(),
            foxglove,
        })
    }

    fn run(
        mut self,
        records: &mut RecordReceiver,
        events: &Receiver<EventMessage>,
        dropped: &AtomicU64,
        health: &LogHealth,
    ) -> Result<Written, Failed> {
        let mut failure: Option<LogError> = None;
        loop {
            let (taken, closed) = self.pass(records, events, dropped, &mut failure, health);
            if closed {
                break;
            }
            if taken == 0 {
                std::thread::sleep(POLL);
            }
        }
        // Events sent before finish() are queued by now; write them last.
        self.drain_events(events, &mut failure, health);
        let written = std::mem::take(&mut self.written);
        match failure {
            Some(error) => Err(Failed { written, error }),
            None => self.close(written),
        }
    }

    /// Keeps the first error and says it at once (stderr, `health`): the writer goes on
    /// taking records, only to drop and count them.
    fn failed(&self, failure: &mut Option<LogError>, error: LogError, health: &LogHealth) {
        if failure.is_none() {
            health.fail(&self.path, &error, self.written.last_t);
            *failure = Some(error);
        }
    }

    /// One batch of records, then events and chunk closing. Returns how many records were
    /// taken and whether the records channel is closed and empty.
    fn pass(
        &mut self,
        records: &mut RecordReceiver,
        events: &Receiver<EventMessage>,
        dropped: &AtomicU64,
        failure: &mut Option<LogError>,
        health: &LogHealth,
    ) -> (usize, bool) {
        let mut taken = 0;
        let mut closed = false;
        while taken < BATCH {
            match records.try_recv() {
                Ok(record) => {
                    taken += 1;
                    if failure.is_some() {
                        dropped.fetch_add(1, Ordering::Relaxed);
                    } else if let Err(error) = self.write_record(&record) {
                        dropped.fetch_add(1, Ordering::Relaxed);
                        self.failed(failure, error, health);
                    }
                }
                Err(NoRecord::Empty) => break,
                Err(NoRecord::Closed) => {
                    closed = true;
                    break;
                }
            }
        }
        self.drain_events(events, failure, health);
        if failure.is_none()
            && let Err(error) = self.close_chunk_if_old()
        {
            self.failed(failure, error, health);
        }
        (taken, closed)
    }

    fn drain_events(
        &mut self,
        events: &Receiver<EventMessage>,
        failure: &mut Option<LogError>,
        health: &LogHealth,
    ) {
        while let Ok(event) = events.try_recv() {
            if failure.is_none()
                && let Err(error) = self.write_event(&event)
            {
                self.failed(failure, error, health);
            }
        }
    }

    fn write_record(&mut self, record: &LogRecord) -> Result<(), LogError> {
        let (channel, seq, t, positions, velocities, late_us) = match record {
            // Widened exactly: the log reads back the very value the jitter counted.
            LogRecord::Command {
                seq,
                t,
                positions,
                velocities,
                late_us,
            } => (
                self.command_channel,
                seq,
                t,
                positions,
                velocities,
                Some(f64::from(*late_us)),
            ),
            LogRecord::State {
                seq,
                t,
                positions,
                velocities,
            } => (self.state_channel, seq, t, positions, velocities, None),
        };
        self.written.last_t = *t;
        self.json.clear();
        let sample = SampleOut {
            seq: *seq,
            t: *t,
            name: &self.joint_names,
            position: positions.as_slice(),
            velocity: velocities.as_slice(),
            late_us,
        };
        serde_json::to_writer(&mut self.json, &sample)
            .map_err(|e| LogError::io("encoding a record", e.into()))?;
        self.write_message(channel, *seq, *t)?;
        if channel == self.command_channel {
            self.written.commands += 1;
        } else {
            self.written.states += 1;
            if let Some(foxglove) = &mut self.foxglove {
                let (p, v) = (positions.as_slice(), velocities.as_slice());
                let bytes = foxglove.state(&mut self.writer, *t, job_time_ns(*t), p, v)?;
                self.count_chunk_bytes(bytes)?;
            }
        }
        Ok(())
    }

    fn write_event(&mut self, event: &EventMessage) -> Result<(), LogError> {
        if event.t.is_finite() {
            self.written.last_t = self.written.last_t.max(event.t);
        }
        self.json.clear();
        let out = EventOut {
            t: event.t,
            kind: &event.kind,
            detail: &event.detail,
        };
        serde_json::to_writer(&mut self.json, &out)
            .map_err(|e| LogError::io("encoding an event", e.into()))?;
        let sequence = u32::try_from(self.written.events).unwrap_or(u32::MAX);
        self.write_message(self.event_channel, sequence, event.t)?;
        self.written.events += 1;
        Ok(())
    }

    /// Writes `self.json` as one message stamped with job time `t`.
    fn write_message(&mut self, channel_id: u16, sequence: u32, t: f64) -> Result<(), LogError> {
        let time = job_time_ns(t);
        let header = MessageHeader {
            channel_id,
            sequence,
            log_time: time,
            publish_time: time,
        };
        self.writer.write_to_known_channel(&header, &self.json)?;
        self.count_chunk_bytes(self.json.len())
    }

    fn count_chunk_bytes(&mut self, bytes: usize) -> Result<(), LogError> {
        self.open_chunk_bytes += bytes;
        self.chunk_opened.get_or_insert_with(|| clock::real().now());
        if self.open_chunk_bytes >= self.chunk_bytes {
            self.close_chunk()?;
        }
        Ok(())
    }

    fn close_chunk_if_old(&mut self) -> Result<(), LogError> {
        match self.chunk_opened {
            Some(opened) if clock::real().now().saturating_sub(opened) >= self.chunk_interval => {
                self.close_chunk()
            }
            _ => Ok(()),
        }
    }

    fn close_chunk(&mut self) -> Result<(), LogError> {
        // Finishes the chunk and pushes it out of the BufWriter to the OS, where a killed
        // process can no longer lose it.
        self.writer.flush()?;
        self.open_chunk_bytes = 0;
        self.chunk_opened = None;
        Ok(())
    }

    fn close(self, written: Written) -> Result<Written, Failed> {
        match self.finish_file() {
            Ok(bytes) => Ok(Written { bytes, ..written }),
            Err(error) => Err(Failed { written, error }),
        }
    }

    /// Writes the summary and footer and syncs the file; its size.
    fn finish_file(mut self) -> Result<u64, LogError> {
        let context = || format!("closing log {}", self.path.display());
        self.writer.finish()?;
        let file = self
            .writer
            .into_inner()
            .into_inner()
            .map_err(|e| LogError::io(context(), e.into_error()))?;
        file.sync_all().map_err(|e| LogError::io(context(), e))?;
        Ok(file
            .metadata()
            .map_err(|e| LogError::io(context(), e))?
            .len())
    }
}

fn add_channels(
    writer: &mut Writer<BufWriter<File>>,
    rig: &str,
    joint_metadata: &BTreeMap<String, String>,
) -> Result<(u16, u16, u16), LogError> {
    let sample_schema = wire::sample_schema();
    let event_schema = wire::event_schema();
    let sample = writer.add_schema(
        SAMPLE_SCHEMA_NAME,
        SCHEMA_ENCODING,
        sample_schema.as_bytes(),
    )?;
    let event = writer.add_schema(EVENT_SCHEMA_NAME, SCHEMA_ENCODING, event_schema.as_bytes())?;
    let command = writer.add_channel(
        sample,
        &wire::command_topic(rig),
        MESSAGE_ENCODING,
        joint_metadata,
    )?;
    let state = writer.add_channel(
        sample,
        &wire::state_topic(rig),
        MESSAGE_ENCODING,
        joint_metadata,
    )?;
    let events = writer.add_channel(event, EVENTS_TOPIC, MESSAGE_ENCODING, &BTreeMap::new())?;
    Ok((command, state, events))
}

/// Job time in MCAP nanoseconds. Times before the job start (or not finite) become 0: MCAP
/// timestamps are unsigned, and the exact `t` is in the message anyway.
fn job_time_ns(t: f64) -> u64 {
    if t.is_finite() && t > 0.0 {
        // `as` saturates at u64::MAX (585 years), which is the right clamp here.
        (t * 1e9).round() as u64
    } else {
        0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn job_time_is_clamped_nanoseconds() {
        assert_eq!(job_time_ns(0.004), 4_000_000);
        assert_eq!(job_time_ns(-1.0), 0);
        assert_eq!(job_time_ns(f64::NAN), 0);
        assert_eq!(job_time_ns(f64::INFINITY), 0);
    }

    #[test]
    fn health_keeps_the_first_failure_with_its_path_and_cause() {
        let health = LogHealth::default();
        assert!(!health.is_failed() && health.failure().is_none());
        let full = std::io::Error::from_raw_os_error(libc::ENOSPC);
        let first = LogError::io("writing a chunk", full);
        health.fail(Path::new("runs/job-7.mcap"), &first, 2.5);
        let later = LogError::Setup("a later failure".into());
        health.fail(Path::new("runs/job-7.mcap"), &later, 3.0);
        assert!(health.is_failed());
        let failure = health.failure().expect("the failure is kept");
        assert_eq!(failure.at_s, 2.5);
        assert!(
            failure.error.contains("runs/job-7.mcap"),
            "{}",
            failure.error
        );
        assert!(
            failure.error.contains("writing a chunk"),
            "{}",
            failure.error
        );
        assert!(!failure.error.contains("later"), "{}", failure.error);
    }

    #[test]
    fn a_record_is_small_enough_to_preallocate_thousands() {
        assert!(std::mem::size_of::<LogRecord>() <= 560);
    }

    #[test]
    fn bad_setups_are_refused() {
        let opts = RecorderOptions::default();
        assert!(check_setup("", &["a".into()], &opts).is_err());
        assert!(check_setup("r", &[], &opts).is_err());
        let zero = RecorderOptions {
            capacity: 0,
            ..RecorderOptions::default()
        };
        assert!(check_setup("r", &["a".into()], &zero).is_err());
        let kinds = RecorderOptions {
            joint_kinds: Some(vec![]),
            ..RecorderOptions::default()
        };
        assert!(check_setup("r", &["a".into()], &kinds).is_err());
    }
}
