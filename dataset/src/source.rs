//! Episodes to index rows, by auto-detection: labrig MCAP episodes (a directory holding
//! `episode_0.mcap`), DROID raw episodes (a directory holding `trajectory.h5` and
//! `metadata_<uuid>.json`), DROID-layout MCAP files (`trajectory.mcap`, any `*.mcap` not in a
//! labrig episode), DROID's RLDS shards (`*.tfrecord-NNNNN-of-NNNNN`, many episodes each) and
//! LeRobot datasets (a directory holding `meta/info.json`, v3.0 or v2.x: the LeRobot DROID
//! port's keys or a labrig export, read in place by [`crate::lerobot_import::Dataset`]).
//! Only low-dimensional data is derived: no image is decoded.

use crate::INDEX_VERSION;
use crate::dv::{self, GraspParams, Vocabulary};
use crate::recal::Recalibration;
use crate::row::{CAMERAS, IndexRow};
use labrig_episode::EpisodeMetadata;
use std::path::{Path, PathBuf};

/// An episode found under a root.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord)]
pub struct Found {
    pub dir: PathBuf,
    pub format: Format,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum Format {
    Labrig,
    DroidRaw,
    /// DROID's MCAP layout (its `dir` is the file).
    DroidMcap,
    /// A TFRecord shard of an RLDS dataset (its `dir` is the file).
    Rlds,
    /// A LeRobot dataset (its `dir` is the root), many episodes.
    LeRobot,
}

impl Format {
    pub fn name(self) -> &'static str {
        match self {
            Format::Labrig => "labrig",
            Format::DroidRaw => "droid_raw",
            Format::DroidMcap => "droid_mcap",
            Format::Rlds => "rlds",
            Format::LeRobot => "lerobot",
        }
    }
}

/// Every episode under `root` (sorted by path, so shards are stable).
pub fn discover(root: &Path) -> Vec<Found> {
    let mut found: Vec<Found> = labrig_episode::episode::find_episodes(root)
        .into_iter()
        .map(|dir| Found { dir, format: Format::Labrig })
        .chain(
            labrig_episode::episode::dirs_holding(root, "trajectory.h5")
                .into_iter()
                .map(|dir| Found { dir, format: Format::DroidRaw }),
        )
        .collect();
    found.extend(tfrecords(root).into_iter().map(|dir| Found { dir, format: Format::Rlds }));
    found.extend(
        labrig_episode::episode::dirs_holding(root, "meta/info.json")
            .into_iter()
            .map(|dir| Found { dir, format: Format::LeRobot }),
    );
    found.extend(
        labrig_droid::droid_mcap::find_droid_mcaps(root)
            .into_iter()
            .map(|dir| Found { dir, format: Format::DroidMcap }),
    );
    found.sort();
    found
}

/// TFRecord shards under `root` (TFDS names them `<name>-<split>.tfrecord-NNNNN-of-NNNNN`).
fn tfrecords(root: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let Ok(entries) = std::fs::read_dir(root) else { return out };
    for e in entries.flatten() {
        let p = e.path();
        if p.is_dir() {
            out.extend(tfrecords(&p));
        } else if p.file_name().and_then(|n| n.to_str()).is_some_and(|n| n.contains(".tfrecord")) {
            out.push(p);
        }
    }
    out
}

/// How rows are derived.
#[derive(Debug, Clone)]
pub struct Derive {
    pub vocabulary: Vocabulary,
    pub grasp: GraspParams,
    /// The table centre in the base frame (m), the origin of the spherical coordinates.
    pub table_centre: [f64; 3],
    /// Re-calibrated extrinsics that replace an episode's own (`--extrinsics`).
    pub recalibration: Option<std::sync::Arc<Recalibration>>,
}

impl Default for Derive {
    fn default() -> Derive {
        Derive {
            vocabulary: Vocabulary::default_words(),
            grasp: GraspParams::default(),
            table_centre: [0.5, 0.0, 0.0],
            recalibration: None,
        }
    }
}

/// The files an episode is (their total size and newest modification time say whether it
/// changed since it was indexed).
pub fn files_of(found: &Found) -> std::io::Result<Vec<PathBuf>> {
    if matches!(found.format, Format::Rlds | Format::DroidMcap) {
        return Ok(vec![found.dir.clone()]);
    }
    if found.format == Format::LeRobot {
        // Its metadata and data files (the videos are not read).
        let mut files = Vec::new();
        let mut stack = vec![found.dir.join("meta"), found.dir.join("data")];
        while let Some(d) = stack.pop() {
            for e in std::fs::read_dir(&d)? {
                let p = e?.path();
                if p.is_dir() { stack.push(p) } else { files.push(p) }
            }
        }
        files.sort();
        return Ok(files);
    }
    let mut files = Vec::new();
    for e in std::fs::read_dir(&found.dir)? {
        let p = e?.path();
        let name = p.file_name().and_then(|n| n.to_str()).unwrap_or("");
        let keep = match found.format {
            Format::Labrig => {
                name.ends_with(".mcap") || name == "metadata.yaml" || name == labrig_episode::judge::JUDGED_FILE
            }
            Format::DroidRaw => name == "trajectory.h5" || (name.starts_with("metadata_") && name.ends_with(".json")),
            Format::Rlds | Format::DroidMcap | Format::LeRobot => false,
        };
        if keep {
            files.push(p);
        }
    }
    files.sort();
    Ok(files)
}

/// (total size, newest mtime in ns) of an episode's files.
pub fn stamp(found: &Found) -> std::io::Result<(u64, i64)> {
    let mut size = 0;
    let mut mtime = 0i64;
    for f in files_of(found)? {
        let m = std::fs::metadata(&f)?;
        size += m.len();
        let t = m.modified()?.duration_since(std::time::UNIX_EPOCH).map(|d| d.as_nanos() as i64).unwrap_or(0);
        mtime = mtime.max(t);
    }
    Ok((size, mtime))
}

/// Why what was found cannot be indexed; each names the file or directory (the index's
/// `reason`).
#[derive(Debug, thiserror::Error)]
pub enum SourceError {
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{}: no steps", dir.display())]
    NoSteps { dir: PathBuf },
    #[error(transparent)]
    Episode(#[from] labrig_episode::ReadError),
    #[error("{}: no DROID metadata record", dir.display())]
    NoMetadata { dir: PathBuf },
    #[error(transparent)]
    Droid(#[from] labrig_droid::DroidError),
    #[error("{}: /robot_state has no cartesian_position of 6 numbers a step", file.display())]
    NoCartesian { file: PathBuf },
    #[error("{}: no gripper_position in /action or /robot_state", file.display())]
    NoGripper { file: PathBuf },
    #[error("{}: no metadata_<uuid>.json beside trajectory.h5", dir.display())]
    NoMetadataJson { dir: PathBuf },
    #[error("{}: not JSON: {source}", path.display())]
    NotJson {
        path: PathBuf,
        #[source]
        source: serde_json::Error,
    },
    #[error("{}: {source}", path.display())]
    Metadata {
        path: PathBuf,
        #[source]
        source: labrig_msgs::Invalid,
    },
    #[error(transparent)]
    H5(#[from] labrig_droid::h5doc::H5Error),
    #[error("{}: no `{key}`", h5.display())]
    NoDataset { h5: PathBuf, key: String },
    #[error("{}: `{key}` is {dtype}, not float64", h5.display())]
    NotFloat64 { h5: PathBuf, key: String, dtype: &'static str },
    #[error("{}: cartesian_position has shape {shape:?}, not (T, 6)", h5.display())]
    CartesianShape { h5: PathBuf, shape: Vec<usize> },
    #[error("{}: gripper_position has {gripper} steps, cartesian_position {steps}", h5.display())]
    GripperSteps { h5: PathBuf, gripper: usize, steps: usize },
    #[error(transparent)]
    LeRobot(#[from] crate::lerobot::LeRobotError),
    #[error("the FR3 model: {0}")]
    Kinematics(#[source] labrig_arm::kinematics::KinematicsError),
    #[error("{}: {source}", file.display())]
    Rlds {
        file: PathBuf,
        #[source]
        source: crate::rlds::RldsError,
    },
    #[error("{} episode {episode}: {source}", file.display())]
    RldsExample {
        file: PathBuf,
        episode: usize,
        #[source]
        source: crate::rlds::RldsError,
    },
    #[error("{} episode {episode}: no steps/observation/cartesian_position", file.display())]
    RldsNoCartesian { file: PathBuf, episode: usize },
    #[error("{} episode {episode}: cartesian_position holds {len} values, not T x 6", file.display())]
    RldsCartesianLen { file: PathBuf, episode: usize, len: usize },
    #[error("{} episode {episode}: no gripper signal of {steps} steps", file.display())]
    RldsNoGripper { file: PathBuf, episode: usize, steps: usize },
}

/// `map_err` for an I/O error on `path`.
fn io(path: &Path) -> impl FnOnce(std::io::Error) -> SourceError + '_ {
    move |source| SourceError::Io { path: path.to_owned(), source }
}

/// The rows of what was found (one episode, or an RLDS shard's many), or why it cannot be
/// indexed.
pub fn rows(found: &Found, d: &Derive) -> Result<Vec<IndexRow>, SourceError> {
    let (file_size, file_mtime_ns) = stamp(found).map_err(io(&found.dir))?;
    let read = match found.format {
        Format::Labrig => vec![read_labrig(&found.dir)?],
        Format::DroidRaw => vec![read_droid_raw(&found.dir)?],
        Format::DroidMcap => vec![read_droid_mcap(&found.dir)?],
        Format::Rlds => read_rlds(&found.dir)?,
        Format::LeRobot => read_lerobot(&found.dir)?,
    };
    let many = read.len() > 1 || matches!(found.format, Format::Rlds | Format::LeRobot);
    read.into_iter()
        .enumerate()
        .map(|(k, r)| {
            let mut row = row_of(found, r, d, (file_size, file_mtime_ns))?;
            if many {
                row.source_path = format!("{}#{k}", row.source_path);
            }
            Ok(row)
        })
        .collect()
}

fn row_of(
    found: &Found,
    read: Read,
    d: &Derive,
    (file_size, file_mtime_ns): (u64, i64),
) -> Result<IndexRow, SourceError> {
    let (meta, xyz, gripper, instructions) = read;
    if xyz.is_empty() {
        return Err(SourceError::NoSteps { dir: found.dir.clone() });
    }
    let instruction = instructions.first().cloned().filter(|s| !s.is_empty());
    let text = instructions.join(" ");
    let object_position = dv::first_grasp(&gripper, d.grasp).map(|t| xyz[t]);
    let mut colour = d.vocabulary.colour(&text);
    if colour.is_none()
        && let Some(scene) = meta.sim_scene.as_deref().and_then(|s| serde_json::from_str::<serde_json::Value>(s).ok())
        && let Some(hsv) = scene.get("object_hsv").and_then(|v| serde_json::from_value::<[f64; 3]>(v.clone()).ok())
    {
        colour = Some(dv::colour_of_hsv(hsv).to_owned());
    }
    let cameras = CAMERAS
        .iter()
        .map(|c| {
            let serial = meta.camera_serials.get(*c).cloned();
            let recalibrated = match (&d.recalibration, &serial) {
                (Some(r), Some(s)) => r.pose(&meta.uuid, s),
                _ => None,
            };
            let mut row =
                dv::camera_row(serial, recalibrated.or_else(|| meta.extrinsics.get(*c).copied()), d.table_centre);
            if recalibrated.is_some() {
                row.extrinsics_from = Some("recalibrated".to_owned());
            }
            row
        })
        .collect();
    Ok(IndexRow {
        index_version: INDEX_VERSION,
        episode_id: meta.uuid.clone(),
        source_path: found.dir.display().to_string(),
        source_format: found.format.name().to_owned(),
        file_size,
        file_mtime_ns,
        success: meta.success,
        lab: meta.lab.clone(),
        building: meta.building.clone(),
        scene_id: meta.scene_id.clone(),
        instruction,
        instruction_2: instructions.get(1).cloned().filter(|s| !s.is_empty()),
        instruction_3: instructions.get(2).cloned().filter(|s| !s.is_empty()),
        length: xyz.len() as u64,
        cameras,
        object_position,
        object: d.vocabulary.object(&text),
        primitive: d.vocabulary.primitive(&text),
        colour,
        sim_dv: meta.sim_scene.clone(),
    })
}

type Read = (EpisodeMetadata, Vec<[f64; 3]>, Vec<f64>, Vec<String>);

fn read_labrig(dir: &Path) -> Result<Read, SourceError> {
    let data = labrig_episode::read_episode(dir)?;
    let meta = data.metadata.ok_or_else(|| SourceError::NoMetadata { dir: dir.to_owned() })?;
    let xyz = data.steps.iter().map(|s| {
        let c = s.robot_state.cartesian_position;
        [c[0], c[1], c[2]]
    });
    // The commanded gripper (the operator's trigger): a gripper closed on an object stalls
    // part-way, so the measured position may never pass the threshold.
    let gripper = data.steps.iter().map(|s| s.action.gripper_position).collect();
    let instructions = vec![meta.task_instruction.clone()];
    Ok((meta, xyz.collect(), gripper, instructions))
}

/// A DROID-layout MCAP: its metadata as `labrig import droid-mcap` reads it, the TCP positions
/// and the gripper (commanded where the file has it). Its images are read too, undecoded.
fn read_droid_mcap(file: &Path) -> Result<Read, SourceError> {
    use labrig_droid::droid_mcap;
    use labrig_droid::h5doc::Data;
    let mut read = droid_mcap::read_mcap(file)?;
    let meta = droid_mcap::episode_metadata(&mut read, file)?.meta;
    let n = read.times_ns.len();
    let column = |key: &str, width: usize| -> Option<Vec<f64>> {
        match &read.doc.datasets.get(key)?.data {
            Data::F64(v) if v.len() == n * width => Some(v.clone()),
            _ => None,
        }
    };
    let cart = column("observation/robot_state/cartesian_position", 6)
        .ok_or_else(|| SourceError::NoCartesian { file: file.to_owned() })?;
    let gripper = column("action/gripper_position", 1)
        .or_else(|| column("observation/robot_state/gripper_position", 1))
        .ok_or_else(|| SourceError::NoGripper { file: file.to_owned() })?;
    let xyz = cart.chunks_exact(6).map(|c| [c[0], c[1], c[2]]).collect();
    let instructions = vec![meta.task_instruction.clone()];
    Ok((meta, xyz, gripper, instructions))
}

fn read_droid_raw(dir: &Path) -> Result<Read, SourceError> {
    let json_path = std::fs::read_dir(dir)
        .map_err(io(dir))?
        .filter_map(Result::ok)
        .map(|e| e.path())
        .find(|p| {
            let n = p.file_name().and_then(|n| n.to_str()).unwrap_or("");
            n.starts_with("metadata_") && n.ends_with(".json")
        })
        .ok_or_else(|| SourceError::NoMetadataJson { dir: dir.to_owned() })?;
    let text = std::fs::read_to_string(&json_path).map_err(io(&json_path))?;
    let value: serde_json::Value =
        serde_json::from_str(&text).map_err(|source| SourceError::NotJson { path: json_path.clone(), source })?;
    let mut meta = labrig_droid::meta::parse(&value)
        .map_err(|source| SourceError::Metadata { path: json_path.clone(), source })?
        .meta;
    // DROID's own files say success by their folder.
    if meta.success.is_none() {
        let path = dir.display().to_string();
        meta.success = if path.contains("/success/") {
            Some(true)
        } else if path.contains("/failure/") {
            Some(false)
        } else {
            None
        };
    }
    let h5 = dir.join("trajectory.h5");
    let doc = labrig_droid::h5doc::read(&h5)?;
    let column = |key: &str| -> Result<(Vec<usize>, Vec<f64>), SourceError> {
        let c = doc.datasets.get(key).ok_or_else(|| SourceError::NoDataset { h5: h5.clone(), key: key.to_owned() })?;
        match &c.data {
            labrig_droid::h5doc::Data::F64(v) => Ok((c.shape.clone(), v.clone())),
            other => Err(SourceError::NotFloat64 { h5: h5.clone(), key: key.to_owned(), dtype: other.dtype() }),
        }
    };
    let (shape, cart) = column("observation/robot_state/cartesian_position")?;
    if shape.len() != 2 || shape[1] != 6 {
        return Err(SourceError::CartesianShape { h5, shape });
    }
    // The commanded gripper where the file has it (a gripper closed on an object stalls
    // part-way), else the measured one.
    let (gshape, gripper) = if doc.datasets.contains_key("action/gripper_position") {
        column("action/gripper_position")?
    } else {
        column("observation/robot_state/gripper_position")?
    };
    let steps = shape[0];
    if gshape.first() != Some(&steps) || gripper.len() != steps {
        return Err(SourceError::GripperSteps { h5, gripper: gshape.first().copied().unwrap_or(0), steps });
    }
    let xyz = cart.chunks_exact(6).map(|c| [c[0], c[1], c[2]]).collect();
    let mut instructions = vec![meta.task_instruction.clone()];
    for key in ["language_instruction_2", "language_instruction_3"] {
        if let Some(s) = value.get(key).and_then(|v| v.as_str()) {
            instructions.push(s.to_owned());
        }
    }
    Ok((meta, xyz, gripper, instructions))
}

/// A LeRobot dataset's episodes: the metadata `labrig import lerobot` would give them, the TCP
/// positions (`observation.state.cartesian_position`, else the FR3's kinematics of the joints),
/// the commanded gripper (the action's) and the episode's tasks.
fn read_lerobot(root: &Path) -> Result<Vec<Read>, SourceError> {
    use labrig_arm::kinematics::{Fr3Kinematics, TcpOffset};
    let mut ds = crate::lerobot_import::Dataset::open(root)?;
    let kin = Fr3Kinematics::from_urdf_file(&labrig_arm::urdf_path(None), TcpOffset::ROBOTIQ_2F85)
        .map_err(SourceError::Kinematics)?;
    let mut out = Vec::new();
    for e in ds.episodes.clone() {
        let r = ds.read(&e, &kin)?;
        let xyz = r.steps.iter().map(|s| {
            let c = s.robot_state.cartesian_position;
            [c[0], c[1], c[2]]
        });
        let gripper = r.steps.iter().map(|s| s.action.gripper_position).collect();
        let mut instructions = e.tasks.clone();
        if instructions.is_empty() {
            instructions.push(r.metadata.task_instruction.clone());
        }
        out.push((r.metadata, xyz.collect(), gripper, instructions));
    }
    Ok(out)
}

/// The features an RLDS episode is indexed by.
const RLDS_KEYS: [&str; 13] = [
    "steps/observation/cartesian_position",
    "steps/observation/gripper_position",
    "steps/action",
    "steps/is_first",
    "steps/language_instruction",
    "steps/language_instruction_2",
    "steps/language_instruction_3",
    "episode_metadata/file_path",
    "episode_metadata/recording_folderpath",
    "episode_metadata/building",
    "episode_metadata/extrinsics_exterior_cam_1",
    "episode_metadata/extrinsics_exterior_cam_2",
    "episode_metadata/extrinsics_wrist_cam",
];

fn read_rlds(file: &Path) -> Result<Vec<Read>, SourceError> {
    use crate::rlds::{self, Values};
    let bytes = std::fs::read(file).map_err(io(file))?;
    let records = rlds::records(&bytes).map_err(|source| SourceError::Rlds { file: file.to_owned(), source })?;
    let mut out = Vec::new();
    for (k, rec) in records.iter().enumerate() {
        let f = rlds::example(rec, &RLDS_KEYS).map_err(|source| SourceError::RldsExample {
            file: file.to_owned(),
            episode: k,
            source,
        })?;
        let floats = |key: &str| match f.get(key) {
            Some(Values::Floats(v)) => Some(v.iter().map(|x| *x as f64).collect::<Vec<f64>>()),
            _ => None,
        };
        let text = |key: &str| match f.get(key) {
            Some(Values::Bytes(v)) => v.iter().map(|b| String::from_utf8_lossy(b).into_owned()).find(|s| !s.is_empty()),
            _ => None,
        };
        let cart = floats("steps/observation/cartesian_position")
            .ok_or_else(|| SourceError::RldsNoCartesian { file: file.to_owned(), episode: k })?;
        if cart.len() % 6 != 0 {
            return Err(SourceError::RldsCartesianLen { file: file.to_owned(), episode: k, len: cart.len() });
        }
        let steps = cart.len() / 6;
        // The commanded gripper (the action's 7th value) where there is an action, as for raw data.
        let gripper = match floats("steps/action") {
            Some(a) if a.len() == steps * 7 => a.chunks_exact(7).map(|c| c[6]).collect(),
            _ => floats("steps/observation/gripper_position")
                .filter(|g| g.len() == steps)
                .ok_or_else(|| SourceError::RldsNoGripper { file: file.to_owned(), episode: k, steps })?,
        };
        let file_path = text("episode_metadata/file_path");
        let folder = text("episode_metadata/recording_folderpath");
        let mut meta = EpisodeMetadata {
            // DROID's episode key (its annotation releases use it).
            uuid: match (&folder, &file_path) {
                (Some(r), Some(p)) => format!("{r}--{p}"),
                (None, Some(p)) => p.clone(),
                _ => format!("{}#{k}", file.display()),
            },
            building: text("episode_metadata/building").unwrap_or_default(),
            task_instruction: text("steps/language_instruction").unwrap_or_default(),
            trajectory_length: steps as u64,
            ..EpisodeMetadata::default()
        };
        meta.success = file_path.as_deref().map(|p| p.contains("/success/"));
        for (id, key) in [
            ("ext1", "episode_metadata/extrinsics_exterior_cam_1"),
            ("ext2", "episode_metadata/extrinsics_exterior_cam_2"),
            ("wrist", "episode_metadata/extrinsics_wrist_cam"),
        ] {
            if let Some(e) = floats(key).filter(|e| e.len() == 6 && e.iter().any(|v| *v != 0.0)) {
                meta.extrinsics.insert(id.to_owned(), [e[0], e[1], e[2], e[3], e[4], e[5]]);
            }
        }
        let xyz = cart.chunks_exact(6).map(|c| [c[0], c[1], c[2]]).collect();
        let mut instructions = vec![meta.task_instruction.clone()];
        for key in ["steps/language_instruction_2", "steps/language_instruction_3"] {
            instructions.push(text(key).unwrap_or_default());
        }
        out.push((meta, xyz, gripper, instructions));
    }
    Ok(out)
}
