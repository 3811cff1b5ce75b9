//! A RealSense's depth aligned to its colour image in Rust, from the device's calibration as
//! librealsense reports it (written once at set-up by `labrig cameras realsense-export`, which
//! runs pyrealsense2 off the robot path), so that a rig reading the camera's nodes directly
//! needs no Python.
//!
//! The alignment is librealsense's (`align_images` in src/proc/align.cpp, with rsutil.h's
//! deproject / transform / project): each depth pixel's two corners are deprojected at its
//! depth, moved into the colour camera's frame, projected; every colour pixel of the rectangle
//! between them takes that depth, the nearest where rectangles overlap. Single precision, as
//! librealsense computes it. Pinhole cameras only: the D435's colour (inverse Brown-Conrady)
//! and depth (Brown-Conrady) models have all-zero coefficients from the factory; a calibration
//! with non-zero ones is refused by name rather than aligned wrongly.

use serde::{Deserialize, Serialize};

/// One stream's intrinsics as librealsense reports them.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StreamIntrinsics {
    pub width: u32,
    pub height: u32,
    pub fx: f32,
    pub fy: f32,
    pub ppx: f32,
    pub ppy: f32,
    /// librealsense's distortion model name (`brown_conrady`, `inverse_brown_conrady`, ...).
    pub model: String,
    pub coeffs: [f32; 5],
}

/// librealsense's extrinsics: `rotation` column-major (as rs2_extrinsics), `translation` in m.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Extrinsics {
    pub rotation: [f32; 9],
    pub translation: [f32; 3],
}

/// A RealSense's calibration file (`labrig cameras realsense-export`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RealSenseCalibration {
    pub serial: String,
    #[serde(default)]
    pub name: String,
    pub colour: StreamIntrinsics,
    pub depth: StreamIntrinsics,
    pub depth_to_colour: Extrinsics,
    /// Metres per depth unit.
    pub depth_scale_m: f32,
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum RealSenseError {
    #[error("{path}: {reason}")]
    File { path: String, reason: String },
    #[error(
        "the {stream} stream's distortion ({model}, coefficients {coeffs:?}) is not all zero: labrig aligns pinhole RealSense streams only (use the pyrealsense2 source for this camera)"
    )]
    Distorted { stream: &'static str, model: String, coeffs: [f32; 5] },
    #[error("a depth frame of {got} pixels for a {width}x{height} depth stream")]
    DepthSize { got: usize, width: u32, height: u32 },
    #[error("a depth scale of {0} m per unit")]
    Scale(f32),
}

impl RealSenseCalibration {
    pub fn load(path: &std::path::Path) -> Result<RealSenseCalibration, RealSenseError> {
        let bad = |reason: String| RealSenseError::File { path: path.display().to_string(), reason };
        let text = std::fs::read_to_string(path).map_err(|e| bad(e.to_string()))?;
        serde_json::from_str(&text).map_err(|e| bad(e.to_string()))
    }

    /// What the alignment needs of the file: pinhole streams, a positive depth scale.
    pub fn check(&self) -> Result<(), RealSenseError> {
        for (stream, s) in [("colour", &self.colour), ("depth", &self.depth)] {
            if s.coeffs.iter().any(|&c| c != 0.0) {
                return Err(RealSenseError::Distorted { stream, model: s.model.clone(), coeffs: s.coeffs });
            }
        }
        if !(self.depth_scale_m.is_finite() && self.depth_scale_m > 0.0) {
            return Err(RealSenseError::Scale(self.depth_scale_m));
        }
        Ok(())
    }
}

fn deproject(i: &StreamIntrinsics, px: [f32; 2], depth: f32) -> [f32; 3] {
    let x = (px[0] - i.ppx) / i.fx;
    let y = (px[1] - i.ppy) / i.fy;
    [depth * x, depth * y, depth]
}

fn transform(e: &Extrinsics, p: [f32; 3]) -> [f32; 3] {
    let r = &e.rotation;
    [
        r[0] * p[0] + r[3] * p[1] + r[6] * p[2] + e.translation[0],
        r[1] * p[0] + r[4] * p[1] + r[7] * p[2] + e.translation[1],
        r[2] * p[0] + r[5] * p[1] + r[8] * p[2] + e.translation[2],
    ]
}

fn project(i: &StreamIntrinsics, p: [f32; 3]) -> [f32; 2] {
    [p[0] / p[2] * i.fx + i.ppx, p[1] / p[2] * i.fy + i.ppy]
}

/// Depth (`z16` units of the depth stream, 0 = none) aligned to the colour image: the colour
/// image's size, the same units.
pub fn align_depth_to_colour(c: &RealSenseCalibration, depth: &[u16]) -> Result<Vec<u16>, RealSenseError> {
    c.check()?;
    let (d, o) = (&c.depth, &c.colour);
    if depth.len() != d.width as usize * d.height as usize {
        return Err(RealSenseError::DepthSize { got: depth.len(), width: d.width, height: d.height });
    }
    let mut out = vec![0u16; o.width as usize * o.height as usize];
    let corner = |px: [f32; 2], z: f32| {
        let q = project(o, transform(&c.depth_to_colour, deproject(d, px, z)));
        // librealsense rounds by truncation after adding a half.
        ((q[0] + 0.5) as i32, (q[1] + 0.5) as i32)
    };
    for dy in 0..d.height {
        for dx in 0..d.width {
            let raw = depth[(dy * d.width + dx) as usize];
            if raw == 0 {
                continue;
            }
            let z = f32::from(raw) * c.depth_scale_m;
            let (x0, y0) = corner([dx as f32 - 0.5, dy as f32 - 0.5], z);
            let (x1, y1) = corner([dx as f32 + 0.5, dy as f32 + 0.5], z);
            if x0 < 0 || y0 < 0 || x1 >= o.width as i32 || y1 >= o.height as i32 {
                continue;
            }
            for y in y0..=y1 {
                for x in x0..=x1 {
                    let t = &mut out[(y as u32 * o.width + x as u32) as usize];
                    *t = if *t == 0 { raw } else { (*t).min(raw) };
                }
            }
        }
    }
    Ok(out)
}

/// A D435 read in Rust: its colour node (YUYV, converted to RGB as librealsense does) and,
/// with `depth`, its depth node (Z16) over V4L2, found by USB serial in sysfs; depth aligned
/// to colour here (no librealsense, no Python). Each colour frame is paired with the next depth frame (both nodes run at the
/// camera's rate). Untested against a device: there is none here (the pyrealsense2 source
/// stays the fallback: a camera without `realsense_calibration`).
pub struct RealSenseV4l2 {
    colour: crate::v4l2::V4l2Source,
    depth: Option<crate::v4l2::V4l2Source>,
    calibration: std::sync::Arc<RealSenseCalibration>,
}

impl std::fmt::Debug for RealSenseV4l2 {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "RealSenseV4l2({})", self.calibration.serial)
    }
}

impl RealSenseV4l2 {
    pub fn open(
        serial: &str,
        calibration: std::sync::Arc<RealSenseCalibration>,
        fps: f64,
        depth: bool,
        read_timeout: std::time::Duration,
    ) -> Result<RealSenseV4l2, crate::source::SourceError> {
        use crate::source::DeviceKind;
        let (c, d) = (&calibration.colour, &calibration.depth);
        let path = crate::v4l2::find_node(DeviceKind::RealSense, serial, "YUYV", (c.width, c.height), fps)?;
        let colour = crate::v4l2::V4l2Source::open(&path, &["YUYV"], (c.width, c.height), fps, read_timeout)?;
        let depth = if depth {
            let path = crate::v4l2::find_node(DeviceKind::RealSense, serial, "Z16 ", (d.width, d.height), fps)?;
            Some(crate::v4l2::V4l2Source::open(&path, &["Z16 "], (d.width, d.height), fps, read_timeout)?)
        } else {
            None
        };
        Ok(RealSenseV4l2 { colour, depth, calibration })
    }
}

impl crate::source::Source for RealSenseV4l2 {
    fn read(&mut self) -> Result<crate::source::RawFrame, crate::source::SourceError> {
        let mut frame = self.colour.read()?;
        // Colour as librealsense converts it, byte for byte (not the generic UVC conversion).
        if let crate::convert::Pixels::Yuyv(yuyv) = &frame.pixels {
            let (w, h) = frame.size;
            let rgb = crate::convert::yuyv_to_rgb_librealsense(yuyv, w, h).map_err(|e| {
                crate::source::SourceError::Io { source_name: self.calibration.serial.clone(), reason: e.to_string() }
            })?;
            frame.pixels = crate::convert::Pixels::Rgb8(rgb);
        }
        if let Some(d) = &mut self.depth {
            let raw = z16(&d.next_buffer()?.data);
            let aligned = align_depth_to_colour(&self.calibration, &raw).map_err(|e| {
                crate::source::SourceError::Io { source_name: self.calibration.serial.clone(), reason: e.to_string() }
            })?;
            // The node's depth frames are millimetres (a D435's units already are, by default).
            let mm = self.calibration.depth_scale_m * 1000.0;
            let bytes: Vec<u8> = if (mm - 1.0).abs() < 1e-6 {
                aligned.iter().flat_map(|z| z.to_le_bytes()).collect()
            } else {
                aligned.iter().flat_map(|&z| ((f32::from(z) * mm).round().min(65535.0) as u16).to_le_bytes()).collect()
            };
            frame.depth = Some(bytes);
        }
        Ok(frame)
    }

    fn intrinsics(&self) -> Option<crate::intrinsics::Intrinsics> {
        Some(self.calibration.colour_intrinsics())
    }
}

impl RealSenseCalibration {
    /// The colour stream's intrinsics as camera_info carries them (the depth is aligned to it).
    pub fn colour_intrinsics(&self) -> crate::intrinsics::Intrinsics {
        let c = &self.colour;
        crate::intrinsics::Intrinsics {
            width: c.width,
            height: c.height,
            fx: f64::from(c.fx),
            fy: f64::from(c.fy),
            cx: f64::from(c.ppx),
            cy: f64::from(c.ppy),
            distortion: c.coeffs.iter().map(|&v| f64::from(v)).collect(),
            source: "realsense".into(),
        }
    }
}

/// The export's script (`python/realsense_export.py`), run with `python -c`.
const EXPORT_SCRIPT: &str = include_str!("../python/realsense_export.py");

/// `labrig cameras realsense-export`: a device (by serial, at the colour size the rig runs it
/// at) or a recording, through pyrealsense2 (`LABRIG_REALSENSE_PYTHON`), into `out`; then the
/// file is read back and checked as the rig will read it.
pub fn export(
    serial: Option<&str>,
    recording: Option<&std::path::Path>,
    size: (u32, u32, u32),
    out: &std::path::Path,
) -> anyhow::Result<RealSenseCalibration> {
    use anyhow::Context;
    let env = crate::source::REALSENSE_PYTHON_ENV;
    let python = std::env::var_os(env)
        .with_context(|| format!("the export needs pyrealsense2: scripts/setup.sh installs it and sets {env}"))?;
    let mut cmd = std::process::Command::new(python);
    cmd.args(["-c", EXPORT_SCRIPT]);
    match (serial, recording) {
        (Some(s), None) => cmd.args(["--serial", s]),
        (None, Some(f)) => cmd.arg("--file").arg(f),
        _ => anyhow::bail!("name the camera by --serial or a --recording, one of them"),
    };
    cmd.args(["--width", &size.0.to_string(), "--height", &size.1.to_string(), "--fps", &size.2.to_string()]);
    cmd.arg("--out").arg(out);
    let o = cmd.output().context("running the RealSense Python")?;
    if !o.status.success() {
        anyhow::bail!("realsense export: {}", String::from_utf8_lossy(&o.stderr).trim());
    }
    print!("{}", String::from_utf8_lossy(&o.stdout));
    let cal = RealSenseCalibration::load(out)?;
    cal.check()?;
    Ok(cal)
}

/// A Z16 frame's bytes (little endian, as the device and librealsense deliver them).
pub fn z16(bytes: &[u8]) -> Vec<u16> {
    bytes.chunks_exact(2).map(|b| u16::from_le_bytes([b[0], b[1]])).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pinhole(w: u32, h: u32, f: f32) -> StreamIntrinsics {
        StreamIntrinsics {
            width: w,
            height: h,
            fx: f,
            fy: f,
            ppx: (w as f32 - 1.0) / 2.0,
            ppy: (h as f32 - 1.0) / 2.0,
            model: "brown_conrady".into(),
            coeffs: [0.0; 5],
        }
    }

    fn calibration(shift_m: f32) -> RealSenseCalibration {
        RealSenseCalibration {
            serial: "T".into(),
            name: String::new(),
            colour: pinhole(64, 48, 60.0),
            depth: pinhole(64, 48, 60.0),
            depth_to_colour: Extrinsics {
                rotation: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                translation: [shift_m, 0.0, 0.0],
            },
            depth_scale_m: 0.001,
        }
    }

    #[test]
    fn the_same_camera_aligns_onto_itself_and_a_shift_moves_the_image() {
        // Each depth pixel covers the colour pixels between its corners' projections (here
        // itself and its right and lower neighbours), the nearest depth winning: a flat wall
        // aligns onto itself but for the last column and row, which reach outside the image.
        let flat = vec![1000u16; 64 * 48];
        let same = align_depth_to_colour(&calibration(0.0), &flat).unwrap();
        let filled = same.iter().filter(|&&z| z == 1000).count();
        assert_eq!(filled, 64 * 48, "every colour pixel has the wall's depth");
        let mut step = flat.clone();
        step[10 * 64 + 10] = 900;
        let near = align_depth_to_colour(&calibration(0.0), &step).unwrap();
        assert_eq!(
            (near[10 * 64 + 10], near[10 * 64 + 11], near[11 * 64 + 11], near[10 * 64 + 12]),
            (900, 900, 900, 1000)
        );
        // 0.1 m along x at 1 m with f = 60: 6 pixels.
        let shifted = align_depth_to_colour(&calibration(0.1), &flat).unwrap();
        assert_eq!(shifted[20 * 64 + 4], 0, "nothing lands left of column 5");
        assert_eq!(shifted[20 * 64 + 7], 1000);
    }

    #[test]
    fn distortion_and_sizes_are_refused_by_name() {
        let mut c = calibration(0.0);
        c.colour.coeffs[0] = 0.1;
        let e = align_depth_to_colour(&c, &[0; 64 * 48]).unwrap_err();
        assert!(e.to_string().starts_with("the colour stream's distortion (brown_conrady"), "{e}");
        let e = align_depth_to_colour(&calibration(0.0), &[0; 10]).unwrap_err();
        assert_eq!(e.to_string(), "a depth frame of 10 pixels for a 64x48 depth stream");
        assert_eq!(z16(&[0x34, 0x12, 0xff, 0x00]), vec![0x1234, 0x00ff]);
    }
}
