//! The camera node: one thread per camera (a camera never blocks another) reads its source,
//! makes one eye's RGB8 image at the configured size and hands it to shared memory
//! (`labrig/camera/<id>/frames`, the interface the sim bridge serves); the node's async side
//! publishes `/cameras/<id>/camera_info` with each frame, a low-rate JPEG preview per camera,
//! `/tf_static` from the configured extrinsics and `/cameras/status`.
//!
//! Time: a frame's capture time is the device's (V4L2 buffer time, CLOCK_MONOTONIC) mapped
//! onto the rig's wall clock by the offset between the two clocks read at arrival; sources
//! without one (HTTP, ffmpeg) use the arrival time, and the status says which.
//!
//! Faults: a source that fails to open, ends or errors is reported (`down`, with the reason
//! and since when) and opened again every `retry_s`; a source that sends nothing for
//! `stall_s` is reported `stalled` (and reopened after `2 x stall_s` of silence, the read
//! timeout); the other cameras are not affected.

use crate::convert::{ConvertError, preview_jpeg, to_rgb};
use crate::intrinsics::{Eye, Intrinsics, IntrinsicsError, ZedCalibration};
use crate::realsense::RealSenseCalibration;
use crate::rectify::EyeRectifier;
use crate::source::{
    DeviceKind, FfmpegSource, MjpegSource, RealSenseSource, Source, SourceError, SourceSpec, Timeouts,
};
use labrig_msgs::builtin_interfaces::Time;
use labrig_msgs::geometry_msgs::{Quaternion, Transform, TransformStamped, Vector3};
use labrig_msgs::sensor_msgs::{CameraInfo, CompressedImage};
use labrig_msgs::std_msgs::{Header, StringMsg};
use labrig_msgs::tf2_msgs::TFMessage;
use labrig_msgs::{Invalid, Nanos, topics};
use labrig_runtime::devices::Devices;
use labrig_runtime::frames::{FrameEncoding, FrameFormat, FrameNode, FramePublisher};
use labrig_runtime::ros::{Ros, RosPublisher, qos};
use labrig_runtime::{Clock, RosConfig, Shutdown};
use nalgebra::{Rotation3, UnitQuaternion};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// The node's config (`labrig-cameras run --config F`).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CamerasConfig {
    pub ros: RosConfig,
    /// The rig's cameras by id (`[cameras.ext1]`).
    pub cameras: BTreeMap<String, CameraConfig>,
    /// Preview images per camera and second on `/cameras/<id>/preview/compressed` (0: none).
    pub preview_hz: f64,
    /// Previews are shrunk to at most this width.
    pub preview_width: u32,
    pub preview_quality: u8,
    /// A camera that sends nothing for this long is `stalled`; after twice as long its source
    /// is closed and opened again (s).
    pub stall_s: f64,
    /// Pause between attempts to open a source that is down (s).
    pub retry_s: f64,
    /// How often `/cameras/status` is published (s); also on every change.
    pub status_period_s: f64,
    /// The frame the extrinsics are given in.
    pub base_frame: String,
    /// Camera calibrations (`calibration/<rig>`, from `labrig calibrate`): a calibrated
    /// camera's `/tf_static` is its calibration's (base -> `<id>_optical`, or for the wrist
    /// camera tcp -> `<id>_optical`) instead of its configured `extrinsics`, and `/calibration`
    /// names them for the recorder; missing or old calibrations are warned at start.
    pub calibration: Option<PathBuf>,
    pub calibration_max_age_s: f64,
}

impl Default for CamerasConfig {
    fn default() -> Self {
        CamerasConfig {
            ros: RosConfig::default(),
            cameras: BTreeMap::new(),
            preview_hz: 2.0,
            preview_width: 320,
            preview_quality: 70,
            stall_s: 1.0,
            retry_s: 1.0,
            status_period_s: 1.0,
            base_frame: "base".into(),
            calibration: None,
            calibration_max_age_s: labrig_episode::calibration::DEFAULT_MAX_AGE_S,
        }
    }
}

/// One camera.
#[derive(Debug, Clone, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct CameraConfig {
    /// `zed:SERIAL`, `realsense:SERIAL`, `v4l2:SERIAL`, `/dev/videoN`, `http://...` (MJPEG),
    /// `rtsp://...`, a video file (relative to the config file) or `testsrc` (a test pattern).
    /// (Defaults to none so that `--set cameras.<id>.width=...` and `--camera <id>=...` can
    /// make a camera together; a camera without one is refused.)
    #[serde(default)]
    pub source: String,
    /// One eye's image size as published (0 x 0: whatever the source sends; a V4L2 device and
    /// a file or RTSP source need it).
    #[serde(default)]
    pub width: u32,
    #[serde(default)]
    pub height: u32,
    /// The frame rate to ask a device for (a file plays at its own).
    #[serde(default = "default_fps")]
    pub fps: f64,
    /// The frames hold a stereo pair side by side (default: true for `zed:`).
    #[serde(default)]
    pub side_by_side: Option<bool>,
    /// Which eye of a side-by-side frame is published (DROID records the left).
    #[serde(default)]
    pub eye: Eye,
    /// Rectify a ZED's frames from its factory file (`intrinsics = "SN<serial>.conf"`), as the
    /// ZED SDK does for DROID: undistorted, both eyes' rows aligned, camera_info with the
    /// rectified K, zero distortion and the stereo R and P. Default: true for ZED sources;
    /// false publishes the raw eye with the factory (distorted) intrinsics.
    #[serde(default)]
    pub rectify: Option<bool>,
    /// A ZED factory file (`SN<serial>.conf`), a labrig intrinsics file (.json/.toml), or the
    /// values inline; scaled to width x height. None: camera_info carries a zero matrix
    /// (uncalibrated, the ROS convention).
    #[serde(default)]
    pub intrinsics: Option<IntrinsicsSpec>,
    /// The camera's optical frame (z forward, x right, y down) in the base frame, DROID's way:
    /// x, y, z (m) and extrinsic x-y-z Euler angles (rad). Published on `/tf_static`.
    #[serde(default)]
    pub extrinsics: Option<[f64; 6]>,
    /// Play a video file again from the start when it ends.
    #[serde(default = "yes")]
    pub loop_file: bool,
    /// Publish an MJPEG source's JPEGs as they arrive (encoding `jpeg` on shared memory)
    /// instead of decoding them to RGB: the recorder stores them unchanged, saving a decode
    /// and a re-encode. Only for MJPEG sources (`http://`, a V4L2 device's MJPG mode) sending
    /// the configured size; the loop decodes them only where a policy observes the camera.
    #[serde(default)]
    pub jpeg_passthrough: bool,
    /// A RealSense's depth too, aligned to the colour image by librealsense (same size, same
    /// intrinsics: pixel (u, v) of both is one ray), on shared memory as camera `<id>_depth`
    /// (`depth16`: uint16 millimetres, 0 = no depth).
    #[serde(default)]
    pub depth: bool,
    /// A rectified ZED's right eye too, as a camera of its own: `<id>_right` on shared memory,
    /// `/cameras/<id>_right/camera_info` (its P's Tx = -fx * baseline) and on `/tf_static` its
    /// optical frame `<id>_right_optical`, the baseline along x from `<id>_optical` (both eyes
    /// rectified: the same orientation, rows aligned; DROID records `<serial>_right` so).
    #[serde(default)]
    pub right_eye: bool,
    /// A RealSense read in Rust over V4L2 (no librealsense, no Python on the rig): its
    /// calibration file from `labrig cameras realsense-export` (colour and depth intrinsics,
    /// depth -> colour extrinsics, depth scale). Without it a `realsense:` camera runs
    /// librealsense through pyrealsense2 in a child process.
    #[serde(default)]
    pub realsense_calibration: Option<PathBuf>,
}

impl CameraConfig {
    /// Whether this camera's frames are rectified (`rectify`, default: a ZED's are).
    pub fn rectifies(&self, spec: &SourceSpec) -> bool {
        self.rectify.unwrap_or(matches!(spec, SourceSpec::Device { kind: DeviceKind::Zed, .. }))
    }
}

fn default_fps() -> f64 {
    30.0
}
fn yes() -> bool {
    true
}

/// Where a camera's intrinsics come from.
#[derive(Debug, Clone, Deserialize, Serialize, PartialEq)]
#[serde(untagged)]
pub enum IntrinsicsSpec {
    File(PathBuf),
    Inline(Intrinsics),
}

impl CameraConfig {
    pub fn new(source: &str) -> CameraConfig {
        CameraConfig {
            source: source.to_owned(),
            width: 0,
            height: 0,
            fps: default_fps(),
            side_by_side: None,
            eye: Eye::Left,
            rectify: None,
            realsense_calibration: None,
            intrinsics: None,
            extrinsics: None,
            loop_file: true,
            jpeg_passthrough: false,
            depth: false,
            right_eye: false,
        }
    }
}

/// The camera id of a rectified ZED `id`'s right eye (`right_eye`).
pub fn right_id(id: &str) -> String {
    format!("{id}_right")
}

/// The shared-memory camera id of camera `id`'s aligned depth.
pub fn depth_id(id: &str) -> String {
    format!("{id}_depth")
}

fn is_camera_id(id: &str) -> bool {
    !id.is_empty() && id.len() <= 32 && id.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-')
}

impl CamerasConfig {
    pub fn validate(&self) -> Result<(), Invalid> {
        self.ros.validate(Path::new("cameras config")).map_err(|e| Invalid::new("ros", e.to_string()))?;
        let bad = |k: &str, why: String| Err(Invalid::new(k, format!("cameras config: `{k}` {why}")));
        if self.cameras.is_empty() {
            return bad(
                "cameras",
                "is empty: name at least one ([cameras.ext1] source = ..., or --camera ext1=SOURCE)".into(),
            );
        }
        for (k, v, lo, hi) in [
            ("preview_hz", self.preview_hz, 0.0, 30.0),
            ("stall_s", self.stall_s, 0.05, 60.0),
            ("retry_s", self.retry_s, 0.05, 60.0),
            ("status_period_s", self.status_period_s, 0.05, 60.0),
        ] {
            if !(v.is_finite() && (lo..=hi).contains(&v)) {
                return bad(k, format!("is {v}, must be {lo}..={hi}"));
            }
        }
        if !(16..=4096).contains(&self.preview_width) {
            return bad("preview_width", format!("is {}, must be 16..=4096", self.preview_width));
        }
        if !(1..=100).contains(&self.preview_quality) {
            return bad("preview_quality", format!("is {}, must be 1..=100", self.preview_quality));
        }
        for (id, c) in &self.cameras {
            let key = |k: &str| format!("cameras.{id}.{k}");
            if !is_camera_id(id) {
                return bad(&format!("cameras.{id}"), "is not a camera id (1-32 of [A-Za-z0-9_-])".into());
            }
            let spec = SourceSpec::parse(&c.source).map_err(|e| {
                Invalid::new(key("source"), format!("cameras config: `{}` of camera {id}: {e}", key("source")))
            })?;
            if (c.width == 0) != (c.height == 0) {
                return bad(&key("width"), format!("and height are {}x{}: give both or neither", c.width, c.height));
            }
            if c.width == 0 && !matches!(spec, SourceSpec::Mjpeg { .. }) {
                return bad(
                    &key("width"),
                    format!("is not set: camera {id}'s source {} needs width and height", c.source),
                );
            }
            if c.width == 0 && c.intrinsics.is_some() {
                return bad(
                    &key("intrinsics"),
                    format!("are set but camera {id} has no width x height to scale them to"),
                );
            }
            if c.rectifies(&spec) {
                let why = if c.side_by_side == Some(false) {
                    Some("needs the side-by-side frame (side_by_side = false)".to_owned())
                } else if !matches!(&c.intrinsics, Some(IntrinsicsSpec::File(p)) if p.extension().is_some_and(|e| e == "conf"))
                {
                    Some("needs the camera's factory file as `intrinsics` (SN<serial>.conf)".to_owned())
                } else if !crate::intrinsics::ZED_RESOLUTIONS.iter().any(|(_, w, h)| (*w, *h) == (c.width, c.height)) {
                    Some(format!(
                        "needs one of the ZED's own sizes per eye (2208x1242, 1920x1080, 1280x720, 672x376), not {}x{}",
                        c.width, c.height
                    ))
                } else {
                    None
                };
                if let Some(why) = why {
                    return bad(
                        &key("rectify"),
                        format!(
                            "is on (the default for a ZED): camera {id}'s rectification {why}; or set rectify = false to publish the raw eye"
                        ),
                    );
                }
            }
            if c.jpeg_passthrough {
                let mjpeg = match &spec {
                    SourceSpec::Mjpeg { .. } => true,
                    SourceSpec::Device { kind, .. } => *kind != DeviceKind::Zed,
                    _ => false,
                };
                if !mjpeg || c.side_by_side == Some(true) {
                    return bad(
                        &key("jpeg_passthrough"),
                        format!(
                            "needs an MJPEG source sending one image (http://, v4l2:, /dev/videoN); camera {id}'s is {}{}",
                            c.source,
                            if c.side_by_side == Some(true) {
                                " with side_by_side (the eye must be cut out)"
                            } else {
                                ""
                            }
                        ),
                    );
                }
            }
            if c.realsense_calibration.is_some() {
                if !matches!(spec, SourceSpec::RealSense { file: None, .. }) {
                    return bad(
                        &key("realsense_calibration"),
                        format!(
                            "is for a RealSense device read over V4L2 (realsense:SERIAL or realsense); camera {id}'s source is {}",
                            c.source
                        ),
                    );
                }
                if c.intrinsics.is_some() {
                    return bad(
                        &key("intrinsics"),
                        format!(
                            "and realsense_calibration are both set for camera {id}: the calibration file has the colour intrinsics"
                        ),
                    );
                }
            }
            if c.depth {
                if !matches!(spec, SourceSpec::RealSense { .. }) {
                    return bad(
                        &key("depth"),
                        format!(
                            "is for a RealSense (realsense:SERIAL or a recording); camera {id}'s source is {}",
                            c.source
                        ),
                    );
                }
                if !is_camera_id(&depth_id(id)) {
                    return bad(
                        &key("depth"),
                        format!("needs a camera id of at most 26 characters (its depth is `{}`)", depth_id(id)),
                    );
                }
            }
            if c.right_eye {
                if !c.rectifies(&spec) || c.eye != Eye::Left {
                    return bad(
                        &key("right_eye"),
                        format!(
                            "is for a rectified ZED publishing its left eye (the right eye's pose follows from the rectified pair); camera {id} has rectify = {}, eye = {:?}",
                            c.rectifies(&spec),
                            c.eye
                        ),
                    );
                }
                if !is_camera_id(&right_id(id)) {
                    return bad(
                        &key("right_eye"),
                        format!("needs a camera id of at most 26 characters (its right eye is `{}`)", right_id(id)),
                    );
                }
            }
            if !(c.fps.is_finite() && (1.0..=240.0).contains(&c.fps)) {
                return bad(&key("fps"), format!("is {}, must be 1..=240", c.fps));
            }
            if let Some(e) = c.extrinsics
                && e.iter().any(|v| !v.is_finite())
            {
                return bad(&key("extrinsics"), format!("has a value that is not a number: {e:?}"));
            }
        }
        Ok(())
    }

    /// Makes relative source and intrinsics paths relative to the config file's directory.
    pub fn resolve_paths(&mut self, file: &Path) {
        let dir = file.parent().unwrap_or(Path::new("."));
        for c in self.cameras.values_mut() {
            let looks_like_file = !c.source.contains("://")
                && !c.source.contains(':')
                && !c.source.starts_with("/dev/")
                && !["testsrc", "zed", "realsense", "v4l2"].contains(&c.source.as_str());
            if looks_like_file && Path::new(&c.source).is_relative() {
                c.source = dir.join(&c.source).display().to_string();
            }
            if let Some(IntrinsicsSpec::File(p)) = &mut c.intrinsics
                && p.is_relative()
            {
                *p = dir.join(&*p);
            }
            if let Some(p) = &mut c.realsense_calibration
                && p.is_relative()
            {
                *p = dir.join(&*p);
            }
        }
    }
}

/// A camera ready to run: its source parsed, its intrinsics loaded and scaled.
#[derive(Debug, Clone)]
pub struct Camera {
    pub id: String,
    pub spec: SourceSpec,
    pub config: CameraConfig,
    pub side_by_side: Option<Eye>,
    pub intrinsics: Option<Intrinsics>,
    /// A rectified ZED eye: its remap table (computed once here) and camera_info.
    pub rectifier: Option<std::sync::Arc<EyeRectifier>>,
    /// The same ZED's rectified right eye, published as camera `<id>_right` (`right_eye`).
    pub right: Option<std::sync::Arc<EyeRectifier>>,
    /// A RealSense read over V4L2: its calibration (loaded and checked here).
    pub realsense: Option<std::sync::Arc<RealSenseCalibration>>,
}

#[derive(Debug, thiserror::Error)]
pub enum CameraError {
    #[error("camera {camera}: {source}")]
    Intrinsics { camera: String, source: IntrinsicsError },
    #[error("camera {camera}: {source}")]
    Source { camera: String, source: SourceError },
    #[error("camera {camera}: {reason}")]
    RealSense { camera: String, reason: String },
}

impl Camera {
    /// Loads what a camera needs before it starts; a missing or unreadable calibration file,
    /// a section it lacks, a size it does not scale to: refused, naming the camera.
    ///
    /// A source named by its kind alone (`zed`, `realsense`, `v4l2`) takes the camera's serial
    /// from the rig's devices (`rig.devices.camera_serials`, handed by the launcher).
    pub fn resolve(id: &str, c: &CameraConfig, devices: Option<&Devices>) -> Result<Camera, CameraError> {
        let source_error = |source| CameraError::Source { camera: id.into(), source };
        let mut spec = SourceSpec::parse(&c.source).map_err(source_error)?;
        if spec.needs_serial() {
            let serial = devices.and_then(|d| d.camera_serials.get(id)).ok_or_else(|| {
                source_error(SourceError::NoSerial { source_name: c.source.clone(), camera: id.into() })
            })?;
            spec = spec.with_serial(serial);
        }
        let sbs = c.side_by_side.unwrap_or_else(|| spec.side_by_side_default());
        let intr = |source| CameraError::Intrinsics { camera: id.into(), source };
        if c.rectifies(&spec)
            && let Some(IntrinsicsSpec::File(p)) = &c.intrinsics
        {
            let zed = ZedCalibration::load(p).map_err(intr)?;
            let r = EyeRectifier::new(&zed, c.eye, c.width, c.height).map_err(intr)?;
            let right = if c.right_eye {
                Some(std::sync::Arc::new(EyeRectifier::new(&zed, Eye::Right, c.width, c.height).map_err(intr)?))
            } else {
                None
            };
            return Ok(Camera {
                id: id.to_owned(),
                spec,
                config: c.clone(),
                side_by_side: Some(c.eye),
                intrinsics: Some(r.intrinsics()),
                rectifier: Some(std::sync::Arc::new(r)),
                right,
                realsense: None,
            });
        }
        if let Some(p) = &c.realsense_calibration {
            let rs_err = |reason: String| CameraError::RealSense { camera: id.into(), reason };
            let cal = RealSenseCalibration::load(p).map_err(|e| rs_err(e.to_string()))?;
            cal.check().map_err(|e| rs_err(format!("{}: {e}", p.display())))?;
            if let SourceSpec::RealSense { serial: Some(s), .. } = &spec
                && !cal.serial.is_empty()
                && &cal.serial != s
            {
                return Err(rs_err(format!(
                    "{} is the calibration of RealSense {}, the camera is {s}: export this camera's (labrig cameras realsense-export --serial {s})",
                    p.display(),
                    cal.serial
                )));
            }
            if (cal.colour.width, cal.colour.height) != (c.width, c.height) {
                return Err(rs_err(format!(
                    "{} was exported at {}x{}, the camera runs at {}x{}: export it at that size (--width {} --height {})",
                    p.display(),
                    cal.colour.width,
                    cal.colour.height,
                    c.width,
                    c.height,
                    c.width,
                    c.height
                )));
            }
            return Ok(Camera {
                id: id.to_owned(),
                spec,
                config: c.clone(),
                side_by_side: None,
                intrinsics: Some(cal.colour_intrinsics()),
                rectifier: None,
                right: None,
                realsense: Some(std::sync::Arc::new(cal)),
            });
        }
        let intrinsics = match &c.intrinsics {
            None => None,
            Some(IntrinsicsSpec::Inline(i)) => {
                let i = Intrinsics {
                    source: if i.source.is_empty() { "config".into() } else { i.source.clone() },
                    ..i.clone()
                };
                Some(i.scaled(c.width, c.height).map_err(|e| intr(e.into()))?)
            }
            Some(IntrinsicsSpec::File(p)) if p.extension().is_some_and(|e| e == "conf") => {
                Some(ZedCalibration::load(p).and_then(|z| z.eye(c.eye, c.width, c.height)).map_err(intr)?)
            }
            Some(IntrinsicsSpec::File(p)) => {
                Some(crate::intrinsics::load(p).and_then(|i| Ok(i.scaled(c.width, c.height)?)).map_err(intr)?)
            }
        };
        Ok(Camera {
            id: id.to_owned(),
            spec,
            config: c.clone(),
            side_by_side: sbs.then_some(c.eye),
            intrinsics,
            rectifier: None,
            right: None,
            realsense: None,
        })
    }

    /// A device camera is checked before the node starts: found by its serial, offering the
    /// configured mode (opened once and closed). A wrong serial or a mode the device does not
    /// offer is refused, naming the camera, what was found and the modes offered. Streams and
    /// files are not: they may come up later, and are retried.
    pub fn check_device(&self, t: Timeouts) -> Result<(), CameraError> {
        if matches!(self.spec, SourceSpec::Device { .. } | SourceSpec::RealSense { serial: Some(_), .. }) {
            self.open(t).map_err(|source| CameraError::Source { camera: self.id.clone(), source })?;
        }
        Ok(())
    }

    /// The size the source is asked for (both eyes of a side-by-side frame).
    fn source_size(&self) -> (u32, u32) {
        let w = if self.side_by_side.is_some() { self.config.width * 2 } else { self.config.width };
        (w, self.config.height)
    }

    fn open(&self, t: Timeouts) -> Result<Box<dyn Source>, SourceError> {
        match &self.spec {
            SourceSpec::Mjpeg { url } => Ok(Box::new(MjpegSource::open(url, t)?)),
            SourceSpec::TestPattern => Ok(Box::new(FfmpegSource::test_pattern(self.source_size(), self.config.fps)?)),
            SourceSpec::RealSense { serial: Some(s), file: None } if self.realsense.is_some() => {
                Ok(Box::new(crate::realsense::RealSenseV4l2::open(
                    s,
                    self.realsense.clone().expect("a calibration"),
                    self.config.fps,
                    self.config.depth,
                    t.read,
                )?))
            }
            SourceSpec::RealSense { serial, file } => Ok(Box::new(RealSenseSource::open(
                serial.as_deref(),
                file.as_deref(),
                self.source_size(),
                self.config.fps,
                self.config.loop_file,
                self.config.depth,
            )?)),
            SourceSpec::Ffmpeg { input, file } => {
                Ok(Box::new(FfmpegSource::open(input, *file, self.source_size(), self.config.loop_file)?))
            }
            SourceSpec::Device { kind, serial, path } => {
                let path = match (serial, path) {
                    (_, Some(p)) => p.clone(),
                    (Some(s), None) => crate::v4l2::find(*kind, s)?,
                    (None, None) => unreachable!("a device source has a serial or a path"),
                };
                let formats: &[&str] = match kind {
                    DeviceKind::Zed => &["YUYV"],
                    _ if self.config.jpeg_passthrough => &["MJPG"],
                    _ => &["MJPG", "YUYV"],
                };
                Ok(Box::new(crate::v4l2::V4l2Source::open(
                    &path,
                    formats,
                    self.source_size(),
                    self.config.fps,
                    t.read,
                )?))
            }
        }
    }

    /// `/tf_static`'s transform base -> `<id>_optical`, if the camera has extrinsics.
    pub fn transform(&self, base: &str, stamp: Time) -> Option<TransformStamped> {
        let [x, y, z, rx, ry, rz] = self.config.extrinsics?;
        let q = UnitQuaternion::from_rotation_matrix(&Rotation3::from_euler_angles(rx, ry, rz));
        Some(TransformStamped {
            header: Header { stamp, frame_id: base.to_owned() },
            child_frame_id: optical_frame(&self.id),
            transform: Transform {
                translation: Vector3 { x, y, z },
                rotation: Quaternion { x: q.i, y: q.j, z: q.k, w: q.w },
            },
        })
    }
}

impl Camera {
    /// `/tf_static`'s transform `<id>_optical` -> `<id>_right_optical` of a ZED publishing its
    /// right eye: the rectified baseline along x, no rotation (both eyes rectified share one
    /// orientation; the left eye's image and K see `<id>_optical` as the rectified left eye).
    pub fn right_transform(&self, stamp: Time) -> Option<TransformStamped> {
        let r = self.right.as_ref()?;
        Some(TransformStamped {
            header: Header { stamp, frame_id: optical_frame(&self.id) },
            child_frame_id: optical_frame(&right_id(&self.id)),
            transform: Transform {
                translation: Vector3 { x: r.rectification.baseline_m, y: 0.0, z: 0.0 },
                rotation: Quaternion { x: 0.0, y: 0.0, z: 0.0, w: 1.0 },
            },
        })
    }
}

/// `/tf_static`'s transform for a calibrated camera: its calibration's parent (`base`, named
/// `base` as configured, or `tcp` for an eye-in-hand camera) -> `<id>_optical`.
pub fn calibrated_transform(
    f: &labrig_msgs::calibration::CalibrationFile,
    base: &str,
    stamp: Time,
) -> TransformStamped {
    let [x, y, z] = f.pose.position;
    let [w, qx, qy, qz] = f.pose.quaternion_wxyz;
    let parent = if f.parent_frame == "base" { base.to_owned() } else { f.parent_frame.clone() };
    TransformStamped {
        header: Header { stamp, frame_id: parent },
        child_frame_id: optical_frame(&f.camera),
        transform: Transform { translation: Vector3 { x, y, z }, rotation: Quaternion { x: qx, y: qy, z: qz, w } },
    }
}

/// The camera's optical frame name (as the sim bridge names it).
pub fn optical_frame(camera: &str) -> String {
    format!("{camera}_optical")
}

/// The wall clock minus CLOCK_MONOTONIC, read back to back (ns): maps V4L2 buffer times onto
/// the rig's clock.
fn wall_minus_monotonic() -> i64 {
    let ns = |t: rustix::time::Timespec| t.tv_sec * 1_000_000_000 + t.tv_nsec;
    let m0 = ns(rustix::time::clock_gettime(rustix::time::ClockId::Monotonic));
    let w = ns(rustix::time::clock_gettime(rustix::time::ClockId::Realtime));
    let m1 = ns(rustix::time::clock_gettime(rustix::time::ClockId::Monotonic));
    w - (m0 + m1) / 2
}

/// What a camera thread tells the node.
#[derive(Debug)]
enum Event {
    Up { camera: usize, description: String, intrinsics: Option<Intrinsics> },
    Down { camera: usize, reason: String },
    Frame(FrameEvent),
}

#[derive(Debug)]
struct FrameEvent {
    camera: usize,
    capture: Nanos,
    width: u32,
    height: u32,
    /// Frames the device's sequence skipped since the last one.
    dropped: u64,
    device_time: bool,
    preview: Option<Vec<u8>>,
}

#[derive(Debug, Clone)]
struct ThreadCtx {
    tx: tokio::sync::mpsc::Sender<Event>,
    shutdown: Shutdown,
    timeouts: Timeouts,
    retry: Duration,
    preview_period: Option<Duration>,
    preview_width: u32,
    preview_quality: u8,
}

fn sleep_unless(shutdown: &Shutdown, d: Duration) {
    let until = Instant::now() + d;
    while !shutdown.is_triggered() && Instant::now() < until {
        std::thread::sleep(Duration::from_millis(20).min(until.saturating_duration_since(Instant::now())));
    }
}

/// One camera's thread: open, read, convert, publish; reopen after a failure.
fn camera_thread(index: usize, cam: Camera, ctx: ThreadCtx) {
    let send = |e: Event| {
        // The node's side never blocks a camera: a full queue drops the report, not a frame.
        let _ = ctx.tx.try_send(e);
    };
    let frames = match FrameNode::new() {
        Ok(f) => f,
        Err(e) => {
            send(Event::Down { camera: index, reason: e.to_string() });
            return;
        }
    };
    let mut publisher: Option<FramePublisher> = None;
    let mut depth_publisher: Option<FramePublisher> = None;
    let mut right_publisher: Option<FramePublisher> = None;
    let mut last_preview: Option<Instant> = None;
    // A rectified frame's buffer, reused frame after frame.
    let mut rectified: Vec<u8> = Vec::new();
    let mut right_rectified: Vec<u8> = Vec::new();
    while !ctx.shutdown.is_triggered() {
        let mut source = match cam.open(ctx.timeouts) {
            Ok(s) => s,
            Err(e) => {
                send(Event::Down { camera: index, reason: e.to_string() });
                sleep_unless(&ctx.shutdown, ctx.retry);
                continue;
            }
        };
        send(Event::Up { camera: index, description: cam.config.source.clone(), intrinsics: source.intrinsics() });
        let mut last_seq: Option<u64> = None;
        while !ctx.shutdown.is_triggered() {
            let mut raw = match source.read() {
                Ok(r) => r,
                Err(e) => {
                    send(Event::Down { camera: index, reason: e.to_string() });
                    break;
                }
            };
            let arrival = Clock::Wall.now();
            let depth = raw.depth.take();
            let device_time = raw.device_monotonic_ns.is_some() || raw.capture_wall_ns.is_some();
            let capture = match (raw.capture_wall_ns, raw.device_monotonic_ns) {
                (Some(w), _) => Nanos(w),
                (None, Some(m)) => Nanos(m + wall_minus_monotonic()),
                (None, None) => arrival,
            };
            let want = (cam.config.width, cam.config.height);
            // The right eye, from the same side-by-side frame (`right_eye`: a rectified ZED).
            let right = cam.right.as_ref().map(|r| {
                to_rgb(raw.pixels.clone(), raw.size, Some(Eye::Right), want).map(|rgb| {
                    r.table.apply(&rgb, &mut right_rectified);
                    std::mem::take(&mut right_rectified)
                })
            });
            let converted = if cam.config.jpeg_passthrough {
                passthrough(raw.pixels, want).map(|(jpeg, size)| (Published::Jpeg(jpeg), size))
            } else if want == (0, 0) {
                // Whatever the source sends: the first frame fixes the size.
                publisher
                    .as_ref()
                    .map(|p| p.format().clone())
                    .map_or_else(|| first_size(&raw.pixels, raw.size, cam.side_by_side), |f| Ok((f.width, f.height)))
                    .and_then(|size| {
                        to_rgb(raw.pixels, raw.size, cam.side_by_side, size).map(|rgb| (Published::Rgb(rgb), size))
                    })
            } else {
                to_rgb(raw.pixels, raw.size, cam.side_by_side, want).map(|rgb| (Published::Rgb(rgb), want))
            };
            let (mut out, (w, h)) = match converted {
                Ok(c) => c,
                Err(e) => {
                    send(Event::Down { camera: index, reason: format!("{}: {e}", cam.config.source) });
                    sleep_unless(&ctx.shutdown, ctx.retry);
                    break;
                }
            };
            if let (Some(r), Published::Rgb(rgb)) = (&cam.rectifier, &mut out) {
                // The table was made for the configured size, which to_rgb has checked.
                r.table.apply(rgb, &mut rectified);
                std::mem::swap(rgb, &mut rectified);
            }
            if publisher.as_ref().is_some_and(|p| (p.format().width, p.format().height) != (w, h)) {
                send(Event::Down {
                    camera: index,
                    reason: format!(
                        "{}: the frames changed size to {w}x{h} from {}x{}",
                        cam.config.source,
                        publisher.as_ref().map_or(0, |p| p.format().width),
                        publisher.as_ref().map_or(0, |p| p.format().height)
                    ),
                });
                sleep_unless(&ctx.shutdown, ctx.retry);
                break;
            }
            if publisher.is_none() {
                let encoding = match out {
                    Published::Rgb(_) => FrameEncoding::Rgb8,
                    Published::Jpeg(_) => FrameEncoding::Jpeg,
                };
                match frames.publisher(&cam.id, FrameFormat { encoding, width: w, height: h }) {
                    Ok(p) => publisher = Some(p),
                    Err(e) => {
                        send(Event::Down { camera: index, reason: e.to_string() });
                        return;
                    }
                }
            }
            let bytes = match &out {
                Published::Rgb(b) | Published::Jpeg(b) => b,
            };
            if let Err(e) = publisher.as_mut().expect("publisher").publish(bytes, capture, arrival) {
                send(Event::Down { camera: index, reason: e.to_string() });
                break;
            }
            if let Some(right) = right {
                let published = right.map_err(|e| format!("right eye: {e}")).and_then(|rgb| {
                    if right_publisher.is_none() {
                        let format = FrameFormat { encoding: FrameEncoding::Rgb8, width: w, height: h };
                        right_publisher =
                            Some(frames.publisher(&right_id(&cam.id), format).map_err(|e| e.to_string())?);
                    }
                    let p = right_publisher.as_mut().expect("right publisher");
                    let sent = p.publish(&rgb, capture, arrival).map_err(|e| format!("right eye: {e}"));
                    right_rectified = rgb;
                    sent
                });
                if let Err(reason) = published {
                    send(Event::Down { camera: index, reason });
                    break;
                }
            }
            // Aligned depth: the colour frame's size, times and sequence.
            if let Some(depth) = depth {
                if depth_publisher.is_none() {
                    let format = FrameFormat { encoding: FrameEncoding::Depth16, width: w, height: h };
                    match frames.publisher(&depth_id(&cam.id), format) {
                        Ok(p) => depth_publisher = Some(p),
                        Err(e) => {
                            send(Event::Down { camera: index, reason: e.to_string() });
                            return;
                        }
                    }
                }
                if let Err(e) = depth_publisher.as_mut().expect("depth publisher").publish(&depth, capture, arrival) {
                    send(Event::Down { camera: index, reason: format!("depth: {e}") });
                    break;
                }
            }
            let dropped = match (last_seq, raw.device_sequence) {
                (Some(prev), Some(seq)) if seq > prev + 1 => seq - prev - 1,
                _ => 0,
            };
            last_seq = raw.device_sequence.or(last_seq);
            let preview = ctx.preview_period.and_then(|period| {
                let due = last_preview.is_none_or(|t| t.elapsed() >= period);
                due.then(|| {
                    last_preview = Some(Instant::now());
                    match &out {
                        Published::Rgb(rgb) => Some(preview_jpeg(rgb, w, h, ctx.preview_width, ctx.preview_quality)),
                        // Decoded only for the preview, at its low rate.
                        Published::Jpeg(jpeg) => crate::convert::decode_jpeg(jpeg)
                            .ok()
                            .map(|(rgb, w, h)| preview_jpeg(&rgb, w, h, ctx.preview_width, ctx.preview_quality)),
                    }
                })
                .flatten()
            });
            send(Event::Frame(FrameEvent {
                camera: index,
                capture,
                width: w,
                height: h,
                dropped,
                device_time,
                preview,
            }));
        }
    }
}

/// A frame as it leaves for shared memory.
enum Published {
    Rgb(Vec<u8>),
    /// An MJPEG source's JPEG, unchanged (`jpeg_passthrough`).
    Jpeg(Vec<u8>),
}

/// `jpeg_passthrough`: the source's JPEG as it came, with its size from the header; refused
/// when the source sends something else or another size than `want` (0 x 0: any).
fn passthrough(pixels: crate::convert::Pixels, want: (u32, u32)) -> Result<(Vec<u8>, (u32, u32)), ConvertError> {
    let size = first_size(&pixels, (0, 0), None)?;
    let crate::convert::Pixels::Jpeg(jpeg) = pixels else {
        return Err(ConvertError::Jpeg("jpeg_passthrough: the source sends raw frames, not JPEG".into()));
    };
    if want != (0, 0) && size != want {
        return Err(ConvertError::Jpeg(format!(
            "jpeg_passthrough: the source sends {}x{} JPEGs, the config asks for {}x{} (passthrough cannot resize: set width/height to the source's or turn it off)",
            size.0, size.1, want.0, want.1
        )));
    }
    Ok((jpeg, size))
}

/// The published size of a source's first frame (one eye of a side-by-side one).
fn first_size(pixels: &crate::convert::Pixels, size: (u32, u32), sbs: Option<Eye>) -> Result<(u32, u32), ConvertError> {
    let (w, h) = match pixels {
        crate::convert::Pixels::Jpeg(j) => {
            let mut d = zune_jpeg::JpegDecoder::new(j.as_slice());
            d.decode_headers().map_err(|e| ConvertError::Jpeg(format!("{e:?}")))?;
            let (w, h) = d.dimensions().ok_or_else(|| ConvertError::Jpeg("no size in the header".into()))?;
            (w as u32, h as u32)
        }
        _ => size,
    };
    Ok(if sbs.is_some() { (w / 2, h) } else { (w, h) })
}

/// A camera's state as `/cameras/status` reports it.
#[derive(Debug, Clone, Serialize)]
pub struct CameraStatus {
    /// `starting`, `streaming`, `stalled` (no frame for stall_s) or `down`.
    pub state: &'static str,
    /// Since when (wall clock, ns).
    pub since_ns: i64,
    /// Why it is down (the last error), empty otherwise.
    pub reason: String,
    pub source: String,
    pub frames: u64,
    pub dropped: u64,
    /// Times the camera went down.
    pub outages: u64,
    pub width: u32,
    pub height: u32,
    /// Frames per second over the last status period.
    pub fps: f64,
    /// `device` (the camera's capture time) or `arrival` (when the node received the frame).
    pub time_source: &'static str,
    /// A ZED's frames rectified from its factory file (camera_info: rectified K, D = 0, R, P).
    pub rectified: bool,
    #[serde(skip)]
    last_frame: Option<Instant>,
    #[serde(skip)]
    frames_at_last_status: u64,
}

/// What the node reports when it stops.
#[derive(Debug, Default, Serialize)]
pub struct CamerasStats {
    pub cameras: BTreeMap<String, CameraStatus>,
}

/// Runs the node until `shutdown`.
pub async fn run(config: CamerasConfig, shutdown: Shutdown) -> anyhow::Result<CamerasStats> {
    let devices = Devices::from_launcher()?;
    let cameras: Vec<Camera> =
        config.cameras.iter().map(|(id, c)| Camera::resolve(id, c, devices.as_ref())).collect::<Result<_, _>>()?;
    let timeouts = Timeouts {
        connect: Duration::from_secs_f64(config.stall_s.max(1.0)),
        read: Duration::from_secs_f64(2.0 * config.stall_s),
    };
    for c in &cameras {
        c.check_device(timeouts)?;
    }
    let mut ros = Ros::new(&config.ros, "labrig_cameras")?;
    let info_pubs: Vec<RosPublisher<CameraInfo>> = cameras
        .iter()
        .map(|c| ros.publisher(&topics::camera_info(&c.id), qos::reliable(10)))
        .collect::<Result<_, _>>()?;
    let right_info_pubs: Vec<Option<RosPublisher<CameraInfo>>> = cameras
        .iter()
        .map(|c| {
            c.right
                .as_ref()
                .map(|_| ros.publisher(&topics::camera_info(&right_id(&c.id)), qos::reliable(10)))
                .transpose()
        })
        .collect::<Result<_, _>>()?;
    let preview_pubs: Vec<RosPublisher<CompressedImage>> = cameras
        .iter()
        .map(|c| ros.publisher(&topics::camera_preview(&c.id), qos::reliable(2)))
        .collect::<Result<_, _>>()?;
    let status_pub = ros.publisher_on(&topics::CAMERAS_STATUS, 1)?;
    let tf_static = ros.publisher_on(&topics::TF_STATIC, 1)?;
    let now = Clock::Wall.now();
    let calibrations = config.calibration.as_ref().map(|dir| {
        let ids: Vec<&str> = cameras.iter().map(|c| c.id.as_str()).collect();
        let c = labrig_episode::calibration::load(dir, &ids);
        for w in c.warnings(now.0 / 1_000_000_000, config.calibration_max_age_s) {
            tracing::warn!("calibration: {w}");
        }
        c
    });
    let statics: Vec<TransformStamped> = cameras
        .iter()
        .filter_map(|c| match calibrations.as_ref().and_then(|k| k.files.get(&c.id)) {
            Some(f) => Some(calibrated_transform(f, &config.base_frame, Time::from(now))),
            None => c.transform(&config.base_frame, Time::from(now)),
        })
        .chain(cameras.iter().filter_map(|c| c.right_transform(Time::from(now))))
        .collect();
    if !statics.is_empty() {
        tf_static.publish(TFMessage { transforms: statics })?;
    }
    // Latched: kept for the node's life so a recorder that starts later still gets it.
    let _calibration_pub = match &calibrations {
        Some(c) => {
            let p = ros.publisher_on(&topics::CALIBRATION, 1)?;
            p.publish(StringMsg { data: c.summary().to_string() })?;
            Some(p)
        }
        None => None,
    };

    let (tx, mut rx) = tokio::sync::mpsc::channel::<Event>(1024);
    let ctx = ThreadCtx {
        tx,
        shutdown: shutdown.clone(),
        timeouts,
        retry: Duration::from_secs_f64(config.retry_s),
        preview_period: (config.preview_hz > 0.0).then(|| Duration::from_secs_f64(1.0 / config.preview_hz)),
        preview_width: config.preview_width,
        preview_quality: config.preview_quality,
    };
    let mut status: Vec<CameraStatus> = cameras
        .iter()
        .map(|c| CameraStatus {
            state: "starting",
            since_ns: now.0,
            reason: String::new(),
            source: c.config.source.clone(),
            frames: 0,
            dropped: 0,
            outages: 0,
            width: c.config.width,
            height: c.config.height,
            fps: 0.0,
            time_source: "arrival",
            rectified: c.rectifier.is_some(),
            last_frame: None,
            frames_at_last_status: 0,
        })
        .collect();
    let mut threads = Vec::new();
    for (i, cam) in cameras.iter().cloned().enumerate() {
        let ctx = ctx.clone();
        threads.push(
            std::thread::Builder::new().name(format!("camera-{}", cam.id)).spawn(move || camera_thread(i, cam, ctx))?,
        );
    }
    drop(ctx);
    tracing::info!(cameras = cameras.len(), "camera node up");

    let mut device_intrinsics: Vec<Option<Intrinsics>> = vec![None; cameras.len()];
    let period = Duration::from_secs_f64(config.status_period_s);
    let mut tick = tokio::time::interval(period);
    let mut last_tick = Instant::now();
    let stall = Duration::from_secs_f64(config.stall_s);
    loop {
        let mut changed = tokio::select! {
            _ = shutdown.wait() => break,
            ev = rx.recv() => {
                let Some(ev) = ev else { break };
                handle(ev, &cameras, &mut device_intrinsics, &mut status, (&info_pubs, &right_info_pubs), &preview_pubs)?
            }
            _ = tick.tick() => {
                let dt = last_tick.elapsed().as_secs_f64().max(1e-3);
                last_tick = Instant::now();
                for s in status.iter_mut() {
                    s.fps = (s.frames - s.frames_at_last_status) as f64 / dt;
                    s.frames_at_last_status = s.frames;
                }
                true
            }
        };
        // A camera with no frame for stall_s is stalled (its thread reopens it at 2 x stall_s).
        for (s, c) in status.iter_mut().zip(&cameras) {
            if s.state == "streaming" && s.last_frame.is_some_and(|t| t.elapsed() > stall) {
                s.state = "stalled";
                s.since_ns = Clock::Wall.now().0;
                s.reason = format!("no frame for {:.1} s", config.stall_s);
                tracing::warn!(camera = %c.id, "stalled: no frame for {:.1} s", config.stall_s);
                changed = true;
            }
        }
        if changed {
            publish_status(&status_pub, &cameras, &status)?;
        }
    }
    shutdown.trigger();
    // Each thread notices within its read timeout; the process does not wait longer than that.
    let deadline = Instant::now() + Duration::from_secs_f64(2.0 * config.stall_s + 0.5);
    for t in threads {
        while !t.is_finished() && Instant::now() < deadline {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        if t.is_finished() {
            let _ = t.join();
        }
    }
    Ok(CamerasStats { cameras: cameras.iter().map(|c| c.id.clone()).zip(status).collect() })
}

fn handle(
    ev: Event,
    cameras: &[Camera],
    device_intrinsics: &mut [Option<Intrinsics>],
    status: &mut [CameraStatus],
    (info, right_info): (&[RosPublisher<CameraInfo>], &[Option<RosPublisher<CameraInfo>>]),
    preview: &[RosPublisher<CompressedImage>],
) -> anyhow::Result<bool> {
    let now = Clock::Wall.now().0;
    match ev {
        Event::Up { camera, description, intrinsics } => {
            tracing::info!(camera = %cameras[camera].id, source = %description, "streaming");
            // The device's own intrinsics where the config gives none (a RealSense's).
            if cameras[camera].intrinsics.is_none() {
                device_intrinsics[camera] = intrinsics;
            }
            Ok(false)
        }
        Event::Down { camera, reason } => {
            let s = &mut status[camera];
            let changed = s.state != "down" || s.reason != reason;
            if s.state != "down" {
                if s.state != "starting" {
                    s.outages += 1;
                }
                s.state = "down";
                s.since_ns = now;
                tracing::warn!(camera = %cameras[camera].id, "down: {reason}");
            }
            s.reason = reason;
            Ok(changed)
        }
        Event::Frame(f) => {
            let cam = &cameras[f.camera];
            let s = &mut status[f.camera];
            let changed = s.state != "streaming";
            if changed {
                s.state = "streaming";
                s.since_ns = now;
                s.reason.clear();
            }
            s.frames += 1;
            s.dropped += f.dropped;
            s.last_frame = Some(Instant::now());
            (s.width, s.height) = (f.width, f.height);
            s.time_source = if f.device_time { "device" } else { "arrival" };
            let stamp = Time::from(f.capture);
            let frame_id = optical_frame(&cam.id);
            let msg = match (&cam.rectifier, cam.intrinsics.as_ref().or(device_intrinsics[f.camera].as_ref())) {
                (Some(r), _) => r.camera_info(stamp, &frame_id),
                (None, Some(i)) => i.camera_info(stamp, &frame_id),
                (None, None) => CameraInfo {
                    header: Header { stamp, frame_id: frame_id.clone() },
                    width: f.width,
                    height: f.height,
                    distortion_model: "plumb_bob".into(),
                    d: vec![0.0; 5],
                    ..CameraInfo::default()
                },
            };
            info[f.camera].publish(msg)?;
            if let (Some(r), Some(p)) = (&cam.right, &right_info[f.camera]) {
                p.publish(r.camera_info(stamp, &optical_frame(&right_id(&cam.id))))?;
            }
            if let Some(jpeg) = f.preview {
                preview[f.camera].publish(CompressedImage {
                    header: Header { stamp, frame_id },
                    format: "jpeg".into(),
                    data: jpeg,
                })?;
            }
            Ok(changed)
        }
    }
}

fn publish_status(
    publisher: &RosPublisher<StringMsg>,
    cameras: &[Camera],
    status: &[CameraStatus],
) -> anyhow::Result<()> {
    let map: BTreeMap<&str, &CameraStatus> = cameras.iter().map(|c| c.id.as_str()).zip(status).collect();
    let json = serde_json::json!({ "stamp_ns": Clock::Wall.now().0, "cameras": map });
    publisher.publish(StringMsg { data: json.to_string() })?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config(toml_text: &str) -> CamerasConfig {
        toml::from_str(toml_text).unwrap()
    }

    #[test]
    fn configs_are_checked_by_key() {
        let c = config("[cameras.ext1]\nsource = \"http://127.0.0.1:9/cam\"\n");
        c.validate().unwrap();
        let e = config("[cameras.ext1]\nsource = \"rtsp://127.0.0.1/x\"\n").validate().unwrap_err();
        assert!(e.to_string().contains("`cameras.ext1.width` is not set"), "{e}");
        let e = config("[cameras.ext1]\nsource = \"zed:1\"\nwidth = 1280\n").validate().unwrap_err();
        assert!(e.to_string().contains("give both or neither"), "{e}");
        let e = config("[cameras.ext1]\nsource = \"gopher://x\"\n").validate().unwrap_err();
        assert_eq!(e.key, "cameras.ext1.source");
        let e = CamerasConfig::default().validate().unwrap_err();
        assert!(e.to_string().contains("`cameras` is empty"), "{e}");
        assert!(toml::from_str::<CamerasConfig>("[cameras.ext1]\nsource = \"x\"\nfocal = 3\n").is_err());
    }

    #[test]
    fn a_source_named_by_its_kind_takes_the_serial_from_the_rigs_devices() {
        let mut c = CameraConfig::new("zed");
        (c.width, c.height) = (1280, 720);
        let devices =
            Devices { camera_serials: [("ext1".to_owned(), "ZED2-7".to_owned())].into(), ..Devices::default() };
        let cam = Camera::resolve("ext1", &c, Some(&devices)).unwrap();
        assert_eq!(cam.spec, SourceSpec::Device { kind: DeviceKind::Zed, serial: Some("ZED2-7".into()), path: None });
        assert_eq!(cam.side_by_side, Some(Eye::Left), "a ZED by kind is still side by side");
        let rs = Camera::resolve(
            "rs1",
            &CameraConfig::new("realsense"),
            Some(&Devices { camera_serials: [("rs1".to_owned(), "D435-4".to_owned())].into(), ..Devices::default() }),
        )
        .unwrap();
        assert_eq!(rs.spec, SourceSpec::RealSense { serial: Some("D435-4".into()), file: None });
        // No devices, or none for this camera: refused, naming the camera and where to put it.
        for d in [None, Some(&devices)] {
            let e = Camera::resolve("ext2", &c, d).unwrap_err().to_string();
            assert!(e.contains("camera ext2") && e.contains("rig.devices.camera_serials"), "{e}");
        }
        // A serial in the source is the source's own.
        let cam = Camera::resolve("ext1", &CameraConfig::new("zed:ZED2-9"), Some(&devices)).unwrap();
        assert_eq!(cam.spec, SourceSpec::Device { kind: DeviceKind::Zed, serial: Some("ZED2-9".into()), path: None });
    }

    #[test]
    fn a_zed_is_rectified_by_default_and_its_camera_info_says_so() {
        let fixture = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/SN000012345.conf");
        let conf = fixture.display();
        let ok = config(&format!(
            "[cameras.ext1]\nsource = \"zed:000012345\"\nwidth = 672\nheight = 376\nintrinsics = \"{conf}\"\n"
        ));
        ok.validate().unwrap();
        let c = &ok.cameras["ext1"];
        let cam = Camera::resolve("ext1", c, None).unwrap();
        let r = cam.rectifier.as_ref().expect("rectified by default");
        assert_eq!(cam.side_by_side, Some(Eye::Left));
        let i = cam.intrinsics.as_ref().unwrap();
        assert_eq!(
            (i.fx, i.fy, i.source.as_str()),
            (r.rectification.left.fx, r.rectification.left.fx, "zed-rectified")
        );
        assert!(i.fx < 264.625, "alpha 0 zooms in: {}", i.fx);
        let info = r.camera_info(Time::default(), "ext1_optical");
        assert_eq!(info.d, vec![0.0; 5]);
        assert_eq!(&info.k[..], &[i.fx, 0.0, i.cx, 0.0, i.fx, i.cy, 0.0, 0.0, 1.0][..]);
        assert_eq!(info.p[3], 0.0, "the left eye's P has no baseline term");
        assert!(info.r != [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0], "the rectifying rotation is in R");
        // The right eye as its own camera: P's Tx = -fx * baseline.
        let mut right = c.clone();
        right.eye = Eye::Right;
        let cam = Camera::resolve("ext1_right", &right, None).unwrap();
        let p = cam.rectifier.unwrap().camera_info(Time::default(), "ext1_right_optical").p;
        assert!((p[3] / -p[0] - 0.11998).abs() < 1e-3, "{p:?}");
        // Raw on request: the factory intrinsics, distortion and all.
        let mut raw = c.clone();
        raw.rectify = Some(false);
        let cam = Camera::resolve("ext1", &raw, None).unwrap();
        assert!(cam.rectifier.is_none());
        assert_eq!(cam.intrinsics.unwrap().distortion[0], -0.0412);
        // What rectification needs, each named by key.
        for (extra, size, want) in [
            ("", "width = 672\nheight = 376\n", "needs the camera's factory file"),
            (&*format!("intrinsics = \"{conf}\"\n"), "width = 640\nheight = 360\n", "not 640x360"),
            (
                &*format!("intrinsics = \"{conf}\"\nside_by_side = false\n"),
                "width = 672\nheight = 376\n",
                "side_by_side = false",
            ),
        ] {
            let e = config(&format!("[cameras.ext1]\nsource = \"zed:1\"\n{size}{extra}")).validate().unwrap_err();
            assert_eq!(e.key, "cameras.ext1.rectify");
            assert!(e.to_string().contains(want) && e.to_string().contains("rectify = false"), "{e}");
        }
        // Not a ZED: raw unless asked.
        assert!(!CameraConfig::new("testsrc").rectifies(&SourceSpec::TestPattern));
        // The right eye too: its own rectifier; only for a rectified ZED's left eye.
        let mut both = c.clone();
        both.right_eye = true;
        let cam = Camera::resolve("ext1", &both, None).unwrap();
        let right = cam.right.as_ref().expect("the right eye's rectifier");
        assert_eq!(right.eye, Eye::Right);
        let t = cam.right_transform(Time::default()).unwrap();
        assert_eq!((t.header.frame_id.as_str(), t.child_frame_id.as_str()), ("ext1_optical", "ext1_right_optical"));
        assert!((t.transform.translation.x - 0.11998).abs() < 1e-3, "{t:?}");
        assert!(Camera::resolve("ext1", c, None).unwrap().right_transform(Time::default()).is_none());
        let zed = format!(
            "[cameras.ext1]\nsource = \"zed:1\"\nwidth = 672\nheight = 376\nintrinsics = \"{conf}\"\nright_eye = true\n"
        );
        config(&zed).validate().unwrap();
        for (extra, want) in [("rectify = false\n", "rectify = false"), ("eye = \"right\"\n", "eye = Right")] {
            let e = config(&format!("{zed}{extra}")).validate().unwrap_err();
            assert_eq!(e.key, "cameras.ext1.right_eye");
            assert!(e.to_string().contains(want), "{e}");
        }
    }

    #[test]
    fn a_realsense_with_a_calibration_file_is_read_in_rust_and_the_file_must_be_its_own() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("rs1.json");
        let stream = |w: u32, h: u32, f: f32| {
            serde_json::json!({"width": w, "height": h, "fx": f, "fy": f, "ppx": 319.5, "ppy": 239.5,
                               "model": "brown_conrady", "coeffs": [0.0, 0.0, 0.0, 0.0, 0.0]})
        };
        let write = |serial: &str, coeffs0: f32| {
            let mut colour = stream(640, 480, 612.0);
            colour["coeffs"][0] = coeffs0.into();
            let cal = serde_json::json!({"serial": serial, "colour": colour, "depth": stream(848, 480, 420.0),
                "depth_to_colour": {"rotation": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0], "translation": [0.015, 0.0, 0.0]},
                "depth_scale_m": 0.001});
            std::fs::write(&file, cal.to_string()).unwrap();
        };
        let toml = format!(
            "[cameras.rs1]\nsource = \"realsense:D435-1\"\nwidth = 640\nheight = 480\ndepth = true\nrealsense_calibration = \"{}\"\n",
            file.display()
        );
        let c = config(&toml);
        c.validate().unwrap();
        write("D435-1", 0.0);
        let cam = Camera::resolve("rs1", &c.cameras["rs1"], None).unwrap();
        assert!(cam.realsense.is_some());
        let i = cam.intrinsics.unwrap();
        assert_eq!((i.fx, i.cx, i.source.as_str()), (612.0, 319.5, "realsense"));
        // Another camera's file, a size it was not exported at, distortion: refused by name.
        write("D435-2", 0.0);
        let e = Camera::resolve("rs1", &c.cameras["rs1"], None).unwrap_err().to_string();
        assert!(e.contains("the calibration of RealSense D435-2, the camera is D435-1"), "{e}");
        write("D435-1", 0.1);
        let e = Camera::resolve("rs1", &c.cameras["rs1"], None).unwrap_err().to_string();
        assert!(e.contains("the colour stream's distortion"), "{e}");
        write("D435-1", 0.0);
        let mut big = c.cameras["rs1"].clone();
        (big.width, big.height) = (1280, 720);
        let e = Camera::resolve("rs1", &big, None).unwrap_err().to_string();
        assert!(e.contains("was exported at 640x480, the camera runs at 1280x720"), "{e}");
        // Only for a device read over V4L2.
        let e = config(&toml.replace("realsense:D435-1", "testsrc")).validate().unwrap_err();
        assert_eq!(e.key, "cameras.rs1.realsense_calibration");
        let e = config(&format!("{toml}intrinsics = \"x.json\"\n")).validate().unwrap_err();
        assert_eq!(e.key, "cameras.rs1.intrinsics");
    }

    #[test]
    fn intrinsics_come_from_a_zed_file_inline_or_nowhere_and_a_missing_file_is_named() {
        let fixture = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/SN000012345.conf");
        let mut c = CameraConfig::new("zed:000012345");
        (c.width, c.height) = (640, 360);
        c.intrinsics = Some(IntrinsicsSpec::File(fixture));
        c.rectify = Some(false);
        let cam = Camera::resolve("ext1", &c, None).unwrap();
        assert_eq!(cam.side_by_side, Some(Eye::Left));
        assert_eq!(cam.source_size(), (1280, 360));
        assert_eq!(cam.intrinsics.unwrap().fx, 264.75);
        c.intrinsics = Some(IntrinsicsSpec::File("/nowhere/SN1.conf".into()));
        let e = Camera::resolve("ext2", &c, None).unwrap_err().to_string();
        assert!(e.starts_with("camera ext2: /nowhere/SN1.conf: "), "{e}");
        let inline: CameraConfig = toml::from_str(
            "source = \"http://127.0.0.1:9/x\"\nwidth = 320\nheight = 180\n\
             intrinsics = { width = 1280, height = 720, fx = 600.0, fy = 600.0, cx = 639.5, cy = 359.5 }\n",
        )
        .unwrap();
        let cam = Camera::resolve("rs1", &inline, None).unwrap();
        let i = cam.intrinsics.unwrap();
        assert_eq!((i.fx, i.cx, i.cy), (150.0, 159.5, 89.5));
        assert_eq!(cam.side_by_side, None);
    }

    #[test]
    fn a_calibration_becomes_the_static_transform_from_its_parent_frame() {
        use labrig_msgs::calibration::{CalibrationFile, Mount, Pose};
        let text = r#"{"version":1,"rig":"lab","camera":"wrist","mount":"eye_in_hand","parent_frame":"tcp",
            "child_frame":"wrist_optical","pose":{"position":[0.01,0.09,0.03],"quaternion_wxyz":[0.0,1.0,0.0,0.0]},
            "droid_extrinsics":[0,0,0,0,0,0],"closed_form":{"position":[0,0,0],"quaternion_wxyz":[1,0,0,0]},
            "method":"daniilidis+refined","board_pose":{"position":[0,0,0],"quaternion_wxyz":[1,0,0,0]},
            "intrinsics":{"width":1280,"height":720,"fx":600,"fy":600,"cx":639.5,"cy":359.5,"source":"zed-factory"},
            "board":{"squares_x":9,"squares_y":14,"square_m":0.02,"marker_m":0.016,"dictionary":"DICT_5X5_100"},
            "rms_px":0.3,"views":[],"check":{"train_views":42,"test_views":18,"position_mse_m2":[0,0,0],
            "rotation_mse_rad2":[0,0,0],"mean_position_error_mm":0.2,"mean_rotation_error_deg":0.05,"pass":true},
            "date":"2026-11-25T12:00:00Z","unix_time_s":1795000000}"#;
        let f: CalibrationFile = serde_json::from_str(text).unwrap();
        assert_eq!(f.mount, Mount::EyeInHand);
        let t = calibrated_transform(&f, "fr3_link0", Time::default());
        assert_eq!((t.header.frame_id.as_str(), t.child_frame_id.as_str()), ("tcp", "wrist_optical"));
        assert_eq!((t.transform.translation.y, t.transform.rotation.x), (0.09, 1.0));
        let ext = CalibrationFile { parent_frame: "base".into(), camera: "ext1".into(), pose: Pose { ..f.pose }, ..f };
        let t = calibrated_transform(&ext, "fr3_link0", Time::default());
        assert_eq!((t.header.frame_id.as_str(), t.child_frame_id.as_str()), ("fr3_link0", "ext1_optical"));
    }

    #[test]
    fn extrinsics_become_a_static_transform_to_the_optical_frame() {
        let mut c = CameraConfig::new("http://127.0.0.1:9/x");
        c.extrinsics = Some([0.1, -0.5, 0.6, 0.0, 0.0, std::f64::consts::FRAC_PI_2]);
        let cam = Camera::resolve("ext1", &c, None).unwrap();
        let t = cam.transform("base", Time::default()).unwrap();
        assert_eq!((t.header.frame_id.as_str(), t.child_frame_id.as_str()), ("base", "ext1_optical"));
        assert_eq!((t.transform.translation.x, t.transform.translation.y), (0.1, -0.5));
        let q = t.transform.rotation;
        assert!(
            (q.z - std::f64::consts::FRAC_1_SQRT_2).abs() < 1e-12
                && (q.w - std::f64::consts::FRAC_1_SQRT_2).abs() < 1e-12
        );
    }

    #[test]
    fn jpeg_passthrough_is_for_mjpeg_sources_of_the_configured_size() {
        let ok = config("[cameras.ext1]\nsource = \"http://127.0.0.1:9/cam\"\njpeg_passthrough = true\n");
        assert!(ok.validate().is_ok());
        for (source, sbs) in [
            ("testsrc", ""),
            ("zed:SN1", "rectify = false\n"),
            ("rtsp://127.0.0.1/x", ""),
            ("http://127.0.0.1:9/c", "side_by_side = true\n"),
        ] {
            let c = config(&format!(
                "[cameras.ext1]\nsource = \"{source}\"\nwidth = 64\nheight = 48\njpeg_passthrough = true\n{sbs}"
            ));
            let e = c.validate().unwrap_err().to_string();
            assert!(
                e.contains("cameras.ext1.jpeg_passthrough") && e.contains("needs an MJPEG source"),
                "{source}: {e}"
            );
        }
        let rgb = vec![90u8; 16 * 8 * 3];
        let mut jpeg = Vec::new();
        jpeg_encoder::Encoder::new(&mut jpeg, 80).encode(&rgb, 16, 8, jpeg_encoder::ColorType::Rgb).unwrap();
        // The JPEG leaves unchanged, its size from its header.
        let (out, size) = passthrough(crate::convert::Pixels::Jpeg(jpeg.clone()), (0, 0)).unwrap();
        assert_eq!((out, size), (jpeg.clone(), (16, 8)));
        assert!(passthrough(crate::convert::Pixels::Jpeg(jpeg.clone()), (16, 8)).is_ok());
        let e = passthrough(crate::convert::Pixels::Jpeg(jpeg), (32, 16)).unwrap_err().to_string();
        assert!(e.contains("sends 16x8 JPEGs, the config asks for 32x16"), "{e}");
        let e = passthrough(crate::convert::Pixels::Yuyv(vec![0; 16 * 8 * 2]), (16, 8)).unwrap_err().to_string();
        assert!(e.contains("not JPEG"), "{e}");
    }
}
