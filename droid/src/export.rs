//! `labrig export droid`: one MCAP episode -> DROID's raw layout.
//!
//! `<out>/{success|failure}/<date>/<asctime>/` holding `trajectory.h5`,
//! `recordings/MP4/<serial>.mp4` (one frame per step: the frame the step's observation used)
//! and `metadata_<uuid>.json`. Everything is written into `<dir>.partial` and renamed at the
//! end, so an export that fails leaves no half episode behind.

use crate::droid::{self, Camera, Episode, HAND_CAMERA};
use crate::h5doc;
use crate::meta;
use crate::video::Mp4Writer;
use crate::{DroidError, bad, io};
use labrig_arm::ik::{pose_from_xyz_euler, xyz_euler};
use labrig_episode::inspect::read_episode;
use labrig_episode::metadata::{Outcome, episode_dir};
use labrig_msgs::Nanos;
use labrig_msgs::sensor_msgs::{CameraInfo, CompressedImage};
use labrig_msgs::tf2_msgs::TFMessage;
use labrig_msgs::topics;
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// The rig's control rate: the MP4s play at it.
pub const FPS: u32 = 20;

#[derive(Debug, Clone, Default)]
pub struct ExportOptions {
    /// Replace an episode already exported to the same directory.
    pub overwrite: bool,
}

/// What one export wrote and how long it took.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Exported {
    pub source: PathBuf,
    pub dir: PathBuf,
    pub uuid: String,
    pub steps: usize,
    pub cameras: Vec<String>,
    /// Step frames taken from a neighbouring step (the camera had no frame at that tick).
    pub frames_filled: usize,
    /// Frames per MP4 (all equal to `steps`).
    pub mp4_frames: Vec<u64>,
    pub seconds: f64,
    pub h5_seconds: f64,
}

/// The hand camera's pose in the TCP frame, from the first /tf that has both.
fn hand_offset_of(tf: &TFMessage) -> Option<[f64; 6]> {
    let pose = |child: &str| {
        tf.transforms.iter().find(|t| t.child_frame_id == child).map(|t| {
            let (p, q) = (&t.transform.translation, &t.transform.rotation);
            Isometry3::from_parts(
                Translation3::new(p.x, p.y, p.z),
                UnitQuaternion::from_quaternion(Quaternion::new(q.w, q.x, q.y, q.z)),
            )
        })
    };
    let (tcp, cam) = (pose("tcp")?, pose(&format!("{HAND_CAMERA}_optical"))?);
    Some(xyz_euler(&(tcp.inverse() * cam)))
}

struct CameraOut {
    refs: Vec<i64>,
    next: usize,
    last: Option<Vec<u8>>,
    filled: usize,
    writer: Mp4Writer,
}

impl CameraOut {
    /// A recorded frame stamped `t`: written for every step that used it; steps whose frame
    /// was never recorded (an older stamp) get the last frame seen.
    fn frame(&mut self, t: i64, jpeg: &[u8]) -> Result<(), crate::video::VideoError> {
        while self.next < self.refs.len() && self.refs[self.next] <= t {
            if self.refs[self.next] == t {
                self.writer.push_jpeg(jpeg)?;
            } else {
                self.filled += 1;
                let last = self.last.as_deref().unwrap_or(jpeg);
                self.writer.push_jpeg(last)?;
            }
            self.next += 1;
        }
        self.last = Some(jpeg.to_vec());
        Ok(())
    }
}

/// A recorded episode, checked for export: its MCAP file, metadata and steps (finished, with
/// metadata, every step there).
pub(crate) fn read_checked(
    source: &Path,
) -> Result<(PathBuf, labrig_episode::EpisodeMetadata, Vec<labrig_msgs::rig::Step>), DroidError> {
    let data = read_episode(source)?;
    let file = data.file.clone();
    if !data.complete {
        return Err(bad(
            &file,
            "the episode was not finished (its recorder stopped early): run `labrig recover` on it first",
        ));
    }
    let mut metadata = data
        .metadata
        .ok_or_else(|| bad(&file, "no droid_episode metadata record: not an episode recorded by labrig"))?;
    let steps = data.steps;
    if steps.is_empty() {
        return Err(bad(&file, "no /rig/step records: nothing to export"));
    }
    for (i, s) in steps.iter().enumerate() {
        if s.step_index != i as u64 {
            let reason = format!("step {i} is missing (the steps go {} -> {})", i.saturating_sub(1), s.step_index);
            return Err(bad(&file, reason));
        }
    }
    metadata.trajectory_length = steps.len() as u64;
    Ok((file, metadata, steps))
}

/// What a pass over a recorded episode finds besides frames.
pub(crate) struct Seen {
    pub intrinsics: BTreeMap<String, [f64; 9]>,
    /// The hand camera's pose in the TCP frame.
    pub hand_offset: Option<[f64; 6]>,
}

impl Seen {
    /// An imported episode carries the hand camera's offset in its metadata; a recorded one
    /// has it on /tf.
    pub fn new(metadata: &labrig_episode::EpisodeMetadata) -> Seen {
        Seen {
            intrinsics: BTreeMap::new(),
            hand_offset: metadata.extrinsics.get(&format!("{HAND_CAMERA}_gripper_offset")).copied(),
        }
    }
}

/// One pass over a recorded episode's messages (`buf`, the bytes of `file`): intrinsics and the
/// hand camera's offset go to `seen`; each frame of `cameras` to `frame(camera index, capture
/// ns, JPEG)`; every other message to `other(topic, CDR bytes)`.
pub(crate) fn scan(
    file: &Path,
    buf: &[u8],
    cameras: &[Camera],
    seen: &mut Seen,
    mut frame: impl FnMut(usize, i64, &[u8]) -> Result<(), DroidError>,
    mut other: impl FnMut(&str, &[u8]),
) -> Result<(), DroidError> {
    let mcap_err = |source| DroidError::Mcap { path: file.to_owned(), source };
    let index: BTreeMap<&str, usize> = cameras.iter().enumerate().map(|(i, c)| (c.id.as_str(), i)).collect();
    for m in mcap::MessageStream::new(buf).map_err(mcap_err)? {
        let m = m.map_err(mcap_err)?;
        let topic = m.channel.topic.as_str();
        let Some(rest) = topic.strip_prefix(topics::CAMERAS_PREFIX) else {
            if topic == topics::TF.name
                && seen.hand_offset.is_none()
                && let Ok(tf) = labrig_msgs::decode::<TFMessage>(&m.data)
            {
                seen.hand_offset = hand_offset_of(&tf);
            }
            other(topic, &m.data);
            continue;
        };
        let Some((id, what)) = rest.split_once('/') else { continue };
        let Some(&c) = index.get(id) else { continue };
        match what {
            "image/compressed" => {
                let img =
                    labrig_msgs::decode::<CompressedImage>(&m.data).map_err(|e| bad(file, format!("{topic}: {e}")))?;
                frame(c, Nanos::from(img.header.stamp).0, &img.data)?;
            }
            "camera_info" if !seen.intrinsics.contains_key(id) => {
                if let Ok(info) = labrig_msgs::decode::<CameraInfo>(&m.data) {
                    seen.intrinsics.insert(id.to_owned(), info.k);
                }
            }
            _ => {}
        }
    }
    Ok(())
}

/// DROID's metadata JSON of an exported episode in `rel_dir` (relative to the dataset root).
pub(crate) fn droid_json(ep: &Episode, rel_dir: &str) -> serde_json::Value {
    let cameras: Vec<(String, String, Option<[f64; 6]>)> =
        ep.cameras.iter().map(|c| (c.id.clone(), c.serial.clone(), camera_extrinsics(ep, c))).collect();
    meta::to_json(&meta::JsonInput {
        meta: &ep.metadata,
        rel_dir,
        cameras: &cameras,
        hand_offset: ep.hand_offset,
        action_source: ep.steps[0].action_source,
    })
}

/// A camera's extrinsics as DROID's metadata JSON gives them: the hand camera's at the first
/// step (the TCP's pose composed with its offset), the others' from the metadata.
fn camera_extrinsics(ep: &Episode, c: &Camera) -> Option<[f64; 6]> {
    if c.id == HAND_CAMERA {
        ep.hand_offset.map(|off| {
            xyz_euler(&(pose_from_xyz_euler(&ep.steps[0].robot_state.cartesian_position) * pose_from_xyz_euler(&off)))
        })
    } else {
        ep.metadata.extrinsics.get(&c.id).copied()
    }
}

/// The frame pass both exporters share: one H.264 writer per camera at `paths`, fed each step's
/// frame as the episode's MCAP is scanned (`refs[camera][step]`; a step whose frame was never
/// recorded gets the camera's previous one, also after its last); the frames written and the
/// steps filled in, per camera. A camera without any recorded frame is an error.
fn camera_videos(
    file: &Path,
    buf: &[u8],
    cameras: &[Camera],
    refs: &[Vec<labrig_msgs::rig::CameraFrameRef>],
    seen: &mut Seen,
    paths: &[PathBuf],
    fps: u32,
) -> Result<(Vec<u64>, Vec<usize>), DroidError> {
    let mut outs = Vec::with_capacity(cameras.len());
    for (r, path) in refs.iter().zip(paths) {
        outs.push(CameraOut {
            refs: r.iter().map(|f| f.capture_ns).collect(),
            next: 0,
            last: None,
            filled: 0,
            writer: Mp4Writer::create(path, fps)?,
        });
    }
    scan(file, buf, cameras, seen, |c, t, jpeg| Ok(outs[c].frame(t, jpeg)?), |_, _| {})?;
    let (mut frames, mut filled) = (Vec::new(), Vec::new());
    for (cam, mut out) in cameras.iter().zip(outs) {
        if out.last.is_none() {
            return Err(bad(file, format!("camera {} has no recorded frames: no video to export", cam.id)));
        }
        // Steps after the last recorded frame.
        while out.next < out.refs.len() {
            let last = out.last.clone().expect("checked");
            out.frame(i64::MAX, &last)?;
        }
        filled.push(out.filled);
        frames.push(out.writer.finish()?);
    }
    Ok((frames, filled))
}

/// An episode's steps and one video per camera, one frame per step (the frame the step used;
/// a step without one gets the camera's previous frame), for other formats' exporters
/// (LeRobot's, in labrig-dataset).
#[derive(Debug)]
pub struct StepVideos {
    pub file: PathBuf,
    pub metadata: labrig_episode::EpisodeMetadata,
    pub steps: Vec<labrig_msgs::rig::Step>,
    /// The cameras in the rig's order, with the path of each one's video.
    pub cameras: Vec<(Camera, PathBuf)>,
    /// Frames per camera, and the steps that had no frame of their own (filled in).
    pub frames: Vec<u64>,
    pub filled: Vec<usize>,
}

/// Reads the finished episode at `source` and writes each camera's frames, one per step, to
/// `video_path(camera id)` as H.264 MP4 at `fps` (a camera with no recorded frame is an error;
/// a camera `video_path` gives no path for is left out).
pub fn step_videos(
    source: &Path,
    fps: u32,
    video_path: impl Fn(&str) -> Option<PathBuf>,
) -> Result<StepVideos, DroidError> {
    let (file, metadata, steps) = read_checked(source)?;
    let buf = std::fs::read(&file).map_err(io(&file))?;
    let mut seen = Seen::new(&metadata);
    let (cameras, paths): (Vec<Camera>, Vec<PathBuf>) = droid::cameras_of(&steps, &metadata, &seen.intrinsics)
        .into_iter()
        .filter_map(|c| video_path(&c.id).map(|p| (c, p)))
        .unzip();
    let (refs, own_missing) = droid::frame_refs(&steps, &cameras);
    for dir in paths.iter().filter_map(|p| p.parent()) {
        std::fs::create_dir_all(dir).map_err(io(dir))?;
    }
    let (frames, mut filled) = camera_videos(&file, &buf, &cameras, &refs, &mut seen, &paths, fps)?;
    filled.iter_mut().zip(&own_missing).for_each(|(f, m)| *f += m);
    let mut cameras = cameras;
    for cam in cameras.iter_mut() {
        cam.k = seen.intrinsics.get(&cam.id).copied();
    }
    Ok(StepVideos { file, metadata, steps, cameras: cameras.into_iter().zip(paths).collect(), frames, filled })
}

/// Exports the episode at `source` (its directory or MCAP file) under `out_root`.
pub fn export_episode(source: &Path, out_root: &Path, opts: &ExportOptions) -> Result<Exported, DroidError> {
    let started = Instant::now();
    let (file, metadata, steps) = read_checked(source)?;

    // Second pass: intrinsics, the hand camera's offset, and the frames into the MP4s.
    let buf = std::fs::read(&file).map_err(io(&file))?;
    let mut seen = Seen::new(&metadata);
    let mut cameras = droid::cameras_of(&steps, &metadata, &seen.intrinsics);
    let (refs, own_missing) = droid::frame_refs(&steps, &cameras);

    let outcome = if metadata.success == Some(true) { Outcome::Success } else { Outcome::Failure };
    let json_name = meta::file_name(&metadata.uuid);
    let dir = crate::destination(
        &episode_dir(out_root, outcome, Nanos(metadata.start_ns)),
        |d| d.join(&json_name).is_file(),
        opts.overwrite,
    )?;
    let rel_dir = dir.strip_prefix(out_root).unwrap_or(&dir).to_string_lossy().into_owned();
    let partial = dir.with_extension("partial");
    let _ = std::fs::remove_dir_all(&partial);
    let mp4_dir = partial.join("recordings").join("MP4");
    std::fs::create_dir_all(&mp4_dir).map_err(io(&mp4_dir))?;
    let result = (|| -> Result<Exported, DroidError> {
        let paths: Vec<PathBuf> = cameras.iter().map(|c| mp4_dir.join(format!("{}.mp4", c.serial))).collect();
        let (mp4_frames, filled) = camera_videos(&file, &buf, &cameras, &refs, &mut seen, &paths, FPS)?;
        // Steps whose frame was never recorded, and steps with no frame of their own.
        let frames_filled: usize = filled.iter().sum::<usize>() + own_missing.iter().sum::<usize>();
        for cam in cameras.iter_mut() {
            cam.k = seen.intrinsics.get(&cam.id).copied();
        }
        let h5_started = Instant::now();
        let ep = Episode { metadata, steps, cameras, hand_offset: seen.hand_offset };
        h5doc::write(&partial.join("trajectory.h5"), &droid::to_droid(&ep))?;
        let h5_seconds = h5_started.elapsed().as_secs_f64();
        let json = droid_json(&ep, &rel_dir);
        let json_path = partial.join(meta::file_name(&ep.metadata.uuid));
        let text = serde_json::to_string_pretty(&json).map_err(|e| bad(&json_path, e.to_string()))?;
        std::fs::write(&json_path, text + "\n").map_err(io(&json_path))?;
        Ok(Exported {
            source: file.clone(),
            dir: dir.clone(),
            uuid: ep.metadata.uuid.clone(),
            steps: ep.steps.len(),
            cameras: ep.cameras.iter().map(|c| c.id.clone()).collect(),
            frames_filled,
            mp4_frames,
            seconds: 0.0,
            h5_seconds,
        })
    })();
    let mut e = crate::settle(&partial, &dir, result)?;
    e.seconds = started.elapsed().as_secs_f64();
    Ok(e)
}

pub use labrig_episode::episode::find_episodes;
