//! Node lifecycle: a shutdown token set by SIGINT/SIGTERM (or by the node itself), so every loop
//! can end cleanly and flush what it holds.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use tokio::sync::Notify;

/// Cloneable shutdown token.
#[derive(Debug, Clone, Default)]
pub struct Shutdown {
    inner: Arc<Inner>,
}

#[derive(Debug, Default)]
struct Inner {
    triggered: AtomicBool,
    notify: Notify,
}

impl Shutdown {
    pub fn new() -> Self {
        Self::default()
    }

    /// Requests shutdown; every waiter wakes.
    pub fn trigger(&self) {
        self.inner.triggered.store(true, Ordering::SeqCst);
        self.inner.notify.notify_waiters();
    }

    pub fn is_triggered(&self) -> bool {
        self.inner.triggered.load(Ordering::SeqCst)
    }

    /// Resolves once shutdown is requested.
    pub async fn wait(&self) {
        loop {
            let notified = self.inner.notify.notified();
            if self.is_triggered() {
                return;
            }
            notified.await;
        }
    }

    /// Triggers this token on SIGINT or SIGTERM. Must be called inside a tokio runtime.
    pub fn trigger_on_signals(&self) -> std::io::Result<()> {
        use tokio::signal::unix::{SignalKind, signal};
        let mut int = signal(SignalKind::interrupt())?;
        let mut term = signal(SignalKind::terminate())?;
        let me = self.clone();
        tokio::spawn(async move {
            let name = tokio::select! {
                _ = int.recv() => "SIGINT",
                _ = term.recv() => "SIGTERM",
            };
            tracing::info!("{name} received, shutting down");
            me.trigger();
        });
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn waiters_wake_on_trigger_and_late_waiters_return_at_once() {
        let s = Shutdown::new();
        let w = tokio::spawn({
            let s = s.clone();
            async move { s.wait().await }
        });
        tokio::task::yield_now().await;
        assert!(!w.is_finished());
        s.trigger();
        w.await.unwrap();
        s.wait().await; // already triggered
        assert!(s.is_triggered());
    }
}

/// Runs the calling thread at SCHED_FIFO `priority` (1..=99): a control loop or the simulated
/// hardware keeps its pace on a busy machine. Threads it starts afterwards inherit the policy.
/// Needs root or CAP_SYS_NICE; the error says so.
pub fn realtime_priority(priority: u8) -> Result<(), PriorityError> {
    use thread_priority::{
        RealtimeThreadSchedulePolicy, ThreadPriority, ThreadSchedulePolicy, set_thread_priority_and_policy,
        thread_native_id,
    };
    let value = priority.try_into().map_err(|e| PriorityError::Value { priority, reason: format!("{e:?}") })?;
    let fifo = ThreadSchedulePolicy::Realtime(RealtimeThreadSchedulePolicy::Fifo);
    set_thread_priority_and_policy(thread_native_id(), ThreadPriority::Crossplatform(value), fifo)
        .map_err(|e| PriorityError::Denied { priority, reason: format!("{e:?}") })
}

/// SCHED_FIFO could not be had.
#[derive(Debug, thiserror::Error)]
pub enum PriorityError {
    #[error("SCHED_FIFO priority {priority}: {reason}")]
    Value { priority: u8, reason: String },
    #[error("cannot run at SCHED_FIFO {priority}: {reason} (needs root or CAP_SYS_NICE)")]
    Denied { priority: u8, reason: String },
}
