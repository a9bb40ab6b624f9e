//! The run's picture, hand-written SVG: the branches and the body's path seen from the side
//! (x-z) and from above (x-y), and a gait diagram with one stance bar per contact per limb
//! over time. Owns drawing only; it computes no figure the report does not already hold.

use super::rig::SlothRig;
use super::scenario::Scenario;
use super::walker::GaitPlan;
use glam::DVec3;
use std::fmt::Write;

const WIDTH: f64 = 900.0;
const VIEW_HEIGHT: f64 = 260.0;
const ROW: f64 = 22.0;
const MARGIN: f64 = 40.0;

/// Maps world coordinates (two of x, y, z) into a panel.
struct Panel {
    top: f64,
    min: (f64, f64),
    scale: f64,
}

impl Panel {
    fn fit(points: &[(f64, f64)], top: f64) -> Panel {
        let (mut lo, mut hi) = (
            (f64::INFINITY, f64::INFINITY),
            (f64::NEG_INFINITY, f64::NEG_INFINITY),
        );
        for (a, b) in points {
            lo = (lo.0.min(*a), lo.1.min(*b));
            hi = (hi.0.max(*a), hi.1.max(*b));
        }
        let span = ((hi.0 - lo.0) / (WIDTH - 2.0 * MARGIN))
            .max((hi.1 - lo.1) / (VIEW_HEIGHT - 2.0 * MARGIN))
            .max(1e-6);
        Panel {
            top,
            min: lo,
            scale: 1.0 / span,
        }
    }

    fn map(&self, (a, b): (f64, f64)) -> (f64, f64) {
        (
            MARGIN + (a - self.min.0) * self.scale,
            self.top + VIEW_HEIGHT - MARGIN - (b - self.min.1) * self.scale,
        )
    }
}

fn polyline(svg: &mut String, panel: &Panel, points: &[(f64, f64)], style: &str) {
    let coordinates: Vec<String> = points
        .iter()
        .map(|p| {
            let (x, y) = panel.map(*p);
            format!("{x:.1},{y:.1}")
        })
        .collect();
    let _ = writeln!(
        svg,
        r#"<polyline points="{}" fill="none" {style}/>"#,
        coordinates.join(" ")
    );
}

fn view(
    svg: &mut String,
    title: &str,
    top: f64,
    scenario: &Scenario,
    body_path: &[DVec3],
    project: impl Fn(DVec3) -> (f64, f64),
) {
    let mut extent: Vec<(f64, f64)> = body_path.iter().map(|p| project(*p)).collect();
    for c in &scenario.terrain.cylinders {
        extent.push(project(c.from));
        extent.push(project(c.to));
    }
    let panel = Panel::fit(&extent, top);
    let _ = writeln!(
        svg,
        r#"<text x="{MARGIN}" y="{:.0}" font-size="14">{title}</text>"#,
        top + 18.0
    );
    for c in &scenario.terrain.cylinders {
        let width = (2.0 * c.radius * panel.scale).max(2.0);
        polyline(
            svg,
            &panel,
            &[project(c.from), project(c.to)],
            &format!(r##"stroke="#8b5a2b" stroke-width="{width:.1}" stroke-linecap="round""##),
        );
    }
    let path: Vec<(f64, f64)> = body_path.iter().map(|p| project(*p)).collect();
    polyline(svg, &panel, &path, r##"stroke="#1f6fb2" stroke-width="2""##);
}

/// The picture of a run: views of the body's `body_path` (the twin's actual positions) and
/// the plan's stances.
pub fn render(
    sloth: &SlothRig,
    scenario: &Scenario,
    plan: &GaitPlan,
    body_path: &[DVec3],
) -> String {
    let limbs = sloth.limbs.len();
    let diagram_top = 2.0 * VIEW_HEIGHT + 20.0;
    let height = diagram_top + 40.0 + ROW * limbs as f64 + MARGIN;
    let mut svg = String::new();
    let _ = writeln!(
        svg,
        r#"<svg xmlns="http://www.w3.org/2000/svg" width="{WIDTH}" height="{height:.0}" font-family="sans-serif">"#
    );
    let _ = writeln!(svg, r#"<rect width="100%" height="100%" fill="white"/>"#);
    view(
        &mut svg,
        &format!("{}: side view (x-z), body path in blue", scenario.name),
        0.0,
        scenario,
        body_path,
        |p| (p.x, p.z),
    );
    view(
        &mut svg,
        "top view (x-y)",
        VIEW_HEIGHT,
        scenario,
        body_path,
        |p| (p.x, p.y),
    );
    let frames = plan.len().max(1) as f64;
    let scale = (WIDTH - 2.0 * MARGIN - 40.0) / frames;
    let _ = writeln!(
        svg,
        r#"<text x="{MARGIN}" y="{:.0}" font-size="14">gait diagram: stance bars over {:.1} s</text>"#,
        diagram_top + 18.0,
        (frames - 1.0) * plan.period.as_secs_f64()
    );
    for (index, limb) in sloth.limbs.iter().enumerate() {
        let y = diagram_top + 30.0 + ROW * index as f64;
        let _ = writeln!(
            svg,
            r#"<text x="{MARGIN}" y="{:.1}" font-size="12">{}</text>"#,
            y + 13.0,
            limb.name
        );
        for stance in plan.stances.iter().filter(|s| s.limb == index) {
            let x = MARGIN + 40.0 + stance.start as f64 * scale;
            let w = ((stance.end - stance.start) as f64 * scale).max(1.0);
            let _ = writeln!(
                svg,
                r##"<rect x="{x:.1}" y="{y:.1}" width="{w:.1}" height="{:.1}" fill="#444"/>"##,
                ROW - 6.0
            );
        }
    }
    svg.push_str("</svg>\n");
    svg
}
