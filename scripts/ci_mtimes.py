#!/usr/bin/env python3
"""Keep a warm CI build warm across fresh clones: content-checked source mtimes.

Cargo decides whether a workspace crate is stale by comparing its source files' mtimes with
its last build's. A fresh clone stamps every file with the clone's time, so CI rebuilt (and
relinked, and re-clippied) the whole workspace on every run although the persistent target
directory held builds of most of those very files. This script records, after a successful
build, each tracked file's git blob id and mtime in the target directory; the next run, on a
clean clone, gives every file whose blob id is the same its recorded (older) mtime back, so
cargo rebuilds what changed and what depends on it, nothing else.

  ci_mtimes.py restore   before the build: restore what matches, then delete the record
  ci_mtimes.py record    after a successful build: write the record anew

The record is deleted before the build starts, so a failed or killed build leaves none and the
next run rebuilds the whole workspace (files keep their clone time): an artifact is only ever
taken as fresh for content it was built from. A tree with local changes is left alone (the
index's blob ids would not describe the files). Only .ci/run uses it: a developer's ad-hoc
builds in the same target directory would break the record's promise.
"""
import os
import subprocess
import sys
from pathlib import Path


def tracked():
    """(blob id, path) of every tracked regular file, from the index."""
    out = subprocess.run(["git", "ls-files", "-s", "-z"], check=True, capture_output=True).stdout
    for entry in out.split(b"\0"):
        if not entry:
            continue
        meta, path = entry.split(b"\t", 1)
        mode, blob, _stage = meta.split(b" ")
        if mode in (b"100644", b"100755"):
            yield blob.decode(), os.fsdecode(path)


def record_path():
    target = os.environ.get("CARGO_TARGET_DIR")
    if not target:
        sys.exit("ci_mtimes.py: CARGO_TARGET_DIR is not set (the record lives beside the build)")
    return Path(target) / "labrig-source-mtimes.tsv"


def clean_tree():
    status = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], check=True,
                            capture_output=True).stdout
    return not status.strip()


def restore():
    rec = record_path()
    if not rec.is_file():
        print("ci_mtimes: no record of a previous build: the workspace builds from scratch")
        return
    if not clean_tree():
        rec.unlink()
        print("ci_mtimes: the tree has local changes: mtimes left as they are, record dropped")
        return
    known = {}
    for line in rec.read_text().splitlines():
        blob, mtime_ns, path = line.split("\t", 2)
        known[path] = (blob, int(mtime_ns))
    same = changed = 0
    for blob, path in tracked():
        old = known.get(path)
        if old and old[0] == blob:
            os.utime(path, ns=(old[1], old[1]), follow_symlinks=False)
            same += 1
        else:
            changed += 1
    # From here until `record`, the target directory may hold builds of other contents.
    rec.unlink()
    print(f"ci_mtimes: {same} files as last built keep their mtimes; {changed} new or changed")


def record():
    if not clean_tree():
        print("ci_mtimes: the tree has local changes: nothing recorded")
        return
    rec = record_path()
    tmp = rec.with_suffix(".tmp")
    lines = [f"{blob}\t{os.lstat(path).st_mtime_ns}\t{path}" for blob, path in tracked()]
    tmp.write_text("\n".join(lines) + "\n")
    tmp.replace(rec)
    print(f"ci_mtimes: recorded {len(lines)} files")


if __name__ == "__main__":
    cmds = {"restore": restore, "record": record}
    if len(sys.argv) != 2 or sys.argv[1] not in cmds:
        sys.exit(__doc__)
    cmds[sys.argv[1]]()
