//! Helpers shared by the integration tests: the shipped IRB 120 rig, the independent
//! reference data in `../shared/reference`, seeded random configurations, the issue's
//! figures every passing gait run must meet, waiting on a condition (never for a fixed
//! time: a loaded machine makes a test slower, not wrong), running the binary with input on
//! stdin, scratch paths in the temporary directory, the shipped settings to copy; `serve` starts `rigbridge serve` and
//! talks to it, `twin` starts and stops `rigbridge twin`, `cli` runs the binary to the end
//! and reads its reports, `runlog` checks a run log read back, `cycles` serves tests that
//! hold real-time cycles, `group` kills a child's whole process group, `can` skips the SocketCAN tests where there is no bus.
#![allow(dead_code)]

pub mod can;
pub mod cli;
pub mod cycles;
pub mod group;
pub mod line_peer;
pub mod runlog;
pub mod serve;
pub mod twin;

use glam::{DQuat, DVec3};
use rand::{Rng, RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rigbridge::rig::{Pose, Rig, load_rig};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// How often [`wait_until`] looks again: short beside anything a test waits for (a chunk
/// of a log, a cycle of 4 ms), long enough not to load the machine.
const POLL: Duration = Duration::from_millis(20);

/// Looks at `condition` until it gives a value, and returns it; fails the test, naming
/// `what`, when `within` has passed first.
pub fn wait_until<T>(what: &str, within: Duration, mut condition: impl FnMut() -> Option<T>) -> T {
    let deadline = Instant::now() + within;
    loop {
        if let Some(value) = condition() {
            return value;
        }
        assert!(
            Instant::now() < deadline,
            "timed out after {} s waiting for {what}",
            within.as_secs_f64()
        );
        std::thread::sleep(POLL);
    }
}

/// Waits until the run log at `path`, still being written, holds more than `commands`
/// commands in its closed chunks (the recorder closes one at least every second): the job
/// is then streaming. Returns how many it holds.
pub fn wait_for_logged_commands(path: &Path, commands: usize, within: Duration) -> usize {
    wait_until(
        &format!("more than {commands} commands in {}", path.display()),
        within,
        || {
            let logged = rigbridge::log::read_log(path).ok()?.commands.len();
            (logged > commands).then_some(logged)
        },
    )
}

/// Waits until the run log at `path`, still being written, holds an event of `kind`.
pub fn wait_for_logged_event(path: &Path, kind: &str, within: Duration) {
    wait_until(
        &format!("a {kind} event in {}", path.display()),
        within,
        || {
            let log = rigbridge::log::read_log(path).ok()?;
            log.events.iter().any(|e| e.kind == kind).then_some(())
        },
    );
}

/// The text of the shipped run settings, `config/rigbridge.toml`, with its rig and its cell
/// named by absolute path: a copy anywhere loads the shipped IRB 120 in the star's cell.
pub fn shipped_settings_text() -> String {
    let text = std::fs::read_to_string(repo_path("config/rigbridge.toml")).unwrap();
    let rig = repo_path("config/irb120.toml");
    let cell = repo_path("config/cell-star.toml");
    text.replacen(
        "rig = \"irb120.toml\"",
        &format!("rig = {:?}", rig.display().to_string()),
        1,
    )
    .replacen(
        "cell = \"cell-star.toml\"",
        &format!("cell = {:?}", cell.display().to_string()),
        1,
    )
}

/// `text` (run settings copied from `config/`) with its cell named by absolute path, so the
/// copy loads from any directory.
pub fn with_absolute_cell(text: &str) -> String {
    let cell = repo_path("config/cell-star.toml");
    text.replacen(
        "cell = \"cell-star.toml\"",
        &format!("cell = {:?}", cell.display().to_string()),
        1,
    )
}

/// [`shipped_settings_text`] with `serve` appended as its `[serve]` table, written to `path`.
pub fn write_settings_with_serve(path: &Path, serve: &str) {
    let text = shipped_settings_text();
    std::fs::write(path, format!("{text}\n[serve]\n{serve}\n")).unwrap();
}

/// The pick-and-place demo's job (`config/pick-place.toml`) with its repeat over two slots
/// only, as the JSON a job request carries: a few seconds of wall time.
pub fn two_part_demo_job() -> serde_json::Value {
    let text = std::fs::read_to_string(repo_path("config/pick-place.toml")).unwrap();
    let text = text.replace("over = \"slot\"", "over = [\"slot[0]\", \"slot[1]\"]");
    assert!(
        text.contains("slot[1]"),
        "the demo's repeat is over the grid"
    );
    let table: toml::Value = toml::from_str(&text).unwrap();
    serde_json::to_value(&table["job"]).unwrap()
}

/// The shipped run settings, `config/rigbridge.toml`.
pub fn shipped_run_settings() -> rigbridge::daemon::config::RunSettings {
    rigbridge::daemon::config::load_run_settings(&repo_path("config/rigbridge.toml"))
        .expect("the default run settings load")
}

/// Runs `command` with `stdin` written to it and collects its output. The command may exit
/// before reading all its input (a usage error): a closed pipe is fine.
pub fn output_with_stdin(command: &mut std::process::Command, stdin: &str) -> std::process::Output {
    use std::io::Write;
    use std::process::Stdio;
    let mut child = command
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut pipe = child.stdin.take().unwrap();
    let input = stdin.to_string();
    let writer = std::thread::spawn(move || pipe.write_all(input.as_bytes()));
    let output = child.wait_with_output().unwrap();
    if let Err(e) = writer.join().unwrap() {
        assert_eq!(e.kind(), std::io::ErrorKind::BrokenPipe, "{e}");
    }
    output
}

/// `name` in the temporary directory of the test file `suite` in this process
/// (`rigbridge-{suite}-{pid}`), with what an earlier test left there removed.
pub fn scratch_file(suite: &str, name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("rigbridge-{suite}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join(name);
    let _ = std::fs::remove_file(&path);
    path
}

/// An empty directory `name` of the test file `suite` in this process
/// (`rigbridge-{suite}-{pid}-{name}` in the temporary directory), emptied if an earlier test
/// left it.
pub fn scratch_dir(suite: &str, name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("rigbridge-{suite}-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

pub fn repo_path(relative: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join(relative)
}

/// Every `.rs` file under `dir`, its folders walked, in sorted order (the source-reading
/// tests, tests/layers.rs and tests/time.rs, read `src/` with it).
pub fn rust_files(dir: &Path) -> Vec<PathBuf> {
    let mut files = Vec::new();
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.is_dir() {
            files.extend(rust_files(&path));
        } else if path.extension().is_some_and(|e| e == "rs") {
            files.push(path);
        }
    }
    files.sort();
    files
}

/// `../shared/reference`, or `RIGBRIDGE_REFERENCE_DIR` where the checkout sits elsewhere.
pub fn reference_path(file: &str) -> PathBuf {
    std::env::var_os("RIGBRIDGE_REFERENCE_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| repo_path("../shared/reference"))
        .join(file)
}

pub fn irb120() -> Rig {
    load_rig(&repo_path("config/irb120.toml")).expect("shipped IRB 120 config loads")
}

pub struct ReferenceRow {
    pub joints_deg: [f64; 6],
    pub pose: Pose,
}

pub fn reference_rows() -> Vec<ReferenceRow> {
    let path = reference_path("irb120_fk.csv");
    let text = std::fs::read_to_string(&path)
        .unwrap_or_else(|e| panic!("reference data {} is needed: {e}", path.display()));
    let mut lines = text.lines();
    assert_eq!(lines.next(), Some("j1,j2,j3,j4,j5,j6,x,y,z,qw,qx,qy,qz"));
    lines
        .map(|line| {
            let v: Vec<f64> = line.split(',').map(|f| f.parse().unwrap()).collect();
            ReferenceRow {
                joints_deg: v[..6].try_into().unwrap(),
                pose: Pose::new(
                    DVec3::new(v[6], v[7], v[8]),
                    DQuat::from_xyzw(v[10], v[11], v[12], v[9]),
                ),
            }
        })
        .collect()
}

pub fn rng(seed: u64) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(seed)
}

/// A uniformly random configuration strictly inside the rig's limits.
pub fn random_configuration(rig: &Rig, rng: &mut impl Rng) -> Vec<f64> {
    rig.joints
        .iter()
        .map(|j| rng.random_range(j.limits.lower..j.limits.upper))
        .collect()
}

pub fn degrees(radians: &[f64]) -> Vec<f64> {
    radians.iter().map(|r| r.to_degrees()).collect()
}

/// The supports `limb` stood on in a gait run, stance by stance in time order.
pub fn supports_walked(run: &rigbridge::apps::gait::run::GaitRun, limb: usize) -> Vec<usize> {
    let mut stances: Vec<_> = run.plan.stances.iter().filter(|s| s.limb == limb).collect();
    stances.sort_by_key(|s| s.start);
    stances.iter().map(|s| s.contact.support).collect()
}

/// The figures every passing gait run meets (issue 6): passed over at least 3 judged cycles,
/// streamed to the end within the limits, feet on the surface within 5 mm, slip within 1 mm,
/// bones in range, the body clear of every support.
pub fn assert_gait_figures(run: &rigbridge::apps::gait::run::GaitRun) {
    let v = &run.verdict;
    assert!(
        v.passed,
        "{} {:?} {:?}: {:?}",
        v.scenario, v.angle_deg, v.gap_m, v.reason
    );
    assert!(v.cycles_judged >= 3);
    assert_eq!(
        run.run.stream.outcome,
        rigbridge::stream::Outcome::Completed
    );
    assert_eq!(run.run.stream.limit_violations, 0);
    for limb in &v.limbs {
        assert!(limb.max_foot_to_surface_mm <= 5.0, "{limb:?}");
        assert!(limb.max_slip_mm <= 1.0, "{limb:?}");
        assert!(
            limb.max_bone_excursion_deg <= limb.bone_limit_deg + 1e-9,
            "{limb:?}"
        );
    }
    assert!(v.min_body_clearance_mm > 0.0);
    // Issue 14: no axis commanded above its max acceleration (the plan keeps 0.8 of it).
    assert!(
        v.peak_acceleration_ratio <= 1.0,
        "{} x max acceleration on {}",
        v.peak_acceleration_ratio,
        v.peak_acceleration_joint
    );
    // No head-first descent beyond the seed's 20 deg (and a degree of the twin's lag).
    assert!(
        v.min_heading_elevation_deg >= -21.0,
        "head down {} deg",
        v.min_heading_elevation_deg
    );
}

/// Whether the full tier runs (docs/testing.md, "Two tiers"): `scripts/test.sh` and CI
/// (`CI=true`) run every test; a plain `cargo test` is the fast tier, where the slow
/// real-time tests (processes streaming for seconds, a browser, the fault injection) say
/// they skip, and how to run them.
pub fn in_full_tier(test: &str) -> bool {
    let full = std::env::var("RIGBRIDGE_TIER").as_deref() == Ok("full")
        || std::env::var("CI").as_deref() == Ok("true");
    if !full {
        println!(
            "skipping {test}: it belongs to the full tier (slow real-time runs); run it with \
             RIGBRIDGE_TIER=full, or run everything with bash scripts/test.sh"
        );
    }
    full
}

/// The Python of a PyPI peer: `$var` (scripts/test.sh sets it to the peer's venv), else
/// `python3`, if it can run `import {imports}`. The error says why not, for the skip note.
pub fn peer_python(var: &str, imports: &str, what: &str) -> Result<String, String> {
    let python = std::env::var(var).unwrap_or_else(|_| "python3".into());
    let probe = std::process::Command::new(&python)
        .args(["-c", &format!("import {imports}")])
        .output()
        .map_err(|e| format!("cannot run {python}: {e}"))?;
    if probe.status.success() {
        Ok(python)
    } else {
        Err(format!(
            "{python} cannot import {what} (scripts/test.sh installs it): {}",
            String::from_utf8_lossy(&probe.stderr).trim()
        ))
    }
}
