//! Loading rigs from `config/`: TOML descriptions (validated, every error naming the file,
//! the key and the bad value) and URDF files. Owns the file formats only; the model itself
//! lives in the parent module.

use super::geometry::{RawBody, bodies_from_raw, check_pairs};
use super::{Joint, JointKind, JointLimits, Rig};
use glam::{DAffine3, DQuat, DVec3, EulerRot};
use serde::Deserialize;
use std::collections::HashSet;
use std::path::{Path, PathBuf};
use thiserror::Error;

#[derive(Debug, Error)]
pub enum ConfigError {
    #[error("{file}: cannot read (looked for {looked})")]
    Io {
        file: PathBuf,
        /// Where it was looked for, absolute (see [`super::shipped::read`]).
        looked: String,
        source: std::io::Error,
    },
    #[error("{file}: no such built-in file (built in: {names})")]
    NotShipped { file: PathBuf, names: String },
    #[error("{file}: {message}")]
    Parse { file: PathBuf, message: String },
    #[error("{file}: key `{key}` = {value}: {reason}")]
    Invalid {
        file: PathBuf,
        key: String,
        value: String,
        reason: String,
    },
}

impl ConfigError {
    /// `key` in `file` holds `value`, refused for `reason`.
    pub fn invalid(file: &Path, key: &str, value: impl Shown, reason: &str) -> Self {
        ConfigError::Invalid {
            file: file.to_path_buf(),
            key: key.to_string(),
            value: value.shown(),
            reason: reason.to_string(),
        }
    }
}

/// `value` of `key` in `file` when it is finite and within `[low, high]`.
pub fn check_range(
    file: &Path,
    key: &str,
    value: f64,
    low: f64,
    high: f64,
) -> Result<f64, ConfigError> {
    if value.is_finite() && value >= low && value <= high {
        Ok(value)
    } else {
        Err(ConfigError::invalid(
            file,
            key,
            value,
            &format!("must lie in [{low}, {high}]"),
        ))
    }
}

/// Reads a rig from a TOML description or a URDF file (a shipped one or one on disk).
pub fn load_rig(path: &Path) -> Result<Rig, ConfigError> {
    load_rig_with_tool(path, None)
}

/// True when `text` is XML (a URDF): TOML cannot start with `<`, so the content decides,
/// whatever the file's extension.
fn is_xml(text: &str) -> bool {
    text.trim_start_matches('\u{feff}')
        .trim_start()
        .starts_with('<')
}

/// [`load_rig`] ending at `tool_frame` when given: any link of a URDF; for a TOML rig, only
/// the frame its file names (a TOML rig has one tool frame).
pub fn load_rig_with_tool(path: &Path, tool_frame: Option<&str>) -> Result<Rig, ConfigError> {
    refuse_oversized(path)?;
    let text = super::shipped::read(path)?;
    if is_xml(&text) || path.extension().is_some_and(|e| e == "urdf") {
        return super::urdf::rig_from_urdf_to(&text, path, tool_frame);
    }
    let rig = rig_from_toml(&text, path)?;
    match tool_frame {
        Some(frame) if frame != rig.tool_frame => Err(ConfigError::invalid(
            path,
            "tool_frame",
            rig.tool_frame.as_str(),
            &format!(
                "a TOML rig has the one tool frame it names, not `{frame}` (choosing among \
                 frames applies to URDF rigs)"
            ),
        )),
        _ => Ok(rig),
    }
}

/// Refuses a rig file on disk larger than [`super::MAX_URDF_BYTES`] before reading it: no
/// rig, TOML or URDF, comes near that, and reading one whole is what the parser would do.
/// A file whose size cannot be read is left to the reader, which says why.
fn refuse_oversized(path: &Path) -> Result<(), ConfigError> {
    let Ok(meta) = std::fs::metadata(path) else {
        return Ok(());
    };
    if meta.len() <= super::MAX_URDF_BYTES as u64 {
        return Ok(());
    }
    Err(ConfigError::invalid(
        path,
        "(file size)",
        Verbatim(format!("{} bytes", meta.len())),
        &format!("a rig file is at most {} bytes", super::MAX_URDF_BYTES),
    ))
}

/// Parses a rig description; `file` is only used to name the source in errors.
pub fn rig_from_toml(text: &str, file: &Path) -> Result<Rig, ConfigError> {
    let raw: RawRig = toml::from_str(text).map_err(|e| ConfigError::Parse {
        file: file.to_path_buf(),
        message: e.to_string().trim_end().to_string(),
    })?;
    raw.validate(file)
}

/// A value as a message shows it: numbers and lists as TOML writes them, text quoted, a
/// missing value as `missing` (never Rust's debug form, such as `Some(120.0)`).
pub trait Shown {
    fn shown(&self) -> String;
}

impl Shown for f64 {
    /// As TOML writes a float: a whole number keeps its `.0`.
    fn shown(&self) -> String {
        if self.is_finite() && self.fract() == 0.0 && self.abs() < 1e15 {
            format!("{self:.1}")
        } else {
            self.to_string()
        }
    }
}

impl Shown for str {
    fn shown(&self) -> String {
        format!("\"{}\"", self.escape_default())
    }
}

impl Shown for String {
    fn shown(&self) -> String {
        self.as_str().shown()
    }
}

impl<T: Shown + ?Sized> Shown for &T {
    fn shown(&self) -> String {
        (**self).shown()
    }
}

impl<T: Shown> Shown for Option<T> {
    fn shown(&self) -> String {
        self.as_ref()
            .map_or_else(|| "missing".to_string(), T::shown)
    }
}

impl<T: Shown> Shown for [T] {
    fn shown(&self) -> String {
        let items: Vec<String> = self.iter().map(T::shown).collect();
        format!("[{}]", items.join(", "))
    }
}

impl<T: Shown, const N: usize> Shown for [T; N] {
    fn shown(&self) -> String {
        self.as_slice().shown()
    }
}

impl<T: Shown> Shown for Vec<T> {
    fn shown(&self) -> String {
        self.as_slice().shown()
    }
}

/// Text that is shown as is, not quoted: a placeholder such as `[]` or a formatted number.
pub struct Verbatim<T>(pub T);

impl<T: std::fmt::Display> Shown for Verbatim<T> {
    fn shown(&self) -> String {
        self.0.to_string()
    }
}

macro_rules! shown_as_display {
    ($($t:ty),*) => { $(impl Shown for $t { fn shown(&self) -> String { self.to_string() } })* };
}
shown_as_display!(u8, u16, u32, u64, usize, i32, i64, bool);

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawRig {
    name: String,
    base_frame: String,
    tool_frame: String,
    joint: Vec<RawJoint>,
    #[serde(default)]
    tool: RawOrigin,
    /// Pairs of bodies never checked (adjacent links; `rigbridge config allowed-pairs`).
    #[serde(default)]
    allowed_pairs: Vec<(String, String)>,
    /// Per-link collision geometry (docs/cell.md, "The rig's body").
    #[serde(default)]
    body: Vec<RawBody>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct RawOrigin {
    #[serde(default)]
    origin_xyz_m: [f64; 3],
    #[serde(default)]
    origin_rpy_deg: [f64; 3],
}

/// One `[[joint]]` table: the joint schema other rig formats (the sloth's limbs) reuse.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct RawJoint {
    name: String,
    kind: RawKind,
    #[serde(default)]
    origin_xyz_m: [f64; 3],
    #[serde(default)]
    origin_rpy_deg: [f64; 3],
    axis: [f64; 3],
    lower_deg: Option<f64>,
    upper_deg: Option<f64>,
    max_speed_deg_s: Option<f64>,
    max_accel_deg_s2: Option<f64>,
    lower_m: Option<f64>,
    upper_m: Option<f64>,
    max_speed_m_s: Option<f64>,
    max_accel_m_s2: Option<f64>,
}

#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(rename_all = "lowercase")]
enum RawKind {
    Revolute,
    Prismatic,
}

/// The largest magnitude an i32 of micro-units carries: every position, speed and
/// acceleration the protocol sends (docs/protocol.md 1).
const WIRE_LIMIT: f64 = i32::MAX as f64 / 1e6;

pub(crate) struct Checker<'a> {
    pub(crate) file: &'a Path,
    /// Where the joint tables sit in the file (`""` for a rig, `limb[2].` for a sloth limb).
    pub(crate) prefix: &'a str,
}

impl Checker<'_> {
    fn invalid(&self, key: String, value: impl Shown, reason: &str) -> ConfigError {
        ConfigError::invalid(self.file, &key, value, reason)
    }

    pub(crate) fn finite3(&self, key: String, v: [f64; 3]) -> Result<DVec3, ConfigError> {
        if v.iter().all(|x| x.is_finite()) {
            Ok(DVec3::from_array(v))
        } else {
            Err(self.invalid(key, v, "every component must be a finite number"))
        }
    }

    fn origin(
        &self,
        prefix: &str,
        xyz: [f64; 3],
        rpy_deg: [f64; 3],
    ) -> Result<DAffine3, ConfigError> {
        let translation = self.finite3(format!("{prefix}origin_xyz_m"), xyz)?;
        let rpy = self.finite3(format!("{prefix}origin_rpy_deg"), rpy_deg)?;
        Ok(origin_from_xyz_rpy(
            translation,
            rpy * (std::f64::consts::PI / 180.0),
        ))
    }

    fn required(&self, key: String, value: Option<f64>, kind: &str) -> Result<f64, ConfigError> {
        match value {
            Some(v) if v.is_finite() => Ok(v),
            Some(v) => Err(self.invalid(key, v, "must be a finite number")),
            None => Err(self.invalid(
                key,
                Verbatim("missing"),
                &format!("required for a {kind} joint"),
            )),
        }
    }

    fn forbidden(&self, key: String, value: Option<f64>, kind: &str) -> Result<(), ConfigError> {
        match value {
            Some(v) => Err(self.invalid(key, v, &format!("not allowed on a {kind} joint"))),
            None => Ok(()),
        }
    }

    fn limits(&self, key: &str, raw: &RawJoint) -> Result<(JointKind, JointLimits), ConfigError> {
        let k = |field: &str| format!("{key}.{field}");
        let (kind, unit_scale, values, others) = match raw.kind {
            RawKind::Revolute => (
                JointKind::Revolute,
                std::f64::consts::PI / 180.0,
                [
                    ("lower_deg", raw.lower_deg),
                    ("upper_deg", raw.upper_deg),
                    ("max_speed_deg_s", raw.max_speed_deg_s),
                    ("max_accel_deg_s2", raw.max_accel_deg_s2),
                ],
                [
                    ("lower_m", raw.lower_m),
                    ("upper_m", raw.upper_m),
                    ("max_speed_m_s", raw.max_speed_m_s),
                    ("max_accel_m_s2", raw.max_accel_m_s2),
                ],
            ),
            RawKind::Prismatic => (
                JointKind::Prismatic,
                1.0,
                [
                    ("lower_m", raw.lower_m),
                    ("upper_m", raw.upper_m),
                    ("max_speed_m_s", raw.max_speed_m_s),
                    ("max_accel_m_s2", raw.max_accel_m_s2),
                ],
                [
                    ("lower_deg", raw.lower_deg),
                    ("upper_deg", raw.upper_deg),
                    ("max_speed_deg_s", raw.max_speed_deg_s),
                    ("max_accel_deg_s2", raw.max_accel_deg_s2),
                ],
            ),
        };
        let kind_name = match kind {
            JointKind::Revolute => "revolute",
            JointKind::Prismatic => "prismatic",
        };
        for (field, value) in others {
            self.forbidden(k(field), value, kind_name)?;
        }
        let mut v = [0.0; 4];
        for (slot, (field, value)) in v.iter_mut().zip(values) {
            *slot = self.required(k(field), value, kind_name)?;
        }
        let [lower, upper, speed, accel] = v;
        if lower >= upper {
            return Err(self.invalid(
                k(values[1].0),
                upper,
                &format!("must be above {} = {lower}", values[0].0),
            ));
        }
        if speed <= 0.0 {
            return Err(self.invalid(k(values[2].0), speed, "must be positive"));
        }
        if accel <= 0.0 {
            return Err(self.invalid(k(values[3].0), accel, "must be positive"));
        }
        // Every limit must travel on the wire (docs/protocol.md 1): i32 of micro-units.
        for (value, (field, _)) in v.iter().zip(values) {
            if (value * unit_scale).abs() > WIRE_LIMIT {
                let reason =
                    format!("is beyond the wire range of ±{WIRE_LIMIT} (rad, m, per s or per s²)");
                return Err(self.invalid(k(field), value, &reason));
            }
        }
        Ok((
            kind,
            JointLimits {
                lower: lower * unit_scale,
                upper: upper * unit_scale,
                max_speed: speed * unit_scale,
                max_acceleration: accel * unit_scale,
            },
        ))
    }

    fn joint(&self, index: usize, raw: &RawJoint) -> Result<Joint, ConfigError> {
        let key = format!("{}joint[{index}]", self.prefix);
        if raw.name.trim().is_empty() {
            return Err(self.invalid(format!("{key}.name"), &raw.name, "must not be empty"));
        }
        let axis = self.finite3(format!("{key}.axis"), raw.axis)?;
        if axis.length() < 1e-9 {
            return Err(self.invalid(
                format!("{key}.axis"),
                raw.axis,
                "must not be the zero vector",
            ));
        }
        let (kind, limits) = self.limits(&key, raw)?;
        Ok(Joint {
            name: raw.name.clone(),
            kind,
            origin: self.origin(&format!("{key}."), raw.origin_xyz_m, raw.origin_rpy_deg)?,
            axis: axis.normalize(),
            limits,
        })
    }
}

/// URDF's convention: rotate about fixed x (roll), then y (pitch), then z (yaw).
pub(crate) fn origin_from_xyz_rpy(xyz: DVec3, rpy_rad: DVec3) -> DAffine3 {
    let rotation = DQuat::from_euler(EulerRot::ZYX, rpy_rad.z, rpy_rad.y, rpy_rad.x);
    DAffine3::from_rotation_translation(rotation, xyz)
}

/// Validates joint tables found under `prefix` (`""` for a rig file): at least one, unique
/// names, every field checked as in a rig file.
pub(crate) fn joints_from_raw(
    file: &Path,
    prefix: &str,
    raw: &[RawJoint],
) -> Result<Vec<Joint>, ConfigError> {
    let checker = Checker { file, prefix };
    if raw.is_empty() {
        return Err(checker.invalid(
            format!("{prefix}joint"),
            crate::rig::Verbatim("[]"),
            "a chain needs at least one joint",
        ));
    }
    let mut seen = HashSet::new();
    let mut joints = Vec::with_capacity(raw.len());
    for (index, joint) in raw.iter().enumerate() {
        if !seen.insert(joint.name.as_str()) {
            return Err(checker.invalid(
                format!("{prefix}joint[{index}].name"),
                &joint.name,
                "duplicate joint name",
            ));
        }
        joints.push(checker.joint(index, joint)?);
    }
    Ok(joints)
}

/// A validated fixed transform from an origin table named `key_prefix` (e.g. `tool.`).
pub(crate) fn origin_from_raw(
    file: &Path,
    key_prefix: &str,
    raw: &RawOrigin,
) -> Result<DAffine3, ConfigError> {
    Checker { file, prefix: "" }.origin(key_prefix, raw.origin_xyz_m, raw.origin_rpy_deg)
}

impl RawRig {
    fn validate(self, file: &Path) -> Result<Rig, ConfigError> {
        let checker = Checker { file, prefix: "" };
        for (key, value) in [
            ("name", &self.name),
            ("base_frame", &self.base_frame),
            ("tool_frame", &self.tool_frame),
        ] {
            if value.trim().is_empty() {
                return Err(checker.invalid(key.to_string(), value, "must not be empty"));
            }
        }
        let joints = joints_from_raw(file, "", &self.joint)?;
        let tool = origin_from_raw(file, "tool.", &self.tool)?;
        let read_mesh = |key: &str, name: &str| super::mesh::read_hull_points(file, key, name);
        let bodies = bodies_from_raw(file, &self.body, joints.len(), &read_mesh)?;
        check_pairs(file, "allowed_pairs", &self.allowed_pairs, |name| {
            bodies.iter().any(|b| b.name == name)
        })?;
        Ok(Rig {
            name: self.name,
            base_frame: self.base_frame,
            tool_frame: self.tool_frame,
            joints,
            tool,
            bodies,
            allowed_pairs: self.allowed_pairs,
        })
    }
}
