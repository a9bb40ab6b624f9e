use rigbridge::task::gait::{Scenario, SlothRig, Walker};
use std::path::Path;
fn main() {
    let sloth = SlothRig::load(Path::new("config/sloth.toml")).unwrap();
    let args: Vec<String> = std::env::args().collect();
    let name = &args[1];
    let angle = args
        .get(2)
        .and_then(|a| a.parse().ok())
        .filter(|a: &f64| *a > 0.0);
    let gap = args.get(3).and_then(|a| a.parse().ok());
    let scenario = Scenario::build(name, angle, gap).unwrap();
    let t = std::time::Instant::now();
    let plan = Walker::new(&sloth, &scenario, 0.004).plan().unwrap();
    println!(
        "{} frames in {:?}, stop {:?}, residual {:.2e}, clearance {:.3}",
        plan.len(),
        t.elapsed(),
        plan.stop_reason,
        plan.ik_residual_max_m,
        plan.plan_clearance_min_m
    );
    let order: Vec<&str> = plan
        .touchdowns
        .iter()
        .map(|(_, l)| sloth.limbs[*l].name.as_str())
        .collect();
    println!("touchdowns {:?}", order);
    let first: Vec<String> = plan
        .frame(0)
        .iter()
        .zip(&sloth.streamed.joints)
        .map(|(q, j)| {
            if j.kind == rigbridge::rig::JointKind::Prismatic {
                format!("{q:.4}")
            } else {
                format!("{:.3}", q.to_degrees())
            }
        })
        .collect();
    println!("first [{}]", first.join(", "));
    let mut lo = vec![f64::INFINITY; plan.dof];
    let mut hi = vec![f64::NEG_INFINITY; plan.dof];
    for i in 0..plan.len() {
        for (a, q) in plan.frame(i).iter().enumerate() {
            lo[a] = lo[a].min(*q);
            hi[a] = hi[a].max(*q);
        }
    }
    for (a, j) in sloth.streamed.joints.iter().enumerate() {
        let f = if a < 3 {
            1.0
        } else {
            180.0 / std::f64::consts::PI
        };
        println!(
            "{:>18} {:9.2} {:9.2} span {:7.2}",
            j.name,
            lo[a] * f,
            hi[a] * f,
            (hi[a] - lo[a]) * f
        );
    }
}
#[allow(dead_code)]
fn unused() {}
