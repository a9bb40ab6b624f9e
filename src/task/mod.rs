//! Tasks: sources of targets that need more than a job description, such as a generated
//! room to paint. A task produces geometry, a plan through the normal pipeline and the
//! measurements that judge it; it never streams and never changes the rig.

pub mod paint;
