//! The sloth gait end to end: planned, validated, streamed through the loopback twin and
//! judged from the twin's actual positions (virtual clock). Scenarios across their ranges,
//! rule stops outside them, and config errors naming file, key and value.

use crate::common;

use common::cli::{assert_succeeded, read_json, rigbridge};
use common::repo_path;
use rigbridge::apps::gait::run::{GaitRun, run_gait};
use rigbridge::apps::gait::{LimbSolver, Scenario, Side, SlothRig, Stance, shared_sloth, sloth_of};
use rigbridge::clock::VirtualClock;
use rigbridge::daemon::config::{RunSettings, load_run_settings};
use rigbridge::rig::ConfigError;
use rigbridge::stream::{Outcome, StreamControl};

fn settings() -> RunSettings {
    load_run_settings(&repo_path("config/gait-run.toml")).expect("config/gait-run.toml loads")
}

fn walk(name: &str, angle: Option<f64>, gap: Option<f64>) -> GaitRun {
    walk_with(settings(), name, angle, gap)
}

/// The gait's run settings with the limbs placed by `solver`.
fn settings_with(solver: LimbSolver) -> RunSettings {
    let mut settings = settings();
    let mut sloth = sloth_of(settings.app_rig.as_deref())
        .cloned()
        .expect("a sloth rig");
    sloth.gait.solver = solver;
    settings.app_rig = Some(std::sync::Arc::new(sloth));
    settings
}

fn walk_with(settings: RunSettings, name: &str, angle: Option<f64>, gap: Option<f64>) -> GaitRun {
    let scenario = Scenario::build(name, angle, gap).expect("scenario builds");
    let dir = std::env::temp_dir().join(format!("rigbridge-gait-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let solver = sloth_of(settings.app_rig.as_deref()).map(|s| s.gait.solver);
    let log = dir.join(format!(
        "{name}-{}-{}-{solver:?}.mcap",
        angle.unwrap_or(0.0),
        gap.unwrap_or(0.0)
    ));
    let _ = std::fs::remove_file(&log);
    let run = run_gait(
        &settings,
        &scenario,
        &VirtualClock::new(),
        Some(&log),
        &StreamControl::default(),
    )
    .expect("the gait plans and streams");
    assert!(log.exists(), "the run is logged");
    run
}

fn assert_passes(run: &GaitRun) {
    common::assert_gait_figures(run);
    let v = &run.verdict;
    for limb in &v.limbs {
        assert!((limb.duty_factor - 2.0 / 3.0).abs() < 0.05, "{limb:?}");
    }
    assert!(v.max_ik_residual_mm <= 1.0);
    let order = ["rh", "lf", "lh", "rf"];
    for (i, name) in v.footfall_order.iter().enumerate() {
        assert_eq!(name, order[i % 4]);
    }
}

/// A gait that stops on a rule: the reason is given, the stream still completes (the
/// swings under way land first), nothing enters a branch and no bone leaves its limits.
fn assert_stops_cleanly(run: &GaitRun, reason_contains: &str) {
    let v = &run.verdict;
    assert!(!v.passed);
    let reason = v.stopped_because.as_deref().unwrap_or_default();
    assert!(reason.contains(reason_contains), "{reason}");
    assert_eq!(run.run.stream.outcome, Outcome::Completed);
    assert!(v.min_body_clearance_mm > 0.0);
    for limb in &v.limbs {
        assert!(
            limb.max_bone_excursion_deg <= limb.bone_limit_deg + 1e-9,
            "{limb:?}"
        );
        assert!(limb.max_foot_to_surface_mm <= 5.0, "{limb:?}");
    }
    let last = run.plan.frame(run.plan.len() - 1);
    let before = run.plan.frame(run.plan.len() - 2);
    let moving = last.iter().zip(before).any(|(a, b)| (a - b).abs() > 1e-6);
    assert!(!moving, "the gait ends at rest");
}

/// The run went at the sloth's speed, 0.11 m/s, within 0.02 m/s.
#[track_caller]
fn assert_sloths_speed(run: &GaitRun) {
    assert!(
        (run.verdict.speed_mps - 0.11).abs() <= 0.02,
        "{}",
        run.verdict.speed_mps
    );
}

#[test]
fn straight_branch_at_the_sloths_speed() {
    let run = walk("straight", None, None);
    assert_passes(&run);
    assert_sloths_speed(&run);
}

#[test]
fn straight_branch_with_fabrik_limbs() {
    let run = walk_with(settings_with(LimbSolver::Fabrik), "straight", None, None);
    assert_eq!(run.verdict.solver, LimbSolver::Fabrik);
    assert_passes(&run);
    assert_sloths_speed(&run);
}

#[test]
fn fabrik_limbs_stop_cleanly_where_their_poses_jump() {
    // At 135 deg a FABRIK pose of the left hind limb jumps (its pelvis above the axis
    // speed in one period): the gait stops there, and never streams the jump.
    let run = walk_with(
        settings_with(LimbSolver::Fabrik),
        "height-change",
        Some(135.0),
        None,
    );
    assert_stops_cleanly(&run, "above 95 % of its max speed");
    assert_eq!(run.run.stream.limit_violations, 0);
}

#[test]
fn branch_turns_from_95_to_175_degrees() {
    // 110, 150 and 160 deg stopped before the body was held back from a trailing hind foot.
    for angle in [95.0, 110.0, 115.0, 135.0, 150.0, 155.0, 160.0, 175.0] {
        assert_passes(&walk("branch-turn", Some(angle), None));
    }
}

#[test]
fn height_changes_from_135_to_200_degrees() {
    for angle in [135.0, 150.0, 155.0, 165.0, 180.0, 200.0] {
        assert_passes(&walk("height-change", Some(angle), None));
    }
}

#[test]
fn a_change_to_a_parallel_branch_10_to_35_cm_away() {
    for gap in [0.10, 0.15, 0.20, 0.25, 0.30, 0.35] {
        assert_passes(&walk("parallel", None, Some(gap)));
    }
}

#[test]
fn straddling_parallel_branches_the_feet_grip_the_facing_sides_and_pass_under_them() {
    let gap = 0.35;
    let run = walk("parallel", None, Some(gap));
    let scenario = Scenario::build("parallel", None, Some(gap)).unwrap();
    // The route straddles the branches (left limbs on the first, at y = 0; right limbs on
    // the second, at y = -gap) for route distances 0..0.25 m: there each hand or foot
    // grips the side of its branch that faces the other branch.
    let straddling: Vec<_> = run
        .plan
        .stances
        .iter()
        .filter(|stance| (0.0..0.25).contains(&stance.contact.s))
        .collect();
    assert!(straddling.len() >= 4, "{straddling:?}");
    for stance in straddling {
        let limb = &run.sloth.limbs[stance.limb];
        let y = stance.contact.point.y;
        match limb.side {
            Side::Left => assert!(y < -0.01, "{} grips y = {y}", limb.name),
            Side::Right => assert!(y > -gap + 0.01, "{} grips y = {y}", limb.name),
        }
    }
    // Turning over to the other side of a branch, a hand or foot passes under it: no
    // hand's or foot's end enters a branch in any frame.
    for k in 0..run.plan.len() {
        let lines = run.sloth.bone_polylines(run.plan.frame(k)).unwrap();
        for (limb, line) in run.sloth.limbs.iter().zip(&lines[1..]) {
            let end = *line.last().unwrap();
            let clearance = scenario.terrain.clearance(end);
            assert!(
                clearance > 0.0,
                "frame {k}: {}'s end {end:?} is {:.1} mm inside a branch",
                limb.name,
                -clearance * 1000.0
            );
        }
    }
}

#[test]
fn a_parallel_branch_too_far_for_the_limbs_stops_the_gait_cleanly() {
    assert_stops_cleanly(&walk("parallel", None, Some(0.40)), "no next step");
}

#[test]
fn too_steep_a_rise_stops_before_the_branch() {
    assert_stops_cleanly(&walk("height-change", Some(130.0), None), "rises 50.0 deg");
}

#[test]
fn head_first_descent_is_refused() {
    assert_stops_cleanly(
        &walk("height-change", Some(210.0), None),
        "head-first descent",
    );
}

/// The spine (hind girdle to fore girdle) at every planned frame, from the rig's own
/// forward kinematics.
fn spines(run: &GaitRun) -> Vec<(glam::DVec3, glam::DVec3)> {
    (0..run.plan.len())
        .map(|k| {
            let lines = run.sloth.bone_polylines(run.plan.frame(k)).unwrap();
            (lines[0][0], *lines[0].last().unwrap())
        })
        .collect()
}

/// A trunk run: passes, stays head-up throughout, and every stance grips the trunk's
/// surface on its own limb's side of the body. Returns the body's planned vertical travel.
fn assert_climbs_head_up(run: &GaitRun) -> f64 {
    assert_passes(run);
    let v = &run.verdict;
    let scene = Scenario::build(&v.scenario, v.angle_deg, v.gap_m).unwrap();
    let trunk = scene.terrain.cylinders[0];
    assert_eq!(
        (trunk.from.x, trunk.from.y),
        (trunk.to.x, trunk.to.y),
        "vertical"
    );
    let spines = spines(run);
    for (k, (tail, head)) in spines.iter().enumerate() {
        assert!(head.z - tail.z > 0.3, "frame {k}: head {head} tail {tail}");
    }
    for stance in &run.plan.stances {
        let (tail, head) = spines[stance.start];
        let limbs = run
            .sloth
            .bone_polylines(run.plan.frame(stance.start))
            .unwrap();
        // The body's left: from the right limbs' girdles to the left ones'.
        let girdle = |name: &str| limbs[1 + run.sloth.limb_index(name).unwrap()][0];
        let left = (girdle("lf") + girdle("lh") - girdle("rf") - girdle("rh")).normalize();
        let middle = (tail + head) / 2.0;
        let point = stance.contact.point;
        let radial = glam::DVec3::new(point.x - trunk.from.x, point.y - trunk.from.y, 0.0);
        assert!(
            (radial.length() - trunk.radius).abs() < 1e-6,
            "on the trunk's surface: {point}"
        );
        let limb = &run.sloth.limbs[stance.limb];
        assert!(
            (point - middle).dot(left) * limb.side.sign() > 0.03,
            "{} grips its own side: {point}",
            limb.name
        );
    }
    let body_z = |k: usize| run.plan.frame(k)[2];
    body_z(run.plan.len() - 1) - body_z(0)
}

#[test]
fn climbs_a_trunk_head_up() {
    let run = walk("trunk", None, None);
    let rise = assert_climbs_head_up(&run);
    assert!(rise > 0.9, "rose {rise} m");
    assert!((run.verdict.body_rise_m - rise).abs() < 0.01);
    assert!((run.verdict.speed_mps - 0.11).abs() <= 0.02);
    assert_eq!(run.verdict.around_trunk_deg.map(f64::round), Some(0.0));
}

#[test]
fn climbs_down_a_trunk_tail_first() {
    let run = walk("trunk-down", None, None);
    let rise = assert_climbs_head_up(&run);
    assert!(rise < -0.9, "descended {} m", -rise);
    assert!(run.verdict.min_head_above_tail_m > 0.3);
    // Tail first: the hind limbs lead downward, below the fore limbs at every touchdown.
    let lowest_fore = |k: usize| {
        ["lf", "rf"]
            .iter()
            .map(|n| {
                run.sloth.bone_polylines(run.plan.frame(k)).unwrap()
                    [1 + run.sloth.limb_index(n).unwrap()]
                .last()
                .unwrap()
                .z
            })
            .fold(f64::INFINITY, f64::min)
    };
    for (frame, limb) in &run.plan.touchdowns {
        let lines = run.sloth.bone_polylines(run.plan.frame(*frame)).unwrap();
        let foot = lines[1 + limb].last().unwrap().z;
        if run.sloth.limbs[*limb].name.ends_with('h') {
            assert!(foot < lowest_fore(*frame) - 0.1, "frame {frame}");
        }
    }
}

#[test]
fn goes_around_a_trunk_while_descending_tail_first() {
    for (angle, least_around) in [(20.0, 19.0), (-15.0, -14.0)] {
        let run = walk("trunk-down", Some(angle), None);
        let rise = assert_climbs_head_up(&run);
        assert!(rise < -0.9, "descended {} m", -rise);
        let around = run.verdict.around_trunk_deg.expect("on a trunk");
        // Counterclockwise seen from above for a positive angle, as `trunk-spiral`.
        assert!(
            around * angle.signum() > least_around * angle.signum(),
            "{angle} deg/m: went {around} deg around"
        );
    }
}

#[test]
fn side_steps_around_a_trunk() {
    let run = walk("trunk-around", None, None);
    let rise = assert_climbs_head_up(&run);
    assert!(rise.abs() < 0.01, "stays at its height: {rise} m");
    let around = run.verdict.around_trunk_deg.expect("on a trunk");
    assert!(around > 120.0, "went {around} deg around");
    let back = walk("trunk-around", Some(-150.0), None);
    assert_climbs_head_up(&back);
    let around = back.verdict.around_trunk_deg.expect("on a trunk");
    assert!(around < -150.0, "went {around} deg around the other way");
}

#[test]
fn side_steps_too_long_for_the_limbs_stop_cleanly() {
    assert_stops_cleanly(&walk("trunk-around", Some(180.0), None), "no next step");
}

#[test]
fn spirals_up_a_trunk() {
    let run = walk("trunk-spiral", None, None);
    let rise = assert_climbs_head_up(&run);
    assert!(rise > 0.9, "rose {rise} m");
    let around = run.verdict.around_trunk_deg.expect("on a trunk");
    assert!(around > 35.0, "went {around} deg around");
}

/// Every limb starts on support `from`, ends on `to`, and changes support once (never back).
fn assert_every_limb_moves_once(run: &GaitRun, from: usize, to: usize) {
    for limb in 0..4 {
        let mut supports = common::supports_walked(run, limb);
        supports.dedup();
        assert_eq!(supports, [from, to], "limb {limb}");
    }
}

/// The planned stances on support `support` of the limbs `whose` holds for (by index).
fn stances_on(
    run: &GaitRun,
    support: usize,
    whose: impl Fn(usize) -> bool,
) -> impl Iterator<Item = &Stance> {
    run.plan
        .stances
        .iter()
        .filter(move |s| whose(s.limb) && s.contact.support == support)
}

/// A trunk-to-branch transfer: passes; every limb ends on the branch; every limb leaves the
/// trunk for the branch (never back), fore limbs first, and a hind limb lifts off the trunk
/// only once no fore limb is still on it (seed 004); the head stays above the tail.
fn assert_transfers_head_first(run: &GaitRun) {
    assert_passes(run);
    let (trunk, branch) = (0, 1);
    let fore = |limb: usize| run.sloth.limbs[limb].name.ends_with('f');
    let stances = &run.plan.stances;
    assert_every_limb_moves_once(run, trunk, branch);
    // The frame each limb lifts off the trunk for the branch: the end of its last trunk stance.
    let leaves_trunk = |limb: usize| {
        stances_on(run, trunk, |l| l == limb)
            .map(|s| s.end)
            .max()
            .unwrap()
    };
    let last_fore_leaves = (0..4).filter(|l| fore(*l)).map(leaves_trunk).max().unwrap();
    let first_fore_lands = stances_on(run, branch, fore)
        .map(|s| s.start)
        .min()
        .unwrap();
    for hind in (0..4).filter(|l| !fore(*l)) {
        let lifts = leaves_trunk(hind);
        assert!(
            lifts > first_fore_lands,
            "fore limbs reach the branch first"
        );
        // No fore limb holds the trunk when a hind limb lets go of it.
        for stance in stances.iter().filter(|s| fore(s.limb)) {
            let holds = stance.start <= lifts && lifts <= stance.end;
            assert!(
                !(holds && stance.contact.support == trunk),
                "{} lifts off the trunk at frame {lifts} while {} holds it",
                run.sloth.limbs[hind].name,
                run.sloth.limbs[stance.limb].name
            );
        }
        assert!(lifts >= last_fore_leaves);
    }
    // Never head down: level at the end under a 90 deg (level) branch.
    let heading = run.verdict.min_heading_elevation_deg;
    assert!(heading > -0.5, "the head pointed {heading} deg down");
}

#[test]
fn transfers_from_a_trunk_to_a_branch_head_first() {
    for angle in [90.0, 95.0, 120.0, 140.0] {
        assert_transfers_head_first(&walk("transfer", Some(angle), None));
    }
}

/// A branch-to-trunk transfer (seed 004's Transfer to Trunk): passes; tail first and head up
/// throughout; every limb ends on the trunk, having left the branch for it and never gone
/// back; the hind limbs, which lead, reach the trunk first; the body ends well down the trunk.
fn assert_transfers_to_the_trunk_tail_first(run: &GaitRun) {
    assert_passes(run);
    let (trunk, branch) = (0, 1);
    let hind = |limb: usize| run.sloth.limbs[limb].name.ends_with('h');
    assert_every_limb_moves_once(run, branch, trunk);
    let first_on_trunk = |limb: usize| {
        stances_on(run, trunk, |l| l == limb)
            .map(|s| s.start)
            .min()
            .unwrap()
    };
    let first_hind = (0..4)
        .filter(|l| hind(*l))
        .map(first_on_trunk)
        .min()
        .unwrap();
    let first_fore = (0..4)
        .filter(|l| !hind(*l))
        .map(first_on_trunk)
        .min()
        .unwrap();
    assert!(
        first_hind < first_fore,
        "the hind limbs lead onto the trunk"
    );
    // Head up throughout: the body's forward axis never points down (under the 5 deg branch
    // of 95 deg the shoulders, 6 cm below the hips in the body frame, hang lower than them;
    // under the level branch of 90 deg it is level, to rounding).
    let heading = run.verdict.min_heading_elevation_deg;
    assert!(heading > -1e-9, "the head pointed {} deg down", -heading);
    let rise = run.verdict.body_rise_m;
    // Down the trunk: 0.15 m at 90 deg and 0.26 m at 95, where more of the walk is on the
    // branch; 1.04 m at 150.
    assert!(rise < -0.1, "the body went down {} m", -rise);
}

#[test]
fn transfers_from_a_branch_to_a_trunk_tail_first() {
    for angle in [90.0, 95.0, 120.0, 150.0] {
        assert_transfers_to_the_trunk_tail_first(&walk("transfer-to-trunk", Some(angle), None));
    }
}

#[test]
fn a_transfer_to_the_trunk_from_a_branch_leaning_down_stops_cleanly() {
    // 85 deg: the branch falls 5 deg away from the trunk; lh, leading down the trunk, finds no
    // next step while the fore limbs still hold the branch.
    assert_stops_cleanly(&walk("transfer-to-trunk", Some(85.0), None), "no next step");
}

#[test]
fn a_transfer_to_the_trunk_never_starts_head_down() {
    // A branch falling away 30 deg from the trunk: going tail first toward the trunk, the
    // sloth would hang on it head down. Refused before any motion, with the reason.
    let scenario = Scenario::build("transfer-to-trunk", Some(60.0), None).unwrap();
    let error = run_gait(
        &settings(),
        &scenario,
        &VirtualClock::new(),
        None,
        &StreamControl::default(),
    )
    .err()
    .expect("refused");
    let mut message = error.to_string();
    let mut source = std::error::Error::source(&error);
    while let Some(cause) = source {
        message.push_str(&format!(": {cause}"));
        source = cause.source();
    }
    assert!(
        message.contains("cannot stand at its start")
            && message.contains("descends 30.0 deg: head-first descent"),
        "{message}"
    );
}

#[test]
fn a_transfer_onto_a_branch_leaning_back_down_stops_cleanly() {
    // 85 deg: the branch falls 5 deg from the bark; the trailing hind limb cannot follow.
    assert_stops_cleanly(&walk("transfer", Some(85.0), None), "no next step");
}

#[test]
fn a_transfer_onto_a_descending_branch_stops_cleanly() {
    // A branch falling away 30 deg lies across the climb: the body would meet it first.
    assert_stops_cleanly(&walk("transfer", Some(60.0), None), "no next step");
}

#[test]
fn the_streamed_rig_fits_the_wire_protocol() {
    let sloth = SlothRig::load(&repo_path("config/sloth.toml")).unwrap();
    assert_eq!(sloth.dof(), 6 + 4 * 5);
    assert!(sloth.dof() <= rigbridge::protocol::MAX_AXES);
    let names: Vec<&str> = sloth.limbs.iter().map(|l| l.name.as_str()).collect();
    assert_eq!(names, ["rh", "lf", "lh", "rf"]);
    let polylines = sloth.bone_polylines(&vec![0.0; sloth.dof()]).unwrap();
    assert_eq!(polylines.len(), 5, "the spine and four limbs");
    assert!(
        polylines[1..].iter().all(|limb| limb.len() == 5),
        "girdle and four bone ends"
    );
    assert!(sloth.bone_polylines(&[0.0; 3]).is_err());
}

/// `config/sloth.toml` with the first `from` made `to`, loaded from a copy named `name`.
fn sloth_variant(name: &str, from: &str, to: &str) -> Result<SlothRig, ConfigError> {
    let original = std::fs::read_to_string(repo_path("config/sloth.toml")).unwrap();
    let dir = std::env::temp_dir().join(format!("rigbridge-sloth-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join(name);
    std::fs::write(&path, original.replacen(from, to, 1)).unwrap();
    SlothRig::load(&path)
}

/// Why [`sloth_variant`] refuses the edited file, as a user reads it.
fn variant_refusal(name: &str, from: &str, to: &str) -> String {
    sloth_variant(name, from, to).unwrap_err().to_string()
}

/// Fails the test, showing `message`, unless it holds every one of `parts`.
#[track_caller]
fn assert_mentions(message: &str, parts: &[&str]) {
    for part in parts {
        assert!(message.contains(part), "{message}");
    }
}

#[test]
fn a_bad_bone_limit_names_file_key_and_value() {
    let error =
        sloth_variant("inverted.toml", "lower_deg = -20.8", "lower_deg = 200.0").unwrap_err();
    match error {
        ConfigError::Invalid {
            file, key, value, ..
        } => {
            assert!(file.ends_with("inverted.toml"));
            assert!(
                key.starts_with("limb[1].joint[") && key.ends_with("upper_deg"),
                "{key}"
            );
            assert!(!value.is_empty());
        }
        other => panic!("{other}"),
    }
}

#[test]
fn a_bad_gait_setting_names_file_key_and_value() {
    let message = variant_refusal("speed.toml", "speed_m_s = 0.11", "speed_m_s = -1.0");
    assert_mentions(&message, &["speed.toml", "gait.speed_m_s", "-1.0"]);
}

#[test]
fn an_unknown_limb_solver_names_file_key_and_value() {
    let message = variant_refusal("solver.toml", "solver = \"ccd\"", "solver = \"jacobian\"");
    assert_mentions(&message, &["solver.toml", "gait.solver", "jacobian"]);
}

#[test]
fn fabrik_limbs_load_from_the_file() {
    let sloth = sloth_variant("fabrik.toml", "solver = \"ccd\"", "solver = \"fabrik\"")
        .expect("solver = \"fabrik\" loads");
    assert_eq!(sloth.gait.solver, LimbSolver::Fabrik);
}

#[test]
fn an_unknown_footfall_limb_is_refused() {
    let message = variant_refusal("order.toml", "\"lf\", \"lh\"", "\"lf\", \"xx\"");
    assert_mentions(&message, &["gait.footfall_order[2]", "xx"]);
}

/// A `run` or `serve` job starts from the twin's configured position (the straight scene's
/// start) and moves to the scenario's start before walking: on a trunk, that approach keeps
/// the torso clear of the trunk too.
#[test]
fn a_trunk_job_approaches_from_the_configured_start_clear_of_the_trunk() {
    let settings = settings();
    let sloth = shared_sloth(settings.app_rig.as_ref()).unwrap();
    for name in [
        "trunk",
        "trunk-down",
        "trunk-around",
        "trunk-spiral",
        "transfer-to-trunk",
    ] {
        let scenario = Scenario::build(name, None, None).unwrap();
        let trajectory = rigbridge::apps::gait::plan_gait_job(
            &sloth,
            &scenario,
            &settings.initial(),
            &rigbridge::daemon::plan_settings(&settings),
        )
        .expect("the job plans");
        let trunk = scenario.terrain.cylinders[0];
        let least = (0..trajectory.len())
            .map(|k| {
                let spine = &sloth.bone_polylines(&trajectory.position(k)).unwrap()[0];
                let (tail, head) = (spine[0], *spine.last().unwrap());
                let axis = |p: glam::DVec3| glam::DVec3::new(trunk.from.x, trunk.from.y, p.z);
                // The torso's nearest approach to the vertical axis, sampled along the spine.
                (0..=20)
                    .map(|i| {
                        let p = tail.lerp(head, i as f64 / 20.0);
                        p.distance(axis(p))
                    })
                    .fold(f64::INFINITY, f64::min)
                    - sloth.body_radius_m
                    - trunk.radius
            })
            .fold(f64::INFINITY, f64::min);
        assert!(
            least > 0.02,
            "{name}: the torso comes {least} m from the bark"
        );
    }
}

#[test]
fn trunk_geometry_options_are_checked() {
    let error = Scenario::build("trunk", Some(30.0), None).unwrap_err();
    assert!(error.to_string().contains("takes no --angle"), "{error}");
    let error = Scenario::build("trunk-down", None, Some(0.2)).unwrap_err();
    assert!(error.to_string().contains("takes no --gap"), "{error}");
    let error = Scenario::build("trunk-around", Some(200.0), None).unwrap_err();
    assert!(error.to_string().contains("--angle = 200"), "{error}");
    let up = Scenario::build("trunk", None, None).unwrap();
    assert_eq!(
        up.terrain,
        Scenario::build("trunk-up", None, None).unwrap().terrain
    );
    assert!(!up.tail_first && !up.sideways);
    assert!(
        Scenario::build("trunk-down", None, None)
            .unwrap()
            .tail_first
    );
}

#[test]
fn an_unknown_scenario_is_refused_by_name() {
    let error = Scenario::build("loop-the-loop", None, None).unwrap_err();
    assert!(error.to_string().contains("loop-the-loop"));
    assert!(
        error.to_string().contains("transfer"),
        "lists every name: {error}"
    );
}

fn scratch(name: &str) -> std::path::PathBuf {
    common::scratch_file("gait-cli", name)
}

#[test]
fn the_gait_command_reports_and_draws() {
    let (report, picture, log) = (scratch("r.json"), scratch("p.svg"), scratch("g.mcap"));
    let output = rigbridge()
        .args([
            "gait",
            "--scenario",
            "branch-turn",
            "--angle",
            "135",
            "--clock",
            "virtual",
        ])
        .arg("--report")
        .arg(&report)
        .arg("--picture")
        .arg(&picture)
        .arg("--log")
        .arg(&log)
        .output()
        .unwrap();
    assert_succeeded(&output);
    let json = read_json(&report);
    assert_eq!(json["passed"], true);
    assert_eq!(json["limbs"].as_array().unwrap().len(), 4);
    assert_eq!(json["run"]["outcome"], "completed");
    let svg = std::fs::read_to_string(&picture).unwrap();
    assert!(svg.starts_with("<svg") && svg.contains("gait diagram"));
    assert!(log.exists());
    assert_eq!(json["solver"], "ccd");
}

/// `rigbridge gait` on the straight branch with `--{option} {value}`: its output and the
/// report it was asked to write.
fn gait_straight_with(option: &str, value: &str) -> (std::process::Output, std::path::PathBuf) {
    let report = scratch(&format!("{option}-{value}.json"));
    let output = rigbridge()
        .args(["gait", "--scenario", "straight", "--clock", "virtual"])
        .args([format!("--{option}").as_str(), value])
        .arg("--report")
        .arg(&report)
        .arg("--log")
        .arg(scratch(&format!("{option}-{value}.mcap")))
        .output()
        .unwrap();
    (output, report)
}

/// `rigbridge gait` refused `--{option} {value}`, naming both.
#[track_caller]
fn assert_refuses(option: &str, value: &str) {
    let (refused, _) = gait_straight_with(option, value);
    assert!(!refused.status.success());
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(
        stderr.contains(&format!("--{option}")) && stderr.contains(value),
        "{stderr}"
    );
}

#[test]
fn the_gait_command_takes_the_limb_solver() {
    let (output, report) = gait_straight_with("solver", "fabrik");
    assert_succeeded(&output);
    let json = read_json(&report);
    assert_eq!(json["solver"], "fabrik");
    assert_eq!(json["passed"], true);

    assert_refuses("solver", "newton");
}

#[test]
fn the_gait_command_takes_the_footfall_sequence() {
    let (output, report) = gait_straight_with("sequence", "lateral");
    assert_succeeded(&output);
    let json = read_json(&report);
    assert_eq!(json["passed"], true);
    let order: Vec<&str> = json["footfall_order"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_str().unwrap())
        .collect();
    assert_eq!(&order[..4], ["rh", "rf", "lh", "lf"]);

    assert_refuses("sequence", "pace");
}

#[test]
fn run_takes_a_gait_job() {
    let log = scratch("run.mcap");
    let output = rigbridge()
        .args([
            "run",
            "--config",
            "config/gait-run.toml",
            "--clock",
            "virtual",
        ])
        .arg("--log")
        .arg(&log)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(
        output.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&output.stderr)
    );
    assert!(stdout.contains("gait straight on sloth"), "{stdout}");
}

/// The judge fails a run whose body the twin saw pointing head down beyond the seed's 20 deg,
/// from the twin's positions alone: the straight branch's plan observed as planned passes,
/// the same frames with the body pitched 0.6 rad nose down fail with the reason.
#[test]
fn the_judge_fails_a_head_first_descent_seen_on_the_twin() {
    use rigbridge::apps::gait::{GaitWorld, Walker, judge};
    use rigbridge::twin::TwinWorld;
    let settings = settings();
    let sloth = shared_sloth(settings.app_rig.as_ref()).unwrap();
    let scenario = Scenario::build("straight", None, None).unwrap();
    let plan = Walker::new(&sloth, &scenario, settings.period())
        .plan()
        .unwrap();
    let pitch = sloth
        .streamed
        .joints
        .iter()
        .position(|j| j.name == "body_pitch")
        .unwrap();
    let verdict = |nose_down: f64| {
        let mut world = GaitWorld::new(&sloth, &scenario, &plan, 0);
        for k in 0..plan.len() {
            let mut frame = plan.frame(k).to_vec();
            frame[pitch] += nose_down;
            world.observe(&frame);
        }
        judge(&sloth, &scenario, &plan, &world, true)
    };
    let level = verdict(0.0);
    assert!(level.passed, "{:?}", level.reason);
    assert!(level.min_heading_elevation_deg.abs() < 0.5);
    let down = verdict(0.6);
    assert!(!down.passed);
    let reason = down.reason.unwrap_or_default();
    assert!(
        reason.contains("head-first descent: the body pointed 34.4 deg down"),
        "{reason}"
    );
}

/// The seed's lateral sequence (rh, rf, lh, lf), which it uses for transfers: a trunk-to-
/// branch transfer walks and is judged in it.
#[test]
fn a_transfer_walks_in_the_lateral_sequence() {
    use rigbridge::apps::gait::FootfallSequence;
    let mut settings = settings();
    let mut sloth = sloth_of(settings.app_rig.as_deref()).cloned().unwrap();
    sloth.gait.footfall_order = FootfallSequence::Lateral
        .limb_names()
        .iter()
        .map(|name| sloth.limb_index(name).unwrap())
        .collect();
    settings.app_rig = Some(std::sync::Arc::new(sloth));
    let run = walk_with(settings, "transfer", Some(120.0), None);
    common::assert_gait_figures(&run);
    let lateral = ["rh", "rf", "lh", "lf"];
    let order = &run.verdict.footfall_order;
    assert!(order.len() >= 16, "{order:?}");
    for (i, name) in order.iter().enumerate() {
        assert_eq!(name, lateral[i % 4], "touchdown {i} of {order:?}");
    }
    for limb in 0..4 {
        let supports = common::supports_walked(&run, limb);
        assert_eq!(supports.last(), Some(&1), "{limb} ends on the branch");
    }
}
