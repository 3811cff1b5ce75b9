#!/usr/bin/env bash
# Data-parallel training on one machine: samples/s of `labrig train` as one process and as
# 2 Gloo ranks on loopback, at the same global batch and the same cores in all.
#   scripts/scale/bench_train_ranks.sh EPISODES_DIR [PRESET] [GLOBAL_BATCH] [STEPS] [CORES]
# Prints one line per configuration and writes <tmp>/bench.json. Ranks are launched the way
# torchrun --no-python does (WORLD_SIZE, RANK, MASTER_ADDR, MASTER_PORT).
set -euo pipefail
eps=${1:?usage: bench_train_ranks.sh EPISODES_DIR [PRESET] [GLOBAL_BATCH] [STEPS] [CORES]}
preset=${2:-small_vision}
batch=${3:-32}
steps=${4:-40}
cores=${5:-$(nproc)}
labrig=${LABRIG:-labrig}
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
common=(train --target "$eps" --preset "$preset" --val-every 100000
        --checkpoint-every 100000 --cache "$work/cache" --json)
# Decode the frames once, so neither configuration pays for it.
"$labrig" "${common[@]}" --out "$work/warm" --steps 1 --batch-size 2 --threads "$cores" >/dev/null
sps() { python3 -c 'import json,sys; print(json.load(open(sys.argv[1]))["samples_per_s"])' "$1/run.json"; }
OMP_NUM_THREADS=$cores "$labrig" "${common[@]}" --out "$work/one" --steps "$steps" --batch-size "$batch" --threads "$cores" >/dev/null
one=$(sps "$work/one")
port=$(python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])')
per=$((cores / 2 > 0 ? cores / 2 : 1))
for r in 0 1; do
    WORLD_SIZE=2 RANK=$r MASTER_ADDR=127.0.0.1 MASTER_PORT=$port OMP_NUM_THREADS=$per \
        "$labrig" "${common[@]}" --out "$work/two" --steps "$steps" --batch-size $((batch / 2)) --threads "$per" \
        >"$work/rank$r.log" 2>&1 &
done
wait
two=$(sps "$work/two")
comm=$(python3 -c 'import json,sys; print(100 * json.load(open(sys.argv[1]))["allreduce_share"])' "$work/two/run.json")
printf 'labrig train %s, global batch %d, %d steps, %d cores:\n' "$preset" "$batch" "$steps" "$cores"
printf '  1 process  x %d threads: %8.1f samples/s\n' "$cores" "$one"
printf '  2 ranks    x %d threads: %8.1f samples/s (%.2fx), the all-reduce %.1f%% of a step\n' "$per" "$two" "$(python3 -c "print($two/$one)")" "$comm"
