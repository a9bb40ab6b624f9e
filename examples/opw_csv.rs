use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rigbridge::rig::load_rig;
use rs_opw_kinematics::kinematic_traits::Kinematics;
use rs_opw_kinematics::kinematics_impl::OPWKinematics;
use rs_opw_kinematics::parameters::opw_kinematics::Parameters;
use std::path::Path;

fn main() {
    let rig = load_rig(Path::new("config/irb120.toml")).unwrap();
    let kin = OPWKinematics::new(Parameters::irb120_3_58());
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    for _ in 0..5 {
        let q: Vec<f64> = rig
            .joints
            .iter()
            .map(|j| rng.random_range(j.limits.lower..j.limits.upper))
            .collect();
        let ours = rig.tool_pose(&q).unwrap();
        let theirs = kin.forward(&q.clone().try_into().unwrap());
        println!("ours {:?} {:?}", ours.position, ours.orientation);
        println!("opw  {:?} {:?}", theirs.translation, theirs.rotation);
        let sols = kin.inverse(&theirs);
        println!("q {:?}", q);
        for s in sols {
            println!("  sol {:?}", s);
        }
    }
}
