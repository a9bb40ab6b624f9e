//! The WebSocket messages of `/api/live`, as JSON text: a `scene` message when a client
//! connects and whenever the job (and so the scene) changes, then a `frame` message about
//! 50 times a second. Field by field in `docs/live-view.md`. Owns the message shapes only.

use super::JointLabel;
use crate::link::LinkCounters;
use crate::scene::{ClosestView, PaintQuad, Point, PoseView, SceneView};
use serde::Serialize;

#[derive(Debug, Serialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum Message<'a> {
    Scene(SceneMessage<'a>),
    Frame(&'a Frame),
}

#[derive(Debug, Serialize)]
pub struct SceneMessage<'a> {
    pub rig: &'a str,
    pub joints: &'a [JointLabel],
    /// The configured streaming rate (Hz).
    pub rate_hz: f64,
    /// Frames per second the server sends.
    pub frame_rate_hz: f64,
    pub scene: &'a SceneView,
    /// The running job's tool path and targets; `null` before the first job is planned.
    pub plan: Option<&'a super::PlanView>,
    /// The cell's parts' solids, each in its own frame (a frame's `program.parts` poses
    /// them); empty for a cell without parts or a remote controller.
    pub parts: &'a [crate::scene::SolidView],
}

#[derive(Debug, Serialize)]
pub struct Frame {
    /// Counts frames since the server started.
    pub frame: u64,
    /// The last streamed cycle's sequence number and time in its job (s).
    pub seq: u32,
    pub t: f64,
    /// Joint values in the units of the scene message's `joints` (deg or m).
    pub actual: Vec<f64>,
    pub commanded: Vec<f64>,
    /// The rig as world-space polylines (m).
    pub chains: Vec<Vec<Point>>,
    /// Paint added since the previous frame.
    pub paint: Vec<PaintQuad>,
    /// Each of the scene's `bodies` at its pose now, in its order (empty without a cell).
    pub bodies: Vec<PoseView>,
    /// The cell's closest pair when within the margin (or touching), else `null`.
    pub closest: Option<ClosestView>,
    pub link: LinkView,
    pub job: super::JobView,
    /// The program's current step and the cell's parts; `null` for other jobs in a cell
    /// without parts.
    pub program: Option<super::ProgramView>,
}

/// The link and the cycle, as of the last streamed cycle.
#[derive(Debug, Serialize)]
pub struct LinkView {
    /// `ok`, `holding`, `fault: ...`, or `none` before the controller has answered.
    pub status: String,
    pub rate_hz: f64,
    /// Cycles streamed per second of real time, over about the last half second (0 idle).
    pub cycles_per_s: f64,
    pub cycles: u64,
    /// How late the last cycle woke, and the worst over about the last second (us).
    pub jitter_us: f64,
    pub jitter_max_us: f64,
    pub latency_us: f64,
    pub latency_max_us: f64,
    /// Largest |commanded - actual| over the revolute axes (deg).
    pub tracking_error_deg: f64,
    /// The link's own counters, as in the run report: frames_sent ... reconnects.
    #[serde(flatten)]
    pub counters: LinkCounters,
    pub feedback_timeouts: u64,
}
