//! IK (next)
