//! One action chunk from a checkpoint, for an observation and initial noise given as tensors
//! in LeRobot's names and layouts: `observation.images.<camera>` (B, To, 3, H, W) in [0, 1],
//! `observation.state` (B, To, state_dim) and `noise` (B, Tp, action_dim); the result is
//! `action` (B, Tp, action_dim) in the robot's units (the whole chunk) and `action.executed`
//! (B, Ta, action_dim), the steps a rollout executes.

use crate::checkpoint::CheckpointMeta;
use crate::normalize::NormalizeError;
use crate::policy::{DiffusionPolicy, PolicyError, Trace};
use std::collections::BTreeMap;
use tch::{Kind, Tensor};

#[derive(Debug, thiserror::Error)]
pub enum InferError {
    #[error("no tensor `{name}` in the observation (it has {has:?})")]
    Missing { name: String, has: Vec<String> },
    #[error("the checkpoint has image statistics for {has:?} but none for camera `{camera}`")]
    ImageStats { camera: String, has: Vec<String> },
    #[error("normaliser statistics: {0}")]
    Normalize(#[from] NormalizeError),
    #[error(transparent)]
    Policy(#[from] PolicyError),
    #[error("real-time chunking: {0}")]
    Prefix(#[from] crate::rtc::RtcError),
}

/// A chunk in the robot's units beside the model's trace.
#[derive(Debug)]
pub struct Inference {
    pub trace: Trace,
    /// (B, Tp, action_dim), unnormalised.
    pub action: Tensor,
    /// (B, Ta, action_dim), unnormalised.
    pub executed: Tensor,
    /// What the model saw: normalised images per camera and state.
    pub images: Vec<Tensor>,
    pub state: Tensor,
}

fn take<'a>(named: &'a BTreeMap<String, Tensor>, name: &str) -> Result<&'a Tensor, InferError> {
    named.get(name).ok_or_else(|| InferError::Missing { name: name.to_owned(), has: named.keys().cloned().collect() })
}

/// The observation in `named` normalised as the checkpoint says: images per camera (its
/// mean-std statistics where it has them), the state min-max.
pub fn observation(
    meta: &CheckpointMeta,
    named: &BTreeMap<String, Tensor>,
) -> Result<(Vec<Tensor>, Tensor), InferError> {
    let mut images = Vec::new();
    for camera in &meta.config.cameras {
        let img = take(named, &format!("observation.images.{camera}"))?;
        let img = match meta.image_stats.get(camera) {
            Some(s) => {
                let per_channel = |v: &[f32; 3]| Tensor::from_slice(v).view([3, 1, 1]).to_kind(img.kind());
                (img - per_channel(&s.mean)) / (per_channel(&s.std) + f64::from(s.eps))
            }
            None if !meta.image_stats.is_empty() => {
                return Err(InferError::ImageStats {
                    camera: camera.clone(),
                    has: meta.image_stats.keys().cloned().collect(),
                });
            }
            None => img.shallow_clone(),
        };
        images.push(img);
    }
    let state = meta.state_stats.normalize(take(named, "observation.state")?)?;
    Ok((images, state))
}

/// One chunk from `noise` (deterministic given it).
pub fn infer(
    policy: &DiffusionPolicy,
    meta: &CheckpointMeta,
    named: &BTreeMap<String, Tensor>,
    noise: &Tensor,
) -> Result<Inference, InferError> {
    let (images, state) = observation(meta, named)?;
    let trace = tch::no_grad(|| policy.sample_traced(&images, &state, noise))?;
    let action = to_robot(meta, named, &trace.chunk)?;
    let executed = policy.executed(&action);
    Ok(Inference { trace, action, executed, images, state })
}

/// A normalised chunk (B, Tp, action_dim) in the robot's units: with `action_relative`, the
/// TCP's position at the newest observation added back to the target positions.
fn to_robot(meta: &CheckpointMeta, named: &BTreeMap<String, Tensor>, chunk: &Tensor) -> Result<Tensor, InferError> {
    let mut action = meta.action_stats.unnormalize(chunk)?;
    if meta.config.action_relative {
        let raw = take(named, "observation.state")?;
        action += crate::data::tcp_offset(&raw.select(1, -1), action.size()[2], action.kind());
    }
    Ok(action)
}

/// The rows of the chunk a loop is executing, from the newest observation's tick on, in the
/// robot's units (row-major): what real-time chunking guides the next chunk toward.
#[derive(Debug, Clone, Copy)]
pub struct Prefix<'a> {
    pub actions: &'a [f64],
    /// Rows the loop executes from them before the new chunk starts (d).
    pub frozen: usize,
    /// beta, the clip of the guidance weight.
    pub max_weight: f64,
    pub method: crate::rtc::Method,
}

/// [`infer`] guided toward `prefix` ([`crate::rtc`]); the result's `action` (B = 1). The
/// frozen rows are not yet overwritten (the caller does, in f64: [`crate::rtc::freeze`]).
pub fn infer_guided(
    policy: &DiffusionPolicy,
    meta: &CheckpointMeta,
    named: &BTreeMap<String, Tensor>,
    noise: &Tensor,
    prefix: Prefix<'_>,
) -> Result<Tensor, InferError> {
    let c = &meta.config;
    let (width, offset) = (c.action_dim as usize, (c.n_obs_steps - 1) as usize);
    let chunk_rows = (c.horizon - c.n_obs_steps + 1) as usize;
    let rows = crate::rtc::prefix_rows(prefix.actions.len(), width, chunk_rows, prefix.frozen)?;
    let (images, state) = observation(meta, named)?;
    // The prefix in the model's space: the model's row offset + i is the chunk's row i.
    let mut target = vec![0f32; c.horizon as usize * width];
    for (i, v) in prefix.actions.iter().enumerate() {
        target[offset * width + i] = *v as f32;
    }
    let mut target = Tensor::from_slice(&target).view([1, c.horizon, c.action_dim]);
    if c.action_relative {
        let raw = take(named, "observation.state")?;
        target -= crate::data::tcp_offset(&raw.select(1, -1), c.action_dim, Kind::Float);
    }
    let target = meta.action_stats.normalize(&target)?;
    let weights = crate::rtc::prefix_weights(c.horizon as usize, offset, prefix.frozen, rows);
    let guide = crate::rtc::Guide { target, weights, max_weight: prefix.max_weight, method: prefix.method };
    let chunk = tch::no_grad(|| policy.sample_guided(&images, &state, noise, &guide))?;
    to_robot(meta, named, &chunk)
}
