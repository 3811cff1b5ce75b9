"""A LeRobot dataset written by LeRobot's own writer (LeRobotDataset.create / add_frame /
save_episode), with the LeRobot DROID port's keys (examples/port_datasets/port_droid.py), for
`labrig import lerobot`'s test. lerobot 0.4.x writes format v3.0 (episodes share one data file and
one MP4 per camera, AV1 by default); lerobot 0.3.x writes v2.1 (one of each per episode).

usage: lerobot_write.py <root> <episodes> <frames> <fps> <truth.json>

truth.json: per episode, per frame, what was written (state, action sub-keys, task, the image
block means) for the test to compare with what labrig imported.
"""

import json
import shutil
import sys
from pathlib import Path

import numpy as np
from lerobot.datasets.lerobot_dataset import LeRobotDataset

root, episodes, frames, fps, truth_path = Path(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), Path(sys.argv[5])
shutil.rmtree(root, ignore_errors=True)
H, W = 48, 64
JOINTS = [f"joint_{i}" for i in range(7)]
POSE = ["x", "y", "z", "roll", "pitch", "yaw"]
video = {"dtype": "video", "shape": (H, W, 3), "names": ["height", "width", "channels"]}
f32 = lambda names: {"dtype": "float32", "shape": (len(names),), "names": names}  # noqa: E731
features = {
    "observation.images.exterior_1_left": video,
    "observation.images.wrist_left": video,
    # Stored in the Parquet as PNG (dtype image), as openpi's DROID converter stores its cameras.
    "observation.images.exterior_2_left": {"dtype": "image", "shape": (H, W, 3), "names": ["height", "width", "channels"]},
    "observation.state": f32(JOINTS + ["gripper"]),
    "observation.state.joint_position": f32(JOINTS),
    "observation.state.cartesian_position": f32(POSE),
    "observation.state.gripper_position": f32(["gripper_position"]),
    "action": f32(JOINTS + ["gripper"]),
    "action.joint_position": f32(JOINTS),
    "action.gripper_position": f32(["gripper_position"]),
    "action.cartesian_position": f32(POSE),
    "action.cartesian_velocity": f32(POSE),
    "action.joint_velocity": f32(JOINTS),
    "action.gripper_velocity": f32(["gripper_velocity"]),
    "camera_extrinsics.exterior_1_left": f32(POSE),
    # The port's per-frame copies of its episode metadata.
    "is_episode_successful": {"dtype": "bool", "shape": (1,), "names": None},
    "building": {"dtype": "string", "shape": (1,), "names": None},
    "collector_id": {"dtype": "string", "shape": (1,), "names": None},
}
SCALARS = ["observation.state.gripper_position", "action.gripper_position", "action.gripper_velocity", "is_episode_successful"]
v4 = "vcodec" in LeRobotDataset.create.__code__.co_varnames
ds = LeRobotDataset.create(repo_id="local/droid_port_like", root=root, fps=fps, features=features, robot_type="Franka", use_videos=True)

HOME = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])
truth = []


def blocks(img):
    """8x8 block means per channel in [0, 1], as the Rust test computes them."""
    h, w = img.shape[0] // 8, img.shape[1] // 8
    return [[[float(img[by * h:(by + 1) * h, bx * w:(bx + 1) * w, c].mean() / 255.0) for bx in range(8)] for by in range(8)] for c in range(3)]


for ep in range(episodes):
    task = f"put the cube in the bowl ({ep})"
    ext = np.array([0.3 + 0.01 * ep, -0.4, 0.5, -2.0, 0.1, 0.2], np.float32)
    rows = []
    for f in range(frames):
        t = f / frames
        # A slow joint-space motion; the action is the next frame's joints (as a recording's).
        joints_at = lambda t: (HOME + 0.1 * np.sin(np.pi * t + np.arange(7) * 0.3 + ep)).astype(np.float32)  # noqa: E731
        q, aq = joints_at(t), joints_at((f + 1) / frames)
        g = np.float32(0.5 + 0.5 * np.sin(2 * np.pi * t + ep))
        pose = np.array([0.4 + 0.1 * t, 0.05 * ep, 0.3, np.pi, 0.0, 0.1 * t], np.float32)
        img = np.zeros((H, W, 3), np.uint8)
        img[:, :, 0] = 40 + 4 * f + 30 * ep
        img[:, : W // 2, 1] = 200
        img[(2 * f) % H:(2 * f) % H + 6, :, 2] = 255
        wrist = (255 - img).copy()
        side = np.roll(img, 7 * f, axis=1)
        frame = {
            "observation.images.exterior_1_left": img,
            "observation.images.wrist_left": wrist,
            "observation.images.exterior_2_left": side,
            "observation.state": np.concatenate([q, [g]]).astype(np.float32),
            "observation.state.joint_position": q,
            "observation.state.cartesian_position": pose,
            "observation.state.gripper_position": np.array([g], np.float32),
            "action": np.concatenate([aq, [g]]).astype(np.float32),
            "action.joint_position": aq,
            "action.gripper_position": np.array([g], np.float32),
            "action.cartesian_position": pose + 0.001,
            "action.cartesian_velocity": np.full(6, 0.1 * ep, np.float32),
            "action.joint_velocity": np.full(7, -0.2, np.float32),
            "action.gripper_velocity": np.array([0.3], np.float32),
            "camera_extrinsics.exterior_1_left": ext,
            # The last episode failed (the port keeps failures too).
            "is_episode_successful": np.array([ep != episodes - 1], bool),
            "building": f"lab {ep}",
            "collector_id": "c0ffee",
        }
        rows.append({
            "joints": q.tolist(), "gripper": float(g), "cartesian": pose.tolist(),
            "action_joints": aq.tolist(), "action_cartesian": (pose + 0.001).tolist(),
            "ext1": blocks(img), "wrist": blocks(wrist), "ext2": blocks(side),
        })
        if v4:
            ds.add_frame({**frame, "task": task})
        else:
            ds.add_frame(frame, task=task)
    # lerobot 0.4.4 and 0.3.3 with numpy 2.x cannot store a shape-(1,) float feature (datasets'
    # Value encoder calls float() on a 1-element array): their own writer needs 0-d values here.
    for k in SCALARS:
        ds.episode_buffer[k] = [np.asarray(v).reshape(()) for v in ds.episode_buffer[k]]
    ds.save_episode()
    truth.append({"task": task, "extrinsics_ext1": ext.tolist(), "success": ep != episodes - 1, "building": f"lab {ep}", "frames": rows})
if hasattr(ds, "finalize"):
    ds.finalize()
truth_path.write_text(json.dumps({"fps": fps, "episodes": truth}))
print(f"wrote {episodes} episodes x {frames} frames to {root}")
