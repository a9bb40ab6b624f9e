//! The `[gait]` table of the sloth file: speed, step search, timing, rules and the limb
//! solver. Owns parsing and validating it (errors name the file, the key and the value),
//! and building the chosen core solver for a limb; the walker reads the result, it never
//! changes it.

use super::rig::Limb;
use crate::ik::{CcdSolver, IkSolver, PositionFabrikSolver, Tolerance};
use crate::rig::{ConfigError, Rig, check_range};
use serde::Deserialize;
use std::path::Path;

/// Which of the core's solvers places each limb (`[gait] solver`, `rigbridge gait --solver`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum LimbSolver {
    /// Cyclic coordinate descent with per-bone limits (the thesis's solver).
    Ccd,
    /// Position-only FABRIK with per-bone limits, for comparison.
    Fabrik,
}

impl LimbSolver {
    pub const NAMES: [&'static str; 2] = ["ccd", "fabrik"];

    /// The name `[gait] solver` and `--solver` use.
    pub fn name(self) -> &'static str {
        match self {
            Self::Ccd => "ccd",
            Self::Fabrik => "fabrik",
        }
    }

    /// The solver named `name` as in `[gait] solver`.
    pub fn from_name(name: &str) -> Option<Self> {
        match name {
            "ccd" => Some(Self::Ccd),
            "fabrik" => Some(Self::Fabrik),
            _ => None,
        }
    }

    /// The core's solver for one limb chain, placing the tool's origin only.
    pub fn build(
        self,
        chain: Rig,
        tolerance: Tolerance,
        max_iterations: u32,
    ) -> Box<dyn IkSolver + Send + Sync> {
        match self {
            Self::Ccd => Box::new(
                CcdSolver::new(chain)
                    .position_only()
                    .with_tolerance(tolerance)
                    .with_max_iterations(max_iterations),
            ),
            Self::Fabrik => Box::new(
                PositionFabrikSolver::new(chain)
                    .with_tolerance(tolerance)
                    .with_max_iterations(max_iterations),
            ),
        }
    }
}

/// The seed's footfall sequences by name (`rigbridge gait --sequence`): the diagonal one
/// (DSDC, its steady gait) and the lateral one (LSDC, which it uses for transfers).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FootfallSequence {
    Diagonal,
    Lateral,
}

impl FootfallSequence {
    pub const NAMES: [&'static str; 2] = ["diagonal", "lateral"];

    pub fn from_name(name: &str) -> Option<Self> {
        match name {
            "diagonal" => Some(Self::Diagonal),
            "lateral" => Some(Self::Lateral),
            _ => None,
        }
    }

    /// The limbs in footfall order, from the right hind: diagonal, each hind limb followed
    /// by the fore limb of the other side; lateral, by the fore limb of its own side.
    pub fn limb_names(self) -> [&'static str; 4] {
        match self {
            Self::Diagonal => ["rh", "lf", "lh", "rf"],
            Self::Lateral => ["rh", "rf", "lh", "lf"],
        }
    }
}

#[derive(Debug, Clone, PartialEq)]
pub struct GaitConfig {
    pub speed_m_s: f64,
    pub max_step_m: f64,
    pub min_step_m: f64,
    pub retry_step_m: f64,
    pub duty_factor: f64,
    pub swing_lift_m: f64,
    /// Limb indices in footfall order.
    pub footfall_order: Vec<usize>,
    pub trunk_tilt_rad: f64,
    pub max_rise_rad: f64,
    pub max_descent_rad: f64,
    pub solver: LimbSolver,
    pub ik_tolerance_m: f64,
    pub ik_max_iterations: u32,
}

impl GaitConfig {
    /// One gait cycle: each limb steps once by the max step.
    pub fn cycle_s(&self) -> f64 {
        self.max_step_m / self.speed_m_s
    }

    pub fn swing_s(&self) -> f64 {
        (1.0 - self.duty_factor) * self.cycle_s()
    }
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawGait {
    speed_m_s: f64,
    max_step_m: f64,
    min_step_m: f64,
    retry_step_m: f64,
    duty_factor: f64,
    swing_lift_m: f64,
    footfall_order: Vec<String>,
    trunk_tilt_deg: f64,
    max_rise_deg: f64,
    max_descent_deg: f64,
    solver: String,
    ik_tolerance_m: f64,
    ik_max_iterations: u32,
}

impl RawGait {
    pub(super) fn validate(self, file: &Path, limbs: &[Limb]) -> Result<GaitConfig, ConfigError> {
        let speed_m_s = check_range(file, "gait.speed_m_s", self.speed_m_s, 0.01, 1.0)?;
        let max_step_m = check_range(file, "gait.max_step_m", self.max_step_m, 0.01, 1.0)?;
        let min_step_m = check_range(file, "gait.min_step_m", self.min_step_m, 0.0, max_step_m)?;
        let retry_step_m = check_range(file, "gait.retry_step_m", self.retry_step_m, 0.001, 0.1)?;
        let duty_factor = check_range(file, "gait.duty_factor", self.duty_factor, 0.5, 0.9)?;
        let swing_lift_m = check_range(file, "gait.swing_lift_m", self.swing_lift_m, 0.0, 0.3)?;
        let mut footfall_order = Vec::with_capacity(self.footfall_order.len());
        for (index, name) in self.footfall_order.iter().enumerate() {
            let Some(limb) = limbs.iter().position(|l| &l.name == name) else {
                return Err(ConfigError::invalid(
                    file,
                    &format!("gait.footfall_order[{index}]"),
                    name,
                    "names no limb",
                ));
            };
            if footfall_order.contains(&limb) {
                return Err(ConfigError::invalid(
                    file,
                    &format!("gait.footfall_order[{index}]"),
                    name,
                    "each limb appears once",
                ));
            }
            footfall_order.push(limb);
        }
        if footfall_order.len() != limbs.len() {
            return Err(ConfigError::invalid(
                file,
                "gait.footfall_order",
                &self.footfall_order,
                "must name every limb once",
            ));
        }
        let degrees = |key: &str, value: f64, high: f64| {
            check_range(file, key, value, 0.0, high).map(f64::to_radians)
        };
        Ok(GaitConfig {
            speed_m_s,
            max_step_m,
            min_step_m,
            retry_step_m,
            duty_factor,
            swing_lift_m,
            footfall_order,
            trunk_tilt_rad: degrees("gait.trunk_tilt_deg", self.trunk_tilt_deg, 90.0)?,
            max_rise_rad: degrees("gait.max_rise_deg", self.max_rise_deg, 90.0)?,
            max_descent_rad: degrees("gait.max_descent_deg", self.max_descent_deg, 90.0)?,
            solver: LimbSolver::from_name(&self.solver).ok_or_else(|| {
                ConfigError::invalid(
                    file,
                    "gait.solver",
                    &self.solver,
                    &format!("must be one of {}", LimbSolver::NAMES.join(", ")),
                )
            })?,
            ik_tolerance_m: check_range(
                file,
                "gait.ik_tolerance_m",
                self.ik_tolerance_m,
                1e-7,
                1e-3,
            )?,
            ik_max_iterations: if (1..=10_000).contains(&self.ik_max_iterations) {
                self.ik_max_iterations
            } else {
                return Err(ConfigError::invalid(
                    file,
                    "gait.ik_max_iterations",
                    self.ik_max_iterations,
                    "must lie in [1, 10000]",
                ));
            },
        })
    }
}
