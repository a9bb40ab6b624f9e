//! Tasks: sources of targets for rigs other than the arm's jobs (the sloth's gait). A task
//! produces a joint trajectory and hands it to the pipeline; it never streams itself.

pub mod gait;
