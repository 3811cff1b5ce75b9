"""Checks a DROID raw dataset root the way DROID's own tooling reads it: h5py for
trajectory.h5, json for metadata_<uuid>.json, ffprobe for the MP4s.

    python check_droid.py <droid_root>

Prints one JSON object per episode (keys, shapes, dtypes, frame counts) and exits 1 with
the problems on stderr when any episode differs from DROID's layout (FACTS.md, "DROID's
formats"). Written from DROID's format, not from labrig's code: the expected key set is
spelled out here.
"""

import json
import math
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np

ROBOT_STATE = {
    "cartesian_position": (6,),
    "gripper_position": (),
    "joint_positions": (7,),
    "joint_velocities": (7,),
    "joint_torques_computed": (7,),
    "prev_joint_torques_computed": (7,),
    "prev_joint_torques_computed_safened": (7,),
    "motor_torques_measured": (7,),
    "prev_controller_latency_ms": (),
}
ACTION = {
    "cartesian_velocity": (6,),
    "cartesian_position": (6,),
    "joint_velocity": (7,),
    "joint_position": (7,),
    "gripper_velocity": (),
    "gripper_position": (),
    "target_cartesian_position": (6,),
    "target_gripper_position": (),
}
CONTROL = ["step_start", "policy_start", "sleep_start", "control_start", "step_end"]
DROID_FIELDS = [
    "uuid", "lab", "user", "user_id", "date", "timestamp", "hdf5_path", "building", "scene_id",
    "success", "robot_serial", "droid_version", "current_task", "trajectory_length",
]
ROLES = ["wrist", "ext1", "ext2"]


def euler_matrix(rx, ry, rz):
    """Extrinsic xyz Euler angles (scipy's 'xyz') -> rotation matrix."""
    cx, sx, cy, sy, cz, sz = math.cos(rx), math.sin(rx), math.cos(ry), math.sin(ry), math.cos(rz), math.sin(rz)
    rot_x = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    rot_y = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rot_z = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rot_z @ rot_y @ rot_x


def pose(v):
    t = np.eye(4)
    t[:3, :3] = euler_matrix(*v[3:])
    t[:3, 3] = v[:3]
    return t


def frames(mp4):
    out = subprocess.run(
        ["ffprobe", "-v", "error", "-select_streams", "v:0", "-count_frames",
         "-show_entries", "stream=nb_read_frames,codec_name", "-of", "json", str(mp4)],
        capture_output=True, text=True, check=True)
    s = json.loads(out.stdout)["streams"][0]
    return int(s["nb_read_frames"]), s["codec_name"]


def check_episode(root, h5_path, problems):
    ep = h5_path.parent
    report = {"dir": str(ep.relative_to(root))}
    metas = sorted(ep.glob("metadata_*.json"))
    if len(metas) != 1:
        problems.append(f"{ep}: {len(metas)} metadata_*.json files")
        return report
    meta = json.loads(metas[0].read_text())
    with h5py.File(h5_path, "r") as f:
        datasets = {}
        f.visititems(lambda name, obj: datasets.__setitem__(name, obj) if isinstance(obj, h5py.Dataset) else None)
        n = f["action/joint_position"].shape[0]
        report["steps"] = n
        serials = sorted(k for k in f["observation/camera_type"].keys())
        report["serials"] = serials
        hand = [s for s in serials if f[f"observation/camera_type/{s}"][0] == 0]
        expected = {}
        for k, shape in ROBOT_STATE.items():
            expected[f"observation/robot_state/{k}"] = ((n, *shape), "float64")
        expected["observation/robot_state/prev_command_successful"] = ((n,), "bool")
        for k, shape in ACTION.items():
            expected[f"action/{k}"] = ((n, *shape), "float64")
        for k in CONTROL:
            expected[f"observation/timestamp/control/{k}"] = ((n,), "int64")
        for k in ["robot_timestamp_seconds", "robot_timestamp_nanos"]:
            expected[f"observation/timestamp/robot_state/{k}"] = ((n,), "int64")
        for s in serials:
            expected[f"observation/camera_type/{s}"] = ((n,), "int64")
            for k in ["estimated_capture", "frame_received"]:
                expected[f"observation/timestamp/cameras/{s}_{k}"] = ((n,), "int64")
            expected[f"observation/camera_extrinsics/{s}_left"] = ((n, 6), "float64")
            expected[f"observation/camera_intrinsics/{s}_left"] = ((n, 3, 3), "float64")
        for s in hand:
            expected[f"observation/camera_extrinsics/{s}_left_gripper_offset"] = ((n, 6), "float64")
        expected["observation/controller_info/movement_enabled"] = ((n,), "bool")
        # labrig's own key (who acted at each step), not DROID's: its readers skip it
        expected["observation/controller_info/labrig_action_source"] = ((n,), "int64")
        for k in sorted(set(expected) - set(datasets)):
            problems.append(f"{h5_path}: missing {k}")
        for k in sorted(set(datasets) - set(expected)):
            problems.append(f"{h5_path}: unexpected {k}")
        for k in sorted(set(expected) & set(datasets)):
            shape, dtype = expected[k]
            d = datasets[k]
            if d.shape != shape or str(d.dtype) != dtype:
                problems.append(f"{h5_path}: {k} is {d.dtype}{d.shape}, expected {dtype}{shape}")
        report["datasets"] = len(datasets)
        if problems:
            return report
        # Values as DROID defines them.
        grip = f["observation/robot_state/gripper_position"][:]
        if grip.min() < 0 or grip.max() > 1:
            problems.append(f"{h5_path}: gripper_position outside 0..1 (0 open, 1 closed)")
        for k in ROBOT_STATE:
            if not np.isfinite(f[f"observation/robot_state/{k}"][:]).all():
                problems.append(f"{h5_path}: {k} not finite")
        start = f["observation/timestamp/control/step_start"][:]
        if (np.diff(start) <= 0).any():
            problems.append(f"{h5_path}: control step_start not increasing")
        for s in serials:
            want = 0 if s in hand else 1
            if (f[f"observation/camera_type/{s}"][:] != want).any():
                problems.append(f"{h5_path}: camera_type/{s} not constant")
            k = f[f"observation/camera_intrinsics/{s}_left"][0]
            if not (k[0, 0] > 0 and k[1, 1] > 0 and k[2, 2] == 1):
                problems.append(f"{h5_path}: camera_intrinsics/{s}_left is not a pinhole K: {k}")
        # The hand camera moves with the gripper: its extrinsics are the TCP pose composed
        # with its gripper offset.
        cart = f["observation/robot_state/cartesian_position"][:]
        for s in hand:
            off = pose(f[f"observation/camera_extrinsics/{s}_left_gripper_offset"][0])
            ext = f[f"observation/camera_extrinsics/{s}_left"][:]
            worst = max(np.abs(pose(cart[i]) @ off - pose(ext[i])).max() for i in range(n))
            report["hand_extrinsics_error"] = float(worst)
            if worst > 1e-9:
                problems.append(f"{h5_path}: {s}_left is not cartesian_position x gripper offset ({worst})")
        attrs = dict(f.attrs)
        report["attrs"] = sorted(attrs)
        for k in ["user", "building", "scene_id", "current_task"]:
            if not isinstance(attrs.get(k), str):
                problems.append(f"{h5_path}: attribute {k} is {type(attrs.get(k)).__name__}, expected str")
        for k in ["success", "failure"]:
            if not isinstance(attrs.get(k), (bool, np.bool_)):
                problems.append(f"{h5_path}: attribute {k} is {type(attrs.get(k)).__name__}, expected bool")
    # Metadata: every DROID field, and the paths it names exist.
    for k in DROID_FIELDS + [f"{r}_{x}" for r in ROLES for x in ["cam_serial", "cam_extrinsics", "svo_path", "mp4_path"]]:
        if k not in meta:
            problems.append(f"{metas[0]}: no `{k}`")
    if meta.get("trajectory_length") != n:
        problems.append(f"{metas[0]}: trajectory_length {meta.get('trajectory_length')} != {n} steps")
    if metas[0].name != f"metadata_{meta.get('uuid')}.json":
        problems.append(f"{metas[0]}: file name does not carry the uuid {meta.get('uuid')}")
    if not meta.get("uuid", "").startswith(f"{meta.get('lab')}+{meta.get('user_id')}+"):
        problems.append(f"{metas[0]}: uuid is not <lab>+<user_id>+<timestamp>")
    if (root / meta.get("hdf5_path", "")).resolve() != h5_path.resolve():
        problems.append(f"{metas[0]}: hdf5_path {meta.get('hdf5_path')} does not name {h5_path}")
    if meta.get("success") != bool(attrs["success"]):
        problems.append(f"{metas[0]}: success differs from trajectory.h5's")
    if ep.parent.parent.name != ("success" if meta.get("success") else "failure"):
        problems.append(f"{ep}: not under {'success' if meta.get('success') else 'failure'}/")
    # One MP4 per camera, named by serial, a frame per step.
    report["mp4"] = {}
    for s in serials:
        mp4 = ep / "recordings" / "MP4" / f"{s}.mp4"
        if not mp4.is_file():
            problems.append(f"{ep}: no recordings/MP4/{s}.mp4")
            continue
        count, codec = frames(mp4)
        report["mp4"][s] = {"frames": count, "codec": codec}
        if count != n:
            problems.append(f"{mp4}: {count} frames for {n} steps")
    for r in ROLES:
        p = meta.get(f"{r}_mp4_path")
        if p is not None and not (root / p).is_file():
            problems.append(f"{metas[0]}: {r}_mp4_path {p} does not exist")
    return report


def main():
    root = Path(sys.argv[1])
    problems = []
    episodes = sorted(root.rglob("trajectory.h5"))
    if not episodes:
        problems.append(f"{root}: no trajectory.h5 under it")
    for h5 in episodes:
        print(json.dumps(check_episode(root, h5, problems)), flush=True)
    for p in problems:
        print(p, file=sys.stderr)
    sys.exit(1 if problems else 0)


if __name__ == "__main__":
    main()
