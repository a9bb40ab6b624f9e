//! What a run log's messages and metadata look like: topic names, the JSON schemas, the JSON
//! message encoding and the string-valued metadata maps. Shared by the recorder and the
//! reader so the two cannot drift apart. Owns bytes-in-a-message only; must not know about
//! MCAP framing, threads or files.

use super::{LoggedEvent, LoggedSample};
use crate::rig::JointKind;
use serde::{Deserialize, Deserializer, Serialize};
use std::collections::BTreeMap;
use thiserror::Error;

/// Why a well-framed record's content is not what a run log holds.
#[derive(Debug, Error)]
pub enum LogDecodeError {
    /// A message that is not the JSON its channel's schema describes.
    #[error("{0}")]
    Json(#[from] serde_json::Error),
    /// An identity or metadata entry whose value is not the JSON it should be.
    #[error("{key}: {source}")]
    Entry {
        key: &'static str,
        source: serde_json::Error,
    },
    #[error("{}: unknown joint kind `{kind}`", key::JOINT_KINDS)]
    UnknownJointKind { kind: String },
    #[error("message encoding `{found}`, expected `{}`", MESSAGE_ENCODING)]
    Encoding { found: String },
}

/// Topic of job events (started, ended, pause, stop, fault, link errors).
pub const EVENTS_TOPIC: &str = "/rigbridge/events";
/// Name of the MCAP Metadata record holding the rig, its joints and the job metadata.
pub const METADATA_NAME: &str = "rigbridge";

/// The log format's version (`docs/logs.md`, "Versions"): 2 moved each wake's lateness
/// from the state to the command and records stalls; version 1 logs still read.
pub(super) const FORMAT: &str = "rigbridge-log/2";
pub(super) const MESSAGE_ENCODING: &str = "json";
pub(super) const SCHEMA_ENCODING: &str = "jsonschema";
pub(super) const SAMPLE_SCHEMA_NAME: &str = "rigbridge.JointSample";
pub(super) const EVENT_SCHEMA_NAME: &str = "rigbridge.Event";

/// Keys of the Metadata record and of the joint channels' metadata maps.
pub(super) mod key {
    pub const FORMAT: &str = "format";
    pub const RIG: &str = "rig";
    pub const JOINT_NAMES: &str = "joint_names";
    pub const JOINT_KINDS: &str = "joint_kinds";
    pub const METADATA: &str = "metadata";
}

const COMMAND_SUFFIX: &str = "/joint_command";
const STATE_SUFFIX: &str = "/joint_state";

/// `/<rig>/joint_command`: the targets the bridge sent.
pub fn command_topic(rig: &str) -> String {
    format!("/{rig}{COMMAND_SUFFIX}")
}

/// `/<rig>/joint_state`: the positions the controller reported.
pub fn state_topic(rig: &str) -> String {
    format!("/{rig}{STATE_SUFFIX}")
}

/// What a channel carries, judged by its topic.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Role {
    Command,
    State,
    Events,
    Other,
}

impl Role {
    pub(super) fn of_topic(topic: &str) -> Self {
        if topic == EVENTS_TOPIC {
            Self::Events
        } else if topic.ends_with(COMMAND_SUFFIX) {
            Self::Command
        } else if topic.ends_with(STATE_SUFFIX) {
            Self::State
        } else {
            Self::Other
        }
    }
}

/// The rig named by a joint topic (`/arm/joint_command` -> `arm`).
pub(super) fn rig_of_topic(topic: &str) -> Option<&str> {
    let inner = topic.strip_prefix('/')?;
    inner
        .strip_suffix(COMMAND_SUFFIX)
        .or_else(|| inner.strip_suffix(STATE_SUFFIX))
}

pub(super) fn sample_schema() -> String {
    let number_array = |description: &str| {
        serde_json::json!({
            "type": "array",
            "items": { "type": "number" },
            "description": description,
        })
    };
    let schema = serde_json::json!({
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": SAMPLE_SCHEMA_NAME,
        "description": "One streaming cycle of one rig, in the rig's joint order. JSON has no NaN or infinity: a non-finite value is written as null.",
        "type": "object",
        "properties": {
            "seq": {
                "type": "integer", "minimum": 0, "maximum": u32::MAX,
                "description": "Cycle sequence number (the JointTarget's seq; for states, the seq the state answers)."
            },
            "t": { "type": "number", "description": "Seconds since the job started." },
            "name": {
                "type": "array", "items": { "type": "string" },
                "description": "Joint names, one per position and velocity."
            },
            "position": number_array("rad (revolute joints) or m (prismatic joints)."),
            "velocity": number_array("rad/s or m/s."),
            "late_us": {
                "type": "number",
                "description": "Commands only, optional: how late the cycle that sent it woke after its deadline (its jitter), microseconds. Format 1 logs had it on states."
            },
        },
        "required": ["seq", "t", "name", "position", "velocity"],
    });
    pretty(&schema)
}

pub(super) fn event_schema() -> String {
    let schema = serde_json::json!({
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": EVENT_SCHEMA_NAME,
        "description": "A job event: job_started, job_ended, pause, resume, stop, fault, link_error, ...",
        "type": "object",
        "properties": {
            "t": { "type": "number", "description": "Seconds since the job started." },
            "kind": { "type": "string" },
            "detail": { "description": "Free-form details of the event (any JSON value)." },
        },
        "required": ["t", "kind", "detail"],
    });
    pretty(&schema)
}

fn pretty(value: &serde_json::Value) -> String {
    // A json! literal always serialises; the fallback only keeps this free of unwrap.
    serde_json::to_string_pretty(value).unwrap_or_default()
}

#[derive(Serialize)]
pub(super) struct SampleOut<'a> {
    pub seq: u32,
    pub t: f64,
    pub name: &'a [String],
    pub position: &'a [f64],
    pub velocity: &'a [f64],
    /// Commands only: how late the cycle that sent it woke, microseconds.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub late_us: Option<f64>,
}

#[derive(Serialize)]
pub(super) struct EventOut<'a> {
    pub t: f64,
    pub kind: &'a str,
    pub detail: &'a serde_json::Value,
}

#[derive(Deserialize)]
struct SampleIn {
    seq: u32,
    #[serde(deserialize_with = "nullable_f64")]
    t: f64,
    position: Vec<Option<f64>>,
    velocity: Vec<Option<f64>>,
    #[serde(default)]
    late_us: Option<f64>,
}

#[derive(Deserialize)]
struct EventIn {
    #[serde(deserialize_with = "nullable_f64")]
    t: f64,
    kind: String,
    #[serde(default)]
    detail: serde_json::Value,
}

/// `null` (what serde_json writes for NaN and infinities) reads back as NaN; a field that is
/// missing altogether is still an error.
fn nullable_f64<'de, D: Deserializer<'de>>(deserializer: D) -> Result<f64, D::Error> {
    Ok(Option::<f64>::deserialize(deserializer)?.unwrap_or(f64::NAN))
}

pub(super) fn decode_sample(json: &[u8]) -> Result<LoggedSample, LogDecodeError> {
    let sample: SampleIn = serde_json::from_slice(json)?;
    let nan_for_null = |values: Vec<Option<f64>>| -> Vec<f64> {
        values.into_iter().map(|v| v.unwrap_or(f64::NAN)).collect()
    };
    Ok(LoggedSample {
        seq: sample.seq,
        t: sample.t,
        positions: nan_for_null(sample.position),
        velocities: nan_for_null(sample.velocity),
        late_us: sample.late_us,
    })
}

pub(super) fn decode_event(json: &[u8]) -> Result<LoggedEvent, LogDecodeError> {
    let event: EventIn = serde_json::from_slice(json)?;
    Ok(LoggedEvent {
        t: event.t,
        kind: event.kind,
        detail: event.detail,
    })
}

fn kind_name(kind: JointKind) -> &'static str {
    match kind {
        JointKind::Revolute => "revolute",
        JointKind::Prismatic => "prismatic",
    }
}

/// The map stored in the Metadata record and, without `metadata`, in each joint channel's
/// metadata (which a truncated file keeps even when readers skip Metadata records).
pub(super) fn identity_map(
    rig: &str,
    joint_names: &[String],
    joint_kinds: Option<&[JointKind]>,
) -> BTreeMap<String, String> {
    let mut map = BTreeMap::new();
    map.insert(key::FORMAT.to_owned(), FORMAT.to_owned());
    map.insert(key::RIG.to_owned(), rig.to_owned());
    map.insert(key::JOINT_NAMES.to_owned(), json_string(&joint_names));
    if let Some(kinds) = joint_kinds {
        let names: Vec<&str> = kinds.iter().map(|k| kind_name(*k)).collect();
        map.insert(key::JOINT_KINDS.to_owned(), json_string(&names));
    }
    map
}

pub(super) fn json_string<T: Serialize + ?Sized>(value: &T) -> String {
    // Strings, string arrays and serde_json::Values always serialise.
    serde_json::to_string(value).unwrap_or_default()
}

/// Rig, joints and kinds read back from an identity map.
#[derive(Debug, Clone, Default, PartialEq)]
pub(super) struct Identity {
    pub rig: Option<String>,
    pub joint_names: Option<Vec<String>>,
    pub joint_kinds: Option<Vec<JointKind>>,
}

pub(super) fn parse_identity(map: &BTreeMap<String, String>) -> Result<Identity, LogDecodeError> {
    let joint_names = match map.get(key::JOINT_NAMES) {
        Some(text) => Some(serde_json::from_str::<Vec<String>>(text).map_err(|source| {
            LogDecodeError::Entry {
                key: key::JOINT_NAMES,
                source,
            }
        })?),
        None => None,
    };
    let joint_kinds = match map.get(key::JOINT_KINDS) {
        Some(text) => Some(parse_kinds(text)?),
        None => None,
    };
    Ok(Identity {
        rig: map.get(key::RIG).cloned(),
        joint_names,
        joint_kinds,
    })
}

fn parse_kinds(text: &str) -> Result<Vec<JointKind>, LogDecodeError> {
    let names: Vec<String> =
        serde_json::from_str(text).map_err(|source| LogDecodeError::Entry {
            key: key::JOINT_KINDS,
            source,
        })?;
    names
        .iter()
        .map(|name| match name.as_str() {
            "revolute" => Ok(JointKind::Revolute),
            "prismatic" => Ok(JointKind::Prismatic),
            other => Err(LogDecodeError::UnknownJointKind {
                kind: other.to_owned(),
            }),
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn samples_round_trip_bit_for_bit_and_null_reads_as_nan() {
        let names = vec!["a".to_owned(), "b".to_owned()];
        let position = [0.1 + 0.2, f64::NAN];
        let velocity = [-1e-300, 12345.678901234567];
        let out = SampleOut {
            seq: 7,
            t: 0.028,
            name: &names,
            position: &position,
            velocity: &velocity,
            late_us: Some(12.5),
        };
        let json = serde_json::to_vec(&out).expect("the sample serialises");
        let back = decode_sample(&json).expect("the sample decodes");
        assert_eq!(back.seq, 7);
        assert_eq!(back.positions[0].to_bits(), position[0].to_bits());
        assert!(back.positions[1].is_nan());
        assert_eq!(back.velocities, velocity);
        assert_eq!(back.late_us, Some(12.5));
    }

    /// serde_json's `float_roundtrip` feature (Cargo.toml) is what makes a log give back
    /// the very bits it was given: without it, a 17-digit number may parse one ulp away.
    #[test]
    fn every_float_serde_json_writes_reads_back_bit_for_bit() {
        let mut state = 0x9e37_79b9_7f4a_7c15_u64;
        let mut checked = 0;
        while checked < 20_000 {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            let value = f64::from_bits(state);
            if !value.is_finite() {
                continue;
            }
            checked += 1;
            let names = vec!["a".to_owned()];
            let out = SampleOut {
                seq: 1,
                t: value,
                name: &names,
                position: &[value],
                velocity: &[-value],
                late_us: None,
            };
            let back = decode_sample(&serde_json::to_vec(&out).expect("the sample serialises"))
                .expect("the sample decodes");
            assert_eq!(back.t.to_bits(), value.to_bits(), "{value:e}");
            assert_eq!(back.positions[0].to_bits(), value.to_bits(), "{value:e}");
            assert_eq!(
                back.velocities[0].to_bits(),
                (-value).to_bits(),
                "{value:e}"
            );
        }
    }

    #[test]
    fn wrong_fields_are_errors() {
        assert!(decode_sample(br#"{"seq":-1,"t":0,"position":[],"velocity":[]}"#).is_err());
        assert!(decode_sample(br#"{"seq":1,"t":0,"position":[]}"#).is_err());
        assert!(decode_sample(br#"{"seq":1,"t":"0","position":[],"velocity":[]}"#).is_err());
        assert!(decode_event(br#"{"t":0}"#).is_err());
    }

    #[test]
    fn topics_name_their_rig_and_role() {
        assert_eq!(rig_of_topic(&command_topic("irb120")), Some("irb120"));
        assert_eq!(Role::of_topic(&state_topic("x")), Role::State);
        assert_eq!(Role::of_topic(EVENTS_TOPIC), Role::Events);
        assert_eq!(Role::of_topic("/camera"), Role::Other);
    }

    #[test]
    fn identity_maps_round_trip() {
        let names = vec!["j1".to_owned(), "slide".to_owned()];
        let kinds = [JointKind::Revolute, JointKind::Prismatic];
        let map = identity_map("rig", &names, Some(&kinds));
        let identity = parse_identity(&map).expect("the identity map parses");
        assert_eq!(identity.rig.as_deref(), Some("rig"));
        assert_eq!(identity.joint_names, Some(names));
        assert_eq!(identity.joint_kinds, Some(kinds.to_vec()));
    }
}
