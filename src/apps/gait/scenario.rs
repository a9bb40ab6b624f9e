//! Scenarios: a terrain (branches as cylinders) and the route the sloth follows over it,
//! built from a name and its geometry (`--angle`, `--gap`). Owns the scenes and the route's
//! question "which support does a limb on this side grip at route distance s?"; it must
//! not place feet or judge a gait.

use super::body::WORLD_UP;
use super::terrain::{Cylinder, Terrain};
use glam::{DQuat, DVec3};
use serde::Serialize;
use thiserror::Error;

/// Branch radius: the 40 mm pole of Nyakatura et al.'s experiments (seed 004, Table 2).
pub const BRANCH_RADIUS_M: f64 = 0.02;
/// Trunk radius: a 16 cm trunk (ours: the thesis gives no size), four times the branch's
/// and wider than the sloth's girdles, so that the limbs hug it rather than grip around it.
pub const TRUNK_RADIUS_M: f64 = 0.08;
/// Where the trunk scenes' trunk stands: clear of a sloth hanging in the straight scene's
/// start (config/gait-run.toml's initial position), so that a `run` or `serve` job's
/// approach from there to the trunk never moves the body through the trunk.
pub const TRUNK_AXIS: DVec3 = DVec3::new(0.8, 0.0, 0.0);
/// How far around its trunk `trunk-around` side-steps per metre of route, by default.
pub const TRUNK_AROUND_DEG_PER_M: f64 = 120.0;
/// How far around its trunk `trunk-spiral` turns per metre climbed, by default.
pub const TRUNK_SPIRAL_DEG_PER_M: f64 = 40.0;

#[derive(Debug, Clone, PartialEq, Error)]
pub enum ScenarioError {
    #[error(
        "unknown scenario `{0}`: expected straight, branch-turn, parallel, height-change, \
         trunk (= trunk-up), trunk-up, trunk-down, trunk-around, trunk-spiral, transfer or \
         transfer-to-trunk"
    )]
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
/// `direction`, and each side's limbs grip the given supports. `up` is the side the
/// supports are on, seen from the body, at `start_s` (the world's up under a branch; on a
/// trunk, horizontal toward its axis); going around a trunk, it turns about `direction` by
/// `twist_rad_per_m` per metre of route.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Leg {
    pub start_s: f64,
    pub origin: DVec3,
    pub direction: DVec3,
    pub left: usize,
    pub right: usize,
    pub up: DVec3,
    pub twist_rad_per_m: f64,
}

impl Leg {
    /// A leg under branches: the supports are above.
    fn under(start_s: f64, origin: DVec3, direction: DVec3, left: usize, right: usize) -> Self {
        Self {
            start_s,
            origin,
            direction,
            left,
            right,
            up: WORLD_UP,
            twist_rad_per_m: 0.0,
        }
    }
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

    /// The side the supports are on, seen from the body, at route distance `s`.
    pub fn up(&self, s: f64) -> DVec3 {
        let leg = self.leg(s);
        let turn = leg.twist_rad_per_m * (s - leg.start_s);
        DQuat::from_axis_angle(leg.direction, turn) * leg.up
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
    /// The sloth moves tail first (down a trunk, head up): its head points against the
    /// route's direction, and its hind limbs lead.
    pub tail_first: bool,
    /// The sloth side-steps around its trunk, head up: the route's distance turns it about
    /// the trunk's axis (its leg's twist) at a fixed height, and each limb grips at its
    /// girdle's height.
    pub sideways: bool,
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
            Leg::under(0.0, DVec3::ZERO, DVec3::X, 0, 0),
            Leg::under(0.0, DVec3::ZERO, second, 1, 1),
        ],
    }
}

/// Height of the branch's junction above the trunk's origin in `transfer`: the sloth starts
/// with its fore limbs about 0.4 m below it, so it climbs a step or two before it reaches up.
const TRANSFER_JUNCTION_M: f64 = 0.3;

/// Trunk to branch, head first: the sloth climbs the trunk (on its -x side, facing +x) to
/// where a branch leaves it over the sloth's back, toward -x. `angle` is the angle between
/// the trunk below the junction and the branch: 90 deg a level branch, more a rising one.
fn transfer(angle: f64) -> (Terrain, Route, f64) {
    let rise = angle - std::f64::consts::FRAC_PI_2;
    let along_branch = DVec3::new(-rise.cos(), 0.0, rise.sin());
    let junction = TRUNK_AXIS + DVec3::Z * TRANSFER_JUNCTION_M;
    let terrain = Terrain {
        cylinders: vec![
            Cylinder {
                from: TRUNK_AXIS - DVec3::Z,
                to: TRUNK_AXIS + DVec3::Z * 2.5,
                radius: TRUNK_RADIUS_M,
            },
            branch(junction, junction + along_branch * 1.5),
        ],
    };
    let route = Route {
        legs: vec![
            Leg {
                start_s: 0.0,
                origin: TRUNK_AXIS,
                direction: DVec3::Z,
                left: 0,
                right: 0,
                up: DVec3::X,
                twist_rad_per_m: 0.0,
            },
            // The branch's route starts where it leaves the bark: the part inside the trunk
            // is no place for a hand.
            Leg::under(
                TRANSFER_JUNCTION_M,
                junction + along_branch * (TRUNK_RADIUS_M + BRANCH_RADIUS_M),
                along_branch,
                1,
                1,
            ),
        ],
    };
    (terrain, route, -0.3)
}

/// How far the sloth starts along its branch from the bark in `transfer-to-trunk`.
/// How far before the bark the body's middle starts in `transfer-to-trunk` (route
/// distance). Where the steps fall at the junction depends on it; 0.75 m passes the most
/// angles (docs/gait.md).
const TO_TRUNK_START_M: f64 = 0.75;

/// Branch to trunk, the seed's Transfer to Trunk: `transfer`'s scene walked the other way,
/// tail first and head up: along the branch toward the trunk, then down the trunk. `angle`
/// is `transfer`'s: between the trunk below the junction and the branch (90 deg a level
/// branch, more a branch rising away from the trunk).
fn transfer_to_trunk(angle: f64) -> (Terrain, Route, f64) {
    let rise = angle - std::f64::consts::FRAC_PI_2;
    let along_branch = DVec3::new(-rise.cos(), 0.0, rise.sin());
    let junction = TRUNK_AXIS + DVec3::Z * TRANSFER_JUNCTION_M;
    let branch_length = 1.5;
    let far_end = junction + along_branch * branch_length;
    // Travel runs along each support from its `from` to its `to`: in from the branch's far
    // end, then down the trunk.
    let terrain = Terrain {
        cylinders: vec![
            Cylinder {
                from: TRUNK_AXIS + DVec3::Z * 2.5,
                to: TRUNK_AXIS - DVec3::Z,
                radius: TRUNK_RADIUS_M,
            },
            branch(far_end, junction),
        ],
    };
    // The branch's route ends where it meets the bark: the part inside the trunk is no
    // place for a foot.
    let bark_s = branch_length - (TRUNK_RADIUS_M + BRANCH_RADIUS_M);
    let route = Route {
        legs: vec![
            Leg::under(0.0, far_end, -along_branch, 1, 1),
            Leg {
                start_s: bark_s,
                origin: junction,
                direction: -DVec3::Z,
                left: 0,
                right: 0,
                up: DVec3::X,
                twist_rad_per_m: 0.0,
            },
        ],
    };
    (terrain, route, bark_s - TO_TRUNK_START_M)
}

/// One level branch along +x, walked from its start.
fn straight() -> (Terrain, Route, f64) {
    let terrain = Terrain {
        cylinders: vec![branch(
            DVec3::new(-1.0, 0.0, 0.0),
            DVec3::new(2.0, 0.0, 0.0),
        )],
    };
    let route = Route {
        legs: vec![Leg::under(0.0, DVec3::ZERO, DVec3::X, 0, 0)],
    };
    (terrain, route, -0.3)
}

/// A level branch, then one at `angle_deg` to it (180: straight on): turning left when
/// `turn`, else rising (below 180 deg) or descending (above).
fn bend(turn: bool, angle_deg: f64) -> (Terrain, Route, f64) {
    let bend = (180.0 - angle_deg).to_radians();
    let second = if turn {
        DVec3::new(bend.cos(), bend.sin(), 0.0)
    } else {
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

/// Two parallel level branches `gap` apart (axes), overlapping where the sloth straddles
/// them.
fn parallel(gap: f64) -> (Terrain, Route, f64) {
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
    let leg = |start_s: f64, left: usize, right: usize| {
        Leg::under(
            start_s,
            DVec3::new(start_s, 0.0, 0.0),
            DVec3::X,
            left,
            right,
        )
    };
    let route = Route {
        legs: vec![leg(-1.0, 0, 0), leg(0.0, 0, 1), leg(0.25, 1, 1)],
    };
    (terrain, route, -0.45)
}

/// How far the route of trunk scenario `name` turns the sloth around the trunk, per metre
/// of route (deg): `angle_deg`, or the scenario's default; none for a straight climb.
fn trunk_twist(name: &str, angle_deg: Option<f64>) -> Result<f64, ScenarioError> {
    let default_twist = match name {
        "trunk-around" => Some(TRUNK_AROUND_DEG_PER_M),
        "trunk-spiral" => Some(TRUNK_SPIRAL_DEG_PER_M),
        "trunk-down" => Some(0.0),
        _ => None,
    };
    match (default_twist, angle_deg) {
        (Some(default), angle) => check(name, "angle", angle.unwrap_or(default), -180.0, 180.0),
        (None, Some(_)) => Err(ScenarioError::Unused {
            scenario: name.into(),
            name: "angle",
        }),
        (None, None) => Ok(0.0),
    }
}

/// A vertical trunk, climbed (or descended tail first when `down`), the route turning
/// `twist_deg_per_m` around it per metre.
fn trunk(down: bool, twist_deg_per_m: f64) -> (Terrain, Route, f64) {
    // Travel runs along the trunk: up it, or down it for the tail-first descent.
    let travel = if down { -DVec3::Z } else { DVec3::Z };
    let terrain = Terrain {
        cylinders: vec![Cylinder {
            from: TRUNK_AXIS - travel,
            to: TRUNK_AXIS + travel * 2.5,
            radius: TRUNK_RADIUS_M,
        }],
    };
    // The sloth clings to the trunk's -x side, facing +x.
    let route = Route {
        legs: vec![Leg {
            start_s: 0.0,
            origin: TRUNK_AXIS,
            direction: travel,
            left: 0,
            right: 0,
            up: DVec3::X,
            // About the travel: positive is counterclockwise seen from above going up, and
            // must stay so going down.
            twist_rad_per_m: twist_deg_per_m.to_radians() * travel.z,
        }],
    };
    (terrain, route, -0.3)
}

impl Scenario {
    /// +1 when the head leads along the route, -1 going tail first.
    pub fn heading_sign(&self) -> f64 {
        if self.tail_first { -1.0 } else { 1.0 }
    }

    /// Builds a named scenario. `angle_deg` is the angle between the branches (180: straight
    /// on), or for `trunk-around`, `trunk-spiral` and `trunk-down` how far the route turns around the
    /// trunk per metre (deg); `gap_m` the distance between parallel branches' axes.
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
                straight()
            }
            "branch-turn" | "height-change" => {
                if gap_m.is_some() {
                    return Err(unused("gap"));
                }
                let angle = check(name, "angle", angle_deg.unwrap_or(135.0), 0.0, 270.0)?;
                bend(name == "branch-turn", angle)
            }
            "parallel" => {
                if angle_deg.is_some() {
                    return Err(unused("angle"));
                }
                parallel(check(name, "gap", gap_m.unwrap_or(0.25), 0.0, 1.0)?)
            }
            "trunk" | "trunk-up" | "trunk-down" | "trunk-around" | "trunk-spiral" => {
                if gap_m.is_some() {
                    return Err(unused("gap"));
                }
                trunk(name == "trunk-down", trunk_twist(name, angle_deg)?)
            }
            "transfer" => {
                if gap_m.is_some() {
                    return Err(unused("gap"));
                }
                let angle = check(name, "angle", angle_deg.unwrap_or(90.0), 45.0, 180.0)?;
                transfer(angle.to_radians())
            }
            "transfer-to-trunk" => {
                if gap_m.is_some() {
                    return Err(unused("gap"));
                }
                let angle = check(name, "angle", angle_deg.unwrap_or(120.0), 45.0, 155.0)?;
                transfer_to_trunk(angle.to_radians())
            }
            other => return Err(ScenarioError::Unknown(other.into())),
        };
        // A transfer walks one cycle more: the hind limbs reach the branch in the fourth.
        let cycles = if name.starts_with("transfer") {
            CYCLES + 1
        } else {
            CYCLES
        };
        let tail_first = name == "trunk-down" || name == "transfer-to-trunk";
        let sideways = name == "trunk-around";
        Ok(Scenario {
            name: name.into(),
            angle_deg,
            gap_m,
            terrain,
            route,
            start_s,
            cycles,
            tail_first,
            sideways,
        })
    }
}
