//! The EGM wire messages (ABB Externally Guided Motion, UDP + protobuf 2), written by hand as
//! `prost` structs from the field numbers of abb_libegm's `proto/egm.proto` ("ABB sensor
//! interface V1.1", RobotWare 6.07.01 and later; github.com/ros-industrial/abb_libegm). Only
//! the fields joint mode needs are declared: RobotWare 7's additions (EgmRobot 11 moveIndex,
//! 12 CollisionInfo, 13 RAPIDfromRobot; EgmSensor 4 RAPIDtoRobot, as in abb-robot-client's
//! egm_pb2) and every other field are skipped by the decoder, never an error.
//!
//! Shared by the bridge's EGM link (the sensor) and the EGM twin (the robot). Owns the
//! message layout and the degree conversions; it must not know about streaming or sessions.
//!
//! Written by hand rather than generated: a `prost-build` step would need `protoc` on every
//! machine before `cargo clippy`, and a copy of ABB's file in this repository.

use prost::Message;

/// proto2 repeated scalars are not packed unless declared so, and egm.proto does not.
#[derive(Clone, PartialEq, Message)]
pub struct EgmJoints {
    #[prost(double, repeated, packed = "false", tag = "1")]
    pub joints: Vec<f64>,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, prost::Enumeration)]
#[repr(i32)]
pub enum MessageType {
    Undefined = 0,
    Command = 1,
    Data = 2,
    Correction = 3,
    PathCorrection = 4,
}

#[derive(Clone, PartialEq, Message)]
pub struct EgmHeader {
    #[prost(uint32, optional, tag = "1")]
    pub seqno: Option<u32>,
    /// Send time stamp, ms.
    #[prost(uint32, optional, tag = "2")]
    pub tm: Option<u32>,
    #[prost(enumeration = "MessageType", optional, tag = "3")]
    pub mtype: Option<i32>,
}

/// Seconds and microseconds since 1970 (both required in proto2).
#[derive(Clone, PartialEq, Message)]
pub struct EgmClock {
    #[prost(uint64, required, tag = "1")]
    pub sec: u64,
    #[prost(uint64, required, tag = "2")]
    pub usec: u64,
}

/// egm.proto's EgmPlanned (the robot's planned or the sensor's commanded position) and
/// EgmFeedBack (the measured position): the same fields, joints 1, cartesian 2 (not used
/// here), external joints 3 and time 4, so one struct serves both.
#[derive(Clone, PartialEq, Message)]
pub struct EgmJointPosition {
    #[prost(message, optional, tag = "1")]
    pub joints: Option<EgmJoints>,
    #[prost(message, optional, tag = "3")]
    pub external_joints: Option<EgmJoints>,
    #[prost(message, optional, tag = "4")]
    pub time: Option<EgmClock>,
}

pub type EgmPlanned = EgmJointPosition;
pub type EgmFeedBack = EgmJointPosition;

/// Speed references, deg/s in joint mode; field 2 (cartesians) is not used here.
#[derive(Clone, PartialEq, Message)]
pub struct EgmSpeedRef {
    #[prost(message, optional, tag = "1")]
    pub joints: Option<EgmJoints>,
    #[prost(message, optional, tag = "3")]
    pub external_joints: Option<EgmJoints>,
}

/// One EGM state: its enumeration (0 is `Undefined` in every one, which an absent or
/// unknown value reads as), and the message that carries it as its field 1, required
/// (egm.proto wraps every state so). `$name` is the enumeration's name as prost wants it.
macro_rules! egm_state {
    ($(#[$doc:meta])* $state:ident, $name:tt, $message:ident { $($variant:ident = $value:tt),+ }) => {
        $(#[$doc])*
        #[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, prost::Enumeration)]
        #[repr(i32)]
        pub enum $state {
            Undefined = 0,
            $($variant = $value),+
        }

        #[derive(Clone, PartialEq, Message)]
        pub struct $message {
            #[prost(enumeration = $name, required, tag = "1")]
            pub state: i32,
        }

        impl $message {
            /// The state `message` carries: `Undefined` when it is absent or unknown.
            pub fn of(message: Option<&Self>) -> $state {
                message
                    .and_then(|m| $state::try_from(m.state).ok())
                    .unwrap_or($state::Undefined)
            }
        }
    };
}

egm_state!(MotorState, "MotorState", EgmMotorState { On = 1, Off = 2 });
egm_state!(
    /// The EGM (motion control interface) state.
    MciState,
    "MciState",
    EgmMciState { Error = 1, Stopped = 2, Running = 3 }
);
egm_state!(
    RapidState,
    "RapidState",
    EgmRapidCtrlExecState { Stopped = 1, Running = 2 }
);

/// From the robot controller, every EGM cycle.
#[derive(Clone, PartialEq, Message)]
pub struct EgmRobot {
    #[prost(message, optional, tag = "1")]
    pub header: Option<EgmHeader>,
    #[prost(message, optional, tag = "2")]
    pub feed_back: Option<EgmFeedBack>,
    #[prost(message, optional, tag = "3")]
    pub planned: Option<EgmPlanned>,
    #[prost(message, optional, tag = "4")]
    pub motor_state: Option<EgmMotorState>,
    #[prost(message, optional, tag = "5")]
    pub mci_state: Option<EgmMciState>,
    #[prost(bool, optional, tag = "6")]
    pub mci_convergence_met: Option<bool>,
    #[prost(message, optional, tag = "8")]
    pub rapid_exec_state: Option<EgmRapidCtrlExecState>,
    /// How much of the allowed correction speed the sensor's references use, percent.
    #[prost(double, optional, tag = "10")]
    pub utilization_rate: Option<f64>,
}

/// To the robot controller, one per EgmRobot, in position guidance.
#[derive(Clone, PartialEq, Message)]
pub struct EgmSensor {
    #[prost(message, optional, tag = "1")]
    pub header: Option<EgmHeader>,
    #[prost(message, optional, tag = "2")]
    pub planned: Option<EgmPlanned>,
    #[prost(message, optional, tag = "3")]
    pub speed_ref: Option<EgmSpeedRef>,
}

impl EgmRobot {
    pub fn motors(&self) -> MotorState {
        EgmMotorState::of(self.motor_state.as_ref())
    }

    pub fn mci(&self) -> MciState {
        EgmMciState::of(self.mci_state.as_ref())
    }

    pub fn rapid(&self) -> RapidState {
        EgmRapidCtrlExecState::of(self.rapid_exec_state.as_ref())
    }

    /// The measured joint positions, degrees, when the message has them.
    pub fn feedback_joints(&self) -> Option<&[f64]> {
        self.feed_back
            .as_ref()
            .and_then(|f| f.joints.as_ref())
            .map(|j| j.joints.as_slice())
    }

    pub fn seqno(&self) -> Option<u32> {
        self.header.as_ref().and_then(|h| h.seqno)
    }
}

impl EgmSensor {
    /// A joint-mode correction: positions (rad) and speeds (rad/s), sent in degrees.
    pub fn joint_correction(seqno: u32, tm_ms: u32, positions: &[f64], speeds: &[f64]) -> Self {
        Self {
            header: Some(EgmHeader {
                seqno: Some(seqno),
                tm: Some(tm_ms),
                mtype: Some(MessageType::Correction as i32),
            }),
            planned: Some(EgmPlanned {
                joints: Some(degrees(positions)),
                external_joints: None,
                time: None,
            }),
            speed_ref: Some(EgmSpeedRef {
                joints: Some(degrees(speeds)),
                external_joints: None,
            }),
        }
    }

    /// The commanded joint positions, degrees, when the message has them.
    pub fn planned_joints(&self) -> Option<&[f64]> {
        self.planned
            .as_ref()
            .and_then(|p| p.joints.as_ref())
            .map(|j| j.joints.as_slice())
    }

    /// The speed references, deg/s, when the message has them.
    pub fn speed_joints(&self) -> Option<&[f64]> {
        self.speed_ref
            .as_ref()
            .and_then(|p| p.joints.as_ref())
            .map(|j| j.joints.as_slice())
    }

    pub fn message_type(&self) -> MessageType {
        self.header
            .as_ref()
            .and_then(|h| h.mtype)
            .and_then(|t| MessageType::try_from(t).ok())
            .unwrap_or(MessageType::Undefined)
    }
}

/// Radians (or rad/s) to the degrees EGM joint mode speaks.
pub fn degrees(values: &[f64]) -> EgmJoints {
    EgmJoints {
        joints: values.iter().map(|v| v.to_degrees()).collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn header_fields_sit_at_abb_field_numbers() {
        // Field 1 varint 5, field 2 varint 7, field 3 varint 3 (MSGTYPE_CORRECTION).
        let bytes = [0x08, 5, 0x10, 7, 0x18, 3];
        let header = EgmHeader::decode(&bytes[..]).expect("valid header");
        assert_eq!(header.seqno, Some(5));
        assert_eq!(header.tm, Some(7));
        assert_eq!(header.mtype, Some(3));
        assert_eq!(header.encode_to_vec(), bytes);
    }

    #[test]
    fn joints_go_out_unpacked_as_proto2_declares() {
        let joints = EgmJoints {
            joints: vec![1.0, -2.5],
        };
        let mut expected = vec![0x09];
        expected.extend_from_slice(&1.0f64.to_le_bytes());
        expected.push(0x09);
        expected.extend_from_slice(&(-2.5f64).to_le_bytes());
        assert_eq!(joints.encode_to_vec(), expected);
        // A packed sender (proto3 style) must still be understood.
        let mut packed = vec![0x0A, 16];
        packed.extend_from_slice(&1.0f64.to_le_bytes());
        packed.extend_from_slice(&(-2.5f64).to_le_bytes());
        assert_eq!(EgmJoints::decode(&packed[..]).expect("packed"), joints);
    }

    #[test]
    fn robot_states_decode_and_robotware_7_fields_are_skipped() {
        let mut bytes = Vec::new();
        // motorState {state: MOTORS_ON}, mciState {state: MCI_RUNNING},
        // rapidExecState {state: RAPID_RUNNING}, utilizationRate 12.5.
        bytes.extend_from_slice(&[0x22, 2, 0x08, 1, 0x2A, 2, 0x08, 3, 0x42, 2, 0x08, 2, 0x51]);
        bytes.extend_from_slice(&12.5f64.to_le_bytes());
        // RobotWare 7: moveIndex (11) = 4, RAPIDfromRobot (13) = an empty message.
        bytes.extend_from_slice(&[0x58, 4, 0x6A, 0]);
        let robot = EgmRobot::decode(&bytes[..]).expect("valid robot message");
        assert_eq!(robot.motors(), MotorState::On);
        assert_eq!(robot.mci(), MciState::Running);
        assert_eq!(robot.rapid(), RapidState::Running);
        assert_eq!(robot.utilization_rate, Some(12.5));
        assert_eq!(robot.feedback_joints(), None);
    }

    #[test]
    fn a_correction_carries_degrees_and_its_type() {
        let sensor = EgmSensor::joint_correction(
            9,
            40,
            &[std::f64::consts::FRAC_PI_2],
            &[std::f64::consts::PI],
        );
        let decoded = EgmSensor::decode(&sensor.encode_to_vec()[..]).expect("round trip");
        assert_eq!(decoded.message_type(), MessageType::Correction);
        assert!((decoded.planned_joints().expect("planned")[0] - 90.0).abs() < 1e-12);
        assert!((decoded.speed_joints().expect("speed")[0] - 180.0).abs() < 1e-12);
    }
}
