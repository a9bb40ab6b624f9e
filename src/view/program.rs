//! A program on the live page and in Foxglove (issue 29): the step the stream is in, found
//! from the streamed cycle's place on the job's trajectory (the step whose span holds it,
//! [`StepSpans::current`]), and the cell's parts as the twin has them (where each lies or
//! is carried, and its judgement so far, from the twin's [`PartsBoard`]).
//!
//! Built once per cell (the parts' solids) and per job (the spans); read about 50 times a
//! second from the view's sampling task, never from the streaming cycle. Owns only what is
//! shown: which step a place belongs to is the job's, what became of a part the twin's.

use super::solid::{pose_view, solid};
use crate::cell::Cell;
use crate::job::{StepLabel, StepSpans};
use crate::scene::{PoseView, SolidView};
use crate::stream::JobPosition;
use crate::twin::{CellJudgement, PartsBoard};
use glam::DAffine3;
use serde::Serialize;
use std::sync::Arc;

/// The cell's parts as drawn: each part's solid (in its own frame) and where that frame
/// sits on the part's grasp frame.
pub struct PartsDrawing {
    board: Arc<PartsBoard>,
    base_from_cell: DAffine3,
    /// Each part's solid frame in its grasp frame.
    origins: Vec<DAffine3>,
    /// Each part's solid, its triangles in the solid's frame (pose: identity).
    pub solids: Vec<SolidView>,
}

impl PartsDrawing {
    /// The parts of `cell`, as the twin's `board` tells where they are.
    pub fn new(cell: &Cell, board: Arc<PartsBoard>) -> Self {
        PartsDrawing {
            board,
            base_from_cell: cell.mount.inverse(),
            origins: cell.parts.iter().map(|part| part.solid.origin).collect(),
            solids: cell
                .parts
                .iter()
                .map(|part| solid(&part.name, DAffine3::IDENTITY, &part.solid.shape))
                .collect(),
        }
    }

    /// Each part's solid posed in the rig's base frame, and the judgement so far.
    fn now(&self) -> (Vec<PoseView>, Option<CellJudgement>) {
        let now = self.board.read();
        let poses = now
            .poses
            .iter()
            .zip(&self.origins)
            .map(|(grasp, origin)| pose_view(self.base_from_cell * *grasp * *origin))
            .collect();
        (poses, now.judgement)
    }
}

/// What a frame shows of a program and its parts (docs/live-view.md, "Programs").
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ProgramView {
    /// The step the last streamed cycle is in; `null` when no program streams (or before
    /// its first cycle).
    pub step: Option<StepLabel>,
    /// Each part's solid where it is now, in the scene's `parts` order (empty without parts).
    pub parts: Vec<PoseView>,
    /// The twin's judgement so far (`null` without parts).
    pub judgement: Option<CellJudgement>,
}

/// The program view of a frame: the step of `on_job` among `steps`, the parts of `parts`;
/// `None` when there is neither a program nor parts to show.
pub fn program_view(
    steps: Option<&StepSpans>,
    on_job: Option<JobPosition>,
    parts: Option<&PartsDrawing>,
) -> Option<ProgramView> {
    if steps.is_none() && parts.is_none() {
        return None;
    }
    let step = steps
        .zip(on_job)
        .and_then(|(steps, at)| steps.label(steps.current(at)).cloned());
    let (parts, judgement) = parts.map(PartsDrawing::now).unwrap_or_default();
    Some(ProgramView {
        step,
        parts,
        judgement,
    })
}
