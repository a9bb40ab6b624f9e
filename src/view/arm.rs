//! The live scene of a serial rig (the arm): its links from forward kinematics of the rig
//! model, the wall of the star job, and the tool's trace on that wall. Generic over the
//! rig's joints; it must not know about the streamer or the page.

use super::LiveScene;
use super::trace::ToolTrace;
use crate::job::Job as JobConfig;
use crate::rig::Rig;
use crate::scene::{PaintQuad, Point, SceneView, WallView};
use crate::twin::SharedWorld;
use glam::{DAffine3, DVec3};
use std::sync::PoisonError;

/// Margin of the drawn wall around the job's figure, as a multiple of its radius, and the
/// least width and height it is drawn with (m): a wall, not a sticker.
const WALL_MARGIN_RADII: f64 = 3.0;
const WALL_MIN_SIZE_M: f64 = 0.8;

pub struct ArmScene {
    rig: Rig,
    walls: Vec<WallView>,
    trace: Option<SharedWorld<ToolTrace>>,
}

impl ArmScene {
    /// The rig alone, base at the world origin.
    pub fn new(rig: Rig) -> Self {
        ArmScene {
            rig,
            walls: Vec::new(),
            trace: None,
        }
    }

    /// The rig in front of the wall `job` works on (if it works on one). With `trace`, the
    /// tool's contact with that wall shows as paint.
    pub fn for_job(rig: Rig, job: &JobConfig, trace: Option<SharedWorld<ToolTrace>>) -> Self {
        let walls: Vec<WallView> = job_wall(job).into_iter().collect();
        if let Some(trace) = &trace {
            trace
                .lock()
                .unwrap_or_else(PoisonError::into_inner)
                .set_wall(walls.first().map(|wall| (0, wall)));
        }
        ArmScene {
            walls,
            trace,
            ..ArmScene::new(rig)
        }
    }
}

/// The wall a job draws on: the plane x = `wall_x_m` of the star job, square around its
/// figure, standing on the floor (z = 0).
pub fn job_wall(job: &JobConfig) -> Option<WallView> {
    let crate::job::Scene::Wall(figure) = job.scene() else {
        return None;
    };
    let (wall_x_m, centre_yz_m, radius_m) =
        (&figure.wall_x_m, &figure.centre_yz_m, &figure.radius_m);
    let half_width = (WALL_MARGIN_RADII * radius_m).max(WALL_MIN_SIZE_M / 2.0);
    let top = (centre_yz_m[1] + WALL_MARGIN_RADII * radius_m).max(WALL_MIN_SIZE_M);
    let (y0, y1) = (centre_yz_m[0] - half_width, centre_yz_m[0] + half_width);
    // Counter-clockwise seen from the arm (x < wall_x_m): the face the tool works on.
    Some(WallView {
        corners: [
            [*wall_x_m, y1, 0.0],
            [*wall_x_m, y0, 0.0],
            [*wall_x_m, y0, top],
            [*wall_x_m, y1, top],
        ],
        openings: Vec::new(),
    })
}

/// The origin of every joint frame of `rig` at `positions`, then the tool frame's: the
/// links as the page draws them. Empty when `positions` does not fit the rig.
pub fn joint_origins(rig: &Rig, positions: &[f64]) -> Vec<Point> {
    joint_origins_from(rig, positions, 0)
}

/// [`joint_origins`] for a rig whose first `carried_by` joints move it rather than being
/// links, such as a mobile base's x, y and heading: the polyline starts where those joints
/// put the rig (its base), so no link is drawn from the world origin to it.
pub fn joint_origins_from(rig: &Rig, positions: &[f64], carried_by: usize) -> Vec<Point> {
    if positions.len() != rig.dof() || carried_by > rig.dof() {
        return Vec::new();
    }
    let mut frame = DAffine3::IDENTITY;
    for (joint, q) in rig.joints.iter().zip(positions).take(carried_by) {
        frame *= joint.transform(*q);
    }
    let mut points = Vec::with_capacity(rig.dof() + 2);
    points.push(point(frame.translation));
    for (joint, q) in rig.joints.iter().zip(positions).skip(carried_by) {
        points.push(point((frame * joint.origin).translation));
        frame *= joint.transform(*q);
    }
    points.push(point((frame * rig.tool).translation));
    points.dedup();
    points
}

fn point(v: DVec3) -> Point {
    [v.x, v.y, v.z]
}

impl LiveScene for ArmScene {
    fn scene(&self) -> SceneView {
        SceneView {
            walls: self.walls.clone(),
            ..SceneView::default()
        }
    }

    fn chains(&self, actual: &[f64]) -> Vec<Vec<Point>> {
        vec![joint_origins(&self.rig, actual)]
    }

    fn drain_paint(&mut self) -> Vec<PaintQuad> {
        match &self.trace {
            Some(trace) => trace.lock().unwrap_or_else(PoisonError::into_inner).drain(),
            None => Vec::new(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rig::{Joint, JointKind, JointLimits};

    fn limits() -> JointLimits {
        JointLimits {
            lower: -3.0,
            upper: 3.0,
            max_speed: 1.0,
            max_acceleration: 10.0,
        }
    }

    /// A lift (prismatic z) carrying a 0.5 m arm that turns about z.
    fn lift_and_arm() -> Rig {
        Rig {
            name: "lift-arm".into(),
            base_frame: "base".into(),
            tool_frame: "tool".into(),
            joints: vec![
                Joint {
                    name: "lift".into(),
                    kind: JointKind::Prismatic,
                    origin: DAffine3::from_translation(DVec3::new(1.0, 0.0, 0.0)),
                    axis: DVec3::Z,
                    limits: limits(),
                },
                Joint {
                    name: "turn".into(),
                    kind: JointKind::Revolute,
                    origin: DAffine3::from_translation(DVec3::new(0.0, 0.0, 0.2)),
                    axis: DVec3::Z,
                    limits: limits(),
                },
            ],
            tool: DAffine3::from_translation(DVec3::new(0.5, 0.0, 0.0)),
            bodies: Vec::new(),
            allowed_pairs: Vec::new(),
        }
    }

    fn close(a: Point, b: Point) -> bool {
        a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-12)
    }

    #[test]
    fn links_follow_the_rig_model_not_a_picture() {
        let rig = lift_and_arm();
        let chain = joint_origins(&rig, &[0.3, std::f64::consts::FRAC_PI_2]);
        let expected = [
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [1.0, 0.0, 0.5],
            [1.0, 0.5, 0.5],
        ];
        assert_eq!(chain.len(), expected.len(), "{chain:?}");
        for (got, want) in chain.iter().zip(expected) {
            assert!(close(*got, want), "{chain:?}");
        }
        let tool = rig
            .forward(&[0.3, std::f64::consts::FRAC_PI_2])
            .expect("the rig takes two positions");
        assert!(close(
            *chain.last().expect("the chain has points"),
            point(tool.translation)
        ));
        assert!(joint_origins(&rig, &[0.3]).is_empty(), "wrong axis count");
    }

    #[test]
    fn a_rig_carried_by_its_first_joints_starts_at_its_base() {
        // The lift's slide, seen as what carries the arm: no link from the origin to it.
        let rig = lift_and_arm();
        let chain = joint_origins_from(&rig, &[0.3, 0.0], 1);
        let expected = [[1.0, 0.0, 0.3], [1.0, 0.0, 0.5], [1.5, 0.0, 0.5]];
        assert_eq!(chain.len(), expected.len(), "{chain:?}");
        for (got, want) in chain.iter().zip(expected) {
            assert!(close(*got, want), "{chain:?}");
        }
        assert!(joint_origins_from(&rig, &[0.3, 0.0], 3).is_empty());
    }

    #[test]
    fn the_star_job_shows_its_wall_at_wall_x() {
        let job = JobConfig::WallFigure(crate::job::WallFigure {
            wall_x_m: 0.45,
            centre_yz_m: [0.1, 0.45],
            radius_m: 0.12,
            laps: 1,
        });
        let wall = job_wall(&job).expect("the star job has a wall");
        assert!(wall.corners.iter().all(|c| c[0] == 0.45));
        let (ys, zs): (Vec<f64>, Vec<f64>) = wall.corners.iter().map(|c| (c[1], c[2])).unzip();
        let span = |v: &[f64]| {
            (
                v.iter().cloned().fold(f64::INFINITY, f64::min),
                v.iter().cloned().fold(f64::NEG_INFINITY, f64::max),
            )
        };
        let (y0, y1) = span(&ys);
        let (z0, z1) = span(&zs);
        assert!(y0 < 0.1 - 0.12 && y1 > 0.1 + 0.12, "{wall:?}");
        assert!(z0 <= 0.0 && z1 > 0.45 + 0.12, "{wall:?}");
        let [a, b, c, _] = wall.corners.map(glam::DVec3::from_array);
        let facing = (b - a).cross(c - a);
        assert!(facing.x < 0.0, "the wall's front faces the arm: {facing}");
        let waypoints = JobConfig::JointWaypoints(crate::job::JointWaypoints {
            waypoints_deg: vec![vec![0.0; 6]],
        });
        assert!(job_wall(&waypoints).is_none());
    }
}
