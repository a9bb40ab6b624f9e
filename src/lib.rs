//! rigbridge: plans joint motion for robot rigs and streams it to controllers or to a
//! simulated twin.
//!
//! The crate is laid out by pipeline stage:
//! - [`rig`]: rig models, their TOML/URDF descriptions and forward kinematics;
//! - [`ik`]: inverse-kinematics solvers behind one trait (FABRIK planner, CCD, gradient descent);
//! - [`batch`]: the CSV contract of the `fk` and `ik` batch tools.

pub mod batch;
pub mod clock;
pub mod daemon;
pub mod ik;
pub mod job;
pub mod link;
pub mod log;
pub mod protocol;
pub mod rig;
pub mod stream;
pub mod task;
pub mod trajectory;
pub mod twin;

#[doc = include_str!("../README.md")]
#[cfg(doctest)]
struct ReadmeDoctests;
