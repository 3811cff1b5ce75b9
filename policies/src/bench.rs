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
