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

/// A node binary's `main` in one call: logging at `info` (RUST_LOG overrides), a two-worker
/// tokio runtime, SIGINT/SIGTERM -> the [`Shutdown`] token handed to `body`, and the exit code:
/// success, or the error printed as `<name>: <error chain>` and failure.
pub fn main_node<F, Fut>(name: &str, body: F) -> std::process::ExitCode
where
    F: FnOnce(Shutdown) -> Fut,
    Fut: std::future::Future<Output = anyhow::Result<()>>,
{
    crate::logging::init("info");
    let rt = match tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build() {
        Ok(rt) => rt,
        Err(e) => {
            eprintln!("{name}: cannot start the runtime: {e}");
            return std::process::ExitCode::FAILURE;
        }
    };
    let result = rt.block_on(async {
        let shutdown = Shutdown::new();
        shutdown.trigger_on_signals()?;
        body(shutdown).await
    });
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("{name}: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

/// What a node's `run` gets besides its config.
#[derive(Debug, Clone)]
pub struct NodeContext {
    /// The node's name (also its ROS node name).
    pub name: String,
    /// Triggered by SIGINT/SIGTERM; `run` must return soon after.
    pub shutdown: Shutdown,
}

/// Why a node stopped with an error.
#[derive(Debug, thiserror::Error)]
pub enum NodeError {
    #[error(transparent)]
    Config(#[from] crate::config::ConfigError),
    #[error("node {node}: cannot start: {source}")]
    Start {
        node: String,
        #[source]
        source: std::io::Error,
    },
    #[error("node {node}: {source}")]
    Run {
        node: String,
        #[source]
        source: Box<dyn std::error::Error + Send + Sync>,
    },
}

/// The one shape of every labrig node: typed config (unknown keys rejected) -> `run(config,
/// ctx)` on a tokio runtime -> clean return on SIGINT/SIGTERM. A node's `main` parses its
/// command line and calls this; `run` stays an ordinary, testable async function.
pub fn run_node<C, F, Fut, E>(name: &str, config_path: &std::path::Path, run: F) -> Result<(), NodeError>
where
    C: serde::de::DeserializeOwned,
    F: FnOnce(C, NodeContext) -> Fut,
    Fut: std::future::Future<Output = Result<(), E>>,
    E: Into<Box<dyn std::error::Error + Send + Sync>>,
{
    let config: C = crate::config::load_config(config_path)?;
    let start = |source| NodeError::Start { node: name.to_owned(), source };
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().map_err(start)?;
    rt.block_on(async {
        let shutdown = Shutdown::new();
        shutdown.trigger_on_signals().map_err(start)?;
        tracing::info!(node = name, config = %config_path.display(), "starting");
        let ctx = NodeContext { name: name.to_owned(), shutdown };
        let result = run(config, ctx).await;
        tracing::info!(node = name, "stopped");
        result.map_err(|e| NodeError::Run { node: name.to_owned(), source: e.into() })
    })
}

#[cfg(test)]
mod node_tests {
    use super::*;

    #[derive(Debug, serde::Deserialize)]
    #[serde(deny_unknown_fields)]
    struct Cfg {
        ticks: u32,
    }

    #[test]
    fn a_node_gets_its_typed_config_and_stops_on_shutdown() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("node.toml");
        std::fs::write(&path, "ticks = 3\n").unwrap();
        let mut seen = 0;
        run_node("test_node", &path, |cfg: Cfg, ctx| {
            let seen = &mut seen;
            async move {
                for _ in 0..cfg.ticks {
                    *seen += 1;
                }
                ctx.shutdown.trigger();
                ctx.shutdown.wait().await;
                Ok::<(), std::io::Error>(())
            }
        })
        .unwrap();
        assert_eq!(seen, 3);
    }

    #[test]
    fn a_node_with_an_unknown_config_key_does_not_start() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("node.toml");
        std::fs::write(&path, "ticks = 3\ntikcs = 4\n").unwrap();
        let err = run_node("test_node", &path, |_: Cfg, _| async { Ok::<(), std::io::Error>(()) }).unwrap_err();
        assert!(err.to_string().contains("unknown field `tikcs`"), "{err}");
    }
}

/// Runs the calling thread at SCHED_FIFO `priority` (1..=99): a control loop or the simulated
/// hardware keeps its pace on a busy machine. Threads it starts afterwards inherit the policy.
/// Needs root or CAP_SYS_NICE; the error says so.
pub fn realtime_priority(priority: u8) -> Result<(), String> {
    use thread_priority::{
        RealtimeThreadSchedulePolicy, ThreadPriority, ThreadSchedulePolicy, set_thread_priority_and_policy,
        thread_native_id,
    };
    let value = priority.try_into().map_err(|e| format!("SCHED_FIFO priority {priority}: {e:?}"))?;
    let fifo = ThreadSchedulePolicy::Realtime(RealtimeThreadSchedulePolicy::Fifo);
    set_thread_priority_and_policy(thread_native_id(), ThreadPriority::Crossplatform(value), fifo)
        .map_err(|e| format!("cannot run at SCHED_FIFO {priority}: {e:?} (needs root or CAP_SYS_NICE)"))
}
