//! labrig-arm: the FR3's maths, shared by the franka node, the rig loop, the sim and the tools.
//!
//! - [`kinematics`]: forward kinematics and the geometric Jacobian from the FR3's URDF.
//! - [`ik`]: damped-least-squares IK steps (nullspace pull to the reset pose, joint-limit
//!   margins) and DROID's action spaces (cartesian velocity scaling, absolute poses).
//! - [`calib_path`]: the pose set a calibration capture drives the arm over (DROID's), shared
//!   by the sim's capture and a live rig's.
//! - [`safety`]: the safety layer every command passes (NaN/stale refusal, workspace box,
//!   joint limits and margins, per-step limits) and the watchdog.
//!
//! Depends on labrig-msgs, nalgebra, urdf-rs, serde, thiserror. Must never depend on tokio, DDS,
//! iceoryx2, franka-rs or the heavy native crates (checked by `tests/tests/layering.rs`).

pub mod calib_path;
pub mod ik;
pub mod kinematics;
pub mod safety;

pub use kinematics::{Fr3Kinematics, Joints, TcpOffset};

use std::path::{Path, PathBuf};

/// Where setup puts the FR3's URDF, relative to the repository root.
pub const DEFAULT_URDF: &str = ".labrig/mujoco/assets/fr3/fr3.urdf";

/// The FR3 URDF: `path` if given, else `$LABRIG_MUJOCO_DIR/assets/fr3/fr3.urdf` (setup's
/// env.sh), else [`DEFAULT_URDF`] in the current directory or the repository this was built from.
pub fn urdf_path(path: Option<&Path>) -> PathBuf {
    if let Some(p) = path {
        return p.to_owned();
    }
    if let Some(dir) = std::env::var_os("LABRIG_MUJOCO_DIR") {
        return PathBuf::from(dir).join("assets/fr3/fr3.urdf");
    }
    let local = PathBuf::from(DEFAULT_URDF);
    if local.exists() {
        return local;
    }
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..").join(DEFAULT_URDF)
}
