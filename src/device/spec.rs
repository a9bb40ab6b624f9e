//! Link addresses as users write them: `loopback`, `tcp://HOST:PORT`,
//! `serial:///dev/PATH?baud=N`, `can://IFACE`, `egm://ADDR:PORT[?robot=HOST:PORT&mode=joint|pose]` (rigbridge
//! as an ABB EGM sensor, bound to ADDR:PORT, answering only the robot at HOST:PORT when
//! named), `dynamixel:///dev/PATH?baud=N&ids=1,2,...` (rigbridge as
//! the Dynamixel Protocol 2.0 master of one servo per axis, ids in axis order),
//! `canopen://IFACE?nodes=1,2,...&counts_per_turn=N` (rigbridge as the CANopen master of one
//! CiA 402 drive per axis, node ids in axis order). Each device protocol in
//! [`super::BACKENDS`] parses the addresses of its own schemes; this file owns the
//! dispatch by scheme and the one list of forms.

use super::BACKENDS;
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
/// them: `loopback` and each backend's forms, from the one list, so a new protocol cannot
/// be left out of either.
pub fn link_forms() -> String {
    let mut forms = vec!["loopback"];
    forms.extend(BACKENDS.iter().map(|backend| backend.forms()));
    forms.join(", ")
}

#[derive(Debug, Clone, PartialEq, Eq, Error)]
#[error("link `{text}`: {reason} (expected {forms})", forms = link_forms())]
pub struct LinkSpecError {
    pub text: String,
    pub reason: String,
}

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
        let (scheme, rest) = text
            .split_once("://")
            .ok_or_else(|| fail("unknown scheme"))?;
        let backend = BACKENDS
            .iter()
            .find(|backend| backend.schemes().contains(&scheme))
            .ok_or_else(|| fail("unknown scheme"))?;
        backend.parse(scheme, rest).map_err(fail)
    }
}

impl LinkSpec {
    /// The device or address the link occupies, whatever its options (a serial port is the
    /// same port at any baud rate); `None` for the in-process twin, which every cell has
    /// its own of.
    pub fn occupied_resource(&self) -> Option<String> {
        match self {
            LinkSpec::Loopback => None,
            LinkSpec::Tcp { address } => Some(format!("tcp://{address}")),
            LinkSpec::Serial { path, .. } => Some(format!("serial://{path}")),
            LinkSpec::Can { interface } => Some(format!("can://{interface}")),
            LinkSpec::Egm { address, .. } => Some(format!("egm://{address}")),
            // One SYNC producer and NMT master a bus: the interface is the resource.
            LinkSpec::Canopen { interface, .. } => Some(format!("can://{interface}")),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::device::dynamixel::DYNAMIXEL_DEFAULT_BAUD;
    use crate::device::ours::DEFAULT_BAUD;

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
