//! The coverage planner: vertical strokes over every wall, base stations that make each
//! stroke reachable and collision-free, and the moves between them, all as one trajectory
//! of the painter rig (base, lift and arm) through the normal planning stages.
//!
//! Each wall is cut into intervals at its openings' edges; each interval is filled with
//! columns one brush width apart minus the overlap, the last flush with the interval's
//! edge; a column over an opening stops below it and resumes above. A stroke is an arm
//! move (FABRIK, straight line at 1 mm steps, with continuity) from the floor up to the
//! hold height, then the lift carries the held arm to the top: an exact vertical line. For
//! every column a short list of brush attitudes (turned about the wall normal, tilted
//! about the contact line) and base stations is tried in order; the first whose poses the
//! arm reaches and whose body clears every wall by the planning clearance is used. A
//! column with none is reported before motion and left out. The whole plan is checked
//! against the walls sample by sample before it is returned.
//!
//! Owns choosing strokes, attitudes and stations. Must not stream, and never clamps a
//! target: everything is solved, validated and collision-checked.

use super::body::{Body, RoomTravel, Scratch, Travel};
use super::config::{EXTRA_AXES, LIFT_AXIS, PaintSettings};
use super::room::{Room, Wall};
use crate::ik::{BaseHeldSolver, IkSolver, StructureError, plan_cartesian};
use crate::rig::{JointList, Pose, Rig};
use crate::trajectory::{
    PlanError, PlanSettings, Trajectory, TrajectoryError, plan_joint_moves, validate,
};
use glam::{DVec2, DVec3};
use serde::Serialize;
use std::collections::HashMap;
use std::num::NonZeroUsize;
use std::sync::atomic::{AtomicUsize, Ordering};
use thiserror::Error;

#[derive(Debug, Error)]
pub enum PaintPlanError {
    #[error(transparent)]
    Structure(#[from] StructureError),
    #[error(transparent)]
    Plan(#[from] PlanError),
    #[error(transparent)]
    Trajectory(#[from] TrajectoryError),
    #[error("start position {start}: the painter rig has {dof} axes")]
    BadStart { start: JointList, dof: usize },
    #[error(
        "no collision-free route from wall {from_wall} to wall {to_wall}: from {from} to {to}: \
         {tries}"
    )]
    NoRoute {
        from_wall: usize,
        to_wall: usize,
        from: JointList,
        to: JointList,
        tries: RouteTries,
    },
    #[error(
        "plan check: sample {sample} comes {clearance_m:.4} m from a wall or the floor (body must stay clear)"
    )]
    Collides { sample: usize, clearance_m: f64 },
    #[error("the painter's collision model")]
    Cell(#[from] crate::cell::CellError),
    #[error(
        "the cell's margin_m = {margin_m} m is not below the paint config's \
         body.planning_clearance_m = {clearance_m} m: the planner keeps its clearance at its \
         samples, and the check before motion, continuous between them, would refuse the plan"
    )]
    MarginNotBelowClearance { margin_m: f64, clearance_m: f64 },
}

/// Why a column, a stroke or a move between strokes is refused.
#[derive(Debug, Error)]
pub enum PlanRefusal {
    #[error("no candidate")]
    NoCandidate,
    #[error("no base position at standoff {standoff_m:.2} m")]
    NoBasePosition { standoff_m: f64 },
    #[error("body comes {clearance_m:.3} m from a wall or the floor (needs {needed_m:.3})")]
    BodyTooClose { clearance_m: f64, needed_m: f64 },
    #[error("arm cannot paint up to {height_m:.3} m above its base")]
    CannotPaint { height_m: f64 },
    #[error("arm cannot retract at {height_m:.3} m above its base")]
    CannotRetract { height_m: f64 },
    #[error("the body would come {clearance_m:.3} m from a wall or the floor")]
    RouteCollides { clearance_m: f64 },
    #[error("the brush would come {off_m:.4} m from a wall (needs {needed_m:.4})")]
    BrushNearWall { off_m: f64, needed_m: f64 },
    #[error(transparent)]
    Trajectory(#[from] TrajectoryError),
    #[error(transparent)]
    Plan(#[from] PlanError),
}

/// One way a free move was tried.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum RouteTry {
    Direct,
    BackingOff { distance_m: f64 },
    ViaCentre,
}

/// Every way a free move was tried, and why each was refused.
#[derive(Debug, Default)]
pub struct RouteTries(pub Vec<(RouteTry, PlanRefusal)>);

impl std::fmt::Display for RouteTries {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        for (i, (route, why)) in self.0.iter().enumerate() {
            if i > 0 {
                f.write_str("; ")?;
            }
            match route {
                RouteTry::Direct => write!(f, "direct: {why}")?,
                RouteTry::BackingOff { distance_m } => {
                    write!(f, "backing off {distance_m} m: {why}")?
                }
                RouteTry::ViaCentre => write!(f, "via the centre: {why}")?,
            }
        }
        Ok(())
    }
}

/// A stroke the planner could not reach, reported before motion.
#[derive(Debug, Clone, Serialize)]
pub struct UnreachableStroke {
    pub wall: usize,
    pub s_m: f64,
    pub v_from_m: f64,
    pub v_to_m: f64,
    pub reason: String,
}

/// One planned stroke, in wall coordinates (the brush centre's path).
#[derive(Debug, Clone, Serialize)]
pub struct PlannedStroke {
    pub wall: usize,
    pub s_m: f64,
    pub v_from_m: f64,
    pub v_to_m: f64,
    pub turn_deg: f64,
    pub tilt_deg: f64,
    /// First and last sample of the stroke (approach to retract) in the plan.
    pub samples: [usize; 2],
}

pub struct PaintPlan {
    pub trajectory: Trajectory,
    pub strokes: Vec<PlannedStroke>,
    pub unreachable: Vec<UnreachableStroke>,
}

/// Brush attitude: turned by `phi` about the wall normal (contact line rising toward +s
/// for phi > 0), tilted by `theta` about the contact line (handle rising from the wall).
#[derive(Debug, Clone, Copy, PartialEq)]
struct Attitude {
    phi: f64,
    theta: f64,
}

/// Where the base stands for a column: `s` along the wall, `standoff` from its plane.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Station {
    s: f64,
    standoff: f64,
}

/// A column of strokes: band centre, attitude, station and its vertical segments.
#[derive(Debug, Clone)]
struct Column {
    s: f64,
    attitude: Attitude,
    station: Station,
    segments: Vec<(f64, f64)>,
    /// One upward stroke per segment, planned and checked.
    strokes: Vec<Trajectory>,
}

/// A column's band before its attitude is chosen: flush with an edge, or centred.
#[derive(Debug, Clone, Copy)]
enum Band {
    /// Flush against an edge at `edge` on its right (`toward` = +1) or left (-1), in a
    /// gap `room` wide (a band wider than that must be turned to fit).
    Flush { edge: f64, toward: f64, room: f64 },
    /// Centred at `centre`, one brush width wide.
    Centred { centre: f64 },
}

/// Canonical frame for cached arm moves: base at the origin with yaw 0 and lift
/// [`CANONICAL_LIFT`], the wall's plane at x = standoff, `s` growing along -y.
const CANONICAL_LIFT: f64 = 1.0;
/// Base back-off before the arm changes pose between stations, tried in order (m).
const BACKOFFS: [f64; 6] = [0.3, 0.5, 0.8, 0.2, 0.12, 0.06];
/// During free moves the brush's ends stay at least this many contact tolerances off
/// every wall, so nothing is painted between strokes.
const FREE_MOVE_OFF_WALL: f64 = 3.0;
/// Turns a band between two others may take near a corner (deg).
const CENTRED_TURNS_DEG: [f64; 4] = [0.0, 8.0, 14.0, 20.0];
/// Bands this close to a corner may turn the brush too (m).
const NEAR_CORNER_M: f64 = 0.6;
/// Brush tilts about the contact line a column tries, in order (deg): level first, then
/// the handle rising from the wall, which lets the arm reach lower and higher on it.
const TILTS_DEG: [f64; 5] = [0.0, 25.0, 45.0, 52.0, 60.0];
/// Margin on the least turn that fits a band into a gap narrower than the brush: the
/// turned brush then clears the gap's edges by 2 % rather than touching them.
const FIT_TURN_MARGIN: f64 = 1.02;
/// Base standoffs a column tries, as offsets from `strokes.reach_m` (m), in order: the
/// usual reach, nearer, farther, then nearer still for the ceiling's top strokes.
const STANDOFF_OFFSETS_M: [f64; 4] = [0.0, -0.08, 0.07, -0.15];
/// The most a brush is turned about the wall normal to get into a corner (deg).
const MAX_TURN_DEG: f64 = 55.0;

type PieceKey = Vec<i64>;

pub struct Planner<'a> {
    settings: &'a PaintSettings,
    room: &'a Room,
    plan: PlanSettings,
    rig: &'a Rig,
    solver: BaseHeldSolver,
    body: Body,
    scratch: Scratch,
    /// Bounds the body's clearance from the walls and from the floor between samples.
    travel: RoomTravel,
    /// Bounds the brush's distance from the walls' planes between samples.
    travel_planar: Travel,
    travel_arm: Vec<f64>,
    pieces: HashMap<PieceKey, Option<Trajectory>>,
    /// [`Planner::base_range`] by wall and standoff (bits): every band of a wall asks
    /// again for the same few standoffs.
    base_ranges: HashMap<(usize, u64), Option<(f64, f64)>>,
    threads: NonZeroUsize,
}

/// A stroke in painting order (downward columns already reversed), with what the plan
/// reports of it; `record.samples` is filled in when the plan is put together.
struct Leg {
    stroke: Trajectory,
    record: PlannedStroke,
}

/// One wall's strokes in painting order and the bands it could not place: all a wall
/// needs of the planner once the route between walls is left aside.
struct WallStrokes {
    legs: Vec<Leg>,
    unreachable: Vec<UnreachableStroke>,
}

/// A free move still to plan: from, to, and the walls it joins (for the error).
struct RouteRequest {
    from: Vec<f64>,
    to: Vec<f64>,
    walls: (usize, usize),
}

fn quantise(x: f64) -> i64 {
    (x * 1e5).round() as i64
}

impl<'a> Planner<'a> {
    pub fn new(
        settings: &'a PaintSettings,
        room: &'a Room,
        plan: PlanSettings,
    ) -> Result<Self, PaintPlanError> {
        let rig = &settings.rig;
        let body = Body::new(rig, room, &settings.config)?;
        Ok(Self {
            settings,
            room,
            plan,
            rig,
            solver: BaseHeldSolver::new(rig.clone(), EXTRA_AXES)?,
            travel: RoomTravel::new(rig, &body.brush),
            travel_planar: Travel::planar(rig, &body.brush),
            scratch: Scratch::new(rig, &body),
            body,
            travel_arm: settings
                .config
                .strokes
                .travel_arm_deg
                .iter()
                .map(|d| d.to_radians())
                .collect(),
            pieces: HashMap::new(),
            base_ranges: HashMap::new(),
            threads: std::thread::available_parallelism().unwrap_or(NonZeroUsize::MIN),
        })
    }

    /// Plans on `threads` threads (by default, as many as the machine runs at once). The
    /// plan is the same, bit for bit, whatever the number.
    pub fn with_threads(mut self, threads: NonZeroUsize) -> Self {
        self.threads = threads;
        self
    }

    fn inset(&self) -> f64 {
        self.settings.config.brush.edge_inset_m
    }

    fn brush_width(&self) -> f64 {
        self.settings.config.brush.width_m
    }

    fn margin(&self) -> f64 {
        self.settings.config.body.planning_clearance_m
    }

    /// The painter's joint values with the base at `station` of `wall` and the arm at `arm`.
    fn joints_at(&self, wall: &Wall, station: Station, lift: f64, arm: &[f64]) -> Vec<f64> {
        let base = wall.point(station.s, 0.0, station.standoff);
        let mut joints = vec![base.x, base.y, wall.heading_rad, lift];
        joints.extend_from_slice(arm);
        joints
    }

    /// The brush's tool0 pose in the canonical frame for a brush centre `lateral` (along
    /// s) from the base, `height` above the arm's base plate, `off` from the wall.
    fn canonical_pose(
        &self,
        station: Station,
        attitude: Attitude,
        lateral: f64,
        height: f64,
        off: f64,
    ) -> Pose {
        let n = DVec3::X;
        let t = -DVec3::Y;
        let v = DVec3::Z;
        let (sp, cp) = attitude.phi.sin_cos();
        let (st, ct) = attitude.theta.sin_cos();
        let line = t * cp + v * sp;
        let m = -t * sp + v * cp;
        let handle_out = -n * ct + m * st;
        let centre = DVec3::new(station.standoff - off, -lateral, CANONICAL_LIFT + height);
        Pose::from_affine(&self.body.brush.tool0_for(centre, line, -handle_out))
    }

    fn canonical_seed(&self) -> Vec<f64> {
        let mut seed = vec![0.0, 0.0, 0.0, CANONICAL_LIFT];
        seed.extend_from_slice(&self.travel_arm);
        seed
    }

    /// A straight brush move in the canonical frame through `(off, height)` waypoints
    /// (from the first), cached: every wall is the same to the arm.
    fn piece(
        &mut self,
        station: Station,
        attitude: Attitude,
        lateral: f64,
        path: &[(f64, f64)],
        start_arm: Option<&[f64]>,
    ) -> Option<Trajectory> {
        let mut key: PieceKey = vec![
            quantise(station.standoff),
            quantise(lateral),
            quantise(attitude.phi),
            quantise(attitude.theta),
        ];
        key.extend(path.iter().flat_map(|(o, h)| [quantise(*o), quantise(*h)]));
        key.extend(start_arm.unwrap_or(&[]).iter().map(|q| quantise(*q)));
        if let Some(cached) = self.pieces.get(&key) {
            return cached.clone();
        }
        let planned = self.plan_piece(station, attitude, lateral, path, start_arm);
        self.pieces.insert(key, planned.clone());
        planned
    }

    fn plan_piece(
        &mut self,
        station: Station,
        attitude: Attitude,
        lateral: f64,
        path: &[(f64, f64)],
        start_arm: Option<&[f64]>,
    ) -> Option<Trajectory> {
        let poses: Vec<Pose> = path
            .iter()
            .map(|(off, h)| self.canonical_pose(station, attitude, lateral, *h, *off))
            .collect();
        let start = match start_arm {
            // Continue from where the previous piece left the arm (same branch).
            Some(arm) => {
                let mut joints = self.canonical_seed();
                joints[EXTRA_AXES..].copy_from_slice(arm);
                joints
            }
            None => {
                self.solver
                    .solve(&poses[0], &self.canonical_seed())
                    .ok()?
                    .joints
            }
        };
        plan_cartesian(&self.solver, &start, &poses[1..], &self.plan).ok()
    }

    /// Re-bases a canonical piece onto `wall` at `station` and lift `lift`.
    fn placed(
        &self,
        piece: &Trajectory,
        wall: &Wall,
        station: Station,
        lift: f64,
    ) -> Result<Trajectory, TrajectoryError> {
        let base = self.joints_at(wall, station, lift, &[]);
        let dof = piece.dof();
        let mut positions = Vec::with_capacity(piece.len() * dof);
        let mut velocities = Vec::with_capacity(piece.len() * dof);
        for i in 0..piece.len() {
            positions.extend_from_slice(&base);
            positions.extend_from_slice(&piece.position(i)[EXTRA_AXES..]);
            velocities.extend_from_slice(&[0.0; EXTRA_AXES]);
            velocities.extend_from_slice(&piece.velocity(i)[EXTRA_AXES..]);
        }
        Trajectory::new(
            piece.rig.clone(),
            piece.joint_names.clone(),
            piece.period,
            positions,
            velocities,
        )
    }

    /// Worst body clearance over `trajectory`'s samples (every `stride`-th and the last)
    /// when it is at most `needed`, otherwise some clearance above `needed`.
    fn worst_clearance(&mut self, trajectory: &Trajectory, stride: usize, needed: f64) -> f64 {
        let last = trajectory.len().saturating_sub(1);
        let samples = (0..trajectory.len())
            .step_by(stride.max(1))
            .chain([last])
            .map(|i| trajectory.position(i));
        let (body, scratch) = (&self.body, &mut self.scratch);
        self.travel.lowest(samples, needed, |part, positions| {
            body.part_distance(part, positions, scratch)
        })
    }

    /// How far the brush stays from painting over `trajectory`: for each sample, the
    /// smallest over walls of the farther contact end's distance from that wall's plane
    /// (the brush paints a wall only with both ends near it). Exact when at most `needed`,
    /// otherwise some distance above `needed`.
    fn brush_off_wall(&mut self, trajectory: &Trajectory, needed: f64) -> f64 {
        let samples = (0..trajectory.len()).map(|i| trajectory.position(i));
        let (body, room, scratch) = (&self.body, self.room, &mut self.scratch);
        self.travel_planar.lowest(samples, needed, |positions| {
            // The brush's contact line only: tool0 from the kinematics.
            let tool0 = scratch
                .rig
                .forward_with_axes(positions, &mut scratch.axes)
                .unwrap_or(glam::DAffine3::IDENTITY);
            let ends = body.brush.contact(&tool0);
            room.walls
                .iter()
                .map(|wall| wall.local(ends[0]).2.abs().max(wall.local(ends[1]).2.abs()))
                .fold(f64::INFINITY, f64::min)
        })
    }

    /// The feasible base positions along `wall` at `standoff`: (lowest s, highest s).
    fn base_range(&mut self, wall: &Wall, standoff: f64) -> Option<(f64, f64)> {
        let key = (wall.index, standoff.to_bits());
        if let Some(range) = self.base_ranges.get(&key) {
            return *range;
        }
        let range = self.search_base_range(wall, standoff);
        self.base_ranges.insert(key, range);
        range
    }

    fn search_base_range(&self, wall: &Wall, standoff: f64) -> Option<(f64, f64)> {
        let need = self.body.base_radius() + self.margin();
        let width = self.room.wall_width_m;
        let ok = |s: f64| self.room.clearance(wall.point(s, 0.0, standoff).truncate()) >= need;
        let steps = (width / 0.005) as usize;
        let feasible: Vec<f64> = (0..=steps)
            .map(|k| k as f64 * width / steps as f64)
            .filter(|s| ok(*s))
            .collect();
        Some((*feasible.first()?, *feasible.last()?))
    }

    /// Attitudes to try for a band: turned away from a corner when flush against one, and
    /// turned at least enough to fit a gap narrower than the brush.
    fn attitudes(&self, band: Band, corner: bool) -> Vec<Attitude> {
        let deg = f64::to_radians;
        let thetas = TILTS_DEG;
        let (at, fit, flush) = match band {
            Band::Flush { edge, room, toward } => (edge, room, toward),
            Band::Centred { centre } => (centre, f64::INFINITY, 1.0),
        };
        // Near a corner, lean the handle away from it (positive turns lean toward -s).
        // Elsewhere, the two bands of a narrow gap turn opposite ways, so that each covers
        // the small triangle the other leaves at the floor and the ceiling.
        let width = self.room.wall_width_m;
        let near_corner = at.min(width - at) < NEAR_CORNER_M;
        let toward = match (near_corner, at > width / 2.0) {
            (true, true) => 1.0,
            (true, false) => -1.0,
            (false, _) => -flush,
        };
        let narrowest = if fit < self.brush_width() {
            (fit / self.brush_width()).clamp(0.0, 1.0).acos() * FIT_TURN_MARGIN
        } else {
            0.0
        };
        let is_flush = matches!(band, Band::Flush { .. });
        let turns: &[f64] = if !is_flush && near_corner {
            &CENTRED_TURNS_DEG
        } else if corner || near_corner {
            &[
                0.0,
                8.0,
                14.0,
                20.0,
                27.0,
                35.0,
                40.0,
                45.0,
                50.0,
                MAX_TURN_DEG,
            ]
        } else {
            &[0.0]
        };
        // A band between others must still meet its neighbours when both are turned:
        // width x cos(phi) >= width - overlap.
        let overlap_share = self.settings.config.brush.overlap_m / self.brush_width();
        let meets = |phi: &f64| is_flush || phi.cos() >= 1.0 - overlap_share;
        let mut phis: Vec<f64> = turns
            .iter()
            .map(|p| deg(*p).max(narrowest))
            .filter(meets)
            .collect();
        phis.dedup();
        phis.iter()
            .flat_map(|phi| {
                thetas.iter().map(move |theta| Attitude {
                    phi: toward * phi,
                    theta: deg(*theta),
                })
            })
            .collect()
    }

    /// The band's centre for an attitude.
    fn band_centre(&self, band: Band, attitude: Attitude) -> f64 {
        let half = self.brush_width() * attitude.phi.cos() / 2.0;
        match band {
            Band::Flush { edge, toward, .. } => edge - toward * (self.inset() + half),
            Band::Centred { centre, .. } => centre,
        }
    }

    /// The brush centre's lowest and highest heights on a segment between two edges.
    fn centre_span(&self, attitude: Attitude, segment: (f64, f64)) -> (f64, f64) {
        let rise = self.brush_width() * attitude.phi.sin().abs() / 2.0 + self.inset();
        (segment.0 + rise, segment.1 - rise)
    }

    /// Finds an attitude and a station for a band whose segments lie between `segments`
    /// (wall edges, before insets): the first candidate that plans and clears the walls.
    fn choose(
        &mut self,
        wall: &Wall,
        band: Band,
        corner: bool,
        segments: &[(f64, f64)],
    ) -> Result<Column, PlanRefusal> {
        let strokes = &self.settings.config.strokes;
        let reach = strokes.reach_m;
        let standoffs = STANDOFF_OFFSETS_M.map(|offset| reach + offset);
        let mut last_reason = PlanRefusal::NoCandidate;
        for attitude in self.attitudes(band, corner) {
            let s = self.band_centre(band, attitude);
            for standoff in standoffs {
                let Some((lo, hi)) = self.base_range(wall, standoff) else {
                    last_reason = PlanRefusal::NoBasePosition {
                        standoff_m: standoff,
                    };
                    continue;
                };
                let mut tried: Vec<f64> = Vec::new();
                for shift in [0.0, 0.1, -0.1, 0.2, -0.2, 0.3, -0.3] {
                    let station_s = (s + shift).clamp(lo, hi);
                    if tried.iter().any(|t| (t - station_s).abs() < 1e-9) {
                        continue;
                    }
                    tried.push(station_s);
                    let station = Station {
                        s: station_s,
                        standoff,
                    };
                    let mut column = Column {
                        s,
                        attitude,
                        station,
                        segments: segments
                            .iter()
                            .map(|seg| self.centre_span(attitude, *seg))
                            .filter(|(a, b)| b > a)
                            .collect(),
                        strokes: Vec::new(),
                    };
                    match self.check_column(wall, &column) {
                        Ok(strokes) => {
                            column.strokes = strokes;
                            return Ok(column);
                        }
                        Err(reason) => last_reason = reason,
                    }
                }
            }
        }
        Err(last_reason)
    }

    /// Plans every stroke of a column and checks its clearance (cached per shape).
    fn check_column(
        &mut self,
        wall: &Wall,
        column: &Column,
    ) -> Result<Vec<Trajectory>, PlanRefusal> {
        let mut strokes = Vec::with_capacity(column.segments.len());
        for segment in &column.segments {
            let stroke = self.stroke(wall, column, *segment)?;
            let clearance = self.worst_clearance(&stroke, 4, self.margin());
            if clearance < self.margin() {
                return Err(PlanRefusal::BodyTooClose {
                    clearance_m: clearance,
                    needed_m: self.margin(),
                });
            }
            strokes.push(stroke);
        }
        Ok(strokes)
    }

    /// One upward stroke: approach along the normal, paint (arm from the floor, then the
    /// lift), retract along the normal. Rest to rest.
    fn stroke(
        &mut self,
        wall: &Wall,
        column: &Column,
        (from, to): (f64, f64),
    ) -> Result<Trajectory, PlanRefusal> {
        let strokes = &self.settings.config.strokes;
        let (hold, low_lift, retract) =
            (strokes.hold_height_m, strokes.low_lift_m, strokes.retract_m);
        let lateral = column.s - column.station.s;
        let (station, attitude) = (column.station, column.attitude);
        let from_floor = from - hold < low_lift;
        let (lift_from, arm_top) = if from_floor {
            (low_lift, (to - low_lift).min(hold))
        } else {
            (from - hold, hold)
        };
        let lift_to = (to - arm_top).max(lift_from);
        let mut path = vec![(retract, from - lift_from), (0.0, from - lift_from)];
        if from_floor && arm_top > from - lift_from {
            path.push((0.0, arm_top));
        }
        let approach = self
            .piece(station, attitude, lateral, &path, None)
            .ok_or(PlanRefusal::CannotPaint { height_m: arm_top })?;
        let held_arm = approach.position(approach.len() - 1)[EXTRA_AXES..].to_vec();
        let retreat = self
            .piece(
                station,
                attitude,
                lateral,
                &[(0.0, arm_top), (retract, arm_top)],
                Some(&held_arm),
            )
            .ok_or(PlanRefusal::CannotRetract { height_m: arm_top })?;
        let mut trajectory = self.placed(&approach, wall, station, lift_from)?;
        let held = trajectory.position(trajectory.len() - 1).to_vec();
        if lift_to > lift_from {
            let mut top = held.clone();
            top[LIFT_AXIS] = lift_to;
            let lift = plan_joint_moves(self.rig, &held, &[top], &self.plan)?;
            trajectory.append(&lift);
        }
        let retreat = self.placed(&retreat, wall, station, lift_to)?;
        trajectory.append(&retreat);
        Ok(trajectory)
    }

    /// Columns of one wall, from its right end to its left end.
    fn columns(&mut self, wall: &Wall, unreachable: &mut Vec<UnreachableStroke>) -> Vec<Column> {
        let width = self.room.wall_width_m;
        let height = self.room.wall_height_m;
        let mut edges: Vec<f64> = vec![0.0, width];
        for o in &wall.openings {
            edges.extend([o.left_m, o.right_m]);
        }
        edges.sort_by(f64::total_cmp);
        edges.dedup_by(|a, b| (*a - *b).abs() < 1e-9);
        let mut columns = Vec::new();
        for pair in edges.windows(2).rev() {
            let (a, e) = (pair[0], pair[1]);
            let middle = (a + e) / 2.0;
            let segments = self.segments(wall, middle, height);
            if segments.is_empty() {
                continue;
            }
            // The two bands flush with the interval's edges first: how far they reach
            // (turned bands are narrower) decides the bands between them.
            let (x0, x1) = (a + self.inset(), e - self.inset());
            let [right, left] = self.flush_bands(a, e, width);
            let right = self.place(wall, right, &segments, unreachable);
            let left = self.place(wall, left, &segments, unreachable);
            let reach = |column: &Option<Column>| {
                column
                    .as_ref()
                    .map_or(0.0, |c| self.brush_width() * c.attitude.phi.cos())
            };
            let middle: Vec<(Band, bool)> = self
                .middle_centres(x0 + reach(&left), x1 - reach(&right), (x0, x1))
                .into_iter()
                .rev()
                .map(|centre| (Band::Centred { centre }, false))
                .collect();
            columns.extend(right);
            for band in middle {
                columns.extend(self.place(wall, band, &segments, unreachable));
            }
            columns.extend(left);
        }
        columns
    }

    /// Paintable vertical segments (edges, before insets) of a column at `s`.
    fn segments(&self, wall: &Wall, s: f64, height: f64) -> Vec<(f64, f64)> {
        let mut cuts: Vec<(f64, f64)> = wall
            .openings
            .iter()
            .filter(|o| s > o.left_m && s < o.right_m)
            .map(|o| (o.bottom_m, o.top_m))
            .collect();
        cuts.sort_by(|x, y| x.0.total_cmp(&y.0));
        let mut segments = Vec::new();
        let mut at = 0.0;
        for (bottom, top) in cuts {
            if bottom > at {
                segments.push((at, bottom));
            }
            at = at.max(top);
        }
        if height > at {
            segments.push((at, height));
        }
        segments
    }

    /// Chooses an attitude and station for `band`, or records it as unreachable.
    fn place(
        &mut self,
        wall: &Wall,
        (band, corner): (Band, bool),
        segments: &[(f64, f64)],
        unreachable: &mut Vec<UnreachableStroke>,
    ) -> Option<Column> {
        match self.choose(wall, band, corner, segments) {
            Ok(column) => Some(column),
            Err(reason) => {
                let level = Attitude {
                    phi: 0.0,
                    theta: 0.0,
                };
                unreachable.push(UnreachableStroke {
                    wall: wall.index,
                    s_m: self.band_centre(band, level),
                    v_from_m: segments[0].0,
                    v_to_m: segments[segments.len() - 1].1,
                    reason: reason.to_string(),
                });
                None
            }
        }
    }

    /// The bands flush with the right and left edges of the interval [a, e] (each flagged
    /// when its edge is a corner of the room).
    fn flush_bands(&self, a: f64, e: f64, width: f64) -> [(Band, bool); 2] {
        let span = e - a - 2.0 * self.inset();
        [
            (
                Band::Flush {
                    edge: e,
                    toward: 1.0,
                    room: span,
                },
                e >= width - 1e-9,
            ),
            (
                Band::Flush {
                    edge: a,
                    toward: -1.0,
                    room: span,
                },
                a <= 1e-9,
            ),
        ]
    }

    /// Centres of the bands that cover [from, to] (what the flush bands left), one brush
    /// width minus the overlap apart at most, overlapping the flush bands by the overlap,
    /// each inside the interval `within`.
    fn middle_centres(&self, from: f64, to: f64, within: (f64, f64)) -> Vec<f64> {
        let b = self.brush_width();
        let overlap = self.settings.config.brush.overlap_m;
        let (m0, m1) = (from - overlap, to + overlap);
        // Nothing left between the flush bands, or no room for a level band (a gap
        // narrower than the brush only takes the two turned flush bands).
        if m1 <= m0 + 2.0 * overlap || within.1 - within.0 < b {
            return Vec::new();
        }
        let (lo, hi) = (
            (m0 + b / 2.0).max(within.0 + b / 2.0),
            (m1 - b / 2.0).min(within.1 - b / 2.0),
        );
        if hi <= lo {
            return vec![((m0 + m1) / 2.0).clamp(within.0 + b / 2.0, within.1 - b / 2.0)];
        }
        let count = ((hi - lo) / (b - overlap)).ceil() as usize + 1;
        (0..count)
            .map(|k| lo + (hi - lo) * k as f64 / (count - 1) as f64)
            .collect()
    }

    /// A rest-to-rest move from `from` to `to` that keeps the body clear of the walls and
    /// the brush off them: straight when both ends share the arm's pose, otherwise backing
    /// the base off, moving with the arm in its travel pose, and coming back in.
    fn free_move(
        &mut self,
        from: &[f64],
        to: &[f64],
        walls: (usize, usize),
    ) -> Result<Trajectory, PaintPlanError> {
        let same_arm = from[EXTRA_AXES..]
            .iter()
            .zip(&to[EXTRA_AXES..])
            .all(|(a, b)| (a - b).abs() < 1e-6)
            && (from[2] - to[2]).abs() < 1e-9;
        let mut tries = RouteTries::default();
        if same_arm {
            match self.try_route(from, to, &[]) {
                Ok(direct) => return Ok(direct),
                Err(why) => tries.0.push((RouteTry::Direct, why)),
            }
        }
        for backoff in BACKOFFS {
            let out_from = self.backed_off(from, backoff);
            let out_to = self.backed_off(to, backoff);
            let mut travel_from = out_from.clone();
            travel_from[EXTRA_AXES..].copy_from_slice(&self.travel_arm);
            let mut travel_to = out_to.clone();
            travel_to[EXTRA_AXES..].copy_from_slice(&self.travel_arm);
            let via = [out_from, travel_from, travel_to, out_to];
            match self.try_route(from, to, &via) {
                Ok(route) => return Ok(route),
                Err(why) => tries.0.push((
                    RouteTry::BackingOff {
                        distance_m: backoff,
                    },
                    why,
                )),
            }
            // Through the room's centre, where the arm turns freely.
            let mut centre_from = via[1].clone();
            centre_from[..2].copy_from_slice(&[0.0, 0.0]);
            let mut centre_to = via[2].clone();
            centre_to[..2].copy_from_slice(&[0.0, 0.0]);
            let via = [
                via[0].clone(),
                via[1].clone(),
                centre_from,
                centre_to,
                via[2].clone(),
                via[3].clone(),
            ];
            match self.try_route(from, to, &via) {
                Ok(route) => return Ok(route),
                Err(why) => tries.0.push((RouteTry::ViaCentre, why)),
            }
        }
        Err(PaintPlanError::NoRoute {
            from_wall: walls.0,
            to_wall: walls.1,
            from: JointList(from.to_vec()),
            to: JointList(to.to_vec()),
            tries,
        })
    }

    /// `joints` with the base moved `distance` toward the room's centre (at most onto it):
    /// away from every wall it is near, the brush leaving the wall it faces.
    fn backed_off(&self, joints: &[f64], distance: f64) -> Vec<f64> {
        let base = DVec2::new(joints[0], joints[1]);
        let moved = base - base.clamp_length_max(distance);
        let mut out = joints.to_vec();
        out[0] = moved.x;
        out[1] = moved.y;
        out
    }

    fn try_route(
        &mut self,
        from: &[f64],
        to: &[f64],
        via: &[Vec<f64>],
    ) -> Result<Trajectory, PlanRefusal> {
        let mut waypoints: Vec<Vec<f64>> = via.to_vec();
        waypoints.push(to.to_vec());
        waypoints.dedup_by(|a, b| a == b);
        let route = plan_joint_moves(self.rig, from, &waypoints, &self.plan)?;
        let clearance = self.worst_clearance(&route, 2, 0.0);
        if clearance < 0.0 {
            return Err(PlanRefusal::RouteCollides {
                clearance_m: clearance,
            });
        }
        let needed = FREE_MOVE_OFF_WALL * self.settings.config.brush.contact_tolerance_m;
        let off_wall = self.brush_off_wall(&route, needed);
        if off_wall <= needed {
            return Err(PlanRefusal::BrushNearWall {
                off_m: off_wall,
                needed_m: needed,
            });
        }
        Ok(route)
    }

    /// The whole job from `start` back to `start`. Walls are planned side by side on the
    /// planner's threads (each wall's strokes depend only on the wall and the shape cache),
    /// then the free moves between strokes (each depends only on its two ends), then the
    /// check of every sample; the pieces are put together in order, as one thread would.
    pub fn plan(mut self, start: &[f64]) -> Result<PaintPlan, PaintPlanError> {
        if start.len() != self.rig.dof() {
            return Err(PaintPlanError::BadStart {
                start: JointList(start.to_vec()),
                dof: self.rig.dof(),
            });
        }
        let mut trajectory = plan_joint_moves(self.rig, start, &[], &self.plan)?;
        let mut helpers = (1..self.threads.get())
            .map(|_| Planner::new(self.settings, self.room, self.plan))
            .collect::<Result<Vec<_>, _>>()?;
        let walls = self.all_wall_strokes(&mut helpers);
        let mut legs = Vec::new();
        let mut unreachable = Vec::new();
        for wall in walls {
            let wall = wall?;
            legs.extend(wall.legs);
            unreachable.extend(wall.unreachable);
        }
        let requests = route_requests(start, &legs);
        let mut routes = self
            .share(&mut helpers, requests.len(), |planner, i| {
                let request = &requests[i];
                planner.free_move(&request.from, &request.to, request.walls)
            })
            .into_iter();
        let mut strokes = Vec::with_capacity(legs.len());
        for (leg, route) in legs.into_iter().zip(routes.by_ref()) {
            trajectory.append(&route?);
            let first_sample = trajectory.len() - 1;
            trajectory.append(&leg.stroke);
            strokes.push(PlannedStroke {
                samples: [first_sample, trajectory.len() - 1],
                ..leg.record
            });
        }
        for home in routes {
            trajectory.append(&home?);
        }
        validate(&trajectory, self.rig)?;
        self.check_all(&mut helpers, &trajectory)?;
        Ok(PaintPlan {
            trajectory,
            strokes,
            unreachable,
        })
    }

    /// Every wall's strokes, planned on this planner and `helpers`, each taking the next
    /// wall in turn. Each keeps its own cache of arm moves, so the arm move for a shape
    /// may be computed by more than one of them: when all agree bit for bit, every wall got
    /// what one planner taking the walls in order would have given it (the move cached
    /// for a shape is the one its first request computes). Otherwise (moves whose inputs
    /// differ below the cache key's resolution, planned differently) the walls are planned
    /// again in order on this planner alone.
    fn all_wall_strokes(
        &mut self,
        helpers: &mut [Planner<'a>],
    ) -> Vec<Result<WallStrokes, TrajectoryError>> {
        let room = self.room;
        let walls = self.share(helpers, room.walls.len(), |planner, i| {
            planner.wall_strokes(&room.walls[i])
        });
        let caches: Vec<_> = std::iter::once(&self.pieces)
            .chain(helpers.iter().map(|helper| &helper.pieces))
            .collect();
        if caches_agree(&caches) {
            return walls;
        }
        self.pieces.clear();
        self.share(&mut [], room.walls.len(), |planner, i| {
            planner.wall_strokes(&room.walls[i])
        })
    }

    /// One wall's strokes in painting order: its columns from right to left, every other
    /// one downward (the same stroke reversed in time).
    fn wall_strokes(&mut self, wall: &Wall) -> Result<WallStrokes, TrajectoryError> {
        let mut unreachable = Vec::new();
        let columns = self.columns(wall, &mut unreachable);
        let mut legs = Vec::new();
        for (k, column) in columns.into_iter().enumerate() {
            let downward = k % 2 == 1;
            let mut order: Vec<_> = column.segments.iter().zip(column.strokes).collect();
            if downward {
                order.reverse();
            }
            for (&(bottom, top), stroke) in order {
                let (stroke, v_from_m, v_to_m) = if downward {
                    (reversed(&stroke)?, top, bottom)
                } else {
                    (stroke, bottom, top)
                };
                legs.push(Leg {
                    stroke,
                    record: PlannedStroke {
                        wall: wall.index,
                        s_m: column.s,
                        v_from_m,
                        v_to_m,
                        turn_deg: column.attitude.phi.to_degrees(),
                        tilt_deg: column.attitude.theta.to_degrees(),
                        samples: [0, 0],
                    },
                });
            }
        }
        Ok(WallStrokes { legs, unreachable })
    }

    /// Runs `job(planner, item)` for every item in `0..count` on this planner and
    /// `helpers` (one thread each), each taking the next item in turn, so every planner
    /// sees its items in increasing order. Results come back in item order. With no
    /// helpers it is a plain loop on this thread.
    fn share<T: Send>(
        &mut self,
        helpers: &mut [Planner<'a>],
        count: usize,
        job: impl Fn(&mut Planner<'a>, usize) -> T + Sync,
    ) -> Vec<T> {
        let next = AtomicUsize::new(0);
        let work = &|planner: &mut Planner<'a>| {
            let mut done = Vec::new();
            loop {
                let item = next.fetch_add(1, Ordering::Relaxed);
                if item >= count {
                    return done;
                }
                done.push((item, job(planner, item)));
            }
        };
        let mut results = std::thread::scope(|scope| {
            let running: Vec<_> = helpers
                .iter_mut()
                .map(|helper| scope.spawn(move || work(helper)))
                .collect();
            let mut results = work(self);
            for thread in running {
                match thread.join() {
                    Ok(done) => results.extend(done),
                    Err(panic) => std::panic::resume_unwind(panic),
                }
            }
            results
        });
        results.sort_unstable_by_key(|(item, _)| *item);
        results.into_iter().map(|(_, result)| result).collect()
    }

    /// Every sample of the plan clears the walls: nothing moves otherwise. The samples are
    /// cut into one run per planner; the first collision in time is the one reported.
    fn check_all(
        &mut self,
        helpers: &mut [Planner<'a>],
        trajectory: &Trajectory,
    ) -> Result<(), PaintPlanError> {
        let runs = helpers.len() + 1;
        let run_length = trajectory.len().div_ceil(runs);
        let first_collisions = self.share(helpers, runs, |planner, run| {
            let samples = (run * run_length..((run + 1) * run_length).min(trajectory.len()))
                .map(|sample| (sample, trajectory.position(sample)));
            let (body, scratch) = (&planner.body, &mut planner.scratch);
            planner
                .travel
                .first_below(samples, 0.0, |part, positions| {
                    body.part_distance(part, positions, scratch)
                })
                .map(|(sample, clearance_m)| PaintPlanError::Collides {
                    sample,
                    clearance_m,
                })
        });
        match first_collisions.into_iter().flatten().next() {
            Some(collision) => Err(collision),
            None => Ok(()),
        }
    }
}

/// The free moves of a plan: from `start` to the first stroke, between consecutive
/// strokes, and from the last stroke back to `start`.
fn route_requests(start: &[f64], legs: &[Leg]) -> Vec<RouteRequest> {
    let mut requests = Vec::with_capacity(legs.len() + 1);
    let mut at = start.to_vec();
    let mut at_wall = 0;
    for leg in legs {
        requests.push(RouteRequest {
            from: at.to_vec(),
            to: leg.stroke.position(0).to_vec(),
            walls: (at_wall, leg.record.wall),
        });
        at = leg.stroke.position(leg.stroke.len() - 1).to_vec();
        at_wall = leg.record.wall;
    }
    requests.push(RouteRequest {
        from: at.to_vec(),
        to: start.to_vec(),
        walls: (at_wall, 0),
    });
    requests
}

/// True when every shape cached by more than one planner has the same arm move (or the
/// same refusal) in each, bit for bit.
fn caches_agree(caches: &[&HashMap<PieceKey, Option<Trajectory>>]) -> bool {
    caches.iter().enumerate().all(|(i, cache)| {
        caches[i + 1..].iter().all(|other| {
            cache.iter().all(|(key, piece)| {
                other
                    .get(key)
                    .is_none_or(|theirs| same_piece(piece.as_ref(), theirs.as_ref()))
            })
        })
    })
}

fn same_piece(a: Option<&Trajectory>, b: Option<&Trajectory>) -> bool {
    match (a, b) {
        (None, None) => true,
        (Some(a), Some(b)) => same_bits(a, b),
        _ => false,
    }
}

/// Two trajectories equal bit for bit (`==` on floats would take -0.0 for 0.0).
fn same_bits(a: &Trajectory, b: &Trajectory) -> bool {
    let same = |x: &[f64], y: &[f64]| x.iter().zip(y).all(|(x, y)| x.to_bits() == y.to_bits());
    a.rig == b.rig
        && a.joint_names == b.joint_names
        && a.period == b.period
        && a.len() == b.len()
        && a.dof() == b.dof()
        && (0..a.len())
            .all(|i| same(&a.position(i), &b.position(i)) && same(&a.velocity(i), &b.velocity(i)))
}

/// The same motion backwards in time (positions in reverse order, velocities negated).
fn reversed(trajectory: &Trajectory) -> Result<Trajectory, TrajectoryError> {
    let dof = trajectory.dof();
    let mut positions = Vec::with_capacity(trajectory.len() * dof);
    let mut velocities = Vec::with_capacity(trajectory.len() * dof);
    for i in (0..trajectory.len()).rev() {
        let (at, moving) = trajectory.sample(i);
        positions.extend_from_slice(&at);
        velocities.extend(moving.iter().map(|v| -v));
    }
    Trajectory::new(
        trajectory.rig.clone(),
        trajectory.joint_names.clone(),
        trajectory.period,
        positions,
        velocities,
    )
}

/// Plans the whole painting job for `room` from `start`.
pub fn plan_paint(
    settings: &PaintSettings,
    room: &Room,
    start: &[f64],
    plan: &PlanSettings,
) -> Result<PaintPlan, PaintPlanError> {
    Planner::new(settings, room, *plan)?.plan(start)
}
