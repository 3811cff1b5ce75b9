//! The live rig in Foxglove: the Foxglove WebSocket protocol (subprotocol
//! `foxglove.websocket.v1`) on the station's own server, at `ws://127.0.0.1:8080/foxglove`
//! (beyond loopback `?token=...`, the station's token rule). Implemented on axum's WebSocket
//! rather than the `foxglove` crate's server: one listener, one token check, no second runtime,
//! and the protocol's part the station needs (server info, advertise, subscribe/unsubscribe,
//! binary message frames) is small.
//!
//! Channels carry the DDS samples as received (`cdr` with their `ros2msg` schemas, which
//! Foxglove decodes itself): `/joint_states`, `/tf`, `/tf_static`, `/rig/step`, `/rig/episode`,
//! `/cameras/<id>/camera_info`, and the station's thumbnails as
//! `/cameras/<id>/preview/compressed` (sensor_msgs/CompressedImage, JPEG). A latched topic's
//! last sample goes to each new subscriber first. Every queue is bounded: a slow client loses
//! its own oldest messages and holds nothing else back.

use axum::body::Bytes;
use axum::extract::ws::{Message, WebSocket};
use serde_json::{Value, json};
use std::collections::HashMap;
use std::sync::Mutex;
use tokio::sync::broadcast;

/// The subprotocol Foxglove speaks.
pub const SUBPROTOCOL: &str = "foxglove.websocket.v1";
/// Messages a channel keeps for its slowest subscriber before that one loses the oldest.
const CHANNEL_DEPTH: usize = 32;

/// One advertised channel.
#[derive(Debug)]
pub struct Channel {
    pub id: u32,
    pub topic: String,
    pub schema_name: String,
    pub schema: String,
    pub latched: bool,
    tx: broadcast::Sender<(u64, Bytes)>,
    last: Mutex<Option<(u64, Bytes)>>,
}

/// The channels and their fan-out.
#[derive(Debug, Default)]
pub struct Hub {
    pub channels: Vec<Channel>,
}

impl Hub {
    /// Adds a channel (ids from 1, in order).
    pub fn add(&mut self, topic: &str, schema_name: &str, schema: String, latched: bool) {
        let (tx, _) = broadcast::channel(CHANNEL_DEPTH);
        let id = self.channels.len() as u32 + 1;
        self.channels.push(Channel {
            id,
            topic: topic.to_owned(),
            schema_name: schema_name.to_owned(),
            schema,
            latched,
            tx,
            last: Mutex::new(None),
        });
    }

    pub fn by_topic(&self, topic: &str) -> Option<&Channel> {
        self.channels.iter().find(|c| c.topic == topic)
    }

    /// A sample for `topic` (CDR with its encapsulation header), stamped `ns`.
    pub fn publish(&self, topic: &str, ns: u64, cdr: Bytes) {
        let Some(c) = self.by_topic(topic) else { return };
        if c.latched {
            *c.last.lock().expect("latched sample") = Some((ns, cdr.clone()));
        }
        // No subscriber is no error.
        let _ = c.tx.send((ns, cdr));
    }

    fn advertise(&self) -> Value {
        let channels: Vec<Value> = self
            .channels
            .iter()
            .map(|c| {
                json!({"id": c.id, "topic": c.topic, "encoding": "cdr", "schemaName": c.schema_name,
                       "schema": c.schema, "schemaEncoding": "ros2msg"})
            })
            .collect();
        json!({"op": "advertise", "channels": channels})
    }
}

/// A binary message frame: opcode 1, subscription id, receive time (ns), payload.
fn frame(sub: u32, ns: u64, payload: &[u8]) -> Bytes {
    let mut b = Vec::with_capacity(13 + payload.len());
    b.push(0x01);
    b.extend_from_slice(&sub.to_le_bytes());
    b.extend_from_slice(&ns.to_le_bytes());
    b.extend_from_slice(payload);
    Bytes::from(b)
}

/// Serves one client until it goes or `stop` fires.
pub async fn serve(mut ws: WebSocket, hub: std::sync::Arc<Hub>, started_ms: u64, stop: labrig_runtime::Shutdown) {
    let info = json!({"op": "serverInfo", "name": "labrig station", "capabilities": [],
                      "supportedEncodings": [], "metadata": {}, "sessionId": started_ms.to_string()});
    for m in [info, hub.advertise()] {
        if ws.send(Message::Text(m.to_string().into())).await.is_err() {
            return;
        }
    }
    // Subscriptions forward into one bounded queue per client.
    let (tx, mut rx) = tokio::sync::mpsc::channel::<Bytes>(64);
    let mut subs: HashMap<u32, tokio::task::JoinHandle<()>> = HashMap::new();
    loop {
        tokio::select! {
            _ = stop.wait() => break,
            out = rx.recv() => {
                let Some(b) = out else { break };
                if ws.send(Message::Binary(b)).await.is_err() {
                    break;
                }
            }
            msg = ws.recv() => {
                let text = match msg {
                    Some(Ok(Message::Text(t))) => t,
                    Some(Ok(Message::Close(_))) | None | Some(Err(_)) => break,
                    Some(Ok(_)) => continue,
                };
                let Ok(v) = serde_json::from_str::<Value>(&text) else {
                    tracing::debug!("foxglove client: not JSON: {text}");
                    continue;
                };
                match v["op"].as_str() {
                    Some("subscribe") => {
                        for s in v["subscriptions"].as_array().into_iter().flatten() {
                            let (Some(sid), Some(cid)) = (s["id"].as_u64(), s["channelId"].as_u64()) else { continue };
                            let Some(c) = hub.channels.iter().find(|c| u64::from(c.id) == cid) else { continue };
                            let sid = sid as u32;
                            let mut brx = c.tx.subscribe();
                            let first = c.last.lock().expect("latched sample").clone();
                            let tx = tx.clone();
                            let task = tokio::spawn(async move {
                                if let Some((ns, b)) = first {
                                    let _ = tx.send(frame(sid, ns, &b)).await;
                                }
                                loop {
                                    match brx.recv().await {
                                        // Full client queue: this message is dropped, not waited for.
                                        Ok((ns, b)) => if tx.try_send(frame(sid, ns, &b)).is_err() && tx.is_closed() {
                                            break;
                                        },
                                        Err(broadcast::error::RecvError::Lagged(_)) => continue,
                                        Err(broadcast::error::RecvError::Closed) => break,
                                    }
                                }
                            });
                            if let Some(old) = subs.insert(sid, task) {
                                old.abort();
                            }
                        }
                    }
                    Some("unsubscribe") => {
                        for id in v["subscriptionIds"].as_array().into_iter().flatten().filter_map(Value::as_u64) {
                            if let Some(t) = subs.remove(&(id as u32)) {
                                t.abort();
                            }
                        }
                    }
                    _ => {}
                }
            }
        }
    }
    for (_, t) in subs {
        t.abort();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_follow_the_protocols_layout() {
        let f = frame(7, 0x0102_0304_0506_0708, b"cdr");
        assert_eq!(f[0], 1);
        assert_eq!(&f[1..5], &7u32.to_le_bytes());
        assert_eq!(&f[5..13], &0x0102_0304_0506_0708u64.to_le_bytes());
        assert_eq!(&f[13..], b"cdr");
        let mut hub = Hub::default();
        hub.add("/tf_static", "tf2_msgs/msg/TFMessage", "schema".into(), true);
        hub.publish("/tf_static", 5, Bytes::from_static(b"x"));
        assert_eq!(hub.channels[0].last.lock().unwrap().clone().map(|(n, _)| n), Some(5));
        let a = hub.advertise();
        assert_eq!(a["channels"][0]["encoding"], "cdr");
        assert_eq!(a["channels"][0]["schemaEncoding"], "ros2msg");
    }
}
