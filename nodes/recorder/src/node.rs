//! The recorder node: records what the rig publishes — every configured ROS 2 topic as it came
//! off DDS (CDR passed through with its schema) and every camera's frames from shared memory
//! (JPEG) — into one MCAP per episode, started and ended by `/rig/episode` events.
//!
//! An episode is written under `<root>/.recording/<uuid>/` and moved to DROID's
//! `<root>/{success|failure}/<date>/<time>/` when it ends (`Success`, or `Failure`/`Stop`);
//! `Discard` deletes it. An ended episode stays open 300 ms for what was sent before its end
//! event but is still in flight on other topics (the last step, the last frames), taking
//! nothing sent after it. A recorder killed mid-episode leaves its directory in `.recording/`
//! for `labrig recover`. A write error (a full disk) ends the episode with the error reported
//! on `/recorder/status` and in the log; the node goes on and takes the next `Start`.
//! `/recorder/status` (std_msgs/String, JSON) says what it is doing once a second and after
//! every episode.

use labrig_episode::bag::Reliability;
use labrig_episode::episode::{EpisodeError, EpisodeWriter, RawType};
use labrig_episode::metadata::{EpisodeMetadata, Outcome, RigIdentity, episode_dir};
use labrig_msgs::Invalid;
use labrig_msgs::labrig_msgs::{EpisodeEventKind, RIG_CAMERAS};
use labrig_msgs::sensor_msgs::CompressedImage;
use labrig_msgs::std_msgs::{Header, StringMsg};
use labrig_msgs::tf2_msgs::TFMessage;
use labrig_msgs::topics;
use labrig_msgs::{Nanos, RosMessage, TypeVisitor, dds_type_name, visit_type};
use labrig_runtime::frames::{FrameEncoding, FrameNode, FrameSubscriber};
use labrig_runtime::ros::{RawSubscription, Ros, qos};
use labrig_runtime::{Clock, RosConfig, Shutdown};
use serde::Deserialize;
use serde_json::json;
use std::path::PathBuf;
use std::time::{Duration, Instant};

/// One recorded topic.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct TopicSpec {
    pub topic: String,
    /// `pkg/msg/Name`; must be a type labrig-msgs knows (its schema goes into the file).
    #[serde(rename = "type")]
    pub type_name: String,
    #[serde(default = "yes")]
    pub reliable: bool,
    /// Transient-local (latched) topics like /tf_static and /sim/scene.
    #[serde(default)]
    pub latched: bool,
}

fn yes() -> bool {
    true
}

fn spec(topic: &str, type_name: &str, latched: bool) -> TopicSpec {
    TopicSpec { topic: topic.into(), type_name: type_name.into(), reliable: true, latched }
}

/// The rig's topics recorded by default.
pub fn default_topics() -> Vec<TopicSpec> {
    let mut t = vec![
        spec(topics::RIG_STEP.name, "labrig_msgs/msg/Step", false),
        spec(topics::RIG_EPISODE.name, "labrig_msgs/msg/EpisodeEvent", false),
        spec(topics::ARM_STATE.name, "labrig_msgs/msg/RobotState", false),
        spec(topics::ARM_COMMAND.name, "labrig_msgs/msg/ArmCommand", false),
        spec(topics::GRIPPER_STATE.name, "labrig_msgs/msg/GripperState", false),
        spec(topics::GRIPPER_COMMAND.name, "labrig_msgs/msg/GripperCommand", false),
        spec(topics::JOINT_STATES.name, "sensor_msgs/msg/JointState", false),
        spec(topics::TF.name, "tf2_msgs/msg/TFMessage", false),
        spec(topics::TF_STATIC.name, "tf2_msgs/msg/TFMessage", true),
        spec(topics::SIM_SCENE.name, "std_msgs/msg/String", true),
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
        }
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
    writer: EpisodeWriter,
    staging: PathBuf,
    started: Instant,
    frames: u64,
    /// The Start event's send time (wall, ns): earlier messages are not the episode's.
    opened_ns: i64,
    /// The end event came: finishing once the grace period is over.
    closing: Option<Closing>,
}

/// How long an ended episode still takes messages sent before its end event.
const CLOSE_GRACE: Duration = Duration::from_millis(300);

/// A frame kept from before a Start is the first step's when captured at most this long
/// before the Start's stamp (the loop's stale-frame limit is 100 ms).
const PREROLL_NS: i64 = 200_000_000;

/// One camera frame into the episode, as JPEG (rgb8 frames only).
fn write_frame(
    ep: &mut Episode,
    camera: &str,
    frame: &labrig_runtime::frames::Frame,
    quality: u8,
    log_ns: i64,
) -> Result<(), EpisodeError> {
    let h = *frame.header();
    if h.encoding() != Some(FrameEncoding::Rgb8) {
        tracing::warn!("camera {camera}: only rgb8 frames are recorded, got {:?}", h.encoding());
        return Ok(());
    }
    let data = match labrig_episode::jpeg::encode_rgb(frame.pixels(), h.width as u16, h.height as u16, quality) {
        Ok(d) => d,
        Err(e) => {
            tracing::warn!("camera {camera}: {e}");
            return Ok(());
        }
    };
    let img = CompressedImage {
        header: Header { stamp: Nanos(h.capture_ns).into(), frame_id: format!("{camera}_optical") },
        format: "jpeg".into(),
        data,
    };
    let topic = topics::camera_image(camera);
    ep.writer.write(&topic, &img, Nanos(log_ns), Nanos(h.capture_ns), Reliability::BestEffort)?;
    ep.frames += 1;
    Ok(())
}

#[derive(Debug, Clone, Copy)]
struct Closing {
    outcome: Outcome,
    /// The end event's send time (wall, ns): later messages are not the episode's.
    sent_before_ns: i64,
    until: Instant,
}

fn finish_closing(ep: Episode, root: &std::path::Path) -> serde_json::Value {
    let outcome = ep.closing.map_or(Outcome::Failure, |c| c.outcome);
    end(ep, outcome, root, "")
}

/// Runs the node until `shutdown`.
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
        Ok(())
    }
}

pub async fn run(cfg: RecorderConfig, shutdown: Shutdown) -> anyhow::Result<()> {
    cfg.validate()?;
    let mut ros = Ros::new(&cfg.ros, "labrig_recorder")?;
    let mut topics = Vec::new();
    for t in &cfg.topics {
        let schema = visit_type(&t.type_name, SchemaOf)
            .ok_or_else(|| anyhow::anyhow!("recorder config: topic {}: unknown type {}", t.topic, t.type_name))?;
        let q = if t.latched { qos::latched(10) } else { qos::reliable(1000) };
        let sub = ros.raw_subscription(&t.topic, &dds_type_name(&t.type_name), q)?;
        topics.push(Recorded { spec: t.clone(), schema, sub });
    }
    let events = ros.subscription_on(&topics::RIG_EPISODE, 100)?;
    let status = ros.publisher_on(&topics::RECORDER_STATUS, 1)?;
    let frames = match &cfg.frames_namespace {
        Some(ns) => FrameNode::new_in(ns)?,
        None => FrameNode::new()?,
    };
    let cameras: Vec<(String, FrameSubscriber)> =
        cfg.cameras.iter().map(|c| Ok((c.clone(), frames.subscriber(c)?))).collect::<Result<_, anyhow::Error>>()?;
    let mut context = Context::default();
    let clock = Clock::Wall;
    let mut episode: Option<Episode> = None;
    // Each camera's newest frame while no episode is open.
    let mut held: std::collections::BTreeMap<String, labrig_runtime::frames::Frame> = Default::default();
    let mut last = json!({ "state": "idle" });
    let mut status_at = Instant::now();
    let mut errors = 0u64;
    tracing::info!(root = %cfg.root.display(), topics = topics.len(), cameras = cameras.len(), "recorder up");
    let publish_status = |v: &serde_json::Value| {
        if let Err(e) = status.publish(StringMsg { data: v.to_string() }) {
            tracing::warn!("/recorder/status: {e}");
        }
    };
    publish_status(&last);
    while !shutdown.is_triggered() {
        // Events, each after the messages that arrived before it: an episode's last steps
        // are in it when it ends, and a Start sees the scene published just before it.
        let mut pending = Vec::new();
        while let Some(ev) = events.try_take().unwrap_or_else(|e| {
            tracing::warn!("/rig/episode: {e}");
            None
        }) {
            pending.push(ev);
        }
        for received in pending {
            let ev = received.msg;
            let sent_ns = received.source_time.unwrap_or(received.receive_time).0;
            // An episode still closing ends before the next one starts.
            if ev.kind() == Ok(EpisodeEventKind::Start) && episode.as_ref().is_some_and(|e| e.closing.is_some()) {
                let _ = drain_topics(&topics, &mut context, episode.as_mut(), false);
                if let Some(ep) = episode.take() {
                    last = finish_closing(ep, &cfg.root);
                    publish_status(&last);
                }
            }
            // Before a Start only the latched topics (the scene, the camera poses published
            // just before it); the rest is taken after, each message by its send time.
            let latched_only = ev.kind() == Ok(EpisodeEventKind::Start);
            if let Some(e) = drain_topics(&topics, &mut context, episode.as_mut(), latched_only) {
                tracing::error!("recording: {e}");
            }
            match ev.kind() {
                Ok(EpisodeEventKind::Start) => {
                    if let Some(ep) = episode.take() {
                        let ended = end(ep, Outcome::Failure, &cfg.root, "a new episode started before this one ended");
                        publish_status(&ended);
                    }
                    let start_ns = clock.now().0;
                    let scene_id = context
                        .scene_json
                        .as_deref()
                        .and_then(|s| serde_json::from_str::<serde_json::Value>(s).ok())
                        .and_then(|v| v["spec_name"].as_str().map(str::to_owned))
                        .unwrap_or_default();
                    let mut meta = EpisodeMetadata::new(&cfg.rig, &scene_id, &ev.note, Nanos(start_ns));
                    if !ev.episode_id.is_empty() {
                        meta.uuid.clone_from(&ev.episode_id);
                    }
                    meta.sim_scene.clone_from(&context.scene_json);
                    if let Some(tf) = &context.tf_static {
                        meta.extrinsics = extrinsics(tf);
                    }
                    let staging = unused(cfg.root.join(".recording").join(sanitize(&meta.uuid)));
                    match EpisodeWriter::create(&staging, meta) {
                        Ok(mut writer) => {
                            for r in topics.iter().filter(|r| r.spec.latched) {
                                let Some((cdr, publish)) = context.latched.get(&r.spec.topic) else { continue };
                                let ty = RawType { name: &r.spec.type_name, schema: &r.schema };
                                if let Err(e) = writer.write_cdr(
                                    &r.spec.topic,
                                    &ty,
                                    cdr,
                                    Nanos(start_ns),
                                    Nanos(*publish),
                                    Reliability::Reliable,
                                ) {
                                    tracing::warn!("{}: {e}", r.spec.topic);
                                }
                            }
                            if let Err(e) = writer.write(
                                topics::RIG_EPISODE.name,
                                &ev,
                                Nanos(start_ns),
                                Nanos(sent_ns),
                                Reliability::Reliable,
                            ) {
                                tracing::warn!("/rig/episode: {e}");
                            }
                            tracing::info!(dir = %staging.display(), "recording");
                            last = json!({ "state": "recording", "staging": staging });
                            let mut ep = Episode {
                                writer,
                                staging,
                                started: Instant::now(),
                                frames: 0,
                                opened_ns: sent_ns,
                                closing: None,
                            };
                            // The first step's frames were published before the Start (the
                            // loop announces an episode on its first tick): the frames kept
                            // while idle go in when they belong to that tick.
                            let first_tick = Nanos::from(ev.header.stamp).0;
                            for (camera, frame) in std::mem::take(&mut held) {
                                if frame.header().capture_ns >= first_tick - PREROLL_NS
                                    && let Err(e) = write_frame(&mut ep, &camera, &frame, cfg.jpeg_quality, start_ns)
                                {
                                    tracing::warn!("camera {camera}: {e}");
                                }
                            }
                            episode = Some(ep);
                        }
                        Err(e) => {
                            errors += 1;
                            tracing::error!("cannot start the episode: {e}");
                            last = json!({ "state": "error", "error": e.to_string(), "disk_full": e.is_disk_full() });
                        }
                    }
                    publish_status(&last);
                }
                Ok(kind @ (EpisodeEventKind::Success | EpisodeEventKind::Failure | EpisodeEventKind::Stop)) => {
                    // Messages sent before the event still in flight on other topics (the
                    // last step, the last frames) belong to the episode: it stays open for
                    // CLOSE_GRACE, taking only what was sent before the event.
                    if let Some(ep) = episode.as_mut() {
                        let outcome =
                            if kind == EpisodeEventKind::Success { Outcome::Success } else { Outcome::Failure };
                        ep.writer.metadata_mut().success = Some(outcome == Outcome::Success);
                        if let Err(e) = ep.writer.write(
                            topics::RIG_EPISODE.name,
                            &ev,
                            clock.now(),
                            Nanos(sent_ns),
                            Reliability::Reliable,
                        ) {
                            tracing::warn!("/rig/episode: {e}");
                        }
                        ep.closing =
                            Some(Closing { outcome, sent_before_ns: sent_ns, until: Instant::now() + CLOSE_GRACE });
                    }
                }
                Ok(EpisodeEventKind::Discard) => {
                    if let Some(ep) = episode.take() {
                        let staging = ep.staging.clone();
                        let _ = ep.writer.finish();
                        let _ = std::fs::remove_dir_all(&staging);
                        last = json!({ "state": "discarded", "staging": staging });
                        publish_status(&last);
                    }
                }
                Ok(EpisodeEventKind::Reset) => {}
                Err(e) => tracing::warn!("/rig/episode: {e}"),
            }
        }
        // Topics.
        let mut failed: Option<EpisodeError> = drain_topics(&topics, &mut context, episode.as_mut(), false);
        // Camera frames (JPEG).
        for (camera, sub) in &cameras {
            loop {
                let frame = match sub.receive() {
                    Ok(Some(f)) => f,
                    Ok(None) => break,
                    Err(e) => {
                        tracing::warn!("camera {camera}: {e}");
                        break;
                    }
                };
                let Some(ep) = &mut episode else {
                    // Idle: the newest frame is kept, for a Start whose first step uses it.
                    held.insert(camera.clone(), frame);
                    continue;
                };
                if ep.closing.is_some_and(|c| frame.header().publish_ns > c.sent_before_ns) {
                    continue;
                }
                if let Err(e) = write_frame(ep, camera, &frame, cfg.jpeg_quality, clock.now().0) {
                    failed = Some(e);
                    break;
                }
            }
        }
        if let Some(e) = failed {
            errors += 1;
            tracing::error!("recording stopped: {e}");
            if let Some(ep) = episode.take() {
                let staging = ep.staging.clone();
                drop(ep);
                last = json!({ "state": "error", "error": e.to_string(), "disk_full": e.is_disk_full(), "staging": staging });
                publish_status(&last);
            }
        }
        if episode.as_ref().and_then(|e| e.closing).is_some_and(|c| Instant::now() >= c.until)
            && let Some(ep) = episode.take()
        {
            last = finish_closing(ep, &cfg.root);
            publish_status(&last);
        }
        // Once a second, recording or not (the launcher watches it as the node's heartbeat).
        if status_at.elapsed() > Duration::from_secs(1) {
            status_at = Instant::now();
            if let Some(ep) = &episode {
                last = json!({
                    "state": "recording", "staging": ep.staging, "messages": ep.writer.messages(),
                    "frames": ep.frames, "seconds": ep.started.elapsed().as_secs_f64(), "errors": errors,
                });
            }
            publish_status(&last);
        }
        tokio::time::sleep(Duration::from_millis(2)).await;
    }
    if let Some(ep) = episode.take() {
        if ep.closing.is_some() {
            finish_closing(ep, &cfg.root);
        } else {
            end(ep, Outcome::Failure, &cfg.root, "the recorder stopped mid-episode");
        }
    }
    Ok(())
}

/// Latched context an episode's metadata is filled from.
#[derive(Default)]
struct Context {
    tf_static: Option<TFMessage>,
    scene_json: Option<String>,
    /// The last message of each latched topic (published once, before any episode): written
    /// into every episode at its start, so each file holds its own /tf_static and scene.
    latched: std::collections::BTreeMap<String, (Vec<u8>, i64)>,
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
            }
            if r.spec.latched {
                ctx.latched
                    .insert(r.spec.topic.clone(), (cdr.clone(), sample.source_time.unwrap_or(sample.receive_time).0));
            }
            if let Some(ep) = episode.as_mut() {
                let log = sample.receive_time.0;
                let publish = sample.source_time.map_or(log, |t| t.0);
                // Sent before the episode's Start or after its end: not the episode's.
                if publish < ep.opened_ns || ep.closing.is_some_and(|c| publish > c.sent_before_ns) {
                    continue;
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
fn unused(path: PathBuf) -> PathBuf {
    if !path.exists() {
        return path;
    }
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    (2..).map(|k| path.with_file_name(format!("{name}_{k}"))).find(|p| !p.exists()).expect("unbounded")
}

/// Finishes an episode and moves it into DROID's layout; returns the status to publish.
fn end(ep: Episode, outcome: Outcome, root: &std::path::Path, why: &str) -> serde_json::Value {
    let Episode { mut writer, staging, .. } = ep;
    let start_ns = writer.metadata_mut().start_ns;
    writer.metadata_mut().trajectory_length = writer.count(topics::RIG_STEP.name);
    match writer.finish() {
        Ok(summary) => {
            // Two episodes may start in the same second (DROID's directory names are to the
            // second): the later one gets a suffix rather than failing to move.
            let dest = unused(episode_dir(root, outcome, Nanos(start_ns)));
            let moved =
                dest.parent().map(std::fs::create_dir_all).transpose().and_then(|_| std::fs::rename(&staging, &dest));
            match moved {
                Ok(()) => {
                    tracing::info!(dir = %dest.display(), messages = summary.messages, "episode recorded {}", why);
                    json!({ "state": "recorded", "outcome": outcome.dir(), "dir": dest, "messages": summary.messages, "bytes": summary.bytes, "note": why })
                }
                Err(e) => {
                    tracing::error!("moving {} to {}: {e}", staging.display(), dest.display());
                    json!({ "state": "error", "error": format!("moving the episode: {e}"), "staging": staging })
                }
            }
        }
        Err(e) => {
            tracing::error!("finishing the episode: {e}");
            json!({ "state": "error", "error": e.to_string(), "disk_full": e.is_disk_full(), "staging": staging })
        }
    }
}

/// Camera extrinsics from /tf_static: every `<camera>_optical` child of the base frame as
/// DROID's [x, y, z, rx, ry, rz] (extrinsic XYZ euler).
fn extrinsics(tf: &TFMessage) -> std::collections::BTreeMap<String, [f64; 6]> {
    tf.transforms
        .iter()
        .filter_map(|t| {
            let cam = t.child_frame_id.strip_suffix("_optical")?;
            let (p, q) = (&t.transform.translation, &t.transform.rotation);
            let rot = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(q.w, q.x, q.y, q.z));
            let (r, pi, y) = rot.euler_angles();
            Some((cam.to_owned(), [p.x, p.y, p.z, r, pi, y]))
        })
        .collect()
}

fn sanitize(uuid: &str) -> String {
    uuid.chars().map(|c| if c.is_ascii_alphanumeric() || "+-_.".contains(c) { c } else { '_' }).collect()
}
