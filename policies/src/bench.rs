//! `labrig bench policy`: the Diffusion Policy's speed on this machine. Inference of one
//! chunk at batch 1 (the encoders on one observation, one U-Net call, the whole DDIM chunk),
//! p50/p99 over many runs, and training throughput (samples/s) on synthetic batches, for a
//! preset. Figures from a shared, noisy 2-core machine: compare ratios within one run.

use crate::policy::{DiffusionConfig, DiffusionPolicy, PolicyError};
use crate::train::{Batch, Preset, TrainError, Trainer};
use labrig_episode::inspect::Percentiles;
use serde::Serialize;
use std::time::Instant;
use tch::{Device, Kind, Tensor};

/// Times per stage, ms.
#[derive(Debug, Clone, Serialize)]
pub struct Inference {
    pub encoder_ms: Percentiles,
    pub unet_step_ms: Percentiles,
    pub chunk_ms: Percentiles,
    pub parameters: i64,
}

fn time_ms(runs: usize, warmup: usize, mut f: impl FnMut()) -> Percentiles {
    for _ in 0..warmup {
        f();
    }
    let v: Vec<f64> = (0..runs.max(1))
        .map(|_| {
            let t = Instant::now();
            f();
            t.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    Percentiles::of(v).expect("at least one run")
}

fn observation(cfg: &DiffusionConfig, b: i64) -> (Vec<Tensor>, Tensor) {
    let opts = (Kind::Float, Device::Cpu);
    let images = cfg
        .cameras
        .iter()
        .map(|_| Tensor::rand([b, cfg.n_obs_steps, 3, cfg.image_size, cfg.image_size], opts))
        .collect();
    (images, Tensor::rand([b, cfg.n_obs_steps, cfg.state_dim], opts) * 2.0 - 1.0)
}

/// One chunk at batch 1 with random weights (the time does not depend on their values).
pub fn inference(cfg: &DiffusionConfig, runs: usize, warmup: usize) -> Result<Inference, PolicyError> {
    tch::manual_seed(0);
    let vs = tch::nn::VarStore::new(Device::Cpu);
    let policy = DiffusionPolicy::new(vs.root(), cfg.clone())?;
    let parameters = vs.variables().values().map(|t| t.numel() as i64).sum();
    let (images, state) = observation(cfg, 1);
    let noise = Tensor::randn([1, cfg.horizon, cfg.action_dim], (Kind::Float, Device::Cpu));
    let (cond, _) = tch::no_grad(|| policy.global_cond(&images, &state, false))?;
    let encoder_ms = time_ms(runs, warmup, || {
        let _ = tch::no_grad(|| policy.encode(&images, 1, false));
    });
    let unet_step_ms = time_ms(runs, warmup, || {
        let _ = tch::no_grad(|| policy.denoise(&noise, 50, &cond));
    });
    let chunk_ms = time_ms(runs, warmup, || {
        let _ = tch::no_grad(|| policy.sample(&images, &state, &noise));
    });
    Ok(Inference { encoder_ms, unet_step_ms, chunk_ms, parameters })
}

/// One chunk at batch 1 (random weights) sampled with each of `steps` DDIM steps: what
/// fewer steps save (the encoders run once either way).
pub fn chunk_by_steps(
    cfg: &DiffusionConfig,
    steps: &[usize],
    runs: usize,
    warmup: usize,
) -> Result<Vec<(usize, Percentiles)>, PolicyError> {
    tch::manual_seed(0);
    let vs = tch::nn::VarStore::new(Device::Cpu);
    let mut policy = DiffusionPolicy::new(vs.root(), cfg.clone())?;
    let (images, state) = observation(cfg, 1);
    let noise = Tensor::randn([1, cfg.horizon, cfg.action_dim], (Kind::Float, Device::Cpu));
    let mut out = Vec::new();
    for &n in steps {
        policy.set_inference_steps(n)?;
        let ms = time_ms(runs, warmup, || {
            let _ = tch::no_grad(|| policy.sample(&images, &state, &noise));
        });
        out.push((n, ms));
    }
    Ok(out)
}

/// A checkpoint's open-loop error per DDIM step count on recorded episodes.
#[derive(Debug, Clone, Serialize)]
pub struct OpenLoop {
    pub inference_steps: usize,
    /// Mean distance (mm) between the executed rows' target positions and the recorded ones,
    /// over `samples` windows spread across the episodes, each from the same fixed noise.
    pub open_loop_mm: f64,
    pub samples: usize,
}

/// [`OpenLoop`] for each of `steps`: the checkpoint at `dir` on the successful episodes at
/// `episodes` (ones it was not trained on, for a fair figure), `samples` windows.
pub fn open_loop_by_steps(
    dir: &std::path::Path,
    episodes: &[std::path::PathBuf],
    steps: &[usize],
    samples: usize,
) -> Result<Vec<OpenLoop>, TrainError> {
    use crate::train::{SampleSet, Validation};
    let (_vs, mut policy, meta) = crate::checkpoint::load(&crate::checkpoint::resolve(dir)?, Device::Cpu)?;
    let cfg = meta.config.clone();
    let (eps, _) = crate::train::load_set(episodes, &cfg, None, false, false, "episodes")?;
    let set = SampleSet::new(&eps, &cfg);
    if set.is_empty() {
        return Err(TrainError::Setup(format!("no successful episode with samples among {} given", episodes.len())));
    }
    let n = samples.min(set.len());
    // The windows' noise comes from torch's generator: seeded, so a rerun gives the same figure.
    tch::manual_seed(0);
    let val = Validation::new(&set, (&meta.state_stats, &meta.action_stats), &cfg, n, n, 0)?;
    let mut out = Vec::new();
    for &k in steps {
        policy.set_inference_steps(k)?;
        let mm = val.open_loop_mm(&policy, &meta.action_stats, &cfg)?.ok_or_else(|| {
            TrainError::Setup(format!("open-loop error needs eef_axis_angle actions, not {:?}", cfg.action_space))
        })?;
        out.push(OpenLoop { inference_steps: k, open_loop_mm: mm, samples: n });
    }
    Ok(out)
}

/// Training steps on synthetic batches of the preset's size: samples/s (the model's share
/// only; `labrig train` reports the loader's share on real data).
pub fn training(preset: &Preset, steps: usize) -> Result<f64, TrainError> {
    let (cfg, tc) = (&preset.model, &preset.train);
    let mut trainer = Trainer::new(cfg, tc)?;
    let b = tc.batch_size as i64;
    let (images, state) = observation(cfg, b);
    let batch = Batch {
        images,
        state,
        action: Tensor::rand([b, cfg.horizon, cfg.action_dim], (Kind::Float, Device::Cpu)) * 2.0 - 1.0,
        waypoint: Tensor::rand([b, 3], (Kind::Float, Device::Cpu)) * 0.2 - 0.1,
        episodes: vec!["synthetic".into()],
    };
    let noise = Tensor::randn([b, cfg.horizon, cfg.action_dim], (Kind::Float, Device::Cpu));
    let t: Vec<i64> = (0..b).map(|i| i * 7 % cfg.train_steps as i64).collect();
    let step = |trainer: &mut Trainer| {
        trainer
            .step(&batch, tc.lr, &noise, &t)
            .map_err(|(what, _)| TrainError::Setup(format!("the synthetic batch's {what} is not finite")))
    };
    step(&mut trainer)?;
    let started = Instant::now();
    for _ in 0..steps.max(1) {
        step(&mut trainer)?;
    }
    Ok((steps.max(1) as i64 * b) as f64 / started.elapsed().as_secs_f64())
}
