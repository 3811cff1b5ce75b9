//! LeRobot datasets read by labrig: `labrig import lerobot <root> [--episodes ...] <out>` (to
//! labrig episodes) and `labrig dataset index <root>` (read in place, no images).
//!
//! - Formats: v3.0 (LeRobot 0.4: many episodes per data file and per MP4, each episode's span in
//!   `meta/episodes/`) and v2.1 / v2.0 (LeRobot 0.3: a data file and an MP4 per episode,
//!   `meta/episodes.jsonl`). The layout is read from `meta/info.json` (its path templates).
//! - Keys: DROID's, as the LeRobot DROID port and `labrig export lerobot` write them.
//!   Joints: `observation.state.joint_position`, else `observation.state[0..7]` (7 joints +
//!   gripper); the gripper: `observation.state.gripper_position`, else `observation.state[7]`;
//!   the TCP pose: `observation.state.cartesian_position`, else the FR3's forward kinematics of
//!   the joints (2F-85 TCP). The action likewise from `action.joint_position` /
//!   `action.gripper_position` or `action[0..8]`; `action.cartesian_position`,
//!   `.cartesian_velocity`, `.joint_velocity`, `.gripper_velocity` where the dataset has them
//!   (zeros otherwise, said in the report). openpi's flat DROID keys (`joint_position`,
//!   `gripper_position`, `actions` = joint velocity + gripper) are read too, the commanded
//!   joint position being where the joints went next. A dataset with another state layout is
//!   refused by name.
//! - Cameras: every video feature `observation.images.<key>`; the DROID port's and openpi's
//!   camera names map to labrig's ids (`exterior_1_left` -> `ext1`, `exterior_2_left` -> `ext2`,
//!   `wrist_left` -> `wrist`), other keys keep their name. Image features stored in the
//!   Parquet (dtype `image`, as openpi's DROID converter writes them: PNG or JPEG bytes per
//!   frame) are cameras too: a JPEG is kept as it is, a PNG re-encoded.
//! - Time: step k at `start + k / fps` (LeRobot's grid); each camera's frame of step k is the
//!   video's frame at the episode's `from_timestamp + k / fps`.
//! - Metadata: a dataset exported by labrig carries each episode's labrig metadata
//!   (`labrig/metadata`) and gets it back whole (uuid, task, outcome, scene, extrinsics ...).
//!   Any other dataset: uuid `<dataset name>+episode_<index>`, the task from the episode's
//!   tasks, the cameras' extrinsics from `camera_extrinsics.<key>` where present (the DROID
//!   port's), the outcome a success (LeRobot's format has no outcome: its episodes are the
//!   training set), episodes laid end to end from the time of `meta/info.json`.

use crate::lerobot::LeRobotError;
use arrow_array::{
    Array, ArrayRef, BooleanArray, FixedSizeListArray, Float32Array, Float64Array, Int32Array, Int64Array,
    LargeListArray, LargeStringArray, ListArray, RecordBatch, StringArray,
};
use arrow_schema::DataType;
use labrig_arm::kinematics::{Fr3Kinematics, TcpOffset};
use labrig_droid::droid::Camera;
use labrig_droid::import::{FrameSource, ImportOptions, StepFrame, next_step_frame};
use labrig_droid::video::Mp4Reader;
use labrig_episode::metadata::EpisodeMetadata;
use labrig_msgs::Nanos;
use labrig_msgs::rig::{ActionDict, CameraFrameRef, ControlTiming, RobotState, Step};
use labrig_msgs::std_msgs::Header;
use parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder;
use serde_json::Value;
use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};

fn bad(path: &Path, why: impl Into<String>) -> LeRobotError {
    LeRobotError::Bad { path: path.to_owned(), why: why.into() }
}

fn io(path: &Path) -> impl Fn(std::io::Error) -> LeRobotError + '_ {
    move |e| LeRobotError::Io { path: path.to_owned(), source: e }
}

/// labrig's id for a LeRobot camera key (the part after `observation.images.`).
pub fn camera_id(key: &str) -> String {
    match key {
        "exterior_1_left" | "exterior_image_1_left" => "ext1".into(),
        "exterior_2_left" | "exterior_image_2_left" => "ext2".into(),
        "wrist_left" | "wrist_image_left" => "wrist".into(),
        other => other.into(),
    }
}

/// A camera feature: LeRobot's key, labrig's camera id, and where its frames are: a video
/// (dtype `video`) or the data file itself (dtype `image`: PNG or JPEG bytes per frame, as
/// openpi's DROID converter writes them).
#[derive(Debug, Clone, serde::Serialize)]
pub struct CameraKey {
    pub key: String,
    pub id: String,
    pub video: bool,
}

/// One episode as the dataset's metadata lists it.
#[derive(Debug, Clone)]
pub struct EpisodeEntry {
    pub index: i64,
    pub length: usize,
    pub tasks: Vec<String>,
    /// v3.0: the data file's (chunk, file).
    data_file: Option<(i64, i64)>,
    /// Per video key: (chunk, file, from_timestamp) in v3.0; v2.x has one file per episode.
    videos: BTreeMap<String, (i64, i64, f64)>,
    /// labrig's metadata (JSON), where labrig exported the dataset.
    pub labrig_metadata: Option<String>,
    /// Where it starts on the timeline of a dataset without times of its own (s after the
    /// first): episodes end to end, a second apart, in index order.
    offset_s: f64,
}

/// A LeRobot dataset opened for reading.
#[derive(Debug)]
pub struct Dataset {
    pub root: PathBuf,
    pub version: String,
    pub fps: f64,
    pub features: serde_json::Map<String, Value>,
    pub episodes: Vec<EpisodeEntry>,
    pub cameras: Vec<CameraKey>,
    /// Camera features of another dtype: not read.
    pub image_features: Vec<String>,
    data_path: String,
    video_path: String,
    chunks_size: i64,
    /// Where the first episode starts when the dataset carries no time of its own.
    base_ns: i64,
    /// The data file read last: each episode's rows in it, split once when it is read.
    cache: Option<(PathBuf, HashMap<i64, Vec<RecordBatch>>)>,
}

/// An episode's steps and metadata.
#[derive(Debug)]
pub struct ReadEpisode {
    pub metadata: EpisodeMetadata,
    pub steps: Vec<Step>,
    /// Keys the steps were made without (their fields left at zero).
    pub absent: Vec<String>,
}

/// Fills a LeRobot path template: `{name}` and `{name:03d}`-style fields.
fn fill(template: &str, values: &[(&str, String)]) -> String {
    let mut out = String::new();
    let mut rest = template;
    while let Some(open) = rest.find('{') {
        out.push_str(&rest[..open]);
        let Some(close) = rest[open..].find('}') else { break };
        let field = &rest[open + 1..open + close];
        let (name, spec) = field.split_once(':').unwrap_or((field, ""));
        let value = values.iter().find(|(n, _)| *n == name).map(|(_, v)| v.clone()).unwrap_or_default();
        let width: usize = spec.trim_end_matches('d').trim_start_matches('0').parse().unwrap_or(0);
        if width > 0 && value.parse::<i64>().is_ok() {
            out.push_str(&format!("{value:0>width$}"));
        } else {
            out.push_str(&value);
        }
        rest = &rest[open + close + 1..];
    }
    out.push_str(rest);
    out
}

pub(crate) fn read_parquet(path: &Path) -> Result<Vec<RecordBatch>, LeRobotError> {
    let file = std::fs::File::open(path).map_err(io(path))?;
    let reader = ParquetRecordBatchReaderBuilder::try_new(file)
        .and_then(|b| b.with_batch_size(8192).build())
        .map_err(|e| bad(path, format!("not a readable Parquet file: {e}")))?;
    reader.collect::<Result<Vec<_>, _>>().map_err(|e| bad(path, e.to_string()))
}

/// A numeric array's values as f64.
fn floats(a: &dyn Array) -> Option<Vec<f64>> {
    let any = a.as_any();
    if let Some(x) = any.downcast_ref::<Float32Array>() {
        return Some(x.values().iter().map(|v| f64::from(*v)).collect());
    }
    if let Some(x) = any.downcast_ref::<Float64Array>() {
        return Some(x.values().to_vec());
    }
    if let Some(x) = any.downcast_ref::<Int64Array>() {
        return Some(x.values().iter().map(|v| *v as f64).collect());
    }
    if let Some(x) = any.downcast_ref::<Int32Array>() {
        return Some(x.values().iter().map(|v| f64::from(*v)).collect());
    }
    if let Some(x) = any.downcast_ref::<BooleanArray>() {
        return Some((0..x.len()).map(|i| if x.value(i) { 1.0 } else { 0.0 }).collect());
    }
    None
}

/// A column's rows as vectors (a scalar column: vectors of one).
fn rows_of(a: &ArrayRef) -> Option<Vec<Vec<f64>>> {
    match a.data_type() {
        DataType::FixedSizeList(_, n) => {
            let l = a.as_any().downcast_ref::<FixedSizeListArray>()?;
            let v = floats(l.values().as_ref())?;
            let n = *n as usize;
            Some(v.chunks(n.max(1)).take(l.len()).map(<[f64]>::to_vec).collect())
        }
        DataType::List(_) => {
            let l = a.as_any().downcast_ref::<ListArray>()?;
            (0..l.len()).map(|i| floats(l.value(i).as_ref())).collect()
        }
        DataType::LargeList(_) => {
            let l = a.as_any().downcast_ref::<LargeListArray>()?;
            (0..l.len()).map(|i| floats(l.value(i).as_ref())).collect()
        }
        _ => floats(a.as_ref()).map(|v| v.into_iter().map(|x| vec![x]).collect()),
    }
}

/// A column of strings (or lists of strings: each row's first).
fn strings_of(a: &ArrayRef) -> Option<Vec<Vec<String>>> {
    let any = a.as_any();
    if let Some(s) = any.downcast_ref::<StringArray>() {
        return Some((0..s.len()).map(|i| vec![s.value(i).to_owned()]).collect());
    }
    if let Some(s) = any.downcast_ref::<LargeStringArray>() {
        return Some((0..s.len()).map(|i| vec![s.value(i).to_owned()]).collect());
    }
    if let Some(l) = any.downcast_ref::<ListArray>() {
        return (0..l.len()).map(|i| strings_of(&l.value(i)).map(|v| v.into_iter().flatten().collect())).collect();
    }
    if let Some(l) = any.downcast_ref::<LargeListArray>() {
        return (0..l.len()).map(|i| strings_of(&l.value(i)).map(|v| v.into_iter().flatten().collect())).collect();
    }
    None
}

/// A column over several batches.
fn column<T>(batches: &[RecordBatch], name: &str, f: impl Fn(&ArrayRef) -> Option<Vec<T>>) -> Option<Vec<T>> {
    let mut out = Vec::new();
    for b in batches {
        out.extend(f(b.column_by_name(name)?)?);
    }
    Some(out)
}

impl Dataset {
    /// Opens the dataset at `root` (its `meta/info.json` names the format).
    pub fn open(root: &Path) -> Result<Dataset, LeRobotError> {
        let info_path = root.join("meta/info.json");
        let text = std::fs::read_to_string(&info_path)
            .map_err(|e| bad(root, format!("not a LeRobot dataset (meta/info.json: {e})")))?;
        let info: Value = serde_json::from_str(&text).map_err(|e| bad(&info_path, format!("not JSON: {e}")))?;
        let version = info["codebase_version"].as_str().unwrap_or("").to_owned();
        if !matches!(version.as_str(), "v3.0" | "v2.1" | "v2.0") {
            return Err(bad(&info_path, format!("codebase_version {version:?}: labrig reads v3.0, v2.1 and v2.0")));
        }
        let fps = info["fps"].as_f64().filter(|f| *f > 0.0).ok_or_else(|| bad(&info_path, "no positive `fps`"))?;
        let features = info["features"].as_object().cloned().ok_or_else(|| bad(&info_path, "no `features`"))?;
        let text_of = |k: &str| info[k].as_str().map(str::to_owned).ok_or_else(|| bad(&info_path, format!("no `{k}`")));
        let data_path = text_of("data_path")?;
        let video_path = info["video_path"].as_str().unwrap_or("").to_owned();
        let chunks_size = info["chunks_size"].as_i64().unwrap_or(1000).max(1);
        let mut cameras = Vec::new();
        let mut image_features = Vec::new();
        for (key, f) in &features {
            // `observation.images.<name>`, or openpi's flat DROID image keys.
            let name = match key.strip_prefix("observation.images.") {
                Some(name) => name,
                None if matches!(f["dtype"].as_str(), Some("video" | "image")) && key.contains("image") => key.as_str(),
                None => continue,
            };
            match f["dtype"].as_str() {
                Some(d @ ("video" | "image")) => {
                    cameras.push(CameraKey { key: key.clone(), id: camera_id(name), video: d == "video" })
                }
                _ => image_features.push(key.clone()),
            }
        }
        // In info.json's order (the writer's, e.g. the rig's), which a parsed object loses.
        cameras.sort_by_key(|c: &CameraKey| text.find(&format!("\"{}\"", c.key)).unwrap_or(usize::MAX));
        let base_ns = std::fs::metadata(&info_path)
            .and_then(|m| m.modified())
            .ok()
            .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
            .map_or(0, |d| d.as_secs() as i64 * 1_000_000_000);
        let mut ds = Dataset {
            root: root.to_owned(),
            version,
            fps,
            features,
            episodes: Vec::new(),
            cameras,
            image_features,
            data_path,
            video_path,
            chunks_size,
            base_ns,
            cache: None,
        };
        ds.episodes = if ds.version == "v3.0" { ds.episodes_v30()? } else { ds.episodes_v2()? };
        ds.episodes.sort_by_key(|e| e.index);
        let mut offset_s = 0.0;
        for e in &mut ds.episodes {
            e.offset_s = offset_s;
            offset_s += e.length as f64 / ds.fps + 1.0;
        }
        Ok(ds)
    }

    fn episodes_v30(&self) -> Result<Vec<EpisodeEntry>, LeRobotError> {
        let dir = self.root.join("meta/episodes");
        let mut files: Vec<PathBuf> = Vec::new();
        for chunk in std::fs::read_dir(&dir).map_err(io(&dir))?.flatten() {
            if let Ok(rd) = std::fs::read_dir(chunk.path()) {
                files.extend(rd.flatten().map(|e| e.path()).filter(|p| p.extension().is_some_and(|x| x == "parquet")));
            }
        }
        files.sort();
        let mut out = Vec::new();
        for f in files {
            let batches = read_parquet(&f)?;
            let int = |name: &str| -> Result<Vec<i64>, LeRobotError> {
                column(&batches, name, |a| floats(a.as_ref()))
                    .map(|v| v.into_iter().map(|x| x as i64).collect())
                    .ok_or_else(|| bad(&f, format!("no integer column `{name}`")))
            };
            let index = int("episode_index")?;
            let length = int("length")?;
            let chunk = int("data/chunk_index")?;
            let file = int("data/file_index")?;
            let tasks = column(&batches, "tasks", strings_of).ok_or_else(|| bad(&f, "no `tasks` column"))?;
            let meta = column(&batches, "labrig/metadata", strings_of);
            let mut videos: Vec<BTreeMap<String, (i64, i64, f64)>> = vec![BTreeMap::new(); index.len()];
            for cam in self.cameras.iter().filter(|c| c.video) {
                let k = format!("videos/{}", cam.key);
                let c = int(&format!("{k}/chunk_index"))?;
                let fi = int(&format!("{k}/file_index"))?;
                let from = column(&batches, &format!("{k}/from_timestamp"), |a| floats(a.as_ref()))
                    .ok_or_else(|| bad(&f, format!("no `{k}/from_timestamp`")))?;
                for i in 0..index.len() {
                    videos[i].insert(cam.key.clone(), (c[i], fi[i], from[i]));
                }
            }
            for i in 0..index.len() {
                out.push(EpisodeEntry {
                    index: index[i],
                    length: length[i].max(0) as usize,
                    tasks: tasks[i].clone(),
                    data_file: Some((chunk[i], file[i])),
                    videos: std::mem::take(&mut videos[i]),
                    labrig_metadata: meta.as_ref().and_then(|m| m[i].first().cloned()).filter(|s| !s.is_empty()),
                    offset_s: 0.0,
                });
            }
        }
        Ok(out)
    }

    fn episodes_v2(&self) -> Result<Vec<EpisodeEntry>, LeRobotError> {
        let path = self.root.join("meta/episodes.jsonl");
        let text = std::fs::read_to_string(&path).map_err(io(&path))?;
        let mut out = Vec::new();
        for (n, line) in text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty()) {
            let v: Value = serde_json::from_str(line).map_err(|e| bad(&path, format!("line {}: {e}", n + 1)))?;
            let index =
                v["episode_index"].as_i64().ok_or_else(|| bad(&path, format!("line {}: no episode_index", n + 1)))?;
            out.push(EpisodeEntry {
                index,
                length: v["length"].as_u64().unwrap_or(0) as usize,
                tasks: v["tasks"]
                    .as_array()
                    .map(|a| a.iter().filter_map(|t| t.as_str().map(str::to_owned)).collect())
                    .unwrap_or_default(),
                data_file: None,
                videos: BTreeMap::new(),
                labrig_metadata: v.get("labrig_metadata").map(|m| m.to_string()),
                offset_s: 0.0,
            });
        }
        Ok(out)
    }

    fn data_file(&self, e: &EpisodeEntry) -> PathBuf {
        let values = match e.data_file {
            Some((c, f)) => vec![("chunk_index", c.to_string()), ("file_index", f.to_string())],
            None => vec![
                ("episode_chunk", (e.index / self.chunks_size).to_string()),
                ("episode_index", e.index.to_string()),
            ],
        };
        self.root.join(fill(&self.data_path, &values))
    }

    /// The MP4 holding `camera`'s frames of `e`, and the time of the episode's first frame in it.
    pub fn video(&self, e: &EpisodeEntry, camera: &CameraKey) -> (PathBuf, f64) {
        let (values, from) = match e.videos.get(&camera.key) {
            Some((c, f, from)) => (
                vec![("video_key", camera.key.clone()), ("chunk_index", c.to_string()), ("file_index", f.to_string())],
                *from,
            ),
            None => (
                vec![
                    ("video_key", camera.key.clone()),
                    ("episode_chunk", (e.index / self.chunks_size).to_string()),
                    ("episode_index", e.index.to_string()),
                ],
                0.0,
            ),
        };
        (self.root.join(fill(&self.video_path, &values)), from)
    }

    /// The rows of `e` in its data file, in frame order.
    fn rows(&mut self, e: &EpisodeEntry) -> Result<Vec<RecordBatch>, LeRobotError> {
        let path = self.data_file(e);
        if self.cache.as_ref().is_none_or(|(p, _)| *p != path) {
            // Each run of one episode's rows (they are consecutive), by episode.
            let mut by_episode: HashMap<i64, Vec<RecordBatch>> = HashMap::new();
            for b in read_parquet(&path)? {
                let idx = b
                    .column_by_name("episode_index")
                    .and_then(|a| floats(a.as_ref()))
                    .ok_or_else(|| bad(&path, "no `episode_index` column"))?;
                let mut start = 0;
                for k in 1..=idx.len() {
                    if k == idx.len() || idx[k] != idx[start] {
                        by_episode.entry(idx[start] as i64).or_default().push(b.slice(start, k - start));
                        start = k;
                    }
                }
            }
            self.cache = Some((path.clone(), by_episode));
        }
        let (_, by_episode) = self.cache.as_ref().expect("cached");
        Ok(by_episode.get(&e.index).cloned().unwrap_or_default())
    }

    /// Episode `e`'s frames of an image feature (dtype `image`): each frame's encoded bytes.
    pub fn image_frames(&mut self, e: &EpisodeEntry, key: &str) -> Result<Vec<Vec<u8>>, LeRobotError> {
        let path = self.data_file(e);
        let rows = self.rows(e)?;
        let mut out = Vec::new();
        for b in &rows {
            let col = b.column_by_name(key).ok_or_else(|| bad(&path, format!("no column `{key}`")))?;
            let st = col
                .as_any()
                .downcast_ref::<arrow_array::StructArray>()
                .ok_or_else(|| bad(&path, format!("`{key}` is not an image struct (bytes, path)")))?;
            let bytes = st.column_by_name("bytes").ok_or_else(|| bad(&path, format!("`{key}` has no `bytes`")))?;
            let any = bytes.as_any();
            for i in 0..st.len() {
                let v = if let Some(x) = any.downcast_ref::<arrow_array::BinaryArray>() {
                    x.value(i).to_vec()
                } else if let Some(x) = any.downcast_ref::<arrow_array::LargeBinaryArray>() {
                    x.value(i).to_vec()
                } else {
                    return Err(bad(&path, format!("`{key}.bytes` is not binary")));
                };
                out.push(v);
            }
        }
        Ok(out)
    }

    /// Episode `e`'s steps and metadata (no images). `kin` computes the TCP pose where the
    /// dataset has no `observation.state.cartesian_position`.
    pub fn read(&mut self, e: &EpisodeEntry, kin: &Fr3Kinematics) -> Result<ReadEpisode, LeRobotError> {
        let path = self.data_file(e);
        let rows = self.rows(e)?;
        let n = checked_length(&path, e, &rows)?;
        let cols = EpisodeColumns::read(&ColumnReader { path: &path, rows: &rows, episode: e.index }, n)?;
        let metadata = self.episode_metadata(&path, e, &rows, n)?;
        let steps = self.steps_of(&metadata, &cols, kin, n);
        Ok(ReadEpisode { metadata, steps, absent: cols.absent })
    }

    /// Episode `e`'s metadata: labrig's, where labrig exported the dataset, else what the
    /// dataset says; its length `n`.
    fn episode_metadata(
        &self,
        path: &Path,
        e: &EpisodeEntry,
        rows: &[RecordBatch],
        n: usize,
    ) -> Result<EpisodeMetadata, LeRobotError> {
        let mut metadata = match &e.labrig_metadata {
            Some(text) => labrig_metadata(path, text)?,
            None => self.metadata_of(e, rows, n),
        };
        metadata.trajectory_length = n as u64;
        Ok(metadata)
    }

    /// The `n` steps from the columns read: on the dataset's frame grid from the episode's
    /// start, every camera with a frame at each step.
    fn steps_of(&self, metadata: &EpisodeMetadata, cols: &EpisodeColumns, kin: &Fr3Kinematics, n: usize) -> Vec<Step> {
        let dt = (1e9 / self.fps).round() as i64;
        let arr = |v: &[f64]| -> [f64; 7] { std::array::from_fn(|i| v[i]) };
        let arr6 = |v: &[f64]| -> [f64; 6] { std::array::from_fn(|i| v[i]) };
        let mut steps = Vec::with_capacity(n);
        for k in 0..n {
            let t = metadata.start_ns + k as i64 * dt;
            let header = Header { stamp: Nanos(t).into(), frame_id: String::new() };
            let q = arr(&cols.joints[k]);
            let cart = match &cols.cartesian {
                Some(c) => arr6(&c[k]),
                None => labrig_arm::ik::xyz_euler(&kin.tcp_pose(&q)),
            };
            steps.push(Step {
                header: header.clone(),
                episode_id: metadata.uuid.clone(),
                step_index: k as u64,
                robot_state: RobotState {
                    header,
                    cartesian_position: cart,
                    gripper_position: cols.gripper[k],
                    joint_positions: q,
                    joint_velocities: arr(&cols.j_vel[k]),
                    prev_command_successful: true,
                    mode: RobotState::MODE_MOVING,
                    ..RobotState::default()
                },
                cameras: self
                    .cameras
                    .iter()
                    .map(|c| CameraFrameRef {
                        camera_id: c.id.clone(),
                        sequence: k as u64,
                        capture_ns: t,
                        arrival_ns: t,
                        ..CameraFrameRef::default()
                    })
                    .collect(),
                timing: ControlTiming {
                    step_start: t,
                    policy_start: t,
                    sleep_start: t,
                    control_start: t,
                    step_end: t + dt,
                    ..ControlTiming::default()
                },
                action: ActionDict {
                    cartesian_velocity: arr6(&cols.a_cvel[k]),
                    cartesian_position: arr6(&cols.a_cart[k]),
                    joint_velocity: arr(&cols.a_jvel[k]),
                    joint_position: arr(&cols.a_joints[k]),
                    gripper_velocity: cols.a_gvel[k][0],
                    gripper_position: cols.a_gripper[k],
                    target_cartesian_position: arr6(&cols.a_cart[k]),
                    target_gripper_position: cols.a_gripper[k],
                    ..ActionDict::default()
                },
                action_source: Step::SOURCE_TELEOP,
                movement_enabled: true,
                ..Step::default()
            });
        }
        steps
    }

    /// The metadata of an episode labrig did not export.
    fn metadata_of(&self, e: &EpisodeEntry, rows: &[RecordBatch], n: usize) -> EpisodeMetadata {
        let name = self.root.file_name().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| "lerobot".into());
        let mut extrinsics = BTreeMap::new();
        let mut serials = BTreeMap::new();
        for c in &self.cameras {
            let short = c.key.trim_start_matches("observation.images.");
            serials.insert(c.id.clone(), short.to_owned());
            for key in [format!("camera_extrinsics.{short}"), format!("observation.camera_extrinsics.{short}")] {
                if let Some(v) = column(rows, &key, rows_of).and_then(|v| v.into_iter().next())
                    && v.len() == 6
                    && v.iter().all(|x| x.is_finite())
                {
                    extrinsics.insert(c.id.clone(), std::array::from_fn(|i| v[i]));
                }
            }
        }
        // The DROID port's per-frame copies of its episode metadata.
        let text = |key: &str| -> String {
            column(rows, key, strings_of)
                .and_then(|v| v.into_iter().next())
                .and_then(|v| v.into_iter().next())
                .unwrap_or_default()
        };
        let success = column(rows, "is_episode_successful", rows_of).and_then(|v| v.first().map(|r| r[0] != 0.0));
        EpisodeMetadata {
            uuid: format!("{name}+episode_{:06}", e.index),
            lab: "lerobot".into(),
            building: text("building"),
            user: text("collector_id"),
            task_instruction: e.tasks.first().cloned().unwrap_or_default(),
            success: Some(success.unwrap_or(true)),
            camera_serials: serials,
            extrinsics,
            start_ns: self.base_ns + (e.offset_s * 1e9) as i64,
            trajectory_length: n as u64,
            ..EpisodeMetadata::default()
        }
    }
}

/// Episode `e`'s number of rows, refused if there are none, if the metadata says another
/// length, or if the frame indices are not 0..n in order.
fn checked_length(path: &Path, e: &EpisodeEntry, rows: &[RecordBatch]) -> Result<usize, LeRobotError> {
    let n = rows.iter().map(RecordBatch::num_rows).sum::<usize>();
    if n == 0 {
        return Err(bad(path, format!("episode {}: no rows", e.index)));
    }
    if e.length != 0 && e.length != n {
        return Err(bad(path, format!("episode {}: {n} rows, the metadata says {}", e.index, e.length)));
    }
    let frame_index: Vec<i64> = column(rows, "frame_index", |a| floats(a.as_ref()))
        .map(|v| v.into_iter().map(|x| x as i64).collect())
        .unwrap_or_else(|| (0..n as i64).collect());
    if frame_index.iter().enumerate().any(|(k, f)| *f != k as i64) {
        return Err(bad(path, format!("episode {}: frame_index is not 0..{n} in order", e.index)));
    }
    Ok(n)
}

/// Reads an episode's numeric columns from its rows (of the data file at `path`).
struct ColumnReader<'a> {
    path: &'a Path,
    rows: &'a [RecordBatch],
    episode: i64,
}

impl ColumnReader<'_> {
    /// Column `key`, each row at least `width` wide and finite; None: no such column.
    fn get(&self, key: &str, width: usize) -> Result<Option<Vec<Vec<f64>>>, LeRobotError> {
        let Some(v) = column(self.rows, key, rows_of) else {
            if self.rows.first().is_some_and(|b| b.column_by_name(key).is_some()) {
                return Err(bad(self.path, format!("`{key}` is not numeric")));
            }
            return Ok(None);
        };
        if let Some((k, r)) = v.iter().enumerate().find(|(_, r)| r.len() < width) {
            return Err(bad(
                self.path,
                format!("episode {}, frame {k}: `{key}` has {} values, labrig reads {width}", self.episode, r.len()),
            ));
        }
        if let Some(k) = v.iter().position(|r| r.iter().any(|x| !x.is_finite())) {
            return Err(bad(self.path, format!("episode {}, frame {k}: `{key}` is not finite", self.episode)));
        }
        Ok(Some(v))
    }

    /// Column `key` of `n` rows `w` wide, zeros where there is none (its key added to `absent`).
    fn optional(&self, key: &str, w: usize, n: usize, absent: &mut Vec<String>) -> Result<Vec<Vec<f64>>, LeRobotError> {
        Ok(match self.get(key, w)? {
            Some(v) => v,
            None => {
                absent.push(key.to_owned());
                vec![vec![0.0; w]; n]
            }
        })
    }
}

/// The width of a column's narrowest row (0: no column, or no rows): a ragged column is read
/// only as wide as all its rows are (a row shorter than the first once panicked the import).
fn width(v: &Option<Vec<Vec<f64>>>) -> usize {
    v.as_ref().and_then(|v| v.iter().map(Vec::len).min()).unwrap_or(0)
}

/// An episode's columns as labrig's steps need them, from DROID's keys (the LeRobot DROID
/// port's), the 8-wide state and action, or openpi's flat keys.
struct EpisodeColumns {
    joints: Vec<Vec<f64>>,
    gripper: Vec<f64>,
    cartesian: Option<Vec<Vec<f64>>>,
    j_vel: Vec<Vec<f64>>,
    a_joints: Vec<Vec<f64>>,
    a_gripper: Vec<f64>,
    a_cart: Vec<Vec<f64>>,
    a_cvel: Vec<Vec<f64>>,
    a_jvel: Vec<Vec<f64>>,
    a_gvel: Vec<Vec<f64>>,
    /// Keys the steps are made without (their fields left at zero).
    absent: Vec<String>,
}

impl EpisodeColumns {
    /// Reads the columns of `n` rows, state then action.
    fn read(r: &ColumnReader, n: usize) -> Result<EpisodeColumns, LeRobotError> {
        let state = r.get("observation.state", 0)?;
        // openpi's flat DROID keys (`labrig export lerobot --schema openpi-droid`, openpi's own
        // converter): `joint_position`, `gripper_position`, `actions` = joint velocity + gripper.
        let flat_joints = r.get("joint_position", 7)?;
        let flat_gripper = r.get("gripper_position", 1)?;
        let flat_actions = r.get("actions", 8)?;
        let joints = state_joints(r, &state, &flat_joints)?;
        let gripper = state_gripper(r, &state, &flat_gripper)?;
        let cartesian = r.get("observation.state.cartesian_position", 6)?;
        let action = r.get("action", 0)?;
        let a_joints = action_joints(r, &action, &flat_actions, &joints, n)?;
        let a_gripper = action_gripper(r, &action, &flat_actions)?;
        let mut absent = Vec::new();
        let a_cart = r.optional("action.cartesian_position", 6, n, &mut absent)?;
        let a_cvel = r.optional("action.cartesian_velocity", 6, n, &mut absent)?;
        let a_jvel = match &flat_actions {
            Some(a) if r.get("action.joint_velocity", 7)?.is_none() => a.iter().map(|r| r[..7].to_vec()).collect(),
            _ => r.optional("action.joint_velocity", 7, n, &mut absent)?,
        };
        let a_gvel = r.optional("action.gripper_velocity", 1, n, &mut absent)?;
        let j_vel = r.optional("observation.state.joint_velocity", 7, n, &mut absent)?;
        absent.retain(|k| k != "observation.state.joint_velocity");
        Ok(EpisodeColumns {
            joints,
            gripper,
            cartesian,
            j_vel,
            a_joints,
            a_gripper,
            a_cart,
            a_cvel,
            a_jvel,
            a_gvel,
            absent,
        })
    }
}

/// The 7 joint positions: `observation.state.joint_position`, else the 8-wide state's, else
/// openpi's `joint_position`.
fn state_joints(
    r: &ColumnReader,
    state: &Option<Vec<Vec<f64>>>,
    flat_joints: &Option<Vec<Vec<f64>>>,
) -> Result<Vec<Vec<f64>>, LeRobotError> {
    Ok(match r.get("observation.state.joint_position", 7)? {
        Some(j) => j,
        None if width(state) >= 8 => state.clone().expect("wide"),
        None if flat_joints.is_some() => flat_joints.clone().expect("there"),
        None => {
            return Err(bad(
                r.path,
                format!(
                    "observation.state has {} values and there is no observation.state.joint_position: labrig reads DROID's layout (7 joints + gripper)",
                    width(state)
                ),
            ));
        }
    })
}

/// The gripper position: `observation.state.gripper_position`, else the 8-wide state's
/// last, else openpi's `gripper_position`.
fn state_gripper(
    r: &ColumnReader,
    state: &Option<Vec<Vec<f64>>>,
    flat_gripper: &Option<Vec<Vec<f64>>>,
) -> Result<Vec<f64>, LeRobotError> {
    Ok(match r.get("observation.state.gripper_position", 1)? {
        Some(g) => g.into_iter().map(|r| r[0]).collect::<Vec<_>>(),
        None if width(state) >= 8 => state.as_ref().expect("wide").iter().map(|r| r[7]).collect(),
        None if flat_gripper.is_some() => flat_gripper.as_ref().expect("there").iter().map(|r| r[0]).collect(),
        None => {
            return Err(bad(r.path, "no gripper: neither observation.state.gripper_position nor observation.state[7]"));
        }
    })
}

/// The commanded joint positions: `action.joint_position`, else the 8-wide action's, else
/// (openpi's `actions` are velocities) where the joints went: the next step's `joints`.
fn action_joints(
    r: &ColumnReader,
    action: &Option<Vec<Vec<f64>>>,
    flat_actions: &Option<Vec<Vec<f64>>>,
    joints: &[Vec<f64>],
    n: usize,
) -> Result<Vec<Vec<f64>>, LeRobotError> {
    Ok(match r.get("action.joint_position", 7)? {
        Some(j) => j,
        None if width(action) >= 8 => action.clone().expect("wide"),
        // openpi's `actions` are velocities: the commanded position is where the joints went.
        None if flat_actions.is_some() => (0..n).map(|k| joints[(k + 1).min(n - 1)].clone()).collect(),
        None => {
            return Err(bad(
                r.path,
                format!(
                    "action has {} values and there is no action.joint_position: labrig reads DROID's action (7 joint positions + gripper)",
                    width(action)
                ),
            ));
        }
    })
}

/// The commanded gripper position: `action.gripper_position`, else the 8-wide action's or
/// openpi's `actions`' last.
fn action_gripper(
    r: &ColumnReader,
    action: &Option<Vec<Vec<f64>>>,
    flat_actions: &Option<Vec<Vec<f64>>>,
) -> Result<Vec<f64>, LeRobotError> {
    Ok(match r.get("action.gripper_position", 1)? {
        Some(g) => g.into_iter().map(|r| r[0]).collect(),
        None if width(action) >= 8 => action.as_ref().expect("wide").iter().map(|r| r[7]).collect(),
        None if flat_actions.is_some() => flat_actions.as_ref().expect("there").iter().map(|r| r[7]).collect(),
        None => return Err(bad(r.path, "no gripper action: neither action.gripper_position nor action[7]")),
    })
}

/// labrig's metadata carried in the dataset (`labrig/metadata`: v2.x keeps it as an object,
/// v3.0 as a JSON string).
fn labrig_metadata(path: &Path, text: &str) -> Result<EpisodeMetadata, LeRobotError> {
    let v: Value = serde_json::from_str(text).map_err(|x| bad(path, format!("labrig/metadata: {x}")))?;
    let v = match v {
        Value::String(s) => serde_json::from_str(&s).map_err(|x| bad(path, format!("labrig/metadata: {x}")))?,
        other => other,
    };
    serde_json::from_value::<EpisodeMetadata>(v).map_err(|x| bad(path, format!("labrig/metadata: {x}")))
}

/// What an import did.
#[derive(Debug, Clone, serde::Serialize)]
pub struct ImportReport {
    pub source: PathBuf,
    pub version: String,
    pub out: PathBuf,
    /// Each imported episode: its LeRobot index, labrig directory, steps and frames.
    pub episodes: Vec<(i64, PathBuf, usize, u64)>,
    pub cameras: Vec<CameraKey>,
    /// Keys the dataset lacks (the steps' fields left at zero), with how many episodes.
    pub absent: BTreeMap<String, usize>,
    pub warnings: Vec<String>,
    /// Episodes left out, each with why.
    pub skipped: Vec<(i64, String)>,
    pub steps: usize,
    pub frames: u64,
    pub seconds: f64,
}

/// Where one camera's frames of an episode come from.
enum Frames {
    /// Its span of the MP4, decoded.
    Video(Mp4Reader),
    /// Its encoded images from the data file (JPEG kept as is, PNG re-encoded), and their size.
    Images { encoded: Vec<Vec<u8>>, width: u32, height: u32 },
}

/// Why `--episodes` is malformed, or why an episode could not be imported (it is skipped, named).
#[derive(Debug, thiserror::Error)]
pub enum LeRobotImportError {
    #[error("--episodes {arg}: `{part}` is not an episode index")]
    NotAnIndex { arg: String, part: String },
    #[error("--episodes {arg}: the range {range} is empty")]
    EmptyRange { arg: String, range: String },
    #[error(transparent)]
    Dataset(#[from] LeRobotError),
    #[error("camera {camera}: no images")]
    NoImages { camera: String },
    #[error("camera {camera} frame 0: {source}")]
    FirstImage {
        camera: String,
        #[source]
        source: ImageError,
    },
    #[error("camera {camera}: no video {}", path.display())]
    NoVideo { camera: String, path: PathBuf },
    #[error(transparent)]
    Video(#[from] labrig_droid::video::VideoError),
    #[error(transparent)]
    Write(#[from] labrig_droid::DroidError),
}

/// An image stored in the data file that labrig cannot read.
#[derive(Debug, thiserror::Error)]
pub enum ImageError {
    #[error(transparent)]
    Jpeg(#[from] labrig_episode::jpeg::JpegError),
    #[error("not a PNG or JPEG: {0}")]
    NotPngOrJpeg(#[source] png::DecodingError),
    #[error("a PNG too large")]
    TooLarge,
    #[error(transparent)]
    Png(png::DecodingError),
    #[error("a {0:?}-bit PNG (labrig reads 8-bit images)")]
    BitDepth(png::BitDepth),
    #[error("a {0:?} PNG (labrig reads RGB, RGBA and grey)")]
    ColorType(png::ColorType),
}

/// The size of an encoded PNG or JPEG image.
fn image_size(bytes: &[u8]) -> Result<(u32, u32), ImageError> {
    if bytes.starts_with(&[0xff, 0xd8]) {
        let img = labrig_episode::jpeg::decode_rgb(bytes)?;
        return Ok((img.width as u32, img.height as u32));
    }
    let r = png::Decoder::new(std::io::Cursor::new(bytes)).read_info().map_err(ImageError::NotPngOrJpeg)?;
    let info = r.info();
    Ok((info.width, info.height))
}

/// An encoded image as JPEG: a JPEG as it is, a PNG (8-bit RGB, RGBA or grey) re-encoded.
fn as_jpeg(bytes: &[u8], quality: u8) -> Result<Vec<u8>, ImageError> {
    if bytes.starts_with(&[0xff, 0xd8]) {
        return Ok(bytes.to_vec());
    }
    let mut r = png::Decoder::new(std::io::Cursor::new(bytes)).read_info().map_err(ImageError::NotPngOrJpeg)?;
    let mut buf = vec![0u8; r.output_buffer_size().ok_or(ImageError::TooLarge)?];
    let info = r.next_frame(&mut buf).map_err(ImageError::Png)?;
    if info.bit_depth != png::BitDepth::Eight {
        return Err(ImageError::BitDepth(info.bit_depth));
    }
    let px = &buf[..info.buffer_size()];
    let rgb: Vec<u8> = match info.color_type {
        png::ColorType::Rgb => px.to_vec(),
        png::ColorType::Rgba => px.chunks_exact(4).flat_map(|p| [p[0], p[1], p[2]]).collect(),
        png::ColorType::Grayscale => px.iter().flat_map(|&g| [g, g, g]).collect(),
        other => return Err(ImageError::ColorType(other)),
    };
    Ok(labrig_episode::jpeg::encode_rgb(&rgb, info.width as u16, info.height as u16, quality)?)
}

/// One camera's frames of an episode, decoded from its span of the MP4 (or its images).
struct VideoFrames {
    readers: Vec<Option<Frames>>,
    ids: Vec<String>,
    quality: u8,
    path: PathBuf,
    short: Vec<bool>,
    warnings: Vec<String>,
    steps: usize,
}

impl FrameSource for VideoFrames {
    fn size(&self, camera: usize) -> Option<(u32, u32)> {
        self.readers[camera].as_ref().map(|r| match r {
            Frames::Video(r) => (r.width, r.height),
            Frames::Images { width, height, .. } => (*width, *height),
        })
    }

    fn frame(&mut self, camera: usize, step: usize, wanted: bool) -> Result<Option<Vec<u8>>, labrig_droid::DroidError> {
        let failed = |path: &Path, what: String| labrig_droid::DroidError::Io {
            path: path.to_owned(),
            source: std::io::Error::other(what),
        };
        let r = match self.readers[camera].as_mut() {
            None => return Ok(None),
            Some(Frames::Images { encoded, .. }) => {
                return match encoded.get(step) {
                    Some(bytes) if wanted => as_jpeg(bytes, self.quality)
                        .map(Some)
                        .map_err(|e| failed(&self.path, format!("camera {} frame {step}: {e}", self.ids[camera]))),
                    _ => Ok(None),
                };
            }
            Some(Frames::Video(r)) => r,
        };
        let at = StepFrame { camera: &self.ids[camera], step, steps: self.steps, wanted, quality: self.quality };
        next_step_frame(r, &mut self.short[camera], &at, &mut self.warnings, &self.path)
    }

    fn finish(&mut self, warnings: &mut Vec<String>) -> Result<(), labrig_droid::DroidError> {
        warnings.append(&mut self.warnings);
        Ok(())
    }
}

/// Parses `--episodes` (`0,3,5-9`).
pub fn parse_episodes(s: &str) -> Result<Vec<i64>, LeRobotImportError> {
    let mut out = Vec::new();
    for part in s.split(',').map(str::trim).filter(|p| !p.is_empty()) {
        let num = |x: &str| {
            x.trim()
                .parse::<i64>()
                .map_err(|_| LeRobotImportError::NotAnIndex { arg: s.to_owned(), part: x.to_owned() })
        };
        match part.split_once('-') {
            Some((a, b)) => {
                let (a, b) = (num(a)?, num(b)?);
                if b < a {
                    return Err(LeRobotImportError::EmptyRange { arg: s.to_owned(), range: part.to_owned() });
                }
                out.extend(a..=b);
            }
            None => out.push(num(part)?),
        }
    }
    Ok(out)
}

/// Imports the episodes of the LeRobot dataset at `root` (all, or `only`) as labrig episodes
/// under `out` (the recorder's layout). A bad episode is skipped and named; nothing of it is
/// left. `progress(done, total)`.
pub fn import(
    root: &Path,
    only: Option<&[i64]>,
    out: &Path,
    opts: &ImportOptions,
    mut progress: impl FnMut(usize, usize),
) -> Result<ImportReport, LeRobotError> {
    let started = std::time::Instant::now();
    let mut ds = Dataset::open(root)?;
    let kin = Fr3Kinematics::from_urdf_file(&labrig_arm::urdf_path(None), TcpOffset::ROBOTIQ_2F85)
        .map_err(|e| bad(root, format!("the FR3 model: {e}")))?;
    let entries: Vec<EpisodeEntry> = match only {
        None => ds.episodes.clone(),
        Some(want) => {
            let missing: Vec<&i64> = want.iter().filter(|i| !ds.episodes.iter().any(|e| e.index == **i)).collect();
            if !missing.is_empty() {
                return Err(bad(
                    root,
                    format!("no episode {missing:?} in the dataset (it has {} episodes)", ds.episodes.len()),
                ));
            }
            ds.episodes.iter().filter(|e| want.contains(&e.index)).cloned().collect()
        }
    };
    let mut report = ImportReport {
        source: root.to_owned(),
        version: ds.version.clone(),
        out: out.to_owned(),
        episodes: Vec::new(),
        cameras: ds.cameras.clone(),
        absent: BTreeMap::new(),
        warnings: ds
            .image_features
            .iter()
            .map(|k| format!("{k}: stored as images in the Parquet, not imported"))
            .collect(),
        skipped: Vec::new(),
        steps: 0,
        frames: 0,
        seconds: 0.0,
    };
    for (done, e) in entries.iter().enumerate() {
        progress(done, entries.len());
        match import_one(&mut ds, e, &kin, out, opts) {
            Ok((dir, read, frames, warnings)) => {
                for k in read.absent {
                    *report.absent.entry(k).or_default() += 1;
                }
                report.warnings.extend(warnings.into_iter().map(|w| format!("episode {}: {w}", e.index)));
                report.steps += read.steps.len();
                report.frames += frames;
                report.episodes.push((e.index, dir, read.steps.len(), frames));
            }
            Err(why) => report.skipped.push((e.index, why.to_string())),
        }
    }
    progress(entries.len(), entries.len());
    report.seconds = started.elapsed().as_secs_f64();
    Ok(report)
}

type Imported = (PathBuf, ReadEpisode, u64, Vec<String>);

fn import_one(
    ds: &mut Dataset,
    e: &EpisodeEntry,
    kin: &Fr3Kinematics,
    out: &Path,
    opts: &ImportOptions,
) -> Result<Imported, LeRobotImportError> {
    let read = ds.read(e, kin)?;
    let n = read.steps.len();
    let mut readers = Vec::new();
    for c in ds.cameras.clone() {
        if !c.video {
            let encoded = ds.image_frames(e, &c.key)?;
            let first = encoded.first().ok_or_else(|| LeRobotImportError::NoImages { camera: c.key.clone() })?;
            let (width, height) =
                image_size(first).map_err(|source| LeRobotImportError::FirstImage { camera: c.key.clone(), source })?;
            readers.push(Some(Frames::Images { encoded, width, height }));
            continue;
        }
        let (path, from) = ds.video(e, &c);
        if !path.is_file() {
            return Err(LeRobotImportError::NoVideo { camera: c.key.clone(), path });
        }
        readers.push(Some(Frames::Video(Mp4Reader::open_at(&path, from, ds.fps, n)?)));
    }
    let cameras: Vec<Camera> = ds
        .cameras
        .iter()
        .map(|c| Camera {
            id: c.id.clone(),
            serial: read.metadata.camera_serials.get(&c.id).cloned().unwrap_or_else(|| c.id.clone()),
            k: None,
        })
        .collect();
    let mut frames = VideoFrames {
        short: vec![false; readers.len()],
        readers,
        ids: ds.cameras.iter().map(|c| c.id.clone()).collect(),
        quality: opts.jpeg_quality,
        path: ds.root.clone(),
        warnings: Vec::new(),
        steps: n,
    };
    let mut warnings = Vec::new();
    let note = format!("imported from LeRobot {} {}", ds.version, ds.root.display());
    let (dir, written) = labrig_droid::import::write_imported(
        read.metadata.clone(),
        &read.steps,
        &cameras,
        None,
        out,
        opts,
        &mut frames,
        &[],
        &mut warnings,
        &note,
    )?;
    Ok((dir, read, written, warnings))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_ragged_column_is_as_wide_as_its_narrowest_row() {
        assert_eq!(width(&None), 0);
        assert_eq!(width(&Some(vec![])), 0);
        assert_eq!(width(&Some(vec![vec![0.0; 8], vec![0.0; 4], vec![0.0; 8]])), 4);
        assert_eq!(width(&Some(vec![vec![0.0; 8]; 3])), 8);
    }

    #[test]
    fn templates_fill_as_python_formats_them() {
        assert_eq!(
            fill(
                "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet",
                &[("chunk_index", "0".into()), ("file_index", "12".into())]
            ),
            "data/chunk-000/file-012.parquet"
        );
        assert_eq!(
            fill(
                "videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4",
                &[
                    ("episode_chunk", "1".into()),
                    ("video_key", "observation.images.ext1".into()),
                    ("episode_index", "1042".into())
                ]
            ),
            "videos/chunk-001/observation.images.ext1/episode_001042.mp4"
        );
    }

    #[test]
    fn episode_lists_parse_and_bad_ones_are_named() {
        assert_eq!(parse_episodes("0,3,5-7").unwrap(), vec![0, 3, 5, 6, 7]);
        assert!(parse_episodes("1,x").unwrap_err().to_string().contains("`x`"));
        assert!(parse_episodes("5-2").unwrap_err().to_string().contains("empty"));
    }

    #[test]
    fn droid_port_cameras_get_labrigs_ids() {
        assert_eq!(camera_id("exterior_1_left"), "ext1");
        assert_eq!(camera_id("wrist_image_left"), "wrist");
        assert_eq!(camera_id("top"), "top");
    }
}
