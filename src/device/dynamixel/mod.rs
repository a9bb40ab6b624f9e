//! Dynamixel Protocol 2.0 servos (docs/dynamixel.md): rigbridge as the bus master. The wire
//! codec (`wire`: packets, the control table, the line's time budget), the bridge's link
//! (`link`) and the twin's servos (`twin`).

use super::{Backend, LinkSpec};

mod link;
pub mod twin;
pub mod wire;

pub use link::{
    DynamixelError, DynamixelLink, DynamixelSettings, LOST_AFTER_CYCLES, connect_dynamixel,
    operating_mode,
};

/// A Dynamixel X-series servo's factory baud rate (XM430 e-manual, "Baud Rate (8)").
pub const DYNAMIXEL_DEFAULT_BAUD: u32 = 57_600;

/// Dynamixel in [`super::BACKENDS`]: `dynamixel://`, and the twin's `--dynamixel`.
pub struct Dynamixel;

impl Backend for Dynamixel {
    fn schemes(&self) -> &'static [&'static str] {
        &["dynamixel"]
    }

    fn forms(&self) -> &'static str {
        "dynamixel:///dev/PATH?baud=N&ids=1,2,..."
    }

    fn parse(&self, _scheme: &str, rest: &str) -> Result<LinkSpec, &'static str> {
        parse_dynamixel(rest)
    }

    fn twin_flags(&self) -> &'static [&'static str] {
        &["--dynamixel"]
    }

    fn twin_log_target(&self) -> &'static str {
        concat!(module_path!(), "::twin")
    }
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
                    Ok(list) if list.iter().all(|id| *id <= wire::MAX_SERVO_ID) => ids = Some(list),
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
