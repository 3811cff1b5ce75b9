#!/usr/bin/env bash
# A one-node Slurm on this machine for tests and laptops (issue 36): munged, slurmctld and
# slurmd, with a private slurm.conf, key, sockets, state, spool and logs in one state dir.
#
#   scripts/scale/slurm_local.sh start <state dir> [port base]   # prints: export SLURM_CONF=<state dir>/slurm.conf
#   scripts/scale/slurm_local.sh stop  <state dir>
#
# Then `SLURM_CONF=<state dir>/slurm.conf sbatch ...` (or squeue, sinfo, scontrol) talks to
# it. Ports from the base (default 22850, below the ephemeral range and in a block DDS leaves
# free, as ray_local.sh's): slurmctld base+0, slurmd base+1, srun base+10..+29.
# Nothing binds the wildcard address: NodeAddr and SlurmctldHost are 127.0.0.1 and
# CommunicationParameters=NoInAddrAny,NoCtldInAddrAny (slurmd, the clients and slurmctld bind
# the node's address, not INADDR_ANY);
# munged has no TCP port (a Unix socket in the state dir).
#
# Debian 12: apt-get install slurm-wlm munge (slurm 22.05.8, munge 0.5.15; scripts/setup.sh).
# Run it as root (slurmd starts each job as its submitter); nothing of the system's Slurm or
# munge (/etc/slurm, /etc/munge, /run/munge, their systemd units) is used or touched.
# Sizes: SLURM_LOCAL_CPUS (default 2), SLURM_LOCAL_MEMORY_MB (default 4096).
set -euo pipefail

cmd="${1:-}"
state="${2:-}"
base="${3:-22850}"
[ -n "$cmd" ] && [ -n "$state" ] || { echo "usage: $0 start|stop <state dir> [port base]" >&2; exit 2; }

stop_pidfile() {  # stop_pidfile FILE: TERM the daemon, KILL it after 5 s
    local f="$1" pid
    [ -f "$f" ] || return 0
    pid="$(cat "$f")"
    if [ -n "$pid" ] && kill -0 "$pid" 2>/dev/null; then
        kill -TERM "$pid" 2>/dev/null || true
        for _ in $(seq 50); do
            kill -0 "$pid" 2>/dev/null || break
            sleep 0.1
        done
        kill -KILL "$pid" 2>/dev/null || true
    fi
    rm -f "$f"
}

case "$cmd" in
start)
    for b in munged mungekey slurmctld slurmd; do
        command -v "$b" >/dev/null || [ -x "/usr/sbin/$b" ] || {
            echo "slurm_local.sh: $b is missing (apt-get install slurm-wlm munge; scripts/setup.sh does)" >&2
            exit 1
        }
    done
    export PATH="$PATH:/usr/sbin"
    mkdir -p "$state"
    state="$(cd "$state" && pwd)"
    mkdir -p "$state/munge" "$state/ctld" "$state/spool" "$state/log" "$state/run"
    # munged checks that its key is private to its user and its directory not writable by others.
    chmod 755 "$state/munge"
    [ -f "$state/munge/munge.key" ] || mungekey --create --keyfile="$state/munge/munge.key" >/dev/null
    chmod 600 "$state/munge/munge.key"
    user="$(id -un)"
    cat >"$state/slurm.conf" <<EOF
# written by labrig scripts/scale/slurm_local.sh: a one-node cluster on 127.0.0.1
ClusterName=labrig
SlurmctldHost=localhost(127.0.0.1)
SlurmctldPort=$base
SlurmdPort=$((base + 1))
SrunPortRange=$((base + 10))-$((base + 29))
CommunicationParameters=NoInAddrAny,NoCtldInAddrAny
SlurmUser=$user
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket=$state/munge/munge.socket
StateSaveLocation=$state/ctld
SlurmdSpoolDir=$state/spool/%n
SlurmctldPidFile=$state/run/slurmctld.pid
SlurmdPidFile=$state/run/slurmd.pid
SlurmctldLogFile=$state/log/slurmctld.log
SlurmdLogFile=$state/log/slurmd.log
SlurmctldDebug=info
SlurmdDebug=info
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/none
MpiDefault=none
SwitchType=switch/none
# One node, a handful of jobs: the builtin FIFO scheduler, started without delay (backfill's
# cycles and the batch delay took an array + dependent merge from 5 s to 9 s).
SchedulerType=sched/builtin
SchedulerParameters=sched_min_interval=0,batch_sched_delay=0
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
DefMemPerCPU=512
ReturnToService=2
MaxArraySize=100001
MinJobAge=300
KillWait=5
InactiveLimit=0
SlurmctldTimeout=30
SlurmdTimeout=30
NodeName=localhost NodeAddr=127.0.0.1 NodeHostname=localhost CPUs=${SLURM_LOCAL_CPUS:-2} RealMemory=${SLURM_LOCAL_MEMORY_MB:-4096} State=UNKNOWN
PartitionName=local Nodes=localhost Default=YES MaxTime=INFINITE State=UP
EOF
    stop_pidfile "$state/run/munged.pid"
    munged --socket="$state/munge/munge.socket" --key-file="$state/munge/munge.key" \
        --pid-file="$state/run/munged.pid" --log-file="$state/log/munged.log" \
        --seed-file="$state/munge/munged.seed" --force
    export SLURM_CONF="$state/slurm.conf"
    slurmctld -f "$SLURM_CONF" -i
    slurmd -f "$SLURM_CONF" -N localhost
    # Ready when the node is idle (bounded).
    for _ in $(seq 100); do
        st="$(sinfo -h -N -o '%T' 2>/dev/null | head -n1 || true)"
        [ "$st" = idle ] && break
        sleep 0.2
    done
    if [ "${st:-}" != idle ]; then
        echo "slurm_local.sh: the node is not idle after 20 s (state: ${st:-none}); logs in $state/log:" >&2
        tail -n 20 "$state"/log/*.log >&2 || true
        exit 1
    fi
    echo "export SLURM_CONF=$SLURM_CONF"
    ;;
stop)
    [ -d "$state" ] || exit 0
    state="$(cd "$state" && pwd)"
    # All three told at once, then each waited for (KILLed after 5 s).
    for d in slurmd slurmctld munged; do
        [ -f "$state/run/$d.pid" ] && kill -TERM "$(cat "$state/run/$d.pid")" 2>/dev/null || true
    done
    stop_pidfile "$state/run/slurmd.pid"
    stop_pidfile "$state/run/slurmctld.pid"
    stop_pidfile "$state/run/munged.pid"
    ;;
*)
    echo "usage: $0 start|stop <state dir> [port base]" >&2
    exit 2
    ;;
esac
