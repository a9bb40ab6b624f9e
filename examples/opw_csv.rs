//! The `rigbridge ik` CSV job done by rs-opw-kinematics' closed-form solver instead of
//! FABRIK: the yardstick of `scripts/bench-ik-cli.sh`, and the `opw` entry of `benches/ik.rs`
//! (which includes this file as a module for [`OpwSolver`]).
//!
//! ```text
//! cargo run --release --example opw_csv -- --rig config/irb120.toml --input poses.csv --output joints.csv
//! ```
//!
//! Same contract as `rigbridge ik`: input header `x,y,z,qw,qx,qy,qz` (columns found by name),
//! output `j1..j6,pos_err_m,rot_err_rad,iterations,status` in degrees, each row seeded by the
//! previous row's answer (all zeros first; a failed row leaves the seed as it was), every
//! answer checked by our forward kinematics at 1e-6 m / 1e-6 rad. `iterations` is always 0
//! (closed form).
//!
//! Frame conventions, checked rather than assumed ([`OpwSolver::check_frames`] compares the
//! two forward kinematics): rs-opw's `Parameters::irb120_3_58()` is written in ROS-Industrial
//! joint coordinates (its `-pi/2` offset on axis 3 turns OPW's arm-straight-up zero into the
//! ROS zero) and ends in the `tool0` frame, exactly our rig's base_link -> tool0. So no
//! conversion is needed, of joints or of poses: its FK matches ours to ~1e-15.

use clap::Parser;
use glam::{DQuat, DVec3};
use rigbridge::ik::{IkError, IkSolution, IkSolver, Tolerance};
use rigbridge::rig::{Pose, Rig, load_rig};
use rs_opw_kinematics::glam as opw_glam;
use rs_opw_kinematics::kinematic_traits::{Joints, Kinematics};
use rs_opw_kinematics::kinematics_impl::OPWKinematics;
use rs_opw_kinematics::parameters::opw_kinematics::Parameters;
use rs_opw_kinematics::pose::Pose as OpwPose;
use std::f64::consts::TAU;
use std::path::PathBuf;

/// A joint value within this of a limit (rad) counts as on it: the same rounding allowance
/// as the FABRIK planner's, so the two solvers accept the same answers.
const LIMIT_SNAP: f64 = 1e-9;

/// rs-opw behind our [`IkSolver`] trait, doing the FABRIK planner's job: of all closed-form
/// solutions, plus every extra +-2pi turn that fits the rig's limits (raw values: axis 4
/// +-160 deg, axis 6 +-400 deg on the IRB 120), the in-limit one nearest the seed by the
/// planner's own cost (sum of squared joint moves divided by max speed), verified by our FK.
pub struct OpwSolver {
    rig: Rig,
    kinematics: OPWKinematics,
    tolerance: Tolerance,
}

impl OpwSolver {
    /// rs-opw's IRB 120-3/0.58 preset, for a rig loaded from `config/irb120.toml`.
    pub fn irb120(rig: Rig) -> Self {
        assert_eq!(rig.dof(), 6, "rs-opw solves six-axis arms");
        Self {
            rig,
            kinematics: OPWKinematics::new(Parameters::irb120_3_58()),
            tolerance: Tolerance::default(),
        }
    }

    pub fn kinematics(&self) -> &OPWKinematics {
        &self.kinematics
    }

    /// Our pose as rs-opw's (rs-opw is built on another glam version: copy the numbers).
    pub fn to_opw_pose(pose: &Pose) -> OpwPose {
        let (p, q) = (pose.position, pose.orientation);
        OpwPose::from_parts(
            opw_glam::DVec3::new(p.x, p.y, p.z),
            opw_glam::DQuat::from_xyzw(q.x, q.y, q.z, q.w),
        )
    }

    pub fn from_opw_pose(pose: &OpwPose) -> Pose {
        let (p, q) = (pose.translation, pose.rotation);
        Pose::new(
            DVec3::new(p.x, p.y, p.z),
            DQuat::from_xyzw(q.x, q.y, q.z, q.w),
        )
    }

    /// The largest (position m, orientation rad) gap between rs-opw's FK and ours over
    /// `configurations`: the frame-convention check.
    pub fn check_frames(&self, configurations: &[Vec<f64>]) -> (f64, f64) {
        configurations.iter().fold((0.0, 0.0), |(dp, dr), q| {
            let joints: Joints = q.as_slice().try_into().expect("six joints");
            let theirs = Self::from_opw_pose(&self.kinematics.forward(&joints));
            let ours = self.rig.tool_pose(q).expect("six joints");
            (
                dp.max(ours.position_error(&theirs)),
                dr.max(ours.orientation_error(&theirs)),
            )
        })
    }

    /// rs-opw's raw answers (all branches, each axis wrapped into (-pi, pi]).
    pub fn all_solutions(&self, target: &Pose) -> Vec<Joints> {
        self.kinematics.inverse(&Self::to_opw_pose(target))
    }

    /// The in-limit `value + k * 2pi` nearest `seed` (a hair past a limit snaps onto it).
    fn nearest_turn(&self, axis: usize, value: f64, seed: f64) -> Option<f64> {
        let limits = self.rig.joints[axis].limits;
        let first = ((limits.lower - LIMIT_SNAP - value) / TAU).ceil() as i64;
        let last = ((limits.upper + LIMIT_SNAP - value) / TAU).floor() as i64;
        (first..=last)
            .map(|k| (value + k as f64 * TAU).clamp(limits.lower, limits.upper))
            .min_by(|a, b| (a - seed).abs().total_cmp(&(b - seed).abs()))
    }
}

impl IkSolver for OpwSolver {
    fn name(&self) -> &'static str {
        "opw"
    }

    fn rig(&self) -> &Rig {
        &self.rig
    }

    fn solve(&self, target: &Pose, seed: &[f64]) -> Result<IkSolution, IkError> {
        let target = target.validated()?;
        if seed.len() != 6 || seed.iter().any(|s| !s.is_finite()) {
            return Err(IkError::InvalidSeed(format!("{seed:?}")));
        }
        let solutions = self.all_solutions(&target);
        if solutions.is_empty() {
            // rs-opw does not say why it found nothing; for a finite unit pose that means
            // the wrist centre is out of the arm's reach.
            return Err(IkError::OutOfReach {
                excess_m: f64::NAN,
                distance_m: f64::NAN,
                reach_m: f64::NAN,
            });
        }
        // The planner's cost is a sum over axes and the limits are per axis, so the best
        // turn of each axis is chosen alone: the nearest in-limit one.
        let mut best: Option<([f64; 6], f64)> = None;
        let mut blocked: Option<usize> = None;
        'solutions: for solution in &solutions {
            let mut joints = [0.0; 6];
            let mut cost = 0.0;
            for axis in 0..6 {
                let Some(q) = self.nearest_turn(axis, solution[axis], seed[axis]) else {
                    blocked.get_or_insert(axis);
                    continue 'solutions;
                };
                joints[axis] = q;
                cost += ((q - seed[axis]) / self.rig.joints[axis].limits.max_speed).powi(2);
            }
            if best.is_none_or(|(_, c)| cost < c) {
                best = Some((joints, cost));
            }
        }
        let Some((joints, _)) = best else {
            let axis = blocked.unwrap_or(0);
            return Err(IkError::NoSolutionWithinLimits {
                axis: axis + 1,
                joint: self.rig.joints[axis].name.clone(),
            });
        };
        // The same final gate as our solvers: our FK, our tolerance.
        let reached = self.rig.tool_pose(&joints)?;
        let position_error_m = reached.position_error(&target);
        let orientation_error_rad = reached.orientation_error(&target);
        if position_error_m <= self.tolerance.position_m
            && orientation_error_rad <= self.tolerance.orientation_rad
        {
            Ok(IkSolution {
                joints: joints.to_vec(),
                position_error_m,
                orientation_error_rad,
                iterations: 0,
            })
        } else {
            Err(IkError::NotConverged {
                iterations: 0,
                position_error_m,
                orientation_error_rad,
            })
        }
    }
}

#[derive(Parser)]
#[command(about = "The `rigbridge ik` CSV job, solved by rs-opw-kinematics")]
struct Args {
    #[arg(long, default_value = "config/irb120.toml")]
    rig: PathBuf,
    #[arg(long)]
    input: PathBuf,
    #[arg(long)]
    output: PathBuf,
}

/// The same CSV job as `rigbridge ik`: the library's own batch function, with the closed-form
/// solver behind the `IkSolver` trait, so only the solver differs between the two timings.
fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let rig = load_rig(&args.rig)?;
    let solver = OpwSolver::irb120(rig);
    let input = std::io::BufReader::new(std::fs::File::open(&args.input)?);
    let output = std::fs::File::create(&args.output)?;
    let summary = rigbridge::batch::ik_batch(&solver, &[0.0; 6], input, output, |_| {})?;
    eprintln!(
        "{} rows: {} ok, {} failed",
        summary.rows,
        summary.solved,
        summary.failed.values().sum::<usize>()
    );
    Ok(())
}
