//! What the twin's sloth did, measured from its actual joint positions every cycle (a
//! [`TwinWorld`]), and the verdict against the figures. Owns the measurements and
//! the report; it must not change the twin's state or the plan.

use super::config::LimbSolver;
use super::rig::SlothRig;
use super::scenario::Scenario;
use super::walker::{GaitPlan, Stance};
use crate::twin::TwinWorld;
use glam::DVec3;
use serde::Serialize;

/// Pass thresholds (issue 6).
pub const MAX_SURFACE_ERROR_M: f64 = 0.005;
pub const MAX_SLIP_M: f64 = 0.001;
pub const MAX_IK_RESIDUAL_M: f64 = 0.001;
pub const STRAIGHT_SPEED_M_S: f64 = 0.11;
pub const SPEED_TOLERANCE_M_S: f64 = 0.02;
pub const MIN_JUDGED_CYCLES: u32 = 3;
/// Time after touchdown before a stance is judged: the twin's transport delay and servo
/// lag (12 ms and 8 ms by default) are still bringing the foot down.
pub const SETTLE_AFTER_TOUCHDOWN_S: f64 = 0.06;
/// How far past the gait's allowed head-first descent the body's forward axis may point
/// down before a run fails as a head-first descent (1 deg).
pub const HEADING_SLACK_RAD: f64 = 0.017_453_292_519_943_295;

/// One limb's measurements over the run.
#[derive(Debug, Clone, Default, Serialize)]
pub struct LimbMeasure {
    pub max_surface_error_m: f64,
    pub max_slip_m: f64,
    /// The joint of this limb furthest from its neutral (mid-range) position, how far, and
    /// its half-range (the Table 2 amplitude / 2).
    pub max_excursion_joint: String,
    pub max_excursion_deg: f64,
    pub excursion_limit_deg: f64,
    pub within_limits: bool,
}

/// The world the twin's sloth hangs in: measures every cycle.
pub struct GaitWorld {
    sloth: SlothRig,
    scenario: Scenario,
    /// Stances in plan frames, per limb.
    stances: Vec<Vec<Stance>>,
    /// Plan frames the twin's actual position trails the commands by.
    lag_frames: usize,
    settle_frames: usize,
    cycles_seen: usize,
    /// The claw tip where the current stance began, per limb (and that stance's index).
    stance_origin: Vec<Option<(usize, DVec3)>>,
    pub limbs: Vec<LimbMeasure>,
    pub min_body_clearance_m: f64,
    /// The body's actual position each cycle.
    pub body_path: Vec<DVec3>,
    /// The least height of the fore girdle over the hind one (negative: head below tail).
    pub min_head_above_tail_m: f64,
    /// The least elevation of the body's forward axis, head end (rad; negative: head down).
    pub min_heading_elevation_rad: f64,
}

impl GaitWorld {
    pub fn new(sloth: &SlothRig, scenario: &Scenario, plan: &GaitPlan, lag_frames: usize) -> Self {
        let mut stances = vec![Vec::new(); sloth.limbs.len()];
        for stance in &plan.stances {
            stances[stance.limb].push(*stance);
        }
        let limbs = sloth
            .limbs
            .iter()
            .map(|_| LimbMeasure {
                within_limits: true,
                ..LimbMeasure::default()
            })
            .collect();
        Self {
            sloth: sloth.clone(),
            scenario: scenario.clone(),
            stances,
            lag_frames,
            settle_frames: (SETTLE_AFTER_TOUCHDOWN_S / plan.period.as_secs_f64()).round() as usize,
            cycles_seen: 0,
            stance_origin: vec![None; sloth.limbs.len()],
            limbs,
            min_body_clearance_m: f64::INFINITY,
            body_path: Vec::new(),
            min_head_above_tail_m: f64::INFINITY,
            min_heading_elevation_rad: f64::INFINITY,
        }
    }

    fn measure_limb(&mut self, index: usize, frame: usize, actual: &[f64], body: &glam::DAffine3) {
        let limb = &self.sloth.limbs[index];
        let stance = self.stances[index].iter().enumerate().find(|(_, s)| {
            frame >= (s.start + self.settle_frames).max(s.settled) && frame <= s.end
        });
        let measure = &mut self.limbs[index];
        for (joint, q) in limb.chain.joints.iter().zip(&actual[limb.axes()]) {
            let middle = 0.5 * (joint.limits.lower + joint.limits.upper);
            let half = 0.5 * (joint.limits.upper - joint.limits.lower);
            let excursion = (q - middle).abs();
            if excursion.to_degrees() > measure.max_excursion_deg {
                measure.max_excursion_deg = excursion.to_degrees();
                measure.excursion_limit_deg = half.to_degrees();
                measure.max_excursion_joint = joint.name.clone();
            }
            if !joint.limits.contains(*q) {
                measure.within_limits = false;
            }
        }
        let Some((stance_index, stance)) = stance else {
            self.stance_origin[index] = None;
            return;
        };
        let tip = self.sloth.limb_tip(body, limb, actual);
        let claw = tip - stance.contact.normal * limb.claw_m;
        let cylinder = &self.scenario.terrain.cylinders[stance.contact.support];
        measure.max_surface_error_m = measure
            .max_surface_error_m
            .max(cylinder.signed_distance(claw).abs());
        match self.stance_origin[index] {
            Some((seen, origin)) if seen == stance_index => {
                measure.max_slip_m = measure.max_slip_m.max(origin.distance(tip));
            }
            _ => self.stance_origin[index] = Some((stance_index, tip)),
        }
    }
}

impl TwinWorld for GaitWorld {
    fn observe(&mut self, actual: &[f64]) {
        let count = self.cycles_seen;
        self.cycles_seen += 1;
        if actual.len() != self.sloth.dof() {
            return;
        }
        let frame = count.saturating_sub(self.lag_frames);
        let body = self.sloth.body_frame(actual);
        self.body_path.push(body.translation);
        let (hind, fore) = self.sloth.spine();
        let head_above_tail = (body.transform_point3(fore) - body.transform_point3(hind)).z;
        self.min_head_above_tail_m = self.min_head_above_tail_m.min(head_above_tail);
        let elevation = body.matrix3.x_axis.z.clamp(-1.0, 1.0).asin();
        self.min_heading_elevation_rad = self.min_heading_elevation_rad.min(elevation);
        self.min_body_clearance_m =
            self.min_body_clearance_m
                .min(self.scenario.terrain.capsule_clearance(
                    body.transform_point3(hind),
                    body.transform_point3(fore),
                    self.sloth.body_radius_m,
                ));
        for index in 0..self.sloth.limbs.len() {
            self.measure_limb(index, frame, actual, &body);
        }
    }
}

/// Per-limb figures of the report.
#[derive(Debug, Clone, Serialize)]
pub struct LimbReport {
    pub limb: String,
    pub duty_factor: f64,
    pub max_foot_to_surface_mm: f64,
    pub max_slip_mm: f64,
    pub max_bone_excursion_joint: String,
    pub max_bone_excursion_deg: f64,
    pub bone_limit_deg: f64,
}

/// The gait's verdict, as written with `--report`.
#[derive(Debug, Clone, Serialize)]
pub struct GaitReport {
    pub scenario: String,
    pub angle_deg: Option<f64>,
    pub gap_m: Option<f64>,
    /// The limb IK solver the gait was planned with (`[gait] solver`).
    pub solver: LimbSolver,
    pub passed: bool,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
    /// Why the gait stopped before its cycles (a rule), if it did.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub stopped_because: Option<String>,
    pub speed_mps: f64,
    pub cycles_judged: u32,
    pub footfall_order: Vec<String>,
    pub limbs: Vec<LimbReport>,
    pub min_body_clearance_mm: f64,
    pub max_ik_residual_mm: f64,
    pub duration_s: f64,
    /// How far the body rose (negative: descended) from the start to the end of the run.
    pub body_rise_m: f64,
    /// The least height of the head's girdle over the tail's during the run (negative:
    /// head below tail).
    pub min_head_above_tail_m: f64,
    /// The least elevation of the body's forward axis during the run (deg; negative: the
    /// head pointed down).
    pub min_heading_elevation_deg: f64,
    /// On a trunk: how far the body went around its axis (deg, counterclockwise seen from
    /// above).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub around_trunk_deg: Option<f64>,
    /// The largest commanded acceleration of any axis against its max (the positions'
    /// second difference over the period squared): at most the gait's share, 0.8.
    pub peak_acceleration_ratio: f64,
    /// The axis where it is.
    pub peak_acceleration_joint: String,
}

/// The plan's largest acceleration against its axis' max, as (ratio, axis): from the
/// second differences of the commanded positions (the central-difference velocities the
/// trajectory carries change by the mean of two of them, never more).
pub fn peak_acceleration(sloth: &SlothRig, plan: &GaitPlan) -> (f64, usize) {
    let dt = plan.period.as_secs_f64();
    let dt2 = dt * dt;
    let mut peak = (0.0, 0);
    for k in 1..plan.len().saturating_sub(1) {
        let (before, here, after) = (plan.frame(k - 1), plan.frame(k), plan.frame(k + 1));
        for (axis, joint) in sloth.streamed.joints.iter().enumerate() {
            let second = after[axis] - 2.0 * here[axis] + before[axis];
            let ratio = second.abs() / (joint.limits.max_acceleration * dt2);
            if ratio > peak.0 {
                peak = (ratio, axis);
            }
        }
    }
    peak
}

/// The angle the body's path sweeps about the first support's axis, when that is a trunk.
fn around_trunk(sloth: &SlothRig, scenario: &Scenario, path: &[DVec3]) -> Option<f64> {
    let trunk = scenario.terrain.cylinders.first()?;
    if !trunk.is_trunk(sloth.gait.trunk_tilt_rad) {
        return None;
    }
    // Counterclockwise seen from above, whichever way the trunk's axis runs.
    let axis = trunk.direction() * trunk.direction().z.signum();
    let bearing = |p: &DVec3| {
        let radial = *p - trunk.axis_point(trunk.parameter(*p));
        radial - axis * radial.dot(axis)
    };
    let swept: f64 = path
        .windows(2)
        .map(|w| {
            let (a, b) = (bearing(&w[0]), bearing(&w[1]));
            a.cross(b).dot(axis).atan2(a.dot(b))
        })
        .sum();
    Some(swept.to_degrees())
}

/// Whole cycles walked after the first (which starts from a standstill).
fn judged_cycles(plan: &GaitPlan, scenario: &Scenario) -> u32 {
    let walked = plan.cycle_starts.len().saturating_sub(1) as u32;
    walked.min(scenario.cycles).saturating_sub(1)
}

fn duty_factor(plan: &GaitPlan, limb: usize, from: usize, to: usize) -> f64 {
    let stance_frames: usize = plan
        .stances
        .iter()
        .filter(|s| s.limb == limb)
        .map(|s| s.end.min(to).saturating_sub(s.start.max(from)))
        .sum();
    stance_frames as f64 / (to - from).max(1) as f64
}

/// Mean speed along the body's actual path over the judged cycles.
fn speed(world: &GaitWorld, plan: &GaitPlan, from: usize, to: usize) -> f64 {
    let path = &world.body_path;
    let (from, to) = (
        (from + world.lag_frames).min(path.len().saturating_sub(1)),
        (to + world.lag_frames).min(path.len().saturating_sub(1)),
    );
    if to <= from {
        return 0.0;
    }
    let length: f64 = path[from..=to]
        .windows(2)
        .map(|w| w[0].distance(w[1]))
        .sum();
    length / ((to - from) as f64 * plan.period.as_secs_f64())
}

/// Judges a run: the plan's schedule and residuals, the twin's measurements.
pub fn judge(
    sloth: &SlothRig,
    scenario: &Scenario,
    plan: &GaitPlan,
    world: &GaitWorld,
    streamed_completely: bool,
) -> GaitReport {
    let cycles_judged = judged_cycles(plan, scenario);
    let cycle_start = |cycle: usize| plan.cycle_starts.get(cycle).copied().unwrap_or(0);
    let from = cycle_start(1);
    let to = cycle_start(cycles_judged as usize + 1);
    let footfall_order: Vec<String> = plan
        .touchdowns
        .iter()
        .map(|(_, limb)| sloth.limbs[*limb].name.clone())
        .collect();
    let limbs = limb_reports(sloth, plan, world, from, to);
    let speed_mps = speed(world, plan, from, to);
    let (peak_acceleration_ratio, peak_axis) = peak_acceleration(sloth, plan);
    let mut failures = run_failures(plan, streamed_completely, cycles_judged);
    failures.extend(limb_failures(&limbs, world));
    failures.extend(motion_failures(
        sloth,
        scenario,
        plan,
        world,
        &footfall_order,
        speed_mps,
    ));
    GaitReport {
        scenario: scenario.name.clone(),
        angle_deg: scenario.angle_deg,
        gap_m: scenario.gap_m,
        solver: sloth.gait.solver,
        passed: failures.is_empty(),
        reason: (!failures.is_empty()).then(|| failures.join("; ")),
        stopped_because: plan.stop_reason.as_ref().map(ToString::to_string),
        speed_mps,
        cycles_judged,
        footfall_order,
        limbs,
        min_body_clearance_mm: world.min_body_clearance_m * 1000.0,
        max_ik_residual_mm: plan.ik_residual_max_m * 1000.0,
        duration_s: plan.len().saturating_sub(1) as f64 * plan.period.as_secs_f64(),
        body_rise_m: match (world.body_path.first(), world.body_path.last()) {
            (Some(first), Some(last)) => last.z - first.z,
            _ => 0.0,
        },
        min_head_above_tail_m: world.min_head_above_tail_m,
        min_heading_elevation_deg: world.min_heading_elevation_rad.to_degrees(),
        around_trunk_deg: around_trunk(sloth, scenario, &world.body_path),
        peak_acceleration_ratio,
        peak_acceleration_joint: sloth.streamed.joints[peak_axis].name.clone(),
    }
}

/// Each limb's figures between frames `from` and `to`.
fn limb_reports(
    sloth: &SlothRig,
    plan: &GaitPlan,
    world: &GaitWorld,
    from: usize,
    to: usize,
) -> Vec<LimbReport> {
    sloth
        .limbs
        .iter()
        .enumerate()
        .map(|(index, limb)| {
            let m = &world.limbs[index];
            LimbReport {
                limb: limb.name.clone(),
                duty_factor: duty_factor(plan, index, from, to),
                max_foot_to_surface_mm: m.max_surface_error_m * 1000.0,
                max_slip_mm: m.max_slip_m * 1000.0,
                max_bone_excursion_joint: m.max_excursion_joint.clone(),
                max_bone_excursion_deg: m.max_excursion_deg,
                bone_limit_deg: m.excursion_limit_deg,
            }
        })
        .collect()
}

/// Whether the run itself went the distance: no rule stopped it, the stream completed,
/// enough whole cycles to judge.
fn run_failures(plan: &GaitPlan, streamed_completely: bool, cycles_judged: u32) -> Vec<String> {
    let mut failures = Vec::new();
    if let Some(reason) = &plan.stop_reason {
        failures.push(format!("stopped: {reason}"));
    }
    if !streamed_completely {
        failures.push("the stream did not complete".into());
    }
    if cycles_judged < MIN_JUDGED_CYCLES {
        failures.push(format!(
            "{cycles_judged} full cycles judged, fewer than {MIN_JUDGED_CYCLES}"
        ));
    }
    failures
}

/// Each limb against the thresholds: on the surface, not slipping, bones within limits.
fn limb_failures(limbs: &[LimbReport], world: &GaitWorld) -> Vec<String> {
    let mut failures = Vec::new();
    for (limb, measure) in limbs.iter().zip(&world.limbs) {
        if measure.max_surface_error_m > MAX_SURFACE_ERROR_M {
            failures.push(format!(
                "{}: foot-to-surface {:.2} mm",
                limb.limb, limb.max_foot_to_surface_mm
            ));
        }
        if measure.max_slip_m > MAX_SLIP_M {
            failures.push(format!("{}: slip {:.2} mm", limb.limb, limb.max_slip_mm));
        }
        if !measure.within_limits {
            failures.push(format!("{}: a bone left its limits", limb.limb));
        }
    }
    failures
}

/// The whole body's motion against the thresholds: clear of the branches, IK residual,
/// footfall order, no head-first descent, and on a straight branch the speed.
fn motion_failures(
    sloth: &SlothRig,
    scenario: &Scenario,
    plan: &GaitPlan,
    world: &GaitWorld,
    footfall_order: &[String],
    speed_mps: f64,
) -> Vec<String> {
    let mut failures = Vec::new();
    if world.min_body_clearance_m <= 0.0 {
        failures.push(format!(
            "body-to-branch clearance {:.1} mm",
            world.min_body_clearance_m * 1000.0
        ));
    }
    if plan.ik_residual_max_m > MAX_IK_RESIDUAL_M {
        failures.push(format!(
            "IK residual {:.2} mm",
            plan.ik_residual_max_m * 1000.0
        ));
    }
    let expected: Vec<&str> = sloth
        .gait
        .footfall_order
        .iter()
        .map(|l| sloth.limbs[*l].name.as_str())
        .collect();
    if footfall_order
        .iter()
        .enumerate()
        .any(|(i, name)| name != expected[i % expected.len()])
    {
        failures.push(format!("footfall order {}", footfall_order.join(" ")));
    }
    // The gait's own rule allows a descent of `max_descent` head first (under a branch); the
    // twin's lag and the body's averaging may add a fraction of a degree.
    let head_down_allowed = sloth.gait.max_descent_rad + HEADING_SLACK_RAD;
    if world.min_heading_elevation_rad < -head_down_allowed {
        failures.push(format!(
            "head-first descent: the body pointed {:.1} deg down, beyond {:.1} deg",
            -world.min_heading_elevation_rad.to_degrees(),
            sloth.gait.max_descent_rad.to_degrees()
        ));
    }
    if scenario.name == "straight" && (speed_mps - STRAIGHT_SPEED_M_S).abs() > SPEED_TOLERANCE_M_S {
        failures.push(format!("speed {speed_mps:.3} m/s"));
    }
    failures
}
