//! Jerk-limited timing of a joint path (a program's moves, issue 29): the path is followed
//! by one rest-to-rest S-curve in its length (rsruckig, one axis: jerk, acceleration and
//! speed each capped), so every axis' speed, acceleration and jerk are its share of the
//! path's. The caps are the tightest any piece of the path allows (each axis' scaled limit
//! over its share of the piece's direction, the speed times the step's `speed`, the
//! acceleration and jerk times the move's share: less for a move blended at a zone); the
//! samples are then checked against every axis' scaled speed, acceleration and jerk, and
//! the whole move slowed down until they pass (the bends of a polyline cost acceleration
//! and jerk the caps do not see).
//!
//! Owns the S-curve, the sampling on the polyline and that check. Must not change the path
//! (every sample lies on it, the last at its end, at rest) nor clamp: a path whose samples
//! cannot be brought within the limits fails with [`PlanError::OverLimits`].

use super::path::JointPath;
use super::plan::{AxisLimits, PlanError, Samples, snap_to_limits};
use crate::rig::Rig;
use rsruckig::prelude::{
    DataArrayOrVec, DurationDiscretization, InputParameter, Ruckig, RuckigResult,
    ThrowErrorHandler, Trajectory as Profile,
};
use std::time::Duration;

/// Share of each axis' (scaled) acceleration and jerk a move at rest at both ends takes
/// along its path; the rest is kept for what the path's own bending costs at speed (the
/// joint paths of straight tool lines are curved), as `path.rs` keeps a quarter of the
/// acceleration.
pub(crate) const REST_TO_REST_SHARE: f64 = 0.75;

/// The share a move that is blended into its neighbour at a zone takes: half, so that the
/// two moves of a corner (never more than two overlap) add up within each axis' limit at
/// any phase of their S-curves. With more, a corner where an axis goes on the same way
/// would break the jerk limit wherever the end of one move's deceleration met the start
/// of the next's acceleration, and the overlap would shrink to nothing.
pub(crate) const BLENDED_SHARE: f64 = 0.5;

/// How often a move is slowed down before it is refused. A polyline's bends cost
/// acceleration and jerk in proportion to its speed rather than its square or cube, so the
/// slowdowns below (which assume the square and cube) may take several rounds to cure them.
const MAX_SLOWDOWNS: u32 = 24;

/// Extra factor on each slowdown so that rounding cannot keep a move a hair over a limit.
const SLOWDOWN_MARGIN: f64 = 1.001;

/// The jerk-limited timing of one move of a plan, ending at waypoint `waypoint`.
pub(crate) struct SmoothTiming<'a> {
    pub rig: &'a Rig,
    pub period: Duration,
    pub limits: &'a AxisLimits,
    pub waypoint: usize,
    /// Share of each axis' acceleration and jerk the S-curve takes: [`REST_TO_REST_SHARE`]
    /// or [`BLENDED_SHARE`].
    pub share: f64,
}

/// Path speed, acceleration and jerk (in path length per second, ^2, ^3) of an S-curve.
#[derive(Debug, Clone, Copy)]
struct Caps {
    speed: f64,
    acceleration: f64,
    jerk: f64,
}

impl Caps {
    /// The same profile `slowdown` times slower.
    fn slower(self, slowdown: f64) -> Caps {
        Caps {
            speed: self.speed / slowdown,
            acceleration: self.acceleration / slowdown.powi(2),
            jerk: self.jerk / slowdown.powi(3),
        }
    }
}

/// The worst overshoot of a sampled move: the slowdown that would cure it (at most 1 when
/// the samples keep within every limit) and the axis and limit it is on.
struct Excess {
    slowdown: f64,
    axis: usize,
    limit: &'static str,
}

impl SmoothTiming<'_> {
    /// The samples of `path` (after its first node, the last at its end, at rest) along an
    /// S-curve within every axis' scaled speed, acceleration and jerk. `path` must have two
    /// nodes or more; its parameter must be its joint-space length (each piece's direction
    /// a unit vector), as a program's moves build it.
    pub(crate) fn rows(
        &self,
        path: &JointPath,
        samples: &Samples,
    ) -> Result<Vec<Vec<f64>>, PlanError> {
        let caps = self.caps(path);
        let start = &path.nodes()[0].joints;
        let mut slowdown = 1.0;
        let mut attempts = 0;
        loop {
            let rows = self.sample(path, caps.slower(slowdown), samples)?;
            let excess = self.excess(start, &rows);
            attempts += 1;
            if excess.slowdown <= 1.0 {
                return Ok(rows);
            }
            if attempts == MAX_SLOWDOWNS {
                return Err(PlanError::OverLimits {
                    waypoint: self.waypoint,
                    joint: self.rig.joints[excess.axis].name.clone(),
                    ratio: excess.slowdown,
                    limit: excess.limit,
                });
            }
            slowdown *= excess.slowdown * SLOWDOWN_MARGIN;
        }
    }

    /// The path's caps: per piece, each axis' limit over its share of the piece's
    /// direction; the tightest piece's.
    fn caps(&self, path: &JointPath) -> Caps {
        let allowed = |direction: &[f64], limits: &[f64]| {
            direction
                .iter()
                .zip(limits)
                .filter(|(d, _)| **d != 0.0)
                .map(|(d, limit)| limit / d.abs())
                .fold(f64::INFINITY, f64::min)
        };
        let mut caps = Caps {
            speed: f64::INFINITY,
            acceleration: f64::INFINITY,
            jerk: f64::INFINITY,
        };
        for piece in 0..path.nodes().len() - 1 {
            let direction = path.direction(piece);
            let share = path.share(piece + 1);
            caps.speed = caps
                .speed
                .min(share * allowed(&direction, &self.limits.speed));
            caps.acceleration = caps
                .acceleration
                .min(self.share * allowed(&direction, &self.limits.acceleration));
            caps.jerk = caps
                .jerk
                .min(self.share * allowed(&direction, &self.limits.jerk));
        }
        caps
    }

    /// The S-curve from 0 to the path's length under `caps`, sampled on the path every
    /// period (whole periods: the last sample is the path's end).
    fn sample(
        &self,
        path: &JointPath,
        caps: Caps,
        samples: &Samples,
    ) -> Result<Vec<Vec<f64>>, PlanError> {
        let nodes = path.nodes();
        let length = nodes[nodes.len() - 1].u - nodes[0].u;
        let profile = self.profile(length, caps)?;
        let dt = self.period.as_secs_f64();
        // Discrete durations are whole periods up to rounding.
        let periods = ((profile.get_duration() / dt).round() as usize).max(1);
        samples.ensure_room(periods)?;
        let mut position = DataArrayOrVec::<f64, 0>::new(Some(1), 0.0);
        let mut rows = Vec::with_capacity(periods);
        let mut cursor = 0;
        for k in 1..periods {
            let mut section = None;
            profile.at_time(
                k as f64 * dt,
                &mut Some(&mut position),
                &mut None,
                &mut None,
                &mut None,
                &mut section,
            );
            // The profile's rounding may put a hair outside the path's ends.
            let u = nodes[0].u + position[0].clamp(0.0, length);
            while cursor + 2 < nodes.len() && nodes[cursor + 1].u <= u {
                cursor += 1;
            }
            let (a, b) = (&nodes[cursor], &nodes[cursor + 1]);
            let along = ((u - a.u) / (b.u - a.u)).clamp(0.0, 1.0);
            let mut joints: Vec<f64> = a
                .joints
                .iter()
                .zip(&b.joints)
                .map(|(qa, qb)| qa + (qb - qa) * along)
                .collect();
            snap_to_limits(self.rig, &mut joints);
            rows.push(joints);
        }
        rows.push(path.end().to_vec());
        Ok(rows)
    }

    /// rsruckig's time-optimal rest-to-rest profile from 0 to `length` under `caps`.
    fn profile(&self, length: f64, caps: Caps) -> Result<Profile<0>, PlanError> {
        let failed = |message: String| PlanError::Profile {
            waypoint: self.waypoint,
            message,
        };
        let one = |value: f64| DataArrayOrVec::Heap(vec![value]);
        let mut input = InputParameter::<0>::new(Some(1));
        // Whole periods: the last sample is then the path's end itself, at rest.
        input.duration_discretization = DurationDiscretization::Discrete;
        input.current_position = one(0.0);
        input.target_position = one(length);
        input.max_velocity = one(caps.speed);
        input.max_acceleration = one(caps.acceleration);
        input.max_jerk = one(caps.jerk);
        let mut otg = Ruckig::<0, ThrowErrorHandler>::new(Some(1), self.period.as_secs_f64());
        let mut profile = Profile::<0>::new(Some(1));
        match otg.calculate(&input, &mut profile) {
            Ok(RuckigResult::Working | RuckigResult::Finished) => {}
            Ok(other) => {
                let code = other as i32;
                return Err(failed(format!("the profile generator's result {code}")));
            }
            Err(e) => return Err(failed(e.to_string())),
        }
        let duration = profile.get_duration();
        if !duration.is_finite() {
            return Err(failed(format!("duration {duration} s")));
        }
        Ok(profile)
    }

    /// How far the samples' own speed (step / period), acceleration (second difference /
    /// period^2) and jerk (third difference / period^3) go past the scaled limits, the
    /// move at rest before its start and after its end.
    fn excess(&self, start: &[f64], rows: &[Vec<f64>]) -> Excess {
        let dt = self.period.as_secs_f64();
        let end = &rows[rows.len() - 1];
        let mut positions: Vec<&[f64]> = vec![start, start, start];
        positions.extend(rows.iter().map(Vec::as_slice));
        positions.extend([end.as_slice(), end.as_slice()]);
        let mut worst = Excess {
            slowdown: 0.0,
            axis: 0,
            limit: "speed",
        };
        for w in positions.windows(4) {
            for axis in 0..start.len() {
                let [speed, acceleration, jerk] = differences(w, axis, dt);
                let ratios = [
                    (speed / self.limits.speed[axis], "speed"),
                    (
                        (acceleration / self.limits.acceleration[axis]).sqrt(),
                        "acceleration",
                    ),
                    ((jerk / self.limits.jerk[axis]).cbrt(), "jerk"),
                ];
                for (slowdown, limit) in ratios {
                    if slowdown > worst.slowdown {
                        worst = Excess {
                            slowdown,
                            axis,
                            limit,
                        };
                    }
                }
            }
        }
        worst
    }
}

/// `axis`' speed, acceleration and jerk (magnitudes) over four consecutive samples `w`,
/// `dt` apart: the last step, the last second difference and the third difference.
pub(crate) fn differences(w: &[&[f64]], axis: usize, dt: f64) -> [f64; 3] {
    let [a, b, c, d] = [w[0][axis], w[1][axis], w[2][axis], w[3][axis]];
    [
        (d - c).abs() / dt,
        (d - 2.0 * c + b).abs() / (dt * dt),
        (d - 3.0 * c + 3.0 * b - a).abs() / (dt * dt * dt),
    ]
}
