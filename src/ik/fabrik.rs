//! The planner's solver: FABRIK for the full 6-DOF tool pose of a six-axis arm whose first
//! three axes place a spherical wrist (the IRB 120 and most industrial arms).
//!
//! The wrist centre is found from the target pose. Axis 1 turns the arm's plane toward it;
//! in that plane FABRIK solves the two-segment chain shoulder -> elbow -> wrist centre with
//! axes 2 and 3 enforced as hinge limits on every reaching pass; the wrist's three angles
//! then follow exactly. Every branch is tried (axis 1 front and back, elbow up and down,
//! wrist flip, the extra turns of axes 4 and 6) and the one nearest the seed in time, at
//! the axes' max speeds, is returned. It must not touch the rig, and never returns a value
//! outside a limit: a rounding hair past a limit is snapped onto it, anything more is an error.

use super::chain::{ChainSettings, JointConstraint, fabrik};
use super::wrist::SphericalWrist;
use super::{IkError, IkSolution, IkSolver, Tolerance, verified};
use crate::rig::{DofMismatch, JointKind, JointList, Pose, Rig};
use glam::{DAffine3, DMat3, DQuat, DVec3};
use std::cell::Cell;
use std::f64::consts::{PI, TAU};
use thiserror::Error;

/// A joint value within this of a limit (rad) counts as on the limit: it is rounding noise
/// from atan2, far below any tolerance, and the final FK check still applies.
const LIMIT_SNAP: f64 = 1e-9;
/// Wrist centres closer than this to axis 1 leave axis 1 free: the seed's value is kept.
const ON_AXIS_1: f64 = 1e-9;
const GEOMETRY_TOLERANCE: f64 = 1e-9;
/// FABRIK's own stopping distance (m) and iteration budget. Near full stretch its linear
/// convergence slows to thousands of iterations per digit. So unless a hinge limit holds
/// the chain (it stalls farther than [`CLOSING_DISTANCE`] from the target), the exact
/// triangle on FABRIK's elbow side finishes the job, and the limits are checked on that.
const FABRIK_TOLERANCE: f64 = 3e-3;
const FABRIK_MAX_ITERATIONS: u32 = 32;
const CLOSING_DISTANCE: f64 = 1e-3;

#[derive(Debug, Clone, PartialEq, Error)]
#[error("rig {rig} does not suit the FABRIK arm planner: {reason}")]
pub struct StructureError {
    pub rig: String,
    pub reason: StructureProblem,
}

/// What about a rig's structure the FABRIK arm planner cannot work with.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum StructureProblem {
    #[error("needs 6 revolute joints, has {0} joints")]
    NotSixRevolute(usize),
    #[error("holding {held} of {dof} axes leaves no arm")]
    NoArmLeft { held: usize, dof: usize },
    #[error("axis 2 must be perpendicular to axis 1")]
    ShoulderNotPerpendicular,
    #[error("axes 2 and 3 must be parallel")]
    ElbowNotParallel,
    #[error("axes 4 and 5 must intersect")]
    WristAxesMiss,
    #[error("axis {axis} misses the wrist centre by {off_m} m")]
    OffWristCentre { axis: usize, off_m: f64 },
    #[error("{0} lies off the plane of axis 1 (lateral offset)")]
    OffPlane(&'static str),
    #[error("axes 4 and 6 must be parallel and axis 5 perpendicular to them")]
    WristNotSpherical,
    #[error("{0}")]
    Dof(#[from] DofMismatch),
    #[error("self-check failed at {joints}: {source}")]
    SelfCheck { joints: JointList, source: IkError },
}

/// Plane coordinates: x along the arm's reach (away from axis 1), z along axis 1.
fn plane_angle(direction: DVec3) -> f64 {
    direction.x.atan2(direction.z)
}

fn plane_direction(angle: f64) -> DVec3 {
    let (sin, cos) = angle.sin_cos();
    DVec3::new(sin, 0.0, cos)
}

fn wrap(angle: f64) -> f64 {
    let wrapped = (angle + PI).rem_euclid(TAU) - PI;
    if wrapped == -PI { PI } else { wrapped }
}

/// A direction in the arm's plane as the unit complex number cos a + i sin a of its plane
/// angle: relative angles and rotations become products, with no trigonometry in the loop.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Turn {
    cos: f64,
    sin: f64,
}

impl Turn {
    fn of_angle(angle: f64) -> Self {
        let (sin, cos) = angle.sin_cos();
        Self { cos, sin }
    }

    fn of_direction(direction: DVec3) -> Self {
        Self {
            cos: direction.z,
            sin: direction.x,
        }
    }

    fn direction(self) -> DVec3 {
        DVec3::new(self.sin, 0.0, self.cos)
    }

    fn then(self, other: Turn) -> Turn {
        Turn {
            cos: self.cos * other.cos - self.sin * other.sin,
            sin: self.sin * other.cos + self.cos * other.sin,
        }
    }

    fn inverse(self) -> Turn {
        Turn {
            cos: self.cos,
            sin: -self.sin,
        }
    }
}

/// Allowed relative angles of a hinge in the arm's plane: a window of half-width at most
/// pi around a centre.
#[derive(Debug, Clone, Copy, PartialEq)]
struct HingeWindow {
    centre: Turn,
    cos_half_width: f64,
    lower_edge: Turn,
    upper_edge: Turn,
}

impl HingeWindow {
    fn new(centre: f64, half_width: f64) -> Self {
        Self {
            centre: Turn::of_angle(centre),
            cos_half_width: half_width.cos(),
            lower_edge: Turn::of_angle(centre - half_width),
            upper_edge: Turn::of_angle(centre + half_width),
        }
    }

    /// The nearer edge of the window when `relative` lies outside it; `None` inside.
    fn clamp(&self, relative: Turn) -> Option<Turn> {
        let offset = relative.then(self.centre.inverse());
        (offset.cos < self.cos_half_width).then_some(if offset.sin >= 0.0 {
            self.upper_edge
        } else {
            self.lower_edge
        })
    }
}

/// Axes 2 and 3 as hinge constraints in the arm's plane; remembers which one last held.
struct ArmHinges {
    windows: [HingeWindow; 2],
    last_clamped: Cell<Option<usize>>,
}

impl JointConstraint for ArmHinges {
    fn clamp_child(&self, joint: usize, parent: DVec3, child: DVec3) -> DVec3 {
        let parent = Turn::of_direction(parent);
        let relative = Turn::of_direction(child).then(parent.inverse());
        match self.windows[joint].clamp(relative) {
            Some(edge) => {
                self.last_clamped.set(Some(joint));
                parent.then(edge).direction()
            }
            None => child,
        }
    }

    fn clamp_parent(&self, joint: usize, parent: DVec3, child: DVec3) -> DVec3 {
        let child_turn = Turn::of_direction(child);
        let relative = child_turn.then(Turn::of_direction(parent).inverse());
        match self.windows[joint].clamp(relative) {
            Some(edge) => {
                self.last_clamped.set(Some(joint));
                child_turn.then(edge.inverse()).direction()
            }
            None => parent,
        }
    }
}

/// The arm's geometry, read once from the rig.
#[derive(Debug, Clone, PartialEq)]
struct ArmGeometry {
    /// From the rig's base frame into joint 1's origin frame; everything below is in it.
    to_base: DAffine3,
    up: DVec3,
    reach: DVec3,
    side: DVec3,
    /// Axis 2 in plane coordinates (x, 0, z).
    shoulder: DVec3,
    upper_arm: f64,
    forearm: f64,
    /// Plane angle of shoulder -> elbow at q2 = 0.
    upper_arm_angle: f64,
    /// Relative plane angle elbow -> wrist centre at q3 = 0.
    elbow_angle: f64,
    /// +1 when axis 3 turns like axis 2, -1 when opposite.
    elbow_sign: f64,
    /// Wrist centre -> tool origin, in the tool frame.
    tool_offset: DVec3,
}

pub struct FabrikSolver {
    rig: Rig,
    arm: ArmGeometry,
    wrist: SphericalWrist,
    windows: [HingeWindow; 2],
    tolerance: Tolerance,
    chain: ChainSettings,
}

/// One candidate answer, before the FK check.
#[derive(Debug, Clone, Copy)]
struct Candidate {
    joints: [f64; 6],
    cost: f64,
    iterations: u32,
    rank: Rank,
}

/// A branch's place in the planner's enumeration order: axis 1 turn (k = -2..=2), elbow
/// side (the seed's first), wrist branch, axis 4 turn, axis 6 turn. Among equal costs the
/// first in this order wins, and the first refusal in it is the one reported, whatever
/// order the branches are searched in.
type Rank = [u8; 5];

/// The search over branches: the best candidate so far and the first refusal, by rank.
#[derive(Default)]
struct Search {
    best: Option<Candidate>,
    blocked: Option<(Rank, usize)>,
}

impl Search {
    /// False when every candidate costing at least `bound` loses to the best so far: the
    /// cost is a sum of squares, so a branch whose first axes already cost more than the
    /// best need not be solved further.
    fn open(&self, bound: f64) -> bool {
        self.best.is_none_or(|best| bound <= best.cost)
    }

    fn offer(&mut self, candidate: Candidate) {
        if self
            .best
            .is_none_or(|best| (candidate.cost, candidate.rank) < (best.cost, best.rank))
        {
            self.best = Some(candidate);
        }
    }

    /// Records that the branch at `rank` is refused because of `axis` (0-based).
    fn block(&mut self, rank: Rank, axis: usize) {
        if self.blocked.is_none_or(|(first, _)| rank < first) {
            self.blocked = Some((rank, axis));
        }
    }
}

/// One in-limit value of axis 1 for the wrist centre's heading.
#[derive(Debug, Clone, Copy)]
struct Axis1Turn {
    /// Its k in `heading + k pi`, shifted to 0..=4 (its rank).
    rank: u8,
    q1: f64,
    /// Its own share of the cost: a lower bound on every candidate through it.
    cost: f64,
}

/// One axis-1 branch's problem in the arm's plane.
#[derive(Debug, Clone, Copy)]
struct PlaneTarget {
    /// The wrist centre, plane coordinates.
    target: DVec3,
    /// Unit direction and plane angle of the shoulder -> target line.
    line: DVec3,
    line_angle: f64,
    /// Angle between that line and the upper arm when the wrist centre is on the target.
    opening: f64,
    /// Axes 2 and 3 with the elbow exactly closed on side -1 and +1 of the line.
    closed: [Result<[f64; 2], usize>; 2],
}

/// Axes 2 and 3 from one FABRIK run, the index in `PlaneTarget::closed` of the exact elbow
/// it closed on, and its iterations.
type Closed = ([f64; 2], usize, u32);

/// Values `heading + k pi` for k in -2..=2 (front, back, and their full turns).
const AXIS_1_TURNS: i32 = 2;

impl FabrikSolver {
    pub fn new(rig: Rig) -> Result<Self, StructureError> {
        Self::with_tolerance(rig, Tolerance::default())
    }

    pub fn with_tolerance(rig: Rig, tolerance: Tolerance) -> Result<Self, StructureError> {
        let rig_name = rig.name.clone();
        let fail = |reason: StructureProblem| StructureError {
            rig: rig_name.clone(),
            reason,
        };
        if rig.dof() != 6 || rig.joints.iter().any(|j| j.kind != JointKind::Revolute) {
            return Err(fail(StructureProblem::NotSixRevolute(rig.dof())));
        }
        let arm = ArmGeometry::read(&rig).map_err(&fail)?;
        let rotation = |t: &DAffine3| t.matrix3;
        let wrist = SphericalWrist::new(
            [3, 4, 5].map(|i| rotation(&rig.joints[i].origin)),
            [3, 4, 5].map(|i| rig.joints[i].axis),
            rotation(&rig.tool),
        )
        .ok_or_else(|| fail(StructureProblem::WristNotSpherical))?;
        let window = |index: usize, zero_angle: f64, sign: f64| {
            let limits = rig.joints[index].limits;
            HingeWindow::new(
                zero_angle + sign * (limits.lower + limits.upper) / 2.0,
                ((limits.upper - limits.lower) / 2.0).min(PI),
            )
        };
        let windows = [
            window(1, arm.upper_arm_angle, 1.0),
            window(2, arm.elbow_angle, arm.elbow_sign),
        ];
        let solver = Self {
            windows,
            arm,
            wrist,
            tolerance,
            chain: ChainSettings {
                tolerance: FABRIK_TOLERANCE,
                max_iterations: FABRIK_MAX_ITERATIONS,
                min_improvement: 1e-9,
            },
            rig,
        };
        solver.self_check().map_err(fail)?;
        Ok(solver)
    }

    /// Round-trips a spread of in-limit configurations: a rig whose structure was misread
    /// (say, a wrist whose axes only nearly meet) fails here rather than in use.
    fn self_check(&self) -> Result<(), StructureProblem> {
        for step in 1..=24 {
            let joints: Vec<f64> = self
                .rig
                .joints
                .iter()
                .enumerate()
                .map(|(i, j)| {
                    let fraction = ((step * (i + 3) * 7919) % 97) as f64 / 97.0;
                    j.limits.lower + (j.limits.upper - j.limits.lower) * (0.05 + 0.9 * fraction)
                })
                .collect();
            let pose = self.rig.tool_pose(&joints)?;
            self.solve(&pose, &joints)
                .map_err(|source| StructureProblem::SelfCheck {
                    joints: JointList(joints.clone()),
                    source,
                })?;
        }
        Ok(())
    }

    fn limit(&self, axis: usize) -> (f64, f64) {
        let limits = self.rig.joints[axis].limits;
        (limits.lower, limits.upper)
    }

    /// `value` or a rounding hair away from it snapped onto a limit; `None` when outside.
    fn within(&self, axis: usize, value: f64) -> Option<f64> {
        let (lower, upper) = self.limit(axis);
        if value < lower {
            (value > lower - LIMIT_SNAP).then_some(lower)
        } else if value > upper {
            (value < upper + LIMIT_SNAP).then_some(upper)
        } else {
            Some(value)
        }
    }

    /// Every in-limit value `value + k * 2pi` of an axis (at most a few).
    fn turns(&self, axis: usize, value: f64) -> impl Iterator<Item = f64> + '_ {
        let (lower, upper) = self.limit(axis);
        let first = ((lower - LIMIT_SNAP - value) / TAU).ceil() as i64;
        let last = ((upper + LIMIT_SNAP - value) / TAU).floor() as i64;
        (first..=last).filter_map(move |k| self.within(axis, value + k as f64 * TAU))
    }

    /// Time-weighted distance from the seed over the first `joints.len()` axes.
    fn cost(&self, joints: &[f64], seed: &[f64]) -> f64 {
        joints
            .iter()
            .zip(seed)
            .zip(&self.rig.joints)
            .map(|((q, s), j)| ((q - s) / j.limits.max_speed).powi(2))
            .sum()
    }

    /// The wrist centre `target` (plane coordinates) for one axis-1 branch, with axes 2
    /// and 3 worked out exactly for the elbow on either side of the shoulder -> target
    /// line: whatever FABRIK's path, it closes on one of these two.
    fn plane_target(&self, target: DVec3) -> PlaneTarget {
        let arm = &self.arm;
        let to_target = target - arm.shoulder;
        let distance = to_target.length();
        let cosine = (arm.upper_arm * arm.upper_arm + distance * distance
            - arm.forearm * arm.forearm)
            / (2.0 * arm.upper_arm * distance);
        let opening = cosine.clamp(-1.0, 1.0).acos();
        let line_angle = plane_angle(to_target);
        let mut plane = PlaneTarget {
            target,
            line: to_target.normalize_or(DVec3::Z),
            line_angle,
            opening,
            closed: [Err(1); 2],
        };
        plane.closed = [-1.0, 1.0].map(|side| self.close_triangle(&plane, side));
        plane
    }

    /// Axes 2 and 3 that put the wrist centre exactly on the target with the elbow on
    /// `side` (-1 or +1) of the shoulder -> target line (law of cosines); Err names the
    /// axis whose limit refuses them.
    fn close_triangle(&self, plane: &PlaneTarget, side: f64) -> Result<[f64; 2], usize> {
        let arm = &self.arm;
        let elbow =
            arm.shoulder + arm.upper_arm * plane_direction(plane.line_angle + side * plane.opening);
        let upper = plane_angle(elbow - arm.shoulder);
        let fore = plane_angle(plane.target - elbow);
        let (lower2, upper2) = self.limit(1);
        let (lower3, upper3) = self.limit(2);
        let middle2 = (lower2 + upper2) / 2.0;
        let middle3 = (lower3 + upper3) / 2.0;
        let q2 = middle2 + wrap(upper - arm.upper_arm_angle - middle2);
        let q3 = middle3
            + arm.elbow_sign * wrap(fore - upper - arm.elbow_angle - arm.elbow_sign * middle3);
        let q2 = self.within(1, q2).ok_or(1usize)?;
        let q3 = self.within(2, q3).ok_or(2usize)?;
        Ok([q2, q3])
    }

    /// FABRIK toward the wrist centre at `plane`, starting from `elbow`: axes 2 and 3, which
    /// of the two exact elbows (`plane.closed`) it closes on, and its iterations.
    /// FABRIK stops short of the target ([`FABRIK_TOLERANCE`]); the exact triangle on its
    /// elbow's side finishes. Err carries the index of the axis that held the chain back.
    fn solve_plane(&self, plane: &PlaneTarget, elbow: DVec3) -> Result<Closed, usize> {
        let arm = &self.arm;
        let hinges = ArmHinges {
            windows: self.windows,
            last_clamped: Cell::new(None),
        };
        let target = plane.target;
        let wrist = elbow + arm.forearm * (target - elbow).normalize_or(DVec3::Z);
        let mut points = [arm.shoulder, elbow, wrist];
        let outcome = fabrik(
            &mut points,
            &[arm.upper_arm, arm.forearm],
            target,
            self.chain,
            &hinges,
            DVec3::Z,
        );
        if outcome.stalled && outcome.error > CLOSING_DISTANCE {
            return Err(hinges.last_clamped.get().map_or(1, |joint| joint + 1));
        }
        let side = wrap(plane_angle(points[1] - arm.shoulder) - plane.line_angle);
        let closed_on = usize::from(side.is_sign_positive());
        plane.closed[closed_on].map(|angles| (angles, closed_on, outcome.iterations))
    }

    fn elbow_at(&self, q2: f64) -> DVec3 {
        self.arm.shoulder + self.arm.upper_arm * plane_direction(self.arm.upper_arm_angle + q2)
    }

    /// The two elbow sides of the shoulder -> target line, the seed's side first.
    fn elbow_sides(&self, seed_elbow: DVec3, line: DVec3) -> [f64; 2] {
        let relative = seed_elbow - self.arm.shoulder;
        let side = if line.cross(relative).y < 0.0 {
            -1.0
        } else {
            1.0
        };
        [side, -side]
    }

    /// Runs FABRIK on one elbow side: from the seed's elbow (moved to that side), and, if
    /// a hinge limit traps it there, again from an upper arm turned toward the target, bent
    /// to that side (the classic FABRIK start; it escapes the traps the seed can set).
    fn solve_side(
        &self,
        plane: &PlaneTarget,
        side: f64,
        seed_elbow: DVec3,
    ) -> Result<Closed, usize> {
        let line = plane.line;
        self.solve_plane(plane, self.on_side(seed_elbow, line, side))
            .or_else(|_| {
                let toward = plane_angle(line) - self.arm.upper_arm_angle;
                let turned = self.elbow_at(toward + 0.3 * side);
                self.solve_plane(plane, self.on_side(turned, line, side))
            })
    }

    /// `elbow`, reflected across the shoulder -> target line if it lies on the other side
    /// (or nudged off the line if on it, so FABRIK knows which way to bend).
    fn on_side(&self, elbow: DVec3, line: DVec3, side: f64) -> DVec3 {
        let shoulder = self.arm.shoulder;
        let across = line.cross(elbow - shoulder).y;
        if across.abs() < 1e-9 {
            let normal = DVec3::new(line.z, 0.0, -line.x);
            return elbow + normal * side * 1e-3;
        }
        if across.signum() == side {
            elbow
        } else {
            reflect_across_line(elbow, shoulder, line)
        }
    }

    /// The arm's rotation up to and including joint 3.
    fn arm_rotation(&self, q: [f64; 3]) -> DMat3 {
        let frame = (0..3).fold(DAffine3::IDENTITY, |frame, i| {
            frame * self.rig.joints[i].transform(q[i])
        });
        frame.matrix3
    }

    /// Offers every wrist branch and turn for one arm solution (at `rank`) to `search`.
    fn add_wrist_branches(
        &self,
        arm: [f64; 3],
        target: DMat3,
        seed: &[f64],
        iterations: u32,
        [k, side, ..]: Rank,
        search: &mut Search,
    ) {
        let arm_rotation = self.arm_rotation(arm);
        let branches = self.wrist.solve(arm_rotation, target, seed[3]);
        for (branch, [q4, q5, q6]) in (0u8..).zip(branches) {
            let rank = [k, side, branch, 0, 0];
            let Some(q5) = self.within(4, q5) else {
                search.block(rank, 4);
                continue;
            };
            let mut any = false;
            for (turn4, q4) in (0u8..).zip(self.turns(3, q4)) {
                for (turn6, q6) in (0u8..).zip(self.turns(5, q6)) {
                    any = true;
                    let joints = [arm[0], arm[1], arm[2], q4, q5, q6];
                    search.offer(Candidate {
                        joints,
                        cost: self.cost(&joints, seed),
                        iterations,
                        rank: [k, side, branch, turn4, turn6],
                    });
                }
            }
            if !any {
                search.block(rank, 3);
            }
        }
    }

    /// The least cost of axes 1 to 3 on this branch: FABRIK closes on one of the two exact
    /// elbows, so no candidate through it costs less (infinite when neither fits).
    fn arm_bound(&self, q1: f64, plane: &PlaneTarget, seed: &[f64]) -> f64 {
        plane
            .closed
            .iter()
            .flatten()
            .map(|[q2, q3]| self.cost(&[q1, *q2, *q3], seed))
            .fold(f64::INFINITY, f64::min)
    }

    /// The cost of axes 1 to 3 with the elbow closed exactly as `plane.closed[index]`
    /// (infinite when that elbow is out of limits).
    fn closed_bound(&self, q1: f64, plane: &PlaneTarget, index: usize, seed: &[f64]) -> f64 {
        plane.closed[index].map_or(f64::INFINITY, |[q2, q3]| self.cost(&[q1, q2, q3], seed))
    }

    /// Axis 1's in-limit values `heading + k pi`, nearest the seed first (so that the far
    /// ones can be cut off by cost), ties in the order of k.
    fn axis_1_turns(&self, heading: f64, seed: &[f64]) -> ([Axis1Turn; 5], usize) {
        let mut turns = [Axis1Turn {
            rank: 0,
            q1: 0.0,
            cost: 0.0,
        }; 5];
        let mut count = 0;
        for (rank, k) in (0u8..).zip(-AXIS_1_TURNS..=AXIS_1_TURNS) {
            if let Some(q1) = self.within(0, heading + f64::from(k) * PI) {
                let cost = self.cost(&[q1], seed);
                turns[count] = Axis1Turn { rank, q1, cost };
                count += 1;
            }
        }
        turns[..count].sort_by(|a, b| a.cost.total_cmp(&b.cost));
        (turns, count)
    }

    /// Every branch for the wrist centre at `radius` from axis 1 and `height` along it,
    /// searched nearest the seed first and cut off where its first axes already cost more
    /// than the best candidate found.
    fn search(
        &self,
        (radius, height, heading): (f64, f64, f64),
        target_rotation: DMat3,
        seed: &[f64],
    ) -> Search {
        let seed_elbow = self.elbow_at(seed[1]);
        let mut search = Search::default();
        let (turns, count) = self.axis_1_turns(heading, seed);
        for turn in &turns[..count] {
            if !search.open(turn.cost) {
                continue;
            }
            let signed_radius = if turn.rank % 2 == 0 { radius } else { -radius };
            let plane = self.plane_target(DVec3::new(signed_radius, 0.0, height));
            if !search.open(self.arm_bound(turn.q1, &plane, seed)) {
                continue;
            }
            // Once the first side's run closes on one exact elbow, the second side's can only
            // add the other: closing on the same would repeat the first's candidates at a
            // later rank, which never wins.
            let mut first_closed_on = None;
            for (side_rank, side) in (0u8..).zip(self.elbow_sides(seed_elbow, plane.line)) {
                let rank = [turn.rank, side_rank, 0, 0, 0];
                if let Some(first) = first_closed_on
                    && !search.open(self.closed_bound(turn.q1, &plane, 1 - first, seed))
                {
                    continue;
                }
                match self.solve_side(&plane, side, seed_elbow) {
                    Ok(([q2, q3], closed_on, iterations)) => {
                        first_closed_on.get_or_insert(closed_on);
                        let joints = [turn.q1, q2, q3];
                        if search.open(self.cost(&joints, seed)) {
                            self.add_wrist_branches(
                                joints,
                                target_rotation,
                                seed,
                                iterations,
                                rank,
                                &mut search,
                            );
                        }
                    }
                    Err(axis) => search.block(rank, axis),
                }
            }
        }
        search
    }
}

impl ArmGeometry {
    fn read(rig: &Rig) -> Result<Self, StructureProblem> {
        let zero = [0.0; 6];
        let mut axes = Vec::with_capacity(6);
        let tool_frame = rig.forward_with_axes(&zero, &mut axes)?;
        let base = rig.joints[0].origin;
        let to_base = base.inverse();
        let point = |i: usize| to_base.transform_point3(axes[i].point);
        let axis = |i: usize| to_base.transform_vector3(axes[i].direction);
        let up = axis(0);
        let hinge = axis(1);
        if up.dot(hinge).abs() > GEOMETRY_TOLERANCE {
            return Err(StructureProblem::ShoulderNotPerpendicular);
        }
        if (hinge.dot(axis(2)).abs() - 1.0).abs() > GEOMETRY_TOLERANCE {
            return Err(StructureProblem::ElbowNotParallel);
        }
        let wrist_centre = closest_point_between_lines(point(3), axis(3), point(4), axis(4))
            .ok_or(StructureProblem::WristAxesMiss)?;
        for i in [3, 4, 5] {
            let off = (wrist_centre - point(i))
                .reject_from_normalized(axis(i))
                .length();
            if off > GEOMETRY_TOLERANCE {
                return Err(StructureProblem::OffWristCentre {
                    axis: i + 1,
                    off_m: off,
                });
            }
        }
        let (shoulder, elbow) = (point(1), point(2));
        for (name, p) in [
            ("axis 2", shoulder),
            ("axis 3", elbow),
            ("the wrist centre", wrist_centre),
        ] {
            if p.dot(hinge).abs() > GEOMETRY_TOLERANCE {
                return Err(StructureProblem::OffPlane(name));
            }
        }
        let reach = hinge.cross(up);
        let in_plane = |p: DVec3| DVec3::new(p.dot(reach), 0.0, p.dot(up));
        let (shoulder, elbow, wrist) =
            (in_plane(shoulder), in_plane(elbow), in_plane(wrist_centre));
        let upper_arm_angle = plane_angle(elbow - shoulder);
        let tool_rotation = DQuat::from_mat3(&tool_frame.matrix3);
        Ok(Self {
            to_base,
            up,
            reach,
            side: up.cross(reach),
            shoulder,
            upper_arm: shoulder.distance(elbow),
            forearm: elbow.distance(wrist),
            upper_arm_angle,
            elbow_angle: wrap(plane_angle(wrist - elbow) - upper_arm_angle),
            elbow_sign: hinge.dot(axis(2)).signum(),
            tool_offset: tool_rotation.inverse()
                * (tool_frame.translation - base.transform_point3(wrist_centre)),
        })
    }
}

fn closest_point_between_lines(p: DVec3, u: DVec3, q: DVec3, v: DVec3) -> Option<DVec3> {
    let w = p - q;
    let (a, b, c, d, e) = (u.dot(u), u.dot(v), v.dot(v), u.dot(w), v.dot(w));
    let denominator = a * c - b * b;
    if denominator.abs() < 1e-12 {
        return None;
    }
    let s = (b * e - c * d) / denominator;
    let t = (a * e - b * d) / denominator;
    let (on_p, on_q) = (p + u * s, q + v * t);
    (on_p.distance(on_q) <= GEOMETRY_TOLERANCE).then(|| (on_p + on_q) / 2.0)
}

fn reflect_across_line(point: DVec3, origin: DVec3, direction: DVec3) -> DVec3 {
    let relative = point - origin;
    let along = direction * relative.dot(direction);
    origin + 2.0 * along - relative
}

impl IkSolver for FabrikSolver {
    fn name(&self) -> &'static str {
        "fabrik"
    }

    fn rig(&self) -> &Rig {
        &self.rig
    }

    fn solve(&self, target: &Pose, seed: &[f64]) -> Result<IkSolution, IkError> {
        let target = self.checked_input(target, seed)?;
        let arm = &self.arm;
        let wrist_centre = target.position - target.orientation * arm.tool_offset;
        let local = arm.to_base.transform_point3(wrist_centre);
        let height = local.dot(arm.up);
        let horizontal = local - arm.up * height;
        let radius = horizontal.length();
        let heading = if radius < ON_AXIS_1 {
            seed[0]
        } else {
            horizontal.dot(arm.side).atan2(horizontal.dot(arm.reach))
        };
        check_reach(arm, radius, height)?;
        let target_rotation = DMat3::from_quat(target.orientation);
        let search = self.search((radius, height, heading), target_rotation, seed);
        let Some(best) = search.best else {
            let axis = search.blocked.map_or(0, |(_, axis)| axis);
            return Err(IkError::NoSolutionWithinLimits {
                axis: axis + 1,
                joint: self.rig.joints[axis].name.clone(),
            });
        };
        verified(
            &self.rig,
            &target,
            best.joints.to_vec(),
            best.iterations,
            self.tolerance,
        )
    }
}

/// Distance checks in the arm's plane, before any iteration: beyond the stretched arm, or
/// inside the sphere the folded arm cannot reach.
fn check_reach(arm: &ArmGeometry, radius: f64, height: f64) -> Result<(), IkError> {
    let longest = arm.upper_arm + arm.forearm;
    let shortest = (arm.upper_arm - arm.forearm).abs();
    let distance = |r: f64| DVec3::new(r, 0.0, height).distance(arm.shoulder);
    let (near, far) = {
        let (a, b) = (distance(radius), distance(-radius));
        (a.min(b), a.max(b))
    };
    if near > longest + GEOMETRY_TOLERANCE {
        return Err(IkError::OutOfReach {
            excess_m: near - longest,
            distance_m: near,
            reach_m: longest,
        });
    }
    if far < shortest - GEOMETRY_TOLERANCE {
        return Err(IkError::TooClose {
            shortfall_m: shortest - far,
            distance_m: far,
            min_reach_m: shortest,
        });
    }
    Ok(())
}
