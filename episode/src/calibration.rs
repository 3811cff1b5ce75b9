//! A rig's camera calibrations as its nodes read them: `calibration/<rig>/<camera>.json`
//! (written by `labrig calibrate`, schema `labrig_msgs::calibration`), the warnings a rig
//! gives at start (missing, unreadable, older than allowed), and the summary that goes on the
//! latched `/calibration` topic and into every episode's metadata.

use labrig_msgs::calibration::{CALIBRATION_VERSION, CalibrationFile};
use std::collections::BTreeMap;
use std::path::Path;

/// DROID's GUI warns when a calibration is older than an hour.
pub const DEFAULT_MAX_AGE_S: f64 = 3600.0;

/// The calibrations found in a folder, and what was wrong with the others.
#[derive(Debug, Clone, Default)]
pub struct Calibrations {
    pub files: BTreeMap<String, CalibrationFile>,
    /// One line per camera whose file is missing or unreadable, naming the file.
    pub problems: Vec<String>,
}

/// Reads `<dir>/<camera>.json` for each of `cameras`.
pub fn load(dir: &Path, cameras: &[&str]) -> Calibrations {
    let mut out = Calibrations::default();
    for &camera in cameras {
        let path = dir.join(format!("{camera}.json"));
        let text = match std::fs::read_to_string(&path) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                out.problems.push(format!(
                    "camera `{camera}` has no calibration ({} missing): run `labrig calibrate --camera {camera}`",
                    path.display()
                ));
                continue;
            }
            Err(e) => {
                out.problems.push(format!("camera `{camera}`: cannot read {}: {e}", path.display()));
                continue;
            }
        };
        match serde_json::from_str::<CalibrationFile>(&text) {
            Ok(f) if f.version != CALIBRATION_VERSION => out.problems.push(format!(
                "camera `{camera}`: {} is calibration version {} (this labrig reads {CALIBRATION_VERSION})",
                path.display(),
                f.version
            )),
            Ok(f) if f.camera != camera => out.problems.push(format!(
                "camera `{camera}`: {} is the calibration of camera `{}`",
                path.display(),
                f.camera
            )),
            Ok(f) => {
                out.files.insert(camera.to_owned(), f);
            }
            Err(e) => out.problems.push(format!("camera `{camera}`: {} is not a calibration: {e}", path.display())),
        }
    }
    out
}

impl Calibrations {
    /// Keeps only the calibrations made in sim scene `scene` (or on a real rig); returns a
    /// warning per camera dropped.
    pub fn for_sim_scene(&mut self, scene: &str) -> Vec<String> {
        let mut dropped = Vec::new();
        self.files.retain(|camera, f| match &f.sim_scene {
            Some(s) if s != scene => {
                dropped.push(format!(
                    "camera `{camera}`'s calibration was made in scene `{s}`, not this scene `{scene}`: \
                     the scene's own pose is used"
                ));
                false
            }
            _ => true,
        });
        dropped
    }

    /// What a rig warns about at start: the problems, and each calibration older than
    /// `max_age_s` at `now_unix_s`.
    pub fn warnings(&self, now_unix_s: i64, max_age_s: f64) -> Vec<String> {
        let mut w = self.problems.clone();
        for (camera, f) in &self.files {
            let age = f.age_s(now_unix_s);
            if age as f64 > max_age_s {
                w.push(format!(
                    "camera `{camera}` was calibrated {} ago ({}), more than the {} allowed: check it with \
                     `labrig calibrate check --camera {camera}`",
                    human(age),
                    f.date,
                    human(max_age_s as i64)
                ));
            }
        }
        w
    }

    /// The summary for `/calibration` and the episode metadata (JSON): per camera its date,
    /// method, parent frame, DROID extrinsics, RMS and check figures.
    pub fn summary(&self) -> serde_json::Value {
        let cams: serde_json::Map<String, serde_json::Value> = self
            .files
            .iter()
            .map(|(c, f)| {
                (
                    c.clone(),
                    serde_json::json!({
                        "rig": f.rig, "date": f.date, "unix_time_s": f.unix_time_s, "method": f.method,
                        "parent_frame": f.parent_frame, "child_frame": f.child_frame,
                        "droid_extrinsics": f.droid_extrinsics, "rms_px": f.rms_px,
                        "check_mm": f.check.mean_position_error_mm, "check_deg": f.check.mean_rotation_error_deg,
                        "sim_scene": f.sim_scene,
                    }),
                )
            })
            .collect();
        serde_json::Value::Object(cams)
    }
}

/// `3h 12m`, `45 s`.
/// An age for people: seconds, minutes, hours and minutes, or days.
pub fn human(s: i64) -> String {
    match s {
        s if s < 120 => format!("{s} s"),
        s if s < 7200 => format!("{} min", s / 60),
        s if s < 172_800 => format!("{}h {:02}m", s / 3600, (s % 3600) / 60),
        s => format!("{} days", s / 86_400),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn file(camera: &str, unix_time_s: i64) -> CalibrationFile {
        CalibrationFile::example(camera, unix_time_s)
    }

    #[test]
    fn missing_wrong_and_old_calibrations_are_named() {
        let dir = tempfile::tempdir().unwrap();
        let now = 1_790_000_000;
        std::fs::write(dir.path().join("ext1.json"), serde_json::to_string(&file("ext1", now - 60)).unwrap()).unwrap();
        std::fs::write(dir.path().join("ext2.json"), serde_json::to_string(&file("ext2", now - 7300)).unwrap())
            .unwrap();
        std::fs::write(dir.path().join("rs1.json"), serde_json::to_string(&file("rs2", now)).unwrap()).unwrap();
        std::fs::write(dir.path().join("rs2.json"), "{").unwrap();
        let c = load(dir.path(), &["ext1", "ext2", "wrist", "rs1", "rs2"]);
        assert_eq!(c.files.keys().collect::<Vec<_>>(), ["ext1", "ext2"]);
        let w = c.warnings(now, DEFAULT_MAX_AGE_S);
        assert_eq!(w.len(), 4, "{w:#?}");
        assert!(
            w.iter().any(|l| l.contains("`wrist` has no calibration") && l.contains("wrist.json missing")),
            "{w:#?}"
        );
        assert!(w.iter().any(|l| l.contains("is the calibration of camera `rs2`")), "{w:#?}");
        assert!(w.iter().any(|l| l.contains("rs2.json is not a calibration")), "{w:#?}");
        assert!(w.iter().any(|l| l.contains("`ext2` was calibrated 2h 01m ago")), "{w:#?}");
        assert!(!w.iter().any(|l| l.contains("`ext1`")), "{w:#?}");
        let s = c.summary();
        assert_eq!(s["ext1"]["date"], "2026-11-25T12:00:00Z");
        assert_eq!(s["ext2"]["droid_extrinsics"][2], 0.3);
    }
}
