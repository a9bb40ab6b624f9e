//! Reshaping a trajectory in time: resampling it at another period and time scale (a
//! replayed log at the stream's own rate, `--speed`), and ending it at rest with a stop ramp
//! within the axes' accelerations (a log that ends with the axes moving).
//!
//! Owns only these two constructions; neither checks the result against the rig's limits.
//! That stays `validate`'s job, which every caller must run on what these return. Must not
//! talk to links or controllers.

use super::{Trajectory, TrajectoryError};
use crate::rig::Rig;
use std::time::Duration;

/// Two periods (times a time scale) this close count as the same: the samples are then
/// taken verbatim, bit for bit, rather than interpolated (a replay at its own rate must
/// send the very values that were streamed).
const SAME_PERIOD: f64 = 1e-12;

/// The longest stop ramp built, in samples: 10 minutes at 1 kHz. Only a trajectory whose
/// last velocity is far beyond any axis speed would need more, and `validate` refuses that
/// one anyway; the cap keeps a crafted input from exhausting memory.
const MAX_RAMP_SAMPLES: usize = 600_000;

/// `trajectory` as seen at `speed` x its own pace, sampled every `period`. Samples are
/// the cubic Hermite interpolation of the positions and velocities around each instant (C1:
/// the positions and velocities of the source are honoured at every source sample); the
/// velocities scale by the time factor. The time grid is stretched by less than half a
/// period over the whole trajectory so that its last sample is the source's last sample.
/// When `period` x `speed` is the source's period, positions are taken verbatim.
pub fn resample(
    trajectory: &Trajectory,
    period: Duration,
    speed: f64,
) -> Result<Trajectory, TrajectoryError> {
    if !(speed.is_finite() && speed > 0.0) {
        return Err(TrajectoryError::BadTimeScale { speed });
    }
    let period_s = period.as_secs_f64();
    let source_period = trajectory.period.as_secs_f64();
    let samples = trajectory.len();
    if (period_s * speed - source_period).abs() <= SAME_PERIOD * source_period || samples < 2 {
        let positions = (0..samples).flat_map(|k| trajectory.position(k).to_vec());
        let velocities = (0..samples).flat_map(|k| {
            let moving = trajectory.velocity(k);
            (0..moving.len()).map(move |axis| moving[axis] * speed)
        });
        return Trajectory::new(
            trajectory.rig.clone(),
            trajectory.joint_names.clone(),
            period,
            positions.collect(),
            velocities.collect(),
        );
    }
    let duration = trajectory.duration_s();
    let cycles = ((duration / (period_s * speed)).round() as usize).max(1);
    // The time factor actually used, once the grid is stretched onto the last sample.
    let factor = duration / (cycles as f64 * period_s);
    let dof = trajectory.dof();
    let mut positions = Vec::with_capacity((cycles + 1) * dof);
    let mut velocities = Vec::with_capacity((cycles + 1) * dof);
    for k in 0..=cycles {
        let t = duration * k as f64 / cycles as f64;
        let (index, s) = segment(t, source_period, samples);
        for axis in 0..dof {
            let (p, v) = hermite(trajectory, source_period, index, s, axis);
            positions.push(p);
            velocities.push(v * factor);
        }
    }
    Trajectory::new(
        trajectory.rig.clone(),
        trajectory.joint_names.clone(),
        period,
        positions,
        velocities,
    )
}

/// The source segment holding time `t`, and where in it (0..=1).
fn segment(t: f64, period_s: f64, samples: usize) -> (usize, f64) {
    let last_segment = samples - 2;
    let index = ((t / period_s).floor().max(0.0) as usize).min(last_segment);
    let s = ((t - index as f64 * period_s) / period_s).clamp(0.0, 1.0);
    (index, s)
}

/// Position and time derivative of `axis` at fraction `s` of segment `index`, `h` the
/// trajectory's period in seconds.
fn hermite(trajectory: &Trajectory, h: f64, index: usize, s: f64, axis: usize) -> (f64, f64) {
    let (p0, p1) = (
        trajectory.position(index)[axis],
        trajectory.position(index + 1)[axis],
    );
    let (m0, m1) = (
        trajectory.velocity(index)[axis] * h,
        trajectory.velocity(index + 1)[axis] * h,
    );
    let (s2, s3) = (s * s, s * s * s);
    let position = (2.0 * s3 - 3.0 * s2 + 1.0) * p0
        + (s3 - 2.0 * s2 + s) * m0
        + (-2.0 * s3 + 3.0 * s2) * p1
        + (s3 - s2) * m1;
    let slope = (6.0 * s2 - 6.0 * s) * p0
        + (3.0 * s2 - 4.0 * s + 1.0) * m0
        + (-6.0 * s2 + 6.0 * s) * p1
        + (3.0 * s2 - 2.0 * s) * m1;
    (position, slope / h)
}

/// `trajectory` followed by a stop ramp that brings every axis to rest: the last step and
/// velocity shrink linearly to zero, all axes together (a straight line in joint space,
/// continuing the last motion), over as many samples as the slowest axis needs to stay
/// within `accel_share` of its max acceleration in both of `validate`'s measures (the
/// positions' second difference and the velocity change). Returns the new trajectory and
/// the number of samples the ramp added (0 when the trajectory ends so near rest that
/// holding its last sample is within those accelerations).
pub fn ramp_to_rest(
    trajectory: &Trajectory,
    rig: &Rig,
    accel_share: f64,
) -> Result<(Trajectory, usize), TrajectoryError> {
    let len = trajectory.len();
    let period = trajectory.period.as_secs_f64();
    if len == 0 || rig.dof() != trajectory.dof() {
        return Ok((trajectory.clone(), 0));
    }
    let last = trajectory.position(len - 1).to_vec();
    let velocity = trajectory.velocity(len - 1).to_vec();
    let step: Vec<f64> = if len > 1 {
        let before = trajectory.position(len - 2);
        last.iter().zip(before.iter()).map(|(a, b)| a - b).collect()
    } else {
        velocity.iter().map(|v| v * period).collect()
    };
    let mut needed = 0.0_f64;
    for ((joint, d), v) in rig.joints.iter().zip(&step).zip(&velocity) {
        let a = accel_share * joint.limits.max_acceleration;
        needed = needed.max(d.abs() / (a * period * period));
        needed = needed.max(v.abs() / (a * period));
    }
    // Within one sample's acceleration of rest already: holding the last sample from the
    // next cycle on is itself within every axis' acceleration.
    if needed <= 1.0 {
        return Ok((trajectory.clone(), 0));
    }
    if !needed.is_finite() || needed > MAX_RAMP_SAMPLES as f64 {
        return Err(TrajectoryError::RampTooLong {
            samples: needed,
            max: MAX_RAMP_SAMPLES,
        });
    }
    let count = needed.ceil() as usize;
    let dof = trajectory.dof();
    let mut positions = Vec::with_capacity((count + 1) * dof);
    let mut velocities = Vec::with_capacity((count + 1) * dof);
    positions.extend_from_slice(&last);
    velocities.extend_from_slice(&velocity);
    let mut at = last;
    for j in 1..=count {
        let share = 1.0 - j as f64 / count as f64;
        for axis in 0..dof {
            at[axis] += step[axis] * share;
            positions.push(at[axis]);
            velocities.push(velocity[axis] * share);
        }
    }
    let ramp = Trajectory::new(
        trajectory.rig.clone(),
        trajectory.joint_names.clone(),
        trajectory.period,
        positions,
        velocities,
    )?;
    let mut ended = trajectory.clone();
    ended.append(&ramp);
    Ok((ended, count))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn line(period_s: f64, samples: usize, speed: f64) -> Trajectory {
        let positions = (0..samples).map(|k| k as f64 * period_s * speed).collect();
        Trajectory::new(
            "r".into(),
            vec!["a".into()],
            Duration::from_secs_f64(period_s),
            positions,
            vec![speed; samples],
        )
        .expect("the line is a valid trajectory")
    }

    #[test]
    fn a_constant_speed_line_resamples_onto_the_same_line() {
        let source = line(0.01, 101, 0.5);
        let resampled =
            resample(&source, Duration::from_millis(4), 1.0).expect("the line resamples");
        assert_eq!(resampled.len(), 251);
        for k in 0..resampled.len() {
            let expected = k as f64 * 0.004 * 0.5;
            assert!((resampled.position(k)[0] - expected).abs() < 1e-12, "{k}");
            assert!((resampled.velocity(k)[0] - 0.5).abs() < 1e-9, "{k}");
        }
    }

    #[test]
    fn half_speed_takes_twice_the_samples_at_half_the_velocity() {
        let source = line(0.004, 101, 0.5);
        let slow = resample(&source, Duration::from_millis(4), 0.5).expect("the line resamples");
        assert_eq!(slow.len(), 201);
        assert!((slow.velocity(100)[0] - 0.25).abs() < 1e-9);
        assert_eq!(slow.position(200), source.position(100));
    }

    #[test]
    fn the_same_period_is_taken_verbatim() {
        let source = line(0.004, 11, 0.3);
        let same = resample(&source, Duration::from_millis(4), 1.0).expect("the line resamples");
        assert_eq!(same, source);
    }
}
