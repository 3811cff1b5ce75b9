#!/usr/bin/env python3
"""Keep CI's persistent target directory bounded: delete the build units no build uses.

Every change to the dependency graph, the workspace's path or a crate's features gives cargo
new unit hashes, and cargo never deletes the old units: the shared target directory grew to
56 GB in one day of commits (5,000 units, 730 of them in use) and a CI run failed with "No
space left on device" half way through its build. This script records, after a successful
build and lint, the hashes of every unit that build, its tests and clippy use (cargo's own
`--message-format=json` list, asked of the builds just made, so it costs seconds), and deletes
from the dev profile's deps/, build/, .fingerprint/ and examples/ every unit whose hash the
record lacks.

  prune_target.py record   after a successful build and lint: write the record anew
  prune_target.py prune    delete what the record lacks (no record: nothing, unless the disk has
                           under 20 GB free: then the whole debug build, for a cold one)

Deleting a unit that a later build wants only costs its rebuild: cargo finds the output gone
and compiles it again. Only .ci/run uses it (a developer's per-crate builds, whose feature sets
give other hashes, would be deleted by the next run).
"""
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

# The builds the suite makes (scripts/test.sh); `cargo test --no-run` (nextest) uses the very
# units of `build --all-targets`, clippy its own check units.
BUILDS = [
    ["cargo", "build", "--workspace", "--all-targets", "--locked"],
    ["cargo", "clippy", "--workspace", "--all-targets", "--locked", "-q", "--", "-D", "warnings"],
]
HASH = re.compile(r"-([0-9a-f]{16})(?=[./]|$)")
PRUNED = ["deps", "build", ".fingerprint", "examples"]


def target_dir():
    target = os.environ.get("CARGO_TARGET_DIR")
    if not target:
        sys.exit("prune_target.py: CARGO_TARGET_DIR is not set")
    return Path(target)


def record_path():
    return target_dir() / "labrig-live-units.txt"


def unit_hash(name):
    found = HASH.search(name)
    return found.group(1) if found else None


def live_units():
    """The hashes of every unit the suite's builds use, as cargo lists them.

    A binary is listed by its uplifted name alone (target/debug/labrig, no hash): its unit is
    the file of deps/ that is the same inode (cargo hard-links the two)."""
    live = set()
    by_inode = {}
    for entry in (target_dir() / "debug" / "deps").iterdir():
        st = entry.lstat()
        by_inode[(st.st_dev, st.st_ino)] = entry.name
    for build in BUILDS:
        cmd = build[:2] + ["--message-format=json"] + build[2:]
        out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
        for line in out.splitlines():
            msg = json.loads(line)
            paths = []
            if msg.get("reason") == "compiler-artifact":
                paths = msg["filenames"]
            elif msg.get("reason") == "build-script-executed":
                paths = [msg["out_dir"]]
            for path in paths:
                found = unit_hash(path)
                if found is None and os.path.exists(path):
                    st = os.stat(path)
                    found = unit_hash(by_inode.get((st.st_dev, st.st_ino), ""))
                if found:
                    live.add(found)
    return live


def record():
    live = live_units()
    if not live:
        sys.exit("prune_target.py: cargo listed no unit: nothing recorded")
    record_path().write_text("".join(f"{h}\n" for h in sorted(live)))
    print(f"prune_target: {len(live)} units in use recorded")


def size(path):
    if path.is_symlink() or not path.is_dir():
        return path.lstat().st_size
    return sum(size(p) for p in path.iterdir())


# Below this much free space a target dir without a record (nothing says which units are in
# use) is deleted whole: a cold build (~30 min here) beats a build that dies for want of disk.
LOW_DISK_BYTES = 20e9


def prune():
    rec = record_path()
    if not rec.exists():
        free = shutil.disk_usage(target_dir()).free
        profile = target_dir() / "debug"
        if free < LOW_DISK_BYTES and profile.is_dir():
            freed = size(profile)
            shutil.rmtree(profile)
            print(f"prune_target: no record of the units in use and {free / 1e9:.1f} GB free: the whole "
                  f"debug build deleted ({freed / 1e9:.1f} GB; this run builds cold)")
        else:
            print("prune_target: no record of the units in use (no successful build yet): nothing pruned")
        return
    live = set(rec.read_text().split())
    profile = target_dir() / "debug"
    removed, freed = 0, 0
    for sub in PRUNED:
        folder = profile / sub
        if not folder.is_dir():
            continue
        for entry in folder.iterdir():
            found = unit_hash(entry.name)
            if found is None or found in live:
                continue
            freed += size(entry)
            removed += 1
            if entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry)
            else:
                entry.unlink()
    # CARGO_INCREMENTAL=0 in the suite: incremental caches are a developer's leftovers.
    incremental = profile / "incremental"
    if incremental.is_dir():
        freed += size(incremental)
        shutil.rmtree(incremental)
    print(f"prune_target: {removed} unused unit files and folders deleted, {freed / 1e9:.1f} GB freed "
          f"({len(live)} units in use kept)")


def main():
    if len(sys.argv) != 2 or sys.argv[1] not in ("record", "prune"):
        sys.exit(__doc__)
    {"record": record, "prune": prune}[sys.argv[1]]()


if __name__ == "__main__":
    main()
