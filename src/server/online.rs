//! The online routes (docs/online.md): `POST .../speed` (the override), `POST .../jog` (a
//! joint or a Cartesian jog, its keep-alives and its release) and `POST .../goal` (a new
//! goal for the running motion, or a move from rest). Owns reading and checking the bodies
//! only: every value is checked here (a joint's goal within its limits, a direction that is
//! not zero) and refused with words naming it, never clamped; the cell acts and logs.

use super::cell::{Cell, OnlineRefused};
use super::{Daemon, error, guard, start_refused};
use crate::protocol::AxisValues;
use crate::rig::Rig;
use crate::stream::{Frame, Jog, OnlineCommand};
use axum::Json;
use axum::extract::{Request, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use serde::Deserialize;
use std::sync::Arc;

/// `POST .../speed`'s body.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct SpeedRequest {
    percent: f64,
}

/// `POST .../jog`'s body: one of a joint (`joint` by name or `axis` from 1) with a
/// `direction` of +1 or -1, a `frame` with a `direction` [x, y, z], `keep_alive` or
/// `release`.
#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct JogRequest {
    joint: Option<String>,
    axis: Option<usize>,
    frame: Option<Frame>,
    direction: Option<serde_json::Value>,
    #[serde(default)]
    keep_alive: bool,
    #[serde(default)]
    release: bool,
}

/// `POST .../goal`'s body: a position per joint, in the joint's unit (deg or m).
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct GoalRequest {
    joints: Vec<f64>,
}

async fn body<T: for<'de> Deserialize<'de>>(request: Request, what: &str) -> Result<T, Response> {
    let bytes = guard::read_body(request).await?;
    serde_json::from_slice(&bytes).map_err(|e| {
        error(
            StatusCode::BAD_REQUEST,
            format!(
                "{what} request is not valid: {} (docs/online.md)",
                guard::shorten(&e.to_string())
            ),
        )
    })
}

/// `POST .../speed {"percent": P}`: the override of every motion of the cell, 0..=100.
pub async fn speed(super::CellRef(cell): super::CellRef, request: Request) -> Response {
    let request: SpeedRequest = match body(request, "speed").await {
        Ok(request) => request,
        Err(refused) => return refused,
    };
    let fraction = request.percent / 100.0;
    if !request.percent.is_finite() || !cell.set_speed(fraction) {
        return error(
            StatusCode::UNPROCESSABLE_ENTITY,
            format!("speed override {} % is outside 0..=100 %", request.percent),
        );
    }
    Json(serde_json::json!({ "percent": request.percent })).into_response()
}

/// `POST .../jog`: starts or changes a jog (a session when none runs), keeps it alive, or
/// releases it.
pub async fn jog(
    State(daemon): State<Arc<Daemon>>,
    super::CellRef(cell): super::CellRef,
    request: Request,
) -> Response {
    let request: JogRequest = match body(request, "jog").await {
        Ok(request) => request,
        Err(refused) => return refused,
    };
    let command = match jog_command(&request, &cell.settings().rig) {
        Ok(command) => command,
        Err(why) => return error(StatusCode::UNPROCESSABLE_ENTITY, why),
    };
    let log = command.map(|_| "jog");
    act(&daemon, &cell, command, log)
}

/// `POST .../goal`: a new goal for the running motion (it blends from where the arm is),
/// or a move from rest when nothing runs.
pub async fn goal(
    State(daemon): State<Arc<Daemon>>,
    super::CellRef(cell): super::CellRef,
    request: Request,
) -> Response {
    let request: GoalRequest = match body(request, "goal").await {
        Ok(request) => request,
        Err(refused) => return refused,
    };
    let goal = match goal_within_limits(&request.joints, &cell.settings().rig) {
        Ok(goal) => goal,
        Err(why) => return error(StatusCode::UNPROCESSABLE_ENTITY, why.to_string()),
    };
    act(
        &daemon,
        &cell,
        Some(OnlineCommand::Goal(goal)),
        Some("goal"),
    )
}

fn act(
    daemon: &Arc<Daemon>,
    cell: &Arc<Cell>,
    command: Option<OnlineCommand>,
    log: Option<&'static str>,
) -> Response {
    match cell.online(command, log, || daemon.next_job_id(), &daemon.options) {
        Ok(id) => Json(serde_json::json!({ "id": id })).into_response(),
        Err(OnlineRefused::JobRunning(id)) => error(
            StatusCode::CONFLICT,
            format!(
                "job {id} runs a planned motion in cell `{}`: stop it before jogging \
                 (a new goal blends into it: POST .../goal)",
                cell.name()
            ),
        ),
        Err(OnlineRefused::NoSession) => error(
            StatusCode::CONFLICT,
            format!("no jog runs in cell `{}`: start one first", cell.name()),
        ),
        Err(OnlineRefused::Start(refused)) => start_refused(cell, refused),
    }
}

/// Why a jog body is refused: it names the joint, axis or direction it could not take.
#[derive(Debug, thiserror::Error)]
enum JogRefused {
    #[error("jog: the rig {rig} has no joint `{joint}`")]
    NoSuchJoint { rig: String, joint: String },
    #[error("jog: axis {axis} is not one of the rig's axes 1..={dof}")]
    NoSuchAxis { axis: usize, dof: usize },
    #[error("jog: give `joint` or `axis`, not both")]
    JointAndAxis,
    #[error("jog: a joint's direction is 1 or -1")]
    JointDirection,
    #[error("jog: a Cartesian direction is [x, y, z]")]
    CartesianDirection,
    #[error("jog: the direction [0, 0, 0] points nowhere")]
    ZeroDirection,
    #[error(
        "jog: send a joint (or axis) and a direction, a frame and a direction, keep_alive or \
         release"
    )]
    Incomplete,
}

/// The command a jog body asks for; `None` for a keep-alive.
fn jog_command(request: &JogRequest, rig: &Rig) -> Result<Option<OnlineCommand>, JogRefused> {
    if request.release {
        return Ok(Some(OnlineCommand::Release));
    }
    let axis = match (&request.joint, request.axis) {
        (Some(name), None) => Some(rig.joints.iter().position(|j| &j.name == name).ok_or_else(
            || JogRefused::NoSuchJoint {
                rig: rig.name.clone(),
                joint: name.clone(),
            },
        )?),
        (None, Some(axis)) if (1..=rig.dof()).contains(&axis) => Some(axis - 1),
        (None, Some(axis)) => {
            return Err(JogRefused::NoSuchAxis {
                axis,
                dof: rig.dof(),
            });
        }
        (Some(_), Some(_)) => return Err(JogRefused::JointAndAxis),
        (None, None) => None,
    };
    match (axis, request.frame, &request.direction) {
        (Some(axis), None, Some(direction)) => {
            let direction = direction.as_f64().filter(|d| *d == 1.0 || *d == -1.0);
            let direction = direction.ok_or(JogRefused::JointDirection)?;
            Ok(Some(OnlineCommand::Jog(Jog::Joint { axis, direction })))
        }
        (None, Some(frame), Some(direction)) => {
            let xyz: Option<Vec<f64>> = direction
                .as_array()
                .map(|values| values.iter().filter_map(|v| v.as_f64()).collect());
            let xyz = xyz
                .filter(|v| v.len() == 3 && v.iter().all(|c| c.is_finite()))
                .ok_or(JogRefused::CartesianDirection)?;
            let direction = glam::DVec3::new(xyz[0], xyz[1], xyz[2]);
            let unit = direction.try_normalize().ok_or(JogRefused::ZeroDirection)?;
            Ok(Some(OnlineCommand::Jog(Jog::Cartesian {
                frame,
                direction: unit,
            })))
        }
        (None, None, None) if request.keep_alive => Ok(None),
        _ => Err(JogRefused::Incomplete),
    }
}

/// Why a goal is refused: it names the joint, the value and the limits in the user's unit.
#[derive(Debug, thiserror::Error)]
enum GoalRefused {
    #[error("goal: {given} values given, the rig {rig} has {dof} joints")]
    Count {
        given: usize,
        rig: String,
        dof: usize,
    },
    #[error("goal: {0}")]
    Outside(crate::rig::OutsideLimits),
}

/// The goal in SI units, each joint within its limits; the first that is not, named.
fn goal_within_limits(joints: &[f64], rig: &Rig) -> Result<AxisValues, GoalRefused> {
    if joints.len() != rig.dof() {
        return Err(GoalRefused::Count {
            given: joints.len(),
            rig: rig.name.clone(),
            dof: rig.dof(),
        });
    }
    let mut goal = AxisValues::zeros(rig.dof());
    for ((joint, value), out) in rig.joints.iter().zip(joints).zip(goal.as_mut_slice()) {
        // A value that is not finite is outside every limit too.
        let si = joint.kind.from_user(*value);
        joint.check_limits(si).map_err(GoalRefused::Outside)?;
        *out = si;
    }
    Ok(goal)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_goal_outside_a_limit_names_the_value_and_the_limits_in_degrees() {
        let rig = crate::rig::load_rig(&crate::rig::shipped::path("irb120.toml")).unwrap();
        // joint_3 of the IRB 120 is +70 / -110 deg (ABB's product manual).
        let refused =
            goal_within_limits(&[0.0, 0.0, 80.0, 0.0, 30.0, 0.0], &rig).expect_err("refused");
        assert_eq!(
            refused.to_string(),
            "goal: joint_3 = 80.000 deg is outside its limits [-110.000, 70.000] deg"
        );
    }
}
