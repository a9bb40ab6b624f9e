//! The collision model's speed (issue 27): one configuration of the IRB 120 with a tool and
//! 20 objects (target: median <= 5 us), and the continuous check of the star demo's whole
//! trajectory in its cell (config/cell-star.toml: floor, wall, pen; planned at the pen's
//! tip) (target: <= 10 ms).
//!
//! ```text
//! cargo bench --bench cell
//! ```
//!
//! The configurations are 1,000 seeded uniform ones within the joint limits; each iteration
//! measures the next, so the time is per configuration. The 20 objects are boxes, cylinders
//! and spheres spread around the arm within its reach, and the floor; the tool is a gripper
//! of two boxes. Before timing, prints how many configurations were free, within the margin
//! and in collision, so the figure is known to include both exact and pruned queries.

use criterion::{Criterion, criterion_group, criterion_main};
use glam::{DAffine3, DVec3};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rigbridge::cell::{Cell, CellObject, CollisionModel, Status, Tool};
use rigbridge::daemon::config::load_run_settings;
use rigbridge::rig::{Collision, Rig, Shape, load_rig, shipped};
use std::hint::black_box;

const SEED: u64 = 27;
const CONFIGURATIONS: usize = 1000;
/// Objects besides the floor: 19, so the cell holds 20.
const OBJECTS: usize = 19;

fn irb120() -> Rig {
    load_rig(&shipped::path("irb120.toml")).expect("the shipped IRB 120 loads")
}

/// A gripper: a body 60 x 80 x 60 mm on the flange and a finger block beyond it.
fn gripper() -> Tool {
    let block = |size: [f64; 3], z: f64| Collision {
        origin: DAffine3::from_translation(DVec3::new(0.0, 0.0, z)),
        shape: Shape::Box {
            half_extents: DVec3::from_array(size) / 2.0,
        },
    };
    Tool {
        name: "gripper".into(),
        bodies: vec![
            block([0.06, 0.08, 0.06], 0.03),
            block([0.02, 0.06, 0.04], 0.08),
        ],
        tcp: DAffine3::from_translation(DVec3::new(0.0, 0.0, 0.1)),
    }
}

/// Nineteen solids around the arm, 0.35 to 0.75 m from its axis, at heights up to 0.8 m.
fn objects(rng: &mut ChaCha8Rng) -> Vec<CellObject> {
    (0..OBJECTS)
        .map(|i| {
            let angle = std::f64::consts::TAU * i as f64 / OBJECTS as f64;
            let reach = rng.random_range(0.35..0.75);
            let centre = DVec3::new(
                reach * angle.cos(),
                reach * angle.sin(),
                rng.random_range(0.05..0.8),
            );
            let size = rng.random_range(0.03..0.1);
            let shape = match i % 3 {
                0 => Shape::Box {
                    half_extents: DVec3::new(size, size * 0.8, size * 1.2),
                },
                1 => Shape::Cylinder {
                    radius: size,
                    half_length: size * 1.5,
                },
                _ => Shape::Sphere { radius: size },
            };
            CellObject {
                name: format!("object_{i}"),
                pose: DAffine3::from_translation(centre),
                shape,
            }
        })
        .collect()
}

fn configurations(rig: &Rig, rng: &mut ChaCha8Rng) -> Vec<Vec<f64>> {
    (0..CONFIGURATIONS)
        .map(|_| {
            rig.joints
                .iter()
                .map(|j| rng.random_range(j.limits.lower..j.limits.upper))
                .collect()
        })
        .collect()
}

fn one_configuration(c: &mut Criterion) {
    let rig = irb120();
    let mut rng = ChaCha8Rng::seed_from_u64(SEED);
    let mut cell = Cell::builtin();
    cell.tool = Some(gripper());
    cell.objects.extend(objects(&mut rng));
    let model = CollisionModel::new(&rig, &cell).expect("the bench's cell fits the rig");
    let qs = configurations(&rig, &mut rng);
    let mut scratch = model.scratch();
    let mut counts = [0usize; 3];
    for q in &qs {
        let status = model.status(model.clearance(q, &mut scratch).distance_m);
        counts[match status {
            Status::Free => 0,
            Status::WithinMargin => 1,
            Status::Collision => 2,
        }] += 1;
    }
    eprintln!(
        "cell bench: {} objects, {} checked pairs; of {CONFIGURATIONS} configurations {} free, \
         {} within the margin, {} in collision",
        cell.objects.len(),
        model.checked_pairs().len(),
        counts[0],
        counts[1],
        counts[2]
    );
    let mut next = 0;
    c.bench_function("cell/clearance_irb120_tool_20_objects", |b| {
        b.iter(|| {
            next = (next + 1) % qs.len();
            black_box(model.clearance(black_box(&qs[next]), &mut scratch))
        })
    });
}

fn star_trajectory(c: &mut Criterion) {
    let settings = load_run_settings(&shipped::path("rigbridge.toml")).expect("the demo loads");
    let plan = rigbridge::daemon::plan_settings(&settings);
    // Planned at the pen's tip, as the job runs in its cell (the TCP, docs/cell.md).
    let at_tcp = settings.cell.rig_at_tcp(&settings.rig);
    let trajectory =
        rigbridge::job::plan_job(&settings.config.job, &at_tcp, &settings.initial(), &plan)
            .expect("the star plans");
    let period = plan.period.as_secs_f64();
    let model = &settings.collision;
    let mut scratch = model.scratch();
    let samples = || (0..trajectory.len()).map(|i| (i as f64 * period, trajectory.position(i)));
    match model.check_path(samples(), &mut scratch) {
        Ok(clear) => eprintln!(
            "star: {} samples ({:.1} s), clear; smallest measured clearance {:.4} m ({} - {}) at {:.3} s",
            trajectory.len(),
            trajectory.duration_s(),
            clear.min.distance_m,
            model.body_name(clear.min.a),
            model.body_name(clear.min.b),
            clear.at_t
        ),
        Err(hit) => eprintln!(
            "star: {} samples, REFUSED at {:.3} s: {} - {} at {:.4} m ({})",
            trajectory.len(),
            hit.t,
            model.body_name(hit.clearance.a),
            model.body_name(hit.clearance.b),
            hit.clearance.distance_m,
            hit.status
        ),
    }
    c.bench_function("cell/check_path_star", |b| {
        b.iter(|| black_box(model.check_path(samples(), &mut scratch).is_ok()))
    });
}

criterion_group!(benches, one_configuration, star_trajectory);
criterion_main!(benches);
