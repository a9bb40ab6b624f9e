//! Our own protocol (docs/protocol.md, versions 2 and 3) to a controller or `rigbridge twin`:
//! the bridge's links over TCP (`tcp`), a serial line (`serial`) and SocketCAN (`can`), and
//! the twin's CAN port (`can_port`). The messages and their byte and CAN encodings are the
//! shared `protocol` module's (every link and the in-process twin speak them), and the
//! session rules both ends keep are `link::BridgeSession` and `twin::server`.

mod can;
pub mod can_port;
mod serial;
mod tcp;

pub use can::connect_can;
pub use serial::connect_serial;
pub use tcp::{TcpSettings, connect_tcp};
