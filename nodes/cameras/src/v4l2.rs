//! V4L2 devices (ZED 2 / ZED Mini, a D435's colour stream, any UVC camera) through the `v4l`
//! crate: found by USB serial in sysfs, a mode checked against the ones the device offers,
//! memory-mapped streaming with the kernel's buffer time (CLOCK_MONOTONIC) and sequence.
//!
//! A ZED sends one YUYV frame with both eyes side by side (2560x720 for 1280x720 per eye).
//! Its serial as Stereolabs prints it lives in the camera's SPI flash behind a UVC extension
//! unit; the USB descriptor's serial (what sysfs shows, and what this module matches) is
//! what `labrig cameras list` prints, and what rig configs name.

use crate::convert::Pixels;
use crate::source::{DeviceKind, RawFrame, Source, SourceError};
use std::path::{Path, PathBuf};
use std::time::Duration;
use v4l::buffer::{Flags, Type};
use v4l::io::traits::CaptureStream;
use v4l::video::Capture;
use v4l::{Device, FourCC};

/// A mode a device offers: pixel format, size and frame rates.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Mode {
    pub fourcc: String,
    pub width: u32,
    pub height: u32,
    pub fps: Vec<f64>,
}

/// A V4L2 capture device as `labrig cameras list` shows it.
#[derive(Debug, Clone, serde::Serialize)]
pub struct DeviceInfo {
    pub path: PathBuf,
    pub card: String,
    pub driver: String,
    pub serial: Option<String>,
    pub usb_vendor: Option<u16>,
    pub usb_product: Option<u16>,
    pub modes: Vec<Mode>,
}

impl DeviceInfo {
    /// Which backend kind it looks like, by USB vendor.
    pub fn kind(&self) -> DeviceKind {
        match self.usb_vendor {
            Some(0x2b03) => DeviceKind::Zed,
            Some(0x8086) => DeviceKind::RealSense,
            _ => DeviceKind::Uvc,
        }
    }
}

fn read_attr(dir: &Path, name: &str) -> Option<String> {
    std::fs::read_to_string(dir.join(name)).ok().map(|s| s.trim().to_owned()).filter(|s| !s.is_empty())
}

/// The USB device's serial, vendor and product of `/dev/videoN`, from sysfs (the
/// video4linux node's `device` is the USB interface; its parent the device).
fn usb_attrs(path: &Path) -> (Option<String>, Option<u16>, Option<u16>) {
    let Some(name) = path.file_name() else { return (None, None, None) };
    let Ok(iface) = std::fs::canonicalize(Path::new("/sys/class/video4linux").join(name).join("device")) else {
        return (None, None, None);
    };
    let Some(dev) = iface.parent() else { return (None, None, None) };
    let hex = |n: &str| read_attr(dev, n).and_then(|s| u16::from_str_radix(&s, 16).ok());
    (read_attr(dev, "serial"), hex("idVendor"), hex("idProduct"))
}

fn fps_of(f: &v4l::Fraction) -> f64 {
    if f.numerator == 0 { 0.0 } else { f64::from(f.denominator) / f64::from(f.numerator) }
}

/// The modes a device offers (discrete sizes and frame rates; stepwise ranges by their ends).
pub fn modes(dev: &Device) -> std::io::Result<Vec<Mode>> {
    let mut out = Vec::new();
    for f in dev.enum_formats()? {
        for size in dev.enum_framesizes(f.fourcc)? {
            let sizes: Vec<(u32, u32)> = match size.size {
                v4l::framesize::FrameSizeEnum::Discrete(d) => vec![(d.width, d.height)],
                v4l::framesize::FrameSizeEnum::Stepwise(s) => {
                    vec![(s.min_width, s.min_height), (s.max_width, s.max_height)]
                }
            };
            for (width, height) in sizes {
                let mut fps: Vec<f64> = dev
                    .enum_frameintervals(f.fourcc, width, height)
                    .unwrap_or_default()
                    .iter()
                    .flat_map(|i| match &i.interval {
                        v4l::frameinterval::FrameIntervalEnum::Discrete(d) => vec![fps_of(d)],
                        v4l::frameinterval::FrameIntervalEnum::Stepwise(s) => vec![fps_of(&s.max), fps_of(&s.min)],
                    })
                    .collect();
                fps.sort_by(|a, b| b.total_cmp(a));
                fps.dedup();
                out.push(Mode { fourcc: f.fourcc.str().unwrap_or("????").to_owned(), width, height, fps });
            }
        }
    }
    Ok(out)
}

/// Every V4L2 video capture device on this machine.
pub fn list() -> Vec<DeviceInfo> {
    let mut out = Vec::new();
    for node in v4l::context::enum_devices() {
        let path = node.path().to_owned();
        let Ok(dev) = Device::with_path(&path) else { continue };
        let Ok(caps) = dev.query_caps() else { continue };
        if !caps.capabilities.contains(v4l::capability::Flags::VIDEO_CAPTURE) {
            continue;
        }
        let (serial, usb_vendor, usb_product) = usb_attrs(&path);
        out.push(DeviceInfo {
            path,
            card: caps.card,
            driver: caps.driver,
            serial,
            usb_vendor,
            usb_product,
            modes: modes(&dev).unwrap_or_default(),
        });
    }
    out.sort_by(|a, b| a.path.cmp(&b.path));
    out
}

/// The device path of the camera with this USB serial (and vendor, for the ZED and
/// RealSense kinds), naming what was found where it is not there.
pub fn find(kind: DeviceKind, serial: &str) -> Result<PathBuf, SourceError> {
    let all = list();
    let hit = all
        .iter()
        .find(|d| d.serial.as_deref() == Some(serial) && kind.usb_vendor().is_none_or(|v| d.usb_vendor == Some(v)));
    match hit {
        Some(d) => Ok(d.path.clone()),
        None => {
            let found: Vec<String> = all
                .iter()
                .map(|d| format!("{} {} serial {}", d.path.display(), d.card, d.serial.as_deref().unwrap_or("-")))
                .collect();
            Err(SourceError::Device(format!(
                "no {kind:?} camera with serial {serial} (V4L2 capture devices: {})",
                if found.is_empty() { "none".to_owned() } else { found.join("; ") }
            )))
        }
    }
}

/// The node of a multi-node camera (a D435: depth, infrared, colour, metadata) with this USB
/// serial and vendor that offers `fourcc` at `size` and `fps`; none: named, with the nodes of
/// that serial and their modes.
pub fn find_node(
    kind: DeviceKind,
    serial: &str,
    fourcc: &str,
    size: (u32, u32),
    fps: f64,
) -> Result<PathBuf, SourceError> {
    let all = list();
    let same: Vec<&DeviceInfo> = all
        .iter()
        .filter(|d| d.serial.as_deref() == Some(serial) && kind.usb_vendor().is_none_or(|v| d.usb_vendor == Some(v)))
        .collect();
    let offers = |d: &&&DeviceInfo| {
        d.modes
            .iter()
            .any(|m| m.fourcc == fourcc && (m.width, m.height) == size && m.fps.iter().any(|r| (r - fps).abs() < 0.5))
    };
    if let Some(d) = same.iter().find(offers) {
        return Ok(d.path.clone());
    }
    if same.is_empty() {
        return find(kind, serial);
    }
    let nodes: Vec<String> = same
        .iter()
        .map(|d| {
            let modes: Vec<String> = d.modes.iter().map(|m| format!("{} {}x{}", m.fourcc, m.width, m.height)).collect();
            format!("{} ({})", d.path.display(), modes.join(", "))
        })
        .collect();
    Err(SourceError::Device(format!(
        "the {kind:?} camera with serial {serial} has no node offering {fourcc} {}x{} at {fps} fps: {}",
        size.0,
        size.1,
        nodes.join("; ")
    )))
}

/// A streaming V4L2 device.
pub struct V4l2Source {
    path: PathBuf,
    // Declared before the device: the stream unmaps its buffers before the device closes.
    stream: v4l::io::mmap::Stream<'static>,
    _device: Device,
    fourcc: FourCC,
    size: (u32, u32),
}

impl std::fmt::Debug for V4l2Source {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "V4l2Source({})", self.path.display())
    }
}

impl V4l2Source {
    /// Opens `path` at `size` (the whole frame: both eyes for a ZED) and `fps`, in the first of
    /// `formats` the device offers at that size; a mode it does not offer is refused with the
    /// modes it does.
    pub fn open(
        path: &Path,
        formats: &[&str],
        size: (u32, u32),
        fps: f64,
        read_timeout: Duration,
    ) -> Result<V4l2Source, SourceError> {
        let dev_err = |what: &str, e: std::io::Error| SourceError::Device(format!("{}: {what}: {e}", path.display()));
        let dev = Device::with_path(path).map_err(|e| dev_err("open", e))?;
        let offered = modes(&dev).map_err(|e| dev_err("list modes", e))?;
        let fits = |m: &Mode, f: &str| {
            m.fourcc == f && (m.width, m.height) == size && m.fps.iter().any(|r| (r - fps).abs() < 0.5)
        };
        let Some(fourcc) = formats.iter().find(|f| offered.iter().any(|m| fits(m, f))) else {
            let list: Vec<String> = offered
                .iter()
                .map(|m| {
                    let fps: Vec<String> = m.fps.iter().map(|f| format!("{f:.0}")).collect();
                    format!("{} {}x{} @ {}", m.fourcc, m.width, m.height, fps.join("/"))
                })
                .collect();
            return Err(SourceError::Device(format!(
                "{} does not offer {} {}x{} at {fps} fps; it offers: {}",
                path.display(),
                formats.join(" or "),
                size.0,
                size.1,
                list.join(", ")
            )));
        };
        let fourcc = FourCC::new(&<[u8; 4]>::try_from(fourcc.as_bytes()).expect("four-character code"));
        let set = dev.set_format(&v4l::Format::new(size.0, size.1, fourcc)).map_err(|e| dev_err("set format", e))?;
        if (set.width, set.height, set.fourcc) != (size.0, size.1, fourcc) {
            return Err(SourceError::Device(format!(
                "{}: asked for {fourcc} {}x{}, the driver set {} {}x{}",
                path.display(),
                size.0,
                size.1,
                set.fourcc,
                set.width,
                set.height
            )));
        }
        let interval = v4l::Fraction::new(1000, (fps * 1000.0).round() as u32);
        dev.set_params(&v4l::video::capture::Parameters::new(interval)).map_err(|e| dev_err("set frame rate", e))?;
        let mut stream =
            v4l::io::mmap::Stream::with_buffers(&dev, Type::VideoCapture, 4).map_err(|e| dev_err("map buffers", e))?;
        stream.set_timeout(read_timeout);
        Ok(V4l2Source { path: path.to_owned(), stream, _device: dev, fourcc, size })
    }
}

/// One buffer as the driver filled it.
#[derive(Debug)]
pub struct Buffer {
    pub data: Vec<u8>,
    /// The kernel's buffer time on CLOCK_MONOTONIC, ns, where the driver stamps it so.
    pub monotonic_ns: Option<i64>,
    pub sequence: u64,
}

impl V4l2Source {
    /// The next buffer, its bytes as they came (a RealSense's Z16 depth: little-endian uint16).
    pub fn next_buffer(&mut self) -> Result<Buffer, SourceError> {
        let (bytes, meta) = self
            .stream
            .next()
            .map_err(|e| SourceError::Io { source_name: self.path.display().to_string(), reason: e.to_string() })?;
        let data = bytes[..(meta.bytesused as usize).min(bytes.len())].to_vec();
        let monotonic = meta.flags.contains(Flags::TIMESTAMP_MONOTONIC);
        let ns = meta.timestamp.sec * 1_000_000_000 + meta.timestamp.usec * 1000;
        Ok(Buffer { data, monotonic_ns: monotonic.then_some(ns), sequence: u64::from(meta.sequence) })
    }
}

impl Source for V4l2Source {
    fn read(&mut self) -> Result<RawFrame, SourceError> {
        let Buffer { data, monotonic_ns, sequence } = self.next_buffer()?;
        let pixels = match &self.fourcc.repr {
            b"MJPG" | b"JPEG" => Pixels::Jpeg(data),
            _ => Pixels::Yuyv(data),
        };
        Ok(RawFrame {
            pixels,
            size: self.size,
            device_monotonic_ns: monotonic_ns,
            device_sequence: Some(sequence),
            capture_wall_ns: None,
            depth: None,
        })
    }
}
