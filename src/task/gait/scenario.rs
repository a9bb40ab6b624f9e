//! Scenarios: a terrain (branches as cylinders) and the route the sloth follows over it,
//! built from a name and its geometry (`--angle`, `--gap`). Owns the scenes and the route's
//! question "which support does a limb on this side grip at route distance s?"; it must
//! not place feet or judge a gait.

use super::terrain::{Cylinder, Terrain};
use glam::DVec3;
use serde::Serialize;
use thiserror::Error;

/// Branch radius: the 40 mm pole of Nyakatura et al.'s experiments (seed 004, Table 2).
pub const BRANCH_RADIUS_M: f64 = 0.02;

#[derive(Debug, Clone, PartialEq, Error)]
pub enum ScenarioError {
    #[error("unknown scenario `{0}`: expected straight, branch-turn, parallel or height-change")]
    Unknown(String),
    #[error("scenario {scenario}: --{name} = {value} must lie in [{low}, {high}]")]
    OutOfRange {
        scenario: String,
        name: &'static str,
        value: f64,
        low: f64,
        high: f64,
    },
    #[error("scenario {scenario} takes no --{name}")]
    Unused {
        scenario: String,
        name: &'static str,
    },
}

/// One stretch of the route: from `start_s` on, the path runs from `origin` along
/// `direction`, and each side's limbs grip the given supports.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Leg {
    pub start_s: f64,
    pub origin: DVec3,
    pub direction: DVec3,
    pub left: usize,
    pub right: usize,
}

/// The legs in order of `start_s` (ties: the later one wins from its start); the first one
/// also covers everything before it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Route {
    pub legs: Vec<Leg>,
}

impl Route {
    pub fn leg(&self, s: f64) -> &Leg {
        self.legs
            .iter()
            .rev()
            .find(|leg| leg.start_s <= s)
            .unwrap_or(&self.legs[0])
    }

    /// The path point at route distance `s`.
    pub fn point(&self, s: f64) -> DVec3 {
        let leg = self.leg(s);
        leg.origin + leg.direction * (s - leg.start_s)
    }
}

/// A scene to walk: where, how far, and what to call it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Scenario {
    pub name: String,
    pub angle_deg: Option<f64>,
    pub gap_m: Option<f64>,
    pub terrain: Terrain,
    pub route: Route,
    /// Route distance of the body's middle at the start.
    pub start_s: f64,
    /// Gait cycles to walk before stopping (at least 3 are judged).
    pub cycles: u32,
}

/// Cycles every scenario walks: 3 judged plus the first, which starts from a standstill.
pub const CYCLES: u32 = 4;

fn branch(from: DVec3, to: DVec3) -> Cylinder {
    Cylinder {
        from,
        to,
        radius: BRANCH_RADIUS_M,
    }
}

fn check(
    scenario: &str,
    name: &'static str,
    value: f64,
    low: f64,
    high: f64,
) -> Result<f64, ScenarioError> {
    if value.is_finite() && (low..=high).contains(&value) {
        Ok(value)
    } else {
        Err(ScenarioError::OutOfRange {
            scenario: scenario.into(),
            name,
            value,
            low,
            high,
        })
    }
}

/// A route of two legs meeting at the origin: the first along +x, the second along
/// `second` (unit), both sides on the same branch.
fn bent_route(second: DVec3) -> Route {
    Route {
        legs: vec![
            Leg {
                start_s: 0.0,
                origin: DVec3::ZERO,
                direction: DVec3::X,
                left: 0,
                right: 0,
            },
            Leg {
                start_s: 0.0,
                origin: DVec3::ZERO,
                direction: second,
                left: 1,
                right: 1,
            },
        ],
    }
}

impl Scenario {
    /// Builds a named scenario. `angle_deg` is the angle between the branches (180: straight
    /// on); `gap_m` the distance between parallel branches' axes.
    pub fn build(
        name: &str,
        angle_deg: Option<f64>,
        gap_m: Option<f64>,
    ) -> Result<Scenario, ScenarioError> {
        let unused = |what: &'static str| ScenarioError::Unused {
            scenario: name.into(),
            name: what,
        };
        let (terrain, route, start_s) = match name {
            "straight" => {
                if angle_deg.is_some() {
                    return Err(unused("angle"));
                }
                if gap_m.is_some() {
                    return Err(unused("gap"));
                }
                let terrain = Terrain {
                    cylinders: vec![branch(
                        DVec3::new(-1.0, 0.0, 0.0),
                        DVec3::new(2.0, 0.0, 0.0),
                    )],
                };
                let route = Route {
                    legs: vec![Leg {
                        start_s: 0.0,
                        origin: DVec3::ZERO,
                        direction: DVec3::X,
                        left: 0,
                        right: 0,
                    }],
                };
                (terrain, route, -0.3)
            }
            "branch-turn" | "height-change" => {
                if gap_m.is_some() {
                    return Err(unused("gap"));
                }
                let angle = check(name, "angle", angle_deg.unwrap_or(135.0), 0.0, 270.0)?;
                let bend = (180.0 - angle).to_radians();
                let second = if name == "branch-turn" {
                    // Turning left by the bend.
                    DVec3::new(bend.cos(), bend.sin(), 0.0)
                } else {
                    // Rising by the bend (below 180 deg) or descending (above).
                    DVec3::new(bend.cos(), 0.0, bend.sin())
                };
                let terrain = Terrain {
                    cylinders: vec![
                        branch(DVec3::new(-1.2, 0.0, 0.0), DVec3::ZERO),
                        branch(DVec3::ZERO, second * 1.5),
                    ],
                };
                (terrain, bent_route(second), -0.55)
            }
            "parallel" => {
                if angle_deg.is_some() {
                    return Err(unused("angle"));
                }
                let gap = check(name, "gap", gap_m.unwrap_or(0.25), 0.0, 1.0)?;
                let right = DVec3::new(0.0, -gap, 0.0);
                let terrain = Terrain {
                    cylinders: vec![
                        branch(DVec3::new(-1.0, 0.0, 0.0), DVec3::new(0.6, 0.0, 0.0)),
                        branch(
                            DVec3::new(-0.4, 0.0, 0.0) + right,
                            DVec3::new(2.0, 0.0, 0.0) + right,
                        ),
                    ],
                };
                let leg = |start_s: f64, left: usize, right: usize| Leg {
                    start_s,
                    origin: DVec3::new(start_s, 0.0, 0.0),
                    direction: DVec3::X,
                    left,
                    right,
                };
                let route = Route {
                    legs: vec![leg(-1.0, 0, 0), leg(0.0, 0, 1), leg(0.25, 1, 1)],
                };
                (terrain, route, -0.45)
            }
            other => return Err(ScenarioError::Unknown(other.into())),
        };
        Ok(Scenario {
            name: name.into(),
            angle_deg,
            gap_m,
            terrain,
            route,
            start_s,
            cycles: CYCLES,
        })
    }
}
