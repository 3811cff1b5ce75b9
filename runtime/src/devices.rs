//! The real rig's devices, written once in the launch config (`[rig.devices]`) and handed by the
//! launcher to every node it starts (the `LABRIG_RIG_DEVICES` environment variable, JSON), so a
//! camera's serial lives in one place: the camera node opens `source = "zed"` by it, the recorder
//! writes it into every episode's metadata, `labrig doctor` checks it.

use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// The environment variable the launcher hands the rig's devices in.
pub const DEVICES_ENV: &str = "LABRIG_RIG_DEVICES";

/// The real rig's devices (`[rig.devices]` of a launch config).
#[derive(Debug, Clone, Deserialize, Serialize, Default, PartialEq, Eq)]
#[serde(deny_unknown_fields)]
pub struct Devices {
    pub robot_ip: Option<String>,
    pub gripper_port: Option<String>,
    pub quest_device: Option<String>,
    /// Camera id -> its USB serial (`labrig cameras list` prints them).
    #[serde(default)]
    pub camera_serials: BTreeMap<String, String>,
}

/// The launcher's hand-off could not be read.
#[derive(Debug, thiserror::Error)]
#[error("{DEVICES_ENV} (the rig's devices from the launcher) is not valid: {0}")]
pub struct DevicesError(#[from] serde_json::Error);

impl Devices {
    /// The devices the launcher handed this process; `None` when it was not started by a
    /// launcher (or the launch config names no devices).
    pub fn from_launcher() -> Result<Option<Devices>, DevicesError> {
        match std::env::var(DEVICES_ENV) {
            Ok(text) if !text.is_empty() => Ok(Some(serde_json::from_str(&text)?)),
            _ => Ok(None),
        }
    }

    /// The value of [`DEVICES_ENV`] for these devices.
    pub fn to_env(&self) -> String {
        serde_json::to_string(self).expect("plain strings serialise")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_hand_off_reads_back_what_was_handed() {
        let d = Devices {
            robot_ip: Some("127.0.0.1".into()),
            camera_serials: [("ext1".to_owned(), "ZED2-1".to_owned())].into(),
            ..Devices::default()
        };
        assert_eq!(serde_json::from_str::<Devices>(&d.to_env()).unwrap(), d);
        assert!(serde_json::from_str::<Devices>("{\"camera_serial\": {}}").is_err(), "unknown keys are refused");
    }
}
