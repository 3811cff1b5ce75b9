"""LeRobot's own LeRobotDataset reading a dataset labrig exported: lerobot 0.4.4 (setup's
venv-lerobot-data) for format v3.0, lerobot 0.3.3 (venv-lerobot-v21) for v2.1; offline, the PyAV
video backend, an action chunk of 16 by delta_timestamps.

  lerobot_read.py <root>

Prints one JSON object: the dataset's episodes / frames / fps; per frame its episode, frame
index, timestamp, state, action chunk (16 x 8) with its padding flags, task, and for the first,
middle and last frame of each episode each camera's 8x8 block means (decoded, in [0, 1]); and
LeRobot's own statistics recomputed from the frames it read (compute_episode_stats per episode,
aggregate_stats), for the numeric features, to compare with the meta/stats.json labrig wrote.
"""

import json
import sys

import numpy as np
from lerobot.datasets.compute_stats import aggregate_stats, compute_episode_stats
from lerobot.datasets.lerobot_dataset import LeRobotDataset


def blocks(img):
    # (3, H, W) in [0, 1] -> 8 x 8 block means per channel.
    c, h, w = img.shape
    a = img[:, : h - h % 8, : w - w % 8].reshape(c, 8, (h - h % 8) // 8, 8, (w - w % 8) // 8)
    return a.mean(axis=(2, 4)).tolist()


def main():
    root = sys.argv[1]
    ds = LeRobotDataset("labrig/export", root=root, video_backend="pyav",
                        delta_timestamps={"action": [i / 20 for i in range(16)]})
    cams = [k for k in ds.meta.features if k.startswith("observation.images.")]
    numeric = [k for k, f in ds.meta.features.items() if f["dtype"] == "float32" or f["dtype"] == "int64"]
    frames = []
    per_episode = {}
    bounds = {}
    for ep in range(ds.num_episodes):
        if getattr(ds, "episode_data_index", None) is not None:  # 0.3.x (v2.1)
            bounds[ep] = (int(ds.episode_data_index["from"][ep]), int(ds.episode_data_index["to"][ep]))
        else:  # 0.4.x (v3.0)
            e = ds.meta.episodes[ep]
            bounds[ep] = (e["dataset_from_index"], e["dataset_to_index"])
    for i in range(len(ds)):
        it = ds[i]
        ep = int(it["episode_index"])
        lo, hi = bounds[ep]
        rec = {
            "episode": ep,
            "frame": int(it["frame_index"]),
            "timestamp": float(it["timestamp"]),
            "state": it["observation.state"].tolist(),
            "action": it["action"].tolist(),
            "pad": it["action_is_pad"].tolist(),
            "task": it["task"],
        }
        if i in (lo, (lo + hi) // 2, hi - 1):
            rec["blocks"] = {c: blocks(it[c].numpy()) for c in cams}
        frames.append(rec)
        d = per_episode.setdefault(ep, {k: [] for k in numeric})
        for k in numeric:
            v = it[k].numpy()
            if k == "action":
                v = v[0]  # the frame's own action (row 0 of its chunk)
            d[k].append(np.atleast_1d(v))
    stats = []
    for ep, d in per_episode.items():
        data = {k: np.stack(v) for k, v in d.items()}
        feats = {k: ds.meta.features[k] for k in data}
        stats.append(compute_episode_stats(data, feats))
    agg = aggregate_stats(stats)
    # v3.0 keeps each episode's statistics in its episodes table (`stats/<feature>/<stat>`), read
    # as LeRobot's dataset tools (delete_episodes, split_dataset) read them.
    episode_stats_file = []
    if getattr(ds, "episode_data_index", None) is None:
        from lerobot.datasets.dataset_tools import _load_episode_with_stats

        def plain(v):
            # pandas gives nested object arrays for the images' (3, 1, 1).
            if isinstance(v, np.ndarray) and v.dtype == object:
                return [plain(x) for x in v]
            return np.asarray(v).tolist()

        for ep in range(ds.num_episodes):
            per = {}
            for key, v in _load_episode_with_stats(ds, ep).items():
                if key.startswith("stats/"):
                    _, feature, stat = key.split("/")
                    per.setdefault(feature, {})[stat] = plain(v)
            episode_stats_file.append(per)
    import lerobot
    out = {
        "lerobot": getattr(lerobot, "__version__", "?"),
        "codebase_version": ds.meta.info["codebase_version"],
        "episodes": ds.num_episodes,
        "frames": len(ds),
        "fps": ds.fps,
        "cameras": cams,
        "frames_data": frames,
        "stats_lerobot": {k: {s: np.asarray(v).tolist() for s, v in d.items()} for k, d in agg.items()},
        "stats_file": {k: {s: np.asarray(v).tolist() for s, v in d.items()} for k, d in ds.meta.stats.items()},
        "episode_stats_lerobot": [{k: {s: np.asarray(v).tolist() for s, v in d.items()} for k, d in e.items()} for e in stats],
        "episode_stats_file": episode_stats_file,
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
