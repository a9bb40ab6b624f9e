//! Tasks: sources of targets that need more than a job description: a generated room to
//! paint, the sloth's gait over its branches. A task produces geometry, a plan through the
//! normal pipeline and the measurements that judge it; it never streams and never changes
//! the rig.

pub mod gait;
pub mod paint;
