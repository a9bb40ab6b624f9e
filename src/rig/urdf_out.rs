//! URDF export: a [`Rig`] written as a URDF serial chain, for tools that know robots by
//! their URDF (Foxglove's 3D panel reads it from a log attachment, `rigbridge config urdf`
//! writes it for any URDF tool). Owns the text format of the export only; it must not change
//! the rig, and loading stays in `urdf.rs`. A link with collision geometry carries it as
//! `<collision>` and the same solids as `<visual>`; a link without any gets a plain cylinder
//! from its origin to the next joint's as its visual, so a viewer has something to draw.
//!
//! URDF has no capsule and no half-space: a capsule is written as a cylinder plus a sphere
//! at each end (their union is exactly the capsule), a half-space as a cube with one face on
//! its plane, large enough that for everything the rig can reach the distance and the
//! penetration depth to the cube are those to the half-space ([`half_space_as_box`]).
//! A convex hull is written as a mesh file named in the text, whose vertices
//! [`UrdfExport::meshes`] holds (Wavefront OBJ, vertices only: the solid is their hull).

use super::geometry::{Collision, Shape};
use super::{JointKind, Rig};
use glam::{DAffine3, DQuat, DVec3, EulerRot};
use std::fmt::Write;

/// Radius of the cylinder drawn along a link with no collision geometry: thick enough to see
/// at arm scale (the IRB 120's links are 0.07 to 0.3 m long), thin enough not to hide frames.
const LINK_RADIUS_M: f64 = 0.025;
/// Segments shorter than this get no cylinder: a zero-length cylinder has no direction.
const MIN_SEGMENT_M: f64 = 1e-6;
/// URDF requires an effort limit on actuated joints; rigs carry none, and 0 means unknown.
const UNKNOWN_EFFORT: f64 = 0.0;
/// A half-space's cube is this many times the reach around the rig's base (its reach plus
/// the base's distance to the plane): for a point within reach R of the base, the cube's
/// top face is then nearer than its sides by more than R, so its distance and penetration
/// depth are the half-space's (docs/cell.md, "The floor in the URDF").
const HALF_SPACE_CUBE_PER_REACH: f64 = 4.0;

/// A link fixed to another one: a tool at its TCP, a cell object, a second body on one of
/// the rig's frames. Plain data: `origin` places it in `parent`, its solids are in its frame.
#[derive(Debug, Clone, PartialEq)]
pub struct FixedLink {
    pub name: String,
    pub parent: String,
    pub origin: DAffine3,
    pub collisions: Vec<Collision>,
}

/// A convex hull's points, to be written as the mesh file `file` the URDF text names.
#[derive(Debug, Clone, PartialEq)]
pub struct HullMesh {
    pub file: String,
    pub points: Vec<DVec3>,
}

impl HullMesh {
    /// The points as a Wavefront OBJ file of vertices (the solid is their convex hull).
    pub fn obj_text(&self) -> String {
        let mut out = String::from("# convex hull points, written by rigbridge\n");
        for p in &self.points {
            let _ = writeln!(out, "v {} {} {}", p.x, p.y, p.z);
        }
        out
    }
}

/// A URDF and the fixed links it holds beyond the rig's chain (a log's `/tf` gives each a
/// frame), with the hull meshes it names.
#[derive(Debug, Clone, PartialEq)]
pub struct UrdfExport {
    pub text: String,
    /// Every fixed link besides the chain's own tool frame, with its solids as written
    /// (half-spaces already cubes).
    pub fixed: Vec<FixedLink>,
    pub meshes: Vec<HullMesh>,
}

/// The links the export names, one per joint (the link the joint moves): the name of the
/// first body riding that joint's frame when there is one (so the URDF's link is the body a
/// collision report names), else the joint's own name, as `Rig::sub_chain` names the frame
/// after a joint; `<name>_link` where either would clash with the base or tool frame or an
/// earlier link.
pub fn generated_link_names(rig: &Rig) -> Vec<String> {
    let mut names: Vec<String> = Vec::with_capacity(rig.dof());
    for (k, joint) in rig.joints.iter().enumerate() {
        let body = rig.bodies.iter().find(|b| b.frame == k + 1);
        let wanted = body.map_or(joint.name.as_str(), |b| b.name.as_str());
        let taken = |name: &str| {
            name == rig.base_frame || name == rig.tool_frame || names.iter().any(|n| n == name)
        };
        let name = if taken(wanted) {
            format!("{wanted}_link")
        } else {
            wanted.to_string()
        };
        names.push(name);
    }
    names
}

/// The chain's link for frame `k` (0: the base).
fn frame_link<'a>(rig: &'a Rig, links: &'a [String], k: usize) -> &'a str {
    match k {
        0 => &rig.base_frame,
        _ => &links[k - 1],
    }
}

/// A bound on how far from the base's origin any point of the rig reaches, with `beyond_flange_m`
/// the reach of what rides on the tool frame (a tool's bodies): the chain's offsets laid end to
/// end, prismatic travel, and the largest body.
pub fn reach_bound_m(rig: &Rig, beyond_flange_m: f64) -> f64 {
    let chain: f64 = rig
        .joints
        .iter()
        .map(|j| {
            let travel = match j.kind {
                JointKind::Revolute => 0.0,
                JointKind::Prismatic => j.limits.lower.abs().max(j.limits.upper.abs()),
            };
            j.origin.translation.length() + travel
        })
        .sum::<f64>()
        + rig.tool.translation.length();
    let bodies = rig
        .bodies
        .iter()
        .flat_map(|b| &b.collisions)
        .filter_map(|c| Some(c.origin.translation.length() + c.shape.bounding_radius()?))
        .fold(0.0, f64::max);
    chain + bodies.max(beyond_flange_m)
}

/// A half-space `{ p : p . normal <= 0 }` in the frame `origin` (in its owner's frame, the
/// owner at `owner_in_base` in the rig's base frame) as a cube in the owner's frame: one face
/// on the plane, centred below the base's foot on it, its half side
/// [`HALF_SPACE_CUBE_PER_REACH`] times (`reach_m` + the base's distance to the plane).
pub fn half_space_as_box(
    owner_in_base: DAffine3,
    origin: DAffine3,
    normal: DVec3,
    reach_m: f64,
) -> Collision {
    let base_in_shape = (owner_in_base * origin)
        .inverse()
        .transform_point3(DVec3::ZERO);
    let height = base_in_shape.dot(normal);
    let foot = base_in_shape - normal * height;
    let half = HALF_SPACE_CUBE_PER_REACH * (reach_m + height.abs());
    let placement = DAffine3::from_rotation_translation(
        DQuat::from_rotation_arc(DVec3::Z, normal),
        foot - normal * half,
    );
    Collision {
        origin: origin * placement,
        shape: Shape::Box {
            half_extents: DVec3::splat(half),
        },
    }
}

/// The rig as URDF text ([`export`] with no fixed links).
pub fn rig_to_urdf(rig: &Rig) -> String {
    export(rig, Vec::new()).text
}

/// The rig as URDF: base frame, one link per joint ([`generated_link_names`]), the tool
/// frame on a fixed joint, then `fixed` (tool, cell objects); origins, axes, limits (with
/// URDF 1.2's `acceleration`) exactly as the rig has them, so loading it back gives the same
/// forward kinematics. Each body of the rig is written on its frame's link when it names
/// that link, else as a fixed link of its own on it. Half-spaces (the base's, or `fixed`
/// ones hung on the base) become cubes ([`half_space_as_box`]) sized for `reach_m` (at least
/// the rig's own [`reach_bound_m`]).
pub fn export(rig: &Rig, fixed: Vec<FixedLink>) -> UrdfExport {
    export_with_reach(rig, fixed, reach_bound_m(rig, 0.0))
}

/// [`export`] with half-space cubes sized for `reach_m` (a tool makes the rig reach further).
pub fn export_with_reach(rig: &Rig, fixed: Vec<FixedLink>, reach_m: f64) -> UrdfExport {
    let links = generated_link_names(rig);
    let mut on_chain: Vec<Vec<Collision>> = vec![Vec::new(); rig.dof() + 1];
    let mut extra: Vec<FixedLink> = Vec::new();
    for body in &rig.bodies {
        let link = frame_link(rig, &links, body.frame);
        if body.name == link {
            on_chain[body.frame].extend(body.collisions.iter().cloned());
        } else {
            extra.push(FixedLink {
                name: body.name.clone(),
                parent: link.to_string(),
                origin: DAffine3::IDENTITY,
                collisions: body.collisions.clone(),
            });
        }
    }
    extra.extend(fixed);
    // Half-spaces sit on the base or on links hung from it (validated on load): their pose
    // in the base frame is their fixed origin there.
    let in_base = |link: &FixedLink| {
        if link.parent == rig.base_frame {
            link.origin
        } else {
            DAffine3::IDENTITY
        }
    };
    on_chain[0] = boxed(&on_chain[0], DAffine3::IDENTITY, reach_m);
    for link in &mut extra {
        link.collisions = boxed(&link.collisions, in_base(link), reach_m);
    }
    let mut writer = Writer::default();
    writer.robot(rig, &links, &on_chain, &extra);
    UrdfExport {
        text: writer.out,
        fixed: extra,
        meshes: writer.meshes,
    }
}

/// `collisions` with every half-space a cube ([`half_space_as_box`]).
fn boxed(collisions: &[Collision], owner_in_base: DAffine3, reach_m: f64) -> Vec<Collision> {
    collisions
        .iter()
        .map(|c| match &c.shape {
            Shape::HalfSpace { normal } => {
                half_space_as_box(owner_in_base, c.origin, *normal, reach_m)
            }
            _ => c.clone(),
        })
        .collect()
}

/// The text being written and the hull meshes it names. Writing to a String cannot fail;
/// the results of `writeln!` are ignored for that reason only.
#[derive(Default)]
struct Writer {
    out: String,
    meshes: Vec<HullMesh>,
}

impl Writer {
    fn robot(
        &mut self,
        rig: &Rig,
        links: &[String],
        on_chain: &[Vec<Collision>],
        extra: &[FixedLink],
    ) {
        let _ = writeln!(self.out, "<?xml version=\"1.0\"?>");
        // Version 1.2: the first with `acceleration` on `<limit>` (urdf-rs ignores it before).
        let _ = writeln!(
            self.out,
            "<robot name=\"{}\" version=\"1.2\">",
            xml_escape(&rig.name)
        );
        let next_origins = rig
            .joints
            .iter()
            .skip(1)
            .map(|j| j.origin.translation)
            .chain(std::iter::once(rig.tool.translation));
        let first = rig
            .joints
            .first()
            .map_or(DVec3::ZERO, |j| j.origin.translation);
        self.link(&rig.base_frame, first, &on_chain[0]);
        for ((name, next), collisions) in links.iter().zip(next_origins).zip(&on_chain[1..]) {
            self.link(name, next, collisions);
        }
        let _ = writeln!(
            self.out,
            "  <link name=\"{}\"/>",
            xml_escape(&rig.tool_frame)
        );
        for link in extra {
            self.link(&link.name, DVec3::ZERO, &link.collisions);
        }
        let parents = std::iter::once(&rig.base_frame).chain(links.iter());
        for ((joint, parent), child) in rig.joints.iter().zip(parents).zip(links) {
            let kind = match joint.kind {
                JointKind::Revolute => "revolute",
                JointKind::Prismatic => "prismatic",
            };
            let _ = writeln!(
                self.out,
                "  <joint name=\"{}\" type=\"{kind}\">",
                xml_escape(&joint.name)
            );
            self.frames(parent, child, &joint.origin);
            let a = joint.axis;
            let l = joint.limits;
            let _ = writeln!(self.out, "    <axis xyz=\"{} {} {}\"/>", a.x, a.y, a.z);
            let _ = writeln!(
                self.out,
                "    <limit lower=\"{}\" upper=\"{}\" velocity=\"{}\" acceleration=\"{}\" effort=\"{UNKNOWN_EFFORT}\"/>",
                l.lower, l.upper, l.max_speed, l.max_acceleration
            );
            let _ = writeln!(self.out, "  </joint>");
        }
        let last = links.last().unwrap_or(&rig.base_frame);
        self.fixed_joint(last, &rig.tool_frame, &rig.tool);
        for link in extra {
            self.fixed_joint(&link.parent, &link.name, &link.origin);
        }
        let _ = writeln!(self.out, "</robot>");
    }

    fn fixed_joint(&mut self, parent: &str, child: &str, origin: &DAffine3) {
        let _ = writeln!(
            self.out,
            "  <joint name=\"{}_joint\" type=\"fixed\">",
            xml_escape(child)
        );
        self.frames(parent, child, origin);
        let _ = writeln!(self.out, "  </joint>");
    }

    fn frames(&mut self, parent: &str, child: &str, origin: &DAffine3) {
        let _ = writeln!(self.out, "    <parent link=\"{}\"/>", xml_escape(parent));
        let _ = writeln!(self.out, "    <child link=\"{}\"/>", xml_escape(child));
        let _ = writeln!(self.out, "    {}", origin_element(origin));
    }

    /// A link with its solids as `<collision>` and `<visual>`; without any, a visual cylinder
    /// from its origin to `to` (the next joint's origin, in this link's frame).
    fn link(&mut self, name: &str, to: DVec3, collisions: &[Collision]) {
        let length = to.length();
        if collisions.is_empty() && length < MIN_SEGMENT_M {
            let _ = writeln!(self.out, "  <link name=\"{}\"/>", xml_escape(name));
            return;
        }
        let _ = writeln!(self.out, "  <link name=\"{}\">", xml_escape(name));
        if collisions.is_empty() {
            // URDF cylinders lie along their own z axis, centred on their origin.
            let rotation = DQuat::from_rotation_arc(DVec3::Z, to / length);
            let placement = DAffine3::from_rotation_translation(rotation, to * 0.5);
            let geometry = format!("<cylinder radius=\"{LINK_RADIUS_M}\" length=\"{length}\"/>");
            self.element("visual", &placement, &geometry);
        }
        for (i, collision) in collisions.iter().enumerate() {
            for (placement, geometry) in self.solids(name, i, collision) {
                self.element("collision", &placement, &geometry);
                self.element("visual", &placement, &geometry);
            }
        }
        let _ = writeln!(self.out, "  </link>");
    }

    fn element(&mut self, tag: &str, placement: &DAffine3, geometry: &str) {
        let _ = writeln!(self.out, "    <{tag}>");
        let _ = writeln!(self.out, "      {}", origin_element(placement));
        let _ = writeln!(self.out, "      <geometry>{geometry}</geometry>");
        let _ = writeln!(self.out, "    </{tag}>");
    }

    /// The URDF solids of one collision (`index` on link `link`), placed in the link's frame:
    /// one, or three for a capsule (a cylinder and two spheres).
    fn solids(&mut self, link: &str, index: usize, c: &Collision) -> Vec<(DAffine3, String)> {
        match &c.shape {
            Shape::Box { half_extents: h } => vec![(
                c.origin,
                format!("<box size=\"{} {} {}\"/>", 2.0 * h.x, 2.0 * h.y, 2.0 * h.z),
            )],
            Shape::Cylinder {
                radius,
                half_length,
            } => vec![(
                c.origin,
                format!(
                    "<cylinder radius=\"{radius}\" length=\"{}\"/>",
                    2.0 * half_length
                ),
            )],
            Shape::Sphere { radius } => vec![(c.origin, sphere(*radius))],
            Shape::Capsule { a, b, radius } => capsule(c.origin, *a, *b, *radius),
            Shape::ConvexHull { points } => {
                let file = format!("{}_{index}.obj", file_stem(link));
                self.meshes.push(HullMesh {
                    file: file.clone(),
                    points: points.clone(),
                });
                vec![(
                    c.origin,
                    format!("<mesh filename=\"{}\"/>", xml_escape(&file)),
                )]
            }
            // Converted to cubes before writing (`boxed`); a half-space left on a moving link
            // was refused on load, so there is nothing to write for it.
            Shape::HalfSpace { .. } => Vec::new(),
        }
    }
}

fn sphere(radius: f64) -> String {
    format!("<sphere radius=\"{radius}\"/>")
}

/// A capsule as a cylinder along its segment and a sphere at each end: the same solid.
fn capsule(origin: DAffine3, a: DVec3, b: DVec3, radius: f64) -> Vec<(DAffine3, String)> {
    let ends = [a, b].map(|p| (origin * DAffine3::from_translation(p), sphere(radius)));
    let length = (b - a).length();
    if length < MIN_SEGMENT_M {
        return vec![ends[0].clone()];
    }
    let rotation = DQuat::from_rotation_arc(DVec3::Z, (b - a) / length);
    let middle = origin * DAffine3::from_rotation_translation(rotation, (a + b) * 0.5);
    let cylinder = format!("<cylinder radius=\"{radius}\" length=\"{length}\"/>");
    let [first, second] = ends;
    vec![(middle, cylinder), first, second]
}

/// A link name as a file name: anything but letters, digits, `-` and `_` becomes `_`.
fn file_stem(name: &str) -> String {
    name.chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '_' {
                c
            } else {
                '_'
            }
        })
        .collect()
}

/// `<origin xyz rpy>` of a rigid transform; rpy in URDF's fixed-axis x, y, z order, the
/// inverse of `config::origin_from_xyz_rpy`. `{}` prints the shortest text that reads back
/// to the same f64.
fn origin_element(transform: &DAffine3) -> String {
    let (_, rotation, t) = transform.to_scale_rotation_translation();
    let (yaw, pitch, roll) = rotation.to_euler(EulerRot::ZYX);
    format!(
        "<origin xyz=\"{} {} {}\" rpy=\"{roll} {pitch} {yaw}\"/>",
        t.x, t.y, t.z
    )
}

fn xml_escape(text: &str) -> String {
    text.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rig::{load_rig, rig_from_urdf};
    use std::path::Path;

    fn config(name: &str) -> std::path::PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("config")
            .join(name)
    }

    /// Positions spread over each joint's range, none at zero, so every axis and origin counts.
    fn probes(rig: &Rig) -> Vec<Vec<f64>> {
        [0.13, 0.5, 0.87]
            .iter()
            .map(|share| {
                rig.joints
                    .iter()
                    .enumerate()
                    .map(|(i, j)| {
                        let s = (share + 0.11 * i as f64) % 1.0;
                        j.limits.lower + s * (j.limits.upper - j.limits.lower)
                    })
                    .collect()
            })
            .collect()
    }

    #[test]
    fn the_generated_urdf_loads_back_with_urdf_rs_and_gives_the_same_fk() {
        for file in ["irb120.toml", "painter.toml"] {
            let rig = load_rig(&config(file)).expect("the shipped rig loads");
            let text = rig_to_urdf(&rig);
            let robot = urdf_rs::read_from_string(&text).expect("urdf-rs reads the generated URDF");
            let links: Vec<&str> = robot.links.iter().map(|l| l.name.as_str()).collect();
            assert!(links.contains(&rig.base_frame.as_str()) && links.contains(&"tool0"));
            let back = rig_from_urdf(&text, Path::new("generated.urdf"))
                .expect("the generated URDF loads back as a rig");
            assert_eq!(back.dof(), rig.dof());
            assert_eq!(back.base_frame, rig.base_frame);
            assert_eq!(back.tool_frame, rig.tool_frame);
            for (a, b) in back.joints.iter().zip(&rig.joints) {
                assert_eq!((&a.name, a.kind), (&b.name, b.kind));
                assert_eq!(a.limits, b.limits);
            }
            for q in probes(&rig) {
                let ours = rig.forward(&q).expect("the rig takes the probe positions");
                let theirs = back
                    .forward(&q)
                    .expect("the loaded-back rig takes the probe positions");
                let dp = (ours.translation - theirs.translation).length();
                let dr = (ours.matrix3 - theirs.matrix3).abs().to_cols_array();
                assert!(dp <= 1e-12, "{file}: tool moved {dp} m");
                assert!(dr.iter().all(|d| *d <= 1e-12), "{file}: rotation differs");
            }
        }
    }

    #[test]
    fn link_names_avoid_the_base_and_tool_frames() {
        let mut rig = load_rig(&config("irb120.toml")).expect("the IRB 120 rig loads");
        rig.bodies.clear();
        rig.joints[0].name = rig.base_frame.clone();
        assert_eq!(generated_link_names(&rig)[0], "base_link_link");
        assert_eq!(generated_link_names(&rig)[1], "joint_2");
    }

    #[test]
    fn links_are_named_after_the_bodies_riding_them() {
        let rig = load_rig(&config("irb120.toml")).expect("the IRB 120 rig loads");
        let names = generated_link_names(&rig);
        for (k, name) in names.iter().enumerate() {
            if let Some(body) = rig.bodies.iter().find(|b| b.frame == k + 1) {
                assert_eq!(name, &body.name);
            }
        }
    }

    /// The rig's solids as urdf-rs reads them back: (link, placement, geometry).
    fn solids_of(text: &str) -> Vec<(String, DAffine3, urdf_rs::Geometry)> {
        let robot = urdf_rs::read_from_string(text).expect("urdf-rs reads the export");
        robot
            .links
            .iter()
            .flat_map(|l| {
                l.collision.iter().map(|c| {
                    let origin = crate::rig::origin_from_xyz_rpy(
                        DVec3::from_array(*c.origin.xyz),
                        DVec3::from_array(*c.origin.rpy),
                    );
                    (l.name.clone(), origin, c.geometry.clone())
                })
            })
            .collect()
    }

    #[test]
    fn a_capsule_is_a_cylinder_between_two_spheres() {
        let mut rig = load_rig(&config("irb120.toml")).expect("the IRB 120 rig loads");
        let (a, b) = (DVec3::new(0.1, 0.0, 0.0), DVec3::new(0.1, 0.0, 0.3));
        rig.bodies = vec![super::super::LinkBody {
            name: "upper".into(),
            frame: 2,
            collisions: vec![Collision {
                origin: DAffine3::from_translation(DVec3::new(0.0, 0.05, 0.0)),
                shape: Shape::Capsule { a, b, radius: 0.04 },
            }],
        }];
        let solids = solids_of(&rig_to_urdf(&rig));
        assert_eq!(solids.len(), 3);
        assert!(solids.iter().all(|(link, ..)| link == "upper"));
        let mut spheres = Vec::new();
        for (_, origin, geometry) in &solids {
            match geometry {
                urdf_rs::Geometry::Cylinder { radius, length } => {
                    assert_eq!((*radius, *length), (0.04, 0.3));
                    let centre = origin.translation;
                    assert!((centre - DVec3::new(0.1, 0.05, 0.15)).length() < 1e-12);
                    let axis = origin.transform_vector3(DVec3::Z);
                    assert!((axis - DVec3::Z).length() < 1e-12);
                }
                urdf_rs::Geometry::Sphere { radius } => {
                    assert_eq!(*radius, 0.04);
                    spheres.push(origin.translation);
                }
                _ => panic!("a capsule writes a cylinder and two spheres"),
            }
        }
        let expected = [a, b].map(|p| p + DVec3::new(0.0, 0.05, 0.0));
        assert!(
            spheres
                .iter()
                .zip(expected)
                .all(|(s, e)| (*s - e).length() < 1e-12)
        );
    }

    #[test]
    fn a_half_space_is_a_cube_whose_top_face_is_its_plane_below_the_reach() {
        let normal = DVec3::new(0.0, 0.6, 0.8);
        // The plane 0.2 m below the base along its normal.
        let origin = DAffine3::from_translation(-normal * 0.2);
        let reach = 0.7;
        let cube = half_space_as_box(DAffine3::IDENTITY, origin, normal, reach);
        let Shape::Box { half_extents } = cube.shape else {
            panic!("a half-space is written as a box");
        };
        let half = half_extents.x;
        assert_eq!(half_extents, DVec3::splat(half));
        assert!(half >= 2.0 * (reach + 0.2));
        // Its top face lies on the plane, facing out along the normal, under the base.
        let top = cube.origin.transform_point3(DVec3::Z * half);
        let up = cube.origin.transform_vector3(DVec3::Z);
        assert!((up - normal).length() < 1e-12);
        assert!((top - (-normal * 0.2)).length() < 1e-12, "{top}");
    }
}
