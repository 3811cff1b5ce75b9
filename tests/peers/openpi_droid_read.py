"""A `labrig export lerobot --schema openpi-droid` dataset read the way openpi's
`pi05_droid_finetune` reads its LeRobot dataset (openpi is not on PyPI; its data path is
reproduced here from its source, src/openpi/training/config.py LeRobotDROIDDataConfig,
data_loader.py, policies/droid_policy.py): LeRobot 0.3.3's LeRobotDataset (format v2.1, what
openpi's pinned LeRobot reads) with `delta_timestamps = {"actions": [t / fps for t in
range(16)]}`, the repack (openpi key <- dataset key), the prompt from the frame's task, the
state as joint_position + gripper_position, the images as uint8 HWC.

  openpi_droid_read.py <root>

Prints one JSON object: per frame its episode, frame, state (8), actions chunk (16 x 8), padding,
prompt and the images' shapes and dtypes.
"""

import json
import sys

import numpy as np
from lerobot.datasets.lerobot_dataset import LeRobotDataset

ACTION_HORIZON = 16
# LeRobotDROIDDataConfig's repack: openpi's key <- the dataset's key.
REPACK = {
    "observation/exterior_image_1_left": "exterior_image_1_left",
    "observation/exterior_image_2_left": "exterior_image_2_left",
    "observation/wrist_image_left": "wrist_image_left",
    "observation/joint_position": "joint_position",
    "observation/gripper_position": "gripper_position",
    "actions": "actions",
    "prompt": "prompt",
}


def parse_image(img):
    # droid_policy._parse_image: float CHW in [0, 1] -> uint8 HWC.
    img = np.asarray(img)
    if np.issubdtype(img.dtype, np.floating):
        img = (255 * img).astype(np.uint8)
    if img.shape[0] == 3:
        img = np.transpose(img, (1, 2, 0))
    return img


def main():
    root = sys.argv[1]
    meta = LeRobotDataset("labrig/openpi_droid", root=root, video_backend="pyav").meta
    ds = LeRobotDataset(
        "labrig/openpi_droid",
        root=root,
        video_backend="pyav",
        delta_timestamps={"actions": [t / meta.fps for t in range(ACTION_HORIZON)]},
    )
    frames = []
    for i in range(len(ds)):
        item = ds[i]
        item["prompt"] = meta.tasks[int(item["task_index"])]  # PromptFromLeRobotTask
        data = {new: item[old] for new, old in REPACK.items()}
        state = np.concatenate([np.asarray(data["observation/joint_position"]),
                                np.atleast_1d(np.asarray(data["observation/gripper_position"]))])
        images = {k: parse_image(data[k]) for k in REPACK if "image" in k}
        frames.append({
            "episode": int(item["episode_index"]),
            "frame": int(item["frame_index"]),
            "state": state.tolist(),
            "actions": np.asarray(data["actions"]).tolist(),
            "pad": item["actions_is_pad"].tolist(),
            "prompt": data["prompt"],
            "images": {k: [list(v.shape), str(v.dtype)] for k, v in images.items()},
        })
    print(json.dumps({"fps": meta.fps, "codebase_version": meta.info["codebase_version"], "frames": frames}))


if __name__ == "__main__":
    main()
