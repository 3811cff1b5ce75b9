//! Recovering an episode whose recorder died (SIGKILL, power loss): its MCAP has no summary or
//! footer and ends in a chunk that never closed. Every chunk that closed (at most a quarter second
//! of log time each) was fsynced whole; [`recover`] copies every complete chunk, metadata
//! record and attachment into a new, valid file and rebuilds the rosbag2 record from what it
//! copied. A chunk is copied only if every record in it parses. [`recover_in_place`] does it
//! for every unfinished part of an episode directory and rewrites its `metadata.yaml`.

use crate::bag::{BagInfo, TopicInfo};
use crate::episode::{EpisodeError, write_metadata_yaml};
use crate::metadata::EpisodeMetadata;
use mcap::read::{LinearReader, Options};
use mcap::records::Record;
use mcap::{Attachment, Compression, WriteOptions, Writer};
use std::collections::BTreeMap;
use std::fs::File;
use std::io::BufWriter;
use std::path::Path;

/// What a recovery copied.
#[derive(Debug, Clone, PartialEq)]
pub struct RecoverReport {
    pub messages: u64,
    pub chunks: u64,
    pub metadata: u64,
    pub attachments: u64,
    /// Log time of the first and last message copied.
    pub start_ns: i64,
    pub end_ns: i64,
    /// Why reading stopped: "complete file" or the damage found.
    pub stopped: String,
    /// The recovered file as rosbag2 describes it.
    pub info: BagInfo,
}

/// Copies what is complete in `input` into `output` (a new file).
pub fn recover(input: &Path, output: &Path) -> Result<RecoverReport, EpisodeError> {
    recover_with(input, output, None)
}

/// Changes to the episode's DROID metadata, written as the recovered file's final record
/// (the verdict that came after the recorder died, what was recovered).
pub type Amend<'a> = &'a dyn Fn(&mut EpisodeMetadata);

/// [`recover`], ending the file with the last DROID record found, changed by `amend`.
pub fn recover_with(input: &Path, output: &Path, amend: Option<Amend<'_>>) -> Result<RecoverReport, EpisodeError> {
    let io = |path: &Path, what, source| EpisodeError::Io { path: path.to_owned(), what, source };
    let buf = std::fs::read(input).map_err(|e| io(input, "reading the episode", e))?;
    let mcap_err = |source| EpisodeError::Mcap { path: output.to_owned(), source };
    let mut out: Option<Writer<BufWriter<File>>> = None;
    let mut schemas: BTreeMap<u16, String> = BTreeMap::new();
    let mut topics: BTreeMap<u16, TopicInfo> = BTreeMap::new();
    let mut droid: Option<BTreeMap<String, String>> = None;
    let mut report = RecoverReport {
        messages: 0,
        chunks: 0,
        metadata: 0,
        attachments: 0,
        start_ns: i64::MAX,
        end_ns: 0,
        stopped: "complete file".into(),
        info: BagInfo::single("", 0, 0, Vec::new(), Vec::new()),
    };
    let mut copy = |rec: Record<'_>, out: &mut Option<Writer<BufWriter<File>>>| -> Result<(), EpisodeError> {
        if let Record::Header(h) = &rec {
            let file = File::create(output).map_err(|e| io(output, "creating the recovered file", e))?;
            let opts = WriteOptions::new()
                .profile(h.profile.clone())
                .library(h.library.clone())
                .compression(Some(Compression::Zstd))
                .compression_threads(0)
                .chunk_size(None);
            *out = Some(Writer::with_options(BufWriter::new(file), opts).map_err(mcap_err)?);
            return Ok(());
        }
        let Some(w) = out.as_mut() else { return Ok(()) };
        match rec {
            Record::Schema { header, data } => {
                w.add_schema_with_id(header.id, &header.name, &header.encoding, &data).map_err(mcap_err)?;
                schemas.insert(header.id, header.name);
            }
            Record::Channel(c) => {
                w.add_channel_with_id(c.id, c.schema_id, &c.topic, &c.message_encoding, &c.metadata)
                    .map_err(mcap_err)?;
                topics.entry(c.id).or_insert_with(|| TopicInfo {
                    name: c.topic.clone(),
                    type_name: schemas.get(&c.schema_id).cloned().unwrap_or_default(),
                    qos_yaml: c.metadata.get("offered_qos_profiles").cloned().unwrap_or_default(),
                    count: 0,
                });
            }
            Record::Message { header, data } => {
                w.write_to_known_channel(&header, &data).map_err(mcap_err)?;
                if let Some(t) = topics.get_mut(&header.channel_id) {
                    t.count += 1;
                }
                report.messages += 1;
                report.start_ns = report.start_ns.min(crate::log_ns(header.log_time));
                report.end_ns = report.end_ns.max(crate::log_ns(header.log_time));
            }
            // The rosbag2 record is rebuilt from what was copied.
            Record::Metadata(m) if m.name != "rosbag2" => {
                if m.name == crate::episode::DROID_RECORD {
                    droid = Some(m.metadata.clone());
                }
                w.write_metadata(&m).map_err(mcap_err)?;
                report.metadata += 1;
            }
            Record::Attachment { header, data, .. } => {
                let a = Attachment {
                    log_time: header.log_time,
                    create_time: header.create_time,
                    name: header.name,
                    media_type: header.media_type,
                    data,
                };
                w.attach(&a).map_err(mcap_err)?;
                report.attachments += 1;
            }
            // Indexes, statistics, summary: rebuilt by finish().
            _ => {}
        }
        Ok(())
    };
    let reader = LinearReader::new_with_options(&buf, Options::IgnoreEndMagic.into())
        .map_err(|source| EpisodeError::Mcap { path: input.to_owned(), source })?;
    for rec in reader {
        let rec = match rec {
            Ok(r) => r,
            Err(e) => {
                report.stopped = format!("stopped at damage: {e}");
                break;
            }
        };
        if let Record::Chunk { header, data } = rec {
            let inner = crate::chunk::chunk_records(&header, &data);
            match inner {
                Ok(records) => {
                    for r in records {
                        copy(r.into_owned(), &mut out)?;
                    }
                    if let Some(w) = out.as_mut() {
                        w.flush().map_err(mcap_err)?;
                    }
                    report.chunks += 1;
                }
                Err(e) => {
                    report.stopped = format!("stopped at a damaged chunk: {e}");
                    break;
                }
            }
        } else {
            copy(rec, &mut out)?;
        }
    }
    let Some(mut w) = out else {
        return Err(EpisodeError::Io {
            path: input.to_owned(),
            what: "recovering",
            source: std::io::Error::new(std::io::ErrorKind::InvalidData, "not an MCAP file: no header record survived"),
        });
    };
    if report.messages == 0 {
        report.start_ns = 0;
    }
    if let (Some(amend), Some(record)) = (amend, &droid)
        && let Ok(mut meta) = EpisodeMetadata::from_record(record)
    {
        amend(&mut meta);
        w.write_metadata(&mcap::records::Metadata {
            name: crate::episode::DROID_RECORD.into(),
            metadata: meta.to_record(),
        })
        .map_err(mcap_err)?;
        report.metadata += 1;
    }
    let mut topics: Vec<TopicInfo> = topics.into_values().collect();
    topics.sort_by(|a, b| a.name.cmp(&b.name));
    let file_name = output.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let info = BagInfo::single(
        &file_name,
        report.start_ns,
        report.end_ns,
        topics,
        vec![("recovered".into(), report.stopped.clone())],
    );
    w.write_metadata(&mcap::records::Metadata { name: "rosbag2".into(), metadata: info.record() }).map_err(mcap_err)?;
    w.finish().map_err(mcap_err)?;
    let file = w.into_inner().into_inner().map_err(|e| io(output, "writing the recovered file", e.into_error()))?;
    file.sync_all().map_err(|e| io(output, "syncing the recovered file", e))?;
    report.info = info;
    Ok(report)
}

/// One part of a recovered episode directory.
#[derive(Debug, Clone, PartialEq)]
pub struct PartRecovery {
    pub file: std::path::PathBuf,
    /// `None`: the part was finished already and is left as it is.
    pub report: Option<RecoverReport>,
    /// The part as rosbag2 describes it.
    pub info: BagInfo,
}

/// What [`recover_in_place`] did to an episode directory.
#[derive(Debug, Clone, PartialEq)]
pub struct DirRecovery {
    pub parts: Vec<PartRecovery>,
    /// The whole episode as `metadata.yaml` now describes it.
    pub info: BagInfo,
}

impl DirRecovery {
    /// Messages in the episode after recovery.
    pub fn messages(&self) -> u64 {
        self.info.message_count()
    }
}

/// The rosbag2 description of a finished part, from its MCAP summary.
pub fn bag_info_of(file: &Path) -> Result<BagInfo, EpisodeError> {
    let io = |what, source| EpisodeError::Io { path: file.to_owned(), what, source };
    let buf = std::fs::read(file).map_err(|e| io("reading the episode", e))?;
    let invalid =
        |why: &str| io("reading the summary", std::io::Error::new(std::io::ErrorKind::InvalidData, why.to_owned()));
    // A summary is read from the footer backwards: a file whose start is damaged has one too.
    if !buf.starts_with(mcap::MAGIC) {
        return Err(invalid("it does not start with MCAP's magic bytes"));
    }
    let summary = mcap::Summary::read(&buf)
        .map_err(|source| EpisodeError::Mcap { path: file.to_owned(), source })?
        .ok_or_else(|| invalid("the file has no summary (unfinished)"))?;
    let stats = summary.stats.as_ref().ok_or_else(|| invalid("the summary has no statistics"))?;
    let mut topics: Vec<TopicInfo> = summary
        .channels
        .iter()
        .map(|(id, c)| TopicInfo {
            name: c.topic.clone(),
            type_name: c.schema.as_ref().map(|s| s.name.clone()).unwrap_or_default(),
            qos_yaml: c.metadata.get("offered_qos_profiles").cloned().unwrap_or_default(),
            count: stats.channel_message_counts.get(id).copied().unwrap_or(0),
        })
        .collect();
    topics.sort_by(|a, b| a.name.cmp(&b.name));
    let name = file.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    Ok(BagInfo::single(
        &name,
        crate::log_ns(stats.message_start_time),
        crate::log_ns(stats.message_end_time),
        topics,
        Vec::new(),
    ))
}

/// `labrig recover <episode_dir>` and a restarted recorder: every unfinished part of the
/// episode in `dir` (`episode_<k>.mcap`) recovered in place, the damaged file kept beside it
/// as `episode_<k>.mcap.damaged`; finished parts are left as they are; `metadata.yaml` then
/// describes all of them.
pub fn recover_in_place(dir: &Path) -> Result<DirRecovery, EpisodeError> {
    recover_in_place_with(dir, None)
}

/// [`recover_in_place`], the last part ending with the episode's DROID record changed by
/// `amend` (a finished last part is rewritten through a temporary file for it).
pub fn recover_in_place_with(dir: &Path, amend: Option<Amend<'_>>) -> Result<DirRecovery, EpisodeError> {
    let io = |what, source| EpisodeError::Io { path: dir.to_owned(), what, source };
    let files = crate::episode::part_files(dir).map_err(|e| io("listing the episode's parts", e))?;
    if files.is_empty() {
        let none = std::io::Error::new(std::io::ErrorKind::NotFound, "no episode_<k>.mcap in it");
        return Err(io("recovering", none));
    }
    let mut parts = Vec::new();
    let last = files.len() - 1;
    for (k, file) in files.into_iter().enumerate() {
        let amend = if k == last { amend } else { None };
        let name = file.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        let file_err = |what, source| EpisodeError::Io { path: file.clone(), what, source };
        if let Ok(info) = bag_info_of(&file) {
            if amend.is_none() {
                parts.push(PartRecovery { file, report: None, info });
                continue;
            }
            let tmp = file.with_file_name(format!(".{name}.amended"));
            let report = recover_with(&file, &tmp, amend)?;
            std::fs::rename(&tmp, &file).map_err(|e| file_err("replacing the finished part", e))?;
            let mut info = report.info.clone();
            info.files[0].path = name;
            parts.push(PartRecovery { file, info, report: Some(report) });
            continue;
        }
        let damaged = file.with_file_name(format!("{name}.damaged"));
        if !damaged.exists() {
            std::fs::rename(&file, &damaged).map_err(|e| file_err("keeping the damaged file", e))?;
        }
        let report = recover_with(&damaged, &file, amend)?;
        parts.push(PartRecovery { file, info: report.info.clone(), report: Some(report) });
    }
    let infos: Vec<BagInfo> = parts.iter().map(|p| p.info.clone()).collect();
    let info = BagInfo::merged(&infos);
    write_metadata_yaml(dir, &info)?;
    Ok(DirRecovery { parts, info })
}
