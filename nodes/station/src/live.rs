//! The rig as the page sees it, kept up to date by the station's ROS side, and the operator's
//! requests going out.

use labrig_msgs::rig::{EpisodeEvent, EpisodeEventKind};
use labrig_msgs::session::Session;
use labrig_msgs::std_msgs::StringMsg;
use labrig_msgs::topics;
use labrig_runtime::Shutdown;
use labrig_runtime::ros::Ros;
use serde_json::{Value, json};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// What the page shows, as last heard (each part with when).
#[derive(Debug, Default)]
pub struct Live {
    pub robot: Option<(Value, Instant)>,
    pub gripper: Option<(Value, Instant)>,
    pub control: Option<(Value, Instant)>,
    pub recorder: Option<(Value, Instant)>,
    pub step: Option<(Value, Instant)>,
    pub teleop: Option<(Value, Instant)>,
    /// `/calibration`: per camera its Unix time.
    pub calibration: Option<Value>,
    pub last_event: Option<(Value, Instant)>,
    /// Episode events seen since the station started.
    pub events_seen: u64,
    pub session: Session,
    /// Requests sent (for the page's log and the stats).
    pub sent: u64,
}

/// What the web side asks the ROS side to do.
#[derive(Debug)]
pub enum Command {
    Episode(EpisodeEventKind, String),
    Session(Session),
}

fn age(at: &Instant) -> f64 {
    at.elapsed().as_secs_f64()
}

impl Live {
    /// The status document the page polls (`GET /api/status`).
    pub fn status(&self, max_calibration_age_s: f64) -> Value {
        let with_age = |v: &Option<(Value, Instant)>| match v {
            Some((v, at)) => {
                let mut v = v.clone();
                if let Some(o) = v.as_object_mut() {
                    o.insert("age_s".into(), json!(age(at)));
                }
                v
            }
            None => Value::Null,
        };
        let now =
            std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_secs_f64()).unwrap_or(0.0);
        let calibration: serde_json::Map<String, Value> = self
            .calibration
            .as_ref()
            .and_then(|c| c.as_object())
            .map(|cams| {
                cams.iter()
                    .map(|(cam, c)| {
                        let age_s = c["unix_time_s"].as_f64().map(|t| (now - t).max(0.0));
                        let stale = age_s.is_none_or(|a| a > max_calibration_age_s);
                        (cam.clone(), json!({"date": c["date"], "age_s": age_s, "stale": stale, "method": c["method"]}))
                    })
                    .collect()
            })
            .unwrap_or_default();
        json!({
            "robot": with_age(&self.robot),
            "gripper": with_age(&self.gripper),
            "loop": with_age(&self.control),
            "recorder": with_age(&self.recorder),
            "step": with_age(&self.step),
            "teleop": with_age(&self.teleop),
            "calibration": calibration,
            "last_event": with_age(&self.last_event),
            "session": self.session,
            "requests_sent": self.sent,
        })
    }
}

fn event_name(kind: u8) -> &'static str {
    match EpisodeEventKind::try_from(kind) {
        Ok(EpisodeEventKind::Start) => "start",
        Ok(EpisodeEventKind::Stop) => "stop",
        Ok(EpisodeEventKind::Success) => "success",
        Ok(EpisodeEventKind::Failure) => "failure",
        Ok(EpisodeEventKind::Discard) => "discard",
        Ok(EpisodeEventKind::Reset) => "reset",
        Err(_) => "unknown",
    }
}

fn source_name(s: u8) -> &'static str {
    ["none", "teleop", "policy", "scripted", "replay"].get(s as usize).copied().unwrap_or("unknown")
}

/// Parses a JSON status string, keeping a non-JSON one as text.
fn json_of(text: &str) -> Value {
    serde_json::from_str(text).unwrap_or_else(|_| json!({ "text": text }))
}

/// The ROS side: subscriptions into `live`, `commands` out, until `shutdown`.
pub async fn run(
    ros_cfg: &labrig_runtime::RosConfig,
    url: &str,
    hub: Arc<crate::foxglove::Hub>,
    live: Arc<Mutex<Live>>,
    mut commands: tokio::sync::mpsc::UnboundedReceiver<Command>,
    shutdown: Shutdown,
) -> anyhow::Result<()> {
    let mut ros = Ros::new(ros_cfg, "labrig_station")?;
    let arm = ros.subscription_on(&topics::ARM_STATE, 4)?;
    let gripper = ros.subscription_on(&topics::GRIPPER_STATE, 4)?;
    let control = ros.subscription_on(&topics::CONTROL_STATUS, 1)?;
    let recorder = ros.subscription_on(&topics::RECORDER_STATUS, 1)?;
    let step = ros.subscription_on(&topics::RIG_STEP, 4)?;
    let teleop = ros.subscription_on(&topics::TELEOP_STATE, 4)?;
    let calibration = ros.subscription_on(&topics::CALIBRATION, 1)?;
    let events = ros.subscription_on(&topics::RIG_EPISODE, 10)?;
    let requests = ros.publisher_on(&topics::RIG_REQUEST, 10)?;
    let session_pub = ros.publisher_on(&topics::RIG_SESSION, 1)?;
    let status_pub = ros.publisher_on(&topics::STATION_STATUS, 1)?;
    // The DDS topics Foxglove gets as received (the thumbnails go to the hub from their thread).
    let mut forwarded = Vec::new();
    for c in hub.channels.iter().filter(|c| !c.topic.ends_with("/preview/compressed")) {
        let q = if c.latched { labrig_runtime::ros::qos::latched(1) } else { labrig_runtime::ros::qos::reliable(16) };
        forwarded
            .push((c.topic.clone(), ros.raw_subscription(&c.topic, &labrig_msgs::dds_type_name(&c.schema_name), q)?));
    }
    let mut status_at = Instant::now() - Duration::from_secs(2);
    // The kept session goes out at start (latched: the loop and the recorder get it whenever
    // they come up).
    let initial = live.lock().expect("live state").session.clone();
    session_pub.publish(StringMsg { data: serde_json::to_string(&initial)? })?;
    let mut tick = tokio::time::interval(Duration::from_millis(20));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    loop {
        tokio::select! {
            _ = shutdown.wait() => break,
            c = commands.recv() => match c {
                Some(Command::Episode(kind, note)) => {
                    requests.publish(EpisodeEvent { kind: kind as u8, note, ..Default::default() })?;
                    live.lock().expect("live state").sent += 1;
                }
                Some(Command::Session(s)) => {
                    session_pub.publish(StringMsg { data: serde_json::to_string(&s)? })?;
                    live.lock().expect("live state").session = s;
                }
                None => break,
            },
            _ = tick.tick() => {}
        }
        let now = Instant::now();
        if now.duration_since(status_at) >= Duration::from_secs(1) {
            status_at = now;
            let sent = live.lock().expect("live state").sent;
            status_pub.publish(StringMsg { data: json!({"url": url, "requests_sent": sent}).to_string() })?;
        }
        for (topic, sub) in &forwarded {
            while let Some(s) = sub.try_take()? {
                let ns = s.receive_time.0.max(0) as u64;
                hub.publish(topic, ns, axum::body::Bytes::from(s.msg.to_cdr_bytes()));
            }
        }
        let mut l = live.lock().expect("live state");
        while let Some(s) = arm.try_take()? {
            let m = s.msg;
            l.robot = Some((
                json!({"joints": m.joint_positions, "tcp": m.cartesian_position, "mode": m.mode, "fault": m.fault}),
                now,
            ));
        }
        while let Some(s) = gripper.try_take()? {
            let m = s.msg;
            l.gripper =
                Some((json!({"position": m.position, "object_detected": m.object_detected, "fault": m.fault}), now));
        }
        while let Some(s) = control.try_take()? {
            l.control = Some((json_of(&s.msg.data), now));
        }
        while let Some(s) = recorder.try_take()? {
            l.recorder = Some((json_of(&s.msg.data), now));
        }
        while let Some(s) = step.try_take()? {
            let m = s.msg;
            l.step = Some((
                json!({"episode": m.episode_id, "index": m.step_index, "source": source_name(m.action_source),
                       "movement_enabled": m.movement_enabled, "camera_skew_ms": m.camera_skew_ns as f64 / 1e6}),
                now,
            ));
        }
        while let Some(s) = teleop.try_take()? {
            let m = s.msg;
            l.teleop = Some((
                json!({"connected": m.controller_connected, "deadman": m.movement_enabled, "hand": m.hand}),
                now,
            ));
        }
        while let Some(s) = calibration.try_take()? {
            l.calibration = serde_json::from_str(&s.msg.data).ok();
        }
        while let Some(s) = events.try_take()? {
            let m = s.msg;
            l.events_seen += 1;
            l.last_event = Some((
                json!({"kind": event_name(m.kind), "episode": m.episode_id, "note": m.note, "seq": l.events_seen}),
                now,
            ));
        }
    }
    Ok(())
}
