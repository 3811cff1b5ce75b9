//! Typed node configuration from TOML.
//!
//! Every config struct derives `Deserialize` with `#[serde(deny_unknown_fields)]`: a misspelt
//! key is an error naming the key and the file, never silently ignored. Raw structs are then
//! validated into the types a node uses.

use serde::Deserialize;
use serde::de::DeserializeOwned;
use std::path::{Path, PathBuf};

#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("cannot read config {path}: {source}")]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// The TOML did not match the config type; toml's message names the key (for an unknown
    /// key: ``unknown field `x`, expected one of ...``) and the line.
    #[error("invalid config {path}: {message}")]
    Parse { path: PathBuf, message: String },
    #[error("invalid config {path}: `{key}` {reason}")]
    Invalid { path: PathBuf, key: String, reason: String },
    /// A value breaks a rule of the node's (its message names the key).
    #[error("invalid config {path}: {rule}")]
    Rule { path: PathBuf, rule: labrig_msgs::Invalid },
}

/// Reads and parses a TOML config file into `T`.
pub fn load_config<T: DeserializeOwned>(path: &Path) -> Result<T, ConfigError> {
    let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read { path: path.to_owned(), source })?;
    parse_config(&text, path)
}

/// Parses TOML text into `T`; `origin` names the source in errors.
pub fn parse_config<T: DeserializeOwned>(text: &str, origin: &Path) -> Result<T, ConfigError> {
    toml::from_str(text)
        .map_err(|e| ConfigError::Parse { path: origin.to_owned(), message: e.to_string().trim_end().to_owned() })
}

/// How a node joins ROS 2.
#[derive(Debug, Clone, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RosConfig {
    /// DDS domain id (0..=232, as ROS 2 allows). ros2-client ignores ROS_DOMAIN_ID, so it is
    /// set here.
    #[serde(default)]
    pub domain_id: u16,
    /// Keep all DDS traffic on 127.0.0.1 (the default). Set false only on a real rig whose
    /// nodes run on several machines.
    #[serde(default = "default_true")]
    pub loopback_only: bool,
    /// Node namespace, e.g. "/" or "/rig1".
    #[serde(default = "default_namespace")]
    pub namespace: String,
}

fn default_true() -> bool {
    true
}

fn default_namespace() -> String {
    "/".to_owned()
}

impl Default for RosConfig {
    fn default() -> Self {
        RosConfig { domain_id: 0, loopback_only: true, namespace: default_namespace() }
    }
}

impl RosConfig {
    /// Largest domain id ROS 2 accepts (port arithmetic overflows beyond it).
    pub const MAX_DOMAIN_ID: u16 = 232;

    /// Checks the values serde cannot: the domain id range and the namespace form.
    pub fn validate(&self, origin: &Path) -> Result<(), ConfigError> {
        let invalid =
            |key: &str, reason: String| ConfigError::Invalid { path: origin.to_owned(), key: key.to_owned(), reason };
        if self.domain_id > Self::MAX_DOMAIN_ID {
            return Err(invalid(
                "ros.domain_id",
                format!("is {}, must be 0..={}", self.domain_id, Self::MAX_DOMAIN_ID),
            ));
        }
        if !self.namespace.starts_with('/') {
            return Err(invalid("ros.namespace", format!("is {:?}, must start with '/'", self.namespace)));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, Deserialize)]
    #[serde(deny_unknown_fields)]
    struct NodeCfg {
        #[allow(dead_code)]
        rate_hz: f64,
        #[serde(default)]
        ros: RosConfig,
    }

    #[test]
    fn unknown_key_is_rejected_with_the_key_named() {
        let err = parse_config::<NodeCfg>("rate_hz = 20.0\nrate_hx = 3\n", Path::new("node.toml")).unwrap_err();
        let text = err.to_string();
        assert!(text.contains("node.toml") && text.contains("unknown field `rate_hx`"), "{text}");
    }

    #[test]
    fn unknown_nested_key_is_rejected_with_the_key_named() {
        let err = parse_config::<NodeCfg>("rate_hz = 20.0\n[ros]\ndomian_id = 3\n", Path::new("n.toml")).unwrap_err();
        assert!(err.to_string().contains("unknown field `domian_id`"), "{err}");
    }

    #[test]
    fn ros_defaults_are_loopback_domain_zero() {
        let cfg = parse_config::<NodeCfg>("rate_hz = 20.0\n", Path::new("n.toml")).unwrap();
        assert_eq!(cfg.ros, RosConfig::default());
        assert!(cfg.ros.loopback_only);
    }

    #[test]
    fn out_of_range_domain_is_rejected() {
        let cfg = parse_config::<NodeCfg>("rate_hz = 1.0\n[ros]\ndomain_id = 300\n", Path::new("n.toml")).unwrap();
        let err = cfg.ros.validate(Path::new("n.toml")).unwrap_err();
        assert_eq!(err.to_string(), "invalid config n.toml: `ros.domain_id` is 300, must be 0..=232");
    }
}
