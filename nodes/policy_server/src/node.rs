//! The node: `/policy/request` in, `/policy/chunk` out, inference on its own thread.

use crate::serve::Server;
use labrig_msgs::Invalid;
use labrig_msgs::rig::{ActionChunk, PolicyRequest, RIG_CAMERAS};
use labrig_msgs::topics;
use labrig_runtime::ros::Ros;
use labrig_runtime::{RosConfig, Shutdown};
use serde::{Deserialize, Serialize};
use std::path::PathBuf;
use std::sync::{Arc, Condvar, Mutex};
use std::time::Duration;

/// The node's config (TOML; every key optional, unknown keys refused).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PolicyServerConfig {
    pub ros: RosConfig,
    /// The checkpoint: a run directory (`labrig train --out`'s; its last checkpoint), a run's
    /// `checkpoints/last` or `checkpoints/step_<n>`, or an imported checkpoint directory.
    pub checkpoint: Option<PathBuf>,
    /// Or a TorchScript module saved by PyTorch, with its `spec` ([`crate::torchscript`]).
    pub torchscript: Option<PathBuf>,
    pub spec: Option<PathBuf>,
    /// Inference threads; 0 = every core.
    pub threads: i32,
    /// The rig's cameras: a checkpoint observing another is refused at start.
    pub rig_cameras: Vec<String>,
    /// Also answer openpi clients on this address (`host:port`; a bare port binds 127.0.0.1):
    /// DROID's observation keys in, the checkpoint's chunk out (see [`crate::openpi`]).
    pub openpi: Option<String>,
    /// openpi: the checkpoint's control period (s), the spacing of its chunk's rows.
    pub period_s: f64,
    /// openpi: the FR3 URDF whose kinematics give the pose from the joints (default: setup's).
    pub urdf: Option<PathBuf>,
    /// Real-time chunking's guidance toward the rows a request carries: `"x0"` (in the clean
    /// estimate's space) or `"vjp"` (PiGDM's, through the U-Net's Jacobian); see
    /// labrig_policies::rtc.
    pub rtc_guidance: labrig_policies::rtc::Method,
    /// DDIM steps per chunk instead of the checkpoint's (fewer: faster, see
    /// experiments/latency/README.md for what it costs); none keeps the checkpoint's.
    pub inference_steps: Option<usize>,
}

impl Default for PolicyServerConfig {
    fn default() -> PolicyServerConfig {
        PolicyServerConfig {
            ros: RosConfig::default(),
            checkpoint: None,
            torchscript: None,
            spec: None,
            threads: 0,
            rig_cameras: RIG_CAMERAS.iter().map(|c| c.to_string()).collect(),
            openpi: None,
            period_s: 0.05,
            urdf: None,
            rtc_guidance: labrig_policies::rtc::Method::default(),
            inference_steps: None,
        }
    }
}

impl PolicyServerConfig {
    pub fn validate(&self) -> Result<(), Invalid> {
        match (&self.checkpoint, &self.torchscript, &self.spec) {
            (Some(_), None, None) | (None, Some(_), Some(_)) => {}
            (None, None, _) => {
                return Err(Invalid::new(
                    "checkpoint",
                    "policy server config: no `checkpoint` (--checkpoint <dir>) nor `torchscript` (--torchscript model.pt --spec spec.toml)",
                ));
            }
            (Some(_), Some(_), _) => {
                return Err(Invalid::new(
                    "torchscript",
                    "policy server config: `checkpoint` or `torchscript`, not both",
                ));
            }
            (_, Some(_), None) | (Some(_), None, Some(_)) => {
                return Err(Invalid::new("spec", "policy server config: `torchscript` and `spec` go together"));
            }
        }
        if self.threads < 0 {
            return Err(Invalid::new(
                "threads",
                format!("policy server config: `threads` must be >= 0, got {}", self.threads),
            ));
        }
        if !(self.period_s.is_finite() && (0.001..=1.0).contains(&self.period_s)) {
            return Err(Invalid::new(
                "period_s",
                format!("policy server config: period_s = {} must be in 0.001..=1", self.period_s),
            ));
        }
        if let Some(a) = &self.openpi {
            openpi_addr(a).map_err(|e| Invalid::new("openpi", e.to_string()))?;
        }
        if self.inference_steps == Some(0) {
            return Err(Invalid::new("inference_steps", "policy server config: `inference_steps` must be >= 1, got 0"));
        }
        Ok(())
    }
}

/// Why `--openpi`'s address is not one to listen on.
#[derive(Debug, thiserror::Error)]
pub enum OpenpiAddrError {
    #[error("policy server config: openpi = {addr:?} is not host:port ({source})")]
    NotHostPort {
        addr: String,
        #[source]
        source: std::io::Error,
    },
    #[error("policy server config: openpi = {addr:?} names no address")]
    NoAddress { addr: String },
}

/// `--openpi`'s address: `host:port`, or a bare port on 127.0.0.1.
pub fn openpi_addr(a: &str) -> Result<String, OpenpiAddrError> {
    let full = if a.parse::<u16>().is_ok() { format!("127.0.0.1:{a}") } else { a.to_owned() };
    use std::net::ToSocketAddrs;
    full.to_socket_addrs()
        .map_err(|source| OpenpiAddrError::NotHostPort { addr: a.to_owned(), source })?
        .next()
        .ok_or_else(|| OpenpiAddrError::NoAddress { addr: a.to_owned() })?;
    Ok(full)
}

/// What a run served.
#[derive(Debug, Clone, Default, Serialize)]
pub struct ServeStats {
    pub policy_id: String,
    pub requests: u64,
    pub chunks: u64,
    /// Requests replaced by a newer one before inference took them.
    pub superseded: u64,
    /// Requests that could not be answered (each named in the log and on `/policy/refused`).
    pub failed: u64,
    pub inference_ms_p50: f64,
    pub inference_ms_p99: f64,
    /// openpi: connections, requests, and requests answered with an error frame.
    pub openpi_connections: u64,
    pub openpi_requests: u64,
    pub openpi_errors: u64,
}

/// The request waiting for the inference thread (the newest only) and whether to stop.
#[derive(Debug, Default)]
struct Waiting {
    request: Option<PolicyRequest>,
    stop: bool,
}

/// `labrig-policy check <run's flags>`: the checkpoint loaded as `run` loads it (the same
/// flags and config), checked against the rig's cameras, one chunk computed; nothing served
/// (`labrig doctor` asks this). Returns the line it prints.
pub fn check(args: &[String]) -> anyhow::Result<String> {
    let mut argv = vec!["run".to_owned()];
    argv.extend(args.iter().cloned());
    let cfg = labrig_runtime::node::run_config::<crate::PolicyServerNode>(&argv, None)?;
    let (server, from) = match (&cfg.checkpoint, &cfg.torchscript, &cfg.spec) {
        (Some(dir), _, _) => (Server::load(dir)?, dir.clone()),
        (None, Some(module), Some(spec)) => (Server::load_torchscript(module, spec)?, module.clone()),
        _ => unreachable!("validated"),
    };
    server.check_rig(&cfg.rig_cameras)?;
    let server = match cfg.inference_steps {
        Some(n) => server.with_inference_steps(n)?,
        None => server,
    };
    let ms = server.warm_up()?;
    Ok(format!(
        "{} ({}): loads, observes {:?}, one chunk in {ms:.0} ms",
        server.id(),
        from.display(),
        server.config().cameras
    ))
}

pub async fn run(cfg: PolicyServerConfig, shutdown: Shutdown) -> anyhow::Result<ServeStats> {
    let threads = if cfg.threads > 0 {
        cfg.threads
    } else {
        std::thread::available_parallelism().map(|n| n.get() as i32).unwrap_or(1)
    };
    let (server, dir) = match (&cfg.checkpoint, &cfg.torchscript, &cfg.spec) {
        (Some(dir), _, _) => (Server::load(dir)?, dir.clone()),
        (None, Some(module), Some(spec)) => (Server::load_torchscript(module, spec)?, module.clone()),
        _ => unreachable!("validated"),
    };
    server.check_rig(&cfg.rig_cameras)?;
    let mut server = server.with_rtc_method(cfg.rtc_guidance);
    if let Some(n) = cfg.inference_steps {
        server = server.with_inference_steps(n)?;
        tracing::info!("sampling with {n} DDIM steps (inference_steps), not the checkpoint's own");
    }
    let mut stats = ServeStats { policy_id: server.id().to_owned(), ..ServeStats::default() };
    let (id, cameras, info_json) = (server.id().to_owned(), server.config().cameras.clone(), server.info().to_string());
    // One model for both faces; openpi's requests and the loop's take turns.
    let server = Arc::new(Mutex::new(server));
    let openpi = match &cfg.openpi {
        Some(addr) => {
            let addr = openpi_addr(addr)?;
            let kin = labrig_arm::kinematics::Fr3Kinematics::from_urdf_file(
                &labrig_arm::urdf_path(cfg.urdf.as_deref()),
                labrig_arm::kinematics::TcpOffset::ROBOTIQ_2F85,
            )?;
            let policy = crate::openpi::OpenpiPolicy::new(Arc::clone(&server), kin, cfg.period_s)?;
            let metadata = policy.metadata();
            let s = labrig_openpi::Server::bind(&addr, metadata, Arc::new(policy))
                .map_err(|e| anyhow::anyhow!("openpi: cannot listen on {addr}: {e}"))?;
            tracing::info!(policy = %id, addr = %s.local_addr(), "answering openpi clients (ws://{})", s.local_addr());
            Some(s)
        }
        None => None,
    };
    let mut ros = Ros::new(&cfg.ros, "labrig_policy")?;
    let requests = ros.subscription_on(&topics::POLICY_REQUEST, 10)?;
    let chunks = ros.publisher_on(&topics::POLICY_CHUNK, 10)?;
    let info = ros.publisher_on(&topics::POLICY_INFO, 1)?;
    let refused = ros.publisher_on(&topics::POLICY_REFUSED, 10)?;
    // The inference thread warms up (one chunk on a blank observation) before /policy/info
    // goes out: libtorch's first call on a thread sets up its pool and buffers, which took over
    // a second on a busy machine, past the loop's default 1 s server timeout.
    let (warm_tx, warm_rx) = std::sync::mpsc::channel::<Result<f64, crate::serve::ServeError>>();

    let waiting = Arc::new((Mutex::new(Waiting::default()), Condvar::new()));
    let (done_tx, mut done_rx) = tokio::sync::mpsc::unbounded_channel::<Result<ActionChunk, (u64, String)>>();
    let worker = {
        let waiting = Arc::clone(&waiting);
        std::thread::Builder::new().name("inference".into()).spawn(move || {
            tch::set_num_threads(threads);
            let lock = || server.lock().unwrap_or_else(|p| p.into_inner());
            let _ = warm_tx.send(lock().warm_up());
            loop {
                let req = {
                    let (lock, cv) = &*waiting;
                    let mut w = lock.lock().unwrap_or_else(|p| p.into_inner());
                    while w.request.is_none() && !w.stop {
                        w = cv.wait(w).unwrap_or_else(|p| p.into_inner());
                    }
                    if w.stop {
                        return;
                    }
                    w.request.take().expect("checked")
                };
                let answer = lock().chunk(&req).map_err(|e| (req.request_id, e.to_string()));
                if done_tx.send(answer).is_err() {
                    return;
                }
            }
        })?
    };
    let warm_up_ms = match warm_rx.recv() {
        Ok(Ok(ms)) => ms,
        Ok(Err(e)) => anyhow::bail!("{id}: the warm-up chunk failed: {e}"),
        Err(_) => anyhow::bail!("{id}: the inference thread ended before its warm-up"),
    };
    tracing::info!(policy = %id, ?cameras, threads, warm_up_ms, "serving {} on /policy/chunk", dir.display());
    info.publish(labrig_msgs::std_msgs::StringMsg { data: info_json })?;

    let mut latencies: Vec<f64> = Vec::new();
    while !shutdown.is_triggered() {
        while let Some(r) = requests.try_take()? {
            stats.requests += 1;
            let (lock, cv) = &*waiting;
            let mut w = lock.lock().unwrap_or_else(|p| p.into_inner());
            if w.request.replace(r.msg).is_some() {
                stats.superseded += 1;
            }
            cv.notify_one();
        }
        while let Ok(answer) = done_rx.try_recv() {
            match answer {
                Ok(chunk) => {
                    latencies.push(chunk.inference_ms);
                    chunks.publish(chunk)?;
                    stats.chunks += 1;
                }
                Err((request_id, error)) => {
                    stats.failed += 1;
                    tracing::warn!(request_id, "request refused: {error}");
                    let data = serde_json::json!({ "request_id": request_id, "policy_id": id, "error": error });
                    refused.publish(labrig_msgs::std_msgs::StringMsg { data: data.to_string() })?;
                }
            }
        }
        tokio::time::sleep(Duration::from_millis(1)).await;
    }
    {
        let (lock, cv) = &*waiting;
        lock.lock().unwrap_or_else(|p| p.into_inner()).stop = true;
        cv.notify_one();
    }
    let _ = worker.join();
    if let Some(s) = openpi {
        use std::sync::atomic::Ordering::Relaxed;
        let c = s.counters();
        (stats.openpi_connections, stats.openpi_requests, stats.openpi_errors) =
            (c.connections.load(Relaxed), c.requests.load(Relaxed), c.errors.load(Relaxed));
    }
    if let Some(p) = labrig_episode::inspect::Percentiles::of(latencies) {
        (stats.inference_ms_p50, stats.inference_ms_p99) = (p.p50, p.p99);
    }
    Ok(stats)
}
