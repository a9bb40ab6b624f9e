//! Run settings (`config/rigbridge.toml`): which rig, how to stream, the twin's servo model,
//! the plan's speed shares and the job. Validated on load; every error names the file,
//! the key and the value.

use crate::protocol::can::{CAN_ID_BLOCK, CanMappingError, MAX_CAN_BASE_ID};
use crate::protocol::{CanMapping, CanSender};
use crate::rig::{ConfigError, Rig, check_range, load_rig};
use serde::Deserialize;
use std::path::{Path, PathBuf};

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RunConfig {
    /// Rig description, relative to the config file.
    pub rig: PathBuf,
    pub stream: StreamConfig,
    pub twin: TwinConfig,
    pub plan: PlanConfig,
    pub job: JobConfig,
    /// `rigbridge serve`: where to listen and the control API's bearer token.
    #[serde(default)]
    pub serve: ServeConfig,
}

/// `[serve]`: optional; without it `serve` binds 127.0.0.1 with no token.
#[derive(Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ServeConfig {
    /// The address to listen on (an IP address; `--bind` overrides it). Any address but a
    /// loopback one requires a token.
    #[serde(default = "default_bind")]
    pub bind: String,
    /// The bearer token the control API requires (`RIGBRIDGE_TOKEN` overrides it).
    #[serde(default)]
    pub token: Option<String>,
}

impl Default for ServeConfig {
    fn default() -> Self {
        ServeConfig {
            bind: default_bind(),
            token: None,
        }
    }
}

/// Never prints the token itself.
impl std::fmt::Debug for ServeConfig {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ServeConfig")
            .field("bind", &self.bind)
            .field("token", &self.token.as_ref().map(|_| "<redacted>"))
            .finish()
    }
}

fn default_bind() -> String {
    "127.0.0.1".to_string()
}

/// Why a bearer token is not usable (empty, or not sendable in an HTTP header), if it is not.
pub fn token_problem(token: &str) -> Option<&'static str> {
    if token.is_empty() {
        Some("must not be empty")
    } else if !token.bytes().all(|b| b.is_ascii_graphic()) {
        Some("must be printable ASCII without spaces (it is sent in an HTTP header)")
    } else {
        None
    }
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StreamConfig {
    pub rate_hz: f64,
    #[serde(default = "default_link")]
    pub link: String,
    /// After a link loss, how long to wait for the link before aborting the job.
    #[serde(default = "default_reconnect_timeout")]
    pub reconnect_timeout_s: f64,
    /// `can://` links: CAN FD frames (64-byte payloads) instead of classic CAN (8 bytes).
    #[serde(default)]
    pub can_fd: bool,
    /// `can://` links: the first of the 128 standard identifiers the protocol uses
    /// (`docs/protocol.md`, section 7.1); at most 0x780.
    #[serde(default = "default_can_base_id")]
    pub can_base_id: u16,
    /// `serial://` links: the line's framing beyond the baud rate (8 data bits always).
    #[serde(default)]
    pub serial_parity: SerialParity,
    #[serde(default = "default_stop_bits")]
    pub serial_stop_bits: u8,
    #[serde(default)]
    pub serial_flow_control: SerialFlowControl,
    /// Following (docs/protocol.md 6.9): how far the arm may be from the target while
    /// moving, and from the last target at the end, within `goal_time_s`. `_deg` applies
    /// to revolute axes, `_m` to prismatic ones; each is one number or one per axis.
    #[serde(default)]
    pub path_tolerance_deg: Option<PerAxis>,
    #[serde(default)]
    pub path_tolerance_m: Option<PerAxis>,
    #[serde(default)]
    pub goal_tolerance_deg: Option<PerAxis>,
    #[serde(default)]
    pub goal_tolerance_m: Option<PerAxis>,
    #[serde(default)]
    pub goal_time_s: Option<f64>,
}

/// One value for every axis, or one per axis in the rig's order.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(untagged)]
pub enum PerAxis {
    One(f64),
    Each(Vec<f64>),
}

impl PerAxis {
    fn value(&self, axis: usize) -> Option<f64> {
        match self {
            PerAxis::One(value) => Some(*value),
            PerAxis::Each(values) => values.get(axis).copied(),
        }
    }
}

#[derive(Debug, Clone, Copy, Default, Deserialize, serde::Serialize, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub enum SerialParity {
    #[default]
    None,
    Odd,
    Even,
}

#[derive(Debug, Clone, Copy, Default, Deserialize, serde::Serialize, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub enum SerialFlowControl {
    #[default]
    None,
    Software,
    Hardware,
}

fn default_stop_bits() -> u8 {
    1
}

/// The widest tolerance accepted: beyond it nothing would be checked.
const MAX_TOLERANCE_DEG: f64 = 180.0;
const MAX_TOLERANCE_M: f64 = 1.0;
const MAX_GOAL_TIME_S: f64 = 60.0;

impl StreamConfig {
    /// The following tolerances for `rig`, defaults where unset; errors name the key.
    pub fn tolerances(
        &self,
        file: &Path,
        rig: &Rig,
    ) -> Result<crate::stream::Tolerances, ConfigError> {
        let mut tolerances = crate::stream::Tolerances::for_rig(rig);
        let keys = [
            (
                "path_tolerance",
                &self.path_tolerance_deg,
                &self.path_tolerance_m,
                &mut tolerances.path,
            ),
            (
                "goal_tolerance",
                &self.goal_tolerance_deg,
                &self.goal_tolerance_m,
                &mut tolerances.goal,
            ),
        ];
        for (key, degrees, metres, slot) in keys {
            for (name, given, revolute) in [("deg", degrees, true), ("m", metres, false)] {
                let Some(given) = given else { continue };
                let key = format!("stream.{key}_{name}");
                if let PerAxis::Each(values) = given
                    && values.len() != rig.dof()
                {
                    let reason = format!("needs one value per axis ({})", rig.dof());
                    return Err(ConfigError::invalid(file, &key, values.len(), &reason));
                }
                for (axis, joint) in rig.joints.iter().enumerate() {
                    if (joint.kind == crate::rig::JointKind::Revolute) != revolute {
                        continue;
                    }
                    let value = given.value(axis).unwrap_or_default();
                    let high = if revolute {
                        MAX_TOLERANCE_DEG
                    } else {
                        MAX_TOLERANCE_M
                    };
                    let value = check_range(file, &key, value, 0.0, high)?;
                    slot.as_mut_slice()[axis] = if revolute { value.to_radians() } else { value };
                }
            }
        }
        if let Some(seconds) = self.goal_time_s {
            let seconds = check_range(file, "stream.goal_time_s", seconds, 0.0, MAX_GOAL_TIME_S)?;
            tolerances.goal_time = std::time::Duration::from_secs_f64(seconds);
        }
        Ok(tolerances)
    }

    /// The serial settings of these settings for a `serial://PATH?baud=N` link.
    pub fn serial_settings(&self, path: &str, baud: u32) -> crate::link::SerialSettings {
        let mut settings = crate::link::SerialSettings::new(path, baud);
        settings.parity = match self.serial_parity {
            SerialParity::None => serialport::Parity::None,
            SerialParity::Odd => serialport::Parity::Odd,
            SerialParity::Even => serialport::Parity::Even,
        };
        settings.stop_bits = if self.serial_stop_bits == 2 {
            serialport::StopBits::Two
        } else {
            serialport::StopBits::One
        };
        settings.flow_control = match self.serial_flow_control {
            SerialFlowControl::None => serialport::FlowControl::None,
            SerialFlowControl::Software => serialport::FlowControl::Software,
            SerialFlowControl::Hardware => serialport::FlowControl::Hardware,
        };
        settings
    }

    /// The CAN mapping of these settings for `sender`'s end of a `can://` link.
    pub fn can_mapping(&self, sender: CanSender) -> Result<CanMapping, CanMappingError> {
        CanMapping::new(self.can_base_id, self.can_fd, sender)
    }
}

fn default_link() -> String {
    "loopback".to_string()
}

fn default_reconnect_timeout() -> f64 {
    5.0
}

fn default_can_base_id() -> u16 {
    0x100
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TwinConfig {
    pub bandwidth_hz: f64,
    pub delay_ms: f64,
    pub watchdog_cycles: u32,
    pub initial_deg: Vec<f64>,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlanConfig {
    pub speed_scale: f64,
    pub accel_scale: f64,
}

#[derive(Debug, Clone, Deserialize, serde::Serialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum JobConfig {
    /// A five-pointed star on a wall plane x = wall_x_m, tool normal to the wall.
    WallFigure {
        wall_x_m: f64,
        centre_yz_m: [f64; 2],
        radius_m: f64,
        laps: u32,
    },
    /// Point-to-point joint moves through these configurations (degrees).
    JointWaypoints { waypoints_deg: Vec<Vec<f64>> },
    /// The sloth's gait over a scenario (`rig` must then be a sloth file, config/sloth.toml).
    Gait {
        scenario: String,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        angle_deg: Option<f64>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        gap_m: Option<f64>,
        /// A forest file (config/forest.toml, relative to this file, resolved on load):
        /// `scenario` is then one of its walks.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        forest: Option<PathBuf>,
    },
    /// Paint a generated room of `walls` walls (seed `seed`) with the painter rig;
    /// `paint_config` (config/paint.toml) is relative to this file, resolved on load.
    Paint {
        walls: u32,
        seed: u64,
        paint_config: PathBuf,
    },
}

/// A loaded, validated configuration with its rig.
#[derive(Debug, Clone)]
pub struct RunSettings {
    pub file: PathBuf,
    pub config: RunConfig,
    pub rig: Rig,
    /// The sloth behind `rig` when the job is a gait (`rig` is then its streamed axes).
    pub sloth: Option<std::sync::Arc<crate::task::gait::SlothRig>>,
}

impl RunSettings {
    pub fn period_s(&self) -> f64 {
        1.0 / self.config.stream.rate_hz
    }

    /// The twin's initial position: degrees for revolute axes, metres for prismatic ones.
    pub fn initial(&self) -> Vec<f64> {
        to_si(&self.config.twin.initial_deg, &self.rig)
    }
}

/// Reads and validates run settings and the rig they name.
pub fn load_run_settings(file: &Path) -> Result<RunSettings, ConfigError> {
    let text = std::fs::read_to_string(file).map_err(|source| ConfigError::Io {
        file: file.to_path_buf(),
        source,
    })?;
    let mut config: RunConfig = toml::from_str(&text).map_err(|e| ConfigError::Parse {
        file: file.to_path_buf(),
        message: e.to_string().trim_end().to_string(),
    })?;
    if let JobConfig::Paint { paint_config, .. } = &mut config.job {
        *paint_config = file.parent().unwrap_or(Path::new(".")).join(&*paint_config);
    }
    if let JobConfig::Gait {
        forest: Some(forest),
        ..
    } = &mut config.job
    {
        *forest = file.parent().unwrap_or(Path::new(".")).join(&*forest);
    }
    let rig_path = file.parent().unwrap_or(Path::new(".")).join(&config.rig);
    let sloth = match config.job {
        JobConfig::Gait { .. } => Some(std::sync::Arc::new(crate::task::gait::SlothRig::load(
            &rig_path,
        )?)),
        _ => None,
    };
    let rig = match &sloth {
        Some(sloth) => sloth.streamed.clone(),
        None => load_rig(&rig_path)?,
    };
    check_range(file, "stream.rate_hz", config.stream.rate_hz, 1.0, 1000.0)?;
    if let Err(e) = config.stream.link.parse::<crate::link::LinkSpec>() {
        return Err(ConfigError::invalid(
            file,
            "stream.link",
            &config.stream.link,
            &e.reason,
        ));
    }
    if !matches!(config.stream.serial_stop_bits, 1 | 2) {
        return Err(ConfigError::invalid(
            file,
            "stream.serial_stop_bits",
            config.stream.serial_stop_bits,
            "must be 1 or 2",
        ));
    }
    check_range(
        file,
        "stream.reconnect_timeout_s",
        config.stream.reconnect_timeout_s,
        0.0,
        3600.0,
    )?;
    config.stream.tolerances(file, &rig)?;
    if config.stream.can_base_id > MAX_CAN_BASE_ID {
        return Err(ConfigError::invalid(
            file,
            "stream.can_base_id",
            format_args!("{:#x}", config.stream.can_base_id),
            &format!(
                "must be at most {MAX_CAN_BASE_ID:#x}: the protocol's {CAN_ID_BLOCK:#x} \
                 identifiers from the base must fit the 11-bit range"
            ),
        ));
    }
    check_range(
        file,
        "twin.bandwidth_hz",
        config.twin.bandwidth_hz,
        0.1,
        1000.0,
    )?;
    check_range(file, "twin.delay_ms", config.twin.delay_ms, 0.0, 1000.0)?;
    if config.twin.watchdog_cycles == 0 {
        return Err(ConfigError::invalid(
            file,
            "twin.watchdog_cycles",
            0,
            "must be at least 1",
        ));
    }
    check_joints(file, "twin.initial_deg", &config.twin.initial_deg, &rig)?;
    check_range(
        file,
        "plan.speed_scale",
        config.plan.speed_scale,
        0.01,
        0.99,
    )?;
    check_range(
        file,
        "plan.accel_scale",
        config.plan.accel_scale,
        0.01,
        0.99,
    )?;
    check_job(file, &config.job, &rig, sloth.as_deref())?;
    if config.serve.bind.parse::<std::net::IpAddr>().is_err() {
        return Err(ConfigError::invalid(
            file,
            "serve.bind",
            &config.serve.bind,
            "must be an IP address, such as 127.0.0.1 or 0.0.0.0",
        ));
    }
    if let Some(reason) = config.serve.token.as_deref().and_then(token_problem) {
        return Err(ConfigError::invalid(
            file,
            "serve.token",
            "<redacted>",
            reason,
        ));
    }
    Ok(RunSettings {
        file: file.to_path_buf(),
        config,
        rig,
        sloth,
    })
}

/// Config joint values in SI units: revolute axes are written in degrees, prismatic ones in
/// metres.
fn to_si(values: &[f64], rig: &Rig) -> Vec<f64> {
    values
        .iter()
        .zip(&rig.joints)
        .map(|(v, joint)| match joint.kind {
            crate::rig::JointKind::Revolute => v.to_radians(),
            crate::rig::JointKind::Prismatic => *v,
        })
        .collect()
}

fn check_joints(file: &Path, key: &str, degrees: &[f64], rig: &Rig) -> Result<(), ConfigError> {
    if degrees.len() != rig.dof() {
        return Err(ConfigError::invalid(
            file,
            key,
            degrees,
            &format!("needs {} values for rig {}", rig.dof(), rig.name),
        ));
    }
    let radians = to_si(degrees, rig);
    if degrees.iter().any(|d| !d.is_finite()) {
        return Err(ConfigError::invalid(
            file,
            key,
            degrees,
            "values must be finite",
        ));
    }
    if let Some((index, _)) = rig.first_limit_violation(&radians) {
        return Err(ConfigError::invalid(
            file,
            &format!("{key}[{index}]"),
            degrees[index],
            &format!("outside the limits of {}", rig.joints[index].name),
        ));
    }
    Ok(())
}

fn check_job(
    file: &Path,
    job: &JobConfig,
    rig: &Rig,
    sloth: Option<&crate::task::gait::SlothRig>,
) -> Result<(), ConfigError> {
    match job {
        JobConfig::WallFigure {
            wall_x_m,
            centre_yz_m,
            radius_m,
            laps,
        } => {
            check_range(file, "job.wall_x_m", *wall_x_m, -2.0, 2.0)?;
            check_range(file, "job.centre_yz_m[0]", centre_yz_m[0], -2.0, 2.0)?;
            check_range(file, "job.centre_yz_m[1]", centre_yz_m[1], -2.0, 2.0)?;
            check_range(file, "job.radius_m", *radius_m, 0.001, 1.0)?;
            if *laps == 0 || *laps > 1000 {
                return Err(ConfigError::invalid(
                    file,
                    "job.laps",
                    laps,
                    "must lie in [1, 1000]",
                ));
            }
        }
        JobConfig::Paint {
            walls,
            paint_config,
            ..
        } => {
            let max = crate::task::paint::room::MAX_WALLS;
            if !(3..=max).contains(walls) {
                return Err(ConfigError::invalid(
                    file,
                    "job.walls",
                    walls,
                    &format!("must lie in [3, {max}]"),
                ));
            }
            let paint = crate::task::paint::load_paint_settings(paint_config)?;
            if paint.rig != *rig {
                return Err(ConfigError::invalid(
                    file,
                    "rig",
                    &rig.name,
                    &format!(
                        "must be the painter rig {} named by {}",
                        paint.rig.name,
                        paint_config.display()
                    ),
                ));
            }
        }
        JobConfig::JointWaypoints { waypoints_deg } => {
            if waypoints_deg.is_empty() {
                return Err(ConfigError::invalid(
                    file,
                    "job.waypoints_deg",
                    "[]",
                    "needs at least one waypoint",
                ));
            }
            for (i, waypoint) in waypoints_deg.iter().enumerate() {
                check_joints(file, &format!("job.waypoints_deg[{i}]"), waypoint, rig)?;
            }
        }
        JobConfig::Gait {
            scenario,
            forest: Some(forest),
            angle_deg,
            gap_m,
        } => check_forest_walk(file, scenario, forest, *angle_deg, *gap_m, sloth)?,
        JobConfig::Gait {
            scenario,
            angle_deg,
            gap_m,
            forest: None,
        } => {
            if let Err(e) = crate::task::gait::Scenario::build(scenario, *angle_deg, *gap_m) {
                return Err(ConfigError::invalid(
                    file,
                    "job.scenario",
                    scenario,
                    &e.to_string(),
                ));
            }
        }
    }
    Ok(())
}

/// A gait job's walk from a forest file: the file loads, holds the walk, and the job gives
/// no built-in scenario's `angle_deg` or `gap_m`.
fn check_forest_walk(
    file: &Path,
    walk: &str,
    forest: &Path,
    angle_deg: Option<f64>,
    gap_m: Option<f64>,
    sloth: Option<&crate::task::gait::SlothRig>,
) -> Result<(), ConfigError> {
    let geometry = "a walk from `forest` takes its geometry from that file";
    if let Some(angle) = angle_deg {
        return Err(ConfigError::invalid(file, "job.angle_deg", angle, geometry));
    }
    if let Some(gap) = gap_m {
        return Err(ConfigError::invalid(file, "job.gap_m", gap, geometry));
    }
    // Its supports are trunks or branches by the sloth's `[gait] trunk_tilt_deg`.
    let Some(sloth) = sloth else {
        return Err(ConfigError::invalid(
            file,
            "job.forest",
            forest,
            "a gait job needs a sloth rig (`rig`) to walk it",
        ));
    };
    let loaded = crate::task::gait::Forest::load(forest, sloth.gait.trunk_tilt_rad)?;
    if let Err(e) = loaded.scenario(walk) {
        return Err(ConfigError::invalid(
            file,
            "job.scenario",
            walk,
            &e.to_string(),
        ));
    }
    Ok(())
}
