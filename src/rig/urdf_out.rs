//! URDF export: a [`Rig`] written as a URDF serial chain, for tools that know robots by
//! their URDF (Foxglove's 3D panel reads it from a log attachment). Owns the text format of
//! the export only; it must not change the rig, and loading stays in `urdf.rs`. Each link
//! carries a plain cylinder from its origin to the next joint's, so a viewer has something to
//! draw for rigs that come without meshes.

use super::{JointKind, Rig};
use glam::{DAffine3, DQuat, DVec3, EulerRot};
use std::fmt::Write;

/// Radius of the cylinder drawn along each link: thick enough to see at arm scale (the IRB
/// 120's links are 0.07 to 0.3 m long), thin enough not to hide the frames.
const LINK_RADIUS_M: f64 = 0.025;
/// Segments shorter than this get no cylinder: a zero-length cylinder has no direction.
const MIN_SEGMENT_M: f64 = 1e-6;
/// URDF requires an effort limit on actuated joints; rigs carry none, and 0 means unknown.
const UNKNOWN_EFFORT: f64 = 0.0;

/// The links the export names, one per joint (the link the joint moves): the joint's own name,
/// as `Rig::sub_chain` names the frame after a joint, or `<joint>_link` where that would
/// clash with the base or tool frame.
pub fn generated_link_names(rig: &Rig) -> Vec<String> {
    rig.joints
        .iter()
        .map(|joint| {
            if joint.name == rig.base_frame || joint.name == rig.tool_frame {
                format!("{}_link", joint.name)
            } else {
                joint.name.clone()
            }
        })
        .collect()
}

/// The rig as URDF text: base frame, one link per joint ([`generated_link_names`]), the tool
/// frame on a fixed joint; origins, axes, limits (with URDF 1.2's `acceleration`) exactly as
/// the rig has them, so loading it back gives the same forward kinematics.
pub fn rig_to_urdf(rig: &Rig) -> String {
    let links = generated_link_names(rig);
    let mut out = String::new();
    // Writing to a String cannot fail; the results are ignored for that reason only.
    let _ = writeln!(out, "<?xml version=\"1.0\"?>");
    // Version 1.2: the first with `acceleration` on `<limit>` (urdf-rs ignores it before).
    let _ = writeln!(
        out,
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
    write_link(&mut out, &rig.base_frame, first);
    for (name, next) in links.iter().zip(next_origins) {
        write_link(&mut out, name, next);
    }
    let _ = writeln!(out, "  <link name=\"{}\"/>", xml_escape(&rig.tool_frame));
    let parents = std::iter::once(&rig.base_frame).chain(links.iter());
    for ((joint, parent), child) in rig.joints.iter().zip(parents).zip(&links) {
        let kind = match joint.kind {
            JointKind::Revolute => "revolute",
            JointKind::Prismatic => "prismatic",
        };
        let _ = writeln!(
            out,
            "  <joint name=\"{}\" type=\"{kind}\">",
            xml_escape(&joint.name)
        );
        write_frames(&mut out, parent, child, &joint.origin);
        let a = joint.axis;
        let l = joint.limits;
        let _ = writeln!(out, "    <axis xyz=\"{} {} {}\"/>", a.x, a.y, a.z);
        let _ = writeln!(
            out,
            "    <limit lower=\"{}\" upper=\"{}\" velocity=\"{}\" acceleration=\"{}\" effort=\"{UNKNOWN_EFFORT}\"/>",
            l.lower, l.upper, l.max_speed, l.max_acceleration
        );
        let _ = writeln!(out, "  </joint>");
    }
    let last = links.last().unwrap_or(&rig.base_frame);
    let _ = writeln!(
        out,
        "  <joint name=\"{}_joint\" type=\"fixed\">",
        xml_escape(&rig.tool_frame)
    );
    write_frames(&mut out, last, &rig.tool_frame, &rig.tool);
    let _ = writeln!(out, "  </joint>");
    let _ = writeln!(out, "</robot>");
    out
}

fn write_frames(out: &mut String, parent: &str, child: &str, origin: &DAffine3) {
    let _ = writeln!(out, "    <parent link=\"{}\"/>", xml_escape(parent));
    let _ = writeln!(out, "    <child link=\"{}\"/>", xml_escape(child));
    let _ = writeln!(out, "    {}", origin_element(origin));
}

/// A link with a cylinder from its origin to `to` (the next joint's origin, in this link's
/// frame); URDF cylinders lie along their own z axis, centred on their origin.
fn write_link(out: &mut String, name: &str, to: DVec3) {
    let length = to.length();
    if length < MIN_SEGMENT_M {
        let _ = writeln!(out, "  <link name=\"{}\"/>", xml_escape(name));
        return;
    }
    let rotation = DQuat::from_rotation_arc(DVec3::Z, to / length);
    let placement = DAffine3::from_rotation_translation(rotation, to * 0.5);
    let _ = writeln!(out, "  <link name=\"{}\">", xml_escape(name));
    let _ = writeln!(out, "    <visual>");
    let _ = writeln!(out, "      {}", origin_element(&placement));
    let _ = writeln!(
        out,
        "      <geometry><cylinder radius=\"{LINK_RADIUS_M}\" length=\"{length}\"/></geometry>"
    );
    let _ = writeln!(out, "    </visual>");
    let _ = writeln!(out, "  </link>");
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
        rig.joints[0].name = rig.base_frame.clone();
        assert_eq!(generated_link_names(&rig)[0], "base_link_link");
        assert_eq!(generated_link_names(&rig)[1], "joint_2");
    }
}
