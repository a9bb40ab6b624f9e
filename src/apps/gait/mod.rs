//! The sloth gait of seed 004 as a second rig on the bridge's pipeline: the rig and its
//! file, terrain, scenarios (built in or from a forest file), foot placement, the walker
//! that plans joint motion, the twin-side measurements and the report. Owns producing the
//! sloth's joint trajectory and judging it; streaming, the twin and logging are the
//! pipeline's.

mod app;
pub mod body;
pub mod config;
pub mod forest;
pub mod job;
pub mod metrics;
pub mod picture;
pub mod pipeline;
pub mod placement;
pub mod rig;
pub mod rule;
pub mod run;
pub mod scenario;
pub mod scene;
pub mod smooth;
pub mod terrain;
pub mod walker;

pub use app::{GaitApp, shared_sloth, sloth_of};
pub use config::{FootfallSequence, GaitConfig, LimbSolver};
pub use forest::{Forest, ForestError};
pub use job::Gait;
pub use metrics::{GaitReport, GaitWorld, judge};
pub use pipeline::{GaitError, plan_gait, plan_gait_job, trajectory_from_plan};
pub use rig::{Girdle, Limb, Side, SlothRig};
pub use rule::RuleBroken;
pub use scenario::{Scenario, ScenarioError};
pub use scene::SlothScene;
pub use terrain::{Cylinder, Terrain};
pub use walker::{GaitPlan, GaitState, Stance, WalkError, Walker};
