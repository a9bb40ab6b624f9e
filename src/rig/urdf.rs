//! URDF import: the serial chain from the root link to the tool frame (named, or the only
//! leaf a moving joint leads to) becomes a [`Rig`].
//! Fixed joints fold into the next joint's origin (or the tool transform). URDF carries no
//! acceleration limit before version 1.2; where it is absent we assume the axis reaches full
//! speed in [`DEFAULT_TIME_TO_FULL_SPEED_S`].

use super::config::origin_from_xyz_rpy;
use super::geometry::{hull, read_hull_points};
use super::{
    Collision, ConfigError, Joint, JointKind, JointLimits, LinkBody, Rig, Shape, Verbatim,
};
use glam::{DAffine3, DVec3};
use std::collections::{HashMap, HashSet};
use std::path::Path;

pub const DEFAULT_TIME_TO_FULL_SPEED_S: f64 = 0.25;

/// Builds a rig from URDF text, ending at the only leaf frame reached through a moving
/// joint; `file` names the source in errors. See [`rig_from_urdf_to`].
pub fn rig_from_urdf(text: &str, file: &Path) -> Result<Rig, ConfigError> {
    rig_from_urdf_to(text, file, None)
}

/// Builds a rig from URDF text, from the root link to `tool_frame` (any link), or when it
/// is `None` to the one leaf link that a moving joint leads to: with several, the error
/// names them all, since guessing the tool would plan for the wrong point.
pub fn rig_from_urdf_to(
    text: &str,
    file: &Path,
    tool_frame: Option<&str>,
) -> Result<Rig, ConfigError> {
    check_size(text, file)?;
    let robot = urdf_rs::read_from_string(text).map_err(|e| ConfigError::Parse {
        file: file.to_path_buf(),
        message: e.to_string(),
    })?;
    let tree = UrdfTree::new(&robot, file)?;
    let tip = match tool_frame {
        Some(frame) => frame.to_string(),
        None => only_tool_candidate(&tree, file)?,
    };
    let path = tree.path_to(&tip).ok_or_else(|| {
        let reason = format!(
            "no link `{tip}` below the root link {}; its leaf frames: {}",
            tree.root(),
            tree.tool_candidates().join(", ")
        );
        ConfigError::invalid(file, "tool frame", Verbatim(&tip), &reason)
    })?;

    let mut joints = Vec::new();
    let mut pending = DAffine3::IDENTITY;
    // Each link of the chain with the frame it rides on and its place in that frame.
    let mut chain_links = vec![(tree.root().to_string(), 0, DAffine3::IDENTITY)];
    for urdf_joint in path {
        let origin = pending
            * origin_from_xyz_rpy(
                DVec3::from_array(*urdf_joint.origin.xyz),
                DVec3::from_array(*urdf_joint.origin.rpy),
            );
        match moving_joint(urdf_joint, origin, file)? {
            // A fixed joint folds into the next joint's origin (or the tool transform).
            None => pending = origin,
            Some(joint) => {
                joints.push(joint);
                pending = DAffine3::IDENTITY;
            }
        }
        chain_links.push((urdf_joint.child.link.clone(), joints.len(), pending));
    }
    let (bodies, allowed_pairs) = collision_bodies(&robot, &chain_links, file)?;
    if joints.is_empty() {
        return Err(ConfigError::invalid(
            file,
            "joint",
            Verbatim("(none)"),
            "the chain has no revolute or prismatic joint",
        ));
    }
    Ok(Rig {
        name: robot.name.clone(),
        base_frame: tree.root().to_string(),
        tool_frame: tip,
        joints,
        tool: pending,
        bodies,
        allowed_pairs,
    })
}

/// A URDF chain's collision bodies and the pairs of neighbours never checked.
type BodiesAndPairs = (Vec<LinkBody>, Vec<(String, String)>);

/// The `<collision>` elements of the chain's links as bodies (a link without any is no
/// body; links off the chain are not read), and each pair of neighbouring links that both
/// have a body as an allowed pair: they meet at their joint, as MoveIt's adjacent pairs.
fn collision_bodies(
    robot: &urdf_rs::Robot,
    chain_links: &[(String, usize, DAffine3)],
    file: &Path,
) -> Result<BodiesAndPairs, ConfigError> {
    let mut bodies: Vec<LinkBody> = Vec::new();
    for (name, frame, place) in chain_links {
        let Some(link) = robot.links.iter().find(|l| &l.name == name) else {
            continue;
        };
        let mut collisions = Vec::with_capacity(link.collision.len());
        for (i, element) in link.collision.iter().enumerate() {
            let key = format!("link[name={name}].collision[{i}]");
            let origin = origin_from_xyz_rpy(
                DVec3::from_array(*element.origin.xyz),
                DVec3::from_array(*element.origin.rpy),
            );
            let shape = urdf_shape(&element.geometry, &key, file)?;
            collisions.push(Collision {
                origin: *place * origin,
                shape,
            });
        }
        if !collisions.is_empty() {
            bodies.push(LinkBody {
                name: name.clone(),
                frame: *frame,
                collisions,
            });
        }
    }
    let has_body = |name: &str| bodies.iter().any(|b| b.name == name);
    let allowed = chain_links
        .windows(2)
        .filter(|w| has_body(&w[0].0) && has_body(&w[1].0))
        .map(|w| (w[0].0.clone(), w[1].0.clone()))
        .collect();
    Ok((bodies, allowed))
}

/// A URDF geometry as a solid: box, cylinder, sphere and capsule as they are, a mesh as the
/// convex hull of its (scaled) vertices.
fn urdf_shape(geometry: &urdf_rs::Geometry, key: &str, file: &Path) -> Result<Shape, ConfigError> {
    let positive = |field: &str, value: f64| {
        if value.is_finite() && value > 0.0 {
            Ok(value)
        } else {
            Err(ConfigError::invalid(
                file,
                &format!("{key}.{field}"),
                value,
                "must be a positive number",
            ))
        }
    };
    Ok(match geometry {
        urdf_rs::Geometry::Box { size } => {
            let size = [
                positive("box.size", size[0])?,
                positive("box.size", size[1])?,
                positive("box.size", size[2])?,
            ];
            Shape::Box {
                half_extents: DVec3::from_array(size) / 2.0,
            }
        }
        urdf_rs::Geometry::Cylinder { radius, length } => Shape::Cylinder {
            radius: positive("cylinder.radius", *radius)?,
            half_length: positive("cylinder.length", *length)? / 2.0,
        },
        urdf_rs::Geometry::Capsule { radius, length } => {
            let half = positive("capsule.length", *length)? / 2.0;
            Shape::Capsule {
                a: DVec3::new(0.0, 0.0, -half),
                b: DVec3::new(0.0, 0.0, half),
                radius: positive("capsule.radius", *radius)?,
            }
        }
        urdf_rs::Geometry::Sphere { radius } => Shape::Sphere {
            radius: positive("sphere.radius", *radius)?,
        },
        urdf_rs::Geometry::Mesh { filename, scale } => {
            let mesh_key = format!("{key}.mesh.filename");
            let scale = scale.map_or(DVec3::ONE, |s| DVec3::from_array(*s));
            let points = read_hull_points(file, &mesh_key, filename)?
                .into_iter()
                .map(|p| p * scale)
                .collect();
            hull(file, &mesh_key, points)?
        }
    })
}

/// One URDF joint of the chain as a rig joint, with its `origin` (fixed joints before it
/// folded in); `None` for a fixed joint. Limits, speed and axis are checked here, so the
/// error names the joint's key.
fn moving_joint(
    urdf_joint: &urdf_rs::Joint,
    origin: DAffine3,
    file: &Path,
) -> Result<Option<Joint>, ConfigError> {
    let invalid = |key: &str, value: &str, reason: &str| {
        ConfigError::invalid(file, key, Verbatim(value), reason)
    };
    let key = format!("joint[name={}]", urdf_joint.name);
    let kind = match urdf_joint.joint_type {
        urdf_rs::JointType::Fixed => return Ok(None),
        urdf_rs::JointType::Revolute => JointKind::Revolute,
        urdf_rs::JointType::Prismatic => JointKind::Prismatic,
        ref other => {
            return Err(invalid(
                &format!("{key}.type"),
                joint_type_name(other),
                "only revolute, prismatic and fixed joints are supported (a rig needs finite limits)",
            ));
        }
    };
    let limit = &urdf_joint.limit;
    if !(limit.lower.is_finite() && limit.upper.is_finite() && limit.lower < limit.upper) {
        return Err(invalid(
            &format!("{key}.limit"),
            &format!("lower={} upper={}", limit.lower, limit.upper),
            "needs finite lower < upper",
        ));
    }
    if !(limit.velocity.is_finite() && limit.velocity > 0.0) {
        return Err(invalid(
            &format!("{key}.limit.velocity"),
            &limit.velocity.to_string(),
            "must be positive",
        ));
    }
    let max_acceleration = if limit.acceleration.is_finite() && limit.acceleration > 0.0 {
        limit.acceleration
    } else {
        limit.velocity / DEFAULT_TIME_TO_FULL_SPEED_S
    };
    let axis = DVec3::from_array(*urdf_joint.axis.xyz);
    if !axis.is_finite() || axis.length() < 1e-9 {
        return Err(invalid(
            &format!("{key}.axis"),
            &format!("[{}, {}, {}]", axis.x, axis.y, axis.z),
            "must be a non-zero finite vector",
        ));
    }
    Ok(Some(Joint {
        name: urdf_joint.name.clone(),
        kind,
        origin,
        axis: axis.normalize(),
        limits: JointLimits {
            lower: limit.lower,
            upper: limit.upper,
            max_speed: limit.velocity,
            max_acceleration,
        },
    }))
}

/// Longest URDF text read (bytes), checked before parsing: a URDF names its meshes as
/// separate files, so it is text for links and joints only (the reference IRB 120's is
/// 2.8 kB). The parser (urdf-rs) takes about 0.5 s and 70 MB for 1 MiB (a 1,000-joint chain) on this project's
/// machine, time and memory growing with the text (a 100,000-joint chain, 18 MB, took 42 s
/// and 932 MB before this cap), so 1 MiB, over 300 times the reference arm, keeps any
/// file's load under a second.
pub const MAX_URDF_BYTES: usize = 1024 * 1024;
/// Most joints (fixed ones included) a URDF may have. A rig streams at most
/// [`crate::protocol::MAX_AXES`] moving joints; the rest of a tree is fixed frames and other
/// branches (grippers, sensors). 1,024 leaves room for any real robot and bounds the tree's
/// depth, the walks below and the size of an error's list of frames.
pub const MAX_URDF_JOINTS: usize = 1024;

/// Refuses URDF text over [`MAX_URDF_BYTES`], before the parser sees it.
pub(crate) fn check_size(text: &str, file: &Path) -> Result<(), ConfigError> {
    if text.len() <= MAX_URDF_BYTES {
        return Ok(());
    }
    Err(ConfigError::invalid(
        file,
        "(file size)",
        Verbatim(format!("{} bytes", text.len())),
        &format!("a URDF is at most {MAX_URDF_BYTES} bytes"),
    ))
}

/// A URDF checked as a tree: at most [`MAX_URDF_JOINTS`] joints, unique link and joint
/// names, every joint's parent and child links declared, no link with two parent joints,
/// one root link and no cycle. Built and walked without recursion, so neither a cycle nor
/// a deep chain can exhaust the stack; every walk is linear in the joints.
pub(crate) struct UrdfTree<'a> {
    robot: &'a urdf_rs::Robot,
    root: &'a str,
    /// Each link's parent joint (an index into `robot.joints`); the root has none.
    parent: HashMap<&'a str, usize>,
    /// Each link's child joints, in the file's order.
    children: HashMap<&'a str, Vec<usize>>,
}

impl<'a> UrdfTree<'a> {
    /// The tree of `robot`, or the first thing that makes it none; `file` names the source.
    pub(crate) fn new(robot: &'a urdf_rs::Robot, file: &Path) -> Result<Self, ConfigError> {
        let joint_key = |j: &urdf_rs::Joint| format!("joint[name={}]", j.name);
        let refuse = |key: String, value: &str, reason: String| {
            ConfigError::invalid(file, &key, Verbatim(value), &reason)
        };
        if let Some(extra) = robot.joints.get(MAX_URDF_JOINTS) {
            return Err(refuse(
                joint_key(extra),
                &extra.name,
                format!(
                    "the URDF has {} joints; at most {MAX_URDF_JOINTS} are read",
                    robot.joints.len()
                ),
            ));
        }
        if let Some(extra) = robot.links.get(MAX_URDF_JOINTS + 1) {
            return Err(refuse(
                format!("link[name={}]", extra.name),
                &extra.name,
                format!(
                    "the URDF has {} links; a tree of at most {MAX_URDF_JOINTS} joints has at \
                     most {} links",
                    robot.links.len(),
                    MAX_URDF_JOINTS + 1
                ),
            ));
        }
        let mut links = HashSet::new();
        for link in &robot.links {
            if !links.insert(link.name.as_str()) {
                let key = format!("link[name={}]", link.name);
                return Err(refuse(key, &link.name, "declared twice".into()));
            }
        }
        let mut joints = HashSet::new();
        let mut parent: HashMap<&str, usize> = HashMap::new();
        let mut children: HashMap<&str, Vec<usize>> = HashMap::new();
        for (index, joint) in robot.joints.iter().enumerate() {
            if !joints.insert(joint.name.as_str()) {
                return Err(refuse(
                    joint_key(joint),
                    &joint.name,
                    "declared twice".into(),
                ));
            }
            for (end, link) in [("parent", &joint.parent.link), ("child", &joint.child.link)] {
                if !links.contains(link.as_str()) {
                    return Err(refuse(
                        format!("{}.{end}", joint_key(joint)),
                        link,
                        "no link of that name in the file".into(),
                    ));
                }
            }
            if let Some(&first) = parent.get(joint.child.link.as_str()) {
                return Err(refuse(
                    format!("{}.child", joint_key(joint)),
                    &joint.child.link,
                    format!(
                        "that link is already the child of joint {}: in a URDF tree a link has \
                         one parent joint",
                        robot.joints[first].name
                    ),
                ));
            }
            parent.insert(&joint.child.link, index);
            children.entry(&joint.parent.link).or_default().push(index);
        }
        let roots: Vec<&str> = robot
            .links
            .iter()
            .map(|l| l.name.as_str())
            .filter(|l| !parent.contains_key(l))
            .collect();
        let root = match roots.as_slice() {
            [root] => *root,
            [] => {
                let joint = cycle_joint(robot, &parent, robot.links.first().map(|l| &*l.name));
                return Err(cycle_error(file, robot, joint));
            }
            several => {
                return Err(refuse(
                    "link".into(),
                    &listed(several),
                    "several root links (links no joint leads to): a URDF is one tree".into(),
                ));
            }
        };
        let tree = UrdfTree {
            robot,
            root,
            parent,
            children,
        };
        // Every link has one parent joint and one has none: a link the walk from the root
        // does not reach hangs from a cycle.
        let reached = tree.below_root();
        if reached.len() < robot.links.len() {
            let stray = robot
                .links
                .iter()
                .map(|l| l.name.as_str())
                .find(|l| !reached.contains(l));
            let joint = cycle_joint(robot, &tree.parent, stray);
            return Err(cycle_error(file, robot, joint));
        }
        Ok(tree)
    }

    /// The root link: the base frame.
    pub(crate) fn root(&self) -> &'a str {
        self.root
    }

    /// Every link below the root, the root included (a walk with a stack, no recursion).
    fn below_root(&self) -> HashSet<&'a str> {
        let mut seen = HashSet::from([self.root]);
        let mut stack = vec![self.root];
        while let Some(link) = stack.pop() {
            for child in self.child_links(link) {
                if seen.insert(child) {
                    stack.push(child);
                }
            }
        }
        seen
    }

    fn child_joints(&self, link: &str) -> &[usize] {
        self.children.get(link).map_or(&[], Vec::as_slice)
    }

    fn child_links(&self, link: &str) -> impl Iterator<Item = &'a str> + '_ {
        let robot = self.robot;
        self.child_joints(link)
            .iter()
            .map(move |&j| robot.joints[j].child.link.as_str())
    }

    /// The joints from the root down to the link `tip`, when there is such a link: up from
    /// `tip` by parent joints, then reversed.
    pub(crate) fn path_to(&self, tip: &str) -> Option<Vec<&'a urdf_rs::Joint>> {
        if !self.robot.links.iter().any(|l| l.name == tip) {
            return None;
        }
        let mut path = Vec::new();
        let mut link = tip;
        while let Some(&joint) = self.parent.get(link) {
            let joint = &self.robot.joints[joint];
            path.push(joint);
            link = &joint.parent.link;
        }
        path.reverse();
        Some(path)
    }

    /// The leaf links that a revolute or prismatic joint leads to: the frames a tool may be
    /// (a leaf hanging from the base by fixed joints only moves with nothing). In the order
    /// of a depth-first walk taking each link's joints in the file's order.
    pub(crate) fn tool_candidates(&self) -> Vec<String> {
        let mut out = Vec::new();
        let mut stack = vec![(self.root, false)];
        while let Some((link, moved)) = stack.pop() {
            let joints = self.child_joints(link);
            if joints.is_empty() && moved {
                out.push(link.to_string());
            }
            // Pushed last to first, so the first joint's branch is walked first.
            for &j in joints.iter().rev() {
                let joint = &self.robot.joints[j];
                let moving = !matches!(joint.joint_type, urdf_rs::JointType::Fixed);
                stack.push((joint.child.link.as_str(), moved || moving));
            }
        }
        out
    }
}

/// A joint on the cycle above `start`: up by parent joints until a link repeats; the
/// joint into the repeated link closes the cycle.
fn cycle_joint<'a>(
    robot: &'a urdf_rs::Robot,
    parent: &HashMap<&str, usize>,
    start: Option<&'a str>,
) -> Option<&'a urdf_rs::Joint> {
    let mut seen = HashSet::new();
    let mut link = start?;
    loop {
        let joint = &robot.joints[*parent.get(link)?];
        if !seen.insert(link) {
            return Some(joint);
        }
        link = &joint.parent.link;
    }
}

fn cycle_error(file: &Path, robot: &urdf_rs::Robot, joint: Option<&urdf_rs::Joint>) -> ConfigError {
    match joint {
        Some(joint) => ConfigError::invalid(
            file,
            &format!("joint[name={}]", joint.name),
            Verbatim(format!("{} -> {}", joint.parent.link, joint.child.link)),
            "the joints form a cycle through it: a URDF is a tree",
        ),
        None => ConfigError::invalid(
            file,
            "link",
            Verbatim(format!("{} links", robot.links.len())),
            "no root link: the links form a cycle",
        ),
    }
}

/// Names shown in a message: the first [`MAX_LISTED`], then how many there are in all.
fn listed(names: &[&str]) -> String {
    match names.get(MAX_LISTED..) {
        Some(rest) if !rest.is_empty() => format!(
            "{}, ... ({} in all)",
            names[..MAX_LISTED].join(", "),
            names.len()
        ),
        _ => names.join(", "),
    }
}

/// Most names a message lists: enough to find them, short enough to read.
const MAX_LISTED: usize = 8;

fn only_tool_candidate(tree: &UrdfTree<'_>, file: &Path) -> Result<String, ConfigError> {
    let mut candidates = tree.tool_candidates();
    match candidates.len() {
        1 => Ok(candidates.remove(0)),
        0 => Err(ConfigError::invalid(
            file,
            "joint",
            Verbatim("(none)"),
            "no revolute or prismatic joint leads to a leaf link",
        )),
        _ => Err(ConfigError::invalid(
            file,
            "tool frame",
            Verbatim(candidates.join(", ")),
            "several leaf frames could be the tool: choose one with --tool-frame NAME",
        )),
    }
}

/// A URDF joint type as the file writes it.
fn joint_type_name(kind: &urdf_rs::JointType) -> &'static str {
    match kind {
        urdf_rs::JointType::Revolute => "revolute",
        urdf_rs::JointType::Continuous => "continuous",
        urdf_rs::JointType::Prismatic => "prismatic",
        urdf_rs::JointType::Fixed => "fixed",
        urdf_rs::JointType::Floating => "floating",
        urdf_rs::JointType::Planar => "planar",
        urdf_rs::JointType::Spherical => "spherical",
    }
}
