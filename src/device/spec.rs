//! Link addresses as users write them: `loopback`, `tcp://HOST:PORT`,
//! `serial:///dev/PATH?baud=N`, `can://IFACE`, `egm://ADDR:PORT[?robot=HOST:PORT&mode=joint|pose]` (rigbridge
//! as an ABB EGM sensor, bound to ADDR:PORT, answering only the robot at HOST:PORT when
//! named), `dynamixel:///dev/PATH?baud=N&ids=1,2,...` (rigbridge as
//! the Dynamixel Protocol 2.0 master of one servo per axis, ids in axis order),
//! `canopen://IFACE?nodes=1,2,...&counts_per_turn=N` (rigbridge as the CANopen master of one
//! CiA 402 drive per axis, node ids in axis order).

use std::str::FromStr;
use thiserror::Error;

#[derive(Debug, Clone, PartialEq, Eq)]
pub enum LinkSpec {
    Loopback,
    Tcp {
        address: String,
    },
    /// A serial line: rigbridge's own protocol, or with `dynamixel` the servo ids (in axis
    /// order) of a Dynamixel Protocol 2.0 bus (the same device either way).
    Serial {
        path: String,
        baud: u32,
        dynamixel: Option<Vec<u8>>,
    },
    Can {
        interface: String,
    },
    /// The UDP address to bind, such as `0.0.0.0:6510`, and the robot controller's address
    /// and port (`?robot=`), the only source the session takes; without it, the first robot
    /// to send is (docs/egm.md); `?mode=pose` streams tool poses (RAPID's EGMActPose)
    /// rather than joints.
    Egm {
        address: String,
        robot: Option<std::net::SocketAddr>,
        mode: crate::device::egm::wire::EgmMode,
    },
    /// CiA 402 drives on a SocketCAN interface: node ids in axis order, and the counts a
    /// turn of every axis (when given; `[canopen]` in the config may set them per axis).
    Canopen {
        interface: String,
        nodes: Vec<u8>,
        counts_per_turn: Option<u32>,
    },
}

/// Every link address form, as the command line's help and a bad address's error list
/// them: one text, so a new scheme cannot be left out of either.
pub const LINK_FORMS: &str = "loopback, tcp://HOST:PORT, serial:///dev/PATH?baud=N, can://IFACE, egm://ADDR:PORT[?robot=HOST:PORT&mode=joint|pose], dynamixel:///dev/PATH?baud=N&ids=1,2,... or canopen://IFACE?nodes=1,2,...[&counts_per_turn=N]";

#[derive(Debug, Clone, PartialEq, Eq, Error)]
#[error("link `{text}`: {reason} (expected {LINK_FORMS})")]
pub struct LinkSpecError {
    pub text: String,
    pub reason: String,
}

pub const DEFAULT_BAUD: u32 = 115_200;
/// A Dynamixel X-series servo's factory baud rate (XM430 e-manual, "Baud Rate (8)").
pub const DYNAMIXEL_DEFAULT_BAUD: u32 = 57_600;

impl FromStr for LinkSpec {
    type Err = LinkSpecError;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        let fail = |reason: &str| LinkSpecError {
            text: text.to_string(),
            reason: reason.to_string(),
        };
        if text == "loopback" {
            return Ok(LinkSpec::Loopback);
        }
        if let Some(address) = text.strip_prefix("tcp://") {
            let (host, port) = address.rsplit_once(':').ok_or_else(|| fail("no port"))?;
            if host.is_empty() || port.parse::<u16>().is_err() {
                return Err(fail("needs HOST:PORT with a port from 0 to 65535"));
            }
            return Ok(LinkSpec::Tcp {
                address: address.to_string(),
            });
        }
        if let Some(rest) = text.strip_prefix("serial://") {
            let (path, query) = rest.split_once('?').unwrap_or((rest, ""));
            if !path.starts_with('/') {
                return Err(fail("needs an absolute device path"));
            }
            let baud = match query.strip_prefix("baud=") {
                Some(b) => b.parse().map_err(|_| fail("baud must be a whole number"))?,
                None if query.is_empty() => DEFAULT_BAUD,
                None => return Err(fail("the only option is baud=N")),
            };
            return Ok(LinkSpec::Serial {
                path: path.to_string(),
                baud,
                dynamixel: None,
            });
        }
        if let Some(rest) = text.strip_prefix("dynamixel://") {
            return parse_dynamixel(rest).map_err(fail);
        }
        if let Some(rest) = text.strip_prefix("canopen://") {
            return parse_canopen(rest).map_err(fail);
        }
        if let Some(rest) = text.strip_prefix("egm://") {
            return parse_egm(rest).map_err(fail);
        }
        if let Some(interface) = text.strip_prefix("can://") {
            if interface.is_empty() || interface.contains('/') {
                return Err(fail("needs an interface name such as vcan0"));
            }
            return Ok(LinkSpec::Can {
                interface: interface.to_string(),
            });
        }
        Err(fail("unknown scheme"))
    }
}

/// `ADDR:PORT?robot=HOST:PORT&mode=joint|pose`: the address to bind, the robot's (optional)
/// and what is streamed (joints when absent). Both addresses are IP addresses: a name would
/// be resolved to whatever a name server says.
fn parse_egm(rest: &str) -> Result<LinkSpec, &'static str> {
    use crate::device::egm::wire::EgmMode;
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

/// `PATH?baud=N&ids=1,2,...`: ids required (one per axis, in axis order), baud optional.
fn parse_dynamixel(rest: &str) -> Result<LinkSpec, &'static str> {
    let (path, query) = rest.split_once('?').unwrap_or((rest, ""));
    if !path.starts_with('/') {
        return Err("needs an absolute device path");
    }
    let mut baud = DYNAMIXEL_DEFAULT_BAUD;
    let mut ids = None;
    for option in query.split('&').filter(|o| !o.is_empty()) {
        match option.split_once('=') {
            Some(("baud", b)) => {
                baud = b.parse().map_err(|_| "baud must be a whole number")?;
            }
            Some(("ids", list)) => {
                let parsed: Result<Vec<u8>, _> = list.split(',').map(str::parse::<u8>).collect();
                match parsed {
                    Ok(list)
                        if list
                            .iter()
                            .all(|id| *id <= crate::device::dynamixel::wire::MAX_SERVO_ID) =>
                    {
                        ids = Some(list)
                    }
                    _ => {
                        return Err("ids must be servo ids from 0 to 252, such as ids=1,2,3");
                    }
                }
            }
            _ => return Err("the options are baud=N and ids=1,2,..."),
        }
    }
    let ids = ids.ok_or("needs ids=1,2,... (one servo id per axis, in axis order)")?;
    Ok(LinkSpec::Serial {
        path: path.to_string(),
        baud,
        dynamixel: Some(ids),
    })
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_every_scheme_and_names_bad_input() {
        assert_eq!("loopback".parse(), Ok(LinkSpec::Loopback));
        assert_eq!(
            "tcp://127.0.0.1:7000".parse(),
            Ok(LinkSpec::Tcp {
                address: "127.0.0.1:7000".into()
            })
        );
        assert_eq!(
            "serial:///dev/ttyUSB0?baud=1000000".parse(),
            Ok(LinkSpec::Serial {
                path: "/dev/ttyUSB0".into(),
                baud: 1_000_000,
                dynamixel: None
            })
        );
        assert_eq!(
            "serial:///dev/pts/3".parse(),
            Ok(LinkSpec::Serial {
                path: "/dev/pts/3".into(),
                baud: DEFAULT_BAUD,
                dynamixel: None
            })
        );
        assert_eq!(
            "dynamixel:///dev/ttyUSB0?baud=1000000&ids=1,2,3,4,5,6".parse(),
            Ok(LinkSpec::Serial {
                path: "/dev/ttyUSB0".into(),
                baud: 1_000_000,
                dynamixel: Some(vec![1, 2, 3, 4, 5, 6])
            })
        );
        assert_eq!(
            "dynamixel:///dev/pts/4?ids=7".parse(),
            Ok(LinkSpec::Serial {
                path: "/dev/pts/4".into(),
                baud: DYNAMIXEL_DEFAULT_BAUD,
                dynamixel: Some(vec![7])
            })
        );
        assert_eq!(
            "can://vcan0".parse(),
            Ok(LinkSpec::Can {
                interface: "vcan0".into()
            })
        );
        assert_eq!(
            "egm://0.0.0.0:6510".parse(),
            Ok(LinkSpec::Egm {
                address: "0.0.0.0:6510".into(),
                robot: None,
                mode: crate::device::egm::wire::EgmMode::Joint,
            })
        );
        assert_eq!(
            "egm://0.0.0.0:6510?mode=pose&robot=192.168.125.1:6511".parse(),
            Ok(LinkSpec::Egm {
                address: "0.0.0.0:6510".into(),
                robot: Some("192.168.125.1:6511".parse().expect("an address")),
                mode: crate::device::egm::wire::EgmMode::Pose,
            })
        );
        assert_eq!(
            "egm://0.0.0.0:6510?robot=192.168.125.1:6511".parse(),
            Ok(LinkSpec::Egm {
                address: "0.0.0.0:6510".into(),
                robot: Some("192.168.125.1:6511".parse().expect("an address")),
                mode: crate::device::egm::wire::EgmMode::Joint,
            })
        );
        assert_eq!(
            "canopen://vcan0?nodes=1,2,3,4,5,6&counts_per_turn=1048576".parse(),
            Ok(LinkSpec::Canopen {
                interface: "vcan0".into(),
                nodes: vec![1, 2, 3, 4, 5, 6],
                counts_per_turn: Some(1_048_576)
            })
        );
        assert_eq!(
            "canopen://can1?nodes=9".parse(),
            Ok(LinkSpec::Canopen {
                interface: "can1".into(),
                nodes: vec![9],
                counts_per_turn: None
            })
        );
        for bad in [
            "canopen://vcan0",
            "canopen://vcan0?nodes=0,1",
            "canopen://vcan0?nodes=1,128",
            "canopen://?nodes=1",
            "canopen://vcan0?nodes=1&counts_per_turn=0",
            "canopen://vcan0?nodes=1&bitrate=500000",
            "egm://robot:6510",
            "egm://127.0.0.1",
            "egm://0.0.0.0:6510?robot=controller:6511",
            "egm://0.0.0.0:6510?robot=192.168.125.1",
            "egm://0.0.0.0:6510?peer=192.168.125.1:6511",
            "egm://0.0.0.0:6510?mode=cartesian",
            "tcp://nohost",
            "tcp://h:99999",
            "serial://dev/x",
            "udp://x:1",
            "can://",
            "dynamixel:///dev/ttyUSB0",
            "dynamixel:///dev/ttyUSB0?ids=1,300",
            "dynamixel://ttyUSB0?ids=1",
            "dynamixel:///dev/ttyUSB0?ids=1&parity=odd",
        ] {
            let error = bad.parse::<LinkSpec>().unwrap_err();
            assert!(error.to_string().contains(bad), "{error}");
        }
    }
}
