"""openpi's own client and server (PyPI openpi-client 0.1.2, openpi-server 0.1.0) as labrig's
test peers.

  openpi_peer.py serve --chunks FILE [--fail-on N] [--log FILE] [--metadata JSON] [--port P]
      Runs the upstream WebsocketPolicyServer on 127.0.0.1 (P or a free port, printed as the first
      stdout line: {"port": P}) serving a test policy: request k (from 0) gets chunk
      k % len(chunks) of FILE (a JSON list of N x 8 lists); with --fail-on N, request N raises
      (the server's error frame). --log writes one JSON line per request: the keys, shapes and
      dtypes it received, the joint and gripper positions, the prompt, the actions it returned.

  openpi_peer.py client --url URL [--requests N] [--horizon H]
      openpi's WebsocketClientPolicy (and ActionChunkBroker over it) query URL with DROID
      observations (random 224x224 images, joints, gripper, prompt); prints one JSON object:
      the server metadata, each reply's action shape / dtype / finiteness / server_timing, the
      broker's per-step action shapes, and the error text of a bad request.
"""

import argparse
import json
import socket
import sys
import time

import numpy as np


def free_port():
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


def describe(obs):
    out = {}
    for k, v in obs.items():
        if isinstance(v, np.ndarray):
            out[k] = {"shape": list(v.shape), "dtype": v.dtype.str}
        else:
            out[k] = {"type": type(v).__name__}
    return out


def serve(args):
    from openpi_client import base_policy
    from openpi_server import websocket_policy_server

    chunks = [np.asarray(c, dtype=np.float32) for c in json.load(open(args.chunks))]
    log = open(args.log, "a") if args.log else None

    class ChunkPolicy(base_policy.BasePolicy):
        def __init__(self):
            self.n = 0

        def infer(self, obs):
            k = self.n
            self.n += 1
            if args.fail_on is not None and k == args.fail_on:
                raise RuntimeError(f"test policy: request {k} fails on purpose")
            actions = chunks[k % len(chunks)]
            if log:
                rec = {
                    "request": k,
                    "keys": describe(obs),
                    "joint_position": np.asarray(obs.get("observation/joint_position", [])).tolist(),
                    "gripper_position": np.asarray(obs.get("observation/gripper_position", [])).tolist(),
                    "prompt": obs.get("prompt"),
                    "image_mean": float(np.asarray(obs["observation/exterior_image_1_left"]).mean())
                    if "observation/exterior_image_1_left" in obs
                    else None,
                    "actions": actions.tolist(),
                    "time": time.time(),
                }
                log.write(json.dumps(rec) + "\n")
                log.flush()
            return {"actions": actions, "policy_timing": {"infer_ms": 0.1}}

    port = args.port or free_port()
    metadata = json.loads(args.metadata) if args.metadata else {}
    server = websocket_policy_server.WebsocketPolicyServer(ChunkPolicy(), host="127.0.0.1", port=port, metadata=metadata)
    print(json.dumps({"port": port}), flush=True)
    server.serve_forever()


def client(args):
    from openpi_client import action_chunk_broker, websocket_client_policy

    rng = np.random.default_rng(0)

    def observation(drop=None):
        obs = {
            "observation/exterior_image_1_left": rng.integers(0, 256, (224, 224, 3), dtype=np.uint8),
            "observation/wrist_image_left": rng.integers(0, 256, (224, 224, 3), dtype=np.uint8),
            "observation/joint_position": np.array([0.0, -0.5, 0.0, -2.2, 0.0, 1.8, 0.8]),
            "observation/gripper_position": np.array([0.0]),
            "prompt": "put the cube in the bowl",
        }
        if drop:
            del obs[drop]
        return obs

    policy = websocket_client_policy.WebsocketClientPolicy(args.url)
    out = {"metadata": policy.get_server_metadata(), "replies": [], "broker": []}
    for _ in range(args.requests):
        t = time.monotonic()
        r = policy.infer(observation())
        a = np.asarray(r["actions"])
        out["replies"].append(
            {
                "shape": list(a.shape),
                "dtype": a.dtype.str,
                "finite": bool(np.isfinite(a).all()),
                "server_timing": r.get("server_timing"),
                "round_trip_ms": (time.monotonic() - t) * 1e3,
                "first_row": a[0].tolist(),
            }
        )
    broker = action_chunk_broker.ActionChunkBroker(policy, action_horizon=args.horizon)
    for _ in range(args.horizon + 1):
        r = broker.infer(observation())
        out["broker"].append(list(np.asarray(r["actions"]).shape))
    try:
        policy.infer(observation(drop="observation/wrist_image_left"))
        out["error"] = None
    except Exception as e:  # the server's error frame
        out["error"] = str(e)
    print(json.dumps(out))


def main():
    p = argparse.ArgumentParser()
    sub = p.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("serve")
    s.add_argument("--chunks", required=True)
    s.add_argument("--fail-on", type=int)
    s.add_argument("--log")
    s.add_argument("--metadata")
    s.add_argument("--port", type=int, help="this port (default: a free one)")
    c = sub.add_parser("client")
    c.add_argument("--url", required=True)
    c.add_argument("--requests", type=int, default=3)
    c.add_argument("--horizon", type=int, default=8)
    args = p.parse_args()
    serve(args) if args.cmd == "serve" else client(args)


if __name__ == "__main__":
    sys.exit(main())
