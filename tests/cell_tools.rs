//! The workcell's command-line tools (issue 27): `rigbridge check` (rows, statuses, bad
//! values named, exit codes), `rigbridge config urdf` (the rig in its cell, loadable by a
//! URDF reader we did not write), the batch tools at the cell tool's TCP, and the worked
//! example of docs/cell.md loading and running clear of its table.

use crate::common;

use common::{output_with_stdin, repo_path};
use rigbridge::daemon::config::load_run_settings;
use rigbridge::rig::rig_from_urdf;
use std::path::Path;
use std::process::{Command, Output};

const TABLE_CELL: &str = "config/table-cell.toml";

fn rigbridge(args: &[&str], stdin: &str) -> Output {
    output_with_stdin(
        Command::new(env!("CARGO_BIN_EXE_rigbridge"))
            .args(args)
            .current_dir(repo_path(""))
            .env_remove("RIGBRIDGE_CONFIG"),
        stdin,
    )
}

fn text(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).into_owned()
}

fn fields(line: &str) -> Vec<&str> {
    line.split(',').collect()
}

#[test]
fn check_passes_home_and_names_the_bodies_of_the_issues_folded_wrist() {
    let output = rigbridge(
        &["check"],
        "j1,j2,j3,j4,j5,j6\n0,0,0,0,30,0\n0,100,60,0,90,0\n",
    );
    // A row in collision: the batch ran, exit 3.
    assert_eq!(output.status.code(), Some(3), "{}", text(&output.stderr));
    let out = text(&output.stdout);
    let lines: Vec<&str> = out.lines().collect();
    assert_eq!(lines[0], "min_clearance_m,body_a,body_b,status");
    let home = fields(lines[1]);
    assert_eq!(home[3], "free", "{out}");
    assert!(home[0].parse::<f64>().unwrap() >= 0.01, "{out}");
    let folded = fields(lines[2]);
    assert_eq!(folded[3], "collision", "{out}");
    assert!(folded[0].parse::<f64>().unwrap() < 0.0, "{out}");
    assert!(!folded[1].is_empty() && !folded[2].is_empty() && folded[1] != folded[2]);
    let summary = text(&output.stderr);
    assert!(
        summary.contains("1 free") && summary.contains("1 collision"),
        "{summary}"
    );
}

#[test]
fn check_rows_name_the_column_and_the_value_that_is_wrong() {
    let output = rigbridge(
        &["check"],
        "j1,j2,j3,j4,j5,j6\n0,0,abc,0,30,0\n0,130,0,0,30,0\n0,0,0,0,30,0\n",
    );
    assert_eq!(output.status.code(), Some(3));
    let out = text(&output.stdout);
    let lines: Vec<&str> = out.lines().collect();
    assert_eq!(
        lines[1], ",,,invalid_input: j3 = abc is not a number",
        "{out}"
    );
    let outside = fields(lines[2]);
    assert_eq!(
        outside[3], "outside_limits: j2 = 130 deg outside [-110 110] deg",
        "{out}"
    );
    assert!(outside[0].parse::<f64>().is_ok(), "still measured: {out}");
    assert_eq!(fields(lines[3])[3], "free");
    let summary = text(&output.stderr);
    assert!(
        summary.contains("row 1 (line 2): j3 = abc is not a number"),
        "{summary}"
    );
    assert!(!summary.contains("Some("), "no debug text: {summary}");
    let missing = rigbridge(&["check"], "j1,j2\n0,0\n");
    assert_eq!(missing.status.code(), Some(1));
    assert!(text(&missing.stderr).contains("no column `j3`"));
}

#[test]
fn all_free_rows_exit_zero_and_a_file_output_is_written() {
    let dir = common::scratch_dir("cell_tools", "free");
    let (input, output) = (dir.join("in.csv"), dir.join("out.csv"));
    std::fs::write(&input, "j1,j2,j3,j4,j5,j6\n0,0,0,0,30,0\n10,5,5,0,30,0\n").unwrap();
    let run = rigbridge(
        &[
            "check",
            "--input",
            input.to_str().unwrap(),
            "--output",
            output.to_str().unwrap(),
        ],
        "",
    );
    assert!(run.status.success(), "{}", text(&run.stderr));
    let written = std::fs::read_to_string(&output).unwrap();
    assert_eq!(written.lines().count(), 3);
    assert!(
        written.lines().skip(1).all(|l| l.ends_with(",free")),
        "{written}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// The `<collision>` geometry elements of `link` in URDF text, by kind.
fn collision_kinds(robot: &urdf_rs::Robot, link: &str) -> Vec<&'static str> {
    let link = robot
        .links
        .iter()
        .find(|l| l.name == link)
        .unwrap_or_else(|| panic!("no link {link}"));
    link.collision
        .iter()
        .map(|c| match c.geometry {
            urdf_rs::Geometry::Box { .. } => "box",
            urdf_rs::Geometry::Cylinder { .. } => "cylinder",
            urdf_rs::Geometry::Sphere { .. } => "sphere",
            urdf_rs::Geometry::Mesh { .. } => "mesh",
            _ => "other",
        })
        .collect()
}

#[test]
fn config_urdf_writes_the_rig_its_tool_and_its_cell_for_a_urdf_reader() {
    let dir = common::scratch_dir("cell_tools", "urdf");
    let (urdf, srdf) = (dir.join("cell.urdf"), dir.join("cell.srdf"));
    let run = rigbridge(
        &[
            "config",
            "urdf",
            "--config",
            TABLE_CELL,
            "--output",
            urdf.to_str().unwrap(),
            "--srdf",
            srdf.to_str().unwrap(),
        ],
        "",
    );
    assert!(run.status.success(), "{}", text(&run.stderr));
    let written = std::fs::read_to_string(&urdf).unwrap();
    let robot = urdf_rs::read_from_string(&written).expect("urdf-rs reads it");
    let settings = load_run_settings(&repo_path(TABLE_CELL)).unwrap();
    // The objects and the tool, each a link of its own with its solids.
    assert_eq!(collision_kinds(&robot, "table"), ["box"]);
    assert_eq!(collision_kinds(&robot, "fixture"), ["box"]);
    assert_eq!(
        collision_kinds(&robot, "floor"),
        ["box"],
        "the floor's cube"
    );
    let tool = settings.cell.tool.as_ref().unwrap();
    assert_eq!(collision_kinds(&robot, &tool.name).len(), tool.bodies.len());
    // Every rig body is a link; a capsule is a cylinder and two spheres.
    for body in &settings.rig.bodies {
        let kinds = collision_kinds(&robot, &body.name);
        let capsules = body
            .collisions
            .iter()
            .filter(|c| matches!(c.shape, rigbridge::rig::Shape::Capsule { .. }))
            .count();
        let count = |k: &str| kinds.iter().filter(|x| **x == k).count();
        assert!(count("cylinder") >= capsules && count("sphere") >= 2 * capsules);
    }
    // Loaded back, the chain ends at the tool's TCP: the rig as jobs use it.
    let back = rig_from_urdf(&written, Path::new("cell.urdf")).expect("loads back as a rig");
    let at_tcp = settings.cell.rig_at_tcp(&settings.rig);
    assert_eq!(back.tool_frame, tool.name);
    let q = [0.4, -0.3, 0.2, 1.0, -0.8, 2.5];
    let (a, b) = (back.forward(&q).unwrap(), at_tcp.forward(&q).unwrap());
    assert!((a.translation - b.translation).length() < 1e-12);
    assert!(a.matrix3.abs_diff_eq(b.matrix3, 1e-12));
    let pairs = std::fs::read_to_string(&srdf).unwrap();
    for (a, b) in settings
        .rig
        .allowed_pairs
        .iter()
        .chain(&settings.cell.allowed_pairs)
    {
        assert!(
            pairs.contains(&format!("link1=\"{a}\" link2=\"{b}\"")),
            "{a} - {b} in {pairs}"
        );
    }
    // The built-in cell: the IRB 120 on its floor, to stdout.
    let builtin = rigbridge(&["config", "urdf"], "");
    assert!(builtin.status.success(), "{}", text(&builtin.stderr));
    let robot = urdf_rs::read_from_string(&text(&builtin.stdout)).unwrap();
    assert_eq!(collision_kinds(&robot, "floor"), ["box"]);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn the_worked_example_loads_and_its_job_keeps_clear_of_the_table() {
    let settings = load_run_settings(&repo_path(TABLE_CELL)).expect("the example loads");
    let cell = &settings.cell;
    let names: Vec<&str> = cell.objects.iter().map(|o| o.name.as_str()).collect();
    assert_eq!(names, ["floor", "table", "fixture"]);
    assert_eq!(cell.tool.as_ref().map(|t| t.name.as_str()), Some("gripper"));
    assert!((cell.mount.translation.z - 0.75).abs() < 1e-12);
    let rigbridge::daemon::config::JobConfig::MoveJoints(job) = &settings.config.job else {
        panic!("the example's job is move_joints");
    };
    let mut rows = String::from("j1,j2,j3,j4,j5,j6\n");
    for target in job
        .targets_deg
        .iter()
        .chain([&settings.config.twin.initial_deg])
    {
        let line: Vec<String> = target.iter().map(f64::to_string).collect();
        rows.push_str(&line.join(","));
        rows.push('\n');
    }
    let output = rigbridge(&["check", "--config", TABLE_CELL], &rows);
    assert!(
        output.status.success(),
        "{}{}",
        text(&output.stdout),
        text(&output.stderr)
    );
}

#[test]
fn fk_with_a_cell_tool_works_at_its_tcp_and_tool0_stays_available() {
    let rows = "j1,j2,j3,j4,j5,j6\n10,20,-10,30,40,50\n";
    let position = |args: &[&str]| -> [f64; 3] {
        let output = rigbridge(args, rows);
        assert!(output.status.success(), "{}", text(&output.stderr));
        let out = text(&output.stdout);
        let f = fields(out.lines().nth(1).unwrap());
        [0, 1, 2].map(|i| f[i].parse().unwrap())
    };
    let tcp = position(&["fk", "--config", TABLE_CELL]);
    let named = position(&["fk", "--config", TABLE_CELL, "--tool", "gripper"]);
    let flange = position(&["fk", "--config", TABLE_CELL, "--tool", "tool0"]);
    assert_eq!(tcp, named);
    let apart = (0..3)
        .map(|i| (tcp[i] - flange[i]).powi(2))
        .sum::<f64>()
        .sqrt();
    assert!(
        (apart - 0.15).abs() < 1e-9,
        "the TCP is 0.15 m out: {apart}"
    );
    let wrong = rigbridge(&["fk", "--config", TABLE_CELL, "--tool", "pen"], rows);
    assert_eq!(wrong.status.code(), Some(2));
    let message = text(&wrong.stderr);
    assert!(
        message.contains("gripper") && message.contains("tool0"),
        "{message}"
    );
}

/// Configurations the "never" pairs are tried in: ten times the command's own 10,000, from
/// another generator, so the check does not repeat the command's samples.
const NEVER_TRIALS: usize = 100_000;

#[test]
fn allowed_pairs_command_reproduces_the_shipped_rig_and_its_never_pairs_never_touch() {
    let rig_file = "config/irb120.toml";
    let output = rigbridge(&["config", "allowed-pairs", "--rig", rig_file], "");
    assert!(output.status.success(), "{}", text(&output.stderr));
    let key = text(&output.stdout);
    let key = key.trim_end();
    // The command's key put into the shipped file leaves it as it is: the two cannot drift.
    let shipped = std::fs::read_to_string(repo_path(rig_file)).unwrap();
    assert_eq!(
        rigbridge::cell::replace_allowed_pairs(&shipped, key),
        shipped,
        "{rig_file} does not hold what `rigbridge config allowed-pairs` finds:\n{key}"
    );
    // Each pair line: `["a", "b"], # reason, closest 0.123 m`.
    let pair_of = |line: &str| {
        let names: Vec<&str> = line.split('"').collect();
        (names[1].to_string(), names[3].to_string())
    };
    let never: Vec<(String, String)> = key
        .lines()
        .filter(|line| line.contains("# never in collision"))
        .map(pair_of)
        .collect();
    let adjacent = key.lines().filter(|l| l.contains("# adjacent")).count();
    assert_eq!(
        adjacent, 6,
        "the IRB 120's six joints each join two links:\n{key}"
    );
    assert!(!never.is_empty(), "{key}");
    // Every pair checked (none allowed), over fresh random configurations: a pair called
    // "never" must never touch.
    let rig = rigbridge::rig::Rig {
        allowed_pairs: Vec::new(),
        ..rigbridge::rig::load_rig(&repo_path(rig_file)).unwrap()
    };
    let empty = rigbridge::cell::Cell {
        objects: Vec::new(),
        ..rigbridge::cell::Cell::builtin()
    };
    let model = rigbridge::cell::CollisionModel::new(&rig, &empty).unwrap();
    let ids: Vec<(usize, usize)> = never
        .iter()
        .map(|(a, b)| {
            let (a, b) = (model.body_id(a).unwrap(), model.body_id(b).unwrap());
            (a.min(b), a.max(b))
        })
        .collect();
    let mut scratch = model.scratch();
    let mut within = Vec::new();
    let mut closest = f64::INFINITY;
    let mut rng = common::rng(27);
    for _ in 0..NEVER_TRIALS {
        let q = common::random_configuration(&rig, &mut rng);
        model.pairs_within(&q, f64::INFINITY, &mut scratch, &mut within);
        for c in within
            .iter()
            .filter(|c| ids.contains(&(c.a.min(c.b), c.a.max(c.b))))
        {
            assert!(
                c.distance_m > 0.0,
                "{} and {} touch at [{}] deg ({} m)",
                model.body_name(c.a),
                model.body_name(c.b),
                common::degrees(&q)
                    .iter()
                    .map(|v| format!("{v:.3}"))
                    .collect::<Vec<_>>()
                    .join(", "),
                c.distance_m
            );
            closest = closest.min(c.distance_m);
        }
    }
    eprintln!(
        "{} never pairs, closest over {NEVER_TRIALS} configurations: {closest:.4} m",
        never.len()
    );
}
