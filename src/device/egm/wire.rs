//! The EGM wire messages (ABB Externally Guided Motion, UDP + protobuf 2), written by hand as
//! `prost` structs from the field numbers of abb_libegm's `proto/egm.proto` ("ABB sensor
//! interface V1.1", RobotWare 6.07.01 and later; github.com/ros-industrial/abb_libegm). Only
//! the fields joint mode needs are declared: RobotWare 7's additions (EgmRobot 11 moveIndex,
//! 12 CollisionInfo, 13 RAPIDfromRobot; EgmSensor 4 RAPIDtoRobot, as in abb-robot-client's
//! egm_pb2) and every other field are skipped by the decoder, never an error.
//!
//! Shared by the bridge's EGM link (the sensor) and the EGM twin (the robot). Owns the
//! message layout, which rig axes travel as the robot's `joints` and which as
//! `externalJoints` ([`EgmAxes`]), and the unit conversions (degrees; mm on linear axes);
//! it must not know about streaming or sessions.
//!
//! The robot's pose travels as egm.proto's EgmPose: `pos` in mm, `orient` a unit quaternion
//! (`u0` the scalar part), relative to the robot's base frame ([`robot_pose`]).
//!
//! Written by hand rather than generated: a `prost-build` step would need `protoc` on every
//! machine before `cargo clippy`, and a copy of ABB's file in this repository.

use crate::rig::{JointKind, Pose, Rig};
use glam::{DAffine3, DQuat, DVec3};
use prost::Message;
use thiserror::Error;

/// The robot's own joints in `joints`: egm.proto's EgmJoints is "Array of 6 joint values for
/// TCP robot".
pub const MAX_ROBOT_JOINTS: usize = 6;
/// egm.proto's EgmExternalJoints: "Array of 6 joint values for additional axis".
pub const MAX_EXTERNAL_AXES: usize = 6;
/// Millimetres a metre: EGM gives linear axes in mm (and mm/s).
const MM_PER_M: f64 = 1000.0;

/// What the sensor streams: joint references (RAPID's EGMActJoint / EGMRunJoint, EGMSetupUC
/// `\Joint`) or tool poses (EGMActPose / EGMRunPose, `\Pose`), which the controller solves
/// into joints itself.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum EgmMode {
    #[default]
    Joint,
    Pose,
}

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

/// egm.proto's EgmCartesian: "Cartesian position in mm" (every field required).
#[derive(Clone, PartialEq, Message)]
pub struct EgmCartesian {
    #[prost(double, required, tag = "1")]
    pub x: f64,
    #[prost(double, required, tag = "2")]
    pub y: f64,
    #[prost(double, required, tag = "3")]
    pub z: f64,
}

/// egm.proto's EgmQuaternion: u0 the scalar part, u1..u3 x, y, z (every field required).
#[derive(Clone, PartialEq, Message)]
pub struct EgmQuaternion {
    #[prost(double, required, tag = "1")]
    pub u0: f64,
    #[prost(double, required, tag = "2")]
    pub u1: f64,
    #[prost(double, required, tag = "3")]
    pub u2: f64,
    #[prost(double, required, tag = "4")]
    pub u3: f64,
}

/// egm.proto's EgmPose: "Pose (i.e. cartesian position and Quaternion orientation) relative
/// to the correction frame defined by EGMActPose". Its field 3 (Euler angles, which take
/// priority when a sensor sends both) is not sent; a received one is skipped.
#[derive(Clone, PartialEq, Message)]
pub struct EgmPose {
    #[prost(message, optional, tag = "1")]
    pub pos: Option<EgmCartesian>,
    #[prost(message, optional, tag = "2")]
    pub orient: Option<EgmQuaternion>,
}

impl EgmPose {
    /// `pose` (m, unit quaternion) on the wire: mm and the quaternion w first.
    pub fn from_pose(pose: &Pose) -> Self {
        let (p, q) = (pose.position * MM_PER_M, pose.orientation);
        Self {
            pos: Some(EgmCartesian {
                x: p.x,
                y: p.y,
                z: p.z,
            }),
            orient: Some(EgmQuaternion {
                u0: q.w,
                u1: q.x,
                u2: q.y,
                u3: q.z,
            }),
        }
    }

    /// The pose in metres, `None` without a position or an orientation. The quaternion is
    /// as sent: whether it is a unit one is the reader's check.
    pub fn to_pose(&self) -> Option<Pose> {
        let (p, q) = (self.pos.as_ref()?, self.orient.as_ref()?);
        Some(Pose::new(
            DVec3::new(p.x, p.y, p.z) / MM_PER_M,
            DQuat::from_xyzw(q.u1, q.u2, q.u3, q.u0),
        ))
    }
}

/// egm.proto's EgmCartesianSpeed: "Array of 6 speed reference values in mm/s or degrees/s"
/// (the tool's linear x, y, z then angular x, y, z).
#[derive(Clone, PartialEq, Message)]
pub struct EgmCartesianSpeed {
    #[prost(double, repeated, packed = "false", tag = "1")]
    pub value: Vec<f64>,
}

/// egm.proto's EgmPlanned (the robot's planned or the sensor's commanded position) and
/// EgmFeedBack (the measured position): the same fields, joints 1, cartesian 2, external
/// joints 3 and time 4, so one struct serves both.
#[derive(Clone, PartialEq, Message)]
pub struct EgmJointPosition {
    #[prost(message, optional, tag = "1")]
    pub joints: Option<EgmJoints>,
    #[prost(message, optional, tag = "2")]
    pub cartesian: Option<EgmPose>,
    #[prost(message, optional, tag = "3")]
    pub external_joints: Option<EgmJoints>,
    #[prost(message, optional, tag = "4")]
    pub time: Option<EgmClock>,
}

pub type EgmPlanned = EgmJointPosition;
pub type EgmFeedBack = EgmJointPosition;

/// Speed references: deg/s in joint mode, mm/s and deg/s of the tool in pose mode.
#[derive(Clone, PartialEq, Message)]
pub struct EgmSpeedRef {
    #[prost(message, optional, tag = "1")]
    pub joints: Option<EgmJoints>,
    #[prost(message, optional, tag = "2")]
    pub cartesians: Option<EgmCartesianSpeed>,
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

    /// The measured external axis positions (degrees, mm), when the message has them.
    pub fn feedback_external(&self) -> Option<&[f64]> {
        self.feed_back
            .as_ref()
            .and_then(|f| f.external_joints.as_ref())
            .map(|j| j.joints.as_slice())
    }

    pub fn seqno(&self) -> Option<u32> {
        self.header.as_ref().and_then(|h| h.seqno)
    }

    /// The measured tool pose (m), when the message has one.
    pub fn feedback_pose(&self) -> Option<Pose> {
        self.feed_back.as_ref()?.cartesian.as_ref()?.to_pose()
    }

    /// The planned tool pose (m), when the message has one.
    pub fn planned_pose(&self) -> Option<Pose> {
        self.planned.as_ref()?.cartesian.as_ref()?.to_pose()
    }
}

/// Time step of the numerical derivative that turns joint speeds into the tool's speed: 1 ms
/// of motion, small enough that the curvature of the tool's path at the IRB 120's speeds
/// changes the result by well under 0.1 %, large enough that rounding does not matter.
const SPEED_STEP_S: f64 = 1e-3;

/// The robot's kinematics as EGM sees them: the rig, and which of its axes are the robot's.
/// Poses are the rig's tool frame (tool0 for the shipped IRB 120) in the robot's base frame:
/// the frame before the robot's first joint, which the external axes before it (a track, a
/// lift) carry. With `\Tool:=tool0 \WObj:=wobj0` and the correction frame EGM_FRAME_BASE at
/// no offset (docs/egm.md), that is the frame of EGMActPose's poses.
#[derive(Debug, Clone, PartialEq)]
pub struct EgmKinematics {
    pub rig: Rig,
    pub axes: EgmAxes,
}

impl EgmKinematics {
    /// The robot's base frame in the rig's base frame at `positions`.
    fn robot_base(&self, positions: &[f64]) -> DAffine3 {
        let first = self.axes.robot.first().copied().unwrap_or(0);
        self.rig.joints[..first]
            .iter()
            .zip(positions)
            .fold(DAffine3::IDENTITY, |frame, (joint, q)| {
                frame * joint.transform(*q)
            })
    }

    /// The tool's pose in the robot's base frame at `positions` (rig axes, rad and m).
    pub fn pose(&self, positions: &[f64]) -> Pose {
        let base = self.robot_base(positions);
        let tool = self.rig.forward(positions).unwrap_or(DAffine3::IDENTITY);
        Pose::from_affine(&(base.inverse() * tool))
    }

    /// The tool's speed at `positions` moving at `speeds`, as EgmCartesianSpeed carries it:
    /// linear mm/s then angular deg/s, in the robot's base frame.
    pub fn tool_speed(&self, positions: &[f64], speeds: &[f64]) -> [f64; 6] {
        let ahead: Vec<f64> = positions
            .iter()
            .zip(speeds)
            .map(|(q, v)| q + v * SPEED_STEP_S)
            .collect();
        let (now, next) = (self.pose(positions), self.pose(&ahead));
        let linear = (next.position - now.position) * (MM_PER_M / SPEED_STEP_S);
        let turn = next.orientation * now.orientation.conjugate();
        // The short way round: q and -q are the same rotation.
        let turn = if turn.w < 0.0 { -turn } else { turn };
        let (axis, angle) = turn.to_axis_angle();
        let angular = axis * (angle.to_degrees() / SPEED_STEP_S);
        [
            linear.x, linear.y, linear.z, angular.x, angular.y, angular.z,
        ]
    }
}

impl EgmSensor {
    /// A joint-mode correction: positions and speeds of every rig axis (rad, m; per s),
    /// sent as `axes` lays them out, in degrees (mm on linear axes).
    pub fn joint_correction(
        seqno: u32,
        tm_ms: u32,
        axes: &EgmAxes,
        positions: &[f64],
        speeds: &[f64],
    ) -> Self {
        let (joints, external) = axes.split(positions);
        let (joint_speeds, external_speeds) = axes.split(speeds);
        Self {
            header: Some(EgmHeader {
                seqno: Some(seqno),
                tm: Some(tm_ms),
                mtype: Some(MessageType::Correction as i32),
            }),
            planned: Some(EgmPlanned {
                joints: Some(joints),
                cartesian: None,
                external_joints: external,
                time: None,
            }),
            speed_ref: Some(EgmSpeedRef {
                joints: Some(joint_speeds),
                cartesians: None,
                external_joints: external_speeds,
            }),
        }
    }

    /// A pose-mode correction: the tool's pose at `positions` (rig axes, rad and m) in the
    /// robot's base frame, and its speed at `speeds`; the external axes as in joint mode.
    pub fn pose_correction(
        seqno: u32,
        tm_ms: u32,
        kinematics: &EgmKinematics,
        positions: &[f64],
        speeds: &[f64],
    ) -> Self {
        let (_, external) = kinematics.axes.split(positions);
        let (_, external_speeds) = kinematics.axes.split(speeds);
        Self {
            header: Some(EgmHeader {
                seqno: Some(seqno),
                tm: Some(tm_ms),
                mtype: Some(MessageType::Correction as i32),
            }),
            planned: Some(EgmPlanned {
                joints: None,
                cartesian: Some(EgmPose::from_pose(&kinematics.pose(positions))),
                external_joints: external,
                time: None,
            }),
            speed_ref: Some(EgmSpeedRef {
                joints: None,
                cartesians: Some(EgmCartesianSpeed {
                    value: kinematics.tool_speed(positions, speeds).to_vec(),
                }),
                external_joints: external_speeds,
            }),
        }
    }

    /// The commanded pose (m), when the message has one with a position and an orientation.
    pub fn planned_pose(&self) -> Option<Pose> {
        self.planned.as_ref()?.cartesian.as_ref()?.to_pose()
    }

    /// The commanded joint positions, degrees, when the message has them.
    pub fn planned_joints(&self) -> Option<&[f64]> {
        self.planned
            .as_ref()
            .and_then(|p| p.joints.as_ref())
            .map(|j| j.joints.as_slice())
    }

    /// The commanded external axis positions (degrees, mm), when the message has them.
    pub fn planned_external(&self) -> Option<&[f64]> {
        self.planned
            .as_ref()
            .and_then(|p| p.external_joints.as_ref())
            .map(|j| j.joints.as_slice())
    }

    /// The speed references, deg/s, when the message has them.
    pub fn speed_joints(&self) -> Option<&[f64]> {
        self.speed_ref
            .as_ref()
            .and_then(|p| p.joints.as_ref())
            .map(|j| j.joints.as_slice())
    }

    /// The external axes' speed references (deg/s, mm/s), when the message has them.
    pub fn speed_external(&self) -> Option<&[f64]> {
        self.speed_ref
            .as_ref()
            .and_then(|p| p.external_joints.as_ref())
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

#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum EgmAxesError {
    #[error("{0} is not a joint of the rig")]
    UnknownJoint(String),
    #[error("{0} is named twice")]
    Twice(String),
    #[error("{0} external axes: EGM carries at most {MAX_EXTERNAL_AXES}")]
    TooManyExternal(usize),
    #[error(
        "{0} robot joints left: EGM's joints are the robot's own, 1 to {MAX_ROBOT_JOINTS}; name the others as external axes"
    )]
    RobotJoints(usize),
}

/// Where each rig axis travels in EGM: the robot's joints (rig order) in `joints`, the
/// external axes (in the order named) in `externalJoints`, and each axis' unit.
#[derive(Debug, Clone, PartialEq)]
pub struct EgmAxes {
    robot: Vec<usize>,
    external: Vec<usize>,
    /// Per rig axis: wire units per SI unit (degrees a radian, mm a metre).
    scale: Vec<f64>,
}

impl EgmAxes {
    /// The layout for `rig` with `external` (joint names) as external axes; without a
    /// list, every joint before the rig's last six (the arm rides on the axes before it:
    /// a track, a lift, a positioner).
    pub fn new(rig: &Rig, external: Option<&[String]>) -> Result<Self, EgmAxesError> {
        let names: Vec<&str> = rig.joint_names().collect();
        let external: Vec<usize> = match external {
            Some(list) => {
                let mut indices = Vec::with_capacity(list.len());
                for name in list {
                    let index = names
                        .iter()
                        .position(|n| n == name)
                        .ok_or_else(|| EgmAxesError::UnknownJoint(name.clone()))?;
                    if indices.contains(&index) {
                        return Err(EgmAxesError::Twice(name.clone()));
                    }
                    indices.push(index);
                }
                indices
            }
            None => (0..names.len().saturating_sub(MAX_ROBOT_JOINTS)).collect(),
        };
        if external.len() > MAX_EXTERNAL_AXES {
            return Err(EgmAxesError::TooManyExternal(external.len()));
        }
        let robot: Vec<usize> = (0..names.len()).filter(|i| !external.contains(i)).collect();
        if robot.is_empty() || robot.len() > MAX_ROBOT_JOINTS {
            return Err(EgmAxesError::RobotJoints(robot.len()));
        }
        let scale = rig
            .joints
            .iter()
            .map(|j| match j.kind {
                JointKind::Revolute => 1f64.to_degrees(),
                JointKind::Prismatic => MM_PER_M,
            })
            .collect();
        Ok(Self {
            robot,
            external,
            scale,
        })
    }

    /// The rig's axes, robot joints and external axes together.
    pub fn dof(&self) -> usize {
        self.scale.len()
    }

    /// The rig axes that are external axes, in `externalJoints` order.
    pub fn external_indices(&self) -> &[usize] {
        &self.external
    }

    /// Rig-order values (rad, m) as EGM's joints and external joints (degrees, mm); no
    /// external joints when the rig has no external axes.
    pub fn split(&self, values: &[f64]) -> (EgmJoints, Option<EgmJoints>) {
        let wire = |indices: &[usize]| EgmJoints {
            joints: indices.iter().map(|&i| values[i] * self.scale[i]).collect(),
        };
        let external = (!self.external.is_empty()).then(|| wire(&self.external));
        (wire(&self.robot), external)
    }

    /// EGM's joints and external joints (degrees, mm) as rig-order values (rad, m);
    /// `None` unless there are as many of each as the layout has (extra values, such as a
    /// robot's unused seventh joint, are ignored).
    pub fn join(&self, joints: &[f64], external: Option<&[f64]>) -> Option<Vec<f64>> {
        let external = external.unwrap_or(&[]);
        if joints.len() < self.robot.len() || external.len() < self.external.len() {
            return None;
        }
        let mut values = vec![0.0; self.dof()];
        let sources = self.robot.iter().zip(joints);
        for (&axis, &wire) in sources.chain(self.external.iter().zip(external)) {
            values[axis] = wire / self.scale[axis];
        }
        Some(values)
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

    fn rig(name: &str) -> Rig {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("config")
            .join(name);
        crate::rig::load_rig(&path).expect("a shipped rig")
    }

    #[test]
    fn a_correction_carries_degrees_and_its_type() {
        let irb120 = rig("irb120.toml");
        let axes = EgmAxes::new(&irb120, None).expect("six robot joints");
        let mut positions = [0.0; 6];
        positions[0] = std::f64::consts::FRAC_PI_2;
        let mut speeds = [0.0; 6];
        speeds[0] = std::f64::consts::PI;
        let sensor = EgmSensor::joint_correction(9, 40, &axes, &positions, &speeds);
        let decoded = EgmSensor::decode(&sensor.encode_to_vec()[..]).expect("round trip");
        assert_eq!(decoded.message_type(), MessageType::Correction);
        assert!((decoded.planned_joints().expect("planned")[0] - 90.0).abs() < 1e-12);
        assert!((decoded.speed_joints().expect("speed")[0] - 180.0).abs() < 1e-12);
        assert_eq!(decoded.planned_external(), None, "no external axes");
    }

    #[test]
    fn the_painter_sends_its_base_and_lift_as_external_axes_in_mm_and_degrees() {
        let painter = rig("painter.toml");
        let axes = EgmAxes::new(&painter, None).expect("the last six are the robot's");
        assert_eq!(axes.external_indices(), &[0, 1, 2, 3]);
        // base_x 1.5 m, base_y -0.25 m, base_yaw 90 deg, lift 2 m; joint_1 45 deg.
        let mut values = vec![0.0; 10];
        values[..5].copy_from_slice(&[1.5, -0.25, std::f64::consts::FRAC_PI_2, 2.0, 0.5]);
        let (joints, external) = axes.split(&values);
        let external = external.expect("external joints");
        assert_eq!(external.joints.len(), 4);
        assert!((external.joints[0] - 1500.0).abs() < 1e-9);
        assert!((external.joints[1] + 250.0).abs() < 1e-9);
        assert!((external.joints[2] - 90.0).abs() < 1e-9);
        assert!((external.joints[3] - 2000.0).abs() < 1e-9);
        assert_eq!(joints.joints.len(), 6);
        assert!((joints.joints[0] - 0.5f64.to_degrees()).abs() < 1e-9);
        let back = axes
            .join(&joints.joints, Some(&external.joints))
            .expect("joins");
        for (b, v) in back.iter().zip(&values) {
            assert!((b - v).abs() < 1e-12);
        }
        assert_eq!(
            axes.join(&joints.joints, None),
            None,
            "external axes missing"
        );
        // Named in another order: externalJoints follows the list.
        let named: Vec<String> = ["lift", "base_x", "base_y", "base_yaw"]
            .map(String::from)
            .into();
        let axes = EgmAxes::new(&painter, Some(&named)).expect("valid list");
        assert_eq!(axes.external_indices(), &[3, 0, 1, 2]);
    }

    #[test]
    fn external_axes_are_refused_when_unknown_named_twice_or_leaving_too_many_joints() {
        let painter = rig("painter.toml");
        let names = |list: &[&str]| -> Vec<String> { list.iter().map(|s| s.to_string()).collect() };
        assert_eq!(
            EgmAxes::new(&painter, Some(&names(&["base_x", "track"]))),
            Err(EgmAxesError::UnknownJoint("track".into()))
        );
        assert_eq!(
            EgmAxes::new(&painter, Some(&names(&["base_x", "base_x"]))),
            Err(EgmAxesError::Twice("base_x".into()))
        );
        assert_eq!(
            EgmAxes::new(&painter, Some(&names(&["base_x"]))),
            Err(EgmAxesError::RobotJoints(9))
        );
    }
}
