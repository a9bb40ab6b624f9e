//! The view's hub: holds the current [`LiveScene`] and the paint so far, samples the
//! [`LiveSlot`] when asked (the server's frame task, about 50 times a second) and
//! broadcasts each frame, as JSON text, to every connected page. Time is handed in. It runs
//! outside the streaming cycle and must not touch the link or the job.

use super::frame::{Frame, LinkView, Message, SceneMessage};
use super::plan::PlanView;
use super::program::{PartsDrawing, program_view};
use super::solid::CellDrawing;
use super::{JointLabel, LiveScene, LiveSlot};
use crate::job::StepSpans;
use crate::protocol::{AxisValues, ControllerStatus};
use crate::rig::{JointKind, Rig};
use crate::scene::{ClosestView, PaintQuad, SceneView};
use serde::Serialize;
use std::collections::VecDeque;
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;
use tokio::sync::broadcast;

/// Frames a slow page may fall behind before it skips ahead (and gets the scene again).
const BACKLOG_FRAMES: usize = 64;
/// How far back the measured cycle rate looks.
const RATE_WINDOW: Duration = Duration::from_millis(500);

/// The job as the page shows it.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct JobView {
    /// `idle`, `running` or `paused`.
    pub state: &'static str,
    pub id: Option<u64>,
    pub name: Option<String>,
    /// 0..=1 of the running job's trajectory.
    pub progress: f64,
    /// How the last job ended (`completed`, `stopped`, `e_stopped`, ... or an error).
    pub last: Option<String>,
    /// The controller's latched fault (an e-stop included) until a reset clears it: the
    /// page shows it in place of the last cycle's status, which predates the latch.
    pub controller: Option<String>,
    /// The running job's log failure, or the last job's: the page shows it until the next
    /// job starts with a sound log (docs/logs.md).
    pub log_error: Option<String>,
}

/// How far a follower of the scene has got ([`LiveHub::scene_since`]).
#[derive(Debug, Clone, Copy, Default)]
pub struct SceneCursor {
    generation: Option<u64>,
    paint: usize,
}

/// A change of the scene, for a follower.
#[derive(Debug, Clone, PartialEq)]
pub enum SceneChange {
    /// Another scene (a new job): everything, its paint so far included.
    New(SceneView),
    /// Paint added to the same scene.
    Paint(Vec<PaintQuad>),
}

struct HubState {
    scene: Box<dyn LiveScene>,
    /// The cell's objects, tool and collision bodies, drawn over every job's scene.
    cell: Option<CellDrawing>,
    /// The closest pair within the margin as of the last frame.
    closest: Option<ClosestView>,
    /// Counts [`LiveHub::set_scene`] calls: a follower's cursor from an older scene is stale.
    generation: u64,
    /// The scene with every paint quad drained since it was set.
    view: SceneView,
    /// The running job's plan (tool path and targets), from when it was planned.
    plan: Option<PlanView>,
    /// The running program's steps on its trajectory.
    steps: Option<StepSpans>,
    frames: u64,
    /// (time, cycles) of recent frames, for the measured cycle rate.
    recent: VecDeque<(Duration, u64)>,
}

pub struct LiveHub {
    slot: Arc<LiveSlot>,
    rig: Rig,
    joints: Vec<JointLabel>,
    rate_hz: f64,
    frame_rate_hz: f64,
    state: Mutex<HubState>,
    sender: broadcast::Sender<Arc<str>>,
    /// The cell's parts as the in-process twin has them.
    parts: Option<PartsDrawing>,
}

impl LiveHub {
    pub fn new(
        rig: Rig,
        rate_hz: f64,
        frame_rate_hz: f64,
        slot: Arc<LiveSlot>,
        scene: Box<dyn LiveScene>,
    ) -> Self {
        let (sender, _) = broadcast::channel(BACKLOG_FRAMES);
        LiveHub {
            slot,
            joints: JointLabel::for_rig(&rig),
            rig,
            rate_hz,
            frame_rate_hz,
            state: Mutex::new(HubState {
                view: scene.scene(),
                plan: None,
                steps: None,
                scene,
                cell: None,
                closest: None,
                generation: 0,
                frames: 0,
                recent: VecDeque::new(),
            }),
            sender,
            parts: None,
        }
    }

    /// Draws the cell's parts where the twin has them, with its judgement, in every frame.
    pub fn with_parts(self, parts: PartsDrawing) -> Self {
        LiveHub {
            parts: Some(parts),
            ..self
        }
    }

    /// The running program's steps (none for other jobs): each frame names the step its
    /// last cycle is in.
    pub fn set_steps(&self, steps: Option<StepSpans>) {
        self.state().steps = steps;
    }

    /// The cell's parts' solids, in the order a frame's `program.parts` poses them.
    pub fn part_solids(&self) -> &[crate::scene::SolidView] {
        self.parts
            .as_ref()
            .map_or(&[], |parts| parts.solids.as_slice())
    }

    /// The program view as of the latest sample (Foxglove's `/program`).
    pub fn program_now(&self) -> Option<super::ProgramView> {
        let sample = self.slot.latest();
        program_view(
            self.state().steps.as_ref(),
            sample.on_job,
            self.parts.as_ref(),
        )
    }

    /// Draws `cell` (its objects, the tool, the rig's collision bodies) in every scene, and
    /// marks its closest pair in each frame when it is within the margin.
    pub fn with_cell(self, cell: CellDrawing) -> Self {
        {
            let mut state = self.state();
            with_cell_solids(&mut state.view, &cell);
            state.cell = Some(cell);
        }
        self
    }

    /// The closest pair within the margin as of the last frame.
    pub fn closest(&self) -> Option<ClosestView> {
        self.state().closest.clone()
    }

    pub fn slot(&self) -> &Arc<LiveSlot> {
        &self.slot
    }

    fn state(&self) -> std::sync::MutexGuard<'_, HubState> {
        self.state.lock().unwrap_or_else(PoisonError::into_inner)
    }

    fn scene_message(&self, state: &HubState) -> Arc<str> {
        let message = Message::Scene(SceneMessage {
            rig: &self.rig.name,
            joints: &self.joints,
            rate_hz: self.rate_hz,
            frame_rate_hz: self.frame_rate_hz,
            scene: &state.view,
            plan: state.plan.as_ref(),
            parts: self.part_solids(),
        });
        Arc::from(serde_json::to_string(&message).unwrap_or_default())
    }

    /// A new page: the scene as it stands (paint included), then every frame from now on.
    /// Subscribed before the scene is taken, so no paint falls between them.
    pub fn subscribe(&self) -> (Arc<str>, broadcast::Receiver<Arc<str>>) {
        let frames = self.sender.subscribe();
        let scene = self.scene_message(&self.state());
        (scene, frames)
    }

    /// The scene as it stands, for a page that fell behind.
    pub fn scene_now(&self) -> Arc<str> {
        self.scene_message(&self.state())
    }

    /// Shows `scene` from now on (a new job); every page gets the new scene.
    pub fn set_scene(&self, scene: Box<dyn LiveScene>) {
        self.set_job_scene(scene, None);
    }

    /// Shows `scene` and the running job's `plan` (its tool path and targets) from now on;
    /// every page gets them.
    pub fn set_job_scene(&self, scene: Box<dyn LiveScene>, plan: Option<PlanView>) {
        let message = {
            let mut state = self.state();
            let mut view = scene.scene();
            if let Some(cell) = &state.cell {
                with_cell_solids(&mut view, cell);
            }
            state.view = view;
            state.plan = plan;
            state.steps = None;
            state.scene = scene;
            state.generation += 1;
            self.scene_message(&state)
        };
        let _ = self.sender.send(message);
    }

    /// What changed in the scene since `cursor` was last here (the live Foxglove server
    /// follows the scene this way): the whole scene when it is another one (or the cursor
    /// is new), else the paint added since, if any.
    pub fn scene_since(&self, cursor: &mut SceneCursor) -> Option<SceneChange> {
        let state = self.state();
        if cursor.generation != Some(state.generation) {
            cursor.generation = Some(state.generation);
            cursor.paint = state.view.paint.len();
            return Some(SceneChange::New(state.view.clone()));
        }
        let fresh = state.view.paint.get(cursor.paint..).unwrap_or_default();
        cursor.paint = state.view.paint.len();
        (!fresh.is_empty()).then(|| SceneChange::Paint(fresh.to_vec()))
    }

    /// Samples the slot at time `now` and sends every page the frame; returns it.
    pub fn tick(&self, now: Duration, job: JobView) -> Arc<str> {
        let sample = self.slot.latest();
        let mut state = self.state();
        let chains = state.scene.chains(sample.actual.as_slice());
        let paint = state.scene.drain_paint();
        let (bodies, closest) = match state.cell.as_mut() {
            Some(cell) => (
                cell.body_poses(sample.actual.as_slice()),
                cell.closest(sample.actual.as_slice()),
            ),
            None => (Vec::new(), None),
        };
        state.closest.clone_from(&closest);
        state.view.paint.extend_from_slice(&paint);
        state.frames += 1;
        state.recent.push_back((now, sample.cycles));
        while state
            .recent
            .front()
            .is_some_and(|(t, _)| now.saturating_sub(*t) > RATE_WINDOW)
        {
            state.recent.pop_front();
        }
        let cycles_per_s = match state.recent.front() {
            Some((t, cycles)) if now > *t => {
                sample.cycles.saturating_sub(*cycles) as f64 / (now - *t).as_secs_f64()
            }
            _ => 0.0,
        };
        let frame = Frame {
            frame: state.frames,
            seq: sample.seq,
            t: sample.t,
            actual: self.display(&sample.actual),
            commanded: self.display(&sample.commanded),
            chains,
            paint,
            bodies,
            closest,
            link: LinkView {
                status: status_text(sample.status),
                rate_hz: self.rate_hz,
                cycles_per_s,
                cycles: sample.cycles,
                jitter_us: f64::from(sample.late_us),
                jitter_max_us: f64::from(sample.late_max_us),
                latency_us: f64::from(sample.latency_us),
                latency_max_us: f64::from(sample.latency_max_us),
                tracking_error_deg: self.tracking_error_deg(&sample.commanded, &sample.actual),
                counters: sample.counters,
                feedback_timeouts: sample.feedback_timeouts,
            },
            job,
            program: program_view(state.steps.as_ref(), sample.on_job, self.parts.as_ref()),
        };
        drop(state);
        let text: Arc<str> =
            Arc::from(serde_json::to_string(&Message::Frame(&frame)).unwrap_or_default());
        if self.sender.receiver_count() > 0 {
            let _ = self.sender.send(text.clone());
        }
        text
    }

    /// Degrees for revolute axes, metres for prismatic ones.
    fn display(&self, values: &AxisValues) -> Vec<f64> {
        self.rig
            .joints
            .iter()
            .zip(values.as_slice())
            .map(|(joint, value)| joint.kind.to_user(*value))
            .collect()
    }

    fn tracking_error_deg(&self, commanded: &AxisValues, actual: &AxisValues) -> f64 {
        self.rig
            .joints
            .iter()
            .zip(commanded.as_slice().iter().zip(actual.as_slice()))
            .filter(|(joint, _)| joint.kind == JointKind::Revolute)
            .map(|(_, (c, a))| (c - a).abs().to_degrees())
            .fold(0.0, f64::max)
    }
}

/// The cell's objects and bodies added to a job's scene.
fn with_cell_solids(view: &mut SceneView, cell: &CellDrawing) {
    view.solids.extend(cell.solids.iter().cloned());
    view.bodies.extend(cell.bodies.iter().cloned());
}

fn status_text(status: Option<ControllerStatus>) -> String {
    match status {
        None => "none".into(),
        Some(ControllerStatus::Ok) => "ok".into(),
        Some(ControllerStatus::Holding) => "holding".into(),
        Some(ControllerStatus::Fault(fault)) => format!("fault: {fault}"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{PaintQuad, Point};
    use crate::view::LiveSample;

    struct Painter {
        rig: Rig,
        pending: Vec<PaintQuad>,
    }

    impl LiveScene for Painter {
        fn scene(&self) -> SceneView {
            SceneView::default()
        }
        fn chains(&self, actual: &[f64]) -> Vec<Vec<Point>> {
            vec![crate::view::joint_origins(&self.rig, actual)]
        }
        fn drain_paint(&mut self) -> Vec<PaintQuad> {
            std::mem::take(&mut self.pending)
        }
    }

    fn rig() -> Rig {
        crate::rig::load_rig(std::path::Path::new(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/config/irb120.toml"
        )))
        .expect("the IRB 120 rig loads")
    }

    #[test]
    fn frames_carry_the_sample_and_paint_reaches_late_pages_in_the_scene() {
        let home = [0.0, 0.0, 0.0, 0.0, std::f64::consts::FRAC_PI_6, 0.0];
        let slot = Arc::new(LiveSlot::new(LiveSample::at_rest(&home)));
        let quad = PaintQuad {
            wall: 0,
            quad: [[0.5, 0.0, 0.5]; 4],
        };
        let painter = Painter {
            rig: rig(),
            pending: vec![quad],
        };
        let hub = LiveHub::new(rig(), 250.0, 50.0, slot, Box::new(painter));
        let (_, mut frames) = hub.subscribe();
        let sent = hub.tick(Duration::from_millis(20), JobView::default());
        assert_eq!(
            frames.try_recv().expect("the frame reached the subscriber"),
            sent
        );
        let frame: serde_json::Value = serde_json::from_str(&sent).expect("the frame is JSON");
        assert_eq!(frame["type"], "frame");
        let actual: Vec<f64> =
            serde_json::from_value(frame["actual"].clone()).expect("actual is a list of numbers");
        assert!((actual[4] - 30.0).abs() < 1e-9, "degrees: {actual:?}");
        let chain = frame["chains"][0]
            .as_array()
            .expect("the first chain is a list");
        // Joint 1 sits on the base and tool0 on joint 6's origin: they add no point.
        assert_eq!(chain.len(), 6, "base and joints 2..=6: {chain:?}");
        assert_eq!(frame["paint"].as_array().expect("paint is a list").len(), 1);
        let again: serde_json::Value =
            serde_json::from_str(&hub.tick(Duration::from_millis(40), JobView::default()))
                .expect("the second frame is JSON");
        assert!(
            again["paint"]
                .as_array()
                .expect("paint is a list")
                .is_empty(),
            "sent once"
        );
        let (scene, _) = hub.subscribe();
        let scene: serde_json::Value = serde_json::from_str(&scene).expect("the scene is JSON");
        assert_eq!(scene["type"], "scene");
        assert_eq!(
            scene["scene"]["paint"]
                .as_array()
                .expect("the scene's paint is a list")
                .len(),
            1
        );
        assert_eq!(scene["joints"][0]["unit"], "deg");
    }

    #[test]
    fn a_scene_follower_gets_the_scene_then_only_new_paint() {
        let slot = Arc::new(LiveSlot::new(LiveSample::at_rest(&[0.0; 6])));
        let quad = PaintQuad {
            wall: 0,
            quad: [[0.5, 0.0, 0.5]; 4],
        };
        let painter = |pending| Painter {
            rig: rig(),
            pending,
        };
        let hub = LiveHub::new(rig(), 250.0, 50.0, slot, Box::new(painter(vec![quad])));
        let mut cursor = SceneCursor::default();
        assert!(
            matches!(hub.scene_since(&mut cursor), Some(SceneChange::New(v)) if v.paint.is_empty())
        );
        assert_eq!(hub.scene_since(&mut cursor), None);
        hub.tick(Duration::from_millis(20), JobView::default());
        assert_eq!(
            hub.scene_since(&mut cursor),
            Some(SceneChange::Paint(vec![quad]))
        );
        assert_eq!(hub.scene_since(&mut cursor), None);
        hub.set_scene(Box::new(painter(Vec::new())));
        assert!(matches!(
            hub.scene_since(&mut cursor),
            Some(SceneChange::New(_))
        ));
    }

    /// A vertical slide carrying a ball of 0.05 m: the cell's bodies in their simplest.
    fn slide() -> Rig {
        use crate::rig::{Collision, Joint, JointLimits, LinkBody, Shape};
        use glam::{DAffine3, DVec3};
        Rig {
            name: "slide".into(),
            base_frame: "base".into(),
            tool_frame: "tool".into(),
            joints: vec![Joint {
                name: "z".into(),
                kind: JointKind::Prismatic,
                origin: DAffine3::IDENTITY,
                axis: DVec3::Z,
                limits: JointLimits {
                    lower: -1.0,
                    upper: 1.0,
                    max_speed: 1.0,
                    max_acceleration: 10.0,
                },
            }],
            tool: DAffine3::IDENTITY,
            bodies: vec![LinkBody {
                name: "ball".into(),
                frame: 1,
                collisions: vec![Collision {
                    origin: DAffine3::IDENTITY,
                    shape: Shape::Sphere { radius: 0.05 },
                }],
            }],
            allowed_pairs: Vec::new(),
        }
    }

    #[test]
    fn frames_pose_the_cells_bodies_and_mark_the_closest_pair_within_the_margin() {
        use crate::cell::{Cell, CollisionModel};
        let rig = slide();
        let cell = Cell::builtin();
        let model = Arc::new(CollisionModel::new(&rig, &cell).expect("the slide's model builds"));
        let drawing = super::CellDrawing::new(&rig, &cell, model, rig.tool);
        let hub_at = |z: f64| {
            let slot = Arc::new(LiveSlot::new(LiveSample::at_rest(&[z])));
            let painter = Painter {
                rig: rig.clone(),
                pending: Vec::new(),
            };
            let drawing = super::CellDrawing::new(
                &rig,
                &cell,
                Arc::new(CollisionModel::new(&rig, &cell).expect("the model builds")),
                rig.tool,
            );
            LiveHub::new(rig.clone(), 250.0, 50.0, slot, Box::new(painter)).with_cell(drawing)
        };
        assert_eq!(drawing.bodies.len(), 1);
        // 5 mm over the floor: within the 10 mm margin.
        let hub = hub_at(0.055);
        let (scene, _) = hub.subscribe();
        let scene: serde_json::Value = serde_json::from_str(&scene).expect("the scene is JSON");
        assert_eq!(scene["scene"]["solids"][0]["name"], "floor");
        assert_eq!(scene["scene"]["bodies"][0]["frame"], 1);
        assert_eq!(scene["scene"]["bodies"][0]["solid"]["name"], "ball");
        let frame: serde_json::Value =
            serde_json::from_str(&hub.tick(Duration::from_millis(20), JobView::default()))
                .expect("the frame is JSON");
        let z = frame["bodies"][0]["position"][2]
            .as_f64()
            .expect("a position");
        assert!((z - 0.055).abs() < 1e-12, "{frame}");
        assert_eq!(frame["closest"]["a"], "ball");
        assert_eq!(frame["closest"]["b"], "floor");
        assert_eq!(frame["closest"]["status"], "within_margin");
        let d = frame["closest"]["distance_m"].as_f64().expect("a distance");
        assert!((d - 0.005).abs() < 1e-9, "{d}");
        assert_eq!(
            hub.closest().map(|c| c.status),
            Some("within_margin".into())
        );
        // 0.25 m over it: clear, no mark.
        let hub = hub_at(0.3);
        let frame: serde_json::Value =
            serde_json::from_str(&hub.tick(Duration::from_millis(20), JobView::default()))
                .expect("the frame is JSON");
        assert!(frame["closest"].is_null(), "{frame}");
        assert_eq!(frame["bodies"].as_array().map(Vec::len), Some(1));
    }
}
