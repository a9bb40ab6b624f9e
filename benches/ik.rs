//! Time per pose of every IK solver on the IRB 120, in one criterion group (`ik`) so the
//! numbers compare: our FABRIK planner, CCD and gradient descent, rs-opw-kinematics' closed
//! form doing the planner's job (see `examples/opw_csv.rs`), and openrr's `k` Jacobian IK.
//! A second group (`fabrik_paper`) times one solve of the FABRIK paper's 10-ball-joint chain
//! experiment (`examples/fabrik_paper.rs`).
//!
//! ```text
//! cargo bench --bench ik
//! ```
//!
//! Before timing, prints once (stderr) each solver's success rate on the 1,000 poses (in
//! limits, and our FK within 1e-6 m / 1e-6 rad of the target, checked here, independently
//! of what the solver says), per-pose p50/p99/mean measured with `Instant`, FABRIK's p99,
//! and the median ratio fabrik/opw; then the paper experiment's table.
//!
//! Criterion entries time one pose per iteration, cycling through the pose set, so each
//! reported time is per pose (a mean over the poses a sample covered). `gd` cycles through
//! the first 50 poses only: it is slow.

#[allow(dead_code)]
#[path = "../examples/fabrik_paper.rs"]
mod fabrik_paper;
#[allow(dead_code)]
#[path = "../examples/opw_csv.rs"]
mod opw_csv;

use criterion::{Criterion, criterion_group, criterion_main};
use k::InverseKinematicsSolver;
use opw_csv::OpwSolver;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rigbridge::ik::{CcdSolver, FabrikSolver, GradientDescentSolver, IkSolver};
use rigbridge::rig::{Pose, Rig, load_rig};
use std::hint::black_box;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

const SEED: u64 = 120;
const POSES: usize = 1000;
/// Poses the `gd` entry cycles through (it takes milliseconds per pose).
const GD_POSES: usize = 50;
/// Success: position and orientation errors, as our solvers' default tolerance.
const TOLERANCE_M: f64 = 1e-6;
const TOLERANCE_RAD: f64 = 1e-6;
/// rs-opw's and k's FK must agree with ours this closely before they are timed.
const FRAME_AGREEMENT: f64 = 1e-9;

fn manifest(relative: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(relative)
}

struct Fixture {
    rig: Rig,
    configurations: Vec<Vec<f64>>,
    poses: Vec<Pose>,
}

impl Fixture {
    fn new() -> Self {
        let rig = load_rig(&manifest("config/irb120.toml")).expect("shipped IRB 120 config");
        let mut rng = ChaCha8Rng::seed_from_u64(SEED);
        let configurations: Vec<Vec<f64>> = (0..POSES)
            .map(|_| {
                rig.joints
                    .iter()
                    .map(|j| rng.random_range(j.limits.lower..j.limits.upper))
                    .collect()
            })
            .collect();
        let poses = configurations
            .iter()
            .map(|q| rig.tool_pose(q).expect("six joints"))
            .collect();
        Self {
            rig,
            configurations,
            poses,
        }
    }
}

/// Our own verdict on an answer: in limits, and our FK within tolerance of the target.
fn verifies(rig: &Rig, target: &Pose, joints: &[f64]) -> bool {
    if joints.len() != rig.dof() || rig.first_limit_violation(joints).is_some() {
        return false;
    }
    let reached = rig.tool_pose(joints).expect("dof checked");
    reached.position_error(target) <= TOLERANCE_M
        && reached.orientation_error(target) <= TOLERANCE_RAD
}

/// openrr's `k` on the IRB 120 URDF (ROS-Industrial's, base_link -> tool0), Jacobian IK,
/// every solve from the same start.
///
/// The `k` entry is the default solver (1 mm / 0.005 rad, 10 tries, gain 0.5) from
/// the zero configuration. But zero is a wrist singularity of the IRB 120 (axis 5 at 0 puts
/// axes 4 and 6 on one line), so k's square Jacobian has no inverse there and every solve
/// fails at once with `InverseMatrixError`: that entry times a failure. Two more entries say
/// what k does from a regular start (axis 5 at 30 deg, the rest 0): `k_j5_30deg` with its
/// defaults, and `k_tight_j5_30deg` asked for our 1e-6 m / 1e-6 rad with 100 tries.
struct KSolver {
    arm: k::SerialChain<f64>,
    solver: k::JacobianIkSolver<f64>,
    start: [f64; 6],
}

const K_REGULAR_START: [f64; 6] = [0.0, 0.0, 0.0, 0.0, 0.5235987755982988, 0.0];

impl KSolver {
    fn with(solver: k::JacobianIkSolver<f64>, start: [f64; 6]) -> Self {
        Self {
            solver,
            start,
            ..Self::new()
        }
    }

    fn new() -> Self {
        let urdf = std::env::var_os("RIGBRIDGE_REFERENCE_DIR")
            .map(PathBuf::from)
            .unwrap_or_else(|| manifest("../shared/reference"))
            .join("irb120_3_58.urdf");
        let chain = k::Chain::<f64>::from_urdf_file(&urdf)
            .unwrap_or_else(|e| panic!("{} is needed: {e}", urdf.display()));
        let tool0 = chain.find("link_6-tool0").expect("URDF has tool0");
        let arm = k::SerialChain::from_end(tool0);
        assert_eq!(arm.dof(), 6);
        Self {
            arm,
            solver: k::JacobianIkSolver::default(),
            start: [0.0; 6],
        }
    }

    fn forward(&self, joints: &[f64]) -> Pose {
        self.arm.set_joint_positions_unchecked(joints);
        let end = self.arm.end_transform();
        let (t, q) = (end.translation.vector, end.rotation.quaternion());
        Pose::new(
            glam::DVec3::new(t.x, t.y, t.z),
            glam::DQuat::from_xyzw(q.i, q.j, q.k, q.w),
        )
    }

    fn solve(&self, target: &Pose) -> Result<Vec<f64>, k::Error> {
        let (p, q) = (target.position, target.orientation);
        let target = k::Isometry3::from_parts(
            k::Translation3::new(p.x, p.y, p.z),
            k::UnitQuaternion::from_quaternion(k::nalgebra::Quaternion::new(q.w, q.x, q.y, q.z)),
        );
        self.arm.set_joint_positions_unchecked(&self.start);
        self.solver.solve(&self.arm, &target)?;
        Ok(self.arm.joint_positions())
    }
}

/// The largest (position, orientation) gap between `theirs` FK and ours.
fn frame_gap(fixture: &Fixture, theirs: impl Fn(&[f64]) -> Pose) -> (f64, f64) {
    fixture
        .configurations
        .iter()
        .fold((0.0, 0.0), |(dp, dr), q| {
            let ours = fixture.rig.tool_pose(q).expect("six joints");
            let other = theirs(q);
            (
                dp.max(ours.position_error(&other)),
                dr.max(ours.orientation_error(&other)),
            )
        })
}

/// One solver's run over a pose set: answers (None on failure) and per-pose times.
struct Run {
    answers: Vec<Option<Vec<f64>>>,
    nanos: Vec<f64>,
}

impl Run {
    fn measure(poses: &[Pose], mut solve: impl FnMut(&Pose) -> Option<Vec<f64>>) -> Self {
        let mut answers = Vec::with_capacity(poses.len());
        let mut nanos = Vec::with_capacity(poses.len());
        for pose in poses {
            let start = Instant::now();
            let answer = black_box(solve(black_box(pose)));
            nanos.push(start.elapsed().as_nanos() as f64);
            answers.push(answer);
        }
        nanos.sort_by(f64::total_cmp);
        Self { answers, nanos }
    }

    fn successes(&self, rig: &Rig, poses: &[Pose]) -> usize {
        self.answers
            .iter()
            .zip(poses)
            .filter(|(a, p)| a.as_deref().is_some_and(|q| verifies(rig, p, q)))
            .count()
    }

    /// Nearest-rank percentile, in microseconds.
    fn percentile_us(&self, p: f64) -> f64 {
        let rank = ((p / 100.0) * self.nanos.len() as f64).ceil().max(1.0) as usize;
        self.nanos[rank - 1] / 1e3
    }

    fn mean_us(&self) -> f64 {
        self.nanos.iter().sum::<f64>() / self.nanos.len() as f64 / 1e3
    }
}

/// A `k` run, with k's own verdicts beside ours.
struct KRun {
    run: Run,
    own_ok: usize,
    errors: std::collections::BTreeMap<String, usize>,
}

impl KRun {
    fn measure(solver: &KSolver, poses: &[Pose]) -> Self {
        let mut own_ok = 0;
        let mut errors = std::collections::BTreeMap::new();
        let run = Run::measure(poses, |p| match solver.solve(p) {
            Ok(answer) => {
                own_ok += 1;
                Some(answer)
            }
            Err(e) => {
                let debug = format!("{e:?}");
                let variant = debug.split([' ', '(', '{']).next().unwrap_or_default();
                *errors.entry(variant.to_string()).or_default() += 1;
                None
            }
        });
        Self {
            run,
            own_ok,
            errors,
        }
    }
}

struct Solvers {
    fabrik: FabrikSolver,
    ccd: CcdSolver,
    gd: GradientDescentSolver,
    opw: OpwSolver,
    k: KSolver,
    k_regular: KSolver,
    k_tight: KSolver,
}

impl Solvers {
    fn new(fixture: &Fixture) -> Self {
        let rig = fixture.rig.clone();
        let solvers = Self {
            fabrik: FabrikSolver::new(rig.clone()).expect("IRB 120 suits FABRIK"),
            ccd: CcdSolver::new(rig.clone()),
            gd: GradientDescentSolver::new(rig.clone()),
            opw: OpwSolver::irb120(rig),
            k: KSolver::new(),
            k_regular: KSolver::with(k::JacobianIkSolver::default(), K_REGULAR_START),
            k_tight: KSolver::with(
                k::JacobianIkSolver::new(TOLERANCE_M, TOLERANCE_RAD, 0.5, 100),
                K_REGULAR_START,
            ),
        };
        // An honest comparison needs the same robot and frames everywhere.
        let (dp, dr) = solvers.opw.check_frames(&fixture.configurations);
        assert!(
            dp <= FRAME_AGREEMENT && dr <= FRAME_AGREEMENT,
            "rs-opw's FK differs from ours by {dp:e} m / {dr:e} rad: fix the frame conversion"
        );
        let (kp, kr) = frame_gap(fixture, |q| solvers.k.forward(q));
        assert!(
            kp <= FRAME_AGREEMENT && kr <= FRAME_AGREEMENT,
            "k's FK differs from ours by {kp:e} m / {kr:e} rad"
        );
        eprintln!(
            "frame check over {POSES} configurations: rs-opw FK vs ours {dp:.1e} m / {dr:.1e} rad, \
             k FK vs ours {kp:.1e} m / {kr:.1e} rad (no conversion needed)"
        );
        solvers
    }
}

fn ours(solver: &impl IkSolver, pose: &Pose, seed: &[f64]) -> Option<Vec<f64>> {
    solver.solve(pose, seed).ok().map(|s| s.joints)
}

/// The once-only printout: success rates and `Instant` percentiles on the 1,000 poses.
fn report(fixture: &Fixture, solvers: &Solvers) {
    let (rig, poses) = (&fixture.rig, fixture.poses.as_slice());
    let zero = [0.0; 6];
    let fabrik = Run::measure(poses, |p| ours(&solvers.fabrik, p, &zero));
    let ccd = Run::measure(poses, |p| ours(&solvers.ccd, p, &zero));
    let gd = Run::measure(poses, |p| ours(&solvers.gd, p, &zero));
    let opw = Run::measure(poses, |p| ours(&solvers.opw, p, &zero));
    let k = KRun::measure(&solvers.k, poses);
    let k_regular = KRun::measure(&solvers.k_regular, poses);
    let k_tight = KRun::measure(&solvers.k_tight, poses);

    let opw_ok = opw.successes(rig, poses);
    assert_eq!(
        opw_ok, POSES,
        "every pose comes from an in-limit configuration: rs-opw must verify on all"
    );
    let same = fabrik
        .answers
        .iter()
        .zip(&opw.answers)
        .filter(|(a, b)| match (a, b) {
            (Some(a), Some(b)) => a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-6),
            _ => false,
        })
        .count();

    eprintln!(
        "\nIRB 120: {POSES} seeded random in-limit configurations (seed {SEED}), their FK poses, \
         seed all zeros.\nsuccess = in limits and our FK within {TOLERANCE_M:e} m / \
         {TOLERANCE_RAD:e} rad (checked here for every solver). Times per pose, Instant.\n"
    );
    eprintln!(
        "{:<16} {:>16} {:>10} {:>10} {:>10}",
        "solver", "success", "p50 us", "p99 us", "mean us"
    );
    for (name, run) in [
        ("fabrik", &fabrik),
        ("ccd", &ccd),
        ("gd", &gd),
        ("opw", &opw),
        ("k", &k.run),
        ("k_j5_30deg", &k_regular.run),
        ("k_tight_j5_30deg", &k_tight.run),
    ] {
        let ok = run.successes(rig, poses);
        eprintln!(
            "{name:<16} {:>16} {:>10.3} {:>10.3} {:>10.3}",
            format!("{ok}/{POSES} {:.1}%", 100.0 * ok as f64 / POSES as f64),
            run.percentile_us(50.0),
            run.percentile_us(99.0),
            run.mean_us()
        );
    }
    eprintln!(
        "\nFABRIK p50 {:.3} us, p99 {:.3} us; median ratio fabrik/opw = {:.2} \
         (Instant p50s; criterion's medians follow)",
        fabrik.percentile_us(50.0),
        fabrik.percentile_us(99.0),
        fabrik.percentile_us(50.0) / opw.percentile_us(50.0)
    );
    eprintln!(
        "fabrik and opw chose the same answer (every joint within 1e-6 rad) on {same}/{POSES} poses"
    );
    for (name, run) in [
        ("k", &k),
        ("k_j5_30deg", &k_regular),
        ("k_tight_j5_30deg", &k_tight),
    ] {
        eprintln!(
            "{name}: Ok by its own tolerance on {}/{POSES}; errors {:?}",
            run.own_ok, run.errors
        );
    }
    eprintln!();
}

/// Hands out the items of `items` in turn, forever.
fn cycle<'a, T>(items: &'a [T]) -> impl FnMut() -> &'a T {
    let mut i = 0;
    move || {
        let item = &items[i];
        i = (i + 1) % items.len();
        black_box(item)
    }
}

fn bench_ik(c: &mut Criterion) {
    let fixture = Fixture::new();
    let solvers = Solvers::new(&fixture);
    report(&fixture, &solvers);
    let poses = fixture.poses.as_slice();
    let zero = [0.0; 6];

    let mut group = c.benchmark_group("ik");
    group.bench_function("fabrik", |b| {
        let mut next = cycle(poses);
        b.iter(|| solvers.fabrik.solve(next(), &zero))
    });
    group.bench_function("ccd", |b| {
        let mut next = cycle(poses);
        b.iter(|| solvers.ccd.solve(next(), &zero))
    });
    group.bench_function("gd", |b| {
        let mut next = cycle(&poses[..GD_POSES]);
        b.iter(|| solvers.gd.solve(next(), &zero))
    });
    group.bench_function("opw", |b| {
        let mut next = cycle(poses);
        b.iter(|| solvers.opw.solve(next(), &zero))
    });
    group.bench_function("opw_inverse_only", |b| {
        let mut next = cycle(poses);
        b.iter(|| solvers.opw.all_solutions(next()))
    });
    for (name, k) in [
        ("k", &solvers.k),
        ("k_j5_30deg", &solvers.k_regular),
        ("k_tight_j5_30deg", &solvers.k_tight),
    ] {
        group.bench_function(name, |b| {
            let mut next = cycle(poses);
            b.iter(|| k.solve(next()))
        });
    }
    group.finish();
}

fn bench_fabrik_paper(c: &mut Criterion) {
    eprint!("\n{}", fabrik_paper::table(1000));
    let targets = fabrik_paper::targets(1000, fabrik_paper::SEED);
    let mut group = c.benchmark_group("fabrik_paper");
    for (name, solve) in [
        ("fabrik", fabrik_paper::solve_fabrik as fn(_) -> _),
        ("ccd", fabrik_paper::solve_ccd),
    ] {
        group.bench_function(name, |b| {
            let mut next = cycle(&targets);
            b.iter(|| solve(*next()))
        });
    }
    group.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default()
        .sample_size(20)
        .warm_up_time(Duration::from_secs(1))
        .measurement_time(Duration::from_secs(3));
    targets = bench_ik, bench_fabrik_paper
}
criterion_main!(benches);
