//! Building time-parameterised joint trajectories, generic over the rig: jerk-limited joint
//! moves (`plan`), the timing of a joint path along a Cartesian line (`path`) and its
//! jerk-limited timing for a program's moves (`smooth`), free moves
//! around the cell's obstacles (`free`), resampling and retiming, and a run log's commands
//! read back as a trajectory (`recorded`). The
//! [`Trajectory`] type and [`validate`] live in the leaf `motion` (re-exported here), so
//! the streamer below can take them. Must not solve IK (the `ik` stage above calls into
//! `path`) or talk to links or controllers.

mod budget;
mod clearance;
pub mod free;
mod origins;
mod path;
mod plan;
mod recorded;
mod resample;
mod retime;
mod smooth;

pub use budget::{
    BYTES_PER_AXIS_SAMPLE, BYTES_PER_MB, DEFAULT_MAX_DURATION_S, DEFAULT_MAX_PLAN_MB, OverBudget,
    SampleBudget, plan_mb,
};
pub use clearance::{CollisionRefusal, JointValue, check_clear, joint_values};
pub use origins::Origins;
pub(crate) use path::{JointPath, PathNode, PathTiming};
pub(crate) use plan::{AxisLimits, Samples, check_start};
pub use plan::{InvalidValue, PlanError, PlanSettings, plan_joint_moves, plan_joint_moves_marked};
pub use recorded::{RecordedError, TIME_TOLERANCE_S};
pub use resample::{ramp_to_rest, resample};
pub use retime::{RetimeError, Retimed, retime};
pub(crate) use smooth::{BLENDED_SHARE, REST_TO_REST_SHARE, SmoothTiming, differences};

pub use crate::motion::{
    PeakAcceleration, SPEED_SLACK, Trajectory, TrajectoryError, peak_accelerations, validate,
    validate_motion,
};
