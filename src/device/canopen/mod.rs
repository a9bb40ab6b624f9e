//! CiA 402 drives over CANopen (docs/canopen.md): rigbridge as the NMT master, SYNC producer
//! and SDO client. The wire (`wire`: COB-IDs, objects, power states), the bridge's link
//! (`link`) and the twin's drives (`twin`).

mod link;
pub mod twin;
pub mod wire;

pub use link::{
    CanopenError, CanopenLink, CanopenSettings, HEARTBEAT_LOST_FACTOR, SETUP_PATIENCE,
    connect_canopen,
};
