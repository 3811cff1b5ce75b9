//! A policy served elsewhere over openpi's websocket protocol (`source = "remote"`, config
//! `[remote]`): pi0-FAST-DROID / pi0.5-DROID behind openpi's `serve_policy.py`, or any
//! server speaking it (labrig's own `labrig policy run --openpi`).
//!
//! The loop's policy source does the scheduling (receding horizon, lead, lockstep waits,
//! skipped rows, the staleness hold, timeouts) exactly as for labrig's own server; this module
//! is the transport. Its thread turns the newest observation into openpi's DROID keys (one
//! exterior camera and the wrist camera resized with padding to 224 x 224, the 7 joint
//! positions, the gripper, the prompt), sends it, and turns the reply's N x 8 chunk (DROID's
//! 15 Hz joint velocities + gripper, by default) into joint-position targets at the loop's own
//! ticks ([`labrig_openpi::droid::resample`]): an action runs at the time it is meant for, not
//! one per tick at the wrong rate. Every target then goes through the arm's safety filter.
//!
//! Faults: no server at start is named; an error frame fails the episode with the traceback's
//! last line (the arm holds); a dropped connection holds the arm while the thread reconnects
//! (a new handshake) within `policy.server_timeout_s`, past which the episode fails as an
//! unanswered request does; a chunk of the wrong shape fails the episode, naming the shape.

use crate::info::PolicyInfo;
use labrig_msgs::Nanos;
use labrig_msgs::rig::{ActionChunk, PolicyRequest};
use labrig_msgs::std_msgs::{Header, StringMsg};
use labrig_openpi::codec::{self, Value};
use labrig_openpi::droid::{self, ActionConvention, ActionMode, DroidActionError};
use labrig_openpi::{Client, ClientError};
use labrig_runtime::ros::RosPublisher;
use serde::{Deserialize, Serialize};
use std::sync::Arc;
use std::sync::mpsc;
use std::time::{Duration, Instant};

/// Why the remote policy could not be reached or a request of it failed (the text is what the
/// episode's failure and `/policy/refused` say).
#[derive(Debug, thiserror::Error)]
pub enum RemoteError {
    #[error("{source} (tried for {timeout_s:.0} s: is the openpi server up?)")]
    Unreachable {
        #[source]
        source: ClientError,
        timeout_s: f64,
    },
    #[error("a request without observations")]
    NoObservation,
    #[error("no frame of camera {camera:?} at step {step}")]
    NoFrame { camera: String, step: u64 },
    #[error("the connection is lost and reconnecting failed: {0}")]
    Reconnect(#[source] ClientError),
    /// The policy raised: its traceback's last line.
    #[error("the server failed: {last_line}")]
    ServerFailed { last_line: String },
    #[error(transparent)]
    Client(#[from] ClientError),
    #[error("the server's chunk: {0}")]
    Chunk(#[source] DroidActionError),
    #[error("the server's chunk of {rows} steps at {rate_hz} Hz spans less than one {tick_ms} ms tick")]
    ChunkTooShort { rows: usize, rate_hz: f64, tick_ms: i64 },
}

/// `[remote]` in the control node's config.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RemoteConfig {
    /// The openpi server: `host:port` or `ws://host:port[/path]`.
    pub url: String,
    /// The rig camera sent as `observation/exterior_image_1_left`.
    pub exterior_camera: String,
    /// The rig camera sent as `observation/wrist_image_left`.
    pub wrist_camera: String,
    /// Images are resized with padding to this square (openpi's DROID examples: 224).
    pub image_size: u32,
    /// The language instruction sent as `prompt`; empty: the episode's instruction.
    pub prompt: String,
    /// What the chunk's 7 arm columns are: `"joint_velocity"` (DROID's) or `"joint_position"`.
    pub actions: String,
    /// The policy's step rate (DROID: 15 Hz).
    pub rate_hz: f64,
    /// `joint_velocity`: rad per step at velocity 1 (DROID: 0.2).
    pub max_joint_delta_rad: f64,
    /// The gripper closes at or above this (DROID: 0.5); negative: the value as sent.
    pub gripper_threshold: f64,
    /// Policy steps executed per chunk before the next is due (DROID's client: 8).
    pub open_loop_horizon: u32,
    /// How long to try to reach the server at start (s).
    pub connect_timeout_s: f64,
}

impl Default for RemoteConfig {
    fn default() -> Self {
        RemoteConfig {
            url: "127.0.0.1:8000".into(),
            exterior_camera: "ext1".into(),
            wrist_camera: "wrist".into(),
            image_size: 224,
            prompt: String::new(),
            actions: "joint_velocity".into(),
            rate_hz: 15.0,
            max_joint_delta_rad: 0.2,
            gripper_threshold: 0.5,
            open_loop_horizon: 8,
            connect_timeout_s: 10.0,
        }
    }
}

impl RemoteConfig {
    pub fn validate(&self) -> Result<(), labrig_msgs::Invalid> {
        use labrig_msgs::Invalid;
        let bad = |k: &str, why: String| Err(Invalid::new(k, format!("remote.{k}: {why}")));
        if self.url.trim().is_empty() {
            return bad("url", "empty: the openpi server's host:port".into());
        }
        ActionMode::parse(&self.actions).map_err(|e| Invalid::new("actions", format!("remote.actions: {e}")))?;
        if !(8..=2048).contains(&self.image_size) {
            return bad("image_size", format!("{} must be in 8..=2048", self.image_size));
        }
        if !(self.rate_hz.is_finite() && self.rate_hz > 0.0 && self.rate_hz <= 1000.0) {
            return bad("rate_hz", format!("{} must be in (0, 1000]", self.rate_hz));
        }
        if !(self.max_joint_delta_rad.is_finite() && self.max_joint_delta_rad > 0.0 && self.max_joint_delta_rad <= 1.0)
        {
            return bad("max_joint_delta_rad", format!("{} must be in (0, 1]", self.max_joint_delta_rad));
        }
        if !(self.gripper_threshold.is_finite() && self.gripper_threshold <= 1.0) {
            return bad(
                "gripper_threshold",
                format!("{} must be <= 1 (negative: no threshold)", self.gripper_threshold),
            );
        }
        if !(1..=1000).contains(&self.open_loop_horizon) {
            return bad("open_loop_horizon", format!("{} must be in 1..=1000", self.open_loop_horizon));
        }
        if !(self.connect_timeout_s.is_finite() && self.connect_timeout_s > 0.0 && self.connect_timeout_s <= 3600.0) {
            return bad("connect_timeout_s", format!("{} must be in (0, 3600]", self.connect_timeout_s));
        }
        if self.exterior_camera == self.wrist_camera {
            return bad("wrist_camera", format!("{:?} is also the exterior camera", self.wrist_camera));
        }
        Ok(())
    }

    pub fn convention(&self) -> ActionConvention {
        ActionConvention {
            mode: ActionMode::parse(&self.actions).expect("validated"),
            rate_hz: self.rate_hz,
            max_joint_delta_rad: self.max_joint_delta_rad,
            gripper_threshold: (self.gripper_threshold >= 0.0).then_some(self.gripper_threshold),
        }
    }

    /// Loop ticks the open-loop horizon spans (8 DROID steps at 15 Hz: 10 ticks of 50 ms).
    pub fn execute_ticks(&self, period_s: f64) -> u32 {
        ((f64::from(self.open_loop_horizon) / self.rate_hz / period_s) + 1e-9).floor().max(1.0) as u32
    }
}

/// The policy id recorded with every step: the server's URL and its metadata.
pub fn policy_id(url: &str, metadata: &Value) -> String {
    format!("openpi {url} {}", codec::to_json_text(metadata))
}

/// Connects (retrying until `connect_timeout_s`) and describes the remote policy to the loop.
pub fn connect(cfg: &RemoteConfig, period_s: f64) -> Result<(Client, PolicyInfo), RemoteError> {
    let until = Instant::now() + Duration::from_secs_f64(cfg.connect_timeout_s);
    let client = loop {
        let left = until.saturating_duration_since(Instant::now()).max(Duration::from_millis(100));
        match Client::connect(&cfg.url, left.min(Duration::from_secs(5))) {
            Ok(c) => break c,
            Err(source) if Instant::now() >= until => {
                return Err(RemoteError::Unreachable { source, timeout_s: cfg.connect_timeout_s });
            }
            Err(_) => std::thread::sleep(Duration::from_millis(200)),
        }
    };
    let ticks = cfg.execute_ticks(period_s) as usize;
    let info = PolicyInfo {
        policy_id: policy_id(client.url(), client.metadata()),
        cameras: vec![cfg.exterior_camera.clone(), cfg.wrist_camera.clone()],
        n_obs_steps: 1,
        horizon: ticks,
        n_action_steps: ticks,
        action_space: "joint_position".into(),
        action_dim: 8,
        sim_only: Vec::new(),
    };
    Ok((client, info))
}

/// A request for the transport thread: the observations (the newest is sent) with raw pixels.
pub struct RemoteJob {
    pub request: PolicyRequest,
    pub images: Vec<Vec<(String, Arc<crate::source::RgbFrame>)>>,
    pub instruction: String,
}

/// What the thread answers: a chunk, or (request id, why the episode fails).
pub type RemoteReply = Result<ActionChunk, (u64, String)>;

impl std::fmt::Debug for RemoteJob {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RemoteJob").field("request_id", &self.request.request_id).finish_non_exhaustive()
    }
}

/// The transport thread: one request at a time (openpi's protocol has no request ids). Each
/// chunk also goes out on `/policy/chunk` (and each failure on `/policy/refused`) for
/// observers (`labrig rollout`, the station), as labrig's own server publishes them.
pub fn run_worker(
    mut client: Option<Client>,
    cfg: RemoteConfig,
    policy_id: String,
    timeout_s: f64,
    jobs: &mpsc::Receiver<RemoteJob>,
    replies: &mpsc::Sender<RemoteReply>,
    observers: Option<(RosPublisher<ActionChunk>, RosPublisher<StringMsg>)>,
) {
    let conv = cfg.convention();
    let timeout = Duration::from_secs_f64(timeout_s);
    while let Ok(mut job) = jobs.recv() {
        // Only the newest waiting request matters.
        while let Ok(newer) = jobs.try_recv() {
            job = newer;
        }
        let id = job.request.request_id;
        let obs = match observation(&cfg, &job) {
            Ok(o) => o,
            Err(e) => {
                let _ = replies.send(Err((id, e.to_string())));
                continue;
            }
        };
        let started = Instant::now();
        let reply = loop {
            if client.as_ref().is_none_or(Client::is_broken) {
                // Reconnect with a new handshake; the loop holds the arm meanwhile.
                match Client::connect(&cfg.url, Duration::from_millis(500)) {
                    Ok(c) => {
                        tracing::info!(url = %cfg.url, "reconnected to the openpi server");
                        client = Some(c);
                    }
                    Err(e) => {
                        if started.elapsed() >= timeout {
                            break Err(RemoteError::Reconnect(e));
                        }
                        std::thread::sleep(Duration::from_millis(100));
                        continue;
                    }
                }
            }
            let c = client.as_mut().expect("connected above");
            match c.infer(&obs, timeout.saturating_sub(started.elapsed()).max(Duration::from_millis(50))) {
                Ok(v) => break Ok(v),
                // The policy raised: the episode fails with its last line.
                Err(ClientError::Server { last_line, .. }) => break Err(RemoteError::ServerFailed { last_line }),
                Err(e @ ClientError::Timeout { .. }) => break Err(e.into()),
                Err(e) if e.connection_lost() && started.elapsed() < timeout => {
                    tracing::warn!("openpi request {id}: {e}; reconnecting");
                }
                Err(e) => break Err(e.into()),
            }
        };
        let round_trip_ms = started.elapsed().as_secs_f64() * 1e3;
        let answer = reply.and_then(|v| chunk(&v, &job, &conv, &policy_id, round_trip_ms));
        if let Some((chunks, refused)) = &observers {
            let sent = match &answer {
                Ok(c) => chunks.publish(c.clone()).err(),
                Err(e) => {
                    let data = serde_json::json!({ "request_id": id, "policy_id": policy_id, "error": e.to_string() });
                    refused.publish(StringMsg { data: data.to_string() }).err()
                }
            };
            if let Some(e) = sent {
                tracing::warn!("publishing the remote chunk for observers: {e}");
            }
        }
        if replies.send(answer.map_err(|e| (id, e.to_string()))).is_err() {
            return;
        }
    }
}

/// openpi's DROID observation of the request's newest step.
fn observation(cfg: &RemoteConfig, job: &RemoteJob) -> Result<Value, RemoteError> {
    let (obs, images) = job.request.observations.last().zip(job.images.last()).ok_or(RemoteError::NoObservation)?;
    let frame = |camera: &str| -> Result<Vec<u8>, RemoteError> {
        let (_, f) = images
            .iter()
            .find(|(c, _)| c == camera)
            .ok_or_else(|| RemoteError::NoFrame { camera: camera.to_owned(), step: obs.step_index })?;
        Ok(droid::resize_with_pad(&f.pixels, f.width, f.height, cfg.image_size, cfg.image_size))
    };
    let (ext, wrist) = (frame(&cfg.exterior_camera)?, frame(&cfg.wrist_camera)?);
    let prompt = if cfg.prompt.is_empty() { job.instruction.as_str() } else { cfg.prompt.as_str() };
    let s = cfg.image_size;
    Ok(droid::Observation {
        exterior: (&ext, s, s),
        wrist: (&wrist, s, s),
        joint_position: obs.robot_state.joint_positions,
        gripper_position: obs.robot_state.gripper_position,
        prompt,
    }
    .to_value())
}

/// The reply's chunk as joint targets at the loop's ticks from the observation's.
fn chunk(
    reply: &Value,
    job: &RemoteJob,
    conv: &ActionConvention,
    policy_id: &str,
    round_trip_ms: f64,
) -> Result<ActionChunk, RemoteError> {
    let rows = droid::action_rows(reply, 8).map_err(RemoteError::Chunk)?;
    let rows: Vec<droid::Row> = rows.iter().map(|r| std::array::from_fn(|k| r[k])).collect();
    let obs = job.request.observations.last().expect("checked");
    let period_ns = job.request.period_ns;
    let resampled = droid::resample(&rows, &obs.robot_state.joint_positions, conv, period_ns as f64 * 1e-9);
    if resampled.is_empty() {
        return Err(RemoteError::ChunkTooShort {
            rows: rows.len(),
            rate_hz: conv.rate_hz,
            tick_ms: period_ns / 1_000_000,
        });
    }
    let obs_ns = Nanos::from(obs.header.stamp).0;
    let infer_ms = codec::get(reply, "server_timing")
        .and_then(|t| codec::numbers(t, "infer_ms").ok())
        .and_then(|(_, v)| v.first().copied())
        .unwrap_or(round_trip_ms);
    Ok(ActionChunk {
        header: Header { stamp: job.request.header.stamp, frame_id: String::new() },
        policy_id: policy_id.to_owned(),
        observation_step: obs.step_index,
        first_step: obs.step_index,
        horizon: resampled.len() as u32,
        action_dim: 8,
        actions: resampled.iter().flatten().copied().collect(),
        inference_ms: infer_ms,
        request_id: job.request.request_id,
        times_ns: (0..resampled.len() as i64).map(|m| obs_ns + m * period_ns).collect(),
        ..ActionChunk::default()
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn droids_open_loop_horizon_spans_ten_ticks_at_twenty_hz() {
        let c = RemoteConfig::default();
        assert_eq!(c.execute_ticks(0.05), 10);
        assert_eq!(RemoteConfig { open_loop_horizon: 15, ..c.clone() }.execute_ticks(0.05), 20);
        assert!(c.validate().is_ok());
        let e = RemoteConfig { actions: "eef".into(), ..c.clone() }.validate().unwrap_err();
        assert!(e.to_string().contains("remote.actions"), "{e}");
        let e = RemoteConfig { wrist_camera: "ext1".into(), ..c }.validate().unwrap_err();
        assert!(e.to_string().contains("also the exterior camera"), "{e}");
    }
}
