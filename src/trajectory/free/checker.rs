//! The free planner's questions to the cell: is a configuration clear, is the straight
//! joint-space stretch between two clear, continuously ([`CollisionModel::check_step`]).
//! Stretches are proven at the cell's margin plus the planner's allowance, so that every
//! point of them is clear by the cell's own margin; only a stretch that leaves or reaches a
//! start or goal lying inside that allowance is proven at the cell's margin itself (the
//! arm is there, or is asked to go there, and nothing else could leave or reach it). Owns
//! that choice and the scratch buffers; the proof is `cell`'s.

use crate::cell::{Clearance, CollisionModel, Scratch};
use std::cell::RefCell;

pub(super) struct Checker<'a> {
    /// The cell at its own margin: the ends, and stretches touching a tight end.
    cell: &'a CollisionModel,
    /// The cell at its margin plus the allowance: every other stretch.
    planning: CollisionModel,
    /// The start and goal when they lie inside the allowance (tight), else `None`.
    tight: [Option<&'a [f64]>; 2],
    scratch: RefCell<Scratch>,
}

impl<'a> Checker<'a> {
    pub(super) fn new(
        cell: &'a CollisionModel,
        start: &'a [f64],
        goal: &'a [f64],
        allowance_m: f64,
    ) -> Self {
        let planning = cell.with_margin(cell.margin() + allowance_m);
        let mut scratch = cell.scratch();
        let mut tight_end = |q: &'a [f64]| {
            (cell.clearance(q, &mut scratch).distance_m < planning.margin()).then_some(q)
        };
        let tight = [tight_end(start), tight_end(goal)];
        Checker {
            cell,
            planning,
            tight,
            scratch: RefCell::new(scratch),
        }
    }

    /// The closest checked pair at `q`.
    pub(super) fn point(&self, q: &[f64]) -> Clearance {
        self.cell.clearance(q, &mut self.scratch.borrow_mut())
    }

    /// True when the straight stretch from `a` to `b` is proven clear.
    pub(super) fn edge(&self, a: &[f64], b: &[f64]) -> bool {
        self.model_for(a, b)
            .check_step(a, b, &mut self.scratch.borrow_mut())
            .is_ok()
    }

    /// The first pair found closer than the planner's margin on the straight stretch from
    /// `a` to `b` (at the cell's margin first: what the direct move would hit), or the
    /// closest pair at its ends when the stretch is clear.
    pub(super) fn first_block(&self, a: &[f64], b: &[f64]) -> Clearance {
        let scratch = &mut self.scratch.borrow_mut();
        match self.cell.check_step(a, b, scratch) {
            Err(blocked) => blocked,
            Ok(closest) => self
                .model_for(a, b)
                .check_step(a, b, scratch)
                .err()
                .unwrap_or(closest),
        }
    }

    fn model_for(&self, a: &[f64], b: &[f64]) -> &CollisionModel {
        let touches_tight = self
            .tight
            .iter()
            .flatten()
            .any(|end| *end == a || *end == b);
        if touches_tight {
            self.cell
        } else {
            &self.planning
        }
    }
}
