//! ABB Externally Guided Motion (docs/egm.md): rigbridge as the sensor. The wire codec
//! (`wire`: the EgmRobot and EgmSensor messages, the axis layout), the bridge's link
//! (`link`) and what it takes from the network (`guard`), and the twin that plays the robot
//! controller (`twin`).

mod guard;
mod link;
pub mod twin;
pub mod wire;

pub use guard::{JUMP_SLACK, LOCK_RELEASE};
pub use link::{
    EgmClock, EgmLink, EgmLinkSettings, EgmState, LINK_SILENCE, PLAYOUT_DEPTH, bind_egm,
};
