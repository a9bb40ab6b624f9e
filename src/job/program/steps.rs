//! A program's steps as users write them (TOML `[[job.steps]]`, or JSON), and their
//! validation into [`Op`]s: every target resolved against the cell's named targets (poses
//! into the rig's base frame, offsets applied), repeats unrolled, zones checked against
//! their neighbours. Owns every key of a step and its refusal text; plans nothing.

use super::super::{JobContext, JobInvalid, check_joints, in_range, to_si};
use crate::cell::{Cell, NamedTarget, Spot};
use crate::motion::IoAction;
use crate::rig::{Pose, Rig};
use glam::{DAffine3, DVec3};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use std::time::Duration;

/// Most operations a program may unroll to (its steps, each repeat's steps once per
/// item): the cap every job's count of targets has.
const MAX_OPS: usize = super::super::MAX_TARGETS;

/// A step's `speed`: a share of the plan's speed, at least 1 % (slower is a typo for a
/// percentage, and a crawl the path timing would take minutes over).
const MIN_SPEED: f64 = 0.01;

/// The zone's range (m): at least 1 mm (RAPID's smallest predefined zone, z1), at most
/// 200 mm (its largest, z200; ABB, RAPID Reference Manual, "zonedata", predefined data).
const ZONE_RANGE_M: (f64, f64) = (0.001, 0.2);

/// The longest dwell or input timeout (s): an hour; longer is a job of its own.
const MAX_WAIT_S: f64 = 3600.0;

/// Largest offset (m) from a target: beyond any cell's reach, so it only catches typos.
const MAX_OFFSET_M: f64 = 2.0;

/// The flange's name as a step's `tool`: the rig's own tool frame without the cell's tool.
pub const FLANGE: &str = "tool0";

/// What marks a repeat's variable in a step's `to` (`$slot`).
const VARIABLE: char = '$';

fn full_speed() -> f64 {
    1.0
}

/// One step of a program.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize, JsonSchema)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Step {
    /// A joint move to a joint target (all axes arriving together).
    MoveJoints(Move),
    /// A joint move to a pose: inverse kinematics nearest the configuration before.
    MovePoses(Move),
    /// A straight tool line to a pose.
    MoveLinear(Move),
    /// A dwell at rest.
    Wait(Wait),
    /// Set a digital output (refused before motion: no link carries I/O yet).
    SetOutput(SetOutput),
    /// Wait for a digital input, with a timeout (refused before motion: no link carries
    /// I/O yet).
    WaitInput(WaitInput),
    /// Close the gripper (refused before motion: no link carries I/O yet).
    Grip(NoKeys),
    /// Open the gripper (refused before motion: no link carries I/O yet).
    Release(NoKeys),
    /// The steps inside, once for each target of a list or a grid.
    Repeat(Repeat),
}

/// A move to a named target, or to an offset from it.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Move {
    /// The target: a name from the cell (`home`, `slot[3]`), or a repeat's variable
    /// (`$slot`).
    pub to: String,
    /// An offset (m) from the target along its own tool axes x, y, z (as RAPID's
    /// RelTool): `[0, 0, -0.05]` is 50 mm back along the tool's z. Not for move_joints.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub offset_m: Option<[f64; 3]>,
    /// Share of the plan's speed ([plan] speed_scale of each axis' max), in [0.01, 1]; 1
    /// when absent.
    #[serde(default = "full_speed")]
    pub speed: f64,
    /// Fly-by zone (m) in [0.001, 0.2]: the motion leaves the path toward the next point
    /// once the tool is this close to this one, and passes it without stopping (RAPID's
    /// zone). Absent: a fine point, reached at rest.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub zone_m: Option<f64>,
    /// The tool whose TCP goes to the target: the cell's tool (the default) or `tool0`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tool: Option<String>,
}

#[derive(Debug, Clone, PartialEq, Deserialize, Serialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Wait {
    /// How long to dwell at rest (s), in (0, 3600].
    pub duration_s: f64,
}

#[derive(Debug, Clone, PartialEq, Deserialize, Serialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct SetOutput {
    /// The output's name: letters, digits and `_`.
    pub output: String,
    pub value: bool,
}

#[derive(Debug, Clone, PartialEq, Deserialize, Serialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct WaitInput {
    /// The input's name: letters, digits and `_`.
    pub input: String,
    pub value: bool,
    /// How long to wait at most (s), in (0, 3600]: required, a program never waits forever.
    pub timeout_s: Option<f64>,
}

/// A step that takes no keys besides its kind.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct NoKeys {}

#[derive(Debug, Clone, PartialEq, Deserialize, Serialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Repeat {
    /// The targets to repeat over: a grid's name from the cell (`slot`: all its slots in
    /// order), or a list of target names.
    pub over: Over,
    /// The variable's name: the steps inside write `$name` for the current target.
    #[serde(rename = "as")]
    pub var: String,
    /// The steps, once per target (no repeat inside a repeat).
    pub steps: Vec<Step>,
}

/// A repeat's targets.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize, JsonSchema)]
#[serde(untagged)]
pub enum Over {
    /// A grid's name: all its slots, in order.
    Grid(String),
    /// Target names, in order.
    List(Vec<String>),
}

/// A step validated and resolved: where it was written, what it does in words, the loop
/// it belongs to, and the action.
#[derive(Debug, Clone, PartialEq)]
pub struct Op {
    /// `job.steps[3]`, `job.steps[2].steps[1]`.
    pub key: String,
    /// `move_linear to slot[2] + [0, 0, -0.05] m`, `wait 0.5 s`.
    pub what: String,
    /// The repeat and pass this op belongs to, if any.
    pub lap: Option<Lap>,
    pub action: Action,
}

/// A pass of a repeat: the repeat's key, the pass' index and its target.
#[derive(Debug, Clone, PartialEq)]
pub struct Lap {
    pub repeat: String,
    pub index: usize,
    pub item: String,
}

#[derive(Debug, Clone, PartialEq)]
pub enum Action {
    Move(MoveOp),
    Dwell(Duration),
    /// A step that needs I/O: the stream stops at rest there until it is done.
    Io(IoAction),
}

/// How a move goes to its goal.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum How {
    Joints,
    Poses,
    Linear,
}

#[derive(Debug, Clone, PartialEq)]
pub enum Goal {
    /// A configuration (SI units).
    Joints(Vec<f64>),
    /// The step's tool's pose in the rig's base frame.
    Pose(Pose),
}

#[derive(Debug, Clone, PartialEq)]
pub struct MoveOp {
    pub how: How,
    pub goal: Goal,
    /// The step's tool: the rig's tool transform (last joint to TCP) for it.
    pub tool: DAffine3,
    pub speed: f64,
    pub zone_m: Option<f64>,
}

/// What validating steps needs: the rig at the cell tool's TCP, the cell, and the rig's
/// tool transforms for the cell's tool and the flange.
pub struct Scope<'a> {
    pub rig: &'a Rig,
    pub cell: &'a Cell,
    /// (name, the rig's tool transform for it): the cell's tool first (the default), then
    /// the flange.
    pub tools: Vec<(String, DAffine3)>,
}

impl<'a> Scope<'a> {
    pub fn new(context: &JobContext<'a>) -> Scope<'a> {
        let (rig, cell) = (context.rig, context.cell);
        let mut tools = Vec::new();
        let flange = match &cell.tool {
            Some(tool) if rig.tool_frame == tool.name => {
                tools.push((tool.name.clone(), rig.tool));
                rig.tool * tool.tcp.inverse()
            }
            Some(tool) => {
                tools.push((tool.name.clone(), rig.tool * tool.tcp));
                rig.tool
            }
            None => rig.tool,
        };
        tools.push((FLANGE.to_string(), flange));
        Scope { rig, cell, tools }
    }

    /// The rig's tool transform for `tool` (the first, the cell's, when absent).
    fn tool(&self, key: &str, tool: Option<&String>) -> Result<DAffine3, JobInvalid> {
        let Some(name) = tool else {
            return Ok(self.tools[0].1);
        };
        self.tools
            .iter()
            .find(|(known, _)| known == name)
            .map(|(_, transform)| *transform)
            .ok_or_else(|| {
                let known: Vec<&str> = self.tools.iter().map(|(n, _)| n.as_str()).collect();
                JobInvalid::new(
                    format!("{key}.tool"),
                    name,
                    format!("no such tool (tools: {})", known.join(", ")),
                )
            })
    }

    /// `rig` with `tool` as its tool transform.
    pub fn rig_with(&self, tool: DAffine3) -> Rig {
        Rig {
            tool,
            ..self.rig.clone()
        }
    }
}

/// The ops of `steps` (at `job.steps`), in order.
pub fn unroll(steps: &[Step], scope: &Scope) -> Result<Vec<Op>, JobInvalid> {
    super::super::check_count("job.steps", steps.len())?;
    let mut ops = Vec::new();
    for (i, step) in steps.iter().enumerate() {
        let key = format!("job.steps[{i}]");
        match step {
            Step::Repeat(repeat) => unroll_repeat(&key, repeat, scope, &mut ops)?,
            other => ops.push(op_of(&key, other, None, scope)?),
        }
        if ops.len() > MAX_OPS {
            return Err(JobInvalid::new(
                key,
                format!("{} steps", ops.len()),
                format!("a program unrolls to at most {MAX_OPS} steps"),
            ));
        }
    }
    Ok(ops)
}

fn unroll_repeat(
    key: &str,
    repeat: &Repeat,
    scope: &Scope,
    ops: &mut Vec<Op>,
) -> Result<(), JobInvalid> {
    let items = match &repeat.over {
        Over::Grid(name) => scope.cell.targets.grid(name).ok_or_else(|| {
            JobInvalid::new(
                format!("{key}.over"),
                name,
                format!(
                    "no grid of this name in the cell (targets: {})",
                    scope.cell.targets.known()
                ),
            )
        })?,
        Over::List(names) => names.clone(),
    };
    if items.is_empty() {
        return Err(JobInvalid::new(
            format!("{key}.over"),
            "[]",
            "a repeat needs at least one target to go over",
        ));
    }
    check_name(&format!("{key}.as"), &repeat.var, "a variable's")?;
    if repeat.steps.is_empty() {
        return Err(JobInvalid::new(
            format!("{key}.steps"),
            "[]",
            "a repeat needs at least one step",
        ));
    }
    for (index, item) in items.iter().enumerate() {
        let lap = Lap {
            repeat: key.to_string(),
            index,
            item: item.clone(),
        };
        if scope.cell.targets.get(item).is_none() {
            return Err(unknown_target(&format!("{key}.over[{index}]"), item, scope));
        }
        for (j, step) in repeat.steps.iter().enumerate() {
            let inner = format!("{key}.steps[{j}]");
            if let Step::Repeat(_) = step {
                return Err(JobInvalid::new(
                    format!("{inner}.kind"),
                    "repeat",
                    "a repeat inside a repeat is not supported: unroll the outer one",
                ));
            }
            let bound = Binding {
                var: &repeat.var,
                item,
            };
            ops.push(op_of(&inner, step, Some((&lap, bound)), scope)?);
        }
    }
    Ok(())
}

/// A repeat's variable bound to the current pass' target.
#[derive(Clone, Copy)]
struct Binding<'a> {
    var: &'a str,
    item: &'a str,
}

fn unknown_target(key: &str, name: &str, scope: &Scope) -> JobInvalid {
    JobInvalid::new(
        key,
        name,
        format!(
            "no target of this name in the cell (targets: {})",
            scope.cell.targets.known()
        ),
    )
}

/// A signal's or a variable's name: letters, digits and `_`, at least one.
/// The output `grip` and `release` set (docs/protocol.md 6.10: 1 closes, 0 opens).
const GRIPPER_OUTPUT: &str = "gripper";
/// The longest I/O name: what protocol v3 carries (docs/protocol.md 3.6).
const MAX_IO_NAME_LEN: usize = 32;

fn gripper(close: bool) -> Action {
    Action::Io(IoAction::SetOutput {
        name: GRIPPER_OUTPUT.to_string(),
        value: close,
    })
}

fn check_name(key: &str, name: &str, whose: &str) -> Result<(), JobInvalid> {
    if name.is_empty()
        || name.len() > MAX_IO_NAME_LEN
        || !name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
    {
        return Err(JobInvalid::new(
            key,
            name,
            format!("{whose} name is 1 to {MAX_IO_NAME_LEN} letters, digits and `_`"),
        ));
    }
    Ok(())
}

fn wait_time(key: &str, seconds: f64) -> Result<f64, JobInvalid> {
    if seconds.is_finite() && seconds > 0.0 && seconds <= MAX_WAIT_S {
        Ok(seconds)
    } else {
        Err(JobInvalid::new(
            key,
            seconds,
            format!("must lie in (0, {MAX_WAIT_S}] s"),
        ))
    }
}

fn op_of(
    key: &str,
    step: &Step,
    lap: Option<(&Lap, Binding)>,
    scope: &Scope,
) -> Result<Op, JobInvalid> {
    let (what, action) = match step {
        Step::MoveJoints(m) => move_op(key, How::Joints, m, lap.map(|l| l.1), scope)?,
        Step::MovePoses(m) => move_op(key, How::Poses, m, lap.map(|l| l.1), scope)?,
        Step::MoveLinear(m) => move_op(key, How::Linear, m, lap.map(|l| l.1), scope)?,
        Step::Wait(w) => {
            let s = wait_time(&format!("{key}.duration_s"), w.duration_s)?;
            (
                format!("wait {s} s"),
                Action::Dwell(Duration::from_secs_f64(s)),
            )
        }
        Step::SetOutput(s) => {
            check_name(&format!("{key}.output"), &s.output, "an output's")?;
            (
                format!("set_output {} = {}", s.output, s.value),
                Action::Io(IoAction::SetOutput {
                    name: s.output.clone(),
                    value: s.value,
                }),
            )
        }
        Step::WaitInput(w) => {
            check_name(&format!("{key}.input"), &w.input, "an input's")?;
            let timeout = w.timeout_s.ok_or_else(|| {
                JobInvalid::new(
                    format!("{key}.timeout_s"),
                    "missing",
                    "a wait_input needs a timeout_s: a program never waits forever",
                )
            })?;
            wait_time(&format!("{key}.timeout_s"), timeout)?;
            (
                format!("wait_input {} = {}", w.input, w.value),
                Action::Io(IoAction::WaitInput {
                    name: w.input.clone(),
                    value: w.value,
                    timeout: Duration::from_secs_f64(timeout),
                }),
            )
        }
        Step::Grip(_) => ("grip".to_string(), gripper(true)),
        Step::Release(_) => ("release".to_string(), gripper(false)),
        Step::Repeat(_) => unreachable!("repeats are unrolled by the caller"),
    };
    Ok(Op {
        key: key.to_string(),
        what,
        lap: lap.map(|(lap, _)| lap.clone()),
        action,
    })
}

fn how_name(how: How) -> &'static str {
    match how {
        How::Joints => "move_joints",
        How::Poses => "move_poses",
        How::Linear => "move_linear",
    }
}

fn move_op(
    key: &str,
    how: How,
    step: &Move,
    binding: Option<Binding>,
    scope: &Scope,
) -> Result<(String, Action), JobInvalid> {
    let name = resolve_name(key, &step.to, binding)?;
    let target = scope
        .cell
        .targets
        .get(&name)
        .ok_or_else(|| unknown_target(&format!("{key}.to"), &step.to, scope))?;
    in_range(&format!("{key}.speed"), step.speed, MIN_SPEED, 1.0)?;
    if let Some(zone) = step.zone_m {
        in_range(
            &format!("{key}.zone_m"),
            zone,
            ZONE_RANGE_M.0,
            ZONE_RANGE_M.1,
        )?;
    }
    let tool = scope.tool(key, step.tool.as_ref())?;
    let offset = match step.offset_m {
        Some(offset) => Some(check_offset(key, how, offset)?),
        None => None,
    };
    let target_key = format!("{key}.to");
    let goal = match (&target.spot, offset, how) {
        (Spot::Joints(joints), None, How::Joints | How::Poses) => {
            Goal::Joints(joint_target(&target_key, target, joints, scope.rig)?)
        }
        (Spot::Pose(_), _, How::Joints) => {
            return Err(JobInvalid::new(
                target_key,
                &step.to,
                format!("`{name}` is a pose: move_joints goes to joint targets; use move_poses"),
            ));
        }
        (Spot::Joints(joints), _, _) => {
            let joints = joint_target(&target_key, target, joints, scope.rig)?;
            let at = scope
                .rig_with(tool)
                .forward(&joints)
                .map_err(|e| JobInvalid::new(target_key.clone(), &step.to, e.to_string()))?;
            Goal::Pose(offset_pose(at, offset))
        }
        (Spot::Pose(in_cell), _, _) => {
            Goal::Pose(offset_pose(scope.cell.mount.inverse() * *in_cell, offset))
        }
    };
    let mut what = format!("{} to {name}", how_name(how));
    if let Some(offset) = offset {
        what += &format!(" + [{}, {}, {}] m", offset.x, offset.y, offset.z);
    }
    let op = MoveOp {
        how,
        goal,
        tool,
        speed: step.speed,
        zone_m: step.zone_m,
    };
    Ok((what, Action::Move(op)))
}

/// The target's name: `to` itself, or the current pass' target for `$var`.
fn resolve_name(key: &str, to: &str, binding: Option<Binding>) -> Result<String, JobInvalid> {
    let Some(var) = to.strip_prefix(VARIABLE) else {
        return Ok(to.to_string());
    };
    match binding {
        Some(bound) if bound.var == var => Ok(bound.item.to_string()),
        Some(bound) => Err(JobInvalid::new(
            format!("{key}.to"),
            to,
            format!("the repeat's variable is `${}`", bound.var),
        )),
        None => Err(JobInvalid::new(
            format!("{key}.to"),
            to,
            "a `$` variable is only defined inside a repeat",
        )),
    }
}

fn check_offset(key: &str, how: How, offset: [f64; 3]) -> Result<DVec3, JobInvalid> {
    let key = format!("{key}.offset_m");
    if how == How::Joints {
        return Err(JobInvalid::new(
            key,
            offset,
            "an offset needs a pose: use move_poses or move_linear",
        ));
    }
    if !offset
        .iter()
        .all(|v| v.is_finite() && v.abs() <= MAX_OFFSET_M)
    {
        return Err(JobInvalid::new(
            key,
            offset,
            format!("every component must lie in [-{MAX_OFFSET_M}, {MAX_OFFSET_M}] m"),
        ));
    }
    Ok(DVec3::from_array(offset))
}

/// A joint target checked against the rig's axes and limits, in SI units; a refusal names
/// the step's key, the target and the cell's key that holds the bad value.
fn joint_target(
    key: &str,
    target: &NamedTarget,
    joints: &[f64],
    rig: &Rig,
) -> Result<Vec<f64>, JobInvalid> {
    check_joints(&format!("{}.joints_deg", target.key), joints, rig).map_err(|bad| {
        JobInvalid::new(
            key,
            &target.name,
            format!("the cell's {} = {}: {}", bad.key, bad.value, bad.reason),
        )
    })?;
    Ok(to_si(joints, rig))
}

/// `at` moved by `offset` along its own axes.
fn offset_pose(at: DAffine3, offset: Option<DVec3>) -> Pose {
    let moved = match offset {
        Some(offset) => at * DAffine3::from_translation(offset),
        None => at,
    };
    Pose::from_affine(&moved)
}

/// The tool's position at `op`'s goal (for a joint goal, by forward kinematics with its
/// tool), in the base frame.
pub fn goal_position(op: &MoveOp, rig: &Rig) -> Result<DVec3, JobInvalid> {
    match &op.goal {
        Goal::Pose(pose) => Ok(pose.position),
        Goal::Joints(joints) => Rig {
            tool: op.tool,
            ..rig.clone()
        }
        .tool_pose(joints)
        .map(|pose| pose.position)
        .map_err(|e| JobInvalid::new("job.steps", joints, e.to_string())),
    }
}
