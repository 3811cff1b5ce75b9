//! labrig-station (program `labrig-station`, `labrig station`): the operator station, a web
//! page for collecting demos on the rig's machine or a tablet beside it.
//!
//! - [`live`]: the rig as the page sees it: robot state, the loop's and the recorder's status,
//!   the teleop deadman, calibration ages, the last episode event; and the ROS side that
//!   publishes the operator's requests (`/rig/request`, the same events as `labrig episode`
//!   and the Quest's A/B) and session (`/rig/session`, latched).
//! - [`thumbs`]: camera thumbnails from the iceoryx2 frames, on a thread of their own at a few
//!   frames per second (a subscriber more: a camera never waits for it).
//! - [`episodes`]: the episodes under the recorder's root with their `labrig inspect`
//!   verdicts, relabel and trash (labrig_episode::judge), contact sheets.
//! - [`web`]: the HTTP server (axum): the page, its JSON API, the token and origin checks.
//! - [`foxglove`]: the live rig for Foxglove (the Foxglove WebSocket protocol at `/foxglove`).
//!
//! If the station dies the rig goes on: nothing in the loop or the recorder waits for it.

pub mod episodes;
pub mod foxglove;
pub mod live;
pub mod thumbs;
pub mod web;

use labrig_msgs::Invalid;
use labrig_msgs::rig::RIG_CAMERAS;
use labrig_runtime::{RosConfig, Shutdown};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// The station's config (`labrig-station run --config F`, `--set key=value`, flags).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct StationConfig {
    pub ros: RosConfig,
    /// Where the page is served. Loopback by default; any other address needs a token.
    pub listen: String,
    /// The token state-changing requests carry (header `x-labrig-token`); beyond loopback
    /// every API request needs it and the page asks for it. Default: $LABRIG_STATION_TOKEN,
    /// else (loopback only) a random one the page is given.
    pub token: Option<String>,
    /// The recorder's episodes root (episodes, relabel, trash).
    pub root: PathBuf,
    /// Where the session is kept across restarts (default `<root>/session.json`).
    pub session_file: Option<PathBuf>,
    /// The cameras shown.
    pub cameras: Vec<String>,
    pub frames_namespace: Option<String>,
    /// Thumbnails per second per camera.
    pub thumbnail_hz: f64,
    /// Thumbnail width (px); the enlarged view is twice that.
    pub thumbnail_width: u32,
    /// A calibration older than this is shown as a warning (s; DROID's GUI warns after an hour).
    pub calibration_max_age_s: f64,
}

impl Default for StationConfig {
    fn default() -> Self {
        StationConfig {
            ros: RosConfig::default(),
            listen: "127.0.0.1:8080".into(),
            token: None,
            root: PathBuf::from("episodes"),
            session_file: None,
            cameras: RIG_CAMERAS.iter().map(|c| c.to_string()).collect(),
            frames_namespace: labrig_runtime::frames::default_namespace(),
            thumbnail_hz: 4.0,
            thumbnail_width: 320,
            calibration_max_age_s: labrig_episode::calibration::DEFAULT_MAX_AGE_S,
        }
    }
}

/// The environment variable a token may come from.
pub const TOKEN_ENV: &str = "LABRIG_STATION_TOKEN";

impl StationConfig {
    pub fn validate(&self) -> Result<(), Invalid> {
        let addr: std::net::SocketAddr = self
            .listen
            .parse()
            .map_err(|e| Invalid::new("listen", format!("listen = {:?} is not an address:port ({e})", self.listen)))?;
        if !addr.ip().is_loopback() && self.token.as_deref().is_none_or(str::is_empty) {
            return Err(Invalid::new(
                "token",
                format!(
                    "listening on {addr} (beyond loopback) needs a token: --token, token = \"...\" or ${TOKEN_ENV}"
                ),
            ));
        }
        if let Some(t) = &self.token
            && (t.len() < 8 || !t.bytes().all(|b| b.is_ascii_graphic()))
        {
            return Err(Invalid::new("token", "token must be at least 8 printable characters without spaces"));
        }
        if !(self.thumbnail_hz.is_finite() && (0.2..=30.0).contains(&self.thumbnail_hz)) {
            return Err(Invalid::new(
                "thumbnail_hz",
                format!("thumbnail_hz = {} must be in 0.2..=30", self.thumbnail_hz),
            ));
        }
        if !(self.calibration_max_age_s.is_finite() && self.calibration_max_age_s > 0.0) {
            return Err(Invalid::new(
                "calibration_max_age_s",
                format!("calibration_max_age_s = {} must be a positive number of seconds", self.calibration_max_age_s),
            ));
        }
        if !(32..=1280).contains(&self.thumbnail_width) {
            return Err(Invalid::new(
                "thumbnail_width",
                format!("thumbnail_width = {} must be in 32..=1280", self.thumbnail_width),
            ));
        }
        if let Some(c) =
            self.cameras.iter().find(|c| c.is_empty() || !c.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_'))
        {
            return Err(Invalid::new("cameras", format!("cameras: camera id {c:?}: letters, digits and '_' only")));
        }
        Ok(())
    }

    pub fn session_path(&self) -> PathBuf {
        self.session_file.clone().unwrap_or_else(|| self.root.join("session.json"))
    }
}

/// The station: `labrig-station run` (`labrig_runtime::node_main`).
#[derive(Debug)]
pub struct StationNode;

/// `labrig-station run`'s own flags.
#[derive(Debug, clap::Args, Serialize)]
pub struct StationFlags {
    /// Serve on this address:port (loopback by default; another address needs a token).
    #[arg(long)]
    #[serde(skip_serializing_if = "Option::is_none")]
    listen: Option<String>,
    /// The token (default: $LABRIG_STATION_TOKEN).
    #[arg(long)]
    #[serde(skip_serializing_if = "Option::is_none")]
    token: Option<String>,
    /// The recorder's episodes root.
    #[arg(long)]
    #[serde(skip_serializing_if = "Option::is_none")]
    root: Option<PathBuf>,
}

/// What a run reports when it stops.
#[derive(Debug, Default, Serialize)]
pub struct StationStats {
    pub requests: u64,
    pub events_sent: u64,
}

impl labrig_runtime::Node for StationNode {
    const NAME: &'static str = "labrig-station";
    const ABOUT: &'static str = "the operator station: a web page for collecting demos (http://127.0.0.1:8080)";
    type Config = StationConfig;
    type Flags = StationFlags;
    type Stats = StationStats;

    fn ros(config: &mut StationConfig) -> &mut RosConfig {
        &mut config.ros
    }

    fn apply(_: &StationFlags, cfg: &mut StationConfig, _: Option<&Path>) {
        if cfg.token.is_none()
            && let Ok(t) = std::env::var(TOKEN_ENV)
            && !t.is_empty()
        {
            cfg.token = Some(t);
        }
    }

    fn validate(config: &StationConfig) -> Result<(), Invalid> {
        config.validate()
    }

    async fn run(config: StationConfig, shutdown: Shutdown) -> anyhow::Result<StationStats> {
        web::run(config, shutdown).await
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn beyond_loopback_a_token_is_required_by_name() {
        let mut c = StationConfig { listen: "0.0.0.0:8080".into(), ..StationConfig::default() };
        let e = c.validate().unwrap_err().to_string();
        assert!(e.contains("beyond loopback) needs a token"), "{e}");
        c.token = Some("short".into());
        assert!(c.validate().unwrap_err().to_string().contains("at least 8"));
        c.token = Some("s3cret-token".into());
        assert!(c.validate().is_ok());
        let e = StationConfig { listen: "localhost".into(), ..StationConfig::default() }.validate().unwrap_err();
        assert!(e.to_string().contains("is not an address:port"), "{e}");
    }
}
