#!/usr/bin/env bash
# DROID-scale indexing on Slurm (issue 36): a job array of N shards, then the merge, which
# depends on the whole array (afterok: it runs only if every shard succeeded).
#
#   scripts/scale/slurm_index.sh --shards N --out <out> [--labrig PATH] [--cpus-per-task C]
#       [--mem M] [--time T] [--partition P] [--wait] [--json] <root>... [-- <index args>...]
#
# prints the two job ids (`array <id>` and `merge <id>`, or one JSON object with --json).
# Logs: <out>/logs/index-<array>_<i>.out and merge-<id>.out; shard reports:
# <out>/reports/part-*.json; the merged index: <out>/index (its report: <out>/merge.json).
# --wait blocks until the merge has ended and exits 1 unless it completed, naming the array
# tasks that did not complete (a failed shard cancels the merge: --kill-on-invalid-dep).
# Re-submitting redoes only what is missing (unchanged episodes are reused from the parts).
# The cluster is the one SLURM_CONF (or /etc/slurm/slurm.conf) names; for a one-node cluster on
# this machine see slurm_local.sh.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
shards="" out="" labrig="" wait=0 json=0
opts=()
roots=()
extra=()
while [ $# -gt 0 ]; do
    case "$1" in
    --shards) shards="$2"; shift 2 ;;
    --out) out="$2"; shift 2 ;;
    --labrig) labrig="$2"; shift 2 ;;
    --cpus-per-task|--mem|--time|--partition) opts+=("$1=$2"); shift 2 ;;
    --wait) wait=1; shift ;;
    --json) json=1; shift ;;
    --) shift; extra=("$@"); break ;;
    -*) echo "slurm_index.sh: unknown option $1" >&2; exit 2 ;;
    *) roots+=("$1"); shift ;;
    esac
done
[ -n "$shards" ] && [ -n "$out" ] && ((${#roots[@]})) || {
    echo "usage: $0 --shards N --out <out> [--labrig PATH] [--wait] [--json] <root>... [-- <index args>...]" >&2
    exit 2
}
[ "$shards" -ge 1 ] 2>/dev/null || { echo "slurm_index.sh: --shards must be a number >= 1" >&2; exit 2; }
# Absolute paths: the jobs run elsewhere.
abs() { case "$1" in /*) echo "$1" ;; *) echo "$PWD/$1" ;; esac; }
out="$(abs "$out")"
for k in "${!roots[@]}"; do roots[k]="$(abs "${roots[k]}")"; done
if [ -z "$labrig" ]; then
    labrig="$(command -v labrig)" || { echo "slurm_index.sh: no labrig on PATH; pass --labrig" >&2; exit 2; }
fi
case "$labrig" in */*) labrig="$(abs "$labrig")" ;; esac
mkdir -p "$out/logs" "$out/parts" "$out/reports"
sep=()
((${#extra[@]})) && sep=(--)

array="$(sbatch --parsable --array="0-$((shards - 1))" "${opts[@]}" \
    --output="$out/logs/index-%A_%a.out" \
    "$here/slurm_index.sbatch" "$labrig" "$out" "${roots[@]}" "${sep[@]}" "${extra[@]}")"
array="${array%%;*}"
merge="$(sbatch --parsable --dependency="afterok:$array" --kill-on-invalid-dep=yes "${opts[@]}" \
    --output="$out/logs/merge-%j.out" \
    "$here/slurm_merge.sbatch" "$labrig" "$out")"
merge="${merge%%;*}"
if [ "$json" = 1 ]; then
    printf '{"array": "%s", "merge": "%s", "shards": %s, "out": "%s"}\n' "$array" "$merge" "$shards" "$out"
else
    echo "array $array"
    echo "merge $merge"
fi
[ "$wait" = 1 ] || exit 0

# Wait for the merge (and so the array) to end; squeue forgets a job MinJobAge after it ends,
# scontrol tells its final state until then.
state_of() { scontrol -o show job "$1" 2>/dev/null | tr ' ' '\n' | sed -n 's/^JobState=//p' | sort -u | tr '\n' ' '; }
while :; do
    st="$(state_of "$merge")"
    case "$st" in
    *COMPLETED*|*FAILED*|*CANCELLED*|*TIMEOUT*|*OUT_OF_MEMORY*|*NODE_FAIL*) break ;;
    "") break ;;
    esac
    sleep 1
done
failed="$(scontrol -o show job "$array" 2>/dev/null | grep -v 'JobState=COMPLETED' \
    | sed -n 's/.*ArrayTaskId=\([0-9]*\).*JobState=\([A-Z_]*\).*/\1 (\2)/p' | tr '\n' ' ' || true)"
if [ "$(state_of "$merge")" != "COMPLETED " ]; then
    echo "slurm_index.sh: the merge $merge did not complete ($(state_of "$merge")); failed array tasks: ${failed:-none}" >&2
    exit 1
fi
