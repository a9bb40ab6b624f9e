//! Position-only FABRIK for any serial rig (the sloth's limbs): places the tool's origin,
//! ignoring orientation. The rig is seen as a chain of points (its distinct joint origins,
//! then the tool's origin; joints sharing an origin pivot the same bone). Each iteration is
//! FABRIK's two passes (Aristidou & Lasenby 2011): forward reaching, tip to root, on the
//! points (the tip on the target, each point on the line toward where it was, at its bone's
//! length: `chain::forward_reaching`, the same pass as the arm planner's); then backward
//! reaching, root to tip, *in joint space*: each joint in turn takes
//! the angle that best brings the points beyond it toward where forward reaching put them,
//! clamped to its limits. So every iteration ends on a real pose of the rig within its
//! limits, and the answer is read straight off the joints: no conversion from points after
//! the fact. docs/kinematics.md has the measurements behind the choices.
//! It must not touch the rig, and never clamps a final answer: the best pose found is
//! checked by `ik::verified` (limits, then the forward-kinematics residual).

use super::chain::{STALL_PATIENCE, Unconstrained, forward_reaching};
use super::{IkError, IkSolution, IkSolver, Tolerance, verified};
use crate::rig::{JointKind, Pose, Rig};
use glam::{DAffine3, DQuat, DVec3};

/// Points of the chain closer than this (m) are one point: joints sharing an origin (a
/// bone's flexion and abduction) pivot the same segment.
const SAME_POINT_M: f64 = 1e-9;
/// An iteration counts as progress when it lowers the best residual by this fraction.
const MIN_IMPROVEMENT: f64 = 1e-3;

#[derive(Debug, Clone)]
pub struct PositionFabrikSolver {
    rig: Rig,
    tolerance: Tolerance,
    max_iterations: u32,
    /// The farthest the tool's origin gets from joint 1's origin, when every joint is
    /// revolute (a prismatic joint changes it): targets beyond are refused at once.
    reach_m: Option<f64>,
}

/// The rig's point chain at one pose: the distinct joint origins, root first, then the
/// tool's origin; and for every joint, which point it sits on.
#[derive(Debug, Default)]
struct PointChain {
    points: Vec<DVec3>,
    point_of_joint: Vec<usize>,
}

impl PositionFabrikSolver {
    pub fn new(rig: Rig) -> Self {
        let all_revolute = rig.joints.iter().all(|j| j.kind == JointKind::Revolute);
        let reach_m = all_revolute.then(|| {
            rig.joints
                .iter()
                .skip(1)
                .map(|j| j.origin.translation.length())
                .sum::<f64>()
                + rig.tool.translation.length()
        });
        Self {
            rig,
            tolerance: Tolerance {
                position_m: 1e-6,
                orientation_rad: std::f64::consts::PI,
            },
            max_iterations: 500,
            reach_m,
        }
    }

    /// The position tolerance; orientation is never checked (any is accepted).
    pub fn with_tolerance(mut self, tolerance: Tolerance) -> Self {
        self.tolerance = Tolerance {
            position_m: tolerance.position_m,
            orientation_rad: std::f64::consts::PI,
        };
        self
    }

    pub fn with_max_iterations(mut self, max_iterations: u32) -> Self {
        self.max_iterations = max_iterations;
        self
    }

    /// The point chain of the pose `joints` (in limits), and the tool's origin.
    fn point_chain(&self, joints: &[f64], chain: &mut PointChain) {
        chain.points.clear();
        chain.point_of_joint.clear();
        let mut frame = DAffine3::IDENTITY;
        for (joint, q) in self.rig.joints.iter().zip(joints) {
            let origin = (frame * joint.origin).translation;
            push_point(chain, origin);
            chain.point_of_joint.push(chain.points.len() - 1);
            frame *= joint.transform(*q);
        }
        push_point(chain, (frame * self.rig.tool).translation);
    }

    /// Backward reaching in joint space: root to tip, each joint turns (or slides) so that
    /// the points beyond it head for `wanted`'s, within its limits. Returns the tool's
    /// origin at the new joints.
    fn reach_back(&self, joints: &mut [f64], chain: &PointChain, wanted: &[DVec3]) -> DVec3 {
        let mut frame = DAffine3::IDENTITY;
        for index in 0..joints.len() {
            let joint = &self.rig.joints[index];
            let at_origin = frame * joint.origin;
            let step = self.fit_step(index, &at_origin, joints, chain, wanted);
            let limits = joint.limits;
            joints[index] = (joints[index] + step).clamp(limits.lower, limits.upper);
            frame *= joint.transform(joints[index]);
        }
        (frame * self.rig.tool).translation
    }

    /// The change of joint `index` (whose origin is at `at_origin`) that best brings the
    /// chain's points beyond it toward where forward reaching put them. All of them, not
    /// only the next: a bone pivoted by two axes then also turns the plane its hinges bend
    /// in toward the points further on.
    fn fit_step(
        &self,
        index: usize,
        at_origin: &DAffine3,
        joints: &[f64],
        chain: &PointChain,
        wanted: &[DVec3],
    ) -> f64 {
        let joint = &self.rig.joints[index];
        let mut fit = Fit::new(
            joint.kind,
            at_origin.translation,
            at_origin.transform_vector3(joint.axis),
        );
        let own = chain.point_of_joint[index];
        let mut frame = *at_origin * motion(joint.kind, joint.axis, joints[index]);
        let beyond = self
            .rig
            .joints
            .iter()
            .zip(joints)
            .zip(&chain.point_of_joint);
        let mut previous_point = own;
        for ((next, q), &point) in beyond.skip(index + 1) {
            let origin = frame * next.origin;
            // The first joint on a point beyond this one's stands for that point.
            if point != previous_point {
                fit.add(origin.translation, wanted[point]);
            }
            previous_point = point;
            frame = origin * motion(next.kind, next.axis, *q);
        }
        let tip = wanted.len() - 1;
        if chain.point_of_joint.last().is_some_and(|last| tip > *last) {
            fit.add((frame * self.rig.tool).translation, wanted[tip]);
        }
        fit.step()
    }
}

/// Where FABRIK's forward reaching (`chain::forward_reaching`, unconstrained) puts the
/// points of `points`, its bones' current lengths kept, into `wanted`.
fn reach_forward(points: &[DVec3], goal: DVec3, wanted: &mut Vec<DVec3>, lengths: &mut Vec<f64>) {
    lengths.clear();
    lengths.extend(points.windows(2).map(|bone| bone[0].distance(bone[1])));
    wanted.clear();
    wanted.extend_from_slice(points);
    forward_reaching(wanted, lengths, goal, &Unconstrained);
}

fn push_point(chain: &mut PointChain, point: DVec3) {
    match chain.points.last() {
        Some(last) if last.distance(point) <= SAME_POINT_M => {}
        _ => chain.points.push(point),
    }
}

/// A joint's own motion at `position` (after its origin).
fn motion(kind: JointKind, axis: DVec3, position: f64) -> DAffine3 {
    match kind {
        JointKind::Revolute => DAffine3::from_quat(DQuat::from_axis_angle(axis, position)),
        JointKind::Prismatic => DAffine3::from_translation(axis * position),
    }
}

/// Least-squares fit of one joint's change to moving points toward wanted positions: for
/// a revolute joint the angle about the axis (sums of the sines and cosines of each point's
/// angle, as CCD's markers), for a prismatic one the mean shift along it.
struct Fit {
    kind: JointKind,
    pivot: DVec3,
    axis: DVec3,
    sine: f64,
    cosine: f64,
    shift: f64,
    count: usize,
}

impl Fit {
    fn new(kind: JointKind, pivot: DVec3, axis: DVec3) -> Self {
        Self {
            kind,
            pivot,
            axis,
            sine: 0.0,
            cosine: 0.0,
            shift: 0.0,
            count: 0,
        }
    }

    fn add(&mut self, current: DVec3, wanted: DVec3) {
        let from = (current - self.pivot).reject_from_normalized(self.axis);
        let to = (wanted - self.pivot).reject_from_normalized(self.axis);
        self.sine += self.axis.dot(from.cross(to));
        self.cosine += from.dot(to);
        self.shift += (wanted - current).dot(self.axis);
        self.count += 1;
    }

    fn step(&self) -> f64 {
        match self.kind {
            JointKind::Revolute => self.sine.atan2(self.cosine),
            JointKind::Prismatic => self.shift / self.count.max(1) as f64,
        }
    }
}

impl IkSolver for PositionFabrikSolver {
    fn name(&self) -> &'static str {
        "fabrik_position"
    }

    fn rig(&self) -> &Rig {
        &self.rig
    }

    fn solve(&self, target: &Pose, seed: &[f64]) -> Result<IkSolution, IkError> {
        let target = self.checked_input(target, seed)?;
        let goal = target.position;
        let mut joints: Vec<f64> = seed
            .iter()
            .zip(&self.rig.joints)
            .map(|(q, j)| q.clamp(j.limits.lower, j.limits.upper))
            .collect();
        let mut chain = PointChain::default();
        self.point_chain(&joints, &mut chain);
        if let Some(reach_m) = self.reach_m {
            let distance_m = chain.points[0].distance(goal);
            if distance_m > reach_m + self.tolerance.position_m {
                return Err(IkError::OutOfReach {
                    excess_m: distance_m - reach_m,
                    distance_m,
                    reach_m,
                });
            }
        }
        let start_error = chain.points.last().map_or(0.0, |tip| tip.distance(goal));
        let mut best = (start_error, joints.clone());
        let mut wanted = Vec::with_capacity(chain.points.len());
        let mut lengths = Vec::with_capacity(chain.points.len());
        let mut iterations = 0;
        let mut since_best = 0;
        while best.0 > self.tolerance.position_m && iterations < self.max_iterations {
            iterations += 1;
            reach_forward(&chain.points, goal, &mut wanted, &mut lengths);
            let error = self.reach_back(&mut joints, &chain, &wanted).distance(goal);
            if error < best.0 * (1.0 - MIN_IMPROVEMENT) {
                since_best = 0;
            } else {
                since_best += 1;
            }
            if error < best.0 {
                best = (error, joints.clone());
            }
            if since_best >= STALL_PATIENCE {
                break;
            }
            self.point_chain(&joints, &mut chain);
        }
        verified(&self.rig, &target, best.1, iterations, self.tolerance)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::apps::gait::SlothRig;
    use crate::rig::load_rig;
    use rand::{RngExt, SeedableRng};
    use rand_chacha::ChaCha8Rng;
    use std::path::Path;

    const TOLERANCE_M: f64 = 3e-4;

    fn limbs() -> Vec<Rig> {
        let file = Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/config/sloth.toml"));
        let sloth = SlothRig::load(file).expect("config/sloth.toml loads");
        sloth.limbs.into_iter().map(|limb| limb.chain).collect()
    }

    fn solver(rig: Rig) -> PositionFabrikSolver {
        PositionFabrikSolver::new(rig)
            .with_tolerance(Tolerance {
                position_m: TOLERANCE_M,
                orientation_rad: 0.0,
            })
            .with_max_iterations(500)
    }

    fn random_joints(rig: &Rig, rng: &mut ChaCha8Rng) -> Vec<f64> {
        rig.joints
            .iter()
            .map(|j| rng.random_range(j.limits.lower..=j.limits.upper))
            .collect()
    }

    fn middle(rig: &Rig) -> Vec<f64> {
        rig.joints
            .iter()
            .map(|j| 0.5 * (j.limits.lower + j.limits.upper))
            .collect()
    }

    /// The solution's own claim checked from scratch: joints within limits as raw numbers,
    /// and forward kinematics of those joints within the tolerance of the target.
    fn assert_genuine(rig: &Rig, target: DVec3, solution: &IkSolution) {
        assert_eq!(rig.first_limit_violation(&solution.joints), None);
        let reached = rig
            .tool_pose(&solution.joints)
            .expect("the solution has the rig's joint count")
            .position;
        assert!(reached.distance(target) <= TOLERANCE_M, "{solution:?}");
        assert!((reached.distance(target) - solution.position_error_m).abs() < 1e-12);
    }

    #[test]
    fn reaches_targets_of_in_limit_poses_from_a_nearby_seed() {
        let mut rng = ChaCha8Rng::seed_from_u64(6);
        for rig in limbs() {
            let solver = solver(rig.clone());
            for _ in 0..200 {
                let pose = random_joints(&rig, &mut rng);
                let target = rig
                    .tool_pose(&pose)
                    .expect("the pose has the rig's joint count");
                // The previous frame's joints, as in the gait: within a degree or so.
                let seed: Vec<f64> = pose
                    .iter()
                    .map(|q| q + rng.random_range(-0.02..0.02))
                    .collect();
                let solution = solver
                    .solve(&target, &seed)
                    .unwrap_or_else(|e| panic!("{}: {pose:?}: {e}", rig.name));
                assert_genuine(&rig, target.position, &solution);
            }
        }
    }

    #[test]
    fn never_returns_a_joint_outside_its_limits_or_short_of_the_tolerance() {
        // From the middle of every range (a cold start), far from the answer: whatever
        // comes back is within limits and within the tolerance, or a structured error.
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let mut solved = 0;
        for rig in limbs() {
            let solver = solver(rig.clone());
            for _ in 0..250 {
                let target = rig
                    .tool_pose(&random_joints(&rig, &mut rng))
                    .expect("the random pose has the rig's joint count");
                match solver.solve(&target, &middle(&rig)) {
                    Ok(solution) => {
                        solved += 1;
                        assert_genuine(&rig, target.position, &solution);
                    }
                    Err(IkError::NotConverged {
                        position_error_m, ..
                    }) => assert!(position_error_m > TOLERANCE_M),
                    Err(other) => panic!("{}: unexpected {other}", rig.name),
                }
            }
        }
        assert!(solved >= 990, "{solved} of 1000 cold starts solved");
    }

    #[test]
    fn refuses_a_target_beyond_the_limb_with_the_distance() {
        let rig = limbs().remove(0);
        let root = rig.joints[0].origin.translation;
        let target = Pose::new(root + DVec3::new(0.0, 0.0, 0.5), DQuat::IDENTITY);
        match solver(rig.clone()).solve(&target, &middle(&rig)) {
            Err(IkError::OutOfReach {
                excess_m,
                distance_m,
                reach_m,
            }) => {
                assert!((distance_m - 0.5).abs() < 1e-12);
                assert!((reach_m - 0.27).abs() < 1e-9, "{reach_m}");
                assert!((excess_m - 0.23).abs() < 1e-9);
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn refuses_a_target_its_limits_forbid_with_the_residual() {
        // Within the hind limb's length, but behind its back: no pose within the bones'
        // ranges reaches it, and the error carries how far the best one stayed.
        let rig = limbs().remove(0);
        let root = rig.joints[0].origin.translation;
        let target = Pose::new(root + DVec3::new(0.0, 0.0, -0.15), DQuat::IDENTITY);
        match solver(rig.clone()).solve(&target, &middle(&rig)) {
            Err(IkError::NotConverged {
                position_error_m, ..
            }) => assert!(position_error_m > 0.05, "{position_error_m}"),
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn places_the_tool_of_any_serial_rig() {
        // The six-axis arm, position only: not the sloth's structure, same solver.
        let rig = load_rig(Path::new(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/config/irb120.toml"
        )))
        .expect("config/irb120.toml loads");
        let mut rng = ChaCha8Rng::seed_from_u64(8);
        let solver = solver(rig.clone());
        for _ in 0..100 {
            let pose = random_joints(&rig, &mut rng);
            let target = rig
                .tool_pose(&pose)
                .expect("the pose has the rig's joint count");
            let seed: Vec<f64> = pose
                .iter()
                .map(|q| q + rng.random_range(-0.05..0.05))
                .collect();
            let solution = solver.solve(&target, &seed).expect("reaches");
            assert_genuine(&rig, target.position, &solution);
        }
    }

    /// A turntable carrying a telescopic boom: a revolute joint, then a prismatic one.
    fn boom() -> Rig {
        let joint = |name: &str, kind, origin: DVec3, axis, lower, upper| crate::rig::Joint {
            name: name.into(),
            kind,
            origin: DAffine3::from_translation(origin),
            axis,
            limits: crate::rig::JointLimits {
                lower,
                upper,
                max_speed: 1.0,
                max_acceleration: 1.0,
            },
        };
        Rig {
            name: "boom".into(),
            base_frame: "base".into(),
            tool_frame: "tip".into(),
            joints: vec![
                joint(
                    "turn",
                    JointKind::Revolute,
                    DVec3::ZERO,
                    DVec3::Z,
                    -2.0,
                    2.0,
                ),
                joint(
                    "reach",
                    JointKind::Prismatic,
                    DVec3::new(0.0, 0.0, 0.1),
                    DVec3::X,
                    0.0,
                    0.3,
                ),
            ],
            tool: DAffine3::from_translation(DVec3::new(0.05, 0.0, 0.0)),
            bodies: Vec::new(),
            allowed_pairs: Vec::new(),
        }
    }

    #[test]
    fn slides_a_prismatic_joint_too() {
        let rig = boom();
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let solver = solver(rig.clone());
        for _ in 0..100 {
            let pose = random_joints(&rig, &mut rng);
            let target = rig
                .tool_pose(&pose)
                .expect("the pose has the rig's joint count");
            let solution = solver.solve(&target, &middle(&rig)).expect("reaches");
            assert_genuine(&rig, target.position, &solution);
        }
        // Beyond the boom's stroke: refused with the residual, the boom at its end stop.
        let far = Pose::new(DVec3::new(0.5, 0.0, 0.1), DQuat::IDENTITY);
        match solver.solve(&far, &middle(&rig)) {
            Err(IkError::NotConverged {
                position_error_m, ..
            }) => assert!((position_error_m - 0.15).abs() < 1e-6, "{position_error_m}"),
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn refuses_a_seed_of_the_wrong_length() {
        let rig = limbs().remove(0);
        let target = rig
            .tool_pose(&middle(&rig))
            .expect("the middle pose has the rig's joint count");
        assert!(matches!(
            solver(rig).solve(&target, &[0.0; 3]),
            Err(IkError::InvalidSeed(_))
        ));
    }
}
