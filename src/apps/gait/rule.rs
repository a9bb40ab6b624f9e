//! Why a gait move is refused: every rule the placement and the walker check, as one typed
//! reason whose text the report and the CLI print. Owns the reasons' wording only; the
//! checks themselves stay with placement.rs and walker.rs.

use crate::ik::IkError;
use glam::DVec3;
use std::fmt;
use thiserror::Error;

/// The part of a swinging limb that must stay out of the supports.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SwingPart {
    /// The claw's point.
    Claw,
    /// The end of the hand or foot, beyond the claw.
    End,
}

impl fmt::Display for SwingPart {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            SwingPart::Claw => "swinging claw",
            SwingPart::End => "swinging hand or foot",
        })
    }
}

/// A point in metres, printed as `(x, y, z)` to the millimetre.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Point(pub DVec3);

impl fmt::Display for Point {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "({:.3}, {:.3}, {:.3})", self.0.x, self.0.y, self.0.z)
    }
}

/// A rule a placement or a frame of the gait breaks.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum RuleBroken {
    #[error(
        "the trace for {limb} at s = {s:.2} m meets support {support} {off_m:.3} m from its grip \
         (the support bends there)"
    )]
    TraceOffGrip {
        limb: String,
        s: f64,
        support: usize,
        off_m: f64,
    },
    #[error("the trace for {limb} at s = {s:.2} m meets support {hit} before support {support}")]
    TraceMeetsOther {
        limb: String,
        s: f64,
        hit: usize,
        support: usize,
    },
    #[error("the trace for {limb} at s = {s:.2} m finds no surface (end of support {support})")]
    TraceNoSurface {
        limb: String,
        s: f64,
        support: usize,
    },
    #[error(
        "support {support} descends {:.1} deg: head-first descent beyond {:.1} deg",
        .descent_rad.to_degrees(),
        .max_rad.to_degrees()
    )]
    HeadFirstDescent {
        support: usize,
        descent_rad: f64,
        max_rad: f64,
    },
    #[error(
        "support {support} rises {:.1} deg, {:.1} deg more than support {from}: more than {:.1} \
         deg, the body would meet the branch",
        .slope_rad.to_degrees(),
        .bend_rad.to_degrees(),
        .max_rad.to_degrees()
    )]
    TooSteepRise {
        support: usize,
        slope_rad: f64,
        bend_rad: f64,
        from: usize,
        max_rad: f64,
    },
    #[error("{limb} would land behind its pair {pair}")]
    BehindPair { limb: String, pair: String },
    #[error("{limb} would land ahead of {other}")]
    AheadOf { limb: String, other: String },
    #[error("{limb} follows to support {to} only once {other} has left support {from}")]
    FollowsTooSoon {
        limb: String,
        to: usize,
        other: String,
        from: usize,
    },
    #[error(
        "{limb} would reach {distance_m:.3} m, beyond {:.0} % of its {reach_m:.3} m",
        .share * 100.0
    )]
    OutOfReach {
        limb: String,
        distance_m: f64,
        share: f64,
        reach_m: f64,
    },
    #[error("{joint} would be {value:.4}, outside its limits [{lower:.4}, {upper:.4}]")]
    BodyOutsideLimits {
        joint: String,
        value: f64,
        lower: f64,
        upper: f64,
    },
    #[error("{limb}'s {part} would enter a branch by {:.1} mm", .depth_m * 1000.0)]
    EntersBranch {
        limb: String,
        part: SwingPart,
        depth_m: f64,
    },
    #[error("{limb} cannot reach {target} (body frame) at frame {frame}: {source}")]
    Unreachable {
        limb: String,
        target: Point,
        frame: usize,
        source: Box<IkError>,
    },
    #[error(
        "{joint} would move {step:.5} in one period, above {:.0} % of its max speed",
        .share * 100.0
    )]
    TooFast {
        joint: String,
        step: f64,
        share: f64,
    },
    #[error("the body would touch a branch (clearance {:.1} mm)", .clearance_m * 1000.0)]
    BodyTouches { clearance_m: f64 },
    #[error("no step to try for {limb}: the gait's step range is empty")]
    NoCandidates { limb: String },
    #[error("no next step for {limb}: at the max step {at_max}; at the min step {at_min}")]
    NoNextStep {
        limb: String,
        at_max: Box<RuleBroken>,
        at_min: Box<RuleBroken>,
    },
    #[error("stopped mid-motion at frame {frame}: {reason}")]
    StoppedMidMotion {
        frame: usize,
        reason: Box<RuleBroken>,
    },
}
