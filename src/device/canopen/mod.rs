//! CiA 402 drives over CANopen (docs/canopen.md): rigbridge as the NMT master, SYNC producer
//! and SDO client. The wire (`wire`: COB-IDs, objects, power states), the bridge's link
//! (`link`) and the twin's drives (`twin`).

use super::{Backend, LinkSpec};

mod link;
pub mod twin;
pub mod wire;

pub use link::{
    CanopenError, CanopenLink, CanopenSettings, HEARTBEAT_LOST_FACTOR, SETUP_PATIENCE,
    connect_canopen,
};

/// CiA 402 in [`super::BACKENDS`]: `canopen://`, and the twin's `--canopen`.
pub struct Canopen;

impl Backend for Canopen {
    fn schemes(&self) -> &'static [&'static str] {
        &["canopen"]
    }

    fn forms(&self) -> &'static str {
        "canopen://IFACE?nodes=1,2,...[&counts_per_turn=N]"
    }

    fn parse(&self, _scheme: &str, rest: &str) -> Result<LinkSpec, &'static str> {
        parse_canopen(rest)
    }

    fn twin_flags(&self) -> &'static [&'static str] {
        &["--canopen"]
    }

    fn twin_log_target(&self) -> &'static str {
        concat!(module_path!(), "::twin")
    }
}

/// `IFACE?nodes=1,2,...&counts_per_turn=N`: nodes required (one per axis, in axis order).
fn parse_canopen(rest: &str) -> Result<LinkSpec, &'static str> {
    let (interface, query) = rest.split_once('?').unwrap_or((rest, ""));
    if interface.is_empty() || interface.contains('/') {
        return Err("needs an interface name such as vcan0");
    }
    let mut nodes = None;
    let mut counts_per_turn = None;
    for option in query.split('&').filter(|o| !o.is_empty()) {
        match option.split_once('=') {
            Some(("nodes", list)) => {
                let parsed: Result<Vec<u8>, _> = list.split(',').map(str::parse::<u8>).collect();
                match parsed {
                    Ok(list) if list.iter().all(|id| (1..=127).contains(id)) => nodes = Some(list),
                    _ => {
                        return Err(
                            "nodes must be CANopen node ids from 1 to 127, such as nodes=1,2,3",
                        );
                    }
                }
            }
            Some(("counts_per_turn", n)) => match n.parse::<u32>() {
                Ok(n) if n > 0 => counts_per_turn = Some(n),
                _ => return Err("counts_per_turn must be a whole number above 0"),
            },
            _ => return Err("the options are nodes=1,2,... and counts_per_turn=N"),
        }
    }
    let nodes = nodes.ok_or("needs nodes=1,2,... (one drive's node id per axis, in axis order)")?;
    Ok(LinkSpec::Canopen {
        interface: interface.to_string(),
        nodes,
        counts_per_turn,
    })
}
