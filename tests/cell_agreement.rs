//! `rigbridge check` against a collision checker we did not write (issue 27): 100,000
//! seeded random in-limit configurations of the IRB 120 with a gripper on a table
//! (config/table-cell.toml, docs/cell.md's worked example). PyPI's `coal` measures the same
//! world from the URDF and SRDF `rigbridge config urdf` writes (tests/peers/coal_distance.py
//! parses them and does its own forward kinematics): the same status on every row, and the
//! clearances within 1e-4 m wherever both say free.

use crate::common;

use common::{random_configuration, repo_path, rng};
use rigbridge::daemon::config::load_run_settings;
use std::path::Path;
use std::process::Command;
use std::time::Instant;

/// The figure: this many configurations.
const ROWS: usize = 100_000;
/// The figure: clearances agree to this where both checkers say free.
const CLEARANCE_TOLERANCE_M: f64 = 1e-4;
const SEED: u64 = 27;
const SETTINGS: &str = "config/table-cell.toml";

/// The Python with coal (RIGBRIDGE_COAL_PYTHON, set by scripts/test.sh).
fn peer_python() -> Result<String, String> {
    common::peer_python("RIGBRIDGE_COAL_PYTHON", "coal, numpy", "coal")
}

fn rigbridge(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_rigbridge"))
        .args(args)
        .env_remove("RIGBRIDGE_CONFIG")
        .output()
        .expect("rigbridge runs")
}

/// One output row: clearance, the two bodies (as a sorted pair), the status.
#[derive(Debug, Clone, PartialEq)]
struct Row {
    distance_m: f64,
    pair: (String, String),
    status: String,
}

fn rows(text: &str, header: bool) -> Vec<Row> {
    text.lines()
        .skip(usize::from(header))
        .map(|line| {
            let f: Vec<&str> = line.split(',').collect();
            assert_eq!(f.len(), 4, "a row of four fields: {line}");
            let (a, b) = (f[1].to_string(), f[2].to_string());
            Row {
                distance_m: f[0]
                    .parse()
                    .unwrap_or_else(|_| panic!("a clearance: {line}")),
                pair: if a <= b { (a, b) } else { (b, a) },
                status: f[3].to_string(),
            }
        })
        .collect()
}

fn path_str(path: &Path) -> &str {
    path.to_str().expect("a UTF-8 path")
}

#[test]
fn check_agrees_with_coal_on_100000_random_configurations_of_the_table_cell() {
    let python = match peer_python() {
        Ok(python) => python,
        Err(reason) if std::env::var("CI").as_deref() == Ok("true") => {
            panic!("CI must test the collision model against PyPI's coal: {reason}")
        }
        Err(reason) => {
            println!("skipping the coal agreement test: {reason}");
            return;
        }
    };
    let settings_path = repo_path(SETTINGS);
    let settings = load_run_settings(&settings_path).expect("the worked example loads");
    let dir = common::scratch_dir("cell_agreement", "coal");
    let mut rng = rng(SEED);
    let mut joints = String::from("j1,j2,j3,j4,j5,j6\n");
    for _ in 0..ROWS {
        let q = random_configuration(&settings.rig, &mut rng);
        let line: Vec<String> = q.iter().map(|r| format!("{:.9}", r.to_degrees())).collect();
        joints.push_str(&line.join(","));
        joints.push('\n');
    }
    let input = dir.join("joints.csv");
    std::fs::write(&input, joints).unwrap();
    let (urdf, srdf, ours) = (
        dir.join("table-cell.urdf"),
        dir.join("table-cell.srdf"),
        dir.join("ours.csv"),
    );
    let settings_arg = path_str(&settings_path);
    let written = rigbridge(&[
        "config",
        "urdf",
        "--config",
        settings_arg,
        "--output",
        path_str(&urdf),
        "--srdf",
        path_str(&srdf),
    ]);
    assert!(
        written.status.success(),
        "{}",
        String::from_utf8_lossy(&written.stderr)
    );

    let start = Instant::now();
    let checked = rigbridge(&[
        "check",
        "--config",
        settings_arg,
        "--input",
        path_str(&input),
        "--output",
        path_str(&ours),
    ]);
    let ours_s = start.elapsed().as_secs_f64();
    // Some rows collide, so the batch exits 3 (not every row free).
    assert_eq!(
        checked.status.code(),
        Some(3),
        "{}",
        String::from_utf8_lossy(&checked.stderr)
    );

    let start = Instant::now();
    let peer = Command::new(&python)
        .arg(repo_path("tests/peers/coal_distance.py"))
        .args([&urdf, &srdf, &input])
        .arg(settings.cell.margin_m.to_string())
        .output()
        .expect("the coal peer runs");
    let peer_s = start.elapsed().as_secs_f64();
    assert!(
        peer.status.success(),
        "coal peer: {}",
        String::from_utf8_lossy(&peer.stderr)
    );

    let ours = rows(&std::fs::read_to_string(&ours).unwrap(), true);
    let theirs = rows(&String::from_utf8_lossy(&peer.stdout), false);
    assert_eq!((ours.len(), theirs.len()), (ROWS, ROWS));
    let mut mismatches = Vec::new();
    let (mut max_difference, mut free_rows, mut same_pair) = (0.0f64, 0, 0);
    let mut counts = std::collections::BTreeMap::<&str, usize>::new();
    for (i, (a, b)) in ours.iter().zip(&theirs).enumerate() {
        *counts.entry(a.status.as_str()).or_default() += 1;
        if a.status != b.status {
            mismatches.push(format!("row {}: ours {a:?}, coal {b:?}", i + 1));
            continue;
        }
        if a.status == "free" {
            free_rows += 1;
            let difference = (a.distance_m - b.distance_m).abs();
            max_difference = max_difference.max(difference);
            if difference > CLEARANCE_TOLERANCE_M {
                mismatches.push(format!("row {}: clearance ours {a:?}, coal {b:?}", i + 1));
            }
            same_pair += usize::from(a.pair == b.pair);
        }
    }
    println!(
        "cell agreement: {ROWS} rows ({counts:?}), {} mismatches, max clearance difference \
         {max_difference:.3e} m over {free_rows} free rows, same closest pair on {same_pair}; \
         rigbridge check {ours_s:.2} s, coal peer {peer_s:.1} s",
        mismatches.len()
    );
    assert!(
        mismatches.is_empty(),
        "{} rows disagree; the first: {}",
        mismatches.len(),
        mismatches
            .iter()
            .take(10)
            .cloned()
            .collect::<Vec<_>>()
            .join("\n")
    );
    // Every status is exercised, or the agreement would prove less than it says.
    for status in ["free", "within_margin", "collision"] {
        assert!(
            counts.get(status).copied().unwrap_or(0) >= 100,
            "{status}: {counts:?}"
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}
