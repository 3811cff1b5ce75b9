#!/usr/bin/env python3
"""DROID-scale indexing on a Ray cluster (issue 36): one Ray task per shard, then the merge.

Each task runs the labrig binary on a worker:

    labrig dataset index <roots>... --out <out>/parts --shard i/N --json

so the N parts land in one folder on the disk every node shares; then one task runs

    labrig dataset merge <out>/parts --out <out>/index --json

which checks that the parts are one complete set and writes the index partitioned by source
format (<out>/index/source_format=<fmt>/..., <out>/index/_index.json). A shard whose worker is
lost (the node dies, the worker is killed, Ray's memory monitor kills it past 95% of the node's
memory) is retried by Ray (--max-retries); so is a shard whose command fails (retry_exceptions).
Shards that still fail are named at the end and the run exits 1 without merging: run it again
and only what is missing is redone (an unchanged episode's rows are reused from its part).

Run it against a running cluster (the head's GCS address; `auto` = $RAY_ADDRESS or the head
started with Ray's default temp dir; a cluster with token authentication needs its token:
--auth-token-path or $RAY_AUTH_TOKEN_PATH):

    scripts/scale/ray_local.sh start /tmp/ray-idx 22600      # or any cluster
    source /tmp/ray-idx/env.sh                                # RAY_ADDRESS, the token
    python scripts/scale/ray_index.py /data/droid_raw /data/droid_rlds --out /data/idx \\
        --shards 64 --labrig /opt/labrig/bin/labrig --json

or start a local one just for this run, bound to 127.0.0.1:

    python scripts/scale/ray_index.py <roots>... --out <out> --shards 4 --local

or submit it as a Ray job (the driver then runs on the head, in the head's environment: its
address and token; the job server is the dashboard's port, RAY_API_SERVER_ADDRESS in env.sh):

    source /tmp/ray-idx/env.sh
    ray job submit --working-dir scripts/scale -- \\
        python ray_index.py /data/droid_raw --out /data/idx --shards 64 \\
        --labrig /opt/labrig/bin/labrig --json

Paths (roots, --out, a --labrig with a slash) are made absolute on the driver: every node must
see them at the same place (a shared disk) and have the labrig binary (`labrig dataset ...`
runs labrig-dataset beside it). Progress goes to stderr with --json, else stdout; with --json
the summary is one JSON object on stdout.
"""

import argparse
import json
import os
import secrets
import shutil
import socket
import subprocess
import sys
import tempfile
import time


def size_bytes(text):
    """`2G`, `512M`, `1048576` -> bytes."""
    t = text.strip().upper().removesuffix("B").removesuffix("I")
    mult = {"K": 1 << 10, "M": 1 << 20, "G": 1 << 30, "T": 1 << 40}
    if t and t[-1] in mult:
        return int(float(t[:-1]) * mult[t[-1]])
    return int(t)


def parse_args(argv):
    p = argparse.ArgumentParser(
        description="Index episodes on a Ray cluster: one `labrig dataset index --shard i/N` task per shard, then `labrig dataset merge`."
    )
    p.add_argument("roots", nargs="+", help="folders searched for episodes (seen by every node at the same path)")
    p.add_argument("--out", required=True, help="output folder: <out>/parts (the N parts) and <out>/index (merged)")
    p.add_argument("--shards", type=int, required=True, help="N, the number of shards (tasks)")
    p.add_argument("--labrig", default="labrig", help="the labrig binary on the workers (default: `labrig` on their PATH)")
    p.add_argument(
        "--address",
        default="auto",
        help="the cluster's GCS address (host:port), or `auto` ($RAY_ADDRESS, or a head started with the default temp dir)",
    )
    p.add_argument(
        "--auth-token-path",
        default=os.environ.get("RAY_AUTH_TOKEN_PATH"),
        help="the cluster's token file (Ray's token authentication; default $RAY_AUTH_TOKEN_PATH; "
        "ray_local.sh writes <temp dir>/auth_token)",
    )
    p.add_argument(
        "--local",
        action="store_true",
        help="start a local Ray for this run instead, bound to 127.0.0.1 (its ports are Ray's: random, and the "
        "fixed 44217, 44227, 52365: one such run at a time; for more, ray_local.sh heads with their own ports)",
    )
    p.add_argument("--local-num-cpus", type=int, default=None, help="--local: the CPUs it offers (default: all)")
    p.add_argument("--num-cpus-per-task", type=float, default=1.0, help="CPUs each shard's task reserves (default 1)")
    p.add_argument(
        "--memory-per-task",
        default="1G",
        help="memory each shard's task reserves for scheduling, bytes or with K/M/G (default 1G)",
    )
    p.add_argument(
        "--max-retries",
        type=int,
        default=3,
        help="retries of a shard whose worker is lost or whose command fails (default 3)",
    )
    p.add_argument("--task-timeout", type=float, default=None, help="seconds a shard's command may run (then it fails and is retried)")
    p.add_argument("--extra", action="append", default=[], help="an argument passed on to `labrig dataset index` (repeatable), e.g. --extra=--extrinsics=/data/cam2base_extrinsics.json")
    p.add_argument("--no-merge", action="store_true", help="index the shards only")
    p.add_argument("--json", action="store_true", help="print the summary as JSON on stdout")
    a = p.parse_args(argv)
    if a.shards < 1:
        p.error("--shards must be at least 1")
    if a.max_retries < 0:
        p.error("--max-retries must be 0 or more")
    a.memory_per_task = size_bytes(a.memory_per_task)
    return a


def part_name(i, n):
    return f"part-{i:05d}-of-{n:05d}"


def is_loopback(address):
    host = address.split("://", 1)[-1].rsplit(":", 1)[0].strip("[]")
    return host in ("127.0.0.1", "localhost", "::1")


class ShardFailed(Exception):
    """The labrig command of a shard exited non-zero (or timed out); Ray retries it."""


def run_labrig(argv, timeout):
    try:
        p = subprocess.run(argv, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        raise ShardFailed(f"`{' '.join(argv[:3])} ...` ran past {timeout} s")
    except OSError as e:
        raise ShardFailed(f"cannot run {argv[0]}: {e}")
    if p.returncode != 0:
        tail = (p.stderr or p.stdout).strip().splitlines()[-5:]
        raise ShardFailed(f"`{' '.join(argv[:3])} ...` exited {p.returncode}: " + " | ".join(tail))
    try:
        return json.loads(p.stdout)
    except ValueError:
        raise ShardFailed(f"`{' '.join(argv[:3])} ...` printed no JSON: {p.stdout[-300:]!r}")


def index_shard(labrig, roots, parts, i, n, extra, attempts_dir, timeout):
    """One shard (runs in a Ray worker). Each attempt appends a line to its attempts log on
    the shared disk, so the driver can tell a retried shard from one that ran once."""
    name = part_name(i, n)
    log = os.path.join(attempts_dir, name + ".log")
    with open(log, "a") as f:
        f.write(f"{time.time():.3f} {socket.gethostname()} {os.getpid()}\n")
    with open(log) as f:
        attempt = sum(1 for _ in f)
    t0 = time.time()
    report = run_labrig([labrig, "dataset", "index", *roots, "--out", parts, "--shard", f"{i}/{n}", "--json", *extra], timeout)
    return {
        "shard": name,
        "attempt": attempt,
        "host": socket.gethostname(),
        "seconds": time.time() - t0,
        "report": report,
    }


def merge(labrig, parts, index, timeout):
    t0 = time.time()
    report = run_labrig([labrig, "dataset", "merge", parts, "--out", index, "--json"], timeout)
    return {"seconds": time.time() - t0, "host": socket.gethostname(), "report": report}


def main(argv=None):
    a = parse_args(sys.argv[1:] if argv is None else argv)
    say_to = sys.stderr if a.json else sys.stdout

    def say(msg):
        print(msg, file=say_to, flush=True)

    roots = [os.path.abspath(r) for r in a.roots]
    out = os.path.abspath(a.out)
    labrig = os.path.abspath(a.labrig) if os.sep in a.labrig else a.labrig
    if os.sep not in labrig and shutil.which(labrig) is None:
        say(f"ray_index: note: `{labrig}` is not on this machine's PATH; the workers must have it")
    parts, index, attempts_dir = (os.path.join(out, d) for d in ("parts", "index", "attempts"))
    os.makedirs(parts, exist_ok=True)
    # The attempts of this run only.
    shutil.rmtree(attempts_dir, ignore_errors=True)
    os.makedirs(attempts_dir)

    # Ray replaces a loopback node address by the machine's outward one unless "clusters" are
    # off (as on macOS/Windows); a driver of a loopback head (or --local) must stay on 127.0.0.1.
    address = os.environ.get("RAY_ADDRESS", "") if a.address == "auto" else a.address
    if a.local or is_loopback(address):
        os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    # Token authentication: the cluster's token, or for --local one of this run's own (a plain
    # local ray.init() would write ~/.ray/auth_token, which every later `ray start` on the
    # machine then silently enables token authentication with).
    token_dir = None
    if a.local and not a.auth_token_path:
        token_dir = tempfile.mkdtemp(prefix="ray-index-token-")
        a.auth_token_path = os.path.join(token_dir, "auth_token")
        fd = os.open(a.auth_token_path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w") as f:
            f.write(secrets.token_hex(32))
    if a.auth_token_path:
        os.environ["RAY_AUTH_MODE"] = "token"
        os.environ["RAY_AUTH_TOKEN_PATH"] = os.path.abspath(a.auth_token_path)
    import ray

    if a.local:
        ray.init(
            address="local",
            num_cpus=a.local_num_cpus,
            include_dashboard=False,
            _node_ip_address="127.0.0.1",
            object_store_memory=128 * 1024 * 1024,
            logging_level="WARNING",
            log_to_driver=False,
        )
    else:
        try:
            ray.init(address=a.address, logging_level="WARNING", log_to_driver=False)
        except (ConnectionError, RuntimeError) as e:
            cause = e.__cause__ or e
            lines = [l.strip() for l in str(cause).splitlines() if l.strip()]
            why = lines[-1] if lines else type(cause).__name__
            say(f"ray_index: cannot join the cluster at {a.address}: {why[:400]}")
            if not a.auth_token_path:
                say("ray_index: (a cluster with token authentication needs --auth-token-path or RAY_AUTH_TOKEN_PATH)")
            return 2

    resources = {"num_cpus": a.num_cpus_per_task, "memory": a.memory_per_task}
    task = ray.remote(index_shard)
    t0 = time.time()
    refs = {
        task.options(
            **resources,
            max_retries=a.max_retries,
            retry_exceptions=True,
            name=f"labrig-index-{part_name(i, a.shards)}",
        ).remote(labrig, roots, parts, i, a.shards, a.extra, attempts_dir, a.task_timeout): i
        for i in range(a.shards)
    }
    say(
        f"ray_index: {a.shards} shards of {', '.join(roots)} on {ray.cluster_resources().get('CPU', 0):g} CPUs "
        f"({a.num_cpus_per_task:g} CPU, {a.memory_per_task / 2**20:.0f} MiB per task, max_retries {a.max_retries})"
    )
    done, failed = [], []
    pending = list(refs)
    while pending:
        ready, pending = ray.wait(pending, num_returns=1)
        for ref in ready:
            i = refs[ref]
            name = part_name(i, a.shards)
            try:
                r = ray.get(ref)
            except Exception as e:  # RayTaskError(ShardFailed), WorkerCrashedError, ...
                attempts = _attempts(attempts_dir, name)
                why = f"{type(e).__name__}: {str(e).strip().splitlines()[-1] if str(e).strip() else ''}"
                failed.append({"shard": name, "attempts": attempts, "error": why})
                say(f"  {name}: FAILED after {attempts} attempt(s): {why}")
                continue
            rep = r["report"]
            r["attempts"] = _attempts(attempts_dir, name)
            done.append(r)
            retried = f", attempt {r['attempt']} (retried)" if r["attempt"] > 1 else ""
            say(
                f"  {name}: {rep.get('indexed', 0) + rep.get('unchanged', 0)} episodes from {rep.get('in_shard', 0)} sources "
                f"({rep.get('indexed', 0)} indexed, {rep.get('unchanged', 0)} unchanged, {len(rep.get('bad', []))} bad sources) "
                f"in {r['seconds']:.2f} s on {r['host']}{retried} [{len(done) + len(failed)}/{a.shards}]"
            )
    index_seconds = time.time() - t0
    done.sort(key=lambda r: r["shard"])
    failed.sort(key=lambda r: r["shard"])
    summary = {
        "shards": a.shards,
        "roots": roots,
        "parts": parts,
        "index": None,
        "resources_per_task": resources,
        "max_retries": a.max_retries,
        "ok": [
            {
                "shard": r["shard"],
                "attempts": r["attempts"],
                "host": r["host"],
                "seconds": r["seconds"],
                "sources": r["report"].get("in_shard"),
                "episodes": r["report"].get("indexed", 0) + r["report"].get("unchanged", 0),
                "indexed": r["report"].get("indexed"),
                "unchanged": r["report"].get("unchanged"),
                "bad": len(r["report"].get("bad", [])),
                "by_format": r["report"].get("by_format"),
                "episodes_per_s": r["report"].get("episodes_per_s"),
                "mb_per_s": r["report"].get("mb_per_s"),
                "labrig_seconds": r["report"].get("seconds"),
            }
            for r in done
        ],
        "retried": [{"shard": r["shard"], "attempts": r["attempts"]} for r in done if r["attempts"] > 1],
        "failed": failed,
        "sources": sum(r["report"].get("in_shard", 0) for r in done),
        "episodes": sum(r["report"].get("indexed", 0) + r["report"].get("unchanged", 0) for r in done),
        "index_seconds": index_seconds,
        "merge": None,
    }
    for r in summary["retried"]:
        say(f"ray_index: {r['shard']} was retried: {r['attempts']} attempts")
    code = 0
    if failed:
        say(
            f"ray_index: {len(failed)} of {a.shards} shards failed: {', '.join(f['shard'] for f in failed)}; "
            "not merged (run again: only what is missing is redone)"
        )
        code = 1
    elif not a.no_merge:
        m = ray.remote(merge).options(num_cpus=a.num_cpus_per_task, max_retries=a.max_retries, retry_exceptions=True)
        try:
            summary["merge"] = ray.get(m.remote(labrig, parts, index, a.task_timeout))
            summary["index"] = index
            say(f"ray_index: merged {a.shards} parts into {index} in {summary['merge']['seconds']:.2f} s")
        except Exception as e:
            summary["merge_error"] = f"{type(e).__name__}: {str(e).strip().splitlines()[-1]}"
            say(f"ray_index: the merge failed: {summary['merge_error']}")
            code = 1
    summary["seconds"] = time.time() - t0
    say(
        f"ray_index: {summary['episodes']} episodes from {summary['sources']} sources in {len(done)}/{a.shards} shards, "
        f"{index_seconds:.2f} s indexing, {summary['seconds']:.2f} s in all"
    )
    if a.json:
        print(json.dumps(summary))
    ray.shutdown()
    if token_dir:
        shutil.rmtree(token_dir, ignore_errors=True)
    return code


def _attempts(attempts_dir, name):
    try:
        with open(os.path.join(attempts_dir, name + ".log")) as f:
            return sum(1 for _ in f)
    except OSError:
        return 0


if __name__ == "__main__":
    sys.exit(main())
