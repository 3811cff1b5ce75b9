//! The checkpoint behind openpi's websocket protocol (`labrig policy run --openpi ADDR`), so
//! openpi's clients (`WebsocketClientPolicy`, DROID's `main.py`, a labrig loop with
//! `source = "remote"`) can query a labrig policy.
//!
//! A request carries DROID's keys: the images (`observation/exterior_image_1_left`,
//! `observation/wrist_image_left`, `observation/exterior_image_2_left`; uint8 H x W x 3) mapped
//! to the checkpoint's cameras, `observation/joint_position` (7) and
//! `observation/gripper_position` (1). The end-effector pose the checkpoint observes is the
//! FR3's forward kinematics of the joints (TCP of the 2F-85, as the rig reports it); the images
//! go through the same JPEG and resize as the loop's requests; the To history is kept per
//! connection (the first request repeated, as LeRobot's queue does). The reply's `actions` is
//! the chunk in the checkpoint's own action space (Tp - To + 1 rows x its width, at the
//! checkpoint's rate), with `policy_timing` and openpi's `server_timing`. A request missing a
//! key the checkpoint needs gets openpi's error frame naming the key.

use crate::serve::{ServeError, Server};
use labrig_arm::kinematics::Fr3Kinematics;
use labrig_episode::jpeg::JpegError;
use labrig_msgs::Nanos;
use labrig_msgs::rig::{PolicyObservation, PolicyRequest, RobotState};
use labrig_msgs::sensor_msgs::CompressedImage;
use labrig_msgs::std_msgs::Header;
use labrig_openpi::codec::{self, Array, CodecError, Value};
use labrig_openpi::droid;
use std::collections::{BTreeMap, VecDeque};
use std::sync::{Arc, Mutex};

/// DROID's observation key for each rig camera.
pub fn droid_key(camera: &str) -> Option<&'static str> {
    match camera {
        "ext1" => Some(droid::EXTERIOR_IMAGE),
        "wrist" => Some(droid::WRIST_IMAGE),
        "ext2" => Some("observation/exterior_image_2_left"),
        _ => None,
    }
}

/// Why a checkpoint cannot be served over openpi, or a request cannot be answered (its text is
/// what the client is sent in openpi's error frame).
#[derive(Debug, thiserror::Error)]
pub enum OpenpiError {
    #[error(
        "{id} observes {inputs:?}, which openpi's DROID observation does not carry: it cannot be served over openpi"
    )]
    SimOnlyInputs { id: String, inputs: Vec<&'static str> },
    #[error("{id} observes camera {camera:?}, which has no DROID observation key (ext1, ext2, wrist do)")]
    NoDroidKey { id: String, camera: String },
    #[error("KeyError: the observation has no {key:?}, which this policy needs")]
    MissingKey { key: String },
    #[error(transparent)]
    Codec(#[from] CodecError),
    #[error("{key}: an image of shape {shape:?} and dtype {}: expected H x W x 3 uint8 RGB", .dtype.str())]
    NotRgb { key: String, shape: Vec<usize>, dtype: codec::Dtype },
    #[error("{key}: an image of {width} x {height}: expected 1..=4096 a side")]
    ImageSize { key: String, width: usize, height: usize },
    #[error("{key}: {source}")]
    Jpeg {
        key: String,
        #[source]
        source: JpegError,
    },
    #[error("{}: {joints:?} (shape {shape:?}): expected 7 finite joint positions", droid::JOINT_POSITION)]
    JointPositions { joints: Vec<f64>, shape: Vec<usize> },
    #[error("{}: {values:?}: expected one finite value", droid::GRIPPER_POSITION)]
    GripperPosition { values: Vec<f64> },
    #[error(transparent)]
    Serve(#[from] ServeError),
}

/// The openpi face of a loaded checkpoint.
pub struct OpenpiPolicy {
    server: Arc<Mutex<Server>>,
    kin: Fr3Kinematics,
    /// (checkpoint camera, the request key it is read from).
    cameras: Vec<(String, String)>,
    n_obs_steps: usize,
    period_ns: i64,
    action_dim: usize,
    jpeg_quality: u8,
}

impl std::fmt::Debug for OpenpiPolicy {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("OpenpiPolicy").field("cameras", &self.cameras).finish_non_exhaustive()
    }
}

/// Per connection: the observations so far (the newest To kept).
#[derive(Debug, Default)]
pub struct Session {
    history: VecDeque<PolicyObservation>,
    steps: u64,
}

impl OpenpiPolicy {
    /// Refuses a checkpoint openpi's DROID observation cannot feed (a camera without a DROID
    /// key, inputs only the simulator has), naming it.
    pub fn new(server: Arc<Mutex<Server>>, kin: Fr3Kinematics, period_s: f64) -> Result<OpenpiPolicy, OpenpiError> {
        let s = server.lock().unwrap_or_else(|p| p.into_inner());
        let c = s.config();
        let id = s.id().to_owned();
        let sim_only = c.sim_only_inputs();
        if !sim_only.is_empty() {
            return Err(OpenpiError::SimOnlyInputs { id, inputs: sim_only });
        }
        let cameras = c
            .cameras
            .iter()
            .map(|cam| {
                droid_key(cam)
                    .map(|k| (cam.clone(), k.to_owned()))
                    .ok_or_else(|| OpenpiError::NoDroidKey { id: id.clone(), camera: cam.clone() })
            })
            .collect::<Result<Vec<_>, _>>()?;
        let (n_obs_steps, action_dim) = (c.n_obs_steps as usize, c.action_dim as usize);
        drop(s);
        Ok(OpenpiPolicy {
            server,
            kin,
            cameras,
            n_obs_steps,
            period_ns: Nanos::from_secs_rounded(period_s).0,
            action_dim,
            jpeg_quality: 90,
        })
    }

    /// The handshake metadata: what `/policy/info` says, the keys it reads, its rate.
    pub fn metadata(&self) -> Value {
        let info = self.server.lock().unwrap_or_else(|p| p.into_inner()).info();
        let mut m = json_to_msgpack(&info);
        let keys: BTreeMap<&str, &str> = self.cameras.iter().map(|(c, k)| (k.as_str(), c.as_str())).collect();
        codec::set(&mut m, "image_keys", json_to_msgpack(&serde_json::json!(keys)));
        codec::set(&mut m, "action_rate_hz", Value::F64(1e9 / self.period_ns as f64));
        m
    }

    /// One openpi observation as the loop's observation of a step.
    fn observation(&self, obs: &Value, step: u64) -> Result<PolicyObservation, OpenpiError> {
        let need = |key: &str| -> Result<&Value, OpenpiError> {
            codec::get(obs, key).ok_or_else(|| OpenpiError::MissingKey { key: key.to_owned() })
        };
        let mut images = Vec::new();
        for (camera, key) in &self.cameras {
            let a = Array::from_value(key, need(key)?)?;
            if a.shape.len() != 3 || a.shape[2] != 3 || a.dtype != codec::Dtype::U8 {
                return Err(OpenpiError::NotRgb { key: key.clone(), shape: a.shape, dtype: a.dtype });
            }
            let (h, w) = (a.shape[0], a.shape[1]);
            if !(1..=4096).contains(&h) || !(1..=4096).contains(&w) {
                return Err(OpenpiError::ImageSize { key: key.clone(), width: w, height: h });
            }
            let data = labrig_episode::jpeg::encode_rgb(&a.data, w as u16, h as u16, self.jpeg_quality)
                .map_err(|source| OpenpiError::Jpeg { key: key.clone(), source })?;
            images.push(CompressedImage {
                header: Header { stamp: Nanos(step as i64 * self.period_ns).into(), frame_id: camera.clone() },
                format: "jpeg".into(),
                data,
            });
        }
        need(droid::JOINT_POSITION)?;
        let (shape, q) = codec::numbers(obs, droid::JOINT_POSITION)?;
        if q.len() != 7 || q.iter().any(|x| !x.is_finite()) {
            return Err(OpenpiError::JointPositions { joints: q, shape });
        }
        need(droid::GRIPPER_POSITION)?;
        let (_, g) = codec::numbers(obs, droid::GRIPPER_POSITION)?;
        let gripper = match g.as_slice() {
            [x] if x.is_finite() => *x,
            _ => return Err(OpenpiError::GripperPosition { values: g }),
        };
        let joints: [f64; 7] = std::array::from_fn(|j| q[j]);
        let tcp = self.kin.tcp_pose(&joints);
        Ok(PolicyObservation {
            header: Header { stamp: Nanos(step as i64 * self.period_ns).into(), frame_id: "base".into() },
            step_index: step,
            robot_state: RobotState {
                joint_positions: joints,
                cartesian_position: labrig_arm::ik::xyz_euler(&tcp),
                gripper_position: gripper,
                ..RobotState::default()
            },
            images,
            ..PolicyObservation::default()
        })
    }
}

impl labrig_openpi::Handler for OpenpiPolicy {
    type Session = Session;
    type Error = OpenpiError;

    fn session(&self) -> Session {
        Session::default()
    }

    fn infer(&self, session: &mut Session, obs: Value) -> Result<Value, OpenpiError> {
        let o = self.observation(&obs, session.steps)?;
        session.steps += 1;
        session.history.push_back(o);
        while session.history.len() > self.n_obs_steps {
            session.history.pop_front();
        }
        let request = PolicyRequest {
            request_id: session.steps,
            observations: session.history.iter().cloned().collect(),
            seed: 0,
            period_ns: self.period_ns,
            ..PolicyRequest::default()
        };
        let chunk = self.server.lock().unwrap_or_else(|p| p.into_inner()).chunk(&request)?;
        let rows = chunk.horizon as usize;
        let values: Vec<f32> = chunk.actions.iter().map(|&a| a as f32).collect();
        Ok(codec::map([
            ("actions", Array::f32(&[rows, self.action_dim], &values).to_value()),
            ("policy_timing", codec::map([("infer_ms", Value::F64(chunk.inference_ms))])),
        ]))
    }
}

/// JSON as msgpack (str keys; numbers as they are).
pub fn json_to_msgpack(v: &serde_json::Value) -> Value {
    match v {
        serde_json::Value::Null => Value::Nil,
        serde_json::Value::Bool(b) => Value::Boolean(*b),
        serde_json::Value::Number(n) => {
            if let Some(i) = n.as_i64() {
                Value::from(i)
            } else if let Some(u) = n.as_u64() {
                Value::from(u)
            } else {
                Value::F64(n.as_f64().unwrap_or(f64::NAN))
            }
        }
        serde_json::Value::String(s) => Value::from(s.as_str()),
        serde_json::Value::Array(a) => Value::Array(a.iter().map(json_to_msgpack).collect()),
        serde_json::Value::Object(o) => codec::map(o.iter().map(|(k, v)| (k.clone(), json_to_msgpack(v)))),
    }
}
