//! DROID's own MCAP layout (`trajectory.mcap`): JSON messages with `jsonschema` schemas, one
//! timestep per log time, images as Foxglove `CompressedImage` (base64 JPEG) on
//! `/camera/<serial>_left/compressed`.
//!
//! Upstream wrote two generations (shared/FACTS.md):
//! - **wrapped** (DROID's trajectory.h5 -> MCAP converter, its first live writer and the reader
//!   that goes with them): every payload is `{"timestamp": {"sec", "nsec"}, "data": ...}` where
//!   `data` is trajectory.h5's subtree at that step, with DROID's keys, on `/robot_state`
//!   (`observation/robot_state`), `/action` (`action`), `/camera_extrinsics`,
//!   `/camera_intrinsics` and `/camera_type` (`observation/<name>`);
//! - **flat** (the newer live writer and its reader): `/robot_state` carries `joint_positions`,
//!   `cartesian_position`, `gripper_position` ... at the top level, `/action` is
//!   `{"timestamp", "data": [7 numbers]}` (DROID's default cartesian velocity + gripper
//!   velocity), `/vr_controller` the Quest's state; no camera extrinsics, intrinsics or types.
//!
//! Export writes the wrapped variant, the one DROID's converter and reader agree on. The keys
//! trajectory.h5 has beyond those five topics go on topics named the same way
//! (`observation/timestamp/...` on `/timestamp`, `observation/controller_info/...` on
//! `/controller_info`), wrapped alike, so nothing of the raw export is lost. Log times are real
//! nanoseconds (upstream puts DROID's millisecond times in MCAP's nanosecond field, which makes
//! Foxglove play an episode a million times too fast); an import reads either, told apart by
//! the steps' spacing.
//!
//! Import tells the variants apart by what `/robot_state` holds, rebuilds trajectory.h5's
//! content from the messages and goes through the same mapping as `labrig import droid`
//! ([`crate::droid::from_droid`]); the JPEG bytes are kept as they were.

use crate::droid::{self, Episode};
use crate::export::{self, Seen};
use crate::h5doc::{Attr, Column, Data, H5Doc};
use crate::import::{self, FrameSource, ImportOptions};
use crate::{DroidError, bad, io, meta};
use base64::Engine as _;
use labrig_episode::metadata::{EpisodeMetadata, Outcome, episode_dir};
use labrig_msgs::Nanos;
use labrig_msgs::rig::TeleopState;
use labrig_msgs::topics;
use mcap::records::Record;
use serde_json::{Map, Value, json};
use std::collections::BTreeMap;
use std::io::BufWriter;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// DROID's file name for an episode in this layout.
pub const FILE_NAME: &str = "trajectory.mcap";
pub const ROBOT_STATE: &str = "/robot_state";
pub const ACTION: &str = "/action";
pub const VR_CONTROLLER: &str = "/vr_controller";
const IMAGE_SCHEMA: &str = "foxglove.CompressedImage";

/// The schema of every wrapped topic (DROID's converter registers this one text under
/// `droid.<Name>` for each).
const WRAPPED_SCHEMA: &str = r#"{"type":"object","properties":{"timestamp":{"type":"object","properties":{"sec":{"type":"integer"},"nsec":{"type":"integer"}}},"data":{"type":"object","additionalProperties":true}}}"#;

/// Foxglove's CompressedImage as JSON: `data` base64 (Foxglove decodes a JSON bytes field only
/// when the schema says `contentEncoding: base64`).
const IMAGE_SCHEMA_TEXT: &str = r#"{"type":"object","properties":{"timestamp":{"type":"object","properties":{"sec":{"type":"integer"},"nsec":{"type":"integer"}}},"frame_id":{"type":"string"},"data":{"type":"string","contentEncoding":"base64"},"format":{"type":"string"}}}"#;

/// The newer live writer's `/vr_controller` (labrig writes it where the episode recorded the
/// Quest's `/teleop/state`).
const VR_SCHEMA_TEXT: &str = r#"{"type":"object","properties":{"timestamp":{"type":"object","properties":{"sec":{"type":"integer"},"nsec":{"type":"integer"}}},"poses":{"type":"object","description":"hand ('r' or 'l') -> the controller's pose, a row-major 4x4 matrix; labrig's is in the robot frame (after the forward redefinition), DROID's in the headset's"},"buttons":{"type":"object"},"movement_enabled":{"type":"boolean"},"controller_on":{"type":"boolean"},"success":{"type":"boolean"},"failure":{"type":"boolean"}}}"#;

/// Which of upstream's writers a file follows.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Variant {
    Wrapped,
    Flat,
}

impl Variant {
    pub fn describe(self) -> &'static str {
        match self {
            Variant::Wrapped => "wrapped {timestamp, data} (DROID's h5 -> MCAP converter and reader)",
            Variant::Flat => "flat top-level fields (DROID's newer live writer)",
        }
    }
}

// ---------------------------------------------------------------------------------------------
// trajectory.h5's keys <-> topics and JSON.

/// The topic a trajectory.h5 dataset goes on and its path inside `data`:
/// `action/x` -> (`/action`, [x]); `observation/<group>/rest` -> (`/<group>`, rest).
fn topic_of(key: &str) -> (String, Vec<&str>) {
    let parts: Vec<&str> = key.split('/').collect();
    match parts.as_slice() {
        ["observation", group, rest @ ..] if !rest.is_empty() => (format!("/{group}"), rest.to_vec()),
        [first, rest @ ..] => (format!("/{first}"), rest.to_vec()),
        [] => (String::from("/"), Vec::new()),
    }
}

/// The inverse of [`topic_of`].
fn key_of(topic: &str, path: &[String]) -> String {
    let t = topic.trim_start_matches('/');
    let base = if t == "action" { String::from("action") } else { format!("observation/{t}") };
    std::iter::once(base).chain(path.iter().cloned()).collect::<Vec<_>>().join("/")
}

/// `droid.RobotState` for `/robot_state`.
fn schema_name(topic: &str) -> String {
    let camel: String = topic
        .trim_start_matches('/')
        .split('_')
        .map(|w| {
            let mut c = w.chars();
            c.next().map(|f| f.to_uppercase().chain(c).collect::<String>()).unwrap_or_default()
        })
        .collect();
    format!("droid.{camel}")
}

/// What in a DROID-layout MCAP (or a trajectory bound for one) does not fit the layout; the
/// file is named by [`DroidError::Layout`] around it.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DroidMcapError {
    #[error("`{key}` step {step} is {value} (JSON has no such number)")]
    NotJsonNumber { key: String, step: usize, value: f64 },
    #[error("`{key}` is under a dataset, not a group")]
    UnderDataset { key: String },
    #[error("step {step}: `{key}` is {leaf}")]
    NotNumbers { step: usize, key: String, leaf: LeafError },
    #[error("step {step}: `{key}` has shape {shape:?}, earlier steps {earlier:?}")]
    Reshaped { step: usize, key: String, shape: Vec<usize>, earlier: Vec<usize> },
    #[error("step {step}: `{key}` is missing from step {from} on")]
    MissingFrom { step: usize, key: String, from: usize },
    #[error("`{key}` is in {steps} of {n} steps (missing from step {steps} on)")]
    Partial { key: String, steps: usize, n: usize },
    #[error("`{key}` mixes booleans and numbers")]
    Mixed { key: String },
    #[error("step {step}: /vr_controller: {source}")]
    VrController {
        step: usize,
        #[source]
        source: VrControllerError,
    },
    #[error("/robot_state has no `{key}` of {width} numbers per step, which the flat action needs")]
    NoStateForAction { key: String, width: usize },
}

/// What a step's leaf is instead of a number or a regular array of numbers.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum LeafError {
    #[error("a ragged array ({len} against {expected} items)")]
    RaggedLength { len: usize, expected: usize },
    #[error("a ragged array")]
    Ragged,
    #[error("null (NaN or a missing value?)")]
    Null,
    #[error("a string, where DROID has numbers")]
    String,
    #[error("an object inside an array")]
    Object,
}

/// Why a `/vr_controller` message is not the newer DROID writer's controller state.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum VrControllerError {
    #[error("no `poses` object")]
    NoPoses,
    #[error("`poses` has neither `r` nor `l`")]
    NoHand,
    #[error("a pose is not 16 finite numbers (a row-major 4x4 matrix)")]
    BadPose,
}

/// `map_err` naming `path` around a layout error.
fn layout(path: &Path) -> impl FnOnce(DroidMcapError) -> DroidError + '_ {
    move |source| DroidError::Layout { path: path.to_owned(), source }
}

/// Row `i` of a column as JSON: a scalar for a 1-D column, nested arrays for the rest.
fn row_value(col: &Column, i: usize, key: &str) -> Result<Value, DroidMcapError> {
    let tail = &col.shape[1..];
    let width: usize = tail.iter().product();
    let scalar = |k: usize| -> Result<Value, DroidMcapError> {
        Ok(match &col.data {
            Data::F64(v) if !v[k].is_finite() => {
                return Err(DroidMcapError::NotJsonNumber { key: key.to_owned(), step: i, value: v[k] });
            }
            Data::F64(v) => json!(v[k]),
            Data::I64(v) => json!(v[k]),
            Data::Bool(v) => json!(v[k]),
        })
    };
    fn nest(
        tail: &[usize],
        at: usize,
        scalar: &dyn Fn(usize) -> Result<Value, DroidMcapError>,
    ) -> Result<Value, DroidMcapError> {
        match tail.split_first() {
            None => scalar(at),
            Some((&d, rest)) => {
                let w: usize = rest.iter().product();
                (0..d).map(|j| nest(rest, at + j * w, scalar)).collect::<Result<Vec<_>, _>>().map(Value::Array)
            }
        }
    }
    nest(tail, i * width, &scalar)
}

/// Each topic's `data` object at step `i` of `doc`.
fn step_data(doc: &H5Doc, i: usize) -> Result<BTreeMap<String, Map<String, Value>>, DroidMcapError> {
    let mut out: BTreeMap<String, Map<String, Value>> = BTreeMap::new();
    for (key, col) in &doc.datasets {
        let (topic, path) = topic_of(key);
        let mut obj = out.entry(topic).or_default();
        for (k, p) in path.iter().enumerate() {
            if k + 1 == path.len() {
                obj.insert((*p).to_owned(), row_value(col, i, key)?);
            } else {
                let next = obj.entry((*p).to_owned()).or_insert_with(|| Value::Object(Map::new()));
                obj = next.as_object_mut().ok_or_else(|| DroidMcapError::UnderDataset { key: key.clone() })?;
            }
        }
    }
    Ok(out)
}

fn stamp(ns: i64) -> Value {
    json!({"sec": ns.div_euclid(1_000_000_000), "nsec": ns.rem_euclid(1_000_000_000)})
}

/// A leaf of a step's JSON, stacked over the steps into a column.
#[derive(Debug, Default)]
struct Stack {
    tail: Vec<usize>,
    values: Vec<Value>,
    steps: usize,
}

/// The shape of a nested JSON array (and its numbers in row-major order), or why it has none.
fn flatten_leaf(v: &Value, shape: &mut Vec<usize>, depth: usize, out: &mut Vec<Value>) -> Result<(), LeafError> {
    match v {
        Value::Array(items) => {
            if shape.len() == depth {
                shape.push(items.len());
            } else if shape[depth] != items.len() {
                return Err(LeafError::RaggedLength { len: items.len(), expected: shape[depth] });
            }
            items.iter().try_for_each(|x| flatten_leaf(x, shape, depth + 1, out))
        }
        Value::Number(_) | Value::Bool(_) if shape.len() == depth => {
            out.push(v.clone());
            Ok(())
        }
        Value::Number(_) | Value::Bool(_) => Err(LeafError::Ragged),
        Value::Null => Err(LeafError::Null),
        Value::String(_) => Err(LeafError::String),
        Value::Object(_) => Err(LeafError::Object),
    }
}

/// The stacked leaves of every step's topics, by trajectory.h5 key.
#[derive(Debug, Default)]
struct Stacks {
    by_key: BTreeMap<String, Stack>,
}

impl Stacks {
    /// Adds step `step`'s `data` object of `topic` (objects recurse; other values are leaves).
    fn add(&mut self, topic: &str, path: &mut Vec<String>, v: &Value, step: usize) -> Result<(), DroidMcapError> {
        if let Value::Object(m) = v {
            for (k, x) in m {
                path.push(k.clone());
                self.add(topic, path, x, step)?;
                path.pop();
            }
            return Ok(());
        }
        let key = key_of(topic, path);
        let mut shape = Vec::new();
        let mut values = Vec::new();
        flatten_leaf(v, &mut shape, 0, &mut values).map_err(|leaf| DroidMcapError::NotNumbers {
            step,
            key: key.clone(),
            leaf,
        })?;
        let s = self.by_key.entry(key.clone()).or_default();
        if s.steps == 0 {
            s.tail = shape;
        } else if s.tail != shape {
            return Err(DroidMcapError::Reshaped { step, key, shape, earlier: s.tail.clone() });
        }
        if s.steps != step {
            return Err(DroidMcapError::MissingFrom { step, key, from: s.steps });
        }
        s.steps += 1;
        s.values.extend(values);
        Ok(())
    }

    /// The columns, each checked to have all `n` steps; integers stay int64, bools bool.
    fn into_doc(self, n: usize, doc: &mut H5Doc) -> Result<(), DroidMcapError> {
        for (key, s) in self.by_key {
            if s.steps != n {
                return Err(DroidMcapError::Partial { key, steps: s.steps, n });
            }
            let data = if s.values.iter().all(Value::is_boolean) {
                Data::Bool(s.values.iter().map(|v| v.as_bool().unwrap_or_default()).collect())
            } else if s.values.iter().all(|v| v.is_i64()) {
                Data::I64(s.values.iter().map(|v| v.as_i64().unwrap_or_default()).collect())
            } else if s.values.iter().all(Value::is_number) {
                Data::F64(s.values.iter().map(|v| v.as_f64().unwrap_or(f64::NAN)).collect())
            } else {
                return Err(DroidMcapError::Mixed { key });
            };
            let shape = std::iter::once(n).chain(s.tail).collect();
            doc.datasets.insert(key, Column { shape, data });
        }
        Ok(())
    }
}

// ---------------------------------------------------------------------------------------------
// Export.

/// What one export wrote.
#[derive(Debug, Clone, serde::Serialize)]
pub struct ExportedMcap {
    pub source: PathBuf,
    pub file: PathBuf,
    pub uuid: String,
    pub steps: usize,
    pub cameras: Vec<String>,
    /// Step images taken from a neighbouring frame (the camera had none at that tick).
    pub frames_filled: usize,
    pub images: usize,
    /// `/vr_controller` messages (the episode's `/teleop/state`), 0 when it has none.
    pub vr_messages: usize,
    pub bytes: u64,
    pub seconds: f64,
}

struct McapOut {
    writer: mcap::Writer<BufWriter<std::fs::File>>,
    channels: BTreeMap<String, u16>,
    sequence: u32,
    path: PathBuf,
}

impl McapOut {
    fn err(&self) -> impl FnOnce(mcap::McapError) -> DroidError + '_ {
        |source| DroidError::Mcap { path: self.path.clone(), source }
    }

    fn write(&mut self, topic: &str, log_ns: i64, payload: &Value) -> Result<(), DroidError> {
        let channel = match self.channels.get(topic) {
            Some(&c) => c,
            None => {
                let (name, text) = if topic.starts_with("/camera/") {
                    (IMAGE_SCHEMA.to_owned(), IMAGE_SCHEMA_TEXT)
                } else if topic == VR_CONTROLLER {
                    (String::from("droid.VRController"), VR_SCHEMA_TEXT)
                } else {
                    (schema_name(topic), WRAPPED_SCHEMA)
                };
                let schema = self.writer.add_schema(&name, "jsonschema", text.as_bytes()).map_err(self.err())?;
                let c = self.writer.add_channel(schema, topic, "json", &BTreeMap::new()).map_err(self.err())?;
                self.channels.insert(topic.to_owned(), c);
                c
            }
        };
        self.sequence = self.sequence.wrapping_add(1);
        let header = mcap::records::MessageHeader {
            channel_id: channel,
            sequence: self.sequence,
            log_time: log_ns.max(0) as u64,
            publish_time: log_ns.max(0) as u64,
        };
        let bytes = serde_json::to_vec(payload).map_err(|e| bad(&self.path, e.to_string()))?;
        self.writer.write_to_known_channel(&header, &bytes).map_err(self.err())
    }
}

/// The Quest's state as the newer DROID writer's `/vr_controller` payload.
fn vr_payload(s: &TeleopState, t: i64) -> Value {
    let p = &s.controller_pose;
    let q = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
        p.orientation.w,
        p.orientation.x,
        p.orientation.y,
        p.orientation.z,
    ));
    let m = nalgebra::Isometry3::from_parts(nalgebra::Translation3::new(p.position.x, p.position.y, p.position.z), q)
        .to_homogeneous();
    let rows: Vec<f64> = (0..4).flat_map(|r| (0..4).map(move |c| m[(r, c)])).collect();
    // DROID's keys: `r`/`l` for the pose, RG/RJ and A/B (LG/LJ and X/Y on the left),
    // rightTrig/rightJS/rightGrip (left...).
    let (hand, side, ok, fail) = if s.hand == "left" { ("l", "left", "X", "Y") } else { ("r", "right", "A", "B") };
    let (grip, jsp) = (hand.to_uppercase() + "G", hand.to_uppercase() + "J");
    json!({
        "timestamp": stamp(t),
        "poses": { hand: rows },
        "buttons": { ok: s.button_success, fail: s.button_failure, grip: s.movement_enabled, jsp: s.joystick_pressed,
                     format!("{side}Trig"): [s.trigger], format!("{side}JS"): s.joystick, format!("{side}Grip"): [s.grip] },
        "movement_enabled": s.movement_enabled,
        "controller_on": s.controller_connected,
        "success": s.button_success,
        "failure": s.button_failure,
    })
}

/// The newer DROID writer's `/vr_controller` payload as the Quest's state (the inverse of
/// [`vr_payload`]; DROID's own files carry its headset-frame pose, kept as it is).
fn teleop_state(v: &Value) -> Result<TeleopState, VrControllerError> {
    let poses = v.get("poses").and_then(Value::as_object).ok_or(VrControllerError::NoPoses)?;
    let (hand, m) = match (poses.get("r"), poses.get("l")) {
        (Some(m), _) => ("right", m),
        (None, Some(m)) => ("left", m),
        (None, None) => return Err(VrControllerError::NoHand),
    };
    let m: Vec<f64> = m
        .as_array()
        .filter(|a| a.len() == 16)
        .and_then(|a| a.iter().map(Value::as_f64).collect::<Option<Vec<f64>>>())
        .filter(|m| m.iter().all(|x| x.is_finite()))
        .ok_or(VrControllerError::BadPose)?;
    let rot = nalgebra::Matrix3::new(m[0], m[1], m[2], m[4], m[5], m[6], m[8], m[9], m[10]);
    let q = nalgebra::UnitQuaternion::from_matrix(&rot);
    let side = if hand == "left" { "left" } else { "right" };
    let b = v.get("buttons").cloned().unwrap_or(Value::Null);
    let flag = |key: &str| b.get(key).and_then(Value::as_bool).unwrap_or(false);
    let first = |key: &str| b.get(key).and_then(|x| x.get(0)).and_then(Value::as_f64).unwrap_or(0.0);
    let top = |key: &str| v.get(key).and_then(Value::as_bool).unwrap_or(false);
    let js = b
        .get(format!("{side}JS"))
        .and_then(Value::as_array)
        .map(|a| a.iter().filter_map(Value::as_f64).collect::<Vec<_>>());
    let t = v.get("timestamp").cloned().unwrap_or(Value::Null);
    let ns = t.get("sec").and_then(Value::as_i64).unwrap_or(0) * 1_000_000_000
        + t.get("nsec").and_then(Value::as_i64).unwrap_or(0);
    let mut s = TeleopState {
        controller_connected: top("controller_on"),
        hand: hand.into(),
        movement_enabled: top("movement_enabled"),
        grip: first(&format!("{side}Grip")),
        trigger: first(&format!("{side}Trig")),
        joystick: match js.as_deref() {
            Some([x, y]) => [*x, *y],
            _ => [0.0, 0.0],
        },
        joystick_pressed: flag(if hand == "left" { "LJ" } else { "RJ" }),
        button_success: top("success"),
        button_failure: top("failure"),
        ..TeleopState::default()
    };
    s.header.stamp = Nanos(ns).into();
    s.header.frame_id = "vr_head".into();
    s.controller_pose.position = labrig_msgs::geometry_msgs::Point { x: m[3], y: m[7], z: m[11] };
    s.controller_pose.orientation = labrig_msgs::geometry_msgs::Quaternion { w: q.w, x: q.i, y: q.j, z: q.k };
    Ok(s)
}

/// Exports the episode at `source` (its directory or MCAP file) as
/// `<out_root>/{success|failure}/<date>/<time>/trajectory.mcap`.
pub fn export_mcap(source: &Path, out_root: &Path, opts: &export::ExportOptions) -> Result<ExportedMcap, DroidError> {
    let started = Instant::now();
    let (file, mut metadata, steps) = export::read_checked(source)?;
    let buf = std::fs::read(&file).map_err(io(&file))?;
    let mut seen = Seen::new(&metadata);
    let mut cameras = droid::cameras_of(&steps, &metadata, &BTreeMap::new());
    // Every recorded frame by camera and capture time, and the Quest's states.
    let mut frames: Vec<BTreeMap<i64, Vec<u8>>> = vec![BTreeMap::new(); cameras.len()];
    let mut teleop: Vec<(i64, TeleopState)> = Vec::new();
    export::scan(
        &file,
        &buf,
        &cameras,
        &mut seen,
        |c, t, jpeg| {
            frames[c].insert(t, jpeg.to_vec());
            Ok(())
        },
        |topic, data| {
            if topic == topics::TELEOP_STATE.name
                && let Ok(s) = labrig_msgs::decode::<TeleopState>(data)
            {
                teleop.push((Nanos::from(s.header.stamp).0, s));
            }
        },
    )?;
    for (cam, f) in cameras.iter().zip(&frames) {
        if f.is_empty() {
            return Err(bad(&file, format!("camera {} has no recorded frames: no images to export", cam.id)));
        }
    }
    for cam in cameras.iter_mut() {
        cam.k = seen.intrinsics.get(&cam.id).copied();
    }
    metadata.trajectory_length = steps.len() as u64;
    let ep = Episode { metadata, steps, cameras, hand_offset: seen.hand_offset };
    let doc = droid::to_droid(&ep);
    // Steps with no frame of their own (filled with a neighbour's) count as filled too.
    let (refs, own_missing) = droid::frame_refs(&ep.steps, &ep.cameras);

    let outcome = if ep.metadata.success == Some(true) { Outcome::Success } else { Outcome::Failure };
    let uuid = ep.metadata.uuid.clone();
    let same =
        |d: &Path| std::fs::read(d.join(FILE_NAME)).is_ok_and(|b| b.windows(uuid.len()).any(|w| w == uuid.as_bytes()));
    let dir = crate::destination(&episode_dir(out_root, outcome, Nanos(ep.metadata.start_ns)), same, opts.overwrite)?;
    let rel_dir = dir.strip_prefix(out_root).unwrap_or(&dir).to_string_lossy().into_owned();
    let partial = dir.with_extension("partial");
    let _ = std::fs::remove_dir_all(&partial);
    std::fs::create_dir_all(&partial).map_err(io(&partial))?;
    let path = partial.join(FILE_NAME);
    let result = (|| -> Result<ExportedMcap, DroidError> {
        let f = std::fs::File::create(&path).map_err(io(&path))?;
        let wopts = mcap::WriteOptions::new()
            // The newer DROID writer's profile; the converter wrote "ros2" over JSON payloads.
            .profile("droid")
            .library(concat!("labrig-droid ", env!("CARGO_PKG_VERSION")))
            .compression(Some(mcap::Compression::Zstd));
        let writer = wopts
            .create(BufWriter::with_capacity(1 << 20, f))
            .map_err(|source| DroidError::Mcap { path: path.clone(), source })?;
        let mut out = McapOut { writer, channels: BTreeMap::new(), sequence: 0, path: path.clone() };
        let b64 = base64::engine::general_purpose::STANDARD;
        let (mut images, mut filled, mut vr_messages) = (0usize, own_missing.iter().sum::<usize>(), 0usize);
        let mut last_t = i64::MIN;
        let mut next_vr = 0usize;
        for (i, s) in ep.steps.iter().enumerate() {
            // The step's time (the robot state's); strictly rising, so each step is one timestep.
            let t = Nanos::from(s.header.stamp).0.max(last_t + 1);
            last_t = t;
            let data = step_data(&doc, i).map_err(layout(&file))?;
            for (topic, d) in data {
                out.write(&topic, t, &json!({"timestamp": stamp(t), "data": d}))?;
            }
            for (c, cam) in ep.cameras.iter().enumerate() {
                let want = refs[c][i].capture_ns;
                let (got, jpeg) = match frames[c].range(..=want).next_back() {
                    Some((&k, j)) => (k, j),
                    None => frames[c].iter().next().map(|(&k, j)| (k, j)).expect("checked above"),
                };
                if got != want {
                    filled += 1;
                }
                let payload = json!({
                    "timestamp": stamp(got),
                    "frame_id": format!("{}_left", cam.serial),
                    "data": b64.encode(jpeg),
                    "format": "jpeg",
                });
                out.write(&format!("/camera/{}_left/compressed", cam.serial), t, &payload)?;
                images += 1;
            }
            // The Quest's state as of this step (the last one received by its time).
            while next_vr + 1 < teleop.len() && teleop[next_vr + 1].0 <= t {
                next_vr += 1;
            }
            if let Some((ts, st)) = teleop.get(next_vr)
                && *ts <= t
            {
                out.write(VR_CONTROLLER, t, &vr_payload(st, *ts))?;
                vr_messages += 1;
            }
        }
        let err = |source| DroidError::Mcap { path: path.clone(), source };
        // labrig's record (lossless), DROID's metadata JSON, and trajectory.h5's attributes one
        // record each, as DROID's converter writes them.
        out.writer
            .write_metadata(&mcap::records::Metadata {
                name: labrig_episode::episode::DROID_RECORD.into(),
                metadata: ep.metadata.to_record(),
            })
            .map_err(err)?;
        let droid_json = export::droid_json(&ep, &rel_dir);
        let flat: BTreeMap<String, String> = droid_json
            .as_object()
            .map(|m| {
                m.iter()
                    .map(|(k, v)| (k.clone(), v.as_str().map(str::to_owned).unwrap_or_else(|| v.to_string())))
                    .collect()
            })
            .unwrap_or_default();
        out.writer
            .write_metadata(&mcap::records::Metadata { name: "droid_metadata".into(), metadata: flat })
            .map_err(err)?;
        for (k, a) in &doc.attrs {
            let text = match a {
                Attr::Str(s) => s.clone(),
                Attr::Bool(b) => if *b { "True" } else { "False" }.to_owned(),
                Attr::I64(x) => x.to_string(),
                Attr::F64(x) => x.to_string(),
            };
            let metadata = BTreeMap::from([(String::from("value"), text)]);
            out.writer.write_metadata(&mcap::records::Metadata { name: k.clone(), metadata }).map_err(err)?;
        }
        out.writer.finish().map_err(err)?;
        drop(out);
        Ok(ExportedMcap {
            source: file.clone(),
            file: dir.join(FILE_NAME),
            uuid: ep.metadata.uuid.clone(),
            steps: ep.steps.len(),
            cameras: ep.cameras.iter().map(|c| c.id.clone()).collect(),
            frames_filled: filled,
            images,
            vr_messages,
            bytes: std::fs::metadata(&path).map(|m| m.len()).unwrap_or(0),
            seconds: 0.0,
        })
    })();
    let mut e = crate::settle(&partial, &dir, result)?;
    e.seconds = started.elapsed().as_secs_f64();
    Ok(e)
}

// ---------------------------------------------------------------------------------------------
// Reading a DROID-layout MCAP.

/// A DROID-layout MCAP read back: trajectory.h5's content, the images and the metadata.
#[derive(Debug, Clone)]
pub struct DroidMcap {
    pub variant: Variant,
    pub doc: H5Doc,
    /// Each step's log time, in ns.
    pub times_ns: Vec<i64>,
    /// The file's log times were DROID's milliseconds (read as such).
    pub times_in_ms: bool,
    /// Serial -> each step's JPEG (None: the camera had no image at that step).
    pub images: BTreeMap<String, Vec<Option<Vec<u8>>>>,
    /// Metadata records by name.
    pub records: BTreeMap<String, BTreeMap<String, String>>,
    /// Each step's `/vr_controller` (the Quest's state), where the file has it.
    pub vr: Vec<Option<TeleopState>>,
    pub warnings: Vec<String>,
}

/// What the newer writer's top-level `/robot_state` fields are.
const FLAT_STATE_KEYS: [&str; 3] = ["joint_positions", "cartesian_position", "gripper_position"];

fn variant_of(v: &Value) -> Option<Variant> {
    if v.get("data").is_some_and(Value::is_object) {
        Some(Variant::Wrapped)
    } else if FLAT_STATE_KEYS.iter().any(|k| v.get(*k).is_some()) {
        Some(Variant::Flat)
    } else {
        None
    }
}

/// Reads a DROID-layout MCAP file (either variant).
pub fn read_mcap(path: &Path) -> Result<DroidMcap, DroidError> {
    let buf = std::fs::read(path).map_err(io(path))?;
    let FileRecords { channels, records, by_time } = FileRecords::read(path, &buf)?;
    check_droid_layout(path, &channels)?;
    let mut timeline = Timeline::default();
    for (t, msgs) in &by_time {
        let (here, imgs) = messages_at(path, &channels, *t, msgs)?;
        timeline.add(path, *t, here, imgs)?;
    }
    let mut warnings = Vec::new();
    let (steps, images) = timeline.finish(path, &mut warnings)?;
    let n = steps.len();
    let (times_ns, times_in_ms) = log_times_ns(&steps);
    let variant = common_variant(path, &steps)?;
    let contents = StepContents::gather(path, &steps, variant)?;
    let mut doc = H5Doc::default();
    contents.stacks.into_doc(n, &mut doc).map_err(layout(path))?;
    add_derived_actions(path, &mut doc, &contents.flat_actions, n, &mut warnings)?;
    add_log_times(&mut doc, &times_ns, n);
    add_camera_types(&mut doc, &images, n);
    add_attributes(&mut doc, &records);
    Ok(DroidMcap { variant, doc, times_ns, times_in_ms, images, records, vr: contents.vr, warnings })
}

/// One log time's JSON payloads by topic.
type Messages = BTreeMap<String, Value>;

/// One log time's left images: (camera serial, JPEG).
type Jpegs = Vec<(String, Vec<u8>)>;

/// Each camera's JPEG (by serial) per step; None: no image at that step.
type StepImages = BTreeMap<String, Vec<Option<Vec<u8>>>>;

/// What an MCAP file holds, as read record by record.
struct FileRecords {
    /// Channel id -> (topic, message encoding, schema name).
    channels: BTreeMap<u16, (String, String, String)>,
    /// Metadata records by name.
    records: BTreeMap<String, BTreeMap<String, String>>,
    /// Log time -> (channel, payload) in file order.
    by_time: BTreeMap<u64, Vec<(u16, Vec<u8>)>>,
}

impl FileRecords {
    /// Reads every record of `buf` (the file at `path`), refusing what is not a readable MCAP.
    fn read(path: &Path, buf: &[u8]) -> Result<FileRecords, DroidError> {
        if !buf.starts_with(mcap::MAGIC) {
            return Err(bad(path, "not an MCAP file (it does not start with MCAP's magic bytes)"));
        }
        let mut schemas: BTreeMap<u16, String> = BTreeMap::new();
        let mut channels: BTreeMap<u16, (String, String, String)> = BTreeMap::new();
        let mut records: BTreeMap<String, BTreeMap<String, String>> = BTreeMap::new();
        // Log time -> (topic, payload) in file order.
        let mut by_time: BTreeMap<u64, Vec<(u16, Vec<u8>)>> = BTreeMap::new();
        labrig_episode::walk_records(buf, |rec| match rec {
            Record::Schema { header, .. } => {
                schemas.insert(header.id, header.name);
            }
            Record::Channel(c) => {
                let schema = schemas.get(&c.schema_id).cloned().unwrap_or_default();
                channels.insert(c.id, (c.topic, c.message_encoding, schema));
            }
            Record::Metadata(m) => {
                records.insert(m.name, m.metadata);
            }
            Record::Message { header, data } => {
                by_time.entry(header.log_time).or_default().push((header.channel_id, data.into_owned()))
            }
            _ => {}
        })
        .map_err(|e| match e {
            mcap::McapError::UnsupportedCompression(c) => bad(
                path,
                format!(
                    "its chunks are compressed with {c}, which labrig does not read (zstd or none): re-write it with zstd"
                ),
            ),
            e => bad(path, format!("a damaged MCAP file: {e}")),
        })?;
        Ok(FileRecords { channels, records, by_time })
    }
}

/// Refuses a file without DROID's JSON `/robot_state` channel (naming a labrig episode as such).
fn check_droid_layout(path: &Path, channels: &BTreeMap<u16, (String, String, String)>) -> Result<(), DroidError> {
    let topic_names: Vec<&str> = channels.values().map(|(t, ..)| t.as_str()).collect();
    let Some((_, (_, encoding, _))) = channels.iter().find(|(_, (t, ..))| t == ROBOT_STATE) else {
        if topic_names.contains(&topics::RIG_STEP.name) {
            return Err(bad(
                path,
                "a labrig episode (ROS 2 CDR messages), not DROID's MCAP layout: it needs no import; \
                 `labrig export droid-mcap` writes DROID's layout from it",
            ));
        }
        return Err(bad(
            path,
            format!("no /robot_state channel: not DROID's MCAP layout (its topics: {topic_names:?})"),
        ));
    };
    if encoding != "json" {
        return Err(bad(path, format!("/robot_state is encoded as `{encoding}`; DROID's MCAP layout is JSON")));
    }
    Ok(())
}

/// The JSON messages logged at time `t`: the payloads by topic, and the left images (JPEG) by
/// camera serial; messages of other encodings are passed over.
fn messages_at(
    path: &Path,
    channels: &BTreeMap<u16, (String, String, String)>,
    t: u64,
    msgs: &[(u16, Vec<u8>)],
) -> Result<(Messages, Jpegs), DroidError> {
    let mut here: Messages = BTreeMap::new();
    let mut imgs: Jpegs = Vec::new();
    for (channel, data) in msgs {
        let Some((topic, enc, _)) = channels.get(channel) else { continue };
        if enc != "json" {
            continue;
        }
        let v: Value =
            serde_json::from_slice(data).map_err(|e| bad(path, format!("{topic} at log time {t}: not JSON ({e})")))?;
        if let Some(cam) = topic.strip_prefix("/camera/").and_then(|r| r.strip_suffix("/compressed")) {
            imgs.extend(left_image(path, topic, cam, t, &v)?);
            continue;
        }
        if here.insert(topic.clone(), v).is_some() && topic == ROBOT_STATE {
            return Err(bad(path, format!("two /robot_state messages at log time {t}: which is the step?")));
        }
    }
    Ok((here, imgs))
}

/// The JPEG of camera message `v` (on `topic`, camera `cam`) with its serial; None: a stereo
/// right image (labrig's cameras are monocular).
fn left_image(path: &Path, topic: &str, cam: &str, t: u64, v: &Value) -> Result<Option<(String, Vec<u8>)>, DroidError> {
    let Some(serial) = cam.strip_suffix("_left") else {
        if cam.ends_with("_right") {
            return Ok(None); // stereo right images: labrig's cameras are monocular
        }
        return Err(bad(path, format!("{topic}: DROID names images <serial>_left or <serial>_right")));
    };
    let text = v
        .get("data")
        .and_then(Value::as_str)
        .ok_or_else(|| bad(path, format!("{topic} at log time {t}: no base64 `data` string")))?;
    let jpeg = base64::engine::general_purpose::STANDARD
        .decode(text)
        .map_err(|e| bad(path, format!("{topic} at log time {t}: `data` is not base64 ({e})")))?;
    if !(jpeg.starts_with(&[0xFF, 0xD8]) && jpeg.ends_with(&[0xFF, 0xD9])) {
        return Err(bad(path, format!("{topic} at log time {t}: the image is not a whole JPEG")));
    }
    Ok(Some((serial.to_owned(), jpeg)))
}

/// The timesteps and each camera's image per step, as the log times come. One timestep per log
/// time that has a /robot_state; images logged between steps (DROID's converter logs a video's
/// frames at its own times) go to the step before them.
#[derive(Default)]
struct Timeline {
    steps: Vec<(u64, Messages)>,
    images: StepImages,
    /// Images at no step's time (before the first, or a second one for a step).
    orphans: usize,
}

impl Timeline {
    /// Adds the messages of log time `t`: a new step, or images for the step before.
    fn add(&mut self, path: &Path, t: u64, here: Messages, imgs: Jpegs) -> Result<(), DroidError> {
        if here.contains_key(ROBOT_STATE) {
            self.steps.push((t, here));
            let i = self.steps.len() - 1;
            for cams in self.images.values_mut() {
                cams.resize(i + 1, None);
            }
            for (serial, jpeg) in imgs {
                let cams = self.images.entry(serial).or_insert_with(|| vec![None; i + 1]);
                cams[i] = Some(jpeg);
            }
        } else if !here.is_empty() {
            let names: Vec<&String> = here.keys().collect();
            return Err(bad(path, format!("the timestep at log time {t} has no /robot_state (it has {names:?})")));
        } else if let Some(i) = self.steps.len().checked_sub(1) {
            for (serial, jpeg) in imgs {
                let cams = self.images.entry(serial).or_insert_with(|| vec![None; i + 1]);
                cams.resize(i + 1, None);
                if cams[i].is_none() {
                    cams[i] = Some(jpeg);
                } else {
                    self.orphans += 1;
                }
            }
        } else {
            self.orphans += imgs.len();
        }
        Ok(())
    }

    /// The steps and every camera's images over all of them; refused without a step, the
    /// images left out counted in `warnings`.
    fn finish(self, path: &Path, warnings: &mut Vec<String>) -> Result<(Vec<(u64, Messages)>, StepImages), DroidError> {
        let Timeline { steps, mut images, orphans } = self;
        if steps.is_empty() {
            return Err(bad(path, "no /robot_state message: no step to import"));
        }
        let n = steps.len();
        for cams in images.values_mut() {
            cams.resize(n, None);
        }
        if orphans > 0 {
            warnings.push(format!(
                "{orphans} images at no step's time (before the first, or a second one for a step) were left out"
            ));
        }
        Ok((steps, images))
    }
}

/// Each step's log time in ns, and whether the file's log times were DROID's milliseconds.
fn log_times_ns(steps: &[(u64, Messages)]) -> (Vec<i64>, bool) {
    // DROID's writers put time_ms() in the nanosecond field. Told apart by the steps' spacing: a
    // rig steps every 50-100 ms, so a median step under 100,000 units is milliseconds (in ns it
    // would be 0.1 ms); a file of one step by magnitude (below 1e15: 11 days in ns, 31,700
    // years in ms). Sim-time episodes start near 0, so magnitude alone cannot tell.
    let mut gaps: Vec<u64> = steps.windows(2).map(|w| w[1].0 - w[0].0).collect();
    gaps.sort_unstable();
    let times_in_ms = match gaps.get(gaps.len() / 2) {
        Some(&median) => median < 100_000,
        None => steps[0].0 < 1_000_000_000_000_000,
    };
    let scale = if times_in_ms { 1_000_000 } else { 1 };
    let times_ns: Vec<i64> = steps.iter().map(|(t, _)| (*t as i64).saturating_mul(scale)).collect();
    (times_ns, times_in_ms)
}

/// The variant of step 0's `/robot_state`, refused unless every step's is the same.
fn common_variant(path: &Path, steps: &[(u64, Messages)]) -> Result<Variant, DroidError> {
    let variant = variant_of(&steps[0].1[ROBOT_STATE]).ok_or_else(|| {
        let keys: Vec<&String> = steps[0].1[ROBOT_STATE].as_object().map(|m| m.keys().collect()).unwrap_or_default();
        bad(
            path,
            format!(
                "step 0: /robot_state has neither `data` (wrapped) nor {FLAT_STATE_KEYS:?} (flat); its keys: {keys:?}"
            ),
        )
    })?;
    for (i, (_, m)) in steps.iter().enumerate() {
        let v = variant_of(&m[ROBOT_STATE]);
        if v != Some(variant) {
            return Err(bad(
                path,
                format!(
                    "step {i}: /robot_state is {} where step 0's is {}",
                    v.map_or("neither variant", |v| v.describe()),
                    variant.describe()
                ),
            ));
        }
    }
    Ok(variant)
}

/// The steps' messages sorted by kind: trajectory.h5's columns, the flat variant's 7-vector
/// actions, and the `/vr_controller` states.
struct StepContents {
    stacks: Stacks,
    flat_actions: Vec<Vec<f64>>,
    vr: Vec<Option<TeleopState>>,
}

impl StepContents {
    /// Goes through every step's messages in order.
    fn gather(path: &Path, steps: &[(u64, Messages)], variant: Variant) -> Result<StepContents, DroidError> {
        let mut contents =
            StepContents { stacks: Stacks::default(), flat_actions: Vec::new(), vr: vec![None; steps.len()] };
        for (i, (_, m)) in steps.iter().enumerate() {
            for (topic, v) in m {
                contents.add(path, i, topic, v, variant)?;
            }
        }
        Ok(contents)
    }

    /// Adds step `i`'s message `v` on `topic`.
    fn add(&mut self, path: &Path, i: usize, topic: &str, v: &Value, variant: Variant) -> Result<(), DroidError> {
        if topic == VR_CONTROLLER {
            self.vr[i] = Some(
                teleop_state(v)
                    .map_err(|source| DroidMcapError::VrController { step: i, source })
                    .map_err(layout(path))?,
            );
            return Ok(());
        }
        let data = if variant == Variant::Flat && topic == ROBOT_STATE {
            // The top level, without the stamp and the fields the writer left empty.
            let mut obj = v.as_object().cloned().unwrap_or_default();
            obj.remove("timestamp");
            obj.retain(|_, x| !matches!(x, Value::Array(a) if a.is_empty()));
            Value::Object(obj)
        } else {
            match v.get("data") {
                Some(d) => d.clone(),
                None => return Err(bad(path, format!("step {i}: {topic} has no `data`"))),
            }
        };
        if topic == ACTION && data.is_array() {
            let a: Vec<f64> =
                data.as_array().map(|a| a.iter().map(|x| x.as_f64().unwrap_or(f64::NAN)).collect()).unwrap_or_default();
            if a.len() != 7 || a.iter().any(|x| !x.is_finite()) {
                return Err(bad(
                    path,
                    format!(
                        "step {i}: /action is {data}, DROID's is 7 numbers (cartesian velocity + gripper velocity)"
                    ),
                ));
            }
            if self.flat_actions.len() != i {
                return Err(bad(path, format!("step {i}: an /action is missing before it")));
            }
            self.flat_actions.push(a);
            return Ok(());
        }
        if !data.is_object() {
            return Err(bad(path, format!("step {i}: {topic}'s `data` is {data}, not an object of DROID's keys")));
        }
        self.stacks.add(topic, &mut Vec::new(), &data, i).map_err(layout(path))
    }
}

/// DROID's action keys from the flat variant's 7-vector actions, where the file has them
/// (every step or none), with a warning that says where they came from.
fn add_derived_actions(
    path: &Path,
    doc: &mut H5Doc,
    flat_actions: &[Vec<f64>],
    n: usize,
    warnings: &mut Vec<String>,
) -> Result<(), DroidError> {
    if flat_actions.is_empty() {
        return Ok(());
    }
    if flat_actions.len() != n {
        return Err(bad(path, format!("/action is in {} of {n} steps", flat_actions.len())));
    }
    derive_actions(doc, flat_actions, n).map_err(layout(path))?;
    warnings.push(
        "the action is DROID's 7-vector (cartesian velocity + gripper velocity); action/joint_position, \
         cartesian_position, gripper_position and joint_velocity are the next step's observed state"
            .into(),
    );
    Ok(())
}

/// Times the file does not carry as datasets: from the log times.
fn add_log_times(doc: &mut H5Doc, times_ns: &[i64], n: usize) {
    let t = "observation/timestamp";
    if !doc.datasets.contains_key(&format!("{t}/robot_state/robot_timestamp_seconds")) {
        let secs = times_ns.iter().map(|x| x.div_euclid(1_000_000_000)).collect();
        let nanos = times_ns.iter().map(|x| x.rem_euclid(1_000_000_000)).collect();
        doc.datasets.insert(
            format!("{t}/robot_state/robot_timestamp_seconds"),
            Column { shape: vec![n], data: Data::I64(secs) },
        );
        doc.datasets.insert(
            format!("{t}/robot_state/robot_timestamp_nanos"),
            Column { shape: vec![n], data: Data::I64(nanos) },
        );
        doc.datasets.insert(
            format!("{t}/control/step_start"),
            Column { shape: vec![n], data: Data::I64(times_ns.iter().map(|x| x.div_euclid(1_000_000)).collect()) },
        );
    }
}

/// Cameras that only have images (the flat writer has no camera_type): external ones.
fn add_camera_types(doc: &mut H5Doc, images: &StepImages, n: usize) {
    for serial in images.keys() {
        let key = format!("observation/camera_type/{serial}");
        doc.datasets.entry(key).or_insert_with(|| Column { shape: vec![n], data: Data::I64(vec![1; n]) });
    }
}

/// trajectory.h5's attributes, one metadata record each (DROID's converter).
fn add_attributes(doc: &mut H5Doc, records: &BTreeMap<String, BTreeMap<String, String>>) {
    for key in ["user", "building", "scene_id", "current_task", "success", "failure"] {
        if let Some(v) = records.get(key).and_then(|r| r.get("value")) {
            let a = match key {
                "success" | "failure" => Attr::Bool(matches!(v.as_str(), "True" | "true" | "1")),
                _ => Attr::Str(v.clone()),
            };
            doc.attrs.insert(key.to_owned(), a);
        }
    }
}

/// The flat variant's 7-vector as DROID's action keys; the position targets DROID's raw files
/// also carry are the next step's observed state (the last step: its own).
fn derive_actions(doc: &mut H5Doc, a: &[Vec<f64>], n: usize) -> Result<(), DroidMcapError> {
    let get = |key: &str, w: usize| -> Result<Vec<f64>, DroidMcapError> {
        match doc.datasets.get(&format!("observation/robot_state/{key}")) {
            Some(Column { data: Data::F64(v), .. }) if v.len() == n * w => Ok(v.clone()),
            Some(Column { data: Data::I64(v), .. }) if v.len() == n * w => Ok(v.iter().map(|x| *x as f64).collect()),
            _ => Err(DroidMcapError::NoStateForAction { key: key.to_owned(), width: w }),
        }
    };
    let (q, cart, g) = (get("joint_positions", 7)?, get("cartesian_position", 6)?, get("gripper_position", 1)?);
    let dq = get("joint_velocities", 7).unwrap_or_else(|_| vec![0.0; n * 7]);
    let next =
        |v: &[f64], w: usize| -> Vec<f64> { (0..n).flat_map(|i| v[(i + 1).min(n - 1) * w..][..w].to_vec()).collect() };
    let mut put = |key: &str, w: usize, v: Vec<f64>| {
        doc.datasets.insert(format!("action/{key}"), Column::f64_rows(n, w, v));
    };
    put("cartesian_velocity", 6, a.iter().flat_map(|x| x[..6].to_vec()).collect());
    put("gripper_velocity", 0, a.iter().map(|x| x[6]).collect());
    put("joint_position", 7, next(&q, 7));
    put("cartesian_position", 6, next(&cart, 6));
    put("gripper_position", 0, next(&g, 1));
    put("joint_velocity", 7, next(&dq, 7));
    Ok(())
}

// ---------------------------------------------------------------------------------------------
// Import.

/// What one import wrote.
#[derive(Debug, Clone, serde::Serialize)]
pub struct ImportedMcap {
    #[serde(flatten)]
    pub imported: import::Imported,
    pub variant: Variant,
    pub times_in_ms: bool,
}

/// DROID-layout MCAP files under `root`: every `*.mcap` that is not part of a labrig episode.
pub fn find_droid_mcaps(root: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![root.to_owned()];
    while let Some(d) = stack.pop() {
        let Ok(rd) = std::fs::read_dir(&d) else { continue };
        if d.join(labrig_episode::episode::EPISODE_FILE).is_file() {
            continue;
        }
        for e in rd.flatten() {
            let p = e.path();
            let hidden = p.file_name().and_then(|n| n.to_str()).is_some_and(|n| n.starts_with('.'));
            if hidden {
                continue;
            }
            if p.is_dir() {
                stack.push(p);
            } else if p.extension().is_some_and(|x| x == "mcap") {
                out.push(p);
            }
        }
    }
    out.sort();
    out
}

/// The JPEGs of a DROID MCAP, for the episode writer (passed through as they are).
struct JpegFrames {
    /// Per camera (the writer's order): each step's JPEG.
    per_camera: Vec<Vec<Option<Vec<u8>>>>,
    sizes: Vec<Option<(u32, u32)>>,
}

impl FrameSource for JpegFrames {
    fn size(&self, camera: usize) -> Option<(u32, u32)> {
        self.sizes[camera]
    }

    fn frame(&mut self, camera: usize, step: usize, wanted: bool) -> Result<Option<Vec<u8>>, DroidError> {
        Ok(if wanted { self.per_camera[camera].get_mut(step).and_then(Option::take) } else { None })
    }

    fn finish(&mut self, _warnings: &mut Vec<String>) -> Result<(), DroidError> {
        Ok(())
    }
}

/// The episode's metadata: labrig's own record, else DROID's metadata JSON (`droid_metadata`),
/// else made from trajectory.h5's attributes (the uuid from the user and the start time, said
/// in a warning); the attributes win for who, where and what, as in `labrig import droid`.
pub fn episode_metadata(read: &mut DroidMcap, source: &Path) -> Result<meta::Parsed, DroidError> {
    let mut parsed = if let Some(r) = read.records.get(labrig_episode::episode::DROID_RECORD) {
        let m = EpisodeMetadata::from_record(r).map_err(|e| bad(source, format!("its droid_episode record: {e}")))?;
        let serial_to_id = m.camera_serials.iter().map(|(id, s)| (s.clone(), id.clone())).collect();
        meta::Parsed { action_source: 0, has_start: true, serial_to_id, meta: m }
    } else if let Some(r) = read.records.get("droid_metadata") {
        let v: Map<String, Value> = r
            .iter()
            .map(|(k, s)| (k.clone(), serde_json::from_str(s).unwrap_or_else(|_| Value::String(s.clone()))))
            .collect();
        meta::parse(&Value::Object(v)).map_err(|e| bad(source, format!("its droid_metadata record: {e}")))?
    } else {
        let start = Nanos(read.times_ns[0]);
        let user = droid::attr_text(&read.doc, "user").unwrap_or_else(|| "unknown".into());
        let rig = labrig_episode::RigIdentity { lab: "unknown".into(), user, ..labrig_episode::RigIdentity::default() };
        let m = EpisodeMetadata::new(&rig, "", "", start);
        read.warnings.push("no droid_metadata record: the uuid is made from the user and the start time".into());
        meta::Parsed { action_source: 0, has_start: true, serial_to_id: BTreeMap::new(), meta: m }
    };
    import::apply_attrs(&read.doc, &mut parsed.meta);
    match (read.doc.attrs.get("success"), read.doc.attrs.get("failure")) {
        (Some(Attr::Bool(true)), _) => parsed.meta.success = Some(true),
        (_, Some(Attr::Bool(true))) => parsed.meta.success = Some(false),
        _ => {}
    }
    Ok(parsed)
}

/// Imports a DROID-layout MCAP file under `out_root` (the recorder's layout).
pub fn import_mcap(source: &Path, out_root: &Path, opts: &ImportOptions) -> Result<ImportedMcap, DroidError> {
    let started = Instant::now();
    let mut read = read_mcap(source)?;
    let parsed = episode_metadata(&mut read, source)?;
    let mut meta = parsed.meta;
    let traj =
        droid::from_droid(&read.doc, &meta.uuid, &parsed.serial_to_id).map_err(|e| bad(source, e.to_string()))?;
    import::merge_trajectory(&mut meta, &traj, parsed.has_start);
    let mut steps = traj.steps;
    if !read.doc.datasets.contains_key(droid::ACTION_SOURCE_KEY) {
        for s in &mut steps {
            s.action_source = parsed.action_source;
        }
    }
    let mut per_camera = Vec::new();
    let mut sizes = Vec::new();
    for cam in &traj.cameras {
        let imgs = read.images.remove(&cam.serial).unwrap_or_default();
        let size = match imgs.iter().flatten().next() {
            Some(j) => {
                let rgb = labrig_episode::jpeg::decode_rgb(j)
                    .map_err(|e| bad(source, format!("camera {} ({}): its first image: {e}", cam.id, cam.serial)))?;
                Some((rgb.width as u32, rgb.height as u32))
            }
            None => {
                read.warnings.push(format!("camera {} ({}): no images: imported without them", cam.id, cam.serial));
                None
            }
        };
        sizes.push(size);
        per_camera.push(imgs);
    }
    let mut frames = JpegFrames { per_camera, sizes };
    let mut warnings = std::mem::take(&mut read.warnings);
    let (dir, frames_written) = import::write_imported(
        meta.clone(),
        &steps,
        &traj.cameras,
        traj.hand_offset,
        out_root,
        opts,
        &mut frames,
        &read.vr,
        &mut warnings,
        "imported from DROID's MCAP layout",
    )?;
    Ok(ImportedMcap {
        imported: import::Imported {
            source: source.to_owned(),
            dir,
            uuid: meta.uuid,
            steps: steps.len(),
            cameras: traj.cameras.iter().map(|c| c.id.clone()).collect(),
            frames: frames_written,
            warnings,
            seconds: started.elapsed().as_secs_f64(),
        },
        variant: read.variant,
        times_in_ms: read.times_in_ms,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_and_topics_map_both_ways() {
        for key in [
            "observation/robot_state/joint_positions",
            "observation/camera_extrinsics/SN1_left",
            "observation/timestamp/cameras/SN1_estimated_capture",
            "action/joint_position",
        ] {
            let (topic, path) = topic_of(key);
            let path: Vec<String> = path.iter().map(|s| (*s).to_owned()).collect();
            assert_eq!(key_of(&topic, &path), key);
        }
        assert_eq!(topic_of("observation/robot_state/x").0, "/robot_state");
        assert_eq!(schema_name("/camera_extrinsics"), "droid.CameraExtrinsics");
    }

    #[test]
    fn steps_stack_back_into_the_same_columns() {
        let mut doc = H5Doc::default();
        doc.datasets.insert(
            "observation/robot_state/joint_positions".into(),
            Column::f64_rows(3, 2, vec![0.1, 1.0, 2.5, -3.0, 1e-300, 7.0]),
        );
        doc.datasets.insert(
            "observation/camera_intrinsics/S_left".into(),
            Column { shape: vec![3, 2, 2], data: Data::F64((0..12).map(f64::from).collect()) },
        );
        doc.datasets.insert(
            "observation/timestamp/control/step_start".into(),
            Column { shape: vec![3], data: Data::I64(vec![1, 2, 3]) },
        );
        doc.datasets.insert(
            "observation/robot_state/prev_command_successful".into(),
            Column { shape: vec![3], data: Data::Bool(vec![true, false, true]) },
        );
        doc.datasets.insert("action/gripper_position".into(), Column::f64_rows(3, 0, vec![0.0, 0.5, 1.0]));
        let mut stacks = Stacks::default();
        for i in 0..3 {
            for (topic, data) in step_data(&doc, i).unwrap() {
                // Through JSON text, as a file carries it.
                let v: Value = serde_json::from_str(&Value::Object(data).to_string()).unwrap();
                stacks.add(&topic, &mut Vec::new(), &v, i).unwrap();
            }
        }
        let mut back = H5Doc::default();
        stacks.into_doc(3, &mut back).unwrap();
        assert_eq!(back.datasets, doc.datasets);
    }

    #[test]
    fn a_missing_or_reshaped_leaf_is_named() {
        let mut s = Stacks::default();
        s.add("/robot_state", &mut Vec::new(), &json!({"q": [1.0, 2.0]}), 0).unwrap();
        let e = s.add("/robot_state", &mut Vec::new(), &json!({"q": [1.0]}), 1).unwrap_err().to_string();
        assert!(e.contains("step 1: `observation/robot_state/q` has shape [1], earlier steps [2]"), "{e}");
        let e =
            Stacks::default().add("/action", &mut Vec::new(), &json!({"x": [1.0, null]}), 0).unwrap_err().to_string();
        assert!(e.contains("`action/x` is null"), "{e}");
        let mut s = Stacks::default();
        s.add("/action", &mut Vec::new(), &json!({"x": 1.0}), 0).unwrap();
        let e = s.into_doc(2, &mut H5Doc::default()).unwrap_err().to_string();
        assert!(e.contains("`action/x` is in 1 of 2 steps"), "{e}");
    }

    #[test]
    fn variants_are_told_apart_by_content() {
        assert_eq!(variant_of(&json!({"timestamp": {}, "data": {"joint_positions": []}})), Some(Variant::Wrapped));
        assert_eq!(variant_of(&json!({"timestamp": {}, "joint_positions": [0.0]})), Some(Variant::Flat));
        assert_eq!(variant_of(&json!({"timestamp": {}, "pose": [0.0]})), None);
    }
}
