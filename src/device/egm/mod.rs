//! ABB Externally Guided Motion (docs/egm.md): rigbridge as the sensor. The wire codec
//! (`wire`: the EgmRobot and EgmSensor messages, the axis layout), the bridge's link
//! (`link`) and what it takes from the network (`guard`), and the twin that plays the robot
//! controller (`twin`).

use super::{Backend, LinkSpec};

mod guard;
mod link;
pub mod twin;
pub mod wire;

pub use guard::{JUMP_SLACK, LOCK_RELEASE};
pub use link::{
    EgmClock, EgmLink, EgmLinkSettings, EgmState, LINK_SILENCE, PLAYOUT_DEPTH, bind_egm,
};

/// EGM in [`super::BACKENDS`]: `egm://`, and the twin's `--egm`.
pub struct Egm;

impl Backend for Egm {
    fn schemes(&self) -> &'static [&'static str] {
        &["egm"]
    }

    fn forms(&self) -> &'static str {
        "egm://ADDR:PORT[?robot=HOST:PORT&mode=joint|pose]"
    }

    fn parse(&self, _scheme: &str, rest: &str) -> Result<LinkSpec, &'static str> {
        parse_egm(rest)
    }

    fn twin_flags(&self) -> &'static [&'static str] {
        &["--egm"]
    }

    fn twin_log_target(&self) -> &'static str {
        concat!(module_path!(), "::twin")
    }
}

/// `ADDR:PORT?robot=HOST:PORT&mode=joint|pose`: the address to bind, the robot's (optional)
/// and what is streamed (joints when absent). Both addresses are IP addresses: a name would
/// be resolved to whatever a name server says.
fn parse_egm(rest: &str) -> Result<LinkSpec, &'static str> {
    use wire::EgmMode;
    let (address, query) = rest.split_once('?').unwrap_or((rest, ""));
    if address.parse::<std::net::SocketAddr>().is_err() {
        return Err("needs an IP address and port to bind, such as 0.0.0.0:6510");
    }
    let mut robot = None;
    let mut mode = EgmMode::Joint;
    for option in query.split('&').filter(|o| !o.is_empty()) {
        match option.split_once('=') {
            Some(("robot", value)) => robot = Some(value.parse().map_err(|_| {
                "robot= needs the robot controller's IP address and the port it sends from, such as robot=192.168.125.1:6510"
            })?),
            Some(("mode", "joint")) => mode = EgmMode::Joint,
            Some(("mode", "pose")) => mode = EgmMode::Pose,
            Some(("mode", _)) => return Err("mode= is joint (EGMActJoint) or pose (EGMActPose)"),
            _ => return Err("the options are robot=HOST:PORT and mode=joint|pose"),
        }
    }
    Ok(LinkSpec::Egm {
        address: address.to_string(),
        robot,
        mode,
    })
}
