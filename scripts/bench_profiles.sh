#!/usr/bin/env bash
# Debug against release, side by side (docs/install.md): for each profile's programs
# ($CARGO_TARGET_DIR/debug and .../release, both built first: `cargo build` and
# `bash scripts/install.sh`), on the simulated rig:
#   - the 20 Hz loop's tick jitter and each process's CPU, five 320x240 cameras recorded
#     (`labrig bench loop --seconds 60`);
#   - the recorder's JPEG encode per 640x480 frame and its CPU (`labrig bench record`);
#   - one Diffusion Policy chunk, the small preset (`labrig bench policy`);
#   - `labrig demo`'s wall time (three lockstep episodes).
# Prints a Markdown table; the raw JSON stays in $OUT (default: a temporary folder).
#   bash scripts/bench_profiles.sh
set -euo pipefail
REPO_DIR="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
TARGET="${CARGO_TARGET_DIR:-${LABRIG_CACHE:-$HOME/.cache/labrig}/target}"
OUT="${OUT:-$(mktemp -d)}"
mkdir -p "$OUT"
for profile in debug release; do
    bin="$TARGET/$profile"
    for p in labrig labrig-sim labrig-recorder labrig-control labrig-policies; do
        [ -x "$bin/$p" ] || { echo "missing $bin/$p: build the $profile programs first" >&2; exit 1; }
    done
    echo "[bench] $profile: loop" >&2
    "$bin/labrig" bench loop --seconds 60 --width 320 --height 240 --domain-id 61 --json > "$OUT/$profile-loop.json"
    echo "[bench] $profile: record" >&2
    "$bin/labrig-recorder" bench --seconds 5 --size 640 --json | tail -n 1 > "$OUT/$profile-record.json"
    echo "[bench] $profile: policy" >&2
    "$bin/labrig-policies" bench --preset small --runs 20 --train-steps 0 --no-lerobot --json > "$OUT/$profile-policy.json"
    echo "[bench] $profile: demo" >&2
    start=$(date +%s%N)
    "$bin/labrig" demo --out "$OUT/$profile-demo" --domain-id 62 > "$OUT/$profile-demo.log" 2>&1
    echo "{\"wall_s\": $(( ($(date +%s%N) - start) / 1000000 )).0e-3}" > "$OUT/$profile-demo.json"
done
python3 - "$OUT" <<'PY'
import json, sys, pathlib
out = pathlib.Path(sys.argv[1])
d = {p: {k: json.loads((out / f"{p}-{k}.json").read_text()) for k in ["loop", "record", "policy", "demo"]} for p in ["debug", "release"]}
rows = [
    ("rig loop tick jitter p50 / p99 (us)", lambda r: f"{r['loop']['tick_jitter_us']['p50']:.0f} / {r['loop']['tick_jitter_us']['p99']:.0f}"),
    ("recorder CPU, five 320x240 cameras (% of a core)", lambda r: f"{r['loop']['cpu_percent']['labrig-recorder']:.1f}"),
    ("control loop CPU (% of a core)", lambda r: f"{r['loop']['cpu_percent']['labrig-control']:.1f}"),
    ("sim bridge CPU (% of a core)", lambda r: f"{r['loop']['cpu_percent']['labrig-sim']:.1f}"),
    ("JPEG encode per 640x480 frame p50 / p99 (ms)", lambda r: f"{r['record']['jpeg_p50_us'] / 1e3:.1f} / {r['record']['jpeg_p99_us'] / 1e3:.1f}"),
    ("policy chunk, small preset, p50 / p99 (ms)", lambda r: f"{r['policy']['small']['labrig']['chunk_ms']['p50']:.1f} / {r['policy']['small']['labrig']['chunk_ms']['p99']:.1f}"),
    ("`labrig demo` wall time, 3 episodes (s)", lambda r: f"{r['demo']['wall_s']:.1f}"),
]
print("| measured | debug (dev profile) | release |")
print("|---|---|---|")
for name, f in rows:
    print(f"| {name} | {f(d['debug'])} | {f(d['release'])} |")
print(f"\n(raw JSON in {out})")
PY
