//! Link addresses as users write them: `loopback`, `tcp://HOST:PORT`,
//! `serial:///dev/PATH?baud=N`, `can://IFACE`, `egm://ADDR:PORT` (rigbridge as an ABB EGM
//! sensor, bound to ADDR:PORT).

use std::str::FromStr;
use thiserror::Error;

#[derive(Debug, Clone, PartialEq, Eq)]
pub enum LinkSpec {
    Loopback,
    Tcp {
        address: String,
    },
    Serial {
        path: String,
        baud: u32,
    },
    Can {
        interface: String,
    },
    /// The UDP address to bind, such as `0.0.0.0:6510`.
    Egm {
        address: String,
    },
}

#[derive(Debug, Clone, PartialEq, Eq, Error)]
#[error(
    "link `{text}`: {reason} (expected loopback, tcp://HOST:PORT, serial:///dev/PATH?baud=N, can://IFACE or egm://ADDR:PORT)"
)]
pub struct LinkSpecError {
    pub text: String,
    pub reason: String,
}

pub const DEFAULT_BAUD: u32 = 115_200;

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
            });
        }
        if let Some(address) = text.strip_prefix("egm://") {
            if address.parse::<std::net::SocketAddr>().is_err() {
                return Err(fail(
                    "needs an IP address and port to bind, such as 0.0.0.0:6510",
                ));
            }
            return Ok(LinkSpec::Egm {
                address: address.to_string(),
            });
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
                baud: 1_000_000
            })
        );
        assert_eq!(
            "serial:///dev/pts/3".parse(),
            Ok(LinkSpec::Serial {
                path: "/dev/pts/3".into(),
                baud: DEFAULT_BAUD
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
                address: "0.0.0.0:6510".into()
            })
        );
        for bad in [
            "egm://robot:6510",
            "egm://127.0.0.1",
            "tcp://nohost",
            "tcp://h:99999",
            "serial://dev/x",
            "udp://x:1",
            "can://",
        ] {
            let error = bad.parse::<LinkSpec>().unwrap_err();
            assert!(error.to_string().contains(bad), "{error}");
        }
    }
}
