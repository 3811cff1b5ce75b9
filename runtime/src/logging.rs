//! tracing setup. Level policy: losing data is ERROR, degraded operation WARN, lifecycle INFO,
//! per-message DEBUG, per-tick TRACE. RustDDS logs ERRORs for normal events (a participant
//! shutting down, a multicast group it never joined), so it is off unless RUST_LOG asks for it
//! (e.g. `RUST_LOG=rustdds=warn`); ros2-client starts at ERROR.

use tracing_subscriber::EnvFilter;

/// Installs a stderr subscriber. `RUST_LOG` overrides `default_filter` (standard tracing
/// practice, not a config channel). Calling it twice is harmless.
pub fn init(default_filter: &str) {
    let filter = EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| EnvFilter::new(format!("{default_filter},rustdds=off,ros2_client=error,mujoco=warn")));
    let _ = tracing_subscriber::fmt().with_env_filter(filter).with_writer(std::io::stderr).try_init();
}
