//! Terrain and walks from a file (`config/forest.toml`): named supports (cylinders) and
//! named walks over them. Owns loading and validating the file (every error naming the
//! file, the key and the value) and turning a walk into a [`Scenario`] (its terrain and
//! route); it must not place feet or judge a gait.

use super::body::WORLD_UP;
use super::scenario::{CYCLES, Leg, Route, Scenario, ScenarioError};
use super::terrain::{Cylinder, Terrain, segment_nearest};
use crate::rig::{ConfigError, check_range};
use glam::DVec3;
use serde::Deserialize;
use std::path::{Path, PathBuf};
use thiserror::Error;

/// How far apart (beyond the sum of their radii) two consecutive supports' axes may pass
/// and still count as meeting: a sloth's reach spans that, a wider gap is a jump.
pub const MEET_SLACK_M: f64 = 0.05;
/// Shortest support: shorter ones are typing errors (`from_m` = `to_m`), not branches.
const MIN_SUPPORT_LENGTH_M: f64 = 1e-3;

#[derive(Debug, Error)]
pub enum ForestError {
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error("{file}: no walk named `{walk}`: the file's walks are {known}")]
    UnknownWalk {
        file: PathBuf,
        walk: String,
        known: String,
    },
    #[error(transparent)]
    Scenario(#[from] ScenarioError),
}

/// A loaded forest: every walk of the file already turned into its scenario (so a walk
/// that cannot be built is refused on load, not when it is run).
#[derive(Debug, Clone)]
pub struct Forest {
    pub file: PathBuf,
    walks: Vec<Scenario>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawForest {
    #[serde(default)]
    support: Vec<RawSupport>,
    #[serde(default)]
    walk: Vec<RawWalk>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawSupport {
    name: String,
    from_m: [f64; 3],
    to_m: [f64; 3],
    radius_m: f64,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawWalk {
    name: String,
    supports: Vec<String>,
    start_m: f64,
    toward_trunk: Option<[f64; 3]>,
}

/// A validated support with its name.
struct Named {
    name: String,
    cylinder: Cylinder,
}

impl Forest {
    /// Reads and validates a forest file. `trunk_tilt_rad` is the sloth's `[gait]
    /// trunk_tilt_deg`: a support tilted more is a trunk, which decides each leg's up.
    pub fn load(file: &Path, trunk_tilt_rad: f64) -> Result<Forest, ConfigError> {
        let text = crate::rig::shipped::read(file)?;
        let raw: RawForest = toml::from_str(&text).map_err(|e| ConfigError::Parse {
            file: file.to_path_buf(),
            message: e.to_string().trim_end().to_string(),
        })?;
        let supports = raw
            .support
            .iter()
            .enumerate()
            .map(|(i, s)| support(file, i, s))
            .collect::<Result<Vec<_>, _>>()?;
        check_unique(file, "support", supports.iter().map(|s| s.name.as_str()))?;
        if raw.walk.is_empty() {
            return Err(ConfigError::invalid(
                file,
                "walk",
                crate::rig::Verbatim("[]"),
                "needs at least one [[walk]]",
            ));
        }
        check_unique(file, "walk", raw.walk.iter().map(|w| w.name.as_str()))?;
        let walks = raw
            .walk
            .iter()
            .enumerate()
            .map(|(i, w)| {
                WalkBuilder {
                    file,
                    key: format!("walk[{i}]"),
                    walk: w,
                    supports: &supports,
                    trunk_tilt_rad,
                }
                .scenario()
            })
            .collect::<Result<Vec<_>, _>>()?;
        Ok(Forest {
            file: file.to_path_buf(),
            walks,
        })
    }

    /// The walks' names, in file order.
    pub fn walk_names(&self) -> impl Iterator<Item = &str> {
        self.walks.iter().map(|w| w.name.as_str())
    }

    /// The scenario of the walk named `walk`.
    pub fn scenario(&self, walk: &str) -> Result<Scenario, ForestError> {
        self.walks
            .iter()
            .find(|w| w.name == walk)
            .cloned()
            .ok_or_else(|| ForestError::UnknownWalk {
                file: self.file.clone(),
                walk: walk.to_string(),
                known: self.walk_names().collect::<Vec<_>>().join(", "),
            })
    }
}

/// The scenario called `name`: the walk of that name in the forest file `forest` when one
/// is given (which holds all its geometry, so `angle_deg` and `gap_m` are refused), else
/// the built-in scenario.
pub fn scenario_named(
    name: &str,
    angle_deg: Option<f64>,
    gap_m: Option<f64>,
    forest: Option<&Path>,
    trunk_tilt_rad: f64,
) -> Result<Scenario, ForestError> {
    let Some(file) = forest else {
        return Ok(Scenario::build(name, angle_deg, gap_m)?);
    };
    let unused = |what: &'static str| ScenarioError::Unused {
        scenario: name.into(),
        name: what,
    };
    if angle_deg.is_some() {
        return Err(unused("angle").into());
    }
    if gap_m.is_some() {
        return Err(unused("gap").into());
    }
    Forest::load(file, trunk_tilt_rad)?.scenario(name)
}

fn finite3(file: &Path, key: &str, v: [f64; 3]) -> Result<DVec3, ConfigError> {
    if v.iter().all(|x| x.is_finite()) {
        Ok(DVec3::from_array(v))
    } else {
        Err(ConfigError::invalid(
            file,
            key,
            v,
            "every component must be a finite number",
        ))
    }
}

fn support(file: &Path, index: usize, raw: &RawSupport) -> Result<Named, ConfigError> {
    let key = |field: &str| format!("support[{index}].{field}");
    if raw.name.is_empty() {
        return Err(ConfigError::invalid(
            file,
            &key("name"),
            &raw.name,
            "must not be empty",
        ));
    }
    let from = finite3(file, &key("from_m"), raw.from_m)?;
    let to = finite3(file, &key("to_m"), raw.to_m)?;
    if from.distance(to) < MIN_SUPPORT_LENGTH_M {
        return Err(ConfigError::invalid(
            file,
            &key("to_m"),
            raw.to_m,
            &format!(
                "support {} must be at least {MIN_SUPPORT_LENGTH_M} m long: from_m is [{}, {}, {}]",
                raw.name, raw.from_m[0], raw.from_m[1], raw.from_m[2]
            ),
        ));
    }
    if !(raw.radius_m.is_finite() && raw.radius_m > 0.0) {
        return Err(ConfigError::invalid(
            file,
            &key("radius_m"),
            raw.radius_m,
            "must be a finite number above 0",
        ));
    }
    Ok(Named {
        name: raw.name.clone(),
        cylinder: Cylinder {
            from,
            to,
            radius: raw.radius_m,
        },
    })
}

/// Refuses the second of two `[[table]]` entries with the same name.
fn check_unique<'a>(
    file: &Path,
    table: &str,
    names: impl Iterator<Item = &'a str>,
) -> Result<(), ConfigError> {
    let mut seen: Vec<&str> = Vec::new();
    for (i, name) in names.enumerate() {
        if let Some(first) = seen.iter().position(|n| *n == name) {
            return Err(ConfigError::invalid(
                file,
                &format!("{table}[{i}].name"),
                name,
                &format!("{table}[{first}] has that name already: names must be unique"),
            ));
        }
        seen.push(name);
    }
    Ok(())
}

/// Turns one `[[walk]]` into a scenario.
struct WalkBuilder<'a> {
    file: &'a Path,
    /// `walk[i]`: where the walk sits in the file.
    key: String,
    walk: &'a RawWalk,
    supports: &'a [Named],
    trunk_tilt_rad: f64,
}

impl WalkBuilder<'_> {
    fn invalid(&self, field: &str, value: impl crate::rig::Shown, reason: &str) -> ConfigError {
        ConfigError::invalid(self.file, &format!("{}.{field}", self.key), value, reason)
    }

    fn scenario(&self) -> Result<Scenario, ConfigError> {
        let walked = self.walked()?;
        // The terrain is the walk's own supports, each once, in order of first appearance.
        let mut terrain = Terrain::default();
        let mut indices = Vec::with_capacity(walked.len());
        for (position, named) in walked.iter().enumerate() {
            let first = walked[..position]
                .iter()
                .position(|other| other.name == named.name);
            indices.push(first.map_or(terrain.cylinders.len(), |p| indices[p]));
            if first.is_none() {
                terrain.cylinders.push(named.cylinder);
            }
        }
        let first = &walked[0].cylinder;
        let start_s = check_range(
            self.file,
            &format!("{}.start_m", self.key),
            self.walk.start_m,
            0.0,
            first.length(),
        )?;
        let mut legs = vec![Leg {
            start_s: 0.0,
            origin: first.from,
            direction: first.direction(),
            left: indices[0],
            right: indices[0],
            up: self.first_up(first)?,
            twist_rad_per_m: 0.0,
        }];
        for position in 1..walked.len() {
            let leg = self.next_leg(&legs[position - 1], &walked, position, indices[position])?;
            legs.push(leg);
        }
        Ok(Scenario {
            name: self.walk.name.clone(),
            angle_deg: None,
            gap_m: None,
            terrain,
            route: Route { legs },
            start_s,
            cycles: CYCLES,
            tail_first: false,
            sideways: false,
        })
    }

    /// The walk's supports, looked up by name: at least one, none twice in a row.
    fn walked(&self) -> Result<Vec<&Named>, ConfigError> {
        if self.walk.supports.is_empty() {
            return Err(self.invalid(
                "supports",
                &self.walk.supports,
                &format!("walk {} needs at least one support", self.walk.name),
            ));
        }
        let mut walked: Vec<&Named> = Vec::with_capacity(self.walk.supports.len());
        for (i, name) in self.walk.supports.iter().enumerate() {
            let field = format!("supports[{i}]");
            let Some(named) = self.supports.iter().find(|s| s.name == *name) else {
                let known: Vec<&str> = self.supports.iter().map(|s| s.name.as_str()).collect();
                return Err(self.invalid(
                    &field,
                    name,
                    &format!(
                        "walk {}: no support of that name (the file's supports: {})",
                        self.walk.name,
                        known.join(", ")
                    ),
                ));
            };
            if walked.last().is_some_and(|last| last.name == *name) {
                return Err(self.invalid(
                    &field,
                    name,
                    &format!(
                        "walk {}: the walk is on that support already: consecutive supports \
                         must differ",
                        self.walk.name
                    ),
                ));
            }
            walked.push(named);
        }
        Ok(walked)
    }

    /// The first leg's up: the world's up under a branch; on a trunk, toward its axis from
    /// the side `toward_trunk` names.
    fn first_up(&self, first: &Cylinder) -> Result<DVec3, ConfigError> {
        if !first.is_trunk(self.trunk_tilt_rad) {
            return match self.walk.toward_trunk {
                Some(v) => Err(self.invalid(
                    "toward_trunk",
                    v,
                    &format!(
                        "walk {} starts on a branch (tilted {:.1} deg, a trunk is tilted more \
                         than {:.1} deg): only a walk starting on a trunk takes it",
                        self.walk.name,
                        first.slope().abs().to_degrees(),
                        self.trunk_tilt_rad.to_degrees()
                    ),
                )),
                None => Ok(WORLD_UP),
            };
        }
        let raw = self.walk.toward_trunk.unwrap_or([1.0, 0.0, 0.0]);
        let toward = finite3(self.file, &format!("{}.toward_trunk", self.key), raw)?;
        if toward.z != 0.0 || toward.length() < 1e-9 {
            return Err(self.invalid(
                "toward_trunk",
                raw,
                "must be a horizontal direction (z = 0), not zero",
            ));
        }
        Ok(toward_axis(toward, first))
    }

    /// The leg onto support `position` of the walk, after `previous`: it starts where the
    /// previous support's axis comes nearest this one's.
    fn next_leg(
        &self,
        previous: &Leg,
        walked: &[&Named],
        position: usize,
        index: usize,
    ) -> Result<Leg, ConfigError> {
        let (from, onto) = (walked[position - 1], walked[position]);
        let (a, b) = (&from.cylinder, &onto.cylinder);
        let (on_from, on_onto) = segment_nearest(a.from, a.to, b.from, b.to);
        let field = format!("supports[{position}]");
        let nearest = on_from.distance(on_onto);
        let reach = a.radius + b.radius + MEET_SLACK_M;
        if nearest > reach {
            return Err(self.invalid(
                &field,
                &onto.name,
                &format!(
                    "walk {}: supports {} and {} do not meet (nearest {nearest:.2} m; at most \
                     {reach:.2} m, their radii + {MEET_SLACK_M} m)",
                    self.walk.name, from.name, onto.name
                ),
            ));
        }
        let start_s = previous.start_s + (on_from - previous.origin).dot(previous.direction);
        if start_s < previous.start_s {
            return Err(self.invalid(
                &field,
                &onto.name,
                &format!(
                    "walk {}: support {} meets {} at route distance {start_s:.3} m, behind \
                     where the walk joins {} ({:.3} m): a walk only goes forward",
                    self.walk.name, onto.name, from.name, from.name, previous.start_s
                ),
            ));
        }
        let up = if !b.is_trunk(self.trunk_tilt_rad) {
            WORLD_UP
        } else if a.is_trunk(self.trunk_tilt_rad) {
            // From trunk to trunk the sloth keeps the side it faces.
            toward_axis(horizontal(previous.up), b)
        } else {
            // Along a branch onto a trunk the trunk lies ahead: the sloth faces it.
            toward_axis(horizontal(previous.direction), b)
        };
        Ok(Leg {
            start_s,
            origin: on_onto,
            direction: b.direction(),
            left: index,
            right: index,
            up,
            twist_rad_per_m: 0.0,
        })
    }
}

fn horizontal(v: DVec3) -> DVec3 {
    DVec3::new(v.x, v.y, 0.0)
}

/// Toward the trunk's axis, from the side the horizontal `toward` names: `toward` without
/// its part along the axis, so that it points straight at the axis (on a vertical trunk,
/// `toward` itself). On a trunk tilted more than 70 deg a horizontal direction keeps at
/// least 94 % of its length; only a direction along a far less tilted "trunk" (a lower
/// `trunk_tilt_deg`) could vanish, and its up is then the world's.
fn toward_axis(toward: DVec3, trunk: &Cylinder) -> DVec3 {
    let axis = trunk.direction();
    (toward - axis * toward.dot(axis)).normalize_or(WORLD_UP)
}
