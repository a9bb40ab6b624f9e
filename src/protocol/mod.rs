//! The messages between rigbridge and a controller (real, or the twin), independent of how
//! they travel. Fixed-size and `Copy`, so the streaming cycle moves them without allocating.
//! The byte encoding for serial, TCP and CAN lives beside this (see `docs/protocol.md`); the
//! wire codecs of the other device protocols are in their `device` folders. Both ends
//! import this module; it imports neither (`link`, `twin`), and owns bytes only: no
//! sessions, no transports.

pub mod can;
pub mod codec;
pub mod io;

pub use can::{CanAssembler, CanCounters, CanMapping, CanPayload, CanSender, can_frames};
pub use codec::{
    DecodeError, DecoderCounters, EncodeError, FaultReport, FrameDecoder, Hello, Message,
    PROTOCOL_VERSION_IO, cycle_us, decode_body, encode_body, encode_frame,
};
pub use io::{IoKind, IoMessage, IoResult, IoState, io_name_ok};

/// The most axes one rig may stream (the arm with its base, the sloth's bones and body).
pub const MAX_AXES: usize = 32;

/// Up to [`MAX_AXES`] values, one per axis, in the rig's joint order.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AxisValues {
    len: u8,
    values: [f64; MAX_AXES],
}

impl AxisValues {
    /// `None` when there are more than [`MAX_AXES`] values.
    pub fn from_slice(values: &[f64]) -> Option<Self> {
        if values.len() > MAX_AXES {
            return None;
        }
        let mut out = Self::zeros(values.len());
        out.values[..values.len()].copy_from_slice(values);
        Some(out)
    }

    /// `len` zeros (capped at [`MAX_AXES`]).
    pub fn zeros(len: usize) -> Self {
        Self {
            len: len.min(MAX_AXES) as u8,
            values: [0.0; MAX_AXES],
        }
    }

    pub fn as_slice(&self) -> &[f64] {
        &self.values[..usize::from(self.len)]
    }

    pub fn as_mut_slice(&mut self) -> &mut [f64] {
        &mut self.values[..usize::from(self.len)]
    }

    pub fn len(&self) -> usize {
        usize::from(self.len)
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }
}

/// One cycle's command: where each axis should be at time `t`, and how fast it moves there.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct JointTarget {
    pub seq: u32,
    /// Time since the job started (the wire carries whole microseconds).
    pub t: std::time::Duration,
    /// rad (revolute) or m (prismatic).
    pub positions: AxisValues,
    /// rad/s or m/s.
    pub velocities: AxisValues,
}

/// What the bridge may send a controller.
// A target is large next to the other variants, but boxing it would allocate every cycle.
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Command {
    Target(JointTarget),
    /// Decelerate within the limits and hold.
    Stop,
    /// Halt at once and refuse targets until reset.
    EStop,
    Heartbeat,
    /// Clear a latched fault (e-stop included) once its cause is gone.
    Reset,
}

/// Why a controller refuses to move.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Fault {
    /// A target outside the axis's position limits (0-based axis index).
    OutsideLimits {
        axis: u8,
    },
    /// A target step faster than the axis's max speed.
    OverSpeed {
        axis: u8,
    },
    /// A target with the wrong number of axes.
    AxisCount {
        expected: u8,
        got: u8,
    },
    EStop,
    /// A target's velocity change or position second difference above the axis's max
    /// acceleration (0-based axis index).
    OverAcceleration {
        axis: u8,
    },
    /// Bound to another bridge: sent to a second one before the controller closes it.
    /// Only ever in a Fault message, never latched.
    Busy,
    /// The axis's drive reported an error of its own (a servo's status error or hardware
    /// error: Dynamixel, docs/dynamixel.md), 0-based axis index.
    Drive {
        axis: u8,
    },
    /// Two bodies of the cell touched (the twin's collision detection, as a controller's
    /// stops the arm): which, and how deep, are in the Fault notice's text.
    Collision,
}

impl std::fmt::Display for Fault {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Fault::OutsideLimits { axis } => {
                write!(f, "outside limits (axis {})", u32::from(*axis) + 1)
            }
            Fault::OverSpeed { axis } => write!(f, "over speed (axis {})", u32::from(*axis) + 1),
            Fault::AxisCount { expected, got } => {
                write!(
                    f,
                    "axis count (controller has {expected}, target had {got})"
                )
            }
            Fault::EStop => write!(f, "e-stop"),
            Fault::OverAcceleration { axis } => {
                write!(f, "over acceleration (axis {})", u32::from(*axis) + 1)
            }
            Fault::Busy => write!(f, "busy with another bridge"),
            Fault::Drive { axis } => write!(f, "drive error (axis {})", u32::from(*axis) + 1),
            Fault::Collision => write!(f, "collision"),
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ControllerStatus {
    Ok,
    /// No target within the watchdog, or a stop: at rest, waiting.
    Holding,
    Fault(Fault),
}

/// The controller's answer each cycle.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Feedback {
    /// The sequence number of the last target the controller accepted.
    pub seq: u32,
    /// Measured axis positions.
    pub positions: AxisValues,
    pub status: ControllerStatus,
}
