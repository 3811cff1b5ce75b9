//! TorchScript policies (`labrig policy run --torchscript model.pt --spec spec.toml`).
//!
//! The module's signature:
//!
//! ```text
//! forward(obs: Dict[str, Tensor]) -> Tensor
//!   obs["observation.images.<camera>"]  (1, To, 3, S, S) float32 RGB, [0, 1] (image_range =
//!                                       "unit") or [0, 255] ("byte"), each camera the spec names
//!   obs["observation.state"]            (1, To, 7 or 8) float32: the TCP's xyz (m, robot base),
//!                                       its quaternion x y z w (w >= 0), then, with
//!                                       "gripper_position", the gripper (0 open .. 1 closed)
//!   returns                             (1, Tp, 7) float32 actions in the robot's units; row
//!                                       To - 1 is for the newest observation's tick, the chunk
//!                                       served is rows To - 1 .. Tp, one per 50 ms tick
//! ```
//!
//! The images are the loop's frames through the same JPEG and antialiased resize as a labrig
//! checkpoint's; the state is labrig's `state_row`. Normalisation belongs inside the module.
//! The spec is checked at start (its fields, then one forward on zeros: the output's shape);
//! the loop then refuses it as it refuses a checkpoint (cameras it does not record, an action
//! space it does not execute), each named.

use labrig_policies::policy::{ActionSpace, DiffusionConfig};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// `spec.toml`: what a TorchScript module takes and gives.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TorchScriptSpec {
    /// The policy id in chunks and episode metadata (`torchscript:<id>`; default the file stem).
    #[serde(default)]
    pub id: Option<String>,
    /// The cameras it observes, each an input `observation.images.<camera>`.
    pub cameras: Vec<String>,
    /// The images' side S (square, antialiased resize of the whole frame).
    pub image_size: i64,
    /// "unit" ([0, 1]) or "byte" ([0, 255]).
    #[serde(default = "unit")]
    pub image_range: String,
    /// The state's layout: `["eef_pose"]` or `["eef_pose", "gripper_position"]`.
    pub state: Vec<String>,
    pub n_obs_steps: i64,
    pub horizon: i64,
    pub n_action_steps: i64,
    /// `eef_axis_angle` (xyz + axis-angle + gripper) or `cartesian_velocity` (DROID's, 6 in
    /// [-1, 1] + gripper).
    pub action_space: String,
    pub action_dim: i64,
    /// The rate its rows are for: the loop's 20 Hz.
    #[serde(default = "twenty")]
    pub rate_hz: f64,
}

fn unit() -> String {
    "unit".into()
}

fn twenty() -> f64 {
    20.0
}

/// Why a spec file cannot be used; each names the file.
#[derive(Debug, thiserror::Error)]
pub enum TorchScriptError {
    #[error("the spec {}: {source}", path.display())]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("the spec {}: {source}", path.display())]
    Parse {
        path: PathBuf,
        #[source]
        source: Box<toml::de::Error>,
    },
    #[error("the spec {}: {source}", path.display())]
    Invalid {
        path: PathBuf,
        #[source]
        source: SpecError,
    },
}

/// A spec field labrig cannot serve, named with its value.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SpecError {
    #[error("image_size = {0} must be in 8..=1024")]
    ImageSize(i64),
    #[error("image_range = {0:?}: \"unit\" ([0, 1]) or \"byte\" ([0, 255])")]
    ImageRange(String),
    #[error(
        "state = {0:?}: labrig gives [\"eef_pose\"] or [\"eef_pose\", \"gripper_position\"] (xyz + quaternion xyzw, then the gripper)"
    )]
    State(Vec<String>),
    #[error("n_obs_steps {n_obs_steps} and horizon {horizon}: need 1 <= To <= Tp")]
    Steps { n_obs_steps: i64, horizon: i64 },
    #[error("n_action_steps = {n_action_steps} must be in 1..={rows} (Tp - To + 1)")]
    ActionSteps { n_action_steps: i64, rows: i64 },
    #[error(
        "action_space = {0:?}: labrig executes \"eef_axis_angle\" or \"cartesian_velocity\" from a TorchScript module"
    )]
    ActionSpace(String),
    #[error("action_dim = {action_dim}: {action_space:?} is 7 wide (6 + the gripper)")]
    ActionDim { action_dim: i64, action_space: String },
    #[error("rate_hz = {0}: the loop runs at 20 Hz; a chunk's rows are one tick apart")]
    RateHz(f64),
    #[error("cameras = {0:?}: names without dots")]
    Cameras(Vec<String>),
}

impl TorchScriptSpec {
    pub fn load(path: &Path) -> Result<TorchScriptSpec, TorchScriptError> {
        let text =
            std::fs::read_to_string(path).map_err(|source| TorchScriptError::Read { path: path.to_owned(), source })?;
        let spec: TorchScriptSpec = toml::from_str(&text)
            .map_err(|source| TorchScriptError::Parse { path: path.to_owned(), source: Box::new(source) })?;
        spec.validate().map_err(|source| TorchScriptError::Invalid { path: path.to_owned(), source })?;
        Ok(spec)
    }

    pub fn validate(&self) -> Result<(), SpecError> {
        if !(8..=1024).contains(&self.image_size) {
            return Err(SpecError::ImageSize(self.image_size));
        }
        if !["unit", "byte"].contains(&self.image_range.as_str()) {
            return Err(SpecError::ImageRange(self.image_range.clone()));
        }
        let layouts: [&[&str]; 2] = [&["eef_pose"], &["eef_pose", "gripper_position"]];
        if !layouts.iter().any(|l| self.state.iter().map(String::as_str).eq(l.iter().copied())) {
            return Err(SpecError::State(self.state.clone()));
        }
        if self.n_obs_steps < 1 || self.horizon < self.n_obs_steps {
            return Err(SpecError::Steps { n_obs_steps: self.n_obs_steps, horizon: self.horizon });
        }
        let rows = self.horizon - self.n_obs_steps + 1;
        if !(1..=rows).contains(&self.n_action_steps) {
            return Err(SpecError::ActionSteps { n_action_steps: self.n_action_steps, rows });
        }
        if !["eef_axis_angle", "cartesian_velocity"].contains(&self.action_space.as_str()) {
            return Err(SpecError::ActionSpace(self.action_space.clone()));
        }
        if self.action_dim != 7 {
            return Err(SpecError::ActionDim { action_dim: self.action_dim, action_space: self.action_space.clone() });
        }
        if (self.rate_hz - 20.0).abs() > 1e-9 {
            return Err(SpecError::RateHz(self.rate_hz));
        }
        if self.cameras.iter().any(|c| c.is_empty() || c.contains('.')) {
            return Err(SpecError::Cameras(self.cameras.clone()));
        }
        Ok(())
    }

    /// The spec as the config the server's observation code reads.
    pub fn config(&self) -> DiffusionConfig {
        let gripper = self.state.len() == 2;
        DiffusionConfig {
            cameras: self.cameras.clone(),
            image_size: self.image_size,
            crop_size: self.image_size,
            state_dim: if gripper { 8 } else { 7 },
            action_dim: self.action_dim,
            n_obs_steps: self.n_obs_steps,
            horizon: self.horizon,
            n_action_steps: self.n_action_steps,
            action_space: if self.action_space == "cartesian_velocity" {
                ActionSpace::CartesianVelocity
            } else {
                ActionSpace::EefAxisAngle
            },
            scene_state: false,
            scene_yaw: false,
            scene_relative: false,
            action_relative: false,
            gripper_state: gripper,
            ..DiffusionConfig::small_vision()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec() -> TorchScriptSpec {
        toml::from_str(
            r#"cameras = ["wrist"]
image_size = 64
state = ["eef_pose", "gripper_position"]
n_obs_steps = 2
horizon = 16
n_action_steps = 8
action_space = "cartesian_velocity"
action_dim = 7"#,
        )
        .unwrap()
    }

    #[test]
    fn a_spec_is_checked_field_by_field() {
        assert_eq!(spec().validate(), Ok(()));
        assert_eq!(spec().config().state_dim, 8);
        let e = TorchScriptSpec { state: vec!["joints".into()], ..spec() }.validate().unwrap_err().to_string();
        assert!(e.starts_with("state = [\"joints\"]"), "{e}");
        let e = TorchScriptSpec { action_space: "joint_velocity".into(), ..spec() }.validate().unwrap_err().to_string();
        assert!(e.contains("labrig executes"), "{e}");
        let e = TorchScriptSpec { n_action_steps: 16, ..spec() }.validate().unwrap_err().to_string();
        assert!(e.contains("1..=15"), "{e}");
        let e = TorchScriptSpec { rate_hz: 15.0, ..spec() }.validate().unwrap_err().to_string();
        assert!(e.contains("20 Hz"), "{e}");
        assert!(toml::from_str::<TorchScriptSpec>("cameras = []\nbogus = 1").is_err());
    }
}
