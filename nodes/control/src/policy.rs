//! The policy server as the loop's action source (`source = "policy"`, `labrig-policy run`).
//!
//! Each recorded tick the loop hands the source its observation ([`TickView`]: the Step's
//! robot state and the pixels of the cameras the policy names). The source keeps the newest
//! `n_obs_steps` of them and, when the next chunk is due, sends them on `/policy/request`
//! (JPEG-encoded on its own thread at the recorder's quality, so the policy sees what it was
//! trained on; the loop's thread only copies pixels). Chunks come back on `/policy/chunk`,
//! each row with the time it is meant for; a tick executes the row meant for it:
//!
//! - A chunk is asked for once `execute_steps` rows of the newest one have run (the
//!   receding horizon), `lead` ticks early so that it arrives in time: on the wall clock
//!   `lead` is the slowest of the last 20 round trips in ticks (rounded up) plus
//!   `request_margin_steps`, so the arm does not run out of rows; in lockstep it is
//!   `lockstep_delay_steps` (0: the loop waits for the chunk, as synchronous inference does;
//!   N: the sim plays an inference latency of N ticks, deterministically).
//! - Rows whose time passed before their chunk arrived are skipped (counted); no row for a
//!   tick (the server is slow, stalled or gone) holds the arm, as any stale source does.
//! - A new chunk replaces the rest of the old one (`blend = "replace"`), or overlapping rows
//!   are averaged with weights `exp(-blend_decay * k)`, `k` how many steps older a chunk's
//!   observation is than the newest's (`"exponential"`; rotations by slerp).
//! - `blend = "wait"` is synchronous execution: a chunk is asked for once `execute_steps` rows
//!   of the last have run, nothing runs meanwhile (the arm holds), and its rows run from its
//!   arrival.
//! - `blend = "rtc"` (real-time chunking) replaces as `"replace"` does, and each request
//!   carries the newest chunk's rows from the observation's tick on and `d`, the rows of them
//!   the loop runs before the new chunk can (the delay in ticks): the server freezes the new
//!   chunk's first `d` rows to them and guides the rest of the overlap toward them
//!   (labrig_policies::rtc). An openpi server is not guided: it gets the schedule alone, and
//!   the log says so.
//! - No answer to a request within `server_timeout_s`: the episode fails, saying so.
//! - In the sim, `/sim/task` (the physics' success predicate) ends an episode as a success;
//!   on a real rig the operator judges (`/rig/request`).
//!
//! At start the loop waits for the server's `/policy/info` and refuses a policy it cannot
//! serve: a camera it does not record, an action space it cannot execute, or another action
//! width, each named.

use crate::config::{Blend, ChunkTiming, ClockKind, PolicySourceConfig};
use crate::info::PolicyInfo;
use crate::remote::{RemoteConfig, RemoteJob, RemoteReply};
use crate::source::{ActionSource, Proposal, RgbFrame, SourceError, TickView, Verdict};
use crate::step::ChunkRef;
use labrig_msgs::Nanos;
use labrig_msgs::rig::{ActionChunk, ArmCommand, ArmCommandMode, PolicyObservation, PolicyRequest, Step, TeleopState};
use labrig_msgs::sensor_msgs::CompressedImage;
use labrig_msgs::std_msgs::{Header, StringMsg};
use labrig_msgs::topics;
use labrig_runtime::Shutdown;
use labrig_runtime::ros::{Ros, RosError, RosPublisher, RosSubscription};
use nalgebra::{UnitQuaternion, Vector3};
use serde::Serialize;
use std::collections::VecDeque;
use std::sync::Arc;
use std::sync::mpsc;
use std::time::{Duration, Instant};

/// What a run of the policy source did.
#[derive(Debug, Clone, Default, Serialize)]
pub struct PolicyStats {
    pub policy_id: String,
    pub requests: u64,
    pub chunks: u64,
    /// Rows whose time had passed when their chunk arrived.
    pub rows_skipped: u64,
    /// Rows executed (blended ones count once).
    pub rows_executed: u64,
    /// Ticks the policy had no row for (the arm held).
    pub ticks_without_action: u64,
    /// Requests not sent for lack of a camera's frame.
    pub requests_without_images: u64,
    /// Ticks with a row whose movement the deadman withheld (the arm held).
    pub deadman_held: u64,
    /// Request to chunk, wall time (ms): p50, p99, max (NaN before any).
    pub round_trip_ms: [f64; 3],
    /// The lead (ticks) the last request was sent with.
    pub lead_steps: u32,
    /// `rtc`: requests that carried the executing chunk's rows, and the d the last one froze.
    pub prefix_requests: u64,
    pub frozen_steps: u32,
}

/// One tick as the policy sees it.
#[derive(Debug, Clone)]
struct Obs {
    step_index: u64,
    tick_ns: i64,
    robot: labrig_msgs::rig::RobotState,
    images: Vec<(String, Arc<RgbFrame>)>,
}

/// A chunk being executed.
#[derive(Debug, Clone)]
struct Chunk {
    id: u64,
    obs_step: u64,
    times_ns: Vec<i64>,
    /// `action_dim` wide.
    rows: Vec<Vec<f64>>,
    /// The first row executed (the ones before it were late).
    first_used: Option<usize>,
    /// Rows of it executed.
    executed: u32,
    /// Lockstep: the tick it was due at (not used before it, so the run does not depend on
    /// how fast the server answered); on the wall clock, from its arrival.
    usable_from: i64,
}

impl Chunk {
    /// The row meant for `tick` (within half a period).
    fn row_at(&self, tick: i64, tol: i64) -> Option<usize> {
        self.times_ns.iter().position(|&t| (t - tick).abs() <= tol)
    }
}

#[derive(Debug, Clone, Copy)]
struct InFlight {
    id: u64,
    /// The tick it was sent at.
    sent_ns: i64,
    /// The tick its chunk is due at (lockstep waits for it there).
    due_ns: i64,
    sent: Instant,
}

/// A request for the encoder thread: observations with raw pixels.
struct Job {
    request: PolicyRequest,
    images: Vec<Vec<(String, Arc<RgbFrame>)>>,
}

/// Where requests go: labrig's policy server over DDS, or an openpi server's websocket.
enum Requests {
    Dds(mpsc::Sender<Job>),
    Remote(mpsc::Sender<RemoteJob>),
}

/// Where chunks come from.
enum Chunks {
    Dds(Box<RosSubscription<ActionChunk>>),
    Remote(mpsc::Receiver<RemoteReply>),
}

pub struct PolicySource {
    cfg: PolicySourceConfig,
    info: PolicyInfo,
    clock: ClockKind,
    period_ns: i64,
    chunks: Chunks,
    task_sub: RosSubscription<StringMsg>,
    /// With `deadman`: the Quest's state and when it arrived.
    deadman_sub: Option<RosSubscription<TeleopState>>,
    grip: Option<(bool, Instant)>,
    jobs: Option<Requests>,
    encoder: Option<std::thread::JoinHandle<()>>,
    /// Why the episode fails (a remote policy's error, a chunk of the wrong shape).
    failure: Option<String>,
    history: VecDeque<Obs>,
    /// Oldest first; the last is the newest.
    active: Vec<Chunk>,
    in_flight: Option<InFlight>,
    next_request: u64,
    /// Chunks answering older requests belong to an earlier episode (or to the policy's turn
    /// before an operator took over).
    first_request_of_episode: u64,
    since_ns: i64,
    /// (stamp, success) of the newest `/sim/task`.
    task: Option<(i64, bool)>,
    round_trips_ms: Vec<f64>,
    stats: PolicyStats,
    warned_images: bool,
    warned_prefix: bool,
    /// An operator has taken over: observe, ask for nothing.
    suspended: bool,
}

impl std::fmt::Debug for PolicySource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PolicySource").field("info", &self.info).field("stats", &self.stats).finish_non_exhaustive()
    }
}

/// Why the policy source could not start.
#[derive(Debug, thiserror::Error)]
pub enum PolicyStartError {
    #[error(transparent)]
    Ros(#[from] RosError),
    #[error(
        "no /policy/info within {0:.0} s: is the policy server (`labrig policy run --checkpoint <dir>`) running on this domain?"
    )]
    NoServer(f64),
    #[error("/policy/info is not what a policy server sends: {0}")]
    BadInfo(String),
    #[error(transparent)]
    Mismatch(#[from] crate::info::PolicyMismatch),
    #[error("stopped before the policy server came up")]
    Stopped,
    #[error(transparent)]
    Remote(#[from] crate::remote::RemoteError),
    /// The thread connecting to the openpi server panicked or was cancelled.
    #[error(transparent)]
    RemoteThread(#[from] tokio::task::JoinError),
    #[error(transparent)]
    Rtc(#[from] labrig_msgs::rig::RtcBoundsError),
}

/// Real-time chunking's bounds for this policy, where the delay is known at start (lockstep,
/// or `rtc_delay_steps` set); a measured delay is clamped to the prefix as it comes.
fn check_rtc(cfg: &PolicySourceConfig, info: &PolicyInfo, clock: ClockKind) -> Result<(), PolicyStartError> {
    if cfg.blend != Blend::Rtc {
        return Ok(());
    }
    let rows = (info.horizon + 1).saturating_sub(info.n_obs_steps) as u32;
    let s = if cfg.execute_steps > 0 { cfg.execute_steps } else { info.n_action_steps as u32 };
    let d = match (cfg.rtc_delay_steps, clock) {
        (0, ClockKind::Sim) => cfg.lockstep_delay_steps,
        (0, ClockKind::Wall) => return Ok(()),
        (d, _) => d,
    };
    Ok(labrig_msgs::rig::rtc_bounds(d, s, rows)?)
}

impl PolicySource {
    fn timeout_s(&self) -> f64 {
        self.cfg.server_timeout_s
    }

    /// Connects to the server: waits for its `/policy/info` and checks the policy against
    /// this loop (`cameras` it records).
    pub async fn connect(
        ros: &mut Ros,
        cfg: PolicySourceConfig,
        clock: ClockKind,
        period: Nanos,
        cameras: &[String],
        shutdown: &Shutdown,
    ) -> Result<PolicySource, PolicyStartError> {
        let info_sub: RosSubscription<StringMsg> = ros.subscription_on(&topics::POLICY_INFO, 1)?;
        let chunks_sub = ros.subscription_on(&topics::POLICY_CHUNK, 100)?;
        let task_sub = ros.subscription_on(&topics::SIM_TASK, 100)?;
        let requests: RosPublisher<PolicyRequest> = ros.publisher_on(&topics::POLICY_REQUEST, 10)?;
        let deadman_sub = if cfg.deadman { Some(ros.subscription_on(&topics::TELEOP_STATE, 100)?) } else { None };
        let until = Instant::now() + Duration::from_secs_f64(cfg.server_wait_s);
        let info: PolicyInfo = loop {
            if let Some(m) = info_sub.try_take()? {
                break serde_json::from_str(&m.msg.data).map_err(|e| PolicyStartError::BadInfo(format!("{e}")))?;
            }
            if shutdown.is_triggered() {
                return Err(PolicyStartError::Stopped);
            }
            if Instant::now() > until {
                return Err(PolicyStartError::NoServer(cfg.server_wait_s));
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        };
        info.check(cameras, &cfg.action_space, cfg.sim_rig).map_err(PolicyStartError::Mismatch)?;
        check_rtc(&cfg, &info, clock)?;
        let (jobs, rx) = mpsc::channel::<Job>();
        let quality = cfg.jpeg_quality;
        let encoder = std::thread::Builder::new()
            .name("policy-requests".into())
            .spawn(move || encode_and_send(&rx, &requests, quality))
            .map_err(|e| PolicyStartError::BadInfo(format!("cannot start the request thread: {e}")))?;
        Ok(PolicySource::new(
            cfg,
            info,
            clock,
            period,
            (Chunks::Dds(Box::new(chunks_sub)), Requests::Dds(jobs), encoder),
            task_sub,
            deadman_sub,
        ))
    }

    /// Connects to an openpi server (`source = "remote"`): its metadata frame is the policy's
    /// id; the observation and the actions follow `remote` (DROID's keys and conventions).
    pub async fn connect_remote(
        ros: &mut Ros,
        cfg: PolicySourceConfig,
        remote: RemoteConfig,
        clock: ClockKind,
        period: Nanos,
        cameras: &[String],
    ) -> Result<PolicySource, PolicyStartError> {
        let task_sub = ros.subscription_on(&topics::SIM_TASK, 100)?;
        let deadman_sub = if cfg.deadman { Some(ros.subscription_on(&topics::TELEOP_STATE, 100)?) } else { None };
        let period_s = period.0 as f64 * 1e-9;
        let r = remote.clone();
        let (client, info) = tokio::task::spawn_blocking(move || crate::remote::connect(&r, period_s)).await??;
        info.check(cameras, &cfg.action_space, cfg.sim_rig).map_err(PolicyStartError::Mismatch)?;
        check_rtc(&cfg, &info, clock)?;
        if cfg.blend == Blend::Rtc {
            tracing::warn!(
                policy = %info.policy_id,
                "policy.blend = \"rtc\": an openpi server cannot be guided toward the executing chunk; its chunks come on real-time chunking's schedule without the guidance"
            );
        }
        let (jobs, rx) = mpsc::channel::<RemoteJob>();
        let (replies, chunks) = mpsc::channel::<RemoteReply>();
        let (id, timeout) = (info.policy_id.clone(), cfg.server_timeout_s);
        let observers = (ros.publisher_on(&topics::POLICY_CHUNK, 10)?, ros.publisher_on(&topics::POLICY_REFUSED, 10)?);
        let worker = std::thread::Builder::new()
            .name("openpi-requests".into())
            .spawn(move || crate::remote::run_worker(Some(client), remote, id, timeout, &rx, &replies, Some(observers)))
            .map_err(|e| PolicyStartError::BadInfo(format!("cannot start the request thread: {e}")))?;
        Ok(PolicySource::new(
            cfg,
            info,
            clock,
            period,
            (Chunks::Remote(chunks), Requests::Remote(jobs), worker),
            task_sub,
            deadman_sub,
        ))
    }

    fn new(
        cfg: PolicySourceConfig,
        info: PolicyInfo,
        clock: ClockKind,
        period: Nanos,
        (chunks, jobs, encoder): (Chunks, Requests, std::thread::JoinHandle<()>),
        task_sub: RosSubscription<StringMsg>,
        deadman_sub: Option<RosSubscription<TeleopState>>,
    ) -> PolicySource {
        tracing::info!(policy = %info.policy_id, cameras = ?info.cameras, action_space = %info.action_space, "policy source up");
        let stats =
            PolicyStats { policy_id: info.policy_id.clone(), round_trip_ms: [f64::NAN; 3], ..PolicyStats::default() };
        PolicySource {
            cfg,
            info,
            clock,
            period_ns: period.0,
            chunks,
            task_sub,
            deadman_sub,
            grip: None,
            jobs: Some(jobs),
            encoder: Some(encoder),
            failure: None,
            history: VecDeque::new(),
            active: Vec::new(),
            in_flight: None,
            next_request: 1,
            first_request_of_episode: 1,
            since_ns: i64::MIN,
            task: None,
            round_trips_ms: Vec::new(),
            stats,
            warned_images: false,
            warned_prefix: false,
            suspended: false,
        }
    }

    pub fn info(&self) -> &PolicyInfo {
        &self.info
    }

    pub fn stats(&self) -> PolicyStats {
        let mut s = self.stats.clone();
        if let Some(p) = labrig_episode::inspect::Percentiles::of(self.round_trips_ms.clone()) {
            s.round_trip_ms = [p.p50, p.p99, p.max];
        }
        s
    }

    fn execute_steps(&self) -> u32 {
        if self.cfg.execute_steps > 0 { self.cfg.execute_steps } else { self.info.n_action_steps as u32 }
    }

    /// The ticks a request takes to answer: in lockstep the played delay; on the wall clock the
    /// slowest of the last 20 round trips, in ticks, rounded up (1 before any).
    fn delay_steps(&self) -> u32 {
        match self.clock {
            ClockKind::Sim => self.cfg.lockstep_delay_steps,
            ClockKind::Wall => {
                let recent = &self.round_trips_ms[self.round_trips_ms.len().saturating_sub(20)..];
                let worst = recent.iter().copied().fold(f64::NAN, f64::max);
                if worst.is_nan() { 1 } else { (worst * 1e6 / self.period_ns as f64).ceil().max(1.0) as u32 }
            }
        }
    }

    /// How many ticks before the newest chunk's `execute_steps` are spent the next is asked for:
    /// the delay (on the wall clock plus `request_margin_steps`), or none when the loop waits.
    fn lead_steps(&self) -> u32 {
        match (self.cfg.blend, self.clock) {
            (Blend::Wait, _) => 0,
            (_, ClockKind::Sim) => self.delay_steps(),
            (_, ClockKind::Wall) => self.delay_steps() + self.cfg.request_margin_steps,
        }
    }

    /// The rows of the newest chunk from `tick` on, and d (how many of them run before a chunk
    /// asked for now can), for a real-time chunking request.
    fn prefix(&mut self, tick: i64) -> Option<(Vec<f64>, u32)> {
        if self.cfg.blend != Blend::Rtc || !matches!(self.jobs, Some(Requests::Dds(_))) {
            return None;
        }
        let c = self.active.last()?;
        let tol = self.tolerance();
        let from = c.times_ns.iter().position(|&t| t >= tick - tol)?;
        let rows: Vec<f64> = c.rows[from..].iter().flatten().copied().collect();
        let n = (c.rows.len() - from) as u32;
        let want = if self.cfg.rtc_delay_steps > 0 { self.cfg.rtc_delay_steps } else { self.delay_steps() };
        if want > n && !self.warned_prefix {
            tracing::warn!(
                "real-time chunking: the delay ({want} ticks) outruns the executing chunk's {n} rows left: d clamped to {n}"
            );
            self.warned_prefix = true;
        }
        Some((rows, want.min(n)))
    }

    fn tolerance(&self) -> i64 {
        self.period_ns / 2
    }

    fn take_chunk(&mut self, c: ActionChunk) {
        if c.request_id < self.first_request_of_episode {
            return; // an earlier episode's
        }
        if c.action_dim as usize != self.info.action_dim || c.times_ns.len() != c.horizon as usize {
            tracing::warn!(chunk = c.request_id, "a chunk of {} x {}: ignored", c.horizon, c.action_dim);
            return;
        }
        let mut usable_from = i64::MIN;
        let mut times_ns = c.times_ns.clone();
        if let Some(f) = self.in_flight.filter(|f| f.id == c.request_id) {
            let elapsed = f.sent.elapsed();
            self.round_trips_ms.push(elapsed.as_secs_f64() * 1e3);
            self.in_flight = None;
            if self.clock == ClockKind::Sim {
                usable_from = f.due_ns;
            }
            if self.cfg.chunk_timing == ChunkTiming::Arrival || self.cfg.blend == Blend::Wait {
                // The first tick at or after its arrival: in lockstep the tick it was due at,
                // on the wall clock the sending tick + the round trip rounded up to ticks.
                let arrival = match self.clock {
                    ClockKind::Sim => f.due_ns,
                    ClockKind::Wall => {
                        let ticks = (elapsed.as_nanos() as i64 + self.period_ns - 1) / self.period_ns;
                        f.sent_ns + ticks * self.period_ns
                    }
                };
                let shift = times_ns.first().map_or(0, |&t0| (arrival - t0).max(0));
                times_ns.iter_mut().for_each(|t| *t += shift);
            }
        }
        self.stats.chunks += 1;
        let rows = (0..c.horizon as usize).map(|i| c.action(i).expect("validated width").to_vec()).collect();
        self.active.push(Chunk {
            id: c.request_id,
            obs_step: c.observation_step,
            times_ns,
            rows,
            first_used: None,
            executed: 0,
            usable_from,
        });
    }

    /// A request the policy could not answer: the episode fails with the reason (the arm
    /// holds: no rows come).
    fn refused(&mut self, request_id: u64, why: String) {
        if request_id < self.first_request_of_episode {
            return;
        }
        if self.in_flight.is_some_and(|f| f.id == request_id) {
            self.in_flight = None;
        }
        tracing::warn!(request_id, "{}: {why}", self.info.policy_id);
        self.failure.get_or_insert(format!("the policy {} failed request {request_id}: {why}", self.info.policy_id));
    }

    fn send(&mut self, tick_ns: i64, lead: u32, view: &TickView<'_>) {
        let (prefix_actions, prefix_frozen_steps) = self.prefix(tick_ns).unwrap_or_default();
        if !prefix_actions.is_empty() {
            self.stats.prefix_requests += 1;
            self.stats.frozen_steps = prefix_frozen_steps;
        }
        let n = self.info.n_obs_steps;
        let newest: Vec<&Obs> = self.history.iter().rev().take(n).rev().collect();
        let id = self.next_request;
        self.next_request += 1;
        let seed = view.scene_seed.unwrap_or_else(|| fnv1a(view.episode_id));
        let request = PolicyRequest {
            header: Header { stamp: Nanos(tick_ns).into(), frame_id: String::new() },
            request_id: id,
            episode_id: view.episode_id.to_owned(),
            scene: view.scene.to_owned(),
            observations: newest
                .iter()
                .map(|o| PolicyObservation {
                    header: Header { stamp: Nanos(o.tick_ns).into(), frame_id: "base".into() },
                    step_index: o.step_index,
                    robot_state: o.robot.clone(),
                    images: Vec::new(),
                    ..PolicyObservation::default()
                })
                .collect(),
            seed,
            period_ns: self.period_ns,
            prefix_actions,
            prefix_frozen_steps,
            guidance_max_weight: self.cfg.guidance_max_weight,
            ..PolicyRequest::default()
        };
        let images = newest.iter().map(|o| o.images.clone()).collect();
        let sent = match &self.jobs {
            Some(Requests::Dds(jobs)) => jobs.send(Job { request, images }).is_ok(),
            Some(Requests::Remote(jobs)) => {
                jobs.send(RemoteJob { request, images, instruction: view.instruction.to_owned() }).is_ok()
            }
            None => false,
        };
        if !sent {
            tracing::error!("the policy request thread is gone");
        }
        self.stats.requests += 1;
        self.stats.lead_steps = lead;
        self.in_flight = Some(InFlight {
            id,
            sent_ns: tick_ns,
            due_ns: tick_ns + i64::from(self.delay_steps()) * self.period_ns,
            sent: Instant::now(),
        });
    }

    /// The action meant for `tick`: per blending, from the chunks that have a row for it; the
    /// newest such chunk and its row.
    fn blended(&self, tick: i64) -> Option<(Vec<f64>, usize, usize)> {
        let tol = self.tolerance();
        // Waiting, a chunk whose `execute_steps` rows have run is spent.
        let spent = |c: &Chunk| self.cfg.blend == Blend::Wait && c.executed >= self.execute_steps();
        let rows: Vec<(usize, usize)> = self
            .active
            .iter()
            .enumerate()
            .filter(|(_, c)| c.usable_from <= tick && !spent(c))
            .filter_map(|(k, c)| c.row_at(tick, tol).map(|r| (k, r)))
            .collect();
        let &(newest, row) = rows.last()?;
        if self.cfg.blend != Blend::Exponential || rows.len() == 1 {
            return Some((self.active[newest].rows[row].clone(), newest, row));
        }
        let newest_step = self.active[newest].obs_step;
        let weighted: Vec<(&[f64], f64)> = rows
            .iter()
            .map(|&(k, r)| {
                let age = newest_step.saturating_sub(self.active[k].obs_step) as f64;
                (self.active[k].rows[r].as_slice(), (-self.cfg.blend_decay * age).exp())
            })
            .collect();
        Some((blend(&weighted, &self.info.action_space), newest, row))
    }
}

/// Weighted average of actions: positions (or velocities, joint targets) and the gripper
/// linearly, axis-angle rotations by incremental slerp.
fn blend(rows: &[(&[f64], f64)], action_space: &str) -> Vec<f64> {
    let total: f64 = rows.iter().map(|(_, w)| w).sum();
    let mut out = vec![0.0; rows[0].0.len()];
    for (a, w) in rows {
        for (o, x) in out.iter_mut().zip(a.iter()) {
            *o += x * w / total;
        }
    }
    if action_space == "eef_axis_angle" {
        let rot = |a: &[f64]| UnitQuaternion::from_scaled_axis(Vector3::new(a[3], a[4], a[5]));
        let mut q = rot(rows[0].0);
        let mut acc = rows[0].1;
        for (a, w) in &rows[1..] {
            let mut next = rot(a);
            if q.coords.dot(&next.coords) < 0.0 {
                next = UnitQuaternion::new_unchecked(-next.into_inner());
            }
            q = q.slerp(&next, w / (acc + w));
            acc += w;
        }
        let v = q.scaled_axis();
        out[3..6].copy_from_slice(&[v.x, v.y, v.z]);
    }
    out
}

/// The request thread: each observation's images JPEG-encoded, the request sent.
fn encode_and_send(rx: &mpsc::Receiver<Job>, requests: &RosPublisher<PolicyRequest>, quality: u8) {
    while let Ok(Job { mut request, images }) = rx.recv() {
        for (obs, imgs) in request.observations.iter_mut().zip(images) {
            for (camera, frame) in imgs {
                match labrig_episode::jpeg::encode_rgb(&frame.pixels, frame.width as u16, frame.height as u16, quality)
                {
                    Ok(data) => obs.images.push(CompressedImage {
                        header: Header { stamp: Nanos(frame.capture_ns).into(), frame_id: camera },
                        format: "jpeg".into(),
                        data,
                    }),
                    Err(e) => tracing::warn!("camera {camera}: {e}"),
                }
            }
        }
        if let Err(e) = requests.publish(request) {
            tracing::warn!("/policy/request: {e}");
        }
    }
}

/// FNV-1a of a string: a seed from an episode id where no scene seed is known.
fn fnv1a(s: &str) -> u64 {
    s.bytes().fold(0xcbf2_9ce4_8422_2325u64, |h, b| (h ^ u64::from(b)).wrapping_mul(0x100_0000_01b3))
}

impl Drop for PolicySource {
    fn drop(&mut self) {
        self.jobs = None;
        if let Some(t) = self.encoder.take() {
            let _ = t.join();
        }
    }
}

impl ActionSource for PolicySource {
    fn name(&self) -> &'static str {
        match self.chunks {
            Chunks::Dds(_) => "the policy server (/policy/chunk)",
            Chunks::Remote(_) => "the openpi server (websocket)",
        }
    }

    fn kind(&self) -> u8 {
        Step::SOURCE_POLICY
    }

    fn poll(&mut self) -> Result<(), RosError> {
        let mut got = Vec::new();
        match &self.chunks {
            Chunks::Dds(sub) => {
                while let Some(c) = sub.try_take()? {
                    got.push(Ok(c.msg));
                }
            }
            Chunks::Remote(rx) => got.extend(rx.try_iter()),
        }
        for answer in got {
            match answer {
                Ok(c) => self.take_chunk(c),
                Err((id, why)) => self.refused(id, why),
            }
        }
        if let Some(sub) = &self.deadman_sub {
            while let Some(t) = sub.try_take()? {
                self.grip = Some((t.msg.movement_enabled && t.msg.controller_connected, Instant::now()));
            }
        }
        while let Some(t) = self.task_sub.try_take()? {
            let Ok(v) = serde_json::from_str::<serde_json::Value>(&t.msg.data) else {
                tracing::warn!("/sim/task: not JSON: {:?}", t.msg.data);
                continue;
            };
            self.task = Some((v["stamp_ns"].as_i64().unwrap_or(i64::MIN), v["success"] == true));
        }
        Ok(())
    }

    /// Lockstep: the tick a chunk is due at waits for it (until the server's timeout).
    fn has(&self, tick: Nanos) -> bool {
        let timeout = self.timeout_s();
        !self.in_flight.is_some_and(|f| f.due_ns <= tick.0 && f.sent.elapsed().as_secs_f64() < timeout)
    }

    fn action(&mut self, tick: Nanos, _max_age: Nanos) -> Result<Proposal, SourceError> {
        let from = "the policy server";
        let Some((a, k, row)) = self.blended(tick.0) else {
            self.stats.ticks_without_action += 1;
            let last = self.active.last().and_then(|c| c.times_ns.last().copied());
            return Err(match last {
                None => SourceError::Silent { from },
                Some(t) => SourceError::Stale {
                    from,
                    age_ms: (tick.0 - t) as f64 / 1e6,
                    limit_ms: self.tolerance() as f64 / 1e6,
                },
            });
        };
        let chunk = &mut self.active[k];
        if chunk.first_used.is_none() {
            chunk.first_used = Some(row);
            self.stats.rows_skipped += row as u64;
        }
        chunk.executed += 1;
        let chunk_ref = ChunkRef { policy_id: self.info.policy_id.clone(), chunk_id: chunk.id, row: row as u32 };
        self.stats.rows_executed += 1;
        // Replaced chunks (older than the one executed) and chunks with no row left after
        // this tick are done; the newest is kept (the next request counts its rows).
        let tol = self.tolerance();
        let (last, replace) = (self.active.len() - 1, self.cfg.blend != Blend::Exponential);
        let mut i = 0;
        self.active.retain(|c| {
            let keep = i == last || (!(replace && i < k) && c.times_ns.last().is_some_and(|&t| t > tick.0 + tol));
            i += 1;
            keep
        });
        let mut command = ArmCommand { gripper_position: a[a.len() - 1], ..ArmCommand::default() };
        if self.info.action_space == "joint_position" {
            command.mode = ArmCommandMode::JointPosition as u8;
            command.joint_position.copy_from_slice(&a[..7]);
        } else if self.info.action_space == "cartesian_velocity" {
            command.mode = ArmCommandMode::CartesianVelocity as u8;
            command.cartesian_velocity.copy_from_slice(&a[..6]);
        } else {
            command.mode = ArmCommandMode::CartesianPositionAxisAngle as u8;
            command.cartesian_position.copy_from_slice(&a[..6]);
        }
        command.header.stamp = tick.into();
        // The deadman: held and fresh, or no movement (the row still counts as executed: the
        // chunk's timing goes on).
        let enabled =
            !self.cfg.deadman || self.grip.is_some_and(|(held, at)| held && at.elapsed() <= Duration::from_millis(100));
        self.stats.deadman_held += u64::from(!enabled);
        Ok(Proposal { command, movement_enabled: enabled, chunk: Some(chunk_ref) })
    }

    /// A request unanswered for `server_timeout_s` fails the episode: wall time (the server
    /// process) and the loop's time (in lockstep the ticks go on after the wait gives up,
    /// executing the rows left and then holding, as they would on the wall clock).
    fn verdict(&self, tick: Nanos) -> Verdict {
        if let Some(why) = &self.failure {
            return Verdict::Failed { why: Some(why.clone()) };
        }
        let timeout = self.timeout_s();
        if let Some(f) = self.in_flight
            && f.sent.elapsed().as_secs_f64() >= timeout
            && (tick.0 - f.sent_ns) as f64 / 1e9 >= timeout
        {
            return Verdict::Failed {
                why: Some(format!(
                    "the policy server ({}) did not answer request {} within {:.1} s",
                    self.info.policy_id, f.id, timeout
                )),
            };
        }
        match self.task {
            Some((t, true)) if t >= self.since_ns => Verdict::Succeeded,
            _ => Verdict::Running,
        }
    }

    fn restart(&mut self, start: Nanos) {
        self.since_ns = start.0;
        self.history.clear();
        self.active.clear();
        self.in_flight = None;
        self.first_request_of_episode = self.next_request;
        self.suspended = false;
        self.failure = None;
    }

    /// Either way what it has is dropped: the chunks (for other states than the arm's now)
    /// and the request in flight, whose answer, when it comes, is older than
    /// `first_request_of_episode` and ignored as an earlier episode's is. Resumed, the next
    /// `observe` asks at once (nothing is active), from the observations kept meanwhile.
    fn suspend(&mut self, on: bool) {
        self.suspended = on;
        self.active.clear();
        self.in_flight = None;
        self.first_request_of_episode = self.next_request;
    }

    fn cameras(&self) -> &[String] {
        &self.info.cameras
    }

    /// A policy acts on the episode's own observations: it is ready before its first chunk.
    fn ready(&mut self, _tick: Nanos, _max_age: Nanos) -> bool {
        true
    }

    fn stats(&self) -> Option<serde_json::Value> {
        serde_json::to_value(PolicySource::stats(self)).ok()
    }

    fn observe(&mut self, view: TickView<'_>) {
        let tick = view.tick.0;
        let images: Vec<(String, Arc<RgbFrame>)> =
            view.images.iter().map(|(c, f)| (c.to_string(), Arc::clone(f))).collect();
        self.history.push_back(Obs { step_index: view.step_index, tick_ns: tick, robot: view.robot.clone(), images });
        while self.history.len() > self.info.n_obs_steps {
            self.history.pop_front();
        }
        // Every observation the request carries needs every policy camera's frame (the server
        // refuses a step without one): a camera's first frame may come a tick after another's.
        let complete =
            self.history.iter().all(|o| self.info.cameras.iter().all(|c| o.images.iter().any(|(n, _)| n == c)));
        if self.in_flight.is_some() || self.suspended {
            return;
        }
        let lead = self.lead_steps();
        let due = match self.active.last() {
            None => true,
            Some(c) => {
                let left = c.times_ns.iter().filter(|&&t| t > tick + self.tolerance()).count() as u32;
                c.executed + lead >= self.execute_steps() || left <= lead
            }
        };
        if !due {
            return;
        }
        if !complete {
            self.stats.requests_without_images += 1;
            if !self.warned_images {
                tracing::warn!(step = view.step_index, cameras = ?self.info.cameras, "no frame of a policy camera at the tick: no request");
                self.warned_images = true;
            }
            return;
        }
        self.send(tick, lead, &view);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn info() -> PolicyInfo {
        PolicyInfo {
            policy_id: "run@600".into(),
            cameras: vec!["ext1".into()],
            n_obs_steps: 2,
            horizon: 16,
            n_action_steps: 8,
            action_space: "eef_axis_angle".into(),
            action_dim: 7,
            sim_only: vec![],
        }
    }

    #[test]
    fn a_policy_the_rig_cannot_serve_is_refused_by_name() {
        let rig: Vec<String> = ["ext1", "wrist"].map(String::from).to_vec();
        assert_eq!(info().check(&rig, "", false), Ok(()));
        assert_eq!(info().check(&rig, "eef_axis_angle", false), Ok(()));
        let e = info().check(&["wrist".to_string()], "", false).unwrap_err().to_string();
        assert!(e.contains("run@600 observes cameras [\"ext1\"], which this rig does not record"), "{e}");
        let e = PolicyInfo { action_space: "joint_velocity".into(), ..info() }
            .check(&rig, "", false)
            .unwrap_err()
            .to_string();
        assert!(e.contains("predicts \"joint_velocity\" actions, which the loop cannot execute"), "{e}");
        let e = info().check(&rig, "cartesian_velocity", false).unwrap_err().to_string();
        assert!(e.contains("this rig is configured for \"cartesian_velocity\""), "{e}");
        let e = PolicyInfo { action_dim: 10, ..info() }.check(&rig, "", false).unwrap_err().to_string();
        assert!(e.contains("10-wide"), "{e}");
    }

    /// A policy that reads the sim scene's positions runs on the sim rig only; the refusal
    /// names the input. Old servers' info (no `sim_only`) reads as observing none.
    #[test]
    fn a_sim_only_policy_is_refused_on_a_real_rig_naming_its_input() {
        let rig: Vec<String> = ["ext1", "wrist"].map(String::from).to_vec();
        let sim_only = PolicyInfo {
            sim_only: vec!["scene_state (the sim scene's object and receptacle positions)".into()],
            ..info()
        };
        assert_eq!(sim_only.check(&rig, "", true), Ok(()));
        let e = sim_only.check(&rig, "", false).unwrap_err().to_string();
        assert!(e.contains("run@600 observes [\"scene_state (the sim scene's object and receptacle positions)\"], which only the simulator has"), "{e}");
        let old: PolicyInfo = serde_json::from_str(
            r#"{"policy_id": "a@1", "cameras": [], "n_obs_steps": 2, "horizon": 16, "n_action_steps": 8, "action_space": "eef_axis_angle", "action_dim": 7}"#,
        )
        .unwrap();
        assert!(old.sim_only.is_empty());
    }

    #[test]
    fn blending_weights_newer_chunks_and_slerps_rotations() {
        let a = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        let b = [1.0, 0.0, 0.0, 0.0, 0.0, std::f64::consts::FRAC_PI_2, 1.0];
        let even = blend(&[(&a[..], 1.0), (&b[..], 1.0)], "eef_axis_angle");
        assert!((even[0] - 0.5).abs() < 1e-12 && (even[6] - 0.5).abs() < 1e-12);
        assert!((even[5] - std::f64::consts::FRAC_PI_4).abs() < 1e-9, "{even:?}");
        let newer = blend(&[(&a[..], (-2.0f64).exp()), (&b[..], 1.0)], "eef_axis_angle");
        assert!(newer[0] > 0.85 && newer[5] > even[5], "{newer:?}");
        // The same rotation written two ways (angle 3 vs 3 - 2 pi about the same axis)
        // averages to itself, not to the identity.
        let r = [0.0, 0.0, 0.0, 3.0, 0.0, 0.0, 0.0];
        let r2 = [0.0, 0.0, 0.0, 3.0 - 2.0 * std::f64::consts::PI, 0.0, 0.0, 0.0];
        let m = blend(&[(&r[..], 1.0), (&r2[..], 1.0)], "eef_axis_angle");
        let q = UnitQuaternion::from_scaled_axis(Vector3::new(m[3], m[4], m[5]));
        assert!(q.angle_to(&UnitQuaternion::from_scaled_axis(Vector3::new(3.0, 0.0, 0.0))) < 1e-9, "{m:?}");
        // Velocities average linearly.
        let v = blend(&[(&a[..], 1.0), (&b[..], 1.0)], "cartesian_velocity");
        assert!((v[5] - std::f64::consts::FRAC_PI_4).abs() < 1e-12);
    }
}
