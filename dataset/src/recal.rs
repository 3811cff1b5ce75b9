//! DROID's re-calibrated camera extrinsics (`cam2base_extrinsics.json` of its annotation
//! release, ~36k episodes): a JSON object keyed by episode (the metadata's `uuid`, e.g.
//! `AUTOLab+5d05c5aa+2023-07-07-10h-19m-06s`, or the RLDS key `recording_folderpath--file_path`),
//! each value an object from camera serial to the left lens's pose in the robot base frame
//! as DROID writes extrinsics (x, y, z, then extrinsic xyz Euler angles, rad). Keys that are not
//! a serial (`<serial>_left` is read as `<serial>`) or values that are not six numbers (the
//! release's quality figures) are ignored.
//!
//! `labrig dataset index --extrinsics <file>` replaces an episode's camera pose with the
//! file's where the episode's metadata names that camera's serial; the index column
//! `<camera>_extrinsics_from` says which one a row has (`metadata` or `recalibrated`).

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};

/// The override file, read once.
#[derive(Debug, Clone, Default)]
pub struct Recalibration {
    by_episode: HashMap<String, BTreeMap<String, [f64; 6]>>,
    /// The file's path, size and modification time: an index made with another one is redone.
    pub stamp: String,
}

/// Why the override file cannot be used, naming it.
#[derive(Debug, thiserror::Error)]
pub enum RecalError {
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{}: not JSON: {source}", path.display())]
    NotJson {
        path: PathBuf,
        #[source]
        source: serde_json::Error,
    },
    #[error("{}: expected an object keyed by episode, as DROID's cam2base_extrinsics.json", path.display())]
    NotAnObject { path: PathBuf },
    #[error("{}: episode {episode}: expected an object of camera serial -> 6 numbers", path.display())]
    EpisodeNotAnObject { path: PathBuf, episode: String },
    #[error("{}: episode {episode}, camera {camera}: expected 6 finite numbers, got {value}", path.display())]
    NotAPose { path: PathBuf, episode: String, camera: String, value: serde_json::Value },
}

impl Recalibration {
    pub fn load(path: &Path) -> Result<Recalibration, RecalError> {
        let io = |source| RecalError::Io { path: path.to_owned(), source };
        let bytes = std::fs::read(path).map_err(io)?;
        let value: serde_json::Value =
            serde_json::from_slice(&bytes).map_err(|source| RecalError::NotJson { path: path.to_owned(), source })?;
        let serde_json::Value::Object(top) = value else {
            return Err(RecalError::NotAnObject { path: path.to_owned() });
        };
        let mut by_episode = HashMap::with_capacity(top.len());
        for (episode, cams) in top {
            let serde_json::Value::Object(cams) = cams else {
                return Err(RecalError::EpisodeNotAnObject { path: path.to_owned(), episode });
            };
            let mut poses = BTreeMap::new();
            for (key, v) in cams {
                let serial = key.strip_suffix("_left").unwrap_or(&key);
                if serial.is_empty() || !serial.bytes().all(|b| b.is_ascii_digit()) {
                    continue;
                }
                let pose: Option<Vec<f64>> = v.as_array().and_then(|a| a.iter().map(|x| x.as_f64()).collect());
                match pose {
                    Some(p) if p.len() == 6 && p.iter().all(|x| x.is_finite()) => {
                        poses.insert(serial.to_owned(), [p[0], p[1], p[2], p[3], p[4], p[5]]);
                    }
                    _ => {
                        return Err(RecalError::NotAPose { path: path.to_owned(), episode, camera: key, value: v });
                    }
                }
            }
            by_episode.insert(episode, poses);
        }
        let meta = std::fs::metadata(path).map_err(io)?;
        let mtime = meta
            .modified()
            .ok()
            .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
            .map(|d| d.as_nanos())
            .unwrap_or(0);
        let canonical = std::fs::canonicalize(path).unwrap_or_else(|_| path.to_owned());
        Ok(Recalibration { by_episode, stamp: format!("{} {} {mtime}", canonical.display(), meta.len()) })
    }

    pub fn episodes(&self) -> usize {
        self.by_episode.len()
    }

    /// The re-calibrated pose of the camera with `serial` in `episode`, if the file has one.
    pub fn pose(&self, episode: &str, serial: &str) -> Option<[f64; 6]> {
        self.by_episode.get(episode)?.get(serial).copied()
    }

    /// Whether the file names `episode` at all.
    pub fn has(&self, episode: &str) -> bool {
        self.by_episode.contains_key(episode)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn serials_are_read_and_quality_figures_skipped() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("cam2base_extrinsics.json");
        std::fs::write(
            &p,
            r#"{"LAB+op+1": {"21": [0.1, 0.2, 0.3, 0, 0, 1], "22_left": [1, 2, 3, 0, 0, 0], "21_metric": 0.4}}"#,
        )
        .unwrap();
        let r = Recalibration::load(&p).unwrap();
        assert_eq!(r.pose("LAB+op+1", "21"), Some([0.1, 0.2, 0.3, 0.0, 0.0, 1.0]));
        assert_eq!(r.pose("LAB+op+1", "22"), Some([1.0, 2.0, 3.0, 0.0, 0.0, 0.0]));
        assert_eq!(r.pose("LAB+op+1", "23"), None);
        assert!(r.has("LAB+op+1") && !r.has("LAB+op+2"));
        std::fs::write(&p, r#"{"LAB+op+1": {"21": [0.1, 0.2]}}"#).unwrap();
        let e = Recalibration::load(&p).unwrap_err().to_string();
        assert!(e.contains("episode LAB+op+1, camera 21: expected 6 finite numbers"), "{e}");
    }
}
