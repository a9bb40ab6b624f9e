//! The world around the twin's body: what it touches, paints or stands on.
//!
//! A world sees the twin's actual joint positions once per controller cycle, after the servo
//! model has moved them: measurements such as paint coverage, collisions or foot contact are
//! made from what the twin did, never from what was planned. A world must not change the
//! twin's state or talk to the link.

use std::sync::{Arc, Mutex, PoisonError};

/// Something that watches the twin's actual positions, one call per controller cycle.
pub trait TwinWorld: Send {
    fn observe(&mut self, actual: &[f64]);
}

/// A world shared with whoever reads its measurements (a report, the live view).
pub type SharedWorld<W> = Arc<Mutex<W>>;

impl<W: TwinWorld> TwinWorld for Arc<Mutex<W>> {
    fn observe(&mut self, actual: &[f64]) {
        // A reader that panicked holding the lock leaves the measurements as they were.
        self.lock()
            .unwrap_or_else(PoisonError::into_inner)
            .observe(actual);
    }
}

/// A world only a view watches (the tool's trace the live view draws): an observation that
/// would wait for its reader is skipped, so the twin's cycle, which may run on the shared
/// real-time executor, never waits for a view's thread (a reader preempted while holding
/// the lock would hold the cycle for milliseconds). A measuring world (paint) must not be
/// wrapped: it must see every cycle.
pub struct ViewOnly<W>(pub Arc<Mutex<W>>);

impl<W: TwinWorld> TwinWorld for ViewOnly<W> {
    fn observe(&mut self, actual: &[f64]) {
        match self.0.try_lock() {
            Ok(mut world) => world.observe(actual),
            Err(std::sync::TryLockError::Poisoned(world)) => world.into_inner().observe(actual),
            Err(std::sync::TryLockError::WouldBlock) => {}
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rig::{Joint, JointKind, JointLimits, Rig};
    use crate::twin::{Twin, TwinSettings};
    use glam::{DAffine3, DVec3};

    struct Trace(Vec<Vec<f64>>);

    impl TwinWorld for Trace {
        fn observe(&mut self, actual: &[f64]) {
            self.0.push(actual.to_vec());
        }
    }

    fn one_axis_rig() -> Rig {
        Rig {
            name: "slide".into(),
            base_frame: "base".into(),
            tool_frame: "tool".into(),
            joints: vec![Joint {
                name: "x".into(),
                kind: JointKind::Prismatic,
                origin: DAffine3::IDENTITY,
                axis: DVec3::X,
                limits: JointLimits {
                    lower: -1.0,
                    upper: 1.0,
                    max_speed: 1.0,
                    max_acceleration: 10.0,
                },
            }],
            tool: DAffine3::IDENTITY,
            bodies: Vec::new(),
            allowed_pairs: Vec::new(),
        }
    }

    #[test]
    fn the_world_sees_every_cycle_of_actual_positions() {
        let trace = Arc::new(Mutex::new(Trace(Vec::new())));
        let mut twin = Twin::new(&one_axis_rig(), TwinSettings::default(), &[0.25])
            .expect("the one-axis twin starts")
            .with_world(Box::new(trace.clone()));
        let mut reported = Vec::new();
        for _ in 0..3 {
            reported.push(twin.tick().positions.as_slice().to_vec());
        }
        assert_eq!(
            trace.lock().expect("the trace lock is not poisoned").0,
            reported
        );
    }
}
