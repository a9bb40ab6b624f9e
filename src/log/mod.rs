//! Run logs: recording a streamed job to an MCAP file and reading it back (`docs/logs.md`
//! describes the file). Owns the file layout, the recorder's writer thread, the tolerant
//! reader and the `log info` summary (the stage above, `trajectory/recorded.rs`, turns the
//! recorded commands into a trajectory to replay). It must not touch links, controllers or
//! the streaming loop itself: the loop hands it [`LogRecord`]s and events, and gets nothing
//! back that could make it wait.
//!
//! - [`Recorder`]: non-blocking recording (a preallocated ring of packed records, writer
//!   thread, small chunks so a killed run leaves a readable file);
//! - [`read_log`]: every complete chunk of a file, even a truncated or damaged one;
//! - [`RobotDescription`]: the rig's links and URDF behind the Foxglove channels (`/tf`,
//!   `/joint_states`) and the `robot_description.urdf` attachment (`docs/foxglove.md`), and
//!   [`LoggedScene`]: the world drawn on `/scene`;
//! - [`summarize`]: counts, gaps, events, jitter, stalls and tracking error for
//!   `rigbridge log info`;
//! - [`Jitter`] and [`MicrosHistogram`]: the one way the stream, `log info` and `log plot`
//!   count the cycle's wakes (`wakes`), and the stalls a log records.

mod foxglove;
mod reader;
mod recorder;
mod records;
mod ring;
mod summary;
mod wakes;
mod wire;

pub use foxglove::{
    JOINT_STATES_TOPIC, LoggedScene, RobotDescription, RobotMessages, SCENE_REPEAT_S, SCENE_TOPIC,
    SceneSource, TF_PERIOD_S, TF_TOPIC, URDF_ATTACHMENT, timestamp,
};
pub use reader::{read_log, read_log_from};
pub use recorder::{
    Closed, DEFAULT_CAPACITY, DEFAULT_CHUNK_BYTES, DEFAULT_CHUNK_INTERVAL, EventSender, LogFailure,
    LogHealth, LogRecord, MAX_CHUNK_BYTES, Recorder, RecorderOptions, RecorderStats,
    capacity_for_rate,
};
pub use summary::{ChannelSummary, LogSummary, SeqGap, TrackingError, summarize};
pub use wakes::{
    JITTER_CEILING_US, Jitter, LoggedStall, MicrosHistogram, STALL_EVENT, jitter, stalls,
    wake_lateness,
};
pub use wire::{EVENTS_TOPIC, LogDecodeError, METADATA_NAME, command_topic, state_topic};

use crate::rig::JointKind;
use serde::Serialize;
use std::path::PathBuf;
use thiserror::Error;

#[derive(Debug, Error)]
pub enum LogError {
    #[error("{context}: {source}")]
    Io {
        context: String,
        #[source]
        source: std::io::Error,
    },
    #[error("MCAP writer: {0}")]
    Mcap(#[from] mcap::McapError),
    #[error("cannot record: {0}")]
    Setup(String),
    #[error("the recorder's writer thread panicked; {path} may end early")]
    WriterPanicked { path: PathBuf },
    #[error("not a rigbridge run log: {0}")]
    NotARunLog(String),
    #[error("metadata record `{name}`: {reason}")]
    BadMetadata {
        name: String,
        reason: LogDecodeError,
    },
    #[error("channel {topic}: {reason}")]
    BadChannel {
        topic: String,
        reason: LogDecodeError,
    },
    #[error("{topic} message {index} (0-based, byte {offset}): {reason}")]
    BadMessage {
        topic: String,
        index: usize,
        offset: u64,
        reason: LogDecodeError,
    },
}

impl LogError {
    fn io(context: impl Into<String>, source: std::io::Error) -> Self {
        Self::Io {
            context: context.into(),
            source,
        }
    }
}

/// One recorded command or state, as read back.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LoggedSample {
    pub seq: u32,
    /// Seconds since the job started.
    pub t: f64,
    /// rad (revolute) or m (prismatic); NaN where the recorder was handed a non-finite value.
    pub positions: Vec<f64>,
    /// rad/s or m/s; NaN as for positions.
    pub velocities: Vec<f64>,
    /// How late the cycle that sent this command woke after its deadline (jitter),
    /// microseconds: on commands from format 2 on, on states before (`docs/logs.md`);
    /// `None` where the log holds none.
    pub late_us: Option<f64>,
}

/// One job event (started, ended, pause, stop, fault, link error...), as read back.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LoggedEvent {
    pub t: f64,
    pub kind: String,
    pub detail: serde_json::Value,
}

/// Where and why reading stopped before the end of the data section.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct ReadStop {
    /// Byte offset of the first record that could not be read whole and intact.
    pub offset: u64,
    pub reason: String,
}

/// Everything a run log holds, in file order. The default is an empty log of no rig.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RunLog {
    pub rig: String,
    pub joint_names: Vec<String>,
    /// Known when the recorder was told (see [`RecorderOptions::joint_kinds`]).
    pub joint_kinds: Option<Vec<JointKind>>,
    /// The job description and config given to [`Recorder::create`]; `Null` when the
    /// metadata record is missing.
    pub metadata: serde_json::Value,
    pub commands: Vec<LoggedSample>,
    pub states: Vec<LoggedSample>,
    pub events: Vec<LoggedEvent>,
    /// Messages on channels that are not rigbridge's (skipped, counted).
    pub other_messages: u64,
    /// True when the data section did not end cleanly: the file was cut (a killed run), a
    /// chunk was damaged, or the data-section CRC did not match. Everything before
    /// `stopped.offset` was read.
    pub truncated: bool,
    pub stopped: Option<ReadStop>,
}

/// An error and all its sources, as one line ("job refused before motion: job target 0 ...").
/// Here because a failed log write is said this way too, and every layer above `log` uses
/// it through `daemon::error_chain`.
pub fn error_chain(error: &dyn std::error::Error) -> String {
    let mut text = error.to_string();
    let mut source = error.source();
    while let Some(cause) = source {
        // A message that already ends with its cause's (thiserror's `{source}` in the
        // format) says it once.
        let cause_text = cause.to_string();
        if !text.ends_with(&cause_text) {
            text.push_str(": ");
            text.push_str(&cause_text);
        }
        source = cause.source();
    }
    text
}
