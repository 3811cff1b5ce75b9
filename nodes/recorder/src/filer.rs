//! Ended episodes finished and filed beside the recording loop.
//!
//! Finishing an episode waits for the disk (the file's last fsync) and a busy disk makes that
//! wait seconds; the loop meanwhile must go on taking the next episode's frames, or its
//! frame intake overflows and loses frames that steps use. So a thread of its own finishes
//! each ended episode (summary, fsync, `metadata.yaml`) and moves it into DROID's layout, in
//! the order they ended, and reports back what the status should say.

use labrig_episode::episode::EpisodeWriter;
use labrig_episode::metadata::{Outcome, episode_dir};
use labrig_msgs::Nanos;
use serde_json::json;
use std::path::{Path, PathBuf};
use std::sync::mpsc::{Receiver, Sender, channel};
use std::thread::JoinHandle;

/// An ended episode to finish.
pub(crate) struct Filing {
    pub writer: EpisodeWriter,
    /// Its staging directory (`<root>/.recording/<uuid>`).
    pub staging: PathBuf,
    pub uuid: String,
    pub outcome: Outcome,
    /// Why it ended, when the loop did not end it ("" otherwise).
    pub why: String,
    /// The disk filled up: filed as it is, reported as an error.
    pub disk_full: bool,
    /// Deleted, not filed (a `Discard`).
    pub discard: bool,
}

/// What a filing came to: the recorder's status (`state` recorded, discarded or error).
#[derive(Debug)]
pub(crate) struct Filed {
    pub status: serde_json::Value,
    pub failed: bool,
}

/// The thread finishing ended episodes, in order.
pub(crate) struct Filer {
    jobs: Option<Sender<Filing>>,
    done: Receiver<Filed>,
    thread: Option<JoinHandle<()>>,
    /// Filings handed over and not reported back yet.
    pending: usize,
    /// Filings done on the loop after the thread was lost.
    inline: Vec<Filed>,
}

impl Filer {
    /// Files episodes under `root` (DROID's `<root>/{success|failure}/<date>/<time>/`).
    pub(crate) fn start(root: PathBuf) -> std::io::Result<Filer> {
        let (jobs, todo) = channel::<Filing>();
        let (report, done) = channel();
        let thread = std::thread::Builder::new().name("episode-filer".into()).spawn(move || {
            for f in todo {
                if report.send(file(&root, f)).is_err() {
                    break;
                }
            }
        })?;
        Ok(Filer { jobs: Some(jobs), done, thread: Some(thread), pending: 0, inline: Vec::new() })
    }

    /// Hands an ended episode over; its report comes from [`Filer::reports`].
    pub(crate) fn submit(&mut self, f: Filing) {
        let Some(jobs) = &self.jobs else { return };
        match jobs.send(f) {
            Ok(()) => self.pending += 1,
            // The thread is gone (it panicked): finish here rather than lose the episode.
            Err(std::sync::mpsc::SendError(f)) => {
                tracing::error!("the episode filer thread is gone: filing {} on the loop", f.uuid);
                let root = f.staging.parent().and_then(Path::parent).map(Path::to_path_buf).unwrap_or_default();
                let filed = file(&root, f);
                self.inline.push(filed);
            }
        }
    }

    /// The filings done since the last call.
    pub(crate) fn reports(&mut self) -> Vec<Filed> {
        let mut filed: Vec<Filed> = self.done.try_iter().collect();
        self.pending = self.pending.saturating_sub(filed.len());
        filed.append(&mut self.inline);
        filed
    }

    /// Waits for every filing handed over, and returns their reports.
    pub(crate) fn stop(&mut self) -> Vec<Filed> {
        drop(self.jobs.take());
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
        let mut filed: Vec<Filed> = self.done.try_iter().collect();
        filed.append(&mut self.inline);
        filed
    }
}

/// Finishes one episode and moves it into DROID's layout (or deletes it, discarded).
fn file(root: &Path, f: Filing) -> Filed {
    let Filing { writer, staging, uuid, outcome, why, disk_full, discard } = f;
    let start_ns = writer.metadata().start_ns;
    if discard {
        let _ = writer.finish();
        let _ = std::fs::remove_dir_all(&staging);
        return Filed { status: json!({ "state": "discarded", "staging": staging }), failed: false };
    }
    let summary = match writer.finish() {
        Ok(s) => s,
        Err(e) => {
            tracing::error!("finishing the episode: {e}");
            let status =
                json!({ "state": "error", "error": e.to_string(), "disk_full": e.is_disk_full(), "staging": staging });
            return Filed { status, failed: true };
        }
    };
    // Two episodes may start in the same second (DROID's directory names are to the second):
    // the later one gets a suffix rather than failing to move.
    let dest = crate::node::free_name(episode_dir(root, outcome, Nanos(start_ns)));
    let moved = dest.parent().map(std::fs::create_dir_all).transpose().and_then(|_| std::fs::rename(&staging, &dest));
    match moved {
        Ok(()) if disk_full => {
            tracing::info!(dir = %dest.display(), messages = summary.messages, "episode recorded {why}");
            let status = json!({ "state": "error", "episode": uuid, "error": why, "disk_full": true, "dir": dest });
            Filed { status, failed: false }
        }
        Ok(()) => {
            tracing::info!(dir = %dest.display(), messages = summary.messages, "episode recorded {why}");
            let status = json!({ "state": "recorded", "episode": uuid, "outcome": outcome.dir(), "dir": dest, "messages": summary.messages, "bytes": summary.bytes, "note": why });
            Filed { status, failed: false }
        }
        Err(e) => {
            tracing::error!("moving {} to {}: {e}", staging.display(), dest.display());
            let status = json!({ "state": "error", "error": format!("moving the episode: {e}"), "staging": staging });
            Filed { status, failed: false }
        }
    }
}
