//! Run settings (`config/rigbridge.toml`): which rig, how to stream, the twin's servo model,
//! the plan's speed shares and the job. Validated on load; every error names the file,
//! the key and the value.

use crate::cell::{Cell, CellError, CollisionModel, RawCell, cell_from_raw, load_cell};
use crate::protocol::can::{CAN_ID_BLOCK, CanMappingError, MAX_CAN_BASE_ID};
use crate::protocol::{CanMapping, CanSender};
use crate::rig::{ConfigError, Rig, Shown, Verbatim, check_range, load_rig};
use serde::Deserialize;
use std::path::{Path, PathBuf};
use std::time::Duration;

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RunConfig {
    /// Rig description, relative to the config file.
    pub rig: PathBuf,
    /// The workcell (docs/cell.md): `cell = "cell.toml"`, a cell file relative to this file,
    /// or a `[cell]` section of this file. Optional: none is [`Cell::builtin`], the floor
    /// the robot stands on.
    #[serde(default)]
    pub cell: Option<toml::Value>,
    /// `[stream]`: optional, every key has a default (250 Hz to the in-process twin).
    #[serde(default = "default_stream")]
    pub stream: StreamConfig,
    /// `[twin]`: optional, see [`TwinConfig`]'s defaults.
    #[serde(default)]
    pub twin: TwinConfig,
    /// `[plan]`: optional, see [`PlanConfig`]'s defaults.
    #[serde(default)]
    pub plan: PlanConfig,
    pub job: JobConfig,
    /// `rigbridge serve`: where to listen and the control API's bearer token.
    #[serde(default)]
    pub serve: ServeConfig,
    /// `[dynamixel]`: how axes map to servo ticks on `dynamixel://` links (and in the
    /// twin's servos). Optional.
    #[serde(default)]
    pub dynamixel: DynamixelConfig,
    /// `[ros2]`: the rig as a ROS 2 node, over DDS or Zenoh (docs/ros2.md). Optional: off
    /// when the table is absent (and `--zenoh-connect` is not given).
    #[serde(default, deserialize_with = "present_ros2")]
    pub ros2: Ros2Config,
    /// `[canopen]`: how axes map to drive counts on `canopen://` links (and in the twin's
    /// drives), and the drives' heartbeat. Optional.
    #[serde(default)]
    pub canopen: CanopenConfig,
    /// `[egm]`: which axes travel as EGM external axes on `egm://` links (and in the EGM
    /// twin). Optional.
    #[serde(default)]
    pub egm: EgmConfig,
    /// `[limits]`: the caps on one job's duration, points and plan memory (docs/jobs.md,
    /// "Limits"). Optional: every key has a default.
    #[serde(default)]
    pub limits: crate::job::JobLimits,
    /// `[log]`: what a job does when its log cannot be written (docs/logs.md). Optional.
    #[serde(default)]
    pub log: LogConfig,
}

/// `[log]`: the run log of every job (docs/logs.md, "When the log cannot be written").
#[derive(Debug, Clone, Copy, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LogConfig {
    /// What a job does once a write to its log fails (a full disk): `stop` (default) or
    /// `continue`. Checked on load: any other value is refused, naming the key.
    #[serde(default)]
    pub on_error: OnLogError,
}

/// See [`LogConfig::on_error`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum OnLogError {
    /// Bring the job to rest along its path, as an operator's Stop does: a job with no
    /// record of what the arm did does not go on (the default).
    #[default]
    Stop,
    /// Go on streaming without a log; the failure is still said at once and reported.
    Continue,
}

impl std::fmt::Display for OnLogError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            OnLogError::Stop => "stop",
            OnLogError::Continue => "continue",
        })
    }
}

/// `[egm]`: a rig with more axes than the robot's six (a track, a lift) sends the others as
/// EGM external axes (`externalJoints`: degrees, or mm on linear axes; docs/egm.md).
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EgmConfig {
    /// The rig's joints that are external axes, in `externalJoints` order (the controller's
    /// additional axes in order). Absent: every joint before the rig's last six.
    pub external_axes: Option<Vec<String>>,
}

impl EgmConfig {
    /// Where each axis travels in EGM; errors name the key and value.
    pub fn axes(
        &self,
        file: &Path,
        rig: &Rig,
    ) -> Result<crate::device::egm::wire::EgmAxes, ConfigError> {
        crate::device::egm::wire::EgmAxes::new(rig, self.external_axes.as_deref()).map_err(|e| {
            let value = match &self.external_axes {
                Some(names) => format!("[{}]", names.join(", ")),
                None => "absent (every joint before the last six)".to_string(),
            };
            ConfigError::invalid(
                file,
                "egm.external_axes",
                crate::rig::Verbatim(value),
                &e.to_string(),
            )
        })
    }
}

/// `[ros2]` read from the settings: the table is there, so ROS 2 is on.
fn present_ros2<'de, D: serde::Deserializer<'de>>(deserializer: D) -> Result<Ros2Config, D::Error> {
    let mut config = Ros2Config::deserialize(deserializer)?;
    config.present = true;
    Ok(config)
}

/// `[ros2] middleware`: what the rig's node speaks.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum MiddlewareName {
    /// DDS, a stock ROS 2 install's default (Fast DDS): `ros2 topic echo` sees it as is.
    Dds,
    /// Zenoh as rmw_zenoh: needs `zenoh_connect`.
    Zenoh,
}

/// `[ros2] discovery_range`: whom DDS discovery reaches (`ROS_AUTOMATIC_DISCOVERY_RANGE`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum RangeName {
    Localhost,
    Subnet,
}

/// `[ros2]`: publish the rig's joint states, over DDS (with `/tf`, `/tf_static` and the
/// robot description) or over Zenoh the way rmw_zenoh does (and there, under `serve`, when
/// `accept_motion` says so, take joint trajectories as jobs).
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Ros2Config {
    /// `dds` or `zenoh`; absent: `zenoh` when `zenoh_connect` is given, else `dds`.
    pub middleware: Option<MiddlewareName>,
    /// DDS only: `localhost` (127.0.0.1 only, no multicast) or `subnet` (every interface,
    /// multicast discovery); `localhost` when absent, so nothing leaves the machine unasked.
    pub discovery_range: Option<RangeName>,
    /// The Zenoh router or peer to connect to, `tcp/HOST:PORT` (rmw_zenohd listens on
    /// `tcp/localhost:7447`). `--zenoh-connect` overrides it (and means Zenoh).
    pub zenoh_connect: Option<String>,
    /// The ROS 2 domain (`ROS_DOMAIN_ID`), 0 when absent; 0..=232.
    #[serde(default)]
    pub domain_id: u32,
    /// JointState messages a second, 125 when absent; 1..=1000.
    pub joint_states_hz: Option<f64>,
    /// Whether `serve` takes JointTrajectory messages as jobs; false when absent (the node
    /// then does not subscribe at all). True needs `user` and `password_file`, unless
    /// `allow_unauthenticated_motion` is set.
    #[serde(default)]
    pub accept_motion: bool,
    /// The Zenoh user the session logs in to its router as (Zenoh's `usrpwd`
    /// authentication); with `password_file`, both or neither.
    pub user: Option<String>,
    /// A file holding the password (one line), relative to this file. Never the password
    /// itself in the settings: they are logged and shown.
    pub password_file: Option<PathBuf>,
    /// `accept_motion` without a login: anyone who reaches the Zenoh network can then move
    /// the arm. Only for an isolated lab network; false when absent.
    #[serde(default)]
    pub allow_unauthenticated_motion: bool,
    /// A FollowJointTrajectory goal's path tolerance where it names none (rad, m for a
    /// prismatic joint, as ROS 2's JointTolerance); 0.05 when absent; 0 checks nothing.
    pub path_tolerance: Option<f64>,
    /// A goal's tolerance at the last point where it names none (rad, m); 0.01 when absent.
    pub goal_tolerance: Option<f64>,
    /// Seconds after a goal's last point by which the goal must be reached, where the goal
    /// names none; 0 (not checked, as JointTrajectoryController's default) when absent.
    #[serde(default)]
    pub goal_time_tolerance_s: f64,
    /// The login read from `user` and `password_file` on load.
    #[serde(skip)]
    login: Option<crate::ros2::Login>,
    /// Whether the settings hold a `[ros2]` table (ROS 2 is then on).
    #[serde(skip)]
    present: bool,
}

/// Largest password file read (bytes): a password is a line, and the file is read whole.
const MAX_PASSWORD_FILE_BYTES: u64 = 4096;
/// Largest tolerance taken (rad, m): a full turn; more checks nothing a turn would not.
const MAX_TOLERANCE: f64 = std::f64::consts::TAU;
/// Longest Zenoh user name taken.
const MAX_USER_CHARS: usize = 256;

impl Ros2Config {
    /// The ROS 2 settings of `file`, with `endpoint` (`--zenoh-connect`, already checked)
    /// in place of `zenoh_connect` when given (Zenoh then, whatever `middleware` says);
    /// `None` when the settings have no `[ros2]` and no endpoint is given.
    pub fn settings(&self, endpoint: Option<&str>) -> Option<crate::ros2::Ros2Settings> {
        if !self.present && endpoint.is_none() {
            return None;
        }
        let middleware = match endpoint.or(self.zenoh_connect.as_deref()) {
            Some(connect) => crate::ros2::Middleware::Zenoh {
                connect: connect.to_string(),
            },
            None => crate::ros2::Middleware::Dds {
                range: match self.discovery_range {
                    Some(RangeName::Subnet) => crate::ros2::DiscoveryRange::Subnet,
                    Some(RangeName::Localhost) | None => crate::ros2::DiscoveryRange::Localhost,
                },
            },
        };
        Some(crate::ros2::Ros2Settings {
            middleware,
            domain_id: self.domain_id,
            joint_states_hz: self
                .joint_states_hz
                .unwrap_or(crate::ros2::DEFAULT_JOINT_STATES_HZ),
            login: self.login.clone(),
            accept_motion: self.accept_motion,
            tolerances: crate::ros2::fjt::Tolerances {
                path: self
                    .path_tolerance
                    .unwrap_or(crate::ros2::DEFAULT_PATH_TOLERANCE),
                goal: self
                    .goal_tolerance
                    .unwrap_or(crate::ros2::DEFAULT_GOAL_TOLERANCE),
                goal_time_s: self.goal_time_tolerance_s,
            },
        })
    }

    /// Checks the keys and reads the password file.
    fn check(&mut self, file: &Path) -> Result<(), ConfigError> {
        self.check_middleware(file)?;
        if let Some(endpoint) = &self.zenoh_connect
            && let Some(reason) = crate::ros2::endpoint_problem(endpoint)
        {
            return Err(ConfigError::invalid(
                file,
                "ros2.zenoh_connect",
                endpoint,
                reason,
            ));
        }
        if self.domain_id > crate::ros2::MAX_DOMAIN_ID {
            return Err(ConfigError::invalid(
                file,
                "ros2.domain_id",
                self.domain_id,
                &format!("must be at most {}", crate::ros2::MAX_DOMAIN_ID),
            ));
        }
        if let Some(rate) = self.joint_states_hz {
            check_range(file, "ros2.joint_states_hz", rate, 1.0, 1000.0)?;
        }
        self.check_tolerances(file)?;
        self.login = self.read_login(file)?;
        if self.accept_motion && self.login.is_none() && !self.allow_unauthenticated_motion {
            return Err(ConfigError::invalid(
                file,
                "ros2.accept_motion",
                true,
                "needs Zenoh authentication: set ros2.user and ros2.password_file (and a \
                 router that asks for them, docs/ros2.md), or, on an isolated lab network \
                 only, ros2.allow_unauthenticated_motion = true",
            ));
        }
        Ok(())
    }

    /// The tolerances are finite and not negative; the goal time at most a minute (a goal
    /// late by more is not late, it is stuck).
    fn check_tolerances(&self, file: &Path) -> Result<(), ConfigError> {
        for (key, value) in [
            ("ros2.path_tolerance", self.path_tolerance),
            ("ros2.goal_tolerance", self.goal_tolerance),
        ] {
            if let Some(value) = value {
                check_range(file, key, value, 0.0, MAX_TOLERANCE)?;
            }
        }
        check_range(
            file,
            "ros2.goal_time_tolerance_s",
            self.goal_time_tolerance_s,
            0.0,
            MAX_GOAL_TIME_S,
        )
        .map(|_| ())
    }

    /// `middleware` agrees with `zenoh_connect`; `discovery_range` is for DDS only.
    fn check_middleware(&self, file: &Path) -> Result<(), ConfigError> {
        match (self.middleware, &self.zenoh_connect) {
            (Some(MiddlewareName::Dds), Some(endpoint)) => Err(ConfigError::invalid(
                file,
                "ros2.zenoh_connect",
                endpoint,
                "is for middleware = \"zenoh\"; ros2.middleware says \"dds\"",
            )),
            (Some(MiddlewareName::Zenoh), None) => Err(ConfigError::invalid(
                file,
                "ros2.middleware",
                "zenoh",
                "needs ros2.zenoh_connect = \"tcp/HOST:PORT\" (the router or peer to reach)",
            )),
            (_, Some(_)) if self.discovery_range.is_some() => Err(ConfigError::invalid(
                file,
                "ros2.discovery_range",
                if self.discovery_range == Some(RangeName::Subnet) {
                    "subnet"
                } else {
                    "localhost"
                },
                "is for middleware = \"dds\"; Zenoh reaches only ros2.zenoh_connect",
            )),
            _ => Ok(()),
        }
    }

    /// The login of `user` and `password_file`: both or neither.
    fn read_login(&self, file: &Path) -> Result<Option<crate::ros2::Login>, ConfigError> {
        let (user, password_file) = match (&self.user, &self.password_file) {
            (None, None) => return Ok(None),
            (Some(user), Some(password_file)) => (user, password_file),
            (Some(user), None) => {
                return Err(ConfigError::invalid(
                    file,
                    "ros2.user",
                    user,
                    "needs ros2.password_file too",
                ));
            }
            (None, Some(password_file)) => {
                return Err(ConfigError::invalid(
                    file,
                    "ros2.password_file",
                    password_file.display().to_string(),
                    "needs ros2.user too",
                ));
            }
        };
        if user.is_empty()
            || user.chars().count() > MAX_USER_CHARS
            || user.contains(|c: char| c == ':' || c.is_whitespace() || c.is_control())
        {
            return Err(ConfigError::invalid(
                file,
                "ros2.user",
                user,
                &format!(
                    "must be 1 to {MAX_USER_CHARS} characters without `:`, spaces or control \
                     characters (a Zenoh dictionary file holds `user:password` lines)"
                ),
            ));
        }
        let path = config_dir(file).join(password_file);
        let password = read_password(&path).map_err(|reason| {
            ConfigError::invalid(
                file,
                "ros2.password_file",
                password_file.display().to_string(),
                &format!("{}: {reason}", path.display()),
            )
        })?;
        Ok(Some(crate::ros2::Login::new(user.clone(), password)))
    }
}

/// Why a password file cannot be used; never quotes the content.
#[derive(Debug, thiserror::Error)]
enum PasswordFileError {
    #[error("cannot read: {0}")]
    Unreadable(#[from] std::io::Error),
    #[error("{0} bytes; a password file holds one line of at most {MAX_PASSWORD_FILE_BYTES} bytes")]
    TooLarge(u64),
    #[error("is empty: it must hold the password")]
    Empty,
    #[error("must hold the password alone, on one line")]
    NotOneLine,
}

/// The password in `path`: its one line, without surrounding whitespace (a Zenoh dictionary
/// trims its entries the same way).
fn read_password(path: &Path) -> Result<String, PasswordFileError> {
    let size = std::fs::metadata(path)?.len();
    if size > MAX_PASSWORD_FILE_BYTES {
        return Err(PasswordFileError::TooLarge(size));
    }
    let text = std::fs::read_to_string(path)?;
    let password = text.trim();
    if password.is_empty() {
        return Err(PasswordFileError::Empty);
    }
    if password.lines().count() > 1 || password.contains(|c: char| c.is_control()) {
        return Err(PasswordFileError::NotOneLine);
    }
    Ok(password.to_string())
}

/// `[canopen]`: per axis, counts = zero_offset + rad * counts_per_turn / 2 pi, or on a
/// prismatic axis zero_offset + m * counts_per_metre (docs/canopen.md). `counts_per_turn`
/// and `zero_offset` are one whole number for every axis or one per axis; they override the
/// link address's `counts_per_turn`.
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CanopenConfig {
    /// The link's `counts_per_turn`, else 1,048,576 (a 20-bit encoder), when absent.
    pub counts_per_turn: Option<PerAxis>,
    /// 0 when absent: counts 0 at the axis' zero.
    pub zero_offset: Option<PerAxis>,
    /// A linear drive's increments a metre of travel: one number for every prismatic axis,
    /// or one per axis (0 on revolute ones). No default: required for prismatic axes.
    pub counts_per_metre: Option<PerAxis>,
    /// The heartbeat producer time asked of each drive (0x1017), ms; 100 when absent.
    pub heartbeat_ms: Option<f64>,
}

/// Counts a turn when neither the link nor `[canopen]` says: a 20-bit single-turn encoder.
pub const DEFAULT_COUNTS_PER_TURN: f64 = 1_048_576.0;
/// The heartbeat producer time asked of each drive when `[canopen]` does not say: 100 ms,
/// 25 cycles at 250 Hz (the streamer's own patience for a silent controller).
pub const DEFAULT_HEARTBEAT_MS: f64 = 100.0;
/// Largest counts a turn accepted: 2^30, far above any encoder, keeps a turn in 32 bits.
const MAX_COUNTS_PER_TURN: f64 = 1_073_741_824.0;

impl CanopenConfig {
    /// Each axis' count map, `counts_per_turn` from the link address unless `[canopen]`
    /// sets it, `counts_per_metre` on prismatic axes (required there); errors name the key
    /// and value.
    pub fn axes(
        &self,
        file: &Path,
        rig: &Rig,
        link_counts_per_turn: Option<u32>,
    ) -> Result<Vec<crate::device::dynamixel::wire::AxisTicks>, ConfigError> {
        self.count_maps(file, rig, link_counts_per_turn, true)
    }

    /// Checks the keys given, on load: `counts_per_metre` is required only when `linear`
    /// (the config's own link is `canopen://`).
    pub fn check(&self, file: &Path, rig: &Rig, linear: bool) -> Result<(), ConfigError> {
        self.count_maps(file, rig, None, linear).map(drop)
    }

    fn count_maps(
        &self,
        file: &Path,
        rig: &Rig,
        link_counts_per_turn: Option<u32>,
        required: bool,
    ) -> Result<Vec<crate::device::dynamixel::wire::AxisTicks>, ConfigError> {
        let default = crate::device::dynamixel::wire::AxisTicks {
            ticks_per_turn: link_counts_per_turn.map_or(DEFAULT_COUNTS_PER_TURN, f64::from),
            zero_tick: 0.0,
            ticks_per_metre: None,
        };
        let mut axes = vec![default; rig.dof()];
        let keys = [
            (
                "canopen.counts_per_turn",
                &self.counts_per_turn,
                1.0,
                MAX_COUNTS_PER_TURN,
            ),
            (
                "canopen.zero_offset",
                &self.zero_offset,
                f64::from(i32::MIN),
                f64::from(i32::MAX),
            ),
        ];
        set_axis_ticks(file, rig, keys, &mut axes)?;
        let linear = ("canopen.counts_per_metre", &self.counts_per_metre);
        set_linear_ticks(file, rig, linear, required, &mut axes)?;
        Ok(axes)
    }

    /// The heartbeat producer time, ms: 1 to 65535 (0x1017 is UNSIGNED16), whole.
    pub fn heartbeat_ms(&self, file: &Path) -> Result<u16, ConfigError> {
        let Some(ms) = self.heartbeat_ms else {
            return Ok(DEFAULT_HEARTBEAT_MS as u16);
        };
        let ms = check_range(file, "canopen.heartbeat_ms", ms, 1.0, 65535.0)?;
        if ms.fract() != 0.0 {
            return Err(ConfigError::invalid(
                file,
                "canopen.heartbeat_ms",
                ms,
                "must be a whole number",
            ));
        }
        Ok(ms as u16)
    }
}

/// `[dynamixel]`: per axis, tick = zero_tick + rad * ticks_per_turn / 2 pi, or on a prismatic
/// axis (a servo on a lead screw or a rack) zero_tick + m * ticks_per_metre
/// (docs/dynamixel.md). Each key is one number for every axis or one per axis.
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DynamixelConfig {
    /// 4096 when absent (X series: 0.088 deg a tick).
    pub ticks_per_turn: Option<PerAxis>,
    /// 2048 when absent: the centre of an X-series servo's single-turn range.
    pub zero_tick: Option<PerAxis>,
    /// Ticks a metre of a linear axis' travel (ticks_per_turn / the screw's lead or the
    /// pinion's travel a turn, m): one number for every prismatic axis, or one per axis (0
    /// on revolute ones). No default: required for prismatic axes.
    pub ticks_per_metre: Option<PerAxis>,
}

/// Largest ticks (counts) a metre accepted: 2^30, a 1 um increment is 1e6; keeps a metre in
/// 32 bits.
const MAX_TICKS_PER_METRE: f64 = 1_073_741_824.0;

/// Sets each prismatic axis' ticks a metre from `key` (one value for every prismatic axis,
/// or one per axis with 0 on revolute ones); when `required`, a prismatic axis without one
/// is refused, naming the key and the axes.
fn set_linear_ticks(
    file: &Path,
    rig: &Rig,
    (key, given): (&'static str, &Option<PerAxis>),
    required: bool,
    axes: &mut [crate::device::dynamixel::wire::AxisTicks],
) -> Result<(), ConfigError> {
    let prismatic: Vec<&str> = rig
        .joints
        .iter()
        .filter(|j| j.kind == crate::rig::JointKind::Prismatic)
        .map(|j| j.name.as_str())
        .collect();
    let Some(given) = given else {
        if prismatic.is_empty() || !required {
            return Ok(());
        }
        let reason = format!("required for prismatic axes ({})", prismatic.join(", "));
        return Err(ConfigError::invalid(
            file,
            key,
            crate::rig::Verbatim("missing"),
            &reason,
        ));
    };
    if let PerAxis::Each(values) = given
        && values.len() != rig.dof()
    {
        let reason = format!("needs one value per axis ({})", rig.dof());
        return Err(ConfigError::invalid(file, key, values.len(), &reason));
    }
    for (axis, (ticks, joint)) in axes.iter_mut().zip(&rig.joints).enumerate() {
        let value = given.value(axis).unwrap_or_default();
        if joint.kind == crate::rig::JointKind::Revolute {
            if matches!(given, PerAxis::Each(_)) && value != 0.0 {
                let reason = format!("{} is revolute: its entry must be 0", joint.name);
                return Err(ConfigError::invalid(file, key, value, &reason));
            }
            continue;
        }
        ticks.ticks_per_metre = Some(check_range(file, key, value, 1.0, MAX_TICKS_PER_METRE)?);
    }
    Ok(())
}

/// Largest ticks a turn accepted: the finest Dynamixel-P resolution (1,003,846) fits.
const MAX_TICKS_PER_TURN: f64 = 4_194_304.0;

/// A per-axis tick map's two keys, (key, value, lowest, highest): the turn's ticks first,
/// then the zero tick.
type TickKeys<'a> = [(&'static str, &'a Option<PerAxis>, f64, f64); 2];

/// Sets each axis' ticks a turn and zero tick from `keys` where given (one value for every
/// axis, or one per axis), each a whole number within its range; errors name the key.
fn set_axis_ticks(
    file: &Path,
    rig: &Rig,
    keys: TickKeys<'_>,
    axes: &mut [crate::device::dynamixel::wire::AxisTicks],
) -> Result<(), ConfigError> {
    for (index, (key, given, low, high)) in keys.into_iter().enumerate() {
        let Some(given) = given else { continue };
        if let PerAxis::Each(values) = given
            && values.len() != rig.dof()
        {
            let reason = format!("needs one value per axis ({})", rig.dof());
            return Err(ConfigError::invalid(file, key, values.len(), &reason));
        }
        for (axis, ticks) in axes.iter_mut().enumerate() {
            let value = check_range(file, key, given.value(axis).unwrap_or_default(), low, high)?;
            if value.fract() != 0.0 {
                return Err(ConfigError::invalid(
                    file,
                    key,
                    value,
                    "must be a whole number",
                ));
            }
            if index == 0 {
                ticks.ticks_per_turn = value;
            } else {
                ticks.zero_tick = value;
            }
        }
    }
    Ok(())
}

impl DynamixelConfig {
    /// Each axis' tick map, `ticks_per_metre` on prismatic axes (required there); errors
    /// name the key and value.
    pub fn axes(
        &self,
        file: &Path,
        rig: &Rig,
    ) -> Result<Vec<crate::device::dynamixel::wire::AxisTicks>, ConfigError> {
        self.tick_maps(file, rig, true)
    }

    /// Checks the keys given, on load: `ticks_per_metre` is required only when `linear`
    /// (the config's own link is `dynamixel://`).
    pub fn check(&self, file: &Path, rig: &Rig, linear: bool) -> Result<(), ConfigError> {
        self.tick_maps(file, rig, linear).map(drop)
    }

    fn tick_maps(
        &self,
        file: &Path,
        rig: &Rig,
        required: bool,
    ) -> Result<Vec<crate::device::dynamixel::wire::AxisTicks>, ConfigError> {
        let defaults = crate::device::dynamixel::wire::AxisTicks::default();
        let mut axes = vec![defaults; rig.dof()];
        let keys = [
            (
                "dynamixel.ticks_per_turn",
                &self.ticks_per_turn,
                1.0,
                MAX_TICKS_PER_TURN,
            ),
            (
                "dynamixel.zero_tick",
                &self.zero_tick,
                -(crate::device::dynamixel::wire::EXTENDED_RANGE as f64),
                crate::device::dynamixel::wire::EXTENDED_RANGE as f64,
            ),
        ];
        set_axis_ticks(file, rig, keys, &mut axes)?;
        let linear = ("dynamixel.ticks_per_metre", &self.ticks_per_metre);
        set_linear_ticks(file, rig, linear, required, &mut axes)?;
        Ok(axes)
    }
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
    /// Host names (besides IP addresses and `localhost`) clients may reach the daemon under:
    /// a request with any other `Host` header is refused (DNS rebinding).
    #[serde(default)]
    pub hosts: Vec<String>,
    /// The port of the live Foxglove WebSocket server on the bind address
    /// (`docs/foxglove.md`); 0 turns it off. Default 8765, Foxglove's own.
    #[serde(default = "default_foxglove_port")]
    pub foxglove_port: u16,
    /// Let the Foxglove server listen on an address that is not loopback. It has no
    /// authentication (the Foxglove app sends no token): anyone who reaches the port sees
    /// the rigs' state. Off by default; without it such a bind is refused.
    #[serde(default)]
    pub foxglove_allow_remote: bool,
    /// Browser origins the Foxglove server lets in besides the Foxglove app's own
    /// (`docs/foxglove.md`: `https://app.foxglove.dev`, `https://studio.foxglove.dev`,
    /// `file://`) and clients that send none: each `scheme://host[:port]`, or `null`
    /// (which any site can send from a sandboxed frame: add it only when the desktop app
    /// is refused with it). Default none.
    #[serde(default)]
    pub foxglove_origins: Vec<String>,
    /// Who runs the cells' streaming cycles (docs/architecture.md, "The shared executor"):
    /// `shared` (default), a small pool of real-time threads for every cell on the in-process
    /// twin; or `thread_per_cell`, each job's own thread.
    #[serde(default)]
    pub executor: ExecutorKind,
    /// The shared executor's threads (1..=64, default 1).
    #[serde(default = "default_executor_threads")]
    pub executor_threads: usize,
    /// The shared executor's threads keep to the last CPUs, one each, and the daemon's other
    /// threads keep off them (when at least one CPU is left over). Default on.
    #[serde(default = "default_pin_executor")]
    pub pin_executor: bool,
}

/// See [`ServeConfig::executor`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ExecutorKind {
    #[default]
    Shared,
    ThreadPerCell,
}

/// One thread serves 128 cells at 250 Hz on the bench (`cargo bench --bench cells`).
fn default_executor_threads() -> usize {
    1
}

/// On this machine's kernel (no forced preemption) a thread in a system call, the log
/// writers' among them, keeps its CPU until it yields, hundreds of microseconds at times:
/// the executor's wakes are only sure on a CPU of its own (docs/architecture.md).
fn default_pin_executor() -> bool {
    true
}

/// More threads than this would be a thread per cell again, in all but name.
pub const MAX_EXECUTOR_THREADS: usize = 64;

impl Default for ServeConfig {
    fn default() -> Self {
        ServeConfig {
            bind: default_bind(),
            token: None,
            hosts: Vec::new(),
            foxglove_port: default_foxglove_port(),
            foxglove_allow_remote: false,
            foxglove_origins: Vec::new(),
            executor: ExecutorKind::default(),
            executor_threads: default_executor_threads(),
            pin_executor: default_pin_executor(),
        }
    }
}

impl ServeConfig {
    /// The CPUs the shared executor's threads keep to (`pin_executor`): the process's last
    /// `executor_threads` CPUs, when at least one is left for the daemon's other threads;
    /// none otherwise, or for a thread per cell.
    pub fn executor_cpus(&self) -> Vec<usize> {
        if self.executor != ExecutorKind::Shared || !self.pin_executor {
            return Vec::new();
        }
        crate::realtime::reserved_cpus(self.executor_threads).unwrap_or_default()
    }
}

/// Foxglove's default port for a WebSocket connection (the app's *Open connection* dialog
/// offers `ws://localhost:8765`).
pub const DEFAULT_FOXGLOVE_PORT: u16 = 8765;

fn default_foxglove_port() -> u16 {
    DEFAULT_FOXGLOVE_PORT
}

/// Why the Foxglove server may not listen on `bind` at `port`, if it may not: off loopback
/// it is unauthenticated and needs `foxglove_allow_remote = true`.
pub fn foxglove_bind_problem(
    bind: std::net::IpAddr,
    port: u16,
    allow_remote: bool,
) -> Option<String> {
    (port != 0 && !bind.is_loopback() && !allow_remote).then(|| {
        format!(
            "the Foxglove server would listen on {bind}:{port} without authentication (the \
             Foxglove app sends no token): set `foxglove_allow_remote = true` under [serve] \
             to allow it, or `foxglove_port = 0` to turn it off"
        )
    })
}

/// Whether `text` is an `Origin` value: `null`, or a scheme, `://` and a host with an
/// optional port and nothing after it (`file://` has an empty host).
fn is_origin(text: &str) -> bool {
    if text == "null" {
        return true;
    }
    let Some((scheme, host)) = text.split_once("://") else {
        return false;
    };
    let scheme_ok = scheme.starts_with(|c: char| c.is_ascii_alphabetic())
        && scheme
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || "+-.".contains(c));
    scheme_ok && !host.contains(['/', '?', '#', ' ', '@'])
}

/// Never prints the token itself.
impl std::fmt::Debug for ServeConfig {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ServeConfig")
            .field("bind", &self.bind)
            .field("token", &self.token.as_ref().map(|_| "<redacted>"))
            .field("hosts", &self.hosts)
            .field("foxglove_port", &self.foxglove_port)
            .field("foxglove_allow_remote", &self.foxglove_allow_remote)
            .field("foxglove_origins", &self.foxglove_origins)
            .field("executor", &self.executor)
            .field("executor_threads", &self.executor_threads)
            .field("pin_executor", &self.pin_executor)
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
    /// Streaming rate (Hz), 250 when absent: the 4 ms cycle of ABB's Externally Guided
    /// Motion.
    #[serde(default = "default_rate")]
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
    pub fn serial_settings(&self, path: &str, baud: u32) -> crate::transport::SerialSettings {
        let mut settings = crate::transport::SerialSettings::new(path, baud);
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

fn default_rate() -> f64 {
    250.0
}

/// `[stream]` with every key at its default.
fn default_stream() -> StreamConfig {
    // Every key of `[stream]` has a serde default, so the empty table always parses.
    toml::from_str("").expect("every [stream] key has a default")
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

/// `[twin]`, the simulated controller. Every key is optional.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TwinConfig {
    /// Servo bandwidth (Hz), 20 when absent: EGM users report ~20 Hz filtering.
    pub bandwidth_hz: f64,
    /// Transport delay (ms), 12 when absent.
    pub delay_ms: f64,
    /// Cycles without a target before the twin decelerates and holds, 25 when absent.
    pub watchdog_cycles: u32,
    /// The twin's initial position (degrees, metres for prismatic axes). When absent: 0 on
    /// every axis whose range holds 0, else the axis' limit nearest 0.
    pub initial_deg: Vec<f64>,
    /// The protocol version the twin speaks (docs/protocol.md 6.10), 3 when absent: 3
    /// carries I/O (its gripper), 2 plays a controller from before I/O (a program with I/O
    /// is then refused before motion).
    pub protocol_version: u8,
}

impl Default for TwinConfig {
    fn default() -> Self {
        TwinConfig {
            bandwidth_hz: 20.0,
            delay_ms: 12.0,
            watchdog_cycles: 25,
            initial_deg: Vec::new(),
            protocol_version: crate::protocol::PROTOCOL_VERSION_IO,
        }
    }
}

/// `[plan]`: the shares of each axis' max speed and acceleration a plan may use, and the
/// free planner's seed and budget (moves around the cell, `plan_around`). Optional.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PlanConfig {
    /// 0.9 when absent: the rest is headroom for pausing and stopping along the path.
    pub speed_scale: f64,
    /// 0.8 when absent.
    pub accel_scale: f64,
    /// The free planner's seed, 0 when absent: the same seed plans the same path.
    pub free_seed: u64,
    /// The free planner's budget: random configurations drawn before a move around the
    /// cell is refused (`FreePlanOptions::max_samples`' default when absent).
    pub free_max_samples: usize,
}

/// The most random configurations `[plan] free_max_samples` may allow: 50 times the
/// default, about a minute of searching on the demo cell before a refusal, so that one
/// job cannot hold a cell's planner for longer.
const CEILING_FREE_MAX_SAMPLES: usize = 100_000;

impl Default for PlanConfig {
    fn default() -> Self {
        PlanConfig {
            speed_scale: 0.9,
            accel_scale: 0.8,
            free_seed: 0,
            free_max_samples: crate::trajectory::free::DEFAULT_MAX_SAMPLES,
        }
    }
}

/// The default initial position in config units: 0, or the limit nearest 0 for an axis
/// whose range leaves 0 out.
fn default_initial(rig: &Rig) -> Vec<f64> {
    rig.joints
        .iter()
        .map(|joint| {
            let zero = 0.0_f64.clamp(joint.limits.lower, joint.limits.upper);
            joint.kind.to_user(zero)
        })
        .collect()
}

/// The job of a run settings file: the kinds live in [`crate::job`], one file each.
pub use crate::job::Job as JobConfig;

/// A loaded, validated configuration with its rig.
#[derive(Debug, Clone)]
pub struct RunSettings {
    pub file: PathBuf,
    pub config: RunConfig,
    pub rig: Rig,
    /// `rig` ending at the cell tool's TCP ([`Cell::rig_at_tcp`]; `rig` itself without a
    /// tool): what every job is validated and planned with. `rig` keeps its own tool frame
    /// (tool0) for the URDF, the logs, the view and the batch tools.
    pub tcp_rig: Rig,
    /// What the job's app loaded beside `rig` ([`crate::apps::App::load_rig`]), whose
    /// streamed axes `rig` then is.
    pub app_rig: Option<std::sync::Arc<crate::job::AppRig>>,
    /// The workcell `cell` names (the built-in floor when it names none).
    pub cell: Cell,
    /// `rig`'s bodies, the cell's tool and objects: the one collision model of the run.
    pub collision: std::sync::Arc<CollisionModel>,
}

impl RunSettings {
    /// The stream period, `1 / stream.rate_hz` to the nanosecond.
    pub fn period(&self) -> Duration {
        loaded_seconds(1.0 / self.config.stream.rate_hz)
    }

    /// `[twin] delay_ms` as a time.
    pub fn twin_delay(&self) -> Duration {
        loaded_seconds(self.config.twin.delay_ms / 1000.0)
    }

    /// `[stream] reconnect_timeout_s` as a time.
    pub fn reconnect_timeout(&self) -> Duration {
        loaded_seconds(self.config.stream.reconnect_timeout_s)
    }

    /// The twin's initial position: degrees for revolute axes, metres for prismatic ones.
    pub fn initial(&self) -> Vec<f64> {
        to_si(&self.config.twin.initial_deg, &self.rig)
    }
}

/// Seconds from a loaded file as a time. Loading refused what is negative, not finite or
/// out of range, naming the file, key and value (`check_range`); a settings value built by
/// hand past that check becomes zero rather than a panic, and zero is no period any
/// consumer takes (`Trajectory::new` refuses it).
fn loaded_seconds(seconds: f64) -> Duration {
    Duration::try_from_secs_f64(seconds).unwrap_or(Duration::ZERO)
}

/// The axis maps of `[dynamixel]`, `[canopen]` and `[egm]`: the keys given are checked, and
/// what the config's own link needs is required.
fn check_link_axes(file: &Path, config: &RunConfig, rig: &Rig) -> Result<(), ConfigError> {
    use crate::device::LinkSpec;
    let link = config.stream.link.parse::<LinkSpec>().ok();
    let dynamixel = matches!(
        link,
        Some(LinkSpec::Serial {
            dynamixel: Some(_),
            ..
        })
    );
    config.dynamixel.check(file, rig, dynamixel)?;
    let canopen = matches!(link, Some(LinkSpec::Canopen { .. }));
    config.canopen.check(file, rig, canopen)?;
    if matches!(link, Some(LinkSpec::Egm { .. })) || config.egm.external_axes.is_some() {
        config.egm.axes(file, rig)?;
    }
    Ok(())
}

/// Reads and validates run settings and the rig they name, section by section.
pub fn load_run_settings(file: &Path) -> Result<RunSettings, ConfigError> {
    let mut config = parse_run_config(file)?;
    let base_dir = config_dir(file);
    let (rig, app_rig) = load_rigs(&base_dir.join(&config.rig), &config.job)?;
    let cell = load_cell_setting(file, &base_dir, config.cell.as_ref())?;
    // Every job is validated and planned at the cell tool's TCP (the pen's tip), not at
    // tool0: a pose in a job is where the tool does its work.
    let tcp_rig = cell.rig_at_tcp(&rig);
    check_links(file, &config, &rig)?;
    config.twin.check(file, &rig)?;
    config.plan.check(file)?;
    check_limits(file, &config.limits)?;
    let context = crate::job::JobContext {
        rig: &tcp_rig,
        cell: &cell,
        app_rig: app_rig.as_deref(),
        base_dir: &base_dir,
        limits: &config.limits,
        period: loaded_seconds(1.0 / config.stream.rate_hz),
    };
    config.job = config
        .job
        .validate(&context)
        .map_err(|e| job_refused(file, e))?;
    config.ros2.check(file)?;
    config.ros2.check_namespace(file, &rig)?;
    config.serve.check(file)?;
    let collision = CollisionModel::new(&rig, &cell).map_err(|e| cell_refused(file, &config, e))?;
    Ok(RunSettings {
        file: file.to_path_buf(),
        config,
        rig,
        tcp_rig,
        app_rig,
        cell,
        collision: std::sync::Arc::new(collision),
    })
}

/// The cell of the `cell` key: a file (relative to the settings' directory), a `[cell]`
/// section, or the built-in floor when absent.
fn load_cell_setting(
    file: &Path,
    base_dir: &Path,
    setting: Option<&toml::Value>,
) -> Result<Cell, ConfigError> {
    match setting {
        None => Ok(Cell::builtin()),
        Some(toml::Value::String(name)) => load_cell(&base_dir.join(name)).map_err(|e| match e {
            CellError::Config(e) => e,
            other => ConfigError::invalid(file, "cell", name, &other.to_string()),
        }),
        Some(toml::Value::Table(table)) => {
            let raw: RawCell =
                toml::Value::Table(table.clone())
                    .try_into()
                    .map_err(|e: toml::de::Error| ConfigError::Parse {
                        file: file.to_path_buf(),
                        message: format!("[cell]: {}", e.message()),
                    })?;
            cell_from_raw(&raw, file, "cell.")
        }
        Some(other) => Err(ConfigError::invalid(
            file,
            "cell",
            Verbatim(other.to_string()),
            "a cell file's name (\"cell.toml\") or a [cell] section",
        )),
    }
}

/// A cell that loaded but does not fit the rig (a pair naming no body, a half-space on a
/// link), as the settings' error naming the `cell` key.
fn cell_refused(file: &Path, config: &RunConfig, e: CellError) -> ConfigError {
    let value = match &config.cell {
        Some(toml::Value::String(name)) => name.shown(),
        Some(_) => "[cell]".to_string(),
        None => "(built in)".to_string(),
    };
    match e {
        CellError::Config(e) => e,
        other => ConfigError::invalid(file, "cell", Verbatim(value), &other.to_string()),
    }
}

/// `file` read (a shipped config by its name too) and parsed, not yet checked.
fn parse_run_config(file: &Path) -> Result<RunConfig, ConfigError> {
    let text = crate::rig::shipped::read(file)?;
    toml::from_str(&text).map_err(|e| ConfigError::Parse {
        file: file.to_path_buf(),
        message: e.to_string().trim_end().to_string(),
    })
}

/// The rig at `rig_path`, loaded by the job's app when it is an app's (with what the app
/// keeps beside it).
fn load_rigs(rig_path: &Path, job: &JobConfig) -> Result<crate::apps::LoadedRig, ConfigError> {
    match crate::apps::app_of(job) {
        Some(app) => app.load_rig(rig_path),
        None => Ok((load_rig(rig_path)?, None)),
    }
}

/// `[stream]` and the link sections it points at (`[dynamixel]`, `[canopen]`).
fn check_links(file: &Path, config: &RunConfig, rig: &Rig) -> Result<(), ConfigError> {
    let stream = &config.stream;
    check_range(file, "stream.rate_hz", stream.rate_hz, 1.0, 1000.0)?;
    if let Err(e) = stream.link.parse::<crate::device::LinkSpec>() {
        return Err(ConfigError::invalid(
            file,
            "stream.link",
            &stream.link,
            &e.reason,
        ));
    }
    if !matches!(stream.serial_stop_bits, 1 | 2) {
        return Err(ConfigError::invalid(
            file,
            "stream.serial_stop_bits",
            stream.serial_stop_bits,
            "must be 1 or 2",
        ));
    }
    check_range(
        file,
        "stream.reconnect_timeout_s",
        stream.reconnect_timeout_s,
        0.0,
        3600.0,
    )?;
    stream.tolerances(file, rig)?;
    check_link_axes(file, config, rig)?;
    config.canopen.heartbeat_ms(file)?;
    if stream.can_base_id > MAX_CAN_BASE_ID {
        return Err(ConfigError::invalid(
            file,
            "stream.can_base_id",
            crate::rig::Verbatim(format!("{:#x}", stream.can_base_id)),
            &format!(
                "must be at most {MAX_CAN_BASE_ID:#x}: the protocol's {CAN_ID_BLOCK:#x} \
                 identifiers from the base must fit the 11-bit range"
            ),
        ));
    }
    Ok(())
}

impl TwinConfig {
    /// Checks `[twin]`, filling in the default initial position when it is absent.
    fn check(&mut self, file: &Path, rig: &Rig) -> Result<(), ConfigError> {
        check_range(file, "twin.bandwidth_hz", self.bandwidth_hz, 0.1, 1000.0)?;
        check_range(file, "twin.delay_ms", self.delay_ms, 0.0, 1000.0)?;
        if self.watchdog_cycles == 0 {
            return Err(ConfigError::invalid(
                file,
                "twin.watchdog_cycles",
                0,
                "must be at least 1",
            ));
        }
        if !(crate::protocol::codec::PROTOCOL_VERSION..=crate::protocol::PROTOCOL_VERSION_IO)
            .contains(&self.protocol_version)
        {
            return Err(ConfigError::invalid(
                file,
                "twin.protocol_version",
                self.protocol_version,
                "must be 2 or 3 (docs/protocol.md 6.10)",
            ));
        }
        if self.initial_deg.is_empty() {
            self.initial_deg = default_initial(rig);
        }
        check_joints(file, "twin.initial_deg", &self.initial_deg, rig)
    }
}

impl PlanConfig {
    fn check(&self, file: &Path) -> Result<(), ConfigError> {
        check_range(file, "plan.speed_scale", self.speed_scale, 0.01, 0.99)?;
        check_range(file, "plan.accel_scale", self.accel_scale, 0.01, 0.99)?;
        if !(1..=CEILING_FREE_MAX_SAMPLES).contains(&self.free_max_samples) {
            return Err(ConfigError::invalid(
                file,
                "plan.free_max_samples",
                self.free_max_samples,
                &format!("must lie in [1, {CEILING_FREE_MAX_SAMPLES}]"),
            ));
        }
        Ok(())
    }
}

/// `[limits]`: each cap positive, and no wider than a config may set (`crate::job`'s
/// ceilings).
fn check_limits(file: &Path, limits: &crate::job::JobLimits) -> Result<(), ConfigError> {
    use crate::job::{CEILING_DURATION_S, CEILING_PLAN_MB, CEILING_POINTS};
    let duration = limits.max_job_duration_s;
    check_range(
        file,
        "limits.max_job_duration_s",
        duration,
        1.0,
        CEILING_DURATION_S,
    )?;
    check_range(
        file,
        "limits.max_plan_mb",
        limits.max_plan_mb,
        1.0,
        CEILING_PLAN_MB,
    )?;
    if !(2..=CEILING_POINTS).contains(&limits.max_job_points) {
        return Err(ConfigError::invalid(
            file,
            "limits.max_job_points",
            limits.max_job_points,
            &format!("must lie in [2, {CEILING_POINTS}]"),
        ));
    }
    Ok(())
}

impl Ros2Config {
    /// The rig's name becomes the ROS 2 namespace when the rig joins a graph: it must be
    /// one.
    fn check_namespace(&self, file: &Path, rig: &Rig) -> Result<(), ConfigError> {
        if self.present
            && self.zenoh_connect.is_none()
            && let Err(e) = crate::ros2::graph::check_namespace(&rig.name)
        {
            return Err(ConfigError::invalid(
                file,
                "ros2.middleware",
                "dds",
                &e.to_string(),
            ));
        }
        if self.zenoh_connect.is_some()
            && let Err(e) = crate::ros2::graph::check_namespace(&rig.name)
        {
            return Err(ConfigError::invalid(
                file,
                "ros2.zenoh_connect",
                self.zenoh_connect.as_deref().unwrap_or_default(),
                &e.to_string(),
            ));
        }
        Ok(())
    }
}

impl ServeConfig {
    fn check(&self, file: &Path) -> Result<(), ConfigError> {
        let Ok(bind) = self.bind.parse::<std::net::IpAddr>() else {
            return Err(ConfigError::invalid(
                file,
                "serve.bind",
                &self.bind,
                "must be an IP address, such as 127.0.0.1 or 0.0.0.0",
            ));
        };
        if let Some(reason) =
            foxglove_bind_problem(bind, self.foxglove_port, self.foxglove_allow_remote)
        {
            return Err(ConfigError::invalid(
                file,
                "serve.foxglove_allow_remote",
                crate::rig::Verbatim(self.foxglove_allow_remote),
                &reason,
            ));
        }
        if let Some(bad) = self.foxglove_origins.iter().find(|o| !is_origin(o)) {
            return Err(ConfigError::invalid(
                file,
                "serve.foxglove_origins",
                bad,
                "each must be an origin as a browser sends it, `scheme://host[:port]` with no \
                 path (`https://app.example.com`), or `null`",
            ));
        }
        if !(1..=MAX_EXECUTOR_THREADS).contains(&self.executor_threads) {
            return Err(ConfigError::invalid(
                file,
                "serve.executor_threads",
                self.executor_threads,
                &format!("must be 1..={MAX_EXECUTOR_THREADS}"),
            ));
        }
        if let Some(reason) = self.token.as_deref().and_then(token_problem) {
            return Err(ConfigError::invalid(
                file,
                "serve.token",
                crate::rig::Verbatim("<redacted>"),
                reason,
            ));
        }
        Ok(())
    }
}

/// The directory files named in `file` are relative to.
pub fn config_dir(file: &Path) -> PathBuf {
    match file.parent() {
        Some(dir) if !dir.as_os_str().is_empty() => dir.to_path_buf(),
        _ => PathBuf::from("."),
    }
}

/// Config joint values in SI units: revolute axes are written in degrees, prismatic ones in
/// metres.
fn to_si(values: &[f64], rig: &Rig) -> Vec<f64> {
    crate::job::to_si(values, rig)
}

fn check_joints(file: &Path, key: &str, values: &[f64], rig: &Rig) -> Result<(), ConfigError> {
    crate::job::check_joints(key, values, rig).map_err(|e| job_refused(file, e))
}

/// A refused job as a config error: the same key, value and reason, and a file that would
/// not load (only the config's author reads this) with its own error after the reason.
fn job_refused(file: &Path, e: crate::job::JobInvalid) -> ConfigError {
    let reason = match &e.cause {
        Some(cause) => format!("{}: {}", e.reason, super::error_chain(cause.as_ref())),
        None => e.reason,
    };
    ConfigError::Invalid {
        file: file.to_path_buf(),
        key: e.key,
        value: e.value,
        reason,
    }
}
