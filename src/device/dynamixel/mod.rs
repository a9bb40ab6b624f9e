//! Dynamixel Protocol 2.0 servos (docs/dynamixel.md): rigbridge as the bus master. The wire
//! codec (`wire`: packets, the control table, the line's time budget), the bridge's link
//! (`link`) and the twin's servos (`twin`).

mod link;
pub mod twin;
pub mod wire;

pub use link::{
    DynamixelError, DynamixelLink, DynamixelSettings, LOST_AFTER_CYCLES, connect_dynamixel,
    operating_mode,
};
