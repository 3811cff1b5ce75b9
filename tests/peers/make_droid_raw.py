"""Writes DROID raw episodes for the dataset tests with h5py (DROID's own reader/writer),
independently of labrig's exporter.

usage: make_droid_raw.py ROOT < spec.json
spec: a JSON list of episodes, each {"name", "success", "uuid", "task", "steps",
"ext1": [x, y, z, rx, ry, rz], "ext2": [...], "grasp_step", "grasp_xyz": [x, y, z],
"accidental_step" (optional), "decoy_xyz"}: the end effector is at decoy_xyz for the
accidental 3-step close and at grasp_xyz from grasp_step on, where the gripper closes for good.
"""
import json
import os
import sys

import h5py
import numpy as np

root = sys.argv[1]
for ep in json.load(sys.stdin):
    d = os.path.join(root, "success" if ep["success"] else "failure", "2026-11-26", ep["name"])
    os.makedirs(d, exist_ok=True)
    t = ep["steps"]
    cart = np.zeros((t, 6))
    cart[:, :3] = [0.4, 0.0, 0.4]
    cart[:, 3:] = [np.pi, 0.0, 0.0]
    grip = np.zeros(t)
    a = ep.get("accidental_step")
    if a is not None:
        cart[a : a + 3, :3] = ep["decoy_xyz"]
        grip[a : a + 3] = 1.0
    g = ep["grasp_step"]
    if g is not None:
        cart[g:, :3] = ep["grasp_xyz"]
        grip[g:] = 0.9
    with h5py.File(os.path.join(d, "trajectory.h5"), "w") as f:
        f["observation/robot_state/cartesian_position"] = cart
        f["observation/robot_state/gripper_position"] = grip * 0.5  # stalled on the object
        f["action/gripper_position"] = grip
        f["observation/robot_state/joint_positions"] = np.zeros((t, 7))
        f.attrs["current_task"] = ep["task"]
    meta = {
        "uuid": ep["uuid"],
        "lab": ep["uuid"].split("+")[0],
        "user": "fixture",
        "building": "b1",
        "scene_id": 7,
        "current_task": ep["task"],
        "trajectory_length": t,
        "wrist_cam_serial": "13",
        "ext1_cam_serial": "21",
        "ext2_cam_serial": "22",
        "ext1_cam_extrinsics": ep["ext1"],
        "ext2_cam_extrinsics": ep["ext2"],
        "success": ep["success"],
    }
    with open(os.path.join(d, f"metadata_{ep['uuid']}.json"), "w") as f:
        json.dump(meta, f)
