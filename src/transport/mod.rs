//! The transports both sides of a link share: the SocketCAN socket, the serial line's
//! settings and the reconnect backoff, used by the bridge's links (`link`) and by the
//! twin's ports (`twin`) alike. One file per piece. This is a leaf beside `protocol`: it may use the protocol's frame
//! types, and must not import `link`, `twin` or anything above them, nor keep a session.

pub mod backoff;
pub mod can;
pub mod serial;

pub use backoff::{BACKOFF_INITIAL, BACKOFF_MAX, Backoff};
pub use can::{CanBus, SEND_PATIENCE, interface_mtu, interface_up};
pub use serial::SerialSettings;
