//! The walker: turns a scenario into the sloth's sampled joint motion, frame by frame.
//! Swings start on the footfall schedule (diagonal sequence, contact about twice swing);
//! each swing's target comes from FindNextStep, and is accepted only once the motion it
//! implies (every frame until all swinging limbs are down again) is possible: limb IK
//! within the bones' limits, axis speeds, the body clear of the branches, swinging claws
//! and the ends of swinging hands and feet outside them. A move that breaks a rule is never
//! started: the gait stops there, with the reason, after the swings under way have landed.
//! The body follows the feet (body.rs), held back where a hind foot would otherwise trail
//! out of reach, and, while it holds a trunk, moved away from the support its torso would
//! otherwise meet and, once only the hind limbs hold the trunk, brought a little closer to
//! its supports.
//!
//! Owns the gait's state and schedule; it must not stream, or measure what the twin did.

use super::body::{body_axes, body_from_feet};
use super::placement::{
    Contact, candidate_steps, check_descent, check_rules, contact_at, toward_supports,
};
use super::rig::{Girdle, SlothRig};
use super::rule::{Point, RuleBroken, SwingPart};
use super::scenario::Scenario;
use super::terrain::segment_nearest;
use crate::ik::{IkSolver, Tolerance};
use crate::rig::Pose;
use glam::{DAffine3, DQuat, DVec3};
use serde::Serialize;
use std::time::Duration;
use thiserror::Error;

#[derive(Debug, Clone, PartialEq, Error)]
pub enum WalkError {
    #[error("scenario {scenario}: the sloth cannot stand at its start: {reason}")]
    NoStart {
        scenario: String,
        reason: RuleBroken,
    },
}

/// Standstill before the first swing and after the last landing.
const SETTLE_S: f64 = 0.2;
/// Share of an axis' max speed a frame-to-frame step may use.
const SPEED_SHARE: f64 = 0.95;
/// How far a swinging claw may dip into a surface (mm-level numeric slack only).
const PENETRATION_SLACK_M: f64 = 1e-4;

/// One limb's contact from `start` to `end` (frames, inclusive).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Stance {
    pub limb: usize,
    pub start: usize,
    pub end: usize,
    /// The first frame from which the plan holds the hand or foot on its contact (after
    /// any fade-in of a correction); re-timing keeps it on the same moment of the path.
    pub settled: usize,
    pub contact: Contact,
}

/// The planned gait: joint samples at the stream period and what they mean.
#[derive(Debug, Clone)]
pub struct GaitPlan {
    pub period: Duration,
    pub dof: usize,
    /// Row-major samples of the streamed joint vector.
    pub frames: Vec<f64>,
    pub stances: Vec<Stance>,
    /// (frame, limb) of every touchdown after a swing, in time order.
    pub touchdowns: Vec<(usize, usize)>,
    /// The frame where each whole gait cycle starts, the first at the first swing, and
    /// the frame after the last whole cycle walked: frame numbers, so that re-timing the
    /// samples moves them with the events they mark.
    pub cycle_starts: Vec<usize>,
    /// Why the gait stopped before walking all its cycles.
    pub stop_reason: Option<RuleBroken>,
    pub ik_residual_max_m: f64,
    /// Worst body-to-branch gap in the plan (the twin's world measures the actual one).
    pub plan_clearance_min_m: f64,
}

impl GaitPlan {
    pub fn len(&self) -> usize {
        self.frames.len() / self.dof
    }

    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }

    pub fn frame(&self, index: usize) -> &[f64] {
        &self.frames[index * self.dof..(index + 1) * self.dof]
    }
}

#[derive(Debug, Clone, Copy)]
struct Swing {
    from: Contact,
    start: usize,
    end: usize,
}

#[derive(Debug, Clone)]
struct LimbState {
    /// The stance contact, or the swing's target while swinging.
    contact: Contact,
    swing: Option<Swing>,
}

#[derive(Debug, Clone)]
struct State {
    limbs: Vec<LimbState>,
    /// The last frame's joints (the IK's warm start and the speed check's reference).
    joints: Vec<f64>,
    has_previous: bool,
    /// The body's hold-back in the last frame (m along its forward axis).
    held_back_m: f64,
    /// How far the body was moved off its place in the last frame (world, m): away from a
    /// support its torso would meet, and toward its supports while only the hind limbs
    /// hold a trunk.
    shift: DVec3,
    /// How far a hind foot may trail behind its girdle in this step (the hold-back's limit).
    max_trail_m: f64,
    /// How far the torso is kept off the supports in this step (the clearing's margin).
    torso_margin_m: f64,
}

/// Where a limb's claw goes in one frame, before the body is placed.
#[derive(Debug, Clone, Copy)]
struct LimbTarget {
    /// The claw's point on (or between) its contacts.
    ground: DVec3,
    /// The surface normal there: the hand or foot lies along it.
    normal: DVec3,
    /// How far the claw is lifted off the supports (m).
    lift: f64,
    /// The side the supports are on, seen from the body.
    up: DVec3,
}

/// Where the body goes in one frame, and the adjustments that placed it.
#[derive(Debug, Clone, Copy)]
struct BodyPose {
    body: DAffine3,
    held_back_m: f64,
    shift: DVec3,
}

/// What one frame measured in the plan.
#[derive(Debug, Clone, Copy)]
struct FrameCheck {
    residual: f64,
    clearance: f64,
}

/// Plans and checks the gait of one scenario.
pub struct Walker<'a> {
    sloth: &'a SlothRig,
    scenario: &'a Scenario,
    /// Each limb's solver (`[gait] solver`).
    solvers: Vec<Box<dyn IkSolver + Send + Sync>>,
    /// The same solvers with room for the first frame's cold start from the neutral pose.
    cold_solvers: Vec<Box<dyn IkSolver + Send + Sync>>,
    /// Each limb's neutral pose: the middle of every joint's range.
    neutral: Vec<Vec<f64>>,
    period: Duration,
}

/// Iterations for a cold start (the first frame), where no previous frame is near.
const COLD_START_ITERATIONS: u32 = 2_000;

/// Share of a swing spent lifting (and as much lowering): the foot travels mostly while
/// lifted, and leaves and reaches its contact along the body's up, so it never sweeps
/// through a branch on its way.
const LIFT_SHARE: f64 = 0.25;

/// Share of a swing at which the hand or foot starts travelling toward its new contact
/// (and as long before the end at which it arrives): 60 % into the lift, so that it leaves
/// and reaches the contact along the body's up, clear of the branch's surface.
const TRAVEL_START: f64 = 0.6 * LIFT_SHARE;

/// The body's yaw among the streamed axes (x, y, z, yaw, ...: `rig::BODY_AXES`): the next
/// frame's yaw is unwrapped next to it.
const BODY_YAW_AXIS: usize = 3;

/// Lift over the swing, 0 to 1: up, hold, down, each change minimum-jerk.
fn swing_lift(phase: f64) -> f64 {
    min_jerk(phase / LIFT_SHARE).min(min_jerk((1.0 - phase) / LIFT_SHARE))
}

/// Share of a turning-over swing spent lifting (and as much lowering): it lowers by the
/// claw's length more than other swings, and at their pace the hand's flexion outran its
/// speed (lf_hand 0.0403 rad per period, 0.0398 allowed, parallel 0.10-0.35).
const TURN_OVER_LIFT_SHARE: f64 = 0.45;

/// Lift over a turning-over swing, 0 to 1: as `swing_lift`, over `TURN_OVER_LIFT_SHARE`.
fn turn_over_lift(phase: f64) -> f64 {
    min_jerk(phase / TURN_OVER_LIFT_SHARE).min(min_jerk((1.0 - phase) / TURN_OVER_LIFT_SHARE))
}

/// Minimum-jerk progress: zero velocity and acceleration at lift-off and touchdown.
fn min_jerk(phase: f64) -> f64 {
    let p = phase.clamp(0.0, 1.0);
    p * p * p * (10.0 - 15.0 * p + 6.0 * p * p)
}

impl<'a> Walker<'a> {
    pub fn new(sloth: &'a SlothRig, scenario: &'a Scenario, period: Duration) -> Self {
        let tolerance = Tolerance {
            position_m: sloth.gait.ik_tolerance_m,
            orientation_rad: std::f64::consts::PI,
        };
        let solvers_with = |iterations: u32| {
            sloth
                .limbs
                .iter()
                .map(|limb| {
                    sloth
                        .gait
                        .solver
                        .build(limb.chain.clone(), tolerance, iterations)
                })
                .collect()
        };
        Self {
            sloth,
            scenario,
            solvers: solvers_with(sloth.gait.ik_max_iterations),
            cold_solvers: solvers_with(COLD_START_ITERATIONS),
            neutral: sloth
                .limbs
                .iter()
                .map(|limb| {
                    limb.chain
                        .joints
                        .iter()
                        .map(|j| 0.5 * (j.limits.lower + j.limits.upper))
                        .collect()
                })
                .collect(),
            period,
        }
    }

    /// `seconds` (the gait's maths) in whole frames of the period.
    fn frames(&self, seconds: f64) -> usize {
        (seconds / self.period.as_secs_f64()).round() as usize
    }

    /// Where each limb stands at the start: staggered as in the steady gait (a limb that
    /// swings later in the cycle stands further ahead, so that every step can be the max
    /// step), each girdle's pair straddling its girdle.
    fn start_state(&self) -> Result<State, RuleBroken> {
        let gait = &self.sloth.gait;
        let order = &gait.footfall_order;
        let stagger = |index: usize| {
            let slot = order.iter().position(|l| *l == index).unwrap_or(0);
            gait.max_step_m * slot as f64 / order.len() as f64
        };
        let mut limbs = Vec::with_capacity(self.sloth.limbs.len());
        for (index, limb) in self.sloth.limbs.iter().enumerate() {
            let pair: Vec<f64> = (0..self.sloth.limbs.len())
                .filter(|other| self.sloth.limbs[*other].girdle == limb.girdle)
                .map(stagger)
                .collect();
            let centre = pair.iter().sum::<f64>() / pair.len() as f64;
            let along = if self.scenario.sideways {
                0.0
            } else {
                limb.attachment().x * self.scenario.heading_sign()
            };
            let s = self.scenario.start_s + along + stagger(index) - centre;
            let contact = contact_at(self.sloth, self.scenario, index, s)?;
            check_descent(self.sloth, self.scenario, contact.support)?;
            limbs.push(LimbState {
                contact,
                swing: None,
            });
        }
        let mut joints = vec![0.0; self.sloth.dof()];
        for (limb, neutral) in self.sloth.limbs.iter().zip(&self.neutral) {
            joints[limb.axes()].copy_from_slice(neutral);
        }
        Ok(State {
            limbs,
            joints,
            has_previous: false,
            held_back_m: 0.0,
            shift: DVec3::ZERO,
            max_trail_m: MAX_HIND_TRAIL_M,
            torso_margin_m: TORSO_MARGIN_M,
        })
    }

    /// Computes frame `k` from `state` into `state.joints`, or says which rule it breaks:
    /// where each hand or foot is, where the body goes, the limbs' IK, then the frame's checks.
    fn step(&self, k: usize, state: &mut State) -> Result<FrameCheck, RuleBroken> {
        let targets = self.swing_targets(k, state);
        let pose = self.body_pose(state, &targets);
        let mut joints = self.body_joints(state, &pose.body)?;
        let body = self.sloth.body_frame(&joints);
        let residual = self.limb_ik(k, state, &targets, &body, &mut joints)?;
        let clearance = self.frame_checks(state, &joints, &body)?;
        state.joints = joints;
        state.has_previous = true;
        state.held_back_m = pose.held_back_m;
        state.shift = pose.shift;
        Ok(FrameCheck {
            residual,
            clearance,
        })
    }

    /// Where each limb's claw is on (or between) its contacts at frame `k`.
    fn swing_targets(&self, k: usize, state: &State) -> Vec<LimbTarget> {
        state
            .limbs
            .iter()
            .enumerate()
            .map(|(index, limb)| match limb.swing {
                Some(swing) => self.swing_target(index, k, limb, &swing),
                None => LimbTarget {
                    ground: limb.contact.point,
                    normal: limb.contact.normal,
                    lift: 0.0,
                    up: limb.contact.up,
                },
            })
            .collect()
    }

    /// A swinging limb's target at frame `k`: travelling from its old contact to its new
    /// one while lifted off the supports.
    fn swing_target(&self, index: usize, k: usize, limb: &LimbState, swing: &Swing) -> LimbTarget {
        let lift_m = self.sloth.gait.swing_lift_m;
        let phase = k.saturating_sub(swing.start) as f64 / (swing.end - swing.start).max(1) as f64;
        let m = min_jerk((phase - TRAVEL_START) / (1.0 - 2.0 * TRAVEL_START));
        let up = swing.from.up.lerp(limb.contact.up, m);
        let mut normal = swing.from.normal.lerp(limb.contact.normal, m);
        let mut lift = lift_m * self.lift_share(index, swing) * swing_lift(phase);
        if turns_over(&swing.from, &limb.contact) {
            // The hand or foot turns over through the supports' side, its end lowered by
            // the claw's length more, so it passes under a branch.
            normal += up.normalize_or_zero() * (std::f64::consts::PI * m).sin();
            lift = (lift_m + self.sloth.limbs[index].claw_m) * turn_over_lift(phase);
        }
        LimbTarget {
            ground: swing.from.point.lerp(limb.contact.point, m),
            normal: normal.normalize_or(limb.contact.normal),
            lift,
            up,
        }
    }

    /// Where the body goes for `targets`: over the feet, held back from a trailing hind
    /// foot, and shifted off the supports its torso would meet.
    fn body_pose(&self, state: &State, targets: &[LimbTarget]) -> BodyPose {
        let sloth = self.sloth;
        let ground: Vec<DVec3> = targets.iter().map(|t| t.ground).collect();
        let mut body = body_from_feet(
            sloth,
            &ground,
            toward_supports(targets.iter().map(|t| t.up)),
        );
        let feet: Vec<DVec3> = targets
            .iter()
            .zip(&sloth.limbs)
            .map(|(t, limb)| t.ground + t.normal * limb.claw_m)
            .collect();
        let held_back_m = self.hold_back(state, &body, &feet);
        body.translation -= body.matrix3.x_axis * held_back_m;
        let shift = self.body_shift(state, &body);
        body.translation += shift;
        BodyPose {
            body,
            held_back_m,
            shift,
        }
    }

    /// How far the body at `body` is held back so that no hind foot (`feet`) trails out of
    /// reach, changing at most at the hold-back rate. On a trunk the body climbs along its
    /// forward axis: holding it back there fights the climb, so only between a trunk and a
    /// branch, or on branches, is it held back.
    fn hold_back(&self, state: &State, body: &DAffine3, feet: &[DVec3]) -> f64 {
        let all_on_trunk = state.limbs.iter().all(|limb| {
            self.on_trunk(&limb.contact) && limb.swing.is_none_or(|s| self.on_trunk(&s.from))
        });
        if all_on_trunk {
            return 0.0;
        }
        let held_back = trailing_excess(self.sloth, body, feet, state.max_trail_m);
        if !state.has_previous {
            return held_back;
        }
        let rate = if state.max_trail_m < MAX_HIND_TRAIL_M {
            TIGHTER_HOLD_BACK_RATE_M_S
        } else {
            HOLD_BACK_RATE_M_S
        };
        let most = rate * self.period.as_secs_f64();
        held_back.clamp(state.held_back_m - most, state.held_back_m + most)
    }

    /// How far the body at `body` moves off its place while it holds a trunk (raised while
    /// only the hind limbs do, and cleared off the supports), changing at most at the
    /// shift rate.
    fn body_shift(&self, state: &State, body: &DAffine3) -> DVec3 {
        let sloth = self.sloth;
        // Per limb: does it hold a trunk (or leave one, mid-swing)?
        let trunk_held: Vec<bool> = state
            .limbs
            .iter()
            .map(|limb| {
                self.on_trunk(&limb.contact) || limb.swing.is_some_and(|s| self.on_trunk(&s.from))
            })
            .collect();
        let mut shift = DVec3::ZERO;
        if trunk_held.contains(&true) {
            let girdle_holds = |girdle: Girdle| {
                (sloth.limbs.iter().zip(&trunk_held)).any(|(l, held)| l.girdle == girdle && *held)
            };
            // Only head first: going tail first from a branch the hind limbs lead onto the
            // trunk, and the fore limbs never hold it alone.
            if !self.scenario.tail_first
                && !girdle_holds(Girdle::Fore)
                && girdle_holds(Girdle::Hind)
            {
                shift = body.matrix3.z_axis * HIND_CLIMB_RAISE_M;
            }
            let mut raised = *body;
            raised.translation += shift;
            shift += self.torso_clearing(&raised, state.torso_margin_m);
        }
        if state.has_previous {
            let most = SHIFT_RATE_M_S * self.period.as_secs_f64();
            let change = shift - state.shift;
            if change.length() > most {
                shift = state.shift + change * (most / change.length());
            }
        }
        shift
    }

    /// The joint vector with the body's virtual axes for `body` (the limbs' from the last
    /// frame), refused when a body axis would leave its limits.
    fn body_joints(&self, state: &State, body: &DAffine3) -> Result<Vec<f64>, RuleBroken> {
        let previous_yaw = if state.has_previous {
            state.joints[BODY_YAW_AXIS]
        } else {
            0.0
        };
        let axes = body_axes(body, previous_yaw);
        for (joint, value) in self.sloth.body.joints.iter().zip(axes) {
            if !joint.limits.contains(value) {
                return Err(RuleBroken::BodyOutsideLimits {
                    joint: joint.name.clone(),
                    value,
                    lower: joint.limits.lower,
                    upper: joint.limits.upper,
                });
            }
        }
        let mut joints = state.joints.clone();
        joints[..axes.len()].copy_from_slice(&axes);
        Ok(joints)
    }

    /// Solves every limb for its target from the body at `body` into `joints`, refusing a
    /// swinging claw or hand inside a support; returns the worst residual (m).
    fn limb_ik(
        &self,
        k: usize,
        state: &State,
        targets: &[LimbTarget],
        body: &DAffine3,
        joints: &mut [f64],
    ) -> Result<f64, RuleBroken> {
        let sloth = self.sloth;
        let up = body.matrix3.z_axis;
        let to_body = body.inverse();
        let mut residual: f64 = 0.0;
        for (index, (limb, target)) in sloth.limbs.iter().zip(targets).enumerate() {
            // Under a branch, straight down, away from it: from a contact on the branch's
            // side this never cuts into it, and adds no sideways reach. On a trunk, straight
            // off its surface: "down" there is toward the body, and would fold a leading hind
            // limb against its girdle.
            let away = if self.on_trunk(&state.limbs[index].contact) {
                target.normal
            } else {
                -up
            };
            let claw = target.ground + away * target.lift;
            let target_world = claw + target.normal * limb.claw_m;
            if target.lift > 0.0 {
                self.keep_out(claw, &limb.name, SwingPart::Claw)?;
                self.keep_out(target_world, &limb.name, SwingPart::End)?;
            }
            let pose = Pose::new(to_body.transform_point3(target_world), DQuat::IDENTITY);
            let seed = &state.joints[limb.axes()];
            let solver = if state.has_previous {
                &self.solvers[index]
            } else {
                &self.cold_solvers[index]
            };
            // CCD can stall against a limit from the previous frame's pose: once, start
            // again from the neutral pose (the speed check refuses a jump).
            let solution = solver
                .solve(&pose, seed)
                .or_else(|_| self.cold_solvers[index].solve(&pose, &self.neutral[index]))
                .map_err(|source| RuleBroken::Unreachable {
                    limb: limb.name.clone(),
                    target: Point(pose.position),
                    frame: k,
                    source: Box::new(source),
                })?;
            joints[limb.axes()].copy_from_slice(&solution.joints);
            residual = residual.max(sloth.limb_tip(body, limb, joints).distance(target_world));
        }
        Ok(residual)
    }

    /// The frame's own checks: every axis within its speed of the last frame, and the body
    /// clear of the branches; returns that clearance (m).
    fn frame_checks(
        &self,
        state: &State,
        joints: &[f64],
        body: &DAffine3,
    ) -> Result<f64, RuleBroken> {
        if state.has_previous {
            self.check_speeds(&state.joints, joints)?;
        }
        let (hind, fore) = self.sloth.spine();
        let clearance = self.scenario.terrain.capsule_clearance(
            body.transform_point3(hind),
            body.transform_point3(fore),
            self.sloth.body_radius_m,
        );
        if clearance <= 0.0 {
            return Err(RuleBroken::BodyTouches {
                clearance_m: clearance,
            });
        }
        Ok(clearance)
    }

    /// Refuses a swinging `point` (`part` of `limb`) inside a support, beyond numeric slack.
    fn keep_out(&self, point: DVec3, limb: &str, part: SwingPart) -> Result<(), RuleBroken> {
        let gap = self.scenario.terrain.clearance(point);
        if gap < -PENETRATION_SLACK_M {
            return Err(RuleBroken::EntersBranch {
                limb: limb.to_owned(),
                part,
                depth_m: -gap,
            });
        }
        Ok(())
    }

    /// How far (world, m) the body at `body` must move for its torso to clear every support
    /// by `margin_m` (`TORSO_MARGIN_M`, less in a step's retry): reaching from a trunk for a branch over its back, the mean of the
    /// feet brings the shoulders up against the branch (the seed moves the head aside
    /// there). It moves straight away from the nearest support (from the nearest point of
    /// its axis to the spine's), within the body's own plane (no sideways part): under a
    /// level branch that is down the trunk, under a steep one mostly away from the bark.
    /// Going tail first it moves along its own length instead. Zero when the torso is clear
    /// already.
    fn torso_clearing(&self, body: &DAffine3, margin_m: f64) -> DVec3 {
        let (hind, fore) = self.sloth.spine();
        let (hind, fore) = (body.transform_point3(hind), body.transform_point3(fore));
        let radius = self.sloth.body_radius_m;
        let terrain = &self.scenario.terrain;
        let nearest = terrain.cylinders.iter().min_by(|a, b| {
            a.capsule_clearance(hind, fore, radius)
                .total_cmp(&b.capsule_clearance(hind, fore, radius))
        });
        let Some(nearest) = nearest else {
            return DVec3::ZERO;
        };
        if nearest.capsule_clearance(hind, fore, radius) >= margin_m {
            return DVec3::ZERO;
        }
        let (on_spine, on_axis) = segment_nearest(hind, fore, nearest.from, nearest.to);
        let away = on_spine - on_axis;
        let away = if self.scenario.tail_first {
            // Tail first, the support it nears is the trunk its tail reaches for: it moves
            // along its own length, away from it (moving away across its length carried the
            // hind foot still on the branch out of reach).
            let forward = body.matrix3.x_axis;
            forward * away.dot(forward).signum()
        } else {
            let side = body.matrix3.y_axis;
            (away - side * away.dot(side)).normalize_or(-body.matrix3.z_axis)
        };
        let clearance = |shift: f64| {
            terrain.capsule_clearance(hind + away * shift, fore + away * shift, radius)
        };
        let (mut low, mut high) = (0.0, MAX_TORSO_SHIFT_M);
        if clearance(high) < margin_m {
            return away * high;
        }
        for _ in 0..40 {
            let middle = 0.5 * (low + high);
            if clearance(middle) >= margin_m {
                high = middle;
            } else {
                low = middle;
            }
        }
        away * high
    }

    /// Share of the swing lift for `limb`'s swing: a hind foot leaving a trunk grips it at
    /// its side, where the surface normal points mostly sideways, so its lift carries the
    /// foot out sideways (past the hindlimb's reach while its body reaches for a branch).
    fn lift_share(&self, limb: usize, swing: &Swing) -> f64 {
        if self.sloth.limbs[limb].girdle == Girdle::Hind && self.on_trunk(&swing.from) {
            TRUNK_HIND_LIFT_SHARE
        } else {
            1.0
        }
    }

    fn has_trunk(&self) -> bool {
        let tilt = self.sloth.gait.trunk_tilt_rad;
        self.scenario
            .terrain
            .cylinders
            .iter()
            .any(|c| c.is_trunk(tilt))
    }

    fn on_trunk(&self, contact: &Contact) -> bool {
        self.scenario.terrain.cylinders[contact.support].is_trunk(self.sloth.gait.trunk_tilt_rad)
    }

    fn check_speeds(&self, previous: &[f64], next: &[f64]) -> Result<(), RuleBroken> {
        for ((joint, a), b) in self.sloth.streamed.joints.iter().zip(previous).zip(next) {
            let max_step = SPEED_SHARE * joint.limits.max_speed * self.period.as_secs_f64();
            if (b - a).abs() > max_step {
                return Err(RuleBroken::TooFast {
                    joint: joint.name.clone(),
                    step: (b - a).abs(),
                    share: SPEED_SHARE,
                });
            }
        }
        Ok(())
    }

    /// Runs frames from `k` with no new swings until every limb is down: proof that the
    /// gait can stop cleanly after the swings now under way.
    fn look_ahead(&self, k: usize, state: &State) -> Result<(), RuleBroken> {
        let mut trial = state.clone();
        let last = trial
            .limbs
            .iter()
            .filter_map(|l| l.swing.map(|s| s.end))
            .max()
            .unwrap_or(k);
        for frame in k..=last {
            self.step(frame, &mut trial)?;
            land(&mut trial, frame);
        }
        Ok(())
    }

    /// FindNextStep for `limb` lifting off at frame `k`: the first candidate (max step
    /// first, then closer) that passes the placement rules and whose motion is possible.
    /// When none is, the same candidates again with the body held back further (each of
    /// `TRAIL_LIMITS_M` in turn, for this step only; the hold-back's rate limit makes the
    /// change continuous), then, in a scene with a trunk, with the torso kept less far off
    /// the supports (each of `TIGHTER_TORSO_MARGINS_M`, for this step only; the shift's rate
    /// limit makes that continuous too). The reason given is the usual limit's.
    fn next_step(
        &self,
        limb: usize,
        k: usize,
        state: &State,
        swing_frames: usize,
    ) -> Result<State, RuleBroken> {
        let mut usual_reason = None;
        let limb_name = &self.sloth.limbs[limb].name;
        let variations = TRAIL_LIMITS_M
            .iter()
            .map(|limit| (*limit, TORSO_MARGIN_M))
            .chain(
                TIGHTER_TORSO_MARGINS_M
                    .iter()
                    .filter(|_| self.has_trunk())
                    .map(|margin| (MAX_HIND_TRAIL_M, *margin)),
            );
        for (limit, margin) in variations {
            let mut trial = state.clone();
            trial.max_trail_m = limit;
            trial.torso_margin_m = margin;
            match self.placement_for(limb, k, &trial, swing_frames) {
                Ok(next) => return Ok(next),
                Err(reason) => {
                    usual_reason.get_or_insert(reason);
                }
            }
        }
        Err(usual_reason.unwrap_or_else(|| RuleBroken::NoCandidates {
            limb: limb_name.clone(),
        }))
    }

    /// FindNextStep's candidates for `limb` with the body held back as `state` says.
    fn placement_for(
        &self,
        limb: usize,
        k: usize,
        state: &State,
        swing_frames: usize,
    ) -> Result<State, RuleBroken> {
        let current = state.limbs[limb].contact;
        let planned: Vec<Contact> = state.limbs.iter().map(|l| l.contact).collect();
        let mut first_reason = None;
        let mut last_reason = None;
        for s in candidate_steps(self.sloth, current.s) {
            let verdict = contact_at(self.sloth, self.scenario, limb, s)
                .and_then(|contact| {
                    check_rules(self.sloth, self.scenario, limb, &contact, &planned)?;
                    Ok(contact)
                })
                .and_then(|contact| {
                    let mut next = state.clone();
                    next.limbs[limb] = LimbState {
                        contact,
                        swing: Some(Swing {
                            from: current,
                            start: k,
                            end: k + swing_frames,
                        }),
                    };
                    self.look_ahead(k, &next)?;
                    Ok(next)
                });
            match verdict {
                Ok(next) => return Ok(next),
                Err(reason) => {
                    first_reason.get_or_insert_with(|| reason.clone());
                    last_reason = Some(reason);
                }
            }
        }
        let limb = self.sloth.limbs[limb].name.clone();
        match (first_reason, last_reason) {
            (Some(at_max), Some(at_min)) => Err(RuleBroken::NoNextStep {
                limb,
                at_max: Box::new(at_max),
                at_min: Box::new(at_min),
            }),
            _ => Err(RuleBroken::NoCandidates { limb }),
        }
    }

    /// Walks the scenario's cycles (or until a rule stops the gait) and returns the plan.
    pub fn plan(&self) -> Result<GaitPlan, WalkError> {
        self.walk(usize::MAX).map(|(plan, _)| plan)
    }

    /// The walker's state just before frame `frame` (or at the end, if the gait ends
    /// sooner): where a frame-by-frame consumer (the bench, a live view) picks up.
    pub fn state_before(&self, frame: usize) -> Result<GaitState, WalkError> {
        self.walk(frame).map(|(plan, state)| GaitState {
            next_frame: plan.len(),
            state,
        })
    }

    /// One frame of the whole gait (swing interpolation, body pose, IK of every limb),
    /// advancing `state`; no new swings start. Returns the streamed joint vector.
    pub fn step_frame<'s>(&self, state: &'s mut GaitState) -> Result<&'s [f64], RuleBroken> {
        self.step(state.next_frame, &mut state.state)?;
        land(&mut state.state, state.next_frame);
        state.next_frame += 1;
        Ok(&state.state.joints)
    }

    fn walk(&self, stop_before: usize) -> Result<(GaitPlan, State), WalkError> {
        let mut state = self.start_state().map_err(|reason| WalkError::NoStart {
            scenario: self.scenario.name.clone(),
            reason,
        })?;
        let schedule = self.schedule();
        let mut plan = self.empty_plan();
        let mut stance_start = vec![0usize; self.sloth.limbs.len()];
        let mut k = 0;
        loop {
            let swinging = state.limbs.iter().any(|l| l.swing.is_some());
            let walking = plan.stop_reason.is_none() && k < schedule.last_start;
            if (!walking && !swinging) || k >= stop_before {
                break;
            }
            if let Some(limb) = schedule.lifting_at(k).filter(|_| walking) {
                match self.next_step(limb, k, &state, schedule.swing_frames) {
                    Ok(next) => {
                        plan.stances.push(Stance {
                            limb,
                            start: stance_start[limb],
                            end: k,
                            settled: stance_start[limb],
                            contact: state.limbs[limb].contact,
                        });
                        state = next;
                    }
                    Err(reason) => plan.stop_reason = Some(reason),
                }
            }
            if !self.record_frame(k, &mut state, &mut plan) {
                break;
            }
            for (limb, landed) in land(&mut state, k).into_iter().enumerate() {
                if landed {
                    plan.touchdowns.push((k, limb));
                    stance_start[limb] = k;
                }
            }
            k += 1;
        }
        if k < stop_before && !plan.is_empty() {
            // Hold the final pose a moment: the stream ends at rest, every foot down.
            let last_frame = plan.frame(plan.len() - 1).to_vec();
            for _ in 0..self.frames(SETTLE_S) {
                plan.frames.extend_from_slice(&last_frame);
            }
        }
        finish_plan(&mut plan, &state, &stance_start, &schedule);
        Ok((plan, state))
    }

    /// The footfall schedule in frames at this walker's period.
    fn schedule(&self) -> Schedule {
        let gait = &self.sloth.gait;
        let cycle_frames = self.frames(gait.cycle_s());
        let first_swing = self.frames(SETTLE_S);
        let order = gait.footfall_order.clone();
        let slot_frames = (0..order.len())
            .map(|slot| (slot as f64 * cycle_frames as f64 / order.len() as f64).round() as usize)
            .collect();
        Schedule {
            cycle_frames,
            swing_frames: self.frames(gait.swing_s()).max(1),
            first_swing,
            last_start: first_swing + self.scenario.cycles as usize * cycle_frames,
            order,
            slot_frames,
        }
    }

    fn empty_plan(&self) -> GaitPlan {
        GaitPlan {
            period: self.period,
            dof: self.sloth.dof(),
            frames: Vec::new(),
            stances: Vec::new(),
            touchdowns: Vec::new(),
            cycle_starts: Vec::new(),
            stop_reason: None,
            ik_residual_max_m: 0.0,
            plan_clearance_min_m: f64::INFINITY,
        }
    }

    /// Steps frame `k` and adds it to `plan`; false (and the reason in the plan) when the
    /// frame breaks a rule.
    fn record_frame(&self, k: usize, state: &mut State, plan: &mut GaitPlan) -> bool {
        match self.step(k, state) {
            Ok(check) => {
                plan.ik_residual_max_m = plan.ik_residual_max_m.max(check.residual);
                plan.plan_clearance_min_m = plan.plan_clearance_min_m.min(check.clearance);
                plan.frames.extend_from_slice(&state.joints);
                true
            }
            Err(reason) => {
                // Only reachable if the look-ahead and the walk disagree: stop here.
                plan.stop_reason = Some(RuleBroken::StoppedMidMotion {
                    frame: k,
                    reason: Box::new(reason),
                });
                false
            }
        }
    }
}

/// When each limb lifts off, in frames.
struct Schedule {
    cycle_frames: usize,
    swing_frames: usize,
    first_swing: usize,
    /// No swing starts at or after this frame (the scenario's cycles are walked).
    last_start: usize,
    /// The limbs in footfall order, one per slot of the cycle.
    order: Vec<usize>,
    /// Each slot's frame within the cycle.
    slot_frames: Vec<usize>,
}

impl Schedule {
    /// The limb whose swing starts at frame `k`, if any.
    fn lifting_at(&self, k: usize) -> Option<usize> {
        if k < self.first_swing || self.cycle_frames == 0 {
            return None;
        }
        let into_cycle = (k - self.first_swing) % self.cycle_frames;
        let slot = self.slot_frames.iter().position(|f| *f == into_cycle)?;
        Some(self.order[slot])
    }
}

/// Marks the whole cycles walked and closes every limb's last stance at the plan's end.
fn finish_plan(plan: &mut GaitPlan, state: &State, stance_start: &[usize], schedule: &Schedule) {
    plan.cycle_starts = (0..)
        .map(|cycle| schedule.first_swing + cycle * schedule.cycle_frames)
        .take_while(|frame| schedule.cycle_frames > 0 && *frame <= plan.len())
        .collect();
    let last = plan.len().saturating_sub(1);
    for (limb, start) in stance_start.iter().copied().enumerate() {
        if state.limbs[limb].swing.is_none() {
            plan.stances.push(Stance {
                limb,
                start,
                end: last,
                settled: start,
                contact: state.limbs[limb].contact,
            });
        }
    }
}

/// How far a hind foot may trail behind its girdle, along the body's forward axis. At
/// stance height the hindlimb's rear reach within its bones' limits ends about 0.106 m
/// behind the hip, less with the foot nearer the midline (measured: a straight stance ends
/// at 0.1065 m; turns of 110-160 deg stopped at 0.104-0.107 m, CCD 0.3-0.7 mm short). Any
/// of 0.102-0.105 m passes every required turn and height change (docs/gait.md).
const MAX_HIND_TRAIL_M: f64 = 0.104;

/// The hind feet's trail limits a step tries, in order: the usual one, then tighter ones
/// (4 mm at a time) for a step that finds no placement with it. Straddling parallel
/// branches 25 cm apart, the body turns toward the new branch, which brings a trailing hind
/// foot in toward the body's midline, where the hindlimb reaches less far back (lh 0.6 mm
/// out of reach at 0.104 m behind its hip, 0.058 m inside it); 0.100 m lets it reach. One
/// tighter limit for every step loses the 160 deg height change (docs/gait.md).
const TRAIL_LIMITS_M: [f64; 5] = [MAX_HIND_TRAIL_M, 0.100, 0.096, 0.092, 0.088];

/// How far the body at `body` must be held back (against its forward axis) so that no
/// hind foot, at `feet` (the ends of the hands and feet, world), trails more than
/// `max_trail_m` behind its girdle: the mean of the feet would otherwise carry a
/// stance hind foot out of reach while a fore limb swings ahead. Zero when none trails.
fn trailing_excess(sloth: &SlothRig, body: &DAffine3, feet: &[DVec3], max_trail_m: f64) -> f64 {
    let to_body = body.inverse();
    sloth
        .limbs
        .iter()
        .zip(feet)
        .filter(|(limb, _)| limb.girdle == Girdle::Hind)
        .map(|(limb, foot)| limb.attachment().x - to_body.transform_point3(*foot).x - max_trail_m)
        .fold(0.0, f64::max)
}

/// How fast the hold-back may change: when the most trailing hind foot swings, the
/// hold-back would otherwise let the body go at the foot's speed.
const HOLD_BACK_RATE_M_S: f64 = 0.1;

/// How fast the hold-back may change in a step that tightened the trail limit: at the usual
/// rate the body, carried forward by a fore limb's swing, outruns the tighter limit (at
/// 0.1 m/s parallel 0.30 and 0.35 stop on a hind limb's reach, at 0.2 m/s 0.35 does;
/// docs/gait.md). Within the body's 0.5 m/s, which the speed check judges as always.
const TIGHTER_HOLD_BACK_RATE_M_S: f64 = 0.3;

/// Whether a swing from `from` to `to` turns its hand or foot over, from one side of a
/// branch to the side facing the other way (opposite normals): lerped, the normal would
/// flip the hand or foot's end through the claw point in one frame.
fn turns_over(from: &Contact, to: &Contact) -> bool {
    from.normal.dot(to.normal) < -0.5
}

/// The torso's least gap to the supports while the sloth straddles a trunk and a branch.
const TORSO_MARGIN_M: f64 = 0.02;
/// The torso's margins a step tries, in order, once every trail limit has failed with the
/// usual margin, in a scene with a trunk: going tail first from a level branch down a trunk
/// the clearing moves the body along its length away from the bark, which stretches the
/// fore limbs still on the branch toward the trunk until a fore hand's IK slides along its
/// limits (lh's step at 90 deg: lf_hand 0.040-0.083 rad in one period); 10 mm less of
/// clearing lets it through (docs/gait.md).
const TIGHTER_TORSO_MARGINS_M: [f64; 2] = [0.015, 0.010];
/// How fast the body's shift off its place (clearing, raise) may change.
const SHIFT_RATE_M_S: f64 = 0.1;
/// How much closer to its supports the body hangs once the fore limbs have left a trunk
/// and a hind limb still holds it (ours, after the seed's "Offset Back" of the rear while
/// the hind limbs climb onto the branch): the hind feet, still on the bark below the
/// branch, are otherwise at the deep edge of their reach.
const HIND_CLIMB_RAISE_M: f64 = 0.0075;
/// Share of the swing lift a hind foot leaving a trunk uses (`Walker::lift_share`).
const TRUNK_HIND_LIFT_SHARE: f64 = 0.5;
/// The farthest the body moves to keep that gap (a bound for the search).
const MAX_TORSO_SHIFT_M: f64 = 0.15;

/// The walker's state between two frames.
#[derive(Debug, Clone)]
pub struct GaitState {
    next_frame: usize,
    state: State,
}

/// Ends the swings that finish at frame `k`; says which limbs landed.
fn land(state: &mut State, k: usize) -> Vec<bool> {
    state
        .limbs
        .iter_mut()
        .map(|limb| {
            let landed = limb.swing.is_some_and(|s| s.end <= k);
            if landed {
                limb.swing = None;
            }
            landed
        })
        .collect()
}
