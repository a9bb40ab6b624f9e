//! The servo route (docs/online.md, Servo): `GET .../servo` upgraded to a WebSocket on
//! which one client at a time streams targets at its own rate, each a JSON text message
//! `{"joints_deg": [...]}` (degrees, or metres for a prismatic axis) or `{"pose": {"xyz_m":
//! [...], "quat_wxyz": [...]}}` (solved by the planner's IK nearest the last target), with
//! an optional `"sent_s"`, when the client sent it on its own clock. Owns reading and
//! checking the targets only: each is checked here (finite, within every joint limit, clear
//! of the cell by its margin, a pose reachable without a jump of its joints, sent after the
//! one before) and refused on the socket with words naming it, never clamped; the online
//! generator follows the targets it is given (`stream/online.rs`), and brings the arm to
//! rest when they stop. The same messages come over Zenoh on `<rig>/servo` when the cell
//! takes motion from ROS 2 (`[ros2] accept_motion`, its login): [`zenoh_handler`], whose
//! refusals are logged as a trajectory's are (there is no socket to answer on).

use super::cell::{Cell, OnlineRefused, ServoClaim};
use super::{Daemon, error, start_refusal};
use crate::clock::{Clock, WallClock};
use crate::ik::{FabrikSolver, IkError, IkSolver};
use crate::job::PoseSpec;
use crate::protocol::AxisValues;
use crate::rig::{OutsideLimits, Rig};
use crate::stream::{OnlineCommand, SERVO_TIMEOUT, ServoTarget};
use axum::extract::State;
use axum::extract::ws::{Message, WebSocket, WebSocketUpgrade};
use axum::http::StatusCode;
use axum::response::Response;
use serde::Deserialize;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

/// Largest servo message (bytes): a target is a few hundred; more is not a target.
const MAX_SERVO_MESSAGE_BYTES: usize = 4096;

/// The event of a servo target over Zenoh refused (or its stream: the slot taken), logged
/// rate-limited as a JointTrajectory's refusal is.
pub const ZENOH_SERVO_REFUSED: &str = "ros2_servo_refused";

/// Servo clients connected since the daemon started: a client is named by its number in
/// the refusal a second one gets (the server does not keep peers' addresses).
static SERVO_CLIENTS: AtomicU64 = AtomicU64::new(0);

/// One servo message: a joint target or a tool pose, not both.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct ServoMessage {
    joints_deg: Option<Vec<f64>>,
    pose: Option<PoseSpec>,
    /// When the client sent it (s, its own clock): the target's velocity is measured over
    /// these. Without it, the time the route read it stands in.
    sent_s: Option<f64>,
}

/// Why a servo target was refused: it names the value and what it broke.
#[derive(Debug, thiserror::Error)]
enum ServoRefused {
    #[error("servo target {index}: not a target: {why} (docs/online.md, Servo)")]
    Unreadable { index: u64, why: String },
    #[error("servo target {index}: send `joints_deg` or `pose`, one of them")]
    NotOne { index: u64 },
    #[error(
        "servo target {index}: sent_s = {sent_s} is not after the target before's {before} \
         (the client's clock must go forward)"
    )]
    NotAfter {
        index: u64,
        sent_s: f64,
        before: f64,
    },
    #[error(
        "servo target {index}: pose {pose} solves to {joint} = {to:.3} {unit} from {from:.3} \
         {unit} (the last target), a jump of {jump:.3} {unit} beyond the {bound:.3} {unit} the \
         arm can move in {timeout_s} s at its speed limit: the IK changed branch; send poses \
         closer together"
    )]
    Jump {
        index: u64,
        pose: Box<PoseSpec>,
        joint: String,
        from: f64,
        to: f64,
        jump: f64,
        bound: f64,
        unit: &'static str,
        timeout_s: f64,
    },
    #[error("servo target {index}: {given} joint values given, the rig {rig} has {dof} joints")]
    Count {
        index: u64,
        given: usize,
        rig: String,
        dof: usize,
    },
    #[error("servo target {index}: {source}")]
    Outside { index: u64, source: OutsideLimits },
    #[error("servo target {index}: pose {pose}: {source}")]
    BadPose {
        index: u64,
        // Boxed: a refusal is rare, and the common `Ok` stays small.
        pose: Box<PoseSpec>,
        source: Box<crate::job::JobInvalid>,
    },
    #[error("servo target {index}: pose {pose} is unreachable: {source}")]
    Unreachable {
        index: u64,
        pose: Box<PoseSpec>,
        source: Box<IkError>,
    },
    #[error("servo target {index}: the rig {rig} has no pose solver: {why}")]
    NoSolver {
        index: u64,
        rig: String,
        why: String,
    },
    #[error(
        "servo target {index}: a pose needs the arm's position to solve from, and it is not \
         known yet: send a joint target first"
    )]
    NoSeed { index: u64 },
    #[error(
        "servo target {index}: [{joints}] brings {a} within {distance_m:.4} m of {b}, inside \
         the cell's margin {margin_m:.4} m"
    )]
    InCollision {
        index: u64,
        joints: String,
        a: String,
        b: String,
        distance_m: f64,
        margin_m: f64,
    },
}

/// `GET .../servo`: a WebSocket for one servo client (see the module doc). A second client
/// is refused with 409 naming the first, and so is a client while a planned job runs.
pub async fn servo(
    State(daemon): State<Arc<Daemon>>,
    super::CellRef(cell): super::CellRef,
    upgrade: WebSocketUpgrade,
) -> Response {
    if let Some(id) = cell.planned_job() {
        return error(
            StatusCode::CONFLICT,
            format!(
                "job {id} runs a planned motion in cell `{}`: stop it before servoing",
                cell.name()
            ),
        );
    }
    let number = SERVO_CLIENTS.fetch_add(1, Ordering::SeqCst) + 1;
    let client = format!("servo client {number}");
    let claim = match cell.claim_servo(&client) {
        Ok(claim) => claim,
        Err(taken) => return error(StatusCode::CONFLICT, taken.to_string()),
    };
    upgrade
        .max_message_size(MAX_SERVO_MESSAGE_BYTES)
        .max_frame_size(MAX_SERVO_MESSAGE_BYTES)
        .on_upgrade(move |socket| async move {
            serve_servo(socket, &daemon, &cell).await;
            drop(claim);
        })
}

/// The client's targets until it goes or the server stops. Replies: `{"session": id}`
/// when a target starts (or joins) a session, `{"error": words}` for a refused one.
async fn serve_servo(mut socket: WebSocket, daemon: &Arc<Daemon>, cell: &Arc<Cell>) {
    let mut stopping = daemon.stopping.clone();
    let mut servo = Servo::new(cell);
    loop {
        let text = tokio::select! {
            incoming = socket.recv() => match incoming {
                Some(Ok(Message::Text(text))) => text,
                Some(Ok(Message::Binary(_))) => {
                    let refused = serde_json::json!({
                        "error": "servo: a binary message is not a target: send JSON text"
                    });
                    if socket.send(Message::Text(refused.to_string().into())).await.is_err() {
                        return;
                    }
                    continue;
                }
                Some(Ok(Message::Ping(_) | Message::Pong(_))) => continue,
                None | Some(Err(_)) | Some(Ok(Message::Close(_))) => return,
            },
            _ = stopping.changed() => {
                let _ = socket.send(Message::Close(None)).await;
                return;
            }
        };
        let reply = servo.take(daemon, text.as_str());
        if let Some(reply) = reply
            && socket
                .send(Message::Text(reply.to_string().into()))
                .await
                .is_err()
        {
            return;
        }
    }
}

/// One client's stream: its count, its last target (a pose's IK seed) and its session.
struct Servo {
    cell: Arc<Cell>,
    solver: Result<FabrikSolver, crate::ik::StructureError>,
    index: u64,
    last: Option<Vec<f64>>,
    /// When the last target taken was sent (the client's clock, or the route's).
    last_sent: Option<f64>,
    /// The route's clock: a target's time when the client gives none.
    clock: WallClock,
    session: Option<u64>,
    scratch: crate::cell::Scratch,
}

impl Servo {
    fn new(cell: &Arc<Cell>) -> Self {
        let settings = cell.settings();
        Servo {
            cell: cell.clone(),
            solver: FabrikSolver::new(settings.rig.clone()),
            index: 0,
            last: None,
            last_sent: None,
            clock: WallClock::new(),
            session: None,
            scratch: settings.collision.scratch(),
        }
    }

    /// Checks and gives one message's target; the reply, if there is one.
    fn take(&mut self, daemon: &Arc<Daemon>, text: &str) -> Option<serde_json::Value> {
        self.index += 1;
        let target = match self.target(text) {
            Ok(target) => target,
            Err(refused) => return Some(serde_json::json!({ "error": refused.to_string() })),
        };
        let first = self.session.is_none();
        let log = first.then_some("servo");
        let given = self.cell.online(
            Some(OnlineCommand::Servo(target)),
            log,
            || daemon.next_job_id(),
            &daemon.options,
        );
        match given {
            Ok(id) => {
                self.last = Some(target.joints.as_slice().to_vec());
                self.last_sent = Some(target.sent_s);
                (self.session.replace(id) != Some(id)).then(|| serde_json::json!({ "session": id }))
            }
            Err(refused) => Some(serde_json::json!({ "error": self.refusal(refused) })),
        }
    }

    fn refusal(&self, refused: OnlineRefused) -> String {
        let name = self.cell.name();
        match refused {
            OnlineRefused::JobRunning(id) => format!(
                "servo target {}: job {id} runs a planned motion in cell `{name}`: stop it \
                 before servoing",
                self.index
            ),
            OnlineRefused::NoSession => format!("servo target {}: no session", self.index),
            OnlineRefused::Start(refused) => format!(
                "servo target {}: {}",
                self.index,
                start_refusal(&self.cell, refused)
            ),
        }
    }

    /// The message's target in SI units, within every limit and clear of the cell, and
    /// when it was sent.
    fn target(&mut self, text: &str) -> Result<ServoTarget, ServoRefused> {
        let index = self.index;
        let message: ServoMessage =
            serde_json::from_str(text).map_err(|e| ServoRefused::Unreadable {
                index,
                why: super::guard::shorten(&e.to_string()),
            })?;
        let sent_s = self.sent(index, message.sent_s)?;
        let rig = &self.cell.settings().rig;
        let joints = match (message.joints_deg, message.pose) {
            (Some(joints), None) => within_limits(index, &joints, rig)?,
            (None, Some(pose)) => self.solve(index, pose)?,
            _ => return Err(ServoRefused::NotOne { index }),
        };
        self.clear_of_the_cell(index, &joints)?;
        Ok(ServoTarget { joints, sent_s })
    }

    /// When the target was sent: the client's time, after the last target's (a value that
    /// is not finite is after nothing), or the route's clock now.
    fn sent(&self, index: u64, given: Option<f64>) -> Result<f64, ServoRefused> {
        let Some(sent_s) = given else {
            return Ok(self.clock.now().as_secs_f64());
        };
        let before = self.last_sent.unwrap_or(f64::NEG_INFINITY);
        // Not finite: after nothing (NaN compares false, so the check is spelled out).
        if !sent_s.is_finite() || sent_s <= before {
            return Err(ServoRefused::NotAfter {
                index,
                sent_s,
                before,
            });
        }
        Ok(sent_s)
    }

    /// The joints placing the tool at `pose`, nearest the last target (else the arm).
    fn solve(&self, index: u64, pose: PoseSpec) -> Result<AxisValues, ServoRefused> {
        let rig = &self.cell.settings().rig;
        let target = pose
            .to_pose("pose")
            .map_err(|source| ServoRefused::BadPose {
                index,
                pose: Box::new(pose),
                source: Box::new(source),
            })?;
        let solver = self.solver.as_ref().map_err(|why| ServoRefused::NoSolver {
            index,
            rig: rig.name.clone(),
            why: why.to_string(),
        })?;
        let seed = self
            .last
            .clone()
            .or_else(|| self.cell.current_position())
            .ok_or(ServoRefused::NoSeed { index })?;
        let solution =
            solver
                .solve(&target, &seed)
                .map_err(|source| ServoRefused::Unreachable {
                    index,
                    pose: Box::new(pose),
                    source: Box::new(source),
                })?;
        if self.last.is_some() {
            no_jump(index, rig, &pose, &seed, &solution.joints)?;
        }
        let mut joints = AxisValues::zeros(rig.dof());
        joints.as_mut_slice().copy_from_slice(&solution.joints);
        Ok(joints)
    }

    /// Refuses a target inside the cell's margin (the cycle checks every step to it too).
    fn clear_of_the_cell(&mut self, index: u64, target: &AxisValues) -> Result<(), ServoRefused> {
        let settings = self.cell.settings();
        let model = &settings.collision;
        let at = target.as_slice();
        let Err(clearance) = model.check_step(at, at, &mut self.scratch) else {
            return Ok(());
        };
        Err(ServoRefused::InCollision {
            index,
            joints: shown(&settings.rig, at),
            a: model.body_name(clearance.a).to_string(),
            b: model.body_name(clearance.b).to_string(),
            distance_m: clearance.distance_m,
            margin_m: model.margin(),
        })
    }
}

/// The servo messages of one cell over Zenoh (`<rig>/servo`, see the module doc): a
/// stream holds the cell's servo slot from its first message until the node's
/// poll finds none for a while (longer than [`SERVO_TIMEOUT`], so the arm is at rest by then);
/// a WebSocket client holding the slot refuses it, and it refuses one.
pub fn zenoh_handler(daemon: Arc<Daemon>, cell: Arc<Cell>) -> crate::ros2::ServoHandler {
    let mut refusals = crate::server::ros2::Refusals::new(Box::new(WallClock::new()));
    let key = crate::ros2::servo_key(cell.name());
    let mut stream: Option<(Servo, ServoClaim)> = None;
    Box::new(move |payload| {
        let Some(payload) = payload else {
            // No message for the node's poll: the stream is over; the slot is free.
            stream = None;
            return;
        };
        let refused = match zenoh_target(&daemon, &cell, &key, &mut stream, payload) {
            Ok(()) => return,
            Err(refused) => refused,
        };
        if let Some(text) = refusals.refuse(&refused.to_string()) {
            cell.log_ros2(ZENOH_SERVO_REFUSED, None, text);
        }
    })
}

/// Why a Zenoh servo message was not followed.
#[derive(Debug, thiserror::Error)]
enum ZenohServoRefused {
    /// Another stream holds the cell's servo slot.
    #[error("servo over Zenoh on {key}: {why}")]
    Taken { key: String, why: String },
    #[error("servo over Zenoh on {key}: a payload that is not UTF-8 text")]
    NotText { key: String },
    /// The target's own refusal, as the WebSocket route words it.
    #[error("servo over Zenoh on {key}: {why}")]
    Target { key: String, why: String },
}

/// One Zenoh servo message, given to the stream (started if there is none): why it was
/// refused, if it was.
fn zenoh_target(
    daemon: &Arc<Daemon>,
    cell: &Arc<Cell>,
    key: &str,
    stream: &mut Option<(Servo, ServoClaim)>,
    payload: &[u8],
) -> Result<(), ZenohServoRefused> {
    if stream.is_none() {
        let claim = cell
            .claim_servo(&format!("the Zenoh servo stream on {key}"))
            .map_err(|taken| ZenohServoRefused::Taken {
                key: key.to_owned(),
                why: taken.to_string(),
            })?;
        *stream = Some((Servo::new(cell), claim));
    }
    let Some((servo, _)) = stream.as_mut() else {
        return Ok(());
    };
    let text = std::str::from_utf8(payload).map_err(|_| ZenohServoRefused::NotText {
        key: key.to_owned(),
    })?;
    match servo.take(daemon, text) {
        Some(reply) => match reply.get("error").and_then(|e| e.as_str()) {
            Some(error) => Err(ZenohServoRefused::Target {
                key: key.to_owned(),
                why: error.to_owned(),
            }),
            None => Ok(()),
        },
        None => Ok(()),
    }
}

/// A pose's solution `to`, from the last target `from`: refused when an axis jumps further than its speed limit covers in [`SERVO_TIMEOUT`], the
/// longest a stream's targets may be apart. The circle of tests/servo.rs moves an axis at
/// most a few degrees between targets; a jump beyond that bound is the IK's other branch
/// (the wrist flipped), and following it would swing the tool off the client's path.
fn no_jump(
    index: u64,
    rig: &Rig,
    pose: &PoseSpec,
    from: &[f64],
    to: &[f64],
) -> Result<(), ServoRefused> {
    let timeout_s = SERVO_TIMEOUT.as_secs_f64();
    for (joint, (a, b)) in rig.joints.iter().zip(from.iter().zip(to)) {
        let bound = joint.limits.max_speed * timeout_s;
        if (b - a).abs() > bound {
            let user = |v: f64| joint.kind.to_user(v);
            return Err(ServoRefused::Jump {
                index,
                pose: Box::new(*pose),
                joint: joint.name.clone(),
                from: user(*a),
                to: user(*b),
                jump: user((b - a).abs()),
                bound: user(bound),
                unit: joint.kind.unit(),
                timeout_s,
            });
        }
    }
    Ok(())
}

/// Joint values in the user's units: `10.000, -20.000, ...`.
fn shown(rig: &Rig, values: &[f64]) -> String {
    let shown: Vec<String> = rig
        .joints
        .iter()
        .zip(values)
        .map(|(joint, q)| format!("{:.3}", joint.kind.to_user(*q)))
        .collect();
    shown.join(", ")
}

/// The joint target in SI units, each joint within its limits; the first that is not,
/// named (a value that is not finite is outside every limit).
fn within_limits(index: u64, joints: &[f64], rig: &Rig) -> Result<AxisValues, ServoRefused> {
    if joints.len() != rig.dof() {
        return Err(ServoRefused::Count {
            index,
            given: joints.len(),
            rig: rig.name.clone(),
            dof: rig.dof(),
        });
    }
    let mut target = AxisValues::zeros(rig.dof());
    for ((joint, value), out) in rig.joints.iter().zip(joints).zip(target.as_mut_slice()) {
        let si = joint.kind.from_user(*value);
        joint
            .check_limits(si)
            .map_err(|source| ServoRefused::Outside { index, source })?;
        *out = si;
    }
    Ok(target)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rig::load_rig;
    use std::path::Path;

    fn irb120() -> Rig {
        load_rig(&Path::new(env!("CARGO_MANIFEST_DIR")).join("config/irb120.toml"))
            .expect("the shipped rig loads")
    }

    fn pose() -> PoseSpec {
        serde_json::from_str(r#"{"xyz_m": [0.3, 0.0, 0.5], "quat_wxyz": [1.0, 0.0, 0.0, 0.0]}"#)
            .expect("a pose")
    }

    #[test]
    fn a_pose_whose_solution_jumps_further_than_the_arm_moves_in_the_timeout_is_refused() {
        let rig = irb120();
        let from = [0.0, 0.0, 0.0, 0.0, 30f64.to_radians(), 0.0];
        // joint_4 at 320 deg/s (config/irb120.toml) covers 32 deg in the 100 ms timeout:
        // 31 deg passes, 33 deg (a wrist flip's first step is far more) is refused.
        let mut near = from;
        near[3] = 31f64.to_radians();
        assert!(no_jump(7, &rig, &pose(), &from, &near).is_ok());
        let mut flipped = from;
        flipped[3] = 33f64.to_radians();
        let refused = no_jump(7, &rig, &pose(), &from, &flipped)
            .expect_err("a jump past the bound")
            .to_string();
        assert!(
            refused.contains("servo target 7")
                && refused.contains("joint_4 = 33.000 deg from 0.000 deg")
                && refused.contains("a jump of 33.000 deg beyond the 32.000 deg")
                && refused.contains("0.1 s"),
            "{refused}"
        );
    }
}
