//! labrig-reports: the reports one labrig program writes and another reads back, as one type
//! each, so that a field renamed by the writer breaks the reader's build instead of turning into
//! a silent `null`. A leaf crate (serde only): the CLI reads what labrig-policies (libtorch) and
//! labrig-dataset (libhdf5) write without linking either.
//!
//! - [`RunReport`]: a training run's `run.json` (`labrig train`).
//! - [`Stage`], [`Retrieved`], [`ManifestEpisodes`]: a retrieval manifest's funnel and episodes
//!   (`labrig dataset retrieve`; the whole manifest is labrig-dataset's `Manifest`).
//! - [`DemoReport`]: `labrig demo --json`.
//! - [`IndexReport`], [`BadSource`]: `labrig dataset index --json`.

use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::PathBuf;

/// The figures of a run (also `run.json`).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RunReport {
    pub steps: u64,
    pub resumed_from: Option<u64>,
    pub target_episodes: usize,
    pub val_episodes: usize,
    pub cotrain_episodes: usize,
    pub skipped_unsuccessful: usize,
    /// Episodes (target and co-training) in which an operator took over from a policy.
    #[serde(default)]
    pub correction_episodes: usize,
    /// The training samples (windows) drawn from those.
    #[serde(default)]
    pub correction_samples: usize,
    /// With `skip_missed_grasps`: missed grasps found in the training episodes, and the
    /// windows left out for holding their mistake.
    #[serde(default)]
    pub missed_grasps: usize,
    #[serde(default)]
    pub mistake_windows: usize,
    #[serde(deserialize_with = "nan_if_null")]
    pub w: f64,
    pub drawn_target: u64,
    pub drawn_cotrain: u64,
    pub first_val_loss: Option<f64>,
    pub last_val_loss: Option<f64>,
    /// The last validation's open-loop position error (mm; see labrig-policies' `Validation::open_loop_mm`).
    #[serde(default)]
    pub last_open_loop_mm: Option<f64>,
    /// The last validation's waypoint errors (mm; see `Validation::waypoint_mm`): held-out
    /// samples, and the held-out episodes' first steps.
    #[serde(default)]
    pub last_waypoint_mm: Option<f64>,
    #[serde(default)]
    pub last_first_waypoint_mm: Option<f64>,
    #[serde(deserialize_with = "nan_if_null")]
    pub last_train_loss: f64,
    #[serde(deserialize_with = "nan_if_null")]
    pub samples_per_s: f64,
    /// The share of a step's time spent assembling its batch.
    #[serde(deserialize_with = "nan_if_null")]
    pub loader_share: f64,
    #[serde(deserialize_with = "nan_if_null")]
    pub decode_s: f64,
    pub threads: i32,
    /// Data-parallel ranks (1: one process); `samples_per_s` counts all of them.
    #[serde(default = "one")]
    pub world_size: usize,
    /// Data-parallel: the largest difference between a rank's final weights and rank 0's,
    /// summed over the ranks (0 when they stayed in step, as they must).
    #[serde(default)]
    pub ranks_weight_diff: Option<f64>,
    /// Data-parallel: the share of a step's time rank 0 spent in the gradients' all-reduce
    /// (waiting for the slowest rank included).
    #[serde(default)]
    pub allreduce_share: Option<f64>,
    pub checkpoint: PathBuf,
}

fn one() -> usize {
    1
}

/// A report file read as its type; `None` when it is missing or not that report.
pub fn read<T: serde::de::DeserializeOwned>(path: &std::path::Path) -> Option<T> {
    serde_json::from_str(&std::fs::read_to_string(path).ok()?).ok()
}

/// A figure JSON wrote as `null` (serde_json writes NaN so: a run resumed at its length trained
/// no step, so it has no throughput; a rollout timed no chunk) read back as NaN. For
/// `#[serde(deserialize_with = "labrig_reports::nan_if_null")]`.
pub fn nan_if_null<'de, D: serde::Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::NAN))
}

/// One rule of a retrieval and the episodes left after it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Stage {
    pub stage: String,
    pub kept: usize,
}

/// A retrieved episode.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Retrieved {
    pub id: String,
    pub format: String,
    pub path: String,
    /// The rules it passed, in order.
    pub passed: Vec<String>,
}

/// What a retrieval manifest says of its episodes (the rest of the file, the alignment, the
/// thresholds and the target, is labrig-dataset's `Manifest`, which holds these two fields).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ManifestEpisodes {
    pub funnel: Vec<Stage>,
    pub episodes: Vec<Retrieved>,
}

/// `labrig demo --json`: the episodes recorded and how they ended.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct DemoReport {
    /// Each episode: its folder, contact sheet and `labrig inspect` summary.
    pub episodes: Vec<serde_json::Value>,
    pub recorded: usize,
    pub successes: usize,
    pub root: PathBuf,
    /// Every episode recorded whole, none flagged.
    pub ok: bool,
    pub errors: Vec<String>,
}

/// A source `labrig dataset index` could not read, and why.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct BadSource {
    pub path: String,
    pub format: String,
    pub reason: String,
}

/// `labrig dataset index --json`: one shard's part of the index.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct IndexReport {
    pub part: PathBuf,
    /// This shard's number and the shard count.
    pub shard: [usize; 2],
    /// Sources found, in every shard.
    pub found: usize,
    pub in_shard: usize,
    pub indexed: usize,
    pub unchanged: usize,
    pub bad: Vec<BadSource>,
    pub by_format: BTreeMap<String, usize>,
    /// What `--extrinsics` changed (null without it).
    pub extrinsics_override: Option<serde_json::Value>,
    pub seconds: f64,
    pub episodes_per_s: f64,
    pub mb_per_s: f64,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_run_json_of_an_older_run_reads_with_the_defaults() {
        let old = r#"{"steps": 4, "resumed_from": null, "target_episodes": 2, "val_episodes": 1,
            "cotrain_episodes": 0, "skipped_unsuccessful": 0, "w": 1.0, "drawn_target": 8,
            "drawn_cotrain": 0, "first_val_loss": 1.0, "last_val_loss": 0.5, "last_train_loss": 0.4,
            "samples_per_s": 10.0, "loader_share": 0.1, "decode_s": 1.0, "threads": 2,
            "checkpoint": "run/checkpoints/step_4"}"#;
        let r: RunReport = serde_json::from_str(old).unwrap();
        assert_eq!((r.steps, r.world_size, r.last_open_loop_mm), (4, 1, None));
        // A run resumed at its length trained nothing: its NaN figures are JSON nulls.
        let mut again = serde_json::to_value(&r).unwrap();
        again["samples_per_s"] = serde_json::Value::Null;
        let back: RunReport = serde_json::from_value(again).unwrap();
        assert!(back.samples_per_s.is_nan());
        let nan = RunReport { loader_share: f64::NAN, ..back };
        assert!(
            serde_json::from_str::<RunReport>(&serde_json::to_string(&nan).unwrap()).unwrap().loader_share.is_nan()
        );
    }

    #[test]
    fn a_manifest_s_episodes_read_from_the_whole_file() {
        let m = r#"{"manifest_version": 1, "align": ["camPose"], "funnel": [{"stage": "all", "kept": 3}],
            "episodes": [{"id": "e", "format": "labrig", "path": "/x", "passed": ["camPose"]}]}"#;
        let e: ManifestEpisodes = serde_json::from_str(m).unwrap();
        assert_eq!(e.funnel, [Stage { stage: "all".into(), kept: 3 }]);
        assert_eq!(e.episodes[0].path, "/x");
    }
}
