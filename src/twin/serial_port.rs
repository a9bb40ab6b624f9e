//! The twin's serial ports: a real device (`--serial PATH`), always attached, where link
//! loss shows as silence and the watchdog holds; and a pseudo-terminal (`--pty`), whose
//! master side reads EIO while no one holds the slave open: that is how a peer arriving
//! and leaving is seen.

use super::server::{ControllerPort, DETACHED_POLL};
use crate::transport::SerialSettings;
use serialport::{SerialPort, TTYPort};
use std::io::ErrorKind;
use std::time::Duration;

pub struct SerialControllerPort {
    port: Box<dyn SerialPort>,
    description: String,
    /// Pty only: whether a peer holds the slave side open.
    peer: Option<bool>,
}

impl SerialControllerPort {
    pub fn open(settings: &SerialSettings) -> serialport::Result<Self> {
        Ok(Self {
            port: settings.open()?,
            description: format!("serial://{}?baud={}", settings.path, settings.baud),
            peer: None,
        })
    }

    /// Opens a pty pair, keeps the master, and returns the slave's path for the peer.
    pub fn pty() -> serialport::Result<(Self, String)> {
        let (master, slave) = TTYPort::pair()?;
        let path = slave.name().ok_or_else(|| {
            serialport::Error::new(serialport::ErrorKind::Unknown, "pty has no slave path")
        })?;
        // The slave keeps its raw termios after this handle closes; the peer reopens it.
        drop(slave);
        Ok((
            Self {
                port: Box::new(master),
                description: format!("pty {path}"),
                peer: Some(false),
            },
            path,
        ))
    }
}

fn is_hangup(error: &std::io::Error) -> bool {
    error.raw_os_error() == Some(libc::EIO) || error.kind() == ErrorKind::BrokenPipe
}

impl ControllerPort for SerialControllerPort {
    fn attached(&mut self) -> bool {
        self.peer.unwrap_or(true)
    }

    fn read_within(&mut self, buffer: &mut [u8], timeout: Duration) -> std::io::Result<usize> {
        self.port
            .set_timeout(timeout.max(Duration::from_micros(100)))?;
        match self.port.read(buffer) {
            Ok(n) => {
                if self.peer == Some(false) && n > 0 {
                    self.peer = Some(true);
                }
                Ok(n)
            }
            Err(e) if e.kind() == ErrorKind::TimedOut || e.kind() == ErrorKind::WouldBlock => Ok(0),
            Err(e) if is_hangup(&e) && self.peer.is_some() => {
                std::thread::sleep(timeout.min(DETACHED_POLL));
                if self.peer == Some(true) {
                    self.peer = Some(false);
                    return Err(std::io::Error::new(
                        ErrorKind::BrokenPipe,
                        "peer closed the pty",
                    ));
                }
                Ok(0)
            }
            Err(e) => Err(e),
        }
    }

    fn write_frame(&mut self, frame: &[u8]) -> std::io::Result<()> {
        match self.port.write_all(frame) {
            Err(e) if is_hangup(&e) && self.peer.is_some() => Ok(()),
            other => other,
        }
    }

    fn detach(&mut self) {
        if self.peer.is_some() {
            self.peer = Some(false);
        }
    }

    fn describe(&self) -> String {
        self.description.clone()
    }
}
