//! The servo route (`GET /api/servo`, docs/online.md) against a client we did not write
//! the WebSocket side of: PyPI's `websockets` (tests/peers/servo_client.py) streams tool
//! poses on a circle at 100 Hz, 0.2 m/s, to the daemon in this process (wall clock, the
//! in-process twin), stops, sends bad targets, tries a second client and a client while a
//! job runs. Judged here: from what the peer saw, and from the session's log (every target
//! the twin was sent: within every limit, on the circle).

use crate::common;
use crate::in_process;

use common::serve::request_json;
use rigbridge::log::read_log;
use std::process::Command;

/// The peer's circle: radius (m), speed (m/s), rate (Hz), seconds.
const RADIUS_M: f64 = 0.05;
const SPEED_M_S: f64 = 0.2;
const RATE_HZ: f64 = 100.0;
const SECONDS: f64 = 3.0;
/// How far the commanded tool may stray from the circle's line (m) once it caught up, for
/// 95 % of its targets. The follower's own bound is the virtual-clock test's
/// (tests/online.rs: within 6 mm once caught up). Over the socket, with late targets no
/// longer braked (docs/online.md, Servo): p95 4.4 to 4.5 mm over 12 runs, 4.6 to 8.8 mm
/// with a release build or clippy running beside it (but one run in eleven, below); the
/// margin is for the whole suite's load.
const OFF_THE_CIRCLE_M: f64 = 0.012;
/// The share of caught-up targets that must lie within [`OFF_THE_CIRCLE_M`].
const ON_THE_CIRCLE_SHARE: f64 = 0.95;
/// No caught-up target further from the line than this (m): at most 5.3 mm in those 12
/// runs, 11 mm loaded. Before, one run in three cut 35 to 90 mm off it, each time after a
/// late target had braked the arm for a cycle or two. Open: with clippy compiling beside
/// it, one loaded run in eleven (the cycle itself stalled 27 ms) still cut 43 mm off it
/// while catching up after starved targets.
const WORST_OFF_THE_CIRCLE_M: f64 = 0.025;
/// The share of the client's angle round the circle the tool must sweep: it starts behind
/// (the session starts while the client streams) and slows down on a late target.
const SWEPT_SHARE: f64 = 0.8;
/// The start left out of that (s), and the same after each resumption from a stall: the
/// client streams from its first message while the session starts (it waits for the
/// controller's hold), so the arm starts behind a circle already at full speed and
/// overshoots it catching up (up to 32 mm seen on a loaded machine).
const CAUGHT_UP_S: f64 = 0.5;
/// Relative slack of the limit checks: one rounding of the maths.
const SLACK: f64 = 1e-6;

/// The Python with websockets (RIGBRIDGE_FOXGLOVE_PYTHON, set by scripts/test.sh); on CI a
/// missing peer fails.
fn peer_python() -> Option<String> {
    match common::peer_python(
        "RIGBRIDGE_FOXGLOVE_PYTHON",
        "websockets.asyncio.client",
        "websockets",
    ) {
        Ok(python) => Some(python),
        Err(reason) if std::env::var("CI").as_deref() == Ok("true") => {
            panic!("CI must test the servo route against PyPI's websockets: {reason}")
        }
        Err(reason) => {
            println!("skipping the servo peer test: {reason}");
            None
        }
    }
}

/// The distance of `p` from the circle through `start` in the base's y-z plane.
/// The angle of `p` round the circle's centre, in the circle's (y, z) plane.
fn angle_on_the_circle(start: glam::DVec3, p: glam::DVec3) -> f64 {
    let d = p - (start - glam::DVec3::new(0.0, RADIUS_M, 0.0));
    d.z.atan2(d.y)
}

fn off_the_circle(start: glam::DVec3, p: glam::DVec3) -> f64 {
    let centre = start - glam::DVec3::new(0.0, RADIUS_M, 0.0);
    let d = p - centre;
    let in_plane = (d.y * d.y + d.z * d.z).sqrt();
    (d.x * d.x + (in_plane - RADIUS_M).powi(2)).sqrt()
}

#[test]
fn a_websocket_client_servos_a_circle_within_limits_and_bad_targets_move_nothing() {
    let Some(python) = peer_python() else {
        return;
    };
    let settings = common::shipped_run_settings();
    let rig = settings.rig.clone();
    let dt = settings.period().as_secs_f64();
    let start = rig.forward(&settings.initial()).unwrap();
    let q = glam::DQuat::from_mat3(&start.matrix3);
    let runs = common::scratch_dir("servo", "circle").join("runs");
    let served = in_process::start(vec![settings], in_process::options(runs.clone()));
    let address = served.address.to_string();
    let t = start.translation;
    let args: Vec<String> = [
        t.x, t.y, t.z, q.w, q.x, q.y, q.z, RADIUS_M, SPEED_M_S, RATE_HZ, SECONDS,
    ]
    .iter()
    .map(|v| v.to_string())
    .collect();
    let output = Command::new(&python)
        .arg(common::repo_path("tests/peers/servo_client.py"))
        .arg(&address)
        .args(&args)
        .output()
        .unwrap();
    assert!(
        output.status.success(),
        "the peer failed: {}",
        String::from_utf8_lossy(&output.stderr)
    );
    let seen: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    // The peer's last job is stopped; on a loaded machine it may have ended already.
    let (code, body) = request_json(&address, "POST", "/api/stop", "", "");
    assert!(
        code == 200 || (code == 409 && body.to_string().contains("no job is running")),
        "{code} {body}"
    );
    // One session, every target taken.
    assert_eq!(seen["stream_errors"], serde_json::json!([]), "{seen}");
    let sessions = seen["sessions"].as_array().unwrap();
    assert_eq!(sessions.len(), 1, "{seen}");
    let session = sessions[0].as_u64().unwrap();
    // At rest after the stream stopped: two readings 0.1 s apart agree.
    assert_eq!(seen["rest"][0], seen["rest"][1], "{seen}");
    // Each bad target is refused by name, and the arm does not move.
    let wanted = [
        "joint_3 = 80.000 deg is outside its limits",
        "not a target",
        "6 joints",
        "unreachable",
        "send `joints_deg` or `pose`, one of them",
        "sent_s = 0 is not after the target before's 2.99",
    ];
    for (bad, words) in seen["bad"].as_array().unwrap().iter().zip(wanted) {
        let replies = bad["replies"].as_array().unwrap();
        assert_eq!(replies.len(), 1, "{bad}");
        let error = replies[0]["error"].as_str().unwrap_or_default();
        assert!(error.contains(words), "{bad}: wanted `{words}`");
    }
    assert_eq!(seen["after_bad"], seen["rest"][1], "{seen}");
    // One client at a time, named; none while a planned job runs.
    assert_eq!(seen["second_client"]["status"], 409, "{seen}");
    let second = seen["second_client"]["body"].as_str().unwrap();
    assert!(second.contains("servo client") && second.contains("one servo client at a time"));
    assert_eq!(seen["during_job"]["status"], 409, "{seen}");
    let during = seen["during_job"]["body"].as_str().unwrap();
    assert!(during.contains("runs a planned motion"), "{during}");
    served.stop().unwrap().unwrap();
    // The session's log: every target within every limit, on the circle.
    let log = read_log(&runs.join(format!("job-{session}.mcap"))).unwrap();
    let commands = &log.commands;
    assert!(
        commands.len() as f64 >= SECONDS / dt,
        "{} targets",
        commands.len()
    );
    let mut worst: f64 = 0.0;
    let mut caught_up: Vec<f64> = Vec::new();
    let mut swept = 0.0;
    let mut last_angle: Option<f64> = None;
    // A stall on a loaded machine (the cycle woke over 5 cycles late) ends the part and
    // resumes from the hold, from rest: the arm starts behind the client again.
    let resumed: Vec<f64> = log
        .events
        .iter()
        .filter(|e| e.kind == "resumed")
        .map(|e| e.t)
        .collect();
    // A resumption starts again from where the controller held (it lags the target
    // before): the differences across it are not the controller's.
    let across = |from: f64, to: f64| resumed.iter().any(|r| (from..to).contains(r));
    for (k, c) in commands.iter().enumerate() {
        for (axis, joint) in rig.joints.iter().enumerate() {
            let l = joint.limits;
            let p = c.positions[axis];
            assert!(l.contains(p), "target {k}: {} at {p}", joint.name);
            assert!(c.velocities[axis].abs() <= l.max_speed * (1.0 + SLACK));
            if k >= 2 && !across(commands[k - 2].t, c.t) {
                let (b, o) = (&commands[k - 1], &commands[k - 2]);
                let step = (p - b.positions[axis]) / dt;
                let second = (p - 2.0 * b.positions[axis] + o.positions[axis]) / (dt * dt);
                assert!(
                    step.abs() <= l.max_speed * (1.0 + SLACK),
                    "target {k} steps {step}"
                );
                assert!(
                    second.abs() <= l.max_acceleration * (1.0 + SLACK),
                    "target {k}: {} second difference {second}",
                    joint.name
                );
            }
        }
        let tool = rig.forward(&c.positions).unwrap().translation;
        let off = off_the_circle(t, tool);
        worst = worst.max(off);
        let angle = angle_on_the_circle(t, tool);
        if let Some(last) = last_angle {
            // Unwrapped: a cycle turns the tool far less than half a turn.
            let turn = (angle - last + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU)
                - std::f64::consts::PI;
            swept += turn;
        }
        last_angle = Some(angle);
        let starting = std::iter::once(commands[0].t)
            .chain(resumed.iter().copied())
            .any(|from| (from..from + CAUGHT_UP_S).contains(&c.t));
        if !starting {
            caught_up.push(off);
        }
    }
    assert!(
        !caught_up.is_empty(),
        "no target after the first {CAUGHT_UP_S} s of a part"
    );
    caught_up.sort_by(f64::total_cmp);
    let share =
        |q: f64| caught_up[((caught_up.len() as f64 * q) as usize).min(caught_up.len() - 1)];
    let (median, p95) = (share(0.5), share(ON_THE_CIRCLE_SHARE));
    let worst_caught_up = caught_up.last().copied().unwrap_or(0.0);
    println!(
        "servo over the WebSocket: {} targets, {} resumptions after a stall, the tool at most \
         {:.2} mm off the circle; but for the first {CAUGHT_UP_S} s of each part median \
         {:.2} mm, p95 {:.2} mm, max {:.2} mm",
        commands.len(),
        resumed.len(),
        1e3 * worst,
        1e3 * median,
        1e3 * p95,
        1e3 * worst_caught_up
    );
    println!(
        "the client's longest gap between two sends: {} s",
        seen["max_gap_s"]
    );
    assert!(
        p95 <= OFF_THE_CIRCLE_M,
        "95 % of the caught-up targets within {p95} m of the circle, above {OFF_THE_CIRCLE_M} m"
    );
    assert!(
        worst_caught_up <= WORST_OFF_THE_CIRCLE_M,
        "a caught-up target {worst_caught_up} m off the circle, above {WORST_OFF_THE_CIRCLE_M} m"
    );
    let client_angle = SPEED_M_S * SECONDS / RADIUS_M;
    println!("the tool swept {swept:.2} rad round the circle of the client's {client_angle:.2}");
    assert!(
        swept.abs() >= SWEPT_SHARE * client_angle,
        "the tool swept {swept} rad round the circle, the client {client_angle} rad"
    );
}

#[test]
fn a_servo_client_without_the_token_or_from_another_site_is_refused() {
    use tungstenite::client::IntoClientRequest;
    let settings = common::shipped_run_settings();
    let runs = common::scratch_dir("servo", "token").join("runs");
    let options = rigbridge::server::ServeOptions {
        token: Some("sesame".into()),
        ..in_process::options(runs)
    };
    let served = in_process::start(vec![settings], options);
    let address = served.address.to_string();
    let refused = tungstenite::connect(format!("ws://{address}/api/servo"));
    match refused {
        Err(tungstenite::Error::Http(response)) => assert_eq!(response.status(), 401),
        other => panic!(
            "a servo client without the token got in: {:?}",
            other.is_ok()
        ),
    }
    // A page of another site in the operator's browser, token and all.
    let mut foreign = format!("ws://{address}/api/servo?token=sesame")
        .into_client_request()
        .unwrap();
    foreign
        .headers_mut()
        .insert("Origin", "https://attacker.example".parse().unwrap());
    match tungstenite::connect(foreign) {
        Err(tungstenite::Error::Http(response)) => assert_eq!(response.status(), 403),
        other => panic!("a page of another site got in: {:?}", other.is_ok()),
    }
    let (_, response) = tungstenite::connect(format!("ws://{address}/api/servo?token=sesame"))
        .expect("the token lets a client in");
    assert_eq!(response.status(), 101);
    served.stop().unwrap().unwrap();
}
