//! rigbridge: plans joint motion for robot rigs and streams it to controllers or to a
//! simulated twin.
//!
//! The crate is laid out by pipeline stage, in the order data flows (imports point down
//! the chain from `job` to `log`, never up; the view, the ROS 2 node and the daemon, which
//! show or wire all of it, sit above it: `docs/architecture.md`, "Layers", gives the whole
//! order and `tests/layers.rs` keeps it):
//! - [`job`]: job kinds, one file each: validation, file resolution, planning, scene;
//! - [`task`]: tasks that produce targets from generated worlds (painting, the sloth gait);
//! - [`ik`]: inverse-kinematics solvers behind one trait (FABRIK planner, CCD, gradient descent)
//!   and Cartesian lines solved into joint paths;
//! - [`trajectory`]: planning fixed-period joint trajectories (joint moves, the timing of a
//!   joint path, resampling, retiming) and a run log read back for replay;
//! - [`stream`]: the fixed-rate cycle, its safety gate and the following checks;
//! - [`device`]: one folder per device protocol (ours over TCP, serial and CAN; EGM; CiA 402;
//!   Dynamixel): its wire codec, its link, its twin side, and the one list of them;
//! - [`link`]: the `Link` trait, the in-process loopback and what every protocol's link
//!   shares (the session state machine, the channel to an I/O thread);
//! - [`twin`]: the strict simulated controller, in process or on the far side of a link;
//! - [`log`]: MCAP recording and reading, summaries;
//! - [`view`]: the live 3D view;
//! - [`ros2`]: each rig as a ROS 2 node over Zenoh (joint states out, trajectories in);
//! - [`daemon`]: the wiring of the stages for `run`, `serve` and `replay`, and resuming;
//!
//! and beside the chain: [`cell`] (the workcell: the robot's body, its tool, the objects
//! around it, and the one collision model every check uses), [`motion`] (the `Trajectory` type and `validate`, which the
//! planners build and the streamer runs), [`scene`] (a world's geometry, drawn by the view
//! and written by the log), [`rig`] (rig models, TOML/URDF descriptions, forward kinematics),
//! [`clock`] (wall and virtual clocks), [`realtime`] (thread scheduling) and
//! [`batch`] (the CSV contract of `fk` and `ik`);
//! and the two leaves both ends of a link share, which `link` and `twin` import and which
//! import neither (so `twin` never imports `link`):
//! - [`protocol`]: the messages and their byte and CAN encodings (`docs/protocol.md`);
//! - [`transport`]: the SocketCAN socket and the serial line's settings.

pub mod apps;
pub mod batch;
pub mod cell;
pub mod clock;
pub mod daemon;
pub mod device;
pub mod ik;
pub mod job;
pub mod link;
pub mod log;
pub mod motion;
pub mod protocol;
pub mod realtime;
pub mod rig;
pub mod ros2;
pub mod scene;
pub mod server;
pub mod stream;
pub mod trajectory;
pub mod transport;
pub mod twin;
pub mod view;

#[doc = include_str!("../README.md")]
#[cfg(doctest)]
struct ReadmeDoctests;
