//! The trainer behind `labrig train`: the paper's Diffusion Policy fitted to labrig episodes,
//! with the co-training sampler, Adam + cosine schedule with warm-up, an EMA of the weights,
//! a held-out validation split, checkpoints every N steps and `--resume`.
//!
//! One run directory holds `checkpoints/step_<n>/` (see [`crate::checkpoint`]),
//! `checkpoints/last` (the name of the newest), `loss.csv` (step, train loss, validation loss,
//! learning rate), `loss.png` and `run.json` (the figures of the run).

use crate::checkpoint::{self, CheckpointError, CheckpointMeta};
use crate::data::{DataError, EpisodeTensors, load_episode};
use crate::normalize::{MinMax, NormalizeError};
use crate::policy::{DiffusionConfig, DiffusionPolicy, PolicyError};
use crate::sampler::{CotrainSampler, Draw, SamplerError};
use crate::window::windows;
use serde::{Deserialize, Serialize};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;
use tch::nn::{self, OptimizerConfig};
use tch::{Device, Kind, Tensor};

/// The optimisation's numbers (the paper's / LeRobot's defaults).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TrainConfig {
    pub batch_size: usize,
    pub lr: f64,
    pub betas: [f64; 2],
    pub weight_decay: f64,
    /// Linear warm-up, capped at a tenth of the run.
    pub warmup_steps: usize,
    pub grad_clip_norm: f64,
    /// EMA decay = 1 - (1 + step)^-power, at most `ema_max` (diffusion_policy's EMAModel).
    pub ema_power: f64,
    pub ema_max: f64,
    /// The fraction of the target episodes held out for validation (at least one episode).
    pub val_fraction: f64,
    pub val_every: usize,
    /// Validation samples (a fixed set, fixed noise and timesteps).
    pub val_samples: usize,
    pub checkpoint_every: usize,
    pub seed: u64,
    /// Leave out, as labels, the recorded mistake of every missed grasp in the episodes
    /// ([`crate::data::missed_grasps`]: the fingers shut on nothing before the arm rose): the
    /// windows whose action rows include its descent or its close. The recovery after it (the
    /// arm rising, the fingers opening, the new approach) stays, and waypoints skip the miss.
    /// For demos with deliberate misses (`labrig demo --expert-miss-fraction`); needs
    /// `gripper_state`.
    pub skip_missed_grasps: bool,
}

impl Default for TrainConfig {
    fn default() -> TrainConfig {
        TrainConfig {
            batch_size: 128,
            lr: 1e-4,
            betas: [0.95, 0.999],
            weight_decay: 1e-6,
            warmup_steps: 500,
            grad_clip_norm: 10.0,
            ema_power: 0.75,
            ema_max: 0.9999,
            val_fraction: 0.1,
            val_every: 250,
            val_samples: 256,
            checkpoint_every: 1000,
            seed: 0,
            skip_missed_grasps: false,
        }
    }
}

/// A model and how to train it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Preset {
    pub model: DiffusionConfig,
    #[serde(default)]
    pub train: TrainConfig,
}

impl Preset {
    pub const NAMES: [&str; 5] = ["paper_dp", "small", "small_vision", "small_vision_recover", "small_lowdim"];

    pub fn named(name: &str) -> Option<Preset> {
        match name {
            "paper_dp" => Some(Preset { model: DiffusionConfig::paper_dp(), train: TrainConfig::default() }),
            "small" => Some(Preset {
                model: DiffusionConfig::small(),
                train: TrainConfig { batch_size: 64, lr: 3e-4, ..TrainConfig::default() },
            }),
            "small_vision" => Some(Preset {
                model: DiffusionConfig::small_vision(),
                train: TrainConfig { batch_size: 128, lr: 1e-3, ..TrainConfig::default() },
            }),
            // The recipe that reached 80% from pixels (issue 32, docs/policy_results.md): the
            // waypoint head, and the missed grasps of demos that miss and recover left out as
            // labels; for `labrig demo --expert-aim-error-m 0.06 --expert-miss-fraction 0.4`.
            "small_vision_recover" => Some(Preset {
                model: DiffusionConfig { waypoint: true, ..DiffusionConfig::small_vision() },
                train: TrainConfig {
                    batch_size: 128,
                    lr: 1e-3,
                    checkpoint_every: 500,
                    val_every: 500,
                    skip_missed_grasps: true,
                    ..TrainConfig::default()
                },
            }),
            "small_lowdim" => Some(Preset {
                model: DiffusionConfig::small_lowdim(),
                train: TrainConfig { batch_size: 64, lr: 1e-3, ..TrainConfig::default() },
            }),
            _ => None,
        }
    }

    /// A preset by name, or a TOML file: `preset = "small"` (the base, default paper_dp) with
    /// `[model]` and `[train]` tables overriding any of its fields.
    pub fn resolve(arg: &str) -> Result<Preset, TrainError> {
        if let Some(p) = Preset::named(arg) {
            return Ok(p);
        }
        let path = Path::new(arg);
        let bad = |reason: String| TrainError::Preset { arg: arg.to_owned(), reason };
        if !path.is_file() {
            return Err(bad(format!("neither a preset ({}) nor a TOML file", Preset::NAMES.join(", "))));
        }
        let text = std::fs::read_to_string(path).map_err(|e| bad(e.to_string()))?;
        let mut over: toml::Table = text.parse().map_err(|e: toml::de::Error| bad(e.to_string()))?;
        let base_name = match over.remove("preset") {
            Some(toml::Value::String(s)) => s,
            None => "paper_dp".to_owned(),
            Some(v) => return Err(bad(format!("`preset` must be a name, not {v}"))),
        };
        let base = Preset::named(&base_name).ok_or_else(|| bad(format!("unknown base preset `{base_name}`")))?;
        let mut merged = toml::Table::try_from(&base).map_err(|e| bad(e.to_string()))?;
        for (section, table) in over {
            let (Some(toml::Value::Table(into)), toml::Value::Table(from)) = (merged.get_mut(&section), table) else {
                return Err(bad(format!("unknown section `{section}` (the sections are [model] and [train])")));
            };
            into.extend(from);
        }
        let p: Preset = toml::Value::Table(merged).try_into().map_err(|e: toml::de::Error| bad(e.to_string()))?;
        if p.model.state_dim != p.model.data_state_dim() {
            return Err(bad(format!(
                "state_dim = {} but the data gives {} (pose 7{}{})",
                p.model.state_dim,
                p.model.data_state_dim(),
                if p.model.gripper_state { " + gripper 1" } else { "" },
                match (p.model.scene_state, p.model.scene_yaw) {
                    (true, true) => " + scene 6 + object yaw 2",
                    (true, false) => " + scene 6",
                    _ => "",
                }
            )));
        }
        let w = p.model.encoder_width;
        if !((1..8).contains(&w) || (w % 8 == 0 && (8..=256).contains(&w))) {
            return Err(bad(format!(
                "encoder_width = {w}: the shallow trunk's GroupNorms take width / 8 groups, so it must be 1..=7 or a multiple of 8 up to 256"
            )));
        }
        if !(0..=p.model.n_obs_steps).contains(&p.model.image_obs_steps) {
            return Err(bad(format!(
                "image_obs_steps = {} must be in 0..={} (n_obs_steps; 0: all)",
                p.model.image_obs_steps, p.model.n_obs_steps
            )));
        }
        if p.model.mask_state_xy && !p.model.action_relative {
            return Err(bad(
                "mask_state_xy hides the TCP's x and y, so the chunk's targets must be relative to it: set action_relative = true".into(),
            ));
        }
        if !(p.model.waypoint_weight.is_finite() && p.model.waypoint_weight >= 0.0) {
            return Err(bad(format!("waypoint_weight = {} must be a finite number >= 0", p.model.waypoint_weight)));
        }
        if p.model.action_relative && p.model.action_space != crate::policy::ActionSpace::EefAxisAngle {
            return Err(bad(format!(
                "action_relative applies to eef_axis_angle targets; {:?} actions are velocities already",
                p.model.action_space
            )));
        }
        Ok(p)
    }
}

/// Why a run could not go on; each names what it is about.
#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    #[error("--preset {arg}: {reason}")]
    Preset { arg: String, reason: String },
    #[error(transparent)]
    Data(#[from] DataError),
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
    #[error(transparent)]
    Policy(#[from] PolicyError),
    #[error(transparent)]
    Sampler(#[from] SamplerError),
    #[error("normaliser statistics: {0}")]
    Normalize(#[from] NormalizeError),
    #[error(transparent)]
    Io(#[from] crate::FileError),
    #[error("{0}")]
    Setup(String),
    #[error(
        "step {step}: {what} is not finite; the step was refused and the run stopped (the last good checkpoint, {last_checkpoint}, is kept). The batch came from {episodes:?}"
    )]
    NotFinite { step: u64, what: &'static str, episodes: Vec<String>, last_checkpoint: String },
    #[error("the checkpoint in {} was made by another model config than --preset's: {reason}", path.display())]
    OtherPreset { path: PathBuf, reason: String },
    #[error(transparent)]
    Torch(#[from] tch::TchError),
}

fn io<'a>(path: &'a Path, what: &'static str) -> impl FnOnce(std::io::Error) -> TrainError + 'a {
    move |source| crate::FileError::at(path, what)(source).into()
}

/// One set of episodes as training samples: every step of every episode, its window's
/// observation and action rows as indices into the set's concatenated tensors.
#[derive(Debug)]
pub struct SampleSet {
    pub uuids: Vec<String>,
    frames: Tensor,
    state: Tensor,
    action: Tensor,
    /// Each row's waypoint in the base frame ([`crate::data::waypoints`]).
    waypoint: Tensor,
    /// The sample of each episode's first step (the arm at its start, where only the
    /// images can say where the object is).
    pub first_samples: Vec<usize>,
    /// With `skip_missed_grasps`: the missed grasps found, and the windows left out for
    /// holding their mistake.
    pub missed_grasps: usize,
    pub mistake_windows: usize,
    /// (samples, To) and (samples, Tp) row indices.
    obs_rows: Vec<i64>,
    action_rows: Vec<i64>,
    episode_of: Vec<usize>,
    n_obs: usize,
    horizon: usize,
    action_relative: bool,
}

/// A batch ready for the model: normalised, images in [0, 1] per camera.
#[derive(Debug)]
pub struct Batch {
    pub images: Vec<Tensor>,
    pub state: Tensor,
    pub action: Tensor,
    /// The next gripper event's TCP position relative to the newest observed TCP (B, 3),
    /// metres: the waypoint head's label.
    pub waypoint: Tensor,
    /// The episodes (uuids) the samples came from.
    pub episodes: Vec<String>,
}

/// Which samples of a correction episode (a policy's rollout in which an operator took over,
/// [`EpisodeTensors::is_correction`]) are trained on; other episodes give every sample.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Corrections {
    /// Every step, the policy's own actions too.
    #[default]
    All,
    /// The windows whose newest observation is an operator's step, or lies at most `before`
    /// steps before one. A window's labels are its Tp recorded actions: near a hand-back they
    /// include the policy's own rows after the operator's, and with `before` > 0 the rows the
    /// policy executed before the takeover (what led into it); 0 keeps those out at the start.
    Operator { before: usize },
}

impl SampleSet {
    pub fn new(episodes: &[EpisodeTensors], cfg: &DiffusionConfig) -> SampleSet {
        SampleSet::selecting(episodes, cfg, Corrections::All, false)
    }

    /// The samples of `episodes`, correction episodes' chosen by `corrections`; with
    /// `skip_missed`, none whose labels hold a missed grasp's mistake
    /// ([`TrainConfig::skip_missed_grasps`]).
    pub fn selecting(
        episodes: &[EpisodeTensors],
        cfg: &DiffusionConfig,
        corrections: Corrections,
        skip_missed: bool,
    ) -> SampleSet {
        let (n_obs, horizon) = (cfg.n_obs_steps as usize, cfg.horizon as usize);
        // LeRobot's drop_n_last_frames: the last steps, whose chunks would be mostly padding,
        // are not sampled.
        let drop_last = (cfg.horizon - cfg.n_action_steps - cfg.n_obs_steps + 1).max(0) as usize;
        let (mut obs_rows, mut action_rows, mut episode_of) = (Vec::new(), Vec::new(), Vec::new());
        let mut first_samples = Vec::new();
        let (mut missed_grasps, mut mistake_windows) = (0, 0);
        let mut waypoints = Vec::with_capacity(episodes.len());
        let mut offset = 0i64;
        for (e, ep) in episodes.iter().enumerate() {
            let keep = ep.len().saturating_sub(drop_last).max(1);
            let operator: Vec<bool> = ep.source.iter().map(|&s| labrig_msgs::rig::Step::is_operator(s)).collect();
            let missed = if skip_missed {
                crate::data::missed_grasps(&ep.state, &ep.action, crate::data::GRIPPER_COLUMN)
            } else {
                Vec::new()
            };
            let mut mistake = vec![false; ep.len()];
            missed.iter().flat_map(|m| m.mistake()).for_each(|k| mistake[k] = true);
            missed_grasps += missed.len();
            let ignore: Vec<usize> = missed.iter().flat_map(|m| [m.close, m.reopen]).collect();
            waypoints.push(crate::data::waypoints(&ep.state, &ep.action, &ignore));
            for w in windows(ep.len(), n_obs, horizon).into_iter().take(keep) {
                if w.actions.iter().any(|&k| mistake[k]) {
                    mistake_windows += 1;
                    continue;
                }
                if w.t == 0 && !ep.is_correction() {
                    first_samples.push(episode_of.len());
                }
                if let Corrections::Operator { before } = corrections
                    && ep.is_correction()
                {
                    let newest = *w.obs.last().expect("To >= 1");
                    let upto = (newest + before).min(operator.len().saturating_sub(1));
                    if !operator[newest..=upto].contains(&true) {
                        continue;
                    }
                }
                obs_rows.extend(w.obs.iter().map(|&i| offset + i as i64));
                action_rows.extend(w.actions.iter().map(|&i| offset + i as i64));
                episode_of.push(e);
            }
            offset += ep.len() as i64;
        }
        let cat = |f: &dyn Fn(&EpisodeTensors) -> Tensor| {
            if episodes.is_empty() {
                Tensor::empty([0], (Kind::Float, Device::Cpu))
            } else {
                Tensor::cat(&episodes.iter().map(f).collect::<Vec<_>>(), 0)
            }
        };
        SampleSet {
            uuids: episodes.iter().map(|e| e.uuid.clone()).collect(),
            frames: cat(&|e| e.frames.shallow_clone()),
            state: cat(&|e| e.state.shallow_clone()),
            action: cat(&|e| e.action.shallow_clone()),
            waypoint: if waypoints.is_empty() {
                Tensor::zeros([0, 3], (Kind::Float, Device::Cpu))
            } else {
                Tensor::cat(&waypoints, 0)
            },
            first_samples,
            missed_grasps,
            mistake_windows,
            obs_rows,
            action_rows,
            episode_of,
            n_obs,
            horizon,
            action_relative: cfg.action_relative,
        }
    }

    /// The windows' actions (B, Tp, action_dim), unnormalised, in the policy's terms: with
    /// `action_relative`, the target positions minus the TCP position at the window's newest
    /// observation (the state's first three values).
    fn actions(&self, idx: &[usize]) -> Tensor {
        let b = idx.len() as i64;
        let act = Self::rows(&self.action_rows, self.horizon, idx);
        let a = self.action.index_select(0, &act).view([b, self.horizon as i64, -1]);
        if !self.action_relative {
            return a;
        }
        let newest = self.state.index_select(0, &self.newest_rows(idx));
        let shift = crate::data::tcp_offset(&newest, a.size()[2], a.kind());
        a - shift
    }

    /// The action rows the normaliser is fitted on: every step's action, or with
    /// `action_relative` every window's relative chunk (the values the model is trained on).
    fn action_rows_for_stats(&self) -> Vec<Vec<f32>> {
        if !self.action_relative {
            return Self::rows_of(&self.action);
        }
        let idx: Vec<usize> = (0..self.len()).collect();
        idx.chunks(4096).flat_map(|c| Self::rows_of(&self.actions(c).flatten(0, 1))).collect()
    }

    pub fn len(&self) -> usize {
        self.episode_of.len()
    }

    pub fn is_empty(&self) -> bool {
        self.episode_of.is_empty()
    }

    /// The row of each of `idx`'s windows' newest observation.
    fn newest_rows(&self, idx: &[usize]) -> Tensor {
        let rows: Vec<i64> = idx.iter().map(|&i| self.obs_rows[(i + 1) * self.n_obs - 1]).collect();
        Tensor::from_slice(&rows)
    }

    /// The rows of `idx`'s windows (`per` rows each).
    fn rows(all: &[i64], per: usize, idx: &[usize]) -> Tensor {
        let v: Vec<i64> = idx.iter().flat_map(|&i| all[i * per..(i + 1) * per].iter().copied()).collect();
        Tensor::from_slice(&v)
    }

    /// Samples `idx` as a batch, normalised with `stats` (state, action).
    pub fn batch(&self, idx: &[usize], stats: (&MinMax, &MinMax)) -> Result<Batch, NormalizeError> {
        let b = idx.len() as i64;
        let obs = Self::rows(&self.obs_rows, self.n_obs, idx);
        let frames = self.frames.index_select(0, &obs);
        let cams = frames.size()[1];
        let frames = frames.to_kind(Kind::Float) / 255.0;
        let s = frames.size();
        let frames = frames.view([b, self.n_obs as i64, cams, 3, s[3], s[4]]);
        let images = (0..cams).map(|k| frames.select(2, k)).collect();
        let state = stats.0.normalize(&self.state.index_select(0, &obs).view([b, self.n_obs as i64, -1]))?;
        let action = stats.1.normalize(&self.actions(idx))?;
        let newest = self.newest_rows(idx);
        let waypoint = self.waypoint.index_select(0, &newest)
            - self.state.index_select(0, &newest).narrow(1, 0, 3).to_kind(Kind::Float);
        let mut episodes: Vec<String> = idx.iter().map(|&i| self.uuids[self.episode_of[i]].clone()).collect();
        episodes.sort();
        episodes.dedup();
        Ok(Batch { images, state, action, waypoint, episodes })
    }

    /// Every state and action row (for the normaliser's statistics).
    fn rows_of(t: &Tensor) -> Vec<Vec<f32>> {
        if t.numel() == 0 {
            return Vec::new();
        }
        let w = t.size()[1];
        let flat: Vec<f32> = t.flatten(0, -1).try_into().unwrap_or_default();
        flat.chunks(w as usize).map(<[f32]>::to_vec).collect()
    }
}

/// How long a run trains.
#[derive(Debug, Clone, Copy)]
pub enum Length {
    /// Optimisation steps in all.
    Steps(usize),
    /// Passes over the target's training samples (rounded up to whole steps).
    Epochs(f64),
}

/// What `labrig train` was asked to do.
#[derive(Debug, Clone)]
pub struct RunOptions {
    pub target: Vec<PathBuf>,
    pub cotrain: Vec<PathBuf>,
    pub w: f64,
    pub preset: Preset,
    pub out: PathBuf,
    pub length: Length,
    pub resume: bool,
    pub include_failures: bool,
    pub cache: PathBuf,
    pub progress: bool,
    /// Which samples of correction episodes are trained on.
    pub corrections: Corrections,
    /// Data-parallel: this process is one rank of the group (see [`crate::dist`]).
    pub dist: Option<std::sync::Arc<crate::dist::Group>>,
}

/// The figures of a run (also `run.json`), read back by `labrig experiment`.
pub use labrig_reports::RunReport;

/// diffusers' cosine schedule with linear warm-up: the learning rate's factor at `step`.
pub fn lr_factor(step: usize, warmup: usize, total: usize) -> f64 {
    if step < warmup {
        return (step + 1) as f64 / warmup.max(1) as f64;
    }
    let progress = (step - warmup) as f64 / (total.saturating_sub(warmup)).max(1) as f64;
    0.5 * (1.0 + (std::f64::consts::PI * progress.min(1.0)).cos())
}

/// diffusion_policy's EMA decay after `step` optimisation steps.
pub fn ema_decay(step: u64, power: f64, max: f64) -> f64 {
    if step == 0 {
        return 0.0;
    }
    (1.0 - (1.0 + step as f64).powf(-power)).clamp(0.0, max)
}

/// Loads the episodes at `paths` (a progress bar when asked; decoded frames cached under
/// `cache` when given), dropping unsuccessful ones unless `include_failures`; returns them and
/// how many were dropped.
pub fn load_set(
    paths: &[PathBuf],
    cfg: &DiffusionConfig,
    cache: Option<&Path>,
    include_failures: bool,
    progress: bool,
    what: &str,
) -> Result<(Vec<EpisodeTensors>, usize), TrainError> {
    let bar = labrig_episode::progress::bar(
        &format!("decoding {what} {{bar:30}} {{pos}}/{{len}} episodes (ETA {{eta}})"),
        paths.len() as u64,
        !progress,
    );
    let mut kept = Vec::new();
    let mut skipped = 0;
    for p in paths {
        let ep = load_episode(p, cfg, cache)?;
        bar.inc(1);
        if ep.success != Some(true) && !include_failures {
            skipped += 1;
            continue;
        }
        if !ep.is_empty() {
            kept.push(ep);
        }
    }
    bar.finish_and_clear();
    Ok((kept, skipped))
}

/// Splits off `fraction` of the episodes (at least one when there are two or more; none of
/// a single one) for validation, by a seeded shuffle.
pub fn split(mut eps: Vec<EpisodeTensors>, fraction: f64, seed: u64) -> (Vec<EpisodeTensors>, Vec<EpisodeTensors>) {
    use rand::SeedableRng;
    use rand::seq::SliceRandom;
    if fraction <= 0.0 || eps.len() < 2 {
        return (eps, Vec::new());
    }
    let n_val = ((eps.len() as f64 * fraction).round() as usize).clamp(1, eps.len() - 1);
    eps.sort_by(|a, b| a.uuid.cmp(&b.uuid));
    eps.shuffle(&mut rand_chacha::ChaCha8Rng::seed_from_u64(seed));
    let val = eps.split_off(eps.len() - n_val);
    (eps, val)
}

/// The newest checkpoint of a run (what `checkpoints/last` names).
pub fn last_checkpoint(out: &Path) -> Option<PathBuf> {
    let name = std::fs::read_to_string(out.join("checkpoints").join("last")).ok()?;
    let dir = out.join("checkpoints").join(name.trim());
    dir.join(checkpoint::META).is_file().then_some(dir)
}

/// The model being trained, its EMA copy and optimiser.
#[derive(Debug)]
pub struct Trainer {
    pub vs: nn::VarStore,
    pub policy: DiffusionPolicy,
    pub ema_vs: nn::VarStore,
    pub ema: DiffusionPolicy,
    opt: nn::Optimizer,
    pub cfg: TrainConfig,
    pub step: u64,
    /// Seconds spent in the gradients' all-reduce (data-parallel runs).
    pub comm_s: f64,
}

impl Trainer {
    pub fn new(model: &DiffusionConfig, cfg: &TrainConfig) -> Result<Trainer, TrainError> {
        let vs = nn::VarStore::new(Device::Cpu);
        let policy = DiffusionPolicy::new(vs.root(), model.clone())?;
        let mut ema_vs = nn::VarStore::new(Device::Cpu);
        let ema = DiffusionPolicy::new(ema_vs.root(), model.clone())?;
        ema_vs.copy(&vs)?;
        let opt = nn::Adam { beta1: cfg.betas[0], beta2: cfg.betas[1], wd: cfg.weight_decay, ..Default::default() }
            .build(&vs, cfg.lr)?;
        Ok(Trainer { vs, policy, ema_vs, ema, opt, cfg: cfg.clone(), step: 0, comm_s: 0.0 })
    }

    /// Continues from a checkpoint's weights, EMA weights and step (the optimiser's moments
    /// start afresh: tch cannot save them).
    pub fn restore(&mut self, dir: &Path) -> Result<CheckpointMeta, TrainError> {
        let (vs, _policy, meta) = checkpoint::load(dir, Device::Cpu)?;
        if &meta.config != self.policy.config() {
            let reason = format!("checkpoint {:?} vs preset {:?}", meta.config, self.policy.config());
            return Err(TrainError::OtherPreset { path: dir.to_owned(), reason });
        }
        let model = dir.join(checkpoint::WEIGHTS);
        self.vs.load(&model).map_err(|source| CheckpointError::Torch {
            path: model,
            what: "loading the weights",
            source,
        })?;
        self.ema_vs.copy(&vs)?;
        self.step = meta.step;
        Ok(meta)
    }

    /// One optimisation step on `batch` at learning rate `lr`: the loss, or the step refused
    /// (nothing changed) when the batch or its loss is not finite.
    pub fn step(
        &mut self,
        batch: &Batch,
        lr: f64,
        rng_noise: &Tensor,
        t: &[i64],
    ) -> Result<f64, (&'static str, Vec<String>)> {
        self.step_in(batch, lr, rng_noise, t, None).map_err(|e| match e {
            StepError::Refused(what, eps) => (what, eps),
            StepError::Dist(_) => unreachable!("no process group"),
        })
    }

    /// [`Trainer::step`] as one rank of `group`: the gradients are averaged over the ranks
    /// before the optimiser steps (the loss returned is the ranks' mean), and a step any rank
    /// refuses is refused by all, so the ranks' weights stay identical.
    pub fn step_in(
        &mut self,
        batch: &Batch,
        lr: f64,
        rng_noise: &Tensor,
        t: &[i64],
        group: Option<&crate::dist::Group>,
    ) -> Result<f64, StepError> {
        let finite = |x: &Tensor| x.isfinite().all().int64_value(&[]) == 1;
        let mut refused: Option<&'static str> = None;
        if !batch.images.iter().all(finite)
            || !finite(&batch.state)
            || !finite(&batch.action)
            || !finite(&batch.waypoint)
        {
            refused = Some("the batch");
        }
        let loss = match refused {
            Some(_) => None,
            None => self
                .policy
                .loss(&batch.images, &batch.state, &batch.action, Some(&batch.waypoint), rng_noise, t, true)
                .map_err(|_| refused = Some("the batch's shape"))
                .ok(),
        };
        let mut value = loss.as_ref().map(|l| l.double_value(&[])).unwrap_or(f64::NAN);
        if refused.is_none() && !value.is_finite() {
            refused = Some("the loss");
        }
        self.opt.zero_grad();
        if let (None, Some(loss)) = (refused, &loss) {
            loss.backward();
            let grads_finite = self.vs.trainable_variables().iter().all(|v| {
                let g = v.grad();
                !g.defined() || finite(&g)
            });
            if !grads_finite {
                refused = Some("a gradient");
            }
        }
        if let Some(g) = group {
            // One all-reduce carries the gradients, the loss and whether any rank refused.
            let mut extra = [if refused.is_some() { 0.0 } else { value }, refused.is_some() as u8 as f64];
            let t0 = Instant::now();
            g.average_grads(&self.vs.trainable_variables(), &mut extra).map_err(StepError::Dist)?;
            self.comm_s += t0.elapsed().as_secs_f64();
            if extra[1] > 0.0 && refused.is_none() {
                refused = Some("another rank's batch");
            }
            value = extra[0] / g.world as f64;
        }
        if let Some(what) = refused {
            self.opt.zero_grad();
            return Err(StepError::Refused(what, batch.episodes.clone()));
        }
        self.opt.set_lr(lr);
        self.opt.clip_grad_norm(self.cfg.grad_clip_norm);
        self.opt.step();
        self.step += 1;
        let decay = ema_decay(self.step, self.cfg.ema_power, self.cfg.ema_max);
        tch::no_grad(|| {
            let live = self.vs.variables();
            for (name, mut e) in self.ema_vs.variables() {
                if let Some(p) = live.get(&name) {
                    e.copy_(&(&e * decay + p * (1.0 - decay)));
                }
            }
        });
        Ok(value)
    }

    /// How far this rank's weights are from rank 0's (the largest difference), summed over
    /// the ranks: 0 when every rank holds the same model.
    pub fn weight_diff(&self, group: &crate::dist::Group) -> Result<f64, crate::dist::DistError> {
        let own = Tensor::cat(&by_name(&self.vs).iter().map(|t| t.detach().reshape([-1])).collect::<Vec<_>>(), 0);
        let lead = own.copy();
        group.broadcast(std::slice::from_ref(&lead), 0)?;
        group.sum((&lead - &own).abs().max().double_value(&[]))
    }

    /// Every rank's weights, EMA weights and step made rank 0's (after a fresh start or a
    /// resume, so the ranks begin identical whatever their seeds).
    pub fn share_weights(&mut self, group: &crate::dist::Group) -> Result<(), crate::dist::DistError> {
        group.broadcast(&by_name(&self.vs), 0)?;
        group.broadcast(&by_name(&self.ema_vs), 0)?;
        let step = group.sum(if group.rank == 0 { self.step as f64 } else { 0.0 })?;
        self.step = step as u64;
        Ok(())
    }
}

/// A var store's variables in name order (the same on every rank).
fn by_name(vs: &nn::VarStore) -> Vec<Tensor> {
    let mut v: Vec<(String, Tensor)> = vs.variables().into_iter().collect();
    v.sort_by(|a, b| a.0.cmp(&b.0));
    v.into_iter().map(|(_, t)| t).collect()
}

/// Why a step was not taken.
#[derive(Debug)]
pub enum StepError {
    /// What was not finite, and the episodes of the batch.
    Refused(&'static str, Vec<String>),
    Dist(crate::dist::DistError),
}

/// The validation loss of the EMA weights on a fixed set: the first `n` samples spread over
/// the set, centre crops, noise and timesteps from `seed`.
#[derive(Debug)]
pub struct Validation {
    batches: Vec<(Batch, Tensor, Vec<i64>)>,
    /// Each held-out episode's first step (at most 64).
    first: Option<Batch>,
}

impl Validation {
    pub fn new(
        set: &SampleSet,
        stats: (&MinMax, &MinMax),
        cfg: &DiffusionConfig,
        n: usize,
        batch: usize,
        seed: u64,
    ) -> Result<Validation, TrainError> {
        use rand::{Rng, SeedableRng};
        if set.is_empty() {
            return Ok(Validation { batches: Vec::new(), first: None });
        }
        let n = n.min(set.len()).max(1);
        let idx: Vec<usize> = (0..n).map(|k| k * set.len() / n).collect();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed ^ 0x0005_EED0_F7A1);
        let gen_noise = Tensor::randn([n as i64, cfg.horizon, cfg.action_dim], (Kind::Float, Device::Cpu));
        let mut batches = Vec::new();
        for (c, chunk) in idx.chunks(batch.max(1)).enumerate() {
            let b = set.batch(chunk, stats)?;
            let noise = gen_noise.narrow(0, (c * batch) as i64, chunk.len() as i64);
            let t: Vec<i64> = chunk.iter().map(|_| rng.random_range(0..cfg.train_steps as i64)).collect();
            batches.push((b, noise, t));
        }
        let first: Vec<usize> = set.first_samples.iter().copied().take(64).collect();
        let first = if first.is_empty() { None } else { Some(set.batch(&first, stats)?) };
        Ok(Validation { batches, first })
    }

    /// The waypoint head's error (mm, mean Euclidean distance) on the first validation batch's
    /// samples (at most 64, spread over the held-out steps) and on each held-out episode's
    /// first step (the arm at home: the images alone place the grasp). None without a head or
    /// validation samples.
    pub fn waypoint_mm(&self, policy: &DiffusionPolicy) -> Result<(Option<f64>, Option<f64>), TrainError> {
        let err = |b: &Batch| -> Result<Option<f64>, TrainError> {
            let n = b.state.size()[0].min(64);
            let images: Vec<Tensor> = b.images.iter().map(|t| t.narrow(0, 0, n)).collect();
            let got = tch::no_grad(|| policy.predict_waypoint(&images, &b.state.narrow(0, 0, n)))?;
            Ok(got.map(|w| {
                let d =
                    (w - b.waypoint.narrow(0, 0, n)).square().sum_dim_intlist(&[1i64][..], false, Kind::Float).sqrt();
                d.mean(Kind::Float).double_value(&[]) * 1e3
            }))
        };
        let all = match self.batches.first() {
            Some((b, _, _)) => err(b)?,
            None => None,
        };
        let first = match &self.first {
            Some(b) => err(b)?,
            None => None,
        };
        Ok((all, first))
    }

    pub fn loss(&self, policy: &DiffusionPolicy) -> Result<Option<f64>, TrainError> {
        if self.batches.is_empty() {
            return Ok(None);
        }
        let (mut sum, mut n) = (0.0, 0usize);
        for (b, noise, t) in &self.batches {
            let l = tch::no_grad(|| policy.loss(&b.images, &b.state, &b.action, Some(&b.waypoint), noise, t, false))?;
            sum += l.double_value(&[]) * t.len() as f64;
            n += t.len();
        }
        Ok(Some(sum / n as f64))
    }

    /// Open loop on the held-out samples (at most the first batch, 64 samples): the EMA
    /// policy samples each chunk from the batch's fixed noise (DDIM, centre crops); the mean
    /// Euclidean distance (mm) between its executed rows' target positions and the recorded
    /// ones, in the robot's units (relative chunks compare the same way: both are shifted by
    /// the same TCP). None without validation samples or for velocity actions.
    pub fn open_loop_mm(
        &self,
        policy: &DiffusionPolicy,
        action_stats: &MinMax,
        cfg: &DiffusionConfig,
    ) -> Result<Option<f64>, TrainError> {
        let Some((b, noise, _)) = self.batches.first() else { return Ok(None) };
        if cfg.action_space != crate::policy::ActionSpace::EefAxisAngle {
            return Ok(None);
        }
        let n = b.state.size()[0].min(64);
        let images: Vec<Tensor> = b.images.iter().map(|t| t.narrow(0, 0, n)).collect();
        let chunk = tch::no_grad(|| policy.sample(&images, &b.state.narrow(0, 0, n), &noise.narrow(0, 0, n)))?;
        let got = action_stats.unnormalize(&policy.executed(&chunk))?;
        let want = action_stats.unnormalize(&policy.executed(&b.action.narrow(0, 0, n)))?;
        let d = (got.narrow(2, 0, 3) - want.narrow(2, 0, 3))
            .square()
            .sum_dim_intlist(&[2i64][..], false, Kind::Float)
            .sqrt();
        Ok(Some(d.mean(Kind::Float).double_value(&[]) * 1e3))
    }
}

/// One row of `loss.csv`.
#[derive(Debug, Clone, Copy)]
pub struct LossRow {
    pub step: u64,
    pub train: f64,
    pub val: Option<f64>,
    pub lr: f64,
    /// Open loop on the held-out samples: mean distance (mm) between the executed rows'
    /// sampled and recorded target positions.
    pub open_loop_mm: Option<f64>,
    /// The waypoint head's error (mm) on held-out samples, and on the held-out episodes'
    /// first steps ([`Validation::waypoint_mm`]).
    pub waypoint_mm: Option<f64>,
    pub first_waypoint_mm: Option<f64>,
}

fn read_loss_csv(path: &Path, up_to: u64) -> Vec<LossRow> {
    let Ok(text) = std::fs::read_to_string(path) else { return Vec::new() };
    text.lines()
        .skip(1)
        .filter_map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            Some(LossRow {
                step: f.first()?.parse().ok()?,
                train: f.get(1)?.parse().ok()?,
                val: f.get(2).and_then(|v| v.parse().ok()),
                lr: f.get(3)?.parse().ok()?,
                open_loop_mm: f.get(4).and_then(|v| v.parse().ok()),
                waypoint_mm: f.get(5).and_then(|v| v.parse().ok()),
                first_waypoint_mm: f.get(6).and_then(|v| v.parse().ok()),
            })
        })
        .filter(|r| r.step <= up_to)
        .collect()
}

fn write_loss_csv(path: &Path, rows: &[LossRow]) -> Result<(), TrainError> {
    let mut s = String::from("step,train_loss,val_loss,lr,open_loop_mm,waypoint_mm,first_waypoint_mm\n");
    let mm = |v: Option<f64>| v.map(|v| format!("{v:.2}")).unwrap_or_default();
    for r in rows {
        let val = r.val.map(|v| format!("{v:.6}")).unwrap_or_default();
        s.push_str(&format!(
            "{},{:.6},{},{:.3e},{},{},{}\n",
            r.step,
            r.train,
            val,
            r.lr,
            mm(r.open_loop_mm),
            mm(r.waypoint_mm),
            mm(r.first_waypoint_mm)
        ));
    }
    std::fs::write(path, s).map_err(io(path, "writing the loss log"))
}

/// The loss curve: training loss (per logged step) and validation loss, log scale.
pub fn plot_loss(rows: &[LossRow], title: &str, path: &Path) -> Result<(), TrainError> {
    use plotters::prelude::*;
    let fail = |e: String| TrainError::Setup(format!("{}: plotting the loss curve: {e}", path.display()));
    let font = labrig_episode::font::dejavu_sans().map_err(|e| fail(e.to_string()))?;
    let _ = plotters::style::register_font("sans-serif", FontStyle::Normal, font);
    let train: Vec<(f64, f64)> = rows.iter().filter(|r| r.train > 0.0).map(|r| (r.step as f64, r.train)).collect();
    let val: Vec<(f64, f64)> =
        rows.iter().filter_map(|r| r.val.filter(|v| *v > 0.0).map(|v| (r.step as f64, v))).collect();
    let all = train.iter().chain(&val).map(|p| p.1);
    let (lo, hi) = all.fold((f64::MAX, f64::MIN), |(lo, hi), v| (lo.min(v), hi.max(v)));
    if lo > hi {
        return Err(fail("no losses to plot".into()));
    }
    let last = rows.iter().map(|r| r.step).max().unwrap_or(1).max(1) as f64;
    let root = BitMapBackend::new(path, (1000, 600)).into_drawing_area();
    let e = |e: DrawingAreaErrorKind<_>| fail(format!("{e:?}"));
    root.fill(&WHITE).map_err(e)?;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 22))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(70)
        .build_cartesian_2d(0.0..last, (lo * 0.8..hi * 1.25).log_scale())
        .map_err(e)?;
    chart
        .configure_mesh()
        .x_desc("step")
        .y_desc("noise-prediction MSE (log)")
        .x_label_formatter(&|x| format!("{x:.0}"))
        .y_label_formatter(&|y| format!("{y:.3}"))
        .draw()
        .map_err(e)?;
    chart
        .draw_series(LineSeries::new(train, RGBColor(120, 120, 220).stroke_width(1)))
        .map_err(e)?
        .label("training batch")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], RGBColor(120, 120, 220).stroke_width(2)));
    chart
        .draw_series(LineSeries::new(val.clone(), RED.stroke_width(3)))
        .map_err(e)?
        .label("validation (EMA weights)")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], RED.stroke_width(3)));
    chart.draw_series(val.iter().map(|p| Circle::new(*p, 3, RED.filled()))).map_err(e)?;
    chart.configure_series_labels().background_style(WHITE.mix(0.85)).border_style(BLACK).draw().map_err(e)?;
    root.present().map_err(e)?;
    Ok(())
}

/// Runs `labrig train`.
pub fn run(opts: &RunOptions) -> Result<RunReport, TrainError> {
    let Preset { model, train: tc } = &opts.preset;
    let threads = tch::get_num_threads();
    let ranks = Ranks::of(opts.dist.as_deref());
    std::fs::create_dir_all(&opts.out).map_err(io(&opts.out, "creating the run directory"))?;
    let episodes = Episodes::load(opts, ranks)?;
    let (mut trainer, last) = start_trainer(opts)?;
    let sets = SampleSets::select(&episodes, model, opts.corrections, tc.skip_missed_grasps);
    let (state_stats, action_stats, resumed_from) = normaliser_stats(&mut trainer, last.as_deref(), &episodes, &sets)?;
    let counts = episodes.counts;
    let manifest = episodes.into_manifest();
    let stats = (&state_stats, &action_stats);
    let w = if sets.cotrain.is_empty() { 1.0 } else { opts.w };
    if let Some(g) = ranks.group {
        trainer.share_weights(g).map_err(dist_err)?;
    }
    // Every rank draws the same global batch (world x batch size) and trains on its slice.
    let mut sampler = CotrainSampler::new(sets.train.len(), sets.cotrain.len(), w, tc.seed ^ trainer.step)?;
    // Rank 0 validates (every rank holds the same held-out split; the others skip it).
    let empty = SampleSet::new(&[], model);
    let validation = Validation::new(
        if ranks.lead { &sets.val } else { &empty },
        stats,
        model,
        tc.val_samples,
        tc.batch_size,
        tc.seed,
    )?;
    let csv = opts.out.join("loss.csv");
    let mut log = if resumed_from.is_some() { read_loss_csv(&csv, trainer.step) } else { Vec::new() };
    let total = total_steps(opts.length, sets.train.len(), tc.batch_size * ranks.world);
    let mut ckpt = Checkpointer {
        dir: opts.out.join("checkpoints"),
        model,
        state_stats: &state_stats,
        action_stats: &action_stats,
        manifest,
        lead: ranks.lead,
        last: last.as_ref().map(|p| p.display().to_string()).unwrap_or_else(|| "none yet".into()),
    };
    let first_val = first_validation(&validation, &trainer, &action_stats, model, &mut log)?;
    let training = Training {
        opts,
        ranks,
        sets: &sets,
        stats,
        validation: &validation,
        total,
        warmup: tc.warmup_steps.min(total as usize / 10),
        csv: &csv,
        first_val,
        w,
        counts,
        resumed_from,
        threads,
    };
    training.print_banner();
    let tally = training.train(&mut trainer, &mut sampler, &mut ckpt, &mut log)?;
    let (ranks_weight_diff, checkpoint) = training.finish(&trainer, &mut ckpt, &log)?;
    let report = training.report(&trainer, &sampler, &tally, ranks_weight_diff, checkpoint);
    if !ranks.lead {
        return Ok(report);
    }
    write_run_json(&opts.out, &report)?;
    Ok(report)
}

/// A data-parallel failure as the run's error.
fn dist_err(e: crate::dist::DistError) -> TrainError {
    TrainError::Setup(e.to_string())
}

/// This process's place in a data-parallel group (rank 0 of 1 without one).
#[derive(Clone, Copy)]
struct Ranks<'a> {
    group: Option<&'a crate::dist::Group>,
    rank: usize,
    world: usize,
    /// Rank 0 alone writes the run's files; the others train beside it.
    lead: bool,
}

impl Ranks<'_> {
    /// The ranks of `group`, or a single process's.
    fn of(group: Option<&crate::dist::Group>) -> Ranks<'_> {
        let (rank, world) = group.map(|g| (g.rank, g.world)).unwrap_or((0, 1));
        Ranks { group, rank, world, lead: rank == 0 }
    }
}

/// How many episodes went where, and how long decoding them took.
#[derive(Clone, Copy)]
struct EpisodeCounts {
    train: usize,
    val: usize,
    cotrain: usize,
    /// Unsuccessful episodes left out (target and co-training).
    skipped: usize,
    decode_s: f64,
}

/// The decoded episodes: the target's split into training and validation, and the
/// co-training set.
struct Episodes {
    train: Vec<EpisodeTensors>,
    val: Vec<EpisodeTensors>,
    cotrain: Vec<EpisodeTensors>,
    counts: EpisodeCounts,
}

impl Episodes {
    /// Decodes the target and co-training episodes (rank 0 first, filling the frame cache the
    /// others then read) and splits the target's for validation.
    fn load(opts: &RunOptions, ranks: Ranks<'_>) -> Result<Episodes, TrainError> {
        let Preset { model, train: tc } = &opts.preset;
        let decode_started = Instant::now();
        // Rank 0 decodes first and fills the frame cache; the others then read it.
        if let (Some(g), false) = (ranks.group, ranks.lead) {
            g.sum(0.0).map_err(dist_err)?;
        }
        let progress = opts.progress && ranks.lead;
        let (target, skipped_t) =
            load_set(&opts.target, model, Some(&opts.cache), opts.include_failures, progress, "target")?;
        let (cotrain, skipped_c) =
            load_set(&opts.cotrain, model, Some(&opts.cache), opts.include_failures, progress, "co-training")?;
        if let (Some(g), true) = (ranks.group, ranks.lead) {
            g.sum(0.0).map_err(dist_err)?;
        }
        let decode_s = decode_started.elapsed().as_secs_f64();
        if target.is_empty() {
            return Err(TrainError::Setup(format!(
                "no successful target episodes among {} found ({} unsuccessful skipped; --include-failures trains on them)",
                opts.target.len(),
                skipped_t
            )));
        }
        let (train, val) = split(target, tc.val_fraction, tc.seed);
        let counts = EpisodeCounts {
            train: train.len(),
            val: val.len(),
            cotrain: cotrain.len(),
            skipped: skipped_t + skipped_c,
            decode_s,
        };
        Ok(Episodes { train, val, cotrain, counts })
    }

    /// The training and co-training episodes (what the normaliser is fitted on).
    fn trained(&self) -> impl Iterator<Item = &EpisodeTensors> {
        self.train.iter().chain(&self.cotrain)
    }

    /// Every episode's uuid (the checkpoints' manifest); the episodes themselves are dropped.
    fn into_manifest(self) -> Vec<String> {
        self.train.iter().chain(&self.val).chain(&self.cotrain).map(|e| e.uuid.clone()).collect()
    }
}

/// A fresh trainer, and the checkpoint `--resume` continues from: refuses to start over a
/// run already in `--out`, and a config that cannot skip missed grasps.
fn start_trainer(opts: &RunOptions) -> Result<(Trainer, Option<PathBuf>), TrainError> {
    let Preset { model, train: tc } = &opts.preset;
    let trainer = Trainer::new(model, tc)?;
    let last = if opts.resume { last_checkpoint(&opts.out) } else { None };
    if !opts.resume && last_checkpoint(&opts.out).is_some() {
        return Err(TrainError::Setup(format!(
            "{} holds a run already: --resume continues it; another --out starts a new one",
            opts.out.display()
        )));
    }
    if opts.resume && last.is_none() {
        eprintln!("--resume: no checkpoint in {} yet; starting from step 0", opts.out.display());
    }
    if tc.skip_missed_grasps && !model.gripper_state {
        return Err(TrainError::Setup(
            "skip_missed_grasps reads the gripper's opening from the state: set gripper_state = true".into(),
        ));
    }
    Ok((trainer, last))
}

/// The samples the run trains and validates on, and what choosing them found and left out.
struct SampleSets {
    train: SampleSet,
    val: SampleSet,
    cotrain: SampleSet,
    missed_grasps: usize,
    mistake_windows: usize,
    correction_episodes: usize,
    correction_samples: usize,
}

impl SampleSets {
    /// The episodes' samples (correction episodes' chosen by `corrections`, validation's all),
    /// with `skip` none holding a missed grasp's mistake, which it reports.
    fn select(eps: &Episodes, model: &DiffusionConfig, corrections: Corrections, skip: bool) -> SampleSets {
        let train = SampleSet::selecting(&eps.train, model, corrections, skip);
        let val = SampleSet::selecting(&eps.val, model, Corrections::All, skip);
        let cotrain = SampleSet::selecting(&eps.cotrain, model, corrections, skip);
        let (missed_grasps, mistake_windows) =
            (train.missed_grasps + cotrain.missed_grasps, train.mistake_windows + cotrain.mistake_windows);
        if skip {
            eprintln!(
                "skip_missed_grasps: {missed_grasps} missed grasps in the training episodes, {mistake_windows} windows holding their mistake left out ({} kept)",
                train.len() + cotrain.len()
            );
        }
        let correction_eps: Vec<&EpisodeTensors> = eps.trained().filter(|e| e.is_correction()).collect();
        let correction_episodes = correction_eps.len();
        let correction_samples = correction_eps
            .iter()
            .map(|e| SampleSet::selecting(std::slice::from_ref(*e), model, corrections, skip).len())
            .sum::<usize>();
        SampleSets { train, val, cotrain, missed_grasps, mistake_windows, correction_episodes, correction_samples }
    }
}

/// The normaliser's statistics (state, action) and the step resumed from: a resumed run's
/// from its checkpoint (restoring `trainer` from it), a fresh run's fitted to its training
/// samples.
fn normaliser_stats(
    trainer: &mut Trainer,
    last: Option<&Path>,
    eps: &Episodes,
    sets: &SampleSets,
) -> Result<(MinMax, MinMax, Option<u64>), TrainError> {
    if let Some(dir) = last {
        let meta = trainer.restore(dir)?;
        let now: std::collections::BTreeSet<&String> =
            eps.train.iter().chain(&eps.val).chain(&eps.cotrain).map(|e| &e.uuid).collect();
        if now != meta.manifest.iter().collect() {
            eprintln!(
                "warning: resuming on other episodes than the checkpoint's ({} now, {} then); its normaliser statistics are kept",
                now.len(),
                meta.manifest.len()
            );
        }
        return Ok((meta.state_stats, meta.action_stats, Some(meta.step)));
    }
    let s: Vec<Vec<f32>> = eps.trained().flat_map(|e| SampleSet::rows_of(&e.state)).collect();
    let a: Vec<Vec<f32>> =
        sets.train.action_rows_for_stats().into_iter().chain(sets.cotrain.action_rows_for_stats()).collect();
    Ok((MinMax::fit(s.iter().map(Vec::as_slice))?, MinMax::fit(a.iter().map(Vec::as_slice))?, None))
}

/// The run's length in optimisation steps (`global_batch`: all ranks' samples per step).
fn total_steps(length: Length, train_samples: usize, global_batch: usize) -> u64 {
    match length {
        Length::Steps(n) => n as u64,
        Length::Epochs(e) => (e * train_samples as f64 / global_batch as f64).ceil() as u64,
    }
}

/// Whether step `at` is due for what is done every `every` steps and at the run's end.
// `%` as before (a zero interval panics; the CLI refuses one), not `is_multiple_of`.
#[allow(clippy::manual_is_multiple_of)]
fn due(at: u64, every: usize, total: u64) -> bool {
    at % every as u64 == 0 || at == total
}

/// Saves checkpoints (rank 0 alone) and remembers the newest, which a refused step names.
struct Checkpointer<'a> {
    dir: PathBuf,
    model: &'a DiffusionConfig,
    state_stats: &'a MinMax,
    action_stats: &'a MinMax,
    manifest: Vec<String>,
    lead: bool,
    /// The newest checkpoint's directory, or "none yet".
    last: String,
}

impl Checkpointer<'_> {
    /// Saves `trainer` as `checkpoints/step_<n>` and points `checkpoints/last` at it (other
    /// ranks only name the directory).
    fn save(&mut self, trainer: &Trainer) -> Result<PathBuf, TrainError> {
        if !self.lead {
            return Ok(self.dir.join(format!("step_{}", trainer.step)));
        }
        let name = format!("step_{}", trainer.step);
        let dir = self.dir.join(&name);
        let meta = CheckpointMeta {
            format: checkpoint::FORMAT,
            config: self.model.clone(),
            action_stats: self.action_stats.clone(),
            state_stats: self.state_stats.clone(),
            image_stats: Default::default(),
            manifest: self.manifest.clone(),
            step: trainer.step,
        };
        checkpoint::save(&dir, &meta, &trainer.vs, Some(&trainer.ema_vs))?;
        let pointer = self.dir.join("last");
        let tmp = self.dir.join(".last.tmp");
        std::fs::write(&tmp, &name).map_err(io(&tmp, "writing"))?;
        std::fs::rename(&tmp, &pointer).map_err(io(&pointer, "moving into place"))?;
        self.last = dir.display().to_string();
        Ok(dir)
    }
}

/// The validation loss the run starts from: a fresh run's measured now (its step-0 row added
/// to `log`), a resumed run's the first in its log.
fn first_validation(
    validation: &Validation,
    trainer: &Trainer,
    action_stats: &MinMax,
    model: &DiffusionConfig,
    log: &mut Vec<LossRow>,
) -> Result<Option<f64>, TrainError> {
    let first_val = if trainer.step == 0 { validation.loss(&trainer.ema)? } else { log.iter().find_map(|r| r.val) };
    if trainer.step == 0 {
        let open_loop_mm = validation.open_loop_mm(&trainer.ema, action_stats, model)?;
        let (waypoint_mm, first_waypoint_mm) = validation.waypoint_mm(&trainer.ema)?;
        log.push(LossRow {
            step: 0,
            train: 0.0,
            val: first_val,
            lr: 0.0,
            open_loop_mm,
            waypoint_mm,
            first_waypoint_mm,
        });
    }
    Ok(first_val)
}

/// What the training loop measured: its timings, and the latest losses and errors.
struct Tally {
    load_s: f64,
    step_s: f64,
    samples: u64,
    last_train: f64,
    last_val: Option<f64>,
    last_open_loop: Option<f64>,
    last_waypoint: Option<f64>,
    last_first_waypoint: Option<f64>,
}

impl Tally {
    /// Nothing timed yet; the latest figures are the start's and the log's.
    fn new(first_val: Option<f64>, log: &[LossRow]) -> Tally {
        Tally {
            load_s: 0.0,
            step_s: 0.0,
            samples: 0,
            last_train: f64::NAN,
            // A resumed run's newest validation is its log's last (the first was the run's start).
            last_val: log.iter().rev().find_map(|r| r.val).or(first_val),
            last_open_loop: log.iter().rev().find_map(|r| r.open_loop_mm),
            last_waypoint: log.iter().rev().find_map(|r| r.waypoint_mm),
            last_first_waypoint: log.iter().rev().find_map(|r| r.first_waypoint_mm),
        }
    }

    /// The throughput so far (all ranks' samples).
    fn samples_per_s(&self) -> f64 {
        self.samples as f64 / self.step_s.max(1e-9)
    }
}

/// What the training loop works with, set up by [`run`].
struct Training<'a> {
    opts: &'a RunOptions,
    ranks: Ranks<'a>,
    sets: &'a SampleSets,
    stats: (&'a MinMax, &'a MinMax),
    validation: &'a Validation,
    total: u64,
    warmup: usize,
    csv: &'a Path,
    first_val: Option<f64>,
    w: f64,
    counts: EpisodeCounts,
    resumed_from: Option<u64>,
    threads: i32,
}

impl Training<'_> {
    /// The line that says what the run is about to do.
    fn print_banner(&self) {
        let (tc, world, c) = (&self.opts.preset.train, self.ranks.world, &self.counts);
        let ranks = if world > 1 {
            format!(", rank {} of {world} (global batch {})", self.ranks.rank, tc.batch_size * world)
        } else {
            String::new()
        };
        println!(
            "training {} ({} steps, batch {}{ranks}): {} target episodes ({} samples) + {} held out for validation, {} co-training ({} samples), w = {}, {} threads",
            if self.resumed_from.is_some() { "resumed" } else { "from scratch" },
            self.total,
            tc.batch_size,
            c.train,
            self.sets.train.len(),
            c.val,
            c.cotrain,
            self.sets.cotrain.len(),
            self.w,
            self.threads
        );
    }

    /// Steps `trainer` to the run's length: validates, logs and checkpoints as configured.
    fn train(
        &self,
        trainer: &mut Trainer,
        sampler: &mut CotrainSampler,
        ckpt: &mut Checkpointer<'_>,
        log: &mut Vec<LossRow>,
    ) -> Result<Tally, TrainError> {
        use rand::SeedableRng;
        let (tc, model, world, lead) =
            (&self.opts.preset.train, &self.opts.preset.model, self.ranks.world, self.ranks.lead);
        let total = self.total;
        let progress = self.opts.progress && lead;
        let bar = labrig_episode::progress::bar("{bar:30} {pos}/{len} steps (ETA {eta})", total, !progress);
        bar.set_position(trainer.step);
        let mut tally = Tally::new(self.first_val, log);
        let mut rng =
            rand_chacha::ChaCha8Rng::seed_from_u64(tc.seed.wrapping_add(trainer.step).wrapping_mul(0x9E37_79B9));
        while trainer.step < total {
            let t0 = Instant::now();
            let (batch, noise, t) = self.draw_batch(trainer.step, sampler, &mut rng)?;
            let t1 = Instant::now();
            let lr = tc.lr * lr_factor(trainer.step as usize, self.warmup, total as usize);
            let loss = trainer.step_in(&batch, lr, &noise, &t, self.ranks.group).map_err(|e| match e {
                StepError::Refused(what, episodes) => {
                    TrainError::NotFinite { step: trainer.step, what, episodes, last_checkpoint: ckpt.last.clone() }
                }
                StepError::Dist(e) => dist_err(e),
            })?;
            let t2 = Instant::now();
            tally.load_s += (t1 - t0).as_secs_f64();
            tally.step_s += (t2 - t0).as_secs_f64();
            tally.samples += (tc.batch_size as i64 * world as i64) as u64;
            tally.last_train = loss;
            let at = trainer.step;
            let mut row = LossRow {
                step: at,
                train: loss,
                val: None,
                lr,
                open_loop_mm: None,
                waypoint_mm: None,
                first_waypoint_mm: None,
            };
            if lead && due(at, tc.val_every, total) {
                self.validate(trainer, model, &mut row, &mut tally, &bar)?;
            }
            log.push(row);
            if lead && due(at, tc.checkpoint_every, total) {
                ckpt.save(trainer)?;
                write_loss_csv(self.csv, log)?;
            }
            bar.set_message(format!("loss {loss:.4}  {:.1} samples/s", tally.samples_per_s()));
            bar.inc(1);
        }
        bar.finish_and_clear();
        Ok(tally)
    }

    /// This rank's slice of the step's global batch (the target's samples, then the
    /// co-training set's), with the noise and timesteps one process with the whole batch
    /// would give those samples.
    fn draw_batch(
        &self,
        step: u64,
        sampler: &mut CotrainSampler,
        rng: &mut rand_chacha::ChaCha8Rng,
    ) -> Result<(Batch, Tensor, Vec<i64>), TrainError> {
        use rand::Rng;
        let (tc, model, rank, world) =
            (&self.opts.preset.train, &self.opts.preset.model, self.ranks.rank, self.ranks.world);
        let b = tc.batch_size as i64;
        let global = sampler.batch(tc.batch_size * world);
        // Noise and timesteps belong to a draw of the global batch, so a rank's slice gets what
        // one process with the whole batch would give those samples.
        tch::manual_seed(tc.seed.wrapping_mul(0x9E37_79B9).wrapping_add(step) as i64);
        let noise_all = Tensor::randn([b * world as i64, model.horizon, model.action_dim], (Kind::Float, Device::Cpu));
        let t_all: Vec<i64> = (0..global.len()).map(|_| rng.random_range(0..model.train_steps as i64)).collect();
        // The random crops differ by rank.
        tch::manual_seed(tc.seed.wrapping_mul(0x85EB_CA6B).wrapping_add(step * world as u64 + rank as u64) as i64);
        let mine = (rank * tc.batch_size)..((rank + 1) * tc.batch_size);
        let draws = &global[mine.clone()];
        // The batch holds the target's samples, then the co-training set's.
        let order: Vec<usize> = (0..draws.len())
            .filter(|&k| matches!(draws[k], Draw::Target(_)))
            .chain((0..draws.len()).filter(|&k| matches!(draws[k], Draw::Cotrain(_))))
            .collect();
        let (ti, ci): (Vec<usize>, Vec<usize>) = draws.iter().fold((Vec::new(), Vec::new()), |(mut t, mut c), d| {
            match *d {
                Draw::Target(i) => t.push(i),
                Draw::Cotrain(i) => c.push(i),
            }
            (t, c)
        });
        let mut parts = Vec::new();
        if !ti.is_empty() {
            parts.push(self.sets.train.batch(&ti, self.stats)?);
        }
        if !ci.is_empty() {
            parts.push(self.sets.cotrain.batch(&ci, self.stats)?);
        }
        let batch = concat(parts);
        let rows_at: Vec<i64> = order.iter().map(|&k| (mine.start + k) as i64).collect();
        let noise = noise_all.index_select(0, &Tensor::from_slice(&rows_at));
        let t: Vec<i64> = order.iter().map(|&k| t_all[mine.start + k]).collect();
        Ok((batch, noise, t))
    }

    /// Rank 0's validation of the EMA weights after a step: fills `row`'s figures, keeps them
    /// as the latest, and prints them above the progress bar.
    fn validate(
        &self,
        trainer: &Trainer,
        model: &DiffusionConfig,
        row: &mut LossRow,
        tally: &mut Tally,
        bar: &indicatif::ProgressBar,
    ) -> Result<(), TrainError> {
        let (at, total, loss, lr) = (row.step, self.total, row.train, row.lr);
        row.val = self.validation.loss(&trainer.ema)?;
        row.open_loop_mm = self.validation.open_loop_mm(&trainer.ema, self.stats.1, model)?;
        (row.waypoint_mm, row.first_waypoint_mm) = self.validation.waypoint_mm(&trainer.ema)?;
        tally.last_val = row.val.or(tally.last_val);
        tally.last_open_loop = row.open_loop_mm.or(tally.last_open_loop);
        tally.last_waypoint = row.waypoint_mm.or(tally.last_waypoint);
        tally.last_first_waypoint = row.first_waypoint_mm.or(tally.last_first_waypoint);
        let fall = match (self.first_val, row.val) {
            (Some(a), Some(b)) if b > 0.0 => format!(" ({:.1}x below the start)", a / b),
            _ => String::new(),
        };
        bar.suspend(|| {
            let mm = |v: Option<f64>| v.map(|v| format!("{v:.1}")).unwrap_or_else(|| "-".into());
            let waypoint = match row.waypoint_mm {
                Some(_) => format!(
                    ", waypoint {} mm ({} mm at the first steps)",
                    mm(row.waypoint_mm),
                    mm(row.first_waypoint_mm)
                ),
                None => String::new(),
            };
            println!(
                "step {at}/{total}: train {loss:.4}, validation {}{fall}, open loop {} mm{waypoint}, lr {lr:.2e}, {:.1} samples/s",
                row.val.map(|v| format!("{v:.4}")).unwrap_or_else(|| "-".into()),
                mm(row.open_loop_mm),
                tally.samples_per_s()
            )
        });
        Ok(())
    }

    /// The run's end: the ranks' weight check, the final checkpoint (the newest saved, or one
    /// saved now), and rank 0's loss log and plot.
    fn finish(
        &self,
        trainer: &Trainer,
        ckpt: &mut Checkpointer<'_>,
        log: &[LossRow],
    ) -> Result<(Option<f64>, PathBuf), TrainError> {
        let ranks_weight_diff = match self.ranks.group {
            None => None,
            Some(g) => Some(trainer.weight_diff(g).map_err(dist_err)?),
        };
        let checkpoint = match last_checkpoint(&self.opts.out) {
            Some(dir) => dir,
            None => ckpt.save(trainer)?,
        };
        if self.ranks.lead {
            write_loss_csv(self.csv, log)?;
            let title = format!(
                "labrig train: {} target + {} co-training episodes, w = {}, batch {}",
                self.counts.train, self.counts.cotrain, self.w, self.opts.preset.train.batch_size
            );
            if let Err(e) = plot_loss(log, &title, &self.opts.out.join("loss.png")) {
                eprintln!("warning: {e}");
            }
        }
        Ok((ranks_weight_diff, checkpoint))
    }

    /// The run's figures.
    fn report(
        &self,
        trainer: &Trainer,
        sampler: &CotrainSampler,
        tally: &Tally,
        ranks_weight_diff: Option<f64>,
        checkpoint: PathBuf,
    ) -> RunReport {
        let (c, sets) = (&self.counts, self.sets);
        RunReport {
            steps: trainer.step,
            resumed_from: self.resumed_from,
            target_episodes: c.train,
            val_episodes: c.val,
            cotrain_episodes: c.cotrain,
            skipped_unsuccessful: c.skipped,
            correction_episodes: sets.correction_episodes,
            correction_samples: sets.correction_samples,
            missed_grasps: sets.missed_grasps,
            mistake_windows: sets.mistake_windows,
            w: self.w,
            drawn_target: sampler.drawn_target,
            drawn_cotrain: sampler.drawn_cotrain,
            first_val_loss: self.first_val,
            last_val_loss: tally.last_val,
            last_open_loop_mm: tally.last_open_loop,
            last_waypoint_mm: tally.last_waypoint,
            last_first_waypoint_mm: tally.last_first_waypoint,
            last_train_loss: tally.last_train,
            samples_per_s: tally.samples_per_s(),
            loader_share: tally.load_s / tally.step_s.max(1e-9),
            decode_s: c.decode_s,
            threads: self.threads,
            world_size: self.ranks.world,
            ranks_weight_diff,
            allreduce_share: self.ranks.group.map(|_| trainer.comm_s / tally.step_s.max(1e-9)),
            checkpoint,
        }
    }
}

/// Writes `run.json` (the run's figures) into `out`.
fn write_run_json(out: &Path, report: &RunReport) -> Result<(), TrainError> {
    let path = out.join("run.json");
    let mut f = std::fs::File::create(&path).map_err(io(&path, "writing"))?;
    f.write_all(serde_json::to_string_pretty(report).unwrap_or_default().as_bytes()).map_err(io(&path, "writing"))?;
    Ok(())
}

/// One batch of several sets' samples.
fn concat(mut parts: Vec<Batch>) -> Batch {
    if parts.len() == 1 {
        return parts.pop().expect("one");
    }
    let cams = parts[0].images.len();
    let images = (0..cams)
        .map(|k| Tensor::cat(&parts.iter().map(|p| p.images[k].shallow_clone()).collect::<Vec<_>>(), 0))
        .collect();
    let cat = |f: &dyn Fn(&Batch) -> Tensor| Tensor::cat(&parts.iter().map(f).collect::<Vec<_>>(), 0);
    let mut episodes: Vec<String> = parts.iter().flat_map(|p| p.episodes.iter().cloned()).collect();
    episodes.sort();
    episodes.dedup();
    Batch {
        images,
        state: cat(&|p| p.state.shallow_clone()),
        action: cat(&|p| p.action.shallow_clone()),
        waypoint: cat(&|p| p.waypoint.shallow_clone()),
        episodes,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use labrig_msgs::rig::Step;

    #[test]
    fn the_learning_rate_warms_up_then_follows_a_cosine() {
        assert!((lr_factor(0, 10, 100) - 0.1).abs() < 1e-12);
        assert!((lr_factor(9, 10, 100) - 1.0).abs() < 1e-12);
        assert!((lr_factor(10, 10, 100) - 1.0).abs() < 1e-12);
        assert!((lr_factor(55, 10, 100) - 0.5).abs() < 1e-12);
        assert!(lr_factor(100, 10, 100).abs() < 1e-12);
        assert_eq!(ema_decay(0, 0.75, 0.9999), 0.0);
        assert!((ema_decay(1, 0.75, 0.9999) - (1.0 - 2f64.powf(-0.75))).abs() < 1e-12);
        assert_eq!(ema_decay(10_000_000, 0.75, 0.9999), 0.9999);
    }

    #[test]
    fn presets_resolve_by_name_or_from_toml_overrides() {
        assert_eq!(Preset::resolve("small").unwrap().model, DiffusionConfig::small());
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("p.toml");
        std::fs::write(&f, "preset = \"small\"\n[model]\nimage_size = 32\ncrop_size = 28\n[train]\nbatch_size = 8\n")
            .unwrap();
        let p = Preset::resolve(f.to_str().unwrap()).unwrap();
        assert_eq!((p.model.image_size, p.model.crop_size, p.train.batch_size), (32, 28, 8));
        assert_eq!(p.model.down_dims, DiffusionConfig::small().down_dims);
        std::fs::write(&f, "[model]\nimage_sise = 32\n").unwrap();
        let e = Preset::resolve(f.to_str().unwrap()).unwrap_err().to_string();
        assert!(e.contains("image_sise"), "{e}");
        let e = Preset::resolve("big").unwrap_err().to_string();
        assert!(
            e.contains(
                "neither a preset (paper_dp, small, small_vision, small_vision_recover, small_lowdim) nor a TOML file"
            ),
            "{e}"
        );
        std::fs::write(
            &f,
            "preset = \"small_lowdim\"\n[model]\naction_relative = true\naction_space = \"cartesian_velocity\"\n",
        )
        .unwrap();
        let e = Preset::resolve(f.to_str().unwrap()).unwrap_err().to_string();
        assert!(e.contains("action_relative applies to eef_axis_angle"), "{e}");
        std::fs::write(&f, "preset = \"small_vision\"\n[model]\nencoder_width = 13\n").unwrap();
        let e = Preset::resolve(f.to_str().unwrap()).unwrap_err().to_string();
        assert!(e.contains("encoder_width = 13"), "{e}");
        std::fs::write(&f, "preset = \"small_vision\"\n[model]\nimage_obs_steps = 3\n").unwrap();
        let e = Preset::resolve(f.to_str().unwrap()).unwrap_err().to_string();
        assert!(e.contains("image_obs_steps = 3 must be in 0..=2"), "{e}");
        assert_eq!(Preset::resolve("small_vision").unwrap().model, DiffusionConfig::small_vision());
        // The shipped recipe is the TOML it was trained with (tests/fixtures/policies/small_vision_recover).
        let f = dir.path().join("recover.toml");
        std::fs::write(
            &f,
            "preset = \"small_vision\"\n[model]\nwaypoint = true\n[train]\nbatch_size = 128\nlr = 1e-3\ncheckpoint_every = 500\nval_every = 500\nskip_missed_grasps = true\n",
        )
        .unwrap();
        assert_eq!(Preset::resolve(f.to_str().unwrap()).unwrap(), Preset::resolve("small_vision_recover").unwrap());
    }

    /// A batch holding NaN is refused: the weights are untouched and the episodes named.
    #[test]
    fn relative_actions_are_targets_minus_the_newest_observed_tcp() {
        // One 5-step episode: the TCP at x = k, the target at x = k + 0.5 (y, z likewise).
        let t = 5;
        let state = Tensor::arange(t, (Kind::Float, Device::Cpu)).unsqueeze(1).repeat([1, 7]);
        let action = &state + 0.5;
        let ep = EpisodeTensors {
            path: "ep".into(),
            uuid: "ep".into(),
            success: Some(true),
            state,
            action,
            frames: Tensor::zeros([t, 0, 3, 1, 1], (Kind::Uint8, Device::Cpu)),
            source: vec![Step::SOURCE_SCRIPTED; t as usize],
        };
        let cfg = DiffusionConfig { horizon: 4, n_action_steps: 2, ..DiffusionConfig::tiny() };
        let abs = SampleSet::new(std::slice::from_ref(&ep), &cfg);
        let rel = SampleSet::new(&[ep], &DiffusionConfig { action_relative: true, ..cfg });
        // Window t = 2: observations 1, 2; actions 1..=4.
        let a = Vec::<f32>::try_from(abs.actions(&[2]).get(0).select(1, 0)).unwrap();
        let r: Vec<Vec<f32>> = SampleSet::rows_of(&rel.actions(&[2]).get(0));
        assert_eq!(a, [1.5, 2.5, 3.5, 4.5]);
        // Positions relative to the TCP at step 2; orientation and gripper absolute.
        assert_eq!(r.iter().map(|row| row[0]).collect::<Vec<_>>(), [-0.5, 0.5, 1.5, 2.5]);
        assert_eq!(r[0][2], -0.5);
        assert_eq!(r[0][3..], [1.5; 4]);
        // The normaliser sees what the model is trained on.
        let rows = rel.action_rows_for_stats();
        assert_eq!(rows.len(), rel.len() * 4);
        assert!(rows.iter().all(|row| row[0] >= -1.0 && row[0] <= 3.5), "{rows:?}");
    }

    /// A correction episode (policy, then the operator for steps 4..=6, then policy) gives
    /// every window by default, and with `Operator` only those whose newest observation is an
    /// operator's step or lies `before` steps ahead of one; a demo gives all its windows.
    #[test]
    fn correction_episodes_give_the_operators_windows_when_asked() {
        let t = 10usize;
        let mut source = vec![Step::SOURCE_POLICY; t];
        source[4..=6].fill(Step::SOURCE_TELEOP);
        let ep = |source: Vec<u8>| EpisodeTensors {
            path: "ep".into(),
            uuid: "ep".into(),
            success: Some(true),
            state: Tensor::zeros([t as i64, 7], (Kind::Float, Device::Cpu)),
            action: Tensor::zeros([t as i64, 7], (Kind::Float, Device::Cpu)),
            frames: Tensor::zeros([t as i64, 0, 3, 1, 1], (Kind::Uint8, Device::Cpu)),
            source,
        };
        let cfg = DiffusionConfig { horizon: 4, n_action_steps: 3, n_obs_steps: 2, ..DiffusionConfig::tiny() };
        let newest = |set: &SampleSet| -> Vec<i64> { (0..set.len()).map(|i| set.obs_rows[i * 2 + 1]).collect() };
        let correction = ep(source.clone());
        assert!(correction.is_correction());
        let all = SampleSet::selecting(std::slice::from_ref(&correction), &cfg, Corrections::All, false);
        assert_eq!(newest(&all), (0..10).collect::<Vec<_>>());
        let op =
            SampleSet::selecting(std::slice::from_ref(&correction), &cfg, Corrections::Operator { before: 0 }, false);
        assert_eq!(newest(&op), [4, 5, 6]);
        let lead =
            SampleSet::selecting(std::slice::from_ref(&correction), &cfg, Corrections::Operator { before: 2 }, false);
        assert_eq!(newest(&lead), [2, 3, 4, 5, 6]);
        let demo = ep(vec![Step::SOURCE_SCRIPTED; t]);
        assert!(!demo.is_correction());
        assert_eq!(SampleSet::selecting(&[demo], &cfg, Corrections::Operator { before: 0 }, false).len(), 10);
    }

    /// With `skip_missed`, the windows whose labels hold a missed grasp's descent or close
    /// (steps 1..8 of `data::miss_then_grasp`) are left out; the recovery's stay.
    #[test]
    fn windows_holding_a_missed_grasp_are_left_out_when_asked() {
        let (state, action) = crate::data::miss_then_grasp();
        let t = state.size()[0] as usize;
        let ep = EpisodeTensors {
            path: "ep".into(),
            uuid: "ep".into(),
            success: Some(true),
            state,
            action,
            frames: Tensor::zeros([t as i64, 0, 3, 1, 1], (Kind::Uint8, Device::Cpu)),
            source: vec![Step::SOURCE_SCRIPTED; t],
        };
        let cfg = DiffusionConfig { horizon: 4, n_action_steps: 3, n_obs_steps: 2, ..DiffusionConfig::tiny() };
        let newest = |set: &SampleSet| -> Vec<i64> { (0..set.len()).map(|i| set.obs_rows[i * 2 + 1]).collect() };
        let all = SampleSet::selecting(std::slice::from_ref(&ep), &cfg, Corrections::All, false);
        assert_eq!((all.len(), all.missed_grasps), (t, 0));
        let kept = SampleSet::selecting(std::slice::from_ref(&ep), &cfg, Corrections::All, true);
        // A window at t holds actions t-1..=t+2: those touching 1..=7 go (t = 0..=8).
        assert_eq!(newest(&kept), (9..t as i64).collect::<Vec<_>>());
        assert_eq!((kept.missed_grasps, kept.mistake_windows), (1, 9));
    }

    #[test]
    fn a_batch_with_nan_is_refused_and_named() {
        tch::manual_seed(1);
        let cfg = DiffusionConfig::tiny();
        let mut tr = Trainer::new(&cfg, &TrainConfig::default()).unwrap();
        let b = 2;
        let batch = Batch {
            images: vec![Tensor::rand([b, 2, 3, 32, 32], (Kind::Float, Device::Cpu))],
            state: Tensor::zeros([b, 2, 7], (Kind::Float, Device::Cpu)),
            action: Tensor::zeros([b, 16, 7], (Kind::Float, Device::Cpu)),
            waypoint: Tensor::zeros([b, 3], (Kind::Float, Device::Cpu)),
            episodes: vec!["ep-a".into()],
        };
        let noise = Tensor::randn([b, 16, 7], (Kind::Float, Device::Cpu));
        assert!(tr.step(&batch, 1e-4, &noise, &[3, 50]).is_ok());
        let before: Vec<Tensor> = tr.vs.trainable_variables().iter().map(|v| v.copy()).collect();
        let _ = batch.action.get(1).get(3).get(2).fill_(f64::NAN);
        let (what, eps) = tr.step(&batch, 1e-4, &noise, &[3, 50]).unwrap_err();
        assert_eq!((what, eps), ("the batch", vec!["ep-a".to_owned()]));
        for (a, b) in before.iter().zip(tr.vs.trainable_variables()) {
            assert!(a.equal(&b));
        }
        assert_eq!(tr.step, 1);
    }
}
