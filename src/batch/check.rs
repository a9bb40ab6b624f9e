//! The CSV contract of `rigbridge check`: joint rows in (the `fk` convention: header
//! `j1..jN`, degrees for revolute axes, metres for prismatic ones, columns found by name),
//! one row out per row in: `min_clearance_m,body_a,body_b,status`. The clearance is the
//! closest checked pair's distance in metres (negative: their penetration depth), status
//! `free`, `within_margin` or `collision` as the cell's margin says, or `outside_limits: ...`
//! / `invalid_input: ...` naming the column and the value. A bad row never stops the batch.
//! Owns the format only; the geometry is [`crate::cell::CollisionModel`]'s.

use super::{BatchError, joint_columns, joint_positions, reader};
use crate::cell::{Clearance, CollisionModel};
use crate::rig::Rig;
use std::collections::BTreeMap;
use std::io::{Read, Write};

/// The output header.
pub const CHECK_COLUMNS: &str = "min_clearance_m,body_a,body_b,status";
/// Statuses of rows that could not be checked as given.
pub const OUTSIDE_LIMITS: &str = "outside_limits";
pub const INVALID_INPUT: &str = "invalid_input";
/// How much of a bad value a status quotes: enough to recognise it, never a whole line.
const QUOTED_CHARS: usize = 24;

/// The row with the smallest clearance of a batch.
#[derive(Debug, Clone, PartialEq)]
pub struct ClosestRow {
    /// 1-based data row (the header is not counted).
    pub row: usize,
    pub distance_m: f64,
    pub body_a: String,
    pub body_b: String,
}

/// What a check batch found, for the closing summary and the exit code.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct CheckSummary {
    pub rows: usize,
    /// Rows by status kind (`free`, `within_margin`, `collision`, `outside_limits`,
    /// `invalid_input`).
    pub counts: BTreeMap<String, usize>,
    pub closest: Option<ClosestRow>,
    /// The first row that could not be checked as given, in words (row, column, value).
    pub first_problem: Option<String>,
}

impl CheckSummary {
    /// Every row was valid and free.
    pub fn all_free(&self) -> bool {
        self.counts.keys().all(|k| k == "free")
    }

    fn count(&mut self, kind: &str) {
        *self.counts.entry(kind.to_string()).or_default() += 1;
    }

    fn note_problem(&mut self, row: usize, line: u64, problem: impl std::fmt::Display) {
        if self.first_problem.is_none() {
            self.first_problem = Some(format!("row {row} (line {line}): {problem}"));
        }
    }

    fn note_clearance(&mut self, row: usize, model: &CollisionModel, c: &Clearance) {
        if self
            .closest
            .as_ref()
            .is_none_or(|best| c.distance_m < best.distance_m)
        {
            self.closest = Some(ClosestRow {
                row,
                distance_m: c.distance_m,
                body_a: model.body_name(c.a).to_string(),
                body_b: model.body_name(c.b).to_string(),
            });
        }
    }
}

/// A value as a status may quote it: no commas or line breaks (the status is one CSV
/// field), at most [`QUOTED_CHARS`] characters.
fn quoted(text: &str) -> String {
    let mut out: String = text
        .chars()
        .take(QUOTED_CHARS)
        .map(|c| if c == ',' || c.is_control() { ' ' } else { c })
        .collect();
    if text.chars().count() > QUOTED_CHARS {
        out.push_str("...");
    }
    out
}

/// Why a row's joints cannot be read: the column's name and what it holds.
#[derive(Debug, thiserror::Error)]
enum RowProblem {
    #[error("{column} is missing")]
    Missing { column: String },
    #[error("{column} = {quoted} is not a number")]
    NotANumber { column: String, quoted: String },
}

/// One row's joints in SI units, or why not: the column and what it holds.
fn row_joints(
    rig: &Rig,
    record: &csv::StringRecord,
    columns: &[usize],
    names: &[String],
) -> Result<Vec<f64>, RowProblem> {
    let mut joints = Vec::with_capacity(columns.len());
    for ((&c, joint), name) in columns.iter().zip(&rig.joints).zip(names) {
        let text = record.get(c).unwrap_or("").trim();
        if text.is_empty() {
            return Err(RowProblem::Missing {
                column: name.clone(),
            });
        }
        match text.parse::<f64>() {
            Ok(v) if v.is_finite() => joints.push(joint.kind.from_user(v)),
            _ => {
                return Err(RowProblem::NotANumber {
                    column: name.clone(),
                    quoted: quoted(text),
                });
            }
        }
    }
    Ok(joints)
}

/// The first joint outside its limits, in words, in the file's units.
fn limit_problem(rig: &Rig, joints: &[f64], names: &[String]) -> Option<String> {
    let (index, q) = rig.first_limit_violation(joints)?;
    let joint = &rig.joints[index];
    let (kind, l) = (joint.kind, joint.limits);
    Some(format!(
        "{} = {} {unit} outside [{} {}] {unit}",
        names[index],
        kind.to_user(q),
        kind.to_user(l.lower),
        kind.to_user(l.upper),
        unit = kind.unit()
    ))
}

/// Checks every joint row of `input` against `model` (built for `rig`), writing one output
/// row each. Rows outside the limits are still measured (their status says they are out).
pub fn check_batch(
    model: &CollisionModel,
    rig: &Rig,
    input: impl Read,
    output: impl Write,
    mut progress: impl FnMut(usize),
) -> Result<CheckSummary, BatchError> {
    let mut reader = reader(input);
    let names = joint_columns(rig.dof());
    let columns = joint_positions(&mut reader, &names)?;
    let mut out = std::io::BufWriter::new(output);
    writeln!(out, "{CHECK_COLUMNS}")?;
    let mut scratch = model.scratch();
    let mut summary = CheckSummary::default();
    let mut record = csv::StringRecord::new();
    while reader.read_record(&mut record)? {
        summary.rows += 1;
        let row = summary.rows;
        let line = record.position().map_or(0, |p| p.line());
        match row_joints(rig, &record, &columns, &names) {
            Ok(joints) => {
                let clearance = model.clearance(&joints, &mut scratch);
                let status = match limit_problem(rig, &joints, &names) {
                    Some(problem) => {
                        summary.count(OUTSIDE_LIMITS);
                        summary.note_problem(row, line, &problem);
                        format!("{OUTSIDE_LIMITS}: {problem}")
                    }
                    None => {
                        let status = model.status(clearance.distance_m).to_string();
                        summary.count(&status);
                        summary.note_clearance(row, model, &clearance);
                        status
                    }
                };
                writeln!(
                    out,
                    "{:.9},{},{},{status}",
                    clearance.distance_m,
                    model.body_name(clearance.a),
                    model.body_name(clearance.b)
                )?;
            }
            Err(problem) => {
                summary.count(INVALID_INPUT);
                summary.note_problem(row, line, &problem);
                writeln!(out, ",,,{INVALID_INPUT}: {problem}")?;
            }
        }
        progress(row);
    }
    out.flush()?;
    Ok(summary)
}
