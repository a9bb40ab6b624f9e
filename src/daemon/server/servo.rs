//! The servo route (docs/online.md, Servo): `GET .../servo` upgraded to a WebSocket on
//! which one client at a time streams targets at its own rate, each a JSON text message
//! `{"joints_deg": [...]}` (degrees, or metres for a prismatic axis) or `{"pose": {"xyz_m":
//! [...], "quat_wxyz": [...]}}` (solved by the planner's IK nearest the last target). Owns
//! reading and checking the targets only: each is checked here (finite, within every joint
//! limit, clear of the cell by its margin, a pose reachable) and refused on the socket with
//! words naming it, never clamped; the online generator follows the targets it is given
//! (`stream/online.rs`), and brings the arm to rest when they stop.

use super::cell::{Cell, OnlineRefused};
use super::{Daemon, error, start_refusal};
use crate::ik::{FabrikSolver, IkError, IkSolver};
use crate::job::PoseSpec;
use crate::protocol::AxisValues;
use crate::rig::{OutsideLimits, Rig};
use crate::stream::OnlineCommand;
use axum::extract::State;
use axum::extract::ws::{Message, WebSocket, WebSocketUpgrade};
use axum::http::StatusCode;
use axum::response::Response;
use serde::Deserialize;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

/// Largest servo message (bytes): a target is a few hundred; more is not a target.
const MAX_SERVO_MESSAGE_BYTES: usize = 4096;

/// Servo clients connected since the daemon started: a client is named by its number in
/// the refusal a second one gets (the server does not keep peers' addresses).
static SERVO_CLIENTS: AtomicU64 = AtomicU64::new(0);

/// One servo message: a joint target or a tool pose, not both.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct ServoMessage {
    joints_deg: Option<Vec<f64>>,
    pose: Option<PoseSpec>,
}

/// Why a servo target was refused: it names the value and what it broke.
#[derive(Debug, thiserror::Error)]
enum ServoRefused {
    #[error("servo target {index}: not a target: {why} (docs/online.md, Servo)")]
    Unreadable { index: u64, why: String },
    #[error("servo target {index}: send `joints_deg` or `pose`, one of them")]
    NotOne { index: u64 },
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
struct Servo<'a> {
    cell: &'a Arc<Cell>,
    solver: Result<FabrikSolver, crate::ik::StructureError>,
    index: u64,
    last: Option<Vec<f64>>,
    session: Option<u64>,
    scratch: crate::cell::Scratch,
}

impl<'a> Servo<'a> {
    fn new(cell: &'a Arc<Cell>) -> Self {
        let settings = cell.settings();
        Servo {
            cell,
            solver: FabrikSolver::new(settings.rig.clone()),
            index: 0,
            last: None,
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
                self.last = Some(target.as_slice().to_vec());
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
                start_refusal(self.cell, refused)
            ),
        }
    }

    /// The message's target in SI units: within every limit and clear of the cell.
    fn target(&mut self, text: &str) -> Result<AxisValues, ServoRefused> {
        let index = self.index;
        let message: ServoMessage =
            serde_json::from_str(text).map_err(|e| ServoRefused::Unreadable {
                index,
                why: super::guard::shorten(&e.to_string()),
            })?;
        let rig = &self.cell.settings().rig;
        let target = match (message.joints_deg, message.pose) {
            (Some(joints), None) => within_limits(index, &joints, rig)?,
            (None, Some(pose)) => self.solve(index, pose)?,
            _ => return Err(ServoRefused::NotOne { index }),
        };
        self.clear_of_the_cell(index, &target)?;
        Ok(target)
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
