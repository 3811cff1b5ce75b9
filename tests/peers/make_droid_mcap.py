"""Writes a DROID-layout MCAP from a trajectory.h5, the way DROID's own tools do, with h5py and
the PyPI `mcap` writer (no labrig code).

usage: make_droid_mcap.py TRAJECTORY_H5 OUT_MCAP --images DIR [--variant wrapped|flat] [--bad CASE]

--variant wrapped (default): as DROID's converter (scripts/convert/h5_to_mcap.py): profile "ros2",
  schemas droid.RobotState / Action / CameraExtrinsics / CameraIntrinsics / CameraType (one
  jsonschema text), payloads {"timestamp": {sec, nsec}, "data": <the h5 group at this step>} on
  /robot_state, /action, /camera_extrinsics, /camera_intrinsics, /camera_type; one metadata
  record per h5 attribute. Images per step at the step's log time, as DROID's first live writer
  does (the converter takes them from an MP4 stored inside the h5, which released files lack).
--variant flat: as DROID's newer live writer: profile "droid", /robot_state with top-level
  joint_positions, joint_velocities, joint_efforts, cartesian_position, cartesian_velocity,
  gripper_position, gripper_velocity (empty or 0.0 where the h5 has none), /action
  {"timestamp", "data": cartesian_velocity + [gripper_velocity]}, images with frame_id.
Log times are DROID's time_ms() in MCAP's nanosecond field (observation/timestamp/control/
step_start), as both writers store them.

Deviations from upstream that its code needs to run at all (mcap 1.6.0, h5py 3.16):
- numpy values become JSON through .tolist() / .item() (json.dumps of numpy values raises);
- add_metadata takes a dict of strings, so each attribute is {"value": str(v)} (upstream passes
  bytes, which the writer rejects).

--vr (flat): a /vr_controller per step as the newer writer's: poses {"r": row-major 4x4},
  buttons, movement_enabled, controller_on, success, failure.
--images DIR holds DIR/<serial>_left/<step>.jpg for the cameras of observation/camera_type.
--bad CASE writes a file labrig must refuse by name: no_robot_state (step 3 has none),
  bad_image (step 2's first image is not a JPEG), not_droid (an /imu topic only).
Prints a JSON summary: steps, log times, per-image sha256.
"""
import argparse
import base64
import hashlib
import json
import math
import os

import h5py
from mcap.writer import CompressionType, Writer

STAMP = {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}}
WRAPPED = {"type": "object", "properties": {"timestamp": STAMP, "data": {"type": "object", "additionalProperties": True}}}
IMAGE_C = {"type": "object", "properties": {"timestamp": STAMP, "format": {"type": "string"}, "data": {"type": "string"}}}
IMAGE_W2 = {
    "type": "object",
    "properties": {
        "timestamp": STAMP,
        "frame_id": {"type": "string"},
        "data": {"type": "string", "contentEncoding": "base64"},
        "format": {"type": "string"},
    },
}
TOPICS = [
    ("/robot_state", "observation/robot_state", "droid.RobotState"),
    ("/action", "action", "droid.Action"),
    ("/camera_extrinsics", "observation/camera_extrinsics", "droid.CameraExtrinsics"),
    ("/camera_intrinsics", "observation/camera_intrinsics", "droid.CameraIntrinsics"),
    ("/camera_type", "observation/camera_type", "droid.CameraType"),
]


def at_step(group, i):
    """The h5 group's values at step i, nested like the group (DROID's load_hdf5_to_dict)."""
    out = {}
    for k, v in group.items():
        out[k] = at_step(v, i) if isinstance(v, h5py.Group) else v[i].tolist()
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("h5")
    ap.add_argument("out")
    ap.add_argument("--images", required=True)
    ap.add_argument("--variant", default="wrapped", choices=["wrapped", "flat"])
    ap.add_argument("--bad", default=None, choices=["no_robot_state", "bad_image", "not_droid"])
    ap.add_argument("--lz4", action="store_true", help="LZ4 chunks (the writer's other codec) instead of zstd")
    ap.add_argument("--vr", action="store_true", help="flat: a /vr_controller per step, as DROID's newer writer")
    a = ap.parse_args()
    summary = {"steps": 0, "log_times": [], "images": {}, "vr": []}
    with h5py.File(a.h5, "r") as f, open(a.out, "wb") as stream:
        n = f["action/joint_position"].shape[0]
        serials = sorted(f["observation/camera_type"].keys())
        w = Writer(stream, compression=CompressionType.LZ4 if a.lz4 else CompressionType.ZSTD)
        w.start(profile="ros2" if a.variant == "wrapped" else "droid", library="droid-franka-robots")
        if a.bad == "not_droid":
            s = w.register_schema("sensor.Imu", "jsonschema", json.dumps(WRAPPED).encode())
            c = w.register_channel("/imu", "json", s)
            for i in range(3):
                w.add_message(c, log_time=i + 1, publish_time=i + 1, data=b'{"data": {}}')
            w.finish()
            print(json.dumps(summary))
            return
        ch = {}
        if a.variant == "wrapped":
            for topic, group, name in TOPICS:
                if group in f:
                    s = w.register_schema(name, "jsonschema", json.dumps(WRAPPED).encode())
                    ch[topic] = w.register_channel(topic, "json", s)
        else:
            s = w.register_schema("droid.RobotState", "jsonschema", json.dumps({"type": "object"}).encode())
            ch["/robot_state"] = w.register_channel("/robot_state", "json", s)
            s = w.register_schema("droid.Action", "jsonschema", json.dumps({"type": "object"}).encode())
            ch["/action"] = w.register_channel("/action", "json", s)
            if a.vr:
                s = w.register_schema("droid.VRController", "jsonschema", json.dumps({"type": "object"}).encode())
                ch["/vr_controller"] = w.register_channel("/vr_controller", "json", s)
        img_schema = w.register_schema(
            "foxglove.CompressedImage", "jsonschema", json.dumps(IMAGE_C if a.variant == "wrapped" else IMAGE_W2).encode()
        )
        for serial in serials:
            ch[serial] = w.register_channel(f"/camera/{serial}_left/compressed", "json", img_schema)
        times = f["observation/timestamp/control/step_start"][:]
        rs = f["observation/robot_state"]
        for i in range(n):
            log = int(times[i])  # DROID's time_ms(), in the ns field
            ts = {"sec": log // 1000, "nsec": (log % 1000) * 1_000_000}
            summary["log_times"].append(log)
            if a.variant == "wrapped":
                for topic, group, _ in TOPICS:
                    if group not in f or (topic == "/robot_state" and a.bad == "no_robot_state" and i == 3):
                        continue
                    data = json.dumps({"timestamp": ts, "data": at_step(f[group], i)}).encode()
                    w.add_message(ch[topic], log_time=log, publish_time=log, data=data)
            else:
                def get(key, default):
                    return rs[key][i].tolist() if key in rs else default

                state = {
                    "timestamp": ts,
                    "joint_positions": get("joint_positions", []),
                    "joint_velocities": get("joint_velocities", []),
                    "joint_efforts": get("joint_efforts", []),
                    "cartesian_position": get("cartesian_position", []),
                    "cartesian_velocity": get("cartesian_velocity", []),
                    "gripper_position": get("gripper_position", 0.0),
                    "gripper_velocity": get("gripper_velocity", 0.0),
                }
                if not (a.bad == "no_robot_state" and i == 3):
                    w.add_message(ch["/robot_state"], log_time=log, publish_time=log, data=json.dumps(state).encode())
                act = f["action/cartesian_velocity"][i].tolist() + [f["action/gripper_velocity"][i].item()]
                w.add_message(ch["/action"], log_time=log, publish_time=log, data=json.dumps({"timestamp": ts, "data": act}).encode())
                if a.vr:
                    # The right controller turning about z and moving along x; grip held for the
                    # first half, the A button (success) on the last step.
                    c, s_ = math.cos(0.02 * i), math.sin(0.02 * i)
                    pose = [c, -s_, 0.0, 0.3 + 0.001 * i, s_, c, 0.0, -0.1, 0.0, 0.0, 1.0, 1.2, 0.0, 0.0, 0.0, 1.0]
                    held = i < n // 2
                    vr = {
                        "timestamp": ts,
                        "poses": {"r": pose},
                        "buttons": {"A": i == n - 1, "B": False, "RG": held, "RJ": i % 7 == 0,
                                    "rightTrig": [i / n], "rightGrip": [1.0 if held else 0.0], "rightJS": [0.1, -0.2]},
                        "movement_enabled": held,
                        "controller_on": True,
                        "success": i == n - 1,
                        "failure": False,
                    }
                    summary["vr"].append(vr)
                    w.add_message(ch["/vr_controller"], log_time=log, publish_time=log, data=json.dumps(vr).encode())
            for k, serial in enumerate(serials):
                with open(os.path.join(a.images, f"{serial}_left", f"{i}.jpg"), "rb") as jf:
                    jpeg = jf.read()
                if a.bad == "bad_image" and i == 2 and k == 0:
                    jpeg = b"not a jpeg"
                summary["images"].setdefault(serial, []).append(hashlib.sha256(jpeg).hexdigest())
                msg = {"timestamp": ts, "format": "jpeg", "data": base64.b64encode(jpeg).decode()}
                if a.variant == "flat":
                    msg["frame_id"] = f"{serial}_left"
                w.add_message(ch[serial], log_time=log, publish_time=log, data=json.dumps(msg).encode())
        if a.variant == "wrapped":
            for k, v in f.attrs.items():
                v = v.item() if hasattr(v, "item") else v
                if isinstance(v, bytes):
                    v = v.decode()
                if isinstance(v, (str, int, float, bool)):
                    w.add_metadata(k, {"value": str(v)})
        w.finish()
        summary["steps"] = n
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
