//! Our own protocol (docs/protocol.md, versions 2 and 3) to a controller or `rigbridge twin`:
//! the bridge's links over TCP (`tcp`), a serial line (`serial`) and SocketCAN (`can`), and
//! the twin's CAN port (`can_port`). The messages and their byte and CAN encodings are the
//! shared `protocol` module's (every link and the in-process twin speak them), and the
//! session rules both ends keep are `link::BridgeSession` and `twin::server`.

use super::{Backend, LinkSpec};

mod can;
pub mod can_port;
mod serial;
mod tcp;

pub use can::connect_can;
pub use serial::connect_serial;
pub use tcp::{TcpSettings, connect_tcp};

/// A serial line's baud rate when the address gives none.
pub const DEFAULT_BAUD: u32 = 115_200;

/// Our protocol in [`super::BACKENDS`]: `tcp://`, `serial://` and `can://`, and the twin's transports.
pub struct Ours;

impl Backend for Ours {
    fn schemes(&self) -> &'static [&'static str] {
        &["tcp", "serial", "can"]
    }

    fn forms(&self) -> &'static str {
        "tcp://HOST:PORT, serial:///dev/PATH?baud=N, can://IFACE"
    }

    fn parse(&self, scheme: &str, rest: &str) -> Result<LinkSpec, &'static str> {
        match scheme {
            "tcp" => parse_tcp(rest),
            "serial" => parse_serial(rest),
            "can" => parse_can(rest),
            _ => Err("unknown scheme"),
        }
    }

    fn twin_flags(&self) -> &'static [&'static str] {
        &["--listen", "--serial", "--pty", "--can"]
    }

    fn twin_log_target(&self) -> &'static str {
        concat!(module_path!(), "::can_port")
    }
}

/// `HOST:PORT`.
fn parse_tcp(address: &str) -> Result<LinkSpec, &'static str> {
    let (host, port) = address.rsplit_once(':').ok_or("no port")?;
    if host.is_empty() || port.parse::<u16>().is_err() {
        return Err("needs HOST:PORT with a port from 0 to 65535");
    }
    Ok(LinkSpec::Tcp {
        address: address.to_string(),
    })
}

/// `/dev/PATH?baud=N`: baud optional.
fn parse_serial(rest: &str) -> Result<LinkSpec, &'static str> {
    let (path, query) = rest.split_once('?').unwrap_or((rest, ""));
    if !path.starts_with('/') {
        return Err("needs an absolute device path");
    }
    let baud = match query.strip_prefix("baud=") {
        Some(b) => b.parse().map_err(|_| "baud must be a whole number")?,
        None if query.is_empty() => DEFAULT_BAUD,
        None => return Err("the only option is baud=N"),
    };
    Ok(LinkSpec::Serial {
        path: path.to_string(),
        baud,
        dynamixel: None,
    })
}

/// `IFACE`: a SocketCAN interface's name.
fn parse_can(interface: &str) -> Result<LinkSpec, &'static str> {
    if interface.is_empty() || interface.contains('/') {
        return Err("needs an interface name such as vcan0");
    }
    Ok(LinkSpec::Can {
        interface: interface.to_string(),
    })
}
