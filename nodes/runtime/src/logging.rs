//! tracing setup. Level policy: losing data is ERROR, degraded operation WARN, lifecycle INFO,
//! per-message DEBUG, per-tick TRACE. RustDDS is noisy at INFO, so it starts at ERROR.

use tracing_subscriber::EnvFilter;

/// Installs a stderr subscriber. `RUST_LOG` overrides `default_filter` (standard tracing
/// practice, not a config channel). Calling it twice is harmless.
pub fn init(default_filter: &str) {
    let filter = EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| EnvFilter::new(format!("{default_filter},rustdds=error,ros2_client=warn")));
    let _ = tracing_subscriber::fmt().with_env_filter(filter).with_writer(std::io::stderr).try_init();
}
