//! Making an episode file durable without waiting for the disk: the writer hands each closed
//! chunk to the kernel at once (a killed recorder loses none of it) and asks this thread to
//! fsync it (a machine that loses power loses none of it once the fsync returns).
//!
//! An fsync waits for the disk, and a busy disk (another process writing, a loaded CI machine)
//! makes it wait seconds: measured here at up to 2.1 s. Done in the recorder's loop, that wait
//! let the frame intake overflow and lose frames that steps had used. Here it runs beside the
//! loop; requests that come while one runs are folded into the next one, since an fsync covers
//! everything written before it starts.

use std::fs::File;
use std::io;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{Receiver, SyncSender, TrySendError, sync_channel};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;

/// What the thread has done, shared with the writer.
#[derive(Debug, Default)]
struct Shared {
    /// Chunks handed to the kernel when the newest request was made.
    requested: AtomicU64,
    /// Chunks on the disk: those handed over before the last fsync that returned began.
    synced: AtomicU64,
    /// The first fsync error, for the writer's next call to report.
    error: Mutex<Option<io::Error>>,
}

/// How a file is made durable: `File::sync_data`, or in tests a stand-in that can be held.
pub(crate) type SyncFn = Box<dyn FnMut(&File) -> io::Result<()> + Send>;

/// A thread fsyncing one file on request.
#[derive(Debug)]
pub(crate) struct Syncer {
    wake: Option<SyncSender<()>>,
    shared: Arc<Shared>,
    thread: Option<JoinHandle<()>>,
}

impl Syncer {
    /// A thread fsyncing `file` (a second handle on the file being written).
    pub(crate) fn start(file: File) -> io::Result<Syncer> {
        Syncer::start_with(file, Box::new(|f: &File| f.sync_data()))
    }

    pub(crate) fn start_with(file: File, mut sync: SyncFn) -> io::Result<Syncer> {
        let shared = Arc::new(Shared::default());
        // One request waiting is enough: it runs after the fsync in progress, covering all.
        let (wake, asked): (SyncSender<()>, Receiver<()>) = sync_channel(1);
        let theirs = Arc::clone(&shared);
        let thread = std::thread::Builder::new().name("episode-fsync".into()).spawn(move || {
            while asked.recv().is_ok() {
                let covers = theirs.requested.load(Ordering::Acquire);
                match sync(&file) {
                    Ok(()) => theirs.synced.fetch_max(covers, Ordering::AcqRel),
                    Err(e) => {
                        theirs.error.lock().unwrap_or_else(|p| p.into_inner()).get_or_insert(e);
                        0
                    }
                };
            }
        })?;
        Ok(Syncer { wake: Some(wake), shared, thread: Some(thread) })
    }

    /// Asks for an fsync of everything handed to the kernel so far (`chunks` closed), without
    /// waiting for it; an earlier fsync's error is returned instead.
    pub(crate) fn request(&self, chunks: u64) -> io::Result<()> {
        self.take_error()?;
        self.shared.requested.fetch_max(chunks, Ordering::AcqRel);
        match self.wake.as_ref().map(|w| w.try_send(())) {
            Some(Ok(()) | Err(TrySendError::Full(()))) => Ok(()),
            Some(Err(TrySendError::Disconnected(()))) | None => {
                Err(io::Error::other("the fsync thread of the episode file ended"))
            }
        }
    }

    /// Chunks known to be on the disk.
    pub(crate) fn synced(&self) -> u64 {
        self.shared.synced.load(Ordering::Acquire)
    }

    /// An fsync that failed since the last call.
    pub(crate) fn take_error(&self) -> io::Result<()> {
        match self.shared.error.lock().unwrap_or_else(|p| p.into_inner()).take() {
            Some(e) => Err(e),
            None => Ok(()),
        }
    }

    /// Waits for the requests made so far to be done, and ends the thread.
    pub(crate) fn stop(mut self) -> io::Result<()> {
        self.join();
        self.take_error()
    }

    fn join(&mut self) {
        drop(self.wake.take());
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl Drop for Syncer {
    /// A writer dropped unfinished (a write failed, a test's simulated kill) leaves the thread
    /// to finish its fsync in progress on its own: nothing waits for the disk here.
    fn drop(&mut self) {
        drop(self.wake.take());
        drop(self.thread.take());
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::mpsc::channel;

    /// A stand-in fsync that waits for `release` before returning, and reports each start.
    fn held() -> (SyncFn, std::sync::mpsc::Sender<io::Result<()>>, Receiver<()>) {
        let (release, released) = channel::<io::Result<()>>();
        let (started, starts) = channel();
        let f: SyncFn = Box::new(move |_| {
            let _ = started.send(());
            released.recv().unwrap_or(Ok(()))
        });
        (f, release, starts)
    }

    #[test]
    fn requests_while_an_fsync_runs_return_at_once_and_are_folded_into_the_next() {
        let file = tempfile::tempfile().unwrap();
        let (f, release, starts) = held();
        let s = Syncer::start_with(file, f).unwrap();
        s.request(1).unwrap();
        starts.recv().unwrap(); // the first fsync runs, held
        // Ten more chunks handed over while the disk "waits": none of these calls waits.
        for k in 2..=11 {
            s.request(k).unwrap();
        }
        assert_eq!(s.synced(), 0, "nothing is on the disk until an fsync returns");
        release.send(Ok(())).unwrap();
        starts.recv().unwrap(); // one more fsync for the ten, not ten
        assert!(s.synced() >= 1);
        release.send(Ok(())).unwrap();
        let shared = Arc::clone(&s.shared);
        s.stop().unwrap();
        assert!(starts.try_recv().is_err(), "two fsyncs in all");
        assert_eq!(shared.synced.load(Ordering::Acquire), 11);
    }

    #[test]
    fn stop_waits_for_the_last_request_and_reports_every_chunk_synced() {
        let file = tempfile::tempfile().unwrap();
        let (f, release, starts) = held();
        let s = Syncer::start_with(file, f).unwrap();
        s.request(3).unwrap();
        starts.recv().unwrap();
        let shared = Arc::clone(&s.shared);
        release.send(Ok(())).unwrap();
        s.stop().unwrap();
        assert_eq!(shared.synced.load(Ordering::Acquire), 3);
    }

    #[test]
    fn a_failed_fsync_is_reported_when_the_writer_stops() {
        let file = tempfile::tempfile().unwrap();
        let (f, release, starts) = held();
        let s = Syncer::start_with(file, f).unwrap();
        s.request(1).unwrap();
        starts.recv().unwrap();
        release.send(Err(io::Error::from_raw_os_error(28))).unwrap();
        // The error is stored before the thread waits again: a stop joins it and then reads it.
        let e = s.stop().unwrap_err();
        assert_eq!(e.raw_os_error(), Some(28));
    }
}
