//! The painting task (issue 5): the room generator's geometry and errors, the painter rig,
//! the base-held FABRIK solver, and whole jobs streamed to the twin under the virtual
//! clock, judged by what the twin's world measured.

use crate::common;

use common::repo_path;
use glam::{DVec2, DVec3};
use rigbridge::apps::paint::body::{
    Body, Part, RoomTravel, Scratch, Travel, merge_room, room_cell,
};
use rigbridge::apps::paint::planner::Planner;
use rigbridge::apps::paint::room::{OpeningKind, RoomError, WallType, apothem};
use rigbridge::apps::paint::run::{PaintRun, run_paint};
use rigbridge::apps::paint::{
    EXTRA_AXES, LIFT_AXIS, PaintPlan, PaintSettings, load_paint_settings, plan_room, room_for,
    world_for,
};
use rigbridge::cell::CollisionModel;
use rigbridge::clock::VirtualClock;
use rigbridge::daemon::config::load_run_settings;
use rigbridge::ik::{BaseHeldSolver, IkSolver};
use rigbridge::link::LoopbackLink;
use rigbridge::rig::{ConfigError, Rig, Shape, load_rig};
use rigbridge::stream::{Outcome, StreamControl, StreamSettings, slowdown_rate, stream};
use rigbridge::trajectory::{PlanSettings, Trajectory};
use rigbridge::twin::{Twin, TwinSettings};
use std::num::NonZeroUsize;
use std::sync::{Arc, Mutex};

fn paint_settings() -> PaintSettings {
    load_paint_settings(&repo_path("config/paint.toml")).unwrap()
}

fn paint(walls: u32, seed: u64) -> PaintRun {
    let settings = load_run_settings(&repo_path("config/paint-run.toml")).unwrap();
    run_paint(
        &settings,
        &paint_settings(),
        walls,
        seed,
        &VirtualClock::new(),
        None,
        &StreamControl::default(),
        &mut |_| {},
    )
    .unwrap_or_else(|e| {
        panic!(
            "{walls} walls, seed {seed}: {}",
            rigbridge::daemon::error_chain(&e)
        )
    })
}

#[test]
fn wall_distance_is_the_seeds_formula() {
    let settings = paint_settings();
    for (walls, expected) in [(3, 1.5 / 3f64.sqrt()), (4, 1.5), (6, 1.5 * 3f64.sqrt())] {
        let room = room_for(&settings, walls, 0).unwrap();
        assert!(
            (room.apothem_m - expected).abs() < 1e-12,
            "{walls}: {}",
            room.apothem_m
        );
        for wall in &room.walls {
            let centre = (DVec2::from_array(wall.corners_xy[0])
                + DVec2::from_array(wall.corners_xy[1]))
                / 2.0;
            assert!((centre.length() - expected).abs() < 1e-12);
            let width = DVec2::from_array(wall.corners_xy[0])
                .distance(DVec2::from_array(wall.corners_xy[1]));
            assert!((width - 3.0).abs() < 1e-12);
        }
    }
    // 32 walls of 3 m stand 15.23 m from the centre: the base's x and y limits cover it.
    assert!((apothem(32, 3.0) - 15.229_7).abs() < 1e-4);
}

#[test]
fn walls_close_the_polygon_turning_by_360_over_n() {
    let settings = paint_settings();
    for walls in [3u32, 5, 8, 32] {
        let room = room_for(&settings, walls, 7).unwrap();
        for (i, wall) in room.walls.iter().enumerate() {
            let next = &room.walls[(i + 1) % room.walls.len()];
            let meet = DVec2::from_array(wall.corners_xy[0])
                .distance(DVec2::from_array(next.corners_xy[1]));
            assert!(meet < 1e-9, "wall {i} and {} do not meet: {meet}", i + 1);
            let step = next.heading_rad - wall.heading_rad;
            let expected = std::f64::consts::TAU / f64::from(walls);
            assert!(
                (step.rem_euclid(std::f64::consts::TAU) - expected).abs() < 1e-12,
                "{step}"
            );
        }
    }
}

#[test]
fn openings_keep_a_brush_width_apart_on_the_grid_and_never_overlap() {
    let settings = paint_settings();
    let brush = settings.config.brush.width_m;
    let mut seen = std::collections::HashSet::new();
    for seed in 0..40 {
        let room = room_for(&settings, 8, seed).unwrap();
        for wall in &room.walls {
            seen.insert(wall.wall_type);
            let mut edges = vec![0.0];
            for o in &wall.openings {
                edges.extend([o.left_m, o.right_m]);
                for x in [o.left_m, o.right_m, o.bottom_m, o.top_m] {
                    assert!(
                        ((x / 0.01) - (x / 0.01).round()).abs() < 1e-6,
                        "{x} off grid"
                    );
                }
                let expected = match o.kind {
                    OpeningKind::Door => (0.0, 2.0),
                    OpeningKind::Window => (0.9, 2.1),
                };
                assert_eq!((o.bottom_m, o.top_m), expected);
            }
            edges.push(room.wall_width_m);
            for gap in edges.windows(2).step_by(2) {
                assert!(gap[1] - gap[0] >= brush - 1e-9, "gap {gap:?} on {wall:?}");
            }
            let kinds: Vec<OpeningKind> = wall.openings.iter().map(|o| o.kind).collect();
            let doors = kinds.iter().filter(|k| **k == OpeningKind::Door).count();
            let windows = kinds.len() - doors;
            let expected = match wall.wall_type {
                WallType::Blank => (0, 0),
                WallType::Door => (1, 0),
                WallType::TwoWindows => (0, 2),
                WallType::DoorAndTwoWindows => (1, 2),
            };
            assert_eq!((doors, windows), expected);
        }
    }
    assert_eq!(seen.len(), 4, "every wall type appears: {seen:?}");
}

#[test]
fn door_and_two_windows_narrow_the_windows_to_fit_a_3_m_wall() {
    let settings = paint_settings();
    let wall = (0..50)
        .flat_map(|seed| room_for(&settings, 6, seed).unwrap().walls)
        .find(|w| w.wall_type == WallType::DoorAndTwoWindows)
        .expect("some seed draws a door and two windows");
    // 3.0 m - 0.9 m door - 4 brush widths = 1.7 m for two windows.
    assert_eq!(wall.narrowed_window_m, Some(0.85));
    for o in wall
        .openings
        .iter()
        .filter(|o| o.kind == OpeningKind::Window)
    {
        assert!((o.right_m - o.left_m - 0.85).abs() < 1e-9);
    }
}

#[test]
fn rooms_are_determined_by_the_seed() {
    let settings = paint_settings();
    let a = room_for(&settings, 12, 99).unwrap();
    let b = room_for(&settings, 12, 99).unwrap();
    assert_eq!(a, b);
    let c = room_for(&settings, 12, 100).unwrap();
    assert_ne!(a.walls, c.walls);
}

#[test]
fn bad_rooms_are_refused_with_the_value() {
    let settings = paint_settings();
    assert_eq!(
        room_for(&settings, 2, 0).unwrap_err(),
        RoomError::TooFewWalls { walls: 2 }
    );
    assert!(matches!(
        room_for(&settings, 33, 0),
        Err(RoomError::TooManyWalls { walls: 33, .. })
    ));
    let mut narrow = settings.config.room.clone();
    narrow.wall_width_m = 1.2;
    let error = (0..20)
        .find_map(|seed| {
            rigbridge::apps::paint::generate_room(4, seed, &narrow, 0.1)
                .err()
                .filter(|e| matches!(e, RoomError::OpeningsDoNotFit { .. }))
        })
        .expect("a 1.2 m wall cannot hold a door and two windows");
    let message = error.to_string();
    assert!(message.contains("1.2 m wall"), "{message}");
}

fn write_paint_variant(name: &str, edit: impl Fn(String) -> String) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("rigbridge-paint-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    for file in ["painter.toml", "paint.toml", "cell-painter.toml"] {
        std::fs::copy(repo_path(&format!("config/{file}")), dir.join(file)).unwrap();
    }
    let text = std::fs::read_to_string(repo_path("config/paint.toml")).unwrap();
    let path = dir.join(name);
    std::fs::write(&path, edit(text)).unwrap();
    path
}

#[test]
fn bad_paint_config_names_file_key_and_value() {
    let path = write_paint_variant("unknown.toml", |t| {
        t.replacen("width_m = 0.10", "width_m = 0.10\ncolour = \"red\"", 1)
    });
    let message = load_paint_settings(&path).unwrap_err().to_string();
    assert!(
        message.contains("unknown.toml") && message.contains("colour"),
        "{message}"
    );
    let path = write_paint_variant("off_grid.toml", |t| {
        t.replacen("door_width_m = 0.9", "door_width_m = 0.905", 1)
    });
    match load_paint_settings(&path).unwrap_err() {
        ConfigError::Invalid { key, value, .. } => {
            assert_eq!(key, "room.door_width_m");
            assert_eq!(value, "0.905");
        }
        other => panic!("{other}"),
    }
}

#[test]
fn a_travel_pose_outside_the_arms_limits_names_the_value_and_the_limits() {
    // joint_3 of the IRB 120 is +70 / -110 deg (config/painter.toml, as irb120.toml).
    let path = write_paint_variant("travel.toml", |t| {
        t.replacen(
            "travel_arm_deg = [0.0, 0.0, 0.0, 0.0, 30.0, 0.0]",
            "travel_arm_deg = [0.0, 0.0, 80.0, 0.0, 30.0, 0.0]",
            1,
        )
    });
    let message = load_paint_settings(&path).unwrap_err().to_string();
    assert!(
        message.contains(
            "key `strokes.travel_arm_deg[2]` = 80.0: \
             joint_3 = 80.000 deg is outside its limits [-110.000, 70.000] deg"
        ),
        "{message}"
    );
}

#[test]
fn the_painters_arm_is_the_irb120() {
    let painter = load_rig(&repo_path("config/painter.toml")).unwrap();
    let irb120 = load_rig(&repo_path("config/irb120.toml")).unwrap();
    let arm = painter.sub_chain(EXTRA_AXES).unwrap();
    assert_eq!(arm.joints, irb120.joints);
    assert_eq!(arm.tool, irb120.tool);
    assert_eq!(painter.dof(), 10);
}

#[test]
fn base_held_solver_moves_only_the_arm() {
    let painter = load_rig(&repo_path("config/painter.toml")).unwrap();
    let solver = BaseHeldSolver::new(painter.clone(), EXTRA_AXES).unwrap();
    let target_joints = [3.0, -2.0, 2.0, 1.2, 0.3, 0.4, -0.2, 0.5, 0.6, -0.4];
    let target = painter.tool_pose(&target_joints).unwrap();
    let mut seed = target_joints;
    for q in &mut seed[EXTRA_AXES..] {
        *q += 0.05;
    }
    let solution = solver.solve(&target, &seed).unwrap();
    assert_eq!(&solution.joints[..EXTRA_AXES], &target_joints[..EXTRA_AXES]);
    for (got, want) in solution.joints.iter().zip(target_joints) {
        assert!((got - want).abs() < 1e-6, "{got} vs {want}");
    }
    // Out of the arm's reach from where the base stands: an error, never a base move.
    let mut far = target;
    far.position.x += 2.0;
    assert!(solver.solve(&far, &seed).is_err());
}

/// The figures over a spread of N and seeds, measured by the twin.
fn assert_figures(run: &PaintRun, walls: u32, seed: u64) {
    let t = &run.paint.totals;
    let tag = format!("{walls} walls, seed {seed}");
    assert!(t.coverage >= 0.995, "{tag}: coverage {}", t.coverage);
    assert_eq!(t.paint_in_openings_m2, 0.0, "{tag}");
    assert_eq!(t.limit_violations, 0, "{tag}");
    assert_eq!(t.collisions, 0, "{tag}");
    assert!(
        run.paint.unreachable.is_empty(),
        "{tag}: {:?}",
        run.paint.unreachable
    );
    assert_eq!(run.run.stream.outcome, Outcome::Completed, "{tag}");
    assert_eq!(run.paint.walls.len(), walls as usize);
    for wall in &run.paint.walls {
        assert!(
            wall.coverage >= 0.99,
            "{tag}: wall {}: {}",
            wall.index,
            wall.coverage
        );
    }
    let sum: f64 = run.paint.walls.iter().map(|w| w.painted_m2).sum();
    assert!((sum - t.painted_m2).abs() < 1e-9);
}

#[test]
fn small_rooms_with_sharp_corners_are_painted() {
    for (walls, seed) in [(3, 0), (3, 5), (4, 1), (4, 6), (5, 2)] {
        assert_figures(&paint(walls, seed), walls, seed);
    }
}

#[test]
fn larger_rooms_are_painted() {
    for (walls, seed) in [(6, 3), (8, 4), (12, 8)] {
        assert_figures(&paint(walls, seed), walls, seed);
    }
}

#[test]
fn a_32_wall_room_is_painted() {
    assert_figures(&paint(32, 11), 32, 11);
}

/// Streams `trajectory` to a fresh twin whose world is `world`.
fn stream_into(
    trajectory: &Trajectory,
    settings: &PaintSettings,
    world: Arc<Mutex<rigbridge::apps::paint::PaintWorld>>,
    start: &[f64],
) {
    let twin = Twin::new(
        &settings.rig,
        TwinSettings {
            period: trajectory.period,
            ..TwinSettings::default()
        },
        start,
    )
    .unwrap()
    .with_world(Box::new(world));
    let mut link = LoopbackLink::new(twin);
    let report = stream(
        trajectory,
        &settings.rig,
        &mut link,
        &VirtualClock::new(),
        &mut (),
        &StreamControl::default(),
        &StreamSettings::new(trajectory.period, slowdown_rate(&settings.rig, 0.9, 0.8)),
    )
    .unwrap();
    assert_eq!(report.outcome, Outcome::Completed);
}

fn start_position() -> Vec<f64> {
    let mut start = vec![0.0; 10];
    start[8] = 30f64.to_radians();
    start
}

/// The first `last + 1` samples of `trajectory`.
fn head(trajectory: &Trajectory, last: usize) -> Trajectory {
    let (mut positions, mut velocities) = (Vec::new(), Vec::new());
    for i in 0..=last {
        positions.extend_from_slice(&trajectory.position(i));
        velocities.extend_from_slice(&trajectory.velocity(i));
    }
    Trajectory::new(
        trajectory.rig.clone(),
        trajectory.joint_names.clone(),
        trajectory.period,
        positions,
        velocities,
    )
    .unwrap()
}

#[test]
fn stroke_edges_are_straight_within_5_mm() {
    // A 2 mm grid, the first strokes of a room streamed through the twin (servo lag
    // included): every row of each band's interior has its left and right edges in the
    // same place to within 5 mm.
    let mut settings = paint_settings();
    settings.config.coverage.cell_m = 0.002;
    let start = start_position();
    let plan = PlanSettings {
        period: std::time::Duration::from_millis(10),
        ..PlanSettings::default()
    };
    let (room, planned) = plan_room(&settings, 5, 1, &start, &plan).unwrap();
    // The second and third strokes: ordinary columns, one up, one down.
    for stroke in &planned.strokes[1..3] {
        let world = Arc::new(Mutex::new(world_for(&settings, &room).unwrap()));
        stream_into(
            &head(&planned.trajectory, stroke.samples[1]),
            &settings,
            world.clone(),
            &start,
        );
        let world = world.lock().unwrap();
        let grid = &world.grids()[stroke.wall];
        let (lo, hi) = (
            stroke.v_from_m.min(stroke.v_to_m) + 0.1,
            stroke.v_from_m.max(stroke.v_to_m) - 0.1,
        );
        let s_cell = (stroke.s_m / grid.cell) as usize;
        let (mut lefts, mut rights) = (Vec::new(), Vec::new());
        for row in (lo / grid.cell) as usize..(hi / grid.cell) as usize {
            let painted = |c: usize| grid.painted[row * grid.cols + c];
            assert!(painted(s_cell), "row {row}: the band's centre is unpainted");
            // Walk out from the band's centre to the painted area's edges: on the left this
            // stroke's edge (columns go right to left), on the right an earlier stroke's.
            let mut left = s_cell;
            while left > 0 && painted(left - 1) {
                left -= 1;
            }
            let mut right = s_cell;
            while right + 1 < grid.cols && painted(right + 1) {
                right += 1;
            }
            lefts.push(left);
            rights.push(right);
        }
        for edges in [&lefts, &rights] {
            let spread = edges.iter().max().unwrap() - edges.iter().min().unwrap();
            assert!(
                spread as f64 * grid.cell <= 0.005,
                "edge wanders {spread} cells of {} m",
                grid.cell
            );
        }
    }
}

#[test]
fn the_brush_is_where_the_streamed_joints_put_it() {
    // The world computes the brush from the actual joints only (forward kinematics of
    // the whole rig and the tool): streaming the same plan twice paints the same cells,
    // and paint lands only inside the bands of the strokes streamed so far.
    let settings = paint_settings();
    let start = start_position();
    let plan = PlanSettings {
        period: std::time::Duration::from_millis(10),
        ..PlanSettings::default()
    };
    let (room, planned) = plan_room(&settings, 4, 2, &start, &plan).unwrap();
    let first = &planned.strokes[1];
    let trajectory = head(&planned.trajectory, first.samples[1]);
    let paint_with = |trajectory: &Trajectory| {
        let world = Arc::new(Mutex::new(world_for(&settings, &room).unwrap()));
        stream_into(trajectory, &settings, world.clone(), &start);
        let world = world.lock().unwrap();
        world.grids()[first.wall].painted.clone()
    };
    let once = paint_with(&trajectory);
    assert_eq!(once, paint_with(&trajectory));
    assert!(once.iter().any(|p| *p));
    let cols = (room.wall_width_m / settings.config.coverage.cell_m).round() as usize;
    let painted_cols: std::collections::BTreeSet<usize> = once
        .iter()
        .enumerate()
        .filter(|(_, p)| **p)
        .map(|(i, _)| i % cols)
        .collect();
    // Every painted column lies within the planned bands of the strokes streamed so far.
    for col in painted_cols {
        let s = (col as f64 + 0.5) * settings.config.coverage.cell_m;
        let near = planned.strokes[..2]
            .iter()
            .any(|st| st.wall == first.wall && (s - st.s_m).abs() <= 0.05 + 1e-9);
        assert!(near, "paint at s = {s} is outside the strokes streamed");
    }
}

#[test]
fn an_unreachable_stroke_is_reported_before_motion_and_planned_around() {
    // A reach the arm cannot hold from the floor: the planner finds no station for some
    // columns, says so, and plans the rest; nothing it plans collides.
    let mut settings = paint_settings();
    settings.config.strokes.reach_m = 0.95;
    let start = start_position();
    let plan = PlanSettings {
        period: std::time::Duration::from_millis(10),
        ..PlanSettings::default()
    };
    let outcome = plan_room(&settings, 3, 0, &start, &plan);
    match outcome {
        Ok((_, planned)) => {
            assert!(!planned.unreachable.is_empty());
            for stroke in &planned.unreachable {
                assert!(!stroke.reason.is_empty());
            }
            rigbridge::trajectory::validate(&planned.trajectory, &settings.rig).unwrap();
        }
        Err(e) => panic!("{}", rigbridge::daemon::error_chain(&e)),
    }
}

#[test]
fn shipped_paint_configs_load_and_run_knows_the_job() {
    let paint = paint_settings();
    assert_eq!(paint.rig.name, "painter");
    let run = load_run_settings(&repo_path("config/paint-run.toml")).unwrap();
    match &run.config.job {
        rigbridge::daemon::config::JobConfig::Paint(rigbridge::job::Paint {
            walls,
            paint_config,
            ..
        }) => {
            assert_eq!(*walls, 4);
            assert!(paint_config.ends_with("paint.toml") && paint_config.exists());
        }
        other => panic!("{other:?}"),
    }
    // `run` plans the same job through the job stage.
    let start = start_position();
    let plan = PlanSettings {
        period: std::time::Duration::from_millis(10),
        ..PlanSettings::default()
    };
    let trajectory = rigbridge::job::plan_job(&run.config.job, &run.rig, &start, &plan).unwrap();
    rigbridge::trajectory::validate(&trajectory, &run.rig).unwrap();
    assert!(trajectory.duration_s() > 100.0);
}

/// The report's room and tool and the log's joint states are enough to recompute the
/// coverage: this does it independently of the world's code (its own contact test, its own
/// rasterisation by two triangles per swept quad) and finds the report's figures.
#[test]
fn coverage_is_recomputed_from_the_log_and_the_report() {
    let settings = load_run_settings(&repo_path("config/paint-run.toml")).unwrap();
    let dir = std::env::temp_dir().join(format!("rigbridge-paint-log-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let log = dir.join("paint.mcap");
    let _ = std::fs::remove_file(&log);
    let run = run_paint(
        &settings,
        &paint_settings(),
        4,
        3,
        &VirtualClock::new(),
        Some(&log),
        &StreamControl::default(),
        &mut |_| {},
    )
    .unwrap();
    let report = serde_json::to_value(&run.paint).unwrap();
    let recorded = run.run.log.as_ref().unwrap();
    assert_eq!(recorded.dropped, 0, "{recorded:?}");
    let logged = rigbridge::log::read_log(&log).unwrap();
    assert_eq!(logged.states.len() as u64, run.run.stream.cycles);
    let rig = load_rig(&repo_path("config/painter.toml")).unwrap();
    assert_eq!(logged.joint_names, rig.joint_names().collect::<Vec<_>>());

    let tool = &report["tool"];
    let (width, handle, tolerance, cell) = (
        tool["brush_width_m"].as_f64().unwrap(),
        tool["handle_m"].as_f64().unwrap(),
        tool["contact_tolerance_m"].as_f64().unwrap(),
        tool["coverage_cell_m"].as_f64().unwrap(),
    );
    let room = &report["room"];
    let apothem = room["apothem_m"].as_f64().unwrap();
    let (wall_w, wall_h) = (
        room["wall_width_m"].as_f64().unwrap(),
        room["wall_height_m"].as_f64().unwrap(),
    );
    let walls: Vec<(DVec2, DVec2, Vec<[f64; 4]>)> = room["walls"]
        .as_array()
        .unwrap()
        .iter()
        .map(|w| {
            let n = DVec2::new(
                w["normal_xy"][0].as_f64().unwrap(),
                w["normal_xy"][1].as_f64().unwrap(),
            );
            let left = DVec2::new(
                w["corners_xy"][0][0].as_f64().unwrap(),
                w["corners_xy"][0][1].as_f64().unwrap(),
            );
            let openings = w["openings"]
                .as_array()
                .unwrap()
                .iter()
                .map(|o| ["left_m", "right_m", "bottom_m", "top_m"].map(|k| o[k].as_f64().unwrap()))
                .collect();
            (n, left, openings)
        })
        .collect();
    let (cols, rows) = (
        (wall_w / cell).round() as usize,
        (wall_h / cell).round() as usize,
    );
    let mut painted = vec![vec![false; cols * rows]; walls.len()];
    // Where the brush touches: the wall and its ends in (s, v), for one logged state.
    let touch = |q: &[f64]| -> Option<(usize, [DVec2; 2])> {
        let t = rig.forward(q).unwrap();
        let centre = t.transform_point3(glam::DVec3::new(0.0, 0.0, handle));
        let half = t.transform_vector3(glam::DVec3::X) * (width / 2.0);
        let ends = [centre - half, centre + half];
        walls.iter().enumerate().find_map(|(i, (n, left, _))| {
            let tangent = DVec2::new(n.y, -n.x);
            let on = ends.iter().all(|p| {
                let s = (p.truncate() - *left).dot(tangent);
                (apothem - p.truncate().dot(*n)).abs() <= tolerance
                    && s >= -tolerance
                    && s <= wall_w + tolerance
            });
            on.then(|| {
                let st = |p: &glam::DVec3| DVec2::new((p.truncate() - *left).dot(tangent), p.z);
                (i, [st(&ends[0]), st(&ends[1])])
            })
        })
    };
    let in_triangle = |p: DVec2, a: DVec2, b: DVec2, c: DVec2| {
        let d = |u: DVec2, v: DVec2, w: DVec2| (v - u).perp_dot(w - u);
        let (d1, d2, d3) = (d(a, b, p), d(b, c, p), d(c, a, p));
        let tol = 1e-12;
        (d1 >= -tol && d2 >= -tol && d3 >= -tol) || (d1 <= tol && d2 <= tol && d3 <= tol)
    };
    let mut previous: Option<(usize, [DVec2; 2])> = None;
    for state in &logged.states {
        let now = touch(&state.positions);
        if let (Some((wall, [b0, b1])), Some((before, [a0, a1]))) = (now, previous)
            && wall == before
        {
            let grid = &mut painted[wall];
            for row in 0..rows {
                for col in 0..cols {
                    let p = DVec2::new((col as f64 + 0.5) * cell, (row as f64 + 0.5) * cell);
                    let lo = a0.min(a1).min(b0).min(b1);
                    let hi = a0.max(a1).max(b0).max(b1);
                    if p.x < lo.x || p.y < lo.y || p.x > hi.x || p.y > hi.y {
                        continue;
                    }
                    let area =
                        (a1 - a0).perp_dot(b1 - a0).abs() + (b1 - a0).perp_dot(b0 - a0).abs();
                    if area > 0.0 && (in_triangle(p, a0, a1, b1) || in_triangle(p, a0, b1, b0)) {
                        grid[row * cols + col] = true;
                    }
                }
            }
        }
        previous = now;
    }
    let (mut paintable, mut covered, mut in_openings) = (0u64, 0u64, 0u64);
    for ((_, _, openings), grid) in walls.iter().zip(&painted) {
        for row in 0..rows {
            for col in 0..cols {
                let (s, v) = ((col as f64 + 0.5) * cell, (row as f64 + 0.5) * cell);
                let opening = openings
                    .iter()
                    .any(|[l, r, b, t]| s > *l && s < *r && v > *b && v < *t);
                let p = grid[row * cols + col];
                match (opening, p) {
                    (true, true) => in_openings += 1,
                    (true, false) => {}
                    (false, true) => {
                        paintable += 1;
                        covered += 1;
                    }
                    (false, false) => paintable += 1,
                }
            }
        }
    }
    let coverage = covered as f64 / paintable as f64;
    let reported = report["totals"]["coverage"].as_f64().unwrap();
    assert!(
        (coverage - reported).abs() < 1e-4,
        "recomputed {coverage}, reported {reported}"
    );
    assert_eq!(in_openings, 0);
    assert!(coverage >= 0.995);
}

/// `rigbridge paint --config FILE` from another directory paints with FILE's own
/// `[job] paint_config` (resolved next to FILE), not with a path relative to where it runs.
#[test]
fn the_paint_command_takes_the_paint_settings_from_its_run_settings() {
    let dir = std::env::temp_dir().join(format!("rigbridge-paint-cli-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let report = common::cli::paint_three_walls_in(&dir);
    assert_eq!(report["room"]["walls"].as_array().map(Vec::len), Some(3));
    assert!(
        report["totals"]["coverage"].as_f64().unwrap() >= 0.995,
        "{}",
        report["totals"]
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// The brush's sweep does not depend on how often the world sees it: the same strokes seen
/// at every 10 ms sample, at one in 10 and at one in 25 (a brush 10 or 25 times faster, or a
/// 10 or 4 Hz twin; these strokes cover 2.5 m in 3.77 s approach to retract, so one in 25
/// sees the brush move about 17 cm between two looks on average, more than its 10 cm
/// width) paint the same band with no hole in it or between neighbouring strokes. The thesis's strokes
/// were uneven because its counters ran per frame.
#[test]
fn paint_does_not_depend_on_how_often_the_brush_is_seen() {
    let settings = paint_settings();
    let start = start_position();
    let plan = PlanSettings {
        period: std::time::Duration::from_millis(10),
        ..PlanSettings::default()
    };
    let (room, planned) = plan_room(&settings, 4, 1, &start, &plan).unwrap();
    let last = planned.strokes[3].samples[1];
    let seen_every = |step: usize| {
        let mut world = world_for(&settings, &room).unwrap();
        let samples: Vec<usize> = (0..=last).step_by(step).chain([last]).collect();
        for &i in &samples {
            rigbridge::twin::TwinWorld::observe(&mut world, &planned.trajectory.position(i));
        }
        world
    };
    let wall = planned.strokes[1].wall;
    let painted =
        |world: &rigbridge::apps::paint::PaintWorld| world.grids()[wall].stats().painted_m2;
    let (every, tenth) = (painted(&seen_every(1)), painted(&seen_every(10)));
    assert!(every > 0.5, "three strokes paint more than 0.5 m2: {every}");
    assert!(
        (every - tenth).abs() <= 0.001 * every,
        "every sample {every} m2, one in 10 {tenth} m2"
    );
    // One in 25: the strokes' ends, where the brush lands and leaves, may lose a few
    // centimetres; their length and the seams between them may not.
    let sparse = seen_every(25);
    let grid = &sparse.grids()[wall];
    let (first, second) = (&planned.strokes[1], &planned.strokes[2]);
    let lowest = |s: &rigbridge::apps::paint::planner::PlannedStroke| s.v_from_m.min(s.v_to_m);
    let highest = |s: &rigbridge::apps::paint::planner::PlannedStroke| s.v_from_m.max(s.v_to_m);
    let (lo, hi) = (
        lowest(first).max(lowest(second)) + 0.05,
        highest(first).min(highest(second)) - 0.05,
    );
    let (left, right) = (first.s_m.min(second.s_m), first.s_m.max(second.s_m));
    let cell = grid.cell;
    for row in (lo / cell).ceil() as usize..(hi / cell) as usize {
        for column in (left / cell).ceil() as usize..=(right / cell) as usize {
            assert!(
                grid.painted[row * grid.cols + column],
                "a hole at s = {:.3} m, {:.3} m up, between strokes at {:.3} and {:.3} m",
                column as f64 * cell,
                row as f64 * cell,
                first.s_m,
                second.s_m
            );
        }
    }
}

/// Every number of `a` and `b` (strokes, unreachable bands, trajectory samples) is the
/// same bit for bit.
fn assert_same_plan(a: &PaintPlan, b: &PaintPlan, what: &str) {
    let bits = |values: &[f64]| values.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
    assert_eq!(a.strokes.len(), b.strokes.len(), "{what}: strokes");
    for (x, y) in a.strokes.iter().zip(&b.strokes) {
        assert_eq!(
            (x.wall, x.samples),
            (y.wall, y.samples),
            "{what}: stroke {x:?} vs {y:?}"
        );
        assert_eq!(
            bits(&[x.s_m, x.v_from_m, x.v_to_m, x.turn_deg, x.tilt_deg]),
            bits(&[y.s_m, y.v_from_m, y.v_to_m, y.turn_deg, y.tilt_deg]),
            "{what}: stroke {x:?} vs {y:?}"
        );
    }
    let unreachable = |plan: &PaintPlan| {
        plan.unreachable
            .iter()
            .map(|u| {
                (
                    u.wall,
                    bits(&[u.s_m, u.v_from_m, u.v_to_m]),
                    u.reason.clone(),
                )
            })
            .collect::<Vec<_>>()
    };
    assert_eq!(unreachable(a), unreachable(b), "{what}: unreachable");
    let (ta, tb) = (&a.trajectory, &b.trajectory);
    assert_eq!(ta.len(), tb.len(), "{what}: samples");
    assert_eq!(ta.period, tb.period);
    for i in 0..ta.len() {
        assert_eq!(
            bits(&ta.position(i)),
            bits(&tb.position(i)),
            "{what}: sample {i}"
        );
        assert_eq!(
            bits(&ta.velocity(i)),
            bits(&tb.velocity(i)),
            "{what}: sample {i}"
        );
    }
}

#[test]
fn the_plan_is_the_same_on_any_number_of_threads() {
    // Walls are planned side by side; the result must not depend on how many threads
    // share them, nor on which thread took which wall. A 3-walled room has the sharpest
    // corners (the most attitude search), the 8-walled one more walls than threads.
    let settings = paint_settings();
    let start = start_position();
    let plan = PlanSettings {
        period: std::time::Duration::from_millis(10),
        ..PlanSettings::default()
    };
    for (walls, seed) in [(8, 0), (3, 1)] {
        let room = room_for(&settings, walls, seed).unwrap();
        let planned = |threads: usize| {
            Planner::new(&settings, &room, plan)
                .unwrap()
                .with_threads(NonZeroUsize::new(threads).unwrap())
                .plan(&start)
                .unwrap()
        };
        let one = planned(1);
        assert!(one.strokes.len() > 10 * walls as usize);
        for threads in [2, 3] {
            let what = format!("{walls} walls, seed {seed}, {threads} threads");
            assert_same_plan(&one, &planned(threads), &what);
        }
    }
}

/// The rounding allowance the planner's sweeps add to the travel bound (m).
const BOUND_ROUNDING_M: f64 = 1e-9;

/// Uniform numbers in [0, 1) from a fixed seed (xorshift64), so the trials repeat.
fn uniform(seed: u64) -> impl FnMut() -> f64 {
    let mut state = seed;
    move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// Every point whose distance from a wall or the floor the planner measures: the ends of
/// the capsules' segments and the axes' centres of the vertical cylinders of the collision
/// model (the painter's bodies and the brush's handle; a cylinder stays vertical, so its
/// centre's motion is every point's), and the brush's contact ends.
fn measured_points(body: &Body, rig: &Rig, positions: &[f64]) -> Vec<DVec3> {
    let model = body.model();
    let mut scratch = model.scratch();
    let mut points = Vec::new();
    for placed in model.body_poses(positions, &mut scratch) {
        match model.shape(placed.shape) {
            Shape::Capsule { a, b, .. } => {
                points.extend([a, b].map(|p| placed.pose.transform_point3(*p)))
            }
            Shape::Cylinder { .. } => points.push(placed.pose.translation),
            _ => {}
        }
    }
    let tool0 = rig.forward(positions).unwrap();
    points.extend(body.brush.contact(&tool0));
    points
}

#[test]
fn the_travel_bounds_cover_every_point_the_planner_measures() {
    // The planner skips measuring samples these bounds place clear, so they must hold for
    // any two in-limit positions: far apart, a plan's step apart, or one joint moved. The
    // planar bound covers motion in the floor plan (the body's and the brush's distances
    // from the walls' planes), the vertical one motion up and down (the body's distance
    // from the floor).
    let settings = paint_settings();
    let rig = &settings.rig;
    let room = room_for(&settings, 3, 0).unwrap();
    let body = Body::new(rig, &room, &settings.config).unwrap();
    let vertical = Travel::vertical(rig, &body.brush);
    let planar = Travel::planar(rig, &body.brush);
    let mut next = uniform(0x2545_f491_4f6c_dd1d);
    let (mut tightest_vertical, mut tightest_planar) = (0.0f64, 0.0f64);
    let mut lift_only_vertical = 0.0f64;
    for trial in 0..20_000 {
        let a: Vec<f64> = rig
            .joints
            .iter()
            .map(|j| j.limits.lower + (j.limits.upper - j.limits.lower) * next())
            .collect();
        let (share, only) = match trial % 4 {
            0 => (1.0, None),
            1 => (0.01, None),
            _ => (0.05, Some(trial / 4 % rig.dof())),
        };
        let b: Vec<f64> = (a.iter().zip(&rig.joints).enumerate())
            .map(|(axis, (q, j))| {
                let span = j.limits.upper - j.limits.lower;
                let moved = q + (next() - 0.5) * share * span;
                match only {
                    Some(one) if one != axis => *q,
                    _ => moved.clamp(j.limits.lower, j.limits.upper),
                }
            })
            .collect();
        let (from, to) = (
            measured_points(&body, rig, &a),
            measured_points(&body, rig, &b),
        );
        let moved = |flat: bool| {
            from.iter()
                .zip(&to)
                .map(|(p, q)| match flat {
                    true => p.truncate().distance(q.truncate()),
                    false => (p.z - q.z).abs(),
                })
                .fold(0.0, f64::max)
        };
        for (travel, flat, tightest) in [
            (&vertical, false, &mut tightest_vertical),
            (&planar, true, &mut tightest_planar),
        ] {
            let bound = travel.between(&a, &b);
            let moved = moved(flat);
            assert!(
                moved <= bound + BOUND_ROUNDING_M,
                "from {a:?} to {b:?}: a point moves {moved} m (floor plan: {flat}, else up or down), bound {bound} m"
            );
            if bound > 0.0 {
                *tightest = tightest.max(moved / bound);
            }
        }
        if only == Some(LIFT_AXIS) && b[LIFT_AXIS] != a[LIFT_AXIS] {
            lift_only_vertical = lift_only_vertical.max(moved(false) / vertical.between(&a, &b));
            assert_eq!(
                planar.between(&a, &b),
                0.0,
                "the lift moves nothing in the plan"
            );
        }
    }
    // Not vacuous: moving the base alone moves every point by exactly the planar bound,
    // and the lift alone every point by exactly its stroke up (none in the floor plan).
    assert!(tightest_vertical > 0.99, "{tightest_vertical}");
    assert!(tightest_planar > 0.99, "{tightest_planar}");
    assert!(lift_only_vertical > 0.99, "{lift_only_vertical}");
}

#[test]
fn sweeps_skipping_samples_give_the_same_answers_as_measuring_all() {
    // A random walk of the painter through a 3-walled room, in and out of its walls and
    // its floor. The sweeps measure the walls and the floor apart, each with its own bound;
    // their answers must be those of the whole room's clearance at every sample.
    let settings = paint_settings();
    let rig = &settings.rig;
    let room = room_for(&settings, 3, 0).unwrap();
    let body = Body::new(rig, &room, &settings.config).unwrap();
    let travel = RoomTravel::new(rig, &body.brush);
    let mut scratch = Scratch::new(rig, &body);
    let mut next = uniform(0x9e37_79b9_7f4a_7c15);
    let mut walk = vec![start_position()];
    for _ in 0..4000 {
        let last = &walk[walk.len() - 1];
        let step: Vec<f64> = (last.iter().zip(&rig.joints))
            .map(|(q, j)| (q + (next() - 0.5) * 0.05).clamp(j.limits.lower, j.limits.upper))
            .collect();
        walk.push(step);
    }
    let measured: Vec<f64> = walk
        .iter()
        .map(|q| body.clearance(q, &mut scratch).0)
        .collect();
    let least = measured.iter().copied().fold(f64::INFINITY, f64::min);
    assert!(least < 0.0, "the walk must leave the room: {least}");
    let mut parts = Scratch::new(rig, &body);
    let floor_nearest = walk
        .iter()
        .filter(|q| {
            body.part_distance(Part::Floor, q, &mut parts)
                < body.part_distance(Part::Walls, q, &mut parts)
        })
        .count();
    // Not vacuous: the floor's part decides the answer at many samples (2087 of 4001).
    assert!(
        floor_nearest > 0,
        "the walk must come nearer the floor than the walls"
    );
    let mut measure = |part: Part, q: &[f64]| body.part_distance(part, q, &mut parts);
    for needed in [least - 0.1, least, 0.0, 0.01, 0.5, 10.0] {
        let lowest = travel.lowest(walk.iter().map(Vec::as_slice), needed, &mut measure);
        if least <= needed {
            assert_eq!(lowest.to_bits(), least.to_bits(), "needed {needed}");
        } else {
            assert!(lowest > needed, "needed {needed}: {lowest}");
        }
        let first = measured.iter().position(|c| *c < needed);
        let samples = walk.iter().map(Vec::as_slice).enumerate();
        let found = travel.first_below(samples, needed, &mut measure);
        assert_eq!(found.map(|(i, _)| i), first, "needed {needed}");
        if let (Some((i, value)), Some(_)) = (found, first) {
            assert_eq!(value.to_bits(), measured[i].to_bits());
        }
    }
}

/// A paint job is checked before motion against its own room's walls at the run cell's
/// margin, which must lie below the planner's clearance (kept at the planner's samples
/// only): a cell whose margin is not below it is refused before motion, naming both values.
#[test]
fn a_cell_margin_not_below_the_planners_clearance_is_refused_naming_both() {
    let dir = std::env::temp_dir().join(format!("rigbridge-paint-margin-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    for file in ["painter.toml", "paint.toml", "paint-run.toml"] {
        std::fs::copy(repo_path(&format!("config/{file}")), dir.join(file)).unwrap();
    }
    let cell = std::fs::read_to_string(repo_path("config/cell-painter.toml")).unwrap();
    assert!(
        cell.contains("margin_m = 0.005"),
        "the shipped painter cell's margin"
    );
    std::fs::write(
        dir.join("cell-painter.toml"),
        cell.replace("margin_m = 0.005", "margin_m = 0.01"),
    )
    .unwrap();
    let output = std::process::Command::new(env!("CARGO_BIN_EXE_rigbridge"))
        .args(["paint", "--walls", "3", "--seed", "2", "--clock", "virtual"])
        .arg("--config")
        .arg(dir.join("paint-run.toml"))
        .current_dir(&dir)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(!output.status.success(), "{stderr}");
    assert!(
        stderr.contains("margin_m = 0.01 m is not below")
            && stderr.contains("body.planning_clearance_m = 0.01 m"),
        "{stderr}"
    );
    let logged = std::fs::read_dir(dir.join("runs")).map_or(0, |entries| entries.count());
    assert_eq!(logged, 0, "refused before its log opened: nothing moved");
    let _ = std::fs::remove_dir_all(&dir);
}

/// The bottom strokes start at the floor (the brush 0.5 mm above it): the planner plans
/// against the room's floor as well as its walls, so every body of every plan's samples
/// stays above the floor by the painter cell's margin (config/cell-painter.toml, 5 mm;
/// docs/cell.md, "The painter's floor"). Measured here against the floor alone, every
/// sample, on the rooms the other tests paint.
#[test]
fn the_painters_plans_keep_every_body_above_the_floor() {
    let settings = paint_settings();
    let rig = &settings.rig;
    let plan = PlanSettings {
        period: std::time::Duration::from_millis(10),
        ..PlanSettings::default()
    };
    for (walls, seed) in [(3, 0), (3, 5), (4, 1), (5, 2), (8, 4)] {
        let (room, planned) = plan_room(&settings, walls, seed, &start_position(), &plan).unwrap();
        let mut floor_only = room_cell(rig, &room, &settings.config);
        floor_only.objects.retain(|object| object.name == "floor");
        assert_eq!(floor_only.objects.len(), 1, "the room's cell has its floor");
        let model = CollisionModel::new(rig, &floor_only).unwrap();
        let mut scratch = model.scratch();
        let trajectory = &planned.trajectory;
        let (lowest, at) = (0..trajectory.len())
            .map(|i| (model.clearance(&trajectory.position(i), &mut scratch), i))
            .min_by(|a, b| a.0.distance_m.total_cmp(&b.0.distance_m))
            .unwrap();
        let pair = format!(
            "{}-{}",
            model.body_name(lowest.a),
            model.body_name(lowest.b)
        );
        println!(
            "{walls} walls, seed {seed}: lowest {:.4} m above the floor ({pair}, sample {at} of {})",
            lowest.distance_m,
            trajectory.len()
        );
        assert!(
            lowest.distance_m >= 0.005,
            "{walls} walls, seed {seed}: {pair} {} m from the floor at sample {at}",
            lowest.distance_m
        );
        // Not vacuous: the strokes do reach down to the floor.
        assert!(
            lowest.distance_m < 0.1,
            "{walls}/{seed}: {}",
            lowest.distance_m
        );
    }
}

/// The painter's cell file gives the floor the room's cell gives too: merged, it is one
/// object; a cell whose `floor` is another solid (raised 5 cm) clashes with the room's and
/// the model refuses it, naming the floor, rather than keeping either silently.
#[test]
fn the_room_and_its_cells_floor_are_one_object_and_a_different_floor_is_refused() {
    let settings = paint_settings();
    let rig = &settings.rig;
    let room = room_cell(rig, &room_for(&settings, 4, 1).unwrap(), &settings.config);
    let run = load_run_settings(&repo_path("config/paint-run.toml")).unwrap();
    let merged = merge_room(&run.cell, &room);
    let floors = merged.objects.iter().filter(|o| o.name == "floor").count();
    assert_eq!(floors, 1, "{:?}", merged.objects);
    assert_eq!(merged.objects.len(), 4 + 1, "four walls and the floor");
    CollisionModel::new(rig, &merged).unwrap();
    let mut raised = run.cell.clone();
    let floor = raised
        .objects
        .iter_mut()
        .find(|o| o.name == "floor")
        .unwrap();
    floor.pose = glam::DAffine3::from_translation(DVec3::Z * 0.05);
    let refused = CollisionModel::new(rig, &merge_room(&raised, &room)).unwrap_err();
    assert!(refused.to_string().contains("floor"), "{refused}");
}
