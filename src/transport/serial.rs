//! The serial line's settings ([`SerialSettings`]) both sides of a serial link use: the
//! bridge's serial and Dynamixel links and the twin's serial port. Device, baud, parity,
//! stop bits and flow control, and how a port is opened with them (8 data bits, a short
//! read timeout).
//!
//! It owns the settings and the open only: it must not frame, read or write (its callers
//! do).

use serialport::{DataBits, FlowControl, Parity, SerialPort, StopBits};
use std::time::Duration;

#[derive(Debug, Clone, PartialEq)]
pub struct SerialSettings {
    pub path: String,
    pub baud: u32,
    pub parity: Parity,
    pub stop_bits: StopBits,
    pub flow_control: FlowControl,
}

impl SerialSettings {
    /// 8N1, no flow control.
    pub fn new(path: impl Into<String>, baud: u32) -> Self {
        Self {
            path: path.into(),
            baud,
            parity: Parity::None,
            stop_bits: StopBits::One,
            flow_control: FlowControl::None,
        }
    }

    pub fn open(&self) -> serialport::Result<Box<dyn SerialPort>> {
        serialport::new(&self.path, self.baud)
            .data_bits(DataBits::Eight)
            .parity(self.parity)
            .stop_bits(self.stop_bits)
            .flow_control(self.flow_control)
            .timeout(READ_TIMEOUT)
            .open()
    }

    /// Why [`SerialSettings::open`] failed, naming the device: a missing device and a
    /// refused permission in those words, anything else with the system's.
    pub fn open_failure(&self, error: &serialport::Error) -> String {
        use serialport::ErrorKind;
        match error.kind() {
            ErrorKind::Io(std::io::ErrorKind::NotFound) => format!("no such device {}", self.path),
            ErrorKind::Io(std::io::ErrorKind::PermissionDenied) => {
                format!("permission denied opening {}", self.path)
            }
            _ => format!("cannot open {}: {error}", self.path),
        }
    }
}

/// How long a read waits before the reader checks whether the link was closed.
const READ_TIMEOUT: Duration = Duration::from_millis(20);

#[cfg(test)]
mod tests {
    use super::*;
    use serialport::{Error, ErrorKind};
    use std::io::ErrorKind as Io;

    /// What the system says when opening fails, in words naming the device (a permission
    /// cannot be refused to the root user these tests run as, so the error is made here).
    #[test]
    fn open_failures_name_the_device_and_the_cause() {
        let settings = SerialSettings::new("/dev/ttyUSB7", 115_200);
        let said = |kind| settings.open_failure(&Error::new(kind, "from the system"));
        assert_eq!(
            said(ErrorKind::Io(Io::NotFound)),
            "no such device /dev/ttyUSB7"
        );
        assert_eq!(
            said(ErrorKind::Io(Io::PermissionDenied)),
            "permission denied opening /dev/ttyUSB7"
        );
        assert_eq!(
            said(ErrorKind::NoDevice),
            "cannot open /dev/ttyUSB7: from the system"
        );
    }
}
