//! Terrain and walks from a file (config/forest.toml): the shipped walks rebuild the built-in
//! scenes exactly, a bad file is refused naming the file, the key and the value, a gait job
//! takes a walk from a forest, and the `fork` walk passes end to end on the twin.

use crate::common;

use common::repo_path;
use rigbridge::apps::gait::run::run_gait;
use rigbridge::apps::gait::scenario::Leg;
use rigbridge::apps::gait::{Forest, ForestError, Scenario, SlothRig};
use rigbridge::clock::VirtualClock;
use rigbridge::daemon::config::{JobConfig, load_run_settings};
use rigbridge::rig::ConfigError;
use rigbridge::stream::StreamControl;
use std::path::{Path, PathBuf};

fn trunk_tilt_rad() -> f64 {
    SlothRig::load(&repo_path("config/sloth.toml"))
        .expect("config/sloth.toml loads")
        .gait
        .trunk_tilt_rad
}

fn shipped() -> Forest {
    Forest::load(&repo_path("config/forest.toml"), trunk_tilt_rad())
        .unwrap_or_else(|e| panic!("{e}"))
}

fn temp_dir() -> PathBuf {
    let dir = std::env::temp_dir().join(format!("rigbridge-forest-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn close(a: glam::DVec3, b: glam::DVec3) -> bool {
    a.distance(b) <= 1e-12
}

/// A leg as the route uses it, with route distances measured from the scenario's start
/// (a file's walk counts from its first support's start, the built-in scenes from their
/// bend or trunk). The first leg also covers everything before it, so it is anchored at the
/// start itself.
fn from_start(scenario: &Scenario) -> Vec<Leg> {
    let mut legs = scenario.route.legs.clone();
    let first = &mut legs[0];
    first.origin += first.direction * (scenario.start_s - first.start_s);
    first.start_s = scenario.start_s;
    for leg in &mut legs {
        leg.start_s -= scenario.start_s;
    }
    legs
}

fn assert_same_scene(walk: &Scenario, built_in: &Scenario) {
    let (a, b) = (&walk.terrain.cylinders, &built_in.terrain.cylinders);
    assert_eq!(a.len(), b.len(), "{}", walk.name);
    for (x, y) in a.iter().zip(b) {
        assert!(close(x.from, y.from) && close(x.to, y.to), "{x:?} vs {y:?}");
        assert!((x.radius - y.radius).abs() <= 1e-12, "{x:?} vs {y:?}");
    }
    let (a, b) = (from_start(walk), from_start(built_in));
    assert_eq!(a.len(), b.len(), "{}", walk.name);
    for (x, y) in a.iter().zip(&b) {
        assert!((x.start_s - y.start_s).abs() <= 1e-12, "{x:?} vs {y:?}");
        assert!(close(x.origin, y.origin), "{x:?} vs {y:?}");
        assert!(close(x.direction, y.direction), "{x:?} vs {y:?}");
        assert!(close(x.up, y.up), "{x:?} vs {y:?}");
        assert_eq!((x.left, x.right), (y.left, y.right), "{x:?} vs {y:?}");
        assert_eq!(x.twist_rad_per_m, y.twist_rad_per_m);
    }
    // The body's middle starts at the same place.
    assert!(close(
        walk.route.point(walk.start_s),
        built_in.route.point(built_in.start_s)
    ));
    assert_eq!(walk.cycles, built_in.cycles);
    assert_eq!(
        (walk.tail_first, walk.sideways),
        (built_in.tail_first, built_in.sideways)
    );
    assert_eq!((walk.angle_deg, walk.gap_m), (None, None));
}

#[test]
fn the_shipped_forest_loads_its_walks() {
    let forest = shipped();
    let names: Vec<&str> = forest.walk_names().collect();
    assert_eq!(names, ["fork", "rise", "climb", "climb-out"]);
    let fork = forest.scenario("fork").unwrap();
    assert_eq!(fork.name, "fork");
    // The fork's second leg starts at the bend, 1.2 m along the first branch.
    assert!((fork.route.legs[1].start_s - 1.2).abs() <= 1e-12);
}

#[test]
fn fork_is_the_135_deg_branch_turn() {
    let built_in = Scenario::build("branch-turn", Some(135.0), None).unwrap();
    assert_same_scene(&shipped().scenario("fork").unwrap(), &built_in);
}

#[test]
fn rise_is_the_150_deg_height_change() {
    let built_in = Scenario::build("height-change", Some(150.0), None).unwrap();
    assert_same_scene(&shipped().scenario("rise").unwrap(), &built_in);
}

#[test]
fn climb_is_the_trunk_up_scene() {
    let built_in = Scenario::build("trunk-up", None, None).unwrap();
    let climb = shipped().scenario("climb").unwrap();
    assert_same_scene(&climb, &built_in);
    assert!(close(climb.route.legs[0].up, glam::DVec3::X));
}

#[test]
fn an_unknown_walk_is_refused_with_the_file_and_the_walks() {
    let error = shipped().scenario("canopy").unwrap_err();
    assert!(matches!(error, ForestError::UnknownWalk { .. }));
    let message = error.to_string();
    assert!(message.contains("forest.toml"), "{message}");
    assert!(message.contains("canopy"), "{message}");
    assert!(message.contains("fork, rise, climb"), "{message}");
}

/// A small forest: a branch along +x ending at the origin, one going on toward +x+y, a
/// vertical trunk at x = 1.
const SMALL: &str = r#"
[[support]]
name = "west"
from_m = [-1.0, 0.0, 0.0]
to_m = [0.0, 0.0, 0.0]
radius_m = 0.02

[[support]]
name = "east"
from_m = [0.0, 0.0, 0.0]
to_m = [1.0, 1.0, 0.0]
radius_m = 0.02

[[support]]
name = "trunk"
from_m = [1.0, 0.0, -1.0]
to_m = [1.0, 0.0, 2.0]
radius_m = 0.08

[[walk]]
name = "fork"
supports = ["west", "east"]
start_m = 0.5

[[walk]]
name = "climb"
supports = ["trunk"]
start_m = 0.5
"#;

fn write_forest(name: &str, text: &str) -> PathBuf {
    let path = temp_dir().join(name);
    std::fs::write(&path, text).unwrap();
    path
}

/// `SMALL` with `from` replaced by `to` (once), loaded: the error it gives.
fn refused(name: &str, from: &str, to: &str) -> ConfigError {
    assert!(SMALL.contains(from), "{from}");
    let path = write_forest(name, &SMALL.replacen(from, to, 1));
    Forest::load(&path, trunk_tilt_rad()).expect_err("the bad forest is refused")
}

/// The error names the file, the key and the value, and gives `reason_contains`.
fn assert_names(error: &ConfigError, name: &str, key: &str, value: &str, reason_contains: &str) {
    let message = error.to_string();
    match error {
        ConfigError::Invalid {
            file,
            key: k,
            value: v,
            reason,
        } => {
            assert!(file.ends_with(name), "{message}");
            assert_eq!(k, key, "{message}");
            assert_eq!(v, value, "{message}");
            assert!(reason.contains(reason_contains), "{message}");
        }
        other => panic!("expected Invalid, got {other}"),
    }
    assert!(message.contains(name) && message.contains(key) && message.contains(value));
}

#[test]
fn the_small_forest_loads() {
    let path = write_forest("small.toml", SMALL);
    let forest = Forest::load(&path, trunk_tilt_rad()).unwrap_or_else(|e| panic!("{e}"));
    let fork = forest.scenario("fork").unwrap();
    assert_eq!(fork.terrain.cylinders.len(), 2);
    let second = fork.route.legs[1];
    assert!((second.start_s - 1.0).abs() <= 1e-12);
    assert!(close(second.origin, glam::DVec3::ZERO));
    assert!(close(
        second.direction,
        glam::DVec3::new(1.0, 1.0, 0.0).normalize()
    ));
}

#[test]
fn an_unknown_support_in_a_walk_is_refused() {
    let error = refused(
        "unknown-support.toml",
        r#"supports = ["west", "east"]"#,
        r#"supports = ["west", "nowhere"]"#,
    );
    assert_names(
        &error,
        "unknown-support.toml",
        "walk[0].supports[1]",
        "\"nowhere\"",
        "no support of that name (the file's supports: west, east, trunk)",
    );
}

#[test]
fn a_radius_of_zero_or_less_is_refused() {
    for (name, radius) in [
        ("zero-radius.toml", "0.0"),
        ("negative-radius.toml", "-0.02"),
    ] {
        let error = refused(name, "radius_m = 0.08", &format!("radius_m = {radius}"));
        assert_names(
            &error,
            name,
            "support[2].radius_m",
            radius,
            "must be a finite number above 0",
        );
    }
}

#[test]
fn a_support_of_no_length_is_refused() {
    let error = refused(
        "no-length.toml",
        "to_m = [1.0, 1.0, 0.0]",
        "to_m = [0.0, 0.0, 0.0]",
    );
    assert_names(
        &error,
        "no-length.toml",
        "support[1].to_m",
        "[0.0, 0.0, 0.0]",
        "support east must be at least 0.001 m long",
    );
    let error = refused(
        "almost-no-length.toml",
        "to_m = [1.0, 1.0, 0.0]",
        "to_m = [0.0, 0.0, 0.0001]",
    );
    assert_names(
        &error,
        "almost-no-length.toml",
        "support[1].to_m",
        "[0.0, 0.0, 0.0001]",
        "at least 0.001 m long",
    );
}

#[test]
fn non_finite_numbers_are_refused() {
    let error = refused(
        "nan.toml",
        "from_m = [-1.0, 0.0, 0.0]",
        "from_m = [nan, 0.0, 0.0]",
    );
    assert_names(
        &error,
        "nan.toml",
        "support[0].from_m",
        "[NaN, 0.0, 0.0]",
        "finite",
    );
    let error = refused("inf-radius.toml", "radius_m = 0.08", "radius_m = inf");
    assert_names(
        &error,
        "inf-radius.toml",
        "support[2].radius_m",
        "inf",
        "finite",
    );
    let error = refused("inf-start.toml", "start_m = 0.5", "start_m = inf");
    assert_names(
        &error,
        "inf-start.toml",
        "walk[0].start_m",
        "inf",
        "must lie in [0, 1]",
    );
}

#[test]
fn duplicate_names_are_refused() {
    let error = refused("twin-supports.toml", r#"name = "east""#, r#"name = "west""#);
    assert_names(
        &error,
        "twin-supports.toml",
        "support[1].name",
        "\"west\"",
        "support[0] has that name already",
    );
    let error = refused("twin-walks.toml", r#"name = "climb""#, r#"name = "fork""#);
    assert_names(
        &error,
        "twin-walks.toml",
        "walk[1].name",
        "\"fork\"",
        "walk[0] has that name already",
    );
}

#[test]
fn an_empty_walk_is_refused() {
    let error = refused(
        "empty-walk.toml",
        r#"supports = ["trunk"]"#,
        "supports = []",
    );
    assert_names(
        &error,
        "empty-walk.toml",
        "walk[1].supports",
        "[]",
        "walk climb needs at least one support",
    );
}

#[test]
fn supports_that_do_not_meet_are_refused() {
    // `east` moved 0.41 m sideways: its start is the point nearest `west`.
    let error = refused(
        "apart.toml",
        "from_m = [0.0, 0.0, 0.0]\nto_m = [1.0, 1.0, 0.0]",
        "from_m = [0.0, 0.41, 0.0]\nto_m = [1.0, 1.41, 0.0]",
    );
    assert_names(
        &error,
        "apart.toml",
        "walk[0].supports[1]",
        "\"east\"",
        "walk fork: supports west and east do not meet (nearest 0.41 m",
    );
    // Within the sum of the radii + 5 cm they meet.
    let path = write_forest(
        "near.toml",
        &SMALL.replacen(
            "from_m = [0.0, 0.0, 0.0]\nto_m = [1.0, 1.0, 0.0]",
            "from_m = [0.0, 0.085, 0.0]\nto_m = [1.0, 1.085, 0.0]",
            1,
        ),
    );
    let fork = Forest::load(&path, trunk_tilt_rad())
        .unwrap_or_else(|e| panic!("{e}"))
        .scenario("fork")
        .unwrap();
    assert!(close(
        fork.route.legs[1].origin,
        glam::DVec3::new(0.0, 0.085, 0.0)
    ));
}

#[test]
fn consecutive_repeats_and_unknown_keys_are_refused() {
    let error = refused(
        "repeat.toml",
        r#"supports = ["west", "east"]"#,
        r#"supports = ["west", "west"]"#,
    );
    assert_names(
        &error,
        "repeat.toml",
        "walk[0].supports[1]",
        "\"west\"",
        "consecutive supports must differ",
    );
    let error = refused(
        "unknown-key.toml",
        "radius_m = 0.08",
        "radius_m = 0.08\nbark = \"rough\"",
    );
    let message = error.to_string();
    assert!(matches!(error, ConfigError::Parse { .. }), "{message}");
    assert!(
        message.contains("unknown-key.toml") && message.contains("bark"),
        "{message}"
    );
}

#[test]
fn toward_trunk_is_for_a_walk_on_a_trunk_and_horizontal() {
    let error = refused(
        "toward-on-branch.toml",
        "start_m = 0.5",
        "start_m = 0.5\ntoward_trunk = [0.0, 1.0, 0.0]",
    );
    assert_names(
        &error,
        "toward-on-branch.toml",
        "walk[0].toward_trunk",
        "[0.0, 1.0, 0.0]",
        "walk fork starts on a branch",
    );
    let climb = "supports = [\"trunk\"]\nstart_m = 0.5";
    let error = refused(
        "toward-up.toml",
        climb,
        &format!("{climb}\ntoward_trunk = [1.0, 0.0, 0.5]"),
    );
    assert_names(
        &error,
        "toward-up.toml",
        "walk[1].toward_trunk",
        "[1.0, 0.0, 0.5]",
        "must be a horizontal direction",
    );
    // From the trunk's +y side the sloth faces -y.
    let path = write_forest(
        "toward-y.toml",
        &SMALL.replacen(
            climb,
            &format!("{climb}\ntoward_trunk = [0.0, -2.0, 0.0]"),
            1,
        ),
    );
    let climb = Forest::load(&path, trunk_tilt_rad())
        .unwrap_or_else(|e| panic!("{e}"))
        .scenario("climb")
        .unwrap();
    assert!(close(climb.route.legs[0].up, -glam::DVec3::Y));
}

#[test]
fn a_trunk_after_a_branch_faces_along_the_branch() {
    // A branch along +x that ends at the trunk at x = 1.
    let text = SMALL.replacen(
        "[[walk]]",
        "[[support]]\nname = \"to-trunk\"\nfrom_m = [0.0, 0.0, 0.3]\nto_m = [0.92, 0.0, 0.3]\n\
         radius_m = 0.02\n\n[[walk]]\nname = \"onto\"\nsupports = [\"to-trunk\", \"trunk\"]\n\
         start_m = 0.3\n\n[[walk]]",
        1,
    );
    let path = write_forest("onto-trunk.toml", &text);
    let onto = Forest::load(&path, trunk_tilt_rad())
        .unwrap_or_else(|e| panic!("{e}"))
        .scenario("onto")
        .unwrap();
    let (branch, trunk) = (onto.route.legs[0], onto.route.legs[1]);
    assert!(close(branch.up, glam::DVec3::Z));
    assert!(close(trunk.up, glam::DVec3::X));
    assert!(close(trunk.origin, glam::DVec3::new(1.0, 0.0, 0.3)));
    assert!((trunk.start_s - 0.92).abs() <= 1e-12);
    assert!(close(trunk.direction, glam::DVec3::Z));
}

/// `config/gait-run.toml` with its job replaced by `job` and the rig's path made absolute,
/// next to a copy of the shipped forest.
fn run_settings_with(name: &str, job: &str) -> PathBuf {
    let dir = temp_dir().join(name);
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::copy(repo_path("config/forest.toml"), dir.join("forest.toml")).unwrap();
    let original = std::fs::read_to_string(repo_path("config/gait-run.toml")).unwrap();
    let rig = repo_path("config/sloth.toml");
    let text = original
        .replacen(
            "rig = \"sloth.toml\"",
            &format!("rig = {:?}", rig.display().to_string()),
            1,
        )
        .replacen("scenario = \"straight\"", job, 1);
    let path = dir.join("gait-run.toml");
    std::fs::write(&path, text).unwrap();
    path
}

#[test]
fn a_gait_job_walks_a_forest_walk() {
    let path = run_settings_with("job", "scenario = \"fork\"\nforest = \"forest.toml\"");
    let settings = load_run_settings(&path).unwrap_or_else(|e| panic!("{e}"));
    match &settings.config.job {
        JobConfig::Gait(rigbridge::job::Gait {
            scenario, forest, ..
        }) => {
            assert_eq!(scenario, "fork");
            let forest = forest.as_deref().expect("the forest is kept");
            assert_eq!(forest, path.parent().unwrap().join("forest.toml"));
        }
        other => panic!("expected a gait job, got {other:?}"),
    }
}

#[test]
fn a_gait_job_with_a_missing_walk_or_an_angle_is_refused() {
    let path = run_settings_with(
        "missing-walk",
        "scenario = \"canopy\"\nforest = \"forest.toml\"",
    );
    let error = load_run_settings(&path).unwrap_err();
    assert_names(
        &error,
        "gait-run.toml",
        "job.scenario",
        "\"canopy\"",
        "no walk named `canopy`",
    );
    let path = run_settings_with(
        "angle",
        "scenario = \"fork\"\nforest = \"forest.toml\"\nangle_deg = 120.0",
    );
    let error = load_run_settings(&path).unwrap_err();
    assert_names(
        &error,
        "gait-run.toml",
        "job.angle_deg",
        "120.0",
        "takes its geometry from that file",
    );
    let path = run_settings_with("no-forest", "scenario = \"fork\"\nforest = \"none.toml\"");
    let message = load_run_settings(&path).unwrap_err().to_string();
    assert!(message.contains("none.toml"), "{message}");
}

fn log_path(name: &str) -> PathBuf {
    let log = temp_dir().join(name);
    let _ = std::fs::remove_file(&log);
    log
}

/// Runs a walk of the shipped forest end to end on the twin (virtual clock), logged.
fn run_shipped_walk(name: &str) -> rigbridge::apps::gait::run::GaitRun {
    let settings =
        load_run_settings(&repo_path("config/gait-run.toml")).unwrap_or_else(|e| panic!("{e}"));
    let walk = shipped().scenario(name).unwrap();
    let log = log_path(&format!("{name}.mcap"));
    let run = run_gait(
        &settings,
        &walk,
        &VirtualClock::new(),
        Some(Path::new(&log)),
        &StreamControl::default(),
    )
    .unwrap_or_else(|e| panic!("{name} plans and streams: {e}"));
    assert!(log.exists(), "the run is logged");
    run
}

#[test]
fn the_fork_walk_passes_end_to_end() {
    let run = run_shipped_walk("fork");
    common::assert_gait_figures(&run);
    assert_eq!(run.verdict.scenario, "fork");
    // The sloth went round the bend: its body's path ends on the second branch, left of +x.
    let end = *run.body_path.last().expect("a body path");
    assert!(end.y > 0.1, "{end:?}");
}

#[test]
fn the_climb_out_walk_transfers_from_the_trunk_to_the_branch() {
    let run = run_shipped_walk("climb-out");
    let v = &run.verdict;
    assert!(v.passed, "{:?}", v.reason);
    assert!(v.cycles_judged >= 3);
    assert_eq!(run.run.stream.limit_violations, 0);
    // Every limb's last stance is on the branch (support 1 of the walk's terrain).
    for limb in 0..4 {
        let supports = common::supports_walked(&run, limb);
        assert_eq!(supports.last(), Some(&1), "limb {limb} ends on the branch");
    }
    assert!(v.min_head_above_tail_m > 0.0);
}
