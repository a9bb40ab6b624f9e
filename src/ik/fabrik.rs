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
use super::{IkError, IkSolution, IkSolver, Tolerance, check_seed, verified};
use crate::rig::{JointKind, Pose, Rig};
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
    pub reason: String,
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
    /// Joint 1's origin; everything below is in its frame.
    base: DAffine3,
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
}

impl FabrikSolver {
    pub fn new(rig: Rig) -> Result<Self, StructureError> {
        Self::with_tolerance(rig, Tolerance::default())
    }

    pub fn with_tolerance(rig: Rig, tolerance: Tolerance) -> Result<Self, StructureError> {
        let rig_name = rig.name.clone();
        let fail = |reason: String| StructureError {
            rig: rig_name.clone(),
            reason,
        };
        if rig.dof() != 6 || rig.joints.iter().any(|j| j.kind != JointKind::Revolute) {
            return Err(fail(format!(
                "needs 6 revolute joints, has {} joints",
                rig.dof()
            )));
        }
        let arm = ArmGeometry::read(&rig).map_err(&fail)?;
        let rotation = |t: &DAffine3| t.matrix3;
        let wrist = SphericalWrist::new(
            [3, 4, 5].map(|i| rotation(&rig.joints[i].origin)),
            [3, 4, 5].map(|i| rig.joints[i].axis),
            rotation(&rig.tool),
        )
        .ok_or_else(|| {
            fail("axes 4 and 6 must be parallel and axis 5 perpendicular to them".into())
        })?;
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
    fn self_check(&self) -> Result<(), String> {
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
            let pose = self.rig.tool_pose(&joints).map_err(|e| e.to_string())?;
            self.solve(&pose, &joints).map_err(|e| {
                let degrees: Vec<f64> = joints.iter().map(|q| q.to_degrees()).collect();
                format!(
                    "self-check failed at {} deg: {e}",
                    crate::rig::Shown::shown(&degrees)
                )
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

    fn cost(&self, joints: &[f64; 6], seed: &[f64]) -> f64 {
        joints
            .iter()
            .zip(seed)
            .zip(&self.rig.joints)
            .map(|((q, s), j)| ((q - s) / j.limits.max_speed).powi(2))
            .sum()
    }

    /// Axes 2 and 3 for the wrist centre at `target` (plane coordinates), starting FABRIK
    /// from `elbow`. Err carries the index of the axis that held the chain back.
    fn solve_plane(&self, target: DVec3, elbow: DVec3) -> Result<([f64; 2], u32), usize> {
        let arm = &self.arm;
        let hinges = ArmHinges {
            windows: self.windows,
            last_clamped: Cell::new(None),
        };
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
        let blocking_axis = || hinges.last_clamped.get().map_or(1, |joint| joint + 1);
        if outcome.stalled && outcome.error > CLOSING_DISTANCE {
            return Err(blocking_axis());
        }
        let elbow = close_triangle(arm.shoulder, points[1], target, arm.upper_arm, arm.forearm);
        let upper = plane_angle(elbow - arm.shoulder);
        let fore = plane_angle(target - elbow);
        let (lower2, upper2) = self.limit(1);
        let (lower3, upper3) = self.limit(2);
        let middle2 = (lower2 + upper2) / 2.0;
        let middle3 = (lower3 + upper3) / 2.0;
        let q2 = middle2 + wrap(upper - arm.upper_arm_angle - middle2);
        let q3 = middle3
            + arm.elbow_sign * wrap(fore - upper - arm.elbow_angle - arm.elbow_sign * middle3);
        let q2 = self.within(1, q2).ok_or(1usize)?;
        let q3 = self.within(2, q3).ok_or(2usize)?;
        Ok(([q2, q3], outcome.iterations))
    }

    fn elbow_at(&self, q2: f64) -> DVec3 {
        self.arm.shoulder + self.arm.upper_arm * plane_direction(self.arm.upper_arm_angle + q2)
    }

    /// The two elbow sides of the shoulder -> target line, the seed's side first.
    fn elbow_sides(&self, seed: &[f64], line: DVec3) -> [f64; 2] {
        let relative = self.elbow_at(seed[1]) - self.arm.shoulder;
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
        target: DVec3,
        line: DVec3,
        side: f64,
        seed: &[f64],
    ) -> Result<([f64; 2], u32), usize> {
        let toward = plane_angle(line) - self.arm.upper_arm_angle;
        let mut blocked = 1;
        for q2 in [seed[1], toward + 0.3 * side] {
            let elbow = self.on_side(self.elbow_at(q2), line, side);
            match self.solve_plane(target, elbow) {
                Ok(solution) => return Ok(solution),
                Err(axis) => blocked = axis,
            }
        }
        Err(blocked)
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

    /// Adds every wrist branch and turn for one arm solution to `best`.
    fn add_wrist_branches(
        &self,
        arm: [f64; 3],
        target: DMat3,
        seed: &[f64],
        iterations: u32,
        best: &mut Option<Candidate>,
        blocked: &mut Option<usize>,
    ) {
        let arm_rotation = self.arm_rotation(arm);
        for [q4, q5, q6] in self.wrist.solve(arm_rotation, target, seed[3]) {
            let Some(q5) = self.within(4, q5) else {
                blocked.get_or_insert(4);
                continue;
            };
            let mut any = false;
            for q4 in self.turns(3, q4) {
                for q6 in self.turns(5, q6) {
                    any = true;
                    let joints = [arm[0], arm[1], arm[2], q4, q5, q6];
                    let cost = self.cost(&joints, seed);
                    if best.is_none_or(|b| cost < b.cost) {
                        *best = Some(Candidate {
                            joints,
                            cost,
                            iterations,
                        });
                    }
                }
            }
            if !any {
                blocked.get_or_insert(3);
            }
        }
    }
}

impl ArmGeometry {
    fn read(rig: &Rig) -> Result<Self, String> {
        let zero = [0.0; 6];
        let mut axes = Vec::with_capacity(6);
        let tool_frame = rig
            .forward_with_axes(&zero, &mut axes)
            .map_err(|e| e.to_string())?;
        let base = rig.joints[0].origin;
        let to_base = base.inverse();
        let point = |i: usize| to_base.transform_point3(axes[i].point);
        let axis = |i: usize| to_base.transform_vector3(axes[i].direction);
        let up = axis(0);
        let hinge = axis(1);
        if up.dot(hinge).abs() > GEOMETRY_TOLERANCE {
            return Err("axis 2 must be perpendicular to axis 1".into());
        }
        if (hinge.dot(axis(2)).abs() - 1.0).abs() > GEOMETRY_TOLERANCE {
            return Err("axes 2 and 3 must be parallel".into());
        }
        let wrist_centre = closest_point_between_lines(point(3), axis(3), point(4), axis(4))
            .ok_or("axes 4 and 5 must intersect")?;
        for i in [3, 4, 5] {
            let off = (wrist_centre - point(i))
                .reject_from_normalized(axis(i))
                .length();
            if off > GEOMETRY_TOLERANCE {
                return Err(format!("axis {} misses the wrist centre by {off} m", i + 1));
            }
        }
        let (shoulder, elbow) = (point(1), point(2));
        for (name, p) in [
            ("axis 2", shoulder),
            ("axis 3", elbow),
            ("the wrist centre", wrist_centre),
        ] {
            if p.dot(hinge).abs() > GEOMETRY_TOLERANCE {
                return Err(format!(
                    "{name} lies off the plane of axis 1 (lateral offset)"
                ));
            }
        }
        let reach = hinge.cross(up);
        let in_plane = |p: DVec3| DVec3::new(p.dot(reach), 0.0, p.dot(up));
        let (shoulder, elbow, wrist) =
            (in_plane(shoulder), in_plane(elbow), in_plane(wrist_centre));
        let upper_arm_angle = plane_angle(elbow - shoulder);
        let tool_rotation = DQuat::from_mat3(&tool_frame.matrix3);
        Ok(Self {
            base,
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

/// The elbow that puts the wrist centre exactly on `target`, on the same side of the
/// shoulder-target line as FABRIK's `elbow` (law of cosines).
fn close_triangle(
    shoulder: DVec3,
    elbow: DVec3,
    target: DVec3,
    upper_arm: f64,
    forearm: f64,
) -> DVec3 {
    let to_target = target - shoulder;
    let distance = to_target.length();
    let cosine = (upper_arm * upper_arm + distance * distance - forearm * forearm)
        / (2.0 * upper_arm * distance);
    let opening = cosine.clamp(-1.0, 1.0).acos();
    let line = plane_angle(to_target);
    let side = wrap(plane_angle(elbow - shoulder) - line).signum();
    shoulder + upper_arm * plane_direction(line + side * opening)
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
        let target = target.validated()?;
        check_seed(&self.rig, seed)?;
        let arm = &self.arm;
        let wrist_centre = target.position - target.orientation * arm.tool_offset;
        let local = arm.base.inverse().transform_point3(wrist_centre);
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
        let mut best: Option<Candidate> = None;
        let mut blocked: Option<usize> = None;
        for k in -2i32..=2 {
            let Some(q1) = self.within(0, heading + f64::from(k) * PI) else {
                continue;
            };
            let signed_radius = if k % 2 == 0 { radius } else { -radius };
            let plane_target = DVec3::new(signed_radius, 0.0, height);
            let line = (plane_target - arm.shoulder).normalize_or(DVec3::Z);
            for side in self.elbow_sides(seed, line) {
                match self.solve_side(plane_target, line, side, seed) {
                    Ok(([q2, q3], iterations)) => self.add_wrist_branches(
                        [q1, q2, q3],
                        target_rotation,
                        seed,
                        iterations,
                        &mut best,
                        &mut blocked,
                    ),
                    Err(axis) => {
                        blocked.get_or_insert(axis);
                    }
                }
            }
        }
        let Some(best) = best else {
            let axis = blocked.unwrap_or(0);
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
