//! DROID's episode metadata and directory layout.
//!
//! DROID names an episode `<lab>+<user>+<YYYY-MM-DD-HHh-MMm-SSs>` and files it under
//! `{success|failure}/<YYYY-MM-DD>/<asctime>/` (e.g. `success/2023-07-07/Fri_Jul__7_09:42:23_2023/`).
//! The same keys go into each MCAP as a `droid_episode` metadata record (string map), so the
//! file carries its own description.

use chrono::{DateTime, Datelike, Utc};
use labrig_msgs::Nanos;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// How an episode ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Outcome {
    Success,
    Failure,
}

impl Outcome {
    pub fn dir(self) -> &'static str {
        match self {
            Outcome::Success => "success",
            Outcome::Failure => "failure",
        }
    }
}

/// Who and where: the parts of DROID's metadata a rig config sets once.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RigIdentity {
    pub lab: String,
    pub building: String,
    pub user: String,
    pub robot_serial: String,
    /// Camera id (ext1, ext2, wrist, rs1, rs2) -> the camera's serial (on a launched rig, the
    /// launch config's `rig.devices.camera_serials` fill the cameras not named here).
    #[serde(default)]
    pub camera_serials: BTreeMap<String, String>,
}

impl RigIdentity {
    /// The rig's camera serials (the launch config's `rig.devices.camera_serials`) for the
    /// cameras this identity does not name; a serial named here is kept.
    pub fn fill_camera_serials(&mut self, rig: &BTreeMap<String, String>) {
        for (camera, serial) in rig {
            self.camera_serials.entry(camera.clone()).or_insert_with(|| serial.clone());
        }
    }
}

impl Default for RigIdentity {
    fn default() -> Self {
        RigIdentity {
            lab: "LABRIG".into(),
            building: "sim".into(),
            user: "operator".into(),
            robot_serial: "sim-fr3".into(),
            camera_serials: BTreeMap::new(),
        }
    }
}

/// One episode's DROID metadata (`Default`: every field empty, for importers that fill some).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct EpisodeMetadata {
    pub uuid: String,
    pub lab: String,
    pub building: String,
    pub user: String,
    pub scene_id: String,
    pub task_instruction: String,
    /// Set when the episode ends.
    pub success: Option<bool>,
    pub robot_serial: String,
    pub camera_serials: BTreeMap<String, String>,
    /// Camera id -> extrinsics in the robot base frame as DROID stores them:
    /// [x, y, z, rx, ry, rz] (m, extrinsic XYZ euler rad).
    pub extrinsics: BTreeMap<String, [f64; 6]>,
    /// Start of recording, ns since the Unix epoch.
    pub start_ns: i64,
    /// Steps recorded (DROID's trajectory_length); set when the episode ends.
    pub trajectory_length: u64,
    /// Simulated episodes: the scene spec and its sampled values (JSON).
    pub sim_scene: Option<String>,
    /// Set when a recorder died while recording it: what was recovered and how it was judged
    /// (e.g. "recorder restarted: 2 parts, the loop's verdict" or "unjudged").
    pub recovered: Option<String>,
    /// A policy's rollout: the checkpoint whose actions the steps executed (`<dir>@<step>`).
    pub policy: Option<String>,
    /// The rig's camera calibrations in force (JSON from `/calibration`: per camera its date,
    /// method and extrinsics; [`crate::calibration::Calibrations::summary`]).
    pub calibration: Option<String>,
    /// A policy's rollout with operator corrections: how many times an operator took over
    /// (a run of steps whose `action_source` is not the policy's) and how many steps the
    /// operators acted. Absent in episodes recorded before takeovers existed, and in those
    /// of other sources.
    pub takeovers: Option<u64>,
    pub operator_steps: Option<u64>,
}

impl EpisodeMetadata {
    pub fn new(rig: &RigIdentity, scene_id: &str, task_instruction: &str, start: Nanos) -> EpisodeMetadata {
        let start_ns = start.0;
        EpisodeMetadata {
            uuid: episode_uuid(&rig.lab, &rig.user, start),
            lab: rig.lab.clone(),
            building: rig.building.clone(),
            user: rig.user.clone(),
            scene_id: scene_id.to_owned(),
            task_instruction: task_instruction.to_owned(),
            success: None,
            robot_serial: rig.robot_serial.clone(),
            camera_serials: rig.camera_serials.clone(),
            extrinsics: BTreeMap::new(),
            start_ns,
            trajectory_length: 0,
            sim_scene: None,
            recovered: None,
            policy: None,
            calibration: None,
            takeovers: None,
            operator_steps: None,
        }
    }

    /// The string map of the MCAP `droid_episode` metadata record (DROID's key names;
    /// maps and arrays as JSON).
    pub fn to_record(&self) -> BTreeMap<String, String> {
        let mut m = BTreeMap::new();
        let start = utc(self.start_ns);
        m.insert("uuid".into(), self.uuid.clone());
        m.insert("lab".into(), self.lab.clone());
        m.insert("building".into(), self.building.clone());
        m.insert("user".into(), self.user.clone());
        m.insert("scene_id".into(), self.scene_id.clone());
        m.insert("current_task".into(), self.task_instruction.clone());
        m.insert("success".into(), self.success.map_or("unknown".into(), |s| s.to_string()));
        m.insert("robot_serial".into(), self.robot_serial.clone());
        m.insert("date".into(), start.format("%Y-%m-%d").to_string());
        m.insert("time".into(), asctime(&start));
        m.insert("start_ns".into(), self.start_ns.to_string());
        m.insert("trajectory_length".into(), self.trajectory_length.to_string());
        m.insert("camera_serials".into(), serde_json::to_string(&self.camera_serials).unwrap_or_default());
        m.insert("extrinsics".into(), serde_json::to_string(&self.extrinsics).unwrap_or_default());
        if let Some(scene) = &self.sim_scene {
            m.insert("sim_scene".into(), scene.clone());
        }
        if let Some(r) = &self.recovered {
            m.insert("recovered".into(), r.clone());
        }
        if let Some(p) = &self.policy {
            m.insert("policy".into(), p.clone());
        }
        if let Some(c) = &self.calibration {
            m.insert("calibration".into(), c.clone());
        }
        if let Some(n) = self.takeovers {
            m.insert("takeovers".into(), n.to_string());
        }
        if let Some(n) = self.operator_steps {
            m.insert("operator_steps".into(), n.to_string());
        }
        m
    }

    /// Reads a `droid_episode` record back.
    pub fn from_record(m: &BTreeMap<String, String>) -> Result<EpisodeMetadata, MetadataError> {
        let get = |k: &'static str| m.get(k).cloned().ok_or(MetadataError::Missing { key: k });
        let bad =
            |key: &'static str| move |e: &dyn std::fmt::Display| MetadataError::Invalid { key, reason: e.to_string() };
        let num = |k: &'static str| get(k)?.parse::<i64>().map_err(|e| bad(k)(&e));
        Ok(EpisodeMetadata {
            uuid: get("uuid")?,
            lab: get("lab")?,
            building: get("building")?,
            user: get("user")?,
            scene_id: get("scene_id")?,
            task_instruction: get("current_task")?,
            success: match get("success")?.as_str() {
                "true" => Some(true),
                "false" => Some(false),
                _ => None,
            },
            robot_serial: get("robot_serial")?,
            camera_serials: serde_json::from_str(&get("camera_serials")?).map_err(|e| bad("camera_serials")(&e))?,
            extrinsics: serde_json::from_str(&get("extrinsics")?).map_err(|e| bad("extrinsics")(&e))?,
            start_ns: num("start_ns")?,
            trajectory_length: num("trajectory_length")? as u64,
            sim_scene: m.get("sim_scene").cloned(),
            recovered: m.get("recovered").cloned(),
            policy: m.get("policy").cloned(),
            calibration: m.get("calibration").cloned(),
            takeovers: m.get("takeovers").map(|n| n.parse().map_err(|e| bad("takeovers")(&e))).transpose()?,
            operator_steps: m
                .get("operator_steps")
                .map(|n| n.parse().map_err(|e| bad("operator_steps")(&e)))
                .transpose()?,
        })
    }
}

/// A `droid_episode` record that cannot be read back.
#[derive(Debug, thiserror::Error)]
pub enum MetadataError {
    #[error("droid_episode metadata has no `{key}`")]
    Missing { key: &'static str },
    #[error("droid_episode `{key}`: {reason}")]
    Invalid { key: &'static str, reason: String },
}

fn utc(ns: i64) -> DateTime<Utc> {
    DateTime::from_timestamp_nanos(ns)
}

/// Python's `time.asctime()` form DROID uses for directory names, with `:` kept
/// (`Fri Jul  7 09:42:23 2023` -> `Fri_Jul__7_09:42:23_2023`).
fn asctime(t: &DateTime<Utc>) -> String {
    format!("{}_{:>2}_{}_{}", t.format("%a_%b"), t.day(), t.format("%H:%M:%S"), t.year()).replace(' ', "_")
}

/// DROID's episode id: `<lab>+<user>+<YYYY-MM-DD-HHh-MMm-SSs>`.
pub fn episode_uuid(lab: &str, user: &str, start: Nanos) -> String {
    format!("{lab}+{user}+{}", utc(start.0).format("%Y-%m-%d-%Hh-%Mm-%Ss"))
}

/// `<root>/{success|failure}/<YYYY-MM-DD>/<asctime>/`.
pub fn episode_dir(root: &Path, outcome: Outcome, start: Nanos) -> PathBuf {
    let t = utc(start.0);
    root.join(outcome.dir()).join(t.format("%Y-%m-%d").to_string()).join(asctime(&t))
}

#[cfg(test)]
mod tests {
    use super::*;

    // 2023-07-07 09:42:23 UTC, DROID's own example directory.
    const T: i64 = 1_688_722_943_000_000_000;

    #[test]
    fn names_follow_droid() {
        assert_eq!(episode_uuid("IRIS", "7dfa2da3", Nanos(T)), "IRIS+7dfa2da3+2023-07-07-09h-42m-23s");
        assert_eq!(
            episode_dir(Path::new("/data"), Outcome::Success, Nanos(T)),
            Path::new("/data/success/2023-07-07/Fri_Jul__7_09:42:23_2023")
        );
        assert_eq!(
            episode_dir(Path::new("/d"), Outcome::Failure, Nanos(T + 7 * 86_400_000_000_000)),
            Path::new("/d/failure/2023-07-14/Fri_Jul_14_09:42:23_2023")
        );
    }

    #[test]
    fn the_record_round_trips() {
        let mut rig = RigIdentity::default();
        rig.camera_serials.insert("ext1".into(), "ZED2-123".into());
        let mut m = EpisodeMetadata::new(&rig, "pick_place_cube", "put the cube in the bin", Nanos(T));
        m.extrinsics.insert("ext1".into(), [0.1, 0.2, 0.3, 0.4, 0.5, 0.6]);
        m.success = Some(true);
        m.trajectory_length = 123;
        m.sim_scene = Some("{\"seed\":3}".into());
        m.recovered = Some("recorder restarted: 2 parts".into());
        m.policy = Some("run@600".into());
        m.calibration = Some("{\"ext1\":{\"date\":\"2026-11-25T12:00:00Z\"}}".into());
        m.takeovers = Some(2);
        m.operator_steps = Some(80);
        let back = EpisodeMetadata::from_record(&m.to_record()).unwrap();
        assert_eq!(back, m);
        // Records from before takeovers existed read as none known.
        let mut old = m.to_record();
        old.remove("takeovers");
        old.remove("operator_steps");
        let back = EpisodeMetadata::from_record(&old).unwrap();
        assert_eq!((back.takeovers, back.operator_steps), (None, None));
        assert_eq!(m.to_record()["current_task"], "put the cube in the bin");
        let mut r = m.to_record();
        r.remove("lab");
        assert_eq!(EpisodeMetadata::from_record(&r).unwrap_err().to_string(), "droid_episode metadata has no `lab`");
    }
}
