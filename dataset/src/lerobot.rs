//! labrig episodes as a LeRobot dataset, format v3.0 (what LeRobot 0.4 reads):
//! `labrig export lerobot <episodes|dir> <out>`.
//!
//! - One frame per step at the rig's 20 Hz: frame k of an episode has `timestamp = k / 20`
//!   exactly (LeRobot checks it), whatever the step's receive time was; the step index is the
//!   grid (a wall-clock rig's missed tick is not a frame: the steps are consecutive).
//! - Each recorded camera as `observation.images.<camera>`: an H.264 MP4 (yuv420p, constant
//!   20 fps, first pts 0), one per camera per episode, frame k = the frame step k used (a step
//!   without one repeats the camera's previous frame; counted). H.264 rather than LeRobot's
//!   default AV1: Debian's ffmpeg encodes it (libx264), LeRobot's PyAV decoder and ordinary
//!   players read it.
//! - `observation.state` = the 7 joint positions + the gripper (DROID's, as the LeRobot DROID
//!   port), with `observation.state.{joint_position, cartesian_position, gripper_position}`
//!   beside it; `action` = the commanded joint position + gripper, with
//!   `action.{joint_position, gripper_position, cartesian_position, cartesian_velocity,
//!   joint_velocity, gripper_velocity}`. The task is the episode's instruction.
//! - `meta/stats.json` as LeRobot computes it (`compute_stats.py`): per episode, per feature
//!   dimension min / max / mean / std / count and the quantiles q01 q10 q50 q90 q99 from a
//!   5000-bin histogram with LeRobot's interpolation, images per channel in [0, 1] over
//!   LeRobot's sample of frames (`sample_indices`, downsampled past 300 px), then aggregated
//!   across episodes with counts as weights (quantiles too, as LeRobot does).
//! - Written under `<out>.partial` and renamed when whole: a failed export leaves no dataset; a
//!   bad episode is skipped and named.

use arrow_array::{
    ArrayRef, FixedSizeListArray, Float32Array, Float64Array, Int64Array, LargeStringArray, ListArray, RecordBatch,
    StringArray,
};
use arrow_schema::{DataType, Field};
use labrig_msgs::rig::Step;
use parquet::arrow::ArrowWriter;
use serde_json::{Value, json};
use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// The rig's control rate: LeRobot's fps.
pub const FPS: u32 = 20;
/// LeRobot's quantiles and their keys.
pub const QUANTILES: [(f64, &str); 5] = [(0.01, "q01"), (0.10, "q10"), (0.50, "q50"), (0.90, "q90"), (0.99, "q99")];
const BINS: usize = 5000;
const CHUNKS_SIZE: usize = 1000;

/// Why an export failed, naming the file (or the flag).
#[derive(Debug, thiserror::Error)]
pub enum LeRobotError {
    #[error("{}: {source}", path.display())]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{}: {why}", path.display())]
    Bad { path: PathBuf, why: String },
    #[error("--format {0}: v3.0 (LeRobot 0.4+) or v2.1 (LeRobot 0.3, openpi)")]
    UnknownFormat(String),
    #[error("--schema {0}: droid (default), openpi-droid or labrig")]
    UnknownSchema(String),
}

fn io(path: &Path) -> impl Fn(std::io::Error) -> LeRobotError + '_ {
    move |e| LeRobotError::Io { path: path.to_owned(), source: e }
}

fn bad(path: &Path, why: impl Into<String>) -> LeRobotError {
    LeRobotError::Bad { path: path.to_owned(), why: why.into() }
}

/// The dataset format written.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub enum Format {
    /// v3.0 (LeRobot 0.4+): many episodes per data file, meta/episodes parquet, stats.json.
    V30,
    /// v2.1 (LeRobot 0.3, openpi's pinned version): a data file and an MP4 per episode,
    /// meta/episodes.jsonl, episodes_stats.jsonl, tasks.jsonl.
    V21,
}

impl Format {
    pub fn parse(s: &str) -> Result<Format, LeRobotError> {
        match s {
            "v3.0" | "3.0" | "v3" => Ok(Format::V30),
            "v2.1" | "2.1" => Ok(Format::V21),
            other => Err(LeRobotError::UnknownFormat(other.to_owned())),
        }
    }

    pub fn version(&self) -> &'static str {
        match self {
            Format::V30 => "v3.0",
            Format::V21 => "v2.1",
        }
    }
}

/// Which keys the dataset carries.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub enum Schema {
    /// DROID's keys, as the LeRobot DROID port: `observation.state` = 7 joints + gripper,
    /// `action` = the commanded joints + gripper, DROID's sub-keys beside them.
    Droid,
    /// The flat keys openpi's `pi05_droid_finetune` reads (its `LeRobotDROIDDataConfig`):
    /// `exterior_image_1_left`, `exterior_image_2_left`, `wrist_image_left`, `joint_position`
    /// (7), `gripper_position` (1), `actions` (8: the joint velocity + the gripper position, as
    /// openpi's DROID converter writes it); the task is the prompt.
    OpenpiDroid,
    /// What labrig's Diffusion Policy trains on, so that LeRobot's trainer learns the same
    /// policy and `labrig policy import-lerobot` brings it back to the rig: `observation.state`
    /// = the TCP position + its quaternion (x, y, z, w; labrig's canonical sign) + the gripper,
    /// `action` = the target position + axis-angle + gripper (`eef_axis_angle`).
    Labrig,
}

impl Schema {
    pub fn parse(s: &str) -> Result<Schema, LeRobotError> {
        match s {
            "droid" => Ok(Schema::Droid),
            "openpi-droid" => Ok(Schema::OpenpiDroid),
            "labrig" => Ok(Schema::Labrig),
            other => Err(LeRobotError::UnknownSchema(other.to_owned())),
        }
    }

    /// The feature key of a labrig camera; None: not in this schema.
    pub fn camera_key(&self, camera: &str) -> Option<String> {
        match self {
            Schema::Droid | Schema::Labrig => Some(format!("observation.images.{camera}")),
            Schema::OpenpiDroid => match camera {
                "ext1" => Some("exterior_image_1_left".into()),
                "ext2" => Some("exterior_image_2_left".into()),
                "wrist" => Some("wrist_image_left".into()),
                _ => None,
            },
        }
    }
}

/// One feature's statistics, per dimension (images: per channel).
#[derive(Debug, Clone, PartialEq)]
pub struct Stats {
    pub min: Vec<f64>,
    pub max: Vec<f64>,
    pub mean: Vec<f64>,
    pub std: Vec<f64>,
    pub count: u64,
    /// In [`QUANTILES`]' order.
    pub quantiles: Vec<Vec<f64>>,
}

/// LeRobot's `get_feature_stats` over `rows` (each `dim` wide) counting `count` samples:
/// `RunningQuantileStats` with one batch (histogram quantiles); fewer than 2 rows: the
/// quantiles are the mean.
pub fn feature_stats(values: &[f64], dim: usize, count: u64) -> Stats {
    let n = values.len() / dim;
    let col = |j: usize| values.iter().skip(j).step_by(dim).copied();
    let mut s = Stats {
        min: (0..dim).map(|j| col(j).fold(f64::INFINITY, f64::min)).collect(),
        max: (0..dim).map(|j| col(j).fold(f64::NEG_INFINITY, f64::max)).collect(),
        mean: (0..dim).map(|j| col(j).sum::<f64>() / n as f64).collect(),
        std: vec![0.0; dim],
        count,
        quantiles: vec![vec![0.0; dim]; QUANTILES.len()],
    };
    for j in 0..dim {
        let mean_sq = col(j).map(|x| x * x).sum::<f64>() / n as f64;
        if n < 2 {
            // np.std of the values.
            s.std[j] = (col(j).map(|x| (x - s.mean[j]).powi(2)).sum::<f64>() / n as f64).sqrt();
            for q in &mut s.quantiles {
                q[j] = s.mean[j];
            }
            continue;
        }
        s.std[j] = (mean_sq - s.mean[j] * s.mean[j]).max(0.0).sqrt();
        let (lo, hi) = (s.min[j] - 1e-10, s.max[j] + 1e-10);
        let width = (hi - lo) / BINS as f64;
        let edges: Vec<f64> = (0..=BINS).map(|i| lo + (hi - lo) * i as f64 / BINS as f64).collect();
        let mut hist = vec![0u64; BINS];
        for x in col(j) {
            let mut b = ((x - lo) / width) as usize;
            b = b.min(BINS - 1);
            // numpy's correction at the bin edges.
            if x < edges[b] {
                b = b.saturating_sub(1);
            } else if b + 1 < BINS && x >= edges[b + 1] {
                b += 1;
            }
            hist[b] += 1;
        }
        let mut cumsum = Vec::with_capacity(BINS);
        let mut acc = 0u64;
        for h in &hist {
            acc += h;
            cumsum.push(acc as f64);
        }
        for (k, (q, _)) in QUANTILES.iter().enumerate() {
            let target = q * n as f64;
            // np.searchsorted(cumsum, target), side left.
            let idx = cumsum.partition_point(|&c| c < target);
            s.quantiles[k][j] = if idx == 0 {
                edges[0]
            } else if idx >= cumsum.len() {
                edges[BINS]
            } else {
                let before = cumsum[idx - 1];
                let inside = cumsum[idx] - before;
                if inside == 0.0 {
                    edges[idx]
                } else {
                    edges[idx] + (target - before) / inside * (edges[idx + 1] - edges[idx])
                }
            };
        }
    }
    s
}

/// LeRobot's `aggregate_feature_stats`: counts as weights (the quantiles too).
pub fn aggregate(stats: &[Stats]) -> Stats {
    let dim = stats[0].mean.len();
    let total: f64 = stats.iter().map(|s| s.count as f64).sum();
    let mean: Vec<f64> =
        (0..dim).map(|j| stats.iter().map(|s| s.mean[j] * s.count as f64).sum::<f64>() / total).collect();
    let std = (0..dim)
        .map(|j| {
            let v: f64 =
                stats.iter().map(|s| (s.std[j].powi(2) + (s.mean[j] - mean[j]).powi(2)) * s.count as f64).sum::<f64>()
                    / total;
            v.sqrt()
        })
        .collect();
    Stats {
        min: (0..dim).map(|j| stats.iter().map(|s| s.min[j]).fold(f64::INFINITY, f64::min)).collect(),
        max: (0..dim).map(|j| stats.iter().map(|s| s.max[j]).fold(f64::NEG_INFINITY, f64::max)).collect(),
        mean,
        std,
        count: total as u64,
        quantiles: (0..QUANTILES.len())
            .map(|k| {
                (0..dim)
                    .map(|j| stats.iter().map(|s| s.quantiles[k][j] * s.count as f64).sum::<f64>() / total)
                    .collect()
            })
            .collect(),
    }
}

/// LeRobot's `sample_indices`: which of an episode's frames its image statistics read.
pub fn sample_indices(len: usize) -> Vec<usize> {
    let (min, max, power) = (100usize, 10_000usize, 0.75f64);
    let min = min.min(len);
    let n = min.max(((len as f64).powf(power) as usize).min(max));
    if n <= 1 {
        return vec![0; n];
    }
    (0..n).map(|i| ((i as f64) * (len - 1) as f64 / (n - 1) as f64).round_ties_even() as usize).collect()
}

impl Stats {
    /// stats.json's entry: images as (3, 1, 1) nested lists.
    pub fn to_json(&self, image: bool) -> Value {
        let v =
            |x: &Vec<f64>| if image { json!(x.iter().map(|c| vec![vec![*c]]).collect::<Vec<_>>()) } else { json!(x) };
        let mut m = serde_json::Map::new();
        m.insert("min".into(), v(&self.min));
        m.insert("max".into(), v(&self.max));
        m.insert("mean".into(), v(&self.mean));
        m.insert("std".into(), v(&self.std));
        m.insert("count".into(), json!([self.count]));
        for (k, (_, key)) in QUANTILES.iter().enumerate() {
            m.insert((*key).into(), v(&self.quantiles[k]));
        }
        Value::Object(m)
    }
}

/// A numeric feature: its key, width and values at a step.
type Feature = (&'static str, usize, fn(&Step) -> Vec<f64>);

/// The numeric features of a frame in `schema`.
fn numeric_features(schema: Schema) -> Vec<Feature> {
    match schema {
        Schema::Droid => vec![
            ("observation.state", 8, |s| {
                let mut v = s.robot_state.joint_positions.to_vec();
                v.push(s.robot_state.gripper_position);
                v
            }),
            ("observation.state.joint_position", 7, |s| s.robot_state.joint_positions.to_vec()),
            ("observation.state.cartesian_position", 6, |s| s.robot_state.cartesian_position.to_vec()),
            ("observation.state.gripper_position", 1, |s| vec![s.robot_state.gripper_position]),
            ("action", 8, |s| {
                let mut v = s.action.joint_position.to_vec();
                v.push(s.action.gripper_position);
                v
            }),
            ("action.joint_position", 7, |s| s.action.joint_position.to_vec()),
            ("action.gripper_position", 1, |s| vec![s.action.gripper_position]),
            ("action.cartesian_position", 6, |s| s.action.cartesian_position.to_vec()),
            ("action.cartesian_velocity", 6, |s| s.action.cartesian_velocity.to_vec()),
            ("action.joint_velocity", 7, |s| s.action.joint_velocity.to_vec()),
            ("action.gripper_velocity", 1, |s| vec![s.action.gripper_velocity]),
        ],
        Schema::OpenpiDroid => vec![
            ("joint_position", 7, |s| s.robot_state.joint_positions.to_vec()),
            ("gripper_position", 1, |s| vec![s.robot_state.gripper_position]),
            ("actions", 8, |s| {
                let mut v = s.action.joint_velocity.to_vec();
                v.push(s.action.gripper_position);
                v
            }),
        ],
        Schema::Labrig => vec![
            ("observation.state", 8, |s| {
                let p = &s.robot_state.cartesian_position;
                let q = labrig_arm::ik::canonical_quaternion(&labrig_arm::ik::pose_from_xyz_euler(p).rotation);
                vec![p[0], p[1], p[2], q[0], q[1], q[2], q[3], s.robot_state.gripper_position]
            }),
            ("action", 7, |s| {
                let p = &s.action.cartesian_position;
                let r = labrig_arm::ik::canonical_axis_angle(&labrig_arm::ik::pose_from_xyz_euler(p).rotation);
                vec![p[0], p[1], p[2], r[0], r[1], r[2], s.action.gripper_position]
            }),
        ],
    }
}

fn names(schema: Schema, key: &str, dim: usize) -> Value {
    let joints = |n: usize| (0..n).map(|i| format!("joint_{i}")).collect::<Vec<_>>();
    let pose = ["x", "y", "z", "roll", "pitch", "yaw"].map(String::from).to_vec();
    let v: Vec<String> = match (key, dim) {
        ("observation.state", 8) if schema == Schema::Labrig => {
            ["x", "y", "z", "qx", "qy", "qz", "qw", "gripper"].map(String::from).to_vec()
        }
        ("action", 7) if schema == Schema::Labrig => {
            ["x", "y", "z", "rx", "ry", "rz", "gripper"].map(String::from).to_vec()
        }
        ("observation.state" | "action" | "actions", 8) => {
            let mut v = joints(7);
            v.push("gripper".into());
            v
        }
        (_, 7) => joints(7),
        (_, 6) => pose,
        _ => vec![key.rsplit('.').next().unwrap_or(key).to_owned()],
    };
    json!(v)
}

/// What to write: the format, the keys, the cameras (None: every recorded one).
#[derive(Debug, Clone)]
pub struct Spec {
    pub format: Format,
    pub schema: Schema,
    pub cameras: Option<Vec<String>>,
}

/// What an export did.
#[derive(Debug, Clone, serde::Serialize)]
pub struct ExportReport {
    pub out: PathBuf,
    pub format: Format,
    pub schema: Schema,
    pub episodes: usize,
    pub frames: usize,
    pub cameras: Vec<String>,
    /// Steps without a frame of their own, per camera (the previous frame repeated).
    pub frames_filled: BTreeMap<String, usize>,
    /// Episodes left out, each with why.
    pub skipped: Vec<(PathBuf, String)>,
    pub bytes: u64,
    pub seconds: f64,
}

struct Exported {
    steps: Vec<Step>,
    /// The dataset-wide index of its first frame.
    first_index: usize,
    task: String,
    /// The episode's labrig metadata (carried in the episodes table for `labrig import lerobot`).
    metadata: labrig_episode::EpisodeMetadata,
    videos: Vec<(String, PathBuf)>,
    image_stats: Vec<(String, Stats, [usize; 2])>,
}

/// Exports `episodes` (directories or MCAP files of finished labrig episodes) to a LeRobot v3.0
/// dataset at `out` (refused if it exists unless `overwrite`). `progress(done, total)`.
pub fn export(
    episodes: &[PathBuf],
    out: &Path,
    spec: &Spec,
    overwrite: bool,
    mut progress: impl FnMut(usize, usize),
) -> Result<ExportReport, LeRobotError> {
    let started = std::time::Instant::now();
    if out.exists() && !overwrite {
        return Err(bad(out, "exists: choose another output or pass --overwrite"));
    }
    // `<out>.partial` beside it (appended: `with_extension` would eat a dotted name's tail).
    let mut partial_name = out.file_name().unwrap_or_default().to_os_string();
    partial_name.push(".partial");
    let partial = out.with_file_name(partial_name);
    let _ = std::fs::remove_dir_all(&partial);
    std::fs::create_dir_all(partial.join("meta")).map_err(io(&partial))?;
    let result = write_all(episodes, &partial, spec, &mut progress);
    let mut report = match result {
        Ok(r) => r,
        Err(e) => {
            let _ = std::fs::remove_dir_all(&partial);
            return Err(e);
        }
    };
    if out.exists() {
        std::fs::remove_dir_all(out).map_err(io(out))?;
    }
    std::fs::rename(&partial, out).map_err(io(out))?;
    report.out = out.to_owned();
    report.bytes = dir_bytes(out);
    report.seconds = started.elapsed().as_secs_f64();
    Ok(report)
}

fn dir_bytes(dir: &Path) -> u64 {
    let Ok(rd) = std::fs::read_dir(dir) else { return 0 };
    rd.flatten()
        .map(|e| {
            let p = e.path();
            if p.is_dir() { dir_bytes(&p) } else { e.metadata().map_or(0, |m| m.len()) }
        })
        .sum()
}

/// Removes whatever videos a failed export of the episode at `index` left.
fn remove_videos_of(root: &Path, format: Format, index: usize) {
    let (chunk, name) = match format {
        Format::V30 => (format!("chunk-{:03}", index / CHUNKS_SIZE), format!("file-{:03}.mp4", index % CHUNKS_SIZE)),
        Format::V21 => (format!("chunk-{:03}", index / CHUNKS_SIZE), format!("episode_{index:06}.mp4")),
    };
    let mut stack = vec![root.join("videos")];
    while let Some(d) = stack.pop() {
        let Ok(rd) = std::fs::read_dir(&d) else { continue };
        for e in rd.flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else if p.file_name().is_some_and(|n| *n == *name)
                && p.ancestors().any(|a| a.file_name().is_some_and(|n| *n == *chunk))
            {
                let _ = std::fs::remove_file(&p);
            }
        }
    }
}

/// Where `key`'s video of `episode` goes.
fn video_rel(format: Format, key: &str, episode: usize) -> String {
    match format {
        Format::V30 => format!("videos/{key}/chunk-{:03}/file-{:03}.mp4", episode / CHUNKS_SIZE, episode % CHUNKS_SIZE),
        Format::V21 => {
            format!("videos/chunk-{:03}/{key}/episode_{episode:06}.mp4", episode / CHUNKS_SIZE)
        }
    }
}

/// Exports `episodes` into the dataset at `root`: the episodes (in parallel), the ones kept
/// renumbered, the frames, the statistics, then the metadata of `spec.format`.
fn write_all(
    episodes: &[PathBuf],
    root: &Path,
    spec: &Spec,
    progress: &mut impl FnMut(usize, usize),
) -> Result<ExportReport, LeRobotError> {
    let format = spec.format;
    let results = export_in_parallel(episodes, root, spec, progress);
    let Kept { mut done, skipped, cameras, sizes, filled } = Kept::gather(episodes, results, root, format)?;
    progress(episodes.len(), episodes.len());
    if done.is_empty() {
        return Err(nothing_exported(root, &skipped));
    }
    let cameras = cameras.expect("an episode was exported");
    number_frames(&mut done);
    let tasks = tasks_in_order(&done);
    let total: usize = done.iter().map(|e| e.steps.len()).sum();
    write_frames(root, format, spec.schema, &done, &tasks)?;
    let per_feature = episode_stats(&done, &tasks, spec.schema);
    if format == Format::V21 {
        return write_v21_meta(root, spec.schema, &done, &tasks, &cameras, &sizes, &per_feature, filled, skipped);
    }
    write_stats_json(root, &per_feature, &cameras)?;
    write_tasks_parquet(root, &tasks)?;
    write_episodes_parquet(root, &done, &cameras, &per_feature)?;
    let info = info_json(Format::V30, spec.schema, done.len(), total, tasks.len(), &cameras, &sizes);
    std::fs::write(root.join("meta/info.json"), serde_json::to_string_pretty(&info).expect("json") + "\n")
        .map_err(io(root))?;
    Ok(ExportReport {
        out: root.to_owned(),
        format: Format::V30,
        schema: spec.schema,
        episodes: done.len(),
        frames: total,
        cameras,
        frames_filled: filled,
        skipped,
        bytes: 0,
        seconds: 0.0,
    })
}

/// Exports each episode (`export_one`) on a worker per core, reporting progress as each ends;
/// the results by the episode's place in the input.
fn export_in_parallel(
    episodes: &[PathBuf],
    root: &Path,
    spec: &Spec,
    progress: &mut impl FnMut(usize, usize),
) -> Vec<Option<OneExport>> {
    let format = spec.format;
    // Episodes in parallel (each one's MP4s are written by its own ffmpeg processes), a worker
    // per core; each writes its videos under its place in the input, renumbered below once the
    // skipped ones are known.
    let workers = std::thread::available_parallelism().map_or(1, |n| n.get()).min(episodes.len()).max(1);
    let next = std::sync::atomic::AtomicUsize::new(0);
    let (tx, rx) = std::sync::mpsc::channel();
    let mut results: Vec<Option<OneExport>> = (0..episodes.len()).map(|_| None).collect();
    std::thread::scope(|scope| {
        for _ in 0..workers {
            let (tx, next) = (tx.clone(), &next);
            scope.spawn(move || {
                loop {
                    let k = next.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
                    let Some(src) = episodes.get(k) else { break };
                    let r = export_one(src, root, spec, k);
                    if r.is_err() {
                        remove_videos_of(root, format, k);
                    }
                    if tx.send((k, r)).is_err() {
                        break;
                    }
                }
            });
        }
        drop(tx);
        for (received, (k, r)) in rx.iter().enumerate() {
            results[k] = Some(r);
            progress(received + 1, episodes.len());
        }
    });
    results
}

/// The episodes kept for the dataset, the ones skipped, and what the kept ones share.
struct Kept {
    done: Vec<Exported>,
    skipped: Vec<(PathBuf, String)>,
    /// The first kept episode's cameras: every other one must have the same.
    cameras: Option<Vec<String>>,
    sizes: BTreeMap<String, [usize; 2]>,
    filled: BTreeMap<String, usize>,
}

impl Kept {
    /// Goes through the export results in input order, keeping or skipping each episode.
    fn gather(
        episodes: &[PathBuf],
        results: Vec<Option<OneExport>>,
        root: &Path,
        format: Format,
    ) -> Result<Kept, LeRobotError> {
        let mut kept = Kept {
            done: Vec::new(),
            skipped: Vec::new(),
            cameras: None,
            sizes: BTreeMap::new(),
            filled: BTreeMap::new(),
        };
        for (k, (src, result)) in episodes.iter().zip(results).enumerate() {
            match result.expect("every episode was exported or failed") {
                Ok((e, fill)) => kept.admit(k, src, e, fill, root, format)?,
                Err(why) => kept.skipped.push((src.clone(), why.to_string())),
            }
        }
        Ok(kept)
    }

    /// Keeps episode `k` (its videos moved to its place in the dataset), or skips it (its
    /// videos removed) where its cameras or their sizes differ from the first kept one's.
    fn admit(
        &mut self,
        k: usize,
        src: &Path,
        mut e: Exported,
        fill: Vec<(String, usize)>,
        root: &Path,
        format: Format,
    ) -> Result<(), LeRobotError> {
        let cams: Vec<String> = e.videos.iter().map(|(c, _)| c.clone()).collect();
        let same_sizes = e.image_stats.iter().all(|(c, _, wh)| self.sizes.get(c).is_none_or(|s| s == wh));
        match &self.cameras {
            Some(want) if *want != cams || !same_sizes => {
                for (_, p) in &e.videos {
                    let _ = std::fs::remove_file(p);
                }
                self.skipped.push((
                    src.to_owned(),
                    format!("its cameras {cams:?} (or their sizes) differ from the first episode's {want:?}"),
                ));
                return Ok(());
            }
            None => self.cameras = Some(cams),
            _ => {}
        }
        // Its place in the dataset (earlier ones skipped: its videos move down).
        let index = self.done.len();
        if index != k {
            for (key, path) in &mut e.videos {
                let to = root.join(video_rel(format, key, index));
                std::fs::rename(&*path, &to).map_err(io(&to))?;
                *path = to;
            }
        }
        for (c, _, wh) in &e.image_stats {
            self.sizes.insert(c.clone(), *wh);
        }
        for (c, n) in fill {
            *self.filled.entry(c).or_default() += n;
        }
        self.done.push(e);
        Ok(())
    }
}

/// The error of an export that kept no episode, with why each one was skipped.
fn nothing_exported(root: &Path, skipped: &[(PathBuf, String)]) -> LeRobotError {
    let why = skipped.iter().map(|(p, w)| format!("{}: {w}", p.display())).collect::<Vec<_>>().join("; ");
    bad(root, format!("no episode could be exported ({why})"))
}

/// Numbers each episode's first frame in the dataset: the episodes end to end.
fn number_frames(done: &mut [Exported]) {
    let mut first_index = 0;
    for e in done {
        e.first_index = first_index;
        first_index += e.steps.len();
    }
}

/// The episodes' tasks in order of first appearance.
fn tasks_in_order(done: &[Exported]) -> Vec<String> {
    let mut tasks: Vec<String> = Vec::new();
    for e in done {
        if !tasks.contains(&e.task) {
            tasks.push(e.task.clone());
        }
    }
    tasks
}

/// The frames: one data file (v3.0), or one per episode (v2.1).
fn write_frames(
    root: &Path,
    format: Format,
    schema: Schema,
    done: &[Exported],
    tasks: &[String],
) -> Result<(), LeRobotError> {
    match format {
        Format::V30 => write_data(&root.join("data/chunk-000/file-000.parquet"), done, 0, tasks, "List", schema)?,
        Format::V21 => {
            for ei in 0..done.len() {
                let path = root.join(format!("data/chunk-{:03}/episode_{ei:06}.parquet", ei / CHUNKS_SIZE));
                write_data(&path, &done[ei..=ei], ei, tasks, "Sequence", schema)?;
            }
        }
    }
    Ok(())
}

/// Each feature's statistics per episode, in episode order (the images' from `export_one`).
fn episode_stats(done: &[Exported], tasks: &[String], schema: Schema) -> BTreeMap<String, Vec<Stats>> {
    let feats = numeric_features(schema);
    let mut per_feature: BTreeMap<String, Vec<Stats>> = BTreeMap::new();
    for (ei, e) in done.iter().enumerate() {
        let n = e.steps.len();
        for (name, dim, f) in &feats {
            // LeRobot computes on the stored float32 values.
            let v: Vec<f64> = e.steps.iter().flat_map(f).map(|x| f64::from(x as f32)).collect();
            per_feature.entry((*name).into()).or_default().push(feature_stats(&v, *dim, n as u64));
        }
        let ints: [(&str, Vec<f64>); 4] = [
            ("frame_index", (0..n).map(|k| k as f64).collect()),
            ("episode_index", vec![ei as f64; n]),
            ("index", (0..n).map(|k| (e.first_index + k) as f64).collect()),
            ("task_index", vec![tasks.iter().position(|x| *x == e.task).expect("listed") as f64; n]),
        ];
        for (name, v) in ints {
            per_feature.entry(name.into()).or_default().push(feature_stats(&v, 1, n as u64));
        }
        let t: Vec<f64> = (0..n).map(|k| f64::from(k as f32 / FPS as f32)).collect();
        per_feature.entry("timestamp".into()).or_default().push(feature_stats(&t, 1, n as u64));
        for (c, s, _) in &e.image_stats {
            per_feature.entry(c.clone()).or_default().push(s.clone());
        }
    }
    per_feature
}

/// meta/stats.json: each feature's statistics aggregated across the episodes.
fn write_stats_json(
    root: &Path,
    per_feature: &BTreeMap<String, Vec<Stats>>,
    cameras: &[String],
) -> Result<(), LeRobotError> {
    let stats: serde_json::Map<String, Value> =
        per_feature.iter().map(|(k, v)| (k.clone(), aggregate(v).to_json(cameras.contains(k)))).collect();
    std::fs::write(root.join("meta/stats.json"), serde_json::to_string_pretty(&stats).expect("json")).map_err(io(root))
}

/// meta/tasks.parquet, as pandas writes it (the task string is the index).
fn write_tasks_parquet(root: &Path, tasks: &[String]) -> Result<(), LeRobotError> {
    let pandas = json!({
        "index_columns": ["__index_level_0__"],
        "column_indexes": [{"name": null, "field_name": null, "pandas_type": "unicode", "numpy_type": "object", "metadata": {"encoding": "UTF-8"}}],
        "columns": [
            {"name": "task_index", "field_name": "task_index", "pandas_type": "int64", "numpy_type": "int64", "metadata": null},
            {"name": null, "field_name": "__index_level_0__", "pandas_type": "unicode", "numpy_type": "object", "metadata": null}
        ],
        "attributes": {},
        "creator": {"library": "labrig", "version": env!("CARGO_PKG_VERSION")},
        "pandas_version": "2.2.3"
    });
    write_parquet(
        &root.join("meta/tasks.parquet"),
        vec![
            (
                Field::new("task_index", DataType::Int64, true),
                Arc::new(Int64Array::from((0..tasks.len() as i64).collect::<Vec<_>>())),
            ),
            (
                Field::new("__index_level_0__", DataType::LargeUtf8, true),
                Arc::new(LargeStringArray::from(tasks.to_vec())),
            ),
        ],
        Some(("pandas", pandas.to_string())),
    )
}

/// meta/episodes/chunk-000/file-000.parquet: a row per episode, its place in the data and
/// video files, its statistics and labrig's own columns.
fn write_episodes_parquet(
    root: &Path,
    done: &[Exported],
    cameras: &[String],
    per_feature: &BTreeMap<String, Vec<Stats>>,
) -> Result<(), LeRobotError> {
    let n_ep = done.len();
    let lengths: Vec<i64> = done.iter().map(|e| e.steps.len() as i64).collect();
    let mut ep_cols = episode_columns(root, done, &lengths)?;
    ep_cols.extend(video_columns(cameras, &lengths));
    ep_cols.extend(episode_stats_columns(root, per_feature, cameras, n_ep)?);
    ep_cols.push((Field::new("meta/episodes/chunk_index", DataType::Int64, true), i64s(vec![0; n_ep])));
    ep_cols.push((Field::new("meta/episodes/file_index", DataType::Int64, true), i64s(vec![0; n_ep])));
    ep_cols.extend(labrig_columns(done));
    write_parquet(&root.join("meta/episodes/chunk-000/file-000.parquet"), ep_cols, None)
}

/// An int64 column.
fn i64s(v: Vec<i64>) -> ArrayRef {
    Arc::new(Int64Array::from(v))
}

/// The episodes table's first columns: each episode's index, tasks, length and rows in the
/// data file.
fn episode_columns(root: &Path, done: &[Exported], lengths: &[i64]) -> Result<Vec<(Field, ArrayRef)>, LeRobotError> {
    let n_ep = done.len();
    let mut from = 0i64;
    let (mut froms, mut tos) = (vec![], vec![]);
    for l in lengths {
        froms.push(from);
        from += l;
        tos.push(from);
    }
    let task_lists = {
        let values = StringArray::from(done.iter().map(|e| e.task.as_str()).collect::<Vec<_>>());
        let offsets = arrow_array::builder::OffsetBufferBuilder::<i32>::new(n_ep);
        let mut offsets = offsets;
        for _ in 0..n_ep {
            offsets.push_length(1);
        }
        ListArray::try_new(
            Arc::new(Field::new("element", DataType::Utf8, true)),
            offsets.finish(),
            Arc::new(values),
            None,
        )
        .map_err(|e| bad(root, e.to_string()))?
    };
    Ok(vec![
        (Field::new("episode_index", DataType::Int64, true), i64s((0..n_ep as i64).collect())),
        (
            Field::new("tasks", DataType::List(Arc::new(Field::new("element", DataType::Utf8, true))), true),
            Arc::new(task_lists),
        ),
        (Field::new("length", DataType::Int64, true), i64s(lengths.to_vec())),
        (Field::new("data/chunk_index", DataType::Int64, true), i64s(vec![0; n_ep])),
        (Field::new("data/file_index", DataType::Int64, true), i64s(vec![0; n_ep])),
        (Field::new("dataset_from_index", DataType::Int64, true), i64s(froms)),
        (Field::new("dataset_to_index", DataType::Int64, true), i64s(tos)),
    ])
}

/// Per camera, where each episode's video is: its chunk and file, from and to which time.
fn video_columns(cameras: &[String], lengths: &[i64]) -> Vec<(Field, ArrayRef)> {
    let n_ep = lengths.len();
    let mut cols: Vec<(Field, ArrayRef)> = Vec::new();
    for c in cameras {
        let key = format!("videos/{c}");
        cols.push((
            Field::new(format!("{key}/chunk_index"), DataType::Int64, true),
            i64s((0..n_ep).map(|i| (i / CHUNKS_SIZE) as i64).collect()),
        ));
        cols.push((
            Field::new(format!("{key}/file_index"), DataType::Int64, true),
            i64s((0..n_ep).map(|i| (i % CHUNKS_SIZE) as i64).collect()),
        ));
        cols.push((
            Field::new(format!("{key}/from_timestamp"), DataType::Float64, true),
            Arc::new(Float64Array::from(vec![0.0; n_ep])),
        ));
        cols.push((
            Field::new(format!("{key}/to_timestamp"), DataType::Float64, true),
            Arc::new(Float64Array::from(lengths.iter().map(|&l| l as f64 / f64::from(FPS)).collect::<Vec<_>>())),
        ));
    }
    cols
}

/// Each episode's own statistics (`stats/<feature>/<stat>`), as LeRobot 0.4 keeps them (its
/// dataset tools, e.g. deleting episodes, re-aggregate from these).
fn episode_stats_columns(
    root: &Path,
    per_feature: &BTreeMap<String, Vec<Stats>>,
    cameras: &[String],
    n_ep: usize,
) -> Result<Vec<(Field, ArrayRef)>, LeRobotError> {
    let mut cols: Vec<(Field, ArrayRef)> = Vec::new();
    for (feature, per_episode) in per_feature {
        let image = cameras.contains(feature);
        let mut stat_cols: Vec<(String, Vec<Vec<f64>>)> = ["min", "max", "mean", "std"]
            .iter()
            .map(|k| (k.to_string(), Vec::new()))
            .chain(QUANTILES.iter().map(|(_, k)| (k.to_string(), Vec::new())))
            .collect();
        for st in per_episode {
            let values = [&st.min, &st.max, &st.mean, &st.std].into_iter().chain(st.quantiles.iter());
            for ((_, col), v) in stat_cols.iter_mut().zip(values) {
                col.push(v.clone());
            }
        }
        for (stat, rows) in stat_cols {
            let name = format!("stats/{feature}/{stat}");
            cols.push(if image { image_stat_column(&name, &rows)? } else { list_column(&name, &rows)? });
        }
        let counts: Vec<i64> = per_episode.iter().map(|st| st.count as i64).collect();
        let item = Arc::new(Field::new("element", DataType::Int64, true));
        let mut ones = arrow_array::builder::OffsetBufferBuilder::<i32>::new(n_ep);
        (0..n_ep).for_each(|_| ones.push_length(1));
        let arr = ListArray::try_new(item.clone(), ones.finish(), Arc::new(Int64Array::from(counts)), None)
            .map_err(|e| bad(root, e.to_string()))?;
        cols.push((Field::new(format!("stats/{feature}/count"), DataType::List(item), true), Arc::new(arr)));
    }
    Ok(cols)
}

/// labrig's own: the DROID metadata LeRobot has no field for (the whole record, as JSON, so
/// `labrig import lerobot` gets it back).
fn labrig_columns(done: &[Exported]) -> [(Field, ArrayRef); 2] {
    [
        (
            Field::new("labrig/uuid", DataType::Utf8, true),
            Arc::new(StringArray::from(done.iter().map(|e| e.steps[0].episode_id.clone()).collect::<Vec<_>>())),
        ),
        (
            Field::new("labrig/metadata", DataType::Utf8, true),
            Arc::new(StringArray::from(
                done.iter().map(|e| serde_json::to_string(&e.metadata).expect("json")).collect::<Vec<_>>(),
            )),
        ),
    ]
}

/// v2.1's metadata: episodes.jsonl, episodes_stats.jsonl (min, max, mean, std, count per
/// feature, as LeRobot 0.3 writes them), tasks.jsonl, info.json.
#[allow(clippy::too_many_arguments)]
fn write_v21_meta(
    root: &Path,
    schema: Schema,
    done: &[Exported],
    tasks: &[String],
    cameras: &[String],
    sizes: &BTreeMap<String, [usize; 2]>,
    per_feature: &BTreeMap<String, Vec<Stats>>,
    filled: BTreeMap<String, usize>,
    skipped: Vec<(PathBuf, String)>,
) -> Result<ExportReport, LeRobotError> {
    let lines = |name: &str, rows: Vec<Value>| -> Result<(), LeRobotError> {
        let text: String = rows.iter().map(|r| r.to_string() + "\n").collect();
        let path = root.join("meta").join(name);
        std::fs::write(&path, text).map_err(io(&path))
    };
    lines(
        "episodes.jsonl",
        done.iter()
            .enumerate()
            .map(|(i, e)| {
                json!({"episode_index": i, "tasks": [e.task], "length": e.steps.len(), "labrig_metadata": e.metadata})
            })
            .collect(),
    )?;
    lines(
        "episodes_stats.jsonl",
        (0..done.len())
            .map(|i| {
                let stats: serde_json::Map<String, Value> = per_feature
                    .iter()
                    .map(|(k, v)| {
                        let mut j = v[i].to_json(cameras.contains(k));
                        if let Value::Object(m) = &mut j {
                            m.retain(|key, _| !key.starts_with('q'));
                        }
                        (k.clone(), j)
                    })
                    .collect();
                json!({"episode_index": i, "stats": stats})
            })
            .collect(),
    )?;
    lines("tasks.jsonl", tasks.iter().enumerate().map(|(i, t)| json!({"task_index": i, "task": t})).collect())?;
    let total: usize = done.iter().map(|e| e.steps.len()).sum();
    let mut info = info_json(Format::V21, schema, done.len(), total, tasks.len(), cameras, sizes);
    info["total_videos"] = json!(done.len() * cameras.len());
    info["total_chunks"] = json!(done.len().div_ceil(CHUNKS_SIZE));
    std::fs::write(root.join("meta/info.json"), serde_json::to_string_pretty(&info).expect("json") + "\n")
        .map_err(io(root))?;
    Ok(ExportReport {
        out: root.to_owned(),
        format: Format::V21,
        schema,
        episodes: done.len(),
        frames: total,
        cameras: cameras.to_vec(),
        frames_filled: filled,
        skipped,
        bytes: 0,
        seconds: 0.0,
    })
}

/// info.json for `format`.
#[allow(clippy::too_many_arguments)]
fn info_json(
    format: Format,
    schema: Schema,
    episodes: usize,
    frames: usize,
    tasks: usize,
    cameras: &[String],
    sizes: &BTreeMap<String, [usize; 2]>,
) -> Value {
    let mut features = serde_json::Map::new();
    for c in cameras {
        let [w, h] = sizes[c];
        features.insert(
            c.clone(),
            json!({
                "dtype": "video", "shape": [h, w, 3], "names": ["height", "width", "channels"],
                "info": {"video.height": h, "video.width": w, "video.codec": "h264", "video.pix_fmt": "yuv420p",
                         "video.is_depth_map": false, "video.fps": FPS, "video.channels": 3, "has_audio": false}
            }),
        );
    }
    for (name, dim, _) in &numeric_features(schema) {
        features
            .insert((*name).into(), json!({"dtype": "float32", "shape": [dim], "names": names(schema, name, *dim)}));
    }
    features.insert("timestamp".into(), json!({"dtype": "float32", "shape": [1], "names": null}));
    for name in ["frame_index", "episode_index", "index", "task_index"] {
        features.insert(name.into(), json!({"dtype": "int64", "shape": [1], "names": null}));
    }
    let mut info = json!({
        "codebase_version": format.version(),
        "robot_type": "franka_fr3_robotiq_2f85",
        "total_episodes": episodes,
        "total_frames": frames,
        "total_tasks": tasks,
        "chunks_size": CHUNKS_SIZE,
        "fps": FPS,
        "splits": {"train": format!("0:{episodes}")},
        "features": Value::Object(features),
    });
    match format {
        Format::V30 => {
            info["data_files_size_in_mb"] = json!(100);
            info["video_files_size_in_mb"] = json!(200);
            info["data_path"] = json!("data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet");
            info["video_path"] = json!("videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4");
        }
        Format::V21 => {
            info["data_path"] = json!("data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet");
            info["video_path"] = json!("videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4");
        }
    }
    info
}

/// The data file of `episodes` (the first one numbered `first`): every numeric feature,
/// timestamps on the grid, the indices. `list_type`: the `datasets` feature type of a vector
/// (`List` in datasets 4, which LeRobot 0.4 uses; `Sequence` in datasets 3, LeRobot 0.3).
fn write_data(
    path: &Path,
    episodes: &[Exported],
    first: usize,
    tasks: &[String],
    list_type: &str,
    schema: Schema,
) -> Result<(), LeRobotError> {
    let feats = numeric_features(schema);
    let mut cols: Vec<(Field, ArrayRef)> = Vec::new();
    let mut hf = serde_json::Map::new();
    for (name, dim, f) in &feats {
        let values: Vec<f32> = episodes.iter().flat_map(|e| e.steps.iter().flat_map(f)).map(|x| x as f32).collect();
        if *dim == 1 {
            // LeRobot reads a shape-[1] feature as a scalar column (as `timestamp`).
            cols.push((Field::new(*name, DataType::Float32, true), Arc::new(Float32Array::from(values))));
            hf.insert((*name).into(), json!({"dtype": "float32", "_type": "Value"}));
            continue;
        }
        let item = Arc::new(Field::new("element", DataType::Float32, true));
        let arr = FixedSizeListArray::try_new(item.clone(), *dim as i32, Arc::new(Float32Array::from(values)), None)
            .map_err(|e| bad(path, e.to_string()))?;
        cols.push((Field::new(*name, DataType::FixedSizeList(item, *dim as i32), true), Arc::new(arr)));
        hf.insert(
            (*name).into(),
            json!({"feature": {"dtype": "float32", "_type": "Value"}, "length": dim, "_type": list_type}),
        );
    }
    let mut ts = Vec::new();
    let (mut frame_index, mut episode_index, mut index, mut task_index) = (vec![], vec![], vec![], vec![]);
    for (k, e) in episodes.iter().enumerate() {
        let t = tasks.iter().position(|x| *x == e.task).expect("listed") as i64;
        for f in 0..e.steps.len() {
            ts.push(f as f32 / FPS as f32);
            frame_index.push(f as i64);
            episode_index.push((first + k) as i64);
            index.push(e.first_index as i64 + f as i64);
            task_index.push(t);
        }
    }
    cols.push((Field::new("timestamp", DataType::Float32, true), Arc::new(Float32Array::from(ts))));
    hf.insert("timestamp".into(), json!({"dtype": "float32", "_type": "Value"}));
    for (name, v) in
        [("frame_index", frame_index), ("episode_index", episode_index), ("index", index), ("task_index", task_index)]
    {
        cols.push((Field::new(name, DataType::Int64, true), Arc::new(Int64Array::from(v))));
        hf.insert(name.into(), json!({"dtype": "int64", "_type": "Value"}));
    }
    let hf_meta = json!({"info": {"features": Value::Object(hf)}}).to_string();
    write_parquet(path, cols, Some(("huggingface", hf_meta)))
}

/// A list<double> column, a row a vector.
fn list_column(name: &str, rows: &[Vec<f64>]) -> Result<(Field, ArrayRef), LeRobotError> {
    let item = Arc::new(Field::new("element", DataType::Float64, true));
    let mut offsets = arrow_array::builder::OffsetBufferBuilder::<i32>::new(rows.len());
    for r in rows {
        offsets.push_length(r.len());
    }
    let values = Float64Array::from(rows.concat());
    let arr = ListArray::try_new(item.clone(), offsets.finish(), Arc::new(values), None)
        .map_err(|e| bad(Path::new(name), e.to_string()))?;
    Ok((Field::new(name, DataType::List(item), true), Arc::new(arr)))
}

/// An image statistic's column: per row the channels as LeRobot shapes them, (3, 1, 1):
/// list<list<list<double>>>.
fn image_stat_column(name: &str, rows: &[Vec<f64>]) -> Result<(Field, ArrayRef), LeRobotError> {
    let err = |e: arrow_schema::ArrowError| bad(Path::new(name), e.to_string());
    let leaf = Arc::new(Field::new("element", DataType::Float64, true));
    let values: Vec<f64> = rows.concat();
    let n = values.len();
    let ones = |k: usize| {
        let mut b = arrow_array::builder::OffsetBufferBuilder::<i32>::new(k);
        (0..k).for_each(|_| b.push_length(1));
        b.finish()
    };
    // [v] per channel value, then [[v]], then the channels of a row.
    let inner = ListArray::try_new(leaf.clone(), ones(n), Arc::new(Float64Array::from(values)), None).map_err(err)?;
    let mid_field = Arc::new(Field::new("element", DataType::List(leaf), true));
    let mid = ListArray::try_new(mid_field.clone(), ones(n), Arc::new(inner), None).map_err(err)?;
    let top_field = Arc::new(Field::new("element", DataType::List(mid_field), true));
    let mut offsets = arrow_array::builder::OffsetBufferBuilder::<i32>::new(rows.len());
    for r in rows {
        offsets.push_length(r.len());
    }
    let top = ListArray::try_new(top_field.clone(), offsets.finish(), Arc::new(mid), None).map_err(err)?;
    Ok((Field::new(name, DataType::List(top_field), true), Arc::new(top)))
}

/// One episode exported, with the steps each camera filled in.
type OneExport = Result<(Exported, Vec<(String, usize)>), LeRobotError>;

fn export_one(src: &Path, root: &Path, spec: &Spec, index: usize) -> OneExport {
    let wanted = |cam: &str| spec.cameras.as_ref().is_none_or(|c| c.iter().any(|x| x == cam));
    let key = |cam: &str| spec.schema.camera_key(cam).filter(|_| wanted(cam));
    let v = labrig_droid::export::step_videos(src, FPS, |cam| {
        key(cam).map(|k| root.join(video_rel(spec.format, &k, index)))
    })
    .map_err(|e| bad(src, e.to_string()))?;
    // Every camera asked for (and openpi's three) must be in the episode.
    let needed: Vec<String> = match (&spec.cameras, spec.schema) {
        (Some(c), _) => c.clone(),
        (None, Schema::OpenpiDroid) => vec!["ext1".into(), "ext2".into(), "wrist".into()],
        (None, _) => Vec::new(),
    };
    for c in &needed {
        if !v.cameras.iter().any(|(cam, _)| cam.id == *c) {
            for (_, p) in &v.cameras {
                let _ = std::fs::remove_file(p);
            }
            let have: Vec<&str> =
                v.steps.first().map(|s| s.cameras.iter().map(|c| c.camera_id.as_str()).collect()).unwrap_or_default();
            return Err(bad(
                src,
                format!(
                    "no camera {c} (it has {have:?}){}",
                    if spec.schema == Schema::OpenpiDroid {
                        ": openpi's DROID schema needs ext1, ext2 and wrist"
                    } else {
                        ""
                    }
                ),
            ));
        }
    }
    let task = v.metadata.task_instruction.clone();
    let mut image_stats = Vec::new();
    let picks = sample_indices(v.steps.len());
    for (cam, path) in &v.cameras {
        let mut r = labrig_droid::video::Mp4Reader::open(path).map_err(|e| bad(path, e.to_string()))?;
        let (w, h) = (r.width as usize, r.height as usize);
        // LeRobot's auto_downsample_height_width: past 300 px, every int(size / 150)-th pixel.
        let step = if w.max(h) < 300 {
            1
        } else if w > h {
            w / 150
        } else {
            h / 150
        };
        let mut pixels: Vec<f64> = Vec::new();
        let mut k = 0usize;
        let mut wanted = picks.iter().copied().peekable();
        while let Some(frame) = r.next_frame().map_err(|e| bad(path, e.to_string()))? {
            while wanted.peek() == Some(&k) {
                wanted.next();
                for y in (0..h).step_by(step) {
                    for x in (0..w).step_by(step) {
                        let i = (y * w + x) * 3;
                        pixels.extend([f64::from(frame[i]), f64::from(frame[i + 1]), f64::from(frame[i + 2])]);
                    }
                }
            }
            k += 1;
        }
        let mut s = feature_stats(&pixels, 3, picks.len() as u64);
        for list in [&mut s.min, &mut s.max, &mut s.mean, &mut s.std] {
            list.iter_mut().for_each(|x| *x /= 255.0);
        }
        for q in &mut s.quantiles {
            q.iter_mut().for_each(|x| *x /= 255.0);
        }
        image_stats.push((key(&cam.id).expect("exported"), s, [w, h]));
    }
    let fill = v.cameras.iter().map(|(c, _)| key(&c.id).expect("exported")).zip(v.filled.iter().copied()).collect();
    let videos = v.cameras.into_iter().map(|(c, p)| (key(&c.id).expect("exported"), p)).collect();
    Ok((Exported { steps: v.steps, first_index: 0, task, metadata: v.metadata, videos, image_stats }, fill))
}

fn write_parquet(path: &Path, cols: Vec<(Field, ArrayRef)>, meta: Option<(&str, String)>) -> Result<(), LeRobotError> {
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).map_err(io(dir))?;
    }
    let (fields, arrays): (Vec<Field>, Vec<ArrayRef>) = cols.into_iter().unzip();
    let md: HashMap<String, String> = meta.map(|(k, v)| (k.to_owned(), v)).into_iter().collect();
    let schema = Arc::new(arrow_schema::Schema::new_with_metadata(fields, md));
    let batch = RecordBatch::try_new(schema.clone(), arrays).map_err(|e| bad(path, e.to_string()))?;
    let file = std::fs::File::create(path).map_err(io(path))?;
    let mut w = ArrowWriter::try_new(file, schema, None).map_err(|e| bad(path, e.to_string()))?;
    w.write(&batch).map_err(|e| bad(path, e.to_string()))?;
    w.close().map_err(|e| bad(path, e.to_string()))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// LeRobot's numbers for 0..29 (its stats for the episode above, from compute_stats.py).
    #[test]
    fn stats_follow_lerobots_histogram_quantiles() {
        let v: Vec<f64> = (0..30).map(f64::from).collect();
        let s = feature_stats(&v, 1, 30);
        assert_eq!((s.min[0], s.max[0], s.mean[0]), (0.0, 29.0, 14.5));
        assert!((s.std[0] - 8.655441448399191).abs() < 1e-12);
        let want = [-1e-10, 2.0009999999138, 14.00119999999656, 26.00140000007932, 28.998260000099986];
        for (k, w) in want.iter().enumerate() {
            assert!((s.quantiles[k][0] - w).abs() < 1e-9, "{}: {} vs {w}", QUANTILES[k].1, s.quantiles[k][0]);
        }
        // Aggregating two episodes weights the quantiles by count, as LeRobot does.
        let b = feature_stats(&v.iter().map(|x| x + 100.0).collect::<Vec<_>>(), 1, 30);
        let a = aggregate(&[s, b]);
        assert!((a.quantiles[0][0] - 50.0).abs() < 1e-6 && a.count == 60, "{a:?}");
    }

    #[test]
    fn sample_indices_are_lerobots() {
        assert_eq!(sample_indices(5), vec![0, 1, 2, 3, 4]);
        let s = sample_indices(1000);
        assert_eq!(s.len(), 177);
        assert_eq!((s[0], s[176]), (0, 999));
    }
}
