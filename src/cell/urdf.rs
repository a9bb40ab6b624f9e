//! The cell as one URDF (`rigbridge config urdf`, the attachment of every run log): the
//! rig's chain with its collision geometry, the tool fixed to the flange at its TCP, the
//! cell's objects fixed to the base, so any URDF tool sees the world the checker checks;
//! and the pairs never checked as an SRDF (MoveIt's `disable_collisions`). Owns the mapping
//! from a [`Cell`] to the rig's URDF writer only (`crate::rig::urdf_out` writes the text).

use super::Cell;
use crate::rig::{Collision, FixedLink, Rig, UrdfExport, export_with_reach, reach_bound_m};
use glam::DAffine3;
use std::fmt::Write;

/// `rig` (ending at its flange, tool0) in `cell` as URDF. The root is the rig's base frame;
/// each cell object is a fixed link on it (at `mount⁻¹ · pose`); the tool is a fixed link on
/// the rig's tool frame, placed at its TCP, named after the tool and carrying its solids, so
/// the chain ends at the TCP as `Cell::rig_at_tcp` does. Half-spaces become cubes sized for
/// the rig's reach with the tool (`crate::rig::half_space_as_box`).
pub fn cell_to_urdf(rig: &Rig, cell: &Cell) -> UrdfExport {
    let mut fixed = Vec::with_capacity(cell.objects.len() + 1);
    let mut beyond_flange = 0.0;
    if let Some(tool) = &cell.tool {
        let from_tcp = tool.tcp.inverse();
        beyond_flange = tool
            .bodies
            .iter()
            .filter_map(|c| Some(c.origin.translation.length() + c.shape.bounding_radius()?))
            .fold(tool.tcp.translation.length(), f64::max);
        fixed.push(FixedLink {
            name: tool.name.clone(),
            parent: rig.tool_frame.clone(),
            origin: tool.tcp,
            collisions: tool
                .bodies
                .iter()
                .map(|c| Collision {
                    origin: from_tcp * c.origin,
                    shape: c.shape.clone(),
                })
                .collect(),
        });
    }
    let cell_in_base = cell.mount.inverse();
    for object in &cell.objects {
        fixed.push(FixedLink {
            name: object.name.clone(),
            parent: rig.base_frame.clone(),
            origin: cell_in_base * object.pose,
            collisions: vec![Collision {
                origin: DAffine3::IDENTITY,
                shape: object.shape.clone(),
            }],
        });
    }
    export_with_reach(rig, fixed, reach_bound_m(rig, beyond_flange))
}

/// The pairs of bodies `rig` and `cell` list as never checked, as an SRDF (the file MoveIt
/// reads beside a URDF): one `disable_collisions` each, reason `rig` or `cell`. Pairs that
/// cannot move against each other (two bodies on one link, the objects and the base) are
/// not listed: any checker skips links joined by fixed joints only.
pub fn cell_to_srdf(rig: &Rig, cell: &Cell) -> String {
    let mut out = String::new();
    // Writing to a String cannot fail; the results are ignored for that reason only.
    let _ = writeln!(out, "<?xml version=\"1.0\"?>");
    let _ = writeln!(out, "<robot name=\"{}\">", escape(&rig.name));
    let listed = [("rig", &rig.allowed_pairs), ("cell", &cell.allowed_pairs)];
    for (reason, pairs) in listed {
        for (a, b) in pairs {
            let _ = writeln!(
                out,
                "  <disable_collisions link1=\"{}\" link2=\"{}\" reason=\"{reason}\"/>",
                escape(a),
                escape(b)
            );
        }
    }
    let _ = writeln!(out, "</robot>");
    out
}

fn escape(text: &str) -> String {
    text.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}
