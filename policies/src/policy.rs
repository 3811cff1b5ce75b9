//! The Diffusion Policy assembled (LeRobot's `DiffusionModel`): one [`RgbEncoder`] per camera,
//! the observation of `To` steps as global conditioning, the [`ConditionalUnet1d`] noise
//! network, training's noise-prediction loss and inference's DDIM sampling of a `Tp`-step chunk
//! of which `Ta` steps are executed.
//!
//! Tensors use LeRobot's layouts: images (B, To, 3, H, W) in [0, 1] per camera, the low-dim
//! state (B, To, state_dim) and actions (B, Tp, action_dim) already normalised (see
//! [`crate::normalize`]).

use crate::encoder::{Backbone, RgbEncoder};
use crate::schedule::{Ddim, NoiseSchedule, Prediction, ScheduleError};
use crate::unet::{ConditionalUnet1d, UnetConfig};
use tch::nn::{self, Module};
use tch::{Kind, Tensor};

/// Every number of the model (the presets are [`DiffusionConfig::paper_dp`] and
/// [`DiffusionConfig::small`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DiffusionConfig {
    /// Cameras whose images are observed, one encoder each (the paper: the two shoulder ones).
    pub cameras: Vec<String>,
    /// Images are resized to this square before cropping.
    pub image_size: i64,
    /// The crop taken from it: random in training, centred at inference.
    pub crop_size: i64,
    pub keypoints: i64,
    pub state_dim: i64,
    pub action_dim: i64,
    /// To, Tp, Ta.
    pub n_obs_steps: i64,
    pub horizon: i64,
    pub n_action_steps: i64,
    pub down_dims: Vec<i64>,
    pub kernel_size: i64,
    pub n_groups: i64,
    pub step_embed_dim: i64,
    pub film_scale: bool,
    pub train_steps: usize,
    pub inference_steps: usize,
    /// Predicted clean samples clipped to [-clip, clip].
    pub clip: Option<f64>,
    /// Which of the recorded `action` keys the policy outputs.
    #[serde(default)]
    pub action_space: ActionSpace,
    /// Append the sim scene's object and receptacle positions (3 + 3) to the state (the
    /// low-dimensional variant of the small preset: no cameras, the scene's ground truth).
    #[serde(default)]
    pub scene_state: bool,
    /// Append the gripper's measured opening to the state (after the pose). The paper's state
    /// is the pose alone (its cameras show the gripper); the CPU presets' one small camera,
    /// or none, does not show whether it holds the object.
    #[serde(default)]
    pub gripper_state: bool,
    /// With `scene_state`, also the object's yaw as (cos 4 yaw, sin 4 yaw): the scripted
    /// expert turns the gripper to the cube's yaw (modulo its 90 degree symmetry), which no
    /// position shows.
    #[serde(default)]
    pub scene_yaw: bool,
    /// With `scene_state`, the object's and the receptacle's positions relative to the
    /// gripper (position - TCP) instead of in the base frame: "where is it from here" is the
    /// same function everywhere on the table, where absolute positions let a small data set
    /// be memorised trajectory by trajectory (seen: held-out scenes reached 5 cm off).
    #[serde(default)]
    pub scene_relative: bool,
    /// With `eef_axis_angle`, the chunk's target positions relative to the TCP's position at
    /// the newest observation (target - TCP), added back at inference: an approach is then the
    /// same chunk wherever on the table it starts, where absolute targets tie each chunk to
    /// the positions the demos happened to visit. Orientation and gripper stay absolute.
    #[serde(default)]
    pub action_relative: bool,
    /// What the U-Net is trained to predict: the added noise (`epsilon`, the paper's) or the
    /// clean chunk (`sample`, LeRobot's other `prediction_type`).
    #[serde(default)]
    pub prediction: Prediction,
    /// The image encoders' trunk: the paper's ResNet-18 or a shallow conv net (this CPU's).
    #[serde(default)]
    pub encoder: Backbone,
    /// The shallow trunk's first width (its last is twice that).
    #[serde(default = "default_encoder_width")]
    pub encoder_width: i64,
    /// How many of the `To` observations' images are encoded, the newest ones (0: all, the
    /// paper's). With fewer, the state keeps all `To` steps (the motion) and the encoders
    /// run on fewer images: 1 of 2 halves their cost.
    #[serde(default)]
    pub image_obs_steps: i64,
    /// A waypoint head: from the observation (state + image features) the model predicts
    /// where the TCP will be at the episode's next gripper event (the next close or open of
    /// the recorded gripper command; after the last one, the episode's last pose), relative
    /// to the TCP, and the U-Net is conditioned on that prediction. Trained with its own
    /// squared error beside the diffusion loss. The label comes from the recorded
    /// proprioception and gripper commands, which a real rig's episodes hold as well: the
    /// images must say where the grasp will be, at every step, not only through the chunk's
    /// first centimetres.
    #[serde(default)]
    pub waypoint: bool,
    /// The waypoint loss's weight beside the diffusion loss (positions in units of
    /// [`WAYPOINT_SCALE`]).
    #[serde(default = "default_waypoint_weight")]
    pub waypoint_weight: f64,
    /// Leave the TCP's x and y out of what the model sees (the state's first two values,
    /// zeroed after normalisation, every observed step): with `action_relative` chunks and the
    /// waypoint head, where to go in the table plane must then come from the images, as it
    /// must on a table the demos did not cover; height, orientation and the gripper stay.
    /// (With them, a policy can follow the demos' motion from home instead of looking.)
    #[serde(default)]
    pub mask_state_xy: bool,
}

fn default_encoder_width() -> i64 {
    16
}

fn default_waypoint_weight() -> f64 {
    1.0
}

/// Waypoints (metres, relative to the TCP) are divided by this before the head sees them.
pub const WAYPOINT_SCALE: f64 = 0.2;

/// The action a policy outputs, taken from the episodes' recorded `action` dictionary.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ActionSpace {
    /// The paper's: the end-effector target position (3) + orientation as an axis-angle
    /// vector (3) + the gripper position (1) (`cartesian_position`, `gripper_position`).
    #[default]
    EefAxisAngle,
    /// DROID's: the end-effector velocity (3 linear + 3 angular, in [-1, 1]) + the gripper
    /// position (`cartesian_velocity`, `gripper_position`).
    CartesianVelocity,
}

impl DiffusionConfig {
    /// The paper's model: two shoulder cameras at 128x128 with a 90% crop, end-effector pose
    /// (3 + quaternion 4) as state, 7-d actions, To 2, Tp 16, Ta 8, U-Net 256/512/1024, kernel
    /// 5, 8 groups, step embedding 256, FiLM, 100 training steps, DDIM 16.
    pub fn paper_dp() -> DiffusionConfig {
        DiffusionConfig {
            cameras: vec!["ext1".into(), "ext2".into()],
            image_size: 128,
            crop_size: 115,
            keypoints: 32,
            state_dim: 7,
            action_dim: 7,
            n_obs_steps: 2,
            horizon: 16,
            n_action_steps: 8,
            down_dims: vec![256, 512, 1024],
            kernel_size: 5,
            n_groups: 8,
            step_embed_dim: 256,
            film_scale: true,
            train_steps: 100,
            inference_steps: 16,
            clip: Some(1.0),
            action_space: ActionSpace::EefAxisAngle,
            scene_state: false,
            gripper_state: false,
            scene_yaw: false,
            scene_relative: false,
            action_relative: false,
            prediction: Prediction::Epsilon,
            encoder: Backbone::Resnet18,
            encoder_width: default_encoder_width(),
            image_obs_steps: 0,
            waypoint: false,
            waypoint_weight: default_waypoint_weight(),
            mask_state_xy: false,
        }
    }

    /// For this 2-core CPU: one camera at 64x64, a U-Net of 64/128/256, step embedding 64;
    /// the state is the pose and the gripper's opening (8).
    pub fn small() -> DiffusionConfig {
        DiffusionConfig {
            cameras: vec!["ext1".into()],
            image_size: 64,
            crop_size: 58,
            down_dims: vec![64, 128, 256],
            step_embed_dim: 64,
            state_dim: 8,
            gripper_state: true,
            ..DiffusionConfig::paper_dp()
        }
    }

    /// Low-dimensional only, for this CPU: no cameras; the state is the end-effector pose,
    /// the gripper's opening and the sim scene's object and receptacle positions (14); U-Net
    /// 64/128/256.
    pub fn small_lowdim() -> DiffusionConfig {
        DiffusionConfig { cameras: vec![], state_dim: 7 + 1 + 6, scene_state: true, ..DiffusionConfig::small() }
    }

    /// Pixels and proprioception for this CPU, what a real rig records and nothing else: the
    /// wrist camera and `ext1` at 64x64 (random 58x58 crops in training), each through a
    /// shallow conv trunk (16/32/32 channels, a 15x15 map) + 32-keypoint spatial softmax;
    /// the state is the end-effector pose and the gripper's opening (8); U-Net 32/64/128,
    /// step embedding 32; chunk positions relative to the TCP; sample prediction; the images of
    /// the newest observation only (the state keeps both).
    pub fn small_vision() -> DiffusionConfig {
        DiffusionConfig {
            cameras: vec!["wrist".into(), "ext1".into()],
            image_size: 64,
            crop_size: 58,
            encoder: Backbone::Shallow,
            encoder_width: 16,
            down_dims: vec![32, 64, 128],
            step_embed_dim: 32,
            action_relative: true,
            prediction: Prediction::Sample,
            image_obs_steps: 1,
            ..DiffusionConfig::small()
        }
    }

    /// The inputs this config observes that only a simulator has (a real rig records camera
    /// images and proprioception only); empty for a policy a real rig can feed.
    pub fn sim_only_inputs(&self) -> Vec<&'static str> {
        let mut v = Vec::new();
        if self.scene_state {
            v.push("scene_state (the sim scene's object and receptacle positions)");
        }
        if self.scene_yaw {
            v.push("scene_yaw (the sim scene's object yaw)");
        }
        v
    }

    /// What the policy observes, named: `camera:<id>` per camera, the proprioception, and any
    /// sim-only input.
    pub fn observes(&self) -> Vec<String> {
        let mut v: Vec<String> = self.cameras.iter().map(|c| format!("camera:{c}")).collect();
        v.push("eef_pose".into());
        if self.gripper_state {
            v.push("gripper_position".into());
        }
        if self.scene_state {
            v.push("sim:scene_positions".into());
        }
        if self.scene_yaw {
            v.push("sim:scene_yaw".into());
        }
        v
    }

    /// The state's width the data gives this config (pose 7, + 1 with the gripper, + 6 with
    /// the scene's positions).
    pub fn data_state_dim(&self) -> i64 {
        7 + i64::from(self.gripper_state) + i64::from(self.scene_state) * (6 + 2 * i64::from(self.scene_yaw))
    }

    /// Width of the global conditioning: To x state + the encoded steps x 2 x keypoints per
    /// camera (+ 3, the predicted waypoint, with `waypoint`).
    pub fn global_cond_dim(&self) -> i64 {
        self.observation_dim() + 3 * i64::from(self.waypoint)
    }

    /// Width of the encoded observation (what the waypoint head reads).
    pub fn observation_dim(&self) -> i64 {
        self.n_obs_steps * self.state_dim + self.image_steps() * 2 * self.keypoints * self.cameras.len() as i64
    }

    /// The observations whose images are encoded (the newest ones).
    pub fn image_steps(&self) -> i64 {
        if self.image_obs_steps <= 0 || self.image_obs_steps > self.n_obs_steps {
            self.n_obs_steps
        } else {
            self.image_obs_steps
        }
    }

    fn unet(&self) -> UnetConfig {
        UnetConfig {
            action_dim: self.action_dim,
            global_cond_dim: self.global_cond_dim(),
            down_dims: self.down_dims.clone(),
            kernel_size: self.kernel_size,
            n_groups: self.n_groups,
            step_embed_dim: self.step_embed_dim,
            film_scale: self.film_scale,
        }
    }
}

/// torchvision's CenterCrop offset: `int(round((size - crop) / 2))`, Python's round (half to
/// even), so a crop an odd number of pixels smaller starts where LeRobot's does.
pub fn centre_offset(size: i64, crop: i64) -> i64 {
    let d = size - crop;
    let half = d / 2;
    if d % 2 == 1 && half % 2 == 1 { half + 1 } else { half }
}

/// What a policy's input must look like, when it does not.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum PolicyError {
    #[error("{what}: expected shape {want:?}, got {got:?}")]
    Shape { what: String, want: Vec<i64>, got: Vec<i64> },
    #[error("{given} camera image tensors for {wanted} cameras")]
    Cameras { given: usize, wanted: usize },
    #[error(transparent)]
    Schedule(#[from] ScheduleError),
}

/// A sampled chunk and the stages it went through.
#[derive(Debug)]
pub struct Trace {
    /// Per camera (B, To, features).
    pub features: Vec<Tensor>,
    /// The waypoint head's prediction (B, 3), metres relative to the TCP (with `waypoint`).
    pub waypoint: Option<Tensor>,
    pub global_cond: Tensor,
    /// The U-Net's noise estimate at the first and the last DDIM timestep (with the timestep).
    pub eps_first: (i64, Tensor),
    pub eps_last: (i64, Tensor),
    /// (B, Tp, action_dim), normalised.
    pub chunk: Tensor,
}

/// The model with its weights (in the `VarStore` it was made in).
#[derive(Debug)]
pub struct DiffusionPolicy {
    cfg: DiffusionConfig,
    encoders: Vec<RgbEncoder>,
    waypoint: Option<WaypointHead>,
    unet: ConditionalUnet1d,
    schedule: NoiseSchedule,
    ddim: Ddim,
}

/// Observation -> the next gripper event's TCP position relative to the TCP, in units of
/// [`WAYPOINT_SCALE`]: Linear + ReLU + Linear.
#[derive(Debug)]
struct WaypointHead {
    hidden: nn::Linear,
    out: nn::Linear,
}

impl WaypointHead {
    const HIDDEN: i64 = 128;

    fn new(vs: nn::Path<'_>, input: i64) -> WaypointHead {
        WaypointHead {
            hidden: nn::linear(&vs / "hidden", input, Self::HIDDEN, Default::default()),
            out: nn::linear(&vs / "out", Self::HIDDEN, 3, Default::default()),
        }
    }

    fn forward(&self, obs: &Tensor) -> Tensor {
        obs.apply(&self.hidden).relu().apply(&self.out)
    }
}

impl DiffusionPolicy {
    /// LeRobot's names: `rgb_encoder.<k>.*` per camera, `unet.*`.
    pub fn new(vs: nn::Path<'_>, cfg: DiffusionConfig) -> Result<DiffusionPolicy, PolicyError> {
        let encoders = (0..cfg.cameras.len())
            .map(|k| {
                RgbEncoder::with_backbone(
                    &vs / "rgb_encoder" / k.to_string(),
                    cfg.keypoints,
                    cfg.encoder,
                    cfg.encoder_width,
                )
            })
            .collect();
        let waypoint = cfg.waypoint.then(|| WaypointHead::new(&vs / "waypoint", cfg.observation_dim()));
        let unet = ConditionalUnet1d::new(&vs / "unet", &cfg.unet());
        let schedule = NoiseSchedule::squared_cosine(cfg.train_steps)?;
        let ddim = Ddim::new(schedule.clone(), cfg.inference_steps, cfg.clip)?.predicting(cfg.prediction);
        Ok(DiffusionPolicy { cfg, encoders, waypoint, unet, schedule, ddim })
    }

    pub fn config(&self) -> &DiffusionConfig {
        &self.cfg
    }

    /// Samples with `n` DDIM steps instead of the checkpoint's (the same network; fewer,
    /// larger steps through the same noise schedule). Refused when the schedule cannot
    /// take them (0, or more than its training steps).
    pub fn set_inference_steps(&mut self, n: usize) -> Result<(), PolicyError> {
        self.ddim = Ddim::new(self.schedule.clone(), n, self.cfg.clip)?.predicting(self.cfg.prediction);
        self.cfg.inference_steps = n;
        Ok(())
    }

    fn expect(what: &str, t: &Tensor, want: &[i64]) -> Result<(), PolicyError> {
        let got = t.size();
        let ok = got.len() == want.len() && got.iter().zip(want).all(|(g, w)| *w < 0 || g == w);
        if ok { Ok(()) } else { Err(PolicyError::Shape { what: what.to_owned(), want: want.to_vec(), got }) }
    }

    /// Crops (B*, 3, S, S) images to `crop_size`: at random offsets in training (one per
    /// image), centred otherwise.
    fn crop(&self, images: &Tensor, train: bool) -> Tensor {
        let (size, crop) = (self.cfg.image_size, self.cfg.crop_size);
        if crop >= size {
            return images.shallow_clone();
        }
        if !train {
            let off = centre_offset(size, crop);
            return images.narrow(2, off, crop).narrow(3, off, crop);
        }
        let n = images.size()[0];
        let offs = Tensor::randint(size - crop + 1, [n, 2], (Kind::Int64, images.device()));
        let crops: Vec<Tensor> = (0..n)
            .map(|i| {
                let (r, c) = (offs.int64_value(&[i, 0]), offs.int64_value(&[i, 1]));
                images.get(i).narrow(1, r, crop).narrow(2, c, crop)
            })
            .collect();
        Tensor::stack(&crops, 0)
    }

    /// Each camera's features (B, To, 2 x keypoints), its images (B, To, 3, S, S) cropped
    /// (random crops in training, centred otherwise).
    pub fn encode(&self, images: &[Tensor], b: i64, train: bool) -> Result<Vec<Tensor>, PolicyError> {
        let c = &self.cfg;
        if images.len() != self.encoders.len() {
            return Err(PolicyError::Cameras { given: images.len(), wanted: self.encoders.len() });
        }
        let mut features = Vec::with_capacity(images.len());
        for (k, (enc, img)) in self.encoders.iter().zip(images).enumerate() {
            Self::expect(
                &format!("observation.images.{}", c.cameras[k]),
                img,
                &[b, c.n_obs_steps, 3, c.image_size, c.image_size],
            )?;
            let k = c.image_steps();
            let newest = img.narrow(1, c.n_obs_steps - k, k);
            let flat = newest.reshape([b * k, 3, c.image_size, c.image_size]);
            features.push(enc.forward(&self.crop(&flat, train)).reshape([b, k, -1]));
        }
        Ok(features)
    }

    /// The observation as the U-Net's conditioning: per step [state, camera 0's features, ...],
    /// the `To` steps concatenated, then with `waypoint` the head's prediction (in units of
    /// [`WAYPOINT_SCALE`]): (B, global_cond_dim), and that prediction.
    pub fn global_cond(
        &self,
        images: &[Tensor],
        state: &Tensor,
        train: bool,
    ) -> Result<(Tensor, Option<Tensor>), PolicyError> {
        let c = &self.cfg;
        Self::expect("observation.state", state, &[-1, c.n_obs_steps, c.state_dim])?;
        let features = self.encode(images, state.size()[0], train)?;
        Ok(self.with_waypoint(Self::cond_of(&self.seen_state(state), &features)))
    }

    fn with_waypoint(&self, obs: Tensor) -> (Tensor, Option<Tensor>) {
        match &self.waypoint {
            Some(head) => {
                let w = head.forward(&obs);
                (Tensor::cat(&[obs, w.shallow_clone()], -1), Some(w))
            }
            None => (obs, None),
        }
    }

    /// The state as the model sees it: with `mask_state_xy`, the TCP's x and y zeroed.
    fn seen_state(&self, state: &Tensor) -> Tensor {
        if !self.cfg.mask_state_xy {
            return state.shallow_clone();
        }
        let keep = Tensor::ones([self.cfg.state_dim], (state.kind(), state.device()));
        let _ = keep.narrow(0, 0, 2).fill_(0.0);
        state * keep
    }

    fn cond_of(state: &Tensor, features: &[Tensor]) -> Tensor {
        if let Some(f) = features.first()
            && f.size()[1] != state.size()[1]
        {
            // Fewer image steps than states: all states, then each camera's features.
            let parts: Vec<Tensor> =
                std::iter::once(state.flatten(1, -1)).chain(features.iter().map(|f| f.flatten(1, -1))).collect();
            return Tensor::cat(&parts, -1);
        }
        let per_step: Vec<Tensor> =
            std::iter::once(state.shallow_clone()).chain(features.iter().map(Tensor::shallow_clone)).collect();
        Tensor::cat(&per_step, -1).flatten(1, -1)
    }

    /// Training's loss for a batch: the noise added at timesteps `t` (B) to the action chunk
    /// (B, Tp, action_dim), or with `prediction = "sample"` the chunk itself, predicted by the
    /// U-Net from the noisy chunk; mean squared error. With `waypoint`, plus `waypoint_weight`
    /// x the head's squared error against `waypoint` (B, 3), metres relative to the TCP (the
    /// data's [`crate::data::waypoints`]). `train`: random crops (validation takes the centre
    /// ones).
    #[allow(clippy::too_many_arguments)]
    pub fn loss(
        &self,
        images: &[Tensor],
        state: &Tensor,
        actions: &Tensor,
        waypoint: Option<&Tensor>,
        noise: &Tensor,
        t: &[i64],
        train: bool,
    ) -> Result<Tensor, PolicyError> {
        let c = &self.cfg;
        Self::expect("action", actions, &[-1, c.horizon, c.action_dim])?;
        let (cond, predicted) = self.global_cond(images, state, train)?;
        let noisy = self.schedule.add_noise(actions, noise, t)?;
        let pred = self.unet.forward(&noisy, &Tensor::from_slice(t).to_device(actions.device()), &cond);
        let target = match c.prediction {
            Prediction::Epsilon => noise,
            Prediction::Sample => actions,
        };
        let loss = pred.mse_loss(target, tch::Reduction::Mean);
        match (predicted, waypoint) {
            (Some(p), Some(w)) => {
                Self::expect("waypoint", w, &[actions.size()[0], 3])?;
                let w = w.to_kind(p.kind()) / WAYPOINT_SCALE;
                Ok(loss + p.mse_loss(&w, tch::Reduction::Mean) * c.waypoint_weight)
            }
            (Some(_), None) => Err(PolicyError::Shape {
                what: "waypoint (the config has a waypoint head)".into(),
                want: vec![-1, 3],
                got: vec![],
            }),
            (None, _) => Ok(loss),
        }
    }

    /// The waypoint head's prediction (B, 3), metres relative to the TCP; None without one.
    pub fn predict_waypoint(&self, images: &[Tensor], state: &Tensor) -> Result<Option<Tensor>, PolicyError> {
        Ok(self.global_cond(images, state, false)?.1.map(|w| w * WAYPOINT_SCALE))
    }

    /// One action chunk (B, Tp, action_dim), normalised, from the initial `noise` (DDIM,
    /// deterministic given it). The executed actions are [`DiffusionPolicy::executed`].
    pub fn sample(&self, images: &[Tensor], state: &Tensor, noise: &Tensor) -> Result<Tensor, PolicyError> {
        Ok(self.sample_traced(images, state, noise)?.chunk)
    }

    /// [`DiffusionPolicy::sample`] with what happened on the way (to compare stage by stage
    /// with a reference implementation).
    pub fn sample_traced(&self, images: &[Tensor], state: &Tensor, noise: &Tensor) -> Result<Trace, PolicyError> {
        let c = &self.cfg;
        Self::expect("noise", noise, &[-1, c.horizon, c.action_dim])?;
        Self::expect("observation.state", state, &[noise.size()[0], c.n_obs_steps, c.state_dim])?;
        let features = self.encode(images, noise.size()[0], false)?;
        let (global_cond, waypoint) = self.with_waypoint(Self::cond_of(&self.seen_state(state), &features));
        let waypoint = waypoint.map(|w| w * WAYPOINT_SCALE);
        let mut first: Option<(i64, Tensor)> = None;
        let mut last: Option<(i64, Tensor)> = None;
        let chunk = self.ddim.sample(noise, |x, t| {
            let e = self.denoise(x, t, &global_cond);
            if first.is_none() {
                first = Some((t, e.shallow_clone()));
            }
            last = Some((t, e.shallow_clone()));
            e
        })?;
        let (eps_first, eps_last) = (first.expect("DDIM takes >= 1 step"), last.expect("DDIM takes >= 1 step"));
        Ok(Trace { features, waypoint, global_cond, eps_first, eps_last, chunk })
    }

    /// [`DiffusionPolicy::sample`] guided toward the prefix in `guide` (real-time chunking,
    /// [`crate::rtc`]): the image encoders run once, the U-Net once per DDIM step plus its
    /// vector-Jacobian product.
    pub fn sample_guided(
        &self,
        images: &[Tensor],
        state: &Tensor,
        noise: &Tensor,
        guide: &crate::rtc::Guide,
    ) -> Result<Tensor, PolicyError> {
        let c = &self.cfg;
        Self::expect("noise", noise, &[-1, c.horizon, c.action_dim])?;
        Self::expect("observation.state", state, &[noise.size()[0], c.n_obs_steps, c.state_dim])?;
        Self::expect("the guidance target", &guide.target, &[noise.size()[0], c.horizon, c.action_dim])?;
        let features = self.encode(images, noise.size()[0], false)?;
        let (global_cond, _) = self.with_waypoint(Self::cond_of(&self.seen_state(state), &features));
        let global_cond = global_cond.detach();
        Ok(crate::rtc::sample_guided(&self.ddim, noise, guide, |x, t| self.denoise(x, t, &global_cond))?)
    }

    /// The U-Net's noise estimate for `x` at timestep `t` (one DDIM step's network call).
    pub fn denoise(&self, x: &Tensor, t: i64, global_cond: &Tensor) -> Tensor {
        self.unet.forward(x, &Tensor::full([x.size()[0]], t, (Kind::Int64, x.device())), global_cond)
    }

    /// The `Ta` steps a chunk executes: from the last observed step on.
    pub fn executed(&self, chunk: &Tensor) -> Tensor {
        chunk.narrow(1, self.cfg.n_obs_steps - 1, self.cfg.n_action_steps)
    }
}

/// A model small enough for tests (32x32 images, 8 keypoints, a 16/32 U-Net): this crate's
/// and the policy server's.
impl DiffusionConfig {
    pub fn tiny() -> DiffusionConfig {
        DiffusionConfig {
            image_size: 32,
            crop_size: 28,
            keypoints: 8,
            down_dims: vec![16, 32],
            step_embed_dim: 16,
            state_dim: 7,
            gripper_state: false,
            ..DiffusionConfig::small()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::Device;
    use tch::nn::OptimizerConfig;

    fn batch(cfg: &DiffusionConfig, b: i64) -> (Vec<Tensor>, Tensor, Tensor) {
        let images = cfg
            .cameras
            .iter()
            .map(|_| Tensor::rand([b, cfg.n_obs_steps, 3, cfg.image_size, cfg.image_size], (Kind::Float, Device::Cpu)))
            .collect();
        let state = Tensor::rand([b, cfg.n_obs_steps, cfg.state_dim], (Kind::Float, Device::Cpu)) * 2.0 - 1.0;
        let actions = Tensor::rand([b, cfg.horizon, cfg.action_dim], (Kind::Float, Device::Cpu)) * 2.0 - 1.0;
        (images, state, actions)
    }

    #[test]
    fn presets_have_the_papers_numbers() {
        let p = DiffusionConfig::paper_dp();
        assert_eq!((p.n_obs_steps, p.horizon, p.n_action_steps), (2, 16, 8));
        assert_eq!(p.down_dims, [256, 512, 1024]);
        assert_eq!(p.global_cond_dim(), 2 * (7 + 2 * 64));
        assert_eq!(p.crop_size as f64 / p.image_size as f64, 115.0 / 128.0);
        assert_eq!(DiffusionConfig::small().global_cond_dim(), 2 * (8 + 64));
        assert_eq!(DiffusionConfig::small_vision().global_cond_dim(), 2 * 8 + 2 * 64);
        assert_eq!(DiffusionConfig::small_lowdim().data_state_dim(), 14);
        assert_eq!(DiffusionConfig::paper_dp().data_state_dim(), 7);
    }

    /// torchvision rounds half to even: 13 -> 6 (128 -> 115), 7 -> 4, 5 -> 2, 8 -> 4.
    #[test]
    fn centre_crops_start_where_torchvisions_do() {
        assert_eq!([(128, 115), (64, 57), (64, 59), (64, 56)].map(|(s, c)| centre_offset(s, c)), [6, 4, 2, 4]);
    }

    /// Sampling is deterministic given the initial noise, has the chunk's shape, stays inside
    /// [-1, 1] (clipping), and executes Ta steps from the last observed one.
    #[test]
    fn a_chunk_is_sampled_deterministically_from_its_noise() {
        tch::manual_seed(3);
        let cfg = DiffusionConfig::tiny();
        let vs = nn::VarStore::new(Device::Cpu);
        let policy = DiffusionPolicy::new(vs.root(), cfg.clone()).unwrap();
        let (images, state, _) = batch(&cfg, 2);
        let noise = Tensor::randn([2, cfg.horizon, cfg.action_dim], (Kind::Float, Device::Cpu));
        let a = tch::no_grad(|| policy.sample(&images, &state, &noise)).unwrap();
        let b = tch::no_grad(|| policy.sample(&images, &state, &noise)).unwrap();
        assert_eq!(a.size(), [2, 16, 7]);
        assert_eq!((&a - &b).abs().max().double_value(&[]), 0.0);
        assert!(a.abs().max().double_value(&[]) <= 1.0 + 1e-6);
        assert_eq!(policy.executed(&a).size(), [2, 8, 7]);
        // Wrong shapes are named, not panics.
        let err = policy.sample(&images, &state.narrow(1, 0, 1), &noise).unwrap_err();
        assert!(err.to_string().starts_with("observation.state: expected shape [2, 2, 7], got [2, 1, 7]"), "{err}");
        assert_eq!(policy.sample(&[], &state, &noise).unwrap_err(), PolicyError::Cameras { given: 0, wanted: 1 });
    }

    /// Fewer DDIM steps: the same policy sampling through fewer, larger steps; back to the
    /// checkpoint's count it samples exactly as before; 0 and more than the schedule's
    /// training steps are refused by name.
    #[test]
    fn the_ddim_step_count_can_be_changed_and_back() {
        tch::manual_seed(5);
        let cfg = DiffusionConfig::tiny();
        let vs = nn::VarStore::new(Device::Cpu);
        let mut policy = DiffusionPolicy::new(vs.root(), cfg.clone()).unwrap();
        let (images, state, _) = batch(&cfg, 1);
        let noise = Tensor::randn([1, cfg.horizon, cfg.action_dim], (Kind::Float, Device::Cpu));
        let own = cfg.inference_steps;
        let a = tch::no_grad(|| policy.sample(&images, &state, &noise)).unwrap();
        policy.set_inference_steps(4).unwrap();
        assert_eq!(policy.config().inference_steps, 4);
        let four = tch::no_grad(|| policy.sample(&images, &state, &noise)).unwrap();
        assert!((&a - &four).abs().max().double_value(&[]) > 0.0, "4 steps sample another chunk");
        policy.set_inference_steps(own).unwrap();
        let again = tch::no_grad(|| policy.sample(&images, &state, &noise)).unwrap();
        assert_eq!((&a - &again).abs().max().double_value(&[]), 0.0);
        for bad in [0, cfg.train_steps + 1] {
            let e = policy.set_inference_steps(bad).unwrap_err().to_string();
            assert!(e.contains(&bad.to_string()), "{e}");
        }
        assert_eq!(policy.config().inference_steps, own, "a refused count changes nothing");
    }

    /// With `image_obs_steps = 1` only the newest observation's images are encoded: changing
    /// the older image leaves the chunk as it was, changing the newest does not; the state's
    /// older step still counts. The conditioning is To x state + one step of features.
    #[test]
    fn only_the_newest_images_are_encoded_when_asked() {
        tch::manual_seed(4);
        let cfg = DiffusionConfig { image_obs_steps: 1, encoder: Backbone::Shallow, ..DiffusionConfig::tiny() };
        assert_eq!(cfg.global_cond_dim(), 2 * 7 + 2 * 8);
        let vs = nn::VarStore::new(Device::Cpu);
        let policy = DiffusionPolicy::new(vs.root(), cfg.clone()).unwrap();
        let (images, state, _) = batch(&cfg, 1);
        let noise = Tensor::randn([1, cfg.horizon, cfg.action_dim], (Kind::Float, Device::Cpu));
        let chunk = |images: &[Tensor], state: &Tensor| tch::no_grad(|| policy.sample(images, state, &noise)).unwrap();
        let base = chunk(&images, &state);
        let older = images[0].copy();
        let _ = older.narrow(1, 0, 1).fill_(0.5);
        assert_eq!((chunk(&[older], &state) - &base).abs().max().double_value(&[]), 0.0);
        let newest = images[0].copy();
        let _ = newest.narrow(1, 1, 1).fill_(0.5);
        assert!((chunk(&[newest], &state) - &base).abs().max().double_value(&[]) > 0.0);
        let moved = state.copy();
        let _ = moved.narrow(1, 0, 1).fill_(0.9);
        assert!((chunk(&images, &moved) - &base).abs().max().double_value(&[]) > 0.0);
    }

    /// With a waypoint head the conditioning grows by its 3 values, the loss asks for the
    /// label (named when missing), and training on a fixed batch brings the head's prediction
    /// to the label; a sampled chunk's trace carries the prediction.
    #[test]
    fn the_waypoint_head_learns_its_label_and_conditions_the_chunk() {
        tch::manual_seed(6);
        let cfg = DiffusionConfig { waypoint: true, encoder: Backbone::Shallow, ..DiffusionConfig::tiny() };
        assert_eq!(cfg.global_cond_dim(), DiffusionConfig::tiny().global_cond_dim() + 3);
        let vs = nn::VarStore::new(Device::Cpu);
        let policy = DiffusionPolicy::new(vs.root(), cfg.clone()).unwrap();
        assert!(vs.variables().contains_key("waypoint.out.weight"));
        let mut opt = nn::Adam::default().build(&vs, 3e-3).unwrap();
        let (images, state, actions) = batch(&cfg, 4);
        let label =
            Tensor::from_slice(&[0.1f32, -0.05, -0.2, 0.0, 0.1, -0.1, -0.1, 0.0, -0.3, 0.05, 0.05, 0.0]).view([4, 3]);
        let noise = Tensor::randn([4, cfg.horizon, cfg.action_dim], (Kind::Float, Device::Cpu));
        let t = [5i64, 30, 60, 95];
        let err = |p: &DiffusionPolicy| {
            let w = tch::no_grad(|| p.predict_waypoint(&images, &state)).unwrap().unwrap();
            (w - &label).abs().max().double_value(&[])
        };
        let before = err(&policy);
        let missing = policy.loss(&images, &state, &actions, None, &noise, &t, true).unwrap_err();
        assert!(missing.to_string().starts_with("waypoint"), "{missing}");
        for _ in 0..150 {
            let loss = policy.loss(&images, &state, &actions, Some(&label), &noise, &t, true).unwrap();
            opt.backward_step(&loss);
        }
        let after = err(&policy);
        assert!(after < 0.2 * before && after < 0.02, "waypoint error {before:.3} -> {after:.3} m");
        let trace = tch::no_grad(|| policy.sample_traced(&images, &state, &noise)).unwrap();
        assert_eq!(trace.waypoint.as_ref().unwrap().size(), [4, 3]);
        assert_eq!(trace.global_cond.size(), [4, cfg.global_cond_dim()]);
    }

    /// With `mask_state_xy` the TCP's x and y do not reach the model (any value gives the
    /// same chunk) while its height does.
    #[test]
    fn a_masked_state_hides_the_tcps_x_and_y() {
        tch::manual_seed(7);
        let cfg = DiffusionConfig { mask_state_xy: true, ..DiffusionConfig::tiny() };
        let vs = nn::VarStore::new(Device::Cpu);
        let policy = DiffusionPolicy::new(vs.root(), cfg.clone()).unwrap();
        let (images, state, _) = batch(&cfg, 1);
        let noise = Tensor::randn([1, cfg.horizon, cfg.action_dim], (Kind::Float, Device::Cpu));
        let chunk = |state: &Tensor| tch::no_grad(|| policy.sample(&images, state, &noise)).unwrap();
        let base = chunk(&state);
        let moved = state.copy();
        let _ = moved.narrow(2, 0, 2).fill_(0.7);
        assert_eq!((chunk(&moved) - &base).abs().max().double_value(&[]), 0.0);
        let lifted = state.copy();
        let _ = lifted.narrow(2, 2, 1).fill_(0.7);
        assert!((chunk(&lifted) - &base).abs().max().double_value(&[]) > 0.0);
    }

    /// The model learns: Adam on one fixed batch drives the noise-prediction loss down.
    #[test]
    fn training_steps_lower_the_loss_on_a_fixed_batch() {
        tch::manual_seed(5);
        let cfg = DiffusionConfig::tiny();
        let vs = nn::VarStore::new(Device::Cpu);
        let policy = DiffusionPolicy::new(vs.root(), cfg.clone()).unwrap();
        let mut opt = nn::Adam { beta1: 0.95, beta2: 0.999, wd: 1e-6, ..Default::default() }.build(&vs, 1e-3).unwrap();
        let (images, state, actions) = batch(&cfg, 4);
        let noise = Tensor::randn([4, cfg.horizon, cfg.action_dim], (Kind::Float, Device::Cpu));
        let t = [5i64, 30, 60, 95];
        let first = policy.loss(&images, &state, &actions, None, &noise, &t, true).unwrap().double_value(&[]);
        let mut last = first;
        for _ in 0..40 {
            let loss = policy.loss(&images, &state, &actions, None, &noise, &t, true).unwrap();
            opt.backward_step(&loss);
            last = loss.double_value(&[]);
        }
        assert!(last < 0.5 * first, "loss {first:.4} -> {last:.4}");
    }
}
