//! The episodes under the recorder's root as the page lists them: each with its `labrig
//! inspect` figures (cached by file size and time, so a list costs one pass per new episode),
//! relabel and trash through labrig_episode::judge. A client names an episode by its uuid
//! only; the path is looked up here, never built from what the client sent.

use labrig_episode::judge;
use serde::Serialize;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::SystemTime;

/// One episode as listed.
#[derive(Debug, Clone, Serialize)]
pub struct Listed {
    pub id: String,
    /// `success` or `failure` (the folder it is in).
    pub outcome: String,
    pub success: Option<bool>,
    pub relabeled: bool,
    pub steps: u64,
    pub duration_s: f64,
    pub dropped: u64,
    pub camera_skew_p99_ms: Option<f64>,
    /// `OK`, or the inspection's flags.
    pub verdict: String,
    pub flags: Vec<String>,
    pub operator: String,
    pub lab: String,
    pub building: String,
    pub scene_id: String,
    pub task: String,
    pub start_ns: i64,
    #[serde(skip)]
    pub dir: PathBuf,
}

#[derive(Debug, thiserror::Error)]
pub enum EpisodesError {
    #[error("no episode {0} under the root")]
    Unknown(String),
    #[error("{0:?} is not an episode id (letters, digits, '+', '-', '_', '.', ':')")]
    BadId(String),
    #[error(transparent)]
    Judge(#[from] judge::JudgeError),
    #[error("{0}")]
    Other(String),
}

/// An episode id as a client may send it: DROID's `<lab>+<user>+<time>` characters only.
pub fn check_id(id: &str) -> Result<(), EpisodesError> {
    let ok = !id.is_empty()
        && id.len() <= 200
        && id.bytes().all(|b| b.is_ascii_alphanumeric() || b"+-_.:".contains(&b))
        && !id.contains("..");
    if ok { Ok(()) } else { Err(EpisodesError::BadId(id.to_owned())) }
}

/// How many episodes the page lists (and the station acts on): the newest.
pub const LISTED: usize = 200;

/// The list, cached per episode file.
#[derive(Debug, Default)]
pub struct Episodes {
    cache: BTreeMap<PathBuf, ((u64, SystemTime), Listed)>,
}

fn stamp(dir: &Path) -> Option<(u64, SystemTime)> {
    let mut size = 0;
    let mut newest = SystemTime::UNIX_EPOCH;
    for f in [labrig_episode::episode::EPISODE_FILE, judge::JUDGED_FILE] {
        if let Ok(m) = std::fs::metadata(dir.join(f)) {
            size += m.len();
            newest = newest.max(m.modified().ok()?);
        }
    }
    Some((size, newest))
}

fn listed(dir: &Path, outcome: &str) -> Option<Listed> {
    let i = labrig_episode::inspect(dir).ok()?;
    let meta = i.metadata.clone()?;
    Some(Listed {
        id: meta.uuid.clone(),
        outcome: outcome.to_owned(),
        success: meta.success,
        relabeled: judge::judged(dir).is_some(),
        steps: i.steps,
        duration_s: i.duration_s,
        dropped: i.cameras.iter().map(|c| c.dropped).sum(),
        camera_skew_p99_ms: i.camera_skew_ms.as_ref().map(|p| p.p99),
        verdict: if i.flags.is_empty() { "OK".into() } else { format!("{} flagged", i.flags.len()) },
        flags: i.flags.clone(),
        operator: meta.user,
        lab: meta.lab,
        building: meta.building,
        scene_id: meta.scene_id,
        task: meta.task_instruction,
        start_ns: meta.start_ns,
        dir: dir.to_owned(),
    })
}

impl Episodes {
    /// The episodes under `root`'s success/ and failure/, newest first (at most `limit`).
    pub fn list(&mut self, root: &Path, limit: usize) -> Vec<Listed> {
        // The newest `limit` by file time first (a rig's root holds thousands: only those are
        // inspected), then each read once and cached while its files stay as they were.
        let mut found: Vec<(SystemTime, u64, PathBuf, &str)> = Vec::new();
        for outcome in ["success", "failure"] {
            for dir in labrig_episode::episode::find_episodes(&root.join(outcome)) {
                let Some((size, time)) = stamp(&dir) else { continue };
                found.push((time, size, dir, outcome));
            }
        }
        found.sort_by_key(|f| std::cmp::Reverse(f.0));
        found.truncate(limit);
        let mut out = Vec::new();
        for (time, size, dir, outcome) in &found {
            let st = (*size, *time);
            match self.cache.get(dir) {
                Some((s, l)) if *s == st => out.push(l.clone()),
                _ => {
                    // An episode being finished is skipped until it reads.
                    if let Some(l) = listed(dir, outcome) {
                        self.cache.insert(dir.clone(), (st, l.clone()));
                        out.push(l);
                    }
                }
            }
        }
        self.cache.retain(|d, _| found.iter().any(|f| &f.2 == d));
        out.sort_by_key(|l| std::cmp::Reverse(l.start_ns));
        out.truncate(limit);
        out
    }

    /// The folder of episode `id` (looked up in a fresh list of the newest [`LISTED`]: the ones
    /// the page shows).
    pub fn find(&mut self, root: &Path, id: &str) -> Result<PathBuf, EpisodesError> {
        check_id(id)?;
        self.list(root, LISTED)
            .into_iter()
            .find(|l| l.id == id)
            .map(|l| l.dir)
            .ok_or_else(|| EpisodesError::Unknown(id.to_owned()))
    }

    pub fn relabel(&mut self, root: &Path, id: &str, success: bool, by: &str) -> Result<PathBuf, EpisodesError> {
        let dir = self.find(root, id)?;
        Ok(judge::relabel(root, &dir, success, by)?)
    }

    pub fn trash(&mut self, root: &Path, id: &str) -> Result<PathBuf, EpisodesError> {
        let dir = self.find(root, id)?;
        Ok(judge::trash(root, &dir)?)
    }

    pub fn sheet(&mut self, root: &Path, id: &str) -> Result<Vec<u8>, EpisodesError> {
        let dir = self.find(root, id)?;
        labrig_episode::sheet::contact_sheet_png(&dir.join(labrig_episode::episode::EPISODE_FILE))
            .map_err(|e| EpisodesError::Other(e.to_string()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ids_that_could_reach_the_filesystem_are_refused() {
        assert!(check_id("LABRIG+alice+2026-11-27-10h-00m-00s").is_ok());
        for bad in ["", "../etc", "a/b", "a\\b", "x..y", "a b", "%2e%2e"] {
            assert!(check_id(bad).is_err(), "{bad}");
        }
    }
}
