//! The ROS 2 messages rigbridge speaks, as CDR: `sensor_msgs/msg/JointState`,
//! `tf2_msgs/msg/TFMessage` and `std_msgs/msg/String` out, `trajectory_msgs/msg/JointTrajectory`
//! in. A CDR payload as rmw_zenoh carries it starts
//! with the 4-byte encapsulation header (`00 01 00 00`: plain CDR, little-endian), then the
//! fields in order, each aligned to its size from the end of that header (OMG CDR, the
//! `cdr` crate). Decoding takes either byte order, as the header says.
//!
//! Owns the message structs and their encoding; it must not know about jobs or Zenoh.

use serde::{Deserialize, Serialize};
use thiserror::Error;

/// Largest payload decoded (bytes): a trajectory of 10,000 points of 32 axes with every
/// field filled is about 10 MB; anything larger is refused before it is read.
pub const MAX_PAYLOAD_BYTES: usize = 16 * 1024 * 1024;

#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Time {
    pub sec: i32,
    pub nanosec: u32,
}

/// `builtin_interfaces/msg/Duration`: the same two fields as `Time`.
pub type Duration = Time;

#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Header {
    pub stamp: Time,
    pub frame_id: String,
}

/// `sensor_msgs/msg/JointState`: each array empty or one value per name (rad, m).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct JointState {
    pub header: Header,
    pub name: Vec<String>,
    pub position: Vec<f64>,
    pub velocity: Vec<f64>,
    pub effort: Vec<f64>,
}

/// `geometry_msgs/msg/Vector3` (m).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Vector3 {
    pub x: f64,
    pub y: f64,
    pub z: f64,
}

/// `geometry_msgs/msg/Quaternion`, unit length.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Quaternion {
    pub x: f64,
    pub y: f64,
    pub z: f64,
    pub w: f64,
}

/// `geometry_msgs/msg/Transform`: the child frame in its parent.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Transform {
    pub translation: Vector3,
    pub rotation: Quaternion,
}

/// `geometry_msgs/msg/TransformStamped`: `header.frame_id` is the parent frame.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct TransformStamped {
    pub header: Header,
    pub child_frame_id: String,
    pub transform: Transform,
}

/// `tf2_msgs/msg/TFMessage`, what `/tf` and `/tf_static` carry.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct TfMessage {
    pub transforms: Vec<TransformStamped>,
}

/// `std_msgs/msg/String`, what `robot_description` carries.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct StringMessage {
    pub data: String,
}

#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct JointTrajectoryPoint {
    pub positions: Vec<f64>,
    pub velocities: Vec<f64>,
    pub accelerations: Vec<f64>,
    pub effort: Vec<f64>,
    pub time_from_start: Duration,
}

/// `trajectory_msgs/msg/JointTrajectory`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct JointTrajectory {
    pub header: Header,
    pub joint_names: Vec<String>,
    pub points: Vec<JointTrajectoryPoint>,
}

#[derive(Debug, Error)]
pub enum CdrError {
    #[error("encoding CDR: {0}")]
    Encode(cdr::Error),
    #[error("the payload of {0} bytes is larger than {MAX_PAYLOAD_BYTES}")]
    TooLarge(usize),
    #[error("not a CDR {what}: {source}")]
    Decode {
        what: &'static str,
        source: cdr::Error,
    },
}

/// `message` as CDR, little-endian, encapsulation header first.
pub fn encode<T: Serialize>(message: &T) -> Result<Vec<u8>, CdrError> {
    cdr::serialize::<_, _, cdr::CdrLe>(message, cdr::Infinite).map_err(CdrError::Encode)
}

/// A JointTrajectory from its CDR payload (encapsulation header first).
pub fn decode_joint_trajectory(payload: &[u8]) -> Result<JointTrajectory, CdrError> {
    decode(payload, "trajectory_msgs/msg/JointTrajectory")
}

/// A JointState from its CDR payload (encapsulation header first).
pub fn decode_joint_state(payload: &[u8]) -> Result<JointState, CdrError> {
    decode(payload, "sensor_msgs/msg/JointState")
}

fn decode<T: for<'de> Deserialize<'de>>(payload: &[u8], what: &'static str) -> Result<T, CdrError> {
    if payload.len() > MAX_PAYLOAD_BYTES {
        return Err(CdrError::TooLarge(payload.len()));
    }
    // The bound also caps what a sequence's stated length may make the decoder allocate.
    cdr::deserialize_from(payload, cdr::size::Bounded(payload.len() as u64))
        .map_err(|source| CdrError::Decode { what, source })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_joint_state_is_little_endian_cdr_behind_its_encapsulation_header() {
        let state = JointState {
            header: Header {
                stamp: Time { sec: 1, nanosec: 2 },
                frame_id: String::new(),
            },
            name: vec!["a".into()],
            position: vec![0.5],
            velocity: vec![],
            effort: vec![],
        };
        let bytes = encode(&state).expect("the joint state encodes");
        // Written out from the OMG CDR rules by hand: header, sec, nanosec, the empty
        // frame_id (length 1: its NUL), one name "a" (length 2 with its NUL), padding to 8,
        // then one double, and the two empty sequences.
        let expected: Vec<u8> = [
            &[0x00, 0x01, 0x00, 0x00][..],
            &1i32.to_le_bytes(),
            &2u32.to_le_bytes(),
            &1u32.to_le_bytes(),
            &[0, 0, 0, 0],
            &1u32.to_le_bytes(),
            &2u32.to_le_bytes(),
            b"a\0",
            &[0, 0],
            &1u32.to_le_bytes(),
            &0.5f64.to_le_bytes(),
            &0u32.to_le_bytes(),
            &0u32.to_le_bytes(),
        ]
        .concat();
        assert_eq!(bytes, expected);
        assert_eq!(
            decode_joint_state(&bytes).expect("the joint state decodes"),
            state
        );
    }

    #[test]
    fn a_truncated_or_lying_payload_is_refused() {
        let trajectory = JointTrajectory {
            joint_names: vec!["j".into()],
            points: vec![JointTrajectoryPoint {
                positions: vec![1.0],
                ..Default::default()
            }],
            ..Default::default()
        };
        let bytes = encode(&trajectory).expect("the trajectory encodes");
        assert_eq!(
            decode_joint_trajectory(&bytes).expect("the trajectory decodes"),
            trajectory
        );
        assert!(decode_joint_trajectory(&bytes[..bytes.len() - 3]).is_err());
        // A points count of four billion in a short payload.
        let mut lying = encode(&JointTrajectory::default()).expect("an empty trajectory encodes");
        let count = lying.len() - 4;
        lying[count..].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(decode_joint_trajectory(&lying).is_err());
    }
}
