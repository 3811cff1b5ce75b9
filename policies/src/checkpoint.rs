//! A trained policy on disk: a directory holding
//! - `model.safetensors`: the weights (LeRobot's parameter names);
//! - `ema.safetensors`: the EMA weights inference uses, when training kept them;
//! - `checkpoint.json`: the model's config, the normaliser statistics (actions, state), the
//!   data manifest (the episodes trained on, by uuid) and the training step.
//!
//! Loading builds the model from the config and loads the weights by name (EMA first when
//! present), so a checkpoint carries everything inference needs.

use crate::normalize::MinMax;
use crate::policy::{DiffusionConfig, DiffusionPolicy, PolicyError};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use tch::nn::VarStore;

pub const WEIGHTS: &str = "model.safetensors";
pub const EMA_WEIGHTS: &str = "ema.safetensors";
pub const META: &str = "checkpoint.json";
/// The layout of `checkpoint.json`; a reader refuses a newer one.
pub const FORMAT: u32 = 1;

#[derive(Debug, thiserror::Error)]
pub enum CheckpointError {
    #[error(transparent)]
    Io(#[from] crate::FileError),
    #[error("{}: {source}", path.display())]
    Json {
        path: PathBuf,
        #[source]
        source: serde_json::Error,
    },
    #[error("{}: {what}: {source}", path.display())]
    Torch {
        path: PathBuf,
        what: &'static str,
        #[source]
        source: tch::TchError,
    },
    #[error("{}: checkpoint format {found}, this labrig reads up to {FORMAT}", path.display())]
    Format { path: PathBuf, found: u32 },
    #[error(transparent)]
    Policy(#[from] PolicyError),
}

/// A camera's per-channel image statistics: x -> (x - mean) / (std + eps).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MeanStd {
    pub mean: [f32; 3],
    pub std: [f32; 3],
    /// Added to `std` (in f32) before dividing: LeRobot's 1e-8.
    #[serde(default)]
    pub eps: f32,
}

/// Everything but the weights.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CheckpointMeta {
    pub format: u32,
    pub config: DiffusionConfig,
    pub action_stats: MinMax,
    pub state_stats: MinMax,
    /// Per camera, the images' mean-std normalisation (LeRobot's; labrig's own training feeds
    /// images in [0, 1] and leaves this empty).
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub image_stats: BTreeMap<String, MeanStd>,
    /// The episodes trained on (DROID uuids), target then co-training set.
    pub manifest: Vec<String>,
    pub step: u64,
}

/// Writes `meta`, the weights of `vs` and, if given, the EMA weights into `dir` (made if
/// missing; files replaced through a temporary name, so a crash leaves the last checkpoint).
pub fn save(dir: &Path, meta: &CheckpointMeta, vs: &VarStore, ema: Option<&VarStore>) -> Result<(), CheckpointError> {
    let io =
        |path: &Path, what, source| CheckpointError::from(crate::FileError { path: path.to_owned(), what, source });
    std::fs::create_dir_all(dir).map_err(|e| io(dir, "creating the checkpoint directory", e))?;
    let put_weights = |store: &VarStore, name: &str| -> Result<(), CheckpointError> {
        let path = dir.join(name);
        let tmp = dir.join(format!(".{name}.tmp.safetensors"));
        store.save(&tmp).map_err(|source| CheckpointError::Torch {
            path: path.clone(),
            what: "saving the weights",
            source,
        })?;
        std::fs::rename(&tmp, &path).map_err(|e| io(&path, "moving the weights into place", e))
    };
    put_weights(vs, WEIGHTS)?;
    if let Some(ema) = ema {
        put_weights(ema, EMA_WEIGHTS)?;
    }
    let path = dir.join(META);
    let text =
        serde_json::to_string_pretty(meta).map_err(|source| CheckpointError::Json { path: path.clone(), source })?;
    let tmp = dir.join(format!(".{META}.tmp"));
    std::fs::write(&tmp, text).map_err(|e| io(&path, "writing", e))?;
    std::fs::rename(&tmp, &path).map_err(|e| io(&path, "moving into place", e))
}

/// The policy of the checkpoint in `dir`, on `device`, with its EMA weights when it has them.
/// The checkpoint a path names: a checkpoint directory itself, a run's `checkpoints/last`
/// pointer, or a run directory (its last checkpoint).
pub fn resolve(path: &Path) -> Result<PathBuf, CheckpointError> {
    let pointer = |file: &Path| -> Result<PathBuf, CheckpointError> {
        let name = std::fs::read_to_string(file).map_err(crate::FileError::at(file, "reading"))?;
        Ok(file.with_file_name(name.trim()))
    };
    let dir = if path.join(META).is_file() {
        path.to_path_buf()
    } else if path.is_file() {
        pointer(path)?
    } else if path.join("checkpoints").join("last").is_file() {
        pointer(&path.join("checkpoints").join("last"))?
    } else {
        path.to_path_buf()
    };
    Ok(dir)
}

/// A checkpoint's id in chunks and episode metadata: `<run>@<step>` for a run's
/// `checkpoints/step_<n>`, else `<directory>@<step>`.
pub fn id(dir: &Path, step: u64) -> String {
    let name = |p: &Path| p.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let run = dir.parent().filter(|p| name(p) == "checkpoints").and_then(Path::parent);
    format!("{}@{step}", run.map_or_else(|| name(dir), name))
}

pub fn load(dir: &Path, device: tch::Device) -> Result<(VarStore, DiffusionPolicy, CheckpointMeta), CheckpointError> {
    let path = dir.join(META);
    let text = std::fs::read_to_string(&path).map_err(crate::FileError::at(&path, "reading"))?;
    let meta: CheckpointMeta =
        serde_json::from_str(&text).map_err(|source| CheckpointError::Json { path: path.clone(), source })?;
    if meta.format > FORMAT {
        return Err(CheckpointError::Format { path, found: meta.format });
    }
    let mut vs = VarStore::new(device);
    let policy = DiffusionPolicy::new(vs.root(), meta.config.clone())?;
    let weights =
        [EMA_WEIGHTS, WEIGHTS].into_iter().map(|n| dir.join(n)).find(|p| p.is_file()).unwrap_or(dir.join(WEIGHTS));
    vs.load(&weights).map_err(|source| CheckpointError::Torch {
        path: weights,
        what: "loading the weights",
        source,
    })?;
    Ok((vs, policy, meta))
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::{Device, Kind, Tensor};

    #[test]
    fn a_run_its_last_pointer_and_a_checkpoint_all_resolve() {
        let run = tempfile::tempdir().unwrap();
        let ckpt = run.path().join("checkpoints").join("step_40");
        std::fs::create_dir_all(&ckpt).unwrap();
        std::fs::write(ckpt.join(META), "{}").unwrap();
        std::fs::write(run.path().join("checkpoints").join("last"), "step_40\n").unwrap();
        for p in [ckpt.clone(), run.path().join("checkpoints").join("last"), run.path().to_path_buf()] {
            assert_eq!(resolve(&p).unwrap(), ckpt, "{}", p.display());
        }
        let run_name = run.path().file_name().unwrap().to_string_lossy().into_owned();
        assert_eq!(id(&ckpt, 40), format!("{run_name}@40"));
        assert_eq!(id(Path::new("/x/imported"), 3), "imported@3");
    }

    fn meta(config: DiffusionConfig) -> CheckpointMeta {
        CheckpointMeta {
            format: FORMAT,
            config,
            action_stats: MinMax { min: vec![-1.0; 7], max: vec![1.0; 7], zero_range_eps: None },
            state_stats: MinMax { min: vec![0.0; 7], max: vec![2.0; 7], zero_range_eps: None },
            image_stats: BTreeMap::new(),
            manifest: vec!["LABRIG+operator+2026-11-24-22h-04m-49s".into()],
            step: 1200,
        }
    }

    /// Saved and loaded, the policy gives the same chunk for the same observation and noise;
    /// the EMA weights are the ones loaded when present.
    #[test]
    fn a_saved_policy_loads_and_samples_the_same_chunk() {
        tch::manual_seed(11);
        let dir = tempfile::tempdir().unwrap();
        let vs = VarStore::new(Device::Cpu);
        let policy = DiffusionPolicy::new(vs.root(), DiffusionConfig::tiny()).unwrap();
        let images = vec![Tensor::rand([1, 2, 3, 32, 32], (Kind::Float, Device::Cpu))];
        let state = Tensor::rand([1, 2, 7], (Kind::Float, Device::Cpu));
        let noise = Tensor::randn([1, 16, 7], (Kind::Float, Device::Cpu));
        let chunk = tch::no_grad(|| policy.sample(&images, &state, &noise)).unwrap();
        save(dir.path(), &meta(DiffusionConfig::tiny()), &vs, None).unwrap();
        let (_vs2, loaded, m) = load(dir.path(), Device::Cpu).unwrap();
        assert_eq!(m, meta(DiffusionConfig::tiny()));
        let again = tch::no_grad(|| loaded.sample(&images, &state, &noise)).unwrap();
        assert_eq!((&chunk - &again).abs().max().double_value(&[]), 0.0);
        // With EMA weights beside them, those are loaded: other weights, another chunk.
        let ema = VarStore::new(Device::Cpu);
        let _other = DiffusionPolicy::new(ema.root(), DiffusionConfig::tiny()).unwrap();
        save(dir.path(), &meta(DiffusionConfig::tiny()), &vs, Some(&ema)).unwrap();
        let (_vs3, from_ema, _) = load(dir.path(), Device::Cpu).unwrap();
        let ema_chunk = tch::no_grad(|| from_ema.sample(&images, &state, &noise)).unwrap();
        assert!((&chunk - &ema_chunk).abs().max().double_value(&[]) > 1e-6);
    }

    #[test]
    fn a_damaged_or_foreign_checkpoint_is_named() {
        let dir = tempfile::tempdir().unwrap();
        let e = load(dir.path(), Device::Cpu).unwrap_err();
        assert!(e.to_string().contains("checkpoint.json: reading"), "{e}");
        let vs = VarStore::new(Device::Cpu);
        let _p = DiffusionPolicy::new(vs.root(), DiffusionConfig::tiny()).unwrap();
        save(dir.path(), &meta(DiffusionConfig::tiny()), &vs, None).unwrap();
        // Weights of another shape than the config says: refused by tch, naming the file.
        let other = CheckpointMeta {
            config: DiffusionConfig { keypoints: 4, ..DiffusionConfig::tiny() },
            ..meta(DiffusionConfig::tiny())
        };
        std::fs::write(dir.path().join(META), serde_json::to_string(&other).unwrap()).unwrap();
        let e = load(dir.path(), Device::Cpu).unwrap_err();
        assert!(e.to_string().contains("model.safetensors: loading the weights"), "{e}");
        // A missing normaliser statistic is named.
        let mut v = serde_json::to_value(meta(DiffusionConfig::tiny())).unwrap();
        v.as_object_mut().unwrap().remove("action_stats");
        std::fs::write(dir.path().join(META), v.to_string()).unwrap();
        let e = load(dir.path(), Device::Cpu).unwrap_err().to_string();
        assert!(e.contains("checkpoint.json") && e.contains("missing field `action_stats`"), "{e}");
        let newer = CheckpointMeta { format: FORMAT + 1, ..meta(DiffusionConfig::tiny()) };
        std::fs::write(dir.path().join(META), serde_json::to_string(&newer).unwrap()).unwrap();
        assert!(matches!(load(dir.path(), Device::Cpu).unwrap_err(), CheckpointError::Format { found: 2, .. }));
    }
}
