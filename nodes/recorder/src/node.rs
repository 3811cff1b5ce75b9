//! The recorder node: records what the rig publishes — every configured ROS 2 topic as it came
//! off DDS (CDR passed through with its schema) and every camera's frames from shared memory
//! (JPEG) — into one MCAP per episode, started and ended by `/rig/episode` events.
//!
//! An episode is written under `<root>/.recording/<uuid>/` and moved to DROID's
//! `<root>/{success|failure}/<date>/<time>/` when it ends (`Success`, or `Failure`/`Stop`);
//! `Discard` deletes it. An ended episode stays open 300 ms for what was sent before its end
//! event but is still in flight on other topics (the last step, the last frames), taking
//! nothing sent after it.
//!
//! A recorder that dies loses no episode. `/rig/episode` and `/rig/step` are latched (the loop
//! keeps the last 100 events and 200 steps, ten seconds), so a restarted recorder learns what
//! happened while it was down and gets the steps it missed. On start it waits for that history
//! (`rejoin_wait_s`), then: an episode still in progress whose staging directory a dead
//! recorder left is recovered (every closed chunk) and continued as its next part
//! (`episode_1.mcap`, same id; the steps after the recovered part come from the loop's
//! history, so none are lost); an episode in progress with no staging directory is joined
//! late; a staging directory whose episode ended meanwhile is recovered and filed with the
//! loop's verdict; one nobody speaks for is recovered and filed under `failure/`, unjudged
//! (`success` unknown, `recovered` saying so). `labrig recover` stays for files copied off a
//! dead machine.
//!
//! Space: an episode is refused when the free space under `root` is below a margin (a few
//! episodes of the running average size, at least `min_free_mb`); `/recorder/status` then says
//! `accepting: false` with the free space and the estimate, and the loop holds the rig in Idle.
//! A write error (a full disk) ends the episode with the error reported; what was written is
//! moved where the operator looks (unfinished: `labrig recover` it once there is space).
//!
//! `/recorder/status` (std_msgs/String, JSON, latched) says what it is doing once a second and
//! after every episode.

use crate::filer::{Filed, Filer, Filing};
use labrig_episode::bag::{BagInfo, Reliability};
use labrig_episode::episode::{EpisodeError, EpisodeWriter, RawType};
use labrig_episode::metadata::{EpisodeMetadata, Outcome, RigIdentity, episode_dir};
use labrig_msgs::Invalid;
use labrig_msgs::rig::{EpisodeEvent, EpisodeEventKind, RIG_CAMERAS};
use labrig_msgs::sensor_msgs::CompressedImage;
use labrig_msgs::std_msgs::{Header, StringMsg};
use labrig_msgs::tf2_msgs::TFMessage;
use labrig_msgs::topics;
use labrig_msgs::{Nanos, RosMessage, TypeVisitor, dds_type_name, visit_type};
use labrig_runtime::frames::{FrameEncoding, FrameIntake, FrameNode, FrameSubscriber, OwnedFrame};
use labrig_runtime::ros::{RawSubscription, Ros, RosPublisher, qos};
use labrig_runtime::{Clock, RosConfig, Shutdown};
use serde::Deserialize;
use serde_json::json;
use std::collections::{BTreeMap, VecDeque};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// One recorded topic.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct TopicSpec {
    pub topic: String,
    /// `pkg/msg/Name`; must be a type labrig-msgs knows (its schema goes into the file).
    #[serde(rename = "type")]
    pub type_name: String,
    #[serde(default = "default_true")]
    pub reliable: bool,
    /// Transient-local (latched) context topics like /tf_static and /sim/scene: their last
    /// message goes into every episode at its start.
    #[serde(default)]
    pub latched: bool,
    /// Transient-local streams (`/rig/step`): read as a late joiner, so a restarted recorder
    /// gets the history the publisher keeps.
    #[serde(default)]
    pub durable: bool,
}

fn default_true() -> bool {
    true
}

fn spec(topic: &str, type_name: &str, latched: bool) -> TopicSpec {
    TopicSpec { topic: topic.into(), type_name: type_name.into(), reliable: true, latched, durable: false }
}

/// The rig's topics recorded by default.
pub fn default_topics() -> Vec<TopicSpec> {
    let mut t = vec![
        TopicSpec { durable: true, ..spec(topics::RIG_STEP.name, "labrig_msgs/msg/Step", false) },
        TopicSpec { durable: true, ..spec(topics::RIG_EPISODE.name, "labrig_msgs/msg/EpisodeEvent", false) },
        spec(topics::ARM_STATE.name, "labrig_msgs/msg/RobotState", false),
        spec(topics::ARM_COMMAND.name, "labrig_msgs/msg/ArmCommand", false),
        spec(topics::GRIPPER_STATE.name, "labrig_msgs/msg/GripperState", false),
        spec(topics::GRIPPER_COMMAND.name, "labrig_msgs/msg/GripperCommand", false),
        spec(topics::JOINT_STATES.name, "sensor_msgs/msg/JointState", false),
        spec(topics::TF.name, "tf2_msgs/msg/TFMessage", false),
        spec(topics::TF_STATIC.name, "tf2_msgs/msg/TFMessage", true),
        spec(topics::SIM_SCENE.name, "std_msgs/msg/String", true),
        spec(topics::CALIBRATION.name, "std_msgs/msg/String", true),
        spec(topics::RIG_SESSION.name, "std_msgs/msg/String", true),
        spec(topics::TELEOP_STATE.name, "labrig_msgs/msg/TeleopState", false),
        spec(topics::TELEOP_ACTION.name, "labrig_msgs/msg/ArmCommand", false),
    ];
    t.extend(RIG_CAMERAS.iter().map(|c| spec(&topics::camera_info(c), topics::CAMERA_INFO_TYPE, false)));
    t
}

/// The node's config (TOML; every key optional, unknown keys refused).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RecorderConfig {
    pub ros: RosConfig,
    /// Where episodes go (DROID's layout below it).
    pub root: PathBuf,
    pub topics: Vec<TopicSpec>,
    /// Cameras whose frames are recorded (iceoryx2 shared memory).
    pub cameras: Vec<String>,
    pub jpeg_quality: u8,
    /// The shared-memory namespace of the frames (tests, several rigs on one machine).
    pub frames_namespace: Option<String>,
    pub rig: RigIdentity,
    /// On start, how long to wait for the loop's latched episode history (what happened while
    /// the recorder was down) before deciding on the episodes a dead recorder left.
    pub rejoin_wait_s: f64,
    /// An episode is refused below this much free space under `root` (MB)...
    pub min_free_mb: f64,
    /// ...or below this many episodes of the running average size, if that is more.
    pub free_margin_episodes: f64,
}

impl Default for RecorderConfig {
    fn default() -> Self {
        RecorderConfig {
            ros: RosConfig::default(),
            root: PathBuf::from("episodes"),
            topics: default_topics(),
            cameras: RIG_CAMERAS.iter().map(|c| c.to_string()).collect(),
            jpeg_quality: 90,
            frames_namespace: labrig_runtime::frames::default_namespace(),
            rig: RigIdentity::default(),
            rejoin_wait_s: 3.0,
            min_free_mb: 100.0,
            free_margin_episodes: 3.0,
        }
    }
}

impl RecorderConfig {
    /// Checks what serde cannot, naming the key.
    pub fn validate(&self) -> Result<(), Invalid> {
        if !(1..=100).contains(&self.jpeg_quality) {
            return Err(Invalid::new("jpeg_quality", "recorder config: `jpeg_quality` must be 1..=100"));
        }
        for (k, t) in self.topics.iter().enumerate() {
            if visit_type(&t.type_name, SchemaOf).is_none() {
                return Err(Invalid::new(
                    format!("topics[{k}].type"),
                    format!("recorder config: topic {}: unknown type {}", t.topic, t.type_name),
                ));
            }
        }
        for (key, v) in [
            ("rejoin_wait_s", self.rejoin_wait_s),
            ("min_free_mb", self.min_free_mb),
            ("free_margin_episodes", self.free_margin_episodes),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(Invalid::new(key, format!("recorder config: `{key}` must be a number >= 0, got {v}")));
            }
        }
        // Waited for as a Duration when the recorder starts (1e300 panicked there).
        if self.rejoin_wait_s > 3600.0 {
            let v = self.rejoin_wait_s;
            return Err(Invalid::new(
                "rejoin_wait_s",
                format!("recorder config: `rejoin_wait_s` must be at most 3600, got {v}"),
            ));
        }
        Ok(())
    }
}

struct SchemaOf;
impl TypeVisitor for SchemaOf {
    type Output = String;
    fn visit<T: RosMessage>(self) -> String {
        labrig_msgs::schema_text::<T>()
    }
}

struct Recorded {
    spec: TopicSpec,
    schema: String,
    sub: RawSubscription,
}

struct Episode {
    uuid: String,
    writer: EpisodeWriter,
    staging: PathBuf,
    started: Instant,
    frames: u64,
    /// The Start event's send time (wall, ns): earlier messages are not the episode's.
    opened_ns: i64,
    /// The end event came: finishing once the grace period is over.
    closing: Option<Closing>,
    /// While closing, the cameras that have delivered a frame sent after the end event: all
    /// their frames the episode's steps used are in.
    passed_end: std::collections::BTreeSet<String>,
    /// Steps in the parts a dead recorder wrote (this is a continuation when non-zero parts).
    prior_steps: u64,
    prior_parts: usize,
    /// Per topic, the newest publish time in the earlier parts: what is not newer is in them.
    resume_after: BTreeMap<String, i64>,
    /// Frames captured before this (the rig's clock) are not the episode's: [`PREROLL_NS`]
    /// before the Start's stamp (the loop's first tick), and in the sim not before its scene was
    /// set (`/sim/scene`'s `since_ns`: a frame of the last scene is another episode's).
    frames_from_ns: i64,
    /// Operator corrections in a policy's rollout, from the steps' `action_source`: whether
    /// the last step was an operator's (not the policy's), the runs of such steps (takeovers)
    /// and their steps. This part's only: a continuation after a recorder restart starts
    /// them at 0 (`labrig inspect` counts from all the steps).
    operator_acting: bool,
    takeovers: u64,
    operator_steps: u64,
}

impl Episode {
    /// A part written from now on, with no earlier parts (a continuation sets them).
    fn new(writer: EpisodeWriter, staging: PathBuf, opened_ns: i64, frames_from_ns: i64) -> Episode {
        Episode {
            uuid: writer.metadata().uuid.clone(),
            writer,
            staging,
            started: Instant::now(),
            frames: 0,
            opened_ns,
            closing: None,
            passed_end: Default::default(),
            prior_steps: 0,
            prior_parts: 0,
            resume_after: BTreeMap::new(),
            frames_from_ns,
            operator_acting: false,
            takeovers: 0,
            operator_steps: 0,
        }
    }

    /// A step's `action_source`, for the takeover counts.
    fn count_source(&mut self, source: u8) {
        use labrig_msgs::rig::Step;
        let operator = Step::is_operator(source);
        self.takeovers += u64::from(operator && !self.operator_acting);
        self.operator_steps += u64::from(operator);
        self.operator_acting = operator;
    }

    /// Whether a camera frame belongs in this part: captured at most [`PREROLL_NS`] before the
    /// Start's stamp (the intake may hold seconds of frames from before a Start that came while
    /// the loop was busy) and not before the sim's scene was set ([`Episode::frames_from_ns`]),
    /// not in an earlier part (by capture time, the frames' publish time in the file), not sent
    /// after the end event. Frames are stamped on the rig's clock (the sim's, in a simulation),
    /// so the Start's wall time is no bound.
    fn takes_frame(&self, camera: &str, capture_ns: i64, publish_ns: i64) -> bool {
        let before_start = capture_ns < self.frames_from_ns;
        let in_earlier = self.resume_after.get(&topics::camera_image(camera)).is_some_and(|&t| capture_ns <= t);
        !before_start && !in_earlier && self.closing.is_none_or(|c| publish_ns <= c.sent_before_ns)
    }

    /// Whether a closing episode is done: the grace period over and every camera that has been
    /// sending (`cameras`) past the end event, or [`CLOSE_MAX`] more gone by.
    fn closed(&self, cameras: &std::collections::BTreeSet<String>) -> bool {
        let Some(c) = self.closing else { return false };
        let now = Instant::now();
        now >= c.until && (now >= c.deadline || cameras.iter().all(|cam| self.passed_end.contains(cam)))
    }

    /// Whether a message published at `publish_ns` on `topic` belongs in this part.
    fn takes(&self, topic: &str, publish_ns: i64) -> bool {
        publish_ns >= self.opened_ns
            && self.closing.is_none_or(|c| publish_ns <= c.sent_before_ns)
            && self.resume_after.get(topic).is_none_or(|&t| publish_ns > t)
    }
}

/// No episode starts with less free space than this, whatever the configured margin.
const HARD_FLOOR_BYTES: u64 = 1_000_000;

/// How long an ended episode still takes messages sent before its end event...
const CLOSE_GRACE: Duration = Duration::from_millis(300);
/// ...and, past that, how long it waits at most for each camera that has been sending to
/// deliver a frame sent after the end: a frame the last step used may still be on its way
/// through shared memory and the intake on a loaded machine.
const CLOSE_MAX: Duration = Duration::from_secs(2);

/// A frame kept from before a Start is the first step's when captured at most this long
/// before the Start's stamp (the loop's stale-frame limit is 100 ms).
const PREROLL_NS: i64 = 200_000_000;

/// Keeps `frame` among `camera`'s last [`HELD_FRAMES_PER_CAMERA`] frames, for the next
/// episode's first step. By count, not by age against the newest frame: the loop's clock (a
/// simulation's, say) may run behind the cameras' by more than the pre-roll, and the frame its
/// first step uses must still be here ([`Recorder::open`] picks by the Start's stamp).
fn hold(held: &mut BTreeMap<String, VecDeque<OwnedFrame>>, camera: &str, frame: OwnedFrame) {
    let kept = held.entry(camera.to_owned()).or_default();
    kept.push_back(frame);
    while kept.len() > HELD_FRAMES_PER_CAMERA {
        kept.pop_front();
    }
}

/// At most this many frames a camera kept while idle (half a second at 30 fps).
const HELD_FRAMES_PER_CAMERA: usize = 16;

#[derive(Debug, Clone, Copy)]
struct Closing {
    outcome: Outcome,
    /// The end event's send time (wall, ns): later messages are not the episode's.
    sent_before_ns: i64,
    until: Instant,
    /// The latest it finishes, whatever the cameras ([`CLOSE_MAX`]).
    deadline: Instant,
}

/// Latched context an episode's metadata is filled from.
#[derive(Default)]
struct Context {
    tf_static: Option<TFMessage>,
    scene_json: Option<String>,
    /// `/calibration`: the calibrations in force, for the metadata.
    calibration_json: Option<String>,
    /// `/rig/session`: the operator's session (operator, lab, building, scene, task).
    session: Option<labrig_msgs::session::Session>,
    /// The last message of each latched topic (published once, before any episode): written
    /// into every episode at its start, so each file holds its own /tf_static and scene.
    latched: BTreeMap<String, (Vec<u8>, i64)>,
}

/// A received episode event with its send time (wall, ns).
#[derive(Debug, Clone)]
struct Event {
    ev: EpisodeEvent,
    sent_ns: i64,
}

/// What the loop said about an episode a dead recorder left.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Verdict {
    Ended(Outcome),
    Discarded,
    Unjudged,
}

/// The recorder's state between iterations of its loop.
struct Recorder {
    cfg: RecorderConfig,
    topics: Vec<Recorded>,
    /// Every camera's frames, taken from shared memory by a thread of its own.
    intake: FrameIntake,
    /// Frames the intake let go so far (it queued [`INTAKE_FRAMES_PER_CAMERA`] of a camera).
    intake_dropped: u64,
    status: RosPublisher<StringMsg>,
    context: Context,
    episode: Option<Episode>,
    /// Each camera's last [`HELD_FRAMES_PER_CAMERA`] frames while no episode is open (the
    /// first step uses the newest one captured at or before its tick, which frames captured
    /// after the tick must not displace).
    held: BTreeMap<String, VecDeque<OwnedFrame>>,
    /// The cameras a frame has come from since the recorder started (the status says them).
    cameras_seen: std::collections::BTreeSet<String>,
    last: serde_json::Value,
    errors: u64,
    /// Sizes of the episodes recorded by this process (bytes), for the free-space margin.
    sizes: Vec<u64>,
    /// The last free-space reading: (free bytes, needed bytes).
    space: Option<(u64, u64)>,
    /// Frames taken (encoded) while waiting for the loop's history on start: an episode it
    /// continues gets them.
    buffered: std::collections::VecDeque<Encoded>,
    /// Finishes and files ended episodes beside the loop (the last fsync waits on the disk).
    filer: Filer,
}

/// Frames kept per camera while a restarted recorder waits to rejoin (three seconds).
const REJOIN_FRAMES_PER_CAMERA: usize = 60;

/// Frames the intake queues per camera while the recorder's loop is busy (a chunk's fsync, an
/// episode being filed): three seconds at 20 Hz, where shared memory alone keeps 200 ms...
const INTAKE_FRAMES_PER_CAMERA: usize = 60;
/// ...and at most this many bytes of them (1280x720 RGB: 34 frames, 1.7 s).
const INTAKE_BYTES_PER_CAMERA: usize = 96 << 20;

pub async fn run(mut cfg: RecorderConfig, shutdown: Shutdown) -> anyhow::Result<()> {
    cfg.validate()?;
    // The cameras' serials are the rig's, written once in the launch config and handed by the
    // launcher; a serial in this config's [rig.camera_serials] is its own (the doctor checks
    // that the two agree).
    if let Some(devices) = labrig_runtime::devices::Devices::from_launcher()? {
        cfg.rig.fill_camera_serials(&devices.camera_serials);
    }
    // Frames first: a restarted recorder takes them again as soon as it can (shared memory
    // keeps none for a subscriber that is not there).
    let frames = match &cfg.frames_namespace {
        Some(ns) => FrameNode::new_in(ns)?,
        None => FrameNode::new()?,
    };
    let cameras: Vec<(String, FrameSubscriber)> =
        cfg.cameras.iter().map(|c| Ok((c.clone(), frames.subscriber(c)?))).collect::<Result<_, anyhow::Error>>()?;
    let intake = FrameIntake::start("recorder-frames", cameras, INTAKE_FRAMES_PER_CAMERA, INTAKE_BYTES_PER_CAMERA)
        .map_err(|e| anyhow::anyhow!("starting the frame intake thread: {e}"))?;
    let mut ros = Ros::new(&cfg.ros, "labrig_recorder")?;
    let mut recorded = Vec::new();
    for t in &cfg.topics {
        let schema = visit_type(&t.type_name, SchemaOf)
            .ok_or_else(|| anyhow::anyhow!("recorder config: topic {}: unknown type {}", t.topic, t.type_name))?;
        let q = if t.latched {
            qos::latched(10)
        } else if t.durable {
            qos::latched(1000)
        } else {
            qos::reliable(1000)
        };
        let sub = ros.raw_subscription(&t.topic, &dds_type_name(&t.type_name), q)?;
        recorded.push(Recorded { spec: t.clone(), schema, sub });
    }
    let events = ros.subscription_on(&topics::RIG_EPISODE, 1000)?;
    let status = ros.publisher_on(&topics::RECORDER_STATUS, 1)?;
    std::fs::create_dir_all(cfg.root.join(".recording"))
        .map_err(|e| anyhow::anyhow!("creating {}: {e}", cfg.root.join(".recording").display()))?;
    let orphans = orphans(&cfg.root);
    tracing::info!(root = %cfg.root.display(), topics = recorded.len(), cameras = intake.cameras().len(), orphans = orphans.len(), "recorder up");
    let cfg_root = cfg.root.clone();
    let mut rec = Recorder {
        cfg,
        topics: recorded,
        intake,
        intake_dropped: 0,
        status,
        context: Context::default(),
        episode: None,
        held: BTreeMap::new(),
        cameras_seen: Default::default(),
        last: json!({ "state": "idle" }),
        errors: 0,
        sizes: Vec::new(),
        space: None,
        buffered: Default::default(),
        filer: Filer::start(cfg_root).map_err(|e| anyhow::anyhow!("starting the episode filer thread: {e}"))?,
    };
    rec.check_space();
    rec.publish_status();
    let take_events = |out: &mut Vec<Event>| {
        while let Some(r) = events.try_take().unwrap_or_else(|e| {
            tracing::warn!("/rig/episode: {e}");
            None
        }) {
            let sent_ns = r.source_time.unwrap_or(r.receive_time).0;
            out.push(Event { ev: r.msg, sent_ns });
        }
    };
    // Rejoin: the loop's latched history says what happened while no recorder ran. Wait for
    // it (the publisher matched, then a moment for its history), without taking any other
    // topic, so the steps kept for a continuation stay queued.
    let began = Instant::now();
    let wait = Duration::from_secs_f64(rec.cfg.rejoin_wait_s);
    let mut matched_at: Option<Instant> = None;
    let mut history = Vec::new();
    // The frames wait in the intake meanwhile (as many as are kept for a continuation), and
    // are encoded once the decision is made, not out of the wait's time.
    while !shutdown.is_triggered() && began.elapsed() < wait {
        take_events(&mut history);
        if matched_at.is_none() && ros.publisher_count(topics::RIG_EPISODE.name) > 0 {
            matched_at = Some(Instant::now());
        }
        if matched_at.is_some_and(|t| t.elapsed() > Duration::from_millis(500)) {
            break;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    take_events(&mut history);
    rec.buffer_frames();
    rec.rejoin(&history, orphans);
    rec.write_buffered();
    let mut status_at = Instant::now();
    let mut space_at = Instant::now();
    let mut pending = Vec::new();
    let mut intake_died = false;
    while !shutdown.is_triggered() {
        // Events, each after the messages that arrived before it: an episode's last steps
        // are in it when it ends, and a Start sees the scene published just before it.
        pending.clear();
        take_events(&mut pending);
        for e in &pending {
            rec.on_event(e);
        }
        rec.record();
        // The disk filling while recording (another writer, a margin set to 0): the episode
        // ends, finished and filed, before a write fails on it.
        if rec.episode.is_some() && space_at.elapsed() > Duration::from_millis(100) {
            space_at = Instant::now();
            rec.end_if_disk_full();
        }
        if rec.episode.as_ref().is_some_and(|e| e.closed(&rec.cameras_seen)) {
            rec.finish_closing();
        }
        rec.filed();
        // Once a second, recording or not (the launcher watches it as the node's heartbeat).
        if status_at.elapsed() > Duration::from_secs(1) {
            status_at = Instant::now();
            // Without its intake the recorder would go on recording no frames: it stops
            // instead (an open episode is filed below), and the launcher starts it again.
            if !rec.intake.running() {
                intake_died = true;
                break;
            }
            rec.note_intake_drops();
            rec.check_space();
            if let Some(ep) = &rec.episode {
                rec.last = json!({
                    "state": "recording", "staging": ep.staging, "episode": ep.uuid, "messages": ep.writer.messages(),
                    "frames": ep.frames, "seconds": ep.started.elapsed().as_secs_f64(), "errors": rec.errors,
                    "part": ep.prior_parts, "bytes": dir_bytes(&ep.staging),
                });
            }
            rec.publish_status();
        }
        tokio::time::sleep(Duration::from_millis(2)).await;
    }
    if let Some(ep) = rec.episode.take() {
        if ep.closing.is_some() {
            rec.episode = Some(ep);
            rec.finish_closing();
        } else {
            rec.end(ep, Outcome::Failure, "the recorder stopped mid-episode");
        }
    }
    rec.stop_filing();
    anyhow::ensure!(!intake_died, "the frame intake thread ended: no camera frames would be recorded");
    Ok(())
}

/// Staging directories in `<root>/.recording/` (a dead recorder's episodes).
fn orphans(root: &Path) -> Vec<PathBuf> {
    let Ok(entries) = std::fs::read_dir(root.join(".recording")) else { return Vec::new() };
    let mut dirs: Vec<PathBuf> = entries.filter_map(|e| e.ok()).map(|e| e.path()).filter(|p| p.is_dir()).collect();
    dirs.sort();
    dirs
}

impl Recorder {
    fn publish_status(&self) {
        let mut v = self.last.clone();
        if let Some(obj) = v.as_object_mut() {
            let (free, needed) = self.space.unwrap_or((0, 0));
            obj.insert("accepting".into(), json!(self.space.is_none_or(|(f, n)| f >= n)));
            obj.insert("free_bytes".into(), json!(free));
            obj.insert("needed_bytes".into(), json!(needed));
            obj.insert("episode_bytes_avg".into(), json!(self.average_size()));
            // What an episode started now would hold from the start: the cameras heard from
            // and the latched topics (scene, /tf_static, calibration) received.
            obj.insert(
                "seen".into(),
                json!({
                    "cameras": self.cameras_seen,
                    "latched": self.context.latched.keys().collect::<Vec<_>>(),
                    "session": self.context.session,
                }),
            );
        }
        if let Err(e) = self.status.publish(StringMsg { data: v.to_string() }) {
            tracing::warn!("/recorder/status: {e}");
        }
    }

    fn average_size(&self) -> u64 {
        if self.sizes.is_empty() { 0 } else { self.sizes.iter().sum::<u64>() / self.sizes.len() as u64 }
    }

    /// The free space under `root` and the margin an episode needs.
    fn check_space(&mut self) {
        // Below a megabyte nothing useful fits, whatever the margin says (a disk that filled
        // up mid-episode stays refused until space is made).
        let needed = ((self.cfg.min_free_mb * 1e6) as u64)
            .max((self.cfg.free_margin_episodes * self.average_size() as f64) as u64)
            .max(HARD_FLOOR_BYTES);
        match free_bytes(&self.cfg.root) {
            Ok(free) => self.space = Some((free, needed)),
            Err(e) => {
                tracing::warn!("free space of {}: {e}", self.cfg.root.display());
                self.space = None;
            }
        }
    }

    /// Frames while no decision on the episodes is made yet (the rejoin wait): encoded and kept,
    /// the oldest dropped past [`REJOIN_FRAMES_PER_CAMERA`] per camera.
    fn buffer_frames(&mut self) {
        let taken = self.intake.take();
        for (camera, frames) in self.intake.cameras().iter().zip(taken) {
            for frame in frames {
                if let Some(e) = encode_frame(camera, &frame, self.cfg.jpeg_quality) {
                    self.buffered.push_back(e);
                }
            }
        }
        let limit = REJOIN_FRAMES_PER_CAMERA * self.intake.cameras().len().max(1);
        while self.buffered.len() > limit {
            self.buffered.pop_front();
        }
    }

    /// Logs the frames the intake let go since the last call (once a second, off the loop's
    /// every iteration).
    fn note_intake_drops(&mut self) {
        let dropped: u64 = self.intake.dropped().iter().sum();
        if dropped > self.intake_dropped {
            tracing::warn!(
                frames = dropped - self.intake_dropped,
                "the recorder fell {INTAKE_FRAMES_PER_CAMERA} frames ({} MB) behind a camera: its oldest frames were let go",
                INTAKE_BYTES_PER_CAMERA >> 20
            );
            self.intake_dropped = dropped;
        }
    }

    /// The frames kept during the rejoin wait into the episode it opened, if any.
    fn write_buffered(&mut self) {
        let buffered = std::mem::take(&mut self.buffered);
        let Some(ep) = self.episode.as_mut() else { return };
        let now = Clock::Wall.now().0;
        let mut written = 0;
        for e in &buffered {
            if !ep.takes_frame(&e.camera, e.capture_ns, e.publish_ns) {
                continue;
            }
            if let Err(err) = write_image(ep, e, now) {
                tracing::error!("writing the frames kept while rejoining: {err}");
                break;
            }
            written += 1;
        }
        if written > 0 {
            tracing::info!(frames = written, "frames kept while rejoining written");
        }
    }

    /// What the loop's history says about the episodes a dead recorder left (`orphans`), and
    /// the episode in progress, if any.
    fn rejoin(&mut self, history: &[Event], orphans: Vec<PathBuf>) {
        let mut orphans: BTreeMap<String, PathBuf> =
            orphans.into_iter().filter_map(|p| Some((p.file_name()?.to_string_lossy().into_owned(), p))).collect();
        if !history.is_empty() || !orphans.is_empty() {
            tracing::info!(events = history.len(), orphans = orphans.len(), "rejoining");
        }
        // The episode in progress: the newest Start with no end after it.
        let ended = |k: usize| {
            history[k + 1..]
                .iter()
                .any(|e| e.ev.episode_id == history[k].ev.episode_id && e.ev.kind() != Ok(EpisodeEventKind::Start))
        };
        let starts: Vec<usize> =
            (0..history.len()).filter(|&k| history[k].ev.kind() == Ok(EpisodeEventKind::Start)).collect();
        let current = starts.last().copied().filter(|&k| !ended(k));
        for (k, e) in history.iter().enumerate() {
            let id = sanitize(&e.ev.episode_id);
            match e.ev.kind() {
                Ok(EpisodeEventKind::Start) if Some(k) == current => {
                    // Continued (its staging is there) or joined late.
                    orphans.remove(&id);
                    self.on_event(e);
                }
                Ok(EpisodeEventKind::Start) if current.is_none() && orphans.contains_key(&id) && ended(k) => {
                    // Ended while the recorder was down, nothing after it: continued for the
                    // steps the loop kept, then closed by its end event below.
                    orphans.remove(&id);
                    self.on_event(e);
                }
                Ok(
                    EpisodeEventKind::Success
                    | EpisodeEventKind::Failure
                    | EpisodeEventKind::Stop
                    | EpisodeEventKind::Discard,
                ) if self.episode.as_ref().is_some_and(|ep| ep.uuid == e.ev.episode_id) => {
                    self.on_event(e);
                }
                Ok(kind @ (EpisodeEventKind::Success | EpisodeEventKind::Failure | EpisodeEventKind::Stop)) => {
                    if let Some(dir) = orphans.remove(&id) {
                        let outcome =
                            if kind == EpisodeEventKind::Success { Outcome::Success } else { Outcome::Failure };
                        self.file_orphan(&dir, Verdict::Ended(outcome));
                    }
                }
                Ok(EpisodeEventKind::Discard) => {
                    if let Some(dir) = orphans.remove(&id) {
                        self.file_orphan(&dir, Verdict::Discarded);
                    }
                }
                _ => {}
            }
        }
        for dir in orphans.into_values() {
            self.file_orphan(&dir, Verdict::Unjudged);
        }
    }

    /// A dead recorder's episode, recovered and filed with the loop's verdict.
    fn file_orphan(&mut self, dir: &Path, verdict: Verdict) {
        if verdict == Verdict::Discarded {
            tracing::info!(dir = %dir.display(), "a dead recorder's episode was discarded by the loop: deleted");
            if let Err(e) = std::fs::remove_dir_all(dir) {
                tracing::error!("deleting {}: {e}", dir.display());
            }
            return;
        }
        let (success, note) = match verdict {
            Verdict::Ended(o) => {
                (Some(o == Outcome::Success), "the recorder died during the episode; the loop's verdict")
            }
            _ => (None, "the recorder died during the episode; unjudged: no verdict came"),
        };
        if labrig_episode::episode::part_files(dir).map_or(true, |p| p.is_empty()) {
            // Killed before the file existed: nothing was recorded.
            tracing::warn!(dir = %dir.display(), "a dead recorder's staging directory holds no episode: removed");
            let _ = std::fs::remove_dir_all(dir);
            return;
        }
        let amend = |m: &mut EpisodeMetadata| {
            m.success = success;
            m.recovered = Some(note.to_owned());
        };
        let recovered = labrig_episode::recover::recover_in_place_with(dir, Some(&amend));
        let (start_ns, steps) = match &recovered {
            Ok(r) => {
                let steps = r.info.topics.iter().find(|t| t.name == topics::RIG_STEP.name).map_or(0, |t| t.count);
                let start = labrig_episode::read_episode(dir).ok().and_then(|d| d.metadata).map(|m| m.start_ns);
                (start.unwrap_or(r.info.start_ns), steps)
            }
            Err(e) => {
                self.errors += 1;
                tracing::error!(dir = %dir.display(), "recovering a dead recorder's episode: {e}; filed unfinished");
                (
                    std::fs::metadata(dir)
                        .ok()
                        .and_then(|m| m.modified().ok())
                        .map_or(0, |t| t.duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_nanos() as i64)),
                    0,
                )
            }
        };
        let outcome = match verdict {
            Verdict::Ended(o) => o,
            _ => Outcome::Failure,
        };
        let dest = free_name(episode_dir(&self.cfg.root, outcome, Nanos(start_ns)));
        let moved = dest.parent().map(std::fs::create_dir_all).transpose().and_then(|_| std::fs::rename(dir, &dest));
        self.last = match moved {
            Ok(()) => {
                tracing::info!(dir = %dest.display(), steps, ?verdict, "a dead recorder's episode recovered");
                json!({ "state": "recovered", "dir": dest, "steps": steps, "outcome": outcome.dir(),
                        "judged": success.is_some(), "note": note })
            }
            Err(e) => {
                tracing::error!("moving {} to {}: {e}", dir.display(), dest.display());
                json!({ "state": "error", "error": format!("moving a recovered episode: {e}"), "staging": dir })
            }
        };
        self.publish_status();
    }

    fn on_event(&mut self, e: &Event) {
        let ev = &e.ev;
        let sent_ns = e.sent_ns;
        let kind = ev.kind();
        // A Start for the episode being recorded (its history arriving late): nothing to do.
        if kind == Ok(EpisodeEventKind::Start)
            && !ev.episode_id.is_empty()
            && self.episode.as_ref().is_some_and(|ep| ep.uuid == ev.episode_id)
        {
            return;
        }
        // An episode still closing ends before the next one starts.
        if kind == Ok(EpisodeEventKind::Start) && self.episode.as_ref().is_some_and(|e| e.closing.is_some()) {
            let _ = drain_topics(&self.topics, &mut self.context, self.episode.as_mut(), false);
            self.finish_closing();
        }
        // Before a Start only the latched topics (the scene, the camera poses published
        // just before it); the rest is taken after, each message by its send time.
        let latched_only = kind == Ok(EpisodeEventKind::Start);
        if let Some(err) = drain_topics(&self.topics, &mut self.context, self.episode.as_mut(), latched_only) {
            tracing::error!("recording: {err}");
        }
        match kind {
            Ok(EpisodeEventKind::Start) => {
                if let Some(ep) = self.episode.take() {
                    self.end(ep, Outcome::Failure, "a new episode started before this one ended");
                }
                self.check_space();
                if let Some((free, needed)) = self.space.filter(|(f, n)| f < n) {
                    self.errors += 1;
                    let error = format!(
                        "episode {} refused: {:.1} MB free under {}, {:.1} MB needed (min_free_mb / free_margin_episodes)",
                        ev.episode_id,
                        free as f64 / 1e6,
                        self.cfg.root.display(),
                        needed as f64 / 1e6
                    );
                    tracing::error!("{error}");
                    self.last =
                        json!({ "state": "refused", "episode": ev.episode_id, "error": error, "disk_full": true });
                    self.publish_status();
                    return;
                }
                match self.open(ev, sent_ns) {
                    Ok(ep) => {
                        tracing::info!(dir = %ep.staging.display(), part = ep.prior_parts, "recording");
                        self.last = json!({ "state": "recording", "staging": ep.staging, "episode": ep.uuid, "part": ep.prior_parts });
                        self.episode = Some(ep);
                    }
                    Err(err) => {
                        self.errors += 1;
                        tracing::error!("cannot start the episode: {err}");
                        self.last = json!({ "state": "error", "episode": ev.episode_id, "error": err.to_string(), "disk_full": err.is_disk_full() });
                    }
                }
                self.publish_status();
            }
            Ok(kind @ (EpisodeEventKind::Success | EpisodeEventKind::Failure | EpisodeEventKind::Stop)) => {
                // Messages sent before the event still in flight on other topics (the
                // last step, the last frames) belong to the episode: it stays open for
                // CLOSE_GRACE, taking only what was sent before the event.
                if let Some(ep) = self.episode.as_mut().filter(|ep| ep.closing.is_none()) {
                    let outcome = if kind == EpisodeEventKind::Success { Outcome::Success } else { Outcome::Failure };
                    ep.writer.metadata_mut().success = Some(outcome == Outcome::Success);
                    if let Err(err) = ep.writer.write(
                        topics::RIG_EPISODE.name,
                        ev,
                        Clock::Wall.now(),
                        Nanos(sent_ns),
                        Reliability::Reliable,
                    ) {
                        tracing::warn!("/rig/episode: {err}");
                    }
                    let now = Instant::now();
                    ep.closing = Some(Closing {
                        outcome,
                        sent_before_ns: sent_ns,
                        until: now + CLOSE_GRACE,
                        deadline: now + CLOSE_GRACE + CLOSE_MAX,
                    });
                }
            }
            Ok(EpisodeEventKind::Discard) => {
                if let Some(ep) = self.episode.take() {
                    let Episode { writer, staging, uuid, .. } = ep;
                    let why = String::new();
                    let f = Filing {
                        writer,
                        staging,
                        uuid,
                        outcome: Outcome::Failure,
                        why,
                        disk_full: false,
                        discard: true,
                    };
                    self.filer.submit(f);
                }
            }
            Ok(EpisodeEventKind::Reset) => {}
            Err(err) => tracing::warn!("/rig/episode: {err}"),
        }
    }

    /// The earliest capture time of an episode's frames whose first tick is `first_tick_ns`:
    /// [`PREROLL_NS`] before it, and not before the sim's scene was set.
    fn frames_from(&self, first_tick_ns: i64) -> i64 {
        let since = self
            .context
            .scene_json
            .as_deref()
            .and_then(|s| serde_json::from_str::<serde_json::Value>(s).ok())
            .and_then(|v| v["since_ns"].as_i64());
        (first_tick_ns - PREROLL_NS).max(since.unwrap_or(i64::MIN))
    }

    /// Opens the episode a Start announces: a new one, or the next part of one a dead
    /// recorder left in its staging directory.
    fn open(&mut self, ev: &EpisodeEvent, sent_ns: i64) -> Result<Episode, EpisodeError> {
        let start_ns = Clock::Wall.now().0;
        let scene_id = self
            .context
            .scene_json
            .as_deref()
            .and_then(|s| serde_json::from_str::<serde_json::Value>(s).ok())
            .and_then(|v| v["spec_name"].as_str().map(str::to_owned))
            .unwrap_or_default();
        // The operator's session (`labrig station`) names who, where and what, over the
        // recorder's own config; an empty field leaves it.
        let mut rig = self.cfg.rig.clone();
        let (mut scene_id, mut task) = (scene_id, ev.note.clone());
        if let Some(s) = &self.context.session {
            let set = |field: &mut String, v: &str| {
                if !v.is_empty() {
                    v.clone_into(field);
                }
            };
            set(&mut rig.user, &s.operator);
            set(&mut rig.lab, &s.lab);
            set(&mut rig.building, &s.building);
            set(&mut scene_id, &s.scene_id);
            if task.is_empty() {
                s.task.clone_into(&mut task);
            }
        }
        let mut meta = EpisodeMetadata::new(&rig, &scene_id, &task, Nanos(start_ns));
        if !ev.episode_id.is_empty() {
            meta.uuid.clone_from(&ev.episode_id);
        }
        meta.sim_scene.clone_from(&self.context.scene_json);
        meta.calibration.clone_from(&self.context.calibration_json);
        if let Some(tf) = &self.context.tf_static {
            meta.extrinsics = extrinsics(tf);
        }
        let staging = self.cfg.root.join(".recording").join(sanitize(&meta.uuid));
        let parts = labrig_episode::episode::part_files(&staging).unwrap_or_default();
        if !parts.is_empty() {
            let from = self.frames_from(Nanos::from(ev.header.stamp).0);
            return self.continue_episode(staging, meta, sent_ns, from);
        }
        let mut writer = EpisodeWriter::create(&staging, meta)?;
        for r in self.topics.iter().filter(|r| r.spec.latched) {
            let Some((cdr, publish)) = self.context.latched.get(&r.spec.topic) else { continue };
            let ty = RawType { name: &r.spec.type_name, schema: &r.schema };
            if let Err(e) =
                writer.write_cdr(&r.spec.topic, &ty, cdr, Nanos(start_ns), Nanos(*publish), Reliability::Reliable)
            {
                tracing::warn!("{}: {e}", r.spec.topic);
            }
        }
        if let Err(e) =
            writer.write(topics::RIG_EPISODE.name, ev, Nanos(start_ns), Nanos(sent_ns), Reliability::Reliable)
        {
            tracing::warn!("/rig/episode: {e}");
        }
        let from = self.frames_from(Nanos::from(ev.header.stamp).0);
        let mut ep = Episode::new(writer, staging, sent_ns, from);
        // The first step's frames were published before the Start (the loop announces an
        // episode on its first tick): the frames kept while idle go in when they belong to
        // that tick (and to its scene).
        let first_tick = Nanos::from(ev.header.stamp).0;
        for (camera, frames) in std::mem::take(&mut self.held) {
            // From the frame the first step uses (the newest at or before its tick) on.
            let used = frames.iter().rev().map(|f| f.header().capture_ns).find(|&t| t <= first_tick);
            let keep_from = used.unwrap_or(from).max(from);
            for frame in frames.iter().filter(|f| f.header().capture_ns >= keep_from) {
                if let Err(e) = write_frame(&mut ep, &camera, frame, self.cfg.jpeg_quality, start_ns) {
                    tracing::warn!("camera {camera}: {e}");
                }
            }
        }
        Ok(ep)
    }

    /// The next part of an episode a dead recorder was writing: its parts recovered (every
    /// closed chunk), then `episode_<k>.mcap` taking only what is newer than they hold.
    fn continue_episode(
        &mut self,
        staging: PathBuf,
        meta: EpisodeMetadata,
        sent_ns: i64,
        frames_from_ns: i64,
    ) -> Result<Episode, EpisodeError> {
        let recovered = labrig_episode::recover::recover_in_place(&staging)?;
        let infos: Vec<BagInfo> = recovered.parts.iter().map(|p| p.info.clone()).collect();
        let earlier = labrig_episode::inspect(&staging).ok();
        let resume_after: BTreeMap<String, i64> =
            earlier.iter().flat_map(|i| &i.topics).map(|t| (t.topic.clone(), t.last_publish_ns)).collect();
        let prior_steps = earlier.as_ref().map_or(0, |i| i.steps);
        // The episode's own metadata (start time, scene, extrinsics) from its first part.
        let mut meta = earlier.and_then(|i| i.metadata).unwrap_or(meta);
        meta.recovered =
            Some(format!("the recorder restarted during the episode: recorded in {} parts", infos.len() + 1));
        tracing::warn!(
            dir = %staging.display(), parts = infos.len(), steps = prior_steps,
            "a dead recorder's episode is still in progress: recovered, recording its next part"
        );
        let prior_parts = infos.len();
        let writer = EpisodeWriter::create_part(&staging, meta, infos)?;
        self.held.clear();
        Ok(Episode { prior_steps, prior_parts, resume_after, ..Episode::new(writer, staging, sent_ns, frames_from_ns) })
    }

    /// Topics and camera frames into the open episode.
    fn record(&mut self) {
        let mut failed: Option<EpisodeError> =
            drain_topics(&self.topics, &mut self.context, self.episode.as_mut(), false);
        let taken = self.intake.take();
        'cameras: for (camera, frames) in self.intake.cameras().iter().zip(taken) {
            if !frames.is_empty() && !self.cameras_seen.contains(camera) {
                self.cameras_seen.insert(camera.clone());
            }
            for frame in frames {
                let Some(ep) = &mut self.episode else {
                    // Idle: the last pre-roll's frames are kept, for a Start whose first step
                    // uses one of them.
                    hold(&mut self.held, camera, frame);
                    continue;
                };
                let h = frame.header();
                if !ep.takes_frame(camera, h.capture_ns, h.publish_ns) {
                    // Sent after a closing episode's end: the next episode's first step may
                    // use it (back to back, the Start comes while the last one closes).
                    if ep.closing.is_some() {
                        ep.passed_end.insert(camera.clone());
                        hold(&mut self.held, camera, frame);
                    }
                    continue;
                }
                if let Err(e) = write_frame(ep, camera, &frame, self.cfg.jpeg_quality, Clock::Wall.now().0) {
                    failed = Some(e);
                    break 'cameras;
                }
            }
        }
        if let Some(e) = failed {
            self.errors += 1;
            tracing::error!("recording stopped: {e}");
            if let Some(ep) = self.episode.take() {
                self.abandon(ep, &e);
            }
        }
    }

    /// A write error (a full disk): what was written is moved where the operator looks,
    /// unfinished (every closed chunk is readable; `labrig recover` makes it whole).
    fn abandon(&mut self, ep: Episode, err: &EpisodeError) {
        let Episode { staging, writer, uuid, .. } = ep;
        let start_ns = writer.metadata().start_ns;
        drop(writer);
        let dest = free_name(episode_dir(&self.cfg.root, Outcome::Failure, Nanos(start_ns)));
        let moved =
            dest.parent().map(std::fs::create_dir_all).transpose().and_then(|_| std::fs::rename(&staging, &dest));
        let kept = match moved {
            Ok(()) => dest,
            Err(e) => {
                tracing::error!("moving {} to {}: {e}", staging.display(), dest.display());
                staging
            }
        };
        tracing::error!(dir = %kept.display(), "the episode is kept unfinished: `labrig recover` it once there is space");
        self.last = json!({ "state": "error", "episode": uuid, "error": err.to_string(), "disk_full": err.is_disk_full(), "kept": kept });
        self.check_space();
        self.publish_status();
    }

    /// Ends the open episode (a failure, finished and filed) when the free space is below
    /// half of [`HARD_FLOOR_BYTES`]: what is left still holds its summary.
    fn end_if_disk_full(&mut self) {
        let Ok(free) = free_bytes(&self.cfg.root) else { return };
        if free >= HARD_FLOOR_BYTES / 2 {
            return;
        }
        let Some(ep) = self.episode.take() else { return };
        let uuid = ep.uuid.clone();
        let why = format!(
            "the disk is full ({} KB free under {}): the episode ended early",
            free / 1000,
            self.cfg.root.display()
        );
        tracing::error!(episode = %uuid, "{why}");
        self.errors += 1;
        // The loop stops the episode on the status this files (an error: the disk is full).
        self.file(ep, Outcome::Failure, &why, true);
    }

    fn finish_closing(&mut self) {
        if let Some(ep) = self.episode.take() {
            let outcome = ep.closing.map_or(Outcome::Failure, |c| c.outcome);
            self.end(ep, outcome, "");
        }
    }

    /// Finishes an episode and moves it into DROID's layout, beside the loop ([`Filer`]); its
    /// status comes back through [`Recorder::filed`].
    fn end(&mut self, ep: Episode, outcome: Outcome, why: &str) {
        self.file(ep, outcome, why, false);
    }

    fn file(&mut self, ep: Episode, outcome: Outcome, why: &str, disk_full: bool) {
        let Episode { mut writer, staging, prior_steps, takeovers, operator_steps, uuid, .. } = ep;
        writer.metadata_mut().trajectory_length = prior_steps + writer.count(topics::RIG_STEP.name);
        // A policy's rollout says how much of it was operator corrections (none: 0 and 0).
        if writer.metadata().policy.is_some() {
            writer.metadata_mut().takeovers = Some(takeovers);
            writer.metadata_mut().operator_steps = Some(operator_steps);
        }
        // Its size for the free-space margin: every closed chunk is in the file already.
        self.sizes.push(dir_bytes(&staging));
        self.filer.submit(Filing { writer, staging, uuid, outcome, why: why.to_owned(), disk_full, discard: false });
    }

    /// The statuses of the episodes filed since the last call.
    fn filed(&mut self) {
        for f in self.filer.reports() {
            self.report_filed(f);
        }
    }

    fn report_filed(&mut self, f: Filed) {
        self.errors += u64::from(f.failed);
        self.last = f.status;
        self.check_space();
        self.publish_status();
    }

    /// Waits for the episodes still being filed (the recorder is stopping).
    fn stop_filing(&mut self) {
        for f in self.filer.stop() {
            self.report_filed(f);
        }
    }
}

/// Bytes of the files in `dir` (not recursive).
fn dir_bytes(dir: &Path) -> u64 {
    std::fs::read_dir(dir)
        .map(|d| d.filter_map(|e| e.ok()?.metadata().ok()).filter(|m| m.is_file()).map(|m| m.len()).sum())
        .unwrap_or(0)
}

/// Bytes free for an unprivileged writer on the filesystem holding `path`.
pub fn free_bytes(path: &Path) -> std::io::Result<u64> {
    let stat = nix::sys::statvfs::statvfs(path).map_err(std::io::Error::from)?;
    Ok(stat.blocks_available() as u64 * stat.fragment_size() as u64)
}

/// One camera frame as the episode stores it: rgb8 frames encoded to JPEG, JPEG frames (a
/// camera's `jpeg_passthrough`) as they came, depth16 frames (a RealSense's aligned depth,
/// camera `<id>_depth`) as a 16-bit greyscale PNG of millimetres, lossless; anything else is
/// logged and skipped.
fn encode_frame(camera: &str, frame: &OwnedFrame, quality: u8) -> Option<Encoded> {
    let h = *frame.header();
    let (encoded, format) = match h.encoding() {
        Some(FrameEncoding::Rgb8) => (
            labrig_episode::jpeg::encode_rgb(frame.pixels(), h.width as u16, h.height as u16, quality)
                .map_err(|e| e.to_string()),
            "jpeg",
        ),
        Some(FrameEncoding::Jpeg) => (Ok(frame.pixels().to_vec()), "jpeg"),
        Some(FrameEncoding::Depth16) => {
            (depth_png(frame.pixels(), h.width, h.height).map_err(|e| e.to_string()), "png")
        }
        other => {
            tracing::warn!("camera {camera}: only rgb8, jpeg and depth16 frames are recorded, got {other:?}");
            return None;
        }
    };
    let data = match encoded {
        Ok(d) => d,
        Err(e) => {
            tracing::warn!("camera {camera}: {e}");
            return None;
        }
    };
    // A depth camera `<id>_depth` shares `<id>`'s optical frame (it is aligned to it).
    let optical = camera.strip_suffix("_depth").filter(|_| format == "png").unwrap_or(camera);
    let image = CompressedImage {
        header: Header { stamp: Nanos(h.capture_ns).into(), frame_id: format!("{optical}_optical") },
        format: format.into(),
        data,
    };
    Some(Encoded { camera: camera.to_owned(), image, capture_ns: h.capture_ns, publish_ns: h.publish_ns })
}

/// Little-endian uint16 depth (mm) as a 16-bit greyscale PNG (PNG is big endian).
fn depth_png(le: &[u8], width: u32, height: u32) -> Result<Vec<u8>, DepthPngError> {
    let n = width as usize * height as usize * 2;
    let Some(le) = le.get(..n) else {
        return Err(DepthPngError::Size { width, height, len: le.len(), expected: n });
    };
    let be: Vec<u8> = le.chunks_exact(2).flat_map(|p| [p[1], p[0]]).collect();
    let mut out = Vec::new();
    let mut enc = png::Encoder::new(&mut out, width, height);
    enc.set_color(png::ColorType::Grayscale);
    enc.set_depth(png::BitDepth::Sixteen);
    enc.set_compression(png::Compression::Fast);
    let mut w = enc.write_header()?;
    w.write_image_data(&be)?;
    w.finish()?;
    Ok(out)
}

/// Why a depth frame could not be recorded as PNG.
#[derive(Debug, thiserror::Error)]
enum DepthPngError {
    #[error("a {width}x{height} depth frame of {len} bytes, expected {expected}")]
    Size { width: u32, height: u32, len: usize, expected: usize },
    #[error("{0}")]
    Png(#[from] png::EncodingError),
}

/// A camera frame encoded, with its times.
struct Encoded {
    camera: String,
    image: CompressedImage,
    capture_ns: i64,
    publish_ns: i64,
}

/// One encoded frame into the episode.
fn write_image(ep: &mut Episode, e: &Encoded, log_ns: i64) -> Result<(), EpisodeError> {
    let topic = topics::camera_image(&e.camera);
    ep.writer.write(&topic, &e.image, Nanos(log_ns), Nanos(e.capture_ns), Reliability::BestEffort)?;
    ep.frames += 1;
    Ok(())
}

/// One camera frame into the episode, as JPEG.
fn write_frame(
    ep: &mut Episode,
    camera: &str,
    frame: &OwnedFrame,
    quality: u8,
    log_ns: i64,
) -> Result<(), EpisodeError> {
    match encode_frame(camera, frame, quality) {
        Some(e) => write_image(ep, &e, log_ns),
        None => Ok(()),
    }
}

/// Takes every topic's waiting messages: latched context updated, messages written into the
/// open episode. Stops at the first write error.
fn drain_topics(
    topics: &[Recorded],
    ctx: &mut Context,
    mut episode: Option<&mut Episode>,
    latched_only: bool,
) -> Option<EpisodeError> {
    for r in topics.iter().filter(|r| r.spec.latched || !latched_only) {
        loop {
            let sample = match r.sub.try_take() {
                Ok(Some(s)) => s,
                Ok(None) => break,
                Err(e) => {
                    tracing::warn!("{}: {e}", r.spec.topic);
                    break;
                }
            };
            // Episode events are written as the episode starts and ends, not here.
            if r.spec.topic == topics::RIG_EPISODE.name {
                continue;
            }
            let cdr = sample.msg.to_cdr_bytes();
            if r.spec.topic == topics::TF_STATIC.name {
                ctx.tf_static = labrig_msgs::decode::<TFMessage>(&cdr).ok();
            } else if r.spec.topic == topics::SIM_SCENE.name {
                ctx.scene_json = labrig_msgs::decode::<StringMsg>(&cdr).ok().map(|s| s.data);
            } else if r.spec.topic == topics::CALIBRATION.name {
                ctx.calibration_json = labrig_msgs::decode::<StringMsg>(&cdr).ok().map(|s| s.data);
            } else if r.spec.topic == topics::RIG_SESSION.name {
                let text = labrig_msgs::decode::<StringMsg>(&cdr).map(|s| s.data).unwrap_or_default();
                match serde_json::from_str::<labrig_msgs::session::Session>(&text) {
                    Ok(s) => ctx.session = Some(s),
                    Err(e) => tracing::warn!("/rig/session: not a session ({e}): kept the last one"),
                }
            }
            if r.spec.latched {
                ctx.latched
                    .insert(r.spec.topic.clone(), (cdr.clone(), sample.source_time.unwrap_or(sample.receive_time).0));
            }
            if let Some(ep) = episode.as_mut() {
                let log = sample.receive_time.0;
                let publish = sample.source_time.map_or(log, |t| t.0);
                // Sent before the episode's Start or after its end, or in an earlier part: not
                // this part's.
                if !ep.takes(&r.spec.topic, publish) {
                    continue;
                }
                // A policy's rollout: the checkpoint its steps executed goes into the metadata,
                // and who acted each step into the takeover counts.
                if r.spec.topic == topics::RIG_STEP.name
                    && let Ok(step) = labrig_msgs::decode::<labrig_msgs::rig::Step>(&cdr)
                {
                    // A step names its episode: another episode's is never this one's, whatever
                    // its time. (A recorder killed at an episode's end and back after the next
                    // one started took the next episode's first steps into the one it
                    // continued: its end event, which bounds it in time, comes after them.)
                    if !step.episode_id.is_empty() && step.episode_id != ep.uuid {
                        continue;
                    }
                    ep.count_source(step.action_source);
                    if ep.writer.metadata().policy.is_none() && !step.policy_id.is_empty() {
                        ep.writer.metadata_mut().policy = Some(step.policy_id);
                    }
                }
                let reliability = if r.spec.reliable { Reliability::Reliable } else { Reliability::BestEffort };
                let ty = RawType { name: &r.spec.type_name, schema: &r.schema };
                if let Err(e) = ep.writer.write_cdr(&r.spec.topic, &ty, &cdr, Nanos(log), Nanos(publish), reliability) {
                    return Some(e);
                }
            }
        }
    }
    None
}

/// `path`, or `path_2`, `path_3`, ... when it exists.
pub(crate) fn free_name(path: PathBuf) -> PathBuf {
    if !path.exists() {
        return path;
    }
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    (2..).map(|k| path.with_file_name(format!("{name}_{k}"))).find(|p| !p.exists()).expect("unbounded")
}

/// Camera extrinsics from /tf_static: every `<camera>_optical` child of the base frame as
/// DROID's [x, y, z, rx, ry, rz] (extrinsic XYZ euler).
fn extrinsics(tf: &TFMessage) -> BTreeMap<String, [f64; 6]> {
    tf.transforms
        .iter()
        .filter_map(|t| {
            let cam = t.child_frame_id.strip_suffix("_optical")?;
            let (p, q) = (&t.transform.translation, &t.transform.rotation);
            let rot = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(q.w, q.x, q.y, q.z));
            let (roll, pitch, yaw) = rot.euler_angles();
            Some((cam.to_owned(), [p.x, p.y, p.z, roll, pitch, yaw]))
        })
        .collect()
}

fn sanitize(uuid: &str) -> String {
    uuid.chars().map(|c| if c.is_ascii_alphanumeric() || "+-_.".contains(c) { c } else { '_' }).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use labrig_runtime::frames::FrameFormat;

    /// One frame of `encoding` through shared memory, as the recorder stores it.
    fn stored(encoding: FrameEncoding, width: u32, height: u32, bytes: &[u8]) -> Option<Encoded> {
        let node = FrameNode::new_in(&format!("recorder_unit_{}", std::process::id())).unwrap();
        let cam = format!("enc{}", encoding as u16);
        let mut publisher = node.publisher(&cam, FrameFormat { encoding, width, height }).unwrap();
        let subscriber = node.subscriber(&cam).unwrap();
        publisher.publish(bytes, Nanos(5), Nanos(6)).unwrap();
        let frame = subscriber.receive().unwrap().expect("frame");
        encode_frame("ext1", &OwnedFrame::from(&frame), 90)
    }

    #[test]
    fn rgb_frames_are_encoded_jpeg_frames_stored_as_they_came_others_skipped() {
        let rgb: Vec<u8> = (0..16 * 8 * 3).map(|i| (i % 251) as u8).collect();
        let e = stored(FrameEncoding::Rgb8, 16, 8, &rgb).expect("an rgb8 frame is recorded");
        let back = labrig_episode::jpeg::decode_rgb(&e.image.data).unwrap();
        assert_eq!((back.width, back.height, e.image.format.as_str(), e.capture_ns), (16, 8, "jpeg", 5));

        let jpeg = labrig_episode::jpeg::encode_rgb(&rgb, 16, 8, 40).unwrap();
        let e = stored(FrameEncoding::Jpeg, 16, 8, &jpeg).expect("a jpeg frame is recorded");
        assert_eq!(e.image.data, jpeg, "a passed-through JPEG is stored byte for byte");
        assert_eq!(e.image.header.frame_id, "ext1_optical");

        // Depth: a lossless 16-bit PNG of the millimetres, in the colour camera's optical frame.
        let mm: Vec<u16> = vec![0, 1, 900, 1000, 65535, 300, 301, 4242];
        let le: Vec<u8> = mm.iter().flat_map(|v| v.to_le_bytes()).collect();
        let node = FrameNode::new_in(&format!("recorder_unit_{}", std::process::id())).unwrap();
        let mut publisher =
            node.publisher("rs1_depth", FrameFormat { encoding: FrameEncoding::Depth16, width: 4, height: 2 }).unwrap();
        let subscriber = node.subscriber("rs1_depth").unwrap();
        publisher.publish(&le, Nanos(5), Nanos(6)).unwrap();
        let e = encode_frame("rs1_depth", &OwnedFrame::from(&subscriber.receive().unwrap().unwrap()), 90)
            .expect("depth is recorded");
        assert_eq!((e.image.format.as_str(), e.image.header.frame_id.as_str()), ("png", "rs1_optical"));
        let mut reader = png::Decoder::new(std::io::Cursor::new(e.image.data)).read_info().unwrap();
        let mut buf = vec![0u8; reader.output_buffer_size().unwrap()];
        let info = reader.next_frame(&mut buf).unwrap();
        assert_eq!((info.width, info.height, info.bit_depth), (4, 2, png::BitDepth::Sixteen));
        let back: Vec<u16> =
            buf[..info.buffer_size()].chunks_exact(2).map(|p| u16::from_be_bytes([p[0], p[1]])).collect();
        assert_eq!(back, mm);

        assert!(stored(FrameEncoding::Mono8, 4, 2, &[0u8; 8]).is_none());
    }
}
