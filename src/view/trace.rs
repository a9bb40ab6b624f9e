//! The tool's trace on a wall: a twin world that turns every cycle where the tool touches
//! the wall (within [`CONTACT_TOLERANCE_M`] of its plane) into a stroke of paint, from the
//! twin's actual positions. Runs inside the twin's cycle, so it never allocates there: its
//! queue is reserved up front and strokes beyond it are counted, not kept. It must not change
//! the twin's state.
//! Its queue is reserved only once a wall is set: a job without one (most cells of a
//! many-cell daemon) pays nothing for it.

use crate::rig::Rig;
use crate::scene::{PaintQuad, Point, WallView};
use crate::twin::TwinWorld;
use glam::DVec3;

/// How close to the wall plane the tool counts as touching it (m): a few servo-lag
/// millimetres either side of a figure planned exactly on the plane.
pub const CONTACT_TOLERANCE_M: f64 = 0.003;
/// Width of the stroke the tool leaves (m).
pub const STROKE_WIDTH_M: f64 = 0.008;
/// Shortest stroke recorded (m): slower motion extends the current stroke instead.
const MIN_STROKE_M: f64 = 0.002;
/// Strokes waiting for the view; more are counted in [`ToolTrace::dropped`].
const QUEUE_CAPACITY: usize = 16_384;

#[derive(Debug, Clone, Copy)]
struct Plane {
    wall: usize,
    point: DVec3,
    /// Unit normal.
    normal: DVec3,
}

pub struct ToolTrace {
    rig: Rig,
    plane: Option<Plane>,
    last_contact: Option<DVec3>,
    pending: Vec<PaintQuad>,
    dropped: u64,
}

impl ToolTrace {
    pub fn new(rig: Rig) -> Self {
        ToolTrace {
            rig,
            plane: None,
            last_contact: None,
            pending: Vec::new(),
            dropped: 0,
        }
    }

    /// The wall (its index in the scene, and its outline) the tool may touch from now on.
    pub fn set_wall(&mut self, wall: Option<(usize, &WallView)>) {
        self.plane = wall.and_then(|(index, view)| {
            let [a, b, c, _] = view.corners.map(DVec3::from_array);
            let normal = (b - a).cross(c - a).try_normalize()?;
            Some(Plane {
                wall: index,
                point: a,
                normal,
            })
        });
        self.last_contact = None;
        if self.plane.is_some() {
            // Here, before the job streams: strokes come only with a wall, in the cycle.
            let room = QUEUE_CAPACITY.saturating_sub(self.pending.len());
            self.pending.reserve_exact(room);
        }
    }

    /// Strokes since the previous call.
    pub fn drain(&mut self) -> Vec<PaintQuad> {
        let mut drained = Vec::with_capacity(self.pending.len());
        drained.append(&mut self.pending);
        drained
    }

    /// Strokes lost because the view did not drain them in time.
    pub fn dropped(&self) -> u64 {
        self.dropped
    }

    fn stroke(&mut self, plane: Plane, from: DVec3, to: DVec3) {
        let along = (to - from).reject_from_normalized(plane.normal);
        let Some(direction) = along.try_normalize() else {
            return;
        };
        let half = STROKE_WIDTH_M / 2.0;
        let side = plane.normal.cross(direction) * half;
        // Round-ish caps: each stroke reaches half a width past its ends, so strokes join.
        let (start, end) = (from - direction * half, to + direction * half);
        let quad: [Point; 4] =
            [start - side, start + side, end + side, end - side].map(|p| p.to_array());
        // Never beyond what set_wall reserved: a push in the cycle must not allocate.
        if self.pending.len() < self.pending.capacity().min(QUEUE_CAPACITY) {
            self.pending.push(PaintQuad {
                wall: plane.wall,
                quad,
            });
        } else {
            self.dropped += 1;
        }
    }
}

impl TwinWorld for ToolTrace {
    fn observe(&mut self, actual: &[f64]) {
        let Some(plane) = self.plane else {
            return;
        };
        let Ok(tool) = self.rig.forward(actual) else {
            return;
        };
        let tip = tool.translation;
        let distance = (tip - plane.point).dot(plane.normal);
        if distance.abs() > CONTACT_TOLERANCE_M {
            self.last_contact = None;
            return;
        }
        let on_wall = tip - plane.normal * distance;
        match self.last_contact {
            Some(last) if last.distance(on_wall) >= MIN_STROKE_M => {
                self.stroke(plane, last, on_wall);
                self.last_contact = Some(on_wall);
            }
            Some(_) => {}
            None => self.last_contact = Some(on_wall),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rig::{Joint, JointKind, JointLimits};
    use glam::DAffine3;

    /// A tool that slides along y on the plane x = 0.5.
    fn slider() -> Rig {
        Rig {
            name: "slider".into(),
            base_frame: "base".into(),
            tool_frame: "tool".into(),
            joints: vec![Joint {
                name: "y".into(),
                kind: JointKind::Prismatic,
                origin: DAffine3::IDENTITY,
                axis: DVec3::Y,
                limits: JointLimits {
                    lower: -1.0,
                    upper: 1.0,
                    max_speed: 1.0,
                    max_acceleration: 10.0,
                },
            }],
            tool: DAffine3::from_translation(DVec3::new(0.5, 0.0, 0.3)),
            bodies: Vec::new(),
            allowed_pairs: Vec::new(),
        }
    }

    fn wall_at(x: f64) -> WallView {
        WallView {
            corners: [[x, -1.0, 0.0], [x, 1.0, 0.0], [x, 1.0, 1.0], [x, -1.0, 1.0]],
            openings: Vec::new(),
        }
    }

    #[test]
    fn touching_the_wall_leaves_strokes_and_missing_it_leaves_none() {
        let mut trace = ToolTrace::new(slider());
        trace.set_wall(Some((2, &wall_at(0.5))));
        for step in 0..=10 {
            trace.observe(&[0.01 * f64::from(step)]);
        }
        let strokes = trace.drain();
        assert_eq!(strokes.len(), 10, "one 1 cm stroke per step");
        for stroke in &strokes {
            assert_eq!(stroke.wall, 2);
            assert!(stroke.quad.iter().all(|p| (p[0] - 0.5).abs() < 1e-12));
            assert!(
                stroke
                    .quad
                    .iter()
                    .all(|p| (p[2] - 0.3).abs() <= STROKE_WIDTH_M)
            );
        }
        assert!(trace.drain().is_empty(), "drained once");

        trace.set_wall(Some((0, &wall_at(0.6))));
        for step in 0..=10 {
            trace.observe(&[0.01 * f64::from(step)]);
        }
        assert!(trace.drain().is_empty(), "10 cm off the wall");
        assert_eq!(trace.dropped(), 0);
    }
}
