//! Smoothing the walker's joint samples before they are re-timed within the axes'
//! accelerations (`pipeline::retime_plan`). The walker solves each frame's limbs by IK from
//! the frame before; the solver moves the hands and feet's last joints first, so they swing
//! across their range and stop at a limit within a few frames (a commanded 10-18 x their
//! max acceleration), and the body follows the feet's mean, whose corners are sharp where a
//! foot lands. Re-timing those spikes alone would slow the walk to a crawl around each;
//! after this filter the samples ask at most about 1.8 x, which re-timing absorbs in brief
//! slow-downs.
//!
//! Owns that filter only: the same moving averages on every axis at once (so a stance
//! foot, held still by all its axes together, stays where it was up to second-order
//! terms), which keeps every sample inside the limits and every step within max speed (an
//! average of in-limit values and steps), then each stance's hold on its contact. It must
//! not change the walker's schedule, and it does not depend on the axes' accelerations:
//! the same samples for any, so the geometry the judge measures is the re-timing's input.

use super::rig::SlothRig;
use super::walker::GaitPlan;
use glam::{DMat3, DVec3};
use std::time::Duration;

/// The moving average every frame gets: 60 ms, three times (a 180 ms bell). Wider smears
/// a limb's lift-off and touchdown into its stance (the twin judges slip from 60 ms after
/// touchdown to lift-off): at three passes of 84 ms the straight branch's stances slipped
/// 0.90 mm of the 1 mm allowed, at 60 ms 0.77 mm (docs/gait.md, "Acceleration").
const BASE_WIDTH_S: f64 = 0.06;
const BASE_PASSES: usize = 3;

/// Smooths `plan`'s frames in place, then brings every stance hand or foot back onto its
/// planned place. The local passes of more averaging where an axis still asked more than
/// its share, tried before re-timing, are gone: they depended on the accelerations, and on
/// the sloth's own ones they widened the stance holds' failures on transfer-to-trunk
/// (slip 2-3 mm; docs/gait.md, "Acceleration").
pub fn smooth_plan(plan: &mut GaitPlan, sloth: &SlothRig) {
    let width = odd_frames(BASE_WIDTH_S, plan.period);
    for _ in 0..BASE_PASSES {
        plan.frames = moving_average(&plan.frames, plan.dof, width);
    }
    hold_stances(plan, sloth);
    // Each stance is held on its contact once its correction has faded in.
    let fade = frames(HOLD_FADE_S, plan.period).max(1);
    for stance in &mut plan.stances {
        stance.settled = stance.settled.max((stance.start + fade).min(stance.end));
    }
}

/// `seconds` (the smoothing's maths) in whole frames of `period`.
fn frames(seconds: f64, period: Duration) -> usize {
    (seconds / period.as_secs_f64()).round() as usize
}

/// `seconds` as a whole, odd number of frames (at least 1), so the average is centred.
fn odd_frames(seconds: f64, period: Duration) -> usize {
    let frames = frames(seconds, period);
    frames.max(1) | 1
}

/// The centred moving average of `width` (odd) frames on every axis, the first and last
/// frames repeated beyond the ends (the gait starts and ends at rest). Each value is kept
/// within its window's least and greatest, which an average is, up to rounding: so no
/// rounding can carry a value at a limit past it.
fn moving_average(frames: &[f64], dof: usize, width: usize) -> Vec<f64> {
    let len = frames.len() / dof;
    let half = (width / 2) as isize;
    let mut out = vec![0.0; frames.len()];
    for axis in 0..dof {
        let at = |k: isize| frames[(k.clamp(0, len as isize - 1) as usize) * dof + axis];
        for k in 0..len as isize {
            let (mut sum, mut low, mut high) = (0.0, f64::INFINITY, f64::NEG_INFINITY);
            for j in k - half..=k + half {
                let value = at(j);
                sum += value;
                low = low.min(value);
                high = high.max(value);
            }
            out[k as usize * dof + axis] = (sum / width as f64).clamp(low, high);
        }
    }
    out
}

/// Frames over which a stance's correction fades in after touchdown and out after lift-off:
/// the 60 ms the twin's judge leaves after touchdown (`metrics::SETTLE_AFTER_TOUCHDOWN_S`).
const HOLD_FADE_S: f64 = 0.06;
/// ... and over which it fades out after lift-off: longer, since nothing is judged there
/// and a correction of up to a few hundredths of a radian must not fade faster than the
/// joint may accelerate.
const HOLD_FADE_OUT_S: f64 = 0.2;
/// Damping of the least-squares correction (m): keeps it small near a limb's singular,
/// stretched poses, where an undamped step would be large.
const HOLD_DAMPING_M: f64 = 0.01;
/// Gauss-Newton steps per frame and limb: the smoothing moves a stance foot by at most a
/// few millimetres, which two steps bring back to within microns.
const HOLD_STEPS: usize = 2;
/// Finite-difference step for the limb's Jacobian (rad).
const JACOBIAN_STEP_RAD: f64 = 1e-6;

/// Averaging every axis the same way keeps a stance hand or foot still only to first
/// order: where a neighbouring limb lifts off or lands, or the body turns a corner, it
/// moves by up to a millimetre. Each stance limb's own joints are moved back so its hand or
/// foot is on its contact, where the walker aimed it, by damped least squares from the
/// smoothed joints: a smooth function of them, so it adds no sharp corner. The correction
/// fades in over the first `HOLD_FADE_S` of a stance (which the judge does not judge) and
/// out over as long after lift-off (the hand or foot is lifting away). A joint the
/// correction would take past a limit keeps the share of it that stays inside.
fn hold_stances(plan: &mut GaitPlan, sloth: &SlothRig) {
    let fade = frames(HOLD_FADE_S, plan.period).max(1);
    let fade_out = frames(HOLD_FADE_OUT_S, plan.period).max(1);
    let dof = plan.dof;
    for stance in &plan.stances {
        let limb = &sloth.limbs[stance.limb];
        let last = (stance.end + fade_out).min(plan.len().saturating_sub(1));
        // After lift-off the hand or foot swings: the correction it had at lift-off fades.
        let mut at_lift_off = vec![0.0; limb.axes().len()];
        for k in stance.start..=last {
            let frame = &mut plan.frames[k * dof..(k + 1) * dof];
            let before: Vec<f64> = frame[limb.axes()].to_vec();
            let (weight, correction) = if k <= stance.end {
                let goal = stance.contact.point + stance.contact.normal * limb.claw_m;
                for _ in 0..HOLD_STEPS {
                    correct_towards(sloth, stance.limb, frame, goal);
                }
                let correction: Vec<f64> = limb
                    .axes()
                    .zip(&before)
                    .map(|(axis, b)| frame[axis] - b)
                    .collect();
                at_lift_off.clone_from(&correction);
                let weight = fade_in((k - stance.start) as f64 / fade as f64);
                (weight, correction)
            } else {
                let weight = 1.0 - fade_in((k - stance.end) as f64 / fade_out as f64);
                (weight, at_lift_off.clone())
            };
            // The largest share of the correction that keeps every joint inside its limits
            // (a continuous function of the joints, unlike dropping it).
            let share = limb
                .axes()
                .zip(&before)
                .zip(&correction)
                .map(|((axis, b), c)| {
                    let limits = sloth.streamed.joints[axis].limits;
                    let room = if *c > 0.0 {
                        limits.upper - b
                    } else {
                        limits.lower - b
                    };
                    if (weight * c).abs() > room.abs() {
                        room / (weight * c)
                    } else {
                        1.0
                    }
                })
                .fold(1.0, f64::min)
                .clamp(0.0, 1.0);
            for ((axis, b), c) in limb.axes().zip(&before).zip(&correction) {
                let limits = sloth.streamed.joints[axis].limits;
                frame[axis] =
                    (b + share * weight * c).clamp(limits.lower.min(*b), limits.upper.max(*b));
            }
        }
    }
}

/// Minimum-jerk fade, 0 to 1.
fn fade_in(phase: f64) -> f64 {
    let p = phase.clamp(0.0, 1.0);
    p * p * p * (10.0 - 15.0 * p + 6.0 * p * p)
}

/// One damped Gauss-Newton step of limb `index`'s joints in `frame` toward `goal` (world).
fn correct_towards(sloth: &SlothRig, index: usize, frame: &mut [f64], goal: DVec3) {
    let limb = &sloth.limbs[index];
    let body = sloth.body_frame(frame);
    let tip = sloth.limb_tip(&body, limb, frame);
    let error = goal - tip;
    let columns: Vec<DVec3> = limb
        .axes()
        .map(|axis| {
            let saved = frame[axis];
            frame[axis] = saved + JACOBIAN_STEP_RAD;
            let moved = sloth.limb_tip(&body, limb, frame);
            frame[axis] = saved;
            (moved - tip) / JACOBIAN_STEP_RAD
        })
        .collect();
    // J J^T + damping^2 I, 3 x 3; the step is J^T (J J^T + d^2 I)^-1 e.
    let mut jjt = DMat3::from_diagonal(DVec3::splat(HOLD_DAMPING_M * HOLD_DAMPING_M));
    for c in &columns {
        jjt += DMat3::from_cols(*c * c.x, *c * c.y, *c * c.z);
    }
    let solved = jjt.inverse() * error;
    for (axis, c) in limb.axes().zip(&columns) {
        frame[axis] += c.dot(solved);
    }
}
