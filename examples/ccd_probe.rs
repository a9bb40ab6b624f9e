use glam::{DQuat, DVec3};
use rigbridge::ik::{CcdSolver, IkSolver, Tolerance};
use rigbridge::rig::Pose;
use rigbridge::task::gait::SlothRig;
fn main() {
    let sloth = SlothRig::load(std::path::Path::new("config/sloth.toml")).unwrap();
    let a: Vec<f64> = std::env::args()
        .skip(1)
        .map(|x| x.parse().unwrap())
        .collect();
    let limb = &sloth.limbs[a[0] as usize];
    let solver = CcdSolver::new(limb.chain.clone())
        .position_only()
        .with_tolerance(Tolerance {
            position_m: 1e-4,
            orientation_rad: 3.2,
        })
        .with_max_iterations(2000);
    let seed: Vec<f64> = a[4..].iter().map(|d| d.to_radians()).collect();
    let r = solver.solve(
        &Pose::new(DVec3::new(a[1], a[2], a[3]), DQuat::IDENTITY),
        &seed,
    );
    match r {
        Ok(s) => println!(
            "ok {:?} it {}",
            s.joints.iter().map(|q| q.to_degrees()).collect::<Vec<_>>(),
            s.iterations
        ),
        Err(e) => println!("{e}"),
    }
}
