//! `labrig import droid`: a DROID raw episode -> an MCAP episode in the recorder's layout.
//!
//! Reads `trajectory.h5`, `metadata_<uuid>.json` and `recordings/MP4/<serial>.mp4`, and writes
//! what the recorder would have: the DROID metadata record, `/rig/episode` Start and
//! Success/Failure, one `/rig/step` per step, `/cameras/<id>/camera_info` (from the
//! intrinsics) and `/cameras/<id>/image/compressed` (each distinct frame once, JPEG), so the
//! episode can be inspected, indexed, replayed (when it carries a sim scene) and exported
//! again (to the same trajectory.h5).

use crate::droid::{self, Camera};
use crate::h5doc;
use crate::meta;
use crate::video::Mp4Reader;
use crate::{DroidError, bad, io};
use labrig_episode::bag::Reliability;
use labrig_episode::episode::EpisodeWriter;
use labrig_episode::metadata::{Outcome, episode_dir};
use labrig_msgs::Nanos;
use labrig_msgs::rig::{EpisodeEvent, EpisodeEventKind, TeleopState};
use labrig_msgs::sensor_msgs::{CameraInfo, CompressedImage};
use labrig_msgs::std_msgs::Header;
use labrig_msgs::topics;
use std::path::{Path, PathBuf};
use std::time::Instant;

#[derive(Debug, Clone)]
pub struct ImportOptions {
    pub overwrite: bool,
    /// JPEG quality of the imported frames.
    pub jpeg_quality: u8,
}

impl Default for ImportOptions {
    fn default() -> Self {
        ImportOptions { overwrite: false, jpeg_quality: 90 }
    }
}

#[derive(Debug, Clone, serde::Serialize)]
pub struct Imported {
    pub source: PathBuf,
    pub dir: PathBuf,
    pub uuid: String,
    pub steps: usize,
    pub cameras: Vec<String>,
    pub frames: u64,
    /// Problems that did not stop the import (a video shorter than the trajectory ...).
    pub warnings: Vec<String>,
    pub seconds: f64,
}

/// DROID episode directories under `root`: every directory holding a trajectory.h5.
pub fn find_droid_episodes(root: &Path) -> Vec<PathBuf> {
    crate::dirs_holding(root, "trajectory.h5")
}

fn metadata_json(dir: &Path) -> Result<PathBuf, DroidError> {
    let mut found: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(io(dir))?
        .flatten()
        .map(|e| e.path())
        .filter(|p| {
            p.file_name().and_then(|n| n.to_str()).is_some_and(|n| n.starts_with("metadata_") && n.ends_with(".json"))
        })
        .collect();
    found.sort();
    match found.len() {
        0 => Err(bad(dir, "no metadata_<uuid>.json: not a DROID episode directory")),
        1 => Ok(found.remove(0)),
        n => Err(bad(dir, format!("{n} metadata_*.json files: which episode is this?"))),
    }
}

/// Imports the DROID episode in `source` under `out_root`.
pub fn import_episode(source: &Path, out_root: &Path, opts: &ImportOptions) -> Result<Imported, DroidError> {
    let started = Instant::now();
    // trajectory.h5 itself names its episode directory.
    let source = match source.parent() {
        Some(parent) if source.is_file() => parent,
        _ => source,
    };
    let h5_path = source.join("trajectory.h5");
    if !h5_path.is_file() {
        return Err(bad(source, "no trajectory.h5: not a DROID episode directory"));
    }
    let json_path = metadata_json(source)?;
    let text = std::fs::read_to_string(&json_path).map_err(io(&json_path))?;
    let value: serde_json::Value =
        serde_json::from_str(&text).map_err(|e| bad(&json_path, format!("not JSON: {e}")))?;
    let parsed = meta::parse(&value).map_err(|e| bad(&json_path, e.to_string()))?;
    let doc = h5doc::read(&h5_path)?;
    let mut meta = parsed.meta;
    let traj = droid::from_droid(&doc, &meta.uuid, &parsed.serial_to_id).map_err(|e| bad(&h5_path, e.to_string()))?;
    merge_trajectory(&mut meta, &traj, parsed.has_start);
    let mut steps = traj.steps;
    for s in &mut steps {
        s.action_source = parsed.action_source;
    }
    apply_attrs(&doc, &mut meta);

    let mut frames = Mp4Frames::open(source, &traj.cameras, opts.jpeg_quality, steps.len())?;
    let mut warnings = std::mem::take(&mut frames.warnings);
    let (dir, frames) = write_imported(
        meta.clone(),
        &steps,
        &traj.cameras,
        traj.hand_offset,
        out_root,
        opts,
        &mut frames,
        &[],
        &mut warnings,
        "imported from DROID",
    )?;
    Ok(Imported {
        source: source.to_owned(),
        dir,
        uuid: meta.uuid,
        steps: steps.len(),
        cameras: traj.cameras.iter().map(|c| c.id.clone()).collect(),
        frames,
        warnings,
        seconds: started.elapsed().as_secs_f64(),
    })
}

/// What trajectory.h5 says of the episode, into its metadata: the outcome (where the file is
/// labelled), the start (unless the metadata had one), the length, the cameras' serials and
/// the external cameras' extrinsics (the metadata's win).
pub(crate) fn merge_trajectory(
    meta: &mut labrig_episode::metadata::EpisodeMetadata,
    traj: &droid::Trajectory,
    has_start: bool,
) {
    let steps = &traj.steps;
    if traj.labelled {
        meta.success = traj.success;
    }
    if !has_start {
        meta.start_ns = steps[0].timing.step_start;
    }
    meta.trajectory_length = steps.len() as u64;
    for cam in &traj.cameras {
        meta.camera_serials.insert(cam.id.clone(), cam.serial.clone());
    }
    for (id, e) in &traj.extrinsics {
        meta.extrinsics.entry(id.clone()).or_insert(*e);
    }
}

/// trajectory.h5's attributes are DROID's record of who, where and what; they win over the
/// metadata JSON's.
pub(crate) fn apply_attrs(doc: &h5doc::H5Doc, meta: &mut labrig_episode::metadata::EpisodeMetadata) {
    for (key, field) in [
        ("user", &mut meta.user),
        ("building", &mut meta.building),
        ("scene_id", &mut meta.scene_id),
        ("current_task", &mut meta.task_instruction),
    ] {
        if let Some(v) = droid::attr_text(doc, key) {
            *field = v;
        }
    }
}

/// Where an import's camera frames come from, as JPEG.
pub trait FrameSource {
    /// The camera's image size (None: no images, so no camera_info either).
    fn size(&self, camera: usize) -> Option<(u32, u32)>;
    /// `camera`'s frame at `step`, asked once per step in order: the JPEG when `wanted` (the
    /// step names a frame of that camera), None when there is none.
    fn frame(&mut self, camera: usize, step: usize, wanted: bool) -> Result<Option<Vec<u8>>, DroidError>;
    /// After the last step: anything left over, as warnings.
    fn finish(&mut self, warnings: &mut Vec<String>) -> Result<(), DroidError>;
}

/// Which step's frame [`next_step_frame`] reads, and how.
#[derive(Debug)]
pub struct StepFrame<'a> {
    pub camera: &'a str,
    pub step: usize,
    /// The episode's steps (for the warning of a short video).
    pub steps: usize,
    /// Encode it (else it is read and dropped).
    pub wanted: bool,
    pub quality: u8,
}

/// The next frame of a video holding one frame per step: read whether or not it is wanted (so
/// the next step's comes next), JPEG-encoded when it is; past the video's end None, said once
/// in `warnings` (`short` remembers it).
pub fn next_step_frame(
    r: &mut Mp4Reader,
    short: &mut bool,
    at: &StepFrame,
    warnings: &mut Vec<String>,
    source: &Path,
) -> Result<Option<Vec<u8>>, DroidError> {
    let pixels = if *short { None } else { r.next_frame()? };
    let Some(pixels) = pixels else {
        if !*short {
            *short = true;
            warnings.push(format!("camera {}: the video ends at frame {} of {} steps", at.camera, at.step, at.steps));
        }
        return Ok(None);
    };
    if !at.wanted {
        return Ok(None);
    }
    labrig_episode::jpeg::encode_rgb(&pixels, r.width as u16, r.height as u16, at.quality)
        .map(Some)
        .map_err(|e| bad(source, format!("camera {}: {e}", at.camera)))
}

/// The MP4s of a DROID raw episode: one frame per step, encoded to JPEG.
struct Mp4Frames {
    readers: Vec<Option<Mp4Reader>>,
    short: Vec<bool>,
    ids: Vec<String>,
    quality: u8,
    source: PathBuf,
    warnings: Vec<String>,
    steps: usize,
}

impl Mp4Frames {
    fn open(source: &Path, cameras: &[Camera], quality: u8, steps: usize) -> Result<Mp4Frames, DroidError> {
        let mp4_dir = source.join("recordings").join("MP4");
        let mut readers = Vec::new();
        let mut warnings = Vec::new();
        for cam in cameras {
            let p = mp4_dir.join(format!("{}.mp4", cam.serial));
            if !p.is_file() {
                warnings.push(format!(
                    "camera {} ({}): no {}: imported without images",
                    cam.id,
                    cam.serial,
                    p.display()
                ));
                readers.push(None);
                continue;
            }
            readers.push(Some(Mp4Reader::open(&p)?));
        }
        Ok(Mp4Frames {
            short: vec![false; cameras.len()],
            readers,
            ids: cameras.iter().map(|c| c.id.clone()).collect(),
            quality,
            source: source.to_owned(),
            warnings,
            steps,
        })
    }
}

impl FrameSource for Mp4Frames {
    fn size(&self, camera: usize) -> Option<(u32, u32)> {
        self.readers[camera].as_ref().map(|r| (r.width, r.height))
    }

    fn frame(&mut self, camera: usize, step: usize, wanted: bool) -> Result<Option<Vec<u8>>, DroidError> {
        let Some(r) = self.readers[camera].as_mut() else { return Ok(None) };
        let at = StepFrame { camera: &self.ids[camera], step, steps: self.steps, wanted, quality: self.quality };
        next_step_frame(r, &mut self.short[camera], &at, &mut self.warnings, &self.source)
    }

    fn finish(&mut self, warnings: &mut Vec<String>) -> Result<(), DroidError> {
        warnings.append(&mut self.warnings);
        for (c, r) in self.readers.iter_mut().enumerate() {
            if let Some(r) = r
                && !self.short[c]
                && r.next_frame()?.is_some()
            {
                warnings.push(format!(
                    "camera {}: the video has more frames than the {} steps; the rest were left out",
                    self.ids[c], self.steps
                ));
            }
        }
        Ok(())
    }
}

/// Writes an imported episode under `out_root`'s recorder layout (into `<dir>.partial`, renamed
/// at the end: a failed import leaves nothing); returns its directory and the frames written.
#[allow(clippy::too_many_arguments)]
pub fn write_imported(
    meta: labrig_episode::metadata::EpisodeMetadata,
    steps: &[labrig_msgs::rig::Step],
    cameras: &[Camera],
    hand_offset: Option<[f64; 6]>,
    out_root: &Path,
    opts: &ImportOptions,
    frames: &mut dyn FrameSource,
    teleop: &[Option<TeleopState>],
    warnings: &mut Vec<String>,
    note: &str,
) -> Result<(PathBuf, u64), DroidError> {
    let outcome = if meta.success == Some(true) { Outcome::Success } else { Outcome::Failure };
    // The recorder's metadata.yaml names the episode's uuid.
    let uuid = meta.uuid.clone();
    let same = |d: &Path| std::fs::read_to_string(d.join("metadata.yaml")).is_ok_and(|y| y.contains(&uuid));
    let dir = crate::destination(&episode_dir(out_root, outcome, Nanos(meta.start_ns)), same, opts.overwrite)?;
    let partial = dir.with_extension("partial");
    let _ = std::fs::remove_dir_all(&partial);
    let n = crate::settle(
        &partial,
        &dir,
        write_episode(&partial, meta, steps, cameras, hand_offset, frames, teleop, warnings, note),
    )?;
    Ok((dir, n))
}

#[allow(clippy::too_many_arguments)]
fn write_episode(
    dir: &Path,
    mut meta: labrig_episode::metadata::EpisodeMetadata,
    steps: &[labrig_msgs::rig::Step],
    cameras: &[Camera],
    hand_offset: Option<[f64; 6]>,
    frames: &mut dyn FrameSource,
    teleop: &[Option<TeleopState>],
    warnings: &mut Vec<String>,
    note: &str,
) -> Result<u64, DroidError> {
    if let Some(off) = hand_offset {
        // Where the recorder keeps extrinsics; an export reads the hand camera's from here.
        meta.extrinsics.insert(format!("{}_gripper_offset", droid::HAND_CAMERA), off);
    }
    let success = meta.success;
    let uuid = meta.uuid.clone();
    let mut w = EpisodeWriter::create(dir, meta)?;
    let t0 = steps[0].timing.step_start.max(Nanos::from(steps[0].header.stamp).0);
    let event = |kind: EpisodeEventKind, t: i64| EpisodeEvent {
        header: Header { stamp: Nanos(t).into(), frame_id: String::new() },
        kind: kind as u8,
        episode_id: uuid.clone(),
        note: note.into(),
        ..EpisodeEvent::default()
    };
    w.write(
        topics::RIG_EPISODE.name,
        &event(EpisodeEventKind::Start, t0),
        Nanos(t0),
        Nanos(t0),
        Reliability::Reliable,
    )?;
    let mut written = 0u64;
    let mut last_t = t0;
    for (i, s) in steps.iter().enumerate() {
        let t = s.timing.step_start.max(Nanos::from(s.header.stamp).0).max(last_t);
        last_t = t;
        for (c, cam) in cameras.iter().enumerate() {
            let Some((width, height)) = frames.size(c) else { continue };
            if i == 0 {
                let k = cam.k.unwrap_or([0.0; 9]);
                let info = CameraInfo {
                    header: Header { stamp: Nanos(t).into(), frame_id: format!("{}_optical", cam.id) },
                    width,
                    height,
                    distortion_model: "plumb_bob".into(),
                    d: vec![0.0; 5],
                    k,
                    r: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                    p: [k[0], k[1], k[2], 0.0, k[3], k[4], k[5], 0.0, k[6], k[7], k[8], 0.0],
                    ..CameraInfo::default()
                };
                w.write(&topics::camera_info(&cam.id), &info, Nanos(t), Nanos(t), Reliability::Reliable)?;
            }
            let fr = s.cameras.iter().find(|f| f.camera_id == cam.id);
            // DROID's files hold one image per step, also where two steps name the same
            // capture time (a step that reused a frame, or a recording's leading steps filled
            // with the first frame): each step keeps its own, so none is lost.
            let Some(jpeg) = frames.frame(c, i, fr.is_some())? else { continue };
            let Some(fr) = fr else { continue };
            let img = CompressedImage {
                header: Header { stamp: Nanos(fr.capture_ns).into(), frame_id: format!("{}_optical", cam.id) },
                format: "jpeg".into(),
                data: jpeg,
            };
            w.write(&topics::camera_image(&cam.id), &img, Nanos(t), Nanos(fr.capture_ns), Reliability::BestEffort)?;
            written += 1;
        }
        if let Some(Some(st)) = teleop.get(i) {
            w.write(topics::TELEOP_STATE.name, st, Nanos(t), Nanos::from(st.header.stamp), Reliability::Reliable)?;
        }
        w.write(topics::RIG_STEP.name, s, Nanos(t), Nanos::from(s.header.stamp), Reliability::Reliable)?;
    }
    frames.finish(warnings)?;
    let end = match success {
        Some(true) => EpisodeEventKind::Success,
        _ => EpisodeEventKind::Failure,
    };
    w.write(topics::RIG_EPISODE.name, &event(end, last_t), Nanos(last_t), Nanos(last_t), Reliability::Reliable)?;
    w.finish()?;
    Ok(written)
}
