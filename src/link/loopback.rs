//! In-process loopback to the twin (being written).
pub struct LoopbackLink;
