//! Training data from labrig's own episodes: each episode's `/rig/step` records give the
//! low-dimensional observation (end-effector position + quaternion) and the action (the
//! config's [`ActionSpace`]); its recorded JPEG frames of the config's cameras are decoded
//! once, resized to the config's square, and kept as u8 tensors (cached on disk, so that a
//! second run or a resumed one does not decode video again).
//!
//! A step's frame for a camera is the one the step referenced (by capture time); a step that
//! referenced none takes the camera's previous frame (the DROID export's rule).

use crate::policy::{ActionSpace, DiffusionConfig};
// The pose conventions training and the policy server share (also what `labrig export lerobot
// --schema labrig` writes), in labrig-arm so the dataset tools use the very same numbers.
pub use labrig_arm::ik::{canonical_axis_angle, canonical_quaternion};
use labrig_episode::{ReadError, read_episode};
use labrig_msgs::rig::{ActionDict, RobotState, Step};
use labrig_msgs::sensor_msgs::CompressedImage;
use labrig_msgs::topics::CAMERAS_PREFIX;
use nalgebra::UnitQuaternion;
use std::collections::BTreeMap;
use std::hash::{Hash, Hasher};
use std::path::{Path, PathBuf};
use tch::{Kind, Tensor};

/// Bumped when what a cache file holds changes.
const CACHE_VERSION: u32 = 3;

/// Why an episode cannot be trained on; every variant names it.
#[derive(Debug, thiserror::Error)]
pub enum DataError {
    #[error(transparent)]
    Read(#[from] ReadError),
    #[error(transparent)]
    Io(#[from] crate::FileError),
    #[error("{}: {reason}", path.display())]
    Bad { path: PathBuf, reason: String },
    #[error("{}: no camera `{camera}` (the config's cameras are {wanted:?}; the episode has {has:?})", path.display())]
    MissingCamera { path: PathBuf, camera: String, wanted: Vec<String>, has: Vec<String> },
    #[error("{}: step {step}: {what} holds a value that is not a finite number ({values:?})", path.display())]
    NotFinite { path: PathBuf, step: u64, what: &'static str, values: Vec<f64> },
    #[error("{}: the frame cache: {source}", path.display())]
    Cache {
        path: PathBuf,
        #[source]
        source: tch::TchError,
    },
}

/// One episode, ready to train on.
#[derive(Debug)]
pub struct EpisodeTensors {
    pub path: PathBuf,
    pub uuid: String,
    pub success: Option<bool>,
    /// (T, 7): position xyz + quaternion (x, y, z, w), sign kept continuous along the episode.
    pub state: Tensor,
    /// (T, 7): the config's action space.
    pub action: Tensor,
    /// (T, cameras, 3, S, S) u8.
    pub frames: Tensor,
    /// Who acted at each step (`Step::action_source`: teleop, policy, scripted, ...).
    pub source: Vec<u8>,
}

impl EpisodeTensors {
    pub fn len(&self) -> usize {
        self.state.size()[0] as usize
    }

    /// A rollout with corrections: some steps the policy's, some an operator's (the Quest's
    /// teleop or the sim's expert standing in for one).
    pub fn is_correction(&self) -> bool {
        self.source.contains(&Step::SOURCE_POLICY) && self.source.iter().any(|&s| Step::is_operator(s))
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// xyz + euler xyz (DROID's `cartesian_position`) -> the rotation.
fn rotation(p: &[f64; 6]) -> UnitQuaternion<f64> {
    UnitQuaternion::from_euler_angles(p[3], p[4], p[5])
}

/// The observed pose: position + [`canonical_quaternion`] (x, y, z, w).
pub fn state_of(rs: &RobotState) -> [f32; 7] {
    let p = &rs.cartesian_position;
    let [qx, qy, qz, qw] = canonical_quaternion(&rotation(p));
    [p[0], p[1], p[2], qx, qy, qz, qw].map(|x| x as f32)
}

/// The state's column of the gripper's opening, with `gripper_state` ([`state_row`]: after the
/// pose's 7 values).
pub const GRIPPER_COLUMN: i64 = 7;

/// A policy's state for one step: the pose (`state_of`), then the gripper's opening
/// (`gripper_state`), then the scene's positions (`scene_state`). Training and the policy
/// server build it here alike.
pub fn state_row(pose: &[f32; 7], rs: &RobotState, cfg: &DiffusionConfig, scene: Option<&[f32]>) -> Vec<f32> {
    let mut row = pose.to_vec();
    if cfg.gripper_state {
        row.push(rs.gripper_position as f32);
    }
    let at = row.len();
    row.extend(scene.into_iter().flatten().copied());
    if cfg.scene_relative && scene.is_some() {
        for k in 0..6 {
            row[at + k] -= pose[k % 3];
        }
    }
    row
}

/// The offset that makes `action_relative` chunks absolute: (B, 1, action_dim) holding each
/// row's TCP position (`state`'s first three values, (B, >=3)) then zeros. Training subtracts
/// it from the recorded chunk, inference adds it to the sampled one.
pub fn tcp_offset(state: &Tensor, action_dim: i64, kind: tch::Kind) -> Tensor {
    let tcp = state.narrow(1, 0, 3).to_kind(kind);
    let rest = Tensor::zeros([tcp.size()[0], action_dim - 3], (kind, tcp.device()));
    Tensor::cat(&[tcp, rest], 1).unsqueeze(1)
}

/// Each step's waypoint (T, 3), in the base frame: the TCP position (`state`'s first three
/// values) at the episode's next gripper event after the step, an event being a step whose
/// recorded gripper command (`action`'s column 6) is on the other side of one half from the
/// step's; after the last event, the episode's last TCP position. For a pick-and-place demo:
/// the grasp point until the gripper closes, then where it lets go, then where it ends.
/// Events at the steps in `ignore` do not count (a missed grasp's close and reopen, so the
/// steps before it point at the grasp that holds).
pub fn waypoints(state: &Tensor, action: &Tensor, ignore: &[usize]) -> Tensor {
    let n = state.size()[0];
    if n == 0 {
        return Tensor::zeros([0, 3], (Kind::Float, tch::Device::Cpu));
    }
    let tcp: Vec<f32> =
        Vec::try_from(state.narrow(1, 0, 3).to_kind(Kind::Float).contiguous().view([-1])).unwrap_or_default();
    let closed = gripper_closed(action);
    let n = n as usize;
    let mut at = vec![n - 1; n];
    for t in (0..n.saturating_sub(1)).rev() {
        let event = closed[t + 1] != closed[t] && !ignore.contains(&(t + 1));
        at[t] = if event { t + 1 } else { at[t + 1] };
    }
    let rows: Vec<f32> = at.iter().flat_map(|&k| tcp[3 * k..3 * k + 3].to_vec()).collect();
    Tensor::from_slice(&rows).view([n as i64, 3])
}

/// Each step's recorded gripper command (`action`'s column 6) as closed (> 0.5) or not.
fn gripper_closed(action: &Tensor) -> Vec<bool> {
    Vec::<f32>::try_from(action.select(1, 6).to_kind(Kind::Float).contiguous())
        .unwrap_or_default()
        .into_iter()
        .map(|g| g > 0.5)
        .collect()
}

/// A gripper reading (0 open .. 1 shut) at or above this while the fingers are commanded
/// closed and before the arm rises: they shut on nothing. The sim's 2F-85 reads about 0.45 on
/// the 50 mm cube, 0.75 on its edge, 0.82 on the drawer's 16 mm handle bar, and 0.97-0.98 shut
/// on nothing once the fingers settle (0.91 five steps after the close).
pub const MISSED_OPENING: f32 = 0.9;

/// Steps a missed grasp's descent may spend at the bottom before the close: resting, or
/// rising back from an overshoot (the drawer's descents dip ~7 mm below their goal and
/// come back up over ~5 steps).
const BOTTOM_STEPS: usize = 8;

/// A grasp in a recorded episode that closed on nothing: the fingers shut
/// ([`MISSED_OPENING`]) before the arm rose. Its descent and close are the mistake; what
/// follows from `lift` (rising with the fingers shut, opening, coming back) is the recovery.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MissedGrasp {
    /// The step whose action started the descent that led to the close (the last one at its
    /// top; the TCP went down every step after it, then waited at most [`BOTTOM_STEPS`]).
    pub descent: usize,
    /// The step the gripper command closed.
    pub close: usize,
    /// The first step the TCP is 5 mm above where it closed (the episode's length if never).
    pub lift: usize,
    /// The step the command opened again (the episode's length if never).
    pub reopen: usize,
}

impl MissedGrasp {
    /// The steps whose actions are the mistake: the descent and the close, up to the lift.
    pub fn mistake(&self) -> std::ops::Range<usize> {
        self.descent..self.lift
    }
}

/// The missed grasps of an episode, read from its state (position first; the gripper's
/// reading in column `gripper`) and its recorded gripper commands. A real rig's recordings
/// give them too: an operator's missed grasp is found the same way.
pub fn missed_grasps(state: &Tensor, action: &Tensor, gripper: i64) -> Vec<MissedGrasp> {
    let n = state.size()[0] as usize;
    if n == 0 || state.size()[1] <= gripper {
        return Vec::new();
    }
    let col = |c: i64| -> Vec<f32> {
        Vec::try_from(state.select(1, c).to_kind(Kind::Float).contiguous()).unwrap_or_default()
    };
    let (z, reading) = (col(2), col(gripper));
    let closed = gripper_closed(action);
    let mut out = Vec::new();
    let mut t = 1;
    while t < n {
        let closes = closed[t] && !closed[t - 1];
        if !closes {
            t += 1;
            continue;
        }
        let close = t;
        let reopen = (close..n).find(|&k| !closed[k]).unwrap_or(n);
        let lift = (close..reopen).find(|&k| z[k] > z[close] + 0.005).unwrap_or(reopen);
        if reading[close..lift].iter().any(|&g| g >= MISSED_OPENING) {
            // Back over the few steps at the bottom before the close (resting, or coming back
            // up from an overshoot: none higher than the next by over 1 mm), then up the descent to
            // the last step at its top: that step's action started it.
            let mut descent = close;
            while descent > 0 && close - descent < BOTTOM_STEPS && z[descent - 1] <= z[descent] + 1e-3 {
                descent -= 1;
            }
            while descent > 0 && z[descent - 1] > z[descent] + 1e-3 {
                descent -= 1;
            }
            out.push(MissedGrasp { descent, close, lift, reopen });
        }
        t = reopen.max(close + 1);
    }
    out
}

/// The recorded action in `space`: for `eef_axis_angle`, the target position and its
/// rotation as a [`canonical_axis_angle`].
pub fn action_of(a: &ActionDict, space: ActionSpace) -> [f32; 7] {
    let v: [f64; 7] = match space {
        ActionSpace::CartesianVelocity => {
            let c = &a.cartesian_velocity;
            [c[0], c[1], c[2], c[3], c[4], c[5], a.gripper_position]
        }
        ActionSpace::EefAxisAngle => {
            let p = &a.cartesian_position;
            let [rx, ry, rz] = canonical_axis_angle(&rotation(p));
            [p[0], p[1], p[2], rx, ry, rz, a.gripper_position]
        }
    };
    v.map(|x| x as f32)
}

/// The part files of an episode (its directory, or one `.mcap` file).
fn part_files(path: &Path) -> Result<Vec<PathBuf>, DataError> {
    if path.is_file() {
        return Ok(vec![path.to_owned()]);
    }
    let parts =
        labrig_episode::episode::part_files(path).map_err(crate::FileError::at(path, "listing the episode's files"))?;
    if parts.is_empty() {
        let droid = path.join("trajectory.h5").is_file();
        let reason = if droid {
            "a DROID raw episode: convert it first with `labrig import droid <dir> --out <episodes>`".to_owned()
        } else {
            "no episode_<k>.mcap here: not a labrig episode".to_owned()
        };
        return Err(DataError::Bad { path: path.to_owned(), reason });
    }
    Ok(parts)
}

/// The cache file for `path`'s episode as `cfg` sees it: keyed by the episode's files (path,
/// size, modification time), the cameras, the image size and the action space.
fn cache_file(cache: &Path, path: &Path, parts: &[PathBuf], cfg: &DiffusionConfig) -> PathBuf {
    let mut h = std::collections::hash_map::DefaultHasher::new();
    CACHE_VERSION.hash(&mut h);
    std::fs::canonicalize(path).unwrap_or(path.to_owned()).hash(&mut h);
    for p in parts {
        if let Ok(m) = std::fs::metadata(p) {
            (p, m.len(), m.modified().ok()).hash(&mut h);
        }
    }
    (
        &cfg.cameras,
        cfg.image_size,
        cfg.action_space,
        cfg.scene_state,
        cfg.gripper_state,
        cfg.scene_yaw,
        cfg.scene_relative,
    )
        .hash(&mut h);
    cache.join(format!("{:016x}.safetensors", h.finish()))
}

/// Loads one episode (from `cache` when it holds it; decoded and written there otherwise).
pub fn load_episode(path: &Path, cfg: &DiffusionConfig, cache: Option<&Path>) -> Result<EpisodeTensors, DataError> {
    let parts = part_files(path)?;
    let cached = cache.map(|c| cache_file(c, path, &parts, cfg));
    if let Some(file) = cached.as_ref().filter(|f| f.is_file())
        && let Ok(ep) = read_cache(file, path)
    {
        return Ok(ep);
    }
    let ep = decode_episode(path, &parts, cfg)?;
    if let Some(file) = cached {
        write_cache(&file, &ep)?;
    }
    Ok(ep)
}

fn read_cache(file: &Path, path: &Path) -> Result<EpisodeTensors, tch::TchError> {
    let mut named: BTreeMap<String, Tensor> = Tensor::read_safetensors(file)?.into_iter().collect();
    let mut take = |k: &str| named.remove(k).ok_or_else(|| tch::TchError::FileFormat(format!("no {k}")));
    let uuid: Vec<u8> = Vec::try_from(take("uuid")?)?;
    let success: Vec<i8> = Vec::try_from(take("success")?)?;
    Ok(EpisodeTensors {
        path: path.to_owned(),
        uuid: String::from_utf8_lossy(&uuid).into_owned(),
        success: match success.first() {
            Some(1) => Some(true),
            Some(0) => Some(false),
            _ => None,
        },
        state: take("state")?,
        action: take("action")?,
        frames: take("frames")?,
        source: Vec::try_from(take("source")?)?,
    })
}

fn write_cache(file: &Path, ep: &EpisodeTensors) -> Result<(), DataError> {
    let dir = file.parent().unwrap_or(Path::new("."));
    std::fs::create_dir_all(dir).map_err(crate::FileError::at(dir, "creating the frame cache"))?;
    let success = match ep.success {
        Some(true) => 1i8,
        Some(false) => 0,
        None => -1,
    };
    let tmp = file.with_extension("tmp");
    let tensors = [
        ("uuid", Tensor::from_slice(ep.uuid.as_bytes())),
        ("success", Tensor::from_slice(&[success])),
        ("state", ep.state.shallow_clone()),
        ("action", ep.action.shallow_clone()),
        ("frames", ep.frames.shallow_clone()),
        ("source", Tensor::from_slice(&ep.source)),
    ];
    Tensor::write_safetensors(&tensors, &tmp).map_err(|source| DataError::Cache { path: tmp.clone(), source })?;
    std::fs::rename(&tmp, file).map_err(|e| crate::FileError::at(file, "moving the cache file into place")(e).into())
}

/// The episode's steps as state and action rows, every value checked finite.
/// An episode's rows: per step 7 values.
type Rows = Vec<[f32; 7]>;

fn rows(path: &Path, steps: &[Step], space: ActionSpace) -> Result<(Rows, Rows), DataError> {
    let mut states: Vec<[f32; 7]> = Vec::with_capacity(steps.len());
    let mut actions: Vec<[f32; 7]> = Vec::with_capacity(steps.len());
    for s in steps {
        let not_finite =
            |what, values: Vec<f64>| DataError::NotFinite { path: path.to_owned(), step: s.step_index, what, values };
        let rs = &s.robot_state;
        if rs.cartesian_position.iter().any(|v| !v.is_finite()) {
            return Err(not_finite("robot_state.cartesian_position", rs.cartesian_position.to_vec()));
        }
        let a = &s.action;
        let used: Vec<f64> = match space {
            ActionSpace::EefAxisAngle => a.cartesian_position.iter().copied().chain([a.gripper_position]).collect(),
            ActionSpace::CartesianVelocity => {
                a.cartesian_velocity.iter().copied().chain([a.gripper_position]).collect()
            }
        };
        if used.iter().any(|v| !v.is_finite()) {
            return Err(not_finite("action", used));
        }
        states.push(state_of(rs));
        actions.push(action_of(a, space));
    }
    Ok((states, actions))
}

/// Every recorded frame of `cameras` in the episode's files: camera -> capture time -> JPEG.
/// An unfinished file is read up to its damage.
fn recorded_frames(parts: &[PathBuf], cameras: &[String]) -> Result<Vec<BTreeMap<i64, Vec<u8>>>, DataError> {
    let mut frames = vec![BTreeMap::new(); cameras.len()];
    for part in parts {
        let buf = std::fs::read(part).map_err(crate::FileError::at(part, "reading"))?;
        let Ok(stream) = mcap::MessageStream::new(&buf) else { continue };
        for m in stream {
            let Ok(m) = m else { break };
            let Some(cam) =
                m.channel.topic.strip_prefix(CAMERAS_PREFIX).and_then(|t| t.strip_suffix("/image/compressed"))
            else {
                continue;
            };
            let Some(k) = cameras.iter().position(|c| c == cam) else { continue };
            let img = labrig_msgs::decode::<CompressedImage>(&m.data)
                .map_err(|e| DataError::Bad { path: part.clone(), reason: format!("{}: {e}", m.channel.topic) })?;
            frames[k].insert(labrig_msgs::Nanos::from(img.header.stamp).0, img.data);
        }
    }
    Ok(frames)
}

/// The sim scene's object and receptacle positions (from the episode's `sim_scene` metadata,
/// or the `/sim/scene` JSON a policy request carries), and with `yaw` the object's yaw as
/// (cos 4 yaw, sin 4 yaw).
pub fn scene_positions(path: &Path, scene: Option<&str>, yaw: bool) -> Result<Vec<f32>, DataError> {
    let bad = |reason: String| DataError::Bad { path: path.to_owned(), reason };
    let scene = scene
        .ok_or_else(|| bad("no sim scene in the metadata: scene_state needs episodes of the simulated rig".into()))?;
    let v: serde_json::Value = serde_json::from_str(scene).map_err(|e| bad(format!("the sim scene: {e}")))?;
    let xyz = |k: &str| -> Result<Vec<f32>, DataError> {
        v.get(k)
            .and_then(serde_json::Value::as_array)
            .and_then(|a| a.iter().map(|x| x.as_f64().map(|x| x as f32)).collect::<Option<Vec<f32>>>())
            .filter(|a| a.len() == 3)
            .ok_or_else(|| bad(format!("the sim scene has no `{k}` [x, y, z]")))
    };
    let (o, r) = (xyz("object_position")?, xyz("receptacle_position")?);
    let mut out = vec![o[0], o[1], o[2], r[0], r[1], r[2]];
    if yaw {
        let deg = v
            .get("object_yaw_deg")
            .and_then(serde_json::Value::as_f64)
            .ok_or_else(|| bad("the sim scene has no `object_yaw_deg`".into()))?;
        let a = 4.0 * deg.to_radians();
        out.extend([a.cos() as f32, a.sin() as f32]);
    }
    Ok(out)
}

/// A decoded RGB frame resized (antialiased bilinear, torchvision's `Resize`) to size x size:
/// (3, size, size) u8.
pub fn resize_rgb(rgb: &labrig_episode::jpeg::Rgb, size: i64) -> Tensor {
    let img = Tensor::from_slice(&rgb.pixels).view([rgb.height as i64, rgb.width as i64, 3]).permute([2, 0, 1]);
    if rgb.height as i64 == size && rgb.width as i64 == size {
        return img.contiguous();
    }
    img.to_kind(Kind::Float)
        .unsqueeze(0)
        .internal_upsample_bilinear2d_aa([size, size], false, None, None)
        .squeeze_dim(0)
        .round()
        .clamp(0.0, 255.0)
        .to_kind(Kind::Uint8)
}

fn decode_episode(path: &Path, parts: &[PathBuf], cfg: &DiffusionConfig) -> Result<EpisodeTensors, DataError> {
    let data = read_episode(path)?;
    let meta = data.metadata.as_ref();
    let uuid = meta.map(|m| m.uuid.clone()).unwrap_or_else(|| path.display().to_string());
    if data.steps.is_empty() {
        return Err(DataError::Bad {
            path: path.to_owned(),
            reason: "no /rig/step records: nothing to train on".into(),
        });
    }
    let (states, actions) = rows(path, &data.steps, cfg.action_space)?;
    let scene = if cfg.scene_state {
        Some(scene_positions(path, meta.and_then(|m| m.sim_scene.as_deref()), cfg.scene_yaw)?)
    } else {
        None
    };
    let states: Vec<Vec<f32>> = states
        .iter()
        .zip(&data.steps)
        .map(|(s, step)| state_row(s, &step.robot_state, cfg, scene.as_deref()))
        .collect();
    let recorded = recorded_frames(parts, &cfg.cameras)?;
    let mut per_camera = Vec::with_capacity(cfg.cameras.len());
    for (camera, frames) in cfg.cameras.iter().zip(&recorded) {
        if frames.is_empty() {
            let mut has: Vec<String> =
                data.steps.iter().flat_map(|s| s.cameras.iter().map(|c| c.camera_id.clone())).collect();
            has.sort();
            has.dedup();
            return Err(DataError::MissingCamera {
                path: path.to_owned(),
                camera: camera.clone(),
                wanted: cfg.cameras.clone(),
                has,
            });
        }
        // The step's own frame; else the last one at or before the step's time; else the first.
        let mut decoded: BTreeMap<i64, Tensor> = BTreeMap::new();
        let mut last: Option<i64> = None;
        let mut images = Vec::with_capacity(data.steps.len());
        for s in &data.steps {
            let wanted = s.cameras.iter().find(|c| &c.camera_id == camera).map(|c| c.capture_ns);
            let key = match wanted {
                Some(t) if frames.contains_key(&t) => t,
                Some(t) => frames
                    .range(..=t)
                    .next_back()
                    .map(|(k, _)| *k)
                    .or(last)
                    .unwrap_or(*frames.keys().next().expect("not empty")),
                None => last.unwrap_or(*frames.keys().next().expect("not empty")),
            };
            last = Some(key);
            if let std::collections::btree_map::Entry::Vacant(slot) = decoded.entry(key) {
                let rgb = labrig_episode::jpeg::decode_rgb(&frames[&key]).map_err(|e| DataError::Bad {
                    path: path.to_owned(),
                    reason: format!("camera {camera}, step {}: {e}", s.step_index),
                })?;
                slot.insert(resize_rgb(&rgb, cfg.image_size));
            }
            images.push(decoded[&key].shallow_clone());
        }
        per_camera.push(Tensor::stack(&images, 0));
    }
    let width = states[0].len() as i64;
    Ok(EpisodeTensors {
        path: path.to_owned(),
        uuid,
        success: meta.and_then(|m| m.success),
        state: Tensor::from_slice(&states.concat()).view([states.len() as i64, width]),
        action: Tensor::from_slice(actions.as_flattened()).view([actions.len() as i64, 7]),
        frames: if per_camera.is_empty() {
            Tensor::zeros(
                [data.steps.len() as i64, 0, 3, cfg.image_size, cfg.image_size],
                (Kind::Uint8, tch::Device::Cpu),
            )
        } else {
            Tensor::stack(&per_camera, 1)
        },
        source: data.steps.iter().map(|s| s.action_source).collect(),
    })
}

/// For tests: a demo that misses, then grasps: z (m), the gripper command and its reading per step.
/// Steps 0-1 hover (step 1's action starts down), 2-4 descend, 5-7 closed on nothing (reading 1.0), 8-9 rise shut,
/// 10 opens, 11-13 descend again, 14-16 closed on the cube (0.45), 17 rises.
#[cfg(test)]
pub(crate) fn miss_then_grasp() -> (Tensor, Tensor) {
    let z = [0.2f32, 0.2, 0.15, 0.1, 0.05, 0.05, 0.05, 0.05, 0.1, 0.15, 0.15, 0.12, 0.08, 0.05, 0.05, 0.05, 0.05, 0.1];
    let cmd = [0.0f32, 0., 0., 0., 0., 1., 1., 1., 1., 1., 0., 0., 0., 0., 1., 1., 1., 1.];
    let reading = [0.0f32, 0., 0., 0., 0., 0.5, 0.9, 1.0, 1.0, 1.0, 0.3, 0., 0., 0., 0.3, 0.45, 0.45, 0.45];
    let n = z.len() as i64;
    let state: Vec<f32> = (0..z.len()).flat_map(|t| [t as f32, 0.0, z[t], 1.0, 0.0, 0.0, 0.0, reading[t]]).collect();
    let action: Vec<f32> = cmd.iter().flat_map(|&g| [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, g]).collect();
    (Tensor::from_slice(&state).view([n, 8]), Tensor::from_slice(&action).view([n, 7]))
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    fn robot_state(p: [f64; 6]) -> RobotState {
        RobotState { cartesian_position: p, ..Default::default() }
    }

    /// A top-down grasp whose roll wobbles across pi (euler +pi, then -pi + a little: the same
    /// orientation) gives the same state and action numbers either way, with no history.
    #[test]
    fn top_down_orientations_read_the_same_across_the_half_turn() {
        use std::f64::consts::PI;
        let a = state_of(&robot_state([0.5, 0.0, 0.3, PI - 1e-3, 0.0, 0.1]));
        let b = state_of(&robot_state([0.5, 0.0, 0.3, -PI + 1e-3, 0.0, 0.1]));
        assert!((a[3..].iter().map(|x| x * x).sum::<f32>() - 1.0).abs() < 1e-6 && a[3] > 0.99, "{a:?}");
        let dist: f32 = (3..7).map(|k| (a[k] - b[k]).powi(2)).sum::<f32>().sqrt();
        assert!(dist < 0.01, "{a:?} {b:?}");

        let act = |roll: f64| ActionDict { cartesian_position: [0.5, 0.0, 0.3, roll, 0.0, 0.2], ..Default::default() };
        let first = action_of(&act(PI - 1e-3), ActionSpace::EefAxisAngle);
        let second = action_of(&act(-PI + 1e-3), ActionSpace::EefAxisAngle);
        let jump: f32 = (3..6).map(|k| (first[k] - second[k]).powi(2)).sum::<f32>().sqrt();
        assert!(jump < 0.01, "axis-angle jumped {jump}: {first:?} -> {second:?}");
        assert!(first[3] > 3.0 && second[3] > 3.0, "both about +x: {first:?} {second:?}");
        // The rotations are still the recorded ones (an angle past pi included).
        for (v, roll) in [(first, PI - 1e-3), (second, -PI + 1e-3)] {
            let r = UnitQuaternion::from_scaled_axis(Vector3::new(v[3] as f64, v[4] as f64, v[5] as f64));
            assert!(r.angle_to(&rotation(&act(roll).cartesian_position)) < 1e-5, "{v:?}");
        }
        // DROID's velocity action: 6 + gripper.
        let v = ActionDict {
            cartesian_velocity: [0.1, 0.2, 0.3, 0.4, 0.5, 0.6],
            gripper_position: 0.7,
            ..Default::default()
        };
        assert_eq!(action_of(&v, ActionSpace::CartesianVelocity), [0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7]);
    }

    /// A step whose pose or action is NaN is named (episode and step), not trained on.
    #[test]
    fn a_step_with_nan_is_named() {
        let step = |i: u64, x: f64| Step {
            step_index: i,
            robot_state: robot_state([0.5, 0.0, 0.3, 3.0, 0.0, 0.0]),
            action: ActionDict { cartesian_position: [x, 0.0, 0.3, 3.0, 0.0, 0.0], ..Default::default() },
            ..Default::default()
        };
        let path = Path::new("episodes/ep7");
        let (s, a) = rows(path, &[step(0, 0.5), step(1, 0.51)], ActionSpace::EefAxisAngle).unwrap();
        assert_eq!((s.len(), a.len()), (2, 2));
        let e = rows(path, &[step(0, 0.5), step(1, f64::NAN)], ActionSpace::EefAxisAngle).unwrap_err();
        assert!(
            e.to_string().starts_with("episodes/ep7: step 1: action holds a value that is not a finite number"),
            "{e}"
        );
        let mut bad = step(2, 0.5);
        bad.robot_state.cartesian_position[4] = f64::INFINITY;
        let e = rows(path, &[bad], ActionSpace::CartesianVelocity).unwrap_err();
        assert!(e.to_string().contains("step 2: robot_state.cartesian_position"), "{e}");
    }

    /// The miss is found from the recording alone (its descent from the hover, the close, the
    /// first step 5 mm up, the reopen); the grasp on the cube is not a miss; with the miss's
    /// events ignored, the steps before it point at the grasp that held.
    #[test]
    fn a_missed_grasp_is_read_from_the_recording() {
        let (state, action) = super::miss_then_grasp();
        let missed = missed_grasps(&state, &action, GRIPPER_COLUMN);
        assert_eq!(missed, [MissedGrasp { descent: 1, close: 5, lift: 8, reopen: 10 }]);
        assert_eq!(missed[0].mistake(), 1..8);
        // Without the gripper's reading nothing can be told.
        assert!(missed_grasps(&state.narrow(1, 0, 7), &action, GRIPPER_COLUMN).is_empty());
        let x = |w: &Tensor| -> Vec<f32> { Vec::try_from(w.select(1, 0).contiguous()).unwrap() };
        // Plain: steps 0..=4 point at the miss (step 5's TCP, x = 5).
        assert_eq!(x(&waypoints(&state, &action, &[]))[..5], [5.0; 5]);
        // Ignoring the miss's close and reopen: at the grasp that held (step 14).
        let w = x(&waypoints(&state, &action, &[5, 10]));
        assert_eq!(w[..14], [14.0; 14]);
        assert_eq!(w[14..17], [17.0; 3]);
    }

    /// A pick and place of six steps: the gripper closes at step 2 and opens at step 4. Steps
    /// 0..=1 point at the grasp (step 2's TCP), 2..=3 at the release (step 4's), 4..=5 at the
    /// last pose; an episode with no event points at its last pose throughout.
    /// The drawer's shapes, as the sim records them: a miss whose descent overshoots and comes
    /// back up before the close is walked back to the descent's top; a grasp on the 16 mm
    /// handle (0.82) that slides the drawer out level, never rising 5 mm, is not a miss.
    #[test]
    fn a_drawer_miss_with_an_overshoot_is_found_and_a_handle_grasp_is_not() {
        // 0-1 hover, 2-5 down past the goal (0.004), 6-8 back up to it, 9-13 closed on nothing
        // (0.98), 14-15 rise and open; 16-19 down again, 20-25 closed on the handle, pulled level.
        let z = [
            0.12f32, 0.12, 0.08, 0.04, 0.0, -0.003, -0.001, 0.002, 0.004, 0.004, 0.005, 0.005, 0.005, 0.005, 0.02,
            0.06, 0.04, 0.02, 0.005, 0.004, 0.004, 0.005, 0.006, 0.007, 0.007, 0.007,
        ];
        let cmd = [
            0.0f32, 0., 0., 0., 0., 0., 0., 0., 0., 1., 1., 1., 1., 1., 0., 0., 0., 0., 0., 0., 1., 1., 1., 1., 1., 1.,
        ];
        let reading = [
            0.0f32, 0., 0., 0., 0., 0., 0., 0., 0., 0.34, 0.6, 0.85, 0.95, 0.98, 0.6, 0.2, 0., 0., 0., 0., 0.34, 0.6,
            0.8, 0.82, 0.82, 0.82,
        ];
        let n = z.len();
        let state: Vec<f32> = (0..n).flat_map(|t| [0.5, 0.0, z[t], 1.0, 0.0, 0.0, 0.0, reading[t]]).collect();
        let action: Vec<f32> = cmd.iter().flat_map(|&g| [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, g]).collect();
        let (state, action) =
            (Tensor::from_slice(&state).view([n as i64, 8]), Tensor::from_slice(&action).view([n as i64, 7]));
        let missed = missed_grasps(&state, &action, GRIPPER_COLUMN);
        assert_eq!(missed, [MissedGrasp { descent: 1, close: 9, lift: 14, reopen: 14 }]);
    }

    #[test]
    fn waypoints_are_the_tcp_at_the_next_gripper_event() {
        let tcp =
            [[0.0f32, 0.0, 0.5], [0.1, 0.0, 0.4], [0.2, 0.1, 0.1], [0.3, 0.2, 0.3], [0.4, 0.3, 0.2], [0.4, 0.3, 0.4]];
        let grip = [0.0f32, 0.0, 1.0, 1.0, 0.0, 0.0];
        let state: Vec<f32> = tcp.iter().flat_map(|p| [p[0], p[1], p[2], 1.0, 0.0, 0.0, 0.0]).collect();
        let action: Vec<f32> = grip.iter().flat_map(|&g| [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, g]).collect();
        let state = Tensor::from_slice(&state).view([6, 7]);
        let w = waypoints(&state, &Tensor::from_slice(&action).view([6, 7]), &[]);
        let rows: Vec<f32> = Vec::try_from(w.view([-1])).unwrap();
        let want: Vec<f32> = [2, 2, 4, 4, 5, 5].iter().flat_map(|&k| tcp[k]).collect();
        assert_eq!(rows, want);
        let none = waypoints(&state, &Tensor::zeros([6, 7], (Kind::Float, tch::Device::Cpu)), &[]);
        let rows: Vec<f32> = Vec::try_from(none.view([-1])).unwrap();
        assert_eq!(rows, tcp.iter().flat_map(|_| tcp[5]).collect::<Vec<_>>());
        assert_eq!(waypoints(&state.narrow(0, 0, 0), &state.narrow(0, 0, 0), &[]).size(), [0, 3]);
    }

    #[test]
    fn frames_resize_with_antialiasing() {
        let rgb = labrig_episode::jpeg::Rgb {
            width: 4,
            height: 4,
            pixels: (0..16).flat_map(|i| if (i / 4 + i % 4) % 2 == 0 { [255u8; 3] } else { [0u8; 3] }).collect(),
        };
        let small = resize_rgb(&rgb, 2);
        assert_eq!(small.size(), [3, 2, 2]);
        assert_eq!(small.kind(), Kind::Uint8);
        // A checkerboard averages to grey, not to one of its squares.
        let v: Vec<u8> = small.flatten(0, -1).try_into().unwrap();
        assert!(v.iter().all(|&x| (100..=155).contains(&x)), "{v:?}");
        assert_eq!(resize_rgb(&rgb, 4).size(), [3, 4, 4]);
    }

    /// The scene part of the state: object and receptacle positions, and with `scene_yaw` the
    /// cube's yaw as (cos 4 yaw, sin 4 yaw), the same for yaws 90 degrees apart.
    #[test]
    fn scene_state_with_and_without_the_object_yaw() {
        let scene = |yaw: f64| {
            format!(
                r#"{{"object_position": [0.5, 0.1, 0.025], "receptacle_position": [0.4, -0.2, 0.0], "object_yaw_deg": {yaw}}}"#
            )
        };
        let p = Path::new("ep");
        assert_eq!(scene_positions(p, Some(&scene(10.0)), false).unwrap(), vec![0.5, 0.1, 0.025, 0.4, -0.2, 0.0]);
        let a = scene_positions(p, Some(&scene(10.0)), true).unwrap();
        let b = scene_positions(p, Some(&scene(-80.0)), true).unwrap();
        assert_eq!(a.len(), 8);
        assert!((a[6] - 40f32.to_radians().cos()).abs() < 1e-6 && (a[7] - 40f32.to_radians().sin()).abs() < 1e-6);
        assert!(a.iter().zip(&b).all(|(x, y)| (x - y).abs() < 1e-6), "{a:?} vs {b:?}");
        let e = scene_positions(p, Some(r#"{"object_position": [0, 0, 0], "receptacle_position": [0, 0, 0]}"#), true);
        assert!(e.unwrap_err().to_string().contains("no `object_yaw_deg`"));
        let cfg = DiffusionConfig { scene_yaw: true, state_dim: 16, ..DiffusionConfig::small_lowdim() };
        assert_eq!(cfg.data_state_dim(), 16);
        let row = state_row(&[0.0; 7], &RobotState::default(), &cfg, Some(&a));
        assert_eq!(row.len(), 16);
        // Relative: the positions seen from the TCP (here at 0.5, 0.1, 0.2); the yaw unchanged.
        let rel = DiffusionConfig { scene_relative: true, ..cfg };
        let row = state_row(&[0.5, 0.1, 0.2, 1.0, 0.0, 0.0, 0.0], &RobotState::default(), &rel, Some(&a));
        let want = [0.0, 0.0, -0.175, -0.1, -0.3, -0.2];
        assert!(row[8..14].iter().zip(want).all(|(x, w)| (x - w).abs() < 1e-6), "{:?}", &row[8..14]);
        assert_eq!(row[14..], a[6..]);
    }
}
