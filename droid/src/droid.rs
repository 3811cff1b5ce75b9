//! The mapping between labrig's recorded steps and DROID's trajectory.h5 (FACTS.md, "DROID's
//! formats"): both directions, no HDF5 or files here.
//!
//! Per step `i` (first axis of every dataset):
//! - `observation/robot_state/*`: the step's RobotState, DROID's key names (float64; the
//!   `prev_command_successful` flag as bool).
//! - `observation/timestamp/robot_state/robot_timestamp_{seconds,nanos}`: the state's stamp;
//!   `observation/timestamp/control/{step_start,policy_start,sleep_start,control_start,step_end}`
//!   and `observation/timestamp/cameras/<serial>_{estimated_capture,frame_received}`: int64
//!   milliseconds since the epoch, as DROID's `time_ms()`.
//! - `observation/camera_type/<serial>`: int64, 0 = hand camera, 1 = varied (external).
//! - `observation/camera_extrinsics/<serial>_left`: [x, y, z, rx, ry, rz] in the robot base
//!   frame (extrinsic xyz euler). The hand camera's moves with the gripper: the step's TCP pose
//!   composed with `<serial>_left_gripper_offset` (its pose in the TCP frame), as DROID does.
//! - `observation/camera_intrinsics/<serial>_left`: 3x3 K.
//! - `observation/controller_info/movement_enabled`: bool.
//! - `observation/controller_info/labrig_action_source`: int64, who acted at the step (labrig's
//!   `Step::action_source`: teleop, policy, scripted, ...; a labrig extension DROID's readers
//!   skip). An import without it reads every step as teleop, as DROID's data is.
//! - `action/*`: DROID's eight action keys (float64).
//!
//! labrig's cameras are monocular, so only `_left` keys exist (the one image is the "left").
//! Root attributes: `user`, `building`, `scene_id`, `current_task` (strings), `success`,
//! `failure` (bool).

use crate::h5doc::{Attr, Column, Data, H5Doc};
use labrig_arm::ik::{pose_from_xyz_euler, xyz_euler};
use labrig_episode::metadata::EpisodeMetadata;
use labrig_msgs::Invalid;
use labrig_msgs::builtin_interfaces::Time;
use labrig_msgs::rig::{ActionDict, CameraFrameRef, ControlTiming, RobotState, Step};
use labrig_msgs::std_msgs::Header;
use std::collections::BTreeMap;

/// The camera DROID calls the hand camera (camera_type 0).
pub const HAND_CAMERA: &str = "wrist";

const NS_PER_MS: i64 = 1_000_000;

/// Where an export keeps each step's `action_source` (not a DROID key).
pub const ACTION_SOURCE_KEY: &str = "observation/controller_info/labrig_action_source";

/// DROID's control timestamp keys, in ControlTiming's order.
pub const CONTROL_KEYS: [&str; 5] = ["step_start", "policy_start", "sleep_start", "control_start", "step_end"];

/// One camera of an exported episode.
#[derive(Debug, Clone, PartialEq)]
pub struct Camera {
    /// labrig's camera id (`wrist`, `ext1`, ...).
    pub id: String,
    /// DROID names files and keys by serial.
    pub serial: String,
    /// Intrinsics (row-major K), where the recording had a camera_info.
    pub k: Option<[f64; 9]>,
}

/// What trajectory.h5 is made from: the episode's steps, metadata and cameras.
#[derive(Debug, Clone)]
pub struct Episode {
    pub metadata: EpisodeMetadata,
    pub steps: Vec<Step>,
    pub cameras: Vec<Camera>,
    /// The hand camera's pose in the TCP frame (xyz + euler), where known.
    pub hand_offset: Option<[f64; 6]>,
}

/// Each camera's frame for each step: the one the step used; a step that had none for a
/// camera (missing at its tick) gets the camera's previous step's frame (or the next one's).
/// Returns `refs[camera][step]` and, per camera, how many were filled in.
pub fn frame_refs(steps: &[Step], cameras: &[Camera]) -> (Vec<Vec<CameraFrameRef>>, Vec<usize>) {
    let mut filled = vec![0; cameras.len()];
    let refs = cameras
        .iter()
        .enumerate()
        .map(|(c, cam)| {
            let own: Vec<Option<&CameraFrameRef>> =
                steps.iter().map(|s| s.cameras.iter().find(|c| c.camera_id == cam.id)).collect();
            let first = own.iter().flatten().next().copied().cloned().unwrap_or_default();
            let mut last = first;
            own.iter()
                .map(|r| match r {
                    Some(r) => {
                        last = (*r).clone();
                        last.clone()
                    }
                    None => {
                        filled[c] += 1;
                        last.clone()
                    }
                })
                .collect()
        })
        .collect();
    (refs, filled)
}

/// The cameras of `steps` (every camera id any step refers to, in the rig's order), with
/// their serials from the metadata (the id where the rig config named none).
pub fn cameras_of(steps: &[Step], meta: &EpisodeMetadata, intrinsics: &BTreeMap<String, [f64; 9]>) -> Vec<Camera> {
    let mut ids: Vec<String> = Vec::new();
    for s in steps {
        for c in &s.cameras {
            if !ids.contains(&c.camera_id) {
                ids.push(c.camera_id.clone());
            }
        }
    }
    let rank = |id: &str| labrig_msgs::rig::RIG_CAMERAS.iter().position(|c| *c == id).unwrap_or(usize::MAX);
    ids.sort_by(|a, b| rank(a).cmp(&rank(b)).then(a.cmp(b)));
    ids.into_iter()
        .map(|id| Camera {
            serial: meta.camera_serials.get(&id).cloned().unwrap_or_else(|| id.clone()),
            k: intrinsics.get(&id).copied(),
            id,
        })
        .collect()
}

fn ms(ns: i64) -> i64 {
    ns.div_euclid(NS_PER_MS)
}

struct Cols<'a> {
    doc: &'a mut H5Doc,
    n: usize,
}

impl Cols<'_> {
    fn f64(&mut self, key: &str, width: usize, values: impl Iterator<Item = f64>) {
        let v: Vec<f64> = values.collect();
        self.doc.datasets.insert(key.to_owned(), Column::f64_rows(self.n, width, v));
    }
    fn rows<const W: usize>(&mut self, key: &str, rows: impl Iterator<Item = [f64; W]>) {
        self.f64(key, W, rows.flatten());
    }
    fn i64(&mut self, key: &str, values: impl Iterator<Item = i64>) {
        let shape = vec![self.n];
        self.doc.datasets.insert(key.to_owned(), Column { shape, data: Data::I64(values.collect()) });
    }
    fn bool(&mut self, key: &str, values: impl Iterator<Item = bool>) {
        let shape = vec![self.n];
        self.doc.datasets.insert(key.to_owned(), Column { shape, data: Data::Bool(values.collect()) });
    }
}

/// trajectory.h5's content for `ep`.
pub fn to_droid(ep: &Episode) -> H5Doc {
    let mut doc = H5Doc::default();
    let n = ep.steps.len();
    let steps = &ep.steps;
    let mut c = Cols { doc: &mut doc, n };
    let rs = |f: fn(&RobotState) -> [f64; 7]| steps.iter().map(move |s| f(&s.robot_state));
    let o = "observation/robot_state";
    c.rows(&format!("{o}/cartesian_position"), steps.iter().map(|s| s.robot_state.cartesian_position));
    c.f64(&format!("{o}/gripper_position"), 0, steps.iter().map(|s| s.robot_state.gripper_position));
    c.rows(&format!("{o}/joint_positions"), rs(|r| r.joint_positions));
    c.rows(&format!("{o}/joint_velocities"), rs(|r| r.joint_velocities));
    c.rows(&format!("{o}/joint_torques_computed"), rs(|r| r.joint_torques_computed));
    c.rows(&format!("{o}/prev_joint_torques_computed"), rs(|r| r.prev_joint_torques_computed));
    c.rows(&format!("{o}/prev_joint_torques_computed_safened"), rs(|r| r.prev_joint_torques_computed_safened));
    c.rows(&format!("{o}/motor_torques_measured"), rs(|r| r.motor_torques_measured));
    c.f64(
        &format!("{o}/prev_controller_latency_ms"),
        0,
        steps.iter().map(|s| s.robot_state.prev_controller_latency_ms),
    );
    c.bool(&format!("{o}/prev_command_successful"), steps.iter().map(|s| s.robot_state.prev_command_successful));

    let t = "observation/timestamp";
    c.i64(
        &format!("{t}/robot_state/robot_timestamp_seconds"),
        steps.iter().map(|s| s.robot_state.header.stamp.sec as i64),
    );
    c.i64(
        &format!("{t}/robot_state/robot_timestamp_nanos"),
        steps.iter().map(|s| s.robot_state.header.stamp.nanosec as i64),
    );
    for (i, key) in CONTROL_KEYS.iter().enumerate() {
        c.i64(&format!("{t}/control/{key}"), steps.iter().map(|s| ms(timing(&s.timing)[i])));
    }
    let (refs, _) = frame_refs(steps, &ep.cameras);
    for (cam, refs) in ep.cameras.iter().zip(&refs) {
        let serial = &cam.serial;
        c.i64(&format!("{t}/cameras/{serial}_estimated_capture"), refs.iter().map(|r| ms(r.capture_ns)));
        c.i64(&format!("{t}/cameras/{serial}_frame_received"), refs.iter().map(|r| ms(r.arrival_ns)));
        let hand = cam.id == HAND_CAMERA;
        c.i64(&format!("observation/camera_type/{serial}"), std::iter::repeat_n(if hand { 0 } else { 1 }, n));
        let ext = format!("observation/camera_extrinsics/{serial}_left");
        if hand {
            if let Some(off) = ep.hand_offset {
                let offset = pose_from_xyz_euler(&off);
                c.rows(
                    &ext,
                    steps.iter().map(|s| xyz_euler(&(pose_from_xyz_euler(&s.robot_state.cartesian_position) * offset))),
                );
                c.rows(&format!("{ext}_gripper_offset"), std::iter::repeat_n(off, n));
            }
        } else if let Some(e) = ep.metadata.extrinsics.get(&cam.id) {
            c.rows(&ext, std::iter::repeat_n(*e, n));
        }
        if let Some(k) = cam.k {
            let key = format!("observation/camera_intrinsics/{serial}_left");
            c.doc.datasets.insert(key, Column { shape: vec![n, 3, 3], data: Data::F64(k.repeat(n)) });
        }
    }
    c.bool("observation/controller_info/movement_enabled", steps.iter().map(|s| s.movement_enabled));
    c.i64(ACTION_SOURCE_KEY, steps.iter().map(|s| i64::from(s.action_source)));

    let a = |f: fn(&ActionDict) -> f64| steps.iter().map(move |s| f(&s.action));
    c.rows("action/cartesian_velocity", steps.iter().map(|s| s.action.cartesian_velocity));
    c.rows("action/cartesian_position", steps.iter().map(|s| s.action.cartesian_position));
    c.rows("action/joint_velocity", steps.iter().map(|s| s.action.joint_velocity));
    c.rows("action/joint_position", steps.iter().map(|s| s.action.joint_position));
    c.f64("action/gripper_velocity", 0, a(|x| x.gripper_velocity));
    c.f64("action/gripper_position", 0, a(|x| x.gripper_position));
    c.rows("action/target_cartesian_position", steps.iter().map(|s| s.action.target_cartesian_position));
    c.f64("action/target_gripper_position", 0, a(|x| x.target_gripper_position));

    let m = &ep.metadata;
    doc.attrs.insert("user".into(), Attr::Str(m.user.clone()));
    doc.attrs.insert("building".into(), Attr::Str(m.building.clone()));
    doc.attrs.insert("scene_id".into(), Attr::Str(m.scene_id.clone()));
    doc.attrs.insert("current_task".into(), Attr::Str(m.task_instruction.clone()));
    doc.attrs.insert("success".into(), Attr::Bool(m.success == Some(true)));
    doc.attrs.insert("failure".into(), Attr::Bool(m.success == Some(false)));
    doc
}

fn timing(t: &ControlTiming) -> [i64; 5] {
    [t.step_start, t.policy_start, t.sleep_start, t.control_start, t.step_end]
}

/// What reading trajectory.h5 back gives besides the metadata: steps, cameras, hand offset.
#[derive(Debug, Clone)]
pub struct Trajectory {
    pub steps: Vec<Step>,
    pub cameras: Vec<Camera>,
    pub hand_offset: Option<[f64; 6]>,
    /// Extrinsics of the external cameras (first step), by camera id.
    pub extrinsics: BTreeMap<String, [f64; 6]>,
    pub success: Option<bool>,
    /// The file carries DROID's success/failure attributes (then `success` is its word).
    pub labelled: bool,
}

/// A column of `doc` as rows of `W` float64, checked against `n` steps.
fn rows<const W: usize>(doc: &H5Doc, key: &str, n: usize) -> Result<Vec<[f64; W]>, Invalid> {
    let col = doc.datasets.get(key).ok_or_else(|| Invalid::new(key, format!("trajectory.h5 has no `{key}`")))?;
    let want: Vec<usize> = if W == 1 { vec![n] } else { vec![n, W] };
    let Data::F64(v) = &col.data else {
        return Err(Invalid::new(key, format!("trajectory.h5 `{key}` is {}, DROID's is float64", col.data.dtype())));
    };
    if col.shape != want && !(W == 1 && col.shape == [n, 1]) {
        return Err(Invalid::new(key, format!("trajectory.h5 `{key}` has shape {:?}, expected {want:?}", col.shape)));
    }
    Ok(v.chunks_exact(W).map(|c| c.try_into().expect("chunk of W")).collect())
}

fn opt_rows<const W: usize>(doc: &H5Doc, key: &str, n: usize) -> Result<Option<Vec<[f64; W]>>, Invalid> {
    if doc.datasets.contains_key(key) { rows::<W>(doc, key, n).map(Some) } else { Ok(None) }
}

fn ints(doc: &H5Doc, key: &str, n: usize) -> Result<Option<Vec<i64>>, Invalid> {
    let Some(col) = doc.datasets.get(key) else { return Ok(None) };
    if col.shape != [n] {
        return Err(Invalid::new(key, format!("trajectory.h5 `{key}` has shape {:?}, expected [{n}]", col.shape)));
    }
    match &col.data {
        Data::I64(v) => Ok(Some(v.clone())),
        Data::F64(v) => Ok(Some(v.iter().map(|x| *x as i64).collect())),
        Data::Bool(_) => Err(Invalid::new(key, format!("trajectory.h5 `{key}` is bool, expected integers"))),
    }
}

fn bools(doc: &H5Doc, key: &str, n: usize) -> Result<Option<Vec<bool>>, Invalid> {
    let Some(col) = doc.datasets.get(key) else { return Ok(None) };
    if col.shape != [n] {
        return Err(Invalid::new(key, format!("trajectory.h5 `{key}` has shape {:?}, expected [{n}]", col.shape)));
    }
    match &col.data {
        Data::Bool(v) => Ok(Some(v.clone())),
        Data::I64(v) => Ok(Some(v.iter().map(|x| *x != 0).collect())),
        Data::F64(v) => Ok(Some(v.iter().map(|x| *x != 0.0).collect())),
    }
}

/// The first step's K of a (n, 3, 3) intrinsics column, where there is one.
fn intrinsics(doc: &H5Doc, key: &str, n: usize) -> Result<Option<[f64; 9]>, Invalid> {
    match doc.datasets.get(key) {
        Some(Column { shape, data: Data::F64(v) }) if shape == &[n, 3, 3] => Ok(v[..9].try_into().ok()),
        Some(c) => Err(Invalid::new(
            key,
            format!("trajectory.h5 `{key}` is {} {:?}, expected float64 [{n}, 3, 3]", c.data.dtype(), c.shape),
        )),
        None => Ok(None),
    }
}

/// A timestamp column (DROID's int64 ms since the epoch) in ns. A time before the epoch or
/// past i64 nanoseconds (year 2262) is refused naming the key and the step: a garbled value
/// would overflow the conversion, the camera skew and the episode's log times.
fn times_ns(doc: &H5Doc, key: &str, n: usize) -> Result<Option<Vec<i64>>, Invalid> {
    let Some(ms) = ints(doc, key, n)? else { return Ok(None) };
    let max = i64::MAX / NS_PER_MS;
    ms.iter()
        .enumerate()
        .map(|(i, &t)| {
            if !(0..=max).contains(&t) {
                return Err(Invalid::new(
                    key,
                    format!("trajectory.h5 `{key}` step {i}: {t} ms is not a time (0..={max})"),
                ));
            }
            Ok(t * NS_PER_MS)
        })
        .collect::<Result<Vec<i64>, Invalid>>()
        .map(Some)
}

fn scalars(doc: &H5Doc, key: &str, n: usize) -> Result<Vec<f64>, Invalid> {
    Ok(rows::<1>(doc, key, n)?.into_iter().map(|[x]| x).collect())
}

/// Reads trajectory.h5's content back into steps. `serial_to_id` names the cameras (DROID
/// files know serials only); a serial it does not know keeps the serial as its id.
pub fn from_droid(
    doc: &H5Doc,
    episode_id: &str,
    serial_to_id: &BTreeMap<String, String>,
) -> Result<Trajectory, Invalid> {
    let n = step_count(doc)?;
    let state = StateColumns::read(doc, n)?;
    let clock = Clock::read(doc, n)?;
    let cams = CameraColumns::read(doc, n, serial_to_id, &clock.control[0])?.in_rig_order();
    let actions = ActionColumns::read(doc, n)?;
    let steps = build_steps(episode_id, n, &state, &clock, &cams, &actions);
    let (success, labelled) = outcome(doc);
    let CameraColumns { cameras, hand_offset, extrinsics, .. } = cams;
    Ok(Trajectory { steps, cameras, hand_offset, extrinsics, success, labelled })
}

/// The number of steps: `action/joint_position`'s rows, refused if there are none.
fn step_count(doc: &H5Doc) -> Result<usize, Invalid> {
    let n = *doc
        .datasets
        .get("action/joint_position")
        .ok_or_else(|| {
            Invalid::new(
                "action/joint_position",
                "trajectory.h5 has no `action/joint_position`: not a DROID trajectory",
            )
        })?
        .shape
        .first()
        .ok_or_else(|| {
            Invalid::new(
                "action/joint_position",
                "trajectory.h5 `action/joint_position` is a scalar, not one row per step",
            )
        })?;
    if n == 0 {
        return Err(Invalid::new("trajectory", "trajectory.h5 holds no steps"));
    }
    Ok(n)
}

/// `observation/robot_state/*` per step; the optional keys default to zeros (latency), true
/// (command successful).
struct StateColumns {
    cart: Vec<[f64; 6]>,
    grip: Vec<f64>,
    q: Vec<[f64; 7]>,
    dq: Vec<[f64; 7]>,
    tau: Vec<[f64; 7]>,
    ptau: Vec<[f64; 7]>,
    ptau_s: Vec<[f64; 7]>,
    motor: Vec<[f64; 7]>,
    latency: Vec<f64>,
    ok: Vec<bool>,
}

impl StateColumns {
    /// Reads the robot state's columns of `n` steps.
    fn read(doc: &H5Doc, n: usize) -> Result<StateColumns, Invalid> {
        let o = "observation/robot_state";
        let zeros7 = || vec![[0.0; 7]; n];
        let cart = rows::<6>(doc, &format!("{o}/cartesian_position"), n)?;
        let grip = scalars(doc, &format!("{o}/gripper_position"), n)?;
        let q = rows::<7>(doc, &format!("{o}/joint_positions"), n)?;
        let dq = opt_rows::<7>(doc, &format!("{o}/joint_velocities"), n)?.unwrap_or_else(zeros7);
        let tau = opt_rows::<7>(doc, &format!("{o}/joint_torques_computed"), n)?.unwrap_or_else(zeros7);
        let ptau = opt_rows::<7>(doc, &format!("{o}/prev_joint_torques_computed"), n)?.unwrap_or_else(zeros7);
        let ptau_s = opt_rows::<7>(doc, &format!("{o}/prev_joint_torques_computed_safened"), n)?.unwrap_or_else(zeros7);
        let motor = opt_rows::<7>(doc, &format!("{o}/motor_torques_measured"), n)?.unwrap_or_else(zeros7);
        let latency = match opt_rows::<1>(doc, &format!("{o}/prev_controller_latency_ms"), n)? {
            Some(v) => v.into_iter().map(|[x]| x).collect(),
            None => vec![0.0; n],
        };
        let ok = bools(doc, &format!("{o}/prev_command_successful"), n)?.unwrap_or_else(|| vec![true; n]);
        Ok(StateColumns { cart, grip, q, dq, tau, ptau, ptau_s, motor, latency, ok })
    }
}

/// The steps' times (ns from here on): the control timestamps in [`CONTROL_KEYS`]' order
/// (zeros where absent) and the robot state's stamp, where the file has it.
struct Clock {
    control: Vec<Vec<i64>>,
    secs: Option<Vec<i64>>,
    nanos: Option<Vec<i64>>,
}

impl Clock {
    /// Reads `observation/timestamp`'s control and robot state times of `n` steps.
    fn read(doc: &H5Doc, n: usize) -> Result<Clock, Invalid> {
        let t = "observation/timestamp";
        let mut control: Vec<Vec<i64>> = Vec::new();
        for key in CONTROL_KEYS {
            control.push(times_ns(doc, &format!("{t}/control/{key}"), n)?.unwrap_or_else(|| vec![0; n]));
        }
        let secs = ints(doc, &format!("{t}/robot_state/robot_timestamp_seconds"), n)?;
        let nanos = ints(doc, &format!("{t}/robot_state/robot_timestamp_nanos"), n)?;
        Ok(Clock { control, secs, nanos })
    }

    /// Step `i`'s stamp: the robot state's, else the step's start.
    fn stamp(&self, i: usize) -> Time {
        match (&self.secs, &self.nanos) {
            (Some(s), Some(ns)) => Time { sec: s[i] as i32, nanosec: ns[i] as u32 },
            _ => Time::from(labrig_msgs::Nanos(self.control[0][i])),
        }
    }
}

/// The cameras: every serial with a camera_type (DROID writes one per camera), with each
/// one's capture and arrival time per step, the external ones' extrinsics and the hand
/// camera's offset.
struct CameraColumns {
    cameras: Vec<Camera>,
    /// Per camera, each step's (capture, arrival) time in ns.
    frames: Vec<(Vec<i64>, Vec<i64>)>,
    extrinsics: BTreeMap<String, [f64; 6]>,
    hand_offset: Option<[f64; 6]>,
}

impl CameraColumns {
    /// Reads the cameras of `n` steps in the file's key order; a camera without times of its
    /// own takes `step_start`'s.
    fn read(
        doc: &H5Doc,
        n: usize,
        serial_to_id: &BTreeMap<String, String>,
        step_start: &[i64],
    ) -> Result<CameraColumns, Invalid> {
        let t = "observation/timestamp";
        let mut cameras = Vec::new();
        let mut extrinsics = BTreeMap::new();
        let mut hand_offset = None;
        let mut frames: Vec<(Vec<i64>, Vec<i64>)> = Vec::new();
        let prefix = "observation/camera_type/";
        for key in doc.datasets.keys().filter(|k| k.starts_with(prefix)) {
            let serial = key[prefix.len()..].to_owned();
            let k = intrinsics(doc, &format!("observation/camera_intrinsics/{serial}_left"), n)?;
            let hand_type = ints(doc, key, n)?.is_some_and(|t| t[0] == 0);
            let id = match serial_to_id.get(&serial) {
                Some(id) => id.clone(),
                None if hand_type => HAND_CAMERA.to_owned(),
                None => serial.clone(),
            };
            let ext = format!("observation/camera_extrinsics/{serial}_left");
            if let Some(off) = opt_rows::<6>(doc, &format!("{ext}_gripper_offset"), n)? {
                hand_offset = Some(off[0]);
            } else if let Some(e) = opt_rows::<6>(doc, &ext, n)? {
                extrinsics.insert(id.clone(), e[0]);
            }
            let capture = times_ns(doc, &format!("{t}/cameras/{serial}_estimated_capture"), n)?;
            let received = times_ns(doc, &format!("{t}/cameras/{serial}_frame_received"), n)?;
            let capture = capture.or_else(|| received.clone()).unwrap_or_else(|| step_start.to_vec());
            let received = received.unwrap_or_else(|| capture.clone());
            frames.push((capture, received));
            cameras.push(Camera { id, serial, k });
        }
        Ok(CameraColumns { cameras, frames, extrinsics, hand_offset })
    }

    /// The cameras in the rig's order, as an export lists them.
    fn in_rig_order(self) -> CameraColumns {
        let CameraColumns { cameras, frames, extrinsics, hand_offset } = self;
        let mut order: Vec<usize> = (0..cameras.len()).collect();
        let rank = |id: &str| labrig_msgs::rig::RIG_CAMERAS.iter().position(|c| *c == id).unwrap_or(usize::MAX);
        order.sort_by(|&a, &b| rank(&cameras[a].id).cmp(&rank(&cameras[b].id)).then(cameras[a].id.cmp(&cameras[b].id)));
        let cameras: Vec<Camera> = order.iter().map(|&i| cameras[i].clone()).collect();
        let frames: Vec<(Vec<i64>, Vec<i64>)> = order.iter().map(|&i| frames[i].clone()).collect();
        CameraColumns { cameras, frames, extrinsics, hand_offset }
    }

    /// Step `i`'s frame of each camera; a camera's sequence (in `sequence`) counts a new
    /// capture time as a new frame.
    fn frame_refs(&self, i: usize, sequence: &mut [u64]) -> Vec<CameraFrameRef> {
        self.cameras
            .iter()
            .zip(&self.frames)
            .enumerate()
            .map(|(c, (cam, (cap, rec)))| {
                if i > 0 && cap[i] != cap[i - 1] {
                    sequence[c] += 1;
                }
                CameraFrameRef {
                    camera_id: cam.id.clone(),
                    sequence: sequence[c],
                    capture_ns: cap[i],
                    arrival_ns: rec[i],
                    ..CameraFrameRef::default()
                }
            })
            .collect()
    }
}

/// Who acted at each step and DROID's `action/*` keys; the targets default to the
/// commanded positions, the source to teleop and movement_enabled to true.
struct ActionColumns {
    enabled: Vec<bool>,
    sources: Vec<u8>,
    acart_v: Vec<[f64; 6]>,
    acart: Vec<[f64; 6]>,
    aq_v: Vec<[f64; 7]>,
    aq: Vec<[f64; 7]>,
    ag_v: Vec<f64>,
    ag: Vec<f64>,
    at_cart: Vec<[f64; 6]>,
    at_g: Vec<f64>,
}

impl ActionColumns {
    /// Reads the controller info and action columns of `n` steps.
    fn read(doc: &H5Doc, n: usize) -> Result<ActionColumns, Invalid> {
        let enabled = bools(doc, "observation/controller_info/movement_enabled", n)?.unwrap_or_else(|| vec![true; n]);
        let sources: Vec<u8> = match ints(doc, ACTION_SOURCE_KEY, n)? {
            Some(v) => v
                .iter()
                .map(|&x| {
                    u8::try_from(x).map_err(|_| {
                        Invalid::new(
                            ACTION_SOURCE_KEY,
                            format!("trajectory.h5 `{ACTION_SOURCE_KEY}` holds {x}, not a source (0..=255)"),
                        )
                    })
                })
                .collect::<Result<_, _>>()?,
            None => vec![Step::SOURCE_TELEOP; n],
        };
        let acart_v = rows::<6>(doc, "action/cartesian_velocity", n)?;
        let acart = rows::<6>(doc, "action/cartesian_position", n)?;
        let aq_v = rows::<7>(doc, "action/joint_velocity", n)?;
        let aq = rows::<7>(doc, "action/joint_position", n)?;
        let ag_v = scalars(doc, "action/gripper_velocity", n)?;
        let ag = scalars(doc, "action/gripper_position", n)?;
        let at_cart = opt_rows::<6>(doc, "action/target_cartesian_position", n)?.unwrap_or_else(|| acart.clone());
        let at_g = match opt_rows::<1>(doc, "action/target_gripper_position", n)? {
            Some(v) => v.into_iter().map(|[x]| x).collect(),
            None => ag.clone(),
        };
        Ok(ActionColumns { enabled, sources, acart_v, acart, aq_v, aq, ag_v, ag, at_cart, at_g })
    }
}

/// The `n` steps from the columns read.
fn build_steps(
    episode_id: &str,
    n: usize,
    state: &StateColumns,
    clock: &Clock,
    cameras: &CameraColumns,
    actions: &ActionColumns,
) -> Vec<Step> {
    let (s, a, control) = (state, actions, &clock.control);
    let mut sequence = vec![0u64; cameras.cameras.len()];
    (0..n)
        .map(|i| {
            let frames = cameras.frame_refs(i, &mut sequence);
            let (lo, hi) =
                frames.iter().fold((i64::MAX, i64::MIN), |(lo, hi), c| (lo.min(c.capture_ns), hi.max(c.capture_ns)));
            let header = Header { stamp: clock.stamp(i), frame_id: "base".into() };
            Step {
                header: header.clone(),
                episode_id: episode_id.to_owned(),
                step_index: i as u64,
                robot_state: RobotState {
                    header,
                    cartesian_position: s.cart[i],
                    gripper_position: s.grip[i],
                    joint_positions: s.q[i],
                    joint_velocities: s.dq[i],
                    joint_torques_computed: s.tau[i],
                    prev_joint_torques_computed: s.ptau[i],
                    prev_joint_torques_computed_safened: s.ptau_s[i],
                    motor_torques_measured: s.motor[i],
                    prev_controller_latency_ms: s.latency[i],
                    prev_command_successful: s.ok[i],
                    mode: RobotState::MODE_MOVING,
                    ..RobotState::default()
                },
                camera_skew_ns: if frames.is_empty() { 0 } else { hi - lo },
                cameras: frames,
                timing: ControlTiming {
                    step_start: control[0][i],
                    policy_start: control[1][i],
                    sleep_start: control[2][i],
                    control_start: control[3][i],
                    step_end: control[4][i],
                    ..ControlTiming::default()
                },
                action: ActionDict {
                    cartesian_velocity: a.acart_v[i],
                    cartesian_position: a.acart[i],
                    joint_velocity: a.aq_v[i],
                    joint_position: a.aq[i],
                    gripper_velocity: a.ag_v[i],
                    gripper_position: a.ag[i],
                    target_cartesian_position: a.at_cart[i],
                    target_gripper_position: a.at_g[i],
                    ..ActionDict::default()
                },
                action_source: a.sources[i],
                movement_enabled: a.enabled[i],
                ..Step::default()
            }
        })
        .collect()
}

/// The episode's success (None: nobody judged it; DROID's own can have success and failure
/// both false) and whether the file carries DROID's success/failure attributes.
fn outcome(doc: &H5Doc) -> (Option<bool>, bool) {
    let labelled = doc.attrs.contains_key("success") || doc.attrs.contains_key("failure");
    let success = match (doc.attrs.get("success"), doc.attrs.get("failure")) {
        (Some(Attr::Bool(true)), _) => Some(true),
        (_, Some(Attr::Bool(true))) => Some(false),
        _ => None,
    };
    (success, labelled)
}

/// A root attribute of trajectory.h5 as text (DROID writes strings; numbers are accepted).
pub fn attr_text(doc: &H5Doc, key: &str) -> Option<String> {
    match doc.attrs.get(key)? {
        Attr::Str(s) => Some(s.clone()),
        Attr::I64(i) => Some(i.to_string()),
        Attr::F64(f) => Some(f.to_string()),
        Attr::Bool(b) => Some(b.to_string()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use labrig_episode::metadata::RigIdentity;

    fn episode(success: Option<bool>) -> Episode {
        let mut metadata =
            EpisodeMetadata::new(&RigIdentity::default(), "s", "t", labrig_msgs::Nanos(1_700_000_000_000_000_000));
        metadata.success = success;
        let steps = (0..3).map(|i| Step { step_index: i, ..Step::default() }).collect();
        Episode { metadata, steps, cameras: Vec::new(), hand_offset: None }
    }

    #[test]
    fn the_outcome_round_trips_unjudged_included() {
        for success in [Some(true), Some(false), None] {
            let t = from_droid(&to_droid(&episode(success)), "x", &BTreeMap::new()).unwrap();
            assert!(t.labelled);
            assert_eq!(t.success, success);
            assert_eq!(t.steps.len(), 3);
        }
    }

    /// Who acted at each step survives an export and an import (a correction rollout's policy
    /// and operator steps); DROID's own data, without the key, reads as teleop; a value that is
    /// no source is named.
    #[test]
    fn each_steps_source_round_trips() {
        let mut ep = episode(Some(true));
        let sources = [Step::SOURCE_POLICY, Step::SOURCE_SCRIPTED, Step::SOURCE_POLICY];
        for (s, src) in ep.steps.iter_mut().zip(sources) {
            s.action_source = src;
        }
        let mut doc = to_droid(&ep);
        let t = from_droid(&doc, "x", &BTreeMap::new()).unwrap();
        assert_eq!(t.steps.iter().map(|s| s.action_source).collect::<Vec<_>>(), sources);
        doc.datasets.get_mut(ACTION_SOURCE_KEY).unwrap().data = Data::I64(vec![1, 300, 1]);
        let e = from_droid(&doc, "x", &BTreeMap::new()).unwrap_err().to_string();
        assert!(e.contains("holds 300"), "{e}");
        doc.datasets.remove(ACTION_SOURCE_KEY);
        let t = from_droid(&doc, "x", &BTreeMap::new()).unwrap();
        assert!(t.steps.iter().all(|s| s.action_source == Step::SOURCE_TELEOP));
    }

    #[test]
    fn a_scalar_or_missing_action_is_named() {
        let mut doc = to_droid(&episode(None));
        doc.datasets.get_mut("action/joint_position").unwrap().shape = vec![];
        assert!(from_droid(&doc, "x", &BTreeMap::new()).unwrap_err().to_string().contains("is a scalar"));
        doc.datasets.remove("action/joint_position");
        assert!(
            from_droid(&doc, "x", &BTreeMap::new()).unwrap_err().to_string().contains("no `action/joint_position`")
        );
    }
}
