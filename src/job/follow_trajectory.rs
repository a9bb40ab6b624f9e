//! `kind = "follow_trajectory"`: a timed joint trajectory from a CSV file next to the config
//! (`file = "t.csv"`, columns `t,j1..jN`: seconds, then degrees, metres for prismatic axes),
//! or the same rows inline (`rows = [[t, j1, .., jN], ...]`; a ROS 2 JointTrajectory
//! arrives this way, docs/ros2.md). Owns reading those rows and turning them into a
//! trajectory at the stream's period: a joint move from where the rig is to the first row,
//! then the rows, joined by cubic Hermite pieces (tangents from the neighbouring rows, at
//! rest at both ends), checked like every trajectory and for acceleration too. It stays at
//! the last row. No error quotes the file's text: they name the row and column, and the
//! numbers read there; a refused curve is named by the rows either side and their times,
//! in the rows' units, with what to change. The rows' count and duration, and the memory
//! their plan takes, are held to `[limits]` (`super::limits`) while they are read, before
//! anything is sampled.

use super::limits::{CEILING_DURATION_S, CEILING_POINTS, JobLimits};
use super::{JobContext, JobError, JobInvalid, PlanContext, resolve_file, to_si};
use crate::motion::HermiteCurve;
use crate::rig::{JointKind, OutsideLimits, Rig};
use crate::trajectory::{
    Origins, OverBudget, SampleBudget, Trajectory, TrajectoryError, plan_joint_moves, validate,
};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::time::Duration;
use thiserror::Error;

/// Largest trajectory file (bytes), read before anything is parsed.
const MAX_FILE_BYTES: u64 = 32 * 1024 * 1024;

/// How many rows may be read and how far their `t` may go: `[limits]`' caps when a job is
/// validated; at planning, when the rows were validated already, only the ceilings a config
/// may set (the plan's own budget bounds what is sampled).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RowCaps {
    pub max_rows: usize,
    pub max_t_s: f64,
}

impl RowCaps {
    pub fn of(limits: &JobLimits) -> Self {
        RowCaps {
            max_rows: limits.max_job_points,
            max_t_s: limits.max_job_duration_s,
        }
    }

    /// The widest caps a config may set: for rows that were validated under the config's.
    pub const CEILING: RowCaps = RowCaps {
        max_rows: CEILING_POINTS,
        max_t_s: CEILING_DURATION_S,
    };
}

#[derive(Debug, Clone, PartialEq, Deserialize, Serialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct FollowTrajectory {
    /// The CSV file, relative to the config's directory.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub file: Option<PathBuf>,
    /// Or the rows themselves, as the file would hold them: `t` (s, from 0, increasing),
    /// then one value per joint (degrees, metres for prismatic axes). One of the two.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rows: Option<Vec<Vec<f64>>>,
    /// Whether the rig first moves to the first row from wherever it holds (true when
    /// absent). False: the first row must be where the rig holds, every axis within one
    /// cycle's step at its speed limit (the check the stream makes of a trajectory's first
    /// target against the controller), else the job is refused before anything moves. A
    /// trajectory from ROS 2 is taken this way (docs/ros2.md).
    #[serde(default = "approach_when_absent", skip_serializing_if = "approaches")]
    pub approach: bool,
}

fn approach_when_absent() -> bool {
    true
}

fn approaches(approach: &bool) -> bool {
    *approach
}

/// Why a trajectory file is refused: where, never what it holds.
#[derive(Debug, Error)]
pub enum TrajectoryFileError {
    #[error("{file}: cannot read")]
    Io {
        file: PathBuf,
        source: std::io::Error,
    },
    #[error("{file}: larger than {MAX_FILE_BYTES} bytes")]
    TooLarge { file: PathBuf },
    #[error("{file}: the header must be `{expected}`")]
    Header { file: PathBuf, expected: String },
    #[error("{file}: row {row}: {reason}")]
    Row {
        file: PathBuf,
        row: usize,
        reason: RowProblem,
    },
    #[error("{file}: {reason}")]
    Shape { file: PathBuf, reason: ShapeProblem },
    #[error("job.rows[{row}]: {reason}")]
    InlineRow { row: usize, reason: RowProblem },
    #[error("job.rows: {reason}")]
    InlineShape { reason: ShapeProblem },
}

/// What is wrong with one row of a trajectory file.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum RowProblem {
    #[error("more than the cap of {max} rows (`[limits] max_job_points`)")]
    TooMany { max: usize },
    #[error("needs {0} columns")]
    Columns(usize),
    #[error("column {0} is not a finite number")]
    NotANumber(usize),
    #[error("the first row's t must be 0")]
    FirstNotZero,
    #[error("t must increase from row to row")]
    NotIncreasing,
    #[error(
        "t = {t} s is beyond the cap of {max_s} s on a job's duration (`[limits] max_job_duration_s`)"
    )]
    TooLong { t: f64, max_s: f64 },
    #[error("column {column}: {outside}")]
    OutsideLimits {
        column: usize,
        outside: OutsideLimits,
    },
}

/// What is wrong with the trajectory a file's rows make.
#[derive(Debug, Error)]
pub enum ShapeProblem {
    #[error("no rows after the header")]
    NoRows,
    #[error(transparent)]
    Samples(Box<TrajectoryError>),
    #[error("refused before sampling: {0}")]
    OverBudget(OverBudget),
    #[error("the sampled trajectory is refused: {0}")]
    Refused(Box<TrajectoryError>),
    /// Boxed to keep every `Result<_, JobError>` small.
    #[error(transparent)]
    Between(Box<BetweenRows>),
}

/// A sample of the curve through the rows refused, named by the rows either side of it.
#[derive(Debug, Error)]
#[error(
    "at t = {t:.3} s, on the curve from {from} (t = {from_t:.3} s) to {to} (t = {to_t:.3} s): {problem}; hint: {hint}"
)]
pub struct BetweenRows {
    pub problem: CurveProblem,
    /// The file's time of the refused sample (s), and of the rows either side of it.
    pub t: f64,
    pub from: String,
    pub from_t: f64,
    pub to: String,
    pub to_t: f64,
    pub hint: Hint,
}

/// What a sample of the curve through the rows breaks, in the rows' units (degrees, metres
/// for prismatic axes) though the values are kept in SI units.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum CurveProblem {
    #[error("{0}")]
    Outside(OutsideLimits),
    #[error(
        "{joint} moves at {:.3} {unit}/s, above its max speed {:.3} {unit}/s",
        kind.to_user(*speed), kind.to_user(*max_speed), unit = kind.unit()
    )]
    Speed {
        joint: String,
        speed: f64,
        max_speed: f64,
        kind: JointKind,
    },
    #[error(
        "{joint} accelerates at {:.3} {unit}/s^2, above its max acceleration {:.3} {unit}/s^2",
        kind.to_user(*acceleration), kind.to_user(*max_acceleration), unit = kind.unit()
    )]
    Acceleration {
        joint: String,
        acceleration: f64,
        max_acceleration: f64,
        kind: JointKind,
    },
}

/// What to change in the rows so that the curve through them keeps within the limits.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Error)]
pub enum Hint {
    #[error(
        "the curve starts at rest at the first row: put the next row later, or add rows that speed up gradually"
    )]
    StartsAtRest,
    #[error(
        "the curve comes to rest at the last row: put the row before it earlier, or add rows that slow down gradually"
    )]
    EndsAtRest,
    #[error("space the rows further apart in time, or change speed less between them")]
    SpaceOut,
    #[error("slow down: space the rows further apart in time")]
    SlowDown,
    #[error(
        "the curve swings past the rows between them: keep the rows further inside the limits, or add rows near the limit"
    )]
    Overshoots,
}

/// One row: its time (s) and its joint values in SI units (rad, m).
pub type Row = (f64, Vec<f64>);

impl FollowTrajectory {
    pub fn validate(self, context: &JobContext) -> Result<Self, JobInvalid> {
        let caps = RowCaps::of(context.limits);
        match (self.file, self.rows) {
            (Some(file), None) => {
                let given = file.display().to_string();
                let file = resolve_file(context.base_dir, "job.file", &file)?;
                match read_trajectory_csv(&file, context.rig, caps) {
                    Ok(rows) => check_plan_size("job.file", &rows, context)?,
                    Err(e) => return Err(JobInvalid::new("job.file", given, trim_file(&e, &file))),
                }
                Ok(FollowTrajectory {
                    file: Some(file),
                    rows: None,
                    approach: self.approach,
                })
            }
            (None, Some(rows)) => match inline_rows(&rows, context.rig, caps) {
                Ok(checked) => {
                    check_plan_size("job.rows", &checked, context)?;
                    Ok(FollowTrajectory {
                        file: None,
                        rows: Some(rows),
                        approach: self.approach,
                    })
                }
                Err(TrajectoryFileError::InlineRow { row, reason }) => Err(JobInvalid::new(
                    format!("job.rows[{row}]"),
                    &rows[row],
                    reason.to_string(),
                )),
                Err(e) => Err(JobInvalid::new("job.rows", rows.len(), e.to_string())),
            },
            _ => Err(JobInvalid::new(
                "job",
                "follow_trajectory",
                "needs `file` (a CSV file) or `rows` (the rows inline), one of the two",
            )),
        }
    }

    /// The rows in SI units, from the file or inline, each with its name as the user finds
    /// it: the file's line number, or the index in `job.rows`.
    fn rows(&self, rig: &Rig) -> Result<(Vec<Row>, Vec<String>), TrajectoryFileError> {
        match (&self.file, &self.rows) {
            (Some(file), _) => {
                let (rows, lines) = read_numbered_rows(file, rig, RowCaps::CEILING)?;
                let name = file.file_name().unwrap_or(file.as_os_str()).display();
                let names = lines.iter().map(|l| format!("row {l} of {name}")).collect();
                Ok((rows, names))
            }
            (None, Some(rows)) => {
                let names = (0..rows.len()).map(|k| format!("job.rows[{k}]")).collect();
                Ok((inline_rows(rows, rig, RowCaps::CEILING)?, names))
            }
            (None, None) => Err(TrajectoryFileError::InlineShape {
                reason: ShapeProblem::NoRows,
            }),
        }
    }

    /// The approach and the rows; each stretch named by the rows it joins (see [`Origins`]).
    pub fn plan(&self, context: &PlanContext) -> Result<(Trajectory, Origins), JobError> {
        let (rows, names) = self.rows(context.rig)?;
        let (rig, settings) = (context.rig, context.settings);
        if !self.approach {
            starts_where_held(rig, &rows[0].1, context.start, settings.period)?;
        }
        let mut trajectory = plan_joint_moves(
            rig,
            context.start,
            std::slice::from_ref(&rows[0].1),
            settings,
        )?;
        // The curve's first sample is the approach's last: joined, it is one sample.
        let budget = settings.budget.after(trajectory.len() - 1);
        let followed =
            sample_rows(rig, &rows, settings.period, budget).map_err(|e| self.shape(e))?;
        let on_rows = |(sample, problem): (usize, CurveProblem)| {
            self.shape(between_rows(
                &rows,
                &names,
                settings.period,
                sample,
                problem,
            ))
        };
        validate(&followed, rig).map_err(|e| match curve_problem(rig, &followed, &e) {
            Some(located) => on_rows(located),
            None => self.shape(ShapeProblem::Refused(Box::new(e))),
        })?;
        check_acceleration(rig, &followed).map_err(on_rows)?;
        let mut origins = Origins::default();
        let joined = trajectory.len() - 1;
        origins.push(joined, format!("the approach to {}", names[0]));
        push_pieces(&mut origins, &rows, &names, settings.period, joined);
        trajectory.append(&followed);
        Ok((trajectory, origins))
    }

    fn shape(&self, reason: ShapeProblem) -> JobError {
        match &self.file {
            Some(file) => TrajectoryFileError::Shape {
                file: file.clone(),
                reason,
            },
            None => TrajectoryFileError::InlineShape { reason },
        }
        .into()
    }
}

/// A refusal of sample `sample` of the curve through `rows` (as [`sample_rows`] made it,
/// every `period`) told in the rows' words: the file's time of the sample, the rows either
/// side (named by `names`) and what to change.
fn between_rows(
    rows: &[Row],
    names: &[String],
    period: Duration,
    sample: usize,
    problem: CurveProblem,
) -> ShapeProblem {
    let last = rows.len() - 1;
    let t = (sample as f64 * period.as_secs_f64()).min(rows[last].0);
    // The piece ending at the first row not before `t` (a sample on a row ends its piece);
    // a single row is its own piece.
    let to = rows
        .partition_point(|row| row.0 < t)
        .clamp(1.min(last), last);
    let from = to.saturating_sub(1);
    let hint = match problem {
        CurveProblem::Outside(_) => Hint::Overshoots,
        CurveProblem::Speed { .. } => Hint::SlowDown,
        CurveProblem::Acceleration { .. } if from == 0 => Hint::StartsAtRest,
        CurveProblem::Acceleration { .. } if to == last => Hint::EndsAtRest,
        CurveProblem::Acceleration { .. } => Hint::SpaceOut,
    };
    ShapeProblem::Between(Box::new(BetweenRows {
        problem,
        t,
        from: names[from].clone(),
        from_t: rows[from].0,
        to: names[to].clone(),
        to_t: rows[to].0,
        hint,
    }))
}

/// `error` of [`validate`] as the sample it refused and what that sample breaks, when it is
/// about one sample's motion (the others stay as they are).
fn curve_problem(
    rig: &Rig,
    followed: &Trajectory,
    error: &TrajectoryError,
) -> Option<(usize, CurveProblem)> {
    let joint_named = |name: &str| rig.joints.iter().find(|joint| joint.name == name);
    let dt = followed.period.as_secs_f64();
    match error {
        TrajectoryError::OutsideLimits {
            sample,
            joint,
            value,
            ..
        } => {
            let outside = joint_named(joint)?.check_limits(*value).err()?;
            Some((*sample, CurveProblem::Outside(outside)))
        }
        TrajectoryError::VelocityOverSpeed {
            sample,
            joint,
            velocity,
            max_speed,
        } => {
            let joint = joint_named(joint)?;
            Some((
                *sample,
                CurveProblem::Speed {
                    joint: joint.name.clone(),
                    speed: velocity.abs(),
                    max_speed: *max_speed,
                    kind: joint.kind,
                },
            ))
        }
        TrajectoryError::OverSpeed {
            sample,
            joint,
            step,
            max_step,
        } => {
            let joint = joint_named(joint)?;
            Some((
                *sample,
                CurveProblem::Speed {
                    joint: joint.name.clone(),
                    speed: step / dt,
                    max_speed: max_step / dt,
                    kind: joint.kind,
                },
            ))
        }
        TrajectoryError::OverAcceleration {
            sample,
            joint,
            acceleration,
            max_acceleration,
            ..
        }
        | TrajectoryError::VelocityOverAcceleration {
            sample,
            joint,
            acceleration,
            max_acceleration,
            ..
        } => {
            let joint = joint_named(joint)?;
            Some((
                *sample,
                CurveProblem::Acceleration {
                    joint: joint.name.clone(),
                    acceleration: *acceleration,
                    max_acceleration: *max_acceleration,
                    kind: joint.kind,
                },
            ))
        }
        _ => None,
    }
}

/// The stretches of the sampled rows (from sample `offset` of the job on): the piece from
/// row `r - 1` to row `r` ends at the last sample not after row `r`'s time. Named with
/// both rows and the file's time of the first, as the user wrote them.
fn push_pieces(
    origins: &mut Origins,
    rows: &[Row],
    names: &[String],
    period: Duration,
    offset: usize,
) {
    let period_s = period.as_secs_f64();
    for r in 1..rows.len() {
        let last = (rows[r].0 / period_s).floor() as usize;
        origins.push(
            offset + last,
            format!(
                "the piece from {} (t = {:.3} s) to {}",
                names[r - 1],
                rows[r - 1].0,
                names[r]
            ),
        );
    }
    if rows.len() == 1 {
        origins.push(offset, names[0].clone());
    }
}

/// Refuses a first row (SI units) further from `held` than one cycle of `period` at an
/// axis' speed limit: the tolerance the stream gives a trajectory's first target against
/// the controller's position (`stream::check_start`).
fn starts_where_held(
    rig: &Rig,
    first: &[f64],
    held: &[f64],
    period: Duration,
) -> Result<(), JobInvalid> {
    let dt = period.as_secs_f64();
    for ((joint, first), held) in rig.joints.iter().zip(first).zip(held) {
        if !joint.limits.step_ok(first - held, dt) {
            let (kind, unit) = (joint.kind, joint.kind.unit());
            return Err(JobInvalid::new(
                "job.rows[0]",
                kind.to_user(*first),
                format!(
                    "starts {} at {:.3} {unit} but the rig holds it at {:.3} {unit}: with \
                     approach = false the first point must be where the rig holds (within \
                     {:.3} {unit}, one cycle at the axis' speed limit)",
                    joint.name,
                    kind.to_user(*first),
                    kind.to_user(*held),
                    kind.to_user(joint.limits.max_speed * dt),
                ),
            ));
        }
    }
    Ok(())
}

/// The plan of `rows` (already within the caps on points and `t`) within the memory cap
/// too: a curve through the rows, sampled on demand (its samples count against the
/// duration cap, its rows against the memory cap), refused under `key`.
fn check_plan_size(key: &str, rows: &[Row], context: &JobContext) -> Result<(), JobInvalid> {
    let last_t = rows.last().map_or(0.0, |row| row.0);
    context
        .limits
        .check_curve(key, last_t, rows.len(), context.period, context.rig.dof())
}

/// Inline rows (`t` then the joints, config units) checked like a file's, in SI units.
fn inline_rows(
    rows: &[Vec<f64>],
    rig: &Rig,
    caps: RowCaps,
) -> Result<Vec<Row>, TrajectoryFileError> {
    if rows.is_empty() {
        return Err(TrajectoryFileError::InlineShape {
            reason: ShapeProblem::NoRows,
        });
    }
    if rows.len() > caps.max_rows {
        return Err(TrajectoryFileError::InlineRow {
            row: caps.max_rows,
            reason: RowProblem::TooMany { max: caps.max_rows },
        });
    }
    let mut checked: Vec<Row> = Vec::with_capacity(rows.len());
    for (row, values) in rows.iter().enumerate() {
        let bad = |reason| TrajectoryFileError::InlineRow { row, reason };
        let previous = checked.last().map(|r| r.0);
        checked.push(check_row(values, rig, previous, caps.max_t_s).map_err(bad)?);
    }
    Ok(checked)
}

/// The message of `e` without the file name in front (the refusal names the key already).
fn trim_file(e: &TrajectoryFileError, file: &Path) -> String {
    let text = e.to_string();
    let prefix = format!("{}: ", file.display());
    text.strip_prefix(&prefix).unwrap_or(&text).to_string()
}

/// The rows of a trajectory file for `rig`: header `t,j1,...,jN` (or `t` and the rig's joint
/// names), `t` from 0 and strictly increasing, every value finite and inside its limits, at
/// most `caps.max_rows` rows and `t` at most `caps.max_t_s`.
pub fn read_trajectory_csv(
    file: &Path,
    rig: &Rig,
    caps: RowCaps,
) -> Result<Vec<Row>, TrajectoryFileError> {
    read_numbered_rows(file, rig, caps).map(|(rows, _)| rows)
}

/// [`read_trajectory_csv`], with each row's line number in the file (from 1, the header's
/// line counted): how errors and refusals name a row.
fn read_numbered_rows(
    file: &Path,
    rig: &Rig,
    caps: RowCaps,
) -> Result<(Vec<Row>, Vec<usize>), TrajectoryFileError> {
    let io = |source| TrajectoryFileError::Io {
        file: file.to_path_buf(),
        source,
    };
    if std::fs::metadata(file).map_err(io)?.len() > MAX_FILE_BYTES {
        return Err(TrajectoryFileError::TooLarge {
            file: file.to_path_buf(),
        });
    }
    let text = std::fs::read_to_string(file).map_err(io)?;
    let mut lines = text
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty() && !l.trim_start().starts_with('#'));
    check_header(file, rig, lines.next().map(|(_, l)| l))?;
    let mut rows: Vec<Row> = Vec::new();
    let mut numbers = Vec::new();
    for (index, line) in lines {
        let row = index + 1;
        let bad = |reason: RowProblem| TrajectoryFileError::Row {
            file: file.to_path_buf(),
            row,
            reason,
        };
        if rows.len() == caps.max_rows {
            return Err(bad(RowProblem::TooMany { max: caps.max_rows }));
        }
        let parsed = parse_row(line, rig, rows.last().map(|r| r.0), caps.max_t_s).map_err(bad)?;
        rows.push(parsed);
        numbers.push(row);
    }
    if rows.is_empty() {
        return Err(TrajectoryFileError::Shape {
            file: file.to_path_buf(),
            reason: ShapeProblem::NoRows,
        });
    }
    Ok((rows, numbers))
}

fn check_header(file: &Path, rig: &Rig, header: Option<&str>) -> Result<(), TrajectoryFileError> {
    let cells: Vec<String> = header
        .unwrap_or_default()
        .split(',')
        .map(|c| c.trim().to_string())
        .collect();
    let numbered: Vec<String> = std::iter::once("t".to_string())
        .chain((1..=rig.dof()).map(|i| format!("j{i}")))
        .collect();
    let named: Vec<String> = std::iter::once("t".to_string())
        .chain(rig.joint_names().map(str::to_owned))
        .collect();
    if cells == numbered || cells == named {
        Ok(())
    } else {
        Err(TrajectoryFileError::Header {
            file: file.to_path_buf(),
            expected: numbered.join(","),
        })
    }
}

/// One data row; `previous` is the time of the row before, `max_t_s` the cap on `t`.
fn parse_row(
    line: &str,
    rig: &Rig,
    previous: Option<f64>,
    max_t_s: f64,
) -> Result<Row, RowProblem> {
    let cells: Vec<&str> = line.split(',').map(str::trim).collect();
    if cells.len() != rig.dof() + 1 {
        return Err(RowProblem::Columns(rig.dof() + 1));
    }
    let values = cells
        .iter()
        .enumerate()
        .map(|(column, cell)| match cell.parse::<f64>() {
            Ok(v) if v.is_finite() => Ok(v),
            _ => Err(RowProblem::NotANumber(column + 1)),
        })
        .collect::<Result<Vec<_>, _>>()?;
    check_row(&values, rig, previous, max_t_s)
}

/// One row's values (`t`, then each joint in config units) checked: the column count,
/// every value finite, `t` from 0, increasing and at most `max_t_s`, the joints inside their
/// limits.
fn check_row(
    values: &[f64],
    rig: &Rig,
    previous: Option<f64>,
    max_t_s: f64,
) -> Result<Row, RowProblem> {
    if values.len() != rig.dof() + 1 {
        return Err(RowProblem::Columns(rig.dof() + 1));
    }
    if let Some(column) = values.iter().position(|v| !v.is_finite()) {
        return Err(RowProblem::NotANumber(column + 1));
    }
    let t = values[0];
    match previous {
        None if t != 0.0 => return Err(RowProblem::FirstNotZero),
        Some(before) if t <= before => return Err(RowProblem::NotIncreasing),
        _ if t > max_t_s => return Err(RowProblem::TooLong { t, max_s: max_t_s }),
        _ => {}
    }
    let si = to_si(&values[1..], rig);
    rig.check_limits(&si)
        .map_err(|(axis, outside)| RowProblem::OutsideLimits {
            column: axis + 2,
            outside,
        })?;
    Ok((t, si))
}

/// The rows sampled every `period`: a cubic Hermite piece between consecutive rows, its
/// tangents the slope over the rows either side (zero at the first and last row, so the
/// trajectory starts and ends at rest). The last row is the last sample, exactly. Stored as
/// the rows and their tangents, sampled on demand ([`HermiteCurve`]): a day through two
/// rows stores two rows. Refused before anything is built when it would break `budget`.
fn sample_rows(
    rig: &Rig,
    rows: &[Row],
    period: Duration,
    budget: SampleBudget,
) -> Result<Trajectory, ShapeProblem> {
    let dof = rig.dof();
    let end = rows[rows.len() - 1].0;
    budget
        .check_curve(end, rows.len(), period, dof)
        .map_err(ShapeProblem::OverBudget)?;
    let samples = |e| ShapeProblem::Samples(Box::new(e));
    let times = rows.iter().map(|row| row.0).collect();
    let positions = rows.iter().flat_map(|row| row.1.iter().copied()).collect();
    let tangents = (0..rows.len())
        .flat_map(|k| tangent(rows, k, dof))
        .collect();
    let curve = HermiteCurve::new(times, positions, tangents, dof, period).map_err(samples)?;
    Trajectory::from_curve(
        rig.name.clone(),
        rig.joint_names().map(str::to_owned).collect(),
        period,
        curve,
    )
    .map_err(samples)
}

/// The tangent (per second) at row `k` of `dof` axes: the slope over the rows either side,
/// zero at the first and last row.
fn tangent(rows: &[Row], k: usize, dof: usize) -> Vec<f64> {
    if k == 0 || k + 1 == rows.len() {
        return vec![0.0; dof];
    }
    let (before, after) = (&rows[k - 1], &rows[k + 1]);
    (0..dof)
        .map(|a| (after.1[a] - before.1[a]) / (after.0 - before.0))
        .collect()
}

/// Every second difference of the samples (at rest before the first and after the last)
/// within the axis' max acceleration; the first that is not, as its sample and what it
/// breaks.
fn check_acceleration(rig: &Rig, trajectory: &Trajectory) -> Result<(), (usize, CurveProblem)> {
    let n = trajectory.len();
    let at = |k: usize| trajectory.position(k.min(n - 1));
    let dt = trajectory.period.as_secs_f64();
    // Each sample is evaluated once, the window sliding along (a curve is sampled on demand).
    let (mut before, mut here) = (at(0), at(0));
    for k in 0..n {
        let after = at(k + 1);
        for (axis, joint) in rig.joints.iter().enumerate() {
            let second = after[axis] - 2.0 * here[axis] + before[axis];
            if !joint.limits.second_difference_ok(second, dt) {
                let problem = CurveProblem::Acceleration {
                    joint: joint.name.clone(),
                    acceleration: second / (dt * dt),
                    max_acceleration: joint.limits.max_acceleration,
                    kind: joint.kind,
                };
                return Err((k, problem));
            }
        }
        (before, here) = (here, after);
    }
    Ok(())
}
