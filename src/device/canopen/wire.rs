//! CANopen on the wire, shared by the bridge's CiA 402 link (the NMT master, SYNC producer
//! and SDO client) and the twin's drives: the COB-IDs of the predefined connection set,
//! the object numbers both sides use, PDO mapping entries, the CiA 402 power states and
//! the bits of the controlword and statusword, SDO requests as a server reads them, and
//! the bus time of a frame. SDO, NMT and EMCY payloads themselves come from the
//! `canopen-rs` crate.
//!
//! Sources: CiA 301 v4.2 (communication profile: 7.3.3 predefined connection set, 7.2.2
//! PDO, 7.2.4 SDO, 7.2.5 SYNC, 7.2.7 EMCY, 7.2.8 NMT, 7.4.8 PDO mapping procedure, 7.5.2
//! objects 0x1000..0x1A00) and CiA 402-2 v4.1 (drive profile: 6.3 power state machine,
//! 0x6040, 0x6041, 0x6060, 0x6064, 0x607A, 0x60C2). docs/canopen.md lists each. It owns
//! bytes and numbers only: it must not decide what to send or judge what a drive does.

pub use canopen_rs::datatypes::Value;
pub use canopen_rs::object_dictionary::Address;
pub use canopen_rs::sdo::SdoAbortCode;

/// COB-IDs of the predefined connection set (CiA 301 7.3.3), for node `id` where it applies.
pub mod cob {
    pub const NMT: u32 = 0x000;
    pub const SYNC: u32 = 0x080;
    pub const EMCY: u32 = 0x080;
    pub const TPDO1: u32 = 0x180;
    pub const RPDO1: u32 = 0x200;
    /// SDO server to client (the drive's answers).
    pub const SDO_TX: u32 = 0x580;
    /// SDO client to server (the master's requests).
    pub const SDO_RX: u32 = 0x600;
    pub const HEARTBEAT: u32 = 0x700;
    /// The function code of a COB-ID (its top 4 bits) and the node id (its low 7).
    pub fn split(id: u32) -> (u32, u8) {
        (id & 0x780, (id & 0x7F) as u8)
    }
}

/// Object numbers (CiA 301 7.5.2, CiA 402-2 6).
pub mod object {
    /// UNSIGNED32: low 16 bits the device profile (402 for a drive).
    pub const DEVICE_TYPE: u16 = 0x1000;
    /// UNSIGNED8: set while an error is active.
    pub const ERROR_REGISTER: u16 = 0x1001;
    /// UNSIGNED16: the producer heartbeat time, ms (0 off).
    pub const HEARTBEAT_PRODUCER: u16 = 0x1017;
    /// RPDO1 communication (sub 1 COB-ID, sub 2 transmission type) and mapping.
    pub const RPDO1_COMM: u16 = 0x1400;
    pub const RPDO1_MAP: u16 = 0x1600;
    pub const TPDO1_COMM: u16 = 0x1800;
    pub const TPDO1_MAP: u16 = 0x1A00;
    pub const CONTROLWORD: u16 = 0x6040;
    pub const STATUSWORD: u16 = 0x6041;
    /// INTEGER8: 8 is cyclic synchronous position (CSP).
    pub const MODES_OF_OPERATION: u16 = 0x6060;
    pub const MODES_OF_OPERATION_DISPLAY: u16 = 0x6061;
    /// INTEGER32, counts.
    pub const POSITION_ACTUAL: u16 = 0x6064;
    /// INTEGER32, counts.
    pub const TARGET_POSITION: u16 = 0x607A;
    /// Interpolation time period: sub 1 UNSIGNED8 value, sub 2 INTEGER8 power of ten (s).
    pub const INTERPOLATION_PERIOD: u16 = 0x60C2;
}

/// The profile number in the low 16 bits of 0x1000 of a CiA 402 drive.
pub const DRIVE_PROFILE: u32 = 402;
/// 0x6060 value of cyclic synchronous position mode (CiA 402-2 6.2.2).
pub const CSP_MODE: i8 = 8;
/// Bit 31 of a PDO COB-ID (sub 1 of 0x1400/0x1800): set, the PDO does not exist (invalid).
pub const PDO_INVALID: u32 = 0x8000_0000;
/// Transmission type 1: synchronous, every SYNC (CiA 301 7.5.2.35/37).
pub const SYNCHRONOUS_EVERY_SYNC: u8 = 1;
/// The data bytes of a classic CAN frame: a PDO maps at most 64 bits.
pub const PDO_BYTES: usize = 8;

/// A PDO mapping entry: index, sub-index and length in bits (CiA 301 7.4.8).
pub const fn mapping_entry(index: u16, sub: u8, bits: u8) -> u32 {
    ((index as u32) << 16) | ((sub as u32) << 8) | bits as u32
}

/// RPDO1: controlword (16 bits) then target position (32 bits), 6 bytes.
pub const RPDO1_ENTRIES: [u32; 2] = [
    mapping_entry(object::CONTROLWORD, 0, 16),
    mapping_entry(object::TARGET_POSITION, 0, 32),
];
/// TPDO1: statusword (16 bits) then position actual value (32 bits), 6 bytes.
pub const TPDO1_ENTRIES: [u32; 2] = [
    mapping_entry(object::STATUSWORD, 0, 16),
    mapping_entry(object::POSITION_ACTUAL, 0, 32),
];

/// Controlword commands (CiA 402-2 6.3.1, table 7).
pub mod controlword {
    pub const SHUTDOWN: u16 = 0x06;
    pub const SWITCH_ON: u16 = 0x07;
    pub const ENABLE_OPERATION: u16 = 0x0F;
    pub const DISABLE_VOLTAGE: u16 = 0x00;
    /// Quick stop: bit 2 low, bit 1 high.
    pub const QUICK_STOP: u16 = 0x02;
    /// Bit 7: fault reset on its rising edge.
    pub const FAULT_RESET: u16 = 0x80;
}

/// Statusword bit 3: fault.
pub const STATUS_FAULT: u16 = 0x0008;

/// The power states of CiA 402-2 6.3.1 (figure 6), as the statusword shows them (table 8).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PowerState {
    NotReadyToSwitchOn,
    SwitchOnDisabled,
    ReadyToSwitchOn,
    SwitchedOn,
    OperationEnabled,
    QuickStopActive,
    FaultReactionActive,
    Fault,
}

impl PowerState {
    /// The state a statusword shows (bits 0-3, 5 and 6); `None` for a pattern table 8 lacks.
    pub fn of(statusword: u16) -> Option<Self> {
        let wide = statusword & 0x6F;
        match statusword & 0x4F {
            0x00 => return Some(Self::NotReadyToSwitchOn),
            0x40 => return Some(Self::SwitchOnDisabled),
            0x0F => return Some(Self::FaultReactionActive),
            0x08 => return Some(Self::Fault),
            _ => {}
        }
        match wide {
            0x21 => Some(Self::ReadyToSwitchOn),
            0x23 => Some(Self::SwitchedOn),
            0x27 => Some(Self::OperationEnabled),
            0x07 => Some(Self::QuickStopActive),
            _ => None,
        }
    }

    /// The statusword bits 0-6 of this state, with voltage enabled (bit 4) where power is
    /// on; the twin adds bit 9 (remote).
    pub fn bits(self) -> u16 {
        match self {
            Self::NotReadyToSwitchOn => 0x00,
            Self::SwitchOnDisabled => 0x40,
            Self::ReadyToSwitchOn => 0x31,
            Self::SwitchedOn => 0x33,
            Self::OperationEnabled => 0x37,
            Self::QuickStopActive => 0x17,
            Self::FaultReactionActive => 0x0F,
            Self::Fault => 0x08,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Self::NotReadyToSwitchOn => "not ready to switch on",
            Self::SwitchOnDisabled => "switch on disabled",
            Self::ReadyToSwitchOn => "ready to switch on",
            Self::SwitchedOn => "switched on",
            Self::OperationEnabled => "operation enabled",
            Self::QuickStopActive => "quick stop active",
            Self::FaultReactionActive => "fault reaction active",
            Self::Fault => "fault",
        }
    }
}

/// NMT states as a heartbeat carries them (CiA 301 7.2.8.3.2.1).
pub mod nmt_state {
    pub const BOOT_UP: u8 = 0x00;
    pub const STOPPED: u8 = 0x04;
    pub const OPERATIONAL: u8 = 0x05;
    pub const PRE_OPERATIONAL: u8 = 0x7F;
}

/// NMT command specifiers (CiA 301 7.2.8.3.1).
pub mod nmt_command {
    pub const START: u8 = 0x01;
    pub const STOP: u8 = 0x02;
    pub const ENTER_PRE_OPERATIONAL: u8 = 0x80;
    pub const RESET_NODE: u8 = 0x81;
    pub const RESET_COMMUNICATION: u8 = 0x82;
}

/// An SDO request as a server reads it (CiA 301 7.2.4.3): expedited transfers only, which
/// carry every object of a CSP drive's set-up (4 bytes at most).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SdoRequest {
    /// Download (write) of `len` bytes, little endian in `data`.
    Download {
        at: (u16, u8),
        data: [u8; 4],
        len: usize,
    },
    /// Upload (read).
    Upload { at: (u16, u8) },
    /// Anything else (segmented, block, abort): the address, if it has one.
    Unsupported { at: (u16, u8) },
}

impl SdoRequest {
    pub fn parse(payload: &[u8]) -> Option<Self> {
        let p: &[u8; 8] = payload.get(..8)?.try_into().ok()?;
        let at = (u16::from_le_bytes([p[1], p[2]]), p[3]);
        let command = p[0];
        Some(match command & 0xE0 {
            // Initiate download, expedited (e) with its size indicated (s).
            0x20 if command & 0x03 == 0x03 => {
                let len = 4 - usize::from((command >> 2) & 0x03);
                let mut data = [0u8; 4];
                data[..len].copy_from_slice(&p[4..4 + len]);
                SdoRequest::Download { at, data, len }
            }
            0x40 => SdoRequest::Upload { at },
            _ => SdoRequest::Unsupported { at },
        })
    }
}

/// The 8-byte payload of an expedited download of `value` to `at`; `None` for a value
/// longer than 4 bytes (which needs a segmented transfer).
pub fn sdo_download(at: (u16, u8), value: &Value) -> Option<[u8; 8]> {
    canopen_rs::sdo::encode_download_expedited(Address::new(at.0, at.1), value).ok()
}

/// The 8-byte payload of an upload request for `at`.
pub fn sdo_upload(at: (u16, u8)) -> [u8; 8] {
    canopen_rs::sdo::encode_upload_request(Address::new(at.0, at.1))
}

/// What an SDO answer said.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SdoAnswer {
    /// Download confirmed for this address.
    Written((u16, u8)),
    /// Upload answered, expedited: the address, the bytes (little endian) and their count.
    Read((u16, u8), [u8; 4], usize),
    /// Aborted with this CiA 301 abort code.
    Aborted((u16, u8), u32),
}

impl SdoAnswer {
    pub fn parse(payload: &[u8]) -> Option<Self> {
        let p: &[u8; 8] = payload.get(..8)?.try_into().ok()?;
        if let Ok(at) = canopen_rs::sdo::decode_download_response(p) {
            return Some(SdoAnswer::Written((at.index, at.subindex)));
        }
        if let Ok((at, code)) = canopen_rs::sdo::decode_abort(p) {
            return Some(SdoAnswer::Aborted((at.index, at.subindex), code));
        }
        // Upload initiate response, expedited with size (scs 2, e and s set).
        if p[0] & 0xE3 == 0x43 {
            let len = 4 - usize::from((p[0] >> 2) & 0x03);
            let mut data = [0u8; 4];
            data[..len].copy_from_slice(&p[4..4 + len]);
            return Some(SdoAnswer::Read(
                (u16::from_le_bytes([p[1], p[2]]), p[3]),
                data,
                len,
            ));
        }
        None
    }
}

/// CiA 301 abort codes the twin answers with (7.2.4.3.17, table 22).
pub mod abort {
    pub const COMMAND_INVALID: u32 = 0x0504_0001;
    pub const WRITE_READ_ONLY: u32 = 0x0601_0002;
    pub const NO_OBJECT: u32 = 0x0602_0000;
    pub const CANNOT_MAP: u32 = 0x0604_0041;
    pub const MAPPING_TOO_LONG: u32 = 0x0604_0042;
    pub const LENGTH_MISMATCH: u32 = 0x0607_0010;
    pub const NO_SUB_INDEX: u32 = 0x0609_0011;
    pub const INVALID_VALUE: u32 = 0x0609_0030;
    /// Data cannot be transferred because of the present device state (a mapping written
    /// while its PDO is valid, a PDO while operational).
    pub const DEVICE_STATE: u32 = 0x0800_0022;
}

/// EMCY error codes the twin sends (CiA 402-2 table 2 / CiA 301 table 21).
pub mod emcy_code {
    /// 0x8611: following error (a target the drive cannot follow: too fast).
    pub const FOLLOWING_ERROR: u16 = 0x8611;
    /// 0x8612: reference limit (a target outside the position range).
    pub const REFERENCE_LIMIT: u16 = 0x8612;
    /// 0x8400: velocity/speed controller (a step over the axis' speed).
    pub const SPEED: u16 = 0x8400;
    /// 0x8A00: positioning controller (a second difference over the acceleration).
    pub const POSITIONING: u16 = 0x8A00;
    /// 0x5000: device hardware (an injected drive fault).
    pub const HARDWARE: u16 = 0x5000;
    /// 0x8100: communication (SYNC lost while enabled).
    pub const COMMUNICATION: u16 = 0x8100;
}

/// The interpolation period 0x60C2 for `period`: (value, power of ten), the coarsest unit
/// from ms down to us that expresses it exactly in 1..=255; `None` when none does.
pub fn interpolation_period(period: std::time::Duration) -> Option<(u8, i8)> {
    let nanos = period.as_nanos();
    for (exponent, unit) in [
        (-3i8, 1_000_000u128),
        (-4, 100_000),
        (-5, 10_000),
        (-6, 1_000),
    ] {
        if nanos.is_multiple_of(unit) && (1..=255).contains(&(nanos / unit)) {
            return Some(((nanos / unit) as u8, exponent));
        }
    }
    None
}

/// The period an interpolation period (value, power of ten) means.
pub fn period_of(value: u8, exponent: i8) -> Option<std::time::Duration> {
    if !(-9..=0).contains(&exponent) {
        return None;
    }
    let nanos = u64::from(value) * 10u64.pow((9 + i32::from(exponent)) as u32);
    Some(std::time::Duration::from_nanos(nanos))
}

/// The predefined-set payload of an RPDO1: controlword and target, little endian.
pub fn rpdo1(controlword: u16, target: i32) -> [u8; 6] {
    let mut out = [0u8; 6];
    out[..2].copy_from_slice(&controlword.to_le_bytes());
    out[2..].copy_from_slice(&target.to_le_bytes());
    out
}

/// Statusword and position actual of a TPDO1 payload.
pub fn tpdo1(data: &[u8]) -> Option<(u16, i32)> {
    let status = u16::from_le_bytes(data.get(..2)?.try_into().ok()?);
    let position = i32::from_le_bytes(data.get(2..6)?.try_into().ok()?);
    Some((status, position))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn statusword_patterns_of_table_8() {
        for state in [
            PowerState::NotReadyToSwitchOn,
            PowerState::SwitchOnDisabled,
            PowerState::ReadyToSwitchOn,
            PowerState::SwitchedOn,
            PowerState::OperationEnabled,
            PowerState::QuickStopActive,
            PowerState::FaultReactionActive,
            PowerState::Fault,
        ] {
            // Bit 9 (remote) and manufacturer bits do not change the state.
            assert_eq!(PowerState::of(state.bits() | 0x0200 | 0x8000), Some(state));
        }
        // CiA 402-2 table 8 examples: 0x0237 operation enabled, 0x0250 switch on disabled.
        assert_eq!(PowerState::of(0x0237), Some(PowerState::OperationEnabled));
        assert_eq!(PowerState::of(0x0250), Some(PowerState::SwitchOnDisabled));
        assert_eq!(PowerState::of(0x0218), Some(PowerState::Fault));
    }

    #[test]
    fn interpolation_period_in_the_coarsest_exact_unit() {
        assert_eq!(
            interpolation_period(Duration::from_millis(4)),
            Some((4, -3))
        );
        assert_eq!(
            interpolation_period(Duration::from_micros(2500)),
            Some((25, -4))
        );
        assert_eq!(
            interpolation_period(Duration::from_micros(1)),
            Some((1, -6))
        );
        assert_eq!(interpolation_period(Duration::from_secs(1)), None);
        assert_eq!(period_of(4, -3), Some(Duration::from_millis(4)));
        assert_eq!(period_of(25, -4), Some(Duration::from_micros(2500)));
    }

    #[test]
    fn sdo_requests_and_answers_round_trip() {
        let write = sdo_download((0x6060, 0), &Value::Integer8(8))
            .expect("an Integer8 fits an expedited download");
        // CiA 301 example: 0x2F = download, expedited, size indicated, 1 byte.
        assert_eq!(write, [0x2F, 0x60, 0x60, 0, 8, 0, 0, 0]);
        assert_eq!(
            SdoRequest::parse(&write),
            Some(SdoRequest::Download {
                at: (0x6060, 0),
                data: [8, 0, 0, 0],
                len: 1
            })
        );
        assert_eq!(
            SdoRequest::parse(&sdo_upload((0x6064, 0))),
            Some(SdoRequest::Upload { at: (0x6064, 0) })
        );
        let answer = [0x43, 0x64, 0x60, 0, 1, 2, 3, 4];
        assert_eq!(
            SdoAnswer::parse(&answer),
            Some(SdoAnswer::Read((0x6064, 0), [1, 2, 3, 4], 4))
        );
        assert_eq!(
            SdoAnswer::parse(&[0x60, 0x40, 0x60, 0, 0, 0, 0, 0]),
            Some(SdoAnswer::Written((0x6040, 0)))
        );
        assert_eq!(
            SdoAnswer::parse(&[0x80, 0x00, 0x16, 1, 0x22, 0, 0, 8]),
            Some(SdoAnswer::Aborted((0x1600, 1), abort::DEVICE_STATE))
        );
        assert_eq!(mapping_entry(0x607A, 0, 32), 0x607A_0020);
        assert_eq!(tpdo1(&[0x37, 0x02, 0x10, 0, 0, 0]), Some((0x0237, 16)));
        assert_eq!(rpdo1(0x0F, -1), [0x0F, 0, 0xFF, 0xFF, 0xFF, 0xFF]);
    }
}
