//! DROID's `metadata_<uuid>.json`, written and read.
//!
//! DROID's fields (FACTS.md): uuid, lab, user, user_id, date, timestamp, hdf5_path, building,
//! scene_id, success, robot_serial, droid_version, current_task, trajectory_length, and per
//! DROID camera role (wrist, ext1, ext2) `<role>_cam_serial`, `<role>_cam_extrinsics`,
//! `<role>_svo_path`, `<role>_mp4_path` (paths relative to the dataset root, as DROID's). labrig
//! records no SVO, so the SVO paths are null. What DROID has no field for (the rig's other
//! cameras, the scene of a simulated episode, the recording's start in ns, the action source)
//! goes under one extra key, `labrig`, so an exported episode imports back whole.

use chrono::{DateTime, NaiveDateTime, Utc};
use labrig_episode::metadata::EpisodeMetadata;
use labrig_msgs::Invalid;
use labrig_msgs::rig::Step;
use serde_json::{Value, json};
use std::collections::BTreeMap;

/// The `droid_version` written (the DROID raw dataset release whose layout this follows).
pub const DROID_VERSION: &str = "1.0.1";
/// DROID's camera roles, each a labrig camera id.
pub const ROLES: [&str; 3] = ["wrist", "ext1", "ext2"];

/// DROID's `timestamp` form (also the tail of its uuid).
const STAMP_FORMAT: &str = "%Y-%m-%d-%Hh-%Mm-%Ss";

/// What the JSON is written from.
#[derive(Debug)]
pub struct JsonInput<'a> {
    pub meta: &'a EpisodeMetadata,
    /// The episode directory relative to the dataset root (`success/2023-07-07/...`).
    pub rel_dir: &'a str,
    /// (camera id, serial, base-frame extrinsics of the first step).
    pub cameras: &'a [(String, String, Option<[f64; 6]>)],
    pub hand_offset: Option<[f64; 6]>,
    pub action_source: u8,
}

fn source_name(s: u8) -> &'static str {
    match s {
        Step::SOURCE_TELEOP => "teleop",
        Step::SOURCE_POLICY => "policy",
        Step::SOURCE_SCRIPTED => "scripted",
        Step::SOURCE_REPLAY => "replay",
        _ => "none",
    }
}

fn source_of(name: &str) -> u8 {
    match name {
        "teleop" => Step::SOURCE_TELEOP,
        "policy" => Step::SOURCE_POLICY,
        "scripted" => Step::SOURCE_SCRIPTED,
        "replay" => Step::SOURCE_REPLAY,
        _ => Step::SOURCE_NONE,
    }
}

/// `metadata_<uuid>.json`'s file name.
pub fn file_name(uuid: &str) -> String {
    format!("metadata_{uuid}.json")
}

/// The JSON document.
pub fn to_json(i: &JsonInput<'_>) -> Value {
    let m = i.meta;
    let start: DateTime<Utc> = DateTime::from_timestamp_nanos(m.start_ns);
    let mut v = json!({
        "uuid": m.uuid,
        "lab": m.lab,
        "user": m.user,
        "user_id": m.user,
        "date": start.format("%Y-%m-%d").to_string(),
        "timestamp": start.format(STAMP_FORMAT).to_string(),
        "hdf5_path": format!("{}/trajectory.h5", i.rel_dir),
        "building": m.building,
        "scene_id": m.scene_id,
        "success": m.success == Some(true),
        "robot_serial": m.robot_serial,
        "droid_version": DROID_VERSION,
        "current_task": m.task_instruction,
        "trajectory_length": m.trajectory_length,
    });
    let obj = v.as_object_mut().expect("an object");
    for role in ROLES {
        let cam = i.cameras.iter().find(|(id, _, _)| id == role);
        obj.insert(format!("{role}_cam_serial"), json!(cam.map(|c| &c.1)));
        obj.insert(format!("{role}_cam_extrinsics"), json!(cam.and_then(|c| c.2)));
        obj.insert(format!("{role}_svo_path"), Value::Null);
        obj.insert(format!("{role}_mp4_path"), json!(cam.map(|c| format!("{}/recordings/MP4/{}.mp4", i.rel_dir, c.1))));
    }
    let cameras: BTreeMap<&str, &str> = i.cameras.iter().map(|(id, s, _)| (id.as_str(), s.as_str())).collect();
    // The hand camera's offset has a key of its own (an imported episode keeps it among the
    // extrinsics).
    let extrinsics: BTreeMap<&String, &[f64; 6]> =
        m.extrinsics.iter().filter(|(k, _)| !k.ends_with("_gripper_offset")).collect();
    obj.insert(
        "labrig".into(),
        json!({
            "format": 1,
            "cameras": cameras,
            "extrinsics": extrinsics,
            "hand_camera_offset": i.hand_offset,
            "start_ns": m.start_ns,
            "action_source": source_name(i.action_source),
            "sim_scene": m.sim_scene,
            "recovered": m.recovered,
            "policy": m.policy,
            "calibration": m.calibration,
        }),
    );
    v
}

/// What an import takes from the JSON.
#[derive(Debug, Clone)]
pub struct Parsed {
    pub meta: EpisodeMetadata,
    /// Serial -> labrig camera id.
    pub serial_to_id: BTreeMap<String, String>,
    pub action_source: u8,
    /// Whether `start_ns` came from the file (else the caller takes the first step's time).
    pub has_start: bool,
}

fn text(v: &Value, key: &str) -> Result<String, Invalid> {
    match v.get(key) {
        Some(Value::String(s)) => Ok(s.clone()),
        Some(Value::Number(n)) => Ok(n.to_string()),
        Some(Value::Null) | None => Err(Invalid::new(key, format!("metadata JSON has no `{key}`"))),
        Some(other) => Err(Invalid::new(key, format!("metadata JSON `{key}` is {other}, expected a string"))),
    }
}

fn text_or(v: &Value, key: &str, default: &str) -> String {
    text(v, key).unwrap_or_else(|_| default.to_owned())
}

/// Reads a DROID metadata JSON (DROID's own or one labrig wrote).
pub fn parse(v: &Value) -> Result<Parsed, Invalid> {
    if !v.is_object() {
        return Err(Invalid::new("metadata", "metadata JSON is not an object"));
    }
    let uuid = text(v, "uuid")?;
    let lab = text_or(v, "lab", uuid.split('+').next().unwrap_or("unknown"));
    let user = text(v, "user").or_else(|_| text(v, "user_id")).unwrap_or_else(|_| "unknown".into());
    let labrig = v.get("labrig").filter(|l| l.is_object());
    let mut serial_to_id = BTreeMap::new();
    let mut camera_serials = BTreeMap::new();
    if let Some(cams) = labrig.and_then(|l| l.get("cameras")).and_then(Value::as_object) {
        for (id, serial) in cams {
            let serial = serial.as_str().ok_or_else(|| {
                Invalid::new(
                    format!("labrig.cameras.{id}"),
                    format!("metadata JSON `labrig.cameras.{id}` is not a string"),
                )
            })?;
            serial_to_id.insert(serial.to_owned(), id.clone());
            camera_serials.insert(id.clone(), serial.to_owned());
        }
    } else {
        for role in ROLES {
            if let Ok(serial) = text(v, &format!("{role}_cam_serial")) {
                serial_to_id.insert(serial.clone(), role.to_owned());
                camera_serials.insert(role.to_owned(), serial);
            }
        }
    }
    let mut extrinsics: BTreeMap<String, [f64; 6]> = BTreeMap::new();
    if let Some(e) = labrig.and_then(|l| l.get("extrinsics")) {
        extrinsics = serde_json::from_value(e.clone())
            .map_err(|e| Invalid::new("labrig.extrinsics", format!("metadata JSON `labrig.extrinsics`: {e}")))?;
    } else {
        for role in ["ext1", "ext2"] {
            if let Some(e) = v.get(format!("{role}_cam_extrinsics")).filter(|e| !e.is_null()) {
                let e: [f64; 6] = serde_json::from_value(e.clone()).map_err(|err| {
                    Invalid::new(
                        format!("{role}_cam_extrinsics"),
                        format!("metadata JSON `{role}_cam_extrinsics`: {err}"),
                    )
                })?;
                extrinsics.insert(role.to_owned(), e);
            }
        }
    }
    let start_ns = match labrig.and_then(|l| l.get("start_ns")).and_then(Value::as_i64) {
        Some(ns) => Some(ns),
        None => text(v, "timestamp")
            .ok()
            .and_then(|t| NaiveDateTime::parse_from_str(&t, STAMP_FORMAT).ok())
            .and_then(|t| t.and_utc().timestamp_nanos_opt()),
    };
    let success = match v.get("success") {
        Some(Value::Bool(b)) => Some(*b),
        _ => None,
    };
    let meta = EpisodeMetadata {
        uuid,
        lab,
        building: text_or(v, "building", ""),
        user,
        scene_id: text_or(v, "scene_id", ""),
        task_instruction: text_or(v, "current_task", ""),
        success,
        robot_serial: text_or(v, "robot_serial", ""),
        camera_serials,
        extrinsics,
        start_ns: start_ns.unwrap_or(0),
        trajectory_length: v.get("trajectory_length").and_then(Value::as_u64).unwrap_or(0),
        sim_scene: labrig.and_then(|l| l.get("sim_scene")).and_then(Value::as_str).map(str::to_owned),
        recovered: labrig.and_then(|l| l.get("recovered")).and_then(Value::as_str).map(str::to_owned),
        policy: labrig.and_then(|l| l.get("policy")).and_then(Value::as_str).map(str::to_owned),
        calibration: labrig.and_then(|l| l.get("calibration")).and_then(Value::as_str).map(str::to_owned),
        takeovers: None,
        operator_steps: None,
    };
    let action_source =
        labrig.and_then(|l| l.get("action_source")).and_then(Value::as_str).map_or(Step::SOURCE_TELEOP, source_of);
    Ok(Parsed { meta, serial_to_id, action_source, has_start: start_ns.is_some() })
}

#[cfg(test)]
mod tests {
    use super::*;
    use labrig_episode::metadata::RigIdentity;

    #[test]
    fn a_written_json_parses_back_to_the_same_metadata() {
        let mut rig = RigIdentity::default();
        rig.camera_serials.insert("wrist".into(), "18026681".into());
        let mut m = EpisodeMetadata::new(
            &rig,
            "scene 3",
            "put the cube in the bin",
            labrig_msgs::Nanos(1_688_722_943_123_456_789),
        );
        m.success = Some(false);
        m.trajectory_length = 7;
        m.extrinsics.insert("ext1".into(), [0.1, -0.2, 0.3, 1.0, 0.5, -3.0]);
        m.sim_scene = Some("{\"seed\":3}".into());
        m.policy = Some("run@600".into());
        m.camera_serials.insert("ext1".into(), "ext1".into());
        let cams = vec![
            ("ext1".to_owned(), "ext1".to_owned(), Some([0.1, -0.2, 0.3, 1.0, 0.5, -3.0])),
            ("wrist".to_owned(), "18026681".to_owned(), None),
        ];
        let i = JsonInput {
            meta: &m,
            rel_dir: "failure/2023-07-07/x",
            cameras: &cams,
            hand_offset: None,
            action_source: 3,
        };
        let v = to_json(&i);
        assert_eq!(v["timestamp"], "2023-07-07-09h-42m-23s");
        assert_eq!(v["wrist_mp4_path"], "failure/2023-07-07/x/recordings/MP4/18026681.mp4");
        assert_eq!(v["ext2_cam_serial"], Value::Null);
        let back = parse(&serde_json::from_str(&v.to_string()).unwrap()).unwrap();
        assert_eq!(back.meta, m);
        assert_eq!(back.action_source, Step::SOURCE_SCRIPTED);
        assert_eq!(back.serial_to_id["18026681"], "wrist");
    }

    #[test]
    fn droid_s_own_json_needs_only_droid_s_fields() {
        let v = json!({"uuid": "IRIS+7dfa2da3+2023-07-07-09h-42m-23s", "lab": "IRIS", "user": "Alice",
            "timestamp": "2023-07-07-09h-42m-23s", "scene_id": 4211, "success": true,
            "current_task": "Put the marker in the pot", "wrist_cam_serial": "138", "ext1_cam_serial": "239",
            "ext1_cam_extrinsics": [0.2, 0.5, 0.4, -2.0, 0.1, -1.0]});
        let p = parse(&v).unwrap();
        assert_eq!(p.meta.start_ns, 1_688_722_943_000_000_000);
        assert_eq!(p.meta.scene_id, "4211");
        assert_eq!(p.serial_to_id["239"], "ext1");
        assert_eq!(p.meta.extrinsics["ext1"], [0.2, 0.5, 0.4, -2.0, 0.1, -1.0]);
        assert_eq!(p.action_source, Step::SOURCE_TELEOP);
        assert!(parse(&json!({"lab": "x"})).unwrap_err().to_string().contains("no `uuid`"));
    }
}
