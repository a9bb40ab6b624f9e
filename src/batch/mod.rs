//! The CSV contract of the batch tools (placeholder until written).
