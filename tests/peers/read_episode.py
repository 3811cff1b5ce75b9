#!/usr/bin/env python3
"""Reads a labrig episode (a rosbag2 directory: episode_0.mcap, and episode_1.mcap ... when a
recorder restart split it into parts, + metadata.yaml) with the reference readers and prints
one JSON object for the Rust test to check:

- mcap + mcap-ros2-support: every message decoded through the schema embedded in the file
  (counts per topic, decode failures, metadata records, attachments, every /rig/step's
  step_index in log-time order, a few decoded values);
- rosbags 0.11.9: AnyReader on the directory (uses metadata.yaml) and on the bare .mcap
  files, every message deserialized (counts per topic).

Parts are read in order and summed (metadata records and samples: the last part's win).

Usage: read_episode.py <episode_dir>
"""
import json
import sys
from collections import Counter
from pathlib import Path

from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rosbags.highlevel import AnyReader


def with_mcap(path: Path) -> dict:
    out = {"counts": Counter(), "failures": [], "metadata": {}, "attachments": [], "profile": None,
           "step_indices": []}
    samples = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        out["profile"] = reader.get_header().profile
        for schema, channel, message, msg in reader.iter_decoded_messages(log_time_order=True):
            out["counts"][channel.topic] += 1
            if schema.name == "labrig_msgs/msg/Step":
                out["step_indices"].append(msg.step_index)
                samples["last_step_index"] = msg.step_index
                samples["last_step_joint_positions"] = list(msg.robot_state.joint_positions)
                samples["step_cameras"] = [c.camera_id for c in msg.cameras]
            elif schema.name == "sensor_msgs/msg/CompressedImage":
                data = bytes(msg.data)
                samples["image_format"] = msg.format
                samples["image_jpeg_markers"] = data[:2] == b"\xff\xd8" and data[-2:] == b"\xff\xd9"
        for m in reader.iter_metadata():
            out["metadata"][m.name] = dict(m.metadata)
        out["attachments"] = [a.name for a in reader.iter_attachments()]
    out["samples"] = samples
    return out


def with_mcap_parts(paths: list) -> dict:
    out = {"counts": Counter(), "failures": [], "metadata": {}, "attachments": [], "profile": None, "samples": {},
           "step_indices": []}
    for path in paths:
        part = with_mcap(path)
        out["counts"].update(part["counts"])
        out["failures"] += part["failures"]
        out["metadata"].update(part["metadata"])
        out["attachments"] += part["attachments"]
        out["step_indices"] += part["step_indices"]
        out["profile"] = part["profile"]
        out["samples"].update(part["samples"])
    return out


def with_rosbags(paths: list) -> dict:
    counts = Counter()
    with AnyReader(paths) as reader:
        for conn, _ts, raw in reader.messages():
            reader.deserialize(raw, conn.msgtype)
            counts[conn.topic] += 1
    return counts


def main() -> None:
    ep = Path(sys.argv[1])
    files = sorted(ep.glob("episode_*.mcap"), key=lambda f: int(f.stem.split("_")[1]))
    if not files:
        raise SystemExit(f"{ep}: no episode_<k>.mcap in it")
    result = {
        "parts": len(files),
        "mcap": with_mcap_parts(files),
        "rosbags_dir": with_rosbags([ep]),
        "rosbags_file": with_rosbags(files),
    }
    print(json.dumps(result, default=dict))


if __name__ == "__main__":
    main()
