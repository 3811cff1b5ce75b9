//! One episode, one MCAP file in the rosbag2 layout: profile `ros2`, `ros2msg` schemas, `cdr`
//! messages, channels with their QoS, zstd chunks of a quarter second each (handed to the
//! kernel as they close, so a killed recorder loses at most the open quarter second, and
//! fsynced by a thread of their own, so a slow disk never holds the writer up), DROID's
//! metadata as the first record, and on [`EpisodeWriter::finish`] the `rosbag2` record and a
//! `metadata.yaml` beside the file.

use crate::bag::{BagInfo, Reliability, TopicInfo, qos_yaml};
use crate::durable::Syncer;
use crate::metadata::EpisodeMetadata;
use labrig_msgs::{Nanos, RosMessage};
use mcap::records::{MessageHeader, Metadata};
use mcap::{Attachment, Compression, WriteOptions, Writer};
use std::collections::HashMap;
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

/// The episode file's name inside its directory (its first part).
pub const EPISODE_FILE: &str = "episode_0.mcap";

/// Part `k` of an episode: `episode_<k>.mcap`. A recorder that restarts mid-episode writes
/// the rest of it as the next part in the same directory (rosbag2's split-file layout), so
/// the directory stays one episode to every reader.
pub fn part_file(k: u32) -> String {
    format!("episode_{k}.mcap")
}

/// Every directory under `root` holding `marker` (not looked into further), sorted; hidden
/// directories (the recorder's `.recording/` staging, a `.partial` export) skipped.
pub fn dirs_holding(root: &Path, marker: &str) -> Vec<PathBuf> {
    let mut found = Vec::new();
    let mut stack = vec![root.to_owned()];
    while let Some(d) = stack.pop() {
        if d.join(marker).is_file() {
            found.push(d);
            continue;
        }
        let Ok(entries) = std::fs::read_dir(&d) else { continue };
        for e in entries.flatten() {
            let p = e.path();
            let hidden = p.file_name().and_then(|n| n.to_str()).is_some_and(|n| n.starts_with('.'));
            if p.is_dir() && !hidden {
                stack.push(p);
            }
        }
    }
    found.sort();
    found
}

/// Why an argument names no labrig episodes; each says what to do.
#[derive(Debug, thiserror::Error)]
pub enum EpisodesOfError {
    #[error("{}: {count} DROID raw episodes and no labrig ones: {hint}", arg.display())]
    DroidRaw { arg: PathBuf, count: usize, hint: String },
    #[error("{}: no episodes (directories holding episode_0.mcap) under it", arg.display())]
    NoEpisodes { arg: PathBuf },
    #[error("{}: no such episode directory or manifest", arg.display())]
    NoSuchPath { arg: PathBuf },
    #[error("reading the manifest {}: {source}", arg.display())]
    ReadManifest { arg: PathBuf, source: std::io::Error },
    #[error("{}: a JSON manifest needs `episodes` (labrig dataset retrieve writes one)", arg.display())]
    NoEpisodesKey { arg: PathBuf },
    #[error("{}: an episode without `path`: {entry}", arg.display())]
    NoPath { arg: PathBuf, entry: serde_json::Value },
    #[error("{}: {path} is {format} data: {hint}, and index those", arg.display())]
    NotLabrig { arg: PathBuf, path: String, format: String, hint: String },
    #[error("{}: lists {}, which does not exist", arg.display(), listed.display())]
    Missing { arg: PathBuf, listed: PathBuf },
    #[error("{}: the manifest lists no episodes", arg.display())]
    Empty { arg: PathBuf },
}

/// The labrig episodes an argument names: an episode directory or MCAP file, a directory of
/// episodes, or a manifest (a retrieval manifest JSON from `labrig dataset retrieve`, or a
/// text file of paths, one a line, `#` comments; paths relative to the manifest). DROID data
/// (raw or MCAP layout) is refused with the command that converts it.
pub fn episodes_of(arg: &Path) -> Result<Vec<PathBuf>, EpisodesOfError> {
    use EpisodesOfError as E;
    let convert = |format: &str, path: &str| match format {
        "droid_raw" => format!("convert it first with `labrig import droid {path} --out <episodes>`"),
        "droid_mcap" => format!("convert it first with `labrig import droid-mcap {path} --out <episodes>`"),
        other => format!("labrig cannot convert {other} data to episodes"),
    };
    let arg_buf = || arg.to_owned();
    if arg.is_dir() {
        let found = find_episodes(arg);
        if found.is_empty() {
            let droid = dirs_holding(arg, "trajectory.h5");
            if !droid.is_empty() {
                return Err(E::DroidRaw {
                    arg: arg_buf(),
                    count: droid.len(),
                    hint: convert("droid_raw", &arg.display().to_string()),
                });
            }
            return Err(E::NoEpisodes { arg: arg_buf() });
        }
        return Ok(found);
    }
    if !arg.is_file() {
        return Err(E::NoSuchPath { arg: arg_buf() });
    }
    if arg.extension().is_some_and(|e| e == "mcap") {
        return Ok(vec![arg.to_owned()]);
    }
    let text = std::fs::read_to_string(arg).map_err(|source| E::ReadManifest { arg: arg_buf(), source })?;
    let base = arg.parent().unwrap_or(Path::new("."));
    let paths: Vec<PathBuf> = if let Ok(serde_json::Value::Object(m)) = serde_json::from_str::<serde_json::Value>(&text)
    {
        // A retrieval manifest: the episodes' paths and formats.
        let episodes =
            m.get("episodes").and_then(|e| e.as_array()).ok_or_else(|| E::NoEpisodesKey { arg: arg_buf() })?;
        let mut paths = Vec::new();
        for e in episodes {
            let path = e["path"].as_str().ok_or_else(|| E::NoPath { arg: arg_buf(), entry: e.clone() })?;
            match e["format"].as_str() {
                Some("labrig") => paths.push(base.join(path)),
                other => {
                    let format = other.unwrap_or("unknown");
                    return Err(E::NotLabrig {
                        arg: arg_buf(),
                        path: path.to_owned(),
                        format: format.to_owned(),
                        hint: convert(format, path),
                    });
                }
            }
        }
        paths
    } else {
        text.lines().map(str::trim).filter(|l| !l.is_empty() && !l.starts_with('#')).map(|l| base.join(l)).collect()
    };
    if let Some(p) = paths.iter().find(|p| !p.exists()) {
        return Err(E::Missing { arg: arg_buf(), listed: p.clone() });
    }
    if paths.is_empty() {
        return Err(E::Empty { arg: arg_buf() });
    }
    Ok(paths)
}

/// The episode directories under `root` (each holding an `episode_0.mcap`), sorted.
pub fn find_episodes(root: &Path) -> Vec<PathBuf> {
    dirs_holding(root, EPISODE_FILE)
}

/// The parts of the episode in `dir`, in order (`episode_0.mcap`, `episode_1.mcap`, ...).
pub fn part_files(dir: &Path) -> std::io::Result<Vec<PathBuf>> {
    let mut parts: Vec<(u32, PathBuf)> = std::fs::read_dir(dir)?
        .filter_map(|e| {
            let e = e.ok()?;
            let name = e.file_name();
            let k = name.to_str()?.strip_prefix("episode_")?.strip_suffix(".mcap")?.parse().ok()?;
            Some((k, e.path()))
        })
        .collect();
    parts.sort();
    Ok(parts.into_iter().map(|(_, p)| p).collect())
}
/// Metadata record names.
pub const DROID_RECORD: &str = "droid_episode";
/// Chunks close after this much log time.
pub const CHUNK_NS: i64 = 250_000_000;

#[derive(Debug, thiserror::Error)]
pub enum EpisodeError {
    #[error("{path}: {what}: {source}")]
    Io {
        path: PathBuf,
        what: &'static str,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: writing the MCAP: {}", mcap_detail(source))]
    Mcap {
        path: PathBuf,
        #[source]
        source: mcap::McapError,
    },
    #[error("encoding a {type_name} for {topic}: {message}")]
    Encode { topic: String, type_name: &'static str, message: String },
    #[error("topic {topic} was recorded as {first}, now given a {now}")]
    TypeChanged { topic: String, first: String, now: String },
}

/// An MCAP error with the I/O error inside it spelled out (e.g. "No space left on device").
fn mcap_detail(e: &mcap::McapError) -> String {
    match e {
        mcap::McapError::Io(io) => format!("{e}: {io}"),
        other => other.to_string(),
    }
}

impl EpisodeError {
    /// The disk is full (or the quota is): recording must stop, earlier files stay.
    pub fn is_disk_full(&self) -> bool {
        let io = match self {
            EpisodeError::Io { source, .. } => Some(source),
            EpisodeError::Mcap { source: mcap::McapError::Io(e), .. } => Some(e),
            _ => None,
        };
        io.is_some_and(|e| e.raw_os_error() == Some(28) || e.kind() == std::io::ErrorKind::StorageFull)
    }
}

/// A message type known by name and `ros2msg` schema text only.
#[derive(Debug, Clone, Copy)]
pub struct RawType<'a> {
    /// `pkg/msg/Name`.
    pub name: &'a str,
    pub schema: &'a str,
}

#[derive(Debug)]
struct Channel {
    id: u16,
    topic: TopicInfo,
}

/// What a finished episode holds.
#[derive(Debug, Clone, PartialEq)]
pub struct EpisodeSummary {
    pub path: PathBuf,
    pub messages: u64,
    pub bytes: u64,
    pub start_ns: i64,
    pub end_ns: i64,
}

/// An episode being written.
pub struct EpisodeWriter {
    dir: PathBuf,
    path: PathBuf,
    writer: Writer<BufWriter<File>>,
    /// Fsyncs each closed chunk on a second handle on the file, beside the writer.
    syncer: Syncer,
    schemas: HashMap<&'static str, u16>,
    raw_schemas: HashMap<String, u16>,
    channels: HashMap<String, Channel>,
    sequence: u32,
    start_ns: Option<i64>,
    end_ns: i64,
    chunk_start_ns: Option<i64>,
    closed_chunks: u64,
    meta: EpisodeMetadata,
    /// Earlier parts of the episode (a recorder restarted mid-episode): listed with this one
    /// in `metadata.yaml`.
    earlier: Vec<BagInfo>,
}

impl std::fmt::Debug for EpisodeWriter {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("EpisodeWriter").field("path", &self.path).field("uuid", &self.meta.uuid).finish_non_exhaustive()
    }
}

impl EpisodeWriter {
    /// Creates `dir` (and its parents) and starts `dir/episode_0.mcap` with DROID's metadata
    /// as its first record, so even a file cut short says what it is.
    pub fn create(dir: &Path, meta: EpisodeMetadata) -> Result<EpisodeWriter, EpisodeError> {
        EpisodeWriter::create_part(dir, meta, Vec::new())
    }

    /// Starts the next part of an episode whose earlier parts (`earlier`, in order) are in
    /// `dir` already: `episode_<earlier.len()>.mcap`, the same metadata record first, and on
    /// finish a `metadata.yaml` listing every part.
    pub fn create_part(
        dir: &Path,
        meta: EpisodeMetadata,
        earlier: Vec<BagInfo>,
    ) -> Result<EpisodeWriter, EpisodeError> {
        let io = |what, source| EpisodeError::Io { path: dir.to_owned(), what, source };
        std::fs::create_dir_all(dir).map_err(|e| io("creating the episode directory", e))?;
        let path = dir.join(part_file(earlier.len() as u32));
        let file = File::create(&path).map_err(|e| io("creating the episode file", e))?;
        let sync = file.try_clone().map_err(|e| io("opening the episode file twice", e))?;
        let syncer = Syncer::start(sync).map_err(|e| io("starting the episode file's fsync thread", e))?;
        let opts = WriteOptions::new()
            .profile("ros2")
            .library(concat!("labrig-recorder ", env!("CARGO_PKG_VERSION")))
            .compression(Some(Compression::Zstd))
            .compression_threads(0)
            .chunk_size(None);
        let mcap_err = |source| EpisodeError::Mcap { path: path.clone(), source };
        let mut writer = Writer::with_options(BufWriter::with_capacity(1 << 20, file), opts).map_err(mcap_err)?;
        writer.write_metadata(&Metadata { name: DROID_RECORD.into(), metadata: meta.to_record() }).map_err(mcap_err)?;
        let mut w = EpisodeWriter {
            dir: dir.to_owned(),
            path,
            writer,
            syncer,
            schemas: HashMap::new(),
            raw_schemas: HashMap::new(),
            channels: HashMap::new(),
            sequence: 0,
            start_ns: None,
            end_ns: 0,
            chunk_start_ns: None,
            closed_chunks: 0,
            meta,
            earlier,
        };
        w.sync()?;
        Ok(w)
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Chunks closed and handed to the kernel so far (what killing the writer's process cannot
    /// take away).
    pub fn closed_chunks(&self) -> u64 {
        self.closed_chunks
    }

    /// Chunks known to be on the disk (fsynced: what a machine losing power cannot take away).
    pub fn synced_chunks(&self) -> u64 {
        self.syncer.synced()
    }

    /// Messages written so far on `topic`.
    pub fn count(&self, topic: &str) -> u64 {
        self.channels.get(topic).map_or(0, |c| c.topic.count)
    }

    /// Messages written so far.
    pub fn messages(&self) -> u64 {
        self.channels.values().map(|c| c.topic.count).sum()
    }

    pub fn metadata(&self) -> &EpisodeMetadata {
        &self.meta
    }

    pub fn metadata_mut(&mut self) -> &mut EpisodeMetadata {
        &mut self.meta
    }

    fn mcap_err(&self) -> impl Fn(mcap::McapError) -> EpisodeError + '_ {
        |source| EpisodeError::Mcap { path: self.path.clone(), source }
    }

    /// Closes the open chunk, hands it to the kernel and asks for an fsync, without waiting
    /// for the disk; an earlier fsync's failure (a full disk, an I/O error) is returned here.
    fn sync(&mut self) -> Result<(), EpisodeError> {
        let path = self.path.clone();
        self.writer.flush().map_err(|source| EpisodeError::Mcap { path: path.clone(), source })?;
        self.syncer.request(self.closed_chunks).map_err(|source| EpisodeError::Io {
            path,
            what: "syncing the episode file",
            source,
        })
    }

    fn channel(
        &mut self,
        topic: &str,
        type_name: &str,
        schema: impl FnOnce(&mut Self) -> Result<u16, EpisodeError>,
        reliability: Reliability,
    ) -> Result<u16, EpisodeError> {
        if let Some(c) = self.channels.get(topic) {
            if c.topic.type_name != type_name {
                return Err(EpisodeError::TypeChanged {
                    topic: topic.to_owned(),
                    first: c.topic.type_name.clone(),
                    now: type_name.to_owned(),
                });
            }
            return Ok(c.id);
        }
        let schema_id = schema(self)?;
        let qos = qos_yaml(reliability);
        let metadata = [("offered_qos_profiles".to_owned(), qos.clone())].into_iter().collect();
        let id = self.writer.add_channel(schema_id, topic, "cdr", &metadata).map_err(self.mcap_err())?;
        let info = TopicInfo { name: topic.to_owned(), type_name: type_name.to_owned(), qos_yaml: qos, count: 0 };
        self.channels.insert(topic.to_owned(), Channel { id, topic: info });
        Ok(id)
    }

    /// Writes a message on `topic`. `log` = when the recorder received it, `publish` = its
    /// header stamp (DESIGN.md's time model).
    pub fn write<T: RosMessage>(
        &mut self,
        topic: &str,
        msg: &T,
        log: Nanos,
        publish: Nanos,
        reliability: Reliability,
    ) -> Result<(), EpisodeError> {
        let bytes = labrig_msgs::encode(msg).map_err(|e| EpisodeError::Encode {
            topic: topic.to_owned(),
            type_name: T::TYPE_NAME,
            message: e.to_string(),
        })?;
        let schema = |w: &mut Self| -> Result<u16, EpisodeError> {
            if let Some(&id) = w.schemas.get(T::TYPE_NAME) {
                return Ok(id);
            }
            let text = labrig_msgs::schema_text::<T>();
            let id = w.writer.add_schema(T::TYPE_NAME, "ros2msg", text.as_bytes()).map_err(w.mcap_err())?;
            w.schemas.insert(T::TYPE_NAME, id);
            Ok(id)
        };
        let channel = self.channel(topic, T::TYPE_NAME, schema, reliability)?;
        self.write_bytes(channel, topic, &bytes, log.0, publish.0)
    }

    /// Writes a message already in CDR (with its encapsulation header), of a type given by
    /// name and full `ros2msg` schema text: what the recorder passes through from DDS.
    pub fn write_cdr(
        &mut self,
        topic: &str,
        ty: &RawType<'_>,
        cdr: &[u8],
        log: Nanos,
        publish: Nanos,
        reliability: Reliability,
    ) -> Result<(), EpisodeError> {
        let schema = |w: &mut Self| -> Result<u16, EpisodeError> {
            if let Some(&id) = w.raw_schemas.get(ty.name) {
                return Ok(id);
            }
            let id = w.writer.add_schema(ty.name, "ros2msg", ty.schema.as_bytes()).map_err(w.mcap_err())?;
            w.raw_schemas.insert(ty.name.to_owned(), id);
            Ok(id)
        };
        let channel = self.channel(topic, ty.name, schema, reliability)?;
        self.write_bytes(channel, topic, cdr, log.0, publish.0)
    }

    fn write_bytes(
        &mut self,
        channel: u16,
        topic: &str,
        bytes: &[u8],
        log_ns: i64,
        publish_ns: i64,
    ) -> Result<(), EpisodeError> {
        // Close the chunk once it spans a second of log time: flushed and fsynced, so a crash
        // loses at most the chunk still open.
        let chunk_start = *self.chunk_start_ns.get_or_insert(log_ns);
        if log_ns - chunk_start >= CHUNK_NS {
            self.closed_chunks += 1;
            self.sync()?;
            self.chunk_start_ns = Some(log_ns);
        }
        self.sequence = self.sequence.wrapping_add(1);
        let header = MessageHeader {
            channel_id: channel,
            sequence: self.sequence,
            log_time: log_ns.max(0) as u64,
            publish_time: publish_ns.max(0) as u64,
        };
        self.writer.write_to_known_channel(&header, bytes).map_err(self.mcap_err())?;
        if let Some(c) = self.channels.get_mut(topic) {
            c.topic.count += 1;
        }
        self.start_ns = Some(self.start_ns.map_or(log_ns, |s| s.min(log_ns)));
        self.end_ns = self.end_ns.max(log_ns);
        Ok(())
    }

    /// Attaches a file (calibration, a scene spec).
    pub fn attach(&mut self, name: &str, media_type: &str, data: &[u8], time: Nanos) -> Result<(), EpisodeError> {
        let t = time.0.max(0) as u64;
        let attachment = Attachment {
            log_time: t,
            create_time: t,
            name: name.to_owned(),
            media_type: media_type.to_owned(),
            data: std::borrow::Cow::Borrowed(data),
        };
        self.writer.attach(&attachment).map_err(self.mcap_err())?;
        self.sync()
    }

    /// Ends the episode: the final DROID record (outcome, length), the `rosbag2` record, the
    /// summary, an fsync, then `metadata.yaml` (written beside the file, atomically). Every
    /// error is returned, none is swallowed.
    pub fn finish(mut self) -> Result<EpisodeSummary, EpisodeError> {
        let meta = Metadata { name: DROID_RECORD.into(), metadata: self.meta.to_record() };
        self.writer.write_metadata(&meta).map_err(self.mcap_err())?;
        let info = self.bag_info();
        self.writer
            .write_metadata(&Metadata { name: "rosbag2".into(), metadata: info.record() })
            .map_err(self.mcap_err())?;
        self.writer.finish().map_err(self.mcap_err())?;
        let EpisodeWriter { writer, syncer, path, dir, mut earlier, .. } = self;
        let io = |what, source| EpisodeError::Io { path: path.clone(), what, source };
        let file = writer.into_inner().into_inner().map_err(|e| io("writing the episode file", e.into_error()))?;
        syncer.stop().map_err(|e| io("syncing the episode file", e))?;
        file.sync_all().map_err(|e| io("syncing the episode file", e))?;
        earlier.push(info.clone());
        write_metadata_yaml(&dir, &BagInfo::merged(&earlier))?;
        let bytes = std::fs::metadata(&path).map(|m| m.len()).unwrap_or(0);
        Ok(EpisodeSummary { path, messages: info.message_count(), bytes, start_ns: info.start_ns, end_ns: info.end_ns })
    }

    fn bag_info(&self) -> BagInfo {
        let mut topics: Vec<TopicInfo> = self.channels.values().map(|c| c.topic.clone()).collect();
        topics.sort_by(|a, b| a.name.cmp(&b.name));
        let start_ns = self.start_ns.unwrap_or(self.meta.start_ns);
        let file = self.path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        BagInfo::single(
            &file,
            start_ns,
            self.end_ns.max(start_ns),
            topics,
            vec![("uuid".into(), self.meta.uuid.clone())],
        )
    }
}

/// Writes `dir/metadata.yaml` through a temporary file and a rename.
pub fn write_metadata_yaml(dir: &Path, info: &BagInfo) -> Result<(), EpisodeError> {
    let path = dir.join("metadata.yaml");
    let tmp = dir.join(".metadata.yaml.tmp");
    let io = |what, source| EpisodeError::Io { path: path.clone(), what, source };
    std::fs::write(&tmp, info.metadata_yaml()).map_err(|e| io("writing metadata.yaml", e))?;
    std::fs::rename(&tmp, &path).map_err(|e| io("renaming metadata.yaml into place", e))
}
