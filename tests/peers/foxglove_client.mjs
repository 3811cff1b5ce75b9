// An independent Foxglove WebSocket client for the station's test: Foxglove's own
// @foxglove/ws-protocol client (over the `ws` package) connects, lists the advertised channels,
// subscribes to the joint states and a camera preview, and decodes them with Foxglove's own
// ros2msg parser and CDR reader (@foxglove/rosmsg, @foxglove/rosmsg2-serialization), as the
// Foxglove app does.
//
// usage: node foxglove_client.mjs ws://127.0.0.1:PORT/foxglove CAMERA
// prints one JSON object: {channels: [{topic, schemaName, encoding}], joint_state: {...},
// image: {format, bytes, frame_id, jpeg}}; exits 1 on a timeout or an error.
import wsProtocol from "@foxglove/ws-protocol";
import { parse } from "@foxglove/rosmsg";
import { MessageReader } from "@foxglove/rosmsg2-serialization";
import WebSocket from "ws";

const { FoxgloveClient } = wsProtocol; // a CommonJS package: its exports object
const [url, camera] = process.argv.slice(2);
const ws = new WebSocket(url, [FoxgloveClient.SUPPORTED_SUBPROTOCOL]);
const client = new FoxgloveClient({ ws });
const out = { channels: [], joint_state: null, image: null };
const readers = new Map(); // subscription id -> [topic, MessageReader]
const timer = setTimeout(() => {
  console.error("timed out: " + JSON.stringify(out).slice(0, 400));
  process.exit(1);
}, 20000);

client.on("error", (e) => { console.error("error: " + e); process.exit(1); });
client.on("advertise", (channels) => {
  for (const c of channels) {
    out.channels.push({ topic: c.topic, schemaName: c.schemaName, encoding: c.encoding });
    if (c.topic === "/joint_states" || c.topic === `/cameras/${camera}/preview/compressed`) {
      const reader = new MessageReader(parse(c.schema, { ros2: true }));
      readers.set(client.subscribe(c.id), [c.topic, reader]);
    }
  }
});
client.on("message", ({ subscriptionId, data }) => {
  const entry = readers.get(subscriptionId);
  if (!entry) return;
  const [topic, reader] = entry;
  const bytes = new Uint8Array(data.buffer, data.byteOffset, data.byteLength);
  const msg = reader.readMessage(bytes);
  if (topic === "/joint_states" && !out.joint_state) {
    out.joint_state = { name: msg.name, position: Array.from(msg.position), stamp_sec: msg.header.stamp.sec };
  } else if (topic.endsWith("/preview/compressed") && !out.image) {
    const d = msg.data;
    out.image = { format: msg.format, bytes: d.length, frame_id: msg.header.frame_id, jpeg: d[0] === 0xff && d[1] === 0xd8 };
  }
  if (out.joint_state && out.image) {
    clearTimeout(timer);
    console.log(JSON.stringify(out));
    client.close();
    process.exit(0);
  }
});
