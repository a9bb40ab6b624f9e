//! The live scene of the sloth: its bones from the gait's rig model at the streamed joint
//! values, and the branches and trunks of its scenario as cylinders. It must not plan or
//! judge the gait; it only draws what the twin reports.

use super::{Scenario, SlothRig};
use crate::scene::{CylinderView, Point, SceneView};
use crate::view::LiveScene;
use std::sync::Arc;

pub struct SlothScene {
    sloth: Arc<SlothRig>,
    cylinders: Vec<CylinderView>,
}

impl SlothScene {
    pub fn new(sloth: Arc<SlothRig>, scenario: &Scenario) -> Self {
        let cylinders = scenario
            .terrain
            .cylinders
            .iter()
            .map(|c| CylinderView {
                from: c.from.to_array(),
                to: c.to.to_array(),
                radius: c.radius,
            })
            .collect();
        SlothScene { sloth, cylinders }
    }
}

impl LiveScene for SlothScene {
    fn scene(&self) -> SceneView {
        SceneView {
            cylinders: self.cylinders.clone(),
            ..SceneView::default()
        }
    }

    /// The spine, then one polyline per limb; nothing when `actual` does not fit the rig.
    fn chains(&self, actual: &[f64]) -> Vec<Vec<Point>> {
        self.sloth
            .bone_polylines(actual)
            .map(|lines| {
                lines
                    .into_iter()
                    .map(|line| line.into_iter().map(|p| p.to_array()).collect())
                    .collect()
            })
            .unwrap_or_default()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    fn straight() -> (Arc<SlothRig>, Scenario) {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/sloth.toml");
        let sloth = Arc::new(SlothRig::load(&path).expect("config/sloth.toml loads"));
        let scenario = Scenario::build("straight", None, None).expect("straight builds");
        (sloth, scenario)
    }

    #[test]
    fn the_scene_holds_the_scenario_branches() {
        let (sloth, scenario) = straight();
        let scene = SlothScene::new(sloth, &scenario).scene();
        assert_eq!(scene.cylinders.len(), scenario.terrain.cylinders.len());
        assert!(scene.walls.is_empty());
        let first = &scenario.terrain.cylinders[0];
        assert_eq!(scene.cylinders[0].from, first.from.to_array());
        assert_eq!(scene.cylinders[0].radius, first.radius);
    }

    #[test]
    fn chains_are_the_spine_and_four_limbs_and_follow_the_joints() {
        let (sloth, scenario) = straight();
        let scene = SlothScene::new(sloth.clone(), &scenario);
        let rest = vec![0.0; sloth.dof()];
        let chains = scene.chains(&rest);
        assert_eq!(chains.len(), 5);
        let mut moved = rest.clone();
        moved[0] += 0.25; // the body's x axis
        let shifted = scene.chains(&moved);
        assert!((shifted[0][0][0] - chains[0][0][0] - 0.25).abs() < 1e-9);
        assert!(scene.chains(&rest[1..]).is_empty());
    }
}
