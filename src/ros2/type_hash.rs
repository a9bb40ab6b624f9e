//! RIHS01 type hashes (ROS 2 Iron and later, REP-2011): the SHA-256 of a message type's
//! description (its fields and, sorted by name, every type it refers to) written as JSON the
//! way `rosidl_generator_type_description` writes it for hashing: default values left out,
//! `", "` and `": "` as separators, keys in the description's order. rmw_zenoh puts the hash
//! in every topic's key expression and liveliness token, so a subscriber only matches a
//! publisher of the same type.
//!
//! Owns the descriptions of the messages rigbridge speaks (and those they contain); it must
//! not know about Zenoh or the daemon.

use serde::Serialize;
use sha2::{Digest, Sha256};

/// Field type ids of `type_description_interfaces/msg/FieldType` (REP-2011).
const NESTED_TYPE: u8 = 1;
const INT32: u8 = 6;
const UINT32: u8 = 7;
const DOUBLE: u8 = 11;
const STRING: u8 = 17;
/// Added to an element's id for an unbounded sequence of it (`FieldType`: 144..=167).
const UNBOUNDED_SEQUENCE: u8 = 144;

/// One field: its name, type id and, for a nested type, that type.
type FieldSpec = (&'static str, u8, Option<&'static MessageType>);

/// A message type: its full name (`package/msg/Name`) and fields in order.
pub struct MessageType {
    pub name: &'static str,
    fields: &'static [FieldSpec],
}

pub static TIME: MessageType = MessageType {
    name: "builtin_interfaces/msg/Time",
    fields: &[("sec", INT32, None), ("nanosec", UINT32, None)],
};

pub static DURATION: MessageType = MessageType {
    name: "builtin_interfaces/msg/Duration",
    fields: &[("sec", INT32, None), ("nanosec", UINT32, None)],
};

pub static HEADER: MessageType = MessageType {
    name: "std_msgs/msg/Header",
    fields: &[
        ("stamp", NESTED_TYPE, Some(&TIME)),
        ("frame_id", STRING, None),
    ],
};

pub static JOINT_STATE: MessageType = MessageType {
    name: "sensor_msgs/msg/JointState",
    fields: &[
        ("header", NESTED_TYPE, Some(&HEADER)),
        ("name", STRING + UNBOUNDED_SEQUENCE, None),
        ("position", DOUBLE + UNBOUNDED_SEQUENCE, None),
        ("velocity", DOUBLE + UNBOUNDED_SEQUENCE, None),
        ("effort", DOUBLE + UNBOUNDED_SEQUENCE, None),
    ],
};

pub static JOINT_TRAJECTORY_POINT: MessageType = MessageType {
    name: "trajectory_msgs/msg/JointTrajectoryPoint",
    fields: &[
        ("positions", DOUBLE + UNBOUNDED_SEQUENCE, None),
        ("velocities", DOUBLE + UNBOUNDED_SEQUENCE, None),
        ("accelerations", DOUBLE + UNBOUNDED_SEQUENCE, None),
        ("effort", DOUBLE + UNBOUNDED_SEQUENCE, None),
        ("time_from_start", NESTED_TYPE, Some(&DURATION)),
    ],
};

pub static JOINT_TRAJECTORY: MessageType = MessageType {
    name: "trajectory_msgs/msg/JointTrajectory",
    fields: &[
        ("header", NESTED_TYPE, Some(&HEADER)),
        ("joint_names", STRING + UNBOUNDED_SEQUENCE, None),
        (
            "points",
            NESTED_TYPE + UNBOUNDED_SEQUENCE,
            Some(&JOINT_TRAJECTORY_POINT),
        ),
    ],
};

#[derive(Serialize)]
struct FieldTypeJson {
    type_id: u8,
    capacity: u64,
    string_capacity: u64,
    nested_type_name: &'static str,
}

#[derive(Serialize)]
struct FieldJson {
    name: &'static str,
    #[serde(rename = "type")]
    field_type: FieldTypeJson,
}

#[derive(Serialize)]
struct DescriptionJson {
    type_name: &'static str,
    fields: Vec<FieldJson>,
}

#[derive(Serialize)]
struct HashedJson {
    type_description: DescriptionJson,
    referenced_type_descriptions: Vec<DescriptionJson>,
}

impl MessageType {
    fn description(&self) -> DescriptionJson {
        DescriptionJson {
            type_name: self.name,
            fields: self
                .fields
                .iter()
                .map(|&(name, type_id, nested)| FieldJson {
                    name,
                    field_type: FieldTypeJson {
                        type_id,
                        capacity: 0,
                        string_capacity: 0,
                        nested_type_name: nested.map_or("", |n| n.name),
                    },
                })
                .collect(),
        }
    }

    /// Every type this one refers to, directly or not, sorted by name, each once.
    fn referenced(&self) -> Vec<&'static MessageType> {
        let mut found: Vec<&'static MessageType> = Vec::new();
        let mut pending: Vec<&'static MessageType> =
            self.fields.iter().filter_map(|f| f.2).collect();
        while let Some(next) = pending.pop() {
            if !found.iter().any(|f| f.name == next.name) {
                found.push(next);
                pending.extend(next.fields.iter().filter_map(|f| f.2));
            }
        }
        found.sort_by_key(|t| t.name);
        found
    }

    /// The JSON that is hashed.
    pub fn hashed_json(&self) -> String {
        let hashed = HashedJson {
            type_description: self.description(),
            referenced_type_descriptions: self
                .referenced()
                .iter()
                .map(|t| t.description())
                .collect(),
        };
        let mut out = Vec::new();
        let mut serializer = serde_json::Serializer::with_formatter(&mut out, SpacedJson);
        // Plain structs of strings and numbers: serialising into memory cannot fail.
        hashed
            .serialize(&mut serializer)
            .expect("a type description serialises");
        String::from_utf8(out).expect("serde_json writes UTF-8")
    }

    /// `RIHS01_` and the SHA-256 of [`Self::hashed_json`] in lowercase hex.
    pub fn rihs01(&self) -> String {
        let digest = Sha256::digest(self.hashed_json().as_bytes());
        let mut text = String::from("RIHS01_");
        for byte in digest {
            text.push_str(&format!("{byte:02x}"));
        }
        text
    }
}

/// JSON with Python's `json.dumps(separators=(", ", ": "))` spacing, which the hash is
/// defined over.
struct SpacedJson;

impl serde_json::ser::Formatter for SpacedJson {
    fn begin_array_value<W: ?Sized + std::io::Write>(
        &mut self,
        writer: &mut W,
        first: bool,
    ) -> std::io::Result<()> {
        if first {
            Ok(())
        } else {
            writer.write_all(b", ")
        }
    }

    fn begin_object_key<W: ?Sized + std::io::Write>(
        &mut self,
        writer: &mut W,
        first: bool,
    ) -> std::io::Result<()> {
        self.begin_array_value(writer, first)
    }

    fn begin_object_value<W: ?Sized + std::io::Write>(
        &mut self,
        writer: &mut W,
    ) -> std::io::Result<()> {
        writer.write_all(b": ")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The hashes ROS 2 Jazzy's own interface packages carry (`ros2 topic info --verbose`
    /// prints them as "Topic type hash"; docs/ros2.md says where they are published). Not
    /// computed here: copied from there.
    const JAZZY_JOINT_STATE: &str =
        "RIHS01_a13ee3a330e346c9d87b5aa18d24e11690752bd33a0350f11c5882bc9179260e";
    const JAZZY_JOINT_TRAJECTORY: &str =
        "RIHS01_179b33eba59d676f6d967ac71fe35e7ca2f64b2f3928f4a018cec115e213796e";
    const JAZZY_TIME: &str =
        "RIHS01_b106235e25a4c5ed35098aa0a61a3ee9c9b18d197f398b0e4206cea9acf9c197";
    const JAZZY_DURATION: &str =
        "RIHS01_e8d009f659816f758b75334ee1a9ca5b5c0b859843261f14c7f937349599d93b";

    #[test]
    fn hashes_match_the_ones_ros_2_jazzy_publishes() {
        assert_eq!(JOINT_STATE.rihs01(), JAZZY_JOINT_STATE);
        assert_eq!(JOINT_TRAJECTORY.rihs01(), JAZZY_JOINT_TRAJECTORY);
        assert_eq!(TIME.rihs01(), JAZZY_TIME);
        assert_eq!(DURATION.rihs01(), JAZZY_DURATION);
    }

    #[test]
    fn referenced_types_are_sorted_by_name_and_listed_once() {
        let names: Vec<&str> = JOINT_TRAJECTORY
            .referenced()
            .iter()
            .map(|t| t.name)
            .collect();
        assert_eq!(
            names,
            [
                "builtin_interfaces/msg/Duration",
                "builtin_interfaces/msg/Time",
                "std_msgs/msg/Header",
                "trajectory_msgs/msg/JointTrajectoryPoint",
            ]
        );
    }
}
