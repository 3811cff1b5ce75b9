//! `labrig inspect`: what an episode holds and how well it was recorded — duration, per-topic
//! counts and rates, messages that do not decode or arrive out of order, dropped and late
//! camera frames, the camera skew of each step, the control loop's period and jitter, and
//! DROID's metadata. Reads damaged (unfinished) files too, up to their damage.

use crate::metadata::EpisodeMetadata;
use labrig_msgs::rig::Step;
use labrig_msgs::sensor_msgs::{CameraInfo, CompressedImage};
use labrig_msgs::topics;
use labrig_msgs::{TypeVisitor, visit_type};
use mcap::read::{LinearReader, Options};
use mcap::records::Record;
use serde::Serialize;
use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};

/// The rig's control period.
pub const CONTROL_PERIOD_NS: i64 = 50_000_000;

#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct Percentiles {
    pub p50: f64,
    pub p99: f64,
    pub max: f64,
    pub n: usize,
}

impl Percentiles {
    /// The percentiles of `v` (nearest rank); none of an empty set.
    pub fn of(mut v: Vec<f64>) -> Option<Percentiles> {
        if v.is_empty() {
            return None;
        }
        v.sort_by(f64::total_cmp);
        let p = |q: f64| v[((v.len() - 1) as f64 * q).round() as usize];
        Some(Percentiles { p50: p(0.5), p99: p(0.99), max: p(1.0), n: v.len() })
    }
}

#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct TopicStats {
    pub topic: String,
    pub type_name: String,
    pub count: u64,
    /// Messages per second of the episode's own time ([`Inspection::clock`]; the receive times'
    /// span for a file without steps).
    pub rate_hz: f64,
    /// Messages that do not decode as their type.
    pub malformed: u64,
    /// Messages whose log time is earlier than the previous one's on the topic.
    pub out_of_order: u64,
    /// The newest publish time on the topic (ns) as the file stores it: for camera images
    /// their capture time on the rig's clock (sim time in the sim); for the other topics their
    /// DDS source time (the publisher's wall clock).
    pub last_publish_ns: i64,
}

#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct CameraStats {
    pub camera: String,
    pub frames: u64,
    /// Frames missing between consecutive stamps (gaps longer than 1.5 periods).
    pub dropped: u64,
    /// Steps whose frame from this camera was captured more than one period before the step.
    pub late: u64,
    /// Steps that name no frame of this camera (a tick before its first frame came).
    pub steps_without_frame: u64,
    /// Steps that name a frame of this camera which the file does not hold...
    pub frames_missing: u64,
    /// ...their `step_index`es (the first ten), to tell an episode's first or last step from
    /// one in the middle.
    pub frames_missing_steps: Vec<u64>,
    /// Frames captured before the sim's scene was set (`sim_scene.since_ns`): another scene's,
    /// so another episode's.
    pub frames_before_scene: u64,
    /// What the images are, from the camera's recorded camera_info: `rectified` (a stereo eye
    /// rectified: no distortion, a rectifying rotation R), `distorted` (raw, with the lens's
    /// distortion coefficients), `pinhole` (no distortion, no rectification), `uncalibrated`
    /// (K all zero), or `unknown` (no camera_info recorded).
    pub image: &'static str,
}

/// What a camera_info says the images are (see [`CameraStats::image`]).
pub fn image_model(info: &CameraInfo) -> &'static str {
    let identity = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];
    if info.k.iter().all(|&v| v == 0.0) {
        "uncalibrated"
    } else if info.d.iter().any(|&v| v != 0.0) {
        "distorted"
    } else if info.r.iter().zip(identity).any(|(a, b)| (a - b).abs() > 1e-12) {
        "rectified"
    } else {
        "pinhole"
    }
}

#[derive(Debug, Clone, Serialize)]
pub struct Inspection {
    pub path: PathBuf,
    /// The file has its summary and footer (the recorder finished it).
    pub complete: bool,
    /// What stopped the reading early, for a damaged file.
    pub damage: Option<String>,
    /// The file's first and last receive (log) times, wall clock.
    pub start_ns: i64,
    pub end_ns: i64,
    /// The episode's span in its own time (first to last step on the rig's clock, [`Self::clock`];
    /// the receive times' span for a file without steps).
    pub duration_s: f64,
    /// The receive times' span (wall clock): how long the recording took.
    pub wall_duration_s: f64,
    /// The clock of the steps and frames: `sim` (the simulator's time) or `wall`.
    pub clock: &'static str,
    pub messages: u64,
    pub topics: Vec<TopicStats>,
    pub steps: u64,
    /// Per step: the spread of the capture times of the frames it used (ms).
    pub camera_skew_ms: Option<Percentiles>,
    /// Step-to-step period (ms) and its deviation from 50 ms (ms).
    pub control_period_ms: Option<Percentiles>,
    pub control_jitter_ms: Option<Percentiles>,
    /// Steps more than 1.5 periods after the previous one.
    pub missed_ticks: u64,
    pub cameras: Vec<CameraStats>,
    pub metadata: Option<EpisodeMetadata>,
    /// What is wrong, for the operator; empty for a good episode.
    pub flags: Vec<String>,
    /// The episode's files (more than one after a recorder restart) and the gaps between them.
    pub parts: Vec<Part>,
    pub gaps: Vec<Gap>,
    /// A policy's rollout (any step by the policy): who acted, per step.
    pub sources: Option<StepSources>,
}

/// Who acted in a policy's rollout, from the steps' `action_source`: the policy, or an
/// operator who took over (the Quest: teleop; the sim's expert: scripted).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct StepSources {
    pub policy_steps: u64,
    pub operator_steps: u64,
    pub takeovers: u64,
    /// Each run of operator steps.
    pub takeover_segments: Vec<TakeoverSegment>,
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TakeoverSegment {
    /// The first operator step's `step_index`, and how many steps the run has.
    pub start_step: u64,
    pub steps: u64,
    /// Its `action_source` by name (`teleop`, `scripted`).
    pub source: String,
}

/// [`StepSources`] of steps sorted by `step_index`; None unless the policy acted in any.
pub fn step_sources(steps: &[Step]) -> Option<StepSources> {
    if !steps.iter().any(|s| s.action_source == Step::SOURCE_POLICY) {
        return None;
    }
    let mut out = StepSources { policy_steps: 0, operator_steps: 0, takeovers: 0, takeover_segments: vec![] };
    let mut acting = false;
    for s in steps {
        let operator = Step::is_operator(s.action_source);
        out.policy_steps += u64::from(s.action_source == Step::SOURCE_POLICY);
        if operator {
            out.operator_steps += 1;
            match out.takeover_segments.last_mut() {
                Some(seg) if acting => seg.steps += 1,
                _ => out.takeover_segments.push(TakeoverSegment {
                    start_step: s.step_index,
                    steps: 1,
                    source: match s.action_source {
                        Step::SOURCE_TELEOP => "teleop",
                        Step::SOURCE_SCRIPTED => "scripted",
                        Step::SOURCE_REPLAY => "replay",
                        _ => "other",
                    }
                    .into(),
                }),
            }
        }
        acting = operator;
    }
    out.takeovers = out.takeover_segments.len() as u64;
    Some(out)
}

struct Decodes<'a>(&'a [u8]);
impl TypeVisitor for Decodes<'_> {
    type Output = bool;
    fn visit<T: labrig_msgs::RosMessage>(self) -> bool {
        labrig_msgs::decode::<T>(self.0).is_ok()
    }
}

#[derive(Default)]
struct Topic {
    type_name: String,
    count: u64,
    malformed: u64,
    out_of_order: u64,
    last_log: Option<u64>,
    first: u64,
    last: u64,
    /// The newest publish time (what a recorder rejoining the episode continues after).
    last_publish: u64,
    stamps: Vec<i64>,
    /// A camera_info topic's first message's [`image_model`].
    image: Option<&'static str>,
}

/// An episode file that cannot be read at all (damage after a readable start is reported in
/// the [`Inspection`], not here).
#[derive(Debug, thiserror::Error)]
pub enum ReadError {
    #[error("{}: {source}", file.display())]
    Io {
        file: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{}: not an MCAP file ({reason})", file.display())]
    NotMcap { file: PathBuf, reason: String },
    #[error("{}: {source}", file.display())]
    Metadata {
        file: PathBuf,
        #[source]
        source: crate::metadata::MetadataError,
    },
}

/// Reads `path` (an episode file or its directory).
pub fn inspect(path: &Path) -> Result<Inspection, ReadError> {
    let scan = scan(path)?;
    Ok(summarise(scan))
}

/// What replay and export need of an episode: its steps in order and its metadata.
#[derive(Debug, Clone)]
pub struct EpisodeData {
    pub file: PathBuf,
    /// The file was finished (an unfinished one is read up to its damage).
    pub complete: bool,
    pub metadata: Option<EpisodeMetadata>,
    /// `/rig/step` records by step index.
    pub steps: Vec<Step>,
    /// Files the episode was recorded in (more than one after a recorder restart).
    pub parts: usize,
    /// What was lost between the parts.
    pub gaps: Vec<Gap>,
}

/// Reads an episode's steps and metadata (`path`: the episode file or its directory).
pub fn read_episode(path: &Path) -> Result<EpisodeData, ReadError> {
    let Scan { file, complete, mut steps, droid, parts, .. } = scan(path)?;
    steps.sort_by_key(|s| s.step_index);
    steps.dedup_by_key(|s| s.step_index);
    let gaps = gaps(&parts);
    let metadata = droid
        .as_ref()
        .map(EpisodeMetadata::from_record)
        .transpose()
        .map_err(|source| ReadError::Metadata { file: file.clone(), source })?;
    Ok(EpisodeData { file, complete, metadata, steps, parts: parts.len(), gaps })
}

struct Scan {
    file: PathBuf,
    complete: bool,
    damage: Option<String>,
    topics: BTreeMap<String, Topic>,
    steps: Vec<Step>,
    droid: Option<BTreeMap<String, String>>,
    parts: Vec<Part>,
}

/// One file of an episode (an episode recorded across a recorder restart has several).
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct Part {
    pub file: PathBuf,
    pub complete: bool,
    pub damage: Option<String>,
    pub messages: u64,
    /// Log time of its first and last message (0 when it has none).
    pub start_ns: i64,
    pub end_ns: i64,
    /// Step indices of its first and last `/rig/step`.
    pub first_step: Option<u64>,
    pub last_step: Option<u64>,
}

/// The time between two parts of an episode, and the steps it lost.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct Gap {
    /// The gap is between part `after` and part `after + 1`.
    pub after: usize,
    pub seconds: f64,
    /// Step indices missing between the parts' last and first steps.
    pub steps_missing: u64,
}

fn gaps(parts: &[Part]) -> Vec<Gap> {
    parts
        .windows(2)
        .enumerate()
        .map(|(k, w)| {
            let seconds = if w[0].messages > 0 && w[1].messages > 0 {
                w[1].start_ns.saturating_sub(w[0].end_ns).max(0) as f64 / 1e9
            } else {
                0.0
            };
            let steps_missing = match (w[0].last_step, w[1].first_step) {
                (Some(a), Some(b)) => b.saturating_sub(a.saturating_add(1)),
                _ => 0,
            };
            Gap { after: k, seconds, steps_missing }
        })
        .collect()
}

/// The files of the episode at `path`: its parts in order for a directory, else the file.
fn files_of(path: &Path) -> Result<Vec<PathBuf>, ReadError> {
    if !path.is_dir() {
        return Ok(vec![path.to_owned()]);
    }
    let first = path.join(crate::episode::EPISODE_FILE);
    match crate::episode::part_files(path) {
        Ok(files) if !files.is_empty() => Ok(files),
        Ok(_) => Err(ReadError::Io {
            file: first,
            source: std::io::Error::new(std::io::ErrorKind::NotFound, "no episode file in the directory"),
        }),
        Err(source) => Err(ReadError::Io { file: path.to_owned(), source }),
    }
}

/// One pass over every record of the episode's files (chunks included), each up to its
/// first damage.
fn scan(path: &Path) -> Result<Scan, ReadError> {
    let files = files_of(path)?;
    let mut topics: BTreeMap<String, Topic> = BTreeMap::new();
    let mut steps: Vec<Step> = Vec::new();
    let mut droid = None;
    let mut parts = Vec::new();
    for file in &files {
        let steps_before = steps.len();
        let mut part = scan_file(file, &mut topics, &mut steps, &mut droid)?;
        let indices = steps[steps_before..].iter().map(|s| s.step_index);
        part.first_step = indices.clone().min();
        part.last_step = indices.max();
        parts.push(part);
    }
    // A relabelled episode's judged flag (judged.json) over the recording's.
    if let (Some(record), Some(j)) = (droid.as_mut(), files[0].parent().and_then(crate::judge::judged)) {
        record.insert("success".into(), j.success.to_string());
    }
    Ok(Scan {
        file: files[0].clone(),
        complete: parts.iter().all(|p| p.complete),
        damage: parts.iter().find_map(|p| p.damage.clone()),
        topics,
        steps,
        droid,
        parts,
    })
}

fn scan_file(
    file: &Path,
    topics: &mut BTreeMap<String, Topic>,
    steps: &mut Vec<Step>,
    droid: &mut Option<BTreeMap<String, String>>,
) -> Result<Part, ReadError> {
    let buf = match std::fs::read(file) {
        Ok(buf) => buf,
        Err(source) => return Err(ReadError::Io { file: file.to_owned(), source }),
    };
    if !buf.starts_with(mcap::MAGIC) {
        return Err(ReadError::NotMcap {
            file: file.to_owned(),
            reason: "it does not start with MCAP's magic bytes".into(),
        });
    }
    let complete = mcap::Summary::read(&buf).ok().flatten().is_some();
    let reader = match LinearReader::new_with_options(&buf, Options::IgnoreEndMagic.into()) {
        Ok(r) => r,
        Err(e) => return Err(ReadError::NotMcap { file: file.to_owned(), reason: e.to_string() }),
    };
    let mut schemas: HashMap<u16, String> = HashMap::new();
    let mut channels: HashMap<u16, (String, String)> = HashMap::new();
    let mut damage = None;
    let (mut messages, mut start_ns, mut end_ns) = (0u64, i64::MAX, 0i64);
    let mut on_record = |rec: Record<'_>| match rec {
        Record::Schema { header, .. } => {
            schemas.insert(header.id, header.name);
        }
        Record::Channel(c) => {
            let ty = schemas.get(&c.schema_id).cloned().unwrap_or_default();
            channels.insert(c.id, (c.topic, ty));
        }
        Record::Metadata(m) if m.name == crate::episode::DROID_RECORD => *droid = Some(m.metadata),
        Record::Message { header, data } => {
            let Some((topic, ty)) = channels.get(&header.channel_id) else { return };
            messages += 1;
            start_ns = start_ns.min(crate::log_ns(header.log_time));
            end_ns = end_ns.max(crate::log_ns(header.log_time));
            let t = topics.entry(topic.clone()).or_default();
            t.type_name.clone_from(ty);
            t.count += 1;
            if t.count == 1 {
                t.first = header.log_time;
            }
            t.last = t.last.max(header.log_time);
            t.last_publish = t.last_publish.max(header.publish_time);
            if t.last_log.is_some_and(|l| header.log_time < l) {
                t.out_of_order += 1;
            }
            t.last_log = Some(header.log_time);
            let ok = match ty.as_str() {
                "labrig_msgs/msg/Step" => match labrig_msgs::decode::<Step>(&data) {
                    Ok(s) => {
                        steps.push(s);
                        true
                    }
                    Err(_) => false,
                },
                "sensor_msgs/msg/CameraInfo" => match labrig_msgs::decode::<CameraInfo>(&data) {
                    Ok(info) => {
                        t.image.get_or_insert(image_model(&info));
                        true
                    }
                    Err(_) => false,
                },
                "sensor_msgs/msg/CompressedImage" => match labrig_msgs::decode::<CompressedImage>(&data) {
                    Ok(img) => {
                        t.stamps.push(labrig_msgs::Nanos::from(img.header.stamp).0);
                        !img.data.is_empty()
                    }
                    Err(_) => false,
                },
                other => visit_type(other, Decodes(&data)).unwrap_or(true),
            };
            if !ok {
                t.malformed += 1;
            }
        }
        _ => {}
    };
    for rec in reader {
        match rec {
            Ok(Record::Chunk { header, data }) => match crate::chunk::chunk_records(&header, &data) {
                Ok(inner) => inner.into_iter().for_each(&mut on_record),
                Err(e) => damage = Some(format!("a damaged chunk: {e}")),
            },
            Ok(r) => on_record(r),
            Err(e) => {
                damage = Some(e.to_string());
                break;
            }
        }
        if damage.is_some() {
            break;
        }
    }
    if messages == 0 {
        start_ns = 0;
    }
    Ok(Part { file: file.to_owned(), complete, damage, messages, start_ns, end_ns, first_step: None, last_step: None })
}

/// The inspection of a scanned episode: its figures, and the flags that say what is wrong.
fn summarise(scan: Scan) -> Inspection {
    let Scan { file: path, complete, damage, topics, mut steps, droid, parts } = scan;
    let gaps = gaps(&parts);
    let start = crate::log_ns(topics.values().map(|t| t.first).min().unwrap_or(0));
    let end = crate::log_ns(topics.values().map(|t| t.last).max().unwrap_or(0));
    let wall_duration_s = end.saturating_sub(start).max(0) as f64 / 1e9;
    let metadata = droid.as_ref().and_then(|m| EpisodeMetadata::from_record(m).ok());
    let clock = if metadata.as_ref().is_some_and(|m| m.sim_scene.is_some()) { "sim" } else { "wall" };
    steps.sort_by_key(|s| s.step_index);
    steps.dedup_by_key(|s| s.step_index);
    let episode_s = episode_span_s(&steps);
    let duration_s = episode_s.unwrap_or(wall_duration_s);
    let topic_stats = topic_stats(&topics, episode_s);
    let timing = ControlTiming::of(&steps);
    let cameras = camera_stats(&topics, &steps, scene_since(metadata.as_ref()));
    let sources = step_sources(&steps);
    let mut flags = topic_flags(&topic_stats, &gaps);
    let span = steps.first().zip(steps.last()).map(|(a, b)| (a.step_index, b.step_index));
    flags.extend(camera_flags(&cameras, span));
    flags.extend(record_flags(&steps, timing.missed_ticks, &parts, &gaps, metadata.as_ref(), sources.as_ref()));
    Inspection {
        path,
        complete,
        damage,
        start_ns: start,
        end_ns: end,
        duration_s,
        wall_duration_s,
        clock,
        messages: topic_stats.iter().map(|t| t.count).sum(),
        topics: topic_stats,
        steps: steps.len() as u64,
        camera_skew_ms: Percentiles::of(timing.skew),
        control_period_ms: Percentiles::of(timing.periods),
        control_jitter_ms: Percentiles::of(timing.jitter),
        missed_ticks: timing.missed_ticks,
        cameras,
        metadata,
        flags,
        parts,
        gaps,
        sources,
    }
}

/// A step's time on the rig's clock: its start, or its stamp when the timing is not filled.
fn step_time(s: &Step) -> i64 {
    if s.timing.step_start != 0 { s.timing.step_start } else { labrig_msgs::Nanos::from(s.header.stamp).0 }
}

/// The episode's own time: its steps' span on the rig's clock (lockstep sim time runs at
/// whatever pace the machine allows, so receive times say nothing of it); None under two steps.
fn episode_span_s(steps: &[Step]) -> Option<f64> {
    match (steps.first(), steps.last()) {
        (Some(a), Some(b)) if steps.len() > 1 => Some(step_time(b).saturating_sub(step_time(a)) as f64 / 1e9),
        _ => None,
    }
}

/// Each topic's figures; rates over the episode's span (`episode_s`), else the topic's own.
fn topic_stats(topics: &BTreeMap<String, Topic>, episode_s: Option<f64>) -> Vec<TopicStats> {
    topics
        .iter()
        .map(|(name, t)| {
            let span = episode_s.unwrap_or((t.last - t.first) as f64 / 1e9);
            TopicStats {
                topic: name.clone(),
                type_name: t.type_name.clone(),
                count: t.count,
                rate_hz: if span > 0.0 { (t.count - 1) as f64 / span } else { 0.0 },
                malformed: t.malformed,
                out_of_order: t.out_of_order,
                last_publish_ns: crate::log_ns(t.last_publish),
            }
        })
        .collect()
}

/// The steps' timing: the cameras' skew per step, the control period and its jitter (ms),
/// and the ticks missed.
struct ControlTiming {
    skew: Vec<f64>,
    periods: Vec<f64>,
    jitter: Vec<f64>,
    /// Steps more than 1.5 periods after the previous one.
    missed_ticks: u64,
}

impl ControlTiming {
    fn of(steps: &[Step]) -> ControlTiming {
        let skew: Vec<f64> = steps
            .iter()
            .filter(|s| s.cameras.len() > 1)
            .map(|s| {
                let (lo, hi) =
                    s.cameras.iter().fold((i64::MAX, i64::MIN), |(a, b), c| (a.min(c.capture_ns), b.max(c.capture_ns)));
                hi.saturating_sub(lo) as f64 / 1e6
            })
            .collect();
        let periods: Vec<f64> =
            steps.windows(2).map(|w| step_time(&w[1]).saturating_sub(step_time(&w[0])) as f64 / 1e6).collect();
        let nominal = CONTROL_PERIOD_NS as f64 / 1e6;
        let missed_ticks = periods.iter().filter(|&&p| p > 1.5 * nominal).count() as u64;
        let jitter: Vec<f64> = periods.iter().map(|p| (p - nominal).abs()).collect();
        ControlTiming { skew, periods, jitter, missed_ticks }
    }
}

/// When the sim's scene was set (`sim_scene.since_ns`), if the metadata says.
fn scene_since(metadata: Option<&EpisodeMetadata>) -> Option<i64> {
    metadata
        .and_then(|m| m.sim_scene.as_deref())
        .and_then(|s| serde_json::from_str::<serde_json::Value>(s).ok())
        .and_then(|v| v["since_ns"].as_i64())
}

/// Cameras: frames and gaps per image topic; late frames from the steps' references.
fn camera_stats(topics: &BTreeMap<String, Topic>, steps: &[Step], scene_since: Option<i64>) -> Vec<CameraStats> {
    topics
        .iter()
        .filter(|(_, t)| t.type_name == "sensor_msgs/msg/CompressedImage")
        .map(|(name, t)| {
            let mut c = camera_stats_of(name, t, steps, scene_since);
            c.image = topics.get(&topics::camera_info(&c.camera)).and_then(|t| t.image).unwrap_or("unknown");
            c
        })
        .collect()
}

/// One image topic's camera figures.
fn camera_stats_of(name: &str, t: &Topic, steps: &[Step], scene_since: Option<i64>) -> CameraStats {
    let camera = name.trim_start_matches(topics::CAMERAS_PREFIX).split('/').next().unwrap_or(name).to_owned();
    let mut stamps = t.stamps.clone();
    stamps.sort_unstable();
    let dropped = stamps
        .windows(2)
        .map(|w| w[1] - w[0])
        .filter(|&g| g as f64 > 1.5 * CONTROL_PERIOD_NS as f64)
        .map(|g| (g as f64 / CONTROL_PERIOD_NS as f64).round() as u64 - 1)
        .sum();
    let late = steps
        .iter()
        .filter(|s| {
            s.cameras
                .iter()
                .any(|c| c.camera_id == camera && step_time(s).saturating_sub(c.capture_ns) > CONTROL_PERIOD_NS)
        })
        .count() as u64;
    let named = |s: &Step| s.cameras.iter().find(|c| c.camera_id == camera).map(|c| c.capture_ns);
    let steps_without_frame = steps.iter().filter(|s| named(s).is_none()).count() as u64;
    let missing: Vec<u64> = steps
        .iter()
        .filter(|s| named(s).is_some_and(|t| stamps.binary_search(&t).is_err()))
        .map(|s| s.step_index)
        .collect();
    let frames_missing = missing.len() as u64;
    let frames_missing_steps: Vec<u64> = missing.into_iter().take(10).collect();
    let frames_before_scene = scene_since.map_or(0, |since| stamps.iter().filter(|&&t| t < since).count() as u64);
    CameraStats {
        camera,
        frames: t.count,
        dropped,
        late,
        steps_without_frame,
        frames_missing,
        frames_missing_steps,
        frames_before_scene,
        image: "unknown",
    }
}

/// The topics' malformed and out-of-order messages, and the recorder restarts between parts.
fn topic_flags(topic_stats: &[TopicStats], gaps: &[Gap]) -> Vec<String> {
    let mut flags = Vec::new();
    for t in topic_stats {
        if t.malformed > 0 {
            flags.push(format!("{}: {} malformed messages", t.topic, t.malformed));
        }
        if t.out_of_order > 0 {
            flags.push(format!("{}: {} messages out of order", t.topic, t.out_of_order));
        }
    }
    for g in gaps {
        flags.push(format!(
            "recorded in parts: {:.2} s between part {} and part {} (a recorder restart), {} steps missing",
            g.seconds,
            g.after,
            g.after + 1,
            g.steps_missing
        ));
    }
    flags
}

/// No images at all, and each camera's dropped, missing and other-scene frames.
fn camera_flags(cameras: &[CameraStats], steps: Option<(u64, u64)>) -> Vec<String> {
    let mut flags = Vec::new();
    if cameras.iter().all(|c| c.frames == 0) {
        flags.push("no camera frames: the episode has no images".into());
    }
    for c in cameras {
        if c.dropped > 0 {
            flags.push(format!("camera {}: {} frames dropped", c.camera, c.dropped));
        }
        if c.frames_missing > 0 {
            let which: Vec<String> = c.frames_missing_steps.iter().map(u64::to_string).collect();
            let more = if c.frames_missing > c.frames_missing_steps.len() as u64 { ", ..." } else { "" };
            flags.push(format!(
                "camera {}: {} steps name a frame the file does not hold (step_index {}{more} of {})",
                c.camera,
                c.frames_missing,
                which.join(", "),
                steps.map_or_else(String::new, |(a, b)| format!("{a}..={b}"))
            ));
        }
        if c.frames_before_scene > 0 {
            flags.push(format!(
                "camera {}: {} frames captured before the episode's scene was set (another episode's)",
                c.camera, c.frames_before_scene
            ));
        }
    }
    flags
}

/// What is wrong with the record itself: no steps, missed ticks, unfinished files, no
/// metadata, a takeover count the steps do not show.
fn record_flags(
    steps: &[Step],
    missed_ticks: u64,
    parts: &[Part],
    gaps: &[Gap],
    metadata: Option<&EpisodeMetadata>,
    sources: Option<&StepSources>,
) -> Vec<String> {
    let mut flags = Vec::new();
    if steps.is_empty() {
        flags.push("no /rig/step records".into());
    }
    if missed_ticks > 0 {
        flags.push(format!("{missed_ticks} missed control ticks"));
    }
    for p in parts.iter().filter(|p| !p.complete) {
        flags.push(format!(
            "unfinished file {} (recorder stopped before finish): run `labrig recover` on its directory{}",
            p.file.display(),
            p.damage.as_ref().map_or(String::new(), |d| format!(" ({d})"))
        ));
    }
    if metadata.is_none() {
        flags.push("no DROID episode metadata".into());
    }
    // The recorder counts takeovers as the steps come; a restart loses its count (the
    // steps' own count here is the one to trust).
    if let (Some(src), Some(n)) = (sources, metadata.and_then(|m| m.takeovers))
        && n != src.takeovers
        && gaps.is_empty()
        && parts.len() <= 1
    {
        flags.push(format!("the metadata says {n} takeovers, the steps show {}", src.takeovers));
    }
    flags
}

impl Inspection {
    /// The text report.
    pub fn text(&self) -> String {
        use std::fmt::Write;
        let mut s = String::new();
        let _ = writeln!(s, "{}", self.path.display());
        if let Some(m) = &self.metadata {
            let _ = writeln!(
                s,
                "  episode {}  task {:?}  scene {}  success {}",
                m.uuid,
                m.task_instruction,
                m.scene_id,
                m.success.map_or("unknown".into(), |b| b.to_string())
            );
        }
        let _ = writeln!(
            s,
            "  {:.2} s of {} time ({:.2} s to record), {} messages, {} steps, file {}",
            self.duration_s,
            self.clock,
            self.wall_duration_s,
            self.messages,
            self.steps,
            if self.complete { "complete" } else { "UNFINISHED" }
        );
        let _ = writeln!(
            s,
            "  {:<40} {:<34} {:>7} {:>8} {:>9} {:>6}",
            "topic",
            "type",
            "count",
            format!("Hz ({})", self.clock),
            "malformed",
            "order"
        );
        for t in &self.topics {
            let _ = writeln!(
                s,
                "  {:<40} {:<34} {:>7} {:>8.1} {:>9} {:>6}",
                t.topic, t.type_name, t.count, t.rate_hz, t.malformed, t.out_of_order
            );
        }
        for c in &self.cameras {
            let _ = writeln!(
                s,
                "  camera {:<8} frames {:>6}  dropped {:>4}  late {:>4}  steps without a frame {:>3}  images {}",
                c.camera, c.frames, c.dropped, c.late, c.steps_without_frame, c.image
            );
        }
        let pct = |name: &str, p: &Option<Percentiles>| match p {
            Some(p) => {
                format!("  {name}: p50 {:.3} ms  p99 {:.3} ms  max {:.3} ms (n = {})\n", p.p50, p.p99, p.max, p.n)
            }
            None => format!("  {name}: -\n"),
        };
        s.push_str(&pct("camera skew per step", &self.camera_skew_ms));
        s.push_str(&pct("control period", &self.control_period_ms));
        s.push_str(&pct("control jitter", &self.control_jitter_ms));
        let _ = writeln!(s, "  missed ticks: {}", self.missed_ticks);
        if self.parts.len() > 1 {
            let _ = writeln!(s, "  recorded in {} parts", self.parts.len());
        }
        if let Some(r) = self.metadata.as_ref().and_then(|m| m.recovered.as_ref()) {
            let _ = writeln!(s, "  recovered: {r}");
        }
        if let Some(p) = self.metadata.as_ref().and_then(|m| m.policy.as_ref()) {
            let _ = writeln!(s, "  policy rollout: {p}");
        }
        if let Some(src) = &self.sources {
            let _ = writeln!(
                s,
                "  steps by the policy: {}, by an operator: {} in {} takeovers",
                src.policy_steps, src.operator_steps, src.takeovers
            );
            for seg in &src.takeover_segments {
                let _ = writeln!(s, "    takeover at step {} for {} steps ({})", seg.start_step, seg.steps, seg.source);
            }
        }
        if self.flags.is_empty() {
            s.push_str("  OK\n");
        }
        for f in &self.flags {
            let _ = writeln!(s, "  FLAG: {f}");
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn steps(sources: &[u8]) -> Vec<Step> {
        sources
            .iter()
            .enumerate()
            .map(|(i, &s)| Step { step_index: i as u64, action_source: s, ..Step::default() })
            .collect()
    }

    #[test]
    fn takeovers_are_the_runs_of_operator_steps_in_a_policy_rollout() {
        const P: u8 = Step::SOURCE_POLICY;
        const T: u8 = Step::SOURCE_TELEOP;
        const S: u8 = Step::SOURCE_SCRIPTED;
        let src = step_sources(&steps(&[P, P, T, T, T, P, S, S, P])).unwrap();
        assert_eq!((src.policy_steps, src.operator_steps, src.takeovers), (4, 5, 2));
        let segs: Vec<(u64, u64, &str)> =
            src.takeover_segments.iter().map(|s| (s.start_step, s.steps, s.source.as_str())).collect();
        assert_eq!(segs, vec![(2, 3, "teleop"), (6, 2, "scripted")]);
        // An operator from the first step on is a takeover too; a demo is no rollout.
        assert_eq!(step_sources(&steps(&[T, P])).unwrap().takeovers, 1);
        assert_eq!(step_sources(&steps(&[T, T, S])), None);
    }
}
