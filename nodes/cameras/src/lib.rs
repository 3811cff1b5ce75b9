//! labrig-cameras: the camera node (`labrig-cameras run`). Real cameras (ZED 2 / ZED Mini and
//! a RealSense's colour stream over V4L2, any UVC camera) and stand-ins (MJPEG over HTTP,
//! RTSP, a video file) behind exactly the interfaces the sim bridge serves: frames on shared
//! memory (`labrig/camera/<id>/frames`), `/cameras/<id>/camera_info` with each frame,
//! `/tf_static` from the rig's extrinsics; plus a low-rate JPEG preview per camera and
//! `/cameras/status`. The library parts (sources, decoding, intrinsics) have no ROS in them.

pub mod convert;
pub mod intrinsics;
pub mod node;
pub mod realsense;
pub mod rectify;
pub mod source;
pub mod v4l2;

use labrig_msgs::Invalid;
use labrig_runtime::{RosConfig, Shutdown};
use node::{CameraConfig, CamerasConfig, CamerasStats};
use std::path::Path;

/// The camera node: `labrig-cameras run` (`labrig_runtime::node_main_with`).
#[derive(Debug)]
pub struct CamerasNode;

/// `labrig-cameras run`'s own flags.
#[derive(Debug, clap::Args, serde::Serialize)]
pub struct CamerasFlags {
    /// A camera without a config file, `ID=SOURCE` (repeatable): SOURCE is zed:SERIAL,
    /// realsense:SERIAL, v4l2:SERIAL, /dev/videoN, http://... (MJPEG), rtsp://..., testsrc or a video
    /// file; size and rate as the source sends them (set them with
    /// `--set cameras.ID.width=...`).
    #[arg(long = "camera", value_name = "ID=SOURCE")]
    #[serde(skip)]
    camera: Vec<String>,
}

impl labrig_runtime::Node for CamerasNode {
    const NAME: &'static str = "labrig-cameras";
    const ABOUT: &'static str = "The rig's cameras: frames on shared memory, camera_info, tf_static, previews, status";
    type Config = CamerasConfig;
    type Flags = CamerasFlags;
    type Stats = CamerasStats;

    fn ros(config: &mut CamerasConfig) -> &mut RosConfig {
        &mut config.ros
    }

    fn apply(flags: &CamerasFlags, config: &mut CamerasConfig, file: Option<&Path>) {
        if let Some(f) = file {
            config.resolve_paths(f);
        }
        for c in &flags.camera {
            // A malformed one becomes a camera whose source names the problem in validate.
            let (id, source) = c.split_once('=').unwrap_or((c.as_str(), ""));
            let entry = config.cameras.entry(id.trim().to_owned()).or_insert_with(|| CameraConfig::new(""));
            entry.source = source.trim().to_owned();
        }
    }

    fn validate(config: &CamerasConfig) -> Result<(), Invalid> {
        config.validate()
    }

    async fn run(config: CamerasConfig, shutdown: Shutdown) -> anyhow::Result<CamerasStats> {
        node::run(config, shutdown).await
    }
}

/// `labrig-cameras list`: the V4L2 capture devices on this machine.
#[derive(Debug, clap::Subcommand)]
pub enum CamerasTools {
    /// The V4L2 capture devices this machine has: path, name, USB serial and vendor, modes.
    List {
        #[arg(long)]
        json: bool,
    },
    /// ZED rectification's cost: the remap alone and the whole per-frame path (a side-by-side
    /// YUYV frame -> the eye's RGB -> rectified) on synthetic frames, per frame p50/p99, and
    /// the share of one core `--zeds` cameras at `--fps` take.
    BenchRectify {
        /// A factory file (default: the test fixture's values).
        #[arg(long)]
        intrinsics: Option<std::path::PathBuf>,
        /// One eye's width x height: a ZED resolution.
        #[arg(long, default_value_t = 1280)]
        width: u32,
        #[arg(long, default_value_t = 720)]
        height: u32,
        #[arg(long, default_value_t = 300)]
        frames: usize,
        #[arg(long, default_value_t = 3)]
        zeds: u32,
        #[arg(long, default_value_t = 30.0)]
        fps: f64,
        #[arg(long)]
        json: bool,
    },
    /// Writes a RealSense's calibration for the Rust depth alignment (colour and depth
    /// intrinsics, depth -> colour extrinsics, depth scale) through pyrealsense2, once at
    /// set-up: the running rig reads the file.
    RealsenseExport {
        /// The camera's serial (`labrig cameras list`).
        #[arg(long, conflicts_with = "recording")]
        serial: Option<String>,
        /// A librealsense recording (.db3/.bag) instead of a device.
        #[arg(long)]
        recording: Option<std::path::PathBuf>,
        /// The colour size and rate the rig runs the camera at (the intrinsics depend on it).
        #[arg(long, default_value_t = 1280)]
        width: u32,
        #[arg(long, default_value_t = 720)]
        height: u32,
        #[arg(long, default_value_t = 30)]
        fps: u32,
        #[arg(long)]
        out: std::path::PathBuf,
    },
    /// Rectifies a ZED side-by-side image (PNG, both eyes) with its factory file, as the node
    /// does each frame: writes left.png, right.png and rectification.json (each eye's K, R and
    /// P as camera_info carries them) into --out.
    Rectify {
        /// The camera's factory calibration, SN<serial>.conf.
        #[arg(long)]
        intrinsics: std::path::PathBuf,
        /// A side-by-side RGB or grey PNG (two eyes of a ZED resolution).
        #[arg(long)]
        input: std::path::PathBuf,
        #[arg(long)]
        out: std::path::PathBuf,
    },
}

impl CamerasTools {
    pub fn run(self) -> anyhow::Result<std::process::ExitCode> {
        match self {
            CamerasTools::List { json } => {
                let devices = v4l2::list();
                if json {
                    println!("{}", serde_json::to_string_pretty(&devices)?);
                } else if devices.is_empty() {
                    println!("no V4L2 capture devices (no /dev/video* this process can open)");
                } else {
                    for d in &devices {
                        let vendor = d.usb_vendor.map_or("-".to_owned(), |v| format!("{v:04x}"));
                        println!(
                            "{}  {} ({:?}, driver {}, USB vendor {vendor}, serial {})",
                            d.path.display(),
                            d.card,
                            d.kind(),
                            d.driver,
                            d.serial.as_deref().unwrap_or("-")
                        );
                        for m in &d.modes {
                            let fps: Vec<String> = m.fps.iter().map(|f| format!("{f:.0}")).collect();
                            println!("    {} {}x{} @ {} fps", m.fourcc, m.width, m.height, fps.join("/"));
                        }
                    }
                }
                Ok(std::process::ExitCode::SUCCESS)
            }
            CamerasTools::BenchRectify { intrinsics, width, height, frames, zeds, fps, json } => {
                rectify::bench(rectify::BenchArgs { intrinsics, width, height, frames, zeds, fps, json })?;
                Ok(std::process::ExitCode::SUCCESS)
            }
            CamerasTools::RealsenseExport { serial, recording, width, height, fps, out } => {
                realsense::export(serial.as_deref(), recording.as_deref(), (width, height, fps), &out)?;
                Ok(std::process::ExitCode::SUCCESS)
            }
            CamerasTools::Rectify { intrinsics, input, out } => {
                rectify::rectify_png(&intrinsics, &input, &out)?;
                Ok(std::process::ExitCode::SUCCESS)
            }
        }
    }
}
