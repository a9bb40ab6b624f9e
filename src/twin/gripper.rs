//! The twin's I/O (protocol v3, docs/protocol.md 6.10): its gripper (the output `gripper`,
//! 1 closes, 0 opens, answered when its closing time has passed), the input `part_held`,
//! and the cell's parts (issue 29): a part lying within the grasp zone when the gripper
//! has closed is grasped, moves with the TCP while held, and stays where it is when the
//! gripper has opened. A part at rest (at its start, or released anywhere but a goal that
//! takes it in) is an obstacle: every cycle the carried part is checked against the cell's
//! objects and the resting parts, and the robot's bodies and tool against the resting
//! parts. Then the judge: each part's final pose against its goal, parts dropped or never
//! picked, carried parts' collisions, and the time between one pick and the next (measured
//! on the twin's cycles).
//!
//! Owns the gripper, the parts and their judgement. It must not change the arm's motion
//! (the twin's servo model does that), talk to a link, or allocate in a cycle that neither
//! grasps nor releases.

use crate::cell::{Cell, CellObject, CollisionModel, Gripper, Part, Scratch, Tool};
use crate::protocol::{IoKind, IoMessage, IoResult, IoState};
use crate::rig::{Rig, rotation_angle_between};
use glam::{DAffine3, DQuat};
use serde::Serialize;
use std::collections::VecDeque;
use std::sync::{Arc, Mutex, PoisonError};

/// The gripper's output: 1 closes it, 0 opens it.
pub const GRIPPER_OUTPUT: &str = "gripper";
/// The input that is on while the gripper holds a part.
pub const PART_HELD_INPUT: &str = "part_held";
/// The judge's tolerances for a placed part (issue 29's figure): within 1 mm and 1 deg of
/// its goal.
pub const PLACED_WITHIN_M: f64 = 0.001;
pub const PLACED_WITHIN_DEG: f64 = 1.0;
/// A carried part is in contact when it sinks into a cell object deeper than this: a part
/// picked off (or set down on) a surface touches it at distance 0, which rounding puts a
/// few nanometres either side; a tenth of a millimetre is far above that and far below any
/// real collision.
pub const CONTACT_DEPTH_M: f64 = 1e-4;

/// Where the gripper is in its travel.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Travel {
    /// At rest, open (false) or closed (true).
    At(bool),
    /// Moving toward closed (true) or open (false); cycles left.
    Moving(bool, u32),
}

/// What became of one part, for the report.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PartJudgement {
    pub name: String,
    pub goal: String,
    /// `placed` (released within the tolerances of its goal), `dropped` (released anywhere
    /// else), `carried` (still held at the end), `never_picked`.
    pub state: &'static str,
    /// The final grasp frame's distance (mm) and angle (deg) from the goal.
    pub position_error_mm: f64,
    pub orientation_error_deg: f64,
    /// The twin's time (s from its start) when the part was grasped and released.
    pub picked_at_s: Option<f64>,
    pub released_at_s: Option<f64>,
    /// Cycles in which the carried part sank into a cell object.
    pub collision_cycles: u64,
    /// The deepest of them (mm) and the object, when there was one.
    pub collision_depth_mm: f64,
    pub collided_with: Option<String>,
    /// Cycles in which a body of the robot or its tool sank into this part while it
    /// rested, the deepest (mm) and the body.
    pub struck_cycles: u64,
    pub struck_depth_mm: f64,
    pub struck_by: Option<String>,
}

/// The twin's verdict on the cell.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CellJudgement {
    pub parts: usize,
    pub placed: usize,
    pub dropped: usize,
    pub never_picked: usize,
    pub carried: usize,
    /// Carried parts that sank into a cell object or a resting part at least once.
    pub collisions: usize,
    /// Resting parts a body of the robot or its tool sank into at least once.
    pub struck: usize,
    pub placed_within_mm: f64,
    pub placed_within_deg: f64,
    pub worst_position_error_mm: f64,
    pub worst_orientation_error_deg: f64,
    /// Seconds from each part's pick to the next part's pick (the last: to its release),
    /// measured on the twin's cycles, in pick order.
    pub cycle_times_s: Vec<f64>,
    pub per_part: Vec<PartJudgement>,
}

/// The parts as the twin last saw them, for the live page and Foxglove to draw and judge:
/// every part's grasp frame (cell frame), refreshed each cycle one is carried (a `try_lock`
/// that never waits: a cycle that finds a reader skips one refresh), and the judgement,
/// renewed when a part is grasped or released.
#[derive(Debug, Default)]
pub struct PartsBoard {
    state: Mutex<PartsNow>,
}

/// What a [`PartsBoard`] holds.
#[derive(Debug, Clone, Default)]
pub struct PartsNow {
    /// Each part's grasp frame in the cell frame, in the cell's part order.
    pub poses: Vec<DAffine3>,
    pub judgement: Option<CellJudgement>,
}

impl PartsBoard {
    pub fn read(&self) -> PartsNow {
        self.state
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }
}

struct PartState {
    part: Part,
    pose: DAffine3,
    picked_cycle: Option<u64>,
    released_cycle: Option<u64>,
    collision_cycles: u64,
    deepest: f64,
    collided_with: Option<String>,
    struck: Contact,
}

/// The contacts of one part with one kind of body: cycles, the deepest and with what.
#[derive(Debug, Clone, Default)]
struct Contact {
    cycles: u64,
    deepest: f64,
    with: Option<String>,
}

impl Contact {
    /// One cycle's clearance `distance_m` to body `other`: counted when deeper than a touch.
    fn observe(&mut self, distance_m: f64, other: &str) {
        if distance_m >= -CONTACT_DEPTH_M {
            return;
        }
        self.cycles += 1;
        if -distance_m > self.deepest {
            self.deepest = -distance_m;
            if self.with.as_deref() != Some(other) {
                self.with = Some(other.to_owned());
            }
        }
    }
}

/// The robot's bodies and tool against the resting parts alone (the cell's objects are
/// the contact watch's), rebuilt when a part is grasped or released.
struct Resting {
    model: CollisionModel,
    scratch: Scratch,
}

/// The carried part as a tool of its own against the cell's objects.
struct Carried {
    part: usize,
    /// The part's grasp frame in the TCP frame.
    grip: DAffine3,
    model: CollisionModel,
    scratch: Scratch,
}

impl Carried {
    /// Part `part` held at `grip`, as `model`, with the scratch space its queries use.
    fn new(part: usize, grip: DAffine3, model: CollisionModel) -> Carried {
        let scratch = model.scratch();
        Carried {
            part,
            grip,
            model,
            scratch,
        }
    }
}

/// How the twin finds its TCP in the cell frame.
struct Kinematics {
    rig_at_tcp: Rig,
    /// The flange rig (what a collision model is built on).
    rig: Rig,
    cell: Cell,
}

pub struct TwinIo {
    gripper: Gripper,
    period_s: f64,
    travel: Travel,
    /// The request answered when the gripper's travel ends.
    pending: Option<u32>,
    answers: VecDeque<IoState>,
    kinematics: Option<Kinematics>,
    parts: Vec<PartState>,
    carried: Option<Carried>,
    resting: Option<Resting>,
    board: Arc<PartsBoard>,
    cycle: u64,
    /// Trouble the twin could not act on (a collision model that would not build), in words.
    pub trouble: Option<String>,
}

impl TwinIo {
    /// A gripper with no parts and no cell: it opens and closes, holds nothing.
    pub fn bare(period_s: f64) -> Self {
        TwinIo {
            gripper: Gripper::default(),
            period_s,
            travel: Travel::At(false),
            pending: None,
            answers: VecDeque::with_capacity(4),
            kinematics: None,
            parts: Vec::new(),
            carried: None,
            resting: None,
            board: Arc::default(),
            cycle: 0,
            trouble: None,
        }
    }

    /// The gripper and parts of `cell` on `rig` (its flange frame, as loaded).
    pub fn in_cell(rig: &Rig, cell: &Cell, period_s: f64) -> Self {
        let parts = cell
            .parts
            .iter()
            .map(|part| PartState {
                part: part.clone(),
                pose: part.start,
                picked_cycle: None,
                released_cycle: None,
                collision_cycles: 0,
                deepest: 0.0,
                collided_with: None,
                struck: Contact::default(),
            })
            .collect();
        let mut io = TwinIo {
            gripper: cell.gripper,
            kinematics: Some(Kinematics {
                rig_at_tcp: cell.rig_at_tcp(rig),
                rig: rig.clone(),
                cell: cell.clone(),
            }),
            parts,
            ..TwinIo::bare(period_s)
        };
        io.rebuild_resting();
        io.publish();
        io
    }

    /// Where the parts are and the judgement, shared with the view; `None` without parts.
    pub fn board(&self) -> Option<Arc<PartsBoard>> {
        (!self.parts.is_empty()).then(|| self.board.clone())
    }

    /// Every part's pose and the judgement onto the board (a grasp, a release, the start).
    fn publish(&self) {
        let now = PartsNow {
            poses: self.parts.iter().map(|state| state.pose).collect(),
            judgement: self.judgement(),
        };
        *self
            .board
            .state
            .lock()
            .unwrap_or_else(PoisonError::into_inner) = now;
    }

    /// The carried part's pose onto the board, in place, unless a reader holds it.
    fn publish_carried(&self, part: usize) {
        if let Ok(mut board) = self.board.state.try_lock()
            && let Some(pose) = board.poses.get_mut(part)
        {
            *pose = self.parts[part].pose;
        }
    }

    /// A request from the bridge; `may_change` is false while the twin is unbound or
    /// faulted (a SetOutput is then refused, docs/protocol.md 6.10 rule 5).
    pub fn request(&mut self, message: &IoMessage, may_change: bool) {
        let answer = match message {
            IoMessage::SetOutput {
                request,
                name,
                value,
            } => self.set_output(*request, name, *value, may_change),
            IoMessage::ReadInput { request, name } => Some(IoState {
                request: *request,
                kind: IoKind::Input,
                result: if name == PART_HELD_INPUT {
                    IoResult::Done
                } else {
                    IoResult::NoSuch
                },
                value: name == PART_HELD_INPUT && self.carried.is_some(),
                name: name.clone(),
            }),
            IoMessage::State(_) => None,
        };
        if let Some(answer) = answer {
            self.answers.push_back(answer);
        }
    }

    fn set_output(
        &mut self,
        request: u32,
        name: &str,
        value: bool,
        may_change: bool,
    ) -> Option<IoState> {
        let answer = |result, value| IoState {
            request,
            kind: IoKind::Output,
            result,
            value,
            name: name.to_owned(),
        };
        if name != GRIPPER_OUTPUT {
            return Some(answer(IoResult::NoSuch, false));
        }
        if !may_change || self.pending.is_some() {
            return Some(answer(IoResult::Refused, false));
        }
        if self.travel == Travel::At(value) {
            return Some(answer(IoResult::Done, value));
        }
        let cycles = (self.gripper.closing_s / self.period_s).ceil().max(1.0) as u32;
        self.travel = Travel::Moving(value, cycles);
        self.pending = Some(request);
        None
    }

    /// The session ended (link loss, a reset): the answers still owed are dropped, never
    /// sent into a later session, where a restarted request number could match another
    /// request (docs/protocol.md 6.10 rule 2). A gripper still moving goes on moving.
    pub fn end_session(&mut self) {
        self.pending = None;
        self.answers.clear();
    }

    /// The next answer due, if any.
    pub fn take_answer(&mut self) -> Option<IoState> {
        self.answers.pop_front()
    }

    /// One cycle at the arm's `actual` positions: the carried part follows the TCP and is
    /// checked against the cell; the gripper travels, grasping or releasing at its end.
    pub fn tick(&mut self, actual: &[f64]) {
        self.cycle += 1;
        let tcp = self.tcp(actual);
        if let (Some(carried), Some(tcp)) = (self.carried.as_mut(), tcp) {
            let state = &mut self.parts[carried.part];
            state.pose = tcp * carried.grip;
            let clearance = carried.model.clearance(actual, &mut carried.scratch);
            if clearance.distance_m < -CONTACT_DEPTH_M {
                state.collision_cycles += 1;
                if -clearance.distance_m > state.deepest {
                    state.deepest = -clearance.distance_m;
                    let other = [clearance.a, clearance.b]
                        .into_iter()
                        .map(|id| carried.model.body_name(id))
                        .find(|name| *name != state.part.name)
                        .unwrap_or("?");
                    state.collided_with = Some(other.to_owned());
                }
            }
        }
        if let Some(part) = self.carried.as_ref().map(|c| c.part) {
            self.publish_carried(part);
        }
        self.watch_resting(actual);
        let Travel::Moving(closing, left) = self.travel else {
            return;
        };
        if left > 1 {
            self.travel = Travel::Moving(closing, left - 1);
            return;
        }
        self.travel = Travel::At(closing);
        if closing {
            self.grasp(tcp);
        } else {
            self.release();
        }
        if let Some(request) = self.pending.take() {
            self.answers.push_back(IoState {
                request,
                kind: IoKind::Output,
                result: IoResult::Done,
                value: closing,
                name: GRIPPER_OUTPUT.to_owned(),
            });
        }
    }

    /// The robot's bodies and tool against the resting parts at `actual`: the part a body
    /// sank into counts the contact.
    fn watch_resting(&mut self, actual: &[f64]) {
        let Some(resting) = self.resting.as_mut() else {
            return;
        };
        let clearance = resting.model.clearance(actual, &mut resting.scratch);
        if clearance.distance_m >= -CONTACT_DEPTH_M {
            return;
        }
        let (a, b) = (
            resting.model.body_name(clearance.a),
            resting.model.body_name(clearance.b),
        );
        let Some((state, body)) = self.parts.iter_mut().find_map(|state| {
            if state.part.name == a {
                Some((state, b))
            } else if state.part.name == b {
                Some((state, a))
            } else {
                None
            }
        }) else {
            return;
        };
        state.struck.observe(clearance.distance_m, body);
    }

    /// Whether part `index` rests in the cell as an obstacle: not carried, and not placed
    /// on a goal that takes it in.
    fn rests(&self, index: usize) -> bool {
        let state = &self.parts[index];
        if self.carried.as_ref().is_some_and(|c| c.part == index) {
            return false;
        }
        !(state.part.taken_at_goal && state.released_cycle.is_some() && placed(state))
    }

    /// The resting parts as cell objects (their solids where they lie).
    fn resting_objects(&self) -> Vec<CellObject> {
        (0..self.parts.len())
            .filter(|&index| self.rests(index))
            .map(|index| {
                let state = &self.parts[index];
                CellObject {
                    name: state.part.name.clone(),
                    pose: state.pose * state.part.solid.origin,
                    shape: state.part.solid.shape.clone(),
                }
            })
            .collect()
    }

    /// The models that see the resting parts, after a part was grasped or released (or at
    /// the start): the robot's against them, and the carried part's against them and the
    /// cell's objects.
    fn rebuild_resting(&mut self) {
        let Some(kinematics) = self.kinematics.as_ref() else {
            return;
        };
        let objects = self.resting_objects();
        self.resting = None;
        if !objects.is_empty() {
            match robot_against(kinematics, objects.clone()) {
                Ok(model) => {
                    let scratch = model.scratch();
                    self.resting = Some(Resting { model, scratch });
                }
                Err(error) => self.trouble = Some(error.to_string()),
            }
        }
        let Some(carried) = self.carried.as_ref() else {
            return;
        };
        let (index, grip) = (carried.part, carried.grip);
        match carried_model(kinematics, &self.parts[index].part, grip, objects) {
            Ok(model) => self.carried = Some(Carried::new(index, grip, model)),
            Err(error) => self.trouble = Some(error.to_string()),
        }
    }

    fn tcp(&self, actual: &[f64]) -> Option<DAffine3> {
        let kinematics = self.kinematics.as_ref()?;
        let base_to_tcp = kinematics.rig_at_tcp.forward(actual).ok()?;
        Some(kinematics.cell.mount * base_to_tcp)
    }

    /// The gripper has closed at `tcp`: the first free part within the grasp zone is held.
    fn grasp(&mut self, tcp: Option<DAffine3>) {
        let (Some(tcp), Some(kinematics)) = (tcp, self.kinematics.as_ref()) else {
            return;
        };
        let zone = (self.gripper.grasp_zone_m, self.gripper.grasp_zone_rad);
        let Some(index) = self.parts.iter().position(|state| {
            let (distance, angle) = pose_error(&state.pose, &tcp);
            distance <= zone.0 && angle <= zone.1
        }) else {
            return;
        };
        let grip = tcp.inverse() * self.parts[index].pose;
        match carried_model(kinematics, &self.parts[index].part, grip, Vec::new()) {
            Ok(model) => {
                self.carried = Some(Carried::new(index, grip, model));
                let state = &mut self.parts[index];
                state.picked_cycle.get_or_insert(self.cycle);
                state.released_cycle = None;
                self.rebuild_resting();
                self.publish();
            }
            Err(error) => self.trouble = Some(error.to_string()),
        }
    }

    fn release(&mut self) {
        if let Some(carried) = self.carried.take() {
            self.parts[carried.part].released_cycle = Some(self.cycle);
            self.rebuild_resting();
            self.publish();
        }
    }

    /// The judgement so far; `None` for a twin without parts.
    pub fn judgement(&self) -> Option<CellJudgement> {
        if self.parts.is_empty() {
            return None;
        }
        let seconds = |cycle: u64| cycle as f64 * self.period_s;
        let carried = self.carried.as_ref().map(|c| c.part);
        let per_part: Vec<PartJudgement> = self
            .parts
            .iter()
            .enumerate()
            .map(|(index, state)| {
                let (distance, angle) = pose_error(&state.pose, &state.part.goal);
                let fate = match (state.picked_cycle, state.released_cycle) {
                    _ if carried == Some(index) => "carried",
                    (None, _) => "never_picked",
                    (Some(_), Some(_)) if placed(state) => "placed",
                    _ => "dropped",
                };
                PartJudgement {
                    name: state.part.name.clone(),
                    goal: state.part.goal_name.clone(),
                    state: fate,
                    position_error_mm: distance * 1e3,
                    orientation_error_deg: angle.to_degrees(),
                    picked_at_s: state.picked_cycle.map(seconds),
                    released_at_s: state.released_cycle.map(seconds),
                    collision_cycles: state.collision_cycles,
                    collision_depth_mm: state.deepest * 1e3,
                    collided_with: state.collided_with.clone(),
                    struck_cycles: state.struck.cycles,
                    struck_depth_mm: state.struck.deepest * 1e3,
                    struck_by: state.struck.with.clone(),
                }
            })
            .collect();
        let count = |fate: &str| per_part.iter().filter(|p| p.state == fate).count();
        let mut picks: Vec<(u64, Option<u64>)> = self
            .parts
            .iter()
            .filter_map(|s| s.picked_cycle.map(|p| (p, s.released_cycle)))
            .collect();
        picks.sort_unstable();
        let cycle_times_s = picks
            .iter()
            .enumerate()
            .filter_map(|(k, (picked, released))| {
                let end = picks.get(k + 1).map(|next| next.0).or(*released)?;
                Some(seconds(end - picked))
            })
            .collect();
        let placed: Vec<&PartJudgement> = per_part.iter().filter(|p| p.state == "placed").collect();
        Some(CellJudgement {
            parts: per_part.len(),
            placed: placed.len(),
            dropped: count("dropped"),
            never_picked: count("never_picked"),
            carried: count("carried"),
            collisions: per_part.iter().filter(|p| p.collision_cycles > 0).count(),
            struck: per_part.iter().filter(|p| p.struck_cycles > 0).count(),
            placed_within_mm: PLACED_WITHIN_M * 1e3,
            placed_within_deg: PLACED_WITHIN_DEG,
            worst_position_error_mm: placed
                .iter()
                .map(|p| p.position_error_mm)
                .fold(0.0, f64::max),
            worst_orientation_error_deg: placed
                .iter()
                .map(|p| p.orientation_error_deg)
                .fold(0.0, f64::max),
            cycle_times_s,
            per_part,
        })
    }
}

/// Whether a part's grasp frame lies within the judge's tolerances of its goal.
fn placed(state: &PartState) -> bool {
    let (distance, angle) = pose_error(&state.pose, &state.part.goal);
    distance <= PLACED_WITHIN_M && angle.to_degrees() <= PLACED_WITHIN_DEG
}

/// The robot's bodies and its tool against `objects` (the resting parts) alone: the
/// cell's own objects are left out (the contact watch measures them), and so are the
/// pairs of the robot's own bodies (the same).
fn robot_against(
    kinematics: &Kinematics,
    objects: Vec<CellObject>,
) -> Result<CollisionModel, crate::cell::CellError> {
    let mut moving: Vec<&str> = kinematics
        .rig
        .bodies
        .iter()
        .map(|b| b.name.as_str())
        .collect();
    moving.extend(kinematics.cell.tool.as_ref().map(|tool| tool.name.as_str()));
    let mut allowed = Vec::with_capacity(moving.len() * moving.len());
    for (i, a) in moving.iter().enumerate() {
        for b in &moving[i + 1..] {
            allowed.push(((*a).to_owned(), (*b).to_owned()));
        }
    }
    let cell = Cell {
        objects,
        allowed_pairs: allowed,
        ..kinematics.cell.clone()
    };
    CollisionModel::new(&kinematics.rig, &cell)
}

/// Distance (m) and angle (rad) between two frames.
fn pose_error(a: &DAffine3, b: &DAffine3) -> (f64, f64) {
    let rotation = |m: &DAffine3| DQuat::from_mat3(&m.matrix3);
    (
        a.translation.distance(b.translation),
        rotation_angle_between(rotation(a), rotation(b)),
    )
}

/// The cell's objects and the resting parts (`resting`) against the carried part alone,
/// as a tool on the flange: its solid placed by the grasp (`grip`, the part's frame in the
/// TCP's) behind the TCP.
fn carried_model(
    kinematics: &Kinematics,
    part: &Part,
    grip: DAffine3,
    resting: Vec<CellObject>,
) -> Result<CollisionModel, crate::cell::CellError> {
    let tcp = kinematics
        .cell
        .tool
        .as_ref()
        .map_or(DAffine3::IDENTITY, |tool| tool.tcp);
    let mut rig = kinematics.rig.clone();
    rig.bodies.clear();
    rig.allowed_pairs.clear();
    let cell = Cell {
        tool: Some(Tool {
            name: part.name.clone(),
            bodies: vec![crate::rig::geometry::Collision {
                origin: tcp * grip * part.solid.origin,
                shape: part.solid.shape.clone(),
            }],
            tcp,
        }),
        allowed_pairs: Vec::new(),
        objects: kinematics
            .cell
            .objects
            .iter()
            .cloned()
            .chain(resting)
            .collect(),
        ..kinematics.cell.clone()
    };
    CollisionModel::new(&rig, &cell)
}
