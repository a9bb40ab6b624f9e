//! Foot placement, the seed's FindNextStep: where on which support a limb may put its
//! hand or foot next. Owns the contact geometry (a trace toward the correct side of the
//! branch, the surface point and its normal) and the placement rules; it must not move
//! the body or solve IK (the walker tries a placement and judges the motion).

use super::body::{WORLD_UP, body_from_feet};
use super::rig::{Girdle, SlothRig};
use super::rule::RuleBroken;
use super::scenario::Scenario;
use glam::DVec3;

/// A hand or foot on a support: the claw's point on the surface.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Contact {
    pub point: DVec3,
    /// Outward surface normal: the claw lies along it, the hand or foot beyond it.
    pub normal: DVec3,
    pub support: usize,
    /// Route distance the contact was found at.
    pub s: f64,
    /// The side the supports are on, seen from the body, there (the body's z leans to it).
    pub up: DVec3,
}

/// How far outside the expected surface the placement trace starts.
const TRACE_START_M: f64 = 0.03;
/// On a trunk, the farthest a grip may lie from the axis sideways, as a share of the radius
/// (the rest of the half-circle faces away from the body).
const TRUNK_GRIP_SHARE: f64 = 0.9;
/// Share of a limb's reach a placement may use: a fully stretched limb has no room left
/// for the body's motion during the stance.
const USABLE_REACH: f64 = 0.95;

/// The contact of a limb on `side` at route distance `s`: trace from outside toward the
/// expected support, from that limb's side, and take the first surface hit. A hit on
/// another support, or no hit (past the end of the branch), is refused with the reason.
///
/// On a branch the hand or foot grips the branch's side (the thesis's "surface + thickness
/// / 2"). A trunk is wider than the girdles: each hand or foot grips its near half in line
/// with its girdle, on its own side, traced from the body toward the trunk.
pub fn contact_at(
    sloth: &SlothRig,
    scenario: &Scenario,
    limb: usize,
    s: f64,
) -> Result<Contact, RuleBroken> {
    let limb = &sloth.limbs[limb];
    let leg = scenario.route.leg(s);
    let support = match limb.side {
        super::rig::Side::Left => leg.left,
        super::rig::Side::Right => leg.right,
    };
    let cylinder = &scenario.terrain.cylinders[support];
    let heading = cylinder.direction() * scenario.heading_sign();
    // Side-stepping, the route turns the sloth at a fixed height: each limb grips at its
    // girdle's height; otherwise the route runs along the support, girdles included.
    let along = if scenario.sideways {
        leg.origin + heading * limb.attachment().x
    } else {
        scenario.route.point(s)
    };
    let axis_point = cylinder.axis_point(cylinder.parameter(along));
    let up = scenario.route.up(s);
    let mut outward = up.cross(heading).normalize_or(DVec3::Y) * limb.side.sign();
    if leg.left != leg.right {
        // Straddling two supports, each hand or foot grips the side of its support that
        // faces the other: the hind feet then stand the gap - 8 cm apart, not gap + 8 cm,
        // which the hindlimbs' 27 cm cannot span beyond a gap of 30 cm (docs/gait.md).
        outward = -outward;
    }
    let (expected, inward) = if cylinder.is_trunk(sloth.gait.trunk_tilt_rad) {
        let lateral = limb
            .attachment()
            .y
            .abs()
            .min(TRUNK_GRIP_SHARE * cylinder.radius);
        let depth = (cylinder.radius.powi(2) - lateral.powi(2)).sqrt();
        (axis_point + outward * lateral - up * depth, up)
    } else {
        (axis_point + outward * cylinder.radius, -outward)
    };
    let start = expected - inward * (limb.claw_m + TRACE_START_M);
    match scenario.terrain.trace(start, inward) {
        Some(hit) if hit.support == support && hit.point.distance(expected) < 1e-6 => Ok(Contact {
            point: hit.point,
            normal: hit.normal,
            support,
            s,
            up,
        }),
        Some(hit) if hit.support == support => Err(RuleBroken::TraceOffGrip {
            limb: limb.name.clone(),
            s,
            support,
            off_m: hit.point.distance(expected),
        }),
        Some(hit) => Err(RuleBroken::TraceMeetsOther {
            limb: limb.name.clone(),
            s,
            hit: hit.support,
            support,
        }),
        None => Err(RuleBroken::TraceNoSurface {
            limb: limb.name.clone(),
            s,
            support,
        }),
    }
}

/// The side the supports are on, seen from the body, for a set of contacts: the mean of
/// their own.
pub fn toward_supports(ups: impl Iterator<Item = DVec3>) -> DVec3 {
    ups.sum::<DVec3>().normalize_or(WORLD_UP)
}

/// The slope a support presents to the head: going tail first, the head points against the
/// travel.
fn head_slope(scenario: &Scenario, support: usize) -> f64 {
    scenario.terrain.cylinders[support].slope() * scenario.heading_sign()
}

/// Refuses a support the sloth would hang on head down beyond the gait's max descent (no
/// head-first descent, seed 004 after Mendel [9]).
pub fn check_descent(
    sloth: &SlothRig,
    scenario: &Scenario,
    support: usize,
) -> Result<(), RuleBroken> {
    let slope = head_slope(scenario, support);
    let max_descent = sloth.gait.max_descent_rad;
    if -slope > max_descent {
        return Err(RuleBroken::HeadFirstDescent {
            support,
            descent_rad: -slope,
            max_rad: max_descent,
        });
    }
    Ok(())
}

/// Checks a candidate contact for `limb` against the rules, given where every limb is
/// (or will be, for swinging limbs): the support's slope, never behind the paired limb,
/// hind limbs never ahead of a fore limb nor leaving a support a fore limb of their side is
/// still on, and within reach from where the body will be.
pub fn check_rules(
    sloth: &SlothRig,
    scenario: &Scenario,
    limb: usize,
    candidate: &Contact,
    planned: &[Contact],
) -> Result<(), RuleBroken> {
    let this = &sloth.limbs[limb];
    let gait = &sloth.gait;
    let cylinder = &scenario.terrain.cylinders[candidate.support];
    let slope = head_slope(scenario, candidate.support);
    // The girdle that follows: the hind one, or the fore one going down a trunk tail first.
    let trailing = if scenario.tail_first {
        Girdle::Fore
    } else {
        Girdle::Hind
    };
    check_descent(sloth, scenario, candidate.support)?;
    if !cylinder.is_trunk(gait.trunk_tilt_rad) {
        // The thesis's limit is on the bend up from the support the limb leaves (its
        // branch-to-branch height changes); from a trunk, a rising branch is a bend down.
        let bend_up = slope - head_slope(scenario, planned[limb].support);
        if bend_up > gait.max_rise_rad + 1e-9 {
            return Err(RuleBroken::TooSteepRise {
                support: candidate.support,
                slope_rad: slope,
                bend_rad: bend_up,
                from: planned[limb].support,
                max_rad: gait.max_rise_rad,
            });
        }
    }
    for (other, (limb_other, contact)) in sloth.limbs.iter().zip(planned).enumerate() {
        if other == limb {
            continue;
        }
        let same_girdle = limb_other.girdle == this.girdle;
        if same_girdle && candidate.s < contact.s {
            return Err(RuleBroken::BehindPair {
                limb: this.name.clone(),
                pair: limb_other.name.clone(),
            });
        }
        if !scenario.sideways && this.girdle == trailing && limb_other.girdle != trailing {
            if candidate.s > contact.s {
                return Err(RuleBroken::AheadOf {
                    limb: this.name.clone(),
                    other: limb_other.name.clone(),
                });
            }
            let current = planned[limb].support;
            // Off a trunk the hind limbs follow only once no fore limb is still on it (seed
            // 004's Transfer to Branch); between branches, once the fore limb of their side
            // has left.
            let leaving_trunk = scenario.terrain.cylinders[current].is_trunk(gait.trunk_tilt_rad);
            if (limb_other.side == this.side || leaving_trunk)
                && candidate.support != current
                && contact.support == current
            {
                return Err(RuleBroken::FollowsTooSoon {
                    limb: this.name.clone(),
                    to: candidate.support,
                    other: limb_other.name.clone(),
                    from: current,
                });
            }
        }
    }
    check_reach(sloth, limb, candidate, planned)
}

/// Refuses a candidate contact beyond the limb's usable reach from where the body will be
/// (over every limb's planned contact, `limb`'s at `candidate`).
fn check_reach(
    sloth: &SlothRig,
    limb: usize,
    candidate: &Contact,
    planned: &[Contact],
) -> Result<(), RuleBroken> {
    let this = &sloth.limbs[limb];
    let mut feet: Vec<DVec3> = planned.iter().map(|c| c.point).collect();
    feet[limb] = candidate.point;
    let mut ups: Vec<DVec3> = planned.iter().map(|c| c.up).collect();
    ups[limb] = candidate.up;
    let body = body_from_feet(sloth, &feet, toward_supports(ups.into_iter()));
    let girdle = body.transform_point3(this.attachment());
    let tip = candidate.point + candidate.normal * this.claw_m;
    let distance = girdle.distance(tip);
    if distance > USABLE_REACH * this.reach_m {
        return Err(RuleBroken::OutOfReach {
            limb: this.name.clone(),
            distance_m: distance,
            share: USABLE_REACH,
            reach_m: this.reach_m,
        });
    }
    Ok(())
}

/// The route distances FindNextStep tries for a limb at `current`: the max step first,
/// then 1 cm (the retry step) closer each time, down to the min step.
pub fn candidate_steps(sloth: &SlothRig, current: f64) -> impl Iterator<Item = f64> {
    let gait = &sloth.gait;
    let tries = ((gait.max_step_m - gait.min_step_m) / gait.retry_step_m + 1e-9).floor() as usize;
    let (max, retry) = (gait.max_step_m, gait.retry_step_m);
    (0..=tries).map(move |i| current + max - retry * i as f64)
}
