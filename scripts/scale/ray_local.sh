#!/usr/bin/env bash
# A local Ray head for tests and laptops, everything on loopback (issue 36).
#
#   scripts/scale/ray_local.sh start <temp dir> [port base]   # prints the GCS address (127.0.0.1:<base>)
#   scripts/scale/ray_local.sh stop  <temp dir>
#
# Every port is pinned from the base (default 22600), so that parallel runs with their own
# temp dir and base never clash (below Linux's ephemeral range, 32768-60999, so that no outgoing
# connection holds one; 7400 + 250 k + 200..249 is a block DDS's port mapping leaves free):
#   base+0 GCS (--port)            base+1 dashboard (job submission: http://127.0.0.1:<base+1>)
#   base+2 Ray client server       base+3 node manager (raylet)   base+4 object manager
#   base+5 dashboard agent HTTP    base+6 dashboard agent gRPC    base+7 metrics export
#   base+8 runtime-env agent       base+9 autoscaler metrics      base+10 dashboard metrics
#   base+20 .. base+49 worker ports (30 workers and drivers at most)
# (the two metrics ports are Ray's environment variables AUTOSCALER_METRIC_PORT and
# DASHBOARD_METRIC_PORT, fixed at 44217 and 44227 otherwise: two heads would clash).
# The temp dir holds Ray's session (logs, sockets); keep it short: Ray's Unix socket paths
# live under it and must stay under 107 bytes.
#
# Token authentication is on, with a token of its own (<temp dir>/auth_token, mode 600): a head
# on loopback still runs any local user's code as its own user otherwise. (Ray 2.60 turns it
# on by itself for a head started where ~/.ray/auth_token exists, which a plain local
# `ray.init()` writes; the head and its clients must then agree, so it is never left to that.)
# Clients (a driver, `ray job submit`, `ray status`) take it from the environment:
#   source <temp dir>/env.sh    # RAY_ADDRESS, RAY_API_SERVER_ADDRESS, RAY_AUTH_MODE=token, RAY_AUTH_TOKEN_PATH,
#                               # RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0 (a driver stays on loopback)
#
# Ray is `ray` on PATH or that of $LABRIG_SCALE_PYTHON's venv (scripts/setup.sh). Sizes:
# RAY_LOCAL_NUM_CPUS (default 2), RAY_LOCAL_OBJECT_STORE_BYTES (default 256 MB: the jobs pass
# file paths, never data, through it), RAY_LOCAL_MEMORY_BYTES (default: unset, Ray's own).
#
# `stop` ends the processes of this head only: its process group (never `ray stop`, which stops
# every Ray on the machine), TERM then, after 3 s, KILL (the GCS, the raylet, the autoscaler's
# monitor and the runtime-env agent were still running 6 s after a TERM here).
set -euo pipefail

cmd="${1:-}"
temp="${2:-}"
base="${3:-22600}"
[ -n "$cmd" ] && [ -n "$temp" ] || { echo "usage: $0 start|stop <temp dir> [port base]" >&2; exit 2; }

ray_bin() {
    if [ -n "${LABRIG_SCALE_PYTHON:-}" ] && [ -x "$(dirname "$LABRIG_SCALE_PYTHON")/ray" ]; then
        echo "$(dirname "$LABRIG_SCALE_PYTHON")/ray"
    elif command -v ray >/dev/null; then
        command -v ray
    else
        echo "ray_local.sh: no ray (run scripts/setup.sh and source env.sh, or put ray on PATH)" >&2
        exit 1
    fi
}

# The process group of this head: `ray start` runs under setsid, and every process it starts
# (GCS, raylet, dashboard, agents, client server, workers) stays in its group.
group_alive() { [ -n "$(ps -o pid= -g "$1" 2>/dev/null)" ]; }

case "$cmd" in
start)
    mkdir -p "$temp"
    temp="$(cd "$temp" && pwd)"
    export RAY_USAGE_STATS_ENABLED=0
    (umask 077 && head -c 32 /dev/urandom | od -An -tx1 | tr -d ' \n' >"$temp/auth_token")
    export RAY_AUTH_MODE=token RAY_AUTH_TOKEN_PATH="$temp/auth_token"
    # RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0 for the drivers too: without it a driver's own node
    # address becomes the machine's outward one and it never reaches the loopback GCS.
    printf 'export RAY_ADDRESS=127.0.0.1:%s\nexport RAY_API_SERVER_ADDRESS=http://127.0.0.1:%s\nexport RAY_AUTH_MODE=token\nexport RAY_AUTH_TOKEN_PATH=%s\nexport RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0\nexport RAY_USAGE_STATS_ENABLED=0\n' \
        "$base" "$((base + 1))" "$temp/auth_token" >"$temp/env.sh"
    # The venv first on the head's PATH: a job's entrypoint (`ray job submit -- python ...`)
    # runs under it and finds Ray's Python.
    export PATH="$(dirname "$(ray_bin)"):$PATH"
    # No prompt, no network look-ups at start.
    export RAY_USAGE_STATS_PROMPT_ENABLED=0
    # Ray replaces a loopback --node-ip-address by the machine's outward address (its
    # resolve_ip_for_localhost) unless "clusters" are off, as Ray does on macOS and Windows:
    # then the node's address, and the GCS's, raylet's and agents' advertised ones, are 127.0.0.1.
    # A one-node head needs nothing more (only `ray start --address` of a second node is refused).
    export RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0
    export AUTOSCALER_METRIC_PORT="$((base + 9))" DASHBOARD_METRIC_PORT="$((base + 10))"
    mem=()
    [ -n "${RAY_LOCAL_MEMORY_BYTES:-}" ] && mem=(--memory "$RAY_LOCAL_MEMORY_BYTES")
    # setsid: a session and process group of its own, which `stop` ends.
    setsid "$(ray_bin)" start --head \
        --node-ip-address 127.0.0.1 \
        --port "$base" \
        --dashboard-host 127.0.0.1 --dashboard-port "$((base + 1))" \
        --ray-client-server-port "$((base + 2))" \
        --node-manager-port "$((base + 3))" \
        --object-manager-port "$((base + 4))" \
        --dashboard-agent-listen-port "$((base + 5))" \
        --dashboard-agent-grpc-port "$((base + 6))" \
        --metrics-export-port "$((base + 7))" \
        --runtime-env-agent-port "$((base + 8))" \
        --min-worker-port "$((base + 20))" --max-worker-port "$((base + 49))" \
        --num-cpus "${RAY_LOCAL_NUM_CPUS:-2}" \
        --object-store-memory "${RAY_LOCAL_OBJECT_STORE_BYTES:-256000000}" \
        "${mem[@]}" \
        --temp-dir "$temp" \
        --disable-usage-stats \
        --log-style record >"$temp/start.log" 2>&1 &
    starter=$!
    # Kept before waiting, so that `stop` finds a head whose start failed half-way.
    printf '%s\n' "$starter" >"$temp/pgid"
    wait "$starter" || {
        cat "$temp/start.log" >&2
        exit 1
    }
    printf '%s\n' "$base" >"$temp/port_base"
    echo "127.0.0.1:$base"
    ;;
stop)
    [ -f "$temp/pgid" ] || exit 0
    temp="$(cd "$temp" && pwd)"
    pgid="$(cat "$temp/pgid")"
    # Only a group that is still this head's (its raylet names this temp dir): pids are reused.
    mine=0
    for p in $(ps -o pid= -g "$pgid" 2>/dev/null); do
        tr '\0' ' ' <"/proc/$p/cmdline" 2>/dev/null | grep -qF -- "$temp/" && mine=1
    done
    if [ "$mine" = 1 ]; then
        kill -TERM -- "-$pgid" 2>/dev/null || true
        for _ in $(seq 30); do
            group_alive "$pgid" || break
            sleep 0.1
        done
        group_alive "$pgid" && kill -KILL -- "-$pgid" 2>/dev/null
    fi
    rm -f "$temp/pgid"
    ;;
*)
    echo "usage: $0 start|stop <temp dir> [port base]" >&2
    exit 2
    ;;
esac
