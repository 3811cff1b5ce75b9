//! Where a camera's frames come from, one backend per kind of source. A source is opened on
//! the camera's own thread and read there (blocking); a read error closes it and the node
//! opens it again after a pause, so an unplugged camera or a restarted stream comes back.
//!
//! - `zed:SERIAL`, `v4l2:SERIAL`, `/dev/videoN`: a V4L2 device ([`crate::v4l2`]), found by its
//!   USB serial (never by its /dev/videoN order);
//! - `realsense:SERIAL`, or a RealSense recording (`.db3`/`.bag`): librealsense through
//!   pyrealsense2 in a child process ([`RealSenseSource`]);
//! - `http://host:port/path`: MJPEG over HTTP (multipart, as IP cameras and `ffmpeg -f mpjpeg`
//!   serve it), read natively: no decoder process, the JPEG goes straight to the decoder;
//! - `testsrc`: ffmpeg's moving test pattern at the configured size and rate;
//! - `rtsp://...` or a video file (a recorded DROID MP4, a webcam capture): decoded by an
//!   `ffmpeg` child process to raw RGB at the configured size, a file at its own frame rate
//!   (looped unless `loop_file = false`).

use crate::convert::Pixels;
use std::io::{BufRead, BufReader, Read};
use std::path::PathBuf;
use std::process::{Child, ChildStdout, Command, Stdio};
use std::time::Duration;

/// A camera's source as the config or the command line names it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum SourceSpec {
    /// A V4L2 device: by USB serial, or by path (quick checks).
    Device { kind: DeviceKind, serial: Option<String>, path: Option<PathBuf> },
    /// A RealSense through librealsense: a device by serial, or a recording played back.
    RealSense { serial: Option<String>, file: Option<PathBuf> },
    /// MJPEG over HTTP.
    Mjpeg { url: String },
    /// Anything ffmpeg reads (RTSP, a file), decoded by an ffmpeg child process.
    Ffmpeg { input: String, file: bool },
    /// ffmpeg's moving test pattern (`testsrc`: lavfi testsrc2) at the configured size and
    /// rate: a camera with no camera, for bench rigs and demos.
    TestPattern,
}

/// What kind of device a V4L2 source is (it decides the defaults: a ZED is side by side).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DeviceKind {
    /// ZED 2 / ZED Mini (USB vendor 0x2b03): YUYV, both eyes side by side.
    Zed,
    /// A RealSense (USB vendor 0x8086), seen as V4L2 devices; `realsense:SERIAL` reads it
    /// through librealsense instead, `v4l2:SERIAL` through its colour node.
    RealSense,
    /// Any UVC camera.
    Uvc,
}

impl DeviceKind {
    pub fn usb_vendor(self) -> Option<u16> {
        match self {
            DeviceKind::Zed => Some(0x2b03),
            DeviceKind::RealSense => Some(0x8086),
            DeviceKind::Uvc => None,
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum SourceError {
    #[error(
        "`{0}` is not a camera source: use zed:SERIAL, realsense:SERIAL, v4l2:SERIAL, /dev/videoN, http://..., rtsp://..., a video file or testsrc"
    )]
    Unknown(String),
    #[error(
        "`{source_name}` names no serial, and the launch config's rig.devices.camera_serials has none for camera {camera} (give it one there, or write {source_name}:SERIAL)"
    )]
    NoSerial { source_name: String, camera: String },
    #[error("{0}: no such video file")]
    NoFile(String),
    #[error("{url}: {reason}")]
    Http { url: String, reason: String },
    #[error("{source_name}: the stream ended")]
    Ended { source_name: String },
    #[error("{source_name}: {reason}")]
    Io { source_name: String, reason: String },
    #[error("{0}")]
    Device(String),
}

impl SourceSpec {
    pub fn parse(s: &str) -> Result<SourceSpec, SourceError> {
        let device = |kind, serial: &str| {
            if serial.is_empty() {
                return Err(SourceError::Unknown(s.to_owned()));
            }
            Ok(SourceSpec::Device { kind, serial: Some(serial.to_owned()), path: None })
        };
        // A kind alone: the serial is the rig's (`rig.devices.camera_serials`, handed by the
        // launcher; [`SourceSpec::with_serial`]).
        match s {
            "zed" => return Ok(SourceSpec::Device { kind: DeviceKind::Zed, serial: None, path: None }),
            "v4l2" => return Ok(SourceSpec::Device { kind: DeviceKind::Uvc, serial: None, path: None }),
            "realsense" => return Ok(SourceSpec::RealSense { serial: None, file: None }),
            _ => {}
        }
        if let Some(serial) = s.strip_prefix("zed:") {
            return device(DeviceKind::Zed, serial);
        }
        if let Some(serial) = s.strip_prefix("realsense:") {
            if serial.is_empty() {
                return Err(SourceError::Unknown(s.to_owned()));
            }
            return Ok(SourceSpec::RealSense { serial: Some(serial.to_owned()), file: None });
        }
        if let Some(serial) = s.strip_prefix("v4l2:") {
            return device(DeviceKind::Uvc, serial);
        }
        if s == "testsrc" {
            return Ok(SourceSpec::TestPattern);
        }
        if s.starts_with("/dev/video") {
            return Ok(SourceSpec::Device { kind: DeviceKind::Uvc, serial: None, path: Some(PathBuf::from(s)) });
        }
        if s.starts_with("http://") {
            return Ok(SourceSpec::Mjpeg { url: s.to_owned() });
        }
        if s.starts_with("rtsp://") || s.starts_with("rtsps://") {
            return Ok(SourceSpec::Ffmpeg { input: s.to_owned(), file: false });
        }
        if s.contains("://") || s.is_empty() {
            return Err(SourceError::Unknown(s.to_owned()));
        }
        if !std::path::Path::new(s).is_file() {
            return Err(SourceError::NoFile(s.to_owned()));
        }
        if s.ends_with(".db3") || s.ends_with(".bag") {
            return Ok(SourceSpec::RealSense { serial: None, file: Some(PathBuf::from(s)) });
        }
        Ok(SourceSpec::Ffmpeg { input: s.to_owned(), file: true })
    }

    /// A device named by its kind alone (`zed`, `realsense`, `v4l2`), whose serial comes from the
    /// rig's devices.
    pub fn needs_serial(&self) -> bool {
        matches!(
            self,
            SourceSpec::Device { serial: None, path: None, .. } | SourceSpec::RealSense { serial: None, file: None }
        )
    }

    /// The device with `serial` (for a source that [needs one](Self::needs_serial)).
    pub fn with_serial(self, serial: &str) -> SourceSpec {
        match self {
            SourceSpec::Device { kind, serial: None, path: None } => {
                SourceSpec::Device { kind, serial: Some(serial.to_owned()), path: None }
            }
            SourceSpec::RealSense { serial: None, file: None } => {
                SourceSpec::RealSense { serial: Some(serial.to_owned()), file: None }
            }
            other => other,
        }
    }

    /// Whether the frames carry a stereo pair side by side by default (the ZEDs).
    pub fn side_by_side_default(&self) -> bool {
        matches!(self, SourceSpec::Device { kind: DeviceKind::Zed, .. })
    }
}

/// One frame as read from a source.
#[derive(Debug)]
pub struct RawFrame {
    pub pixels: Pixels,
    /// The frame's size as sent ((0, 0) for a JPEG: its own header says).
    pub size: (u32, u32),
    /// The device's capture time on CLOCK_MONOTONIC (V4L2 buffer time), if it has one.
    pub device_monotonic_ns: Option<i64>,
    /// The device's frame counter, if it has one (gaps are drops).
    pub device_sequence: Option<u64>,
    /// The device's capture time already on the wall clock (librealsense's global or system
    /// time domain), ns.
    pub capture_wall_ns: Option<i64>,
    /// Depth aligned to this frame's (colour) image, same size: uint16 little endian,
    /// millimetres, 0 = none (a RealSense with `depth = true`).
    pub depth: Option<Vec<u8>>,
}

/// A source opened and streaming.
pub trait Source {
    /// The next frame (blocking, bounded by the source's read timeout).
    fn read(&mut self) -> Result<RawFrame, SourceError>;

    /// The intrinsics the device itself reports (a RealSense's), if any.
    fn intrinsics(&self) -> Option<crate::intrinsics::Intrinsics> {
        None
    }
}

/// How long a read may block before the source is closed and opened again.
#[derive(Debug, Clone, Copy)]
pub struct Timeouts {
    pub connect: Duration,
    pub read: Duration,
}

// ------------------------------------------------------------------ MJPEG over HTTP

/// MJPEG over HTTP: a `multipart/x-mixed-replace` body whose parts are JPEG images (the
/// boundary from the Content-Type, or the body's first line where the server names none, as
/// ffmpeg's `mpjpeg` muxer does); parts with a Content-Length are read by length, others up
/// to the next boundary.
pub struct MjpegSource {
    url: String,
    body: BufReader<Box<dyn Read + Send + Sync>>,
    boundary: Option<Vec<u8>>,
}

impl std::fmt::Debug for MjpegSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "MjpegSource({})", self.url)
    }
}

impl MjpegSource {
    pub fn open(url: &str, t: Timeouts) -> Result<MjpegSource, SourceError> {
        let http = |reason: String| SourceError::Http { url: url.to_owned(), reason };
        let agent = ureq::AgentBuilder::new().timeout_connect(t.connect).timeout_read(t.read).build();
        // ureq's message starts with the URL itself.
        let resp = agent
            .get(url)
            .call()
            .map_err(|e| http(e.to_string().trim_start_matches(url).trim_start_matches(": ").to_owned()))?;
        let boundary = resp
            .header("content-type")
            .and_then(|ct| ct.split(';').find_map(|p| p.trim().strip_prefix("boundary=")))
            .map(|b| b.trim_matches('"').trim_start_matches("--").as_bytes().to_vec());
        Ok(MjpegSource { url: url.to_owned(), body: BufReader::with_capacity(1 << 20, resp.into_reader()), boundary })
    }

    /// Wraps any reader of a multipart body (tests).
    pub fn from_reader(name: &str, r: Box<dyn Read + Send + Sync>, boundary: Option<&str>) -> MjpegSource {
        MjpegSource { url: name.to_owned(), body: BufReader::new(r), boundary: boundary.map(|b| b.as_bytes().to_vec()) }
    }

    fn line(&mut self) -> Result<Vec<u8>, SourceError> {
        let mut line = Vec::new();
        let n = self.body.read_until(b'\n', &mut line).map_err(|e| self.io(e))?;
        if n == 0 {
            return Err(SourceError::Ended { source_name: self.url.clone() });
        }
        Ok(line)
    }

    fn io(&self, e: std::io::Error) -> SourceError {
        SourceError::Io { source_name: self.url.clone(), reason: e.to_string() }
    }

    fn is_boundary(&self, line: &[u8]) -> bool {
        let l = trim_crlf(line);
        match &self.boundary {
            Some(b) => l.strip_prefix(b"--").is_some_and(|rest| rest.starts_with(b)),
            None => false,
        }
    }

    /// The next part's JPEG bytes.
    pub fn next_part(&mut self) -> Result<Vec<u8>, SourceError> {
        // Up to the boundary line (the first one names the boundary if the headers did not).
        let mut skipped = 0usize;
        loop {
            let line = self.line()?;
            let l = trim_crlf(&line);
            if l.is_empty() {
                continue;
            }
            if self.boundary.is_none() && l.starts_with(b"--") {
                self.boundary = Some(l[2..].to_vec());
                break;
            }
            if self.is_boundary(&line) {
                break;
            }
            skipped += line.len();
            if skipped > 16 << 20 {
                return Err(SourceError::Io {
                    source_name: self.url.clone(),
                    reason: "no multipart boundary in 16 MiB: not an MJPEG stream".into(),
                });
            }
        }
        // The part's headers.
        let mut length = None;
        loop {
            let line = self.line()?;
            let l = trim_crlf(&line);
            if l.is_empty() {
                break;
            }
            let text = String::from_utf8_lossy(l);
            if let Some((k, v)) = text.split_once(':')
                && k.trim().eq_ignore_ascii_case("content-length")
            {
                length = v.trim().parse::<usize>().ok();
            }
        }
        match length {
            Some(n) => {
                let mut jpeg = vec![0u8; n];
                self.body.read_exact(&mut jpeg).map_err(|e| self.io(e))?;
                Ok(jpeg)
            }
            None => {
                // Up to the next boundary; it stays unread for the next part.
                let mut jpeg = Vec::new();
                let name = self.url.clone();
                loop {
                    let buf = self
                        .body
                        .fill_buf()
                        .map_err(|e| SourceError::Io { source_name: name.clone(), reason: e.to_string() })?;
                    if buf.is_empty() {
                        return Err(SourceError::Ended { source_name: self.url.clone() });
                    }
                    let b = self.boundary.clone().expect("boundary known");
                    let mut marker = b"\r\n--".to_vec();
                    marker.extend_from_slice(&b);
                    jpeg.extend_from_slice(buf);
                    let n = buf.len();
                    self.body.consume(n);
                    if let Some(pos) = find(&jpeg, &marker) {
                        // Put back what follows the part: re-read it as the next boundary.
                        let rest = jpeg.split_off(pos + 2);
                        jpeg.truncate(pos);
                        let old = std::mem::replace(&mut self.body, BufReader::new(Box::new(std::io::empty())));
                        let chained: Box<dyn Read + Send + Sync> = Box::new(std::io::Cursor::new(rest).chain(old));
                        self.body = BufReader::with_capacity(1 << 20, chained);
                        return Ok(jpeg);
                    }
                }
            }
        }
    }
}

fn trim_crlf(l: &[u8]) -> &[u8] {
    let l = l.strip_suffix(b"\n").unwrap_or(l);
    l.strip_suffix(b"\r").unwrap_or(l)
}

fn find(hay: &[u8], needle: &[u8]) -> Option<usize> {
    hay.windows(needle.len()).position(|w| w == needle)
}

impl Source for MjpegSource {
    fn read(&mut self) -> Result<RawFrame, SourceError> {
        let jpeg = self.next_part()?;
        Ok(RawFrame {
            pixels: Pixels::Jpeg(jpeg),
            size: (0, 0),
            device_monotonic_ns: None,
            device_sequence: None,
            capture_wall_ns: None,
            depth: None,
        })
    }
}

// ------------------------------------------------------------------ ffmpeg child process

/// RTSP or a video file through an `ffmpeg` child: raw RGB24 at `size` on its stdout, a file
/// paced at its own frame rate (`-re`) and looped if asked.
#[derive(Debug)]
pub struct FfmpegSource {
    input: String,
    child: Child,
    out: ChildStdout,
    size: (u32, u32),
}

impl FfmpegSource {
    pub fn open(input: &str, file: bool, size: (u32, u32), loop_file: bool) -> Result<FfmpegSource, SourceError> {
        Self::spawn(input, file, size, loop_file, false)
    }

    /// ffmpeg's testsrc2 pattern at `size` and `fps`, paced in real time.
    pub fn test_pattern(size: (u32, u32), fps: f64) -> Result<FfmpegSource, SourceError> {
        Self::spawn(&format!("testsrc2=size={}x{}:rate={fps}", size.0, size.1), true, size, false, true)
    }

    fn spawn(
        input: &str,
        file: bool,
        size: (u32, u32),
        loop_file: bool,
        lavfi: bool,
    ) -> Result<FfmpegSource, SourceError> {
        let mut cmd = Command::new("ffmpeg");
        cmd.args(["-nostdin", "-hide_banner", "-loglevel", "error"]);
        if lavfi {
            cmd.args(["-re", "-f", "lavfi"]);
        } else if file {
            cmd.arg("-re");
            if loop_file {
                cmd.args(["-stream_loop", "-1"]);
            }
        } else if input.starts_with("rtsp") {
            cmd.args(["-rtsp_transport", "tcp"]);
        }
        cmd.args(["-i", input, "-an", "-vf", &format!("scale={}:{}", size.0, size.1)]);
        cmd.args(["-f", "rawvideo", "-pix_fmt", "rgb24", "-"]);
        cmd.stdin(Stdio::null()).stdout(Stdio::piped()).stderr(Stdio::inherit());
        let mut child = cmd.spawn().map_err(|e| SourceError::Io {
            source_name: input.to_owned(),
            reason: format!("cannot run ffmpeg: {e}"),
        })?;
        let out = child.stdout.take().expect("piped stdout");
        Ok(FfmpegSource { input: input.to_owned(), child, out, size })
    }
}

impl Drop for FfmpegSource {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Source for FfmpegSource {
    fn read(&mut self) -> Result<RawFrame, SourceError> {
        let mut rgb = vec![0u8; self.size.0 as usize * self.size.1 as usize * 3];
        self.out.read_exact(&mut rgb).map_err(|e| match e.kind() {
            std::io::ErrorKind::UnexpectedEof => SourceError::Ended { source_name: self.input.clone() },
            _ => SourceError::Io { source_name: self.input.clone(), reason: e.to_string() },
        })?;
        Ok(RawFrame {
            pixels: Pixels::Rgb8(rgb),
            size: self.size,
            device_monotonic_ns: None,
            device_sequence: None,
            capture_wall_ns: None,
            depth: None,
        })
    }
}

// ------------------------------------------------------------------ RealSense (librealsense)

/// The child process's script (`python/realsense_source.py`), run with `python -c`.
const REALSENSE_SCRIPT: &str = include_str!("../python/realsense_source.py");

/// The Python with pyrealsense2 that scripts/setup.sh installs.
pub const REALSENSE_PYTHON_ENV: &str = "LABRIG_REALSENSE_PYTHON";

/// A RealSense's colour stream through librealsense (pyrealsense2) in a child process: the
/// device's own intrinsics, frame numbers and timestamps (global/system time domains are on
/// the wall clock; the hardware clock is not, and arrival is used). pyrealsense2 cannot be
/// loaded into this process (it leaves CPython's symbols unresolved), hence the child.
#[derive(Debug)]
pub struct RealSenseSource {
    name: String,
    child: Child,
    out: BufReader<ChildStdout>,
    stderr: std::sync::Arc<std::sync::Mutex<String>>,
    intrinsics: crate::intrinsics::Intrinsics,
    size: (u32, u32),
    depth: bool,
}

#[derive(serde::Deserialize)]
struct RealSenseHead {
    serial: String,
    intrinsics: crate::intrinsics::Intrinsics,
}

#[derive(serde::Deserialize)]
struct RealSenseFrame {
    seq: u64,
    ts_ms: f64,
    domain: String,
    bytes: usize,
    #[serde(default)]
    depth_bytes: usize,
}

impl RealSenseSource {
    pub fn open(
        serial: Option<&str>,
        file: Option<&std::path::Path>,
        size: (u32, u32),
        fps: f64,
        loop_file: bool,
        depth: bool,
    ) -> Result<RealSenseSource, SourceError> {
        let name = match (serial, file) {
            (Some(s), _) => format!("realsense:{s}"),
            (None, Some(f)) => f.display().to_string(),
            (None, None) => unreachable!("a RealSense source has a serial or a file"),
        };
        let python = std::env::var_os(REALSENSE_PYTHON_ENV).ok_or_else(|| SourceError::Io {
            source_name: name.clone(),
            reason: format!(
                "the RealSense source needs pyrealsense2: scripts/setup.sh installs it and sets {REALSENSE_PYTHON_ENV}"
            ),
        })?;
        let mut cmd = Command::new(python);
        cmd.args(["-c", REALSENSE_SCRIPT]);
        match (serial, file) {
            (Some(s), _) => cmd.args(["--serial", s]),
            (None, Some(f)) => cmd.arg("--file").arg(f),
            (None, None) => unreachable!(),
        };
        if loop_file {
            cmd.arg("--loop");
        }
        if depth {
            cmd.arg("--depth");
        }
        cmd.args(["--width", &size.0.to_string(), "--height", &size.1.to_string()]);
        cmd.args(["--fps", &(fps.round() as u32).to_string()]);
        cmd.stdin(Stdio::null()).stdout(Stdio::piped()).stderr(Stdio::piped());
        let mut child = cmd.spawn().map_err(|e| SourceError::Io {
            source_name: name.clone(),
            reason: format!("cannot run the RealSense Python: {e}"),
        })?;
        // The child's complaints, kept for the error that ends it.
        let stderr = std::sync::Arc::new(std::sync::Mutex::new(String::new()));
        let mut err_pipe = child.stderr.take().expect("piped stderr");
        let sink = stderr.clone();
        std::thread::spawn(move || {
            let mut text = String::new();
            let _ = err_pipe.read_to_string(&mut text);
            *sink.lock().expect("stderr buffer") = text;
        });
        let mut out = BufReader::new(child.stdout.take().expect("piped stdout"));
        let mut line = String::new();
        let n = out.read_line(&mut line).unwrap_or(0);
        let mut src = RealSenseSource {
            name,
            child,
            out,
            stderr,
            intrinsics: crate::intrinsics::Intrinsics {
                width: size.0,
                height: size.1,
                fx: 0.0,
                fy: 0.0,
                cx: 0.0,
                cy: 0.0,
                distortion: vec![],
                source: "realsense".into(),
            },
            size,
            depth,
        };
        if n == 0 {
            return Err(src.died());
        }
        let head: RealSenseHead = serde_json::from_str(&line).map_err(|e| SourceError::Io {
            source_name: src.name.clone(),
            reason: format!("the RealSense child's first line is not its header: {e}"),
        })?;
        tracing::info!(source = %src.name, serial = %head.serial, "RealSense streaming");
        src.intrinsics = head.intrinsics;
        Ok(src)
    }

    /// The error of a child that stopped: what it said, or its exit.
    fn died(&mut self) -> SourceError {
        let status = self.child.wait().ok();
        // Give the stderr reader a moment to collect the last words.
        let mut said = String::new();
        for _ in 0..50 {
            said = self.stderr.lock().expect("stderr buffer").trim().to_owned();
            if !said.is_empty() {
                break;
            }
            std::thread::sleep(std::time::Duration::from_millis(10));
        }
        let last = said.lines().last().unwrap_or("").to_owned();
        match (status.and_then(|s| s.code()), last.is_empty()) {
            (Some(0), _) => SourceError::Ended { source_name: self.name.clone() },
            (_, false) => SourceError::Device(format!("{}: {last}", self.name)),
            (code, true) => SourceError::Io {
                source_name: self.name.clone(),
                reason: format!("the RealSense child exited ({code:?})"),
            },
        }
    }
}

impl Drop for RealSenseSource {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Source for RealSenseSource {
    fn read(&mut self) -> Result<RawFrame, SourceError> {
        let mut line = String::new();
        if self.out.read_line(&mut line).unwrap_or(0) == 0 {
            return Err(self.died());
        }
        let bad = |reason: String| SourceError::Io { source_name: self.name.clone(), reason };
        let meta: RealSenseFrame = serde_json::from_str(&line).map_err(|e| bad(format!("a frame header: {e}")))?;
        let expected = self.size.0 as usize * self.size.1 as usize * 3;
        if meta.bytes != expected {
            return Err(bad(format!("a frame of {} bytes, expected {expected}", meta.bytes)));
        }
        let depth_expected = if self.depth { self.size.0 as usize * self.size.1 as usize * 2 } else { 0 };
        if meta.depth_bytes != depth_expected {
            return Err(bad(format!("a depth frame of {} bytes, expected {depth_expected}", meta.depth_bytes)));
        }
        let mut rgb = vec![0u8; meta.bytes];
        if self.out.read_exact(&mut rgb).is_err() {
            return Err(self.died());
        }
        let mut depth = self.depth.then(|| vec![0u8; depth_expected]);
        if let Some(d) = depth.as_mut()
            && self.out.read_exact(d).is_err()
        {
            return Err(self.died());
        }
        // Global time and system time are the host's wall clock (ms); the hardware clock is the
        // camera's own, with no offset known here: arrival time is used instead.
        let wall = matches!(meta.domain.as_str(), "global_time" | "system_time");
        Ok(RawFrame {
            pixels: Pixels::Rgb8(rgb),
            size: self.size,
            device_monotonic_ns: None,
            device_sequence: Some(meta.seq),
            capture_wall_ns: wall.then(|| (meta.ts_ms * 1e6).round() as i64),
            depth,
        })
    }

    fn intrinsics(&self) -> Option<crate::intrinsics::Intrinsics> {
        Some(self.intrinsics.clone())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sources_parse_by_prefix() {
        assert_eq!(
            SourceSpec::parse("zed:12345").unwrap(),
            SourceSpec::Device { kind: DeviceKind::Zed, serial: Some("12345".into()), path: None }
        );
        assert!(SourceSpec::parse("zed:12345").unwrap().side_by_side_default());
        assert!(matches!(SourceSpec::parse("http://127.0.0.1:1/cam").unwrap(), SourceSpec::Mjpeg { .. }));
        assert!(matches!(SourceSpec::parse("rtsp://127.0.0.1/x").unwrap(), SourceSpec::Ffmpeg { file: false, .. }));
        assert!(matches!(SourceSpec::parse("/dev/video3").unwrap(), SourceSpec::Device { path: Some(_), .. }));
        assert_eq!(SourceSpec::parse("/nope.mp4").unwrap_err().to_string(), "/nope.mp4: no such video file");
        assert!(SourceSpec::parse("ftp://x").unwrap_err().to_string().starts_with("`ftp://x` is not a camera source"));
        assert!(SourceSpec::parse("zed:").is_err());
        assert_eq!(SourceSpec::parse("testsrc").unwrap(), SourceSpec::TestPattern);
        assert_eq!(
            SourceSpec::parse("realsense:D435-1").unwrap(),
            SourceSpec::RealSense { serial: Some("D435-1".into()), file: None }
        );
        let rec = tempfile::NamedTempFile::with_suffix(".db3").unwrap();
        let path = rec.path().to_str().unwrap();
        assert_eq!(SourceSpec::parse(path).unwrap(), SourceSpec::RealSense { serial: None, file: Some(path.into()) });
    }

    fn part(jpeg: &[u8], with_length: bool) -> Vec<u8> {
        let mut p = b"--frame\r\nContent-Type: image/jpeg\r\n".to_vec();
        if with_length {
            p.extend_from_slice(format!("Content-Length: {}\r\n", jpeg.len()).as_bytes());
        }
        p.extend_from_slice(b"\r\n");
        p.extend_from_slice(jpeg);
        p.extend_from_slice(b"\r\n");
        p
    }

    #[test]
    fn multipart_parts_by_length_or_by_boundary() {
        // Payloads with CR/LF and boundary-like bytes inside.
        let a = b"\xff\xd8abc\r\n--fram\r\n\xff\xd9".to_vec();
        let b = b"\xff\xd8second\n\xff\xd9".to_vec();
        for with_length in [true, false] {
            let mut body = part(&a, with_length);
            body.extend(part(&b, with_length));
            body.extend_from_slice(b"--frame--\r\n");
            // Boundary named by the header, or learned from the first line.
            for boundary in [Some("frame"), None] {
                let mut s = MjpegSource::from_reader("test", Box::new(std::io::Cursor::new(body.clone())), boundary);
                assert_eq!(s.next_part().unwrap(), a, "length {with_length} boundary {boundary:?}");
                assert_eq!(s.next_part().unwrap(), b);
                assert!(matches!(s.next_part(), Err(SourceError::Ended { .. })));
            }
        }
    }

    #[test]
    fn a_body_that_is_not_multipart_is_named() {
        let body = vec![b'x'; 17 << 20];
        let mut s = MjpegSource::from_reader("test", Box::new(std::io::Cursor::new(body)), Some("frame"));
        let e = s.next_part().unwrap_err().to_string();
        assert!(e.contains("not an MJPEG stream"), "{e}");
    }
}
