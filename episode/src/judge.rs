//! Judging a recorded episode again without rewriting its recording: relabel success <->
//! failure, or put it in the trash (never erased).
//!
//! - Relabel moves `<root>/success/<date>/<name>` to `<root>/failure/<date>/<name>` (or back)
//!   and writes `judged.json` beside the MCAP: `{"success": bool, "history": [{"from", "to",
//!   "at", "by"}]}`, each relabel appended to the history. Every reader in labrig
//!   ([`crate::read_episode`], [`crate::inspect`], the DROID export, the dataset index) takes
//!   the judged flag from it over the MCAP's `droid_episode` record, which stays as recorded.
//! - Trash moves the episode to `<root>/trash/<date>/<name>`; `labrig` never deletes one.

use crate::metadata::Outcome;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// The sidecar that holds an episode's judged flag after a relabel.
pub const JUDGED_FILE: &str = "judged.json";
/// Where trashed episodes go, under the episodes root.
pub const TRASH_DIR: &str = "trash";

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Judged {
    pub success: bool,
    #[serde(default)]
    pub history: Vec<Relabel>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Relabel {
    /// The flag before (null when the recording had none).
    pub from: Option<bool>,
    pub to: bool,
    /// When (UTC, RFC 3339).
    pub at: String,
    /// Who or what relabelled it (e.g. `station:alice`).
    pub by: String,
}

#[derive(Debug, thiserror::Error)]
pub enum JudgeError {
    #[error("{path}: not an episode under {root}/success or {root}/failure")]
    NotUnder { path: String, root: String },
    #[error("{path}: {what}: {source}")]
    Io { path: String, what: &'static str, source: std::io::Error },
    #[error("{path} exists already: the episode is not moved over it")]
    Exists { path: String },
}

fn io(path: &Path, what: &'static str) -> impl FnOnce(std::io::Error) -> JudgeError {
    let path = path.display().to_string();
    move |source| JudgeError::Io { path, what, source }
}

/// The judged flag of the episode in `dir`, if it was relabelled (an unreadable sidecar
/// counts as none: the recording's flag stands).
pub fn judged(dir: &Path) -> Option<Judged> {
    let text = std::fs::read_to_string(dir.join(JUDGED_FILE)).ok()?;
    serde_json::from_str(&text).ok()
}

/// Where `dir` sits: its outcome folder, date folder and name, if it is
/// `<root>/{success|failure}/<date>/<name>`.
fn place(root: &Path, dir: &Path) -> Result<(Outcome, String, String), JudgeError> {
    let not_under = || JudgeError::NotUnder { path: dir.display().to_string(), root: root.display().to_string() };
    let root_c = std::fs::canonicalize(root).map_err(io(root, "resolving the episodes root"))?;
    let dir_c = std::fs::canonicalize(dir).map_err(io(dir, "resolving the episode"))?;
    let rel = dir_c.strip_prefix(&root_c).map_err(|_| not_under())?;
    let parts: Vec<&str> = rel.iter().filter_map(|p| p.to_str()).collect();
    let [outcome, date, name] = parts.as_slice() else { return Err(not_under()) };
    let outcome = match *outcome {
        "success" => Outcome::Success,
        "failure" => Outcome::Failure,
        _ => return Err(not_under()),
    };
    if !dir_c.join(crate::episode::EPISODE_FILE).is_file() {
        return Err(not_under());
    }
    Ok((outcome, date.to_string(), name.to_string()))
}

fn move_dir(from: &Path, to: &Path) -> Result<(), JudgeError> {
    if to.exists() {
        return Err(JudgeError::Exists { path: to.display().to_string() });
    }
    if let Some(parent) = to.parent() {
        std::fs::create_dir_all(parent).map_err(io(parent, "creating"))?;
    }
    std::fs::rename(from, to).map_err(io(from, "moving"))?;
    // Leave no empty date folder behind.
    if let Some(parent) = from.parent() {
        let _ = std::fs::remove_dir(parent);
    }
    Ok(())
}

/// Judges the episode in `dir` (under `root`) `success` or not: moves it to that outcome's
/// folder (when it is not there already) and records the relabel in [`JUDGED_FILE`].
/// Returns where the episode is now.
pub fn relabel(root: &Path, dir: &Path, success: bool, by: &str) -> Result<PathBuf, JudgeError> {
    let (outcome, date, name) = place(root, dir)?;
    let target = if success { Outcome::Success } else { Outcome::Failure };
    let before = judged(dir).map(|j| Some(j.success)).unwrap_or(match outcome {
        Outcome::Success => Some(true),
        Outcome::Failure => Some(false),
    });
    let dest = root.join(target.dir()).join(&date).join(&name);
    let mut j = judged(dir).unwrap_or(Judged { success, history: Vec::new() });
    j.success = success;
    j.history.push(Relabel {
        from: before,
        to: success,
        at: chrono::Utc::now().to_rfc3339_opts(chrono::SecondsFormat::Millis, true),
        by: by.to_owned(),
    });
    // The sidecar first (through a temporary name), then the move: a crash in between leaves
    // the flag right and the folder to move again.
    let tmp = dir.join(".judged.json.tmp");
    let text = serde_json::to_string_pretty(&j).expect("plain data");
    std::fs::write(&tmp, text).map_err(io(&tmp, "writing"))?;
    std::fs::rename(&tmp, dir.join(JUDGED_FILE)).map_err(io(dir, "writing judged.json"))?;
    if outcome != target {
        move_dir(dir, &dest)?;
        Ok(dest)
    } else {
        Ok(dir.to_owned())
    }
}

/// Moves the episode in `dir` (under `root`) to `<root>/trash/<date>/<name>`; returns where.
pub fn trash(root: &Path, dir: &Path) -> Result<PathBuf, JudgeError> {
    let (_, date, name) = place(root, dir)?;
    let base = root.join(TRASH_DIR).join(&date);
    let mut dest = base.join(&name);
    let mut k = 1;
    while dest.exists() {
        dest = base.join(format!("{name}-{k}"));
        k += 1;
    }
    move_dir(dir, &dest)?;
    Ok(dest)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn episode(root: &Path, outcome: &str) -> PathBuf {
        let dir = root.join(outcome).join("2026-11-27").join("Fri_Nov_27_10:00:00_2026");
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join(crate::episode::EPISODE_FILE), b"mcap").unwrap();
        dir
    }

    #[test]
    fn relabel_moves_and_keeps_a_history_and_trash_never_erases() {
        let t = tempfile::tempdir().unwrap();
        let root = t.path();
        let dir = episode(root, "success");
        let moved = relabel(root, &dir, false, "station:alice").unwrap();
        assert_eq!(moved, root.join("failure/2026-11-27/Fri_Nov_27_10:00:00_2026"));
        assert!(!dir.exists() && !root.join("success/2026-11-27").exists());
        let j = judged(&moved).unwrap();
        assert!(!j.success && j.history.len() == 1 && j.history[0].from == Some(true));
        let back = relabel(root, &moved, true, "cli").unwrap();
        assert_eq!(judged(&back).unwrap().history.len(), 2);
        let gone = trash(root, &back).unwrap();
        assert!(gone.starts_with(root.join("trash")) && gone.join(crate::episode::EPISODE_FILE).is_file());
        // A path outside the layout is refused by name.
        let e = relabel(root, root, true, "x").unwrap_err();
        assert!(e.to_string().contains("not an episode under"), "{e}");
        let e = trash(root, &gone).unwrap_err();
        assert!(e.to_string().contains("not an episode under"), "{e}");
    }
}
