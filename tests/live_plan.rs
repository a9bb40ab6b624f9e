//! The live page's plan and pasted jobs (issue 32, item 5), over `rigbridge serve`'s own
//! channels: a job of any kind, posted over HTTP, sends its tool path and targets in the
//! scene message of `/api/live` (the page's data channel), derived from the planned
//! trajectory; a job pasted as TOML text starts and runs; a bad one comes back with the
//! validation text, naming key and value (or the line and column of the TOML). Waits are
//! on the API's own `?wait_s=` and on the WebSocket, never on sleeps. Traffic only ever
//! goes to 127.0.0.1.

use crate::common;

use common::serve::{Served, request_json, serve_command, start_serve};
use serde_json::Value;
use std::net::TcpStream;
use std::process::Stdio;
use std::time::{Duration, Instant};

type LiveSocket = tungstenite::WebSocket<tungstenite::stream::MaybeTlsStream<TcpStream>>;

/// Far beyond any message's gap: only to fail rather than hang.
const WITHIN: Duration = Duration::from_secs(60);
/// Where the pen's tip (the TCP) may be off a pose it was asked for: the IK's tolerance is
/// far finer; this leaves room for the printed decimals of the poses only.
const AT_POSE_M: f64 = 1e-3;
/// The pen of `config/cell-star.toml`: its TCP 0.1 m out of the flange, on tool0's z.
const PEN_M: f64 = 0.1;
/// The IRB 120 at its zero position (ABB, IRB 120 product specification, dimensions):
/// tool0 is 302 + 72 = 374 mm in front of axis 1 and 290 + 270 + 70 = 630 mm above the
/// base, its z axis pointing forward (along the base's x).
const TOOL0_AT_ZERO_M: [f64; 3] = [0.374, 0.0, 0.630];

/// A daemon with the shipped cell, its logs in a directory of its own (`test`).
fn start(test: &str) -> Served {
    let runs =
        std::env::temp_dir().join(format!("rigbridge-live-plan-{test}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&runs);
    std::fs::create_dir_all(&runs).unwrap();
    start_serve(serve_command(&runs).stderr(Stdio::null()))
}

fn open_live(server: &Served) -> LiveSocket {
    let (socket, _) = tungstenite::connect(format!("ws://{}/api/live", server.address)).unwrap();
    if let tungstenite::stream::MaybeTlsStream::Plain(stream) = socket.get_ref() {
        stream.set_read_timeout(Some(WITHIN)).unwrap();
    }
    socket
}

/// The next scene message on `socket` (frames skipped).
fn next_scene(socket: &mut LiveSocket) -> Value {
    let deadline = Instant::now() + WITHIN;
    loop {
        assert!(Instant::now() < deadline, "no scene message");
        if let tungstenite::Message::Text(text) = socket.read().unwrap() {
            let message: Value = serde_json::from_str(&text).unwrap();
            if message["type"] == "scene" {
                return message;
            }
        }
    }
}

fn post_job(server: &Served, body: &str) -> (u16, Value) {
    request_json(&server.address, "POST", "/api/jobs", "", body)
}

/// Waits for job `id` to end (the API holds the answer until it does, up to its 30 s
/// most); its report.
fn ended(server: &Served, id: u64) -> Value {
    let path = format!("/api/jobs/{id}?wait_s=30");
    let (code, entry) = request_json(&server.address, "GET", &path, "", "");
    assert_eq!(code, 200, "{entry}");
    assert_eq!(
        entry["result"], "finished",
        "not finished after 30 s: {entry}"
    );
    entry["report"].clone()
}

fn point(value: &Value) -> [f64; 3] {
    let v: Vec<f64> = serde_json::from_value(value.clone()).unwrap();
    [v[0], v[1], v[2]]
}

fn distance(a: [f64; 3], b: [f64; 3]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y) * (x - y))
        .sum::<f64>()
        .sqrt()
}

/// A drawn target: where, and the job's words for it.
type Target = ([f64; 3], String);

/// The plan of a scene message: its tool path and targets.
fn plan_of(scene: &Value) -> (Vec<[f64; 3]>, Vec<Target>) {
    let plan = &scene["plan"];
    assert!(plan.is_object(), "the scene has no plan: {plan}");
    let path = plan["tool_path"]
        .as_array()
        .unwrap()
        .iter()
        .map(point)
        .collect();
    let targets = plan["targets"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| (point(&t["at"]), t["what"].as_str().unwrap().to_string()))
        .collect();
    (path, targets)
}

/// The largest step between two drawn points: the path is one continuous line.
fn largest_step(path: &[[f64; 3]]) -> f64 {
    path.windows(2)
        .map(|w| distance(w[0], w[1]))
        .fold(0.0, f64::max)
}

#[test]
fn jobs_posted_over_http_show_their_tool_path_and_targets_whatever_their_kind() {
    let server = start("kinds");
    let mut live = open_live(&server);
    let before = next_scene(&mut live);
    assert!(
        before["plan"].is_null(),
        "no job planned yet: {}",
        before["plan"]
    );

    // move_poses: never drawn by its kind before; its targets are the poses as written.
    let poses = [[0.40, -0.10, 0.45], [0.35, 0.15, 0.50]];
    let body = r#"{"job": {"kind": "move_poses", "poses": [
        {"xyz_m": [0.40, -0.10, 0.45], "quat_wxyz": [0.7071, 0.0, 0.7071, 0.0]},
        {"xyz_m": [0.35, 0.15, 0.50], "quat_wxyz": [0.7071, 0.0, 0.7071, 0.0]}]}}"#;
    let (code, started) = post_job(&server, body);
    assert_eq!(code, 202, "{started}");
    let (path, targets) = plan_of(&next_scene(&mut live));
    assert!(path.len() > 10, "{} points", path.len());
    assert!(
        path.len() <= rigbridge::view::MAX_PATH_POINTS + targets.len() + 1,
        "{}",
        path.len()
    );
    let step = largest_step(&path);
    assert!(step < 0.02, "a gap of {step} m in the drawn path");
    let at_end = distance(*path.last().unwrap(), poses[1]);
    assert!(at_end < AT_POSE_M, "the path ends {at_end} m from pose 1");
    assert_eq!(targets.len(), 2, "{targets:?}");
    for (k, ((at, what), pose)) in targets.iter().zip(poses).enumerate() {
        assert!(distance(*at, pose) < AT_POSE_M, "target {k} at {at:?}");
        assert_eq!(what, &format!("the joint move to job.poses[{k}]"));
    }
    println!(
        "move_poses: {} path points, largest step {:.1} mm, end {:.3} mm from pose 1",
        path.len(),
        step * 1e3,
        at_end * 1e3
    );
    assert_eq!(
        ended(&server, started["id"].as_u64().unwrap())["outcome"],
        "completed"
    );

    // follow_trajectory with inline rows: the kind a ROS 2 JointTrajectory becomes. It ends
    // with axis 1 at +90 deg and the rest at zero: tool0's zero position turned a quarter
    // about z, the pen forward of it along y.
    let body = r#"{"job": {"kind": "follow_trajectory", "rows": [
        [0.0, 0, 0, 0, 0, 30, 0], [2.0, 45, 0, 0, 0, 15, 0], [4.0, 90, 0, 0, 0, 0, 0]]}}"#;
    let (code, started) = post_job(&server, body);
    assert_eq!(code, 202, "{started}");
    let (path, targets) = plan_of(&next_scene(&mut live));
    let [x, _, z] = TOOL0_AT_ZERO_M;
    let expected_end = [0.0, x + PEN_M, z];
    let at_end = distance(*path.last().unwrap(), expected_end);
    assert!(
        at_end < AT_POSE_M,
        "the path ends at {:?}, {at_end} m from {expected_end:?}",
        path.last()
    );
    let step = largest_step(&path);
    assert!(step < 0.02, "a gap of {step} m in the drawn path");
    assert!(targets.len() >= 3, "the approach and the rows: {targets:?}");
    let (last_at, last_what) = targets.last().unwrap();
    assert!(distance(*last_at, expected_end) < AT_POSE_M, "{last_at:?}");
    assert!(last_what.contains("row"), "{last_what}");
    println!(
        "follow_trajectory: {} path points, {} targets, end {:.3} mm from the IRB 120's \
         zero pose turned 90 deg",
        path.len(),
        targets.len(),
        at_end * 1e3
    );
    assert_eq!(
        ended(&server, started["id"].as_u64().unwrap())["outcome"],
        "completed"
    );
}

#[test]
fn a_job_pasted_as_toml_starts_and_runs_and_a_bad_one_comes_back_with_why() {
    let server = start("pasted");
    let mut live = open_live(&server);
    next_scene(&mut live);
    let pasted = serde_json::json!({
        "toml": "[job]\nkind = \"move_joints\"\ntargets_deg = [[10, 5, 0, 0, 30, 0]]\n"
    });
    let (code, started) = post_job(&server, &pasted.to_string());
    assert_eq!(code, 202, "{started}");
    assert_eq!(started["job"], "move_joints");
    let (path, targets) = plan_of(&next_scene(&mut live));
    assert!(!path.is_empty());
    assert_eq!(targets.len(), 1, "{targets:?}");
    let entry = ended(&server, started["id"].as_u64().unwrap());
    assert_eq!(entry["outcome"], "completed", "{entry}");

    // The job's keys alone, without the [job] header, read the same.
    let keys = serde_json::json!({
        "toml": "kind = \"move_joints\"\ntargets_deg = [[0, 0, 0, 0, 30, 0]]\n"
    });
    let (code, started) = post_job(&server, &keys.to_string());
    assert_eq!(code, 202, "{started}");
    assert_eq!(
        ended(&server, started["id"].as_u64().unwrap())["outcome"],
        "completed"
    );

    // Refused by the job's validation, as a config file's [job] would be.
    let out_of_range = serde_json::json!({
        "toml": "[job]\nkind = \"move_joints\"\ntargets_deg = [[0, 130, 0, 0, 30, 0]]\n"
    });
    let (code, refused) = post_job(&server, &out_of_range.to_string());
    assert_eq!(code, 422, "{refused}");
    let text = refused["error"].as_str().unwrap();
    println!("refused: {text}");
    assert!(
        text.starts_with("key `job.targets_deg[0][1]` = 130"),
        "names the key and the value: {text}"
    );
    assert!(text.contains("joint_2"), "{text}");

    // Not a job at all: the TOML's own line and column.
    let unknown = serde_json::json!({ "toml": "[job]\nkind = \"dance\"\n" });
    let (code, refused) = post_job(&server, &unknown.to_string());
    assert_eq!(code, 400, "{refused}");
    let text = refused["error"].as_str().unwrap();
    println!("refused: {text}");
    assert!(
        text.starts_with(
            "job request is not valid: pasted TOML, line 2, column 8: unknown variant `dance`"
        ),
        "{text}"
    );
    let both = serde_json::json!({
        "toml": "kind = \"move_joints\"",
        "job": {"kind": "move_joints", "targets_deg": [[0, 0, 0, 0, 30, 0]]}
    });
    let (code, refused) = post_job(&server, &both.to_string());
    assert_eq!(code, 400, "{refused}");
    assert!(
        refused["error"]
            .as_str()
            .unwrap()
            .starts_with("job request is not valid: both `job` and `toml` given: send one"),
        "{refused}"
    );
}
