"""Reads a DROID-layout MCAP with the PyPI `mcap` reader and json (no labrig code, no DROID code)
and, given a trajectory.h5, compares every value of the wrapped topics with the h5's (h5py).

usage: read_droid_mcap.py FILE [--h5 TRAJECTORY_H5]

Timesteps are grouped by log time, as DROID's reader does. Prints JSON: profile, channels
(schema name and encoding, message encoding, whether an image schema declares base64),
steps (per step: topics present, images' sha256 by topic, the /vr_controller payload), metadata records, and with --h5:
how many values were compared, every key that differed and the first mismatches.
"""
import argparse
import base64
import hashlib
import json
from collections import OrderedDict

from mcap.reader import make_reader

GROUPS = {
    "/robot_state": "observation/robot_state",
    "/action": "action",
    "/camera_extrinsics": "observation/camera_extrinsics",
    "/camera_intrinsics": "observation/camera_intrinsics",
    "/camera_type": "observation/camera_type",
}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("file")
    ap.add_argument("--h5", default=None)
    a = ap.parse_args()
    out = {"channels": {}, "steps": [], "metadata": {}}
    steps = OrderedDict()
    with open(a.file, "rb") as f:
        r = make_reader(f)
        out["profile"] = r.get_header().profile
        for schema, channel, message in r.iter_messages(log_time_order=True):
            c = out["channels"].setdefault(
                channel.topic,
                {
                    "schema": schema.name,
                    "schema_encoding": schema.encoding,
                    "message_encoding": channel.message_encoding,
                    "base64_declared": '"contentEncoding": "base64"' in schema.data.decode()
                    or '"contentEncoding":"base64"' in schema.data.decode(),
                    "count": 0,
                },
            )
            c["count"] += 1
            payload = json.loads(message.data)
            steps.setdefault(message.log_time, {})[channel.topic] = payload
        for m in r.iter_metadata():
            out["metadata"][m.name] = dict(m.metadata)
    for t, topics in steps.items():
        images = {
            k: hashlib.sha256(base64.b64decode(v["data"])).hexdigest() for k, v in topics.items() if k.startswith("/camera/")
        }
        out["steps"].append({"log_time": t, "topics": sorted(topics), "images": images, "vr": topics.get("/vr_controller")})
    if a.h5:
        import h5py

        compared, mismatches, keys = 0, [], set()
        with h5py.File(a.h5, "r") as h:

            def walk(group, data, step, path):
                nonlocal compared
                for k, v in group.items():
                    if isinstance(v, h5py.Group):
                        walk(v, data.get(k, {}), step, f"{path}/{k}")
                        continue
                    want = v[step].tolist()
                    got = data.get(k)
                    compared += 1
                    if got != want:
                        keys.add(f"{path}/{k}")
                        if len(mismatches) < 5:
                            mismatches.append({"step": step, "key": f"{path}/{k}", "h5": want, "mcap": got})

            for i, (t, topics) in enumerate(steps.items()):
                for topic, group in GROUPS.items():
                    if group in h and topic in topics:
                        walk(h[group], topics[topic]["data"], i, group)
        out["h5"] = {"compared": compared, "mismatches": mismatches, "mismatched_keys": sorted(keys), "steps": len(steps)}
    print(json.dumps(out))


if __name__ == "__main__":
    main()
