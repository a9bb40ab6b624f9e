//! The Foxglove-native channels of a run log, read by a peer we did not write: PyPI's `mcap`
//! with `mcap-protobuf-support` (tests/peers/foxglove_log.py) decodes every `/tf` message and
//! composes the base-to-tool transform; we compare it with our own FK of the actual positions
//! logged at the same time, count the `/tf` rate over log time, and read the URDF attachment
//! back. Run through the binary (`rigbridge run --clock virtual --log X`), for a TOML rig (the
//! URDF generated from the model) and a URDF rig (the file attached as is, fixed links kept).

use crate::common;

use common::cli::{assert_succeeded_as, numbers};
use common::{reference_path, repo_path};
use rigbridge::log::{TF_TOPIC, URDF_ATTACHMENT, read_log};
use rigbridge::rig::{Rig, load_rig, rig_from_urdf_to};
use std::path::{Path, PathBuf};
use std::process::Command;

/// The figures: /tf agrees with our FK at tool0 to 1e-9 m, at 50 Hz or more.
const MAX_TOOL_DEVIATION_M: f64 = 1e-9;
const MIN_TF_RATE_HZ: f64 = 50.0;

/// The Python with mcap and mcap-protobuf-support (RIGBRIDGE_FOXGLOVE_PYTHON, set by
/// scripts/test.sh).
fn peer_python() -> Result<String, String> {
    common::peer_python(
        "RIGBRIDGE_FOXGLOVE_PYTHON",
        "mcap.reader, mcap_protobuf.decoder",
        "mcap and mcap_protobuf",
    )
}

fn scratch(name: &str) -> PathBuf {
    common::scratch_dir("foxglove", name)
}

fn record_run(config: &Path, log: &Path) {
    let output = Command::new(env!("CARGO_BIN_EXE_rigbridge"))
        .arg("run")
        .arg("--config")
        .arg(config)
        .args(["--clock", "virtual", "--log"])
        .arg(log)
        .output()
        .unwrap();
    assert_succeeded_as(&output, "rigbridge run");
}

/// The default run settings with `rig` pointing at the reference URDF.
fn urdf_run_settings(dir: &Path) -> PathBuf {
    let text = common::with_absolute_cell(
        &std::fs::read_to_string(repo_path("config/rigbridge.toml")).unwrap(),
    );
    let urdf = reference_path("irb120_3_58.urdf");
    let replaced = text.replacen(
        "rig = \"irb120.toml\"",
        &format!("rig = {}", toml_string(&urdf)),
        1,
    );
    assert_ne!(
        replaced, text,
        "config/rigbridge.toml names its rig differently"
    );
    let path = dir.join("urdf-run.toml");
    std::fs::write(&path, replaced).unwrap();
    path
}

fn toml_string(path: &Path) -> String {
    format!("\"{}\"", path.display().to_string().replace('\\', "\\\\"))
}

struct Peer {
    rows: Vec<serde_json::Value>,
    summary: serde_json::Value,
}

fn run_peer(python: &str, log: &Path, rig: &Rig) -> Peer {
    let output = Command::new(python)
        .arg(repo_path("tests/peers/foxglove_log.py"))
        .arg(log)
        .args([&rig.base_frame, &rig.tool_frame])
        .output()
        .unwrap();
    assert_succeeded_as(&output, "the peer");
    let mut rows: Vec<serde_json::Value> = String::from_utf8(output.stdout)
        .unwrap()
        .lines()
        .map(|line| serde_json::from_str(line).unwrap())
        .collect();
    let summary = rows.pop().unwrap()["summary"].clone();
    Peer { rows, summary }
}

/// Largest distance at the tool between the peer's composed /tf and our FK of the positions.
fn max_tool_deviation(peer: &Peer, rig: &Rig) -> (f64, f64) {
    let (mut position, mut rotation) = (0.0_f64, 0.0_f64);
    for row in &peer.rows {
        let q = numbers(&row["positions"]);
        let ours = rig.forward(&q).unwrap();
        let tool = numbers(&row["tool"]);
        let d = ours.translation - glam::DVec3::new(tool[0], tool[1], tool[2]);
        position = position.max(d.length());
        let r = numbers(&row["rotation"]);
        let theirs = glam::DQuat::from_xyzw(r[1], r[2], r[3], r[0]);
        let ours_q = glam::DQuat::from_mat3(&ours.matrix3);
        // q and -q are the same rotation.
        rotation = rotation.max(1.0 - ours_q.dot(theirs).abs());
    }
    (position, rotation)
}

fn check_log(name: &str, config: &Path, rig: &Rig, python: &str) {
    let dir = scratch(name);
    let log = dir.join("run.mcap");
    record_run(config, &log);
    let ours = read_log(&log).unwrap();
    assert!(
        !ours.truncated && ours.states.len() > 1000,
        "{name}: a full run"
    );

    let peer = run_peer(python, &log, rig);
    let count = peer.rows.len();
    assert_eq!(peer.summary["tf_messages"].as_u64(), Some(count as u64));
    assert!(
        peer.rows.iter().all(|r| r["positions"].is_array()),
        "{name}: each /tf has its state"
    );
    let (deviation, rotation) = max_tool_deviation(&peer, rig);
    let first = peer.summary["first_log_time"].as_f64().unwrap();
    let last = peer.summary["last_log_time"].as_f64().unwrap();
    let rate = (count - 1) as f64 / ((last - first) * 1e-9);
    let span = ours.states.last().unwrap().t - ours.states[0].t;
    println!(
        "{name}: {count} /tf messages over {span:.3} s of states, {rate:.2} Hz; max deviation at {}: {deviation:.3e} m, rotation 1-|dot| {rotation:.3e}; log {} bytes",
        rig.tool_frame,
        std::fs::metadata(&log).unwrap().len()
    );
    assert!(
        deviation <= MAX_TOOL_DEVIATION_M,
        "{name}: {deviation} m at the tool"
    );
    assert!(
        rotation <= 1e-12,
        "{name}: tool rotation differs by {rotation}"
    );
    assert!(rate >= MIN_TF_RATE_HZ, "{name}: /tf at {rate} Hz");
    // The /tf messages cover the whole run, not just a part at that rate.
    assert!(
        (last - first) * 1e-9 >= span - 0.05,
        "{name}: /tf stops early"
    );
    check_attachment(name, &log, rig, &peer);
    assert!(
        ours.other_messages >= count as u64,
        "{name}: our reader skips {TF_TOPIC}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// robot_description.urdf is there for the peer, and it is the rig: it loads with urdf-rs and
/// gives the rig's FK.
fn check_attachment(name: &str, log: &Path, rig: &Rig, peer: &Peer) {
    let attachments: Vec<&str> = peer.summary["attachments"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_str().unwrap())
        .collect();
    assert_eq!(attachments, [URDF_ATTACHMENT], "{name}");
    let links: Vec<&str> = peer.summary["urdf_links"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_str().unwrap())
        .collect();
    assert!(links.contains(&rig.base_frame.as_str()) && links.contains(&rig.tool_frame.as_str()));
    let bytes = std::fs::read(log).unwrap();
    let summary = mcap::Summary::read(&bytes).unwrap().unwrap();
    assert_eq!(summary.attachment_indexes.len(), 1);
    let attachment = mcap::read::attachment(&bytes, &summary.attachment_indexes[0]).unwrap();
    let text = std::str::from_utf8(&attachment.data).unwrap();
    // The attachment carries the cell (a tool, if any, past tool0): the chain to the rig's
    // tool frame is the rig's.
    let back = rig_from_urdf_to(text, Path::new(URDF_ATTACHMENT), Some(&rig.tool_frame)).unwrap();
    let q = [0.4, -0.3, 0.2, 1.0, -0.8, 2.5];
    let (a, b) = (back.forward(&q).unwrap(), rig.forward(&q).unwrap());
    assert!(
        (a.translation - b.translation).length() <= 1e-12,
        "{name}: URDF FK differs"
    );
}

#[test]
fn foxglove_channels_agree_with_our_fk_for_a_reader_we_did_not_write() {
    let python = match peer_python() {
        Ok(python) => python,
        Err(reason) if std::env::var("CI").as_deref() == Ok("true") => {
            panic!("CI must test the log against PyPI's mcap: {reason}")
        }
        Err(reason) => {
            println!("skipping the mcap-protobuf-support peer test: {reason}");
            return;
        }
    };
    let toml_rig = load_rig(&repo_path("config/irb120.toml")).unwrap();
    check_log(
        "toml-rig",
        &repo_path("config/rigbridge.toml"),
        &toml_rig,
        &python,
    );
    let dir = scratch("urdf-settings");
    let urdf_rig = load_rig(&reference_path("irb120_3_58.urdf")).unwrap();
    check_log("urdf-rig", &urdf_run_settings(&dir), &urdf_rig, &python);
    let _ = std::fs::remove_dir_all(&dir);
}

fn scene_peer(python: &str, log: &Path) -> serde_json::Value {
    let output = Command::new(python)
        .arg(repo_path("tests/peers/foxglove_scene.py"))
        .arg(log)
        .output()
        .unwrap();
    assert_succeeded_as(&output, "the scene peer");
    serde_json::from_slice(&output.stdout).unwrap()
}

/// Paint sits this far in front of its wall (`scene::foxglove`).
const PAINT_OFFSET_M: f64 = 0.002;

/// A paint log's `/scene`, replayed by the peer: the walls are the report's room less its
/// openings, outlined; paint grows over the run and lies on the walls.
#[test]
fn the_paint_room_is_a_scene_update_for_a_reader_we_did_not_write() {
    let python = match peer_python() {
        Ok(python) => python,
        Err(reason) if std::env::var("CI").as_deref() == Ok("true") => {
            panic!("CI must test the log against PyPI's mcap: {reason}")
        }
        Err(reason) => {
            println!("skipping the SceneUpdate peer test: {reason}");
            return;
        }
    };
    let dir = scratch("paint-scene");
    let report = common::cli::paint_three_walls_in(&dir);
    let room = &report["room"];
    let peer = scene_peer(&python, &dir.join("p.mcap"));
    assert_eq!(peer["schema"], "foxglove.SceneUpdate");

    let (width, height) = (
        room["wall_width_m"].as_f64().unwrap(),
        room["wall_height_m"].as_f64().unwrap(),
    );
    let walls = room["walls"].as_array().unwrap();
    let openings: Vec<&serde_json::Value> = walls
        .iter()
        .flat_map(|w| w["openings"].as_array().unwrap())
        .collect();
    let open_area: f64 = openings
        .iter()
        .map(|o| {
            let n = |k: &str| o[k].as_f64().unwrap();
            (n("right_m") - n("left_m")) * (n("top_m") - n("bottom_m"))
        })
        .sum();
    let expected_area = walls.len() as f64 * width * height - open_area;
    let drawn = &peer["entities"]["walls"];
    assert!(
        (drawn["area"].as_f64().unwrap() - expected_area).abs() < 1e-9,
        "walls {} m2, the room {expected_area} m2",
        drawn["area"]
    );
    let loops = drawn["loops"].as_array().unwrap();
    assert_eq!(loops.len(), walls.len() + openings.len());
    // Each wall's outline: its two bottom corners at the floor, the top ones at its height.
    for wall in walls {
        let c: Vec<Vec<f64>> = wall["corners_xy"]
            .as_array()
            .unwrap()
            .iter()
            .map(numbers)
            .collect();
        let expected = [
            [c[0][0], c[0][1], 0.0],
            [c[1][0], c[1][1], 0.0],
            [c[1][0], c[1][1], height],
            [c[0][0], c[0][1], height],
        ];
        let found = loops.iter().any(|l| {
            let points: Vec<Vec<f64>> = l.as_array().unwrap().iter().map(numbers).collect();
            points.len() == 4
                && points
                    .iter()
                    .zip(&expected)
                    .all(|(p, e)| p.iter().zip(e).all(|(a, b)| (a - b).abs() < 1e-9))
        });
        assert!(found, "wall {} is outlined", wall["index"]);
    }

    // Paint goes on as the run goes: none at first, never less, most of the walls at the end.
    let areas: Vec<f64> = peer["paint_area"]
        .as_array()
        .unwrap()
        .iter()
        .map(|a| a[1].as_f64().unwrap())
        .collect();
    assert_eq!(areas[0], 0.0);
    assert!(
        areas.windows(2).all(|w| w[1] >= w[0] - 1e-9),
        "paint only grows"
    );
    let painted = report["totals"]["painted_m2"].as_f64().unwrap();
    let last = *areas.last().unwrap();
    println!(
        "/scene: {} messages, walls {expected_area:.3} m2, paint {last:.3} m2 (report: {painted:.3} m2 painted)",
        areas.len()
    );
    // Quads of 0.25 m of stroke cover what the coverage grid counts, overlaps counted twice.
    assert!(last >= painted * 0.95, "paint {last} m2 of {painted} m2");
    // Every paint point lies just in front of a wall's plane.
    for p in peer["paint_points"].as_array().unwrap().iter().map(numbers) {
        let off = walls
            .iter()
            .map(|w| {
                let c = numbers(&w["corners_xy"][0]);
                let n = numbers(&w["normal_xy"]);
                ((p[0] - c[0]) * n[0] + (p[1] - c[1]) * n[1]).abs()
            })
            .map(|d| (d - PAINT_OFFSET_M).abs())
            .fold(f64::MAX, f64::min);
        assert!(off < 1e-9, "paint at {p:?} is off its wall by {off} m");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// The sloth's log: its branch as a cylinder from the scenario's ends, its radius.
#[test]
fn the_sloths_branches_are_cylinders_for_a_reader_we_did_not_write() {
    let Ok(python) = peer_python() else {
        println!("skipping the SceneUpdate peer test: no peer (see the test above)");
        return;
    };
    let settings =
        rigbridge::daemon::config::load_run_settings(&repo_path("config/gait-run.toml")).unwrap();
    assert_eq!(
        serde_json::to_value(&settings.config.job).unwrap()["scenario"],
        "straight"
    );
    let scenario = rigbridge::apps::gait::Scenario::build("straight", None, None).unwrap();
    let dir = scratch("gait-scene");
    let log = dir.join("g.mcap");
    record_run(&repo_path("config/gait-run.toml"), &log);
    let peer = scene_peer(&python, &log);
    let drawn = peer["entities"]["cylinders"]["cylinders"]
        .as_array()
        .unwrap();
    assert_eq!(drawn.len(), scenario.terrain.cylinders.len());
    for (cylinder, branch) in drawn.iter().zip(&scenario.terrain.cylinders) {
        let centre = numbers(&cylinder["centre"]);
        let size = numbers(&cylinder["size"]);
        let q = numbers(&cylinder["orientation"]);
        let axis = glam::DQuat::from_xyzw(q[1], q[2], q[3], q[0]) * glam::DVec3::Z;
        let centre = glam::DVec3::new(centre[0], centre[1], centre[2]);
        let ends = [centre - axis * size[2] / 2.0, centre + axis * size[2] / 2.0];
        assert!((ends[0] - branch.from).length() < 1e-9, "{ends:?}");
        assert!((ends[1] - branch.to).length() < 1e-9, "{ends:?}");
        assert!((size[0] - 2.0 * branch.radius).abs() < 1e-12);
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// An arm's log draws its cell (issue 27): the cell's objects in the base frame, and each
/// frame's collision bodies (the tool's on the last) in that frame's `/tf` id, as a reader
/// we did not write replays `/scene`; triangles as many as the solids' meshes have.
#[test]
fn the_cell_and_the_arms_bodies_are_in_the_scene_for_a_reader_we_did_not_write() {
    let Ok(python) = peer_python() else {
        println!("skipping the SceneUpdate peer test: no peer (see the test above)");
        return;
    };
    let config = repo_path("config/rigbridge.toml");
    let settings = rigbridge::daemon::config::load_run_settings(&config).unwrap();
    let dir = scratch("cell-scene");
    let log = dir.join("star.mcap");
    record_run(&config, &log);
    let peer = scene_peer(&python, &log);
    let entities = &peer["entities"];
    let triangles_of =
        |shape: &rigbridge::rig::Shape| rigbridge::view::solid::shape_triangles(shape).len() as u64;
    if !settings.cell.objects.is_empty() {
        let cell = &entities["cell"];
        assert_eq!(cell["frame_id"], settings.rig.base_frame.as_str(), "{cell}");
        let expected: u64 = settings
            .cell
            .objects
            .iter()
            .map(|o| triangles_of(&o.shape))
            .sum();
        assert_eq!(cell["triangles"], expected, "{cell}");
    }
    let robot = rigbridge::log::RobotDescription::generated(&settings.rig, &settings.cell);
    let frames = robot.rig_frames();
    let mut per_frame = std::collections::BTreeMap::<usize, u64>::new();
    for body in &settings.rig.bodies {
        for c in &body.collisions {
            *per_frame.entry(body.frame).or_default() += triangles_of(&c.shape);
        }
    }
    if let Some(tool) = &settings.cell.tool {
        for c in &tool.bodies {
            *per_frame.entry(settings.rig.dof()).or_default() += triangles_of(&c.shape);
        }
    }
    assert!(!per_frame.is_empty(), "the IRB 120 has collision bodies");
    for (frame, triangles) in &per_frame {
        let entity = &entities[format!("bodies-{frame}")];
        assert_eq!(entity["frame_id"], frames[*frame].as_str(), "{entity}");
        assert_eq!(entity["triangles"], *triangles, "{entity}");
        assert!(entity["area"].as_f64().unwrap() > 0.0);
    }
    println!(
        "/scene of the star job: {} messages; entities {:?}",
        peer["messages"],
        entities
            .as_object()
            .unwrap()
            .iter()
            .map(|(id, e)| format!("{id} on {} ({} triangles)", e["frame_id"], e["triangles"]))
            .collect::<Vec<_>>()
    );
    let _ = std::fs::remove_dir_all(&dir);
}
