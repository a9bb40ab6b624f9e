//! Free moves around the cell (issue 29, `trajectory::free`): 100 seeded random pairs of
//! clear configurations in the demo cell (config/pick-place.toml) are planned, timed and
//! checked again densely, independently of the planner's own check; the same seed plans
//! the same path; a goal inside an obstacle and a goal walled off from the start are
//! refused before motion with the reason; and a `move_joints` job with `plan_around = true`
//! whose direct move the pillar blocks runs to the end with no contact at the twin.

use crate::common;
use crate::free_pairs;

use common::repo_path;
use free_pairs::{blocked_pairs, demo_settings, direct_is_clear, pairs};
use glam::{DAffine3, DVec3};
use rigbridge::cell::{Cell, CellObject, CollisionModel};
use rigbridge::rig::Shape;
use rigbridge::trajectory::free::{
    End, FreePlanError, FreePlanOptions, path_length, plan_free, time_free,
};
use rigbridge::trajectory::{
    Origins, PlanSettings, Trajectory, check_clear, plan_joint_moves, validate,
};
use std::process::Command;
use std::time::Instant;

/// Points checked between two consecutive samples of a timed path, besides the samples
/// themselves: 4 ms / 5 = 0.8 ms apart, at most 4 mrad of any axis' motion at full speed,
/// nearly a hundred times finer than the planner's tree step (0.35 rad).
const DENSE_POINTS_PER_SAMPLE: usize = 4;

/// The continuous check's promise between the configurations it measures: the margin
/// less 1 mm (src/cell/path.rs, `PROOF_SLACK_M`). The planner keeps 2 mm more, so every
/// dense point should in fact be clear by the margin itself; this is what may not fail.
const PROOF_SLACK_M: f64 = 0.001;

/// The figures.
const MIN_PLANNED_SHARE: f64 = 0.98;
const MAX_MEDIAN_LENGTH_RATIO: f64 = 1.5;

/// The smallest clearance along `trajectory`, at every sample and at
/// [`DENSE_POINTS_PER_SAMPLE`] points between each two, joint-space linear as the streamer
/// interpolates them; and how many of those points are in collision (clearance <= 0).
fn dense_clearance(model: &CollisionModel, trajectory: &Trajectory) -> (f64, usize) {
    let mut scratch = model.scratch();
    let mut smallest = f64::INFINITY;
    let mut collisions = 0;
    let mut measure = |q: &[f64]| {
        let d = model.clearance(q, &mut scratch).distance_m;
        smallest = smallest.min(d);
        collisions += usize::from(d <= 0.0);
    };
    measure(&trajectory.position(0));
    for k in 1..trajectory.len() {
        let (a, b) = (trajectory.position(k - 1), trajectory.position(k));
        for i in 1..=DENSE_POINTS_PER_SAMPLE + 1 {
            let s = i as f64 / (DENSE_POINTS_PER_SAMPLE + 1) as f64;
            let q: Vec<f64> = a
                .iter()
                .zip(b.iter())
                .map(|(x, y)| x + s * (y - x))
                .collect();
            measure(&q);
        }
    }
    (smallest, collisions)
}

/// The median; not a number for no values.
fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    let n = values.len();
    if n == 0 {
        f64::NAN
    } else if n % 2 == 1 {
        values[n / 2]
    } else {
        (values[n / 2 - 1] + values[n / 2]) / 2.0
    }
}

fn deg(q: &[f64]) -> String {
    let values: Vec<String> = q.iter().map(|r| format!("{:.1}", r.to_degrees())).collect();
    format!("[{}]", values.join(", "))
}

/// What planning a set of pairs measured.
struct Figures {
    planned: usize,
    /// Pairs whose direct move is blocked.
    blocked: usize,
    refused: Vec<String>,
    /// Path length over the straight move's, where that is clear and where it is not.
    free_ratios: Vec<f64>,
    around_ratios: Vec<f64>,
    /// The smallest clearance densely along every timed path.
    smallest: f64,
    /// Planning time (search and shortening, not timing), ms, sorted.
    plan_ms: Vec<f64>,
}

/// Plans, times and checks again densely each of `pairs` in the demo cell, with the
/// run settings' free-planner options. Panics on a path that is not clear, not within
/// the limits or not from start to goal.
fn plan_pairs(pairs: &[free_pairs::Pair]) -> Figures {
    let settings = demo_settings();
    let (rig, model) = (&settings.tcp_rig, settings.collision.as_ref());
    let plan = rigbridge::daemon::plan_settings(&settings);
    let mut figures = Figures {
        planned: 0,
        blocked: 0,
        refused: Vec::new(),
        free_ratios: Vec::new(),
        around_ratios: Vec::new(),
        smallest: f64::INFINITY,
        plan_ms: Vec::new(),
    };
    for (index, (start, goal)) in pairs.iter().enumerate() {
        let direct_clear = direct_is_clear(model, start, goal);
        figures.blocked += usize::from(!direct_clear);
        let began = Instant::now();
        let planned = plan_free(model, rig, start, goal, &plan.free);
        figures.plan_ms.push(began.elapsed().as_secs_f64() * 1e3);
        let waypoints = match planned {
            Ok(waypoints) => waypoints,
            Err(error) => {
                figures.refused.push(format!("pair {index}: {error}"));
                continue;
            }
        };
        let trajectory = time_free(rig, model, &waypoints, 0, &plan)
            .unwrap_or_else(|e| panic!("pair {index}: planned but not timed: {e}"));
        figures.planned += 1;
        assert_eq!(trajectory.position(0), start.as_slice(), "pair {index}");
        let last = trajectory.position(trajectory.len() - 1);
        assert_eq!(last, goal.as_slice(), "pair {index}");
        validate(&trajectory, rig).unwrap_or_else(|e| panic!("pair {index}: {e}"));
        let (least, collisions) = dense_clearance(model, &trajectory);
        assert_eq!(collisions, 0, "pair {index}: {least} m");
        assert!(
            least >= model.margin() - PROOF_SLACK_M,
            "pair {index} {} -> {}: {least} m at its closest",
            deg(start),
            deg(goal)
        );
        figures.smallest = figures.smallest.min(least);
        let ratio = path_length(&waypoints) / path_length(&[start.clone(), goal.clone()]);
        if direct_clear {
            figures.free_ratios.push(ratio);
        } else {
            figures.around_ratios.push(ratio);
        }
    }
    figures.plan_ms.sort_by(f64::total_cmp);
    figures
}

impl Figures {
    fn print(&self, what: &str, pairs: usize, margin: f64) {
        let at = |q: f64| self.plan_ms[((self.plan_ms.len() - 1) as f64 * q).round() as usize];
        println!(
            "free moves, {what}: {pairs} pairs ({} with the direct move blocked), {} planned; \
             smallest dense clearance {:.4} m (margin {margin}); median length over the \
             straight move {:.3} where it is clear ({} pairs), {:.3} where it is blocked ({} \
             pairs); planning p50 {:.1} ms, p95 {:.1} ms, max {:.1} ms (this test's machine, \
             not a benchmark)",
            self.blocked,
            self.planned,
            self.smallest,
            median(self.free_ratios.clone()),
            self.free_ratios.len(),
            median(self.around_ratios.clone()),
            self.around_ratios.len(),
            at(0.5),
            at(0.95),
            at(1.0),
        );
        for line in &self.refused {
            println!("refused: {line}");
        }
    }
}

#[test]
fn a_hundred_random_pairs_in_the_demo_cell_are_planned_clear_and_short() {
    let settings = demo_settings();
    let pairs = pairs(&settings.tcp_rig, &settings.collision);
    let figures = plan_pairs(&pairs);
    figures.print("random pairs", pairs.len(), settings.collision.margin());
    let share = figures.planned as f64 / pairs.len() as f64;
    assert!(
        share >= MIN_PLANNED_SHARE,
        "{} of {} planned",
        figures.planned,
        pairs.len()
    );
    assert!(!figures.free_ratios.is_empty());
    assert!(median(figures.free_ratios) <= MAX_MEDIAN_LENGTH_RATIO);
}

/// Blocked pairs planned here: a quarter of the figure's hundred, so the suite stays short;
/// `cargo bench --bench free_plan` measures all hundred.
const BLOCKED_PAIRS_TESTED: usize = 25;

#[test]
fn random_pairs_the_direct_move_cannot_join_are_planned_around() {
    let settings = demo_settings();
    let pairs = blocked_pairs(&settings.tcp_rig, &settings.collision, BLOCKED_PAIRS_TESTED);
    let figures = plan_pairs(&pairs);
    figures.print("blocked pairs", pairs.len(), settings.collision.margin());
    assert_eq!(figures.blocked, pairs.len());
    let share = figures.planned as f64 / pairs.len() as f64;
    assert!(
        share >= MIN_PLANNED_SHARE,
        "{} of {} planned",
        figures.planned,
        pairs.len()
    );
}

/// The first of the pairs whose direct move is blocked.
fn blocked_pair(settings: &rigbridge::daemon::config::RunSettings) -> (Vec<f64>, Vec<f64>) {
    let model = settings.collision.as_ref();
    blocked_pairs(&settings.tcp_rig, model, 1).remove(0)
}

#[test]
fn the_same_seed_plans_the_same_path() {
    let settings = demo_settings();
    let (rig, model) = (&settings.tcp_rig, settings.collision.as_ref());
    let (start, goal) = blocked_pair(&settings);
    let options = FreePlanOptions::default();
    let first = plan_free(model, rig, &start, &goal, &options).expect("planned");
    let again = plan_free(model, rig, &start, &goal, &options).expect("planned");
    assert!(
        first.len() > 2,
        "the direct move is blocked: the path goes around"
    );
    assert_eq!(first, again, "bit for bit");
    // Other seeds find other trees; at least one of a few ends on another path.
    let others: Vec<Vec<Vec<f64>>> = (1..4)
        .map(|seed| {
            let options = FreePlanOptions { seed, ..options };
            plan_free(model, rig, &start, &goal, &options).expect("planned")
        })
        .collect();
    assert!(others.iter().any(|path| *path != first));
}

#[test]
fn a_goal_inside_the_pillar_is_refused_naming_it() {
    let settings = demo_settings();
    let (rig, model) = (&settings.tcp_rig, settings.collision.as_ref());
    let start = [43.0_f64, 20.0, 20.0, 0.0, 50.0, 0.0].map(f64::to_radians);
    // Seeded search for a configuration whose closest pair overlaps the pillar.
    let mut rng = common::rng(7);
    let pillar = model.body_id("pillar").expect("the demo cell has a pillar");
    let mut scratch = model.scratch();
    let goal = (0..100_000)
        .map(|_| common::random_configuration(rig, &mut rng))
        .find(|q| {
            let c = model.clearance(q, &mut scratch);
            c.distance_m < 0.0 && (c.a == pillar || c.b == pillar)
        })
        .expect("some configuration runs into the pillar");
    let error = plan_free(model, rig, &start, &goal, &FreePlanOptions::default())
        .expect_err("a goal inside the pillar is refused");
    let text = error.to_string();
    println!("{text}");
    assert!(
        matches!(&error, FreePlanError::EndBlocked { end: End::Goal, body_b, distance_m, .. }
            if body_b == "pillar" && *distance_m < 0.0),
        "{text}"
    );
    assert!(text.contains("goal") && text.contains("pillar") && text.contains(" deg"));
    assert!(text.contains("overlap by"), "{text}");
}

/// The IRB 120 on its floor with a divider in the plane y = 0: plates everywhere within
/// 1 m except a slot round the base and the first link (|x| < 0.15 m, z < 0.40 m), so no
/// configuration whose second link lies in that plane is clear, and the arm on the left
/// (joint 1 at +90 deg, leaning out) cannot reach the right.
fn divided_cell() -> Cell {
    const HALF_THICKNESS_M: f64 = 0.005;
    let plate = |name: &str, (x0, x1): (f64, f64), (z0, z1): (f64, f64)| CellObject {
        name: name.to_string(),
        pose: DAffine3::from_translation(DVec3::new((x0 + x1) / 2.0, 0.0, (z0 + z1) / 2.0)),
        shape: Shape::Box {
            half_extents: DVec3::new((x1 - x0) / 2.0, HALF_THICKNESS_M, (z1 - z0) / 2.0),
        },
    };
    let mut cell = Cell::builtin();
    cell.objects
        .push(plate("divider_front", (0.15, 1.0), (0.0, 1.2)));
    cell.objects
        .push(plate("divider_back", (-1.0, -0.15), (0.0, 1.2)));
    cell.objects
        .push(plate("divider_top", (-0.15, 0.15), (0.40, 1.2)));
    cell
}

#[test]
fn a_goal_walled_off_from_the_start_is_refused_within_the_budget() {
    let rig = common::irb120();
    let model = CollisionModel::new(&rig, &divided_cell()).expect("the model builds");
    let start = [90.0_f64, 60.0, -30.0, 0.0, 30.0, 0.0].map(f64::to_radians);
    let goal = [-90.0_f64, 60.0, -30.0, 0.0, 30.0, 0.0].map(f64::to_radians);
    let mut scratch = model.scratch();
    for q in [&start, &goal] {
        let c = model.clearance(q, &mut scratch);
        assert!(
            c.distance_m >= model.margin(),
            "{} is not clear: {} and {} at {} m",
            deg(q),
            model.body_name(c.a),
            model.body_name(c.b),
            c.distance_m
        );
    }
    // A small budget keeps the test short; the wall holds whatever the budget.
    let options = FreePlanOptions {
        max_samples: 300,
        ..FreePlanOptions::default()
    };
    let error =
        plan_free(&model, &rig, &start, &goal, &options).expect_err("no path crosses the divider");
    let text = error.to_string();
    println!("{text}");
    let FreePlanError::NoPath {
        blocked_a,
        blocked_b,
        samples,
        max_samples,
        ..
    } = &error
    else {
        panic!("not a refusal for want of a path: {text}");
    };
    assert_eq!((*samples, *max_samples), (300, 300));
    assert!(blocked_b.starts_with("divider"), "{text}");
    assert!(blocked_a.starts_with("link_"), "{text}");
    // As a job: refused when planned, naming the target.
    let job: rigbridge::job::Job = serde_json::from_value(serde_json::json!({
        "kind": "move_joints",
        "targets_deg": [[-90.0, 60.0, -30.0, 0.0, 30.0, 0.0]],
        "plan_around": true,
    }))
    .expect("the job parses");
    let settings = PlanSettings {
        free: options,
        ..PlanSettings::default()
    };
    let refused = job
        .plan(&rigbridge::job::PlanContext {
            rig: &rig,
            app_rig: None,
            start: &start,
            settings: &settings,
            model: Some(&model),
        })
        .expect_err("the job is refused before motion");
    let job_text = refused.to_string();
    assert!(job_text.starts_with("job.targets_deg[0]: "), "{job_text}");
    assert!(job_text.ends_with(&text), "{job_text}");
    for needle in [
        "joint_1 90.000 deg",
        "joint_1 -90.000 deg",
        "free_max_samples = 300",
    ] {
        assert!(text.contains(needle), "`{needle}` missing from {text}");
    }
}

/// The demo's targets over the tray and over the fixture: the pillar stands between them.
const OVER_TRAY_DEG: [f64; 6] = [43.0, 20.0, 20.0, 0.0, 50.0, 0.0];
const OVER_FIXTURE_DEG: [f64; 6] = [-43.0, 20.0, 20.0, 0.0, 50.0, 0.0];

#[test]
fn a_move_joints_job_with_plan_around_runs_past_the_pillar_without_contact() {
    let settings = demo_settings();
    let (rig, model) = (&settings.tcp_rig, settings.collision.as_ref());
    let start: Vec<f64> = OVER_TRAY_DEG.map(f64::to_radians).to_vec();
    let goal: Vec<f64> = OVER_FIXTURE_DEG.map(f64::to_radians).to_vec();
    // The premise: the joint move the user wrote runs into the pillar.
    let direct = plan_joint_moves(
        rig,
        &start,
        std::slice::from_ref(&goal),
        &PlanSettings::default(),
    )
    .expect("the direct move plans");
    let refusal = check_clear(&direct, rig, model, &Origins::default())
        .expect_err("the direct move hits the pillar");
    assert!(
        [&refusal.body_a, &refusal.body_b].contains(&&"pillar".to_string()),
        "{refusal}"
    );
    let dir = common::scratch_dir("free_plan", "run");
    for file in ["irb120.toml", "cells/pick-place.toml"] {
        std::fs::create_dir_all(dir.join(file).parent().unwrap()).unwrap();
        std::fs::copy(repo_path(&format!("config/{file}")), dir.join(file)).unwrap();
    }
    let job = |plan_around: bool| {
        format!(
            "rig = \"irb120.toml\"\ncell = \"cells/pick-place.toml\"\n\n[twin]\n\
             initial_deg = {OVER_TRAY_DEG:?}\n\n[job]\nkind = \"move_joints\"\n\
             targets_deg = [{OVER_FIXTURE_DEG:?}]\nplan_around = {plan_around}\n"
        )
    };
    let run = |plan_around: bool| {
        std::fs::write(dir.join("job.toml"), job(plan_around)).unwrap();
        let output = Command::new(env!("CARGO_BIN_EXE_rigbridge"))
            .args(["run", "--config", "job.toml", "--clock", "virtual"])
            .args(["--report", "report.json"])
            .current_dir(&dir)
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&output.stderr).to_string();
        let report: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(dir.join("report.json")).unwrap())
                .unwrap();
        (output.status.success(), stderr, report)
    };
    // The key is in the jobs' JSON Schema (GET /api/schema).
    assert!(
        rigbridge::job::request_schema()
            .to_string()
            .contains("plan_around")
    );
    // Without the key: refused before motion, with the hint.
    let (ok, stderr, report) = run(false);
    assert!(!ok, "{stderr}");
    assert_eq!(report["outcome"], "refused", "{report}");
    assert_eq!(report["cycles"], 0, "{report}");
    let fault = report["fault"].as_str().unwrap_or_default();
    assert!(fault.contains("pillar"), "{fault}");
    assert!(fault.contains("job.plan_around = true"), "{fault}");
    // With it: around the pillar, to the end, and the twin measured no contact.
    let (ok, stderr, report) = run(true);
    assert!(ok, "{stderr}\n{report}");
    assert_eq!(report["outcome"], "completed", "{report}");
    let contacts = &report["contacts"];
    println!(
        "plan_around run: {} cycles, contacts {contacts}",
        report["cycles"]
    );
    assert_eq!(contacts["collisions"], 0, "{report}");
    assert!(
        contacts["measured_cycles"].as_u64().unwrap_or(0) > 0,
        "{report}"
    );
}

#[test]
fn plan_around_without_a_cell_to_plan_around_is_refused_naming_the_key() {
    let job: rigbridge::job::Job = serde_json::from_value(serde_json::json!({
        "kind": "move_joints",
        "targets_deg": [OVER_FIXTURE_DEG],
        "plan_around": true,
    }))
    .expect("the job parses");
    let rig = common::irb120();
    let start = OVER_TRAY_DEG.map(f64::to_radians);
    // `plan_job` plans without a cell.
    let refused = rigbridge::job::plan_job(&job, &rig, &start, &PlanSettings::default())
        .expect_err("nothing to plan around");
    assert_eq!(
        refused.to_string(),
        "job.plan_around = true needs the cell's collision model, and this plan was given none"
    );
}

#[test]
fn a_free_budget_out_of_range_is_refused_on_load_naming_file_key_and_value() {
    let dir = common::scratch_dir("free_plan", "budget");
    std::fs::copy(repo_path("config/irb120.toml"), dir.join("irb120.toml")).unwrap();
    for (value, loads) in [
        ("0", false),
        ("100001", false),
        ("1", true),
        ("100000", true),
    ] {
        let file = dir.join("job.toml");
        std::fs::write(
            &file,
            format!(
                "rig = \"irb120.toml\"\n\n[plan]\nfree_max_samples = {value}\n\n[job]\n\
                 kind = \"move_joints\"\ntargets_deg = [[0.0, 0.0, 0.0, 0.0, 30.0, 0.0]]\n"
            ),
        )
        .unwrap();
        let loaded = rigbridge::daemon::config::load_run_settings(&file);
        assert_eq!(loaded.is_ok(), loads, "free_max_samples = {value}");
        if let Err(error) = loaded {
            let text = error.to_string();
            for needle in ["job.toml", "plan.free_max_samples", value, "[1, 100000]"] {
                assert!(text.contains(needle), "`{needle}` missing from {text}");
            }
        }
    }
}
