//! The CSV contract of the `fk` and `ik` batch tools, as library functions over any reader
//! and writer (the binary only opens files and draws progress).
//!
//! Joint files: header `j1..jN`, degrees for revolute axes and metres for prismatic ones
//! ([`crate::rig::JointKind::unit`], read and written alike). Pose files: header
//! `x,y,z,qw,qx,qy,qz`, metres and a unit quaternion (within
//! [`crate::rig::UNIT_QUATERNION_TOLERANCE`], then normalised), tool frame in base frame.
//! Columns are found by name; extra columns are ignored. A bad row never stops a batch: it
//! gets an error status and the batch goes on. Opening files is the binary's business.
//! `rigbridge check`'s rows are [`check`]'s.

pub mod check;

use crate::ik::{IkError, IkSolver};
use crate::rig::{Pose, PoseError, Rig, UNIT_QUATERNION_TOLERANCE};
use glam::{DQuat, DVec3};
use std::collections::BTreeMap;
use std::io::{Read, Write};
use thiserror::Error;

pub const POSE_COLUMNS: [&str; 7] = ["x", "y", "z", "qw", "qx", "qy", "qz"];

#[derive(Debug, Error)]
pub enum BatchError {
    #[error("input has no column `{column}` (header: {header})")]
    MissingColumn { column: String, header: String },
    #[error("cannot read input: {0}")]
    Read(#[from] csv::Error),
    #[error("cannot write output: {0}")]
    Write(#[from] std::io::Error),
}

/// What a batch did, for the closing summary.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct BatchSummary {
    pub rows: usize,
    pub solved: usize,
    /// Failed rows by status.
    pub failed: BTreeMap<&'static str, usize>,
    pub max_position_error_m: f64,
    pub max_orientation_error_rad: f64,
}

impl BatchSummary {
    fn fail(&mut self, status: &'static str) {
        *self.failed.entry(status).or_default() += 1;
    }
}

/// Column positions of `names` in `header`.
fn locate<const N: usize>(
    header: &csv::StringRecord,
    names: [&str; N],
) -> Result<[usize; N], BatchError> {
    let mut positions = [0; N];
    for (slot, name) in positions.iter_mut().zip(names) {
        *slot = header
            .iter()
            .position(|h| h.trim() == name)
            .ok_or_else(|| BatchError::MissingColumn {
                column: name.to_string(),
                header: header.iter().collect::<Vec<_>>().join(","),
            })?;
    }
    Ok(positions)
}

fn field(record: &csv::StringRecord, index: usize) -> Option<f64> {
    record
        .get(index)?
        .trim()
        .parse()
        .ok()
        .filter(|v: &f64| v.is_finite())
}

fn reader(input: impl Read) -> csv::Reader<impl Read> {
    csv::ReaderBuilder::new()
        .flexible(true)
        .trim(csv::Trim::All)
        .from_reader(input)
}

pub fn joint_columns(dof: usize) -> Vec<String> {
    (1..=dof).map(|i| format!("j{i}")).collect()
}

/// Where the joint columns `names` ([`joint_columns`]) are in `reader`'s header.
fn joint_positions(
    reader: &mut csv::Reader<impl Read>,
    names: &[String],
) -> Result<Vec<usize>, BatchError> {
    let header = reader.headers()?;
    names
        .iter()
        .map(|n| locate(header, [n.as_str()]).map(|[c]| c))
        .collect()
}

/// Parses one joint row into SI units (radians, metres for prismatic axes).
fn joints_from(rig: &Rig, record: &csv::StringRecord, columns: &[usize]) -> Option<Vec<f64>> {
    columns
        .iter()
        .zip(&rig.joints)
        .map(|(&c, joint)| field(record, c).map(|v| joint.kind.from_user(v)))
        .collect()
}

/// The status of a row whose target was refused: its kind, and for a pose that could not be
/// used, why (the quaternion's norm), in words without commas so the CSV stays one column.
fn failed_status(error: &IkError) -> String {
    match error {
        IkError::InvalidTarget(PoseError::NotUnitQuaternion { norm, .. }) => format!(
            "{}: quaternion norm {norm:.6} is not 1 within {UNIT_QUATERNION_TOLERANCE}",
            error.kind()
        ),
        IkError::InvalidTarget(PoseError::Unparsable) => {
            format!("{}: a value is missing or not a number", error.kind())
        }
        other => other.kind().to_string(),
    }
}

fn pose_from(record: &csv::StringRecord, columns: &[usize; 7]) -> Option<Pose> {
    let v = columns.map(|c| field(record, c));
    let [x, y, z, w, i, j, k] = v;
    Some(Pose::new(
        DVec3::new(x?, y?, z?),
        DQuat::from_xyzw(i?, j?, k?, w?),
    ))
}

/// Forward kinematics of every joint row. Output: `x,y,z,qw,qx,qy,qz,status`; status is
/// `ok`, `outside_limits` (the pose is still given) or `invalid_input` (no pose).
pub fn fk_batch(
    rig: &Rig,
    input: impl Read,
    output: impl Write,
    mut progress: impl FnMut(usize),
) -> Result<BatchSummary, BatchError> {
    let mut reader = reader(input);
    let names = joint_columns(rig.dof());
    let columns = joint_positions(&mut reader, &names)?;
    let mut out = std::io::BufWriter::new(output);
    writeln!(out, "{},status", POSE_COLUMNS.join(","))?;
    let mut summary = BatchSummary::default();
    let mut record = csv::StringRecord::new();
    while reader.read_record(&mut record)? {
        summary.rows += 1;
        match joints_from(rig, &record, &columns) {
            Some(joints) => {
                let pose = rig
                    .tool_pose(&joints)
                    .expect("row has the rig's joint count");
                let (p, q) = (pose.position, pose.orientation);
                let status = if rig.first_limit_violation(&joints).is_some() {
                    summary.fail("outside_limits");
                    "outside_limits"
                } else {
                    summary.solved += 1;
                    "ok"
                };
                writeln!(
                    out,
                    "{:.12},{:.12},{:.12},{:.12},{:.12},{:.12},{:.12},{status}",
                    p.x, p.y, p.z, q.w, q.x, q.y, q.z
                )?;
            }
            None => {
                summary.fail("invalid_input");
                writeln!(out, ",,,,,,,invalid_input")?;
            }
        }
        progress(summary.rows);
    }
    out.flush()?;
    Ok(summary)
}

/// Inverse kinematics of every pose row, each seeded by the previous row's solution (the
/// first by `seed`), so a path in gives a smooth joint path out. Output:
/// `j1..jN,pos_err_m,rot_err_rad,iterations,status`; a failed row has empty values and its
/// error kind as status, and leaves the seed where it was.
pub fn ik_batch(
    solver: &dyn IkSolver,
    seed: &[f64],
    input: impl Read,
    output: impl Write,
    mut progress: impl FnMut(usize),
) -> Result<BatchSummary, BatchError> {
    let dof = solver.rig().dof();
    let mut reader = reader(input);
    let header = reader.headers()?.clone();
    let columns = locate(&header, POSE_COLUMNS)?;
    let mut out = std::io::BufWriter::new(output);
    writeln!(
        out,
        "{},pos_err_m,rot_err_rad,iterations,status",
        joint_columns(dof).join(",")
    )?;
    let empty_joints = ",".repeat(dof);
    let mut seed = seed.to_vec();
    let mut summary = BatchSummary::default();
    let mut record = csv::StringRecord::new();
    while reader.read_record(&mut record)? {
        summary.rows += 1;
        let result = match pose_from(&record, &columns) {
            Some(pose) => solver.solve(&pose, &seed),
            None => Err(IkError::InvalidTarget(crate::rig::PoseError::Unparsable)),
        };
        match result {
            Ok(solution) => {
                for (q, joint) in solution.joints.iter().zip(&solver.rig().joints) {
                    write!(out, "{:.9},", joint.kind.to_user(*q))?;
                }
                writeln!(
                    out,
                    "{:.3e},{:.3e},{},ok",
                    solution.position_error_m, solution.orientation_error_rad, solution.iterations
                )?;
                summary.solved += 1;
                summary.max_position_error_m =
                    summary.max_position_error_m.max(solution.position_error_m);
                summary.max_orientation_error_rad = summary
                    .max_orientation_error_rad
                    .max(solution.orientation_error_rad);
                seed = solution.joints;
            }
            Err(error) => {
                summary.fail(error.kind());
                writeln!(out, "{empty_joints},,,{}", failed_status(&error))?;
            }
        }
        progress(summary.rows);
    }
    out.flush()?;
    Ok(summary)
}
