//! Pinhole intrinsics (plumb-bob distortion) of one camera image, where they come from (a ZED's
//! factory file `SN<serial>.conf`, a labrig intrinsics file, the config itself) and how they
//! scale to the resolution a camera is configured at.

use std::collections::BTreeMap;
use std::path::Path;

/// The intrinsics type is labrig-msgs' (calibration files, configs and sources share it).
pub use labrig_msgs::calibration::{AspectMismatch, Intrinsics};

/// Why intrinsics could not be had; each names the file or the resolution.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum IntrinsicsError {
    #[error("{path}: {reason}")]
    File { path: String, reason: String },
    #[error(transparent)]
    Aspect(#[from] AspectMismatch),
    #[error("{path}: no [{section}] section{}", if available.is_empty() { String::new() } else { format!(" (it has {})", available.join(", ")) })]
    MissingSection { path: String, section: String, available: Vec<String> },
    #[error(
        "{width}x{height} is no ZED resolution and has the aspect ratio of none (per eye: 2208x1242, 1920x1080, 1280x720, 672x376)"
    )]
    NotAZedSize { width: u32, height: u32 },
    #[error("{path}: [{section}] has no `{key}`")]
    MissingKey { path: String, section: String, key: String },
    #[error(
        "{width}x{height} cannot be rectified: the factory file rectifies the ZED's own resolutions only (per eye: 2208x1242, 1920x1080, 1280x720, 672x376)"
    )]
    NotRectifiable { width: u32, height: u32 },
}

/// A labrig intrinsics file: JSON or TOML with [`Intrinsics`]' fields (`source` = `file` when
/// it does not say).
pub fn load(path: &Path) -> Result<Intrinsics, IntrinsicsError> {
    let bad = |reason: String| IntrinsicsError::File { path: path.display().to_string(), reason };
    let text = std::fs::read_to_string(path).map_err(|e| bad(e.to_string()))?;
    let mut i: Intrinsics = if path.extension().is_some_and(|e| e == "json") {
        serde_json::from_str(&text).map_err(|e| bad(e.to_string()))?
    } else {
        toml::from_str(&text).map_err(|e| bad(e.to_string()))?
    };
    if i.source.is_empty() {
        i.source = "file".into();
    }
    Ok(i)
}

/// Which image of a stereo camera.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Eye {
    /// The one DROID records.
    #[default]
    Left,
    Right,
}

impl Eye {
    fn section_prefix(self) -> &'static str {
        match self {
            Eye::Left => "LEFT_CAM_",
            Eye::Right => "RIGHT_CAM_",
        }
    }
}

/// The per-eye resolutions of a ZED 2 / ZED Mini and the names of their sections in the
/// factory calibration file.
pub const ZED_RESOLUTIONS: [(&str, u32, u32); 4] =
    [("2K", 2208, 1242), ("FHD", 1920, 1080), ("HD", 1280, 720), ("VGA", 672, 376)];

/// A ZED's factory calibration file (`SN<serial>.conf`, INI): per eye and resolution
/// `[LEFT_CAM_HD]` with fx fy cx cy k1 k2 p1 p2 k3, and `[STEREO]` (Baseline in mm, ...).
#[derive(Debug, Clone, PartialEq)]
pub struct ZedCalibration {
    path: String,
    sections: BTreeMap<String, BTreeMap<String, f64>>,
}

impl ZedCalibration {
    pub fn load(path: &Path) -> Result<ZedCalibration, IntrinsicsError> {
        let text = std::fs::read_to_string(path)
            .map_err(|e| IntrinsicsError::File { path: path.display().to_string(), reason: e.to_string() })?;
        ZedCalibration::parse(&text, &path.display().to_string())
    }

    /// Parses the INI text (`path` names it in errors). Comments (`#`, `;`) and blank lines
    /// are skipped; keys are case-insensitive; a value that is not a number is refused.
    pub fn parse(text: &str, path: &str) -> Result<ZedCalibration, IntrinsicsError> {
        let mut sections: BTreeMap<String, BTreeMap<String, f64>> = BTreeMap::new();
        let mut current: Option<String> = None;
        for (n, line) in text.lines().enumerate() {
            let line = line.trim();
            if line.is_empty() || line.starts_with('#') || line.starts_with(';') {
                continue;
            }
            let bad = |reason: String| IntrinsicsError::File {
                path: path.to_owned(),
                reason: format!("line {}: {reason}", n + 1),
            };
            if let Some(name) = line.strip_prefix('[').and_then(|l| l.strip_suffix(']')) {
                let name = name.trim().to_ascii_uppercase();
                sections.entry(name.clone()).or_default();
                current = Some(name);
                continue;
            }
            let (key, value) =
                line.split_once('=').ok_or_else(|| bad(format!("`{line}` is neither [section] nor key = value")))?;
            let section = current.as_ref().ok_or_else(|| bad("a key before any [section]".into()))?;
            let v: f64 = value.trim().parse().map_err(|_| bad(format!("`{}` is not a number", value.trim())))?;
            sections.get_mut(section).expect("section").insert(key.trim().to_ascii_lowercase(), v);
        }
        if sections.is_empty() {
            return Err(IntrinsicsError::File {
                path: path.to_owned(),
                reason: "no sections (not a ZED calibration file)".into(),
            });
        }
        Ok(ZedCalibration { path: path.to_owned(), sections })
    }

    fn section(&self, name: &str) -> Result<&BTreeMap<String, f64>, IntrinsicsError> {
        self.sections.get(name).ok_or_else(|| IntrinsicsError::MissingSection {
            path: self.path.clone(),
            section: name.to_owned(),
            available: self.sections.keys().cloned().collect(),
        })
    }

    /// The eye's intrinsics at `width` x `height` (one eye's size, not the side-by-side
    /// frame's): the resolution's own section where there is one, else the nearest larger
    /// section of the same aspect ratio, scaled ([`Intrinsics::scaled`]).
    pub fn eye(&self, eye: Eye, width: u32, height: u32) -> Result<Intrinsics, IntrinsicsError> {
        let exact = ZED_RESOLUTIONS.iter().find(|(_, w, h)| (*w, *h) == (width, height));
        let (name, w, h) = match exact {
            Some(r) => *r,
            None => {
                // Each ZED resolution is its own sensor readout (crop or binning): scale from the
                // nearest one at least as large, of the same aspect ratio.
                let same_aspect = |(_, w, h): &&(&str, u32, u32)| {
                    ((*w as f64 / *h as f64) / (width as f64 / height as f64) - 1.0).abs() <= 1e-3
                };
                let mut candidates = ZED_RESOLUTIONS.iter().rev().filter(same_aspect);
                let nearest = candidates.clone().find(|(_, w, _)| *w >= width).or_else(|| candidates.next_back());
                *nearest.ok_or(IntrinsicsError::NotAZedSize { width, height })?
            }
        };
        let section_name = format!("{}{name}", eye.section_prefix());
        let s = self.section(&section_name)?;
        let get = |key: &str| self.value(&section_name, key);
        let native = Intrinsics {
            width: w,
            height: h,
            fx: get("fx")?,
            fy: get("fy")?,
            cx: get("cx")?,
            cy: get("cy")?,
            distortion: vec![get("k1")?, get("k2")?, get("p1")?, get("p2")?, s.get("k3").copied().unwrap_or(0.0)],
            source: "zed-factory".into(),
        };
        Ok(native.scaled(width, height)?)
    }

    /// The stereo baseline in metres (`[STEREO] Baseline`, in mm in the file).
    pub fn baseline_m(&self) -> Result<f64, IntrinsicsError> {
        Ok(self.value("STEREO", "baseline")? / 1000.0)
    }

    /// One key of one section (keys are case-insensitive); missing: named.
    pub fn value(&self, section: &str, key: &str) -> Result<f64, IntrinsicsError> {
        let key = key.to_ascii_lowercase();
        self.section(section)?.get(&key).copied().ok_or_else(|| IntrinsicsError::MissingKey {
            path: self.path.clone(),
            section: section.to_owned(),
            key,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use labrig_msgs::builtin_interfaces::Time;

    const FIXTURE: &str = include_str!("../tests/fixtures/SN000012345.conf");

    #[test]
    fn a_zed_file_gives_each_resolution_its_own_section() {
        let z = ZedCalibration::parse(FIXTURE, "SN000012345.conf").unwrap();
        // [LEFT_CAM_HD] as written in the fixture.
        let hd = z.eye(Eye::Left, 1280, 720).unwrap();
        assert_eq!((hd.fx, hd.fy, hd.cx, hd.cy), (529.5, 529.25, 641.25, 352.75));
        assert_eq!(hd.distortion, vec![-0.0412, 0.0101, 0.0002, -0.0003, -0.0049]);
        // [LEFT_CAM_VGA] (672x376 per eye: not 16:9, its own section).
        let vga = z.eye(Eye::Left, 672, 376).unwrap();
        assert_eq!((vga.fx, vga.fy, vga.cx, vga.cy), (264.75, 264.625, 334.125, 183.875));
        let right = z.eye(Eye::Right, 1280, 720).unwrap();
        assert_eq!(right.fx, 528.75);
        assert!((z.baseline_m().unwrap() - 0.11998).abs() < 1e-12);
    }

    #[test]
    fn other_sizes_scale_from_the_same_aspect_ratio() {
        let z = ZedCalibration::parse(FIXTURE, "SN000012345.conf").unwrap();
        // 640x360 is HD halved: fx 529.5 / 2; cx (641.25 + 0.5) / 2 - 0.5 = 320.375.
        let half = z.eye(Eye::Left, 640, 360).unwrap();
        assert_eq!((half.fx, half.fy, half.cx, half.cy), (264.75, 264.625, 320.375, 176.125));
        let e = z.eye(Eye::Left, 640, 480).unwrap_err();
        assert!(e.to_string().starts_with("640x480 is no ZED resolution"), "{e}");
    }

    #[test]
    fn missing_sections_and_keys_are_named() {
        let text = "[LEFT_CAM_HD]\nfx = 1\nfy = 1\ncx = 1\n";
        let z = ZedCalibration::parse(text, "SN1.conf").unwrap();
        assert_eq!(z.eye(Eye::Left, 1280, 720).unwrap_err().to_string(), "SN1.conf: [LEFT_CAM_HD] has no `cy`");
        assert_eq!(
            z.eye(Eye::Left, 1920, 1080).unwrap_err().to_string(),
            "SN1.conf: no [LEFT_CAM_FHD] section (it has LEFT_CAM_HD)"
        );
        let e = ZedCalibration::parse("[STEREO]\nBaseline = twelve\n", "SN2.conf").unwrap_err();
        assert_eq!(e.to_string(), "SN2.conf: line 2: `twelve` is not a number");
    }

    #[test]
    fn camera_info_carries_the_matrix_and_five_coefficients() {
        let i = Intrinsics {
            width: 4,
            height: 2,
            fx: 2.0,
            fy: 3.0,
            cx: 1.5,
            cy: 0.5,
            distortion: vec![0.1],
            source: String::new(),
        };
        let info = i.camera_info(Time { sec: 1, nanosec: 2 }, "ext1_optical");
        assert_eq!(info.k, [2.0, 0.0, 1.5, 0.0, 3.0, 0.5, 0.0, 0.0, 1.0]);
        assert_eq!(info.d, vec![0.1, 0.0, 0.0, 0.0, 0.0]);
        assert_eq!((info.width, info.height, info.header.frame_id.as_str()), (4, 2, "ext1_optical"));
    }
}
