//! The device protocols rigbridge speaks to a controller, one folder each: our own protocol
//! over TCP, serial and CAN (`ours`), ABB EGM (`egm`), CiA 402 over CANopen (`canopen`) and
//! Dynamixel Protocol 2.0 (`dynamixel`). A folder holds its protocol's wire codec, its link
//! (the bridge's side), its twin side (the device played for tests and `rigbridge twin`)
//! and their settings; what the links of several protocols share is here too (`bus`, the
//! I/O thread of the links that master a bus of devices) and the link addresses users
//! write (`spec`).
//!
//! It sits between the streamer and the shared link and twin machinery: it may import
//! `link` (the `Link` trait, the session state machine, the channel), `twin` (the strict
//! controller model and its port and session over a byte transport), `transport` and
//! `protocol`; none of those imports it.

mod bus;
pub mod canopen;
pub mod dynamixel;
pub mod egm;
pub mod ours;
mod spec;

pub use spec::{DEFAULT_BAUD, DYNAMIXEL_DEFAULT_BAUD, LINK_FORMS, LinkSpec, LinkSpecError};
