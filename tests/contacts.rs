//! The twin measures the cell's clearances from the positions it reaches (issue 27): per
//! pair the smallest clearance within the cutoff, the collision episodes, and a strict
//! twin's collision fault when the arm runs into something. Checked against the collision
//! model asked at every cycle's actual positions, which the twin skips when a bound says
//! nothing can have changed.

use glam::{DAffine3, DVec3};
use rigbridge::cell::{Cell, CellObject, CollisionModel};
use rigbridge::protocol::{AxisValues, Command, ControllerStatus, Fault, JointTarget};
use rigbridge::rig::{Collision, Joint, JointKind, JointLimits, LinkBody, Rig, Shape};
use rigbridge::twin::{ContactWatch, Twin, TwinSettings, TwinWorld};
use std::sync::{Arc, Mutex};

const PERIOD_S: f64 = 0.004;
/// The ball's radius and the height its centre starts at, above the floor.
const BALL_M: f64 = 0.05;
const START_M: f64 = 0.3;

/// A vertical slide (z, from -1 m to 1 m) carrying a ball, over a floor half-space and
/// beside a post (a box whose near face is 0.12 m from the slide's axis).
fn slide() -> Rig {
    Rig {
        name: "slide".into(),
        base_frame: "base".into(),
        tool_frame: "tool".into(),
        joints: vec![Joint {
            name: "z".into(),
            kind: JointKind::Prismatic,
            origin: DAffine3::IDENTITY,
            axis: DVec3::Z,
            limits: JointLimits {
                lower: -1.0,
                upper: 1.0,
                max_speed: 1.0,
                max_acceleration: 10.0,
            },
        }],
        tool: DAffine3::IDENTITY,
        bodies: vec![LinkBody {
            name: "ball".into(),
            frame: 1,
            collisions: vec![Collision {
                origin: DAffine3::IDENTITY,
                shape: Shape::Sphere { radius: BALL_M },
            }],
        }],
        allowed_pairs: Vec::new(),
    }
}

fn cell() -> Cell {
    Cell {
        mount: DAffine3::IDENTITY,
        objects: vec![
            CellObject {
                name: "floor".into(),
                pose: DAffine3::IDENTITY,
                shape: Shape::HalfSpace { normal: DVec3::Z },
            },
            CellObject {
                name: "post".into(),
                pose: DAffine3::from_translation(DVec3::new(0.22, 0.0, 0.5)),
                shape: Shape::Box {
                    half_extents: DVec3::new(0.1, 0.1, 0.5),
                },
            },
        ],
        tool: None,
        margin_m: 0.01,
        allowed_pairs: Vec::new(),
        targets: Default::default(),
        parts: Vec::new(),
        gripper: Default::default(),
    }
}

/// Every cycle's actual position, as the twin reached it.
struct Trace(Vec<f64>);

impl TwinWorld for Trace {
    fn observe(&mut self, actual: &[f64]) {
        self.0.push(actual[0]);
    }
}

/// A twin of the slide at `START_M`, bound, watching its cell, tracing its positions.
fn watched_twin() -> (Twin, Arc<Mutex<Trace>>, Arc<CollisionModel>) {
    let (rig, cell) = (slide(), cell());
    let model = Arc::new(CollisionModel::new(&rig, &cell).expect("the slide's model builds"));
    let trace = Arc::new(Mutex::new(Trace(Vec::new())));
    let watch = ContactWatch::new(model.clone(), &rig, &cell, PERIOD_S);
    let mut twin = Twin::new(&rig, TwinSettings::default(), &[START_M])
        .expect("the slide's twin starts")
        .with_contacts(watch)
        .with_world(Box::new(trace.clone()));
    twin.bridge_hello();
    (twin, trace, model)
}

fn target(seq: u32, position: f64, velocity: f64) -> Command {
    Command::Target(JointTarget {
        seq,
        t: std::time::Duration::from_secs_f64(PERIOD_S) * seq,
        positions: AxisValues::from_slice(&[position]).expect("one axis"),
        velocities: AxisValues::from_slice(&[velocity]).expect("one axis"),
    })
}

/// Streams the slide from `START_M` down at `speed` (m/s, after a ramp at 5 m/s^2) to
/// `to`, holds there, then back up to `START_M` and holds, every target within the limits.
fn run(twin: &mut Twin, to: f64, speed: f64) {
    let (mut q, mut v, mut seq) = (START_M, 0.0f64, 1u32);
    let mut step = |twin: &mut Twin, goal: f64| {
        for _ in 0..2000 {
            let left = goal - q;
            let brake = (2.0 * 5.0 * left.abs()).sqrt().min(speed);
            let wanted = brake.copysign(left);
            v += (wanted - v).clamp(-5.0 * PERIOD_S, 5.0 * PERIOD_S);
            let next = q + v * PERIOD_S;
            q = if (goal - next) * left <= 0.0 {
                goal
            } else {
                next
            };
            if q == goal {
                v = 0.0;
            }
            twin.handle(&target(seq, q, v));
            twin.tick();
            seq += 1;
        }
    };
    step(twin, to);
    step(twin, START_M);
}

/// The least distance from the ball to each object over `trace`, asked of the model at
/// every position: (floor, post).
fn every_cycle(model: &CollisionModel, trace: &[f64]) -> (f64, f64) {
    let mut scratch = model.scratch();
    let mut found = Vec::new();
    let (mut floor, mut post) = (f64::INFINITY, f64::INFINITY);
    for q in trace {
        model.pairs_within(&[*q], f64::INFINITY, &mut scratch, &mut found);
        for c in &found {
            let other = if c.a == model.body_id("ball").expect("the ball") {
                c.b
            } else {
                c.a
            };
            match model.body_name(other) {
                "floor" => floor = floor.min(c.distance_m),
                "post" => post = post.min(c.distance_m),
                name => panic!("unexpected body {name}"),
            }
        }
    }
    (floor, post)
}

#[test]
fn the_twin_measures_each_pairs_least_clearance_from_the_positions_it_reached() {
    let (mut twin, trace, model) = watched_twin();
    let _ = twin.take_contacts();
    // Down to 0.08 m: the ball's surface 0.03 m over the floor, within the 0.05 m cutoff.
    run(&mut twin, 0.08, 0.5);
    let report = twin.take_contacts().expect("the twin watches its cell");
    let trace = trace.lock().expect("the trace is not poisoned");
    let (floor, post) = every_cycle(&model, &trace.0);
    assert_eq!(report.collisions, 0, "{report:?}");
    assert!(report.episodes.is_empty());
    let pair = report
        .pairs
        .iter()
        .find(|p| [p.a.as_str(), p.b.as_str()].contains(&"floor"))
        .expect("the floor came within the cutoff");
    assert!(
        (pair.min_clearance_m - floor).abs() <= rigbridge::twin::contact::RESOLUTION_M,
        "the least clearance of every cycle: {} and {floor}",
        pair.min_clearance_m
    );
    assert!((floor - 0.03).abs() < 0.005, "{floor}");
    assert_eq!(pair.status, "free");
    // The post's face stays 0.12 - 0.05 = 0.07 m away: beyond the cutoff, not listed.
    assert!(post > report.cutoff_m, "{post}");
    assert_eq!(report.pairs.len(), 1, "{report:?}");
    assert_eq!(report.cycles, trace.0.len() as u64);
    println!(
        "{} cycles, {} measured ({:.1} %); floor {:.6} m at {:.3} s",
        report.cycles,
        report.measured_cycles,
        100.0 * report.measured_cycles as f64 / report.cycles as f64,
        pair.min_clearance_m,
        pair.at_s
    );
    assert!(
        report.measured_cycles < report.cycles / 2,
        "the bound skips the cycles that change nothing: {} of {}",
        report.measured_cycles,
        report.cycles
    );
}

#[test]
fn a_twin_that_runs_into_its_floor_faults_with_the_bodies_named() {
    let (mut twin, trace, model) = watched_twin();
    let _ = twin.take_contacts();
    // Down to 0.02 m: the ball would sink 0.03 m into the floor.
    run(&mut twin, 0.02, 0.5);
    let status = twin.status();
    assert_eq!(status, ControllerStatus::Fault(Fault::Collision));
    let notice = twin
        .take_fault_notice()
        .expect("one Fault notice when the contact began");
    assert_eq!(notice.fault, Fault::Collision);
    assert!(
        notice.text.contains("ball") && notice.text.contains("floor"),
        "{}",
        notice.text
    );
    let report = twin.take_contacts().expect("the twin watches its cell");
    let trace = trace.lock().expect("the trace is not poisoned");
    let (floor, _) = every_cycle(&model, &trace.0);
    // Stopped where the contact began: the arm did not go on down to 0.02 m.
    let lowest = trace.0.iter().copied().fold(f64::INFINITY, f64::min);
    println!(
        "stopped at {lowest:.5} m (contact at {BALL_M} m), deepest {:.6} m; {}",
        -floor, notice.text
    );
    assert!(lowest > 0.045, "the arm stopped at the contact: {lowest}");
    assert_eq!(report.collisions, 1, "{report:?}");
    let episode = &report.episodes[0];
    assert_eq!(
        (episode.a.as_str(), episode.b.as_str()),
        ("ball", "floor"),
        "{report:?}"
    );
    assert!(
        (episode.depth_m + floor).abs() <= rigbridge::twin::contact::RESOLUTION_M,
        "the deepest of every cycle: {} and {}",
        episode.depth_m,
        -floor
    );
    assert!(report.pairs[0].status == "collision", "{report:?}");
    // Targets after the fault are dropped without motion.
    assert!(twin.counters().faulted_targets > 0);
}

#[test]
fn a_reset_lets_the_arm_leave_the_contact_it_stopped_in() {
    let (mut twin, _, _) = watched_twin();
    run(&mut twin, 0.02, 0.5);
    assert_eq!(twin.status(), ControllerStatus::Fault(Fault::Collision));
    let stopped = twin.actual()[0];
    assert!(twin.reset(), "the collision fault clears");
    twin.bridge_hello();
    let _ = twin.take_fault_notice();
    // Straight up out of the contact (0.1 m/s after a ramp at 5 m/s^2): no new impact,
    // so no new fault.
    let (mut q, mut v) = (stopped, 0.0f64);
    for seq in 1..250u32 {
        v = (v + 5.0 * PERIOD_S).min(0.1);
        q += v * PERIOD_S;
        twin.handle(&target(seq, q, v));
        twin.tick();
    }
    assert_ne!(
        twin.status(),
        ControllerStatus::Fault(Fault::Collision),
        "{:?}",
        twin.take_fault_notice()
    );
    assert!(twin.actual()[0] > BALL_M + 0.01, "{}", twin.actual()[0]);
}

#[test]
fn the_star_demo_reports_its_cells_clearances_and_no_collision() {
    let settings = rigbridge::daemon::config::load_run_settings(std::path::Path::new(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/config/rigbridge.toml"
    )))
    .expect("the shipped run settings load");
    let mut link = rigbridge::daemon::loopback_twin(&settings).expect("the twin starts");
    let clock = rigbridge::clock::VirtualClock::new();
    let control = rigbridge::stream::StreamControl::default();
    let job = settings.config.job.clone();
    let report = rigbridge::daemon::run_job(&settings, &job, &mut link, &clock, None, &control)
        .expect("the star job runs");
    let contacts = report
        .contacts
        .expect("the in-process twin measures its cell");
    println!(
        "star job: {} cycles, {} measured; {} pairs checked; closest {}",
        contacts.cycles,
        contacts.measured_cycles,
        contacts.checked_pairs,
        serde_json::to_string(&contacts.min_clearance).expect("JSON")
    );
    assert_eq!(contacts.collisions, 0, "{contacts:?}");
    assert!(contacts.checked_pairs > 0);
    // Measured from the job's first cycle: one twin cycle per streamed one.
    assert!(
        contacts.cycles as f64 >= 0.9 * report.stream.cycles as f64,
        "{} twin cycles, {} streamed",
        contacts.cycles,
        report.stream.cycles
    );
    assert!(contacts.measured_cycles > 0);
    let json = serde_json::to_value(&report.stream).expect("JSON");
    assert_eq!(json["outcome"], "completed");
}
