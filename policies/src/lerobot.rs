//! `labrig policy import-lerobot`: a LeRobot (0.4.x) Diffusion Policy directory, as its
//! `save_pretrained` writes it (`config.json`, `model.safetensors`, the pre/post-processor
//! pipelines with the normaliser statistics), converted into a labrig checkpoint without
//! re-training: the config mapped field by field, the weights by name (LeRobot's `diffusion.`
//! prefix dropped; the spatial-softmax `pos_grid` buffers labrig computes), the statistics
//! with LeRobot's arithmetic kept (its zero-range eps, its image mean-std eps).
//!
//! What labrig's model does not implement is refused by name (another backbone, BatchNorm, a
//! shared encoder, DDPM sampling, another beta schedule or prediction type, resized inputs,
//! an environment-state input).

use crate::checkpoint::{self, CheckpointMeta, MeanStd};
use crate::normalize::MinMax;
use crate::policy::{ActionSpace, DiffusionConfig, DiffusionPolicy};
use serde_json::Value;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use tch::Tensor;

#[derive(Debug, thiserror::Error)]
pub enum ImportError {
    #[error("{}: {reason}", path.display())]
    Bad { path: PathBuf, reason: String },
    #[error("{}: labrig's Diffusion Policy does not implement {what} (LeRobot's `{field}` = {value})", path.display())]
    Unsupported { path: PathBuf, field: &'static str, value: String, what: &'static str },
    #[error(transparent)]
    Checkpoint(#[from] checkpoint::CheckpointError),
    #[error(transparent)]
    Policy(#[from] crate::policy::PolicyError),
}

fn bad(path: &Path, reason: impl Into<String>) -> ImportError {
    ImportError::Bad { path: path.to_owned(), reason: reason.into() }
}

fn read_json(path: &Path) -> Result<(String, Value), ImportError> {
    let text = std::fs::read_to_string(path).map_err(|e| bad(path, e.to_string()))?;
    let v = serde_json::from_str(&text).map_err(|e| bad(path, e.to_string()))?;
    Ok((text, v))
}

/// LeRobot's `config.json` as labrig's config. `text` is the file itself: the cameras keep
/// its order (the encoders' order), which a parsed JSON object does not.
pub fn config_of(path: &Path, text: &str, c: &Value) -> Result<DiffusionConfig, ImportError> {
    let field = |k: &'static str| c.get(k).ok_or_else(|| bad(path, format!("no `{k}`")));
    let int = |k: &'static str| field(k)?.as_i64().ok_or_else(|| bad(path, format!("`{k}` is not an integer")));
    let ints = |k: &'static str| -> Result<Vec<i64>, ImportError> {
        field(k)?
            .as_array()
            .and_then(|a| a.iter().map(Value::as_i64).collect::<Option<Vec<_>>>())
            .ok_or_else(|| bad(path, format!("`{k}` is not a list of integers")))
    };
    let unsupported = |field: &'static str, value: &Value, what: &'static str| ImportError::Unsupported {
        path: path.to_owned(),
        field,
        value: value.to_string(),
        what,
    };
    let want = |k: &'static str, ok: &dyn Fn(&Value) -> bool, what: &'static str| -> Result<(), ImportError> {
        let v = c.get(k).unwrap_or(&Value::Null);
        if ok(v) { Ok(()) } else { Err(unsupported(k, v, what)) }
    };
    if c.get("type").and_then(Value::as_str) != Some("diffusion") {
        return Err(bad(path, format!("not a Diffusion Policy (type {})", c.get("type").unwrap_or(&Value::Null))));
    }
    want("vision_backbone", &|v| v == "resnet18", "a backbone other than ResNet-18")?;
    want("use_group_norm", &|v| v == true, "BatchNorm (only the GroupNorm ResNet)")?;
    want("use_separate_rgb_encoder_per_camera", &|v| v == true, "one encoder shared by the cameras")?;
    want("noise_scheduler_type", &|v| v == "DDIM", "sampling other than DDIM")?;
    want("beta_schedule", &|v| v == "squaredcos_cap_v2", "a beta schedule other than squared cosine")?;
    want("prediction_type", &|v| v == "epsilon" || v == "sample", "a prediction type other than epsilon or sample")?;
    want("resize_shape", &|v| v.is_null(), "resizing inputs inside the policy")?;
    want(
        "spatial_softmax_num_keypoints",
        &|v| v.as_i64().is_some_and(|k| k > 0),
        "a pooling other than spatial softmax",
    )?;

    let inputs = field("input_features")?.as_object().ok_or_else(|| bad(path, "`input_features` is not an object"))?;
    let mut cameras: Vec<(usize, String, Vec<i64>)> = Vec::new();
    let mut state_dim = None;
    for (key, feature) in inputs {
        let shape: Vec<i64> = feature
            .get("shape")
            .and_then(Value::as_array)
            .map(|a| a.iter().filter_map(Value::as_i64).collect())
            .unwrap_or_default();
        match (key.strip_prefix("observation.images."), key.as_str()) {
            (Some(cam), _) => {
                let at = text.find(&format!("\"{key}\"")).unwrap_or(usize::MAX);
                cameras.push((at, cam.to_owned(), shape));
            }
            (None, "observation.state") => state_dim = shape.first().copied(),
            // DROID's sub-keys: a dataset of DROID's keys, whose `observation.state` is joints.
            (None, other) if other.starts_with("observation.state.") => {
                return Err(bad(
                    path,
                    format!(
                        "input `{other}`: trained on DROID's keys (a joint-space observation.state); labrig's Diffusion Policy reads the TCP pose: train on `labrig export lerobot --schema labrig`"
                    ),
                ));
            }
            (None, other) => return Err(unsupported("input_features", &Value::String(other.into()), "this input")),
        }
    }
    cameras.sort();
    let state_dim = state_dim.ok_or_else(|| bad(path, "no `observation.state` input"))?;
    let image_size = match cameras.first() {
        Some((_, _, s)) => s.get(1).copied().unwrap_or(0),
        None => 0,
    };
    for (_, cam, s) in &cameras {
        if s.len() != 3 || s[0] != 3 || s[1] != s[2] || s[1] != image_size {
            return Err(bad(
                path,
                format!("camera {cam}: image shape {s:?}; labrig needs the same square (3, S, S) for every camera"),
            ));
        }
    }
    let crop = match c.get("crop_shape") {
        Some(Value::Null) | None => image_size,
        Some(v) => {
            let s = ints("crop_shape")?;
            if s.len() != 2 || s[0] != s[1] {
                return Err(unsupported("crop_shape", v, "a non-square crop"));
            }
            s[0]
        }
    };
    let action_dim = field("output_features")?
        .get("action")
        .and_then(|a| a.get("shape"))
        .and_then(Value::as_array)
        .and_then(|a| a.first())
        .and_then(Value::as_i64)
        .ok_or_else(|| bad(path, "no `action` output with a shape"))?;
    let clip = match field("clip_sample")?.as_bool() {
        Some(true) => {
            Some(field("clip_sample_range")?.as_f64().ok_or_else(|| bad(path, "`clip_sample_range` is not a number"))?)
        }
        _ => None,
    };
    let train_steps = int("num_train_timesteps")? as usize;
    Ok(DiffusionConfig {
        cameras: cameras.into_iter().map(|(_, c, _)| c).collect(),
        image_size,
        crop_size: crop,
        keypoints: int("spatial_softmax_num_keypoints")?,
        state_dim,
        action_dim,
        n_obs_steps: int("n_obs_steps")?,
        horizon: int("horizon")?,
        n_action_steps: int("n_action_steps")?,
        down_dims: ints("down_dims")?,
        kernel_size: int("kernel_size")?,
        n_groups: int("n_groups")?,
        step_embed_dim: int("diffusion_step_embed_dim")?,
        film_scale: field("use_film_scale_modulation")?.as_bool().unwrap_or(false),
        train_steps,
        inference_steps: c
            .get("num_inference_steps")
            .and_then(Value::as_u64)
            .map(|n| n as usize)
            .unwrap_or(train_steps),
        clip,
        action_space: ActionSpace::default(),
        scene_state: false,
        scene_yaw: false,
        scene_relative: false,
        action_relative: false,
        prediction: if c.get("prediction_type").and_then(Value::as_str) == Some("sample") {
            crate::schedule::Prediction::Sample
        } else {
            crate::schedule::Prediction::Epsilon
        },
        // labrig's state is the TCP pose (7) and, 8 wide, the gripper after it: what
        // `labrig export lerobot --schema labrig` writes as `observation.state`.
        gripper_state: state_dim == 8,
        encoder: crate::encoder::Backbone::Resnet18,
        encoder_width: 16,
        image_obs_steps: 0,
        waypoint: false,
        waypoint_weight: 1.0,
        mask_state_xy: false,
    })
}

/// The normaliser's statistics: the pre-processor pipeline's `normalizer_processor` step.
fn statistics(dir: &Path, cfg: &DiffusionConfig) -> Result<(MinMax, MinMax, BTreeMap<String, MeanStd>), ImportError> {
    let pipeline = dir.join("policy_preprocessor.json");
    let (_, p) = read_json(&pipeline)?;
    let step = p
        .get("steps")
        .and_then(Value::as_array)
        .and_then(|s| s.iter().find(|s| s.get("registry_name").and_then(Value::as_str) == Some("normalizer_processor")))
        .ok_or_else(|| bad(&pipeline, "no normalizer_processor step"))?;
    let config = step.get("config").cloned().unwrap_or(Value::Null);
    let eps = config.get("eps").and_then(Value::as_f64).unwrap_or(1e-8) as f32;
    let modes = config.get("norm_map").cloned().unwrap_or(Value::Null);
    for (kind, want) in [("VISUAL", "MEAN_STD"), ("STATE", "MIN_MAX"), ("ACTION", "MIN_MAX")] {
        let got = modes.get(kind).and_then(Value::as_str).unwrap_or("?");
        if got != want && !(kind == "VISUAL" && cfg.cameras.is_empty()) {
            return Err(bad(&pipeline, format!("{kind} normalised with {got}; labrig imports {want}")));
        }
    }
    let file = step
        .get("state_file")
        .and_then(Value::as_str)
        .ok_or_else(|| bad(&pipeline, "the normaliser has no state_file"))?;
    let stats_path = dir.join(file);
    let stats: BTreeMap<String, Tensor> =
        Tensor::read_safetensors(&stats_path).map_err(|e| bad(&stats_path, e.to_string()))?.into_iter().collect();
    let vec = |k: &str| -> Result<Vec<f32>, ImportError> {
        let t = stats.get(k).ok_or_else(|| {
            bad(&stats_path, format!("no statistic `{k}` (the file has {:?})", stats.keys().collect::<Vec<_>>()))
        })?;
        Vec::<f32>::try_from(t.to_kind(tch::Kind::Float).flatten(0, -1)).map_err(|e| bad(&stats_path, e.to_string()))
    };
    let min_max = |k: &str| -> Result<MinMax, ImportError> {
        Ok(MinMax { min: vec(&format!("{k}.min"))?, max: vec(&format!("{k}.max"))?, zero_range_eps: Some(eps) })
    };
    let mut images = BTreeMap::new();
    for cam in &cfg.cameras {
        let three = |s: &str| -> Result<[f32; 3], ImportError> {
            let v = vec(&format!("observation.images.{cam}.{s}"))?;
            v.try_into()
                .map_err(|v: Vec<f32>| bad(&stats_path, format!("camera {cam}: {s} has {} values, not 3", v.len())))
        };
        images.insert(cam.clone(), MeanStd { mean: three("mean")?, std: three("std")?, eps });
    }
    Ok((min_max("observation.state")?, min_max("action")?, images))
}

/// What an import did.
#[derive(Debug)]
pub struct Imported {
    pub config: DiffusionConfig,
    pub tensors: usize,
    pub parameters: i64,
}

/// Converts the LeRobot directory `dir` into a labrig checkpoint at `out`.
pub fn import(dir: &Path, out: &Path) -> Result<Imported, ImportError> {
    let config_path = dir.join("config.json");
    let (text, c) = read_json(&config_path)?;
    let config = config_of(&config_path, &text, &c)?;
    let (state_stats, action_stats, image_stats) = statistics(dir, &config)?;
    let weights = dir.join("model.safetensors");
    let mut theirs: BTreeMap<String, Tensor> =
        Tensor::read_safetensors(&weights).map_err(|e| bad(&weights, e.to_string()))?.into_iter().collect();
    theirs.retain(|k, _| !k.ends_with(".pos_grid"));
    let vs = tch::nn::VarStore::new(tch::Device::Cpu);
    let _policy = DiffusionPolicy::new(vs.root(), config.clone())?;
    let mut ours = vs.variables();
    let mut missing = Vec::new();
    tch::no_grad(|| {
        for (name, var) in ours.iter_mut() {
            match theirs.remove(&format!("diffusion.{name}")) {
                Some(t) if t.size() == var.size() => {
                    var.copy_(&t.to_kind(var.kind()));
                }
                Some(t) => missing.push(format!("{name} (shape {:?} there, {:?} here)", t.size(), var.size())),
                None => missing.push(name.clone()),
            }
        }
    });
    if !missing.is_empty() || !theirs.is_empty() {
        missing.sort();
        let extra: Vec<&String> = theirs.keys().collect();
        return Err(bad(
            &weights,
            format!("the weights do not match the config: missing or mismatched {missing:?}; unexpected {extra:?}"),
        ));
    }
    let parameters = ours.values().map(|t| t.numel() as i64).sum();
    let meta = CheckpointMeta {
        format: checkpoint::FORMAT,
        config: config.clone(),
        action_stats,
        state_stats,
        image_stats,
        manifest: vec![format!("imported from LeRobot: {}", dir.display())],
        step: 0,
    };
    checkpoint::save(out, &meta, &vs, None)?;
    Ok(Imported { config, tensors: ours.len(), parameters })
}
